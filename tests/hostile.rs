//! Hostile inputs and faults: no crash, no silent garbage, nothing lost.
//!
//! - [`bad_input_corpus`]: a corpus built here (no large files in git) of
//!   hostile headers, truncations, bit flips, forged archives, absurd
//!   options, special files and non-finite values. Each case runs the
//!   binary under a memory cap (an unguarded allocation fails the case,
//!   not the machine) and a time limit, and must end in its one-line error
//!   with the expected exit code, no panic or signal, and leave no output
//!   or temporary file. The test prints the counts.
//! - `mutated_*`: seeded random mutations of `.nmat`, model and checkpoint
//!   files; none may panic, and any file that is accepted must decode to
//!   the values of the original.
//! - SIGTERM and SIGHUP during training, then `--resume`: bit-identical to
//!   an uninterrupted run.
//! - A diverging run stops with one line and keeps its last good checkpoint.
//!
//! Counts: `cargo test --release --test hostile -- --nocapture`.

use flashmat::archive::Archive;
use flashmat::infer::NeuralMaterial;
use flashmat::model::{Model, ModelConfig, ModelInfo};
use flashmat::train::run::{self, RunOptions};
use flashmat::train::{TrainConfig, Trainer};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use serde_json::{Map, Value};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use tch::Device;

const BIN: &str = env!("CARGO_BIN_EXE_flashmat");

/// Address space of every child process: libtorch maps about 3 GB of
/// libraries; the allocations the limits refuse are tens of GB.
const MEMORY_CAP_KB: u64 = 6 << 20;

/// Longest a case may take: a blocked read (a FIFO) is a hang.
const CASE_TIMEOUT: Duration = Duration::from_secs(90);

/// What a finished child left: exit code (None: killed by a signal),
/// stderr, and whether it ran out of time.
struct Outcome {
    code: Option<i32>,
    stderr: String,
    timed_out: bool,
}

/// Runs flashmat with `args` in `cwd` under [`MEMORY_CAP_KB`] and
/// [`CASE_TIMEOUT`].
fn run_capped(args: &[String], cwd: &Path, logs: &Path) -> Outcome {
    std::fs::create_dir_all(logs).unwrap();
    let (out, err) = (logs.join("stdout"), logs.join("stderr"));
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {MEMORY_CAP_KB} && exec \"$0\" \"$@\""))
        .arg(BIN)
        .args(args)
        .current_dir(cwd)
        .env("OMP_WAIT_POLICY", "PASSIVE")
        .env("OMP_NUM_THREADS", "1")
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap())
        .spawn()
        .expect("run flashmat");
    let start = Instant::now();
    let (status, timed_out) = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break (s, false);
        }
        if start.elapsed() > CASE_TIMEOUT {
            let _ = child.kill();
            break (child.wait().unwrap(), true);
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Outcome { code: status.code(), stderr: std::fs::read_to_string(&err).unwrap_or_default(), timed_out }
}

/// Signs of a crash in stderr: our panic hook, Rust's abort on a failed
/// allocation, C++ exceptions and frames.
fn crash_text(stderr: &str) -> Option<&'static str> {
    ["internal error", "panicked", "memory allocation of", "terminate called", "Exception raised from", "frame #", "C++", "Segmentation", "Aborted"]
        .into_iter()
        .find(|t| stderr.contains(t))
}

/// How a case must end.
enum Expect {
    /// Exit 1, exactly one line "error: ..." holding every needle.
    Error(Vec<String>),
    /// A refusal by the option parser (clap): exit 2, first line "error: ..." holding every needle.
    Usage(Vec<String>),
}

fn error(needles: &[&str]) -> Expect {
    Expect::Error(needles.iter().map(|s| s.to_string()).collect())
}

fn usage(needles: &[&str]) -> Expect {
    Expect::Usage(needles.iter().map(|s| s.to_string()).collect())
}

struct Case {
    name: String,
    /// Arguments; `{out}` is replaced by the case's own empty output folder.
    args: Vec<String>,
    expect: Expect,
}

/// Files under `dir` (relative paths, with sizes), sorted; special files included.
fn listing(dir: &Path) -> Vec<(String, u64)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let e = e.unwrap();
            let meta = std::fs::symlink_metadata(e.path()).unwrap();
            let rel = e.path().strip_prefix(dir).unwrap().display().to_string();
            if meta.is_dir() {
                stack.push(e.path());
                out.push((rel + "/", 0));
            } else {
                out.push((rel, meta.len()));
            }
        }
    }
    out.sort();
    out
}

/// The verdict on one case: None when it ended as it must.
fn judge(c: &Case, o: &Outcome, leftovers: &[(String, u64)]) -> Option<(&'static str, String)> {
    let first = o.stderr.lines().find(|l| !l.trim().is_empty()).unwrap_or("").to_string();
    if o.timed_out {
        return Some(("hang", format!("no exit after {CASE_TIMEOUT:?}")));
    }
    let Some(code) = o.code else { return Some(("crash", format!("killed by a signal; stderr: {}", o.stderr))) };
    if let Some(t) = crash_text(&o.stderr) {
        return Some(("crash", format!("'{t}' in stderr: {}", o.stderr)));
    }
    if code == 0 {
        return Some(("silent accept", format!("exit 0; stderr: {}", o.stderr)));
    }
    if !leftovers.is_empty() {
        return Some(("leftover", format!("{leftovers:?}")));
    }
    let (want_code, needles) = match &c.expect {
        Expect::Error(n) => (1, n),
        Expect::Usage(n) => (2, n),
    };
    if code != want_code {
        return Some(("wrong exit code", format!("exit {code}, expected {want_code}: {}", o.stderr)));
    }
    let lines = o.stderr.lines().filter(|l| !l.trim().is_empty()).count();
    if !first.starts_with("error: ") || (want_code == 1 && lines != 1) {
        return Some(("message", format!("expected one 'error: ' line, got: {}", o.stderr)));
    }
    if let Some(n) = needles.iter().find(|n| !first.contains(*n)) {
        return Some(("message", format!("'{n}' not in: {first}")));
    }
    None
}

// ---------------------------------------------------------------------------
// Building the corpus.

/// A co-located flash render of a procedural material, linear `[3, H, W]`.
fn flash_render(width: usize, height: usize) -> flashmat::image::Image {
    let side = width.max(height);
    let m = flashmat::data::procedural::generate(21, &flashmat::data::procedural::ProceduralConfig::with_size(side));
    let m = m.crop((side - height) / 2, (side - width) / 2, height, width).unwrap();
    flashmat::svbrdf::render::render_material(&m, &[flashmat::geometry::LightView::colocated(28.0)]).unwrap().remove(0)
}

/// The smallest model the architecture allows: archives of a few hundred
/// kilobytes, so thousands of mutations take seconds.
fn mini_config() -> ModelConfig {
    ModelConfig {
        name: "mini".into(),
        est_width: 2,
        neural_channels: 4,
        enc_frequencies: 2,
        enc_hidden: 8,
        enc_out: 4,
        render_hidden: 8,
        render_narrow: 4,
        disc_width: 2,
        half_angle_feature: false,
        ggx_codes: false,
    }
}

fn mini_train_config(model: ModelConfig) -> TrainConfig {
    TrainConfig { model, material_size: 32, crop: 32, outputs_per_material: 1, weight_lpips: 0.0, steps: 1, checkpoint_every: 1, preview_every: 0, seed: 3, ..Default::default() }
}

/// A safetensors file's JSON header and data.
fn split(bytes: &[u8]) -> (Map<String, Value>, Vec<u8>) {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    (serde_json::from_slice(&bytes[8..8 + n]).unwrap(), bytes[8 + n..].to_vec())
}

/// Byte range of a tensor's data.
fn offsets(header: &Map<String, Value>, name: &str) -> std::ops::Range<usize> {
    let o = header[name]["data_offsets"].as_array().unwrap();
    o[0].as_u64().unwrap() as usize..o[1].as_u64().unwrap() as usize
}

/// Rewrites a flashmat archive after `edit` with both checksums recomputed
/// as docs/NMAT.md specifies them: a forgery that only the content checks
/// can refuse (and a check of the specification).
fn reseal(bytes: &[u8], edit: impl FnOnce(&mut Map<String, Value>, &mut Vec<u8>)) -> Vec<u8> {
    let (mut header, mut data) = split(bytes);
    edit(&mut header, &mut data);
    let mut meta: BTreeMap<String, String> =
        header.remove("__metadata__").unwrap().as_object().unwrap().iter().map(|(k, v)| (k.clone(), v.as_str().unwrap().to_string())).collect();
    let mut names: Vec<String> = header.keys().cloned().collect();
    names.sort();
    let mut crc = crc32fast::Hasher::new();
    for n in &names {
        crc.update(n.as_bytes());
        crc.update(&data[offsets(&header, n)]);
    }
    meta.insert("flashmat.crc32".into(), format!("{:08x}", crc.finalize()));
    let mut crc = crc32fast::Hasher::new();
    let mut field = |s: &str| {
        crc.update(s.as_bytes());
        crc.update(&[0]);
    };
    for n in &names {
        field(n);
        field(header[n]["dtype"].as_str().unwrap());
        field(&header[n]["shape"].as_array().unwrap().iter().map(|d| d.to_string()).collect::<Vec<_>>().join(","));
    }
    for (k, v) in meta.iter().filter(|(k, _)| *k != "flashmat.meta_crc32") {
        field(k);
        field(v);
    }
    meta.insert("flashmat.meta_crc32".into(), format!("{:08x}", crc.finalize()));
    header.insert("__metadata__".into(), serde_json::to_value(&meta).unwrap());
    let mut json = serde_json::to_vec(&header).unwrap();
    while json.len() % 8 != 0 {
        json.push(b' ');
    }
    [&(json.len() as u64).to_le_bytes()[..], &json, &data].concat()
}

/// Sets the first value of a tensor (F32 or F16) in a split archive.
fn set_first(header: &Map<String, Value>, data: &mut [u8], name: &str, v: f32) {
    let at = offsets(header, name).start;
    match header[name]["dtype"].as_str().unwrap() {
        "F32" => data[at..at + 4].copy_from_slice(&v.to_le_bytes()),
        _ => data[at..at + 2].copy_from_slice(&half::f16::from_f32(v).to_le_bytes()),
    }
}

/// An OpenEXR file (one float channel Y, no compression) whose header says
/// `w x h` pixels, with a complete offset table (one chunk per line) but a
/// single chunk of data: what a hostile file of about 8 bytes per claimed
/// line looks like.
fn hostile_exr(w: i32, h: i32) -> Vec<u8> {
    fn attr(out: &mut Vec<u8>, name: &str, kind: &str, data: &[u8]) {
        out.extend_from_slice(name.as_bytes());
        out.push(0);
        out.extend_from_slice(kind.as_bytes());
        out.push(0);
        out.extend_from_slice(&(data.len() as i32).to_le_bytes());
        out.extend_from_slice(data);
    }
    let window: Vec<u8> = [0i32, 0, w - 1, h - 1].iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut channel = b"Y\0".to_vec();
    channel.extend_from_slice(&2i32.to_le_bytes()); // FLOAT
    channel.extend_from_slice(&[0, 0, 0, 0]);
    channel.extend_from_slice(&1i32.to_le_bytes());
    channel.extend_from_slice(&1i32.to_le_bytes());
    channel.push(0);
    let mut out = vec![0x76, 0x2F, 0x31, 0x01, 2, 0, 0, 0];
    attr(&mut out, "channels", "chlist", &channel);
    attr(&mut out, "compression", "compression", &[0]);
    attr(&mut out, "dataWindow", "box2i", &window);
    attr(&mut out, "displayWindow", "box2i", &window);
    attr(&mut out, "lineOrder", "lineOrder", &[0]);
    attr(&mut out, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    attr(&mut out, "screenWindowCenter", "v2f", &[0; 8]);
    attr(&mut out, "screenWindowWidth", "float", &1f32.to_le_bytes());
    out.push(0);
    let first_chunk = (out.len() + 8 * h as usize) as u64;
    for _ in 0..h {
        out.extend_from_slice(&first_chunk.to_le_bytes());
    }
    out.extend_from_slice(&0i32.to_le_bytes());
    out.extend_from_slice(&w.saturating_mul(4).to_le_bytes());
    out.extend_from_slice(&vec![0u8; (4 * w as usize).min(4096)]);
    out
}

fn mkfifo(path: &Path) {
    assert!(Command::new("mkfifo").arg(path).status().unwrap().success());
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> String {
    std::fs::write(dir.join(name), bytes).unwrap();
    format!("in/{name}")
}

fn flip(bytes: &[u8], at: usize, mask: u8) -> Vec<u8> {
    let mut b = bytes.to_vec();
    b[at] ^= mask;
    b
}

/// Length of a safetensors header (the JSON part).
fn header_len(bytes: &[u8]) -> usize {
    u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize
}

/// The inputs (in `root/in`) and the cases run on them.
fn build_corpus(root: &Path) -> Vec<Case> {
    let dir = root.join("in");
    std::fs::create_dir_all(&dir).unwrap();
    let d = dir.as_path();

    // Valid inputs.
    let linear = flash_render(160, 120);
    let display = linear.map(flashmat::spaces::gamma_encode);
    flashmat::io::write_png(&d.join("photo.png"), &display, flashmat::io::BitDepth::Eight).unwrap();
    flashmat::io::write_jpeg(&d.join("photo.jpg"), &display, 90).unwrap();
    flashmat::io::write_exr(&d.join("photo.exr"), &flash_render(64, 64)).unwrap();
    tch::manual_seed(1);
    let model = Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap();
    let info = ModelInfo { ldr_input: true, steps: 3 };
    model.save(d.join("tiny.safetensors"), &info, true).unwrap();
    model.save(d.join("tiny32.safetensors"), &info, false).unwrap();
    let photo = flashmat::infer::load_photo(&d.join("photo.png"), None, 64).unwrap();
    let material = flashmat::infer::estimate(&model, &info, &photo).unwrap();
    material.save(&d.join("m.nmat")).unwrap();
    run::start(mini_train_config(ModelConfig::tiny()), &RunOptions { max_steps_this_run: Some(1), ..RunOptions::new(d.join("run"), Device::Cpu, false) }).unwrap();
    let read = |name: &str| std::fs::read(d.join(name)).unwrap();
    let (png, jpg, exr, nmat, tiny, ckpt) = (read("photo.png"), read("photo.jpg"), read("photo.exr"), read("m.nmat"), read("tiny.safetensors"), read("run/checkpoint.safetensors"));

    let mut cases = Vec::new();
    let est = |photo: &str, extra: &[&str]| -> Vec<String> {
        let mut a = vec!["estimate".to_string(), photo.to_string(), "--model".into(), "in/tiny.safetensors".into(), "--size".into(), "64".into(), "-o".into(), "{out}/m.nmat".into()];
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let push = |cases: &mut Vec<Case>, name: String, args: Vec<String>, expect: Expect| cases.push(Case { name, args, expect });

    // Hostile image headers: 100000 x 100000 pixels in a few hundred bytes.
    let mut b = png.clone();
    b[16..20].copy_from_slice(&100_000u32.to_be_bytes());
    b[20..24].copy_from_slice(&100_000u32.to_be_bytes());
    let crc = crc32fast::hash(&b[12..29]);
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    let huge_png = write(d, "huge.png", &b);
    let mut b = jpg.clone();
    let sof = b.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
    b[sof + 5..sof + 9].copy_from_slice(&[0xFF; 4]);
    let huge_jpg = write(d, "huge.jpg", &b);
    let huge_exr = write(d, "huge.exr", &hostile_exr(100_000, 100_000));
    let wide_exr = write(d, "wide.exr", &hostile_exr(1 << 30, 4));
    for (name, path) in [("png", &huge_png), ("jpg", &huge_jpg), ("exr", &huge_exr)] {
        push(&mut cases, format!("hostile {name} header: estimate"), est(path, &[]), error(&["FLASHMAT_MAX_IMAGE_PIXELS", "above the limit"]));
        push(&mut cases, format!("hostile {name} header: relight"), vec!["relight".into(), path.clone(), "--identity".into(), "--model".into(), "in/tiny.safetensors".into(), "-o".into(), "{out}/r.png".into()], error(&["FLASHMAT_MAX_IMAGE_PIXELS"]));
        push(&mut cases, format!("hostile {name} header: show"), vec!["show".into(), path.clone(), "--model".into(), "in/tiny.safetensors".into(), "-o".into(), "{out}/s.png".into()], error(&["FLASHMAT_MAX_IMAGE_PIXELS"]));
    }
    push(&mut cases, "hostile exr: 2^30 pixels wide".into(), est(&wide_exr, &[]), error(&["wide.exr"]));

    // Truncations at several offsets.
    for (name, bytes, cuts) in [
        ("png", &png, vec![8, 33, png.len() / 2, png.len() - 12]),
        ("jpg", &jpg, vec![2, 200, jpg.len() / 3, jpg.len() / 2, jpg.len() - 40, jpg.len() - 2]),
        ("exr", &exr, vec![4, 100, exr.len() / 2, exr.len() - 10]),
    ] {
        for cut in cuts {
            let p = write(d, &format!("cut{cut}.{name}"), &bytes[..cut]);
            push(&mut cases, format!("truncated {name} at {cut}"), est(&p, &[]), error(&["cannot read image", &p]));
        }
    }
    for cut in [0, 8, 100, header_len(&nmat) + 8, nmat.len() / 2, nmat.len() - 1] {
        let p = write(d, &format!("cut{cut}.nmat"), &nmat[..cut]);
        push(&mut cases, format!("truncated nmat at {cut}"), vec!["relight".into(), p.clone(), "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&[&p]));
    }
    for cut in [100, tiny.len() / 2] {
        let p = write(d, &format!("cut{cut}.safetensors"), &tiny[..cut]);
        push(&mut cases, format!("truncated model at {cut}"), vec!["estimate".into(), "in/photo.png".into(), "--model".into(), p.clone(), "--size".into(), "64".into(), "-o".into(), "{out}/m.nmat".into()], error(&[&p]));
    }

    // Bit flips: PNG chunks carry CRCs, archives two checksums.
    for at in [12, 18, 40, png.len() / 2] {
        let p = write(d, &format!("flip{at}.png"), &flip(&png, at, 0x10));
        push(&mut cases, format!("png bit flip at {at}"), est(&p, &[]), error(&["cannot read image"]));
    }
    // (OpenEXR has no checksum: a flip in its pixels is undetectable, one in its structure is not.)
    let ty = exr.windows(7).position(|w| w == b"chlist\0").unwrap() + 7 + 4 + 2; // first channel's pixel type
    let exr_flip = write(d, "flip.exr", &flip(&exr, ty, 0x03)); // FLOAT -> HALF
    push(&mut cases, "exr channel type bit flip".into(), est(&exr_flip, &[]), error(&["flip.exr", "corrupt"]));
    for at in [9, 30, header_len(&nmat) / 2, header_len(&nmat) + 20, nmat.len() - 100] {
        let p = write(d, &format!("flip{at}.nmat"), &flip(&nmat, at, 0x04));
        push(&mut cases, format!("nmat bit flip at {at}"), vec!["relight".into(), p.clone(), "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&[&p]));
    }
    let p = write(d, "flipped.safetensors", &flip(&tiny, tiny.len() / 3, 0x20));
    push(&mut cases, "model bit flip".into(), est("in/photo.png", &[]).into_iter().map(|a| a.replace("in/tiny.safetensors", &p)).collect(), error(&["flipped.safetensors", "checksum"]));
    std::fs::create_dir_all(d.join("run-flipped")).unwrap();
    std::fs::write(d.join("run-flipped/checkpoint.safetensors"), flip(&ckpt, ckpt.len() / 3, 0x20)).unwrap();
    push(&mut cases, "checkpoint bit flip: resume".into(), vec!["train".into(), "--resume".into(), "in/run-flipped".into()], error(&["checkpoint.safetensors", "checksum"]));
    push(&mut cases, "checkpoint bit flip: export".into(), vec!["export".into(), "--run".into(), "in/run-flipped".into(), "-o".into(), "{out}/m.safetensors".into()], error(&["checkpoint.safetensors", "checksum"]));
    let average = |files: &[&str]| -> Vec<String> { ["average"].iter().chain(files).chain(&["-o", "{out}/avg.safetensors"]).map(|s| s.to_string()).collect() };
    push(&mut cases, "average: a damaged model among them".into(), average(&["in/tiny.safetensors", &p]), error(&["flipped.safetensors", "checksum"]));
    push(&mut cases, "average: a missing model".into(), average(&["in/tiny.safetensors", "in/absent.safetensors"]), error(&["absent.safetensors"]));
    push(&mut cases, "average: a checkpoint instead of a model".into(), average(&["in/tiny.safetensors", "in/run/checkpoint.safetensors"]), error(&["checkpoint.safetensors"]));
    push(&mut cases, "average: no model".into(), vec!["average".into(), "-o".into(), "{out}/avg.safetensors".into()], usage(&["required arguments"]));
    push(
        &mut cases,
        "train --checkerboard-free on a baseline".into(),
        ["train", "--method", "analytic", "--checkerboard-free", "--preset", "tiny", "--steps", "1", "--out", "{out}/cb-run"].map(String::from).to_vec(),
        error(&["--checkerboard-free", "flashmat only"]),
    );

    // Forged archives: checksums recomputed over the edited content.
    let swapped = reseal(&nmat, |h, _| {
        for name in ["neural_map", "input_photo"] {
            let s = h[name]["shape"].as_array_mut().unwrap();
            s.swap(0, 1);
        }
    });
    let p = write(d, "swapped.nmat", &swapped);
    push(&mut cases, "nmat with swapped dimensions, checksums recomputed".into(), vec!["relight".into(), p, "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&["swapped.nmat"]));
    let mut swapped_meta = split(&nmat).0["__metadata__"].as_object().unwrap().clone();
    swapped_meta.insert("resolution".into(), Value::String("[64,65]".into()));
    let p = write(d, "resolution.nmat", &reseal(&nmat, |h, _| { h.insert("__metadata__".into(), Value::Object(swapped_meta)); }));
    push(&mut cases, "nmat with a forged resolution".into(), vec!["relight".into(), p, "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&["resolution.nmat", "resolution"]));
    for (what, v) in [("nan", f32::NAN), ("inf", f32::INFINITY)] {
        let p = write(d, &format!("{what}.nmat"), &reseal(&nmat, |h, data| set_first(h, data, "neural_map", v)));
        push(&mut cases, format!("nmat holding {what}: relight"), vec!["relight".into(), p.clone(), "--light".into(), "1,0,2".into(), "-o".into(), "{out}/r.exr".into()], error(&["non-finite"]));
        push(&mut cases, format!("nmat holding {what}: nmat-rows"), vec!["nmat-rows".into(), p.clone(), "-o".into(), "{out}/rows.json".into()], error(&["non-finite"]));
        let p = write(d, &format!("{what}.safetensors"), &reseal(&tiny, |h, data| {
            let name = h.keys().find(|k| k.starts_with("est.") && k.ends_with("weight")).unwrap().clone();
            set_first(h, data, &name, v)
        }));
        push(&mut cases, format!("model holding {what}"), vec!["estimate".into(), "in/photo.png".into(), "--model".into(), p, "--size".into(), "64".into(), "-o".into(), "{out}/m.nmat".into()], error(&["non-finite"]));
    }
    // Finite weights far out of range (what a diverged run used to export): the estimate overflows.
    let (huge, _) = Model::load(d.join("tiny32.safetensors"), Device::Cpu).unwrap();
    tch::no_grad(|| huge.est_vs.variables().values().for_each(|v| {
        let _ = v.shallow_clone().g_mul_scalar_(1e30);
    }));
    huge.save(d.join("huge-weights.safetensors"), &info, false).unwrap();
    push(&mut cases, "model with 1e30 weights: estimate".into(), est("in/photo.png", &[]).into_iter().map(|a| a.replace("tiny.safetensors", "huge-weights.safetensors")).collect(), error(&["huge-weights.safetensors", "NaN/Inf"]));
    drop(huge);

    // Inputs that parse but contradict themselves or describe nothing.
    let nmat_meta = split(&nmat).0["__metadata__"].as_object().unwrap().clone();
    let with_meta = |key: &str, value: &str| -> Vec<u8> {
        let mut meta = nmat_meta.clone();
        meta.insert(key.into(), Value::String(value.into()));
        reseal(&nmat, |h, _| {
            h.insert("__metadata__".into(), Value::Object(meta));
        })
    };
    let relight = |p: String| -> Vec<String> { vec!["relight".into(), p, "--identity".into(), "-o".into(), "{out}/r.png".into()] };
    let p = write(d, "fov-nan.nmat", &with_meta("fov_deg", "NaN"));
    push(&mut cases, "nmat with fov_deg NaN, checksums recomputed".into(), relight(p), error(&["fov-nan.nmat", "'fov_deg' is NaN"]));
    let p = write(d, "crop-outside.nmat", &with_meta("crop", r#"{"x0":100,"y0":0,"width":150,"height":120,"source_width":160,"source_height":120}"#));
    push(&mut cases, "nmat with a crop outside its photo, checksums recomputed".into(), relight(p), error(&["crop-outside.nmat", "outside its 160x120 source photo"]));
    // Both tensors and the resolution transposed: consistent, but not with the crop.
    let transposed = reseal(&nmat, |h, _| {
        for name in ["neural_map", "input_photo"] {
            h[name]["shape"].as_array_mut().unwrap().swap(1, 2);
        }
        let mut meta = h["__metadata__"].as_object().unwrap().clone();
        let r: Vec<i64> = serde_json::from_str(meta["resolution"].as_str().unwrap()).unwrap();
        meta.insert("resolution".into(), Value::String(format!("[{},{}]", r[1], r[0])));
        h.insert("__metadata__".into(), Value::Object(meta));
    });
    let p = write(d, "transposed.nmat", &transposed);
    push(&mut cases, "nmat stored transposed with a matching resolution".into(), relight(p), error(&["transposed.nmat", "aspect"]));
    flashmat::io::write_exr(&d.join("allneg.exr"), &flashmat::image::Image::filled(3, 64, 64, -0.25)).unwrap();
    push(&mut cases, "exr photo with every value negative".into(), est("in/allneg.exr", &[]), error(&["allneg.exr", "the photo is black"]));
    // Material folders with float maps no material has.
    for (name, map, channels, v, needle) in [
        ("neg-diffuse", "diffuse", 3, -1.0f32, "diffuse.exr has the value -1"),
        ("huge-specular", "specular", 3, 1e30, "specular.exr has the value 1000000000000000000000000000000"),
        ("zero-normals", "normals", 3, 0.5, "zero-length normal"),
    ] {
        let m = d.join(name);
        flashmat::data::loaders::write_material_dir(&m, &flashmat::svbrdf::Svbrdf::uniform(32, 32, [0.3; 3], [0.04; 3], 0.5)).unwrap();
        std::fs::remove_file(m.join(format!("{map}.png"))).unwrap();
        flashmat::io::write_exr(&m.join(format!("{map}.exr")), &flashmat::image::Image::filled(channels, 32, 32, v)).unwrap();
        let dir = format!("in/{name}");
        push(&mut cases, format!("material {name}: render"), vec!["render".into(), "--svbrdf".into(), dir.clone(), "-o".into(), "{out}/r.png".into()], error(&[needle]));
        // Training stops on it, naming the material.
        push(&mut cases, format!("material {name}: train"), ["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--lpips-weight", "0", "--threads", "1", "--steps", "1", "--data", &dir, "--out", "{out}/run"].map(String::from).to_vec(), error(&[needle, &format!("material {name}: ")]));
    }
    // A run already at step 1 asked for a total of 1 (or fewer) steps.
    push(&mut cases, "train --resume to a total it already reached".into(), ["train", "--resume", "in/run", "--steps", "1"].map(String::from).to_vec(), error(&["run in/run is already at step 1", "--steps 1"]));
    // Run folders owned by another process (the test holds their locks).
    std::fs::create_dir_all(d.join("owned-run")).unwrap();
    for f in ["checkpoint.safetensors", "config.json"] {
        std::fs::copy(d.join("run").join(f), d.join("owned-run").join(f)).unwrap();
    }
    std::fs::create_dir_all(d.join("owned-new")).unwrap();
    push(&mut cases, "train --resume of a folder another process trains".into(), ["train", "--resume", "in/owned-run"].map(String::from).to_vec(), error(&["in/owned-run is in use by flashmat pid", "wait for it to finish"]));
    push(&mut cases, "train --out a folder another process owns".into(), ["train", "--preset", "tiny", "--crop", "32", "--steps", "1", "--out", "in/owned-new"].map(String::from).to_vec(), error(&["in/owned-new is in use by flashmat pid"]));

    // Misleading names: a damaged picture is not a damaged material.
    let garbage: Vec<u8> = (0..3000u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
    let p = write(d, "garbage.png", &garbage);
    push(&mut cases, "garbage .png to relight".into(), vec!["relight".into(), p, "--identity".into(), "--model".into(), "in/tiny.safetensors".into(), "-o".into(), "{out}/r.png".into()], error(&["garbage.png", "not a valid .png"]));
    let p = write(d, "garbage.nmat", &garbage);
    push(&mut cases, "garbage .nmat".into(), vec!["show".into(), p, "-o".into(), "{out}/s.png".into()], error(&["garbage.nmat", "nmat"]));
    push(&mut cases, "model file as material".into(), vec!["relight".into(), "in/tiny.safetensors".into(), "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&["tiny.safetensors", "expected a 'flashmat-nmat'"]));
    push(&mut cases, "material as model".into(), est("in/photo.png", &[]).into_iter().map(|a| a.replace("tiny.safetensors", "m.nmat")).collect(), error(&["m.nmat", "expected a 'flashmat-model'"]));
    for (name, bytes) in [("empty.png", &b""[..]), ("empty.nmat", &b""[..])] {
        let p = write(d, name, bytes);
        push(&mut cases, format!("empty {name}"), vec!["relight".into(), p, "--identity".into(), "--model".into(), "in/tiny.safetensors".into(), "-o".into(), "{out}/r.png".into()], error(&[name]));
    }
    let nan_exr = flashmat::image::Image::from_fn(3, 64, 64, |c, y, x| if (c, y, x) == (1, 5, 6) { f32::INFINITY } else { 0.5 });
    flashmat::io::write_exr(&d.join("inf.exr"), &nan_exr).unwrap();
    push(&mut cases, "exr holding inf".into(), est("in/inf.exr", &[]), error(&["inf.exr", "row 5, column 6"]));

    // Special files.
    mkfifo(&d.join("fifo.png"));
    mkfifo(&d.join("fifo.nmat"));
    mkfifo(&d.join("fifo.safetensors"));
    mkfifo(&d.join("fifo.toml"));
    mkfifo(&d.join("out-fifo.nmat"));
    mkfifo(&d.join("out-fifo.png"));
    std::fs::create_dir_all(d.join("folder.nmat")).unwrap();
    std::fs::File::create(d.join("sparse.png")).unwrap().set_len(flashmat::limits::FILE_BYTES.get() + 1).unwrap();
    push(&mut cases, "FIFO as photo".into(), est("in/fifo.png", &[]), error(&["fifo.png", "FIFO"]));
    push(&mut cases, "FIFO as material".into(), vec!["relight".into(), "in/fifo.nmat".into(), "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&["fifo.nmat", "FIFO"]));
    push(&mut cases, "FIFO as model".into(), est("in/photo.png", &[]).into_iter().map(|a| a.replace("tiny.safetensors", "fifo.safetensors")).collect(), error(&["fifo.safetensors", "FIFO"]));
    push(&mut cases, "FIFO as model config".into(), vec!["train".into(), "--model-config".into(), "in/fifo.toml".into(), "--out".into(), "{out}/run".into()], error(&["fifo.toml", "FIFO"]));
    push(&mut cases, "FIFO as nmat-rows input".into(), vec!["nmat-rows".into(), "in/fifo.nmat".into(), "-o".into(), "{out}/rows.json".into()], error(&["fifo.nmat", "FIFO"]));
    push(&mut cases, "character device as photo".into(), est("/dev/zero", &[]), error(&["/dev/zero", "character device"]));
    push(&mut cases, "character device as material".into(), vec!["show".into(), "/dev/null".into(), "-o".into(), "{out}/s.png".into()], error(&["/dev/null", "character device"]));
    push(&mut cases, "folder as photo".into(), est("in", &[]), error(&["directory"]));
    push(&mut cases, "folder as material".into(), vec!["relight".into(), "in/folder.nmat".into(), "--identity".into(), "-o".into(), "{out}/r.png".into()], error(&["folder.nmat", "directory"]));
    push(&mut cases, "sparse file over the size limit".into(), est("in/sparse.png", &[]), error(&["sparse.png", "FLASHMAT_MAX_FILE_BYTES"]));
    push(&mut cases, "FIFO as output".into(), est("in/photo.png", &[]).into_iter().map(|a| a.replace("{out}/m.nmat", "in/out-fifo.nmat")).collect(), error(&["out-fifo.nmat", "not a regular file"]));
    push(&mut cases, "folder as output".into(), est("in/photo.png", &[]).into_iter().map(|a| a.replace("{out}/m.nmat", "in/folder.nmat")).collect(), error(&["folder.nmat", "not a regular file"]));
    push(&mut cases, "FIFO as render output".into(), ["render", "--svbrdf", "procedural:1", "--size", "16", "-o", "in/out-fifo.png"].map(String::from).to_vec(), error(&["out-fifo.png", "not a regular file"]));

    // A failed command leaves no output folder behind.
    push(&mut cases, "failed estimate into new folders".into(), est("in/garbage.png", &[]).into_iter().map(|a| a.replace("{out}/m.nmat", "{out}/new/sub/m.nmat")).collect(), error(&["garbage.png"]));
    push(&mut cases, "failed export into new folders".into(), vec!["export".into(), "--run".into(), "in/run-flipped".into(), "-o".into(), "{out}/new/m.safetensors".into()], error(&["checksum"]));

    // Absurd sizes and counts: refused before anything is allocated.
    let toml_wide = write(d, "wide.toml", b"name = \"wide\"\nest_width = 100000\n");
    let toml_hidden = write(d, "hidden.toml", b"name = \"deep\"\nenc_hidden = 1000000000\n");
    // A tiny run, `extra` replacing its options of the same name.
    let train = |extra: &[&str]| -> Vec<String> {
        let base = [("--preset", "tiny"), ("--crop", "32"), ("--outputs", "2"), ("--lpips-weight", "0"), ("--threads", "1"), ("--steps", "2"), ("--out", "{out}/run")];
        let mut a = vec!["train".to_string()];
        for (k, v) in base.iter().filter(|(k, _)| !extra.iter().any(|e| e == k || e.starts_with(&format!("{k}=")))) {
            a.extend([k.to_string(), v.to_string()]);
        }
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let absurd: Vec<(&str, Vec<String>, Expect)> = vec![
        ("render --size 100000", vec!["render", "--svbrdf", "procedural:1", "--size", "100000", "-o", "{out}/r.png"].into_iter().map(String::from).collect(), error(&["--size is 100000", "FLASHMAT_MAX_MATERIAL_SIZE"])),
        ("render --size 0", vec!["render", "--svbrdf", "procedural:1", "--size", "0", "-o", "{out}/r.png"].into_iter().map(String::from).collect(), error(&["--size"])),
        ("render --light 1e308,0,1", vec!["render", "--svbrdf", "procedural:1", "--size", "16", "--light", "1e308,0,1", "-o", "{out}/r.png"].into_iter().map(String::from).collect(), usage(&["--light", "1e308"])),
        ("relight --light 1e308,0,1", vec!["relight", "in/m.nmat", "--light", "1e308,0,1", "-o", "{out}/r.png"].into_iter().map(String::from).collect(), usage(&["--light", "1e308"])),
        ("relight --view 0,0,1e300", vec!["relight", "in/m.nmat", "--identity", "--view", "0,0,1e300", "-o", "{out}/r.png"].into_iter().map(String::from).collect(), usage(&["--view"])),
        ("svbrdf generate --count 10^12", vec!["svbrdf", "generate", "--count", "1000000000000", "--size", "8", "--out", "{out}/data"].into_iter().map(String::from).collect(), error(&["--count", "FLASHMAT_MAX_COUNT"])),
        ("svbrdf generate --size 10^6", vec!["svbrdf", "generate", "--count", "1", "--size", "1000000", "--out", "{out}/data"].into_iter().map(String::from).collect(), error(&["--size", "FLASHMAT_MAX_MATERIAL_SIZE"])),
        ("svbrdf preview --count --size", vec!["svbrdf", "preview", "procedural", "--count", "100000", "--size", "4096", "-o", "{out}/p.png"].into_iter().map(String::from).collect(), error(&["preview grid", "FLASHMAT_MAX_IMAGE_PIXELS"])),
        ("estimate --size 4096", est("in/photo.png", &[]).into_iter().map(|a| if a == "64" { "4096".into() } else { a }).collect(), error(&["--size is 4096", "FLASHMAT_MAX_SIZE"])),
        ("estimate --size 0", est("in/photo.png", &[]).into_iter().map(|a| if a == "64" { "0".into() } else { a }).collect(), error(&["--size"])),
        ("estimate --fov nan", est("in/photo.png", &["--fov", "nan"]), error(&["--fov"])),
        ("relight --orbit 100000", vec!["relight", "in/m.nmat", "--orbit", "100000", "-o", "{out}/o.gif"].into_iter().map(String::from).collect(), error(&["--orbit"])),
        ("train --crop 100000", train(&["--crop", "100000"]), error(&["--crop is 100000", "FLASHMAT_MAX_CROP"])),
        ("train --batch 100000", train(&["--batch", "100000"]), error(&["--batch 100000", "FLASHMAT_MAX_STEP_PIXELS"])),
        ("train --outputs 100000", train(&["--outputs", "100000"]), error(&["FLASHMAT_MAX_STEP_PIXELS"])),
        ("train --bank 10^9", train(&["--bank", "1000000000"]), error(&["--bank 1000000000", "FLASHMAT_MAX_BANK_PIXELS"])),
        ("train --model-config est_width 100000", vec!["train".into(), "--model-config".into(), toml_wide, "--out".into(), "{out}/run".into()], error(&["wide.toml", "est_width is 100000", "FLASHMAT_MAX_EST_WIDTH"])),
        ("train --model-config enc_hidden 10^9", vec!["train".into(), "--model-config".into(), toml_hidden, "--out".into(), "{out}/run".into()], error(&["hidden.toml", "enc_hidden", "FLASHMAT_MAX_LAYER_WIDTH"])),
        ("train --threads 0", train(&["--threads", "0"]), usage(&["--threads"])),
        ("train --threads 100000", train(&["--threads", "100000"]), usage(&["--threads"])),
        ("train --grad-clip -1", train(&["--grad-clip=-1"]), usage(&["--grad-clip"])),
        ("train --grad-clip nan", train(&["--grad-clip", "nan"]), usage(&["--grad-clip"])),
        ("train --grad-clip 0", train(&["--grad-clip", "0"]), usage(&["--grad-clip"])),
        ("train --lr nan", train(&["--lr", "nan"]), usage(&["--lr"])),
        ("train --lr -1", train(&["--lr=-1"]), usage(&["--lr"])),
        ("train --minutes nan", train(&["--minutes", "nan"]), error(&["--minutes"])),
        ("train --data missing", train(&["--data", "/nonexistent/materials"]), error(&["/nonexistent/materials"])),
        ("train-teacher --pixels 10^12", vec!["train-teacher", "--preset", "tiny", "--pixels", "1000000000000", "--out", "{out}/teacher"].into_iter().map(String::from).collect(), error(&["--pixels", "FLASHMAT_MAX_STEP_PIXELS"])),
        ("train-teacher --threads 0", vec!["train-teacher", "--threads", "0", "--out", "{out}/teacher"].into_iter().map(String::from).collect(), usage(&["--threads"])),
        ("train-teacher --dark-floor nan", vec!["train-teacher", "--dark-floor", "nan", "--out", "{out}/teacher"].into_iter().map(String::from).collect(), usage(&["--dark-floor"])),
        ("train-teacher --min-roughness 0.01", vec!["train-teacher", "--preset", "tiny", "--min-roughness", "0.01", "--out", "{out}/teacher"].into_iter().map(String::from).collect(), error(&["--min-roughness must be from 0.02"])),
        ("nmat-rows --count 10^12", vec!["nmat-rows", "in/m.nmat", "--count", "1000000000000", "-o", "{out}/rows.json"].into_iter().map(String::from).collect(), error(&["--count", "FLASHMAT_MAX_COUNT"])),
        ("nmat-rows --count 0", vec!["nmat-rows", "in/m.nmat", "--count", "0", "-o", "{out}/rows.json"].into_iter().map(String::from).collect(), error(&["--count"])),
        ("train --phone-inputs without --ldr", vec!["train", "--preset", "tiny", "--phone-inputs", "0.5", "--out", "{out}/run"].into_iter().map(String::from).collect(), error(&["--phone-inputs needs --ldr "])),
        ("train --phone-jpeg without --phone-inputs", vec!["train", "--preset", "tiny", "--ldr", "--phone-jpeg", "--out", "{out}/run"].into_iter().map(String::from).collect(), usage(&["required arguments were not provided"])),
        ("eval --phone-photos without --ldr-input", vec!["eval", "--model", "printout", "--phone-photos", "-o", "{out}/report"].into_iter().map(String::from).collect(), usage(&["required arguments were not provided"])),
        ("eval --limit 0", vec!["eval", "--model", "printout", "--limit", "0", "-o", "{out}/report"].into_iter().map(String::from).collect(), usage(&["--limit"])),
        ("eval --configs 0", vec!["eval", "--model", "printout", "--configs", "0", "-o", "{out}/report"].into_iter().map(String::from).collect(), usage(&["--configs"])),
        ("eval --configs 10^12", vec!["eval", "--model", "printout", "--configs", "1000000000000", "-o", "{out}/report"].into_iter().map(String::from).collect(), usage(&["--configs", "FLASHMAT_MAX_COUNT"])),
        ("eval --size 100000", vec!["eval", "--model", "printout", "--size", "100000", "-o", "{out}/report"].into_iter().map(String::from).collect(), error(&["--size is 100000", "FLASHMAT_MAX_SIZE"])),
        ("shadow-eval --limit 0", vec!["shadow-eval", "--model", "printout", "--limit", "0", "-o", "{out}/report"].into_iter().map(String::from).collect(), usage(&["--limit"])),
    ];
    for (name, args, expect) in absurd {
        push(&mut cases, name.to_string(), args, expect);
    }
    // A diverging first step leaves no run folder (a diverging resumed run: see its own test).
    push(&mut cases, "train --lr 1e30 from scratch".into(), train(&["--lr", "1e30", "--checkpoint-every", "1"]), error(&["training diverged", "nothing was kept"]));
    cases
}

/// The bad-input corpus: every case ends in its one-line error, with no
/// crash, hang, silent accept or leftover file.
#[test]
fn bad_input_corpus() {
    let root = tempfile::tempdir().unwrap();
    let cases = build_corpus(root.path());
    // The owner of two run folders of the corpus, for as long as it runs.
    let _owners = ["owned-run", "owned-new"].map(|f| flashmat::io::lock_folder(&root.path().join("in").join(f)).unwrap());
    let inputs_before = listing(&root.path().join("in"));
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results = std::sync::Mutex::new(Vec::new());
    let started = Instant::now();
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                let Some(c) = cases.get(i) else { break };
                let out = root.path().join(format!("out/{i:03}"));
                std::fs::create_dir_all(&out).unwrap();
                let args: Vec<String> = c.args.iter().map(|a| a.replace("{out}", out.strip_prefix(root.path()).unwrap().to_str().unwrap())).collect();
                let o = run_capped(&args, root.path(), &root.path().join(format!("logs/{i:03}")));
                let left = listing(&out);
                let verdict = judge(c, &o, &left);
                results.lock().unwrap().push((i, verdict));
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|r| r.0);
    // Inputs are never modified, replaced or joined by temporaries.
    let inputs_after = listing(&root.path().join("in"));
    let mut counts: BTreeMap<&str, usize> = ["crash", "hang", "silent accept", "leftover", "wrong exit code", "message"].into_iter().map(|k| (k, 0)).collect();
    let mut failures = Vec::new();
    for (i, verdict) in &results {
        if let Some((kind, detail)) = verdict {
            *counts.entry(kind).or_default() += 1;
            failures.push(format!("[{}] {}: {kind}: {detail}", i, cases[*i].name));
        }
    }
    if inputs_after != inputs_before {
        *counts.entry("leftover").or_default() += 1;
        failures.push(format!("inputs changed: {:?}", inputs_after.iter().filter(|e| !inputs_before.contains(e)).collect::<Vec<_>>()));
    }
    eprintln!(
        "bad-input corpus: {} cases in {:.0} s under a {} GiB memory cap: {}",
        cases.len(),
        started.elapsed().as_secs_f64(),
        MEMORY_CAP_KB >> 20,
        counts.iter().map(|(k, v)| format!("{k} {v}")).collect::<Vec<_>>().join(", ")
    );
    assert!(failures.is_empty(), "{} of {} cases failed:\n{}", failures.len(), cases.len(), failures.join("\n"));
}

// ---------------------------------------------------------------------------
// Randomised mutations of the archive readers.

/// 1 to 3 random mutations of `original`. Half of them land in the 8-byte
/// length and the JSON header: small, but where the structure is.
fn mutate(rng: &mut Pcg64, original: &[u8]) -> Vec<u8> {
    let header_end = (8 + header_len(original)).min(original.len());
    let mut b = original.to_vec();
    for _ in 0..rng.random_range(1..=3) {
        if b.is_empty() {
            break;
        }
        let end = if rng.random_bool(0.5) { header_end.min(b.len()) } else { b.len() };
        let at = rng.random_range(0..end.max(1)).min(b.len() - 1);
        match rng.random_range(0..8) {
            0 => b[at] ^= 1 << rng.random_range(0..8),
            1 => b[at] = rng.random(),
            2 => {
                // Another digit: shapes, offsets, lengths and numbers in the metadata.
                if let Some(i) = (at..end.min(b.len())).find(|&i| b[i].is_ascii_digit()) {
                    b[i] = b'0' + rng.random_range(0..10u8);
                }
            }
            3 => b.truncate(at),
            4 => {
                let n = rng.random_range(1..16);
                let junk: Vec<u8> = (0..n).map(|_| rng.random()).collect();
                b.splice(at..at, junk);
            }
            5 => {
                let n = rng.random_range(1..16).min(b.len() - at);
                b.drain(at..at + n);
            }
            6 => {
                // A chunk copied over another place (same length).
                let n = rng.random_range(1..64).min(b.len() - at);
                let from = rng.random_range(0..=b.len() - n);
                let chunk = b[from..from + n].to_vec();
                b[at..at + n].copy_from_slice(&chunk);
            }
            _ => {
                let v = [0x00, 0xFF, 0x7F, 0x80, b'"', b',', b'[', b'-'][rng.random_range(0..8)];
                let n = rng.random_range(1..5).min(b.len() - at);
                b[at..at + n].fill(v);
            }
        }
    }
    b
}

/// Feeds `iterations` mutations of `original` to `load`. A mutation may be
/// refused (with a one-line message naming the file) or accepted when
/// `same` finds the values of the original; a panic or different values
/// fail. Returns (refused, accepted) counts.
fn fuzz<T>(name: &str, original: &[u8], iterations: usize, seed: u64, load: impl Fn(&Path) -> anyhow::Result<T>, same: impl Fn(&T) -> bool) -> (usize, usize) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(name);
    let mut rng = Pcg64::seed_from_u64(seed);
    let (mut refused, mut accepted, mut failures) = (0, 0, Vec::new());
    let started = Instant::now();
    for i in 0..iterations {
        let bytes = mutate(&mut rng, original);
        std::fs::write(&p, &bytes).unwrap();
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| load(&p))) {
            Err(_) => failures.push(format!("mutation {i} panicked")),
            Ok(Err(e)) => {
                refused += 1;
                let m = format!("{e:#}");
                if m.contains('\n') || !m.contains(name) {
                    failures.push(format!("mutation {i}: message not one line naming the file: {m}"));
                }
            }
            Ok(Ok(v)) if same(&v) => accepted += 1,
            Ok(Ok(_)) => failures.push(format!("mutation {i} was accepted with other values ({} bytes, {} changed)", bytes.len(), bytes.iter().zip(original).filter(|(a, b)| a != b).count())),
        }
        if failures.len() == 1 && failures[0].contains("mutation") && !dir.path().join("first-failure").exists() {
            std::fs::write(dir.path().join("first-failure"), &bytes).unwrap();
        }
    }
    eprintln!("{name}: {iterations} mutations in {:.1} s: {refused} refused, {accepted} accepted with identical values, {} failures", started.elapsed().as_secs_f64(), failures.len());
    assert!(failures.is_empty(), "{name}:\n{}", failures.join("\n"));
    (refused, accepted)
}

fn same_tensors(a: &[(String, tch::Tensor)], b: &[(String, tch::Tensor)]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|((na, ta), (nb, tb))| na == nb && ta.size() == tb.size() && ta.equal(tb))
}

fn sorted_vars(vs: &tch::nn::VarStore) -> Vec<(String, tch::Tensor)> {
    let mut v: Vec<_> = vs.variables().into_iter().collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

#[test]
fn mutated_nmat_files_are_refused_or_identical() {
    tch::manual_seed(7);
    let cfg = mini_config();
    let model = Model::new(&cfg, Device::Cpu).unwrap();
    let meta = flashmat::infer::NmatMeta {
        model_id: cfg.model_id(),
        fov_deg: 45.0,
        // The 6x10 map's aspect (a crop of another aspect is refused).
        crop: flashmat::infer::Crop { x0: 3, y0: 4, width: 20, height: 12, source_width: 26, source_height: 20 },
        source: "photo.png".into(),
        ldr_input: true,
        model_info: ModelInfo { ldr_input: true, steps: 7 },
        refine: None,
        gain: [0.5; 3],
    };
    // Not square: swapped dimensions must not go unnoticed.
    let map = tch::Tensor::randn([cfg.neural_channels, 6, 10], (tch::Kind::Float, Device::Cpu));
    let photo = tch::Tensor::rand([3, 6, 10], (tch::Kind::Float, Device::Cpu));
    let m = NeuralMaterial::from_parts(map, photo, &cfg, &model.renderer_vs.variables(), meta).unwrap();
    let dir = tempfile::tempdir().unwrap();
    m.save(&dir.path().join("m.nmat")).unwrap();
    let original = std::fs::read(dir.path().join("m.nmat")).unwrap();
    let (_, accepted) = fuzz("m.nmat", &original, 2000, 1, |p| NeuralMaterial::load(p, Device::Cpu), |b| {
        b.meta == m.meta
            && b.config == m.config
            && b.neural_map.equal(&m.neural_map)
            && b.input_photo.equal(&m.input_photo)
            && same_tensors(&sorted_vars(&b.renderer_vs), &sorted_vars(&m.renderer_vs))
    });
    assert!(accepted < 200, "most mutations must change something a check sees ({accepted} accepted)");
}

#[test]
fn mutated_model_files_are_refused_or_identical() {
    tch::manual_seed(8);
    let model = Model::new(&mini_config(), Device::Cpu).unwrap();
    let info = ModelInfo { ldr_input: false, steps: 12 };
    let dir = tempfile::tempdir().unwrap();
    model.save(dir.path().join("m.safetensors"), &info, true).unwrap();
    let original = std::fs::read(dir.path().join("m.safetensors")).unwrap();
    // What the file holds (large tensors as f16), not the model in memory.
    let (want, _) = Model::load(dir.path().join("m.safetensors"), Device::Cpu).unwrap();
    let want = want.named_variables();
    fuzz("m.safetensors", &original, 1500, 2, |p| Model::load(p, Device::Cpu), |(b, i)| *i == info && b.config == model.config && same_tensors(&b.named_variables(), &want));
}

#[test]
fn mutated_checkpoints_are_refused_or_identical() {
    let dir = tempfile::tempdir().unwrap();
    let opts = RunOptions { max_steps_this_run: Some(1), ..RunOptions::new(dir.path().join("run"), Device::Cpu, false) };
    run::start(mini_train_config(mini_config()), &opts).unwrap();
    let ckpt = run::checkpoint_path(&opts.run_dir);
    let original = std::fs::read(&ckpt).unwrap();
    let want = Archive::load(&ckpt, "flashmat-checkpoint", 1).unwrap();
    // Everything a resumed trainer holds, written back: weights, moments, step, configuration.
    let resaved = dir.path().join("resaved.safetensors");
    fuzz("checkpoint.safetensors", &original, 1000, 3, |p| Trainer::resume(p, Device::Cpu, None), |t| {
        t.save_checkpoint(&resaved).unwrap();
        let got = Archive::load(&resaved, "flashmat-checkpoint", 1).unwrap();
        got.metadata == want.metadata && got.tensors.len() == want.tensors.len() && got.tensors.iter().all(|(k, v)| want.tensors.get(k).is_some_and(|w| w.equal(v)))
    });
}

// ---------------------------------------------------------------------------
// Faults during training.

fn flashmat_cmd(args: &[&str], cwd: &Path) -> Command {
    let mut c = Command::new(BIN);
    c.args(args).current_dir(cwd).env("OMP_WAIT_POLICY", "PASSIVE").env("OMP_NUM_THREADS", "1").stdin(Stdio::null());
    c
}

fn checkpoint_step(run_dir: &Path) -> u64 {
    Archive::load(&run::checkpoint_path(run_dir), "flashmat-checkpoint", 1).unwrap().meta("step").unwrap().parse().unwrap()
}

fn log_lines(run_dir: &Path) -> usize {
    std::fs::read_to_string(run_dir.join("log.jsonl")).map(|t| t.lines().count()).unwrap_or(0)
}

/// Starts `args`, waits until the run's log holds `after` steps, sends
/// `signal`, and returns the finished process's stderr (it must exit 0).
fn interrupt(args: &[&str], cwd: &Path, run_dir: &Path, after: usize, signal: &str) -> String {
    let child = flashmat_cmd(args, cwd).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    let start = Instant::now();
    while log_lines(run_dir) < after {
        assert!(start.elapsed() < Duration::from_secs(120), "the run never reached step {after}");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(Command::new("kill").args([signal, &child.id().to_string()]).status().unwrap().success());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(0), "{signal}: {err}");
    assert!(!err.contains("internal error"), "{err}");
    err
}

/// SIGTERM (a scheduler, `kill`) and SIGHUP (a closed terminal) end a run
/// with a checkpoint like Ctrl-C; resumed, it is bit-identical to a run
/// that was never interrupted (as one killed with SIGKILL and resumed from
/// its last checkpoint is: `interrupted_and_resumed_run_equals_straight_run`).
#[test]
fn sigterm_and_sighup_checkpoint_and_the_resumed_run_is_bit_identical() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    const STEPS: u64 = 16;
    let steps = STEPS.to_string();
    let train = |out: &str| -> Vec<String> {
        ["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--lpips-weight", "0", "--threads", "1", "--steps", &steps, "--checkpoint-every", "1000", "--preview-every", "0", "--seed", "4", "--out", out]
            .map(String::from)
            .to_vec()
    };
    let straight = flashmat_cmd(&train("a").iter().map(String::as_str).collect::<Vec<_>>(), d).output().unwrap();
    assert!(straight.status.success(), "{}", String::from_utf8_lossy(&straight.stderr));

    let b = d.join("b");
    let args = train("b");
    let err = interrupt(&args.iter().map(String::as_str).collect::<Vec<_>>(), d, &b, 3, "-TERM");
    let k1 = checkpoint_step(&b);
    assert!(err.contains(&format!("run b at step {k1} of {STEPS}")), "{err}");
    assert!((3..STEPS).contains(&k1), "SIGTERM checkpoint at step {k1}");
    let err = interrupt(&["train", "--resume", "b"], d, &b, k1 as usize + 2, "-HUP");
    let k2 = checkpoint_step(&b);
    assert!(err.contains(&format!("run b at step {k2} of {STEPS}")), "{err}");
    assert!(k2 > k1 && k2 < STEPS, "SIGHUP checkpoint at step {k2} (after {k1})");
    let rest = flashmat_cmd(&["train", "--resume", "b"], d).output().unwrap();
    assert!(rest.status.success(), "{}", String::from_utf8_lossy(&rest.stderr));

    let (a, b_) = (Archive::load(&run::checkpoint_path(&d.join("a")), "flashmat-checkpoint", 1).unwrap(), Archive::load(&run::checkpoint_path(&b), "flashmat-checkpoint", 1).unwrap());
    assert_eq!(a.meta("step").unwrap(), steps);
    assert_eq!(a.metadata, b_.metadata);
    assert_eq!(a.tensors.len(), b_.tensors.len());
    for (name, t) in &a.tensors {
        assert!(t.equal(&b_.tensors[name]), "{name} differs after SIGTERM, SIGHUP and resume");
    }
    let logged: Vec<u64> = run::read_log(&b).iter().map(|l| l.step).collect();
    assert_eq!(logged, (1..=STEPS).collect::<Vec<_>>());
    eprintln!("SIGTERM at step {k1}, SIGHUP at step {k2}, resumed to {STEPS}: bit-identical to the straight run");
}

/// A diverging run stops with one line, writes nothing, keeps its last
/// good checkpoint (which exports and estimates), and continues with a
/// sane learning rate.
#[test]
fn diverging_run_stops_and_keeps_its_last_good_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let base = ["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--lpips-weight", "0", "--threads", "1", "--steps", "2", "--checkpoint-every", "1", "--preview-every", "1", "--out", "r"];
    let out = flashmat_cmd(&base, d).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let run_dir = d.join("r");
    let good = std::fs::read(run::checkpoint_path(&run_dir)).unwrap();
    let before = listing(&run_dir);

    let out = flashmat_cmd(&["train", "--resume", "r", "--lr", "1e30", "--steps", "12"], d).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty() && l.starts_with("error: ")).collect();
    assert_eq!(lines.len(), 1, "{err}");
    for needle in ["training diverged at step 3", "last good checkpoint (step 2)", "--resume r --lr"] {
        assert!(lines[0].contains(needle), "'{needle}' not in: {err}");
    }
    assert_eq!(std::fs::read(run::checkpoint_path(&run_dir)).unwrap(), good, "the last good checkpoint was replaced");
    let after: Vec<_> = listing(&run_dir).into_iter().filter(|(n, _)| n != "log.jsonl").collect();
    let before: Vec<_> = before.into_iter().filter(|(n, _)| n != "log.jsonl").collect();
    assert_eq!(after, before, "a diverged run wrote files");

    let model = d.join("m.safetensors");
    let out = flashmat_cmd(&["export", "--run", "r", "-o", "m.safetensors"], d).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    flashmat::io::write_png(&d.join("p.png"), &flash_render(128, 128).map(flashmat::spaces::gamma_encode), flashmat::io::BitDepth::Eight).unwrap();
    let out = flashmat_cmd(&["estimate", "p.png", "--model", model.to_str().unwrap(), "--size", "64", "-o", "m.nmat"], d).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let m = NeuralMaterial::load(&d.join("m.nmat"), Device::Cpu).unwrap();
    assert!(flashmat::image::all_finite(&m.neural_map));

    // Continued with a sane learning rate from the kept checkpoint.
    let out = flashmat_cmd(&["train", "--resume", "r", "--lr", "1e-4", "--steps", "3"], d).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(checkpoint_step(&run_dir), 3);
    let logged: Vec<u64> = run::read_log(&run_dir).iter().map(|l| l.step).collect();
    assert_eq!(logged, vec![1, 2, 3]);
}

/// A process id that ran and has ended (a finished child's).
fn ended_pid() -> u32 {
    let mut child = Command::new("true").spawn().unwrap();
    let pid = child.id();
    child.wait().unwrap();
    pid
}

/// One run folder, one owner: of two `train --out` started together, one
/// ends at once with one line naming the other; `--resume` of the running
/// run meets the same line; `export --run` exports its last checkpoint and
/// says the run is still training. SIGKILLed, the owner leaves no stuck
/// lock, and the run that resumes removes the temporary a killed
/// checkpoint write left.
#[test]
fn a_run_folder_has_one_owner_and_a_killed_one_leaves_nothing_stuck() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let r = d.join("r");
    let args = ["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--lpips-weight", "0", "--threads", "1", "--steps", "1000000", "--checkpoint-every", "2", "--preview-every", "0", "--out", "r"];
    // No bundled photos under this root: checkpoints skip the photo check (seconds each).
    let cmd = |args: &[&str]| {
        let mut c = flashmat_cmd(args, d);
        c.env(flashmat::ROOT_ENV, d);
        c
    };
    let spawn = |name: &str| cmd(&args).stdout(Stdio::null()).stderr(std::fs::File::create(d.join(name)).unwrap()).spawn().unwrap();
    let (mut a, mut b) = (spawn("a.err"), spawn("b.err"));
    let start = Instant::now();
    let (mut winner, loser, loser_err) = loop {
        if let Some(status) = a.try_wait().unwrap() {
            break (b, status, "a.err");
        }
        if let Some(status) = b.try_wait().unwrap() {
            break (a, status, "b.err");
        }
        assert!(start.elapsed() < Duration::from_secs(60), "neither run of the same folder stopped");
        std::thread::sleep(Duration::from_millis(10));
    };
    let one_error_line = |code: Option<i32>, err: &str, needles: &[&str]| {
        let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
        assert!(code == Some(1) && lines.len() == 1 && lines[0].starts_with("error: "), "exit {code:?}: {err}");
        for n in needles {
            assert!(lines[0].contains(n), "'{n}' not in: {err}");
        }
    };
    let owner = format!("r is in use by flashmat pid {}", winner.id());
    one_error_line(loser.code(), &std::fs::read_to_string(d.join(loser_err)).unwrap(), &[&owner, "wait for it to finish"]);
    while !run::checkpoint_path(&r).exists() {
        assert!(start.elapsed() < Duration::from_secs(120), "the run wrote no checkpoint");
        std::thread::sleep(Duration::from_millis(10));
    }
    let out = cmd(&["train", "--resume", "r"]).output().unwrap();
    one_error_line(out.status.code(), &String::from_utf8_lossy(&out.stderr), &[&owner]);
    let out = cmd(&["export", "--run", "r", "-o", "m.safetensors"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains(&format!("the run is still training (flashmat pid {}", winner.id())), "{err}");
    Model::load(d.join("m.safetensors"), Device::Cpu).unwrap();

    // What a checkpoint write killed by SIGKILL leaves behind.
    let stale = r.join(format!(".checkpoint.safetensors.tmp-{}-0", ended_pid()));
    std::fs::write(&stale, b"half a checkpoint").unwrap();
    winner.kill().unwrap();
    winner.wait().unwrap();
    assert!(r.join(flashmat::io::LOCK_FILE).exists(), "a killed owner cannot remove its lock file");
    let k = checkpoint_step(&r);
    let total = (k + 1).to_string();
    let out = cmd(&["train", "--resume", "r", "--steps", &total]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(checkpoint_step(&r), k + 1);
    let left: Vec<String> = listing(&r).into_iter().map(|(n, _)| n).filter(|n| n.contains(".tmp-") || n.contains(flashmat::io::LOCK_FILE)).collect();
    assert!(left.is_empty(), "left in the run folder: {left:?}");
}

/// Runs flashmat in `cwd` under a 900 MB data cap (`ulimit -d`: the heap
/// and anonymous mappings, not the 3 GB of mapped libraries), without the
/// bundled photos (a checkpoint's photo check takes seconds).
fn run_data_capped(args: &[&str], cwd: &Path) -> std::process::Output {
    Command::new("sh")
        .arg("-c")
        .arg("ulimit -d 900000 && exec \"$0\" \"$@\"")
        .arg(BIN)
        .args(args)
        .current_dir(cwd)
        .env("OMP_WAIT_POLICY", "PASSIVE")
        .env("OMP_NUM_THREADS", "1")
        .env(flashmat::ROOT_ENV, cwd)
        .output()
        .unwrap()
}

/// The one error line of an out-of-memory, ending with what to lower.
fn assert_out_of_memory_line(out: &std::process::Output, hint: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(crash_text(&err), None, "{err}");
    assert_eq!(out.status.code(), Some(1), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{err}");
    assert!(lines[0].starts_with("error: ") && lines[0].contains("out of memory") && lines[0].ends_with(hint), "{err}");
}

/// Running out of memory is one line that says what to lower, not a panic
/// with libtorch's backtrace, under a memory cap: a 1024x1024 estimate
/// forced whole (`--max-memory 1T`) fails in libtorch's CPU allocator
/// within its first layers and writes nothing; a training step of crops
/// too large for the cap stops the resumed run, whose checkpoint stays as
/// it was.
#[test]
fn out_of_memory_is_one_line_naming_what_to_lower() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    flashmat::io::write_png(&d.join("p.png"), &flashmat::image::Image::filled(3, 1024, 1024, 0.5), flashmat::io::BitDepth::Eight).unwrap();
    tch::manual_seed(1);
    Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(d.join("tiny.safetensors"), &ModelInfo { ldr_input: true, steps: 1 }, false).unwrap();
    std::fs::create_dir(d.join("out")).unwrap();
    let out = run_data_capped(&["estimate", "p.png", "--model", "tiny.safetensors", "--size", "1024", "--max-memory", "1T", "-o", "out/m.nmat"], d);
    assert_out_of_memory_line(&out, ": lower --max-memory (M_est then runs in tiles) or --size");
    assert!(listing(&d.join("out")).is_empty());

    // One step without the cap (about 1 GB at its peak), the next under it.
    let out = flashmat_cmd(&["train", "--preset", "tiny", "--crop", "96", "--batch", "2", "--outputs", "6", "--lpips-weight", "0", "--adv-weight", "0", "--threads", "1", "--steps", "1", "--preview-every", "0", "--out", "r"], d)
        .env(flashmat::ROOT_ENV, d)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let before = listing(&d.join("r"));
    let checkpoint = std::fs::read(run::checkpoint_path(&d.join("r"))).unwrap();
    let out = run_data_capped(&["train", "--resume", "r", "--steps", "2"], d);
    assert_out_of_memory_line(&out, ": lower --batch, --crop or --outputs");
    assert_eq!(std::fs::read(run::checkpoint_path(&d.join("r"))).unwrap(), checkpoint);
    let after: Vec<_> = listing(&d.join("r")).into_iter().filter(|(n, _)| n != "log.jsonl").collect();
    assert_eq!(after, before.into_iter().filter(|(n, _)| n != "log.jsonl").collect::<Vec<_>>(), "the run folder changed");
}

// ---------------------------------------------------------------------------
// Datasets with a material that cannot be read.

/// `svbrdf preview` on a folder with one unreadable material (a NaN in its
/// EXR normal map) among good ones (issue 69): the grid of the good ones is
/// written, the same as without the bad one, which is named in a warning
/// and in the last line, an error (exit code 1). A good one's short normal
/// is normalised, with one warning giving the count.
#[test]
fn a_dataset_with_one_unreadable_material_is_previewed_without_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let m = flashmat::svbrdf::Svbrdf::uniform(16, 16, [0.3; 3], [0.04; 3], 0.5);
    for name in ["a", "b", "c"] {
        flashmat::data::loaders::write_material_dir(&d.join("data").join(name), &m).unwrap();
    }
    let mut normals = image::RgbImage::from_pixel(16, 16, image::Rgb([128, 128, 255]));
    normals.put_pixel(5, 3, image::Rgb([130, 139, 131]));
    normals.save(d.join("data/a/normals.png")).unwrap();
    std::fs::remove_file(d.join("data/b/normals.png")).unwrap();
    exr::prelude::write_rgb_file(d.join("data/b/normals.exr"), 16, 16, |x, y| (0.5f32, if (x, y) == (7, 2) { f32::NAN } else { 0.5 }, 1.0f32)).unwrap();
    std::fs::create_dir(d.join("out")).unwrap();

    let out = flashmat_cmd(&["svbrdf", "preview", "data", "--size", "16", "-o", "out/p.png"], d).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!((out.status.code(), crash_text(&err)), (Some(1), None), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    let line = |start: &str| lines.iter().find(|l| l.starts_with(start)).unwrap_or_else(|| panic!("no '{start}' line in: {err}")).to_string();
    let skipped = line("warning: skipped material b: ");
    assert!(skipped.contains("data/b/normals.exr") && skipped.contains("NaN/Inf") && skipped.contains("row 2, column 7"), "{skipped}");
    assert!(line("warning: normal map ").contains("a/normals.png: 1 of 256 normals were shorter than 0.1 and were normalised"), "{err}");
    assert!(line("wrote out/p.png").contains("2 materials") && line("wrote").contains("left out, unreadable: b"), "{err}");
    assert_eq!(lines.last(), Some(&"error: 1 of 3 materials could not be read and were skipped: b"), "{err}");
    assert_eq!(lines.iter().filter(|l| l.starts_with("error: ")).count(), 1, "{err}");

    std::fs::remove_dir_all(d.join("data/b")).unwrap();
    let good = flashmat_cmd(&["svbrdf", "preview", "data", "--size", "16", "-o", "out/good.png"], d).output().unwrap();
    assert!(good.status.success(), "{}", String::from_utf8_lossy(&good.stderr));
    assert_eq!(std::fs::read(d.join("out/p.png")).unwrap(), std::fs::read(d.join("out/good.png")).unwrap());
}
