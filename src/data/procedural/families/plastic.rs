//! Plastics: smooth or textured dielectrics (orange peel, stipple, dimples or
//! bumps, ribs).

use super::*;

#[derive(Clone, Copy)]
enum PlasticTexture {
    Smooth,
    Stipple,
    Dimple,
    Ribbed,
}

pub(super) struct Plastic {
    seed: u32,
    kd: Rgb,
    ks: Rgb,
    rough: f32,
    rough_var: f32,
    texture: PlasticTexture,
    freq: f32,
    oct: u32,
    amp: f32,
    radius: f32,
    tone: f32,
}

impl Plastic {
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let kd = if rng.chance(0.65) {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.5, 1.0), rng.uni(0.3, 0.95))
        } else {
            grey(rng.uni(0.02, 0.9))
        };
        let (texture, freq, slope) = match rng.random_range(0..10) {
            0..=3 => (PlasticTexture::Smooth, rng.uni(5.0, 15.0), rng.uni(0.005, 0.04)),
            4..=5 => (PlasticTexture::Stipple, ctx.cap(rng.uni(20.0, 60.0), 0.25), rng.uni(0.1, 0.5)),
            6..=7 => (PlasticTexture::Dimple, ctx.cap(rng.uni(5.0, 20.0), 0.12), rng.uni(0.2, 0.8)),
            _ => (PlasticTexture::Ribbed, ctx.cap(rng.uni(3.0, 15.0), 0.1), rng.uni(0.2, 0.8)),
        };
        let radius = rng.uni(0.25, 0.45);
        let amp = match texture {
            // smoothstep over `radius` has a peak slope of 1.5 amp / radius.
            PlasticTexture::Dimple => slope * radius / 1.5 / freq * if rng.chance(0.5) { 1.0 } else { -1.0 },
            // Ribs: smoothstep over 0.4 of the period, twice per period.
            PlasticTexture::Ribbed => slope * 0.2 / 1.5 / freq,
            _ => slope / freq,
        };
        Self {
            seed: ctx.seed(10),
            kd,
            ks: f0(rng, 0.04, 0.05),
            rough: rng.uni(0.04, 0.55),
            rough_var: rng.uni(0.0, 0.1),
            texture,
            freq,
            oct: ctx.oct(freq, 3),
            amp,
            radius,
            tone: rng.uni(0.0, 0.04),
        }
    }
}

impl Pattern for Plastic {
    fn texel(&self, p: V2) -> Texel {
        let q = [p[0] * self.freq, p[1] * self.freq];
        let (h, var) = match self.texture {
            PlasticTexture::Smooth => (self.amp * fbm(q, self.seed, self.oct, 0.5), 0.0),
            PlasticTexture::Stipple => {
                let n = fbm(q, self.seed, self.oct.min(2), 0.5);
                (self.amp * n, n)
            }
            PlasticTexture::Dimple => {
                let c = worley(q, self.seed, 0.8);
                let w = smoothstep(self.radius, 0.0, c.f1);
                (-self.amp * w, w)
            }
            PlasticTexture::Ribbed => {
                let t = (2.0 * fract(q[0]) - 1.0).abs();
                let w = smoothstep(0.3, 0.7, t);
                (self.amp * w, w - 0.5)
            }
        };
        let v = vnoise([p[0] * 2.0, p[1] * 2.0], self.seed ^ 0x1) - 0.5;
        Texel {
            kd: mul(self.kd, 1.0 + self.tone * v),
            ks: self.ks,
            rough: self.rough * (1.0 + self.rough_var * (var + v)),
            h,
        }
    }
}
