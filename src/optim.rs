//! Adam written out with tensors so that its moment estimates can be saved
//! in checkpoints (tch's built-in optimizer does not expose its state) and a
//! resumed run continues bit-for-bit.

use crate::archive::Archive;
use anyhow::{Context, Result};
use std::collections::{BTreeMap, HashMap};
use tch::Tensor;

pub struct Adam {
    /// Trainable parameters by name (sorted for a deterministic update order).
    params: BTreeMap<String, Tensor>,
    exp_avg: BTreeMap<String, Tensor>,
    exp_avg_sq: BTreeMap<String, Tensor>,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Number of updates applied (for bias correction).
    pub steps: i64,
}

impl Adam {
    /// params: the trainable variables of one network (name -> tensor).
    pub fn new(params: HashMap<String, Tensor>) -> Self {
        let params: BTreeMap<String, Tensor> = params.into_iter().filter(|(_, t)| t.requires_grad()).collect();
        let exp_avg = params.iter().map(|(k, v)| (k.clone(), v.zeros_like())).collect();
        let exp_avg_sq = params.iter().map(|(k, v)| (k.clone(), v.zeros_like())).collect();
        Self { params, exp_avg, exp_avg_sq, beta1: 0.9, beta2: 0.999, eps: 1e-8, steps: 0 }
    }

    pub fn zero_grad(&mut self) {
        for p in self.params.values() {
            let mut g = p.grad();
            if g.defined() {
                let _ = g.detach_().zero_();
            }
        }
    }

    /// Global L2 norm of the current gradients (NaN/Inf if any gradient is).
    pub fn grad_norm(&self) -> f64 {
        let mut total = 0f64;
        for p in self.params.values() {
            let g = p.grad();
            if g.defined() {
                total += g.square().sum(tch::Kind::Double).double_value(&[]);
            }
        }
        total.sqrt()
    }

    /// Applies one update with learning rate `lr`, first scaling gradients
    /// so that their global norm is at most `clip` when given.
    pub fn step(&mut self, lr: f64, clip: Option<f64>) {
        let scale = match clip {
            Some(max) => {
                let n = self.grad_norm();
                if n > max { max / (n + 1e-12) } else { 1.0 }
            }
            None => 1.0,
        };
        self.steps += 1;
        let bc1 = 1.0 - self.beta1.powi(self.steps as i32);
        let bc2 = 1.0 - self.beta2.powi(self.steps as i32);
        tch::no_grad(|| {
            for (name, p) in &self.params {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let g = if scale != 1.0 { &g * scale } else { g };
                let mut m = self.exp_avg[name].shallow_clone();
                let mut v = self.exp_avg_sq[name].shallow_clone();
                let _ = m.g_mul_scalar_(self.beta1).g_add_(&(&g * (1.0 - self.beta1)));
                let _ = v.g_mul_scalar_(self.beta2).g_add_(&(g.square() * (1.0 - self.beta2)));
                let denom = (&v / bc2).sqrt() + self.eps;
                let update = (&m / bc1) / denom * lr;
                let _ = p.shallow_clone().g_sub_(&update);
            }
        });
    }

    /// Stores the moments under `prefix` and the step count in metadata.
    pub fn save_into(&self, archive: &mut Archive, prefix: &str) {
        for (k, v) in &self.exp_avg {
            archive.insert(format!("{prefix}m/{k}"), v);
        }
        for (k, v) in &self.exp_avg_sq {
            archive.insert(format!("{prefix}v/{k}"), v);
        }
        archive.set_meta(&format!("{prefix}steps"), self.steps.to_string());
    }

    pub fn load_from(&mut self, archive: &Archive, prefix: &str) -> Result<()> {
        for (kind, store) in [("m", &self.exp_avg), ("v", &self.exp_avg_sq)] {
            for (k, dst) in store {
                let src = archive.tensor(&format!("{prefix}{kind}/{k}")).context("optimizer state")?;
                anyhow::ensure!(src.size() == dst.size(), "optimizer state for '{k}' has the wrong shape");
                tch::no_grad(|| dst.shallow_clone().copy_(&src.to_device(dst.device())));
            }
        }
        self.steps = archive.meta(&format!("{prefix}steps"))?.parse().context("optimizer step count")?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn first_step_moves_by_lr_against_gradient_sign() {
        // With bias correction, the first Adam step is lr * g / (|g| + eps).
        let w = Tensor::from_slice(&[1.0f32, -2.0, 0.5]).set_requires_grad(true);
        let mut opt = Adam::new([("w".to_string(), w.shallow_clone())].into());
        let loss = (&w * Tensor::from_slice(&[3.0f32, -1.0, 0.0])).sum(Kind::Float);
        loss.backward();
        opt.step(0.1, None);
        let got: Vec<f32> = Vec::try_from(w.detach()).unwrap();
        assert!((got[0] - 0.9).abs() < 1e-6 && (got[1] + 1.9).abs() < 1e-6 && (got[2] - 0.5).abs() < 1e-6, "{got:?}");
    }

    #[test]
    fn minimises_a_quadratic_and_clips() {
        let w = Tensor::from_slice(&[5.0f32, -3.0]).set_requires_grad(true);
        let mut opt = Adam::new([("w".to_string(), w.shallow_clone())].into());
        for _ in 0..500 {
            opt.zero_grad();
            w.square().sum(Kind::Float).backward();
            opt.step(0.05, Some(1.0));
        }
        assert!(w.abs().max().double_value(&[]) < 0.05);
        assert_eq!(opt.steps, 500);
    }

    #[test]
    fn state_round_trip() {
        let w = Tensor::from_slice(&[1.0f32, 2.0]).set_requires_grad(true);
        let mut opt = Adam::new([("w".to_string(), w.shallow_clone())].into());
        w.square().sum(Kind::Float).backward();
        opt.step(0.01, None);
        let mut a = Archive::new();
        opt.save_into(&mut a, "opt/");
        let w2 = Tensor::zeros([2], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let mut opt2 = Adam::new([("w".to_string(), w2)].into());
        opt2.load_from(&a, "opt/").unwrap();
        assert_eq!(opt2.steps, 1);
        assert!(opt2.exp_avg["w"].equal(&opt.exp_avg["w"]));
        assert!(opt2.exp_avg_sq["w"].equal(&opt.exp_avg_sq["w"]));
    }
}
