//! The `sfm` family: structure from motion (pair matching, tracks, incremental reconstruction)
//! and dense stereo.

pub mod depth;
pub mod incremental;
pub mod pairs;
pub mod stereo;
pub mod tracks;
