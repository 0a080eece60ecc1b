//! The `flashmat` command line: argument parsing and dispatch. Each
//! subcommand's work lives in the module of its pipeline stage.

pub mod batch;
pub mod bench;
pub mod capture;
pub mod estimate_capture;
pub mod estimate_options;
pub mod eval;
pub mod fit;
pub mod infer;
pub mod materials;
pub mod nmat_rows;
pub mod reference_bench;
pub mod train;
pub mod view;


use flashmat::geometry::LightView;
use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(name = "flashmat", version, about = "One flash photograph of a flat material in, a relightable neural material out.")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Render a GGX material for a point light and a camera (PNG: 8-bit sRGB, as estimate reads photos; EXR: linear HDR).
    Render(RenderArgs),
    /// Procedural and on-disk SVBRDF datasets.
    #[command(subcommand)]
    Svbrdf(SvbrdfCommand),
    /// Train M_est, ND_enc + M_render (and the discriminator) on SVBRDF renders, or a baseline (--method).
    Train(train::TrainArgs),
    /// Curriculum stage 1: train a per-pixel teacher (GGX values -> neural code) with ND_enc + M_render on random pixels.
    TrainTeacher(train::TeacherArgs),
    /// Write a run's inference weights (M_est, ND_enc, M_render, or the baseline's network), method and configuration to one file.
    Export(train::ExportArgs),
    /// Average the weights of several exported models of one run (late checkpoints) into one model file.
    Average(train::AverageArgs),
    /// Estimate a neural material (.nmat) from one flash photo (or one each from several photos or a folder), or one from all
    /// photos of a capture folder (--capture).
    Estimate(infer::EstimateArgs),
    /// Phone photos of the printed frame to a capture folder (tags, camera poses, rectified sample), or with --estimate
    /// to one material; `capture frame` writes the frame to print.
    Capture(capture::CaptureCommandArgs),
    /// Render a neural material (or a photo, estimated first) under a new light and view, or an orbit GIF.
    Relight(infer::RelightArgs),
    /// One picture of a neural material: photo, neural map (norm, PCA), identity render, relit views.
    Show(infer::ShowArgs),
    /// Write a neural material (or a photo, estimated first) as one self-contained HTML page that relights it live (WebGL2).
    View(view::ViewArgs),
    /// Fit GGX maps per pixel to a neural material (or a photo, estimated first) and export them: PNG/EXR maps, glTF, MatFusion layout.
    Fit(fit::FitArgs),
    /// Score models (flashmat and baseline model files) and the print-out baseline against GGX renders (Reflect / Identity / Hemisphere).
    Eval(eval::EvalArgs),
    /// The shadows experiment: score models on shadowed GGX renders (height-field shadows) against the un-shadowed GGX of the true maps.
    ShadowEval(eval::ShadowEvalArgs),
    /// Reference rows (pixel parameters, wi, wo, M_render output) of a neural material, as JSON.
    NmatRows(nmat_rows::NmatRowsArgs),
    /// Speed benchmarks (ratios against a baseline measured in the same run).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

#[derive(Subcommand, Debug)]
pub enum SvbrdfCommand {
    /// Write procedural materials in the MatFusion folder layout (diffuse/ specular/ normals/ roughness/).
    Generate(GenerateArgs),
    /// Draw a grid of maps and a co-located render for each material of a dataset.
    Preview(PreviewArgs),
    /// Write a synthetic capture folder of a material (8-bit flash photos with 1/r^2 fall-off, camera_pos.txt,
    /// light_pos.txt, image_size.txt): the format `eval --captures` reads.
    Captures(CapturesArgs),
}

#[derive(Args, Debug)]
pub struct CapturesArgs {
    #[command(flatten)]
    pub material: MaterialArgs,
    /// Output folder (created).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Photos: one straight overhead, the others co-located flash photos around the sample (elevations 65/50/35 degrees).
    #[arg(long, default_value_t = 9)]
    pub photos: usize,
    /// The sample's width, the unit of the written positions (e.g. centimetres).
    #[arg(long, default_value_t = 10.0)]
    pub sample_width: f64,
}

/// A 3-vector given as `X,Y,Z` ([`flashmat::geometry::parse_position`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Vec3Arg(pub [f64; 3]);

impl std::str::FromStr for Vec3Arg {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        flashmat::geometry::parse_position(s).map(Self)
    }
}

/// clap parser of a number that must be finite and > 0 (`--grad-clip`,
/// `--lr`): NaN, Inf, 0 and negatives have no meaning there.
pub fn positive_number(s: &str) -> std::result::Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite number > 0")),
        Err(_) => Err(format!("'{s}' is not a number")),
    }
}

/// clap parser of a probability: a number in [0, 1].
pub fn fraction(s: &str) -> std::result::Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        Ok(v) => Err(format!("{v} is not a number from 0 to 1")),
        Err(_) => Err(format!("'{s}' is not a number")),
    }
}

/// clap parser of a count of items held in memory: 1 to
/// [`flashmat::limits::COUNT`] (`--limit 0` would average nothing).
pub fn count(s: &str) -> std::result::Result<usize, String> {
    let n: usize = s.trim().parse().map_err(|_| format!("'{s}' is not a whole number"))?;
    if n == 0 {
        return Err("must be at least 1".into());
    }
    flashmat::limits::COUNT.check("it", n as u64).map_err(|e| e.to_string())?;
    Ok(n)
}

/// Which material to use: a dataset path (with --index), or `procedural:SEED[:FAMILY]`.
#[derive(Args, Debug, Clone)]
pub struct MaterialArgs {
    /// Material source: a folder in the MatFusion or per-material layout, an INRIA strip PNG (or a folder of
    /// them), `procedural:SEED` / `procedural:SEED:FAMILY` for a built-in procedural material, or `procedural-test:I`
    /// for held-out material I (0-49; `testII` of `flashmat eval`).
    #[arg(long = "svbrdf", value_name = "SOURCE")]
    pub source: String,
    /// Which material of a multi-material source (0-based, sorted by name).
    #[arg(long, default_value_t = 0)]
    pub index: usize,
    /// Resolution of procedural materials (loaded maps keep their size).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
}

#[derive(Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub material: MaterialArgs,
    /// Point light position X,Y,Z (the material spans [-1,1]^2 at z = 0; z must be > 0).
    /// Default: co-located with the camera.
    #[arg(long, value_name = "X,Y,Z")]
    pub light: Option<Vec3Arg>,
    /// Camera position X,Y,Z (z must be > 0). Default: straight overhead at the 28 degree model FOV distance.
    #[arg(long, value_name = "X,Y,Z")]
    pub view: Option<Vec3Arg>,
    /// Output image: .png (8-bit sRGB, as estimate reads photos) or .exr (linear HDR radiance).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Cast shadows from the material's height field (maps loaded from disk get one integrated from their normals).
    #[arg(long)]
    pub shadows: bool,
    /// Multiplies the height field for --shadows (plane units: the material spans [-1,1]).
    #[arg(long, default_value_t = 1.0, requires = "shadows")]
    pub height_scale: f64,
    /// Radius of a disc light for soft shadows (plane units; 0: point light, hard shadows).
    #[arg(long, default_value_t = 0.0, requires = "shadows")]
    pub light_radius: f64,
    /// Points sampled on the disc light (--light-radius > 0).
    #[arg(long, default_value_t = 16, requires = "shadows")]
    pub light_samples: usize,
    /// Renderer: the batched tensor ops or the f32 CPU renderer of the training data.
    #[arg(long, value_enum, default_value_t = Renderer::Tensor)]
    pub renderer: Renderer,
    /// Keep only the centre ROWS rows of the material (a landscape rectangle: its shorter side, the rows,
    /// spans [-1, 1], the longer one [-a, a]); default: all rows. Not with --shadows (square only).
    #[arg(long, value_name = "ROWS", conflicts_with = "shadows")]
    pub rows: Option<usize>,
}

/// Which implementation renders `flashmat render`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Renderer {
    Tensor,
    Cpu,
}

#[derive(Args, Debug)]
pub struct GenerateArgs {
    /// Number of materials.
    #[arg(long, default_value_t = 16)]
    pub count: usize,
    /// Output root folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Resolution in pixels.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// First index of the procedural training stream (materials are deterministic per index).
    #[arg(long, default_value_t = 0)]
    pub start: u64,
    /// Write the 50 held-out test materials instead of training materials (per-material layout).
    #[arg(long)]
    pub test_set: bool,
}

#[derive(Args, Debug)]
pub struct PreviewArgs {
    /// Dataset folder or strip file, or `procedural` for the procedural training stream,
    /// or `procedural-test` for the held-out set. A dataset material that cannot be read is
    /// left out and named, and the command then exits with 1.
    pub source: String,
    /// Output PNG.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Maximum number of materials shown.
    #[arg(long, default_value_t = 12)]
    pub count: usize,
    /// Cell size in pixels.
    #[arg(long, default_value_t = 128)]
    pub size: usize,
}

/// Resolves render positions: defaults are the co-located input configuration.
pub fn light_view(light: Option<Vec3Arg>, view: Option<Vec3Arg>) -> Result<LightView> {
    flashmat::geometry::light_view_or_input(light.map(|v| v.0), view.map(|v| v.0))
}

/// Folders that [`prepare_output`] created for an output. Dropped without
/// [`OutputDir::keep`] (an error on the way), it removes them again while
/// they are empty, so a failed command leaves no folder behind.
#[must_use = "dropping it removes the folders it created"]
pub struct OutputDir {
    /// Created folders, deepest first.
    created: Vec<std::path::PathBuf>,
}

impl OutputDir {
    /// The output was written: keep its folders.
    pub fn keep(mut self) {
        self.created.clear();
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        for d in &self.created {
            // Only empty folders go: remove_dir refuses any other.
            let _ = std::fs::remove_dir(d);
        }
    }
}

/// Makes sure the folder that will hold `path` exists (creating it and
/// its missing parents) and that `path` is not a folder or a special file.
/// Call [`OutputDir::keep`] once the output is written.
pub fn prepare_output(path: &std::path::Path) -> Result<OutputDir> {
    let mut guard = OutputDir { created: Vec::new() };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        let mut missing = Some(dir);
        while let Some(d) = missing.filter(|d| !d.as_os_str().is_empty() && std::fs::symlink_metadata(d).is_err()) {
            guard.created.push(d.to_path_buf());
            missing = d.parent();
        }
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create output folder {}", dir.display()))?;
    }
    if let Ok(m) = std::fs::symlink_metadata(path) {
        if !m.is_file() && !m.file_type().is_symlink() {
            bail!("cannot write {}: it exists and is not a regular file", path.display());
        }
    }
    Ok(guard)
}

/// What to lower when `command` runs out of memory: the end of its one
/// error line (`main`; the line's start is `flashmat::limits::out_of_memory`).
pub fn memory_hint(command: &Command) -> &'static str {
    match command {
        Command::Train(_) => "lower --batch, --crop or --outputs",
        Command::TrainTeacher(_) => "lower --pixels",
        Command::Estimate(_) | Command::Capture(_) | Command::Relight(_) | Command::Show(_) | Command::View(_) | Command::Fit(_) => {
            "lower --max-memory (M_est then runs in tiles) or --size"
        }
        Command::Bench(_) => "lower --max-memory (bench infer: M_est then runs in tiles), --size, --crop or --batch",
        Command::Render(_) | Command::Svbrdf(_) | Command::Eval(_) | Command::ShadowEval(_) => "lower --size",
        Command::Export(_) | Command::Average(_) | Command::NmatRows(_) => "free memory or use a machine with more",
    }
}

pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Render(a) => materials::render(&a),
        Command::Svbrdf(SvbrdfCommand::Generate(a)) => materials::generate(&a),
        Command::Svbrdf(SvbrdfCommand::Preview(a)) => materials::preview(&a),
        Command::Svbrdf(SvbrdfCommand::Captures(a)) => materials::captures(&a),
        Command::Estimate(a) => infer::estimate(&a),
        Command::Capture(a) => capture::run(&a),
        Command::Relight(a) => infer::relight(&a),
        Command::Show(a) => infer::show(&a),
        Command::View(a) => view::view(&a),
        Command::Fit(a) => fit::fit(&a),
        Command::NmatRows(a) => nmat_rows::nmat_rows(&a),
        Command::Train(a) => train::train(&a),
        Command::TrainTeacher(a) => train::train_teacher(&a),
        Command::Export(a) => train::export(&a),
        Command::Average(a) => train::average(&a),
        Command::Eval(a) => eval::eval(&a),
        Command::ShadowEval(a) => eval::shadow_eval(&a),
        Command::Bench(b) => bench::run(&b),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vec3_parsing() {
        assert_eq!("1,2.5,-3".parse::<Vec3Arg>().unwrap(), Vec3Arg([1.0, 2.5, -3.0]));
        assert_eq!(" 0, 0 ,4".parse::<Vec3Arg>().unwrap(), Vec3Arg([0.0, 0.0, 4.0]));
        assert!("1,2".parse::<Vec3Arg>().is_err());
        assert!("1,x,3".parse::<Vec3Arg>().is_err());
        assert!("1,nan,3".parse::<Vec3Arg>().is_err());
        assert!("1e308,0,1".parse::<Vec3Arg>().unwrap_err().contains("beyond"));
        assert_eq!("-1e6,0,1e6".parse::<Vec3Arg>().unwrap(), Vec3Arg([-1e6, 0.0, 1e6]));
    }

    #[test]
    fn option_parsers_refuse_meaningless_values() {
        assert_eq!(positive_number("0.5"), Ok(0.5));
        for bad in ["0", "-1", "nan", "inf", "x"] {
            assert!(positive_number(bad).is_err(), "{bad}");
        }
        assert_eq!(count("3"), Ok(3));
        for bad in ["0", "-1", "1000000000000", "x"] {
            assert!(count(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn positions_must_be_above_the_surface() {
        let lv = light_view(None, None).unwrap();
        assert_eq!(lv, LightView::colocated(28.0));
        let e = light_view(Some(Vec3Arg([0.0, 0.0, -1.0])), None).unwrap_err();
        assert!(e.to_string().contains("light position 0,0,-1 is not above the surface"));
        assert!(light_view(None, Some(Vec3Arg([1.0, 1.0, 0.0]))).is_err());
    }
}
