//! Sources that synthesise or capture images.

pub mod moving;
pub mod moving_camera;
pub mod pattern;
pub mod render;
pub mod sequence;
