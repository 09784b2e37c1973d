//! The `mesh` family: point clouds (downsampling, outliers, normals), registration (ICP),
//! primitive fitting and surface reconstruction (marching cubes, screened Poisson) — Open3D's
//! and PCL's territory.

pub mod fit;
pub mod icp;
pub mod kdtree;
pub mod pointcloud;
pub mod marching_cubes;
pub mod poisson;
