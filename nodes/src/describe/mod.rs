//! Feature description (family `describe`): scale spaces, keypoint detectors with
//! descriptors (SIFT, ORB), descriptors for given keypoints (BRIEF) and dense descriptors (HOG).

pub mod brief;
pub mod features;
pub mod hog;
pub mod orb;
pub mod scale_space;
pub mod sift;
