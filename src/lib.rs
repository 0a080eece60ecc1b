//! flashmat: one flash photograph of a flat material in, a relightable
//! neural material out. See docs/ARCHITECTURE.md for the pipeline.

pub mod archive;
pub mod baselines;
pub mod cli;
pub mod data;
pub mod eval;
pub mod geometry;
pub mod image;
pub mod infer;
pub mod io;
pub mod lpips;
pub mod model;
pub mod spaces;
pub mod svbrdf;
pub mod train;
pub mod viz;
