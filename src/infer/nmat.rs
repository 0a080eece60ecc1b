//! The `.nmat` neural material file: everything needed to render a material
//! estimated from a photo, without M_est. A checksummed, versioned
//! safetensors archive (see `crate::archive`, format tag `flashmat-nmat`,
//! version 3), specified in docs/NMAT.md for readers in other languages.
//!
//! Tensors (f32): `neural_map` `[C, H, W]`, `input_photo` `[3, H, W]` (the
//! linear photo M_est saw) and the renderer weights under their model names
//! (`renderer.nd_enc.*`, `renderer.m_render.*`). Metadata: `model_id`,
//! `config` (TOML), `fov_deg`, `crop` (JSON), `source`, `ldr_input`,
//! `model_info` (JSON), `resolution` (JSON), `gain` (the exposure and white
//! balance the network's radiance is multiplied by, [`NmatMeta::gain`]).

use super::photo::Crop;
use crate::archive::{restore_vars, Archive};
use crate::geometry::{LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::model::{ModelConfig, ModelInfo, NeuralRenderer};
use anyhow::{bail, ensure, Context, Result};
use std::collections::HashMap;
use std::path::Path;
use tch::{nn, Device, Tensor};

/// Format tag and version of `.nmat` files. Version 4 makes the gain one
/// per channel (a JSON array `[r, g, b]`); version 3 adds the exposure
/// `gain` (one number); version 2 allows rectangular maps (the shorter side spans
/// [-1, 1]) and stores the crop's width and height. Version-1 files
/// (square, `side`) and version-2 files are still read (gain 1).
pub const NMAT_FORMAT: &str = "flashmat-nmat";
pub const NMAT_VERSION: u32 = 4;

/// Older versions this flashmat still reads.
pub const NMAT_READABLE_VERSIONS: &[u32] = &[1, 2, 3, 4];

/// Largest ln(1 + R) turned into radiance: exp(80) = 5.5e34 stays finite in
/// f32, so renders of untrained or diverged models can still be written
/// (trained ones stay far below: a mirror-like GGX highlight is ln(1 + R) ~ 10).
pub const MAX_LOG_RADIANCE: f64 = 80.0;

/// Where a neural material came from.
#[derive(Clone, Debug, PartialEq)]
pub struct NmatMeta {
    /// Id of the model that estimated it ([`ModelConfig::model_id`]).
    pub model_id: String,
    /// Field of view of the source photo across its shorter side.
    pub fov_deg: f64,
    /// Part of the source photo that became the model input.
    pub crop: Crop,
    /// File name of the source photo.
    pub source: String,
    /// The photo was an 8/16-bit display-encoded file (LDR), not an EXR.
    pub ldr_input: bool,
    /// What the estimating model's file recorded.
    pub model_info: ModelInfo,
    /// The refinement on the photo applied after M_est, if any.
    pub refine: Option<super::refine::settings::RefineReport>,
    /// Exposure and white balance of the material, per channel (R, G, B):
    /// every render is the network's radiance times this (finite, > 0).
    /// M_est saw the photo times the inverse of its exposure part (and
    /// clamped for an LDR model), so a photo one stop darker gives the same
    /// neural map and half the gain; the calibration on the identity render
    /// sets each channel ([`super::exposure`]). One number for all three in
    /// version-3 files, 1 in files written before.
    pub gain: [f64; 3],
}

/// A relightable neural material: per-pixel parameters and the neural BRDF
/// that renders them.
#[derive(Debug)]
pub struct NeuralMaterial {
    /// Learned per-pixel parameters `[C, H, W]` (C = `config.neural_channels`).
    pub neural_map: Tensor,
    /// The linear input photo as M_est saw it `[3, H, W]`.
    pub input_photo: Tensor,
    pub config: ModelConfig,
    /// ND_enc + M_render; its variables live in `renderer_vs` (frozen).
    pub renderer: NeuralRenderer,
    pub renderer_vs: nn::VarStore,
    pub meta: NmatMeta,
}

impl NeuralMaterial {
    /// Builds a material from its parts; the renderer weights (named
    /// `renderer.nd_enc.*`, `renderer.m_render.*` as in
    /// `Model::renderer_vs`) are copied into a fresh, frozen renderer on
    /// the neural map's device.
    /// neural_map: `[C, H, W]`; input_photo: `[3, H, W]`.
    pub fn from_parts(
        neural_map: Tensor,
        input_photo: Tensor,
        config: &ModelConfig,
        weights: &HashMap<String, Tensor>,
        meta: NmatMeta,
    ) -> Result<Self> {
        let s = neural_map.size();
        ensure!(s.len() == 3 && s[0] == config.neural_channels, "neural map must be [{}, H, W], got {s:?}", config.neural_channels);
        ensure!(input_photo.size() == [3, s[1], s[2]], "input photo must be [3, {}, {}], got {:?}", s[1], s[2], input_photo.size());
        ensure!(meta.gain.iter().all(|g| g.is_finite() && *g > 0.0), "the exposure gain must be three positive numbers, got {:?}", meta.gain);
        let device = neural_map.device();
        let mut renderer_vs = nn::VarStore::new(device);
        let renderer = NeuralRenderer::new(&(renderer_vs.root() / "renderer"), config)?;
        restore_vars(&renderer_vs.variables(), weights, "renderer")?;
        renderer_vs.freeze();
        let neural_map = neural_map.detach().to_kind(tch::Kind::Float);
        let input_photo = input_photo.detach().to_device(device).to_kind(tch::Kind::Float);
        Ok(Self { neural_map, input_photo, config: config.clone(), renderer, renderer_vs, meta })
    }

    /// Fills the photographed flash highlight in the map with the codes of
    /// the material beside it ([`super::highlight_fill`]); the report says
    /// what was done.
    pub fn fill_highlight(&mut self, cfg: &super::highlight_fill::HighlightFillConfig) -> Result<super::highlight_fill::FillReport> {
        let (map, report) = super::highlight_fill::fill_highlight(&self.neural_map, &self.input_photo, cfg)?;
        self.neural_map = map;
        Ok(report)
    }

    /// An independent copy (own map, photo and renderer weights): to try
    /// several refinements of one estimate.
    pub fn duplicate(&self) -> Result<Self> {
        Self::from_parts(self.neural_map.copy(), self.input_photo.copy(), &self.config, &self.renderer_vs.variables(), self.meta.clone())
    }

    /// (H, W) of the neural map.
    pub fn size(&self) -> (usize, usize) {
        let s = self.neural_map.size();
        (s[1] as usize, s[2] as usize)
    }

    pub fn device(&self) -> Device {
        self.neural_map.device()
    }

    /// Light and camera of the input photo (after the FOV crop the photo is
    /// always the model's 28 degree co-located view).
    pub fn identity_config() -> LightView {
        LightView::colocated(MODEL_FOV_DEG)
    }

    /// Writes the material (atomically) in the documented `.nmat` format.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut a = Archive::new();
        a.insert("neural_map", &self.neural_map);
        a.insert("input_photo", &self.input_photo);
        for (name, t) in self.renderer_vs.variables() {
            a.insert(name, &t);
        }
        let (h, w) = self.size();
        let m = &self.meta;
        a.set_meta("model_id", m.model_id.clone());
        a.set_meta("config", self.config.to_toml_string()?);
        a.set_meta("fov_deg", m.fov_deg.to_string());
        a.set_meta("crop", serde_json::to_string(&m.crop)?);
        a.set_meta("source", m.source.clone());
        a.set_meta("ldr_input", m.ldr_input.to_string());
        a.set_meta("model_info", serde_json::to_string(&m.model_info)?);
        a.set_meta("resolution", serde_json::to_string(&[h, w])?);
        a.set_meta("gain", serde_json::to_string(&m.gain)?);
        if let Some(r) = &m.refine {
            a.set_meta("refine", serde_json::to_string(r)?);
        }
        a.save(path, NMAT_FORMAT, NMAT_VERSION)
    }

    /// Reads a `.nmat` file onto `device`. Damaged, truncated, foreign or
    /// other-version files, and inconsistent contents, are refused with a
    /// message naming the file.
    pub fn load(path: &Path, device: Device) -> Result<Self> {
        let a = Archive::load_versions(path, NMAT_FORMAT, NMAT_READABLE_VERSIONS).context("cannot load neural material")?;
        Self::from_archive(&a, device).with_context(|| format!("neural material {}", path.display()))
    }

    fn from_archive(a: &Archive, device: Device) -> Result<Self> {
        let config = ModelConfig::from_toml_str(a.meta("config")?)?;
        let model_id = a.meta("model_id")?.to_string();
        ensure!(model_id == config.model_id(), "model id '{model_id}' does not match the stored configuration");
        let parse_bool = |k: &str| -> Result<bool> {
            match a.meta(k)? {
                "true" => Ok(true),
                "false" => Ok(false),
                other => bail!("metadata field '{k}' must be true or false, got '{other}'"),
            }
        };
        let fov_deg: f64 = a.meta("fov_deg")?.parse().context("metadata field 'fov_deg' is not a number")?;
        let gain = match a.metadata.get("gain") {
            Some(g) => parse_gain(g)?,
            // Files before version 3 have no exposure: the network's radiance as it is.
            None => [1.0; 3],
        };
        let meta = NmatMeta {
            model_id,
            fov_deg,
            crop: serde_json::from_str(a.meta("crop")?).context("metadata field 'crop'")?,
            source: a.meta("source")?.to_string(),
            ldr_input: parse_bool("ldr_input")?,
            model_info: serde_json::from_str(a.meta("model_info")?).context("metadata field 'model_info'")?,
            refine: a.metadata.get("refine").map(|r| serde_json::from_str(r)).transpose().context("metadata field 'refine'")?,
            gain,
        };
        let neural_map = a.tensor("neural_map")?.to_device(device);
        let input_photo = a.tensor("input_photo")?.shallow_clone();
        let resolution: [i64; 2] = serde_json::from_str(a.meta("resolution")?).context("metadata field 'resolution'")?;
        let s = neural_map.size();
        ensure!(s.len() == 3 && s[1..] == resolution, "neural_map has shape {s:?}, the metadata says resolution {resolution:?}");
        let weights: HashMap<String, Tensor> =
            a.tensors.iter().filter(|(k, _)| k.starts_with("renderer.")).map(|(k, v)| (k.clone(), v.shallow_clone())).collect();
        let unknown: Vec<&String> =
            a.tensors.keys().filter(|k| !k.starts_with("renderer.") && *k != "neural_map" && *k != "input_photo").collect();
        ensure!(unknown.is_empty(), "unexpected tensors {unknown:?}");
        check_meta(&meta, s[1], s[2])?;
        Self::from_parts(neural_map, input_photo, &config, &weights, meta)
    }

    /// Linear radiance for K light/view configurations (camera-independent
    /// rectified view: every pixel is its own BRDF sample, REFERENCE section 1):
    /// the network's radiance times the material's exposure
    /// [`NmatMeta::gain`]. Returns `[K, 3, H, W]`, clamped at 0 (M_render's
    /// final LeakyReLU can dip slightly below ln(1 + 0)) and, in log space
    /// before the gain, at [`MAX_LOG_RADIANCE`].
    pub fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        let rows = super::tiles::render_band_rows(&self.config, self.size().1, configs.len());
        self.render_in_bands(configs, rows)
    }

    /// [`NeuralMaterial::render`] `rows` rows at a time. Returns `[K, 3, H, W]`.
    pub fn render_in_bands(&self, configs: &[LightView], rows: usize) -> Result<Tensor> {
        ensure!(rows > 0, "render bands need at least one row");
        check_configs(configs)?;
        let (wi, wo) = self.direction_maps(configs); // [1, K, 3, H, W]
        let h = self.size().0;
        // Bands of rows bound the memory of large maps (M_render is per pixel: exact).
        let map = self.neural_map.unsqueeze(0); // [1, C, H, W]
        let log = tch::no_grad(|| -> Result<Tensor> {
            if rows >= h {
                return self.renderer.forward_maps(&map, &wi, &wo);
            }
            let bands = (0..h)
                .step_by(rows)
                .map(|r0| {
                    let n = rows.min(h - r0) as i64;
                    let r0 = r0 as i64;
                    self.renderer.forward_maps(&map.narrow(2, r0, n), &wi.narrow(3, r0, n), &wo.narrow(3, r0, n))
                })
                .collect::<Result<Vec<_>>>()?;
            Ok(Tensor::cat(&bands, 3))
        })?;
        self.radiance_of_log(&log.get(0))
    }

    /// Radiance under per-pixel directions, with autograd: gradients reach
    /// the neural map, the renderer's weights and the directions wherever
    /// they require them (the Python `render_dirs`; the renders above run
    /// without a graph, in bands). wi, wo: `[K, 3, H, W]` unit vectors
    /// towards the light and the camera -> `[K, 3, H, W]`, clamped as in
    /// [`NeuralMaterial::render`].
    pub fn render_directions(&self, wi: &Tensor, wo: &Tensor) -> Result<Tensor> {
        self.render_map_directions(&self.neural_map, wi, wo)
    }

    /// [`NeuralMaterial::render_directions`] for light/view positions, with
    /// autograd (the Python `render`), at the map's resolution or with its
    /// shorter side resampled to `size` pixels (bilinear in the codes, the
    /// longer side following the aspect; an approximation, as the Mitsuba
    /// plugin's `bilinear` filter). Returns `[K, 3, H', W']`.
    pub fn render_differentiable(&self, configs: &[LightView], size: Option<usize>) -> Result<Tensor> {
        check_configs(configs)?;
        let (h, w) = self.size();
        let (oh, ow) = match size {
            None => (h, w),
            Some(s) => {
                ensure!(s >= 1, "the render size must be at least 1 pixel");
                crate::limits::MATERIAL_SIZE.check("the render size", s as u64)?;
                let scale = s as f64 / h.min(w) as f64;
                (((h as f64 * scale).round() as usize).max(1), ((w as f64 * scale).round() as usize).max(1))
            }
        };
        let map = match (oh, ow) == (h, w) {
            true => self.neural_map.shallow_clone(),
            false => self.neural_map.unsqueeze(0).upsample_bilinear2d([oh as i64, ow as i64], false, None, None).get(0),
        };
        let (wi, wo) = self.direction_maps_at(configs, oh, ow);
        self.render_map_directions(&map, &wi.get(0), &wo.get(0))
    }

    /// map: `[C, H, W]`; wi, wo: `[K, 3, H, W]` -> radiance `[K, 3, H, W]`.
    fn render_map_directions(&self, map: &Tensor, wi: &Tensor, wo: &Tensor) -> Result<Tensor> {
        let s = map.size();
        let (h, w) = (s[1], s[2]);
        for (name, d) in [("wi", wi), ("wo", wo)] {
            let ds = d.size();
            ensure!(ds.len() == 4 && ds[1] == 3 && ds[2] == h && ds[3] == w, "{name} must be [K, 3, {h}, {w}], got {ds:?}");
            ensure!(d.device() == self.device(), "{name} is on {:?}, the material on {:?}", d.device(), self.device());
            ensure!(crate::image::all_finite(d), "{name} holds NaN or infinite values");
        }
        ensure!(wi.size() == wo.size(), "wi {:?} and wo {:?} must have the same shape", wi.size(), wo.size());
        let kind = tch::Kind::Float;
        let log = self.renderer.forward_maps(&map.unsqueeze(0), &wi.to_kind(kind).unsqueeze(0), &wo.to_kind(kind).unsqueeze(0))?;
        self.radiance_of_log(&log.get(0))
    }

    /// Radiance of the network's ln(1 + R) `[K, 3, H, W]`: clamped, times
    /// the gain.
    fn radiance_of_log(&self, log: &Tensor) -> Result<Tensor> {
        // Finite weights can still overflow to Inf - Inf = NaN, which the
        // clamps below would keep (Inf itself clamps to MAX_LOG_RADIANCE).
        ensure!(log.isnan().any().int64_value(&[]) == 0, "M_render produced NaN values for this material (weights out of range?)");
        Ok(crate::spaces::from_log(&log.clamp_max(MAX_LOG_RADIANCE)).clamp_min(0.0) * self.gain_tensor().view([3, 1, 1]))
    }

    /// The same material on `device` (map, photo and renderer copied).
    pub fn to_device(&self, device: Device) -> Result<Self> {
        Self::from_parts(self.neural_map.to_device(device), self.input_photo.to_device(device), &self.config, &self.renderer_vs.variables(), self.meta.clone())
    }

    /// [`NmatMeta::gain`] as a `[3]` float tensor on the material's device.
    pub fn gain_tensor(&self) -> Tensor {
        Tensor::from_slice(&self.meta.gain).to_kind(tch::Kind::Float).to_device(self.device())
    }

    /// The network's ln(1 + R) `[.., 3]` (channels last; clamped to
    /// [0, [`MAX_LOG_RADIANCE`]]) as the material renders it: ln(1 + gain R)
    /// per channel. Identity at gain 1.
    pub fn with_gain_log(&self, network_log: &Tensor) -> Tensor {
        let log = network_log.clamp(0.0, MAX_LOG_RADIANCE);
        if self.meta.gain == [1.0; 3] {
            return log;
        }
        crate::spaces::to_log(&(crate::spaces::from_log(&log) * self.gain_tensor()))
    }

    /// Per-pixel unit directions towards the light and the camera of each
    /// configuration over this material's pixels: wi, wo `[1, K, 3, H, W]`.
    pub fn direction_maps(&self, configs: &[LightView]) -> (Tensor, Tensor) {
        let (h, w) = self.size();
        self.direction_maps_at(configs, h, w)
    }

    /// [`NeuralMaterial::direction_maps`] over an `h x w` grid of the same
    /// extent: `[1, K, 3, h, w]` each.
    fn direction_maps_at(&self, configs: &[LightView], h: usize, w: usize) -> (Tensor, Tensor) {
        let k = configs.len() as i64;
        let (lights, views) = crate::geometry::config_tensors(configs, self.device());
        crate::svbrdf::render::direction_maps_for(&lights.view([1, k, 3]), &views.view([1, k, 3]), h, w)
    }

    /// One linear render `[3, H, W]` as an image.
    pub fn render_image(&self, config: &LightView) -> Result<Image> {
        Image::from_tensor(&self.render(std::slice::from_ref(config))?.get(0))
    }

    /// The stored input photo (linear) as an image.
    pub fn input_image(&self) -> Result<Image> {
        Image::from_tensor(&self.input_photo)
    }
}

/// Renders need at least one configuration, with light and camera above
/// the surface.
fn check_configs(configs: &[LightView]) -> Result<()> {
    ensure!(!configs.is_empty(), "no light/view configuration to render");
    for c in configs {
        crate::geometry::above_surface("light", c.light)?;
        crate::geometry::above_surface("camera", c.view)?;
    }
    Ok(())
}

/// The stored `gain`: a JSON array of three positive numbers (version 4)
/// or one number for all three channels (version 3).
fn parse_gain(text: &str) -> Result<[f64; 3]> {
    let gain = match text.trim().parse::<f64>() {
        Ok(g) => Some([g; 3]),
        Err(_) => serde_json::from_str::<[f64; 3]>(text).ok(),
    };
    gain.filter(|g| g.iter().all(|v| v.is_finite() && *v > 0.0))
        .with_context(|| format!("metadata field 'gain' must be a positive number or three of them ([r, g, b]), got '{text}'"))
}

/// Refuses metadata that contradicts itself or the `h x w` neural map
/// (checksums only prove the file is as written, not that its writer was
/// right): a field of view outside what a photo can have, a crop outside
/// its source photo, or a crop whose aspect is not the map's (a map stored
/// transposed under a consistent header would render scrambled).
fn check_meta(meta: &NmatMeta, h: i64, w: i64) -> Result<()> {
    let fov = meta.fov_deg;
    ensure!(
        fov.is_finite() && (MODEL_FOV_DEG - 1e-9..=super::photo::MAX_FOV_DEG).contains(&fov),
        "metadata field 'fov_deg' is {fov}, not a field of view from {MODEL_FOV_DEG} to {} degrees",
        super::photo::MAX_FOV_DEG
    );
    let c = &meta.crop;
    let inside = |start: usize, len: usize, source: usize| len >= 1 && start.checked_add(len).is_some_and(|end| end <= source);
    ensure!(
        inside(c.x0, c.width, c.source_width) && inside(c.y0, c.height, c.source_height),
        "metadata field 'crop' ({}x{} at ({}, {})) lies outside its {}x{} source photo",
        c.width,
        c.height,
        c.x0,
        c.y0,
        c.source_width,
        c.source_height
    );
    // The estimate trims the crop to the map's aspect within one source
    // pixel of its longer side (`photo::prepare_image_with`).
    let (cw, ch) = (c.width as f64, c.height as f64);
    let (h, w) = (h as f64, w as f64);
    ensure!(
        (cw * h - ch * w).abs() <= h.max(w) + 1e-9,
        "metadata field 'crop' ({}x{}) does not have the aspect of the {w}x{h} neural map",
        c.width,
        c.height
    );
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::model::{Model, ModelInfo};

    pub(crate) fn random_material(seed: i64, size: i64) -> NeuralMaterial {
        tch::manual_seed(seed);
        let cfg = ModelConfig::tiny();
        let model = Model::new(&cfg, Device::Cpu).unwrap();
        let weights: HashMap<String, Tensor> = model.renderer_vs.variables();
        let meta = NmatMeta {
            model_id: cfg.model_id(),
            fov_deg: 45.0,
            crop: Crop { x0: 3, y0: 0, width: 20, height: 20, source_width: 26, source_height: 20 },
            source: "photo é.png".into(),
            ldr_input: true,
            model_info: ModelInfo { ldr_input: true, steps: 7 },
            refine: None,
            gain: [1.0; 3],
        };
        let map = Tensor::randn([cfg.neural_channels, size, size], (tch::Kind::Float, Device::Cpu));
        let photo = Tensor::rand([3, size, size], (tch::Kind::Float, Device::Cpu));
        NeuralMaterial::from_parts(map, photo, &cfg, &weights, meta).unwrap()
    }

    fn configs() -> Vec<LightView> {
        vec![NeuralMaterial::identity_config(), LightView { light: [1.0, -0.5, 2.0], view: [0.3, 0.2, 3.0] }]
    }

    #[test]
    fn the_differentiable_render_is_the_render_and_carries_gradients() {
        let mut m = random_material(5, 16);
        m.meta.gain = [1.5, 1.0, 0.5];
        let plain = m.render(&configs()).unwrap();
        let graph = m.render_differentiable(&configs(), None).unwrap();
        assert_eq!(graph.size(), [2, 3, 16, 16]);
        assert!((&plain - &graph).abs().max().double_value(&[]) <= 1e-5 * plain.abs().max().double_value(&[]));
        // Through render_directions with the same direction maps.
        let (wi, wo) = m.direction_maps(&configs());
        let dirs = m.render_directions(&wi.get(0), &wo.get(0)).unwrap();
        assert!((&plain - &dirs).abs().max().double_value(&[]) <= 1e-5 * plain.abs().max().double_value(&[]));
        // Gradients reach the map and the directions.
        let _ = m.neural_map.set_requires_grad(true);
        let wi = wi.get(0).set_requires_grad(true);
        m.render_directions(&wi, &wo.get(0)).unwrap().sum(tch::Kind::Float).backward();
        assert!(m.neural_map.grad().abs().sum(tch::Kind::Float).double_value(&[]) > 0.0);
        assert!(wi.grad().abs().sum(tch::Kind::Float).double_value(&[]) > 0.0);
        // Half the size: the codes resampled, the directions of the new pixels.
        assert_eq!(m.render_differentiable(&configs(), Some(8)).unwrap().size(), [2, 3, 8, 8]);
        assert!(m.render_differentiable(&configs(), Some(0)).is_err());
        let bad = Tensor::full([1, 3, 16, 16], f64::NAN, (tch::Kind::Float, Device::Cpu));
        assert!(format!("{:#}", m.render_directions(&bad, &bad).unwrap_err()).contains("NaN"));
        assert!(m.render_directions(&wi.narrow(2, 0, 8), &wi.narrow(2, 0, 8)).is_err());
    }

    #[test]
    fn round_trip_renders_identical_pixels() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.nmat");
        let m = random_material(1, 16);
        m.save(&p).unwrap();
        let back = NeuralMaterial::load(&p, Device::Cpu).unwrap();
        assert_eq!(back.meta, m.meta);
        assert_eq!(back.config, m.config);
        assert_eq!(back.size(), (16, 16));
        assert!(back.neural_map.equal(&m.neural_map));
        assert!(back.input_photo.equal(&m.input_photo));
        let (a, b) = (m.render(&configs()).unwrap(), back.render(&configs()).unwrap());
        assert_eq!(a.size(), [2, 3, 16, 16]);
        assert!(a.equal(&b), "renders differ after a round trip");
        assert!(a.min().double_value(&[]) >= 0.0);
        // Only the file itself: no temporary left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn damaged_truncated_and_foreign_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.nmat");
        random_material(2, 8).save(&p).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let err = |path: &Path| format!("{:#}", NeuralMaterial::load(path, Device::Cpu).unwrap_err());

        let mut flipped = bytes.clone();
        let n = flipped.len();
        flipped[n - 100] ^= 0x10;
        let bad = dir.path().join("flipped.nmat");
        std::fs::write(&bad, &flipped).unwrap();
        let e = err(&bad);
        assert!(e.contains("flipped.nmat") && e.contains("checksum"), "{e}");

        let cut = dir.path().join("cut.nmat");
        std::fs::write(&cut, &bytes[..n / 2]).unwrap();
        let e = err(&cut);
        assert!(e.contains("cut.nmat") && e.contains("truncated"), "{e}");

        // An exported model file is a flashmat archive of another format.
        let model_file = dir.path().join("model.safetensors");
        Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(&model_file, &ModelInfo::default(), false).unwrap();
        let e = err(&model_file);
        assert!(e.contains("model.safetensors") && e.contains("'flashmat-model' file, expected a 'flashmat-nmat'"), "{e}");

        // A plain safetensors file from elsewhere.
        let foreign = dir.path().join("random.safetensors");
        let data: Vec<u8> = (0..64u32).flat_map(|i| (i as f32).to_le_bytes()).collect();
        let view = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![8, 8], &data).unwrap();
        std::fs::write(&foreign, safetensors::tensor::serialize([("w", view)], None).unwrap()).unwrap();
        let e = err(&foreign);
        assert!(e.contains("random.safetensors") && e.contains("no format tag"), "{e}");

        // Another version of the format.
        let mut a = Archive::load(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
        let v5 = dir.path().join("v5.nmat");
        a.save(&v5, NMAT_FORMAT, 5).unwrap();
        let e = err(&v5);
        assert!(e.contains("v5.nmat") && e.contains("version 5 is not supported (this flashmat reads versions 1, 2, 3 and 4)"), "{e}");
        // A gain that is not a positive number, or not three of them.
        for bad in ["0", "-2", "NaN", "inf", "bright", "[1, 2]", "[1, 0, 1]", "[1, 2, 3, 4]", "[1, null, 1]"] {
            let mut g = Archive::load(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
            g.set_meta("gain", bad);
            let path = dir.path().join("gain.nmat");
            g.save(&path, NMAT_FORMAT, NMAT_VERSION).unwrap();
            assert!(err(&path).contains("metadata field 'gain' must be a positive number or three"), "{bad}: {}", err(&path));
        }
        // Version 3 stored one number for all three channels.
        let mut v3 = Archive::load(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
        v3.set_meta("gain", "0.25");
        let old3 = dir.path().join("v3.nmat");
        v3.save(&old3, NMAT_FORMAT, 3).unwrap();
        assert_eq!(NeuralMaterial::load(&old3, Device::Cpu).unwrap().meta.gain, [0.25; 3]);
        // A version-1 file (square crop stored as `side`) is still read.
        let mut v1 = Archive::load(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
        v1.set_meta("crop", r#"{"x0":3,"y0":0,"side":20,"source_width":26,"source_height":20}"#.to_string());
        let old = dir.path().join("v1.nmat");
        v1.save(&old, NMAT_FORMAT, 1).unwrap();
        let back = NeuralMaterial::load(&old, Device::Cpu).unwrap();
        assert_eq!((back.meta.crop.width, back.meta.crop.height, back.meta.crop.x0), (20, 20, 3));
        assert_eq!(back.meta.gain, [1.0; 3], "files before version 3 have no exposure gain");
        v1.set_meta("crop", r#"{"x0":3,"y0":0,"width":20,"source_width":26,"source_height":20}"#.to_string());
        v1.save(&old, NMAT_FORMAT, 1).unwrap();
        assert!(err(&old).contains("width and height"), "{}", err(&old));

        // Consistent checksum but inconsistent contents.
        a.insert("neural_map", &Tensor::zeros([3, 8, 8], (tch::Kind::Float, Device::Cpu)));
        let wrong = dir.path().join("wrong.nmat");
        a.save(&wrong, NMAT_FORMAT, NMAT_VERSION).unwrap();
        let e = err(&wrong);
        assert!(e.contains("wrong.nmat") && e.contains("neural map must be [16, H, W]"), "{e}");
        a.insert("neural_map", &Tensor::zeros([16, 8, 8], (tch::Kind::Float, Device::Cpu)));
        a.tensors.remove("renderer.m_render.3.weight");
        a.save(&wrong, NMAT_FORMAT, NMAT_VERSION).unwrap();
        assert!(err(&wrong).contains("renderer.m_render.3.weight"));

        let e = err(&dir.path().join("missing.nmat"));
        assert!(e.contains("missing.nmat") && e.contains("No such file"), "{e}");
    }

    /// The exposure gain survives the file and multiplies every render,
    /// each channel by its own, and [`NeuralMaterial::with_gain_log`] is the
    /// same in log space (channels last).
    #[test]
    fn the_gain_is_stored_and_scales_every_render() {
        let dir = tempfile::tempdir().unwrap();
        let mut m = random_material(5, 8);
        let unit = m.render(&configs()).unwrap(); // [K, 3, H, W]
        let gain = [0.0625, 0.5, 2.0];
        m.meta.gain = gain;
        let p = dir.path().join("g.nmat");
        m.save(&p).unwrap();
        let back = NeuralMaterial::load(&p, Device::Cpu).unwrap();
        assert_eq!(back.meta.gain, gain);
        let scaled = back.render(&configs()).unwrap();
        assert!(unit.max().double_value(&[]) > 0.0);
        for (c, g) in gain.iter().enumerate() {
            let (s, u) = (scaled.select(1, c as i64), unit.select(1, c as i64));
            assert!((&s - &u * *g).abs().max().double_value(&[]) < 1e-6 * (1.0 + unit.max().double_value(&[])), "channel {c}");
        }
        // ln(1 + R) values in rows of [R, G, B]: each column by its own gain.
        let log = Tensor::from_slice(&[0.0f32, 0.5, 3.0, 100.0, 1.0, 2.0]).view([2, 3]);
        let e = |v: f64, c: usize| (v.min(MAX_LOG_RADIANCE).exp_m1() * gain[c]).ln_1p();
        let expect = Tensor::from_slice(&[e(0.0, 0), e(0.5, 1), e(3.0, 2), e(100.0, 0), e(1.0, 1), e(2.0, 2)]).view([2, 3]);
        assert!((back.with_gain_log(&log).to_kind(tch::Kind::Double) - expect).abs().max().double_value(&[]) < 1e-5);
        for bad in [[f64::NAN, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, -1.0]] {
            assert!(NeuralMaterial::from_parts(m.neural_map.copy(), m.input_photo.copy(), &m.config, &m.renderer_vs.variables(), NmatMeta { gain: bad, ..m.meta.clone() }).is_err());
        }
    }

    /// Metadata whose checksums are intact but which contradicts itself is
    /// refused at load with one line naming the field.
    #[test]
    fn contradictory_metadata_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.nmat");
        random_material(2, 8).save(&p).unwrap();
        let good = Archive::load(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
        for (field, value, needle) in [
            ("fov_deg", "NaN", "'fov_deg' is NaN"),
            ("fov_deg", "12", "'fov_deg' is 12"),
            ("fov_deg", "179", "'fov_deg' is 179"),
            ("crop", r#"{"x0":10,"y0":0,"width":20,"height":20,"source_width":26,"source_height":20}"#, "outside its 26x20 source photo"),
            ("crop", r#"{"x0":0,"y0":0,"width":0,"height":0,"source_width":26,"source_height":20}"#, "outside"),
            ("crop", r#"{"x0":0,"y0":0,"width":26,"height":13,"source_width":26,"source_height":20}"#, "aspect of the 8x8 neural map"),
            ("resolution", "[8,9]", "resolution [8, 9]"),
        ] {
            let mut a = Archive::load(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
            a.set_meta(field, value.to_string());
            let bad = dir.path().join("bad.nmat");
            a.save(&bad, NMAT_FORMAT, NMAT_VERSION).unwrap();
            let e = format!("{:#}", NeuralMaterial::load(&bad, Device::Cpu).unwrap_err());
            assert!(e.contains("bad.nmat") && e.contains(needle) && !e.contains('\n'), "{field} = {value}: {e}");
        }
        // Within a source pixel of the map's aspect, as estimates trim crops.
        let mut a = good;
        a.set_meta("crop", r#"{"x0":0,"y0":0,"width":21,"height":20,"source_width":26,"source_height":20}"#.to_string());
        a.save(&p, NMAT_FORMAT, NMAT_VERSION).unwrap();
        NeuralMaterial::load(&p, Device::Cpu).unwrap();
    }

    /// Rendering in bands of rows is the whole render (M_render is per
    /// pixel); only BLAS blocking can differ, measured 0 on CPU.
    #[test]
    fn banded_render_equals_whole_render() {
        let m = random_material(6, 16);
        let whole = m.render_in_bands(&configs(), 16).unwrap();
        let banded = m.render_in_bands(&configs(), 5).unwrap();
        assert_eq!(banded.size(), [2, 3, 16, 16]);
        let d = (&whole - &banded).abs().max().double_value(&[]);
        assert!(d <= 1e-5 * (1.0 + whole.abs().max().double_value(&[])), "{d}");
    }

    #[test]
    fn lights_below_the_surface_are_refused() {
        let m = random_material(3, 8);
        let e = m.render(&[LightView { light: [0.0, 1.0, -0.5], view: [0.0, 0.0, 4.0] }]).unwrap_err();
        assert!(e.to_string().contains("light position 0,1,-0.5 is not above the surface"), "{e}");
        assert!(m.render(&[LightView { light: [0.0, 1.0, 1.0], view: [0.0, 0.0, 0.0] }]).is_err());
    }
}
