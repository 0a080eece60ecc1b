//! Photos in: decoding to linear radiance, the field-of-view crop and the
//! anti-aliased resize to the model resolution.
//!
//! The model's input camera sees the material from straight above with a
//! 28 degree field of view across the photo's shorter side, which spans
//! [-1, 1]; the longer side spans [-a, a], a = long / short, with the same
//! pixel pitch (REFERENCE section 1, `geometry::half_extents`). A photo
//! taken with a wider lens shows more: its centre is cropped to the
//! fraction `fov_crop_ratio(fov)` = tan(14 deg) / tan(fov / 2) of both
//! sides (a centred rectangle of the photo's aspect), so the kept pixels
//! span the same view angles as the model's camera, and then shrunk to the
//! model resolution: `--size` pixels on the shorter side, the longer side
//! rounded down to a multiple of [`SIZE_MULTIPLE`] (M_est halves three
//! times) with the crop trimmed to match, so pixels stay square. With
//! `--square` ([`PhotoOptions::square`]) only the centre square is kept.

use crate::geometry::{fov_crop_ratio, MODEL_FOV_DEG};
use crate::image::Image;
use crate::io::read_image_with_format;
use anyhow::{bail, ensure, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Widest accepted field of view (the crop ratio vanishes at 180 degrees).
pub const MAX_FOV_DEG: f64 = 170.0;

/// Longest accepted aspect ratio (long side / short side) of a photo
/// estimated as a rectangle: beyond it, crop the photo or pass `--square`.
pub const MAX_ASPECT: f64 = 4.0;

/// M_est's input sides must be multiples of this (three stride-2 stages).
pub const SIZE_MULTIPLE: usize = 8;

/// Where the model's view was cut from the source photo, in source pixels.
/// Stored in `.nmat` files as JSON (`x0, y0, width, height, source_width,
/// source_height`); version-1 files stored a square `side`, still read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "CropRecord")]
pub struct Crop {
    /// Left column of the crop.
    pub x0: usize,
    /// Top row of the crop.
    pub y0: usize,
    /// Columns of the crop.
    pub width: usize,
    /// Rows of the crop.
    pub height: usize,
    pub source_width: usize,
    pub source_height: usize,
}

/// A crop as stored: version 2 (`width`, `height`) or version 1 (`side`).
#[derive(Deserialize)]
struct CropRecord {
    x0: usize,
    y0: usize,
    side: Option<usize>,
    width: Option<usize>,
    height: Option<usize>,
    source_width: usize,
    source_height: usize,
}

impl TryFrom<CropRecord> for Crop {
    type Error = String;
    fn try_from(r: CropRecord) -> std::result::Result<Self, String> {
        let (width, height) = match (r.width, r.height, r.side) {
            (Some(w), Some(h), _) => (w, h),
            (None, None, Some(s)) => (s, s),
            _ => return Err("a crop needs width and height (or the side of a square)".into()),
        };
        Ok(Crop { x0: r.x0, y0: r.y0, width, height, source_width: r.source_width, source_height: r.source_height })
    }
}

impl Crop {
    /// The whole of a `width x height` photo.
    pub fn whole(width: usize, height: usize) -> Self {
        Crop { x0: 0, y0: 0, width, height, source_width: width, source_height: height }
    }
}

/// A photo ready for M_est.
#[derive(Clone, Debug)]
pub struct PreparedPhoto {
    /// Linear RGB `[3, H, W]` at the model resolution. 8-bit photos are
    /// sRGB-decoded and lie in [0, 1]; EXR values are kept as-is.
    pub linear: Image,
    /// The photo is a display-encoded 8/16-bit PNG or JPEG (LDR) rather
    /// than a linear EXR (HDR).
    pub ldr: bool,
    /// Field of view across the photo's shorter side, in degrees.
    pub fov_deg: f64,
    pub crop: Crop,
    /// File name of the source (no folders).
    pub source: String,
    /// Where the field of view came from and what the camera's EXIF said
    /// (exposure, rotation), for the terminal.
    pub camera_note: String,
    /// What was done to a usable photo that was not quite right (negative
    /// EXR values clamped, transparency dropped): one line each, naming the
    /// file, for the terminal.
    pub warnings: Vec<String>,
}

impl PreparedPhoto {
    /// A linear photo `[3, H, W]` already at the model's 28 degree
    /// co-located view (renders, evaluation photos): no crop.
    pub fn at_model_view(linear: Image, ldr: bool, source: impl Into<String>) -> Self {
        let crop = Crop::whole(linear.width, linear.height);
        Self {
            linear,
            ldr,
            fov_deg: crate::geometry::MODEL_FOV_DEG,
            crop,
            source: source.into(),
            camera_note: String::new(),
            warnings: Vec::new(),
        }
    }
}

/// How a photo is read: the field of view (None: from the EXIF, else the
/// model's own), the model resolution, and an exposure change in stops.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct PhotoOptions {
    pub fov_deg: Option<f64>,
    /// Pixels of the model input's shorter side.
    pub size: usize,
    /// Multiplies the linearised photo by 2^EV.
    pub exposure_ev: Option<f64>,
    /// Keep only the centre square (the behaviour before rectangles).
    pub square: bool,
}

/// Largest `--exposure` change, in stops.
pub const MAX_EXPOSURE_EV: f64 = 20.0;

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

/// The integer nearest to `exact` (<= `len`) of the same parity as `len`,
/// so that a centred cut of it is exactly centred.
fn centred_length(len: usize, exact: f64) -> usize {
    let n = (len as f64 - 2.0 * ((len as f64 - exact) / 2.0).round()).max(0.0) as usize;
    n.min(len)
}

/// The centre square of a `width x height` photo that a `fov_deg` camera
/// shares with the model's 28 degree camera: the centred square of the
/// shorter side, scaled by [`fov_crop_ratio`]. The side is rounded to the
/// parity of the square so the crop stays exactly centred (at most 1 pixel
/// of rounding).
pub fn fov_crop(width: usize, height: usize, fov_deg: f64) -> Result<Crop> {
    check_fov(fov_deg)?;
    let q = width.min(height);
    let side = centred_length(q, q as f64 * fov_crop_ratio(fov_deg).min(1.0));
    Ok(Crop { x0: (width - side) / 2, y0: (height - side) / 2, width: side, height: side, source_width: width, source_height: height })
}

/// The centred rectangle of a `width x height` photo that a `fov_deg`
/// camera shares with the model's camera: both sides scaled by
/// [`fov_crop_ratio`] (the FOV is across the shorter side), each rounded to
/// its own parity so the crop stays exactly centred.
pub fn fov_crop_rect(width: usize, height: usize, fov_deg: f64) -> Result<Crop> {
    check_fov(fov_deg)?;
    let r = fov_crop_ratio(fov_deg).min(1.0);
    let (cw, ch) = (centred_length(width, width as f64 * r), centred_length(height, height as f64 * r));
    Ok(Crop { x0: (width - cw) / 2, y0: (height - ch) / 2, width: cw, height: ch, source_width: width, source_height: height })
}

/// Model resolution (H, W) for a crop of `crop_w x crop_h` pixels: the
/// shorter side is `size`, the longer one `size * long / short` rounded
/// down to a multiple of [`SIZE_MULTIPLE`].
pub fn model_shape(crop_w: usize, crop_h: usize, size: usize) -> (usize, usize) {
    let (short, long) = (crop_w.min(crop_h).max(1), crop_w.max(crop_h));
    let out_long = ((size as f64 * long as f64 / short as f64 + 1e-9) as usize / SIZE_MULTIPLE * SIZE_MULTIPLE).max(size);
    if crop_w >= crop_h {
        (size, out_long)
    } else {
        (out_long, size)
    }
}

/// Crops a linear `[C, H, W]` photo to the model's view and shrinks it to
/// `size` pixels on the shorter side: a rectangle of the photo's aspect
/// ([`model_shape`]; the crop's longer side is trimmed, centred, by less
/// than [`SIZE_MULTIPLE`] model pixels so pixels stay square), or with
/// `square` its centre square. Returns `[C, H, W]` and the crop. Errors
/// when the crop has fewer than `size` pixels across, saying how large a
/// photo is needed, or when the photo is longer than [`MAX_ASPECT`].
pub fn prepare_image_with(linear: &Image, fov_deg: f64, size: usize, square: bool) -> Result<(Image, Crop)> {
    check_size(size)?;
    let mut crop = if square { fov_crop(linear.width, linear.height, fov_deg)? } else { fov_crop_rect(linear.width, linear.height, fov_deg)? };
    let short = crop.width.min(crop.height);
    if short < size {
        // Smallest shorter side whose crop still holds `size` pixels.
        let need = (size as f64 / fov_crop_ratio(fov_deg) - 1e-9).ceil() as usize;
        bail!(
            "the photo is too small: {}x{} pixels, cropped to the model's {MODEL_FOV_DEG} degree view (--fov {fov_deg}), keeps {}x{} pixels, but --size {size} needs at least {size} on the shorter side (a photo whose shorter side is at least {need} pixels)",
            linear.width,
            linear.height,
            crop.width,
            crop.height
        );
    }
    let aspect = crop.width.max(crop.height) as f64 / short as f64;
    ensure!(
        aspect <= MAX_ASPECT + 1e-9,
        "the photo's aspect ratio is {aspect:.2}:1, beyond {MAX_ASPECT}:1: crop it, or pass --square to keep its centre square"
    );
    let (h, w) = model_shape(crop.width, crop.height, size);
    // Trim the longer side so the crop has exactly the output's aspect.
    if crop.width > crop.height {
        let cw = centred_length(crop.width, crop.height as f64 * w as f64 / h as f64);
        crop.x0 += (crop.width - cw) / 2;
        crop.width = cw;
    } else if crop.height > crop.width {
        let ch = centred_length(crop.height, crop.width as f64 * h as f64 / w as f64);
        crop.y0 += (crop.height - ch) / 2;
        crop.height = ch;
    }
    let cut = linear.crop(crop.y0, crop.x0, crop.height, crop.width)?;
    Ok((cut.resize_area(h, w), crop))
}

/// [`prepare_image_with`] keeping the photo's aspect (not `--square`).
pub fn prepare_image(linear: &Image, fov_deg: f64, size: usize) -> Result<(Image, Crop)> {
    prepare_image_with(linear, fov_deg, size, false)
}

/// Reads and prepares a photo: PNG/JPEG (and HEIC/AVIF with an SDR
/// transfer, at their 8 to 12 bits) are LDR and decoded to linear with
/// the exact sRGB curve ([`crate::spaces::photo_decode`]), EXR is linear HDR (NaN/Inf refused
/// by the reader), and so are PQ/HLG HEIC/AVIF files (`io::heif`). The
/// field of view comes from `fov_deg`, else the EXIF's focal length, else
/// it is the model's own (no crop). Errors name the file.
pub fn load_photo(path: &Path, fov_deg: Option<f64>, size: usize) -> Result<PreparedPhoto> {
    load_photo_with(path, &PhotoOptions { fov_deg, size, ..Default::default() })
}

/// Checks a photo's options before anything is read.
fn check_options(opts: &PhotoOptions) -> Result<()> {
    check_size(opts.size)?;
    if let Some(f) = opts.fov_deg {
        check_fov(f)?;
    }
    if let Some(ev) = opts.exposure_ev {
        ensure!(ev.is_finite() && ev.abs() <= MAX_EXPOSURE_EV, "--exposure must be a number of stops within +-{MAX_EXPOSURE_EV}, got {ev}");
    }
    Ok(())
}

/// [`load_photo`] with every option: the EXIF orientation is applied, the
/// exposure change scales the linear photo.
pub fn load_photo_with(path: &Path, opts: &PhotoOptions) -> Result<PreparedPhoto> {
    // Before the file is read (prepare_decoded checks again, for pixels):
    // a bad option is named first.
    check_options(opts)?;
    let (image, format) = read_image_with_format(path)?;
    let ldr = !format.is_float();
    // EXR has no EXIF; HEIF files have it whatever their transfer.
    let camera = if format != crate::io::FileFormat::Exr {
        super::camera::read_camera(path, format, image.width, image.height)?
    } else {
        super::camera::CameraInfo { orientation: 1, ..Default::default() }
    };
    let rgb = crate::io::to_rgb(&image).oriented(camera.orientation);
    let alpha = (image.channels % 2 == 0).then(|| image.plane(image.channels - 1));
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mut prepared = prepare_decoded(rgb, alpha, ldr, &camera, opts, &path.display().to_string(), &name)?;
    // A RAW photo is linear (nothing to decode) but stops at its sensor's
    // white level, 1, as an 8-bit photo does: LDR for the model.
    prepared.ldr = format.clips_at_one();
    if format == crate::io::FileFormat::Raw {
        prepared.camera_note.push_str("; RAW: linear, the file's white balance and colour matrix");
    }
    Ok(prepared)
}

/// The part of [`load_photo_with`] after decoding, for photos that come as
/// pixels (the Python `estimate` on arrays): the photo screened
/// ([`screen_photo`]), sRGB-decoded when `ldr`, the exposure change, the
/// field of view (from `opts`, else `camera`, else the model's own), the
/// crop and the resize. rgb: `[3, H, W]` as stored (sRGB codes in [0, 1]
/// when `ldr`, else linear); alpha: its alpha plane, if any. Errors and
/// warnings start with `label` (the file's path); `source` is the name the
/// material records.
pub fn prepare_decoded(mut rgb: Image, alpha: Option<&[f32]>, ldr: bool, camera: &super::camera::CameraInfo, opts: &PhotoOptions, label: &str, source: &str) -> Result<PreparedPhoto> {
    check_options(opts)?;
    ensure!(rgb.channels == 3, "{label}: the photo must have 3 colour channels, got {}", rgb.channels);
    let warnings = screen_photo(alpha, &mut rgb).map_err(|e| anyhow::anyhow!("{label}: {e}"))?;
    let warnings = warnings.into_iter().map(|w| format!("{label}: {w}")).collect();
    let mut linear = if ldr { rgb.map(crate::spaces::photo_decode) } else { rgb };
    if let Some(ev) = opts.exposure_ev {
        let gain = 2f32.powf(ev as f32);
        linear = linear.map(|v| v * gain);
    }
    let (fov, fov_source) = match (opts.fov_deg, &camera.fov) {
        (Some(f), _) => (f, "--fov".to_string()),
        (None, Some((f, from))) => (*f, from.clone()),
        (None, None) => (
            MODEL_FOV_DEG,
            format!("no focal length in the photo's EXIF: taken as the model's own {MODEL_FOV_DEG} degree view, no crop; pass --fov DEGREES for a wider lens"),
        ),
    };
    if opts.fov_deg.is_none() && fov < MODEL_FOV_DEG - 1e-9 {
        bail!("{label}: its {fov_source} gives a {fov:.1} degree field of view, narrower than the model's {MODEL_FOV_DEG}: the photo shows too little of the material (step back, or pass --fov DEGREES)");
    }
    let mut note = format!("photo {}x{}: FOV {fov:.1} deg ({fov_source})", linear.width, linear.height);
    if let Some(e) = &camera.exposure {
        note.push_str(&format!("; exposure {e}"));
    }
    if camera.orientation != 1 {
        note.push_str(&format!("; rotated by its EXIF orientation {}", camera.orientation));
    }
    if let Some(ev) = opts.exposure_ev {
        note.push_str(&format!("; --exposure {ev:+} EV"));
    }
    let (linear, crop) = prepare_image_with(&linear, fov, opts.size, opts.square).map_err(|e| anyhow::anyhow!("{label}: {e:#}"))?;
    Ok(PreparedPhoto { linear, ldr, fov_deg: fov, crop, source: source.to_string(), camera_note: note, warnings })
}

/// Below this fraction of pixels with any light (a colour value above 0)
/// a photo is black: nothing to estimate.
pub const MIN_LIT_FRACTION: f64 = 0.001;

/// Checks a decoded photo's values (`rgb` as stored: codes in [0, 1] or
/// EXR radiance; `alpha` its alpha plane, if any) before they are used:
/// - negative values (EXR noise) are clamped to 0, with a warning saying
///   how many;
/// - any pixel not fully opaque gives a warning that its alpha is ignored
///   (the colour stored under it is estimated as it is); an all-opaque
///   alpha channel says nothing;
/// - a photo where under [`MIN_LIT_FRACTION`] of the pixels hold any
///   light (all zero or negative) is an error.
///
/// Returns the warnings (without the file's name).
pub fn screen_photo(alpha: Option<&[f32]>, rgb: &mut Image) -> Result<Vec<String>> {
    let mut warnings = Vec::new();
    let n = rgb.height * rgb.width;
    let lit = (0..n).filter(|&i| (0..rgb.channels).any(|c| rgb.data[c * n + i] > 0.0)).count();
    ensure!(
        lit as f64 >= MIN_LIT_FRACTION * n as f64 && lit > 0,
        "the photo is black: {} of its {n} pixels are zero or negative in every channel; there is nothing to estimate",
        n - lit
    );
    let negative = rgb.data.iter().filter(|v| **v < 0.0).count();
    if negative > 0 {
        rgb.data.iter_mut().for_each(|v| *v = v.max(0.0));
        let total = rgb.data.len();
        warnings.push(format!("{negative} of its {total} colour values ({:.2}%) are negative (sensor noise?); clamped to 0", 100.0 * negative as f64 / total as f64));
    }
    if let Some(alpha) = alpha {
        let clear = alpha.iter().filter(|a| **a < 1.0 - 1e-6).count();
        if clear > 0 {
            warnings.push(format!(
                "{clear} of its {} pixels ({:.2}%) are transparent or partly so; the alpha channel is ignored and the colour stored under it estimated as it is",
                alpha.len(),
                100.0 * clear as f64 / alpha.len() as f64
            ));
        }
    }
    Ok(warnings)
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
        assert_eq!(fov_crop(300, 200, 28.0).unwrap(), Crop { x0: 50, y0: 0, width: 200, height: 200, source_width: 300, source_height: 200 });
        // 45 degrees keeps 0.6019 of the side; parity of the square kept.
        let c = fov_crop(638, 638, 45.0).unwrap();
        assert_eq!((c.x0, c.y0, c.width, c.height), (127, 127, 384, 384));
        let c = fov_crop(1001, 2000, 45.0).unwrap();
        assert_eq!(c.width % 2, 1);
        assert!((c.width as f64 - 1001.0 * fov_crop_ratio(45.0)).abs() <= 1.0);
        assert_eq!((c.x0, c.y0), ((1001 - c.width) / 2, (2000 - c.width) / 2));
        // The rectangle: both sides scaled, each keeping its parity.
        // 1001 x 0.601938 = 602.5 -> 603 (odd), 2000 x 0.601938 = 1203.9 -> 1204.
        let r = fov_crop_rect(1001, 2000, 45.0).unwrap();
        assert_eq!((r.x0, r.y0, r.width, r.height), (199, 398, 603, 1204));
        assert_eq!(fov_crop_rect(300, 200, 28.0).unwrap(), Crop::whole(300, 200));
        // Model shapes: 3:2 is exact, 4:3 rounds 341.3 down to 336, portrait swaps.
        assert_eq!(model_shape(300, 200, 256), (256, 384));
        assert_eq!(model_shape(400, 300, 256), (256, 336));
        assert_eq!(model_shape(300, 400, 256), (336, 256));
        assert_eq!(model_shape(64, 64, 32), (32, 32));
        assert!(fov_crop(100, 100, 20.0).unwrap_err().to_string().contains("between 28 and"));
        assert!(fov_crop(100, 100, f64::NAN).is_err());
        assert!(fov_crop(100, 100, 180.0).is_err());
    }

    #[test]
    fn pixels_prepare_like_their_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.png");
        let codes = Image::from_fn(3, 48, 64, |c, y, x| ((x * 3 + y * 5 + c * 40) % 256) as f32 / 255.0);
        crate::io::write_image(&path, &codes).unwrap();
        let opts = PhotoOptions { size: 32, fov_deg: Some(40.0), ..Default::default() };
        let from_file = load_photo_with(&path, &opts).unwrap();
        let none = super::super::camera::CameraInfo { orientation: 1, ..Default::default() };
        let from_pixels = prepare_decoded(codes.clone(), None, true, &none, &opts, "pixels", "p.png").unwrap();
        assert_eq!(from_pixels.linear.data, from_file.linear.data);
        assert_eq!((from_pixels.crop, from_pixels.fov_deg, from_pixels.ldr), (from_file.crop, 40.0, true));
        // Without EXIF or a field of view: the model's own (the whole height
        // kept, the width cut to the map's multiple of 8); errors name the label.
        let own = prepare_decoded(codes.clone(), None, true, &none, &PhotoOptions { size: 32, ..Default::default() }, "pixels", "p.png").unwrap();
        assert_eq!((own.fov_deg, own.crop.y0, own.crop.height), (MODEL_FOV_DEG, 0, 48));
        let black = Image::filled(3, 48, 64, 0.0);
        let e = prepare_decoded(black, None, false, &none, &opts, "pixels", "p.png").unwrap_err().to_string();
        assert!(e.starts_with("pixels: the photo is black"), "{e}");
        assert!(prepare_decoded(Image::filled(2, 48, 64, 0.5), None, true, &none, &opts, "pixels", "p.png").is_err());
    }

    #[test]
    fn too_small_photo_says_what_is_needed() {
        let im = Image::filled(3, 300, 400, 0.5);
        let e = prepare_image(&im, 45.0, 256).unwrap_err().to_string();
        // 300 * 0.6019 = 180.6 -> 180 (even) rows and 400 * 0.6019 = 240.8 -> 240
        // columns kept; 256 / 0.6019 = 425.3.
        assert!(e.contains("keeps 240x180") && e.contains("at least 426 pixels"), "{e}");
        // 400 x 300 at 256: 256 x 336 (341.3 rounded down to a multiple of 8); the crop
        // is trimmed to 300 x 336 / 256 = 393.75 -> 394 columns (even, like 400), x0 = 3.
        let (p, c) = prepare_image(&im, 28.0, 256).unwrap();
        assert_eq!((p.height, p.width, c.width, c.height, c.x0, c.y0), (256, 336, 394, 300, 3, 0));
        let (p, c) = prepare_image_with(&im, 28.0, 256, true).unwrap();
        assert_eq!((p.height, p.width, c.width, c.height, c.x0), (256, 256, 300, 300, 50));
        let long = Image::filled(3, 64, 320, 0.5);
        let e = prepare_image(&long, 28.0, 32).unwrap_err().to_string();
        assert!(e.contains("5.00:1") && e.contains("--square"), "{e}");
        assert!(prepare_image_with(&long, 28.0, 32, true).is_ok());
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
        assert_eq!((crop.x0, crop.y0, crop.width, crop.height), (127, 127, 384, 384));

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

    /// A JPEG of `image` with an EXIF block of `fields` (APP1 after SOI).
    fn jpeg_with_exif(path: &Path, image: &Image, fields: &[exif::Field]) {
        crate::io::write_jpeg(path, image, 95).unwrap();
        let jpeg = std::fs::read(path).unwrap();
        let mut writer = exif::experimental::Writer::new();
        for f in fields {
            writer.push_field(f);
        }
        let mut tiff = std::io::Cursor::new(Vec::new());
        writer.write(&mut tiff, false).unwrap();
        let payload = [b"Exif\0\0".as_slice(), tiff.get_ref()].concat();
        let len = (payload.len() + 2) as u16;
        let out = [&jpeg[..2], &[0xFF, 0xE1], &len.to_be_bytes(), &payload, &jpeg[2..]].concat();
        std::fs::write(path, out).unwrap();
    }

    fn field(tag: exif::Tag, value: exif::Value) -> exif::Field {
        exif::Field { tag, ifd_num: exif::In::PRIMARY, value }
    }

    fn rational(num: u32, denom: u32) -> exif::Value {
        exif::Value::Rational(vec![exif::Rational { num, denom }])
    }

    #[test]
    fn fov_exposure_and_rotation_come_from_the_exif() {
        use exif::{Tag, Value};
        let dir = tempfile::tempdir().unwrap();
        // 4:3 at a 26 mm equivalent: 53.06 degrees across the shorter side.
        let p = dir.path().join("phone.jpg");
        let im = Image::from_fn(3, 96, 128, |c, y, x| 0.2 + 0.3 * (x as f32 / 128.0) + 0.1 * c as f32 + 0.001 * y as f32);
        jpeg_with_exif(
            &p,
            &im,
            &[
                field(Tag::FocalLengthIn35mmFilm, Value::Short(vec![26])),
                field(Tag::ExposureTime, rational(1, 60)),
                field(Tag::FNumber, rational(18, 10)),
                field(Tag::PhotographicSensitivity, Value::Short(vec![100])),
            ],
        );
        let photo = load_photo(&p, None, 32).unwrap();
        assert!((photo.fov_deg - 53.0595).abs() < 0.01, "{}", photo.fov_deg);
        assert!(photo.camera_note.contains("FocalLengthIn35mmFilm 26 mm") && photo.camera_note.contains("1/60 s, f/1.8, ISO 100"), "{}", photo.camera_note);
        // The crop is the model's 28 degrees of the 96-pixel side: tan(14)/tan(26.53) = 0.4994 -> 48
        // rows, 128 x 0.4994 -> 64 columns; at --size 32 the model sees 32 x 40 (42.7 rounded down),
        // so the 64 columns are trimmed to 48 x 40 / 32 = 60, x0 = 32 + 2.
        assert_eq!((photo.crop.width, photo.crop.height, photo.crop.x0, photo.crop.y0), (60, 48, 34, 24));
        assert_eq!((photo.linear.height, photo.linear.width), (32, 40));
        // --fov wins over the EXIF.
        assert_eq!(load_photo(&p, Some(28.0), 32).unwrap().fov_deg, 28.0);

        // Orientation 6 (turn 90 degrees clockwise): the 96x128 stored photo is shown 128 high, 96 wide,
        // and its stored left column becomes the top row.
        let r = dir.path().join("rotated.jpg");
        jpeg_with_exif(&r, &im, &[field(Tag::Orientation, Value::Short(vec![6]))]);
        let photo = load_photo(&r, None, 32).unwrap();
        assert_eq!((photo.crop.source_width, photo.crop.source_height), (96, 128));
        assert!(photo.camera_note.contains("orientation 6") && photo.camera_note.contains("no focal length"), "{}", photo.camera_note);
        // Stored, brightness grows to the right; shown, it grows downwards.
        let (top, bottom) = (photo.linear.get(0, 0, 16), photo.linear.get(0, 31, 16));
        assert!(bottom > top + 0.1, "{top} {bottom}");

        // Two focal lengths that disagree: 26 mm equivalent (53 degrees) and 10 mm on a 4.2 mm side (24 degrees).
        let c = dir.path().join("contradicts.jpg");
        jpeg_with_exif(
            &c,
            &im,
            &[
                field(Tag::FocalLengthIn35mmFilm, Value::Short(vec![26])),
                field(Tag::FocalLength, rational(10, 1)),
                field(Tag::FocalPlaneXResolution, rational(128, 4)), // 32 px per mm at 128 px: 4 mm wide, 3 mm short side
                field(Tag::FocalPlaneResolutionUnit, Value::Short(vec![4])),
            ],
        );
        let e = format!("{:#}", load_photo(&c, None, 32).unwrap_err());
        assert!(e.contains("contradicts itself") && e.contains("--fov") && !e.contains('\n'), "{e}");
        assert!(load_photo(&c, Some(40.0), 32).is_err(), "the EXIF is read (and refused) even with --fov");
    }

    /// A phone's HEIC: the same FOV from its EXIF as the JPEG above, turned
    /// once by the file's own rotation (not again by its EXIF orientation,
    /// which phones also write), and the same linear photo as that JPEG.
    #[cfg(feature = "heif")]
    #[test]
    fn heic_photos_read_like_jpeg_with_fov_from_exif_and_one_rotation() {
        use exif::{Tag, Value};
        let dir = tempfile::tempdir().unwrap();
        let im = Image::from_fn(3, 96, 128, |c, y, x| 0.2 + 0.3 * (x as f32 / 128.0) + 0.1 * c as f32 + 0.001 * y as f32);
        let fields = [
            field(Tag::FocalLengthIn35mmFilm, Value::Short(vec![26])),
            field(Tag::Orientation, Value::Short(vec![6])),
            field(Tag::ExposureTime, rational(1, 60)),
        ];
        let h = dir.path().join("IMG_0001.HEIC");
        let spec = crate::io::heif::HeifEncoding { orientation: 6, exif: Some(crate::io::heif::tests::exif_tiff(&fields)), ..Default::default() };
        crate::io::heif::write_heif(&h, &im, &spec).unwrap();
        assert!(std::fs::metadata(&h).unwrap().len() < 20_000);
        let heic = load_photo(&h, None, 32).unwrap();
        // 4:3 at 26 mm equivalent: the shorter side is 43.2666 x 3/5 = 25.96 mm, 2 atan(25.96 / 52) = 53.06 degrees.
        let by_hand = 2.0 * (43.266_615 * 0.6 / 52.0f64).atan().to_degrees();
        assert!((heic.fov_deg - by_hand).abs() < 1e-3 && (by_hand - 53.0595).abs() < 1e-3, "{} {by_hand}", heic.fov_deg);
        assert!(heic.camera_note.contains("FocalLengthIn35mmFilm 26 mm") && heic.camera_note.contains("1/60 s"), "{}", heic.camera_note);
        assert!(!heic.camera_note.contains("rotated by its EXIF"), "{}", heic.camera_note);
        assert!(heic.ldr);
        // Shown 128 high, 96 wide: the stored left column is the top row.
        assert_eq!((heic.crop.source_width, heic.crop.source_height), (96, 128));
        assert_eq!((heic.linear.height, heic.linear.width), (40, 32));
        let (top, bottom) = (heic.linear.get(0, 0, 16), heic.linear.get(0, 39, 16));
        assert!(bottom > top + 0.05, "{top} {bottom}");
        // The JPEG of the same picture and EXIF gives the same linear photo.
        let j = dir.path().join("IMG_0001.jpg");
        jpeg_with_exif(&j, &im, &fields);
        let jpeg = load_photo(&j, None, 32).unwrap();
        assert_eq!((jpeg.fov_deg, jpeg.crop), (heic.fov_deg, heic.crop));
        let worst = heic.linear.data.iter().zip(&jpeg.linear.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst < 0.01, "HEIC vs JPEG: worst linear difference {worst}");
    }

    #[test]
    fn oriented_maps_every_tag() {
        // 2x3 image with values 10 r + c.
        let im = Image::from_fn(1, 2, 3, |_, r, c| (10 * r + c) as f32);
        let rows = |m: &Image| (0..m.height).map(|r| (0..m.width).map(|c| m.get(0, r, c) as i32).collect::<Vec<_>>()).collect::<Vec<_>>();
        assert_eq!(rows(&im.oriented(1)), vec![vec![0, 1, 2], vec![10, 11, 12]]);
        assert_eq!(rows(&im.oriented(2)), vec![vec![2, 1, 0], vec![12, 11, 10]]);
        assert_eq!(rows(&im.oriented(3)), vec![vec![12, 11, 10], vec![2, 1, 0]]);
        assert_eq!(rows(&im.oriented(4)), vec![vec![10, 11, 12], vec![0, 1, 2]]);
        assert_eq!(rows(&im.oriented(5)), vec![vec![0, 10], vec![1, 11], vec![2, 12]]);
        assert_eq!(rows(&im.oriented(6)), vec![vec![10, 0], vec![11, 1], vec![12, 2]]);
        assert_eq!(rows(&im.oriented(7)), vec![vec![12, 2], vec![11, 1], vec![10, 0]]);
        assert_eq!(rows(&im.oriented(8)), vec![vec![2, 12], vec![1, 11], vec![0, 10]]);
        assert_eq!(im.oriented(9), im);
    }

    #[test]
    fn exposure_scales_and_heic_is_refused_with_a_way_out() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("p.png");
        crate::io::write_png(&p, &Image::filled(3, 32, 32, 0.5), crate::io::BitDepth::Eight).unwrap();
        let base = load_photo(&p, None, 32).unwrap();
        let brighter = load_photo_with(&p, &PhotoOptions { fov_deg: None, size: 32, exposure_ev: Some(1.0), square: false }).unwrap();
        let ratio = brighter.linear.get(1, 5, 5) / base.linear.get(1, 5, 5);
        assert!((ratio - 2.0).abs() < 1e-5, "{ratio}");
        assert!(brighter.camera_note.contains("--exposure +1 EV"), "{}", brighter.camera_note);
        assert!(load_photo_with(&p, &PhotoOptions { fov_deg: None, size: 32, exposure_ev: Some(f64::NAN), square: false }).is_err());
        // A HEIC file (ftyp box, brand heic), whatever its name.
        let h = dir.path().join("IMG_0001.dat");
        std::fs::write(&h, [&[0, 0, 0, 24][..], b"ftypheic", &[0; 12]].concat()).unwrap();
        let e = format!("{:#}", load_photo(&h, None, 32).unwrap_err());
        if cfg!(feature = "heif") {
            // Read by libheif, which finds no image in it.
            assert!(e.contains("IMG_0001.dat") && e.contains("corrupt or truncated HEIC") && !e.contains('\n'), "{e}");
        } else {
            assert!(e.contains("HEIC/AVIF") && e.contains("heif-convert") && e.contains("--features heif") && !e.contains('\n'), "{e}");
        }
        // A 0-byte file.
        let z = dir.path().join("empty.jpg");
        std::fs::write(&z, b"").unwrap();
        assert!(format!("{:#}", load_photo(&z, None, 32).unwrap_err()).contains("empty"));
    }

    /// Photos that parse but are not quite right: negative EXR noise is
    /// clamped with a warning saying how much, transparency is reported,
    /// all-opaque alpha is not, and a black photo is refused.
    #[test]
    fn questionable_photos_are_warned_about_or_refused() {
        let dir = tempfile::tempdir().unwrap();
        let exr = dir.path().join("noisy.exr");
        let mut noisy = Image::filled(3, 32, 32, 0.2);
        for i in 0..30 {
            noisy.data[i * 7] = -0.01;
        }
        crate::io::write_exr(&exr, &noisy).unwrap();
        let p = load_photo(&exr, None, 32).unwrap();
        assert_eq!(p.warnings.len(), 1, "{:?}", p.warnings);
        assert!(p.warnings[0].contains("noisy.exr: 30 of its 3072 colour values (0.98%) are negative") && p.warnings[0].contains("clamped to 0"), "{}", p.warnings[0]);
        assert!(p.linear.data.iter().all(|v| *v >= 0.0));

        let black = dir.path().join("black.exr");
        let mut dark = Image::filled(3, 40, 40, -0.5);
        dark.data[0] = 1.0; // one lit pixel of 1600: under MIN_LIT_FRACTION
        crate::io::write_exr(&black, &dark).unwrap();
        let e = format!("{:#}", load_photo(&black, None, 32).unwrap_err());
        assert!(e.contains("black.exr: the photo is black: 1599 of its 1600 pixels") && !e.contains('\n'), "{e}");

        let rgba = |alpha: f32| Image::from_fn(4, 32, 32, |c, y, x| if c == 3 { if y == 0 && x < 4 { alpha } else { 1.0 } } else { 0.5 });
        let opaque = dir.path().join("opaque.png");
        crate::io::write_png(&opaque, &rgba(1.0), crate::io::BitDepth::Eight).unwrap();
        assert!(load_photo(&opaque, None, 32).unwrap().warnings.is_empty());
        let clear = dir.path().join("clear.png");
        crate::io::write_png(&clear, &rgba(0.0), crate::io::BitDepth::Eight).unwrap();
        let p = load_photo(&clear, None, 32).unwrap();
        assert_eq!(p.warnings.len(), 1);
        assert!(p.warnings[0].contains("clear.png: 4 of its 1024 pixels (0.39%) are transparent") && p.warnings[0].contains("alpha channel is ignored"), "{}", p.warnings[0]);
        // The colour under transparent pixels is what is estimated.
        assert!(p.linear.data.iter().all(|v| (v - crate::spaces::photo_decode(128.0 / 255.0)).abs() < 1e-6));
    }
}
