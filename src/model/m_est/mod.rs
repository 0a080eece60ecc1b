//! M_est: the highlight-aware U-Net mapping a photo (ln(1+RGB) and h_z) to
//! a map of neural material parameters (REFERENCE section 4).
//!
//! Layout (W = `est_width`; every conv is bias-free, 3x3 and 7x7 convs use
//! replicate padding):
//!
//! ```text
//! stem   7x7 conv 4 -> W
//! enc1   HA-res(W -> W), HA-res(W)                       full resolution
//! enc2   HA-res(W -> 2W, stride 2, 1x1 skip), HA-res(2W)  1/2
//! enc3   HA-res(2W -> 4W, s2), HA-res(4W)                 1/4
//! enc4   HA-res(4W -> 8W, s2), HA-res(8W)                 1/8
//! arctan on enc4's output (the bottleneck)
//! dec4   Up(8W -> 8W), HA-res(8W)                         -> 1/4
//! dec3   concat enc3 (12W), Up(12W -> 4W), HA-res(4W)     -> 1/2
//! dec2   concat enc2 (6W),  Up(6W -> 2W),  HA-res(2W)     -> 1
//! dec1   concat enc1 (3W),  HA-res(3W -> W, 1x1 skip), HA-res(W)
//! head   7x7 conv W -> neural_channels, no activation
//! ```
//!
//! With `ggx_codes` (not the paper's) the head writes the 10 GGX values of
//! each pixel and a frozen per-pixel encoder (`codes`,
//! [`super::ggx_codes`]) turns them, projected onto the ranges it was
//! trained on (`ggx_codes::valid_values`), into the neural map.
//!
//! How the published parameter counts (84,008,960 / 21,060,608 / 5,294,336 /
//! 1,338,176 for W = 64/32/16/8) pin this down: they fit exactly
//! 20,453 W^2 + 3,648 W with no constant term, so no layer has a bias (a
//! head bias would add a constant 64). The encoder above gives 10,959 W^2;
//! the remaining 9,494 W^2 is matched only when the decoder's residual blocks
//! are highlight-aware too ("residual blocks as in the encoder") and the
//! skip features are concatenated *before* each upsampling block, so the
//! up-blocks read 8W, 12W and 6W channels (1,856 + 1,104 + 276 W^2 for the
//! three up-blocks, 4,608 + 1,152 + 288 + 138 + 72 W^2 for the HA blocks).
//! The linear term: stem 196 W + head 3,136 W + BatchNorm affine parameters
//! (2 per channel, 149 W channels: 74 W encoder, 75 W decoder) = 3,630 W;
//! the last 18 W are two normalisation layers the reference implementation
//! constructs but never applies (a W-channel BatchNorm after the stem and
//! an 8W LayerNorm at the bottleneck). They are kept as trainable but unused
//! variables under `est.compat.*` only so that the count, and a checkpoint's
//! variable set, match the published model; they never touch the forward
//! pass and never receive gradients.

use super::config::ModelConfig;
use super::ggx_codes::{GgxEncoder, GGX_CHANNELS};
use super::layers::{conv, conv_init, conv_rep, conv_t, leaky, pad_rep, per_channel, torch_default_init, Bn};
use anyhow::{ensure, Result};
use tch::nn::{self, Init};
use tch::{Kind, Tensor};

/// Channels of M_est's input: ln(1 + RGB) and h_z.
pub const EST_INPUT_CHANNELS: i64 = 4;

/// Slope of the LeakyReLU on the HA feature branch.
const HA_FEAT_SLOPE: f64 = 0.1;

/// Checks an M_est input `[N, 4, H, W]` with H, W positive multiples of 8.
pub fn check_est_input(x: &Tensor) -> Result<(i64, i64)> {
    let s = x.size();
    ensure!(s.len() == 4, "M_est input must be [N, 4, H, W], got shape {s:?}");
    ensure!(s[1] == EST_INPUT_CHANNELS, "M_est input must have 4 channels (ln(1+RGB), h_z), got shape {s:?}");
    let (h, w) = (s[2], s[3]);
    ensure!(
        h >= 8 && w >= 8 && h % 8 == 0 && w % 8 == 0,
        "M_est needs H and W to be positive multiples of 8 (three 2x downsamplings), got {h}x{w}"
    );
    Ok((h, w))
}

/// A highlight-aware layer C -> P with stride s (all 3x3, replicate padded):
/// out = sigmoid(gate(x)) * LeakyReLU_0.1(feat(InstanceNorm(x)))
///       + concat(incep.b(incep.a(x)), incep.c(x)).
#[derive(Debug)]
pub struct HaLayer {
    /// `[P, C, 3, 3]`, stride s.
    pub gate: Tensor,
    /// `[P, C, 3, 3]`, stride s, applied to the instance-normalised input.
    pub feat: Tensor,
    /// `[P, C, 3, 3]`, stride 1.
    pub incep_a: Tensor,
    /// `[P/2, P, 3, 3]`, stride s, applied to incep_a's output.
    pub incep_b: Tensor,
    /// `[P/2, C, 3, 3]`, stride s.
    pub incep_c: Tensor,
    pub stride: i64,
}

impl HaLayer {
    fn new(p: &nn::Path, cin: i64, cout: i64, stride: i64) -> Self {
        let w = |q: nn::Path, o: i64, i: i64| q.var("weight", &[o, i, 3, 3], conv_init());
        Self {
            gate: w(p / "gate", cout, cin),
            feat: w(p / "feat", cout, cin),
            incep_a: w(p / "incep" / "a", cout, cin),
            incep_b: w(p / "incep" / "b", cout / 2, cout),
            incep_c: w(p / "incep" / "c", cout / 2, cin),
            stride,
        }
    }

    /// x: `[N, C, H, W]` -> `[N, P, H/s, W/s]`.
    fn forward(&self, x: &Tensor) -> Tensor {
        let s = self.stride;
        let xp = pad_rep(x, 1);
        let gate = conv(&xp, &self.gate, None, s).sigmoid();
        let xn = instance_norm(x);
        let feat = leaky(&conv_rep(&xn, &self.feat, None, s), HA_FEAT_SLOPE);
        let a = conv(&xp, &self.incep_a, None, 1);
        let b = conv_rep(&a, &self.incep_b, None, s);
        let c = conv(&xp, &self.incep_c, None, s);
        gate * feat + Tensor::cat(&[b, c], 1)
    }
}

/// InstanceNorm without affine parameters (PyTorch's defaults, eps 1e-5).
/// x: `[N, C, H, W]`.
fn instance_norm(x: &Tensor) -> Tensor {
    x.instance_norm(None::<&Tensor>, None, None, None, true, 0.1, 1e-5, true)
}

/// Projection on a residual block's identity path: 1x1 conv (stride s) + BN.
#[derive(Debug)]
pub struct Skip {
    /// `[P, C, 1, 1]`.
    pub conv: Tensor,
    pub bn: Bn,
}

/// Residual block of two HA layers:
/// relu(bn2(ha2(relu(bn1(ha1(x))))) + skip(x)).
#[derive(Debug)]
pub struct ResBlock {
    pub ha1: HaLayer,
    pub bn1: Bn,
    pub ha2: HaLayer,
    pub bn2: Bn,
    pub skip: Option<Skip>,
    pub stride: i64,
}

impl ResBlock {
    pub(crate) fn new(p: &nn::Path, cin: i64, cout: i64, stride: i64) -> Self {
        let skip = (cin != cout || stride != 1).then(|| Skip {
            conv: (p / "skip" / "conv").var("weight", &[cout, cin, 1, 1], conv_init()),
            bn: Bn::new(&(p / "skip" / "bn"), cout),
        });
        Self {
            ha1: HaLayer::new(&(p / "ha1"), cin, cout, stride),
            bn1: Bn::new(&(p / "bn1"), cout),
            ha2: HaLayer::new(&(p / "ha2"), cout, cout, 1),
            bn2: Bn::new(&(p / "bn2"), cout),
            skip,
            stride,
        }
    }

    /// x: `[N, C, H, W]` -> `[N, P, H/s, W/s]`.
    pub(crate) fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let out = self.bn1.forward_t(&self.ha1.forward(x), train).relu();
        let out = self.bn2.forward_t(&self.ha2.forward(&out), train);
        let id = match &self.skip {
            Some(s) => s.bn.forward_t(&conv(x, &s.conv, None, self.stride), train),
            None => x.shallow_clone(),
        };
        (out + id).relu()
    }
}

/// Residual 2x upsampling block:
/// relu(bn2(conv3x3(relu(bn1(tconv4x4(x))))) + skip_bn(tconv2x2(x))).
#[derive(Debug)]
pub struct UpBlock {
    /// `[C, P, 4, 4]`, stride 2, padding 1.
    pub tconv: Tensor,
    pub bn1: Bn,
    /// `[P, P, 3, 3]`, replicate padded.
    pub conv: Tensor,
    pub bn2: Bn,
    /// `[C, P, 2, 2]`, stride 2.
    pub skip_tconv: Tensor,
    pub skip_bn: Bn,
}

impl UpBlock {
    pub(crate) fn new(p: &nn::Path, cin: i64, cout: i64) -> Self {
        // Transposed convs keep PyTorch's default init (as in the reference).
        Self {
            tconv: (p / "tconv").var("weight", &[cin, cout, 4, 4], torch_default_init()),
            bn1: Bn::new(&(p / "bn1"), cout),
            conv: (p / "conv").var("weight", &[cout, cout, 3, 3], conv_init()),
            bn2: Bn::new(&(p / "bn2"), cout),
            skip_tconv: (p / "skip" / "tconv").var("weight", &[cin, cout, 2, 2], torch_default_init()),
            skip_bn: Bn::new(&(p / "skip" / "bn"), cout),
        }
    }

    /// x: `[N, C, H, W]` -> `[N, P, 2H, 2W]`.
    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let out = self.bn1.forward_t(&conv_t(x, &self.tconv, None, 2, 1), train).relu();
        let out = self.bn2.forward_t(&conv_rep(&out, &self.conv, None, 1), train);
        let id = self.skip_bn.forward_t(&conv_t(x, &self.skip_tconv, None, 2, 0), train);
        (out + id).relu()
    }

    /// Projects both transposed convolutions onto the kernels that map a
    /// constant input to a constant output ([`checkerboard_free_kernel`]).
    pub fn project_checkerboard_free(&self) {
        tch::no_grad(|| {
            for w in [&self.tconv, &self.skip_tconv] {
                let projected = checkerboard_free_kernel(w);
                w.shallow_clone().copy_(&projected);
            }
        })
    }
}

/// The nearest kernel (least squares) of a stride-2 transposed convolution
/// without a checkerboard. An output pixel of parity (a, b) sums the input
/// through the taps (ky, kx) with ky = a + padding and kx = b + padding
/// (mod 2) only, so a flat input comes out flat exactly when the four
/// parity classes of taps sum to the same value for every (input, output)
/// channel pair; otherwise the layer stamps a 2x2 pattern on flat regions
/// and every later layer carries it (Odena et al. 2016, "Deconvolution and
/// checkerboard artifacts"). Each class is shifted by the same amount per
/// tap to the mean of the four sums: for the 2x2 skip kernel, every tap
/// becomes the mean (nearest-neighbour upsampling then a 1x1 conv); for the
/// 4x4 kernel, 3 of the 16 degrees of freedom per channel pair go.
/// w: `[C, P, k, k]`, k even -> same shape.
pub fn checkerboard_free_kernel(w: &Tensor) -> Tensor {
    let s = w.size();
    let (c, p, k) = (s[0], s[1], s[2]);
    assert!(s.len() == 4 && k == s[3] && k % 2 == 0, "a stride-2 transposed-convolution kernel [C, P, k, k] with k even, got {s:?}");
    let taps = w.reshape([c, p, k / 2, 2, k / 2, 2]);
    let class_sums = taps.sum_dim_intlist([2i64, 4].as_slice(), true, w.kind());
    let excess = (&class_sums - class_sums.mean_dim([3i64, 5].as_slice(), true, w.kind())) / ((k / 2) * (k / 2)) as f64;
    (taps - excess).reshape([c, p, k, k])
}

/// One decoder stage: an optional upsampling block then residual blocks.
#[derive(Debug)]
pub struct DecStage {
    pub up: Option<UpBlock>,
    pub blocks: Vec<ResBlock>,
}

impl DecStage {
    /// x: `[N, C, H, W]` -> `[N, P, H', W']` (2x larger with an up-block).
    pub(crate) fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        let mut x = match &self.up {
            Some(u) => u.forward_t(x, train),
            None => x.shallow_clone(),
        };
        for b in &self.blocks {
            x = b.forward_t(&x, train);
        }
        x
    }
}

/// The highlight-aware U-Net.
#[derive(Debug)]
pub struct MEst {
    /// `[W, 4, 7, 7]`.
    pub stem: Tensor,
    /// Encoder stages 1..4, two residual blocks each.
    pub enc: Vec<Vec<ResBlock>>,
    /// Decoder stages in execution order: dec4, dec3, dec2, dec1.
    pub dec: Vec<DecStage>,
    /// `[neural_channels, W, 7, 7]` (`[10, W, 7, 7]` with `codes`).
    pub head: Tensor,
    /// The frozen GGX encoder after the head ([`ModelConfig::ggx_codes`]).
    pub codes: Option<GgxEncoder>,
    pub width: i64,
    pub out_channels: i64,
}

impl MEst {
    /// Creates M_est's variables under `p` (conventionally `est`).
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Result<Self> {
        cfg.validate()?;
        let w = cfg.est_width;
        let widths = [w, 2 * w, 4 * w, 8 * w];
        let stem = (p / "stem").var("weight", &[w, EST_INPUT_CHANNELS, 7, 7], conv_init());
        let mut enc = Vec::new();
        let mut cin = w;
        for (i, &c) in widths.iter().enumerate() {
            let q = p / format!("enc{}", i + 1);
            let stride = if i == 0 { 1 } else { 2 };
            enc.push(vec![ResBlock::new(&(&q / 0), cin, c, stride), ResBlock::new(&(&q / 1), c, c, 1)]);
            cin = c;
        }
        // Decoder: dec4, dec3, dec2 = [Up(cin -> c), HA-res(c)], where cin
        // includes the concatenated encoder features (none at dec4);
        // dec1 = [HA-res(3W -> W), HA-res(W)].
        let mut dec = Vec::new();
        for (stage, cin, c) in [(4, 8 * w, 8 * w), (3, 12 * w, 4 * w), (2, 6 * w, 2 * w)] {
            let q = p / format!("dec{stage}");
            dec.push(DecStage { up: Some(UpBlock::new(&(&q / "up"), cin, c)), blocks: vec![ResBlock::new(&(&q / 0), c, c, 1)] });
        }
        let q = p / "dec1";
        dec.push(DecStage { up: None, blocks: vec![ResBlock::new(&(&q / 0), 3 * w, w, 1), ResBlock::new(&(&q / 1), w, w, 1)] });
        let head_out = if cfg.ggx_codes { GGX_CHANNELS } else { cfg.neural_channels };
        let head = (p / "head").var("weight", &[head_out, w, 7, 7], conv_init());
        let codes = cfg.ggx_codes.then(|| GgxEncoder::frozen(&(p / "codes"), cfg.neural_channels));
        // Unused, see the module docs.
        let compat = p / "compat";
        let _ = (&compat / "stem_bn").var("weight", &[w], Init::Const(1.0));
        let _ = (&compat / "stem_bn").var("bias", &[w], Init::Const(0.0));
        let _ = (&compat / "bottleneck_ln").var("weight", &[8 * w], Init::Const(1.0));
        let _ = (&compat / "bottleneck_ln").var("bias", &[8 * w], Init::Const(0.0));
        Ok(Self { stem, enc, dec, head, codes, width: w, out_channels: cfg.neural_channels })
    }

    /// Projects every upsampling block onto checkerboard-free kernels
    /// (`UpBlock::project_checkerboard_free`): a flat photo then gives a flat
    /// neural map. Idempotent; the mean of projected models stays projected.
    pub fn project_checkerboard_free(&self) {
        for stage in &self.dec {
            if let Some(up) = &stage.up {
                up.project_checkerboard_free();
            }
        }
    }

    /// Whether every upsampling kernel is checkerboard-free to `tol`
    /// (largest change the projection would make, relative to the kernel's
    /// largest tap).
    pub fn is_checkerboard_free(&self, tol: f64) -> bool {
        self.dec.iter().filter_map(|s| s.up.as_ref()).flat_map(|u| [&u.tconv, &u.skip_tconv]).all(|w| {
            let change = (checkerboard_free_kernel(w) - w).abs().max().double_value(&[]);
            change <= tol * w.abs().max().double_value(&[]).max(1e-30)
        })
    }

    /// x: `[N, 4, H, W]` (ln(1+RGB), h_z), H and W multiples of 8 ->
    /// neural map `[N, neural_channels, H, W]`. `train` selects BatchNorm
    /// batch statistics (and running-stat updates) vs running statistics.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        self.forward_traced(x, train, None)
    }

    /// [`Self::forward_t`] and the head's output `[N, 10 or C, H, W]` (in
    /// the forward's precision): with [`ModelConfig::ggx_codes`] the GGX
    /// values the head writes, before their projection and the encoder;
    /// otherwise the neural map itself.
    pub fn forward_with_head(&self, x: &Tensor, train: bool) -> Result<(Tensor, Tensor)> {
        let mut head = None;
        let neural = self.forward_traced(x, train, Some(&mut |stage: &str, t: &Tensor| {
            if stage == "head" {
                head = Some(t.shallow_clone());
            }
        }))?;
        Ok((neural, head.ok_or_else(|| anyhow::anyhow!("M_est's forward traced no head"))?))
    }

    /// [`Self::forward_t`], also handing every stage's output to `trace`
    /// as (stage name, `[N, C', H', W']`): the stem, each encoder block,
    /// each decoder stage and the head. For probes of what the stages
    /// carry (`examples/probe_layers.rs`).
    pub fn forward_traced(&self, x: &Tensor, train: bool, mut trace: Option<&mut dyn FnMut(&str, &Tensor)>) -> Result<Tensor> {
        let (h, w) = check_est_input(x)?;
        let n = x.size()[0];
        ensure!(
            !train || n * (h / 8) * (w / 8) > 1,
            "training-mode BatchNorm needs more than one value per channel at 1/8 resolution: use a batch of 2 or inputs larger than 8x8 (got {n} x {h}x{w})"
        );
        let mut record = |name: &str, t: &Tensor| {
            if let Some(f) = trace.as_mut() {
                f(name, t)
            }
        };
        let out = crate::precision::forward(x.device(), || {
            let mut h = conv_rep(x, &self.stem, None, 1);
            record("stem", &h);
            let mut skips = Vec::with_capacity(4);
            for (si, stage) in self.enc.iter().enumerate() {
                for (bi, b) in stage.iter().enumerate() {
                    h = b.forward_t(&h, train);
                    record(&format!("enc{}.{bi}", si + 1), &h);
                }
                skips.push(h.shallow_clone());
            }
            h = h.arctan();
            for (i, st) in self.dec.iter().enumerate() {
                if i > 0 {
                    // Before dec3/dec2/dec1: the encoder features of enc3/enc2/enc1.
                    h = Tensor::cat(&[&h, &skips[3 - i]], 1);
                }
                h = st.forward_t(&h, train);
                record(&format!("dec{}", 4 - i), &h);
            }
            let out = conv_rep(&h, &self.head, None, 1);
            record("head", &out);
            match &self.codes {
                Some(e) => e.forward_maps(&super::ggx_codes::valid_values(&out)),
                None => out,
            }
        });
        Ok(crate::precision::to_f32(out))
    }
}

mod folded;
mod kernels;

pub use folded::{WinogradPolicy, tile_spans, FoldedMEst, NormStats, TileSpan, LAYER_HALO};

/// Same logical `[N, C, H, W]` tensor with NHWC strides.
pub fn to_channels_last(t: &Tensor) -> Tensor {
    t.permute([0, 2, 3, 1]).contiguous().permute([0, 3, 1, 2])
}

/// Analytic multiply-adds x 2 of one M_est forward on an h x w input
/// (convolutions only; normalisations and activations are negligible).
pub fn est_flops(cfg: &ModelConfig, h: i64, w: i64) -> f64 {
    let wd = cfg.est_width as f64;
    let px = |scale: i64| ((h / scale) * (w / scale)) as f64;
    // HA layer C -> P producing an output of `out_px` pixels (input `in_px`).
    let ha = |c: f64, p: f64, in_px: f64, out_px: f64| 9.0 * (2.0 * c * p + c * p / 2.0 + p * p / 2.0) * out_px + 9.0 * c * p * in_px;
    let res = |c: f64, p: f64, in_px: f64, out_px: f64| {
        ha(c, p, in_px, out_px) + ha(p, p, out_px, out_px) + if c != p { c * p * out_px } else { 0.0 }
    };
    let up = |c: f64, p: f64, out_px: f64| (16.0 * c * p / 4.0 + 9.0 * p * p + 4.0 * c * p / 4.0) * out_px;
    let mut macs = 4.0 * 49.0 * wd * px(1) + cfg.neural_channels as f64 * 49.0 * wd * px(1);
    let ws = [wd, 2.0 * wd, 4.0 * wd, 8.0 * wd];
    let mut cin = wd;
    for (i, &c) in ws.iter().enumerate() {
        let (in_s, out_s) = if i == 0 { (1, 1) } else { (1 << (i - 1), 1 << i) };
        macs += res(cin, c, px(in_s), px(out_s)) + res(c, c, px(out_s), px(out_s));
        cin = c;
    }
    // dec4..dec2: Up(cin -> c) to scale `s`, then HA-res(c).
    for (cin, c, s) in [(8.0 * wd, 8.0 * wd, 4), (12.0 * wd, 4.0 * wd, 2), (6.0 * wd, 2.0 * wd, 1)] {
        macs += up(cin, c, px(s)) + res(c, c, px(s), px(s));
    }
    macs += res(3.0 * wd, wd, px(1), px(1)) + res(wd, wd, px(1), px(1));
    2.0 * macs
}
