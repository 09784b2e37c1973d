//! Feature description: keypoint detectors with descriptors, and dense descriptors.

pub mod brief;
pub mod hog;
pub mod orb;
