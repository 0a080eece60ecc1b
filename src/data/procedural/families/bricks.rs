//! Bricks: offset rows, recessed mortar, chipped edges, per-brick colour
//! (two-tone palette, occasional burnt bricks), grain and speckles.

use super::*;

pub(super) struct Bricks {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
