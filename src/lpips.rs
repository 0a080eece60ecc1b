//! LPIPS perceptual distance (Zhang et al. 2018), AlexNet backbone with the
//! v0.1 linear layers: the differentiable perceptual training loss and the
//! evaluation metric.
//!
//! Definition, per image pair:
//! 1. scaling layer: `(x - shift) / scale` per channel;
//! 2. AlexNet features after each of its 5 ReLUs;
//! 3. each feature normalised to unit length along channels
//!    (`f / (sqrt(sum_c f^2) + 1e-10)`);
//! 4. squared difference, weighted 1x1 conv to one channel (no bias),
//!    spatial mean, summed over the 5 layers.
//!
//! Weights: `assets/lpips/alexnet-lpips-v0.1.safetensors`, made by
//! `scripts/convert_lpips.py` (provenance in `assets/lpips/README.md`).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use tch::{Device, Kind, Tensor};

/// Default weights file, inside the crate.
pub const DEFAULT_WEIGHTS: &str = "assets/lpips/alexnet-lpips-v0.1.safetensors";

/// [`DEFAULT_WEIGHTS`] under [`crate::bundled_root`].
pub fn default_weights_path() -> PathBuf {
    crate::bundled_root().join(DEFAULT_WEIGHTS)
}

/// Scaling layer constants of LPIPS (inputs in [-1, 1]).
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// Added to the channel norm before dividing (LPIPS `normalize_tensor`).
const NORM_EPS: f64 = 1e-10;

/// AlexNet convolutions: (torchvision `features` index, out channels,
/// in channels, kernel, stride, padding).
const CONVS: [(usize, i64, i64, i64, i64, i64); 5] = [
    (0, 64, 3, 11, 4, 2),
    (3, 192, 64, 5, 1, 2),
    (6, 384, 192, 3, 1, 1),
    (8, 256, 384, 3, 1, 1),
    (10, 256, 256, 3, 1, 1),
];

/// Frozen LPIPS-Alex v0.1 network.
pub struct Lpips {
    /// Per conv: weight `[O, I, k, k]`, bias `[O]`.
    convs: Vec<(Tensor, Tensor)>,
    /// Per layer: linear weight `[1, C, 1, 1]`.
    lins: Vec<Tensor>,
    /// `[1, 3, 1, 1]` each.
    shift: Tensor,
    scale: Tensor,
    device: Device,
}

impl std::fmt::Debug for Lpips {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lpips").field("device", &self.device).finish_non_exhaustive()
    }
}

impl Lpips {
    /// Loads the weights from [`default_weights_path`] onto `device`.
    pub fn new(device: Device) -> Result<Self> {
        Self::load(default_weights_path(), device)
    }

    /// Loads the weights from a safetensors file onto `device`. Errors (naming
    /// the file) if it is missing, unreadable, or lacks a tensor of the
    /// expected name, shape and dtype.
    pub fn load(path: impl AsRef<Path>, device: Device) -> Result<Self> {
        let path = path.as_ref();
        let ctx = || format!("LPIPS weights {}", path.display());
        if !path.is_file() {
            bail!("{}: file not found (run scripts/convert_lpips.py)", ctx());
        }
        let named = Tensor::read_safetensors(path)
            .map_err(|e| anyhow!("{e}"))
            .with_context(|| format!("{}: not a readable safetensors file", ctx()))?;
        let mut map: std::collections::HashMap<String, Tensor> = named.into_iter().collect();
        let mut take = |name: String, shape: &[i64]| -> Result<Tensor> {
            let t = map.remove(&name).ok_or_else(|| anyhow!("{}: missing tensor {name}", ctx()))?;
            if t.size() != shape || t.kind() != Kind::Float {
                bail!("{}: tensor {name} is {:?} {:?}, expected Float {shape:?}", ctx(), t.kind(), t.size());
            }
            // Frozen: no gradient w.r.t. the weights, only w.r.t. the inputs.
            Ok(t.to_device(device).set_requires_grad(false))
        };
        let mut convs = Vec::with_capacity(5);
        let mut lins = Vec::with_capacity(5);
        for &(idx, o, i, k, _, _) in &CONVS {
            let w = take(format!("features.{idx}.weight"), &[o, i, k, k])?;
            let b = take(format!("features.{idx}.bias"), &[o])?;
            convs.push((w, b));
        }
        for (l, &(_, o, ..)) in CONVS.iter().enumerate() {
            lins.push(take(format!("lin.{l}.weight"), &[1, o, 1, 1])?);
        }
        let finite =
            convs.iter().flat_map(|(w, b)| [w, b]).chain(lins.iter()).all(|t| t.isfinite().all().int64_value(&[]) != 0);
        if !finite {
            bail!("{}: weights contain non-finite values", ctx());
        }
        let consts = |v: [f32; 3]| Tensor::from_slice(&v).view([1, 3, 1, 1]).to_device(device);
        Ok(Self { convs, lins, shift: consts(SHIFT), scale: consts(SCALE), device })
    }

    /// Device the weights live on; inputs must be on it too.
    pub fn device(&self) -> Device {
        self.device
    }

    /// LPIPS distance per pair, differentiable w.r.t. `a` and `b` (wrap in
    /// `tch::no_grad` for evaluation).
    ///
    /// a, b: `[N, 3, H, W]` in [-1, 1], H, W >= 31 (smallest size AlexNet accepts);
    /// returns `[N]` (Float, on the weights' device).
    pub fn distance(&self, a: &Tensor, b: &Tensor) -> Tensor {
        let (sa, sb) = (a.size(), b.size());
        assert!(
            sa.len() == 4 && sa[1] == 3 && sa == sb,
            "LPIPS: inputs must both be [N, 3, H, W], got {sa:?} and {sb:?}"
        );
        assert!(
            a.device() == self.device && b.device() == self.device,
            "LPIPS: inputs on {:?}/{:?}, weights on {:?}",
            a.device(),
            b.device(),
            self.device
        );
        let n = sa[0];
        let prepare = |t: &Tensor| (t.to_kind(Kind::Float) - &self.shift) / &self.scale;
        // One pass for both images, [2N, 3, H, W]; or, when only `a` takes
        // a gradient (a training loss against a fixed target), `b` in its
        // own pass without a graph, so the backward pass covers N images
        // instead of 2N.
        let (mut xa, mut xb) = if a.requires_grad() && !b.requires_grad() && !crate::reference_paths::on() {
            (prepare(a), Some(prepare(b)))
        } else {
            (prepare(&Tensor::cat(&[a, b], 0)), None)
        };
        let mut total: Option<Tensor> = None;
        for (l, ((w, bias), &(_, _, _, _, stride, pad))) in self.convs.iter().zip(&CONVS).enumerate() {
            let features = |x: &Tensor| {
                // AlexNet: max-pool (3, stride 2) before conv2 and conv3.
                let x = if l == 1 || l == 2 { x.max_pool2d([3, 3], [2, 2], [0, 0], [1, 1], false) } else { x.shallow_clone() };
                crate::precision::forward(x.device(), || x.conv2d(w, Some(bias), [stride, stride], [pad, pad], [1, 1], 1).relu())
            };
            // The distance itself in f32 (a loss), from features autocast may have made bf16.
            let unit_normalise = |f: &Tensor| unit_normalise(&crate::precision::to_f32(f.shallow_clone()));
            xa = features(&xa);
            xb = xb.map(|x| tch::no_grad(|| features(&x)));
            let (fa, fb) = match &xb {
                Some(xb) => (unit_normalise(&xa), tch::no_grad(|| unit_normalise(xb))),
                None => {
                    let f = unit_normalise(&xa); // [2N, C, h, w]
                    (f.narrow(0, 0, n), f.narrow(0, n, n))
                }
            };
            let d = (fa - fb).square(); // [N, C, h, w]
            let layer = d
                .conv2d(&self.lins[l], None::<Tensor>, [1, 1], [0, 0], [1, 1], 1) // [N, 1, h, w]
                .mean_dim([1i64, 2, 3].as_slice(), false, Kind::Float); // [N]
            total = Some(match total {
                None => layer,
                Some(t) => t + layer,
            });
        }
        total.expect("five layers")
    }

    /// As [`Lpips::distance`] for inputs in [0, 1] (mapped to [-1, 1]), e.g.
    /// linear renders clamped to [0, 1] as in the paper's protocol.
    ///
    /// a, b: `[N, 3, H, W]` in [0, 1]; returns `[N]`.
    pub fn distance_01(&self, a: &Tensor, b: &Tensor) -> Tensor {
        self.distance(&(a * 2.0 - 1.0), &(b * 2.0 - 1.0))
    }
}

/// f: `[N, C, h, w]` -> f / (||f||_channels + 1e-10).
fn unit_normalise(f: &Tensor) -> Tensor {
    let norm = f.square().sum_dim_intlist([1i64].as_slice(), true, Kind::Float).sqrt();
    f / (norm + NORM_EPS)
}

#[cfg(test)]
mod tests {
    use super::*;

    const CALIBRATION: [(&str, f64); 5] =
        [("I03", 0.7237), ("I04", 0.2572), ("I06", 0.0508), ("I08", 0.0520), ("I19", 0.4253)];

    fn fixtures() -> PathBuf {
        PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/fixtures/lpips-calibration"))
    }

    /// An 8-bit RGB PNG as `[1, 3, H, W]` in [-1, 1] (x / 127.5 - 1).
    fn read_png(path: &Path) -> Tensor {
        let img = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_rgb8();
        let (w, h) = img.dimensions();
        Tensor::from_slice(img.as_raw())
            .view([h as i64, w as i64, 3])
            .permute([2, 0, 1])
            .unsqueeze(0)
            .to_kind(Kind::Float)
            / 127.5
            - 1.0
    }

    fn model() -> Lpips {
        Lpips::new(Device::Cpu).expect("LPIPS weights")
    }

    fn pair(name: &str) -> (Tensor, Tensor) {
        let dir = fixtures();
        (read_png(&dir.join(format!("ref/{name}.png"))), read_png(&dir.join(format!("dist/{name}.png"))))
    }

    #[test]
    fn lpips_calibration() {
        let m = model();
        let (refs, dists): (Vec<_>, Vec<_>) = CALIBRATION.iter().map(|(n, _)| pair(n)).unzip();
        let d = tch::no_grad(|| m.distance(&Tensor::cat(&refs, 0), &Tensor::cat(&dists, 0)));
        let d: Vec<f64> = Vec::try_from(d.to_kind(Kind::Double)).unwrap();
        let mut bad = Vec::new();
        for ((name, want), got) in CALIBRATION.iter().zip(&d) {
            eprintln!("LPIPS {name}: {got:.6} (table {want:.4}, diff {:+.2e})", got - want);
            if (got - want).abs() > 1e-4 {
                bad.push(*name);
            }
        }
        assert!(bad.is_empty(), "LPIPS off by more than 1e-4 on {bad:?}: {d:?}");
    }

    #[test]
    fn lpips_identical_is_zero() {
        let m = model();
        let (a, _) = pair("I06");
        let d = tch::no_grad(|| m.distance(&a, &a.copy()));
        assert_eq!(d.double_value(&[0]), 0.0);
    }

    #[test]
    fn lpips_symmetric() {
        let m = model();
        let (a, b) = pair("I04");
        let (ab, ba) = tch::no_grad(|| (m.distance(&a, &b), m.distance(&b, &a)));
        let (ab, ba) = (ab.double_value(&[0]), ba.double_value(&[0]));
        assert!((ab - ba).abs() <= 1e-6 * ab.abs(), "d(a,b) = {ab}, d(b,a) = {ba}");
    }

    #[test]
    fn lpips_gradient_flows() {
        let m = model();
        let a = Tensor::rand([2, 3, 64, 64], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let b = Tensor::rand([2, 3, 64, 64], (Kind::Float, Device::Cpu));
        let d = m.distance_01(&a, &b);
        assert_eq!(d.size(), [2]);
        d.sum(Kind::Float).backward();
        let g = a.grad();
        assert!(g.defined(), "no gradient on the input");
        assert!(g.isfinite().all().int64_value(&[]) != 0, "non-finite gradient");
        assert!(g.abs().max().double_value(&[]) > 0.0, "zero gradient");
        // The fixed target's own pass without a graph (a takes a gradient, b
        // does not) gives the one-pass distance and gradient.
        let a2 = a.detach().set_requires_grad(true);
        let d2 = m.distance_01(&a2, &b.set_requires_grad(true));
        assert!((&d - &d2).abs().max().double_value(&[]) <= 1e-6, "{d} vs {d2}");
        d2.sum(Kind::Float).backward();
        assert!((a2.grad() - &g).abs().max().double_value(&[]) <= 1e-6 * g.abs().max().double_value(&[]));
        // Weights stay frozen.
        assert!(m.convs.iter().all(|(w, b)| !w.requires_grad() && !b.requires_grad()));
        assert!(m.lins.iter().all(|w| !w.requires_grad()));
    }

    #[test]
    fn lpips_identical_gradient_is_finite() {
        // At a == b the sqrt in the normalisation sees zero-norm pixels; the
        // gradient must still be finite (zero).
        let m = model();
        let b = Tensor::rand([1, 3, 64, 64], (Kind::Float, Device::Cpu));
        let a = b.copy().set_requires_grad(true);
        m.distance_01(&a, &b).sum(Kind::Float).backward();
        assert!(a.grad().isfinite().all().int64_value(&[]) != 0);
    }

    #[test]
    fn lpips_missing_or_damaged_file_errors() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nope.safetensors");
        let err = Lpips::load(&missing, Device::Cpu).unwrap_err();
        assert!(format!("{err:#}").contains("nope.safetensors"), "{err:#}");

        let damaged = dir.path().join("damaged.safetensors");
        let bytes = std::fs::read(default_weights_path()).unwrap();
        std::fs::write(&damaged, &bytes[..bytes.len() / 2]).unwrap();
        let err = Lpips::load(&damaged, Device::Cpu).unwrap_err();
        assert!(format!("{err:#}").contains("damaged.safetensors"), "{err:#}");

        let garbage = dir.path().join("garbage.safetensors");
        std::fs::write(&garbage, b"not a safetensors file").unwrap();
        let err = Lpips::load(&garbage, Device::Cpu).unwrap_err();
        assert!(format!("{err:#}").contains("garbage.safetensors"), "{err:#}");
    }
}
