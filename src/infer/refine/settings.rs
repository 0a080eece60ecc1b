//! The settings of a refinement and the record of what it did: both are
//! stored in the `.nmat` (metadata key `refine`, docs/NMAT.md), so the file
//! format reads them without the optimiser.

use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};

/// Largest accepted step count (a few minutes at 256x256 on a CPU is
/// ~1,000 steps; beyond this the option is a typo).
pub const MAX_REFINE_STEPS: usize = 20_000;

/// Photo values at or above this are treated as clipped in 8-bit photos
/// (8-bit level 254 decodes to 0.991).
pub const CLIP_LEVEL: f64 = 0.999;

/// Gradient of ln(1 + photo) (mean over channels) at which the smoothness
/// weight falls to 1/e.
pub const EDGE_SCALE: f64 = 0.05;

/// Steps of `--refine` given without a number: on 8 held-out materials
/// (LDR photos) Identity LPIPS fell from 0.475 to 0.168 / 0.088 / 0.050 /
/// 0.038 after 25 / 50 / 100 / 200 steps while Reflect and Hemisphere
/// stayed below the unrefined ones (reports/refine.md); 100 reaches the
/// paper's Identity (0.092) with room, at half the time of 200.
pub const DEFAULT_REFINE_STEPS: usize = 100;
/// [`DEFAULT_REFINE_STEPS`] as the command line's default text.
pub const DEFAULT_REFINE_STEPS_ARG: &str = "100";

/// Weight of the relight prior: on the 50 held-out materials (LDR photos,
/// 100 steps) 0.5 lowered the relit log error against the prior-free
/// refinement on 42 (Reflect) and 43 (Hemisphere) of 50 materials, back to
/// the unrefined level (0.091 / 0.083 against 0.090 / 0.087), with Reflect
/// and Hemisphere LPIPS unchanged, for an Identity LPIPS of 0.049 instead
/// of 0.025 (reports/refine.md).
pub const DEFAULT_RELIGHT_WEIGHT: f64 = 0.5;

/// Settings of one refinement (recorded in the `.nmat`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RefineConfig {
    pub steps: usize,
    /// Adam step size, in units of the estimate's RMS value.
    pub learning_rate: f64,
    pub pull_weight: f64,
    pub smooth_weight: f64,
    pub range_weight: f64,
    /// Weight of the relight prior (renders under other lights stay the
    /// network's); 0 in files written before it existed.
    #[serde(default)]
    pub relight_weight: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self { steps: DEFAULT_REFINE_STEPS, learning_rate: 0.02, pull_weight: 0.01, smooth_weight: 0.01, range_weight: 1.0, relight_weight: DEFAULT_RELIGHT_WEIGHT }
    }
}

impl RefineConfig {
    /// The default settings with `steps` steps.
    pub fn with_steps(steps: usize) -> Self {
        Self { steps, ..Self::default() }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.steps <= MAX_REFINE_STEPS, "--refine takes at most {MAX_REFINE_STEPS} steps, got {}", self.steps);
        for (name, v) in [
            ("learning rate", self.learning_rate),
            ("pull weight", self.pull_weight),
            ("smoothness weight", self.smooth_weight),
            ("range weight", self.range_weight),
            ("relight weight", self.relight_weight),
        ] {
            ensure!(v.is_finite() && v >= 0.0, "the refinement {name} must be a finite number >= 0, got {v}");
        }
        Ok(())
    }
}

/// What a refinement did (recorded in the `.nmat` with its settings).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RefineReport {
    pub config: RefineConfig,
    /// Steps applied (fewer than asked when stopped).
    pub steps_done: usize,
    pub seconds: f64,
    /// Data term (mean |ln(1+R) - ln(1+photo)|, one-sided on clipped
    /// pixels, render and photo divided by the exposure gain) of the
    /// identity render before and after.
    pub identity_l1_before: f64,
    pub identity_l1_after: f64,
    /// Why it stopped early and kept the unrefined map, if it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopped: Option<String>,
}

impl RefineReport {
    /// One line for the terminal.
    pub fn summary(&self) -> String {
        match &self.stopped {
            Some(why) => format!("refinement stopped at step {} ({why}); kept the unrefined material", self.steps_done),
            None => format!(
                "refined in {} steps, {:.1} s: identity L1 (log radiance) {:.4} -> {:.4}",
                self.steps_done, self.seconds, self.identity_l1_before, self.identity_l1_after
            ),
        }
    }
}
