//! Issue 48: does a trained M_est's neural map carry what a lobe-drawing
//! renderer needs? The per-pixel teacher trained with lobe samples
//! (`train-teacher --lobe-share 0.5`) draws the moved highlights from the
//! true maps (`examples/teacher_ceiling.rs`); this fits the least-squares
//! linear map from a model's codes of training photos to the teacher's codes
//! of their true maps, folds it into M_est's head (a 7x7 conv with no bias,
//! so a linear map of its output is a conv of the same shape), and writes a
//! model: that M_est with the teacher's renderer. No training; the fit's
//! relative L1 (the `--code-weight` term's measure) says how much of the
//! teacher's code space the codes reach linearly, and `flashmat eval` scores
//! the result. It is also a warm start for `train --teacher` (section 5 of
//! `reports/highlights-experiments.md`).
//!
//! With `ggx` last, the target is the true maps' GGX values instead, and
//! the model written is a `compact-g` one (M_est writes GGX values, the
//! teacher's frozen encoder turns them into codes): its warm start.
//!
//! ```sh
//! cargo run --release --example code_adapter -- MODEL TEACHER OUT.safetensors [MATERIALS] [SIZE] [codes|ggx]
//! ```

use anyhow::{ensure, Context, Result};
use flashmat::data::{procedural, samples};
use flashmat::model::{Model, ModelConfig};
use flashmat::train::teacher::{self, Teacher};
use rand::SeedableRng;
use tch::{Device, Kind, Tensor};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    ensure!(args.len() >= 4, "usage: code_adapter MODEL TEACHER OUT.safetensors [MATERIALS] [SIZE] [codes|ggx]");
    let materials: usize = args.get(4).map_or(Ok(96), |s| s.parse())?;
    let size: usize = args.get(5).map_or(Ok(128), |s| s.parse())?;
    let ggx = match args.get(6).map(String::as_str) {
        None | Some("codes") => false,
        Some("ggx") => true,
        Some(other) => anyhow::bail!("target '{other}': expected codes or ggx"),
    };
    let dev = Device::Cpu;
    let (source, info) = Model::load(&args[1], dev)?;
    ensure!(info.ldr_input, "{}: an LDR model is expected (the bundled one)", args[1]);
    let archive = flashmat::archive::Archive::load(std::path::Path::new(&args[2]), teacher::FORMAT, teacher::VERSION)?;
    let cfg: ModelConfig = serde_json::from_str::<teacher::TeacherConfig>(archive.meta("teacher_config")?)?.model;
    let out = Model::new(&ModelConfig { ggx_codes: ggx, ..cfg.clone() }, dev)?;
    let targets = if ggx { teacher::GGX_CHANNELS } else { 64 };
    let teacher = Teacher::load(std::path::Path::new(&args[2]), &cfg, dev, Some(&out.renderer_vs))?;

    // Codes of training photos (8-bit, as the bundled model trains) and the
    // teacher's codes of their true maps, in chunks of 8 materials.
    let sample = samples::SampleConfig { outputs_per_material: 1, ldr_input: true, ..Default::default() };
    let mut rng = rand_pcg::Pcg64::seed_from_u64(48);
    let (mut xtx, mut xty, mut yy, mut n) = (Tensor::zeros([64, 64], (Kind::Double, dev)), Tensor::zeros([64, targets], (Kind::Double, dev)), vec![], 0i64);
    let mut held = vec![];
    for start in (0..materials).step_by(8) {
        let seeds: Vec<u64> = (start..(start + 8).min(materials)).map(|i| procedural::training_seed(i as u64)).collect();
        let batch = samples::make_batch(&procedural::generate_many(&seeds, size), &sample, &mut rng, dev)?;
        let (x, y) = tch::no_grad(|| -> Result<_> {
            let x = source.est.forward_t(&batch.est_input, false)?;
            let y = if ggx { batch.maps.shallow_clone() } else { teacher.encoder.forward_maps(&batch.maps) };
            Ok((x.permute([0, 2, 3, 1]).reshape([-1, 64]).to_kind(Kind::Double), y.permute([0, 2, 3, 1]).reshape([-1, targets]).to_kind(Kind::Double)))
        })?;
        ensure!(x.size()[1] == 64, "64-channel codes expected");
        // Every fourth chunk is held out to score the fit.
        if start % 32 == 24 {
            held.push((x, y));
            continue;
        }
        xtx += x.tr().matmul(&x);
        xty += x.tr().matmul(&y);
        yy.push(y.abs().mean(Kind::Double).double_value(&[]));
        n += x.size()[0];
    }
    ensure!(!held.is_empty(), "too few materials to hold some out (at least 32)");
    // Ridge at a millionth of the mean diagonal: the codes' channels are correlated.
    let ridge = 1e-6 * xtx.diagonal(0, 0, 1).mean(Kind::Double).double_value(&[]);
    let a = Tensor::linalg_solve(&(&xtx + Tensor::eye(64, (Kind::Double, dev)) * ridge), &xty, true);
    let rel = |f: &dyn Fn(&Tensor) -> Tensor| -> f64 {
        let (num, den): (f64, f64) = held.iter().map(|(x, y)| ((f(x) - y).abs().mean(Kind::Double).double_value(&[]), y.abs().mean(Kind::Double).double_value(&[]))).fold((0.0, 0.0), |s, v| (s.0 + v.0, s.1 + v.1));
        num / den
    };
    if ggx {
        println!("fitted on {n} pixels of {materials} materials at {size}; held-out relative L1 of the GGX values:");
        println!("  zero {:.3}, linear map {:.3}", rel(&|x| x.zeros_like().narrow(1, 0, targets)), rel(&|x| x.matmul(&a)));
    } else {
        println!("fitted on {n} pixels of {materials} materials at {size}; held-out relative L1 of the codes (the --code-weight term):");
        println!("  the model's own codes {:.3}, zero {:.3}, linear map {:.3}", rel(&|x| x.shallow_clone()), rel(&|x| x.zeros_like()), rel(&|x| x.matmul(&a)));
    }

    // Fold: head'[j] = sum_i a[i, j] head[i]; M_est's other weights as they are.
    let names = source.est_vs.variables();
    let mut est = out.est_vs.variables();
    for (name, var) in est.iter_mut() {
        if name.starts_with("est.codes.") {
            continue; // the teacher's encoder, below
        }
        let src = names.get(name).with_context(|| format!("M_est weight '{name}' missing in {}", args[1]))?;
        let value = if name.ends_with("head.weight") {
            let s = src.size();
            a.tr().to_kind(Kind::Float).matmul(&src.reshape([s[0], -1])).reshape(var.size().as_slice())
        } else {
            src.shallow_clone()
        };
        ensure!(value.size() == var.size(), "M_est weight '{name}': layouts differ");
        tch::no_grad(|| var.copy_(&value));
    }
    ensure!(est.keys().any(|k| k.ends_with("head.weight")), "no head weight in M_est");
    if let Some(codes) = &out.est.codes {
        tch::no_grad(|| codes.weights().into_iter().zip(teacher.encoder.weights()).for_each(|(mut mine, theirs)| {
            mine.copy_(&theirs);
        }));
    }
    drop(teacher);
    // f16 storage as `flashmat export` writes (11 MB: it travels in .gpu/ to a GPU job).
    out.save(&args[3], &info, true)?;
    println!("wrote {} (M_est of {} with its head remapped, the teacher's renderer)", args[3], args[1]);
    Ok(())
}
