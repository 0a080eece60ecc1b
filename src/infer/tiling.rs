//! Seamless tiling of a neural map (`--tile`): the map made periodic in
//! code space without inventing codes.
//!
//! Method (per axis, x then y). A copy rolled by half the width has
//! opposite edges that were interior neighbours (so it wraps), but the
//! map's own left and right edges now meet in its middle. That middle is
//! replaced by the unrolled map, which is continuous there; the two are
//! joined along two minimum-error seams found by dynamic programming: one
//! left and one right of the middle, each a path that moves at most one
//! pixel per row, minimising the summed squared code difference across the
//! join (`|O(y, x) - A(y, x - 1)|^2` where the rolled copy A gives way to
//! the map O, and the mirror image on the right). Then the same along y on
//! the result, with seams that wrap around in x themselves (the path's two
//! ends at most a row apart), so the x periodicity survives.
//!
//! Every output pixel is a code of the input (copied, never blended), so
//! M_render only sees codes M_est produced. The seams are as good as the
//! material allows: a stochastic texture finds a path where the two copies
//! agree; a strongly structured one (a single large feature) cannot hide it.

use anyhow::{ensure, Result};
use tch::{Kind, Tensor};

/// Smallest side `--tile` accepts (the seams need room on both sides).
pub const MIN_SIDE: usize = 16;

/// A planar `[C, H, W]` map on the CPU.
#[derive(Clone)]
struct Codes {
    c: usize,
    h: usize,
    w: usize,
    data: Vec<f32>,
}

impl Codes {
    fn at(&self, k: usize, y: usize, x: usize) -> f32 {
        self.data[(k * self.h + y) * self.w + x]
    }

    /// Squared code distance between (ya, xa) of self and (yb, xb) of `other`.
    fn dist(&self, ya: usize, xa: usize, other: &Codes, yb: usize, xb: usize) -> f64 {
        (0..self.c).map(|k| (self.at(k, ya, xa) - other.at(k, yb, xb)) as f64).map(|d| d * d).sum()
    }

    fn transposed(&self) -> Codes {
        let mut data = vec![0f32; self.data.len()];
        for k in 0..self.c {
            for y in 0..self.h {
                for x in 0..self.w {
                    data[(k * self.w + x) * self.h + y] = self.at(k, y, x);
                }
            }
        }
        Codes { c: self.c, h: self.w, w: self.h, data }
    }

    /// Rolled by `s` columns: out(y, x) = self(y, (x + s) % w).
    fn rolled(&self, s: usize) -> Codes {
        let mut out = self.clone();
        for k in 0..self.c {
            for y in 0..self.h {
                for x in 0..self.w {
                    out.data[(k * self.h + y) * self.w + x] = self.at(k, y, (x + s) % self.w);
                }
            }
        }
        out
    }
}

/// The join of two sources, one per row: `L` left of the join's column p,
/// `R` from p on; returns p per row, in `lo..=hi`, moving at most one
/// column per row, minimising the summed squared code steps the join
/// creates: across it in its row, |R(y, p) - L(y, p - 1)|^2, and down at
/// the pixel a move uncovers (p -> p + 1: |L(y, p) - R(y - 1, p)|^2;
/// p -> p - 1: |R(y, p - 1) - L(y - 1, p - 1)|^2). `cyclic`: the last row
/// joins the first too (the path's ends at most a column apart; every
/// first column is tried).
fn seam(l: &Codes, r: &Codes, lo: usize, hi: usize, cyclic: bool) -> Vec<usize> {
    let (steps, n) = (l.h, hi - lo + 1);
    let across: Vec<f64> = (0..steps).flat_map(|y| (lo..=hi).map(move |p| (y, p))).map(|(y, p)| r.dist(y, p, l, y, p - 1)).collect();
    // Step from column index j (row y - 1, wrapping) to i (row y).
    let down = |y: usize, j: usize, i: usize| -> f64 {
        let (py, p) = ((y + steps - 1) % steps, j + lo);
        match i as isize - j as isize {
            1 => l.dist(y, p, r, py, p),
            -1 => r.dist(y, p - 1, l, py, p - 1),
            _ => 0.0,
        }
    };
    let run = |start: Option<usize>| -> (f64, Vec<usize>) {
        let mut acc: Vec<f64> = (0..n).map(|i| if start.is_none_or(|s| s == i) { across[i] } else { f64::INFINITY }).collect();
        let mut from = vec![0u32; steps * n];
        for y in 1..steps {
            let prev = acc.clone();
            for i in 0..n {
                let (mut best, mut arg) = (prev[i], i);
                for j in [i.wrapping_sub(1), i + 1] {
                    if j < n && prev[j] + down(y, j, i) < best {
                        (best, arg) = (prev[j] + down(y, j, i), j);
                    }
                }
                acc[i] = best + across[y * n + i];
                from[y * n + i] = arg as u32;
            }
        }
        // A cyclic path pays for its join from the last row back to the first.
        let total = |i: usize| acc[i] + start.map_or(0.0, |s| down(0, i, s));
        let ends = (0..n).filter(|&i| start.is_none_or(|s| s.abs_diff(i) <= 1));
        let end = ends.min_by(|&a, &b| total(a).total_cmp(&total(b))).expect("a non-empty band");
        let mut path = vec![end; steps];
        for y in (1..steps).rev() {
            path[y - 1] = from[y * n + path[y]] as usize;
        }
        (total(end), path.into_iter().map(|i| i + lo).collect())
    };
    if cyclic {
        (0..n).map(|s| run(Some(s))).min_by(|a, b| a.0.total_cmp(&b.0)).expect("a non-empty band").1
    } else {
        run(None).1
    }
}

/// Makes `o` periodic along x (module docs); `cyclic`: the seams wrap
/// around in y (needed on the second pass only).
fn tile_columns(o: &Codes, cyclic: bool) -> Codes {
    let (h, w) = (o.h, o.w);
    let s = w / 2;
    let a = o.rolled(s);
    // A's own discontinuity lies between columns m - 1 and m: O must cover both.
    let m = w - s;
    let margin = (w / 8).max(1);
    // A left of the left join, O between the joins, A right of the right one.
    let left = seam(&a, o, margin, m - 1, cyclic);
    let right = seam(o, &a, m + 1, w - margin, cyclic);
    let mut out = a;
    for y in 0..h {
        for x in left[y]..right[y] {
            for k in 0..o.c {
                out.data[(k * h + y) * w + x] = o.at(k, y, x);
            }
        }
    }
    out
}

/// The map `[C, H, W]` made seamlessly tileable, `[C, H, W]` on the same
/// device; every output code is one of the input's. Errors when a side is
/// under [`MIN_SIDE`] pixels.
pub fn make_tileable(map: &Tensor) -> Result<Tensor> {
    let size = map.size();
    ensure!(size.len() == 3, "a neural map must be [C, H, W], got {size:?}");
    let (c, h, w) = (size[0] as usize, size[1] as usize, size[2] as usize);
    ensure!(h >= MIN_SIDE && w >= MIN_SIDE, "--tile needs a map of at least {MIN_SIDE}x{MIN_SIDE} pixels, got {w}x{h}");
    let data: Vec<f32> = Vec::try_from(map.to_device(tch::Device::Cpu).to_kind(Kind::Float).contiguous().flatten(0, -1))?;
    let o = Codes { c, h, w, data };
    // x first (plain seams), then y on the transpose with seams that wrap in x.
    let x_periodic = tile_columns(&o, false);
    let both = tile_columns(&x_periodic.transposed(), true).transposed();
    Ok(Tensor::from_slice(&both.data).view([c as i64, h as i64, w as i64]).to_kind(map.kind()).to_device(map.device()))
}

/// Mean squared code step between horizontal neighbours at the wrap
/// (column W-1 beside column 0) and inside (every other pair), of a map
/// `[C, H, W]`; the same for vertical neighbours. Returns
/// (wrap x, interior x, wrap y, interior y).
pub fn wrap_steps(map: &Tensor) -> (f64, f64, f64, f64) {
    let m = map.to_kind(Kind::Double);
    let step = |a: Tensor, b: Tensor| (a - b).square().sum_dim_intlist([0i64].as_slice(), false, Kind::Double).mean(Kind::Double).double_value(&[]);
    let (h, w) = (m.size()[1], m.size()[2]);
    (
        step(m.narrow(2, w - 1, 1), m.narrow(2, 0, 1)),
        step(m.narrow(2, 1, w - 1), m.narrow(2, 0, w - 1)),
        step(m.narrow(1, h - 1, 1), m.narrow(1, 0, 1)),
        step(m.narrow(1, 1, h - 1), m.narrow(1, 0, h - 1)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    /// A smooth stationary random field `[C, H, W]` whose opposite edges do
    /// not match: random waves of non-integer periods in two latent
    /// channels mixed into C (neural maps are low-dimensional: a few PCA
    /// components carry them).
    fn field(c: i64, h: i64, w: i64, seed: i64) -> Tensor {
        tch::manual_seed(seed);
        let opts = (Kind::Float, tch::Device::Cpu);
        let y = Tensor::arange(h, opts).view([1, h, 1]) / h as f64;
        let x = Tensor::arange(w, opts).view([1, 1, w]) / w as f64;
        let mut f = Tensor::zeros([2, h, w], opts);
        for _ in 0..4 {
            let p = Tensor::rand([4, 2, 1, 1], opts);
            f += ((&x * (p.get(0) * 12.0) + &y * (p.get(1) * 12.0) + p.get(2) * 6.3).sin()) * p.get(3);
        }
        Tensor::einsum("ck,khw->chw", &[Tensor::randn([c, 2], opts), f], None::<i64>)
    }

    #[test]
    fn tiled_edges_are_neighbours_like_the_interior_and_codes_are_the_inputs() {
        for (seed, (h, w)) in [(1, (48, 48)), (2, (32, 56)), (3, (45, 33))] {
            let map = field(8, h, w, seed);
            let tiled = make_tileable(&map).unwrap();
            assert_eq!(tiled.size(), map.size());
            let (wx0, ix0, wy0, iy0) = wrap_steps(&map);
            let (wx, ix, wy, iy) = wrap_steps(&tiled);
            eprintln!("{h}x{w}: wrap/interior step before x {:.2} y {:.2}, after x {:.2} y {:.2}", wx0 / ix0, wy0 / iy0, wx / ix, wy / iy);
            assert!(wx0 > 5.0 * ix0 && wy0 > 5.0 * iy0, "the test map must not tile already");
            // The wrap is as smooth as the interior (within its spread: 2x the mean step).
            assert!(wx < 2.0 * ix && wy < 2.0 * iy, "{wx} {ix} {wy} {iy}");
            // The seams cost something inside (a field with no repeats offers no
            // perfect join), far less than joining codes at random would: the
            // mean squared distance of two random pixels is twice the variance.
            let random_pair = 2.0 * map.var_dim([1i64, 2].as_slice(), false, false).sum(Kind::Double).double_value(&[]);
            eprintln!("  interior step x {ix0:.4} -> {ix:.4}, y {iy0:.4} -> {iy:.4}; random pair {random_pair:.3}");
            assert!(ix < 0.1 * random_pair && iy < 0.1 * random_pair, "{ix} {iy} {random_pair}");
            // Every output code is an input code (bit for bit).
            let codes = |t: &Tensor| -> Vec<Vec<u32>> {
                let v: Vec<f32> = Vec::try_from(t.permute([1, 2, 0]).contiguous().flatten(0, -1)).unwrap();
                v.chunks(8).map(|c| c.iter().map(|f| f.to_bits()).collect()).collect()
            };
            let input: HashSet<Vec<u32>> = codes(&map).into_iter().collect();
            assert!(codes(&tiled).iter().all(|c| input.contains(c)));
        }
        assert!(make_tileable(&Tensor::zeros([4, 8, 32], (Kind::Float, tch::Device::Cpu))).unwrap_err().to_string().contains("at least 16x16"));
    }
}
