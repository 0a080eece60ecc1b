//! End-to-end checks of the bundled model (`models/flashmat.safetensors`)
//! on held-out procedural materials: render a flash photo, `flashmat estimate`
//! it, `flashmat relight` the material, and compare with the true renders.
//!
//! The thresholds are what the bundled models meet (measured values in
//! models/MODEL.md), with some margin; each is also checked against a
//! baseline that knows nothing about the material's reflectance (a flat image
//! of the photo's mean colour), so a model that learned nothing fails.

use flashmat::geometry::LightView;
use flashmat::image::Image;
use flashmat::infer::{overhead_camera, NeuralMaterial};
use std::path::Path;
use std::process::Command;

/// Held-out materials (seeds the training never draws) used by the checks.
const MATERIALS: [usize; 3] = [0, 7, 19];

/// Largest accepted ratio of the model's error to the flat image's.
const FLAT_RATIO_MAX: f64 = 2.2;

/// A side light, well away from the co-located input configuration.
const SIDE_LIGHT: [f64; 3] = [1.5, 1.0, 2.5];

fn flashmat(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_flashmat")).args(args).output().expect("run flashmat");
    assert!(out.status.success(), "flashmat {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
}

/// Mean absolute difference of log(1 + radiance), the tone-mapped error
/// that weighs highlights and dark regions alike.
fn log_error(a: &Image, b: &Image) -> f64 {
    flashmat::eval::metrics::log_l1(a, b).unwrap()
}

/// The same image with every pixel replaced by its per-channel mean.
fn flat_mean(im: &Image) -> Image {
    let n = (im.height * im.width) as f32;
    let means: Vec<f32> = (0..im.channels).map(|c| (0..im.height).flat_map(|y| (0..im.width).map(move |x| (y, x))).map(|(y, x)| im.get(c, y, x)).sum::<f32>() / n).collect();
    Image::from_fn(im.channels, im.height, im.width, |c, _, _| means[c])
}

struct RoundTrip {
    identity_error: f64,
    identity_baseline: f64,
    relit_error: f64,
    relit_baseline: f64,
}

/// Photo of held-out material `index` -> estimate with the bundled model ->
/// identity and side-lit renders, compared with the true renders. `ldr`:
/// an 8-bit PNG photo (compared up to 1) rather than an EXR.
fn round_trip(dir: &Path, index: usize, ldr: bool) -> RoundTrip {
    let seed = flashmat::data::procedural::test_seeds()[index];
    let material = flashmat::data::procedural::generate(seed, &flashmat::data::procedural::ProceduralConfig::with_size(256));
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let side = LightView { light: SIDE_LIGHT, view: overhead_camera() };
    let truth = flashmat::svbrdf::render::render_material(&material, &[identity, side]).unwrap();
    let photo = if ldr { dir.join(format!("photo{index}.png")) } else { dir.join(format!("photo{index}.exr")) };
    if ldr {
        flashmat::io::write_png(&photo, &truth[0].map(flashmat::spaces::srgb_encode), flashmat::io::BitDepth::Eight).unwrap();
    } else {
        flashmat::io::write_exr(&photo, &truth[0]).unwrap();
    }
    let nmat = dir.join(format!("m{index}{}.nmat", if ldr { "l" } else { "h" }));
    // The render has the model's own 28 degree view: no crop.
    flashmat(&["estimate", photo.to_str().unwrap(), "--fov", "28", "-o", nmat.to_str().unwrap()]);
    let m = NeuralMaterial::load(&nmat, tch::Device::Cpu).unwrap();
    let renders: Vec<Image> = [identity, side].iter().map(|c| m.render_image(c).unwrap()).collect();
    // An 8-bit photo only shows radiance up to 1: compare there.
    let clamp = |im: &Image| if ldr { im.map(|v| v.min(1.0)) } else { im.clone() };
    let (t_id, t_side) = (clamp(&truth[0]), clamp(&truth[1]));
    RoundTrip {
        identity_error: log_error(&clamp(&renders[0]), &t_id),
        identity_baseline: log_error(&flat_mean(&t_id), &t_id),
        relit_error: log_error(&clamp(&renders[1]), &t_side),
        relit_baseline: log_error(&flat_mean(&t_side), &t_side),
    }
}

fn check(ldr: bool, identity_max: f64, relit_max: f64) {
    let dir = tempfile::tempdir().unwrap();
    let trips: Vec<RoundTrip> = MATERIALS.iter().map(|&i| round_trip(dir.path(), i, ldr)).collect();
    let mean = |f: fn(&RoundTrip) -> f64| trips.iter().map(f).sum::<f64>() / trips.len() as f64;
    let (id, id_base) = (mean(|t| t.identity_error), mean(|t| t.identity_baseline));
    let (relit, relit_base) = (mean(|t| t.relit_error), mean(|t| t.relit_baseline));
    eprintln!("{}: identity {id:.4} (flat baseline {id_base:.4}), side light {relit:.4} (flat baseline {relit_base:.4})", if ldr { "8-bit photos" } else { "EXR photos" });
    assert!(id < identity_max, "identity round-trip log error {id:.4} >= {identity_max}");
    assert!(relit < relit_max, "relit log error {relit:.4} >= {relit_max}");
    assert!(id < FLAT_RATIO_MAX * id_base, "identity {id:.4} is more than {FLAT_RATIO_MAX} x the flat image's ({id_base:.4})");
    assert!(relit < FLAT_RATIO_MAX * relit_base, "relit {relit:.4} is more than {FLAT_RATIO_MAX} x the flat image's ({relit_base:.4})");
}

#[test]
fn bundled_model_round_trips_exr_photos_of_held_out_materials() {
    // Measured with the bundled (LDR-trained, 45,660 steps: four GPU jobs
    // of the halves trained alone in turn) model, which clamps the EXR
    // photo: identity 0.0285, side light 0.0407 (flat image 0.0917, 0.0588)
    // with the exposure calibrated (issue 53); 0.0294, 0.0425 before;
    // 41,607 steps (the renderer settled on the CPU): 0.0339, 0.0411; 36,181 steps: 0.0348, 0.0412; 33,000 steps: 0.0390, 0.0413; 26,500 steps:
    // 0.0445, 0.0435; 24,115 steps, 8 direction frequencies: 0.0439,
    // 0.0448; with 16 frequencies 0.0495,
    // 0.0453 (the HDR identity render had the co-located spike). The 13,500-step model: 0.0732, 0.0553; the 10,400-step
    // one 0.0813, 0.0621; the 4,000-step one 0.0722, 0.0531 (these three
    // materials favoured it over the two CPU models after it: one is green
    // tiles, which they turned teal). The HDR-trained model of 4,000 steps,
    // bundled for EXR photos until 2026-11-23, measured 0.0743, 0.0616.
    check(false, 0.036, 0.048);
}

#[test]
fn bundled_model_round_trips_8_bit_photos_of_held_out_materials() {
    // Measured (45,660 steps): identity 0.0213, side light 0.0378 (flat
    // image 0.0607, 0.0437) with the exposure calibrated (issue 53), 0.0220,
    // 0.0397 before; 41,607 steps: 0.0268, 0.0382; 36,181 steps: 0.0276, 0.0383; 33,000 steps: 0.0319, 0.0384; 26,500 steps: 0.0374, 0.0406; 24,115 steps,
    // 8 frequencies: 0.0333, 0.0420;
    // 16 frequencies: 0.0332, 0.0423. At 13,500 steps: 0.0543, 0.0507; at
    // 10,400: 0.0645, 0.0586; at 4,000: 0.0626, 0.0500; at 1,785: 0.1065, 0.0841.
    check(true, 0.028, 0.045);
}

/// The co-located highlights of the uniform-colour check's near-black
/// materials (`flashmat eval --uniform`): the brightest 1% of the identity
/// render's pixels, unclamped, over the truth's. Measured at 256x256 with
/// the 45,660-step model: glossy 1.20x, matte 1.83x; 41,607 steps: glossy
/// 0.84x, matte 1.86x; 36,181 steps: glossy
/// 1.05x, matte 1.73x; 33,000 steps: glossy
/// 0.60x, matte 1.77x; 26,500 steps
/// (renderer trained on co-located outputs): glossy 1.39x, matte 2.41x;
/// 24,115 steps with 8 direction frequencies: 7.15x,
/// 5.95x; with 16 frequencies: 15.45x, 50.66x (`reports/frequencies.md`:
/// where light and view meet along the normal every high-frequency cosine
/// is 1 and the renderer spikes). Bounds: both within 2x (issue 15's
/// target); the glossy one's chromaticity error below 0.05 (0.014).
#[test]
fn bundled_model_keeps_the_co_located_highlight_spike_down() {
    use flashmat::eval::uniform::{colour_check, summarize};
    let loaded = flashmat::infer::load_model(None, tch::Device::Cpu).unwrap();
    let rows = colour_check(&loaded.model, &loaded.info, 256).unwrap();
    let identity = |set: &str| rows.iter().find(|r| r.set == set && r.material == "near-black" && r.render == "identity").unwrap();
    let (glossy, matte) = (identity("glossy"), identity("matte"));
    eprintln!("near-black identity highlight: glossy {:.2}x, matte {:.2}x the truth", glossy.highlight_ratio, matte.highlight_ratio);
    assert_eq!(summarize(&rows).near_black_highlight_ratio, glossy.highlight_ratio);
    assert_eq!(summarize(&rows).near_black_matte_highlight_ratio, matte.highlight_ratio);
    assert!(glossy.highlight_ratio > 0.5 && glossy.highlight_ratio < 2.0, "{}", glossy.highlight_ratio);
    assert!(matte.highlight_ratio > 0.5 && matte.highlight_ratio < 2.0, "{}", matte.highlight_ratio);
    assert!(glossy.chroma_error < 0.05, "{}", glossy.chroma_error);
}

/// The committed model opens as the method, model and step count its
/// recipe (models/MODEL.md) says.
#[test]
fn bundled_model_records_its_method_and_steps() {
    use flashmat::model::file::{read_header_metadata, METHOD_KEY};
    let root = flashmat::infer::models_dir();
    for (file, method, steps, ldr) in [
        ("flashmat.safetensors", "flashmat", "45660", true),
    ] {
        let meta = read_header_metadata(&root.join(file)).unwrap();
        assert_eq!(meta.get(METHOD_KEY).map(String::as_str), Some(method), "{file}: {meta:?}");
        let info = meta.get("info").cloned().unwrap_or_default();
        assert!(info.contains(&format!("\"steps\":{steps}")) && info.contains(&format!("\"ldr_input\":{ldr}")), "{file}: {info}");
        let opened = flashmat::eval::open_model_file(&root.join(file), "m".into(), false, tch::Device::Cpu).unwrap();
        assert_eq!(opened.name(), "m");
    }
}

/// A 3:2 photo is estimated as a 3:2 material (the shorter side spans
/// [-1, 1], the longer [-1.5, 1.5]) whose identity render matches the photo
/// about as well as the square photo of the rectangle's centre does.
///
/// One held-out material, 256 x 384 maps rendered co-located at the
/// rectangle's geometry; its centre 256 x 256 rendered at the square's
/// geometry is the same surface under the same light (the centre square of
/// the rectangle spans [-1, 1]^2). Both are prepared at --size 64 (64 x 96
/// and 64 x 64) and estimated with the bundled model. Measured mean
/// |ln(1 + R) - ln(1 + photo)| (the photo clamped at 1, as the LDR model
/// sees it), bundled model of 45,660 steps (`models/MODEL.md`): rectangle
/// 0.0199, square 0.0230, the rectangle's centre 64 x 64 0.0215 (the
/// photos' centres agree to 1.8e-9; 41,607 steps: 0.0198, 0.0213, 0.0201;
/// 36,181 steps: 0.0235, 0.0253, 0.0247;
/// 33,000 steps: 0.0253, 0.0278, 0.0284;
/// 26,500 steps: 0.0309, 0.0326, 0.0351;
/// 24,115 steps, 8 frequencies: 0.0255, 0.0266, 0.0278; with 16
/// frequencies 0.0256, 0.0269,
/// 0.0279; the 13,500-step model: 0.0648, 0.0673, 0.0675; the 10,400-step
/// one: 0.0911, 0.0918, 0.0933; the 4,000-step one 0.0633, 0.0719, 0.0732
/// on this green tile material). Bounds: each
/// within 1.1 x its measurement + 0.002, and the rectangle within 1.3 x
/// the square.
#[test]
fn a_three_by_two_photo_is_estimated_as_a_three_by_two_material() {
    use flashmat::data::procedural::{generate, test_seeds, ProceduralConfig};
    let material = generate(test_seeds()[7], &ProceduralConfig::with_size(384));
    let rect = material.crop(64, 0, 256, 384).unwrap();
    let square = material.crop(64, 64, 256, 256).unwrap();
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let loaded = flashmat::infer::load_model(None, tch::Device::Cpu).unwrap();
    let estimate = |m: &flashmat::svbrdf::Svbrdf| {
        let photo = flashmat::svbrdf::render::render_material(m, &[identity]).unwrap().remove(0).map(|v| v.clamp(0.0, 1.0));
        let (linear, crop) = flashmat::infer::prepare_image(&photo, 28.0, 64).unwrap();
        let prepared = flashmat::infer::PreparedPhoto { crop, ..flashmat::infer::PreparedPhoto::at_model_view(linear, true, "p.png") };
        let nm = flashmat::infer::estimate(&loaded.model, &loaded.info, &prepared).unwrap();
        let render = nm.render_image(&identity).unwrap().map(|v| v.min(1.0));
        (nm, render, prepared.linear)
    };
    let (rm, r_render, r_photo) = estimate(&rect);
    let (sm, s_render, s_photo) = estimate(&square);
    assert_eq!((rm.size(), sm.size()), ((64, 96), (64, 64)));
    assert_eq!((rm.meta.crop.width, rm.meta.crop.height), (384, 256));
    let r_err = log_error(&r_render, &r_photo);
    let s_err = log_error(&s_render, &s_photo);
    let centre = |im: &Image| im.crop(0, 16, 64, 64).unwrap();
    let c_err = log_error(&centre(&r_render), &centre(&r_photo));
    // The rectangle's centre is the square's surface: the photos agree.
    let photo_diff = log_error(&centre(&r_photo), &s_photo);
    eprintln!("3:2 photo: identity log error rectangle {r_err:.4}, square {s_err:.4}, rectangle centre {c_err:.4}; photos' centres differ by {photo_diff:.2e}");
    assert!(photo_diff < 1e-3, "{photo_diff}");
    let within = |got: f64, measured: f64| got < 1.1 * measured + 0.002;
    assert!(within(r_err, 0.0199) && within(s_err, 0.0230) && within(c_err, 0.0215), "{r_err} {s_err} {c_err}");
    assert!(r_err < 1.3 * s_err, "rectangle {r_err:.4} vs square {s_err:.4}");
}

/// 8-bit photos are sRGB (what cameras write); `flashmat estimate` decodes
/// them with the exact curve. Held-out materials rendered, written as
/// sRGB 8-bit PNGs, and estimated at 128 pixels after the exact decode
/// (`load_photo`) and after the former ^2.2 decode; both compared with the
/// true identity and side-lit renders (clamped at 1) in mean |ln(1+R)|.
/// Measured (materials 0, 7, 19; bundled model of 45,660 steps): exact
/// decode identity 0.0227, side light 0.0383; ^2.2 decode 0.0228, 0.0388
/// (41,607 steps: 0.0248, 0.0376; 0.0249, 0.0384; 36,181 steps: 0.0252, 0.0377; 0.0258, 0.0386; 33,000 steps: 0.0293, 0.0376; 0.0299, 0.0385; 26,500 steps: 0.0345, 0.0388; 0.0351, 0.0399; 24,115 steps, 8 frequencies: 0.0340, 0.0410; 0.0341, 0.0420; 16 frequencies: 0.0343, 0.0416; 0.0344, 0.0426;
/// 13,500 steps: 0.0540, 0.0522; 0.0535, 0.0522; 10,400 steps: 0.0666,
/// 0.0591; 0.0657, 0.0592): the bundled
/// model (trained on clamped linear renders, no 8-bit curve) barely
/// notices; the exact curve is what the file holds. Bounds: the exact
/// decode within 1.1 x + 0.002.
#[test]
fn srgb_photos_are_decoded_with_the_exact_curve() {
    use flashmat::data::procedural::{generate, test_seeds, ProceduralConfig};
    let dir = tempfile::tempdir().unwrap();
    let loaded = flashmat::infer::load_model(None, tch::Device::Cpu).unwrap();
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let side = LightView { light: SIDE_LIGHT, view: overhead_camera() };
    let (mut exact, mut gamma) = ([0.0f64; 2], [0.0f64; 2]);
    for &i in &MATERIALS {
        let m = generate(test_seeds()[i], &ProceduralConfig::with_size(128));
        let truth: Vec<Image> = flashmat::svbrdf::render::render_material(&m, &[identity, side]).unwrap().into_iter().map(|t| t.map(|v| v.min(1.0))).collect();
        let png = dir.path().join(format!("p{i}.png"));
        flashmat::io::write_png(&png, &truth[0].map(flashmat::spaces::srgb_encode), flashmat::io::BitDepth::Eight).unwrap();
        let new = flashmat::infer::load_photo(&png, Some(28.0), 128).unwrap();
        let mut old = new.clone();
        old.linear = flashmat::io::read_rgb(&png).unwrap().map(flashmat::spaces::gamma_decode);
        for (photo, acc) in [(&new, &mut exact), (&old, &mut gamma)] {
            let nm = flashmat::infer::estimate(&loaded.model, &loaded.info, photo).unwrap();
            for (k, cfg) in [identity, side].iter().enumerate() {
                acc[k] += log_error(&nm.render_image(cfg).unwrap().map(|v| v.min(1.0)), &truth[k]) / MATERIALS.len() as f64;
            }
        }
    }
    eprintln!("8-bit sRGB photos: exact decode identity {:.4} side {:.4}; ^2.2 decode identity {:.4} side {:.4}", exact[0], exact[1], gamma[0], gamma[1]);
    assert!(exact[0] < 1.1 * 0.0227 + 0.002 && exact[1] < 1.1 * 0.0383 + 0.002, "{exact:?}");
    // The two decodes differ (dark codes most: 10/255 -> 0.00304 sRGB, 0.00081 ^2.2).
    assert!((exact[0] - gamma[0]).abs() + (exact[1] - gamma[1]).abs() > 1e-5, "{exact:?} {gamma:?}");
}

/// M_est layer by layer over tiles (each instance norm with its whole
/// input's statistics) against the whole forward on a 512 x 512 photo,
/// bundled model, tiles of 128 (4 x 4 at full resolution): identity renders
/// compared in ln(1 + R). Measured: mean 5.1e-8, max 4.1e-6 (float
/// rounding only); bound 1e-4 on the max.
#[test]
fn tiled_estimate_matches_the_whole_estimate() {
    use flashmat::data::procedural::{generate, test_seeds, ProceduralConfig};
    use flashmat::infer::{estimate_planned, EstPlan, ExposureConfig};
    let m = generate(test_seeds()[7], &ProceduralConfig::with_size(512));
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let photo = flashmat::svbrdf::render::render_material(&m, &[identity]).unwrap().remove(0).map(|v| v.clamp(0.0, 1.0));
    let prepared = flashmat::infer::PreparedPhoto::at_model_view(photo, true, "p.png");
    let loaded = flashmat::infer::load_model(None, tch::Device::Cpu).unwrap();
    let log_render = |plan: &EstPlan| {
        let nm = estimate_planned(&loaded.model, &loaded.info, &prepared, plan, &ExposureConfig::default(), || ()).unwrap();
        nm.render(&[identity]).unwrap().log1p()
    };
    let whole = log_render(&EstPlan::Whole);
    let tiled = log_render(&EstPlan::Tiled(128));
    let d = (&tiled - &whole).abs();
    let (mean, max) = (d.mean(tch::Kind::Double).double_value(&[]), d.max().double_value(&[]));
    eprintln!("layer-wise tiles of 128 vs whole, 512 x 512: identity ln(1+R) difference mean {mean:.2e} max {max:.2e}");
    assert!(max < 1e-4, "mean {mean:.2e} max {max:.2e}");
}
