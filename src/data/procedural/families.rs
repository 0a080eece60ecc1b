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

// ---------------------------------------------------------------------------
// Ceramic tiles: grid (or running bond), recessed grout, bevelled edges,
// per-tile colour jitter and slight tilt, glossy glaze with low waviness.

struct Tiles {
    seed: u32,
    th: f32,
    shift: f32,
    gh: f32,
    bevel: f32,
    depth: f32,
    aa: f32,
    colour: Rgb,
    colour2: Option<Rgb>,
    jitter: f32,
    tint: f32,
    rough: f32,
    rough_jit: f32,
    ks: Rgb,
    grout_kd: Rgb,
    grout_rough: f32,
    grout_ks: Rgb,
    wave_amp: f32,
    wave_freq: f32,
    wave_oct: u32,
    tilt: f32,
    grout_freq: f32,
}

impl Tiles {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let free = rng.uni(0.3, 1.0);
        let th = if rng.chance(0.6) { 1.0 } else { rng.pick(&[0.5, 0.333, 0.25, free]) };
        let shift = if rng.chance(0.25) { rng.pick(&[0.5, 0.333]) } else { 0.0 };
        let depth = rng.uni(0.004, 0.02);
        let kind = rng.uni(0.0, 1.0);
        let (colour, rough, ks) = if kind < 0.35 {
            (
                hsv_lin(rng.uni(0.05, 0.15), rng.uni(0.0, 0.15), rng.uni(0.75, 0.95)),
                rng.uni(0.03, 0.2),
                f0(rng, 0.04, 0.06),
            )
        } else if kind < 0.7 {
            (
                hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.25, 0.85), rng.uni(0.3, 0.85)),
                rng.uni(0.03, 0.3),
                f0(rng, 0.04, 0.06),
            )
        } else if kind < 0.85 {
            (
                hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.3), rng.uni(0.08, 0.3)),
                rng.uni(0.05, 0.35),
                f0(rng, 0.04, 0.06),
            )
        } else {
            // Unglazed terracotta.
            (
                hsv_lin(rng.uni(0.02, 0.08), rng.uni(0.45, 0.75), rng.uni(0.45, 0.8)),
                rng.uni(0.5, 0.85),
                f0(rng, 0.025, 0.04),
            )
        };
        let colour2 = rng.chance(0.15).then(|| {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.6), {
                let mid = rng.uni(0.2, 0.8);
                rng.pick(&[0.1, 0.9, mid])
            })
        });
        let wave_freq = rng.uni(1.5, 4.0);
        Self {
            seed: ctx.seed(1),
            th,
            shift,
            gh: rng.uni(0.01, 0.04),
            // Bevel at least as wide as the grout is deep keeps slopes < 1.5.
            bevel: rng.uni(0.005, 0.04).max(depth),
            depth,
            aa: (0.7 * ctx.pixel).max(0.002),
            colour,
            colour2,
            jitter: rng.uni(0.02, 0.15),
            tint: rng.uni(0.0, 0.05),
            rough,
            rough_jit: rng.uni(0.0, 0.3),
            ks,
            grout_kd: hsv_lin(rng.uni(0.05, 0.15), rng.uni(0.0, 0.2), rng.uni(0.25, 0.85)),
            grout_rough: rng.uni(0.7, 1.0),
            grout_ks: f0(rng, 0.02, 0.04),
            wave_amp: rng.uni(0.005, 0.05) / wave_freq,
            wave_freq,
            wave_oct: ctx.oct(wave_freq, 3),
            tilt: rng.uni(0.0, 0.03),
            grout_freq: ctx.cap(40.0, 0.3),
        }
    }
}

impl Pattern for Tiles {
    fn texel(&self, p: V2) -> Texel {
        let row = floor_i(p[1] / self.th);
        let x = p[0] + row as f32 * self.shift;
        let col = floor_i(x);
        let lx = x - col as f32;
        let ly = p[1] - row as f32 * self.th;
        let e = lx.min(1.0 - lx).min(ly).min(self.th - ly);
        let id = hash2(col, row, self.seed);
        let base = match self.colour2 {
            Some(c2) if (row + col) & 1 == 1 => c2,
            _ => self.colour,
        };
        let b = 1.0 + self.jitter * srnd(id, 1);
        let kd_t = [
            base[0] * b * (1.0 + self.tint * srnd(id, 2)),
            base[1] * b * (1.0 + self.tint * srnd(id, 3)),
            base[2] * b * (1.0 + self.tint * srnd(id, 4)),
        ];
        let rough_t = self.rough * (1.0 + self.rough_jit * srnd(id, 5));
        let h_t = self.tilt * (srnd(id, 6) * (lx - 0.5) + srnd(id, 7) * (ly - 0.5 * self.th))
            + self.wave_amp * fbm([p[0] * self.wave_freq, p[1] * self.wave_freq], self.seed ^ 0x77, self.wave_oct, 0.5);
        if e >= self.gh + self.bevel + self.aa {
            return Texel { kd: kd_t, ks: self.ks, rough: rough_t, h: h_t };
        }
        let mask = smoothstep(self.gh - self.aa, self.gh + self.aa, e);
        let profile = smoothstep(self.gh, self.gh + self.bevel, e);
        let g = gnoise([p[0] * self.grout_freq, p[1] * self.grout_freq], self.seed ^ 0x99);
        let kd_g = mul(self.grout_kd, 1.0 + 0.25 * g);
        let h_g = -self.depth * (1.0 + 0.2 * g);
        Texel {
            kd: mix3(kd_g, kd_t, mask),
            ks: mix3(self.grout_ks, self.ks, mask),
            rough: lerp(self.grout_rough, rough_t, mask),
            h: lerp(h_g, h_t, profile),
        }
    }
}

// ---------------------------------------------------------------------------
// Bricks: offset rows, recessed mortar, chipped edges, per-brick colour
// (two-tone palette, occasional burnt bricks), grain and speckles.

struct Bricks {
    seed: u32,
    bh: f32,
    shift: f32,
    random_rows: bool,
    mh: f32,
    round: f32,
    depth: f32,
    aa: f32,
    chip: f32,
    ca: Rgb,
    cb: Rgb,
    jitter: f32,
    burnt: f32,
    grain_freq: f32,
    grain_oct: u32,
    grain: f32,
    speck_freq: f32,
    rough: f32,
    ks: Rgb,
    surf_amp: f32,
    mortar_kd: Rgb,
    mortar_rough: f32,
    mortar_freq: f32,
}

impl Bricks {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let kind = rng.random_range(0..6);
        let ca = match kind {
            0 => hsv_lin(rng.uni(0.0, 0.04), rng.uni(0.55, 0.8), rng.uni(0.35, 0.65)), // red
            1 => hsv_lin(rng.uni(0.05, 0.1), rng.uni(0.35, 0.6), rng.uni(0.5, 0.8)),   // tan
            2 => hsv_lin(rng.uni(0.03, 0.08), rng.uni(0.4, 0.7), rng.uni(0.2, 0.4)),   // brown
            3 => hsv_lin(rng.uni(0.1, 0.14), rng.uni(0.2, 0.45), rng.uni(0.6, 0.85)),  // yellow
            4 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.1), rng.uni(0.35, 0.65)),   // grey
            _ => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.05), rng.uni(0.85, 0.95)),  // painted
        };
        let painted = kind == 5;
        let cb = vary(rng, ca, (0.6, 1.2), 0.15);
        let bh = rng.uni(0.25, 0.5);
        let mh = rng.uni(0.01, 0.035);
        let depth = rng.uni(0.005, 0.025);
        let grain_freq = rng.uni(3.0, 8.0);
        Self {
            seed: ctx.seed(2),
            bh,
            shift: rng.pick(&[0.5, 0.5, 0.5, 0.25, 0.333, 0.0]),
            random_rows: rng.chance(0.1),
            mh,
            round: rng.uni(0.008, 0.03).max(depth * 0.8),
            depth,
            aa: (0.7 * ctx.pixel).max(0.002),
            chip: if painted { 0.002 } else { rng.uni(0.0, 0.012) },
            ca,
            cb,
            jitter: if painted { 0.03 } else { rng.uni(0.05, 0.3) },
            burnt: if painted { 0.0 } else { rng.uni(0.0, 0.2) },
            grain_freq,
            grain_oct: ctx.oct(grain_freq, 4),
            grain: rng.uni(0.1, 0.35),
            speck_freq: ctx.cap(rng.uni(25.0, 50.0), 0.3),
            rough: rng.uni(0.6, 0.95),
            ks: f0(rng, 0.02, 0.04),
            surf_amp: rng.uni(0.05, 0.25) / grain_freq,
            mortar_kd: hsv_lin(rng.uni(0.05, 0.13), rng.uni(0.0, 0.2), rng.uni(0.3, 0.8)),
            mortar_rough: rng.uni(0.85, 1.0),
            mortar_freq: ctx.cap(30.0, 0.3),
        }
    }
}

impl Pattern for Bricks {
    fn texel(&self, p: V2) -> Texel {
        let row = floor_i(p[1] / self.bh);
        let off = if self.random_rows { rnd(hash1(row, self.seed), 0) } else { row as f32 * self.shift };
        let x = p[0] + off;
        let col = floor_i(x);
        let lx = x - col as f32;
        let ly = p[1] - row as f32 * self.bh;
        let e = lx.min(1.0 - lx).min(ly).min(self.bh - ly);
        let id = hash2(col, row, self.seed);
        let g = fbm([p[0] * self.grain_freq, p[1] * self.grain_freq], self.seed ^ 0x11, self.grain_oct, 0.55);
        // Chipped edges: jitter the distance to the brick border.
        let e = e + self.chip * g * 3.0;
        let mut kd = mix3(self.ca, self.cb, rnd(id, 1));
        let mut b = (1.0 + self.jitter * srnd(id, 2)) * (1.0 + self.grain * g);
        if rnd(id, 3) < self.burnt {
            b *= 0.55;
        }
        let sp = vnoise([p[0] * self.speck_freq, p[1] * self.speck_freq], self.seed ^ 0x22);
        if sp > 0.78 {
            b *= 1.0 - 2.0 * (sp - 0.78);
        }
        kd = mul(kd, b);
        let h_b = self.surf_amp * g + 0.3 * self.depth * (sp - 0.5).min(0.0);
        let rough_b = self.rough * (1.0 + 0.1 * g);
        if e >= self.mh + self.round + self.aa {
            return Texel { kd, ks: self.ks, rough: rough_b, h: h_b };
        }
        let mask = smoothstep(self.mh - self.aa, self.mh + self.aa, e);
        let profile = smoothstep(self.mh, self.mh + self.round, e);
        let m = gnoise([p[0] * self.mortar_freq, p[1] * self.mortar_freq], self.seed ^ 0x33);
        Texel {
            kd: mix3(mul(self.mortar_kd, 1.0 + 0.2 * m), kd, mask),
            ks: self.ks,
            rough: lerp(self.mortar_rough, rough_b, mask),
            h: lerp(-self.depth * (1.0 + 0.3 * m), h_b, profile),
        }
    }
}

// ---------------------------------------------------------------------------
// Wood: planks along x with staggered end joints, growth rings from a
// slightly conical log cut at a random depth (cathedral arches), fine
// streaks and pores stretched along the grain.

struct Wood {
    seed: u32,
    planks: bool,
    pw: f32,
    pl: f32,
    gap: f32,
    bevel: f32,
    depth: f32,
    aa: f32,
    light: Rgb,
    dark: Rgb,
    plank_jit: f32,
    ring_freq: f32,
    ring_jit: f32,
    late_w: f32,
    late_k: f32,
    taper: f32,
    distort: f32,
    streak_freq: f32,
    streak: f32,
    pores: f32,
    rough: f32,
    late_rough: f32,
    ks: Rgb,
    relief: f32,
    streak_relief: f32,
}

impl Wood {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let (h, s, v, dark_k) = match rng.random_range(0..6) {
            0 => (rng.uni(0.08, 0.1), rng.uni(0.35, 0.5), rng.uni(0.65, 0.8), rng.uni(0.55, 0.75)), // oak
            1 => (rng.uni(0.06, 0.08), rng.uni(0.45, 0.6), rng.uni(0.35, 0.5), rng.uni(0.45, 0.65)), // walnut
            2 => (rng.uni(0.1, 0.12), rng.uni(0.3, 0.45), rng.uni(0.8, 0.9), rng.uni(0.6, 0.8)),    // pine
            3 => (rng.uni(0.02, 0.05), rng.uni(0.55, 0.75), rng.uni(0.45, 0.65), rng.uni(0.5, 0.7)), // cherry
            4 => (rng.uni(0.07, 0.1), rng.uni(0.05, 0.15), rng.uni(0.45, 0.65), rng.uni(0.55, 0.75)), // weathered
            _ => (rng.uni(0.05, 0.08), rng.uni(0.4, 0.6), rng.uni(0.15, 0.25), rng.uni(0.5, 0.7)),  // dark stain
        };
        let light = hsv_lin(h, s, v);
        let dark = hsv_lin(h - 0.01, (s + 0.1).min(1.0), v * dark_k);
        let pw = rng.uni(0.15, 0.45);
        let rings = rng.uni(2.0, 10.0);
        // At least 5 pixels per ring.
        let ring_freq = ctx.cap(rings / pw, 0.2);
        let varnished = rng.chance(0.6);
        let depth = rng.uni(0.003, 0.012);
        Self {
            seed: ctx.seed(3),
            planks: rng.chance(0.8),
            pw,
            pl: rng.uni(1.0, 3.0),
            gap: rng.uni(0.001, 0.006),
            bevel: rng.uni(0.004, 0.015).max(depth),
            depth,
            aa: (0.7 * ctx.pixel).max(0.001),
            light,
            dark,
            plank_jit: rng.uni(0.03, 0.2),
            ring_freq,
            ring_jit: rng.uni(0.0, 0.3),
            late_w: rng.uni(0.2, 0.6),
            late_k: rng.uni(0.4, 0.9),
            taper: rng.uni(0.0, 0.08) * if rng.chance(0.5) { 1.0 } else { -1.0 },
            distort: rng.uni(0.1, 0.8),
            streak_freq: ctx.cap(rng.uni(60.0, 200.0), 0.3),
            streak: rng.uni(0.05, 0.25),
            pores: if rng.chance(0.4) { rng.uni(0.2, 0.5) } else { 0.0 },
            rough: if varnished { rng.uni(0.12, 0.35) } else { rng.uni(0.5, 0.85) },
            late_rough: rng.uni(-0.05, 0.08),
            ks: if varnished { f0(rng, 0.04, 0.05) } else { f0(rng, 0.03, 0.04) },
            relief: rng.uni(0.0, 0.002) * if varnished { 0.3 } else { 1.0 },
            streak_relief: rng.uni(0.02, 0.12),
        }
    }
}

impl Pattern for Wood {
    fn texel(&self, p: V2) -> Texel {
        let (u, v) = (p[0], p[1]);
        let (row, lv, lu, col, e) = if self.planks {
            let row = floor_i(v / self.pw);
            let lv = v - row as f32 * self.pw;
            let uu = u + rnd(hash1(row, self.seed), 0) * self.pl;
            let col = floor_i(uu / self.pl);
            let lu = uu - col as f32 * self.pl;
            let e = lv.min(self.pw - lv).min(lu).min(self.pl - lu);
            (row, lv, lu, col, e)
        } else {
            (0, v, u, 0, f32::MAX)
        };
        let id = hash2(col, row, self.seed);
        // Log axis across the plank (may lie outside it) and cut depth.
        let c = (3.0 * rnd(id, 1) - 1.0) * self.pw;
        let z = (0.02 + 0.4 * rnd(id, 2)) * self.pw * 3.0;
        let dv = lv - c;
        let f = self.ring_freq * (1.0 + self.ring_jit * srnd(id, 3));
        let warp = self.distort * fbm([lu * 1.2 + 31.0 * rnd(id, 4), lv * 6.0], self.seed ^ 0x44, 3, 0.5);
        let ring = fract(f * ((dv * dv + z * z).sqrt() - self.taper * lu) + warp);
        // Latewood: darkens towards the end of each year, sharp edge at the wrap.
        let late = smoothstep(1.0 - self.late_w, 1.0 - 0.2 * self.late_w, ring) * self.late_k;
        let st = 0.6 * gnoise([u * 1.5 + 7.0 * rnd(id, 5), v * self.streak_freq], self.seed ^ 0x55)
            + 0.4 * gnoise([u * 0.7, v * self.streak_freq * 0.3], self.seed ^ 0x66);
        let mut t = (late + self.streak * st).clamp(0.0, 1.0);
        if self.pores > 0.0 {
            let pn = vnoise([u * 25.0, v * self.streak_freq * 1.5], self.seed ^ 0x88);
            t = (t + self.pores * smoothstep(0.75, 0.9, pn)).min(1.0);
        }
        let kd = mul(mix3(self.light, self.dark, t), 1.0 + self.plank_jit * srnd(id, 6));
        let rough = self.rough + self.late_rough * late;
        let h_w = self.relief * late + self.streak_relief * st / self.streak_freq + 0.001 * srnd(id, 7);
        if e >= self.gap + self.bevel + self.aa {
            return Texel { kd, ks: self.ks, rough, h: h_w };
        }
        let mask = smoothstep(self.gap - self.aa, self.gap + self.aa, e);
        let profile = smoothstep(self.gap, self.gap + self.bevel, e);
        Texel {
            kd: mix3(mul(self.dark, 0.3), kd, mask),
            ks: self.ks,
            rough: lerp(0.9, rough, mask),
            h: lerp(-self.depth, h_w, profile),
        }
    }
}

// ---------------------------------------------------------------------------
// Polished metal: coloured F0, near-black diffuse, low roughness with smudges;
// sometimes hammered (parabolic dimples on a Voronoi grid).

struct PolishedMetal {
    seed: u32,
    ks: Rgb,
    kd: Rgb,
    rough: f32,
    smudge: f32,
    smudge_freq: f32,
    smudge_oct: u32,
    wave_amp: f32,
    wave_freq: f32,
    hammer: Option<(f32, f32)>,
}

impl PolishedMetal {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let ks = metal_f0(rng);
        let smudge_freq = rng.uni(1.0, 4.0);
        let wave_freq = rng.uni(1.0, 4.0);
        let hammer = rng.chance(0.2).then(|| {
            let f = ctx.cap(rng.uni(4.0, 12.0), 0.08);
            // h = a f1^2 in cell units: slope 2 a f1 <= ~1.4 a.
            (f, rng.uni(0.05, 0.3))
        });
        Self {
            seed: ctx.seed(4),
            kd: metal_kd(rng, ks),
            ks,
            rough: rng.uni(0.03, 0.2),
            smudge: rng.uni(0.0, 0.2),
            smudge_freq,
            smudge_oct: ctx.oct(smudge_freq, 5),
            wave_amp: rng.uni(0.002, 0.02) / wave_freq,
            wave_freq,
            hammer,
        }
    }
}

impl Pattern for PolishedMetal {
    fn texel(&self, p: V2) -> Texel {
        let s = fbm([p[0] * self.smudge_freq, p[1] * self.smudge_freq], self.seed, self.smudge_oct, 0.6);
        let smudge = smoothstep(-0.1, 0.5, s) * self.smudge;
        let mut h = self.wave_amp * gnoise([p[0] * self.wave_freq, p[1] * self.wave_freq], self.seed ^ 0x12);
        if let Some((f, a)) = self.hammer {
            let c = worley([p[0] * f, p[1] * f], self.seed ^ 0x34, 0.9);
            h += a * c.f1 * c.f1 / f;
        }
        Texel { kd: self.kd, ks: mul(self.ks, 1.0 - 0.15 * smudge), rough: self.rough + smudge, h }
    }
}

// ---------------------------------------------------------------------------
// Brushed metal: streak noise stretched along the brushing direction (linear
// or circular around a centre); the streaks modulate roughness and heights,
// so normals vary across the streaks only (anisotropic look).

struct BrushedMetal {
    seed: u32,
    ks: Rgb,
    kd: Rgb,
    rough: f32,
    rough_var: f32,
    freq: f32,
    stretch: f32,
    relief: f32,
    centre: Option<V2>,
    smudge: f32,
}

impl BrushedMetal {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let ks = metal_f0(rng);
        Self {
            seed: ctx.seed(5),
            kd: metal_kd(rng, ks),
            ks,
            rough: rng.uni(0.15, 0.45),
            rough_var: rng.uni(0.03, 0.12),
            // Streak spacing: 1.5-8 pixels at most, finer when the scale allows.
            freq: ctx.cap(rng.uni(80.0, 300.0), rng.uni(0.12, 0.6)),
            stretch: rng.uni(30.0, 150.0),
            relief: rng.uni(0.03, 0.2),
            centre: rng.chance(0.25).then(|| [rng.uni(-1.0, 1.0), rng.uni(-1.0, 1.0)]),
            smudge: rng.uni(0.0, 0.1),
        }
    }
}

impl Pattern for BrushedMetal {
    fn texel(&self, p: V2) -> Texel {
        let (along, across) = match self.centre {
            Some(c) => {
                // Circular brushing: streaks follow circles; the along-stroke
                // variation comes from isotropic noise so there is no seam.
                let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                let r = (dx * dx + dy * dy).sqrt();
                (vnoise([p[0] * 3.0, p[1] * 3.0], self.seed ^ 0x1) * 4.0, r * self.freq)
            }
            None => (p[0] * self.freq / self.stretch, p[1] * self.freq),
        };
        let n = 0.6 * gnoise([along, across], self.seed)
            + 0.3 * gnoise([along * 2.1 + 5.0, across * 2.3], self.seed ^ 0x2)
            + 0.1 * gnoise([along * 4.3 + 9.0, across * 4.1], self.seed ^ 0x3);
        let sm = self.smudge * smoothstep(0.0, 0.6, gnoise([p[0] * 2.0, p[1] * 2.0], self.seed ^ 0x4));
        Texel {
            kd: self.kd,
            ks: mul(self.ks, 1.0 + 0.04 * n),
            rough: self.rough + self.rough_var * n + sm,
            h: self.relief * n / self.freq,
        }
    }
}

// ---------------------------------------------------------------------------
// Rust and paint: a thresholded fbm (optionally with drips stretched along y)
// separates paint (raised layer) from rust, with an optional band of bare
// metal at the peeling edge.

struct RustPaint {
    seed: u32,
    paint_kd: Rgb,
    paint_rough: f32,
    paint_ks: Rgb,
    rust_dark: Rgb,
    rust_light: Rgb,
    rust_rough: f32,
    rust_ks: Rgb,
    metal_ks: Rgb,
    metal_kd: Rgb,
    metal_rough: f32,
    t: f32,
    edge: f32,
    soft: f32,
    mask_freq: f32,
    mask_oct: u32,
    drip: f32,
    drip_fx: f32,
    drip_fy: f32,
    thick: f32,
    rust_freq: f32,
    rust_oct: u32,
    rust_amp: f32,
    fine_freq: f32,
}

impl RustPaint {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let paint_kd = if rng.chance(0.75) {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.3, 0.9), rng.uni(0.2, 0.8))
        } else {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.08), rng.uni(0.3, 0.92))
        };
        let metal_ks = vary(rng, [0.56, 0.57, 0.58], (0.9, 1.05), 0.02);
        let mask_freq = rng.uni(1.0, 3.0);
        let rust_freq = ctx.cap(rng.uni(3.0, 10.0), 0.25);
        Self {
            seed: ctx.seed(6),
            paint_kd,
            paint_rough: rng.uni(0.25, 0.7),
            paint_ks: f0(rng, 0.04, 0.05),
            rust_dark: hsv_lin(rng.uni(0.02, 0.06), rng.uni(0.6, 0.85), rng.uni(0.1, 0.22)),
            rust_light: hsv_lin(rng.uni(0.05, 0.09), rng.uni(0.55, 0.85), rng.uni(0.35, 0.6)),
            rust_rough: rng.uni(0.75, 1.0),
            rust_ks: f0(rng, 0.02, 0.04),
            metal_kd: mul(metal_ks, 0.02),
            metal_ks,
            metal_rough: rng.uni(0.3, 0.5),
            t: rng.uni(-0.35, 0.25),
            edge: if rng.chance(0.6) { rng.uni(0.01, 0.06) } else { 0.0 },
            soft: rng.uni(0.005, 0.02),
            mask_freq,
            mask_oct: ctx.oct(mask_freq, 6),
            drip: if rng.chance(0.4) { rng.uni(0.1, 0.4) } else { 0.0 },
            drip_fx: rng.uni(4.0, 10.0),
            drip_fy: rng.uni(0.3, 1.0),
            thick: rng.uni(0.002, 0.008),
            rust_freq,
            rust_oct: ctx.oct(rust_freq, 5),
            rust_amp: rng.uni(0.05, 0.2) / rust_freq,
            fine_freq: ctx.cap(60.0, 0.3),
        }
    }
}

impl Pattern for RustPaint {
    fn texel(&self, p: V2) -> Texel {
        let mut m = fbm([p[0] * self.mask_freq, p[1] * self.mask_freq], self.seed, self.mask_oct, 0.55);
        if self.drip > 0.0 {
            m -= self.drip * gnoise([p[0] * self.drip_fx, p[1] * self.drip_fy], self.seed ^ 0x5).abs();
        }
        let d = m - self.t;
        let w_paint = smoothstep(0.0, self.soft, d);
        let w_metal = if self.edge > 0.0 { smoothstep(-self.edge, -0.3 * self.edge, d) * (1.0 - w_paint) } else { 0.0 };
        let w_rust = 1.0 - w_paint - w_metal;
        let orange_peel = 0.0003 * gnoise([p[0] * 30.0, p[1] * 30.0], self.seed ^ 0x6);
        let mut out = Texel {
            kd: mul(self.paint_kd, w_paint),
            ks: mul(self.paint_ks, w_paint),
            rough: self.paint_rough * w_paint,
            h: (self.thick + orange_peel) * w_paint,
        };
        if w_metal > 0.0 {
            for c in 0..3 {
                out.kd[c] += self.metal_kd[c] * w_metal;
                out.ks[c] += self.metal_ks[c] * w_metal;
            }
            out.rough += self.metal_rough * w_metal;
        }
        if w_rust > 1e-4 {
            let r = fbm([p[0] * self.rust_freq, p[1] * self.rust_freq], self.seed ^ 0x7, self.rust_oct, 0.55);
            let fine = gnoise([p[0] * self.fine_freq, p[1] * self.fine_freq], self.seed ^ 0x8);
            let kd = mul(mix3(self.rust_dark, self.rust_light, smoothstep(-0.4, 0.4, r)), 1.0 + 0.25 * fine);
            for c in 0..3 {
                out.kd[c] += kd[c] * w_rust;
                out.ks[c] += self.rust_ks[c] * w_rust;
            }
            out.rough += self.rust_rough * w_rust;
            out.h += (self.rust_amp * (r + 0.1 * fine) - 0.5 * self.thick) * w_rust;
        }
        out
    }
}

// ---------------------------------------------------------------------------
// Stone and concrete: multi-scale fbm colour, optional aggregates (Voronoi
// chips of other colours), pits (small round holes), sedimentary banding.

struct Stone {
    seed: u32,
    base: Rgb,
    alt: Rgb,
    freq: f32,
    oct: u32,
    fine_freq: f32,
    fine: f32,
    agg: Option<(f32, f32, f32)>,
    pits: Option<(f32, f32, f32, f32)>,
    band: Option<(f32, f32)>,
    rough: f32,
    ks: Rgb,
    amp: f32,
    fine_amp: f32,
}

impl Stone {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let base = match rng.random_range(0..5) {
            0 => hsv_lin(rng.uni(0.08, 0.12), rng.uni(0.02, 0.12), rng.uni(0.35, 0.7)), // concrete
            1 => hsv_lin(rng.uni(0.07, 0.11), rng.uni(0.25, 0.5), rng.uni(0.5, 0.8)),   // sandstone
            2 => hsv_lin(rng.uni(0.55, 0.65), rng.uni(0.05, 0.2), rng.uni(0.15, 0.35)), // slate
            3 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.2), rng.uni(0.3, 0.7)),      // granite
            _ => hsv_lin(rng.uni(0.02, 0.05), rng.uni(0.4, 0.6), rng.uni(0.35, 0.6)),   // red rock
        };
        let alt = vary(rng, base, (0.55, 1.3), 0.08);
        let freq = rng.uni(1.0, 3.0);
        let fine_freq = ctx.cap(rng.uni(30.0, 80.0), 0.3);
        let agg = rng.chance(0.6).then(|| (ctx.cap(rng.uni(6.0, 20.0), 0.12), rng.uni(0.2, 0.45), rng.uni(0.3, 0.9)));
        let pits = rng.chance(0.6).then(|| {
            let f = ctx.cap(rng.uni(8.0, 30.0), 0.15);
            let r = rng.uni(0.1, 0.35);
            // Depth in cell units, at most 0.6 r: edge slope about 2 d / r <= 1.2.
            (f, r, rng.uni(0.2, 0.7), rng.uni(0.1, 0.6) * r / f)
        });
        Self {
            seed: ctx.seed(7),
            base,
            alt,
            freq,
            oct: ctx.oct(freq, 6),
            fine_freq,
            fine: rng.uni(0.05, 0.2),
            agg,
            pits,
            band: rng.chance(0.2).then(|| (rng.uni(3.0, 12.0), rng.uni(0.1, 0.3))),
            rough: rng.uni(0.55, 1.0),
            ks: f0(rng, 0.02, 0.04),
            amp: rng.uni(0.05, 0.3) / freq,
            fine_amp: rng.uni(0.05, 0.3) / fine_freq,
        }
    }
}

impl Pattern for Stone {
    fn texel(&self, p: V2) -> Texel {
        let n = fbm([p[0] * self.freq, p[1] * self.freq], self.seed, self.oct, 0.55);
        let fine = gnoise([p[0] * self.fine_freq, p[1] * self.fine_freq], self.seed ^ 0x1);
        let mut kd = mul(mix3(self.base, self.alt, smoothstep(-0.5, 0.5, n)), 1.0 + self.fine * fine);
        let mut rough = self.rough * (1.0 - 0.1 * n);
        let mut h = self.amp * n + self.fine_amp * fine;
        if let Some((bf, ba)) = self.band {
            let b = gnoise([p[1] * bf + 2.0 * n, 0.37], self.seed ^ 0x2);
            kd = mul(kd, 1.0 + ba * b);
        }
        if let Some((f, r, prob)) = self.agg {
            let c = worley([p[0] * f, p[1] * f], self.seed ^ 0x3, 1.0);
            let rr = r * (0.5 + rnd(c.id, 1));
            if rnd(c.id, 2) < prob && c.f1 < rr {
                let w = smoothstep(rr, 0.8 * rr, c.f1);
                let chip = mix3(mul(self.base, 0.3), mul(self.alt, 1.4), rnd(c.id, 3));
                kd = mix3(kd, chip, w);
                rough = lerp(rough, rough * 0.8, w);
            }
        }
        if let Some((f, r, prob, depth)) = self.pits {
            let c = worley([p[0] * f, p[1] * f], self.seed ^ 0x4, 1.0);
            let rr = r * (0.4 + rnd(c.id, 1));
            if rnd(c.id, 2) < prob && c.f1 < rr {
                let q = c.f1 / rr;
                let w = (1.0 - q * q) * (1.0 - q * q);
                h -= depth * w * (rr / r);
                kd = mul(kd, 1.0 - 0.5 * w);
                rough = lerp(rough, 1.0, w);
            }
        }
        Texel { kd, ks: self.ks, rough, h }
    }
}

// ---------------------------------------------------------------------------
// Fabric: warp threads along y, weft along x, one thread per pattern unit;
// weave decides which is on top per cell. Optional stripes/plaid.

#[derive(Clone, Copy)]
enum Weave {
    Plain,
    Twill(i32, i32),
    Basket,
    Satin,
}

impl Weave {
    #[inline(always)]
    fn warp_up(self, i: i32, j: i32) -> bool {
        match self {
            Weave::Plain => (i + j) & 1 == 0,
            Weave::Twill(n, k) => (i + j).rem_euclid(n) < k,
            Weave::Basket => ((i >> 1) + (j >> 1)) & 1 == 0,
            Weave::Satin => (2 * i + j).rem_euclid(5) != 0,
        }
    }
}

struct Fabric {
    seed: u32,
    weave: Weave,
    warp: [Rgb; 4],
    weft: [Rgb; 4],
    warp_stripe: i32,
    weft_stripe: i32,
    ncol: u32,
    tw: f32,
    amp: f32,
    fibre: f32,
    fibre_freq: f32,
    slub: f32,
    rough: f32,
    ks: Rgb,
}

impl Fabric {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let weave = match rng.random_range(0..6) {
            0 | 1 => Weave::Plain,
            2 => Weave::Twill(3, rng.random_range(1..3)),
            3 => Weave::Twill(4, 2),
            4 => Weave::Basket,
            _ => Weave::Satin,
        };
        let denim = rng.chance(0.15);
        let base = if denim {
            hsv_lin(rng.uni(0.58, 0.64), rng.uni(0.5, 0.8), rng.uni(0.25, 0.5))
        } else {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.8), rng.uni(0.15, 0.85))
        };
        let weft0 = if denim {
            hsv_lin(0.1, rng.uni(0.05, 0.15), rng.uni(0.7, 0.85))
        } else if rng.chance(0.6) {
            vary(rng, base, (0.85, 1.1), 0.05)
        } else {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.8), rng.uni(0.15, 0.85))
        };
        let mut warp = [base; 4];
        let mut weft = [weft0; 4];
        let striped = !denim && rng.chance(0.35);
        if striped {
            for k in 1..4 {
                warp[k] = hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.8), rng.uni(0.1, 0.9));
                weft[k] = if rng.chance(0.7) { warp[k] } else { weft0 };
            }
        }
        let silky = matches!(weave, Weave::Satin) || rng.chance(0.15);
        Self {
            seed: ctx.seed(8),
            weave,
            warp,
            weft,
            warp_stripe: rng.random_range(2..16),
            weft_stripe: if rng.chance(0.6) { rng.random_range(2..16) } else { i32::MAX },
            ncol: if striped { rng.random_range(2..5) } else { 1 },
            tw: rng.uni(0.7, 0.95),
            amp: rng.uni(0.08, 0.25),
            fibre: rng.uni(0.05, 0.2),
            fibre_freq: ctx.cap(rng.uni(4.0, 10.0), 0.3),
            slub: rng.uni(0.0, 0.1),
            rough: if silky { rng.uni(0.25, 0.45) } else { rng.uni(0.65, 1.0) },
            ks: if silky { f0(rng, 0.04, 0.07) } else { f0(rng, 0.02, 0.04) },
        }
    }
}

impl Pattern for Fabric {
    fn texel(&self, p: V2) -> Texel {
        let i = floor_i(p[0]);
        let j = floor_i(p[1]);
        let fx = p[0] - i as f32;
        let fy = p[1] - j as f32;
        let up = self.weave.warp_up(i, j);
        // Thread cross-sections (warp runs along y, so its profile is in x).
        let half = 0.5 * self.tw;
        let tx = (fx - 0.5) / half;
        let ty = (fy - 0.5) / half;
        let warp_prof = (1.0 - tx * tx).max(0.0);
        let weft_prof = (1.0 - ty * ty).max(0.0);
        // The top thread bows up in the middle of the cell and dives at its ends.
        let bow_warp = 0.75 + 0.25 * (1.0 - (2.0 * fy - 1.0).powi(2));
        let bow_weft = 0.75 + 0.25 * (1.0 - (2.0 * fx - 1.0).powi(2));
        let h_warp = warp_prof * if up { bow_warp } else { 0.45 };
        let h_weft = weft_prof * if up { 0.45 } else { bow_weft };
        let warp_top = h_warp >= h_weft;
        let (col, along, across, th) = if warp_top {
            let k = hash1(i.div_euclid(self.warp_stripe), self.seed) % self.ncol;
            (self.warp[k as usize], p[1], p[0], hash1(i, self.seed ^ 0x1))
        } else {
            let k = if self.weft_stripe == i32::MAX {
                0
            } else {
                hash1(j.div_euclid(self.weft_stripe), self.seed ^ 0x2) % self.ncol
            };
            (self.weft[k as usize], p[0], p[1], hash1(j, self.seed ^ 0x3))
        };
        // Fibres: fine noise across the thread, slow along it, with a twist.
        let fib = gnoise([across * self.fibre_freq + along * 0.8, along * 1.5], self.seed ^ 0x4);
        let hmax = h_warp.max(h_weft);
        // Gaps between threads show the shadowed interior.
        let shade = 0.35 + 0.65 * smoothstep(0.0, 0.35, hmax);
        let kd = mul(col, shade * (1.0 + self.fibre * fib) * (1.0 + self.slub * srnd(th, 1)));
        Texel { kd, ks: self.ks, rough: (self.rough * (1.0 + 0.1 * fib)).min(1.0), h: self.amp * (hmax + 0.05 * fib) }
    }
}

// ---------------------------------------------------------------------------
// Leather: distorted Voronoi cells bulge between creases (F2 - F1 near 0),
// plus a finer crease network and colour mottling.

struct Leather {
    seed: u32,
    kd: Rgb,
    dark: f32,
    rough: f32,
    rough_crease: f32,
    ks: Rgb,
    warp: f32,
    cw: f32,
    depth: f32,
    bulge: f32,
    fine_freq: f32,
    fine_depth: f32,
    mottle: f32,
}

impl Leather {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let kd = match rng.random_range(0..5) {
            0 => hsv_lin(rng.uni(0.05, 0.09), rng.uni(0.4, 0.75), rng.uni(0.15, 0.55)), // brown
            1 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.2), rng.uni(0.03, 0.12)),    // black
            2 => hsv_lin(rng.uni(0.07, 0.1), rng.uni(0.35, 0.6), rng.uni(0.5, 0.75)),   // tan
            3 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.5, 0.9), rng.uni(0.2, 0.6)),      // dyed
            _ => hsv_lin(rng.uni(0.05, 0.12), rng.uni(0.0, 0.1), rng.uni(0.8, 0.9)),    // white
        };
        let cw = rng.uni(0.05, 0.15);
        let fine_freq = ctx.cap(rng.uni(3.0, 6.0), 0.12);
        Self {
            seed: ctx.seed(9),
            kd,
            dark: rng.uni(0.4, 0.85),
            rough: rng.uni(0.3, 0.7),
            rough_crease: rng.uni(0.05, 0.2),
            ks: f0(rng, 0.03, 0.05),
            warp: rng.uni(0.1, 0.35),
            cw,
            // Crease wall slope about 1.5 depth / cw, kept below 1.2.
            depth: rng.uni(0.2, 0.8) * cw,
            bulge: rng.uni(0.01, 0.05),
            fine_freq,
            fine_depth: rng.uni(0.0, 0.03),
            mottle: rng.uni(0.03, 0.15),
        }
    }
}

impl Pattern for Leather {
    fn texel(&self, p: V2) -> Texel {
        let q = [
            p[0] + self.warp * gnoise([p[0] * 0.7, p[1] * 0.7], self.seed),
            p[1] + self.warp * gnoise([p[0] * 0.7 + 5.3, p[1] * 0.7 - 2.1], self.seed ^ 0x1),
        ];
        let c = worley(q, self.seed ^ 0x2, 0.9);
        let border = c.f2 - c.f1;
        let crease = 1.0 - smoothstep(0.0, self.cw, border);
        let c2 = worley([p[0] * self.fine_freq, p[1] * self.fine_freq], self.seed ^ 0x3, 1.0);
        let fine = 1.0 - smoothstep(0.0, 0.15, c2.f2 - c2.f1);
        let h =
            self.bulge * smoothstep(0.0, 0.6, border) - self.depth * crease - self.fine_depth * fine / self.fine_freq;
        let mot = fbm([p[0] * 0.5, p[1] * 0.5], self.seed ^ 0x4, 3, 0.5);
        let shade = lerp(1.0, self.dark, crease.max(0.5 * fine));
        Texel {
            kd: mul(self.kd, shade * (1.0 + self.mottle * (mot + 0.5 * srnd(c.id, 1)))),
            ks: self.ks,
            rough: self.rough + self.rough_crease * crease,
            h,
        }
    }
}

// ---------------------------------------------------------------------------
// Plastics: smooth or textured dielectrics (orange peel, stipple, dimples or
// bumps, ribs).

#[derive(Clone, Copy)]
enum PlasticTexture {
    Smooth,
    Stipple,
    Dimple,
    Ribbed,
}

struct Plastic {
    seed: u32,
    kd: Rgb,
    ks: Rgb,
    rough: f32,
    rough_var: f32,
    texture: PlasticTexture,
    freq: f32,
    oct: u32,
    amp: f32,
    radius: f32,
    tone: f32,
}

impl Plastic {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let kd = if rng.chance(0.65) {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.5, 1.0), rng.uni(0.3, 0.95))
        } else {
            grey(rng.uni(0.02, 0.9))
        };
        let (texture, freq, slope) = match rng.random_range(0..10) {
            0..=3 => (PlasticTexture::Smooth, rng.uni(5.0, 15.0), rng.uni(0.005, 0.04)),
            4..=5 => (PlasticTexture::Stipple, ctx.cap(rng.uni(20.0, 60.0), 0.25), rng.uni(0.1, 0.5)),
            6..=7 => (PlasticTexture::Dimple, ctx.cap(rng.uni(5.0, 20.0), 0.12), rng.uni(0.2, 0.8)),
            _ => (PlasticTexture::Ribbed, ctx.cap(rng.uni(3.0, 15.0), 0.1), rng.uni(0.2, 0.8)),
        };
        let radius = rng.uni(0.25, 0.45);
        let amp = match texture {
            // smoothstep over `radius` has a peak slope of 1.5 amp / radius.
            PlasticTexture::Dimple => slope * radius / 1.5 / freq * if rng.chance(0.5) { 1.0 } else { -1.0 },
            // Ribs: smoothstep over 0.4 of the period, twice per period.
            PlasticTexture::Ribbed => slope * 0.2 / 1.5 / freq,
            _ => slope / freq,
        };
        Self {
            seed: ctx.seed(10),
            kd,
            ks: f0(rng, 0.04, 0.05),
            rough: rng.uni(0.04, 0.55),
            rough_var: rng.uni(0.0, 0.1),
            texture,
            freq,
            oct: ctx.oct(freq, 3),
            amp,
            radius,
            tone: rng.uni(0.0, 0.04),
        }
    }
}

impl Pattern for Plastic {
    fn texel(&self, p: V2) -> Texel {
        let q = [p[0] * self.freq, p[1] * self.freq];
        let (h, var) = match self.texture {
            PlasticTexture::Smooth => (self.amp * fbm(q, self.seed, self.oct, 0.5), 0.0),
            PlasticTexture::Stipple => {
                let n = fbm(q, self.seed, self.oct.min(2), 0.5);
                (self.amp * n, n)
            }
            PlasticTexture::Dimple => {
                let c = worley(q, self.seed, 0.8);
                let w = smoothstep(self.radius, 0.0, c.f1);
                (-self.amp * w, w)
            }
            PlasticTexture::Ribbed => {
                let t = (2.0 * fract(q[0]) - 1.0).abs();
                let w = smoothstep(0.3, 0.7, t);
                (self.amp * w, w - 0.5)
            }
        };
        let v = vnoise([p[0] * 2.0, p[1] * 2.0], self.seed ^ 0x1) - 0.5;
        Texel {
            kd: mul(self.kd, 1.0 + self.tone * v),
            ks: self.ks,
            rough: self.rough * (1.0 + self.rough_var * (var + v)),
            h,
        }
    }
}

// ---------------------------------------------------------------------------
// Marble: broad veins along fbm-warped bands that fade in and out, thin
// crackle veins on the zero set of another noise, over a cloudy base;
// polished or honed.

struct Marble {
    seed: u32,
    base: Rgb,
    base2: Rgb,
    vein: Rgb,
    vein2: Rgb,
    dir: V2,
    freq: f32,
    warp_freq: f32,
    warp_oct: u32,
    warp_amp: f32,
    sharp: f32,
    crack_freq: f32,
    crack_w: f32,
    crack: f32,
    cloud_oct: u32,
    rough: f32,
    ks: Rgb,
    relief: f32,
}

impl Marble {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let (base, vein) = match rng.random_range(0..6) {
            // Carrara: white, grey veins.
            0 => (
                hsv_lin(0.1, rng.uni(0.0, 0.05), rng.uni(0.85, 0.95)),
                hsv_lin(0.6, rng.uni(0.0, 0.1), rng.uni(0.3, 0.6)),
            ),
            // Nero Marquina: black, white veins.
            1 => (hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.1), rng.uni(0.03, 0.1)), grey(rng.uni(0.6, 0.85))),
            // Verde: dark green, light veins.
            2 => (
                hsv_lin(rng.uni(0.3, 0.45), rng.uni(0.3, 0.6), rng.uni(0.15, 0.35)),
                hsv_lin(0.35, 0.1, rng.uni(0.6, 0.9)),
            ),
            // Rosso / pink.
            3 => (
                hsv_lin(rng.uni(-0.02, 0.05), rng.uni(0.2, 0.45), rng.uni(0.55, 0.8)),
                hsv_lin(0.0, 0.5, rng.uni(0.25, 0.45)),
            ),
            // Botticino / travertine beige.
            4 => (
                hsv_lin(rng.uni(0.08, 0.12), rng.uni(0.15, 0.35), rng.uni(0.65, 0.85)),
                hsv_lin(0.07, 0.4, rng.uni(0.3, 0.5)),
            ),
            // Calacatta: white, golden veins.
            _ => (
                hsv_lin(0.1, rng.uni(0.0, 0.05), rng.uni(0.85, 0.95)),
                hsv_lin(0.1, rng.uni(0.25, 0.45), rng.uni(0.45, 0.65)),
            ),
        };
        let a = rng.uni(0.0, std::f32::consts::PI);
        let warp_freq = rng.uni(0.7, 2.0);
        let polished = rng.chance(0.75);
        Self {
            seed: ctx.seed(11),
            base2: vary(rng, base, (0.8, 1.05), 0.05),
            base,
            vein2: mix3(vein, base, rng.uni(0.1, 0.5)),
            vein,
            dir: [a.cos(), a.sin()],
            freq: rng.uni(0.4, 1.5),
            warp_freq,
            warp_oct: ctx.oct(warp_freq, 6),
            warp_amp: rng.uni(1.0, 4.0),
            sharp: rng.log_uni(4.0, 30.0),
            crack_freq: rng.uni(1.5, 5.0),
            crack_w: rng.uni(0.01, 0.05),
            crack: if rng.chance(0.5) { rng.uni(0.15, 0.6) } else { 0.0 },
            cloud_oct: ctx.oct(1.5, 4),
            rough: if polished { rng.uni(0.03, 0.15) } else { rng.uni(0.3, 0.5) },
            ks: f0(rng, 0.04, 0.05),
            relief: rng.uni(0.0, 0.0015),
        }
    }
}

impl Pattern for Marble {
    fn texel(&self, p: V2) -> Texel {
        let w = fbm([p[0] * self.warp_freq, p[1] * self.warp_freq], self.seed, self.warp_oct, 0.5);
        // Triangle wave: 0 on the vein centre lines, 1 half-way between.
        let s1 = (p[0] * self.dir[0] + p[1] * self.dir[1]) * self.freq + self.warp_amp * w;
        let fade = smoothstep(-0.35, 0.25, gnoise([p[0] * 0.6 + 3.1, p[1] * 0.6], self.seed ^ 0x2));
        let v1 = (1.0 - (2.0 * fract(s1) - 1.0).abs()).powf(self.sharp) * (0.25 + 0.75 * fade);
        let v2 = if self.crack > 0.0 {
            let q = [p[0] * self.crack_freq + w, p[1] * self.crack_freq - w];
            let t = gnoise(q, self.seed ^ 0x3).abs();
            self.crack * smoothstep(self.crack_w, 0.0, t)
        } else {
            0.0
        };
        let cloud = fbm([p[0] * 1.5, p[1] * 1.5], self.seed ^ 0x1, self.cloud_oct, 0.5);
        let kd = mix3(self.base, self.base2, smoothstep(-0.4, 0.4, cloud));
        let kd = mix3(mix3(kd, self.vein2, v2), self.vein, v1);
        let v = v1.max(v2);
        Texel { kd, ks: self.ks, rough: self.rough * (1.0 + 0.3 * v), h: -self.relief * v + 0.0005 * cloud }
    }
}

// ---------------------------------------------------------------------------
// Scratched and dented: a base (metal, or paint/plastic that may expose metal
// in the scratches) with two layers of random line scratches (one segment per
// grid cell, searched in 3x3 cells) and parabolic dents.

struct ScratchLayer {
    seed: u32,
    freq: f32,
    prob: f32,
    width: f32,
    depth: f32,
    angle: f32,
    spread: f32,
}

impl ScratchLayer {
    fn new(rng: &mut Pcg64, ctx: &Ctx, seed: u32, freq: f32, angle: f32, spread: f32) -> Self {
        let freq = ctx.cap(freq, 0.05);
        // Width in cell units: at least half a pixel so scratches do not vanish.
        let width = rng.uni(0.008, 0.03).max(0.5 * ctx.pixel * freq);
        Self { seed, freq, prob: rng.uni(0.3, 0.9), width, depth: rng.uni(0.05, 0.3) * width / freq, angle, spread }
    }

    /// Scratch strength in [0, 1] and height at p.
    #[inline]
    fn eval(&self, p: V2) -> (f32, f32) {
        let q = [p[0] * self.freq, p[1] * self.freq];
        let xi = floor_i(q[0]);
        let yi = floor_i(q[1]);
        let mut s = 0.0f32;
        for dy in -1..=1 {
            let row = row_hash(yi + dy, self.seed);
            for dx in -1..=1 {
                let h = cell_hash(xi + dx, row);
                if rnd(h, 0) >= self.prob {
                    continue;
                }
                let cx = (xi + dx) as f32 + rnd(h, 1);
                let cy = (yi + dy) as f32 + rnd(h, 2);
                let half = 0.3 + 0.7 * rnd(h, 3);
                let w = self.width * (0.5 + rnd(h, 4));
                // Cheap reject before the segment distance.
                let (ox, oy) = (q[0] - cx, q[1] - cy);
                if ox * ox + oy * oy > (half + w) * (half + w) {
                    continue;
                }
                let a = self.angle + self.spread * srnd(h, 5);
                let (dxs, dys) = (a.cos() * half, a.sin() * half);
                let d = segment_distance(q, [cx - dxs, cy - dys], [cx + dxs, cy + dys]) / w;
                if d < 1.0 {
                    s = s.max((1.0 - d * d) * (0.5 + 0.5 * rnd(h, 6)));
                }
            }
        }
        (s, -self.depth * s)
    }
}

struct Scratched {
    seed: u32,
    kd: Rgb,
    ks: Rgb,
    rough: f32,
    scratch_kd: Rgb,
    scratch_ks: Rgb,
    scratch_rough: f32,
    layers: [ScratchLayer; 2],
    dents: Option<(f32, f32, f32, f32)>,
    wave_amp: f32,
}

impl Scratched {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let metal = rng.chance(0.55);
        let (kd, ks, rough, scratch_kd, scratch_ks, scratch_rough) = if metal {
            let ks = metal_f0(rng);
            let kd = metal_kd(rng, ks);
            (kd, ks, rng.uni(0.05, 0.35), kd, mul(ks, rng.uni(0.9, 1.0)), rng.uni(0.15, 0.5))
        } else {
            let kd = hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.9), rng.uni(0.1, 0.85));
            let ks = f0(rng, 0.04, 0.05);
            let rough = rng.uni(0.2, 0.6);
            if rng.chance(0.5) {
                // Paint over metal: scratches expose it.
                let m = metal_f0(rng);
                (kd, ks, rough, metal_kd(rng, m), m, rng.uni(0.2, 0.45))
            } else {
                // Scratched plastic whitens and roughens.
                (kd, ks, rough, mix3(kd, grey(0.8), rng.uni(0.1, 0.4)), ks, (rough + rng.uni(0.1, 0.3)).min(1.0))
            }
        };
        let angle = rng.uni(0.0, std::f32::consts::PI);
        let spread = if rng.chance(0.5) { rng.uni(0.05, 0.4) } else { std::f32::consts::FRAC_PI_2 };
        let s = ctx.seed(12);
        let layers = [
            {
                let f = rng.uni(2.0, 6.0);
                ScratchLayer::new(rng, ctx, s ^ 0x1, f, angle, spread)
            },
            {
                let f = rng.uni(8.0, 20.0);
                ScratchLayer::new(rng, ctx, s ^ 0x2, f, angle, spread)
            },
        ];
        let dents = rng.chance(0.6).then(|| {
            let f = ctx.cap(rng.uni(1.5, 5.0), 0.05);
            let r = rng.uni(0.2, 0.45);
            // Peak slope of depth (1 - q^2)^2 is about 1.54 depth / r (cell units).
            (f, r, rng.uni(0.3, 0.8), rng.uni(0.1, 0.5) * r / f)
        });
        Self {
            seed: s,
            kd,
            ks,
            rough,
            scratch_kd,
            scratch_ks,
            scratch_rough,
            layers,
            dents,
            wave_amp: rng.uni(0.002, 0.02) / 2.0,
        }
    }
}

impl Pattern for Scratched {
    fn texel(&self, p: V2) -> Texel {
        let (s1, h1) = self.layers[0].eval(p);
        let (s2, h2) = self.layers[1].eval(p);
        let s = s1.max(s2);
        let mut h = h1 + h2 + self.wave_amp * gnoise([p[0] * 2.0, p[1] * 2.0], self.seed);
        if let Some((f, r, prob, depth)) = self.dents {
            let c = worley([p[0] * f, p[1] * f], self.seed ^ 0x3, 1.0);
            let rr = r * (0.6 + 0.8 * rnd(c.id, 1));
            if rnd(c.id, 2) < prob && c.f1 < rr {
                let q = c.f1 / rr;
                h -= depth * (rr / r) * (1.0 - q * q) * (1.0 - q * q);
            }
        }
        let w = smoothstep(0.0, 0.3, s);
        Texel {
            kd: mix3(self.kd, self.scratch_kd, w),
            ks: mix3(self.ks, self.scratch_ks, w),
            rough: lerp(self.rough, self.scratch_rough, w),
            h,
        }
    }
}

// ---------------------------------------------------------------------------
// Cobblestone: domed Voronoi stones (distorted for irregular outlines) set in
// sand, soil or mortar; stone tops worn smoother.

struct Cobblestone {
    seed: u32,
    c1: Rgb,
    c2: Rgb,
    jitter: f32,
    gap_kd: Rgb,
    gap_rough: f32,
    gap: f32,
    round: f32,
    dome: f32,
    aa: f32,
    distort: f32,
    tex_freq: f32,
    tex_oct: u32,
    rough: f32,
    wear: f32,
    ks: Rgb,
}

impl Cobblestone {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let c1 = match rng.random_range(0..4) {
            0 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.1), rng.uni(0.25, 0.65)),
            1 => hsv_lin(rng.uni(0.06, 0.11), rng.uni(0.15, 0.4), rng.uni(0.35, 0.7)),
            2 => hsv_lin(rng.uni(0.0, 0.05), rng.uni(0.3, 0.55), rng.uni(0.3, 0.55)),
            _ => hsv_lin(rng.uni(0.5, 0.65), rng.uni(0.05, 0.2), rng.uni(0.2, 0.45)),
        };
        let c2 = vary(rng, c1, (0.5, 1.4), 0.15);
        let gap_kd = if rng.chance(0.5) {
            hsv_lin(rng.uni(0.06, 0.1), rng.uni(0.3, 0.5), rng.uni(0.1, 0.3))
        } else {
            hsv_lin(rng.uni(0.05, 0.12), rng.uni(0.0, 0.15), rng.uni(0.35, 0.65))
        };
        let round = rng.uni(0.1, 0.3);
        let tex_freq = rng.uni(4.0, 8.0);
        Self {
            seed: ctx.seed(13),
            c1,
            c2,
            jitter: rng.uni(0.05, 0.25),
            gap_kd,
            gap_rough: rng.uni(0.85, 1.0),
            gap: rng.uni(0.015, 0.05),
            round,
            dome: rng.uni(0.2, 0.5) * round,
            aa: (0.7 * ctx.pixel).max(0.003),
            distort: rng.uni(0.05, 0.2),
            tex_freq,
            tex_oct: ctx.oct(tex_freq, 3),
            rough: rng.uni(0.45, 0.9),
            wear: rng.uni(0.0, 0.3),
            ks: f0(rng, 0.02, 0.04),
        }
    }
}

impl Pattern for Cobblestone {
    fn texel(&self, p: V2) -> Texel {
        let q = [
            p[0] + self.distort * gnoise([p[0] * 2.0, p[1] * 2.0], self.seed),
            p[1] + self.distort * gnoise([p[0] * 2.0 + 7.7, p[1] * 2.0 + 1.3], self.seed ^ 0x1),
        ];
        let c = worley(q, self.seed ^ 0x2, 0.85);
        // Half of F2 - F1 approximates the distance to the cell border.
        let e = 0.5 * (c.f2 - c.f1);
        let tex = fbm([p[0] * self.tex_freq, p[1] * self.tex_freq], self.seed ^ 0x3, self.tex_oct, 0.5);
        let mask = smoothstep(self.gap - self.aa, self.gap + self.aa, e);
        let profile = smoothstep(self.gap, self.gap + self.round, e);
        let stone = mul(mix3(self.c1, self.c2, rnd(c.id, 1)), (1.0 + self.jitter * srnd(c.id, 2)) * (1.0 + 0.2 * tex));
        let gap = mul(self.gap_kd, 1.0 + 0.3 * tex);
        let h_stone = self.dome * profile * (0.7 + 0.3 * rnd(c.id, 3)) + 0.01 * tex / self.tex_freq;
        let h_gap = -0.3 * self.gap + 0.02 * tex / self.tex_freq;
        Texel {
            kd: mix3(gap, stone, mask),
            ks: self.ks,
            rough: lerp(self.gap_rough, self.rough * (1.0 - self.wear * profile), mask),
            h: lerp(h_gap, h_stone, profile),
        }
    }
}

// ---------------------------------------------------------------------------
// Terrazzo: polished cement matrix with two sizes of irregular stone chips
// drawn from a small palette.

struct Terrazzo {
    seed: u32,
    matrix: Rgb,
    chips: [Rgb; 4],
    /// (frequency, radius, probability, edge half-width), radii in cell units.
    layers: [(f32, f32, f32, f32); 2],
    rough: f32,
    ks: Rgb,
    mottle_oct: u32,
}

impl Terrazzo {
    fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let matrix = match rng.random_range(0..4) {
            0 => hsv_lin(rng.uni(0.05, 0.12), rng.uni(0.0, 0.1), rng.uni(0.75, 0.92)),
            1 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.08), rng.uni(0.35, 0.65)),
            2 => hsv_lin(rng.uni(0.95, 1.05), rng.uni(0.15, 0.35), rng.uni(0.7, 0.85)),
            _ => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.1), rng.uni(0.05, 0.15)),
        };
        let mut chips = [[0.0; 3]; 4];
        for c in &mut chips {
            *c = match rng.random_range(0..4) {
                0 => grey(rng.uni(0.02, 0.9)),
                1 => hsv_lin(rng.uni(0.0, 0.08), rng.uni(0.4, 0.8), rng.uni(0.3, 0.7)),
                2 => hsv_lin(rng.uni(0.25, 0.45), rng.uni(0.2, 0.6), rng.uni(0.2, 0.6)),
                _ => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.7), rng.uni(0.2, 0.9)),
            };
        }
        let f1 = ctx.cap(rng.uni(3.0, 8.0), 0.06);
        let f2 = ctx.cap(rng.uni(10.0, 25.0), 0.1);
        Self {
            seed: ctx.seed(14),
            matrix,
            chips,
            layers: [
                (f1, rng.uni(0.25, 0.45), rng.uni(0.4, 0.95), 0.7 * ctx.pixel * f1),
                (f2, rng.uni(0.25, 0.45), rng.uni(0.4, 0.95), 0.7 * ctx.pixel * f2),
            ],
            rough: rng.uni(0.05, 0.3),
            ks: f0(rng, 0.04, 0.05),
            mottle_oct: ctx.oct(2.0, 3),
        }
    }
}

impl Pattern for Terrazzo {
    fn texel(&self, p: V2) -> Texel {
        let mot = fbm([p[0] * 2.0, p[1] * 2.0], self.seed, self.mottle_oct, 0.5);
        let mut kd = mul(self.matrix, 1.0 + 0.08 * mot);
        let mut rough = self.rough + 0.05;
        let mut h = 0.0003 * mot;
        for (k, &(f, r, prob, aa)) in self.layers.iter().enumerate() {
            let c = worley([p[0] * f, p[1] * f], self.seed ^ (k as u32 + 1), 1.0);
            let rr = r * (0.6 + 0.4 * rnd(c.id, 1));
            if c.f1 < 1.3 * rr && rnd(c.id, 2) < prob {
                // Angular outline: radius modulated by noise on the offset direction.
                let edge = rr * (1.0 + 0.25 * gnoise([c.delta[0] * 4.0 / r, c.delta[1] * 4.0 / r], c.id));
                let w = smoothstep(edge + aa, edge - aa, c.f1);
                let chip = mul(self.chips[(c.id >> 3) as usize & 3], 1.0 + 0.1 * srnd(c.id, 3));
                kd = mix3(kd, chip, w);
                rough = lerp(rough, self.rough, w);
                h += 0.0002 * w / f;
            }
        }
        Texel { kd, ks: self.ks, rough, h }
    }
}
