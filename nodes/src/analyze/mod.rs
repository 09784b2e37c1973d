//! Measurements on values.

pub mod quality;
pub mod stats;
