//! ND_enc: sinusoidal encoding of (wi, wo, h) compressed by a 3-layer MLP
//! (REFERENCE section 4; paper eq. for Gamma).
//!
//! Encoding layout per row (width 9 + 18 n, 297 for n = 16):
//! `[v (9) | sin(2^k pi v) for k = 0..n-1 (n x 9, k-major) | cos(...) (n x 9)]`
//! with v = (wi.x, wi.y, wi.z, wo.x, wo.y, wo.z, h.x, h.y, h.z). The order
//! is a convention (the first layer is dense); it is fixed here because
//! trained weights depend on it.

use super::config::ModelConfig;
use super::layers::torch_default_init;
use anyhow::{ensure, Result};
use std::f64::consts::PI;
use tch::{nn, Kind, Tensor};

/// The sinusoidal encoding of wi, wo and their half vector.
/// wi, wo: `[..., 3]` (unit, any float kind) -> `[..., 9 + 18 n]`.
///
/// The phase 2^k pi x is reduced exactly as pi * ((2^k x) mod 2): 2^k x is
/// exact in floating point, so high frequencies keep full precision in f32
/// (a plain f32 product would carry ~1e-3 rad of error at k = 15).
pub fn encode_directions(wi: &Tensor, wo: &Tensor, frequencies: i64) -> Tensor {
    let v = Tensor::cat(&[wi, wo, &crate::geometry::half_vectors_along(wi, wo, -1)], -1);
    if frequencies == 0 {
        return v;
    }
    let scales: Vec<f64> = (0..frequencies).map(|k| (1u64 << k) as f64).collect();
    let scales = Tensor::from_slice(&scales).to_kind(v.kind()).to_device(v.device()).view([frequencies, 1]);
    // [..., n, 9]
    let phase = (v.unsqueeze(-2) * scales).remainder(2.0) * PI;
    let sin = phase.sin().flatten(-2, -1);
    let cos = phase.cos().flatten(-2, -1);
    Tensor::cat(&[v, sin, cos], -1)
}

/// ND_enc: encoding -> Linear(297, 594) -> LeakyReLU -> Linear(594, 594) ->
/// LeakyReLU -> Linear(594, 32), no biases, LeakyReLU slope 0.01.
#[derive(Debug)]
pub struct NdEnc {
    /// Weights `[out, in]` of the three layers.
    pub layers: Vec<Tensor>,
    pub frequencies: i64,
}

/// LeakyReLU slope between ND_enc's layers (PyTorch's default).
pub const ND_ENC_SLOPE: f64 = 0.01;

impl NdEnc {
    /// Variables `<p>.0.weight`, `<p>.1.weight`, `<p>.2.weight`; PyTorch's
    /// default init for the 1x1 convs the paper describes.
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Self {
        let dims = [cfg.encoding_width(), cfg.enc_hidden, cfg.enc_hidden, cfg.enc_out];
        let layers = (0..3).map(|i| (p / i).var("weight", &[dims[i + 1], dims[i]], torch_default_init())).collect();
        Self { layers, frequencies: cfg.enc_frequencies }
    }

    /// wi, wo: `[..., 3]` unit vectors -> direction code `[..., enc_out]`.
    pub fn forward(&self, wi: &Tensor, wo: &Tensor) -> Tensor {
        let mut x = encode_directions(wi, wo, self.frequencies);
        for (i, w) in self.layers.iter().enumerate() {
            x = x.linear(w, None::<&Tensor>);
            if i + 1 < self.layers.len() {
                // In place: the linear output is not needed by its backward.
                x = x.leaky_relu_();
            }
        }
        x
    }

    /// Multiply-adds x 2 per row.
    pub fn flops_per_row(cfg: &ModelConfig) -> f64 {
        let (e, h, o) = (cfg.encoding_width() as f64, cfg.enc_hidden as f64, cfg.enc_out as f64);
        2.0 * (e * h + h * h + h * o)
    }
}

/// Checks a direction tensor `[..., 3]`.
pub(crate) fn check_dirs(name: &str, t: &Tensor) -> Result<()> {
    let s = t.size();
    ensure!(!s.is_empty() && s[s.len() - 1] == 3, "{name} must have 3 components in its last dimension, got shape {s:?}");
    ensure!(matches!(t.kind(), Kind::Float | Kind::Double | Kind::Half | Kind::BFloat16), "{name} must be floating point, got {:?}", t.kind());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn encoding_values_and_order() {
        // Double precision: compare with f64 sin/cos directly.
        let wi = Tensor::from_slice(&[0.25f64, -0.5, 0.8]).view([1, 3]);
        let wo = Tensor::from_slice(&[0.0f64, 0.6, 0.8]).view([1, 3]);
        let e = encode_directions(&wi, &wo, 16);
        assert_eq!(e.size(), [1, 297]);
        let e: Vec<f64> = Vec::try_from(e.flatten(0, -1)).unwrap();
        let h = {
            let s: [f64; 3] = [0.25 + 0.0, -0.5 + 0.6, 0.8 + 0.8];
            let n = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
            [s[0] / n, s[1] / n, s[2] / n]
        };
        let v = [0.25, -0.5, 0.8, 0.0, 0.6, 0.8, h[0], h[1], h[2]];
        for c in 0..9 {
            assert!((e[c] - v[c]).abs() < 1e-12);
        }
        for k in 0..16 {
            for c in 0..9 {
                let arg = (1u64 << k) as f64 * PI * v[c];
                let (s, co) = (e[9 + k * 9 + c], e[9 + 144 + k * 9 + c]);
                // Exact phase reduction: agrees with f64 sin to ~1e-11 even at k = 15.
                assert!((s - arg.sin()).abs() < 1e-9, "sin k={k} c={c}: {s} vs {}", arg.sin());
                assert!((co - arg.cos()).abs() < 1e-9, "cos k={k} c={c}");
            }
        }
        // x = 0.25 (wi.x): sin(2^k pi / 4) = sqrt(2)/2, 1, 0, 0, ...
        assert!((e[9] - 0.5f64.sqrt()).abs() < 1e-12);
        assert!((e[9 + 9] - 1.0).abs() < 1e-12);
        for k in 2..16 {
            assert!(e[9 + k * 9].abs() < 1e-12, "k={k}");
            let expect_cos = if k == 2 { -1.0 } else { 1.0 };
            assert!((e[9 + 144 + k * 9] - expect_cos).abs() < 1e-12, "cos k={k}");
        }
    }

    #[test]
    fn f32_encoding_is_precise_at_high_frequency() {
        let x = 0.123_456_79f32; // not a dyadic value
        let wi = Tensor::from_slice(&[x, 0.0, 1.0]).view([1, 3]);
        let e: Vec<f32> = Vec::try_from(encode_directions(&wi, &wi, 16).flatten(0, -1)).unwrap();
        let k = 15;
        let exact = ((1u64 << k) as f64 * PI * x as f64).sin();
        assert!((e[9 + k * 9] as f64 - exact).abs() < 2e-4, "{} vs {exact}", e[9 + k * 9]);
    }

    #[test]
    fn param_count_paper() {
        let vs = nn::VarStore::new(Device::Cpu);
        let _ = NdEnc::new(&vs.root(), &ModelConfig::paper());
        let n: i64 = vs.trainable_variables().iter().map(|t| t.numel() as i64).sum();
        assert_eq!(n, 548_262);
    }
}
