//! The authors' PyTorch step, timed in the same job as flashmat's
//! (`bench train|infer --reference DIR`), and the GPU's busy fraction while
//! a benchmark runs.
//!
//! `../shared/bench/ref_bench.py` times the authors' own model, losses and
//! training step on synthetic batches of the given shapes and prints one
//! JSON line per measurement; it needs a copy of their repository
//! (`APeculiarCamber/neural_appearance_estimation`) kept outside this one:
//! their code has no license, it is timed, never copied.

use anyhow::{bail, Context, Result};
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// Where the authors' code and the timing script are, and the Python that
/// runs them (it must have PyTorch: on the GPU machines `/opt/torch/.venv`).
pub struct ReferenceBench {
    repo: PathBuf,
    script: PathBuf,
    python: String,
}

/// The timing script's default place: `FLASHMAT_REF_BENCH`, else
/// `../shared/bench/ref_bench.py` beside the checkout, else
/// `.gpu/bench/ref_bench.py` inside it (where `scripts/gpu-train.sh stage`
/// puts a copy for a GPU job).
fn default_script() -> Option<PathBuf> {
    if let Ok(p) = std::env::var("FLASHMAT_REF_BENCH") {
        return Some(PathBuf::from(p));
    }
    let root = flashmat::bundled_root();
    [root.join("../shared/bench/ref_bench.py"), root.join(".gpu/bench/ref_bench.py")].into_iter().find(|p| p.is_file())
}

impl ReferenceBench {
    /// repo: the copy of the authors' repository; script: the timing
    /// script, or its default place. The Python is `FLASHMAT_PYTHON`, else
    /// `python3` on the PATH.
    pub fn new(repo: &Path, script: Option<&Path>) -> Result<Self> {
        if !repo.join("prl_main_train.py").is_file() {
            bail!("--reference {}: not a copy of the authors' repository (no prl_main_train.py there; see ../shared/bench/README.md)", repo.display());
        }
        let script = match script {
            Some(p) => p.to_path_buf(),
            None => default_script().context("--reference: the timing script ref_bench.py was not found (../shared/bench/, .gpu/bench/ or FLASHMAT_REF_BENCH); pass --ref-bench")?,
        };
        if !script.is_file() {
            bail!("--ref-bench {}: no such file", script.display());
        }
        let python = std::env::var("FLASHMAT_PYTHON").unwrap_or_else(|_| "python3".into());
        Ok(Self { repo: repo.to_path_buf(), script, python })
    }

    /// Runs the script with `args` and returns its JSON lines. Its own
    /// prints (stderr) are kept for the error message only: a failure is
    /// one line with the last thing it said.
    pub fn run(&self, args: &[String]) -> Result<Vec<Value>> {
        let out = Command::new(&self.python)
            .arg(&self.script)
            .args(args)
            .env("REF_DIR", &self.repo)
            .stdin(Stdio::null())
            .output()
            .with_context(|| format!("could not start {} for the authors' benchmark", self.python))?;
        let lines: Vec<Value> = String::from_utf8_lossy(&out.stdout).lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
        if !out.status.success() {
            let stderr = String::from_utf8_lossy(&out.stderr);
            let last = stderr.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("(no message)");
            bail!("the authors' benchmark failed ({}): {last}", out.status);
        }
        Ok(lines)
    }
}

/// The first line of `lines` whose "what" is `what` and whose fields
/// `matching` have these values.
pub fn find<'a>(lines: &'a [Value], what: &str, matching: &[(&str, Value)]) -> Option<&'a Value> {
    lines.iter().find(|l| l["what"] == what && matching.iter().all(|(k, v)| &l[*k] == v))
}

/// `nvidia-smi` sampling the GPU's utilisation every 100 ms while a
/// benchmark runs. Its output is read by a thread (a full pipe would stall
/// it) and its stderr goes nowhere: a sampler holding the job's own output
/// open kept two GPU jobs running to their time limit (docs/GPU.md).
pub struct BusySampler {
    child: Child,
    reader: std::thread::JoinHandle<Vec<f64>>,
}

impl BusySampler {
    /// None where there is no `nvidia-smi` (the CPU).
    pub fn start(gpu: usize) -> Option<Self> {
        let mut child = Command::new("nvidia-smi")
            .args(["--query-gpu=utilization.gpu", "--format=csv,noheader,nounits", "-lms", "100", "-i", &gpu.to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .ok()?;
        let stdout = child.stdout.take()?;
        let reader = std::thread::spawn(move || BufReader::new(stdout).lines().map_while(|l| l.ok()).filter_map(|l| l.trim().parse::<f64>().ok()).collect());
        Some(Self { child, reader })
    }

    /// Stops sampling; the mean utilisation as a fraction, None without samples.
    pub fn finish(mut self) -> Option<f64> {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let samples = self.reader.join().ok()?;
        busy_fraction(&samples)
    }
}

/// Mean of `nvidia-smi`'s percentages, as a fraction; None without samples.
pub fn busy_fraction(percent: &[f64]) -> Option<f64> {
    (!percent.is_empty()).then(|| percent.iter().sum::<f64>() / percent.len() as f64 / 100.0)
}

/// One row of a side-by-side table.
pub struct Row {
    pub what: String,
    pub ours_ms: Option<f64>,
    pub theirs_ms: Option<f64>,
    /// Materials (training) or photos (inference) per second, ours and theirs.
    pub ours_rate: Option<f64>,
    pub theirs_rate: Option<f64>,
    pub busy: Option<f64>,
    pub tflops: Option<f64>,
}

/// The table as Markdown: milliseconds, the speed ratio (theirs / ours:
/// above 1 flashmat is faster), rates, the GPU's busy fraction and
/// flashmat's achieved TFLOP/s.
pub fn markdown(title: &str, rows: &[Row]) -> String {
    let f = |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |v| format!("{v:.digits$}"));
    let mut s = format!("{title}\n\n| what | flashmat ms | authors' ms | speed-up (authors' / flashmat) | flashmat per s | authors' per s | GPU busy | flashmat TFLOP/s |\n|---|---|---|---|---|---|---|---|\n");
    for r in rows {
        let ratio = match (r.ours_ms, r.theirs_ms) {
            (Some(a), Some(b)) if a > 0.0 => format!("{:.2}x", b / a),
            _ => "-".into(),
        };
        s += &format!(
            "| {} | {} | {} | {ratio} | {} | {} | {} | {} |\n",
            r.what,
            f(r.ours_ms, 1),
            f(r.theirs_ms, 1),
            f(r.ours_rate, 2),
            f(r.theirs_rate, 2),
            r.busy.map_or("-".into(), |b| format!("{:.0}%", 100.0 * b)),
            f(r.tflops, 3)
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_gives_the_authors_time_over_ours() {
        let rows = [
            Row { what: "step".into(), ours_ms: Some(78.0), theirs_ms: Some(234.0), ours_rate: Some(25.6), theirs_rate: Some(8.5), busy: Some(0.913), tflops: Some(12.345) },
            Row { what: "2048".into(), ours_ms: Some(500.0), theirs_ms: None, ours_rate: None, theirs_rate: None, busy: None, tflops: None },
        ];
        let md = markdown("## t", &rows);
        assert!(md.contains("| step | 78.0 | 234.0 | 3.00x | 25.60 | 8.50 | 91% | 12.345 |"), "{md}");
        assert!(md.contains("| 2048 | 500.0 | - | - | - | - | - | - |"), "{md}");
    }

    #[test]
    fn busy_fraction_is_the_mean_percentage() {
        assert_eq!(busy_fraction(&[]), None);
        assert_eq!(busy_fraction(&[100.0, 50.0, 0.0, 90.0]), Some(0.6));
    }

    #[test]
    fn finds_a_measurement_by_its_fields() {
        let lines: Vec<Value> = ["{\"what\":\"ref_infer\",\"size\":256,\"ms\":24}", "{\"what\":\"ref_infer\",\"size\":1024,\"ms\":222}"].iter().map(|l| serde_json::from_str(l).unwrap()).collect();
        assert_eq!(find(&lines, "ref_infer", &[("size", 1024.into())]).unwrap()["ms"], 222);
        assert!(find(&lines, "ref_infer", &[("size", 2048.into())]).is_none());
    }

    #[test]
    fn refuses_a_folder_that_is_not_the_authors_repository() {
        let dir = tempfile::tempdir().unwrap();
        let e = ReferenceBench::new(dir.path(), None).err().unwrap().to_string();
        assert!(e.contains("not a copy of the authors' repository") && !e.contains('\n'), "{e}");
    }
}
