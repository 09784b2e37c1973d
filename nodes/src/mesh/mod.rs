//! The `mesh` family: point clouds (downsampling, outliers, normals), registration (ICP),
//! primitive fitting, surface reconstruction (marching cubes, screened Poisson, TSDF fusion,
//! depth-map meshing, 2-D Delaunay, convex hulls) — Open3D's and PCL's territory — and
//! triangle-mesh processing on a halfedge structure (normals, tangents, subdivision,
//! simplification, metrics, smoothing, handle-based deformation).

pub mod deform;
pub mod delaunay;
pub mod depth_mesh;
pub mod fit;
pub mod halfedge;
pub mod hull;
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
pub mod tsdf;
