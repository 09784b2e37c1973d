//! The `texture` family: texture synthesis and sparse-coding denoising.

/// Registers the `texture` operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    let _ = registry;
    Ok(())
}
