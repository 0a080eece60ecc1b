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
use crate::model::{Model, ModelConfig};
use crate::svbrdf::render::render_directions;
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
}

/// The committed teacher's lowest sampled roughness.
pub const COMMITTED_MIN_ROUGHNESS: f64 = 0.05;

fn committed_min_roughness() -> f64 {
    COMMITTED_MIN_ROUGHNESS
}

impl Default for TeacherConfig {
    fn default() -> Self {
        Self { model: ModelConfig::compact(), pixels: 16_384, lr: 1e-3, steps: 5_000, checkpoint_every: 250, seed: 1, lobe_share: 0.0, dark_floor: 0.0, min_roughness: COMMITTED_MIN_ROUGHNESS }
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
pub fn pixel_samples(n: i64, lobe_share: f64, min_roughness: f64, device: Device) -> (Tensor, Tensor, Tensor, Tensor) {
    let opts = (Kind::Float, device);
    let kd = Tensor::rand([n, 3], opts).pow_tensor_scalar(2.2);
    let coloured = Tensor::rand([n, 1], opts).lt(0.3).to_kind(Kind::Float);
    let ks = &coloured * Tensor::rand([n, 3], opts).pow_tensor_scalar(2.2) + (1.0 - &coloured) * 0.04;
    let rough = Tensor::rand([n, 1], opts) * (1.0 - min_roughness) + min_roughness;
    let tilt = Tensor::randn([n, 2], opts) * 0.25;
    let normal = normalize_rows(&Tensor::cat(&[tilt, Tensor::ones([n, 1], opts)], 1));
    let cosine = |n: i64| {
        let u1 = Tensor::rand([n, 1], opts);
        let phi = Tensor::rand([n, 1], opts) * (2.0 * std::f64::consts::PI);
        let r = u1.sqrt();
        Tensor::cat(&[&r * phi.cos(), &r * phi.sin(), (1.0f64 - &u1).clamp_min(1e-4).sqrt()], 1)
    };
    let wi = cosine(n);
    let near = normalize_rows(&(&wi + Tensor::randn([n, 3], opts) * 0.05));
    let near = Tensor::cat(&[near.narrow(1, 0, 2), near.narrow(1, 2, 1).clamp_min(0.05)], 1);
    let near = normalize_rows(&near);
    let colocated = Tensor::rand([n, 1], opts).lt(0.25).to_kind(Kind::Float);
    let wo = normalize_rows(&(&colocated * near + (1.0 - &colocated) * cosine(n)));
    let maps = Tensor::cat(&[kd, ks, rough, normal], 1);
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

/// Lights inside each row's GGX lobe: the view `wo` mirrored about a half
/// vector drawn around the row's normal, `offsets` x 1.5 alpha along x and
/// y (alpha = roughness^2). maps: `[R, 10]` (kd, ks, roughness, normal);
/// wo: `[R, 3]` unit; offsets: `[R, 2]` standard normal draws -> (wi
/// `[R, 3]`, `[R, 1]` bool: the light is above the surface, z > 0.02).
pub fn lobe_lights(maps: &Tensor, wo: &Tensor, offsets: &Tensor) -> (Tensor, Tensor) {
    let alpha = maps.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1).square();
    let n = maps.size()[0];
    let shift = Tensor::cat(&[offsets * (&alpha * 1.5), Tensor::zeros([n, 1], (offsets.kind(), offsets.device()))], 1);
    let h = normalize_rows(&(maps.narrow(1, 7, 3) + shift));
    let mirrored = normalize_rows(&(&h * (wo * &h).sum_dim_intlist([1i64].as_slice(), true, Kind::Float) * 2.0 - wo));
    let above = mirrored.narrow(1, 2, 1).gt(0.02);
    (mirrored, above)
}

pub(crate) fn normalize_rows(v: &Tensor) -> Tensor {
    v / v.square().sum_dim_intlist([1i64].as_slice(), true, Kind::Float).sqrt().clamp_min(1e-12)
}

/// ln(1 + R) of the GGX renderer for rows. maps `[R, 10]`, wi, wo `[R, 3]` -> `[R, 3]`.
pub fn ggx_log_rows(maps: &Tensor, wi: &Tensor, wo: &Tensor) -> Tensor {
    let n = maps.size()[0];
    let as_image = |t: &Tensor| t.transpose(0, 1).reshape([1, -1, n, 1]);
    let dirs = |t: &Tensor| as_image(t).unsqueeze(1); // [1, 1, 3, R, 1]
    let r = render_directions(&as_image(maps), &dirs(wi), &dirs(wo)); // [1, 1, 3, R, 1]
    r.reshape([3, n]).transpose(0, 1).clamp_min(0.0).log1p()
}

/// The teacher's loss: the L1 of ln(1 + R), plus with `dark_floor` F > 0 the
/// L1 of ln(F + R) (the prediction's radiance clamped at 0 there; the first
/// term still pulls a negative one up). pred, target: ln(1 + R) `[R, 3]` -> scalar.
pub fn teacher_loss(pred: &Tensor, target: &Tensor, dark_floor: f64) -> Tensor {
    let l1 = (pred - target).abs().mean(Kind::Float);
    if dark_floor <= 0.0 {
        return l1;
    }
    let relative = |log1p: &Tensor| (log1p.expm1().clamp_min(0.0) + dark_floor).log();
    l1 + (relative(pred) - relative(target)).abs().mean(Kind::Float)
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
        let (maps, wi, wo, target) = tch::no_grad(|| pixel_samples(self.config.pixels as i64, self.config.lobe_share, self.config.min_roughness, device));
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

    /// L1 of ln(1 + R) on the fixed held-out samples.
    pub fn held_out_l1(&self) -> Result<f64> {
        let device = self.model.device();
        tch::no_grad(|| {
            tch::manual_seed(HELD_OUT_SEED);
            // The committed recipe's distribution, whatever the run trains on: comparable across runs.
            let (maps, wi, wo, target) = pixel_samples(HELD_OUT_PIXELS, 0.0, COMMITTED_MIN_ROUGHNESS, device);
            let pred = self.model.renderer.forward_rows(&self.encoder.forward_rows(&maps), &wi, &wo)?;
            Ok((pred - target).abs().mean(Kind::Float).double_value(&[]))
        })
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        let mut a = Archive::new();
        a.insert_all("renderer/", &self.model.renderer_vs.variables());
        a.insert_all("teacher/", &self.teacher_vs.variables());
        self.opt.save_into(&mut a, "opt/");
        a.set_meta("step", self.step.to_string());
        a.set_meta("model_id", self.model.model_id());
        a.set_meta("teacher_config", serde_json::to_string(&self.config)?);
        a.save(path, FORMAT, VERSION)
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
        let t = TeacherTrainer::new(config, device)?;
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
        writeln!(log, "{}", serde_json::to_string(&TeacherStep { step: t.step, l1, held_out_l1, seconds: t0.elapsed().as_secs_f64() })?)?;
        if let Some(h) = held_out_l1 {
            log.flush()?;
            t.save(&file)?;
            bar.set_message(format!("held-out L1 {h:.4}"));
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
    fn samples_match_the_scalar_ggx_oracle() {
        tch::manual_seed(3);
        let (maps, wi, wo, target) = pixel_samples(64, 0.5, COMMITTED_MIN_ROUGHNESS, Device::Cpu);
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
        let (_, wi, wo, _) = pixel_samples(20_000, 0.0, COMMITTED_MIN_ROUGHNESS, Device::Cpu);
        let near = (&wi * &wo).sum_dim_intlist([1i64].as_slice(), false, Kind::Float).gt(0.99).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]);
        assert!((0.2..0.32).contains(&near), "fraction of near-co-located pairs {near}");
        // With a lobe share, about that share of a glossy pixel's pairs (alpha
        // below 0.05; less the mirrored lights that fall below the surface)
        // has its half vector within 4 alpha of the normal; without, few.
        let in_lobe = |share: f64| {
            tch::manual_seed(5);
            let (maps, wi, wo, _) = pixel_samples(50_000, share, COMMITTED_MIN_ROUGHNESS, Device::Cpu);
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
        let rough = |floor: f64| pixel_samples(40_000, 0.5, floor, Device::Cpu).0.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1);
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
        let cfg = TeacherConfig { model: ModelConfig::tiny(), pixels: 2048, steps: 60, checkpoint_every: 30, lr: 3e-3, seed: 2, lobe_share: 0.0, dark_floor: 0.0, min_roughness: COMMITTED_MIN_ROUGHNESS };
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
