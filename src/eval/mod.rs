//! Evaluation (REFERENCE section 6): methods re-render held-out materials
//! from their co-located photo; renders are compared with the GGX ground
//! truth in three cases (Reflect, Identity, Hemisphere).
//!
//! ```text
//! material ─► GGX co-located photo ─► Method::prepare ─► Method::render(case configs)
//!    │                                                        │
//!    └──────► GGX renders of the same configs ───────────► metrics ─► CSV, summary.md, grids
//! ```
//!
//! Configurations are drawn per (seed, material index, case), so every
//! method, and every run with the same seed and dataset, sees the same ones.
//! Every run also scores the moved-highlight test ([`highlights`]) and the
//! identity brightness at the photo's exposure and any other asked for
//! ([`exposure`]) on the same prepared materials.

pub mod captures;
pub mod ceiling;
pub mod exposure;
pub mod highlights;
pub mod methods;
pub mod metrics;
pub mod photos;
pub mod report;
pub mod shadows;
pub mod uniform;

pub use methods::{open_methods, open_model_file, AnalyticMethod, Method, ModelMethod, PrintoutMethod, RelightMethod, PRINTOUT};
pub use metrics::{mean_ci95, mean_scores, score_renders, score_renders_on, LpipsOn, Scores, PSNR_CAP_DB};

use crate::data::loaders::{center_crop, load_readable, open_dataset, SvbrdfSource, Unreadable};
use crate::data::phone::{exposure_factor, finish_phone_photo, phone_light_view, PhonePhotoConfig};
use crate::data::procedural;
use crate::geometry::{sample_hemisphere, sample_reflect, fov_to_distance, LightView, Sampling, HEMISPHERE_RADIUS, MODEL_FOV_DEG};
use crate::infer::refine::RefineConfig;
use crate::lpips::Lpips;
use crate::svbrdf::Svbrdf;
use anyhow::{anyhow, ensure, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_pcg::Pcg64;
use std::path::{Path, PathBuf};
use tch::{Device, Tensor};

/// Dataset name of the 50 procedural held-out materials.
pub const PROCEDURAL_TEST: &str = "procedural-test";

/// Dataset name of the held-out dark materials (`procedural::dark_test_set`).
pub const PROCEDURAL_DARK_TEST: &str = "procedural-dark-test";

/// Dataset name of the held-out saturated materials (`procedural::saturated_test_set`).
pub const PROCEDURAL_SATURATED_TEST: &str = "procedural-saturated-test";

/// Dataset name of the held-out coloured metals and saturated glossy
/// materials (`procedural::metal_material`; issue 83).
pub const PROCEDURAL_METALS: &str = "procedural-metals";

/// Configurations per material of the Reflect and Hemisphere cases (the
/// paper's 128 lights x 128 views, paired).
pub const DEFAULT_CONFIGS: usize = 128;

/// Lower-case name of a case (CSV, file names).
pub fn case_name(case: Sampling) -> &'static str {
    match case {
        Sampling::Reflect => "reflect",
        Sampling::Identity => "identity",
        Sampling::Hemisphere => "hemisphere",
    }
}

/// Column title of a case in the summary (the paper's table).
pub fn case_title(case: Sampling) -> &'static str {
    match case {
        Sampling::Reflect => "Reflect",
        Sampling::Identity => "Identity",
        Sampling::Hemisphere => "Hemisphere",
    }
}

/// Seed of the configurations of one (material, case): SplitMix64 of the
/// run seed, material index and case, so streams are unrelated.
pub fn case_seed(seed: u64, material: usize, case: Sampling) -> u64 {
    let tag = match case {
        Sampling::Reflect => 1u64,
        Sampling::Identity => 2,
        Sampling::Hemisphere => 3,
    };
    let mut z = seed ^ (material as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ tag.wrapping_mul(0xd1b5_4a32_d192_ed03);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The output configurations of a case for one material: Reflect draws
/// `count` training-style configurations (camera on the radius-4.010781
/// hemisphere, highlight centred at a sampled point), Hemisphere `count`
/// lights and views independently uniform on the radius-4 hemisphere,
/// Identity the one co-located input configuration.
pub fn case_configs(case: Sampling, seed: u64, material: usize, count: usize) -> Vec<LightView> {
    let mut rng = Pcg64::seed_from_u64(case_seed(seed, material, case));
    match case {
        Sampling::Identity => vec![LightView::colocated(MODEL_FOV_DEG)],
        Sampling::Reflect => (0..count).map(|_| sample_reflect(&mut rng, fov_to_distance(MODEL_FOV_DEG)).0).collect(),
        Sampling::Hemisphere => (0..count).map(|_| sample_hemisphere(&mut rng, HEMISPHERE_RADIUS)).collect(),
    }
}

/// Everything `flashmat eval` needs.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Model files, or `printout`.
    pub models: Vec<String>,
    /// `procedural-test`, `procedural-test:I` (one of its materials) or a
    /// dataset folder/file `open_dataset` reads.
    pub dataset: String,
    pub cases: Vec<Sampling>,
    pub out: PathBuf,
    pub size: usize,
    pub seed: u64,
    pub limit: Option<usize>,
    /// Configurations per material for Reflect and Hemisphere.
    pub configs: usize,
    /// Photos clamped to [0, 1] (what an 8-bit camera keeps).
    pub ldr_input: bool,
    pub device: Device,
    pub progress: bool,
    /// Refined variants of every flashmat model (`--refine`), one per setting.
    pub refine: Vec<RefineConfig>,
    /// Exposures (stops) of the exposure curve; 0 is always scored.
    pub exposures: Vec<f64>,
    /// How flashmat models handle the photo's exposure (`--exposure-mode`).
    pub exposure: crate::infer::ExposureConfig,
    /// Also score every flashmat model with its photographed highlight
    /// filled (`--highlight-fill`; rows `NAME+fill`).
    pub highlight_fill: Option<crate::infer::highlight_fill::HighlightFillConfig>,
    /// Photos taken as a phone takes them, so far astray (`--phone-photos`,
    /// `--phone-jpeg`, [`material_photo`]); None: the exact co-located render.
    pub phone_photos: Option<PhonePhotoConfig>,
}

/// One line of a method's CSV.
#[derive(Clone, Debug)]
pub struct Row {
    pub material: String,
    pub case: Sampling,
    pub scores: Scores,
}

/// Per-method results of a run.
#[derive(Debug)]
pub struct MethodResults {
    pub name: String,
    pub rows: Vec<Row>,
    /// The moved-highlight test, one row per material.
    pub highlights: Vec<highlights::MaterialHighlights>,
    /// The exposure curve, one row per material and exposure.
    pub exposure: Vec<exposure::ExposureRow>,
}

impl MethodResults {
    /// Results with no rows yet.
    pub fn new(name: String) -> Self {
        Self { name, rows: vec![], highlights: vec![], exposure: vec![] }
    }
}

/// Loads the materials at `size x size`: the procedural test set, or a
/// dataset's materials centre-cropped to a square and shrunk (area) or
/// enlarged (bilinear) to `size`. At most `limit` materials. The first
/// that cannot be read is the error, naming it ([`load_readable_materials`]
/// goes on without it).
pub fn load_materials(dataset: &str, size: usize, limit: Option<usize>) -> Result<Vec<(String, Svbrdf)>> {
    if let Some(materials) = procedural_materials(dataset, size, limit)? {
        return Ok(materials);
    }
    let (ds, n) = open_eval_dataset(dataset, limit)?;
    (0..n)
        .map(|i| {
            let m = ds.load(i).and_then(|m| fit_to_size(&m, size)).map_err(|e| anyhow!("material {}: {e:#}", ds.name(i)))?;
            Ok((ds.name(i), m))
        })
        .collect()
}

/// [`load_materials`], going on past dataset materials that cannot be read
/// (each named in a warning line; [`load_readable`]), which it returns
/// beside the others. Errors when none can be read.
pub fn load_readable_materials(dataset: &str, size: usize, limit: Option<usize>) -> Result<(Vec<(String, Svbrdf)>, Vec<Unreadable>)> {
    if let Some(materials) = procedural_materials(dataset, size, limit)? {
        return Ok((materials, vec![]));
    }
    let (ds, n) = open_eval_dataset(dataset, limit)?;
    load_readable(ds.as_ref(), n, |m| fit_to_size(&m, size))
}

/// The procedural sets (`procedural-test`, `procedural-dark-test`,
/// `procedural-saturated-test`, `procedural-metals`, `procedural-test:I`) at `size`; None for a
/// dataset on disk.
fn procedural_materials(dataset: &str, size: usize, limit: Option<usize>) -> Result<Option<Vec<(String, Svbrdf)>>> {
    if dataset == PROCEDURAL_TEST {
        let seeds = procedural::test_seeds();
        let n = limit.unwrap_or(seeds.len()).min(seeds.len());
        let mats = procedural::generate_many(&seeds[..n], size);
        return Ok(Some(mats.into_iter().enumerate().map(|(i, m)| (format!("test{i:02}"), m)).collect()));
    }
    if dataset == PROCEDURAL_DARK_TEST {
        let mats = procedural::dark_test_set(size);
        let n = limit.unwrap_or(mats.len()).min(mats.len());
        return Ok(Some(mats.into_iter().take(n).enumerate().map(|(i, m)| (format!("dark{i:02}"), m)).collect()));
    }
    if dataset == PROCEDURAL_SATURATED_TEST {
        let mats = procedural::saturated_test_set(size);
        let n = limit.unwrap_or(mats.len()).min(mats.len());
        return Ok(Some(mats.into_iter().take(n).enumerate().map(|(i, m)| (format!("sat{i:02}"), m)).collect()));
    }
    if dataset == PROCEDURAL_METALS {
        let n = limit.unwrap_or(procedural::METAL_MATERIALS.len()).min(procedural::METAL_MATERIALS.len());
        return Ok(Some((0..n).map(|i| (procedural::METAL_MATERIALS[i].to_string(), procedural::metal_material(i, size))).collect()));
    }
    if let Some(i) = procedural::parse_test_material(dataset)? {
        return Ok(Some(vec![(format!("test{i:02}"), procedural::test_material(i, size))]));
    }
    Ok(None)
}

/// A dataset on disk and how many of its materials to load (`limit`).
fn open_eval_dataset(dataset: &str, limit: Option<usize>) -> Result<(Box<dyn SvbrdfSource>, usize)> {
    let ds = open_dataset(Path::new(dataset))?;
    let n = limit.unwrap_or(ds.len()).min(ds.len());
    ensure!(n > 0, "dataset {dataset} holds no materials");
    Ok((ds, n))
}

/// Centre square crop, then resized to `size` (normals renormalised, the
/// height field dropped when resized).
pub fn fit_to_size(m: &Svbrdf, size: usize) -> Result<Svbrdf> {
    let side = m.height().min(m.width());
    let sq = center_crop(m, side)?;
    if side == size {
        return Ok(sq);
    }
    let resize = |im: &crate::image::Image| im.resize_to(size, size);
    let normal = crate::svbrdf::renormalize_normals(&resize(&sq.normal));
    Ok(Svbrdf { diffuse: resize(&sq.diffuse), specular: resize(&sq.specular), roughness: resize(&sq.roughness), normal, height_field: None })
}

/// GGX renders of a material (CPU renderer): `[K, 3, H, W]` linear.
pub fn reference_renders(m: &Svbrdf, configs: &[LightView]) -> Tensor {
    crate::svbrdf::cpu::render_tensor(m, configs)
}

/// The co-located GGX render of a material, `[3, H, W]` linear, unclamped.
pub fn colocated_render(m: &Svbrdf) -> Tensor {
    reference_renders(m, &[LightView::colocated(MODEL_FOV_DEG)]).get(0)
}

/// The input photo of a material: its co-located GGX render `[3, H, W]`,
/// clamped to [0, 1] when `ldr` (the exposure curve's photo at 0 stops).
pub fn input_photo(m: &Svbrdf, ldr: bool) -> Tensor {
    exposure::exposed(&colocated_render(m), 0.0, ldr)
}

/// The photo methods estimate material `index` from (`[3, H, W]` linear),
/// with the linear render it was made of (the moved-highlight test's S_in
/// and the exposure curve read that one): the co-located GGX render,
/// clamped when `opts.ldr_input`; with `opts.phone_photos` a phone's 8-bit
/// photo instead ([`crate::data::phone`]: camera, flash and noise drawn from
/// the seed and the index; the render brought to the co-located photo's
/// exposure). -> (linear render, photo).
pub fn material_photo(m: &Svbrdf, index: usize, opts: &EvalOptions) -> Result<(Tensor, Tensor)> {
    let Some(cfg) = &opts.phone_photos else {
        let linear = colocated_render(m);
        let photo = exposure::exposed(&linear, 0.0, opts.ldr_input);
        return Ok((linear, photo));
    };
    let mut rng = Pcg64::seed_from_u64(case_seed(opts.seed, index, Sampling::Identity) ^ PHONE_STREAM);
    let config = phone_light_view(&mut rng, MODEL_FOV_DEG, cfg);
    let gain = exposure_factor(config.light, MODEL_FOV_DEG);
    let mut values = crate::svbrdf::cpu::render(m, &[config]);
    let shape = [3, m.height() as i64, m.width() as i64];
    let linear = Tensor::from_slice(&values).view(shape) * gain;
    finish_phone_photo(&mut values, m.width(), gain, cfg, &mut rng)?;
    Ok((linear, Tensor::from_slice(&values).view(shape)))
}

/// Tells a phone photo's random stream from the identity case's.
const PHONE_STREAM: u64 = 0x5048_4f4e_4521;

/// Scores every method on every material and case; returns rows per method.
pub fn evaluate(
    methods: &mut [Box<dyn Method>],
    materials: &[(String, Svbrdf)],
    opts: &EvalOptions,
    lpips: &Lpips,
) -> Result<Vec<MethodResults>> {
    let mut results: Vec<MethodResults> = methods.iter().map(|m| MethodResults::new(m.name())).collect();
    let moved = highlights::HighlightConfig::default();
    let exposures = exposure_list(&opts.exposures)?;
    let bar = if opts.progress { ProgressBar::new((materials.len() * methods.len()) as u64) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("{bar:40} {pos}/{len} material x method, {elapsed} (eta {eta}) {msg}").expect("valid template"));
    for (mi, (name, m)) in materials.iter().enumerate() {
        let (linear, photo) = material_photo(m, mi, opts)?;
        let moved_truth = reference_renders(m, &moved.configs());
        let glossiness = highlights::glossiness(m);
        let cases: Vec<(Sampling, Vec<LightView>, Tensor)> = opts
            .cases
            .iter()
            .map(|&c| {
                let cfg = case_configs(c, opts.seed, mi, opts.configs);
                let reference = reference_renders(m, &cfg);
                (c, cfg, reference)
            })
            .collect();
        for (method, res) in methods.iter_mut().zip(results.iter_mut()) {
            bar.set_message(format!("{name} / {}", res.name));
            method.prepare(&photo).map_err(|e| anyhow!("{} on {name}: {e:#}", res.name))?;
            for (case, cfg, reference) in &cases {
                let pred = method.render(cfg).map_err(|e| anyhow!("{} on {name}: {e:#}", res.name))?;
                let scores = mean_scores(&score_renders(lpips, &pred, reference)?);
                res.rows.push(Row { material: name.clone(), case: *case, scores });
            }
            let method_name = res.name.clone();
            let fail = |e: anyhow::Error| anyhow!("{method_name} on {name}: {e:#}");
            let (h, moved_pred) = highlights::measure(method.as_ref(), name, glossiness, &linear, &moved_truth, &moved, Some(lpips)).map_err(fail)?;
            res.highlights.push(h);
            let curve = exposure::measure(method.as_mut(), name, &linear, &exposures, opts.ldr_input, &moved.configs(), Some(&moved_pred)).map_err(fail)?;
            res.exposure.extend(curve);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    Ok(results)
}

/// Checks an evaluation resolution: a multiple of 8 (M_est) and at least
/// 32 pixels (LPIPS needs 31x31).
pub fn check_eval_size(size: usize) -> Result<()> {
    ensure!(size >= 32, "--size must be at least 32 (LPIPS needs 31x31 pixels), got {size}");
    crate::infer::photo::check_size(size)
}

/// What [`run`] scored, and the dataset materials it could not read.
#[derive(Debug)]
pub struct EvalRun {
    pub results: Vec<MethodResults>,
    /// Materials scored.
    pub materials: usize,
    /// Dataset materials left out, named in `summary.md`.
    pub skipped: Vec<Unreadable>,
}

/// `flashmat eval`: loads methods and materials, scores them, writes the
/// CSVs, `summary.md` and the best/worst grids into `opts.out`. A dataset
/// material that cannot be read is left out (warned of, and listed in
/// `summary.md` and the result); the run fails only when none can be read.
pub fn run(opts: &EvalOptions) -> Result<EvalRun> {
    ensure!(!opts.cases.is_empty(), "give at least one case with --cases (reflect, identity, hemisphere)");
    ensure!(opts.configs > 0, "--configs must be at least 1");
    ensure!(opts.phone_photos.is_none() || opts.ldr_input, "--phone-photos needs --ldr-input (a phone writes 8-bit photos)");
    check_eval_size(opts.size)?;
    let mut cases = opts.cases.clone();
    cases.dedup();
    let opts = EvalOptions { cases, exposures: exposure_list(&opts.exposures)?, ..opts.clone() };
    let mut methods = open_methods(&opts.models, opts.ldr_input, opts.device, &opts.refine, &opts.exposure, opts.highlight_fill)?;
    let (materials, skipped) = load_readable_materials(&opts.dataset, opts.size, opts.limit)?;
    let lpips = Lpips::new(opts.device)?;
    std::fs::create_dir_all(&opts.out).map_err(|e| anyhow!("cannot create output folder {}: {e}", opts.out.display()))?;
    let results = evaluate(&mut methods, &materials, &opts, &lpips)?;
    report::write_reports(&opts, &results, &skipped)?;
    report::write_grids(&opts, &mut methods, &materials, &results)?;
    report::write_highlight_picture(&opts, &mut methods, &materials)?;
    Ok(EvalRun { results, materials: materials.len(), skipped })
}

/// The exposures to score, checked and sorted: finite, each once, 0
/// included (the relit scale's reference).
pub fn exposure_list(asked: &[f64]) -> Result<Vec<f64>> {
    let mut out = vec![0.0];
    for &ev in asked {
        ensure!(ev.is_finite() && ev.abs() <= 30.0, "--exposures: each exposure must be a number of stops within +-30, got {ev}");
        if !out.contains(&ev) {
            out.push(ev);
        }
    }
    out.sort_by(f64::total_cmp);
    Ok(out)
}

#[cfg(test)]
mod tests;
