//! Element-wise kernels of the folded (inference) M_est, each one pass
//! over memory where libtorch's operator-by-operator version made four to
//! eight: the HA layer's combination of its branches (with the residual
//! block's ReLU and identity add), and the instance norm written straight
//! into the replicate-padded input of the next conv (plain padding stays
//! libtorch's: a hand-written one measured no faster). They run on
//! contiguous f32 CPU tensors; callers keep the tensor version for any
//! other kind or device. On the 2-core development CPU these operations
//! took 0.6 of the paper preset's 6 s at 256x256 and 1.4 of the compact
//! preset's 7 s at 768x768 (`reports/inference-speed.md`).

use crate::model::winograd::{as_mut_slice, as_slice};
use rayon::prelude::*;
use tch::{Device, Kind, Tensor};

/// Whether a tensor can be read by these kernels as it is.
pub fn eligible(t: &Tensor) -> bool {
    t.kind() == Kind::Float && t.device() == Device::Cpu && t.is_contiguous()
}

/// e^x for f32, within about 2e-7 relative of the exact value on
/// [-87, 88] (other inputs are clamped there; NaN gives NaN), written without branches or libm
/// calls so that loops over it vectorise: x = n ln 2 + r with |r| <= ln 2 / 2,
/// e^r by its Taylor series to r^7 (truncation below 6e-9), 2^n through the
/// exponent bits.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    // ln 2 split so that n * LN2_HI is exact for |n| < 2^8.
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    // 1.5 * 2^23: adding it rounds to an integer (ties to even).
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + ROUND;
    let n = shifted - ROUND;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = 1.0 / 5040.0;
    let p = p * r + 1.0 / 720.0;
    let p = p * r + 1.0 / 120.0;
    let p = p * r + 1.0 / 24.0;
    let p = p * r + 1.0 / 6.0;
    let p = p * r + 0.5;
    let p = p * r + 1.0;
    let p = p * r + 1.0;
    // The low mantissa bits of `shifted` hold n (as 0x4B40_0000 + n).
    let n_bits = shifted.to_bits().wrapping_sub(0x4B40_0000);
    let e = f32::from_bits(p.to_bits().wrapping_add(n_bits << 23));
    // NaN stays NaN (a select, so the loop still vectorises).
    if x.is_nan() {
        x
    } else {
        e
    }
}

/// 1 / (1 + e^-x) through [`exp_f32`].
#[inline(always)]
pub fn sigmoid_f32(x: f32) -> f32 {
    1.0 / (1.0 + exp_f32(-x))
}

/// The output of one HA layer (and what follows it in a residual block):
/// out[n, k] = act(sigmoid(gate[n, k]) * leaky(feat[n, k]) * scale[k]
///                 + (b[n, k] for k < P/2, else c[n, k - P/2]) + residual[n, k]),
/// act = ReLU or none, leaky = max(x, slope x).
pub struct HaCombine<'a> {
    /// `[N, M, H, W]`: the gate in channels 0..P, incep_c in
    /// `c_offset..c_offset + P/2` (the merged conv's output).
    pub merged: &'a Tensor,
    pub c_offset: i64,
    /// `[N, P/2, H, W]`: incep_b's output.
    pub b: &'a Tensor,
    /// `[N, P, H, W]`: the feature conv's output, before the LeakyReLU.
    pub feat: &'a Tensor,
    pub slope: f32,
    /// `[P]`, where BN's scale could not be folded into feat.
    pub feat_scale: Option<&'a [f32]>,
    /// `[N, P, H, W]`: added before the activation.
    pub residual: Option<&'a Tensor>,
    pub relu: bool,
}

impl HaCombine<'_> {
    /// -> `[N, P, H, W]`. Every tensor must pass [`eligible`].
    pub fn run(&self) -> Tensor {
        let fs = self.feat.size();
        let (n, p, plane) = (fs[0] as usize, fs[1] as usize, (fs[2] * fs[3]) as usize);
        let half = p / 2;
        let m_channels = self.merged.size()[1] as usize;
        let (merged, b, feat) = (as_slice(self.merged), as_slice(self.b), as_slice(self.feat));
        let residual = self.residual.map(as_slice);
        // Plain values for the threads (tensors are not Sync).
        let (c_offset, feat_scale, slope, relu) = (self.c_offset as usize, self.feat_scale, self.slope, self.relu);
        let mut out = Tensor::empty([n as i64, p as i64, fs[2], fs[3]], (Kind::Float, Device::Cpu));
        as_mut_slice(&mut out).par_chunks_mut(plane).enumerate().for_each(|(plane_index, dst)| {
            let (img, k) = (plane_index / p, plane_index % p);
            let gate = &merged[(img * m_channels + k) * plane..][..plane];
            let f = &feat[(img * p + k) * plane..][..plane];
            let add = if k < half {
                &b[(img * half + k) * plane..][..plane]
            } else {
                &merged[(img * m_channels + c_offset + k - half) * plane..][..plane]
            };
            let scale = feat_scale.map_or(1.0, |s| s[k]);
            let res = residual.map(|r| &r[(img * p + k) * plane..][..plane]);
            combine_plane(dst, gate, f, add, res, slope, scale, relu);
        });
        out
    }
}

avx2_dispatch!(
/// One channel plane of [`HaCombine`], built for AVX2 where the CPU has it
/// (the same operations as the baseline build, eight floats at a time: the
/// same results).
fn combine_plane / combine_plane_avx2(dst: &mut [f32], gate: &[f32], feat: &[f32], add: &[f32], residual: Option<&[f32]>, slope: f32, scale: f32, relu: bool) => combine_plane_body);

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn combine_plane_body(dst: &mut [f32], gate: &[f32], feat: &[f32], add: &[f32], residual: Option<&[f32]>, slope: f32, scale: f32, relu: bool) {
    let len = dst.len();
    let (gate, feat, add) = (&gate[..len], &feat[..len], &add[..len]);
    // Two loop bodies (the ReLU is a select against 0 or -inf), so that
    // neither has a branch inside and both vectorise. NaN and infinities
    // propagate as in libtorch's operations (f32::max would turn NaN into
    // 0 and hide a broken model from the finiteness checks downstream).
    let floor = if relu { 0.0 } else { f32::NEG_INFINITY };
    let act = |v: f32| if v < floor { floor } else { v };
    match residual {
        Some(r) => {
            let r = &r[..len];
            for i in 0..len {
                let f = feat[i].max(slope * feat[i]);
                dst[i] = act(sigmoid_f32(gate[i]) * (f * scale) + add[i] + r[i]);
            }
        }
        None => {
            for i in 0..len {
                let f = feat[i].max(slope * feat[i]);
                dst[i] = act(sigmoid_f32(gate[i]) * (f * scale) + add[i]);
            }
        }
    }
}

/// Each plane's mean and 1 / sqrt(biased variance + eps) (InstanceNorm's
/// statistics), accumulated in f64. x: `[N, C, H, W]` f32 CPU contiguous.
pub fn plane_stats(x: &Tensor, eps: f64) -> Vec<(f32, f32)> {
    let s = x.size();
    let plane = (s[2] * s[3]) as usize;
    as_slice(x)
        .par_chunks(plane)
        .map(|p| {
            let mean = p.iter().map(|&v| v as f64).sum::<f64>() / plane as f64;
            let var = p.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / plane as f64;
            (mean as f32, (1.0 / (var + eps).sqrt()) as f32)
        })
        .collect()
}

/// InstanceNorm with the given per-plane statistics, replicate-padded by
/// one pixel, in one pass. x: `[N, C, H, W]` f32 CPU contiguous, stats:
/// N * C entries (mean, 1 / std) -> `[N, C, H + 2, W + 2]`.
pub fn normalize_pad1(x: &Tensor, stats: &[(f32, f32)]) -> Tensor {
    let s = x.size();
    assert_eq!(stats.len() as i64, s[0] * s[1], "one (mean, 1/std) per plane");
    let (h, w) = (s[2] as usize, s[3] as usize);
    let (hp, wp) = (h + 2, w + 2);
    let src = as_slice(x);
    let mut out = Tensor::empty([s[0], s[1], s[2] + 2, s[3] + 2], (Kind::Float, Device::Cpu));
    as_mut_slice(&mut out).par_chunks_mut(hp * wp).enumerate().for_each(|(plane_index, dst)| {
        let plane = &src[plane_index * h * w..][..h * w];
        let (mean, inv_std) = stats[plane_index];
        for y in 0..hp {
            let row = &plane[y.saturating_sub(1).min(h - 1) * w..][..w];
            let out_row = &mut dst[y * wp..][..wp];
            for (o, &v) in out_row[1..=w].iter_mut().zip(row) {
                *o = (v - mean) * inv_std;
            }
            out_row[0] = out_row[1];
            out_row[w + 1] = out_row[w];
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_matches_f64_across_the_range() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -87.0 + 175.0 * i as f64 / 200_000.0;
            let got = exp_f32(x as f32) as f64;
            let want = (x as f32 as f64).exp();
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 3e-7, "worst relative error {worst:e}");
        // Exact points: e^0 = 1; far outside the clamp, finite.
        assert_eq!(exp_f32(0.0), 1.0);
        assert!(exp_f32(-1000.0) > 0.0 && exp_f32(1000.0).is_finite());
        assert!((sigmoid_f32(0.0) - 0.5).abs() < 1e-7 && sigmoid_f32(-200.0) >= 0.0 && sigmoid_f32(200.0) <= 1.0);
    }

    fn randn(shape: &[i64]) -> Tensor {
        Tensor::randn(shape, (Kind::Float, Device::Cpu))
    }

    #[test]
    fn ha_combine_equals_the_tensor_operations() {
        tch::manual_seed(4);
        let (n, p, h, w) = (2, 6, 5, 7);
        let merged = randn(&[n, 2 * p + p / 2, h, w]) * 3.0;
        let b = randn(&[n, p / 2, h, w]);
        let feat = randn(&[n, p, h, w]);
        let residual = randn(&[n, p, h, w]);
        let scale = [1.0f32, -0.5, 2.0, 0.25, -1.0, 3.0];
        let scale_t = Tensor::from_slice(&scale).view([1, -1, 1, 1]);
        for (res, relu, sc) in [(None, false, None), (Some(&residual), true, Some(&scale[..])), (None, true, None)] {
            let got = HaCombine { merged: &merged, c_offset: 2 * p, b: &b, feat: &feat, slope: 0.1, feat_scale: sc, residual: res, relu }.run();
            let mut f = feat.maximum(&(&feat * 0.1));
            if sc.is_some() {
                f *= &scale_t;
            }
            let mut want = merged.narrow(1, 0, p).sigmoid() * f + Tensor::cat(&[&b, &merged.narrow(1, 2 * p, p / 2)], 1);
            if let Some(r) = res {
                want += r;
            }
            if relu {
                want = want.relu();
            }
            let err = (got - &want).abs().max().double_value(&[]);
            assert!(err < 1e-5, "residual {} relu {relu}: {err}", res.is_some());
        }
        // Non-finite values propagate through the ReLU as in libtorch: a
        // NaN feature or gate, an infinite feature under a closed gate.
        let _ = feat.get(0).get(0).get(0).get(0).fill_(f64::NAN);
        let _ = merged.get(0).get(1).get(0).get(0).fill_(f64::NAN);
        let _ = feat.get(0).get(2).get(0).get(0).fill_(f64::INFINITY);
        let _ = merged.get(0).get(2).get(0).get(0).fill_(-200.0);
        let got = HaCombine { merged: &merged, c_offset: 2 * p, b: &b, feat: &feat, slope: 0.1, feat_scale: None, residual: None, relu: true }.run();
        let at = |k: i64| got.double_value(&[0, k, 0, 0]);
        assert!(at(0).is_nan() && at(1).is_nan(), "{} {}", at(0), at(1));
        assert!(!at(2).is_finite(), "closed gate x inf: {}", at(2));
        assert!(exp_f32(f32::NAN).is_nan() && sigmoid_f32(f32::NAN).is_nan());
    }

    /// The AVX2 build runs the same IEEE operations eight at a time, so its
    /// results are bit for bit the baseline build's.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_build_gives_the_baseline_results() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            eprintln!("this CPU has no AVX2: only the baseline build runs here");
            return;
        }
        let values: Vec<f32> = (0..1003).map(|i| ((i * 7919 % 1000) as f32 - 500.0) * 0.037).collect();
        let shifted: Vec<f32> = values.iter().rev().copied().collect();
        for (residual, relu) in [(None, false), (Some(&shifted[..]), true)] {
            let (mut base, mut wide) = (vec![0.0f32; values.len()], vec![0.0f32; values.len()]);
            combine_plane_body(&mut base, &values, &shifted, &values, residual, 0.1, 0.7, relu);
            // SAFETY: the CPU has AVX2 (checked above).
            unsafe { combine_plane_avx2(&mut wide, &values, &shifted, &values, residual, 0.1, 0.7, relu) };
            assert!(base.iter().zip(&wide).all(|(a, b)| a.to_bits() == b.to_bits()), "relu {relu}");
        }
    }

    #[test]
    fn normalisation_and_padding_equal_libtorch() {
        tch::manual_seed(5);
        let x = randn(&[2, 3, 6, 9]) * 2.0 + 1.5;
        let stats = plane_stats(&x, 1e-5);
        let want = x.instance_norm(None::<&Tensor>, None, None, None, true, 0.1, 1e-5, true).pad([1, 1, 1, 1], "replicate", None);
        let err = (normalize_pad1(&x, &stats) - want).abs().max().double_value(&[]);
        assert!(err < 1e-5, "{err}");
        // A plane of one constant value: mean that value, normalised to 0.
        let c = Tensor::full([1, 1, 4, 4], 2.5, (Kind::Float, Device::Cpu));
        let st = plane_stats(&c, 1e-5);
        assert_eq!(st[0].0, 2.5);
        assert_eq!(normalize_pad1(&c, &st).abs().max().double_value(&[]), 0.0);
    }
}
