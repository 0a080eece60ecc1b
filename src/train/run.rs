//! The training loop around [`Trainer`]: run folder, progress bar, JSONL
//! log, loss charts, preview grids, periodic and final checkpoints, resume.
//!
//! A run folder holds `config.json`, `checkpoint.safetensors`, `log.jsonl`,
//! `losses.png` and `previews/step-NNNNNNN.png`. The same loop trains
//! flashmat ([`Trainer`]) and the baselines ([`BaselineTrainer`]) through
//! [`RunTrainer`]; [`start_any`] / [`resume_any`] pick the trainer from the
//! configuration's (or the checkpoint's) method.

use super::batches::{batch_for_step, MaterialStream, Prefetcher};
use super::{BaselineTrainer, Shard, StepLosses, TrainConfig, Trainer};
use crate::dist::Group;
use crate::data::samples::TrainingBatch;
use crate::image::{all_finite, Image};
use crate::viz::{self, Series};
use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use tch::{Device, Kind};

pub fn checkpoint_path(run: &Path) -> PathBuf {
    run.join("checkpoint.safetensors")
}

fn log_path(run: &Path) -> PathBuf {
    run.join("log.jsonl")
}

/// Reads the JSONL log (lines that do not parse are skipped).
pub fn read_log(run: &Path) -> Vec<StepLosses> {
    std::fs::read_to_string(log_path(run))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// Drops log lines after `step` (they will be trained again after a resume).
fn truncate_log(run: &Path, step: u64) -> Result<()> {
    let kept: Vec<String> = read_log(run).into_iter().filter(|l| l.step <= step).map(|l| serde_json::to_string(&l)).collect::<Result<_, _>>()?;
    let mut text = kept.join("\n");
    if !text.is_empty() {
        text.push('\n');
    }
    crate::io::atomic_write_bytes(&log_path(run), text.as_bytes())
}

/// Moving average over `window` points, for readable charts.
fn smooth(points: &[(f64, f64)], window: usize) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(points.len());
    let mut sum = 0.0;
    for i in 0..points.len() {
        sum += points[i].1;
        if i >= window {
            sum -= points[i - window].1;
        }
        out.push((points[i].0, sum / (i + 1).min(window) as f64));
    }
    out
}

/// Writes `losses.png` from the log.
pub fn write_charts(run: &Path) -> Result<()> {
    let log: Vec<StepLosses> = read_log(run).into_iter().filter(|l| !l.skipped).collect();
    if log.len() < 2 {
        return Ok(());
    }
    let window = (log.len() / 50).clamp(1, 200);
    let series = |name: &str, f: fn(&StepLosses) -> f64| Series {
        name: name.into(),
        points: smooth(&log.iter().map(|l| (l.step as f64, f(l))).collect::<Vec<_>>(), window),
    };
    let top = viz::line_chart(
        "training losses (moving average)",
        &[series("L1 log (M_est)", |l| l.l1), series("L1 sampled (renderer)", |l| l.l1_render), series("LPIPS", |l| l.lpips)],
        900,
        360,
    )?;
    let bottom = viz::line_chart(
        "adversarial terms",
        &[series("|D(pred)-1|", |l| l.adv), series("discriminator LS loss", |l| l.loss_disc)],
        900,
        360,
    )?;
    let chart = viz::grid(&[vec![top], vec![bottom]], 0)?;
    crate::io::write_png(&run.join("losses.png"), &chart, crate::io::BitDepth::Eight)
}

/// Input | targets (top row) and neural-map norm | predictions (bottom row)
/// for the first material of a batch.
pub fn preview_grid(trainer: &Trainer, batch: &TrainingBatch, max_outputs: usize) -> Result<Image> {
    let k = (batch.targets.size()[1] as usize).min(max_outputs) as i64;
    tch::no_grad(|| -> Result<Image> {
        let x = batch.est_input.narrow(0, 0, 1);
        let neural = trainer.model.est.forward_t(&x, false)?;
        let pred = trainer.model.renderer.forward_maps(&neural, &batch.out_wi.narrow(0, 0, 1).narrow(1, 0, k), &batch.out_wo.narrow(0, 0, 1).narrow(1, 0, k))?;
        let display = Image::display_of;
        let mut top = vec![display(&batch.input_linear.get(0))?];
        let norm = neural.get(0).square().sum_dim_intlist([0i64].as_slice(), true, Kind::Float).sqrt();
        let norm = &norm / norm.max().clamp_min(1e-8);
        let mut bottom = vec![Image::from_tensor(&norm)?];
        for i in 0..k {
            top.push(display(&batch.targets.get(0).get(i))?);
            bottom.push(display(&crate::spaces::from_log(&pred.get(0).get(i)))?);
        }
        viz::grid(&[top, bottom], 2)
    })
}

/// What the run loop needs from a trainer.
pub trait RunTrainer: Sized {
    fn config(&self) -> &TrainConfig;
    fn config_mut(&mut self) -> &mut TrainConfig;
    /// Steps completed.
    fn steps_done(&self) -> u64;
    fn train_step(&mut self, batch: &TrainingBatch) -> Result<StepLosses>;
    fn save_checkpoint(&self, path: &Path) -> Result<()>;
    fn preview_grid(&self, batch: &TrainingBatch, max_outputs: usize) -> Result<Image>;
    /// Writes the inference weights as an exported model file (`flashmat
    /// export`; large weights as f16 when `half`).
    fn export_model(&self, path: &Path, half: bool) -> Result<()>;
    /// The uniform-colour check's summary of the current networks (flashmat
    /// runs; `None` for the baselines).
    fn colour_summary(&self) -> Option<Result<crate::eval::uniform::ColourSummary>> {
        None
    }
    /// The photo check's means on the bundled real photos (flashmat runs
    /// where the photos are found; `None` otherwise).
    fn photo_summary(&self) -> Option<Result<crate::eval::photos::PhotoSummary>> {
        None
    }
    /// The moved-highlight test's ratios on a few glossy held-out materials
    /// (flashmat runs; `None` for the baselines).
    fn highlight_summary(&self) -> Option<Result<crate::eval::highlights::HighlightSummary>> {
        None
    }
    /// Whether every weight is finite and so are the networks' inference
    /// outputs on `batch`. Checked before anything of the networks is
    /// written: a diverging step can leave huge but finite weights whose
    /// next forward pass overflows.
    fn is_finite_on(&self, batch: &TrainingBatch) -> Result<bool>;
    /// Projects the weights onto the configuration's constraints (flashmat's
    /// `checkerboard_free`); called when a run starts or resumes.
    fn apply_weight_constraints(&self) {}
    /// Fresh networks for a configuration.
    fn create(config: TrainConfig, device: Device) -> Result<Self>;
    /// Rebuilds the trainer from a checkpoint.
    fn resume_from(path: &Path, device: Device) -> Result<Self>;
    /// Joins a data-parallel run: rank 0's weights everywhere, gradients
    /// averaged over the ranks at every step.
    fn join(&mut self, group: Arc<Group>) -> Result<()>;
}

impl RunTrainer for Trainer {
    fn config(&self) -> &TrainConfig {
        &self.config
    }
    fn config_mut(&mut self) -> &mut TrainConfig {
        &mut self.config
    }
    fn steps_done(&self) -> u64 {
        self.step
    }
    fn train_step(&mut self, batch: &TrainingBatch) -> Result<StepLosses> {
        Trainer::train_step(self, batch)
    }
    fn save_checkpoint(&self, path: &Path) -> Result<()> {
        Trainer::save_checkpoint(self, path)
    }
    fn preview_grid(&self, batch: &TrainingBatch, max_outputs: usize) -> Result<Image> {
        preview_grid(self, batch, max_outputs)
    }
    fn export_model(&self, path: &Path, half: bool) -> Result<()> {
        let info = model_info(&self.config, self.step);
        self.model.save(path, &info, half)
    }
    fn colour_summary(&self) -> Option<Result<crate::eval::uniform::ColourSummary>> {
        let info = model_info(&self.config, self.step);
        Some(crate::eval::uniform::colour_check(&self.model, &info, COLOUR_CHECK_SIZE).map(|rows| crate::eval::uniform::summarize(&rows)))
    }
    fn photo_summary(&self) -> Option<Result<crate::eval::photos::PhotoSummary>> {
        let info = model_info(&self.config, self.step);
        crate::eval::photos::photo_check(&self.model, &info, PHOTO_CHECK_SIZE).transpose()
    }
    fn highlight_summary(&self) -> Option<Result<crate::eval::highlights::HighlightSummary>> {
        let info = model_info(&self.config, self.step);
        Some(crate::eval::highlights::highlight_check(&self.model, &info, HIGHLIGHT_CHECK_SIZE))
    }
    fn is_finite_on(&self, batch: &TrainingBatch) -> Result<bool> {
        if !stores_finite(&[&self.model.est_vs, &self.model.renderer_vs, &self.disc_vs]) {
            return Ok(false);
        }
        tch::no_grad(|| {
            let neural = self.model.est.forward_t(&batch.est_input, false)?;
            let pred = self.model.renderer.forward_maps(&neural, &batch.out_wi, &batch.out_wo)?;
            Ok(all_finite(&neural) && all_finite(&pred))
        })
    }
    fn apply_weight_constraints(&self) {
        Trainer::apply_weight_constraints(self)
    }
    fn create(config: TrainConfig, device: Device) -> Result<Self> {
        let (init, warm) = (config.init_from.clone(), config.warm_start.clone());
        let mut t = Trainer::new(config, device)?;
        if let Some(run) = init {
            t.load_weights_from(&checkpoint_path(Path::new(&run)))?;
        }
        if let Some(file) = warm {
            t.warm_start_from(Path::new(&file))?;
        }
        Ok(t)
    }
    fn resume_from(path: &Path, device: Device) -> Result<Self> {
        Trainer::resume(path, device, None)
    }
    fn join(&mut self, group: Arc<Group>) -> Result<()> {
        Trainer::join(self, group)
    }
}

impl RunTrainer for BaselineTrainer {
    fn config(&self) -> &TrainConfig {
        &self.config
    }
    fn config_mut(&mut self) -> &mut TrainConfig {
        &mut self.config
    }
    fn steps_done(&self) -> u64 {
        self.step
    }
    fn train_step(&mut self, batch: &TrainingBatch) -> Result<StepLosses> {
        BaselineTrainer::train_step(self, batch)
    }
    fn save_checkpoint(&self, path: &Path) -> Result<()> {
        BaselineTrainer::save_checkpoint(self, path)
    }
    fn preview_grid(&self, batch: &TrainingBatch, max_outputs: usize) -> Result<Image> {
        BaselineTrainer::preview_grid(self, batch, max_outputs)
    }
    fn export_model(&self, path: &Path, half: bool) -> Result<()> {
        let info = model_info(&self.config, self.step);
        self.net.save(path, &info, half)
    }
    fn is_finite_on(&self, batch: &TrainingBatch) -> Result<bool> {
        if !stores_finite(&[&self.net.vs, &self.disc_vs]) {
            return Ok(false);
        }
        let pred = tch::no_grad(|| self.net.forward_t(&batch.est_input, &batch.out_wi, &batch.out_wo, false))?;
        Ok(all_finite(&pred))
    }
    fn create(config: TrainConfig, device: Device) -> Result<Self> {
        anyhow::ensure!(config.init_from.is_none() && config.warm_start.is_none(), "--init-from and --warm-start only apply to --method flashmat");
        BaselineTrainer::new(config, device)
    }
    fn resume_from(path: &Path, device: Device) -> Result<Self> {
        BaselineTrainer::resume(path, device)
    }
    fn join(&mut self, group: Arc<Group>) -> Result<()> {
        BaselineTrainer::join(self, group)
    }
}

/// Whether every variable of the stores is finite.
fn stores_finite(stores: &[&tch::nn::VarStore]) -> bool {
    stores.iter().all(|vs| vs.variables().values().all(all_finite))
}

/// The trainer of either kind of run.
pub enum AnyTrainer {
    Flashmat(Trainer),
    Baseline(BaselineTrainer),
}

impl AnyTrainer {
    pub fn config(&self) -> &TrainConfig {
        match self {
            Self::Flashmat(t) => &t.config,
            Self::Baseline(t) => &t.config,
        }
    }
    pub fn steps_done(&self) -> u64 {
        match self {
            Self::Flashmat(t) => t.step,
            Self::Baseline(t) => t.step,
        }
    }
}

/// Options of one `flashmat train` invocation.
pub struct RunOptions {
    pub run_dir: PathBuf,
    pub device: Device,
    /// Stop after this many steps in this invocation (tests, time-boxed runs).
    pub max_steps_this_run: Option<u64>,
    /// Stop cleanly (checkpoint, export) once this many minutes have passed
    /// in this invocation, counted from before the data is opened.
    pub max_minutes: Option<f64>,
    /// Also write `model.safetensors` (an f16 export) here at every
    /// checkpoint: what a time-limited GPU job brings back.
    pub export_dir: Option<PathBuf>,
    /// With `export_dir`: also keep each checkpoint's export as
    /// `step-N.safetensors` beside it, for `flashmat average` over a run's
    /// last checkpoints (a model averaged over them beat each of them).
    pub keep_exports: bool,
    /// With a resume: a new learning rate from the resumed step on (how a
    /// diverged run continues from its last good checkpoint), recorded in
    /// the configuration of its next checkpoints.
    pub new_lr: Option<f64>,
    /// With a resume: keep M_est's upsampling checkerboard-free from the
    /// resumed step on (`TrainConfig::checkerboard_free`), recorded likewise.
    pub checkerboard_free: bool,
    /// With a resume: a new fraction of recoloured training materials
    /// (`TrainConfig::colour_augment`) from the resumed step on, recorded likewise.
    pub new_colour_augment: Option<f64>,
    /// With a resume: co-located outputs per material
    /// (`TrainConfig::colocated_outputs`) from the resumed step on, recorded likewise.
    pub new_colocated_outputs: Option<usize>,
    pub progress: bool,
    /// The process group of a data-parallel run (torchrun): this process
    /// trains its share of every step's global batch, rank 0 alone writes
    /// the run folder and the exports (docs/DISTRIBUTED.md).
    pub group: Option<Arc<Group>>,
}

impl RunOptions {
    /// Options of a plain run in `run_dir` (no step, time or export limits).
    pub fn new(run_dir: impl Into<PathBuf>, device: Device, progress: bool) -> Self {
        Self { run_dir: run_dir.into(), device, max_steps_this_run: None, max_minutes: None, export_dir: None, keep_exports: false, new_lr: None, checkerboard_free: false, new_colour_augment: None, new_colocated_outputs: None, progress, group: None }
    }
}

impl RunOptions {
    /// Whether this process writes the run folder: a plain run, or rank 0.
    pub fn leader(&self) -> bool {
        self.group.as_ref().is_none_or(|g| g.is_leader())
    }
}

/// A data-parallel run's trainer takes its share of the global batch
/// (drawn per material, so the global batch is the same at every world
/// size; recorded, so a later resume draws so too) and rank 0's weights.
fn enter_group<T: RunTrainer>(trainer: &mut T, opts: &RunOptions) -> Result<()> {
    let Some(group) = &opts.group else { return Ok(()) };
    let cfg = trainer.config_mut();
    cfg.shard = Shard { rank: group.rank, world: group.world };
    cfg.material_streams = true;
    let batch = cfg.materials_per_batch;
    trainer.join(group.clone())?;
    if group.is_leader() {
        let backend = if group.device.is_cuda() { "NCCL" } else { "Gloo" };
        let ranks = if group.world == 1 { "1 rank".to_string() } else { format!("{} ranks", group.world) };
        eprintln!("data-parallel training: {ranks} ({backend}) x --batch {batch} = a global batch of {} materials a step", group.world * batch);
    }
    Ok(())
}

/// What an exported model (and the checks run on the live networks)
/// records of the run: its input range and the steps done.
fn model_info(config: &TrainConfig, steps: u64) -> crate::model::ModelInfo {
    crate::model::ModelInfo { ldr_input: config.ldr_input, steps }
}

/// Resolution of the uniform-colour check logged at every checkpoint
/// (`colour.jsonl`): flat materials need few pixels, and it costs well
/// under a second.
const COLOUR_CHECK_SIZE: usize = 32;

/// Resolution of the photo check logged beside it (`colour.jsonl`,
/// `photo_*`): the 13 bundled photos at 128 pixels, 6-9 s a checkpoint
/// for the compact preset on the shared 2-core machine (256: 29-39 s).
/// The chromaticity error at 128 follows the one at 256 within 0.003 on
/// four models (0.066 / 0.064, 0.077 / 0.078, 0.112 / 0.110, 0.045 /
/// 0.048), in the same order; at 64 it is off by up to 0.011.
const PHOTO_CHECK_SIZE: usize = 128;

/// Resolution of the moved-highlight check logged beside them
/// (`colour.jsonl`, `highlight_*`): six glossy held-out materials, 4.7 s a
/// checkpoint for the bundled compact model on the shared 2-core machine
/// (64: 1.6 s, but the ratios move: ghost 3.95 against 2.49 at 128).
const HIGHLIGHT_CHECK_SIZE: usize = 128;

/// File name of the model that `RunOptions::export_dir` receives.
pub const EXPORT_FILE: &str = "model.safetensors";

/// File name of the export kept at `steps` with `RunOptions::keep_exports`.
pub fn kept_export_name(steps: u64) -> String {
    format!("step-{steps}.safetensors")
}

/// Starts a new flashmat run (fails if the folder already holds a checkpoint).
pub fn start(config: TrainConfig, opts: &RunOptions) -> Result<Trainer> {
    start_with::<Trainer>(config, opts)
}

/// Starts a new baseline run (`config.method` analytic or relight-unet).
pub fn start_baseline(config: TrainConfig, opts: &RunOptions) -> Result<BaselineTrainer> {
    start_with::<BaselineTrainer>(config, opts)
}

/// Starts a new run of the configuration's method.
pub fn start_any(config: TrainConfig, opts: &RunOptions) -> Result<AnyTrainer> {
    if config.method.is_flashmat() {
        start(config, opts).map(AnyTrainer::Flashmat)
    } else {
        start_baseline(config, opts).map(AnyTrainer::Baseline)
    }
}

/// Takes ownership of a run folder for this process ([`crate::io::lock_folder`]:
/// a second `train` or `--resume` of it meets one error line) and removes
/// the temporaries that a killed owner left in it.
fn own_run_folder(run: &Path) -> Result<crate::io::FolderLock> {
    let lock = crate::io::lock_folder(run)?;
    for dir in [run.to_path_buf(), run.join("previews")] {
        crate::io::remove_stale_temporaries(&dir);
    }
    Ok(lock)
}

fn start_with<T: RunTrainer>(config: TrainConfig, opts: &RunOptions) -> Result<T> {
    let ckpt = checkpoint_path(&opts.run_dir);
    let holds_a_run = || anyhow::anyhow!("{} already holds a run; continue it with `flashmat train --resume {}`", opts.run_dir.display(), opts.run_dir.display());
    if !opts.leader() {
        // Rank 0 owns the run folder; the others train and write nothing.
        let mut trainer = T::create(config, opts.device)?;
        enter_group(&mut trainer, opts)?;
        return train_loop(trainer, opts);
    }
    if ckpt.exists() {
        return Err(holds_a_run());
    }
    // Networks first: a refused configuration (bad --init-from) leaves no run folder behind.
    let mut trainer = T::create(config, opts.device)?;
    enter_group(&mut trainer, opts)?;
    let config_json = serde_json::to_string_pretty(trainer.config())?;
    let created = !opts.run_dir.exists();
    let remove_created = || {
        if created && !ckpt.exists() {
            let _ = std::fs::remove_dir_all(&opts.run_dir);
        }
    };
    if let Err(e) = std::fs::create_dir_all(&opts.run_dir) {
        remove_created();
        return Err(e).with_context(|| format!("cannot create run folder {}", opts.run_dir.display()));
    }
    // A run started in the same folder at the same moment owns it now (and
    // the folder, even one this process created): leave both alone.
    let _lock = own_run_folder(&opts.run_dir)?;
    if ckpt.exists() {
        return Err(holds_a_run());
    }
    let result = std::fs::create_dir_all(opts.run_dir.join("previews"))
        .with_context(|| format!("cannot create run folder {}", opts.run_dir.display()))
        .and_then(|_| crate::io::atomic_write_bytes(&opts.run_dir.join("config.json"), config_json.as_bytes()))
        .and_then(|_| {
            let _ = std::fs::remove_file(log_path(&opts.run_dir));
            train_loop(trainer, opts)
        });
    // A start that failed before its first checkpoint (unreadable data, a
    // diverging first step) leaves no run folder behind.
    if result.is_err() {
        remove_created();
    }
    result
}

/// Continues a flashmat run from its last checkpoint, optionally to a new step total.
pub fn resume(opts: &RunOptions, steps: Option<u64>) -> Result<Trainer> {
    resume_with::<Trainer>(opts, steps)
}

/// Continues a baseline run from its last checkpoint.
pub fn resume_baseline(opts: &RunOptions, steps: Option<u64>) -> Result<BaselineTrainer> {
    resume_with::<BaselineTrainer>(opts, steps)
}

/// Continues a run of whichever method its checkpoint records.
pub fn resume_any(opts: &RunOptions, steps: Option<u64>) -> Result<AnyTrainer> {
    let ckpt = checkpoint_path(&opts.run_dir);
    anyhow::ensure!(ckpt.exists(), "{} holds no checkpoint to resume", opts.run_dir.display());
    if Trainer::checkpoint_config(&ckpt)?.method.is_flashmat() {
        resume(opts, steps).map(AnyTrainer::Flashmat)
    } else {
        resume_baseline(opts, steps).map(AnyTrainer::Baseline)
    }
}

fn resume_with<T: RunTrainer>(opts: &RunOptions, steps: Option<u64>) -> Result<T> {
    let ckpt = checkpoint_path(&opts.run_dir);
    anyhow::ensure!(ckpt.exists(), "{} holds no checkpoint to resume", opts.run_dir.display());
    let _lock = if opts.leader() { Some(own_run_folder(&opts.run_dir)?) } else { None };
    let mut trainer = T::resume_from(&ckpt, opts.device)?;
    if let Some(s) = steps {
        check_new_total(&opts.run_dir, trainer.steps_done(), s)?;
        trainer.config_mut().steps = s;
    }
    if let Some(lr) = opts.new_lr {
        trainer.config_mut().lr = lr;
        trainer.config().validate()?;
    }
    if opts.checkerboard_free {
        trainer.config_mut().checkerboard_free = true;
        trainer.config().validate()?;
    }
    if let Some(p) = opts.new_colour_augment {
        trainer.config_mut().colour_augment = p;
        trainer.config().validate()?;
    }
    if let Some(c) = opts.new_colocated_outputs {
        trainer.config_mut().colocated_outputs = c;
        trainer.config().validate()?;
    }
    enter_group(&mut trainer, opts)?;
    if opts.leader() {
        truncate_log(&opts.run_dir, trainer.steps_done())?;
    }
    train_loop(trainer, opts)
}

/// A resumed run's new total `--steps` must lie beyond the `done` steps:
/// anything else would train nothing (and used to exit 0 in silence).
fn check_new_total(run: &Path, done: u64, steps: u64) -> Result<()> {
    anyhow::ensure!(
        steps > done,
        "run {} is already at step {done}: --steps {steps} trains nothing (with --resume, --steps is the new total; give more than {done})",
        run.display()
    );
    Ok(())
}

/// Writes the checkpoint, the charts and (with an export folder) the f16
/// export: everything a stopped run leaves.
fn save_all<T: RunTrainer>(trainer: &T, opts: &RunOptions) -> Result<()> {
    trainer.save_checkpoint(&checkpoint_path(&opts.run_dir))?;
    write_charts(&opts.run_dir)?;
    if let Some(dir) = &opts.export_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create export folder {}", dir.display()))?;
        trainer.export_model(&dir.join(EXPORT_FILE), true)?;
        if opts.keep_exports {
            // Copied all-or-nothing, as the export itself is written.
            let export = dir.join(EXPORT_FILE);
            crate::io::atomic_write(&dir.join(kept_export_name(trainer.steps_done())), |tmp| std::fs::copy(&export, tmp).map(drop).map_err(Into::into))?;
        }
    }
    Ok(())
}

/// Set by SIGINT (Ctrl-C), SIGTERM and SIGHUP once [`catch_stop_signals`]
/// ran: the training loops checkpoint and return at the end of the step.
static STOP: AtomicBool = AtomicBool::new(false);

/// Routes SIGINT, SIGTERM (a job scheduler, `kill`) and SIGHUP (a closed
/// terminal) to [`stop_requested`] for the rest of the process, so that
/// each ends a training run with a checkpoint instead of losing the steps
/// since the last one.
pub fn catch_stop_signals() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if let Err(e) = ctrlc::set_handler(|| STOP.store(true, Ordering::SeqCst)) {
            eprintln!("warning: cannot catch Ctrl-C/SIGTERM ({e}); an interrupted run loses the steps since its last checkpoint");
        }
    });
}

/// Whether a stop signal arrived (see [`catch_stop_signals`]).
pub fn stop_requested() -> bool {
    STOP.load(Ordering::SeqCst)
}

/// Steps in a row with a NaN/Inf loss or gradient after which a run counts
/// as diverged: one odd batch is skipped, a diverged network makes every
/// step non-finite.
pub const MAX_SKIPPED_IN_A_ROW: u64 = 10;

/// The one-line error of a diverged run, saying what was kept.
fn diverged(step: u64, why: &str, run: &Path, last_good: Option<u64>) -> anyhow::Error {
    match last_good {
        Some(k) => anyhow::anyhow!(
            "training diverged at step {step} ({why}); nothing was written, the last good checkpoint (step {k}) is kept: continue it with a smaller learning rate, `flashmat train --resume {} --lr LR`",
            run.display()
        ),
        None => anyhow::anyhow!("training diverged at step {step} ({why}) before its first checkpoint; nothing was kept (try a smaller --lr)"),
    }
}

fn flush(log: &mut Option<std::fs::File>) -> Result<()> {
    if let Some(log) = log {
        log.flush()?;
    }
    Ok(())
}

/// A data-parallel step's agreement, one small collective: the losses
/// averaged over the ranks (what the log records: the global batch's, as
/// every loss is a mean over equal shares), whether any rank was asked to
/// stop, and rank 0's time box (`timed_out` is only ever true there).
fn agree_on_step(group: &Group, losses: &mut StepLosses, stop: bool, timed_out: bool) -> Result<(bool, bool)> {
    let l = &*losses;
    let values = [l.l1, l.lpips, l.adv, l.loss_est, l.l1_render, l.loss_render, l.loss_disc, l.code, l.shift, l.ggx_values, l.param_norm, stop as u8 as f64, timed_out as u8 as f64];
    let sum = group.sum_f64(&values)?;
    let mean: Vec<f64> = sum.iter().map(|v| v / group.world as f64).collect();
    let l = losses;
    [l.l1, l.lpips, l.adv, l.loss_est, l.l1_render, l.loss_render, l.loss_disc, l.code, l.shift, l.ggx_values, l.param_norm] = mean[..11].try_into().expect("eleven losses");
    Ok((sum[11] > 0.0, sum[12] > 0.0))
}

/// Whether `ok` holds on every rank (a plain run: `ok`).
fn all_ranks(group: &Option<Arc<Group>>, ok: bool) -> Result<bool> {
    match group {
        Some(g) => Ok(g.sum_f64(&[if ok { 0.0 } else { 1.0 }])?[0] == 0.0),
        None => Ok(ok),
    }
}

fn train_loop<T: RunTrainer>(mut trainer: T, opts: &RunOptions) -> Result<T> {
    let started = Instant::now();
    let out_of_time = || opts.max_minutes.is_some_and(|m| started.elapsed().as_secs_f64() >= m * 60.0);
    let cfg = trainer.config().clone();
    let run = &opts.run_dir;
    trainer.apply_weight_constraints();
    catch_stop_signals();
    let first = trainer.steps_done();
    // The checkpoint on disk: the one resumed from, if any.
    let mut last_good = checkpoint_path(run).exists().then_some(first);
    let last = match opts.max_steps_this_run {
        Some(n) => cfg.steps.min(first + n),
        None => cfg.steps,
    };
    if first >= last {
        return Ok(trainer);
    }
    let stream = MaterialStream::open(&cfg)?;
    let prefetch = Prefetcher::start(stream, cfg.clone(), first, 4);
    let leader = opts.leader();
    let bar = if opts.progress && leader { ProgressBar::new(cfg.steps) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("{bar:30} {pos}/{len} steps  {per_sec}  ETA {eta}  {msg}")?);
    bar.set_position(first);
    let mut log = match leader {
        true => Some(std::fs::OpenOptions::new().create(true).append(true).open(log_path(run)).with_context(|| format!("cannot write {}", log_path(run).display()))?),
        false => None,
    };
    if let Some(group) = &opts.group {
        group.take_seconds(); // joining's broadcast is no step's
    }
    let mut skipped = 0u64;
    let mut skipped_in_a_row = 0u64;
    while trainer.steps_done() < last {
        let step = trainer.steps_done();
        let t0 = Instant::now();
        let materials = prefetch.next(step)?;
        let batch = batch_for_step(&cfg, &materials, step, opts.device)?;
        let mut losses = trainer.train_step(&batch)?;
        // Rank 0 decides the time box, any rank's stop signal stops all.
        let (stop, timed_out) = match &opts.group {
            Some(group) => agree_on_step(group, &mut losses, stop_requested(), leader && out_of_time())?,
            None => (stop_requested(), out_of_time()),
        };
        losses.seconds = t0.elapsed().as_secs_f64();
        if let Some(group) = &opts.group {
            losses.sync_seconds = group.take_seconds();
        }
        if losses.skipped {
            skipped += 1;
            skipped_in_a_row += 1;
            bar.println(format!("step {}: NaN/Inf loss or gradient, update skipped", losses.step));
        } else {
            skipped_in_a_row = 0;
        }
        if let Some(log) = &mut log {
            writeln!(log, "{}", serde_json::to_string(&losses)?)?;
        }
        bar.set_message(format!("L1 {:.4}  LPIPS {:.3}  skipped {skipped}", losses.l1, losses.lpips));
        bar.set_position(trainer.steps_done());
        let done = trainer.steps_done();
        if skipped_in_a_row >= MAX_SKIPPED_IN_A_ROW {
            flush(&mut log)?;
            bar.abandon();
            return Err(diverged(done, &format!("NaN/Inf losses or gradients for {skipped_in_a_row} steps in a row"), run, last_good));
        }
        let preview_due = cfg.preview_every > 0 && done % cfg.preview_every == 0;
        let checkpoint_due = done % cfg.checkpoint_every.max(1) == 0 || done == last || stop || timed_out;
        if (preview_due || checkpoint_due) && !all_ranks(&opts.group, trainer.is_finite_on(&batch)?)? {
            flush(&mut log)?;
            bar.abandon();
            return Err(diverged(done, "NaN/Inf weights or outputs", run, last_good));
        }
        if preview_due && leader {
            let grid = trainer.preview_grid(&batch, 4)?;
            crate::io::write_png(&run.join("previews").join(format!("step-{done:07}.png")), &grid, crate::io::BitDepth::Eight)?;
        }
        if checkpoint_due && leader {
            flush(&mut log)?;
            save_all(&trainer, opts)?;
            last_good = Some(done);
            if let Some(summary) = trainer.colour_summary() {
                let s = summary?;
                let mut line = serde_json::json!({ "step": done, "identity_chroma_error": s.identity_chroma_error, "relit_chroma_error": s.relit_chroma_error, "near_black_highlight_ratio": s.near_black_highlight_ratio, "near_black_matte_highlight_ratio": s.near_black_matte_highlight_ratio, "relit_log_l1": s.relit_log_l1, "code_spread": s.code_spread });
                if let Some(photos) = trainer.photo_summary() {
                    let p = photos?.mean;
                    line["photo_chroma_error"] = p.chroma_error.into();
                    line["photo_log_l1"] = p.log_l1.into();
                    line["photo_checkerboard"] = p.checkerboard.into();
                }
                if let Some(h) = trainer.highlight_summary() {
                    let h = h?;
                    // Geometric means over the materials with the region (null: none had it).
                    let finite = |v: f64| if v.is_finite() { serde_json::json!(v) } else { serde_json::Value::Null };
                    line["highlight_ghost"] = finite(h.ghost.geo_mean);
                    line["highlight_lobe"] = finite(h.lobe.geo_mean);
                    line["highlight_rest"] = finite(h.rest.geo_mean);
                }
                let mut f = std::fs::OpenOptions::new().create(true).append(true).open(run.join("colour.jsonl"))?;
                writeln!(f, "{line}")?;
            }
        }
        if stop {
            bar.abandon_with_message(format!("interrupted at step {done}; checkpoint saved, continue with --resume"));
            return Ok(trainer);
        }
        if timed_out {
            bar.abandon_with_message(format!("time limit reached at step {done}; checkpoint saved, continue with --resume"));
            return Ok(trainer);
        }
    }
    bar.finish_with_message(format!("done at step {}", trainer.steps_done()));
    Ok(trainer)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_resumed_total_must_lie_beyond_the_run() {
        let run = std::path::Path::new("runs/r");
        assert!(super::check_new_total(run, 5, 6).is_ok());
        for steps in [5, 3, 0] {
            let e = super::check_new_total(run, 5, steps).unwrap_err().to_string();
            assert!(e.contains("run runs/r is already at step 5") && e.contains(&format!("--steps {steps}")), "{e}");
        }
    }
}
