//! Shadows cast by the material's height field (REFERENCE section 8): the
//! options and the ray-march definition shared by the f64 oracle
//! ([`super::scalar::visibility`]), the tensor version
//! ([`super::render::shadow_mask`]) and the f32 CPU version
//! ([`super::cpu::visibility`]).
//!
//! The march, for the pixel centre (x, y) and a point light L:
//! - the ray starts on the surface, P = (x, y, h(x, y)), and goes straight
//!   to L; with horizontal length l = |L_xy - P_xy|, unit horizontal
//!   direction u and slope s = (L_z - h(x, y)) / l, the sample k = 1, 2, ...
//!   sits at P_xy + t_k u, z_k = h(x, y) + s t_k, with t_k = k * step;
//! - `step` is one pixel, 2 / max(H, W) plane units horizontally, so the
//!   ray cannot jump over a pixel-wide ridge along an axis (a one-pixel-wide
//!   ridge crossed diagonally can fall between two samples: the usual
//!   height-field-march trade-off);
//! - a sample counts while t_k < l (before the light) and the sample lies in
//!   the material square |x|, |y| <= 1 (past it the ray never comes back);
//! - the pixel is in shadow if any counted sample is strictly below the
//!   height field there, h being bilinear between pixel centres (edge values
//!   extended over the half-pixel border). Samples above max(h) on a rising
//!   ray cannot be blocked, which lets the march stop early.
//!
//! A flat height field never blocks a light above it, so shadowed renders of
//! flat materials are bit-identical to unshadowed ones. Shading itself is
//! unchanged (directions from the pixel centre at z = 0); visibility only
//! multiplies it (hard shadows: 0 or 1; a disc light: the fraction of its
//! sample points that are visible).

use crate::geometry::{cross, dot, normalize, Vec3};
use anyhow::{ensure, Result};
use serde::{Deserialize, Serialize};

/// Most points a disc light may be sampled with.
pub const MAX_LIGHT_SAMPLES: usize = 1024;

/// How shadows are cast.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShadowOptions {
    /// Multiplies the height field before marching (taller or flatter relief
    /// for shadows; the shading normals are not changed).
    pub height_scale: f64,
    /// Radius of a disc light centred on the point light and facing the
    /// material centre (plane units); 0 gives a point light and hard shadows.
    pub light_radius: f64,
    /// Fixed points sampled on the disc light when `light_radius > 0`.
    pub light_samples: usize,
}

impl Default for ShadowOptions {
    fn default() -> Self {
        Self { height_scale: 1.0, light_radius: 0.0, light_samples: 16 }
    }
}

impl ShadowOptions {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.height_scale.is_finite() && self.height_scale >= 0.0, "height scale must be a finite number >= 0 (got {})", self.height_scale);
        ensure!(self.light_radius.is_finite() && self.light_radius >= 0.0, "light radius must be a finite number >= 0 (got {})", self.light_radius);
        ensure!(
            (1..=MAX_LIGHT_SAMPLES).contains(&self.light_samples),
            "light samples must be between 1 and {MAX_LIGHT_SAMPLES} (got {})",
            self.light_samples
        );
        Ok(())
    }

    /// Points whose visibility is averaged for a light at `light`: the light
    /// itself, or the disc light's sample points.
    pub fn light_points(&self, light: Vec3) -> Vec<Vec3> {
        disc_light_points(light, self.light_radius, self.light_samples)
    }

    /// Number of points [`ShadowOptions::light_points`] returns.
    pub fn points_per_light(&self) -> usize {
        if self.light_radius > 0.0 && self.light_samples > 1 {
            self.light_samples
        } else {
            1
        }
    }
}

/// Horizontal march step for an H x W height field: one pixel, 2 / max(H, W).
pub fn march_step(h: usize, w: usize) -> f64 {
    2.0 / h.max(w).max(1) as f64
}

/// Steps that always reach the edge of the material: the diagonal 2 sqrt 2
/// in steps, plus one.
pub fn full_march_steps(h: usize, w: usize) -> i64 {
    (2.0 * std::f64::consts::SQRT_2 / march_step(h, w)).ceil() as i64 + 1
}

/// `samples` fixed points on a disc of `radius` centred on `light`, facing the
/// material centre (the disc's normal is `light` normalised). The points
/// follow a golden-angle (Vogel) spiral: evenly spread, deterministic, and
/// scaling the radius scales the pattern, so the visible fraction behind a
/// straight occluder edge grows monotonically as the light shrinks.
/// `radius <= 0` or `samples <= 1` gives the point light alone.
pub fn disc_light_points(light: Vec3, radius: f64, samples: usize) -> Vec<Vec3> {
    if radius.is_nan() || radius <= 0.0 || samples <= 1 {
        return vec![light];
    }
    let n = if dot(light, light) > 1e-24 { normalize(light) } else { [0.0, 0.0, 1.0] };
    // Any axis not parallel to n gives a tangent frame.
    let a = if n[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let u = normalize(cross(n, a));
    let v = cross(n, u);
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..samples)
        .map(|i| {
            let r = radius * ((i as f64 + 0.5) / samples as f64).sqrt();
            let (s, c) = (i as f64 * golden).sin_cos();
            [0, 1, 2].map(|k| light[k] + r * (c * u[k] + s * v[k]))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{pixel_center, sample_configs, LightView, Sampling};
    use crate::image::Image;
    use crate::svbrdf::render::{render, render_shadowed, shadow_mask, shadow_visibility};
    use crate::svbrdf::{cpu, scalar, Svbrdf};
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;
    use tch::{Kind, Tensor};

    /// Random smooth height field: a few random sinusoids, plane units.
    fn smooth_field(rng: &mut Pcg64, n: usize, amplitude: f32) -> Image {
        let waves: Vec<[f32; 4]> = (0..4)
            .map(|_| [rng.random_range(-6.0..6.0), rng.random_range(-6.0..6.0), rng.random_range(0.0..6.3), amplitude * rng.random_range(0.3..1.0)])
            .collect();
        Image::from_fn(1, n, n, |_, r, c| {
            let p = pixel_center(r, c, n, n);
            waves.iter().map(|w| w[3] * (w[0] * p[0] as f32 + w[1] * p[1] as f32 + w[2]).sin()).sum()
        })
    }

    /// A box of height `b` over columns [c0, c1) and rows [r0, r1) on a flat plane.
    fn box_field(n: usize, b: f32, (r0, r1): (usize, usize), (c0, c1): (usize, usize)) -> Image {
        Image::from_fn(1, n, n, |_, r, c| if (r0..r1).contains(&r) && (c0..c1).contains(&c) { b } else { 0.0 })
    }

    fn random_material(rng: &mut Pcg64, n: usize) -> Svbrdf {
        let mut m = Svbrdf::uniform(n, n, [0.0; 3], [0.0; 3], 0.5);
        for v in m.diffuse.data.iter_mut().chain(m.specular.data.iter_mut()) {
            *v = rng.random();
        }
        for v in m.roughness.data.iter_mut() {
            *v = rng.random_range(0.05..1.0);
        }
        for y in 0..n {
            for x in 0..n {
                let d = crate::geometry::normalize([rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 1.0]);
                (0..3).for_each(|c| m.normal.set(c, y, x, d[c] as f32));
            }
        }
        m
    }

    /// Tensor mask `[1, K, 1, H, W]` for one field, as a flat Vec.
    fn tensor_mask(field: &Image, lights: &[[f64; 3]], kind: Kind, options: &ShadowOptions) -> Vec<f64> {
        let hts = field.to_tensor().unsqueeze(0).to_kind(kind);
        let flat: Vec<f64> = lights.iter().flatten().copied().collect();
        let lt = Tensor::from_slice(&flat).view([1, lights.len() as i64, 3]);
        let m = shadow_visibility(&hts, &lt, options, full_march_steps(field.height, field.width)).unwrap();
        assert_eq!(m.size(), [1, lights.len() as i64, 1, field.height as i64, field.width as i64]);
        Vec::try_from(m.to_kind(Kind::Double).flatten(0, -1)).unwrap()
    }

    fn scalar_mask(field: &Image, lights: &[[f64; 3]], options: &ShadowOptions) -> Vec<f64> {
        let n = field.height;
        let scaled = field.map(|v| v * options.height_scale as f32);
        let mut out = vec![];
        for &l in lights {
            for r in 0..n {
                for c in 0..n {
                    let p = pixel_center(r, c, n, n);
                    out.push(scalar::visibility_disc(&scaled, p[0], p[1], l, options.light_radius, options.light_samples));
                }
            }
        }
        out
    }

    fn cpu_mask(field: &Image, lights: &[[f64; 3]], options: &ShadowOptions) -> Vec<f64> {
        cpu::visibility(field, lights, options).unwrap().into_iter().map(f64::from).collect()
    }

    fn disagreement(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).filter(|(x, y)| (*x - *y).abs() > 1e-6).count() as f64 / a.len() as f64
    }

    #[test]
    fn flat_height_field_gives_the_unshadowed_render() {
        let mut rng = Pcg64::seed_from_u64(11);
        let n = 16;
        let m = Svbrdf { height_field: Some(Image::new(1, n, n)), ..random_material(&mut rng, n) };
        let mut configs = sample_configs(&mut rng, Sampling::Reflect, 5, 28.0);
        configs.extend(sample_configs(&mut rng, Sampling::Hemisphere, 3, 28.0));
        configs.push(LightView { light: [3.0, 0.5, 1e-3], view: [0.0, 0.0, 4.0] }); // grazing
        // A disc light stays above the plane only if the radius is below its height.
        let min_z = configs.iter().map(|c| c.light[2]).fold(f64::MAX, f64::min);
        let soft = ShadowOptions { light_radius: 0.5 * min_z, light_samples: 8, height_scale: 3.0 };
        for options in [ShadowOptions::default(), soft] {
            // CPU renderer: bitwise.
            let (r, wi, wo) = cpu::render_with_directions(&m, &configs);
            let (rs, wis, wos) = cpu::render_with_directions_shadowed(&m, &configs, &options).unwrap();
            assert!(r == rs && wi == wis && wo == wos);
            assert_eq!(cpu::render_shadowed(&m, &configs, &options).unwrap(), r);
            // Tensor renderer: bitwise.
            let maps = m.stacked().to_tensor().unsqueeze(0);
            let (l, v) = crate::geometry::config_tensors(&configs, tch::Device::Cpu);
            let k = configs.len() as i64;
            let (l, v) = (l.view([1, k, 3]), v.view([1, k, 3]));
            let plain = render(&maps, &l, &v);
            let shadowed = render_shadowed(&maps, &Tensor::zeros([1, 1, n as i64, n as i64], (Kind::Float, tch::Device::Cpu)), &l, &v, &options).unwrap();
            assert!(plain.equal(&shadowed));
        }
    }

    #[test]
    fn a_box_casts_a_shadow_of_the_expected_length() {
        let n = 64;
        let step = march_step(n, n);
        let (b, c0, c1) = (0.25f32, 30, 40);
        let field = box_field(n, b, (16, 48), (c0, c1));
        for elevation in [20f64, 30.0, 45.0] {
            let e = elevation.to_radians();
            // A distant light towards +x: the direction is constant within 1e-3 rad.
            let d = 1e3;
            let lights = [[d * e.cos(), 0.0, d * e.sin()]];
            let expected = b as f64 / e.tan();
            let options = ShadowOptions::default();
            for (name, mask) in [
                ("scalar", scalar_mask(&field, &lights, &options)),
                ("tensor", tensor_mask(&field, &lights, Kind::Float, &options)),
                ("cpu", cpu_mask(&field, &lights, &options)),
            ] {
                for row in [20, 32, 44] {
                    let lit = |c: usize| mask[row * n + c] == 1.0;
                    // Shadow: the contiguous run of dark pixels left of the box.
                    let len = (0..c0).rev().take_while(|&c| !lit(c)).count();
                    assert!((0..c0 - len).all(lit), "{name}: stray shadow on row {row}");
                    assert!((c0..n).all(lit), "{name}: box top or the lit side is shadowed on row {row}");
                    let measured = len as f64 * step;
                    if row == 32 {
                        eprintln!("{name} elevation {elevation}: shadow {len} px = {measured:.4}, expected b / tan e = {expected:.4} ({:.2} px)", expected / step);
                    }
                    assert!((measured - expected).abs() <= step, "{name} e={elevation}: shadow {measured} vs {expected} (one pixel = {step})");
                }
                // Rows beside the box are lit everywhere.
                assert!((0..n).all(|c| mask[8 * n + c] == 1.0 && mask[56 * n + c] == 1.0), "{name}");
            }
        }
    }

    #[test]
    fn tensor_and_cpu_march_agree_with_the_oracle() {
        let mut rng = Pcg64::seed_from_u64(21);
        let n = 32;
        let (mut total, mut dark) = (0usize, 0usize);
        let (mut bad_f32, mut bad_f64, mut bad_cpu) = (0f64, 0f64, 0f64);
        let fields = 3;
        for _ in 0..fields {
            let field = smooth_field(&mut rng, n, 0.06);
            let mut lights = vec![];
            for i in 0..8 {
                let elev = if i == 0 { 3f64 } else { rng.random_range(8.0..70.0) }.to_radians();
                let az = rng.random_range(0.0..std::f64::consts::TAU);
                let dist = rng.random_range(1.5..6.0);
                lights.push([dist * elev.cos() * az.cos(), dist * elev.cos() * az.sin(), dist * elev.sin()]);
            }
            lights.push([0.3, -0.2, 0.05]); // low and over the material
            let options = ShadowOptions::default();
            let oracle = scalar_mask(&field, &lights, &options);
            let t32 = tensor_mask(&field, &lights, Kind::Float, &options);
            let t64 = tensor_mask(&field, &lights, Kind::Double, &options);
            let c32 = cpu_mask(&field, &lights, &options);
            total += oracle.len();
            dark += oracle.iter().filter(|&&v| v == 0.0).count();
            bad_f32 += disagreement(&t32, &oracle) * oracle.len() as f64;
            bad_f64 += disagreement(&t64, &oracle) * oracle.len() as f64;
            bad_cpu += disagreement(&c32, &t32) * oracle.len() as f64;
        }
        let total_f = total as f64;
        eprintln!(
            "{total} rays, {:.1}% shadowed; disagreement: tensor f32 vs oracle {:.4}%, tensor f64 vs oracle {:.4}%, cpu vs tensor f32 {:.4}%",
            100.0 * dark as f64 / total_f,
            100.0 * bad_f32 / total_f,
            100.0 * bad_f64 / total_f,
            100.0 * bad_cpu / total_f
        );
        assert!(dark as f64 > 0.1 * total_f, "too few shadows to test anything");
        assert!(bad_f32 / total_f < 2e-3 && bad_f64 / total_f < 1e-3 && bad_cpu / total_f < 1e-3);
    }

    #[test]
    fn soft_shadows_grow_with_the_light_radius() {
        let n = 64;
        let field = box_field(n, 0.25, (8, 56), (30, 40));
        // Light towards +x at 30 degrees, close enough for the radius to matter.
        let e = 30f64.to_radians();
        let lights = [[3.0 * e.cos(), 0.0, 3.0 * e.sin()]];
        let hard = tensor_mask(&field, &lights, Kind::Float, &ShadowOptions::default());
        let row = 32;
        let edge = (0..30).rev().take_while(|&c| hard[row * n + c] == 0.0).count();
        let (inside, outside) = (30 - edge + 1, 30 - edge - 2); // just inside / outside the hard shadow
        let mut last: Option<[f64; 2]> = None;
        let mut penumbra = false;
        for radius in [0.0, 0.05, 0.1, 0.2, 0.3, 0.5] {
            let options = ShadowOptions { light_radius: radius, light_samples: 64, ..Default::default() };
            let t = tensor_mask(&field, &lights, Kind::Float, &options);
            let c = cpu_mask(&field, &lights, &options);
            let s = scalar_mask(&field, &lights, &options);
            for v in t.iter().chain(&c).chain(&s) {
                assert!((0.0..=1.0).contains(v));
            }
            let max_diff = t.iter().zip(&c).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(max_diff <= 1.0 / 64.0 + 1e-6, "cpu vs tensor {max_diff}");
            let now = [t[row * n + outside], t[row * n + inside]];
            assert!((now[0] - s[row * n + outside]).abs() <= 1.0 / 64.0 + 1e-6);
            if let Some(prev) = last {
                // A larger light: the lit side darkens, the shadow side brightens.
                assert!(now[0] <= prev[0] && now[1] >= prev[1], "radius {radius}: {prev:?} -> {now:?}");
            }
            penumbra |= now[0] > 0.0 && now[0] < 1.0;
            eprintln!("radius {radius}: visibility outside {:.3}, inside {:.3}", now[0], now[1]);
            last = Some(now);
        }
        assert!(penumbra, "no penumbra at the shadow edge");
    }

    #[test]
    fn bad_inputs_are_errors() {
        let h = Tensor::zeros([1, 1, 8, 8], (Kind::Float, tch::Device::Cpu));
        let l = Tensor::from_slice(&[0.0f32, 0.0, 4.0]).view([1, 1, 3]);
        assert!(shadow_mask(&h.view([1, 8, 8]), &l, 10).is_err());
        assert!(shadow_mask(&h, &l.view([1, 3]), 10).is_err());
        assert!(shadow_mask(&h, &Tensor::zeros([2, 1, 3], (Kind::Float, tch::Device::Cpu)), 10).is_err());
        assert!(shadow_mask(&h.to_kind(Kind::Int), &l, 10).is_err());
        assert!(shadow_mask(&(h.shallow_clone() / 0.0), &l, 10).unwrap_err().to_string().contains("NaN"));
        let bad = ShadowOptions { light_samples: 0, ..Default::default() };
        assert!(shadow_visibility(&h, &l, &bad, 10).is_err());
        assert!(cpu::visibility(&Image::new(2, 8, 8), &[[0.0, 0.0, 4.0]], &ShadowOptions::default()).is_err());
        assert!(cpu::visibility(&Image::new(1, 8, 8), &[[0.0, f64::NAN, 4.0]], &ShadowOptions::default()).is_err());
        // Height fields that do not fit the material are refused.
        let m = Svbrdf { height_field: Some(Image::new(1, 4, 4)), ..Svbrdf::uniform(8, 8, [0.5; 3], [0.04; 3], 0.5) };
        assert!(cpu::render_shadowed(&m, &[LightView::colocated(28.0)], &ShadowOptions::default()).is_err());
        // Zero steps or no lights: everything lit.
        assert!(bool::try_from(shadow_mask(&h, &l, 0).unwrap().eq(1.0).all()).unwrap());
    }


    #[test]
    fn disc_points_lie_on_the_disc() {
        let l = [1.0, -2.0, 3.0];
        let pts = disc_light_points(l, 0.5, 32);
        assert_eq!(pts.len(), 32);
        let n = crate::geometry::normalize(l);
        let mut mean = [0.0; 3];
        for p in &pts {
            let d = crate::geometry::sub(*p, l);
            assert!(crate::geometry::dot(d, n).abs() < 1e-12, "off the disc plane");
            assert!(crate::geometry::dot(d, d).sqrt() <= 0.5 + 1e-12);
            (0..3).for_each(|k| mean[k] += d[k] / 32.0);
        }
        // The spiral is balanced around the centre.
        assert!(crate::geometry::dot(mean, mean).sqrt() < 0.05, "{mean:?}");
        assert_eq!(disc_light_points(l, 0.0, 32), vec![l]);
        assert_eq!(disc_light_points(l, 0.3, 1), vec![l]);
    }

    #[test]
    fn options_are_checked() {
        assert!(ShadowOptions::default().validate().is_ok());
        for bad in [
            ShadowOptions { height_scale: -1.0, ..Default::default() },
            ShadowOptions { height_scale: f64::NAN, ..Default::default() },
            ShadowOptions { light_radius: f64::INFINITY, ..Default::default() },
            ShadowOptions { light_samples: 0, ..Default::default() },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
        assert_eq!(march_step(32, 64), 2.0 / 64.0);
        assert_eq!(full_march_steps(64, 64), 92);
    }
}
