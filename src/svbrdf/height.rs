//! Height fields for materials that only come with a normal map: least-squares
//! integration of the normals' gradient field in the Fourier domain
//! (Frankot-Chellappa style).
//!
//! Method. A unit normal n = normalize(-dh/dx, -dh/dy, 1) (the convention of
//! [`super::normals_from_height`]: y goes up while rows go down) gives the
//! gradient p = dh/dx = -nx/nz, q = dh/dy = -ny/nz. Per pixel step that is
//! g_col = p * 2/W along a row and g_row = -q * 2/H down a column (plane
//! units: [-1,1] spans the material). We look for the h whose differences
//! best match g in the least-squares sense. On a periodic grid the
//! half-pixel centred difference has the Fourier multiplier
//! D(w) = 2i sin(w/2), so the least-squares solution is, per frequency,
//!   H = (conj(D_col) G_col + conj(D_row) G_row) / (|D_col|^2 + |D_row|^2),
//! i.e. the 5-point discrete Poisson equation, with the mean (w = 0) set to
//! zero. Unlike the central difference (multiplier i sin w, zero at the
//! Nyquist frequency) this operator vanishes only at w = 0, so noise near
//! Nyquist is damped rather than amplified.
//!
//! The maps are not periodic: integrating them as if they were would bend
//! the result to make opposite edges meet. Mirror-extending to 2H x 2W (the
//! gradient component across a mirror flips sign) makes an even extension of
//! the height field, which is periodic, so the FFT solve is exact for it.
//!
//! Normals with nz near or below zero (invalid or extreme) are clamped to
//! nz >= [`MIN_NZ`] (slopes up to about 20) so one bad pixel cannot blow up
//! the whole field.

use super::Svbrdf;
use crate::image::Image;
use anyhow::{bail, Result};
use std::borrow::Cow;
use tch::{Device, Kind, Tensor};

/// Smallest nz used when converting normals to slopes.
pub const MIN_NZ: f64 = 0.05;

/// Integrates unit normals `[3, H, W]` into a zero-mean height field
/// `[1, H, W]` in plane units (the material spans [-1,1], a pixel is 2/W).
/// Errors on a wrong channel count, an empty image or NaN/Inf values.
pub fn height_from_normals(normals: &Image) -> Result<Image> {
    height_from_normals_scaled(normals, 1.0)
}

/// [`height_from_normals`] multiplied by `height_scale` (relief strength of a
/// normal map whose real-world height is unknown).
pub fn height_from_normals_scaled(normals: &Image, height_scale: f64) -> Result<Image> {
    let (sx, sy) = (2.0 / normals.width.max(1) as f64, 2.0 / normals.height.max(1) as f64);
    integrate(normals, sx, sy, height_scale)
}

/// [`height_from_normals`] for a material with square texels, as flashmat
/// lays out rectangles (`geometry::half_extents`: the shorter side spans
/// [-1, 1]): a pixel is 2 / min(H, W) plane units both ways.
pub fn height_from_normals_square_texels(normals: &Image) -> Result<Image> {
    let step = 2.0 / normals.height.min(normals.width).max(1) as f64;
    integrate(normals, step, step, 1.0)
}

/// The integration (module docs) with pixel steps `sx` across, `sy` down.
fn integrate(normals: &Image, sx: f64, sy: f64, height_scale: f64) -> Result<Image> {
    let (h, w) = (normals.height, normals.width);
    if normals.channels != 3 {
        bail!("normal map has {} channels, expected 3", normals.channels);
    }
    if h == 0 || w == 0 {
        bail!("normal map is empty ({w}x{h})");
    }
    if let Some((c, y, x)) = normals.find_non_finite() {
        bail!("normal map has a NaN/Inf value at channel {c}, row {y}, column {x}");
    }
    if !height_scale.is_finite() {
        bail!("height scale must be finite (got {height_scale})");
    }
    let plane = h * w;
    // Per-pixel-step height differences along columns and rows.
    let mut g_col = vec![0f64; plane];
    let mut g_row = vec![0f64; plane];
    for i in 0..plane {
        let nz = (normals.data[2 * plane + i] as f64).max(MIN_NZ);
        g_col[i] = -(normals.data[i] as f64) / nz * sx;
        // Rows go down, y goes up: dh/drow = -dh/dy * 2/H = ny/nz * 2/H.
        g_row[i] = (normals.data[plane + i] as f64) / nz * sy;
    }
    // Even (mirror) extension to 2H x 2W: across a vertical mirror the column
    // gradient flips sign, across a horizontal one the row gradient does.
    let (eh, ew) = (2 * h, 2 * w);
    let mut ext_col = vec![0f64; eh * ew];
    let mut ext_row = vec![0f64; eh * ew];
    for r in 0..eh {
        let (rr, flip_r) = if r < h { (r, 1.0) } else { (eh - 1 - r, -1.0) };
        for c in 0..ew {
            let (cc, flip_c) = if c < w { (c, 1.0) } else { (ew - 1 - c, -1.0) };
            ext_col[r * ew + c] = flip_c * g_col[rr * w + cc];
            ext_row[r * ew + c] = flip_r * g_row[rr * w + cc];
        }
    }
    let opts = (Kind::Double, Device::Cpu);
    let shape = [eh as i64, ew as i64];
    let dims = [0i64, 1];
    let f_col = Tensor::from_slice(&ext_col).view(shape).fft_fft2(None::<&[i64]>, dims.as_slice(), "backward");
    let f_row = Tensor::from_slice(&ext_row).view(shape).fft_fft2(None::<&[i64]>, dims.as_slice(), "backward");
    // sin(w/2) with w = 2 pi k / N over the signed frequencies k.
    let half_sin = |n: usize| (Tensor::fft_fftfreq(n as i64, 1.0, opts) * std::f64::consts::PI).sin();
    let s_col = half_sin(ew).view([1, ew as i64]);
    let s_row = half_sin(eh).view([eh as i64, 1]);
    // conj(D) G = -2i sin(w/2) G; with S = sum sin(w/2) G: -2i S = 2 Im S - 2i Re S.
    let s = &f_col * &s_col + &f_row * &s_row;
    let numerator = Tensor::complex(&(s.imag() * 2.0), &(s.real() * -2.0));
    // |D|^2 = 4 sin^2(w/2) summed; zero only at w = 0, where the numerator is
    // zero too: dividing by 1 there sets the mean to zero.
    let denom = (s_col.square() + s_row.square()) * 4.0;
    let denom = denom.where_self(&denom.gt(0.0), &Tensor::ones_like(&denom));
    let heights = (numerator / denom).fft_ifft2(None::<&[i64]>, dims.as_slice(), "backward").real();
    let heights = heights.narrow(0, 0, h as i64).narrow(1, 0, w as i64);
    let heights = (&heights - heights.mean(Kind::Double)) * height_scale;
    let data: Vec<f64> = Vec::try_from(heights.contiguous().flatten(0, -1))?;
    Image::from_data(1, h, w, data.into_iter().map(|v| v as f32).collect())
}

/// Gives `s` a height field integrated from its normals when it has none
/// (loaded maps); a height field it already has is kept.
pub fn ensure_height_field(s: &mut Svbrdf) -> Result<()> {
    if s.height_field.is_none() {
        s.height_field = Some(height_from_normals(&s.normal)?);
    }
    Ok(())
}

/// The height field of `s` for shadows, `[1, H, W]`: its own (checked), or
/// one integrated from its normals when it has none.
pub fn shadow_heights(s: &Svbrdf) -> Result<Cow<'_, Image>> {
    match &s.height_field {
        Some(hf) => {
            if hf.channels != 1 || hf.height != s.height() || hf.width != s.width() {
                bail!("height field is {}x{}x{}, expected 1x{}x{}", hf.channels, hf.height, hf.width, s.height(), s.width());
            }
            if let Some((_, y, x)) = hf.find_non_finite() {
                bail!("height field has a NaN/Inf value at row {y}, column {x}");
            }
            Ok(Cow::Borrowed(hf))
        }
        None => Ok(Cow::Owned(height_from_normals(&s.normal)?)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::svbrdf::normals_from_height;

    /// Mean and max angle (degrees) between two normal maps over the pixels
    /// at least `margin` pixels from the edge.
    fn angle_stats(a: &Image, b: &Image, margin: usize) -> (f64, f64) {
        let n = a.height * a.width;
        let (mut sum, mut max, mut count) = (0f64, 0f64, 0usize);
        for y in margin..a.height - margin {
            for x in margin..a.width - margin {
                let i = y * a.width + x;
                let d: f64 = (0..3).map(|c| a.data[c * n + i] as f64 * b.data[c * n + i] as f64).sum();
                let ang = d.clamp(-1.0, 1.0).acos().to_degrees();
                sum += ang;
                max = max.max(ang);
                count += 1;
            }
        }
        (sum / count as f64, max)
    }

    /// A smooth non-periodic surface: low-frequency sinusoids (not whole
    /// periods over the square) plus a Gaussian bump, plane units.
    fn smooth_surface(h: usize, w: usize) -> Image {
        Image::from_fn(1, h, w, |_, r, c| {
            let x = 2.0 * (c as f32 + 0.5) / w as f32 - 1.0;
            let y = 1.0 - 2.0 * (r as f32 + 0.5) / h as f32;
            0.08 * (2.1 * x + 0.3).sin() * (1.7 * y - 0.5).cos()
                + 0.05 * (3.3 * (x + y) + 1.0).sin()
                + 0.12 * (-((x - 0.2).powi(2) + (y + 0.3).powi(2)) / (2.0 * 0.25f32.powi(2))).exp()
        })
    }

    #[test]
    fn round_trip_on_a_smooth_surface() {
        let (h, w) = (64, 96);
        let surface = smooth_surface(h, w);
        let normals = normals_from_height(&surface);
        let heights = height_from_normals(&normals).unwrap();
        assert_eq!((heights.channels, heights.height, heights.width), (1, h, w));
        assert!(heights.mean().abs() < 1e-6);
        let back = normals_from_height(&heights);
        let (mean, max) = angle_stats(&normals, &back, 0);
        let (mean_in, max_in) = angle_stats(&normals, &back, 2);
        // Heights themselves (up to the mean) within a small fraction of the relief.
        let m = surface.mean();
        let range = surface.data.iter().fold(0f32, |a, &v| a.max((v - m).abs()));
        let err = surface.data.iter().zip(&heights.data).fold(0f32, |a, (&s, &g)| a.max((s - m - g).abs()));
        eprintln!(
            "round trip {w}x{h}: normal angle mean {mean:.4} deg, max {max:.4} deg (2-pixel border excluded: mean {mean_in:.4}, max {max_in:.4}); height max error {:.3}% of the relief",
            100.0 * err / range
        );
        // The edge pixels carry the one-sided differences of normals_from_height,
        // which the mirrored (even) extension cannot reproduce exactly.
        assert!(mean < 0.3 && max < 6.0, "mean {mean} max {max}");
        assert!(mean_in < 0.1 && max_in < 1.0, "interior mean {mean_in} max {max_in}");
        assert!(err < 0.02 * range, "height error {err} of {range}");
    }

    #[test]
    fn signs_follow_the_y_up_convention() {
        let n = 32;
        // h = 0.3 x - 0.2 y: rising to the right and towards row 0.
        let ramp = Image::from_fn(1, n, n, |_, r, c| {
            let x = 2.0 * (c as f32 + 0.5) / n as f32 - 1.0;
            let y = 1.0 - 2.0 * (r as f32 + 0.5) / n as f32;
            0.3 * x - 0.2 * y
        });
        let hf = height_from_normals(&normals_from_height(&ramp)).unwrap();
        let m = ramp.mean();
        let err = ramp.data.iter().zip(&hf.data).fold(0f32, |a, (&s, &g)| a.max((s - m - g).abs()));
        assert!(err < 0.01, "ramp error {err}");
        assert!(hf.get(0, 10, 30) > hf.get(0, 10, 1));
        assert!(hf.get(0, 30, 10) > hf.get(0, 1, 10));
    }

    #[test]
    fn flat_normals_give_a_flat_field_and_bad_input_is_refused() {
        let s = Svbrdf::uniform(8, 8, [0.5; 3], [0.04; 3], 0.5);
        let hf = height_from_normals(&s.normal).unwrap();
        assert!(hf.data.iter().all(|v| v.abs() < 1e-12));
        assert!(height_from_normals(&Image::new(1, 8, 8)).unwrap_err().to_string().contains("channels"));
        assert!(height_from_normals(&Image::new(3, 0, 8)).unwrap_err().to_string().contains("empty"));
        let mut bad = s.normal.clone();
        bad.data[5] = f32::NAN;
        assert!(height_from_normals(&bad).unwrap_err().to_string().contains("NaN"));
        // Degenerate normals (nz <= 0) are clamped, not turned into NaN.
        let mut grazing = s.normal.clone();
        grazing.set(0, 3, 3, 1.0);
        grazing.set(2, 3, 3, 0.0);
        assert!(height_from_normals(&grazing).unwrap().find_non_finite().is_none());
        // A 1-pixel image works.
        assert_eq!(height_from_normals(&Image::from_fn(3, 1, 1, |c, _, _| (c == 2) as u8 as f32)).unwrap().data, vec![0.0]);
    }

    #[test]
    fn ensure_keeps_an_existing_field_and_scales() {
        let mut s = Svbrdf::uniform(16, 16, [0.5; 3], [0.04; 3], 0.5);
        let surface = smooth_surface(16, 16);
        s.normal = normals_from_height(&surface);
        ensure_height_field(&mut s).unwrap();
        let integrated = s.height_field.clone().unwrap();
        let twice = height_from_normals_scaled(&s.normal, 2.0).unwrap();
        for (a, b) in integrated.data.iter().zip(&twice.data) {
            assert!((2.0 * a - b).abs() < 1e-6);
        }
        s.height_field = Some(surface.clone());
        ensure_height_field(&mut s).unwrap();
        assert_eq!(s.height_field.as_ref(), Some(&surface));
        assert_eq!(*shadow_heights(&s).unwrap(), surface);
        s.height_field = Some(Image::new(1, 8, 8));
        assert!(shadow_heights(&s).is_err());
    }
}
