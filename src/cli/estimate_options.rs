//! The options of how a photo becomes a neural material, shared by the
//! commands that make one (estimate, estimate --capture, relight, show,
//! view, fit, capture --estimate): one home, so no command imports another
//! for them.

use flashmat::infer::exposure::ExposureMode;
use flashmat::infer::refine::RefineConfig;
use clap::Args;
use std::path::PathBuf;

/// How a photo becomes a neural material (shared by estimate, relight, show).
#[derive(Args, Debug, Clone)]
pub struct EstimateOptions {
    /// Model file (flashmat export). Default: the bundled models/flashmat.safetensors, for 8-bit and EXR photos alike
    /// (folder overridden by $FLASHMAT_MODELS).
    #[arg(long, value_name = "FILE")]
    pub model: Option<PathBuf>,
    /// Field of view of the photo across its shorter side, in degrees. Default: from the photo's EXIF
    /// focal length; without one, the model's own 28 degrees (no crop). The centre is cropped to the
    /// model's 28 degree view.
    #[arg(long, value_name = "DEG")]
    pub fov: Option<f64>,
    /// Exposure change in stops applied to the linearised photo (+1 doubles it).
    #[arg(long, value_name = "EV", allow_negative_numbers = true)]
    pub exposure: Option<f64>,
    /// How the photo's exposure reaches the material: `calibrated` (a photo darker than M_est's training photos
    /// is brought up toward their brightness, an 8-bit one no further than its highlight reaches white, trying
    /// lifts up to the level where that stops short and keeping the material that gives the photo's mean back;
    /// the material keeps the exposure as a gain calibrated on the photo, channel by channel: a white balance of the
    /// material against its photo), `calibrated-grey` (the same with one factor for all channels, as before the white
    /// balance), `normalized` (the same without the calibration), `calibrated-capped` (an 8-bit photo lifted no further than
    /// its highlight reaches white, without trying the lifts between that and the level), `calibrated-clipping` (an
    /// 8-bit photo brought up to the level even where that clips its highlight: flashmat before the clip limit) or
    /// `off` (M_est sees the photo as it is, as before version 3 of .nmat).
    #[arg(long, value_enum, default_value_t = ExposureMode::Calibrated)]
    pub exposure_mode: ExposureMode,
    /// Model resolution in pixels of the shorter side (a multiple of 8); the cropped photo is shrunk to it and
    /// the longer side follows the photo's aspect (rounded down to a multiple of 8).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Keep only the centre square of the photo (before rectangles, every photo was estimated this way).
    #[arg(long)]
    pub square: bool,
    /// Memory M_est may use (e.g. 8G, 512M, or bytes): beyond it, M_est runs in overlapping tiles. With --capture,
    /// also the bound on the capture fit: a --size it cannot stay within is refused before any work.
    #[arg(long, value_name = "SIZE", default_value = "8G")]
    pub max_memory: String,
    /// cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// After M_est, optimise the neural map for STEPS steps (100 when no number is given) so that its identity
    /// render matches the photo, with the neural BRDF frozen. On a .nmat, refines on its stored input photo.
    #[arg(long, value_name = "STEPS", num_args = 0..=1, default_missing_value = flashmat::infer::refine::DEFAULT_REFINE_STEPS_ARG)]
    pub refine: Option<usize>,
    #[command(flatten)]
    pub refine_weights: RefineWeights,
    /// Experimental: fill the photographed flash highlight in the neural map, before any refinement: `copy` (the
    /// default with no MODE) takes the codes under it from the material beside it, `blend` interpolates them. Less
    /// of the photo's highlight stays where it was when the light moves (on the held-out set 2.08x -> 1.80x the
    /// truth), but the photo's own render loses it and a copy can bring the wrong material: LPIPS is worse on
    /// average (reports/highlights-experiments.md, section 6).
    #[arg(long, value_enum, value_name = "MODE", num_args = 0..=1, default_missing_value = "copy")]
    pub highlight_fill: Option<flashmat::infer::highlight_fill::FillMode>,
    /// Make the material tile seamlessly (after any refinement): the neural map is made periodic by joining a
    /// half-shifted copy along minimum-error seams, codes copied, never blended (`flashmat::infer::tiling`).
    #[arg(long)]
    pub tile: bool,
}

/// Settings of the refinement on the photo (`--refine`), except its steps.
#[derive(Args, Debug, Clone)]
pub struct RefineWeights {
    /// Refinement: Adam step size, in units of the estimate's RMS value.
    #[arg(long, value_name = "LR", default_value_t = RefineConfig::default().learning_rate)]
    pub refine_lr: f64,
    /// Refinement: weight of the squared pull toward the network's estimate.
    #[arg(long, value_name = "W", default_value_t = RefineConfig::default().pull_weight)]
    pub refine_pull: f64,
    /// Refinement: weight of the edge-aware smoothness of the change.
    #[arg(long, value_name = "W", default_value_t = RefineConfig::default().smooth_weight)]
    pub refine_smooth: f64,
    /// Refinement: weight keeping each pixel's code norm within the estimate's largest.
    #[arg(long, value_name = "W", default_value_t = RefineConfig::default().range_weight)]
    pub refine_range: f64,
    /// Refinement: weight keeping the renders under four other lights near the network's estimate.
    #[arg(long, value_name = "W", default_value_t = RefineConfig::default().relight_weight)]
    pub refine_relight: f64,
}

impl RefineWeights {
    /// The refinement of `steps` steps with these settings.
    pub fn config(&self, steps: usize) -> RefineConfig {
        RefineConfig {
            steps,
            learning_rate: self.refine_lr,
            pull_weight: self.refine_pull,
            smooth_weight: self.refine_smooth,
            range_weight: self.refine_range,
            relight_weight: self.refine_relight,
        }
    }
}
