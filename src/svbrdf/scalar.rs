//! Plain-Rust evaluation of the paper's GGX model for one pixel, in f64.
//! This is the test oracle for the batched tensor renderer; it follows
//! REFERENCE section 2 term by term.

use std::f64::consts::PI;

use super::ggx::{DOT_EPS, FRESNEL_SG_A, FRESNEL_SG_B, SPECULAR_DENOM_EPS};
use crate::geometry::{add, dot, normalize, sub, Vec3};

/// Clamp below used for every dot product of the model.

/// GGX normal distribution D for alpha = r^2.
pub fn ggx_d(n_dot_h: f64, alpha: f64) -> f64 {
    let a2 = alpha * alpha;
    let denom = (n_dot_h * n_dot_h * (a2 - 1.0) + 1.0).max(DOT_EPS);
    a2 / (PI * denom * denom)
}

/// Schlick-GGX masking for one direction, k = max(alpha/2, 1e-8).
pub fn ggx_g1(x: f64, alpha: f64) -> f64 {
    let k = (alpha / 2.0).max(DOT_EPS);
    x / (x * (1.0 - k) + k)
}

/// Spherical-Gaussian Schlick Fresnel.
pub fn fresnel(ks: f64, v_dot_h: f64) -> f64 {
    ks + (1.0 - ks) * 2f64.powf((FRESNEL_SG_A * v_dot_h + FRESNEL_SG_B) * v_dot_h)
}

/// Material sample of one pixel (linear values, unit normal).
#[derive(Clone, Copy, Debug)]
pub struct PixelMaterial {
    pub kd: Vec3,
    pub ks: Vec3,
    pub roughness: f64,
    pub normal: Vec3,
}

/// BRDF value f(wi, wo) (RGB), wi and wo unit vectors.
pub fn brdf(m: &PixelMaterial, wi: Vec3, wo: Vec3) -> Vec3 {
    let h = normalize(add(wi, wo));
    let n = m.normal;
    let n_dot_h = dot(n, h).max(DOT_EPS);
    let n_dot_v = dot(n, wo).max(DOT_EPS);
    let n_dot_l = dot(n, wi).max(DOT_EPS);
    let v_dot_h = dot(wo, h).max(DOT_EPS);
    let alpha = m.roughness * m.roughness;
    let d = ggx_d(n_dot_h, alpha);
    let g = ggx_g1(n_dot_l, alpha) * ggx_g1(n_dot_v, alpha);
    let mut out = [0.0; 3];
    for c in 0..3 {
        let f = fresnel(m.ks[c], v_dot_h);
        out[c] = m.kd[c] / PI + d * g * f / (4.0 * n_dot_l * n_dot_v + SPECULAR_DENOM_EPS);
    }
    out
}

/// Rendered radiance R = f * NoL * pi for unit-intensity light (no falloff).
pub fn radiance(m: &PixelMaterial, wi: Vec3, wo: Vec3) -> Vec3 {
    let n_dot_l = dot(m.normal, wi).max(DOT_EPS);
    let f = brdf(m, wi, wo);
    [f[0] * n_dot_l * PI, f[1] * n_dot_l * PI, f[2] * n_dot_l * PI]
}

/// Radiance at surface point `p` for a point light at `light` and a camera at `view`.
pub fn radiance_at(m: &PixelMaterial, p: Vec3, light: Vec3, view: Vec3) -> Vec3 {
    radiance(m, normalize(sub(light, p)), normalize(sub(view, p)))
}

/// Height at plane point (x, y), bilinear between pixel centres, edge values
/// extended over the half-pixel border. `height` is `[1, H, W]`, non-empty.
pub fn height_at(height: &crate::image::Image, x: f64, y: f64) -> f64 {
    let (h, w) = (height.height, height.width);
    // Pixel-centre coordinates: column j at x = 2(j + 0.5)/W - 1, row i at y = 1 - 2(i + 0.5)/H.
    let fx = ((x + 1.0) * w as f64 * 0.5 - 0.5).clamp(0.0, (w - 1) as f64);
    let fy = ((1.0 - y) * h as f64 * 0.5 - 0.5).clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
    let g = |r: usize, c: usize| height.data[r * w + c] as f64;
    (g(y0, x0) * (1.0 - tx) + g(y0, x1) * tx) * (1.0 - ty) + (g(y1, x0) * (1.0 - tx) + g(y1, x1) * tx) * ty
}

/// Visibility (1 lit, 0 shadowed) of a point light at `light` from the
/// surface point above plane point (x, y) over the height field `height`
/// (`[1, H, W]`, plane units), marched as [`super::shadow`] defines: one-pixel
/// steps from (x, y, h(x, y)) towards the light until the ray passes the
/// light or leaves the material square; blocked if a sample is strictly
/// below the bilinear height field. An empty field blocks nothing.
pub fn visibility(height: &crate::image::Image, x: f64, y: f64, light: Vec3) -> f64 {
    let (h, w) = (height.height, height.width);
    if h == 0 || w == 0 || height.data.len() < h * w {
        return 1.0;
    }
    let step = super::shadow::march_step(h, w);
    let h0 = height_at(height, x, y);
    let (dx, dy, dz) = (light[0] - x, light[1] - y, light[2] - h0);
    let len = (dx * dx + dy * dy).sqrt();
    if len.is_nan() || len <= 0.0 {
        return 1.0; // straight up (or NaN): a height field cannot overhang
    }
    let (ux, uy, slope) = (dx / len, dy / len, dz / len);
    for k in 1.. {
        let t = k as f64 * step;
        if t >= len {
            break;
        }
        let (sx, sy) = (x + ux * t, y + uy * t);
        if sx.abs() > 1.0 || sy.abs() > 1.0 {
            break;
        }
        if h0 + slope * t < height_at(height, sx, sy) {
            return 0.0;
        }
    }
    1.0
}

/// Visible fraction of a disc light (see [`super::shadow::disc_light_points`]):
/// the mean of [`visibility`] over its sample points.
pub fn visibility_disc(height: &crate::image::Image, x: f64, y: f64, light: Vec3, radius: f64, samples: usize) -> f64 {
    let pts = super::shadow::disc_light_points(light, radius, samples);
    pts.iter().map(|&p| visibility(height, x, y, p)).sum::<f64>() / pts.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(kd: f64, ks: f64, r: f64) -> PixelMaterial {
        PixelMaterial { kd: [kd; 3], ks: [ks; 3], roughness: r, normal: [0.0, 0.0, 1.0] }
    }

    #[test]
    fn diffuse_only_at_normal_incidence_gives_kd() {
        // ks = 0 still leaves the Fresnel tail: (1-0)*2^(...) at VoH=1 is 2^-12.53776;
        // choose roughness 1 where D*G is small and check against the closed form.
        let m = PixelMaterial { kd: [0.3, 0.5, 0.7], ks: [0.0; 3], roughness: 1.0, normal: [0.0, 0.0, 1.0] };
        let r = radiance(&m, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]);
        // Specular at NoH=1, alpha=1: D = 1/pi, G = 1, F = 2^(-12.53789), /4.
        let spec = (1.0 / PI) * 2f64.powf(-5.55473 - 6.98316) / 4.0 * PI;
        for c in 0..3 {
            assert!((r[c] - (m.kd[c] + spec)).abs() < 1e-12, "{c}: {}", r[c]);
        }
    }

    #[test]
    fn specular_peak_matches_closed_form() {
        let r = 0.3;
        let alpha: f64 = r * r;
        let m = flat(0.0, 0.04, r);
        let wi = normalize([0.6, 0.0, 0.8]);
        let wo = normalize([-0.6, 0.0, 0.8]);
        let f = brdf(&m, wi, wo);
        // NoH = 1 -> D = 1 / (pi alpha^2); VoH = NoL = NoV = 0.8.
        let d = 1.0 / (PI * alpha * alpha);
        let k = alpha / 2.0;
        let g1 = 0.8 / (0.8 * (1.0 - k) + k);
        let fr = 0.04 + 0.96 * 2f64.powf((-5.55473 * 0.8 - 6.98316) * 0.8);
        let expected = d * g1 * g1 * fr / (4.0 * 0.8 * 0.8 + 1e-12);
        assert!((f[0] - expected).abs() < 1e-9 * expected);
    }

    #[test]
    fn reciprocity_and_black() {
        let m = PixelMaterial { kd: [0.2, 0.4, 0.1], ks: [0.5, 0.3, 0.04], roughness: 0.45, normal: normalize([0.1, -0.2, 0.9]) };
        let a = normalize([0.3, 0.5, 0.7]);
        let b = normalize([-0.4, 0.1, 0.6]);
        let f1 = brdf(&m, a, b);
        let f2 = brdf(&m, b, a);
        for c in 0..3 {
            assert!((f1[c] - f2[c]).abs() < 1e-12 * f1[c].abs().max(1.0));
        }
        // Black maps: no diffuse term at all; with ks = 0 the paper's Fresnel
        // still leaves its tail (1 - 0) * 2^(...), so the render is exactly
        // the closed-form D G F_tail / (4 NoL NoV) * NoL * pi, and zero when
        // the light is below the surface.
        let black = PixelMaterial { kd: [0.0; 3], ks: [0.0; 3], roughness: 0.5, normal: [0.0, 0.0, 1.0] };
        let (wi, wo) = ([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]);
        let alpha: f64 = 0.25;
        let tail = 2f64.powf(-5.55473 - 6.98316);
        let closed = 1.0 / (PI * alpha * alpha) * tail / 4.0 * PI;
        let r = radiance(&black, wi, wo);
        assert!(r.iter().all(|v| (v - closed).abs() < 1e-15), "{r:?} vs {closed}");
        let below = radiance(&black, [0.0, 0.6, -0.8], wo);
        assert!(below.iter().all(|v| v.abs() < 1e-7), "{below:?}");
        let below_kd = radiance(&PixelMaterial { kd: [0.8; 3], ..black }, [0.0, 0.6, -0.8], wo);
        assert!(below_kd.iter().all(|v| v.abs() < 1e-7), "{below_kd:?}");
    }

    #[test]
    fn finite_at_extremes() {
        for r in [0.0, 1e-6, 1.0] {
            let m = flat(0.5, 0.04, r);
            for wi in [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], normalize([1.0, 0.0, 1e-9]), [0.0, 1.0, -0.2]] {
                for wo in [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], normalize([0.0, 1.0, 1e-7])] {
                    let v = radiance(&m, normalize(wi), wo);
                    assert!(v.iter().all(|x| x.is_finite()), "r={r} wi={wi:?} wo={wo:?} -> {v:?}");
                }
            }
        }
    }
}
