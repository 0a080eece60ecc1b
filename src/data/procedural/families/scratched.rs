//! Scratched and dented: a base (metal, or paint/plastic that may expose metal
//! in the scratches) with two layers of random line scratches (one segment per
//! grid cell, searched in 3x3 cells) and parabolic dents.

use super::*;

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

pub(super) struct Scratched {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
