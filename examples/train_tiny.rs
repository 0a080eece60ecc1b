//! Train the tiny preset for 50 steps on procedural materials through the
//! library API, then estimate a held-out material with the result:
//!
//! ```sh
//! cargo run --release --example train_tiny -- [RUN_DIR]   # default: a temporary folder
//! ```
//!
//! `flashmat train --preset tiny --steps 50 --out DIR` does the same from the
//! command line (docs/TRAINING.md has the real recipes).

use anyhow::Result;
use flashmat::model::ModelConfig;
use flashmat::train::config::TrainConfig;
use flashmat::train::run::{self, RunOptions};

fn main() -> Result<()> {
    let temp = tempfile::tempdir()?;
    let dir = std::env::args().nth(1).map_or_else(|| temp.path().join("run"), Into::into);
    let config = TrainConfig {
        model: ModelConfig::tiny(),
        crop: 32,
        material_size: 64,
        outputs_per_material: 2,
        steps: 50,
        checkpoint_every: 50,
        preview_every: 0,
        seed: 1,
        ..TrainConfig::default()
    };
    let trainer = run::start(config, &RunOptions::new(&dir, tch::Device::Cpu, true))?; // trains, checkpoints, logs

    let log = run::read_log(&dir);
    let (first, last) = (log.first().unwrap(), log.last().unwrap());
    println!("{} steps: L1 of log renders {:.4} (step {}) -> {:.4} (step {})", log.len(), first.l1, first.step, last.l1, last.step);

    // The trained model estimates a material it has not seen.
    let material = flashmat::data::procedural::test_material(0, 64);
    let photo = flashmat::eval::input_photo(&material, false); // its co-located GGX render [3, H, W]
    let x = flashmat::data::samples::photo_est_input(&photo, false, tch::Device::Cpu);
    let neural_map = trainer.model.est_inference(&x)?;
    println!("neural map of a held-out material: {:?}, run folder {}", neural_map.size(), dir.display());
    Ok(())
}
