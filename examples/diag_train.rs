//! Diagnostic: trains for a few steps and reports whether the renderer's
//! outputs collapse to the dead side of the final activation.
use flashmat::train::{batches::{batch_for_step, MaterialStream}, TrainConfig, Trainer, UpdateScheme};
use tch::{Device, Kind};
fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let (lr, wl, wa, steps, crop): (f64, f64, f64, u64, usize) = (a[1].parse()?, a[2].parse()?, a[3].parse()?, a[4].parse()?, a[5].parse()?);
    let scheme = if a.get(6).map(|s| s == "combined").unwrap_or(false) { UpdateScheme::Combined } else { UpdateScheme::Alternating };
    let warmup_steps: u64 = a.get(7).map(|s| s.parse()).transpose()?.unwrap_or(0);
    let adv_start: u64 = a.get(8).map(|s| s.parse()).transpose()?.unwrap_or(0);
    let cfg = TrainConfig { lr, weight_lpips: wl, weight_adv: wa, crop, outputs_per_material: 4, scheme, warmup_steps, adv_start, straight_through_output: a.get(9).map(|s| s == "st").unwrap_or(false), ..Default::default() };
    let stream = MaterialStream::open(&cfg)?;
    let mut t = Trainer::new(cfg.clone(), Device::Cpu)?;
    let probe = batch_for_step(&cfg, &stream.materials(&cfg, 1_000_000)?, 1_000_000, Device::Cpu)?;
    let t0 = std::time::Instant::now();
    for s in 0..steps {
        let b = batch_for_step(&cfg, &stream.materials(&cfg, s)?, s, Device::Cpu)?;
        let l = t.train_step(&b)?;
        if s % 10 == 0 || s + 1 == steps {
            let (frac, l1, zero) = tch::no_grad(|| -> anyhow::Result<(f64, f64, f64)> {
                let n = t.model.est.forward_t(&probe.est_input, false)?;
                let p = t.model.renderer.forward_maps(&n, &probe.out_wi, &probe.out_wo)?;
                let tl = flashmat::spaces::to_log(&probe.targets);
                Ok((p.gt(0.0).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]), (&p - &tl).abs().mean(Kind::Float).double_value(&[]), tl.abs().mean(Kind::Float).double_value(&[])))
            })?;
            println!("step {s}: train l1 {:.4} | probe: frac>0 {frac:.3} l1 {l1:.4} (zero predictor {zero:.4}) | {:.1}s", l.l1, t0.elapsed().as_secs_f64());
        }
    }
    Ok(())
}
