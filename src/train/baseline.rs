//! Training of the baselines ([`crate::baselines`]) on flashmat's batches
//! with flashmat's losses: per step one update of the baseline network with
//! L = w_l1 L1(log renders) + w_lpips LPIPS + w_adv |D(prediction, photo) - 1|
//! (the terms and weights of M_est's update; every pixel enters the L1
//! term, as there is no renderer update to sample pixels for), then the
//! same conditional least-squares discriminator update as flashmat's.
//! Checkpoints hold the network, the discriminator and both optimizers'
//! moments, so a resumed run continues exactly.

use crate::optim::Adam;
use super::{trainable, StepLosses, TrainConfig};
use crate::archive::{restore_vars, Archive};
use crate::baselines::{Baseline, BaselineNet};
use crate::data::samples::TrainingBatch;
use crate::image::Image;
use crate::lpips::Lpips;
use crate::model::Discriminator;
use anyhow::{bail, ensure, Context, Result};
use std::path::Path;
use tch::{nn, Device, Tensor};

/// A baseline network, the discriminator, their optimizers and the
/// perceptual metric.
pub struct BaselineTrainer {
    pub config: TrainConfig,
    pub net: Baseline,
    pub disc_vs: nn::VarStore,
    pub disc: Discriminator,
    pub opt_net: Adam,
    pub opt_disc: Adam,
    pub lpips: Option<Lpips>,
    /// Steps completed.
    pub step: u64,
    /// The process group of a data-parallel run ([`BaselineTrainer::join`]).
    pub group: Option<std::sync::Arc<crate::dist::Group>>,
}

impl BaselineTrainer {
    /// Fresh networks initialised from the configured seed.
    pub fn new(config: TrainConfig, device: Device) -> Result<Self> {
        config.validate()?;
        ensure!(!config.method.is_flashmat(), "BaselineTrainer trains the baselines; flashmat runs use train::Trainer");
        tch::manual_seed(config.seed as i64);
        let net = Baseline::new(config.method, &config.model, device)?;
        let (disc_vs, disc) = Discriminator::with_store(&config.model, device);
        let opt_net = Adam::new(trainable(&net.vs));
        let opt_disc = Adam::new(trainable(&disc_vs));
        let lpips = if config.weight_lpips > 0.0 { Some(Lpips::new(device)?) } else { None };
        Ok(Self { config, net, disc_vs, disc, opt_net, opt_disc, lpips, step: 0, group: None })
    }

    /// Joins a data-parallel run (as [`super::Trainer::join`]).
    pub fn join(&mut self, group: std::sync::Arc<crate::dist::Group>) -> Result<()> {
        super::broadcast_stores(&group, &[&self.net.vs, &self.disc_vs])?;
        self.group = Some(group);
        Ok(())
    }

    pub fn device(&self) -> Device {
        self.net.device()
    }

    fn zero_all(&mut self) {
        self.opt_net.zero_grad();
        self.opt_disc.zero_grad();
    }

    /// BatchNorm running statistics of both networks.
    fn buffers(&self) -> Vec<Tensor> {
        super::buffers_of(&[&self.net.vs, &self.disc_vs])
    }

    /// One step on a batch. A NaN/Inf loss or gradient skips every update
    /// of the step (and restores the BatchNorm statistics).
    pub fn train_step(&mut self, batch: &TrainingBatch) -> Result<StepLosses> {
        let lr = self.config.lr_at(self.step);
        let out = super::restoring_buffers_if_skipped(self.buffers(), || self.update(batch, lr))?;
        self.step += 1;
        Ok(StepLosses { step: self.step, lr, ..out })
    }

    fn update(&mut self, b: &TrainingBatch, lr: f64) -> Result<StepLosses> {
        let cfg = self.config.clone();
        let weight_adv = cfg.adv_weight_at(self.step);
        let target_log = crate::spaces::to_log(&b.targets);
        let photo_log = b.est_input.narrow(1, 0, 3);
        self.zero_all();
        let pred = self.net.forward_t(&b.est_input, &b.out_wi, &b.out_wo, true)?;
        let buffers = super::running_stats(&[&self.net.vs, &self.disc_vs]);
        let mut nets = [&mut self.opt_net];
        super::combined_update(&cfg, self.lpips.as_ref(), &self.disc, &mut nets, &mut self.opt_disc, &pred, &target_log, &photo_log, lr, weight_adv, (self.group.as_deref(), &buffers))
    }

    /// Writes a checkpoint (same archive format as flashmat's, with the
    /// baseline's variables under `net/`).
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let mut a = Archive::new();
        a.insert_all("net/", &self.net.vs.variables());
        a.insert_all("disc/", &self.disc_vs.variables());
        self.opt_net.save_into(&mut a, "opt_net/");
        self.opt_disc.save_into(&mut a, "opt_disc/");
        a.set_meta("step", self.step.to_string());
        a.set_meta("model_id", self.net.model_id());
        a.set_meta("train_config", serde_json::to_string(&self.config)?);
        a.save(path, super::checkpoint::FORMAT, super::checkpoint::VERSION)
    }

    /// Rebuilds a trainer from a baseline checkpoint; checkpoints of
    /// flashmat runs, of another model id, or damaged ones are refused.
    pub fn resume(path: &Path, device: Device) -> Result<Self> {
        let a = Archive::load(path, super::checkpoint::FORMAT, super::checkpoint::VERSION)?;
        let config: TrainConfig = serde_json::from_str(a.meta("train_config")?).with_context(|| format!("{}: unreadable training configuration", path.display()))?;
        if config.method.is_flashmat() {
            bail!("{}: a flashmat checkpoint, not a baseline's", path.display());
        }
        let mut t = Self::new(config, device)?;
        if a.meta("model_id")? != t.net.model_id() {
            bail!("{}: model id mismatch inside the checkpoint", path.display());
        }
        let ctx = |what: &str| format!("{}: {what}", path.display());
        restore_vars(&t.net.vs.variables(), &a.with_prefix("net/"), &ctx(t.config.method.name()))?;
        restore_vars(&t.disc_vs.variables(), &a.with_prefix("disc/"), &ctx("discriminator"))?;
        t.opt_net.load_from(&a, "opt_net/")?;
        t.opt_disc.load_from(&a, "opt_disc/")?;
        t.step = a.meta("step")?.parse().with_context(|| ctx("step"))?;
        Ok(t)
    }

    /// Input | targets (top row) and a method picture | predictions (bottom
    /// row) for the first material of a batch. The method picture is the
    /// predicted diffuse albedo (analytic) or the re-rendered input photo
    /// (relighting U-Net).
    pub fn preview_grid(&self, batch: &TrainingBatch, max_outputs: usize) -> Result<Image> {
        let k = (batch.targets.size()[1] as usize).min(max_outputs) as i64;
        tch::no_grad(|| -> Result<Image> {
            let x = batch.est_input.narrow(0, 0, 1);
            let wi = batch.out_wi.narrow(0, 0, 1).narrow(1, 0, k);
            let wo = batch.out_wo.narrow(0, 0, 1).narrow(1, 0, k);
            let pred = self.net.forward_t(&x, &wi, &wo, false)?;
            let display = Image::display_of;
            let first = match &self.net.net {
                BaselineNet::Analytic(a) => display(&a.maps_t(&x, false)?.get(0).narrow(0, 0, 3))?,
                BaselineNet::Relight(r) => {
                    let s = x.size();
                    let (iwi, iwo) = crate::data::samples::input_directions(s[2] as usize, s[3] as usize, crate::geometry::MODEL_FOV_DEG, x.device());
                    let again = r.forward_t(&x, &iwi.unsqueeze(1), &iwo.unsqueeze(1), false)?;
                    display(&crate::spaces::from_log(&again.get(0).get(0)))?
                }
            };
            let mut top = vec![display(&batch.input_linear.get(0))?];
            let mut bottom = vec![first];
            for i in 0..k {
                top.push(display(&batch.targets.get(0).get(i))?);
                bottom.push(display(&crate::spaces::from_log(&pred.get(0).get(i)))?);
            }
            crate::viz::grid(&[top, bottom], 2)
        })
    }
}
