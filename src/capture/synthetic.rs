//! Synthetic phone photos of the printed frame with a material in its
//! opening, rendered in perspective through [`super::camera`]'s model
//! (distortion included), then blurred, noised, made 8-bit and
//! JPEG-compressed as a phone would: the tests' and the docs' captures,
//! with every pose known.

use super::camera::{Intrinsics, Pose};
use super::frame::{tag_cells, FrameLayout, TAG_CELLS, TAG_MM};
use super::rectify::Rgb8;
use crate::geometry::{dot, length, normalize, sub, LightView, Vec3};
use crate::image::Image;
use crate::svbrdf::Svbrdf;
use anyhow::Result;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

/// Albedo-like radiance factors of the paper and the tags' black squares
/// (lit straight on at the reference distance).
const PAPER: f32 = 0.55;
const INK: f32 = 0.025;
/// The table around the frame.
const TABLE: f32 = 0.12;
/// Sub-samples per pixel side: 3 for the tests' small photos (their tag
/// edges exact to a ninth of a pixel); 12 MP benchmark photos take 1.
pub const SUPERSAMPLE: usize = 3;

/// How a synthetic photo is spoiled after rendering.
#[derive(Clone, Copy, Debug)]
pub struct PhoneEffects {
    /// Gaussian blur, standard deviation in pixels (0: none).
    pub blur_px: f64,
    /// Sensor noise, standard deviation in linear units.
    pub noise: f64,
    /// JPEG quality (None: the 8-bit codes as they are).
    pub jpeg_quality: Option<u8>,
    pub seed: u64,
}

impl Default for PhoneEffects {
    fn default() -> Self {
        Self { blur_px: 0.7, noise: 0.004, jpeg_quality: Some(90), seed: 0 }
    }
}

/// One synthetic photo's camera.
#[derive(Clone, Copy, Debug)]
pub struct PhoneView {
    pub intrinsics: Intrinsics,
    pub pose: Pose,
    pub width: usize,
    pub height: usize,
}

/// The opening as the capture folder should hold it: the material
/// rendered for this light and camera (mm), with the light's fall-off
/// relative to `r0` mm, linear `[3, S, S]` (S: the material's side).
pub fn opening_truth(material: &Svbrdf, layout: &FrameLayout, light: Vec3, camera: Vec3, r0: f64) -> Result<Image> {
    let unit = layout.opening_mm() / 2.0;
    let config = LightView { light: light.map(|v| v / unit), view: camera.map(|v| v / unit) };
    let (h, w) = (material.height(), material.width());
    let render = crate::svbrdf::cpu::render_tensor(material, &[config]).get(0);
    Image::from_tensor(&(render * crate::data::captures::falloff(config.light, r0 / unit, h, w)))
}

/// A linear photo `[3, H, W]` of the frame lying on a table, `opening`
/// (linear `[3, S, S]`, e.g. [`opening_truth`]) showing through it, lit by
/// a point light at `light` (mm) whose level is 1 at distance `r0` mm;
/// `samples x samples` rays a pixel.
pub fn render_photo(layout: &FrameLayout, opening: &Image, light: Vec3, r0: f64, view: &PhoneView, samples: usize) -> Result<Image> {
    let samples = samples.max(1);
    let cells: Vec<(super::frame::TagPlace, Vec<bool>)> = layout.tags.iter().map(|t| Ok((*t, tag_cells(t.id)?))).collect::<Result<_>>()?;
    let half = layout.opening_mm() / 2.0;
    let outer = layout.outer_half_mm();
    let cell_mm = TAG_MM / 8.0;
    let tag_half = cell_mm * TAG_CELLS as f64 / 2.0;
    let side = opening.width;
    let shade = |x: f64, y: f64| -> [f32; 3] {
        if x.abs() < half && y.abs() < half {
            // Texels are flat squares (as a material's detail is to a camera
            // that resolves it): interpolating them would blur the sample
            // before the camera sees it.
            let col = (((x + half) / (2.0 * half) * side as f64) as usize).min(side - 1);
            let row = (((half - y) / (2.0 * half) * side as f64) as usize).min(side - 1);
            return std::array::from_fn(|c| opening.get(c, row, col));
        }
        let to_light = sub(light, [x, y, 0.0]);
        let r = length(to_light);
        let lit = (dot(normalize(to_light), [0.0, 0.0, 1.0]).max(0.0) * (r0 / r).powi(2)) as f32;
        if x.abs() > outer || y.abs() > outer {
            return [TABLE * lit; 3];
        }
        let mut albedo = PAPER;
        for (tag, bits) in &cells {
            let (u, v) = (x - (tag.centre[0] - tag_half), (tag.centre[1] + tag_half) - y);
            if (0.0..2.0 * tag_half).contains(&u) && (0.0..2.0 * tag_half).contains(&v) {
                let (c, r) = ((u / cell_mm) as usize, (v / cell_mm) as usize);
                if !bits[r.min(TAG_CELLS - 1) * TAG_CELLS + c.min(TAG_CELLS - 1)] {
                    albedo = INK;
                }
                break;
            }
        }
        [albedo * lit; 3]
    };
    let (w, h) = (view.width, view.height);
    let mut rows = vec![0.0f32; 3 * w * h];
    rows.par_chunks_mut(3 * w).enumerate().for_each(|(row, out)| {
        for col in 0..w {
            let mut acc = [0.0f32; 3];
            for sy in 0..samples {
                for sx in 0..samples {
                    let px = [col as f64 + (sx as f64 + 0.5) / samples as f64, row as f64 + (sy as f64 + 0.5) / samples as f64];
                    if let Some([x, y]) = view.pose.plane_point(&view.intrinsics, px) {
                        let v = shade(x, y);
                        (0..3).for_each(|c| acc[c] += v[c]);
                    }
                }
            }
            let n = (samples * samples) as f32;
            (0..3).for_each(|c| out[3 * col + c] = acc[c] / n);
        }
    });
    Ok(Image::from_fn(3, h, w, |c, y, x| rows[3 * (y * w + x) + c]))
}

/// One synthetic phone photo and the truth of its opening (linear `[3, S, S]`).
pub struct SyntheticPhoto {
    pub rgb: Rgb8,
    pub truth: Image,
}

/// The flash of a phone at `view`, `offset_mm` beside its lens in the camera frame.
pub fn flash_position(view: &PhoneView, offset_mm: [f64; 2]) -> Vec3 {
    crate::geometry::add(view.pose.centre(), view.pose.to_world_dir([offset_mm[0], offset_mm[1], 0.0]))
}

/// Phone photos of the frame with `material` in its opening, one per view,
/// the flash `offset_mm` beside each lens, its level 1 at the first
/// photo's flash distance; `samples` rays a pixel side, `fx` seeded
/// `fx.seed + i` for photo i.
pub fn shoot(material: &Svbrdf, layout: &FrameLayout, views: &[PhoneView], offset_mm: [f64; 2], samples: usize, fx: &PhoneEffects) -> Result<Vec<SyntheticPhoto>> {
    let Some(first) = views.first() else { return Ok(vec![]) };
    let r0 = length(flash_position(first, offset_mm));
    views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let light = flash_position(v, offset_mm);
            let truth = opening_truth(material, layout, light, v.pose.centre(), r0)?;
            let linear = render_photo(layout, &truth, light, r0, v, samples)?;
            let rgb = as_phone_photo(&linear, &PhoneEffects { seed: fx.seed + i as u64, ..*fx })?;
            Ok(SyntheticPhoto { rgb, truth })
        })
        .collect()
}

/// A linear photo as a phone saves it: blurred, noised, sRGB-encoded to
/// 8 bits, JPEG-compressed.
pub fn as_phone_photo(linear: &Image, fx: &PhoneEffects) -> Result<Rgb8> {
    let blurred = if fx.blur_px > 0.0 { gaussian_blur(linear, fx.blur_px) } else { linear.clone() };
    let mut rng = rand_pcg::Pcg64::seed_from_u64(fx.seed);
    let normal = Normal::new(0.0, fx.noise.max(0.0)).expect("a finite standard deviation");
    let (w, h) = (linear.width, linear.height);
    let mut data = vec![0u8; 3 * w * h];
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let v = blurred.get(c, y, x) + normal.sample(&mut rng) as f32;
                data[3 * (y * w + x) + c] = crate::spaces::quantize_u8(crate::spaces::photo_encode(v.clamp(0.0, 1.0)));
            }
        }
    }
    if let Some(q) = fx.jpeg_quality {
        data = crate::io::jpeg_round_trip(&data, w, h, q)?;
    }
    Ok(Rgb8 { width: w, height: h, data })
}

/// Separable Gaussian blur (edges clamped).
fn gaussian_blur(image: &Image, sigma: f64) -> Image {
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> = (-radius..=radius).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32).collect();
    let total: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / total).collect();
    let (h, w) = (image.height as isize, image.width as isize);
    let pass = |src: &Image, along_x: bool| {
        Image::from_fn(src.channels, src.height, src.width, |c, y, x| {
            kernel
                .iter()
                .enumerate()
                .map(|(i, k)| {
                    let d = i as isize - radius;
                    let (yy, xx) = if along_x { (y as isize, (x as isize + d).clamp(0, w - 1)) } else { ((y as isize + d).clamp(0, h - 1), x as isize) };
                    k * src.get(c, yy as usize, xx as usize)
                })
                .sum()
        })
    };
    pass(&pass(image, true), false)
}

/// Phone-like views of the frame: the camera at each `eye` (mm) aimed at
/// the opening's centre (off by `aim_mm` in x, as a hand would), rolled
/// by `roll_deg` about its axis, a `width x height` sensor of focal
/// `focal` pixels with distortion `k1`, `k2` and its principal point a few
/// pixels off centre.
pub fn phone_views(eyes: &[Vec3], roll_deg: &[f64], width: usize, height: usize, focal: f64, k1: f64, k2: f64) -> Vec<PhoneView> {
    eyes.iter()
        .zip(roll_deg.iter().cycle())
        .enumerate()
        .map(|(i, (eye, roll))| {
            let aim = [3.0 * (i as f64 - 1.0), -2.0, 0.0];
            let r = roll.to_radians();
            let pose = Pose::look_at(*eye, aim, [r.sin(), r.cos(), 0.0]);
            let intrinsics = Intrinsics { focal, centre: [width as f64 / 2.0 + 6.0, height as f64 / 2.0 - 4.0], k1, k2 };
            PhoneView { intrinsics, pose, width, height }
        })
        .collect()
}
