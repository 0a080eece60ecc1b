//! The per-pixel teacher: the first stage of a training curriculum (after
//! the encoder of Zeltner et al. 2023, *Real-Time Neural Appearance
//! Models*). A small MLP maps a pixel's GGX parameters (kd, ks, roughness,
//! normal: the 10 values of REFERENCE section 2) to a neural-map code, and
//! is trained together with ND_enc + M_render on random per-pixel
//! materials and directions against ln(1 + R) of the GGX renderer. With
//! dense per-pixel supervision and no U-Net the renderer learns GGX,
//! colours included, in minutes on a CPU (../shared/EXPERIMENTS.md).
//!
//! The second stage trains M_est with the teacher's codes of the true maps
//! as a dense 64-channel target (`TrainConfig::teacher`, `weight_code`)
//! beside the paper's losses, starting from the teacher's renderer. The
//! shipped architecture stays the paper's: the encoder is training-only,
//! except behind M_est in the experimental `compact-g` preset.

use crate::optim::Adam;
use crate::archive::{restore_vars, Archive};
use crate::model::nd_enc::lower_frequencies;
use crate::model::{Model, ModelConfig};
use crate::model::ggx_codes::MIN_NORMAL_Z as MIN_FIT_NORMAL_Z;
pub use crate::svbrdf::rows::{ggx_log_rows, lobe_lights, log_rows_loss as teacher_loss, normalize_rows, random_directions};
use anyhow::{ensure, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{nn, Device, Kind, Tensor};

/// The file format's home is the model layer, which reads teacher files for
/// `fit::photos` too.
pub use crate::model::ggx_codes::{TEACHER_FORMAT as FORMAT, TEACHER_VERSION as VERSION};

/// The encoder lives in the model layer: a `compact-g` model carries a
/// frozen copy behind M_est ([`crate::model::ggx_codes`]).
pub use crate::model::ggx_codes::{GgxEncoder as TeacherEncoder, GGX_CHANNELS};

/// Teacher-stage hyper-parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TeacherConfig {
    pub model: ModelConfig,
    /// Random pixels (material, light, view) per step.
    pub pixels: usize,
    pub lr: f64,
    pub steps: u64,
    pub checkpoint_every: u64,
    pub seed: u64,
    /// Share of the samples whose light is turned into the pixel's GGX lobe
    /// ([`pixel_samples`]); 0 (the committed teacher's recipe): cosine-random
    /// lights, which almost never meet a glossy pixel's mirror direction.
    #[serde(default)]
    pub lobe_share: f64,
    /// With F > 0, the loss adds the L1 of ln(F + R): the errors of dark
    /// pixels counted relative to their radiance, not absolutely as ln(1 + R)
    /// does for R << 1 (a dark metal's diffuse, R ~ 0.02, drawn twice too
    /// bright costs ln(1 + R) 0.02). 0 (the committed recipe): ln(1 + R) alone.
    /// The log's per-step `l1` is then the whole loss; `held_out_l1` stays
    /// the L1 of ln(1 + R), so teachers compare.
    #[serde(default)]
    pub dark_floor: f64,
    /// Lowest roughness [`pixel_samples`] draws; the committed recipe's 0.05
    /// (older teacher files carry none) lies above the procedural materials'
    /// [`MIN_ROUGHNESS`], so their sharpest lobes are never sampled.
    #[serde(default = "committed_min_roughness")]
    pub min_roughness: f64,
    /// Which GGX pixels [`pixel_samples`] draws. Older teacher files carry
    /// none: [`PixelMaterials::Procedural`], the committed recipe.
    #[serde(default)]
    pub materials: PixelMaterials,
    /// The teacher file this run started from (weights only; a fresh
    /// optimizer), for the record: a recipe names its start.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warm_start: Option<String>,
}

/// The GGX pixels a teacher learns.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum PixelMaterials {
    /// The procedural generator's corner (the committed 2026-11-23 teacher):
    /// kd U^2.2 per channel, ks a dielectric 0.04 for 70% of pixels, normals
    /// within about 15 degrees of the axis.
    #[default]
    Procedural,
    /// Every material the capture fit can return ([`any_ggx_values`]):
    /// metals with coloured specular, saturated colours, black to white in
    /// kd and ks independently, and normals out to the fit's limit.
    AnyGgx,
}

/// The committed teacher's lowest sampled roughness.
pub const COMMITTED_MIN_ROUGHNESS: f64 = 0.05;

fn committed_min_roughness() -> f64 {
    COMMITTED_MIN_ROUGHNESS
}

impl Default for TeacherConfig {
    fn default() -> Self {
        Self {
            model: ModelConfig::compact(),
            pixels: 16_384,
            lr: 1e-3,
            steps: 5_000,
            checkpoint_every: 250,
            seed: 1,
            lobe_share: 0.0,
            dark_floor: 0.0,
            min_roughness: COMMITTED_MIN_ROUGHNESS,
            materials: PixelMaterials::Procedural,
            warm_start: None,
        }
    }
}

impl TeacherConfig {
    /// The recipe settings of `given` that differ from this (stored) one, as
    /// "name stored (given)": a continued teacher keeps its stored recipe and
    /// takes only the step count, which a caller must be told.
    pub fn ignored_on_continue(&self, given: &TeacherConfig) -> Vec<String> {
        let mut out = vec![];
        let mut check = |name: &str, stored: String, new: String| {
            if stored != new {
                out.push(format!("{name} {stored} (given {new})"));
            }
        };
        check("--pixels", self.pixels.to_string(), given.pixels.to_string());
        check("--lr", self.lr.to_string(), given.lr.to_string());
        check("--seed", self.seed.to_string(), given.seed.to_string());
        check("--lobe-share", self.lobe_share.to_string(), given.lobe_share.to_string());
        check("--dark-floor", self.dark_floor.to_string(), given.dark_floor.to_string());
        check("--min-roughness", self.min_roughness.to_string(), given.min_roughness.to_string());
        check("--checkpoint-every", self.checkpoint_every.to_string(), given.checkpoint_every.to_string());
        check("--materials", format!("{:?}", self.materials), format!("{:?}", given.materials));
        out
    }
}

/// A trained teacher loaded for the second stage (frozen).
pub struct Teacher {
    pub vs: nn::VarStore,
    pub encoder: TeacherEncoder,
}

impl Teacher {
    /// Loads the encoder of a teacher file, for a model of `model_id`, and
    /// copies the teacher's renderer into `renderer_vs` when given.
    pub fn load(path: &Path, model: &ModelConfig, device: Device, renderer_vs: Option<&nn::VarStore>) -> Result<Self> {
        let a = Archive::load(path, FORMAT, VERSION)?;
        let theirs = a.meta("model_id")?;
        // A compact-g model's renderer and neural map are the compact preset's.
        let renderer_id = model.without_ggx_codes().model_id();
        ensure!(theirs == renderer_id, "{}: a teacher of model '{theirs}' cannot train a '{}' model", path.display(), model.model_id());
        let weights = crate::model::ggx_codes::TeacherWeights::load_for(path, &a, model.without_ggx_codes(), device)?;
        if let Some(r) = renderer_vs {
            restore_vars(&r.variables(), &weights.renderer, &format!("{}: renderer", path.display()))?;
        }
        Ok(Self { vs: weights.vs, encoder: weights.encoder })
    }
}

/// Random per-pixel samples: GGX values `[R, 10]`, light and view
/// directions `[R, 3]` each, and the target ln(1 + R) `[R, 3]`.
/// Diffuse ~ U(0,1)^2.2 per channel; specular 0.04 for 70% of pixels, else
/// U(0,1)^2.2 per channel; roughness U(`min_roughness`, 1); normals tilted by N(0,
/// 0.25); light and view cosine-distributed over the hemisphere, with a
/// quarter of the views near the light (the flash configuration). A share
/// `lobe_share` of the lights is then the view mirrored about a half vector
/// drawn around the pixel's normal with a spread of 1.5 alpha per tangent
/// axis (alpha = roughness^2): inside the GGX lobe, where a glossy pixel's
/// radiance is (kept where the mirrored light stays above the surface).
/// With [`PixelMaterials::AnyGgx`] the GGX values are [`any_ggx_values`]'
/// instead (`min_roughness` then its roughness floor).
pub fn pixel_samples(n: i64, lobe_share: f64, min_roughness: f64, materials: PixelMaterials, device: Device) -> (Tensor, Tensor, Tensor, Tensor) {
    let opts = (Kind::Float, device);
    let values = match materials {
        PixelMaterials::Procedural => {
            let kd = Tensor::rand([n, 3], opts).pow_tensor_scalar(2.2);
            let coloured = Tensor::rand([n, 1], opts).lt(0.3).to_kind(Kind::Float);
            let ks = &coloured * Tensor::rand([n, 3], opts).pow_tensor_scalar(2.2) + (1.0 - &coloured) * 0.04;
            let rough = Tensor::rand([n, 1], opts) * (1.0 - min_roughness) + min_roughness;
            let tilt = Tensor::randn([n, 2], opts) * 0.25;
            let normal = normalize_rows(&Tensor::cat(&[tilt, Tensor::ones([n, 1], opts)], 1));
            Tensor::cat(&[kd, ks, rough, normal], 1)
        }
        PixelMaterials::AnyGgx => any_ggx_values(n, min_roughness, device),
    };
    let (wi, wo) = random_directions(n, device);
    let maps = values;
    let wi = if lobe_share > 0.0 {
        let (mirrored, above) = lobe_lights(&maps, &wo, &Tensor::randn([n, 2], opts));
        let lobe = Tensor::rand([n, 1], opts).lt(lobe_share).logical_and(&above).to_kind(Kind::Float);
        normalize_rows(&(&lobe * mirrored + (1.0 - &lobe) * &wi))
    } else {
        wi
    };
    let target = ggx_log_rows(&maps, &wi, &wo);
    (maps, wi, wo, target)
}

/// Share of [`any_ggx_values`]' pixels that are metals: kd below 0.03,
/// a bright coloured ks.
const METAL_SHARE: f64 = 0.25;
/// Share of its dielectrics whose ks is a grey level of 0.02-0.08.
const GREY_SPECULAR_SHARE: f64 = 0.4;
/// Share of its normals drawn uniformly over the fit's whole cone.
const STEEP_NORMAL_SHARE: f64 = 0.15;

/// A random colour `[R, 3]` in [0, 1]: a hue of saturation up to 1 (the
/// brightest channel 1, the others U^3 scaled, mixed toward white by a
/// random amount) times a brightness `value` `[R, 1]`.
fn random_colours(n: i64, value: &Tensor, device: Device) -> Tensor {
    let opts = (Kind::Float, device);
    let hue = Tensor::rand([n, 3], opts).pow_tensor_scalar(3.0);
    let hue = &hue / hue.amax([1i64].as_slice(), true).clamp_min(1e-6);
    let saturation = Tensor::rand([n, 1], opts);
    (&saturation * hue + (1.0 - saturation)) * value
}

/// GGX values `[R, 10]` of every kind the capture fit can return
/// (issue 83): a quarter metals (kd below 0.03, ks a saturated or pale
/// colour of brightness 0.25-1: gold, copper, anodised colours); the
/// dielectrics' kd half independent channels U^2.2 (black to white), half
/// a random hue of random saturation and brightness U^1.5; their ks a grey
/// 0.02-0.08 for 40%, else a random colour of brightness U^1.5 (ks from
/// black to white, independent of kd). Roughness half uniform and half
/// log-uniform on [`min_roughness`, 1] (sharp lobes are drawn as often as
/// broad ones). Normals: tilted by N(0, 0.25) slopes, or for 15% uniform
/// over the cone the fit allows (z from 0.1, `model::ggx_codes::valid_values`).
pub fn any_ggx_values(n: i64, min_roughness: f64, device: Device) -> Tensor {
    let opts = (Kind::Float, device);
    let share = |p: f64| Tensor::rand([n, 1], opts).lt(p).to_kind(Kind::Float);
    let metal = share(METAL_SHARE);
    let channels = share(0.5);
    let dielectric_kd = &channels * Tensor::rand([n, 3], opts).pow_tensor_scalar(2.2)
        + (1.0 - &channels) * random_colours(n, &Tensor::rand([n, 1], opts).pow_tensor_scalar(1.5), device);
    let metal_kd = Tensor::rand([n, 3], opts) * 0.03;
    let kd = &metal * metal_kd + (1.0 - &metal) * dielectric_kd;
    let grey = share(GREY_SPECULAR_SHARE);
    let grey_ks = (Tensor::rand([n, 1], opts) * 0.06 + 0.02).expand([n, 3], false);
    let dielectric_ks = &grey * grey_ks + (1.0 - &grey) * random_colours(n, &Tensor::rand([n, 1], opts).pow_tensor_scalar(1.5), device);
    let metal_ks = random_colours(n, &(Tensor::rand([n, 1], opts) * 0.75 + 0.25), device);
    let ks = &metal * metal_ks + (1.0 - &metal) * dielectric_ks;
    let uniform = Tensor::rand([n, 1], opts) * (1.0 - min_roughness) + min_roughness;
    let log_uniform = (Tensor::rand([n, 1], opts) * -min_roughness.ln()).exp() * min_roughness;
    let half = share(0.5);
    let rough = &half * uniform + (1.0 - &half) * log_uniform;
    let tilted = normalize_rows(&Tensor::cat(&[Tensor::randn([n, 2], opts) * 0.25, Tensor::ones([n, 1], opts)], 1));
    let z = Tensor::rand([n, 1], opts) * (1.0 - MIN_FIT_NORMAL_Z) + MIN_FIT_NORMAL_Z;
    let phi = Tensor::rand([n, 1], opts) * (2.0 * std::f64::consts::PI);
    let sin = (1.0f64 - z.square()).clamp_min(0.0).sqrt();
    let steep_normal = Tensor::cat(&[&sin * phi.cos(), &sin * phi.sin(), z], 1);
    let steep = share(STEEP_NORMAL_SHARE);
    let normal = &steep * steep_normal + (1.0 - &steep) * tilted;
    Tensor::cat(&[kd, ks, rough, normal], 1)
}

/// The teacher's training state.
pub struct TeacherTrainer {
    pub config: TeacherConfig,
    pub model: Model,
    pub teacher_vs: nn::VarStore,
    pub encoder: TeacherEncoder,
    pub opt: Adam,
    pub step: u64,
}

/// One logged step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TeacherStep {
    pub step: u64,
    pub l1: f64,
    /// L1 on the fixed held-out samples (checkpoint steps only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_l1: Option<f64>,
    /// The same on held-out samples of [`PixelMaterials::AnyGgx`] with lobe
    /// lights (checkpoint steps of such teachers only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_any_l1: Option<f64>,
    pub seconds: f64,
}

/// Held-out samples: fixed, never trained on (a seed of their own).
const HELD_OUT_SEED: i64 = 0x7e57;
const HELD_OUT_PIXELS: i64 = 50_000;

impl TeacherTrainer {
    pub fn new(config: TeacherConfig, device: Device) -> Result<Self> {
        ensure!(config.pixels >= 16, "--pixels must be at least 16");
        crate::limits::STEP_PIXELS.check("--pixels", config.pixels as u64)?;
        ensure!(config.lr > 0.0 && config.lr.is_finite(), "learning rate must be positive");
        ensure!(config.dark_floor >= 0.0 && config.dark_floor.is_finite(), "--dark-floor must be a number >= 0, got {}", config.dark_floor);
        let lowest = crate::data::procedural::MIN_ROUGHNESS; // f32: printed as 0.02, compared as stored
        ensure!(
            (lowest as f64..1.0).contains(&config.min_roughness),
            "--min-roughness must be from {lowest} (the procedural materials' lowest) to below 1, got {}",
            config.min_roughness
        );
        tch::manual_seed(config.seed as i64);
        let model = Model::new(&config.model, device)?;
        model.renderer.m_render.straight_through_output.store(true, std::sync::atomic::Ordering::Relaxed);
        let teacher_vs = nn::VarStore::new(device);
        let encoder = TeacherEncoder::new(&(teacher_vs.root() / "teacher"), config.model.neural_channels as i64);
        let mut params = super::trainable(&model.renderer_vs);
        params.extend(super::trainable(&teacher_vs));
        Ok(Self { config, model, teacher_vs, encoder, opt: Adam::new(params), step: 0 })
    }

    /// One Adam step on fresh random samples (drawn from (seed, step)).
    pub fn train_step(&mut self) -> Result<f64> {
        let device = self.model.device();
        tch::manual_seed((self.config.seed ^ self.step.wrapping_mul(0x9E37_79B9_7F4A_7C15)) as i64);
        let c = &self.config;
        let (maps, wi, wo, target) = tch::no_grad(|| pixel_samples(c.pixels as i64, c.lobe_share, c.min_roughness, c.materials, device));
        self.opt.zero_grad();
        let pred = self.model.renderer.forward_rows(&self.encoder.forward_rows(&maps), &wi, &wo)?;
        let loss = teacher_loss(&pred, &target, self.config.dark_floor);
        let l1 = loss.double_value(&[]);
        ensure!(l1.is_finite(), "teacher step {}: the loss is {l1}", self.step + 1);
        loss.backward();
        self.opt.step(self.config.lr, None);
        self.opt.zero_grad();
        self.step += 1;
        Ok(l1)
    }

    /// L1 of ln(1 + R) on the fixed held-out samples of the committed
    /// recipe's distribution, whatever the run trains on: comparable across runs.
    pub fn held_out_l1(&self) -> Result<f64> {
        self.held_out_l1_of(0.0, COMMITTED_MIN_ROUGHNESS, PixelMaterials::Procedural)
    }

    /// L1 of ln(1 + R) on fixed held-out samples of every GGX material
    /// ([`any_ggx_values`] from the fit's roughness floor, half the lights in the lobe).
    pub fn held_out_any_l1(&self) -> Result<f64> {
        self.held_out_l1_of(0.5, crate::data::procedural::MIN_ROUGHNESS as f64, PixelMaterials::AnyGgx)
    }

    fn held_out_l1_of(&self, lobe_share: f64, min_roughness: f64, materials: PixelMaterials) -> Result<f64> {
        let device = self.model.device();
        tch::no_grad(|| {
            tch::manual_seed(HELD_OUT_SEED);
            let (maps, wi, wo, target) = pixel_samples(HELD_OUT_PIXELS, lobe_share, min_roughness, materials, device);
            let pred = self.model.renderer.forward_rows(&self.encoder.forward_rows(&maps), &wi, &wo)?;
            Ok((pred - target).abs().mean(Kind::Float).double_value(&[]))
        })
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        self.save_with(path, true)
    }

    /// The teacher without its optimizer's moments (a third of the size):
    /// what the encoder's users and `--warm-start` read, not a checkpoint
    /// `--resume` can continue.
    pub fn save_weights(&self, path: &Path) -> Result<()> {
        self.save_with(path, false)
    }

    fn save_with(&self, path: &Path, optimizer: bool) -> Result<()> {
        let mut a = Archive::new();
        a.insert_all("renderer/", &self.model.renderer_vs.variables());
        a.insert_all("teacher/", &self.teacher_vs.variables());
        if optimizer {
            self.opt.save_into(&mut a, "opt/");
        }
        a.set_meta("step", self.step.to_string());
        a.set_meta("model_id", self.model.model_id());
        a.set_meta("teacher_config", serde_json::to_string(&self.config)?);
        a.save(path, FORMAT, VERSION)
    }

    /// A new run of `config` from the encoder and renderer of the teacher
    /// file `from`, with a fresh optimizer at step 0. The same model, or one
    /// that differs only in having more direction frequencies or no half
    /// angle: ND_enc then keeps the columns of the lower ones and adds the
    /// half angle's ([`lower_frequencies`]), how a `compact-f8h` teacher
    /// starts from a `compact` one.
    pub fn warm_started(config: TeacherConfig, from: &Path, device: Device) -> Result<Self> {
        let t = Self::new(config, device)?;
        let a = Archive::load(from, FORMAT, VERSION)?;
        let ctx = |what: &str| format!("{}: {what}", from.display());
        let theirs = a.meta("model_id")?;
        let mut renderer = a.with_prefix("renderer/");
        if theirs != t.model.model_id() {
            let their_config: TeacherConfig = serde_json::from_str(a.meta("teacher_config")?).with_context(|| ctx("unreadable configuration"))?;
            let (ours, their_model) = (&t.config.model, &their_config.model);
            let same_encoder_widths = ModelConfig {
                enc_frequencies: ours.enc_frequencies,
                half_angle_feature: ours.half_angle_feature,
                name: ours.name.clone(),
                ..their_model.clone()
            } == *ours;
            let (fewer, half_kept) = (their_model.enc_frequencies >= ours.enc_frequencies, ours.half_angle_feature || !their_model.half_angle_feature);
            ensure!(
                same_encoder_widths && fewer && half_kept,
                "{}: a teacher of model '{theirs}' cannot start a '{}' teacher (only the same model, or one with more direction frequencies or without the half angle)",
                from.display(),
                t.model.model_id()
            );
            let first = renderer.get_mut(ND_ENC_FIRST_LAYER).with_context(|| ctx("renderer: no ND_enc"))?;
            *first = lower_frequencies(first, their_model.enc_frequencies, their_model.half_angle_feature, ours.enc_frequencies, ours.half_angle_feature)
                .with_context(|| ctx("renderer"))?;
        }
        restore_vars(&t.model.renderer_vs.variables(), &renderer, &ctx("renderer"))?;
        restore_vars(&t.teacher_vs.variables(), &a.with_prefix("teacher/"), &ctx("teacher encoder"))?;
        Ok(t)
    }

    pub fn resume(path: &Path, device: Device) -> Result<Self> {
        let a = Archive::load(path, FORMAT, VERSION)?;
        let config: TeacherConfig = serde_json::from_str(a.meta("teacher_config")?).with_context(|| format!("{}: unreadable configuration", path.display()))?;
        let mut t = Self::new(config, device)?;
        let ctx = |what: &str| format!("{}: {what}", path.display());
        restore_vars(&t.model.renderer_vs.variables(), &a.with_prefix("renderer/"), &ctx("renderer"))?;
        restore_vars(&t.teacher_vs.variables(), &a.with_prefix("teacher/"), &ctx("teacher encoder"))?;
        t.opt.load_from(&a, "opt/")?;
        t.step = a.meta("step")?.parse().with_context(|| ctx("step"))?;
        Ok(t)
    }
}

/// ND_enc's first layer among a teacher file's renderer weights.
const ND_ENC_FIRST_LAYER: &str = "renderer.nd_enc.0.weight";

/// File of a teacher run folder (weights, optimizer, step: checkpoint and
/// the file the second stage reads).
pub fn teacher_file(dir: &Path) -> PathBuf {
    dir.join("teacher.safetensors")
}

/// Trains (or continues) the teacher in `dir` to `config.steps`, stopping
/// early after `minutes`. Logs `log.jsonl` with the held-out L1 at every
/// checkpoint. A folder that holds a teacher continues it (to `steps` when given).
pub fn run(config: TeacherConfig, dir: &Path, device: Device, minutes: Option<f64>, progress: bool) -> Result<TeacherTrainer> {
    let file = teacher_file(dir);
    let mut t = if file.exists() {
        let mut t = TeacherTrainer::resume(&file, device)?;
        ensure!(t.config.model == config.model, "{} holds a teacher of another model; use another folder", dir.display());
        let ignored = t.config.ignored_on_continue(&config);
        if !ignored.is_empty() {
            eprintln!("warning: {} continues with its stored recipe: {}", dir.display(), ignored.join(", "));
        }
        t.config.steps = config.steps;
        t
    } else {
        let t = match config.warm_start.clone() {
            Some(from) => TeacherTrainer::warm_started(config, Path::new(&from), device)?,
            None => TeacherTrainer::new(config, device)?,
        };
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        t
    };
    let started = Instant::now();
    let bar = if progress { ProgressBar::new(t.config.steps) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("teacher {bar:30} {pos}/{len} steps  {per_sec}  ETA {eta}  {msg}")?);
    bar.set_position(t.step);
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(dir.join("log.jsonl"))?;
    super::run::catch_stop_signals();
    while t.step < t.config.steps {
        let t0 = Instant::now();
        let l1 = t.train_step()?;
        let out_of_time = minutes.is_some_and(|m| started.elapsed().as_secs_f64() >= m * 60.0) || super::run::stop_requested();
        let checkpoint = t.step % t.config.checkpoint_every.max(1) == 0 || t.step == t.config.steps || out_of_time;
        let held_out_l1 = if checkpoint { Some(t.held_out_l1()?) } else { None };
        let held_out_any_l1 = if checkpoint && t.config.materials == PixelMaterials::AnyGgx { Some(t.held_out_any_l1()?) } else { None };
        let seconds = t0.elapsed().as_secs_f64();
        writeln!(log, "{}", serde_json::to_string(&TeacherStep { step: t.step, l1, held_out_l1, held_out_any_l1, seconds })?)?;
        if let Some(h) = held_out_l1 {
            log.flush()?;
            t.save(&file)?;
            let any = held_out_any_l1.map(|a| format!(", every GGX material {a:.4}")).unwrap_or_default();
            bar.set_message(format!("held-out L1 {h:.4}{any}"));
        }
        bar.set_position(t.step);
        if out_of_time {
            break;
        }
    }
    bar.finish_with_message(format!("step {}", t.step));
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_teacher_of_fewer_frequencies_or_with_the_half_angle_starts_from_another() {
        let dir = tempfile::tempdir().unwrap();
        let config = |frequencies: i64, hidden: i64| TeacherConfig {
            model: ModelConfig { enc_frequencies: frequencies, enc_hidden: hidden, ..ModelConfig::tiny() },
            ..TeacherConfig::default()
        };
        let from = dir.path().join("t16.safetensors");
        let sixteen = TeacherTrainer::new(config(16, 32), Device::Cpu).unwrap();
        sixteen.save(&from).unwrap();
        let eight = TeacherTrainer::warm_started(config(8, 32), &from, Device::Cpu).unwrap();
        let first = |t: &TeacherTrainer| t.model.renderer_vs.variables()[ND_ENC_FIRST_LAYER].shallow_clone();
        let want = crate::model::nd_enc::lower_frequencies(&first(&sixteen), 16, false, 8, false).unwrap();
        assert_eq!(first(&eight).size(), [32, 153]);
        assert!(first(&eight).equal(&want));
        let with_half = |frequencies| TeacherConfig { model: ModelConfig { half_angle_feature: true, ..config(frequencies, 32).model }, ..TeacherConfig::default() };
        let eight_half = TeacherTrainer::warm_started(with_half(8), &from, Device::Cpu).unwrap();
        assert_eq!(first(&eight_half).size(), [32, 154]);
        assert!(first(&eight_half).narrow(1, 0, 153).equal(&want));
        // The rest of the renderer and the encoder come over as they are.
        let m = "renderer.m_render.0.weight";
        assert!(eight.model.renderer_vs.variables()[m].equal(&sixteen.model.renderer_vs.variables()[m]));
        // Not from fewer frequencies, nor from another width.
        let eight_file = dir.path().join("t8.safetensors");
        eight.save(&eight_file).unwrap();
        let err = |r: Result<TeacherTrainer>| r.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err(TeacherTrainer::warm_started(config(16, 32), &eight_file, Device::Cpu)).contains("more direction frequencies"));
        assert!(err(TeacherTrainer::warm_started(config(8, 16), &from, Device::Cpu)).contains("cannot start"));
        let half_file = dir.path().join("t8h.safetensors");
        eight_half.save(&half_file).unwrap();
        assert!(err(TeacherTrainer::warm_started(config(8, 32), &half_file, Device::Cpu)).contains("without the half angle"));
    }

    #[test]
    fn samples_match_the_scalar_ggx_oracle() {
        tch::manual_seed(3);
        let (maps, wi, wo, target) = pixel_samples(64, 0.5, COMMITTED_MIN_ROUGHNESS, PixelMaterials::Procedural, Device::Cpu);
        assert_eq!(maps.size(), [64, 10]);
        for r in [0i64, 17, 63] {
            let v = |t: &Tensor, i: i64| t.double_value(&[r, i]);
            let pm = crate::svbrdf::scalar::PixelMaterial {
                kd: [v(&maps, 0), v(&maps, 1), v(&maps, 2)],
                ks: [v(&maps, 3), v(&maps, 4), v(&maps, 5)],
                roughness: v(&maps, 6),
                normal: [v(&maps, 7), v(&maps, 8), v(&maps, 9)],
            };
            // Far-away point light and camera along the sampled directions.
            let far = |d: &Tensor| [1e6 * v(d, 0), 1e6 * v(d, 1), 1e6 * v(d, 2)];
            let expected = crate::svbrdf::scalar::radiance_at(&pm, [0.0, 0.0, 0.0], far(&wi), far(&wo));
            for c in 0..3 {
                let want = (1.0 + expected[c].max(0.0)).ln();
                assert!((v(&target, c as i64) - want).abs() < 1e-3 * (1.0 + want), "row {r} channel {c}: {} vs {want}", v(&target, c as i64));
            }
        }
        // Unit directions in the upper hemisphere; a quarter of views near the light.
        let z = |t: &Tensor| t.narrow(1, 2, 1).min().double_value(&[]);
        assert!(z(&wi) > 0.0 && z(&wo) > 0.0);
        tch::manual_seed(4);
        let (_, wi, wo, _) = pixel_samples(20_000, 0.0, COMMITTED_MIN_ROUGHNESS, PixelMaterials::Procedural, Device::Cpu);
        let near = (&wi * &wo).sum_dim_intlist([1i64].as_slice(), false, Kind::Float).gt(0.99).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]);
        assert!((0.2..0.32).contains(&near), "fraction of near-co-located pairs {near}");
        // With a lobe share, about that share of a glossy pixel's pairs (alpha
        // below 0.05; less the mirrored lights that fall below the surface)
        // has its half vector within 4 alpha of the normal; without, few.
        let in_lobe = |share: f64| {
            tch::manual_seed(5);
            let (maps, wi, wo, _) = pixel_samples(50_000, share, COMMITTED_MIN_ROUGHNESS, PixelMaterials::Procedural, Device::Cpu);
            let h = normalize_rows(&(&wi + &wo));
            let cos = (&h * maps.narrow(1, 7, 3)).sum_dim_intlist([1i64].as_slice(), false, Kind::Float).clamp(-1.0, 1.0);
            let alpha = maps.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1).squeeze_dim(1).square();
            let glossy = alpha.lt(0.05);
            let inside = cos.acos().lt_tensor(&(&alpha * 4.0)).logical_and(&glossy);
            inside.to_kind(Kind::Float).sum(Kind::Float).double_value(&[]) / glossy.to_kind(Kind::Float).sum(Kind::Float).double_value(&[])
        };
        let (none, half) = (in_lobe(0.0), in_lobe(0.5));
        assert!(none < 0.05 && (0.35..0.55).contains(&half), "glossy pairs inside the lobe: {none} without, {half} with a share of 0.5");
    }

    #[test]
    fn the_sampled_roughness_starts_at_the_recipes_floor() {
        tch::manual_seed(6);
        let rough = |floor: f64| pixel_samples(40_000, 0.5, floor, PixelMaterials::Procedural, Device::Cpu).0.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1);
        let below = |r: &Tensor, v: f64| r.lt(v).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]);
        let committed = rough(COMMITTED_MIN_ROUGHNESS);
        assert!(committed.min().double_value(&[]) >= COMMITTED_MIN_ROUGHNESS - 1e-7 && below(&committed, COMMITTED_MIN_ROUGHNESS) == 0.0);
        // From 0.02: uniform on [0.02, 1), so 0.03 / 0.98 = 3.06% of the pixels below 0.05.
        let low = rough(0.02);
        assert!(low.min().double_value(&[]) >= 0.02 - 1e-7 && low.max().double_value(&[]) < 1.0);
        assert!((below(&low, 0.05) - 0.0306).abs() < 0.004, "{}", below(&low, 0.05));
        // Below the procedural materials' lowest, or at 1, is refused.
        for floor in [0.01, 1.0] {
            let cfg = TeacherConfig { model: ModelConfig::tiny(), min_roughness: floor, ..Default::default() };
            let e = TeacherTrainer::new(cfg, Device::Cpu).err().unwrap();
            assert!(format!("{e}").contains("--min-roughness must be from 0.02"), "{e}");
        }
    }

    #[test]
    fn the_dark_floor_counts_a_dark_pixels_error_relative_to_its_radiance() {
        // Rows (prediction, truth) as radiance R: a dark pixel drawn twice too
        // bright, and one predicted below zero (clamped to 0 in the second term).
        let as_log1p = |r: [f32; 2]| Tensor::from_slice(&r).view([2, 1]).expand([2, 3], false).log1p();
        let (pred, target) = (as_log1p([0.012, -0.005]), as_log1p([0.006, 0.006]));
        let log1p_l1 = ((1.012f64 / 1.006).ln() + (1.006f64 / 0.995).ln()) / 2.0; // 0.005947, 0.010995
        let relative = ((0.022f64 / 0.016).ln() + (0.016f64 / 0.010).ln()) / 2.0; // 0.318454, 0.470004
        let loss = |f: f64| teacher_loss(&pred, &target, f).double_value(&[]);
        assert!((loss(0.0) - log1p_l1).abs() < 1e-6, "{} against {log1p_l1}", loss(0.0));
        assert!((loss(0.01) - (log1p_l1 + relative)).abs() < 1e-5, "{} against {}", loss(0.01), log1p_l1 + relative);
        assert!(teacher_loss(&target, &target, 0.01).double_value(&[]).abs() < 1e-7);
    }

    #[test]
    fn teacher_learns_and_resumes_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = TeacherConfig { model: ModelConfig::tiny(), pixels: 2048, steps: 60, checkpoint_every: 30, lr: 3e-3, seed: 2, ..Default::default() };
        let fresh = TeacherTrainer::new(cfg.clone(), Device::Cpu).unwrap();
        let before = fresh.held_out_l1().unwrap();
        let full = run(cfg.clone(), &dir.path().join("a"), Device::Cpu, None, false).unwrap();
        let after = full.held_out_l1().unwrap();
        assert!(after < 0.7 * before, "held-out L1 {before} -> {after}");
        // Stopped at step 30 and continued: the same weights.
        run(TeacherConfig { steps: 30, ..cfg.clone() }, &dir.path().join("b"), Device::Cpu, None, false).unwrap();
        let resumed = run(cfg.clone(), &dir.path().join("b"), Device::Cpu, None, false).unwrap();
        assert_eq!(resumed.step, 60);
        // A continued teacher keeps its recipe; what a caller gave otherwise is named.
        assert!(cfg.ignored_on_continue(&TeacherConfig { steps: 90, ..cfg.clone() }).is_empty());
        let ignored = cfg.ignored_on_continue(&TeacherConfig { lr: 3e-4, lobe_share: 0.5, dark_floor: 0.01, min_roughness: 0.02, ..cfg.clone() });
        let named = ["--lr 0.003 (given 0.0003)", "--lobe-share 0 (given 0.5)", "--dark-floor 0 (given 0.01)", "--min-roughness 0.05 (given 0.02)"];
        assert_eq!(ignored, named.map(String::from));
        let theirs = resumed.model.renderer_vs.variables();
        for (name, a) in full.model.renderer_vs.variables() {
            assert!(a.allclose(&theirs[&name], 1e-6, 1e-7, false), "{name}");
        }
        // The second stage loads it: encoder frozen, renderer copied.
        let model = Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap();
        let teacher = Teacher::load(&teacher_file(&dir.path().join("a")), &ModelConfig::tiny(), Device::Cpu, Some(&model.renderer_vs)).unwrap();
        assert!(teacher.vs.variables().values().all(|t| !t.requires_grad()), "the teacher is frozen");
        let codes = teacher.encoder.forward_maps(&Tensor::rand([2, 10, 4, 4], (Kind::Float, Device::Cpu)));
        assert_eq!(codes.size(), [2, ModelConfig::tiny().neural_channels as i64, 4, 4]);
        // Another model is refused.
        let e = Teacher::load(&teacher_file(&dir.path().join("a")), &ModelConfig::compact(), Device::Cpu, None).err().unwrap();
        assert!(format!("{e:#}").contains("cannot train"), "{e:#}");
    }
}
