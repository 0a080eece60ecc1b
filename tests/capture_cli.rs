//! End-to-end checks of `flashmat estimate --capture DIR` (one material
//! from all photos of a capture folder) with the bundled model and teacher
//! on a tiny synthetic capture: a loadable .nmat and PBR maps, and bad
//! inputs (one clear error line, exit code 1, no output).

use flashmat::data::captures::{synthetic_configs, write_synthetic};
use flashmat::infer::NeuralMaterial;
use tch::{Device, Kind};

mod common;
use common::*;

/// A 3-photo synthetic capture of held-out material 3 at 48x48 in `d/capture`.
fn synthetic_capture(d: &std::path::Path) -> std::path::PathBuf {
    let capture = d.join("capture");
    let material = flashmat::data::procedural::test_material(3, 48);
    write_synthetic(&capture, &material, &synthetic_configs(3), 10.0).unwrap();
    capture
}

#[test]
fn a_capture_folder_becomes_one_loadable_material() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let capture = synthetic_capture(d);
    let nmat = d.join("out/m.nmat");
    let pbr = d.join("out/pbr");
    let err = assert_ok(&flashmat(&["estimate", "--capture", s(&capture), "--size", "32", "--steps", "40", "--pbr", s(&pbr), "-o", s(&nmat)]));
    assert!(err.contains("from 3 of 3 photos at 32x32") && err.contains("data term") && err.contains("40 steps"), "{err}");
    let m = NeuralMaterial::load(&nmat, Device::Cpu).unwrap();
    assert_eq!(m.size(), (32, 32));
    assert_eq!(m.meta.gain, [1.0; 3]);
    // The teacher's renderer draws it: finite, lit, under the identity and a moved light.
    let renders = m.render(&[NeuralMaterial::identity_config(), flashmat::geometry::LightView { light: [1.2, 1.2, 3.5], view: [0.0, 0.0, 4.0] }]).unwrap();
    assert!(flashmat::image::all_finite(&renders));
    assert!(renders.mean(Kind::Double).double_value(&[]) > 0.01);
    assert!(pbr.join("fit.json").is_file() && pbr.join("maps").is_dir(), "{:?}", files_in(&pbr));
    no_temp_files(&d.join("out"));

    // --photos 2: the first two only.
    let two = d.join("two.nmat");
    let err = assert_ok(&flashmat(&["estimate", "--capture", s(&capture), "--photos", "2", "--size", "32", "--steps", "5", "--photo-gains", "-o", s(&two)]));
    assert!(err.contains("from 2 of 3 photos"), "{err}");
    // --photo-gains: the overhead photo's gain is 1 by definition.
    assert!(err.contains("exposure gains: 00.png 1.000, 01.png "), "{err}");
}

#[test]
fn bad_captures_give_one_clear_line_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let capture = synthetic_capture(d);
    let out = d.join("out/m.nmat");
    let run = |extra: &[&str]| {
        let mut args = vec!["estimate", "--capture", s(&capture), "--size", "32", "-o", s(&out)];
        args.extend_from_slice(extra);
        flashmat(&args)
    };
    assert_error(&run(&["--photos", "0", "--steps", "5"]), &["--photos must be between 1 and 3"]);
    assert_error(&run(&["--photos", "4", "--steps", "5"]), &["--photos must be between 1 and 3"]);
    assert_error(&run(&["--steps", "0"]), &["--steps must be between 1"]);
    assert_error(&run(&["--steps", "5", "--refine"]), &["--capture takes none of"]);
    // Photos of different sizes.
    flashmat::io::write_png(&capture.join("02.png"), &flashmat::image::Image::filled(3, 64, 64, 0.5), flashmat::io::BitDepth::Eight).unwrap();
    assert_error(&run(&["--steps", "5"]), &["02.png", "64x64", "48x48", "share one size"]);
    // A missing positions file.
    std::fs::remove_file(capture.join("light_pos.txt")).unwrap();
    assert_error(&run(&["--steps", "5"]), &["light_pos.txt"]);
    assert!(!d.join("out").exists(), "no output for a failed run");
}
