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

    /// x: `[N, C, H, W]` -> `[N, P, H/s, W/s]` = bn(ha(x)).
    fn forward(&self, x: &Tensor) -> Tensor {
        let (p, half, s) = (self.out, self.out / 2, self.stride);
        let xp = pad_rep(x, 1);
        let m = conv(&xp, &self.merged, Some(&self.merged_bias), s);
        let gate = m.narrow(1, 0, p).sigmoid();
        let (a, c) = match &self.incep_a {
            None => (m.narrow(1, p, p), m.narrow(1, 2 * p, half)),
            Some(wa) => (conv(&xp, wa, None, 1), m.narrow(1, p, half)),
        };
        let b = conv_rep(&a, &self.incep_b, Some(&self.incep_b_bias), s);
        let mut feat = leaky(&conv_rep(&instance_norm(x), &self.feat, None, s), HA_FEAT_SLOPE);
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

    fn forward(&self, x: &Tensor) -> Tensor {
        let out = self.ha2.forward(&self.ha1.forward(x).relu());
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
        check_est_input(x)?;
        Ok(tch::no_grad(|| {
            let x = if self.channels_last { to_channels_last(x) } else { x.shallow_clone() };
            let mut h = conv_rep(&x, &self.stem, None, 1);
            let mut skips = Vec::with_capacity(4);
            for stage in &self.enc {
                for b in stage {
                    h = b.forward(&h);
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
                    h = b.forward(&h);
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
