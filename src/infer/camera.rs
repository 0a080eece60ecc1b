//! What a photo's EXIF says about its camera: the field of view across the
//! shorter side (from the 35 mm-equivalent focal length, or the focal
//! length and the focal-plane resolution), the orientation tag, and the
//! exposure (printed so a user can see what the camera did, and how
//! `flashmat capture` brings photos of differing exposures to one). JPEG, PNG and
//! TIFF EXIF is found by kamadak-exif; a HEIF (HEIC, AVIF) file's by libheif
//! (`io::heif_exif`), whose decoder has already applied the file's own
//! rotation and mirroring, so there the EXIF orientation is not applied
//! again (ISO/IEC 23008-12 makes it informative; phones write both).
//!
//! 35 mm-equivalent focal lengths are defined on the 36 x 24 mm frame's
//! diagonal (43.27 mm): a photo of aspect w:h has an equivalent shorter side
//! of 43.27 * min(w, h) / hypot(w, h) mm (24 mm at 3:2, 25.96 mm at 4:3), and
//! FOV = 2 atan(side / (2 f)).

use crate::io::FileFormat;
use anyhow::{bail, Result};
use exif::{In, Tag, Value};
use std::path::Path;

/// Diagonal of the 36 x 24 mm frame, mm.
pub const FULL_FRAME_DIAGONAL_MM: f64 = 43.266_615_305_567_87;

/// Two EXIF focal lengths that disagree by more than this (relative, on
/// the resulting FOV) contradict each other.
pub const FOV_AGREEMENT: f64 = 0.15;

/// The camera facts read from a photo.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CameraInfo {
    /// Field of view across the shorter side, degrees, and where it came from.
    pub fov: Option<(f64, String)>,
    /// EXIF orientation 1..=8 (1: as stored).
    pub orientation: u16,
    /// Exposure time, f-number and ISO, as the camera wrote them.
    pub exposure: Option<Exposure>,
}

/// A photo's exposure as its EXIF states it (each part if stated).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Exposure {
    /// Exposure time, seconds.
    pub time_s: Option<f64>,
    pub f_number: Option<f64>,
    pub iso: Option<u32>,
}

impl Exposure {
    /// Exposure time x ISO / f-number^2: proportional to the photo's linear
    /// values for one scene and light. None unless all three are stated.
    pub fn scale(&self) -> Option<f64> {
        Some(self.time_s? * self.iso? as f64 / self.f_number?.powi(2))
    }
}

impl std::fmt::Display for Exposure {
    /// "1/60 s, f/1.8, ISO 100", the parts stated.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut parts = vec![];
        if let Some(t) = self.time_s {
            parts.push(if t < 1.0 { format!("1/{:.0} s", 1.0 / t) } else { format!("{t} s") });
        }
        if let Some(n) = self.f_number {
            parts.push(format!("f/{n}"));
        }
        if let Some(iso) = self.iso {
            parts.push(format!("ISO {iso}"));
        }
        f.write_str(&parts.join(", "))
    }
}

/// FOV across the shorter side of a `width x height` photo taken at a
/// 35 mm-equivalent focal length `f35` mm.
pub fn fov_from_35mm(f35: f64, width: usize, height: usize) -> f64 {
    let (w, h) = (width as f64, height as f64);
    let side = FULL_FRAME_DIAGONAL_MM * w.min(h) / w.hypot(h);
    2.0 * (side / (2.0 * f35)).atan().to_degrees()
}

/// FOV across the shorter side from the real focal length `f` (mm) and the
/// sensor's pixel pitch `pitch_mm`, for a `short_px`-pixel shorter side.
pub fn fov_from_focal_plane(f: f64, pitch_mm: f64, short_px: usize) -> f64 {
    2.0 * (short_px as f64 * pitch_mm / (2.0 * f)).atan().to_degrees()
}

fn rational(field: &exif::Field) -> Option<f64> {
    match &field.value {
        Value::Rational(v) => v.first().filter(|r| r.denom != 0).map(|r| r.to_f64()),
        Value::SRational(v) => v.first().filter(|r| r.denom != 0).map(|r| r.to_f64()),
        // Phones write rationals; editing tools (Pillow among them) may write floats.
        Value::Double(v) => v.first().copied(),
        Value::Float(v) => v.first().map(|&f| f64::from(f)),
        other => other.get_uint(0).map(f64::from),
    }
    .filter(|v| v.is_finite() && *v > 0.0)
}

/// Reads the EXIF of a photo of `width x height` pixels (as decoded, before
/// the EXIF rotation) stored as `format`. No EXIF, or a file format without
/// it, gives the default (no FOV, orientation 1); HEIF files always have
/// orientation 1 (see the module docs). EXIF whose two focal lengths
/// disagree by more than [`FOV_AGREEMENT`] is an error that says how to
/// override.
pub fn read_camera(path: &Path, format: FileFormat, width: usize, height: usize) -> Result<CameraInfo> {
    let none = CameraInfo { orientation: 1, ..Default::default() };
    let exif = if format.is_heif() {
        crate::io::heif_exif(path).and_then(|tiff| exif::Reader::new().read_raw(tiff).ok())
    } else {
        std::fs::File::open(path).ok().and_then(|file| exif::Reader::new().read_from_container(&mut std::io::BufReader::new(file)).ok())
    };
    let Some(exif) = exif else { return Ok(none) };
    let get = |tag: Tag| exif.get_field(tag, In::PRIMARY);
    let num = |tag: Tag| get(tag).and_then(rational);
    let orientation = if format.is_heif() {
        1
    } else {
        get(Tag::Orientation).and_then(|f| f.value.get_uint(0)).filter(|o| (1..=8).contains(o)).unwrap_or(1) as u16
    };

    let from_35 = num(Tag::FocalLengthIn35mmFilm).map(|f35| (fov_from_35mm(f35, width, height), format!("EXIF FocalLengthIn35mmFilm {f35} mm")));
    let from_plane = (|| {
        let f = num(Tag::FocalLength)?;
        let res = num(Tag::FocalPlaneXResolution)?;
        // ResolutionUnit: 2 inch (default), 3 cm, 4 mm (rare), per TIFF/EXIF.
        let unit_mm = match get(Tag::FocalPlaneResolutionUnit).and_then(|u| u.value.get_uint(0)).unwrap_or(2) {
            3 => 10.0,
            4 => 1.0,
            _ => 25.4,
        };
        // The resolution refers to the sensor's full width: scale by the
        // stored width over PixelXDimension when the image was resized.
        let px_dim = num(Tag::PixelXDimension).unwrap_or(width.max(height) as f64);
        let pitch = unit_mm / res * px_dim / width.max(height) as f64;
        Some((fov_from_focal_plane(f, pitch, width.min(height)), format!("EXIF FocalLength {f} mm on a {:.2} mm sensor side", pitch * width.min(height) as f64)))
    })();
    let fov = match (from_35, from_plane) {
        (Some(a), Some(b)) => {
            if (a.0 / b.0 - 1.0).abs() > FOV_AGREEMENT {
                bail!(
                    "{}: the EXIF contradicts itself: {} gives a {:.1} degree field of view, {} gives {:.1}; pass --fov DEGREES",
                    path.display(),
                    a.1,
                    a.0,
                    b.1,
                    b.0
                );
            }
            Some(a)
        }
        (a, b) => a.or(b),
    };

    let exposure = Exposure { time_s: num(Tag::ExposureTime), f_number: num(Tag::FNumber), iso: get(Tag::PhotographicSensitivity).and_then(|f| f.value.get_uint(0)) };
    let stated = exposure != Exposure::default();
    Ok(CameraInfo { fov, orientation, exposure: stated.then_some(exposure) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fov_from_focal_lengths() {
        // 3:2 frame: the equivalent shorter side is 24 mm; 24 mm lens -> 2 atan(0.5) = 53.13 deg.
        assert!((fov_from_35mm(24.0, 3000, 2000) - 53.130_102).abs() < 1e-4);
        // 4:3 phone photo at 26 mm: side 43.2666 * 3/5 = 25.96 mm, 2 atan(25.96/52) = 53.06 deg.
        assert!((fov_from_35mm(26.0, 4032, 3024) - 53.0595).abs() < 1e-3);
        // Orientation does not matter: the shorter side is the shorter side.
        assert_eq!(fov_from_35mm(26.0, 3024, 4032), fov_from_35mm(26.0, 4032, 3024));
        // 4.25 mm lens, 1.4 um pixels, 3024 px: side 4.2336 mm -> 2 atan(0.49807) = 52.95 deg.
        assert!((fov_from_focal_plane(4.25, 0.0014, 3024) - 52.953).abs() < 1e-2);
    }

    /// A number is read whatever type the writer chose; zero, negative and
    /// non-finite values are none.
    #[test]
    fn exif_numbers_of_every_type_are_read() {
        let field = |value: Value| exif::Field { tag: exif::Tag::ExposureTime, ifd_num: exif::In::PRIMARY, value };
        assert_eq!(rational(&field(Value::Rational(vec![exif::Rational { num: 1, denom: 120 }]))), Some(1.0 / 120.0));
        assert_eq!(rational(&field(Value::Double(vec![4e9]))), Some(4e9));
        assert_eq!(rational(&field(Value::Float(vec![0.5]))), Some(0.5));
        assert_eq!(rational(&field(Value::Short(vec![26]))), Some(26.0));
        assert_eq!(rational(&field(Value::Double(vec![f64::NAN]))), None);
        assert_eq!(rational(&field(Value::Rational(vec![exif::Rational { num: 1, denom: 0 }]))), None);
    }

    #[test]
    fn a_photo_without_exif_has_no_fov() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("plain.png");
        crate::io::write_png(&p, &crate::image::Image::filled(3, 8, 8, 0.5), crate::io::BitDepth::Eight).unwrap();
        assert_eq!(read_camera(&p, FileFormat::Png, 8, 8).unwrap(), CameraInfo { fov: None, orientation: 1, exposure: None });
    }
}
