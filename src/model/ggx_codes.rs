//! The per-pixel GGX encoder: 10 GGX values of a pixel (kd, ks,
//! roughness, normal: REFERENCE section 2) -> a neural-map code. The
//! teacher of the training curriculum (`train::teacher`) learns it with its
//! renderer; a model with [`ModelConfig::ggx_codes`] carries a frozen copy
//! behind M_est's head, so M_est writes GGX values and the neural map holds
//! only codes a GGX pixel has (issue 48: M_est's own codes did not tell a
//! matte pixel from a glossy one, and the teacher's renderer draws the moved
//! highlight from the teacher's codes).
//!
//! [`ModelConfig::ggx_codes`]: super::ModelConfig::ggx_codes

use super::layers::leaky;
use super::ModelConfig;
use crate::archive::{restore_vars, Archive};
use anyhow::{anyhow, ensure, Result};
use std::collections::HashMap;
use std::path::Path;
use tch::{nn, Device, Tensor};

/// Format tag and version of a teacher file (`train::teacher` writes it:
/// the encoder under `teacher/`, ND_enc + M_render under `renderer/`, the
/// renderer's `model_id` and the recipe `teacher_config` (JSON, its `model`
/// field the renderer's [`ModelConfig`]) in the metadata).
pub const TEACHER_FORMAT: &str = "flashmat-teacher";
pub const TEACHER_VERSION: u32 = 1;

/// What a teacher file holds for its users outside training: the frozen
/// encoder and the renderer's weights.
pub struct TeacherWeights {
    /// The renderer's configuration (the `compact` preset for the committed teacher).
    pub config: ModelConfig,
    /// Holds the encoder's variables (frozen).
    pub vs: nn::VarStore,
    pub encoder: GgxEncoder,
    /// ND_enc + M_render, named as in `Model::renderer_vs` (`renderer.nd_enc.*`, `renderer.m_render.*`).
    pub renderer: HashMap<String, Tensor>,
}

impl TeacherWeights {
    /// Reads a teacher file; its renderer's configuration comes from the
    /// file (and must agree with its `model_id`). Errors are one line
    /// naming the file.
    pub fn load(path: &Path, device: Device) -> Result<Self> {
        let a = Archive::load(path, TEACHER_FORMAT, TEACHER_VERSION)?;
        let recipe: serde_json::Value =
            serde_json::from_str(a.meta("teacher_config")?).map_err(|e| anyhow!("{}: unreadable teacher_config: {e}", path.display()))?;
        let config: ModelConfig = serde_json::from_value(recipe.get("model").cloned().unwrap_or_default())
            .map_err(|e| anyhow!("{}: unreadable model configuration in teacher_config: {e}", path.display()))?;
        let id = a.meta("model_id")?;
        ensure!(id == config.model_id(), "{}: model_id '{id}' does not match its configuration ('{}')", path.display(), config.model_id());
        Self::load_for(path, &a, config, device)
    }

    /// The weights of an opened teacher archive for a renderer of `config`
    /// (the caller checked the file's `model_id`).
    pub fn load_for(path: &Path, a: &Archive, config: ModelConfig, device: Device) -> Result<Self> {
        let mut vs = nn::VarStore::new(device);
        let encoder = GgxEncoder::new(&(vs.root() / "teacher"), config.neural_channels);
        restore_vars(&vs.variables(), &a.with_prefix("teacher/"), &format!("{}: teacher encoder", path.display()))?;
        vs.freeze();
        Ok(Self { config, vs, encoder, renderer: a.with_prefix("renderer/") })
    }
}

/// GGX values per pixel: kd (3), ks (3), roughness (1), normal (3).
pub const GGX_CHANNELS: i64 = 10;

/// Hidden width of the encoder.
const HIDDEN: i64 = 128;

/// Slope of the encoder's LeakyReLUs.
const SLOPE: f64 = 0.01;

/// 10 GGX values -> 128 -> 128 -> C, LeakyReLU(0.01), no biases.
#[derive(Debug)]
pub struct GgxEncoder {
    layers: Vec<nn::Linear>,
}

impl GgxEncoder {
    /// Trainable variables `l0`, `l1`, `l2` under `p`.
    pub fn new(p: &nn::Path, channels: i64) -> Self {
        let cfg = nn::LinearConfig { bias: false, ..Default::default() };
        let dims = [GGX_CHANNELS, HIDDEN, HIDDEN, channels];
        let layers = dims.windows(2).enumerate().map(|(i, d)| nn::linear(p / format!("l{i}"), d[0], d[1], cfg)).collect();
        Self { layers }
    }

    /// The same variables, never trained (no gradient, no optimizer): the
    /// code space a model's renderer was trained on is the teacher's.
    pub fn frozen(p: &nn::Path, channels: i64) -> Self {
        let e = Self::new(p, channels);
        for l in &e.layers {
            let _ = l.ws.shallow_clone().set_requires_grad(false);
        }
        e
    }

    /// The weights, first layer first: `[out, in]` each.
    pub fn weights(&self) -> Vec<Tensor> {
        self.layers.iter().map(|l| l.ws.shallow_clone()).collect()
    }

    /// rows: `[R, 10]` -> codes `[R, C]`.
    pub fn forward_rows(&self, rows: &Tensor) -> Tensor {
        forward_rows_with(&self.weights(), rows)
    }

    /// maps: `[N, 10, H, W]` -> codes `[N, C, H, W]`.
    pub fn forward_maps(&self, maps: &Tensor) -> Tensor {
        forward_maps_with(&self.weights(), maps)
    }
}

/// The least normal z [`valid_values`] leaves: a normal kept facing the
/// camera, as every normal of the data is.
pub const MIN_NORMAL_Z: f64 = 0.1;

/// GGX values projected onto the data's ranges: kd and ks clamped to
/// [0, 1], roughness to [`MIN_ROUGHNESS`], 1], the normal's z to at least
/// [`MIN_NORMAL_Z`] and the normal made unit length. M_est's head is an
/// unbounded convolution, and trained heads write values no GGX pixel has
/// (held-out photos: roughness up to 2.5 and below 0, ks below 0, normals
/// of length 3; reports/highlights-experiments.md section 8), where the
/// encoder can only extrapolate. Values in range pass unchanged.
/// values: `[N, 10, ...]` (rows `[R, 10]` or maps `[N, 10, H, W]`).
///
/// [`MIN_ROUGHNESS`]: crate::data::procedural::MIN_ROUGHNESS
pub fn valid_values(values: &Tensor) -> Tensor {
    let r = crate::svbrdf::ROUGHNESS_CHANNEL; // kd and ks before it, the normal after
    let albedos = values.narrow(1, 0, r).clamp(0.0, 1.0);
    let roughness = values.narrow(1, r, 1).clamp(crate::data::procedural::MIN_ROUGHNESS as f64, 1.0);
    let normal = Tensor::cat(&[values.narrow(1, r + 1, 2), values.narrow(1, r + 3, 1).clamp_min(MIN_NORMAL_Z)], 1);
    let length = normal.square().sum_dim_intlist([1i64].as_slice(), true, normal.kind()).sqrt();
    Tensor::cat(&[albedos, roughness, normal / length], 1)
}

/// The encoder of `weights` (`[out, in]` each, as [`GgxEncoder::weights`])
/// on rows `[R, 10]` -> codes `[R, C]` (gradients reach the weights).
pub fn forward_rows_with(weights: &[Tensor], rows: &Tensor) -> Tensor {
    layers(weights, rows, |x, w| x.matmul(&w.tr()))
}

/// The encoder of `weights` (`[out, in]` each, as [`GgxEncoder::weights`])
/// on maps `[N, 10, H, W]` -> codes `[N, C, H, W]`, as 1x1 convolutions
/// (any memory order).
pub fn forward_maps_with(weights: &[Tensor], maps: &Tensor) -> Tensor {
    layers(weights, maps, |x, w| {
        let s = w.size();
        x.conv2d(&w.view([s[0], s[1], 1, 1]), None::<Tensor>, [1, 1], [0, 0], [1, 1], 1)
    })
}

/// The encoder's layers on `x`, each applied by `linear(x, w)` (rows or
/// 1x1 convs), LeakyReLU between them.
fn layers(weights: &[Tensor], x: &Tensor, linear: impl Fn(&Tensor, &Tensor) -> Tensor) -> Tensor {
    let last = weights.len() - 1;
    weights.iter().enumerate().fold(x.shallow_clone(), |x, (i, w)| {
        let y = linear(&x, w);
        if i < last {
            leaky(&y, SLOPE)
        } else {
            y
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn maps_and_rows_agree_and_frozen_weights_take_no_gradient() {
        tch::manual_seed(3);
        let vs = nn::VarStore::new(Device::Cpu);
        let e = GgxEncoder::frozen(&(vs.root() / "g"), 5);
        assert_eq!(vs.variables().len(), 3);
        assert!(vs.variables().values().all(|t| !t.requires_grad()));
        let maps = Tensor::randn([2, GGX_CHANNELS, 3, 4], (Kind::Float, Device::Cpu));
        let codes = e.forward_maps(&maps);
        assert_eq!(codes.size(), [2, 5, 3, 4]);
        // Pixel (1, :, 2, 3) by rows.
        let row = maps.select(0, 1).select(1, 2).select(1, 3).view([1, GGX_CHANNELS]);
        let by_row = e.forward_rows(&row).view([5]);
        let d = (by_row - codes.select(0, 1).select(1, 2).select(1, 3)).abs().max().double_value(&[]);
        assert!(d < 1e-5, "1x1 convs and rows differ by {d}");
        // Projection: values in range pass; out of range they are brought in.
        let inside = Tensor::from_slice(&[0.2f32, 0.3, 0.4, 0.04, 0.04, 1.0, 0.02, 0.6, 0.0, 0.8]).view([1, GGX_CHANNELS]);
        assert!((valid_values(&inside) - &inside).abs().max().double_value(&[]) < 1e-7);
        let outside = Tensor::from_slice(&[-0.2f32, 0.3, 1.4, 0.04, -0.1, 1.2, -0.07, 0.0, 0.0, 2.0]).view([1, GGX_CHANNELS]);
        let want = Tensor::from_slice(&[0.0f32, 0.3, 1.0, 0.04, 0.0, 1.0, 0.02, 0.0, 0.0, 1.0]).view([1, GGX_CHANNELS]);
        assert!((valid_values(&outside) - want).abs().max().double_value(&[]) < 1e-7);
        // A normal pointing away: z raised to 0.1, then unit: (0.6, 0, 0.1) / |.|.
        let away = Tensor::from_slice(&[0.5f32, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.6, 0.0, -0.8]).view([1, GGX_CHANNELS]);
        let n = valid_values(&away).narrow(1, 7, 3);
        let len = (0.36f64 + 0.01).sqrt();
        assert!((n - Tensor::from_slice(&[(0.6 / len) as f32, 0.0, (0.1 / len) as f32]).view([1, 3])).abs().max().double_value(&[]) < 1e-6);
        // Linear in a positive scale of its input (no biases, LeakyReLU).
        let twice = e.forward_maps(&(&maps * 2.0));
        assert!((twice - &codes * 2.0).abs().max().double_value(&[]) < 1e-4);
    }
}
