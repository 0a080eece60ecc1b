//! Hand-written, allocation-free noise for the procedural generator: integer
//! hashing, gradient and value noise, fbm and cellular (Worley) noise.
//!
//! Everything is a pure function of the coordinates and a `u32` seed, so
//! results never depend on threads or call order. Coordinates are "pattern
//! units"; callers keep them within a few thousand so f32 keeps sub-cell
//! precision.

/// A 2-D point or vector in pattern units.
pub type V2 = [f32; 2];

/// Integer avalanche mix (a "lowbias32"-style xor-shift-multiply chain).
#[inline(always)]
pub fn mix32(mut h: u32) -> u32 {
    h ^= h >> 16;
    h = h.wrapping_mul(0x7feb_352d);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846c_a68b);
    h ^= h >> 16;
    h
}

/// Hash of an integer lattice point under a seed.
#[inline(always)]
pub fn hash2(x: i32, y: i32, seed: u32) -> u32 {
    cell_hash(x, row_hash(y, seed))
}

/// Row part of [`hash2`]: loops over a 3x3 neighbourhood compute it once
/// per row.
#[inline(always)]
pub fn row_hash(y: i32, seed: u32) -> u32 {
    mix32((y as u32).wrapping_add(seed.wrapping_mul(0x9e37_79b9)))
}

/// Column part of [`hash2`]: `cell_hash(x, row_hash(y, s)) == hash2(x, y, s)`.
#[inline(always)]
pub fn cell_hash(x: i32, row: u32) -> u32 {
    mix32((x as u32) ^ row)
}

/// Hash of one integer under a seed.
#[inline(always)]
pub fn hash1(x: i32, seed: u32) -> u32 {
    mix32((x as u32).wrapping_add(mix32(seed ^ 0x5bd1_e995)))
}

/// A hash mapped to [0, 1).
#[inline(always)]
pub fn unit(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// Derives an independent sub-seed (so two noises of one material differ).
#[inline(always)]
pub fn sub_seed(seed: u32, k: u32) -> u32 {
    mix32(seed ^ k.wrapping_mul(0x68e3_1da4).wrapping_add(0x1b87_3593))
}

/// floor() without the libm call that baseline x86-64 would emit.
#[inline(always)]
pub fn floor_i(x: f32) -> i32 {
    let t = x as i32;
    t - ((x < t as f32) as i32)
}

/// Fractional part in [0, 1).
#[inline(always)]
pub fn fract(x: f32) -> f32 {
    x - floor_i(x) as f32
}

#[inline(always)]
pub fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a + (b - a) * t
}

#[inline(always)]
pub fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Quintic fade: C2 continuous, so normals from noise heights have no creases.
#[inline(always)]
fn fade(t: f32) -> f32 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// 16 unit gradients, evenly spread and offset from the axes so the
/// lattice does not show as axis-aligned ridges.
const GRAD: [V2; 16] = {
    let mut g = [[0.0f32; 2]; 16];
    // cos/sin of (k * 22.5 + 11.25) degrees.
    let c = [
        0.980_785_3,
        0.831_469_6,
        0.555_570_2,
        0.195_090_3,
        -0.195_090_3,
        -0.555_570_2,
        -0.831_469_6,
        -0.980_785_3,
        -0.980_785_3,
        -0.831_469_6,
        -0.555_570_2,
        -0.195_090_3,
        0.195_090_3,
        0.555_570_2,
        0.831_469_6,
        0.980_785_3,
    ];
    let s = [
        0.195_090_3,
        0.555_570_2,
        0.831_469_6,
        0.980_785_3,
        0.980_785_3,
        0.831_469_6,
        0.555_570_2,
        0.195_090_3,
        -0.195_090_3,
        -0.555_570_2,
        -0.831_469_6,
        -0.980_785_3,
        -0.980_785_3,
        -0.831_469_6,
        -0.555_570_2,
        -0.195_090_3,
    ];
    let mut k = 0;
    while k < 16 {
        g[k] = [c[k], s[k]];
        k += 1;
    }
    g
};

/// Gradient (Perlin-style) noise, roughly in [-1, 1], zero at lattice points,
/// standard deviation about 0.3.
#[inline]
pub fn gnoise(p: V2, seed: u32) -> f32 {
    let xi = floor_i(p[0]);
    let yi = floor_i(p[1]);
    let fx = p[0] - xi as f32;
    let fy = p[1] - yi as f32;
    // Shared row hashes: two inner mixes instead of four.
    let s = seed.wrapping_mul(0x9e37_79b9);
    let r0 = mix32((yi as u32).wrapping_add(s));
    let r1 = mix32((yi.wrapping_add(1) as u32).wrapping_add(s));
    let x0 = xi as u32;
    let x1 = xi.wrapping_add(1) as u32;
    let g00 = GRAD[(mix32(x0 ^ r0) & 15) as usize];
    let g10 = GRAD[(mix32(x1 ^ r0) & 15) as usize];
    let g01 = GRAD[(mix32(x0 ^ r1) & 15) as usize];
    let g11 = GRAD[(mix32(x1 ^ r1) & 15) as usize];
    let n00 = g00[0] * fx + g00[1] * fy;
    let n10 = g10[0] * (fx - 1.0) + g10[1] * fy;
    let n01 = g01[0] * fx + g01[1] * (fy - 1.0);
    let n11 = g11[0] * (fx - 1.0) + g11[1] * (fy - 1.0);
    let u = fade(fx);
    let v = fade(fy);
    // Unit gradients bound |n| by sqrt(2)/2; rescale to about [-1, 1].
    lerp(lerp(n00, n10, u), lerp(n01, n11, u), v) * std::f32::consts::SQRT_2
}

/// Value noise in [0, 1] (smoothly interpolated lattice values): cheaper
/// than gradient noise and not zero-mean per cell, good for colour blotches.
#[inline]
pub fn vnoise(p: V2, seed: u32) -> f32 {
    let xi = floor_i(p[0]);
    let yi = floor_i(p[1]);
    let u = fade(p[0] - xi as f32);
    let v = fade(p[1] - yi as f32);
    let s = seed.wrapping_mul(0x9e37_79b9);
    let r0 = mix32((yi as u32).wrapping_add(s));
    let r1 = mix32((yi.wrapping_add(1) as u32).wrapping_add(s));
    let x0 = xi as u32;
    let x1 = xi.wrapping_add(1) as u32;
    let a = unit(mix32(x0 ^ r0));
    let b = unit(mix32(x1 ^ r0));
    let c = unit(mix32(x0 ^ r1));
    let d = unit(mix32(x1 ^ r1));
    lerp(lerp(a, b, u), lerp(c, d, u), v)
}

/// Octave rotation (about 36.87 degrees) with lacunarity 2: decorrelates
/// octaves so the lattice axes do not line up across scales.
#[inline(always)]
fn next_octave(p: V2) -> V2 {
    [2.0 * (0.8 * p[0] - 0.6 * p[1]) + 17.31, 2.0 * (0.6 * p[0] + 0.8 * p[1]) - 5.17]
}

/// Octave count that stops before the pixel Nyquist limit: `freq` is the
/// base frequency (cycles per pattern unit), `pixel` the pixel footprint in
/// pattern units. Saves time and avoids aliasing at small sizes.
pub fn octaves_for(freq: f32, pixel: f32, max: u32) -> u32 {
    let finest = 0.5 / pixel.max(1e-6); // cycles per unit at Nyquist
    let n = (finest / freq.max(1e-6)).max(1.0).log2().floor() as i32 + 1;
    (n.max(1) as u32).min(max.max(1))
}

/// Fractal Brownian motion of gradient noise, normalised by the total
/// amplitude so the range stays about [-1, 1].
#[inline]
pub fn fbm(p: V2, seed: u32, octaves: u32, gain: f32) -> f32 {
    let mut q = p;
    let mut amp = 1.0;
    let mut sum = 0.0;
    let mut norm = 0.0;
    for o in 0..octaves {
        sum += amp * gnoise(q, seed.wrapping_add(o.wrapping_mul(0x2c1b_3c6d)));
        norm += amp;
        amp *= gain;
        q = next_octave(q);
    }
    if norm > 0.0 {
        sum / norm
    } else {
        0.0
    }
}

/// Result of a cellular-noise lookup.
#[derive(Clone, Copy, Debug)]
pub struct Cell {
    /// Distance to the nearest feature point.
    pub f1: f32,
    /// Distance to the second nearest feature point.
    pub f2: f32,
    /// Hash identifying the nearest point's cell (per-cell randomness).
    pub id: u32,
    /// Offset from the nearest feature point to the query point.
    pub delta: V2,
}

/// Worley noise with one jittered feature point per unit cell, searched in
/// the 3x3 neighbourhood. `jitter` in [0, 1] (1 = fully random points).
/// F2 - F1 approximates twice the distance to the Voronoi border.
#[inline]
pub fn worley(p: V2, seed: u32, jitter: f32) -> Cell {
    let xi = floor_i(p[0]);
    let yi = floor_i(p[1]);
    let mut d1 = f32::MAX;
    let mut d2 = f32::MAX;
    let mut id = 0u32;
    let mut delta = [0.0f32; 2];
    for dy in -1..=1 {
        let cy = yi + dy;
        let row = row_hash(cy, seed);
        for dx in -1..=1 {
            let cx = xi + dx;
            let h = cell_hash(cx, row);
            // Disjoint 16-bit halves of one hash: no second mix per cell.
            let jx = 0.5 + jitter * ((h >> 16) as f32 * (1.0 / 65_536.0) - 0.5);
            let jy = 0.5 + jitter * ((h & 0xffff) as f32 * (1.0 / 65_536.0) - 0.5);
            let ox = p[0] - (cx as f32 + jx);
            let oy = p[1] - (cy as f32 + jy);
            let d = ox * ox + oy * oy;
            if d < d1 {
                d2 = d1;
                d1 = d;
                id = h;
                delta = [ox, oy];
            } else if d < d2 {
                d2 = d;
            }
        }
    }
    Cell { f1: d1.sqrt(), f2: d2.sqrt(), id, delta }
}

/// Distance from `p` to the segment a-b.
#[inline(always)]
pub fn segment_distance(p: V2, a: V2, b: V2) -> f32 {
    let (abx, aby) = (b[0] - a[0], b[1] - a[1]);
    let (apx, apy) = (p[0] - a[0], p[1] - a[1]);
    let t = ((apx * abx + apy * aby) / (abx * abx + aby * aby).max(1e-12)).clamp(0.0, 1.0);
    let (dx, dy) = (apx - t * abx, apy - t * aby);
    (dx * dx + dy * dy).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize, scale: f32) -> impl Iterator<Item = V2> {
        (0..n * n).map(move |i| [(i % n) as f32 * scale - 37.3, (i / n) as f32 * scale + 11.9])
    }

    #[test]
    fn floor_matches_std() {
        for x in [-2.5f32, -2.0, -0.1, 0.0, 0.3, 1.0, 7.9, -1e-7] {
            assert_eq!(floor_i(x), x.floor() as i32, "x = {x}");
            assert!((0.0..1.0).contains(&fract(x)));
        }
    }

    #[test]
    fn gradient_noise_range_and_statistics() {
        let v: Vec<f32> = grid(200, 0.173).map(|p| gnoise(p, 7)).collect();
        let mean = v.iter().sum::<f32>() / v.len() as f32;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / v.len() as f32;
        assert!(v.iter().all(|x| x.abs() <= 1.0001));
        assert!(mean.abs() < 0.05, "mean {mean}");
        assert!(var.sqrt() > 0.15 && var.sqrt() < 0.5, "std {}", var.sqrt());
        // Zero at lattice points, deterministic, seed-dependent.
        assert_eq!(gnoise([3.0, -4.0], 1), 0.0);
        assert_eq!(gnoise([0.3, 0.7], 5), gnoise([0.3, 0.7], 5));
        assert_ne!(gnoise([0.3, 0.7], 5), gnoise([0.3, 0.7], 6));
    }

    #[test]
    fn noise_is_continuous() {
        // A step of 1e-3 cells changes the value by at most a few 1e-3.
        for p in grid(50, 0.37) {
            let d = (gnoise(p, 3) - gnoise([p[0] + 1e-3, p[1]], 3)).abs();
            assert!(d < 6e-3, "jump {d} at {p:?}");
            let d = (vnoise(p, 3) - vnoise([p[0], p[1] + 1e-3], 3)).abs();
            assert!(d < 6e-3, "jump {d} at {p:?}");
        }
    }

    #[test]
    fn fbm_and_value_noise_ranges() {
        for p in grid(60, 0.29) {
            let f = fbm(p, 11, 6, 0.5);
            assert!(f.abs() <= 1.0001);
            assert!((0.0..=1.0).contains(&vnoise(p, 2)));
        }
        assert_eq!(octaves_for(1.0, 1.0 / 64.0, 10), 6); // 32 cycles/unit at Nyquist
        assert_eq!(octaves_for(1.0, 1.0, 10), 1);
        assert_eq!(octaves_for(1.0, 1e-9, 7), 7);
    }

    #[test]
    fn worley_distances() {
        for p in grid(40, 0.41) {
            let c = worley(p, 9, 1.0);
            assert!(c.f1 <= c.f2 + 1e-6);
            // With at most unit jitter the nearest point is within sqrt(2).
            assert!(c.f1 <= 1.4143, "f1 {}", c.f1);
            assert!((c.delta[0].hypot(c.delta[1]) - c.f1).abs() < 1e-5);
        }
        // The id is the cell hash (the row-hash hoisting must agree with hash2).
        let c = worley([2.5, 3.5], 4, 0.0);
        assert_eq!(c.id, hash2(2, 3, 4));
        // No jitter: points at cell centres.
        let c = worley([2.5, 3.5], 1, 0.0);
        assert!(c.f1 < 1e-6 && (c.f2 - 1.0).abs() < 1e-6);
    }

    #[test]
    fn segment_distance_cases() {
        assert!((segment_distance([0.0, 1.0], [-1.0, 0.0], [1.0, 0.0]) - 1.0).abs() < 1e-6);
        assert!((segment_distance([3.0, 0.0], [-1.0, 0.0], [1.0, 0.0]) - 2.0).abs() < 1e-6);
        assert!((segment_distance([0.5, 0.5], [0.0, 0.0], [0.0, 0.0]) - 0.5f32.sqrt()).abs() < 1e-6);
    }
}
