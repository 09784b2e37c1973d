//! The `animate` family: keyframed parameters (the engine's timeline, [`ocellus_engine::curves`]),
//! skeletons, skinning and inverse kinematics, and mass–spring physics.
//!
//! Algorithms are plain functions in [`skeleton`], [`skinning`], [`ik`] and [`physics`]; the
//! operators are `animate.cloth` ([`cloth`]), `animate.pick` ([`pick`]), `animate.skin` and
//! `animate.ik` ([`chain`]), `animate.blend_shapes` ([`blend`]).

pub mod blend;
pub mod chain;
pub mod cloth;
pub mod ik;
pub mod physics;
pub mod pick;
pub mod skeleton;
pub mod skinning;
