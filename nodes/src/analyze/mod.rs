//! Measurements on values.

pub mod histogram;
pub mod stats;
