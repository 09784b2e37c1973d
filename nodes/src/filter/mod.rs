//! Image filters: colour conversion, linear and non-linear filtering.

pub mod border;
pub mod box_filter;
pub mod convolve;
pub mod derivatives;
pub mod gaussian;
pub mod grayscale;
pub mod morphology;
pub mod sobel;

#[cfg(test)]
mod test_support;
