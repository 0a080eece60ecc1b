//! Rust and paint: a thresholded fbm (optionally with drips stretched along y)
//! separates paint (raised layer) from rust, with an optional band of bare
//! metal at the peeling edge.

use super::*;

pub(super) struct RustPaint {
    seed: u32,
    paint_kd: Rgb,
    paint_rough: f32,
    paint_ks: Rgb,
    rust_dark: Rgb,
    rust_light: Rgb,
    rust_rough: f32,
    rust_ks: Rgb,
    metal_ks: Rgb,
    metal_kd: Rgb,
    metal_rough: f32,
    t: f32,
    edge: f32,
    soft: f32,
    mask_freq: f32,
    mask_oct: u32,
    drip: f32,
    drip_fx: f32,
    drip_fy: f32,
    thick: f32,
    rust_freq: f32,
    rust_oct: u32,
    rust_amp: f32,
    fine_freq: f32,
}

impl RustPaint {
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let paint_kd = if rng.chance(0.75) {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.3, 0.9), rng.uni(0.2, 0.8))
        } else {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.0, 0.08), rng.uni(0.3, 0.92))
        };
        let metal_ks = vary(rng, [0.56, 0.57, 0.58], (0.9, 1.05), 0.02);
        let mask_freq = rng.uni(1.0, 3.0);
        let rust_freq = ctx.cap(rng.uni(3.0, 10.0), 0.25);
        Self {
            seed: ctx.seed(6),
            paint_kd,
            paint_rough: rng.uni(0.25, 0.7),
            paint_ks: f0(rng, 0.04, 0.05),
            rust_dark: hsv_lin(rng.uni(0.02, 0.06), rng.uni(0.6, 0.85), rng.uni(0.1, 0.22)),
            rust_light: hsv_lin(rng.uni(0.05, 0.09), rng.uni(0.55, 0.85), rng.uni(0.35, 0.6)),
            rust_rough: rng.uni(0.75, 1.0),
            rust_ks: f0(rng, 0.02, 0.04),
            metal_kd: mul(metal_ks, 0.02),
            metal_ks,
            metal_rough: rng.uni(0.3, 0.5),
            t: rng.uni(-0.35, 0.25),
            edge: if rng.chance(0.6) { rng.uni(0.01, 0.06) } else { 0.0 },
            soft: rng.uni(0.005, 0.02),
            mask_freq,
            mask_oct: ctx.oct(mask_freq, 6),
            drip: if rng.chance(0.4) { rng.uni(0.1, 0.4) } else { 0.0 },
            drip_fx: rng.uni(4.0, 10.0),
            drip_fy: rng.uni(0.3, 1.0),
            thick: rng.uni(0.002, 0.008),
            rust_freq,
            rust_oct: ctx.oct(rust_freq, 5),
            rust_amp: rng.uni(0.05, 0.2) / rust_freq,
            fine_freq: ctx.cap(60.0, 0.3),
        }
    }
}

impl Pattern for RustPaint {
    fn texel(&self, p: V2) -> Texel {
        let mut m = fbm([p[0] * self.mask_freq, p[1] * self.mask_freq], self.seed, self.mask_oct, 0.55);
        if self.drip > 0.0 {
            m -= self.drip * gnoise([p[0] * self.drip_fx, p[1] * self.drip_fy], self.seed ^ 0x5).abs();
        }
        let d = m - self.t;
        let w_paint = smoothstep(0.0, self.soft, d);
        let w_metal = if self.edge > 0.0 { smoothstep(-self.edge, -0.3 * self.edge, d) * (1.0 - w_paint) } else { 0.0 };
        let w_rust = 1.0 - w_paint - w_metal;
        let orange_peel = 0.0003 * gnoise([p[0] * 30.0, p[1] * 30.0], self.seed ^ 0x6);
        let mut out = Texel {
            kd: mul(self.paint_kd, w_paint),
            ks: mul(self.paint_ks, w_paint),
            rough: self.paint_rough * w_paint,
            h: (self.thick + orange_peel) * w_paint,
        };
        if w_metal > 0.0 {
            for c in 0..3 {
                out.kd[c] += self.metal_kd[c] * w_metal;
                out.ks[c] += self.metal_ks[c] * w_metal;
            }
            out.rough += self.metal_rough * w_metal;
        }
        if w_rust > 1e-4 {
            let r = fbm([p[0] * self.rust_freq, p[1] * self.rust_freq], self.seed ^ 0x7, self.rust_oct, 0.55);
            let fine = gnoise([p[0] * self.fine_freq, p[1] * self.fine_freq], self.seed ^ 0x8);
            let kd = mul(mix3(self.rust_dark, self.rust_light, smoothstep(-0.4, 0.4, r)), 1.0 + 0.25 * fine);
            for c in 0..3 {
                out.kd[c] += kd[c] * w_rust;
                out.ks[c] += self.rust_ks[c] * w_rust;
            }
            out.rough += self.rust_rough * w_rust;
            out.h += (self.rust_amp * (r + 0.1 * fine) - 0.5 * self.thick) * w_rust;
        }
        out
    }
}
