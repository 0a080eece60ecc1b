use super::export::{from_metallic, to_metallic};
use super::*;
use crate::svbrdf::Svbrdf;
use crate::infer::nmat::MAX_LOG_RADIANCE;

/// Four known GGX materials in 8x8 tiles: (kd, ks, roughness, normal slopes).
fn known_maps(size: usize) -> Tensor {
    let tiles: [([f32; 3], [f32; 3], f32, [f32; 2]); 4] = [
        ([0.6, 0.1, 0.05], [0.04; 3], 0.3, [0.0, 0.0]),
        ([0.2, 0.3, 0.5], [0.25, 0.25, 0.25], 0.55, [0.25, -0.1]),
        ([0.05, 0.05, 0.05], [0.9, 0.6, 0.3], 0.4, [-0.15, 0.2]),
        ([0.4, 0.4, 0.35], [0.08, 0.08, 0.08], 0.8, [0.1, 0.3]),
    ];
    let mut m = Svbrdf::uniform(size, size, [0.0; 3], [0.0; 3], 0.5);
    for y in 0..size {
        for x in 0..size {
            let (kd, ks, r, s) = tiles[((y / 8) % 2) * 2 + (x / 8) % 2];
            let n = crate::geometry::normalize3([s[0], s[1], 1.0]);
            for c in 0..3 {
                m.diffuse.set(c, y, x, kd[c]);
                m.specular.set(c, y, x, ks[c]);
                m.normal.set(c, y, x, n[c]);
            }
            m.roughness.set(0, y, x, r);
        }
    }
    m.stacked().to_tensor()
}

fn mean_abs(a: &Tensor, b: &Tensor) -> f64 {
    (a - b).abs().mean(Kind::Double).double_value(&[])
}

/// The fit recovers GGX maps from their own renders through the same
/// sampling. Measured (32 pairs, 300 steps, 16x16, no smoothness): mean
/// absolute error kd 0.0001, ks 0.0002, roughness 0.0002, normals 0.008
/// degrees, render |ln(1+R) diff| 0.00001 (grid start 0.11). Tolerances
/// are 10-50x that.
#[test]
fn recovers_known_ggx_maps_from_their_own_renders() {
    let truth = known_maps(16);
    let (wi, wo) = sample_directions(32, 3, Device::Cpu);
    let targets = ggx_log(&truth.unsqueeze(0), &wi, &wo).get(0);
    let cfg = FitConfig { steps: 300, smooth_weight: 0.0, ..FitConfig::default() };
    let fit = fit_targets(&targets, &wi, &wo, &cfg, |_| {}).unwrap();
    assert_eq!(fit.maps.size(), [10, 16, 16]);
    let m = &fit.maps;
    let kd = mean_abs(&m.narrow(0, 0, 3), &truth.narrow(0, 0, 3));
    let ks = mean_abs(&m.narrow(0, 3, 3), &truth.narrow(0, 3, 3));
    let r = mean_abs(&m.narrow(0, 6, 1), &truth.narrow(0, 6, 1));
    let cos = (m.narrow(0, 7, 3) * truth.narrow(0, 7, 3)).sum_dim_intlist([0i64].as_slice(), false, Kind::Double).clamp(-1.0, 1.0);
    let angle = cos.acos().mean(Kind::Double).double_value(&[]).to_degrees();
    let err = fit.report.mean_error;
    eprintln!("kd {kd:.4} ks {ks:.4} roughness {r:.4} normal {angle:.3} deg, render {err:.5} (init {:.4})", fit.report.mean_error_init);
    assert!(kd < 0.005, "kd error {kd}");
    assert!(ks < 0.005, "ks error {ks}");
    assert!(r < 0.005, "roughness error {r}");
    assert!(angle < 0.25, "normal error {angle} degrees");
    assert!(err < 0.0005 && err < 0.01 * fit.report.mean_error_init, "render error {err} (init {})", fit.report.mean_error_init);
    assert!((fit.error.mean(Kind::Double).double_value(&[]) - err).abs() < 1e-9);
}

#[test]
fn the_smoothness_prior_removes_speckle_where_the_material_is_flat() {
    // One uniform material with noisy targets: the prior keeps the fitted maps flat.
    let truth = Svbrdf::uniform(16, 16, [0.3, 0.3, 0.3], [0.04; 3], 0.4).stacked().to_tensor();
    let (wi, wo) = sample_directions(16, 5, Device::Cpu);
    tch::manual_seed(2);
    let targets = ggx_log(&truth.unsqueeze(0), &wi, &wo).get(0);
    let noisy = &targets + targets.randn_like() * 0.01;
    let spread = |w: f64| {
        let fit = fit_targets(&noisy, &wi, &wo, &FitConfig { steps: 120, smooth_weight: w, ..FitConfig::default() }, |_| {}).unwrap();
        fit.maps.narrow(0, 6, 1).std(true).double_value(&[])
    };
    let (rough_free, rough_smooth) = (spread(0.0), spread(0.05));
    assert!(rough_smooth < 0.5 * rough_free, "roughness spread {rough_free} -> {rough_smooth}");
}

#[test]
fn broadcast_directions_render_as_expanded_maps() {
    let maps = known_maps(8).unsqueeze(0);
    let (wi, wo) = sample_directions(12, 1, Device::Cpu);
    let expand = |t: &Tensor| t.view([1, 12, 3, 1, 1]).expand([1, 12, 3, 8, 8], false);
    let full = crate::spaces::to_log(&crate::svbrdf::render::render_directions(&maps, &expand(&wi), &expand(&wo)));
    let ours = ggx_log(&maps, &wi, &wo);
    assert_eq!(ours.size(), [1, 12, 3, 8, 8]);
    let worst = (&ours - &full).abs().max().double_value(&[]);
    assert!(worst < 1e-5 * (1.0 + full.abs().max().double_value(&[])), "{worst}");
}

#[test]
fn direction_pairs_cover_the_hemisphere_above_the_minimum_elevation() {
    let (wi, wo) = sample_directions(32, 9, Device::Cpu);
    for t in [&wi, &wo] {
        let norm = t.square().sum_dim_intlist([1i64].as_slice(), false, Kind::Double).sqrt();
        assert!((norm - 1.0).abs().max().double_value(&[]) < 1e-6);
        assert!(t.narrow(1, 2, 1).min().double_value(&[]) >= MIN_DIRECTION_Z - 1e-6);
    }
    // A quarter co-located (identical), the rest not.
    let same = (&wi - &wo).abs().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).lt(1e-6).sum(Kind::Int64).int64_value(&[]);
    assert_eq!(same, 8);
    // Deterministic per seed.
    assert!(sample_directions(32, 9, Device::Cpu).0.equal(&wi));
    assert!(!sample_directions(32, 10, Device::Cpu).0.equal(&wi));
}

#[test]
fn neural_targets_equal_the_neural_renderer() {
    let m = crate::infer::nmat::tests::random_material(4, 8);
    let (wi, wo) = sample_directions(9, 2, Device::Cpu);
    let t = neural_targets(&m, &wi, &wo, |_| {}).unwrap();
    assert_eq!(t.size(), [9, 3, 8, 8]);
    let expand = |d: &Tensor| d.view([1, 9, 3, 1, 1]).expand([1, 9, 3, 8, 8], false).contiguous();
    let direct = tch::no_grad(|| m.renderer.forward_maps(&m.neural_map.unsqueeze(0), &expand(&wi), &expand(&wo))).unwrap().get(0);
    let direct = direct.clamp(0.0, MAX_LOG_RADIANCE);
    assert!(mean_abs(&t, &direct) < 1e-5, "{}", mean_abs(&t, &direct));
    // The material's exposure gain: the targets are ln(1 + gain R), what its renders show.
    let mut m = m;
    m.meta.gain = [3.0, 1.5, 0.5];
    let scaled = neural_targets(&m, &wi, &wo, |_| {}).unwrap();
    let expect = (direct.expm1() * Tensor::from_slice(&[3.0f32, 1.5, 0.5]).view([1, 3, 1, 1])).log1p();
    assert!(mean_abs(&scaled, &expect) < 1e-5, "{}", mean_abs(&scaled, &expect));
    assert!(mean_abs(&scaled, &t) > 0.01);
}

#[test]
fn fit_material_runs_on_a_neural_material_and_improves_on_its_start() {
    let m = crate::infer::nmat::tests::random_material(6, 8);
    let mut calls = 0;
    let fit = fit_material(&m, &FitConfig { steps: 30, samples: 8, ..FitConfig::default() }, |_, total| {
        calls += 1;
        assert_eq!(total, 38);
    })
    .unwrap();
    assert_eq!(calls, 2 + 30);
    assert!(fit.report.mean_error <= fit.report.mean_error_init + 1e-6, "{:?}", fit.report);
    assert!(crate::image::all_finite(&fit.maps));
    let line = fit.report.summary();
    assert!(line.contains("mean error") && !line.contains('\n'));
}

#[test]
fn encode_inverts_decode() {
    tch::manual_seed(1);
    let raw = Tensor::randn([1, 9, 4, 4], (Kind::Float, Device::Cpu));
    let back = encode(&decode(&raw));
    assert!(mean_abs(&raw, &back) < 1e-4, "{}", mean_abs(&raw, &back));
}

#[test]
fn bad_settings_and_targets_are_refused_in_one_line() {
    for cfg in [
        FitConfig { steps: MAX_FIT_STEPS + 1, ..Default::default() },
        FitConfig { samples: 4, ..Default::default() },
        FitConfig { learning_rate: f64::NAN, ..Default::default() },
        FitConfig { smooth_weight: -1.0, ..Default::default() },
    ] {
        let e = cfg.validate().unwrap_err().to_string();
        assert!(!e.contains('\n'), "{e}");
    }
    let (wi, wo) = sample_directions(8, 1, Device::Cpu);
    let t = Tensor::zeros([8, 3, 4, 4], (Kind::Float, Device::Cpu));
    let _ = t.get(0).get(0).get(0).fill_(f64::NAN);
    let e = fit_targets(&t, &wi, &wo, &FitConfig::default(), |_| {}).unwrap_err().to_string();
    assert!(e.contains("NaN"), "{e}");
    let e = fit_targets(&t.narrow(0, 0, 4), &wi, &wo, &FitConfig::default(), |_| {}).unwrap_err().to_string();
    assert!(e.contains("[4, 3]"), "{e}");
}

#[test]
fn metallic_conversion_is_exact_for_dielectrics_and_metals() {
    // Dielectric pixel (ks = 0.04) and metal pixel (kd = 0).
    let kd = Tensor::from_slice(&[0.5f32, 0.0, 0.3, 0.0, 0.1, 0.0]).view([3, 1, 2]);
    let ks = Tensor::from_slice(&[0.04f32, 0.9, 0.04, 0.6, 0.04, 0.3]).view([3, 1, 2]);
    let (base, metallic) = to_metallic(&kd, &ks);
    assert!((metallic.double_value(&[0, 0, 0]) - 0.0).abs() < 1e-6);
    assert!((metallic.double_value(&[0, 0, 1]) - 1.0).abs() < 1e-6);
    assert!((base.double_value(&[0, 0, 0]) - 0.5).abs() < 1e-5 && (base.double_value(&[2, 0, 1]) - 0.3).abs() < 1e-5);
    let (kd2, ks2) = from_metallic(&base, &metallic);
    assert!(mean_abs(&kd, &kd2) < 1e-5 && mean_abs(&ks, &ks2) < 1e-5);
    // An in-between: strong grey dielectric specular; the conversion is the least-squares compromise.
    let kd = Tensor::from_slice(&[0.3f32, 0.3, 0.3]).view([3, 1, 1]);
    let ks = Tensor::from_slice(&[0.1f32, 0.1, 0.1]).view([3, 1, 1]);
    let (base, metallic) = to_metallic(&kd, &ks);
    let (kd2, ks2) = from_metallic(&base, &metallic);
    let m = metallic.double_value(&[0, 0, 0]);
    assert!(m > 0.0 && m < 0.2, "metallic {m}");
    let err = (&kd2 - &kd).square().sum(Kind::Double).double_value(&[]) + (&ks2 - &ks).square().sum(Kind::Double).double_value(&[]);
    assert!(err < 3.0 * 0.06f64.powi(2), "squared error {err} not better than metallic 0");
}
