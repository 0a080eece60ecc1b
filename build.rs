//! Embeds the libtorch directory as a run path so `target/*/flashmat` runs
//! without LD_LIBRARY_PATH, and keeps libtorch_cuda linked (the default
//! `--as-needed` would drop it because no symbol of it is referenced
//! directly, and CUDA would then be invisible at run time).
//!
//! Also compiles `src/dist/shim.cpp`, the C interface to libtorch's own
//! distributed engine (c10d), against the headers of the libtorch that tch
//! links: Gloo always (it lives in libtorch_cpu), NCCL where libtorch_cuda,
//! `nccl.h` and the CUDA runtime headers are found (`cfg(flashmat_nccl)`);
//! and `src/precision/shim.cpp`, the libtorch switches tch does not bind
//! (autocast on a device type in bf16, TF32).
use std::path::{Path, PathBuf};
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-env-changed=FLASHMAT_TORCH_LIB");
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    println!("cargo:rerun-if-env-changed=FLASHMAT_NO_NCCL");
    println!("cargo:rerun-if-env-changed=CUDA_HOME");
    println!("cargo:rerun-if-env-changed=FLASHMAT_CUDA_HEADERS");
    println!("cargo:rerun-if-changed=src/dist/shim.cpp");
    println!("cargo:rerun-if-changed=src/precision/shim.cpp");
    println!("cargo:rerun-if-changed=src/dist/gloo_decl");
    println!("cargo::rustc-check-cfg=cfg(flashmat_nccl)");
    let lib = torch_lib_dir();
    if let Some(dir) = &lib {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
    }
    let cuda_lib = lib.as_ref().map(|d| d.join("libtorch_cuda.so")).filter(|p| p.exists());
    if cuda_lib.is_some() {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
    }
    let Some(lib) = lib else {
        panic!("flashmat's build finds no libtorch: source scripts/env.sh (it sets FLASHMAT_TORCH_LIB), or set LIBTORCH");
    };
    compile_shim(&lib, cuda_lib.is_some());
}

/// The libtorch `lib` folder: FLASHMAT_TORCH_LIB (scripts/env.sh), LIBTORCH/lib,
/// or the torch package of the Python that torch-sys asks (LIBTORCH_USE_PYTORCH).
fn torch_lib_dir() -> Option<PathBuf> {
    if let Ok(dir) = std::env::var("FLASHMAT_TORCH_LIB") {
        return Some(PathBuf::from(dir));
    }
    if let Ok(dir) = std::env::var("LIBTORCH") {
        return Some(Path::new(&dir).join("lib"));
    }
    python_says("import torch,os; print(os.path.join(os.path.dirname(torch.__file__),'lib'))").map(PathBuf::from)
}

fn python_says(code: &str) -> Option<String> {
    let python = std::env::var("PYTHON_SYS_EXECUTABLE").unwrap_or_else(|_| "python3".into());
    let out = Command::new(python).args(["-c", code]).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

fn compile_shim(lib: &Path, has_cuda: bool) {
    let include = lib.parent().expect("libtorch lib folder has a parent").join("include");
    let abi = python_says("import torch; print(int(torch._C._GLIBCXX_USE_CXX11_ABI))").or_else(|| std::env::var("LIBTORCH_CXX11_ABI").ok()).unwrap_or_else(|| "1".into());
    let mut build = cc::Build::new();
    build
        .cpp(true)
        .file("src/dist/shim.cpp")
        .file("src/precision/shim.cpp")
        .include(&include)
        .include(include.join("torch/csrc/api/include"))
        .include("src/dist/gloo_decl")
        .flag("-std=c++17")
        .flag_if_supported("-Wno-unused-parameter")
        .flag_if_supported("-Wno-deprecated-declarations")
        .define("_GLIBCXX_USE_CXX11_ABI", abi.as_str())
        .define("USE_C10D_GLOO", None)
        .warnings(false);
    let nccl = has_cuda && std::env::var_os("FLASHMAT_NO_NCCL").is_none();
    let nccl_dirs = if nccl { nccl_include_dirs(lib) } else { None };
    if let Some(dirs) = &nccl_dirs {
        for d in dirs {
            build.include(d);
        }
        build.define("FLASHMAT_NCCL", None).define("USE_C10D_NCCL", None).define("USE_CUDA", None);
        println!("cargo:rustc-cfg=flashmat_nccl");
    } else if has_cuda {
        println!("cargo:warning=libtorch_cuda found, but not nccl.h and the CUDA toolkit headers (source scripts/env.sh, or set CUDA_HOME): distributed training is built for Gloo (CPU) only");
    }
    build.compile("flashmat_shims");
    // After the static library, so that the linker resolves its c10d
    // symbols in these (tch's own link lines may come before it).
    for l in ["torch_cpu", "c10"] {
        println!("cargo:rustc-link-lib=dylib={l}");
    }
    if nccl_dirs.is_some() {
        println!("cargo:rustc-link-lib=dylib=torch_cuda");
        println!("cargo:rustc-link-lib=dylib=c10_cuda");
    }
}

/// The folders holding `nccl.h`, `cuda_runtime_api.h` and the headers
/// those include: CUDA_HOME's, or the nvidia-* wheels beside the torch
/// package and the crt and CCCL headers scripts/env.sh fetches
/// (FLASHMAT_CUDA_HEADERS).
fn nccl_include_dirs(lib: &Path) -> Option<Vec<PathBuf>> {
    let site = lib.parent()?.parent()?.join("nvidia");
    let mut candidates = vec![site.join("nccl/include")];
    if let Ok(home) = std::env::var("CUDA_HOME") {
        candidates.push(Path::new(&home).join("include"));
    }
    if let Ok(dir) = std::env::var("FLASHMAT_CUDA_HEADERS") {
        candidates.push(Path::new(&dir).join("cccl"));
        candidates.push(PathBuf::from(dir));
    }
    for sub in ["cu13/include", "cuda_runtime/include", "cuda_nvcc/include", "cublas/include", "cusparse/include", "cusolver/include", "cuda_nvrtc/include", "curand/include", "cufft/include"] {
        candidates.push(site.join(sub));
    }
    candidates.push(PathBuf::from("/usr/local/cuda/include"));
    let dirs: Vec<PathBuf> = candidates.into_iter().filter(|d| d.is_dir()).collect();
    let has = |f: &str| dirs.iter().any(|d| d.join(f).exists());
    // cuda_runtime.h includes crt/host_config.h, which the CUDA toolkit has
    // and the runtime wheel lacks.
    (has("nccl.h") && has("cuda_runtime_api.h") && has("crt/host_config.h")).then_some(dirs)
}
