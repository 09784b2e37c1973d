//! The `mesh` family: point clouds (downsampling, outliers, normals), registration (ICP),
//! primitive fitting, surface reconstruction (marching cubes, screened Poisson) — Open3D's
//! and PCL's territory — and triangle-mesh processing on a halfedge structure (normals,
//! tangents, subdivision, simplification, metrics, smoothing).

pub mod fit;
pub mod halfedge;
pub mod icp;
pub mod kdtree;
pub mod marching_cubes;
pub mod metrics;
pub mod normals;
pub mod pointcloud;
pub mod poisson;
pub mod simplify;
pub mod smooth;
pub mod subdivide;
pub mod tangents;
