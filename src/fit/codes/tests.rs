use super::*;
use crate::data::procedural::metal_material;
use crate::fit::photos::{load_teacher, neural_material};
use tch::Device;
use crate::model::ggx_codes::TeacherWeights;

/// Coloured metal `index` at `side x side`: its maps `[10, side, side]` and
/// their neural material under `teacher` (a black photo).
fn metal_and_material(teacher: &TeacherWeights, index: usize, side: usize) -> (Tensor, NeuralMaterial) {
    let maps = metal_material(index, side).stacked().to_tensor();
    let photo = Tensor::zeros([3, side as i64, side as i64], (Kind::Float, Device::Cpu));
    let material = neural_material(&maps, &photo, teacher, crate::data::procedural::METAL_MATERIALS[index]).unwrap();
    (maps, material)
}

#[test]
fn the_gap_of_identical_renders_is_zero_and_a_tint_is_measured() {
    let ggx = Tensor::rand([2, 3, 8, 8], (Kind::Float, Device::Cpu)) + 0.1;
    let same = gap_of_renders(&ggx, &ggx, None).unwrap();
    assert!(same.log_l1 < 1e-9 && same.channel_log_ratio < 1e-9 && same.chromaticity < 1e-9 && same.mean_chromaticity < 1e-9);
    // Red doubled: the channel ratio is ln 2 (the sums scale with it).
    let tint = Tensor::from_slice(&[2.0f32, 1.0, 1.0]).view([1, 3, 1, 1]);
    let gap = gap_of_renders(&(&ggx * &tint), &ggx, None).unwrap();
    assert!((gap.channel_log_ratio - 2f64.ln()).abs() < 1e-6, "{}", gap.channel_log_ratio);
    // A grey pixel (1, 1, 1) drawn (2, 1, 1): chromaticity (1/2, 1/4, 1/4) against
    // (1/3, 1/3, 1/3), distance sqrt(1/36 + 2/144) = 0.2041.
    let grey = Tensor::ones([1, 3, 4, 4], (Kind::Float, Device::Cpu));
    let gap = gap_of_renders(&(&grey * &tint), &grey, None).unwrap();
    assert!((gap.chromaticity - (1.0f64 / 36.0 + 2.0 / 144.0).sqrt()).abs() < 1e-6, "{}", gap.chromaticity);
    assert!((gap.mean_chromaticity - (1.0f64 / 36.0 + 2.0 / 144.0).sqrt()).abs() < 1e-6, "{}", gap.mean_chromaticity);
}

#[test]
fn fitted_codes_bring_a_wrong_encoders_colour_back_to_the_maps() {
    // The gold and teal checker at 48x48, its codes from the bundled
    // teacher's encoder with the last layer's weights of the red-leaning half
    // of the codes scaled by 0.7: an encoder off on this material, as the
    // procedural teacher was on metals. The fit brings the renders back to
    // what the maps draw.
    let teacher = load_teacher(None, Device::Cpu).unwrap();
    let side = 48;
    let (maps, mut material) = metal_and_material(&teacher, 0, side);
    let vs = tch::nn::VarStore::new(Device::Cpu);
    let wrong = GgxEncoder::new(&(vs.root() / "teacher"), teacher.config.neural_channels);
    tch::no_grad(|| {
        for (i, (w, theirs)) in wrong.weights().iter().zip(teacher.encoder.weights()).enumerate() {
            let mut w = w.shallow_clone();
            w.copy_(&theirs);
            if i == 2 {
                let half = w.size()[0] / 2;
                let _ = w.narrow(0, 0, half).g_mul_scalar_(0.7);
            }
        }
    });
    material.neural_map = tch::no_grad(|| wrong.forward_maps(&valid_values(&maps.unsqueeze(0)))).get(0);
    let configs = held_out_configs(4);
    let before = neural_gap(&material, &maps, &configs, None).unwrap();
    let cfg = CodeFitConfig { steps: 100, rows: 4096, ..Default::default() };
    let fit = fit_codes(&mut material, &maps, &wrong, &[NeuralMaterial::identity_config()], &cfg).unwrap();
    let after = neural_gap(&material, &maps, &configs, None).unwrap();
    eprintln!("before {before:?}\nafter {after:?}\nfit {fit:?}");
    assert!(fit.kept && fit.loss_after < 0.7 * fit.loss_before, "{fit:?}");
    assert!(after.log_l1 < 0.6 * before.log_l1, "log L1 {} -> {}", before.log_l1, after.log_l1);
    assert!(after.channel_log_ratio < 0.5 * before.channel_log_ratio, "channel log ratio {} -> {}", before.channel_log_ratio, after.channel_log_ratio);
    assert!(after.chromaticity < before.chromaticity, "chromaticity {} -> {}", before.chromaticity, after.chromaticity);
    assert_eq!(material.neural_map.size(), [teacher.config.neural_channels, side as i64, side as i64]);
}

#[test]
fn the_materials_renderer_is_tuned_with_its_codes_and_travels_in_its_file() {
    // The teacher's renderer with its red output row scaled by 0.9: every
    // red value drawn ~10% low in ln(1 + R), a colour no code fixes exactly
    // everywhere. Tuning the material's own renderer with the encoder
    // brings the red back closer than the codes alone, the tuned weights
    // are what the saved `.nmat` holds, and they come back frozen.
    let teacher = load_teacher(None, Device::Cpu).unwrap();
    let side = 32;
    let maps = metal_and_material(&teacher, 0, side).0;
    let distorted = || {
        let m = metal_and_material(&teacher, 0, side).1;
        tch::no_grad(|| {
            let _ = m.renderer.m_render.layers.last().unwrap().narrow(0, 0, 1).g_mul_scalar_(0.9);
        });
        m
    };
    let configs = held_out_configs(4);
    let before = neural_gap(&distorted(), &maps, &configs, None).unwrap();
    let fit_with = |renderer_learning_rate: f64| {
        let mut m = distorted();
        let cfg = CodeFitConfig { steps: 200, rows: 2048, renderer_learning_rate, ..Default::default() };
        let fit = fit_codes(&mut m, &maps, &teacher.encoder, &[], &cfg).unwrap();
        assert!(fit.kept, "{fit:?}");
        let gap = neural_gap(&m, &maps, &configs, None).unwrap();
        (m, gap)
    };
    let (_, codes_only) = fit_with(0.0);
    let (tuned, both) = fit_with(3e-4);
    eprintln!("before {before:?}\ncodes only {codes_only:?}\nrenderer too {both:?}");
    assert!(both.log_l1 < codes_only.log_l1 && both.log_l1 < 0.6 * before.log_l1, "log L1 {} -> codes only {}, renderer too {}", before.log_l1, codes_only.log_l1, both.log_l1);
    assert!(both.channel_log_ratio < 0.5 * before.channel_log_ratio, "channel log ratio {} -> {}", before.channel_log_ratio, both.channel_log_ratio);
    let vars = tuned.renderer_vs.variables();
    assert!(vars.values().all(|v| !v.requires_grad()), "the renderer is frozen again");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tuned.nmat");
    tuned.save(&path).unwrap();
    let back = NeuralMaterial::load(&path, Device::Cpu).unwrap();
    let config = [NeuralMaterial::identity_config()];
    assert!(back.render(&config).unwrap().allclose(&tuned.render(&config).unwrap(), 1e-5, 1e-6, false));
}

#[test]
fn a_failed_fit_puts_the_renderer_back() {
    // A rate of 1e6 throws the weights far off: the loss becomes non-finite
    // (an error) or rises (not kept); either way the renderer is the one it was.
    let teacher = load_teacher(None, Device::Cpu).unwrap();
    let (maps, mut material) = metal_and_material(&teacher, 2, 16);
    let weights: Vec<(String, Tensor)> = material.renderer_vs.variables().into_iter().map(|(k, v)| (k, v.copy())).collect();
    let cfg = CodeFitConfig { steps: 5, rows: 256, learning_rate: 1e6, renderer_learning_rate: 1e6, ..Default::default() };
    if let Ok(fit) = fit_codes(&mut material, &maps, &teacher.encoder, &[], &cfg) {
        assert!(!fit.kept, "{fit:?}");
    }
    let now = material.renderer_vs.variables();
    for (name, w) in &weights {
        assert!(now[name].equal(w) && !now[name].requires_grad(), "{name} changed");
    }
}

#[test]
fn a_fit_that_does_not_lower_the_loss_keeps_the_teachers_codes() {
    // No steps: the check loss cannot fall, and the codes stay the teacher's.
    let teacher = load_teacher(None, Device::Cpu).unwrap();
    let (maps, mut material) = metal_and_material(&teacher, 4, 16);
    let codes = material.neural_map.copy();
    let fit = fit_codes(&mut material, &maps, &teacher.encoder, &[], &CodeFitConfig::none()).unwrap();
    assert!(!fit.kept && fit.loss_after == fit.loss_before, "{fit:?}");
    assert!(material.neural_map.equal(&codes));
    // Maps of another size are refused in one line.
    let e = fit_codes(&mut material, &maps.narrow(1, 0, 8), &teacher.encoder, &[], &CodeFitConfig::default()).unwrap_err();
    assert!(format!("{e}").contains("the maps must be [10, 16, 16]"), "{e}");
}

#[test]
fn a_gap_past_its_bounds_names_each_measure() {
    let close = NeuralGap { log_l1: 0.01, channel_log_ratio: 0.05, chromaticity: 0.02, mean_chromaticity: 0.01, lpips: Some(0.05) };
    assert_eq!(close.warning(), None);
    // ln 1.3 = 0.262: a channel 1.30x off; LPIPS unmeasured says nothing.
    let far = NeuralGap { channel_log_ratio: 1.3f64.ln(), chromaticity: 0.06, lpips: None, ..close.clone() };
    assert_eq!(far.warning().unwrap(), "a colour channel 1.30x off, chromaticity off by 0.060");
    let blurred = NeuralGap { lpips: Some(0.15), ..close };
    assert_eq!(blurred.warning().unwrap(), "LPIPS 0.150 between their renders");
}

#[test]
fn the_photo_rows_point_where_the_materials_renders_do() {
    // The code fit's rows under a photo take its light and camera from the
    // pixel's surface point, as the material's own direction maps do.
    let teacher = load_teacher(None, Device::Cpu).unwrap();
    let maps = metal_material(2, 24).stacked().to_tensor().narrow(2, 0, 16); // 24 x 16: a rectangle
    let photo = Tensor::zeros([3, 24, 16], (Kind::Float, Device::Cpu));
    let material = neural_material(&maps, &photo, &teacher, "copper").unwrap();
    let config = LightView { light: [0.9, -0.7, 3.7], view: [0.2, 0.1, 3.9] };
    let (lights, views, points) = photo_positions(&material, &[config], 7).unwrap();
    assert_eq!((lights.size(), points.size()), (vec![1 + PHOTO_VARIANTS as i64, 3], vec![24 * 16, 3]));
    let (wi, wo) = material.direction_maps(&[config]); // [1, 1, 3, H, W]
    let as_rows = |t: &Tensor| t.get(0).get(0).view([3, -1]).transpose(0, 1);
    let towards = |p: &Tensor| crate::svbrdf::rows::normalize_rows(&(p.narrow(0, 0, 1) - &points));
    assert!(towards(&lights).allclose(&as_rows(&wi), 1e-5, 1e-6, false));
    assert!(towards(&views).allclose(&as_rows(&wo), 1e-5, 1e-6, false));
    // The jittered copies stay above the sample.
    assert!(lights.narrow(1, 2, 1).min().double_value(&[]) >= 0.5 && views.narrow(1, 2, 1).min().double_value(&[]) >= 0.5);
}
