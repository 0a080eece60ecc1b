//! Inference from photos: one flash photo -> a relightable neural material.
//!
//! ```text
//! photo file ──► photo::load_photo ──► estimate (M_est) ──► NeuralMaterial ──► .nmat
//!  (PNG/JPEG:     (linear, FOV crop,     (BatchNorm folded,   (neural map +       (nmat)
//!   sRGB curve;    area resize: S on     no autograd; whole    ND_enc/M_render)
//!   EXR: linear)   the shorter side)     or layer-wise tiles)     │
//!                                                                 ▼
//!                                           render / orbit / show (linear radiance)
//! ```
//!
//! The model's input view is fixed: light and camera co-located at
//! (0, 0, fov_to_distance(28)) over the material, whose shorter side spans
//! [-1, 1] (a rectangle's longer side [-a, a], `geometry::half_extents`). Photos
//! with a wider lens are cropped to that view ([`photo`]), so the identity
//! configuration of every material is [`NeuralMaterial::identity_config`].

pub mod camera;
pub mod exposure;
pub mod highlight_fill;
pub mod nmat;
pub mod photo;
pub mod refine;
pub mod show;
pub mod tiles;
pub mod tiling;

pub use exposure::{ExposureConfig, ExposureMode};
pub use nmat::{NeuralMaterial, NmatMeta, NMAT_FORMAT, NMAT_VERSION};
pub use photo::{load_photo, load_photo_with, prepare_decoded, prepare_image, prepare_image_with, Crop, PhotoOptions, PreparedPhoto};
pub use tiles::{plan_estimate, EstPlan};

use crate::data::samples::photo_est_input;
use crate::geometry::{fov_to_distance, LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::model::{Model, ModelConfig, ModelInfo};
use anyhow::{bail, ensure, Result};
use std::path::{Path, PathBuf};
use tch::Device;

/// Preset of the bundled model (`models/flashmat.safetensors`).
pub const BUNDLED_PRESET: &str = "compact-f8";

/// Environment variable that replaces the bundled-models folder.
pub const MODELS_ENV: &str = "FLASHMAT_MODELS";

/// Light circle of orbit animations: radius and height above the material
/// (the camera stays overhead at the input configuration).
pub const ORBIT_RADIUS: f64 = 2.0;
pub const ORBIT_HEIGHT: f64 = 3.0;

/// Folder holding the bundled models: `$FLASHMAT_MODELS` when set, else
/// `models/` under [`crate::bundled_root`].
pub fn models_dir() -> PathBuf {
    match std::env::var_os(MODELS_ENV) {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => crate::bundled_root().join("models"),
    }
}

/// File of the bundled model, in [`models_dir`]: one model for 8-bit and
/// EXR photos alike (which run it is: models/MODEL.md). It was trained on
/// clamped (LDR) photos and clamps EXR photos itself; on the 50 held-out
/// materials it scored better LPIPS on HDR photos than the HDR-trained
/// model of the same budget (reports/README.md), so one model is bundled.
pub const BUNDLED_MODEL: &str = "flashmat.safetensors";

/// The bundled model (the same file for every photo type).
pub fn default_model_path() -> PathBuf {
    models_dir().join(BUNDLED_MODEL)
}

/// A loaded model and where it came from.
#[derive(Debug)]
pub struct LoadedModel {
    pub model: Model,
    pub info: ModelInfo,
    pub path: PathBuf,
}

/// Loads `explicit` (any preset), or the bundled model (which must hold
/// the `compact` preset). A missing file names the file and says that
/// `--model` selects another.
pub fn load_model(explicit: Option<&Path>, device: Device) -> Result<LoadedModel> {
    let (model, info, path) = match explicit {
        Some(p) => {
            if !p.exists() {
                bail!("model file {} does not exist (given with --model)", p.display());
            }
            let (m, i) = Model::load(p, device)?;
            (m, i, p.to_path_buf())
        }
        None => {
            let p = default_model_path();
            if !p.exists() {
                bail!("the bundled model {} does not exist (not trained yet?); select a model file with --model FILE", p.display());
            }
            let (m, i) = Model::load_expecting(&p, device, &ModelConfig::preset(BUNDLED_PRESET)?.model_id())?;
            (m, i, p)
        }
    };
    Ok(LoadedModel { model, info, path })
}

/// One-line warning when a model was trained on the other photo type, or
/// None. An LDR model given an HDR photo sees it clamped to [0, 1].
pub fn input_mismatch_warning(info: &ModelInfo, model_path: &Path, ldr_photo: bool) -> Option<String> {
    match (info.ldr_input, ldr_photo) {
        (true, false) => Some(format!(
            "warning: model {} was trained on 8-bit (LDR) photos; the EXR photo is clamped to [0,1] for it",
            model_path.display()
        )),
        (false, true) => Some(format!(
            "warning: model {} was trained on HDR (EXR) photos; an 8-bit photo lacks the highlights above 1 it expects",
            model_path.display()
        )),
        _ => None,
    }
}

/// Runs M_est (inference mode: BatchNorm folded, no autograd) on a
/// prepared photo and packages the result with a copy of the model's
/// renderer, with the default exposure handling ([`ExposureConfig`]: a dark
/// photo brought up for M_est, the gain calibrated on the identity render).
pub fn estimate(model: &Model, info: &ModelInfo, photo: &PreparedPhoto) -> Result<NeuralMaterial> {
    estimate_planned(model, info, photo, &EstPlan::Whole, &ExposureConfig::default(), || ())
}

/// [`estimate`] on the whole photo or in tiles ([`tiles::plan_estimate`]
/// chooses under a memory bound), with the given exposure handling;
/// `on_tile` is called after each layer-wise block. M_est sees the photo
/// times [`exposure::normalizing_scale`], clamped to [0, 1] for LDR-input
/// models (as in their training) and below at 0 otherwise; the material's
/// gain is the inverse scale, calibrated on the identity render when
/// `exposure.calibrate` ([`exposure::calibration_factor`]). The stored
/// input photo is the photo itself (clamped the same way, not normalised).
pub fn estimate_planned(model: &Model, info: &ModelInfo, photo: &PreparedPhoto, plan: &EstPlan, exposure: &ExposureConfig, mut on_tile: impl FnMut()) -> Result<NeuralMaterial> {
    ensure!(photo.linear.channels == 3, "the prepared photo must have 3 channels, got {}", photo.linear.channels);
    exposure.validate()?;
    let linear = photo.linear.to_tensor(); // [3, H, W]
    let clamp = |t: &tch::Tensor| if info.ldr_input { crate::spaces::ldr_clamp(t) } else { t.clamp_min(0.0) };
    let stored = clamp(&linear);
    let scales = exposure::candidate_scales(&stored, exposure, info.ldr_input);
    let mut best: Option<(f64, NeuralMaterial)> = None;
    let choosing = scales.len() > 1;
    for &scale in &scales {
        let (material, identity) = estimate_at_scale(model, info, photo, &linear, &stored, scale, plan, exposure, choosing, &mut on_tile)?;
        let Some(identity) = identity.filter(|_| choosing) else { return Ok(material) };
        let error = exposure::identity_error(&material.input_photo, &identity);
        if best.as_ref().is_none_or(|(e, _)| error < *e) {
            best = Some((error, material));
        }
    }
    Ok(best.expect("candidate_scales returns at least one scale").1)
}

/// M_est on the photo times `scale` and the material around its map (gain
/// 1 / scale, calibrated when asked), with its identity render `[3, H, W]`
/// at the final gain where the calibration or `want_identity` made one
/// (rendered once: the render is linear in the gain). linear: the photo
/// `[3, H, W]`; stored: the same clamped as the material keeps it.
#[allow(clippy::too_many_arguments)]
fn estimate_at_scale(
    model: &Model,
    info: &ModelInfo,
    photo: &PreparedPhoto,
    linear: &tch::Tensor,
    stored: &tch::Tensor,
    scale: f64,
    plan: &EstPlan,
    exposure: &ExposureConfig,
    want_identity: bool,
    on_tile: &mut impl FnMut(),
) -> Result<(NeuralMaterial, Option<tch::Tensor>)> {
    let device = model.device();
    let x = photo_est_input(&(linear * scale), info.ldr_input, device); // [1, 4, H, W]
    let est = model.est.fold_batchnorm();
    let map = match plan {
        EstPlan::Whole => est.forward(&x)?,
        EstPlan::Tiled(core) => est.forward_layerwise(&x, *core, &mut *on_tile)?,
    }; // [1, C, H, W]
    ensure!(crate::image::all_finite(&map), "M_est produced NaN/Inf values for this photo (the model's weights have diverged?)");
    let meta = NmatMeta {
        model_id: model.model_id(),
        fov_deg: photo.fov_deg,
        crop: photo.crop,
        source: photo.source.clone(),
        ldr_input: photo.ldr,
        model_info: info.clone(),
        refine: None,
        gain: [1.0 / scale; 3],
    };
    let mut material = NeuralMaterial::from_parts(map.get(0), stored.to_device(device), &model.config, &model.renderer_vs.variables(), meta)?;
    let mut identity = if exposure.calibrate || want_identity { Some(material.render(&[NeuralMaterial::identity_config()])?.get(0)) } else { None };
    if let (true, Some(id)) = (exposure.calibrate, identity.as_mut()) {
        if let Some(f) = exposure::calibration_factor(&material.input_photo, id, exposure.white_balance) {
            material.meta.gain = [0, 1, 2].map(|c| material.meta.gain[c] * f[c]);
            *id = &*id * tch::Tensor::from_slice(&f).to_kind(tch::Kind::Float).to_device(id.device()).view([3, 1, 1]);
        }
    }
    Ok((material, identity))
}

/// The material's identity render against its stored photo
/// ([`exposure::IdentityCheck`]); None where nothing can be compared.
pub fn identity_check(material: &NeuralMaterial) -> Result<Option<exposure::IdentityCheck>> {
    let identity = material.render(&[NeuralMaterial::identity_config()])?.get(0);
    Ok(exposure::IdentityCheck::measure(&material.input_photo, &identity))
}

/// `frames` configurations of a light circling the material at radius
/// `radius` and height `height` (starting on +x, counter-clockwise), seen
/// by a camera at `camera`.
pub fn orbit_configs(frames: usize, radius: f64, height: f64, camera: [f64; 3]) -> Vec<LightView> {
    (0..frames)
        .map(|i| {
            let a = std::f64::consts::TAU * i as f64 / frames as f64;
            LightView { light: [radius * a.cos(), radius * a.sin(), height], view: camera }
        })
        .collect()
}

/// The overhead camera of the input photo.
pub fn overhead_camera() -> [f64; 3] {
    [0.0, 0.0, fov_to_distance(MODEL_FOV_DEG)]
}

/// Renders configurations one frame at a time (bounded memory), calling
/// `on_frame` after each; linear images `[3, H, W]`.
pub fn render_frames(material: &NeuralMaterial, configs: &[LightView], mut on_frame: impl FnMut(usize)) -> Result<Vec<Image>> {
    configs
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let im = material.render_image(c)?;
            on_frame(i);
            Ok(im)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::samples::{est_input, input_directions};
    use crate::model::ModelConfig;
    use crate::svbrdf::render::half_vector_z;

    fn photo(size: usize, ldr: bool) -> PreparedPhoto {
        let linear = Image::from_fn(3, size, size, |c, y, x| 0.2 + 0.1 * c as f32 + 0.01 * ((x * 7 + y * 3) % 13) as f32 + if ldr { 0.0 } else { 2.0 });
        PreparedPhoto::at_model_view(linear, ldr, "p.exr")
    }

    #[test]
    fn estimate_then_identity_render_has_the_photo_size() {
        tch::manual_seed(4);
        let model = Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap();
        let info = ModelInfo { ldr_input: true, steps: 0 };
        // The photo as it is (no exposure normalisation): M_est's input is the stored photo.
        let m = estimate_planned(&model, &info, &photo(24, false), &EstPlan::Whole, &ExposureConfig::off(), || ()).unwrap();
        assert_eq!(m.meta.gain, [1.0; 3]);
        assert_eq!(m.size(), (24, 24));
        assert_eq!(m.neural_map.size(), [16, 24, 24]);
        // An LDR model sees the HDR photo clamped.
        assert_eq!(m.input_photo.max().double_value(&[]), 1.0);
        let im = m.render_image(&NeuralMaterial::identity_config()).unwrap();
        assert_eq!((im.channels, im.height, im.width), (3, 24, 24));
        assert!(im.find_non_finite().is_none());
        // The estimate equals the unfolded eval-mode forward.
        let x = est_input(&m.input_photo.unsqueeze(0), &{
            let (wi, wo) = input_directions(24, 24, 28.0, Device::Cpu);
            half_vector_z(&wi, &wo)
        });
        let direct = tch::no_grad(|| model.est_forward_t(&x, false)).unwrap().get(0);
        let diff = (&direct - &m.neural_map).abs().max().double_value(&[]);
        assert!(diff < 1e-3 * (1.0 + direct.abs().max().double_value(&[])), "{diff}");
        // The material's renderer is a copy: same output as the model's.
        let cfg = LightView { light: [1.0, 0.0, 2.0], view: overhead_camera() };
        let ours = m.render(&[cfg]).unwrap();
        let (l, v) = crate::geometry::config_tensors(&[cfg], Device::Cpu);
        let (wi, wo) = crate::svbrdf::render::direction_maps_for(&l.view([1, 1, 3]), &v.view([1, 1, 3]), 24, 24);
        let theirs = tch::no_grad(|| model.renderer.forward_maps(&m.neural_map.unsqueeze(0), &wi, &wo)).unwrap();
        assert!(ours.equal(&theirs.get(0).clamp_max(nmat::MAX_LOG_RADIANCE).expm1().clamp_min(0.0)));
    }

    /// Issue 53: of two photos darker than the minimum level, the one two
    /// stops darker gives the same neural map and a quarter of the gain, so
    /// every render is a quarter as bright; the calibration makes the
    /// identity render's mean the photo's over the pixels it compares.
    #[test]
    fn a_darker_photo_gives_the_same_map_and_a_proportional_gain() {
        // The bundled model: a random one renders far from any photo, where the calibration refuses to act.
        let LoadedModel { model, info, .. } = load_model(None, Device::Cpu).unwrap();
        // Medians of about 0.022 and 0.0056: both below the minimum level.
        let base = photo(24, true);
        let bright = PreparedPhoto { linear: base.linear.map(|v| v / 16.0), ..base.clone() };
        let dark = PreparedPhoto { linear: base.linear.map(|v| v / 64.0), ..base.clone() };
        let relit = [NeuralMaterial::identity_config(), LightView { light: [1.0, 0.5, 2.0], view: overhead_camera() }];
        for cfg in [ExposureConfig { calibrate: false, ..Default::default() }, ExposureConfig::default()] {
            let a = estimate_planned(&model, &info, &bright, &EstPlan::Whole, &cfg, || ()).unwrap();
            let b = estimate_planned(&model, &info, &dark, &EstPlan::Whole, &cfg, || ()).unwrap();
            let d = (&a.neural_map - &b.neural_map).abs().max().double_value(&[]);
            assert!(d < 1e-5 * (1.0 + a.neural_map.abs().max().double_value(&[])), "maps differ by {d}");
            for c in 0..3 {
                assert!((a.meta.gain[c] / b.meta.gain[c] - 4.0).abs() < 1e-5, "{:?} / {:?}", a.meta.gain, b.meta.gain);
            }
            let (ra, rb) = (a.render(&relit).unwrap(), b.render(&relit).unwrap());
            let e = (&ra - &rb * 4.0).abs().max().double_value(&[]);
            assert!(e < 1e-4 * (1.0 + ra.max().double_value(&[])), "renders differ by {e}");
            // The stored photo is the photo itself, not what M_est saw.
            assert!(b.input_photo.equal(&dark.linear.to_tensor()));
            if cfg.calibrate {
                let photo = b.input_photo.shallow_clone();
                let mask = exposure::calibration_mask(&photo).unsqueeze(0).expand_as(&photo);
                let mean = |t: &tch::Tensor| t.masked_select(&mask).mean(tch::Kind::Double).double_value(&[]);
                let ratio = mean(&rb.get(0)) / mean(&photo);
                assert!((ratio - 1.0).abs() < 1e-4, "identity over photo {ratio}");
                // ... and per channel (the white balance).
                for r in exposure::identity_channel_ratios(&photo, &rb.get(0)) {
                    assert!((r - 1.0).abs() < 1e-4, "identity over photo per channel {r}");
                }
            } else {
                // Normalised only: M_est saw the photo at the minimum level, the gain undoes it.
                let level = exposure::photo_level(&dark.linear.to_tensor()).unwrap();
                assert!(b.meta.gain.iter().all(|g| (g - level / exposure::DEFAULT_MIN_LEVEL).abs() < 1e-9), "{:?}", b.meta.gain);
                // The bundled model's estimate of a photo above the level is the photo as it is.
                let plain = estimate_planned(&model, &info, &base, &EstPlan::Whole, &cfg, || ()).unwrap();
                assert_eq!(plain.meta.gain, [1.0; 3]);
            }
        }
    }

    /// A dark photo whose highlight the level's lift would clip: the lifts
    /// between are tried, the kept material gives the photo back at least
    /// as well as either end, and the photo two stops darker keeps the same
    /// map at a quarter of the gain.
    #[test]
    fn a_dark_photo_with_a_highlight_keeps_the_lift_that_gives_it_back_best() {
        let LoadedModel { model, info, .. } = load_model(None, Device::Cpu).unwrap();
        // Median 0.0067 (the level asks for 15x), a 4x4 highlight at 0.2-0.26 (the clip allows 3.8x).
        let lin = |k: f32| Image::from_fn(3, 24, 24, move |c, y, x| k * if (9..13).contains(&y) && (9..13).contains(&x) { 0.2 + 0.03 * c as f32 } else { 0.005 + 0.001 * c as f32 + 0.0005 * ((x * 7 + y * 3) % 5) as f32 });
        let at = |k: f32| PreparedPhoto::at_model_view(lin(k), true, "p.png");
        let cfg = ExposureConfig::default();
        assert_eq!(exposure::candidate_scales(&at(1.0).linear.to_tensor(), &cfg, true).len(), 3);
        let error = |m: &NeuralMaterial| exposure::identity_error(&m.input_photo, &m.render(&[NeuralMaterial::identity_config()]).unwrap().get(0));
        let est = |k: f32, cfg: &ExposureConfig| estimate_planned(&model, &info, &at(k), &EstPlan::Whole, cfg, || ()).unwrap();
        let kept = est(1.0, &cfg);
        let capped = est(1.0, &ExposureConfig { lift_candidates: 1, ..cfg });
        let clipping = est(1.0, &ExposureConfig { clip_share: None, ..cfg });
        assert!(capped.meta.gain[1] > clipping.meta.gain[1] * 1.5, "the two ends differ: {:?} / {:?}", capped.meta.gain, clipping.meta.gain);
        let e = error(&kept);
        assert!(e <= error(&capped) + 1e-12 && e <= error(&clipping) + 1e-12, "{e} vs {} and {}", error(&capped), error(&clipping));
        let darker = est(0.25, &cfg);
        let d = (&kept.neural_map - &darker.neural_map).abs().max().double_value(&[]);
        assert!(d < 1e-4 * (1.0 + kept.neural_map.abs().max().double_value(&[])), "maps differ by {d}");
        for c in 0..3 {
            assert!((kept.meta.gain[c] / darker.meta.gain[c] - 4.0).abs() < 1e-4, "{:?} / {:?}", kept.meta.gain, darker.meta.gain);
        }
    }

    #[test]
    fn orbit_circles_above_the_material() {
        let c = orbit_configs(4, 2.0, 3.0, overhead_camera());
        assert_eq!(c.len(), 4);
        assert!((c[1].light[0]).abs() < 1e-12 && (c[1].light[1] - 2.0).abs() < 1e-12);
        assert!(c.iter().all(|lv| lv.light[2] == 3.0 && lv.view == overhead_camera()));
    }

    #[test]
    fn mismatch_warning_is_one_line() {
        let p = Path::new("m.safetensors");
        assert!(input_mismatch_warning(&ModelInfo { ldr_input: true, steps: 1 }, p, true).is_none());
        let w = input_mismatch_warning(&ModelInfo { ldr_input: false, steps: 1 }, p, true).unwrap();
        assert!(w.starts_with("warning: ") && !w.contains('\n'));
        assert!(input_mismatch_warning(&ModelInfo { ldr_input: true, steps: 1 }, p, false).unwrap().contains("clamped"));
    }

    #[test]
    fn missing_model_names_the_file_and_the_option() {
        let e = load_model(Some(Path::new("/nonexistent/m.safetensors")), Device::Cpu).unwrap_err().to_string();
        assert!(e.contains("/nonexistent/m.safetensors") && e.contains("--model"), "{e}");
        assert!(default_model_path().ends_with("flashmat.safetensors"));
    }
}
