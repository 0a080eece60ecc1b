//! Exposure that cannot fool the model (issue 53): M_est never sees a photo
//! darker than the brightness it was trained at, and the material carries
//! the photo's exposure as a gain ([`super::NmatMeta::gain`]) that every
//! renderer applies.
//!
//! ```text
//! level  = median over pixels of the photo's RGB mean        (robust: a highlight is a few pixels)
//! s      = max(1, min(min_level / level, 1 / bright))        (dark photos are brought up, LDR ones no further
//!                                                             than their brightest pixels reach the clip)
//! M_est  sees clamp(s * photo)                               (LDR models: clamped to [0, 1] as in training)
//! gain   = 1 / s, times the identity calibration below
//! ```
//!
//! Every photo darker than the minimum level reaches M_est at that level: a
//! photo taken k stops darker gives the same neural map (wherever the
//! darker 8-bit photo is not quantised away) and a gain 2^-k times the
//! first, so its renders are exactly 2^-k times as bright. Brighter photos
//! are left as they are: the bundled model follows their brightness (and
//! normalising them down cost detail: on held-out material 19, median
//! 0.49, the identity log error doubled, 0.026 -> 0.051; reports/exposure.md).
//!
//! For LDR models the lift stops where the photo's brightest pixels (all
//! but [`ExposureConfig::clip_share`] of them) reach 1: bringing a dark
//! photo up to the level clipped its flash highlight, which M_est then read
//! as a dull one (held-out test21 at -6 stops: identity 0.37x), and an
//! already clipped photo lost its detail above 1 / s (Identity LPIPS
//! +0.011 over the held-out set; reports/exposure.md). The scale is still
//! 2^k times larger for a photo k stops darker, so its map is the same.
//!
//! Where the clip holds the lift below the level, neither end is right for
//! every photo (lifted less, M_est reads the darker photo too bright and its
//! highlight comes back too strong; lifted fully, the clipped highlight
//! comes back too dull), so [`ExposureConfig::lift_candidates`] scales
//! between the two are tried and the material whose identity render gives
//! the unclipped photo's mean back best, highlight included
//! ([`identity_error`]), is kept. The choice is the same k stops darker.
//!
//! The identity calibration then makes the material give its photo back:
//! the network's render under the photo's own flash is compared with the
//! photo over the pixels that are neither clipped nor in the flash
//! highlight (above [`HIGHLIGHT_FACTOR`] x the median: the highlight is
//! what the network is least sure of, and a few bright pixels must not set
//! the brightness of the rest), and the gain takes the ratio of their
//! means, per channel: a white balance of the material against its own
//! photo. The bundled model adds blue where real photos have almost none
//! (identity B over the photo's 1.30 on a real set, 9.0 on a saturated
//! orange; issue 69), which one scalar cannot take out. Texture and the
//! shape of the highlight stay the network's.

use anyhow::{ensure, Result};
use tch::{Kind, Tensor};

/// Median level (RGB mean, linear) below which photos are brought up for
/// M_est: where the bundled model's identity renders follow the photo best
/// (`examples/probe_exposure.rs`). On the 50 held-out 8-bit photos
/// (reports/exposure.md) it keeps the identity ratio at 0.98 / 0.96
/// (geometric mean) at -4 / -6 stops and costs 0.011 Identity LPIPS at 0
/// stops (bringing an 8-bit photo up clips what lay above 1 / scale);
/// 0.03 cost 0.004 but let the near-black matte material's co-located
/// highlight reach 2.27x its truth (the bound is 2x, tests/bundled_model.rs).
pub const DEFAULT_MIN_LEVEL: f64 = 0.1;

/// Pixels brighter than this many times the photo's median are the flash
/// highlight (the moved-highlight test's S_in, issue 48), left out of the
/// identity calibration.
pub const HIGHLIGHT_FACTOR: f64 = 2.0;

/// Photo values at or above this are clipped (8-bit white, after decoding).
pub const CLIPPED_LEVEL: f64 = 0.999;

/// Share of pixels the lift may bring to the clip ([`ExposureConfig::clip_share`]):
/// a tenth of a percent, so one hot pixel does not hold a photo down.
pub const DEFAULT_CLIP_SHARE: f64 = 0.001;

/// Lifts tried between the clip-limited one and the level's
/// ([`ExposureConfig::lift_candidates`]).
pub const DEFAULT_LIFT_CANDIDATES: usize = 3;

/// Calibration factors outside this range are refused (the network's
/// identity render is then far from the photo for another reason, and the
/// normalised gain alone is kept).
pub const MAX_CALIBRATION: f64 = 8.0;

/// `--exposure-mode` (and the Python `exposure_mode`): which of
/// [`ExposureConfig`]'s steps run.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExposureMode {
    Calibrated,
    CalibratedGrey,
    Normalized,
    CalibratedClipping,
    CalibratedCapped,
    Off,
}

impl ExposureMode {
    pub fn config(self) -> ExposureConfig {
        match self {
            ExposureMode::Calibrated => ExposureConfig::default(),
            ExposureMode::CalibratedGrey => ExposureConfig { white_balance: false, ..Default::default() },
            ExposureMode::Normalized => ExposureConfig { calibrate: false, ..Default::default() },
            ExposureMode::CalibratedClipping => ExposureConfig { clip_share: None, ..Default::default() },
            ExposureMode::CalibratedCapped => ExposureConfig { lift_candidates: 1, ..Default::default() },
            ExposureMode::Off => ExposureConfig::off(),
        }
    }
}

/// How a photo's exposure is taken out before M_est and put back after.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExposureConfig {
    /// Bring photos darker than [`ExposureConfig::min_level`] up to it
    /// before M_est (false: the photo as it is, the behaviour before issue 53).
    pub normalize: bool,
    /// Median RGB-mean level below which photos are brought up.
    pub min_level: f64,
    /// Calibrate the gain on the identity render.
    pub calibrate: bool,
    /// Share of pixels an LDR photo's lift may bring to 1 (their brightest
    /// channel); None: lifted to the level whatever it clips.
    pub clip_share: Option<f64>,
    /// Where the clip holds the lift below the level (and the gain is
    /// calibrated): how many lifts, geometrically spaced from the
    /// clip-limited one to the level's, M_est runs at; the material that
    /// gives its photo back best is kept. 1: the clip-limited lift alone.
    pub lift_candidates: usize,
    /// Calibrate each channel on its own (a white balance of the material
    /// against its photo); false: one factor for all three, as before
    /// issue 69.
    pub white_balance: bool,
}

impl Default for ExposureConfig {
    fn default() -> Self {
        Self { normalize: true, min_level: DEFAULT_MIN_LEVEL, calibrate: true, clip_share: Some(DEFAULT_CLIP_SHARE), lift_candidates: DEFAULT_LIFT_CANDIDATES, white_balance: true }
    }
}

impl ExposureConfig {
    /// The photo as it is and no calibration: what flashmat did before.
    pub fn off() -> Self {
        Self { normalize: false, calibrate: false, ..Self::default() }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.min_level.is_finite() && self.min_level > 0.0 && self.min_level <= 1.0, "the exposure's minimum level must be in (0, 1], got {}", self.min_level);
        ensure!(self.lift_candidates >= 1, "at least one lift must be tried");
        if let Some(share) = self.clip_share {
            ensure!((0.0..1.0).contains(&share), "the share of pixels the lift may clip must be in [0, 1), got {share}");
        }
        Ok(())
    }
}

/// Per-pixel RGB mean of a linear photo `[3, H, W]` -> `[H, W]`.
pub(crate) fn luminance(photo: &Tensor) -> Tensor {
    photo.to_kind(Kind::Float).clamp_min(0.0).mean_dim(&[0i64][..], false, Kind::Float)
}

/// The photo's exposure level: the median over pixels of the RGB mean, or
/// None for a photo with no light in half of its pixels (nothing to
/// normalise by). photo: linear `[3, H, W]`.
pub fn photo_level(photo: &Tensor) -> Option<f64> {
    let level = luminance(photo).flatten(0, -1).median().double_value(&[]);
    (level.is_finite() && level > 1e-8).then_some(level)
}

/// The brightest channel of the photo's pixels at the given share from the
/// top: all but `share` of the pixels are at or below it. photo: linear
/// `[3, H, W]`.
pub fn bright_level(photo: &Tensor, share: f64) -> f64 {
    let peaks = photo.to_kind(Kind::Float).max_dim(0, false).0.flatten(0, -1);
    let n = peaks.numel() as i64;
    let k = ((n as f64 * (1.0 - share)).ceil() as i64).clamp(1, n);
    peaks.kthvalue(k, 0, false).0.double_value(&[])
}

/// The scale M_est's input is multiplied by: min_level / level for a photo
/// darker than the minimum, for an LDR photo (`clip_to_one`) no more than
/// brings its [`bright_level`] to 1, and never below 1 (1 also when off,
/// or when the photo has no level). photo: linear `[3, H, W]`.
pub fn normalizing_scale(photo: &Tensor, cfg: &ExposureConfig, clip_to_one: bool) -> f64 {
    match (cfg.normalize, photo_level(photo)) {
        (true, Some(level)) => {
            let cap = match (clip_to_one, cfg.clip_share) {
                (true, Some(share)) => 1.0 / bright_level(photo, share).max(1e-12),
                _ => f64::INFINITY,
            };
            (cfg.min_level / level).min(cap).max(1.0)
        }
        _ => 1.0,
    }
}

/// The scales M_est's input is tried at: [`normalizing_scale`] alone, or,
/// where the clip holds it below the level's lift and the gain is
/// calibrated, `lift_candidates` scales geometrically spaced from it to the
/// level's (both ends included); an LDR photo already clipped (beyond the
/// clip share) gets none. photo: linear `[3, H, W]`.
pub fn candidate_scales(photo: &Tensor, cfg: &ExposureConfig, clip_to_one: bool) -> Vec<f64> {
    let capped = normalizing_scale(photo, cfg, clip_to_one);
    let full = normalizing_scale(photo, cfg, false);
    let n = cfg.lift_candidates;
    // A photo the camera already clipped is not lifted past it: trying lifts
    // on those too cost 0.007 Identity LPIPS at 0 stops (reports/exposure.md).
    let clipped = cfg.clip_share.is_some_and(|share| bright_level(photo, share) >= CLIPPED_LEVEL);
    if !cfg.calibrate || n <= 1 || !clip_to_one || clipped || full <= capped * (1.0 + 1e-9) {
        return vec![capped];
    }
    (0..n).map(|i| capped * (full / capped).powf(i as f64 / (n - 1) as f64)).collect()
}

/// How far a material's identity render `[3, H, W]` is from giving its
/// photo `[3, H, W]` back (both linear): |ln(mean I / mean P)| over the
/// pixels not clipped in any channel, highlight included (the flash
/// highlight carries much of a glossy photo's light, which the calibration
/// leaves to the network). Unchanged by the exposure; infinite when
/// nothing can be compared.
pub fn identity_error(photo: &Tensor, identity: &Tensor) -> f64 {
    let unclipped = unclipped_mask(photo);
    if unclipped.sum(Kind::Int64).int64_value(&[]) == 0 {
        return f64::INFINITY;
    }
    let e = (masked_mean(identity, &unclipped) / masked_mean(photo, &unclipped)).ln().abs();
    if e.is_finite() { e } else { f64::INFINITY }
}

/// How well a material gives its photo back, at a glance (issue 69): its
/// identity render's mean over the photo's, of the RGB means and per
/// channel, over the pixels not clipped in any channel (highlight
/// included, as [`identity_error`]). 1 is right; the estimate's last line,
/// `material.html`'s caption and the demo's summary show it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct IdentityCheck {
    pub brightness: f64,
    pub rgb: [f64; 3],
}

impl IdentityCheck {
    /// photo, identity: linear `[3, H, W]`; None when no pixel is unclipped
    /// or the photo is black.
    pub fn measure(photo: &Tensor, identity: &Tensor) -> Option<Self> {
        let unclipped = unclipped_mask(photo);
        let (p, r) = (masked_channel_means(photo, &unclipped), masked_channel_means(identity, &unclipped));
        let brightness = r.iter().sum::<f64>() / p.iter().sum::<f64>();
        let rgb = [0, 1, 2].map(|c| r[c] / p[c]);
        brightness.is_finite().then_some(Self { brightness, rgb })
    }

    /// `identity render over the photo: brightness 1.03, R / G / B 1.01 / 1.02 / 1.07`
    /// (a channel the photo holds at 0 shows as `-`).
    pub fn summary(&self) -> String {
        let f = |v: f64| if v.is_finite() { format!("{v:.2}") } else { "-".to_string() };
        format!("identity render over the photo: brightness {}, R / G / B {} / {} / {}", f(self.brightness), f(self.rgb[0]), f(self.rgb[1]), f(self.rgb[2]))
    }
}

/// Pixels the identity calibration compares `[H, W]` (bool): not clipped in
/// any channel and not in the flash highlight. photo: linear `[3, H, W]`.
pub fn calibration_mask(photo: &Tensor) -> Tensor {
    let lum = luminance(photo);
    let median = lum.flatten(0, -1).median().double_value(&[]);
    let below_highlight = lum.le(HIGHLIGHT_FACTOR * median.max(0.0));
    unclipped_mask(photo).logical_and(&below_highlight)
}

/// Pixels not clipped in any channel `[H, W]` (bool). photo: linear `[3, H, W]`.
fn unclipped_mask(photo: &Tensor) -> Tensor {
    photo.max_dim(0, false).0.lt(CLIPPED_LEVEL)
}

/// Mean of `t` `[3, H, W]` (clamped at 0) over the pixels of `mask` `[H, W]`.
fn masked_mean(t: &Tensor, mask: &Tensor) -> f64 {
    t.to_kind(Kind::Double).clamp_min(0.0).masked_select(&mask.unsqueeze(0).expand_as(t)).mean(Kind::Double).double_value(&[])
}

/// The factors, per channel, that make the identity render's mean equal
/// the photo's over [`calibration_mask`], or None where they cannot be
/// trusted (under a hundredth of the pixels, a black render, or an overall
/// factor, of the RGB means, beyond [`MAX_CALIBRATION`] either way). Each
/// channel's factor stays within [`MAX_CHANNEL_BALANCE`] of the overall one
/// (a channel black in photo or render gives no ratio to trust), balanced
/// no further than [`BALANCE_STRENGTHS`] finds best; without
/// `white_balance`, all three are the overall one.
/// photo, identity: linear `[3, H, W]`.
pub fn calibration_factor(photo: &Tensor, identity: &Tensor, white_balance: bool) -> Option<[f64; 3]> {
    let mask = calibration_mask(photo);
    let pixels = mask.sum(Kind::Int64).int64_value(&[]);
    if pixels * 100 < mask.numel() as i64 {
        return None;
    }
    let (p, r) = (masked_channel_means(photo, &mask), masked_channel_means(identity, &mask));
    let overall = p.iter().sum::<f64>() / r.iter().sum::<f64>();
    if !(overall.is_finite() && overall > 1.0 / MAX_CALIBRATION && overall < MAX_CALIBRATION) {
        return None;
    }
    if !white_balance {
        return Some([overall; 3]);
    }
    let balanced = [0, 1, 2].map(|c| {
        let f = p[c] / r[c];
        let (lo, hi) = (overall / MAX_CHANNEL_BALANCE, overall * MAX_CHANNEL_BALANCE);
        if f.is_nan() { overall } else { f.clamp(lo, hi) }
    });
    // How far to balance: the strength whose render gives the photo's
    // recorded pixels back best, channel by channel (ties: the weaker).
    let recorded = unclipped_mask(photo);
    let (pk, rk) = (masked_channel_means(photo, &recorded), masked_channel_means(identity, &recorded));
    let at = |t: f64| [0, 1, 2].map(|c| overall * (balanced[c] / overall).powf(t));
    let error = |f: [f64; 3]| (0..3).map(|c| (f[c] * rk[c] / pk[c]).ln().abs()).filter(|e| e.is_finite()).sum::<f64>();
    let best = BALANCE_STRENGTHS.iter().map(|&t| (error(at(t)), t)).fold((f64::INFINITY, 0.0), |a, b| if b.0 < a.0 - 1e-12 { b } else { a });
    Some(at(best.1))
}

/// Strengths of the white balance tried, from one factor for all channels
/// (0) to each channel's own over [`calibration_mask`] (1): the network's
/// colour can be wrong in its diffuse and right in its highlight (or the
/// reverse), and a gain per channel moves both. Balanced fully, the 50
/// held-out materials lost 0.002 Identity LPIPS and 0.006 relit
/// chromaticity, and 4 of the 30 saturated ones up to 0.17 LPIPS
/// (reports/colour.md); the strength whose identity render gives the
/// photo's unclipped pixels back best, channel by channel, is kept.
pub const BALANCE_STRENGTHS: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// How far one channel's calibration factor may stray from the overall
/// one: the saturated orange of issue 69 needed 1 / 9 on blue; a channel the
/// photo holds at 0 is brought this far down and no further.
pub const MAX_CHANNEL_BALANCE: f64 = 16.0;

/// The identity render's mean over the photo's, per channel, over
/// [`calibration_mask`] (NaN where nothing is compared): what the
/// calibration took out, or, after it, how well the material gives its
/// photo back. photo, identity: linear `[3, H, W]`.
pub fn identity_channel_ratios(photo: &Tensor, identity: &Tensor) -> [f64; 3] {
    let mask = calibration_mask(photo);
    let (p, r) = (masked_channel_means(photo, &mask), masked_channel_means(identity, &mask));
    [0, 1, 2].map(|c| r[c] / p[c])
}

/// Per-channel means of `t` `[3, H, W]` (clamped at 0) over the pixels of
/// `mask` `[H, W]` (NaN with no pixel).
fn masked_channel_means(t: &Tensor, mask: &Tensor) -> [f64; 3] {
    let m = mask.unsqueeze(0).to_kind(Kind::Double);
    let sums = (t.to_kind(Kind::Double).clamp_min(0.0) * &m).sum_dim_intlist([1i64, 2].as_slice(), false, Kind::Double);
    let n = m.sum(Kind::Double).double_value(&[]);
    [0, 1, 2].map(|c| sums.double_value(&[c]) / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn photo(f: impl Fn(usize, usize, usize) -> f32) -> Tensor {
        crate::image::Image::from_fn(3, 8, 8, f).to_tensor()
    }

    #[test]
    fn the_level_is_the_median_and_ignores_a_highlight() {
        // 64 pixels: 40 at 0.02, 24 at 0.005 (RGB means); one highlight pixel at
        // 5 (HDR: no clip to respect).
        let p = photo(|c, y, x| if (y, x) == (4, 4) { 5.0 } else if y < 5 { [0.01, 0.02, 0.03][c] } else { 0.005 });
        assert!((photo_level(&p).unwrap() - 0.02).abs() < 1e-7);
        let cfg = ExposureConfig::default();
        assert!((normalizing_scale(&p, &cfg, false) - DEFAULT_MIN_LEVEL / 0.02).abs() < 1e-5);
        // Two stops darker: four times the scale, so the same input for M_est.
        let dark = &p / 4.0;
        assert!((normalizing_scale(&dark, &cfg, false) - 4.0 * normalizing_scale(&p, &cfg, false)).abs() < 1e-4);
        assert_eq!(normalizing_scale(&p, &ExposureConfig::off(), false), 1.0);
        // A photo at or above the minimum level is left as it is.
        assert_eq!(normalizing_scale(&(&p * 6.0), &cfg, false), 1.0);
        assert_eq!(normalizing_scale(&(&p * 50.0), &cfg, false), 1.0);
        // A black photo has no level: left as it is.
        assert_eq!(photo_level(&Tensor::zeros([3, 8, 8], (Kind::Float, Device::Cpu))), None);
        assert_eq!(normalizing_scale(&Tensor::zeros([3, 8, 8], (Kind::Float, Device::Cpu)), &cfg, false), 1.0);
    }

    #[test]
    fn an_ldr_photo_is_lifted_no_further_than_its_highlight_reaches_the_clip() {
        // 64 pixels at 0.01 (RGB mean) with a highlight of 4 pixels at 0.2
        // (green 0.25): the level asks for 10x, the highlight allows 4x.
        let p = photo(|c, y, x| if y == 0 && x < 4 { [0.15, 0.25, 0.2][c] } else { 0.01 });
        assert!((bright_level(&p, 0.0) - 0.25).abs() < 1e-7);
        let cfg = ExposureConfig::default();
        assert!((normalizing_scale(&p, &cfg, true) - 4.0).abs() < 1e-5);
        // HDR input has no clip; nor does a configuration without a share.
        assert!((normalizing_scale(&p, &cfg, false) - 10.0).abs() < 1e-5);
        assert!((normalizing_scale(&p, &ExposureConfig { clip_share: None, ..cfg }, true) - 10.0).abs() < 1e-5);
        // A share above the highlight's 4 of 64 pixels lets them clip.
        assert!((bright_level(&p, 0.1) - 0.01).abs() < 1e-7);
        assert!((normalizing_scale(&p, &ExposureConfig { clip_share: Some(0.1), ..cfg }, true) - 10.0).abs() < 1e-5);
        // Two stops darker: still four times the scale, so the same input for M_est.
        assert!((normalizing_scale(&(&p / 4.0), &cfg, true) - 16.0).abs() < 1e-4);
        // An already clipped photo is not lifted at all.
        let clipped = photo(|_, y, x| if y == 0 && x < 4 { 1.0 } else { 0.01 });
        assert_eq!(normalizing_scale(&clipped, &cfg, true), 1.0);
        assert!(ExposureConfig { clip_share: Some(1.0), ..cfg }.validate().is_err());
    }

    #[test]
    fn lifts_are_tried_between_the_clip_and_the_level() {
        // The photo of the clip test: the clip allows 4x, the level asks for 10x.
        let p = photo(|c, y, x| if y == 0 && x < 4 { [0.15, 0.25, 0.2][c] } else { 0.01 });
        let cfg = ExposureConfig::default();
        let s = candidate_scales(&p, &cfg, true);
        assert_eq!(s.len(), 3);
        for (a, b) in s.iter().zip([4.0, 40f64.sqrt(), 10.0]) {
            assert!((a - b).abs() < 1e-5, "{s:?}");
        }
        // Nothing to choose: no clip in the way, no calibration, one candidate.
        assert_eq!(candidate_scales(&p, &cfg, false).len(), 1);
        assert_eq!(candidate_scales(&p, &ExposureConfig { calibrate: false, ..cfg }, true), vec![s[0]]);
        assert_eq!(candidate_scales(&p, &ExposureConfig { lift_candidates: 1, ..cfg }, true), vec![s[0]]);
        assert!(ExposureConfig { lift_candidates: 0, ..cfg }.validate().is_err());
        // A photo already clipped gets no lift at all.
        let clipped = photo(|_, y, x| if y == 0 && x < 4 { 1.0 } else { 0.01 });
        assert_eq!(candidate_scales(&clipped, &cfg, true), vec![1.0]);
        // Two stops darker: every candidate four times larger.
        for (a, b) in candidate_scales(&(&p / 4.0), &cfg, true).iter().zip(&s) {
            assert!((a - 4.0 * b).abs() < 1e-4);
        }
    }

    #[test]
    fn the_identity_error_counts_the_unclipped_highlight_and_ignores_the_exposure() {
        // Photo mean (63 x 0.02 + 0.5) / 64; a render right outside the
        // highlight and at 1.5 in it: mean (63 x 0.02 + 1.5) / 64.
        let p = photo(|_, y, x| if (y, x) == (0, 0) { 0.5 } else { 0.02 });
        let r = photo(|_, y, x| if (y, x) == (0, 0) { 1.5 } else { 0.02 });
        let want = (2.76f64 / 1.76).ln();
        let e = identity_error(&p, &r);
        assert!((e - want).abs() < 1e-6, "{e} vs {want}");
        let (half, twice) = (identity_error(&p, &(&p * 0.5)), identity_error(&p, &(&p * 2.0)));
        assert!((half - 2f64.ln()).abs() < 1e-6 && (twice - 2f64.ln()).abs() < 1e-6, "too dark counts as much as too bright: {half}, {twice}");
        assert_eq!(identity_error(&p, &p), 0.0);
        assert!((identity_error(&(&p / 8.0), &(&r / 8.0)) - e).abs() < 1e-9);
        // A clipped pixel is left out: no error with the highlight at 1 and drawn at 3.
        let clipped = photo(|_, y, x| if (y, x) == (0, 0) { 1.0 } else { 0.02 });
        let r2 = photo(|_, y, x| if (y, x) == (0, 0) { 3.0 } else { 0.02 });
        assert!(identity_error(&clipped, &r2) < 1e-9);
        assert_eq!(identity_error(&photo(|_, _, _| 1.0), &r2), f64::INFINITY);
        assert_eq!(identity_error(&p, &(&r * 0.0)), f64::INFINITY);
    }

    #[test]
    fn calibration_compares_the_unclipped_pixels_outside_the_highlight() {
        // Photo: 0.2 everywhere, a clipped highlight (1.0) in the top row.
        let p = photo(|_, y, _| if y == 0 { 1.0 } else { 0.2 });
        let mask = calibration_mask(&p);
        assert_eq!(mask.sum(Kind::Int64).int64_value(&[]), 56);
        // The render is half the photo where it counts and 10x in the
        // highlight: the factor is 2, whatever the highlight does.
        let r = photo(|_, y, _| if y == 0 { 10.0 } else { 0.1 });
        for f in calibration_factor(&p, &r, true).unwrap() {
            assert!((f - 2.0).abs() < 1e-9);
        }
        // A bright unclipped pixel above 2x the median is highlight too.
        let p2 = photo(|_, y, x| if (y, x) == (3, 3) { 0.5 } else { 0.2 });
        assert_eq!(calibration_mask(&p2).sum(Kind::Int64).int64_value(&[]), 63);
        // Untrustworthy: a black render, or a factor beyond the bound.
        assert_eq!(calibration_factor(&p, &Tensor::zeros([3, 8, 8], (Kind::Float, Device::Cpu)), true), None);
        assert_eq!(calibration_factor(&p, &(&r * 0.01), true), None);
        // All pixels clipped: nothing to compare.
        assert_eq!(calibration_factor(&photo(|_, _, _| 1.0), &r, true), None);
    }

    /// A render that adds blue where the photo has little: the factors
    /// balance each channel on its own (hand-derived ratios), the overall
    /// bound still refuses, and a channel the photo holds at 0 is brought
    /// down no further than [`MAX_CHANNEL_BALANCE`].
    #[test]
    fn calibration_balances_each_channel() {
        // Photo orange (0.4, 0.2, 0.01); the render (0.2, 0.2, 0.09).
        let p = photo(|c, _, _| [0.4, 0.2, 0.01][c]);
        let r = photo(|c, _, _| [0.2, 0.2, 0.09][c]);
        let f = calibration_factor(&p, &r, true).unwrap();
        for (a, b) in f.iter().zip([2.0, 1.0, 0.01 / 0.09]) {
            assert!((a - b).abs() < 1e-6, "{f:?}");
        }
        let before = identity_channel_ratios(&p, &r);
        for (a, b) in before.iter().zip([0.5, 1.0, 9.0]) {
            assert!((a - b).abs() < 1e-5, "{before:?}");
        }
        let balanced = &r * Tensor::from_slice(&f).to_kind(Kind::Float).view([3, 1, 1]);
        for ratio in identity_channel_ratios(&p, &balanced) {
            assert!((ratio - 1.0).abs() < 1e-5);
        }
        // No blue at all in the photo: the overall factor 0.61 / 0.49 over 16.
        let black_blue = photo(|c, _, _| [0.4, 0.2, 0.0][c]);
        let f = calibration_factor(&black_blue, &r, true).unwrap();
        assert!((f[2] - 0.6 / 0.49 / MAX_CHANNEL_BALANCE).abs() < 1e-6, "{f:?}");
        // Without the white balance: one factor, of the RGB means (0.61 / 0.49).
        for f in calibration_factor(&p, &r, false).unwrap() {
            assert!((f - 0.61 / 0.49).abs() < 1e-6, "{f}");
        }
        // Too red where the mask looks (48 pixels at 0.02, render R 0.03),
        // too dull in red and too bright in green and blue in the unclipped
        // highlight, which carries most of the light (16 pixels at 0.9,
        // render (0.6, 1, 1)). Over the recorded pixels the render is
        // (0.719, 1.104, 1.104) x the photo; the mask's factors are
        // (2/3, 1, 1) x 7/6 of the overall 6/7. Summed |ln| errors by hand:
        // strength 0: 0.484 + 2 x 0.055 = 0.594; 0.25: 0.547 + 2 x 0.017 =
        // 0.581; 0.5: 0.610 + 2 x 0.022 = 0.653; 1: 0.735 + 2 x 0.099 = 0.933.
        let hp = photo(|_, y, _| if y < 6 { 0.02 } else { 0.9 });
        let hr = photo(|c, y, _| if y < 6 { [0.03, 0.02, 0.02][c] } else { [0.6, 1.0, 1.0][c] });
        let f = calibration_factor(&hp, &hr, true).unwrap();
        let overall = 0.06 / 0.07;
        let want = [2.0 / 3.0, 1.0, 1.0].map(|b: f64| overall * (b / overall).powf(0.25));
        assert!(f.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6), "{f:?} vs {want:?}");
        // A render nine times too dark overall is still refused.
        assert_eq!(calibration_factor(&p, &(&r / 12.0), true), None);
    }

    /// The check's ratios by hand: the clipped pixel is left out, the
    /// highlight counted; the line shows them to two decimals.
    #[test]
    fn the_identity_check_compares_the_unclipped_pixels() {
        // 63 pixels at (0.2, 0.1, 0.05) and one clipped; the render is
        // (0.2, 0.1, 0.1) there and 5 on the clipped pixel.
        let p = photo(|c, y, x| if (y, x) == (0, 0) { 1.0 } else { [0.2, 0.1, 0.05][c] });
        let r = photo(|c, y, x| if (y, x) == (0, 0) { 5.0 } else { [0.2, 0.1, 0.1][c] });
        let check = IdentityCheck::measure(&p, &r).unwrap();
        assert!((check.brightness - 0.4 / 0.35).abs() < 1e-6, "{check:?}");
        for (a, b) in check.rgb.iter().zip([1.0, 1.0, 2.0]) {
            assert!((a - b).abs() < 1e-6, "{check:?}");
        }
        assert_eq!(check.summary(), "identity render over the photo: brightness 1.14, R / G / B 1.00 / 1.00 / 2.00");
        // No blue in the photo: that ratio is shown as unknown.
        let no_blue = photo(|c, _, _| [0.2, 0.1, 0.0][c]);
        let line = IdentityCheck::measure(&no_blue, &photo(|c, _, _| [0.2, 0.1, 0.1][c])).unwrap().summary();
        assert!(line.ends_with("1.00 / 1.00 / -"), "{line}");
        assert_eq!(IdentityCheck::measure(&photo(|_, _, _| 1.0), &r), None);
    }

    #[test]
    fn minimum_levels_are_checked() {
        assert!(ExposureConfig::default().validate().is_ok());
        for bad in [0.0, -0.1, 1.5, f64::NAN] {
            assert!(ExposureConfig { min_level: bad, ..Default::default() }.validate().is_err(), "{bad}");
        }
    }
}
