//! Before/after pictures of two models on the bundled real photos (the
//! bundled model's replacement, issue 15):
//!
//! ```sh
//! cargo run --release --example compare_models -- OLD_MODEL NEW_MODEL OUT.jpg [ZOOM.jpg]
//! ```
//!
//! A row per photo: photo | identity old | identity new | side light old |
//! side light new, 96 pixels a cell; prints the identity L1 of log
//! radiance against the photo per model, the chromaticity error of the
//! identity render's mean colour (a photo's own colour kept or lost), and
//! the identity render's checkerboard amplitude beyond the photo's
//! (`flashmat::eval::metrics::checkerboard_amplitude`). ZOOM.jpg: for the
//! four photos with the strongest checkerboard of either model, the centre
//! 48 x 48 pixels of the photo and of both identity renders (at 256),
//! enlarged 4x pixel for pixel.

use anyhow::{bail, ensure, Result};
use flashmat::eval::photos::{bundled_photos, score_identity, PHOTO_FOV_DEG};
use flashmat::geometry::LightView;
use flashmat::image::Image;
use flashmat::infer::{estimate, load_model, load_photo, overhead_camera, NeuralMaterial};
use std::path::PathBuf;

/// Cell size of the picture.
const CELL: usize = 96;
/// Side of the zoomed centre crops, and their enlargement.
const ZOOM_CROP: usize = 48;
const ZOOM: usize = 4;

/// The centre `ZOOM_CROP` square of a linear image, display-encoded and
/// enlarged `ZOOM` x by pixel replication (so a 2x2 pattern stays visible).
fn zoomed(linear: &Image) -> Result<Image> {
    let (top, left) = ((linear.height - ZOOM_CROP) / 2, (linear.width - ZOOM_CROP) / 2);
    let crop = linear.crop(top, left, ZOOM_CROP, ZOOM_CROP)?.to_display();
    Ok(Image::from_fn(crop.channels, ZOOM_CROP * ZOOM, ZOOM_CROP * ZOOM, |c, y, x| crop.get(c, y / ZOOM, x / ZOOM)))
}

/// The side light of the comparison (as in `flashmat show`'s first orbit frame).
const SIDE_LIGHT: [f64; 3] = [2.0, 0.0, 3.0];

fn display(linear: &Image) -> Image {
    linear.to_display().resize_to(CELL, CELL)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (old, new, out, zoom_out) = match args.as_slice() {
        [old, new, out] => (old, new, out, None),
        [old, new, out, zoom] => (old, new, out, Some(zoom)),
        _ => bail!("usage: compare_models OLD_MODEL NEW_MODEL OUT.jpg [ZOOM.jpg]"),
    };
    let models = [load_model(Some(&PathBuf::from(old)), tch::Device::Cpu)?, load_model(Some(&PathBuf::from(new)), tch::Device::Cpu)?];
    let photos = bundled_photos()?;
    ensure!(!photos.is_empty(), "no photos in {}", flashmat::bundled_root().join("examples/photos").display());
    let side = LightView { light: SIDE_LIGHT, view: overhead_camera() };
    let identity = NeuralMaterial::identity_config();
    let mut rows = vec![];
    // (strongest checkerboard of the two models, zoomed row) per photo.
    let mut zoom_rows: Vec<(f64, Vec<Image>)> = vec![];
    let mut sums = [0.0; 6];
    println!("| photo | identity log-L1, old | new | chromaticity error, old | new | checkerboard, old | new |\n|---|---|---|---|---|---|---|");
    for path in &photos {
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let photo = load_photo(path, Some(PHOTO_FOV_DEG), 256)?;
        let materials = [estimate(&models[0].model, &models[0].info, &photo)?, estimate(&models[1].model, &models[1].info, &photo)?];
        let identities = [materials[0].render_image(&identity)?, materials[1].render_image(&identity)?];
        let (old_score, new_score) = (score_identity(&identities[0], &photo.linear)?, score_identity(&identities[1], &photo.linear)?);
        let errors = [old_score.log_l1, new_score.log_l1, old_score.chroma_error, new_score.chroma_error, old_score.checkerboard, new_score.checkerboard];
        for (sum, e) in sums.iter_mut().zip(errors) {
            *sum += e;
        }
        println!("| {name} | {:.4} | {:.4} | {:.3} | {:.3} | {:.4} | {:.4} |", errors[0], errors[1], errors[2], errors[3], errors[4], errors[5]);
        if zoom_out.is_some() {
            zoom_rows.push((errors[4].max(errors[5]), vec![zoomed(&photo.linear)?, zoomed(&identities[0])?, zoomed(&identities[1])?]));
        }
        rows.push(vec![
            display(&photo.linear),
            display(&identities[0]),
            display(&identities[1]),
            display(&materials[0].render_image(&side)?),
            display(&materials[1].render_image(&side)?),
        ]);
    }
    let n = photos.len().max(1) as f64;
    let [a, b, c, d, e, f] = sums.map(|s| s / n);
    println!("| mean | {a:.4} | {b:.4} | {c:.3} | {d:.3} | {e:.4} | {f:.4} |");
    flashmat::io::write_jpeg(&PathBuf::from(out), &flashmat::viz::grid(&rows, 2)?, 80)?;
    eprintln!("wrote {out}");
    if let Some(zoom) = zoom_out {
        zoom_rows.sort_by(|a, b| b.0.total_cmp(&a.0));
        let strongest: Vec<Vec<Image>> = zoom_rows.into_iter().take(4).map(|(_, row)| row).collect();
        flashmat::io::write_jpeg(&PathBuf::from(zoom), &flashmat::viz::grid(&strongest, 4)?, 85)?;
        eprintln!("wrote {zoom}");
    }
    Ok(())
}
