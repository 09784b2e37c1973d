//! Rendering: acceleration structures and ray casting over triangle meshes, and the procedural
//! meshes used as fixtures.

pub mod bsdf;
pub mod bvh;
pub mod primitives;
pub mod raycast;
pub mod scene;
pub mod texture;
pub mod trace;
