//! Rendering: scenes, a tiled rasterizer, a Whitted ray tracer and path tracer, acceleration
//! structures and ray casting over triangle meshes, textures, and the procedural meshes used
//! as fixtures.

pub mod bsdf;
pub mod bvh;
pub mod mesh_scene;
pub mod points;
pub mod primitives;
pub mod raster;
pub mod raycast;
pub mod scene;
pub mod texture;
pub mod trace;
