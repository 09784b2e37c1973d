//! Measurements on values.

pub mod stats;
