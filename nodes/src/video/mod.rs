//! Video: motion between frames (feature tracking, optical flow, block matching).

pub mod block_match;
pub mod gray;
pub mod klt;
pub mod synth;
