//! `flashmat._flashmat`: the Python extension behind the package `flashmat`
//! (python/flashmat). A thin layer: each method checks what Python hands
//! it, calls the library and hands back torch tensors that share memory
//! with flashmat's (no copy: `tensors`). Errors become Python exceptions
//! with the CLI's one-line messages (`errors`), panics included.

mod errors;
mod tensors;

use errors::{guarded, value_error};
use flashmat::device::device_name;
use flashmat::geometry::LightView;
use flashmat::infer::{self, ExposureMode, NeuralMaterial};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};
use std::path::PathBuf;
use tch::{Device, Kind, Tensor};
use tensors::PyTensor;

/// The torch version this extension was built against (build.rs).
const BUILT_TORCH: &str = env!("FLASHMAT_BUILT_TORCH");

/// `device`: a string ("cpu", "cuda", "cuda:1") or a torch.device; None
/// is the CPU.
fn parse_device(device: Option<&Bound<'_, PyAny>>) -> PyResult<Device> {
    let text = match device {
        Some(d) => d.str()?.to_string(),
        None => "cpu".into(),
    };
    guarded(|| flashmat::device::parse_device(&text))
}

/// One position (3 numbers) or several (`[K, 3]`).
#[derive(FromPyObject)]
enum Positions {
    One([f64; 3]),
    Many(Vec<[f64; 3]>),
}

impl Positions {
    fn list(&self) -> Vec<[f64; 3]> {
        match self {
            Positions::One(p) => vec![*p],
            Positions::Many(v) => v.clone(),
        }
    }
}

/// Light/view configurations from `light` and `view` (each one position or
/// K of them; one is repeated against K). Returns them and whether the
/// caller asked for a batch.
fn configs(light: &Positions, view: Option<&Positions>) -> anyhow::Result<(Vec<LightView>, bool)> {
    let lights = light.list();
    let views = view.map(Positions::list).unwrap_or_else(|| vec![NeuralMaterial::identity_config().view]);
    let k = lights.len().max(views.len());
    anyhow::ensure!(k > 0, "no light position given");
    anyhow::ensure!(
        (lights.len() == k || lights.len() == 1) && (views.len() == k || views.len() == 1),
        "light ({} positions) and view ({} positions) must have as many positions, or one of them one",
        lights.len(),
        views.len()
    );
    let batch = matches!(light, Positions::Many(_)) || matches!(view, Some(Positions::Many(_)));
    let pick = |v: &[[f64; 3]], i: usize| v[if v.len() == 1 { 0 } else { i }];
    Ok(((0..k).map(|i| LightView { light: pick(&lights, i), view: pick(&views, i) }).collect(), batch))
}

/// A flashmat model (M_est with its neural BRDF) that turns flash photos
/// into materials.
#[pyclass(name = "Model", module = "flashmat", unsendable)]
struct Model {
    loaded: infer::LoadedModel,
}

#[pymethods]
impl Model {
    /// The model file.
    #[getter]
    fn path(&self) -> PathBuf {
        self.loaded.path.clone()
    }

    /// The model's id (preset and sizes).
    #[getter]
    fn model_id(&self) -> String {
        self.loaded.model.model_id()
    }

    #[getter]
    fn device(&self) -> String {
        device_name(self.loaded.model.device())
    }

    /// One flash photo to a neural material, as `flashmat estimate` does.
    /// photo: a file path, or pixels (a torch tensor or anything
    /// `torch.as_tensor` takes, e.g. a numpy array) `[3, H, W]` or
    /// `[H, W, 3]` (RGBA: alpha ignored with a warning); uint8 is sRGB,
    /// floats need `encoding` ("srgb": display values in [0, 1], "linear":
    /// linear radiance, HDR allowed).
    #[pyo3(signature = (photo, *, fov=None, size=256, exposure_mode="calibrated", encoding=None, exposure=None, square=false, max_memory="8G"))]
    #[allow(clippy::too_many_arguments)]
    fn estimate(
        &self,
        photo: &Bound<'_, PyAny>,
        fov: Option<f64>,
        size: usize,
        exposure_mode: &str,
        encoding: Option<&str>,
        exposure: Option<f64>,
        square: bool,
        max_memory: &str,
    ) -> PyResult<Material> {
        use clap::ValueEnum;
        let mode = ExposureMode::from_str(exposure_mode, true).map_err(|_| {
            let names: Vec<String> = ExposureMode::value_variants().iter().filter_map(|v| v.to_possible_value()).map(|v| v.get_name().to_string()).collect();
            value_error(format!("exposure_mode must be one of {}; got '{exposure_mode}'", names.join(", ")))
        })?;
        let opts = infer::PhotoOptions { fov_deg: fov, size, exposure_ev: exposure, square };
        let prepared = match photo_path(photo) {
            Some(path) => {
                if encoding.is_some() {
                    return Err(value_error("encoding is for pixels: a photo file says its own"));
                }
                guarded(|| infer::load_photo_with(&path, &opts))?
            }
            None => {
                let pixels = tensors::as_tensor(photo)?;
                guarded(|| tensors::prepare_pixels(&pixels, encoding, &opts))?
            }
        };
        for w in &prepared.warnings {
            errors::warn(photo.py(), w)?;
        }
        guarded(|| {
            let max_memory = infer::tiles::parse_memory(max_memory)?;
            let (h, w) = (prepared.linear.height, prepared.linear.width);
            let plan = infer::plan_estimate(&self.loaded.model.config, h, w, max_memory)?;
            let inner = infer::estimate_planned(&self.loaded.model, &self.loaded.info, &prepared, &plan, &mode.config(), || ())?;
            Ok(Material { inner })
        })
    }

    fn __repr__(&self) -> String {
        format!("flashmat.Model('{}', {}, device='{}')", self.loaded.path.display(), self.model_id(), self.device())
    }
}

/// A path (str or os.PathLike), or None for anything else.
fn photo_path(photo: &Bound<'_, PyAny>) -> Option<PathBuf> {
    if photo.is_instance_of::<PyString>() || photo.hasattr("__fspath__").unwrap_or(false) {
        photo.extract::<PathBuf>().ok()
    } else {
        None
    }
}

/// A relightable neural material: per-pixel codes and the neural BRDF that
/// renders them.
#[pyclass(name = "Material", module = "flashmat", unsendable)]
struct Material {
    inner: NeuralMaterial,
}

#[pymethods]
impl Material {
    /// The neural map `[C, H, W]` (float32, on the material's device): the
    /// very tensor the material renders from, no copy. Changes made to it
    /// in place show in the next render; `requires_grad_()` on it lets
    /// gradients of `render` reach it.
    #[getter]
    fn codes(&self) -> PyTensor {
        PyTensor(self.inner.neural_map.shallow_clone())
    }

    /// Replaces the neural map (same shape, float32, same device); the
    /// material then renders from that tensor itself.
    #[setter]
    fn set_codes(&mut self, codes: PyTensor) -> PyResult<()> {
        let want = self.inner.neural_map.size();
        let t = codes.0;
        if t.size() != want || t.kind() != Kind::Float || t.device() != self.inner.device() {
            return Err(value_error(format!(
                "codes must be a float32 tensor {want:?} on {}, got {:?} {:?} on {}",
                device_name(self.inner.device()),
                t.kind(),
                t.size(),
                device_name(t.device())
            )));
        }
        self.inner.neural_map = t;
        Ok(())
    }

    /// The linear photo the material was estimated from `[3, H, W]`.
    #[getter]
    fn input_photo(&self) -> PyTensor {
        PyTensor(self.inner.input_photo.shallow_clone())
    }

    /// (H, W) of the neural map.
    #[getter]
    fn size(&self) -> (usize, usize) {
        self.inner.size()
    }

    #[getter]
    fn device(&self) -> String {
        device_name(self.inner.device())
    }

    /// Exposure and white balance (R, G, B) every render is multiplied by.
    #[getter]
    fn gain(&self) -> (f64, f64, f64) {
        let g = self.inner.meta.gain;
        (g[0], g[1], g[2])
    }

    /// Where the material came from: model, source photo, field of view.
    #[getter]
    fn info<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m = &self.inner.meta;
        let d = PyDict::new(py);
        d.set_item("model_id", &m.model_id)?;
        d.set_item("source", &m.source)?;
        d.set_item("fov_deg", m.fov_deg)?;
        d.set_item("ldr_input", m.ldr_input)?;
        d.set_item("refined", m.refine.is_some())?;
        Ok(d)
    }

    /// The renderer's weights (ND_enc, M_render) by name: the tensors
    /// themselves, frozen; `requires_grad_()` on one lets gradients of
    /// `render` reach it.
    fn parameters<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        let mut vars: Vec<(String, Tensor)> = self.inner.renderer_vs.variables().into_iter().collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        for (name, t) in vars {
            d.set_item(name, PyTensor(t))?;
        }
        Ok(d)
    }

    /// Linear HDR radiance under a point light at `light` seen from `view`
    /// (default: overhead, as in the photo), positions in material units
    /// (the shorter side spans [-1, 1], z > 0). One position gives
    /// `[3, H, W]`; `[K, 3]` positions give `[K, 3, H, W]`. size: the
    /// render's shorter side (codes resampled bilinearly), default the
    /// map's. Differentiable (autograd, under torch's grad mode).
    #[pyo3(signature = (light, view=None, size=None))]
    fn render(&self, light: Positions, view: Option<Positions>, size: Option<usize>) -> PyResult<PyTensor> {
        guarded(|| {
            let (configs, batch) = configs(&light, view.as_ref())?;
            let out = self.inner.render_differentiable(&configs, size)?;
            Ok(PyTensor(if batch { out } else { out.get(0) }))
        })
    }

    /// Radiance for per-pixel directions, for use in another renderer:
    /// wi, wo `[H, W, 3]` (or `[K, H, W, 3]`) unit vectors towards the
    /// light and the camera in the material's frame (+z up), H x W the
    /// map's. Returns `[3, H, W]` (or `[K, 3, H, W]`). Differentiable in
    /// the codes, the weights and the directions.
    fn render_dirs(&self, wi: PyTensor, wo: PyTensor) -> PyResult<PyTensor> {
        guarded(|| {
            let batch = wi.dim() == 4;
            let as_maps = |d: &Tensor, name: &str| -> anyhow::Result<Tensor> {
                let s = d.size();
                anyhow::ensure!((s.len() == 3 || s.len() == 4) && s[s.len() - 1] == 3, "{name} must be [H, W, 3] or [K, H, W, 3], got {s:?}");
                anyhow::ensure!(d.is_floating_point(), "{name} must hold floats, got {:?}", d.kind());
                let d = if s.len() == 3 { d.unsqueeze(0) } else { d.shallow_clone() };
                Ok(d.permute([0, 3, 1, 2]))
            };
            let out = self.inner.render_directions(&as_maps(&wi, "wi")?, &as_maps(&wo, "wo")?)?;
            Ok(PyTensor(if batch { out } else { out.get(0) }))
        })
    }

    /// Writes the material as a `.nmat` file (atomically).
    fn save(&self, path: PathBuf) -> PyResult<()> {
        guarded(|| {
            anyhow::ensure!(path.extension().is_some_and(|e| e.eq_ignore_ascii_case("nmat")), "{}: a material file must end in .nmat", path.display());
            self.inner.save(&path)
        })
    }

    /// The same material on `device` ("cpu", "cuda", "cuda:1" or a
    /// torch.device).
    fn to(&self, device: &Bound<'_, PyAny>) -> PyResult<Material> {
        let device = parse_device(Some(device))?;
        guarded(|| Ok(Material { inner: self.inner.to_device(device)? }))
    }

    /// An independent copy (own codes, photo and weights).
    fn clone(&self) -> PyResult<Material> {
        guarded(|| Ok(Material { inner: self.inner.duplicate()? }))
    }

    /// PBR maps of the material, as `flashmat fit` makes them: GGX fitted
    /// per pixel to the neural renders. Returns a dict of CPU tensors:
    /// diffuse, specular `[3, H, W]`, roughness `[1, H, W]` (alpha), normal
    /// `[3, H, W]` (unit, OpenGL), base_color `[3, H, W]`, metallic
    /// `[1, H, W]`, error `[H, W]`. With `output`, also writes the folder
    /// `flashmat fit -o` writes (PNG/EXR maps, height, AO, glTF).
    #[pyo3(signature = (steps=None, samples=None, output=None))]
    fn fit<'py>(&self, py: Python<'py>, steps: Option<usize>, samples: Option<usize>, output: Option<PathBuf>) -> PyResult<Bound<'py, PyDict>> {
        let defaults = flashmat::fit::FitConfig::default();
        let cfg = flashmat::fit::FitConfig { steps: steps.unwrap_or(defaults.steps), samples: samples.unwrap_or(defaults.samples), ..defaults };
        let fit = guarded(|| {
            if let Some(dir) = &output {
                flashmat::fit::export::check_output_dir(dir)?;
            }
            let fit = errors::without_gil(py, || flashmat::fit::fit_material(&self.inner, &cfg, |_, _| ()))?;
            if let Some(dir) = &output {
                flashmat::fit::export::write_fit(dir, &fit, &flashmat::fit::relief::ReliefConfig::default(), &self.inner.meta.source)?;
            }
            Ok(fit)
        })?;
        let mr = flashmat::fit::export::MetallicRoughness::from_maps(&fit.maps);
        let d = PyDict::new(py);
        let (kd, ks, roughness, normal) = flashmat::fit::export::parts(&fit.maps);
        d.set_item("diffuse", PyTensor(kd))?;
        d.set_item("specular", PyTensor(ks))?;
        d.set_item("roughness", PyTensor(roughness))?;
        d.set_item("normal", PyTensor(normal))?;
        d.set_item("base_color", PyTensor(mr.base_color))?;
        d.set_item("metallic", PyTensor(mr.metallic))?;
        d.set_item("error", PyTensor(fit.error))?;
        Ok(d)
    }

    /// Writes the material's browser page (`flashmat view`): one HTML file.
    #[pyo3(signature = (path, light=None, view=None))]
    fn view(&self, path: PathBuf, light: Option<[f64; 3]>, view: Option<[f64; 3]>) -> PyResult<()> {
        guarded(|| {
            anyhow::ensure!(path.extension().is_some_and(|e| e.eq_ignore_ascii_case("html")), "{}: the page must end in .html", path.display());
            let identity = NeuralMaterial::identity_config();
            let initial = LightView { light: light.unwrap_or(identity.light), view: view.unwrap_or(identity.view) };
            flashmat::geometry::above_surface("light", initial.light)?;
            flashmat::geometry::above_surface("camera", initial.view)?;
            use flashmat::viewer::{Bits, ViewerOptions};
            let opts = ViewerOptions { map_bits: Bits::Auto, weight_bits: Bits::Auto, initial, relight_input: self.inner.meta.source.clone() };
            flashmat::viewer::write_page(&self.inner, &path, &opts)?;
            Ok(())
        })
    }

    /// Refines the codes so that the identity render matches `photo`
    /// (`flashmat estimate --refine`): photo `[3, H, W]` linear at the
    /// map's size, default the photo the material was estimated from.
    /// The codes keep their memory (updated in place). Returns the
    /// refinement's report line.
    #[pyo3(signature = (photo=None, steps=100))]
    fn refine(&mut self, py: Python<'_>, photo: Option<PyTensor>, steps: usize) -> PyResult<String> {
        guarded(|| {
            let cfg = infer::refine::RefineConfig::with_steps(steps);
            let photo = match photo {
                Some(p) => p.0.detach().to_kind(Kind::Float).to_device(self.inner.device()),
                None => self.inner.input_photo.shallow_clone(),
            };
            anyhow::ensure!(flashmat::image::all_finite(&photo), "the photo holds NaN or infinite values");
            let clipped = self.inner.meta.ldr_input;
            let codes = self.inner.neural_map.shallow_clone();
            let report = errors::without_gil(py, || infer::refine::refine(&mut self.inner, &photo, clipped, &cfg, |_| ()))?;
            // The refined map goes back into the codes' own memory.
            tch::no_grad(|| codes.shallow_clone().copy_(&self.inner.neural_map));
            self.inner.neural_map = codes;
            Ok(report.summary())
        })
    }

    fn __repr__(&self) -> String {
        let (h, w) = self.inner.size();
        format!("flashmat.Material({}x{}, {} codes, from '{}', device='{}')", w, h, self.inner.config.neural_channels, self.inner.meta.source, self.device())
    }
}

/// Loads a model file, or the bundled model (`models/flashmat.safetensors`
/// of the checkout flashmat was built from, or `$FLASHMAT_MODELS`).
#[pyfunction]
#[pyo3(signature = (path=None, device=None))]
fn load_model(path: Option<PathBuf>, device: Option<&Bound<'_, PyAny>>) -> PyResult<Model> {
    let device = parse_device(device)?;
    guarded(|| Ok(Model { loaded: infer::load_model(path.as_deref(), device)? }))
}

/// Loads a `.nmat` material.
#[pyfunction]
#[pyo3(signature = (path, device=None))]
fn load(path: PathBuf, device: Option<&Bound<'_, PyAny>>) -> PyResult<Material> {
    let device = parse_device(device)?;
    guarded(|| {
        anyhow::ensure!(path.exists(), "material file {} does not exist", path.display());
        Ok(Material { inner: NeuralMaterial::load(&path, device)? })
    })
}

/// One material from several photos of a capture folder, as
/// `flashmat estimate --capture DIR` makes it: GGX maps fitted to all
/// photos, then a neural material of them. photos: use the first K.
/// max_memory: refused before any work when the fit would need more
/// (as `--max-memory`).
#[pyfunction]
#[pyo3(signature = (folder, *, photos=None, size=256, steps=None, photo_gains=false, model=None, device=None, max_memory="8G"))]
#[allow(clippy::too_many_arguments)]
fn capture(py: Python<'_>, folder: PathBuf, photos: Option<usize>, size: usize, steps: Option<usize>, photo_gains: bool, model: Option<PathBuf>, device: Option<&Bound<'_, PyAny>>, max_memory: &str) -> PyResult<Material> {
    use flashmat::fit::photos as fp;
    let device = parse_device(device)?;
    let defaults = fp::PhotoFitConfig::default();
    let cfg = fp::PhotoFitConfig { steps: steps.unwrap_or(defaults.steps), size, photo_gains, ..defaults };
    let (material, warnings) = guarded(|| {
        let captures = flashmat::data::captures::Captures::open(&folder)?;
        let count = photos.unwrap_or(captures.photos.len());
        let limit = flashmat::infer::tiles::parse_memory(max_memory)?;
        let need = fp::capture_fit_memory(size, count);
        anyhow::ensure!(
            need <= limit as f64,
            "a capture fit at size={size} with {count} photos needs about {:.1} GiB, more than max_memory={max_memory:?}: lower size, or raise max_memory",
            need / (1u64 << 30) as f64
        );
        let mut warnings = Vec::new();
        let made = errors::without_gil(py, || fp::capture_material(&captures, count, &cfg, model.as_deref(), device, |w| warnings.push(w.to_string()), |_, _, _| ()))?;
        Ok((made.material, warnings))
    })?;
    for w in &warnings {
        errors::warn(py, w)?;
    }
    Ok(Material { inner: material })
}

/// Seconds of each of `runs` renders by the library's own call, the one
/// `flashmat relight` makes (row bands, no autograd): the baseline of
/// python/bench/bench_api.py, timed in the same process.
#[pyfunction]
fn _library_render_seconds(material: &Material, light: [f64; 3], view: [f64; 3], runs: usize) -> PyResult<Vec<f64>> {
    guarded(|| {
        let config = [LightView { light, view }];
        (0..runs)
            .map(|_| {
                let t0 = std::time::Instant::now();
                let r = material.inner.render(&config)?;
                synchronize(r.device());
                Ok(t0.elapsed().as_secs_f64())
            })
            .collect()
    })
}

/// Seconds of each of `runs` estimates of a photo file by the library's
/// calls that `flashmat estimate` makes (photo, plan, M_est): the other
/// baseline of python/bench/bench_api.py.
#[pyfunction]
fn _library_estimate_seconds(model: &Model, photo: PathBuf, size: usize, runs: usize) -> PyResult<Vec<f64>> {
    guarded(|| {
        (0..runs)
            .map(|_| {
                let t0 = std::time::Instant::now();
                let prepared = infer::load_photo_with(&photo, &infer::PhotoOptions { size, ..Default::default() })?;
                let plan = infer::plan_estimate(&model.loaded.model.config, prepared.linear.height, prepared.linear.width, infer::tiles::parse_memory("8G")?)?;
                let m = infer::estimate_planned(&model.loaded.model, &model.loaded.info, &prepared, &plan, &infer::ExposureConfig::default(), || ())?;
                synchronize(m.device());
                Ok(t0.elapsed().as_secs_f64())
            })
            .collect()
    })
}

fn synchronize(device: Device) {
    if let Device::Cuda(i) = device {
        tch::Cuda::synchronize(i as i64);
    }
}

#[pymodule]
fn _flashmat(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::quiet_panics();
    m.add("TORCH_VERSION", BUILT_TORCH)?;
    m.add("NMAT_VERSION", infer::NMAT_VERSION)?;
    // Light and camera of the photo itself (co-located, overhead).
    let [x, y, z] = NeuralMaterial::identity_config().view;
    m.add("OVERHEAD", (x, y, z))?;
    m.add_class::<Model>()?;
    m.add_class::<Material>()?;
    m.add_function(wrap_pyfunction!(load_model, m)?)?;
    m.add_function(wrap_pyfunction!(load, m)?)?;
    m.add_function(wrap_pyfunction!(capture, m)?)?;
    m.add_function(wrap_pyfunction!(_library_render_seconds, m)?)?;
    m.add_function(wrap_pyfunction!(_library_estimate_seconds, m)?)?;
    Ok(())
}
