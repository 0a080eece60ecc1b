//! A neural material as true as its maps (issue 83): the codes of fitted
//! GGX maps, fitted to what the maps render.
//!
//! The teacher's encoder turns each pixel's GGX values into a code, but it
//! was trained on a distribution of pixels and is only approximately
//! right on any one material, most of all on the corners of GGX space a
//! real capture lands in (a dark metal with a coloured specular), and its
//! renderer's three channels disagree by a few percent on bright grey
//! facets (a colour speckle in the overhead render). Here the encoder's
//! weights and the material's own copy of the renderer (every `.nmat`
//! carries one) are fine-tuned on this material's own pixels, so that the
//! renderer of the codes draws what the GGX maps draw:
//!
//! ```text
//! rows: random pixels of the maps x directions (cosine-random, half the lights in the
//!       pixel's GGX lobe; a share under the photos' configurations, jittered)
//! loss = L1 ln(1 + R_neural) - ln(1 + R_ggx)  +  L1 ln(F + R_neural) - ln(F + R_ggx)
//! maps ─► fine-tuned encoder ─► codes ─► the material's neural map (its renderer fine-tuned too)
//! ```
//!
//! The encoder is shared by all pixels, so every row teaches every pixel of
//! similar values: a few thousand rows a step cover a 256x256 material in
//! a few seconds. [`neural_gap`] says how far the result is from its maps
//! under held-out directions.

use crate::geometry::{LightView, Sampling, MODEL_FOV_DEG};
use crate::infer::nmat::NeuralMaterial;
use crate::lpips::Lpips;
use crate::model::ggx_codes::{forward_rows_with, valid_values, GgxEncoder, GGX_CHANNELS};
use crate::optim::Adam;
use crate::svbrdf::render::render_directions;
use crate::svbrdf::rows::{ggx_log_rows, lobe_lights, log_rows_loss, random_directions};
use anyhow::{ensure, Result};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::time::Instant;
use tch::{Kind, Tensor};

/// How the codes are fitted to their maps.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CodeFitConfig {
    /// Adam steps on the encoder's (and renderer's) weights (0: the
    /// teacher's codes as they are), their rates decayed to 0 along a cosine. Many small steps beat
    /// few large ones for the same rows (reports/capture.md, twelfth and
    /// seventeenth slices: 3,200 x 512 draws a glossy material's overhead
    /// highlight at half the LPIPS of 800 x 2,048, in 1.1-1.5x the time).
    pub steps: usize,
    /// Rows (pixel, light, view) per step.
    pub rows: usize,
    pub learning_rate: f64,
    /// Adam's rate on the material's own copy of the renderer, fitted with
    /// the encoder (0: the teacher's renderer as it is). Every `.nmat`
    /// carries its renderer, so tuning it to one material costs no reader
    /// anything; the rows cover all directions, so it is not tuned to the
    /// photos alone.
    #[serde(default)]
    pub renderer_learning_rate: f64,
    /// Share of the rows whose light lies inside the pixel's GGX lobe.
    pub lobe_share: f64,
    /// Share of the rows under the photos' configurations (their lights
    /// and cameras moved by up to [`PHOTO_JITTER`]), where the material
    /// will most often be looked at.
    pub photo_share: f64,
    /// F of the loss's ln(F + R) term: dark pixels fitted relative to
    /// their radiance (0: ln(1 + R) alone).
    pub dark_floor: f64,
    pub seed: u64,
}

impl Default for CodeFitConfig {
    fn default() -> Self {
        Self { steps: 3200, rows: 512, learning_rate: 3e-4, renderer_learning_rate: 3e-4, lobe_share: 0.2, photo_share: 0.25, dark_floor: 0.01, seed: 1 }
    }
}

impl CodeFitConfig {
    /// No fit: the teacher's codes as they are (what older fit files did).
    pub fn none() -> Self {
        Self { steps: 0, ..Self::default() }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(self.rows >= 16, "the code fit needs at least 16 rows a step, got {}", self.rows);
        crate::limits::STEP_PIXELS.check("the code fit's rows", self.rows as u64)?;
        ensure!(self.learning_rate.is_finite() && self.learning_rate > 0.0, "the code fit's learning rate must be a positive number, got {}", self.learning_rate);
        ensure!(self.renderer_learning_rate.is_finite() && self.renderer_learning_rate >= 0.0, "the code fit's renderer learning rate must be a number >= 0, got {}", self.renderer_learning_rate);
        for (name, v) in [("lobe share", self.lobe_share), ("photo share", self.photo_share)] {
            ensure!((0.0..=1.0).contains(&v), "the code fit's {name} must be from 0 to 1, got {v}");
        }
        ensure!(self.dark_floor >= 0.0 && self.dark_floor.is_finite(), "the code fit's dark floor must be a number >= 0, got {}", self.dark_floor);
        Ok(())
    }
}

/// Standard deviation (flashmat units, per axis) of the moves of the
/// photos' lights and cameras in the code fit's photo rows.
pub const PHOTO_JITTER: f64 = 0.5;

/// Rows of the fixed draw that decides whether a fit is kept.
const CHECK_ROWS: usize = 4096;

/// Jittered copies of each photo configuration the code fit draws from.
const PHOTO_VARIANTS: usize = 3;

/// What [`fit_codes`] did: its loss on a fixed draw of rows (never
/// trained on) before and after.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CodeFit {
    pub steps: usize,
    pub seconds: f64,
    pub loss_before: f64,
    pub loss_after: f64,
    /// Whether the fitted codes replaced the teacher's (they lowered the loss).
    pub kept: bool,
}

/// Fits the codes of `maps` to what the maps render: the encoder's weights
/// (and the material's renderer, at [`CodeFitConfig::renderer_learning_rate`])
/// fine-tuned as the module says, then `material.neural_map` replaced by
/// the fine-tuned encoder's codes of the maps. Codes and renderer are
/// replaced only where the fit lowered its loss on a fixed draw of rows
/// ([`CodeFit::kept`]); otherwise the renderer's weights are put back.
/// maps: `[10, H, W]` (the material's size); photo_configs: the capture's
/// configurations (may be empty). A non-finite loss is an error and leaves the material as it was
/// (its renderer frozen again either way).
pub fn fit_codes(material: &mut NeuralMaterial, maps: &Tensor, encoder: &GgxEncoder, photo_configs: &[LightView], cfg: &CodeFitConfig) -> Result<CodeFit> {
    cfg.validate()?;
    let (h, w) = material.size();
    ensure!(maps.size() == [GGX_CHANNELS, h as i64, w as i64], "the maps must be [{GGX_CHANNELS}, {h}, {w}], got {:?}", maps.size());
    let device = material.device();
    let t0 = Instant::now();
    let values = valid_values(&maps.to_device(device).to_kind(Kind::Float).unsqueeze(0)).get(0).view([GGX_CHANNELS, -1]).transpose(0, 1).contiguous(); // [P, 10]
    let pixels = values.size()[0];
    let photo = photo_positions(material, photo_configs, cfg.seed);
    let weights: Vec<Tensor> = encoder.weights().iter().map(|w| w.detach().copy().set_requires_grad(true)).collect();
    let mut adam = Adam::new(weights.iter().enumerate().map(|(i, w)| (format!("l{i}"), w.shallow_clone())).collect::<HashMap<_, _>>());
    // The material's renderer, trained in place when asked; its weights as
    // they were, to put back if the fit is not kept.
    let tune_renderer = cfg.renderer_learning_rate > 0.0 && cfg.steps > 0;
    let renderer_vars = material.renderer_vs.variables();
    let renderer_before: HashMap<String, Tensor> = if tune_renderer { renderer_vars.iter().map(|(k, v)| (k.clone(), v.detach().copy())).collect() } else { HashMap::new() };
    if tune_renderer {
        material.renderer_vs.unfreeze(); // before Adam, which keeps only what needs a gradient
    }
    let mut renderer_adam = tune_renderer.then(|| Adam::new(renderer_vars.iter().map(|(k, v)| (k.clone(), v.shallow_clone())).collect()));
    let draw = |step: u64, rows: usize| {
        tch::manual_seed((cfg.seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15)) as i64);
        tch::no_grad(|| sample_rows(&values, pixels, rows as i64, photo.as_ref(), cfg))
    };
    let loss_of = |weights: &[Tensor], (v, wi, wo, target): &(Tensor, Tensor, Tensor, Tensor)| -> Result<Tensor> {
        let pred = material.renderer.forward_rows(&forward_rows_with(weights, v), wi, wo)?;
        Ok(log_rows_loss(&pred, target, cfg.dark_floor))
    };
    // A fixed draw, never trained on, scores before and after: as many rows
    // whatever a step's, so that keeping the fit is not decided by a few.
    let check = draw(u64::MAX, CHECK_ROWS.max(cfg.rows));
    let loss_before = tch::no_grad(|| loss_of(&weights, &check))?.double_value(&[]);
    let restore = || {
        tch::no_grad(|| {
            for (name, before) in &renderer_before {
                renderer_vars[name].detach().copy_(before);
            }
        })
    };
    // One thread: a step's few hundred rows are too small to share, and a
    // second thread's hand-offs cost more than it computes (`flashmat bench
    // capture` on 2 cores: 58.8 s with the code fit on one thread, 71.8 s
    // on two; reports/capture.md, seventeenth slice).
    let threads = tch::get_num_threads();
    tch::set_num_threads(1);
    let trained = (|| -> Result<(Vec<Tensor>, f64)> {
        for step in 0..cfg.steps {
            adam.zero_grad();
            if let Some(a) = renderer_adam.as_mut() {
                a.zero_grad();
            }
            let loss = loss_of(&weights, &draw(step as u64, cfg.rows))?;
            let value = loss.double_value(&[]);
            ensure!(value.is_finite(), "the code fit's loss became {value} at step {}", step + 1);
            loss.backward();
            // Cosine decay: the last steps settle rather than jump between draws.
            let decay = 0.5 * (1.0 + (std::f64::consts::PI * step as f64 / cfg.steps as f64).cos());
            adam.step(cfg.learning_rate * decay, None);
            if let Some(a) = renderer_adam.as_mut() {
                a.step(cfg.renderer_learning_rate * decay, None);
            }
        }
        let weights: Vec<Tensor> = weights.iter().map(Tensor::detach).collect();
        let loss_after = tch::no_grad(|| loss_of(&weights, &check))?.double_value(&[]);
        ensure!(loss_after.is_finite(), "the fitted codes render non-finite values");
        Ok((weights, loss_after))
    })();
    tch::set_num_threads(threads);
    material.renderer_vs.freeze();
    let (weights, loss_after) = match trained {
        Ok(t) => t,
        Err(e) => {
            restore();
            return Err(e);
        }
    };
    let kept = cfg.steps > 0 && loss_after < loss_before;
    if !kept {
        restore();
    }
    if kept {
        let codes = tch::no_grad(|| forward_rows_with(&weights, &values)).transpose(0, 1).reshape([-1, h as i64, w as i64]);
        material.neural_map = codes.contiguous();
    }
    Ok(CodeFit { steps: cfg.steps, seconds: t0.elapsed().as_secs_f64(), loss_before, loss_after: if kept { loss_after } else { loss_before }, kept })
}

/// The photos' configurations and [`PHOTO_VARIANTS`] jittered copies of
/// each, as (lights, cameras) `[M, 3]`, and every pixel's surface point
/// `[P, 3]` (the material's extent, as its renders place them): a row's
/// directions are computed from its pixel and configuration, so memory
/// stays a step's rows at any size. None without configurations.
fn photo_positions(material: &NeuralMaterial, configs: &[LightView], seed: u64) -> Option<(Tensor, Tensor, Tensor)> {
    if configs.is_empty() {
        return None;
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let normal = rand_distr::Normal::new(0.0, PHOTO_JITTER).expect("a positive deviation");
    let mut moved = |p: [f64; 3]| [p[0] + rng.sample(normal), p[1] + rng.sample(normal), p[2].max(0.5)];
    let mut all = configs.to_vec();
    for c in configs {
        for _ in 0..PHOTO_VARIANTS {
            let (light, view) = (moved(c.light), moved(c.view));
            all.push(LightView { light, view });
        }
    }
    let device = material.device();
    let (lights, views) = crate::geometry::config_tensors(&all, device);
    let (h, w) = material.size();
    let points = crate::geometry::pixel_positions(h, w, (Kind::Float, device)).view([3, -1]).transpose(0, 1).contiguous(); // [P, 3]
    Some((lights.to_kind(Kind::Float), views.to_kind(Kind::Float), points))
}

/// A step's rows: values `[R, 10]`, wi, wo `[R, 3]`, target ln(1 + R) `[R, 3]`.
/// photo: the capture's (lights `[M, 3]`, cameras `[M, 3]`, pixel points `[P, 3]`).
fn sample_rows(values: &Tensor, pixels: i64, rows: i64, photo: Option<&(Tensor, Tensor, Tensor)>, cfg: &CodeFitConfig) -> (Tensor, Tensor, Tensor, Tensor) {
    let device = values.device();
    let index = Tensor::randint(pixels, [rows], (Kind::Int64, device));
    let v = values.index_select(0, &index);
    let (mut wi, mut wo) = random_directions(rows, device);
    if let Some((lights, views, points)) = photo {
        let which = Tensor::randint(lights.size()[0], [rows], (Kind::Int64, device));
        let at = points.index_select(0, &index); // [R, 3]
        let towards = |positions: &Tensor| crate::svbrdf::rows::normalize_rows(&(positions.index_select(0, &which) - &at));
        let use_photo = Tensor::rand([rows, 1], (Kind::Float, device)).lt(cfg.photo_share).to_kind(Kind::Float);
        wi = &use_photo * towards(lights) + (1.0 - &use_photo) * wi;
        wo = &use_photo * towards(views) + (1.0 - &use_photo) * wo;
    }
    if cfg.lobe_share > 0.0 {
        let (mirrored, above) = lobe_lights(&v, &wo, &Tensor::randn([rows, 2], (Kind::Float, device)));
        let lobe = Tensor::rand([rows, 1], (Kind::Float, device)).lt(cfg.lobe_share).logical_and(&above).to_kind(Kind::Float);
        wi = crate::svbrdf::rows::normalize_rows(&(&lobe * mirrored + (1.0 - &lobe) * wi));
    }
    let target = ggx_log_rows(&v, &wi, &wo);
    (v, wi, wo, target)
}

/// How far a neural material is from its GGX maps under some
/// configurations (linear renders, no fall-off, both at the material's
/// gain 1).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NeuralGap {
    /// Mean |ln(1 + R_neural) - ln(1 + R_ggx)| over configurations, pixels and channels.
    pub log_l1: f64,
    /// Largest |ln(sum_neural / sum_ggx)| of a channel's radiance summed
    /// over the configurations and pixels: the material's colour and
    /// brightness across the views (a channel 1.5x off: 0.41).
    pub channel_log_ratio: f64,
    /// Mean Euclidean distance of the pixels' chromaticities rgb / (r + g + b),
    /// weighted by the GGX render's brightness (what the eye sees: a black
    /// pixel's hue counts for nothing).
    pub chromaticity: f64,
    /// Mean over the configurations of the distance between the
    /// chromaticities of the two renders' mean colours (the relit colour).
    #[serde(default)]
    pub mean_chromaticity: f64,
    /// Mean LPIPS of the sRGB display renders (clamped to [0, 1]), when measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
}

/// Past these a [`NeuralGap`] is worth a warning: a channel 1.22x off
/// (ln 1.22 = 0.2), a chromaticity off by 0.05, LPIPS 0.1 between the
/// renders. The largest seen on 3-photo captures at 256x256 (held-out
/// materials 10-19 and the gold and teal checker; reports/capture.md,
/// eighth slice): 0.155 and 0.044.
pub const WARN_CHANNEL_LOG_RATIO: f64 = 0.2;
pub const WARN_CHROMATICITY: f64 = 0.05;
pub const WARN_LPIPS: f64 = 0.1;

impl NeuralGap {
    /// Why this gap is large enough to warn about, if it is (one phrase per
    /// measure past its bound, joined by commas).
    pub fn warning(&self) -> Option<String> {
        let mut why = vec![];
        if self.channel_log_ratio > WARN_CHANNEL_LOG_RATIO {
            why.push(format!("a colour channel {:.2}x off", self.channel_log_ratio.exp()));
        }
        if self.chromaticity > WARN_CHROMATICITY {
            why.push(format!("chromaticity off by {:.3}", self.chromaticity));
        }
        if let Some(l) = self.lpips.filter(|l| *l > WARN_LPIPS) {
            why.push(format!("LPIPS {l:.3} between their renders"));
        }
        (!why.is_empty()).then(|| why.join(", "))
    }
}

/// Held-out configurations for [`neural_gap`]: `count` of the Hemisphere
/// case and `count` of the Reflect case (flashmat eval's samplings) from a
/// fixed seed.
pub fn held_out_configs(count: usize) -> Vec<LightView> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(0x9a9);
    let mut configs = crate::geometry::sample_configs(&mut rng, Sampling::Hemisphere, count, MODEL_FOV_DEG);
    configs.extend(crate::geometry::sample_configs(&mut rng, Sampling::Reflect, count, MODEL_FOV_DEG));
    configs
}

/// [`NeuralGap`] of `material` against `maps` `[10, H, W]` under `configs`,
/// with LPIPS when `lpips` is given.
pub fn neural_gap(material: &NeuralMaterial, maps: &Tensor, configs: &[LightView], lpips: Option<&Lpips>) -> Result<NeuralGap> {
    let (h, w) = material.size();
    ensure!(maps.size() == [GGX_CHANNELS, h as i64, w as i64], "the maps must be [{GGX_CHANNELS}, {h}, {w}], got {:?}", maps.size());
    let maps = valid_values(&maps.to_device(material.device()).to_kind(Kind::Float).unsqueeze(0));
    // One configuration at a time: a 4096x4096 material's eight renders at once would take gigabytes.
    let mut sums = GapSums::default();
    for config in configs {
        let neural = material.render(std::slice::from_ref(config))?; // [1, 3, H, W]
        let ggx = tch::no_grad(|| {
            let (wi, wo) = material.direction_maps(std::slice::from_ref(config));
            render_directions(&maps, &wi, &wo).get(0).clamp_min(0.0) // [1, 3, H, W]
        });
        tch::no_grad(|| sums.add(&neural, &ggx, lpips));
    }
    sums.gap(lpips.is_some())
}

/// [`NeuralGap`] of two sets of linear renders `[K, 3, H, W]`.
pub fn gap_of_renders(neural: &Tensor, ggx: &Tensor, lpips: Option<&Lpips>) -> Result<NeuralGap> {
    ensure!(neural.size() == ggx.size() && neural.dim() == 4 && neural.size()[1] == 3, "renders must be two [K, 3, H, W] of one size, got {:?} and {:?}", neural.size(), ggx.size());
    let mut sums = GapSums::default();
    tch::no_grad(|| {
        for k in 0..neural.size()[0] {
            sums.add(&neural.narrow(0, k, 1), &ggx.narrow(0, k, 1), lpips);
        }
    });
    sums.gap(lpips.is_some())
}

/// [`NeuralGap`]'s sums over configurations, one added at a time.
#[derive(Default)]
struct GapSums {
    configs: f64,
    /// Sum of the per-configuration mean |log difference| (each configuration has as many pixels).
    log_l1: f64,
    neural_channels: [f64; 3],
    ggx_channels: [f64; 3],
    /// Brightness-weighted sum of the pixels' chromaticity distances, and the weights.
    chroma_weighted: f64,
    brightness: f64,
    mean_chromaticity: f64,
    lpips: f64,
}

impl GapSums {
    /// One configuration's renders, `[1, 3, H, W]` each.
    fn add(&mut self, neural: &Tensor, ggx: &Tensor, lpips: Option<&Lpips>) {
        let value = |t: Tensor| t.double_value(&[]);
        self.configs += 1.0;
        self.log_l1 += value((neural.log1p() - ggx.log1p()).abs().mean(Kind::Double));
        let channels = |t: &Tensor| Vec::<f64>::try_from(t.sum_dim_intlist([0i64, 2, 3].as_slice(), false, Kind::Double)).expect("three channel sums");
        for (total, v) in self.neural_channels.iter_mut().zip(channels(neural)) {
            *total += v;
        }
        for (total, v) in self.ggx_channels.iter_mut().zip(channels(ggx)) {
            *total += v;
        }
        let chroma = |t: &Tensor| t / t.sum_dim_intlist([1i64].as_slice(), true, Kind::Double).clamp_min(1e-9);
        let (n, g) = (neural.to_kind(Kind::Double), ggx.to_kind(Kind::Double));
        let brightness = g.sum_dim_intlist([1i64].as_slice(), false, Kind::Double); // [1, H, W]
        let distance = (chroma(&n) - chroma(&g)).square().sum_dim_intlist([1i64].as_slice(), false, Kind::Double).sqrt();
        self.chroma_weighted += value((distance * &brightness).sum(Kind::Double));
        self.brightness += value(brightness.sum(Kind::Double));
        let mean_colour = |t: &Tensor| chroma(&t.mean_dim([2i64, 3].as_slice(), false, Kind::Double)); // [1, 3]
        self.mean_chromaticity += value((mean_colour(&n) - mean_colour(&g)).square().sum(Kind::Double).sqrt());
        if let Some(net) = lpips {
            let display = |t: &Tensor| crate::spaces::linear_to_display(t).clamp(0.0, 1.0).to_kind(Kind::Float).to_device(net.device());
            self.lpips += value(net.distance_01(&display(neural), &display(ggx)).mean(Kind::Double));
        }
    }

    fn gap(&self, with_lpips: bool) -> Result<NeuralGap> {
        ensure!(self.configs > 0.0, "the neural material's gap needs at least one configuration");
        let per_config = |v: f64| v / self.configs;
        let channel_log_ratio = (0..3).map(|c| (self.neural_channels[c].max(1e-9) / self.ggx_channels[c].max(1e-9)).ln().abs()).fold(0.0, f64::max);
        Ok(NeuralGap {
            log_l1: per_config(self.log_l1),
            channel_log_ratio,
            chromaticity: self.chroma_weighted / self.brightness.max(1e-12),
            mean_chromaticity: per_config(self.mean_chromaticity),
            lpips: with_lpips.then(|| per_config(self.lpips)),
        })
    }
}

#[cfg(test)]
mod tests;
