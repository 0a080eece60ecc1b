//! Reports of an evaluation run: one CSV per method, `summary.md` (means
//! with 95% intervals in the paper's layout) and picture grids of the best
//! and worst materials.

use super::{case_configs, case_name, case_title, input_photo, mean_ci95, reference_renders, EvalOptions, Method, MethodResults};
use crate::image::Image;
use crate::svbrdf::Svbrdf;
use anyhow::Result;
use std::fmt::Write as _;
use tch::Tensor;

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

/// Markdown summary: one table per metric, rows methods, columns cases,
/// cells `mean ± 1.96 std / sqrt(n)` over materials.
pub fn summary_markdown(opts: &EvalOptions, results: &[MethodResults]) -> String {
    let n = results.first().map(|r| r.rows.iter().filter(|x| Some(x.case) == opts.cases.first().copied()).count()).unwrap_or(0);
    let mut s = String::from("# Evaluation\n\n");
    let _ = writeln!(
        s,
        "Dataset `{}`, {n} materials at {}x{}, seed {}, {} configurations per material (Reflect, Hemisphere), {} input photos.\n",
        opts.dataset,
        opts.size,
        opts.size,
        opts.seed,
        opts.configs,
        if opts.ldr_input { "LDR (clamped)" } else { "HDR" }
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
    s
}

/// Writes `NAME.csv` per method and `summary.md` (atomically).
pub fn write_reports(opts: &EvalOptions, results: &[MethodResults]) -> Result<()> {
    for r in results {
        crate::io::atomic_write_bytes(&opts.out.join(format!("{}.csv", r.name)), csv_text(r).as_bytes())?;
    }
    crate::io::atomic_write_bytes(&opts.out.join("summary.md"), summary_markdown(opts, results).as_bytes())
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

/// Display image of a linear `[3, H, W]` render.
fn display(t: &Tensor) -> Result<Image> {
    Image::from_tensor(&crate::spaces::linear_to_display(t))
}

/// Grid for one material: a row per case (its first configuration):
/// input photo | GGX reference | each method.
pub fn material_grid(opts: &EvalOptions, methods: &mut [Box<dyn Method>], index: usize, m: &Svbrdf) -> Result<Image> {
    let photo = input_photo(m, opts.ldr_input);
    for method in methods.iter_mut() {
        method.prepare(&photo)?;
    }
    let mut rows = Vec::new();
    for &case in &opts.cases {
        let cfg = &case_configs(case, opts.seed, index, opts.configs)[..1];
        let mut row = vec![display(&photo)?, display(&reference_renders(m, cfg).get(0))?];
        for method in methods.iter() {
            row.push(display(&method.render(cfg)?.get(0))?);
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

