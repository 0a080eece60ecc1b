//! Scene geometry (REFERENCE section 1): the material is the square
//! [-1,1]^2 in the z = 0 plane with macro normal +z; every pixel is shaded
//! with its own light and view directions (perspective rectification).

use anyhow::{bail, Result};
use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// A point or direction in f64: the scalar GGX oracle, the shadow
/// marcher and the samplers below share these helpers.
pub type Vec3 = [f64; 3];

pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn length(v: Vec3) -> f64 {
    dot(v, v).sqrt()
}

pub fn normalize(v: Vec3) -> Vec3 {
    let n = length(v).max(1e-12);
    [v[0] / n, v[1] / n, v[2] / n]
}

pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// f32 normalisation for the CPU renderers.
pub fn normalize3(v: [f32; 3]) -> [f32; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    [v[0] / n, v[1] / n, v[2] / n]
}

/// Largest light or camera coordinate, in units of the material's
/// half-width. The renderers normalise directions in f32 (f64 for the
/// tensor GGX one): far beyond this they lose all precision, and near
/// 1e308 the squared length overflows and the render turns NaN.
pub const MAX_POSITION: f64 = 1e6;

/// Parses a position given as `X,Y,Z` (command-line options, capture
/// folders): three finite numbers within +-[`MAX_POSITION`].
pub fn parse_position(s: &str) -> std::result::Result<Vec3, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!("expected X,Y,Z (three comma-separated numbers), got '{s}'"));
    }
    let mut v = [0.0; 3];
    for (i, p) in parts.iter().enumerate() {
        v[i] = p.parse::<f64>().map_err(|_| format!("'{p}' is not a number (in '{s}')"))?;
        if !v[i].is_finite() {
            return Err(format!("'{p}' is not a finite number"));
        }
        if v[i].abs() > MAX_POSITION {
            return Err(format!("'{p}' is beyond +-{MAX_POSITION:e} (positions are in units of the material's half-width)"));
        }
    }
    Ok(v)
}

/// Checks that a light or camera position is above the material plane.
pub fn above_surface(what: &str, p: Vec3) -> Result<Vec3> {
    if p[2] <= 0.0 {
        bail!("the {what} position {},{},{} is not above the surface: z must be > 0", p[0], p[1], p[2]);
    }
    Ok(p)
}

/// Resolves render positions: defaults are the co-located input configuration.
pub fn light_view_or_input(light: Option<Vec3>, view: Option<Vec3>) -> Result<LightView> {
    let d = fov_to_distance(MODEL_FOV_DEG);
    let view = above_surface("camera", view.unwrap_or([0.0, 0.0, d]))?;
    let light = above_surface("light", light.unwrap_or(view))?;
    Ok(LightView { light, view })
}

/// The model's field of view in degrees (the input photo's camera).
pub const MODEL_FOV_DEG: f64 = 28.0;

/// Radius of the hemisphere used by the "hemisphere" evaluation case.
pub const HEMISPHERE_RADIUS: f64 = 4.0;

/// Distance of a camera looking straight down whose FOV exactly covers the
/// material: d = 1 / tan(FOV / 2). 28 degrees -> 4.010781.
pub fn fov_to_distance(fov_deg: f64) -> f64 {
    1.0 / (fov_deg.to_radians() / 2.0).tan()
}

/// Fraction of a photo's width to keep so a `fov_deg` photo shows what the
/// model's 28 degree camera sees: tan(14 deg) / tan(fov / 2).
pub fn fov_crop_ratio(fov_deg: f64) -> f64 {
    (MODEL_FOV_DEG.to_radians() / 2.0).tan() / (fov_deg.to_radians() / 2.0).tan()
}

/// Half-extents (a_x, a_y) of an H x W map in plane units: the shorter
/// side spans [-1, 1], the longer one [-a, a] with a = long / short, so
/// pixels are square (pitch 2 / min(H, W)) in both directions. (1, 1) for
/// square maps.
pub fn half_extents(h: usize, w: usize) -> (f64, f64) {
    let s = h.min(w).max(1) as f64;
    (w as f64 / s, h as f64 / s)
}

/// Pixel centre of row i, column j on an H x W grid: (x, y, 0), with
/// x = (2 (j + 0.5) / W - 1) a_x, y = (1 - 2 (i + 0.5) / H) a_y (see
/// [`half_extents`]). Square grids: a_x = a_y = 1, so the square formula
/// of REFERENCE section 1 is computed bit for bit.
pub fn pixel_center(i: usize, j: usize, h: usize, w: usize) -> [f64; 3] {
    let (ax, ay) = half_extents(h, w);
    [(2.0 * (j as f64 + 0.5) / w as f64 - 1.0) * ax, (1.0 - 2.0 * (i as f64 + 0.5) / h as f64) * ay, 0.0]
}

/// Surface positions of every pixel centre ([`pixel_center`]). Returns
/// `[3, H, W]` (x, y, z=0) of the given kind (Float for training, Double
/// for oracle checks).
pub fn pixel_positions(h: usize, w: usize, opts: (Kind, Device)) -> Tensor {
    let (ax, ay) = half_extents(h, w);
    let mut xs: Tensor = (Tensor::arange(w as i64, opts) + 0.5) * (2.0 / w as f64) - 1.0;
    let mut ys: Tensor = (Tensor::arange(h as i64, opts) + 0.5) * (-2.0 / h as f64) + 1.0;
    // Only rectangles are scaled: square maps stay bit-identical.
    if ax != 1.0 {
        xs *= ax;
    }
    if ay != 1.0 {
        ys *= ay;
    }
    let x = xs.view([1, w as i64]).expand([h as i64, w as i64], false);
    let y = ys.view([h as i64, 1]).expand([h as i64, w as i64], false);
    Tensor::stack(&[x, y, Tensor::zeros([h as i64, w as i64], opts)], 0)
}

/// Unit directions from every surface point towards each of B points.
/// positions: `[3, H, W]`, points: `[B, 3]` -> `[B, 3, H, W]`.
pub fn direction_maps(positions: &Tensor, points: &Tensor) -> Tensor {
    let b = points.size()[0];
    let diff = points.view([b, 3, 1, 1]) - positions.unsqueeze(0);
    normalize_channels(&diff)
}

/// Normalizes the 3 vector components along dimension `dim` (1 for
/// `[B, 3, H, W]` maps, -3 for `[N, K, 3, H, W]`, -1 for `[..., 3]` rows).
pub fn normalize_along(v: &Tensor, dim: i64) -> Tensor {
    let norm = v.square().sum_dim_intlist([dim].as_slice(), true, v.kind()).sqrt().clamp_min(1e-12);
    v / norm
}

/// Normalizes along dimension 1 (the 3 vector components) of `[.., 3, H, W]`.
pub fn normalize_channels(v: &Tensor) -> Tensor {
    normalize_along(v, 1)
}

/// Half vectors h = normalize(wi + wo) with the 3 components along `dim`
/// (see [`normalize_along`]): the GGX renderer, M_est's h_z input and
/// ND_enc all use this one.
pub fn half_vectors_along(wi: &Tensor, wo: &Tensor, dim: i64) -> Tensor {
    normalize_along(&(wi + wo), dim)
}

/// Half vectors h = normalize(wi + wo), both `[B, 3, H, W]`.
pub fn half_vectors(wi: &Tensor, wo: &Tensor) -> Tensor {
    half_vectors_along(wi, wo, 1)
}

/// A point light and a camera position (world units, material at z = 0).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LightView {
    pub light: [f64; 3],
    pub view: [f64; 3],
}

impl LightView {
    /// The input configuration: light and camera co-located at (0, 0, d).
    pub fn colocated(fov_deg: f64) -> Self {
        let d = fov_to_distance(fov_deg);
        Self { light: [0.0, 0.0, d], view: [0.0, 0.0, d] }
    }
}

/// How output light/view configurations are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
pub enum Sampling {
    /// Training sampling: the mirror highlight lands at a random point p.
    Reflect,
    /// Light and view independently uniform on the radius-4 hemisphere.
    Hemisphere,
    /// The input's co-located configuration.
    Identity,
}

/// Uniform direction on the upper unit hemisphere (uniform in solid angle:
/// z ~ U[0,1], azimuth ~ U[0, 2 pi)).
pub fn uniform_hemisphere<R: Rng>(rng: &mut R) -> [f64; 3] {
    let z: f64 = rng.random::<f64>();
    let phi = rng.random::<f64>() * std::f64::consts::TAU;
    let s = (1.0 - z * z).max(0.0).sqrt();
    [s * phi.cos(), s * phi.sin(), z]
}

/// "Reflect" sampling: p = U[-1,1]^2 + N(0, 2^2) per axis; camera uniform
/// on the hemisphere of radius `d_view`; light on the mirror direction of
/// (V - p) about +z at distance |N(0, 2^2)| + 0.5 from p. Returns the
/// configuration and p.
pub fn sample_reflect<R: Rng>(rng: &mut R, d_view: f64) -> (LightView, [f64; 3]) {
    let normal = Normal::new(0.0, 2.0).expect("valid normal distribution");
    let px = rng.random_range(-1.0..1.0) + normal.sample(rng);
    let py = rng.random_range(-1.0..1.0) + normal.sample(rng);
    let p = [px, py, 0.0];
    let dir = uniform_hemisphere(rng);
    let view = [d_view * dir[0], d_view * dir[1], d_view * dir[2]];
    let to_view = normalize(sub(view, p));
    // Mirror about the normal (0,0,1): flip the tangential components.
    let mirror = [-to_view[0], -to_view[1], to_view[2]];
    let dist = normal.sample(rng).abs() + 0.5;
    let light = [p[0] + dist * mirror[0], p[1] + dist * mirror[1], dist * mirror[2]];
    (LightView { light, view }, p)
}

/// "Hemisphere" sampling: light and camera independently uniform on the
/// hemisphere of the given radius.
pub fn sample_hemisphere<R: Rng>(rng: &mut R, radius: f64) -> LightView {
    let l = uniform_hemisphere(rng);
    let v = uniform_hemisphere(rng);
    LightView { light: l.map(|c| c * radius), view: v.map(|c| c * radius) }
}

/// Draws `count` configurations with the given scheme.
pub fn sample_configs<R: Rng>(rng: &mut R, scheme: Sampling, count: usize, fov_deg: f64) -> Vec<LightView> {
    let d = fov_to_distance(fov_deg);
    (0..count)
        .map(|_| match scheme {
            Sampling::Reflect => sample_reflect(rng, d).0,
            Sampling::Hemisphere => sample_hemisphere(rng, HEMISPHERE_RADIUS),
            Sampling::Identity => LightView::colocated(fov_deg),
        })
        .collect()
}

/// Light and view positions as `[B, 3]` tensors.
pub fn config_tensors(configs: &[LightView], device: Device) -> (Tensor, Tensor) {
    let lights: Vec<f32> = configs.iter().flat_map(|c| c.light.map(|v| v as f32)).collect();
    let views: Vec<f32> = configs.iter().flat_map(|c| c.view.map(|v| v as f32)).collect();
    let b = configs.len() as i64;
    (
        Tensor::from_slice(&lights).view([b, 3]).to_device(device),
        Tensor::from_slice(&views).view([b, 3]).to_device(device),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_pcg::Pcg64;

    #[test]
    fn fov_distance() {
        assert!((fov_to_distance(28.0) - 4.010781).abs() < 1e-6);
        assert!((fov_to_distance(90.0) - 1.0).abs() < 1e-12);
        assert!((fov_crop_ratio(28.0) - 1.0).abs() < 1e-12);
        // tan(14)/tan(22.5) = 0.24933 / 0.41421
        assert!((fov_crop_ratio(45.0) - 0.601938).abs() < 1e-5);
    }

    #[test]
    fn pixel_centres() {
        assert_eq!(pixel_center(0, 0, 2, 2), [-0.5, 0.5, 0.0]);
        assert_eq!(pixel_center(1, 1, 2, 2), [0.5, -0.5, 0.0]);
        let p = pixel_positions(3, 4, (Kind::Float, Device::Cpu));
        assert_eq!(p.size(), [3, 3, 4]);
        for (i, j) in [(0, 0), (2, 3), (1, 2)] {
            let c = pixel_center(i, j, 3, 4);
            for k in 0..3 {
                let v = p.double_value(&[k as i64, i as i64, j as i64]);
                assert!((v - c[k]).abs() < 1e-6);
            }
        }
    }

    /// A 3:2 grid of 4 x 6 pixels: the shorter side (4 rows) spans [-1, 1]
    /// with pitch 2/4 = 0.5, the longer one [-1.5, 1.5] with the same pitch.
    /// Corner centres at +-(a - 1/short) = +-(1.5 - 0.25) = +-1.25 and
    /// +-(1 - 0.25) = +-0.75.
    #[test]
    fn rectangle_pixel_centres() {
        assert_eq!(half_extents(4, 6), (1.5, 1.0));
        assert_eq!(half_extents(6, 4), (1.0, 1.5));
        let close = |a: [f64; 3], b: [f64; 3]| (0..3).all(|k| (a[k] - b[k]).abs() < 1e-12);
        assert!(close(pixel_center(0, 0, 4, 6), [-1.25, 0.75, 0.0]));
        assert!(close(pixel_center(3, 5, 4, 6), [1.25, -0.75, 0.0]));
        assert!(close(pixel_center(1, 2, 4, 6), [-0.25, 0.25, 0.0]));
        // Portrait: x is the shorter side.
        assert!(close(pixel_center(0, 0, 6, 4), [-0.75, 1.25, 0.0]));
        assert!(close(pixel_center(5, 3, 6, 4), [0.75, -1.25, 0.0]));
        // Same pitch both ways; the tensor agrees.
        let p = pixel_positions(4, 6, (Kind::Double, Device::Cpu));
        for (i, j) in [(0, 0), (3, 5), (2, 1), (1, 4)] {
            let c = pixel_center(i, j, 4, 6);
            for k in 0..2 {
                assert!((p.double_value(&[k as i64, i as i64, j as i64]) - c[k]).abs() < 1e-12);
            }
        }
        let dx = p.double_value(&[0, 0, 1]) - p.double_value(&[0, 0, 0]);
        let dy = p.double_value(&[1, 0, 0]) - p.double_value(&[1, 1, 0]);
        assert!((dx - 0.5).abs() < 1e-12 && (dy - 0.5).abs() < 1e-12);
        // Square grids keep the square formula exactly.
        assert_eq!(pixel_center(2, 5, 8, 8), [2.0 * 5.5 / 8.0 - 1.0, 1.0 - 2.0 * 2.5 / 8.0, 0.0]);
    }

    #[test]
    fn direction_maps_match_scalar() {
        let p = pixel_positions(4, 4, (Kind::Float, Device::Cpu));
        let pts = Tensor::from_slice(&[0.3f32, -0.2, 2.0, 1.0, 1.0, 0.5]).view([2, 3]);
        let d = direction_maps(&p, &pts);
        assert_eq!(d.size(), [2, 3, 4, 4]);
        let c = pixel_center(1, 3, 4, 4);
        let expect = normalize(sub([1.0, 1.0, 0.5], c));
        for k in 0..3 {
            assert!((d.double_value(&[1, k as i64, 1, 3]) - expect[k]).abs() < 1e-6);
        }
        let h = half_vectors(&d, &d);
        assert!((h - &d).abs().max().double_value(&[]) < 1e-6);
    }

    #[test]
    fn reflect_sampling_centres_highlight() {
        let mut rng = Pcg64::seed_from_u64(7);
        for _ in 0..200 {
            let (cfg, p) = sample_reflect(&mut rng, fov_to_distance(28.0));
            assert!(cfg.light[2] > 0.0 && cfg.view[2] >= 0.0);
            let r = (cfg.view.iter().map(|v| v * v).sum::<f64>()).sqrt();
            assert!((r - 4.010781).abs() < 1e-5);
            let wi = normalize(sub(cfg.light, p));
            let wo = normalize(sub(cfg.view, p));
            let h = normalize(add(wi, wo));
            assert!(h[0].abs() < 1e-9 && h[1].abs() < 1e-9 && (h[2] - 1.0).abs() < 1e-9, "{h:?}");
        }
    }

    #[test]
    fn hemisphere_is_uniform() {
        let mut rng = Pcg64::seed_from_u64(3);
        let n = 20000;
        let (mut mz, mut mx) = (0.0, 0.0);
        for _ in 0..n {
            let c = sample_hemisphere(&mut rng, HEMISPHERE_RADIUS);
            let r = c.light.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!((r - 4.0).abs() < 1e-9 && c.light[2] >= 0.0);
            mz += c.light[2] / 4.0;
            mx += c.view[0] / 4.0;
        }
        // z ~ U[0,1]: mean 0.5, std of the mean sqrt(1/12/n) = 0.002.
        assert!((mz / n as f64 - 0.5).abs() < 0.01);
        assert!((mx / n as f64).abs() < 0.01);
    }

    #[test]
    fn sampling_is_deterministic_per_seed() {
        let a = sample_configs(&mut Pcg64::seed_from_u64(11), Sampling::Reflect, 8, 28.0);
        let b = sample_configs(&mut Pcg64::seed_from_u64(11), Sampling::Reflect, 8, 28.0);
        let c = sample_configs(&mut Pcg64::seed_from_u64(12), Sampling::Reflect, 8, 28.0);
        assert_eq!(a, b);
        assert_ne!(a, c);
        let id = sample_configs(&mut Pcg64::seed_from_u64(0), Sampling::Identity, 2, 28.0);
        assert_eq!(id[0], LightView::colocated(28.0));
    }
}
