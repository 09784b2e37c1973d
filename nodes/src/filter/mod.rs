//! Image filters: colour conversion, linear and non-linear filtering.

pub mod border;
pub mod box_filter;
pub mod gaussian;
pub mod grayscale;
pub mod integral;
pub mod morphology;
pub mod pyramid;
pub mod resize;
pub mod sobel;
pub mod warp;

#[cfg(test)]
mod test_support;
