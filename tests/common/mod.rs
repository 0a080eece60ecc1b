//! Helpers shared by the end-to-end tests that run the `flashmat` binary
//! (each test file uses a subset).
#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// Runs the binary with extra environment variables.
pub fn flashmat_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_flashmat"));
    cmd.args(args);
    for (k, v) in env {
        cmd.env(k, v);
    }
    cmd.output().expect("run flashmat")
}

pub fn flashmat(args: &[&str]) -> Output {
    flashmat_env(args, &[])
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Asserts success; returns stderr (progress and summary lines).
pub fn assert_ok(out: &Output) -> String {
    assert!(out.status.success(), "flashmat failed: {}", stderr(out));
    stderr(out)
}

/// Asserts failure with exit code 1 and exactly one stderr line, starting
/// `error: `, containing every `needle`.
pub fn assert_error(out: &Output, needles: &[&str]) {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(1), "expected exit code 1, stderr: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one error line, got: {err}");
    assert!(lines[0].starts_with("error: "), "{err}");
    for n in needles {
        assert!(lines[0].contains(n), "'{n}' not in: {err}");
    }
}

pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The names in a folder, sorted.
pub fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

pub fn no_temp_files(dir: &Path) {
    for name in files_in(dir) {
        assert!(!name.contains(".tmp-"), "temporary file left behind: {name}");
    }
}
