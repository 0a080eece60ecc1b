//! Marble: broad veins along fbm-warped bands that fade in and out, thin
//! crackle veins on the zero set of another noise, over a cloudy base;
//! polished or honed.

use super::*;

pub(super) struct Marble {
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
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
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
