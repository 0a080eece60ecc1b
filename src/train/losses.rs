//! Loss terms of REFERENCE section 5.

use super::PixelSampling;
use crate::lpips::Lpips;
use crate::model::Discriminator;
use anyhow::Result;
use tch::{Kind, Tensor};

/// Flattens `[N, K, 3, H, W]` to `[N*K, 3, H, W]`.
fn flat(t: &Tensor) -> Tensor {
    t.flatten(0, 1)
}

/// Display transform for LPIPS with a small offset so the 1/2.2 power has a
/// finite gradient at black. log: `[N, K, 3, H, W]` -> `[N*K, 3, H, W]` in [0,1].
fn display_for_lpips(log: &Tensor) -> Tensor {
    (flat(log).expm1().clamp(0.0, 1.0) + 1e-4).pow_tensor_scalar(1.0 / crate::spaces::GAMMA).clamp(0.0, 1.0)
}

/// Mean LPIPS between predicted and target log renders (0 when disabled).
/// pred_log, target_log: `[N, K, 3, H, W]` -> scalar.
pub fn perceptual(lpips: Option<&Lpips>, pred_log: &Tensor, target_log: &Tensor) -> Result<Tensor> {
    match lpips {
        Some(l) => Ok(l.distance_01(&display_for_lpips(pred_log), &display_for_lpips(&target_log.detach())).mean(Kind::Float)),
        None => Ok(Tensor::zeros([], (Kind::Float, pred_log.device()))),
    }
}

/// The colour-balance term: L1 distance between the chromaticities
/// rgb / (r + g + b) of each render's mean linear colour and the truth's,
/// averaged over renders (the uniform-colour check's error, as a loss).
/// pred_log, target_log: `[N, K, 3, H, W]` ln(1 + R) -> scalar.
pub fn chroma_l1(pred_log: &Tensor, target_log: &Tensor) -> Tensor {
    let chroma = |log: &Tensor| {
        let mean = flat(log).expm1().mean_dim([2i64, 3].as_slice(), false, Kind::Float);
        &mean / mean.sum_dim_intlist([1i64].as_slice(), true, Kind::Float).clamp_min(1e-6)
    };
    (chroma(pred_log) - chroma(&target_log.detach())).abs().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).mean(Kind::Float)
}

/// Repeats the input photo once per output render.
/// photo_log: `[N, 3, H, W]`, k -> `[N*K, 3, H, W]`.
fn photo_per_output(photo_log: &Tensor, k: i64) -> Tensor {
    let s = photo_log.size();
    photo_log.unsqueeze(1).expand([s[0], k, s[1], s[2], s[3]], false).flatten(0, 1)
}

/// The model's adversarial term |D(prediction, photo) - 1| (0 when disabled).
/// pred_log: `[N, K, 3, H, W]`, photo_log: `[N, 3, H, W]` -> scalar.
pub fn adversarial(disc: &Discriminator, pred_log: &Tensor, photo_log: &Tensor, weight: f64) -> Result<Tensor> {
    if weight == 0.0 {
        return Ok(Tensor::zeros([], (Kind::Float, pred_log.device())));
    }
    let k = pred_log.size()[1];
    let score = disc.forward_t(&flat(pred_log), &photo_per_output(photo_log, k), true)?;
    Ok((score - 1.0).abs().mean(Kind::Float))
}

/// Least-squares discriminator loss: (target, photo) -> 1, (prediction,
/// photo) -> 0, (another material's target, photo) -> 0.
/// pred_log, target_log: `[N, K, 3, H, W]`, photo_log: `[N, 3, H, W]`.
pub fn discriminator_loss(disc: &Discriminator, pred_log: &Tensor, target_log: &Tensor, photo_log: &Tensor, weight: f64) -> Result<Tensor> {
    if weight == 0.0 {
        return Ok(Tensor::zeros([], (Kind::Float, pred_log.device())));
    }
    let k = pred_log.size()[1];
    let photos = photo_per_output(photo_log, k);
    let real = disc.forward_t(&flat(target_log), &photos, true)?;
    let fake = disc.forward_t(&flat(pred_log), &photos, true)?;
    // Pair each material's photo with the next material's targets.
    let other = flat(&target_log.roll([1i64].as_slice(), [0i64].as_slice()));
    let wrong = disc.forward_t(&other, &photos, true)?;
    Ok((real - 1.0).square().mean(Kind::Float) + fake.square().mean(Kind::Float) + wrong.square().mean(Kind::Float))
}

/// Pixels smoother than this roughness are the glossy ones of the code
/// term's weighting (and of `examples/code_error_by_gloss.rs`).
pub const GLOSSY_ROUGHNESS: f64 = 0.35;

/// The curriculum's dense code target: mean |neural - target| over the
/// mean |target|, so the term's scale does not depend on how large the
/// teacher's codes came out. With `gloss_weight` k > 0 a pixel's error
/// counts 1 + k * max(0, 1 - r / [`GLOSSY_ROUGHNESS`]) times (r its true
/// roughness), a weighted mean: glossy pixels are few in most materials,
/// and an unweighted mean let M_est learn the matte pixels' codes while
/// it unlearned the glossy ones' (reports/highlights-experiments.md
/// section 5). neural, target: `[N, C, H, W]`, roughness: `[N, 1, H, W]`.
pub fn code_l1(neural: &Tensor, target: &Tensor, roughness: &Tensor, gloss_weight: f64) -> Tensor {
    let scale = target.abs().mean(Kind::Float).clamp_min(1e-6);
    gloss_weighted_l1(neural, target, roughness, gloss_weight) / scale
}

/// The GGX-value term of a model whose M_est writes GGX values
/// (`ModelConfig::ggx_codes`): mean |values - maps| over the 10 values of
/// every pixel, glossy pixels weighted as in [`code_l1`]. The code term
/// reaches the head only through the frozen encoder; this one asks the
/// head for the true roughness and ks directly (section 7 of
/// reports/highlights-experiments.md: the head wrote glossy pixels a third
/// too rough). values, maps: `[N, 10, H, W]` (maps as `svbrdf`'s), the
/// roughness weighting read from `maps`.
pub fn ggx_value_l1(values: &Tensor, maps: &Tensor, gloss_weight: f64) -> Tensor {
    let roughness = maps.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1);
    gloss_weighted_l1(values, maps, &roughness, gloss_weight)
}

/// Mean |a - b| over channels and pixels; with `gloss_weight` k > 0 a
/// pixel counts 1 + k * max(0, 1 - r / [`GLOSSY_ROUGHNESS`]) times.
/// a, b: `[N, C, H, W]`, roughness: `[N, 1, H, W]`.
fn gloss_weighted_l1(a: &Tensor, b: &Tensor, roughness: &Tensor, gloss_weight: f64) -> Tensor {
    let err = (a - b).abs();
    if gloss_weight == 0.0 {
        return err.mean(Kind::Float);
    }
    let weight = (roughness.to_kind(Kind::Float) / -GLOSSY_ROUGHNESS + 1.0).clamp_min(0.0) * gloss_weight + 1.0;
    let per_pixel = err.mean_dim([1i64].as_slice(), true, Kind::Float);
    (per_pixel * &weight).sum(Kind::Float) / weight.sum(Kind::Float)
}

/// Mean L2 norm of the neural parameter vectors. neural: `[N, C, H, W]`.
pub fn mean_param_norm(neural: &Tensor) -> f64 {
    mean_param_norm_tensor(neural).double_value(&[])
}

/// [`mean_param_norm`] as a 0-dim tensor on the map's device (no read-back).
pub fn mean_param_norm_tensor(neural: &Tensor) -> Tensor {
    neural.detach().square().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).sqrt().mean(Kind::Float)
}

/// The values of 0-dim tensors, read back in one transfer: on a GPU each
/// `double_value` waits for the queue to drain, so a step reads its losses
/// and gradient norms once, at its end.
pub fn read_scalars(scalars: &[&Tensor]) -> Vec<f64> {
    if scalars.is_empty() {
        return vec![];
    }
    let stacked = Tensor::stack(&scalars.iter().map(|t| t.detach().to_kind(Kind::Double).reshape([])).collect::<Vec<_>>(), 0);
    Vec::<f64>::try_from(stacked.to_device(tch::Device::Cpu)).expect("a 1-D f64 tensor converts to Vec<f64>")
}

/// The shift-consistency term: M_est's codes of two photos of the same
/// materials, the second's window `offsets[i]` = (rows, columns) from the
/// first's, compared where the windows overlap: mean |a - b| over the
/// overlaps, over a scale. By default the scale is the mean |a| taken as a
/// constant (no gradient flows through it, so shrinking every code does
/// lower the term: the runs of `reports/shift-consistency.md` shrank
/// them). `scale_free`: the scale is the mean of both maps' mean |code|
/// with its gradient, so the term is the same for the maps times any k > 0
/// and only disagreement between the photos lowers it.
/// first, second: `[N, C, H, W]` -> scalar.
pub fn shift_consistency(first: &Tensor, second: &Tensor, offsets: &[(i64, i64)], scale_free: bool) -> Tensor {
    let (h, w) = (first.size()[2], first.size()[3]);
    // The window of one photo that the other also shows: start in its own
    // pixels for an offset `d` of the other's, and length.
    let span = |d: i64, n: i64| (d.max(0), (-d).max(0), n - d.abs());
    let mut total = Tensor::zeros([], (Kind::Float, first.device()));
    let mut count = 0i64;
    for (i, &(dy, dx)) in offsets.iter().enumerate() {
        let ((ya, yb, rows), (xa, xb, cols)) = (span(dy, h), span(dx, w));
        if rows <= 0 || cols <= 0 {
            continue;
        }
        let a = first.get(i as i64).narrow(1, ya, rows).narrow(2, xa, cols);
        let b = second.get(i as i64).narrow(1, yb, rows).narrow(2, xb, cols);
        count += a.numel() as i64;
        total = total + (a - b).abs().sum(Kind::Float);
    }
    let scale = if scale_free {
        ((first.abs().mean(Kind::Float) + second.abs().mean(Kind::Float)) * 0.5).clamp_min(1e-6)
    } else {
        first.detach().abs().mean(Kind::Float).clamp_min(1e-6)
    };
    total / (count.max(1) as f64) / scale
}

/// Pixel mask for the renderer's data term: `fraction` of the pixels drawn
/// without replacement from a multinomial. Drawn as the top-k of
/// ln(p) + Gumbel noise (equivalent to sequential sampling without
/// replacement) with noise from `rng`, so the draw does not depend on
/// libtorch's global generator and replays exactly on resume.
/// neural: `[N, C, H, W]`, targets (linear): `[N, K, 3, H, W]` -> mask
/// `[N, K or 1, 1, H, W]` of 0/1 values.
pub fn pixel_mask<R: rand::Rng>(neural: &Tensor, targets: &Tensor, fraction: f64, mode: PixelSampling, rng: &mut R) -> Tensor {
    let s = targets.size();
    let (n, k, h, w) = (s[0], s[1], s[3], s[4]);
    let probs = match mode {
        PixelSampling::All => return Tensor::ones([n, 1, 1, h, w], (Kind::Float, targets.device())),
        PixelSampling::InverseNorm => {
            let norm = neural.detach().square().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).sqrt();
            (norm + 1e-6).reciprocal().view([n, h * w])
        }
        PixelSampling::TargetNorm => {
            targets.detach().square().sum_dim_intlist([2i64].as_slice(), false, Kind::Float).view([n * k, h * w]) + 1e-8
        }
    };
    let count = ((fraction * (h * w) as f64).round() as i64).clamp(1, h * w);
    let rows = probs.size()[0];
    let gumbel: Vec<f32> = (0..rows * h * w).map(|_| -(-(rng.random::<f32>().max(1e-20)).ln()).ln()).collect();
    let keys = probs.log() + Tensor::from_slice(&gumbel).view([rows, h * w]).to_device(probs.device());
    let (_, picked) = keys.topk(count, 1, true, false);
    let mask = Tensor::zeros([rows, h * w], (Kind::Float, targets.device())).scatter_value(1, &picked, 1.0);
    mask.view([n, rows / n, 1, h, w])
}

/// Half-angle of the flash camera's views in the lobe term: a camera at
/// the model's 28 degree field of view sees the material's corners about 14
/// degrees off the normal ([`LobeSampling::camera_share`]).
pub const CAMERA_VIEW_DEG: f64 = 14.0;

/// The lobe term (`TrainConfig::weight_lobe`, issue 48): at
/// `sampling.pixels` random pixels of the batch (uniform, with
/// replacement), a view cosine-distributed over the hemisphere and a light
/// inside the pixel's true GGX lobe (`teacher::lobe_lights`); mean
/// |ln(1 + R) - ln(1 + R_GGX)| over the pairs whose light stays above the
/// surface, R rendered from the neural map's code at the pixel. The other
/// fields of [`LobeSampling`] mix in random lights, camera views and
/// narrower lobe lights ([`lobe_pairs`]). Every draw comes from `rng`, so
/// it replays on resume. neural: `[N, C, H, W]` (with its graph for M_est's
/// half, detached for the renderer's); maps: `[N, 10, H, W]` -> scalar.
pub fn lobe_l1<R: rand::Rng>(renderer: &crate::model::NeuralRenderer, neural: &Tensor, maps: &Tensor, sampling: &LobeSampling, rng: &mut R) -> Result<Tensor> {
    let p = lobe_pairs(maps, sampling, rng);
    let c = neural.size()[1];
    let codes = neural.permute([0, 2, 3, 1]).reshape([-1, c]).index_select(0, &p.index);
    let target = tch::no_grad(|| super::teacher::ggx_log_rows(&p.maps, &p.wi, &p.wo));
    let pred = renderer.forward_rows(&codes, &p.wi, &p.wo)?;
    let weight = p.used.to_kind(Kind::Float);
    Ok(((pred - target).abs() * &weight).sum(Kind::Float) / (weight.sum(Kind::Float) * 3.0).clamp_min(1.0))
}

/// The lobe term's draws (`lobe_l1`): pixel rows, their GGX values and the
/// light and view of each pair.
pub struct LobePairs {
    /// Pixel rows of the batch flattened as `[N * H * W]`: `[R]` (int64).
    pub index: Tensor,
    /// GGX values at those pixels `[R, 10]`.
    pub maps: Tensor,
    /// Light and view directions `[R, 3]` each (unit).
    pub wi: Tensor,
    pub wo: Tensor,
    /// The pairs that count `[R, 1]` (bool): a lobe light above the surface, or a random light.
    pub used: Tensor,
}

/// How the lobe term draws its pairs (`lobe_l1`; `TrainConfig`'s
/// `lobe_pixels`, `lobe_share`, `lobe_camera_share`, `lobe_narrow_share`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LobeSampling {
    /// Pairs per step, over the whole batch.
    pub pixels: usize,
    /// Share of pairs with a light in the lobe; the rest take a
    /// cosine-distributed light at the same pixels and views, meant to hold
    /// the renderer to GGX around the lobe (at 0.5 it did not lower the
    /// rest's overshoot: reports/highlights-experiments.md, E4).
    pub lobe_share: f64,
    /// Share of views from the flash camera's cone, where the photo's camera
    /// and the moved-highlight test look from (the rest: the hemisphere).
    pub camera_share: f64,
    /// Share of lobe lights drawn around the mirror direction with the
    /// spread of a roughness U(0.05, 1) where that is narrower than the
    /// pixel's own: a rough pixel is then also asked how dim it is right at
    /// the mirror direction, where a glossy one is bright (without it, a
    /// renderer taught lobes drew a mirror highlight on matte materials).
    pub narrow_share: f64,
}

impl LobeSampling {
    /// Lobe lights only, at each pixel's own spread, views over the hemisphere.
    pub fn lobes(pixels: usize) -> Self {
        Self { pixels, lobe_share: 1.0, camera_share: 0.0, narrow_share: 0.0 }
    }
}

/// Draws the lobe term's pairs from `rng` (see `lobe_l1`).
/// maps: `[N, 10, H, W]`.
pub fn lobe_pairs<R: rand::Rng>(maps: &Tensor, sampling: &LobeSampling, rng: &mut R) -> LobePairs {
    let LobeSampling { pixels, lobe_share, camera_share, narrow_share } = *sampling;
    use rand_distr::{Distribution, StandardNormal};
    let s = maps.size();
    let total = s[0] * s[2] * s[3];
    let device = maps.device();
    let r = pixels as i64;
    let cosine = |rng: &mut R| {
        let (u, phi) = (rng.random::<f32>(), rng.random::<f32>() * std::f32::consts::TAU);
        [u.sqrt() * phi.cos(), u.sqrt() * phi.sin(), (1.0 - u).max(1e-4).sqrt()]
    };
    let index: Vec<i64> = (0..r).map(|_| rng.random_range(0..total)).collect();
    let mut wo: Vec<f32> = (0..pixels).flat_map(|_| cosine(rng)).collect();
    let offsets: Vec<f32> = (0..2 * pixels).map(|_| StandardNormal.sample(rng)).collect();
    // Each option draws only when it is on, so runs without it replay the stream of runs before it.
    let off_lobe: Option<(Vec<f32>, Vec<f32>)> = (lobe_share < 1.0).then(|| {
        let mut light = Vec::with_capacity(3 * pixels);
        let mut off = Vec::with_capacity(pixels);
        for _ in 0..pixels {
            light.extend_from_slice(&cosine(rng));
            off.push(if rng.random::<f64>() < lobe_share { 0.0 } else { 1.0 });
        }
        (light, off)
    });
    if camera_share > 0.0 {
        // Uniform over the disc the camera's cone cuts from the plane z = 1.
        let reach = CAMERA_VIEW_DEG.to_radians().tan() as f32;
        for i in 0..pixels {
            let (u, phi, pick) = (rng.random::<f32>(), rng.random::<f32>() * std::f32::consts::TAU, rng.random::<f64>());
            if pick < camera_share {
                let (x, y) = (reach * u.sqrt() * phi.cos(), reach * u.sqrt() * phi.sin());
                let norm = (x * x + y * y + 1.0).sqrt();
                wo[3 * i..3 * i + 3].copy_from_slice(&[x / norm, y / norm, 1.0 / norm]);
            }
        }
    }
    let narrow: Option<Vec<f32>> = (narrow_share > 0.0).then(|| {
        (0..pixels)
            .map(|_| {
                let (roughness, pick) = (0.05 + 0.95 * rng.random::<f32>(), rng.random::<f64>());
                if pick < narrow_share { roughness } else { f32::INFINITY }
            })
            .collect()
    });
    let index = Tensor::from_slice(&index).to_device(device);
    let maps = maps.to_kind(Kind::Float).permute([0, 2, 3, 1]).reshape([-1, s[1]]).index_select(0, &index);
    let wo = Tensor::from_slice(&wo).view([r, 3]).to_device(device);
    // The spread's roughness: the pixel's own, or the narrower draw.
    let spread = match narrow {
        Some(roughness) => {
            let own = maps.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1);
            let narrowed = own.minimum(&Tensor::from_slice(&roughness).view([r, 1]).to_device(device));
            Tensor::cat(&[maps.narrow(1, 0, 6), narrowed, maps.narrow(1, 7, 3)], 1)
        }
        None => maps.shallow_clone(),
    };
    let (wi, above) = super::teacher::lobe_lights(&spread, &wo, &Tensor::from_slice(&offsets).view([r, 2]).to_device(device));
    let (wi, used) = match off_lobe {
        Some((light, off)) => {
            let off = Tensor::from_slice(&off).view([r, 1]).to_device(device);
            let light = Tensor::from_slice(&light).view([r, 3]).to_device(device);
            (&off * light + (1.0 - &off) * wi, above.logical_or(&off.gt(0.5)))
        }
        None => (wi, above),
    };
    LobePairs { index, maps, wi, wo, used }
}

/// L1 over the masked pixels only. pred, target: `[N, K, 3, H, W]`; mask broadcastable.
pub fn masked_l1(pred: &Tensor, target: &Tensor, mask: &Tensor) -> Tensor {
    let diff = (pred - target).abs() * mask;
    let denom = (mask.expand_as(pred).sum(Kind::Float)).clamp_min(1.0);
    diff.sum(Kind::Float) / denom
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use tch::Device;

    /// The code term by hand: two pixels of two channels, errors 1 and 3,
    /// mean |target| 2. Unweighted: 2 / 2 = 1. With weight 2 the mirror-smooth
    /// pixel (r = 0) counts 3 times and the matte one (r = 0.7) once:
    /// (3 * 1 + 1 * 3) / 4 / 2 = 0.75; at r = 0.175 it counts 1 + 2 * 0.5 = 2
    /// times: (2 * 1 + 3) / 3 / 2 = 5/6.
    #[test]
    fn the_code_term_weights_glossy_pixels_by_their_roughness() {
        let neural = Tensor::zeros([1, 2, 1, 2], (Kind::Float, Device::Cpu));
        let target = Tensor::from_slice(&[1.0f32, 3.0, -1.0, -3.0]).view([1, 2, 1, 2]);
        let code = |r0: f32, k: f64| code_l1(&neural, &target, &Tensor::from_slice(&[r0, 0.7f32]).view([1, 1, 1, 2]), k).double_value(&[]);
        assert!((code(0.0, 0.0) - 1.0).abs() < 1e-6);
        assert!((code(0.0, 2.0) - 0.75).abs() < 1e-6);
        assert!((code(0.175, 2.0) - 5.0 / 6.0).abs() < 1e-6);
        // A matte material is weighted alike everywhere: the plain mean.
        assert!((code(0.5, 2.0) - 1.0).abs() < 1e-6);
    }

    /// The GGX-value term by hand: two pixels, the head writes zeros, the
    /// true maps are all 0.5 but for roughness (channel 6), 0 on the left
    /// pixel and 0.7 on the right. Errors per pixel: (9 * 0.5 + 0) / 10 =
    /// 0.45 and (9 * 0.5 + 0.7) / 10 = 0.52. Unweighted: 0.485. With weight
    /// 2 the mirror-smooth left pixel counts 3 times: (3 * 0.45 + 0.52) / 4
    /// = 0.4675. No scale: a head that writes the truth scores 0.
    #[test]
    fn the_ggx_value_term_is_the_glossy_weighted_l1_of_the_values() {
        let maps = Tensor::full([1, 10, 1, 2], 0.5, (Kind::Float, Device::Cpu));
        maps.narrow(1, crate::svbrdf::ROUGHNESS_CHANNEL, 1).copy_(&Tensor::from_slice(&[0.0f32, 0.7]).view([1, 1, 1, 2]));
        let values = Tensor::zeros([1, 10, 1, 2], (Kind::Float, Device::Cpu));
        let term = |k: f64| ggx_value_l1(&values, &maps, k).double_value(&[]);
        assert!((term(0.0) - 0.485).abs() < 1e-6, "{}", term(0.0));
        assert!((term(2.0) - 0.4675).abs() < 1e-6, "{}", term(2.0));
        assert_eq!(ggx_value_l1(&maps, &maps, 2.0).double_value(&[]), 0.0);
    }

    /// The lobe term's pairs: with lobe lights only, a near-mirror pixel's
    /// light is its view mirrored about the normal; with none, the lights
    /// are cosine-distributed (mean z 2/3, independent of the view); with
    /// camera views, every view is within the camera's cone.
    #[test]
    fn lobe_pairs_mirror_mix_and_take_the_cameras_views() {
        use rand::SeedableRng;
        let m = crate::svbrdf::Svbrdf::uniform(16, 16, [0.2; 3], [0.5; 3], 0.05);
        let maps = m.stacked().to_tensor().unsqueeze(0); // [1, 10, 16, 16]
        let rng = || rand_pcg::Pcg64::seed_from_u64(5);
        let n = 4000;
        let mirror = lobe_pairs(&maps, &LobeSampling::lobes(n), &mut rng());
        assert_eq!(mirror.maps.size(), [n as i64, 10]);
        let xy = |t: &Tensor| t.narrow(1, 0, 2);
        let used = mirror.used.to_kind(Kind::Float);
        let off = ((xy(&mirror.wi) + xy(&mirror.wo)).abs() * &used).max().double_value(&[]);
        assert!(off < 0.05, "alpha 0.0025: the light mirrors the view, off by {off}");
        let z = |t: &Tensor| t.narrow(1, 2, 1).mean(Kind::Float).double_value(&[]);
        let random = lobe_pairs(&maps, &LobeSampling { lobe_share: 0.0, ..LobeSampling::lobes(n) }, &mut rng());
        assert!(random.used.all().int64_value(&[]) == 1);
        assert!((z(&random.wi) - 2.0 / 3.0).abs() < 0.02, "cosine lights: mean z {}", z(&random.wi));
        // The same pixels and views either way: only the lights change.
        assert!(random.index.equal(&mirror.index) && random.wo.equal(&mirror.wo));
        let half = lobe_pairs(&maps, &LobeSampling { lobe_share: 0.5, ..LobeSampling::lobes(n) }, &mut rng());
        let mirrored = ((xy(&half.wi) + xy(&half.wo)).abs().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).lt(0.05).to_kind(Kind::Float) * half.used.squeeze_dim(1).to_kind(Kind::Float)).mean(Kind::Float).double_value(&[]);
        assert!((0.4..0.55).contains(&mirrored), "about half the pairs in the lobe: {mirrored}");
        let camera = lobe_pairs(&maps, &LobeSampling { camera_share: 1.0, ..LobeSampling::lobes(n) }, &mut rng());
        let min_z = camera.wo.narrow(1, 2, 1).min().double_value(&[]);
        assert!(min_z >= CAMERA_VIEW_DEG.to_radians().cos() - 1e-6 && min_z < 0.975, "views within 14 degrees: min z {min_z}");
        assert!(z(&mirror.wo) < 0.7, "hemisphere views: mean z {}", z(&mirror.wo));
        // A rough pixel's lobe lights spread wide; narrowed, many sit at the mirror direction.
        let rough = crate::svbrdf::Svbrdf::uniform(16, 16, [0.2; 3], [0.5; 3], 1.0).stacked().to_tensor().unsqueeze(0);
        let near_mirror = |p: &LobePairs| (xy(&p.wi) + xy(&p.wo)).abs().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).lt(0.1).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]);
        let wide = near_mirror(&lobe_pairs(&rough, &LobeSampling::lobes(n), &mut rng()));
        let narrowed = near_mirror(&lobe_pairs(&rough, &LobeSampling { narrow_share: 1.0, ..LobeSampling::lobes(n) }, &mut rng()));
        assert!(wide < 0.08 && narrowed > 3.0 * wide, "pairs within 0.1 of the mirror: {wide} at the pixel's spread, {narrowed} narrowed");
    }

    /// Hand-derived: grey against red (0.6, 0.1, 0.1) is |1/3 - 0.75| +
    /// 2 |1/3 - 0.125| = 0.8333; a render twice as bright as the truth
    /// has the same chromaticity (0); two renders average.
    #[test]
    fn chroma_l1_is_the_chromaticity_distance_of_the_mean_colours() {
        let log = |rgb: [f64; 3], scale: f64| Tensor::from_slice(&rgb.map(|v| ((v * scale) as f32).ln_1p())).view([1, 1, 3, 1, 1]).expand([1, 1, 3, 4, 4], false).contiguous();
        let (grey, red) = (log([0.2, 0.2, 0.2], 1.0), log([0.6, 0.1, 0.1], 1.0));
        assert!((chroma_l1(&grey, &red).double_value(&[]) - 0.8333).abs() < 1e-3);
        assert!(chroma_l1(&log([0.6, 0.1, 0.1], 2.0), &red).double_value(&[]).abs() < 1e-5);
        let both = |a: &Tensor, b: &Tensor| Tensor::cat(&[a, b], 1);
        let mean = chroma_l1(&both(&grey, &red), &both(&red, &red)).double_value(&[]);
        assert!((mean - 0.8333 / 2.0).abs() < 1e-3, "{mean}");
        // Only the prediction takes a gradient, and it is finite at black.
        let pred = Tensor::zeros([1, 1, 3, 4, 4], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        chroma_l1(&pred, &red).backward();
        assert!(pred.grad().isfinite().all().int64_value(&[]) == 1);
    }

    /// A map and the same map seen from a window (dy, dx) further on agree
    /// on their overlap: 0 for the right offset, not for the wrong sign;
    /// two constant maps a and b give |a - b| / |a|; a window that misses
    /// the other photo adds nothing; the gradient reaches both maps.
    #[test]
    fn shift_consistency_compares_the_overlap_only() {
        let (h, w) = (6i64, 7i64);
        let plane = Tensor::arange(2 * 9 * 10, (Kind::Float, Device::Cpu)).view([2, 9, 10]) * 0.1; // [C, rows, cols] of a material
        let window = |y: i64, x: i64| plane.narrow(1, y, h).narrow(2, x, w).unsqueeze(0);
        let first = Tensor::cat(&[window(1, 2), window(3, 0)], 0);
        let second = Tensor::cat(&[window(3, 1), window(0, 3)], 0); // offsets (2, -1) and (-3, 3)
        let right = shift_consistency(&first, &second, &[(2, -1), (-3, 3)], false).double_value(&[]);
        assert!(right.abs() < 1e-7, "{right}");
        assert!(shift_consistency(&first, &second, &[(-2, 1), (3, -3)], false).double_value(&[]) > 0.1);
        let constant = |v: f64| Tensor::full([1, 2, h, w], v, (Kind::Float, Device::Cpu));
        let value = shift_consistency(&constant(2.0), &constant(1.5), &[(1, 1)], false).double_value(&[]);
        assert!((value - 0.25).abs() < 1e-6, "{value}");
        // The second material's windows do not overlap: only the first counts.
        let two = |v: f64| Tensor::cat(&[constant(2.0), constant(v)], 0);
        let value = shift_consistency(&two(9.0), &two(-9.0), &[(1, 1), (h, 0)], false).double_value(&[]);
        assert!((value - 0.0).abs() < 1e-6, "{value}");
        let (a, b) = (constant(2.0).set_requires_grad(true), constant(1.5).set_requires_grad(true));
        shift_consistency(&a, &b, &[(0, 2)], false).backward();
        let (ga, gb) = (a.grad(), b.grad());
        // d/da of mean |a - b| / 2 over the overlap's 2 * 6 * 5 values: 1 / (60 * 2) each; none outside it.
        assert!((ga.narrow(3, 2, 5).mean(Kind::Float).double_value(&[]) - 1.0 / 120.0).abs() < 1e-7);
        assert_eq!(ga.narrow(3, 0, 2).abs().sum(Kind::Float).double_value(&[]), 0.0);
        assert!((gb.narrow(3, 0, 5).mean(Kind::Float).double_value(&[]) + 1.0 / 120.0).abs() < 1e-7);
    }

    /// Scale-free: constant maps 2 and 1.5 give 0.5 / mean(2, 1.5); any
    /// two maps times k give the same value, and (Euler, degree 0) the
    /// gradient has no component along the maps themselves, where the
    /// default's (a constant scale: degree 1) has exactly the value.
    #[test]
    fn scale_free_shift_consistency_ignores_the_codes_scale() {
        let constant = |v: f64| Tensor::full([1, 2, 6, 7], v, (Kind::Float, Device::Cpu));
        let value = shift_consistency(&constant(2.0), &constant(1.5), &[(1, 1)], true).double_value(&[]);
        assert!((value - 0.5 / 1.75).abs() < 1e-6, "{value}");
        tch::manual_seed(3);
        let (a, b) = (Tensor::randn([2, 3, 6, 7], (Kind::Float, Device::Cpu)), Tensor::randn([2, 3, 6, 7], (Kind::Float, Device::Cpu)));
        let offsets = [(1, -2), (0, 3)];
        let base = shift_consistency(&a, &b, &offsets, true).double_value(&[]);
        let scaled = shift_consistency(&(&a * 7.5), &(&b * 7.5), &offsets, true).double_value(&[]);
        assert!((base - scaled).abs() < 1e-6 * base, "{base} {scaled}");
        for (scale_free, along) in [(true, 0.0), (false, shift_consistency(&a, &b, &offsets, false).double_value(&[]))] {
            let (ga, gb) = (a.copy().set_requires_grad(true), b.copy().set_requires_grad(true));
            shift_consistency(&ga, &gb, &offsets, scale_free).backward();
            let radial = (ga.grad() * &a).sum(Kind::Float).double_value(&[]) + (gb.grad() * &b).sum(Kind::Float).double_value(&[]);
            assert!((radial - along).abs() < 1e-5, "scale-free {scale_free}: {radial} against {along}");
        }
    }

    #[test]
    fn mask_has_the_requested_fraction_and_prefers_low_norm() {
        let rng = &mut rand_pcg::Pcg64::seed_from_u64(0);
        let (n, h, w) = (2i64, 16i64, 16i64);
        // Left half: norm 1; right half: norm 100.
        let neural = Tensor::ones([n, 4, h, w], (Kind::Float, Device::Cpu)) * 0.5;
        let _ = neural.narrow(3, 8, 8).fill_(50.0);
        let targets = Tensor::ones([n, 3, 3, h, w], (Kind::Float, Device::Cpu));
        let mask = pixel_mask(&neural, &targets, 0.6, PixelSampling::InverseNorm, rng);
        assert_eq!(mask.size(), [n, 1, 1, h, w]);
        let total = mask.sum(Kind::Float).double_value(&[]);
        assert_eq!(total, (2.0 * (0.6f64 * 256.0).round()));
        // 154 of 256 pixels: all 128 low-norm ones are taken before high-norm ones
        // would be likely (weights 1 vs 0.01), so the left half is (almost) full.
        let left = mask.narrow(4, 0, 8).sum(Kind::Float).double_value(&[]);
        assert!(left >= 2.0 * 125.0, "{left}");
        let all = pixel_mask(&neural, &targets, 0.6, PixelSampling::All, rng);
        assert_eq!(all.sum(Kind::Float).double_value(&[]), (n * h * w) as f64);
        let tn = pixel_mask(&neural, &targets, 0.5, PixelSampling::TargetNorm, rng);
        assert_eq!(tn.size(), [n, 3, 1, h, w]);
        assert_eq!(tn.sum(Kind::Float).double_value(&[]), (n * 3 * 128) as f64);
    }

    #[test]
    fn gumbel_top_k_follows_the_probabilities() {
        // One row, 4 pixels with weights 8:4:2:1 (neural norms 1/8..1), pick 1:
        // P(pixel i) = w_i / 15.
        let rng = &mut rand_pcg::Pcg64::seed_from_u64(1);
        let norms = Tensor::from_slice(&[0.125f32, 0.25, 0.5, 1.0]).view([1, 1, 2, 2]);
        let targets = Tensor::ones([1, 1, 3, 2, 2], (Kind::Float, Device::Cpu));
        let trials = 6000;
        let mut counts = [0f64; 4];
        for _ in 0..trials {
            let m = pixel_mask(&norms, &targets, 0.25, PixelSampling::InverseNorm, rng);
            let v: Vec<f32> = Vec::try_from(m.flatten(0, -1)).unwrap();
            for i in 0..4 {
                counts[i] += v[i] as f64;
            }
        }
        for (i, w) in [8.0, 4.0, 2.0, 1.0].iter().enumerate() {
            let p = counts[i] / trials as f64;
            assert!((p - w / 15.0).abs() < 0.02, "pixel {i}: {p} vs {}", w / 15.0);
        }
    }

    #[test]
    fn masked_l1_counts_only_masked_pixels() {
        let pred = Tensor::zeros([1, 1, 3, 2, 2], (Kind::Float, Device::Cpu));
        let target = Tensor::from_slice(&[1.0f32, 2.0, 3.0, 4.0]).view([1, 1, 1, 2, 2]).expand([1, 1, 3, 2, 2], false);
        let mask = Tensor::from_slice(&[1.0f32, 0.0, 0.0, 1.0]).view([1, 1, 1, 2, 2]);
        let v = masked_l1(&pred, &target, &mask).double_value(&[]);
        assert!((v - 2.5).abs() < 1e-6, "{v}");
    }
}
