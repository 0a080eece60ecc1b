//! Scoring real captures (`flashmat eval --captures`, [`run`]): every
//! method estimates from the photo nearest straight overhead and re-renders
//! every other photo's configuration, against the photos with their 1/r^2
//! fall-off compensated ([`crate::data::captures`] reads the folder).
//! Scores are LPIPS on display images, with RMSE of ln(1 + R) and PSNR of
//! display images.

use crate::data::captures::Captures;
use super::metrics::{mean_ci95, score_renders_on, LpipsOn, Scores};
use super::methods::open_methods;
use crate::geometry::{fov_to_distance, LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::lpips::Lpips;
use anyhow::{anyhow, ensure, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use tch::{Device, Tensor};

/// Photos shown in `grid.jpg` at most (besides the input), evenly spaced.
const GRID_PHOTOS: usize = 8;

/// Grid cells are shrunk to at most this many pixels across.
const GRID_CELL: usize = 128;

/// Everything `flashmat eval --captures` needs.
#[derive(Clone, Debug)]
pub struct CaptureEvalOptions {
    /// Model files, or `printout`.
    pub models: Vec<String>,
    /// The capture folder.
    pub dir: PathBuf,
    pub out: PathBuf,
    /// Resolution the photos are scored at.
    pub size: usize,
    pub device: Device,
    pub progress: bool,
    /// Refined variants of every flashmat model (`--refine`), one per setting.
    pub refine: Vec<crate::infer::refine::RefineConfig>,
    /// How flashmat models handle the photo's exposure (`--exposure-mode`).
    pub exposure: crate::infer::ExposureConfig,
    /// Also score every flashmat model with its photographed highlight filled.
    pub highlight_fill: Option<crate::infer::highlight_fill::HighlightFillConfig>,
    /// Also score the several-photo fit (`estimate --capture`) leave-one-out:
    /// for each scored photo, a material fitted to all the other photos
    /// (the bundled model's start, the bundled teacher's renderer).
    pub capture_fit: Option<crate::fit::photos::PhotoFitConfig>,
}

/// Name of the leave-one-out capture fit in the tables.
pub const CAPTURE_FIT_METHOD: &str = "capture-fit (leave-one-out)";

/// Scores of one method on one photo.
#[derive(Clone, Debug)]
pub struct CaptureRow {
    /// File name of the photo.
    pub photo: String,
    pub config: LightView,
    pub scores: Scores,
}

/// Per-method results on a capture folder.
#[derive(Debug)]
pub struct CaptureResults {
    pub name: String,
    pub rows: Vec<CaptureRow>,
    /// The moved-highlight ratios per scored photo (as `rows`): S_in the
    /// input photo's highlight (8-bit: all there is), S_gt the scored photo's own, the method's
    /// render over the photo ([`super::highlights`]; no crop LPIPS).
    pub highlights: Vec<super::highlights::LightRatios>,
}

fn file_name(p: &Path) -> String {
    p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

/// `flashmat eval --captures`: every method estimates from the overhead
/// photo and re-renders the other photos' configurations; writes
/// `captures.csv`, `summary.md`, `grid.jpg` (cells of at most 128 pixels)
/// and `grid.txt` into `opts.out`.
pub fn run(opts: &CaptureEvalOptions) -> Result<Vec<CaptureResults>> {
    super::check_eval_size(opts.size)?;
    let captures = Captures::open(&opts.dir)?;
    let n = captures.photos.len();
    ensure!(n >= 2, "capture folder {} has 1 photo; it needs at least 2 (one to estimate from, others to compare with)", opts.dir.display());
    // Capture photos are 8-bit: the methods get LDR photos.
    let mut methods = open_methods(&opts.models, true, opts.device, &opts.refine, &opts.exposure, opts.highlight_fill)?;
    let photos = captures.load_compensated(opts.size)?;
    let input = captures.overhead();
    let others: Vec<usize> = (0..n).filter(|&i| i != input).collect();
    let configs: Vec<LightView> = others.iter().map(|&i| captures.config(i)).collect();
    let target = Tensor::stack(&others.iter().map(|&i| photos[i].shallow_clone()).collect::<Vec<_>>(), 0);
    let lpips = Lpips::new(opts.device)?;
    std::fs::create_dir_all(&opts.out).map_err(|e| anyhow!("cannot create output folder {}: {e}", opts.out.display()))?;

    let folds = if opts.capture_fit.is_some() { others.len() } else { 0 };
    let bar = if opts.progress { ProgressBar::new((methods.len() + folds) as u64) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("{bar:40} {pos}/{len} methods and folds, {elapsed} {msg}").expect("valid template"));
    let shown: Vec<usize> = grid_picks(others.len());
    let moved = super::highlights::HighlightConfig::default();
    let s_in = super::highlights::highlight_mask(&super::highlights::luminance(&photos[input])?, moved.threshold);
    let mut results = Vec::new();
    // Grid columns: the photos, then each method's renders.
    let mut columns: Vec<Vec<Tensor>> = vec![std::iter::once(photos[input].shallow_clone()).chain(shown.iter().map(|&k| target.get(k as i64))).collect()];
    // Scores a method's renders of the other photos `[N, 3, S, S]` and its identity render `[3, S, S]`.
    let mut score = |name: String, pred: Tensor, identity: Tensor| -> Result<()> {
        let scores = score_renders_on(&lpips, &pred, &target, LpipsOn::Display)?;
        let rows = others
            .iter()
            .zip(&configs)
            .zip(scores)
            .map(|((&i, &config), scores)| CaptureRow { photo: file_name(&captures.photos[i]), config, scores })
            .collect();
        columns.push(std::iter::once(identity).chain(shown.iter().map(|&k| pred.get(k as i64))).collect());
        let highlights = super::highlights::light_ratios(&s_in, &pred, &target, &moved, None).map_err(|e| anyhow!("{name}: {e:#}"))?;
        results.push(CaptureResults { name, rows, highlights });
        Ok(())
    };
    for method in methods.iter_mut() {
        let name = method.name();
        bar.set_message(name.clone());
        method.prepare(&photos[input]).map_err(|e| anyhow!("{name}: {e:#}"))?;
        let pred = method.render(&configs).map_err(|e| anyhow!("{name}: {e:#}"))?;
        let identity = method.render(&[captures.config(input)]).map_err(|e| anyhow!("{name}: {e:#}"))?.get(0);
        score(name, pred, identity)?;
        bar.inc(1);
    }
    if let Some(cfg) = &opts.capture_fit {
        use crate::fit::photos::{fit_capture, load_capture_photos, load_teacher, fitted_neural_material};
        let cfg = crate::fit::photos::PhotoFitConfig { size: opts.size, ..cfg.clone() };
        let loaded = crate::infer::load_model(None, opts.device)?;
        let teacher = load_teacher(None, opts.device)?;
        let mut preds = Vec::with_capacity(others.len());
        let mut identity = None;
        for &left_out in &others {
            bar.set_message(format!("{CAPTURE_FIT_METHOD}: without {}", file_name(&captures.photos[left_out])));
            let kept: Vec<usize> = (0..n).filter(|&i| i != left_out).collect();
            let capture = load_capture_photos(&captures, &kept, opts.size)?;
            let fit = fit_capture(&loaded, &capture, &cfg, opts.device, |_, _, _| {})?;
            let (material, _) = fitted_neural_material(&fit.maps, &capture.photos.get(capture.overhead as i64), &teacher, &capture.configs, &cfg.code_fit, CAPTURE_FIT_METHOD)?;
            preds.push(material.render(&[captures.config(left_out)])?.get(0));
            if identity.is_none() {
                identity = Some(material.render(&[captures.config(input)])?.get(0));
            }
            bar.inc(1);
        }
        let identity = identity.expect("a capture eval has at least one photo to score");
        score(CAPTURE_FIT_METHOD.to_string(), Tensor::stack(&preds, 0), identity)?;
    }
    bar.finish_and_clear();

    crate::io::atomic_write_bytes(&opts.out.join("captures.csv"), csv_text(&results).as_bytes())?;
    crate::io::atomic_write_bytes(&opts.out.join("highlights.csv"), highlights_csv(&results).as_bytes())?;
    crate::io::atomic_write_bytes(&opts.out.join("summary.md"), summary_markdown(&captures, opts.size, &results).as_bytes())?;
    let grid_rows: Vec<Vec<Image>> = (0..=shown.len())
        .map(|r| columns.iter().map(|c| grid_cell(&c[r])).collect::<Result<_>>())
        .collect::<Result<_>>()?;
    crate::io::write_jpeg(&opts.out.join("grid.jpg"), &crate::viz::grid(&grid_rows, 4)?, super::report::REPORT_JPEG_QUALITY)?;
    let mut note = format!(
        "Columns: photo (fall-off compensated) | {}\nRow 1: the input {} and each method's re-render of it.\n",
        results.iter().map(|r| r.name.as_str()).collect::<Vec<_>>().join(" | "),
        file_name(&captures.photos[input])
    );
    for (row, &k) in shown.iter().enumerate() {
        let _ = writeln!(note, "Row {}: {}", row + 2, file_name(&captures.photos[others[k]]));
    }
    crate::io::atomic_write_bytes(&opts.out.join("grid.txt"), note.as_bytes())?;
    Ok(results)
}

/// Display image of a linear `[3, S, S]` render, shrunk (area) to
/// [`GRID_CELL`] pixels when larger.
fn grid_cell(linear: &Tensor) -> Result<Image> {
    let im = Image::display_of(linear)?;
    Ok(if im.width > GRID_CELL { im.resize_area(GRID_CELL, GRID_CELL) } else { im })
}

/// Up to [`GRID_PHOTOS`] indices of `count`, evenly spaced, first included.
fn grid_picks(count: usize) -> Vec<usize> {
    let k = count.min(GRID_PHOTOS);
    let mut picks: Vec<usize> = (0..k).map(|i| i * count / k.max(1)).collect();
    picks.dedup();
    picks
}

/// `method,photo,light_x,light_y,light_z,camera_x,camera_y,camera_z,lpips,rmse_log,psnr`
/// (positions in flashmat units).
pub fn csv_text(results: &[CaptureResults]) -> String {
    let mut s = String::from("method,photo,light_x,light_y,light_z,camera_x,camera_y,camera_z,lpips,rmse_log,psnr\n");
    for r in results {
        for row in &r.rows {
            let (l, c) = (row.config.light, row.config.view);
            let _ = writeln!(
                s,
                "{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.6},{:.6},{:.4}",
                r.name, row.photo, l[0], l[1], l[2], c[0], c[1], c[2], row.scores.lpips, row.scores.rmse_log, row.scores.psnr
            );
        }
    }
    s
}

/// `method,photo,ghost,lobe,rest` (empty where the region is too small).
pub fn highlights_csv(results: &[CaptureResults]) -> String {
    let mut s = String::from("method,photo,ghost,lobe,rest\n");
    let cell = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.5}"));
    for r in results {
        for (row, h) in r.rows.iter().zip(&r.highlights) {
            let _ = writeln!(s, "{},{},{},{},{}", r.name, row.photo, cell(h.ghost), cell(h.lobe), cell(h.rest));
        }
    }
    s
}

/// Markdown summary: the input photo's geometry against the model's, the
/// mean scores per method (95% intervals over photos) and LPIPS per photo.
pub fn summary_markdown(captures: &Captures, size: usize, results: &[CaptureResults]) -> String {
    let input = captures.overhead();
    let cam = captures.cameras[input];
    let light = captures.lights[input];
    let off_vertical = (cam[2] / crate::geometry::length(cam)).clamp(-1.0, 1.0).acos().to_degrees();
    let fmt = |v: [f64; 3]| format!("({:.3}, {:.3}, {:.3})", v[0], v[1], v[2]);
    let mut s = String::from("# Evaluation on captures\n\n");
    let _ = writeln!(
        s,
        "Folder `{}`: {} photos of a sample {} units wide. Positions below are in half-widths (the sample spans [-1, 1]).\n",
        captures.dir.display(),
        captures.photos.len(),
        captures.sample_width
    );
    let _ = writeln!(
        s,
        "Estimated from `{}`, the photo nearest straight overhead: camera at {} ({:.3} from the centre, {:.1} degrees off vertical), light at {} ({:.3} from the camera). \
         The models expect a co-located camera and light {:.3} straight above (a {MODEL_FOV_DEG} degree view of the sample).\n",
        file_name(&captures.photos[input]),
        fmt(cam),
        crate::geometry::length(cam),
        off_vertical,
        fmt(light),
        crate::geometry::length([light[0] - cam[0], light[1] - cam[1], light[2] - cam[2]]),
        fov_to_distance(MODEL_FOV_DEG)
    );
    let _ = writeln!(
        s,
        "Scored on the other {} photos at {size}x{size}, after compensating their 1/r^2 fall-off to r0 = {:.3} (the overhead light's distance to the centre). \
         LPIPS (AlexNet) on display images; RMSE of ln(1 + R); PSNR of display images clamp(R)^(1/2.2).\n",
        captures.photos.len() - 1,
        captures.reference_distance()
    );
    let _ = writeln!(s, "| Method | LPIPS (lower is better) | RMSE ln(1+R) | PSNR, dB |\n|---|---|---|---|");
    for r in results {
        let stat = |get: fn(&Scores) -> f64, digits: usize| {
            let (m, h) = mean_ci95(&r.rows.iter().map(|x| get(&x.scores)).collect::<Vec<_>>());
            format!("{m:.digits$} ± {h:.digits$}")
        };
        let _ = writeln!(s, "| {} | {} | {} | {} |", r.name, stat(|x| x.lpips, 3), stat(|x| x.rmse_log, 3), stat(|x| x.psnr, 2));
    }
    let _ = writeln!(
        s,
        "\n## Moved highlights\n\nMethod's render over the photo on the input photo's highlight minus the scored photo's own (ghost), on the scored photo's highlight minus the input's (lobe) \
         and elsewhere (rest); highlights: pixels brighter than {}x the image's median (RGB mean). Cells: geometric mean | median | photos past 1.5x (ghost), below 0.67x (lobe) / photos with the region (highlights.csv has each photo).\n",
        super::highlights::HIGHLIGHT_THRESHOLD
    );
    let _ = writeln!(s, "| Method | ghost | median | > 1.5x | lobe | median | < 0.67x | rest | median |\n|---|---|---|---|---|---|---|---|---|");
    for r in results {
        let stats = |get: fn(&super::highlights::LightRatios) -> Option<f64>| super::highlights::ratio_stats(r.highlights.iter().map(get));
        let (g, l, rest) = (stats(|h| h.ghost), stats(|h| h.lobe), stats(|h| h.rest));
        let cells = |x: &super::highlights::RatioStats, count: usize| if x.n == 0 { "- | - | -".to_string() } else { format!("{:.2} | {:.2} | {count}/{}", x.geo_mean, x.median, x.n) };
        let rest_cells = if rest.n == 0 { "- | -".to_string() } else { format!("{:.2} | {:.2}", rest.geo_mean, rest.median) };
        let _ = writeln!(s, "| {} | {} | {} | {rest_cells} |", r.name, cells(&g, g.above_1_5), cells(&l, l.below_0_67));
    }
    let _ = writeln!(s, "\n## LPIPS per photo\n");
    let _ = writeln!(s, "| Photo | light | camera | {} |", results.iter().map(|r| r.name.as_str()).collect::<Vec<_>>().join(" | "));
    let _ = writeln!(s, "|---|---|---|{}", "---|".repeat(results.len()));
    if let Some(first) = results.first() {
        for (k, row) in first.rows.iter().enumerate() {
            let cells: Vec<String> = results.iter().map(|r| format!("{:.3}", r.rows[k].scores.lpips)).collect();
            let _ = writeln!(s, "| {} | {} | {} | {} |", row.photo, fmt(row.config.light), fmt(row.config.view), cells.join(" | "));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::captures::{synthetic_configs, write_synthetic};
    use crate::svbrdf::Svbrdf;

    fn eval_opts(dir: &Path, out: &Path, models: &[&str]) -> CaptureEvalOptions {
        CaptureEvalOptions {
            models: models.iter().map(|s| s.to_string()).collect(),
            dir: dir.to_path_buf(),
            out: out.to_path_buf(),
            size: 32,
            device: Device::Cpu,
            progress: false,
            refine: vec![],
            exposure: crate::infer::ExposureConfig::default(),
            highlight_fill: None,
            capture_fit: None,
        }
    }

    #[test]
    fn printout_re_renders_a_lambertian_capture_and_not_a_glossy_one() {
        // Matte: kd varies across the sample, ks = 0. With co-located flash
        // the GGX specular lobe is F(ks = 0, v.h = 1) = 0, so every photo is
        // kd n.l, which the print-out re-renders exactly.
        let t = tempfile::tempdir().unwrap();
        let mut matte = Svbrdf::uniform(32, 32, [0.0; 3], [0.0; 3], 0.5);
        matte.diffuse = Image::from_fn(3, 32, 32, |c, y, x| 0.15 + 0.6 * ((x / 8 + y / 8 + c) % 3) as f32 / 2.0);
        write_synthetic(&t.path().join("matte"), &matte, &synthetic_configs(5), 10.0).unwrap();
        let glossy = Svbrdf { specular: Image::filled(3, 32, 32, 0.6), roughness: Image::filled(1, 32, 32, 0.3), ..matte.clone() };
        write_synthetic(&t.path().join("glossy"), &glossy, &synthetic_configs(5), 10.0).unwrap();

        let out = t.path().join("report");
        let res = run(&eval_opts(&t.path().join("matte"), &out, &["printout"])).unwrap();
        assert_eq!(res.len(), 1);
        assert_eq!(res[0].rows.len(), 4);
        for r in &res[0].rows {
            assert!(r.scores.lpips < 0.02 && r.scores.psnr > 35.0, "{}: {:?}", r.photo, r.scores);
        }
        assert_eq!(res[0].rows[0].photo, "01.png");
        let csv = std::fs::read_to_string(out.join("captures.csv")).unwrap();
        assert_eq!(csv.lines().count(), 5);
        // A matte print-out relights exactly: wherever a highlight region counts, ratios of 1.
        assert_eq!(res[0].highlights.len(), 4);
        for h in &res[0].highlights {
            assert!([h.ghost, h.lobe, h.rest].iter().flatten().all(|v| (v - 1.0).abs() < 0.02), "{h:?}");
        }
        assert_eq!(std::fs::read_to_string(out.join("highlights.csv")).unwrap().lines().count(), 5);
        assert!(csv.lines().nth(1).unwrap().starts_with("printout,01.png,"));
        let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
        assert!(summary.contains("Estimated from `00.png`") && summary.contains("| printout |"), "{summary}");
        let grid = crate::io::read_image(&out.join("grid.jpg")).unwrap();
        // 5 rows (input + 4 photos) x 2 columns of 32 px cells, 4 px gaps.
        assert_eq!((grid.height, grid.width), (5 * 36 + 4, 2 * 36 + 4));

        let glossy_res = run(&eval_opts(&t.path().join("glossy"), &t.path().join("report2"), &["printout"])).unwrap();
        let mean = |r: &CaptureResults| r.rows.iter().map(|x| x.scores.lpips).sum::<f64>() / r.rows.len() as f64;
        assert!(mean(&glossy_res[0]) > 0.1, "{}", mean(&glossy_res[0]));
    }

    #[test]
    fn the_capture_fit_left_out_relights_a_glossy_capture_better_than_the_printout() {
        // kd in blocks, ks 0.6, roughness 0.3: each left-out photo's highlight
        // moves, which the print-out cannot draw and a fit to the other four
        // photos can.
        let t = tempfile::tempdir().unwrap();
        let mut glossy = Svbrdf::uniform(32, 32, [0.0; 3], [0.6; 3], 0.3);
        glossy.diffuse = Image::from_fn(3, 32, 32, |c, y, x| 0.15 + 0.6 * ((x / 8 + y / 8 + c) % 3) as f32 / 2.0);
        write_synthetic(t.path(), &glossy, &synthetic_configs(5), 10.0).unwrap();
        let opts = CaptureEvalOptions { capture_fit: Some(crate::fit::photos::PhotoFitConfig { steps: 300, ..Default::default() }), ..eval_opts(t.path(), &t.path().join("o"), &["printout"]) };
        let res = run(&opts).unwrap();
        assert_eq!(res.iter().map(|r| r.name.as_str()).collect::<Vec<_>>(), ["printout", CAPTURE_FIT_METHOD]);
        assert_eq!(res[1].rows.len(), 4);
        let mean = |r: &CaptureResults, f: fn(&Scores) -> f64| r.rows.iter().map(|x| f(&x.scores)).sum::<f64>() / r.rows.len() as f64;
        let (printout, fit) = (mean(&res[0], |s| s.lpips), mean(&res[1], |s| s.lpips));
        let (printout_log, fit_log) = (mean(&res[0], |s| s.rmse_log), mean(&res[1], |s| s.rmse_log));
        eprintln!("LPIPS printout {printout:.3} capture fit {fit:.3}; log RMSE {printout_log:.3} {fit_log:.3}");
        assert!(fit < 0.7 * printout, "LPIPS printout {printout} capture fit {fit}");
        assert!(fit_log < 0.7 * printout_log, "log RMSE printout {printout_log} capture fit {fit_log}");
        let summary = std::fs::read_to_string(t.path().join("o/summary.md")).unwrap();
        assert!(summary.contains(CAPTURE_FIT_METHOD), "{summary}");
    }

    #[test]
    fn capture_eval_refuses_bad_folders() {
        let t = tempfile::tempdir().unwrap();
        let m = Svbrdf::uniform(32, 32, [0.5; 3], [0.04; 3], 0.5);
        write_synthetic(t.path(), &m, &synthetic_configs(1), 10.0).unwrap();
        let e = format!("{:#}", run(&eval_opts(t.path(), &t.path().join("o"), &["printout"])).unwrap_err());
        assert!(e.contains("has 1 photo") && !e.contains('\n'), "{e}");

        // A photo that is not square.
        write_synthetic(t.path(), &m, &synthetic_configs(2), 10.0).unwrap();
        crate::io::write_png(&t.path().join("01.png"), &Image::filled(3, 32, 48, 0.5), crate::io::BitDepth::Eight).unwrap();
        let e = format!("{:#}", run(&eval_opts(t.path(), &t.path().join("o"), &["printout"])).unwrap_err());
        assert!(e.contains("01.png") && e.contains("not square"), "{e}");
        let e = format!("{:#}", run(&eval_opts(t.path(), &t.path().join("o"), &["/no/model.safetensors"])).unwrap_err());
        assert!(e.contains("/no/model.safetensors"), "{e}");
        assert!(write_synthetic(t.path(), &m, &[], 10.0).is_err());
    }

}
