//! Training and evaluation data: SVBRDF datasets on disk.

pub mod loaders;
