//! Wood: planks along x with staggered end joints, growth rings from a
//! slightly conical log cut at a random depth (cathedral arches), fine
//! streaks and pores stretched along the grain.

use super::*;

pub(super) struct Wood {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
