//! Detectors: edges, corners, blobs.

pub mod canny;
pub mod chessboard;
pub mod corners;
pub mod fast;
#[cfg(target_arch = "x86_64")]
mod fast_avx2;
pub mod gray;
pub mod hough;
pub mod hough_circles;
pub mod marker;
pub mod mser;
pub mod qr;
pub mod template;
