//! Small building blocks shared by the networks: bias-free convolutions
//! with replicate padding, transposed convolutions, BatchNorm with its
//! eval-mode affine form (for folding), and activations.

use tch::nn::{self, Init};
use tch::Tensor;

/// BatchNorm epsilon (PyTorch's default).
pub const BN_EPS: f64 = 1e-5;

/// LeakyReLU with any slope. `Tensor::leaky_relu` only offers 0.01.
pub fn leaky(x: &Tensor, slope: f64) -> Tensor {
    if slope == 0.01 {
        x.leaky_relu()
    } else {
        // max(x, slope x) equals LeakyReLU for 0 <= slope <= 1.
        x.maximum(&(x * slope))
    }
}

/// Kaiming-normal (fan-out, ReLU gain) conv init: the ResNet convention.
pub fn conv_init() -> Init {
    Init::Kaiming { dist: nn::init::NormalOrUniform::Normal, fan: nn::init::FanInOut::FanOut, non_linearity: nn::init::NonLinearity::ReLU }
}

/// U(-1/sqrt(fan_in), 1/sqrt(fan_in)): PyTorch's default for convolutions
/// and linear layers (kaiming_uniform with a = sqrt(5)).
pub fn torch_default_init() -> Init {
    Init::Kaiming {
        dist: nn::init::NormalOrUniform::Uniform,
        fan: nn::init::FanInOut::FanIn,
        non_linearity: nn::init::NonLinearity::ExplicitGain(1.0 / 3f64.sqrt()),
    }
}

/// Replicate-pads by `p` on every side. x: `[N, C, H, W]` -> `[N, C, H+2p, W+2p]`.
pub fn pad_rep(x: &Tensor, p: i64) -> Tensor {
    if p == 0 {
        x.shallow_clone()
    } else {
        x.pad([p, p, p, p], "replicate", None)
    }
}

/// Unpadded convolution of an already padded input.
/// x: `[N, C, H, W]`, w: `[P, C, k, k]` -> `[N, P, H', W']`.
pub fn conv(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, stride: i64) -> Tensor {
    x.conv2d(w, bias, [stride, stride], [0, 0], [1, 1], 1)
}

/// k x k convolution with replicate padding (k odd) of `[N, C, H, W]`.
pub fn conv_rep(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, stride: i64) -> Tensor {
    let k = w.size()[2];
    conv(&pad_rep(x, k / 2), w, bias, stride)
}

/// Transposed convolution. x: `[N, C, H, W]`, w: `[C, P, k, k]` ->
/// `[N, P, (H-1)s - 2 pad + k, ..]`.
pub fn conv_t(x: &Tensor, w: &Tensor, bias: Option<&Tensor>, stride: i64, padding: i64) -> Tensor {
    x.conv_transpose2d(w, bias, [stride, stride], [padding, padding], [0, 0], 1, [1, 1])
}

/// A 2-D BatchNorm (affine, running statistics) with stable variable names
/// `weight`, `bias`, `running_mean`, `running_var`.
#[derive(Debug)]
pub struct Bn {
    pub inner: nn::BatchNorm,
}

impl Bn {
    pub fn new(p: &nn::Path, channels: i64) -> Self {
        let cfg = nn::BatchNormConfig { eps: BN_EPS, ws_init: Init::Const(1.0), bs_init: Init::Const(0.0), ..Default::default() };
        Self { inner: nn::batch_norm2d(p, channels, cfg) }
    }

    /// x: `[N, C, H, W]`; batch statistics (and running-stat updates) when
    /// `train`, running statistics otherwise.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        nn::ModuleT::forward_t(&self.inner, x, train)
    }

    /// Eval-mode BN as y = scale * x + shift; both `[C]`, detached.
    pub fn eval_affine(&self) -> (Tensor, Tensor) {
        let b = &self.inner;
        let gamma = b.ws.as_ref().expect("affine BN").detach();
        let beta = b.bs.as_ref().expect("affine BN").detach();
        let scale = gamma * (b.running_var.detach() + BN_EPS).rsqrt();
        let shift = beta - b.running_mean.detach() * &scale;
        (scale, shift)
    }
}

/// Reshapes a `[C]` vector for broadcasting over `[N, C, H, W]`.
pub fn per_channel(v: &Tensor) -> Tensor {
    v.view([1, -1, 1, 1])
}
