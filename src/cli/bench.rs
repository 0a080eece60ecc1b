//! `flashmat bench ...`: throughput measurements, printed with the ratio to a
//! baseline measured in the same run.

use flashmat::data::procedural;
use flashmat::device::device_name;
use flashmat::data::samples::{make_batch, stack_maps, SampleConfig};
use flashmat::geometry::{config_tensors, pixel_center, sample_configs, Sampling};
use flashmat::svbrdf::cpu;
use flashmat::svbrdf::render::render;
use flashmat::svbrdf::scalar;
use crate::cli::reference_bench::{find, markdown, BusySampler, ReferenceBench, Row};
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
    /// Seconds of `estimate --capture` (start, fit, neural material) on a synthetic capture, against the single-photo
    /// estimate of its overhead photo in the same run.
    Capture(CaptureBenchArgs),
    /// Seconds of `flashmat capture` on synthetic phone photos of the printed frame (JPEG): the tag detection and
    /// pose of one photo against its decode, and the whole capture folder.
    Frame(FrameBenchArgs),
}

#[derive(Args, Debug)]
pub struct FrameBenchArgs {
    /// Photos in the capture.
    #[arg(long, default_value_t = 9)]
    pub photos: usize,
    /// Megapixels of each photo (4:3).
    #[arg(long, default_value_t = 12.0)]
    pub megapixels: f64,
}

#[derive(Args, Debug)]
pub struct CaptureBenchArgs {
    /// Side of the photos and fitted maps.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Photos in the capture (overhead first, then tilted ones with the highlight on the sample).
    #[arg(long, default_value_t = 3)]
    pub photos: usize,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
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

/// The authors' step beside flashmat's (`--reference`), and where the
/// table goes.
#[derive(Args, Debug, Clone)]
pub struct SideBySideArgs {
    /// A copy of the authors' repository (APeculiarCamber/neural_appearance_estimation), kept outside
    /// this one: their step is timed in the same job with the same shapes (../shared/bench/README.md).
    #[arg(long, value_name = "DIR")]
    pub reference: Option<std::path::PathBuf>,
    /// The timing script (default: ../shared/bench/ref_bench.py beside the checkout, .gpu/bench/ref_bench.py, or FLASHMAT_REF_BENCH).
    #[arg(long, value_name = "FILE")]
    pub ref_bench: Option<std::path::PathBuf>,
    /// Also time the authors' code under bf16 autocast.
    #[arg(long)]
    pub amp: bool,
    /// Write the side-by-side table (Markdown) to this file too.
    #[arg(long, value_name = "FILE")]
    pub report: Option<std::path::PathBuf>,
    /// What flashmat's networks compute in (f32, tf32, bf16), as `train --precision`.
    #[arg(long, default_value = "tf32")]
    pub precision: flashmat::precision::Precision,
}

#[derive(Args, Debug)]
pub struct TrainBenchArgs {
    /// Model preset (paper, compact, tiny).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Training crop size.
    #[arg(long, default_value_t = 128)]
    pub crop: usize,
    /// Materials per batch.
    #[arg(long, default_value_t = 2)]
    pub batch: usize,
    /// Output renders per material.
    #[arg(long, default_value_t = 8)]
    pub outputs: usize,
    /// Timed steps per scheme (after one warm-up step).
    #[arg(long, default_value_t = 3)]
    pub steps: usize,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    #[command(flatten)]
    pub side: SideBySideArgs,
}

#[derive(Args, Debug)]
pub struct InferBenchArgs {
    /// Model preset (paper, compact, tiny).
    #[arg(long, default_value = "compact")]
    pub preset: String,
    /// Photo / frame resolutions, comma-separated (256,1024,2048).
    #[arg(long, default_value = "256", value_delimiter = ',')]
    pub size: Vec<usize>,
    /// Timed runs (median reported).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// cpu or cuda.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Memory budget of M_est, as for `estimate`: a photo whose whole forward does not fit runs layer by layer in tiles.
    #[arg(long, default_value = "8G")]
    pub max_memory: String,
    #[command(flatten)]
    pub side: SideBySideArgs,
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
        BenchCommand::Capture(a) => bench_capture(a),
        BenchCommand::Frame(a) => bench_frame(a),
        BenchCommand::Infer(a) => bench_infer(a),
    }
}

/// The authors' benchmark of `side`, when asked for.
fn reference_of(side: &SideBySideArgs) -> Result<Option<ReferenceBench>> {
    side.reference.as_deref().map(|repo| ReferenceBench::new(repo, side.ref_bench.as_deref())).transpose()
}

/// The authors' JSON lines; when their script fails (its own out of
/// memory, say: their words would read as flashmat's), a warning and
/// none, so the table still has flashmat's numbers ("not measured").
fn reference_lines(r: &ReferenceBench, args: &[String]) -> Vec<serde_json::Value> {
    r.run(args).unwrap_or_else(|e| {
        eprintln!("warning: {e}; the table has flashmat's numbers only");
        vec![]
    })
}

/// Prints the side-by-side table and writes it to `--report`.
fn finish_table(side: &SideBySideArgs, title: &str, rows: &[Row]) -> Result<()> {
    let md = markdown(title, rows);
    println!("\n{md}");
    if let Some(path) = &side.report {
        flashmat::io::atomic_write_bytes(path, md.as_bytes())?;
        println!("side-by-side table written to {}", path.display());
    }
    Ok(())
}

/// The authors' median milliseconds and rate of a measurement, or why
/// there is none (their out-of-memory, say), from its JSON line.
fn theirs(line: Option<&serde_json::Value>, rate: &str) -> (Option<f64>, Option<f64>, Option<String>) {
    match line {
        Some(l) if l["error"].is_string() => (None, None, l["error"].as_str().map(|e| e.chars().take(120).collect())),
        Some(l) => (l["ms_median"].as_f64(), l[rate].as_f64(), None),
        None => (None, None, Some("not measured".into())),
    }
}

fn bench_infer(a: &InferBenchArgs) -> Result<()> {
    let device = flashmat::device::parse_device(&a.device)?;
    let cfg = flashmat::model::ModelConfig::preset(&a.preset)?;
    let max_memory = flashmat::infer::tiles::parse_memory(&a.max_memory)?;
    let reference = reference_of(&a.side)?;
    flashmat::precision::set(a.side.precision)?;
    let mut rows = vec![];
    for &size in &a.size {
        flashmat::infer::photo::check_size(size)?;
        let tile_core = match flashmat::infer::plan_estimate(&cfg, size, size, max_memory)? {
            flashmat::infer::tiles::EstPlan::Whole => None,
            flashmat::infer::tiles::EstPlan::Tiled(core) => Some(core),
        };
        let sampler = device_index(device).and_then(BusySampler::start);
        let t = flashmat::model::bench_infer_runs(&cfg, size, device, a.runs, tile_core)?;
        let busy = sampler.and_then(BusySampler::finish);
        println!("{t}");
        if let Some(gib) = peak_device_memory_gib(device) {
            println!("  GPU memory in use on the card: {gib:.2} GiB (the caching allocator keeps its peak; --max-memory {})", a.max_memory);
        }
        let how = tile_core.map_or(String::new(), |c| format!(", tiles of {c}"));
        rows.push(Row { what: format!("M_est forward, {}, {size}x{size}{how}", a.preset), ours_ms: Some(t.est_s * 1e3), theirs_ms: None, ours_rate: Some(1.0 / t.est_s), theirs_rate: None, busy, tflops: Some(t.est_gflop / t.est_s / 1e3) });
        rows.push(Row { what: format!("relit frame, {}, {size}x{size}", a.preset), ours_ms: Some(t.render_s * 1e3), theirs_ms: None, ours_rate: Some(1.0 / t.render_s), theirs_rate: None, busy: None, tflops: Some(t.render_gflop / t.render_s / 1e3) });
    }
    if let Some(r) = &reference {
        let sizes = a.size.iter().map(usize::to_string).collect::<Vec<_>>().join(",");
        let mut args = vec!["--device".into(), device_name(device), "--infer".into(), "--size".into(), sizes, "--steps".into(), a.runs.to_string(), "--warmup".into(), "1".into()];
        if a.side.amp {
            args.push("--amp".into());
        }
        let lines = reference_lines(r, &args);
        let mut extra = vec![];
        for (i, &size) in a.size.iter().enumerate() {
            for (j, what) in ["ref_mest_forward", "ref_render_frame"].into_iter().enumerate() {
                let (ms, rate, why) = theirs(find(&lines, what, &[("size", size.into())]), "per_s");
                let row = &mut rows[2 * i + j];
                (row.theirs_ms, row.theirs_rate) = (ms, rate);
                if let Some(why) = why {
                    row.what += &format!(" (authors': {why})");
                }
                if a.side.amp {
                    let (ms, rate, why) = theirs(find(&lines, &format!("{what}_amp_bf16"), &[("size", size.into())]), "per_s");
                    let what = format!("{} — authors' under bf16 autocast{}", row.what, why.map_or(String::new(), |w| format!(" ({w})")));
                    extra.push(Row { what, ours_ms: row.ours_ms, theirs_ms: ms, ours_rate: row.ours_rate, theirs_rate: rate, busy: None, tflops: None });
                }
            }
        }
        rows.extend(extra);
    } else if device == Device::Cpu {
        println!("paper reference: the authors' PyTorch M_est takes about 20 s at 256x256 (paper preset) on a 2-core CPU");
    }
    finish_table(&a.side, &format!("## bench infer: {} on {}", a.preset, device_name(device)), &rows)
}

fn device_index(device: Device) -> Option<usize> {
    match device {
        Device::Cuda(i) => Some(i),
        _ => None,
    }
}

/// The card's memory in use, in GiB (None on the CPU): the caching
/// allocator keeps what it reached, so after a benchmark about its peak.
/// tch binds no `max_memory_allocated`; the NVML figure from `nvidia-smi`
/// (memory.used: the whole card, this process alone on a GPU job) is read instead.
fn peak_device_memory_gib(device: Device) -> Option<f64> {
    let i = device_index(device)?;
    let out = std::process::Command::new("nvidia-smi").args(["--query-gpu=memory.used", "--format=csv,noheader,nounits", "-i", &i.to_string()]).stderr(std::process::Stdio::null()).output().ok()?;
    String::from_utf8_lossy(&out.stdout).trim().parse::<f64>().ok().map(|mib| mib / 1024.0)
}

/// Refinement cost: ms per step (M_render forward + backward to the map,
/// priors, Adam) against one identity render (ND_enc + M_render forward,
/// no autograd) of the same material, measured in the same run.
fn bench_capture(args: &CaptureBenchArgs) -> Result<()> {
    use flashmat::fit::photos::{fit_capture, load_capture, load_teacher, fitted_neural_material, PhotoFitConfig};
    use flashmat::geometry::LightView;
    let device = flashmat::device::parse_device(&args.device)?;
    let cfg = PhotoFitConfig { size: args.size, ..Default::default() };
    cfg.validate()?;
    anyhow::ensure!((1..=5).contains(&args.photos), "--photos must be between 1 and 5, got {}", args.photos);
    // Overhead, then co-located phones whose flash reflections land in the sample's four quarters.
    let overhead = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let tilted = flashmat::data::captures::TILTED_PHONES.iter().map(|&p| LightView { light: p, view: p });
    let configs: Vec<LightView> = std::iter::once(overhead).chain(tilted).take(args.photos).collect();
    // The capture folder lives only while it is read.
    let dir = std::env::temp_dir().join(format!("flashmat-bench-capture-{}", std::process::id()));
    flashmat::data::captures::write_synthetic(&dir, &procedural::test_material(0, args.size), &configs, 2.0)?;
    let capture = load_capture(&flashmat::data::captures::Captures::open(&dir)?, args.photos, args.size);
    let _ = std::fs::remove_dir_all(&dir);
    let capture = capture?;
    let loaded = flashmat::infer::load_model(None, device)?;
    let teacher = load_teacher(None, device)?;
    let photo = capture.photos.get(capture.overhead as i64);
    let t0 = std::time::Instant::now();
    let image = flashmat::image::Image::from_tensor(&photo.clamp(0.0, 1.0))?;
    let single = flashmat::infer::estimate(&loaded.model, &loaded.info, &flashmat::infer::PreparedPhoto::at_model_view(image, true, "bench"))?;
    let _ = single.render(&[flashmat::infer::NeuralMaterial::identity_config()])?;
    let single_s = t0.elapsed().as_secs_f64();
    let t1 = std::time::Instant::now();
    let fit = fit_capture(&loaded, &capture, &cfg, device, |_, _, _| {})?;
    let _ = fitted_neural_material(&fit.maps, &photo, &teacher, &capture.configs, &cfg.code_fit, "bench")?;
    let capture_s = t1.elapsed().as_secs_f64();
    println!(
        "estimate --capture, {} photos at {}x{} on {:?}: {capture_s:.1} s ({:.1} s the fit, {} steps), {:.1}x the single-photo estimate and identity render of the overhead photo ({single_s:.1} s)",
        args.photos,
        args.size,
        args.size,
        device,
        fit.report.seconds,
        cfg.steps,
        capture_s / single_s
    );
    Ok(())
}

fn bench_frame(args: &FrameBenchArgs) -> Result<()> {
    use flashmat::capture::{frame::FrameLayout, synthetic};
    anyhow::ensure!((2..=20).contains(&args.photos), "--photos must be from 2 to 20, got {}", args.photos);
    anyhow::ensure!(args.megapixels.is_finite() && (0.5..=50.0).contains(&args.megapixels), "--megapixels must be from 0.5 to 50");
    let height = ((args.megapixels * 1e6 * 0.75).sqrt() as usize) / 8 * 8;
    let width = height * 4 / 3;
    // A 26 mm-equivalent lens: f = 26 / 43.27 * the diagonal.
    let focal = 26.0 / flashmat::infer::camera::FULL_FRAME_DIAGONAL_MM * (width as f64).hypot(height as f64);
    let layout = FrameLayout::new(10)?;
    // Around the frame at 26-28 cm, each flash's reflection (about straight below the phone) inside the opening.
    let eyes: Vec<[f64; 3]> = (0..args.photos)
        .map(|i| {
            if i == 0 {
                return [0.0, 0.0, 280.0];
            }
            let a = 2.0 * std::f64::consts::PI * i as f64 / (args.photos - 1) as f64;
            [40.0 * a.cos(), 40.0 * a.sin(), 260.0]
        })
        .collect();
    let views = synthetic::phone_views(&eyes, &[0.0, 15.0, -25.0, 40.0], width, height, focal, -0.03, 0.0);
    // The photos and the capture folder live only while the benchmark runs.
    let root = std::env::temp_dir().join(format!("flashmat-bench-frame-{}", std::process::id()));
    std::fs::create_dir_all(&root)?;
    let result = frame_bench_in(&root, &views, &layout, width, height, focal, args.photos);
    let _ = std::fs::remove_dir_all(&root);
    result
}

fn frame_bench_in(root: &std::path::Path, views: &[flashmat::capture::synthetic::PhoneView], layout: &flashmat::capture::frame::FrameLayout, width: usize, height: usize, focal: f64, count: usize) -> Result<()> {
    use flashmat::capture::{find_frame, frame::FrameLayout, load_frame_photo, synthetic, CaptureConfig};
    let material = procedural::test_material(3, 256);
    let bar = indicatif::ProgressBar::new(views.len() as u64).with_message("rendering photos (not timed)");
    let mut paths = vec![];
    // One ray a pixel: 12 MP photos need no supersampling to be sharp.
    let fx = synthetic::PhoneEffects { jpeg_quality: None, ..Default::default() };
    for (i, shot) in synthetic::shoot(&material, layout, views, [0.0, 0.0], 1, &fx)?.into_iter().enumerate() {
        let path = root.join(format!("IMG_{i:02}.jpg"));
        flashmat::io::write_jpeg(&path, &shot.rgb.to_image(), 90)?;
        paths.push(path);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let t = std::time::Instant::now();
    let photo = load_frame_photo(&paths[0])?;
    let decode_s = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let (layout, found) = find_frame(&photo, 2)?;
    let pairs: Vec<_> = found.iter().filter_map(|m| layout.find(m.id).map(|tag| (FrameLayout::corners(tag), m.corners))).flat_map(|(w, p)| w.into_iter().zip(p)).collect();
    let h = flashmat::capture::camera::homography(&pairs)?;
    let _ = flashmat::capture::camera::pose_from_homography(&h, &flashmat::capture::camera::Intrinsics::centred(focal, width, height));
    let detect_s = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let photos = paths.iter().map(|p| load_frame_photo(p)).collect::<Result<Vec<_>>>()?;
    let capture = flashmat::capture::capture(&photos, &CaptureConfig::default(), |_, _, _| {})?;
    flashmat::capture::write_folder(&capture, &root.join("capture"), &photos)?;
    let total_s = t.elapsed().as_secs_f64();
    let off = capture.photos.iter().zip(views).map(|(p, v)| flashmat::geometry::length(flashmat::geometry::sub(p.camera, v.pose.centre()))).fold(0.0, f64::max);
    println!(
        "capture of {} photos of {width}x{height} ({:.1} MP, JPEG): tags and pose of one photo {detect_s:.2} s ({:.2}x its decode, {decode_s:.2} s; {} tags); the whole capture folder {total_s:.1} s; lenses at most {off:.2} mm off",
        count,
        (width * height) as f64 / 1e6,
        detect_s / decode_s,
        found.len()
    );
    Ok(())
}

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
    anyhow::ensure!(args.batch >= 1 && args.steps >= 1, "--batch and --steps must be at least 1");
    let reference = reference_of(&args.side)?;
    flashmat::precision::set(args.side.precision)?;
    println!(
        "flashmat bench train: {} preset, crop {}, {} materials x (1 + {}) renders, {device:?}, {} torch threads, precision {}",
        args.preset,
        args.crop,
        args.batch,
        args.outputs,
        tch::get_num_threads(),
        args.side.precision
    );
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
    let base = TrainConfig { model: model.clone(), crop: args.crop, material_size: args.crop.max(256), materials_per_batch: args.batch, outputs_per_material: args.outputs, ..Default::default() };
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
    let ms: Vec<f64> = times.iter_mut().map(|t| median(t)).collect();
    for ((name, _, _), t) in variants.iter().zip(&ms) {
        println!("{name:<58} {t:9.1} ms/step (median of {})  {:.2}x the reference's steps per second", args.steps, ms[0] / t);
    }
    drop(trainers);
    // The default step alone, step after step as a run trains, with the
    // GPU's busy fraction sampled meanwhile.
    let mut trainer = Trainer::new(base.clone(), device)?;
    trainer.train_step(&batches[0])?;
    let sampler = device_index(device).and_then(BusySampler::start);
    let mut sustained = vec![];
    for b in &batches[1..] {
        let start = Instant::now();
        trainer.train_step(b)?;
        if let Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
        sustained.push(start.elapsed().as_secs_f64() * 1000.0);
    }
    let busy = sampler.and_then(BusySampler::finish);
    drop(trainer);
    let ours = median(&mut sustained);
    let flops = model_flops_per_step(&base);
    println!(
        "default step, one after another: {ours:.1} ms/step, {:.2} materials/s, {:.2} TFLOP/s of M_est + renderer forward and backward{}",
        args.batch as f64 * 1e3 / ours,
        flops / (ours * 1e9),
        busy.map_or(String::new(), |b| format!(", GPU busy {:.0}%", 100.0 * b))
    );
    step_breakdown(args, &model, device)?;
    if let Some(gib) = peak_memory_gib() {
        println!("peak resident memory: {gib:.2} GiB");
    }
    if let Some(gib) = peak_device_memory_gib(device) {
        println!("GPU memory in use on the card: {gib:.2} GiB (the caching allocator keeps its peak)");
    }
    let shape = format!("{}, crop {}, {} x {}, {}", args.preset, args.crop, args.batch, args.outputs, args.side.precision);
    let mut rows = vec![
        Row { what: format!("training step, {shape}"), ours_ms: Some(ours), theirs_ms: None, ours_rate: Some(args.batch as f64 * 1e3 / ours), theirs_rate: None, busy, tflops: Some(flops / (ours * 1e9)) },
        Row { what: format!("training step, {shape}, flashmat's previous step"), ours_ms: Some(ms[0]), theirs_ms: None, ours_rate: Some(args.batch as f64 * 1e3 / ms[0]), theirs_rate: None, busy: None, tflops: Some(flops / (ms[0] * 1e9)) },
    ];
    if let Some(r) = &reference {
        let mut cmd: Vec<String> = ["--device", &device_name(device), "--crop", &args.crop.to_string(), "--batch", &args.batch.to_string(), "--outputs", &args.outputs.to_string()].map(String::from).to_vec();
        cmd.extend(["--steps".into(), args.steps.max(3).to_string(), "--warmup".into(), "2".into()]);
        if args.side.amp {
            cmd.push("--amp".into());
        }
        let lines = reference_lines(r, &cmd);
        let (ms, rate, why) = theirs(find(&lines, "ref_train_step", &[]), "samples_per_s");
        (rows[0].theirs_ms, rows[0].theirs_rate) = (ms, rate);
        (rows[1].theirs_ms, rows[1].theirs_rate) = (ms, rate);
        if let Some(why) = why {
            rows[0].what += &format!(" (authors': {why})");
        }
        if args.side.amp {
            let (ms, rate, why) = theirs(find(&lines, "ref_train_step_amp_bf16", &[]), "samples_per_s");
            let what = format!("training step, {shape}, authors' under bf16 autocast{}", why.map_or(String::new(), |w| format!(" ({w})")));
            rows.push(Row { what, ours_ms: Some(ours), theirs_ms: ms, ours_rate: rows[0].ours_rate, theirs_rate: rate, busy: None, tflops: None });
        }
        if model.model_id() != flashmat::model::ModelConfig::preset("paper")?.model_id() {
            println!("note: the authors' step is the paper's model; flashmat's is the {} preset", args.preset);
        }
    }
    finish_table(&args.side, &format!("## bench train on {}", device_name(device)), &rows)
}

/// Median of a list of timings.
fn median(t: &mut [f64]) -> f64 {
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// FLOPs of one step's M_est and renderer passes, forward and backward
/// (backward taken as twice the forward): the floor of what a step
/// computes (LPIPS and the discriminator not counted).
fn model_flops_per_step(cfg: &flashmat::train::TrainConfig) -> f64 {
    let (nb, k, px) = (cfg.materials_per_batch as f64, cfg.outputs_per_material as f64, (cfg.crop * cfg.crop) as f64);
    3.0 * nb * (flashmat::model::est_flops(&cfg.model, cfg.crop as i64, cfg.crop as i64) + k * px * flashmat::model::renderer_flops_per_row(&cfg.model))
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
    let cfg = TrainConfig { model: model.clone(), crop: args.crop, material_size: args.crop.max(256), materials_per_batch: args.batch, outputs_per_material: args.outputs, ..Default::default() };
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
