//! Photos in: decoding to linear radiance, the field-of-view crop and the
//! anti-aliased resize to the model resolution.
//!
//! The model's input camera sees the material square [-1,1]^2 with a 28
//! degree field of view from straight above (REFERENCE section 1). A photo
//! taken with a wider lens shows more: its centre square is cropped to the
//! fraction `fov_crop_ratio(fov)` = tan(14 deg) / tan(fov / 2) of its side,
//! so the kept pixels span the same view angles as the model's camera, and
//! then shrunk to the model resolution.

use crate::geometry::{fov_crop_ratio, MODEL_FOV_DEG};
use crate::image::Image;
use crate::io::read_image_with_format;
use anyhow::{bail, ensure, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Default field of view of PNG/JPEG photos: a typical phone main camera
/// across the shorter side of the picture.
pub const PHONE_FOV_DEG: f64 = 45.0;

/// Widest accepted field of view (the crop ratio vanishes at 180 degrees).
pub const MAX_FOV_DEG: f64 = 170.0;

/// Where the model's view was cut from the source photo, in source pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Crop {
    /// Left column of the crop.
    pub x0: usize,
    /// Top row of the crop.
    pub y0: usize,
    /// Side of the square crop.
    pub side: usize,
    pub source_width: usize,
    pub source_height: usize,
}

/// A photo ready for M_est.
#[derive(Clone, Debug)]
pub struct PreparedPhoto {
    /// Linear RGB `[3, S, S]` at the model resolution. 8-bit photos are
    /// gamma-decoded (^2.2) and lie in [0, 1]; EXR values are kept as-is.
    pub linear: Image,
    /// The photo is a display-encoded 8/16-bit PNG or JPEG (LDR) rather
    /// than a linear EXR (HDR).
    pub ldr: bool,
    /// Field of view across the photo's shorter side, in degrees.
    pub fov_deg: f64,
    pub crop: Crop,
    /// File name of the source (no folders).
    pub source: String,
}

impl PreparedPhoto {
    /// A square linear photo `[3, S, S]` already at the model's 28 degree
    /// co-located view (renders, evaluation photos): no crop.
    pub fn at_model_view(linear: Image, ldr: bool, source: impl Into<String>) -> Self {
        let (side, width, height) = (linear.width, linear.width, linear.height);
        Self {
            linear,
            ldr,
            fov_deg: crate::geometry::MODEL_FOV_DEG,
            crop: Crop { x0: 0, y0: 0, side, source_width: width, source_height: height },
            source: source.into(),
        }
    }
}

/// Default field of view for a photo type: phone photos for 8-bit files,
/// the model's own camera for EXR renders (as made by `flashmat render`).
pub fn default_fov(ldr: bool) -> f64 {
    if ldr {
        PHONE_FOV_DEG
    } else {
        MODEL_FOV_DEG
    }
}

/// Checks a resolution for M_est (its U-Net halves three times; memory
/// grows with its square, see [`crate::limits::MODEL_SIZE`]).
pub fn check_size(size: usize) -> Result<()> {
    ensure!(size >= 8 && size.is_multiple_of(8), "--size must be a positive multiple of 8, got {size}");
    crate::limits::MODEL_SIZE.check("--size", size as u64)
}

/// Checks a field of view: a photo narrower than the model's camera does
/// not show the whole material square the model expects.
pub fn check_fov(fov_deg: f64) -> Result<()> {
    ensure!(
        fov_deg.is_finite() && (MODEL_FOV_DEG - 1e-9..=MAX_FOV_DEG).contains(&fov_deg),
        "--fov must be between {MODEL_FOV_DEG} and {MAX_FOV_DEG} degrees (the model's camera sees {MODEL_FOV_DEG} degrees; a narrower photo shows too little), got {fov_deg}"
    );
    Ok(())
}

/// The centre crop of a `width x height` photo that a `fov_deg` camera
/// shares with the model's 28 degree camera: the centred square of the
/// shorter side, scaled by [`fov_crop_ratio`]. The side is rounded to the
/// parity of the square so the crop stays exactly centred (at most 1 pixel
/// of rounding).
pub fn fov_crop(width: usize, height: usize, fov_deg: f64) -> Result<Crop> {
    check_fov(fov_deg)?;
    let q = width.min(height);
    let exact = q as f64 * fov_crop_ratio(fov_deg).min(1.0);
    // Nearest integer of the same parity as q.
    let side = (q as f64 - 2.0 * ((q as f64 - exact) / 2.0).round()).max(0.0) as usize;
    let side = side.min(q);
    Ok(Crop { x0: (width - side) / 2, y0: (height - side) / 2, side, source_width: width, source_height: height })
}

/// Crops a linear `[C, H, W]` photo to the model's view and shrinks it to
/// `size x size`. Errors when the crop has fewer than `size` pixels across,
/// saying how large a photo is needed.
pub fn prepare_image(linear: &Image, fov_deg: f64, size: usize) -> Result<(Image, Crop)> {
    check_size(size)?;
    let crop = fov_crop(linear.width, linear.height, fov_deg)?;
    if crop.side < size {
        // Smallest shorter side whose crop still holds `size` pixels.
        let need = (size as f64 / fov_crop_ratio(fov_deg) - 1e-9).ceil() as usize;
        bail!(
            "the photo is too small: {}x{} pixels, cropped to the model's {MODEL_FOV_DEG} degree view (--fov {fov_deg}), keeps {}x{} pixels, but --size {size} needs at least {size}x{size} (a photo whose shorter side is at least {need} pixels)",
            linear.width,
            linear.height,
            crop.side,
            crop.side
        );
    }
    let cut = linear.crop(crop.y0, crop.x0, crop.side, crop.side)?;
    Ok((cut.resize_area(size, size), crop))
}

/// Reads and prepares a photo: PNG/JPEG are LDR and gamma-decoded to
/// linear (^2.2, REFERENCE section 3), EXR is linear HDR (NaN/Inf refused
/// by the reader). `fov_deg` defaults by type (see [`default_fov`]).
/// Errors name the file.
pub fn load_photo(path: &Path, fov_deg: Option<f64>, size: usize) -> Result<PreparedPhoto> {
    check_size(size)?;
    if let Some(f) = fov_deg {
        check_fov(f)?;
    }
    let (image, format) = read_image_with_format(path)?;
    let ldr = !format.is_float();
    let rgb = crate::io::to_rgb(&image);
    let linear = if ldr { rgb.map(crate::spaces::gamma_decode) } else { rgb };
    let fov = fov_deg.unwrap_or_else(|| default_fov(ldr));
    let (linear, crop) = prepare_image(&linear, fov, size).map_err(|e| anyhow::anyhow!("{}: {e:#}", path.display()))?;
    let source = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    Ok(PreparedPhoto { linear, ldr, fov_deg: fov, crop, source })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{direction_maps, fov_to_distance, pixel_positions};
    use crate::svbrdf::render::render_directions;
    use tch::{Device, Kind, Tensor};

    #[test]
    fn crop_geometry() {
        // 28 degrees keeps the whole centre square.
        assert_eq!(fov_crop(300, 200, 28.0).unwrap(), Crop { x0: 50, y0: 0, side: 200, source_width: 300, source_height: 200 });
        // 45 degrees keeps 0.6019 of the side; parity of the square kept.
        let c = fov_crop(638, 638, 45.0).unwrap();
        assert_eq!((c.x0, c.y0, c.side), (127, 127, 384));
        let c = fov_crop(1001, 2000, 45.0).unwrap();
        assert_eq!(c.side % 2, 1);
        assert!((c.side as f64 - 1001.0 * fov_crop_ratio(45.0)).abs() <= 1.0);
        assert_eq!((c.x0, c.y0), ((1001 - c.side) / 2, (2000 - c.side) / 2));
        assert!(fov_crop(100, 100, 20.0).unwrap_err().to_string().contains("between 28 and"));
        assert!(fov_crop(100, 100, f64::NAN).is_err());
        assert!(fov_crop(100, 100, 180.0).is_err());
    }

    #[test]
    fn too_small_photo_says_what_is_needed() {
        let im = Image::filled(3, 300, 400, 0.5);
        let e = prepare_image(&im, 45.0, 256).unwrap_err().to_string();
        // 300 * 0.6019 = 180.6 -> 180 (even) pixels kept; 256 / 0.6019 = 425.3.
        assert!(e.contains("keeps 180x180") && e.contains("at least 426 pixels"), "{e}");
        let (p, c) = prepare_image(&im, 28.0, 256).unwrap();
        assert_eq!((p.height, p.width, c.side, c.x0), (256, 256, 300, 50));
        assert!(check_size(60).is_err() && check_size(0).is_err());
    }

    /// Renders GGX maps `[1, 10, N, N]` covering the plane window
    /// [-t, t]^2 (instead of [-1, 1]^2) with light and camera at `eye`:
    /// what a camera with a wider FOV at the same height photographs.
    fn render_window(maps: &Tensor, t: f64, eye: [f64; 3]) -> Tensor {
        let n = maps.size()[2] as usize;
        let pos = pixel_positions(n, n, (Kind::Double, Device::Cpu)) * Tensor::from_slice(&[t, t, 0.0]).view([3, 1, 1]);
        let eye = Tensor::from_slice(&eye).view([1, 3]);
        let dir = direction_maps(&pos, &eye).unsqueeze(0); // [1, 1, 3, N, N]
        render_directions(&maps.to_kind(Kind::Double), &dir, &dir).get(0).get(0)
    }

    /// A 45 degree photo, cropped and shrunk by `prepare_image`, equals the
    /// 28 degree photo of the same material from the same height.
    ///
    /// The 45 degree camera at d = fov_to_distance(28) sees [-t, t]^2 with
    /// t = d tan(22.5 deg) = 1.6613. A 638-pixel render of that window
    /// keeps 384 pixels (638 x 0.601937 = 384.04), whose 384-pixel centre
    /// of the maps is exactly the material square [-1, 1]^2 rendered by the
    /// 28 degree camera, up to 0.04 pixel of scale. Both sides are then
    /// area-averaged to 64. Measured worst difference |a - b| / max(b, 0.05):
    /// 3.9e-4 (from the 0.01% scale mismatch at sharp tile edges); the
    /// tolerance is 2e-3. The uncropped photo differs by more than 0.05.
    #[test]
    fn fov_crop_matches_the_model_camera() {
        let d = fov_to_distance(MODEL_FOV_DEG);
        let t = d * (45f64.to_radians() / 2.0).tan();
        let big = crate::data::procedural::generate_family(crate::data::procedural::Family::Tiles, 5, 638);
        let maps = big.stacked().to_tensor().unsqueeze(0);
        let wide = Image::from_tensor(&render_window(&maps, t, [0.0, 0.0, d])).unwrap();
        let (prepared, crop) = prepare_image(&wide, 45.0, 64).unwrap();
        assert_eq!((crop.x0, crop.y0, crop.side), (127, 127, 384));

        let centre = maps.narrow(2, 127, 384).narrow(3, 127, 384);
        let narrow = Image::from_tensor(&render_window(&centre, 1.0, [0.0, 0.0, d])).unwrap();
        let reference = narrow.resize_area(64, 64);
        let worst = prepared.data.iter().zip(&reference.data).map(|(a, b)| (a - b).abs() / b.abs().max(0.05)).fold(0f32, f32::max);
        eprintln!("FOV crop vs 28 degree render: worst relative difference {worst:.2e}");
        assert!(worst < 2e-3, "{worst}");
        // Sanity: the uncropped wide photo is far from it.
        let uncropped = wide.resize_area(64, 64);
        let off = uncropped.data.iter().zip(&reference.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(off > 0.05, "{off}");
    }
}
