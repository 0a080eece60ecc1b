//! `flashmat capture frame`: the frame to print; `flashmat capture
//! PHOTOS... -o DIR`: phone photos of it to a capture folder (work done in
//! `flashmat::capture`), and with `--estimate` on to one material.

use super::estimate_capture::CaptureArgs;
use super::estimate_options::EstimateOptions;
use anyhow::{bail, ensure, Result};
use clap::{Args, Parser, Subcommand};
use flashmat::capture::frame::{self, FrameLayout, Paper};
use flashmat::capture::{load_frame_photo, tilt_deg, CaptureConfig};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::time::Instant;

/// The options of `flashmat capture`.
#[derive(Args, Debug)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct CaptureCommandArgs {
    #[command(subcommand)]
    pub frame: Option<FrameCommand>,
    /// Flash photos of the printed frame lying flat on the material (JPEG, PNG, HEIC; 2 or more, 3-5 is best:
    /// docs/CAPTURE.md). Each must show at least 4 of the frame's tags.
    #[arg(value_name = "PHOTO", required = true)]
    pub photos: Vec<PathBuf>,
    /// The capture folder to write (it must not exist, or be empty). With --estimate: the material (.nmat), and
    /// the capture folder is written beside it as NAME-capture/.
    #[arg(short, long, required = true)]
    pub output: Option<PathBuf>,
    /// The flash's offset from the lens in mm, X,Y in the camera frame of the photo as the phone's sensor stores
    /// it (X along its rows, Y down its columns; turned with each photo's EXIF orientation). 0,0 takes them as
    /// one point; docs/CAPTURE.md says how to measure it.
    #[arg(long, value_name = "X,Y", default_value = "0,0", value_parser = parse_offset, allow_hyphen_values = true)]
    pub flash_offset: [f64; 2],
    /// The largest side of the rectified photos, pixels (they keep the overhead photo's resolution of the opening up to it).
    #[arg(long, default_value_t = CaptureConfig::default().max_side)]
    pub max_size: usize,
    /// Go on to one material from the capture (`flashmat estimate --capture`), written to -o.
    #[arg(long)]
    pub estimate: bool,
    /// With --estimate: side of the fitted maps, pixels (a multiple of 8).
    #[arg(long, requires = "estimate", default_value_t = 256)]
    pub size: usize,
    /// With --estimate: Adam steps of the fit to the photos.
    #[arg(long, requires = "estimate", default_value_t = flashmat::fit::photos::PhotoFitConfig::default().steps)]
    pub steps: usize,
    /// With --estimate: cpu, cuda or cuda:N.
    #[arg(long, requires = "estimate", default_value = "cpu")]
    pub device: String,
}

#[derive(Subcommand, Debug)]
pub enum FrameCommand {
    /// Write the frame to print: tag36h11 tags around a square opening, a 100 mm scale bar and what the frame is.
    /// PDF (vector, prints at its true size) or PNG (--dpi).
    Frame(FrameArgs),
}

#[derive(Args, Debug)]
pub struct FrameArgs {
    /// frame.pdf or frame.png.
    #[arg(short, long)]
    pub output: PathBuf,
    #[arg(long, value_enum, default_value_t = Paper::A4)]
    pub paper: Paper,
    /// Side of the square opening, whole centimetres (5 to 14): the sample that shows through it.
    #[arg(long, value_name = "CM", default_value_t = 10)]
    pub opening: u32,
    /// Resolution of a PNG, dots per inch (default 300; stored in the file, so it prints at its true size). A PDF is
    /// vector: it takes none.
    #[arg(long)]
    pub dpi: Option<f64>,
}

/// The PNG frame's resolution when none is given.
const DEFAULT_FRAME_DPI: f64 = 300.0;

fn parse_offset(s: &str) -> std::result::Result<[f64; 2], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let values: Vec<f64> = parts.iter().filter_map(|p| p.parse().ok()).filter(|v: &f64| v.is_finite() && v.abs() <= 100.0).collect();
    match (parts.len(), values.as_slice()) {
        (2, &[x, y]) => Ok([x, y]),
        _ => Err(format!("'{s}' is not X,Y: two numbers of mm within +-100")),
    }
}

/// `estimate`'s options at their defaults: what `--estimate` runs with.
fn default_estimate_options() -> Result<EstimateOptions> {
    #[derive(Parser)]
    struct Defaults {
        #[command(flatten)]
        options: EstimateOptions,
    }
    Ok(Defaults::try_parse_from(["flashmat"])?.options)
}

pub fn run(a: &CaptureCommandArgs) -> Result<()> {
    if let Some(FrameCommand::Frame(f)) = &a.frame {
        return write_frame(f);
    }
    let output = a.output.as_ref().expect("clap requires -o without a subcommand");
    let t0 = Instant::now();
    let (folder, material) = if a.estimate {
        ensure!(output.extension().is_some_and(|e| e.eq_ignore_ascii_case("nmat")), "{}: with --estimate, -o names the material (.nmat)", output.display());
        let stem = output.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        (output.with_file_name(format!("{stem}-capture")), Some(output.clone()))
    } else {
        if output.extension().is_some_and(|e| e.eq_ignore_ascii_case("nmat")) {
            bail!("{}: -o is the capture folder; pass --estimate to go on to a material", output.display());
        }
        (output.clone(), None)
    };
    if folder.exists() && std::fs::read_dir(&folder).map(|mut d| d.next().is_some()).unwrap_or(true) {
        bail!("{} exists and is not empty: choose a new folder for the capture", folder.display());
    }
    if a.estimate {
        // Every option of the whole command before any work or write.
        flashmat::fit::photos::PhotoFitConfig { steps: a.steps, size: a.size, ..Default::default() }.validate()?;
        flashmat::device::parse_device(&a.device)?;
        let remedy = "lower --size, or write the capture folder alone (no --estimate) and run `flashmat estimate --capture FOLDER` on it with a larger --max-memory";
        super::estimate_capture::check_capture_memory(a.size, a.photos.len(), &default_estimate_options()?.max_memory, remedy)?;
    }
    let cfg = CaptureConfig { flash_offset_mm: a.flash_offset, max_side: a.max_size, ..Default::default() };
    let bar = ProgressBar::new(a.photos.len() as u64).with_style(ProgressStyle::with_template("{msg} {bar:40} {pos}/{len}")?);
    bar.set_message("reading photos");
    let mut photos = Vec::new();
    for (i, p) in a.photos.iter().enumerate() {
        photos.push(load_frame_photo(p)?);
        bar.set_position(i as u64 + 1);
    }
    let exposures_differ = flashmat::capture::exposure_warning(&photos);
    let messages = ["finding the frame's tags", "fitting the camera", "rectifying the opening"];
    let capture = flashmat::capture::capture(&photos, &cfg, |stage, done, total| {
        bar.set_message(messages[stage]);
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    flashmat::capture::write_folder(&capture, &folder, &photos)?;
    let k = &capture.photos[0].intrinsics;
    eprintln!(
        "wrote capture folder {} in {:.1} s: {} photos, the {} cm opening at {}x{} pixels; focal length {:.0} px{}",
        folder.display(),
        t0.elapsed().as_secs_f64(),
        capture.photos.len(),
        capture.layout.opening_cm,
        capture.side,
        capture.side,
        k.focal,
        if capture.distortion { format!(", distortion k1 {:.3} k2 {:.3}", k.k1, k.k2) } else { String::new() }
    );
    let levels = flashmat::capture::photometry::relative_levels(&capture.paper);
    for (n, p) in capture.photos.iter().enumerate() {
        let source = p.source.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
        let paper = match &levels {
            Some(l) => format!("; paper: exposure x{:.3}, R/G/B x{:.3}/{:.3}/{:.3} of the first's", (l[n][0] * l[n][1] * l[n][2]).cbrt(), l[n][0], l[n][1], l[n][2]),
            None => String::new(),
        };
        eprintln!(
            "  {n:02} {source}: lens at ({}, {}, {}) mm, tilt {:.0} deg, {} tags, {:.2} px reprojection{paper}",
            mm(p.camera[0]),
            mm(p.camera[1]),
            mm(p.camera[2]),
            tilt_deg(p.camera),
            p.markers.len(),
            p.rms
        );
    }
    match (&levels, capture.folder_exposures(&photos)?) {
        (Some(_), Some(_)) => eprintln!(
            "the photos' exposure or white balance differ, as the frame's paper shows: {} records them and the fit brings the photos to the first's",
            flashmat::data::captures::EXPOSURES_FILE
        ),
        (None, Some(_)) => eprintln!(
            "the photos' exposures differ (from their EXIF; the frame's paper could not be read in every photo): {} records them and the fit brings the photos to one",
            flashmat::data::captures::EXPOSURES_FILE
        ),
        _ => {}
    }
    if let Some(gamma) = capture.gamma {
        eprintln!("the frame's paper says the photos' tone curve is not the sRGB curve but a pure gamma of {gamma:.2}: the capture's photos are read through it");
    }
    eprintln!("look at {}", folder.join("capture.jpg").display());
    for w in flashmat::capture::photometry::warnings(&capture.photos, &capture.paper) {
        eprintln!("warning: {w}");
    }
    if let (Some(w), None) = (&exposures_differ, &levels) {
        eprintln!("warning: {w}{}", if a.estimate { "; --estimate fits them" } else { "" });
    }
    if let Some(material) = material {
        let mut opts = default_estimate_options()?;
        opts.size = a.size;
        opts.device = a.device.clone();
        let args = CaptureArgs { capture: Some(folder.clone()), photos: None, steps: a.steps, photo_gains: exposures_differ.is_some() && levels.is_none(), pbr: None };
        // The folder and the material together, or neither: a failed estimate takes the folder with it.
        if let Err(e) = super::estimate_capture::estimate_capture(&folder, &material, &args, &opts) {
            let _ = std::fs::remove_dir_all(&folder);
            return Err(e);
        }
    }
    Ok(())
}

/// Whole millimetres, without a "-0".
fn mm(v: f64) -> String {
    format!("{}", v.round() + 0.0)
}

fn write_frame(f: &FrameArgs) -> Result<()> {
    let layout = FrameLayout::new(f.opening)?;
    let ext = f.output.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    if ext == "pdf" {
        anyhow::ensure!(f.dpi.is_none(), "--dpi sets a PNG's resolution; {} is a PDF (vector: it prints at its true size at any resolution)", f.output.display());
    }
    let dpi = f.dpi.unwrap_or(DEFAULT_FRAME_DPI);
    let out = super::prepare_output(&f.output)?;
    match ext.as_str() {
        "pdf" => flashmat::io::atomic_write_bytes(&f.output, &frame::frame_pdf(&layout, f.paper)?)?,
        "png" => {
            let (image, caption) = frame::frame_raster(&layout, f.paper, dpi)?;
            // 9 pt text: 9/72 inch high; `Mark::Text` places its top-left corner.
            let size = dpi / 72.0 * 9.0;
            let marks: Vec<flashmat::viz::Mark> =
                caption.into_iter().map(|(text, [x, baseline])| flashmat::viz::Mark::Text { at: (x, baseline - size), text, size: size * 1.3, color: [0, 0, 0] }).collect();
            let page = flashmat::viz::annotate(&image, &marks)?;
            flashmat::io::write_png_at_dpi(&f.output, &page, flashmat::io::BitDepth::Eight, dpi)?;
        }
        _ => bail!("{}: the frame is written as .pdf or .png", f.output.display()),
    }
    out.keep();
    eprintln!(
        "wrote {}: the {} cm opening's frame ({} tag36h11 tags, ids {}-{}) on {:?} paper; print at 100% and check the {} mm bar",
        f.output.display(),
        layout.opening_cm,
        layout.tags.len(),
        layout.tags[0].id,
        layout.tags.last().map_or(0, |t| t.id),
        f.paper,
        frame::SCALE_BAR_MM
    );
    Ok(())
}
