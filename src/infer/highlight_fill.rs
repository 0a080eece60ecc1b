//! Filling the photographed flash highlight in the neural map
//! (`--highlight-fill`, issue 48).
//!
//! M_est writes the flash highlight of its photo into the codes of the
//! pixels under it, as if they were brighter material: under a moved light
//! the old highlight stays (the "ghost", about 2x the truth on the held-out
//! set). The renderer's ceiling (reports/highlights-experiments.md) showed
//! a map without it exists. This step takes the codes under the highlight
//! from the same material beside it:
//!
//! ```text
//! lum   = RGB mean of the photo; level = its median beyond 0.3 of the
//!         shorter side from the mirror point (the photo's centre for the
//!         co-located overhead view)
//! r     = the radius where the median of the rings around the mirror point
//!         first falls below threshold x level
//! H     = the disc of radius r, grown by `dilate` of the shorter side and
//!         feathered over `feather` of it
//! Copy:  codes under H replaced by the codes a shift t away, t the one of
//!        eight directions (length: H's extent plus a margin) whose codes
//!        agree best with the map's own on the ring around H
//! Blend: codes under H replaced by a push-pull interpolation of those
//!        around it (smooth: the texture under the highlight is lost)
//! map'  = (1 - m) map + m fill            m: the feathered mask in [0, 1]
//! ```
//!
//! The copy keeps the texture statistics and only gives M_render codes M_est
//! produced (as `infer::tiling` does); its blend happens only in the feather.
//! A highlight that covers more than `max_share` of the photo (a rough
//! material's broad lobe, or a close-up of a mirror) is left alone: there is
//! too little material beside it to copy from.

use anyhow::{ensure, Result};
use tch::{Device, Kind, Tensor};

/// How the codes under the highlight are replaced.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FillMode {
    /// Codes copied from a shifted place beside the highlight.
    Copy,
    /// Codes interpolated from around the highlight (push-pull).
    Blend,
}

/// Settings of the highlight fill; the defaults are the ones measured in
/// reports/highlights-experiments.md.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HighlightFillConfig {
    pub mode: FillMode,
    /// The highlight ends where the median of a ring around the mirror
    /// point falls below this many times the photo's outer level.
    pub threshold: f64,
    /// Growth of the highlight's radius, as a share of the shorter side
    /// (the halo just below the threshold carries the ghost too).
    pub dilate: f64,
    /// Width of the mask's soft edge, as a share of the shorter side.
    pub feather: f64,
    /// Largest share of the photo the highlight may cover to be filled.
    pub max_share: f64,
}

impl Default for HighlightFillConfig {
    fn default() -> Self {
        Self { mode: FillMode::Copy, threshold: 2.0, dilate: 0.02, feather: 0.02, max_share: 0.4 }
    }
}

impl HighlightFillConfig {
    /// The default settings with the given mode (the command line's `--highlight-fill MODE`).
    pub fn with_mode(mode: FillMode) -> Self {
        Self { mode, ..Self::default() }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.threshold.is_finite() && self.threshold > 1.0, "the highlight threshold must be above 1 (times the photo's outer level), got {}", self.threshold);
        for (name, v) in [("dilation", self.dilate), ("feather", self.feather), ("largest share", self.max_share)] {
            ensure!(v.is_finite() && (0.0..=1.0).contains(&v), "the highlight fill's {name} must be a share in [0, 1], got {v}");
        }
        Ok(())
    }
}

/// What the fill did, for the report line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FillReport {
    /// Share of the pixels whose codes changed (mask above 0).
    pub share: f64,
    /// The copy's shift in pixels (x, y), for [`FillMode::Copy`].
    pub shift: Option<(i64, i64)>,
    /// True when the highlight was found but too large to fill.
    pub skipped_large: bool,
}

impl FillReport {
    pub fn summary(&self) -> String {
        match (self.skipped_large, self.share, self.shift) {
            (true, _, _) => "highlight fill: the highlight covers too much of the photo, left as it is".to_string(),
            (false, s, _) if s == 0.0 => "highlight fill: no flash highlight found in the photo".to_string(),
            (false, s, Some((x, y))) => format!("highlight fill: codes of {:.1}% of the pixels copied from ({x:+}, {y:+}) px beside the highlight", 100.0 * s),
            (false, s, None) => format!("highlight fill: codes of {:.1}% of the pixels interpolated from around the highlight", 100.0 * s),
        }
    }
}

/// The soft highlight mask `[H, W]` (values in [0, 1]) of a linear photo
/// `[3, H, W]` around the mirror point `centre` (x, y in pixels), and
/// whether it was dropped for covering more than `max_share`.
///
/// The flash highlight is found by its radial profile, not pixel by pixel:
/// the median luminance of rings around the mirror point against the median
/// beyond [`OUTER_RADIUS`] of the shorter side. Its radius is where the ring
/// medians first fall below `threshold` times that level. Bright texture
/// does not move a ring's median; a pixel test (brighter than twice the
/// photo's median) took half of some high-contrast held-out materials for
/// highlight.
pub fn highlight_mask(photo: &Tensor, centre: (f64, f64), cfg: &HighlightFillConfig) -> Result<(Tensor, bool)> {
    let s = photo.size();
    ensure!(s.len() == 3 && s[0] == 3, "the photo must be [3, H, W], got {s:?}");
    let (h, w) = (s[1] as usize, s[2] as usize);
    let lum: Vec<f32> = Vec::try_from(super::exposure::luminance(&photo.to_device(Device::Cpu)).flatten(0, -1))?;
    let short = h.min(w) as f64;
    let distance = |i: usize| ((i % w) as f64 + 0.5 - centre.0).hypot((i / w) as f64 + 0.5 - centre.1);
    let empty = || Tensor::zeros([h as i64, w as i64], (Kind::Float, Device::Cpu));
    let Some(radius) = highlight_radius(&lum, distance, short, cfg.threshold) else { return Ok((empty(), false)) };
    let grown = radius + cfg.dilate * short;
    let inside = (0..h * w).filter(|&i| distance(i) < grown).count();
    if inside as f64 > cfg.max_share * (h * w) as f64 {
        return Ok((empty(), true));
    }
    // Feather outwards: 1 inside the grown disc, falling linearly to 0 over `feather`.
    let f = cfg.feather * short;
    let soft: Vec<f32> = (0..h * w)
        .map(|i| {
            let d = distance(i) - grown;
            if d < 0.0 { 1.0 } else if f > 0.0 { (1.0 - d / f).max(0.0) as f32 } else { 0.0 }
        })
        .collect();
    Ok((Tensor::from_slice(&soft).view([h as i64, w as i64]), false))
}

/// Share of the shorter side beyond which pixels give the photo's outer
/// level (a highlight worth filling ends before it: `max_share` 0.4 is a
/// disc of radius 0.36).
pub const OUTER_RADIUS: f64 = 0.3;

/// The flash highlight's radius in pixels from the ring medians of `lum`
/// (row-major luminance; `distance(i)`: pixel i's distance from the mirror
/// point), or None when the innermost disc is not `threshold` times brighter
/// than the outer level. The innermost disc has a radius of 3 pixels or two
/// rings (enough pixels for a median), the rings around it a width of
/// max(1, short / 128); medians are lower medians (a tie reads dark).
fn highlight_radius(lum: &[f32], distance: impl Fn(usize) -> f64, short: f64, threshold: f64) -> Option<f64> {
    let median = |mut v: Vec<f32>| -> Option<f64> {
        let k = v.len().saturating_sub(1) / 2;
        (!v.is_empty()).then(|| *v.select_nth_unstable_by(k, f32::total_cmp).1 as f64)
    };
    let ring = (short / 128.0).max(1.0);
    let first = (2.0 * ring).max(3.0);
    let mut rings: Vec<Vec<f32>> = vec![];
    let mut outer: Vec<f32> = vec![];
    for (i, &v) in lum.iter().enumerate() {
        let d = distance(i);
        if d >= OUTER_RADIUS * short {
            outer.push(v);
        }
        let b = if d < first { 0 } else { 1 + ((d - first) / ring) as usize };
        if rings.len() <= b {
            rings.resize(b + 1, vec![]);
        }
        rings[b].push(v);
    }
    let level = median(outer)?;
    if level <= 0.0 {
        return None;
    }
    let above = rings.into_iter().take_while(|r| median(r.clone()).is_none_or(|m| m > threshold * level)).count();
    (above > 0).then(|| first + (above - 1) as f64 * ring)
}

/// Fills the flash highlight of `photo` `[3, H, W]` (linear, the photo M_est
/// saw) in `map` `[C, H, W]`; the mirror point is the photo's centre.
/// Returns the new map (on the map's device) and what was done.
pub fn fill_highlight(map: &Tensor, photo: &Tensor, cfg: &HighlightFillConfig) -> Result<(Tensor, FillReport)> {
    cfg.validate()?;
    let s = map.size();
    ensure!(s.len() == 3 && photo.size()[1..] == s[1..], "the neural map [C, H, W] and the photo [3, H, W] must have the same size, got {s:?} and {:?}", photo.size());
    let (h, w) = (s[1], s[2]);
    let (mask, skipped_large) = highlight_mask(photo, (w as f64 / 2.0, h as f64 / 2.0), cfg)?;
    let share = f64::try_from(mask.gt(0.0).to_kind(Kind::Float).mean(Kind::Float))?;
    if skipped_large || share == 0.0 {
        return Ok((map.shallow_clone(), FillReport { share: 0.0, shift: None, skipped_large }));
    }
    let device = map.device();
    let codes = map.to_device(Device::Cpu).to_kind(Kind::Float);
    let (fill, shift) = match cfg.mode {
        FillMode::Copy => {
            let (t, shifted) = best_shift(&codes, &mask);
            (shifted, Some(t))
        }
        FillMode::Blend => (push_pull(&codes, &(1.0 - &mask)), None),
    };
    let m = mask.unsqueeze(0);
    let keep: Tensor = 1.0 - &m;
    let out: Tensor = &codes * keep + fill * &m;
    Ok((out.to_kind(map.kind()).to_device(device), FillReport { share, shift, skipped_large: false }))
}

/// Share of each side the copy never reads from: M_est's codes along the
/// map's border differ from the interior's (its convolutions see padding
/// there), and a copy of them drew a frame line across the highlight.
pub const BORDER_SHARE: f64 = 1.0 / 32.0;

/// `codes` `[C, H, W]` read at (y + dy, x + dx), mirrored at the edges of
/// the interior (the map without a [`BORDER_SHARE`] band, at least 2 px), so
/// a shift larger than the map reads its mirror image; inside that interior
/// (shift 0) the codes are the map's own.
fn shifted(codes: &Tensor, dx: i64, dy: i64) -> Tensor {
    let s = codes.size();
    let idx = |n: i64, d: i64| -> Tensor {
        let band = ((n as f64 * BORDER_SHARE) as i64).max(2).min((n - 1) / 2);
        let (lo, len) = (band, n - 2 * band);
        let period = 2 * len;
        let v: Vec<i64> = (0..n)
            .map(|i| {
                let j = (i + d - lo).rem_euclid(period);
                lo + if j < len { j } else { period - 1 - j }
            })
            .collect();
        Tensor::from_slice(&v)
    };
    codes.index_select(1, &idx(s[1], dy)).index_select(2, &idx(s[2], dx))
}

/// The shift (dx, dy) of eight directions, each as long as the mask's
/// extent along it plus a margin, whose codes agree best (mean squared
/// difference) with the map's own on the ring just outside the mask, and the
/// map read at that shift. codes: `[C, H, W]`; mask: `[H, W]` in [0, 1].
fn best_shift(codes: &Tensor, mask: &Tensor) -> ((i64, i64), Tensor) {
    let (h, w) = (mask.size()[0], mask.size()[1]);
    let hard = mask.gt(0.0);
    let rows = hard.any_dim(1, false).nonzero();
    let cols = hard.any_dim(0, false).nonzero();
    let extent = |t: &Tensor| t.max().int64_value(&[]) - t.min().int64_value(&[]) + 1;
    let (ey, ex) = (extent(&rows), extent(&cols));
    let margin = (h.min(w) / 32).max(2);
    // The ring: pixels within `margin` outside the mask.
    let k = 2 * margin + 1;
    let grown = hard.to_kind(Kind::Float).view([1, 1, h, w]).max_pool2d([k, k], [1, 1], [margin, margin], [1, 1], false).view([h, w]).gt(0.5);
    let ring = grown.logical_and(&hard.logical_not()).to_kind(Kind::Float).unsqueeze(0);
    let ring_pixels = f64::try_from(ring.sum(Kind::Float)).unwrap_or(0.0).max(1.0);
    let mut best: Option<(f64, (i64, i64), Tensor)> = None;
    for (ux, uy) in [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1)] {
        let (dx, dy) = (ux * (ex + margin), uy * (ey + margin));
        let moved = shifted(codes, dx, dy);
        let err = f64::try_from(((&moved - codes).square() * &ring).sum(Kind::Float)).unwrap_or(f64::INFINITY) / ring_pixels;
        if best.as_ref().is_none_or(|(e, _, _)| err < *e) {
            best = Some((err, (dx, dy), moved));
        }
    }
    let (_, t, moved) = best.expect("eight shifts were tried");
    (t, moved)
}

/// Push-pull interpolation of `codes` `[C, H, W]` with known-weights `known`
/// `[H, W]` in [0, 1]: where the weight is 1 the codes stay, elsewhere they
/// come from coarser and coarser weighted averages.
fn push_pull(codes: &Tensor, known: &Tensor) -> Tensor {
    let (h, w) = (codes.size()[1], codes.size()[2]);
    let wt = known.view([1, 1, h, w]);
    let x = codes.unsqueeze(0);
    if h <= 2 || w <= 2 {
        let total = wt.sum(Kind::Float).clamp_min(1e-12);
        let mean = (&x * &wt).sum_dim_intlist(&[2i64, 3][..], true, Kind::Float) / total;
        let unknown: Tensor = 1.0 - &wt;
        let out: Tensor = &x * &wt + mean * unknown;
        return out.squeeze_dim(0);
    }
    let pooled_w = wt.avg_pool2d([2, 2], [2, 2], [0, 0], true, false, None);
    let pooled_x = (&x * &wt).avg_pool2d([2, 2], [2, 2], [0, 0], true, false, None) / pooled_w.clamp_min(1e-12);
    // A coarse pixel is fully known as soon as any of its four is.
    let coarse_known = (&pooled_w * 4.0).clamp_max(1.0).view([pooled_w.size()[2], pooled_w.size()[3]]);
    let coarse = push_pull(&pooled_x.squeeze_dim(0), &coarse_known).unsqueeze(0);
    let up = coarse.upsample_bilinear2d([h, w], false, None, None);
    let unknown: Tensor = 1.0 - &wt;
    let out: Tensor = &x * &wt + up * unknown;
    out.squeeze_dim(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 64x64 photo: median 0.1, a disc of radius 6 at 1.0 around the
    /// centre and a bright square (texture) in a corner.
    fn photo() -> Tensor {
        crate::image::Image::from_fn(3, 64, 64, |_, y, x| {
            let (dx, dy) = (x as f32 + 0.5 - 32.0, y as f32 + 0.5 - 32.0);
            if dx * dx + dy * dy < 36.0 {
                1.0
            } else if x < 6 && y < 6 {
                0.9
            } else {
                0.1
            }
        })
        .to_tensor()
    }

    fn cfg(mode: FillMode) -> HighlightFillConfig {
        HighlightFillConfig { mode, dilate: 0.0, feather: 0.0, ..Default::default() }
    }

    #[test]
    fn the_mask_is_the_central_highlight_not_bright_texture() {
        let (mask, skipped) = highlight_mask(&photo(), (32.0, 32.0), &cfg(FillMode::Copy)).unwrap();
        assert!(!skipped);
        let at = |y: i64, x: i64| mask.double_value(&[y, x]);
        assert_eq!(at(32, 32), 1.0);
        assert_eq!(at(2, 2), 0.0, "the bright corner is texture, far from the mirror point");
        assert_eq!(at(32, 45), 0.0);
        // pixel centres within radius 6 of (32, 32): 112 of them (counted by hand: the disc's area is 113).
        let n = mask.sum(Kind::Float).double_value(&[]);
        let expected = (0..64).flat_map(|y| (0..64).map(move |x| (y, x))).filter(|&(y, x)| {
            let (dx, dy) = (x as f32 + 0.5 - 32.0, y as f32 + 0.5 - 32.0);
            dx * dx + dy * dy < 36.0
        }).count() as f64;
        assert_eq!(n, expected);
        // Dilation by 2 px and a feather: 1 on the grown disc, between 0 and 1 beyond, 0 far away.
        let soft = HighlightFillConfig { dilate: 2.0 / 64.0, feather: 2.0 / 64.0, ..cfg(FillMode::Copy) };
        let (m, _) = highlight_mask(&photo(), (32.0, 32.0), &soft).unwrap();
        assert_eq!(m.double_value(&[32, 39]), 1.0, "6 px disc + 2 px dilation reaches x = 39");
        let edge = m.double_value(&[32, 41]);
        assert!(edge > 0.0 && edge < 1.0, "{edge}");
        assert_eq!(m.double_value(&[32, 50]), 0.0);
    }

    #[test]
    fn bright_texture_through_the_centre_is_not_a_highlight() {
        // Stripes: 40% of the columns at 0.9 (nine times the dark ones), one
        // through the centre; every ring's median is the dark level.
        let stripes = crate::image::Image::from_fn(3, 64, 64, |_, _, x| if (x + 2) % 10 < 4 { 0.9 } else { 0.1 }).to_tensor();
        let (mask, skipped) = highlight_mask(&stripes, (32.0, 32.0), &cfg(FillMode::Copy)).unwrap();
        assert!(!skipped);
        assert_eq!(mask.sum(Kind::Float).double_value(&[]), 0.0);
        // The same stripes with the flash highlight on them: only the disc.
        let both = stripes.maximum(&photo());
        let (mask, _) = highlight_mask(&both, (32.0, 32.0), &cfg(FillMode::Copy)).unwrap();
        let (disc, _) = highlight_mask(&photo(), (32.0, 32.0), &cfg(FillMode::Copy)).unwrap();
        assert_eq!(f64::try_from((&mask - &disc).abs().sum(Kind::Float)).unwrap(), 0.0);
    }

    #[test]
    fn a_highlight_too_large_is_left_alone() {
        let big = HighlightFillConfig { max_share: 0.01, ..cfg(FillMode::Copy) };
        let map = Tensor::rand([4, 64, 64], (Kind::Float, Device::Cpu));
        let (out, report) = fill_highlight(&map, &photo(), &big).unwrap();
        assert!(report.skipped_large);
        assert_eq!(f64::try_from((&out - &map).abs().max()).unwrap(), 0.0);
    }

    #[test]
    fn a_map_with_a_ghost_gets_its_surroundings_back() {
        // Codes: a smooth ramp in x (texture) plus a bump of +3 under the highlight (the ghost).
        let ramp = Tensor::arange(64, (Kind::Float, Device::Cpu)).view([1, 1, 64]).expand([2, 64, 64], false) / 64.0;
        let (mask, _) = highlight_mask(&photo(), (32.0, 32.0), &cfg(FillMode::Copy)).unwrap();
        let ghosted = &ramp + mask.unsqueeze(0) * 3.0;
        for mode in [FillMode::Copy, FillMode::Blend] {
            let (out, report) = fill_highlight(&ghosted, &photo(), &cfg(mode)).unwrap();
            assert_eq!(report.share, f64::try_from(mask.mean(Kind::Float)).unwrap(), "{mode:?}");
            let inside = |t: &Tensor| f64::try_from(((t - &ramp).abs() * &mask).sum(Kind::Float) / mask.sum(Kind::Float)).unwrap();
            // The ghost was 3 everywhere inside; what is left is the ramp's
            // difference across the shift (the copy, vertical shifts leave
            // none) or the interpolation's error.
            assert!(inside(&out) < 0.1, "{mode:?}: {} left of the ghost", inside(&out));
            let away: Tensor = 1.0 - &mask;
            let outside = f64::try_from(((&out - &ghosted).abs() * away).max()).unwrap();
            assert_eq!(outside, 0.0, "{mode:?}: codes outside the highlight must not change");
            if mode == FillMode::Copy {
                let (dx, dy) = report.shift.unwrap();
                assert_eq!(dx, 0, "along the ramp's constant direction the copy agrees best on the ring ({dx}, {dy})");
                assert_eq!(dy.abs(), 12 + 2, "the disc's extent (12 rows) plus the margin");
            }
        }
    }

    #[test]
    fn a_photo_without_a_highlight_changes_nothing() {
        let flat = Tensor::full([3, 32, 32], 0.2, (Kind::Float, Device::Cpu));
        let map = Tensor::rand([4, 32, 32], (Kind::Float, Device::Cpu));
        let (out, report) = fill_highlight(&map, &flat, &HighlightFillConfig::default()).unwrap();
        assert_eq!(report.share, 0.0);
        assert!(!report.skipped_large);
        assert_eq!(f64::try_from((&out - &map).abs().max()).unwrap(), 0.0);
        assert!(report.summary().contains("no flash highlight"));
    }

    #[test]
    fn the_copy_reads_the_interior_mirrored_never_the_border() {
        // Codes = column index, 64 wide: the band is 2 px, the interior columns 2..62.
        let cols = Tensor::arange(64, (Kind::Float, Device::Cpu)).view([1, 1, 64]).expand([1, 4, 64], false).contiguous();
        let read = |dx: i64| Vec::<f32>::try_from(shifted(&cols, dx, 0).get(0).get(0)).unwrap();
        let same = read(0);
        assert_eq!(&same[2..62], &(2..62).map(|v| v as f32).collect::<Vec<_>>()[..]);
        for dx in [-200, -40, 0, 13, 40, 200] {
            assert!(read(dx).iter().all(|&v| (2.0..62.0).contains(&v)), "shift {dx} read the border: {:?}", read(dx));
        }
        // Mirrored at the interior's edge: column 50 shifted by 20 reads 61 - (70 - 62) = 53.
        assert_eq!(read(20)[50], 53.0);
    }

    #[test]
    fn bad_settings_are_refused() {
        assert!(HighlightFillConfig { threshold: 0.5, ..Default::default() }.validate().is_err());
        assert!(HighlightFillConfig { feather: -0.1, ..Default::default() }.validate().is_err());
        assert!(HighlightFillConfig { max_share: f64::NAN, ..Default::default() }.validate().is_err());
        assert!(HighlightFillConfig::default().validate().is_ok());
    }
}
