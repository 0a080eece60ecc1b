//! Drops the high frequencies of a model's direction encoding: the first
//! ND_enc layer keeps its columns for v and for sin/cos(2^k pi v) with
//! k < N, and the model is saved with the configuration of a TOML file
//! that differs from the model's only in `enc_frequencies = N` and its name
//! (a new model id; every consumer reads the count from the file). Issue 15: at
//! directions whose components are dyadic rationals (0 at co-location
//! along the normal, then 1/2, 1/4, ...) every cos(2^k pi v) of high k is
//! 1 at once, so weights that cancel elsewhere add up: the spike and the
//! rings. The truncated model is a starting point for a fine-tune.
//!
//! ```sh
//! cargo run --release --example truncate_frequencies -- target/gpu-25650.safetensors models/compact-f8.toml target/gpu-25650-f8.safetensors
//! ```

use anyhow::{ensure, Context, Result};
use flashmat::model::{Model, ModelConfig};
use std::collections::HashMap;
use tch::{Device, Kind, Tensor};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    ensure!(args.len() == 4, "usage: truncate_frequencies MODEL_IN CONFIG.toml MODEL_OUT");
    let (model, info) = Model::load(&args[1], Device::Cpu)?;
    let config = ModelConfig::from_toml_file(std::path::Path::new(&args[2]))?;
    let (n, keep) = (model.config.enc_frequencies, config.enc_frequencies);
    ensure!(keep <= n, "the configuration has {keep} frequencies, the model only {n}");
    let same_otherwise = ModelConfig { name: model.config.name.clone(), enc_frequencies: n, ..config.clone() };
    ensure!(same_otherwise == model.config, "the configuration differs from the model's in more than its frequencies and name");
    let mut truncated = Model::new(&config, Device::Cpu)?;
    let mut named: HashMap<String, Tensor> = model.named_variables().into_iter().collect();
    let first = named.get("renderer.nd_enc.0.weight").context("no renderer.nd_enc.0.weight")?.to_kind(Kind::Float);
    // Columns: [v (9) | sin, k-major (n x 9) | cos (n x 9)].
    let cols = Tensor::cat(&[first.narrow(1, 0, 9 + 9 * keep), first.narrow(1, 9 + 9 * n, 9 * keep)], 1);
    named.insert("renderer.nd_enc.0.weight".into(), cols);
    truncated.load_named(&named)?;
    truncated.save(&args[3], &info, true)?;
    eprintln!("wrote {} ({} -> {keep} frequencies, model {})", args[3], n, truncated.model_id());
    Ok(())
}
