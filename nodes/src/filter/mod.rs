//! Image filters: colour conversion, linear and non-linear filtering.

pub mod border;
pub mod box_filter;
pub mod frequency;
pub mod gaussian;
pub mod grayscale;
pub mod morphology;
pub mod noise;
pub mod sobel;

#[cfg(test)]
mod test_support;
