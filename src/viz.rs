//! Pictures for people: image grids, loss-curve charts, GIF animations.

use crate::image::Image;
use anyhow::{bail, Context, Result};
use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;

const FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans.ttf");
static FONT_ONCE: Once = Once::new();

fn register_font() {
    FONT_ONCE.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// Lays out `[3, h, w]` display images (values in [0,1]) in rows, with a
/// `gap`-pixel dark border; rows may have different lengths and images
/// different sizes (each cell is as large as the largest image).
pub fn grid(rows: &[Vec<Image>], gap: usize) -> Result<Image> {
    let cells = rows.iter().flatten();
    let cell_h = cells.clone().map(|im| im.height).max().context("empty grid")?;
    let cell_w = cells.clone().map(|im| im.width).max().unwrap_or(0);
    let ncols = rows.iter().map(|r| r.len()).max().unwrap_or(0);
    let height = rows.len() * (cell_h + gap) + gap;
    let width = ncols * (cell_w + gap) + gap;
    let mut out = Image::filled(3, height, width, 0.08);
    for (r, row) in rows.iter().enumerate() {
        for (c, im) in row.iter().enumerate() {
            if im.channels != 3 && im.channels != 1 {
                bail!("grid cells must have 1 or 3 channels, got {}", im.channels);
            }
            let (top, left) = (gap + r * (cell_h + gap), gap + c * (cell_w + gap));
            for ch in 0..3 {
                let src = if im.channels == 1 { 0 } else { ch };
                for y in 0..im.height {
                    for x in 0..im.width {
                        out.set(ch, top + y, left + x, im.get(src, y, x).clamp(0.0, 1.0));
                    }
                }
            }
        }
    }
    Ok(out)
}

/// One named series of (step, value) points.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// Renders loss curves against the step (log-scaled y when all values are
/// positive and span a decade or more) to an RGB image of `width x height`.
pub fn line_chart(title: &str, series: &[Series], width: usize, height: usize) -> Result<Image> {
    line_chart_over(title, "step", series, width, height)
}

/// [`line_chart`] with `x_desc` naming the x axis.
pub fn line_chart_over(title: &str, x_desc: &str, series: &[Series], width: usize, height: usize) -> Result<Image> {
    register_font();
    let mut buf = vec![255u8; width * height * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width as u32, height as u32)).into_drawing_area();
        root.fill(&WHITE)?;
        let all = series.iter().flat_map(|s| s.points.iter()).filter(|p| p.1.is_finite());
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in all {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        if x1 <= x0 {
            x1 = x0 + 1.0;
        }
        if y1 <= y0 {
            y1 = y0 + 1e-6 + y0.abs() * 0.1;
        }
        let colors = [RGBColor(31, 119, 180), RGBColor(255, 127, 14), RGBColor(44, 160, 44), RGBColor(214, 39, 40), RGBColor(148, 103, 189), RGBColor(140, 86, 75), RGBColor(227, 119, 194)];
        let mut builder = ChartBuilder::on(&root);
        builder.caption(title, ("sans-serif", 20)).margin(10).x_label_area_size(30).y_label_area_size(60);
        // The log and linear axes are different types; the drawing is the same.
        macro_rules! draw {
            ($chart:expr, $keep:expr) => {{
                let mut chart = $chart;
                chart
                    .configure_mesh()
                    .x_desc(x_desc)
                    // One light line between labels: a denser mesh costs more ink than it reads.
                    .x_max_light_lines(1)
                    .y_max_light_lines(1)
                    .y_label_formatter(&|v| format!("{v:.3}"))
                    .x_label_formatter(&|v| if (x1 - x0) >= 20.0 { format!("{v:.0}") } else { format!("{v:.1}") })
                    .label_style(("sans-serif", 12))
                    .draw()?;
                for (i, s) in series.iter().enumerate() {
                    let color = colors[i % colors.len()];
                    chart
                        .draw_series(LineSeries::new(s.points.iter().copied().filter($keep), color.stroke_width(2)))?
                        .label(s.name.clone())
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
                    // Markers where a series has few points (measurements, not a curve).
                    if s.points.len() <= 24 {
                        chart.draw_series(s.points.iter().copied().filter($keep).map(|p| Circle::new(p, 3, color.filled())))?;
                    }
                }
                chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).label_font(("sans-serif", 12)).draw()?;
            }};
        }
        // A log axis only where the values span a decade or more: over a
        // narrower range plotters draws no labels on it.
        if y0 > 0.0 && y1 / y0 >= 10.0 {
            draw!(builder.build_cartesian_2d(x0..x1, (y0 * 0.9..y1 * 1.1).log_scale())?, |p: &(f64, f64)| p.1.is_finite() && p.1 > 0.0);
        } else {
            let pad = (y1 - y0) * 0.05;
            draw!(builder.build_cartesian_2d(x0..x1, y0 - pad..y1 + pad)?, |p: &(f64, f64)| p.1.is_finite());
        }
        root.present()?;
    }
    let mut im = Image::new(3, height, width);
    for y in 0..height {
        for x in 0..width {
            for c in 0..3 {
                im.set(c, y, x, buf[(y * width + x) * 3 + c] as f32 / 255.0);
            }
        }
    }
    Ok(im)
}

/// Something drawn over a picture by [`annotate`]: pixel coordinates (x
/// along columns, y down rows), colours as RGB bytes.
pub enum Mark {
    /// A polyline, closed back to its first point when `closed`.
    Line { points: Vec<(f64, f64)>, closed: bool, width: u32, color: [u8; 3] },
    Dot { at: (f64, f64), radius: u32, color: [u8; 3] },
    /// Text whose top-left corner is `at`, `size` pixels high.
    Text { at: (f64, f64), text: String, size: f64, color: [u8; 3] },
}

/// A copy of a display image (`[1 or 3, H, W]`, values in [0, 1]) with
/// `marks` drawn over it.
pub fn annotate(image: &Image, marks: &[Mark]) -> Result<Image> {
    register_font();
    let (w, h) = (image.width, image.height);
    let rgb = if image.channels == 1 { Image::concat_channels(&[image, image, image])? } else { image.clone() };
    let mut buf: Vec<u8> = (0..h * w * 3).map(|i| crate::spaces::quantize_u8(rgb.get(i % 3, i / 3 / w, i / 3 % w))).collect();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w as u32, h as u32)).into_drawing_area();
        let p = |(x, y): (f64, f64)| (x.round() as i32, y.round() as i32);
        for mark in marks {
            match mark {
                Mark::Line { points, closed, width, color } => {
                    let mut pts: Vec<(i32, i32)> = points.iter().map(|&q| p(q)).collect();
                    if *closed && !pts.is_empty() {
                        pts.push(pts[0]);
                    }
                    let style = RGBColor(color[0], color[1], color[2]).stroke_width(*width);
                    root.draw(&PathElement::new(pts, style))?;
                }
                Mark::Dot { at, radius, color } => {
                    root.draw(&Circle::new(p(*at), *radius, RGBColor(color[0], color[1], color[2]).filled()))?;
                }
                Mark::Text { at, text, size, color } => {
                    let style = ("sans-serif", *size).into_font().color(&RGBColor(color[0], color[1], color[2]));
                    root.draw(&plotters::element::Text::new(text.clone(), p(*at), style))?;
                }
            }
        }
        root.present()?;
    }
    Ok(Image::from_fn(3, h, w, |c, y, x| buf[(y * w + x) * 3 + c] as f32 / 255.0))
}

/// Writes display frames (`[3, H, W]` in [0,1]) as a looping GIF,
/// `delay_cs` hundredths of a second per frame (atomic write).
pub fn write_gif(path: &Path, frames: &[Image], delay_cs: u16) -> Result<()> {
    let first = frames.first().context("no frames")?;
    let (w, h) = (first.width, first.height);
    let mut bytes = Vec::new();
    {
        let mut enc = gif::Encoder::new(&mut bytes, w as u16, h as u16, &[])?;
        enc.set_repeat(gif::Repeat::Infinite)?;
        for f in frames {
            if f.width != w || f.height != h || f.channels != 3 {
                bail!("all GIF frames must be 3-channel {w}x{h}");
            }
            let mut rgb = Vec::with_capacity(w * h * 3);
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        rgb.push(crate::spaces::quantize_u8(f.get(c, y, x)));
                    }
                }
            }
            let mut frame = gif::Frame::from_rgb_speed(w as u16, h as u16, &rgb, 10);
            frame.delay = delay_cs;
            enc.write_frame(&frame)?;
        }
    }
    crate::io::atomic_write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_layout() {
        let a = Image::filled(3, 4, 4, 1.0);
        let b = Image::filled(1, 2, 2, 0.5);
        let g = grid(&[vec![a.clone(), b], vec![a]], 1).unwrap();
        assert_eq!((g.height, g.width), (2 * 5 + 1, 2 * 5 + 1));
        assert_eq!(g.get(0, 1, 1), 1.0);
        assert_eq!(g.get(2, 1, 6), 0.5); // grey cell replicated to RGB
        assert!((g.get(0, 0, 0) - 0.08).abs() < 1e-7); // border
        assert!((g.get(0, 4, 7) - 0.08).abs() < 1e-7); // outside the small image
    }

    #[test]
    fn chart_draws_lines() {
        let s = vec![Series { name: "l1".into(), points: (0..50).map(|i| (i as f64, 1.0 / (1.0 + i as f64))).collect() }];
        let im = line_chart("loss", &s, 320, 200).unwrap();
        assert_eq!((im.channels, im.height, im.width), (3, 200, 320));
        // Some pixels are the series colour (not white, not grey).
        let n = im.height * im.width;
        let coloured = (0..n).filter(|&i| (im.data[i] - im.data[2 * n + i]).abs() > 0.3).count();
        assert!(coloured > 50, "{coloured}");
    }

    /// Dark pixels in the y-label area (left of the plot, below the caption).
    fn y_label_ink(im: &Image) -> usize {
        (40..im.height - 40).flat_map(|y| (12..55).map(move |x| (y, x))).filter(|&(y, x)| im.get(0, y, x) < 0.5).count()
    }

    #[test]
    fn narrow_ranges_keep_their_axis_labels() {
        // Held-out scores between 0.35 and 0.37: a log axis over so narrow a
        // range would draw no labels, so the axis is linear and labelled.
        let narrow = vec![Series { name: "lpips".into(), points: vec![(10.0, 0.37), (60.0, 0.36), (160.0, 0.35)] }];
        let im = line_chart_over("held-out", "CPU minutes", &narrow, 320, 200).unwrap();
        assert!(y_label_ink(&im) > 100, "{}", y_label_ink(&im));
        // A loss falling over decades keeps its log axis, labelled too.
        let wide = vec![Series { name: "l1".into(), points: (0..50).map(|i| (i as f64, 1.0 / (1.0 + i as f64 * i as f64))).collect() }];
        let im = line_chart("loss", &wide, 320, 200).unwrap();
        assert!(y_label_ink(&im) > 100, "{}", y_label_ink(&im));
    }

    #[test]
    fn gif_written() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.gif");
        let frames: Vec<Image> = (0..3).map(|i| Image::filled(3, 8, 8, i as f32 / 2.0)).collect();
        write_gif(&p, &frames, 5).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..6], b"GIF89a");
        assert!(write_gif(&p, &[], 5).is_err());
    }

    #[test]
    fn annotate_draws_where_it_is_told() {
        let im = Image::filled(1, 40, 60, 1.0);
        let marks = [
            Mark::Line { points: vec![(5.0, 5.0), (55.0, 5.0)], closed: false, width: 1, color: [255, 0, 0] },
            Mark::Dot { at: (30.0, 30.0), radius: 3, color: [0, 0, 255] },
        ];
        let out = annotate(&im, &marks).unwrap();
        assert_eq!((out.channels, out.height, out.width), (3, 40, 60));
        assert_eq!(out.pixel(5, 30), vec![1.0, 0.0, 0.0]);
        assert_eq!(out.pixel(30, 30), vec![0.0, 0.0, 1.0]);
        assert_eq!(out.pixel(20, 10), vec![1.0, 1.0, 1.0]);
    }
}
