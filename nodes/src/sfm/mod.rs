//! The `sfm` family: structure from motion (pair matching, tracks, incremental reconstruction).

pub mod incremental;
pub mod pairs;
pub mod tracks;
