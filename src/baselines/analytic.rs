//! Analytic SVBRDF estimation: M_est's U-Net (same layout and width) with
//! a 9-channel head decoded into the 10 GGX map channels of
//! [`crate::svbrdf::Svbrdf::stacked`], rendered with the paper's GGX model
//! ([`crate::svbrdf::render::render_directions`]).
//!
//! Head channels -> maps (value ranges of the training data):
//!
//! | head | map | decoding |
//! |---|---|---|
//! | 0..3 | kd (linear diffuse albedo) | sigmoid, in (0, 1) |
//! | 3..6 | ks (linear specular albedo F0) | sigmoid, in (0, 1) |
//! | 6 | roughness r | 0.02 + 0.98 sigmoid, in (0.02, 1) ([`MIN_ROUGHNESS`] is the data's floor) |
//! | 7..9 | normal | n = normalize(x, y, 1): slopes, so z > 0 always |
//!
//! A zero head gives kd = ks = 0.5, r = 0.51 and the flat normal.

use crate::model::MEst;
use crate::data::procedural::MIN_ROUGHNESS;
use crate::model::ModelConfig;
use anyhow::{ensure, Result};
use tch::{nn, Kind, Tensor};

/// Output channels of the analytic U-Net's head.
pub const HEAD_CHANNELS: i64 = 9;

/// Maps a zero head decodes to (a plain dielectric): kd, ks and roughness.
pub const KD_AT_ZERO: f64 = 0.25;
pub const KS_AT_ZERO: f64 = 0.04;
pub const ROUGHNESS_AT_ZERO: f64 = 0.3;

/// The head's initial weights are M_est's scaled by this, so training
/// starts near the zero-head material instead of saturated sigmoids.
pub const HEAD_INIT_SCALE: f64 = 0.1;

fn logit(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

/// The U-Net predicting GGX maps.
#[derive(Debug)]
pub struct AnalyticNet {
    /// M_est's layout with a [`HEAD_CHANNELS`]-channel head.
    pub unet: MEst,
}

impl AnalyticNet {
    /// Variables under `p` named as M_est's (`<p>.stem.weight` ...).
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Result<Self> {
        let cfg = ModelConfig { neural_channels: HEAD_CHANNELS, ..cfg.clone() };
        let unet = MEst::new(p, &cfg)?;
        tch::no_grad(|| {
            let _ = unet.head.shallow_clone().g_mul_scalar_(HEAD_INIT_SCALE);
        });
        Ok(Self { unet })
    }

    /// Decodes head outputs into GGX maps.
    /// raw: `[N, 9, H, W]` -> maps `[N, 10, H, W]` (kd, ks, roughness, unit normal).
    pub fn decode(raw: &Tensor) -> Result<Tensor> {
        let s = raw.size();
        ensure!(s.len() == 4 && s[1] == HEAD_CHANNELS, "analytic head output must be [N, 9, H, W], got {s:?}");
        let kd = (raw.narrow(1, 0, 3) + logit(KD_AT_ZERO)).sigmoid();
        let ks = (raw.narrow(1, 3, 3) + logit(KS_AT_ZERO)).sigmoid();
        let floor = MIN_ROUGHNESS as f64;
        let rough = (raw.narrow(1, 6, 1) + logit((ROUGHNESS_AT_ZERO - floor) / (1.0 - floor))).sigmoid() * (1.0 - floor) + floor;
        let slopes = raw.narrow(1, 7, 2);
        let n = Tensor::cat(&[slopes.shallow_clone(), slopes.narrow(1, 0, 1).ones_like()], 1);
        let norm = n.square().sum_dim_intlist([1i64].as_slice(), true, Kind::Float).sqrt();
        Ok(Tensor::cat(&[kd, ks, rough, n / norm], 1))
    }

    /// GGX maps of photos. x: `[N, 4, H, W]` (ln(1 + RGB), h_z), H and W
    /// multiples of 8 -> `[N, 10, H, W]`.
    pub fn maps_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        Self::decode(&self.unet.forward_t(x, train)?)
    }

    /// Renders the predicted maps with the GGX renderer, in log space.
    /// x: `[N, 4, H, W]`; wi, wo: `[N, K, 3, H, W]` -> ln(1 + R) `[N, K, 3, H, W]`.
    pub fn render_log_t(&self, x: &Tensor, wi: &Tensor, wo: &Tensor, train: bool) -> Result<Tensor> {
        let maps = self.maps_t(x, train)?;
        check_dirs(&maps, wi, wo)?;
        Ok(crate::spaces::to_log(&crate::svbrdf::render::render_directions(&maps, wi, wo)))
    }
}

/// Checks that direction maps `[N, K, 3, H, W]` fit maps `[N, C, H, W]`.
pub(crate) fn check_dirs(maps: &Tensor, wi: &Tensor, wo: &Tensor) -> Result<()> {
    let m = maps.size();
    let d = wi.size();
    ensure!(
        d.len() == 5 && d[0] == m[0] && d[2] == 3 && d[3] == m[2] && d[4] == m[3],
        "direction maps must be [N, K, 3, H, W] = [{}, K, 3, {}, {}], got {d:?}",
        m[0],
        m[2],
        m[3]
    );
    ensure!(wo.size() == d, "wo {:?} must match wi {d:?}", wo.size());
    Ok(())
}
