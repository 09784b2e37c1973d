//! Measurements on values.

#[cfg(test)]
mod decompose_tables;
pub mod depth_agreement;
pub mod disparity_error;
pub mod evaluate;
pub mod face_set;
pub mod fbp;
pub mod histogram;
pub mod homography_error;
pub mod match_accuracy;
pub mod pca;
pub mod phantom;
pub mod quality;
pub mod radon;
pub mod reconstruction_error;
pub mod reconstruction_points;
pub mod running_stats;
pub mod stats;
pub mod svd_compress;
pub mod track_error;

/// Registers the decomposition operators (PCA, SVD, k-means quantization, Radon/FBP).
pub fn register_decomposition(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    registry.register::<pca::Pca>()?;
    registry.register::<face_set::FaceSet>()?;
    registry.register::<svd_compress::SvdCompress>()?;
    registry.register::<phantom::Phantom>()?;
    registry.register::<radon::Radon>()?;
    registry.register::<fbp::Fbp>()?;
    Ok(())
}
