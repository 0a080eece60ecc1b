//! Cobblestone: domed Voronoi stones (distorted for irregular outlines) set in
//! sand, soil or mortar; stone tops worn smoother.

use super::*;

pub(super) struct Cobblestone {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
