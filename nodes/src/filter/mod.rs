//! Image filters: colour conversion, linear and non-linear filtering.

pub mod border;
pub mod box_filter;
pub mod distance;
pub mod flow;
pub mod gaussian;
pub mod grayscale;
pub mod hit_or_miss;
pub mod morphology;
pub mod sobel;

#[cfg(test)]
mod test_support;
