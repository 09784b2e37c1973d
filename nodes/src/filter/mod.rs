//! Image filters: colour conversion, linear and non-linear filtering.

pub mod bilateral;
pub mod border;
pub mod box_filter;
pub mod color;
pub mod composite;
pub mod convert;
pub mod convolve;
pub mod derivatives;
pub mod distance;
pub mod flow;
pub mod frequency;
pub mod gaussian;
pub mod grayscale;
pub mod hit_or_miss;
pub mod kuwahara;
pub mod median;
pub mod morphology;
pub mod noise;
pub mod rank;
pub mod sobel;

#[cfg(test)]
pub(crate) mod test_support;
