//! Leather: distorted Voronoi cells bulge between creases (F2 - F1 near 0),
//! plus a finer crease network and colour mottling.

use super::*;

pub(super) struct Leather {
    seed: u32,
    kd: Rgb,
    dark: f32,
    rough: f32,
    rough_crease: f32,
    ks: Rgb,
    warp: f32,
    cw: f32,
    depth: f32,
    bulge: f32,
    fine_freq: f32,
    fine_depth: f32,
    mottle: f32,
}

impl Leather {
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let kd = match rng.random_range(0..5) {
            0 => hsv_lin(rng.uni(0.05, 0.09), rng.uni(0.4, 0.75), rng.uni(0.15, 0.55)), // brown
            1 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.2), rng.uni(0.03, 0.12)),    // black
            2 => hsv_lin(rng.uni(0.07, 0.1), rng.uni(0.35, 0.6), rng.uni(0.5, 0.75)),   // tan
            3 => hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.5, 0.9), rng.uni(0.2, 0.6)),      // dyed
            _ => hsv_lin(rng.uni(0.05, 0.12), rng.uni(0.0, 0.1), rng.uni(0.8, 0.9)),    // white
        };
        let cw = rng.uni(0.05, 0.15);
        let fine_freq = ctx.cap(rng.uni(3.0, 6.0), 0.12);
        Self {
            seed: ctx.seed(9),
            kd,
            dark: rng.uni(0.4, 0.85),
            rough: rng.uni(0.3, 0.7),
            rough_crease: rng.uni(0.05, 0.2),
            ks: f0(rng, 0.03, 0.05),
            warp: rng.uni(0.1, 0.35),
            cw,
            // Crease wall slope about 1.5 depth / cw, kept below 1.2.
            depth: rng.uni(0.2, 0.8) * cw,
            bulge: rng.uni(0.01, 0.05),
            fine_freq,
            fine_depth: rng.uni(0.0, 0.03),
            mottle: rng.uni(0.03, 0.15),
        }
    }
}

impl Pattern for Leather {
    fn texel(&self, p: V2) -> Texel {
        let q = [
            p[0] + self.warp * gnoise([p[0] * 0.7, p[1] * 0.7], self.seed),
            p[1] + self.warp * gnoise([p[0] * 0.7 + 5.3, p[1] * 0.7 - 2.1], self.seed ^ 0x1),
        ];
        let c = worley(q, self.seed ^ 0x2, 0.9);
        let border = c.f2 - c.f1;
        let crease = 1.0 - smoothstep(0.0, self.cw, border);
        let c2 = worley([p[0] * self.fine_freq, p[1] * self.fine_freq], self.seed ^ 0x3, 1.0);
        let fine = 1.0 - smoothstep(0.0, 0.15, c2.f2 - c2.f1);
        let h =
            self.bulge * smoothstep(0.0, 0.6, border) - self.depth * crease - self.fine_depth * fine / self.fine_freq;
        let mot = fbm([p[0] * 0.5, p[1] * 0.5], self.seed ^ 0x4, 3, 0.5);
        let shade = lerp(1.0, self.dark, crease.max(0.5 * fine));
        Texel {
            kd: mul(self.kd, shade * (1.0 + self.mottle * (mot + 0.5 * srnd(c.id, 1)))),
            ks: self.ks,
            rough: self.rough + self.rough_crease * crease,
            h,
        }
    }
}
