//! Embeds the libtorch directory as a run path so `target/*/flashmat` runs
//! without LD_LIBRARY_PATH, and keeps libtorch_cuda linked (the default
//! `--as-needed` would drop it because no symbol of it is referenced
//! directly, and CUDA would then be invisible at run time).
//!
//! Also compiles `src/precision/shim.cpp` (autocast's dtype and TF32, which
//! tch does not bind) against the headers of the libtorch tch links.
use std::path::PathBuf;
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-env-changed=FLASHMAT_TORCH_LIB");
    println!("cargo:rerun-if-changed=src/precision/shim.cpp");
    let lib = torch_lib_dir().expect("flashmat's build finds no libtorch: source scripts/env.sh (it sets FLASHMAT_TORCH_LIB)");
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    if lib.join("libtorch_cuda.so").exists() {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
    }
    let include = lib.parent().expect("libtorch's lib folder has a parent").join("include");
    let abi = python_says("import torch; print(int(torch._C._GLIBCXX_USE_CXX11_ABI))").unwrap_or_else(|| "1".into());
    cc::Build::new()
        .cpp(true)
        .file("src/precision/shim.cpp")
        .include(&include)
        .include(include.join("torch/csrc/api/include"))
        .flag("-std=c++17")
        .define("_GLIBCXX_USE_CXX11_ABI", abi.as_str())
        .warnings(false)
        .compile("flashmat_precision");
    println!("cargo:rustc-link-search=native={}", lib.display());
    println!("cargo:rustc-link-lib=dylib=torch_cpu");
    println!("cargo:rustc-link-lib=dylib=c10");
}

/// The libtorch `lib` folder: FLASHMAT_TORCH_LIB (scripts/env.sh), else the
/// torch package of the Python torch-sys asks (LIBTORCH_USE_PYTORCH).
fn torch_lib_dir() -> Option<PathBuf> {
    if let Ok(dir) = std::env::var("FLASHMAT_TORCH_LIB") {
        return Some(PathBuf::from(dir));
    }
    python_says("import torch,os; print(os.path.join(os.path.dirname(torch.__file__),'lib'))").map(PathBuf::from)
}

fn python_says(code: &str) -> Option<String> {
    let python = std::env::var("PYTHON_SYS_EXECUTABLE").unwrap_or_else(|_| "python3".into());
    let out = Command::new(python).args(["-c", code]).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}
