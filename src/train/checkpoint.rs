//! Training checkpoints: every network's weights (BatchNorm statistics
//! included), the three optimizers' moments, the step and the full
//! configuration, in one checksummed archive written atomically. All other
//! randomness derives from (seed, step), so this is everything a resumed run
//! needs to continue exactly.

use super::{TrainConfig, Trainer};
use crate::archive::{restore_vars, Archive};
use anyhow::{bail, ensure, Context, Result};
use std::path::Path;
use tch::Device;

pub const FORMAT: &str = "flashmat-checkpoint";
pub const VERSION: u32 = 1;

impl Trainer {
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let mut a = Archive::new();
        a.insert_all("est/", &self.model.est_vs.variables());
        a.insert_all("renderer/", &self.model.renderer_vs.variables());
        a.insert_all("disc/", &self.disc_vs.variables());
        self.opt_est.save_into(&mut a, "opt_est/");
        self.opt_render.save_into(&mut a, "opt_render/");
        self.opt_disc.save_into(&mut a, "opt_disc/");
        a.set_meta("step", self.step.to_string());
        a.set_meta("model_id", self.model.model_id());
        a.set_meta("train_config", serde_json::to_string(&self.config)?);
        a.save(path, FORMAT, VERSION)
    }

    /// The training configuration stored in a checkpoint.
    pub fn checkpoint_config(path: &Path) -> Result<TrainConfig> {
        let a = Archive::load(path, FORMAT, VERSION)?;
        serde_json::from_str(a.meta("train_config")?).with_context(|| format!("{}: unreadable training configuration", path.display()))
    }

    /// Fine-tuning: replaces every network's weights (BatchNorm statistics
    /// included) with those of another run's checkpoint of the same model.
    /// The optimizers and the step stay fresh.
    pub fn load_weights_from(&mut self, path: &Path) -> Result<()> {
        let a = Archive::load(path, FORMAT, VERSION)?;
        let theirs = a.meta("model_id")?;
        if theirs != self.model.model_id() {
            bail!("{}: weights of model '{theirs}' cannot start a '{}' run (another preset or configuration)", path.display(), self.model.model_id());
        }
        let ctx = |what: &str| format!("{}: {what}", path.display());
        restore_vars(&self.model.est_vs.variables(), &a.with_prefix("est/"), &ctx("M_est"))?;
        restore_vars(&self.model.renderer_vs.variables(), &a.with_prefix("renderer/"), &ctx("renderer"))?;
        restore_vars(&self.disc_vs.variables(), &a.with_prefix("disc/"), &ctx("discriminator"))
    }

    /// Warm restart from an exported model file (`flashmat export`): M_est
    /// (BatchNorm statistics included) and the renderer take its weights,
    /// the step count its recorded steps; the optimizers and the
    /// discriminator stay fresh. The file must hold the same model, trained
    /// on the same kind of input photos. With a teacher (`--teacher`) a
    /// model of another preset is accepted where its M_est has the same
    /// layout: M_est alone is taken and the renderer stays the teacher's
    /// (the code term then moves a trained M_est into the teacher's code
    /// space, issue 48); a model of the same preset (a curriculum chunk's
    /// export) gives both halves, as without a teacher.
    pub fn warm_start_from(&mut self, path: &Path) -> Result<()> {
        let device = self.device();
        let (model, info) = if self.teacher.is_some() {
            crate::model::Model::load(path, device)?
        } else {
            crate::model::Model::load_expecting(path, device, &self.model.model_id())?
        };
        let estimator_only = model.model_id() != self.model.model_id();
        ensure!(
            !estimator_only || model.config.ggx_codes == self.model.config.ggx_codes,
            "{}: M_est writes {} there and {} in this run: a compact-g run starts from a compact-g model (`examples/code_adapter.rs ... ggx` makes one from a compact model)",
            path.display(),
            if model.config.ggx_codes { "GGX values" } else { "neural codes" },
            if self.model.config.ggx_codes { "GGX values" } else { "neural codes" }
        );
        if info.ldr_input != self.config.ldr_input {
            bail!(
                "{}: a model trained on {} photos cannot warm-start a run on {} photos (--ldr)",
                path.display(),
                if info.ldr_input { "LDR" } else { "HDR" },
                if self.config.ldr_input { "LDR" } else { "HDR" }
            );
        }
        if estimator_only {
            restore_vars(&self.model.est_vs.variables(), &model.est_vs.variables(), &format!("{}: M_est (warm start beside the teacher's renderer)", path.display()))?;
        } else {
            let named = model.named_variables().into_iter().collect();
            self.model.load_named(&named).with_context(|| format!("{}: warm start", path.display()))?;
        }
        self.codes_from_teacher();
        self.step = info.steps;
        Ok(())
    }

    /// Rebuilds a trainer from a checkpoint. `expect` (when given) must
    /// describe the same model, otherwise the checkpoint is refused.
    pub fn resume(path: &Path, device: Device, expect: Option<&TrainConfig>) -> Result<Self> {
        let a = Archive::load(path, FORMAT, VERSION)?;
        let config: TrainConfig = serde_json::from_str(a.meta("train_config")?).with_context(|| format!("{}: unreadable training configuration", path.display()))?;
        if let Some(e) = expect {
            if e.model.model_id() != config.model.model_id() {
                bail!(
                    "{}: checkpoint of model '{}' cannot be resumed as '{}' (another preset or configuration)",
                    path.display(),
                    config.model.model_id(),
                    e.model.model_id()
                );
            }
        }
        let mut t = Trainer::new(config, device)?;
        if a.meta("model_id")? != t.model.model_id() {
            bail!("{}: model id mismatch inside the checkpoint", path.display());
        }
        let ctx = |what: &str| format!("{}: {what}", path.display());
        restore_vars(&t.model.est_vs.variables(), &a.with_prefix("est/"), &ctx("M_est"))?;
        restore_vars(&t.model.renderer_vs.variables(), &a.with_prefix("renderer/"), &ctx("renderer"))?;
        restore_vars(&t.disc_vs.variables(), &a.with_prefix("disc/"), &ctx("discriminator"))?;
        t.opt_est.load_from(&a, "opt_est/")?;
        t.opt_render.load_from(&a, "opt_render/")?;
        t.opt_disc.load_from(&a, "opt_disc/")?;
        t.step = a.meta("step")?.parse().with_context(|| ctx("step"))?;
        Ok(t)
    }
}
