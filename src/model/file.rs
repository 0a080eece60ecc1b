//! The exported-model file format, for every method: a checksummed
//! safetensors archive (see [`crate::archive`]) tagged `flashmat-model`, with
//! the weights and, in the metadata, the method's name, the model id, the
//! configuration (TOML) and [`ModelInfo`] (JSON). `model` (flashmat's own
//! network) and `baselines` both read and write through here; the method is
//! a name, so this module knows no method but flashmat's.

use super::config::ModelConfig;
use crate::archive::Archive;
use anyhow::{bail, ensure, Context, Result};
use std::collections::BTreeMap;
use std::path::Path;
use tch::Tensor;

/// Format tag and version of exported model files.
pub const MODEL_FORMAT: &str = "flashmat-model";
pub const MODEL_VERSION: u32 = 1;

/// Metadata key naming the method (absent in files written before the
/// baselines existed: those are flashmat models).
pub const METHOD_KEY: &str = "method";

/// The method name of flashmat's own model (M_est + ND_enc + M_render).
pub const FLASHMAT_METHOD: &str = "flashmat";

/// What a model file records besides weights.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ModelInfo {
    /// Trained on LDR (clamped) input photos.
    pub ldr_input: bool,
    /// Training steps completed.
    pub steps: u64,
}

/// Writes an exported-model file: the weights (large ones as f16 when
/// `half`), the method, model id, configuration and `info` in the metadata.
pub fn save_model_file(path: &Path, weights: Vec<(String, Tensor)>, method: &str, model_id: &str, config: &ModelConfig, info: &ModelInfo, half: bool) -> Result<()> {
    let mut a = Archive { store_half: half, ..Archive::new() };
    for (name, t) in weights {
        a.insert(name, &t);
    }
    a.set_meta(METHOD_KEY, method);
    a.set_meta("model_id", model_id);
    a.set_meta("config", config.to_toml_string()?);
    a.set_meta("info", serde_json::to_string(info)?);
    a.save(path, MODEL_FORMAT, MODEL_VERSION)
}

/// A model file read whole: the archive (weights), and what its metadata
/// records. The caller builds the network the method and configuration
/// name, then checks [`ModelFile::model_id`] against it.
pub struct ModelFile {
    pub archive: Archive,
    pub method: String,
    pub config: ModelConfig,
    pub info: ModelInfo,
    pub model_id: String,
}

impl ModelFile {
    /// Reads and checks a model file; damaged, truncated or foreign files
    /// are refused naming the file.
    pub fn load(path: &Path) -> Result<Self> {
        let archive = Archive::load(path, MODEL_FORMAT, MODEL_VERSION)?;
        let ctx = || format!("model file {}", path.display());
        let method = archive.metadata.get(METHOD_KEY).cloned().unwrap_or_else(|| FLASHMAT_METHOD.to_string());
        let config = ModelConfig::from_toml_str(archive.meta("config").with_context(ctx)?).with_context(ctx)?;
        let info: ModelInfo = serde_json::from_str(archive.meta("info").with_context(ctx)?).with_context(ctx)?;
        let model_id = archive.meta("model_id").with_context(ctx)?.to_string();
        Ok(Self { archive, method, config, info, model_id })
    }
}

/// The method name recorded in a model file, read from the safetensors
/// header only (no weights); files without the field are flashmat models.
/// Files that are not readable model files give an error.
pub fn recorded_method(path: &Path) -> Result<String> {
    let meta = read_header_metadata(path)?;
    match meta.get("flashmat.format") {
        Some(f) if f == MODEL_FORMAT => {}
        _ => bail!("{} is not a flashmat model file", path.display()),
    }
    Ok(meta.get(METHOD_KEY).cloned().unwrap_or_else(|| FLASHMAT_METHOD.to_string()))
}

/// The `__metadata__` of a safetensors file's JSON header (8-byte
/// little-endian length, then the header).
pub fn read_header_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len).with_context(|| format!("{}: too short for a model file", path.display()))?;
    let len = u64::from_le_bytes(len);
    ensure!(len <= 100_000_000, "{}: not a safetensors file", path.display());
    let mut header = vec![0u8; len as usize];
    f.read_exact(&mut header).with_context(|| format!("{}: truncated header", path.display()))?;
    let v: serde_json::Value = serde_json::from_slice(&header).with_context(|| format!("{}: unreadable header", path.display()))?;
    let meta = v.get("__metadata__").and_then(|m| m.as_object()).cloned().unwrap_or_default();
    Ok(meta.into_iter().filter_map(|(k, v)| v.as_str().map(|s| (k, s.to_string()))).collect())
}
