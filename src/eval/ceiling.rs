//! The renderer's ceiling (issue 48): how well does a model's renderer
//! (ND_enc + M_render, frozen) relight the best neural map it can be given?
//! M_est's map of the photo is fitted ([`crate::infer::refine::fit_to_renders`])
//! to the true renders of the photo's own configuration and K moved-highlight
//! configurations (the photo's camera, the light moved so the mirror
//! highlight lands on the material at seeded random points), then scored by
//! the moved-highlight test ([`super::highlights`]) under its three lights,
//! which the fit never sees.
//!
//! - K = 0 (the photo alone): the map that reproduces the photo exactly.
//!   A ghost here is what the photo alone asks of a map under this
//!   renderer, the pull M_est (which sees only the photo) trains under.
//! - K > 0: a map exists that no photo could give; if the lobe stays weak
//!   with it, no M_est can fix the lobe with this renderer.
//!
//! So a renderer can be judged apart from M_est: the estimate's row is the
//! model, the fitted rows its renderer's ceiling.

use super::highlights::{self, HighlightConfig, MaterialHighlights};
use super::methods::{Method, ModelMethod};
use crate::geometry::{LightView, MODEL_FOV_DEG};
use crate::infer::refine::fit_to_renders;
use crate::infer::NeuralMaterial;
use anyhow::{anyhow, ensure, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use serde::Serialize;
use std::fmt::Write as _;
use std::path::PathBuf;
use tch::{Device, Kind, Tensor};

/// Seed of the fit's moved-highlight configurations.
pub const FIT_SEED: u64 = 0xCE11_1A6;

/// Settings of the ceiling measurement; the defaults are the probe.
#[derive(Clone, Debug)]
pub struct CeilingConfig {
    /// Moved-highlight configurations fitted besides the photo's, one fit each.
    pub fit_lights: Vec<usize>,
    /// Adam steps of each fit.
    pub steps: usize,
    /// Adam step in units of the estimate's RMS value.
    pub learning_rate: f64,
    /// The glossiest held-out materials scored (matte ones rarely have a
    /// highlight region to measure).
    pub materials: usize,
    /// Held-out materials scored instead of the glossiest (indices, e.g. the
    /// matte ones whose rest a renderer overshoots); empty: the glossiest.
    pub only: Vec<usize>,
    /// Side of the materials' maps (a multiple of 8).
    pub size: usize,
}

impl Default for CeilingConfig {
    fn default() -> Self {
        Self { fit_lights: vec![0, 5], steps: 300, learning_rate: 0.02, materials: highlights::CHECK_MATERIALS, only: vec![], size: 128 }
    }
}

/// The configurations a ceiling fit sees: the photo's own (co-located), then
/// `k` moved-highlight configurations drawn from [`FIT_SEED`] (the first `k`
/// of the same stream for every `k`).
pub fn fit_configs(k: usize) -> Vec<LightView> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(FIT_SEED);
    std::iter::once(LightView::colocated(MODEL_FOV_DEG)).chain((0..k).map(|_| crate::data::samples::moved_highlight_config(&mut rng, MODEL_FOV_DEG).0)).collect()
}

/// One material under one map: the estimate's or a fit's.
#[derive(Clone, Debug, Serialize)]
pub struct CeilingRow {
    /// `estimate` (M_est's map) or `fit K` (the photo and K moved lights).
    pub map: String,
    /// Mean |ln(1+R) - ln(1+truth)| over the fitted configurations, before
    /// and after the fit (the estimate's row: its own, under the K = max set).
    pub fit_l1_before: f64,
    pub fit_l1_after: f64,
    /// The same under the test's moved lights (never fitted).
    pub test_l1: f64,
    pub highlights: MaterialHighlights,
}

/// Mean |ln(1+a) - ln(1+b)| of two linear render stacks.
fn log_l1(a: &Tensor, b: &Tensor) -> f64 {
    (crate::spaces::to_log(&a.clamp_min(0.0)) - crate::spaces::to_log(&b.to_device(a.device()).clamp_min(0.0))).abs().mean(Kind::Float).double_value(&[])
}

/// The estimate's row and one row per `cfg.fit_lights` for one material
/// `m`, from `estimate`, the model's neural material of its photo.
pub fn measure_material(estimate: &NeuralMaterial, name: &str, m: &crate::svbrdf::Svbrdf, cfg: &CeilingConfig) -> Result<Vec<CeilingRow>> {
    let moved = HighlightConfig::default();
    let colocated = super::colocated_render(m);
    let test_truth = super::reference_renders(m, &moved.configs());
    let s_in = highlights::highlight_mask(&highlights::luminance(&colocated)?, moved.threshold);
    let photo_pixels = s_in.iter().filter(|&&b| b).count();
    let glossiness = highlights::glossiness(m);
    let score = |pred: &Tensor| -> Result<MaterialHighlights> {
        Ok(highlights::material_highlights(name, glossiness, photo_pixels, &highlights::light_ratios(&s_in, pred, &test_truth, &moved, None)?))
    };
    let largest = cfg.fit_lights.iter().copied().max().unwrap_or(0);
    let all_configs = fit_configs(largest);
    let all_truth = super::reference_renders(m, &all_configs);
    let pred = estimate.render(&moved.configs())?;
    let own = log_l1(&estimate.render(&all_configs)?, &all_truth);
    let mut rows = vec![CeilingRow { map: "estimate".into(), fit_l1_before: own, fit_l1_after: own, test_l1: log_l1(&pred, &test_truth), highlights: score(&pred)? }];
    for &k in &cfg.fit_lights {
        let mut fitted = estimate.duplicate()?;
        let configs = &all_configs[..k + 1];
        let truth = all_truth.narrow(0, 0, k as i64 + 1);
        let (before, after) = fit_to_renders(&mut fitted, configs, &truth, cfg.steps, cfg.learning_rate).with_context(|| format!("{name}, fit {k}"))?;
        let pred = tch::no_grad(|| fitted.render(&moved.configs()))?;
        rows.push(CeilingRow { map: format!("fit {k}"), fit_l1_before: before, fit_l1_after: after, test_l1: log_l1(&pred, &test_truth), highlights: score(&pred)? });
    }
    Ok(rows)
}

/// Everything `flashmat eval --ceiling` needs.
#[derive(Clone, Debug)]
pub struct CeilingOptions {
    pub model: PathBuf,
    /// Photos clamped to [0, 1] (8-bit), as the evaluation's `--ldr-input`.
    pub ldr_input: bool,
    pub out: PathBuf,
    pub device: Device,
    pub progress: bool,
    pub config: CeilingConfig,
}

/// Scores the estimate and every fit on the glossiest held-out materials
/// (or those of `config.only`),
/// writes `ceiling.md` and `ceiling.csv` into `opts.out`; returns the rows
/// per material.
pub fn run(opts: &CeilingOptions) -> Result<Vec<Vec<CeilingRow>>> {
    let cfg = &opts.config;
    ensure!(cfg.steps > 0, "--ceiling-steps must be at least 1");
    ensure!(cfg.materials > 0, "--ceiling-materials must be at least 1");
    super::check_eval_size(cfg.size)?;
    let name = opts.model.file_stem().map_or_else(|| opts.model.display().to_string(), |s| s.to_string_lossy().into_owned());
    let mut method = ModelMethod::load(&opts.model, name.clone(), opts.ldr_input, opts.device)?;
    let picks = if cfg.only.is_empty() {
        highlights::glossiest_test_materials(cfg.materials)?
    } else {
        let last = crate::data::procedural::TEST_SET_SIZE - 1;
        ensure!(cfg.only.iter().all(|&i| i <= last), "--ceiling-only takes held-out material indices from 0 to {last}, got {:?}", cfg.only);
        cfg.only.clone()
    };
    std::fs::create_dir_all(&opts.out).map_err(|e| anyhow!("cannot create output folder {}: {e}", opts.out.display()))?;
    let bar = if opts.progress { ProgressBar::new(picks.len() as u64) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("{bar:40} {pos}/{len} materials, {elapsed} (eta {eta}) {msg}").expect("valid template"));
    let mut all = vec![];
    for i in picks {
        let label = format!("test{i:02}");
        bar.set_message(label.clone());
        let m = crate::data::procedural::test_material(i, cfg.size);
        method.prepare(&super::exposure::exposed(&super::colocated_render(&m), 0.0, opts.ldr_input)).with_context(|| format!("{name} on {label}"))?;
        let estimate = method.material().ok_or_else(|| anyhow!("{name} on {label}: the model gave no material"))?;
        all.push(measure_material(estimate, &label, &m, cfg)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    crate::io::atomic_write_bytes(&opts.out.join("ceiling.csv"), csv_text(&all).as_bytes())?;
    crate::io::atomic_write_bytes(&opts.out.join("ceiling.md"), markdown(&name, opts, &all).as_bytes())?;
    Ok(all)
}

/// `map,material,glossiness,fit_l1_before,fit_l1_after,test_l1,ghost,lobe,rest`.
pub fn csv_text(all: &[Vec<CeilingRow>]) -> String {
    let cell = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.5}"));
    let mut s = String::from("map,material,glossiness,fit_l1_before,fit_l1_after,test_l1,ghost,lobe,rest\n");
    for r in all.iter().flatten() {
        let h = &r.highlights;
        let _ = writeln!(s, "{},{},{:.5},{:.5},{:.5},{:.5},{},{},{}", r.map, h.material, h.glossiness, r.fit_l1_before, r.fit_l1_after, r.test_l1, cell(h.ghost), cell(h.lobe), cell(h.rest));
    }
    s
}

/// The page: how it was made, then the moved-highlight summary of each map
/// and the fits' log errors.
pub fn markdown(model: &str, opts: &CeilingOptions, all: &[Vec<CeilingRow>]) -> String {
    let cfg = &opts.config;
    let mut s = format!("# The renderer's ceiling: {model}\n\n");
    let _ = writeln!(
        s,
        "The {} {} held-out materials at {}x{} ({} photos). Each map row: M_est's estimate, or that estimate fitted for {} Adam steps \
         (step {} x its RMS, renderer frozen) to the true renders of the photo's configuration and K moved-highlight configurations \
         (the photo's camera, mirror highlight on the material; seed {FIT_SEED:#x}), then relit under the moved-highlight test's lights, \
         which no fit sees. log L1: mean |ln(1+R) - ln(1+truth)|.\n",
        all.len(),
        if cfg.only.is_empty() { "glossiest" } else { "chosen" },
        cfg.size,
        cfg.size,
        if opts.ldr_input { "8-bit" } else { "HDR" },
        cfg.steps,
        cfg.learning_rate
    );
    let maps: Vec<String> = all.first().map(|rows| rows.iter().map(|r| r.map.clone()).collect()).unwrap_or_default();
    let per_map: Vec<(String, Vec<MaterialHighlights>)> =
        maps.iter().enumerate().map(|(j, name)| (name.clone(), all.iter().map(|rows| rows[j].highlights.clone()).collect())).collect();
    let _ = writeln!(s, "| map | ghost | median | > 1.5x | lobe | median | < 0.67x | rest | median | outside 0.9-1.1 | fitted log L1 before | after | test log L1 |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (j, (name, rows)) in per_map.iter().enumerate() {
        let sm = highlights::summarize(&rows.iter().collect::<Vec<_>>());
        let mean = |f: fn(&CeilingRow) -> f64| all.iter().map(|r| f(&r[j])).sum::<f64>() / all.len().max(1) as f64;
        let rest_out = rows.iter().filter_map(|r| r.rest).filter(|&v| !(0.9..=1.1).contains(&v)).count();
        let _ = writeln!(
            s,
            "| {name} | {} | {} | {} | {:.4} | {:.4} | {:.4} |",
            highlights::stats_cells(&sm.ghost, sm.ghost.above_1_5),
            highlights::stats_cells(&sm.lobe, sm.lobe.below_0_67),
            highlights::stats_cells(&sm.rest, rest_out),
            mean(|r| r.fit_l1_before),
            mean(|r| r.fit_l1_after),
            mean(|r| r.test_l1)
        );
    }
    let _ = writeln!(s, "\nPer material (ghost / lobe / rest):\n");
    let _ = writeln!(s, "| material | glossiness | {} |\n|---|---|{}", maps.join(" | "), "---|".repeat(maps.len()));
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
    for rows in all {
        let h = &rows[0].highlights;
        let cells: Vec<String> = rows.iter().map(|r| format!("{} / {} / {}", f(r.highlights.ghost), f(r.highlights.lobe), f(r.highlights.rest))).collect();
        let _ = writeln!(s, "| {} | {:.2} | {} |", h.material, h.glossiness, cells.join(" | "));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fit's configurations: the photo's first, then moved highlights
    /// with the photo's camera, the same prefix for every K.
    #[test]
    fn fit_configurations_share_a_prefix_and_keep_the_camera() {
        let (two, five) = (fit_configs(2), fit_configs(5));
        assert_eq!((two.len(), five.len()), (3, 6));
        assert_eq!(&five[..3], &two[..]);
        let photo = LightView::colocated(MODEL_FOV_DEG);
        assert_eq!(five[0], photo);
        assert!(five[1..].iter().all(|c| c.view == photo.view && c.light != photo.light));
        // None of them is a test light.
        assert!(five.iter().all(|c| !HighlightConfig::default().lights.contains(&c.light)));
    }

    /// A map fitted to renders of its own renderer under other lights comes
    /// back to them: the bundled model's estimate, perturbed, fitted to the
    /// unperturbed one's renders, loses most of its error.
    #[test]
    fn a_fit_recovers_renders_its_renderer_can_draw() {
        tch::manual_seed(7);
        let loaded = crate::infer::load_model(None, Device::Cpu).unwrap();
        let m = crate::svbrdf::Svbrdf::uniform(16, 16, [0.4, 0.3, 0.2], [0.04; 3], 0.3);
        let photo = crate::image::Image::from_tensor(&crate::eval::colocated_render(&m)).unwrap();
        let truth_material = crate::infer::estimate(&loaded.model, &loaded.info, &crate::infer::PreparedPhoto::at_model_view(photo, true, "test")).unwrap();
        let configs = fit_configs(3);
        let truth = truth_material.render(&configs).unwrap();
        let mut start = truth_material.duplicate().unwrap();
        let rms = start.neural_map.square().mean(Kind::Float).sqrt().double_value(&[]);
        start.neural_map = &start.neural_map + Tensor::randn_like(&start.neural_map) * (0.3 * rms);
        let (before, after) = fit_to_renders(&mut start, &configs, &truth, 200, 0.02).unwrap();
        assert!(before > 1e-3 && after < 0.3 * before, "{before} -> {after}");
        // Wrong shapes are one error line.
        let e = fit_to_renders(&mut start, &configs[..2], &truth, 1, 0.05).unwrap_err().to_string();
        assert!(e.contains("targets must be [2, 3, 16, 16]"), "{e}");
    }
}
