//! Detectors: edges, corners, blobs.

pub mod canny;
pub mod chessboard;
pub mod corners;
pub mod fast;
pub mod gray;
pub mod hough;
pub mod hough_circles;
pub mod marker;
pub mod mser;
pub mod qr;
pub mod template;
