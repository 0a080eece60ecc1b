//! Ceramic tiles: grid (or running bond), recessed grout, bevelled edges,
//! per-tile colour jitter and slight tilt, glossy glaze with low waviness.

use super::*;

pub(super) struct Tiles {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
