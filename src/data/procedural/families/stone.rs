//! Stone and concrete: multi-scale fbm colour, optional aggregates (Voronoi
//! chips of other colours), pits (small round holes), sedimentary banding.

use super::*;

pub(super) struct Stone {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
