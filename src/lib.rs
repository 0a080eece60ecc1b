//! flashmat: one flash photograph of a flat material in, a relightable
//! neural material out. See docs/ARCHITECTURE.md for the pipeline.

pub mod archive;
pub mod baselines;
pub mod capture;
pub mod data;
pub mod device;
pub mod dist;
pub mod eval;
pub mod fit;
pub mod geometry;
pub mod image;
pub mod infer;
pub mod io;
pub mod limits;
pub mod lpips;
pub mod model;
pub mod optim;
pub mod precision;
pub mod reference_paths;
pub mod spaces;
pub mod svbrdf;
pub mod train;
pub mod viewer;
pub mod viz;

/// Environment variable naming the folder that holds flashmat's bundled
/// files (`assets/`, `models/`): a binary built on one machine and run from
/// a copy of the repository elsewhere (a GPU job) sets it to that copy.
pub const ROOT_ENV: &str = "FLASHMAT_ROOT";

/// The repository root for bundled files: `$FLASHMAT_ROOT` when set, else
/// the crate folder this binary was built from.
pub fn bundled_root() -> std::path::PathBuf {
    match std::env::var_os(ROOT_ENV) {
        Some(d) if !d.is_empty() => d.into(),
        _ => env!("CARGO_MANIFEST_DIR").into(),
    }
}
