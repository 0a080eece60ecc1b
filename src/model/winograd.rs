//! 3x3 stride-1 convolutions by Winograd's minimal filtering F(4x4, 3x3)
//! (Lavin and Gray, *Fast Algorithms for Convolutional Neural Networks*,
//! 2016): every 4x4 output tile comes from a 6x6 input tile with 36
//! multiplications per (input, output) channel pair instead of direct
//! convolution's 144, so the channel-mixing work, 36 GEMMs of
//! `[P, C] x [C, tiles]`, is 4x smaller. The tile transforms are additions
//! with small constants, written here over whole rows so they vectorise; the
//! GEMMs stay libtorch's. Inference only: f32 on the CPU, no autograd.
//!
//! The image is walked in bands of tile rows (at most 32 MiB of transformed
//! tiles and GEMM output), which bounds the working memory. Inside the
//! paper-size forward, 4 MiB bands (sized for the 32 MiB L3) ran the GEMMs
//! at about 62 GFLOP/s, 16-256 MiB bands at about 90-110, although a layer
//! timed alone favours the small bands. Small bands give each GEMM fewer
//! tiles, and each band hands the two cores from rayon (transforms) to
//! OpenMP (GEMMs) and back; which of the two costs more was not separated.
//! The price of large bands: the tile transforms run from memory, not the
//! cache (about 7 GB/s; `reports/inference-speed.md`, sections 3 and 4).

use rayon::prelude::*;
use tch::{Device, Kind, Tensor};

/// Kernel transform G (6x3) for the interpolation points 0, 1, -1, 2, -2
/// and infinity; B^T and A^T are written out in `bt_rows` and `at_rows`.
const G: [[f64; 3]; 6] = [
    [1.0 / 4.0, 0.0, 0.0],
    [-1.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0],
    [-1.0 / 6.0, 1.0 / 6.0, -1.0 / 6.0],
    [1.0 / 24.0, 1.0 / 12.0, 1.0 / 6.0],
    [1.0 / 24.0, -1.0 / 12.0, 1.0 / 6.0],
    [0.0, 0.0, 1.0],
];

/// Bytes of transformed input and GEMM output held per band of tile rows:
/// large GEMMs, few hand-overs between thread pools, bounded memory (see
/// the module doc).
const BAND_BYTES: i64 = 32 << 20;

/// A 3x3 stride-1 convolution (weights and optional bias) run by F(4x4, 3x3).
#[derive(Debug)]
pub struct Winograd3x3 {
    /// G w G^T, `[36, P, C]` (transform position, output, input channel).
    u: Tensor,
    bias: Option<Vec<f32>>,
    cin: i64,
    cout: i64,
}

/// A pointer shared by the threads of one transform; every thread writes
/// its own channel's elements only.
#[derive(Clone, Copy)]
struct SharedOut(*mut f32);
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// The pointer `offset` floats further (a method, so closures capture
    /// the whole Send + Sync wrapper rather than its raw field).
    fn at(self, offset: usize) -> *mut f32 {
        self.0.wrapping_add(offset)
    }
}

/// A CPU f32 tensor's elements. t must be contiguous and stay alive (and
/// unwritten by anyone else) while the slice is used.
pub(super) fn as_slice(t: &Tensor) -> &[f32] {
    assert!(t.is_contiguous() && t.kind() == Kind::Float && t.device() == Device::Cpu);
    let len = t.numel();
    if len == 0 {
        return &[];
    }
    // SAFETY: a contiguous f32 CPU tensor owns `len` initialised floats at
    // data_ptr, alive as long as `t` is borrowed.
    unsafe { std::slice::from_raw_parts(t.data_ptr() as *const f32, len) }
}

/// [`as_slice`] to write: t must be contiguous, f32 on the CPU and held by
/// no one else while the slice is used (a tensor just made, for one).
pub(super) fn as_mut_slice(t: &mut Tensor) -> &mut [f32] {
    assert!(t.is_contiguous() && t.kind() == Kind::Float && t.device() == Device::Cpu);
    let len = t.numel();
    if len == 0 {
        return &mut [];
    }
    // SAFETY: as in `as_slice`; the exclusive borrow of `t` and the caller's
    // promise keep every other reader and writer away.
    unsafe { std::slice::from_raw_parts_mut(t.data_ptr() as *mut f32, len) }
}

impl Winograd3x3 {
    /// w: `[P, C, 3, 3]`, bias: `[P]` (any float kind, any device; the
    /// transformed kernel is kept as f32 on the CPU).
    pub fn new(w: &Tensor, bias: Option<&Tensor>) -> Self {
        let (cout, cin) = (w.size()[0], w.size()[1]);
        assert_eq!(&w.size()[2..], &[3, 3], "Winograd F(4x4, 3x3) needs a 3x3 kernel");
        // vec(G w G^T) = (G kron G) vec(w): one [P C, 9] x [9, 36] GEMM.
        let g = Tensor::from_slice(&G.concat()).view([6, 3]);
        let gg = g.unsqueeze(1).unsqueeze(3) * g.unsqueeze(0).unsqueeze(2); // [6, 6, 3, 3]: G[a, i] G[b, j]
        let w32 = w.detach().to_device(Device::Cpu).to_kind(Kind::Float).reshape([cout * cin, 9]);
        let u = w32.matmul(&gg.to_kind(Kind::Float).reshape([36, 9]).tr()).tr().reshape([36, cout, cin]);
        let bias = bias.map(|b| Vec::<f32>::try_from(b.detach().to_device(Device::Cpu).to_kind(Kind::Float).contiguous()).expect("f32 bias"));
        Self { u: u.contiguous(), bias, cin, cout }
    }

    /// xp: `[N, C, H + 2, W + 2]` (the input already padded by one pixel),
    /// f32 on the CPU, any H and W -> `[N, P, H, W]`, equal to
    /// `xp.conv2d(w, bias, 1, 0)` up to float rounding.
    pub fn forward(&self, xp: &Tensor) -> Tensor {
        let [n, c, hp, wp] = xp.size()[..] else { panic!("Winograd input must be [N, C, H, W], got {:?}", xp.size()) };
        assert_eq!(c, self.cin, "Winograd input has {c} channels, the kernel {}", self.cin);
        let (h, w, p) = (hp - 2, wp - 2, self.cout);
        let xp = xp.to_kind(Kind::Float).contiguous();
        let out = Tensor::empty([n, p, h, w], (Kind::Float, Device::Cpu));
        if h <= 0 || w <= 0 || n == 0 {
            return out;
        }
        let (tiles_y, tiles_x) = ((h + 3) / 4, (w + 3) / 4);
        let band_rows = (BAND_BYTES / (36 * 4 * (c + p) * tiles_x)).clamp(1, tiles_y);
        let band_tiles = band_rows * tiles_x;
        let v_buf = Tensor::empty([36 * c * band_tiles], (Kind::Float, Device::Cpu));
        let m_buf = Tensor::empty([36 * p * band_tiles], (Kind::Float, Device::Cpu));
        let x = as_slice(&xp);
        let out_ptr = SharedOut(out.data_ptr() as *mut f32);
        let v_ptr = SharedOut(v_buf.data_ptr() as *mut f32);
        let plane_in = (hp * wp) as usize;
        let plane_out = (h * w) as usize;
        for img in 0..n as usize {
            let mut ty0 = 0;
            while ty0 < tiles_y {
                let rows = band_rows.min(tiles_y - ty0);
                let tiles = (rows * tiles_x) as usize;
                let geom = Band { ty0: ty0 as usize, rows: rows as usize, tiles_x: tiles_x as usize, tiles };
                (0..c as usize).into_par_iter().for_each(|ci| {
                    let plane = &x[(img * c as usize + ci) * plane_in..][..plane_in];
                    // SAFETY: channel ci writes V[k, ci, 0..tiles] only, for each k,
                    // inside v_buf (36 * c * band_tiles >= 36 * c * tiles floats).
                    unsafe { input_tiles(plane, hp as usize, wp as usize, &geom, v_ptr, ci, c as usize) };
                });
                let v = v_buf.narrow(0, 0, 36 * c * tiles as i64).view([36, c, tiles as i64]);
                let m = m_buf.narrow(0, 0, 36 * p * tiles as i64).view([36, p, tiles as i64]);
                let _ = self.u.bmm_out(&m, &v);
                let mv = as_slice(&m);
                let biases = self.bias.as_deref();
                (0..p as usize).into_par_iter().for_each(|pi| {
                    let bias = biases.map_or(0.0, |b| b[pi]);
                    // SAFETY: output channel pi writes its own plane of `out` only.
                    unsafe {
                        output_tiles(mv, &geom, pi, p as usize, bias, out_ptr.at((img * p as usize + pi) * plane_out), h as usize, w as usize)
                    };
                });
                ty0 += rows;
            }
        }
        out
    }
}

/// A 4x4 transposed convolution with stride 2 and padding 1 (M_est's
/// upsampling) by Winograd. Output pixel 2m + a (per axis) takes input
/// m - 1 and m through kernel taps 3 and 1 when a = 0, inputs m and m + 1
/// through taps 2 and 0 when a = 1; so the four output phases (a, b) are
/// one stride-1 3x3 conv of the zero-padded input with 4P outputs, each
/// phase's 3x3 kernel holding four of the 16 taps. By F(4x4, 3x3) that is
/// 9 multiplications per input pixel and channel pair against the
/// transposed conv's 16.
#[derive(Debug)]
pub struct WinogradUp4x4 {
    phases: Winograd3x3,
    cout: i64,
}

/// Per axis and output phase: (3x3 tap, 4x4 kernel tap) pairs.
const UP_TAPS: [[(i64, i64); 2]; 2] = [[(0, 3), (1, 1)], [(1, 2), (2, 0)]];

impl WinogradUp4x4 {
    /// w: `[C, P, 4, 4]` (conv_transpose2d's layout), bias: `[P]`.
    pub fn new(w: &Tensor, bias: Option<&Tensor>) -> Self {
        let (cin, cout) = (w.size()[0], w.size()[1]);
        assert_eq!(&w.size()[2..], &[4, 4], "the upsampling's kernel is 4x4");
        let wt = w.detach().to_device(Device::Cpu).to_kind(Kind::Float).transpose(0, 1); // [P, C, 4, 4]
        let mut phases = vec![];
        for ya in UP_TAPS {
            for xa in UP_TAPS {
                let k = Tensor::zeros([cout, cin, 3, 3], (Kind::Float, Device::Cpu));
                for (ty, ky) in ya {
                    for (tx, kx) in xa {
                        k.narrow(2, ty, 1).narrow(3, tx, 1).copy_(&wt.narrow(2, ky, 1).narrow(3, kx, 1));
                    }
                }
                phases.push(k);
            }
        }
        let bias = bias.map(|b| b.detach().to_device(Device::Cpu).to_kind(Kind::Float).repeat([4]));
        Self { phases: Winograd3x3::new(&Tensor::cat(&phases, 0), bias.as_ref()), cout }
    }

    /// x: `[N, C, H, W]` f32 on the CPU -> `[N, P, 2H, 2W]`, equal to
    /// `x.conv_transpose2d(w, bias, stride 2, padding 1)` up to float rounding.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let [n, _, h, w] = x.size()[..] else { panic!("upsampling input must be [N, C, H, W], got {:?}", x.size()) };
        let y = self.phases.forward(&x.constant_pad_nd([1, 1, 1, 1])); // [N, (a, b, P), H, W]
        // [N, a, b, P, H, W] -> [N, P, H, a, W, b]: pixel (2m + a, 2n + b).
        y.view([n, 2, 2, self.cout, h, w]).permute([0, 3, 4, 1, 5, 2]).reshape([n, self.cout, 2 * h, 2 * w])
    }
}

/// A band of tile rows: first row, row count, tiles per row, tiles in all.
struct Band {
    ty0: usize,
    rows: usize,
    tiles_x: usize,
    tiles: usize,
}

/// B^T applied along one axis, element-wise over rows of tiles:
/// out[s][t] = sum_j BT[s][j] d[j][t] (the constants written out so the
/// loop vectorises and skips the zeros).
#[inline(always)]
fn bt_rows(d: [&[f32]; 6], out: [&mut [f32]; 6]) {
    let n = out[0].len();
    // Equal lengths up front, so the loop runs without bounds checks.
    let [d0, d1, d2, d3, d4, d5] = d.map(|row| &row[..n]);
    let [o0, o1, o2, o3, o4, o5] = out.map(|row| &mut row[..n]);
    for t in 0..n {
        let (d0, d1, d2, d3, d4, d5) = (d0[t], d1[t], d2[t], d3[t], d4[t], d5[t]);
        o0[t] = 4.0 * d0 - 5.0 * d2 + d4;
        o1[t] = -4.0 * (d1 + d2) + d3 + d4;
        o2[t] = 4.0 * (d1 - d2) - d3 + d4;
        o3[t] = 2.0 * (d3 - d1) - d2 + d4;
        o4[t] = 2.0 * (d1 - d3) - d2 + d4;
        o5[t] = 4.0 * d1 - 5.0 * d3 + d5;
    }
}

/// A^T along one axis: out[i][t] = sum_r AT[i][r] m[r][t] (+ bias).
#[inline(always)]
fn at_rows(m: [&[f32]; 6], out: [&mut [f32]; 4], bias: f32) {
    let n = out[0].len();
    let [m0, m1, m2, m3, m4, m5] = m.map(|row| &row[..n]);
    let [o0, o1, o2, o3] = out.map(|row| &mut row[..n]);
    for t in 0..n {
        let (m0, m1, m2, m3, m4, m5) = (m0[t], m1[t], m2[t], m3[t], m4[t], m5[t]);
        let (sum12, dif12, sum34, dif34) = (m1 + m2, m1 - m2, m3 + m4, m3 - m4);
        o0[t] = bias + m0 + sum12 + sum34;
        o1[t] = bias + dif12 + 2.0 * dif34;
        o2[t] = bias + sum12 + 4.0 * sum34;
        o3[t] = bias + dif12 + 8.0 * dif34 + m5;
    }
}

/// A buffer cut into its 4 equal quarters (the 4 phases x mod 4 of a row).
fn split4(buf: &mut [f32]) -> [&mut [f32]; 4] {
    let len = buf.len() / 4;
    let mut it = buf.chunks_exact_mut(len);
    std::array::from_fn(|_| it.next().expect("four quarters"))
}

/// Six disjoint mutable rows of `len` floats from a buffer of rows.
fn rows6(buf: &mut [f32], len: usize) -> [&mut [f32]; 6] {
    let mut it = buf.chunks_exact_mut(len);
    std::array::from_fn(|_| it.next().expect("six rows"))
}

avx2_dispatch!(
/// B^T d B for every 6x6 tile of one channel's padded plane in the band,
/// written to V[k, ci, tile] (k = 6 r + s; V is `[36, c, band.tiles]`).
/// Pixels outside the plane read as 0 (they only feed outputs past H, W).
/// Each input row is first split into its 4 phases (x mod 4), so both
/// transform passes run over contiguous rows of tiles.
///
/// # Safety
/// `v` must hold 36 * c * band.tiles floats and no other thread may write
/// channel ci's elements.
unsafe fn input_tiles / input_tiles_avx2(plane: &[f32], hp: usize, wp: usize, band: &Band, v: SharedOut, ci: usize, c: usize) => input_tiles_body);

/// The body of [`input_tiles`], inlined into each build of it.
#[inline(always)]
unsafe fn input_tiles_body(plane: &[f32], hp: usize, wp: usize, band: &Band, v: SharedOut, ci: usize, c: usize) {
    let n = band.tiles_x;
    let len = n + 1; // phase q holds row[4 t + q] for t in 0..=n
    // phases[i][q]: input row i of the tile row, phase q.
    let mut phases = vec![0.0f32; 6 * 4 * len];
    // mixed[r][q]: after B^T along y.
    let mut mixed = vec![0.0f32; 6 * 4 * len];
    for ty in 0..band.rows {
        let y0 = 4 * (band.ty0 + ty);
        phases.fill(0.0);
        for i in 0..6 {
            if y0 + i >= hp {
                continue;
            }
            let src = &plane[(y0 + i) * wp..][..wp];
            let [p0, p1, p2, p3] = split4(&mut phases[i * 4 * len..][..4 * len]);
            let quads = src.chunks_exact(4);
            let rest = quads.remainder();
            let whole = src.len() / 4;
            for (t, q) in quads.enumerate() {
                (p0[t], p1[t], p2[t], p3[t]) = (q[0], q[1], q[2], q[3]);
            }
            for (k, &val) in rest.iter().enumerate() {
                [&mut *p0, &mut *p1, &mut *p2, &mut *p3][k][whole] = val;
            }
        }
        for q in 0..4 {
            let d: [&[f32]; 6] = std::array::from_fn(|i| &phases[(i * 4 + q) * len..][..len]);
            let mut outs: Vec<&mut [f32]> = mixed.chunks_exact_mut(len).skip(q).step_by(4).collect();
            let out: [&mut [f32]; 6] = std::array::from_fn(|r| std::mem::take(&mut outs[r]));
            bt_rows(d, out);
        }
        for r in 0..6 {
            let row = &mixed[r * 4 * len..][..4 * len];
            let d: [&[f32]; 6] = std::array::from_fn(|j| &row[(j % 4) * len + j / 4..][..n]);
            let base = ty * n;
            // SAFETY: V[6r + s, ci, base..base + n] for s in 0..6 are disjoint
            // rows inside v, written by this channel only.
            let out: [&mut [f32]; 6] = std::array::from_fn(|s| unsafe { std::slice::from_raw_parts_mut(v.at(((6 * r + s) * c + ci) * band.tiles + base), n) });
            bt_rows(d, out);
        }
    }
}

avx2_dispatch!(
/// A^T m A (+ bias) for every tile of output channel pi in the band, from
/// M: `[36, p, band.tiles]`, into that channel's `[h, w]` plane at `plane`.
///
/// # Safety
/// `plane` must point at h * w floats that no other thread writes.
unsafe fn output_tiles / output_tiles_avx2(m: &[f32], band: &Band, pi: usize, p: usize, bias: f32, plane: *mut f32, h: usize, w: usize) => output_tiles_body);

/// The body of [`output_tiles`], inlined into each build of it.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn output_tiles_body(m: &[f32], band: &Band, pi: usize, p: usize, bias: f32, plane: *mut f32, h: usize, w: usize) {
    let n = band.tiles_x;
    // mixed[i][s]: after A^T along y; cols[j]: output phase j of one row.
    let mut mixed = vec![0.0f32; 4 * 6 * n];
    let mut cols = vec![0.0f32; 4 * n];
    for ty in 0..band.rows {
        for s in 0..6 {
            let src: [&[f32]; 6] = std::array::from_fn(|r| &m[((6 * r + s) * p + pi) * band.tiles + ty * n..][..n]);
            let mut outs: Vec<&mut [f32]> = mixed.chunks_exact_mut(n).skip(s).step_by(6).collect();
            let out: [&mut [f32]; 4] = std::array::from_fn(|i| std::mem::take(&mut outs[i]));
            at_rows(src, out, 0.0);
        }
        for i in 0..4 {
            let y = 4 * (band.ty0 + ty) + i;
            if y >= h {
                break;
            }
            let rows = rows6(&mut mixed[i * 6 * n..][..6 * n], n);
            let src: [&[f32]; 6] = rows.map(|r| &*r);
            let mut it = cols.chunks_exact_mut(n);
            let out: [&mut [f32]; 4] = std::array::from_fn(|_| it.next().expect("four phases"));
            at_rows(src, out, bias);
            // SAFETY: row y of this channel's plane, w floats, this thread's own.
            let dst = unsafe { std::slice::from_raw_parts_mut(plane.add(y * w), w) };
            let [c0, c1, c2, c3] = split4(&mut cols);
            let whole = w / 4;
            for (t, q) in dst.chunks_exact_mut(4).enumerate() {
                q.copy_from_slice(&[c0[t], c1[t], c2[t], c3[t]]);
            }
            for (k, o) in dst[4 * whole..].iter_mut().enumerate() {
                *o = [&*c0, &*c1, &*c2, &*c3][k][whole];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The matrices bt_rows and at_rows implement (Lavin and Gray's F(4x4, 3x3)).
    const BT: [[f32; 6]; 6] = [
        [4.0, 0.0, -5.0, 0.0, 1.0, 0.0],
        [0.0, -4.0, -4.0, 1.0, 1.0, 0.0],
        [0.0, 4.0, -4.0, -1.0, 1.0, 0.0],
        [0.0, -2.0, -1.0, 2.0, 1.0, 0.0],
        [0.0, 2.0, -1.0, -2.0, 1.0, 0.0],
        [0.0, 4.0, 0.0, -5.0, 0.0, 1.0],
    ];
    const AT: [[f32; 6]; 4] = [
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
        [0.0, 1.0, -1.0, 2.0, -2.0, 0.0],
        [0.0, 1.0, 1.0, 4.0, 4.0, 0.0],
        [0.0, 1.0, -1.0, 8.0, -8.0, 1.0],
    ];

    #[test]
    fn row_kernels_are_the_transform_matrices() {
        // Column e_j of each matrix: feed the unit vector j through the kernel.
        for j in 0..6 {
            let unit: [Vec<f32>; 6] = std::array::from_fn(|i| vec![if i == j { 1.0 } else { 0.0 }]);
            let mut bt = [[0.0f32]; 6];
            bt_rows(std::array::from_fn(|i| &unit[i][..]), bt.each_mut().map(|r| &mut r[..]));
            let mut at = [[0.0f32]; 4];
            at_rows(std::array::from_fn(|i| &unit[i][..]), at.each_mut().map(|r| &mut r[..]), 0.0);
            for r in 0..6 {
                assert_eq!(bt[r][0], BT[r][j], "B^T[{r}][{j}]");
            }
            for r in 0..4 {
                assert_eq!(at[r][0], AT[r][j], "A^T[{r}][{j}]");
            }
        }
    }

    #[test]
    fn one_dimensional_identity_holds() {
        // F(4, 3): A^T [(G g) * (B^T d)] is the valid correlation of d (6)
        // with g (3), exactly for small integers (the 1-D identity the 2-D
        // nesting relies on).
        let d = [1.0f64, -2.0, 3.0, 0.5, 4.0, -1.0];
        let g = [2.0f64, -1.0, 3.0];
        let gg: Vec<f64> = G.iter().map(|row| row.iter().zip(&g).map(|(a, b)| a * b).sum()).collect();
        let bd: Vec<f64> = BT.iter().map(|row| row.iter().zip(&d).map(|(a, b)| *a as f64 * b).sum()).collect();
        let prod: Vec<f64> = gg.iter().zip(&bd).map(|(a, b)| a * b).collect();
        for (i, row) in AT.iter().enumerate() {
            let y: f64 = row.iter().zip(&prod).map(|(a, b)| *a as f64 * b).sum();
            let want = d[i] * g[0] + d[i + 1] * g[1] + d[i + 2] * g[2];
            assert!((y - want).abs() < 1e-12, "output {i}: {y} vs {want}");
        }
    }

    fn direct(xp: &Tensor, w: &Tensor, b: Option<&Tensor>) -> Tensor {
        xp.conv2d(w, b, [1, 1], [0, 0], [1, 1], 1)
    }

    #[test]
    fn matches_direct_convolution_at_any_size() {
        tch::manual_seed(3);
        // Sizes that are and are not multiples of the 4x4 tile, one channel
        // to many, with and without bias, and N = 2.
        for (n, c, p, h, w) in [(1, 1, 1, 4, 4), (2, 3, 5, 9, 7), (1, 16, 8, 13, 21), (1, 8, 24, 1, 6)] {
            let xp = Tensor::randn([n, c, h + 2, w + 2], (Kind::Float, Device::Cpu));
            let wt = Tensor::randn([p, c, 3, 3], (Kind::Float, Device::Cpu)) / (3.0 * (c as f64).sqrt());
            let b = Tensor::randn([p], (Kind::Float, Device::Cpu));
            for bias in [None, Some(&b)] {
                let y = Winograd3x3::new(&wt, bias).forward(&xp);
                // The reference in f64, so the bound measures the F(4x4, 3x3)
                // rounding alone: about 1e-6 of the output scale in f32.
                let r = direct(&xp.to_kind(Kind::Double), &wt.to_kind(Kind::Double), bias.map(|b| b.to_kind(Kind::Double)).as_ref());
                assert_eq!(y.size(), r.size());
                let scale = r.abs().max().double_value(&[]);
                let err = (y.to_kind(Kind::Double) - &r).abs().max().double_value(&[]);
                assert!(err <= 2e-5 * scale, "{n}x{c}->{p} at {h}x{w}: error {err} of {scale}");
            }
        }
    }

    #[test]
    fn upsampling_phases_equal_the_transposed_convolution() {
        tch::manual_seed(6);
        for (n, c, p, h, w) in [(1, 3, 2, 5, 7), (2, 8, 5, 4, 4), (1, 1, 1, 1, 2)] {
            let x = Tensor::randn([n, c, h, w], (Kind::Float, Device::Cpu));
            let wt = Tensor::randn([c, p, 4, 4], (Kind::Float, Device::Cpu));
            let b = Tensor::randn([p], (Kind::Float, Device::Cpu));
            let y = WinogradUp4x4::new(&wt, Some(&b)).forward(&x);
            let want = x.to_kind(Kind::Double).conv_transpose2d(&wt.to_kind(Kind::Double), Some(&b.to_kind(Kind::Double)), [2, 2], [1, 1], [0, 0], 1, [1, 1]);
            assert_eq!(y.size(), want.size());
            let scale = want.abs().max().double_value(&[]);
            let err = (y.to_kind(Kind::Double) - &want).abs().max().double_value(&[]);
            assert!(err <= 2e-5 * scale, "{n}x{c}->{p} at {h}x{w}: error {err} of {scale}");
        }
    }

    #[test]
    fn constant_input_gives_the_hand_sum() {
        // x = 0.5 everywhere, w = 0.25 everywhere, bias 1: every output pixel
        // sums 9 C products 0.125 -> 1 + 9 * 3 * 0.125 = 4.375, exactly.
        let xp = Tensor::full([1, 3, 10, 10], 0.5, (Kind::Float, Device::Cpu));
        let w = Tensor::full([2, 3, 3, 3], 0.25, (Kind::Float, Device::Cpu));
        let b = Tensor::ones([2], (Kind::Float, Device::Cpu));
        let y = Winograd3x3::new(&w, Some(&b)).forward(&xp);
        assert_eq!(y.size(), [1, 2, 8, 8]);
        let err = (y - 4.375).abs().max().double_value(&[]);
        assert!(err < 1e-5, "constant input off by {err}");
    }

    #[test]
    fn a_single_tap_kernel_shifts_the_image() {
        // w = 1 at (0, 2) only: y[i, j] = xp[i, j + 2], an exact shift.
        let xp = Tensor::arange(64, (Kind::Float, Device::Cpu)).view([1, 1, 8, 8]);
        let w = Tensor::zeros([1, 1, 3, 3], (Kind::Float, Device::Cpu));
        let _ = w.narrow(2, 0, 1).narrow(3, 2, 1).fill_(1.0);
        let y = Winograd3x3::new(&w, None).forward(&xp);
        let want = xp.narrow(2, 0, 6).narrow(3, 2, 6);
        let err = (y - want).abs().max().double_value(&[]);
        assert!(err < 1e-4, "shift off by {err}");
    }
}
