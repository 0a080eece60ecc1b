//! Polished metal: coloured F0, near-black diffuse, low roughness with smudges;
//! sometimes hammered (parabolic dimples on a Voronoi grid).

use super::*;

pub(super) struct PolishedMetal {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
