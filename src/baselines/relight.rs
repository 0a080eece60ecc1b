//! Direct relighting U-Net (Bieron 2023 style): the photo in, the relit
//! image out, the light and view injected into the decoder; no per-pixel
//! material parameters.
//!
//! Layout (W = `est_width`, E = `enc_out`; the encoder is M_est's, the
//! decoder M_est's widened by E input channels at each stage):
//!
//! ```text
//! stem   7x7 conv 4 -> W                                 (photo: ln(1+RGB), h_z)
//! enc1..enc4 as M_est (HA residual blocks, W .. 8W), arctan bottleneck
//! code   per pixel: sinusoidal encoding of (wi, wo, h) as ND_enc
//!        (9 + 18 enc_frequencies values) -> MLP enc_hidden, enc_hidden, E
//!        = [N*K, E, H, W]; average-pooled to 1/2, 1/4, 1/8
//! dec4   concat code/8 (8W + E),        Up(8W+E -> 8W),  HA-res(8W)
//! dec3   concat enc3, code/4 (12W + E), Up(12W+E -> 4W), HA-res(4W)
//! dec2   concat enc2, code/2 (6W + E),  Up(6W+E -> 2W),  HA-res(2W)
//! dec1   concat enc1, code (3W + E),    HA-res(3W+E -> W), HA-res(W)
//! head   7x7 conv W -> 3: ln(1 + R) of the relit image, no activation
//! ```
//!
//! The encoder runs once per photo; the decoder once per (photo, light/view
//! configuration), with the encoder features shared by the K
//! configurations of a photo.

use crate::model::layers::conv_init;
use crate::model::m_est::{check_est_input, DecStage, ResBlock, UpBlock, EST_INPUT_CHANNELS};
use crate::model::{ModelConfig, NdEnc};
use anyhow::{ensure, Result};
use tch::{nn, Tensor};

/// Channels of the relit image the head predicts.
pub const OUT_CHANNELS: i64 = 3;

/// The head's initial weights are M_est's scaled by this: log radiance
/// starts near 0 (dark) instead of values of +-2 (e^2 times too bright or
/// negative radiance).
pub const HEAD_INIT_SCALE: f64 = 0.1;

/// The relighting U-Net.
#[derive(Debug)]
pub struct RelightUNet {
    /// `[W, 4, 7, 7]`.
    pub stem: Tensor,
    /// Encoder stages 1..4, two residual blocks each (as M_est).
    pub enc: Vec<Vec<ResBlock>>,
    /// Per-pixel direction code (ND_enc's encoding and MLP layout).
    pub dirs: NdEnc,
    /// Decoder stages in execution order: dec4, dec3, dec2, dec1.
    pub dec: Vec<DecStage>,
    /// `[3, W, 7, 7]`.
    pub head: Tensor,
    pub width: i64,
    /// Channels of the direction code (E).
    pub code_width: i64,
}

/// Encoder features of a batch of photos, reusable for any number of
/// light/view configurations.
#[derive(Debug)]
pub struct RelightEncoded {
    /// arctan of enc4's output `[N, 8W, H/8, W/8]`.
    pub bottleneck: Tensor,
    /// enc1, enc2, enc3 outputs `[N, W, H, W]`, `[N, 2W, H/2, W/2]`, `[N, 4W, H/4, W/4]`.
    pub skips: Vec<Tensor>,
}

impl RelightUNet {
    /// Variables under `p`: `stem`, `enc1..4`, `dirs.0..2`, `dec4..1`, `head`.
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Result<Self> {
        cfg.validate()?;
        let w = cfg.est_width;
        let e = cfg.enc_out;
        let stem = (p / "stem").var("weight", &[w, EST_INPUT_CHANNELS, 7, 7], conv_init());
        let mut enc = Vec::new();
        let mut cin = w;
        for (i, &c) in [w, 2 * w, 4 * w, 8 * w].iter().enumerate() {
            let q = p / format!("enc{}", i + 1);
            let stride = if i == 0 { 1 } else { 2 };
            enc.push(vec![ResBlock::new(&(&q / 0), cin, c, stride), ResBlock::new(&(&q / 1), c, c, 1)]);
            cin = c;
        }
        let dirs = NdEnc::new(&(p / "dirs"), cfg);
        let mut dec = Vec::new();
        for (stage, cin, c) in [(4, 8 * w + e, 8 * w), (3, 12 * w + e, 4 * w), (2, 6 * w + e, 2 * w)] {
            let q = p / format!("dec{stage}");
            dec.push(DecStage { up: Some(UpBlock::new(&(&q / "up"), cin, c)), blocks: vec![ResBlock::new(&(&q / 0), c, c, 1)] });
        }
        let q = p / "dec1";
        dec.push(DecStage { up: None, blocks: vec![ResBlock::new(&(&q / 0), 3 * w + e, w, 1), ResBlock::new(&(&q / 1), w, w, 1)] });
        let head = (p / "head").var("weight", &[OUT_CHANNELS, w, 7, 7], conv_init());
        tch::no_grad(|| {
            let _ = head.shallow_clone().g_mul_scalar_(HEAD_INIT_SCALE);
        });
        Ok(Self { stem, enc, dirs, dec, head, width: w, code_width: e })
    }

    /// Encoder. x: `[N, 4, H, W]` (ln(1+RGB), h_z), H and W multiples of 8.
    pub fn encode_t(&self, x: &Tensor, train: bool) -> Result<RelightEncoded> {
        let (h, w) = check_est_input(x)?;
        let n = x.size()[0];
        ensure!(
            !train || n * (h / 8) * (w / 8) > 1,
            "training-mode BatchNorm needs more than one value per channel at 1/8 resolution: use a batch of 2 or inputs larger than 8x8 (got {n} x {h}x{w})"
        );
        let mut f = crate::model::layers::conv_rep(x, &self.stem, None, 1);
        let mut skips = Vec::with_capacity(4);
        for stage in &self.enc {
            for b in stage {
                f = b.forward_t(&f, train);
            }
            skips.push(f.shallow_clone());
        }
        let bottleneck = skips.pop().expect("four stages").arctan();
        Ok(RelightEncoded { bottleneck, skips })
    }

    /// Per-pixel direction code. wi, wo: `[N, K, 3, H, W]` -> `[N*K, E, H, W]`.
    pub fn direction_code(&self, wi: &Tensor, wo: &Tensor) -> Result<Tensor> {
        let d = wi.size();
        ensure!(d.len() == 5 && d[2] == 3, "wi must be [N, K, 3, H, W], got {d:?}");
        ensure!(wo.size() == d, "wo {:?} must match wi {d:?}", wo.size());
        let rows = |t: &Tensor| t.permute([0, 1, 3, 4, 2]);
        let code = self.dirs.forward(&rows(wi), &rows(wo)); // [N, K, H, W, E]
        Ok(code.permute([0, 1, 4, 2, 3]).flatten(0, 1).contiguous())
    }

    /// Decoder for K configurations per encoded photo.
    /// wi, wo: `[N, K, 3, H, W]` -> ln(1 + R) `[N, K, 3, H, W]`.
    pub fn decode_t(&self, enc: &RelightEncoded, wi: &Tensor, wo: &Tensor, train: bool) -> Result<Tensor> {
        let b = enc.bottleneck.size();
        let (n, h, w) = (b[0], b[2] * 8, b[3] * 8);
        let d = wi.size();
        ensure!(
            d.len() == 5 && d[0] == n && d[3] == h && d[4] == w,
            "direction maps must be [N, K, 3, H, W] = [{n}, K, 3, {h}, {w}], got {d:?}"
        );
        let k = d[1];
        let code = self.direction_code(wi, wo)?;
        // Photo features repeated for each of its K configurations.
        let per_config = |t: &Tensor| {
            let s = t.size();
            t.unsqueeze(1).expand([s[0], k, s[1], s[2], s[3]], false).reshape([s[0] * k, s[1], s[2], s[3]])
        };
        let pooled = |f: i64| if f == 1 { code.shallow_clone() } else { code.avg_pool2d([f, f], [f, f], [0, 0], false, true, None) };
        let mut x = Tensor::cat(&[per_config(&enc.bottleneck), pooled(8)], 1);
        x = self.dec[0].forward_t(&x, train);
        for (i, st) in self.dec.iter().enumerate().skip(1) {
            // Before dec3/dec2/dec1: enc3/enc2/enc1 features and the code at 1/4, 1/2, 1.
            let skip = &enc.skips[3 - i];
            x = Tensor::cat(&[x, per_config(skip), pooled(1 << (3 - i))], 1);
            x = st.forward_t(&x, train);
        }
        let out = crate::model::layers::conv_rep(&x, &self.head, None, 1);
        Ok(out.view([n, k, OUT_CHANNELS, h, w]))
    }

    /// Relit log images. x: `[N, 4, H, W]`; wi, wo: `[N, K, 3, H, W]` ->
    /// ln(1 + R) `[N, K, 3, H, W]`.
    pub fn forward_t(&self, x: &Tensor, wi: &Tensor, wo: &Tensor, train: bool) -> Result<Tensor> {
        let enc = self.encode_t(x, train)?;
        self.decode_t(&enc, wi, wo, train)
    }
}
