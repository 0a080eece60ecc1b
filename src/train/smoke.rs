//! The device smoke test a GPU job runs before spending its time on
//! training: the same networks, the same batches, a few steps on the CPU
//! and on the device, losses compared. It proves that libtorch sees the
//! device, that every kernel of a training step runs there, and that it
//! computes what the CPU computes.

use super::batches::{batch_for_step, MaterialStream};
use super::{StepLosses, TrainConfig, Trainer};
use crate::data::samples::{ShiftedPhotos, TrainingBatch};
use anyhow::Result;
use std::time::Instant;
use tch::Device;

/// Largest accepted relative difference of a loss term between the CPU and
/// the device. cuDNN convolutions run in TF32 by default (10-bit
/// mantissa), which moves the losses by about 1e-3; a wrong kernel, a
/// dropped term or garbage memory moves them by far more.
pub const SMOKE_TOLERANCE: f64 = 2e-2;

/// Per-step losses on both devices and the verdict.
#[derive(Debug)]
pub struct SmokeReport {
    pub cpu: Vec<StepLosses>,
    pub device: Vec<StepLosses>,
    /// Largest relative difference over the steps and loss terms, with the term's name.
    pub worst: (f64, String),
    /// Seconds of the device's last step (after a warm-up step).
    pub device_step_seconds: f64,
    pub cpu_step_seconds: f64,
}

impl SmokeReport {
    pub fn passed(&self) -> bool {
        self.worst.0 <= SMOKE_TOLERANCE
    }
}

/// The batch on another device (renders made once, on the CPU, so both
/// sides see the same numbers).
fn batch_to(b: &TrainingBatch, device: Device) -> TrainingBatch {
    TrainingBatch {
        maps: b.maps.to_device(device),
        input_linear: b.input_linear.to_device(device),
        est_input: b.est_input.to_device(device),
        out_wi: b.out_wi.to_device(device),
        out_wo: b.out_wo.to_device(device),
        targets: b.targets.to_device(device),
        configs: b.configs.clone(),
        shifted: b.shifted.as_ref().map(|s| ShiftedPhotos { est_input: s.est_input.to_device(device), offsets: s.offsets.clone() }),
    }
}

/// Relative difference of two loss values (absolute below 1e-3).
fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(1e-3)
}

/// Trains `steps` steps of `cfg` on the CPU and on `device` from the same
/// weights (initialised on the CPU: the devices' random generators differ)
/// and the same batches, and compares every loss term.
pub fn compare_devices(cfg: &TrainConfig, device: Device, steps: usize) -> Result<SmokeReport> {
    anyhow::ensure!(steps >= 1, "the smoke test needs at least one step");
    let mut on_cpu = Trainer::new(cfg.clone(), Device::Cpu)?;
    let mut on_device = Trainer::new(cfg.clone(), device)?;
    for (from, to) in [(&on_cpu.model.est_vs, &on_device.model.est_vs), (&on_cpu.model.renderer_vs, &on_device.model.renderer_vs), (&on_cpu.disc_vs, &on_device.disc_vs)] {
        let mut to = to.variables();
        for (name, value) in from.variables() {
            let target = to.get_mut(&name).ok_or_else(|| anyhow::anyhow!("variable {name} missing on {device:?}"))?;
            tch::no_grad(|| target.copy_(&value));
        }
    }
    let stream = MaterialStream::open(cfg)?;
    let mut report = SmokeReport { cpu: vec![], device: vec![], worst: (0.0, String::new()), device_step_seconds: 0.0, cpu_step_seconds: 0.0 };
    for step in 0..steps as u64 {
        let batch = batch_for_step(cfg, &stream.materials(cfg, step)?, step, Device::Cpu)?;
        let t = Instant::now();
        report.cpu.push(on_cpu.train_step(&batch)?);
        report.cpu_step_seconds = t.elapsed().as_secs_f64();
        let batch = batch_to(&batch, device);
        let t = Instant::now();
        report.device.push(on_device.train_step(&batch)?);
        if let Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
        report.device_step_seconds = t.elapsed().as_secs_f64();
    }
    for (a, b) in report.cpu.iter().zip(&report.device) {
        let terms = [("L1", a.l1, b.l1), ("LPIPS", a.lpips, b.lpips), ("adversarial", a.adv, b.adv), ("renderer L1", a.l1_render, b.l1_render), ("discriminator", a.loss_disc, b.loss_disc)];
        for (name, x, y) in terms {
            let r = if x.is_finite() && y.is_finite() && !a.skipped && !b.skipped { relative(x, y) } else { f64::INFINITY };
            if r > report.worst.0 || report.worst.1.is_empty() {
                report.worst = (r, format!("{name} at step {} ({x:.6} on the CPU, {y:.6} on the device)", a.step));
            }
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_against_cpu_matches_and_a_changed_term_is_caught() {
        let cfg = TrainConfig { model: crate::model::ModelConfig::tiny(), material_size: 64, crop: 32, outputs_per_material: 2, ..Default::default() };
        let r = compare_devices(&cfg, Device::Cpu, 2).unwrap();
        assert_eq!((r.cpu.len(), r.device.len()), (2, 2));
        // Same device, same weights, same batches: equal up to thread-order rounding.
        assert!(r.worst.0 < 1e-4, "{:?}", r.worst);
        assert!(r.passed());
        assert!(relative(1.0, 1.0 + 2.0 * SMOKE_TOLERANCE) > SMOKE_TOLERANCE);
        assert_eq!(relative(0.0, 1e-6), 1e-3);
    }
}
