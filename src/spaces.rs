//! Radiometric spaces (REFERENCE section 3) and 8-bit encodings.
//!
//! - linear: HDR radiance as rendered, unbounded;
//! - log: ln(1 + R), what the networks read and predict;
//! - display: (exp(log) - 1)^(1/2.2) = R^(1/2.2), clamped to [0,1]: the
//!   paper's display transform, where LPIPS compares pictures;
//! - photo: the exact sRGB curve of every 8-bit picture flashmat writes or
//!   reads as a photo ([`photo_encode`] / [`photo_decode`]), so that
//!   `render -o p.png` and then `estimate p.png` see the same radiance.

use tch::Tensor;

/// Gamma of the paper's display transform and 8-bit map encoding.
pub const GAMMA: f64 = 2.2;

/// ln(1 + R).
pub fn to_log(linear: &Tensor) -> Tensor {
    linear.log1p()
}

/// exp(x) - 1, inverse of [`to_log`].
pub fn from_log(log: &Tensor) -> Tensor {
    log.expm1()
}

/// Linear radiance to display values in [0, 1]: clamp(R, 0, 1)^(1/2.2).
pub fn linear_to_display(linear: &Tensor) -> Tensor {
    linear.clamp(0.0, 1.0).pow_tensor_scalar(1.0 / GAMMA)
}

/// Log radiance to display values in [0, 1].
pub fn log_to_display(log: &Tensor) -> Tensor {
    linear_to_display(&from_log(log))
}

/// LDR input: what an 8-bit camera keeps of an HDR render.
pub fn ldr_clamp(linear: &Tensor) -> Tensor {
    linear.clamp(0.0, 1.0)
}

/// Gamma-encoded value in [0,1] to linear (^2.2), as for 8-bit photos and
/// stored diffuse/specular maps.
pub fn gamma_decode(v: f32) -> f32 {
    v.max(0.0).powf(GAMMA as f32)
}

/// Linear to gamma-encoded (^(1/2.2)), clamped to [0, 1].
pub fn gamma_encode(v: f32) -> f32 {
    v.clamp(0.0, 1.0).powf(1.0 / GAMMA as f32)
}

/// Exact sRGB transfer decode (IEC 61966-2-1): the linear toe v / 12.92 up
/// to 0.04045, then ((v + 0.055) / 1.055)^2.4. How 8-bit photos are
/// linearised for inference ([`photo_decode`]): cameras and phones write
/// sRGB. Stored 8-bit diffuse/specular maps and capture folders keep
/// [`gamma_decode`] (the paper's datasets were made with ^2.2).
pub fn srgb_decode(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// 8-bit (and 16-bit) PNG/JPEG photo value in [0, 1] to linear, as
/// `flashmat estimate` reads them: the exact sRGB curve. The models were
/// trained on linear renders clamped to [0, 1] (`ldr_clamp`, no 8-bit
/// encoding), so the decode only has to undo what the camera did.
pub fn photo_decode(v: f32) -> f32 {
    srgb_decode(v)
}

/// Exact sRGB transfer encode (inverse of [`srgb_decode`]), clamped to [0, 1]:
/// how tests and demos write a linear render as a camera's 8-bit photo.
pub fn srgb_encode(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.0031308 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Linear radiance to the 8-bit picture value flashmat writes (renders,
/// relights, grids, previews): the exact sRGB curve, clamped to [0, 1], the
/// inverse of [`photo_decode`], so flashmat's own pictures read back as the
/// radiance they show. (Image viewers assume sRGB for a PNG without colour
/// chunks, too.)
pub fn photo_encode(v: f32) -> f32 {
    srgb_encode(v)
}

/// [`photo_encode`] of a tensor of linear radiance.
pub fn linear_to_photo(linear: &Tensor) -> Tensor {
    let v = linear.clamp(0.0, 1.0);
    let toe = &v * 12.92;
    let curve = v.pow_tensor_scalar(1.0 / 2.4) * 1.055 - 0.055;
    toe.where_self(&v.le(0.003_130_8), &curve)
}

/// Quantizes a [0,1] value to 8 bits (round to nearest).
pub fn quantize_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_round_trip_and_values() {
        let x = Tensor::from_slice(&[0.0f64, 1.0, 10.0, 1e4]);
        let l = to_log(&x);
        assert!((l.double_value(&[1]) - 2f64.ln()).abs() < 1e-12);
        assert!((from_log(&l) - &x).abs().max().double_value(&[]) < 1e-9);
    }

    #[test]
    fn display_transform() {
        let x = Tensor::from_slice(&[-1.0f64, 0.0, 0.5, 1.0, 7.0]);
        let d = linear_to_display(&x);
        let got: Vec<f64> = Vec::try_from(d).unwrap();
        assert_eq!(got[0], 0.0);
        assert!((got[2] - 0.5f64.powf(1.0 / 2.2)).abs() < 1e-12);
        assert_eq!(got[3], 1.0);
        assert_eq!(got[4], 1.0);
        let l = to_log(&x.narrow(0, 2, 1));
        assert!((log_to_display(&l).double_value(&[0]) - got[2]).abs() < 1e-12);
        let c: Vec<f64> = Vec::try_from(ldr_clamp(&x)).unwrap();
        assert_eq!(c, vec![0.0, 0.0, 0.5, 1.0, 1.0]);
    }

    #[test]
    fn gamma_and_srgb() {
        assert!((gamma_decode(0.5) - 0.217637).abs() < 1e-6);
        assert!((gamma_encode(gamma_decode(0.3)) - 0.3).abs() < 1e-6);
        // sRGB reference points: 0.5 -> 0.214041, 0.04045 -> 0.0031308.
        assert!((srgb_decode(0.5) - 0.214041).abs() < 1e-6);
        assert!((srgb_decode(0.04045) - 0.0031308).abs() < 1e-6);
        for v in [0.0f32, 0.01, 0.2, 0.7, 1.0] {
            assert!((srgb_encode(srgb_decode(v)) - v).abs() < 1e-6);
        }
        // IEC 61966-2-1: 1 -> 1; the linear toe v / 12.92 (0.02 -> 0.00154799);
        // both pieces meet at 0.04045 <-> 0.0031308; encode 0.5 -> 0.735357.
        assert!((srgb_decode(1.0) - 1.0).abs() < 1e-7 && srgb_decode(0.0) == 0.0);
        assert!((srgb_decode(0.02) - 0.001_547_988).abs() < 1e-9);
        assert!((srgb_decode(0.040_45) - (0.040_45f32 + 0.055).powf(2.4) / 1.055f32.powf(2.4)).abs() < 1e-7);
        assert!((srgb_encode(0.003_130_8) - 0.040_45).abs() < 1e-6);
        assert!((srgb_encode(0.5) - 0.735_357).abs() < 1e-6);
        assert!((srgb_encode(0.001) - 0.012_92).abs() < 1e-7);
        // 8-bit code 128 (0.50196): sRGB 0.215861, where ^2.2 gives 0.219520.
        assert!((photo_decode(128.0 / 255.0) - 0.215_861).abs() < 1e-6);
        assert!((gamma_decode(128.0 / 255.0) - 0.219_520).abs() < 1e-5);
        assert_eq!(quantize_u8(0.5), 128);
        assert_eq!(quantize_u8(2.0), 255);
        // The tensor form of the picture curve is the scalar one.
        let x: Vec<f32> = vec![-1.0, 0.0, 0.001, 0.003_130_8, 0.01, 0.2, 0.9, 1.0, 3.0];
        let t: Vec<f32> = Vec::try_from(linear_to_photo(&Tensor::from_slice(&x))).unwrap();
        for (v, got) in x.iter().zip(&t) {
            assert!((got - photo_encode(*v)).abs() < 1e-6, "{v}: {got}");
        }
    }

    /// What flashmat writes as an 8-bit picture, its photo decoder reads
    /// back as the same radiance (to within half a code), dark values
    /// included. The former ^(1/2.2) encode wrote radiance 0.0008 as code
    /// 10, which the sRGB decode reads as 0.0030, 3.8x too bright.
    #[test]
    fn written_pictures_decode_to_their_radiance() {
        assert_eq!(quantize_u8(gamma_encode(0.000_8)), 10);
        assert!((photo_decode(10.0 / 255.0) - 0.003_035).abs() < 1e-6);
        assert_eq!(quantize_u8(photo_encode(0.000_8)), 3);
        for v in [0.000_8f32, 0.002, 0.01, 0.05, 0.2, 0.5, 0.9] {
            let code = quantize_u8(photo_encode(v)) as f32;
            let (lo, hi) = (photo_decode((code - 0.5) / 255.0), photo_decode((code + 0.5) / 255.0));
            assert!(lo <= v && v <= hi, "{v} -> code {code}: [{lo}, {hi}]");
        }
    }
}
