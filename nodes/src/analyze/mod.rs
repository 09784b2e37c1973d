//! Measurements on values.

pub mod evaluate;
pub mod histogram;
pub mod quality;
pub mod stats;
