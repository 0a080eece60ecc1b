//! Inference with BatchNorm folded into the convolutions.
//!
//! Folded (all eval-mode BNs of the network):
//! - conv -> BN pairs: the 1x1 skip convs + BN of the encoder/decoder residual
//!   blocks, and in every up-block tconv4x4 -> bn1, conv3x3 -> bn2 and
//!   tconv2x2 -> skip BN. Weights are scaled per output channel, the shift
//!   becomes a conv bias.
//! - HA layer -> BN (bn1, bn2 of every residual block): the HA output is
//!   gate * feat + incep, so BN's y = s (gate * feat + incep) + t splits into
//!   incep' = s incep + t, folded into the two final inception convs (weights
//!   and bias, per output half), and s * feat, folded into the feat conv's
//!   weights when every s > 0 (LeakyReLU is positively homogeneous); a
//!   channel-wise multiply remains only for BNs with a non-positive scale.
//! Also, the convs reading the same padded input (gate, incep.a, incep.c at
//! stride 1; gate and incep.c at stride 2) run as one wider convolution.

use super::*;

impl MEst {
    /// Inference-only copy with every BatchNorm folded away (eval-mode
    /// statistics) and convs sharing an input merged. See [`FoldedMEst`].
    pub fn fold_batchnorm(&self) -> FoldedMEst {
        tch::no_grad(|| FoldedMEst {
            stem: self.stem.detach().copy(),
            enc: self.enc.iter().map(|s| s.iter().map(FoldedRes::new).collect()).collect(),
            dec: self
                .dec
                .iter()
                .map(|s| FoldedDec { up: s.up.as_ref().map(FoldedUp::new), blocks: s.blocks.iter().map(FoldedRes::new).collect() })
                .collect(),
            head: self.head.detach().copy(),
            channels_last: false,
        })
    }
}

/// BatchNorm-free M_est for inference; equal to `MEst::forward_t(x, false)`
/// up to float rounding.
#[derive(Debug)]
pub struct FoldedMEst {
    stem: Tensor,
    enc: Vec<Vec<FoldedRes>>,
    dec: Vec<FoldedDec>,
    head: Tensor,
    channels_last: bool,
}

#[derive(Debug)]
struct FoldedHa {
    /// gate (+ incep_a at stride 1) + incep_c', merged on output channels.
    merged: Tensor,
    merged_bias: Tensor,
    /// incep_a on its own at stride 2 (it runs at stride 1).
    incep_a: Option<Tensor>,
    incep_b: Tensor,
    incep_b_bias: Tensor,
    feat: Tensor,
    /// `[1, P, 1, 1]` when the BN scale could not go into `feat`.
    feat_scale: Option<Tensor>,
    stride: i64,
    out: i64,
}

impl FoldedHa {
    /// Folds `ha` followed by eval-mode `bn`.
    fn new(ha: &HaLayer, bn: &Bn) -> Self {
        let (s, t) = bn.eval_affine();
        let p = ha.gate.size()[0];
        let half = p / 2;
        let sb = s.narrow(0, 0, half);
        let sc = s.narrow(0, half, half);
        let w4 = |v: &Tensor| v.view([-1, 1, 1, 1]);
        let incep_b = ha.incep_b.detach() * w4(&sb);
        let incep_c = ha.incep_c.detach() * w4(&sc);
        let (feat, feat_scale) = if bool::try_from(s.gt(0.0).all()).unwrap_or(false) {
            (ha.feat.detach() * w4(&s), None)
        } else {
            (ha.feat.detach().copy(), Some(per_channel(&s)))
        };
        let zeros = |n: i64| Tensor::zeros([n], (s.kind(), s.device()));
        let (merged, merged_bias, incep_a) = if ha.stride == 1 {
            (
                Tensor::cat(&[ha.gate.detach(), ha.incep_a.detach(), incep_c], 0),
                Tensor::cat(&[zeros(2 * p), t.narrow(0, half, half)], 0),
                None,
            )
        } else {
            (
                Tensor::cat(&[ha.gate.detach(), incep_c], 0),
                Tensor::cat(&[zeros(p), t.narrow(0, half, half)], 0),
                Some(ha.incep_a.detach().copy()),
            )
        };
        Self {
            merged,
            merged_bias,
            incep_a,
            incep_b,
            incep_b_bias: t.narrow(0, 0, half).copy(),
            feat,
            feat_scale,
            stride: ha.stride,
            out: p,
        }
    }

    /// x: `[N, C, H, W]` -> `[N, P, H/s, W/s]` = bn(ha(x)); the instance
    /// norm takes its statistics as `norm` says.
    fn forward(&self, x: &Tensor, norm: &mut NormStats) -> Tensor {
        let (p, half, s) = (self.out, self.out / 2, self.stride);
        let xp = pad_rep(x, 1);
        let m = conv(&xp, &self.merged, Some(&self.merged_bias), s);
        let gate = m.narrow(1, 0, p).sigmoid();
        let (a, c) = match &self.incep_a {
            None => (m.narrow(1, p, p), m.narrow(1, 2 * p, half)),
            Some(wa) => (conv(&xp, wa, None, 1), m.narrow(1, p, half)),
        };
        let b = conv_rep(&a, &self.incep_b, Some(&self.incep_b_bias), s);
        let mut feat = leaky(&conv_rep(&norm.normalize(x), &self.feat, None, s), HA_FEAT_SLOPE);
        if let Some(sc) = &self.feat_scale {
            feat *= sc;
        }
        gate * feat + Tensor::cat(&[b, c], 1)
    }
}

/// A conv (or transposed conv) with BN folded in: weight and bias.
#[derive(Debug)]
struct FoldedConv {
    w: Tensor,
    b: Tensor,
}

impl FoldedConv {
    /// conv weight `[P, C, k, k]` followed by `bn`.
    fn conv(w: &Tensor, bn: &Bn) -> Self {
        let (s, t) = bn.eval_affine();
        Self { w: w.detach() * s.view([-1, 1, 1, 1]), b: t }
    }

    /// transposed-conv weight `[C, P, k, k]` followed by `bn`.
    fn tconv(w: &Tensor, bn: &Bn) -> Self {
        let (s, t) = bn.eval_affine();
        Self { w: w.detach() * s.view([1, -1, 1, 1]), b: t }
    }
}

#[derive(Debug)]
struct FoldedRes {
    ha1: FoldedHa,
    ha2: FoldedHa,
    skip: Option<FoldedConv>,
    stride: i64,
}

impl FoldedRes {
    fn new(r: &ResBlock) -> Self {
        Self {
            ha1: FoldedHa::new(&r.ha1, &r.bn1),
            ha2: FoldedHa::new(&r.ha2, &r.bn2),
            skip: r.skip.as_ref().map(|s| FoldedConv::conv(&s.conv, &s.bn)),
            stride: r.stride,
        }
    }

    fn forward(&self, x: &Tensor, norm: &mut NormStats) -> Tensor {
        let h1 = self.ha1.forward(x, norm).relu();
        let out = self.ha2.forward(&h1, norm);
        let id = match &self.skip {
            Some(s) => conv(x, &s.w, Some(&s.b), self.stride),
            None => x.shallow_clone(),
        };
        (out + id).relu()
    }
}

#[derive(Debug)]
struct FoldedUp {
    tconv: FoldedConv,
    conv: FoldedConv,
    skip: FoldedConv,
}

impl FoldedUp {
    fn new(u: &UpBlock) -> Self {
        Self {
            tconv: FoldedConv::tconv(&u.tconv, &u.bn1),
            conv: FoldedConv::conv(&u.conv, &u.bn2),
            skip: FoldedConv::tconv(&u.skip_tconv, &u.skip_bn),
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let out = conv_t(x, &self.tconv.w, Some(&self.tconv.b), 2, 1).relu();
        let out = conv_rep(&out, &self.conv.w, Some(&self.conv.b), 1);
        let id = conv_t(x, &self.skip.w, Some(&self.skip.b), 2, 0);
        (out + id).relu()
    }
}

#[derive(Debug)]
struct FoldedDec {
    up: Option<FoldedUp>,
    blocks: Vec<FoldedRes>,
}

impl FoldedMEst {
    /// x: `[N, 4, H, W]`, H and W multiples of 8 -> `[N, neural_channels, H, W]`.
    /// Runs without autograd.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_with(x, &mut NormStats::default())
    }

    /// [`FoldedMEst::forward`] with the instance norms' statistics taken
    /// (and recorded) as `norm` says. x: `[N, 4, H, W]`.
    pub fn forward_with(&self, x: &Tensor, norm: &mut NormStats) -> Result<Tensor> {
        check_est_input(x)?;
        norm.start(x);
        Ok(tch::no_grad(|| {
            let x = if self.channels_last { to_channels_last(x) } else { x.shallow_clone() };
            let mut h = conv_rep(&x, &self.stem, None, 1);
            let mut skips = Vec::with_capacity(4);
            for stage in &self.enc {
                for b in stage {
                    h = b.forward(&h, norm);
                }
                skips.push(h.shallow_clone());
            }
            h = h.arctan();
            for (i, st) in self.dec.iter().enumerate() {
                if i > 0 {
                    h = Tensor::cat(&[&h, &skips[3 - i]], 1);
                }
                if let Some(u) = &st.up {
                    h = u.forward(&h);
                }
                for b in &st.blocks {
                    h = b.forward(&h, norm);
                }
            }
            conv_rep(&h, &self.head, None, 1).contiguous()
        }))
    }

    /// Converts every weight to `kind` (e.g. Double for checks).
    pub fn to_kind(&mut self, kind: Kind) {
        self.map_weights(|t| t.to_kind(kind));
    }

    /// Stores 4-D weights, and runs activations, in channels-last (NHWC)
    /// memory order. Off by default: on the 2-core development CPU it
    /// changed the paper-size 256x256 forward by under 5% (6.3-6.6 s vs 6.6 s).
    pub fn set_channels_last(&mut self, on: bool) {
        self.channels_last = on;
        self.map_weights(|t| if t.dim() == 4 { if on { to_channels_last(t) } else { t.contiguous() } } else { t.shallow_clone() });
    }

    fn map_weights(&mut self, f: impl Fn(&Tensor) -> Tensor) {
        let g = |t: &mut Tensor| *t = f(t);
        g(&mut self.stem);
        g(&mut self.head);
        let res = |r: &mut FoldedRes| {
            for ha in [&mut r.ha1, &mut r.ha2] {
                for t in [&mut ha.merged, &mut ha.merged_bias, &mut ha.incep_b, &mut ha.incep_b_bias, &mut ha.feat] {
                    g(t);
                }
                ha.incep_a.iter_mut().chain(ha.feat_scale.iter_mut()).for_each(g);
            }
            if let Some(s) = r.skip.as_mut() {
                g(&mut s.w);
                g(&mut s.b);
            }
        };
        self.enc.iter_mut().flatten().for_each(res);
        for d in &mut self.dec {
            d.blocks.iter_mut().for_each(res);
            if let Some(u) = d.up.as_mut() {
                for c in [&mut u.tconv, &mut u.conv, &mut u.skip] {
                    g(&mut c.w);
                    g(&mut c.b);
                }
            }
        }
    }
}

/// Where the instance norms of the HA layers take their statistics. M_est's
/// BatchNorms are folded (running statistics, no batch dependence), but
/// every HA layer normalises its input over the whole image (InstanceNorm):
/// a tile normalised by its own statistics would differ from the whole
/// image and show seams. Tiled inference therefore records each layer's
/// statistics over the tiles' cores (the pixels each tile owns), combines
/// them into whole-image statistics and runs the tiles again with those
/// ([`FoldedMEst::forward_tiled`]).
#[derive(Debug, Default)]
pub struct NormStats {
    /// Normalise with `fixed` instead of the input's own statistics.
    use_fixed: bool,
    /// Accumulate each layer's sums over `core` into `sums`.
    record: bool,
    /// Per HA layer (in forward order): mean and biased variance `[1, C, 1, 1]`.
    fixed: Vec<(Tensor, Tensor)>,
    /// Per HA layer: per-channel sum and sum of squares `[C]` (f64), count.
    sums: Vec<(Tensor, Tensor, f64)>,
    /// The region whose pixels are recorded (top, left, height, width) in
    /// input pixels; multiples of 8 so every layer's resolution divides it.
    core: (i64, i64, i64, i64),
    input_hw: (i64, i64),
    layer: usize,
}

impl NormStats {
    /// Record statistics over `core` (top, left, height, width; input
    /// pixels) while normalising with the input's own (`fixed` None) or with
    /// the given whole-image statistics.
    pub fn recording(core: (i64, i64, i64, i64), fixed: Option<&NormStats>) -> Self {
        let (use_fixed, fixed) = match fixed {
            Some(f) => (true, f.fixed.iter().map(|(m, v)| (m.shallow_clone(), v.shallow_clone())).collect()),
            None => (false, vec![]),
        };
        Self { use_fixed, record: true, fixed, core, ..Default::default() }
    }

    /// Continue recording into `self` over another core (next tile).
    pub fn next_core(&mut self, core: (i64, i64, i64, i64)) {
        self.core = core;
    }

    /// The recorded sums as whole-image statistics to normalise with.
    pub fn finish(&self) -> NormStats {
        let fixed = self
            .sums
            .iter()
            .map(|(s, q, n)| {
                let mean = s / *n;
                let var = (q / *n - mean.square()).clamp_min(0.0);
                let c = mean.size()[0];
                (mean.to_kind(Kind::Float).view([1, c, 1, 1]), var.to_kind(Kind::Float).view([1, c, 1, 1]))
            })
            .collect();
        NormStats { use_fixed: true, fixed, ..Default::default() }
    }

    /// Number of normalised layers seen (recorded or fixed).
    pub fn layers(&self) -> usize {
        self.fixed.len().max(self.sums.len())
    }

    fn start(&mut self, x: &Tensor) {
        let s = x.size();
        self.input_hw = (s[2], s[3]);
        self.layer = 0;
    }

    /// x: `[N, C, h, w]` (one HA layer's input) -> normalised per channel.
    fn normalize(&mut self, x: &Tensor) -> Tensor {
        let i = self.layer;
        self.layer += 1;
        if self.record {
            let s = x.size();
            let (fy, fx) = (self.input_hw.0 / s[2], self.input_hw.1 / s[3]);
            let (t, l, h, w) = self.core;
            let core = x.narrow(2, t / fy, h / fy).narrow(3, l / fx, w / fx).to_kind(Kind::Double);
            let dims = [0i64, 2, 3];
            let sum = core.sum_dim_intlist(dims.as_slice(), false, Kind::Double);
            let sq = core.square().sum_dim_intlist(dims.as_slice(), false, Kind::Double);
            let n = (s[0] * (h / fy) * (w / fx)) as f64;
            match self.sums.get_mut(i) {
                Some(acc) => {
                    acc.0 += sum;
                    acc.1 += sq;
                    acc.2 += n;
                }
                None => self.sums.push((sum, sq, n)),
            }
        }
        if self.use_fixed {
            let (m, v) = &self.fixed[i];
            (x - m) * (v + 1e-5).rsqrt()
        } else {
            instance_norm(x)
        }
    }
}

/// One tile along an axis: the core it owns and the tile that computes it
/// (the core plus a margin on each side, within the image); input pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileSpan {
    pub core_start: i64,
    pub core_len: i64,
    pub start: i64,
    pub len: i64,
}

/// Splits `len` pixels into cores of `core` pixels (the last may be
/// shorter) with tiles reaching `margin` further each way. All multiples
/// of 8 when `len`, `core` and `margin` are.
pub fn tile_spans(len: i64, core: i64, margin: i64) -> Vec<TileSpan> {
    let mut out = vec![];
    let mut c = 0;
    while c < len {
        let core_len = core.min(len - c);
        let start = (c - margin).max(0);
        let end = (c + core_len + margin).min(len);
        out.push(TileSpan { core_start: c, core_len, start, len: end - start });
        c += core_len;
    }
    out
}

/// Blending weights `[len]` of a tile along one axis: 1 inside, and across
/// each side shared with a neighbour (not an image border) a linear ramp
/// from 0 at `margin / 2` from the tile's edge to 1 at `3 margin / 2`, so
/// the outermost half-margin (nearest the tile's replicate padding) is
/// never used and two neighbours' weights sum to 1 across their overlap.
pub fn blend_weights(span: &TileSpan, image_len: i64, margin: i64) -> Vec<f32> {
    let m = margin.max(1) as f64;
    let ramp = |d: f64| ((d - m / 2.0) / m).clamp(0.0, 1.0);
    (0..span.len)
        .map(|p| {
            let mut w = 1.0f64;
            if span.start > 0 {
                w = w.min(ramp(p as f64 + 0.5));
            }
            if span.start + span.len < image_len {
                w = w.min(ramp((span.len - p) as f64 - 0.5));
            }
            w as f32
        })
        .collect()
}

/// How [`FoldedMEst::forward_tiled`] splits an image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TilePlan {
    /// Core side (pixels each tile owns), a multiple of 8.
    pub core: i64,
    /// Extra pixels each tile computes on each side, a multiple of 8.
    pub margin: i64,
    /// Passes over the tiles that gather the instance norms' whole-image
    /// statistics before the final pass (1: layers normalised by the
    /// tile's own statistics while recording; 2: once more with the first
    /// pass's statistics, closer to the whole-image forward).
    pub stat_passes: usize,
}

impl FoldedMEst {
    /// M_est over overlapping tiles: the same result as [`FoldedMEst::forward`]
    /// up to the tiles' limited context, with memory for one tile plus the
    /// output. Instance-norm statistics are gathered over the whole image
    /// first ([`NormStats`]); outputs are blended with [`blend_weights`].
    /// x: `[1, 4, H, W]` (H, W multiples of 8) -> `[1, neural_channels, H, W]`.
    pub fn forward_tiled(&self, x: &Tensor, plan: &TilePlan, mut on_tile: impl FnMut()) -> Result<Tensor> {
        let (h, w) = check_est_input(x)?;
        ensure!(x.size()[0] == 1, "tiled M_est takes one image, got a batch of {}", x.size()[0]);
        ensure!(plan.core >= 8 && plan.core % 8 == 0 && plan.margin >= 0 && plan.margin % 8 == 0, "tile core and margin must be multiples of 8, got {plan:?}");
        let (ys, xs) = (tile_spans(h, plan.core, plan.margin), tile_spans(w, plan.core, plan.margin));
        let tile = |ty: &TileSpan, tx: &TileSpan| x.narrow(2, ty.start, ty.len).narrow(3, tx.start, tx.len);
        let mut stats: Option<NormStats> = None;
        for _ in 0..plan.stat_passes.max(1) {
            let mut rec = NormStats::recording((0, 0, 0, 0), stats.as_ref());
            for ty in &ys {
                for tx in &xs {
                    rec.next_core((ty.core_start - ty.start, tx.core_start - tx.start, ty.core_len, tx.core_len));
                    let _ = self.forward_with(&tile(ty, tx), &mut rec)?;
                    on_tile();
                }
            }
            stats = Some(rec.finish());
        }
        let mut fixed = stats.expect("at least one pass");
        let mut out: Option<Tensor> = None;
        let wsum = Tensor::zeros([1, 1, h, w], (Kind::Float, x.device()));
        for ty in &ys {
            for tx in &xs {
                let y = self.forward_with(&tile(ty, tx), &mut fixed)?.to_kind(Kind::Float);
                on_tile();
                let wy = Tensor::from_slice(&blend_weights(ty, h, plan.margin)).to_device(x.device()).view([1, 1, ty.len, 1]);
                let wx = Tensor::from_slice(&blend_weights(tx, w, plan.margin)).to_device(x.device()).view([1, 1, 1, tx.len]);
                let wt = wy * wx; // [1, 1, th, tw]
                let acc = out.get_or_insert_with(|| Tensor::zeros([1, y.size()[1], h, w], (Kind::Float, x.device())));
                let _ = acc.narrow(2, ty.start, ty.len).narrow(3, tx.start, tx.len).g_add_(&(&y * &wt));
                let _ = wsum.narrow(2, ty.start, ty.len).narrow(3, tx.start, tx.len).g_add_(&wt);
            }
        }
        Ok(out.expect("at least one tile") / wsum)
    }
}

#[cfg(test)]
mod tiled_tests {
    use super::*;
    use crate::model::{Model, ModelConfig};
    use tch::Device;

    #[test]
    fn spans_and_weights_partition_the_image() {
        let s = tile_spans(40, 16, 8);
        assert_eq!(
            s,
            vec![
                TileSpan { core_start: 0, core_len: 16, start: 0, len: 24 },
                TileSpan { core_start: 16, core_len: 16, start: 8, len: 32 },
                TileSpan { core_start: 32, core_len: 8, start: 24, len: 16 },
            ]
        );
        // Weights of neighbours sum to 1 everywhere when every core is at least a
        // margin long (48 = 3 x 16); margin 8: ramps over 4..12 from an inner edge.
        // (A shorter last core overlaps more: the blend divides by the sum anyway.)
        let sums = |len: i64| {
            let mut sum = vec![0f32; len as usize];
            for sp in &tile_spans(len, 16, 8) {
                for (p, w) in blend_weights(sp, len, 8).iter().enumerate() {
                    sum[sp.start as usize + p] += w;
                }
            }
            sum
        };
        assert!(sums(48).iter().all(|v| (v - 1.0).abs() < 1e-6), "{:?}", sums(48));
        assert!(sums(40).iter().all(|v| (1.0..=2.0).contains(v)), "{:?}", sums(40));
        let w = blend_weights(&s[1], 40, 8);
        assert_eq!((w[0], w[3], w[31]), (0.0, 0.0, 0.0));
        assert!((w[8] - 0.5).abs() < 1e-6 && w[12] == 1.0 && (w[4] - 0.0625).abs() < 1e-6);
    }

    /// Statistics recorded over the whole image reproduce the plain forward;
    /// tiles that each cover the whole image (margin >= side) are exact.
    #[test]
    fn whole_image_statistics_reproduce_the_forward() {
        tch::manual_seed(2);
        let model = Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap();
        let est = model.est.fold_batchnorm();
        let x = Tensor::rand([1, 4, 32, 48], (Kind::Float, Device::Cpu));
        let plain = est.forward(&x).unwrap();
        let mut rec = NormStats::recording((0, 0, 32, 48), None);
        let _ = est.forward_with(&x, &mut rec).unwrap();
        let mut fixed = rec.finish();
        assert!(fixed.layers() > 10);
        let again = est.forward_with(&x, &mut fixed).unwrap();
        let scale = 1.0 + plain.abs().max().double_value(&[]);
        assert!((&again - &plain).abs().max().double_value(&[]) < 1e-4 * scale);
        let tiled = est.forward_tiled(&x, &TilePlan { core: 16, margin: 48, stat_passes: 1 }, || ()).unwrap();
        assert!((&tiled - &plain).abs().max().double_value(&[]) < 1e-4 * scale);
    }
}
