//! The exposure curve (issue 53): the same material photographed at other
//! exposures should come back at the photo's brightness. For each exposure
//! EV the photo is the linear co-located render times 2^EV, clamped to
//! [0, 1] after the scaling when photos are 8-bit (so clipping happens where
//! a camera's would); each method estimates from it and renders
//!
//! - the identity (the photo's own light and camera): the **identity
//!   ratio** is the render's mean over the photo's, per channel and over
//!   all three, both unclamped: the photo's is the linear render x 2^EV
//!   before the clamp, which is the photo wherever it is not clipped.
//!   (Clamping the render too would hide a highlight drawn five times too
//!   bright under 1; on a clipped photo the ratio says how much of what the
//!   clip hid the method brings back.);
//! - the moved lights of the highlight test: the **relit scale** is the
//!   mean of those renders at EV over their mean at 0 stops, over 2^EV
//!   (1: the material scales with the photo's exposure).
//!
//! A photo with any channel of any pixel at 1 is **clipped**: its
//! highlight is cut and the ratio is a different question (the highlight
//! issue); the summary reports clipped photos apart (for the relit scale,
//! pairs where either photo is clipped), with a second ratio over the
//! pixels the photo kept: whether the method got the exposure of what the
//! camera did record.

use super::methods::Method;
use crate::geometry::{LightView, MODEL_FOV_DEG};
use anyhow::{ensure, Result};
use serde::Serialize;
use std::fmt::Write as _;
use tch::{Kind, Tensor};

/// Exposures scored by default: the identity ratio at the photo's own
/// exposure (cheap: the prepared material of the main evaluation).
pub const DEFAULT_EXPOSURES: [f64; 1] = [0.0];

/// An identity ratio inside this range counts as right (the target).
pub const RATIO_TARGET: (f64, f64) = (0.85, 1.2);

/// The photo of a material at `ev` stops: its linear co-located photo
/// `[3, H, W]` times 2^ev, clamped to [0, 1] when `ldr`.
pub fn exposed(photo_linear: &Tensor, ev: f64, ldr: bool) -> Tensor {
    let scaled = photo_linear * 2f64.powf(ev);
    if ldr {
        crate::spaces::ldr_clamp(&scaled)
    } else {
        scaled
    }
}

/// Fraction of pixels with a channel at 1 or above. photo: `[3, H, W]`.
pub fn clipped_fraction(photo: &Tensor) -> f64 {
    let s = photo.size();
    let any = photo.ge(1.0).any_dim(0, false);
    any.to_kind(Kind::Double).sum(Kind::Double).double_value(&[]) / (s[1] * s[2]).max(1) as f64
}

/// Mean per channel of a `[3, H, W]` or `[K, 3, H, W]` image.
fn channel_means(t: &Tensor) -> [f64; 3] {
    let flat = if t.dim() == 4 { t.transpose(0, 1).reshape([3, -1]) } else { t.reshape([3, -1]) };
    let m = flat.to_kind(Kind::Double).mean_dim([1i64].as_slice(), false, Kind::Double);
    [0, 1, 2].map(|c| m.double_value(&[c]))
}

/// One method on one material at one exposure.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ExposureRow {
    pub material: String,
    pub ev: f64,
    /// [`clipped_fraction`] of the photo.
    pub clipped: f64,
    /// Identity render's mean over the photo's, per channel.
    pub ratio_rgb: [f64; 3],
    /// The same of the RGB means.
    pub ratio: f64,
    /// The same over the pixels not clipped in the photo (= `ratio` on an
    /// unclipped photo; NaN when every pixel is clipped).
    pub ratio_kept: f64,
    /// `ratio_kept` per channel: the colour of what the camera recorded
    /// (issue 69's white balance target).
    pub ratio_kept_rgb: [f64; 3],
    /// Moved lights' mean at EV over at 0 stops, over 2^EV; `None` at 0.
    pub relit_scale: Option<f64>,
    /// The 0-stop photo's [`clipped_fraction`] (the relit scale's reference).
    pub reference_clipped: f64,
}

/// The identity ratio of a prepared method: per channel, of the RGB means,
/// and of the RGB means and per channel over the pixels `photo` does not
/// clip (NaN when it clips all). exposed_truth: `[3, H, W]`, the linear
/// co-located render x 2^EV, unclamped; photo: the same as the method saw it.
pub fn identity_ratio(method: &dyn Method, exposed_truth: &Tensor, photo: &Tensor) -> Result<([f64; 3], f64, f64, [f64; 3])> {
    let render = method.render(&[LightView::colocated(MODEL_FOV_DEG)])?.get(0).clamp_min(0.0);
    let truth = exposed_truth.to_device(tch::Device::Cpu).to_kind(Kind::Float);
    let (r, p) = (channel_means(&render), channel_means(&truth));
    let rgb = [0, 1, 2].map(|c| r[c] / p[c].max(1e-12));
    let all = r.iter().sum::<f64>() / p.iter().sum::<f64>().max(1e-12);
    let kept = photo.to_device(tch::Device::Cpu).lt(1.0).all_dim(0, true).to_kind(Kind::Double); // [1, H, W]
    let masked_sum = |t: &Tensor| f64::try_from((t.to_kind(Kind::Double) * &kept).sum(Kind::Double)).unwrap_or(f64::NAN);
    let kept_ratio = masked_sum(&render) / masked_sum(&truth);
    let kept_rgb = [0, 1, 2].map(|c| {
        let r = masked_sum(&render.get(c).unsqueeze(0)) / masked_sum(&truth.get(c).unsqueeze(0));
        if r.is_finite() { r } else { f64::NAN }
    });
    Ok((rgb, all, if kept_ratio.is_finite() { kept_ratio } else { f64::NAN }, kept_rgb))
}

/// Scores one method on one material at every exposure. photo_linear:
/// the unclamped co-located render `[3, H, W]`; `moved`: the moved
/// configurations of the relit scale. `at_zero`: the method's renders
/// `[L, 3, H, W]` under `moved` from the 0-stop photo when the caller has
/// them with the method still prepared on that photo (then 0 is scored
/// first, without preparing again). The method is left prepared on the
/// last exposure's photo.
pub fn measure(method: &mut dyn Method, material: &str, photo_linear: &Tensor, exposures: &[f64], ldr: bool, moved: &[LightView], at_zero: Option<&Tensor>) -> Result<Vec<ExposureRow>> {
    ensure!(exposures.contains(&0.0), "the exposures must include 0 (the relit scale's reference)");
    let zero_photo = exposed(photo_linear, 0.0, ldr);
    let reference_clipped = clipped_fraction(&zero_photo);
    // 0 first: the reference of the relit scale.
    let mut order: Vec<f64> = vec![0.0];
    order.extend(exposures.iter().copied().filter(|&e| e != 0.0));
    let mut reference: Option<[f64; 3]> = None;
    let mut rows = Vec::with_capacity(order.len());
    for ev in order {
        let photo = exposed(photo_linear, ev, ldr);
        let relit = match (ev == 0.0, at_zero) {
            (true, Some(r)) => r.shallow_clone(),
            _ => {
                method.prepare(&photo)?;
                method.render(moved)?
            }
        };
        let means = channel_means(&relit.clamp_min(0.0));
        let (ratio_rgb, ratio, ratio_kept, ratio_kept_rgb) = identity_ratio(method, &exposed(photo_linear, ev, false), &photo)?;
        let relit_scale = match reference {
            None => {
                reference = Some(means);
                None
            }
            Some(r) => Some(means.iter().sum::<f64>() / r.iter().sum::<f64>().max(1e-12) / 2f64.powf(ev)),
        };
        rows.push(ExposureRow { material: material.to_string(), ev, clipped: clipped_fraction(&photo), ratio_rgb, ratio, ratio_kept, ratio_kept_rgb, relit_scale, reference_clipped });
    }
    // Back in the order asked for.
    rows.sort_by(|a, b| {
        let pos = |ev: f64| exposures.iter().position(|&e| e == ev).unwrap_or(usize::MAX);
        pos(a.ev).cmp(&pos(b.ev))
    });
    Ok(rows)
}

/// Geometric mean, min and max of positive values (NaN for none).
pub fn geo_min_max(values: &[f64]) -> (f64, f64, f64) {
    let v: Vec<f64> = values.iter().copied().filter(|v| *v > 0.0 && v.is_finite()).collect();
    if v.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    (crate::eval::metrics::geometric_mean(&v), v.iter().copied().fold(f64::INFINITY, f64::min), v.iter().copied().fold(f64::NEG_INFINITY, f64::max))
}

/// CSV of every method's rows: `method,material,ev,clipped,ratio,ratio_r,
/// ratio_g,ratio_b,relit_scale,reference_clipped,ratio_kept,ratio_kept_r,
/// ratio_kept_g,ratio_kept_b`.
pub fn csv_text(methods: &[(String, Vec<ExposureRow>)]) -> String {
    let mut s = String::from("method,material,ev,clipped,ratio,ratio_r,ratio_g,ratio_b,relit_scale,reference_clipped,ratio_kept,ratio_kept_r,ratio_kept_g,ratio_kept_b\n");
    for (name, rows) in methods {
        for r in rows {
            let _ = writeln!(
                s,
                "{name},{},{},{:.6},{:.5},{:.5},{:.5},{:.5},{},{:.6},{:.5},{:.5},{:.5},{:.5}",
                r.material,
                r.ev,
                r.clipped,
                r.ratio,
                r.ratio_rgb[0],
                r.ratio_rgb[1],
                r.ratio_rgb[2],
                r.relit_scale.map_or(String::new(), |v| format!("{v:.5}")),
                r.reference_clipped,
                r.ratio_kept,
                r.ratio_kept_rgb[0],
                r.ratio_kept_rgb[1],
                r.ratio_kept_rgb[2]
            );
        }
    }
    s
}

fn gmm(values: &[f64]) -> String {
    if values.is_empty() {
        return "-".into();
    }
    let (g, lo, hi) = geo_min_max(values);
    format!("{g:.2} [{lo:.2}, {hi:.2}]")
}

/// The summary section: per method and exposure, the identity ratio and
/// the relit scale over unclipped photos (geometric mean [min, max]) and
/// the same over clipped ones.
pub fn markdown(methods: &[(String, Vec<ExposureRow>)], ldr: bool) -> String {
    let mut s = String::from("## Exposure (issue 53)\n\n");
    let _ = writeln!(
        s,
        "The photo is the linear co-located render x 2^EV{}. Identity ratio: mean of the identity render over the photo's before the clamp{} (RGB means; per channel in exposure/curve.csv). \
         Relit scale: mean of the renders under the moved-highlight lights at EV over at 0 stops, over 2^EV (1 = scales with the exposure). \
         Cells: geometric mean [min, max] over materials; a photo with any pixel at 1 is clipped and counted apart (for the relit scale: either photo), with the identity ratio also over the pixels it kept (kept pixels). \
         Target: identity ratio within {}-{}.\n",
        if ldr { ", then clamped to [0, 1] (8-bit)" } else { " (HDR: nothing clips)" },
        if ldr { " (on a clipped photo: how much of what the clip hid comes back)" } else { "" },
        RATIO_TARGET.0,
        RATIO_TARGET.1
    );
    let _ = writeln!(s, "| Method | EV | unclipped photos | identity ratio | in target | R / G / B (geo) | relit scale | clipped photos | identity ratio (clipped) | kept pixels (clipped) | relit scale (clipped) |\n|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, rows) in methods {
        let mut evs: Vec<f64> = vec![];
        for r in rows {
            if !evs.contains(&r.ev) {
                evs.push(r.ev);
            }
        }
        for ev in evs {
            let at: Vec<&ExposureRow> = rows.iter().filter(|r| r.ev == ev).collect();
            let (clean, clipped): (Vec<&ExposureRow>, Vec<&ExposureRow>) = at.iter().partition(|r| r.clipped == 0.0);
            let ratios = |v: &[&ExposureRow]| v.iter().map(|r| r.ratio).collect::<Vec<f64>>();
            let scale_clean: Vec<f64> = at.iter().filter(|r| r.clipped == 0.0 && r.reference_clipped == 0.0).filter_map(|r| r.relit_scale).collect();
            let scale_clipped: Vec<f64> = at.iter().filter(|r| r.clipped > 0.0 || r.reference_clipped > 0.0).filter_map(|r| r.relit_scale).collect();
            let in_target = clean.iter().filter(|r| (RATIO_TARGET.0..=RATIO_TARGET.1).contains(&r.ratio)).count();
            let rgb = [0, 1, 2].map(|c| geo_min_max(&clean.iter().map(|r| r.ratio_rgb[c]).collect::<Vec<_>>()).0);
            let rgb = if clean.is_empty() { "-".into() } else { format!("{:.2} / {:.2} / {:.2}", rgb[0], rgb[1], rgb[2]) };
            let scale = |v: &[f64]| if ev == 0.0 { "(reference)".to_string() } else { gmm(v) };
            // Over the pixels the clipped photos kept: geometric mean [min, max] (in target / of them).
            let kept_values: Vec<f64> = clipped.iter().map(|r| r.ratio_kept).filter(|v| v.is_finite()).collect();
            let kept_in = kept_values.iter().filter(|v| (RATIO_TARGET.0..=RATIO_TARGET.1).contains(*v)).count();
            let kept = if kept_values.is_empty() { "-".to_string() } else { format!("{} ({kept_in}/{})", gmm(&kept_values), kept_values.len()) };
            let _ = writeln!(
                s,
                "| {name} | {ev:+} | {} | {} | {in_target}/{} | {rgb} | {} | {} | {} | {kept} | {} |",
                clean.len(),
                gmm(&ratios(&clean)),
                clean.len(),
                scale(&scale_clean),
                clipped.len(),
                gmm(&ratios(&clipped)),
                scale(&scale_clipped)
            );
        }
    }
    s.push_str(&colour_markdown(methods));
    s
}

/// A channel of one material is off when its kept-pixel ratio leaves this
/// band (issue 69: no material's channel off by more than 10%).
pub const CHANNEL_TOLERANCE: f64 = 0.10;

/// The colour table (issue 69): per method and exposure, the identity
/// render's mean over the photo's per channel over the pixels each photo
/// kept, geometric mean over all photos, the largest |ratio - 1| of any
/// channel, and the photos with a channel off by more than
/// [`CHANNEL_TOLERANCE`].
fn colour_markdown(methods: &[(String, Vec<ExposureRow>)]) -> String {
    let mut s = format!(
        "\nColour: identity render over photo per channel, over the pixels each photo kept (all photos). Cells: geometric mean over materials; the largest |ratio - 1| of any channel; materials with a channel off by more than {:.0}%.\n\n\
         | Method | EV | photos | R / G / B kept (geo) | worst channel | channels off > {:.0}% |\n|---|---|---|---|---|---|\n",
        100.0 * CHANNEL_TOLERANCE,
        100.0 * CHANNEL_TOLERANCE
    );
    for (name, rows) in methods {
        let mut evs: Vec<f64> = vec![];
        rows.iter().for_each(|r| if !evs.contains(&r.ev) { evs.push(r.ev) });
        for ev in evs {
            let at: Vec<&ExposureRow> = rows.iter().filter(|r| r.ev == ev && r.ratio_kept_rgb.iter().all(|v| v.is_finite() && *v > 0.0)).collect();
            if at.is_empty() {
                continue;
            }
            let rgb = [0, 1, 2].map(|c| geo_min_max(&at.iter().map(|r| r.ratio_kept_rgb[c]).collect::<Vec<_>>()).0);
            let off = |r: &ExposureRow| r.ratio_kept_rgb.iter().map(|v| (v - 1.0).abs()).fold(0.0, f64::max);
            let (worst, worst_name) = at.iter().map(|r| (off(r), r.material.as_str())).max_by(|a, b| a.0.total_cmp(&b.0)).expect("at is not empty");
            let n_off = at.iter().filter(|r| off(r) > CHANNEL_TOLERANCE).count();
            let _ = writeln!(s, "| {name} | {ev:+} | {} | {:.3} / {:.3} / {:.3} | {worst:.3} ({worst_name}) | {n_off}/{} |", at.len(), rgb[0], rgb[1], rgb[2], at.len());
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::highlights::HighlightConfig;
    use crate::eval::{colocated_render, PrintoutMethod};
    #[test]
    fn exposure_scales_before_the_clamp() {
        let photo = Tensor::from_slice(&[0.25f32, 0.5, 1.5]).view([3, 1, 1]);
        let bright = exposed(&photo, 1.0, true);
        assert_eq!(Vec::<f32>::try_from(bright.reshape([-1])).unwrap(), [0.5, 1.0, 1.0]);
        assert_eq!(clipped_fraction(&bright), 1.0);
        assert_eq!(clipped_fraction(&exposed(&photo, -1.0, true)), 0.0);
        assert_eq!(Vec::<f32>::try_from(exposed(&photo, 1.0, false).reshape([-1])).unwrap(), [0.5, 1.0, 3.0]);
        let (g, lo, hi) = geo_min_max(&[1.0, 4.0]);
        assert!((g - 2.0).abs() < 1e-12 && lo == 1.0 && hi == 4.0);
    }

    /// The print-out returns its photo exactly: identity ratio 1 at every
    /// exposure, and (HDR, nothing clips) renders that scale with it.
    #[test]
    fn the_printout_follows_the_exposure() {
        let m = crate::data::procedural::test_material(3, 32);
        let linear = colocated_render(&m);
        let moved = HighlightConfig::default().configs();
        let mut p = PrintoutMethod::default();
        let rows = measure(&mut p, "test03", &linear, &[-6.0, -2.0, 0.0, 1.0], false, &moved, None).unwrap();
        assert_eq!(rows.iter().map(|r| r.ev).collect::<Vec<_>>(), [-6.0, -2.0, 0.0, 1.0]);
        for r in &rows {
            assert!((r.ratio - 1.0).abs() < 1e-5 && r.ratio_rgb.iter().all(|v| (v - 1.0).abs() < 1e-5), "{r:?}");
            assert_eq!(r.relit_scale.is_none(), r.ev == 0.0);
            assert!(r.relit_scale.is_none_or(|s| (s - 1.0).abs() < 1e-5), "{r:?}");
        }
        // 8-bit photos: 1 wherever nothing clips; a clipped photo's print-out
        // keeps the clip (below 1 against the light the clip hid).
        let rows = measure(&mut p, "test03", &linear, &[-6.0, 0.0, 2.0], true, &moved, None).unwrap();
        assert_eq!((rows[0].clipped, rows[1].clipped), (0.0, 0.0), "{rows:?}");
        assert!((rows[0].ratio - 1.0).abs() < 1e-5 && (rows[1].ratio - 1.0).abs() < 1e-5, "{rows:?}");
        assert!(rows[2].clipped > 0.0 && rows[2].ratio < 1.0, "{:?}", rows[2]);
        // Over the pixels it kept, the clipped photo's print-out is the photo itself.
        assert!((rows[2].ratio_kept - 1.0).abs() < 1e-5, "{:?}", rows[2]);
        assert!(rows.iter().filter(|r| r.clipped == 0.0).all(|r| (r.ratio_kept - r.ratio).abs() < 1e-6), "{rows:?}");
        let md = markdown(&[("printout".into(), rows.clone())], true);
        assert!(md.contains("| printout | -6 | 1 | 1.00 [1.00, 1.00] | 1/1 |"), "{md}");
        assert!(md.contains("| 1.00 [1.00, 1.00] (1/1) |"), "the clipped photo's kept pixels: {md}");
        // The print-out is the photo wherever it kept pixels: every channel 1, none off.
        assert!(rows.iter().all(|r| r.ratio_kept_rgb.iter().all(|v| (v - 1.0).abs() < 1e-5)), "{rows:?}");
        assert!(md.contains("| printout | +2 | 1 | 1.000 / 1.000 / 1.000 | 0.000 (test03) | 0/1 |"), "{md}");
        assert!(csv_text(&[("printout".into(), rows)]).lines().count() == 4);
        assert!(measure(&mut p, "x", &linear, &[-1.0], false, &moved, None).is_err());
    }
}
