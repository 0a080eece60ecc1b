//! `flashmat bench ...`: throughput measurements, printed with the ratio to a
//! baseline measured in the same run.

use crate::data::procedural::{self, ProceduralConfig};
use crate::data::samples::{make_batch, SampleConfig};
use crate::geometry::{pixel_center, sample_configs, Sampling};
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
    let cfg = ProceduralConfig { size, ..Default::default() };

    // Warm-up, then generation alone.
    let _ = procedural::generate_many(&seeds[..2], size);
    let t = Instant::now();
    let materials = procedural::generate_many(&seeds, size);
    let gen_rate = n as f64 / t.elapsed().as_secs_f64();
    let _ = cfg;
    println!("procedural generation : {gen_rate:8.1} materials/s");

    // Tensor renderer: 2 materials x (1 + 8) renders per batch, like training.
    let sample_cfg = SampleConfig::default();
    let mut rng = Pcg64::seed_from_u64(0);
    let _ = make_batch(&materials[..2], &sample_cfg, &mut rng, Device::Cpu)?;
    let t = Instant::now();
    let mut renders = 0usize;
    for pair in materials.chunks_exact(2) {
        let _ = tch::no_grad(|| make_batch(pair, &sample_cfg, &mut rng, Device::Cpu))?;
        renders += 2 * (1 + sample_cfg.outputs_per_material);
    }
    let render_rate = renders as f64 / t.elapsed().as_secs_f64();
    println!("GGX tensor renders    : {render_rate:8.1} renders/s");

    // Baseline: the scalar f64 oracle, parallel over rows.
    let m = &materials[0];
    let configs = sample_configs(&mut rng, Sampling::Reflect, 2, 28.0);
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
    let scalar_rate = configs.len() as f64 / t.elapsed().as_secs_f64();
    println!("GGX scalar oracle     : {scalar_rate:8.1} renders/s (baseline; tensor renderer is {:.1}x)", render_rate / scalar_rate);

    // The two together, as the training loop consumes them.
    let per_material = 1.0 / gen_rate + (1 + sample_cfg.outputs_per_material) as f64 / render_rate;
    let combined = 1.0 / per_material;
    println!(
        "training feed         : {combined:8.1} materials/s with 1 + {} renders each ({:.2}x the 20 materials/s target)",
        sample_cfg.outputs_per_material,
        combined / 20.0
    );
    Ok(())
}
