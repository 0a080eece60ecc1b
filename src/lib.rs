//! flashmat: one flash photograph of a flat material in, a relightable
//! neural material out. See docs/ARCHITECTURE.md for the pipeline.

pub mod geometry;
pub mod image;
pub mod model;
pub mod spaces;
pub mod svbrdf;
