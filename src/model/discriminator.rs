//! Conditional discriminator (training only; REFERENCE section 4).
//!
//! Input: concat(image, input photo), 6 channels. Layers (D = `disc_width`,
//! 64 for the paper; "six layers", kernel 4 except the final 2x2):
//!
//! ```text
//! c0  4x4 s2 conv 6 -> D, bias, LeakyReLU 0.2
//! c1  4x4 s2 conv D -> 2D, BatchNorm, LeakyReLU 0.2
//! c2  4x4 s2 conv 2D -> 4D, BatchNorm, LeakyReLU 0.2
//! c3  4x4 s2 conv 4D -> 8D (512), BatchNorm, LeakyReLU 0.2
//! c4  4x4 s1 conv 8D -> 8D, BatchNorm, LeakyReLU 0.2
//! adaptive max-pool to 2x2
//! c5  2x2 conv 8D -> 1, bias: one score per image
//! ```
//!
//! Choices where REFERENCE is vague: three doubling stride-2 convs take 64
//! to 512 (64 -> 128 -> 256 -> 512); the stride-1 conv keeps 512 channels
//! and has BatchNorm + LeakyReLU like the layers before it (PatchGAN
//! style); convs use zero padding 1 (the discriminator compares textures,
//! borders do not matter); convs followed by BatchNorm have no bias. The
//! input must be at least 32x32 so the stride-1 conv has a non-empty output.

use super::config::ModelConfig;
use super::layers::{leaky, torch_default_init, Bn};
use anyhow::{ensure, Result};
use tch::nn::{self, Init};
use tch::{Device, Tensor};

const SLOPE: f64 = 0.2;

#[derive(Debug)]
pub struct Discriminator {
    /// Conv weights c0..c4 `[out, in, 4, 4]`.
    pub convs: Vec<Tensor>,
    /// Bias of c0.
    pub c0_bias: Tensor,
    /// BatchNorms after c1..c4.
    pub bns: Vec<Bn>,
    /// `[1, 8D, 2, 2]` and its bias `[1]`.
    pub score: Tensor,
    pub score_bias: Tensor,
}

impl Discriminator {
    /// Variables under `p` (conventionally `disc`).
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Self {
        let d = cfg.disc_width;
        let chans = [6, d, 2 * d, 4 * d, 8 * d, 8 * d];
        let init = Init::Randn { mean: 0.0, stdev: 0.02 }; // the DCGAN/pix2pix convention
        let convs = (0..5).map(|i| (p / format!("c{i}")).var("weight", &[chans[i + 1], chans[i], 4, 4], init)).collect();
        let c0_bias = (p / "c0").var("bias", &[d], Init::Const(0.0));
        let bns = (1..5).map(|i| Bn::new(&(p / format!("c{i}_bn")), chans[i + 1])).collect();
        let score = (p / "c5").var("weight", &[1, 8 * d, 2, 2], torch_default_init());
        let score_bias = (p / "c5").var("bias", &[1], Init::Const(0.0));
        Self { convs, c0_bias, bns, score, score_bias }
    }

    /// A discriminator with its own VarStore (root path `disc`), separate
    /// from the model's so training can run its own optimizer on it.
    pub fn with_store(cfg: &ModelConfig, device: Device) -> (nn::VarStore, Self) {
        let vs = nn::VarStore::new(device);
        let d = Self::new(&(vs.root() / "disc"), cfg);
        (vs, d)
    }

    /// image, photo: `[N, 3, H, W]` with H, W >= 32 -> scores `[N, 1]`.
    pub fn forward_t(&self, image: &Tensor, photo: &Tensor, train: bool) -> Result<Tensor> {
        let (si, sp) = (image.size(), photo.size());
        ensure!(si.len() == 4 && si[1] == 3, "discriminator image must be [N, 3, H, W], got {si:?}");
        ensure!(si == sp, "discriminator image {si:?} and photo {sp:?} must have the same shape");
        ensure!(si[2] >= 32 && si[3] >= 32, "discriminator needs inputs of at least 32x32, got {}x{}", si[2], si[3]);
        ensure!(
            !train || si[0] * (si[2] / 16 - 1) * (si[3] / 16 - 1) > 1,
            "training-mode BatchNorm needs more than one value per channel in the last layer: use a batch of 2 or inputs larger than 32x32 (got {si:?})"
        );
        let s = crate::precision::forward(image.device(), || {
            let x = Tensor::cat(&[image, photo], 1);
            let mut x = leaky(&x.conv2d(&self.convs[0], Some(&self.c0_bias), [2, 2], [1, 1], [1, 1], 1), SLOPE);
            for i in 1..5 {
                let stride = if i < 4 { 2 } else { 1 };
                x = x.conv2d(&self.convs[i], None::<&Tensor>, [stride, stride], [1, 1], [1, 1], 1);
                x = leaky(&self.bns[i - 1].forward_t(&x, train), SLOPE);
            }
            let (pooled, _) = x.adaptive_max_pool2d([2, 2]);
            pooled.conv2d(&self.score, Some(&self.score_bias), [1, 1], [0, 0], [1, 1], 1)
        });
        Ok(crate::precision::to_f32(s).flatten(1, -1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_shapes_and_errors() {
        let cfg = ModelConfig::tiny();
        let (vs, d) = Discriminator::with_store(&cfg, Device::Cpu);
        assert!(vs.variables().keys().any(|k| k == "disc.c1_bn.running_mean"));
        for (h, w) in [(64, 64), (96, 128), (32, 32)] {
            let img = Tensor::randn([2, 3, h, w], (tch::Kind::Float, Device::Cpu));
            let out = d.forward_t(&img, &img.rand_like(), true).unwrap();
            assert_eq!(out.size(), [2, 1], "{h}x{w}");
            let out = d.forward_t(&img, &img.rand_like(), false).unwrap();
            assert_eq!(out.size(), [2, 1]);
        }
        let one = Tensor::zeros([1, 3, 32, 32], (tch::Kind::Float, Device::Cpu));
        assert!(d.forward_t(&one, &one, true).is_err());
        assert_eq!(d.forward_t(&one, &one, false).unwrap().size(), [1, 1]);
        let small = Tensor::zeros([1, 3, 16, 16], (tch::Kind::Float, Device::Cpu));
        assert!(d.forward_t(&small, &small, false).unwrap_err().to_string().contains("32x32"));
    }

    #[test]
    fn paper_width_reaches_512() {
        let vs = nn::VarStore::new(Device::Cpu);
        let d = Discriminator::new(&vs.root(), &ModelConfig::paper());
        let outs: Vec<i64> = d.convs.iter().map(|w| w.size()[0]).collect();
        assert_eq!(outs, [64, 128, 256, 512, 512]);
    }
}
