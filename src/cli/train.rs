//! `flashmat train` and `flashmat export`.

use flashmat::baselines::TrainMethod;
use flashmat::model::ModelConfig;
use flashmat::train::run::{self, RunOptions};
use flashmat::train::{BaselineTrainer, PixelSampling, TrainConfig, UpdateScheme};
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use tch::Device;

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// What to train: flashmat (M_est + neural renderer), or a baseline of the evaluation:
    /// analytic (U-Net -> GGX maps, rendering loss) or relight-unet (U-Net predicting the relit image).
    #[arg(long, value_enum, default_value_t = TrainMethod::Flashmat, conflicts_with = "resume")]
    pub method: TrainMethod,
    /// Model size preset: paper (W=64, the paper's sizes), compact (CPU-trainable), compact-f8 (compact with 8 direction frequencies) or tiny (tests).
    #[arg(long, default_value = "compact", conflicts_with = "model_config")]
    pub preset: String,
    /// A TOML file with model sizes (fields of ModelConfig; missing ones take the paper's values).
    #[arg(long, value_name = "FILE")]
    pub model_config: Option<PathBuf>,
    /// Run folder (checkpoint, log, charts, previews). Required for a new run.
    #[arg(long, value_name = "DIR", required_unless_present = "resume")]
    pub out: Option<PathBuf>,
    /// Continue the run in DIR from its last checkpoint.
    #[arg(long, value_name = "DIR", conflicts_with = "out")]
    pub resume: Option<PathBuf>,
    /// cpu or cuda (cuda:N for a given GPU).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// What the networks compute in: f32, tf32 (TF32 matmuls and convolutions on a GPU; f32 on the CPU)
    /// or bf16 (autocast in every network's forward; losses, gradients and weights stay f32). A speed
    /// switch, not part of the run: a resume takes it anew (docs/GPU.md).
    #[arg(long, default_value = "tf32")]
    pub precision: flashmat::precision::Precision,
    /// Train on LDR input photos (clamped to [0,1]); outputs stay HDR.
    #[arg(long)]
    pub ldr: bool,
    /// Shadows from height fields in the training renders (loaded maps get a height field integrated from their normals).
    #[arg(long)]
    pub shadows: bool,
    /// Multiplies the height fields for --shadows.
    #[arg(long, default_value_t = 1.0, requires = "shadows")]
    pub height_scale: f64,
    /// Training data: `procedural`, `procedural-test:I` (only held-out material I: the shadow over-fitting experiment) or a dataset folder (MatFusion, per-material or INRIA strips)
    #[arg(long, default_value = "procedural")]
    pub data: String,
    /// Fine-tune: start from the weights of this run folder's checkpoint (same model size; fresh optimizers, step 0).
    #[arg(long, value_name = "RUN_DIR", conflicts_with = "resume")]
    pub init_from: Option<PathBuf>,
    /// Continue from an exported model file when the run's checkpoint is lost (a GPU job's disk): its weights and
    /// step count, fresh optimizers and discriminator. A new run (--out) with the same model and recipe.
    #[arg(long, value_name = "MODEL_FILE", conflicts_with_all = ["resume", "init_from"])]
    pub warm_start: Option<PathBuf>,
    /// Curriculum stage 2: a teacher file (`flashmat train-teacher`). A new run starts from its renderer, and M_est
    /// learns the teacher's codes of the true maps (--code-weight) beside the paper's losses.
    #[arg(long, value_name = "FILE", conflicts_with = "resume")]
    pub teacher: Option<PathBuf>,
    /// Weight of the teacher-code term (relative L1 of the neural map against the teacher's codes).
    #[arg(long, default_value_t = 1.0, requires = "teacher")]
    pub code_weight: f64,
    /// Extra weight K of glossy pixels in the code term: a pixel of true roughness r counts
    /// 1 + K * max(0, 1 - r / 0.35) times (0: all alike).
    #[arg(long, default_value_t = 0.0, value_name = "K", requires = "teacher")]
    pub code_gloss_weight: f64,
    /// Weight of the GGX-value term: L1 of the GGX values M_est's head writes (--preset compact-g) against the
    /// true maps, glossy pixels weighted as in the code term (0: none).
    #[arg(long, default_value_t = 0.0, value_name = "W", requires = "teacher")]
    pub ggx_value_weight: f64,
    /// The code term fades linearly to zero at step N (0: constant).
    #[arg(long, default_value_t = 0, value_name = "N", requires = "teacher")]
    pub code_until: u64,
    /// Procedural data from a bank of N materials generated once at the start on all cores, drawn with random
    /// crops and the 8 symmetries of the square (0: a fresh material every draw). Keeps a GPU fed.
    #[arg(long, default_value_t = 0, value_name = "N", conflicts_with = "resume")]
    pub bank: usize,
    /// Stop cleanly (checkpoint, export) after M minutes of this invocation; continue with --resume.
    #[arg(long, value_name = "M")]
    pub minutes: Option<f64>,
    /// Also write DIR/model.safetensors (an f16 export, as `flashmat export`) at every checkpoint and at the end.
    #[arg(long, value_name = "DIR")]
    pub export_dir: Option<PathBuf>,
    /// Also keep each checkpoint's export as DIR/step-N.safetensors (for `flashmat average`).
    #[arg(long, requires = "export_dir")]
    pub keep_exports: bool,
    /// Total training steps (with --resume: the new total).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Stop after this many steps in this invocation (the run can be resumed).
    #[arg(long)]
    pub max_steps_now: Option<u64>,
    /// Training crop size (multiple of 8; paper: 192 then 256).
    #[arg(long, default_value_t = 128)]
    pub crop: usize,
    /// Output renders per material (paper: 8 at 192, 4 at 256).
    #[arg(long, default_value_t = 8)]
    pub outputs: usize,
    /// Materials per batch.
    #[arg(long, default_value_t = 2)]
    pub batch: usize,
    /// Learning rate [default: 1e-4]. With --resume: a new learning rate from the resumed step on (how a diverged run
    /// continues from its last good checkpoint).
    #[arg(long, value_parser = super::positive_number)]
    pub lr: Option<f64>,
    /// Pixels used by the renderer's data term (flashmat only) [default: inverse-norm].
    #[arg(long, value_enum)]
    pub pixel_sampling: Option<PixelSampling>,
    /// Update scheme: the paper's alternating optimizers or one combined update (flashmat only)
    /// [default: alternating].
    #[arg(long, value_enum)]
    pub scheme: Option<UpdateScheme>,
    /// Clip each network's global gradient norm to this value (> 0).
    #[arg(long, value_parser = super::positive_number)]
    pub grad_clip: Option<f64>,
    /// Ramp the learning rate up linearly over the first N steps (paper: 0). Short CPU runs need it:
    /// full-size first steps push M_render's outputs below zero, where its final LeakyReLU(0.001) nearly stops learning.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub warmup_steps: u64,
    /// Straight-through gradient below zero for M_render's final LeakyReLU(0.001) (inference unchanged).
    /// Without it short runs settle on black renders: L1 pulls outputs down 1000x harder than it lifts them.
    #[arg(long)]
    pub straight_through_output: bool,
    /// From step N on, M_est's BatchNorm uses its running statistics, frozen, instead of the batch's (paper: never).
    /// With 2 materials a step, batch statistics subtract the colour the two share.
    #[arg(long, value_name = "N")]
    pub frozen_bn_from: Option<u64>,
    /// Recolour this fraction of training materials (random hue turn, saturation x0.6-1.8 of the
    /// diffuse and specular maps) so colour must be read from the photo (default and paper: 0).
    /// With --resume: from the resumed step on.
    #[arg(long, value_name = "P", value_parser = super::fraction)]
    pub colour_augment: Option<f64>,
    /// Make this fraction of the procedural training materials dark (diffuse albedo times 0.02-0.35,
    /// log-uniform: dark wood, slate, black leather, asphalt, dark paint; default and paper: 0; 0.25 is
    /// the share the next GPU campaign trains with, docs/GPU.md). New runs only.
    #[arg(long, value_name = "P", value_parser = super::fraction, conflicts_with = "resume")]
    pub dark_share: Option<f64>,
    /// Make this fraction of the procedural training materials saturated (diffuse albedo given a fully
    /// saturated hue whose weakest channel is 0.004-0.1 of its strongest: orange foam, red paint, green felt;
    /// default and paper: 0). Held out: `eval --dataset procedural-saturated-test`. New runs only.
    #[arg(long, value_name = "P", value_parser = super::fraction, conflicts_with = "resume")]
    pub saturated_share: Option<f64>,
    /// Of each material's output renders, make N co-located: the input's own light and view, then
    /// light and camera together at random points above the material (default and paper: 0, "reflect" only). Trains
    /// the renderer where light and view meet near the normal. With --resume: from the resumed step on.
    #[arg(long, value_name = "N")]
    pub colocated_outputs: Option<usize>,
    /// Of each material's output renders, draw N (before the co-located ones) as the Hemisphere case does: light and
    /// camera independently anywhere on the radius-4 hemisphere, mostly away from the highlight (default and paper: 0).
    #[arg(long, value_name = "N", conflicts_with = "resume")]
    pub hemisphere_outputs: Option<usize>,
    /// Of each material's output renders, make N (before the hemisphere ones) keep the photo's camera with the
    /// light moved so the mirror highlight lands on the material: the moved-highlight test's case (issue 48;
    /// default and paper: 0).
    #[arg(long, value_name = "N", conflicts_with = "resume")]
    pub moved_highlight_outputs: Option<usize>,
    /// Take this fraction of the input photos as a phone takes them: camera off-centre and nearer or
    /// farther, flash 1-2 cm beside the lens, sensor noise, 8-bit sRGB (issue 48; needs --ldr;
    /// default and paper: 0, the exact co-located render). New runs only.
    #[arg(long, value_name = "P", value_parser = super::fraction, conflicts_with = "resume")]
    pub phone_inputs: Option<f64>,
    /// Save those phone photos as JPEGs, at a quality drawn from 85-95 per photo (needs --phone-inputs). New runs
    /// only.
    #[arg(long, requires = "phone_inputs", conflicts_with = "resume")]
    pub phone_jpeg: bool,
    /// Keep M_est's upsampling kernels checkerboard-free (projected after every update: a flat photo
    /// gives a flat neural map; paper: free). With --resume: from the resumed step on.
    #[arg(long)]
    pub checkerboard_free: bool,
    /// Train ND_enc + M_render (and the discriminator) only: M_est keeps the warm start's weights and
    /// runs as at inference (BatchNorm on running statistics). About half the step's time; needs
    /// --warm-start or --init-from (paper: both networks train). A resumed run keeps its own choice.
    #[arg(long, conflicts_with = "resume")]
    pub freeze_estimator: bool,
    /// Train M_est only: ND_enc + M_render keep the warm start's weights (for fixing the colour of M_est's codes
    /// against a renderer that already renders them). Needs --warm-start or --init-from and --adv-weight 0.
    #[arg(long, conflicts_with_all = ["resume", "freeze_estimator"])]
    pub freeze_renderer: bool,
    /// With --freeze-estimator and --colocated-outputs: the outputs that are not co-located take this model's renders
    /// (the same model, usually the warm start) as their targets instead of the GGX truth, so the renderer learns the
    /// co-located light while holding what it renders elsewhere.
    #[arg(long, value_name = "MODEL_FILE", conflicts_with = "resume", requires = "freeze_estimator")]
    pub anchor: Option<PathBuf>,
    /// Start the adversarial term at step N (paper: 0).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub adv_start: u64,
    /// Weight of the LPIPS term (paper 0.01).
    #[arg(long, default_value_t = 0.01)]
    pub lpips_weight: f64,
    /// Weight of the adversarial term (paper 0.03).
    #[arg(long, default_value_t = 0.03)]
    pub adv_weight: f64,
    /// Weight of a colour-balance term: each render's mean chromaticity rgb / (r + g + b) against the truth's, L1
    /// (paper: none). Weighs a dark channel's error like a bright one's, which the log L1 does not.
    #[arg(long, default_value_t = 0.0, value_name = "W")]
    pub chroma_weight: f64,
    /// Weight of a shift-consistency term (paper: none): each material is photographed again with camera and flash
    /// moved by up to --shift-pixels, and M_est's codes of the two photos must agree where they overlap (a code
    /// describes the material, not where the flash was). Costs a second M_est pass; needs --scheme alternating.
    #[arg(long, default_value_t = 0.0, value_name = "W")]
    pub shift_weight: f64,
    /// Weight of a lobe term (issue 48; paper: none): L1 of ln(1 + R) at --lobe-pixels random pixels under lights
    /// inside each pixel's true GGX lobe, rendered from M_est's codes there, in both halves' losses. Trains the renderer
    /// to draw a glossy highlight wherever the light puts it (the output renders show a lobe on a few pixels at best).
    #[arg(long, default_value_t = 0.0, value_name = "W")]
    pub lobe_weight: f64,
    /// Pixels per step of the lobe term (over the whole batch).
    #[arg(long, default_value_t = flashmat::train::config::DEFAULT_LOBE_PIXELS, value_name = "N", value_parser = super::count)]
    pub lobe_pixels: usize,
    /// Share of the lobe term's pairs whose light is inside the lobe; the others take a random light at the same
    /// pixel and view, meant to hold the renderer down around the lobe (1: lobe lights only; at 0.5 the rest's
    /// overshoot stayed, reports/highlights-experiments.md).
    #[arg(long, default_value_t = 1.0, value_name = "P")]
    pub lobe_share: f64,
    /// Share of the lobe term's views taken from the flash camera's cone (within 14 degrees of the normal, where
    /// the photo's camera and the moved-highlight test look from) instead of the whole hemisphere.
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    pub lobe_camera_share: f64,
    /// Share of the lobe term's lobe lights drawn around the mirror direction at the spread of a random roughness
    /// where that is narrower than the pixel's, so rough pixels are taught how dim they are right at the mirror.
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    pub lobe_narrow_share: f64,
    /// Largest shift of the second photo, in pixels per axis (with --shift-weight).
    #[arg(long, default_value_t = 16, value_name = "PIXELS")]
    pub shift_pixels: usize,
    /// Divide the shift term by the codes' mean magnitude with its gradient, so that shrinking every code does not
    /// lower it (by default the magnitude is a constant; runs shrank the codes). Needs --shift-weight.
    #[arg(long)]
    pub shift_scale_free: bool,
    #[arg(long, default_value_t = 250)]
    pub checkpoint_every: u64,
    #[arg(long, default_value_t = 250)]
    pub preview_every: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of CPU threads for libtorch (default: all cores).
    #[arg(long, value_parser = clap::value_parser!(i32).range(1..=flashmat::limits::MAX_THREADS))]
    pub threads: Option<i32>,
}

#[derive(Args, Debug)]
pub struct TeacherArgs {
    /// Model size preset (the teacher's codes have its neural-map width).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Folder: teacher.safetensors (weights, optimizer, step) and log.jsonl. A folder that holds one continues it.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Total steps (a continued teacher goes on to this count).
    #[arg(long, default_value_t = 5000)]
    pub steps: u64,
    /// Stop cleanly after M minutes.
    #[arg(long, value_name = "M")]
    pub minutes: Option<f64>,
    /// Random pixels (material, light, view) per step.
    #[arg(long, default_value_t = 16_384)]
    pub pixels: usize,
    #[arg(long, default_value_t = 1e-3, value_parser = super::positive_number)]
    pub lr: f64,
    #[arg(long, default_value_t = 250)]
    pub checkpoint_every: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Share of the samples whose light is put inside the pixel's GGX lobe (the view mirrored about a half vector
    /// near the normal; default 0, the committed teacher's recipe: glossy lobes are then almost never sampled).
    #[arg(long, default_value_t = 0.0, value_parser = super::fraction)]
    pub lobe_share: f64,
    /// Adds the L1 of ln(F + R) to the loss, so dark pixels (a metal's diffuse) are fitted relative to their
    /// radiance; default 0, the committed teacher's recipe: ln(1 + R) alone.
    #[arg(long, value_name = "F", default_value_t = 0.0, value_parser = super::fraction)]
    pub dark_floor: f64,
    /// Lowest roughness of the sampled pixels, from 0.02 (the procedural materials' lowest); default 0.05, the
    /// committed teacher's recipe, whose renderer then never sees the sharpest lobes.
    #[arg(long, value_name = "R", default_value_t = flashmat::train::teacher::COMMITTED_MIN_ROUGHNESS, value_parser = super::fraction)]
    pub min_roughness: f64,
    /// Which GGX pixels to learn: `procedural` (the committed 2026-11-23 teacher's) or `any-ggx` (every material the
    /// capture fit can return: metals, saturated colours, steep normals; use with --min-roughness 0.02).
    #[arg(long, value_enum, default_value_t = flashmat::train::teacher::PixelMaterials::Procedural)]
    pub materials: flashmat::train::teacher::PixelMaterials,
    /// Start a new teacher from this teacher file's weights (same preset, or one with more direction frequencies or without the half angle: ND_enc keeps the lower frequencies and adds the half angle's column), with a fresh optimizer.
    #[arg(long, value_name = "TEACHER")]
    pub warm_start: Option<PathBuf>,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Number of CPU threads for libtorch (default: all cores).
    #[arg(long, value_parser = clap::value_parser!(i32).range(1..=flashmat::limits::MAX_THREADS))]
    pub threads: Option<i32>,
}

pub fn train_teacher(a: &TeacherArgs) -> Result<()> {
    let device = training_setup(a.threads, &a.device, a.minutes)?;
    let config = flashmat::train::teacher::TeacherConfig {
        model: ModelConfig::preset(&a.preset)?,
        pixels: a.pixels,
        lr: a.lr,
        steps: a.steps,
        checkpoint_every: a.checkpoint_every,
        seed: a.seed,
        lobe_share: a.lobe_share,
        dark_floor: a.dark_floor,
        min_roughness: a.min_roughness,
        materials: a.materials,
        warm_start: a.warm_start.as_ref().map(|p| p.display().to_string()),
    };
    if let Some(from) = &a.warm_start {
        anyhow::ensure!(from.is_file(), "--warm-start {}: no such file", from.display());
    }
    let t = flashmat::train::teacher::run(config, &a.out, device, a.minutes, true)?;
    eprintln!(
        "teacher {} at step {} of {}: held-out L1 of ln(1 + R) {:.4}",
        flashmat::train::teacher::teacher_file(&a.out).display(),
        t.step,
        t.config.steps,
        t.held_out_l1()?
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// Run folder to export from (a `train` run, or a `train-teacher` folder: the teacher's weights without its
    /// optimizer).
    #[arg(long, value_name = "DIR")]
    pub run: PathBuf,
    /// Output model file (.safetensors): inference weights and configuration.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Store every weight as f32 (default: weight tensors of 1024+ values as f16, half the size;
    /// renders differ by about 1e-3 relative).
    #[arg(long)]
    pub f32: bool,
}

#[derive(Args, Debug)]
pub struct AverageArgs {
    /// Exported model files of one run (`flashmat export` snapshots), e.g. its last few checkpoints.
    #[arg(required = true, num_args = 1..)]
    pub models: Vec<PathBuf>,
    /// Output model file (.safetensors).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Store every weight as f32 (default: large weight tensors as f16, as `flashmat export`).
    #[arg(long)]
    pub f32: bool,
    /// Then project M_est's upsampling kernels onto checkerboard-free ones (a flat photo gives a flat
    /// neural map; the nearest such kernels). With one file: only the projection.
    #[arg(long)]
    pub checkerboard_free: bool,
}

/// The options every training command shares: threads, device, time limit.
fn training_setup(threads: Option<i32>, device: &str, minutes: Option<f64>) -> Result<Device> {
    if let Some(t) = threads {
        tch::set_num_threads(t);
    }
    if let Some(m) = minutes {
        anyhow::ensure!(m.is_finite() && m >= 0.0, "--minutes must be a number of minutes >= 0 (got {m})");
    }
    flashmat::device::parse_device(device)
}

/// A process started by torchrun joins its process group (Gloo on the
/// CPU, NCCL on this node's GPU `LOCAL_RANK`); a plain one trains alone.
/// Also returns torchrun's restart count (0 for a plain process).
fn join_process_group(device: Device) -> Result<(Device, Option<std::sync::Arc<flashmat::dist::Group>>, u64)> {
    use flashmat::dist::{Config, Group, Launch};
    let Some(launch) = Launch::from_env()? else { return Ok((device, None, 0)) };
    let device = launch.device_for(device)?;
    let group = Group::join(&launch, device, Config::from_env()?)?;
    Ok((device, Some(std::sync::Arc::new(group)), launch.restart))
}

pub fn train(a: &TrainArgs) -> Result<()> {
    let device = training_setup(a.threads, &a.device, a.minutes)?;
    flashmat::precision::set(a.precision)?;
    let (device, group, restart) = join_process_group(device)?;
    let options = |dir: &PathBuf| RunOptions {
        group: group.clone(),
        max_steps_this_run: a.max_steps_now,
        max_minutes: a.minutes,
        export_dir: a.export_dir.clone(),
        keep_exports: a.keep_exports,
        new_lr: a.resume.as_ref().and(a.lr),
        checkerboard_free: a.resume.is_some() && a.checkerboard_free,
        new_colour_augment: a.resume.as_ref().and(a.colour_augment),
        new_colocated_outputs: a.resume.as_ref().and(a.colocated_outputs),
        ..RunOptions::new(dir.clone(), device, true)
    };
    // torchrun restarted the job (--max-restarts) after a rank died: the
    // same command line continues the run from its last checkpoint.
    let restarted = a.out.as_ref().filter(|dir| restart > 0 && run::checkpoint_path(dir).exists());
    if let Some(dir) = a.resume.as_ref().or(restarted) {
        let opts = options(dir);
        if restarted.is_some() && opts.leader() {
            eprintln!("torchrun restart {restart}: {} continues from its last checkpoint", dir.display());
        }
        let t = run::resume_any(&opts, a.steps)?;
        if opts.leader() {
            eprintln!("run {} at step {} of {}", dir.display(), t.steps_done(), t.config().steps);
        }
        return Ok(());
    }
    if !a.method.is_flashmat() {
        for (given, flag) in [(a.pixel_sampling.is_some(), "--pixel-sampling"), (a.scheme.is_some(), "--scheme")] {
            if given {
                bail!("{flag} only applies to --method flashmat (the {} baseline has one network and one update per step)", a.method);
            }
        }
    }
    let model = match &a.model_config {
        Some(p) => ModelConfig::from_toml_file(p)?,
        None => ModelConfig::preset(&a.preset)?,
    };
    let config = TrainConfig {
        method: a.method,
        model,
        data: a.data.clone(),
        crop: a.crop,
        material_size: a.crop.max(256),
        materials_per_batch: a.batch,
        outputs_per_material: a.outputs,
        ldr_input: a.ldr,
        shadows: a.shadows,
        height_scale: a.height_scale,
        init_from: a.init_from.as_ref().map(|p| p.display().to_string()),
        warm_start: a.warm_start.as_ref().map(|p| p.display().to_string()),
        teacher: a.teacher.as_ref().map(|p| p.display().to_string()),
        weight_code: if a.teacher.is_some() { a.code_weight } else { 0.0 },
        code_gloss_weight: a.code_gloss_weight,
        weight_ggx_values: a.ggx_value_weight,
        code_until: a.code_until,
        bank: a.bank,
        lr: a.lr.unwrap_or(TrainConfig::default().lr),
        pixel_sampling: a.pixel_sampling.unwrap_or(PixelSampling::InverseNorm),
        scheme: a.scheme.unwrap_or(UpdateScheme::Alternating),
        grad_clip: a.grad_clip,
        warmup_steps: a.warmup_steps,
        adv_start: a.adv_start,
        frozen_bn_from: a.frozen_bn_from,
        colour_augment: a.colour_augment.unwrap_or(0.0),
        dark_share: a.dark_share.unwrap_or(0.0),
        saturated_share: a.saturated_share.unwrap_or(0.0),
        colocated_outputs: a.colocated_outputs.unwrap_or(0),
        hemisphere_outputs: a.hemisphere_outputs.unwrap_or(0),
        moved_highlight_outputs: a.moved_highlight_outputs.unwrap_or(0),
        phone_inputs: a.phone_inputs.unwrap_or(0.0),
        phone_jpeg: a.phone_jpeg,
        checkerboard_free: a.checkerboard_free,
        freeze_estimator: a.freeze_estimator,
        freeze_renderer: a.freeze_renderer,
        anchor: a.anchor.as_ref().map(|p| p.display().to_string()),
        straight_through_output: a.straight_through_output,
        weight_lpips: a.lpips_weight,
        weight_adv: a.adv_weight,
        weight_chroma: a.chroma_weight,
        weight_shift: a.shift_weight,
        weight_lobe: a.lobe_weight,
        lobe_pixels: a.lobe_pixels,
        lobe_share: a.lobe_share,
        lobe_camera_share: a.lobe_camera_share,
        lobe_narrow_share: a.lobe_narrow_share,
        shift_pixels: a.shift_pixels,
        shift_scale_free: a.shift_scale_free,
        steps: a.steps.unwrap_or(TrainConfig::default().steps),
        checkpoint_every: a.checkpoint_every,
        preview_every: a.preview_every,
        seed: a.seed,
        ..Default::default()
    };
    let dir = a.out.clone().context("--out DIR is required for a new run")?;
    let opts = options(&dir);
    let t = run::start_any(config, &opts)?;
    if opts.leader() {
        eprintln!("run {} at step {} of {}", dir.display(), t.steps_done(), t.config().steps);
    }
    Ok(())
}

pub fn export(a: &ExportArgs) -> Result<()> {
    use flashmat::train::run::RunTrainer;
    let teacher = flashmat::train::teacher::teacher_file(&a.run);
    if teacher.is_file() {
        // A teacher run: its weights without the optimizer (what models/ holds).
        let t = flashmat::train::teacher::TeacherTrainer::resume(&teacher, Device::Cpu)?;
        let out_dir = super::prepare_output(&a.output)?;
        t.save_weights(&a.output)?;
        out_dir.keep();
        eprintln!("wrote {} (teacher of {}, step {}, weights only)", a.output.display(), t.model.model_id(), t.step);
        return Ok(());
    }
    let ckpt = run::checkpoint_path(&a.run);
    // Exporting a run that is still training is how its snapshots are kept
    // (docs/TRAINING.md): checkpoints are replaced by rename, so the file
    // read is always a whole one. Say so, as the next one will differ.
    let training = flashmat::io::folder_owner(&a.run).map(|owner| format!("; the run is still training ({owner})")).unwrap_or_default();
    if ckpt.exists() && !flashmat::train::Trainer::checkpoint_config(&ckpt)?.method.is_flashmat() {
        let trainer = BaselineTrainer::resume(&ckpt, Device::Cpu)?;
        let out_dir = super::prepare_output(&a.output)?;
        trainer.export_model(&a.output, !a.f32)?;
        out_dir.keep();
        eprintln!("wrote {} ({} baseline {}, step {}{training})", a.output.display(), trainer.config.method, trainer.net.model_id(), trainer.step);
        return Ok(());
    }
    let trainer = flashmat::train::Trainer::resume(&ckpt, Device::Cpu, None)?;
    let out_dir = super::prepare_output(&a.output)?;
    trainer.export_model(&a.output, !a.f32)?;
    out_dir.keep();
    eprintln!("wrote {} (model {}, step {}{training})", a.output.display(), trainer.model.model_id(), trainer.step);
    Ok(())
}

pub fn average(a: &AverageArgs) -> Result<()> {
    let (model, info) = flashmat::model::Model::average(&a.models, Device::Cpu)?;
    if a.checkerboard_free {
        model.est.project_checkerboard_free();
    }
    let out_dir = super::prepare_output(&a.output)?;
    model.save(&a.output, &info, !a.f32)?;
    out_dir.keep();
    eprintln!("wrote {} (mean of {} files of model {}, step {})", a.output.display(), a.models.len(), model.model_id(), info.steps);
    Ok(())
}
