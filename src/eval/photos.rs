//! The photo check: the real flash photos bundled in `examples/photos`
//! estimated and re-rendered under their own light (identity), each
//! render compared with its photo. Real photos have no ground truth
//! beyond themselves, so this measures what survives the round trip: the
//! photo's structure (L1 of ln(1 + R)), its colour (the chromaticity error
//! of the mean colour, as in the uniform-colour check) and the 2x2
//! checkerboard of the upsampling. The uniform-colour check does not
//! predict the photos' colour (`reports/bundled-13500.md`: colour
//! augmentation halved its error and left the photos' magenta cast), so
//! training logs both at every checkpoint.

use super::metrics::{checkerboard_amplitude, log_l1};
use super::uniform::{chromaticity_distance, mean_colour};
use crate::image::Image;
use crate::infer::{self, NeuralMaterial};
use crate::model::{Model, ModelInfo};
use anyhow::{Context, Result};
use serde::Serialize;
use std::path::PathBuf;

/// The bundled photos are already cropped to the material: the model's own
/// field of view, no further crop (as `scripts/demo.sh` passes them).
pub const PHOTO_FOV_DEG: f64 = 28.0;

/// The PNG and JPEG photos of `examples/photos` under [`crate::bundled_root`],
/// sorted by name; empty when the folder is not there (a binary run away
/// from its repository without `FLASHMAT_ROOT`).
pub fn bundled_photos() -> Result<Vec<PathBuf>> {
    let dir = crate::bundled_root().join("examples/photos");
    if !dir.is_dir() {
        return Ok(vec![]);
    }
    let mut photos: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| format!("{}: cannot list the bundled photos", dir.display()))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()?;
    photos.retain(|p| matches!(p.extension().and_then(|e| e.to_str()), Some("png" | "jpg")));
    photos.sort();
    Ok(photos)
}

/// An identity render against its photo.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PhotoScore {
    /// Mean |ln(1 + render) - ln(1 + photo)| over pixels and channels.
    pub log_l1: f64,
    /// Distance of the mean colours' chromaticities rgb / (r + g + b).
    pub chroma_error: f64,
    /// Period-2 amplitude of the render beyond the photo's.
    pub checkerboard: f64,
}

/// identity: `[3, H, W]` render under the photo's own light; photo: the
/// linear photo the material was estimated from, same size.
pub fn score_identity(identity: &Image, photo: &Image) -> Result<PhotoScore> {
    Ok(PhotoScore {
        log_l1: log_l1(identity, photo)?,
        chroma_error: chromaticity_distance(mean_colour(identity), mean_colour(photo)),
        checkerboard: checkerboard_amplitude(identity, photo)?,
    })
}

/// Means of [`PhotoScore`] over the bundled photos.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PhotoSummary {
    pub photos: usize,
    pub mean: PhotoScore,
}

/// Each bundled photo estimated at `size` x `size` (a multiple of 8) and
/// scored on its identity render; `None` when the photos are not there.
pub fn photo_check(model: &Model, info: &ModelInfo, size: usize) -> Result<Option<PhotoSummary>> {
    let photos = bundled_photos()?;
    if photos.is_empty() {
        return Ok(None);
    }
    let identity = NeuralMaterial::identity_config();
    let scores = tch::no_grad(|| {
        photos
            .iter()
            .map(|path| {
                let photo = infer::load_photo(path, Some(PHOTO_FOV_DEG), size)?;
                let render = infer::estimate(model, info, &photo)?.render_image(&identity)?;
                score_identity(&render, &photo.linear)
            })
            .collect::<Result<Vec<_>>>()
    })?;
    let n = scores.len() as f64;
    let mean = |f: fn(&PhotoScore) -> f64| scores.iter().map(f).sum::<f64>() / n;
    Ok(Some(PhotoSummary {
        photos: scores.len(),
        mean: PhotoScore { log_l1: mean(|s| s.log_l1), chroma_error: mean(|s| s.chroma_error), checkerboard: mean(|s| s.checkerboard) },
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(colour: [f32; 3], size: usize) -> Image {
        Image::from_fn(3, size, size, |c, _, _| colour[c])
    }

    #[test]
    fn a_photo_scores_zero_against_itself_and_a_colour_swap_its_chromaticity_distance() {
        let photo = flat([0.2, 0.4, 0.4], 16);
        assert_eq!(score_identity(&photo, &photo).unwrap(), PhotoScore { log_l1: 0.0, chroma_error: 0.0, checkerboard: 0.0 });
        // Chromaticities (0.2, 0.4, 0.4) and (0.4, 0.4, 0.2): distance sqrt(0.2^2 + 0.2^2).
        let swapped = flat([0.4, 0.4, 0.2], 16);
        let s = score_identity(&swapped, &photo).unwrap();
        assert!((s.chroma_error - 0.08f64.sqrt()).abs() < 1e-6, "{s:?}");
        // |ln 1.4 - ln 1.2| on two of three channels.
        assert!((s.log_l1 - 2.0 / 3.0 * (1.4f64 / 1.2).ln()).abs() < 1e-6, "{s:?}");
        // A brighter render of the same colour keeps the chromaticity.
        assert!(score_identity(&flat([0.4, 0.8, 0.8], 16), &photo).unwrap().chroma_error < 1e-7);
    }

    #[test]
    fn the_bundled_photos_are_found_and_checked() {
        let photos = bundled_photos().unwrap();
        assert_eq!(photos.len(), 13, "{photos:?}");
        let model = Model::new(&crate::model::ModelConfig::tiny(), tch::Device::Cpu).unwrap();
        let info = ModelInfo { ldr_input: true, steps: 0 };
        let summary = photo_check(&model, &info, 32).unwrap().unwrap();
        assert_eq!(summary.photos, 13);
        let m = summary.mean;
        assert!(m.log_l1.is_finite() && m.log_l1 > 0.0 && m.chroma_error.is_finite() && m.checkerboard >= 0.0, "{m:?}");
    }
}
