//! Paired LPIPS difference of two scored models, material by material:
//! how a recipe is compared when the spread between materials (±0.03)
//! is larger than the difference between models.
//!
//! ```sh
//! cargo run --release --example paired_lpips -- BASE.csv NEW.csv [NEW2.csv ...]
//! ```
//!
//! Each CSV is a `flashmat eval` output (`OUT/NAME.csv`) of the same
//! dataset, seed and configurations; a folder holding one CSV may be given
//! instead. Prints, per case, mean(NEW - BASE) ± its 95% interval (1.96
//! standard errors) and how many materials NEW scores lower on.

use anyhow::{ensure, Context, Result};
use flashmat::eval::report::{csv_in, read_csv};
use flashmat::eval::{mean_ci95, Row};
use flashmat::geometry::Sampling;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// LPIPS by (material, case).
fn lpips_by_material(rows: &[Row]) -> BTreeMap<(String, String), f64> {
    rows.iter().map(|r| ((r.material.clone(), format!("{:?}", r.case)), r.scores.lpips)).collect()
}

fn main() -> Result<()> {
    let args: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    ensure!(args.len() >= 2, "usage: paired_lpips BASE.csv NEW.csv [NEW2.csv ...]");
    let base_path = csv_in(&args[0])?;
    let base = lpips_by_material(&read_csv(&base_path)?.rows);
    println!("against {}", base_path.display());
    for path in &args[1..] {
        let path = csv_in(path)?;
        let new = lpips_by_material(&read_csv(&path)?.rows);
        let mut cells = Vec::new();
        for case in [Sampling::Reflect, Sampling::Identity, Sampling::Hemisphere] {
            let case = format!("{case:?}");
            let diffs: Vec<f64> = base
                .iter()
                .filter(|((_, c), _)| *c == case)
                .map(|((m, c), b)| new.get(&(m.clone(), c.clone())).map(|v| v - b).with_context(|| format!("{}: material {m} is missing", path.display())))
                .collect::<Result<_>>()?;
            ensure!(!diffs.is_empty(), "{}: no {case} rows", base_path.display());
            let (mean, half) = mean_ci95(&diffs);
            let lower = diffs.iter().filter(|&&d| d < 0.0).count();
            cells.push(format!("{case} {mean:+.3} ± {half:.3} ({lower}/{})", diffs.len()));
        }
        println!("{}: {}", path.display(), cells.join(" | "));
    }
    Ok(())
}
