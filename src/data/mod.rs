//! Training data sources.

pub mod procedural;
