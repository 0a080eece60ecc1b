//! Reports of an evaluation run: one CSV per method, `summary.md` (means
//! with 95% intervals in the paper's layout) and picture grids of the best
//! and worst materials.

use super::methods::split_refined;
use super::{case_configs, case_name, case_title, material_photo, mean_ci95, reference_renders, EvalOptions, Method, MethodResults};
use crate::data::loaders::Unreadable;
use crate::image::Image;
use crate::svbrdf::Svbrdf;
use anyhow::Result;
use std::fmt::Write as _;

/// Subfolder of an evaluation's output with the moved-highlight test's
/// `ratios.csv` and `moved.jpg` (apart, so the folder's `*.csv` stay the
/// methods' own).
pub const HIGHLIGHTS_DIR: &str = "highlights";

/// Subfolder with the exposure curve's `curve.csv`.
pub const EXPOSURE_DIR: &str = "exposure";

/// JPEG quality of report pictures (grids): small enough for the
/// repository, no visible blocking at the grids' cell sizes.
pub const REPORT_JPEG_QUALITY: u8 = 88;

/// CSV text of one method: `material,case,lpips,rmse_log,psnr`.
pub fn csv_text(res: &MethodResults) -> String {
    let mut s = String::from("material,case,lpips,rmse_log,psnr\n");
    for r in &res.rows {
        let _ = writeln!(s, "{},{},{:.6},{:.6},{:.4}", r.material, case_name(r.case), r.scores.lpips, r.scores.rmse_log, r.scores.psnr);
    }
    s
}

/// Reads a CSV written by [`csv_text`] back (method named by the file stem).
pub fn read_csv(path: &std::path::Path) -> Result<MethodResults> {
    use anyhow::{bail, Context};
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let mut lines = text.lines();
    if lines.next() != Some("material,case,lpips,rmse_log,psnr") {
        bail!("{}: not an evaluation CSV (header material,case,lpips,rmse_log,psnr)", path.display());
    }
    let rows = lines
        .enumerate()
        .map(|(i, line)| {
            let bad = || anyhow::anyhow!("{} line {}: expected material,case,lpips,rmse_log,psnr, got '{line}'", path.display(), i + 2);
            let f: Vec<&str> = line.split(',').collect();
            if f.len() != 5 {
                return Err(bad());
            }
            use crate::geometry::Sampling;
            let case = [Sampling::Reflect, Sampling::Identity, Sampling::Hemisphere]
                .into_iter()
                .find(|&c| case_name(c) == f[1])
                .ok_or_else(bad)?;
            let num = |s: &str| s.parse::<f64>().map_err(|_| bad());
            Ok(super::Row { material: f[0].to_string(), case, scores: super::Scores { lpips: num(f[2])?, rmse_log: num(f[3])?, psnr: num(f[4])? } })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(MethodResults { rows, ..MethodResults::new(name) })
}

/// The one evaluation CSV of an output folder (`flashmat eval` names it
/// after the model file); a CSV path is returned as it is.
pub fn csv_in(path: &std::path::Path) -> Result<std::path::PathBuf> {
    use anyhow::{bail, Context};
    if !path.is_dir() {
        return Ok(path.to_path_buf());
    }
    let csvs: Vec<std::path::PathBuf> = std::fs::read_dir(path)
        .with_context(|| format!("cannot read {}", path.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "csv"))
        .collect();
    match csvs.as_slice() {
        [one] => Ok(one.clone()),
        _ => bail!("{}: expected exactly one .csv, found {}", path.display(), csvs.len()),
    }
}

/// Re-reads every `NAME.csv` of `opts.out` (e.g. CSVs of several runs with
/// the same dataset, seed and configurations copied into one folder) and
/// rewrites `summary.md` and `refine.png` from them. Methods are ordered by
/// name, refined variants by their steps after their model.
pub fn resummarize(opts: &EvalOptions) -> Result<Vec<MethodResults>> {
    use anyhow::Context;
    let mut paths: Vec<std::path::PathBuf> = std::fs::read_dir(&opts.out)
        .with_context(|| format!("cannot read {}", opts.out.display()))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()?;
    paths.retain(|p| p.extension().is_some_and(|e| e == "csv"));
    anyhow::ensure!(!paths.is_empty(), "{} holds no evaluation CSV", opts.out.display());
    let mut results = paths.iter().map(|p| read_csv(p)).collect::<Result<Vec<_>>>()?;
    results.sort_by(|a, b| split_refined(&a.name).cmp(&split_refined(&b.name)));
    let n = results[0].rows.len();
    for r in &results {
        anyhow::ensure!(r.rows.len() == n, "{}.csv has {} rows, {}.csv {n}: not the same evaluation", r.name, r.rows.len(), results[0].name);
    }
    let mut cases: Vec<crate::geometry::Sampling> = vec![];
    for row in &results[0].rows {
        if !cases.contains(&row.case) {
            cases.push(row.case);
        }
    }
    let opts = EvalOptions { cases, ..opts.clone() };
    // The CSVs hold the materials scored; the ones skipped are kept from the summary.
    let old = std::fs::read_to_string(opts.out.join("summary.md")).unwrap_or_default();
    write_reports(&opts, &results, &read_skipped(&old))?;
    Ok(results)
}

/// Title of the summary's last section, on materials left out.
const SKIPPED_TITLE: &str = "## Skipped materials";

/// The section naming the dataset materials that could not be read (empty
/// for none): a line ``- `NAME`: REASON`` each.
fn skipped_markdown(skipped: &[Unreadable]) -> String {
    if skipped.is_empty() {
        return String::new();
    }
    let mut s = format!("{SKIPPED_TITLE}\n\n{} material(s) of the dataset could not be read and are in no table above:\n\n", skipped.len());
    for u in skipped {
        let _ = writeln!(s, "- `{}`: {}", u.name, u.reason);
    }
    s
}

/// The materials listed by [`skipped_markdown`] in a summary's text.
fn read_skipped(summary: &str) -> Vec<Unreadable> {
    let Some(at) = summary.find(SKIPPED_TITLE) else { return vec![] };
    summary[at..]
        .lines()
        .filter_map(|l| l.strip_prefix("- `")?.split_once("`: "))
        .map(|(name, reason)| Unreadable { name: name.to_string(), reason: reason.to_string() })
        .collect()
}

/// Markdown summary: one table per metric, rows methods, columns cases,
/// cells `mean ± 1.96 std / sqrt(n)` over materials; last, the dataset
/// materials `skipped` (unreadable), if any.
pub fn summary_markdown(opts: &EvalOptions, results: &[MethodResults], skipped: &[Unreadable]) -> String {
    let n = results.first().map(|r| r.rows.iter().filter(|x| Some(x.case) == opts.cases.first().copied()).count()).unwrap_or(0);
    let mut s = String::from("# Evaluation\n\n");
    let _ = writeln!(
        s,
        "Dataset `{}`, {n} materials{} at {}x{}, seed {}, {} configurations per material (Reflect, Hemisphere), {} input photos.\n",
        opts.dataset,
        if skipped.is_empty() { String::new() } else { format!(" ({} unreadable left out, named at the end)", skipped.len()) },
        opts.size,
        opts.size,
        opts.seed,
        opts.configs,
        match (&opts.phone_photos, opts.ldr_input) {
            (Some(p), _) if p.jpeg_quality.is_some() => "phone (JPEG, camera off-centre, flash beside the lens, noise: `--phone-photos --phone-jpeg`)",
            (Some(_), _) => "phone (8-bit sRGB, camera off-centre, flash beside the lens, noise: `--phone-photos`)",
            (None, true) => "LDR (clamped)",
            (None, false) => "HDR",
        }
    );
    let metrics: [(&str, fn(&super::Scores) -> f64, usize); 3] = [
        ("LPIPS (AlexNet, linear renders clamped to [0,1]; lower is better)", |x| x.lpips, 3),
        ("RMSE of ln(1 + R) (lower is better)", |x| x.rmse_log, 3),
        ("PSNR of display images clamp(R)^(1/2.2), dB (higher is better; identical images count 100 dB)", |x| x.psnr, 2),
    ];
    for (title, get, digits) in metrics {
        let _ = writeln!(s, "## {title}\n");
        let _ = writeln!(s, "| Method | {} |", opts.cases.iter().map(|&c| case_title(c)).collect::<Vec<_>>().join(" | "));
        let _ = writeln!(s, "|---|{}", "---|".repeat(opts.cases.len()));
        for r in results {
            let cells: Vec<String> = opts
                .cases
                .iter()
                .map(|&c| {
                    let v: Vec<f64> = r.rows.iter().filter(|x| x.case == c).map(|x| get(&x.scores)).collect();
                    let (m, h) = mean_ci95(&v);
                    format!("{m:.digits$} ± {h:.digits$}")
                })
                .collect();
            let _ = writeln!(s, "| {} | {} |", r.name, cells.join(" | "));
        }
        s.push('\n');
    }
    if results.iter().any(|r| !r.highlights.is_empty()) {
        s.push_str(&super::highlights::markdown(&highlight_rows(results), &super::highlights::HighlightConfig::default()));
        s.push('\n');
    }
    if results.iter().any(|r| !r.exposure.is_empty()) {
        s.push_str(&super::exposure::markdown(&exposure_rows(results), opts.ldr_input));
        s.push('\n');
    }
    s.push_str(&skipped_markdown(skipped));
    s
}

fn highlight_rows(results: &[MethodResults]) -> Vec<(String, Vec<super::highlights::MaterialHighlights>)> {
    results.iter().map(|r| (r.name.clone(), r.highlights.clone())).collect()
}

fn exposure_rows(results: &[MethodResults]) -> Vec<(String, Vec<super::exposure::ExposureRow>)> {
    results.iter().map(|r| (r.name.clone(), r.exposure.clone())).collect()
}

/// Writes `NAME.csv` per method and `summary.md` (atomically; naming the
/// `skipped` materials), and `refine.png` when a model was scored at two
/// or more refinement steps.
pub fn write_reports(opts: &EvalOptions, results: &[MethodResults], skipped: &[Unreadable]) -> Result<()> {
    for r in results {
        crate::io::atomic_write_bytes(&opts.out.join(format!("{}.csv", r.name)), csv_text(r).as_bytes())?;
    }
    crate::io::atomic_write_bytes(&opts.out.join("summary.md"), summary_markdown(opts, results, skipped).as_bytes())?;
    if results.iter().any(|r| !r.highlights.is_empty()) {
        let dir = opts.out.join(HIGHLIGHTS_DIR);
        std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("cannot create {}: {e}", dir.display()))?;
        crate::io::atomic_write_bytes(&dir.join("ratios.csv"), super::highlights::csv_text(&highlight_rows(results)).as_bytes())?;
    }
    if results.iter().any(|r| !r.exposure.is_empty()) {
        let dir = opts.out.join(EXPOSURE_DIR);
        std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("cannot create {}: {e}", dir.display()))?;
        crate::io::atomic_write_bytes(&dir.join("curve.csv"), super::exposure::csv_text(&exposure_rows(results)).as_bytes())?;
    }
    let series = refine_series(opts, results);
    if series.first().is_some_and(|s| s.points.len() >= 2) {
        let chart = crate::viz::line_chart("mean LPIPS against refinement steps", &series, 640, 360)?;
        crate::io::write_png(&opts.out.join("refine.png"), &chart, crate::io::BitDepth::Eight)?;
    }
    Ok(())
}

/// Writes `highlights/moved.jpg` and `moved.txt`: the moved-highlight
/// test's picture of the glossiest materials ([`super::highlights::picture`]).
pub fn write_highlight_picture(opts: &EvalOptions, methods: &mut [Box<dyn Method>], materials: &[(String, Svbrdf)]) -> Result<()> {
    let cfg = super::highlights::HighlightConfig::default();
    let Some((grid, note)) = super::highlights::picture(methods, materials, opts, &cfg)? else { return Ok(()) };
    let dir = opts.out.join(HIGHLIGHTS_DIR);
    std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("cannot create {}: {e}", dir.display()))?;
    // Half size: the 256-pixel panels of a 50-material run made a 1824x1044
    // picture of 280 KB, and the tracked tree has a 32 MiB budget.
    crate::io::write_jpeg(&dir.join("moved.jpg"), &grid.downsample(2), REPORT_JPEG_QUALITY)?;
    crate::io::atomic_write_bytes(&dir.join("moved.txt"), note.as_bytes())
}

/// Refinement steps of a method name: 0 for a flashmat model `NAME` when
/// `NAME+refineN` methods exist, N for those.
fn refine_steps(name: &str, results: &[MethodResults]) -> Option<(String, usize)> {
    let (base, steps) = split_refined(name);
    let refined_exists = || results.iter().any(|r| r.name != name && split_refined(&r.name).0 == base);
    (steps > 0 || refined_exists()).then(|| (base.to_string(), steps))
}

/// Mean LPIPS per case against refinement steps, for the first model
/// scored at several steps (series named `case (model)`).
pub fn refine_series(opts: &EvalOptions, results: &[MethodResults]) -> Vec<crate::viz::Series> {
    let Some((model, _)) = results.iter().find_map(|r| refine_steps(&r.name, results)) else { return vec![] };
    opts.cases
        .iter()
        .map(|&case| {
            let mut points: Vec<(f64, f64)> = results
                .iter()
                .filter_map(|r| {
                    let (base, steps) = refine_steps(&r.name, results)?;
                    let v: Vec<f64> = r.rows.iter().filter(|x| x.case == case).map(|x| x.scores.lpips).collect();
                    (base == model && !v.is_empty()).then(|| (steps as f64, mean_ci95(&v).0))
                })
                .collect();
            points.sort_by(|a, b| a.0.total_cmp(&b.0));
            crate::viz::Series { name: format!("{} ({model})", case_title(case)), points }
        })
        .collect()
}

/// Material indices ordered from best to worst by the first method's mean
/// LPIPS over all cases.
pub fn rank_materials(results: &[MethodResults], materials: usize) -> Vec<usize> {
    let Some(first) = results.first() else { return vec![] };
    let per_case = first.rows.len() / materials.max(1);
    let mut means: Vec<(f64, usize)> = (0..materials)
        .map(|i| {
            let rows = &first.rows[i * per_case..(i + 1) * per_case];
            (rows.iter().map(|r| r.scores.lpips).sum::<f64>() / per_case.max(1) as f64, i)
        })
        .collect();
    means.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    means.into_iter().map(|(_, i)| i).collect()
}

/// Grid for one material: a row per case (its first configuration):
/// input photo | GGX reference | each method.
pub fn material_grid(opts: &EvalOptions, methods: &mut [Box<dyn Method>], index: usize, m: &Svbrdf) -> Result<Image> {
    let photo = material_photo(m, index, opts)?.1;
    for method in methods.iter_mut() {
        method.prepare(&photo)?;
    }
    let mut rows = Vec::new();
    for &case in &opts.cases {
        let cfg = &case_configs(case, opts.seed, index, opts.configs)[..1];
        let mut row = vec![Image::display_of(&photo)?, Image::display_of(&reference_renders(m, cfg).get(0))?];
        for method in methods.iter() {
            row.push(Image::display_of(&method.render(cfg)?.get(0))?);
        }
        rows.push(row);
    }
    crate::viz::grid(&rows, 4)
}

/// Writes `best.jpg` and `worst.jpg`: grids of the materials the first
/// method re-renders best and worst (mean LPIPS over the cases); the
/// material names go to `grids.txt`.
pub fn write_grids(opts: &EvalOptions, methods: &mut [Box<dyn Method>], materials: &[(String, Svbrdf)], results: &[MethodResults]) -> Result<()> {
    let order = rank_materials(results, materials.len());
    let (Some(&best), Some(&worst)) = (order.first(), order.last()) else { return Ok(()) };
    let names: Vec<String> = methods.iter().map(|m| m.name()).collect();
    let mut note = format!(
        "Columns: input photo | GGX reference | {}\nRows: {}\nRanked by {}'s mean LPIPS over the cases.\n",
        names.join(" | "),
        opts.cases.iter().map(|&c| case_title(c)).collect::<Vec<_>>().join(", "),
        names.first().cloned().unwrap_or_default()
    );
    for (file, i) in [("best.jpg", best), ("worst.jpg", worst)] {
        let g = material_grid(opts, methods, i, &materials[i].1)?;
        crate::io::write_jpeg(&opts.out.join(file), &g, REPORT_JPEG_QUALITY)?;
        let _ = writeln!(note, "{file}: {}", materials[i].0);
    }
    crate::io::atomic_write_bytes(&opts.out.join("grids.txt"), note.as_bytes())
}

