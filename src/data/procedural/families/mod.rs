//! The material families: each is a set of random parameters drawn once per
//! material and a per-point function (`Pattern::texel`) evaluated at every
//! pixel's pattern coordinate.
//!
//! Conventions shared by all families:
//! - a pattern unit is the family's natural feature size (one tile, one
//!   brick, one thread, one leather cell...); the global `Frame` maps plane
//!   coordinates to pattern coordinates with a random scale and rotation;
//! - heights are returned in pattern units and divided by the frame scale by
//!   the rasteriser, so slopes (and hence normals) do not depend on the
//!   random scale; feature profiles are designed for slopes below about 1.5;
//! - colours are linear; palettes are drawn in display (gamma 2.2) HSV,
//!   where "plausible" is easy to judge, then linearised;
//! - frequencies that could alias are capped using `Ctx::pixel`, the pixel
//!   footprint in pattern units.

use super::noise::*;
use super::Family;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

mod tiles;
mod bricks;
mod wood;
mod polished_metal;
mod brushed_metal;
mod rust_paint;
mod stone;
mod fabric;
mod leather;
mod plastic;
mod marble;
mod scratched;
mod cobblestone;
mod terrazzo;

use tiles::Tiles;
use bricks::Bricks;
use wood::Wood;
use polished_metal::PolishedMetal;
use brushed_metal::BrushedMetal;
use rust_paint::RustPaint;
use stone::Stone;
use fabric::Fabric;
use leather::Leather;
use plastic::Plastic;
use marble::Marble;
use scratched::Scratched;
use cobblestone::Cobblestone;
use terrazzo::Terrazzo;

pub(super) type Rgb = [f32; 3];

/// One evaluated point of a material.
#[derive(Clone, Copy, Debug)]
pub(super) struct Texel {
    pub kd: Rgb,
    pub ks: Rgb,
    pub rough: f32,
    /// Height in pattern units.
    pub h: f32,
}

/// A material family instance: pure function of the pattern coordinate.
pub(super) trait Pattern: Sync {
    fn texel(&self, p: V2) -> Texel;
}

/// Planar maps before normals are derived: the unit that mixing works on.
pub(super) struct Layers {
    pub size: usize,
    /// `[3, size, size]` linear diffuse albedo.
    pub kd: Vec<f32>,
    /// `[3, size, size]` linear specular albedo.
    pub ks: Vec<f32>,
    /// `[size, size]` roughness.
    pub rough: Vec<f32>,
    /// `[size, size]` heights in plane units.
    pub height: Vec<f32>,
}

/// Random global transform from plane coordinates to pattern coordinates.
pub(super) struct Frame {
    /// Pattern units per plane unit.
    pub scale: f32,
    cos: f32,
    sin: f32,
    off: V2,
}

impl Frame {
    /// Log-uniform scale in `scale`; with probability `axis_aligned` the
    /// rotation is a multiple of 90 degrees plus a small jitter (man-made
    /// layouts are usually photographed square-on), otherwise uniform.
    pub fn random(rng: &mut Pcg64, scale: (f32, f32), axis_aligned: f32) -> Self {
        let s = rng.log_uni(scale.0, scale.1);
        let angle = if rng.chance(axis_aligned) {
            rng.random_range(0..4) as f32 * std::f32::consts::FRAC_PI_2 + rng.uni(-0.03, 0.03)
        } else {
            rng.uni(0.0, std::f32::consts::TAU)
        };
        // Offsets stay small so f32 noise coordinates keep their precision.
        let off = [rng.uni(-16.0, 16.0), rng.uni(-16.0, 16.0)];
        Self { scale: s, cos: angle.cos(), sin: angle.sin(), off }
    }

    #[inline(always)]
    pub fn apply(&self, x: f32, y: f32) -> V2 {
        let (u, v) = (x * self.scale, y * self.scale);
        [self.cos * u - self.sin * v + self.off[0], self.sin * u + self.cos * v + self.off[1]]
    }
}

/// Per-material context handed to family constructors.
pub(super) struct Ctx {
    /// Pixel footprint in pattern units.
    pub pixel: f32,
    /// Base seed for the material's noise functions.
    pub seed: u32,
}

impl Ctx {
    /// Caps a frequency (cycles per pattern unit) at `cycles_per_pixel`.
    fn cap(&self, freq: f32, cycles_per_pixel: f32) -> f32 {
        freq.min(cycles_per_pixel / self.pixel)
    }
    fn oct(&self, freq: f32, max: u32) -> u32 {
        octaves_for(freq, self.pixel, max)
    }
    fn seed(&self, k: u32) -> u32 {
        sub_seed(self.seed, k)
    }
}

/// Evaluates a pattern at every pixel centre (REFERENCE section 1 mapping:
/// x = 2(j+0.5)/W - 1, y = 1 - 2(i+0.5)/H).
pub(super) fn rasterise<P: Pattern>(pat: &P, frame: &Frame, size: usize) -> Layers {
    let n = size * size;
    let mut kd = vec![0.0f32; 3 * n];
    let mut ks = vec![0.0f32; 3 * n];
    let mut rough = vec![0.0f32; n];
    let mut height = vec![0.0f32; n];
    let inv_scale = 1.0 / frame.scale;
    let step = 2.0 / size.max(1) as f32;
    for i in 0..size {
        let y = 1.0 - (i as f32 + 0.5) * step;
        for j in 0..size {
            let x = (j as f32 + 0.5) * step - 1.0;
            let t = pat.texel(frame.apply(x, y));
            let k = i * size + j;
            for c in 0..3 {
                kd[c * n + k] = t.kd[c];
                ks[c * n + k] = t.ks[c];
            }
            rough[k] = t.rough;
            height[k] = t.h * inv_scale;
        }
    }
    Layers { size, kd, ks, rough, height }
}

/// Scale range (pattern units per plane unit) and the probability of an
/// axis-aligned layout, per family.
fn frame_params(family: Family) -> ((f32, f32), f32) {
    match family {
        Family::Tiles => ((1.0, 4.0), 0.75),
        Family::Bricks => ((1.0, 3.0), 0.8),
        Family::Wood => ((0.5, 1.5), 0.7),
        Family::PolishedMetal => ((0.5, 2.0), 0.0),
        Family::BrushedMetal => ((0.5, 2.0), 0.6),
        Family::RustPaint => ((0.5, 2.0), 0.6),
        Family::Stone => ((0.7, 2.5), 0.0),
        Family::Fabric => ((10.0, 28.0), 0.7),
        Family::Leather => ((4.0, 14.0), 0.0),
        Family::Plastic => ((1.0, 4.0), 0.5),
        Family::Marble => ((0.5, 2.0), 0.0),
        Family::Scratched => ((1.0, 3.0), 0.0),
        Family::Cobblestone => ((1.5, 5.0), 0.0),
        Family::Terrazzo => ((1.0, 3.0), 0.0),
    }
}

/// Generates one family's maps (heights in plane units, no normals yet).
pub(super) fn family_layers(family: Family, seed: u64, size: usize) -> Layers {
    let mut rng = Pcg64::seed_from_u64(seed);
    let (range, axis) = frame_params(family);
    let frame = Frame::random(&mut rng, range, axis);
    let ctx = Ctx { pixel: 2.0 * frame.scale / size.max(1) as f32, seed: rng.random() };
    let r = &mut rng;
    match family {
        Family::Tiles => rasterise(&Tiles::new(r, &ctx), &frame, size),
        Family::Bricks => rasterise(&Bricks::new(r, &ctx), &frame, size),
        Family::Wood => rasterise(&Wood::new(r, &ctx), &frame, size),
        Family::PolishedMetal => rasterise(&PolishedMetal::new(r, &ctx), &frame, size),
        Family::BrushedMetal => rasterise(&BrushedMetal::new(r, &ctx), &frame, size),
        Family::RustPaint => rasterise(&RustPaint::new(r, &ctx), &frame, size),
        Family::Stone => rasterise(&Stone::new(r, &ctx), &frame, size),
        Family::Fabric => rasterise(&Fabric::new(r, &ctx), &frame, size),
        Family::Leather => rasterise(&Leather::new(r, &ctx), &frame, size),
        Family::Plastic => rasterise(&Plastic::new(r, &ctx), &frame, size),
        Family::Marble => rasterise(&Marble::new(r, &ctx), &frame, size),
        Family::Scratched => rasterise(&Scratched::new(r, &ctx), &frame, size),
        Family::Cobblestone => rasterise(&Cobblestone::new(r, &ctx), &frame, size),
        Family::Terrazzo => rasterise(&Terrazzo::new(r, &ctx), &frame, size),
    }
}

// ---------------------------------------------------------------------------
// Random and colour helpers

pub(super) trait RngExt {
    fn uni(&mut self, a: f32, b: f32) -> f32;
    fn log_uni(&mut self, a: f32, b: f32) -> f32;
    fn chance(&mut self, p: f32) -> bool;
    fn pick<T: Copy>(&mut self, xs: &[T]) -> T;
}

impl RngExt for Pcg64 {
    fn uni(&mut self, a: f32, b: f32) -> f32 {
        a + (b - a) * self.random::<f32>()
    }
    fn log_uni(&mut self, a: f32, b: f32) -> f32 {
        (a.ln() + (b.ln() - a.ln()) * self.random::<f32>()).exp()
    }
    fn chance(&mut self, p: f32) -> bool {
        self.random::<f32>() < p
    }
    fn pick<T: Copy>(&mut self, xs: &[T]) -> T {
        xs[self.random_range(0..xs.len())]
    }
}

/// Per-cell random number in [0, 1): the `k`-th draw from a cell hash.
#[inline(always)]
fn rnd(id: u32, k: u32) -> f32 {
    unit(mix32(id ^ k.wrapping_mul(0x9e37_79b9)))
}

/// Signed per-cell random number in [-1, 1).
#[inline(always)]
fn srnd(id: u32, k: u32) -> f32 {
    2.0 * rnd(id, k) - 1.0
}

/// Display-space (gamma 2.2) colour to linear.
fn lin(c: Rgb) -> Rgb {
    c.map(|v| v.clamp(0.0, 1.0).powf(2.2))
}

/// HSV (all in [0,1], hue wraps) to display-space RGB.
fn hsv(h: f32, s: f32, v: f32) -> Rgb {
    let h = fract(h) * 6.0;
    let s = s.clamp(0.0, 1.0);
    let v = v.clamp(0.0, 1.0);
    let i = floor_i(h).clamp(0, 5);
    let f = h - i as f32;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match i {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// HSV in display space, returned linear.
fn hsv_lin(h: f32, s: f32, v: f32) -> Rgb {
    lin(hsv(h, s, v))
}

#[inline(always)]
fn mul(c: Rgb, k: f32) -> Rgb {
    [c[0] * k, c[1] * k, c[2] * k]
}

#[inline(always)]
fn mix3(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [lerp(a[0], b[0], t), lerp(a[1], b[1], t), lerp(a[2], b[2], t)]
}

#[inline(always)]
fn grey(v: f32) -> Rgb {
    [v, v, v]
}

/// A random hue-preserving variation of a linear colour (brightness and a
/// little per-channel tint), for "a second shade of the same material".
fn vary(rng: &mut Pcg64, c: Rgb, bright: (f32, f32), tint: f32) -> Rgb {
    let k = rng.uni(bright.0, bright.1);
    let mut out = c;
    for v in &mut out {
        *v = (*v * k * (1.0 + rng.uni(-tint, tint))).clamp(0.0, 1.0);
    }
    out
}

/// Linear F0 of common metals (measured-data approximations); all have a
/// luminance of at least 0.5.
const METALS: [Rgb; 12] = [
    [0.97, 0.96, 0.91], // silver
    [0.91, 0.92, 0.92], // aluminium
    [1.00, 0.78, 0.34], // gold
    [0.95, 0.64, 0.54], // copper
    [0.91, 0.77, 0.45], // brass
    [0.56, 0.57, 0.58], // iron
    [0.55, 0.56, 0.55], // chromium
    [0.66, 0.61, 0.53], // nickel
    [0.67, 0.64, 0.59], // platinum
    [0.80, 0.60, 0.40], // bronze
    [0.66, 0.67, 0.69], // zinc
    [0.60, 0.56, 0.51], // titanium
];

/// A metal's specular colour, jittered.
fn metal_f0(rng: &mut Pcg64) -> Rgb {
    let m = rng.pick(&METALS);
    vary(rng, m, (0.92, 1.04), 0.02)
}

/// Metals absorb what they do not reflect: near-black diffuse, slightly
/// tinted by the metal colour (dirt, oxide).
fn metal_kd(rng: &mut Pcg64, ks: Rgb) -> Rgb {
    mul(ks, rng.uni(0.0, 0.03))
}

/// Grey dielectric F0 (0.04 is glass/plastic; 0.02 rough organics; 0.08 tops).
fn f0(rng: &mut Pcg64, lo: f32, hi: f32) -> Rgb {
    grey(rng.uni(lo, hi))
}
