//! RAW photos through rawler (dnglab's decoder; the `raw` cargo feature,
//! LGPL-2.1, so optional): DNG (Apple ProRAW's linear DNG, JPEG XL- or
//! lossless-JPEG-compressed; Android's and cameras' Bayer DNG) and the
//! camera RAW formats rawler reads.
//!
//! What comes back is linear sRGB (D65), `[3, H, W]`, 1.0 at the sensor's
//! white level: black and white levels taken out, the DNG's lens-shading
//! gain map (OpcodeList2 GainMap) applied, demosaiced, the file's white
//! balance (AsShotNeutral) and colour matrix (ColorMatrix, D65 preferred)
//! applied, cropped to the default crop. Values stop at 1, so a RAW photo clips
//! where its sensor did, as an 8-bit photo clips at its last code: callers
//! treat it as a linear photo in [0, 1]. No tone curve, no sharpening, no
//! BaselineExposure (see [`baseline_exposure`]). The EXIF (focal length,
//! orientation, exposure) is the TIFF's own, read by kamadak-exif as for
//! other files.

use super::{check_dimensions, DecodeError};
use crate::image::Image;
use rawler::decoders::{RawDecodeParams, WellKnownIFD};
use rawler::imgop::develop::{Intermediate, ProcessingStep, RawDevelop};
use rawler::rawimage::{RawImage, RawPhotometricInterpretation};
use rawler::rawsource::RawSource;
use rawler::tags::DngTag;

/// The DNG opcode that multiplies a region of the image by a smooth map
/// (lens shading, vignetting).
const GAIN_MAP_OPCODE: u32 = 9;

/// Decodes a RAW file's bytes to linear sRGB `[3, H, W]` (module docs).
pub(super) fn decode(bytes: &[u8]) -> Result<Image, DecodeError> {
    let source = RawSource::new_from_slice(bytes);
    let decoder = rawler::get_decoder(&source).map_err(|e| DecodeError::Unsupported(format!("not a RAW file rawler can read ({e})")))?;
    let params = RawDecodeParams::default();
    // The header first: a hostile size is refused before the pixels exist.
    let header = decoder.raw_image(&source, &params, true)?;
    check_dimensions(header.width as u64, header.height as u64)?;
    let mut raw = decoder.raw_image(&source, &params, false)?;
    raw.apply_scaling()?;
    if let Some(list) = decoder.ifd(WellKnownIFD::VirtualDngRawTags)?.and_then(|ifd| ifd.get_entry(DngTag::OpcodeList2).map(|e| e.value.clone())) {
        if let rawler::formats::tiff::Value::Undefined(list) | rawler::formats::tiff::Value::Byte(list) = list {
            apply_gain_maps(&mut raw, &list).map_err(DecodeError::Corrupt)?;
        }
    }
    let steps = [ProcessingStep::Demosaic, ProcessingStep::CropActiveArea, ProcessingStep::WhiteBalance, ProcessingStep::Calibrate, ProcessingStep::CropDefault];
    let developed = RawDevelop::new_with(&steps).develop_intermediate(&raw)?;
    let image = match developed {
        Intermediate::ThreeColor(p) => {
            let (w, h) = (p.width, p.height);
            Image::from_fn(3, h, w, |c, y, x| p.data[y * w + x][c])
        }
        Intermediate::Monochrome(p) => {
            let (w, h) = (p.width, p.height);
            Image::from_fn(1, h, w, |_, y, x| p.data[y * w + x])
        }
        Intermediate::FourColor(_) => return Err(DecodeError::Unsupported("its four-colour sensor has no colour matrix to sRGB".into())),
    };
    // rawler brings a clipped pixel near 1 keeping some of its hue, but can
    // leave a channel a little above; the sensor stopped at 1.
    Ok(image.map(|v| if v.is_finite() { v.clamp(0.0, 1.0) } else { v }))
}

/// The file's BaselineExposure in stops (0 when it states none, or the
/// file is not a DNG): how much the camera meant its linear values to be
/// brightened for a normal exposure.
pub(super) fn baseline_exposure(bytes: &[u8]) -> Option<f64> {
    let source = RawSource::new_from_slice(bytes);
    let decoder = rawler::get_decoder(&source).ok()?;
    let root = decoder.ifd(WellKnownIFD::Root).ok()??;
    let stops = root.get_entry(DngTag::BaselineExposure).map_or(0.0, |e| e.value.force_f32(0) as f64);
    stops.is_finite().then_some(stops)
}

/// Reads big-endian u32 / f64 values from an opcode's parameters.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or("its DNG opcode list is truncated")?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_be_bytes(self.take(4)?.try_into().unwrap_or_default()))
    }
    fn f64(&mut self) -> Result<f64, String> {
        Ok(f64::from_be_bytes(self.take(8)?.try_into().unwrap_or_default()))
    }
    fn f32(&mut self) -> Result<f32, String> {
        Ok(f32::from_be_bytes(self.take(4)?.try_into().unwrap_or_default()))
    }
}

/// Applies the GainMap opcodes of a DNG OpcodeList2 to the scaled raw
/// data (before demosaicing, as the DNG spec orders it); other opcodes
/// are skipped. Coordinates are the active area's; a gain is read at a
/// pixel's centre, bilinear between map points, held at the map's edges.
fn apply_gain_maps(raw: &mut RawImage, list: &[u8]) -> Result<(), String> {
    let mut r = Reader { bytes: list, at: 0 };
    let count = r.u32()?;
    let (ox, oy, area_w, area_h) = match &raw.active_area {
        Some(a) => (a.p.x, a.p.y, a.d.w, a.d.h),
        None => (0, 0, raw.width, raw.height),
    };
    let cpp = raw.cpp;
    let planes_in_image = match raw.photometric {
        RawPhotometricInterpretation::Cfa(_) => 1,
        _ => cpp,
    };
    let (width, height) = (raw.width, raw.height);
    let rawler::RawImageData::Float(data) = &mut raw.data else { return Err("its raw data was not scaled".into()) };
    for _ in 0..count.min(1024) {
        let (id, _version, _flags, size) = (r.u32()?, r.u32()?, r.u32()?, r.u32()? as usize);
        let params = r.take(size)?;
        if id != GAIN_MAP_OPCODE {
            continue;
        }
        let mut p = Reader { bytes: params, at: 0 };
        let (top, left, bottom, right) = (p.u32()? as usize, p.u32()? as usize, p.u32()? as usize, p.u32()? as usize);
        let (plane, planes, row_pitch, col_pitch) = (p.u32()? as usize, p.u32()? as usize, p.u32()?.max(1) as usize, p.u32()?.max(1) as usize);
        let (rows, cols) = (p.u32()? as usize, p.u32()? as usize);
        let (spacing_v, spacing_h, origin_v, origin_h) = (p.f64()?, p.f64()?, p.f64()?, p.f64()?);
        let map_planes = p.u32()? as usize;
        if rows == 0 || cols == 0 || map_planes == 0 || rows.saturating_mul(cols).saturating_mul(map_planes) > 1 << 20 {
            return Err(format!("its gain map is {rows}x{cols}x{map_planes}, not a map"));
        }
        if !(spacing_v > 0.0 && spacing_h > 0.0 && origin_v.is_finite() && origin_h.is_finite()) {
            return Err("its gain map has no spacing".into());
        }
        let gains: Vec<f32> = (0..rows * cols * map_planes).map(|_| p.f32()).collect::<Result<_, _>>()?;
        // Position in map points of a pixel centre along one axis, held at the ends.
        let locate = |pixel: usize, extent: usize, origin: f64, spacing: f64, n: usize| -> (usize, usize, f32) {
            let t = (((pixel as f64 + 0.5) / extent as f64 - origin) / spacing).clamp(0.0, (n - 1) as f64);
            let i = (t.floor() as usize).min(n.saturating_sub(2));
            (i, (i + 1).min(n - 1), (t - i as f64) as f32)
        };
        for y in (top..bottom.min(area_h)).step_by(row_pitch) {
            let (r0, r1, fy) = locate(y, area_h, origin_v, spacing_v, rows);
            for x in (left..right.min(area_w)).step_by(col_pitch) {
                let (c0, c1, fx) = locate(x, area_w, origin_h, spacing_h, cols);
                for pl in plane..(plane + planes).min(planes_in_image) {
                    let mp = pl.min(map_planes - 1);
                    let g = |r: usize, c: usize| gains[(r * cols + c) * map_planes + mp];
                    let gain = (g(r0, c0) * (1.0 - fx) + g(r0, c1) * fx) * (1.0 - fy) + (g(r1, c0) * (1.0 - fx) + g(r1, c1) * fx) * fy;
                    let (py, px) = (y + oy, x + ox);
                    if py < height && px < width {
                        data[(py * width + px) * cpp + pl] *= gain;
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::dng::{write_dng, DngOptions};
    use super::super::{read_image_with_format, FileFormat};
    use crate::image::Image;

    /// A smooth colour image in [0.05, 0.9]: known values to find again.
    fn smooth(w: usize, h: usize) -> Image {
        Image::from_fn(3, h, w, |c, y, x| {
            let (u, v) = (x as f32 / w as f32, y as f32 / h as f32);
            [0.05 + 0.8 * u, 0.1 + 0.6 * v, 0.3 + 0.4 * u * v][c]
        })
    }

    fn max_difference(a: &Image, b: &Image, border: usize) -> f32 {
        let mut worst = 0.0f32;
        for c in 0..3 {
            for y in border..a.height - border {
                for x in border..a.width - border {
                    worst = worst.max((a.get(c, y, x) - b.get(c, y, x)).abs());
                }
            }
        }
        worst
    }

    #[test]
    fn a_linear_dng_reads_back_as_its_linear_srgb_values() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("linear.dng");
        let truth = smooth(40, 30);
        // 12 bits, black 64, neutral (0.5, 1, 0.7): red and blue stored at
        // half and 0.7 of their value, taken back out by the white balance.
        write_dng(&path, &truth, &DngOptions::default()).unwrap();
        let (read, format) = read_image_with_format(&path).unwrap();
        assert_eq!((format, read.channels, read.width, read.height), (FileFormat::Raw, 3, 40, 30));
        // One code of the 4031 between black and white, over the neutral 0.5: 5e-4.
        let d = max_difference(&truth, &read, 0);
        assert!(d < 1.5e-3, "largest difference {d}");
    }

    #[test]
    fn a_bayer_dng_is_demosaiced_to_its_colours() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bayer.dng");
        let truth = smooth(64, 48);
        write_dng(&path, &truth, &DngOptions { bayer: true, bits: 14, ..Default::default() }).unwrap();
        let (read, format) = read_image_with_format(&path).unwrap();
        assert_eq!((format, read.width, read.height), (FileFormat::Raw, 64, 48));
        // A smooth image demosaics to within a hundredth away from the edges.
        let d = max_difference(&truth, &read, 3);
        assert!(d < 0.01, "largest difference {d}");
    }

    #[test]
    fn the_lens_shading_gain_map_is_taken_out() {
        let dir = tempfile::tempdir().unwrap();
        let truth = smooth(48, 48);
        // Corners at 0.5 of the centre (gain 2), as a phone's vignetting.
        let gains = vec![2.0, 1.4, 2.0, 1.4, 1.0, 1.4, 2.0, 1.4, 2.0];
        let shaded = DngOptions { gain_map: Some((3, 3, gains)), ..Default::default() };
        for bayer in [false, true] {
            let path = dir.path().join(format!("shaded-{bayer}.dng"));
            write_dng(&path, &truth, &DngOptions { bayer, ..shaded.clone() }).unwrap();
            let (read, _) = read_image_with_format(&path).unwrap();
            // Without the map the corners would be half as bright (0.2-0.45
            // off); with it, what is left is the 12-bit steps, doubled in the
            // corners, and for the mosaic the demosaicing's own error (PPG
            // moves by a hundredth where a step's noise flips its direction).
            let d = max_difference(&truth, &read, if bayer { 3 } else { 0 });
            assert!(d < if bayer { 0.02 } else { 3e-3 }, "bayer {bayer}: largest difference {d}");
        }
    }

    #[test]
    fn raw_highlights_clip_at_one_and_the_baseline_exposure_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("clipped.dng");
        let bright = Image::from_fn(3, 16, 16, |c, _, x| if x < 8 { 2.0 } else { [0.2, 0.3, 0.4][c] });
        write_dng(&path, &bright, &DngOptions { baseline_exposure: 1.5, ..Default::default() }).unwrap();
        let (read, format) = read_image_with_format(&path).unwrap();
        assert!(format.clips_at_one() && format.is_float());
        let (clipped, kept) = (read.get(1, 4, 2), read.get(1, 4, 12));
        assert!((clipped - 1.0).abs() < 1e-3 && (kept - 0.3).abs() < 2e-3, "clipped {clipped}, kept {kept}");
        assert!((super::super::raw_baseline_gain(&path) - 2f64.powf(1.5)).abs() < 1e-4);
        // A flash peak kept unclipped in 12 bits needs 8-11 stops of
        // headroom: its gain is read whole (it was cut at 8 stops, and the
        // capture fit relit test05 at 0.77 of its brightness); beyond 16
        // stops no sensor value could hold it: cut there.
        for (stops, gain) in [(8.4, 2f64.powf(8.4)), (-3.0, 0.125), (40.0, 65536.0)] {
            let p = dir.path().join(format!("b{stops}.dng"));
            write_dng(&p, &bright, &DngOptions { baseline_exposure: stops, ..Default::default() }).unwrap();
            let read = super::super::raw_baseline_gain(&p);
            assert!((read / gain - 1.0).abs() < 1e-4, "BaselineExposure {stops}: gain {read}, not {gain}");
        }
        // An 8-bit photo has no baseline gain.
        let png = dir.path().join("p.png");
        super::super::write_png(&png, &bright, super::super::BitDepth::Eight).unwrap();
        assert_eq!(super::super::raw_baseline_gain(&png), 1.0);
    }

    #[test]
    fn broken_raw_files_are_one_line_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let good = dir.path().join("good.dng");
        write_dng(&good, &smooth(32, 32), &DngOptions { bayer: true, ..Default::default() }).unwrap();
        let bytes = std::fs::read(&good).unwrap();
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("truncated.dng", bytes[..bytes.len() / 2].to_vec()),
            ("header-only.dng", bytes[..300].to_vec()),
            ("not-a-tiff.dng", b"this is not a photo at all".to_vec()),
            ("plain.tif", b"II*\0\x08\0\0\0\0\0\0\0".to_vec()),
        ];
        for (name, contents) in cases {
            let path = dir.path().join(name);
            std::fs::write(&path, contents).unwrap();
            let e = format!("{:#}", read_image_with_format(&path).unwrap_err());
            assert!(!e.contains('\n') && e.contains(name), "{name}: {e}");
        }
    }
}
