//! The `sfm` family: structure from motion (pair matching, tracks, incremental reconstruction)
//! and dense stereo.

pub mod align;
pub mod dense;
pub mod depth;
pub mod incremental;
pub mod pair_lists;
pub mod pairs;
pub mod stereo;
pub mod tracks;
pub mod visual_hull;

/// Registers the visual-hull operators.
pub fn register_visual_hull(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    registry.register::<visual_hull::VisualHullOp>()?;
    Ok(())
}
