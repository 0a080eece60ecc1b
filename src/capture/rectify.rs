//! The opening, cut out of each photo and made square: every output pixel
//! is a point of the opening, projected through the fitted camera (its
//! distortion included) and read from the photo, in linear light.

use super::camera::{Intrinsics, Pose};
use rayon::prelude::*;

/// An 8-bit RGB photo, rows top to bottom, interleaved.
pub struct Rgb8 {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

impl Rgb8 {
    /// The codes as a display image `[3, H, W]` in [0, 1].
    pub fn to_image(&self) -> crate::image::Image {
        crate::image::Image::from_fn(3, self.height, self.width, |c, y, x| self.data[3 * (y * self.width + x) + c] as f32 / 255.0)
    }

    /// Grey values (Rec. 709 weights on the codes), for the tag detector.
    pub fn gray(&self) -> Vec<u8> {
        self.data.chunks_exact(3).map(|p| (0.2126 * p[0] as f32 + 0.7152 * p[1] as f32 + 0.0722 * p[2] as f32).round() as u8).collect()
    }
}

/// A photo's pixels as [`rectify`] reads them.
pub enum Pixels<'a> {
    /// 8-bit codes, turned to linear light by the `decode` given to [`rectify`].
    Coded(&'a Rgb8),
    /// Linear light `[3, H, W]` (a RAW photo's).
    Linear(&'a crate::image::Image),
}

/// The square `[-half, half]^2` (mm, the frame's axes) as `side x side`
/// linear pixels `[3, side, side]` row-major: row 0 at +y (the top of the
/// page), column 0 at -x. `decode` maps an 8-bit code to linear light.
/// Where one output pixel covers more than a photo pixel, it averages
/// `n x n` samples (n from the photo's own scale), so nothing aliases.
pub fn rectify(photo: Pixels, k: &Intrinsics, pose: &Pose, half: f64, side: usize, decode: &(dyn Fn(u8) -> f32 + Sync)) -> Vec<f32> {
    let lut: Vec<f32> = (0..=255u8).map(decode).collect();
    let step = 2.0 * half / side as f64;
    // Photo pixels per output pixel, at the opening's centre.
    let scale = match (pose.project(k, [0.0, 0.0, 0.0]), pose.project(k, [step, 0.0, 0.0]), pose.project(k, [0.0, step, 0.0])) {
        (Some(a), Some(b), Some(c)) => (b[0] - a[0]).hypot(b[1] - a[1]).max((c[0] - a[0]).hypot(c[1] - a[1])),
        _ => 1.0,
    };
    let n = scale.ceil().clamp(1.0, 8.0) as usize;
    let mut out = vec![0.0f32; 3 * side * side];
    let (r_plane, rest) = out.split_at_mut(side * side);
    let (g_plane, b_plane) = rest.split_at_mut(side * side);
    r_plane
        .par_chunks_mut(side)
        .zip(g_plane.par_chunks_mut(side))
        .zip(b_plane.par_chunks_mut(side))
        .enumerate()
        .for_each(|(row, ((rr, gr), br))| {
            for col in 0..side {
                let mut acc = [0.0f32; 3];
                for sy in 0..n {
                    for sx in 0..n {
                        let x = -half + (col as f64 + (sx as f64 + 0.5) / n as f64) * step;
                        let y = half - (row as f64 + (sy as f64 + 0.5) / n as f64) * step;
                        if let Some(px) = pose.project(k, [x, y, 0.0]) {
                            let v = bilinear(&photo, &lut, px);
                            for c in 0..3 {
                                acc[c] += v[c];
                            }
                        }
                    }
                }
                let w = 1.0 / (n * n) as f32;
                rr[col] = acc[0] * w;
                gr[col] = acc[1] * w;
                br[col] = acc[2] * w;
            }
        });
    out
}

/// The photo at a pixel position (centres at +0.5), bilinear in linear
/// light; positions off the photo take the nearest edge pixel.
fn bilinear(photo: &Pixels, lut: &[f32], p: [f64; 2]) -> [f32; 3] {
    let (w, h) = match photo {
        Pixels::Coded(p) => (p.width as isize, p.height as isize),
        Pixels::Linear(i) => (i.width as isize, i.height as isize),
    };
    let (x, y) = (p[0] - 0.5, p[1] - 0.5);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
    let at = |xi: isize, yi: isize| {
        let (xi, yi) = (xi.clamp(0, w - 1) as usize, yi.clamp(0, h - 1) as usize);
        match photo {
            Pixels::Coded(photo) => {
                let o = (yi * photo.width + xi) * 3;
                [lut[photo.data[o] as usize], lut[photo.data[o + 1] as usize], lut[photo.data[o + 2] as usize]]
            }
            Pixels::Linear(image) => [image.get(0, yi, xi), image.get(1, yi, xi), image.get(2, yi, xi)],
        }
    };
    let (x0, y0) = (x0 as isize, y0 as isize);
    let (a, b, c, d) = (at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1));
    std::array::from_fn(|i| (a[i] * (1.0 - fx) + b[i] * fx) * (1.0 - fy) + (c[i] * (1.0 - fx) + d[i] * fx) * fy)
}
