//! The library's layers (docs/ARCHITECTURE.md): no module imports one above
//! its layer, and no two modules import each other through any chain. Read
//! from the `crate::` and `super::` paths of every file under `src/` except
//! test code (`tests.rs` files and what follows `#[cfg(test)]`): a test may
//! use anything, the oracle of another module included.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Layer of each top-level module, highest first. A module may import its
/// own layer or any below it.
const LAYERS: &[(&str, u32)] = &[
    ("cli", 8),
    ("train", 7),
    ("eval", 7),
    ("viewer", 7),
    ("infer", 6),
    ("baselines", 6),
    ("fit", 6),
    ("capture", 6),
    ("model", 5),
    ("optim", 5),
    ("data", 4),
    ("archive", 4),
    ("viz", 4),
    ("io", 3),
    ("svbrdf", 3),
    ("geometry", 2),
    ("spaces", 2),
    ("image", 2),
    ("lpips", 2),
    ("limits", 1),
    ("device", 1),
    ("precision", 1),
    ("dist", 1),
    ("reference_paths", 1),
];

fn rank(top: &str) -> u32 {
    LAYERS.iter().find(|(m, _)| *m == top).map(|(_, r)| *r).unwrap_or_else(|| panic!("module '{top}' has no layer in tests/layers.rs"))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// `src/a/b.rs` and `src/a/b/mod.rs` -> ["a", "b"].
fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap().with_extension("");
    let mut parts: Vec<String> = rel.components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    parts
}

/// The code of a file without comments and test code.
fn library_code(file: &Path) -> String {
    if file.file_name().is_some_and(|n| n == "tests.rs") {
        return String::new();
    }
    let text = std::fs::read_to_string(file).unwrap();
    let text = text.split("#[cfg(test)]").next().unwrap();
    text.lines().map(|l| l.split("//").next().unwrap()).collect::<Vec<_>>().join("\n")
}

/// Every path that starts with `prefix` (`crate::` or `super::`), with
/// `use` groups (`x::{a, b::{c, d}}`) expanded.
fn paths_after(code: &str, prefix: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find(prefix) {
        let before = rest[..i].chars().last();
        rest = &rest[i + prefix.len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
            continue;
        }
        // The path's text: identifiers, `::` and balanced braces.
        let mut depth = 0;
        let end = rest
            .char_indices()
            .find(|&(_, c)| match c {
                '{' => {
                    depth += 1;
                    false
                }
                '}' if depth > 0 => {
                    depth -= 1;
                    false
                }
                c => depth == 0 && !(c.is_alphanumeric() || c == '_' || c == ':'),
            })
            .map(|(k, _)| k)
            .unwrap_or(rest.len());
        expand(&rest[..end], &mut Vec::new(), &mut out);
    }
    out
}

/// Expands `a::b::{c, d::{e}}` below `head` into full paths.
fn expand(text: &str, head: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
    let text = text.trim();
    match text.find('{') {
        None => {
            let mut p = head.clone();
            p.extend(text.split(" as ").next().unwrap().split("::").map(str::trim).filter(|s| !s.is_empty()).map(String::from));
            if p.len() > head.len() {
                out.push(p);
            }
        }
        Some(open) => {
            let n = head.len();
            head.extend(text[..open].split("::").map(str::trim).filter(|s| !s.is_empty()).map(String::from));
            let inner = &text[open + 1..text.rfind('}').unwrap_or(text.len())];
            // Split at the commas outside nested braces.
            let (mut depth, mut start) = (0, 0);
            for (k, c) in inner.char_indices().chain(std::iter::once((inner.len(), ','))) {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        expand(&inner[start..k], head, out);
                        start = k + 1;
                    }
                    _ => {}
                }
            }
            head.truncate(n);
        }
    }
}

/// The import graph between module files: an edge for every path into
/// another module that is neither an ancestor nor a descendant.
fn import_graph() -> BTreeMap<String, BTreeSet<String>> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let modules: BTreeMap<Vec<String>, PathBuf> = files
        .iter()
        .map(|f| (module_path(&src, f), f.clone()))
        .filter(|(m, _)| !(m.len() == 1 && (m[0] == "main" || m[0] == "lib")))
        .collect();
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (module, file) in &modules {
        if module[0] == "cli" {
            continue; // the binary's own module: it sees the library from outside
        }
        let code = library_code(file);
        let parent: Vec<String> = module[..module.len() - 1].to_vec();
        let mut targets: Vec<Vec<String>> = paths_after(&code, "crate::");
        targets.extend(paths_after(&code, "super::").into_iter().map(|p| parent.iter().cloned().chain(p).collect()));
        for t in targets {
            // The longest prefix that is a module file.
            let Some(k) = (1..=t.len()).rev().find(|&k| modules.contains_key(&t[..k])) else { continue };
            let target = &t[..k];
            if target.starts_with(module) || module.starts_with(target) {
                continue;
            }
            graph.entry(module.join("::")).or_default().insert(target.join("::"));
        }
    }
    graph
}

#[test]
fn no_module_imports_one_above_its_layer() {
    let graph = import_graph();
    let mut upward = Vec::new();
    for (from, tos) in &graph {
        let a = from.split("::").next().unwrap();
        for to in tos {
            let b = to.split("::").next().unwrap();
            if a != b && rank(b) > rank(a) {
                upward.push(format!("{from} -> {to}"));
            }
        }
    }
    assert!(upward.is_empty(), "imports that run up a layer: {upward:?}");
    // The checker sees imports: the model file format is below both users.
    assert!(graph["baselines"].contains("model::file"), "{:?}", graph["baselines"]);
}

#[test]
fn no_circle_of_imports() {
    let graph = import_graph();
    // Depth-first search for a back edge, reporting the circle.
    fn visit(n: &str, g: &BTreeMap<String, BTreeSet<String>>, state: &mut BTreeMap<String, u8>, stack: &mut Vec<String>) -> Option<Vec<String>> {
        state.insert(n.to_string(), 1);
        stack.push(n.to_string());
        for m in g.get(n).into_iter().flatten() {
            match state.get(m.as_str()).copied().unwrap_or(0) {
                1 => {
                    let i = stack.iter().position(|s| s == m).unwrap();
                    return Some(stack[i..].to_vec());
                }
                0 => {
                    if let Some(c) = visit(m, g, state, stack) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(n.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for n in graph.keys() {
        if state.get(n.as_str()).copied().unwrap_or(0) == 0 {
            let circle = visit(n, &graph, &mut state, &mut Vec::new());
            assert!(circle.is_none(), "a circle of imports: {circle:?}");
        }
    }
    // The cli is not part of the library.
    let lib = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/lib.rs")).unwrap();
    assert!(!lib.contains("mod cli"), "lib.rs exports cli");
}

#[test]
fn the_checker_finds_grouped_and_super_paths() {
    let code = "use crate::{geometry::Vec3, model::{file::{self, ModelFile}, Model}, spaces};\nuse super::nmat::X as Y;\nlet y = crate::io::read(x);";
    let path = |s: &str| s.split("::").map(String::from).collect::<Vec<_>>();
    assert_eq!(
        paths_after(code, "crate::"),
        ["geometry::Vec3", "model::file::self", "model::file::ModelFile", "model::Model", "spaces", "io::read"].map(path).to_vec()
    );
    assert_eq!(paths_after(code, "super::"), vec![path("nmat::X")]);
}
