//! Detectors: edges, corners, blobs.

pub mod canny;
pub mod corners;
pub mod fast;
pub mod hough;
pub mod template;
