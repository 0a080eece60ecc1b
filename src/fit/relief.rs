//! Height and ambient occlusion of fitted maps, for displacement, parallax
//! and AO slots (Blender, Unreal, Unity) and glTF's `occlusionTexture`.
//!
//! Height: the fitted normals integrated by [`svbrdf::height`]'s
//! least-squares Poisson solve (mirror-extended FFT), in plane units (the
//! material's shorter side spans [-1, 1]; square texels), mean zero. A
//! normal map fixes height only up to an offset, so the offset is
//! arbitrary; the scale is not: the normals are the fit's, at its size.
//!
//! Ambient occlusion: the cosine-weighted fraction of the hemisphere above
//! a pixel that the height field leaves open,
//!   AO = (1/pi) * integral of V(w) cos(theta) dw,
//! estimated with [`ReliefConfig::ao_directions`] fixed directions that
//! are cosine-distributed themselves (a golden-angle spiral on the unit
//! disc lifted to the hemisphere, Malley's method), so AO is the plain mean
//! of their visibilities. Visibility is [`svbrdf::shadow`]'s height-field
//! march ([`svbrdf::cpu::visibility`]) toward a light placed
//! [`FAR_LIGHT`] plane units away in each direction (a distant light: the
//! direction changes by under 0.002 rad across the material). Rays leaving
//! the material count as open, so edges are a little lighter than an
//! endless surface would be. A flat material has AO 1 exactly. The march
//! assumes the square layout of the shadow renderer; for a rectangle the
//! longer side is squeezed to [-1, 1] (an approximation the maps' README
//! states).

use crate::image::Image;
use crate::svbrdf;
use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};

/// Distance of the lights that stand for directions, in plane units.
pub const FAR_LIGHT: f64 = 1000.0;

/// How height and AO are made.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReliefConfig {
    /// Hemisphere directions averaged for AO (cost: one shadow march each).
    pub ao_directions: usize,
    /// Multiplies the height field for AO only (1: the fitted relief as it
    /// is). Photographed materials are nearly flat at their true scale
    /// (held-out materials: reliefs of 1-4% of the width, AO 1.000 to three
    /// decimals), so artists wanting visible crevice shading raise it.
    pub ao_depth: f64,
}

impl Default for ReliefConfig {
    fn default() -> Self {
        // 32 directions (a shadow march each): a 256 px fit's AO takes about
        // a second at depth 1, 1.6 s more at depth 10 (longer marches).
        Self { ao_directions: 32, ao_depth: 1.0 }
    }
}

impl ReliefConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!((1..=1024).contains(&self.ao_directions), "AO directions must be between 1 and 1024 (got {})", self.ao_directions);
        ensure!(self.ao_depth.is_finite() && self.ao_depth >= 0.0, "--ao-depth must be a finite number >= 0 (got {})", self.ao_depth);
        Ok(())
    }
}

/// Height field `[1, H, W]` (plane units, mean zero) of unit normals `[3, H, W]`.
pub fn height_map(normals: &Image) -> Result<Image> {
    svbrdf::height::height_from_normals_square_texels(normals)
}

/// `n` unit directions on the upper hemisphere, cosine-distributed: the
/// golden-angle spiral's points on the unit disc (equal areas) lifted to
/// z = sqrt(1 - r^2).
pub fn hemisphere_directions(n: usize) -> Vec<[f64; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let r2 = (i as f64 + 0.5) / n as f64;
            let (r, phi) = (r2.sqrt(), i as f64 * golden);
            [r * phi.cos(), r * phi.sin(), (1.0 - r2).sqrt()]
        })
        .collect()
}

/// Ambient occlusion `[1, H, W]` in [0, 1] (1: fully open) of a height
/// field `[1, H, W]` in plane units (module docs).
pub fn ambient_occlusion(heights: &Image, cfg: &ReliefConfig) -> Result<Image> {
    cfg.validate()?;
    let lights: Vec<[f64; 3]> = hemisphere_directions(cfg.ao_directions).iter().map(|d| d.map(|v| v * FAR_LIGHT)).collect();
    let options = svbrdf::shadow::ShadowOptions { height_scale: cfg.ao_depth, ..Default::default() };
    let vis = svbrdf::cpu::visibility(heights, &lights, &options)?; // [K, H, W]
    let plane = heights.height * heights.width;
    let mut ao = vec![0f32; plane];
    for k in 0..lights.len() {
        ao.iter_mut().zip(&vis[k * plane..][..plane]).for_each(|(a, v)| *a += v);
    }
    ao.iter_mut().for_each(|a| *a /= lights.len() as f32);
    Image::from_data(1, heights.height, heights.width, ao)
}

/// A height field as a 16-bit-ready image: (h - min) / (max - min) in
/// [0, 1], with (min, max) in plane units. A flat field gives 0.5 and
/// (min, max) = (h, h).
pub fn normalized_height(heights: &Image) -> (Image, f32, f32) {
    let lo = heights.data.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = heights.data.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let range = hi - lo;
    let norm = if range > 0.0 { heights.map(|v| (v - lo) / range) } else { heights.map(|_| 0.5) };
    (norm, lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth bump field in plane units, `[1, n, n]`.
    fn bumps(n: usize) -> Image {
        Image::from_fn(1, n, n, |_, y, x| {
            let (u, v) = (x as f32 / n as f32 * std::f32::consts::TAU, y as f32 / n as f32 * std::f32::consts::TAU);
            0.05 * (u.sin() * (2.0 * v).cos()) + 0.03 * (3.0 * u + v).cos()
        })
    }

    #[test]
    fn heights_come_back_from_their_normals() {
        let n = 48;
        let truth = bumps(n);
        let normals = svbrdf::normals_from_height(&truth);
        let got = height_map(&normals).unwrap();
        // Up to the offset (a normal map has none): compare mean-free fields.
        let mean = |im: &Image| im.data.iter().sum::<f32>() / im.data.len() as f32;
        let (mt, mg) = (mean(&truth), mean(&got));
        let rms = |f: &dyn Fn(usize) -> f32| ((0..n * n).map(|i| f(i).powi(2)).sum::<f32>() / (n * n) as f32).sqrt();
        let err = rms(&|i| (got.data[i] - mg) - (truth.data[i] - mt));
        let amp = rms(&|i| truth.data[i] - mt);
        eprintln!("height recovery: rms error {err:.5} of rms height {amp:.5}");
        // Central differences blur the finest detail and the border uses one-sided ones: within 3% of the relief.
        assert!(err < 0.03 * amp, "{err} vs {amp}");
        // The scale is the truth's, not just the shape: no free factor.
        let (norm, lo, hi) = normalized_height(&got);
        assert!(norm.data.iter().all(|v| (0.0..=1.0).contains(v)));
        let true_range = truth.data.iter().copied().fold(f32::MIN, f32::max) - truth.data.iter().copied().fold(f32::MAX, f32::min);
        assert!(((hi - lo) / true_range - 1.0).abs() < 0.05, "{} vs {true_range}", hi - lo);
    }

    #[test]
    fn directions_are_cosine_distributed() {
        let d = hemisphere_directions(256);
        assert!(d.iter().all(|v| v[2] > 0.0 && ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) - 1.0).abs() < 1e-12));
        // E[cos theta] under a cosine-weighted hemisphere is 2/3.
        let mean_cos = d.iter().map(|v| v[2]).sum::<f64>() / d.len() as f64;
        assert!((mean_cos - 2.0 / 3.0).abs() < 0.01, "{mean_cos}");
    }

    #[test]
    fn ao_is_one_on_a_plane_and_darkest_at_the_bottom_of_a_pit() {
        let n = 32;
        let cfg = ReliefConfig { ao_directions: 32, ao_depth: 1.0 };
        let flat = ambient_occlusion(&Image::new(1, n, n), &cfg).unwrap();
        assert!(flat.data.iter().all(|&a| a == 1.0));
        // A round pit, 0.3 plane units deep and 0.5 across, in a flat plane.
        let pit = Image::from_fn(1, n, n, |_, y, x| {
            let [px, py, _] = crate::geometry::pixel_center(y, x, n, n);
            let r = (px * px + py * py).sqrt();
            if r < 0.5 { (-0.3 * (1.0 - (r / 0.5).powi(2))) as f32 } else { 0.0 }
        });
        let ao = ambient_occlusion(&pit, &cfg).unwrap();
        let (centre, rim, far) = (ao.get(0, n / 2, n / 2), ao.get(0, n / 2, n / 2 + 8), ao.get(0, 1, 1));
        eprintln!("pit AO: bottom {centre:.3}, rim {rim:.3}, plane {far:.3}");
        assert!(centre < rim && rim <= far, "{centre} {rim} {far}");
        assert!(centre < 0.8, "{centre}");
        assert_eq!(far, 1.0);
        // A deeper pit (--ao-depth) is darker at the bottom; depth 0 is a plane.
        let deeper = ambient_occlusion(&pit, &ReliefConfig { ao_depth: 2.0, ..cfg }).unwrap();
        assert!(deeper.get(0, n / 2, n / 2) < centre);
        assert!(ambient_occlusion(&pit, &ReliefConfig { ao_depth: 0.0, ..cfg }).unwrap().data.iter().all(|&a| a == 1.0));
    }
}
