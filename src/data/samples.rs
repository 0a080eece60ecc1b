//! Training samples (REFERENCE section 5): for a batch of SVBRDFs, the
//! co-located input render with its direction maps, and K output renders
//! under "reflect" (or another) sampling with theirs, on the training device.

use crate::data::phone::{exposure_factor, finish_phone_photo, phone_light_view, PhonePhotoConfig};
use crate::geometry::{config_tensors, sample_configs, LightView, Sampling};
use crate::spaces;
use crate::svbrdf::render::{direction_maps_for, half_vector_z};
use crate::svbrdf::shadow::ShadowOptions;
use crate::svbrdf::{Svbrdf, MAP_CHANNELS};
use anyhow::{bail, ensure, Result};
use rand::Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// How training samples are rendered.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleConfig {
    /// Output renders per material (8 at crop 192, 4 at 256 in the paper).
    pub outputs_per_material: usize,
    /// Field of view of the input camera (sets the co-located distance).
    pub fov_deg: f64,
    /// Clamp the input photo to [0,1] (LDR model); outputs stay HDR.
    pub ldr_input: bool,
    /// Scheme for output configurations.
    pub output_sampling: Sampling,
    /// Of each material's outputs, this many (the last ones) are co-located
    /// instead: the first the input's own configuration (the Identity case),
    /// the others light and camera together at a random point above the
    /// material (x, y ~ U[-1, 1], height U[0.5, 1.5] x the camera's), so
    /// light and view meet at the normal at a random pixel and at
    /// directions between the pixel grid's. "reflect" sampling almost never
    /// puts light and view together near the normal, so without them the
    /// renderer is free to spike there (issue 15).
    #[serde(default)]
    pub colocated_outputs: usize,
    /// Of each material's outputs, this many (just before the co-located
    /// ones) are drawn with "hemisphere" sampling instead: light and camera
    /// independently anywhere above the material, as the paper's Hemisphere
    /// case draws them. "reflect" always puts the mirror highlight in view,
    /// so without them a code that glows away from its highlight is never
    /// seen dark (the rings of a glossy material's flash highlight).
    #[serde(default)]
    pub hemisphere_outputs: usize,
    /// Of each material's outputs, this many (just before the hemisphere
    /// ones) keep the input photo's camera and move the light so that the
    /// mirror highlight lands on the material ([`moved_highlight_config`]):
    /// the moved-highlight test's situation (issue 48). "reflect" puts the
    /// highlight's centre on the material about one draw in seven and
    /// moves the camera with it, so a renderer and an M_est trained on it
    /// rarely see the photographed highlight go and a new one come with the
    /// view held.
    #[serde(default)]
    pub moved_highlight_outputs: usize,
    /// Hard shadows from the materials' height fields (integrated from the
    /// normals where missing) in the input and output renders.
    #[serde(default)]
    pub shadows: bool,
    /// Multiplies the height fields for shadows.
    #[serde(default = "unit_height_scale")]
    pub height_scale: f64,
    /// Share of the materials whose input photo is taken as a phone takes
    /// it ([`crate::data::phone`]: camera off-centre and at another height,
    /// flash beside the lens, brought to the model's exposure, noise,
    /// 8-bit sRGB); M_est is still given the co-located h_z. 0: the
    /// paper's exact co-located render.
    #[serde(default)]
    pub phone_inputs: f64,
    /// How far those photos stray.
    #[serde(default)]
    pub phone: PhonePhotoConfig,
}

fn unit_height_scale() -> f64 {
    1.0
}

impl Default for SampleConfig {
    fn default() -> Self {
        Self {
            outputs_per_material: 8,
            fov_deg: crate::geometry::MODEL_FOV_DEG,
            ldr_input: false,
            output_sampling: Sampling::Reflect,
            colocated_outputs: 0,
            hemisphere_outputs: 0,
            moved_highlight_outputs: 0,
            shadows: false,
            height_scale: 1.0,
            phone_inputs: 0.0,
            phone: PhonePhotoConfig::default(),
        }
    }
}

/// One batch of N materials with K outputs each, all tensors on one device.
pub struct TrainingBatch {
    /// Stacked GGX maps `[N, 10, H, W]`.
    pub maps: Tensor,
    /// Input photo, linear (HDR, or clamped when `ldr_input`) `[N, 3, H, W]`.
    pub input_linear: Tensor,
    /// M_est input: ln(1 + photo) and h_z `[N, 4, H, W]`.
    pub est_input: Tensor,
    /// Output light directions `[N, K, 3, H, W]`.
    pub out_wi: Tensor,
    /// Output view directions `[N, K, 3, H, W]`.
    pub out_wo: Tensor,
    /// Ground-truth output renders, linear HDR `[N, K, 3, H, W]`.
    pub targets: Tensor,
    /// The output configurations, `N * K` in material-major order.
    pub configs: Vec<LightView>,
    /// The same materials photographed again with camera and flash moved
    /// (the shift-consistency term, `TrainConfig::weight_shift`); None: the paper's batch.
    pub shifted: Option<ShiftedPhotos>,
}

impl TrainingBatch {
    /// The batches' materials in one batch, in order: every tensor joined
    /// along its first (material) axis.
    pub fn concat(parts: Vec<TrainingBatch>) -> Result<TrainingBatch> {
        ensure!(!parts.is_empty(), "empty material batch");
        let cat = |f: fn(&TrainingBatch) -> &Tensor| Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 0);
        let shifted = if parts.iter().all(|p| p.shifted.is_some()) {
            let s: Vec<&ShiftedPhotos> = parts.iter().filter_map(|p| p.shifted.as_ref()).collect();
            Some(ShiftedPhotos { est_input: Tensor::cat(&s.iter().map(|s| &s.est_input).collect::<Vec<_>>(), 0), offsets: s.iter().flat_map(|s| s.offsets.clone()).collect() })
        } else {
            None
        };
        Ok(TrainingBatch {
            maps: cat(|b| &b.maps),
            input_linear: cat(|b| &b.input_linear),
            est_input: cat(|b| &b.est_input),
            out_wi: cat(|b| &b.out_wi),
            out_wo: cat(|b| &b.out_wo),
            targets: cat(|b| &b.targets),
            configs: parts.iter().flat_map(|b| b.configs.clone()).collect(),
            shifted,
        })
    }
}

/// Second photos of a batch's materials, each of the window `offsets[i]`
/// = (rows, columns) away from the first photo's (positive: down, right).
pub struct ShiftedPhotos {
    /// M_est input `[N, 4, H, W]`.
    pub est_input: Tensor,
    pub offsets: Vec<(i64, i64)>,
}

/// Stacks materials into `[N, 10, H, W]` on `device`.
pub fn stack_maps(materials: &[Svbrdf], device: Device) -> Result<Tensor> {
    let Some(first) = materials.first() else { bail!("empty material batch") };
    let (h, w) = (first.height(), first.width());
    let mut parts = Vec::with_capacity(materials.len());
    for m in materials {
        if m.height() != h || m.width() != w {
            bail!("materials in one batch must share a size: {}x{} vs {}x{}", m.width(), m.height(), w, h);
        }
        parts.push(m.stacked().to_tensor());
    }
    let maps = Tensor::stack(&parts, 0).to_device(device);
    debug_assert_eq!(maps.size()[1], MAP_CHANNELS as i64);
    Ok(maps)
}

/// M_est input from a linear photo and its half-vector z.
/// photo_linear: `[N, 3, H, W]`, h_z: `[N, 1, H, W]` -> `[N, 4, H, W]`.
pub fn est_input(photo_linear: &Tensor, h_z: &Tensor) -> Tensor {
    Tensor::cat(&[spaces::to_log(&photo_linear.clamp_min(0.0)), h_z.shallow_clone()], 1)
}

/// M_est's input for one photo, as every photo reaches M_est (inference,
/// evaluation, refinement): clamped to [0, 1] for a model trained on LDR
/// photos (as in its training), below at 0 otherwise; h_z of the model's
/// co-located camera at [`crate::geometry::MODEL_FOV_DEG`].
/// photo_linear: `[3, H, W]` -> `[1, 4, H, W]` (f32) on `device`.
pub fn photo_est_input(photo_linear: &Tensor, ldr_model: bool, device: Device) -> Tensor {
    let s = photo_linear.size();
    let linear = photo_linear.to_device(device).to_kind(tch::Kind::Float).unsqueeze(0);
    let linear = if ldr_model { spaces::ldr_clamp(&linear) } else { linear.clamp_min(0.0) };
    let (wi, wo) = input_directions(s[1] as usize, s[2] as usize, crate::geometry::MODEL_FOV_DEG, device);
    est_input(&linear, &half_vector_z(&wi, &wo))
}

/// Co-located input directions for an H x W photo at `fov_deg`:
/// (wi, wo) each `[1, 3, H, W]` (identical, light at the camera).
pub fn input_directions(h: usize, w: usize, fov_deg: f64, device: Device) -> (Tensor, Tensor) {
    let (l, v) = config_tensors(&[LightView::colocated(fov_deg)], device);
    let (wi, wo) = direction_maps_for(&l.view([1, 1, 3]), &v.view([1, 1, 3]), h, w);
    (wi.squeeze_dim(1), wo.squeeze_dim(1))
}

/// Renders each material's input (under `inputs[i]`) and its K outputs,
/// with their direction maps, with the CPU renderer (shadowed when
/// `shadows` is given); `finish(i, photo)` then edits material i's input
/// render (`[3, H, W]` values) in place. Returns (input `[N, 3, H, W]`,
/// outputs, wi, wo `[N, K, 3, H, W]`) on `device`.
fn render_on_cpu(
    materials: &[Svbrdf],
    inputs: &[LightView],
    configs: &[LightView],
    k: usize,
    shadows: Option<&ShadowOptions>,
    finish: &mut dyn FnMut(usize, &mut [f32]) -> Result<()>,
    device: Device,
) -> Result<(Tensor, Tensor, Tensor, Tensor)> {
    let (h, w) = (materials[0].height() as i64, materials[0].width() as i64);
    let (mut input_renders, mut outputs, mut wis, mut wos) = (vec![], vec![], vec![], vec![]);
    for (i, m) in materials.iter().enumerate() {
        let mut all = vec![inputs[i]];
        all.extend_from_slice(&configs[i * k..(i + 1) * k]);
        let (mut r, wi, wo) = match shadows {
            Some(options) => crate::svbrdf::cpu::render_with_directions_shadowed(m, &all, options)?,
            None => crate::svbrdf::cpu::render_with_directions(m, &all),
        };
        finish(i, &mut r[..(3 * h * w) as usize])?;
        let shape = [1 + k as i64, 3, h, w];
        let r = Tensor::from_slice(&r).view(shape);
        input_renders.push(r.get(0));
        outputs.push(r.narrow(0, 1, k as i64));
        wis.push(Tensor::from_slice(&wi).view(shape).narrow(0, 1, k as i64));
        wos.push(Tensor::from_slice(&wo).view(shape).narrow(0, 1, k as i64));
    }
    let stack = |v: &[Tensor]| Tensor::stack(v, 0).to_device(device);
    Ok((stack(&input_renders), stack(&outputs), stack(&wis), stack(&wos)))
}

/// Replaces the last `colocated` of every `k` configurations with co-located
/// ones (`SampleConfig::colocated_outputs`). Drawn after the others, so the
/// remaining configurations are those a run without them draws.
fn with_colocated_outputs<R: Rng>(configs: &mut [LightView], k: usize, colocated: usize, fov_deg: f64, rng: &mut R) -> Result<()> {
    if colocated > k {
        bail!("{colocated} co-located outputs asked of {k} outputs per material");
    }
    let d = crate::geometry::fov_to_distance(fov_deg);
    for material in configs.chunks_mut(k) {
        for (j, config) in material[k - colocated..].iter_mut().enumerate() {
            *config = if j == 0 {
                LightView::colocated(fov_deg)
            } else {
                let at = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), d * rng.random_range(0.5..1.5)];
                LightView { light: at, view: at }
            };
        }
    }
    Ok(())
}

/// Replaces the `hemisphere` configurations before the last `colocated` of
/// every `k` with "hemisphere" draws (`SampleConfig::hemisphere_outputs`),
/// drawn after the others, as `with_colocated_outputs`.
fn with_hemisphere_outputs<R: Rng>(configs: &mut [LightView], k: usize, hemisphere: usize, colocated: usize, rng: &mut R) -> Result<()> {
    if hemisphere + colocated > k {
        bail!("{hemisphere} hemisphere and {colocated} co-located outputs asked of {k} outputs per material");
    }
    for material in configs.chunks_mut(k) {
        for config in &mut material[k - colocated - hemisphere..k - colocated] {
            *config = crate::geometry::sample_hemisphere(rng, crate::geometry::HEMISPHERE_RADIUS);
        }
    }
    Ok(())
}

/// Half-width of the square the moved highlights' centres are drawn in:
/// inside the material ([-1, 1]^2) with the highlight's core clear of the edge.
pub const MOVED_HIGHLIGHT_EXTENT: f64 = 0.8;

/// A moved-highlight configuration: the camera at the co-located photo's
/// (`fov_deg`), the light on the mirror direction of the view about the
/// normal at p = U[-0.8, 0.8]^2, at U[0.5, 1.5] x the camera's distance
/// from p. Returns the configuration and p.
pub fn moved_highlight_config<R: Rng>(rng: &mut R, fov_deg: f64) -> (LightView, [f64; 3]) {
    let view = LightView::colocated(fov_deg).view;
    let e = MOVED_HIGHLIGHT_EXTENT;
    let p = [rng.random_range(-e..e), rng.random_range(-e..e), 0.0];
    let to_view = [view[0] - p[0], view[1] - p[1], view[2]];
    // Mirror about +z: flip the tangential components; same distance times U[0.5, 1.5].
    let dist = rng.random_range(0.5..1.5);
    let light = [p[0] - to_view[0] * dist, p[1] - to_view[1] * dist, to_view[2] * dist];
    (LightView { light, view }, p)
}

/// Replaces the `moved` configurations before the last `hemisphere +
/// colocated` of every `k` with moved-highlight ones
/// (`SampleConfig::moved_highlight_outputs`), drawn after the others.
fn with_moved_highlight_outputs<R: Rng>(configs: &mut [LightView], k: usize, moved: usize, after: usize, fov_deg: f64, rng: &mut R) -> Result<()> {
    if moved + after > k {
        bail!("{moved} moved-highlight outputs and {after} others asked of {k} outputs per material");
    }
    for material in configs.chunks_mut(k) {
        for config in &mut material[k - after - moved..k - after] {
            *config = moved_highlight_config(rng, fov_deg).0;
        }
    }
    Ok(())
}

/// Builds one training batch: input renders plus K sampled output renders.
pub fn make_batch<R: Rng>(materials: &[Svbrdf], cfg: &SampleConfig, rng: &mut R, device: Device) -> Result<TrainingBatch> {
    let maps = stack_maps(materials, device)?;
    let n = maps.size()[0];
    let k = cfg.outputs_per_material as i64;

    let mut configs = sample_configs(rng, cfg.output_sampling, (n * k) as usize, cfg.fov_deg);
    with_colocated_outputs(&mut configs, k as usize, cfg.colocated_outputs, cfg.fov_deg, rng)?;
    with_hemisphere_outputs(&mut configs, k as usize, cfg.hemisphere_outputs, cfg.colocated_outputs, rng)?;
    with_moved_highlight_outputs(&mut configs, k as usize, cfg.moved_highlight_outputs, cfg.hemisphere_outputs + cfg.colocated_outputs, cfg.fov_deg, rng)?;
    // Drawn after the outputs (and not at all without phone inputs), so a
    // run without them draws what it always drew.
    let phone: Vec<Option<LightView>> = (0..n).map(|_| (cfg.phone_inputs > 0.0 && rng.random_bool(cfg.phone_inputs)).then(|| phone_light_view(rng, cfg.fov_deg, &cfg.phone))).collect();
    let inputs: Vec<LightView> = phone.iter().map(|p| p.unwrap_or_else(|| LightView::colocated(cfg.fov_deg))).collect();
    let mut finish = |i: usize, photo: &mut [f32]| match phone[i] {
        Some(p) => finish_phone_photo(photo, materials[i].width(), exposure_factor(p.light, cfg.fov_deg), &cfg.phone, rng),
        None => Ok(()),
    };
    // Input and outputs are rendered together by the f32 CPU renderer (much
    // faster than tensor ops on a CPU), then moved to the device.
    let shadows = ShadowOptions { height_scale: cfg.height_scale, ..Default::default() };
    let shadows = cfg.shadows.then_some(&shadows);
    let (rendered_input, targets, out_wi, out_wo) = render_on_cpu(materials, &inputs, &configs, k as usize, shadows, &mut finish, device)?;
    let (input_linear, est) = training_est_input(rendered_input, cfg, device);
    Ok(TrainingBatch { maps, input_linear, est_input: est, out_wi, out_wo, targets, configs, shifted: None })
}

/// A rendered co-located input photo as training feeds it to M_est:
/// clamped to [0, 1] for LDR inputs, with h_z of the input view.
/// rendered: `[N, 3, H, W]` -> (the photo as M_est sees it, M_est input `[N, 4, H, W]` f32).
fn training_est_input(rendered: Tensor, cfg: &SampleConfig, device: Device) -> (Tensor, Tensor) {
    let size = rendered.size();
    let (n, h, w) = (size[0], size[2], size[3]);
    let input_linear = if cfg.ldr_input { spaces::ldr_clamp(&rendered) } else { rendered };
    let (in_wi, in_wo) = input_directions(h as usize, w as usize, cfg.fov_deg, device);
    let hz = half_vector_z(&in_wi, &in_wo).expand([n, 1, h, w], false);
    let est = est_input(&input_linear, &hz).to_kind(Kind::Float);
    (input_linear, est)
}

/// M_est's input for the co-located photo of each material alone (no
/// outputs), as `make_batch` renders it. -> `[N, 4, H, W]` on `device`.
pub fn input_only(materials: &[Svbrdf], cfg: &SampleConfig, device: Device) -> Result<Tensor> {
    ensure!(!materials.is_empty(), "empty material batch");
    let shadows = ShadowOptions { height_scale: cfg.height_scale, ..Default::default() };
    let inputs = vec![LightView::colocated(cfg.fov_deg); materials.len()];
    let (input, ..) = render_on_cpu(materials, &inputs, &[], 0, cfg.shadows.then_some(&shadows), &mut |_, _| Ok(()), device)?;
    Ok(training_est_input(input, cfg, device).1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{fov_to_distance, pixel_center};
    use crate::svbrdf::scalar;
    use rand::SeedableRng;
    use rand_pcg::Pcg64;

    fn material(h: usize, w: usize, kd: f32) -> Svbrdf {
        let mut s = Svbrdf::uniform(h, w, [kd, 0.5 * kd, 0.2], [0.04; 3], 0.3);
        // A non-trivial normal so the check is not symmetric.
        for y in 0..h {
            for x in 0..w {
                let n = crate::geometry::normalize([0.1 * x as f64 / w as f64, -0.2, 1.0]);
                for c in 0..3 {
                    s.normal.set(c, y, x, n[c] as f32);
                }
            }
        }
        s
    }

    #[test]
    fn batch_shapes_and_input_matches_oracle() {
        let mats = vec![material(8, 16, 0.6), material(8, 16, 0.3)];
        let cfg = SampleConfig { outputs_per_material: 3, ..Default::default() };
        let b = make_batch(&mats, &cfg, &mut Pcg64::seed_from_u64(1), Device::Cpu).unwrap();
        assert_eq!(b.maps.size(), [2, 10, 8, 16]);
        assert_eq!(b.est_input.size(), [2, 4, 8, 16]);
        assert_eq!(b.targets.size(), [2, 3, 3, 8, 16]);
        assert_eq!(b.out_wi.size(), [2, 3, 3, 8, 16]);
        assert_eq!(b.configs.len(), 6);
        // Input pixel vs scalar oracle with the co-located light at d.
        let d = fov_to_distance(28.0);
        let (i, j) = (2usize, 11usize);
        let m = &mats[1];
        let pm = m.pixel_material(i, j);
        let r = scalar::radiance_at(&pm, pixel_center(i, j, 8, 16), [0.0, 0.0, d], [0.0, 0.0, d]);
        for c in 0..3 {
            let t = b.input_linear.double_value(&[1, c as i64, i as i64, j as i64]);
            assert!((t - r[c]).abs() < 1e-4 * r[c].max(1.0), "{t} vs {}", r[c]);
            let l = b.est_input.double_value(&[1, c as i64, i as i64, j as i64]);
            assert!((l - r[c].ln_1p()).abs() < 1e-4);
        }
        // h_z of the co-located configuration = cos of the angle to the camera.
        let p = pixel_center(i, j, 8, 16);
        let expect_hz = d / (p[0] * p[0] + p[1] * p[1] + d * d).sqrt();
        assert!((b.est_input.double_value(&[0, 3, i as i64, j as i64]) - expect_hz).abs() < 1e-5);
        // Output renders equal the oracle for the sampled configuration.
        let cfg1 = b.configs[3 + 2];
        let r = scalar::radiance_at(&pm, pixel_center(i, j, 8, 16), cfg1.light, cfg1.view);
        let t = b.targets.double_value(&[1, 2, 0, i as i64, j as i64]);
        assert!((t - r[0]).abs() < 1e-4 * r[0].max(1.0));
    }

    #[test]
    fn colocated_outputs_replace_the_last_outputs_and_keep_the_others() {
        let mats = vec![material(16, 16, 0.3), material(16, 16, 0.6)];
        let plain = SampleConfig { outputs_per_material: 4, ..Default::default() };
        let with = SampleConfig { colocated_outputs: 2, ..plain.clone() };
        let a = make_batch(&mats, &plain, &mut Pcg64::seed_from_u64(5), Device::Cpu).unwrap();
        let b = make_batch(&mats, &with, &mut Pcg64::seed_from_u64(5), Device::Cpu).unwrap();
        let identity = LightView::colocated(plain.fov_deg);
        let d = fov_to_distance(plain.fov_deg);
        for i in 0..2 {
            // The first two outputs are the reflect draws of a run without the option.
            assert_eq!(&a.configs[i * 4..i * 4 + 2], &b.configs[i * 4..i * 4 + 2]);
            assert_eq!(b.configs[i * 4 + 2], identity);
            let other = b.configs[i * 4 + 3];
            assert_eq!(other.light, other.view);
            assert!(other.light[0].abs() <= 1.0 && other.light[1].abs() <= 1.0 && (0.5 * d..=1.5 * d).contains(&other.light[2]));
            assert_ne!(other, identity);
            // The Identity output re-renders the (HDR) input photo exactly.
            let diff = (b.targets.get(i as i64).get(2) - b.input_linear.get(i as i64)).abs().max().double_value(&[]);
            assert!(diff < 1e-6, "identity output differs from the input by {diff}");
        }
        let too_many = SampleConfig { colocated_outputs: 5, ..plain };
        let err = make_batch(&mats, &too_many, &mut Pcg64::seed_from_u64(5), Device::Cpu).err().unwrap();
        assert!(err.to_string().contains("5 co-located outputs asked of 4"), "{err}");
    }

    #[test]
    fn hemisphere_outputs_sit_before_the_colocated_ones() {
        let mats = vec![material(16, 16, 0.3), material(16, 16, 0.6)];
        let plain = SampleConfig { outputs_per_material: 4, colocated_outputs: 1, ..Default::default() };
        let with = SampleConfig { hemisphere_outputs: 1, ..plain.clone() };
        let a = make_batch(&mats, &plain, &mut Pcg64::seed_from_u64(7), Device::Cpu).unwrap();
        let b = make_batch(&mats, &with, &mut Pcg64::seed_from_u64(7), Device::Cpu).unwrap();
        let norm = |p: [f64; 3]| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        for i in 0..2 {
            // Reflect draws and the Identity output as without the option.
            assert_eq!(&a.configs[i * 4..i * 4 + 2], &b.configs[i * 4..i * 4 + 2]);
            assert_eq!(a.configs[i * 4 + 3], b.configs[i * 4 + 3]);
            // The third: light and camera apart, both on the radius-4 hemisphere.
            let h = b.configs[i * 4 + 2];
            assert_ne!(h, a.configs[i * 4 + 2]);
            assert_ne!(h.light, h.view);
            for p in [h.light, h.view] {
                assert!((norm(p) - crate::geometry::HEMISPHERE_RADIUS).abs() < 1e-9 && p[2] >= 0.0, "{p:?}");
            }
        }
        let too_many = SampleConfig { hemisphere_outputs: 4, ..plain };
        let err = make_batch(&mats, &too_many, &mut Pcg64::seed_from_u64(7), Device::Cpu).err().unwrap();
        assert!(err.to_string().contains("4 hemisphere and 1 co-located outputs asked of 4"), "{err}");
    }

    /// Moved-highlight outputs keep the photo's camera and put the mirror
    /// highlight (half vector = the normal) on the material; the other
    /// outputs are those drawn without them.
    #[test]
    fn moved_highlight_outputs_keep_the_camera_and_land_the_highlight_on_the_material() {
        let mats = vec![material(16, 16, 0.3), material(16, 16, 0.6)];
        let plain = SampleConfig { outputs_per_material: 4, colocated_outputs: 1, hemisphere_outputs: 1, ..Default::default() };
        let with = SampleConfig { moved_highlight_outputs: 1, ..plain.clone() };
        let a = make_batch(&mats, &plain, &mut Pcg64::seed_from_u64(9), Device::Cpu).unwrap();
        let b = make_batch(&mats, &with, &mut Pcg64::seed_from_u64(9), Device::Cpu).unwrap();
        let camera = LightView::colocated(crate::geometry::MODEL_FOV_DEG).view;
        for i in 0..2 {
            assert_eq!(a.configs[i * 4], b.configs[i * 4]);
            assert_eq!(&a.configs[i * 4 + 2..i * 4 + 4], &b.configs[i * 4 + 2..i * 4 + 4]);
            assert_eq!(b.configs[i * 4 + 1].view, camera);
            assert_ne!(a.configs[i * 4 + 1], b.configs[i * 4 + 1]);
        }
        let mut rng = Pcg64::seed_from_u64(3);
        for _ in 0..200 {
            let (c, p) = moved_highlight_config(&mut rng, crate::geometry::MODEL_FOV_DEG);
            assert!(p[0].abs() <= MOVED_HIGHLIGHT_EXTENT && p[1].abs() <= MOVED_HIGHLIGHT_EXTENT && p[2] == 0.0);
            let unit = |q: [f64; 3]| {
                let v = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                (v.map(|x| x / n), n)
            };
            let ((l, dl), (v, dv)) = (unit(c.light), unit(c.view));
            // Mirror directions: the half vector at p is the normal.
            assert!((l[0] + v[0]).abs() < 1e-12 && (l[1] + v[1]).abs() < 1e-12 && (l[2] - v[2]).abs() < 1e-12, "{c:?}");
            assert!((0.5..1.5).contains(&(dl / dv)), "{dl} {dv}");
        }
        let too_many = SampleConfig { moved_highlight_outputs: 3, ..plain };
        let err = make_batch(&mats, &too_many, &mut Pcg64::seed_from_u64(9), Device::Cpu).err().unwrap();
        assert!(err.to_string().contains("3 moved-highlight outputs and 2 others asked of 4"), "{err}");
    }

    #[test]
    fn phone_inputs_are_8_bit_photos_from_elsewhere_with_the_same_outputs() {
        // A glossy material, so where the flash highlight lands shows.
        let mats = vec![Svbrdf::uniform(32, 32, [0.2, 0.2, 0.2], [0.5; 3], 0.2), Svbrdf::uniform(32, 32, [0.4, 0.3, 0.2], [0.5; 3], 0.2)];
        let plain = SampleConfig { outputs_per_material: 2, ldr_input: true, ..Default::default() };
        let phone = SampleConfig { phone_inputs: 1.0, ..plain.clone() };
        let a = make_batch(&mats, &plain, &mut Pcg64::seed_from_u64(9), Device::Cpu).unwrap();
        let b = make_batch(&mats, &phone, &mut Pcg64::seed_from_u64(9), Device::Cpu).unwrap();
        // The outputs are drawn first: the same configurations and targets.
        assert_eq!(a.configs, b.configs);
        assert_eq!(f64::try_from((&a.targets - &b.targets).abs().max()).unwrap(), 0.0);
        // M_est is told the co-located geometry either way.
        assert_eq!(f64::try_from((a.est_input.narrow(1, 3, 1) - b.est_input.narrow(1, 3, 1)).abs().max()).unwrap(), 0.0);
        // The plain photo's highlight (its centroid, weighted by radiance^4)
        // is at the centre; the phone's is not (the camera moved), and every
        // value lies on the 8-bit sRGB grid.
        let off_centre = |t: &Tensor| {
            let w = t.sum_dim_intlist([0i64].as_slice(), false, Kind::Double).pow_tensor_scalar(4);
            let at = Tensor::arange(32, (Kind::Double, Device::Cpu)) - 15.5;
            let total = w.sum(Kind::Double);
            let (y, x) = ((&w * at.unsqueeze(1)).sum(Kind::Double) / &total, (&w * at.unsqueeze(0)).sum(Kind::Double) / &total);
            f64::try_from(y).unwrap().hypot(f64::try_from(x).unwrap())
        };
        for i in 0..2 {
            assert!(off_centre(&a.input_linear.get(i)) < 1e-3);
        }
        assert!(off_centre(&b.input_linear.get(0)).max(off_centre(&b.input_linear.get(1))) > 0.5);
        let values = Vec::<f32>::try_from(b.input_linear.flatten(0, -1)).unwrap();
        for v in values {
            let code = (crate::spaces::photo_encode(v) * 255.0).round();
            assert!((crate::spaces::photo_decode(code / 255.0) - v).abs() < 1e-6, "{v} is off the 8-bit grid");
        }
        // Brought to the co-located photo's exposure: the means agree within the highlight's move.
        let ratio = f64::try_from(b.input_linear.mean(Kind::Float) / a.input_linear.mean(Kind::Float)).unwrap();
        assert!((0.8..1.25).contains(&ratio), "{ratio}");
        // As JPEGs: the same draws (the quality comes after the noise), so
        // the same targets and a photo near the lossless one, but not it.
        let jpeg = SampleConfig { phone: PhonePhotoConfig { jpeg_quality: Some((85, 95)), ..Default::default() }, ..phone };
        let c = make_batch(&mats, &jpeg, &mut Pcg64::seed_from_u64(9), Device::Cpu).unwrap();
        assert_eq!(f64::try_from((&c.targets - &b.targets).abs().max()).unwrap(), 0.0);
        let gap = f64::try_from((&c.input_linear - &b.input_linear).abs().mean(Kind::Float)).unwrap();
        assert!(gap > 0.0 && gap < 0.01, "{gap}");
    }

    #[test]
    fn ldr_input_is_clamped_but_targets_are_not() {
        // A shiny material has a highlight above 1 at the centre.
        let mats = vec![Svbrdf::uniform(16, 16, [0.5; 3], [0.9; 3], 0.1)];
        let hdr = make_batch(&mats, &SampleConfig::default(), &mut Pcg64::seed_from_u64(2), Device::Cpu).unwrap();
        assert!(hdr.input_linear.max().double_value(&[]) > 1.0);
        let cfg = SampleConfig { ldr_input: true, ..Default::default() };
        let ldr = make_batch(&mats, &cfg, &mut Pcg64::seed_from_u64(2), Device::Cpu).unwrap();
        assert!((ldr.input_linear.max().double_value(&[]) - 1.0).abs() < 1e-7);
        assert!(ldr.targets.equal(&hdr.targets));
    }

    #[test]
    fn shadows_darken_input_and_targets_only_when_asked() {
        // A tall block in the middle of a flat material.
        let n = 32;
        let mut m = Svbrdf::uniform(n, n, [0.5; 3], [0.04; 3], 0.5);
        m.height_field = Some(crate::image::Image::from_fn(1, n, n, |_, r, c| if (12..20).contains(&r) && (12..20).contains(&c) { 0.4 } else { 0.0 }));
        let mats = vec![m.clone(), m.clone()];
        let base = SampleConfig { outputs_per_material: 4, output_sampling: Sampling::Hemisphere, ..Default::default() };
        let plain = make_batch(&mats, &base, &mut Pcg64::seed_from_u64(3), Device::Cpu).unwrap();
        let cfg = SampleConfig { shadows: true, ..base.clone() };
        let shadowed = make_batch(&mats, &cfg, &mut Pcg64::seed_from_u64(3), Device::Cpu).unwrap();
        assert_eq!(plain.configs, shadowed.configs);
        assert!(plain.out_wi.equal(&shadowed.out_wi));
        // Shadowing only removes light, and some pixels lose all of it.
        assert!(bool::try_from(shadowed.targets.le_tensor(&plain.targets).all()).unwrap());
        let zeroed = (shadowed.targets.eq(0.0).logical_and(&plain.targets.gt(0.0))).sum(tch::Kind::Int64).int64_value(&[]);
        assert!(zeroed > 0);
        // Height scale 0 flattens the relief: no shadows at all.
        let flat = SampleConfig { height_scale: 0.0, ..cfg };
        let none = make_batch(&mats, &flat, &mut Pcg64::seed_from_u64(3), Device::Cpu).unwrap();
        assert!(none.targets.equal(&plain.targets) && none.input_linear.equal(&plain.input_linear));
        // Materials without a height field get one from their normals.
        let mut loaded = m;
        loaded.normal = crate::svbrdf::normals_from_height(loaded.height_field.as_ref().unwrap());
        loaded.height_field = None;
        assert!(make_batch(&[loaded.clone(), loaded], &SampleConfig { shadows: true, ..base }, &mut Pcg64::seed_from_u64(3), Device::Cpu).is_ok());
    }

    #[test]
    fn mixed_sizes_are_an_error() {
        let mats = vec![material(8, 8, 0.5), material(16, 16, 0.5)];
        assert!(make_batch(&mats, &SampleConfig::default(), &mut Pcg64::seed_from_u64(0), Device::Cpu).is_err());
    }
}
