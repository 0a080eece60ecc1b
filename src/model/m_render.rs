//! M_render: the per-pixel neural BRDF MLP (REFERENCE section 4).
//!
//! concat(neural params (64), direction code (32)) = 96 -> 128 -> 128 ->
//! 128 -> 128 -> 128 -> 64 -> 3, no biases, Xavier-uniform init. No
//! activation between the first two layers, LeakyReLU(0.01) after the
//! others, LeakyReLU(0.001) at the end. Output: ln(1 + R) with R including
//! the cosine foreshortening.
//!
//! Evaluated on channels-last rows (`[..., features]`) with matmuls: for
//! a 256x256 frame at paper size this took 0.16 s against 0.36 s as 1x1
//! convolutions (2-core CPU); activations run in place (safe for autograd:
//! a linear layer's backward does not read its output). The first layer is
//! split into its parameter and direction halves so a
//! neural map is projected once per pixel and broadcast over the K
//! light/view configurations instead of being copied K times.

use super::config::ModelConfig;
use tch::nn::{self, Init};
use std::sync::atomic::{AtomicBool, Ordering};
use tch::Tensor;

/// Slope of the hidden activations.
pub const RENDER_SLOPE: f64 = 0.01;
/// Slope of the final activation.
pub const RENDER_FINAL_SLOPE: f64 = 0.001;

#[derive(Debug)]
pub struct MRender {
    /// Weights `[out, in]` of the seven linear layers.
    pub layers: Vec<Tensor>,
    pub neural_channels: i64,
    /// Training only: the final LeakyReLU(0.001) passes its gradient
    /// unscaled below zero (straight-through; forward values unchanged).
    /// With the paper's slope an L1 loss pulls outputs down 1000x harder
    /// than it pushes them up from below zero, and on dark training renders
    /// the renderer settles on "everything is black" within ~50 steps.
    pub straight_through_output: AtomicBool,
}

/// Xavier-uniform bound sqrt(6 / (fan_in + fan_out)).
pub fn xavier_bound(fan_in: i64, fan_out: i64) -> f64 {
    (6.0 / (fan_in + fan_out) as f64).sqrt()
}

impl MRender {
    /// Layer widths: neural + enc_out, hidden x5, narrow, 3.
    pub fn widths(cfg: &ModelConfig) -> Vec<i64> {
        let h = cfg.render_hidden;
        vec![cfg.neural_channels + cfg.enc_out, h, h, h, h, h, cfg.render_narrow, 3]
    }

    /// Variables `<p>.0.weight` .. `<p>.6.weight`.
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Self {
        let w = Self::widths(cfg);
        let layers = (0..w.len() - 1)
            .map(|i| {
                let b = xavier_bound(w[i], w[i + 1]);
                (p / i).var("weight", &[w[i + 1], w[i]], Init::Uniform { lo: -b, up: b })
            })
            .collect();
        Self { layers, neural_channels: cfg.neural_channels, straight_through_output: AtomicBool::new(false) }
    }

    /// Width of the direction code the first layer expects.
    pub fn code_width(&self) -> i64 {
        self.layers[0].size()[1] - self.neural_channels
    }

    /// params: `[..., neural_channels]`, code: `[..., enc_out]` (leading
    /// dimensions broadcast against each other) -> ln(1 + R) `[..., 3]`.
    pub fn forward(&self, params: &Tensor, code: &Tensor) -> Tensor {
        let c = self.neural_channels;
        let w0 = &self.layers[0];
        let e = w0.size()[1] - c;
        let mut x = params.linear(&w0.narrow(1, 0, c), None::<&Tensor>) + code.linear(&w0.narrow(1, c, e), None::<&Tensor>);
        let last = self.layers.len() - 1;
        for (i, w) in self.layers.iter().enumerate().skip(1) {
            x = x.linear(w, None::<&Tensor>);
            x = if i == last { self.output_activation(&x) } else { x.leaky_relu_() };
        }
        x
    }

    /// The final LeakyReLU(0.001); straight-through below zero when training
    /// asks for it ([`Self::straight_through_output`]).
    fn output_activation(&self, x: &Tensor) -> Tensor {
        let y = super::layers::leaky(x, RENDER_FINAL_SLOPE);
        if self.straight_through_output.load(Ordering::Relaxed) && x.requires_grad() {
            x + (y - x).detach()
        } else {
            y
        }
    }

    /// Multiply-adds x 2 per row (first layer counted in full).
    pub fn flops_per_row(cfg: &ModelConfig) -> f64 {
        let w = Self::widths(cfg);
        2.0 * w.windows(2).map(|p| (p[0] * p[1]) as f64).sum::<f64>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn param_count_and_xavier_bounds() {
        let vs = nn::VarStore::new(Device::Cpu);
        let m = MRender::new(&vs.root(), &ModelConfig::paper());
        let n: i64 = vs.trainable_variables().iter().map(|t| t.numel() as i64).sum();
        assert_eq!(n, 86_208);
        for w in &m.layers {
            let s = w.size();
            let b = xavier_bound(s[1], s[0]);
            let max = w.abs().max().double_value(&[]);
            assert!(max <= b, "{s:?}: {max} > {b}");
            // Uniform on [-b, b]: the largest of thousands of draws is near b,
            // and the variance is b^2 / 3.
            if w.numel() > 1000 {
                assert!(max > 0.95 * b);
                let var = w.square().mean(w.kind()).double_value(&[]);
                assert!((var / (b * b / 3.0) - 1.0).abs() < 0.1, "variance {var}");
            }
        }
    }
}
