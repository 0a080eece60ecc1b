//! The architecture's ceiling on moved highlights (issue 48): the per-pixel
//! teacher (`models/teacher-any-ggx.safetensors`: a GGX-to-code MLP trained
//! with ND_enc + M_render on dense per-pixel GGX supervision, 16 direction
//! frequencies; or any teacher file, e.g. one trained with `--lobe-share`
//! or the `compact-h` preset) renders the six glossiest held-out materials from their true
//! maps under the moved-highlight test's lights; the ratios say whether the
//! compact renderer's layout draws a moved highlight when trained per pixel,
//! apart from how flashmat trains it (`flashmat eval --ceiling`).
//!
//! ```sh
//! cargo run --release --example teacher_ceiling -- [TEACHER] [SIZE] [all | I,J,...]
//! ```
//!
//! The third argument scores other held-out materials than the glossiest
//! six: `all` of them, or the listed indices (the matte ones, where a
//! renderer that draws a lobe for every code overshoots).

use anyhow::Result;
use flashmat::eval::highlights::{self, HighlightConfig};
use flashmat::model::{Model, ModelConfig};
use tch::{Device, Kind};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let teacher_file = args.get(1).map_or("models/teacher-any-ggx.safetensors", |s| s.as_str());
    let size: usize = args.get(2).map_or(Ok(128), |s| s.parse())?;
    // The teacher's own model layout (compact, or compact-h with the half-angle feature).
    let archive = flashmat::archive::Archive::load(std::path::Path::new(teacher_file), flashmat::train::teacher::FORMAT, flashmat::train::teacher::VERSION)?;
    let cfg: ModelConfig = serde_json::from_str::<flashmat::train::teacher::TeacherConfig>(archive.meta("teacher_config")?)?.model;
    let model = Model::new(&cfg, Device::Cpu)?;
    let teacher = flashmat::train::teacher::Teacher::load(std::path::Path::new(teacher_file), &cfg, Device::Cpu, Some(&model.renderer_vs))?;
    let materials: Vec<usize> = match args.get(3).map(|s| s.as_str()) {
        None => highlights::glossiest_test_materials(highlights::CHECK_MATERIALS)?,
        Some("all") => (0..flashmat::data::procedural::TEST_SET_SIZE).collect(),
        Some(list) => list.split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?,
    };
    let moved = HighlightConfig::default();
    let mut rows = vec![];
    println!("| material | glossiness | ghost | lobe | rest | test log L1 |\n|---|---|---|---|---|---|");
    for i in materials {
        let m = flashmat::data::procedural::test_material(i, size);
        let maps = flashmat::data::samples::stack_maps(std::slice::from_ref(&m), Device::Cpu)?;
        let truth = flashmat::eval::reference_renders(&m, &moved.configs());
        let pred = tch::no_grad(|| -> Result<_> {
            let codes = teacher.encoder.forward_maps(&maps);
            let (lights, views) = flashmat::geometry::config_tensors(&moved.configs(), Device::Cpu);
            let k = moved.lights.len() as i64;
            let (wi, wo) = flashmat::svbrdf::render::direction_maps_for(&lights.view([1, k, 3]), &views.view([1, k, 3]), size, size);
            Ok(flashmat::spaces::from_log(&model.renderer.forward_maps(&codes, &wi, &wo)?.get(0)).clamp_min(0.0))
        })?;
        let colocated = flashmat::eval::colocated_render(&m);
        let s_in = highlights::highlight_mask(&highlights::luminance(&colocated)?, moved.threshold);
        let name = format!("test{i:02}");
        let row = highlights::material_highlights(&name, highlights::glossiness(&m), 0, &highlights::light_ratios(&s_in, &pred, &truth, &moved, None)?);
        let l1 = (flashmat::spaces::to_log(&pred) - flashmat::spaces::to_log(&truth)).abs().mean(Kind::Float).double_value(&[]);
        let f = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.2}"));
        println!("| {name} | {:.2} | {} | {} | {} | {l1:.4} |", row.glossiness, f(row.ghost), f(row.lobe), f(row.rest));
        rows.push(row);
    }
    let s = highlights::summarize(&rows.iter().collect::<Vec<_>>());
    println!("\ngeometric means: ghost {:.2}, lobe {:.2}, rest {:.2}", s.ghost.geo_mean, s.lobe.geo_mean, s.rest.geo_mean);
    Ok(())
}
