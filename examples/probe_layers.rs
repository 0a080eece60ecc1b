//! Where in M_est does the colour go? Feeds the matte uniform colours of
//! `flashmat eval --uniform` (64x64, co-located flash, as the model sees
//! them) through M_est in inference mode and prints, at every stage, how
//! far apart the colours' mean activation vectors are, relative to the
//! activations' size (issue 15, `reports/curriculum.md`).
//!
//! A "separation" of 1 means two colours' mean features differ by as much
//! as a typical feature vector is long; a stage where it drops is where the
//! chroma is lost. The input row is ln(1 + RGB), h_z itself.
//!
//! ```sh
//! cargo run --release --example probe_layers -- [MODEL_FILE]
//! ```

use anyhow::Result;
use flashmat::data::samples::photo_est_input;
use flashmat::geometry::LightView;
use flashmat::infer::load_model;
use tch::{Kind, Tensor};

/// Mean activation `[C]` of a `[1, C, H, W]` tensor.
fn mean_features(x: &Tensor) -> Tensor {
    x.mean_dim(&[0i64, 2, 3][..], false, Kind::Float)
}

fn main() -> Result<()> {
    let path = std::env::args().nth(1).map(std::path::PathBuf::from);
    let loaded = load_model(path.as_deref(), tch::Device::Cpu)?;
    let est = &loaded.model.est;
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let names = ["red", "green", "blue", "grey", "wood"];
    // stage name -> per-colour mean features
    let mut stages: Vec<(String, Vec<Tensor>)> = vec![];
    let mut push = |stage: &str, colour: usize, t: &Tensor| {
        if colour == 0 {
            stages.push((stage.to_string(), vec![]));
        }
        let i = stages.iter().position(|(s, _)| s == stage).expect("stage seen for the first colour");
        stages[i].1.push(mean_features(t));
    };
    let _guard = tch::no_grad_guard();
    for (set, u) in flashmat::eval::uniform::uniform_materials() {
        if set != "matte" {
            continue;
        }
        let Some(ci) = names.iter().position(|n| *n == u.name) else { continue };
        let m = flashmat::svbrdf::Svbrdf::uniform(64, 64, u.diffuse, u.specular, u.roughness);
        let photo = flashmat::svbrdf::render::render_material(&m, &[identity])?;
        let x = photo_est_input(&photo[0].to_tensor(), loaded.info.ldr_input, tch::Device::Cpu);
        push("input ln(1+RGB),h_z", ci, &x);
        let _map = est.forward_traced(&x, false, Some(&mut |name: &str, t: &Tensor| push(name, ci, t)))?;
    }
    println!("separation = |mean(a) - mean(b)| / mean |mean(c)| over the colours");
    println!("{:22} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9}", "stage", "red-green", "red-blue", "green-blue", "red-wood", "red-grey", "|feature|");
    for (stage, f) in &stages {
        let norm = f.iter().map(|t| t.norm().double_value(&[])).sum::<f64>() / f.len() as f64;
        let d = |a: usize, b: usize| (&f[a] - &f[b]).norm().double_value(&[]) / norm;
        println!("{:22} {:9.3} {:9.3} {:9.3} {:9.3} {:9.3} {:9.3}", stage, d(0, 1), d(0, 2), d(1, 2), d(0, 4), d(0, 3), norm);
    }
    Ok(())
}
