//! Video: motion between frames (feature tracking, optical flow, block matching).

pub mod block_match;
pub mod codec;
pub mod dense_lk;
pub mod filters;
pub mod flow;
pub mod gray;
pub mod horn_schunck;
pub mod kalman;
pub mod klt;
pub mod klt_tracker;
pub mod particle;
pub mod synth;

/// Registers the block-based codec operators.
pub fn register_codec(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    codec::register(registry)
}
