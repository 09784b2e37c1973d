//! Feature description: scale spaces, keypoint detectors with descriptors.

pub mod scale_space;
pub mod sift;
