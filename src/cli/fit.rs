//! `flashmat fit`: GGX maps fitted to a neural material, exported as PBR
//! texture sets (work done in `flashmat::fit`).

use super::estimate_options::EstimateOptions;
use super::infer::open_material;
use flashmat::fit::export::{check_output_dir, write_fit, GLTF_DIR, GLTF_FILE, MAPS_DIR, SVBRDF_DIR};
use flashmat::fit::relief::ReliefConfig;
use flashmat::fit::{fit_material, FitConfig};
use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct FitArgs {
    /// A neural material (.nmat), or a flash photo (estimated first, as `relight` does, with the options below).
    /// Several, or a folder (its .nmat/.png/.jpg/.jpeg/.exr/.heic/.avif files), make a batch: one OUTDIR/NAME/ each.
    #[arg(required = true, num_args = 1.., value_name = "MATERIAL|DIR")]
    pub material: Vec<PathBuf>,
    /// Output folder (written whole or not at all; an earlier fit's folder is replaced); for a batch, the folder
    /// that receives one fit folder per input.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Adam steps of the per-pixel fit.
    #[arg(long, default_value_t = FitConfig::default().steps)]
    pub steps: usize,
    /// Light/view direction pairs shared by all pixels (each costs one neural render of the material).
    #[arg(long, default_value_t = FitConfig::default().samples)]
    pub samples: usize,
    /// Adam step size in the unconstrained parameters (decayed to a tenth).
    #[arg(long, value_name = "LR", default_value_t = FitConfig::default().learning_rate)]
    pub fit_lr: f64,
    /// Weight of the edge-aware smoothness of the fitted maps (0: none).
    #[arg(long, value_name = "W", default_value_t = FitConfig::default().smooth_weight)]
    pub smooth: f64,
    /// Multiplies the fitted relief for ao.png only (1: as fitted; nearly flat materials then give AO near 1).
    #[arg(long, value_name = "X", allow_negative_numbers = true, default_value_t = ReliefConfig::default().ao_depth)]
    pub ao_depth: f64,
    /// Seed of the direction pairs.
    #[arg(long, default_value_t = FitConfig::default().seed)]
    pub seed: u64,
    #[command(flatten)]
    pub estimate: EstimateOptions,
}

pub fn fit(a: &FitArgs) -> Result<()> {
    let cfg = FitConfig { steps: a.steps, samples: a.samples, learning_rate: a.fit_lr, smooth_weight: a.smooth, seed: a.seed };
    cfg.validate()?;
    let relief = ReliefConfig { ao_depth: a.ao_depth, ..Default::default() };
    relief.validate()?;
    if super::batch::is_batch(&a.material) {
        let mut extensions = super::batch::PHOTO_EXTENSIONS.to_vec();
        extensions.push("nmat");
        let total = cfg.samples + cfg.steps;
        return super::batch::run_batch("fit", &a.material, &extensions, &a.output, "", |input, output, bar| {
            check_output_dir(output)?;
            let (material, _) = open_material(input, &a.estimate)?;
            // The batch's one bar shows this fit's progress in its message.
            let result = fit_material(&material, &cfg, |done, _| bar.set_message(format!("{} {done}/{total}", input.display())))?;
            let report = write_fit(output, &result, &relief, &input.display().to_string())?;
            Ok(format!("mean error {:.4}", report.fit.mean_error))
        });
    }
    let input = &a.material[0];
    check_output_dir(&a.output)?;
    let (material, summary) = open_material(input, &a.estimate)?;
    let bar = ProgressBar::new((cfg.samples + cfg.steps) as u64)
        .with_style(ProgressStyle::with_template("fitting {bar:40} {pos}/{len} (direction pairs, then steps) ETA {eta}")?);
    let result = fit_material(&material, &cfg, |done, _| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    let report = write_fit(&a.output, &result, &relief, &input.display().to_string())?;
    summary.iter().for_each(|l| eprintln!("{l}"));
    eprintln!("{}", report.fit.summary());
    eprintln!(
        "glTF metallic-roughness conversion (mean metallic {:.3}) costs {:.4} in the same error",
        report.mean_metallic, report.gltf_conversion_error
    );
    let d = a.output.display();
    eprintln!("wrote {d}: {MAPS_DIR}/ (textures + README), {SVBRDF_DIR}/ (`flashmat render --svbrdf {d}/{SVBRDF_DIR}`), {GLTF_DIR}/{GLTF_FILE}, error.png, fit.json");
    Ok(())
}
