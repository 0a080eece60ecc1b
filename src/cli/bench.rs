//! `flashmat bench ...`: throughput measurements, printed with the ratio to a
//! baseline measured in the same run.

use flashmat::data::procedural;
use flashmat::data::samples::{make_batch, stack_maps, SampleConfig};
use flashmat::geometry::{config_tensors, pixel_center, sample_configs, Sampling};
use flashmat::svbrdf::cpu;
use flashmat::svbrdf::render::render;
use flashmat::svbrdf::scalar;
use anyhow::Result;
use clap::{Args, Subcommand};
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rayon::prelude::*;
use std::time::Instant;
use tch::{Device, Tensor};

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Procedural generation and GGX rendering throughput at a resolution.
    Data(DataBenchArgs),
    /// Milliseconds per training step (alternating and combined schemes) and peak memory.
    Train(TrainBenchArgs),
    /// M_est forward for one photo and ND_enc + M_render for one frame (inference mode).
    Infer(InferBenchArgs),
    /// Device smoke test: a few training steps on the CPU and on --device from the same weights and batches;
    /// fails (exit 1, one line) when a loss term differs by more than 2%.
    Smoke(SmokeArgs),
    /// Milliseconds per step of the refinement on the photo (`--refine`), against one identity render of the same material.
    Refine(RefineBenchArgs),
}

#[derive(Args, Debug)]
pub struct RefineBenchArgs {
    /// Model preset (paper, compact, tiny); randomly initialised weights (the cost does not depend on them).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Photo resolution.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Timed refinement steps.
    #[arg(long, default_value_t = 20)]
    pub steps: usize,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

#[derive(Args, Debug)]
pub struct SmokeArgs {
    /// Model preset (paper, compact, tiny).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Training crop size.
    #[arg(long, default_value_t = 64)]
    pub crop: usize,
    /// Steps compared (the second and later run after an optimizer update).
    #[arg(long, default_value_t = 2)]
    pub steps: usize,
    /// The device to prove: cuda, cuda:N (cpu compares the CPU with itself).
    #[arg(long, default_value = "cuda")]
    pub device: String,
}

#[derive(Args, Debug)]
pub struct TrainBenchArgs {
    /// Model preset (paper, compact, tiny).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Training crop size.
    #[arg(long, default_value_t = 128)]
    pub crop: usize,
    /// Output renders per material.
    #[arg(long, default_value_t = 8)]
    pub outputs: usize,
    /// Timed steps per scheme (after one warm-up step).
    #[arg(long, default_value_t = 3)]
    pub steps: usize,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

#[derive(Args, Debug)]
pub struct InferBenchArgs {
    /// Model preset (paper, compact, tiny).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Photo / frame resolution.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Timed runs (median reported).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

#[derive(Args, Debug)]
pub struct DataBenchArgs {
    /// Resolution in pixels.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Materials per measurement.
    #[arg(long, default_value_t = 32)]
    pub materials: usize,
}

pub fn run(cmd: &BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Data(a) => bench_data(a),
        BenchCommand::Train(a) => bench_train(a),
        BenchCommand::Smoke(a) => smoke(a),
        BenchCommand::Refine(a) => bench_refine(a),
        BenchCommand::Infer(a) => {
            let device = flashmat::device::parse_device(&a.device)?;
            let t = flashmat::model::bench_infer_runs(&flashmat::model::ModelConfig::preset(&a.preset)?, a.size, device, a.runs)?;
            println!("{t}");
            println!("paper reference: the authors' PyTorch M_est takes about 20 s at 256x256 (paper preset) on a 2-core CPU");
            Ok(())
        }
    }
}

/// Refinement cost: ms per step (M_render forward + backward to the map,
/// priors, Adam) against one identity render (ND_enc + M_render forward,
/// no autograd) of the same material, measured in the same run.
fn bench_refine(args: &RefineBenchArgs) -> Result<()> {
    use flashmat::infer::refine::{refine, RefineConfig};
    use flashmat::infer::{NeuralMaterial, PreparedPhoto};
    let device = flashmat::device::parse_device(&args.device)?;
    flashmat::infer::photo::check_size(args.size)?;
    anyhow::ensure!(args.steps > 0, "--steps must be at least 1");
    tch::manual_seed(0);
    let config = flashmat::model::ModelConfig::preset(&args.preset)?;
    let model = flashmat::model::Model::new(&config, device)?;
    let material = procedural::test_material(0, args.size);
    let linear = flashmat::svbrdf::render::render_material(&material, &[NeuralMaterial::identity_config()])?.remove(0);
    let photo = PreparedPhoto::at_model_view(linear.clone(), true, "bench");
    let info = flashmat::model::ModelInfo { ldr_input: true, steps: 0 };
    let neural = flashmat::infer::estimate(&model, &info, &photo)?;
    let render_ms = median_ms(device, 3, || neural.render(&[NeuralMaterial::identity_config()]).map(|_| ()))?;
    let photo_t = linear.to_tensor().clamp(0.0, 1.0);
    let default_steps = flashmat::infer::refine::DEFAULT_REFINE_STEPS;
    // The default settings, then the same without the relight prior (its cost, in the same run).
    for (what, cfg) in [("default", RefineConfig::with_steps(args.steps)), ("no relight prior", RefineConfig { relight_weight: 0.0, ..RefineConfig::with_steps(args.steps) })] {
        let mut copy = neural.duplicate()?;
        let report = refine(&mut copy, &photo_t, true, &cfg, |_| {})?;
        let step_ms = report.seconds * 1000.0 / args.steps as f64;
        println!(
            "refine ({what}) {} {}x{} on {:?}: {step_ms:.1} ms/step ({:.2}x one identity render of {render_ms:.1} ms); {default_steps} steps: {:.1} s",
            args.preset,
            args.size,
            args.size,
            device,
            step_ms / render_ms,
            step_ms * default_steps as f64 / 1000.0
        );
    }
    Ok(())
}

/// Peak resident memory of this process (VmHWM), in GiB.
pub fn peak_memory_gib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / (1024.0 * 1024.0))
}

fn smoke(args: &SmokeArgs) -> Result<()> {
    use flashmat::train::smoke::{compare_devices, SMOKE_TOLERANCE};
    println!(
        "libtorch: CUDA available {}, {} CUDA device(s), cuDNN {}",
        tch::Cuda::is_available(),
        tch::Cuda::device_count(),
        tch::Cuda::cudnn_is_available()
    );
    let device = flashmat::device::parse_device(&args.device)?;
    let model = flashmat::model::ModelConfig::preset(&args.preset)?;
    let cfg = flashmat::train::TrainConfig { model, crop: args.crop, material_size: args.crop.max(256), outputs_per_material: 4, ..Default::default() };
    let r = compare_devices(&cfg, device, args.steps)?;
    for (a, b) in r.cpu.iter().zip(&r.device) {
        println!(
            "step {}: L1 {:.6} / {:.6}  LPIPS {:.6} / {:.6}  renderer L1 {:.6} / {:.6}  discriminator {:.6} / {:.6}  (CPU / {device:?})",
            a.step, a.l1, b.l1, a.lpips, b.lpips, a.l1_render, b.l1_render, a.loss_disc, b.loss_disc
        );
    }
    println!("step time: {:.3} s on the CPU, {:.3} s on {device:?} ({:.1}x)", r.cpu_step_seconds, r.device_step_seconds, r.cpu_step_seconds / r.device_step_seconds.max(1e-9));
    if !r.passed() {
        anyhow::bail!("smoke test failed on {device:?}: {} differs by {:.2e} relative (tolerance {SMOKE_TOLERANCE})", r.worst.1, r.worst.0);
    }
    println!("smoke test passed on {device:?}: largest difference {:.2e} relative ({}), tolerance {SMOKE_TOLERANCE}", r.worst.0, r.worst.1);
    Ok(())
}

fn bench_train(args: &TrainBenchArgs) -> Result<()> {
    use flashmat::train::{batches::batch_for_step, TrainConfig, Trainer, UpdateScheme};
    let device = flashmat::device::parse_device(&args.device)?;
    let model = flashmat::model::ModelConfig::preset(&args.preset)?;
    println!("flashmat bench train: {} preset, crop {}, 2 materials x (1 + {}) renders, {device:?}, {} torch threads", args.preset, args.crop, args.outputs, tch::get_num_threads());
    // The OpenMP wait is fixed for the whole process and changes every
    // variant's time (reports/training-speed.md): say which one ran.
    let env_or = |name: &str| std::env::var(name).unwrap_or_else(|_| "unset".into());
    println!("OpenMP wait: OMP_WAIT_POLICY={}, GOMP_SPINCOUNT={} (compare settings process against process)", env_or("OMP_WAIT_POLICY"), env_or("GOMP_SPINCOUNT"));
    // Three trainers on the same batches, one step each in turn (so load
    // changes hit all three alike); the median step of each.
    let variants = [
        ("alternating, the previous step (reference)", UpdateScheme::Alternating, true),
        ("alternating (one shared forward, fused Adam)", UpdateScheme::Alternating, false),
        ("combined (one update)", UpdateScheme::Combined, false),
    ];
    let base = TrainConfig { model: model.clone(), crop: args.crop, material_size: args.crop.max(256), outputs_per_material: args.outputs, ..Default::default() };
    let stream = flashmat::train::batches::MaterialStream::open(&base)?;
    let batches: Vec<_> = (0..=args.steps as u64).map(|s| batch_for_step(&base, &stream.materials(&base, s)?, s, device)).collect::<Result<_>>()?;
    let step = |t: &mut Trainer, b, reference: bool| if reference { flashmat::reference_paths::with(|| t.train_step(b)) } else { t.train_step(b) };
    let mut trainers = vec![];
    for (_, scheme, reference) in &variants {
        let mut trainer = Trainer::new(TrainConfig { scheme: *scheme, ..base.clone() }, device)?;
        if *reference {
            trainer.use_reference_step();
        }
        step(&mut trainer, &batches[0], *reference)?; // warm-up
        trainers.push(trainer);
    }
    let mut times = vec![vec![]; variants.len()];
    for b in &batches[1..] {
        for ((trainer, t), (_, _, reference)) in trainers.iter_mut().zip(&mut times).zip(&variants) {
            let start = Instant::now();
            step(trainer, b, *reference)?;
            if let Device::Cuda(i) = device {
                tch::Cuda::synchronize(i as i64);
            }
            t.push(start.elapsed().as_secs_f64() * 1000.0);
        }
    }
    let median = |t: &mut Vec<f64>| {
        t.sort_by(f64::total_cmp);
        t[t.len() / 2]
    };
    let ms: Vec<f64> = times.iter_mut().map(median).collect();
    for ((name, _, _), t) in variants.iter().zip(&ms) {
        println!("{name:<58} {t:9.1} ms/step (median of {})  {:.2}x the reference's steps per second", args.steps, ms[0] / t);
    }
    step_breakdown(args, &model, device)?;
    if let Some(gib) = peak_memory_gib() {
        println!("peak resident memory: {gib:.2} GiB");
    }
    Ok(())
}

/// Median milliseconds of `f` over `runs` calls, after one warm-up call.
fn median_ms(device: Device, runs: usize, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    let mut times = Vec::with_capacity(runs);
    for _ in 0..runs.max(1) {
        let t = Instant::now();
        f()?;
        if let Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
        times.push(t.elapsed().as_secs_f64() * 1000.0);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[times.len() / 2])
}

/// Where one alternating step's time goes: each part run on its own
/// (forward + backward where the step has both) with its analytic FLOPs
/// and the GFLOP/s it reaches against this machine's fp32 matmul rate,
/// measured in the same run.
fn step_breakdown(args: &TrainBenchArgs, model: &flashmat::model::ModelConfig, device: Device) -> Result<()> {
    use flashmat::train::{batches::batch_for_step, losses, TrainConfig, Trainer};
    use tch::Kind;
    let cfg = TrainConfig { model: model.clone(), crop: args.crop, material_size: args.crop.max(256), outputs_per_material: args.outputs, ..Default::default() };
    let runs = args.steps.max(1);
    let opts = (Kind::Float, device);
    let n = 1024;
    let (a, b) = (Tensor::randn([n, n], opts), Tensor::randn([n, n], opts));
    let peak_ms = median_ms(device, 5, || {
        let _ = a.matmul(&b);
        Ok(())
    })?;
    let peak = 2.0 * (n as f64).powi(3) / (peak_ms * 1e6);
    println!("\nstep breakdown (alternating scheme; parts timed on their own, median of {runs}); fp32 1024x1024 matmul: {peak:.1} GFLOP/s");

    let trainer = Trainer::new(cfg.clone(), device)?;
    let stream = flashmat::train::batches::MaterialStream::open(&cfg)?;
    let mut rows: Vec<(&str, f64, f64)> = vec![];
    let mut materials = stream.materials(&cfg, 0)?;
    rows.push(("data: procedural materials + crops", median_ms(device, runs, || {
        materials = stream.materials(&cfg, 1)?;
        Ok(())
    })?, 0.0));
    let mut batch = batch_for_step(&cfg, &materials, 0, device)?;
    rows.push(("data: GGX renders (1 input + K outputs)", median_ms(device, runs, || {
        batch = batch_for_step(&cfg, &materials, 1, device)?;
        Ok(())
    })?, 0.0));
    let (nb, k) = (cfg.materials_per_batch as f64, cfg.outputs_per_material as f64);
    let px = (args.crop * args.crop) as f64;
    let est_flops = 3.0 * nb * flashmat::model::est_flops(model, args.crop as i64, args.crop as i64);
    rows.push(("M_est forward + backward", median_ms(device, runs, || {
        trainer.model.est.forward_t(&batch.est_input, true)?.square().mean(Kind::Float).backward();
        Ok(())
    })?, est_flops));
    let neural = tch::no_grad(|| trainer.model.est.forward_t(&batch.est_input, false))?;
    let render_flops = 3.0 * nb * k * px * flashmat::model::renderer_flops_per_row(model);
    let mut pred = Tensor::zeros([1], opts);
    rows.push(("ND_enc + M_render forward + backward", median_ms(device, runs, || {
        let leaf = neural.detach().set_requires_grad(true);
        pred = trainer.model.renderer.forward_maps(&leaf, &batch.out_wi, &batch.out_wo)?;
        pred.mean(Kind::Float).backward();
        Ok(())
    })?, render_flops));
    let target_log = flashmat::spaces::to_log(&batch.targets);
    let photo_log = batch.est_input.narrow(1, 0, 3);
    let pred = pred.detach();
    rows.push(("LPIPS forward + backward", median_ms(device, runs, || {
        losses::perceptual(trainer.lpips.as_ref(), &pred.set_requires_grad(true), &target_log)?.backward();
        Ok(())
    })?, 0.0));
    rows.push(("discriminator: generator term + its 3-pair loss, forward + backward", median_ms(device, runs, || {
        losses::adversarial(&trainer.disc, &pred.set_requires_grad(true), &photo_log, cfg.weight_adv)?.backward();
        losses::discriminator_loss(&trainer.disc, &pred, &target_log, &photo_log, cfg.weight_adv)?.backward();
        Ok(())
    })?, 0.0));
    let mut t = Trainer::new(cfg.clone(), device)?;
    rows.push(("whole train_step (both halves, optimizers)", median_ms(device, runs, || t.train_step(&batch).map(|_| ()))?, 0.0));
    println!("{:<66} {:>10} {:>12} {:>10}", "part", "ms", "GFLOP", "GFLOP/s");
    for (name, ms, flops) in &rows {
        if *flops > 0.0 {
            println!("{name:<66} {ms:>10.1} {:>12.2} {:>10.1} ({:.0}% of the matmul rate)", flops / 1e9, flops / (ms * 1e6), 100.0 * flops / (ms * 1e6) / peak);
        } else {
            println!("{name:<66} {ms:>10.1} {:>12} {:>10}", "-", "-");
        }
    }
    Ok(())
}

fn bench_data(args: &DataBenchArgs) -> Result<()> {
    let size = args.size;
    let n = args.materials.max(2);
    println!("flashmat bench data: {size}x{size}, {} threads (rayon), {} torch threads", rayon::current_num_threads(), tch::get_num_threads());
    let seeds: Vec<u64> = (0..n as u64).map(procedural::training_seed).collect();

    // Warm-up, then generation alone.
    let _ = procedural::generate_many(&seeds[..2], size);
    let t = Instant::now();
    let materials = procedural::generate_many(&seeds, size);
    let gen_rate = n as f64 / t.elapsed().as_secs_f64();
    println!("procedural generation : {gen_rate:8.1} materials/s");

    // Renderers, 1 + 8 configurations per material as in training.
    let sample_cfg = SampleConfig::default();
    let k = 1 + sample_cfg.outputs_per_material;
    let mut rng = Pcg64::seed_from_u64(0);
    let configs = sample_configs(&mut rng, Sampling::Reflect, k, 28.0);
    let _ = cpu::render(&materials[0], &configs);
    let t = Instant::now();
    for m in &materials {
        let _ = cpu::render(m, &configs);
    }
    let cpu_rate = (n * k) as f64 / t.elapsed().as_secs_f64();

    let maps = stack_maps(&materials[..2], Device::Cpu)?;
    let (lights, views) = config_tensors(&configs, Device::Cpu);
    let (lights, views) = (lights.view([1, k as i64, 3]).repeat([2, 1, 1]), views.view([1, k as i64, 3]).repeat([2, 1, 1]));
    let _ = tch::no_grad(|| render(&maps, &lights, &views));
    let reps = (n / 2).max(1);
    let t = Instant::now();
    for _ in 0..reps {
        let _ = tch::no_grad(|| render(&maps, &lights, &views));
    }
    let tensor_rate = (reps * 2 * k) as f64 / t.elapsed().as_secs_f64();

    // Baseline: the scalar f64 oracle, parallel over rows.
    let m = &materials[0];
    let t = Instant::now();
    for c in &configs {
        let _: Vec<f64> = (0..size)
            .into_par_iter()
            .map(|i| {
                let mut acc = 0.0;
                for j in 0..size {
                    let pm = m.pixel_material(i, j);
                    acc += scalar::radiance_at(&pm, pixel_center(i, j, size, size), c.light, c.view)[0];
                }
                acc
            })
            .collect();
    }
    let scalar_rate = k as f64 / t.elapsed().as_secs_f64();
    println!("GGX scalar f64 oracle : {scalar_rate:8.1} renders/s (baseline)");
    println!("GGX f32 CPU renderer  : {cpu_rate:8.1} renders/s ({:.2}x baseline)", cpu_rate / scalar_rate);
    println!("GGX tensor renderer   : {tensor_rate:8.1} renders/s on CPU ({:.2}x baseline; the CUDA path)", tensor_rate / scalar_rate);

    // The whole feed as training runs it: generate, crop-free batch of 2, render 1 + 8 each.
    let t = Instant::now();
    let mut fed = 0usize;
    for (i, pair) in seeds.chunks_exact(2).enumerate() {
        let mats = procedural::generate_many(pair, size);
        let _ = tch::no_grad(|| make_batch(&mats, &sample_cfg, &mut Pcg64::seed_from_u64(i as u64), Device::Cpu))?;
        fed += 2;
    }
    let feed = fed as f64 / t.elapsed().as_secs_f64();
    println!(
        "training feed         : {feed:8.1} materials/s generated + rendered (1 + {} renders each; {:.2}x the 20 materials/s target)",
        sample_cfg.outputs_per_material,
        feed / 20.0
    );
    Ok(())
}
