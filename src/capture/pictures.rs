//! The picture of a capture (`capture.jpg` in its folder): each photo
//! with its detected tags (green), the opening as the fitted camera sees
//! it (red) and its pose written in; under each, the rectified opening;
//! and a top view of the lens and flash positions over the frame. A bad
//! photo shows at once: tags missing, an outline off the opening.

use super::frame::FrameLayout;
use super::{tilt_deg, Capture, FramePhoto};
use crate::image::Image;
use crate::viz::{annotate, Mark};
use anyhow::{Context, Result};

/// Longer side of each photo's thumbnail, pixels.
const THUMB: usize = 360;

/// Photos per row of the picture.
const PER_ROW: usize = 8;

/// Photos the picture shows at most (six rows; 180 photos in one row
/// made a picture 65,888 pixels wide, past what JPEG can hold).
const MAX_SHOWN: usize = 6 * PER_ROW;

/// The whole picture: a column per photo (the photo over its rectified
/// opening), [`PER_ROW`] to a row, the first [`MAX_SHOWN`] photos; the top
/// view (every photo's position) at the end.
pub fn capture_picture(capture: &Capture, photos: &[FramePhoto]) -> Result<Image> {
    let mut top = Vec::new();
    let mut bottom = Vec::new();
    for (n, result) in capture.photos.iter().enumerate().take(MAX_SHOWN) {
        let photo = photos.iter().find(|p| p.path == result.source).context("a capture's photo is missing from its inputs")?;
        let (w, h) = (photo.rgb.width, photo.rgb.height);
        let scale = THUMB as f64 / w.max(h) as f64;
        let full = photo.rgb.to_image();
        let thumb = full.resize_area(((h as f64 * scale).round() as usize).max(1), ((w as f64 * scale).round() as usize).max(1));
        let s = |p: [f64; 2]| (p[0] * scale, p[1] * scale);
        let mut marks: Vec<Mark> = result.markers.iter().map(|m| Mark::Line { points: m.corners.iter().map(|&c| s(c)).collect(), closed: true, width: 2, color: [40, 220, 60] }).collect();
        let half = capture.layout.opening_mm() / 2.0;
        let outline: Vec<(f64, f64)> = (0..40)
            .map(|i| {
                // The opening's edge, 10 points a side (distortion bends it).
                let t = (i % 10) as f64 / 10.0;
                let [x, y] = match i / 10 {
                    0 => [-half + 2.0 * half * t, -half],
                    1 => [half, -half + 2.0 * half * t],
                    2 => [half - 2.0 * half * t, half],
                    _ => [-half, half - 2.0 * half * t],
                };
                result.pose.project(&result.intrinsics, [x, y, 0.0]).map(s).unwrap_or((0.0, 0.0))
            })
            .collect();
        marks.push(Mark::Line { points: outline, closed: true, width: 2, color: [235, 40, 40] });
        let source = result.source.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
        let label = format!("{n:02} {source}: tilt {:.0} deg, {} tags, {:.2} px", tilt_deg(result.camera), result.markers.len(), result.rms);
        marks.push(Mark::Text { at: (4.0, 4.0), text: label, size: 13.0, color: [255, 230, 0] });
        // What the frame's paper says of the photo's exposure and white balance.
        if let Some(l) = super::photometry::relative_levels(&capture.paper).and_then(|levels| levels.get(n).copied()) {
            let text = format!("paper: x{:.2}, R/G/B x{:.2}/{:.2}/{:.2}", (l[0] * l[1] * l[2]).cbrt(), l[0], l[1], l[2]);
            marks.push(Mark::Text { at: (4.0, 22.0), text, size: 13.0, color: [255, 230, 0] });
        }
        top.push(annotate(&thumb, &marks)?);
        let side = capture.side;
        let display = Image::from_data(3, side, side, capture.rectified[n].iter().map(|&v| crate::spaces::photo_encode(v.clamp(0.0, 1.0))).collect())?;
        let small = (THUMB * 2 / 3).min(side);
        bottom.push(display.resize_area(small, small));
    }
    let mut view = top_view(capture, THUMB)?;
    let total = capture.photos.len();
    if total > MAX_SHOWN {
        view = annotate(&view, &[Mark::Text { at: (4.0, 22.0), text: format!("photos 00-{:02} of {total} shown", MAX_SHOWN - 1), size: 13.0, color: [200, 20, 20] }])?;
    }
    let mut rows = Vec::new();
    let mut bottoms = bottom.chunks(PER_ROW);
    for tops in top.chunks(PER_ROW) {
        rows.push(tops.to_vec());
        rows.push(bottoms.next().map(<[Image]>::to_vec).unwrap_or_default());
    }
    match rows.first_mut() {
        Some(first) => first.push(view),
        None => rows.push(vec![view]),
    }
    crate::viz::grid(&rows, 4)
}

/// The frame seen from above (`size` pixels square): the tags' ring and
/// the opening, each lens (numbered dot) and flash (small dot).
pub fn top_view(capture: &Capture, size: usize) -> Result<Image> {
    let layout: &FrameLayout = &capture.layout;
    let reach = capture.photos.iter().flat_map(|p| [p.camera[0].abs(), p.camera[1].abs()]).fold(layout.outer_half_mm(), f64::max) * 1.15;
    let s = size as f64 / (2.0 * reach);
    let at = |x: f64, y: f64| (size as f64 / 2.0 + x * s, size as f64 / 2.0 - y * s);
    let square = |half: f64| vec![at(-half, -half), at(half, -half), at(half, half), at(-half, half)];
    let mut marks = vec![
        Mark::Line { points: square(layout.outer_half_mm()), closed: true, width: 1, color: [90, 90, 90] },
        Mark::Line { points: square(layout.opening_mm() / 2.0), closed: true, width: 2, color: [235, 40, 40] },
    ];
    for (n, p) in capture.photos.iter().enumerate() {
        marks.push(Mark::Dot { at: at(p.light[0], p.light[1]), radius: 2, color: [255, 200, 0] });
        marks.push(Mark::Dot { at: at(p.camera[0], p.camera[1]), radius: 5, color: [40, 120, 255] });
        let (x, y) = at(p.camera[0], p.camera[1]);
        marks.push(Mark::Text { at: (x + 7.0, y - 7.0), text: format!("{n:02} ({:.0} mm up)", p.camera[2]), size: 12.0, color: [20, 20, 20] });
    }
    marks.push(Mark::Text { at: (4.0, 4.0), text: "top view: lens (blue), flash (yellow)".into(), size: 13.0, color: [20, 20, 20] });
    annotate(&Image::filled(3, size, size, 0.93), &marks)
}
