//! Fabric: warp threads along y, weft along x, one thread per pattern unit;
//! weave decides which is on top per cell. Optional stripes/plaid.

use super::*;

#[derive(Clone, Copy)]
enum Weave {
    Plain,
    Twill(i32, i32),
    Basket,
    Satin,
}

impl Weave {
    #[inline(always)]
    fn warp_up(self, i: i32, j: i32) -> bool {
        match self {
            Weave::Plain => (i + j) & 1 == 0,
            Weave::Twill(n, k) => (i + j).rem_euclid(n) < k,
            Weave::Basket => ((i >> 1) + (j >> 1)) & 1 == 0,
            Weave::Satin => (2 * i + j).rem_euclid(5) != 0,
        }
    }
}

pub(super) struct Fabric {
    seed: u32,
    weave: Weave,
    warp: [Rgb; 4],
    weft: [Rgb; 4],
    warp_stripe: i32,
    weft_stripe: i32,
    ncol: u32,
    tw: f32,
    amp: f32,
    fibre: f32,
    fibre_freq: f32,
    slub: f32,
    rough: f32,
    ks: Rgb,
}

impl Fabric {
    pub(super) fn new(rng: &mut Pcg64, ctx: &Ctx) -> Self {
        let weave = match rng.random_range(0..6) {
            0 | 1 => Weave::Plain,
            2 => Weave::Twill(3, rng.random_range(1..3)),
            3 => Weave::Twill(4, 2),
            4 => Weave::Basket,
            _ => Weave::Satin,
        };
        let denim = rng.chance(0.15);
        let base = if denim {
            hsv_lin(rng.uni(0.58, 0.64), rng.uni(0.5, 0.8), rng.uni(0.25, 0.5))
        } else {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.8), rng.uni(0.15, 0.85))
        };
        let weft0 = if denim {
            hsv_lin(0.1, rng.uni(0.05, 0.15), rng.uni(0.7, 0.85))
        } else if rng.chance(0.6) {
            vary(rng, base, (0.85, 1.1), 0.05)
        } else {
            hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.8), rng.uni(0.15, 0.85))
        };
        let mut warp = [base; 4];
        let mut weft = [weft0; 4];
        let striped = !denim && rng.chance(0.35);
        if striped {
            for k in 1..4 {
                warp[k] = hsv_lin(rng.uni(0.0, 1.0), rng.uni(0.1, 0.8), rng.uni(0.1, 0.9));
                weft[k] = if rng.chance(0.7) { warp[k] } else { weft0 };
            }
        }
        let silky = matches!(weave, Weave::Satin) || rng.chance(0.15);
        Self {
            seed: ctx.seed(8),
            weave,
            warp,
            weft,
            warp_stripe: rng.random_range(2..16),
            weft_stripe: if rng.chance(0.6) { rng.random_range(2..16) } else { i32::MAX },
            ncol: if striped { rng.random_range(2..5) } else { 1 },
            tw: rng.uni(0.7, 0.95),
            amp: rng.uni(0.08, 0.25),
            fibre: rng.uni(0.05, 0.2),
            fibre_freq: ctx.cap(rng.uni(4.0, 10.0), 0.3),
            slub: rng.uni(0.0, 0.1),
            rough: if silky { rng.uni(0.25, 0.45) } else { rng.uni(0.65, 1.0) },
            ks: if silky { f0(rng, 0.04, 0.07) } else { f0(rng, 0.02, 0.04) },
        }
    }
}

impl Pattern for Fabric {
    fn texel(&self, p: V2) -> Texel {
        let i = floor_i(p[0]);
        let j = floor_i(p[1]);
        let fx = p[0] - i as f32;
        let fy = p[1] - j as f32;
        let up = self.weave.warp_up(i, j);
        // Thread cross-sections (warp runs along y, so its profile is in x).
        let half = 0.5 * self.tw;
        let tx = (fx - 0.5) / half;
        let ty = (fy - 0.5) / half;
        let warp_prof = (1.0 - tx * tx).max(0.0);
        let weft_prof = (1.0 - ty * ty).max(0.0);
        // The top thread bows up in the middle of the cell and dives at its ends.
        let bow_warp = 0.75 + 0.25 * (1.0 - (2.0 * fy - 1.0).powi(2));
        let bow_weft = 0.75 + 0.25 * (1.0 - (2.0 * fx - 1.0).powi(2));
        let h_warp = warp_prof * if up { bow_warp } else { 0.45 };
        let h_weft = weft_prof * if up { 0.45 } else { bow_weft };
        let warp_top = h_warp >= h_weft;
        let (col, along, across, th) = if warp_top {
            let k = hash1(i.div_euclid(self.warp_stripe), self.seed) % self.ncol;
            (self.warp[k as usize], p[1], p[0], hash1(i, self.seed ^ 0x1))
        } else {
            let k = if self.weft_stripe == i32::MAX {
                0
            } else {
                hash1(j.div_euclid(self.weft_stripe), self.seed ^ 0x2) % self.ncol
            };
            (self.weft[k as usize], p[0], p[1], hash1(j, self.seed ^ 0x3))
        };
        // Fibres: fine noise across the thread, slow along it, with a twist.
        let fib = gnoise([across * self.fibre_freq + along * 0.8, along * 1.5], self.seed ^ 0x4);
        let hmax = h_warp.max(h_weft);
        // Gaps between threads show the shadowed interior.
        let shade = 0.35 + 0.65 * smoothstep(0.0, 0.35, hmax);
        let kd = mul(col, shade * (1.0 + self.fibre * fib) * (1.0 + self.slub * srnd(th, 1)));
        Texel { kd, ks: self.ks, rough: (self.rough * (1.0 + 0.1 * fib)).min(1.0), h: self.amp * (hmax + 0.05 * fib) }
    }
}
