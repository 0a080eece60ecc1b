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
    let on_host = |t: &Tensor| t.device() == tch::Device::Cpu && t.kind() == Kind::Float && !t.requires_grad();
    if on_host(wi) && on_host(wo) && wi.size() == wo.size() && (0..=MAX_HOST_FREQUENCIES).contains(&frequencies) && !crate::reference_paths::on() {
        encode_directions_host(wi, wo, frequencies as usize)
    } else {
        encode_directions_tensors(wi, wo, frequencies)
    }
}

/// Frequencies the host encoding covers ([`sin_cos_pi`] is exact for
/// |2^k v| < 2^21 with |v| <= 1).
const MAX_HOST_FREQUENCIES: i64 = 20;

/// Rows per rayon task of the host encoding.
const ROWS_PER_TASK: usize = 512;

/// [`encode_directions`] for f32 CPU directions without a gradient (what
/// training and inference pass), row by row in Rust: libtorch's version
/// works along a dimension of 3 with strided loops (36 ms for the 32,768
/// rows of a training step's outputs on the 2-core development machine).
/// The same values to about 1e-6 (`host_encoding_matches_the_tensor_one`):
/// the phase is reduced exactly as there, then sin and cos of pi t come
/// from [`sin_cos_pi`] instead of libtorch's sin(f32(pi t)).
fn encode_directions_host(wi: &Tensor, wo: &Tensor, frequencies: usize) -> Tensor {
    use rayon::prelude::*;
    let dims = wi.size();
    let (wi, wo) = (wi.contiguous(), wo.contiguous());
    let (wi, wo) = (super::winograd::as_slice(&wi), super::winograd::as_slice(&wo));
    let width = 9 + 18 * frequencies;
    let mut shape = dims;
    *shape.last_mut().expect("[..., 3]") = width as i64;
    let mut encoded = Tensor::empty(shape.as_slice(), (Kind::Float, tch::Device::Cpu));
    super::winograd::as_mut_slice(&mut encoded).par_chunks_mut(width * ROWS_PER_TASK).enumerate().for_each(|(task, out)| {
        let mut phases = vec![0f32; 9 * frequencies];
        for (r, row) in out.chunks_mut(width).enumerate() {
            let i = 3 * (task * ROWS_PER_TASK + r);
            let (a, b) = (&wi[i..i + 3], &wo[i..i + 3]);
            let h = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
            let norm = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt().max(1e-12);
            let v = [a[0], a[1], a[2], b[0], b[1], b[2], h[0] / norm, h[1] / norm, h[2] / norm];
            row[..9].copy_from_slice(&v);
            for (k, p) in phases.chunks_mut(9).enumerate() {
                let scale = (1u32 << k) as f32;
                for (p, &x) in p.iter_mut().zip(&v) {
                    *p = x * scale;
                }
            }
            let (sin, cos) = row[9..].split_at_mut(9 * frequencies);
            for ((&y, s), c) in phases.iter().zip(sin).zip(cos) {
                (*s, *c) = sin_cos_pi(y);
            }
        }
    });
    encoded
}

/// sin(pi y) and cos(pi y) for |y| < 2^21: y = q / 2 + r with q the
/// integer nearest 2y (rounded by adding and subtracting 1.5 * 2^23, whose
/// sum's low bits hold q mod 4) and r in [-1/4, 1/4] exact (the phase
/// reduction is exact as in `remainder(y, 2)`); Taylor polynomials of
/// pi r are exact to f32 there (truncation below 2e-9 at pi / 4), and q
/// mod 4 turns the pair. No branches, integer conversions or libm calls,
/// so the loops that call it vectorise.
#[inline(always)]
fn sin_cos_pi(y: f32) -> (f32, f32) {
    const ROUNDING: f32 = 12_582_912.0; // 1.5 * 2^23
    let shifted = 2.0 * y + ROUNDING;
    let q = shifted - ROUNDING;
    let quadrant = shifted.to_bits() & 3;
    let x = (y - 0.5 * q) * std::f32::consts::PI;
    let x2 = x * x;
    let s = x * (1.0 + x2 * (-1.0 / 6.0 + x2 * (1.0 / 120.0 + x2 * (-1.0 / 5040.0 + x2 * (1.0 / 362_880.0)))));
    let c = 1.0 + x2 * (-0.5 + x2 * (1.0 / 24.0 + x2 * (-1.0 / 720.0 + x2 * (1.0 / 40_320.0 + x2 * (-1.0 / 3_628_800.0)))));
    // Quadrant q mod 4: (s, c), (c, -s), (-s, -c), (-c, s).
    let (a, b) = if quadrant & 1 != 0 { (c, s) } else { (s, c) };
    (if quadrant & 2 != 0 { -a } else { a }, if (quadrant + 1) & 2 != 0 { -b } else { b })
}

/// [`encode_directions`] with tensor operations (any device, kind or
/// gradient).
fn encode_directions_tensors(wi: &Tensor, wo: &Tensor, frequencies: i64) -> Tensor {
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

/// Floor under 1 - h_z in [`half_angle_feature`]: a half angle of about
/// 1.4 mrad, below a pixel's change of direction at 1024 pixels.
pub const HALF_ANGLE_EPS: f64 = 1e-6;

/// The log half angle of direction pairs: -ln(1 - h_z + eps) / ln(1 / eps),
/// 0 where h lies in the surface, 1 where it is the normal (h the unit
/// half vector of wi and wo in the surface frame; [`HALF_ANGLE_EPS`]).
/// wi, wo: `[..., 3]` -> `[..., 1]`.
pub fn half_angle_feature(wi: &Tensor, wo: &Tensor) -> Tensor {
    let h = crate::geometry::half_vectors_along(wi, wo, -1);
    let one_minus = (h.narrow(-1, 2, 1) * -1.0 + 1.0).clamp_min(0.0) + HALF_ANGLE_EPS;
    one_minus.log() * (-1.0 / (1.0 / HALF_ANGLE_EPS).ln())
}

/// ND_enc: encoding -> Linear(297, 594) -> LeakyReLU -> Linear(594, 594) ->
/// LeakyReLU -> Linear(594, 32), no biases, LeakyReLU slope 0.01.
#[derive(Debug)]
pub struct NdEnc {
    /// Weights `[out, in]` of the three layers.
    pub layers: Vec<Tensor>,
    pub frequencies: i64,
    /// The input ends with [`half_angle_feature`] (`ModelConfig::half_angle_feature`).
    pub half_angle: bool,
}

/// LeakyReLU slope between ND_enc's layers (PyTorch's default).
pub const ND_ENC_SLOPE: f64 = 0.01;

impl NdEnc {
    /// Variables `<p>.0.weight`, `<p>.1.weight`, `<p>.2.weight`; PyTorch's
    /// default init for the 1x1 convs the paper describes.
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Self {
        let dims = [cfg.encoding_width(), cfg.enc_hidden, cfg.enc_hidden, cfg.enc_out];
        let layers = (0..3).map(|i| (p / i).var("weight", &[dims[i + 1], dims[i]], torch_default_init())).collect();
        Self { layers, frequencies: cfg.enc_frequencies, half_angle: cfg.half_angle_feature }
    }

    /// wi, wo: `[..., 3]` unit vectors -> direction code `[..., enc_out]`.
    pub fn forward(&self, wi: &Tensor, wo: &Tensor) -> Tensor {
        let mut x = encode_directions(wi, wo, self.frequencies);
        if self.half_angle {
            x = Tensor::cat(&[x.shallow_clone(), half_angle_feature(wi, wo).to_kind(x.kind())], -1);
        }
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

/// ND_enc's first layer `[hidden, 9 + 18 from (+1 with from_half)]` cut
/// to the columns of the lowest `to` frequencies `[hidden, 9 + 18 to (+1
/// with to_half)]`: the directions, sin and cos of frequencies 0..to, and
/// the half-angle feature's column, kept, or added as zeros when the source
/// has none. An ND_enc of fewer frequencies, or one that reads the half
/// angle, starts from another this way: what the kept columns compute is
/// unchanged, the high frequencies' share is dropped, and the training that
/// follows makes up for it.
pub fn lower_frequencies(first_layer: &Tensor, from: i64, from_half: bool, to: i64, to_half: bool) -> Result<Tensor> {
    let width = 9 + 18 * from + from_half as i64;
    ensure!(first_layer.dim() == 2 && first_layer.size()[1] == width, "ND_enc's first layer of {from} frequencies has {width} columns, got shape {:?}", first_layer.size());
    ensure!((0..=from).contains(&to), "cannot cut {from} frequencies to {to}");
    ensure!(to_half || !from_half, "cannot drop the half-angle feature");
    // The encoding's order: [v (9), sin (from x 9, frequency-major), cos (the same), half angle].
    let mut parts = vec![first_layer.narrow(1, 0, 9), first_layer.narrow(1, 9, 9 * to), first_layer.narrow(1, 9 + 9 * from, 9 * to)];
    if from_half {
        parts.push(first_layer.narrow(1, width - 1, 1));
    } else if to_half {
        parts.push(first_layer.narrow(1, 0, 1).zeros_like());
    }
    Ok(Tensor::cat(&parts, 1))
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
    fn fewer_frequencies_keep_what_the_low_ones_compute() {
        // Weights that read only the low frequencies' columns compute the
        // same code from the 16-frequency encoding and, cut, from the 8.
        let (wi, wo) = (Tensor::from_slice(&[0.3f32, -0.2, 0.93]).view([1, 3]), Tensor::from_slice(&[-0.1f32, 0.4, 0.91]).view([1, 3]));
        let w16 = Tensor::randn([5, 297], (Kind::Float, Device::Cpu));
        let high: Vec<i64> = (9 + 72..9 + 144).chain(9 + 144 + 72..297).collect();
        let w16 = w16.index_fill(1, &Tensor::from_slice(&high), 0.0);
        let w8 = lower_frequencies(&w16, 16, false, 8, false).unwrap();
        assert_eq!(w8.size(), [5, 153]);
        let a = encode_directions(&wi, &wo, 16).linear(&w16, None::<&Tensor>);
        let b = encode_directions(&wi, &wo, 8).linear(&w8, None::<&Tensor>);
        assert!(f64::try_from((a - b).abs().max()).unwrap() < 1e-4);
        // The half-angle column is the last one either way; added, it reads nothing yet.
        let h = Tensor::arange(298, (Kind::Float, Device::Cpu)).view([1, 298]);
        let cut: Vec<f32> = Vec::try_from(lower_frequencies(&h, 16, true, 8, true).unwrap().flatten(0, -1)).unwrap();
        assert_eq!((cut.len(), cut[8], cut[9], cut[80], cut[81], cut[152], cut[153]), (154, 8.0, 9.0, 80.0, 153.0, 224.0, 297.0));
        let w8h = lower_frequencies(&w16, 16, false, 8, true).unwrap();
        assert_eq!(w8h.size(), [5, 154]);
        assert!(w8h.narrow(1, 0, 153).equal(&w8) && w8h.narrow(1, 153, 1).abs().max().double_value(&[]) == 0.0);
        assert!(lower_frequencies(&h, 16, true, 17, true).is_err() && lower_frequencies(&h, 8, true, 4, true).is_err());
        assert!(lower_frequencies(&h, 16, true, 8, false).is_err());
    }

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

    /// The host encoding on random f32 unit directions (both hemispheres,
    /// some grazing) at 16 frequencies: its sin and cos match f64 ones of
    /// its own v = (wi, wo, h) to 1e-6 at every frequency; against
    /// libtorch's encoding, h differs by up to 2 f32 ulp (libtorch's f32
    /// sqrt is not correctly rounded: 16% of values differ from IEEE's), a
    /// difference frequency k multiplies by 2^k pi (1e-2 at k = 15, 3e-5 at
    /// the bundled model's k = 7) and nothing else; sin/cos of pi y
    /// against f64 at the quadrant edges and for negative y.
    #[test]
    fn host_encoding_matches_the_tensor_one() {
        tch::manual_seed(4);
        let dirs = |n: i64| crate::geometry::normalize_along(&(Tensor::rand([n, 3], (Kind::Float, Device::Cpu)) * 2.0 - 1.0), -1);
        let (wi, wo) = (dirs(3000).view([2, 1500, 3]), dirs(3000).view([2, 1500, 3]));
        let n = 16;
        let host = encode_directions(&wi, &wo, n);
        assert_eq!(host.size(), [2, 1500, 297]);
        let host = host.view([3000, 297]);
        let tensors = encode_directions_tensors(&wi, &wo, n).view([3000, 297]);
        let worst = |a: &Tensor, b: &Tensor| (a - b).abs().max().double_value(&[]);
        assert_eq!(worst(&host.narrow(1, 0, 6), &tensors.narrow(1, 0, 6)), 0.0);
        assert!(worst(&host.narrow(1, 6, 3), &tensors.narrow(1, 6, 3)) <= 2.4e-7);
        let v = host.narrow(1, 0, 9).to_kind(Kind::Double);
        for k in 0..n {
            let phase = (&v * (1u64 << k) as f64).remainder(2.0) * PI;
            let (sin, cos) = (host.narrow(1, 9 + 9 * k, 9), host.narrow(1, 9 + 9 * (n + k), 9));
            assert!(worst(&sin, &phase.sin()) <= 1e-6 && worst(&cos, &phase.cos()) <= 1e-6, "frequency {k}");
            let bound = 1e-6 + (1u64 << k) as f64 * PI * 2.4e-7;
            let d = worst(&sin, &tensors.narrow(1, 9 + 9 * k, 9)).max(worst(&cos, &tensors.narrow(1, 9 + 9 * (n + k), 9)));
            assert!(d <= bound, "frequency {k}: the encodings differ by {d} (bound {bound})");
        }
        // Directions with a gradient take the tensor path.
        let wi_grad = wi.detach().set_requires_grad(true);
        assert!(encode_directions(&wi_grad, &wo, 16).requires_grad());
        for y in [0.0f32, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 1.999_999, -0.3, -1.0, -7.6, 4096.125, 0.123_456_79 * 32768.0] {
            let (s, c) = sin_cos_pi(y);
            let exact = (y as f64 * PI).sin_cos();
            assert!((s as f64 - exact.0).abs() < 3e-7 && (c as f64 - exact.1).abs() < 3e-7, "y = {y}: ({s}, {c}) vs {exact:?}");
        }
    }

    #[test]
    fn param_count_paper() {
        let vs = nn::VarStore::new(Device::Cpu);
        let _ = NdEnc::new(&vs.root(), &ModelConfig::paper());
        let n: i64 = vs.trainable_variables().iter().map(|t| t.numel() as i64).sum();
        assert_eq!(n, 548_262);
    }
}
