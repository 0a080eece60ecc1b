//! Issue 48: where M_est misses the codes a lobe-drawing renderer needs. For
//! each model, the relative L1 between its codes of the 50 held-out photos
//! (8-bit, 128x128) and a teacher's codes of their true maps (the
//! `--code-weight` term's measure; zero codes score 1), over pixels with
//! roughness below 0.35 (`train::losses::GLOSSY_ROUGHNESS`: glossy) and the rest, by the material's glossiness
//! tercile (`eval::highlights::glossiness`). Section 5 of
//! reports/highlights-experiments.md. For a `compact-g` model (M_est writes
//! GGX values) a second table reads its head on the glossy pixels: the
//! roughness and specular albedo it writes against the true ones (section 7),
//! and a third the diffuse albedo it writes inside the photo's own highlight
//! (the eval's S_in, from the unclamped photo), where a head that reads the
//! flash as colour writes a bright kd (section 8).
//!
//! ```sh
//! cargo run --release --example code_error_by_gloss -- TEACHER MODEL [MODEL ...]
//! ```

use anyhow::{ensure, Result};
use flashmat::data::{procedural, samples};
use flashmat::eval::highlights;
use flashmat::model::{Model, ModelConfig};
use flashmat::train::teacher::{self, Teacher};
use tch::{Device, Kind};

/// The eval's 50 pixels of a region at 256x256, scaled to these 128x128 photos.
const MIN_HIGHLIGHT_PIXELS: f64 = 13.0;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    ensure!(args.len() >= 3, "usage: code_error_by_gloss TEACHER MODEL [MODEL ...]");
    let dev = Device::Cpu;
    let path = std::path::Path::new(&args[1]);
    let archive = flashmat::archive::Archive::load(path, teacher::FORMAT, teacher::VERSION)?;
    let cfg: ModelConfig = serde_json::from_str::<teacher::TeacherConfig>(archive.meta("teacher_config")?)?.model;
    let holder = Model::new(&cfg, dev)?;
    let teacher = Teacher::load(path, &cfg, dev, Some(&holder.renderer_vs))?;
    let models = args[2..].iter().map(|p| Ok((p.as_str(), Model::load(p, dev)?.0))).collect::<Result<Vec<_>>>()?;
    // Per material: glossiness, and per model the error over glossy and matte pixels (None under 50 pixels).
    let mut rows: Vec<(f64, Vec<[Option<f64>; 2]>)> = vec![];
    // Per material and compact-g model, over the glossy pixels (None under 50):
    // mean roughness written / true, mean ks written / true, mean |roughness error|.
    let mut heads: Vec<Vec<Option<[f64; 5]>>> = vec![];
    // Per material and compact-g model, over the photo's highlight (None
    // under MIN_HIGHLIGHT_PIXELS): mean kd written / true.
    let mut in_highlight: Vec<Vec<Option<[f64; 2]>>> = vec![];
    for i in 0..procedural::TEST_SET_SIZE {
        let m = procedural::test_material(i, 128);
        let photo = flashmat::eval::colocated_render(&m);
        let x = samples::photo_est_input(&photo, true, dev);
        let s_in = highlights::highlight_mask(&highlights::luminance(&photo)?, highlights::HIGHLIGHT_THRESHOLD);
        let s_in = tch::Tensor::from_slice(&s_in).to_kind(Kind::Float).view([1, 1, 128, 128]);
        let maps = m.stacked().to_tensor().unsqueeze(0); // [1, 10, H, W]
        let y = tch::no_grad(|| teacher.encoder.forward_maps(&maps));
        let glossy = maps.narrow(1, flashmat::svbrdf::ROUGHNESS_CHANNEL, 1).lt(flashmat::train::losses::GLOSSY_ROUGHNESS).to_kind(Kind::Float); // [1, 1, H, W]
        let masks = [glossy.shallow_clone(), 1.0 - &glossy];
        let scale = y.abs().mean(Kind::Float).double_value(&[]);
        let mut per_model = vec![];
        let mut per_head = vec![];
        let mut per_highlight = vec![];
        for (_, model) in &models {
            let (codes, head) = tch::no_grad(|| model.est.forward_with_head(&x, false))?;
            if model.config.ggx_codes {
                let n = glossy.sum(Kind::Float).double_value(&[]);
                let mean = |t: &tch::Tensor| (t * &glossy).sum(Kind::Float).double_value(&[]) / n / t.size()[1] as f64;
                let r = flashmat::svbrdf::ROUGHNESS_CHANNEL;
                per_head.push((n >= 50.0).then(|| {
                    [
                        mean(&head.narrow(1, r, 1)),
                        mean(&maps.narrow(1, r, 1)),
                        mean(&head.narrow(1, 3, 3)),
                        mean(&maps.narrow(1, 3, 3)),
                        mean(&(head.narrow(1, r, 1) - maps.narrow(1, r, 1)).abs()),
                    ]
                }));
                let n_in = s_in.sum(Kind::Float).double_value(&[]);
                let kd_in = |t: &tch::Tensor| (t.narrow(1, 0, 3) * &s_in).sum(Kind::Float).double_value(&[]) / n_in / 3.0;
                per_highlight.push((n_in >= MIN_HIGHLIGHT_PIXELS).then(|| [kd_in(&head), kd_in(&maps)]));
            }
            let err = (codes - &y).abs().mean_dim([1i64].as_slice(), true, Kind::Float);
            per_model.push(masks.each_ref().map(|mask| {
                let n = mask.sum(Kind::Float).double_value(&[]);
                (n >= 50.0).then(|| (&err * mask).sum(Kind::Float).double_value(&[]) / n / scale)
            }));
        }
        rows.push((flashmat::eval::highlights::glossiness(&m), per_model));
        heads.push(per_head);
        in_highlight.push(per_highlight);
    }
    let tercile = flashmat::eval::highlights::terciles(&rows.iter().map(|r| r.0).collect::<Vec<_>>());
    println!("| tercile | model | glossy pixels (materials) | matte pixels (materials) |\n|---|---|---|---|");
    for (k, name) in flashmat::eval::highlights::TERCILES.iter().enumerate() {
        let part: Vec<_> = rows.iter().zip(&tercile).filter(|(_, &t)| t == k).map(|(r, _)| r).collect();
        for (j, (path, _)) in models.iter().enumerate() {
            let cell = |c: usize| {
                let v: Vec<f64> = part.iter().filter_map(|r| r.1[j][c]).collect();
                if v.is_empty() { "-".to_string() } else { format!("{:.3} ({})", v.iter().sum::<f64>() / v.len() as f64, v.len()) }
            };
            println!("| {name} | {path} | {} | {} |", cell(0), cell(1));
        }
    }
    let ggx: Vec<&str> = models.iter().filter(|m| m.1.config.ggx_codes).map(|m| m.0).collect();
    if !ggx.is_empty() {
        println!("\nGGX head on the glossy pixels (materials with 50 or more):\n");
        println!("| tercile | model | roughness written / true | mean abs roughness error | ks written / true |\n|---|---|---|---|---|");
        for (k, name) in flashmat::eval::highlights::TERCILES.iter().enumerate() {
            for (j, path) in ggx.iter().enumerate() {
                let v: Vec<[f64; 5]> = heads.iter().zip(&tercile).filter(|(_, &t)| t == k).filter_map(|(h, _)| h[j]).collect();
                if v.is_empty() {
                    continue;
                }
                let m = |c: usize| v.iter().map(|a| a[c]).sum::<f64>() / v.len() as f64;
                println!("| {name} | {path} | {:.3} / {:.3} | {:.3} | {:.3} / {:.3} ({}) |", m(0), m(1), m(4), m(2), m(3), v.len());
            }
        }
        println!("\nGGX head inside the photo's highlight (S_in, materials with {MIN_HIGHLIGHT_PIXELS} or more of its pixels):\n");
        println!("| tercile | model | kd written / true |\n|---|---|---|");
        for (k, name) in flashmat::eval::highlights::TERCILES.iter().enumerate() {
            for (j, path) in ggx.iter().enumerate() {
                let v: Vec<[f64; 2]> = in_highlight.iter().zip(&tercile).filter(|(_, &t)| t == k).filter_map(|(h, _)| h[j]).collect();
                if !v.is_empty() {
                    let m = |c: usize| v.iter().map(|a| a[c]).sum::<f64>() / v.len() as f64;
                    println!("| {name} | {path} | {:.3} / {:.3} ({}) |", m(0), m(1), v.len());
                }
            }
        }
    }
    Ok(())
}
