//! Before/after pictures of the refinement on the photo (`--refine`) for the
//! bundled real photos, with the bundled model:
//!
//! ```sh
//! cargo run --release --example refine_photos -- [STEPS] [OUT_DIR]   # defaults: 100, reports/refine
//! ```
//!
//! Writes `OUT_DIR/photos.jpg` (a row per photo: photo | identity before |
//! identity after | side light before | side light after, at 128 pixels)
//! and `OUT_DIR/photos.md` (identity L1 of log radiance before and after,
//! seconds per photo).

use anyhow::{Context, Result};
use flashmat::geometry::LightView;
use flashmat::image::Image;
use flashmat::infer::refine::{refine, RefineConfig};
use flashmat::infer::{estimate, load_model, load_photo, overhead_camera, NeuralMaterial};
use std::path::PathBuf;

/// Cell size of the picture.
const CELL: usize = 128;
/// The side light of the comparison (as in `flashmat show`'s first orbit frame).
const SIDE_LIGHT: [f64; 3] = [2.0, 0.0, 3.0];

fn display(linear: &Image) -> Image {
    linear.to_display().resize_to(CELL, CELL)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let steps: usize = args.get(1).map_or(Ok(flashmat::infer::refine::DEFAULT_REFINE_STEPS), |s| s.parse()).context("STEPS must be a whole number")?;
    let out = PathBuf::from(args.get(2).map_or("reports/refine", String::as_str));
    let photos = flashmat::eval::photos::bundled_photos()?;
    let loaded = load_model(None, tch::Device::Cpu)?;
    let cfg = RefineConfig::with_steps(steps);
    let side = LightView { light: SIDE_LIGHT, view: overhead_camera() };
    let mut rows = vec![];
    let mut table = format!(
        "# Refinement on the bundled photos\n\n`cargo run --release --example refine_photos -- {steps}`: bundled model, \
         {steps} steps ({cfg:?}), 256x256, `--fov 28`.\nColumns of `photos.jpg`: photo | identity before | identity after | \
         light at {SIDE_LIGHT:?} before | after.\n\n| photo | identity L1 before | after | seconds |\n|---|---|---|---|\n"
    );
    for path in &photos {
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let photo = load_photo(path, Some(flashmat::eval::photos::PHOTO_FOV_DEG), 256)?;
        let unrefined = estimate(&loaded.model, &loaded.info, &photo)?;
        let mut refined = estimate(&loaded.model, &loaded.info, &photo)?;
        let report = refine(&mut refined, &photo.linear.to_tensor(), photo.ldr, &cfg, |_| {})?;
        eprintln!("{name}: {}", report.summary());
        table.push_str(&format!(
            "| {name} | {:.4} | {:.4} | {:.1} |\n",
            report.identity_l1_before, report.identity_l1_after, report.seconds
        ));
        let render = |m: &NeuralMaterial, c: &LightView| m.render_image(c).map(|im| display(&im));
        let identity = NeuralMaterial::identity_config();
        rows.push(vec![
            display(&photo.linear),
            render(&unrefined, &identity)?,
            render(&refined, &identity)?,
            render(&unrefined, &side)?,
            render(&refined, &side)?,
        ]);
    }
    std::fs::create_dir_all(&out)?;
    let grid = flashmat::viz::grid(&rows, 2)?;
    flashmat::io::write_jpeg(&out.join("photos.jpg"), &grid, 85)?;
    flashmat::io::atomic_write_bytes(&out.join("photos.md"), table.as_bytes())?;
    eprintln!("wrote {} and photos.md", out.join("photos.jpg").display());
    Ok(())
}
