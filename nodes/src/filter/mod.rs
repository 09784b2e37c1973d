//! Image filters: colour conversion, linear and non-linear filtering.

pub mod border;
pub mod gaussian;
pub mod grayscale;
