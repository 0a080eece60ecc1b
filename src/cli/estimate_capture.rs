//! `flashmat estimate --capture DIR`: one neural material from all photos
//! of a capture folder (work done in `flashmat::fit::photos`).

use super::estimate_options::EstimateOptions;
use flashmat::data::captures::Captures;
use flashmat::fit::export::{check_output_dir, write_fit};
use flashmat::fit::photos::{capture_material, PhotoFitConfig};
use flashmat::fit::relief::ReliefConfig;
use anyhow::{bail, ensure, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::Path;
use std::time::Instant;

/// The options of `estimate --capture`.
#[derive(Args, Debug, Clone)]
pub struct CaptureArgs {
    /// A capture folder (photos 00.png or 00.jpg, 01 ..., camera_pos.txt, light_pos.txt, image_size.txt): one material from
    /// all its photos, a per-pixel GGX fit to them with their light and camera positions, started from the estimate
    /// of the most overhead photo, then a neural material of the fitted maps (the bundled teacher's encoder and renderer).
    /// --size sets the side of the fitted maps; --model the model of the start; --device where both run.
    #[arg(long, value_name = "DIR", conflicts_with = "photo")]
    pub capture: Option<std::path::PathBuf>,
    /// With --capture: use the first K photos (default: all).
    #[arg(long, value_name = "K", requires = "capture")]
    pub photos: Option<usize>,
    /// With --capture: Adam steps of the fit to the photos.
    #[arg(long, requires = "capture", default_value_t = PhotoFitConfig::default().steps)]
    pub steps: usize,
    /// With --capture: fit an exposure gain per photo (photos taken with auto exposure; the overhead photo's is 1).
    /// Off by default: with one exposure it costs a little (reports/capture.md).
    #[arg(long, requires = "capture")]
    pub photo_gains: bool,
    /// With --capture: also write the fitted GGX maps as PBR texture sets into DIR (as `flashmat fit` does).
    #[arg(long, value_name = "DIR", requires = "capture")]
    pub pbr: Option<std::path::PathBuf>,
}

pub fn estimate_capture(dir: &Path, output: &Path, a: &CaptureArgs, opts: &EstimateOptions) -> Result<()> {
    let t0 = Instant::now();
    ensure!(output.extension().is_some_and(|e| e.eq_ignore_ascii_case("nmat")), "{}: the output must end in .nmat", output.display());
    if opts.refine.is_some() || opts.tile || opts.highlight_fill.is_some() || opts.fov.is_some() || opts.exposure.is_some() || opts.square {
        bail!("--capture takes none of --refine, --tile, --highlight-fill, --fov, --exposure, --square (capture photos are rectified to the sample)");
    }
    let cfg = PhotoFitConfig { steps: a.steps, size: opts.size, photo_gains: a.photo_gains, ..Default::default() };
    cfg.validate()?;
    if let Some(pbr) = &a.pbr {
        check_output_dir(pbr)?;
    }
    let device = flashmat::device::parse_device(&opts.device)?;
    let captures = Captures::open(dir)?;
    let count = a.photos.unwrap_or(captures.photos.len());
    check_capture_memory(opts.size, count, &opts.max_memory, "lower --size, or raise --max-memory where the machine has it")?;
    let style = |what: &str| ProgressStyle::with_template(&format!("{what} {{bar:40}} {{pos}}/{{len}} ETA {{eta}}"));
    let stages = [style("start: estimate of the overhead photo, GGX fit")?, style(&format!("fitting {count} photos"))?, style("neural material: codes, then its gap to the maps")?];
    let bar = ProgressBar::new(0);
    let mut stage = usize::MAX;
    let made = capture_material(&captures, count, &cfg, opts.model.as_deref(), device, |w| bar.suspend(|| eprintln!("warning: {w}")), |s, done, total| {
        if s != stage {
            stage = s;
            bar.set_style(stages[s].clone());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let out_dir = super::prepare_output(output)?;
    // The maps first: where they cannot be written, the material is not
    // written either (a failed run leaves no .nmat without its maps).
    if let Some(pbr) = &a.pbr {
        write_fit(pbr, &made.fit.as_fit_result(), &ReliefConfig::default(), &dir.display().to_string()).with_context(|| format!("{} not written", output.display()))?;
    }
    made.material.save(output)?;
    out_dir.keep();
    let r = &made.fit.report;
    eprintln!(
        "estimated {} from {} of {} photos at {}x{}: data term {:.4} -> {:.4} (mean |ln(1+R) diff| {:.4} -> {:.4}), {} steps, {:.1} s ({:.1} s fit)",
        output.display(),
        r.photos,
        captures.photos.len(),
        cfg.size,
        cfg.size,
        r.data_before,
        r.data_after,
        r.error_before,
        r.error_after,
        cfg.steps,
        t0.elapsed().as_secs_f64(),
        r.seconds
    );
    if cfg.photo_gains {
        eprintln!("exposure gains: {}", made.names.iter().zip(&r.photo_gains).map(|(n, g)| format!("{n} {g:.3}")).collect::<Vec<_>>().join(", "));
    }
    if let Some(pbr) = &a.pbr {
        eprintln!("wrote PBR maps of the fit to {}", pbr.display());
    }
    let (g, c) = (&made.gap, &made.code_fit);
    let lpips = g.lpips.map(|l| format!(", LPIPS {l:.3}")).unwrap_or_default();
    eprintln!(
        "the neural material against its GGX maps, {} held-out views: log L1 {:.4}, colour {:.3} (largest channel |ln ratio|), chromaticity {:.4}{lpips}; codes {} ({:.1} s, loss {:.4} -> {:.4})",
        2 * flashmat::fit::photos::GAP_CONFIGS,
        g.log_l1,
        g.channel_log_ratio,
        g.chromaticity,
        if c.kept { "fitted to the maps" } else { "as the teacher draws them" },
        c.seconds,
        c.loss_before,
        c.loss_after
    );
    if let Some(why) = g.warning() {
        let pbr = if a.pbr.is_some() { "the PBR maps you wrote" } else { "the PBR maps (--pbr DIR)" };
        eprintln!("warning: the neural material is far from its fitted maps ({why}); relight {pbr} where they matter, or refit at a smaller --size");
    }
    Ok(())
}

/// Refuses a capture fit at side `size` with `photos` photos whose memory
/// ([`capture_fit_memory`](flashmat::fit::photos::capture_fit_memory)) is
/// above `max_memory` (`--max-memory`), before any work; `remedy` ends
/// the line (what the user's command can change).
pub fn check_capture_memory(size: usize, photos: usize, max_memory: &str, remedy: &str) -> Result<()> {
    let limit = flashmat::infer::tiles::parse_memory(max_memory)?;
    let need = flashmat::fit::photos::capture_fit_memory(size, photos);
    ensure!(
        need <= limit as f64,
        "a capture fit at --size {size} with {photos} photos needs about {:.1} GiB, more than the {max_memory} allowed: {remedy}",
        need / (1u64 << 30) as f64
    );
    Ok(())
}
