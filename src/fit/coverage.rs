//! Does every photo show the material over the whole opening? A card, a
//! finger or a strap over part of the sample in one photo is lit by the
//! same flash and passes every other check, and the fit would take it as
//! the material there. What gives it away is texture: the material's
//! grain, print and relief are in every photo, at any light, while a
//! cover is flat. So each photo's opening is cut into cells and each
//! cell's texture (the mean absolute difference of neighbouring pixels) is
//! compared with the other photos' in the same cell, two ways: linear,
//! over the photo's median level (a highlight added on top keeps the
//! material's steps), and relative to the cell's own mean (a dark region
//! beside another photo's highlight keeps its grain). A cover is flat both
//! ways. A photo flat in some cells where the others agree on texture,
//! but not flat everywhere (a blurred or distant photo loses texture all
//! over: another matter), is the odd one.

/// Cells along each side of the opening.
const GRID: usize = 8;
/// The texture is read at this side (or the opening's own, if smaller):
/// a photo's grain and JPEG noise are averaged away, the material's
/// texture stays, and oblique or distant photos read at the same scale.
const TEXTURE_SIDE: usize = 96;
/// A linear value at or above this (any channel) is clipped: no texture to
/// read (an overhead highlight is flat for that reason).
const CLIP: f32 = 0.98;
/// A cell is flat in a photo when its texture is below this share of the
/// other photos' there (their lower median), linear and relative alike.
pub const FLAT_RATIO: f64 = 0.1;
/// Cells whose texture (the other photos' median) is below this share of
/// the capture's median cell are left out: a plain region has none to lose.
const TEXTURED_CELL: f64 = 0.3;
/// Cells where the others' grain (relative) is under this many of the
/// photo's own 8-bit code steps are left out ([`code_step`]).
const RESOLVED_STEPS: f64 = 2.0;
/// Cells whose centre is within this distance (units of half the opening)
/// of a photo's own highlight point are not read in that photo: there a
/// glossy material's specular can wash out its texture (a green glaze lit
/// as bright as its white crackle), which a cover's flatness would be
/// taken for. The coloured-metal set's glazed tile needs 0.43.
pub const OWN_HIGHLIGHT_RADIUS: f64 = 0.5;
/// A photo is refused when this share of the textured cells is flat in it...
pub const MIN_COVERED_SHARE: f64 = 0.06;
/// ...while its other cells keep at least this share of the others' texture
/// (median): it is a cover, not a blurred photo.
const KEPT_ELSEWHERE: f64 = 0.5;

/// A photo that does not show the material over part of the opening.
#[derive(Clone, Debug, PartialEq)]
pub struct Covered {
    /// Index into the openings given to [`covered_photo`].
    pub photo: usize,
    /// Share of the opening's textured cells that are flat in it.
    pub share: f64,
    /// Its texture there over the other photos' (median of those cells).
    pub ratio: f64,
}

/// One cell's texture in one photo, both ways.
#[derive(Clone, Copy, Debug)]
struct Texture {
    /// Mean absolute step, linear, over the photo's median level.
    linear: f64,
    /// Mean absolute step over the cell's own mean.
    relative: f64,
    /// The cell's mean linear level.
    level: f64,
}

/// Per cell, in row-major order: the texture, or None where a third or
/// more of the cell's pixels are clipped. `opening`: `[3, side, side]`,
/// linear.
fn cell_textures(opening: &[f32], side: usize) -> Vec<Option<Texture>> {
    let n = TEXTURE_SIDE.min(side);
    // Area average to n x n, a pixel clipped where any source pixel was.
    let mut small = vec![0f32; 3 * n * n];
    let mut clipped = vec![false; n * n];
    let mut count = vec![0u32; n * n];
    for y in 0..side {
        let sy = y * n / side;
        for x in 0..side {
            let s = sy * n + x * n / side;
            count[s] += 1;
            for c in 0..3 {
                let v = opening[(c * side + y) * side + x];
                small[c * n * n + s] += v;
                clipped[s] |= v >= CLIP;
            }
        }
    }
    for c in 0..3 {
        for s in 0..n * n {
            small[c * n * n + s] /= count[s].max(1) as f32;
        }
    }
    let level = |s: usize| (0..3).map(|c| small[c * n * n + s] as f64).sum::<f64>();
    let Some(photo_level) = median((0..n * n).filter(|&s| !clipped[s]).map(level).collect()) else {
        return vec![None; GRID * GRID];
    };
    let cells = GRID * GRID;
    let (mut steps, mut pairs, mut levels, mut kept, mut total) = (vec![0f64; cells], vec![0u32; cells], vec![0f64; cells], vec![0u32; cells], vec![0u32; cells]);
    for y in 0..n {
        for x in 0..n {
            let cell = (y * GRID / n) * GRID + x * GRID / n;
            total[cell] += 1;
            let s = y * n + x;
            if clipped[s] {
                continue;
            }
            kept[cell] += 1;
            levels[cell] += level(s);
            for t in [(x + 1 < n).then(|| s + 1), (y + 1 < n).then(|| s + n)].into_iter().flatten() {
                if !clipped[t] {
                    steps[cell] += (0..3).map(|c| (small[c * n * n + s] - small[c * n * n + t]).abs() as f64).sum::<f64>();
                    pairs[cell] += 1;
                }
            }
        }
    }
    (0..cells)
        .map(|c| {
            let usable = 3 * (total[c] - kept[c]) < total[c] && pairs[c] > 0 && photo_level > 0.0;
            usable.then(|| {
                let step = steps[c] / pairs[c] as f64;
                let level = levels[c] / kept[c] as f64;
                Texture { linear: step / photo_level, relative: step / level.max(1e-6), level: level / 3.0 }
            })
        })
        .collect()
}

/// The relative step between neighbouring 8-bit codes of a ^2.2-encoded
/// photo at linear level `level`: d(L)/L = 2.2 / 255 L^(-1/2.2) (2.5% at
/// 0.1, 10% at 0.005). RAW photos have finer steps; this is conservative.
fn code_step(level: f64) -> f64 {
    2.2 / 255.0 * level.max(1e-4).powf(-1.0 / 2.2)
}

/// The middle of `v`: of an even count, the upper of the two middle
/// values, or with `lower` the lower one (with two values the smaller, so
/// that a cell counts as textured only where most of the other photos show
/// it: a highlight passing through one photo's cell is not texture).
fn middle(mut v: Vec<f64>, lower: bool) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    Some(v[if lower { (v.len() - 1) / 2 } else { v.len() / 2 }])
}

fn median(v: Vec<f64>) -> Option<f64> {
    middle(v, false)
}

fn lower_median(v: Vec<f64>) -> Option<f64> {
    middle(v, true)
}

/// The photo (the first such) whose opening is flat where the others show
/// the material's texture ([`MIN_COVERED_SHARE`] of the textured cells or
/// more, [`FLAT_RATIO`] both ways), or None. `openings`: each
/// `[3, side, side]`, linear, as rectified (exposure does not matter: each
/// photo's texture is over its own level). With one photo there is nothing
/// to compare: None. `highlights`: each photo's highlight point
/// ([`crate::fit::photos::highlight_point`], x right and y up over the
/// opening's [-1, 1]; row 0 is y = 1) where known, or empty: cells within
/// [`OWN_HIGHLIGHT_RADIUS`] of a photo's own are not read in it.
pub fn covered_photo(openings: &[Vec<f32>], side: usize, highlights: &[Option<[f64; 2]>]) -> Option<Covered> {
    if openings.len() < 2 || openings.iter().any(|o| o.len() != 3 * side * side) {
        return None;
    }
    let textures: Vec<Vec<Option<Texture>>> = openings.iter().map(|o| cell_textures(o, side)).collect();
    let typical = median(textures.iter().flatten().flatten().map(|t| t.linear).collect())?;
    if typical <= 0.0 {
        return None;
    }
    for (i, own) in textures.iter().enumerate() {
        let mut flat = Vec::new();
        let mut kept = Vec::new();
        let mut textured = 0usize;
        for (c, mine) in own.iter().enumerate() {
            let Some(mine) = mine else { continue };
            let centre = [-1.0 + (2 * (c % GRID) + 1) as f64 / GRID as f64, 1.0 - (2 * (c / GRID) + 1) as f64 / GRID as f64];
            if let Some(Some(h)) = highlights.get(i) {
                if (centre[0] - h[0]).hypot(centre[1] - h[1]) < OWN_HIGHLIGHT_RADIUS {
                    continue;
                }
            }
            let others: Vec<Texture> = textures.iter().enumerate().filter(|&(j, _)| j != i).filter_map(|(_, t)| t[c]).collect();
            let (Some(linear), Some(relative)) = (lower_median(others.iter().map(|t| t.linear).collect()), lower_median(others.iter().map(|t| t.relative).collect())) else { continue };
            // A dark cell of an 8-bit photo holds one code where the others
            // show a grain finer than its steps: not a cover's flatness.
            if linear < TEXTURED_CELL * typical || relative < RESOLVED_STEPS * code_step(mine.level) {
                continue;
            }
            textured += 1;
            let ratio = (mine.linear / linear).max(mine.relative / relative.max(1e-12));
            if ratio < FLAT_RATIO {
                flat.push(ratio);
            } else {
                kept.push(ratio);
            }
        }
        let share = flat.len() as f64 / textured.max(1) as f64;
        if textured > 0 && share >= MIN_COVERED_SHARE && median(kept).is_some_and(|k| k >= KEPT_ELSEWHERE) {
            return Some(Covered { photo: i, share, ratio: median(flat).unwrap_or(0.0) });
        }
    }
    None
}

/// The refusal of a covered photo, naming it and what to do.
pub fn covered_error(photo: &str, covered: &Covered) -> anyhow::Error {
    anyhow::anyhow!(
        "{photo}: {:.0}% of the opening is flat in it (texture {:.2}x the other photos') where they show the material: something over the sample (a card, a finger, a shadow)? take it again with the sample uncovered, or leave it out",
        100.0 * covered.share,
        covered.ratio
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured opening `[3, side, side]`: a checker of 4-pixel squares
    /// (values 0.2 and 0.4, coloured) under a smooth shading `light(x, y)`.
    fn textured(side: usize, light: impl Fn(f32, f32) -> f32) -> Vec<f32> {
        let mut o = vec![0f32; 3 * side * side];
        for c in 0..3 {
            for y in 0..side {
                for x in 0..side {
                    let check = if (x / 4 + y / 4) % 2 == 0 { 0.2 } else { 0.4 };
                    let tint = [1.0, 0.8, 0.6][c];
                    o[(c * side + y) * side + x] = check * tint * light(x as f32 / side as f32, y as f32 / side as f32);
                }
            }
        }
        o
    }

    fn cover(o: &mut [f32], side: usize, x0: usize, x1: usize, y0: usize, y1: usize, value: f32) {
        for c in 0..3 {
            for y in y0..y1 {
                for x in x0..x1 {
                    o[(c * side + y) * side + x] = value;
                }
            }
        }
    }

    #[test]
    fn a_card_over_half_the_opening_names_that_photo() {
        let side = 192;
        let mut photos = vec![textured(side, |_, _| 1.0), textured(side, |x, _| 0.5 + x), textured(side, |_, y| 2.0 - y)];
        cover(&mut photos[1], side, 0, side / 2, 0, side, 0.1);
        let c = covered_photo(&photos, side, &[]).expect("the covered photo");
        assert_eq!(c.photo, 1);
        // Half the cells, less the column along the cover's edge, whose
        // cells hold the step from card to checker.
        assert!((0.375..=0.5).contains(&c.share), "{c:?}");
        assert!(c.ratio < 0.05, "{c:?}");
        let line = covered_error("IMG_01.jpg", &c).to_string();
        assert!(line.starts_with(&format!("IMG_01.jpg: {:.0}% of the opening is flat", 100.0 * c.share)) && !line.contains('\n'), "{line}");
    }

    #[test]
    fn texture_washed_out_at_a_photos_own_highlight_is_not_a_cover() {
        // Photo 1 flat over a 72-pixel square at the lower right (cell
        // rows and columns 5-7: 9 of 64), around its own highlight point
        // (0.75, -0.75): 8 of those cells are within the radius and not
        // read, the ninth alone is not a cover. Told no highlight, the
        // same square is one.
        let side = 192;
        let mut photos = vec![textured(side, |_, _| 1.0), textured(side, |x, _| 0.5 + x), textured(side, |_, y| 2.0 - y)];
        cover(&mut photos[1], side, 120, 192, 120, 192, 0.3);
        let highlights = [Some([0.0, 0.0]), Some([0.75, -0.75]), Some([-0.7, 0.8])];
        assert_eq!(covered_photo(&photos, side, &highlights), None);
        assert_eq!(covered_photo(&photos, side, &[]).map(|c| c.photo), Some(1));
        // A square as large elsewhere in the same photo is still named.
        cover(&mut photos[1], side, 0, 72, 0, 72, 0.3);
        assert_eq!(covered_photo(&photos, side, &highlights).map(|c| c.photo), Some(1));
    }

    #[test]
    fn exposure_shading_highlights_and_a_clipped_spot_are_not_a_cover() {
        let side = 192;
        // Exposures 4x apart, fall-off across the sample, and a broad
        // highlight added on top (linear: the texture's steps stay).
        let highlight = |x: f32, y: f32| 1.0 + 3.0 * (-((x - 0.5).powi(2) + (y - 0.5).powi(2)) / 0.02).exp();
        let mut photos = vec![textured(side, highlight), textured(side, |x, _| 0.25 * (0.5 + x)), textured(side, |_, y| 2.0 - y)];
        // The overhead highlight clipped over a sixth of the opening.
        cover(&mut photos[0], side, 64, 128, 64, 128, 1.0);
        assert_eq!(covered_photo(&photos, side, &[]), None);
        // A plain material has no texture to lose: nothing is said.
        let plain = vec![vec![0.3f32; 3 * side * side]; 3];
        assert_eq!(covered_photo(&plain, side, &[]), None);
        // One photo cannot be compared.
        assert_eq!(covered_photo(&photos[..1], side, &[]), None);
    }

    #[test]
    fn a_blurred_photo_is_not_called_covered() {
        // Texture gone everywhere (out of focus): not a cover.
        let side = 96;
        let mut photos = vec![textured(side, |_, _| 1.0), textured(side, |_, _| 1.0), textured(side, |_, _| 1.0)];
        photos[2] = vec![0.3 * 0.8; 3 * side * side];
        assert_eq!(covered_photo(&photos, side, &[]), None);
        // A small cover (one cell in 64) is under the refusal's share.
        let mut small = vec![textured(side, |_, _| 1.0), textured(side, |_, _| 1.0)];
        cover(&mut small[1], side, 0, 12, 0, 12, 0.1);
        assert_eq!(covered_photo(&small, side, &[]), None);
    }
}
