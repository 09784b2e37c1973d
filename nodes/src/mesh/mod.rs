//! The `mesh` family: point clouds (downsampling, outliers, normals), registration (ICP),
//! primitive fitting — Open3D's and PCL's territory — and triangle-mesh processing on a
//! halfedge structure (normals, subdivision, simplification, metrics).

pub mod fit;
pub mod halfedge;
pub mod icp;
pub mod kdtree;
pub mod metrics;
pub mod normals;
pub mod pointcloud;
pub mod simplify;
pub mod smooth;
pub mod subdivide;
