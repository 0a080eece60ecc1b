//! The paper's GGX renderer as batched tensor ops (CPU or CUDA): many
//! materials times many light/view configurations in one call.

use super::shadow::{full_march_steps, march_step, ShadowOptions};
use crate::geometry::{direction_maps, half_vectors, half_vectors_along, pixel_positions};
use anyhow::{bail, ensure, Result};
use std::f64::consts::PI;
use tch::{Kind, Tensor};

use super::ggx::{DOT_EPS, FRESNEL_SG_A, FRESNEL_SG_B, SPECULAR_DENOM_EPS};

fn dot(a: &Tensor, b: &Tensor) -> Tensor {
    (a * b).sum_dim_intlist([-3i64].as_slice(), true, a.kind())
}

/// Radiance R = f * NoL * pi for explicit directions.
///
/// maps: `[N, 10, H, W]` (kd, ks, roughness, unit normal; linear);
/// wi, wo: `[N, K, 3, H, W]` unit vectors -> `[N, K, 3, H, W]`.
pub fn render_directions(maps: &Tensor, wi: &Tensor, wo: &Tensor) -> Tensor {
    let maps = maps.unsqueeze(1); // [N, 1, 10, H, W]
    let kd = maps.narrow(2, 0, 3);
    let ks = maps.narrow(2, 3, 3);
    let rough = maps.narrow(2, 6, 1);
    let normal = maps.narrow(2, 7, 3);
    let h = half_vectors_along(wi, wo, -3);
    let n_dot_h = dot(&normal, &h).clamp_min(DOT_EPS);
    let n_dot_v = dot(&normal, wo).clamp_min(DOT_EPS);
    let n_dot_l = dot(&normal, wi).clamp_min(DOT_EPS);
    let v_dot_h = dot(wo, &h).clamp_min(DOT_EPS);

    let alpha = rough.square();
    let a2 = alpha.square();
    let denom = (n_dot_h.square() * (&a2 - 1.0) + 1.0).clamp_min(DOT_EPS);
    let d = &a2 / (denom.square() * PI);
    let k = (&alpha / 2.0).clamp_min(DOT_EPS);
    let g1 = |x: &Tensor| x / (x * (1.0 - &k) + &k);
    let g = g1(&n_dot_l) * g1(&n_dot_v);
    let fresnel_weight = ((&v_dot_h * FRESNEL_SG_A + FRESNEL_SG_B) * &v_dot_h * std::f64::consts::LN_2).exp();
    let f = &ks + (1.0 - &ks) * fresnel_weight;
    let specular = d * g * f / (&n_dot_l * &n_dot_v * 4.0 + SPECULAR_DENOM_EPS);
    let brdf = kd / PI + specular;
    brdf * n_dot_l * PI
}

/// Per-pixel light and view direction maps for point lights and cameras.
/// lights, views: `[N, K, 3]` -> (wi, wo) each `[N, K, 3, H, W]`.
pub fn direction_maps_for(lights: &Tensor, views: &Tensor, h: usize, w: usize) -> (Tensor, Tensor) {
    let (n, k) = (lights.size()[0], lights.size()[1]);
    let pos = pixel_positions(h, w, (lights.kind(), lights.device()));
    let wi = direction_maps(&pos, &lights.reshape([n * k, 3])).view([n, k, 3, h as i64, w as i64]);
    let wo = direction_maps(&pos, &views.reshape([n * k, 3])).view([n, k, 3, h as i64, w as i64]);
    (wi, wo)
}

/// Renders N materials under K point-light/camera configurations each.
/// maps: `[N, 10, H, W]`; lights, views: `[N, K, 3]` -> `[N, K, 3, H, W]`.
pub fn render(maps: &Tensor, lights: &Tensor, views: &Tensor) -> Tensor {
    let size = maps.size();
    let (wi, wo) = direction_maps_for(lights, views, size[2] as usize, size[3] as usize);
    render_directions(maps, &wi, &wo)
}

/// z component of the half vector, the h_z input channel of M_est.
/// wi, wo: `[B, 3, H, W]` -> `[B, 1, H, W]`.
pub fn half_vector_z(wi: &Tensor, wo: &Tensor) -> Tensor {
    half_vectors(wi, wo).narrow(1, 2, 1)
}

/// Hard-shadow visibility of point lights over height fields, marched as
/// [`super::shadow`] defines (one-pixel steps, bilinear heights through
/// `grid_sampler_2d`, so it runs on CPU and CUDA).
///
/// heights: `[N, 1, H, W]` (plane units; float or double); lights: `[N, K, 3]`
/// -> `[N, K, 1, H, W]` of the heights' kind and device, 1 lit, 0 shadowed.
/// `steps` caps the samples per ray; [`full_march_steps`] always reaches the
/// material's edge. The march also stops once no ray can still be blocked
/// (past its light, the diagonal, or, rising, above the tallest height), so
/// low relief costs few steps.
pub fn shadow_mask(heights: &Tensor, lights: &Tensor, steps: i64) -> Result<Tensor> {
    let hs = heights.size();
    let ls = lights.size();
    if hs.len() != 4 || hs[1] != 1 {
        bail!("shadow_mask: heights must be [N, 1, H, W], got {hs:?}");
    }
    if ls.len() != 3 || ls[0] != hs[0] || ls[2] != 3 {
        bail!("shadow_mask: lights must be [N, K, 3] with N = {}, got {ls:?}", hs[0]);
    }
    let kind = heights.kind();
    ensure!(matches!(kind, Kind::Float | Kind::Double), "shadow_mask: heights must be float or double, got {kind:?}");
    let (n, k, h, w) = (hs[0], ls[1], hs[2], hs[3]);
    let device = heights.device();
    let lit = Tensor::ones([n, k, 1, h, w], (kind, device));
    if n == 0 || k == 0 || h == 0 || w == 0 || steps < 1 {
        return Ok(lit);
    }
    let lights = lights.to_kind(kind).to_device(device);
    ensure!(bool::try_from(heights.isfinite().all())?, "shadow_mask: heights hold NaN/Inf values");
    ensure!(bool::try_from(lights.isfinite().all())?, "shadow_mask: lights hold NaN/Inf values");

    let pos = pixel_positions(h as usize, w as usize, (kind, device));
    let x0 = pos.get(0).view([1, 1, h, w]);
    let y0 = pos.get(1).view([1, 1, h, w]);
    let light = |c: i64| lights.select(2, c).view([n, k, 1, 1]);
    // Per ray [N, K, H, W]: horizontal length, unit direction and slope.
    let dx = light(0) - &x0;
    let dy = light(1) - &y0;
    let dz = light(2) - heights;
    let len = (dx.square() + dy.square()).sqrt();
    let inv = len.clamp_min(1e-12).reciprocal();
    let (ux, uy, slope) = (dx * &inv, dy * &inv, dz * &inv);

    // Samples past this distance cannot be blocked; bound the loop by the
    // longest such distance over all rays (one host sync).
    let step = march_step(h as usize, w as usize);
    let hmax = heights.amax([1i64, 2, 3].as_slice(), true);
    let rise = (hmax - heights) / slope.clamp_min(1e-30);
    let reach = len.minimum(&rise.where_self(&slope.gt(0.0), &len)).clamp_max(2.0 * std::f64::consts::SQRT_2);
    let reach = reach.max().double_value(&[]);
    let steps = steps.min((reach / step).ceil() as i64 + 1);

    let mut blocked = Tensor::zeros([n, k, h, w], (Kind::Bool, device));
    for s in 1..=steps {
        let t = s as f64 * step;
        let xs = &x0 + &ux * t;
        let ys = &y0 + &uy * t;
        let counted = len.gt(t).logical_and(&xs.abs().le(1.0)).logical_and(&ys.abs().le(1.0));
        let zs = heights + &slope * t;
        // grid_sampler's (x, y) in [-1, 1] with align_corners = false is our
        // plane point with y flipped (row 0 is at the top); K lights are
        // stacked along the output rows. Border padding extends edge values.
        let grid = Tensor::stack(&[&xs, &(-&ys)], -1).view([n, k * h, w, 2]);
        let surface = heights.grid_sampler_2d(&grid, 0, 1, false).view([n, k, h, w]);
        blocked = blocked.logical_or(&counted.logical_and(&zs.lt_tensor(&surface)));
    }
    Ok(blocked.logical_not().to_kind(kind).unsqueeze(2))
}

/// Shadow visibility with [`ShadowOptions`]: heights times `height_scale`,
/// and for a disc light the mean over its sample points.
/// heights: `[N, 1, H, W]`; lights: `[N, K, 3]` -> `[N, K, 1, H, W]` in [0, 1].
pub fn shadow_visibility(heights: &Tensor, lights: &Tensor, options: &ShadowOptions, steps: i64) -> Result<Tensor> {
    options.validate()?;
    let scaled;
    let heights = if options.height_scale == 1.0 {
        heights
    } else {
        scaled = heights * options.height_scale;
        &scaled
    };
    let per = options.points_per_light() as i64;
    if per == 1 {
        return shadow_mask(heights, lights, steps);
    }
    let ls = lights.size();
    if ls.len() != 3 || ls[2] != 3 {
        bail!("shadow_visibility: lights must be [N, K, 3], got {ls:?}");
    }
    let flat: Vec<f64> = Vec::try_from(lights.to_device(tch::Device::Cpu).to_kind(Kind::Double).contiguous().flatten(0, -1))?;
    let points: Vec<f64> = flat.chunks(3).flat_map(|l| options.light_points([l[0], l[1], l[2]])).flatten().collect();
    let (n, k) = (ls[0], ls[1]);
    let points = Tensor::from_slice(&points).view([n, k * per, 3]).to_device(heights.device());
    let size = heights.size();
    let mask = shadow_mask(heights, &points, steps)?.view([n, k, per, 1, size[2], size[3]]);
    Ok(mask.sum_dim_intlist([2i64].as_slice(), false, heights.kind()) / per as f64)
}

/// Renders with shadows from height fields (heights times
/// `options.height_scale`); flat height fields give exactly [`render`].
/// maps: `[N, 10, H, W]`; heights: `[N, 1, H, W]`; lights, views: `[N, K, 3]`
/// -> `[N, K, 3, H, W]`.
pub fn render_shadowed(maps: &Tensor, heights: &Tensor, lights: &Tensor, views: &Tensor, options: &ShadowOptions) -> Result<Tensor> {
    let size = maps.size();
    ensure!(size.len() == 4, "render_shadowed: maps must be [N, 10, H, W], got {size:?}");
    ensure!(
        heights.size() == [size[0], 1, size[2], size[3]],
        "render_shadowed: heights {:?} do not match maps {size:?}",
        heights.size()
    );
    let vis = shadow_visibility(&heights.to_kind(maps.kind()), lights, options, full_march_steps(size[2] as usize, size[3] as usize))?;
    Ok(render(maps, lights, views) * vis)
}

/// Renders one material (CPU) under several configurations; linear images `[3, H, W]`.
pub fn render_material(material: &crate::svbrdf::Svbrdf, configs: &[crate::geometry::LightView]) -> anyhow::Result<Vec<crate::image::Image>> {
    material.validate()?;
    let maps = material.stacked().to_tensor().unsqueeze(0);
    let (lights, views) = crate::geometry::config_tensors(configs, tch::Device::Cpu);
    let k = configs.len() as i64;
    let out = tch::no_grad(|| render(&maps, &lights.view([1, k, 3]), &views.view([1, k, 3])));
    (0..k).map(|i| crate::image::Image::from_tensor(&out.get(0).get(i))).collect()
}

/// [`render_material`] with shadows from the material's height field (one is
/// integrated from its normals when it has none).
pub fn render_material_shadowed(
    material: &crate::svbrdf::Svbrdf,
    configs: &[crate::geometry::LightView],
    options: &ShadowOptions,
) -> anyhow::Result<Vec<crate::image::Image>> {
    material.validate()?;
    options.validate()?;
    let heights = crate::svbrdf::height::shadow_heights(material)?.to_tensor().unsqueeze(0);
    let maps = material.stacked().to_tensor().unsqueeze(0);
    let (lights, views) = crate::geometry::config_tensors(configs, tch::Device::Cpu);
    let k = configs.len() as i64;
    let out = tch::no_grad(|| render_shadowed(&maps, &heights, &lights.view([1, k, 3]), &views.view([1, k, 3]), options))?;
    (0..k).map(|i| crate::image::Image::from_tensor(&out.get(0).get(i))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pixel_center;
    use crate::svbrdf::scalar::{self, PixelMaterial};
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;
    use tch::{Device, Kind};

    fn random_maps(rng: &mut Pcg64, n: usize, h: usize, w: usize) -> Vec<f32> {
        let mut v = vec![0f32; n * 10 * h * w];
        let plane = h * w;
        for m in 0..n {
            for p in 0..plane {
                let base = m * 10 * plane;
                for c in 0..6 {
                    v[base + c * plane + p] = rng.random::<f32>();
                }
                // Include the extremes of roughness.
                v[base + 6 * plane + p] = match p % 7 {
                    0 => 0.0,
                    1 => 1.0,
                    _ => rng.random::<f32>(),
                };
                let nrm = crate::geometry::normalize([rng.random_range(-0.6..0.6), rng.random_range(-0.6..0.6), 1.0]);
                for c in 0..3 {
                    v[base + (7 + c) * plane + p] = nrm[c] as f32;
                }
            }
        }
        v
    }

    #[test]
    fn tensor_renderer_equals_scalar_oracle() {
        let mut rng = Pcg64::seed_from_u64(1234);
        let (n, k, h, w) = (2usize, 5usize, 8usize, 8usize);
        let maps_v = random_maps(&mut rng, n, h, w);
        let maps = Tensor::from_slice(&maps_v).view([n as i64, 10, h as i64, w as i64]).to_kind(Kind::Double);
        // Lights and views include grazing ones (z close to 0) and far ones.
        let mut lights = vec![];
        let mut views = vec![];
        for i in 0..n * k {
            let gz = if i % 3 == 0 { 1e-3 } else { rng.random_range(0.1..5.0) };
            lights.extend([rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), gz]);
            views.extend([rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(0.05..5.0)]);
        }
        let lt = Tensor::from_slice(&lights).view([n as i64, k as i64, 3]);
        let vt = Tensor::from_slice(&views).view([n as i64, k as i64, 3]);
        let out = render(&maps, &lt, &vt);
        assert_eq!(out.size(), [n as i64, k as i64, 3, h as i64, w as i64]);
        let out: Vec<f64> = Vec::try_from(out.flatten(0, -1)).unwrap();
        let plane = h * w;
        let mut worst = 0f64;
        for m in 0..n {
            for cfg in 0..k {
                let li = &lights[(m * k + cfg) * 3..][..3];
                let vi = &views[(m * k + cfg) * 3..][..3];
                for i in 0..h {
                    for j in 0..w {
                        let p = i * w + j;
                        let g = |c: usize| maps_v[m * 10 * plane + c * plane + p] as f64;
                        let mat = PixelMaterial {
                            kd: [g(0), g(1), g(2)],
                            ks: [g(3), g(4), g(5)],
                            roughness: g(6),
                            normal: [g(7), g(8), g(9)],
                        };
                        let r = scalar::radiance_at(&mat, pixel_center(i, j, h, w), [li[0], li[1], li[2]], [vi[0], vi[1], vi[2]]);
                        for c in 0..3 {
                            let t = out[(((m * k + cfg) * 3 + c) * h + i) * w + j];
                            let rel = (t - r[c]).abs() / r[c].abs().max(1e-6);
                            worst = worst.max(rel);
                        }
                    }
                }
            }
        }
        assert!(worst < 1e-5, "max relative error {worst}");
    }

    #[test]
    fn float32_renderer_close_to_oracle_and_finite() {
        let mut rng = Pcg64::seed_from_u64(9);
        let maps = Tensor::from_slice(&random_maps(&mut rng, 1, 16, 16)).view([1, 10, 16, 16]);
        let lights = Tensor::from_slice(&[0.0f32, 0.0, 4.0, 5.0, 0.0, 1e-4]).view([1, 2, 3]);
        let out = render(&maps, &lights, &lights);
        assert!(bool::try_from(out.isfinite().all()).unwrap());
        assert!(out.min().double_value(&[]) >= 0.0);
    }

    #[test]
    fn diffuse_only_overhead_gives_kd() {
        // Roughness 1, ks 0: the specular lobe is the Fresnel tail only; with
        // ks = 0 the radiance at the centre pixel is kd + tail (see scalar tests).
        let kd = [0.25f32, 0.5, 0.75];
        let h = 2;
        let mut v = vec![0f32; 10 * h * h];
        for p in 0..h * h {
            for c in 0..3 {
                v[c * 4 + p] = kd[c];
            }
            v[6 * 4 + p] = 1.0;
            v[9 * 4 + p] = 1.0;
        }
        let maps = Tensor::from_slice(&v).view([1, 10, 2, 2]).to_kind(Kind::Double);
        let wi = Tensor::from_slice(&[0.0f64, 0.0, 1.0]).view([1, 1, 3, 1, 1]).expand([1, 1, 3, 2, 2], false);
        let out = render_directions(&maps, &wi, &wi);
        let tail = 2f64.powf(-5.55473 - 6.98316) / 4.0;
        for c in 0..3 {
            assert!((out.double_value(&[0, 0, c as i64, 1, 0]) - (kd[c] as f64 + tail)).abs() < 1e-7);
        }
    }

    #[test]
    fn batch_is_independent() {
        let mut rng = Pcg64::seed_from_u64(5);
        let maps = Tensor::from_slice(&random_maps(&mut rng, 2, 8, 8)).view([2, 10, 8, 8]);
        let lights = Tensor::from_slice(&[0.5f32, 0.1, 3.0, -1.0, 2.0, 1.0]).view([1, 2, 3]).repeat([2, 1, 1]);
        let views = Tensor::from_slice(&[0.0f32, 0.0, 4.0, 1.0, 1.0, 2.0]).view([1, 2, 3]).repeat([2, 1, 1]);
        let all = render(&maps, &lights, &views);
        let one = render(&maps.narrow(0, 1, 1), &lights.narrow(0, 1, 1).narrow(1, 1, 1), &views.narrow(0, 1, 1).narrow(1, 1, 1));
        let diff = (all.narrow(0, 1, 1).narrow(1, 1, 1) - one).abs().max().double_value(&[]);
        assert!(diff < 1e-6);
        let _ = Device::Cpu;
    }
}

