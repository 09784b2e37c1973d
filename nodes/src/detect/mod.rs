//! Detectors: edges, corners, blobs.

pub mod canny;
pub mod chessboard;
pub mod gray;
pub mod marker;
pub mod mser;
pub mod qr;
