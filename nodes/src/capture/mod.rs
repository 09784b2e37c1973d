//! Sources that synthesise or capture images.

pub mod pattern;
pub mod sequence;
