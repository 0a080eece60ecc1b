//! HEIC/HEIF and AVIF files through the system libheif (the `heif` cargo
//! feature; Debian's `libheif-dev`, 1.14 or newer, installed by
//! `scripts/install-libheif.sh`).
//!
//! The primary image is decoded with libheif's own transformations applied
//! (rotation `irot`, mirroring `imir`, clean aperture `clap`): a HEIF file
//! stores its orientation there, and the EXIF orientation tag inside it is
//! informative only (ISO/IEC 23008-12), so flashmat does not turn the
//! photo a second time by it (`infer::camera`).
//!
//! Samples come back as [`super::read_image`] gives PNG and JPEG: codes in
//! [0, 1] in the file's encoding, at the file's precision (8 bits, or 10 or
//! 12 bits divided by 1023 or 4095, like a 16-bit PNG), to be decoded by the
//! caller with the sRGB curve. Files whose colour information (`nclx`) says
//! their transfer is PQ or HLG (HDR photos) or linear are instead returned
//! as linear floats, like OpenEXR: 1.0 is SDR reference white (203 cd/m²
//! for PQ, 75% signal for HLG, ITU-R BT.2408).

use super::{check_dimensions, DecodeError, FileFormat};
use crate::image::Image;
use libheif_rs::{ColorSpace, CompressionFormat, HeifContext, LibHeif, RgbChroma, TransferCharacteristics};
use std::sync::OnceLock;

/// libheif initialised once for the process (its plugins are global).
fn lib() -> &'static LibHeif {
    static LIB: OnceLock<LibHeif> = OnceLock::new();
    LIB.get_or_init(LibHeif::new)
}

/// What a HEIF file holds, by the brands of its `ftyp` box (major, then
/// compatible ones): AVIF (AV1) when one is `avif` or `avis`, else HEIC
/// (HEVC; the generic `mif1` files phones write are HEVC).
pub(super) fn kind(bytes: &[u8]) -> (&'static str, CompressionFormat) {
    let size = bytes.get(..4).map_or(0, |b| u32::from_be_bytes([b[0], b[1], b[2], b[3]]) as usize);
    let ftyp = &bytes[..size.min(bytes.len()).min(256)];
    // Major brand at 8, minor version at 12, compatible brands from 16.
    let brands = ftyp.get(8..12).into_iter().chain(ftyp.get(16..).unwrap_or(&[]).chunks_exact(4));
    let av1 = brands.into_iter().any(|b| b == b"avif" || b == b"avis");
    if av1 {
        ("AVIF", CompressionFormat::Av1)
    } else {
        ("HEIC", CompressionFormat::Hevc)
    }
}

/// Whether this libheif can decode `format` (its AV1 decoder comes from
/// libdav1d or libaom, its HEVC one from libde265, each optional).
pub fn have_decoder(format: CompressionFormat) -> bool {
    lib();
    // SAFETY: a query of libheif's plugin table, initialised by `lib()`.
    unsafe { libheif_sys::heif_have_decoder_for_format(format as libheif_sys::heif_compression_format) != 0 }
}

/// The one line for a file whose codec this libheif cannot decode.
fn no_decoder(name: &str, format: CompressionFormat) -> String {
    let (codec, from) = match format {
        CompressionFormat::Av1 => ("AV1", "libdav1d or libaom; Debian 13 on: libheif-plugin-dav1d"),
        _ => ("HEVC", "libde265; Debian 13 on: libheif-plugin-libde265"),
    };
    format!("this system's libheif has no {codec} decoder, which {name} photos need (a libheif with {from}; or convert it to JPEG first: `heif-convert IN OUT.jpg`)")
}

fn corrupt(e: libheif_rs::HeifError) -> DecodeError {
    // libheif's own text ("Invalid input: No 'ftyp' box"), not the Debug
    // names of its codes.
    let message = e.message.trim();
    DecodeError::Corrupt(if message.is_empty() { format!("{:?}", e.code) } else { message.to_string() })
}

/// Linear light from a PQ code (SMPTE ST 2084), in units of SDR reference
/// white (203 cd/m², ITU-R BT.2408).
pub(crate) fn pq_to_linear(code: f32) -> f32 {
    let (m1, m2) = (2610.0 / 16384.0, 2523.0 / 4096.0 * 128.0);
    let (c1, c2, c3) = (3424.0 / 4096.0, 2413.0 / 4096.0 * 32.0, 2392.0 / 4096.0 * 32.0);
    let p = (code.clamp(0.0, 1.0) as f64).powf(1.0 / m2);
    let nits = 10000.0 * ((p - c1).max(0.0) / (c2 - c3 * p)).powf(1.0 / m1);
    (nits / 203.0) as f32
}

/// Scene light from an HLG code (ITU-R BT.2100's inverse OETF), in units of
/// the scene light that reference white (75% signal, BT.2408) encodes.
pub(crate) fn hlg_to_linear(code: f32) -> f32 {
    let (a, b, c) = (0.178_832_77, 0.284_668_92, 0.559_910_73);
    let scene = |e: f64| if e <= 0.5 { e * e / 3.0 } else { (((e - c) / a).exp() + b) / 12.0 };
    (scene(code.clamp(0.0, 1.0) as f64) / scene(0.75)) as f32
}

/// Decodes the primary image of a HEIF file (see the module docs): `[C, H, W]`
/// with C = 3 (RGB) or 4 (RGBA), and [`FileFormat::Heif`] (codes) or
/// [`FileFormat::HeifLinear`] (linear floats).
pub(super) fn decode(bytes: &[u8]) -> Result<(Image, FileFormat), DecodeError> {
    let lib = lib();
    let (name, format) = kind(bytes);
    let ctx = HeifContext::read_from_bytes(bytes).map_err(corrupt)?;
    let handle = ctx.primary_image_handle().map_err(corrupt)?;
    check_dimensions(handle.width() as u64, handle.height() as u64)?;
    if !have_decoder(format) {
        return Err(DecodeError::Unsupported(no_decoder(name, format)));
    }
    let alpha = handle.has_alpha_channel();
    let high = handle.luma_bits_per_pixel() > 8;
    let chroma = match (high, alpha) {
        (false, false) => RgbChroma::Rgb,
        (false, true) => RgbChroma::Rgba,
        (true, false) => RgbChroma::HdrRgbLe,
        (true, true) => RgbChroma::HdrRgbaLe,
    };
    let image = lib.decode(&handle, ColorSpace::Rgb(chroma), None).map_err(|e| match e.sub_code {
        libheif_rs::HeifErrorSubCode::UnsupportedCodec => DecodeError::Unsupported(format!("libheif cannot decode this {name} file's codec: {}", e.message.trim())),
        _ => corrupt(e),
    })?;
    let planes = image.planes();
    let plane = planes.interleaved.ok_or_else(|| DecodeError::Corrupt("libheif returned no RGB plane".into()))?;
    let (w, h) = (plane.width as usize, plane.height as usize);
    check_dimensions(w as u64, h as u64)?;
    let channels = if alpha { 4 } else { 3 };
    let bytes_per_sample = if high { 2 } else { 1 };
    let row = w * channels * bytes_per_sample;
    if row > plane.stride || plane.stride.checked_mul(h).is_none_or(|n| n > plane.data.len()) {
        return Err(DecodeError::Corrupt(format!("libheif returned a {w}x{h} plane of {} bytes, stride {}", plane.data.len(), plane.stride)));
    }
    let bits = if high { plane.bits_per_pixel } else { 8 };
    if !(8..=16).contains(&bits) {
        return Err(DecodeError::Corrupt(format!("{bits} bits per sample")));
    }
    let max = ((1u32 << bits) - 1) as f32;
    let mut out = Image::new(channels, h, w);
    let n = w * h;
    for y in 0..h {
        let line = &plane.data[y * plane.stride..][..row];
        for x in 0..w {
            for c in 0..channels {
                let k = (x * channels + c) * bytes_per_sample;
                let code = if high { u16::from_le_bytes([line[k], line[k + 1]]) as f32 } else { line[k] as f32 };
                out.data[c * n + y * w + x] = (code / max).min(1.0);
            }
        }
    }
    // The transfer, from the file's `colr` box, else what the decoder
    // attached to the picture.
    let transfer = handle.color_profile_nclx().or_else(|| image.color_profile_nclx()).map(|p| p.transfer_characteristics());
    let linearise: Option<fn(f32) -> f32> = match transfer {
        Some(TransferCharacteristics::ITU_R_BT_2100_0_PQ) => Some(pq_to_linear),
        Some(TransferCharacteristics::ITU_R_BT_2100_0_HLG) => Some(hlg_to_linear),
        Some(TransferCharacteristics::Linear) => Some(|v| v),
        _ => None,
    };
    Ok(match linearise {
        Some(f) => {
            // Alpha stays as stored.
            out.data[..3 * n].iter_mut().for_each(|v| *v = f(*v));
            (out, FileFormat::HeifLinear)
        }
        None => (out, FileFormat::Heif),
    })
}

/// The EXIF block of a HEIF file's primary image, as TIFF bytes (libheif's
/// block starts with a 4-byte big-endian offset to the TIFF header), or
/// `None` when there is none or the file does not parse.
pub(super) fn exif(bytes: &[u8]) -> Option<Vec<u8>> {
    lib();
    let ctx = HeifContext::read_from_bytes(bytes).ok()?;
    let handle = ctx.primary_image_handle().ok()?;
    let mut ids = [0; 4];
    let found = handle.metadata_block_ids(&mut ids, b"Exif");
    let block = ids[..found.min(ids.len())].iter().find_map(|&id| handle.metadata(id).ok())?;
    let offset = u32::from_be_bytes(block.get(..4)?.try_into().ok()?) as usize;
    block.get(4usize.checked_add(offset)?..).filter(|t| !t.is_empty()).map(<[u8]>::to_vec)
}

/// How [`write_heif`] encodes.
#[derive(Clone, Debug, PartialEq)]
pub struct HeifEncoding {
    /// AVIF (AV1) rather than HEIC (HEVC).
    pub av1: bool,
    /// Bits per sample: 8, 10 or 12.
    pub bits: u8,
    /// The EXIF orientation (1..=8) written as the file's `irot` / `imir`
    /// (the pixels are stored as given; readers turn them).
    pub orientation: u16,
    /// The nclx transfer characteristic written in a `colr` box (16: PQ,
    /// 18: HLG), if any.
    pub transfer: Option<u32>,
    /// An EXIF block (TIFF bytes) attached to the image.
    pub exif: Option<Vec<u8>>,
}

impl Default for HeifEncoding {
    fn default() -> Self {
        HeifEncoding { av1: false, bits: 8, orientation: 1, transfer: None, exif: None }
    }
}

fn check(e: libheif_sys::heif_error) -> anyhow::Result<()> {
    if e.code == 0 {
        return Ok(());
    }
    // SAFETY: libheif's messages are C strings that outlive the call.
    let message = if e.message.is_null() { String::new() } else { unsafe { std::ffi::CStr::from_ptr(e.message) }.to_string_lossy().into_owned() };
    anyhow::bail!("libheif: {message}")
}

/// Writes `image` (`[3, H, W]`, codes in [0, 1]) as a HEIC or AVIF file
/// with libheif's encoders at quality 95 (atomically). flashmat reads
/// HEIF photos and writes none; the tests make their phone photos with
/// it. Uses libheif-sys directly: libheif-rs 0.20 frees its encoding
/// options before it encodes with them.
pub fn write_heif(path: &std::path::Path, image: &Image, spec: &HeifEncoding) -> anyhow::Result<()> {
    use libheif_sys as lh;
    anyhow::ensure!(image.channels == 3, "write_heif takes RGB images, not {} channels", image.channels);
    anyhow::ensure!(matches!(spec.bits, 8 | 10 | 12), "write_heif writes 8, 10 or 12 bits, not {}", spec.bits);
    let (w, h) = (i32::try_from(image.width)?, i32::try_from(image.height)?);
    let format = if spec.av1 { CompressionFormat::Av1 } else { CompressionFormat::Hevc };
    lib();
    super::atomic_write(path, |tmp| {
        let name = std::ffi::CString::new(tmp.as_os_str().as_encoded_bytes())?;
        // SAFETY: every pointer comes from libheif, is checked before use,
        // and is released once (below, whatever happened); the plane is
        // written within stride x height bytes.
        unsafe {
            let ctx = lh::heif_context_alloc();
            let nclx = lh::heif_nclx_color_profile_alloc();
            let options = lh::heif_encoding_options_alloc();
            let (mut img, mut encoder, mut handle) = (std::ptr::null_mut(), std::ptr::null_mut(), std::ptr::null_mut());
            let result = (|| -> anyhow::Result<()> {
                anyhow::ensure!(!ctx.is_null() && !nclx.is_null() && !options.is_null(), "libheif: out of memory");
                let chroma = if spec.bits > 8 { lh::heif_chroma_heif_chroma_interleaved_RRGGBB_LE } else { lh::heif_chroma_heif_chroma_interleaved_RGB };
                check(lh::heif_image_create(w, h, lh::heif_colorspace_heif_colorspace_RGB, chroma, &mut img))?;
                check(lh::heif_image_add_plane(img, lh::heif_channel_heif_channel_interleaved, w, h, spec.bits as i32))?;
                let mut stride = 0;
                let data = lh::heif_image_get_plane(img, lh::heif_channel_heif_channel_interleaved, &mut stride);
                anyhow::ensure!(!data.is_null() && stride > 0, "libheif: no plane");
                let stride = stride as usize;
                let plane = std::slice::from_raw_parts_mut(data, stride * image.height);
                let max = ((1u32 << spec.bits) - 1) as f32;
                let n = image.width * image.height;
                for y in 0..image.height {
                    for x in 0..image.width {
                        for c in 0..3 {
                            let code = (image.data[c * n + y * image.width + x].clamp(0.0, 1.0) * max).round() as u16;
                            if spec.bits > 8 {
                                let k = y * stride + (x * 3 + c) * 2;
                                plane[k..k + 2].copy_from_slice(&code.to_le_bytes());
                            } else {
                                plane[y * stride + x * 3 + c] = code as u8;
                            }
                        }
                    }
                }
                check(lh::heif_context_get_encoder_for_format(ctx, format as lh::heif_compression_format, &mut encoder))?;
                check(lh::heif_encoder_set_lossy_quality(encoder, 95))?;
                anyhow::ensure!((*options).version >= 5, "libheif older than 1.14");
                (*options).image_orientation = spec.orientation.clamp(1, 8) as lh::heif_orientation;
                if let Some(t) = spec.transfer {
                    (*nclx).transfer_characteristics = t;
                    check(lh::heif_image_set_nclx_color_profile(img, nclx))?;
                    // Written as a `colr` box (by default libheif leaves it out for macOS).
                    (*options).output_nclx_profile = nclx;
                    (*options).macOS_compatibility_workaround_no_nclx_profile = 0;
                }
                check(lh::heif_context_encode_image(ctx, img, encoder, options, &mut handle))?;
                if let Some(tiff) = &spec.exif {
                    check(lh::heif_context_add_exif_metadata(ctx, handle, tiff.as_ptr() as _, i32::try_from(tiff.len())?))?;
                }
                check(lh::heif_context_write_to_file(ctx, name.as_ptr()))
            })();
            if !handle.is_null() {
                lh::heif_image_handle_release(handle);
            }
            if !encoder.is_null() {
                lh::heif_encoder_release(encoder);
            }
            if !img.is_null() {
                lh::heif_image_release(img);
            }
            if !options.is_null() {
                (*options).output_nclx_profile = std::ptr::null_mut(); // freed below
                lh::heif_encoding_options_free(options);
            }
            if !nclx.is_null() {
                lh::heif_nclx_color_profile_free(nclx);
            }
            if !ctx.is_null() {
                lh::heif_context_free(ctx);
            }
            result
        }
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// `image` as a HEIF file's bytes (see [`write_heif`]).
    pub(crate) fn encode(image: &Image, format: CompressionFormat, bits: u8, orientation: u16, transfer: Option<u32>, exif: Option<&[u8]>) -> Vec<u8> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("encoded.heic");
        let spec = HeifEncoding { av1: format == CompressionFormat::Av1, bits, orientation, transfer, exif: exif.map(<[u8]>::to_vec) };
        write_heif(&p, image, &spec).unwrap();
        std::fs::read(&p).unwrap()
    }

    /// TIFF bytes of an EXIF block holding `fields` (kamadak-exif's writer).
    pub(crate) fn exif_tiff(fields: &[exif::Field]) -> Vec<u8> {
        let mut writer = exif::experimental::Writer::new();
        for f in fields {
            writer.push_field(f);
        }
        let mut tiff = std::io::Cursor::new(Vec::new());
        writer.write(&mut tiff, false).unwrap();
        tiff.into_inner()
    }

    /// Four flat quadrants of known colours, `[3, 48, 64]`: far from their
    /// edges lossy coding keeps them within a code or two.
    pub(crate) fn quadrants() -> Image {
        let colours = [[0.9, 0.2, 0.1], [0.1, 0.7, 0.3], [0.2, 0.3, 0.8], [0.5, 0.5, 0.5]];
        Image::from_fn(3, 48, 64, |c, y, x| colours[(y >= 24) as usize * 2 + (x >= 32) as usize][c])
    }

    /// Worst difference, in [0, 1] units, between the centres (8x8) of the
    /// four quadrants of `got` and those of `want`.
    fn worst_quadrant_error(got: &Image, want: &Image) -> f32 {
        let mut worst = 0f32;
        for (y0, x0) in [(8, 12), (8, 44), (32, 12), (32, 44)] {
            for c in 0..3 {
                for y in y0..y0 + 8 {
                    for x in x0..x0 + 8 {
                        worst = worst.max((got.get(c, y, x) - want.get(c, y, x)).abs());
                    }
                }
            }
        }
        worst
    }

    #[test]
    fn the_codec_comes_from_the_ftyp_brands() {
        let ftyp = |major: &[u8; 4], compatible: &[&[u8; 4]]| {
            let size = 16 + 4 * compatible.len() as u32;
            [&size.to_be_bytes()[..], b"ftyp", major, &[0; 4], &compatible.iter().flat_map(|b| b.iter().copied()).collect::<Vec<u8>>()].concat()
        };
        assert_eq!(kind(&ftyp(b"heic", &[b"mif1", b"heic"])).0, "HEIC");
        assert_eq!(kind(&ftyp(b"avif", &[b"mif1"])).0, "AVIF");
        assert_eq!(kind(&ftyp(b"mif1", &[b"mif1", b"avif", b"miaf"])).0, "AVIF");
        assert_eq!(kind(&ftyp(b"mif1", &[b"mif1"])).0, "HEIC");
        // Our own files say what they are.
        assert_eq!(kind(&encode(&quadrants(), CompressionFormat::Av1, 8, 1, None, None)).1, CompressionFormat::Av1);
        let m = no_decoder("AVIF", CompressionFormat::Av1);
        assert!(m.contains("no AV1 decoder") && m.contains("dav1d") && m.contains("heif-convert") && !m.contains('\n'), "{m}");
        // A truncated or lying box size reads no further than the bytes.
        assert_eq!(kind(&[0xFF, 0xFF, 0xFF, 0xFF, b'f', b't', b'y', b'p', b'a', b'v']).0, "HEIC");
    }

    #[test]
    fn this_libheif_has_the_decoders_and_encoders_the_tests_use() {
        // Debian 12's libheif1 1.15.1: libde265 + x265 (HEVC), libdav1d + libaom (AV1).
        assert!(have_decoder(CompressionFormat::Hevc) && have_decoder(CompressionFormat::Av1));
        let version = lib().version();
        assert!(version >= [1, 14, 0], "{version:?}");
        for f in [CompressionFormat::Hevc, CompressionFormat::Av1] {
            assert!(unsafe { libheif_sys::heif_have_encoder_for_format(f as _) } != 0, "{f:?}");
        }
    }

    #[test]
    fn heic_and_avif_decode_to_the_encoded_codes() {
        let dir = tempfile::tempdir().unwrap();
        let want = quadrants();
        for (name, format, bits, tolerance) in [
            ("q8.heic", CompressionFormat::Hevc, 8, 3.0 / 255.0),
            ("q10.heic", CompressionFormat::Hevc, 10, 3.0 / 255.0),
            ("q8.avif", CompressionFormat::Av1, 8, 3.0 / 255.0),
        ] {
            let p = dir.path().join(name);
            std::fs::write(&p, encode(&want, format, bits, 1, None, None)).unwrap();
            let (got, f) = super::super::read_image_with_format(&p).unwrap();
            assert_eq!(f, FileFormat::Heif, "{name}");
            assert_eq!((got.channels, got.height, got.width), (3, 48, 64), "{name}");
            let worst = worst_quadrant_error(&got, &want);
            eprintln!("{name}: worst quadrant error {:.2} codes of 255", worst * 255.0);
            assert!(worst <= tolerance, "{name}: {worst}");
            if bits > 8 {
                // 10-bit codes are kept: values between the 8-bit steps.
                let off_grid = got.data.iter().filter(|v| ((*v * 255.0) - (*v * 255.0).round()).abs() > 0.1).count();
                assert!(off_grid > got.data.len() / 10, "{name}: {off_grid} of {} values off the 8-bit grid", got.data.len());
            }
        }
    }

    #[test]
    fn heif_orientation_is_applied_once_and_exif_is_read() {
        use exif::{In, Tag, Value};
        // A horizontal ramp, stored with irot for EXIF orientation 6 (90 degrees clockwise) and
        // an EXIF block saying 6 too, as phones write them.
        let im = Image::from_fn(3, 48, 64, |c, _, x| 0.1 + 0.8 * x as f32 / 63.0 - 0.05 * c as f32);
        let tiff = exif_tiff(&[
            exif::Field { tag: Tag::Orientation, ifd_num: In::PRIMARY, value: Value::Short(vec![6]) },
            exif::Field { tag: Tag::FocalLengthIn35mmFilm, ifd_num: In::PRIMARY, value: Value::Short(vec![26]) },
        ]);
        let bytes = encode(&im, CompressionFormat::Hevc, 8, 6, None, Some(&tiff));
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("turned.heic");
        std::fs::write(&p, &bytes).unwrap();
        assert!(bytes.windows(4).any(|w| w == b"irot"), "libheif wrote no rotation");
        let got = super::super::read_image(&p).unwrap();
        // Shown 64 high, 48 wide: the stored left column is the top row, so brightness grows downwards.
        assert_eq!((got.height, got.width), (64, 48));
        let want = im.oriented(6);
        let worst = got.data.iter().zip(&want.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst < 4.0 / 255.0, "{worst}");
        // The EXIF comes back whole, as TIFF bytes.
        let back = exif::Reader::new().read_raw(exif(&bytes).unwrap()).unwrap();
        assert_eq!(back.get_field(Tag::FocalLengthIn35mmFilm, In::PRIMARY).and_then(|f| f.value.get_uint(0)), Some(26));
        assert_eq!(exif(&encode(&im, CompressionFormat::Hevc, 8, 1, None, None)), None);
    }

    #[test]
    fn hdr_transfer_curves_match_their_definitions() {
        // PQ: code 0.5 is 92.25 cd/m², 0.75 is 983.4, 1.0 is 10000 (ST 2084); 0.58069 is 203.
        assert!((pq_to_linear(0.5) * 203.0 - 92.246).abs() < 0.01, "{}", pq_to_linear(0.5) * 203.0);
        assert!((pq_to_linear(0.75) * 203.0 - 983.4).abs() < 0.5, "{}", pq_to_linear(0.75) * 203.0);
        assert!((pq_to_linear(1.0) * 203.0 - 10000.0).abs() < 0.5);
        assert!((pq_to_linear(0.580_69) - 1.0).abs() < 1e-3, "{}", pq_to_linear(0.580_69));
        assert_eq!(pq_to_linear(0.0), 0.0);
        // HLG: reference white (0.75) is 1; below 0.5 the curve is E^2 / 3; 1.0 is scene light 1 = 1 / 0.26496.
        assert!((hlg_to_linear(0.75) - 1.0).abs() < 1e-6);
        assert!((hlg_to_linear(0.5) - (0.25 / 3.0) / 0.264_962).abs() < 1e-4, "{}", hlg_to_linear(0.5));
        assert!((hlg_to_linear(1.0) - 1.0 / 0.264_962).abs() < 1e-3, "{}", hlg_to_linear(1.0));
    }

    #[test]
    fn pq_and_hlg_files_come_out_linear() {
        let dir = tempfile::tempdir().unwrap();
        let want = quadrants();
        for (name, transfer, curve) in [("pq.heic", 16, pq_to_linear as fn(f32) -> f32), ("hlg.heic", 18, hlg_to_linear)] {
            let p = dir.path().join(name);
            std::fs::write(&p, encode(&want, CompressionFormat::Hevc, 10, 1, Some(transfer), None)).unwrap();
            let (got, f) = super::super::read_image_with_format(&p).unwrap();
            assert_eq!(f, FileFormat::HeifLinear, "{name}");
            assert!(f.is_float());
            // Each quadrant's linear value is the curve of its code, within 2 codes of 1023.
            for (y, x) in [(12, 16), (12, 48), (36, 16), (36, 48)] {
                for c in 0..3 {
                    let code = want.get(c, y, x);
                    let (lo, hi) = (curve(code - 2.0 / 1023.0), curve(code + 2.0 / 1023.0));
                    let v = got.get(c, y, x);
                    assert!(v >= lo && v <= hi, "{name} ({c}, {y}, {x}): {v} outside [{lo}, {hi}]");
                }
            }
        }
        // Code 0.9 in PQ is 3906 cd/m², far above SDR white.
        let pq = super::super::read_image(&dir.path().join("pq.heic")).unwrap();
        assert!(pq.get(0, 12, 16) > 15.0, "{}", pq.get(0, 12, 16));
    }

    #[test]
    fn corrupt_and_cut_heif_files_are_one_line_errors() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = encode(&quadrants(), CompressionFormat::Hevc, 8, 1, None, None);
        let garbage: Vec<u8> = (0..400u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("cut.heic", bytes[..bytes.len() / 2].to_vec()),
            ("head.heic", bytes[..40].to_vec()),
            ("garbage.heic", [&bytes[..24], &garbage[..]].concat()),
            ("bare.heic", [&[0, 0, 0, 24][..], b"ftypheic", &[0; 12]].concat()),
            ("signature.heic", b"not a heif file at all".to_vec()),
        ];
        for (name, content) in cases {
            let p = dir.path().join(name);
            std::fs::write(&p, content).unwrap();
            let e = format!("{:#}", super::super::read_image(&p).unwrap_err());
            assert!(e.contains(name) && !e.contains('\n'), "{e}");
            if name == "signature.heic" {
                assert!(e.contains("not a valid .heic file"), "{e}");
            } else {
                assert!(e.contains("corrupt or truncated HEIC file"), "{e}");
            }
            eprintln!("{e}");
            assert_eq!(exif(&std::fs::read(&p).unwrap()), None);
        }
        // Damage inside the coded picture: an error or a picture, never a panic.
        let mut flipped = bytes.clone();
        for k in (bytes.len() / 2..bytes.len()).step_by(7) {
            flipped[k] ^= 0x5A;
        }
        let p = dir.path().join("flipped.heic");
        std::fs::write(&p, flipped).unwrap();
        if let Err(e) = super::super::read_image(&p) {
            assert!(!format!("{e:#}").contains('\n'));
        }
    }
}
