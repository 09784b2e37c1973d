//! Image filters: colour conversion, linear and non-linear filtering.

pub mod border;
pub mod box_filter;
pub mod gaussian;
pub mod grayscale;
pub mod histogram;
pub mod keying;
pub mod morphology;
pub mod sobel;
pub mod threshold;

#[cfg(test)]
mod test_support;
