//! Rendering: acceleration structures and ray casting over triangle meshes, and the procedural
//! meshes used as fixtures.

pub mod bvh;
pub mod primitives;
pub mod raster;
pub mod raycast;
pub mod scene;
pub mod texture;
