//! `flashmat view` in a real browser: the page is opened in headless
//! Chromium (software WebGL2, SwiftShader) with a light and a camera in its
//! URL fragment, renders once at full resolution and writes its canvas
//! pixels into the DOM; they are compared with `flashmat relight` of the
//! same configuration (mean absolute difference < 1.5 of 255, none over 8),
//! for a compact material (the bundled model) and a tiny one.
//!
//! Chromium comes from `scripts/install-chromium.sh` (run by scripts/test.sh;
//! tried here too): the browser tests are skipped, with a message saying
//! so, only when it cannot be installed.

use flashmat::model::{Model, ModelConfig, ModelInfo};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};
use tch::Device;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn flashmat(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flashmat")).args(args).output().expect("run flashmat")
}

fn ok(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "flashmat failed: {err}");
    err
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Chromium's path, installing it when missing; None (with the reason
/// printed) when it cannot be had.
fn chromium() -> Option<PathBuf> {
    let out = Command::new("bash").arg(root().join("scripts/install-chromium.sh")).stderr(Stdio::inherit()).output().ok()?;
    if !out.status.success() {
        eprintln!("SKIPPED: headless Chromium is not available and could not be installed (scripts/install-chromium.sh needs root and apt-get); the browser checks of `flashmat view` did not run");
        return None;
    }
    Some(PathBuf::from(String::from_utf8_lossy(&out.stdout).trim().to_string()))
}

/// The page's DOM after it ran, with `fragment` in its URL.
fn dump_dom(browser: &Path, page: &Path, fragment: &str, profile: &Path) -> String {
    let url = format!("file://{}#{fragment}", page.canonicalize().unwrap().display());
    // To a file: the DOM (megabytes of base64) would fill a pipe that is only read at the end.
    let dom_file = profile.join("dom.html");
    let mut child = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--dump-dom")
        .arg(&url)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&dom_file).unwrap())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromium");
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > Duration::from_secs(600) {
            let _ = child.kill();
            panic!("chromium did not finish {url} within 10 minutes");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    String::from_utf8_lossy(&std::fs::read(&dom_file).unwrap()).into_owned()
}

/// Text content of `<pre id="ID" ...>` and its attributes string.
fn element<'a>(dom: &'a str, id: &str) -> Option<(&'a str, &'a str)> {
    let start = dom.find(&format!("<pre id=\"{id}\""))?;
    let rest = &dom[start..];
    let close = rest.find('>')?;
    let end = rest.find("</pre>")?;
    Some((&rest[..close], &rest[close + 1..end]))
}

fn attribute(attrs: &str, name: &str) -> usize {
    let k = format!("{name}=\"");
    let i = attrs.find(&k).unwrap_or_else(|| panic!("{name} missing in {attrs}")) + k.len();
    attrs[i..].split('"').next().unwrap().parse().unwrap()
}

fn base64_decode(text: &str) -> Vec<u8> {
    let val = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a' + 26) as u32,
            b'0'..=b'9' => (c - b'0' + 52) as u32,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {c}"),
        }
    };
    let bytes: Vec<u8> = text.bytes().filter(|c| !c.is_ascii_whitespace()).collect();
    let mut out = Vec::new();
    for chunk in bytes.chunks(4) {
        let pad = chunk.iter().filter(|&&c| c == b'=').count();
        let n = chunk.iter().take(4 - pad).enumerate().fold(0u32, |n, (i, &c)| n | val(c) << (18 - 6 * i));
        out.extend_from_slice(&[(n >> 16) as u8, (n >> 8) as u8, n as u8][..3 - pad]);
    }
    out
}

/// The canvas the page rendered: (width, height, RGB bytes, rows from the top).
fn page_pixels(browser: &Path, page: &Path, fragment: &str, profile: &Path) -> (usize, usize, Vec<u8>) {
    let dom = dump_dom(browser, page, fragment, profile);
    let status = element(&dom, "status").map(|(_, t)| t.to_string()).unwrap_or_default();
    let (attrs, text) = element(&dom, "pixels").unwrap_or_else(|| panic!("no pixels in the page; status: {status}"));
    assert!(!text.trim().is_empty(), "the page wrote no pixels; status: '{status}'");
    let (w, h) = (attribute(attrs, "data-width"), attribute(attrs, "data-height"));
    let px = base64_decode(text);
    assert_eq!(px.len(), w * h * 3);
    (w, h, px)
}

/// (mean, max) |a - b| over RGB bytes against an 8-bit PNG's codes.
fn compare(px: &[u8], w: usize, h: usize, png: &Path) -> (f64, u8) {
    let im = flashmat::io::read_image(png).unwrap();
    assert_eq!((im.channels, im.height, im.width), (3, h, w));
    let (mut sum, mut max) = (0.0, 0u8);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let r = (im.get(c, y, x) * 255.0).round() as u8;
                let d = px[(y * w + x) * 3 + c].abs_diff(r);
                sum += d as f64;
                max = max.max(d);
            }
        }
    }
    (sum / (w * h * 3) as f64, max)
}

/// A tiny randomly initialised model and an estimate of a procedural flash
/// photo with it: `size` rows, 3:2 (a rectangular map).
fn tiny_material(dir: &Path, size: usize) -> PathBuf {
    tch::manual_seed(11);
    let model = dir.join("tiny.safetensors");
    Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(&model, &ModelInfo { ldr_input: true, steps: 1 }, false).unwrap();
    let wide = size * 3 / 2;
    let m = flashmat::data::procedural::generate(5, &flashmat::data::procedural::ProceduralConfig::with_size(wide));
    let m = m.crop((wide - size) / 2, 0, size, wide).unwrap();
    let linear = flashmat::svbrdf::render::render_material(&m, &[flashmat::geometry::LightView::colocated(28.0)]).unwrap().remove(0);
    let photo = dir.join("photo.png");
    flashmat::io::write_png(&photo, &linear.map(flashmat::spaces::srgb_encode), flashmat::io::BitDepth::Eight).unwrap();
    let nmat = dir.join("tiny.nmat");
    ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--fov", "28", "--size", &size.to_string(), "-o", s(&nmat)]));
    nmat
}

/// A compact material: a bundled photo estimated by the bundled model.
fn compact_material(dir: &Path, size: usize) -> PathBuf {
    let nmat = dir.join("compact.nmat");
    let photo = root().join("examples/photos/IMG_6950.png");
    ok(&flashmat(&["estimate", s(&photo), "--fov", "28", "--size", &size.to_string(), "-o", s(&nmat)]));
    nmat
}

/// Writes the page, renders each (light, view) in Chromium and with
/// `flashmat relight`, and checks the difference; returns the worst (mean, max).
fn check_against_relight(browser: &Path, dir: &Path, nmat: &Path, configs: &[(&str, &str)], what: &str) -> (f64, u8) {
    let page = dir.join(format!("{what}.html"));
    let err = ok(&flashmat(&["view", s(nmat), "-o", s(&page)]));
    assert!(err.contains("display error mean") && err.contains(&format!("wrote {}", page.display())), "{err}");
    let profile = tempfile::tempdir().unwrap();
    let mut worst = (0.0f64, 0u8);
    for (i, (light, view)) in configs.iter().enumerate() {
        let reference = dir.join(format!("{what}-{i}.png"));
        // `--light=X,...`: a negative X would read as an option.
        ok(&flashmat(&["relight", s(nmat), &format!("--light={light}"), &format!("--view={view}"), "-o", s(&reference)]));
        let (w, h, px) = page_pixels(browser, &page, &format!("light={light}&view={view}&test=1"), profile.path());
        let (mean, max) = compare(&px, w, h, &reference);
        eprintln!("{what} {w}x{h}, light {light}, view {view}: browser vs relight mean {mean:.4} max {max} (of 255)");
        assert!(mean < 1.5 && max <= 8, "{what} light {light} view {view}: mean {mean:.3}, max {max} display levels");
        // Not a blank page: the render has structure.
        let lo = px.iter().min().unwrap();
        let hi = px.iter().max().unwrap();
        assert!(hi - lo > 20, "{what}: flat render ({lo}..{hi})");
        worst = (worst.0.max(mean), worst.1.max(max));
    }
    worst
}

#[test]
fn browser_render_matches_relight_for_compact_and_tiny() {
    let Some(browser) = chromium() else { return };
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let configs = [("0.6,-0.4,1.8", "0.3,0.2,3.5"), ("-1.5,0.8,0.7", "0,0,4.010781"), ("0,0,4.010781", "0,0,4.010781")];
    let compact = compact_material(d, 64);
    let (mean, max) = check_against_relight(&browser, d, &compact, &configs, "compact");
    assert!(mean < 1.5 && max <= 8);
    let tiny = tiny_material(d, 48);
    check_against_relight(&browser, d, &tiny, &configs[..2], "tiny");

    // The photo toggle shows the stored input photo as relight would write it (f16 in the page).
    let page = d.join("compact.html");
    let profile = tempfile::tempdir().unwrap();
    let (w, h, px) = page_pixels(&browser, &page, "show=photo&test=1", profile.path());
    let m = flashmat::infer::NeuralMaterial::load(&compact, Device::Cpu).unwrap();
    let photo_png = d.join("photo-display.png");
    flashmat::io::write_png(&photo_png, &m.input_image().unwrap().to_display(), flashmat::io::BitDepth::Eight).unwrap();
    let (mean, max) = compare(&px, w, h, &photo_png);
    eprintln!("input photo toggle: mean {mean:.4} max {max}");
    assert!(mean < 0.5 && max <= 2, "photo toggle: mean {mean}, max {max}");

    // A bad fragment is reported on the page, not a crash.
    let dom = dump_dom(&browser, &page, "light=0,0,-1&test=1", profile.path());
    let (_, status) = element(&dom, "status").unwrap();
    assert!(status.contains("light must be above the material"), "{status}");
}

#[test]
fn damaged_nmat_is_one_error_line_and_no_page() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let nmat = tiny_material(d, 16);
    let mut bytes = std::fs::read(&nmat).unwrap();
    let n = bytes.len();
    bytes[n - 50] ^= 0x08;
    let bad = d.join("bad.nmat");
    std::fs::write(&bad, &bytes).unwrap();
    let out_dir = d.join("pages");
    let page = out_dir.join("material.html");
    let out = flashmat(&["view", s(&bad), "-o", s(&page)]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{err}");
    assert!(lines[0].starts_with("error: ") && lines[0].contains("bad.nmat") && lines[0].contains("checksum"), "{err}");
    // No page, no temporary, and the output folder it would have made is gone.
    assert!(!page.exists() && !out_dir.exists());
    // Truncated: also one line.
    std::fs::write(&bad, &bytes[..n / 3]).unwrap();
    let out = flashmat(&["view", s(&bad), "-o", s(&page)]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!((out.status.code(), err.lines().count()), (Some(1), 1), "{err}");
    assert!(err.contains("truncated"), "{err}");
    // Wrong output extension: refused before any work.
    let out = flashmat(&["view", s(&nmat), "-o", s(&d.join("m.png"))]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("must end in .html"));
    // A valid material writes a page of the expected size: 16 channels of
    // 16 x 16 (f16: 8 KiB, base64 11 KB) plus the weights and the page itself.
    let good = d.join("good.html");
    let err = ok(&flashmat(&["view", s(&nmat), "--map-bits", "16", "--weight-bits", "16", "-o", s(&good)]));
    assert!(err.contains("16-bit floats"), "{err}");
    let len = std::fs::metadata(&good).unwrap().len();
    assert!((40_000..200_000).contains(&len), "{len} bytes");
    let names: Vec<String> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(names.iter().all(|n| !n.contains(".tmp-")), "{names:?}");
}
