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
    // A size the memory bound cannot hold, refused before any work (it grew to 11.5 GB).
    let big = flashmat(&["estimate", "--capture", s(&capture), "--size", "4096", "--max-memory", "2G", "-o", s(&out)]);
    assert_error(&big, &["--size 4096 with 3 photos needs about", "more than the 2G allowed", "raise --max-memory"]);
    // Photos of different sizes.
    flashmat::io::write_png(&capture.join("02.png"), &flashmat::image::Image::filled(3, 64, 64, 0.5), flashmat::io::BitDepth::Eight).unwrap();
    assert_error(&run(&["--steps", "5"]), &["02.png", "64x64", "48x48", "share one size"]);
    // A missing positions file.
    std::fs::remove_file(capture.join("light_pos.txt")).unwrap();
    assert_error(&run(&["--steps", "5"]), &["light_pos.txt"]);
    assert!(!d.join("out").exists(), "no output for a failed run");
}

/// Three synthetic phone photos (960x720 JPEGs, no EXIF) of the printed
/// 10 cm frame around held-out material 3, the flash 8 mm beside the lens.
fn frame_photos(d: &std::path::Path) -> Vec<std::path::PathBuf> {
    use flashmat::capture::{frame::FrameLayout, synthetic};
    let layout = FrameLayout::new(10).unwrap();
    let eyes = [[0.0, 0.0, 250.0], [40.0, -32.0, 240.0], [-36.0, 40.0, 245.0]];
    let views = synthetic::phone_views(&eyes, &[0.0, 15.0, -20.0], 960, 720, 721.0, -0.03, 0.0);
    let material = flashmat::data::procedural::test_material(3, 64);
    let fx = synthetic::PhoneEffects { jpeg_quality: None, ..Default::default() };
    synthetic::shoot(&material, &layout, &views, [8.0, 0.0], synthetic::SUPERSAMPLE, &fx)
        .unwrap()
        .into_iter()
        .enumerate()
        .map(|(i, shot)| {
            let path = d.join(format!("IMG_{i}.jpg"));
            flashmat::io::write_jpeg(&path, &shot.rgb.to_image(), 92).unwrap();
            path
        })
        .collect()
}

#[test]
fn photos_of_the_printed_frame_become_a_capture_folder_and_a_material() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // The frame to print: a vector PDF, or a PNG; other extensions are refused.
    let err = assert_ok(&flashmat(&["capture", "frame", "-o", s(&d.join("frame.pdf"))]));
    assert!(err.contains("24 tag36h11 tags, ids 240-263"), "{err}");
    assert!(std::fs::read(d.join("frame.pdf")).unwrap().starts_with(b"%PDF-"));
    assert_error(&flashmat(&["capture", "frame", "-o", s(&d.join("frame.svg"))]), &["frame.svg: the frame is written as .pdf or .png"]);
    assert_error(&flashmat(&["capture", "frame", "--opening", "20", "-o", s(&d.join("f.pdf"))]), &["--opening must be a whole number of centimetres from 5 to 14"]);
    // A PNG says its resolution (pHYs after IHDR: 100 dpi = 3,937 pixels a metre); --dpi with a PDF is refused.
    assert_ok(&flashmat(&["capture", "frame", "--dpi", "100", "-o", s(&d.join("frame.png"))]));
    let png = std::fs::read(d.join("frame.png")).unwrap();
    assert_eq!((&png[37..41], u32::from_be_bytes(png[41..45].try_into().unwrap())), (&b"pHYs"[..], 3_937));
    assert_error(&flashmat(&["capture", "frame", "--dpi", "5", "-o", s(&d.join("f2.pdf"))]), &["--dpi sets a PNG's resolution; ", "f2.pdf is a PDF"]);
    assert!(!d.join("f2.pdf").exists());
    // capture --estimate checks the estimate's options before it reads a photo or writes the folder.
    let (a, b) = (d.join("a.jpg"), d.join("b.jpg"));
    let none = [s(&a), s(&b)];
    assert_error(&flashmat(&["capture", none[0], none[1], "--estimate", "-o", s(&d.join("m.nmat")), "--size", "7"]), &["--size must be a multiple of 8"]);
    assert_error(&flashmat(&["capture", none[0], none[1], "--estimate", "-o", s(&d.join("m.nmat")), "--device", "tpu"]), &["tpu"]);
    assert!(!d.join("m-capture").exists() && !d.join("m.nmat").exists());

    let photos = frame_photos(d);
    let p: Vec<&str> = photos.iter().map(|p| s(p)).collect();
    let folder = d.join("capture");
    let err = assert_ok(&flashmat(&["capture", p[0], p[1], p[2], "--flash-offset", "8,0", "-o", s(&folder)]));
    assert!(err.contains("3 photos, the 10 cm opening") && err.contains("00 IMG_0.jpg: lens at (0, 0, "), "{err}");
    let c = flashmat::data::captures::Captures::open(&folder).unwrap();
    assert_eq!((c.photos.len(), c.sample_width), (3, 100.0));
    // The lens 250 mm over the centre (no EXIF: the focal length from the photos' perspective); flashmat units are mm / 50.
    assert!((c.cameras[0][2] * 50.0 - 250.0).abs() < 2.0 && c.cameras[0][0].abs() < 0.04, "{:?}", c.cameras[0]);
    // The flash 8 mm along the overhead camera's x: world +x (flashmat units: mm / 50).
    assert!((c.lights[0][0] - c.cameras[0][0] - 0.16).abs() < 0.01, "{:?} {:?}", c.lights[0], c.cameras[0]);
    assert!(folder.join("capture.jpg").is_file());

    // Bad inputs: one line naming the photo, exit 1, no folder.
    let out = d.join("bad");
    assert_error(&flashmat(&["capture", p[0], "-o", s(&out)]), &["a capture needs at least 2 photos of the frame, got 1"]);
    let missing = d.join("IMG_9.jpg");
    assert_error(&flashmat(&["capture", p[0], s(&missing), "-o", s(&out)]), &["IMG_9.jpg"]);
    let bad_offset = flashmat(&["capture", p[0], p[1], "--flash-offset", "8", "-o", s(&out)]);
    assert!(!bad_offset.status.success() && stderr(&bad_offset).contains("'8' is not X,Y"), "{}", stderr(&bad_offset));
    // A negative offset is a value, as written (clap's tip for it, `-- -8,3`, failed).
    assert_error(&flashmat(&["capture", p[0], s(&missing), "--flash-offset", "-8,3", "-o", s(&out)]), &["IMG_9.jpg"]);
    assert_error(&flashmat(&["capture", p[0], p[1], "-o", s(&folder)]), &["exists and is not empty"]);
    assert!(!out.exists());
    no_temp_files(d);

    // --estimate: on to one material, the capture folder beside it.
    let nmat = d.join("m.nmat");
    let err = assert_ok(&flashmat(&["capture", p[0], p[1], p[2], "--estimate", "--size", "32", "--steps", "20", "-o", s(&nmat)]));
    assert!(err.contains("from 3 of 3 photos at 32x32"), "{err}");
    assert!(d.join("m-capture/02.png").is_file());
    assert_eq!(NeuralMaterial::load(&nmat, Device::Cpu).unwrap().size(), (32, 32));
}
