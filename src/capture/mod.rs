//! Photos of the printed frame to a capture folder (`flashmat capture`):
//! the frame's tags are found in each photo ([`markers`]), the camera is
//! fitted over all photos ([`camera`]: one focal length and distortion, a
//! pose per photo), the opening is cut out of each photo and made square
//! ([`rectify`]), and the folder `data::captures` reads is written: photos
//! sorted most overhead first, the lens and flash positions in mm, the
//! opening's width. [`frame`] draws the frame to print; [`synthetic`]
//! renders phone photos of it from known poses (tests, docs).
//!
//! A uniformly scaled print cannot be told from the photos (a frame at 90%
//! seen from 27 cm looks as the true one from 30 cm), and the capture
//! folder's positions are relative to the opening, so the fit does not
//! care; only the material's size in mm would be off. The printed scale bar
//! is the check. What the photos do show is a frame that is not the one
//! its tags name: those tags disagree with the layout, and the photo is
//! refused.

pub mod camera;
pub mod frame;
pub mod markers;
pub mod photometry;
pub mod pictures;
pub mod rectify;
pub mod synthetic;

use crate::geometry::{add, length, Vec3};
use anyhow::{anyhow, bail, ensure, Context, Result};
use camera::{Calibration, Correspondences, Intrinsics, Pose};
use frame::FrameLayout;
use markers::{Gray, Marker};
use rectify::Rgb8;
use std::path::{Path, PathBuf};

/// The options of `flashmat capture`.
#[derive(Clone, Debug)]
pub struct CaptureConfig {
    /// The flash's offset from the lens, mm, in the camera frame of the
    /// photo as the sensor stores it (x along its rows, y down its
    /// columns); turned with the photo's EXIF orientation.
    pub flash_offset_mm: [f64; 2],
    /// The largest side of the rectified photos (they take the overhead
    /// photo's own resolution of the opening up to this).
    pub max_side: usize,
    /// Threads of the tag detector.
    pub threads: usize,
}

impl Default for CaptureConfig {
    fn default() -> Self {
        Self { flash_offset_mm: [0.0, 0.0], max_side: 1024, threads: 2 }
    }
}

/// Fewest of the frame's tags a photo must show (16 corners).
pub const MIN_TAGS: usize = 4;
/// Most reprojection error a photo may keep after the fit, pixels per
/// 1000 pixels of its longer side (2 px on a 12 MP photo's 4032).
pub const MAX_RMS_PER_1000_PX: f64 = 0.5;
/// Photos whose width / height differ by more than this (relative) from
/// the first photo's were cropped.
const MAX_ASPECT_DIFFERENCE: f64 = 0.01;

/// How far the fitted focal length may stray from the EXIF's (relative).
pub const FOCAL_AGREEMENT: f64 = 0.15;
/// Below this sharpness ([`markers::sharpness`]: a Gaussian blur of about
/// 4 pixels) a photo without tags is called blurred.
pub const BLURRED_BELOW: f64 = 0.1;
/// Without an EXIF focal length, at least one photo's optical axis must
/// slant this far from the frame's normal (degrees) for the homographies
/// to fix it.
pub const MIN_TILT_WITHOUT_EXIF_DEG: f64 = 8.0;
/// Focal lengths a phone's photo can have, in units of its longer side
/// (fields of view across it from about 20 to 120 degrees).
pub const FOCAL_RANGE: std::ops::RangeInclusive<f64> = 0.3..=3.0;
/// Smallest rectified side, pixels.
const MIN_SIDE: usize = 64;

/// A RAW photo of the frame as read (`io::raw`).
pub struct RawPixels {
    /// Linear sRGB `[3, H, W]`, upright, 1 at the sensor's white level.
    pub linear: crate::image::Image,
    /// 2^BaselineExposure of the file (`io::raw_baseline_gain`).
    pub baseline_gain: f64,
}

/// A photo of the frame, decoded and turned upright by its EXIF.
pub struct FramePhoto {
    pub path: PathBuf,
    /// The photo's codes (a RAW photo's linear values sRGB-encoded): what
    /// the tag detector and the pictures see.
    pub rgb: Rgb8,
    /// A RAW photo's linear pixels, rectified instead of the codes.
    pub raw: Option<RawPixels>,
    /// The focal length in pixels from the EXIF, if it says.
    pub exif_focal: Option<f64>,
    pub orientation: u16,
    /// Exposure time, f-number and ISO as the EXIF says, if it does.
    pub exposure: Option<crate::infer::camera::Exposure>,
}

/// Reads a photo of the frame (JPEG, PNG, HEIC with the `heif` feature).
pub fn load_frame_photo(path: &Path) -> Result<FramePhoto> {
    let (image, format) = crate::io::read_image_with_format(path)?;
    let raw = format == crate::io::FileFormat::Raw;
    ensure!(raw || !format.is_float(), "{}: a photo of the frame must be an 8-bit photo (JPEG, PNG, HEIC) or a RAW photo (DNG), not HDR", path.display());
    let info = crate::infer::camera::read_camera(path, format, image.width, image.height)?;
    let rgb = crate::io::to_rgb(&image).oriented(info.orientation);
    let (w, h) = (rgb.width, rgb.height);
    // A RAW photo's codes (for the tag detector and the pictures) are its
    // linear values sRGB-encoded; it is rectified from the linear values.
    let code = |v: f32| if raw { crate::spaces::quantize_u8(crate::spaces::photo_encode(v.clamp(0.0, 1.0))) } else { crate::spaces::quantize_u8(v) };
    let data = (0..h).flat_map(|y| (0..w).flat_map(move |x| (0..3).map(move |c| (y, x, c)))).map(|(y, x, c)| code(rgb.get(c, y, x))).collect();
    let exif_focal = info.fov.map(|(fov, _)| w.min(h) as f64 / 2.0 / (fov.to_radians() / 2.0).tan());
    let baseline_gain = crate::io::raw_baseline_gain(path);
    Ok(FramePhoto { path: path.to_path_buf(), rgb: Rgb8 { width: w, height: h, data }, exif_focal, orientation: info.orientation, exposure: info.exposure, raw: raw.then_some(RawPixels { linear: rgb, baseline_gain }) })
}

/// Each photo's exposure relative to the first's (EXIF time x ISO /
/// f-number^2), when they differ and every photo's EXIF states it: the
/// capture folder's `exposures.txt`, which brings bracketed or
/// auto-exposed photos to one exposure. None when they are all the same
/// or some photo does not say (see [`exposure_warning`]).
pub fn relative_exposures(photos: &[FramePhoto]) -> Option<Vec<f64>> {
    let scales: Vec<f64> = photos.iter().map(|p| p.exposure.as_ref()?.scale()).collect::<Option<_>>()?;
    let first = *scales.first()?;
    let differ = scales.iter().any(|&s| (s / first - 1.0).abs() > EXPOSURE_TOLERANCE);
    differ.then(|| scales.iter().map(|s| s / first).collect())
}

/// What a phone's EXIF can state: exposure time (s), f-number, ISO.
const PHONE_TIME_S: std::ops::RangeInclusive<f64> = 1e-6..=60.0;
const PHONE_F_NUMBER: std::ops::RangeInclusive<f64> = 0.7..=64.0;
const PHONE_ISO: std::ops::RangeInclusive<u32> = 10..=409_600;

/// Refuses a photo whose EXIF exposure no phone takes (a time of 4e9 s):
/// a broken EXIF would scale the photo by it in `exposures.txt`.
fn check_exif_exposure(photo: &FramePhoto) -> Result<()> {
    let Some(e) = &photo.exposure else { return Ok(()) };
    let bad = e.time_s.is_some_and(|t| !PHONE_TIME_S.contains(&t)) || e.f_number.is_some_and(|f| !PHONE_F_NUMBER.contains(&f)) || e.iso.is_some_and(|i| !PHONE_ISO.contains(&i));
    ensure!(
        !bad,
        "{}: its EXIF states an exposure no phone takes ({e}; times {}-{} s, f/{}-{}, ISO {}-{}): the EXIF is broken; save the photo again from the phone",
        name(&photo.path),
        PHONE_TIME_S.start(),
        PHONE_TIME_S.end(),
        PHONE_F_NUMBER.start(),
        PHONE_F_NUMBER.end(),
        PHONE_ISO.start(),
        PHONE_ISO.end()
    );
    Ok(())
}

/// Exposures closer than this (relative) are one exposure.
const EXPOSURE_TOLERANCE: f64 = 0.01;

/// A warning when the photos' EXIF exposures differ but some photo's EXIF
/// does not state its whole exposure, so [`relative_exposures`] cannot
/// bring them to one: the fit takes one exposure unless it fits a gain per photo.
pub fn exposure_warning(photos: &[FramePhoto]) -> Option<String> {
    let first = photos.first()?.exposure.as_ref()?;
    if photos.iter().all(|p| p.exposure.as_ref() == Some(first)) || relative_exposures(photos).is_some() {
        return None;
    }
    let list = photos.iter().map(|p| format!("{} {}", name(&p.path), p.exposure.as_ref().map_or("(no EXIF)".into(), |e| e.to_string()))).collect::<Vec<_>>().join(", ");
    Some(format!("the photos' exposures differ ({list}) and not every photo states its exposure time, f-number and ISO: lock the exposure, or fit a gain per photo (estimate --capture --photo-gains)"))
}

/// The flash's offset in the camera frame of a photo shown with EXIF
/// `orientation`, from its offset in the stored photo's frame (the
/// rotation [`crate::image::Image::oriented`] applies, on vectors).
pub fn oriented_offset(offset: [f64; 2], orientation: u16) -> [f64; 2] {
    let [x, y] = offset;
    match orientation {
        2 => [-x, y],
        3 => [-x, -y],
        4 => [x, -y],
        5 => [y, x],
        6 => [-y, x],
        7 => [-y, -x],
        8 => [y, -x],
        _ => [x, y],
    }
}

/// What one photo showed and where its camera was.
#[derive(Clone, Debug)]
pub struct PhotoResult {
    pub source: PathBuf,
    pub markers: Vec<Marker>,
    pub intrinsics: Intrinsics,
    pub pose: Pose,
    /// Lens and flash, mm in the frame's axes.
    pub camera: Vec3,
    pub light: Vec3,
    /// Reprojection error, pixels.
    pub rms: f64,
}

/// A finished capture: the photos in the folder's order (most overhead
/// first), their rectified openings and the frame.
pub struct Capture {
    pub layout: FrameLayout,
    pub photos: Vec<PhotoResult>,
    /// Linear `[3, side, side]` row-major, one per photo, in order.
    pub rectified: Vec<Vec<f32>>,
    pub side: usize,
    pub distortion: bool,
    /// What each photo's paper says of its exposure and white balance
    /// ([`photometry`]), in order.
    pub paper: Vec<photometry::PaperReading>,
    /// The gamma of the pure power curve the paper measured and the
    /// rectified photos were read with (linear = code^gamma) where it said
    /// the sRGB curve is wrong ([`photometry::srgb_mismatch`],
    /// [`photometry::power_gamma`]); None: decoded as sRGB (or RAW).
    pub gamma: Option<f64>,
}

impl Capture {
    /// Each photo's exposure per channel relative to the overhead photo's,
    /// as the folder records it: the paper's reading when every photo has
    /// one, else the EXIF's (one number for all channels), else None. None
    /// too when they are one exposure.
    pub fn folder_exposures(&self, photos: &[FramePhoto]) -> Result<Option<Vec<[f64; 3]>>> {
        if let Some(levels) = photometry::relative_levels(&self.paper) {
            return Ok(photometry::levels_differ(&levels).then_some(levels));
        }
        let Some(exposures) = relative_exposures(photos) else { return Ok(None) };
        // In the folder's order, which is not the inputs'.
        let by_source = |p: &PhotoResult| photos.iter().position(|f| f.path == p.source).map(|i| [exposures[i]; 3]).context("a capture's photo is missing from its inputs");
        Ok(Some(self.photos.iter().map(by_source).collect::<Result<_>>()?))
    }
}

fn name(path: &Path) -> String {
    path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| path.display().to_string())
}

/// A photo whose grey codes all lie within this many of each other shows nothing.
const FLAT_PHOTO_CODES: u8 = 8;

/// The frame's tags in one photo, with the frame they name. Errors are one
/// line naming the photo: no tags (blurred, or another family), too few.
pub fn find_frame(photo: &FramePhoto, threads: usize) -> Result<(FrameLayout, Vec<Marker>)> {
    let values = photo.rgb.gray();
    let gray = Gray { width: photo.rgb.width, height: photo.rgb.height, values: &values };
    let found = markers::detect(&gray, threads);
    let who = name(&photo.path);
    if found.is_empty() {
        let others = markers::other_families(&gray, threads, MIN_TAGS);
        if !others.is_empty() {
            bail!("{who}: its tags are {}, not the frame's tag36h11: print the frame of `flashmat capture frame`", others.join(", "));
        }
        // A mirror image's tags read as no tags: flip it and look again.
        let mirrored: Vec<u8> = values.chunks_exact(photo.rgb.width).flat_map(|row| row.iter().rev().copied()).collect();
        if markers::detect(&Gray { width: photo.rgb.width, height: photo.rgb.height, values: &mirrored }, threads).len() >= MIN_TAGS {
            bail!("{who}: the photo is mirrored (its tags read only flipped left to right: a front camera's mirror image, or flipped in an editor): take it with the back camera, or flip it back");
        }
        // A photo of one level everywhere (white: over-exposed; black: the
        // lens covered) shows nothing, blurred or not.
        let (lo, hi) = values.iter().fold((u8::MAX, 0u8), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        if hi - lo < FLAT_PHOTO_CODES {
            let what = if lo >= 128 { "white: over-exposed, or of a lamp; lower the exposure" } else { "black: the lens covered, or the flash off in a dark room" };
            bail!("{who}: the photo is one level everywhere (codes {lo}-{hi}), {what}");
        }
        let s = markers::sharpness(&gray);
        if s < BLURRED_BELOW {
            bail!("{who}: no frame tags found, and the photo is blurred (sharpness {s:.2}, a sharp photo's is {BLURRED_BELOW} or more): hold still, let it focus");
        }
        bail!("{who}: no frame tags found: keep the whole printed frame in view, lit, and in focus");
    }
    // The frame is the one most of the tags name.
    let mut openings: Vec<(u32, usize)> = Vec::new();
    for m in &found {
        if let Some(cm) = FrameLayout::opening_of(m.id) {
            match openings.iter_mut().find(|(o, _)| *o == cm) {
                Some(e) => e.1 += 1,
                None => openings.push((cm, 1)),
            }
        }
    }
    openings.sort_by_key(|&(cm, n)| (std::cmp::Reverse(n), cm));
    let Some(&(cm, _)) = openings.first() else {
        bail!("{who}: its tag36h11 tags (ids {}) are not those of a flashmat frame", found.iter().map(|m| m.id.to_string()).collect::<Vec<_>>().join(", "));
    };
    let layout = FrameLayout::new(cm)?;
    let ours: Vec<Marker> = found.into_iter().filter(|m| layout.find(m.id).is_some()).collect();
    if ours.len() < MIN_TAGS {
        let s = markers::sharpness(&gray);
        let blur = if s < BLURRED_BELOW { format!("; the photo is blurred (sharpness {s:.2})") } else { String::new() };
        bail!("{who}: only {} of the frame's tags were found (at least {MIN_TAGS} are needed): keep the whole frame in view and in focus{blur}", ours.len());
    }
    Ok((layout, ours))
}

fn correspondences(layout: &FrameLayout, found: &[Marker]) -> Correspondences {
    found
        .iter()
        .filter_map(|m| layout.find(m.id).map(|t| (FrameLayout::corners(t), m.corners)))
        .flat_map(|(world, pixels)| world.into_iter().zip(pixels))
        .collect()
}

/// From photos of the frame to a capture: tags, camera, poses, rectified
/// openings. `on_progress(stage, done, total)`: stage 0 finds the tags
/// (per photo), 1 fits the camera, 2 rectifies (per photo).
pub fn capture(photos: &[FramePhoto], cfg: &CaptureConfig, mut on_progress: impl FnMut(usize, usize, usize)) -> Result<Capture> {
    ensure!(photos.len() >= 2, "a capture needs at least 2 photos of the frame, got {}", photos.len());
    ensure!(cfg.max_side >= MIN_SIDE, "--max-size must be at least {MIN_SIDE}, got {}", cfg.max_side);
    for photo in photos {
        check_exif_exposure(photo)?;
    }
    // RAW and 8-bit photos are on different scales (a RAW photo's white
    // level against a JPEG's tone curve): one capture takes one kind.
    if let (Some(raw), Some(coded)) = (photos.iter().find(|p| p.raw.is_some()), photos.iter().find(|p| p.raw.is_none())) {
        bail!("{} is a RAW photo and {} is not: a capture's photos are all RAW (DNG) or all JPEG/PNG/HEIC; take them in one format", name(&raw.path), name(&coded.path));
    }
    // The same photo twice (given twice, or a copy under another name)
    // would be a second position the frame's tags cannot tell apart.
    for (j, b) in photos.iter().enumerate() {
        if let Some(a) = photos[..j].iter().find(|a| (a.rgb.width, a.rgb.height) == (b.rgb.width, b.rgb.height) && a.rgb.data == b.rgb.data) {
            let how = if a.path == b.path { "given twice".to_string() } else { format!("the same pixels as {}", name(&a.path)) };
            bail!("{}: {how}: give each photo once, each from its own position", name(&b.path));
        }
    }
    let mut found = Vec::new();
    for (i, photo) in photos.iter().enumerate() {
        on_progress(0, i, photos.len());
        found.push(find_frame(photo, cfg.threads)?);
    }
    on_progress(0, photos.len(), photos.len());
    let layout = found[0].0.clone();
    if let Some((i, (other, _))) = found.iter().enumerate().find(|(_, (l, _))| l.opening_cm != layout.opening_cm) {
        bail!(
            "{}: it shows the {} cm frame, {} the {} cm one: one capture, one frame",
            name(&photos[i].path),
            other.opening_cm,
            name(&photos[0].path),
            layout.opening_cm
        );
    }
    let obs: Vec<Correspondences> = found.iter().map(|(_, m)| correspondences(&layout, m)).collect();
    let calibration = calibrate_photos(photos, &obs)?;
    on_progress(1, 1, 1);

    let mut results: Vec<PhotoResult> = Vec::new();
    for (i, photo) in photos.iter().enumerate() {
        let (k, pose) = (calibration.intrinsics[i], calibration.poses[i]);
        let camera = pose.centre();
        let offset = oriented_offset(cfg.flash_offset_mm, photo.orientation);
        let light = add(camera, pose.to_world_dir([offset[0], offset[1], 0.0]));
        ensure!(camera[2] > 0.0 && light[2] > 0.0, "{}: the camera is below the frame: the photo was taken from underneath?", name(&photo.path));
        results.push(PhotoResult { source: photo.path.clone(), markers: found[i].1.clone(), intrinsics: k, pose, camera, light, rms: calibration.rms[i] });
    }
    // Most overhead first, the others in the order given.
    let cameras: Vec<[f64; 3]> = results.iter().map(|r| r.camera).collect();
    let first = crate::data::captures::overhead_index(&cameras);
    let mut order: Vec<usize> = (0..results.len()).collect();
    order.remove(first);
    order.insert(0, first);

    let half = layout.opening_mm() / 2.0;
    let overhead = &results[first];
    let side = rectified_side(&overhead.intrinsics, &overhead.pose, half, cfg.max_side);
    // The paper first: where it says the photos' tone curve is not sRGB
    // (one curve for all of them), they are read through the pure power
    // that makes it linear before anything reads them
    // ([`photometry::srgb_mismatch`], [`photometry::power_gamma`]).
    let margin = layout.paper_margin_centre_mm();
    let read = |curve: photometry::ToneCurve| -> Vec<photometry::PaperReading> { order.iter().map(|&i| photometry::read_paper(&photos[i], &results[i], margin, curve)).collect() };
    let paper = read(photometry::ToneCurve::Srgb);
    let mismatch = if photos[0].raw.is_none() { photometry::srgb_mismatch(&paper) } else { None };
    let gamma = mismatch.and_then(|_| photometry::power_gamma(&read(photometry::ToneCurve::Power(1.0))));
    let curve = gamma.map_or(photometry::ToneCurve::Srgb, photometry::ToneCurve::Power);
    let paper = if gamma.is_some() { read(curve) } else { paper };
    let decode = |v: u8| curve.decode(v as f64 / 255.0) as f32;
    let mut rectified = Vec::new();
    for (n, &i) in order.iter().enumerate() {
        on_progress(2, n, order.len());
        let pixels = match &photos[i].raw {
            Some(raw) => rectify::Pixels::Linear(&raw.linear),
            None => rectify::Pixels::Coded(&photos[i].rgb),
        };
        rectified.push(rectify::rectify(pixels, &results[i].intrinsics, &results[i].pose, half, side, &decode));
    }
    on_progress(2, order.len(), order.len());
    // A grey photo among colour ones, named here while its file is the one
    // the user gave; on the openings brought to one white balance by the
    // paper, as the fit's check is, so a grey material with a cast in one
    // photo is not refused.
    let levels = photometry::relative_levels(&paper);
    let openings: Vec<tch::Tensor> = rectified
        .iter()
        .enumerate()
        .map(|(n, r)| {
            let opening = tch::Tensor::from_slice(r).view([3, side as i64, side as i64]);
            match &levels {
                Some(l) => opening / tch::Tensor::from_slice(&l[n].map(|v| v as f32)).view([3, 1, 1]),
                None => opening,
            }
        })
        .collect();
    if let Some((k, colour, most)) = crate::fit::photos::grey_among_colour(&openings) {
        return Err(crate::fit::photos::grey_photo_error(Path::new(&name(&photos[order[k]].path)), colour, most));
    }
    // Each photo's highlight point over the opening's half-width (mm are
    // the frame's, centred on the opening, as the capture folder's are).
    let half = layout.opening_mm() / 2.0;
    let highlights: Vec<Option<[f64; 2]>> = order
        .iter()
        .map(|&i| {
            let p = &results[i];
            let config = crate::geometry::LightView { light: p.light.map(|v| v / half), view: p.camera.map(|v| v / half) };
            Some(crate::fit::photos::highlight_point(&config))
        })
        .collect();
    if let Some(covered) = crate::fit::coverage::covered_photo(&rectified, side, &highlights) {
        return Err(crate::fit::coverage::covered_error(&name(&photos[order[covered.photo]].path), &covered));
    }
    let photos_out = order.iter().map(|&i| results[i].clone()).collect();
    Ok(Capture { layout, photos: photos_out, rectified, side, distortion: calibration.distortion, paper, gamma })
}

/// The opening's side in the photo's pixels (the mean of its four edges),
/// capped at `max_side`, a multiple of 8.
fn rectified_side(k: &Intrinsics, pose: &Pose, half: f64, max_side: usize) -> usize {
    let c = [[-half, -half], [half, -half], [half, half], [-half, half]].map(|[x, y]| pose.project(k, [x, y, 0.0]).unwrap_or([0.0, 0.0]));
    let edges = (0..4).map(|i| (c[i][0] - c[(i + 1) % 4][0]).hypot(c[i][1] - c[(i + 1) % 4][1])).sum::<f64>() / 4.0;
    ((edges.min(max_side as f64) as usize) / 8 * 8).max(MIN_SIDE)
}

/// First guesses (EXIF focal or the homographies', poses from each
/// homography), then the joint fit, then the checks that name a photo.
fn calibrate_photos(photos: &[FramePhoto], obs: &[Correspondences]) -> Result<Calibration> {
    let homographies: Vec<camera::Mat3> = obs.iter().map(|o| camera::homography(o)).collect::<Result<_>>()?;
    let sizes: Vec<(usize, usize)> = photos.iter().map(|p| (p.rgb.width, p.rgb.height)).collect();
    let (w0, h0) = sizes[0];
    // Photos of one phone at other sizes are downscaled copies (a photo
    // sent through a messenger loses its EXIF and half its pixels): the same
    // field of view, so focal lengths in pixels scale with the longer side.
    // A photo turned a quarter without its EXIF saying so (portrait among
    // landscape) is the same lens too: the calibration gives each size its
    // own principal point, and the distortion is radial. A photo of another
    // aspect ratio was cropped, and its lens centre and field of view are
    // unknown.
    for (p, &(w, h)) in photos.iter().zip(&sizes) {
        let (a, a0) = (w as f64 / h as f64, w0 as f64 / h0 as f64);
        ensure!(
            (a / a0 - 1.0).abs() < MAX_ASPECT_DIFFERENCE || (a * a0 - 1.0).abs() < MAX_ASPECT_DIFFERENCE,
            "{}: the photo is {w}x{h} pixels, {} is {w0}x{h0}, another shape: it was cropped; give every photo uncropped, as the phone took it",
            name(&p.path),
            name(&photos[0].path)
        );
    }
    let to_first = |(w, h): (usize, usize)| w0.max(h0) as f64 / w.max(h) as f64;
    // The first photo whose EXIF states a focal length, and that length in the first photo's pixels.
    let exif_photo = photos.iter().zip(&sizes).find_map(|(p, &s)| p.exif_focal.map(|f| (f * to_first(s), name(&p.path))));
    let exif = exif_photo.as_ref().map(|(f, _)| *f);
    // The homographies in the first photo's pixels, for the focal length they share.
    let in_first: Vec<camera::Mat3> = homographies.iter().zip(&sizes).map(|(h, &s)| [h[0].map(|v| v * to_first(s)), h[1].map(|v| v * to_first(s)), h[2]]).collect();
    let from_tags = camera::focal_from_homographies(&in_first, [w0 as f64 / 2.0, h0 as f64 / 2.0]);
    let focal = match (exif, from_tags) {
        (Some(f), _) => f,
        (None, Some(f)) => f,
        (None, None) => bail!("no focal length: the photos have no EXIF focal length, and all face the frame straight on; add a photo taken at a tilt"),
    };
    let poses: Vec<Pose> = homographies
        .iter()
        .zip(&sizes)
        .zip(photos)
        .map(|((h, &(w, hh)), p)| camera::pose_from_homography(h, &Intrinsics::centred(focal / to_first((w, hh)), w, hh)).ok_or_else(|| anyhow!("{}: no camera pose fits its tags", name(&p.path))))
        .collect::<Result<_>>()?;
    // The photos' perspective fixes the focal length only if one of them
    // looks at the frame at a slant; photos facing it straight on (even
    // from off to the side) give any value their noise makes, traded
    // against the distance.
    let slant = |p: &Pose| (-p.to_world_dir([0.0, 0.0, 1.0])[2]).clamp(-1.0, 1.0).acos().to_degrees();
    let most = poses.iter().map(slant).fold(0.0, f64::max);
    ensure!(
        exif.is_some() || most >= MIN_TILT_WITHOUT_EXIF_DEG,
        "no focal length: the photos have no EXIF focal length, and none looks at the frame at a slant of {MIN_TILT_WITHOUT_EXIF_DEG} degrees or more (the most: {most:.0}); add a photo taken at a tilt"
    );
    // Straight on with an EXIF focal length: that one, held.
    let cal = camera::calibrate(obs, &sizes, focal, &poses, most < MIN_TILT_WITHOUT_EXIF_DEG)?;
    let fitted = cal.intrinsics[0].focal / w0.max(h0) as f64;
    ensure!(
        FOCAL_RANGE.contains(&fitted),
        "the tags say a focal length of {:.2}x the photo's longer side, outside a phone's {}-{}: are the photos cropped, or of another frame?",
        fitted,
        FOCAL_RANGE.start(),
        FOCAL_RANGE.end()
    );
    for (i, p) in photos.iter().enumerate() {
        let limit = MAX_RMS_PER_1000_PX * sizes[i].0.max(sizes[i].1) as f64 / 1000.0;
        let limit = limit.max(1.0);
        if cal.rms[i] > limit {
            bail!(
                "{}: its tags are {:.1} px off the frame's layout after the fit (at most {limit:.1}): the print is not flat, or was scaled unevenly, or the photo is of another frame",
                name(&p.path),
                cal.rms[i]
            );
        }
    }
    if let Some((f, who)) = &exif_photo {
        let (f, fitted) = (*f, cal.intrinsics[0].focal);
        if (fitted / f - 1.0).abs() > FOCAL_AGREEMENT {
            bail!(
                "{who}: its EXIF says a focal length of {f:.0} px, the tags {fitted:.0} px: the photos are cropped or zoomed, the EXIF is of another lens, or the frame is not flat"
            );
        }
    }
    Ok(cal)
}

/// Writes the capture folder (`NN.png` rectified photos, ^2.2-encoded as
/// capture folders are, or `NN.dng`, 16-bit linear, from RAW photos; `camera_pos.txt`, `light_pos.txt` in mm;
/// `image_size.txt`: the opening in mm) and its picture `capture.jpg`, all
/// at once: into a temporary folder beside `dir`, renamed at the end, so
/// nothing is left half-written. `dir` must not exist, or be empty.
pub fn write_folder(capture: &Capture, dir: &Path, photos: &[FramePhoto]) -> Result<()> {
    if dir.exists() {
        let empty = std::fs::read_dir(dir).map_err(|e| anyhow!("cannot read {}: {e}", dir.display()))?.next().is_none();
        ensure!(empty, "{} exists and is not empty: choose a new folder for the capture", dir.display());
    }
    let parent = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(|e| anyhow!("cannot create {}: {e}", parent.display()))?;
    // Named as io's temporaries are, so that a folder an interrupted run
    // left half-written is removed by the next one.
    crate::io::remove_stale_temporaries(parent);
    let tmp = parent.join(format!(".{}.tmp-{}-0", name(dir), std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir(&tmp).map_err(|e| anyhow!("cannot create {}: {e}", tmp.display()))?;
    let written = (|| -> Result<()> {
        let side = capture.side;
        for (i, linear) in capture.rectified.iter().enumerate() {
            let source = photos.iter().find(|f| f.path == capture.photos[i].source).context("a capture's photo is missing from its inputs")?;
            if let Some(raw) = &source.raw {
                // RAW in, RAW out: 16-bit linear, its BaselineExposure kept.
                let image = crate::image::Image::from_data(3, side, side, linear.clone())?;
                let opts = crate::io::dng::DngOptions { bits: 16, black: 0, neutral: [1.0; 3], baseline_exposure: raw.baseline_gain.log2(), ..Default::default() };
                crate::io::dng::write_dng(&tmp.join(format!("{i:02}.dng")), &image, &opts)?;
            } else {
                let image = crate::image::Image::from_data(3, side, side, linear.iter().map(|&v| crate::spaces::gamma_encode(v.clamp(0.0, 1.0))).collect())?;
                crate::io::write_png(&tmp.join(format!("{i:02}.png")), &image, crate::io::BitDepth::Eight)?;
            }
        }
        let lines = |pick: fn(&PhotoResult) -> Vec3| -> String { capture.photos.iter().map(pick).map(|p| format!("{:.3},{:.3},{:.3}\n", p[0], p[1], p[2])).collect() };
        std::fs::write(tmp.join("camera_pos.txt"), lines(|p| p.camera))?;
        std::fs::write(tmp.join("light_pos.txt"), lines(|p| p.light))?;
        std::fs::write(tmp.join("image_size.txt"), format!("{}\n", capture.layout.opening_mm()))?;
        if let Some(exposures) = capture.folder_exposures(photos)? {
            let lines: String = exposures.iter().map(|[r, g, b]| format!("{r:.5},{g:.5},{b:.5}\n")).collect();
            std::fs::write(tmp.join(crate::data::captures::EXPOSURES_FILE), lines)?;
        }
        let picture = pictures::capture_picture(capture, photos)?;
        crate::io::write_jpeg(&tmp.join("capture.jpg"), &picture, 85)?;
        Ok(())
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    if dir.exists() {
        std::fs::remove_dir(dir).map_err(|e| anyhow!("cannot replace the empty folder {}: {e}", dir.display()))?;
    }
    std::fs::rename(&tmp, dir).map_err(|e| {
        let _ = std::fs::remove_dir_all(&tmp);
        anyhow!("cannot move the capture into {}: {e}", dir.display())
    })
}

/// Tilt of a camera from straight overhead, degrees.
pub fn tilt_deg(camera: Vec3) -> f64 {
    (camera[2] / length(camera)).clamp(-1.0, 1.0).acos().to_degrees()
}

#[cfg(test)]
mod tests;
