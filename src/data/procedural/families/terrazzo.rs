//! Terrazzo: polished cement matrix with two sizes of irregular stone chips
//! drawn from a small palette.

use super::*;

pub(super) struct Terrazzo {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
