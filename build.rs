//! Embeds the libtorch directory as a run path so `target/*/flashmat` runs
//! without LD_LIBRARY_PATH, and keeps libtorch_cuda linked (the default
//! `--as-needed` would drop it because no symbol of it is referenced
//! directly, and CUDA would then be invisible at run time).
fn main() {
    println!("cargo:rerun-if-env-changed=FLASHMAT_TORCH_LIB");
    if let Ok(dir) = std::env::var("FLASHMAT_TORCH_LIB") {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
        if std::path::Path::new(&dir).join("libtorch_cuda.so").exists() {
            println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
        }
    }
}
