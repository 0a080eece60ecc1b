//! Several photos, one material (`flashmat estimate --capture DIR`): GGX
//! maps fitted per pixel to all photos of a capture folder
//! ([`crate::data::captures`]) with their known light and camera positions,
//! then a neural material of the fitted maps.
//!
//! ```text
//! overhead photo ─► M_est ─► fit_material ─► start maps ─► lobe by albedo region ─┐
//! photos [K,3,H,W] (fall-off compensated) ────────────────────────────────────────┴─► fit_core ─► maps [10,H,W]
//!   loss = mean charbonnier(ln(1+R_ggx(l_k, v_k)) - ln(1+photo_k))   (clipped channels: only R below the photo)
//!        + smooth (edges of the mean photo) + pull toward the start maps
//!        + the specular tail ks alpha^2 where a photo clipped
//! maps ─► teacher's GgxEncoder ─► neural map; teacher's ND_enc + M_render ─► .nmat
//! ```
//!
//! The Adam loop is `flashmat fit`'s ([`super::fit_core`]); only the data
//! term differs: real point lights and cameras per photo (directions vary
//! over the pixels) instead of shared direction pairs. The pull keeps what
//! the photos do not show: without a highlight in any photo a pixel's
//! roughness and specular level are barely constrained, so there the
//! single-photo estimate holds (the pull weighs them 10x kd's), moved by
//! a shift per albedo region that follows the pixels the highlights moved
//! ([`LobeShift`]). The estimate's lobe enters as its regions' means
//! ([`regional_lobe`]): its texture follows the one photo's highlight.
//!
//! Half the steps run at half the resolution first (coarse to fine); an
//! exposure gain per photo and lobes shared by albedo regions are options
//! (measured in reports/capture.md, off by default). Poses are taken as
//! told: refining them by this fit moved them further off.

use super::codes::{fit_codes, held_out_configs, neural_gap, CodeFit, CodeFitConfig, NeuralGap};
use super::{decode, edge_weights, encode, fit_core, fit_material, region_means, region_mix, sample_directions, with_raw_lobe, CoreSettings, FitConfig, FitReport, FitResult, SharedLobes, CHARBONNIER_EPS, MAX_FIT_STEPS};
use crate::data::captures::{compensated, load_photo_sized, Captures};
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
pub const BUNDLED_TEACHER: &str = "teacher-any-ggx.safetensors";

/// The bundled teacher, in [`crate::infer::models_dir`].
pub fn default_teacher_path() -> PathBuf {
    crate::infer::models_dir().join(BUNDLED_TEACHER)
}

/// An 8-bit photo value at or above this (any channel, before the
/// fall-off compensation) is clipped: the truth may be brighter.
pub const CLIP_LEVEL: f64 = 0.999;

/// A photo whose mean linear value is below this is black (no light).
const BLACK_MEAN: f64 = 1e-4;

/// Stops of a RAW photo's BaselineExposure past which it is warned of: a
/// 12-bit RAW exposed to keep a glossy flash peak (8-11 stops) relit the
/// 50 held-out materials at Identity LPIPS 0.035 against its JPEG twin's
/// 0.018; 4 stops beat the JPEG (reports/capture.md, "Sixteenth slice").
const RAW_HEADROOM_STOPS: f64 = 6.0;

/// Pull factors per map channel (kd 3, ks 3, roughness, normal 3): a
/// specular level and roughness no photo shows stay the start's, while kd
/// and the normal follow the photos' shading.
const PULL_FACTORS: [f64; 10] = [0.1, 0.1, 0.1, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2, 0.2];

/// Maps smaller than this on a side are fitted at full resolution only.
pub const MIN_COARSE_SIDE: i64 = 64;

/// Most regions of [`albedo_regions`].
pub const MAX_LOBE_REGIONS: usize = 8;

/// Width of a region's soft membership in ln(kd) distance (per channel, RMS).
const REGION_WIDTH: f64 = 0.15;

/// Soft regions of an albedo map for [`SharedLobes`]: k-means (10 rounds)
/// on ln(kd) from centres at evenly spaced brightness quantiles, then each
/// pixel's membership exp(-d^2 / (2 * 3 * REGION_WIDTH^2)) normalised over
/// the regions. kd: `[3, H, W]` linear -> `[1, C, H, W]`.
pub fn albedo_regions(kd: &Tensor, count: usize) -> Tensor {
    tch::no_grad(|| {
        let (h, w) = (kd.size()[1], kd.size()[2]);
        let points = kd.to_kind(Kind::Float).clamp_min(1e-3).log().view([3, h * w]).transpose(0, 1); // [P, 3]
        let brightness = points.mean_dim(1, false, Kind::Float);
        let order = brightness.argsort(0, false);
        let n = h * w;
        let picks: Vec<i64> = (0..count as i64).map(|c| ((2 * c + 1) * n / (2 * count as i64)).min(n - 1)).collect();
        let mut centres = points.index_select(0, &order.index_select(0, &Tensor::from_slice(&picks).to_device(kd.device()))); // [C, 3]
        let distances = |centres: &Tensor| (points.unsqueeze(1) - centres.unsqueeze(0)).square().sum_dim_intlist([2i64].as_slice(), false, Kind::Float); // [P, C]
        for _ in 0..10 {
            let nearest = distances(&centres).argmin(1, false).one_hot(count as i64).to_kind(Kind::Float); // [P, C]
            let counts = nearest.sum_dim_intlist([0i64].as_slice(), false, Kind::Float).unsqueeze(1); // [C, 1]
            let means = nearest.transpose(0, 1).matmul(&points) / counts.clamp_min(1.0);
            // An empty region keeps its centre.
            centres = means.where_self(&counts.gt(0.0), &centres);
        }
        let memberships = (-distances(&centres) / (6.0 * REGION_WIDTH * REGION_WIDTH)).softmax(1, Kind::Float); // [P, C]
        memberships.transpose(0, 1).reshape([1, count as i64, h, w])
    })
}

/// Roughness and specular levels of [`searched_lobes`]' grid.
const SEARCH_ROUGHNESS: [f64; 7] = [0.08, 0.12, 0.18, 0.25, 0.35, 0.5, 0.7];
const SEARCH_SPECULAR: [f64; 6] = [0.02, 0.05, 0.12, 0.3, 0.6, 1.0];

/// The start with each region's lobe set to the grid's (roughness, grey
/// specular) pair of lowest data term over the region, where that beats
/// the start's own lobes there. A sharp bright lobe and a broad dim one
/// are far apart for Adam (the way between them draws a broad bright
/// highlight everywhere), while the data term of a whole region tells
/// them apart at once.
/// start: `[1, 10, H, W]`; memberships: `[1, C, H, W]` ([`albedo_regions`]);
/// data_map: maps `[1, 10, H, W]` -> per-pixel data term `[H, W]`.
fn searched_lobes(start: &Tensor, memberships: &Tensor, data_map: impl Fn(&Tensor) -> Tensor) -> Tensor {
    tch::no_grad(|| {
        let m = memberships.get(0); // [C, H, W]
        let weights = m.sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Float).clamp_min(1e-6); // [C]
        let score = |maps: &Tensor| (&m * data_map(maps).unsqueeze(0)).sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Float) / &weights; // [C]
        let mut best = score(start);
        let count = m.size()[0];
        let mut lobes = start.narrow(1, 3, 4).expand([count, 4, -1, -1], false).copy(); // [C, 4, H, W]: each region's lobe map
        let with_lobe = |ks: f64, r: f64| {
            let opts = (Kind::Float, start.device());
            let (h, w) = (start.size()[2], start.size()[3]);
            Tensor::cat(&[start.narrow(1, 0, 3), Tensor::full([1, 3, h, w], ks, opts), Tensor::full([1, 1, h, w], r, opts), start.narrow(1, 7, 3)], 1)
        };
        for &r in &SEARCH_ROUGHNESS {
            for &ks in &SEARCH_SPECULAR {
                let candidate = with_lobe(ks, r);
                let scores = score(&candidate);
                let better = scores.lt_tensor(&best); // [C]
                best = scores.minimum(&best);
                lobes = candidate.narrow(1, 3, 4).expand_as(&lobes).where_self(&better.view([count, 1, 1, 1]), &lobes);
            }
        }
        // Each pixel's lobe: its regions' lobes mixed by its memberships.
        let lobe = (lobes * m.unsqueeze(1)).sum_dim_intlist([0i64].as_slice(), true, Kind::Float); // [1, 4, H, W]
        Tensor::cat(&[start.narrow(1, 0, 3), lobe, start.narrow(1, 7, 3)], 1)
    })
}

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
    /// Regions of the start's albedo whose pixels share a specular lobe
    /// ([`SharedLobes`]), each started from a grid search ([`searched_lobes`]);
    /// 0 (the default) fits every pixel's lobe alone. Measured in
    /// reports/capture.md: 3 regions left the lobe at 0.30-0.36 and cost
    /// identity LPIPS, because an 8-bit photo's clipped highlight does not
    /// say how bright its peak is.
    pub lobe_regions: usize,
    /// Weight of a pixel's squared departure from its regions' lobe.
    pub lobe_weight: f64,
    /// Albedo regions, each with a fitted shift of the pull's lobe
    /// ([`LobeShift`]); 0 pulls toward the start's lobe as it is. Default 3:
    /// on 20 held-out materials at 3 photos, ghost 1.17 -> 1.14 and LPIPS
    /// Reflect 0.153 -> 0.145 against 0, and 0.146 with 1 region.
    #[serde(default)]
    pub lobe_shift_regions: usize,
    /// Weight of the specular tail, mean(ks) x alpha^2 (alpha = roughness^2),
    /// on the pixels clipped in any photo ([`clipped_tail`]); 0 leaves them
    /// to the pull. Default 1: on the 50 held-out materials at 3 photos,
    /// the ghost 1.23 -> 1.19 for a little relit LPIPS (Reflect 0.152 ->
    /// 0.154; reports/capture.md, "Sixth slice").
    #[serde(default)]
    pub clipped_tail_weight: f64,
    /// Weight of the smoothness of the normals on the pixels clipped in any
    /// photo ([`clipped_normal_roughness`]). Default 0.03: on the 50 held-out
    /// materials at 3 photos, the worst material's clipped normals 1.81x ->
    /// 1.26x its error elsewhere, and every relit LPIPS column better
    /// (reports/capture.md, "Fifteenth slice"). Older fit files carry none (0).
    #[serde(default)]
    pub clipped_normal_smooth_weight: f64,
    /// Replace the start's specular lobe (raw ks and roughness) by its
    /// albedo regions' means (the [`LobeShift`]'s regions, or one region
    /// without a shift) before the fit ([`regional_lobe`]). M_est's lobe
    /// from one photo is brightest where that photo's highlight was, and
    /// the pull would keep that texture. Default on: on the 50 held-out
    /// materials at 3 photos, ghost 1.19 -> 1.14 and LPIPS Reflect 0.154
    /// -> 0.148 (reports/capture.md, "Seventh slice").
    #[serde(default)]
    pub regional_start_lobe: bool,
    /// Fit an exposure gain per photo besides the maps (the overhead
    /// photo's held at 1): photos taken with auto exposure. The diffuse
    /// shading every photo shares fixes each one's gain.
    pub photo_gains: bool,
    /// Share of the steps run at half the resolution first ([`fit_photos`];
    /// 0 fits at full resolution throughout; maps under [`MIN_COARSE_SIDE`] always do).
    pub coarse_share: f64,
    /// How the neural material's codes are fitted to the fitted maps
    /// ([`super::codes`]). Older fit files carry none: their codes were
    /// the teacher's as they are (0 steps).
    #[serde(default = "CodeFitConfig::none")]
    pub code_fit: CodeFitConfig,
}

impl Default for PhotoFitConfig {
    fn default() -> Self {
        Self { steps: 600, learning_rate: 0.05, smooth_weight: 0.01, pull_weight: 0.05, size: 256, lobe_regions: 0, lobe_weight: 0.01, lobe_shift_regions: 3, clipped_tail_weight: 1.0, clipped_normal_smooth_weight: 0.03, regional_start_lobe: true, photo_gains: false, coarse_share: 0.5, code_fit: CodeFitConfig::default() }
    }
}


impl PhotoFitConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!((1..=MAX_FIT_STEPS).contains(&self.steps), "--steps must be between 1 and {MAX_FIT_STEPS}, got {}", self.steps);
        ensure!(self.learning_rate.is_finite() && self.learning_rate > 0.0, "the fit's learning rate must be a finite number > 0, got {}", self.learning_rate);
        ensure!(self.smooth_weight.is_finite() && self.smooth_weight >= 0.0, "the smoothness weight must be a finite number >= 0, got {}", self.smooth_weight);
        ensure!(self.pull_weight.is_finite() && self.pull_weight >= 0.0, "the pull weight must be a finite number >= 0, got {}", self.pull_weight);
        ensure!((0.0..1.0).contains(&self.coarse_share), "the coarse share must be in [0, 1), got {}", self.coarse_share);
        ensure!(self.lobe_regions <= MAX_LOBE_REGIONS, "at most {MAX_LOBE_REGIONS} lobe regions, got {}", self.lobe_regions);
        ensure!(self.lobe_shift_regions <= MAX_LOBE_REGIONS, "at most {MAX_LOBE_REGIONS} lobe shift regions, got {}", self.lobe_shift_regions);
        ensure!(self.clipped_tail_weight.is_finite() && self.clipped_tail_weight >= 0.0, "the clipped tail weight must be a finite number >= 0, got {}", self.clipped_tail_weight);
        ensure!(self.clipped_normal_smooth_weight.is_finite() && self.clipped_normal_smooth_weight >= 0.0, "the clipped normals' smoothness weight must be a finite number >= 0, got {}", self.clipped_normal_smooth_weight);
        ensure!(self.lobe_weight.is_finite() && self.lobe_weight >= 0.0, "the lobe weight must be a finite number >= 0, got {}", self.lobe_weight);
        ensure!(self.size >= 32 && self.size.is_multiple_of(8) && self.size <= 4096, "--size must be a multiple of 8 between 32 and 4096, got {}", self.size);
        self.code_fit.validate()
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
    /// Mean |log difference| of the fitted maps per photo (in the photos' order).
    pub photo_errors: Vec<f64>,
    /// Each photo's fitted exposure gain relative to the overhead photo (all 1 without [`PhotoFitConfig::photo_gains`]).
    pub photo_gains: Vec<f64>,
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

/// Channels clipped in 8-bit photos: at or above [`CLIP_LEVEL`]. Per
/// channel: a teal highlight that clipped green and blue still measures
/// its red, which keeps the fitted colour (reports/capture.md, "Ninth slice").
/// photos: `[K, 3, H, W]` as decoded, before any compensation -> `[K, 3, H, W]` bool.
pub fn clip_mask(photos: &Tensor) -> Tensor {
    photos.ge(CLIP_LEVEL)
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
/// ln(1 + R); clipped `[K, 3, H, W]`, where only a render below the photo counts.
fn log_differences(pred: &Tensor, target: &Tensor, clipped: &Tensor) -> (Tensor, Tensor) {
    let diff = pred - target;
    let diff = diff.clamp_max(0.0).where_self(clipped, &diff);
    let charbonnier = (diff.square() + CHARBONNIER_EPS * CHARBONNIER_EPS).sqrt() - CHARBONNIER_EPS;
    (charbonnier, diff.abs())
}

/// The prior on pixels clipped in a photo: mean over the pixels of
/// mean(ks) x alpha^2 (alpha = roughness^2) where `clipped_any` (`[1, 1, H, W]`,
/// 1 where any photo clipped). maps: `[1, 10, H, W]` -> scalar.
///
/// A clipped pixel says only that its highlight reaches the 8-bit ceiling,
/// and every lobe with ks / alpha^2 high enough does. Left to the pull, it
/// keeps the start's broad lobe and raises ks until it reaches the ceiling;
/// that lobe's tail, ks alpha^2, then draws the photographed highlight
/// again under other lights (the ghost). Of the lobes that reach the
/// ceiling, the sharpest has the least tail. The gradient falls with
/// alpha^3, so a lobe already sharp is barely pushed further.
fn clipped_tail(maps: &Tensor, clipped_any: &Tensor) -> Tensor {
    let ks = maps.narrow(1, 3, 3).mean_dim([1i64].as_slice(), true, Kind::Float);
    let alpha2 = maps.narrow(1, 6, 1).pow_tensor_scalar(4);
    (ks * alpha2 * clipped_any).mean(Kind::Float)
}

/// Mean absolute difference of neighbouring normals (maps `[1, 10, H, W]`),
/// summed over x, y and z, on the pairs of pixels either of which a photo
/// clipped (`clipped_any`: `[1, 1, H, W]` float), over all pixels. A
/// clipped pixel bounds its normal from one side only; without this, the
/// photos left to it bend each pixel's normal alone, which relights as
/// speckle where a highlight clipped (reports/capture.md, "Fifteenth slice").
fn clipped_normal_roughness(maps: &Tensor, clipped_any: &Tensor) -> Tensor {
    let (dx, dy) = super::differences(&maps.get(0).narrow(0, 7, 3)); // [3, H, W-1], [3, H-1, W]
    let clipped = clipped_any.get(0); // [1, H, W]
    let (h, w) = (clipped.size()[1], clipped.size()[2]);
    let pairs_x = clipped.narrow(2, 1, w - 1).maximum(&clipped.narrow(2, 0, w - 1));
    let pairs_y = clipped.narrow(1, 1, h - 1).maximum(&clipped.narrow(1, 0, h - 1));
    ((dx.abs() * pairs_x).sum(Kind::Float) + (dy.abs() * pairs_y).sum(Kind::Float)) / (h * w) as f64
}

/// Maps `[1, 10, H, W]` whose specular lobe (raw ks and roughness, as the
/// fit parametrises them) is each pixel's mix, by its memberships
/// `[1, C, H, W]`, of the regions' mean lobes; kd and the normals as they were.
///
/// The single-photo estimate draws its lobe where its photo showed the
/// highlight (its ghost), so its lobe's texture follows that photo's
/// highlight rather than the material. Its regions' means keep its level
/// and drop that texture; the photos' highlights then draw the lobe's
/// texture where they see it (reports/capture.md, "Seventh slice").
fn regional_lobe(maps: &Tensor, memberships: &Tensor) -> Tensor {
    tch::no_grad(|| {
        let raw = encode(maps);
        let (first, count) = super::LOBE_CHANNELS;
        let means = region_means(memberships, &raw.narrow(1, first, count)); // [C, 4]
        decode(&with_raw_lobe(&raw, &region_mix(memberships, &means)))
    })
}

/// The photos at one resolution of the fit.
struct Level {
    /// ln(1 + photo) `[K, 3, H, W]`.
    target: Tensor,
    /// `[K, 3, H, W]` bool.
    clipped: Tensor,
    /// `[1, 1, H, W]` float: 1 where any photo clipped a channel.
    clipped_any: Tensor,
}

impl Level {
    fn new(photos: &Tensor, clipped: &Tensor) -> Self {
        let clipped = clipped.to_device(photos.device()).to_kind(Kind::Bool);
        let clipped_any = clipped.any_dim(0, true).any_dim(1, true).to_kind(Kind::Float);
        Level { target: crate::spaces::to_log(&photos.to_kind(Kind::Float)), clipped, clipped_any }
    }

    /// The level at half the resolution: photos averaged over 2x2 pixels,
    /// a channel clipped where any of its four pixels' was.
    fn halved(photos: &Tensor, clipped: &Tensor) -> Self {
        let photos = average_2x2(&photos.to_kind(Kind::Float));
        let clipped = clipped.to_kind(Kind::Float).max_pool2d([2, 2], [2, 2], [0, 0], [1, 1], false).gt(0.5);
        Self::new(&photos, &clipped)
    }

    /// The renders of maps `[1, 10, H, W]` as the photos took them: `[K, 3, H, W]`.
    fn render(&self, maps: &Tensor, photo: &PhotoParams) -> Tensor {
        let s = self.target.size();
        let (wi, wo) = direction_maps_for(&photo.lights, &photo.views, s[2] as usize, s[3] as usize);
        render_directions(maps, &wi, &wo).get(0) * photo.gains().view([-1, 1, 1, 1])
    }

    /// Per-element data term and |log difference| of maps `[1, 10, H, W]`: `[K, 3, H, W]` each.
    fn differences(&self, maps: &Tensor, photo: &PhotoParams) -> (Tensor, Tensor) {
        log_differences(&crate::spaces::to_log(&self.render(maps, photo)), &self.target, &self.clipped)
    }

    /// `steps` of the fit from `init` with the pull toward `start` (both
    /// `[1, 10, H, W]`); the photos' gains fitted in place with `cfg.photo_gains`.
    /// With `shift`, the pull's lobe is the start's moved by its regions' fitted shifts.
    fn fit(&self, init: &Tensor, start: &Tensor, context: LevelContext, steps: usize, on_step: impl FnMut(usize)) -> Result<Tensor> {
        let LevelContext { photo, shift, cfg } = context;
        let factors = Tensor::from_slice(&PULL_FACTORS).to_kind(Kind::Float).to_device(start.device()).view([1, 10, 1, 1]);
        let memberships = (cfg.lobe_regions > 0).then(|| albedo_regions(&start.get(0).narrow(0, 0, 3), cfg.lobe_regions));
        let (init, start) = match &memberships {
            Some(m) => {
                let searched = searched_lobes(init, m, |maps| tch::no_grad(|| self.differences(maps, photo).0.mean_dim([0i64, 1].as_slice(), false, Kind::Float)));
                (searched.shallow_clone(), searched)
            }
            None => (init.shallow_clone(), start.shallow_clone()),
        };
        let start_raw = encode(&start);
        // The shift with its memberships at this level's side.
        let shift_here = shift.map(|s| (s, s.memberships_at(self.target.size()[2])));
        let data = |maps: &Tensor| {
            let mut loss = self.differences(maps, photo).0.mean(Kind::Float);
            if cfg.clipped_tail_weight > 0.0 {
                loss = loss + clipped_tail(maps, &self.clipped_any) * cfg.clipped_tail_weight;
            }
            if cfg.clipped_normal_smooth_weight > 0.0 {
                loss = loss + clipped_normal_roughness(maps, &self.clipped_any) * cfg.clipped_normal_smooth_weight;
            }
            if cfg.pull_weight > 0.0 {
                let target = match &shift_here {
                    Some((shift, m)) => shift.shifted(&start_raw, m),
                    None => start.shallow_clone(),
                };
                loss = loss + ((maps - &target).square() * &factors).sum_dim_intlist([1i64].as_slice(), false, Kind::Float).mean(Kind::Float) * cfg.pull_weight;
            }
            loss
        };
        let edges = edge_weights(&self.target.mean_dim(0, false, Kind::Float));
        let settings = CoreSettings { steps, learning_rate: cfg.learning_rate, smooth_weight: cfg.smooth_weight };
        let shared = memberships.map(|memberships| SharedLobes { memberships, weight: cfg.lobe_weight });
        let mut extra: Vec<(&str, &Tensor)> = Vec::new();
        if cfg.photo_gains {
            extra.push(("log_gains", &photo.log_gains));
        }
        if let Some(shift) = shift {
            extra.push(("lobe_shift", &shift.values));
        }
        fit_core(&init, &settings, &edges, shared.as_ref(), &extra, data, on_step)
    }
}

/// What the fits of every level share: the photos' positions and gains,
/// the lobe shift, the settings.
#[derive(Clone, Copy)]
struct LevelContext<'a> {
    photo: &'a PhotoParams,
    shift: Option<&'a LobeShift>,
    cfg: &'a PhotoFitConfig,
}

/// A shift of the pull's lobe per albedo region, fitted with the maps. The
/// photos move a pixel's lobe only where they show its highlight, and
/// there they say how far the start's lobe is off (M_est's from one photo
/// is dimmer and broader than the truth on glossy materials). The pull's
/// gradient moves each region's shift toward its pixels' mean departure
/// from the start, so the pixels no highlight touched follow the ones the
/// photos moved instead of staying at the start's lobe, and keep the
/// start's texture (reports/capture.md, "Fifth slice").
struct LobeShift {
    /// Soft memberships `[1, C, H, W]` at full resolution ([`albedo_regions`]).
    memberships: Tensor,
    /// Raw shifts of ks (3) and roughness per region `[C, 4]`, a leaf requiring grad.
    values: Tensor,
}

impl LobeShift {
    /// memberships: `[1, C, H, W]` ([`albedo_regions`] of the start's kd).
    fn new(memberships: Tensor) -> Self {
        let values = Tensor::zeros([memberships.size()[1], 4], (Kind::Float, memberships.device())).set_requires_grad(true);
        LobeShift { memberships, values }
    }

    /// The memberships averaged down to side `h` (a level of the fit): `[1, C, h, w]`.
    fn memberships_at(&self, h: i64) -> Tensor {
        let mut m = self.memberships.shallow_clone();
        while m.size()[2] > h {
            m = average_2x2(&m);
        }
        m
    }

    /// The maps of raw start `[1, 9, h, w]` with each pixel's lobe shifted
    /// by its regions' under memberships `[1, C, h, w]`: `[1, 10, h, w]`.
    fn shifted(&self, start_raw: &Tensor, memberships: &Tensor) -> Tensor {
        let (first, count) = super::LOBE_CHANNELS;
        decode(&with_raw_lobe(start_raw, &(start_raw.narrow(1, first, count) + region_mix(memberships, &self.values))))
    }
}

/// Scale of the fitted log gains' parameter: Adam moves every parameter
/// by about its step, and a photo's gain, which all its pixels inform,
/// wants a tenth of a pixel's step.
const PHOTO_STEP: f64 = 0.1;

/// What the fit knows and learns of each photo: its positions and its
/// exposure gain (relative to the overhead photo's, which is held).
struct PhotoParams {
    /// Told positions `[1, K, 3]`.
    lights: Tensor,
    views: Tensor,
    /// Log gains / [`PHOTO_STEP`] `[K]`, a leaf requiring grad.
    log_gains: Tensor,
    /// `[K]` bool: the overhead photo, whose gain is 1.
    fixed: Tensor,
}

impl PhotoParams {
    fn new(configs: &[LightView], overhead: usize, device: Device) -> Self {
        let k = configs.len() as i64;
        let (lights, views) = crate::geometry::config_tensors(configs, device);
        PhotoParams {
            lights: lights.unsqueeze(0),
            views: views.unsqueeze(0),
            log_gains: Tensor::zeros([k], (Kind::Float, device)).set_requires_grad(true),
            fixed: Tensor::arange(k, (Kind::Int64, device)).eq(overhead as i64),
        }
    }

    /// Exposure gains `[K]` (1 for the overhead photo).
    fn gains(&self) -> Tensor {
        (&self.log_gains * PHOTO_STEP).where_self(&self.fixed.logical_not(), &self.log_gains.zeros_like()).exp()
    }
}

/// First guess of the photos' log gains `[K]`: per photo, the median of
/// ln(photo / render of the start) over the pixels both show above
/// 0.01 and unclipped, less the overhead photo's. photos: `[K, 3, H, W]`
/// linear; start: `[1, 10, H, W]`.
fn start_log_gains(photos: &Tensor, level: &Level, start: &Tensor, photo: &PhotoParams, overhead: usize) -> Tensor {
    let render = level.render(start, photo); // [K, 3, H, W]
    let photos = photos.to_kind(Kind::Float);
    let usable = photos.gt(0.01).logical_and(&render.gt(0.01)).logical_and(&level.clipped.logical_not());
    let ratio = (&photos / render.clamp_min(1e-6)).log();
    let k = photos.size()[0];
    let medians: Vec<f32> = (0..k)
        .map(|i| {
            let values = ratio.get(i).masked_select(&usable.get(i));
            if values.numel() == 0 { 0.0 } else { values.median().double_value(&[]) as f32 }
        })
        .collect();
    let medians = Tensor::from_slice(&medians).to_device(photos.device());
    &medians - medians.get(overhead as i64)
}

/// Unit normals again after resampling maps `[1, 10, H, W]`.
fn renormalised(maps: &Tensor) -> Tensor {
    Tensor::cat(&[maps.narrow(1, 0, 7), crate::geometry::normalize_channels(&maps.narrow(1, 7, 3))], 1)
}

/// Maps `[1, 10, H, W]` whose pixels under `clipped` (`[1, 1, H, W]` bool,
/// where the start's photo clipped) are filled from their unclipped
/// neighbours, ring by ring (each pass the 3x3 mean of the pixels known so
/// far); all of them when nothing is known.
///
/// A start read from a clipped photo (the flat start's kd = photo / cos,
/// or M_est's estimate of it) paints the clipped highlight into kd and
/// ks as a flat, saturated patch. Kept, the fit then explains the other
/// photos' dark view of that patch by bending its normals away from their
/// lights (reports/capture.md, "Ninth slice"). The neighbours' material is
/// the better guess; the photos that saw the pixel unclipped correct it.
fn filled_where_clipped(maps: &Tensor, clipped: &Tensor) -> Tensor {
    let s = maps.size();
    // The clip's shoulder, where the highlight is still most of the photo, too.
    let r = (s[2].min(s[3]) / 32).max(1);
    let clipped = clipped.to_kind(Kind::Float).max_pool2d([2 * r + 1, 2 * r + 1], [1, 1], [r, r], [1, 1], false);
    let mut known = clipped.neg() + 1.0;
    if known.sum(Kind::Double).double_value(&[]) == 0.0 {
        return maps.shallow_clone();
    }
    let mut maps = maps * &known;
    for _ in 0..(s[2] + s[3]) {
        if known.min().double_value(&[]) > 0.0 {
            break;
        }
        let pool = |t: &Tensor| t.avg_pool2d([3, 3], [1, 1], [1, 1], false, false, None::<i64>);
        let (sum, count) = (pool(&maps), pool(&known));
        let fill = count.gt(0.0).logical_and(&known.eq(0.0)).to_kind(Kind::Float);
        maps = &maps + &fill * (sum / count.clamp_min(1e-12));
        known = &known + &fill;
    }
    renormalised(&maps)
}

/// `[N, C, H, W]` averaged over 2x2 pixels: the coarse level's pixels.
fn average_2x2(t: &Tensor) -> Tensor {
    t.avg_pool2d([2, 2], [2, 2], [0, 0], false, true, None::<i64>)
}

/// Maps `[1, 10, H, W]` averaged over 2x2 pixels.
fn halved_maps(maps: &Tensor) -> Tensor {
    renormalised(&average_2x2(maps))
}

/// Fits GGX maps to photos with known lights and cameras.
/// photos: `[K, 3, H, W]` linear, fall-off compensated; clipped: `[K, 3, H, W]`
/// bool ([`clip_mask`]); configs: K lights/cameras (flashmat units); start:
/// `[10, H, W]`. Runs on the photos' device; `on_step(i)` after each step.
///
/// Coarse to fine: the first [`PhotoFitConfig::coarse_share`] of the steps
/// run at half the resolution (a quarter of the cost per step), where the
/// lobes and the low frequencies settle; their change to the (halved)
/// start is then upsampled onto the full-resolution start, which keeps its
/// fine detail, and the remaining steps refine every pixel.
pub fn fit_photos(photos: &Tensor, clipped: &Tensor, configs: &[LightView], start: &Tensor, cfg: &PhotoFitConfig, mut on_step: impl FnMut(usize)) -> Result<PhotoFit> {
    cfg.validate()?;
    let s = photos.size();
    ensure!(s.len() == 4 && s[1] == 3, "photos must be [K, 3, H, W], got {s:?}");
    let (k, h, w) = (s[0], s[2], s[3]);
    ensure!(k >= 1 && configs.len() == k as usize, "{} photos but {} light/camera positions", k, configs.len());
    ensure!(h >= 2 && w >= 2, "the fit needs at least 2x2 pixels, got {w}x{h}");
    ensure!(clipped.size() == [k, 3, h, w], "the clip mask must be [{k}, 3, {h}, {w}], got {:?}", clipped.size());
    ensure!(start.size() == [10, h, w], "the start maps must be [10, {h}, {w}], got {:?}", start.size());
    ensure!(crate::image::all_finite(photos), "the photos hold NaN/Inf values");
    ensure!(crate::image::all_finite(start), "the start maps hold NaN/Inf values");
    let t0 = Instant::now();
    let device = photos.device();
    let full = Level::new(photos, clipped);
    // The start, as `decode` sees it (clamped into its range).
    let start = tch::no_grad(|| decode(&encode(&start.to_device(device).to_kind(Kind::Float).unsqueeze(0))));
    let overhead = crate::data::captures::overhead_index(&configs.iter().map(|c| c.view).collect::<Vec<_>>());
    let photo = PhotoParams::new(configs, overhead, device);
    let start = tch::no_grad(|| filled_where_clipped(&start, &clipped.to_device(device).get(overhead as i64).any_dim(0, true).unsqueeze(0)));
    let measure = |maps: &Tensor| {
        tch::no_grad(|| {
            let (data, diff) = full.differences(maps, &photo);
            (data.mean(Kind::Double).double_value(&[]), diff.mean_dim([1i64].as_slice(), false, Kind::Float))
        })
    };
    let (data_before, error_start) = measure(&start);
    // Regions of the start's albedo: the shift's, and the start lobe's means.
    let use_shift = cfg.lobe_shift_regions > 0 && cfg.pull_weight > 0.0; // without a pull there is nothing to shift
    let memberships = (use_shift || cfg.regional_start_lobe).then(|| albedo_regions(&start.get(0).narrow(0, 0, 3), cfg.lobe_shift_regions.max(1)));
    let start = match (&memberships, cfg.regional_start_lobe) {
        (Some(m), true) => regional_lobe(&start, m),
        _ => start,
    };
    if cfg.photo_gains {
        let guess = tch::no_grad(|| start_log_gains(photos, &full, &start, &photo, overhead) / PHOTO_STEP);
        let mut gains = photo.log_gains.shallow_clone();
        tch::no_grad(|| gains.copy_(&guess));
    }
    let coarse_steps = if h >= MIN_COARSE_SIDE && w >= MIN_COARSE_SIDE && h % 2 == 0 && w % 2 == 0 { (cfg.steps as f64 * cfg.coarse_share).round() as usize } else { 0 };
    let shift = memberships.filter(|_| use_shift).map(LobeShift::new);
    let context = LevelContext { photo: &photo, shift: shift.as_ref(), cfg };
    let init = if coarse_steps > 0 {
        let half_start = tch::no_grad(|| halved_maps(&start));
        let coarse = Level::halved(photos, clipped).fit(&half_start, &half_start, context, coarse_steps, &mut on_step)?;
        tch::no_grad(|| {
            let change = (coarse - &half_start).upsample_bilinear2d([h, w], false, None, None);
            decode(&encode(&renormalised(&(&start + change))))
        })
    } else {
        start.shallow_clone()
    };
    let maps = full.fit(&init, &start, context, cfg.steps - coarse_steps, |step| on_step(coarse_steps + step))?;
    let (data_after, photo_error) = measure(&maps); // [K, H, W]
    let photo_errors = Vec::<f64>::try_from(photo_error.mean_dim([1i64, 2].as_slice(), false, Kind::Double))?;
    let error = photo_error.mean_dim(0, false, Kind::Float);
    ensure!(crate::image::all_finite(&maps) && data_after.is_finite(), "the fitted maps are not finite");
    let report = PhotoFitReport {
        config: cfg.clone(),
        photos: k as usize,
        data_before,
        data_after,
        error_before: error_start.mean(Kind::Double).double_value(&[]),
        error_after: error.mean(Kind::Double).double_value(&[]),
        photo_errors,
        photo_gains: Vec::<f64>::try_from(tch::no_grad(|| photo.gains()).to_kind(Kind::Double))?,
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

/// [`neural_material`] with its codes then fitted to what the maps render
/// ([`fit_codes`], under directions around the photos' `configs`), kept
/// where that lowered the fit's check loss (else the teacher's codes stay,
/// and [`CodeFit::kept`] says so). maps: `[10, H, W]`; photo: `[3, H, W]`.
pub fn fitted_neural_material(maps: &Tensor, photo: &Tensor, teacher: &TeacherWeights, configs: &[LightView], cfg: &CodeFitConfig, source: &str) -> Result<(NeuralMaterial, CodeFit)> {
    let mut material = neural_material(maps, photo, teacher, source)?;
    let fit = fit_codes(&mut material, maps, &teacher.encoder, configs, cfg)?;
    Ok((material, fit))
}

/// The photos of a capture folder ready for [`fit_photos`].
#[derive(Debug)]
pub struct CapturePhotos {
    /// `[K, 3, S, S]` linear, fall-off compensated (on the CPU).
    pub photos: Tensor,
    /// `[K, 3, S, S]` bool: clipped in the 8-bit photo ([`clip_mask`]); in a
    /// RAW photo, above the white of its 8-bit rendering (the value times
    /// its BaselineExposure gain at or above [`CLIP_LEVEL`]): a bound, not a
    /// measure, for the fit either way.
    pub clipped: Tensor,
    pub configs: Vec<LightView>,
    /// Index of the overhead photo ([`Captures::overhead`] among these).
    pub overhead: usize,
    /// File names of the photos, as the folder has them.
    pub names: Vec<String>,
    /// Warnings naming a photo (one line each): what the fit will not
    /// learn from it ([`highlight_point`] off the sample).
    pub warnings: Vec<String>,
}

/// Where a flat sample mirrors the light into the camera (z = 0): the
/// highlight's centre, in the sample's units ([-1, 1] is on the sample).
/// The mirror image of the light below the plane, seen from the camera,
/// crosses the plane there.
pub fn highlight_point(config: &LightView) -> [f64; 2] {
    let (l, v) = (config.light, config.view);
    let t = v[2] / (v[2] + l[2]);
    [v[0] + t * (l[0] - v[0]), v[1] + t * (l[1] - v[1])]
}

/// Loads the first `count` photos of a capture at `size x size`
/// ([`load_capture_photos`]).
pub fn load_capture(captures: &Captures, count: usize, size: usize) -> Result<CapturePhotos> {
    let total = captures.photos.len();
    ensure!((1..=total).contains(&count), "--photos must be between 1 and {total} (the photos in {}), got {count}", captures.dir.display());
    load_capture_photos(captures, &(0..count).collect::<Vec<_>>(), size)
}

/// Loads the photos `indices` of a capture at `size x size`, compensated
/// for the fall-off relative to the most overhead of them and brought to
/// its exposure ([`Captures::exposures`]). Errors (one
/// line, naming the photo): photos of different sizes, a black photo, one
/// clipped everywhere, a grey one among colour ones, one with something
/// over part of the sample ([`super::coverage`]). A photo whose highlight falls off the sample is a
/// warning in [`CapturePhotos::warnings`].
pub fn load_capture_photos(captures: &Captures, indices: &[usize], size: usize) -> Result<CapturePhotos> {
    ensure!(!indices.is_empty(), "a fit needs at least one photo");
    ensure!(indices.iter().all(|&i| i < captures.photos.len()), "photo indices {indices:?} out of the {} photos", captures.photos.len());
    let configs: Vec<LightView> = indices.iter().map(|&i| captures.config(i)).collect();
    let cameras: Vec<[f64; 3]> = configs.iter().map(|c| c.view).collect();
    let overhead = crate::data::captures::overhead_index(&cameras);
    // Compensated relative to the overhead photo used, as `Captures::load_compensated` does.
    let r0 = crate::geometry::length(configs[overhead].light);
    let mut photos = Vec::with_capacity(indices.len());
    let mut raw = Vec::with_capacity(indices.len());
    let mut names = Vec::with_capacity(indices.len());
    let mut warnings = Vec::new();
    let mut first_size = None;
    // (index, photo as decoded) of the photos before this one.
    let mut decoded: Vec<(usize, Tensor)> = Vec::with_capacity(indices.len());
    for (&i, c) in indices.iter().zip(&configs) {
        let path = &captures.photos[i];
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
        // A RAW photo at its camera's exposure: one with 8 stops of
        // headroom for a flash peak reads near 0 as decoded.
        let mean = photo.mean(Kind::Double).double_value(&[]) * captures.raw_gains[i];
        ensure!(mean >= BLACK_MEAN, "{}: the photo is black (mean linear value {mean:.1e}); nothing to fit", path.display());
        let clipped = clip_mask(&photo.unsqueeze(0));
        // What the fit takes as "at least this bright": for a RAW photo,
        // what its 8-bit rendering at the file's own exposure would clip.
        // Taken as measured, those peaks made the relit material worse, not
        // better: the fit's lobe cannot draw them, and it bends normals and
        // kd toward them (relit log error 0.0733 against its 8-bit twin's
        // 0.0699; as bounds 0.0701; reports/capture.md, "Thirteenth slice").
        let beyond_white = clip_mask(&(photo.unsqueeze(0) * captures.raw_gains[i]));
        ensure!(
            clipped.logical_not().any().int64_value(&[]) != 0,
            "{}: the photo is white (clipped everywhere); nothing to fit",
            path.display()
        );
        let clipped_share = clipped.any_dim(1, false).to_kind(Kind::Float).mean(Kind::Double).double_value(&[]);
        ensure!(
            clipped_share < MOSTLY_CLIPPED,
            "{}: {:.0}% of the photo's pixels are clipped (white in a channel); take it again at a lower exposure, or leave it out",
            path.display(),
            100.0 * clipped_share
        );
        let [x, y] = highlight_point(c);
        if x.abs() > 1.0 || y.abs() > 1.0 {
            warnings.push(format!(
                "{}: the flash's reflection falls off the sample (at {x:.2}, {y:.2}; the sample spans -1 to 1), so this photo shows no highlight: it tells the fit the diffuse colour only",
                path.display()
            ));
        }
        let headroom_stops = captures.raw_gains[i].log2();
        if headroom_stops > RAW_HEADROOM_STOPS {
            warnings.push(format!(
                "{}: the RAW photo keeps {headroom_stops:.1} stops above the material's white (BaselineExposure), so the material has few of the sensor's levels and its shadows fit worse; the fit reads a clipped flash reflection as a bound, so next time expose for the material and let the reflection clip",
                path.display()
            ));
        }
        check_distinct(&decoded, &photo, i, captures, &configs[..decoded.len()], c)?;
        // Brought to the overhead photo's exposure; the clipped mask stays the photo's own.
        photos.push(compensated(&photo, c.light, r0, captures.exposure_factor(i, indices[overhead])));
        decoded.push((i, photo));
        raw.push(beyond_white);
        names.push(path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
    }
    // On the photos brought to one exposure and white balance: a grey
    // material shot with a white-balance cast in one photo is still grey.
    let balanced: Vec<(usize, Tensor)> = decoded.iter().zip(&photos).map(|((i, _), p)| (*i, p.shallow_clone())).collect();
    check_colour(&balanced, captures)?;
    let openings: Vec<Vec<f32>> = decoded.iter().map(|(_, p)| Vec::<f32>::try_from(p.to_kind(Kind::Float).flatten(0, -1))).collect::<Result<_, _>>()?;
    let highlights: Vec<Option<[f64; 2]>> = decoded.iter().map(|(i, _)| Some(highlight_point(&captures.config(*i)))).collect();
    if let Some(covered) = super::coverage::covered_photo(&openings, size, &highlights) {
        let photo = &captures.photos[decoded[covered.photo].0];
        return Err(super::coverage::covered_error(&photo.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(), &covered));
    }
    Ok(CapturePhotos { photos: Tensor::stack(&photos, 0), clipped: Tensor::cat(&raw, 0), configs, overhead, names, warnings })
}

/// A photo with at least this share of its pixels clipped is refused: it
/// tells the fit almost nothing but "brighter than white".
const MOSTLY_CLIPPED: f64 = 0.9;

/// Photos whose mean |difference| display-encoded
/// ([`crate::spaces::linear_to_display`]) is below this are the same photo: about 0.4 of an 8-bit step,
/// what re-encoding a photo changes. Display-encoded, so that two dark
/// photos of a dark metal from two places (linear values near 0.01,
/// differing by 5e-4) are not taken for one.
const SAME_PHOTO: f64 = 1.5e-3;

/// Positions (flashmat units, light and camera) closer than this are the same.
const SAME_POSITION: f64 = 1e-4;

/// Refuses a photo `photo` (`[3, S, S]` as decoded, capture index `i`,
/// taken at `config`) that repeats one of `earlier` (index, photo), whose
/// positions are `earlier_configs`: the same picture at two different
/// positions (a photo copied, or a list of positions off by one), or two
/// pictures at one position and one exposure (a line copied in the
/// position files). One position at two exposures is bracketing, and fine.
fn check_distinct(earlier: &[(usize, Tensor)], photo: &Tensor, i: usize, captures: &Captures, earlier_configs: &[LightView], config: &LightView) -> Result<()> {
    let name = |j: usize| captures.photos[j].file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let apart = |a: &LightView, b: &LightView| crate::geometry::length(crate::geometry::sub(a.light, b.light)).max(crate::geometry::length(crate::geometry::sub(a.view, b.view)));
    for ((j, other), other_config) in earlier.iter().zip(earlier_configs) {
        let same_position = apart(config, other_config) < SAME_POSITION;
        // At the cameras' exposures: two RAW photos with 10 stops of
        // headroom differ by a few codes as decoded, and are not one photo.
        let display = |p: &Tensor, k: usize| crate::spaces::linear_to_display(&(p * captures.raw_gains[k]));
        let difference = (display(photo, i) - display(other, *j)).abs().mean(Kind::Double).double_value(&[]);
        ensure!(
            difference >= SAME_PHOTO || same_position,
            "{}: the same photo as {} (mean difference {difference:.1e}) at another position; each position needs its own photo (a file copied, or positions listed in another order?)",
            captures.photos[i].display(),
            name(*j)
        );
        ensure!(
            !(same_position && captures.exposures[i] == captures.exposures[*j]),
            "{}: taken at the same light and camera positions and exposure as {}; each photo needs its own position (a line copied in camera_pos.txt or light_pos.txt?)",
            captures.photos[i].display(),
            name(*j)
        );
    }
    Ok(())
}

/// Colour of a photo: the mean over its pixels of max - min of the
/// chromaticity (r, g, b over their sum); 0 for a grey photo.
fn colourfulness(photo: &Tensor) -> f64 {
    let sum = photo.sum_dim_intlist([0i64].as_slice(), true, Kind::Float).clamp_min(1e-4);
    let chroma = photo / sum;
    (chroma.amax([0i64].as_slice(), false) - chroma.amin([0i64].as_slice(), false)).mean(Kind::Double).double_value(&[])
}

/// Below this colourfulness ([`colourfulness`]) a photo is grey.
const GREY_PHOTO: f64 = 0.01;

/// The first grey photo among colour ones (a black-and-white filter, a
/// monochrome mode), as (its index, its colourfulness, the most colourful
/// photo's); None when none is, or when all are grey (a grey material).
/// photos: `[3, H, W]` linear each.
pub fn grey_among_colour(photos: &[Tensor]) -> Option<(usize, f64, f64)> {
    let colour: Vec<f64> = photos.iter().map(colourfulness).collect();
    let most = colour.iter().cloned().fold(0.0, f64::max);
    if most < 5.0 * GREY_PHOTO {
        return None;
    }
    colour.iter().position(|&c| c < GREY_PHOTO).map(|i| (i, colour[i], most))
}

/// The refusal of a grey photo among colour ones, naming it.
pub fn grey_photo_error(photo: &std::path::Path, colour: f64, most: f64) -> anyhow::Error {
    anyhow::anyhow!("{}: the photo is grey (colour {colour:.4}) where another shows colour ({most:.3}): a black-and-white photo or filter? take it again in colour", photo.display())
}

/// Refuses a grey photo among colour ones: the fit would take the material
/// as grey in that view. `photos`: (capture index, `[3, S, S]` as decoded).
fn check_colour(photos: &[(usize, Tensor)], captures: &Captures) -> Result<()> {
    let tensors: Vec<Tensor> = photos.iter().map(|(_, p)| p.shallow_clone()).collect();
    match grey_among_colour(&tensors) {
        Some((k, colour, most)) => Err(grey_photo_error(&captures.photos[photos[k].0], colour, most)),
        None => Ok(()),
    }
}

/// A photo whose mean error after the fit is above this many times the
/// (lower) median photo's, and above [`OUTLIER_FLOOR`], does not agree
/// with the others: another material, a moved sample, wrong positions.
/// The fit bends toward such a photo, so its error stays a few times the
/// others' rather than far above (a red checkerboard among four photos of
/// a brown bump: 0.048 against a median of 0.007, where the clean
/// capture's worst photo is at 0.020, 14x its median: hence the floor).
pub const OUTLIER_FACTOR: f64 = 3.0;
/// Mean |log difference| (about a relative error) below which no photo is called an outlier.
pub const OUTLIER_FLOOR: f64 = 0.03;

/// Warnings for the photos the fitted maps do not explain
/// ([`OUTLIER_FACTOR`]), naming each with its error and the median.
pub fn outlier_warnings(fit: &PhotoFit, names: &[String]) -> Vec<String> {
    let errors = &fit.report.photo_errors;
    if errors.len() < 3 {
        return Vec::new(); // with two photos, neither is the odd one out
    }
    let mut sorted = errors.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[(sorted.len() - 1) / 2];
    errors
        .iter()
        .zip(names)
        .filter(|(&e, _)| e > OUTLIER_FLOOR && e > OUTLIER_FACTOR * median)
        .map(|(e, name)| format!("{name}: the fitted material explains this photo {:.1}x worse than the others (mean |log difference| {e:.3}, median {median:.3}): is it the same material, and are its positions right?", e / median.max(1e-12)))
        .collect()
}

/// The GGX fit of the start: `flashmat fit`'s, with half its direction
/// pairs and two thirds of its steps. The fit to the photos refines it,
/// so the start needs its lobes roughly right, not to the last step.
pub fn start_fit_config() -> FitConfig {
    let defaults = FitConfig::default();
    FitConfig { samples: START_SAMPLES, steps: START_STEPS, ..defaults }
}

/// Direction pairs and steps of [`start_fit_config`].
pub const START_SAMPLES: usize = 16;
pub const START_STEPS: usize = 100;

/// Maps larger than this on a side get their start at half the side
/// (upsampled): the coarse half of the fit runs there anyway, and M_est and
/// the start's GGX fit cost four times less (1024x1024, 3 photos: 385 ->
/// 252 s on 2 cores, the same data term). Up to this side the start keeps the full size, where
/// M_est sees the texture at the scale it was trained at.
pub const FULL_START_MAX_SIDE: i64 = 512;

/// The whole capture path on loaded photos: the start ([`estimated_start`]
/// on the overhead photo), then [`fit_photos`] on `device`.
/// `on_progress(stage, done, total)`: stage 0 the start, 1 the fit.
pub fn fit_capture(loaded: &LoadedModel, capture: &CapturePhotos, cfg: &PhotoFitConfig, device: Device, mut on_progress: impl FnMut(usize, usize, usize)) -> Result<PhotoFit> {
    let start_cfg = start_fit_config();
    let overhead = capture.photos.get(capture.overhead as i64);
    let (h, w) = (overhead.size()[1], overhead.size()[2]);
    let start = if h.max(w) > FULL_START_MAX_SIDE && h % 2 == 0 && w % 2 == 0 {
        let half = average_2x2(&overhead.unsqueeze(0)).get(0);
        let start = estimated_start(loaded, &half, &start_cfg, |done, total| on_progress(0, done, total))?;
        tch::no_grad(|| renormalised(&start.unsqueeze(0).upsample_bilinear2d([h, w], false, None, None)).get(0))
    } else {
        estimated_start(loaded, &overhead, &start_cfg, |done, total| on_progress(0, done, total))?
    };
    let photos = capture.photos.to_device(device);
    fit_photos(&photos, &capture.clipped, &capture.configs, &start, cfg, |step| on_progress(1, step + 1, cfg.steps))
}

/// A capture folder to a neural material, as `estimate --capture` makes
/// it: its first `count` photos loaded at `cfg.size`, the model `model`
/// (None: the bundled one), [`fit_capture`], then [`neural_material`] of
/// the fitted maps by the bundled teacher, named after the folder.
/// `on_warning` hears the photos' warnings before the fit and the fit's
/// outlier warnings after; `on_progress` as in [`fit_capture`], then
/// stage 2 for the neural material (done 0 of 2: its codes fitted, 1: its
/// gap measured, 2: made).
pub fn capture_material(
    captures: &Captures,
    count: usize,
    cfg: &PhotoFitConfig,
    model: Option<&Path>,
    device: Device,
    mut on_warning: impl FnMut(&str),
    mut on_progress: impl FnMut(usize, usize, usize),
) -> Result<CaptureMaterial> {
    cfg.validate()?;
    let capture = load_capture(captures, count, cfg.size)?;
    capture.warnings.iter().for_each(|w| on_warning(w));
    let loaded = crate::infer::load_model(model, device)?;
    let teacher = load_teacher(None, device)?;
    let fit = fit_capture(&loaded, &capture, cfg, device, &mut on_progress)?;
    outlier_warnings(&fit, &capture.names).iter().for_each(|w| on_warning(w));
    on_progress(2, 0, 2);
    let dir = &captures.dir;
    let source = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| dir.display().to_string());
    let (material, code_fit) = fitted_neural_material(&fit.maps, &capture.photos.get(capture.overhead as i64), &teacher, &capture.configs, &cfg.code_fit, &source)?;
    // LPIPS where its weights are installed; the other figures always.
    let lpips = crate::lpips::Lpips::new(device).ok();
    on_progress(2, 1, 2);
    let gap = neural_gap(&material, &fit.maps, &held_out_configs(GAP_CONFIGS), lpips.as_ref())?;
    on_progress(2, 2, 2);
    Ok(CaptureMaterial { material, fit, code_fit, gap, names: capture.names })
}

/// Bytes [`capture_material`] needs beyond the loaded models, per pixel
/// of the fitted maps and per photo (at least three counted: the neural
/// material's renders and its gap do not shrink with fewer photos).
/// Measured peak memory of `estimate --capture` (`/usr/bin/time`, 3
/// photos of procedural-test:3, CPU): 256 px 1.13 GB, 768 px 2.68 GB,
/// 1024 px 4.17 GB, 1536 px 10.3 GB: 1.1-1.35 kB per pixel and photo
/// above the base, growing with the size; the largest taken (512 px,
/// 2.63 GB, peaks in the start's M_est instead, which `--max-memory` tiles).
const CAPTURE_BYTES_PER_PIXEL_PHOTO: f64 = 1400.0;

/// Peak memory of [`capture_material`] at side `size` with `photos` photos
/// besides what the models take (about 0.8 GB on the CPU), bytes: what
/// `--max-memory` is checked against before any work.
pub fn capture_fit_memory(size: usize, photos: usize) -> f64 {
    CAPTURE_BYTES_PER_PIXEL_PHOTO * (size * size) as f64 * photos.max(3) as f64
}

/// Held-out configurations per case (Hemisphere, Reflect) of the gap
/// [`capture_material`] measures.
pub const GAP_CONFIGS: usize = 4;

/// What [`capture_material`] made.
pub struct CaptureMaterial {
    pub material: NeuralMaterial,
    pub fit: PhotoFit,
    /// How the material's codes were fitted to the maps.
    pub code_fit: CodeFit,
    /// How far the material is from its maps under held-out directions
    /// ([`GAP_CONFIGS`] of each of eval's Hemisphere and Reflect cases).
    pub gap: NeuralGap,
    /// File names of the photos fitted, in the fit's order.
    pub names: Vec<String>,
}

/// The teacher file `explicit`, or the bundled one; a missing file is one line.
pub fn load_teacher(explicit: Option<&Path>, device: Device) -> Result<TeacherWeights> {
    let path = explicit.map(Path::to_path_buf).unwrap_or_else(default_teacher_path);
    ensure!(path.is_file(), "the teacher file {} does not exist (models/MODEL.md: the curriculum's teacher)", path.display());
    TeacherWeights::load(&path, device)
}

#[cfg(test)]
mod tests;
