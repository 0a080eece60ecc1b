//! `flashmat bench ...`: throughput measurements, printed with the ratio to a
//! baseline measured in the same run.

use crate::data::procedural;
use crate::data::samples::{make_batch, stack_maps, SampleConfig};
use crate::geometry::{config_tensors, pixel_center, sample_configs, Sampling};
use crate::svbrdf::cpu;
use crate::svbrdf::render::render;
use crate::svbrdf::scalar::{self, PixelMaterial};
use anyhow::Result;
use clap::{Args, Subcommand};
use rand::SeedableRng;
use rand_pcg::Pcg64;
use rayon::prelude::*;
use std::time::Instant;
use tch::Device;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Procedural generation and GGX rendering throughput at a resolution.
    Data(DataBenchArgs),
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
    }
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
                    let g = |im: &crate::image::Image, ch| im.get(ch, i, j) as f64;
                    let pm = PixelMaterial {
                        kd: [g(&m.diffuse, 0), g(&m.diffuse, 1), g(&m.diffuse, 2)],
                        ks: [g(&m.specular, 0), g(&m.specular, 1), g(&m.specular, 2)],
                        roughness: g(&m.roughness, 0),
                        normal: [g(&m.normal, 0), g(&m.normal, 1), g(&m.normal, 2)],
                    };
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
