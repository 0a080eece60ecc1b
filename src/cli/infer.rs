//! `flashmat estimate | relight | show`: photos to neural materials and
//! pictures of them (work done in `flashmat::infer`).

use super::materials::write_render;
use super::estimate_options::EstimateOptions;
use super::{prepare_output, Vec3Arg};
use flashmat::geometry::above_surface;
use flashmat::infer::refine::{refine, RefineConfig};
use flashmat::infer::{self, NeuralMaterial};
use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::Device;



impl EstimateOptions {
    fn exposure_config(&self) -> infer::ExposureConfig {
        self.exposure_mode.config()
    }

    fn highlight_fill_config(&self) -> Option<infer::highlight_fill::HighlightFillConfig> {
        self.highlight_fill.map(infer::highlight_fill::HighlightFillConfig::with_mode)
    }

    /// The requested refinement, checked; None without `--refine` or with `--refine 0`.
    fn refine_config(&self) -> Result<Option<RefineConfig>> {
        let Some(steps) = self.refine.filter(|&s| s > 0) else { return Ok(None) };
        let cfg = self.refine_weights.config(steps);
        cfg.validate()?;
        Ok(Some(cfg))
    }
}

/// Refines a material on `photo` (`[3, H, W]` linear) with a progress bar;
/// returns the report line. A refinement stopped by a non-finite loss keeps
/// the unrefined material and says so in the line.
fn refine_with_progress(material: &mut NeuralMaterial, photo: &tch::Tensor, clipped: bool, cfg: &RefineConfig) -> Result<String> {
    let bar = ProgressBar::new(cfg.steps as u64).with_style(ProgressStyle::with_template("refining {bar:40} {pos}/{len} steps {per_sec} ETA {eta}")?);
    let report = refine(material, photo, clipped, cfg, |_| bar.inc(1))?;
    bar.finish_and_clear();
    Ok(report.summary())
}

#[derive(Args, Debug)]
pub struct EstimateArgs {
    /// Flash photo: PNG/JPEG/HEIC/AVIF (gamma-decoded, LDR) or EXR (linear HDR). Several photos or a folder (its
    /// .png/.jpg/.jpeg/.exr/.heic/.heif/.avif files) make a batch: one OUTDIR/NAME.nmat each, a failed photo reported
    /// and skipped.
    #[arg(required_unless_present = "capture", num_args = 1.., value_name = "PHOTO|DIR")]
    pub photo: Vec<PathBuf>,
    /// Output neural material (.nmat); for a batch, the output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub capture: super::estimate_capture::CaptureArgs,
    #[command(flatten)]
    pub estimate: EstimateOptions,
}

#[derive(Args, Debug)]
pub struct RelightArgs {
    /// A neural material (.nmat), or a photo (estimated first with the options below).
    pub material: PathBuf,
    /// Point light position X,Y,Z (the material spans [-1,1]^2 at z = 0; z must be > 0).
    #[arg(long, value_name = "X,Y,Z", conflicts_with_all = ["orbit", "identity"])]
    pub light: Option<Vec3Arg>,
    /// Camera position X,Y,Z (z > 0). Default: overhead, as in the photo.
    #[arg(long, value_name = "X,Y,Z", conflicts_with = "identity")]
    pub view: Option<Vec3Arg>,
    /// Animate N frames of a light circling the material (radius 2, height 3) into a GIF.
    #[arg(long, value_name = "N", conflicts_with = "identity")]
    pub orbit: Option<usize>,
    /// Light and camera of the input photo (re-creates the photo).
    #[arg(long)]
    pub identity: bool,
    /// Output: .png (8-bit sRGB) or .exr (linear radiance); .gif with --orbit.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub estimate: EstimateOptions,
}

#[derive(Args, Debug)]
pub struct ShowArgs {
    /// A neural material (.nmat), or a photo (estimated first with the options below).
    pub material: PathBuf,
    /// Output PNG.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub estimate: EstimateOptions,
}

fn extension(path: &Path) -> Option<String> {
    path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase())
}

fn require_extension(path: &Path, allowed: &[&str], what: &str) -> Result<()> {
    match extension(path) {
        Some(e) if allowed.contains(&e.as_str()) => Ok(()),
        _ => bail!("{}: {what}", path.display()),
    }
}

/// Runs M_est on a photo file. Prints the model-mismatch warning (if any)
/// to stderr and returns the timing line, which callers print once their
/// output is written (so a failed write stays a single error line).
pub fn estimate_photo(photo: &Path, opts: &EstimateOptions) -> Result<(NeuralMaterial, String)> {
    let device = flashmat::device::parse_device(&opts.device)?;
    let refine_cfg = opts.refine_config()?;
    let max_memory = infer::tiles::parse_memory(&opts.max_memory)?;
    let t0 = Instant::now();
    let prepared = infer::load_photo_with(photo, &infer::PhotoOptions { fov_deg: opts.fov, size: opts.size, exposure_ev: opts.exposure, square: opts.square })?;
    let t_photo = t0.elapsed().as_secs_f64();
    for w in &prepared.warnings {
        eprintln!("warning: {w}");
    }
    let loaded = infer::load_model(opts.model.as_deref(), device)?;
    // The bundled model serves both photo types by design: warn only for a chosen one.
    if let Some(w) = opts.model.as_ref().and_then(|_| infer::input_mismatch_warning(&loaded.info, &loaded.path, prepared.ldr)) {
        eprintln!("{w}");
    }
    let (h, w) = (prepared.linear.height, prepared.linear.width);
    let plan = infer::plan_estimate(&loaded.model.config, h, w, max_memory).with_context(|| format!("{}", photo.display()))?;
    let t1 = Instant::now();
    let mut material = infer::estimate_planned(&loaded.model, &loaded.info, &prepared, &plan, &opts.exposure_config(), || ())
        .with_context(|| format!("estimating {} with model {}", photo.display(), loaded.path.display()))?;
    if let Device::Cuda(i) = device {
        tch::Cuda::synchronize(i as i64);
    }
    let t_est = t1.elapsed().as_secs_f64();
    let c = prepared.crop;
    let how = match plan {
        infer::EstPlan::Whole => "whole".to_string(),
        infer::EstPlan::Tiled(core) => {
            let n = |len: usize| infer::tiles::tile_count(len, core);
            format!("layer by layer in {} tiles of {core} px (--max-memory {})", n(h) * n(w), opts.max_memory)
        }
    };
    let peak = super::bench::peak_memory_gib().map(|g| format!(", peak memory {g:.2} GiB")).unwrap_or_default();
    let summary = format!(
        "estimated in {:.2} s ({w}x{h} map; photo {:.2} s, model load {:.2} s, M_est {:.2} s {how}{peak}; {}x{} crop at ({}, {}) of the {}x{} photo, FOV {} deg, model {})",
        t0.elapsed().as_secs_f64(),
        t_photo,
        t0.elapsed().as_secs_f64() - t_photo - t_est,
        t_est,
        c.width,
        c.height,
        c.x0,
        c.y0,
        c.source_width,
        c.source_height,
        prepared.fov_deg,
        loaded.model.model_id()
    );
    // The photo's camera line comes with the timing, once the outputs are
    // written: a failure stays a single error line.
    let summary = format!("{}\n{summary}", prepared.camera_note);
    let summary = match opts.highlight_fill_config() {
        Some(cfg) => format!("{summary}\n{}", material.fill_highlight(&cfg)?.summary()),
        None => summary,
    };
    let summary = match &refine_cfg {
        Some(cfg) => format!("{summary}\n{}", refine_with_progress(&mut material, &prepared.linear.to_tensor(), prepared.ldr, cfg)?),
        None => summary,
    };
    let summary = match opts.tile {
        true => format!("{summary}\n{}", tile(&mut material)?),
        false => summary,
    };
    Ok((material, summary))
}

/// `--tile`: makes the material's map periodic; returns the report line.
fn tile(material: &mut NeuralMaterial) -> Result<String> {
    let before = infer::tiling::wrap_steps(&material.neural_map);
    material.neural_map = infer::tiling::make_tileable(&material.neural_map)?;
    let (wx, ix, wy, iy) = infer::tiling::wrap_steps(&material.neural_map);
    Ok(format!(
        "tiled: code step across the wrap / inside {:.2}x {:.2}y (before {:.2}x {:.2}y)",
        wx / ix.max(1e-12),
        wy / iy.max(1e-12),
        before.0 / before.1.max(1e-12),
        before.2 / before.3.max(1e-12)
    ))
}

/// Opens a `.nmat`, or estimates a material from a photo (recognised by its
/// PNG/JPEG/EXR/HEIF signature or extension); see [`estimate_photo`] for the
/// returned line.
pub fn open_material(path: &Path, opts: &EstimateOptions) -> Result<(NeuralMaterial, Option<String>)> {
    flashmat::io::check_input_file(path).with_context(|| format!("cannot read {}", path.display()))?;
    if looks_like_image(path) {
        return estimate_photo(path, opts).map(|(m, line)| (m, Some(line)));
    }
    let refine_cfg = opts.refine_config()?;
    let mut material = NeuralMaterial::load(path, flashmat::device::parse_device(&opts.device)?)?;
    let filled = opts.highlight_fill_config().map(|cfg| material.fill_highlight(&cfg)).transpose()?.map(|r| r.summary());
    let line = match &refine_cfg {
        Some(cfg) => {
            // The stored photo is what M_est saw: clamped to [0, 1] for 8-bit photos and LDR-input models.
            let clipped = material.meta.ldr_input || material.meta.model_info.ldr_input;
            let photo = material.input_photo.shallow_clone();
            Some(refine_with_progress(&mut material, &photo, clipped, cfg)?)
        }
        None => None,
    };
    let line = [filled, line].into_iter().flatten().reduce(|a, b| format!("{a}\n{b}"));
    let line = match opts.tile {
        true => Some([line, Some(tile(&mut material)?)].into_iter().flatten().collect::<Vec<_>>().join("\n")),
        false => line,
    };
    Ok((material, line))
}

/// A photo by its signature, or by its extension: a damaged `.png` is
/// reported as a damaged image, not as a damaged `.nmat`. (A regular file:
/// see [`flashmat::io::check_input_file`].)
fn looks_like_image(path: &Path) -> bool {
    let mut head = [0u8; 12];
    let n = std::fs::File::open(path).and_then(|mut f| std::io::Read::read(&mut f, &mut head)).unwrap_or(0);
    let head = &head[..n];
    head.starts_with(b"\x89PNG") || head.starts_with(&[0xFF, 0xD8, 0xFF]) || head.starts_with(&[0x76, 0x2F, 0x31, 0x01])
        || head.get(4..8) == Some(b"ftyp") // HEIF: HEIC, AVIF
        || matches!(extension(path).as_deref(), Some("png" | "jpg" | "jpeg" | "exr" | "heic" | "heif" | "avif"))
}

pub fn estimate(a: &EstimateArgs) -> Result<()> {
    if let Some(dir) = &a.capture.capture {
        return super::estimate_capture::estimate_capture(dir, &a.output, &a.capture, &a.estimate);
    }
    if super::batch::is_batch(&a.photo) {
        // Settings are checked once, before any photo.
        a.estimate.refine_config()?;
        return super::batch::run_batch("estimate", &a.photo, super::batch::PHOTO_EXTENSIONS, &a.output, ".nmat", |photo, output, _| {
            let (material, _) = estimate_photo(photo, &a.estimate)?;
            material.save(output)?;
            let (h, w) = material.size();
            Ok(format!("{w}x{h} map{}", identity_note(&material)?))
        });
    }
    let photo = &a.photo[0];
    require_extension(&a.output, &["nmat"], "the output must end in .nmat")?;
    let out_dir = prepare_output(&a.output)?;
    let (material, summary) = estimate_photo(photo, &a.estimate)?;
    material.save(&a.output)?;
    out_dir.keep();
    eprintln!("{summary}");
    let (h, w) = material.size();
    eprintln!("wrote {} ({}-channel {w}x{h} neural map){}", a.output.display(), material.config.neural_channels, identity_note(&material)?);
    Ok(())
}

/// `; identity render over the photo: brightness ..., R / G / B ...` (issue
/// 69: what to trust at a glance), or nothing where no pixel compares.
fn identity_note(material: &NeuralMaterial) -> Result<String> {
    Ok(infer::identity_check(material)?.map(|c| format!("; {}", c.summary())).unwrap_or_default())
}

pub fn relight(a: &RelightArgs) -> Result<()> {
    let camera = match a.view {
        Some(v) => above_surface("camera", v.0)?,
        None => infer::overhead_camera(),
    };
    if let Some(l) = a.light {
        above_surface("light", l.0)?;
    }
    if let Some(n) = a.orbit {
        require_extension(&a.output, &["gif"], "an --orbit animation must be written to a .gif")?;
        if !(1..=1000).contains(&n) {
            bail!("--orbit must be between 1 and 1000 frames, got {n}");
        }
    } else {
        require_extension(&a.output, &["png", "exr"], "the output must end in .png or .exr (.gif with --orbit)")?;
        if a.light.is_none() && !a.identity {
            bail!("relight needs a light: --light X,Y,Z, --orbit N or --identity");
        }
    }
    let out_dir = prepare_output(&a.output)?;
    let (material, summary) = open_material(&a.material, &a.estimate)?;
    let rendering = || format!("rendering {}", a.material.display());
    let t0 = Instant::now();
    if let Some(n) = a.orbit {
        let configs = infer::orbit_configs(n, infer::ORBIT_RADIUS, infer::ORBIT_HEIGHT, camera);
        let bar = ProgressBar::new(n as u64).with_style(ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} ETA {eta}")?);
        let frames = infer::render_frames(&material, &configs, |_| bar.inc(1)).with_context(rendering)?;
        bar.finish_and_clear();
        let display: Vec<_> = frames.iter().map(flashmat::image::Image::to_display).collect();
        let secs = t0.elapsed().as_secs_f64();
        flashmat::viz::write_gif(&a.output, &display, 8)?;
        summary.iter().for_each(|l| eprintln!("{l}"));
        eprintln!("rendered {n} frames in {secs:.2} s ({:.3} s/frame)", secs / n as f64);
    } else {
        let config = if a.identity {
            NeuralMaterial::identity_config()
        } else {
            flashmat::geometry::LightView { light: a.light.expect("checked above").0, view: camera }
        };
        let image = material.render_image(&config).with_context(rendering)?;
        let secs = t0.elapsed().as_secs_f64();
        write_render(&a.output, &image)?;
        summary.iter().for_each(|l| eprintln!("{l}"));
        eprintln!("rendered in {secs:.2} s");
    }
    out_dir.keep();
    eprintln!("wrote {}", a.output.display());
    Ok(())
}

pub fn show(a: &ShowArgs) -> Result<()> {
    require_extension(&a.output, &["png"], "the output must end in .png")?;
    let out_dir = prepare_output(&a.output)?;
    let (material, summary) = open_material(&a.material, &a.estimate)?;
    let grid = infer::show::show_grid(&material).with_context(|| format!("rendering {}", a.material.display()))?;
    flashmat::io::write_png(&a.output, &grid, flashmat::io::BitDepth::Eight)?;
    out_dir.keep();
    summary.iter().for_each(|l| eprintln!("{l}"));
    eprintln!(
        "wrote {} (row 1: input photo | neural map norm | neural map PCA (3 components as RGB) | identity render; row 2: light circling at 4 azimuths)",
        a.output.display()
    );
    Ok(())
}
