//! Drops the high frequencies of a model's direction encoding: the first
//! ND_enc layer keeps its columns for v and for sin/cos(2^k pi v) with
//! k < N (`Model::truncate_frequencies`), and the model is saved with the
//! configuration of a preset or TOML file that differs from the model's
//! only in its frequencies and name (a new model id; every consumer reads
//! the count from the file). Issue 15: at directions whose components are
//! dyadic rationals (0 at co-location along the normal, then 1/2, 1/4, ...)
//! every cos(2^k pi v) of high k is 1 at once, so weights that cancel
//! elsewhere add up: the spike and the rings (`reports/frequencies.md`).
//!
//! A configuration that adds the log half-angle feature (`compact-f8h`)
//! also gets its ND_enc column, zero (`Model::with_half_angle_feature`):
//! the renders stay the model's until training moves it.
//!
//! ```sh
//! cargo run --release --example truncate_frequencies -- target/gpu-25650.safetensors compact-f8 target/gpu-25650-f8.safetensors
//! cargo run --release --example truncate_frequencies -- models/flashmat.safetensors compact-f8h target/f8h-start.safetensors
//! ```

use anyhow::{ensure, Result};
use flashmat::model::{Model, ModelConfig};
use tch::Device;

fn main() {
    // One error line and a non-zero exit for bad input, never a backtrace.
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    ensure!(args.len() == 4, "usage: truncate_frequencies MODEL_IN CONFIG.toml|PRESET MODEL_OUT");
    let (model, info) = Model::load(&args[1], Device::Cpu)?;
    let config = match ModelConfig::preset(&args[2]) {
        Ok(preset) => preset,
        Err(_) => ModelConfig::from_toml_file(std::path::Path::new(&args[2]))?,
    };
    let truncated = if config.half_angle_feature && !model.config.half_angle_feature {
        let plain = ModelConfig { half_angle_feature: false, ..config.clone() };
        model.truncate_frequencies(&plain)?.with_half_angle_feature(&config.name)?
    } else {
        model.truncate_frequencies(&config)?
    };
    truncated.save(&args[3], &info, true)?;
    eprintln!("wrote {} ({} -> {} frequencies, model {})", args[3], model.config.enc_frequencies, config.enc_frequencies, truncated.model_id());
    Ok(())
}
