//! Reading and writing files.

pub mod read_bal;
pub mod read_camera;
pub mod read_correspondences;
pub mod read_image;
pub mod write_image;
