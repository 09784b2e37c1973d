//! Measurements on values.

pub mod histogram;
pub mod quality;
pub mod stats;
