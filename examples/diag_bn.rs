use flashmat::train::{batches, Trainer};
use tch::{Device, Kind};
fn main() -> anyhow::Result<()> {
    let ckpt = std::path::PathBuf::from(std::env::args().nth(1).unwrap());
    let trainer = Trainer::resume(&ckpt, Device::Cpu, None)?;
    let cfg = trainer.config.clone();
    let mats: Vec<_> = (0..2u64).map(|i| flashmat::data::procedural::generate(flashmat::data::procedural::training_seed(i), &flashmat::data::procedural::ProceduralConfig::with_size(256))).collect();
    let mats: Vec<_> = mats.iter().map(|m| m.crop(80, 80, 96, 96).unwrap()).collect();
    let b = batches::batch_for_step(&cfg, &mats, 5, Device::Cpu)?;
    tch::no_grad(|| -> anyhow::Result<()> {
        let tl = flashmat::spaces::to_log(&b.targets);
        for train in [true, false] {
            let n = trainer.model.est.forward_t(&b.est_input, train)?;
            let p = trainer.model.renderer.forward_maps(&n, &b.out_wi, &b.out_wo)?;
            println!("pred min {:.5} max {:.5} frac>0 {:.4}", p.min().double_value(&[]), p.max().double_value(&[]), p.gt(0.0).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]));
            println!("train={train}: neural mean {:.4} std {:.4}; pred log mean {:.4}; target log mean {:.4}; L1 {:.4}", n.mean(Kind::Float).double_value(&[]), n.std(true).double_value(&[]), p.mean(Kind::Float).double_value(&[]), tl.mean(Kind::Float).double_value(&[]), (&p - &tl).abs().mean(Kind::Float).double_value(&[]));
        }
        Ok(())
    })?;
    for (name, t) in trainer.model.renderer_vs.variables() { println!("{name}: {:?} norm {:.4} mean {:.5}", t.size(), t.norm().double_value(&[]), t.mean(Kind::Float).double_value(&[])); }
    for (name, t) in trainer.model.est_vs.variables() {
        if name.contains("running") && (name.contains("head") || name.contains("dec") && name.ends_with("0.bn.running_var")) { println!("{name}: mean {:.4}", t.mean(Kind::Float).double_value(&[])); }
    }
    Ok(())
}
