//! Detectors: edges, corners, blobs.

pub mod canny;
