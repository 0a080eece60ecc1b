//! Input photos as a phone takes them (issue 48, "the photo's highlight read
//! as colour"): the camera not exactly above the material's centre (the flash
//! highlight off-centre, the view a little oblique), nearer or farther, the
//! flash beside the lens instead of in it, and the picture an 8-bit sRGB
//! file (optionally a JPEG) with sensor noise. M_est is still told the model's co-located
//! overhead geometry (its h_z channel), as at inference, where the photo's
//! true geometry is unknown.

use crate::geometry::{fov_to_distance, LightView};
use crate::spaces::{photo_decode, photo_encode, quantize_u8};
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// How far a phone photo strays from the model's co-located photo.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhonePhotoConfig {
    /// Largest lateral offset of the camera from the material's centre
    /// along x and y (world units; the material spans [-1, 1]^2), so the
    /// flash highlight lands up to this far from the photo's centre.
    pub camera_offset: f64,
    /// Range of the camera's height, times the model's distance at its FOV.
    pub height: (f64, f64),
    /// Range of the flash's distance from the lens (world units, in the
    /// camera's plane, any direction): 1-2 cm on a phone held about 30 cm
    /// over a 15 cm patch (1 unit = 7.5 cm).
    pub flash_offset: (f64, f64),
    /// Shot noise: the noise variance per unit of linear radiance (a
    /// standard deviation of 0.01 at 1).
    pub shot_noise: f64,
    /// Read noise: the standard deviation at black.
    pub read_noise: f64,
    /// The file a JPEG at a quality drawn from this range (inclusive);
    /// None: a lossless 8-bit file.
    #[serde(default)]
    pub jpeg_quality: Option<(u8, u8)>,
}

/// The JPEG qualities phones' cameras save at (`--phone-jpeg`).
pub const PHONE_JPEG_QUALITY: (u8, u8) = (85, 95);

impl Default for PhonePhotoConfig {
    fn default() -> Self {
        Self { camera_offset: 0.3, height: (0.85, 1.2), flash_offset: (0.1, 0.3), shot_noise: 1e-4, read_noise: 0.002, jpeg_quality: None }
    }
}

impl PhonePhotoConfig {
    /// The default phone, its files JPEGs at [`PHONE_JPEG_QUALITY`] when
    /// `jpeg` (`--phone-jpeg`).
    pub fn saving_jpeg(jpeg: bool) -> Self {
        Self { jpeg_quality: jpeg.then_some(PHONE_JPEG_QUALITY), ..Default::default() }
    }
}

/// One phone photo's camera and flash: the camera at (x, y, h) with x, y
/// ~ U[-offset, offset] and h ~ the height range x the distance at
/// `fov_deg`; the flash beside it in the plane z = h, at a distance drawn
/// from the flash range, in a uniform direction.
pub fn phone_light_view<R: Rng>(rng: &mut R, fov_deg: f64, cfg: &PhonePhotoConfig) -> LightView {
    let d = fov_to_distance(fov_deg);
    let o = cfg.camera_offset;
    let (x, y) = (rng.random_range(-o..=o), rng.random_range(-o..=o));
    let h = d * rng.random_range(cfg.height.0..=cfg.height.1);
    let r = rng.random_range(cfg.flash_offset.0..=cfg.flash_offset.1);
    let phi = rng.random_range(0.0..std::f64::consts::TAU);
    LightView { view: [x, y, h], light: [x + r * phi.cos(), y + r * phi.sin(), h] }
}

/// The factor that brings a photo lit from `light` to the brightness of
/// the model's co-located photo at `fov_deg` (the irradiance at the
/// material's centre, as a camera's auto-exposure would): (|light| / d)^2.
pub fn exposure_factor(light: [f64; 3], fov_deg: f64) -> f64 {
    let d = fov_to_distance(fov_deg);
    (light[0] * light[0] + light[1] * light[1] + light[2] * light[2]) / (d * d)
}

/// Makes a linear render a phone's picture, in place: times `exposure`,
/// noise of variance shot x max(v, 0) + read^2 per value, then the 8-bit
/// sRGB file (a JPEG with `cfg.jpeg_quality`) read back as `flashmat
/// estimate` reads it (clamped to [0, 1], sRGB-encoded, rounded to 1/255,
/// decoded). photo: `[3, H, W]` linear values, W = `width`.
pub fn finish_phone_photo<R: Rng>(photo: &mut [f32], width: usize, exposure: f64, cfg: &PhonePhotoConfig, rng: &mut R) -> anyhow::Result<()> {
    let read = cfg.read_noise * cfg.read_noise;
    let mut codes: Vec<u8> = photo
        .iter()
        .map(|&v| {
            let x = v as f64 * exposure;
            let z: f64 = rng.sample(StandardNormal);
            quantize_u8(photo_encode((x + (cfg.shot_noise * x.max(0.0) + read).sqrt() * z) as f32))
        })
        .collect();
    // Drawn after the noise, so photos without JPEG draw what they always drew.
    if let Some((lo, hi)) = cfg.jpeg_quality {
        let plane = photo.len() / 3;
        let height = plane / width;
        let interleaved: Vec<u8> = (0..plane * 3).map(|i| codes[(i % 3) * plane + i / 3]).collect();
        let decoded = crate::io::jpeg_round_trip(&interleaved, width, height, rng.random_range(lo..=hi))?;
        for (i, &c) in decoded.iter().enumerate() {
            codes[(i % 3) * plane + i / 3] = c;
        }
    }
    for (v, c) in photo.iter_mut().zip(codes) {
        *v = photo_decode(c as f32 / 255.0);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_pcg::Pcg64;

    #[test]
    fn phone_cameras_stay_in_their_ranges_and_the_flash_beside_the_lens() {
        let cfg = PhonePhotoConfig::default();
        let d = fov_to_distance(28.0);
        let mut rng = Pcg64::seed_from_u64(3);
        let (mut off_centre, mut far) = (0, 0);
        for _ in 0..2000 {
            let lv = phone_light_view(&mut rng, 28.0, &cfg);
            let [x, y, h] = lv.view;
            assert!(x.abs() <= 0.3 && y.abs() <= 0.3, "{x} {y}");
            assert!((0.85 * d..=1.2 * d).contains(&h), "{h}");
            assert_eq!(lv.light[2], h);
            let r = ((lv.light[0] - x).powi(2) + (lv.light[1] - y).powi(2)).sqrt();
            assert!((0.1 - 1e-12..=0.3 + 1e-12).contains(&r), "{r}");
            off_centre += (x.abs() > 0.15) as usize;
            far += (h > d) as usize;
        }
        // Uniform draws: half the offsets past half the range, 4/7 of the heights above d.
        assert!((900..1100).contains(&off_centre), "{off_centre}");
        assert!((1043..1243).contains(&far), "{far}");
    }

    #[test]
    fn the_exposure_factor_is_the_squared_distance_ratio() {
        let d = fov_to_distance(28.0);
        assert!((exposure_factor([0.0, 0.0, d], 28.0) - 1.0).abs() < 1e-12);
        // 3-4-5: |(0.6 d, 0, 0.8 d)| = d; |(0, 0, 1.2 d)|^2 / d^2 = 1.44.
        assert!((exposure_factor([0.6 * d, 0.0, 0.8 * d], 28.0) - 1.0).abs() < 1e-12);
        assert!((exposure_factor([0.0, 0.0, 1.2 * d], 28.0) - 1.44).abs() < 1e-12);
    }

    #[test]
    fn a_finished_photo_is_8_bit_srgb_with_the_asked_noise() {
        let quiet = PhonePhotoConfig { shot_noise: 0.0, read_noise: 0.0, ..Default::default() };
        let mut rng = Pcg64::seed_from_u64(5);
        // Without noise: exposure applied, clipped at 1, on the 8-bit sRGB grid.
        let mut v = vec![0.2f32, 0.9, -0.1, 0.5, 0.0, 0.0];
        finish_phone_photo(&mut v, 2, 2.0, &quiet, &mut rng).unwrap();
        assert_eq!(v[1], 1.0);
        assert_eq!(v[2], 0.0);
        assert_eq!(v[3], 1.0);
        // 0.4 linear: sRGB 0.6651 -> 170/255 -> 0.40198.
        assert!((v[0] - 0.401_978).abs() < 1e-5, "{}", v[0]);
        // With noise, at 0.2: standard deviation sqrt(1e-4 x 0.2 + 0.002^2) = 0.00490;
        // the rounding adds the 8-bit step's square / 12 (0.0036 in linear near 0.2).
        let cfg = PhonePhotoConfig::default();
        let mut grey = vec![0.2f32; 3 * 200 * 200];
        finish_phone_photo(&mut grey, 200, 1.0, &cfg, &mut rng).unwrap();
        let n = grey.len() as f64;
        let mean = grey.iter().map(|&v| v as f64).sum::<f64>() / n;
        let sd = (grey.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
        let code = quantize_u8(photo_encode(0.2)) as f32;
        let step = (photo_decode((code + 1.0) / 255.0) - photo_decode(code / 255.0)) as f64;
        let expected = (1e-4 * 0.2 + 0.002f64.powi(2) + step * step / 12.0).sqrt();
        assert!((mean - 0.2).abs() < 2e-4, "{mean}");
        assert!((sd / expected - 1.0).abs() < 0.05, "{sd} against {expected}");
    }

    #[test]
    fn a_jpeg_photo_stays_near_the_lossless_one_and_loses_more_at_lower_quality() {
        // [3, 32, 48]: a smooth ramp with a 4-pixel checker on the red channel.
        let (h, w) = (32, 48);
        let photo: Vec<f32> = (0..3 * h * w)
            .map(|i| {
                let (c, y, x) = (i / (h * w), i / w % h, i % w);
                0.05 + 0.4 * x as f32 / w as f32 + if c == 0 && (x / 4 + y / 4) % 2 == 0 { 0.3 } else { 0.0 }
            })
            .collect();
        let quiet = PhonePhotoConfig { shot_noise: 0.0, read_noise: 0.0, ..Default::default() };
        let finish = |jpeg_quality| {
            let mut v = photo.clone();
            finish_phone_photo(&mut v, w, 1.0, &PhonePhotoConfig { jpeg_quality, ..quiet.clone() }, &mut Pcg64::seed_from_u64(1)).unwrap();
            v
        };
        let lossless = finish(None);
        // Mean absolute error in sRGB codes against the lossless file.
        let error = |v: &[f32]| {
            let codes = |x: &[f32]| x.iter().map(|&x| photo_encode(x) * 255.0).collect::<Vec<_>>();
            codes(v).iter().zip(codes(&lossless)).map(|(a, b)| (a - b).abs() as f64).sum::<f64>() / v.len() as f64
        };
        let (fine, coarse) = (finish(Some((95, 95))), finish(Some((30, 30))));
        for v in fine.iter().chain(&coarse) {
            let code = photo_encode(*v) * 255.0;
            assert!((code - code.round()).abs() < 1e-3, "{code} is off the 8-bit grid");
        }
        let (e_fine, e_coarse) = (error(&fine), error(&coarse));
        assert!(e_fine > 0.05 && e_fine < 3.0, "{e_fine}");
        assert!(e_coarse > 1.5 * e_fine, "{e_coarse} against {e_fine}");
    }
}
