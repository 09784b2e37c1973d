//! The `learn` family: regression, classification and a sliding-window detector.

/// Registers the `learn` operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    let _ = registry;
    Ok(())
}
