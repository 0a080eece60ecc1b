//! The equal-time study of issue 15 (`reports/equal-time.md`): held-out
//! scores of training recipes against the CPU time they spent.
//!
//! Reads, under RUNS (the folder of `scripts/equal-time.sh`):
//! - `eval/NAME-STEP/*.csv`: `flashmat eval` of the snapshot
//!   `NAME-STEP.safetensors` (per material and case: lpips, rmse_log);
//! - `eval/printout/printout.csv`: the print-out baseline on the same set;
//! - `NAME/log.jsonl`: the run's step times (`seconds` per step), summed up
//!   to STEP; past the log's end at the run's mean step time (marked `~`);
//! - `NAME/colour.jsonl` (and `NAME+*/colour.jsonl`, runs that continue
//!   it): the uniform-colour check at STEP, when logged.
//!
//! Writes OUT/points.csv, OUT/table.md and OUT/equal-time.png.
//!
//! ```sh
//! cargo run --release --example equal_time -- RUNS OUT [NAME=EXTRA_MINUTES ...]
//! ```
//! EXTRA_MINUTES is time a recipe spent before its run (the curriculum's teacher).

use anyhow::{bail, Context, Result};
use flashmat::viz::{line_chart_over, Series};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Means per case (reflect, identity, hemisphere) of an eval CSV: (LPIPS, RMSE of ln(1 + R)).
fn case_means(csv: &Path) -> Result<([f64; 3], [f64; 3])> {
    use flashmat::geometry::Sampling;
    let results = flashmat::eval::report::read_csv(csv)?;
    let mean = |case: Sampling, score: fn(&flashmat::eval::Scores) -> f64| {
        let v: Vec<f64> = results.rows.iter().filter(|r| r.case == case).map(|r| score(&r.scores)).collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    let cases = [Sampling::Reflect, Sampling::Identity, Sampling::Hemisphere];
    Ok((cases.map(|c| mean(c, |s| s.lpips)), cases.map(|c| mean(c, |s| s.rmse_log))))
}

/// Lines of a JSONL file as JSON values (missing file: none).
fn jsonl(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path).map(|t| t.lines().filter_map(|l| serde_json::from_str(l).ok()).collect()).unwrap_or_default()
}

/// Minutes of step time up to `step` and whether they were extrapolated.
fn step_minutes(log: &[serde_json::Value], step: u64) -> Option<(f64, bool)> {
    // A resumed run may repeat steps after its last checkpoint: keep the last of each.
    let mut seconds = BTreeMap::new();
    for row in log {
        if let (Some(s), Some(t)) = (row["step"].as_u64(), row["seconds"].as_f64()) {
            seconds.insert(s, t);
        }
    }
    if seconds.is_empty() {
        return None;
    }
    let within: f64 = seconds.range(..=step).map(|(_, t)| t).sum();
    let last = *seconds.keys().next_back()?;
    if step <= last {
        return Some((within / 60.0, false));
    }
    let mean = seconds.values().sum::<f64>() / seconds.len() as f64;
    Some(((within + (step - last) as f64 * mean) / 60.0, true))
}

struct Point {
    recipe: String,
    step: u64,
    minutes: f64,
    extrapolated: bool,
    lpips: [f64; 3],
    rmse: [f64; 3],
    /// Uniform-colour check at the step: identity chromaticity error, near-black highlight ratio.
    colour: Option<(f64, f64)>,
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        bail!("usage: equal_time RUNS OUT [NAME=EXTRA_MINUTES ...]");
    }
    let (runs, out) = (PathBuf::from(&args[0]), PathBuf::from(&args[1]));
    let mut extra = BTreeMap::new();
    for a in &args[2..] {
        let (name, minutes) = a.split_once('=').with_context(|| format!("expected NAME=MINUTES, got {a}"))?;
        extra.insert(name.to_string(), minutes.parse::<f64>()?);
    }
    let printout_csv = runs.join("eval/printout/printout.csv");
    let printout = case_means(&printout_csv)?;
    let mut points = vec![];
    for entry in std::fs::read_dir(runs.join("eval"))? {
        let dir = entry?.path();
        let name = dir.file_name().unwrap_or_default().to_string_lossy().to_string();
        let Some((recipe, step)) = name.rsplit_once('-') else { continue };
        let Ok(step) = step.parse::<u64>() else { continue };
        let csv = flashmat::eval::report::csv_in(&dir)?;
        let log = jsonl(&runs.join(recipe).join("log.jsonl"));
        let (minutes, extrapolated) = step_minutes(&log, step).with_context(|| format!("no step times for {recipe} in {}", runs.join(recipe).display()))?;
        // A recipe's colour rows: its run, and runs that continue it (`NAME+OTHER`, links to them).
        let mut colour_rows = jsonl(&runs.join(recipe).join("colour.jsonl"));
        for other in std::fs::read_dir(&runs)?.filter_map(|e| e.ok()) {
            if other.file_name().to_string_lossy().starts_with(&format!("{recipe}+")) {
                colour_rows.extend(jsonl(&other.path().join("colour.jsonl")));
            }
        }
        let colour = colour_rows
            .iter()
            .find(|r| r["step"].as_u64() == Some(step))
            .and_then(|r| Some((r["identity_chroma_error"].as_f64()?, r["near_black_highlight_ratio"].as_f64()?)));
        let (lpips, rmse) = case_means(&csv)?;
        points.push(Point {
            recipe: recipe.to_string(),
            step,
            minutes: minutes + extra.get(recipe).copied().unwrap_or(0.0),
            extrapolated,
            lpips,
            rmse,
            colour,
        });
    }
    points.sort_by(|a, b| (&a.recipe, a.step).cmp(&(&b.recipe, b.step)));
    std::fs::create_dir_all(&out)?;
    let mut csv = String::from("recipe,step,cpu_minutes,extrapolated,lpips_reflect,lpips_identity,lpips_hemisphere,rmse_reflect,rmse_identity,rmse_hemisphere,identity_chroma_32,near_black_highlight_32\n");
    let mut md = String::from("| recipe | step | CPU minutes | LPIPS Reflect | Identity | Hemisphere | log-RMSE Reflect | Hemisphere | chroma error (32x32) | near-black highlight |\n|---|---|---|---|---|---|---|---|---|---|\n");
    for p in &points {
        let (chroma, highlight) = p.colour.map(|(c, h)| (format!("{c:.3}"), format!("{h:.2}"))).unwrap_or_default();
        writeln!(csv, "{},{},{:.2},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{chroma},{highlight}", p.recipe, p.step, p.minutes, p.extrapolated, p.lpips[0], p.lpips[1], p.lpips[2], p.rmse[0], p.rmse[1], p.rmse[2])?;
        let approx = if p.extrapolated { "~" } else { "" };
        let or_dash = |v: String| if v.is_empty() { "-".to_string() } else { v };
        writeln!(md, "| {} | {} | {approx}{:.1} | {:.3} | {:.3} | {:.3} | {:.4} | {:.4} | {} | {} |", p.recipe, p.step, p.minutes, p.lpips[0], p.lpips[1], p.lpips[2], p.rmse[0], p.rmse[2], or_dash(chroma), or_dash(highlight))?;
    }
    writeln!(md, "| print-out | - | 0 | {:.3} | {:.3} | {:.3} | {:.4} | {:.4} | - | - |", printout.0[0], printout.0[1], printout.0[2], printout.1[0], printout.1[2])?;
    std::fs::write(out.join("points.csv"), csv)?;
    std::fs::write(out.join("table.md"), &md)?;

    let x_max = points.iter().map(|p| p.minutes).fold(1.0, f64::max);
    let chart = |title: &str, value: &dyn Fn(&Point) -> Option<f64>, baseline: Option<f64>| -> Result<flashmat::image::Image> {
        let mut by_recipe: BTreeMap<&str, Vec<(f64, f64)>> = BTreeMap::new();
        for p in &points {
            if let Some(v) = value(p) {
                by_recipe.entry(&p.recipe).or_default().push((p.minutes, v));
            }
        }
        let mut series: Vec<Series> = by_recipe.into_iter().map(|(name, points)| Series { name: name.to_string(), points }).collect();
        if let Some(b) = baseline {
            series.push(Series { name: "print-out".into(), points: vec![(0.0, b), (x_max, b)] });
        }
        line_chart_over(title, "CPU minutes (one thread)", &series, 720, 300)
    };
    let rows = vec![
        vec![chart("held-out LPIPS, Hemisphere (lower is better)", &|p| Some(p.lpips[2]), Some(printout.0[2]))?],
        vec![chart("held-out LPIPS, Reflect", &|p| Some(p.lpips[0]), Some(printout.0[0]))?],
        vec![chart("uniform-colour check: identity chromaticity error (32x32)", &|p| p.colour.map(|c| c.0), None)?],
    ];
    flashmat::io::write_png(&out.join("equal-time.png"), &flashmat::viz::grid(&rows, 0)?, flashmat::io::BitDepth::Eight)?;
    println!("{}", md);
    println!("wrote {}", out.display());
    Ok(())
}
