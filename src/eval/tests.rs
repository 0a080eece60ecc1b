use super::*;
use crate::infer::refine::RefineConfig;
use crate::data::procedural::{generate_family, Family};
use crate::model::{Model, ModelConfig, ModelInfo};
use crate::geometry::{add, normalize, sub};

/// All three cases on 2 held-out materials at 32x32, 2 configurations.
fn small_eval(models: Vec<String>, out: &std::path::Path) -> EvalOptions {
    EvalOptions {
        models,
        dataset: PROCEDURAL_TEST.into(),
        cases: vec![Sampling::Reflect, Sampling::Identity, Sampling::Hemisphere],
        out: out.to_path_buf(),
        size: 32,
        seed: 1,
        limit: Some(2),
        configs: 2,
        ldr_input: false,
        device: Device::Cpu,
        progress: false,
        refine: vec![],
        exposures: vec![0.0],
        exposure: crate::infer::ExposureConfig::default(),
        highlight_fill: None,
        phone_photos: None,
    }
}

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
    let opts = small_eval(vec![model_path.to_string_lossy().into_owned(), PRINTOUT.into()], &out);
    let results = run(&opts).unwrap().results;
    assert_eq!(results.len(), 2);
    for name in ["tiny.csv", "printout.csv", "summary.md", "best.jpg", "worst.jpg", "grids.txt"] {
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
    // The moved-highlight test and the identity ratio, for every method; the
    // folder's own *.csv stay the methods' (so `--summarize` reads them back).
    assert!(summary.contains("## Moved highlights") && summary.contains("## Exposure"), "{summary}");
    for r in &results {
        assert_eq!((r.highlights.len(), r.exposure.len()), (2, 2), "{}", r.name);
        assert!(r.highlights.iter().all(|h| h.rest.is_some_and(|v| v > 0.0)));
    }
    assert!(results[1].exposure.iter().all(|e| (e.ratio - 1.0).abs() < 1e-5), "{:?}", results[1].exposure);
    assert_eq!(std::fs::read_to_string(out.join("highlights/ratios.csv")).unwrap().lines().count(), 1 + 2 * 2);
    assert_eq!(std::fs::read_to_string(out.join("exposure/curve.csv")).unwrap().lines().count(), 1 + 2 * 2);
    assert!(out.join("highlights/moved.jpg").is_file() && out.join("highlights/moved.txt").is_file());
    // Same seed, same numbers.
    let again = run(&EvalOptions { out: t.path().join("again"), ..opts }).unwrap().results;
    assert_eq!(csv, std::fs::read_to_string(t.path().join("again/printout.csv")).unwrap());
    assert_eq!(tiny, std::fs::read_to_string(t.path().join("again/tiny.csv")).unwrap());
    assert_eq!(again[0].rows.len(), 6);
}

/// A dataset with an unreadable material among good ones: the others are
/// scored, the bad one named in the result and in `summary.md` (which
/// `--summarize` keeps); a dataset of unreadable ones only is an error
/// naming the material.
#[test]
fn unreadable_dataset_materials_are_skipped_and_named() {
    let t = tempfile::tempdir().unwrap();
    let data = t.path().join("data");
    for name in ["a", "b", "c"] {
        crate::data::loaders::write_material_dir(&data.join(name), &Svbrdf::uniform(16, 16, [0.3; 3], [0.04; 3], 0.4)).unwrap();
    }
    std::fs::write(data.join("b/normals.png"), b"not a png").unwrap();
    let out = t.path().join("report");
    let opts = EvalOptions { dataset: data.to_string_lossy().into_owned(), cases: vec![Sampling::Identity], limit: None, ..small_eval(vec![PRINTOUT.into()], &out) };
    let done = run(&opts).unwrap();
    assert_eq!(done.materials, 2);
    assert_eq!(done.skipped.iter().map(|u| u.name.as_str()).collect::<Vec<_>>(), ["b"]);
    assert!(done.skipped[0].reason.contains("b/normals.png"), "{:?}", done.skipped);
    let csv = std::fs::read_to_string(out.join("printout.csv")).unwrap();
    let materials: Vec<&str> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap()).collect();
    assert_eq!(materials, ["a", "c"]);
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("2 materials (1 unreadable left out, named at the end)"), "{summary}");
    let section = &summary[summary.find("## Skipped materials").expect("a Skipped materials section")..];
    assert!(section.contains("- `b`: ") && section.contains("b/normals.png"), "{section}");
    report::resummarize(&opts).unwrap();
    let resummary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(resummary.contains("(1 unreadable left out") && resummary.ends_with(section), "{resummary}");

    let bad = t.path().join("bad");
    crate::data::loaders::write_material_dir(&bad.join("x"), &Svbrdf::uniform(16, 16, [0.3; 3], [0.04; 3], 0.4)).unwrap();
    std::fs::write(bad.join("x/normals.png"), b"not a png").unwrap();
    let e = format!("{:#}", run(&EvalOptions { dataset: bad.to_string_lossy().into_owned(), out: t.path().join("none"), ..opts }).unwrap_err());
    assert!(e.starts_with("material x: ") && e.contains("x/normals.png"), "{e}");
}

#[test]
fn refine_variants_are_scored_as_their_own_rows() {
    let t = tempfile::tempdir().unwrap();
    tch::manual_seed(2);
    let model_path = t.path().join("tiny.safetensors");
    Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(&model_path, &ModelInfo::default(), false).unwrap();
    let model = model_path.to_string_lossy().into_owned();
    let out = t.path().join("refined");
    let opts = EvalOptions {
        cases: vec![Sampling::Identity],
        refine: vec![RefineConfig::with_steps(0), RefineConfig::with_steps(40)],
        ..small_eval(vec![model.clone(), PRINTOUT.into()], &out)
    };
    let results = run(&opts).unwrap().results;
    let names: Vec<&str> = results.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(names, ["tiny", "tiny+refine40", "printout"]);
    // The refinement fits the identity render: lower log error on every material.
    for (plain, refined) in results[0].rows.iter().zip(&results[1].rows) {
        assert!(refined.scores.rmse_log < 0.7 * plain.scores.rmse_log, "{plain:?} -> {refined:?}");
    }
    assert!(out.join("tiny+refine40.csv").is_file());
    // The chart's points are the summary's means, at steps 0 and 40.
    let series = report::refine_series(&opts, &results);
    assert_eq!(series.len(), 1);
    assert_eq!(series[0].points.iter().map(|p| p.0).collect::<Vec<_>>(), [0.0, 40.0]);
    let mean = |r: &MethodResults| r.rows.iter().map(|x| x.scores.lpips).sum::<f64>() / r.rows.len() as f64;
    assert!((series[0].points[1].1 - mean(&results[1])).abs() < 1e-9);
    let chart = crate::io::read_image(&out.join("refine.png")).unwrap();
    assert_eq!((chart.width, chart.height), (640, 360));
    // Re-reading the CSVs gives back the same summary.
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    std::fs::remove_file(out.join("summary.md")).unwrap();
    let again = report::resummarize(&opts).unwrap();
    assert_eq!(again.iter().map(|r| r.name.as_str()).collect::<Vec<_>>(), ["printout", "tiny", "tiny+refine40"]);
    let resummary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    for r in &results {
        let line = |s: &str| s.lines().find(|l| l.starts_with(&format!("| {} |", r.name))).unwrap().to_string();
        assert_eq!(line(&summary), line(&resummary));
    }
    // Without 0 in the list only the refined variant is scored.
    let only = run(&EvalOptions { refine: vec![RefineConfig::with_steps(5)], out: t.path().join("only"), ..small_eval(vec![model], &out) }).unwrap().results;
    assert_eq!(only.iter().map(|r| r.name.as_str()).collect::<Vec<_>>(), ["tiny+refine5"]);
}

// ---------------------------------------------------------------------------
// The trained baselines as evaluation methods.
// ---------------------------------------------------------------------------

use crate::baselines::{Baseline, BaselineNet, TrainMethod};

#[test]
fn analytic_method_renders_are_the_ggx_renders_of_its_maps() {
    tch::manual_seed(4);
    let b = Baseline::new(TrainMethod::Analytic, &ModelConfig::tiny(), Device::Cpu).unwrap();
    let mut method = AnalyticMethod::new("analytic".into(), &b, ModelInfo::default()).unwrap();
    let m = generate_family(Family::Stone, 2, 32);
    let photo = input_photo(&m, false);
    method.prepare(&photo).unwrap();
    let maps = method.maps().unwrap();
    assert_eq!(maps.size(), [10, 32, 32]);
    // The folded-BatchNorm inference maps equal the network's eval-mode maps.
    let BaselineNet::Analytic(a) = &b.net else { panic!() };
    let (wi, wo) = crate::data::samples::input_directions(32, 32, MODEL_FOV_DEG, Device::Cpu);
    let x = crate::data::samples::est_input(&photo.unsqueeze(0), &crate::svbrdf::render::half_vector_z(&wi, &wo));
    let unfolded = tch::no_grad(|| a.maps_t(&x, false).unwrap()).get(0);
    // (An untrained network's eval-mode head outputs reach hundreds, so
    // float rounding of the folded convolutions shows at 1e-4.)
    let d = (&maps - &unfolded).abs().max().double_value(&[]);
    assert!(d < 1e-3, "folded maps differ by {d}");
    // Renders = the f32 CPU GGX renderer applied to the predicted maps.
    let estimated = Svbrdf::from_stacked(&crate::image::Image::from_tensor(&maps).unwrap()).unwrap();
    let mut configs = case_configs(Sampling::Hemisphere, 0, 0, 6);
    configs.extend(case_configs(Sampling::Reflect, 0, 0, 5));
    configs.push(LightView::colocated(MODEL_FOV_DEG));
    let pred = method.render(&configs).unwrap();
    assert_eq!(pred.size(), [12, 3, 32, 32]);
    let expect = reference_renders(&estimated, &configs);
    let rel = ((&pred - &expect).abs() / expect.abs().clamp_min(1e-3)).max().double_value(&[]);
    assert!(rel < 1e-3, "relative difference {rel}");
    assert!(pred.max().double_value(&[]) > 0.0);
}

#[test]
fn relight_method_renders_are_the_network_output() {
    tch::manual_seed(5);
    let b = Baseline::new(TrainMethod::RelightUnet, &ModelConfig::tiny(), Device::Cpu).unwrap();
    let m = generate_family(Family::Leather, 1, 32);
    let photo = input_photo(&m, false);
    // 11 configurations: more than one render chunk.
    let configs = case_configs(Sampling::Hemisphere, 0, 1, 11);
    let (wi, wo) = {
        let (l, v) = crate::geometry::config_tensors(&configs, Device::Cpu);
        crate::svbrdf::render::direction_maps_for(&l.view([1, 11, 3]), &v.view([1, 11, 3]), 32, 32)
    };
    let (iwi, iwo) = crate::data::samples::input_directions(32, 32, MODEL_FOV_DEG, Device::Cpu);
    let x = crate::data::samples::est_input(&photo.unsqueeze(0), &crate::svbrdf::render::half_vector_z(&iwi, &iwo));
    let log = tch::no_grad(|| b.forward_t(&x, &wi, &wo, false).unwrap()).get(0);
    let mut method = RelightMethod::new("relight-unet".into(), b, ModelInfo::default()).unwrap();
    assert!(method.render(&configs).is_err(), "render before prepare");
    method.prepare(&photo).unwrap();
    let pred = method.render(&configs).unwrap();
    assert_eq!(pred.size(), [11, 3, 32, 32]);
    // Compared in log space: an untrained decoder reaches the clamp (log
    // radiance 80), where float32 sums that reorder with the thread count
    // differ by ~1e-4 (a few ulps at 80), i.e. ~1e30 in radiance.
    let expect_log = log.clamp(0.0, crate::infer::nmat::MAX_LOG_RADIANCE);
    assert!((pred.log1p() - &expect_log).abs().max().double_value(&[]) < 1e-3);
    assert!(pred.min().double_value(&[]) >= 0.0);
}

#[test]
fn eval_scores_baseline_model_files() {
    let t = tempfile::tempdir().unwrap();
    tch::manual_seed(6);
    let info = ModelInfo { ldr_input: false, steps: 1 };
    let flashmat = t.path().join("flashmat.safetensors");
    Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(&flashmat, &info, false).unwrap();
    let analytic = t.path().join("analytic.safetensors");
    Baseline::new(TrainMethod::Analytic, &ModelConfig::tiny(), Device::Cpu).unwrap().save(&analytic, &info, true).unwrap();
    let relight = t.path().join("relight-unet.safetensors");
    Baseline::new(TrainMethod::RelightUnet, &ModelConfig::tiny(), Device::Cpu).unwrap().save(&relight, &info, false).unwrap();
    let out = t.path().join("report");
    let models = [&flashmat, &analytic, &relight].map(|p| p.to_string_lossy().into_owned());
    let opts = small_eval(vec![models[0].clone(), PRINTOUT.into(), models[1].clone(), models[2].clone()], &out);
    let results = run(&opts).unwrap().results;
    let names: Vec<&str> = results.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(names, ["flashmat", "printout", "analytic", "relight-unet"]);
    for name in ["analytic", "relight-unet"] {
        let csv = std::fs::read_to_string(out.join(format!("{name}.csv"))).unwrap();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + 2 * 3, "{csv}");
        for l in &lines[1..] {
            let f: Vec<f64> = l.split(',').skip(2).map(|v| v.parse().unwrap()).collect();
            assert!(f.len() == 3 && f.iter().all(|v| v.is_finite()), "{name}: {l}");
            assert!(f[0] > 0.0, "{name}: an untrained network matches the reference exactly? {l}");
        }
    }
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    for row in ["| flashmat |", "| printout |", "| analytic |", "| relight-unet |"] {
        assert!(summary.contains(row), "{row} missing from {summary}");
    }
    // Deterministic: the same run gives the same numbers.
    run(&EvalOptions { out: t.path().join("again"), ..opts.clone() }).unwrap();
    for name in ["analytic", "relight-unet"] {
        let a = std::fs::read_to_string(out.join(format!("{name}.csv"))).unwrap();
        assert_eq!(a, std::fs::read_to_string(t.path().join(format!("again/{name}.csv"))).unwrap());
    }
    // A file claiming an unknown method is refused with its name.
    let mut bad = crate::archive::Archive::load(&relight, crate::model::MODEL_FORMAT, crate::model::MODEL_VERSION).unwrap();
    bad.set_meta(crate::model::file::METHOD_KEY, "matfusion");
    let bad_path = t.path().join("bad.safetensors");
    bad.save(&bad_path, crate::model::MODEL_FORMAT, crate::model::MODEL_VERSION).unwrap();
    let e = format!("{:#}", run(&EvalOptions { models: vec![bad_path.to_string_lossy().into_owned()], out: t.path().join("bad"), ..opts }).unwrap_err());
    assert!(e.contains("matfusion"), "{e}");
}

#[test]
fn the_one_csv_of_an_eval_folder_is_found_and_ambiguity_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    assert!(report::csv_in(d).unwrap_err().to_string().contains("found 0"));
    std::fs::write(d.join("m.csv"), "x").unwrap();
    std::fs::write(d.join("summary.md"), "x").unwrap();
    assert_eq!(report::csv_in(d).unwrap(), d.join("m.csv"));
    assert_eq!(report::csv_in(&d.join("m.csv")).unwrap(), d.join("m.csv"));
    std::fs::write(d.join("n.csv"), "x").unwrap();
    assert!(report::csv_in(d).unwrap_err().to_string().contains("found 2"));
}

#[test]
fn phone_photos_are_drawn_per_material_and_scored_against_the_same_truths() {
    let t = tempfile::tempdir().unwrap();
    let opts = EvalOptions { ldr_input: true, phone_photos: Some(Default::default()), cases: vec![Sampling::Identity], ..small_eval(vec![PRINTOUT.into()], t.path()) };
    let m = crate::data::procedural::test_material(0, 32);
    let (linear, photo) = material_photo(&m, 0, &opts).unwrap();
    let (again_linear, again) = material_photo(&m, 0, &opts).unwrap();
    assert_eq!(f64::try_from((&photo - &again).abs().max()).unwrap(), 0.0, "one draw per material and seed");
    assert_eq!(f64::try_from((&linear - &again_linear).abs().max()).unwrap(), 0.0);
    let other = material_photo(&m, 1, &opts).unwrap().1;
    assert!(f64::try_from((&photo - &other).abs().max()).unwrap() > 0.0, "another index draws another photo");
    // The photo is the render, noised and on the 8-bit sRGB grid.
    for v in Vec::<f32>::try_from(photo.flatten(0, -1)).unwrap() {
        let code = (crate::spaces::photo_encode(v) * 255.0).round();
        assert!((crate::spaces::photo_decode(code / 255.0) - v).abs() < 1e-6, "{v}");
    }
    let plain = material_photo(&m, 0, &EvalOptions { phone_photos: None, ..opts.clone() }).unwrap();
    assert!(f64::try_from((&plain.0 - &linear).abs().max()).unwrap() > 0.0, "the phone's render is not the co-located one");
    let mean_gap = f64::try_from((crate::spaces::ldr_clamp(&linear) - &photo).abs().mean(tch::Kind::Float)).unwrap();
    assert!(mean_gap < 0.02, "{mean_gap}");
    // The run scores them and says so; a phone photo without --ldr-input is refused.
    let results = run(&opts).unwrap().results;
    assert_eq!(results[0].rows.len(), 2);
    assert!(std::fs::read_to_string(t.path().join("summary.md")).unwrap().contains("phone (8-bit sRGB"));
    let e = run(&EvalOptions { ldr_input: false, ..opts }).unwrap_err().to_string();
    assert!(e.contains("--phone-photos needs --ldr-input"), "{e}");
}
