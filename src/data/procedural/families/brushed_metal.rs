//! Brushed metal: streak noise stretched along the brushing direction (linear
//! or circular around a centre); the streaks modulate roughness and heights,
//! so normals vary across the streaks only (anisotropic look).

use super::*;

pub(super) struct BrushedMetal {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
