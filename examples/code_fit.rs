//! The neural material of GGX maps against the maps themselves (issue 83):
//! the teacher's codes as they are, and after `fit::codes::fit_codes`, on
//! the coloured-metal set (`data::procedural::metal_material`) and on
//! held-out procedural materials, under held-out directions
//! (`fit::codes::held_out_configs`). Prints log L1, the largest channel
//! mean log ratio, the pixels' chromaticity distance, LPIPS and the fit's
//! seconds.
//!
//! ```sh
//! CONFIGS=moved|identity SAVE=DIR RENDERER_LR=.. PHOTO_SHARE=.. THREADS=1 LOBE_SHARE=.. ROWS=.. LR=.. DARK_FLOOR=.. cargo run --release --example code_fit -- [TEACHER] [SIZE] [STEPS] [MATERIALS: metals,0-4]
//! # defaults: the bundled teacher, 128, CodeFitConfig's steps, metals,0-3
//! # SAVE=DIR writes each material's identity render: maps | neural material | 4x their difference
//! ```

use anyhow::Result;
use flashmat::data::procedural::{metal_material, test_material, METAL_MATERIALS};
use flashmat::fit::codes::{fit_codes, held_out_configs, neural_gap, CodeFitConfig, NeuralGap};
use flashmat::fit::photos::{load_teacher, neural_material};
use flashmat::lpips::Lpips;
use std::path::PathBuf;
use tch::{Device, Kind, Tensor};

fn main() -> Result<()> {
    // One thread: the other core trains (the numbers are per thread).
    tch::set_num_threads(std::env::var("THREADS").ok().and_then(|t| t.parse().ok()).unwrap_or(1));
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize| args.get(i).filter(|a| a.as_str() != "-");
    let teacher = load_teacher(arg(0).map(PathBuf::from).as_deref(), Device::Cpu)?;
    let size: usize = arg(1).map(|s| s.parse()).transpose()?.unwrap_or(128);
    let mut cfg = CodeFitConfig::default();
    if let Some(s) = arg(2) {
        cfg.steps = s.parse()?;
    }
    let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<f64>().ok());
    if let Some(v) = env("LOBE_SHARE") {
        cfg.lobe_share = v;
    }
    if let Some(v) = env("ROWS") {
        cfg.rows = v as usize;
    }
    if let Some(v) = env("LR") {
        cfg.learning_rate = v;
    }
    if let Some(v) = env("RENDERER_LR") {
        cfg.renderer_learning_rate = v;
    }
    if let Some(v) = env("PHOTO_SHARE") {
        cfg.photo_share = v;
    }
    if let Some(v) = env("DARK_FLOOR") {
        cfg.dark_floor = v;
    }
    let list = arg(3).cloned().unwrap_or_else(|| "metals,0-3".into());
    let mut materials = vec![];
    for part in list.split(',') {
        if part == "metals" {
            materials.extend((0..METAL_MATERIALS.len()).map(|i| (METAL_MATERIALS[i].to_string(), metal_material(i, size))));
        } else if let Some((a, b)) = part.split_once('-') {
            materials.extend((a.parse::<usize>()?..=b.parse()?).map(|i| (format!("test{i:02}"), test_material(i, size))));
        } else {
            let i: usize = part.parse()?;
            materials.push((format!("test{i:02}"), test_material(i, size)));
        }
    }
    let lpips = Lpips::new(Device::Cpu)?;
    // CONFIGS=moved: the moved-highlight test's three lights with the photo's camera (eval::highlights).
    // CONFIGS=identity: the overhead photo's co-located flash alone.
    let configs = match std::env::var("CONFIGS").as_deref() {
        Ok("moved") => flashmat::eval::highlights::HighlightConfig::default().configs(),
        Ok("identity") => vec![flashmat::infer::nmat::NeuralMaterial::identity_config()],
        _ => held_out_configs(8),
    };
    let photo_configs = flashmat::data::captures::synthetic_configs(3);
    let show = |g: &NeuralGap| format!("{:.3} {:.3} {:.4} {:.4} {:.3}", g.log_l1, g.channel_log_ratio, g.chromaticity, g.mean_chromaticity, g.lpips.unwrap_or(f64::NAN));
    println!("material | teacher: log L1, channel ratio, chroma (pixels), chroma (mean colour), LPIPS | fitted: the same | seconds");
    let mut sums = [[0.0; 5]; 2];
    for (name, m) in &materials {
        let maps = m.stacked().to_tensor();
        let photo = Tensor::zeros([3, size as i64, size as i64], (Kind::Float, Device::Cpu));
        let mut material = neural_material(&maps, &photo, &teacher, name)?;
        let before = neural_gap(&material, &maps, &configs, Some(&lpips))?;
        let fit = fit_codes(&mut material, &maps, &teacher.encoder, &photo_configs, &cfg)?;
        let after = neural_gap(&material, &maps, &configs, Some(&lpips))?;
        // SAVE=DIR: the identity render, maps | neural material | 4x their difference, display sRGB.
        if let Ok(dir) = std::env::var("SAVE") {
            let config = flashmat::infer::nmat::NeuralMaterial::identity_config();
            let neural = material.render(std::slice::from_ref(&config))?.get(0);
            let (wi, wo) = material.direction_maps(std::slice::from_ref(&config));
            let ggx = flashmat::svbrdf::render::render_directions(&flashmat::model::ggx_codes::valid_values(&maps.unsqueeze(0)), &wi, &wo).get(0).get(0).clamp_min(0.0);
            let diff = (&neural - &ggx).abs() * 4.0;
            let strip = Tensor::cat(&[ggx, neural, diff], 2);
            std::fs::create_dir_all(&dir)?;
            flashmat::io::write_png(&std::path::Path::new(&dir).join(format!("{name}-identity.png")), &flashmat::image::Image::from_tensor(&strip)?.to_display(), flashmat::io::BitDepth::Eight)?;
        }
        println!("{name} | {} | {} | {:.1} (loss {:.4} -> {:.4})", show(&before), show(&after), fit.seconds, fit.loss_before, fit.loss_after);
        for (s, g) in sums.iter_mut().zip([&before, &after]) {
            for (v, x) in s.iter_mut().zip([g.log_l1, g.channel_log_ratio, g.chromaticity, g.mean_chromaticity, g.lpips.unwrap_or(0.0)]) {
                *v += x / materials.len() as f64;
            }
        }
    }
    let row = |s: &[f64; 5]| format!("{:.3} {:.3} {:.4} {:.4} {:.3}", s[0], s[1], s[2], s[3], s[4]);
    println!("mean | {} | {}", row(&sums[0]), row(&sums[1]));
    Ok(())
}
