//! Analytic export of a neural material (`flashmat fit`): per pixel, the
//! GGX SVBRDF of REFERENCE section 2 (diffuse kd, specular ks, roughness r,
//! normal n) closest to the neural BRDF, then PBR texture sets for other
//! tools ([`export`]).
//!
//! ```text
//! .nmat ─► S shared direction pairs (wi, wo) ─► neural targets ln(1+R)  [S, 3, H, W]
//!              │                                      │
//!              └──► GGX render of the maps ◄── Adam ◄─┘  loss = data + smooth
//!                    (svbrdf::render)                    data   = mean charbonnier(ln(1+R_ggx) - target)
//!                                                        smooth = w * mean(e * |grad maps|)
//! ```
//!
//! The direction pairs are the same for every pixel (a quadrature set over
//! the hemisphere: co-located pairs as in the photo, mirror pairs around the
//! specular peak, independent pairs for the off-specular and diffuse part),
//! so ND_enc runs once per pair rather than once per pixel and pair, and the
//! GGX renderer broadcasts the directions over the pixels. Every pixel is
//! still fitted to its own BRDF: the directions are in the material's frame,
//! which the neural renderer and the GGX renderer share.
//!
//! Each pixel is parameterised as 9 unconstrained numbers (sigmoids for the
//! albedos and roughness, normal = normalize(sx, sy, 1)), initialised from a
//! per-pixel grid search over (roughness, specular) with kd from a low
//! quantile of R / cos(wi), then optimised by Adam with a cosine-decayed step.
//! The smoothness term is edge-aware: e = exp(-|grad mean target| / 0.05) is
//! near 1 where the material looks smooth and near 0 across its edges.

pub mod codes;
pub mod coverage;
pub mod export;
pub mod photos;
pub mod relief;

use crate::infer::nmat::NeuralMaterial;
use crate::optim::Adam;
use anyhow::{ensure, Result};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

/// Largest accepted step count (beyond this the option is a typo).
pub const MAX_FIT_STEPS: usize = 20_000;
/// Largest number of direction pairs (each costs one neural render of the material).
pub const MAX_FIT_SAMPLES: usize = 1024;
/// Lowest fitted roughness (the procedural data's floor).
pub const MIN_FIT_ROUGHNESS: f64 = crate::data::procedural::MIN_ROUGHNESS as f64;
/// Lowest elevation of a sampled direction: z = cos(80 degrees). Grazing
/// directions are where neural BRDFs are least trained and least seen.
pub const MIN_DIRECTION_Z: f64 = 0.17;
/// Charbonnier width of the data term in ln(1 + R): L1 beyond it, quadratic within.
pub const CHARBONNIER_EPS: f64 = 0.01;
/// Gradient of the mean target (ln(1 + R)) at which the smoothness weight falls to 1/e.
pub const EDGE_SCALE: f64 = 0.05;
/// Parameters per pixel: kd (3), ks (3), roughness (1), normal slopes (2).
pub const RAW_CHANNELS: i64 = 9;
/// Direction pairs per neural-renderer call in [`neural_targets`] (bounds memory).
const TARGET_CHUNK: i64 = 4;

/// Settings of one fit (recorded in fit.json).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitConfig {
    /// Adam steps.
    pub steps: usize,
    /// Light/view direction pairs shared by all pixels.
    pub samples: usize,
    /// Adam step in the unconstrained parameters (logits, normal slopes), decayed to a tenth (cosine).
    pub learning_rate: f64,
    /// Weight of the edge-aware smoothness of the maps.
    pub smooth_weight: f64,
    /// Seed of the direction pairs.
    pub seed: u64,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self { steps: 150, samples: 32, learning_rate: 0.05, smooth_weight: 0.01, seed: 1 }
    }
}

impl FitConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!(self.steps <= MAX_FIT_STEPS, "--steps must be at most {MAX_FIT_STEPS}, got {}", self.steps);
        ensure!((8..=MAX_FIT_SAMPLES).contains(&self.samples), "--samples must be between 8 and {MAX_FIT_SAMPLES}, got {}", self.samples);
        ensure!(self.learning_rate.is_finite() && self.learning_rate > 0.0, "the fit's learning rate must be a finite number > 0, got {}", self.learning_rate);
        ensure!(self.smooth_weight.is_finite() && self.smooth_weight >= 0.0, "the smoothness weight must be a finite number >= 0, got {}", self.smooth_weight);
        Ok(())
    }
}

/// What a fit produced.
#[derive(Debug)]
pub struct FitResult {
    /// The fitted GGX maps `[10, H, W]` (kd, ks, roughness, unit normal; linear), on the CPU.
    pub maps: Tensor,
    /// Per-pixel fit error `[H, W]`: mean over the direction pairs and RGB
    /// of |ln(1 + R_ggx) - ln(1 + R_neural)|, on the CPU.
    pub error: Tensor,
    /// The direction pairs fitted, `[S, 3]` each, on the CPU.
    pub wi: Tensor,
    pub wo: Tensor,
    pub report: FitReport,
}

/// The numbers of a fit (fit.json).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    pub config: FitConfig,
    /// Mean of the error map after the grid initialisation and after the fit.
    pub mean_error_init: f64,
    pub mean_error: f64,
    /// 95th percentile of the per-pixel error.
    pub p95_error: f64,
    /// Seconds spent on the neural targets and on the fit itself.
    pub seconds_targets: f64,
    pub seconds_fit: f64,
}

impl FitReport {
    /// One line for the terminal.
    pub fn summary(&self) -> String {
        format!(
            "fitted GGX in {} steps over {} direction pairs ({:.1} s targets + {:.1} s fit): mean error |ln(1+R) diff| {:.4} (grid init {:.4}, 95th percentile {:.4})",
            self.config.steps, self.config.samples, self.seconds_targets, self.seconds_fit, self.mean_error, self.mean_error_init, self.p95_error
        )
    }
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    [v[0] / n, v[1] / n, v[2] / n]
}

/// Direction at `theta` from +z and azimuth `phi`.
fn polar(theta: f64, phi: f64) -> [f64; 3] {
    [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()]
}

/// The shared direction pairs: a quarter co-located (wi = wo within 35
/// degrees of the normal, as the photo and the Identity case), three
/// eighths mirror pairs whose half vector tilts up to 30 degrees from +z
/// (the specular peak of tilted normals too), the rest independent
/// uniform directions; every direction at least 10 degrees above the
/// plane ([`MIN_DIRECTION_Z`]). Returns (wi, wo), each `[S, 3]` f32 on `device`.
pub fn sample_directions(count: usize, seed: u64, device: Device) -> (Tensor, Tensor) {
    let mut rng = Pcg64::seed_from_u64(seed ^ 0x6669_745f_6767_7821);
    let max_theta = MIN_DIRECTION_Z.acos();
    let coloc = count / 4;
    let mirror = count * 3 / 8;
    let mut wi = Vec::with_capacity(count * 3);
    let mut wo = Vec::with_capacity(count * 3);
    for i in 0..count {
        let (l, v) = if i < coloc {
            // Stratified in theta so the normal itself is always sampled.
            let t = (i as f64 + rng.random::<f64>()) / coloc as f64;
            let d = polar(t * 35f64.to_radians(), rng.random_range(0.0..std::f64::consts::TAU));
            (d, d)
        } else if i < coloc + mirror {
            loop {
                let j = (i - coloc) as f64;
                let v = polar(((j + rng.random::<f64>()) / mirror as f64) * 70f64.to_radians(), rng.random_range(0.0..std::f64::consts::TAU));
                let tilt = (rng.random::<f64>().powf(1.5) * 30.0).to_radians();
                let h = polar(tilt, rng.random_range(0.0..std::f64::consts::TAU));
                let vh = v[0] * h[0] + v[1] * h[1] + v[2] * h[2];
                let l = unit([2.0 * vh * h[0] - v[0], 2.0 * vh * h[1] - v[1], 2.0 * vh * h[2] - v[2]]);
                if l[2] >= MIN_DIRECTION_Z && v[2] >= MIN_DIRECTION_Z {
                    break (l, v);
                }
            }
        } else {
            // Uniform on the cap z >= MIN_DIRECTION_Z (uniform in z).
            let mut draw = || polar(rng.random_range(MIN_DIRECTION_Z..1.0f64).acos().min(max_theta), rng.random_range(0.0..std::f64::consts::TAU));
            (draw(), draw())
        };
        wi.extend(l);
        wo.extend(v);
    }
    let t = |v: Vec<f64>| Tensor::from_slice(&v).view([count as i64, 3]).to_kind(Kind::Float).to_device(device);
    (t(wi), t(wo))
}

/// ln(1 + R) of the neural material for direction pairs shared by all
/// pixels, clamped and scaled by the material's exposure gain as
/// [`NeuralMaterial::render`] does. ND_enc runs once per pair; M_render per pixel.
/// wi, wo: `[S, 3]` unit vectors -> `[S, 3, H, W]` on the material's device.
/// `on_pair(done)` is called after each chunk of pairs.
pub fn neural_targets(material: &NeuralMaterial, wi: &Tensor, wo: &Tensor, mut on_pair: impl FnMut(usize)) -> Result<Tensor> {
    let s = wi.size();
    ensure!(s.len() == 2 && s[1] == 3 && wo.size() == s, "wi and wo must both be [S, 3], got {s:?} and {:?}", wo.size());
    let device = material.device();
    let (h, w) = material.size();
    let (n, hw) = (s[0], (h * w) as i64);
    let map = &material.neural_map;
    let c = map.size()[0];
    let params = map.permute([1, 2, 0]).reshape([1, hw, c]); // [1, HW, C]
    let parts = tch::no_grad(|| -> Result<Vec<Tensor>> {
        let code = material.renderer.nd_enc.forward(&wi.to_device(device), &wo.to_device(device)); // [S, E]
        let mut parts = Vec::new();
        let mut start = 0;
        while start < n {
            let k = TARGET_CHUNK.min(n - start);
            let chunk = code.narrow(0, start, k).unsqueeze(1); // [k, 1, E]
            let out = material.renderer.m_render.forward(&params, &chunk); // [k, HW, 3]
            ensure!(out.isnan().any().int64_value(&[]) == 0, "M_render produced NaN values for this material (weights out of range?)");
            parts.push(material.with_gain_log(&out).view([k, h as i64, w as i64, 3]).permute([0, 3, 1, 2]).contiguous());
            start += k;
            on_pair(start as usize);
        }
        Ok(parts)
    })?;
    Ok(Tensor::cat(&parts, 0))
}

/// ln(1 + R) of GGX maps for direction pairs shared by all pixels: the
/// equations of [`crate::svbrdf::render::render_directions`] (REFERENCE
/// section 2) arranged for shared directions, which the fit evaluates
/// hundreds of times: the half vector and Fresnel weight are computed once
/// per pair, the three cosines as one matrix product each, and
/// R = kd NoL + S (ks (1 - Fw) + Fw) with S = D G / (4 NoL NoV) NoL pi
/// (a test checks it against `render_directions`).
/// maps: `[N, 10, H, W]`; wi, wo: `[S, 3]` -> `[N, S, 3, H, W]`.
pub fn ggx_log(maps: &Tensor, wi: &Tensor, wo: &Tensor) -> Tensor {
    const DOT_EPS: f64 = 1e-8;
    let ms = maps.size();
    let (n, h, w) = (ms[0], ms[2], ms[3]);
    let s = wi.size()[0];
    let dir = |t: &Tensor| t.to_kind(maps.kind()).to_device(maps.device());
    let (wi, wo) = (dir(wi), dir(wo));
    let half = crate::geometry::normalize_channels(&(&wi + &wo)); // [S, 3]
    let v_dot_h = (&wo * &half).sum_dim_intlist([1i64].as_slice(), false, maps.kind()).clamp_min(DOT_EPS); // [S]
    let fresnel = ((&v_dot_h * -5.55473 - 6.98316) * &v_dot_h * std::f64::consts::LN_2).exp().view([1, s, 1, 1]);
    let flat = maps.reshape([n, 10, h * w]);
    let normal = flat.narrow(1, 7, 3); // [N, 3, HW]
    let cosines = |d: &Tensor| d.matmul(&normal).clamp_min(DOT_EPS).unsqueeze(2); // [N, S, 1, HW]
    let (n_dot_h, n_dot_v, n_dot_l) = (cosines(&half), cosines(&wo), cosines(&wi));
    let alpha = flat.narrow(1, 6, 1).square().unsqueeze(1); // [N, 1, 1, HW]
    let a2 = alpha.square();
    let denom = (n_dot_h.square() * (&a2 - 1.0) + 1.0).clamp_min(1e-8);
    let d = &a2 / (denom.square() * std::f64::consts::PI);
    let k = (&alpha / 2.0).clamp_min(1e-8);
    let g1 = |x: &Tensor| x / (x * (1.0 - &k) + &k);
    let g = g1(&n_dot_l) * g1(&n_dot_v);
    let spec = d * g / (&n_dot_l * &n_dot_v * 4.0 + 1e-12) * &n_dot_l * std::f64::consts::PI; // [N, S, 1, HW]
    let kd = flat.narrow(1, 0, 3).unsqueeze(1); // [N, 1, 3, HW]
    let ks = flat.narrow(1, 3, 3).unsqueeze(1);
    let radiance = kd * &n_dot_l + &spec * (ks * (1.0 - &fresnel) + &fresnel); // [N, S, 3, HW]
    crate::spaces::to_log(&radiance).view([n, s, 3, h, w])
}

/// Unconstrained per-pixel parameters to GGX maps: kd, ks = sigmoid,
/// roughness = floor + (1 - floor) sigmoid, n = normalize(sx, sy, 1).
/// raw: `[N, 9, H, W]` -> maps `[N, 10, H, W]`.
pub fn decode(raw: &Tensor) -> Tensor {
    let albedo = raw.narrow(1, 0, 6).sigmoid();
    let rough = raw.narrow(1, 6, 1).sigmoid() * (1.0 - MIN_FIT_ROUGHNESS) + MIN_FIT_ROUGHNESS;
    let slopes = raw.narrow(1, 7, 2);
    let n = Tensor::cat(&[slopes.shallow_clone(), slopes.narrow(1, 0, 1).ones_like()], 1);
    let norm = n.square().sum_dim_intlist([1i64].as_slice(), true, n.kind()).sqrt();
    Tensor::cat(&[albedo, rough, n / norm], 1)
}

/// Inverse of [`decode`] (values clamped into its range first).
/// maps: `[N, 10, H, W]` -> raw `[N, 9, H, W]`.
pub fn encode(maps: &Tensor) -> Tensor {
    let albedo = maps.narrow(1, 0, 6).clamp(1e-4, 1.0 - 1e-4).logit(None::<f64>);
    let r = ((maps.narrow(1, 6, 1) - MIN_FIT_ROUGHNESS) / (1.0 - MIN_FIT_ROUGHNESS)).clamp(1e-4, 1.0 - 1e-4).logit(None::<f64>);
    let nz = maps.narrow(1, 9, 1).clamp_min(0.05);
    let slopes = maps.narrow(1, 7, 2) / nz;
    Tensor::cat(&[albedo, r, slopes], 1)
}

/// Per-pixel data term: Charbonnier of the log difference, mean over the
/// pairs and RGB. pred, target: `[S, 3, H, W]` -> `[H, W]`.
fn data_map(pred: &Tensor, target: &Tensor) -> Tensor {
    ((pred - target).square() + CHARBONNIER_EPS * CHARBONNIER_EPS).sqrt().mean_dim([0i64, 1].as_slice(), false, Kind::Float) - CHARBONNIER_EPS
}

/// Mean |log difference| per pixel. pred, target: `[S, 3, H, W]` -> `[H, W]`.
fn error_map(pred: &Tensor, target: &Tensor) -> Tensor {
    (pred - target).abs().mean_dim([0i64, 1].as_slice(), false, Kind::Float)
}

/// Edge-aware smoothness weights of the mean target `[3, H, W]`:
/// (x `[1, H, W-1]`, y `[1, H-1, W]`).
pub fn edge_weights(mean_target: &Tensor) -> (Tensor, Tensor) {
    let (gx, gy) = differences(mean_target);
    let weight = |g: Tensor| (-g.abs().mean_dim(0, true, Kind::Float) / EDGE_SCALE).exp();
    (weight(gx), weight(gy))
}

/// Forward differences along x and y: t `[C, H, W]` -> (`[C, H, W-1]`, `[C, H-1, W]`).
fn differences(t: &Tensor) -> (Tensor, Tensor) {
    let (h, w) = (t.size()[1], t.size()[2]);
    (t.narrow(2, 1, w - 1) - t.narrow(2, 0, w - 1), t.narrow(1, 1, h - 1) - t.narrow(1, 0, h - 1))
}

/// Grid initialisation: kd from the 30% quantile over the pairs of
/// R / cos(wi) (low enough to miss highlights), flat normals, and per pixel
/// the (roughness, specular) of a small grid with the lowest data term.
/// targets: `[S, 3, H, W]` log; wi, wo: `[S, 3]` -> maps `[1, 10, H, W]`.
fn initial_maps(targets: &Tensor, wi: &Tensor, wo: &Tensor) -> Tensor {
    tch::no_grad(|| {
        let s = targets.size();
        let (n, h, w) = (s[0], s[2], s[3]);
        let opts = (Kind::Float, targets.device());
        let cos = wi.to_device(targets.device()).narrow(1, 2, 1).view([n, 1, 1, 1]);
        let ratio = crate::spaces::from_log(targets) / cos; // [S, 3, H, W]
        let q = ((n as f64 - 1.0) * 0.3).round() as i64 + 1;
        let kd = ratio.kthvalue(q, 0, false).0.clamp(0.005, 0.95).unsqueeze(0); // [1, 3, H, W]
        let normal = Tensor::cat(&[Tensor::zeros([1, 2, h, w], opts), Tensor::ones([1, 1, h, w], opts)], 1);
        let mut best_loss = Tensor::full([h, w], f64::INFINITY, opts);
        let mut best = Tensor::zeros([1, 10, h, w], opts);
        for &r in &[0.15, 0.3, 0.5, 0.75] {
            for &ks in &[0.02, 0.06, 0.2] {
                let maps = Tensor::cat(&[kd.shallow_clone(), Tensor::full([1, 3, h, w], ks, opts), Tensor::full([1, 1, h, w], r, opts), normal.shallow_clone()], 1);
                let loss = data_map(&ggx_log(&maps, wi, wo).get(0), targets);
                let better = loss.lt_tensor(&best_loss);
                best_loss = loss.minimum(&best_loss);
                best = maps.where_self(&better.view([1, 1, h, w]), &best);
            }
        }
        best
    })
}

/// The settings of [`fit_core`]'s Adam loop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CoreSettings {
    /// Adam steps.
    pub steps: usize,
    /// Step in the unconstrained parameters, cosine-decayed to a tenth.
    pub learning_rate: f64,
    /// Weight of the edge-aware smoothness of the maps.
    pub smooth_weight: f64,
}

/// Specular lobes shared by the regions of a material: each pixel's
/// specular colour and roughness (raw channels 3..7) are its regions' lobes,
/// mixed by its soft memberships, plus a departure of its own whose square
/// costs `weight`. One photo sees a pixel's lobe at one half-angle, where a
/// sharper lobe with a brighter ks draws the same value; the pixels of a
/// region see it at many half-angles, which fixes its shape, and the
/// pixels no highlight touched take their region's lobe instead of staying
/// at the start's.
#[derive(Debug)]
pub struct SharedLobes {
    /// Soft memberships `[1, C, H, W]`, summing to 1 over the C regions.
    pub memberships: Tensor,
    /// Weight of the mean squared departure (raw units, 4 channels summed).
    pub weight: f64,
}

/// Raw channels of the lobe ([`SharedLobes`]): ks (3) and roughness.
const LOBE_CHANNELS: (i64, i64) = (3, 4);

/// Each region's mean of per-pixel values, weighted by the pixels'
/// memberships: memberships `[1, C, H, W]`, values `[1, K, H, W]` -> `[C, K]`.
fn region_means(memberships: &Tensor, values: &Tensor) -> Tensor {
    let weights = memberships.sum_dim_intlist([0i64, 2, 3].as_slice(), false, Kind::Float).clamp_min(1e-6); // [C]
    Tensor::einsum("bchw,bkhw->ck", &[memberships, values], None::<i64>) / weights.unsqueeze(1)
}

/// Each pixel's mix of per-region values by its memberships:
/// memberships `[1, C, H, W]`, per_region `[C, K]` -> `[1, K, H, W]`.
fn region_mix(memberships: &Tensor, per_region: &Tensor) -> Tensor {
    Tensor::einsum("bchw,ck->bkhw", &[memberships, per_region], None::<i64>)
}

/// Raw parameters `[N, 9, H, W]` with their lobe channels ([`LOBE_CHANNELS`]) replaced by `lobe` `[N, 4, H, W]`.
fn with_raw_lobe(raw: &Tensor, lobe: &Tensor) -> Tensor {
    let (first, count) = LOBE_CHANNELS;
    Tensor::cat(&[raw.narrow(1, 0, first), lobe.shallow_clone(), raw.narrow(1, first + count, RAW_CHANNELS - first - count)], 1)
}

/// The one fitting core of `flashmat fit` and of the fit to photos
/// ([`photos`]): Adam on the unconstrained parameters ([`encode`] /
/// [`decode`]) of GGX maps, minimising `data(maps)` plus the edge-aware
/// smoothness `w * mean(e * |grad maps|)`, with a cosine-decayed step.
/// What the maps are compared with lives in `data` (any further prior
/// too), so both fits share the loop, its parameterisation and its checks.
/// With `shared`, the lobe channels are parameterised as [`SharedLobes`]
/// says (started at the regions' mean lobes plus each pixel's departure,
/// so the start is unchanged). `extra`: further parameters `data` uses
/// (leaf tensors requiring grad, updated in place by the same Adam).
/// init: `[1, 10, H, W]`; edges: (x `[1, H, W-1]`, y `[1, H-1, W]`) from
/// [`edge_weights`]; data: maps `[1, 10, H, W]` -> scalar loss.
/// Returns the fitted maps `[1, 10, H, W]` (no gradient). A non-finite
/// loss is an error naming the step.
pub fn fit_core(
    init: &Tensor,
    settings: &CoreSettings,
    edges: &(Tensor, Tensor),
    shared: Option<&SharedLobes>,
    extra: &[(&str, &Tensor)],
    mut data: impl FnMut(&Tensor) -> Tensor,
    mut on_step: impl FnMut(usize),
) -> Result<Tensor> {
    let (edge_x, edge_y) = edges;
    let (first, count) = LOBE_CHANNELS;
    let start = encode(init).detach();
    let mut params: HashMap<String, Tensor> = extra.iter().map(|(name, t)| (format!("extra.{name}"), t.shallow_clone())).collect();
    // The shared lobes [C, 4] and the mixing of them into [1, 4, H, W].
    let lobes = shared.map(|s| {
        let m = s.memberships.to_device(init.device()).to_kind(Kind::Float);
        let means = region_means(&m, &start.narrow(1, first, count)).detach().set_requires_grad(true);
        params.insert("lobes".to_string(), means.shallow_clone());
        (m, means, s.weight)
    });
    let raw = match &lobes {
        // Channels 3..7 hold the departure from the mixed lobe.
        Some((m, means, _)) => tch::no_grad(|| with_raw_lobe(&start, &(start.narrow(1, first, count) - region_mix(m, means)))),
        None => start.shallow_clone(),
    }
    .set_requires_grad(true);
    params.insert("raw".to_string(), raw.shallow_clone());
    let full = |raw: &Tensor| match &lobes {
        Some((m, means, _)) => with_raw_lobe(raw, &(raw.narrow(1, first, count) + region_mix(m, means))),
        None => raw.shallow_clone(),
    };
    let mut adam = Adam::new(params);
    for step in 0..settings.steps {
        adam.zero_grad();
        let maps = decode(&full(&raw));
        let mut loss = data(&maps);
        if settings.smooth_weight > 0.0 {
            let (dx, dy) = differences(&maps.get(0));
            loss = loss + ((dx.abs() * edge_x).mean(Kind::Float) + (dy.abs() * edge_y).mean(Kind::Float)) * settings.smooth_weight;
        }
        if let Some((_, _, weight)) = &lobes {
            loss = loss + raw.narrow(1, first, count).square().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).mean(Kind::Float) * *weight;
        }
        let value = loss.double_value(&[]);
        ensure!(value.is_finite(), "the fit's loss became {value} at step {}", step + 1);
        loss.backward();
        // Cosine decay from the full step to a tenth of it.
        let progress = step as f64 / settings.steps.max(1) as f64;
        let lr = settings.learning_rate * (0.1 + 0.45 * (1.0 + (std::f64::consts::PI * progress).cos()));
        adam.step(lr, None);
        on_step(step);
    }
    Ok(tch::no_grad(|| decode(&full(&raw.detach()))))
}

/// Fits GGX maps to log radiance targets seen under shared direction pairs.
/// targets: `[S, 3, H, W]` ln(1 + R); wi, wo: `[S, 3]` (the pairs the
/// targets were rendered for). `on_step(i)` is called after each step.
/// A non-finite loss is an error (the targets hold NaN/Inf).
pub fn fit_targets(targets: &Tensor, wi: &Tensor, wo: &Tensor, cfg: &FitConfig, on_step: impl FnMut(usize)) -> Result<FitResult> {
    cfg.validate()?;
    let s = targets.size();
    ensure!(s.len() == 4 && s[1] == 3, "fit targets must be [S, 3, H, W], got {s:?}");
    ensure!(wi.size() == [s[0], 3] && wo.size() == [s[0], 3], "wi, wo must be [{}, 3], got {:?} and {:?}", s[0], wi.size(), wo.size());
    ensure!(s[2] >= 2 && s[3] >= 2, "the fit needs at least 2x2 pixels, got {}x{}", s[3], s[2]);
    ensure!(crate::image::all_finite(targets), "the fit targets hold NaN/Inf values");
    let t0 = Instant::now();
    let targets = targets.to_kind(Kind::Float);
    let (wi, wo) = (wi.to_kind(Kind::Float).to_device(targets.device()), wo.to_kind(Kind::Float).to_device(targets.device()));
    let init = initial_maps(&targets, &wi, &wo);
    let init_error = tch::no_grad(|| error_map(&ggx_log(&init, &wi, &wo).get(0), &targets).mean(Kind::Double).double_value(&[]));
    let (edge_x, edge_y) = edge_weights(&targets.mean_dim(0, false, Kind::Float));

    let data = |maps: &Tensor| data_map(&ggx_log(maps, &wi, &wo).get(0), &targets).mean(Kind::Float);
    let settings = CoreSettings { steps: cfg.steps, learning_rate: cfg.learning_rate, smooth_weight: cfg.smooth_weight };
    let maps = fit_core(&init, &settings, &(edge_x, edge_y), None, &[], data, on_step)?;
    let error = tch::no_grad(|| error_map(&ggx_log(&maps, &wi, &wo).get(0), &targets));
    ensure!(crate::image::all_finite(&maps) && crate::image::all_finite(&error), "the fitted maps are not finite");
    let flat = error.flatten(0, -1);
    let p95 = flat.quantile_scalar(0.95, None, false, "linear").double_value(&[]);
    let report = FitReport {
        config: cfg.clone(),
        mean_error_init: init_error,
        mean_error: error.mean(Kind::Double).double_value(&[]),
        p95_error: p95,
        seconds_targets: 0.0,
        seconds_fit: t0.elapsed().as_secs_f64(),
    };
    Ok(FitResult { maps: maps.get(0).to_device(Device::Cpu), error: error.to_device(Device::Cpu), wi: wi.to_device(Device::Cpu), wo: wo.to_device(Device::Cpu), report })
}

/// Fits GGX maps to a neural material: its renders for `cfg.samples`
/// shared direction pairs, then [`fit_targets`]. `on_progress(done, total)`
/// counts the direction pairs rendered, then the steps.
pub fn fit_material(material: &NeuralMaterial, cfg: &FitConfig, mut on_progress: impl FnMut(usize, usize)) -> Result<FitResult> {
    cfg.validate()?;
    let t0 = Instant::now();
    let (wi, wo) = sample_directions(cfg.samples, cfg.seed, material.device());
    let total = cfg.samples + cfg.steps;
    let targets = neural_targets(material, &wi, &wo, |done| on_progress(done, total))?;
    let seconds_targets = t0.elapsed().as_secs_f64();
    let mut result = fit_targets(&targets, &wi, &wo, cfg, |step| on_progress(cfg.samples + step + 1, total))?;
    result.report.seconds_targets = seconds_targets;
    Ok(result)
}

#[cfg(test)]
mod tests;
