//! The frame as a light meter. The white paper between the opening and
//! the tags is in every photo, lit by the same flash, at places the fitted
//! poses know: its linear level over the flash's irradiance there
//! (cos / r^2, the paper being matte) is the photo's exposure times its
//! white balance, per channel. Over the overhead photo's, that puts every
//! photo of a capture on one photometric scale, whatever the phone's auto
//! exposure and auto white balance did (`exposures.txt`, three numbers a
//! photo). Across the paper the irradiance varies (more in tilted photos),
//! so the same samples also check the response: in a linear photo under
//! the flash the paper's log level follows the log irradiance with slope
//! 1; tone mapping flattens it, and a photo without flash has none.

use super::{rectify::Pixels, FramePhoto, PhotoResult};
use crate::geometry::{length, sub};

/// Paper samples along each side of the opening's margin.
const SAMPLES_PER_SIDE: usize = 24;
/// Fewer unclipped paper samples than this and a photo has no reading.
pub const MIN_PAPER_SAMPLES: usize = 24;
/// An 8-bit code at or above this (any channel) is too near clipping to
/// measure; a RAW value likewise, over 255.
const CLIP_CODE: u8 = 250;
/// The response slope is stated only where the log irradiance over the
/// samples spreads at least this much (standard deviation; 0.05 is about
/// 5%): straight overhead the paper is lit almost evenly.
const MIN_LOG_SPREAD: f64 = 0.05;
/// A response slope outside 1 +- this is warned about.
pub const SLOPE_TOLERANCE: f64 = 0.3;
/// The photos' stated response slopes must agree within this for the
/// capture's tone curve to be corrected (one curve for all of them).
const SLOPE_AGREEMENT: f64 = 0.05;
/// A median response slope within this of 1 is an sRGB photo's (a clean
/// photo's slope measures within 0.01 of 1).
const LINEAR_RESPONSE: f64 = 0.03;
/// Measured exposures within this of the overhead photo's (relative, every
/// channel) are one exposure: no `exposures.txt`.
pub const SAME_EXPOSURE: f64 = 0.03;

/// How an 8-bit photo's codes are read as linear light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ToneCurve {
    /// The sRGB curve (what a phone's JPEG states).
    Srgb,
    /// A pure power: linear = (code / 255)^gamma (a display gamma of 2.2
    /// or 2.4 without sRGB's linear toe; 1: the codes themselves).
    Power(f64),
}

impl ToneCurve {
    /// Linear light of a code in [0, 1].
    pub fn decode(self, code: f64) -> f64 {
        match self {
            ToneCurve::Srgb => crate::spaces::photo_decode(code as f32) as f64,
            ToneCurve::Power(gamma) => code.powf(gamma),
        }
    }
}

/// What a photo's paper says.
#[derive(Clone, Debug, PartialEq)]
pub struct PaperReading {
    /// Median over the samples of the paper's linear R, G, B over the
    /// flash's irradiance (cos / r^2, r in metres): the photo's exposure
    /// times its white balance, in one unit for all photos.
    pub level: [f64; 3],
    /// Unclipped samples on the photo.
    pub samples: usize,
    /// Slope of the paper's log grey level against the log irradiance (1
    /// for a linear photo under the flash); None where the irradiance
    /// varies too little over the samples to say.
    pub response_slope: Option<f64>,
}

/// Points in the middle of the white margin between the opening and the
/// tags' black squares, mm in the frame's axes, around all four sides.
fn paper_points(margin_centre_mm: f64) -> Vec<[f64; 2]> {
    let d = margin_centre_mm;
    (0..SAMPLES_PER_SIDE)
        .flat_map(|k| {
            // Away from the corners, where two sides' tags come close.
            let s = -d * 0.9 + 1.8 * d * (k as f64 + 0.5) / SAMPLES_PER_SIDE as f64;
            [[s, -d], [d, s], [-s, d], [-d, -s]]
        })
        .collect()
}

/// Reads the paper of one photo whose pose and light `result` has; an
/// 8-bit photo's codes read through `curve`.
pub fn read_paper(photo: &FramePhoto, result: &PhotoResult, margin_centre_mm: f64, curve: ToneCurve) -> PaperReading {
    let pixels = match &photo.raw {
        Some(raw) => Pixels::Linear(&raw.linear),
        None => Pixels::Coded(&photo.rgb),
    };
    let (w, h) = (photo.rgb.width as f64, photo.rgb.height as f64);
    let mut ratios: [Vec<f64>; 3] = Default::default();
    let mut logs: Vec<(f64, f64)> = Vec::new();
    for p in paper_points(margin_centre_mm) {
        let Some(px) = result.pose.project(&result.intrinsics, [p[0], p[1], 0.0]) else { continue };
        if !(2.0..w - 2.0).contains(&px[0]) || !(2.0..h - 2.0).contains(&px[1]) {
            continue;
        }
        let Some(rgb) = value_at(&pixels, px) else { continue };
        let rgb = match pixels {
            Pixels::Coded(_) => rgb.map(|code| curve.decode(code)),
            Pixels::Linear(_) => rgb,
        };
        let to_light = sub(result.light, [p[0], p[1], 0.0]);
        let r = length(to_light) / 1000.0;
        let irradiance = (to_light[2] / 1000.0 / r) / (r * r);
        if irradiance <= 0.0 || rgb.iter().any(|&v| v <= 0.0) {
            continue;
        }
        for c in 0..3 {
            ratios[c].push(rgb[c] / irradiance);
        }
        logs.push((irradiance.ln(), (rgb.iter().sum::<f64>() / 3.0).ln()));
    }
    let level = ratios.map(|mut v| median(&mut v));
    PaperReading { level, samples: logs.len(), response_slope: slope(&logs) }
}

/// A photo's RGB at a pixel position (centres at +0.5), bilinear: an
/// 8-bit photo's codes in [0, 1], a RAW photo's linear values; None where
/// any of the four pixels is near clipping.
fn value_at(pixels: &Pixels, p: [f64; 2]) -> Option<[f64; 3]> {
    let (x, y) = (p[0] - 0.5, p[1] - 0.5);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let at = |xi: usize, yi: usize| -> Option<[f64; 3]> {
        match pixels {
            Pixels::Coded(photo) => {
                let o = (yi * photo.width + xi) * 3;
                let codes = &photo.data[o..o + 3];
                (codes.iter().all(|&c| c < CLIP_CODE)).then(|| std::array::from_fn(|c| codes[c] as f64 / 255.0))
            }
            Pixels::Linear(image) => {
                let v: [f64; 3] = std::array::from_fn(|c| image.get(c, yi, xi) as f64);
                v.iter().all(|&v| v < CLIP_CODE as f64 / 255.0).then_some(v)
            }
        }
    };
    let (a, b, c, d) = (at(x0, y0)?, at(x0 + 1, y0)?, at(x0, y0 + 1)?, at(x0 + 1, y0 + 1)?);
    Some(std::array::from_fn(|i| (a[i] * (1.0 - fx) + b[i] * fx) * (1.0 - fy) + (c[i] * (1.0 - fx) + d[i] * fx) * fy))
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// Least-squares slope of y on x over `(x, y)` pairs; None when x spreads
/// less than [`MIN_LOG_SPREAD`].
fn slope(points: &[(f64, f64)]) -> Option<f64> {
    let n = points.len() as f64;
    if points.len() < 3 {
        return None;
    }
    let (mx, my) = (points.iter().map(|p| p.0).sum::<f64>() / n, points.iter().map(|p| p.1).sum::<f64>() / n);
    let sxx = points.iter().map(|p| (p.0 - mx).powi(2)).sum::<f64>();
    let sxy = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum::<f64>();
    ((sxx / n).sqrt() >= MIN_LOG_SPREAD).then(|| sxy / sxx)
}

/// Whether the paper says the capture's photos share a tone curve that is
/// not sRGB: the median of the photos' response slopes as read through
/// sRGB (a phone's pure gamma of 2.4 reads about 0.92), when at least two
/// photos state one, all within [`SLOPE_TOLERANCE`] of 1 (a tone-mapped
/// photo is warned about instead) and within [`SLOPE_AGREEMENT`] of each
/// other (one curve for the capture), and it is more than
/// [`LINEAR_RESPONSE`] from 1; None otherwise.
pub fn srgb_mismatch(readings: &[PaperReading]) -> Option<f64> {
    let mut slopes: Vec<f64> = readings.iter().filter_map(|r| r.response_slope).collect();
    if slopes.len() < 2 || slopes.iter().any(|s| (s - 1.0).abs() > SLOPE_TOLERANCE) {
        return None;
    }
    let spread = slopes.iter().cloned().fold(f64::NEG_INFINITY, f64::max) - slopes.iter().cloned().fold(f64::INFINITY, f64::min);
    let k = median(&mut slopes);
    (spread <= SLOPE_AGREEMENT && (k - 1.0).abs() > LINEAR_RESPONSE).then_some(k)
}

/// The gamma of a pure power curve that makes the paper linear: readings
/// of the photos' codes as they are ([`ToneCurve::Power`] of 1) follow
/// the light with slope 1 / gamma. The median over the photos that state
/// a slope (at least two), None otherwise. A pure power is the curve a
/// phone that does not write sRGB most often has (a display gamma), and
/// unlike a power on top of sRGB it is exact from black to white: sRGB's
/// linear toe makes a 2.4 gamma's dark codes read up to twice as bright.
pub fn power_gamma(code_readings: &[PaperReading]) -> Option<f64> {
    let mut slopes: Vec<f64> = code_readings.iter().filter_map(|r| r.response_slope).filter(|s| *s > 0.0).collect();
    (slopes.len() >= 2).then(|| 1.0 / median(&mut slopes))
}

/// Each photo's exposure per channel relative to `readings[0]`'s (the
/// overhead photo's), when every photo has a reading; None otherwise.
pub fn relative_levels(readings: &[PaperReading]) -> Option<Vec<[f64; 3]>> {
    let first = readings.first()?;
    if readings.iter().any(|r| r.samples < MIN_PAPER_SAMPLES || r.level.iter().any(|v| !v.is_finite() || *v <= 0.0)) {
        return None;
    }
    Some(readings.iter().map(|r| std::array::from_fn(|c| r.level[c] / first.level[c])).collect())
}

/// Whether relative levels differ from one exposure by more than [`SAME_EXPOSURE`].
pub fn levels_differ(levels: &[[f64; 3]]) -> bool {
    levels.iter().flatten().any(|v| (v - 1.0).abs() > SAME_EXPOSURE)
}

/// Warnings naming the photo, one per photo at most: its paper does not
/// follow the flash's fall-off (tone mapping, no flash), or too little of
/// it could be read (clipped, off the photo).
pub fn warnings(results: &[PhotoResult], readings: &[PaperReading]) -> Vec<String> {
    let name = |p: &PhotoResult| p.source.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    results
        .iter()
        .zip(readings)
        .filter_map(|(p, r)| {
            if r.samples < MIN_PAPER_SAMPLES {
                return Some(format!(
                    "{}: only {} of the frame's paper samples could be read (clipped or off the photo), too few to measure its exposure and white balance: lower the exposure, or keep the whole frame in view",
                    name(p),
                    r.samples
                ));
            }
            let s = r.response_slope?;
            ((s - 1.0).abs() > SLOPE_TOLERANCE).then(|| {
                format!(
                    "{}: the frame's paper does not brighten with the flash's light as a linear photo's does (slope {s:.2}, 1 expected): the phone tone-mapped it, or the flash did not fire; turn off HDR, or shoot RAW",
                    name(p)
                )
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_curve_for_the_capture_is_read_from_agreeing_slopes() {
        let r = |s: Option<f64>| PaperReading { level: [1.0; 3], samples: 96, response_slope: s };
        // Gamma 2.4 read as 2.2, stated by the two tilted photos.
        assert_eq!(srgb_mismatch(&[r(None), r(Some(0.91)), r(Some(0.93))]), Some(0.92));
        // A linear capture, one photo's word, photos that disagree, a tone-mapped photo: no correction.
        assert_eq!(srgb_mismatch(&[r(None), r(Some(0.99)), r(Some(1.01))]), None);
        assert_eq!(srgb_mismatch(&[r(None), r(Some(0.9)), r(None)]), None);
        assert_eq!(srgb_mismatch(&[r(None), r(Some(0.85)), r(Some(0.95))]), None);
        assert_eq!(srgb_mismatch(&[r(Some(0.92)), r(Some(0.92)), r(Some(0.5))]), None);
    }

    #[test]
    fn a_pure_power_is_read_from_the_codes_slopes() {
        let r = |s: Option<f64>| PaperReading { level: [1.0; 3], samples: 96, response_slope: s };
        // Codes of a 2.4 gamma follow the light with slope 1 / 2.4 (the overhead photo states none).
        let gamma = power_gamma(&[r(None), r(Some(1.0 / 2.4)), r(Some(1.0 / 2.4))]).unwrap();
        assert!((gamma - 2.4).abs() < 1e-12, "{gamma}");
        assert_eq!(power_gamma(&[r(None), r(Some(0.4)), r(None)]), None);
        // 0.5^2.4 = 0.189465; sRGB's 0.5 is 0.214041.
        assert!((ToneCurve::Power(2.4).decode(0.5) - 0.189_465).abs() < 1e-6);
        assert!((ToneCurve::Srgb.decode(0.5) - 0.214_041).abs() < 1e-6);
    }

    #[test]
    fn the_slope_is_the_exponent_and_is_withheld_on_even_light() {
        // y = 0.6 x + 2 over a 20% spread of x: slope 0.6.
        let pts: Vec<(f64, f64)> = (0..10).map(|i| (0.02 * i as f64, 0.6 * 0.02 * i as f64 + 2.0)).collect();
        assert!((slope(&pts).unwrap() - 0.6).abs() < 1e-12);
        // A 1% spread says nothing.
        let flat: Vec<(f64, f64)> = (0..10).map(|i| (0.001 * i as f64, 0.0)).collect();
        assert_eq!(slope(&flat), None);
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0]), 2.5);
    }

    #[test]
    fn levels_are_relative_to_the_overhead_photo_and_need_every_reading() {
        let r = |level: [f64; 3], samples| PaperReading { level, samples, response_slope: Some(1.0) };
        let readings = [r([0.4, 0.5, 0.6], 90), r([0.2, 0.5, 0.9], 90)];
        let levels = relative_levels(&readings).unwrap();
        assert_eq!(levels, [[1.0, 1.0, 1.0], [0.5, 1.0, 1.5]]);
        assert!(levels_differ(&levels) && !levels_differ(&[[1.0, 1.02, 0.98]]));
        assert_eq!(relative_levels(&[r([0.4, 0.5, 0.6], 90), r([0.4, 0.5, 0.6], 3)]), None);
    }
}
