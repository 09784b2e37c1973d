//! The `sensor` family: camera raw capture, demosaicing, radiometric correction, event cameras.

/// Registers the `sensor` operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    let _ = registry;
    Ok(())
}
