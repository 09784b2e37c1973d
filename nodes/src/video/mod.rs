//! Video: motion between frames (feature tracking, optical flow, block matching).

pub mod gray;
pub mod klt;
pub mod synth;
