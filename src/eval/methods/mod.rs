//! Methods under evaluation: each turns the co-located input photo of a
//! material into renders under new light/view configurations. Model files
//! are opened as the method their metadata records (flashmat, analytic,
//! relight-unet); `printout` needs no file.

pub mod fit;

use crate::baselines::{Baseline, BaselineNet, RelightEncoded, TrainMethod};
use crate::geometry::{config_tensors, LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::infer::refine::{refine, RefineConfig};
use crate::infer::highlight_fill::HighlightFillConfig;
use crate::infer::{self, ExposureConfig, NeuralMaterial, PreparedPhoto};
use crate::model::{FoldedMEst, Model, ModelInfo};
use crate::svbrdf::render::direction_maps_for;
use anyhow::{bail, ensure, Context, Result};
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// Name that selects the print-out baseline on the command line.
pub const PRINTOUT: &str = "printout";

/// Name of a flashmat model's refined variant: `NAME+refineSTEPS`.
pub fn refined_name(name: &str, steps: usize) -> String {
    format!("{name}+refine{steps}")
}

/// Name of a flashmat model's variant with the photographed highlight
/// filled in its map ([`infer::highlight_fill`]): `NAME+fill`.
pub fn filled_name(name: &str) -> String {
    format!("{name}+fill")
}

/// Inverse of [`refined_name`]: (model name, refinement steps), steps 0
/// for any other method name.
pub fn split_refined(name: &str) -> (&str, usize) {
    match name.rsplit_once("+refine").and_then(|(base, steps)| Some((base, steps.parse().ok()?))) {
        Some(split) => split,
        None => (name, 0),
    }
}

/// Configurations rendered per neural-renderer call (bounds memory).
const RENDER_CHUNK: usize = 8;

/// A way to re-render a material from its photo.
pub trait Method {
    /// Short name for reports (CSV file name, table row).
    fn name(&self) -> String;
    /// Takes the input photo, linear `[3, H, W]` (clamped to [0, 1] for
    /// LDR-input evaluation), seen from the co-located 28 degree view.
    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()>;
    /// Renders the prepared material: `[K, 3, H, W]` linear radiance on the CPU.
    fn render(&self, configs: &[LightView]) -> Result<Tensor>;
}

/// A flashmat model file: M_est estimates a neural material from the
/// photo, ND_enc + M_render re-render it.
pub struct ModelMethod {
    name: String,
    model: Model,
    info: ModelInfo,
    ldr_photo: bool,
    /// Refinement on the photo after M_est (`flashmat eval --refine`).
    refine: Option<RefineConfig>,
    /// How the photo's exposure reaches the material (`--exposure-mode`).
    exposure: ExposureConfig,
    /// The photographed highlight filled in the map (`--highlight-fill`).
    highlight_fill: Option<HighlightFillConfig>,
    material: Option<NeuralMaterial>,
}

impl ModelMethod {
    /// Loads a model file; `ldr_photo`: the photos are clamped LDR renders
    /// (recorded in the neural material's metadata).
    pub fn load(path: &Path, name: String, ldr_photo: bool, device: Device) -> Result<Self> {
        let loaded = infer::load_model(Some(path), device)?;
        Ok(Self { name, model: loaded.model, info: loaded.info, ldr_photo, refine: None, exposure: ExposureConfig::default(), highlight_fill: None, material: None })
    }

    /// The same method with another exposure handling.
    pub fn with_exposure(self, exposure: ExposureConfig) -> Self {
        Self { exposure, ..self }
    }

    /// The same method with (or without) the photographed highlight filled.
    pub fn with_highlight_fill(self, highlight_fill: Option<HighlightFillConfig>) -> Self {
        Self { highlight_fill, ..self }
    }

    /// The same method with every estimate refined on its photo.
    pub fn with_refine(self, refine: RefineConfig) -> Self {
        Self { refine: Some(refine), ..self }
    }

    /// The prepared material (after any refinement).
    pub fn material(&self) -> Option<&NeuralMaterial> {
        self.material.as_ref()
    }
}

impl Method for ModelMethod {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        self.material = Some(estimate_material(&self.name, &self.model, &self.info, self.ldr_photo, self.refine.as_ref(), &self.exposure, self.highlight_fill.as_ref(), photo_linear)?);
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        render_material(&self.name, self.material.as_ref(), configs)
    }
}

/// A flashmat model's neural material of an evaluation photo `[3, H, W]`
/// (linear, seen from the co-located view), its highlight filled and then
/// refined when `highlight_fill` and `refine` say: the one place evaluation
/// calls inference.
#[allow(clippy::too_many_arguments)]
fn estimate_material(name: &str, model: &Model, info: &ModelInfo, ldr_photo: bool, refine_cfg: Option<&RefineConfig>, exposure: &ExposureConfig, highlight_fill: Option<&HighlightFillConfig>, photo_linear: &Tensor) -> Result<NeuralMaterial> {
    let linear = Image::from_tensor(&photo_linear.to_device(Device::Cpu).to_kind(Kind::Float))?;
    let photo = PreparedPhoto::at_model_view(linear, ldr_photo, "evaluation render");
    let mut material = infer::estimate_planned(model, info, &photo, &infer::EstPlan::Whole, exposure, || ())?;
    if let Some(cfg) = highlight_fill {
        material.fill_highlight(cfg)?;
    }
    if let Some(cfg) = refine_cfg {
        let report = refine(&mut material, &photo.linear.to_tensor(), ldr_photo, cfg, |_| {})?;
        ensure!(report.stopped.is_none(), "{name}: {}", report.summary());
    }
    Ok(material)
}

/// Renders a prepared neural material in chunks: `[K, 3, H, W]` linear on the CPU.
fn render_material(name: &str, material: Option<&NeuralMaterial>, configs: &[LightView]) -> Result<Tensor> {
    let Some(m) = material else { bail!("{name}: render before prepare") };
    let parts: Vec<Tensor> = configs.chunks(RENDER_CHUNK).map(|c| m.render(c).map(|t| t.to_device(Device::Cpu))).collect::<Result<_>>()?;
    Ok(Tensor::cat(&parts, 0))
}

/// [`ModelMethod`] on networks it does not own (the default exposure
/// handling): the checks the training run logs at every checkpoint score
/// its live model through it.
pub struct BorrowedModelMethod<'a> {
    pub model: &'a Model,
    pub info: ModelInfo,
    material: Option<NeuralMaterial>,
}

impl<'a> BorrowedModelMethod<'a> {
    /// LDR-input models ([`ModelInfo::ldr_input`]) see clamped photos.
    pub fn new(model: &'a Model, info: ModelInfo) -> Self {
        Self { model, info, material: None }
    }
}

impl Method for BorrowedModelMethod<'_> {
    fn name(&self) -> String {
        "model".into()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        self.material = Some(estimate_material("model", self.model, &self.info, self.info.ldr_input, None, &ExposureConfig::default(), None, photo_linear)?);
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        render_material("model", self.material.as_ref(), configs)
    }
}

/// The print-out baseline: the photo treated as a flat Lambertian print.
/// Its albedo is the photo divided by the co-located shading of a white
/// Lambertian surface, kd = photo / NoL (R = f NoL pi with f = kd / pi),
/// NoL from each pixel's light direction and the flat normal +z. It is
/// relit with the GGX renderer's diffuse lobe, R = kd max(NoL, 0), and zero
/// specular (the renderer's Schlick term is not zero at ks = 0, so the
/// specular lobe is left out rather than evaluated with ks = 0).
#[derive(Default)]
pub struct PrintoutMethod {
    /// Albedo `[3, H, W]` of the prepared photo.
    kd: Option<Tensor>,
}

/// n.l of a flat surface (+z normal) for each configuration's light:
/// `[K, 1, H, W]`, clamped at 0.
pub fn flat_n_dot_l(configs: &[LightView], h: usize, w: usize) -> Tensor {
    let k = configs.len() as i64;
    let (lights, views) = config_tensors(configs, Device::Cpu);
    let (wi, _) = direction_maps_for(&lights.view([1, k, 3]), &views.view([1, k, 3]), h, w);
    wi.get(0).narrow(1, 2, 1).clamp_min(0.0)
}

impl Method for PrintoutMethod {
    fn name(&self) -> String {
        PRINTOUT.into()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        let s = photo_linear.size();
        ensure!(s.len() == 3 && s[0] == 3, "the photo must be [3, H, W], got {s:?}");
        let nol = flat_n_dot_l(&[LightView::colocated(MODEL_FOV_DEG)], s[1] as usize, s[2] as usize).get(0);
        let photo = photo_linear.to_device(Device::Cpu).to_kind(Kind::Float).clamp_min(0.0);
        self.kd = Some(photo / nol.clamp_min(1e-6));
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        let kd = self.kd.as_ref().context("printout: render before prepare")?;
        ensure!(!configs.is_empty(), "no light/view configuration to render");
        let s = kd.size();
        Ok(kd.unsqueeze(0) * flat_n_dot_l(configs, s[1] as usize, s[2] as usize))
    }
}

/// M_est-style input of a photo for a model trained on `info`'s photos:
/// clamped to [0, 1] for LDR-input models, below at 0 otherwise, and the
/// co-located h_z. photo_linear: `[3, H, W]` -> `[1, 4, H, W]` on `device`.
fn model_input(photo_linear: &Tensor, info: &ModelInfo, device: Device) -> Result<Tensor> {
    let s = photo_linear.size();
    ensure!(s.len() == 3 && s[0] == 3, "the photo must be [3, H, W], got {s:?}");
    Ok(crate::data::samples::photo_est_input(photo_linear, info.ldr_input, device))
}

/// Light/view configurations as `[1, K, 3]` lights and views on `device`.
fn config_batch(configs: &[LightView], device: Device) -> (Tensor, Tensor) {
    let k = configs.len() as i64;
    let (l, v) = config_tensors(configs, device);
    (l.view([1, k, 3]), v.view([1, k, 3]))
}

/// The analytic-SVBRDF baseline: its U-Net (BatchNorm folded) estimates
/// GGX maps from the photo; renders are the GGX renderer's
/// ([`crate::svbrdf::render::render`]) of those maps.
pub struct AnalyticMethod {
    name: String,
    info: ModelInfo,
    unet: FoldedMEst,
    device: Device,
    /// `[1, 10, H, W]` of the prepared photo.
    maps: Option<Tensor>,
}

impl AnalyticMethod {
    /// From a loaded analytic [`Baseline`].
    pub fn new(name: String, baseline: &Baseline, info: ModelInfo) -> Result<Self> {
        let BaselineNet::Analytic(a) = &baseline.net else { bail!("{name}: not an analytic baseline ({})", baseline.method) };
        Ok(Self { name, info, unet: a.unet.fold_batchnorm(), device: baseline.device(), maps: None })
    }

    /// The GGX maps `[10, H, W]` (kd, ks, roughness, normal) estimated from
    /// the prepared photo, on the CPU.
    pub fn maps(&self) -> Option<Tensor> {
        self.maps.as_ref().map(|m| m.get(0).to_device(Device::Cpu))
    }
}

impl Method for AnalyticMethod {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        let x = model_input(photo_linear, &self.info, self.device)?;
        let raw = self.unet.forward(&x)?;
        self.maps = Some(tch::no_grad(|| crate::baselines::analytic::AnalyticNet::decode(&raw))?);
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        render_ggx_maps(&self.name, self.maps.as_ref(), configs, self.device)
    }
}

/// Renders a method's GGX maps `[1, 10, H, W]` (the analytic baseline's,
/// or maps fitted to a neural material) with the tensor GGX renderer, in
/// chunks of configurations: `[K, 3, H, W]` linear on the CPU.
pub(crate) fn render_ggx_maps(name: &str, maps: Option<&Tensor>, configs: &[LightView], device: Device) -> Result<Tensor> {
    let Some(maps) = maps else { bail!("{name}: render before prepare") };
    ensure!(!configs.is_empty(), "no light/view configuration to render");
    let parts: Vec<Tensor> = configs
        .chunks(RENDER_CHUNK)
        .map(|c| {
            let (l, v) = config_batch(c, device);
            tch::no_grad(|| crate::svbrdf::render::render(maps, &l, &v)).get(0).to_device(Device::Cpu)
        })
        .collect();
    Ok(Tensor::cat(&parts, 0))
}

/// The direct relighting U-Net baseline: the encoder runs once on the
/// photo, the decoder once per light/view configuration. Its log output
/// is clamped to [0, [`crate::infer::nmat::MAX_LOG_RADIANCE`]] before
/// exp(x) - 1, as neural materials' renders are.
pub struct RelightMethod {
    name: String,
    info: ModelInfo,
    baseline: Baseline,
    /// Encoder features of the prepared photo and its size.
    encoded: Option<(RelightEncoded, usize, usize)>,
}

impl RelightMethod {
    /// From a loaded relighting [`Baseline`].
    pub fn new(name: String, baseline: Baseline, info: ModelInfo) -> Result<Self> {
        ensure!(matches!(baseline.net, BaselineNet::Relight(_)), "{name}: not a relighting U-Net ({})", baseline.method);
        Ok(Self { name, info, baseline, encoded: None })
    }

    fn unet(&self) -> &crate::baselines::RelightUNet {
        match &self.baseline.net {
            BaselineNet::Relight(r) => r,
            BaselineNet::Analytic(_) => unreachable!("checked in RelightMethod::new"),
        }
    }
}

impl Method for RelightMethod {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        let x = model_input(photo_linear, &self.info, self.baseline.device())?;
        let s = x.size();
        let enc = tch::no_grad(|| self.unet().encode_t(&x, false))?;
        self.encoded = Some((enc, s[2] as usize, s[3] as usize));
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        let Some((enc, h, w)) = &self.encoded else { bail!("{}: render before prepare", self.name) };
        ensure!(!configs.is_empty(), "no light/view configuration to render");
        let parts: Vec<Tensor> = configs
            .chunks(RENDER_CHUNK)
            .map(|c| {
                let (l, v) = config_batch(c, self.baseline.device());
                let (wi, wo) = direction_maps_for(&l, &v, *h, *w);
                let log = tch::no_grad(|| self.unet().decode_t(enc, &wi, &wo, false))?;
                Ok(crate::spaces::from_log(&log.get(0).clamp(0.0, crate::infer::nmat::MAX_LOG_RADIANCE)).to_device(Device::Cpu))
            })
            .collect::<Result<_>>()?;
        Ok(Tensor::cat(&parts, 0))
    }
}

/// The method a model file's metadata records; files that are not
/// readable model files count as flashmat files (whose loader's errors
/// name the problem).
fn recorded_method(path: &Path) -> Result<TrainMethod> {
    Ok(match crate::model::file::recorded_method(path) {
        Ok(name) => TrainMethod::from_name(&name).with_context(|| format!("model file {}", path.display()))?,
        Err(_) => TrainMethod::Flashmat,
    })
}

/// Opens a model file as the method its metadata records: flashmat
/// ([`ModelMethod`]), analytic ([`AnalyticMethod`]) or relight-unet
/// ([`RelightMethod`]).
pub fn open_model_file(path: &Path, name: String, ldr_photo: bool, device: Device) -> Result<Box<dyn Method>> {
    Ok(match recorded_method(path)? {
        TrainMethod::Flashmat => Box::new(ModelMethod::load(path, name, ldr_photo, device)?),
        TrainMethod::Analytic => {
            let (b, info) = Baseline::load(path, device)?;
            Box::new(AnalyticMethod::new(name, &b, info)?)
        }
        TrainMethod::RelightUnet => {
            let (b, info) = Baseline::load(path, device)?;
            Box::new(RelightMethod::new(name, b, info)?)
        }
    })
}

/// Opens `--model` values: `printout` or a model file of any method (named
/// by its file stem; repeated names get `-2`, `-3` ...). With `refine`
/// settings, each flashmat model becomes one method per setting, named
/// `NAME+refineSTEPS`, and a setting of 0 steps is the unrefined `NAME`
/// (so `--refine 0,100` scores both, `--refine 100` only the refined one).
/// Flashmat models handle the photo's exposure as `exposure` says. With
/// `highlight_fill`, each of those also comes with its photographed
/// highlight filled (`NAME+fill`, `NAME+fill+refineSTEPS`), for pairing.
pub fn open_methods(specs: &[String], ldr_photo: bool, device: Device, refine: &[RefineConfig], exposure: &ExposureConfig, highlight_fill: Option<HighlightFillConfig>) -> Result<Vec<Box<dyn Method>>> {
    ensure!(!specs.is_empty(), "give at least one --model (a model file or `printout`)");
    let mut out: Vec<Box<dyn Method>> = Vec::new();
    let mut names: Vec<String> = Vec::new();
    for spec in specs {
        // `FILE+fit[STEPS]`: the model's estimates fitted with GGX maps ([`fit`]).
        let fit_spec = fit::split_fit_spec(spec);
        let file = fit_spec.map_or(spec.as_str(), |(file, _)| file);
        let base = if spec == PRINTOUT {
            PRINTOUT.to_string()
        } else {
            Path::new(file).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| spec.clone())
        };
        let base = fit_spec.map_or(base.clone(), |(_, steps)| fit::fitted_name(&base, steps));
        let mut name = base.clone();
        let mut n = 1;
        while names.contains(&name) {
            n += 1;
            name = format!("{base}-{n}");
        }
        names.push(name.clone());
        if spec == PRINTOUT {
            out.push(Box::new(PrintoutMethod::default()));
            continue;
        }
        if let Some((file, steps)) = fit_spec {
            let cfg = crate::fit::FitConfig { steps, ..Default::default() };
            out.push(Box::new(fit::FitMethod::load(Path::new(file), name, ldr_photo, device, cfg, exposure)?));
            continue;
        }
        let path = Path::new(spec);
        if recorded_method(path)? != TrainMethod::Flashmat {
            out.push(open_model_file(path, name, ldr_photo, device)?);
            continue;
        }
        // One method per refinement setting (0 steps: unrefined), each also
        // with the highlight fill when asked.
        let settings: Vec<Option<&RefineConfig>> = if refine.is_empty() { vec![None] } else { refine.iter().map(|c| (c.steps > 0).then_some(c)).collect() };
        for cfg in settings {
            for fill in std::iter::once(None).chain(highlight_fill.map(Some)) {
                let filled = fill.map_or(name.clone(), |_| filled_name(&name));
                let variant = cfg.map_or(filled.clone(), |c| refined_name(&filled, c.steps));
                if variant != name {
                    names.push(variant.clone());
                }
                let method = ModelMethod::load(path, variant, ldr_photo, device)?.with_exposure(*exposure).with_highlight_fill(fill);
                out.push(Box::new(match cfg {
                    Some(c) => method.with_refine(c.clone()),
                    None => method,
                }));
            }
        }
    }
    Ok(out)
}
