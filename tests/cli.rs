//! End-to-end checks of the `flashmat` binary: outputs and bad-input errors
//! (one clear line, non-zero exit, no partial files).

use std::path::Path;

mod common;
use common::*;

#[test]
fn render_writes_exr_equal_to_the_cpu_renderer_and_png() {
    let dir = tempfile::tempdir().unwrap();
    let exr = dir.path().join("r.exr");
    let out = flashmat(&["render", "--svbrdf", "procedural:11", "--size", "64", "--light", "1,0.5,2", "--view", "0,0,4", "-o", exr.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = flashmat::io::read_image(&exr).unwrap();
    let material = flashmat::data::procedural::generate(11, &flashmat::data::procedural::ProceduralConfig { size: 64, ..Default::default() });
    let cfg = flashmat::geometry::LightView { light: [1.0, 0.5, 2.0], view: [0.0, 0.0, 4.0] };
    let expect = flashmat::svbrdf::cpu::render(&material, &[cfg]);
    let worst = img.data.iter().zip(&expect).map(|(a, b)| (a - b).abs() / b.abs().max(1e-3)).fold(0f32, f32::max);
    assert!(worst < 1e-4, "{worst}");
    let png = dir.path().join("sub/r.png");
    let out = flashmat(&["render", "--svbrdf", "procedural:11", "--size", "64", "-o", png.to_str().unwrap()]);
    assert!(out.status.success());
    let im = flashmat::io::read_image(&png).unwrap();
    assert_eq!((im.channels, im.height, im.width), (3, 64, 64));
    no_temp_files(dir.path());
}

#[test]
fn render_with_shadows_matches_the_cpu_renderer() {
    let dir = tempfile::tempdir().unwrap();
    let exr = dir.path().join("s.exr");
    let args = ["render", "--svbrdf", "procedural:5:tiles", "--size", "64", "--light", "3,0.5,0.8", "--view", "0,0,4", "--shadows", "--height-scale", "4"];
    let out = flashmat(&[&args[..], &["-o", exr.to_str().unwrap()]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = flashmat::io::read_image(&exr).unwrap();
    let family: flashmat::data::procedural::Family = "tiles".parse().unwrap();
    let material = flashmat::data::procedural::generate_family(family, 5, 64);
    let cfg = flashmat::geometry::LightView { light: [3.0, 0.5, 0.8], view: [0.0, 0.0, 4.0] };
    let options = flashmat::svbrdf::shadow::ShadowOptions { height_scale: 4.0, ..Default::default() };
    let expect = flashmat::svbrdf::cpu::render_shadowed(&material, &[cfg], &options).unwrap();
    let plain = flashmat::svbrdf::cpu::render(&material, &[cfg]);
    let shadowed = expect.iter().zip(&plain).filter(|(s, p)| **s == 0.0 && **p > 0.0).count();
    assert!(shadowed > 0, "no shadow in the test scene");
    let off = img.data.iter().zip(&expect).filter(|(a, b)| (*a - *b).abs() > 1e-4 * b.abs().max(1e-3)).count();
    assert!(off <= 3, "{off} of {} values differ", expect.len());
    // The CPU renderer writes the same file.
    let cpu = dir.path().join("c.exr");
    let out = flashmat(&[&args[..], &["--renderer", "cpu", "-o", cpu.to_str().unwrap()]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(flashmat::io::read_image(&cpu).unwrap().data, expect);
    // Maps from disk have no height field: one is integrated.
    let root = dir.path().join("data");
    let out = flashmat(&["svbrdf", "generate", "--count", "1", "--size", "32", "--out", root.to_str().unwrap()]);
    assert!(out.status.success());
    let out = flashmat(&["render", "--svbrdf", root.to_str().unwrap(), "--shadows", "--light-radius", "0.2", "-o", dir.path().join("d.png").to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let o = dir.path().join("o.png");
    let o = o.to_str().unwrap();
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1", "--shadows", "--height-scale=-1", "-o", o]), &["height scale"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1", "--shadows", "--light-samples", "0", "-o", o]), &["light samples"]);
    // Shadow options without --shadows are usage errors.
    assert_eq!(flashmat(&["render", "--svbrdf", "procedural:1", "--height-scale", "2", "-o", o]).status.code(), Some(2));
}

#[test]
fn generate_then_render_and_preview_from_disk() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("data");
    let out = flashmat(&["svbrdf", "generate", "--count", "3", "--size", "32", "--out", root.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for sub in ["diffuse", "specular", "normals", "roughness"] {
        assert!(root.join(sub).join(format!("0000003_{sub}.png")).exists(), "{sub}");
    }
    let r = dir.path().join("r.png");
    let out = flashmat(&["render", "--svbrdf", root.to_str().unwrap(), "--index", "2", "-o", r.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = flashmat(&["render", "--svbrdf", root.to_str().unwrap(), "--index", "3", "-o", r.to_str().unwrap()]);
    assert_error(&out, &["--index 3", "3 material"]);
    let p = dir.path().join("preview.png");
    let out = flashmat(&["svbrdf", "preview", root.to_str().unwrap(), "--size", "32", "-o", p.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let im = flashmat::io::read_image(&p).unwrap();
    // 3 rows and 5 columns of 32 px cells with 4 px gaps.
    assert_eq!((im.height, im.width), (3 * 36 + 4, 5 * 36 + 4));
    // A corrupt map names its file.
    std::fs::write(root.join("diffuse").join("0000002_diffuse.png"), b"\x89PNG\r\n\x1a\nbroken").unwrap();
    let out = flashmat(&["render", "--svbrdf", root.to_str().unwrap(), "--index", "1", "-o", r.to_str().unwrap()]);
    assert_error(&out, &["0000002_diffuse.png"]);
}

#[test]
fn bad_inputs_give_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("o.png");
    let o = o.to_str().unwrap();
    assert_error(&flashmat(&["render", "--svbrdf", "/nonexistent/materials", "-o", o]), &["/nonexistent/materials"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1", "--light", "0,0,-2", "-o", o]), &["light position", "z must be > 0"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1", "--view", "1,1,0", "-o", o]), &["camera position"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:x", "-o", o]), &["procedural:SEED"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1:velvet", "-o", o]), &["velvet"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural-test:50", "-o", o]), &["procedural-test:50", "0 to 49"]);
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1", "--size", "16", "-o", dir.path().join("o.bmp").to_str().unwrap()]), &[".png or .exr"]);
    assert_error(&flashmat(&["train", "--preset", "huge", "--out", dir.path().join("run").to_str().unwrap()]), &["huge", "compact"]);
    assert_error(&flashmat(&["train", "--resume", dir.path().join("norun").to_str().unwrap()]), &["no checkpoint"]);
    assert_error(&flashmat(&["train", "--device", "tpu", "--out", dir.path().join("run").to_str().unwrap()]), &["--device"]);
    assert_error(&flashmat(&["export", "--run", dir.path().join("norun").to_str().unwrap(), "-o", o]), &["checkpoint.safetensors"]);
    // A file where a folder is needed for the output.
    std::fs::write(dir.path().join("file"), b"x").unwrap();
    let blocked = dir.path().join("file").join("o.png");
    assert_error(&flashmat(&["render", "--svbrdf", "procedural:1", "--size", "16", "-o", blocked.to_str().unwrap()]), &["file"]);
    // Option typos are usage errors (clap), exit code 2.
    let out = flashmat(&["render", "--lihgt", "1,1,1"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(!Path::new(o).exists());
}

#[test]
fn synthetic_captures_then_eval_captures() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("capture");
    let out = flashmat(&["svbrdf", "captures", "--svbrdf", "procedural-test:3", "--size", "64", "--photos", "4", "--sample-width", "12", "-o", cap.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // Positions in units of the 12-wide sample: the overhead camera at the
    // model's 4.010781 half-widths, times 6 = 24.064686.
    let cams = std::fs::read_to_string(cap.join("camera_pos.txt")).unwrap();
    assert_eq!(cams.lines().count(), 4);
    assert_eq!(cams.lines().next().unwrap(), "0.000000,0.000000,24.064686");
    assert_eq!(std::fs::read_to_string(cap.join("image_size.txt")).unwrap().trim(), "12");

    let report = dir.path().join("report");
    let out = flashmat(&["eval", "--model", "printout", "--captures", cap.to_str().unwrap(), "--size", "64", "-o", report.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("Scored on the other 3 photos at 64x64"), "{stdout}");
    for f in ["captures.csv", "summary.md", "grid.jpg", "grid.txt", "highlights.csv"] {
        assert!(report.join(f).exists(), "{f}");
    }
    no_temp_files(&report);
    assert!(stdout.contains("## Moved highlights"), "{stdout}");

    // Bad inputs: one line each; eval-table options are usage errors with --captures.
    assert_error(&flashmat(&["svbrdf", "captures", "--svbrdf", "procedural:3", "--photos", "1", "-o", cap.to_str().unwrap()]), &["--photos"]);
    let nowhere = dir.path().join("nowhere");
    assert_error(&flashmat(&["eval", "--model", "printout", "--captures", nowhere.to_str().unwrap(), "-o", report.to_str().unwrap()]), &["nowhere", "does not exist"]);
    std::fs::remove_file(cap.join("light_pos.txt")).unwrap();
    assert_error(&flashmat(&["eval", "--model", "printout", "--captures", cap.to_str().unwrap(), "-o", report.to_str().unwrap()]), &["light_pos.txt"]);
    let out = flashmat(&["eval", "--model", "printout", "--captures", cap.to_str().unwrap(), "--cases", "identity", "-o", report.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn eval_exposures_take_negative_stops_and_refuse_non_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("report");
    let args = |ev: &str| ["eval", "--model", "printout", "--size", "32", "--limit", "1", "--cases", "identity", "--ldr-input", "--exposures", ev, "-o", report.to_str().unwrap()].map(String::from);
    let out = flashmat(&args("-2,1").iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let curve = std::fs::read_to_string(report.join("exposure/curve.csv")).unwrap();
    // -2, 0 (always) and +1 stops.
    assert_eq!(curve.lines().skip(1).map(|l| l.split(',').nth(2).unwrap().to_string()).collect::<Vec<_>>(), ["-2", "0", "1"]);
    assert!(report.join("highlights/ratios.csv").is_file() && report.join("highlights/moved.jpg").is_file());
    no_temp_files(&report);
    assert_error(&flashmat(&args("nan").iter().map(String::as_str).collect::<Vec<_>>()), &["--exposures", "NaN"]);
}

/// `eval --ceiling`: the bundled model's estimate and one fit per K on the
/// glossiest held-out material, written as ceiling.md and ceiling.csv; the
/// print-out (no renderer to fit) is refused in one line.
#[test]
fn eval_ceiling_fits_the_map_and_refuses_the_printout() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ceiling");
    let model = format!("{}/models/flashmat.safetensors", env!("CARGO_MANIFEST_DIR"));
    let args = ["eval", "--ceiling", "0,2", "--ceiling-materials", "1", "--ceiling-steps", "3", "--size", "32", "--ldr-input", "--model", &model, "-o", s(&out)];
    assert_ok(&flashmat(&args));
    let csv = std::fs::read_to_string(out.join("ceiling.csv")).unwrap();
    let maps: Vec<&str> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap()).collect();
    assert_eq!(maps, ["estimate", "fit 0", "fit 2"]);
    // The glossiest held-out material, and each fit lowers its own data term.
    for line in csv.lines().skip(2) {
        let cells: Vec<&str> = line.split(',').collect();
        assert_eq!(cells[1], "test30");
        let (before, after): (f64, f64) = (cells[3].parse().unwrap(), cells[4].parse().unwrap());
        assert!(after < before, "{line}");
    }
    assert!(std::fs::read_to_string(out.join("ceiling.md")).unwrap().contains("| fit 2 |"));
    no_temp_files(&out);
    // Chosen materials instead of the glossiest; an index past the set is refused.
    let only = dir.path().join("only");
    assert_ok(&flashmat(&["eval", "--ceiling", "0", "--ceiling-only", "32,7", "--ceiling-steps", "2", "--size", "32", "--ldr-input", "--model", &model, "-o", s(&only)]));
    let rows: Vec<String> = std::fs::read_to_string(only.join("ceiling.csv")).unwrap().lines().skip(1).map(|l| l.split(',').take(2).collect::<Vec<_>>().join(",")).collect();
    assert_eq!(rows, ["estimate,test32", "fit 0,test32", "estimate,test07", "fit 0,test07"]);
    assert!(std::fs::read_to_string(only.join("ceiling.md")).unwrap().contains("The 2 chosen held-out materials"));
    assert_error(&flashmat(&["eval", "--ceiling", "--ceiling-only", "50", "--model", &model, "-o", s(&only)]), &["--ceiling-only", "0 to 49"]);
    let printout = ["eval", "--ceiling", "--model", "printout", "-o", s(&out)];
    assert_error(&flashmat(&printout), &["--ceiling", "one flashmat model"]);
}

#[test]
fn baselines_train_resume_export_and_eval() {
    let dir = tempfile::tempdir().unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_owned();
    let tiny = ["--preset", "tiny", "--crop", "32", "--outputs", "2", "--lpips-weight", "0", "--threads", "1", "--checkpoint-every", "1"];
    let mut files = vec![];
    for method in ["analytic", "relight-unet"] {
        let run = dir.path().join(format!("run-{method}"));
        let run_s = s(&run);
        let args = [&["train", "--method", method, "--steps", "1", "--preview-every", "1", "--out", &run_s][..], &tiny[..]].concat();
        let out = flashmat(&args);
        assert!(out.status.success(), "{method}: {}", String::from_utf8_lossy(&out.stderr));
        let config = std::fs::read_to_string(run.join("config.json")).unwrap();
        assert!(config.contains(&format!("\"method\": \"{method}\"")), "{config}");
        assert!(run.join("previews/step-0000001.png").is_file());
        // Resume to 2 steps: the method comes from the checkpoint.
        let out = flashmat(&["train", "--resume", &s(&run), "--steps", "2"]);
        assert!(out.status.success(), "{method}: {}", String::from_utf8_lossy(&out.stderr));
        assert_eq!(std::fs::read_to_string(run.join("log.jsonl")).unwrap().lines().count(), 2);
        let model = dir.path().join(format!("{method}.safetensors"));
        let out = flashmat(&["export", "--run", &s(&run), "-o", &s(&model)]);
        assert!(out.status.success(), "{method}: {}", String::from_utf8_lossy(&out.stderr));
        let meta = flashmat::model::file::read_header_metadata(&model).unwrap();
        assert_eq!(meta.get("method").map(String::as_str), Some(method));
        files.push(model);
    }
    let report = dir.path().join("report");
    let out = flashmat(&[
        "eval", "--model", &s(&files[0]), "--model", &s(&files[1]), "--model", "printout", "--size", "32", "--limit", "1", "--configs", "2",
        "-o", &s(&report),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for name in ["analytic", "relight-unet"] {
        let csv = std::fs::read_to_string(report.join(format!("{name}.csv"))).unwrap();
        let rows: Vec<&str> = csv.lines().skip(1).collect();
        assert_eq!(rows.len(), 3, "{csv}");
        for r in rows {
            assert!(r.split(',').skip(2).all(|v| v.parse::<f64>().unwrap().is_finite()), "{r}");
        }
    }
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(summary.contains("| analytic |") && summary.contains("| relight-unet |"), "{summary}");

    // Bad input: one clear line, exit 1.
    let run = dir.path().join("run-bad");
    let run_s = s(&run);
    let bad = [&["train", "--method", "relight-unet", "--scheme", "combined", "--out", &run_s][..], &tiny[..]].concat();
    assert_error(&flashmat(&bad), &["--scheme", "--method flashmat"]);
    assert!(!run.exists());
    let nmat = dir.path().join("m.nmat");
    let photo = dir.path().join("p.png");
    let out = flashmat(&["render", "--svbrdf", "procedural:3", "--size", "64", "-o", &s(&photo)]);
    assert!(out.status.success());
    assert_error(&flashmat(&["estimate", &s(&photo), "--model", &s(&files[0]), "--size", "32", "-o", &s(&nmat)]), &["analytic", "not a flashmat"]);
    // --method with --resume is a usage error (the checkpoint knows its method).
    assert_eq!(flashmat(&["train", "--resume", &s(&dir.path().join("run-analytic")), "--method", "analytic"]).status.code(), Some(2));
}

/// Material folders whose float maps no material has are refused by
/// render, eval and train with one line naming the file; roughness 0 (below
/// the data's floor) is raised to it with a warning.
#[test]
fn absurd_material_maps_are_refused_or_raised_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let m = dir.path().join("m");
    flashmat::data::loaders::write_material_dir(&m, &flashmat::svbrdf::Svbrdf::uniform(16, 16, [0.3; 3], [0.04; 3], 0.5)).unwrap();
    let replace = |map: &str, v: f32| {
        let _ = std::fs::remove_file(m.join(format!("{map}.png")));
        flashmat::io::write_exr(&m.join(format!("{map}.exr")), &flashmat::image::Image::filled(if map == "roughness" { 1 } else { 3 }, 16, 16, v)).unwrap();
    };
    let o = dir.path().join("o.png");
    replace("roughness", 0.0);
    let err = assert_ok(&flashmat(&["render", "--svbrdf", s(&m), "-o", s(&o)]));
    assert!(err.contains("warning: roughness map") && err.contains("256 of its 256 values are below the minimum roughness 0.02 and were raised to it"), "{err}");
    replace("specular", 1e30);
    assert_error(&flashmat(&["render", "--svbrdf", s(&m), "-o", s(&o)]), &["specular.exr has the value", "specular values lie in [0, 1]"]);
    let out = flashmat(&["eval", "--model", "printout", "--dataset", s(&m), "--size", "32", "-o", s(&dir.path().join("eval"))]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(stderr(&out).contains("specular.exr has the value"), "{}", stderr(&out));
}

/// `bench infer` times the plan `estimate` would run (whole, or tiles
/// under `--max-memory`) and sets the authors' numbers beside flashmat's:
/// a stand-in for their timing script answers in its JSON lines (one size
/// measured, one out of memory) and the table takes their figures and the
/// ratio from them.
#[test]
fn bench_infer_plans_tiles_and_sets_the_authors_numbers_beside() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("authors");
    std::fs::create_dir(&repo).unwrap();
    std::fs::write(repo.join("prl_main_train.py"), "").unwrap();
    let script = dir.path().join("ref_bench.py");
    std::fs::write(
        &script,
        r#"import json, os, sys
assert os.environ["REF_DIR"].endswith("authors") and "--infer" in sys.argv and sys.argv[sys.argv.index("--size") + 1] == "64,256"
print(json.dumps({"what": "ref_mest_forward", "size": 64, "ms_median": 5000.0, "per_s": 0.2}))
print(json.dumps({"what": "ref_render_frame", "size": 64, "ms_median": 2500.0, "per_s": 0.4}))
print(json.dumps({"what": "ref_mest_forward", "size": 256, "error": "OutOfMemoryError: CUDA out of memory"}))
print("their own chatter", file=sys.stderr)
"#,
    )
    .unwrap();
    let report = dir.path().join("infer.md");
    let out = flashmat(&[
        "bench", "infer", "--preset", "tiny", "--size", "64,256", "--max-memory", "64M", "--runs", "1",
        "--reference", repo.to_str().unwrap(), "--ref-bench", script.to_str().unwrap(), "--report", report.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let md = std::fs::read_to_string(&report).unwrap();
    let row = |start: &str| -> Vec<String> {
        let line = md.lines().find(|l| l.starts_with(start)).unwrap_or_else(|| panic!("no row {start} in\n{md}"));
        line.split('|').map(|c| c.trim().to_string()).collect()
    };
    let small = row("| M_est forward, tiny, 64x64 |");
    let ours: f64 = small[2].parse().unwrap();
    assert_eq!(small[3], "5000.0");
    let ratio: f64 = small[4].trim_end_matches('x').parse().unwrap();
    assert!((ratio - 5000.0 / ours).abs() <= 0.01 * ratio, "{small:?}"); // ours printed to 0.1 ms
    assert!(row("| relit frame, tiny, 64x64 |")[3] == "2500.0");
    let large = row("| M_est forward, tiny, 256x256, tiles of");
    assert!(large[1].contains("authors': OutOfMemoryError") && large[3] == "-", "{large:?}");
    assert!(large[2].parse::<f64>().unwrap() > 0.0);
    // Their script dies (its own out of memory): a warning naming it, and
    // flashmat's numbers still come (not read as flashmat's out of memory).
    std::fs::write(&script, "raise RuntimeError('CUDA out of memory in their step')\n").unwrap();
    let out = flashmat(&[
        "bench", "infer", "--preset", "tiny", "--size", "64", "--runs", "1",
        "--reference", repo.to_str().unwrap(), "--ref-bench", script.to_str().unwrap(), "--report", report.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && stderr.contains("warning: the authors' benchmark failed"), "{stderr}");
    let md = std::fs::read_to_string(&report).unwrap();
    assert!(md.contains("| M_est forward, tiny, 64x64 (authors': not measured) |"), "{md}");
    // Not the authors' repository: one line.
    assert_error(&flashmat(&["bench", "infer", "--preset", "tiny", "--size", "64", "--reference", dir.path().to_str().unwrap()]), &["not a copy of the authors' repository"]);
}
