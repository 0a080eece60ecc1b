//! Whole folders in one command (`estimate|fit|view DIR|FILE... -o OUTDIR`):
//! the inputs listed, one output per input in OUTDIR, one progress bar, a
//! failed input reported in one line and skipped, a summary at the end.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Extensions of the files a folder contributes: photos, and for commands
/// that open materials, `.nmat` too. HEIC/HEIF/AVIF photos are listed in
/// every build: without the `heif` feature each is reported with the way to
/// convert it.
pub const PHOTO_EXTENSIONS: &[&str] = &["png", "jpg", "jpeg", "exr", "heic", "heif", "avif"];

/// True when the inputs are a batch: several of them, or a folder.
pub fn is_batch(inputs: &[PathBuf]) -> bool {
    inputs.len() > 1 || inputs.iter().any(|p| p.is_dir())
}

/// The files of the batch: each folder's files with one of `extensions`
/// (not recursive, sorted by name; hidden files skipped), files as given.
/// A folder without any is an error (nothing to do is not a success).
pub fn list_inputs(inputs: &[PathBuf], extensions: &[&str]) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)
                .with_context(|| format!("cannot read folder {}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    let hidden = p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with('.'));
                    let ext = p.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
                    !hidden && p.is_file() && ext.is_some_and(|e| extensions.contains(&e.as_str()))
                })
                .collect();
            if found.is_empty() {
                bail!("folder {} holds no input files (.{})", input.display(), extensions.join(", ."));
            }
            found.sort();
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    Ok(files)
}

/// Output names, one per input: the file stem, or the whole file name where
/// two inputs share a stem (`a.png` and `a.exr` give `a.png`, `a.exr`), and
/// `-2`, `-3`... after a name still taken (the same name in two folders), so
/// no output overwrites another.
pub fn output_names(files: &[PathBuf]) -> Vec<String> {
    let stem = |p: &Path| p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "input".into());
    let mut count: HashMap<String, usize> = HashMap::new();
    files.iter().for_each(|f| *count.entry(stem(f)).or_default() += 1);
    let mut taken = std::collections::HashSet::new();
    files
        .iter()
        .map(|f| {
            let s = stem(f);
            let base = if count[&s] > 1 { f.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or(s) } else { s };
            let name = (1..).map(|i| if i == 1 { base.clone() } else { format!("{base}-{i}") }).find(|n| !taken.contains(n)).expect("unbounded");
            taken.insert(name.clone());
            name
        })
        .collect()
}

/// Runs `work(input, output, bar)` on every input, where output is
/// `OUTDIR/NAME{suffix}` (`suffix`: `.nmat`, `.html`, or "" for a folder).
/// `work` returns its report line (printed above the bar) and may set the
/// bar's message to show its own progress. An input that fails is reported
/// in one line and skipped; the summary line ends the run, and when any
/// input failed it is the error (exit code 1).
pub fn run_batch(verb: &str, inputs: &[PathBuf], extensions: &[&str], out_dir: &Path, suffix: &str, mut work: impl FnMut(&Path, &Path, &ProgressBar) -> Result<String>) -> Result<()> {
    // `estimate DIR -o m.nmat` is most likely a mistake (a folder where a photo was meant): one line, no run.
    let ext = suffix.trim_start_matches('.');
    if !ext.is_empty() && out_dir.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case(ext)) {
        bail!("{}: with several inputs or a directory of them, -o names an output folder, not a {suffix} file", out_dir.display());
    }
    if let Ok(m) = std::fs::symlink_metadata(out_dir) {
        if !m.is_dir() {
            bail!("{}: with several inputs or a folder, -o names an output folder, and a file of that name exists", out_dir.display());
        }
    }
    let files = list_inputs(inputs, extensions)?;
    std::fs::create_dir_all(out_dir).with_context(|| format!("cannot create output folder {}", out_dir.display()))?;
    let names = output_names(&files);
    // The verb is plain text in the template (braces would be keys).
    let template = format!("{} {{bar:30}} {{pos}}/{{len}} ETA {{eta}} {{msg}}", verb.replace(['{', '}'], ""));
    let bar = ProgressBar::new(files.len() as u64).with_style(ProgressStyle::with_template(&template)?);
    let mut failed = Vec::new();
    for (file, name) in files.iter().zip(&names) {
        let output = out_dir.join(format!("{name}{suffix}"));
        bar.set_message(file.display().to_string());
        // One line per input, whatever the error chain holds.
        match work(file, &output, &bar) {
            // suspend, not println: println prints nothing when stderr is no terminal.
            Ok(line) => bar.suspend(|| eprintln!("{} -> {}: {line}", file.display(), output.display())),
            Err(e) => {
                bar.suspend(|| eprintln!("failed: {}: {}", file.display(), format!("{e:#}").replace('\n', " ")));
                failed.push(file.display().to_string());
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = files.len();
    let summary = format!("{verb}: {} of {n} inputs written to {}", n - failed.len(), out_dir.display());
    if failed.is_empty() {
        eprintln!("{summary}");
        Ok(())
    } else {
        bail!("{summary}; {} failed: {}", failed.len(), failed.join(", "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_names_never_collide() {
        let files: Vec<PathBuf> = ["d/a.png", "d/a.exr", "d/b.jpg", "e/c.nmat", "f/a.png"].iter().map(PathBuf::from).collect();
        assert_eq!(output_names(&files), ["a.png", "a.exr", "b", "c", "a.png-2"]);
    }

    #[test]
    fn folders_list_their_photos_sorted() {
        let d = tempfile::tempdir().unwrap();
        for n in ["b.PNG", "a.exr", "notes.txt", ".hidden.png", "IMG_0001.HEIC"] {
            std::fs::write(d.path().join(n), b"x").unwrap();
        }
        let got = list_inputs(&[d.path().to_path_buf()], PHOTO_EXTENSIONS).unwrap();
        let names: Vec<_> = got.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["IMG_0001.HEIC", "a.exr", "b.PNG"]);
        assert!(is_batch(&[d.path().to_path_buf()]));
        assert!(!is_batch(&[d.path().join("a.exr")]));
        let empty = tempfile::tempdir().unwrap();
        assert!(list_inputs(&[empty.path().to_path_buf()], PHOTO_EXTENSIONS).unwrap_err().to_string().contains("holds no input files"));
    }
}
