//! End-to-end checks of `flashmat estimate | relight | show` with small
//! randomly initialised models: outputs, and bad inputs (one clear error
//! line, exit code 1, no partial files).

use flashmat::geometry::LightView;
use flashmat::image::Image;
use flashmat::infer::NeuralMaterial;
use flashmat::model::{Model, ModelConfig, ModelInfo};
use std::path::{Path, PathBuf};
use tch::Device;

mod common;
use common::*;

/// A tiny randomly initialised model file.
fn tiny_model(path: &Path, ldr_input: bool, seed: i64) -> PathBuf {
    tch::manual_seed(seed);
    let m = Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap();
    m.save(path, &ModelInfo { ldr_input, steps: 3 }, false).unwrap();
    path.to_path_buf()
}

/// A co-located flash render of a procedural material, `width x height`, linear.
fn flash_render(width: usize, height: usize) -> Image {
    let side = width.max(height);
    let m = flashmat::data::procedural::generate(21, &flashmat::data::procedural::ProceduralConfig::with_size(side));
    let m = m.crop((side - height) / 2, (side - width) / 2, height, width).unwrap();
    flashmat::svbrdf::render::render_material(&m, &[LightView::colocated(28.0)]).unwrap().remove(0)
}

/// An 8-bit sRGB-encoded PNG "phone photo".
fn png_photo(path: &Path, width: usize, height: usize) -> PathBuf {
    let linear = flash_render(width, height);
    flashmat::io::write_png(path, &linear.map(flashmat::spaces::srgb_encode), flashmat::io::BitDepth::Eight).unwrap();
    path.to_path_buf()
}

fn gif_frames(path: &Path) -> (u16, u16, usize) {
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::RGBA);
    let mut dec = opts.read_info(std::fs::File::open(path).unwrap()).unwrap();
    let (w, h) = (dec.width(), dec.height());
    let mut n = 0;
    while dec.read_next_frame().unwrap().is_some() {
        n += 1;
    }
    (w, h, n)
}

#[test]
fn estimate_relight_orbit_show_from_a_phone_photo() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = tiny_model(&d.join("tiny-ldr.safetensors"), true, 1);
    // 160x120 without EXIF: the model's 28 degrees, the whole 4:3 photo, shrunk to 64 rows and
    // 85.3 -> 80 columns (a multiple of 8): the crop is trimmed to 120 x 80 / 64 = 150 columns.
    let photo = png_photo(&d.join("photo.png"), 160, 120);
    let nmat = d.join("out/m.nmat");
    let err = assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--size", "64", "-o", s(&nmat)]));
    assert!(err.contains("estimated in ") && err.contains(" s"), "{err}");
    assert!(!err.contains("warning"), "{err}");
    assert!(err.contains("no focal length in the photo's EXIF") && err.contains("--fov"), "{err}");
    let m = NeuralMaterial::load(&nmat, Device::Cpu).unwrap();
    assert_eq!(m.size(), (64, 80));
    assert_eq!((m.meta.crop.x0, m.meta.crop.y0, m.meta.crop.width, m.meta.crop.height), (5, 0, 150, 120));
    assert_eq!((m.meta.crop.source_width, m.meta.crop.source_height), (160, 120));
    assert_eq!((m.meta.fov_deg, m.meta.ldr_input, m.meta.source.as_str()), (28.0, true, "photo.png"));
    assert_eq!(m.meta.model_id, ModelConfig::tiny().model_id());

    // Identity relight: the photo's (model-resolution) size.
    let id = d.join("id.png");
    let err = assert_ok(&flashmat(&["relight", s(&nmat), "--identity", "-o", s(&id)]));
    assert!(err.contains("rendered in "), "{err}");
    let im = flashmat::io::read_image(&id).unwrap();
    assert_eq!((im.channels, im.height, im.width), (3, 64, 80));
    // Same picture when relight is given the photo itself (estimated on the fly).
    let id2 = d.join("id2.png");
    assert_ok(&flashmat(&["relight", s(&photo), "--identity", "--model", s(&model), "--size", "64", "-o", s(&id2)]));
    assert_eq!(flashmat::io::read_image(&id2).unwrap(), im);

    // A chosen light: linear EXR equal to the library's render.
    let exr = d.join("side.exr");
    assert_ok(&flashmat(&["relight", s(&nmat), "--light", "1.5,1,2", "--view", "0.5,0,3", "-o", s(&exr)]));
    let got = flashmat::io::read_image(&exr).unwrap();
    let want = m.render_image(&LightView { light: [1.5, 1.0, 2.0], view: [0.5, 0.0, 3.0] }).unwrap();
    assert_eq!(got, want);

    // Orbit: N frames at the material's resolution.
    let gif = d.join("orbit.gif");
    let err = assert_ok(&flashmat(&["relight", s(&nmat), "--orbit", "5", "-o", s(&gif)]));
    assert!(err.contains("rendered 5 frames in "), "{err}");
    assert_eq!(gif_frames(&gif), (80, 64, 5));

    // Show: 2 rows x 4 columns of 64 x 80 cells with 4-pixel gaps.
    let grid = d.join("grid.png");
    assert_ok(&flashmat(&["show", s(&nmat), "-o", s(&grid)]));
    let g = flashmat::io::read_image(&grid).unwrap();
    assert_eq!((g.channels, g.height, g.width), (3, 2 * 68 + 4, 4 * 84 + 4));

    // --square keeps the centre square, as before rectangles.
    let sq = d.join("sq.nmat");
    assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--size", "64", "--square", "-o", s(&sq)]));
    let m = NeuralMaterial::load(&sq, Device::Cpu).unwrap();
    assert_eq!((m.size(), m.meta.crop.x0, m.meta.crop.width, m.meta.crop.height), ((64, 64), 20, 120, 120));
    no_temp_files(d);
    no_temp_files(&d.join("out"));
}

/// An iPhone-like HEIC: 8-bit sRGB, stored 160x120 with the rotation of
/// EXIF orientation 6 in the file (and in its EXIF, as phones write it),
/// and a 26 mm equivalent focal length.
#[cfg(feature = "heif")]
#[test]
fn a_heic_phone_photo_goes_through_estimate_with_its_fov_from_exif() {
    use exif::{Field, In, Tag, Value};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = tiny_model(&d.join("tiny-ldr.safetensors"), true, 3);
    let field = |tag, value| Field { tag, ifd_num: In::PRIMARY, value };
    let mut writer = exif::experimental::Writer::new();
    let fields = [field(Tag::FocalLengthIn35mmFilm, Value::Short(vec![26])), field(Tag::Orientation, Value::Short(vec![6]))];
    fields.iter().for_each(|f| writer.push_field(f));
    let mut tiff = std::io::Cursor::new(Vec::new());
    writer.write(&mut tiff, false).unwrap();
    let photo = d.join("IMG_0001.HEIC");
    let codes = flash_render(160, 120).map(flashmat::spaces::srgb_encode);
    let spec = flashmat::io::heif::HeifEncoding { orientation: 6, exif: Some(tiff.into_inner()), ..Default::default() };
    flashmat::io::heif::write_heif(&photo, &codes, &spec).unwrap();
    let nmat = d.join("m.nmat");
    let err = assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--size", "32", "-o", s(&nmat)]));
    assert!(err.contains("FocalLengthIn35mmFilm 26 mm") && !err.contains("warning"), "{err}");
    let m = NeuralMaterial::load(&nmat, Device::Cpu).unwrap();
    // The shorter side of the 35 mm frame at 4:3 is 43.2666 x 3/5 = 25.96 mm: 2 atan(25.96 / 52) = 53.06 degrees.
    let by_hand = 2.0 * (43.266_615 * 0.6 / 52.0f64).atan().to_degrees();
    assert!((m.meta.fov_deg - by_hand).abs() < 1e-3, "{} vs {by_hand}", m.meta.fov_deg);
    assert_eq!((m.meta.ldr_input, m.meta.source.as_str()), (true, "IMG_0001.HEIC"));
    // Turned once: shown 120 wide, 160 high, so the material is portrait.
    assert_eq!((m.meta.crop.source_width, m.meta.crop.source_height), (120, 160));
    let (h, w) = m.size();
    assert!(h > w && w == 32, "{h}x{w}");

    // Commands that open a material take the HEIC as a photo (not as a damaged .nmat).
    let again = d.join("again.png");
    assert_ok(&flashmat(&["relight", s(&photo), "--identity", "--model", s(&model), "--size", "32", "-o", s(&again)]));
    assert_eq!(flashmat::io::read_image(&again).unwrap().width, 32);

    // A damaged HEIC: one line, exit code 1, no output.
    let bytes = std::fs::read(&photo).unwrap();
    let cut = d.join("cut.heic");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    assert_error(&flashmat(&["estimate", s(&cut), "--model", s(&model), "-o", s(&d.join("c.nmat"))]), &["cut.heic", "corrupt or truncated HEIC"]);
    assert!(!d.join("c.nmat").exists());

    // A phone's folder: the HEIC, the same picture as AVIF, and the damaged one, in one run.
    let phone = d.join("phone");
    std::fs::create_dir(&phone).unwrap();
    std::fs::copy(&photo, phone.join("IMG_0001.HEIC")).unwrap();
    std::fs::copy(&cut, phone.join("IMG_0002.HEIC")).unwrap();
    flashmat::io::heif::write_heif(&phone.join("IMG_0003.avif"), &codes, &flashmat::io::heif::HeifEncoding { av1: true, ..Default::default() }).unwrap();
    let out = d.join("materials");
    let run = flashmat(&["estimate", s(&phone), "--model", s(&model), "--size", "32", "--fov", "40", "-o", s(&out)]);
    let err = stderr(&run);
    assert_eq!(run.status.code(), Some(1), "{err}");
    assert!(err.contains("2 of 3 inputs written") && err.contains("failed: ") && err.contains("IMG_0002.HEIC: cannot read image"), "{err}");
    assert_eq!(files_in(&out), ["IMG_0001.nmat", "IMG_0003.nmat"]);
    let avif = NeuralMaterial::load(&out.join("IMG_0003.nmat"), Device::Cpu).unwrap();
    assert_eq!((avif.meta.fov_deg, avif.meta.crop.source_width, avif.meta.crop.source_height), (40.0, 160, 120));
    no_temp_files(d);
    no_temp_files(&out);
}

/// Built without libheif, a HEIC is refused in one line that says how to
/// convert it.
#[cfg(not(feature = "heif"))]
#[test]
fn without_libheif_a_heic_is_refused_with_a_way_out() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let photo = d.join("IMG_0001.HEIC");
    std::fs::write(&photo, [&[0, 0, 0, 24][..], b"ftypheic", &[0; 12]].concat()).unwrap();
    let model = tiny_model(&d.join("tiny.safetensors"), true, 3);
    assert_error(&flashmat(&["estimate", s(&photo), "--model", s(&model), "-o", s(&d.join("m.nmat"))]), &["IMG_0001.HEIC", "heif-convert", "--features heif"]);
}

#[test]
fn exr_photos_default_to_28_degrees_and_mismatched_models_warn() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ldr_model = tiny_model(&d.join("ldr.safetensors"), true, 2);
    let hdr_model = tiny_model(&d.join("hdr.safetensors"), false, 3);
    let photo = d.join("render.exr");
    flashmat::io::write_exr(&photo, &flash_render(64, 64)).unwrap();
    let nmat = d.join("m.nmat");
    let err = assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&hdr_model), "--size", "32", "-o", s(&nmat)]));
    assert!(!err.contains("warning"), "{err}");
    let m = NeuralMaterial::load(&nmat, Device::Cpu).unwrap();
    assert_eq!((m.meta.fov_deg, m.meta.ldr_input, m.meta.crop.width, m.size()), (28.0, false, 64, (32, 32)));

    let out = flashmat(&["estimate", s(&photo), "--model", s(&ldr_model), "--size", "32", "-o", s(&nmat)]);
    let err = assert_ok(&out);
    let warnings: Vec<&str> = err.lines().filter(|l| l.starts_with("warning: ")).collect();
    assert_eq!(warnings.len(), 1, "{err}");
    assert!(warnings[0].contains("ldr.safetensors") && warnings[0].contains("8-bit"), "{err}");
    let png = png_photo(&d.join("p.png"), 64, 64);
    let err = assert_ok(&flashmat(&["estimate", s(&png), "--model", s(&hdr_model), "--fov", "28", "--size", "32", "-o", s(&nmat)]));
    assert!(err.lines().any(|l| l.starts_with("warning: ") && l.contains("HDR")), "{err}");
}

#[test]
fn default_models_are_found_checked_and_explained() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let photo = png_photo(&d.join("p.png"), 64, 64);
    let o = d.join("m.nmat");
    let models = d.join("models");
    std::fs::create_dir(&models).unwrap();
    let env = [("FLASHMAT_MODELS", s(&models))];
    let run = |extra: &[&str]| {
        let mut args = vec!["estimate", s(&photo), "--fov", "28", "--size", "32", "-o", s(&o)];
        args.extend_from_slice(extra);
        flashmat_env(&args, &env)
    };
    // Missing default model: which file, and how to pick another.
    assert_error(&run(&[]), &["flashmat.safetensors", "does not exist", "--model"]);
    // The default file must hold the bundled (compact) preset.
    tiny_model(&models.join("flashmat.safetensors"), true, 4);
    assert_error(&run(&[]), &["flashmat.safetensors", "holds model 'tiny-", "expected 'compact-"]);
    // --model accepts any preset, but not a missing file...
    assert_error(&run(&["--model", s(&d.join("nope.safetensors"))]), &["nope.safetensors", "does not exist", "--model"]);
    // ...nor another version of the model format...
    let a = flashmat::archive::Archive::load(&models.join("flashmat.safetensors"), "flashmat-model", 1).unwrap();
    let v2 = d.join("v2.safetensors");
    a.save(&v2, "flashmat-model", 2).unwrap();
    assert_error(&run(&["--model", s(&v2)]), &["v2.safetensors", "version 2 is not supported"]);
    // ...nor a neural material.
    assert_ok(&flashmat_env(&["estimate", s(&photo), "--fov", "28", "--size", "32", "--model", s(&models.join("flashmat.safetensors")), "-o", s(&o)], &env));
    assert_error(&run(&["--model", s(&o)]), &["m.nmat", "'flashmat-nmat' file, expected a 'flashmat-model' file"]);
    assert_ok(&run(&["--model", s(&models.join("flashmat.safetensors"))]));
}

#[test]
fn bad_inputs_give_one_clear_line_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = tiny_model(&d.join("tiny.safetensors"), true, 5);
    let photo = png_photo(&d.join("p.png"), 64, 64);
    let nmat = d.join("good.nmat");
    assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--fov", "28", "--size", "32", "-o", s(&nmat)]));
    let out = d.join("results");
    std::fs::create_dir(&out).unwrap();
    let o = |name: &str| out.join(name).to_str().unwrap().to_string();
    let est = |input: &Path, extra: &[&str], output: &str| {
        let mut args = vec!["estimate", s(input), "--model", s(&model), "-o", output];
        args.extend_from_slice(extra);
        flashmat(&args)
    };

    // Missing photo and unreadable images.
    assert_error(&est(&d.join("missing.png"), &[], &o("a.nmat")), &["missing.png", "No such file"]);
    let garbage = d.join("garbage.png");
    std::fs::write(&garbage, b"\x89PNG\r\n\x1a\nthis is not a png").unwrap();
    assert_error(&est(&garbage, &[], &o("a.nmat")), &["garbage.png", "corrupt"]);
    let text = d.join("notes.txt");
    std::fs::write(&text, b"hello").unwrap();
    assert_error(&est(&text, &[], &o("a.nmat")), &["notes.txt", "unsupported format"]);
    // Too small after the FOV crop: says what is needed (no EXIF: the model's 28 degrees, the whole photo).
    assert_error(&est(&photo, &[], &o("a.nmat")), &["p.png", "too small", "keeps 64x64", "--size 256", "at least 256 pixels"]);
    assert_error(&est(&photo, &["--fov", "45"], &o("a.nmat")), &["p.png", "too small", "keeps 38x38", "--size 256", "at least 426 pixels"]);
    assert_error(&est(&photo, &["--fov", "28", "--size", "128"], &o("a.nmat")), &["too small", "at least 128 pixels"]);
    // NaN/Inf in an EXR.
    let nan = d.join("nan.exr");
    exr::prelude::write_rgb_file(&nan, 32, 32, |x, y| (0.5f32, if (x, y) == (3, 7) { f32::NAN } else { 0.2 }, 0.1f32)).unwrap();
    assert_error(&est(&nan, &[], &o("a.nmat")), &["nan.exr", "NaN/Inf", "row 7, column 3"]);
    // Options out of range.
    assert_error(&est(&photo, &["--size", "60"], &o("a.nmat")), &["--size", "multiple of 8"]);
    assert_error(&est(&photo, &["--fov", "20"], &o("a.nmat")), &["--fov", "between 28 and"]);
    assert_error(&est(&photo, &["--device", "tpu"], &o("a.nmat")), &["--device"]);
    assert_error(&est(&photo, &["--fov", "28", "--size", "32", "--max-memory", "lots"], &o("a.nmat")), &["--max-memory", "8G"]);
    assert_error(&est(&photo, &["--fov", "28", "--size", "32", "--max-memory", "1K"], &o("a.nmat")), &["--max-memory 1K", "64 MiB"]);
    assert_error(&est(&photo, &["--fov", "28", "--size", "32", "--max-memory", "5000000T"], &o("a.nmat")), &["--max-memory", "absurd"]);
    assert_error(&est(&photo, &["--fov", "28", "--size", "32"], &o("a.png")), &["a.png", ".nmat"]);
    // An output folder that cannot be written (a file stands in its way).
    std::fs::write(d.join("blocker"), b"x").unwrap();
    let blocked = d.join("blocker").join("m.nmat");
    assert_error(&est(&photo, &["--fov", "28", "--size", "32"], s(&blocked)), &["blocker"]);

    // Relight: lights and cameras below the surface, missing light, bad outputs.
    let relight = |extra: &[&str]| {
        let mut args = vec!["relight", s(&nmat)];
        args.extend_from_slice(extra);
        flashmat(&args)
    };
    assert_error(&relight(&["--light", "0,0,-1", "-o", &o("r.png")]), &["light position 0,0,-1", "z must be > 0"]);
    assert_error(&relight(&["--light", "1,1,1", "--view", "1,0,0", "-o", &o("r.png")]), &["camera position 1,0,0", "not above the surface"]);
    assert_error(&relight(&["--orbit", "3", "--view", "0,0,-4", "-o", &o("r.gif")]), &["camera position"]);
    assert_error(&relight(&["-o", &o("r.png")]), &["--light", "--orbit", "--identity"]);
    assert_error(&relight(&["--identity", "-o", &o("r.bmp")]), &["r.bmp", ".png or .exr"]);
    assert_error(&relight(&["--orbit", "4", "-o", &o("r.png")]), &["r.png", ".gif"]);
    assert_error(&relight(&["--orbit", "0", "-o", &o("r.gif")]), &["--orbit", "between 1 and 1000"]);
    assert_error(&relight(&["--identity", "-o", s(&d.join("blocker").join("r.png"))]), &["blocker"]);
    assert_error(&relight(&["--orbit", "2", "-o", s(&d.join("blocker").join("r.gif"))]), &["blocker"]);

    // Damaged, truncated and foreign materials.
    let bytes = std::fs::read(&nmat).unwrap();
    let mut flipped = bytes.clone();
    let n = flipped.len();
    flipped[n - 50] ^= 0x01;
    let bad = d.join("flipped.nmat");
    std::fs::write(&bad, &flipped).unwrap();
    assert_error(&flashmat(&["relight", s(&bad), "--identity", "-o", &o("r.png")]), &["flipped.nmat", "checksum"]);
    let cut = d.join("cut.nmat");
    std::fs::write(&cut, &bytes[..n / 3]).unwrap();
    assert_error(&flashmat(&["show", s(&cut), "-o", &o("g.png")]), &["cut.nmat", "truncated"]);
    assert_error(&flashmat(&["relight", s(&model), "--identity", "-o", &o("r.png")]), &["tiny.safetensors", "'flashmat-model' file"]);
    assert_error(&flashmat(&["relight", s(&d.join("none.nmat")), "--identity", "-o", &o("r.png")]), &["none.nmat", "No such file"]);
    assert_error(&flashmat(&["show", s(&nmat), "-o", &o("g.exr")]), &["g.exr", ".png"]);

    // Nothing was written for any failure.
    assert_eq!(files_in(&out), Vec::<String>::new());
    no_temp_files(d);
}

#[test]
fn refine_on_estimate_and_on_a_nmat_is_recorded_and_checked() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = tiny_model(&d.join("tiny-ldr.safetensors"), true, 5);
    let photo = png_photo(&d.join("photo.png"), 32, 32);
    let plain = d.join("plain.nmat");
    assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--fov", "28", "--size", "32", "-o", s(&plain)]));
    let refined = d.join("refined.nmat");
    let err = assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--fov", "28", "--size", "32", "--refine", "20", "--refine-pull", "0.5", "-o", s(&refined)]));
    let line = err.lines().find(|l| l.starts_with("refined in 20 steps")).unwrap_or_else(|| panic!("no refinement line: {err}"));
    assert!(line.contains("identity L1 (log radiance)") && line.contains(" -> "), "{line}");
    let (p, r) = (NeuralMaterial::load(&plain, Device::Cpu).unwrap(), NeuralMaterial::load(&refined, Device::Cpu).unwrap());
    assert!(p.meta.refine.is_none());
    let report = r.meta.refine.clone().expect("refinement recorded");
    assert_eq!((report.steps_done, report.config.steps, report.config.pull_weight), (20, 20, 0.5));
    assert!(report.identity_l1_after < report.identity_l1_before, "{report:?}");
    assert!(!r.neural_map.equal(&p.neural_map));

    // `--refine` without a number on a .nmat: the default steps, on the stored photo; `--refine 0` changes nothing.
    let grid = d.join("grid.png");
    let err = assert_ok(&flashmat(&["show", s(&plain), "--refine", "-o", s(&grid)]));
    assert!(err.contains("refined in 100 steps"), "{err}");
    let id = d.join("id.png");
    let err = assert_ok(&flashmat(&["relight", s(&plain), "--identity", "--refine", "0", "-o", s(&id)]));
    assert!(!err.contains("refined"), "{err}");

    // Bad step counts: one clear line, no output.
    let out = d.join("bad.nmat");
    assert_error(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--refine", "1000000", "-o", s(&out)]), &["--refine", "at most"]);
    assert_error(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--refine", "2", "--refine-lr", "nan", "-o", s(&out)]), &["learning rate"]);
    let e = flashmat(&["estimate", s(&photo), "--model", s(&model), "--refine", "-3", "-o", s(&out)]);
    assert_eq!(e.status.code(), Some(2), "{}", stderr(&e));
    assert!(!out.exists());
    no_temp_files(d);
}

/// flashmat's pictures carry the curve its photo reader assumes: `render
/// -o p.png` of a dark material read back by `estimate`'s decoder is the
/// radiance `render -o p.exr` writes, to within an 8-bit code, shadows
/// included (with the former ^(1/2.2) encode, code 10 came back 3.8x too
/// bright). Photos that are usable but not quite right are estimated with
/// a one-line warning each.
#[test]
fn rendered_pngs_round_trip_and_questionable_photos_warn() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let render = |out: &Path| assert_ok(&flashmat(&["render", "--svbrdf", "procedural:3", "--size", "32", "--light", "2,1,0.6", "-o", s(out)]));
    render(&d.join("r.png"));
    render(&d.join("r.exr"));
    let (png, exr) = (flashmat::io::read_image(&d.join("r.png")).unwrap(), flashmat::io::read_image(&d.join("r.exr")).unwrap());
    let mut dark = 0;
    for (p, e) in png.data.iter().zip(&exr.data) {
        let e = e.clamp(0.0, 1.0);
        let code = (p * 255.0).round();
        // Half a code either side of the stored one brackets the radiance.
        let (lo, hi) = (flashmat::spaces::photo_decode((code - 0.5).max(0.0) / 255.0), flashmat::spaces::photo_decode((code + 0.5).min(255.0) / 255.0));
        assert!(e >= lo - 1e-6 && e <= hi + 1e-6, "radiance {e} written as code {code}");
        dark += (code <= 12.0) as usize;
    }
    assert!(dark > 10, "the test render has no shadows ({dark} dark values)");

    let model = tiny_model(&d.join("tiny.safetensors"), true, 2);
    let mut rgba = flash_render(64, 64).map(flashmat::spaces::srgb_encode);
    rgba = Image::from_fn(4, 64, 64, |c, y, x| if c < 3 { rgba.get(c, y, x) } else if y < 8 { 0.0 } else { 1.0 });
    flashmat::io::write_png(&d.join("alpha.png"), &rgba, flashmat::io::BitDepth::Eight).unwrap();
    let err = assert_ok(&flashmat(&["estimate", s(&d.join("alpha.png")), "--model", s(&model), "--size", "64", "-o", s(&d.join("a.nmat"))]));
    let warnings: Vec<&str> = err.lines().filter(|l| l.starts_with("warning: ")).collect();
    assert_eq!(warnings.len(), 1, "{err}");
    assert!(warnings[0].contains("alpha.png: 512 of its 4096 pixels (12.50%) are transparent"), "{err}");
    let mut noisy = flash_render(64, 64);
    noisy.data[..100].iter_mut().for_each(|v| *v = -0.001);
    flashmat::io::write_exr(&d.join("noisy.exr"), &noisy).unwrap();
    let err = assert_ok(&flashmat(&["relight", s(&d.join("noisy.exr")), "--identity", "--model", s(&model), "--size", "64", "-o", s(&d.join("n.png"))]));
    assert!(err.contains("warning: ") && err.contains("noisy.exr: 100 of its 12288 colour values (0.81%) are negative"), "{err}");
}

/// `--highlight-fill` on estimate and on a .nmat: the photographed flash
/// highlight's codes are replaced inside its disc and nowhere else, and the
/// line says what was done.
#[test]
fn the_highlight_fill_changes_the_codes_under_the_flash_highlight_only() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = tiny_model(&d.join("tiny-ldr.safetensors"), true, 6);
    // A matte photo with a bright disc of radius 5 px at its centre (the flash highlight) and texture around it.
    let photo_img = Image::from_fn(3, 32, 32, |c, y, x| {
        let r = (x as f32 + 0.5 - 16.0).hypot(y as f32 + 0.5 - 16.0);
        if r < 5.0 { 0.95 } else { 0.08 + 0.04 * (((x / 3 + y / 4) % 3) as f32) + 0.01 * c as f32 }
    });
    let photo = d.join("photo.png");
    flashmat::io::write_png(&photo, &photo_img.map(flashmat::spaces::srgb_encode), flashmat::io::BitDepth::Eight).unwrap();
    let (plain, filled) = (d.join("plain.nmat"), d.join("filled.nmat"));
    let args = |out: &Path| vec!["estimate".to_string(), s(&photo).to_string(), "--model".into(), s(&model).into(), "--fov".into(), "28".into(), "--size".into(), "32".into(), "-o".into(), s(out).into()];
    assert_ok(&flashmat(&args(&plain).iter().map(String::as_str).collect::<Vec<_>>()));
    let mut with_fill = args(&filled);
    with_fill.push("--highlight-fill".into());
    let err = assert_ok(&flashmat(&with_fill.iter().map(String::as_str).collect::<Vec<_>>()));
    assert!(err.contains("highlight fill: codes of") && err.contains("copied from"), "{err}");
    let (p, f) = (NeuralMaterial::load(&plain, Device::Cpu).unwrap(), NeuralMaterial::load(&filled, Device::Cpu).unwrap());
    let changed: Vec<f32> = Vec::try_from((&p.neural_map - &f.neural_map).abs().amax([0i64].as_slice(), false).flatten(0, -1)).unwrap();
    assert!(changed[16 * 32 + 16] > 0.0, "the centre's codes must change");
    // Disc 5 px + 2% dilation + 2% feather of 32 px: nothing changes 7 px or more from the centre.
    for (i, v) in changed.iter().enumerate() {
        let r = ((i % 32) as f32 + 0.5 - 16.0).hypot((i / 32) as f32 + 0.5 - 16.0);
        assert!(r < 7.0 || *v == 0.0, "pixel {i} at {r} px changed by {v}");
    }
    // On a .nmat (its stored photo), and a mode that does not exist.
    let id = d.join("id.png");
    let err = assert_ok(&flashmat(&["relight", s(&plain), "--identity", "--highlight-fill", "blend", "-o", s(&id)]));
    assert!(err.contains("interpolated from around the highlight"), "{err}");
    let e = flashmat(&["relight", s(&plain), "--identity", "--highlight-fill", "smear", "-o", s(&id)]);
    assert_eq!(e.status.code(), Some(2), "{}", stderr(&e));
    no_temp_files(d);
}
