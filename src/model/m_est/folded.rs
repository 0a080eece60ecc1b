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
use super::kernels;
use crate::model::winograd::{Winograd3x3, WinogradUp4x4};
use tch::Device;

impl MEst {
    /// Inference-only copy with every BatchNorm folded away (eval-mode
    /// statistics) and convs sharing an input merged. See [`FoldedMEst`].
    pub fn fold_batchnorm(&self) -> FoldedMEst {
        let mut folded = tch::no_grad(|| FoldedMEst {
            stem: self.stem.detach().copy(),
            enc: self.enc.iter().map(|s| s.iter().map(FoldedRes::new).collect()).collect(),
            dec: self
                .dec
                .iter()
                .map(|s| FoldedDec { up: s.up.as_ref().map(FoldedUp::new), blocks: s.blocks.iter().map(FoldedRes::new).collect() })
                .collect(),
            head: self.head.detach().copy(),
            codes: self.codes.as_ref().map(|e| e.weights().iter().map(|w| w.detach().copy()).collect()).unwrap_or_default(),
            channels_last: false,
        });
        folded.set_winograd(Some(WinogradPolicy::default()));
        folded
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
    /// The GGX encoder's weights after the head, `[out, in]` each (none
    /// without [`ModelConfig::ggx_codes`]).
    codes: Vec<Tensor>,
    channels_last: bool,
}

/// Which stride-1 3x3 convs of [`FoldedMEst`] run by Winograd F(4x4, 3x3)
/// ([`Winograd3x3`]): those with at least `min_channels` input and output
/// channels, on inputs of at least `min_pixels`; and narrower ones with at
/// least `narrow_min_in` input and `narrow_min_out` output channels, on
/// inputs of at least `narrow_min_input_bytes`. Elsewhere the tile
/// transforms (work in proportion to C + P) cost more than the smaller
/// GEMMs (C P) save. The defaults are where the two broke even inside the
/// forward on the 2-core development CPU (`reports/inference-speed.md`):
/// at 768x768 the compact preset's 16 -> 40, 32 -> 80 and 48 -> 40 convs
/// ran 1.1x, 1.3x and 1.4x faster by Winograd, its 16 -> 16, 32 -> 32 and
/// 48 -> 16 ones 1.2-1.4x slower.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WinogradPolicy {
    pub min_channels: i64,
    pub min_pixels: i64,
    pub narrow_min_in: i64,
    pub narrow_min_out: i64,
    pub narrow_min_input_bytes: i64,
}

impl Default for WinogradPolicy {
    fn default() -> Self {
        Self { min_channels: 64, min_pixels: 32 * 32, narrow_min_in: 16, narrow_min_out: 40, narrow_min_input_bytes: 24 << 20 }
    }
}

impl WinogradPolicy {
    /// Every stride-1 3x3 conv (for tests of the Winograd path).
    pub const ALWAYS: Self = Self { min_channels: 1, min_pixels: 1, narrow_min_in: 1, narrow_min_out: 1, narrow_min_input_bytes: 0 };

    /// The smallest input (pixels) on which a conv of `cin` -> `cout`
    /// channels runs by Winograd; None: never.
    pub fn min_pixels_for(&self, cin: i64, cout: i64) -> Option<i64> {
        if cin.min(cout) >= self.min_channels {
            Some(self.min_pixels)
        } else if cin >= self.narrow_min_in && cout >= self.narrow_min_out {
            // The input's f32 planes fill `narrow_min_input_bytes`.
            Some((self.narrow_min_input_bytes + 4 * cin - 1) / (4 * cin))
        } else {
            None
        }
    }

    /// The Winograd form of w `[P, C, 3, 3]` (+ bias `[P]`) if the policy
    /// takes convs of its width; none for weights off the CPU (the
    /// Winograd path is CPU-only).
    fn make(policy: Option<Self>, w: &Tensor, b: Option<&Tensor>) -> Option<WinoConv> {
        let min_pixels = Self::takes(policy, w, w.size()[1], w.size()[0])?;
        Some(WinoConv { conv: Winograd3x3::new(w, b), min_pixels })
    }

    /// [`Self::min_pixels_for`] a conv of `cin` -> `cout` channels whose
    /// weights w are on the CPU; None without a policy or off the CPU.
    fn takes(policy: Option<Self>, w: &Tensor, cin: i64, cout: i64) -> Option<i64> {
        policy.filter(|_| w.device() == Device::Cpu)?.min_pixels_for(cin, cout)
    }
}

/// A conv's Winograd form and the smallest input it is used on.
#[derive(Debug)]
struct WinoConv {
    conv: Winograd3x3,
    min_pixels: i64,
}

/// The Winograd F(4x4, 3x3) forms of one HA layer's stride-1 3x3 convs.
#[derive(Debug, Default)]
struct HaWinograd {
    merged: Option<WinoConv>,
    incep_a: Option<WinoConv>,
    incep_b: Option<WinoConv>,
    feat: Option<WinoConv>,
}

/// xp (padded) -> conv(xp, w, b, stride), by Winograd when `wino` is set,
/// the stride is 1, the input f32 on the CPU and large enough.
/// xp: `[N, C, H + 2, W + 2]` -> `[N, P, H', W']`.
fn conv3(xp: &Tensor, w: &Tensor, b: Option<&Tensor>, stride: i64, wino: Option<&WinoConv>) -> Tensor {
    let pixels = (xp.size()[2] - 2) * (xp.size()[3] - 2);
    match wino {
        Some(wg) if stride == 1 && winograd_runs_on(xp, pixels, wg.min_pixels) => wg.conv.forward(xp),
        _ => conv(xp, w, b, stride),
    }
}

/// Whether a Winograd form runs on input x of `pixels` (unpadded): f32 on
/// the CPU and at least `min_pixels`.
fn winograd_runs_on(x: &Tensor, pixels: i64, min_pixels: i64) -> bool {
    x.kind() == Kind::Float && x.device() == Device::Cpu && pixels >= min_pixels
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
    /// The same scale as host floats for the fused pass (weights only
    /// change layout after folding, never values).
    feat_scale_host: Option<Vec<f32>>,
    stride: i64,
    out: i64,
    wino: HaWinograd,
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
            feat_scale_host: feat_scale.as_ref().map(|t| Vec::<f32>::try_from(t.to_kind(Kind::Float).flatten(0, -1)).expect("f32 BN scale")),
            feat_scale,
            stride: ha.stride,
            out: p,
            wino: HaWinograd::default(),
        }
    }

    /// Builds (or drops) the Winograd forms of the stride-1 3x3 convs.
    fn set_winograd(&mut self, policy: Option<WinogradPolicy>) {
        let make = |w: &Tensor, b: Option<&Tensor>| WinogradPolicy::make(policy, w, b);
        self.wino = if self.stride == 1 {
            HaWinograd {
                merged: make(&self.merged, Some(&self.merged_bias)),
                incep_a: None,
                incep_b: make(&self.incep_b, Some(&self.incep_b_bias)),
                feat: make(&self.feat, None),
            }
        } else {
            HaWinograd { incep_a: self.incep_a.as_ref().and_then(|w| make(w, None)), ..HaWinograd::default() }
        };
    }

    /// x: `[N, C, H, W]` -> `[N, P, H/s, W/s]` = act(bn(ha(x)) + residual),
    /// act = ReLU when `relu`; the instance norm takes its statistics as
    /// `norm` says. On f32 CPU inputs the instance norm with its padding,
    /// and everything after the convs, run as single passes ([`kernels`]).
    fn forward(&self, x: &Tensor, norm: &mut NormStats, residual: Option<&Tensor>, relu: bool) -> Tensor {
        let (p, half, s) = (self.out, self.out / 2, self.stride);
        let wg = &self.wino;
        // Not for channels-last activations (their last dimension is strided).
        let fused = x.kind() == Kind::Float && x.device() == Device::Cpu && x.stride()[3] == 1;
        let x = if fused { x.contiguous() } else { x.shallow_clone() };
        let xp = pad_rep(&x, 1);
        let m = conv3(&xp, &self.merged, Some(&self.merged_bias), s, wg.merged.as_ref());
        let (a, c_offset) = match &self.incep_a {
            None => (m.narrow(1, p, p), 2 * p),
            Some(wa) => (conv3(&xp, wa, None, 1, wg.incep_a.as_ref()), p),
        };
        let b = conv3(&pad_rep(&a, 1), &self.incep_b, Some(&self.incep_b_bias), s, wg.incep_b.as_ref());
        let feat = conv3(&norm.normalize_padded(&x, fused), &self.feat, None, s, wg.feat.as_ref());
        if fused && [&m, &b, &feat].iter().all(|t| kernels::eligible(t)) {
            let residual = residual.map(Tensor::contiguous);
            let combine = kernels::HaCombine {
                merged: &m,
                c_offset,
                b: &b,
                feat: &feat,
                slope: HA_FEAT_SLOPE as f32,
                feat_scale: self.feat_scale_host.as_deref(),
                residual: residual.as_ref(),
                relu,
            };
            return combine.run();
        }
        let gate = m.narrow(1, 0, p).sigmoid();
        let c = m.narrow(1, c_offset, half);
        let mut feat = leaky(&feat, HA_FEAT_SLOPE);
        if let Some(sc) = &self.feat_scale {
            feat *= sc;
        }
        let mut out = gate * feat + Tensor::cat(&[b, c], 1);
        if let Some(r) = residual {
            out += r;
        }
        if relu {
            out.relu()
        } else {
            out
        }
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
        let h1 = self.ha1.forward(x, norm, None, true);
        let id = match &self.skip {
            Some(s) => conv(x, &s.w, Some(&s.b), self.stride),
            None => x.shallow_clone(),
        };
        self.ha2.forward(&h1, norm, Some(&id), true)
    }
}

#[derive(Debug)]
struct FoldedUp {
    tconv: FoldedConv,
    conv: FoldedConv,
    skip: FoldedConv,
    conv_wino: Option<WinoConv>,
    /// The 4x4 transposed conv by Winograd, and the smallest input (pixels)
    /// it is used on.
    tconv_wino: Option<(WinogradUp4x4, i64)>,
}

impl FoldedUp {
    fn new(u: &UpBlock) -> Self {
        Self {
            tconv: FoldedConv::tconv(&u.tconv, &u.bn1),
            conv: FoldedConv::conv(&u.conv, &u.bn2),
            skip: FoldedConv::tconv(&u.skip_tconv, &u.skip_bn),
            conv_wino: None,
            tconv_wino: None,
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let pixels = x.size()[2] * x.size()[3];
        let out = match &self.tconv_wino {
            Some((up, min_pixels)) if winograd_runs_on(x, pixels, *min_pixels) => up.forward(x),
            _ => conv_t(x, &self.tconv.w, Some(&self.tconv.b), 2, 1),
        }
        .relu();
        let out = conv3(&pad_rep(&out, 1), &self.conv.w, Some(&self.conv.b), 1, self.conv_wino.as_ref());
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

    fn forward_with(&self, x: &Tensor, norm: &mut NormStats) -> Result<Tensor> {
        check_est_input(x)?;
        Ok(tch::no_grad(|| {
            let x = if self.channels_last { to_channels_last(x) } else { x.shallow_clone() };
            let h = self.walk(conv_rep(&x, &self.stem, None, 1), |b, h| b.forward(h, norm), |u, h| u.forward(h));
            self.to_codes(conv_rep(&h, &self.head, None, 1)).contiguous()
        }))
    }

    /// The head's output `[N, 10, H, W]`, brought into range
    /// (`ggx_codes::valid_values`), through the GGX encoder where the model
    /// has one, else unchanged.
    fn to_codes(&self, head_out: Tensor) -> Tensor {
        if self.codes.is_empty() {
            head_out
        } else {
            crate::model::ggx_codes::forward_maps_with(&self.codes, &crate::model::ggx_codes::valid_values(&head_out))
        }
    }

    /// The U-Net between stem and head, one way of running a residual block
    /// and an upsampling for both the whole and the layer-wise forward:
    /// encoder stages (their outputs kept as skips), arctan bottleneck,
    /// decoder stages (skip concatenated before each but the first).
    /// stem_out: `[N, W, H, W]` -> `[N, W, H, W]` (the head's input).
    fn walk(&self, stem_out: Tensor, mut block: impl FnMut(&FoldedRes, &Tensor) -> Tensor, mut up: impl FnMut(&FoldedUp, &Tensor) -> Tensor) -> Tensor {
        let mut h = stem_out;
        let mut skips = Vec::with_capacity(4);
        for stage in &self.enc {
            for b in stage {
                h = block(b, &h);
            }
            skips.push(h.shallow_clone());
        }
        h = h.arctan();
        for (i, st) in self.dec.iter().enumerate() {
            if i > 0 {
                h = Tensor::cat(&[&h, &skips[3 - i]], 1);
            }
            if let Some(u) = &st.up {
                h = up(u, &h);
            }
            for b in &st.blocks {
                h = block(b, &h);
            }
        }
        h
    }

    /// Runs the stride-1 3x3 convs and the 4x4 upsampling transposed convs
    /// (as 3x3 convs of 4P outputs) that `policy` takes by Winograd F(4x4,
    /// 3x3) on f32 CPU inputs ([`Winograd3x3`], [`WinogradUp4x4`]); the
    /// stride-2 convs, 7x7 stem and head, 1x1 skips and 2x2 transposed
    /// convs stay direct. None: every conv direct. The default policy is
    /// on; the transformed kernels are taken from the weights as they are
    /// now.
    pub fn set_winograd(&mut self, policy: Option<WinogradPolicy>) {
        let res = |r: &mut FoldedRes| {
            r.ha1.set_winograd(policy);
            r.ha2.set_winograd(policy);
        };
        self.enc.iter_mut().flatten().for_each(res);
        for d in &mut self.dec {
            d.blocks.iter_mut().for_each(res);
            if let Some(u) = d.up.as_mut() {
                u.conv_wino = WinogradPolicy::make(policy, &u.conv.w, Some(&u.conv.b));
                // As a 3x3 conv of C inputs and 4P outputs (its four phases).
                let (cin, cout) = (u.tconv.w.size()[0], u.tconv.w.size()[1]);
                u.tconv_wino = WinogradPolicy::takes(policy, &u.tconv.w, cin, 4 * cout)
                    .map(|min_pixels| (WinogradUp4x4::new(&u.tconv.w, Some(&u.tconv.b)), min_pixels));
            }
        }
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
        for t in self.codes.iter_mut() {
            g(t);
        }
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

/// Where the instance norms of the HA layers take their statistics: the
/// input's own (the plain forward) or given ones. M_est's BatchNorms are
/// folded (running statistics, no batch dependence), but every HA layer
/// normalises its input over the whole image (InstanceNorm): a tile
/// normalised by its own statistics would differ from the whole image and
/// show seams, so tiled inference ([`FoldedMEst::forward_layerwise`])
/// normalises every tile with the statistics of the whole layer input.
#[derive(Debug, Default)]
pub struct NormStats {
    /// Mean and biased variance `[1, C, 1, 1]` of the next HA layer's
    /// input; None: its own.
    fixed: Option<(Tensor, Tensor)>,
}

impl NormStats {
    /// Statistics of a whole layer input x: `[1, C, H, W]` (as InstanceNorm
    /// computes them: per channel, biased variance).
    pub fn of(x: &Tensor) -> Self {
        let (var, mean) = x.var_mean_dim([2i64, 3].as_slice(), false, true);
        Self { fixed: Some((mean, var)) }
    }

    fn shared(&self) -> Self {
        Self { fixed: self.fixed.as_ref().map(|(m, v)| (m.shallow_clone(), v.shallow_clone())) }
    }

    /// x: `[N, C, h, w]` (one HA layer's input) -> normalised per channel
    /// and replicate-padded by one pixel, `[N, C, h + 2, w + 2]`; in one
    /// pass when `fused` (x f32 on the CPU).
    fn normalize_padded(&mut self, x: &Tensor, fused: bool) -> Tensor {
        if !fused {
            let normalized = match &self.fixed {
                Some((m, v)) => (x - m) * (v + 1e-5).rsqrt(),
                None => instance_norm(x),
            };
            return pad_rep(&normalized, 1);
        }
        let x = x.contiguous();
        let stats = match &self.fixed {
            Some((m, v)) => {
                let mean = Vec::<f32>::try_from(m.flatten(0, -1).to_kind(Kind::Float)).expect("f32 mean");
                let inv_std = Vec::<f32>::try_from((v + 1e-5).rsqrt().flatten(0, -1).to_kind(Kind::Float)).expect("f32 variance");
                // The same statistics for every image of the batch.
                (0..x.size()[0]).flat_map(|_| mean.iter().zip(&inv_std).map(|(&m, &s)| (m, s))).collect()
            }
            None => kernels::plane_stats(&x, 1e-5),
        };
        kernels::normalize_pad1(&x, &stats)
    }
}

/// One tile along an axis: the core it owns and the tile that computes it
/// (the core plus a halo on each side, within the image); input pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileSpan {
    pub core_start: i64,
    pub core_len: i64,
    pub start: i64,
    pub len: i64,
}

/// Splits `len` pixels into cores of `core` pixels (the last may be
/// shorter) with tiles reaching `halo` further each way. Starts are
/// multiples of 8 when `core` and `halo` are (stride-2 layers stay aligned).
pub fn tile_spans(len: i64, core: i64, halo: i64) -> Vec<TileSpan> {
    let mut out = vec![];
    let mut c = 0;
    while c < len {
        let core_len = core.min(len - c);
        let start = (c - halo).max(0);
        let end = (c + core_len + halo).min(len);
        out.push(TileSpan { core_start: c, core_len, start, len: end - start });
        c += core_len;
    }
    out
}

/// Input pixels beyond a core that each layer-wise tile reads: every
/// layer reaches at most 3 input pixels (7x7 stem and head; a stride-2 HA
/// layer's two chained 3x3 convs), rounded up to 8 for stride alignment.
pub const LAYER_HALO: i64 = 8;

/// Applies a local layer `f` to same-sized inputs `[1, C_i, H, W]` tile by
/// tile (cores of `core` pixels plus [`LAYER_HALO`]); its output has
/// `num / den` times the input's resolution. Exact: the halo covers the
/// layer's reach, and at the image's borders tiles end where the image
/// does (same replicate padding as the whole forward). -> `[1, P, H', W']`.
fn map_tiles(inputs: &[&Tensor], core: i64, (num, den): (i64, i64), f: impl Fn(&[Tensor]) -> Tensor) -> Tensor {
    let s = inputs[0].size();
    let (h, w) = (s[2], s[3]);
    let mut out: Option<Tensor> = None;
    for ty in tile_spans(h, core, LAYER_HALO) {
        for tx in tile_spans(w, core, LAYER_HALO) {
            let tiles: Vec<Tensor> = inputs.iter().map(|t| t.narrow(2, ty.start, ty.len).narrow(3, tx.start, tx.len)).collect();
            let y = f(&tiles);
            let at = |v: i64| v * num / den;
            let piece = y.narrow(2, at(ty.core_start - ty.start), at(ty.core_len)).narrow(3, at(tx.core_start - tx.start), at(tx.core_len));
            let acc = out.get_or_insert_with(|| Tensor::zeros([1, y.size()[1], at(h), at(w)], (y.kind(), y.device())));
            acc.narrow(2, at(ty.core_start), at(ty.core_len)).narrow(3, at(tx.core_start), at(tx.core_len)).copy_(&piece);
        }
    }
    out.expect("an image has at least one tile")
}

impl FoldedRes {
    /// [`FoldedRes::forward`] one layer at a time over tiles, each HA layer
    /// normalised with its whole input's statistics. x: `[1, C, H, W]`.
    fn forward_layerwise(&self, x: &Tensor, core: i64) -> Tensor {
        let s1 = NormStats::of(x);
        let h1 = map_tiles(&[x], core, (1, self.stride), |t| self.ha1.forward(&t[0], &mut s1.shared(), None, true));
        let s2 = NormStats::of(&h1);
        let id = match &self.skip {
            Some(s) => conv(x, &s.w, Some(&s.b), self.stride), // 1x1: cheap, whole
            None => x.shallow_clone(),
        };
        map_tiles(&[&h1, &id], core, (1, 1), |t| self.ha2.forward(&t[0], &mut s2.shared(), Some(&t[1]), true))
    }
}

impl FoldedMEst {
    /// M_est layer by layer, each layer over tiles of `core` pixels (a
    /// multiple of 8): the same result as [`FoldedMEst::forward`] up to
    /// float rounding (every HA layer is normalised with the statistics of
    /// its whole input, computed once the layer's input is complete), in
    /// less memory: the U-Net's skip tensors and one layer's input and
    /// output at a time, plus one tile's working set, instead of every
    /// layer's working set at full resolution.
    /// x: `[1, 4, H, W]` (H, W multiples of 8) -> `[1, neural_channels, H, W]`.
    pub fn forward_layerwise(&self, x: &Tensor, core: i64, mut on_layer: impl FnMut()) -> Result<Tensor> {
        check_est_input(x)?;
        ensure!(x.size()[0] == 1, "tiled M_est takes one image, got a batch of {}", x.size()[0]);
        ensure!(core >= 8 && core % 8 == 0, "tile core must be a positive multiple of 8, got {core}");
        Ok(tch::no_grad(|| {
            let stem_out = map_tiles(&[x], core, (1, 1), |t| conv_rep(&t[0], &self.stem, None, 1));
            let block = |b: &FoldedRes, h: &Tensor| {
                let out = b.forward_layerwise(h, core);
                on_layer();
                out
            };
            // The skips are dropped when `walk` returns, before the head.
            let h = self.walk(stem_out, block, |u, h| map_tiles(&[h], core, (2, 1), |t| u.forward(&t[0])));
            map_tiles(&[&h], core, (1, 1), |t| self.to_codes(conv_rep(&t[0], &self.head, None, 1)))
        }))
    }
}

#[cfg(test)]
mod tiled_tests {
    use super::*;
    use crate::model::{Model, ModelConfig};
    use tch::Device;

    #[test]
    fn winograd_policy_takes_wide_convs_and_wide_outputs_on_large_inputs() {
        let p = WinogradPolicy::default();
        assert_eq!(p.min_pixels_for(64, 160), Some(1024));
        assert_eq!(p.min_pixels_for(512, 64), Some(1024));
        // 16 -> 40: 24 MiB of 16-channel f32 planes = 393,216 pixels, so
        // 768x768 (589,824) qualifies and 512x512 (262,144) does not.
        assert_eq!(p.min_pixels_for(16, 40), Some(393_216));
        assert_eq!(p.min_pixels_for(48, 40), Some(131_072));
        for (cin, cout) in [(16, 16), (32, 32), (48, 16), (8, 20), (63, 39)] {
            assert_eq!(p.min_pixels_for(cin, cout), None, "{cin} -> {cout}");
        }
        assert_eq!(WinogradPolicy::ALWAYS.min_pixels_for(1, 1), Some(1));
    }

    #[test]
    fn spans_cover_the_image_once() {
        let s = tile_spans(40, 16, 8);
        assert_eq!(
            s,
            vec![
                TileSpan { core_start: 0, core_len: 16, start: 0, len: 24 },
                TileSpan { core_start: 16, core_len: 16, start: 8, len: 32 },
                TileSpan { core_start: 32, core_len: 8, start: 24, len: 16 },
            ]
        );
        assert_eq!(tile_spans(8, 64, 8), vec![TileSpan { core_start: 0, core_len: 8, start: 0, len: 8 }]);
    }

    /// Layer-wise tiles reproduce the plain forward up to float rounding,
    /// for a rectangle split into 3 x 4 tiles at full resolution (and
    /// fewer below); measured max difference 9.0e-2 on a map scale of 27,242
    /// (3.3e-6 relative: an untrained model's large values).
    #[test]
    fn layerwise_tiles_reproduce_the_forward() {
        tch::manual_seed(2);
        let model = Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap();
        let est = model.est.fold_batchnorm();
        let x = Tensor::rand([1, 4, 40, 56], (Kind::Float, Device::Cpu));
        let plain = est.forward(&x).unwrap();
        let mut layers = 0;
        let tiled = est.forward_layerwise(&x, 16, || layers += 1).unwrap();
        assert_eq!(tiled.size(), plain.size());
        assert!(layers > 8, "{layers}");
        let scale = plain.abs().max().double_value(&[]);
        let d = (&tiled - &plain).abs().max().double_value(&[]);
        eprintln!("layer-wise tiles vs whole: max difference {d:.2e} (map scale {scale:.2})");
        assert!(d < 1e-4 * (1.0 + scale), "{d}");
        // Statistics of the whole input reproduce the plain instance norm.
        let mut n = NormStats::of(&x);
        let want = pad_rep(&instance_norm(&x), 1);
        for fused in [false, true] {
            assert!((n.normalize_padded(&x, fused) - &want).abs().max().double_value(&[]) < 1e-5, "fused {fused}");
        }
    }
}
