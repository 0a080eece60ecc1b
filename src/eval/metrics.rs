//! Image metrics of the evaluation (REFERENCE section 6): LPIPS-Alex on
//! linear renders clamped to [0, 1] (the paper's protocol), RMSE of
//! ln(1 + R), and PSNR of display images clamp(R, 0, 1)^(1/2.2).

use crate::lpips::Lpips;
use anyhow::{ensure, Result};
use tch::{Kind, Tensor};

/// PSNR reported for (numerically) identical display images, in dB.
pub const PSNR_CAP_DB: f64 = 100.0;

/// Configurations per LPIPS forward pass (bounds memory at 256^2).
const LPIPS_CHUNK: i64 = 8;

/// Scores of one render (or their mean over several).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scores {
    pub lpips: f64,
    pub rmse_log: f64,
    pub psnr: f64,
}

/// Which images LPIPS compares.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LpipsOn {
    /// Linear renders clamped to [0, 1]: the paper's protocol on renders.
    Linear,
    /// Display images clamp(R, 0, 1)^(1/2.2): what real photos are.
    Display,
}

/// Scores each configuration of `pred` against `target`, LPIPS on linear
/// renders clamped to [0, 1] (the paper's protocol).
/// pred, target: `[K, 3, H, W]` linear radiance (any device; moved to the
/// LPIPS weights' device), H, W >= 31. Returns K scores.
pub fn score_renders(lpips: &Lpips, pred: &Tensor, target: &Tensor) -> Result<Vec<Scores>> {
    score_renders_on(lpips, pred, target, LpipsOn::Linear)
}

/// [`score_renders`] with LPIPS on the images `on` says (RMSE and PSNR are
/// the same either way).
pub fn score_renders_on(lpips: &Lpips, pred: &Tensor, target: &Tensor, on: LpipsOn) -> Result<Vec<Scores>> {
    let (sp, st) = (pred.size(), target.size());
    ensure!(sp.len() == 4 && sp[1] == 3 && sp == st, "renders to compare must both be [K, 3, H, W], got {sp:?} and {st:?}");
    ensure!(sp[2] >= 31 && sp[3] >= 31, "LPIPS needs images of at least 31x31 pixels, got {}x{}", sp[3], sp[2]);
    let device = lpips.device();
    let pred = pred.to_device(device).to_kind(Kind::Float).clamp_min(0.0);
    let target = target.to_device(device).to_kind(Kind::Float).clamp_min(0.0);
    let k = sp[0];
    let mut lp = Vec::with_capacity(k as usize);
    tch::no_grad(|| {
        let mut start = 0;
        while start < k {
            let n = LPIPS_CHUNK.min(k - start);
            let image = |t: &Tensor| match on {
                LpipsOn::Linear => t.narrow(0, start, n).clamp_max(1.0),
                LpipsOn::Display => crate::spaces::linear_to_display(&t.narrow(0, start, n)),
            };
            let d = lpips.distance_01(&image(&pred), &image(&target));
            lp.extend(Vec::<f64>::try_from(d.to_kind(Kind::Double).to_device(tch::Device::Cpu)).unwrap_or_default());
            start += n;
        }
    });
    ensure!(lp.len() == k as usize, "LPIPS returned {} values for {k} renders", lp.len());
    let dims = [1i64, 2, 3];
    let log_mse = (pred.log1p() - target.log1p()).square().mean_dim(dims.as_slice(), false, Kind::Double);
    let disp = |t: &Tensor| crate::spaces::linear_to_display(t);
    let disp_mse = (disp(&pred) - disp(&target)).square().mean_dim(dims.as_slice(), false, Kind::Double);
    let log_mse = Vec::<f64>::try_from(log_mse.to_device(tch::Device::Cpu))?;
    let disp_mse = Vec::<f64>::try_from(disp_mse.to_device(tch::Device::Cpu))?;
    Ok((0..k as usize)
        .map(|i| Scores { lpips: lp[i].max(0.0), rmse_log: log_mse[i].sqrt(), psnr: psnr_db(disp_mse[i]) })
        .collect())
}

/// PSNR of a mean squared error between images in [0, 1], capped at
/// [`PSNR_CAP_DB`] (identical images).
pub fn psnr_db(mse: f64) -> f64 {
    if mse <= 10f64.powf(-PSNR_CAP_DB / 10.0) {
        PSNR_CAP_DB
    } else {
        -10.0 * mse.log10()
    }
}

/// Period-2 components of an image: for each channel, the means of
/// s(x, y) * ln(1 + I) with s = (-1)^x, (-1)^y and (-1)^(x + y).
/// `[channels][3]`.
fn period2_components(im: &crate::image::Image) -> Vec<[f64; 3]> {
    let (h, w) = (im.height, im.width);
    let n = (h * w) as f64;
    (0..im.channels)
        .map(|c| {
            let plane = im.plane(c);
            let mut sums = [0.0f64; 3];
            for y in 0..h {
                for x in 0..w {
                    let v = (plane[y * w + x].max(0.0) as f64).ln_1p();
                    let (sx, sy) = (if x % 2 == 0 { 1.0 } else { -1.0 }, if y % 2 == 0 { 1.0 } else { -1.0 });
                    sums[0] += sx * v;
                    sums[1] += sy * v;
                    sums[2] += sx * sy * v;
                }
            }
            sums.map(|s| s / n)
        })
        .collect()
}

/// The checkerboard of an image against a reference of the same size:
/// the root mean square, over channels and the three period-2 patterns
/// ((-1)^x stripes, (-1)^y stripes, (-1)^(x+y) checkers), of the
/// difference of their amplitudes in ln(1 + value). Subtracting the
/// reference's own takes out what a smooth image has from its gradients;
/// texture averages out over the image, a pattern stamped on every 2x2
/// cell does not. A +-1% checkerboard on a flat image scores
/// 0.01 / sqrt(3) (the one pattern of the three that is there).
pub fn checkerboard_amplitude(pred: &crate::image::Image, reference: &crate::image::Image) -> Result<f64> {
    ensure_same_size("checkerboard amplitude", pred, reference)?;
    let (p, r) = (period2_components(pred), period2_components(reference));
    let squares: f64 = p.iter().zip(&r).flat_map(|(a, b)| (0..3).map(move |i| (a[i] - b[i]).powi(2))).sum();
    Ok((squares / (3 * pred.channels.max(1)) as f64).sqrt())
}

/// Mean |ln(1 + a) - ln(1 + b)| over the pixels and channels of two images
/// of the same size (negative values count as 0): the tone-mapped error
/// that weighs highlights and dark regions alike.
pub fn log_l1(a: &crate::image::Image, b: &crate::image::Image) -> Result<f64> {
    ensure_same_size("log-L1", a, b)?;
    let sum: f64 = a.data.iter().zip(&b.data).map(|(x, y)| ((1.0 + x.max(0.0)).ln() - (1.0 + y.max(0.0)).ln()).abs() as f64).sum();
    Ok(sum / a.data.len().max(1) as f64)
}

fn ensure_same_size(what: &str, a: &crate::image::Image, b: &crate::image::Image) -> Result<()> {
    ensure!(
        (a.channels, a.height, a.width) == (b.channels, b.height, b.width),
        "{what} of images of different sizes ({}x{}x{} and {}x{}x{})",
        a.channels,
        a.height,
        a.width,
        b.channels,
        b.height,
        b.width
    );
    Ok(())
}

/// Mean of each score over configurations (NaN for none).
pub fn mean_scores(scores: &[Scores]) -> Scores {
    let n = scores.len() as f64;
    Scores {
        lpips: scores.iter().map(|s| s.lpips).sum::<f64>() / n,
        rmse_log: scores.iter().map(|s| s.rmse_log).sum::<f64>() / n,
        psnr: scores.iter().map(|s| s.psnr).sum::<f64>() / n,
    }
}

/// Geometric mean of positive values (NaN for none): how ratios average.
pub fn geometric_mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    (values.iter().map(|x| x.ln()).sum::<f64>() / values.len() as f64).exp()
}

/// Mean and half-width of its 95% interval, 1.96 * std / sqrt(n) (sample
/// std, n - 1; half-width 0 for a single value).
pub fn mean_ci95(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let mean = values.iter().sum::<f64>() / n;
    if values.len() < 2 {
        return (mean, 0.0);
    }
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, 1.96 * var.sqrt() / n.sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn geometric_mean_of_ratios() {
        assert!((geometric_mean(&[0.5, 2.0]) - 1.0).abs() < 1e-12);
        assert!((geometric_mean(&[1.0, 4.0, 16.0]) - 4.0).abs() < 1e-12);
        assert!(geometric_mean(&[]).is_nan());
    }

    #[test]
    fn checkerboard_amplitude_of_known_patterns() {
        use crate::image::Image;
        // A flat grey (e - 1, so ln(1 + v) = 1) with ln(1 + v) = 1 +- 0.01 on
        // alternate pixels: amplitude 0.01 in the checker pattern only, so
        // the RMS over the 3 patterns is 0.01 / sqrt(3).
        let e1 = std::f32::consts::E - 1.0;
        let flat = Image::from_fn(3, 16, 16, |_, _, _| e1);
        let checkers = Image::from_fn(3, 16, 16, |_, y, x| (1.0f32 + if (x + y) % 2 == 0 { 0.01 } else { -0.01 }).exp() - 1.0);
        let a = checkerboard_amplitude(&checkers, &flat).unwrap();
        assert!((a - 0.01 / 3f64.sqrt()).abs() < 1e-6, "{a}");
        // Stripes along x as well: two patterns of 0.01 each.
        let both = Image::from_fn(3, 16, 16, |_, y, x| (1.0f32 + if (x + y) % 2 == 0 { 0.01 } else { -0.01 } + if x % 2 == 0 { 0.01 } else { -0.01 }).exp() - 1.0);
        let b = checkerboard_amplitude(&both, &flat).unwrap();
        assert!((b - 0.01 * (2.0f64 / 3.0).sqrt()).abs() < 1e-6, "{b}");
        // A smooth ramp against itself: 0; a texture of period 4 has no period-2 part.
        let ramp = Image::from_fn(3, 16, 16, |c, y, x| 0.1 + 0.02 * (x + y + c) as f32);
        assert_eq!(checkerboard_amplitude(&ramp, &ramp).unwrap(), 0.0);
        let period4 = Image::from_fn(3, 16, 16, |_, _, x| if x % 4 < 2 { 0.5 } else { 0.2 });
        assert!(checkerboard_amplitude(&period4, &flat).unwrap() < 1e-9);
        assert!(checkerboard_amplitude(&flat, &Image::from_fn(3, 8, 16, |_, _, _| 0.5)).is_err());
        // log-L1: e - 1 against 0 is |1 - 0| everywhere.
        assert!((log_l1(&flat, &Image::filled(3, 16, 16, 0.0)).unwrap() - 1.0).abs() < 1e-6);
        assert!(log_l1(&flat, &Image::filled(3, 8, 16, 0.0)).is_err());
    }

    #[test]
    fn identical_renders_score_perfectly() {
        let lpips = Lpips::new(Device::Cpu).unwrap();
        tch::manual_seed(1);
        let a = Tensor::rand([2, 3, 32, 32], (Kind::Float, Device::Cpu)) * 1.5;
        let s = score_renders(&lpips, &a, &a).unwrap();
        assert_eq!(s.len(), 2);
        for x in &s {
            assert!(x.lpips.abs() < 1e-6, "{x:?}");
            assert_eq!(x.rmse_log, 0.0);
            assert_eq!(x.psnr, PSNR_CAP_DB);
        }
        // Different renders score worse.
        let b = &a * 0.5;
        let d = score_renders(&lpips, &a, &b).unwrap();
        assert!(d[0].lpips > 0.01 && d[0].rmse_log > 0.01 && d[0].psnr < 40.0, "{:?}", d[0]);
    }

    #[test]
    fn display_lpips_weighs_dark_differences_more() {
        // Two renders that differ by 0.02 in the shadows: on display images
        // (^(1/2.2)) the gap is 0.06..0.13, on linear ones 0.02.
        let lpips = Lpips::new(Device::Cpu).unwrap();
        tch::manual_seed(3);
        let a = Tensor::rand([1, 3, 32, 32], (Kind::Float, Device::Cpu)) * 0.05;
        let b = &a + 0.02;
        let lin = score_renders_on(&lpips, &a, &b, LpipsOn::Linear).unwrap()[0];
        let disp = score_renders_on(&lpips, &a, &b, LpipsOn::Display).unwrap()[0];
        assert!(disp.lpips > lin.lpips * 1.5, "display {} linear {}", disp.lpips, lin.lpips);
        assert_eq!((disp.rmse_log, disp.psnr), (lin.rmse_log, lin.psnr));
        assert!(score_renders_on(&lpips, &a, &a, LpipsOn::Display).unwrap()[0].lpips.abs() < 1e-6);
    }

    #[test]
    fn rmse_and_psnr_values() {
        let lpips = Lpips::new(Device::Cpu).unwrap();
        let a = Tensor::zeros([1, 3, 32, 32], (Kind::Float, Device::Cpu));
        let b = Tensor::full([1, 3, 32, 32], std::f64::consts::E - 1.0, (Kind::Float, Device::Cpu));
        let s = score_renders(&lpips, &a, &b).unwrap();
        assert!((s[0].rmse_log - 1.0).abs() < 1e-5);
        // Display values 0 vs 1: MSE 1, PSNR 0 dB.
        assert!(s[0].psnr.abs() < 1e-9);
        assert!((psnr_db(0.01) - 20.0).abs() < 1e-9);
    }

    #[test]
    fn confidence_interval() {
        let (m, h) = mean_ci95(&[1.0, 2.0, 3.0, 4.0]);
        assert!((m - 2.5).abs() < 1e-12);
        // std = sqrt(5/3) = 1.29099; 1.96 * 1.29099 / 2 = 1.26517
        assert!((h - 1.265171).abs() < 1e-5);
        assert_eq!(mean_ci95(&[3.0]), (3.0, 0.0));
    }
}
