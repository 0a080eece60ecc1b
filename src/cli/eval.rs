//! `flashmat eval`: scores models and the print-out baseline on held-out
//! materials (work done in `flashmat::eval`).

use flashmat::eval::captures::CaptureEvalOptions;
use flashmat::eval::shadows::ShadowEvalOptions;
use flashmat::data::phone::PhonePhotoConfig;
use flashmat::eval::{self, EvalOptions, DEFAULT_CONFIGS, PROCEDURAL_TEST};
use flashmat::svbrdf::shadow::ShadowOptions;
use flashmat::geometry::Sampling;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// A model file (flashmat export), or `printout` for the print-out baseline. Repeat to compare methods.
    /// `FILE+fit` (or `FILE+fitSTEPS`): the flashmat model's estimates fitted with GGX maps (`flashmat fit`), relit by GGX.
    #[arg(long = "model", value_name = "FILE|printout", required_unless_present = "summarize")]
    pub models: Vec<String>,
    /// Score nothing: re-read the NAME.csv files in the -o folder (CSVs of runs with the same dataset, seed and
    /// configurations, e.g. the unrefined and refined rows of two runs) and rewrite summary.md (and refine.png).
    #[arg(long, conflicts_with_all = ["models", "captures", "uniform"])]
    pub summarize: bool,
    /// `procedural-test` (the 50 held-out procedural materials), `procedural-test:I` (one of them), `procedural-dark-test`
    /// (30 held-out dark materials: diffuse albedo x0.02-0.35), `procedural-saturated-test` (30 held-out saturated
    /// materials: a full hue whose weakest channel is 0.004-0.1 of its strongest), `procedural-metals` (6 held-out coloured
    /// metals and saturated glossy materials: gold, copper, anodised aluminium, a glazed tile) or a dataset folder/strip file
    /// (materials centre-cropped to a square and resized to --size; one that cannot be read is left out and named in
    /// summary.md, and the run then exits with 1).
    #[arg(long, default_value = PROCEDURAL_TEST)]
    pub dataset: String,
    /// Score on real captures instead: a folder of photos NN.png of one flat material with camera_pos.txt, light_pos.txt
    /// (x,y,z per photo, origin at the sample centre) and image_size.txt (the sample's width, the positions' unit).
    /// Estimates from the photo nearest overhead, re-renders the others (1/r^2 fall-off compensated), LPIPS on display images.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["dataset", "cases", "seed", "limit", "configs", "ldr_input", "exposures"])]
    pub captures: Option<PathBuf>,
    /// With --captures: also score the several-photo fit of `estimate --capture` leave-one-out (each scored photo
    /// from a material fitted to all the other photos; one fit per photo, about 20 s each at 256 on 2 cores).
    #[arg(long, requires = "captures")]
    pub capture_fit: bool,
    /// Run the uniform-colour check instead: 9 flat colours, matte and glossy, estimated from their flash photo
    /// and re-rendered (identity, side light); writes uniform.md and uniform.json (flashmat models only).
    #[arg(long, conflicts_with_all = ["captures", "dataset", "cases", "seed", "limit", "configs", "ldr_input", "exposures"])]
    pub uniform: bool,
    /// Measure the renderer's ceiling instead (issue 48): on the --ceiling-materials glossiest held-out materials at
    /// --size, the model's estimate fitted (renderer frozen) to the true renders of the photo and K moved-highlight
    /// lights, one fit per K (default 0,5), then scored by the moved-highlight test; writes ceiling.md and ceiling.csv.
    #[arg(long, value_name = "K", num_args = 0..=1, value_delimiter = ',', default_missing_value = "0,5",
          conflicts_with_all = ["summarize", "captures", "uniform", "dataset", "cases", "seed", "limit", "configs", "exposures", "refine"])]
    pub ceiling: Option<Vec<usize>>,
    /// Adam steps of each ceiling fit.
    #[arg(long, value_name = "N", default_value_t = 300, value_parser = super::count)]
    pub ceiling_steps: usize,
    /// Glossiest held-out materials the ceiling scores.
    #[arg(long, value_name = "N", default_value_t = flashmat::eval::highlights::CHECK_MATERIALS, value_parser = super::count)]
    pub ceiling_materials: usize,
    /// Held-out materials the ceiling scores instead of the glossiest, by index (e.g. 32,42,22: matte ones).
    #[arg(long, value_name = "I", value_delimiter = ',', requires = "ceiling")]
    pub ceiling_only: Vec<usize>,
    /// Cases of the paper's table, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "reflect,identity,hemisphere")]
    pub cases: Vec<Sampling>,
    /// Output folder: NAME.csv per method, summary.md, best.jpg, worst.jpg, grids.txt, highlights/ (ratios.csv, moved.jpg:
    /// the moved-highlight test) and exposure/curve.csv (with --captures: captures.csv, summary.md, grid.jpg, grid.txt).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Resolution in pixels (a multiple of 8, at least 32; capture photos are resized to it).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Seed of the light/view configurations (fixed per material and case).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Evaluate only the first N materials.
    #[arg(long, value_name = "N", value_parser = super::count)]
    pub limit: Option<usize>,
    /// Configurations per material for Reflect and Hemisphere (the paper: 128).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_CONFIGS, value_parser = super::count)]
    pub configs: usize,
    /// Give the methods LDR photos (renders clamped to [0, 1]) instead of HDR ones.
    #[arg(long)]
    pub ldr_input: bool,
    /// Exposures in stops for the exposure curve, comma-separated (e.g. -6,-4,-2,0,1): the photo is the linear render
    /// x 2^EV, clamped after the scaling with --ldr-input; each method estimates from it and renders the identity and the
    /// moved-highlight lights (exposure/curve.csv, summary.md). 0 is always scored (identity brightness ratio).
    #[arg(long, value_name = "EV", value_delimiter = ',', allow_hyphen_values = true, default_value = "0")]
    pub exposures: Vec<f64>,
    /// cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Score every flashmat model with its estimates refined on the photo for STEPS steps (rows NAME+refineSTEPS;
    /// 100 when no number is given; comma-separated for several, 0 = the unrefined model, e.g. 0,100).
    #[arg(long, value_name = "STEPS", num_args = 0..=1, value_delimiter = ',', default_missing_value = flashmat::infer::refine::DEFAULT_REFINE_STEPS_ARG)]
    pub refine: Option<Vec<usize>>,
    #[command(flatten)]
    pub refine_weights: super::estimate_options::RefineWeights,
    /// How flashmat models handle the photo's exposure (see `flashmat estimate --help`).
    #[arg(long, value_enum, default_value_t = flashmat::infer::exposure::ExposureMode::Calibrated)]
    pub exposure_mode: flashmat::infer::exposure::ExposureMode,
    /// Also score every flashmat model with the photographed flash highlight filled in its map (rows NAME+fill;
    /// `copy`: codes copied from beside the highlight, `blend`: interpolated; see `flashmat estimate --help`).
    #[arg(long, value_enum, value_name = "MODE", num_args = 0..=1, default_missing_value = "copy")]
    pub highlight_fill: Option<flashmat::infer::highlight_fill::FillMode>,
    /// Give the methods phone photos of the held-out materials instead of the exact co-located render: the camera up
    /// to 0.3 off the centre and 0.85-1.2x the distance, the flash 1-2 cm beside the lens, sensor noise, 8-bit sRGB
    /// (one draw per material from --seed; needs --ldr-input). The truths are the same.
    #[arg(long, requires = "ldr_input", conflicts_with_all = ["captures", "uniform", "ceiling"])]
    pub phone_photos: bool,
    /// Save those phone photos as JPEGs, at a quality drawn from 85-95 per photo (needs --phone-photos).
    #[arg(long, requires = "phone_photos")]
    pub phone_jpeg: bool,
}

impl EvalArgs {
    fn highlight_fill_config(&self) -> Option<flashmat::infer::highlight_fill::HighlightFillConfig> {
        self.highlight_fill.map(flashmat::infer::highlight_fill::HighlightFillConfig::with_mode)
    }

    /// The variants asked for, checked (0 steps: the unrefined model).
    fn refine_configs(&self) -> Result<Vec<flashmat::infer::refine::RefineConfig>> {
        let mut steps = self.refine.clone().unwrap_or_default();
        steps.dedup();
        let configs: Vec<_> = steps.into_iter().map(|s| self.refine_weights.config(s)).collect();
        configs.iter().try_for_each(|c| c.validate())?;
        Ok(configs)
    }
}

pub fn eval(args: &EvalArgs) -> Result<()> {
    if args.summarize {
        // Nothing is scored: no device, no refinement.
        let opts = EvalOptions { device: tch::Device::Cpu, progress: false, refine: vec![], ..eval_options(args)? };
        eval::report::resummarize(&opts)?;
        return print_summary(&args.output);
    }
    if args.uniform {
        return uniform_check(args);
    }
    if let Some(fit_lights) = &args.ceiling {
        return ceiling(args, fit_lights);
    }
    if let Some(dir) = &args.captures {
        let opts = CaptureEvalOptions {
            models: args.models.clone(),
            dir: dir.clone(),
            out: args.output.clone(),
            size: args.size,
            device: flashmat::device::parse_device(&args.device)?,
            progress: true,
            refine: args.refine_configs()?,
            exposure: args.exposure_mode.config(),
            highlight_fill: args.highlight_fill_config(),
            capture_fit: args.capture_fit.then(flashmat::fit::photos::PhotoFitConfig::default),
        };
        eval::captures::run(&opts)?;
        return print_summary(&args.output);
    }
    let run = eval::run(&eval_options(args)?)?;
    print_summary(&args.output)?;
    if !run.skipped.is_empty() {
        return Err(flashmat::data::loaders::unreadable_error(&run.skipped, run.materials + run.skipped.len()));
    }
    Ok(())
}

/// The held-out evaluation's options from the command line.
fn eval_options(args: &EvalArgs) -> Result<EvalOptions> {
    Ok(EvalOptions {
        models: args.models.clone(),
        dataset: args.dataset.clone(),
        cases: args.cases.clone(),
        out: args.output.clone(),
        size: args.size,
        seed: args.seed,
        limit: args.limit,
        configs: args.configs,
        ldr_input: args.ldr_input,
        device: flashmat::device::parse_device(&args.device)?,
        progress: true,
        refine: args.refine_configs()?,
        exposures: args.exposures.clone(),
        exposure: args.exposure_mode.config(),
        highlight_fill: args.highlight_fill_config(),
        phone_photos: args.phone_photos.then(|| PhonePhotoConfig::saving_jpeg(args.phone_jpeg)),
    })
}

/// `eval --uniform`: the uniform-colour check of every flashmat model given.
fn uniform_check(args: &EvalArgs) -> Result<()> {
    let device = flashmat::device::parse_device(&args.device)?;
    anyhow::ensure!(args.size % 8 == 0 && args.size >= 16, "--size must be a multiple of 8 and at least 16 (got {})", args.size);
    let mut text = String::from("# Uniform-colour check\n\n");
    let mut all = serde_json::Map::new();
    for path in &args.models {
        anyhow::ensure!(path != flashmat::eval::PRINTOUT, "--uniform scores flashmat models (the print-out reproduces its photo exactly)");
        let loaded = flashmat::infer::load_model(Some(std::path::Path::new(path)), device)?;
        let rows = flashmat::eval::uniform::colour_check(&loaded.model, &loaded.info, args.size)?;
        let name = std::path::Path::new(path).file_stem().map_or(path.clone(), |s| s.to_string_lossy().into_owned());
        text.push_str(&flashmat::eval::uniform::markdown(&name, &rows));
        text.push('\n');
        all.insert(name, serde_json::json!({ "summary": flashmat::eval::uniform::summarize(&rows), "rows": rows }));
    }
    std::fs::create_dir_all(&args.output).with_context(|| format!("cannot create {}", args.output.display()))?;
    flashmat::io::atomic_write_bytes(&args.output.join("uniform.md"), text.as_bytes())?;
    flashmat::io::atomic_write_bytes(&args.output.join("uniform.json"), serde_json::to_string_pretty(&all)?.as_bytes())?;
    println!("{text}wrote {}", args.output.display());
    Ok(())
}

/// `eval --ceiling`: the renderer's ceiling of one flashmat model.
fn ceiling(args: &EvalArgs, fit_lights: &[usize]) -> Result<()> {
    use flashmat::eval::ceiling::{CeilingConfig, CeilingOptions};
    anyhow::ensure!(args.models.len() == 1 && args.models[0] != flashmat::eval::PRINTOUT, "--ceiling measures one flashmat model's renderer: give one --model FILE");
    let mut fit_lights = fit_lights.to_vec();
    fit_lights.dedup();
    let opts = CeilingOptions {
        model: PathBuf::from(&args.models[0]),
        ldr_input: args.ldr_input,
        out: args.output.clone(),
        device: flashmat::device::parse_device(&args.device)?,
        progress: true,
        config: CeilingConfig { fit_lights, steps: args.ceiling_steps, materials: args.ceiling_materials, only: args.ceiling_only.clone(), size: args.size, ..CeilingConfig::default() },
    };
    flashmat::eval::ceiling::run(&opts)?;
    println!("{}", std::fs::read_to_string(args.output.join("ceiling.md"))?);
    println!("wrote {}", args.output.display());
    Ok(())
}

/// Prints the `summary.md` an evaluation wrote into `out`, then where it went.
fn print_summary(out: &std::path::Path) -> Result<()> {
    println!("{}", std::fs::read_to_string(out.join("summary.md"))?);
    println!("wrote {}", out.display());
    Ok(())
}

#[derive(Args, Debug)]
pub struct ShadowEvalArgs {
    /// A model file (flashmat or baseline export), or `printout`. Repeat to compare methods.
    #[arg(long = "model", value_name = "FILE|printout", required = true)]
    pub models: Vec<String>,
    /// `procedural-test`, `procedural-test:I` (one held-out material: the over-fitting experiment) or a dataset folder
    /// (loaded maps get a height field integrated from their normals).
    #[arg(long, default_value = PROCEDURAL_TEST)]
    pub dataset: String,
    /// Output folder: shadows.csv, summary.md, grid-NAME.jpg and photo-NAME.jpg of the most shadowed materials.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Resolution in pixels (a multiple of 8, at least 32).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Evaluate only the first N materials.
    #[arg(long, value_name = "N", value_parser = super::count)]
    pub limit: Option<usize>,
    /// Lights per material (elevations 20/30/45/60 degrees in turn, spread in azimuth).
    #[arg(long, default_value_t = 8, value_parser = super::count)]
    pub lights: usize,
    /// Multiplies the height fields (use the value the model was trained with).
    #[arg(long, default_value_t = 1.0)]
    pub height_scale: f64,
    /// Grids of the N most shadowed materials.
    #[arg(long, value_name = "N", default_value_t = 3)]
    pub grids: usize,
    /// Give the methods LDR photos (renders clamped to [0, 1]) instead of HDR ones.
    #[arg(long)]
    pub ldr_input: bool,
    /// cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

pub fn shadow_eval(args: &ShadowEvalArgs) -> Result<()> {
    let opts = ShadowEvalOptions {
        models: args.models.clone(),
        dataset: args.dataset.clone(),
        out: args.output.clone(),
        size: args.size,
        limit: args.limit,
        lights: args.lights,
        shadows: ShadowOptions { height_scale: args.height_scale, ..Default::default() },
        ldr_input: args.ldr_input,
        grids: args.grids,
        device: flashmat::device::parse_device(&args.device)?,
        progress: true,
    };
    eval::shadows::run(&opts)?;
    print_summary(&args.output)
}
