//! Reading and writing files.

pub mod read_bal;
pub mod read_camera;
pub mod read_colmap;
pub mod read_correspondences;
pub mod read_image;
pub mod read_mesh;
pub mod read_point_cloud;
pub mod read_poses;
pub mod read_scene;
pub mod write_image;
pub mod write_mesh;
