use super::*;
use crate::data::procedural::{generate_family, Family};
use crate::model::{Model, ModelConfig, ModelInfo};
use crate::svbrdf::scalar::{add, normalize, sub};

#[test]
fn case_samplers_are_deterministic_and_follow_the_protocol() {
    for case in [Sampling::Reflect, Sampling::Identity, Sampling::Hemisphere] {
        assert_eq!(case_configs(case, 5, 3, 16), case_configs(case, 5, 3, 16));
    }
    assert_ne!(case_configs(Sampling::Hemisphere, 5, 3, 16), case_configs(Sampling::Hemisphere, 6, 3, 16));
    assert_ne!(case_configs(Sampling::Hemisphere, 5, 3, 16), case_configs(Sampling::Hemisphere, 5, 4, 16));
    assert_ne!(case_configs(Sampling::Reflect, 5, 3, 16)[0].view, case_configs(Sampling::Hemisphere, 5, 3, 16)[0].view);
    // Hemisphere: light and view on the radius-4 upper hemisphere.
    let h = case_configs(Sampling::Hemisphere, 1, 0, 500);
    assert_eq!(h.len(), 500);
    for c in &h {
        for p in [c.light, c.view] {
            assert!((p.iter().map(|v| v * v).sum::<f64>().sqrt() - 4.0).abs() < 1e-9 && p[2] >= 0.0, "{p:?}");
        }
    }
    // Identity: one co-located configuration at d = 4.010781.
    let id = case_configs(Sampling::Identity, 1, 0, 128);
    assert_eq!(id.len(), 1);
    assert_eq!(id[0].light, id[0].view);
    assert!(id[0].light[0] == 0.0 && id[0].light[1] == 0.0 && (id[0].light[2] - 4.010781).abs() < 1e-6);
    // Reflect: the same stream as the training sampler, so h = n at the sampled point.
    let r = case_configs(Sampling::Reflect, 9, 2, 50);
    let mut rng = Pcg64::seed_from_u64(case_seed(9, 2, Sampling::Reflect));
    for c in &r {
        let (again, p) = sample_reflect(&mut rng, fov_to_distance(MODEL_FOV_DEG));
        assert_eq!(*c, again);
        let hv = normalize(add(normalize(sub(c.light, p)), normalize(sub(c.view, p))));
        assert!(hv[0].abs() < 1e-9 && hv[1].abs() < 1e-9 && (hv[2] - 1.0).abs() < 1e-9, "{hv:?}");
        assert!((c.view.iter().map(|v| v * v).sum::<f64>().sqrt() - 4.010781).abs() < 1e-5);
    }
}

/// Mean LPIPS of a method over a case's configurations on one material.
fn case_lpips(method: &mut dyn Method, m: &Svbrdf, case: Sampling, lpips: &Lpips) -> f64 {
    method.prepare(&input_photo(m, false)).unwrap();
    let cfg = case_configs(case, 0, 0, 16);
    mean_scores(&score_renders(lpips, &method.render(&cfg).unwrap(), &reference_renders(m, &cfg)).unwrap()).lpips
}

#[test]
fn printout_recreates_the_photo_but_not_new_lighting() {
    let lpips = Lpips::new(Device::Cpu).unwrap();
    let m = generate_family(Family::PolishedMetal, 7, 64);
    let mut p = PrintoutMethod::default();
    let id = case_lpips(&mut p, &m, Sampling::Identity, &lpips);
    let hemi = case_lpips(&mut p, &m, Sampling::Hemisphere, &lpips);
    eprintln!("printout on a polished metal: identity LPIPS {id:.6}, hemisphere LPIPS {hemi:.4}");
    assert!(id < 1e-3, "identity LPIPS {id}");
    assert!(hemi > 0.1 && hemi > 50.0 * id.max(1e-4), "hemisphere LPIPS {hemi} vs identity {id}");
    // The identity render is the photo itself.
    let photo = input_photo(&m, false);
    let again = p.render(&[LightView::colocated(MODEL_FOV_DEG)]).unwrap().get(0);
    assert!((again - &photo).abs().max().double_value(&[]) < 1e-4 * (1.0 + photo.max().double_value(&[])));
}

#[test]
fn fit_to_size_crops_and_resizes() {
    let m = Svbrdf::uniform(40, 48, [0.5, 0.4, 0.3], [0.04; 3], 0.3);
    let f = fit_to_size(&m, 32).unwrap();
    assert_eq!((f.height(), f.width()), (32, 32));
    assert!((f.normal.get(2, 5, 5) - 1.0).abs() < 1e-6);
    assert!((f.diffuse.get(0, 3, 3) - 0.5).abs() < 1e-6);
    let g = fit_to_size(&Svbrdf::uniform(24, 30, [0.5; 3], [0.04; 3], 0.3), 32).unwrap();
    assert_eq!((g.height(), g.width()), (32, 32));
}

#[test]
fn eval_end_to_end_on_two_materials() {
    let t = tempfile::tempdir().unwrap();
    tch::manual_seed(3);
    let model_path = t.path().join("tiny.safetensors");
    Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(&model_path, &ModelInfo::default(), false).unwrap();
    let out = t.path().join("report");
    let opts = EvalOptions {
        models: vec![model_path.to_string_lossy().into_owned(), PRINTOUT.into()],
        dataset: PROCEDURAL_TEST.into(),
        cases: vec![Sampling::Reflect, Sampling::Identity, Sampling::Hemisphere],
        out: out.clone(),
        size: 32,
        seed: 1,
        limit: Some(2),
        configs: 2,
        ldr_input: false,
        device: Device::Cpu,
        progress: false,
    };
    let results = run(&opts).unwrap();
    assert_eq!(results.len(), 2);
    for name in ["tiny.csv", "printout.csv", "summary.md", "best.png", "worst.png", "grids.txt"] {
        assert!(out.join(name).is_file(), "{name} missing");
    }
    let csv = std::fs::read_to_string(out.join("printout.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], "material,case,lpips,rmse_log,psnr");
    assert_eq!(lines.len(), 1 + 2 * 3);
    assert!(lines[1].starts_with("test00,reflect,"));
    assert!(lines[2].starts_with("test00,identity,"));
    assert!(lines[6].starts_with("test01,hemisphere,"));
    for l in &lines[1..] {
        let f: Vec<f64> = l.split(',').skip(2).map(|v| v.parse().unwrap()).collect();
        assert!(f.iter().all(|v| v.is_finite()), "{l}");
    }
    let tiny = std::fs::read_to_string(out.join("tiny.csv")).unwrap();
    assert_eq!(tiny.lines().count(), 7);
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("| Method | Reflect | Identity | Hemisphere |"), "{summary}");
    assert!(summary.contains("| printout |") && summary.contains("| tiny |"));
    // Same seed, same numbers.
    let again = run(&EvalOptions { out: t.path().join("again"), ..opts }).unwrap();
    assert_eq!(csv, std::fs::read_to_string(t.path().join("again/printout.csv")).unwrap());
    assert_eq!(tiny, std::fs::read_to_string(t.path().join("again/tiny.csv")).unwrap());
    assert_eq!(again[0].rows.len(), 6);
}
