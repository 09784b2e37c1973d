//! Image filters: colour conversion, linear and non-linear filtering.

#[cfg(target_arch = "x86_64")]
mod avx2;
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
pub mod histogram;
pub mod hit_or_miss;
pub mod integral;
pub mod keying;
pub mod kuwahara;
pub mod median;
pub mod morphology;
pub mod noise;
pub mod pyramid;
pub mod rank;
pub mod resize;
pub mod sobel;
pub mod threshold;
pub mod warp;

#[cfg(test)]
pub(crate) mod test_support;
