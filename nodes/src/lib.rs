//! # ocellus-nodes
//!
//! The built-in operators, one module per family. An operator's id is `family.name`. Algorithms
//! are plain functions with their own tests; each operator wrapper around one is thin.

pub mod analyze;
pub mod capture;
pub mod detect;
pub mod filter;
pub mod io;

use ocellus_engine::op::{Registry, RegistryError};

/// Registers every built-in operator.
pub fn register_builtins(registry: &mut Registry) -> Result<(), RegistryError> {
    registry.register::<capture::pattern::Pattern>()?;
    registry.register::<filter::grayscale::Grayscale>()?;
    registry.register::<filter::gaussian::Gaussian>()?;
    registry.register::<filter::box_filter::BoxFilter>()?;
    registry.register::<filter::sobel::Sobel>()?;
    registry.register::<filter::sobel::Scharr>()?;
    registry.register::<filter::morphology::Erode>()?;
    registry.register::<filter::morphology::Dilate>()?;
    registry.register::<filter::morphology::Morphology>()?;
    registry.register::<filter::resize::Resize>()?;
    registry.register::<filter::pyramid::PyrDown>()?;
    registry.register::<filter::pyramid::PyrUp>()?;
    registry.register::<filter::pyramid::Pyramid>()?;
    registry.register::<filter::pyramid::PyramidReconstruct>()?;
    registry.register::<filter::integral::Integral>()?;
    registry.register::<filter::warp::WarpAffine>()?;
    registry.register::<filter::warp::WarpPerspective>()?;
    registry.register::<detect::canny::Canny>()?;
    registry.register::<analyze::stats::Stats>()?;
    registry.register::<io::read_image::ReadImage>()?;
    registry.register::<io::write_image::WriteImage>()?;
    Ok(())
}

/// A registry holding every built-in operator.
pub fn builtin_registry() -> Result<Registry, RegistryError> {
    let mut registry = Registry::new();
    register_builtins(&mut registry)?;
    Ok(registry)
}
