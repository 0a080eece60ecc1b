//! Image files in and out, and atomic file replacement.
//!
//! Reading: PNG and JPEG (8 or 16 bit; values scaled to [0, 1] exactly as
//! stored, *not* linearised), OpenEXR (float, returned as-is) and, built
//! with the `heif` feature, HEIC/HEIF and AVIF through libheif (`io::heif`:
//! codes like PNG's at the file's precision, or linear floats for PQ/HLG
//! HDR files; without the feature they are refused with a way to convert
//! them). The decoder is chosen from the file's signature, so a misnamed
//! file still reads; the extension only improves the error message for a
//! bad file.
//! Writing: PNG (8 or 16 bit, clamped to [0, 1]) and OpenEXR (float32).
//! This layer never applies display transforms (gamma, log, tone mapping):
//! callers decide the space (see `crate::spaces`).
//!
//! Every error is one line that names the file, and no input file, however
//! corrupt, makes these functions panic.

use crate::image::Image;
use crate::limits;
use anyhow::{anyhow, Result};
use std::io::{BufWriter, Cursor, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

pub mod dng;
#[cfg(feature = "heif")]
pub mod heif;
#[cfg(feature = "raw")]
mod raw;

/// Sample depth of a written PNG.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BitDepth {
    Eight,
    Sixteen,
}

/// Container format of an image file, as found from its signature.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileFormat {
    Png,
    Jpeg,
    Exr,
    /// HEIC/HEIF or AVIF with integer codes (SDR transfer).
    Heif,
    /// HEIC/HEIF or AVIF whose PQ, HLG or linear transfer was taken out:
    /// linear floats, 1.0 at SDR reference white.
    HeifLinear,
    /// A RAW photo (DNG ...; the `raw` feature): linear sRGB floats, 1.0
    /// at the sensor's white level, clipped there (`io::raw`).
    Raw,
}

impl FileFormat {
    /// Whether the samples are floats in a linear space (EXR, HDR HEIF)
    /// rather than integer codes in whatever encoding the producer used
    /// (PNG, JPEG, HEIF).
    pub fn is_float(self) -> bool {
        matches!(self, FileFormat::Exr | FileFormat::HeifLinear | FileFormat::Raw)
    }

    /// Whether the linear values stop at 1, where the sensor clipped, as an
    /// 8-bit photo's codes do (RAW), rather than going on (EXR, HDR HEIF).
    pub fn clips_at_one(self) -> bool {
        !self.is_float() || self == FileFormat::Raw
    }

    /// Whether the file is HEIF (HEIC, AVIF): decoded with its own
    /// rotation and mirroring applied, so its EXIF orientation is not.
    pub fn is_heif(self) -> bool {
        matches!(self, FileFormat::Heif | FileFormat::HeifLinear)
    }
}

const PNG_SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
const JPEG_SIGNATURE: &[u8] = &[0xFF, 0xD8, 0xFF];
const EXR_SIGNATURE: &[u8] = &[0x76, 0x2F, 0x31, 0x01];

/// A TIFF file, little- or big-endian (DNG and most camera RAW formats).
fn is_tiff(bytes: &[u8]) -> bool {
    bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*")
}

/// Extensions of RAW photos: DNG, and the camera formats rawler reads.
const RAW_EXTENSIONS: [&str; 11] = ["dng", "cr2", "cr3", "crw", "nef", "arw", "orf", "rw2", "raf", "pef", "srw"];

/// The refusal of a RAW photo by a build without the `raw` feature.
const RAW_NOT_BUILT: &str = "RAW photos (DNG) are not supported by this build: export the photo as JPEG from the phone, or build flashmat with `--features raw` (scripts/test.sh and scripts/demo.sh do)";

/// An ISO base-media (HEIF: HEIC, AVIF) file: a `ftyp` box first whose
/// brand is one of the image brands.
fn is_heif(bytes: &[u8]) -> bool {
    bytes.len() >= 12
        && &bytes[4..8] == b"ftyp"
        && matches!(&bytes[8..12], b"heic" | b"heix" | b"hevc" | b"heim" | b"heis" | b"mif1" | b"msf1" | b"avif" | b"avis")
}

/// One-line error for a file that could not be read.
fn read_error(path: &Path, reason: impl std::fmt::Display) -> anyhow::Error {
    // Decoder messages occasionally span lines; keep ours on one.
    let reason = reason.to_string().replace('\n', " ");
    anyhow!("cannot read image {}: {}", path.display(), reason)
}

fn extension_lowercase(path: &Path) -> Option<String> {
    path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase())
}

/// Reads a PNG, JPEG, OpenEXR or (with the `heif` feature) HEIC/HEIF or
/// AVIF image as `[C, H, W]`.
///
/// - PNG/JPEG: 8- or 16-bit codes divided by 255 or 65535, so values are in
///   [0, 1] and still in the file's encoding (typically gamma/sRGB).
///   Palette images are expanded. C is 1 (gray), 2 (gray + alpha),
///   3 (RGB) or 4 (RGBA): the channels the file has.
/// - OpenEXR: the first layer's channels as float32, unchanged: C is 3
///   (R, G, B), 4 (R, G, B, A), 1 (Y, or a single channel of any name)
///   or 2 (Y, A).
/// - HEIC/HEIF, AVIF: the primary image with the file's rotation and
///   mirroring applied, RGB or RGBA: 8-, 10- or 12-bit codes divided by
///   255, 1023 or 4095, or linear floats for PQ/HLG files (`io::heif`).
///
/// Errors (one line, naming the file) for a missing, empty, truncated or
/// corrupt file, an unsupported format or channel layout, and NaN/Inf
/// samples (with the first bad pixel's location).
pub fn read_image(path: &Path) -> Result<Image> {
    Ok(read_image_with_format(path)?.0)
}

/// Checks that `path` can be read whole: a regular file (a FIFO would
/// block forever, a device never ends) of at most [`limits::FILE_BYTES`].
/// Returns its length. Errors say why without the path (callers name it).
pub fn check_input_file(path: &Path) -> Result<u64> {
    use std::os::unix::fs::FileTypeExt;
    let meta = std::fs::metadata(path)?;
    let t = meta.file_type();
    let kind = if t.is_file() {
        None
    } else if t.is_dir() {
        Some("a directory")
    } else if t.is_fifo() {
        Some("a FIFO (named pipe)")
    } else if t.is_char_device() {
        Some("a character device")
    } else if t.is_block_device() {
        Some("a block device")
    } else if t.is_socket() {
        Some("a socket")
    } else {
        Some("a special file")
    };
    if let Some(kind) = kind {
        return Err(anyhow!("it is {kind}, not a regular file"));
    }
    limits::FILE_BYTES.check("the file", meta.len())?;
    Ok(meta.len())
}

/// Reads a whole input file after [`check_input_file`]. Errors say why
/// without the path (callers name it).
pub fn read_input(path: &Path) -> Result<Vec<u8>> {
    check_input_file(path)?;
    Ok(std::fs::read(path)?)
}

/// Why a decoder gave up: a damaged file, one refused by a limit before
/// its pixels were allocated, or one this build cannot decode.
enum DecodeError {
    Corrupt(String),
    TooLarge(String),
    #[cfg_attr(not(any(feature = "heif", feature = "raw")), allow(dead_code))]
    Unsupported(String),
}

impl<E: std::fmt::Display> From<E> for DecodeError {
    fn from(e: E) -> Self {
        DecodeError::Corrupt(e.to_string())
    }
}

/// Refuses dimensions from a file header above [`limits::IMAGE_PIXELS`]
/// (checked before the decoder allocates the pixels).
fn check_dimensions(width: u64, height: u64) -> std::result::Result<(), DecodeError> {
    limits::IMAGE_PIXELS
        .check_product(format_args!("the image ({width}x{height})"), &[width, height])
        .map_err(|e| DecodeError::TooLarge(e.to_string()))
}

/// [`read_image`] that also says which container the file was.
pub(crate) fn read_image_with_format(path: &Path) -> Result<(Image, FileFormat)> {
    let bytes = read_input(path).map_err(|e| read_error(path, format!("{e:#}")))?;
    if bytes.is_empty() {
        return Err(read_error(path, "the file is empty"));
    }
    let format = if bytes.starts_with(PNG_SIGNATURE) {
        FileFormat::Png
    } else if bytes.starts_with(JPEG_SIGNATURE) {
        FileFormat::Jpeg
    } else if bytes.starts_with(EXR_SIGNATURE) {
        FileFormat::Exr
    } else if is_heif(&bytes) && cfg!(feature = "heif") {
        FileFormat::Heif
    } else if (is_tiff(&bytes) || extension_lowercase(path).is_some_and(|e| RAW_EXTENSIONS.contains(&e.as_str()))) && cfg!(feature = "raw") {
        FileFormat::Raw
    } else if is_tiff(&bytes) || extension_lowercase(path).is_some_and(|e| RAW_EXTENSIONS.contains(&e.as_str())) {
        return Err(read_error(path, RAW_NOT_BUILT));
    } else if is_heif(&bytes) || (!cfg!(feature = "heif") && matches!(extension_lowercase(path).as_deref(), Some("heic" | "heif" | "avif"))) {
        return Err(read_error(
            path,
            "HEIC/AVIF photos are not supported by this build: convert it to JPEG first (`heif-convert IN.HEIC OUT.jpg` from Debian's libheif-examples, or set the phone's camera to \"Most Compatible\"), or build flashmat with `--features heif` (needs libheif-dev)",
        ));
    } else {
        return Err(match extension_lowercase(path).as_deref() {
            Some(ext @ ("png" | "jpg" | "jpeg" | "exr" | "heic" | "heif" | "avif")) => {
                read_error(path, format!("not a valid .{ext} file (unrecognised signature)"))
            }
            _ => read_error(path, format!("unsupported format (expected {})", supported_formats())),
        });
    };
    // The decoders are third-party code fed arbitrary bytes; turn any panic
    // on a hostile file into an ordinary error.
    let decoded = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match format {
        FileFormat::Png => decode_png(&bytes).map(|i| (i, format)),
        FileFormat::Jpeg => decode_jpeg(&bytes).map(|i| (i, format)),
        FileFormat::Exr => decode_exr(&bytes).map(|i| (i, format)),
        #[cfg(feature = "heif")]
        FileFormat::Heif | FileFormat::HeifLinear => heif::decode(&bytes),
        #[cfg(not(feature = "heif"))]
        FileFormat::Heif | FileFormat::HeifLinear => unreachable!("HEIF files are refused above without the heif feature"),
        #[cfg(feature = "raw")]
        FileFormat::Raw => raw::decode(&bytes).map(|i| (i, format)),
        #[cfg(not(feature = "raw"))]
        FileFormat::Raw => unreachable!("RAW files are refused above without the raw feature"),
    }))
    .unwrap_or_else(|_| Err(DecodeError::Corrupt("the decoder crashed (corrupt file?)".to_string())));
    let (image, format) = decoded.map_err(|e| {
        let kind = match format {
            FileFormat::Png => "PNG",
            FileFormat::Jpeg => "JPEG",
            FileFormat::Exr => "OpenEXR",
            #[cfg(feature = "heif")]
            FileFormat::Heif | FileFormat::HeifLinear => heif::kind(&bytes).0,
            #[cfg(not(feature = "heif"))]
            FileFormat::Heif | FileFormat::HeifLinear => "HEIF",
            FileFormat::Raw => "RAW",
        };
        match e {
            DecodeError::Corrupt(reason) => read_error(path, format!("corrupt or truncated {kind} file: {reason}")),
            DecodeError::TooLarge(reason) | DecodeError::Unsupported(reason) => read_error(path, reason),
        }
    })?;
    if image.height == 0 || image.width == 0 {
        return Err(read_error(path, "the image has no pixels"));
    }
    if let Some((c, y, x)) = image.find_non_finite() {
        return Err(read_error(path, format!("NaN/Inf value at row {y}, column {x}, channel {c}")));
    }
    Ok((image, format))
}

/// The formats this build reads, for error messages.
fn supported_formats() -> String {
    let mut formats = vec!["PNG", "JPEG", "OpenEXR"];
    if cfg!(feature = "heif") {
        formats.push("HEIC/HEIF, AVIF");
    }
    if cfg!(feature = "raw") {
        formats.push("DNG or camera RAW");
    }
    let last = formats.pop().unwrap_or_default();
    format!("{} or {last}", formats.join(", "))
}

/// The gain a RAW photo's camera meant for its linear values, 2^BaselineExposure
/// (DNG), so that they meet an 8-bit photo's at a normal exposure; 1 for
/// other files, and for builds without the `raw` feature (which read no RAW).
pub fn raw_baseline_gain(path: &Path) -> f64 {
    #[cfg(feature = "raw")]
    {
        // Most photos of a capture are JPEG or PNG: their first 4 bytes say so
        // without reading the file a second time.
        let mut magic = [0u8; 4];
        let head = std::fs::File::open(path).and_then(|mut f| std::io::Read::read_exact(&mut f, &mut magic));
        if head.is_err() || !is_tiff(&magic) {
            return 1.0;
        }
        let Ok(bytes) = read_input(path) else { return 1.0 };
        let stops = std::panic::catch_unwind(|| raw::baseline_exposure(&bytes)).ok().flatten().unwrap_or(0.0);
        // Beyond 16 stops is past what a 16-bit sensor value can hold: a
        // broken tag, not a camera (12-bit RAWs with unclipped flash peaks
        // reach 8-11 stops).
        2f64.powf(stops.clamp(-16.0, 16.0))
    }
    #[cfg(not(feature = "raw"))]
    {
        let _ = path;
        1.0
    }
}

/// The EXIF block of a HEIF (HEIC, AVIF) file as TIFF bytes, read by
/// libheif; `None` for other files, files without one, unreadable files and
/// builds without the `heif` feature.
pub fn heif_exif(path: &Path) -> Option<Vec<u8>> {
    #[cfg(feature = "heif")]
    {
        let bytes = read_input(path).ok()?;
        is_heif(&bytes).then(|| heif::exif(&bytes)).flatten()
    }
    #[cfg(not(feature = "heif"))]
    {
        let _ = path;
        None
    }
}

/// Interleaved `[H, W, C]` samples to a planar image, scaling each sample.
fn planar<T: Copy>(samples: &[T], channels: usize, height: usize, width: usize, scale: impl Fn(T) -> f32) -> Image {
    let mut image = Image::new(channels, height, width);
    let n = height * width;
    for (i, px) in samples.chunks_exact(channels).enumerate().take(n) {
        for (c, &v) in px.iter().enumerate() {
            image.data[c * n + i] = scale(v);
        }
    }
    image
}

/// PNG bytes to an image in [0, 1]. The header's size is checked before
/// the decoder allocates, and the decoder's own allocation limit is set to
/// what an image of that size needs.
fn decode_png(bytes: &[u8]) -> std::result::Result<Image, DecodeError> {
    use image::{DynamicImage as D, ImageDecoder};
    // The largest sample layout: 16-bit RGBA, 8 bytes per pixel (and the
    // row filters' working copy).
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(limits::IMAGE_PIXELS.get().saturating_mul(16));
    let mut decoder = image::codecs::png::PngDecoder::with_limits(Cursor::new(bytes), limits.clone())?;
    let (w, h) = decoder.dimensions();
    check_dimensions(w as u64, h as u64)?;
    limits.max_alloc = Some((w as u64 * h as u64).saturating_mul(16).max(1 << 20));
    decoder.set_limits(limits)?;
    let img = D::from_decoder(decoder)?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let s8 = |v: u8| v as f32 / 255.0;
    let s16 = |v: u16| v as f32 / 65535.0;
    Ok(match &img {
        D::ImageLuma8(b) => planar(b.as_raw(), 1, h, w, s8),
        D::ImageLumaA8(b) => planar(b.as_raw(), 2, h, w, s8),
        D::ImageRgb8(b) => planar(b.as_raw(), 3, h, w, s8),
        D::ImageRgba8(b) => planar(b.as_raw(), 4, h, w, s8),
        D::ImageLuma16(b) => planar(b.as_raw(), 1, h, w, s16),
        D::ImageLumaA16(b) => planar(b.as_raw(), 2, h, w, s16),
        D::ImageRgb16(b) => planar(b.as_raw(), 3, h, w, s16),
        D::ImageRgba16(b) => planar(b.as_raw(), 4, h, w, s16),
        other => return Err(DecodeError::Corrupt(format!("unsupported pixel layout {:?}", other.color()))),
    })
}

/// Whether the end-of-image marker (FF D9) follows the first scan of the
/// main image. Strict decoding misses a file cut within its last row of
/// blocks; the marker is its last two bytes. Segments before the first
/// scan are skipped by their lengths: an EXIF thumbnail inside one has an
/// end marker of its own. (Inside scan data an FF byte is always followed
/// by 00 or a restart marker, so FF D9 there is the real end; data after
/// it, such as a motion photo's video, is allowed.)
fn jpeg_has_end(bytes: &[u8]) -> bool {
    let mut i = 2; // after SOI
    while i + 1 < bytes.len() {
        if bytes[i] != 0xFF {
            return false;
        }
        let marker = bytes[i + 1];
        match marker {
            0xFF => i += 1, // fill byte
            0xDA => return bytes[i..].windows(2).any(|w| w == [0xFF, 0xD9]),
            0x01 | 0xD0..=0xD7 => i += 2,
            _ => {
                let Some(len) = bytes.get(i + 2..i + 4).map(|b| u16::from_be_bytes([b[0], b[1]]) as usize) else { return false };
                i += 2 + len;
            }
        }
    }
    false
}

/// JPEG bytes to an image in [0, 1], with zune-jpeg (the `image` crate's
/// decoder) in strict mode: without it a truncated file decodes with its
/// missing part filled grey, and markers in the wrong place are skipped.
/// Gray stays 1 channel; every other colour space becomes RGB.
fn decode_jpeg(bytes: &[u8]) -> std::result::Result<Image, DecodeError> {
    use zune_core::colorspace::ColorSpace;
    let options = zune_core::options::DecoderOptions::default().set_strict_mode(true).set_max_width(usize::MAX).set_max_height(usize::MAX);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(zune_core::bytestream::ZCursor::new(bytes), options);
    decoder.decode_headers()?;
    if !jpeg_has_end(bytes) {
        return Err(DecodeError::Corrupt("no end-of-image marker after the image data (truncated file)".into()));
    }
    let (w, h) = decoder.dimensions().ok_or("no image dimensions")?;
    check_dimensions(w as u64, h as u64)?;
    let (out, channels) = match decoder.input_colorspace() {
        Some(ColorSpace::Luma) => (ColorSpace::Luma, 1),
        _ => (ColorSpace::RGB, 3),
    };
    decoder.set_options(options.jpeg_set_out_colorspace(out));
    let pixels = decoder.decode()?;
    if pixels.len() != w * h * channels {
        return Err(DecodeError::Corrupt(format!("decoded {} samples, expected {}", pixels.len(), w * h * channels)));
    }
    Ok(planar(&pixels, channels, h, w, |v: u8| v as f32 / 255.0))
}

/// OpenEXR bytes to an image; see [`read_image`] for the channel rules.
fn decode_exr(bytes: &[u8]) -> std::result::Result<Image, DecodeError> {
    use exr::prelude::{read, FlatSamples, ReadChannels, ReadLayers, Vec2};
    // The headers first: every layer's size is checked before any pixel
    // block is allocated.
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), true)?;
    for header in &meta.headers {
        check_dimensions(header.layer_size.width() as u64, header.layer_size.height() as u64)?;
    }
    // Pedantic: a truncated file is an error rather than missing blocks.
    // Sequential: callers already load many files in parallel.
    let exr_image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .pedantic()
        .non_parallel()
        .from_buffered(Cursor::new(bytes))?;
    let layer = &exr_image.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let channels = &layer.channel_data.list;
    let find = |name: &str| channels.iter().position(|c| c.name.eq(name));
    let names: Vec<String> = channels.iter().map(|c| c.name.to_string()).collect();
    let order: Vec<usize> = match (find("R"), find("G"), find("B"), find("A"), find("Y")) {
        (Some(r), Some(g), Some(b), a, _) => [Some(r), Some(g), Some(b), a].into_iter().flatten().collect(),
        (_, _, _, a, Some(y)) => [Some(y), a].into_iter().flatten().collect(),
        _ if channels.len() == 1 => vec![0],
        _ => return Err(DecodeError::Corrupt(format!("unsupported channels {names:?} (expected R,G,B[,A] or Y)"))),
    };
    let mut image = crate::image::Image::new(order.len(), h, w);
    for (c, &k) in order.iter().enumerate() {
        let ch = &channels[k];
        if ch.sampling != Vec2(1, 1) {
            return Err(DecodeError::Corrupt(format!("channel {} is subsampled, which is not supported", ch.name)));
        }
        let plane = image.plane_mut(c);
        let n = match &ch.sample_data {
            FlatSamples::F16(v) => v.len(),
            FlatSamples::F32(v) => v.len(),
            FlatSamples::U32(v) => v.len(),
        };
        if n != plane.len() {
            return Err(DecodeError::Corrupt(format!("channel {} has {n} samples, expected {}", ch.name, plane.len())));
        }
        match &ch.sample_data {
            FlatSamples::F16(v) => plane.iter_mut().zip(v).for_each(|(o, s)| *o = s.to_f32()),
            FlatSamples::F32(v) => plane.copy_from_slice(v),
            FlatSamples::U32(v) => plane.iter_mut().zip(v).for_each(|(o, &s)| *o = s as f32),
        }
    }
    Ok(image)
}

/// Reads an image as 3 channels: RGB(A) keeps R, G, B (alpha dropped);
/// gray (with or without alpha) is replicated into R, G, B. `[3, H, W]`.
pub fn read_rgb(path: &Path) -> Result<Image> {
    Ok(to_rgb(&read_image(path)?))
}

/// Reads an image as 1 channel, `[1, H, W]`: the file's first channel (gray,
/// or R of an RGB image; the other channels are not checked or averaged).
pub fn read_gray(path: &Path) -> Result<Image> {
    Ok(first_channel(&read_image(path)?))
}

/// 3-channel view of a 1- to 4-channel image (see [`read_rgb`]).
pub(crate) fn to_rgb(image: &Image) -> Image {
    match image.channels {
        1 | 2 => Image::concat_channels(&[&first_channel(image), &first_channel(image), &first_channel(image)])
            .expect("planes of one image share their size"),
        _ => image.channel_range(0, 3).expect("3 or more channels"),
    }
}

/// Channel 0 as a `[1, H, W]` image.
pub(crate) fn first_channel(image: &Image) -> Image {
    image.channel_range(0, 1).expect("images have at least one channel")
}

/// One-line error for a file that could not be written.
fn write_error(path: &Path, reason: impl std::fmt::Display) -> anyhow::Error {
    let reason = reason.to_string().replace('\n', " ");
    anyhow!("cannot write {}: {}", path.display(), reason)
}

/// Checks what every encoder needs: 1 to 4 channels, a non-empty size that
/// fits the formats' 32-bit dimensions, and no NaN (which has no meaning in
/// a PNG and which [`read_image`] would refuse to read back).
fn check_writable(path: &Path, image: &Image) -> Result<()> {
    if !(1..=4).contains(&image.channels) {
        return Err(write_error(path, format!("{} channels, expected 1 (gray), 3 (RGB) or 4 (RGBA)", image.channels)));
    }
    if image.width == 0 || image.height == 0 || image.width > u32::MAX as usize || image.height > u32::MAX as usize {
        return Err(write_error(path, format!("unsupported image size {}x{}", image.width, image.height)));
    }
    if image.data.len() != image.channels * image.height * image.width {
        return Err(write_error(path, "image data does not match its shape"));
    }
    if let Some(i) = image.data.iter().position(|v| v.is_nan()) {
        let n = image.height * image.width;
        let (c, y, x) = (i / n, (i % n) / image.width, i % image.width);
        return Err(write_error(path, format!("NaN value at row {y}, column {x}, channel {c}")));
    }
    Ok(())
}

/// Planar image to interleaved `[H, W, C]` samples.
fn interleaved<T>(image: &Image, f: impl Fn(f32) -> T) -> Vec<T> {
    let n = image.height * image.width;
    let mut out = Vec::with_capacity(image.data.len());
    for i in 0..n {
        for c in 0..image.channels {
            out.push(f(image.data[c * n + i]));
        }
    }
    out
}

/// Writes a PNG of 1 (gray), 2 (gray + alpha), 3 (RGB) or 4 (RGBA)
/// channels. Values are clamped to [0, 1] and rounded to 8- or 16-bit codes
/// (Inf clamps; NaN is an error). The file is replaced atomically.
pub fn write_png(path: &Path, image: &Image, bits: BitDepth) -> Result<()> {
    use image::{DynamicImage as D, ImageBuffer};
    check_writable(path, image)?;
    let (w, h) = (image.width as u32, image.height as u32);
    let dynamic = match bits {
        BitDepth::Eight => {
            let raw = interleaved(image, crate::spaces::quantize_u8);
            match image.channels {
                1 => ImageBuffer::from_raw(w, h, raw).map(D::ImageLuma8),
                2 => ImageBuffer::from_raw(w, h, raw).map(D::ImageLumaA8),
                3 => ImageBuffer::from_raw(w, h, raw).map(D::ImageRgb8),
                _ => ImageBuffer::from_raw(w, h, raw).map(D::ImageRgba8),
            }
        }
        BitDepth::Sixteen => {
            let raw = interleaved(image, |v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16);
            match image.channels {
                1 => ImageBuffer::from_raw(w, h, raw).map(D::ImageLuma16),
                2 => ImageBuffer::from_raw(w, h, raw).map(D::ImageLumaA16),
                3 => ImageBuffer::from_raw(w, h, raw).map(D::ImageRgb16),
                _ => ImageBuffer::from_raw(w, h, raw).map(D::ImageRgba16),
            }
        }
    }
    .expect("buffer length follows from the checked shape");
    atomic_write(path, |tmp| {
        let mut out = BufWriter::new(std::fs::File::create(tmp)?);
        dynamic.write_to(&mut out, image::ImageFormat::Png)?;
        // Flush explicitly: BufWriter swallows errors when dropped.
        out.flush()?;
        Ok(())
    })
}

/// [`write_png`] with a pHYs chunk saying `dpi` pixels per inch, so image
/// viewers and printers size the page true (a printed frame's tags must
/// be their stated millimetres). The file is replaced atomically.
pub fn write_png_at_dpi(path: &Path, image: &Image, bits: BitDepth, dpi: f64) -> Result<()> {
    anyhow::ensure!(dpi.is_finite() && dpi > 0.0, "a PNG's resolution must be a number > 0 dpi, got {dpi}");
    write_png(path, image, bits)?;
    let png = std::fs::read(path).map_err(|e| anyhow::anyhow!("cannot read back {}: {e}", path.display()))?;
    atomic_write_bytes(path, &with_png_dpi(&png, dpi)?)
}

/// PNG bytes with a pHYs chunk (pixels per metre, both axes) after IHDR.
fn with_png_dpi(png: &[u8], dpi: f64) -> Result<Vec<u8>> {
    // Signature (8), then IHDR: length (4), type (4), 13 data bytes, CRC (4).
    const AFTER_IHDR: usize = 8 + 4 + 4 + 13 + 4;
    anyhow::ensure!(png.len() > AFTER_IHDR && &png[12..16] == b"IHDR", "not a PNG to give a resolution");
    let per_metre = (dpi / 0.0254).round() as u32;
    let mut chunk = Vec::with_capacity(21);
    chunk.extend_from_slice(&9u32.to_be_bytes());
    chunk.extend_from_slice(b"pHYs");
    chunk.extend_from_slice(&per_metre.to_be_bytes());
    chunk.extend_from_slice(&per_metre.to_be_bytes());
    chunk.push(1); // unit: the metre
    let crc = crc32fast::hash(&chunk[4..]);
    chunk.extend_from_slice(&crc.to_be_bytes());
    Ok([&png[..AFTER_IHDR], &chunk[..], &png[AFTER_IHDR..]].concat())
}

/// Writes an 8-bit JPEG (the display values as [`write_png`] would store
/// them, alpha dropped) at `quality` (1-100): report pictures, a tenth of
/// a PNG's size. Replaced atomically.
pub fn write_jpeg(path: &Path, image: &Image, quality: u8) -> Result<()> {
    use image::{DynamicImage as D, ImageBuffer};
    check_writable(path, image)?;
    let (w, h) = (image.width as u32, image.height as u32);
    let raw = interleaved(image, crate::spaces::quantize_u8);
    let dynamic = match image.channels {
        1 => ImageBuffer::from_raw(w, h, raw).map(D::ImageLuma8),
        2 => ImageBuffer::from_raw(w, h, raw).map(D::ImageLumaA8),
        3 => ImageBuffer::from_raw(w, h, raw).map(D::ImageRgb8),
        _ => ImageBuffer::from_raw(w, h, raw).map(D::ImageRgba8),
    }
    .expect("buffer length follows from the checked shape");
    let dynamic = if image.channels % 2 == 0 { D::ImageRgb8(dynamic.to_rgb8()) } else { dynamic };
    atomic_write(path, |tmp| {
        let mut out = BufWriter::new(std::fs::File::create(tmp)?);
        dynamic.write_with_encoder(image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100)))?;
        out.flush()?;
        Ok(())
    })
}

/// Encodes 8-bit RGB (`[H, W, 3]` interleaved) as a JPEG at `quality`
/// (1-100) in memory and decodes it again: what a phone's file keeps
/// (`data::phone`). -> the decoded `[H, W, 3]` bytes.
pub fn jpeg_round_trip(rgb: &[u8], width: usize, height: usize, quality: u8) -> Result<Vec<u8>> {
    let mut file = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut file, quality.clamp(1, 100)).encode(rgb, width as u32, height as u32, image::ExtendedColorType::Rgb8)?;
    Ok(image::load_from_memory_with_format(&file, image::ImageFormat::Jpeg)?.to_rgb8().into_raw())
}

/// Writes an uncompressed-precision (float32, lossless compression) OpenEXR
/// file: 1 channel as Y, 2 as Y, A, 3 as R, G, B, 4 as R, G, B, A. Values
/// are stored exactly (Inf allowed, NaN an error). Replaced atomically.
pub fn write_exr(path: &Path, image: &Image) -> Result<()> {
    use exr::prelude::{AnyChannel, AnyChannels, Encoding, FlatSamples, Layer, LayerAttributes, SmallVec, WritableImage};
    check_writable(path, image)?;
    let names: &[&str] = match image.channels {
        1 => &["Y"],
        2 => &["Y", "A"],
        3 => &["R", "G", "B"],
        _ => &["R", "G", "B", "A"],
    };
    let list: Vec<AnyChannel<FlatSamples>> = names
        .iter()
        .enumerate()
        .map(|(c, &name)| AnyChannel::new(name, FlatSamples::F32(image.plane(c).to_vec())))
        .collect();
    let layer = Layer::new(
        (image.width, image.height),
        LayerAttributes::default(),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(list)),
    );
    let exr_image = exr::image::Image::from_layer(layer);
    atomic_write(path, |tmp| {
        let mut out = BufWriter::new(std::fs::File::create(tmp)?);
        exr_image.write().non_parallel().to_buffered(&mut out).map_err(|e| anyhow!("{e}"))?;
        out.flush()?;
        Ok(())
    })
}

/// Writes by extension: `.png` as 8-bit PNG, `.exr` as float32 OpenEXR;
/// any other extension is an error. No transform is applied to the values.
pub fn write_image(path: &Path, image: &Image) -> Result<()> {
    match extension_lowercase(path).as_deref() {
        Some("png") => write_png(path, image, BitDepth::Eight),
        Some("exr") => write_exr(path, image),
        _ => Err(write_error(path, "unsupported extension (expected .png or .exr)")),
    }
}

/// Distinguishes temp files of concurrent writes to the same path within
/// one process (the PID alone would not).
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Removes the temporary file unless the write completed, including when
/// the writer panics.
struct TempGuard(Option<PathBuf>);

impl Drop for TempGuard {
    fn drop(&mut self) {
        if let Some(p) = self.0.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// Writes `path` all-or-nothing: `write` is called with a temporary path in
/// the same directory (`.NAME.tmp-PID-N`), and only when it succeeds is the
/// temporary renamed over `path`. On error (or panic) the temporary is
/// removed and any existing file at `path` is left untouched, so an
/// interrupted or failed write never leaves a partial file under the final
/// name. (Same directory, so the rename is atomic on one file system. No
/// fsync: this protects against failures of the process, not power loss.)
///
/// The directory must exist. Errors are one line naming `path`.
pub fn atomic_write<F: FnOnce(&Path) -> Result<()>>(path: &Path, write: F) -> Result<()> {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| write_error(path, "not a file path"))?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        let why = if dir.exists() { "is not a directory" } else { "does not exist" };
        return Err(write_error(path, format!("{} {why}", dir.display())));
    }
    // Renaming over a device or a FIFO would replace the node itself
    // (/dev/null as root); over a folder it fails late.
    if let Ok(m) = std::fs::symlink_metadata(path) {
        if !m.is_file() && !m.file_type().is_symlink() {
            return Err(write_error(path, "it exists and is not a regular file"));
        }
    }
    remove_stale_temporaries_once(dir);
    let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
    let mut guard = TempGuard(Some(tmp.clone()));
    write(&tmp).map_err(|e| write_error(path, format!("{e:#}")))?;
    if !tmp.is_file() {
        return Err(write_error(path, "the writer produced no file"));
    }
    std::fs::rename(&tmp, path).map_err(|e| write_error(path, e))?;
    guard.0 = None;
    Ok(())
}

/// The writer's process id of one of [`atomic_write`]'s temporaries
/// (`.NAME.tmp-PID-N`); None for any other file name.
fn temporary_writer(name: &str) -> Option<i32> {
    let (_, tail) = name.strip_prefix('.')?.rsplit_once(".tmp-")?;
    let (pid, n) = tail.split_once('-')?;
    n.parse::<u64>().ok()?;
    pid.parse::<i32>().ok().filter(|&p| p > 0)
}

/// Whether process `pid` runs (on this machine): kill(pid, 0) fails with
/// ESRCH only when there is no such process.
fn process_runs(pid: i32) -> bool {
    // SAFETY: signal 0 only checks that the process exists; nothing is sent.
    let exists = unsafe { libc::kill(pid, 0) } == 0;
    exists || std::io::Error::last_os_error().raw_os_error() != Some(libc::ESRCH)
}

/// Removes the temporaries of [`atomic_write`] in `dir` whose writer no
/// longer runs: what a process killed during a write (SIGKILL, the
/// out-of-memory killer) left. A running writer's temporary is kept.
/// Returns how many were removed; an unreadable folder removes none.
pub fn remove_stale_temporaries(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    let mut removed = 0;
    for entry in entries.flatten() {
        let stale = entry.file_name().to_str().and_then(temporary_writer).is_some_and(|pid| !process_runs(pid));
        if !stale {
            continue;
        }
        // Files of atomic writes, and folders written whole (a capture folder).
        let gone = match entry.file_type() {
            Ok(t) if t.is_file() => std::fs::remove_file(entry.path()).is_ok(),
            Ok(t) if t.is_dir() => std::fs::remove_dir_all(entry.path()).is_ok(),
            _ => false,
        };
        if gone {
            removed += 1;
        }
    }
    removed
}

/// [`remove_stale_temporaries`] the first time this process writes into
/// `dir` (once per folder: a dataset writer puts thousands of files in one).
fn remove_stale_temporaries_once(dir: &Path) {
    static SEEN: std::sync::Mutex<Option<std::collections::HashSet<PathBuf>>> = std::sync::Mutex::new(None);
    let key = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    let first = SEEN.lock().map(|mut seen| seen.get_or_insert_with(Default::default).insert(key)).unwrap_or(false);
    if first {
        remove_stale_temporaries(dir);
    }
}

/// Name of the lock file of a folder owned with [`lock_folder`].
pub const LOCK_FILE: &str = ".lock";

/// Ownership of a folder (a training run's): an exclusive `flock` on
/// `DIR/.lock`, which holds the owner's process id and host. The kernel
/// releases the lock when the process ends however it ends (SIGKILL
/// included), so a killed owner leaves no stuck lock; dropped, the lock
/// file is removed.
#[derive(Debug)]
pub struct FolderLock {
    /// Holds the lock until dropped (after `drop` removed the file).
    _file: std::fs::File,
    path: PathBuf,
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        // Removed while still locked: a process that opened the file in
        // between finds it gone after its flock and tries again.
        let _ = std::fs::remove_file(&self.path);
    }
}

fn flock(file: &std::fs::File, operation: i32) -> std::io::Result<()> {
    use std::os::unix::io::AsRawFd;
    // SAFETY: flock on a descriptor this File owns.
    if unsafe { libc::flock(file.as_raw_fd(), operation) } == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// "pid P on HOST", the owner's record in a lock file.
fn owner_record() -> String {
    let mut host = [0u8; 256];
    // SAFETY: gethostname writes at most `host.len()` bytes into the buffer.
    let ok = unsafe { libc::gethostname(host.as_mut_ptr().cast(), host.len()) } == 0;
    let end = host.iter().position(|&b| b == 0).unwrap_or(host.len());
    let host = if ok { String::from_utf8_lossy(&host[..end]).into_owned() } else { "this machine".into() };
    format!("pid {} on {host}", std::process::id())
}

/// The owner's record in the lock file at `path` ("" when it has none).
/// An owner writes its record just after it takes the lock, so an empty
/// file is read again for up to half a second before it counts as none
/// (a second run started beside the first has read it empty).
fn owner_record_of(path: &Path) -> String {
    for _ in 0..50 {
        let owner = std::fs::read_to_string(path).unwrap_or_default();
        if !owner.trim().is_empty() {
            return owner.trim().to_string();
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    String::new()
}

/// Takes ownership of the existing folder `dir` for this process (see
/// [`FolderLock`]). When another process owns it, the error is one line
/// naming the owner. Where the file system has no locks, the folder is
/// used unlocked, with a warning.
pub fn lock_folder(dir: &Path) -> Result<FolderLock> {
    use std::os::unix::fs::MetadataExt;
    let path = dir.join(LOCK_FILE);
    for _ in 0..100 {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| anyhow!("cannot lock {}: {e}", dir.display()))?;
        match flock(&file, libc::LOCK_EX | libc::LOCK_NB) {
            Ok(()) => {}
            Err(e) if e.raw_os_error() == Some(libc::EWOULDBLOCK) => {
                let owner = owner_record_of(&path);
                let owner = if owner.is_empty() { "another process".to_string() } else { format!("flashmat {owner}") };
                return Err(anyhow!("{} is in use by {owner}: one process at a time trains in a folder; wait for it to finish or stop it", dir.display()));
            }
            Err(e) => {
                eprintln!("warning: cannot lock {} ({e}); make sure no other flashmat uses it", dir.display());
                return Ok(FolderLock { _file: file, path });
            }
        }
        // Its previous owner may have removed the file between our open
        // and flock: only the file at the path counts.
        let same = matches!((file.metadata(), std::fs::metadata(&path)), (Ok(a), Ok(b)) if (a.dev(), a.ino()) == (b.dev(), b.ino()));
        if !same {
            continue;
        }
        let mut f = &file;
        f.set_len(0).and_then(|_| writeln!(f, "{}", owner_record())).map_err(|e| anyhow!("cannot lock {}: {e}", dir.display()))?;
        return Ok(FolderLock { _file: file, path });
    }
    Err(anyhow!("cannot lock {}: its lock file keeps changing", dir.display()))
}

/// Who owns `dir` ([`lock_folder`]) right now: "flashmat pid P on HOST",
/// or None when no process does.
pub fn folder_owner(dir: &Path) -> Option<String> {
    let path = dir.join(LOCK_FILE);
    let file = std::fs::File::open(&path).ok()?;
    match flock(&file, libc::LOCK_SH | libc::LOCK_NB) {
        Err(e) if e.raw_os_error() == Some(libc::EWOULDBLOCK) => Some(format!("flashmat {}", owner_record_of(&path))),
        _ => None,
    }
}

/// Writes bytes atomically (see [`atomic_write`]).
pub fn atomic_write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    atomic_write(path, |tmp| std::fs::write(tmp, bytes).map_err(Into::into))
}

/// Lists `dir`'s visible entries (names not starting with '.', which skips
/// our own temporaries), sorted by file name for determinism.
pub(crate) fn sorted_entries(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| anyhow!("cannot list {}: {e}", dir.display()))?;
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| anyhow!("cannot list {}: {e}", dir.display()))?;
        if entry.file_name().to_str().is_some_and(|n| !n.starts_with('.')) {
            out.push(entry.path());
        }
    }
    out.sort();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::bail;
    use std::os::unix::fs::FileTypeExt;

    fn ramp(channels: usize, h: usize, w: usize) -> Image {
        Image::from_fn(channels, h, w, |c, y, x| ((c * 37 + y * 11 + x * 5) % 97) as f32 / 96.0)
    }

    fn max_abs_diff(a: &Image, b: &Image) -> f32 {
        assert_eq!((a.channels, a.height, a.width), (b.channels, b.height, b.width));
        a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    fn message(e: anyhow::Error) -> String {
        let m = format!("{e:#}");
        assert!(!m.contains('\n'), "multi-line error: {m}");
        m
    }

    /// A one-row 8-bit indexed PNG, assembled chunk by chunk (the image
    /// crate cannot write palettes): zlib "stored" blocks need no deflate.
    fn indexed_png(palette: &[[u8; 3]], row: &[u8]) -> Vec<u8> {
        fn crc32(bytes: &[u8]) -> u32 {
            let mut crc = !0u32;
            for &b in bytes {
                crc ^= b as u32;
                for _ in 0..8 {
                    crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
                }
            }
            !crc
        }
        fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
            out.extend_from_slice(&(data.len() as u32).to_be_bytes());
            let body = [&kind[..], data].concat();
            out.extend_from_slice(&body);
            out.extend_from_slice(&crc32(&body).to_be_bytes());
        }
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&(row.len() as u32).to_be_bytes());
        ihdr.extend_from_slice(&1u32.to_be_bytes());
        ihdr.extend_from_slice(&[8, 3, 0, 0, 0]); // depth 8, indexed colour
        let raw = [&[0u8][..], row].concat(); // filter type 0
        let (mut a, mut b) = (1u32, 0u32);
        for &v in &raw {
            a = (a + v as u32) % 65521;
            b = (b + a) % 65521;
        }
        let mut zlib = vec![0x78, 0x01, 1];
        zlib.extend_from_slice(&(raw.len() as u16).to_le_bytes());
        zlib.extend_from_slice(&(!(raw.len() as u16)).to_le_bytes());
        zlib.extend_from_slice(&raw);
        zlib.extend_from_slice(&((b << 16) | a).to_be_bytes());
        let mut out = PNG_SIGNATURE.to_vec();
        chunk(&mut out, b"IHDR", &ihdr);
        chunk(&mut out, b"PLTE", &palette.concat());
        chunk(&mut out, b"IDAT", &zlib);
        chunk(&mut out, b"IEND", &[]);
        out
    }

    fn leftovers(dir: &Path) -> Vec<String> {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains(".tmp-"))
            .collect()
    }

    #[test]
    fn png_8_bit_round_trip_all_channel_counts() {
        let dir = tempfile::tempdir().unwrap();
        for c in 1..=4 {
            let im = ramp(c, 7, 9);
            let p = dir.path().join(format!("a{c}.png"));
            write_png(&p, &im, BitDepth::Eight).unwrap();
            let back = read_image(&p).unwrap();
            assert!(max_abs_diff(&im, &back) <= 0.5 / 255.0 + 1e-6, "c={c}");
            // Values are the stored codes / 255 exactly.
            assert_eq!(back.get(0, 3, 4) * 255.0, (im.get(0, 3, 4) * 255.0).round());
        }
        assert!(leftovers(dir.path()).is_empty());
    }

    #[test]
    fn jpeg_keeps_flat_colours_and_drops_alpha() {
        let dir = tempfile::tempdir().unwrap();
        for c in [1, 3, 4] {
            // A flat patch survives JPEG's 8x8 DCT up to about one code.
            let im = Image::filled(c, 16, 24, 0.4);
            let p = dir.path().join(format!("a{c}.jpg"));
            write_jpeg(&p, &im, 90).unwrap();
            let back = read_image(&p).unwrap();
            assert_eq!(back.channels, if c == 1 { 1 } else { 3 }, "c={c}");
            assert_eq!((back.width, back.height), (24, 16));
            assert!(back.data.iter().all(|v| (v - 0.4).abs() <= 1.5 / 255.0), "c={c}");
        }
        assert!(leftovers(dir.path()).is_empty());
    }

    #[test]
    fn a_png_at_a_dpi_says_it_and_reads_back_the_same() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        let im = Image::from_fn(1, 6, 4, |_, y, x| (y * 4 + x) as f32 / 23.0);
        write_png_at_dpi(&path, &im, BitDepth::Eight, 300.0).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        // pHYs right after IHDR: 300 dpi is 300 / 0.0254 = 11,811 pixels a metre on both axes, unit 1.
        assert_eq!(&bytes[37..41], b"pHYs");
        assert_eq!(u32::from_be_bytes(bytes[41..45].try_into().unwrap()), 11_811);
        assert_eq!(u32::from_be_bytes(bytes[45..49].try_into().unwrap()), 11_811);
        assert_eq!(bytes[49], 1);
        assert_eq!(u32::from_be_bytes(bytes[50..54].try_into().unwrap()), crc32fast::hash(&bytes[37..50]));
        // Decoded, the same pixels as the PNG without it.
        let plain = dir.path().join("plain.png");
        write_png(&plain, &im, BitDepth::Eight).unwrap();
        assert_eq!(read_image(&path).unwrap().data, read_image(&plain).unwrap().data);
        assert!(write_png_at_dpi(&path, &im, BitDepth::Eight, f64::NAN).is_err());
    }

    #[test]
    fn png_16_bit_round_trip_and_clamping() {
        let dir = tempfile::tempdir().unwrap();
        let mut im = ramp(3, 5, 6);
        im.set(0, 0, 0, -0.5);
        im.set(1, 0, 0, 7.0);
        im.set(2, 0, 0, f32::INFINITY);
        let p = dir.path().join("a.png");
        write_png(&p, &im, BitDepth::Sixteen).unwrap();
        let back = read_image(&p).unwrap();
        assert_eq!(back.pixel(0, 0), vec![0.0, 1.0, 1.0]);
        let clamped = im.map(|v| v.clamp(0.0, 1.0));
        assert!(max_abs_diff(&clamped, &back) <= 0.5 / 65535.0 + 1e-7);
        // 16-bit really keeps more than 8 bits.
        let fine = Image::filled(1, 2, 2, 1000.0 / 65535.0);
        write_png(&p, &fine, BitDepth::Sixteen).unwrap();
        assert!((read_image(&p).unwrap().data[0] * 65535.0 - 1000.0).abs() < 1e-2);
    }

    #[test]
    fn exr_round_trip_is_exact() {
        let dir = tempfile::tempdir().unwrap();
        for c in [1, 3, 4] {
            let im = Image::from_fn(c, 6, 5, |c, y, x| (c as f32 - 1.0) * 17.25 + y as f32 * 1e-3 - x as f32 * 123.5);
            let p = dir.path().join(format!("a{c}.exr"));
            write_exr(&p, &im).unwrap();
            assert_eq!(read_image(&p).unwrap(), im, "c={c}");
        }
        // HDR values beyond 1 and write_image's dispatch.
        let im = Image::filled(3, 2, 3, 1e6);
        let p = dir.path().join("b.EXR");
        write_image(&p, &im).unwrap();
        assert_eq!(read_image(&p).unwrap(), im);
    }

    #[test]
    fn jpeg_is_readable() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.jpg");
        let (w, h) = (32u32, 16u32);
        let buf = image::RgbImage::from_fn(w, h, |x, _| image::Rgb([200, (x * 4) as u8, 50]));
        buf.save_with_format(&p, image::ImageFormat::Jpeg).unwrap();
        let im = read_image(&p).unwrap();
        assert_eq!((im.channels, im.height, im.width), (3, 16, 32));
        let want = |c: usize, x: usize| [200.0, (x * 4) as f32, 50.0][c] / 255.0;
        for x in [0, 10, 31] {
            for c in 0..3 {
                assert!((im.get(c, 8, x) - want(c, x)).abs() < 0.04, "c={c} x={x}: {}", im.get(c, 8, x));
            }
        }
        let gray = image::GrayImage::from_pixel(8, 8, image::Luma([100]));
        let g = dir.path().join("g.jpeg");
        gray.save_with_format(&g, image::ImageFormat::Jpeg).unwrap();
        let im = read_image(&g).unwrap();
        assert_eq!(im.channels, 1);
        assert!((im.data[0] - 100.0 / 255.0).abs() < 0.02);
    }

    #[test]
    fn palette_png_is_expanded_and_format_found_by_content() {
        let dir = tempfile::tempdir().unwrap();
        // A 2x1 indexed PNG (palette: red, blue; pixels: blue, red).
        let bytes = indexed_png(&[[255, 0, 0], [0, 0, 255]], &[1, 0]);
        let p = dir.path().join("indexed.data"); // no telling extension
        std::fs::write(&p, bytes).unwrap();
        let im = read_image(&p).unwrap();
        assert_eq!(im.channels, 3);
        assert_eq!(im.pixel(0, 0), vec![0.0, 0.0, 1.0]);
        assert_eq!(im.pixel(0, 1), vec![1.0, 0.0, 0.0]);
    }

    #[test]
    fn rgb_and_gray_views() {
        let dir = tempfile::tempdir().unwrap();
        let gray = ramp(1, 3, 4);
        let p = dir.path().join("g.png");
        write_png(&p, &gray, BitDepth::Sixteen).unwrap();
        let rgb = read_rgb(&p).unwrap();
        assert_eq!(rgb.channels, 3);
        assert_eq!(rgb.plane(0), rgb.plane(2));
        let rgba = ramp(4, 3, 4);
        let p = dir.path().join("c.png");
        write_png(&p, &rgba, BitDepth::Sixteen).unwrap();
        let rgb = read_rgb(&p).unwrap();
        assert!(max_abs_diff(&rgb, &rgba.channel_range(0, 3).unwrap()) < 1e-4);
        let g = read_gray(&p).unwrap();
        assert!(max_abs_diff(&g, &rgba.channel_range(0, 1).unwrap()) < 1e-4);
        let ga = ramp(2, 3, 4);
        let p = dir.path().join("ga.png");
        write_png(&p, &ga, BitDepth::Eight).unwrap();
        assert_eq!(read_image(&p).unwrap().channels, 2);
        assert_eq!(read_rgb(&p).unwrap().plane(1), read_gray(&p).unwrap().plane(0));
    }

    #[cfg(not(feature = "raw"))]
    #[test]
    fn a_raw_photo_without_the_raw_feature_says_how_to_read_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("IMG_0001.dng");
        dng::write_dng(&path, &Image::filled(3, 8, 8, 0.5), &dng::DngOptions::default()).unwrap();
        let e = format!("{:#}", read_image(&path).unwrap_err());
        assert!(!e.contains('\n') && e.contains("IMG_0001.dng") && e.contains("--features raw") && e.contains("JPEG"), "{e}");
    }

    #[test]
    fn truncated_and_garbage_files_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("full.png");
        write_png(&png, &ramp(3, 64, 64), BitDepth::Eight).unwrap();
        let exr = dir.path().join("full.exr");
        write_exr(&exr, &ramp(3, 64, 64)).unwrap();
        for src in [&png, &exr] {
            let bytes = std::fs::read(src).unwrap();
            for keep in [bytes.len() / 3, bytes.len() - 20, 12, 4] {
                let p = dir.path().join(format!("cut{keep}_{}", src.file_name().unwrap().to_str().unwrap()));
                std::fs::write(&p, &bytes[..keep]).unwrap();
                let m = message(read_image(&p).unwrap_err());
                assert!(m.contains(p.to_str().unwrap()), "{m}");
            }
        }
        let garbage: Vec<u8> = (0..500u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
        for name in ["junk.png", "junk.exr", "junk.bin"] {
            let p = dir.path().join(name);
            std::fs::write(&p, &garbage).unwrap();
            let m = message(read_image(&p).unwrap_err());
            assert!(m.contains(name), "{m}");
        }
        // A valid signature followed by garbage.
        for sig in [PNG_SIGNATURE, JPEG_SIGNATURE, EXR_SIGNATURE] {
            let p = dir.path().join("sig.png");
            std::fs::write(&p, [sig, &garbage[..]].concat()).unwrap();
            let m = message(read_image(&p).unwrap_err());
            assert!(m.contains("sig.png") && m.contains("corrupt"), "{m}");
        }
        let empty = dir.path().join("empty.png");
        std::fs::write(&empty, b"").unwrap();
        assert!(message(read_image(&empty).unwrap_err()).contains("empty"));
        let missing = dir.path().join("missing.png");
        let m = message(read_rgb(&missing).unwrap_err());
        assert!(m.contains("missing.png") && m.contains("No such file"), "{m}");
        let m = message(read_gray(&missing).unwrap_err());
        assert!(m.contains("missing.png"), "{m}");
    }

    #[test]
    fn truncated_jpeg_is_an_error_not_a_grey_fill() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("full.jpg");
        write_jpeg(&p, &ramp(3, 64, 64), 90).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        for keep in [bytes.len() / 2, bytes.len() * 3 / 4, bytes.len() - 40] {
            let cut = dir.path().join(format!("cut{keep}.jpg"));
            std::fs::write(&cut, &bytes[..keep]).unwrap();
            let m = message(read_image(&cut).unwrap_err());
            assert!(m.contains(&format!("cut{keep}.jpg")) && m.contains("corrupt or truncated JPEG"), "{m}");
        }
    }

    /// Headers claiming 100000 x 100000 pixels (40 GB as f32 RGB) in files
    /// of a few hundred bytes: refused before the pixels are allocated.
    #[test]
    fn hostile_image_headers_are_refused_before_allocating() {
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("huge.png");
        write_png(&png, &ramp(3, 8, 8), BitDepth::Eight).unwrap();
        let mut b = std::fs::read(&png).unwrap();
        // IHDR: width and height at bytes 16..24, its CRC at 29..33.
        b[16..20].copy_from_slice(&100_000u32.to_be_bytes());
        b[20..24].copy_from_slice(&100_000u32.to_be_bytes());
        let crc = crc32fast::hash(&b[12..29]);
        b[29..33].copy_from_slice(&crc.to_be_bytes());
        std::fs::write(&png, &b).unwrap();
        let jpg = dir.path().join("huge.jpg");
        write_jpeg(&jpg, &ramp(3, 8, 8), 90).unwrap();
        let mut b = std::fs::read(&jpg).unwrap();
        // SOF0: FF C0, length, precision, height, width.
        let sof = b.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
        b[sof + 5..sof + 9].copy_from_slice(&[0xFF, 0xFF, 0xFF, 0xFF]);
        std::fs::write(&jpg, &b).unwrap();
        let exr = dir.path().join("huge.exr");
        write_exr(&exr, &ramp(1, 4, 4)).unwrap();
        let mut b = std::fs::read(&exr).unwrap();
        for name in [&b"dataWindow\0box2i\0"[..], b"displayWindow\0box2i\0"] {
            let at = b.windows(name.len()).position(|w| w == name).unwrap() + name.len() + 4;
            b[at + 8..at + 12].copy_from_slice(&99_999i32.to_le_bytes());
            b[at + 12..at + 16].copy_from_slice(&99_999i32.to_le_bytes());
        }
        std::fs::write(&exr, &b).unwrap();
        for (p, want) in [(&png, "(100000x100000)"), (&jpg, "(65535x65535)"), (&exr, "")] {
            let m = message(read_image(p).unwrap_err());
            assert!(m.contains(p.to_str().unwrap()) && m.contains(want), "{m}");
        }
        let m = message(read_image(&png).unwrap_err());
        assert!(m.contains("above the limit of 200000000") && m.contains("FLASHMAT_MAX_IMAGE_PIXELS"), "{m}");
    }

    #[test]
    fn special_files_are_refused_and_never_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.png");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let m = message(read_image(&fifo).unwrap_err());
        assert!(m.contains("pipe.png") && m.contains("FIFO"), "{m}");
        assert!(message(read_image(Path::new("/dev/zero")).unwrap_err()).contains("character device"));
        assert!(message(read_image(dir.path()).unwrap_err()).contains("directory"));
        // Writing over the FIFO would replace the node (a device as root).
        let m = message(write_png(&fifo, &ramp(3, 2, 2), BitDepth::Eight).unwrap_err());
        assert!(m.contains("pipe.png") && m.contains("not a regular file"), "{m}");
        assert!(std::fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());
        assert!(leftovers(dir.path()).is_empty());
        // A sparse file beyond the size limit is refused without being read.
        let big = dir.path().join("big.png");
        std::fs::File::create(&big).unwrap().set_len(limits::FILE_BYTES.get() + 1).unwrap();
        let m = message(read_image(&big).unwrap_err());
        assert!(m.contains("big.png") && m.contains("FLASHMAT_MAX_FILE_BYTES"), "{m}");
    }

    #[test]
    fn non_finite_exr_reports_first_bad_pixel() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nan.exr");
        let mut im = ramp(3, 4, 5);
        im.set(1, 2, 3, f32::INFINITY);
        im.set(2, 3, 0, f32::INFINITY);
        write_exr(&p, &im).unwrap();
        let m = message(read_image(&p).unwrap_err());
        assert!(m.contains("nan.exr") && m.contains("row 2, column 3, channel 1"), "{m}");
        assert!(message(read_rgb(&p).unwrap_err()).contains("row 2, column 3"));
        // NaN cannot be written; craft it with the exr crate directly.
        exr::prelude::write_rgb_file(&p, 3, 2, |x, y| (0.5f32, if (x, y) == (1, 1) { f32::NAN } else { 0.0 }, 0.25f32))
            .unwrap();
        let m = message(read_gray(&p).unwrap_err());
        assert!(m.contains("NaN/Inf") && m.contains("row 1, column 1, channel 1"), "{m}");
    }

    #[test]
    fn write_errors_are_clear() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        let m = message(write_png(&p, &ramp(5, 2, 2), BitDepth::Eight).unwrap_err());
        assert!(m.contains("x.png") && m.contains("5 channels"), "{m}");
        let mut nan = ramp(3, 2, 2);
        nan.set(1, 1, 0, f32::NAN);
        assert!(message(write_exr(&p, &nan).unwrap_err()).contains("row 1, column 0, channel 1"));
        let m = message(write_image(&dir.path().join("x.tiff"), &ramp(3, 2, 2)).unwrap_err());
        assert!(m.contains("x.tiff") && m.contains("extension"), "{m}");
        let m = message(write_image(&dir.path().join("no/such/dir/x.png"), &ramp(3, 2, 2)).unwrap_err());
        assert!(m.contains("no/such/dir/x.png") && m.contains("does not exist"), "{m}");
        // A "directory" that is a file: unwritable even for root.
        let file = dir.path().join("plain");
        std::fs::write(&file, b"x").unwrap();
        let m = message(write_image(&file.join("x.exr"), &ramp(3, 2, 2)).unwrap_err());
        assert!(m.contains("plain/x.exr") && m.contains("not a directory"), "{m}");
        assert_eq!(leftovers(dir.path()), Vec::<String>::new());
    }

    #[test]
    #[cfg(unix)]
    fn unwritable_directory_is_a_clear_error() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let ro = dir.path().join("ro");
        std::fs::create_dir(&ro).unwrap();
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        // Root ignores permissions; only check where they apply.
        if std::fs::write(ro.join("probe"), b"").is_err() {
            let m = message(write_png(&ro.join("x.png"), &ramp(1, 2, 2), BitDepth::Eight).unwrap_err());
            assert!(m.contains("ro/x.png") && m.contains("ermission"), "{m}");
        }
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
    }

    #[test]
    fn atomic_write_keeps_old_file_and_no_temp_on_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model.bin");
        std::fs::write(&p, b"old contents").unwrap();
        let mut seen = PathBuf::new();
        let err = atomic_write(&p, |tmp| {
            seen = tmp.to_path_buf();
            std::fs::write(tmp, b"half")?;
            bail!("disk on fire")
        })
        .unwrap_err();
        let m = message(err);
        assert!(m.contains("model.bin") && m.contains("disk on fire"), "{m}");
        assert_eq!(seen.parent(), Some(dir.path()));
        assert!(seen.file_name().unwrap().to_str().unwrap().starts_with(".model.bin.tmp-"));
        assert!(!seen.exists());
        assert_eq!(std::fs::read(&p).unwrap(), b"old contents");
        assert!(leftovers(dir.path()).is_empty());

        // A panicking writer also leaves nothing behind.
        let r = std::panic::catch_unwind(|| {
            let _ = atomic_write(&p, |tmp| {
                std::fs::write(tmp, b"partial").unwrap();
                panic!("writer bug")
            });
        });
        assert!(r.is_err());
        assert!(leftovers(dir.path()).is_empty());
        assert_eq!(std::fs::read(&p).unwrap(), b"old contents");

        // A writer that writes nothing is an error, not an empty file.
        assert!(atomic_write(&p, |_| Ok(())).is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"old contents");

        atomic_write(&p, |tmp| Ok(std::fs::write(tmp, b"new")?)).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        assert!(leftovers(dir.path()).is_empty());
    }

    #[test]
    fn failed_image_write_does_not_clobber() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("keep.png");
        write_png(&p, &ramp(3, 4, 4), BitDepth::Eight).unwrap();
        let before = std::fs::read(&p).unwrap();
        let mut bad = ramp(3, 4, 4);
        bad.data[5] = f32::NAN;
        assert!(write_png(&p, &bad, BitDepth::Eight).is_err());
        assert_eq!(std::fs::read(&p).unwrap(), before);
    }

    /// A process id that ran and has ended (a finished child's).
    pub(crate) fn ended_pid() -> i32 {
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id() as i32;
        child.wait().unwrap();
        pid
    }

    #[test]
    fn stale_temporaries_of_ended_writers_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let dead = ended_pid();
        let own = std::process::id();
        for name in [
            format!(".checkpoint.safetensors.tmp-{dead}-0"),
            format!(".m.nmat.tmp-{own}-3"),
            format!("visible.tmp-{dead}-0"),
            ".notes.tmp-x-1".to_string(),
            "kept.png".to_string(),
        ] {
            std::fs::write(d.join(name), b"x").unwrap();
        }
        assert_eq!(temporary_writer(&format!(".a.b.tmp-{dead}-7")), Some(dead));
        assert_eq!(temporary_writer(".a.tmp-0-1"), None);
        assert_eq!(remove_stale_temporaries(d), 1);
        let left: Vec<String> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        assert_eq!(left.len(), 4, "{left:?}");
        assert!(!d.join(format!(".checkpoint.safetensors.tmp-{dead}-0")).exists());
        // Any write into a folder removes them there (once per folder).
        let sub = d.join("sub");
        std::fs::create_dir(&sub).unwrap();
        std::fs::write(sub.join(format!(".out.png.tmp-{dead}-2")), b"x").unwrap();
        atomic_write_bytes(&sub.join("out.txt"), b"ok").unwrap();
        assert_eq!(std::fs::read_dir(&sub).unwrap().count(), 1);
        // A folder an interrupted writer left half-written goes too.
        let folder = d.join(format!(".capture.tmp-{dead}-0"));
        std::fs::create_dir(&folder).unwrap();
        std::fs::write(folder.join("00.png"), b"partial").unwrap();
        assert_eq!(remove_stale_temporaries(d), 1);
        assert!(!folder.exists());
    }

    #[test]
    fn a_folder_has_one_owner_at_a_time() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        assert_eq!(folder_owner(d), None);
        let lock = lock_folder(d).unwrap();
        let record = std::fs::read_to_string(d.join(LOCK_FILE)).unwrap();
        assert!(record.starts_with(&format!("pid {} on ", std::process::id())), "{record}");
        // flock locks belong to the open file: a second owner in this
        // process is refused as another process would be.
        let e = lock_folder(d).unwrap_err().to_string();
        assert!(e.contains(&format!("is in use by flashmat pid {}", std::process::id())) && !e.contains('\n'), "{e}");
        assert!(folder_owner(d).unwrap().contains(&format!("pid {}", std::process::id())));
        drop(lock);
        assert!(!d.join(LOCK_FILE).exists());
        assert_eq!(folder_owner(d), None);
        // A lock file left by a killed owner is not a lock.
        std::fs::write(d.join(LOCK_FILE), "pid 1 on elsewhere\n").unwrap();
        let again = lock_folder(d).unwrap();
        drop(again);
        assert!(lock_folder(&d.join("missing")).unwrap_err().to_string().contains("cannot lock"));
    }
}
