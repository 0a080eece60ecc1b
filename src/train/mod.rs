//! Training of M_est, ND_enc + M_render and the discriminator with the
//! paper's losses (REFERENCE section 5): L1 on log renders, LPIPS, and a
//! conditional least-squares discriminator; alternating optimizers;
//! checkpoints that resume exactly. The baselines train on the same
//! batches with the same losses in [`baseline`].

pub mod baseline;
pub mod batches;
pub mod checkpoint;
pub mod config;
pub mod losses;
pub mod run;
pub mod smoke;
pub mod teacher;

pub use baseline::BaselineTrainer;
pub use config::{PixelSampling, Shard, TrainConfig, UpdateScheme};

use crate::data::samples::TrainingBatch;
use crate::dist::Group;
use crate::lpips::Lpips;
use crate::model::{Discriminator, Model};
use crate::optim::Adam;
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Tensor};

/// The lobe term's random stream (`batches::step_rng`; 1-4 are the batch's
/// and the pixel mask's).
const LOBE_STREAM: u64 = 5;

/// Loss terms of one step (what the JSONL log records).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct StepLosses {
    pub step: u64,
    pub lr: f64,
    /// L1 on log renders seen by M_est (full image).
    pub l1: f64,
    pub lpips: f64,
    pub adv: f64,
    /// Total loss of the M_est update.
    pub loss_est: f64,
    /// Pixel-sampled L1 of the renderer update.
    pub l1_render: f64,
    /// Total loss of the renderer update.
    pub loss_render: f64,
    /// Discriminator least-squares loss.
    pub loss_disc: f64,
    /// Relative L1 between M_est's neural map and the teacher's codes (0
    /// without a teacher).
    #[serde(default)]
    pub code: f64,
    /// Shift-consistency term, unweighted (0 without it).
    #[serde(default)]
    pub shift: f64,
    /// GGX-value term (`losses::ggx_value_l1`), plain mean over all pixels
    /// (0 without it).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ggx_values: f64,
    /// Lobe term of the renderer's half, unweighted (0 without it).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub lobe: f64,
    /// Mean L2 norm of the neural parameters (watch for "garbage" vectors).
    pub param_norm: f64,
    /// Global L2 norm of M_est's gradients before any `--grad-clip` (what
    /// a clip value is chosen against; a divergence shows here first); in a
    /// data-parallel run rank 0's own, before averaging. 0 while M_est is frozen.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub grad_norm_est: f64,
    /// True when the step was skipped because a loss or gradient was NaN/Inf.
    pub skipped: bool,
    pub seconds: f64,
    /// Of `seconds`, those spent in a data-parallel run's collectives
    /// (rank 0's, waiting for the slowest rank included; 0 alone).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub sync_seconds: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// Largest change a projection may make to a kernel that counts as
/// projected already (float rounding is ~1e-8 at these weights' scale; one
/// update moves a kernel off by ~lr).
const PROJECTED_TOLERANCE: f64 = 1e-6;

/// M_est's forward on a training batch ([`Trainer::estimate`]).
struct Estimate {
    /// The neural map `[N, C, H, W]`.
    neural: Tensor,
    /// The weighted shift-consistency term, with the term on and a batch
    /// that has second photos.
    shift_term: Option<Tensor>,
    /// The head's GGX values `[N, 10, H, W]`, for a model that writes them
    /// and a run with the GGX-value term.
    ggx_values: Option<Tensor>,
}

/// All trainable state: networks, their optimizers, the perceptual metric.
pub struct Trainer {
    pub config: TrainConfig,
    pub model: Model,
    pub disc_vs: nn::VarStore,
    pub disc: Discriminator,
    pub opt_est: Adam,
    pub opt_render: Adam,
    pub opt_disc: Adam,
    pub lpips: Option<Lpips>,
    /// The frozen per-pixel teacher of the curriculum's second stage.
    pub teacher: Option<teacher::Teacher>,
    /// The frozen model whose renders are the non-co-located outputs'
    /// targets (`TrainConfig::anchor`).
    pub anchor: Option<Model>,
    /// Steps completed.
    pub step: u64,
    /// Runs the alternating scheme as two passes (M_est's update, then
    /// the renderer's on a second forward) instead of the one shared
    /// forward that gives the same gradients: the reference for the
    /// equivalence test and `bench train` ([`Trainer::use_reference_step`]).
    two_pass: bool,
    /// The process group of a data-parallel run ([`Trainer::join`]).
    pub group: Option<std::sync::Arc<Group>>,
}

/// Trainable variables of a store, by name (what an optimizer updates).
pub(crate) fn trainable(vs: &nn::VarStore) -> std::collections::HashMap<String, Tensor> {
    vs.variables().into_iter().filter(|(_, t)| t.requires_grad()).collect()
}

/// Non-trainable state (BatchNorm running statistics) of the stores.
pub(crate) fn buffers_of(stores: &[&nn::VarStore]) -> Vec<Tensor> {
    stores.iter().flat_map(|vs| vs.variables().into_values().filter(|t| !t.requires_grad())).collect()
}

/// BatchNorm running statistics of the stores, by name within each store
/// (one order on every rank: a VarStore's map is ordered per process).
pub(crate) fn running_stats(stores: &[&nn::VarStore]) -> Vec<Tensor> {
    stores
        .iter()
        .flat_map(|vs| {
            let mut v: Vec<(String, Tensor)> = vs.variables().into_iter().filter(|(n, t)| !t.requires_grad() && n.contains("running_")).collect();
            v.sort_by(|a, b| a.0.cmp(&b.0));
            v.into_iter().map(|(_, t)| t)
        })
        .collect()
}

/// Every variable of the stores (weights and BatchNorm statistics) made
/// rank 0's, in place.
pub(crate) fn broadcast_stores(group: &Group, stores: &[&nn::VarStore]) -> Result<()> {
    let mut all: Vec<Tensor> = Vec::new();
    for vs in stores {
        let mut v: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        all.extend(v.into_iter().map(|(_, t)| t));
    }
    tch::no_grad(|| group.broadcast(&mut all, 0))
}

/// Data-parallel training's one collective of a step: the gradients of
/// `nets` and the BatchNorm statistics `buffers` averaged over the ranks,
/// with each rank's verdict on its own step. Every rank calls it exactly
/// once a step, before any optimizer steps (collectives match by order),
/// with `ok` false where its step already failed (a NaN/Inf loss or
/// gradient). Returns whether every rank's step is fine and the averaged
/// gradients are finite: one answer on every rank, so all skip or step
/// together, clip alike (the averaged gradients are the same everywhere)
/// and count skipped steps alike. Without a group: `ok`.
pub(crate) fn synchronise(group: Option<&Group>, nets: &[&Adam], buffers: &[Tensor], ok: bool) -> Result<bool> {
    let Some(group) = group else { return Ok(ok) };
    // A rank that failed before its backward pass may have no gradients:
    // zeros stand in (every rank skips that step).
    let mut all: Vec<Tensor> = nets
        .iter()
        .flat_map(|o| o.params())
        .map(|p| {
            let g = p.grad();
            if g.defined() { g } else { p.zeros_like() }
        })
        .collect();
    all.extend(buffers.iter().map(|b| b.shallow_clone()));
    let failed = group.average(&all, &[if ok { 0.0 } else { 1.0 }])?;
    Ok(failed[0] == 0.0 && nets.iter().all(|o| o.grad_norm().is_finite()))
}

/// Runs one update. Forward passes in training mode update BatchNorm
/// running statistics, so when the update reports a skipped (NaN/Inf) step
/// `buffers` get their values from before it back: never poisoned.
pub(crate) fn restoring_buffers_if_skipped(buffers: Vec<Tensor>, update: impl FnOnce() -> Result<StepLosses>) -> Result<StepLosses> {
    let saved: Vec<Tensor> = buffers.iter().map(|b| b.copy()).collect();
    let out = update()?;
    if out.skipped {
        tch::no_grad(|| {
            for (b, s) in buffers.iter().zip(&saved) {
                b.shallow_clone().copy_(s);
            }
        });
    }
    Ok(out)
}

impl Trainer {
    /// Fresh networks initialised from the configured seed.
    pub fn new(config: TrainConfig, device: Device) -> Result<Self> {
        config.validate()?;
        anyhow::ensure!(
            config.method.is_flashmat(),
            "a '{}' run is trained by train::BaselineTrainer, not the flashmat trainer",
            config.method
        );
        tch::manual_seed(config.seed as i64);
        let model = Model::new(&config.model, device)?;
        model.renderer.m_render.straight_through_output.store(config.straight_through_output, std::sync::atomic::Ordering::Relaxed);
        let (disc_vs, disc) = Discriminator::with_store(&config.model, device);
        let opt_est = Adam::new(trainable(&model.est_vs));
        let opt_render = Adam::new(trainable(&model.renderer_vs));
        let opt_disc = Adam::new(trainable(&disc_vs));
        let lpips = if config.weight_lpips > 0.0 { Some(Lpips::new(device)?) } else { None };
        // The teacher's renderer replaces the fresh one (a checkpoint being
        // resumed overwrites it again with its own).
        let teacher = match &config.teacher {
            Some(file) => Some(teacher::Teacher::load(std::path::Path::new(file), &config.model, device, Some(&model.renderer_vs))?),
            None => None,
        };
        let anchor = match &config.anchor {
            Some(file) => {
                let (mut anchor, _) = Model::load_expecting(file, device, &model.model_id()).context("--anchor")?;
                anchor.est_vs.freeze();
                anchor.renderer_vs.freeze();
                Some(anchor)
            }
            None => None,
        };
        let trainer = Self { config, model, disc_vs, disc, opt_est, opt_render, opt_disc, lpips, teacher, anchor, step: 0, two_pass: false, group: None };
        trainer.codes_from_teacher();
        Ok(trainer)
    }

    /// A model whose M_est writes GGX values takes the teacher's encoder
    /// behind its head (the code space of the teacher's renderer), at full
    /// precision, whatever a warm start's file held.
    pub(crate) fn codes_from_teacher(&self) {
        if let (Some(codes), Some(teacher)) = (&self.model.est.codes, &self.teacher) {
            tch::no_grad(|| {
                for (mut mine, theirs) in codes.weights().into_iter().zip(teacher.encoder.weights()) {
                    mine.copy_(&theirs);
                }
            });
        }
    }

    /// Joins a data-parallel run: every network's weights and BatchNorm
    /// statistics become rank 0's (a fresh start seeds them alike, a
    /// resume reads one checkpoint; this makes sure), and from now on each
    /// step averages the gradients over the ranks before it steps.
    pub fn join(&mut self, group: std::sync::Arc<Group>) -> Result<()> {
        broadcast_stores(&group, &[&self.model.est_vs, &self.model.renderer_vs, &self.disc_vs])?;
        self.group = Some(group);
        Ok(())
    }

    /// [`synchronise`] of this step: all three networks' gradients and
    /// BatchNorm statistics.
    fn synchronise(&self, ok: bool) -> Result<bool> {
        let buffers = running_stats(&[&self.model.est_vs, &self.model.renderer_vs, &self.disc_vs]);
        synchronise(self.group.as_deref(), &[&self.opt_est, &self.opt_render, &self.opt_disc], &buffers, ok)
    }

    pub fn device(&self) -> Device {
        self.model.device()
    }

    /// The step as it ran before the shared forward: the alternating
    /// scheme in two passes and Adam in tensor operations (the same
    /// updates to float rounding). `bench train` times it against the
    /// default, inside [`crate::reference_paths::with`] for the rest.
    pub fn use_reference_step(&mut self) {
        self.two_pass = true;
        for opt in [&mut self.opt_est, &mut self.opt_render, &mut self.opt_disc] {
            opt.fused = false;
        }
    }

    /// Runs the three optimizers on flat buffers, the GPU's path, wherever
    /// the networks are (`optim::Adam::new_flat`): the CPU's tests and
    /// `bench train` prove it with this. Before the first step (the
    /// moments start again from zero).
    pub fn use_flat_optimizers(&mut self) {
        self.opt_est = Adam::new_flat(trainable(&self.model.est_vs));
        self.opt_render = Adam::new_flat(trainable(&self.model.renderer_vs));
        self.opt_disc = Adam::new_flat(trainable(&self.disc_vs));
    }

    /// One training step on a batch; returns its losses. A NaN/Inf loss or
    /// gradient skips every update of the step (logged, never saved).
    pub fn train_step(&mut self, batch: &TrainingBatch) -> Result<StepLosses> {
        let lr = self.config.lr_at(self.step);
        let weight_adv = self.config.adv_weight_at(self.step);
        let out = restoring_buffers_if_skipped(self.buffers(), || match self.config.scheme {
            UpdateScheme::Alternating if self.shares_one_forward() => self.shared_forward_step(batch, lr, weight_adv),
            UpdateScheme::Alternating => self.alternating_step(batch, lr, weight_adv),
            UpdateScheme::Combined => self.combined_step(batch, lr, weight_adv),
        })?;
        self.step += 1;
        if !out.skipped {
            self.apply_weight_constraints();
        }
        Ok(StepLosses { step: self.step, lr, ..out })
    }

    /// Projects the weights onto what the configuration constrains them to
    /// (`checkerboard_free`); nothing otherwise, nor where they already lie
    /// there: projecting a projected kernel again moves it by rounding, and
    /// a resumed run would then drift from the uninterrupted one.
    pub fn apply_weight_constraints(&self) {
        if self.config.checkerboard_free && !self.model.est.is_checkerboard_free(PROJECTED_TOLERANCE) {
            self.model.est.project_checkerboard_free();
        }
    }

    /// Non-trainable state of all networks (BatchNorm running statistics).
    fn buffers(&self) -> Vec<Tensor> {
        buffers_of(&[&self.model.est_vs, &self.model.renderer_vs, &self.disc_vs])
    }

    fn zero_all(&mut self) {
        self.opt_est.zero_grad();
        self.opt_render.zero_grad();
        self.opt_disc.zero_grad();
    }

    fn alternating_step(&mut self, b: &TrainingBatch, lr: f64, weight_adv: f64) -> Result<StepLosses> {
        let cfg = self.config.clone();
        let truth_log = crate::spaces::to_log(&b.targets);
        let mut readout = Readout::default();

        // The direction code does not depend on the neural map: encode once,
        // use it detached for the M_est half (the renderer is frozen there)
        // and with its graph for the renderer half.
        self.zero_all();
        let code = self.model.renderer.encode_maps(&b.out_wi, &b.out_wo)?;

        if cfg.freeze_estimator {
            let neural = self.frozen_neural_map(b)?;
            readout.push(|o, v| o.param_norm = v, losses::mean_param_norm_tensor(&neural));
            return self.renderer_and_discriminator_updates(b, neural, &code, &truth_log, lr, weight_adv, readout);
        }

        let photo_log = b.est_input.narrow(1, 0, 3);

        // 1. M_est update; the renderer takes part in the graph but is not
        // stepped. Nothing is read back until the step's end (`Readout`).
        let Estimate { neural, shift_term, ggx_values } = self.estimate(b)?;
        let pred = self.model.renderer.render_code(&neural, &code.detach())?;
        let l1 = (&pred - &truth_log).abs().mean(tch::Kind::Float);
        let lp = losses::perceptual(self.lpips.as_ref(), &pred, &truth_log)?;
        let adv = losses::adversarial(&self.disc, &pred, &photo_log, weight_adv)?;
        let mut loss_est = &l1 * cfg.weight_l1 + &lp * cfg.weight_lpips + &adv * weight_adv + chroma_term(&cfg, &pred, &truth_log);
        if let Some((code, plain)) = self.code_term(b, &neural) {
            readout.push(|o, v| o.code = v, plain);
            loss_est = loss_est + code * cfg.code_weight_at(self.step);
        }
        if let Some(t) = shift_term {
            readout.push(|o, v| o.shift = v, t.detach() / cfg.weight_shift);
            loss_est = loss_est + t;
        }
        if let Some((term, plain)) = self.ggx_value_term(b, ggx_values.as_ref()) {
            readout.push(|o, v| o.ggx_values = v, plain);
            loss_est = loss_est + term;
        }
        if cfg.weight_lobe > 0.0 {
            loss_est = loss_est + self.lobe_term(b, &neural)? * cfg.weight_lobe;
        }
        readout.push(|o, v| o.l1 = v, l1.detach());
        readout.push(|o, v| o.lpips = v, lp.detach());
        readout.push(|o, v| o.adv = v, adv.detach());
        readout.push(|o, v| o.loss_est = v, loss_est.detach());
        readout.push(|o, v| o.param_norm = v, losses::mean_param_norm_tensor(&neural));
        loss_est.backward();
        readout.push(|o, v| o.grad_norm_est = v, self.opt_est.grad_norm_tensor());
        if cfg.freeze_renderer {
            let (out, finite) = readout.read();
            // Every rank's verdict and gradients averaged (one process: as it is).
            let finite = self.synchronise(finite)?;
            if finite {
                self.opt_est.step(lr, cfg.grad_clip);
            }
            self.zero_all();
            return Ok(StepLosses { skipped: !finite, ..out });
        }

        self.renderer_and_discriminator_updates(b, neural.detach(), &code, &truth_log, lr, weight_adv, readout)
    }

    /// Whether the step's two alternating updates can share one forward
    /// pass: both networks train (neither is frozen) and both see the same
    /// targets (no anchor), so the two halves' losses differ only in their
    /// L1 term.
    fn shares_one_forward(&self) -> bool {
        !self.two_pass && !self.config.freeze_estimator && !self.config.freeze_renderer && self.anchor.is_none() && self.config.weight_lobe == 0.0
    }

    /// The teacher-code term of this step on `neural` `[N, C, H, W]`
    /// (`losses::code_l1`, glossy pixels weighted by `code_gloss_weight`),
    /// before its schedule's weight, and its plain unweighted measure
    /// (detached) for the log, so runs with and without the weighting
    /// compare; None without a teacher or once the term has faded.
    fn code_term(&self, b: &TrainingBatch, neural: &Tensor) -> Option<(Tensor, Tensor)> {
        let teacher = self.teacher.as_ref().filter(|_| self.config.code_weight_at(self.step) > 0.0)?;
        let target = tch::no_grad(|| teacher.encoder.forward_maps(&b.maps));
        let roughness = b.maps.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1);
        let gloss_weight = self.config.code_gloss_weight;
        let term = losses::code_l1(neural, &target, &roughness, gloss_weight);
        let plain = if gloss_weight == 0.0 { term.detach() } else { losses::code_l1(&neural.detach(), &target, &roughness, 0.0) };
        Some((term, plain))
    }

    /// The GGX-value term of this step on the head's values `[N, 10, H, W]`
    /// (`losses::ggx_value_l1`, glossy pixels weighted by
    /// `code_gloss_weight`), weighted, and its plain unweighted-by-gloss
    /// measure (detached) for the log; None without the term.
    fn ggx_value_term(&self, b: &TrainingBatch, values: Option<&Tensor>) -> Option<(Tensor, Tensor)> {
        let values = values.filter(|_| self.config.weight_ggx_values > 0.0)?;
        let gloss_weight = self.config.code_gloss_weight;
        let term = losses::ggx_value_l1(values, &b.maps, gloss_weight);
        let plain = if gloss_weight == 0.0 { term.detach() } else { losses::ggx_value_l1(&values.detach(), &b.maps, 0.0) };
        Some((term * self.config.weight_ggx_values, plain))
    }

    /// The lobe term (`losses::lobe_l1`) of this step on `neural` `[N, C, H, W]`:
    /// the same pixels and directions in both halves (one stream per step).
    fn lobe_term(&self, b: &TrainingBatch, neural: &Tensor) -> Result<Tensor> {
        let mut rng = batches::step_rng(self.config.seed, self.step, self.config.shard.stream(LOBE_STREAM));
        losses::lobe_l1(&self.model.renderer, neural, &b.maps, &self.config.lobe_sampling(), &mut rng)
    }

    /// The alternating scheme's step from one forward pass. The two-pass
    /// step ([`Trainer::alternating_step`]) renders the same prediction
    /// twice (the optimizers step only at the end, so both halves see the
    /// same weights) and runs LPIPS and the discriminator's generator term
    /// on it twice, though its halves' losses differ only in the L1 term
    /// (the whole image for M_est, the sampled pixels for the renderer).
    /// Here the graph is cut at the neural map and at the prediction: the
    /// shared terms' gradient with respect to the prediction is computed
    /// once, each half's is that plus its own L1's, and each is pulled back
    /// only into the networks it updates (M_est's through the renderer's
    /// input side, without the renderer's or the discriminator's weight
    /// gradients, which the two-pass step computes and throws away); the
    /// three backward passes that remain run in three threads. Same
    /// gradients, same updates, up to float rounding
    /// (`shared_forward_step_matches_two_passes`).
    fn shared_forward_step(&mut self, b: &TrainingBatch, lr: f64, weight_adv: f64) -> Result<StepLosses> {
        use tch::Kind;
        let cfg = self.config.clone();
        let truth_log = crate::spaces::to_log(&b.targets);
        let photo_log = b.est_input.narrow(1, 0, 3);
        self.zero_all();

        // Forward, with the graph cut at the neural map and at the prediction.
        let Estimate { neural, shift_term, ggx_values } = self.estimate(b)?;
        let neural_in = neural.detach().set_requires_grad(true);
        let code = self.model.renderer.encode_maps(&b.out_wi, &b.out_wo)?;
        let rendered = self.model.renderer.render_code(&neural_in, &code)?;
        let pred = rendered.detach().set_requires_grad(true);

        // Both halves' losses on the one prediction.
        let l1 = (&pred - &truth_log).abs().mean(Kind::Float);
        let mut rng = batches::step_rng(cfg.seed, self.step, cfg.shard.stream(3));
        let mask = losses::pixel_mask(&neural, &b.targets, cfg.pixel_fraction, cfg.pixel_sampling, &mut rng);
        let l1_r = losses::masked_l1(&pred, &truth_log, &mask);
        let lp = losses::perceptual(self.lpips.as_ref(), &pred, &truth_log)?;
        let adv = losses::adversarial(&self.disc, &pred, &photo_log, weight_adv)?;
        let shared = &lp * cfg.weight_lpips + &adv * weight_adv + chroma_term(&cfg, &pred, &truth_log);
        let (code_term, code_plain) = match self.code_term(b, &neural) {
            Some((term, plain)) => (Some(term * cfg.code_weight_at(self.step)), Some(plain)),
            None => (None, None),
        };
        let (value_term, value_plain) = self.ggx_value_term(b, ggx_values.as_ref()).unzip();
        let mut loss_est = &l1 * cfg.weight_l1 + &shared;
        for t in [&code_term, &shift_term, &value_term].into_iter().flatten() {
            loss_est = loss_est + t;
        }
        let loss_render = &l1_r * cfg.weight_l1 + &shared;
        let mut readout = Readout::default();
        if let Some(plain) = code_plain {
            readout.push(|o, v| o.code = v, plain);
        }
        if let Some(t) = &shift_term {
            readout.push(|o, v| o.shift = v, t.detach() / cfg.weight_shift);
        }
        if let Some(plain) = value_plain {
            readout.push(|o, v| o.ggx_values = v, plain);
        }
        readout.push(|o, v| o.l1 = v, l1.detach());
        readout.push(|o, v| o.lpips = v, lp.detach());
        readout.push(|o, v| o.adv = v, adv.detach());
        readout.push(|o, v| o.loss_est = v, loss_est.detach());
        readout.push(|o, v| o.param_norm = v, losses::mean_param_norm_tensor(&neural));
        readout.push(|o, v| o.l1_render = v, l1_r.detach());
        readout.push(|o, v| o.loss_render = v, loss_render.detach());

        // d(loss)/d(prediction): the shared terms' once, each L1's on its own.
        // Nothing is read back before the step's end: a non-finite loss
        // makes non-finite gradients, and the one check there skips both.
        let grad_of = |loss: &Tensor| {
            let g = if loss.requires_grad() { Tensor::run_backward(&[loss], &[&pred], true, false).pop() } else { None };
            g.filter(|g| g.defined()).unwrap_or_else(|| pred.zeros_like())
        };
        let grad_shared = grad_of(&shared);
        let grad_est = &grad_shared + grad_of(&(&l1 * cfg.weight_l1));
        let grad_render = grad_shared + grad_of(&(&l1_r * cfg.weight_l1));

        // M_est: through the renderer's input side only, then into M_est.
        let grad_neural = Tensor::run_backward(&[(&rendered * &grad_est).sum(Kind::Float)], &[&neural_in], true, false).remove(0);
        let mut est_objective = (&neural * &grad_neural).sum(Kind::Float);
        for term in [code_term, shift_term, value_term].into_iter().flatten() {
            est_objective = est_objective + term;
        }
        // Three independent backward passes at once: M_est's here, the
        // renderer's weights' and the discriminator's update in two more
        // threads. Each touches only its own network, and the small ops
        // of M_est's low-resolution layers leave cores idle that the
        // others fill.
        let render_objective = (&rendered * &grad_render).sum(Kind::Float);
        let (pred, photo) = (pred.detach(), photo_log.shallow_clone());
        let truth = truth_log.shallow_clone();
        let disc = OneThread(&self.disc);
        self.opt_disc.zero_grad();
        let loss_disc = std::thread::scope(|scope| {
            let renderer = scope.spawn(move || render_objective.backward());
            let discriminator = scope.spawn(move || -> Result<Tensor> {
                let loss = losses::discriminator_loss(disc.get(), &pred, &truth, &photo, weight_adv)?;
                if weight_adv > 0.0 {
                    loss.backward();
                }
                Ok(loss.detach())
            });
            est_objective.backward();
            renderer.join().map_err(|_| anyhow::anyhow!("the renderer's backward pass panicked"))?;
            discriminator.join().map_err(|_| anyhow::anyhow!("the discriminator's update panicked"))?
        })?;
        readout.push(|o, v| o.loss_disc = v, loss_disc);
        readout.push(|o, v| o.grad_norm_est = v, self.opt_est.grad_norm_tensor());
        for norm in [self.opt_render.grad_norm_tensor(), self.opt_disc.grad_norm_tensor()] {
            readout.check(norm);
        }
        let (out, finite) = readout.read();
        // Every rank's verdict and gradients averaged (one process: as it is).
        let finite = self.synchronise(finite)?;
        if !finite {
            self.zero_all();
            return Ok(StepLosses { skipped: true, ..out });
        }
        self.apply_steps(lr, weight_adv);
        Ok(out)
    }

    /// M_est's neural map of the batch `[N, C, H, W]`; with the
    /// shift-consistency term on and a batch that has second photos, the
    /// weighted term (`losses::shift_consistency`: both photos go through
    /// one forward); with the GGX-value term, the head's values.
    fn estimate(&self, b: &TrainingBatch) -> Result<Estimate> {
        let batch_stats = self.config.est_batch_stats_at(self.step);
        let n = b.est_input.size()[0];
        let second = b.shifted.as_ref().filter(|_| self.config.weight_shift > 0.0);
        let input = match second {
            Some(second) => Tensor::cat(&[&b.est_input, &second.est_input], 0),
            None => b.est_input.shallow_clone(),
        };
        let (all, head) = self.model.est.forward_with_head(&input, batch_stats)?;
        // The head's GGX values, for the term that reads them.
        let wants_head = self.model.config.ggx_codes && self.config.weight_ggx_values > 0.0;
        let ggx_values = wants_head.then(|| crate::precision::to_f32(head.narrow(0, 0, n)));
        let neural = all.narrow(0, 0, n);
        let shift_term = second.map(|second| {
            losses::shift_consistency(&neural, &all.narrow(0, n, n), &second.offsets, self.config.shift_scale_free) * self.config.weight_shift
        });
        Ok(Estimate { neural, shift_term, ggx_values })
    }

    /// M_est as at inference (`TrainConfig::freeze_estimator`): no
    /// gradient, BatchNorm on its running statistics. -> `[B, C, H, W]`.
    fn frozen_neural_map(&self, b: &TrainingBatch) -> Result<Tensor> {
        tch::no_grad(|| self.model.est.forward_t(&b.est_input, false))
    }

    /// The alternating step's second half: the renderer's update on the
    /// (detached) neural map with pixel-sampled L1, the discriminator's,
    /// then, when everything `readout` holds is finite, the optimizer steps
    /// (M_est's too unless it is frozen). `readout` carries the first
    /// half's losses and gradient norm.
    /// neural: `[B, C, H, W]` detached; code: the direction code of the
    /// outputs; truth_log: ln(1 + R) of `b.targets`.
    #[allow(clippy::too_many_arguments)]
    fn renderer_and_discriminator_updates(
        &mut self,
        b: &TrainingBatch,
        neural: Tensor,
        code: &Tensor,
        truth_log: &Tensor,
        lr: f64,
        weight_adv: f64,
        mut readout: Readout,
    ) -> Result<StepLosses> {
        let cfg = self.config.clone();
        let target_log = match &self.anchor {
            Some(anchor) => anchored_targets(anchor, &neural, b, truth_log, cfg.colocated_outputs)?,
            None => truth_log.shallow_clone(),
        };
        let photo_log = b.est_input.narrow(1, 0, 3);
        // 2. Renderer update on the detached neural map, pixel-sampled L1.
        self.opt_render.zero_grad();
        self.opt_disc.zero_grad();
        let pred_r = self.model.renderer.render_code(&neural, code)?;
        let mut rng = batches::step_rng(cfg.seed, self.step, cfg.shard.stream(3));
        let mask = losses::pixel_mask(&neural, &b.targets, cfg.pixel_fraction, cfg.pixel_sampling, &mut rng);
        let l1_r = losses::masked_l1(&pred_r, &target_log, &mask);
        if cfg.freeze_estimator {
            // No M_est half ran: log the full-image L1 against the truth it would have seen.
            readout.push(|o, v| o.l1 = v, tch::no_grad(|| (&pred_r - truth_log).abs().mean(tch::Kind::Float)));
        }
        let lp_r = losses::perceptual(self.lpips.as_ref(), &pred_r, &target_log)?;
        let adv_r = losses::adversarial(&self.disc, &pred_r, &photo_log, weight_adv)?;
        let mut loss_render = &l1_r * cfg.weight_l1 + &lp_r * cfg.weight_lpips + &adv_r * weight_adv + chroma_term(&cfg, &pred_r, &target_log);
        if cfg.weight_lobe > 0.0 {
            let lobe = self.lobe_term(b, &neural)?;
            readout.push(|o, v| o.lobe = v, lobe.detach());
            loss_render = loss_render + lobe * cfg.weight_lobe;
        }
        readout.push(|o, v| o.l1_render = v, l1_r.detach());
        readout.push(|o, v| o.loss_render = v, loss_render.detach());
        loss_render.backward();
        readout.check(self.opt_render.grad_norm_tensor());

        // 3. The discriminator on the detached prediction.
        self.opt_disc.zero_grad();
        let loss_disc = losses::discriminator_loss(&self.disc, &pred_r.detach(), truth_log, &photo_log, weight_adv)?;
        if weight_adv > 0.0 {
            loss_disc.backward();
        }
        readout.push(|o, v| o.loss_disc = v, loss_disc.detach());
        readout.check(self.opt_disc.grad_norm_tensor());

        let (out, finite) = readout.read();
        // Every rank's verdict and gradients averaged (one process: as it is).
        let finite = self.synchronise(finite)?;
        if !finite {
            self.zero_all();
            return Ok(StepLosses { skipped: true, ..out });
        }
        self.apply_steps(lr, weight_adv);
        Ok(out)
    }

    /// Every loss and gradient is finite: the three optimizer steps (M_est's
    /// unless it is frozen, the discriminator's while it has a weight),
    /// then the gradients cleared.
    fn apply_steps(&mut self, lr: f64, weight_adv: f64) {
        let clip = self.config.grad_clip;
        if !self.config.freeze_estimator {
            self.opt_est.step(lr, clip);
        }
        self.opt_render.step(lr, clip);
        if weight_adv > 0.0 {
            self.opt_disc.step(lr, clip);
        }
        self.zero_all();
    }

    fn combined_step(&mut self, b: &TrainingBatch, lr: f64, weight_adv: f64) -> Result<StepLosses> {
        let cfg = self.config.clone();
        let target_log = crate::spaces::to_log(&b.targets);
        let photo_log = b.est_input.narrow(1, 0, 3);
        self.zero_all();
        let neural = if cfg.freeze_estimator {
            self.frozen_neural_map(b)?
        } else {
            self.model.est.forward_t(&b.est_input, cfg.est_batch_stats_at(self.step))?
        };
        let pred = self.model.renderer.forward_maps(&neural, &b.out_wi, &b.out_wo)?;
        let param_norm = losses::mean_param_norm(&neural);
        let mut nets: Vec<&mut Adam> = match (cfg.freeze_estimator, cfg.freeze_renderer) {
            (true, _) => vec![&mut self.opt_render],
            (_, true) => vec![&mut self.opt_est],
            _ => vec![&mut self.opt_est, &mut self.opt_render],
        };
        let buffers = running_stats(&[&self.model.est_vs, &self.model.renderer_vs, &self.disc_vs]);
        let out = combined_update(&cfg, self.lpips.as_ref(), &self.disc, &mut nets, &mut self.opt_disc, &pred, &target_log, &photo_log, lr, weight_adv, (self.group.as_deref(), &buffers))?;
        Ok(StepLosses { param_norm, ..out })
    }
}

/// A borrowed network handed to one scoped thread of a training step.
/// tch's `Tensor` is `Send` but not `Sync` because nothing stops two
/// threads from mutating one tensor at once; the step gives each network
/// to exactly one thread while its threads run, which is what libtorch's
/// own multithreaded autograd requires.
struct OneThread<'a, T>(&'a T);

// SAFETY: see the type's documentation; only the receiving thread uses
// the network until the scope joins it.
unsafe impl<T> Send for OneThread<'_, T> {}

impl<'a, T> OneThread<'a, T> {
    /// The borrow (a method, so a closure captures the whole wrapper).
    fn get(self) -> &'a T {
        self.0
    }
}

/// A step's loss values and gradient norms, kept on the device and read
/// back together at the step's end ([`losses::read_scalars`]): on a GPU
/// every read waits for the queue to drain. A non-finite loss makes
/// non-finite gradients, so deciding at the end skips the same steps as
/// deciding at each term.
#[derive(Default)]
struct Readout {
    fields: Vec<Option<fn(&mut StepLosses, f64)>>,
    values: Vec<Tensor>,
}

impl Readout {
    /// A 0-dim value for a field of the step's losses (and the finite check).
    fn push(&mut self, field: fn(&mut StepLosses, f64), value: Tensor) {
        self.fields.push(Some(field));
        self.values.push(value);
    }

    /// A 0-dim value for the finite check only (a gradient norm).
    fn check(&mut self, value: Tensor) {
        self.fields.push(None);
        self.values.push(value);
    }

    /// One read-back: the losses, and whether every value was finite.
    fn read(self) -> (StepLosses, bool) {
        let values = losses::read_scalars(&self.values.iter().collect::<Vec<_>>());
        let mut out = StepLosses::default();
        for (field, v) in self.fields.iter().zip(&values) {
            if let Some(set) = field {
                set(&mut out, *v);
            }
        }
        (out, values.iter().all(|v| v.is_finite()))
    }
}

/// The weighted colour-balance term (`TrainConfig::weight_chroma`; a
/// constant 0 when off, so the paper's graph is unchanged).
/// pred, target_log: `[N, K, 3, H, W]` log renders -> scalar.
fn chroma_term(cfg: &TrainConfig, pred: &Tensor, target_log: &Tensor) -> Tensor {
    if cfg.weight_chroma == 0.0 {
        return Tensor::zeros([], (tch::Kind::Float, pred.device()));
    }
    losses::chroma_l1(pred, target_log) * cfg.weight_chroma
}

/// The renderer's targets with an anchor: the last `colocated` outputs of
/// each material keep the truth, the others become the anchor's renders of
/// the same neural map and directions (`TrainConfig::anchor`).
/// neural: `[N, C, H, W]`; truth_log: ln(1 + R) `[N, K, 3, H, W]` -> the same shape.
fn anchored_targets(anchor: &Model, neural: &Tensor, b: &TrainingBatch, truth_log: &Tensor, colocated: usize) -> Result<Tensor> {
    let k = truth_log.size()[1];
    let held = k - colocated as i64;
    if held <= 0 {
        return Ok(truth_log.shallow_clone());
    }
    let (wi, wo) = (b.out_wi.narrow(1, 0, held), b.out_wo.narrow(1, 0, held));
    let anchor_log = tch::no_grad(|| anchor.renderer.forward_maps(neural, &wi, &wo))?;
    Ok(Tensor::cat(&[anchor_log, truth_log.narrow(1, held, k - held)], 1))
}

/// The update shared by one-pass training (flashmat's combined scheme and
/// the baselines): the paper's three loss terms (and the optional colour
/// balance) on `pred`, one backward
/// pass into the networks of `nets`, the discriminator's least-squares
/// step on the detached prediction, then every optimizer step. A NaN/Inf
/// loss or gradient clears all gradients and returns `skipped` without
/// stepping. The caller zeroes the gradients before its forward pass.
/// pred, target_log: `[B, K, 3, H, W]` log renders; photo_log: `[B, 3, H, W]`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn combined_update(
    cfg: &TrainConfig,
    lpips: Option<&Lpips>,
    disc: &Discriminator,
    nets: &mut [&mut Adam],
    opt_disc: &mut Adam,
    pred: &Tensor,
    target_log: &Tensor,
    photo_log: &Tensor,
    lr: f64,
    weight_adv: f64,
    (group, buffers): (Option<&Group>, &[Tensor]),
) -> Result<StepLosses> {
    let mut out = StepLosses::default();
    let l1 = (pred - target_log).abs().mean(tch::Kind::Float);
    let lp = losses::perceptual(lpips, pred, target_log)?;
    let adv = losses::adversarial(disc, pred, photo_log, weight_adv)?;
    let loss = &l1 * cfg.weight_l1 + &lp * cfg.weight_lpips + &adv * weight_adv + chroma_term(cfg, pred, target_log);
    out.l1 = l1.double_value(&[]);
    out.l1_render = out.l1;
    out.lpips = lp.double_value(&[]);
    out.adv = adv.double_value(&[]);
    out.loss_est = loss.double_value(&[]);
    out.loss_render = out.loss_est;
    // Before the step's collective: join it with a failed verdict (every rank skips).
    let skip = |nets: &mut [&mut Adam], opt_disc: &mut Adam, out: StepLosses| {
        nets.iter_mut().for_each(|o| o.zero_grad());
        opt_disc.zero_grad();
        let all: Vec<&Adam> = nets.iter().map(|o| &**o).chain([&*opt_disc]).collect();
        synchronise(group, &all, buffers, false)?;
        Ok(StepLosses { skipped: true, ..out })
    };
    if !out.loss_est.is_finite() {
        return skip(nets, opt_disc, out);
    }
    loss.backward();
    let norms: Vec<f64> = nets.iter().map(|o| o.grad_norm()).collect();
    if !norms.iter().all(|n| n.is_finite()) {
        return skip(nets, opt_disc, out);
    }
    if !cfg.freeze_estimator {
        out.grad_norm_est = norms[0]; // nets: M_est's first when it trains
    }
    opt_disc.zero_grad();
    let loss_disc = losses::discriminator_loss(disc, &pred.detach(), target_log, photo_log, weight_adv)?;
    out.loss_disc = loss_disc.double_value(&[]);
    if weight_adv > 0.0 {
        loss_disc.backward();
        if !(out.loss_disc.is_finite() && opt_disc.grad_norm().is_finite()) {
            return skip(nets, opt_disc, out);
        }
    }
    let all: Vec<&Adam> = nets.iter().map(|o| &**o).chain([&*opt_disc]).collect();
    if !synchronise(group, &all, buffers, true)? {
        nets.iter_mut().for_each(|o| o.zero_grad());
        opt_disc.zero_grad();
        return Ok(StepLosses { skipped: true, ..out });
    }
    nets.iter_mut().for_each(|o| o.step(lr, cfg.grad_clip));
    if weight_adv > 0.0 {
        opt_disc.step(lr, cfg.grad_clip);
    }
    nets.iter_mut().for_each(|o| o.zero_grad());
    opt_disc.zero_grad();
    Ok(out)
}

#[cfg(test)]
mod tests;
