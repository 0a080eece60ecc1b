//! Compiles src/torch_objects.cpp against the headers of the torch the
//! Python interpreter imports (maturin's PYO3_PYTHON, else scripts/env.sh's
//! PYTHON_SYS_EXECUTABLE) and links its libtorch_python; records that
//! torch's version (`FLASHMAT_BUILT_TORCH`) for the import-time check.
use std::path::PathBuf;
use std::process::Command;

fn python_says(code: &str) -> String {
    let python = std::env::var("PYO3_PYTHON").or_else(|_| std::env::var("PYTHON_SYS_EXECUTABLE")).unwrap_or_else(|_| "python3".into());
    let out = Command::new(&python).args(["-c", code]).output().unwrap_or_else(|e| panic!("cannot run {python}: {e}"));
    assert!(out.status.success(), "{python} -c '{code}' failed (is torch installed?): {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

fn main() {
    println!("cargo:rerun-if-changed=src/torch_objects.cpp");
    println!("cargo:rerun-if-env-changed=PYO3_PYTHON");
    println!("cargo:rerun-if-env-changed=PYTHON_SYS_EXECUTABLE");
    let info = python_says(
        "import torch, os, sysconfig; print(os.path.dirname(torch.__file__)); print(sysconfig.get_paths()['include']); print(int(torch._C._GLIBCXX_USE_CXX11_ABI)); print(torch.__version__)",
    );
    let lines: Vec<&str> = info.lines().collect();
    let [torch, python_include, abi, version] = lines[..] else { panic!("unexpected answer from Python: {info}") };
    let torch = PathBuf::from(torch);
    let include = torch.join("include");
    cc::Build::new()
        .cpp(true)
        .file("src/torch_objects.cpp")
        .include(&include)
        .include(include.join("torch/csrc/api/include"))
        .include(python_include)
        .flag("-std=c++17")
        .define("_GLIBCXX_USE_CXX11_ABI", abi)
        .warnings(false)
        .compile("flashmat_torch_objects");
    println!("cargo:rustc-link-search=native={}", torch.join("lib").display());
    println!("cargo:rustc-link-lib=dylib=torch_python");
    println!("cargo:rustc-env=FLASHMAT_BUILT_TORCH={version}");
}
