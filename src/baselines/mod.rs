//! The two trained baselines of the paper's comparison table (issue 5),
//! built from M_est's highlight-aware U-Net at the same width presets and
//! trained on the same batches with the same losses as flashmat:
//!
//! - [`analytic`]: the U-Net predicts the GGX SVBRDF maps (the family of
//!   Deschaintre 2018, Zhou 2021, MatFusion), trained through the tensor
//!   GGX renderer and relit with it at evaluation time.
//! - [`relight`]: a U-Net that predicts the relit image itself (Bieron
//!   2023): the photo goes through the encoder, the per-pixel light/view
//!   directions, encoded as ND_enc does, are injected into every decoder
//!   stage; there are no per-pixel material parameters.
//!
//! [`TrainMethod`] names the three trainable methods (`flashmat` and these
//! two); a [`Baseline`] holds either network with its VarStore and reads and
//! writes exported model files (the `flashmat-model` format, with a
//! `method` metadata field that flashmat model files also carry).

pub mod analytic;
pub mod relight;

pub use analytic::AnalyticNet;
pub use relight::{RelightEncoded, RelightUNet};

use crate::model::file::{self, ModelFile, ModelInfo};
use crate::model::{count_trainable, ModelConfig};
use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;
use tch::{nn, Device, Tensor};

/// What `flashmat train --method` trains.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum TrainMethod {
    /// M_est + ND_enc + M_render (the paper).
    #[default]
    Flashmat,
    /// U-Net -> GGX SVBRDF maps, rendering loss through the GGX renderer.
    Analytic,
    /// U-Net with light/view injected into the decoder -> relit image.
    RelightUnet,
}

impl TrainMethod {
    /// The name used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            Self::Flashmat => file::FLASHMAT_METHOD,
            Self::Analytic => "analytic",
            Self::RelightUnet => "relight-unet",
        }
    }

    /// Parses [`TrainMethod::name`].
    pub fn from_name(s: &str) -> Result<Self> {
        match s {
            "flashmat" => Ok(Self::Flashmat),
            "analytic" => Ok(Self::Analytic),
            "relight-unet" => Ok(Self::RelightUnet),
            other => bail!("unknown method '{other}' (known: flashmat, analytic, relight-unet)"),
        }
    }

    pub fn is_flashmat(&self) -> bool {
        *self == Self::Flashmat
    }
}

impl std::fmt::Display for TrainMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Either baseline network.
#[derive(Debug)]
pub enum BaselineNet {
    Analytic(AnalyticNet),
    Relight(RelightUNet),
}

/// A baseline network with its variables (`net.*`) and sizes.
#[derive(Debug)]
pub struct Baseline {
    pub method: TrainMethod,
    /// The width preset the U-Net follows (`est_width`; the relighting
    /// U-Net's direction code also uses `enc_frequencies`, `enc_hidden`
    /// and `enc_out`).
    pub config: ModelConfig,
    pub vs: nn::VarStore,
    pub net: BaselineNet,
}

impl Baseline {
    /// Fresh, randomly initialised network (libtorch's global generator).
    pub fn new(method: TrainMethod, config: &ModelConfig, device: Device) -> Result<Self> {
        config.validate()?;
        let vs = nn::VarStore::new(device);
        let root = vs.root() / "net";
        let net = match method {
            TrainMethod::Flashmat => bail!("flashmat is not a baseline (use model::Model)"),
            TrainMethod::Analytic => BaselineNet::Analytic(AnalyticNet::new(&root, config)?),
            TrainMethod::RelightUnet => BaselineNet::Relight(RelightUNet::new(&root, config)?),
        };
        Ok(Self { method, config: config.clone(), vs, net })
    }

    /// `METHOD/MODEL_ID` of the width configuration; checkpoints and model
    /// files record it so weights of another method or size are refused.
    pub fn model_id(&self) -> String {
        format!("{}/{}", self.method, self.config.model_id())
    }

    pub fn device(&self) -> Device {
        self.vs.device()
    }

    /// Trainable parameters.
    pub fn param_count(&self) -> i64 {
        count_trainable(&self.vs)
    }

    /// Renders the output configurations of a batch in log space.
    /// est_input: `[N, 4, H, W]` (ln(1 + photo), h_z); wi, wo:
    /// `[N, K, 3, H, W]` unit vectors -> ln(1 + R) `[N, K, 3, H, W]`.
    /// `train` selects BatchNorm batch statistics.
    pub fn forward_t(&self, est_input: &Tensor, wi: &Tensor, wo: &Tensor, train: bool) -> Result<Tensor> {
        match &self.net {
            BaselineNet::Analytic(a) => a.render_log_t(est_input, wi, wo, train),
            BaselineNet::Relight(r) => r.forward_t(est_input, wi, wo, train),
        }
    }

    /// Every variable (BatchNorm statistics included), sorted by name.
    pub fn named_variables(&self) -> Vec<(String, Tensor)> {
        let mut v: Vec<(String, Tensor)> = self.vs.variables().into_iter().collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    /// Writes an exported baseline model: `net.*` weights, and in the
    /// metadata the method, model id, width configuration and `info`.
    /// `half` stores large weight tensors as f16 (as flashmat exports do).
    pub fn save(&self, path: impl AsRef<Path>, info: &ModelInfo, half: bool) -> Result<()> {
        file::save_model_file(path.as_ref(), self.named_variables(), self.method.name(), &self.model_id(), &self.config, info, half)
    }

    /// Reads a file written by [`Baseline::save`]. Flashmat model files,
    /// damaged files and missing, extra or mis-shaped weights are refused
    /// naming the file.
    pub fn load(path: impl AsRef<Path>, device: Device) -> Result<(Self, ModelInfo)> {
        let path = path.as_ref();
        let ctx = || format!("model file {}", path.display());
        let f = ModelFile::load(path)?;
        let method = TrainMethod::from_name(&f.method).with_context(ctx)?;
        ensure!(!method.is_flashmat(), "{} holds a flashmat model, not a baseline", ctx());
        let b = Self::new(method, &f.config, device)?;
        ensure!(f.model_id == b.model_id(), "{}: model id does not match its configuration", ctx());
        crate::archive::restore_vars(&b.vs.variables(), &f.archive.with_prefix(""), &ctx())?;
        let info = f.info;
        Ok((b, info))
    }
}

/// The method recorded in a model file's metadata, read from the
/// safetensors header only (no weights). Files without the field are
/// flashmat models. Files that are not readable model files give an error
/// (callers may then let the full loader report it).
pub fn file_method(path: &Path) -> Result<TrainMethod> {
    let name = file::recorded_method(path)?;
    TrainMethod::from_name(&name).with_context(|| format!("model file {}", path.display()))
}

#[cfg(test)]
mod tests;
