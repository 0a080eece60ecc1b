//! `flashmat view`: a neural material (or a photo, estimated first as
//! `relight` does) as one self-contained HTML page that relights it live
//! in the browser (work done in `flashmat::viewer`).

use super::estimate_options::EstimateOptions;
use super::infer::open_material;
use super::{prepare_output, Vec3Arg};
use flashmat::geometry::above_surface;
use flashmat::geometry::LightView;
use flashmat::infer::NeuralMaterial;
use flashmat::viewer::{write_page, Bits, ViewerOptions};
use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct ViewArgs {
    /// A neural material (.nmat), or a photo (estimated first with the options below). Several, or a folder (its
    /// .nmat/.png/.jpg/.jpeg/.exr/.heic/.avif files), make a batch: one OUTDIR/NAME.html each.
    #[arg(required = true, num_args = 1.., value_name = "MATERIAL|DIR")]
    pub material: Vec<PathBuf>,
    /// Output page (.html): open it in a browser with WebGL2 (double-click; no server needed); for a batch, the
    /// output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Light position X,Y,Z the page opens with (default: the input photo's, co-located with the camera).
    #[arg(long, value_name = "X,Y,Z")]
    pub light: Option<Vec3Arg>,
    /// Camera position X,Y,Z the page opens with (default: overhead, as in the photo).
    #[arg(long, value_name = "X,Y,Z")]
    pub view: Option<Vec3Arg>,
    /// Storage of the neural map in the page: 8 bits per value with a per-channel scale, 16- or 32-bit floats, or
    /// auto: the smallest whose render stays within one display level (of 255) of the f32 material on five views.
    #[arg(long, value_enum, default_value_t = Bits::Auto)]
    pub map_bits: Bits,
    /// Storage of the ND_enc + M_render weights: 16- or 32-bit floats, or auto: 16 bits when they move the render by
    /// less than half a display level.
    #[arg(long, value_enum, default_value_t = Bits::Auto)]
    pub weight_bits: Bits,
    #[command(flatten)]
    pub estimate: EstimateOptions,
}

pub fn view(a: &ViewArgs) -> Result<()> {
    let batch = super::batch::is_batch(&a.material);
    match a.output.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
        _ if batch => {}
        Some("html" | "htm") => {}
        _ => bail!("{}: the output must end in .html", a.output.display()),
    }
    if a.weight_bits == Bits::Eight {
        bail!("--weight-bits takes 16, 32 or auto (8 bits are for the map only)");
    }
    let identity = NeuralMaterial::identity_config();
    let view = match a.view {
        Some(v) => above_surface("camera", v.0)?,
        None => identity.view,
    };
    let light = match a.light {
        Some(l) => above_surface("light", l.0)?,
        None => identity.light,
    };
    if batch {
        let mut extensions = super::batch::PHOTO_EXTENSIONS.to_vec();
        extensions.push("nmat");
        return super::batch::run_batch("view", &a.material, &extensions, &a.output, ".html", |input, output, _| {
            let (material, _) = open_material(input, &a.estimate)?;
            let relight_input = input.to_string_lossy().into_owned();
            let opts = ViewerOptions { map_bits: a.map_bits, weight_bits: a.weight_bits, initial: LightView { light, view }, relight_input };
            let report = write_page(&material, output, &opts)?;
            Ok(format!("{:.1} MB", report.bytes as f64 / 1e6))
        });
    }
    let input = &a.material[0];
    let out_dir = prepare_output(&a.output)?;
    let (material, summary) = open_material(input, &a.estimate)?;
    let relight_input = input.to_string_lossy().into_owned();
    let opts = ViewerOptions { map_bits: a.map_bits, weight_bits: a.weight_bits, initial: LightView { light, view }, relight_input };
    let report = write_page(&material, &a.output, &opts)?;
    out_dir.keep();
    summary.iter().for_each(|l| eprintln!("{l}"));
    eprintln!("{}", report.summary());
    let (h, w) = material.size();
    eprintln!(
        "wrote {} ({:.1} MB, {} preset, {w}x{h} map): open it in a browser, e.g. xdg-open {}",
        a.output.display(),
        report.bytes as f64 / 1e6,
        material.config.name,
        a.output.display()
    );
    Ok(())
}
