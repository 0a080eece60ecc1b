//! flashmat: one flash photograph of a flat material in, a relightable
//! neural material out. See docs/ARCHITECTURE.md for the pipeline.

pub mod geometry;
pub mod image;
pub mod lpips;
pub mod spaces;
pub mod svbrdf;
pub mod data;
pub mod archive;
pub mod fsutil;
pub mod train;
pub mod viz;
pub mod cli;
