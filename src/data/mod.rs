//! SVBRDF data: the procedural generator (the built-in dataset), loaders and
//! writers for on-disk layouts, and training samples rendered from them.

pub mod captures;
pub mod loaders;
pub mod procedural;
pub mod phone;
pub mod samples;
