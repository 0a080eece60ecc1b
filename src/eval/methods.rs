//! Methods under evaluation: each turns the co-located input photo of a
//! material into renders under new light/view configurations.

use crate::geometry::{config_tensors, LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::infer::{self, Crop, NeuralMaterial, PreparedPhoto};
use crate::model::{Model, ModelInfo};
use crate::svbrdf::render::direction_maps_for;
use anyhow::{bail, ensure, Context, Result};
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// Name that selects the print-out baseline on the command line.
pub const PRINTOUT: &str = "printout";

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
    material: Option<NeuralMaterial>,
}

impl ModelMethod {
    /// Loads a model file; `ldr_photo`: the photos are clamped LDR renders
    /// (recorded in the neural material's metadata).
    pub fn load(path: &Path, name: String, ldr_photo: bool, device: Device) -> Result<Self> {
        let loaded = infer::load_model(Some(path), ldr_photo, device)?;
        Ok(Self { name, model: loaded.model, info: loaded.info, ldr_photo, material: None })
    }
}

impl Method for ModelMethod {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        let linear = Image::from_tensor(&photo_linear.to_device(Device::Cpu).to_kind(Kind::Float))?;
        let side = linear.width;
        let photo = PreparedPhoto {
            linear,
            ldr: self.ldr_photo,
            fov_deg: MODEL_FOV_DEG,
            crop: Crop { x0: 0, y0: 0, side, source_width: side, source_height: side },
            source: "evaluation render".into(),
        };
        self.material = Some(infer::estimate(&self.model, &self.info, &photo)?);
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        let Some(m) = &self.material else { bail!("{}: render before prepare", self.name) };
        let parts: Vec<Tensor> =
            configs.chunks(RENDER_CHUNK).map(|c| m.render(c).map(|t| t.to_device(Device::Cpu))).collect::<Result<_>>()?;
        Ok(Tensor::cat(&parts, 0))
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

/// Opens `--model` values: `printout` or a model file (named by its file
/// stem; repeated names get `-2`, `-3` ...).
pub fn open_methods(specs: &[String], ldr_photo: bool, device: Device) -> Result<Vec<Box<dyn Method>>> {
    ensure!(!specs.is_empty(), "give at least one --model (a model file or `printout`)");
    let mut out: Vec<Box<dyn Method>> = Vec::new();
    let mut names: Vec<String> = Vec::new();
    for spec in specs {
        let base = if spec == PRINTOUT {
            PRINTOUT.to_string()
        } else {
            Path::new(spec).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| spec.clone())
        };
        let mut name = base.clone();
        let mut n = 1;
        while names.contains(&name) {
            n += 1;
            name = format!("{base}-{n}");
        }
        names.push(name.clone());
        if spec == PRINTOUT {
            out.push(Box::new(PrintoutMethod::default()));
        } else {
            out.push(Box::new(ModelMethod::load(Path::new(spec), name, ldr_photo, device)?));
        }
    }
    Ok(out)
}
