//! The moved-highlight test (issue 48): does the highlight move when the
//! light does? The camera stays at the photo's camera and three lights
//! move the mirror highlight off the centre. On each material:
//!
//! - S_in: pixels of the true co-located render (the photo before any
//!   8-bit clamp) brighter than [`HighlightConfig::threshold`] x its median
//!   luminance (the RGB mean); S_gt: the same of the truth render under the
//!   new light. Clamped, a bright material's photo has no pixel past twice
//!   its median once half of it clips (three held-out materials at 8 bits),
//!   though its highlight is there; the figures count them too;
//! - **ghost**: the method's mean radiance over the truth's on S_in \ S_gt
//!   (the photographed highlight that should have gone: 1 when it did);
//! - **lobe**: the same on S_gt \ S_in (the new highlight: 1 when drawn at
//!   full strength);
//! - **rest**: the same on the pixels in neither (a model must not win by
//!   brightening everything);
//! - ratios per material are the arithmetic mean over the lights whose
//!   region holds more than [`HighlightConfig::min_pixels`] pixels
//!   (undefined when none does);
//! - **highlight LPIPS**: LPIPS (linear renders clamped to [0, 1], the
//!   paper's protocol) of the method's render against the truth's in a
//!   window centred on the ghost (or lobe) region's centroid, a quarter of
//!   the image side (64 pixels at 256; [`region_window`]), averaged over the
//!   same lights. The regions themselves are too scattered for a bounding
//!   box (texture past twice the median joins them) and LPIPS needs a
//!   rectangle of at least 31 pixels.
//!
//! Over materials: geometric means, medians, the counts past 1.5x (ghost) or
//! below 0.67x (lobe), and the same per glossiness tercile
//! ([`glossiness`]: the co-located mirror highlight's height F0 / (4 alpha^2)).

use super::methods::Method;
use crate::geometry::{LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::lpips::Lpips;
use crate::svbrdf::Svbrdf;
use anyhow::{ensure, Result};
use serde::Serialize;
use std::fmt::Write as _;
use tch::{Kind, Tensor};

/// The three lights: each moves the mirror highlight seen from the
/// photo's camera well away from the centre.
pub const MOVED_LIGHTS: [[f64; 3]; 3] = [[1.2, 1.2, 3.5], [-1.5, 0.6, 3.0], [0.4, -1.6, 3.2]];

/// Highlight pixels are brighter than this many times the median: the
/// flash highlight the exposure calibration leaves out (one home, in the
/// lower layer).
pub const HIGHLIGHT_THRESHOLD: f64 = crate::infer::exposure::HIGHLIGHT_FACTOR;

/// A region counts on a light when it holds more than this many pixels at
/// 256 x 256 (scaled with the pixel count at other sizes).
pub const MIN_REGION_PIXELS_AT_256: usize = 50;

/// Smallest side of a highlight crop scored by LPIPS.
pub const LPIPS_MIN_CROP: usize = 32;

/// A ghost ratio above this counts as a highlight left behind.
pub const GHOST_PAST: f64 = 1.5;

/// A lobe ratio below this counts as a highlight not drawn.
pub const LOBE_BELOW: f64 = 0.67;

/// The test's settings; the defaults are the protocol.
#[derive(Clone, Debug)]
pub struct HighlightConfig {
    /// Lights of the moved renders, camera fixed at the photo's.
    pub lights: Vec<[f64; 3]>,
    pub threshold: f64,
    /// [`MIN_REGION_PIXELS_AT_256`], for other sizes scaled by area.
    pub min_pixels_at_256: usize,
}

impl Default for HighlightConfig {
    fn default() -> Self {
        Self { lights: MOVED_LIGHTS.to_vec(), threshold: HIGHLIGHT_THRESHOLD, min_pixels_at_256: MIN_REGION_PIXELS_AT_256 }
    }
}

impl HighlightConfig {
    /// The moved configurations: each light, the camera of the photo.
    pub fn configs(&self) -> Vec<LightView> {
        let camera = LightView::colocated(MODEL_FOV_DEG).view;
        self.lights.iter().map(|&light| LightView { light, view: camera }).collect()
    }

    /// A region counts when it holds more than this many of `pixels` pixels.
    pub fn min_pixels(&self, pixels: usize) -> usize {
        self.min_pixels_at_256 * pixels / (256 * 256)
    }
}

/// RGB-mean luminance of a `[3, H, W]` image, row-major `H * W`.
pub fn luminance(image: &Tensor) -> Result<Vec<f32>> {
    let s = image.size();
    ensure!(s.len() == 3 && s[0] == 3, "expected a [3, H, W] image, got {s:?}");
    let lum = image.to_device(tch::Device::Cpu).to_kind(Kind::Float).mean_dim([0i64].as_slice(), false, Kind::Float).reshape([-1]);
    Ok(Vec::<f32>::try_from(&lum)?)
}

/// Pixels brighter than `threshold` x the median of `lum` (the lower
/// median for an even count).
pub fn highlight_mask(lum: &[f32], threshold: f64) -> Vec<bool> {
    if lum.is_empty() {
        return vec![];
    }
    let mut sorted = lum.to_vec();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let cut = threshold * sorted[(sorted.len() - 1) / 2] as f64;
    lum.iter().map(|&v| v as f64 > cut).collect()
}

/// Mean of `pred` over mean of `truth` on the pixels of `region`, when it
/// holds more than `min_pixels` of them (and the truth is not black there).
pub fn region_ratio(pred: &[f32], truth: &[f32], region: &[bool], min_pixels: usize) -> Option<f64> {
    let (mut n, mut p, mut t) = (0usize, 0f64, 0f64);
    for ((&a, &b), &inside) in pred.iter().zip(truth).zip(region) {
        if inside {
            n += 1;
            p += a as f64;
            t += b as f64;
        }
    }
    (n > min_pixels && t > 0.0).then(|| p / t)
}

/// The three regions of one moved light, from the photo's highlight and the
/// truth's: (ghost S_in \ S_gt, lobe S_gt \ S_in, rest: neither).
pub fn regions(s_in: &[bool], s_gt: &[bool]) -> [Vec<bool>; 3] {
    let zip = |f: fn(bool, bool) -> bool| s_in.iter().zip(s_gt).map(|(&a, &b)| f(a, b)).collect::<Vec<bool>>();
    [zip(|a, b| a && !b), zip(|a, b| b && !a), zip(|a, b| !a && !b)]
}

/// Window (top, left, side) of the highlight LPIPS: a square of
/// [`lpips_window_side`] pixels centred on the region's centroid, shifted
/// inside the `h x w` image; `None` for an empty region.
pub fn region_window(region: &[bool], h: usize, w: usize) -> Option<(usize, usize, usize)> {
    let (mut n, mut sy, mut sx) = (0usize, 0usize, 0usize);
    for (i, _) in region.iter().enumerate().filter(|(_, &r)| r) {
        (n, sy, sx) = (n + 1, sy + i / w, sx + i % w);
    }
    if n == 0 {
        return None;
    }
    let side = lpips_window_side(h, w);
    let place = |centre: usize, size: usize| centre.saturating_sub(side / 2).min(size - side);
    Some((place((sy + n / 2) / n, h), place((sx + n / 2) / n, w), side))
}

/// Side of the highlight LPIPS window: a quarter of the shorter image side
/// (64 pixels at 256: about a highlight's width), at least
/// [`LPIPS_MIN_CROP`], at most the image.
pub fn lpips_window_side(h: usize, w: usize) -> usize {
    (h.min(w) / 4).max(LPIPS_MIN_CROP).min(h.min(w))
}

/// Per light: ghost, lobe and rest ratios and the two crops' LPIPS.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LightRatios {
    pub ghost: Option<f64>,
    pub lobe: Option<f64>,
    pub rest: Option<f64>,
    pub lpips_ghost: Option<f64>,
    pub lpips_lobe: Option<f64>,
    /// Chromaticity distance of the render's mean colour from the truth's
    /// (rgb / (r + g + b); `uniform::chromaticity_distance`): the relit
    /// colour, whatever the brightness (issue 69).
    pub chroma: Option<f64>,
}

/// The ratios of one method's renders under the moved lights.
/// s_in: the photo's highlight (`H * W`); pred, truth: `[L, 3, H, W]`
/// linear renders of the method and of the truth under the same lights;
/// LPIPS of the crops only with `lpips` (and images of at least
/// [`LPIPS_MIN_CROP`] pixels).
pub fn light_ratios(s_in: &[bool], pred: &Tensor, truth: &Tensor, cfg: &HighlightConfig, lpips: Option<&Lpips>) -> Result<Vec<LightRatios>> {
    let (sp, st) = (pred.size(), truth.size());
    ensure!(sp.len() == 4 && sp[1] == 3 && sp == st, "renders to compare must both be [L, 3, H, W], got {sp:?} and {st:?}");
    let (h, w) = (sp[2] as usize, sp[3] as usize);
    ensure!(s_in.len() == h * w, "the photo's highlight mask has {} pixels, the renders {h}x{w}", s_in.len());
    let min_pixels = cfg.min_pixels(h * w);
    (0..sp[0])
        .map(|l| {
            let (p, t) = (pred.get(l), truth.get(l));
            let (pl, tl) = (luminance(&p)?, luminance(&t)?);
            let s_gt = highlight_mask(&tl, cfg.threshold);
            let [ghost_r, lobe_r, rest_r] = regions(s_in, &s_gt);
            let ratio = |r: &[bool]| region_ratio(&pl, &tl, r, min_pixels);
            let (ghost, lobe, rest) = (ratio(&ghost_r), ratio(&lobe_r), ratio(&rest_r));
            let crop_lpips = |defined: Option<f64>, region: &[bool]| -> Result<Option<f64>> {
                let (Some(lpips), Some(_)) = (lpips, defined) else { return Ok(None) };
                if h < LPIPS_MIN_CROP || w < LPIPS_MIN_CROP {
                    return Ok(None);
                }
                let Some((top, left, side)) = region_window(region, h, w) else { return Ok(None) };
                let crop = |x: &Tensor| x.narrow(1, top as i64, side as i64).narrow(2, left as i64, side as i64).unsqueeze(0);
                Ok(Some(super::metrics::score_renders(lpips, &crop(&p), &crop(&t))?[0].lpips))
            };
            let mean_colour = |x: &Tensor| -> Result<[f64; 3]> { Ok(super::uniform::mean_colour(&Image::from_tensor(x)?)) };
            let chroma = Some(super::uniform::chromaticity_distance(mean_colour(&p)?, mean_colour(&t)?));
            Ok(LightRatios { ghost, lobe, rest, lpips_ghost: crop_lpips(ghost, &ghost_r)?, lpips_lobe: crop_lpips(lobe, &lobe_r)?, chroma })
        })
        .collect()
}

/// The test's numbers for one material and method.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MaterialHighlights {
    pub material: String,
    /// [`glossiness`] of the true material.
    pub glossiness: f64,
    /// Pixels of the photo's highlight S_in.
    pub photo_highlight_pixels: usize,
    pub ghost: Option<f64>,
    pub lobe: Option<f64>,
    pub rest: Option<f64>,
    /// Lights whose ghost / lobe region counted.
    pub ghost_lights: usize,
    pub lobe_lights: usize,
    pub lpips_ghost: Option<f64>,
    pub lpips_lobe: Option<f64>,
    /// Mean over the lights of [`LightRatios::chroma`].
    pub relit_chroma: Option<f64>,
}

/// Mean of the defined values, `None` for none.
fn mean_defined(values: impl Iterator<Item = Option<f64>>) -> (Option<f64>, usize) {
    let v: Vec<f64> = values.flatten().collect();
    ((!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64), v.len())
}

/// Averages a material's per-light ratios over the lights that count.
pub fn material_highlights(material: &str, glossiness: f64, photo_highlight_pixels: usize, lights: &[LightRatios]) -> MaterialHighlights {
    let (ghost, ghost_lights) = mean_defined(lights.iter().map(|l| l.ghost));
    let (lobe, lobe_lights) = mean_defined(lights.iter().map(|l| l.lobe));
    MaterialHighlights {
        material: material.to_string(),
        glossiness,
        photo_highlight_pixels,
        ghost,
        lobe,
        rest: mean_defined(lights.iter().map(|l| l.rest)).0,
        ghost_lights,
        lobe_lights,
        lpips_ghost: mean_defined(lights.iter().map(|l| l.lpips_ghost)).0,
        lpips_lobe: mean_defined(lights.iter().map(|l| l.lpips_lobe)).0,
        relit_chroma: mean_defined(lights.iter().map(|l| l.chroma)).0,
    }
}

/// Scores a prepared method on one material: renders it under the moved
/// lights. colocated: the true co-located render `[3, H, W]`, unclamped
/// (S_in); truth: `[L, 3, H, W]` GGX renders under `cfg`'s configurations.
/// Returns the row and the method's renders `[L, 3, H, W]`.
pub fn measure(method: &dyn Method, material: &str, glossiness: f64, colocated: &Tensor, truth: &Tensor, cfg: &HighlightConfig, lpips: Option<&Lpips>) -> Result<(MaterialHighlights, Tensor)> {
    let pred = method.render(&cfg.configs())?;
    let s_in = highlight_mask(&luminance(colocated)?, cfg.threshold);
    let lights = light_ratios(&s_in, &pred, truth, cfg, lpips)?;
    let pixels = s_in.iter().filter(|&&b| b).count();
    Ok((material_highlights(material, glossiness, pixels, &lights), pred))
}

/// How glossy a material is: the height of its co-located mirror highlight
/// over a flat surface, F0 / (4 alpha^2) (R = f NoL pi at normal incidence,
/// D = 1 / (pi alpha^2)), of the material's mean F0 (RGB mean) and mean
/// alpha = roughness^2. Comparable with the diffuse albedo it stands on.
pub fn glossiness(m: &Svbrdf) -> f64 {
    let mean = |im: &Image| im.data.iter().map(|&v| v as f64).sum::<f64>() / im.data.len().max(1) as f64;
    let alpha = mean(&m.roughness.map(|r| r * r)).max(1e-4);
    mean(&m.specular) / (4.0 * alpha * alpha)
}

/// Statistics of one ratio over materials.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct RatioStats {
    /// Materials where the ratio is defined.
    pub n: usize,
    pub geo_mean: f64,
    pub median: f64,
    pub above_1_5: usize,
    pub below_0_67: usize,
}

/// [`RatioStats`] of the defined values (NaN means for none).
pub fn ratio_stats(values: impl Iterator<Item = Option<f64>>) -> RatioStats {
    let mut v: Vec<f64> = values.flatten().filter(|v| *v > 0.0).collect();
    if v.is_empty() {
        return RatioStats { geo_mean: f64::NAN, median: f64::NAN, ..Default::default() };
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    let median = if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) };
    RatioStats {
        n,
        geo_mean: crate::eval::metrics::geometric_mean(&v),
        median,
        above_1_5: v.iter().filter(|&&x| x > GHOST_PAST).count(),
        below_0_67: v.iter().filter(|&&x| x < LOBE_BELOW).count(),
    }
}

/// Summary of a method over materials.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct HighlightSummary {
    pub ghost: RatioStats,
    pub lobe: RatioStats,
    pub rest: RatioStats,
    /// Arithmetic means of the crops' LPIPS (NaN for none).
    pub lpips_ghost: f64,
    pub lpips_lobe: f64,
    /// Mean over materials of [`MaterialHighlights::relit_chroma`], and the
    /// largest.
    pub relit_chroma: f64,
    pub relit_chroma_max: f64,
}

pub fn summarize(rows: &[&MaterialHighlights]) -> HighlightSummary {
    let mean = |get: fn(&MaterialHighlights) -> Option<f64>| {
        let v: Vec<f64> = rows.iter().filter_map(|r| get(r)).collect();
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    HighlightSummary {
        ghost: ratio_stats(rows.iter().map(|r| r.ghost)),
        lobe: ratio_stats(rows.iter().map(|r| r.lobe)),
        rest: ratio_stats(rows.iter().map(|r| r.rest)),
        lpips_ghost: mean(|r| r.lpips_ghost),
        lpips_lobe: mean(|r| r.lpips_lobe),
        relit_chroma: mean(|r| r.relit_chroma),
        relit_chroma_max: rows.iter().filter_map(|r| r.relit_chroma).fold(f64::NAN, f64::max),
    }
}

/// Names of the glossiness terciles, least glossy first.
pub const TERCILES: [&str; 3] = ["matte", "medium", "glossy"];

/// Tercile (0 matte, 1 medium, 2 glossy) of each of `glossiness`'s values
/// by rank (ties by index): the lowest third, the middle, the highest.
pub fn terciles(glossiness: &[f64]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..glossiness.len()).collect();
    order.sort_by(|&a, &b| glossiness[a].total_cmp(&glossiness[b]).then(a.cmp(&b)));
    let mut out = vec![0; glossiness.len()];
    for (rank, &i) in order.iter().enumerate() {
        out[i] = rank * 3 / glossiness.len().max(1);
    }
    out
}

/// Indices of the `n` glossiest materials, glossiest first.
pub fn glossiest(glossiness: &[f64], n: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..glossiness.len()).collect();
    order.sort_by(|&a, &b| glossiness[b].total_cmp(&glossiness[a]).then(a.cmp(&b)));
    order.truncate(n);
    order
}

fn cell(v: Option<f64>, digits: usize) -> String {
    v.map_or(String::new(), |v| format!("{v:.digits$}"))
}

/// CSV of every method's rows: `method,material,glossiness,photo_highlight_pixels,
/// ghost,lobe,rest,ghost_lights,lobe_lights,lpips_ghost,lpips_lobe,relit_chroma`
/// (empty cells where a ratio is undefined).
pub fn csv_text(methods: &[(String, Vec<MaterialHighlights>)]) -> String {
    let mut s = String::from("method,material,glossiness,photo_highlight_pixels,ghost,lobe,rest,ghost_lights,lobe_lights,lpips_ghost,lpips_lobe,relit_chroma\n");
    for (name, rows) in methods {
        for r in rows {
            let _ = writeln!(
                s,
                "{name},{},{:.5},{},{},{},{},{},{},{},{},{}",
                r.material,
                r.glossiness,
                r.photo_highlight_pixels,
                cell(r.ghost, 5),
                cell(r.lobe, 5),
                cell(r.rest, 5),
                r.ghost_lights,
                r.lobe_lights,
                cell(r.lpips_ghost, 5),
                cell(r.lpips_lobe, 5),
                cell(r.relit_chroma, 5)
            );
        }
    }
    s
}

/// `geometric mean | median | count/n` of one ratio (`- | - | -` for none).
pub(crate) fn stats_cells(s: &RatioStats, count: usize) -> String {
    if s.n == 0 {
        return "- | - | -".into();
    }
    format!("{:.2} | {:.2} | {}/{}", s.geo_mean, s.median, count, s.n)
}

/// The summary section: one row per method, then the same by glossiness
/// tercile.
pub fn markdown(methods: &[(String, Vec<MaterialHighlights>)], cfg: &HighlightConfig) -> String {
    let mut s = String::from("## Moved highlights (issue 48)\n\n");
    let lights: Vec<String> = cfg.lights.iter().map(|l| format!("({}, {}, {})", l[0], l[1], l[2])).collect();
    let _ = writeln!(
        s,
        "Camera fixed at the photo's, lights {}. S_in: pixels of the photo's render before the 8-bit clamp (the co-located truth; with `--phone-photos` the phone's) brighter than {}x its median (RGB mean); S_gt: the same of the truth under the new light. \
         Ratios of mean linear radiance, method over truth: **ghost** on S_in \\ S_gt (1 = the photographed highlight is gone), **lobe** on S_gt \\ S_in \
         (1 = the new highlight at full strength), **rest** elsewhere; per material the mean over the lights leaving more than {} pixels (at 256x256) in the region. \
         Cells: geometric mean | median | materials past {GHOST_PAST}x (ghost), below {LOBE_BELOW}x (lobe), outside 0.9-1.1 (rest) / materials with the region. \
         LPIPS: linear renders clamped to [0, 1] in a window a quarter of the image side centred on the region's centroid, mean over materials. \
         Relit chromaticity: distance of the render's mean rgb / (r + g + b) from the truth's under each light, mean over lights, then mean | largest over materials.\n",
        lights.join(", "),
        cfg.threshold,
        cfg.min_pixels_at_256
    );
    let header = "| Method | ghost | median | > 1.5x | lobe | median | < 0.67x | rest | median | outside 0.9-1.1 | LPIPS ghost window | LPIPS lobe window | relit chromaticity | largest |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|";
    // `lead`: the first cells of the row (method, and tercile).
    let row = |lead: &str, rows: &[&MaterialHighlights]| {
        let sm = summarize(rows);
        let rest_out = rows.iter().filter_map(|r| r.rest).filter(|&v| !(0.9..=1.1).contains(&v)).count();
        format!(
            "| {lead} | {} | {} | {} | {:.3} | {:.3} | {:.4} | {:.4} |",
            stats_cells(&sm.ghost, sm.ghost.above_1_5),
            stats_cells(&sm.lobe, sm.lobe.below_0_67),
            stats_cells(&sm.rest, rest_out),
            sm.lpips_ghost,
            sm.lpips_lobe,
            sm.relit_chroma,
            sm.relit_chroma_max
        )
    };
    let _ = writeln!(s, "{header}");
    for (name, rows) in methods {
        let _ = writeln!(s, "{}", row(name, &rows.iter().collect::<Vec<_>>()));
    }
    let Some((_, first)) = methods.first() else { return s };
    let gloss: Vec<f64> = first.iter().map(|r| r.glossiness).collect();
    let tercile = terciles(&gloss);
    let bounds = |t: usize| {
        let v: Vec<f64> = gloss.iter().zip(&tercile).filter(|(_, &k)| k == t).map(|(&g, _)| g).collect();
        (v.iter().copied().fold(f64::INFINITY, f64::min), v.iter().copied().fold(f64::NEG_INFINITY, f64::max), v.len())
    };
    let _ = writeln!(s, "\nBy glossiness tercile (F0 / (4 alpha^2) of the material's mean F0 and alpha = roughness^2: the co-located highlight's height over a flat surface):\n");
    let _ = writeln!(s, "{}", header.replacen("| Method |", "| Method | glossiness |", 1).replacen("|---|", "|---|---|", 1));
    for (name, rows) in methods {
        for (t, label) in TERCILES.iter().enumerate() {
            let (lo, hi, n) = bounds(t);
            if n == 0 {
                continue;
            }
            let picked: Vec<&MaterialHighlights> = rows.iter().zip(&tercile).filter(|(_, &k)| k == t).map(|(r, _)| r).collect();
            let _ = writeln!(s, "{}", row(&format!("{name} | {label} ({n}: {lo:.2}-{hi:.2})"), &picked));
        }
    }
    s
}

/// Materials in the picture ([`picture`]).
pub const PICTURE_MATERIALS: usize = 4;

/// The picture of the test: for the [`PICTURE_MATERIALS`] glossiest
/// materials a row photo | truth | each method under the first moved
/// light, then truth | each method under the second (display images), and
/// a note of what it shows. Each method is prepared again on the photo
/// the evaluation gave it ([`super::material_photo`]). `None` for no materials.
pub fn picture(methods: &mut [Box<dyn Method>], materials: &[(String, Svbrdf)], opts: &super::EvalOptions, cfg: &HighlightConfig) -> Result<Option<(Image, String)>> {
    let gloss: Vec<f64> = materials.iter().map(|(_, m)| glossiness(m)).collect();
    let picks = glossiest(&gloss, PICTURE_MATERIALS);
    let configs: Vec<LightView> = cfg.configs().into_iter().take(2).collect();
    let mut rows = vec![];
    for &i in &picks {
        let photo = super::material_photo(&materials[i].1, i, opts)?.1;
        let truth = super::reference_renders(&materials[i].1, &configs);
        let mut preds = vec![];
        for method in methods.iter_mut() {
            method.prepare(&photo)?;
            preds.push(method.render(&configs)?);
        }
        let mut row = vec![Image::display_of(&photo)?];
        for l in 0..configs.len() as i64 {
            row.push(Image::display_of(&truth.get(l))?);
            for p in &preds {
                row.push(Image::display_of(&p.get(l))?);
            }
        }
        rows.push(row);
    }
    if rows.is_empty() {
        return Ok(None);
    }
    let names: Vec<String> = methods.iter().map(|m| m.name()).collect();
    let light = |l: &LightView| format!("light ({}, {}, {})", l.light[0], l.light[1], l.light[2]);
    let mut note = format!(
        "Columns: photo | truth, {} ({}) | truth, {} ({})\nRows, glossiest first:\n",
        light(&configs[0]),
        names.join(" | "),
        configs.get(1).map_or(String::new(), light),
        names.join(" | ")
    );
    for &i in &picks {
        let _ = writeln!(note, "{} (glossiness {:.2})", materials[i].0, gloss[i]);
    }
    Ok(Some((crate::viz::grid(&rows, 4)?, note)))
}

/// Indices of the `n` glossiest held-out materials, glossiest first:
/// ranked on 32-pixel maps (the maps' means, so the same order as at any
/// size), for the caller to generate at its size only those it scores.
pub fn glossiest_test_materials(n: usize) -> Result<Vec<usize>> {
    let gloss: Vec<f64> = super::load_materials(super::PROCEDURAL_TEST, 32, None)?.iter().map(|(_, m)| glossiness(m)).collect();
    Ok(glossiest(&gloss, n))
}

/// Materials of the training log's highlight check: the glossiest of the
/// held-out set (matte ones rarely have a highlight region to measure).
pub const CHECK_MATERIALS: usize = 6;

/// The moved-highlight test of a live model on the [`CHECK_MATERIALS`]
/// glossiest held-out materials at `size` x `size` (a multiple of 8), photos
/// clamped for LDR-input models, no LPIPS: the training log's numbers.
pub fn highlight_check(model: &crate::model::Model, info: &crate::model::ModelInfo, size: usize) -> Result<HighlightSummary> {
    let cfg = HighlightConfig::default();
    let mut method = super::methods::BorrowedModelMethod::new(model, info.clone());
    let rows = tch::no_grad(|| {
        glossiest_test_materials(CHECK_MATERIALS)?
            .into_iter()
            .map(|i| {
                let m = crate::data::procedural::test_material(i, size);
                let colocated = super::colocated_render(&m);
                method.prepare(&super::exposure::exposed(&colocated, 0.0, info.ldr_input))?;
                let truth = super::reference_renders(&m, &cfg.configs());
                Ok(measure(&method, &format!("test{i:02}"), glossiness(&m), &colocated, &truth, &cfg, None)?.0)
            })
            .collect::<Result<Vec<_>>>()
    })?;
    Ok(summarize(&rows.iter().collect::<Vec<_>>()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::LightView;
    use tch::Device;

    /// `[3, 64, 64]` grey `base` with `[3, 10, 10]` blocks of the given
    /// values at the top left and bottom right.
    fn image(base: f32, top_left: f32, bottom_right: f32) -> Tensor {
        let t = Tensor::full([3, 64, 64], base as f64, (Kind::Float, Device::Cpu));
        let _ = t.narrow(1, 0, 10).narrow(2, 0, 10).fill_(top_left as f64);
        let _ = t.narrow(1, 54, 10).narrow(2, 54, 10).fill_(bottom_right as f64);
        t
    }

    /// The photo's highlight at the top left, the truth's under the new light
    /// at the bottom right; the method keeps twice the truth at the old place
    /// and a quarter of the new one: ghost 2, lobe 0.25, rest 1 exactly.
    #[test]
    fn ratios_of_a_hand_made_ghost_and_lobe() {
        let photo = image(0.1, 1.0, 0.1);
        let truth = image(0.1, 0.1, 1.0).unsqueeze(0);
        let pred = image(0.1, 0.2, 0.25).unsqueeze(0);
        let s_in = highlight_mask(&luminance(&photo).unwrap(), HIGHLIGHT_THRESHOLD);
        assert_eq!(s_in.iter().filter(|&&b| b).count(), 100);
        let cfg = HighlightConfig::default();
        assert_eq!(cfg.min_pixels(64 * 64), 3);
        let lpips = Lpips::new(Device::Cpu).unwrap();
        let r = light_ratios(&s_in, &pred, &truth, &cfg, Some(&lpips)).unwrap()[0];
        assert!((r.ghost.unwrap() - 2.0).abs() < 1e-6 && (r.lobe.unwrap() - 0.25).abs() < 1e-6 && (r.rest.unwrap() - 1.0).abs() < 1e-6, "{r:?}");
        assert!(r.lpips_ghost.unwrap() > 0.0 && r.lpips_lobe.unwrap() > 0.0);
        // The truth itself: every ratio 1, both crops' LPIPS 0.
        let r = light_ratios(&s_in, &truth, &truth, &cfg, Some(&lpips)).unwrap()[0];
        assert_eq!((r.ghost, r.lobe, r.rest), (Some(1.0), Some(1.0), Some(1.0)));
        assert!(r.lpips_ghost.unwrap() < 1e-6 && r.lpips_lobe.unwrap() < 1e-6);
        assert!(r.chroma.unwrap() < 1e-9, "{r:?}");
        // Grey renders against a truth with twice the red: chromaticities
        // (1/3, 1/3, 1/3) and (1/2, 1/4, 1/4), distance sqrt(1/36 + 2/144).
        let red = &truth * Tensor::from_slice(&[2.0f32, 1.0, 1.0]).view([1, 3, 1, 1]);
        let r = light_ratios(&s_in, &truth, &red, &cfg, None).unwrap()[0];
        assert!((r.chroma.unwrap() - (1.0f64 / 36.0 + 2.0 / 144.0).sqrt()).abs() < 1e-6, "{r:?}");
        // A highlight of 3 pixels (the minimum at 64 x 64) does not count.
        let small = Tensor::full([3, 64, 64], 0.1, (Kind::Float, Device::Cpu));
        let _ = small.narrow(1, 0, 1).narrow(2, 0, 3).fill_(1.0);
        let s_small = highlight_mask(&luminance(&small).unwrap(), HIGHLIGHT_THRESHOLD);
        let r = light_ratios(&s_small, &pred, &truth, &cfg, None).unwrap()[0];
        assert_eq!((r.ghost, r.lpips_ghost), (None, None));
        assert!((r.lobe.unwrap() - 0.25).abs() < 1e-6);
    }

    #[test]
    fn a_material_averages_the_lights_that_count_and_the_summary_uses_geometric_means() {
        let l = |g: Option<f64>, lobe: Option<f64>| LightRatios { ghost: g, lobe, rest: Some(1.0), ..Default::default() };
        let m = material_highlights("m", 1.0, 10, &[l(Some(1.0), None), l(Some(3.0), Some(0.5)), l(None, None)]);
        assert_eq!((m.ghost, m.ghost_lights, m.lobe, m.lobe_lights, m.rest), (Some(2.0), 2, Some(0.5), 1, Some(1.0)));
        let s = ratio_stats([Some(1.0), Some(4.0), None, Some(0.5)].into_iter());
        // (1 * 4 * 0.5)^(1/3) = 2^(1/3); median of 0.5, 1, 4 is 1.
        assert_eq!((s.n, s.above_1_5, s.below_0_67), (3, 1, 1));
        assert!((s.geo_mean - 2f64.powf(1.0 / 3.0)).abs() < 1e-12 && s.median == 1.0);
        assert_eq!(ratio_stats([None].into_iter()).n, 0);
        // Medians of even counts and of masks.
        assert_eq!(ratio_stats([Some(1.0), Some(3.0)].into_iter()).median, 2.0);
        assert_eq!(highlight_mask(&[1.0, 1.0, 2.0, 2.5], 2.0), [false, false, false, true]);
    }

    #[test]
    fn windows_centre_on_the_region_inside_the_image() {
        let mut r = vec![false; 256 * 256];
        r[0] = true;
        assert_eq!(region_window(&r, 256, 256), Some((0, 0, 64)));
        // Two pixels, centroid (100, 151): the window starts 32 before it.
        r[0] = false;
        r[100 * 256 + 150] = true;
        r[100 * 256 + 152] = true;
        assert_eq!(region_window(&r, 256, 256), Some((68, 119, 64)));
        assert_eq!(region_window(&[false; 64], 8, 8), None);
        assert_eq!((lpips_window_side(64, 64), lpips_window_side(16, 16), lpips_window_side(512, 256)), (32, 16, 64));
        assert_eq!(terciles(&[0.3, 0.1, 0.2, 5.0, 0.05, 0.4]), [1, 0, 1, 2, 0, 2]);
        assert_eq!(glossiest(&[0.3, 0.1, 5.0], 2), [2, 0]);
    }

    /// The print-out of a glossy flat material keeps the photographed
    /// highlight (ghost well above 1) and draws no new one (lobe well below).
    #[test]
    fn the_printout_leaves_the_highlight_where_it_was() {
        let m = Svbrdf::uniform(64, 64, [0.2, 0.2, 0.2], [0.04; 3], 0.3);
        let cfg = HighlightConfig::default();
        let mut p = crate::eval::PrintoutMethod::default();
        p.prepare(&crate::eval::input_photo(&m, true)).unwrap();
        let truth = crate::eval::reference_renders(&m, &cfg.configs());
        let (row, pred) = measure(&p, "glossy", glossiness(&m), &crate::eval::colocated_render(&m), &truth, &cfg, None).unwrap();
        assert_eq!(pred.size(), [3, 3, 64, 64]);
        assert!(row.ghost.unwrap() > 2.0 && row.lobe.unwrap() < 0.5 && row.photo_highlight_pixels > 0, "{row:?}");
        // The camera stays at the photo's.
        assert!(cfg.configs().iter().all(|c| c.view == LightView::colocated(MODEL_FOV_DEG).view));
        // F0 / (4 alpha^2) with alpha = 0.09.
        assert!((glossiness(&m) - 0.04 / (4.0 * 0.09f64.powi(2))).abs() < 1e-4);
    }

    #[test]
    fn the_training_check_runs_on_a_tiny_model() {
        let model = crate::model::Model::new(&crate::model::ModelConfig::tiny(), Device::Cpu).unwrap();
        // Weights from a fixed pattern, not the global RNG that tests running
        // beside this one draw from: some random tiny models render Inf, and
        // an Inf render has no ratios (the test then failed about 1 run in 10).
        tch::no_grad(|| {
            for (k, mut v) in model.est_vs.trainable_variables().into_iter().chain(model.renderer_vs.trainable_variables()).enumerate() {
                let pattern = (Tensor::arange(v.numel() as i64, (Kind::Float, Device::Cpu)) * 0.37 + k as f64).sin() * 0.05;
                v.copy_(&pattern.view(v.size().as_slice()));
            }
        });
        let s = highlight_check(&model, &crate::model::ModelInfo { ldr_input: true, steps: 0 }, 32).unwrap();
        assert_eq!(s.rest.n, CHECK_MATERIALS);
        assert!(s.rest.geo_mean > 0.0 && s.ghost.n + s.lobe.n > 0, "{s:?}");
    }
}
