//! Several photos, one material (`flashmat estimate --capture DIR`): GGX
//! maps fitted per pixel to all photos of a capture folder
//! ([`crate::data::captures`]) with their known light and camera positions,
//! then a neural material of the fitted maps.
//!
//! ```text
//! overhead photo ─► M_est ─► fit_material ─► start maps ─┐
//! photos [K,3,H,W] (fall-off compensated) ───────────────┴─► fit_core ─► maps [10,H,W]
//!   loss = mean charbonnier(ln(1+R_ggx(l_k, v_k)) - ln(1+photo_k))   (clipped pixels: only R below the photo)
//!        + smooth (edges of the mean photo) + pull toward the start maps
//! maps ─► teacher's GgxEncoder ─► neural map; teacher's ND_enc + M_render ─► .nmat
//! ```
//!
//! The Adam loop is `flashmat fit`'s ([`super::fit_core`]); only the data
//! term differs: real point lights and cameras per photo (directions vary
//! over the pixels) instead of shared direction pairs. The pull keeps what
//! the photos do not show: without a highlight in any photo a pixel's
//! roughness and specular level are barely constrained, so there the
//! single-photo estimate holds (the pull weighs them 10x kd's).
//!
//! Left for later: pose refinement, coarse-to-fine.

use super::{decode, edge_weights, encode, fit_core, fit_material, sample_directions, CoreSettings, FitConfig, FitReport, FitResult, CHARBONNIER_EPS, MAX_FIT_STEPS};
use crate::data::captures::{falloff, load_photo_sized, Captures};
use crate::geometry::{LightView, MODEL_FOV_DEG};
use crate::infer::nmat::{NeuralMaterial, NmatMeta};
use crate::infer::photo::Crop;
use crate::infer::{LoadedModel, PreparedPhoto};
use crate::model::ggx_codes::{valid_values, TeacherWeights};
use crate::model::ModelInfo;
use crate::svbrdf::render::{direction_maps_for, render_directions};
use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{Device, Kind, Tensor};

/// The committed teacher (models/MODEL.md), whose encoder turns fitted GGX
/// maps into codes its renderer draws.
pub const BUNDLED_TEACHER: &str = "teacher-compact.safetensors";

/// The bundled teacher, in [`crate::infer::models_dir`].
pub fn default_teacher_path() -> PathBuf {
    crate::infer::models_dir().join(BUNDLED_TEACHER)
}

/// An 8-bit photo value at or above this (any channel, before the
/// fall-off compensation) is clipped: the truth may be brighter.
pub const CLIP_LEVEL: f64 = 0.999;

/// A photo whose mean linear value is below this is black (no light).
const BLACK_MEAN: f64 = 1e-4;

/// Pull factors per map channel (kd 3, ks 3, roughness, normal 3): a
/// specular level and roughness no photo shows stay the start's, while kd
/// and the normal follow the photos' shading.
const PULL_FACTORS: [f64; 10] = [0.1, 0.1, 0.1, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2, 0.2];

/// Settings of the fit to photos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhotoFitConfig {
    /// Adam steps (default 600: a synthetic capture's roughness error halves
    /// from 300 to 600 steps, 0.04 -> 0.016, while its data term has long settled).
    pub steps: usize,
    /// Adam step in the unconstrained parameters, cosine-decayed to a tenth (default 0.05, as `flashmat fit`).
    pub learning_rate: f64,
    /// Weight of the edge-aware smoothness (default 0.01, as `flashmat fit`).
    pub smooth_weight: f64,
    /// Weight of the squared pull toward the start maps, times [`PULL_FACTORS`]
    /// per channel (default 0.05; 0 for a start that is no estimate, e.g. [`flat_start`]).
    pub pull_weight: f64,
    /// Side of the fitted maps in pixels, a multiple of 8 (default 256, the model's resolution).
    pub size: usize,
}

impl Default for PhotoFitConfig {
    fn default() -> Self {
        Self { steps: 600, learning_rate: 0.05, smooth_weight: 0.01, pull_weight: 0.05, size: 256 }
    }
}


impl PhotoFitConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!((1..=MAX_FIT_STEPS).contains(&self.steps), "--steps must be between 1 and {MAX_FIT_STEPS}, got {}", self.steps);
        ensure!(self.learning_rate.is_finite() && self.learning_rate > 0.0, "the fit's learning rate must be a finite number > 0, got {}", self.learning_rate);
        ensure!(self.smooth_weight.is_finite() && self.smooth_weight >= 0.0, "the smoothness weight must be a finite number >= 0, got {}", self.smooth_weight);
        ensure!(self.pull_weight.is_finite() && self.pull_weight >= 0.0, "the pull weight must be a finite number >= 0, got {}", self.pull_weight);
        ensure!(self.size >= 32 && self.size.is_multiple_of(8) && self.size <= 4096, "--size must be a multiple of 8 between 32 and 4096, got {}", self.size);
        Ok(())
    }
}

/// The numbers of a fit to photos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhotoFitReport {
    pub config: PhotoFitConfig,
    pub photos: usize,
    /// Mean data term (Charbonnier of the log difference) of the start maps and of the fitted ones.
    pub data_before: f64,
    pub data_after: f64,
    /// Mean |ln(1 + R_ggx) - ln(1 + photo)| of the start maps and of the fitted ones.
    pub error_before: f64,
    pub error_after: f64,
    /// Seconds of the fit itself.
    pub seconds: f64,
}

/// What a fit to photos produced (on the CPU).
#[derive(Debug)]
pub struct PhotoFit {
    /// Fitted GGX maps `[10, H, W]` (kd, ks, roughness, unit normal; linear).
    pub maps: Tensor,
    /// Per-pixel error `[H, W]`: mean over photos and RGB of |log difference| (clipped pixels one-sided).
    pub error: Tensor,
    pub report: PhotoFitReport,
}

/// Pixels clipped in 8-bit photos: any channel at or above [`CLIP_LEVEL`].
/// photos: `[K, 3, H, W]` as decoded, before any compensation -> `[K, 1, H, W]` bool.
pub fn clip_mask(photos: &Tensor) -> Tensor {
    photos.ge(CLIP_LEVEL).any_dim(1, true)
}

/// A start knowing nothing but the photo: kd = photo / cos(light) (the
/// diffuse part alone explains the photo), ks 0.04, roughness 0.5, flat
/// normals. photo: `[3, H, W]` linear, fall-off compensated, taken under
/// `config` -> maps `[10, H, W]`.
pub fn flat_start(photo: &Tensor, config: &LightView) -> Tensor {
    let s = photo.size();
    let (h, w) = (s[1], s[2]);
    let opts = (Kind::Float, photo.device());
    let light = Tensor::from_slice(&config.light.map(|c| c as f32)).to_device(photo.device()).view([1, 1, 3]);
    let (wi, _) = direction_maps_for(&light, &light, h as usize, w as usize); // [1, 1, 3, H, W]
    let cos = wi.get(0).get(0).narrow(0, 2, 1).clamp_min(0.1);
    let kd = (photo.to_kind(Kind::Float) / cos).clamp(0.005, 0.95);
    let normal = Tensor::cat(&[Tensor::zeros([2, h, w], opts), Tensor::ones([1, h, w], opts)], 0);
    Tensor::cat(&[kd, Tensor::full([3, h, w], 0.04, opts), Tensor::full([1, h, w], 0.5, opts), normal], 0)
}

/// The start of `estimate --capture`: the loaded model's estimate of the
/// overhead photo, fitted to GGX by `flashmat fit`'s path ([`fit_material`]).
/// photo: `[3, H, W]` linear at the model's view -> maps `[10, H, W]` (CPU).
/// `on_progress(done, total)` as [`fit_material`]'s.
pub fn estimated_start(loaded: &LoadedModel, photo: &Tensor, fit: &FitConfig, on_progress: impl FnMut(usize, usize)) -> Result<Tensor> {
    let image = crate::image::Image::from_tensor(&photo.to_device(Device::Cpu).clamp(0.0, 1.0))?;
    let prepared = PreparedPhoto::at_model_view(image, true, "overhead capture photo");
    let material = crate::infer::estimate(&loaded.model, &loaded.info, &prepared)?;
    Ok(fit_material(&material, fit, on_progress)?.maps)
}

/// Per-element data term and |log difference|: pred, target `[K, 3, H, W]`
/// ln(1 + R); clipped `[K, 1, H, W]`, where only a render below the photo counts.
fn log_differences(pred: &Tensor, target: &Tensor, clipped: &Tensor) -> (Tensor, Tensor) {
    let diff = pred - target;
    let diff = diff.clamp_max(0.0).where_self(clipped, &diff);
    let charbonnier = (diff.square() + CHARBONNIER_EPS * CHARBONNIER_EPS).sqrt() - CHARBONNIER_EPS;
    (charbonnier, diff.abs())
}

/// Fits GGX maps to photos with known lights and cameras.
/// photos: `[K, 3, H, W]` linear, fall-off compensated; clipped: `[K, 1, H, W]`
/// bool ([`clip_mask`]); configs: K lights/cameras (flashmat units); start:
/// `[10, H, W]`. Runs on the photos' device; `on_step(i)` after each step.
pub fn fit_photos(photos: &Tensor, clipped: &Tensor, configs: &[LightView], start: &Tensor, cfg: &PhotoFitConfig, on_step: impl FnMut(usize)) -> Result<PhotoFit> {
    cfg.validate()?;
    let s = photos.size();
    ensure!(s.len() == 4 && s[1] == 3, "photos must be [K, 3, H, W], got {s:?}");
    let (k, h, w) = (s[0], s[2], s[3]);
    ensure!(k >= 1 && configs.len() == k as usize, "{} photos but {} light/camera positions", k, configs.len());
    ensure!(h >= 2 && w >= 2, "the fit needs at least 2x2 pixels, got {w}x{h}");
    ensure!(clipped.size() == [k, 1, h, w], "the clip mask must be [{k}, 1, {h}, {w}], got {:?}", clipped.size());
    ensure!(start.size() == [10, h, w], "the start maps must be [10, {h}, {w}], got {:?}", start.size());
    ensure!(crate::image::all_finite(photos), "the photos hold NaN/Inf values");
    ensure!(crate::image::all_finite(start), "the start maps hold NaN/Inf values");
    let t0 = Instant::now();
    let device = photos.device();
    let target = crate::spaces::to_log(&photos.to_kind(Kind::Float)); // [K, 3, H, W]
    let clipped = clipped.to_device(device).to_kind(Kind::Bool);
    let position = |pick: fn(&LightView) -> [f64; 3]| {
        let flat: Vec<f32> = configs.iter().flat_map(|c| pick(c).map(|v| v as f32)).collect();
        Tensor::from_slice(&flat).to_device(device).view([1, k, 3])
    };
    let (wi, wo) = direction_maps_for(&position(|c| c.light), &position(|c| c.view), h as usize, w as usize); // [1, K, 3, H, W]
    let log_render = |maps: &Tensor| crate::spaces::to_log(&render_directions(maps, &wi, &wo).get(0)); // [K, 3, H, W]

    // The start, as `decode` sees it (clamped into its range).
    let start = tch::no_grad(|| decode(&encode(&start.to_device(device).to_kind(Kind::Float).unsqueeze(0))));
    let factors = Tensor::from_slice(&PULL_FACTORS).to_kind(Kind::Float).to_device(device).view([1, 10, 1, 1]);
    let measure = |maps: &Tensor| {
        tch::no_grad(|| {
            let (data, diff) = log_differences(&log_render(maps), &target, &clipped);
            (data.mean(Kind::Double).double_value(&[]), diff.mean_dim([0i64, 1].as_slice(), false, Kind::Float))
        })
    };
    let (data_before, error_start) = measure(&start);
    let data = |maps: &Tensor| {
        let term = log_differences(&log_render(maps), &target, &clipped).0.mean(Kind::Float);
        if cfg.pull_weight > 0.0 {
            term + ((maps - &start).square() * &factors).sum_dim_intlist([1i64].as_slice(), false, Kind::Float).mean(Kind::Float) * cfg.pull_weight
        } else {
            term
        }
    };
    let edges = edge_weights(&target.mean_dim(0, false, Kind::Float));
    let settings = CoreSettings { steps: cfg.steps, learning_rate: cfg.learning_rate, smooth_weight: cfg.smooth_weight };
    let maps = fit_core(&start, &settings, &edges, data, on_step)?;
    let (data_after, error) = measure(&maps);
    ensure!(crate::image::all_finite(&maps) && data_after.is_finite(), "the fitted maps are not finite");
    let report = PhotoFitReport {
        config: cfg.clone(),
        photos: k as usize,
        data_before,
        data_after,
        error_before: error_start.mean(Kind::Double).double_value(&[]),
        error_after: error.mean(Kind::Double).double_value(&[]),
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok(PhotoFit { maps: maps.get(0).to_device(Device::Cpu), error: error.to_device(Device::Cpu), report })
}

impl PhotoFit {
    /// The fit as `flashmat fit`'s result, for its PBR export
    /// ([`super::export::write_fit`]): the glTF conversion is measured on
    /// `flashmat fit`'s default direction pairs; fit.json records the
    /// steps, step size and smoothness, the mean errors before and after.
    pub fn as_fit_result(&self) -> FitResult {
        let defaults = FitConfig::default();
        let (wi, wo) = sample_directions(defaults.samples, defaults.seed, Device::Cpu);
        let c = &self.report.config;
        let p95 = self.error.flatten(0, -1).quantile_scalar(0.95, None, false, "linear").double_value(&[]);
        let report = FitReport {
            config: FitConfig { steps: c.steps, learning_rate: c.learning_rate, smooth_weight: c.smooth_weight, ..defaults },
            mean_error_init: self.report.error_before,
            mean_error: self.report.error_after,
            p95_error: p95,
            seconds_targets: 0.0,
            seconds_fit: self.report.seconds,
        };
        FitResult { maps: self.maps.shallow_clone(), error: self.error.shallow_clone(), wi, wo, report }
    }
}

/// A neural material of GGX maps: the teacher's encoder gives the codes,
/// its ND_enc + M_render render them, so `.nmat` readers, relight, view
/// and Mitsuba take it as any material (gain 1: the teacher learned GGX's
/// radiance). maps: `[10, H, W]`; photo: `[3, H, W]` (stored as the input photo).
pub fn neural_material(maps: &Tensor, photo: &Tensor, teacher: &TeacherWeights, source: &str) -> Result<NeuralMaterial> {
    let s = maps.size();
    ensure!(s.len() == 3 && s[0] == 10, "GGX maps must be [10, H, W], got {s:?}");
    let device = teacher.vs.device();
    let codes = tch::no_grad(|| teacher.encoder.forward_maps(&valid_values(&maps.to_device(device).to_kind(Kind::Float).unsqueeze(0)))).get(0);
    let (h, w) = (s[1] as usize, s[2] as usize);
    let meta = NmatMeta {
        model_id: teacher.config.model_id(),
        fov_deg: MODEL_FOV_DEG,
        crop: Crop::whole(w, h),
        source: source.to_string(),
        ldr_input: true,
        model_info: ModelInfo { ldr_input: true, steps: 0 },
        refine: None,
        gain: [1.0; 3],
    };
    NeuralMaterial::from_parts(codes, photo.shallow_clone(), &teacher.config, &teacher.renderer, meta)
}

/// The photos of a capture folder ready for [`fit_photos`].
#[derive(Debug)]
pub struct CapturePhotos {
    /// `[K, 3, S, S]` linear, fall-off compensated (on the CPU).
    pub photos: Tensor,
    /// `[K, 1, S, S]` bool: clipped in the 8-bit photo ([`clip_mask`]).
    pub clipped: Tensor,
    pub configs: Vec<LightView>,
    /// Index of the overhead photo ([`Captures::overhead`] among the first K).
    pub overhead: usize,
}

/// Loads the first `count` photos of a capture at `size x size`. Errors
/// (one line, naming the photo): photos of different sizes, a black photo,
/// one clipped everywhere.
pub fn load_capture(captures: &Captures, count: usize, size: usize) -> Result<CapturePhotos> {
    let total = captures.photos.len();
    ensure!((1..=total).contains(&count), "--photos must be between 1 and {total} (the photos in {}), got {count}", captures.dir.display());
    let configs: Vec<LightView> = (0..count).map(|i| captures.config(i)).collect();
    let cameras: Vec<[f64; 3]> = configs.iter().map(|c| c.view).collect();
    let overhead = crate::data::captures::overhead_index(&cameras);
    // Compensated relative to the overhead photo used, as `Captures::load_compensated` does.
    let r0 = crate::geometry::length(configs[overhead].light);
    let mut photos = Vec::with_capacity(count);
    let mut raw = Vec::with_capacity(count);
    let mut first_size = None;
    for (path, c) in captures.photos.iter().zip(&configs) {
        let (photo, dims) = load_photo_sized(path, size)?;
        match first_size {
            None => first_size = Some((dims, path)),
            Some(((w0, h0), p0)) => ensure!(
                dims == (w0, h0),
                "{}: the photo is {}x{} pixels but {} is {w0}x{h0}; a capture's photos must share one size",
                path.display(),
                dims.0,
                dims.1,
                p0.display()
            ),
        }
        let mean = photo.mean(Kind::Double).double_value(&[]);
        ensure!(mean >= BLACK_MEAN, "{}: the photo is black (mean linear value {mean:.1e}); nothing to fit", path.display());
        let clipped = clip_mask(&photo.unsqueeze(0));
        ensure!(
            clipped.logical_not().any().int64_value(&[]) != 0,
            "{}: the photo is white (clipped everywhere); nothing to fit",
            path.display()
        );
        photos.push(&photo / falloff(c.light, r0, size, size));
        raw.push(clipped);
    }
    Ok(CapturePhotos { photos: Tensor::stack(&photos, 0), clipped: Tensor::cat(&raw, 0), configs, overhead })
}

/// The teacher file `explicit`, or the bundled one; a missing file is one line.
pub fn load_teacher(explicit: Option<&Path>, device: Device) -> Result<TeacherWeights> {
    let path = explicit.map(Path::to_path_buf).unwrap_or_else(default_teacher_path);
    ensure!(path.is_file(), "the teacher file {} does not exist (models/MODEL.md: the curriculum's teacher)", path.display());
    TeacherWeights::load(&path, device)
}

#[cfg(test)]
mod tests;
