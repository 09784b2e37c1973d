//! Segmentation operators (family `segment`): connected components, region growing, marker
//! watershed, k-means colour clustering, background subtraction over frame sequences and binary
//! MRF segmentation by graph cut. Label images are gray f32 images holding exact integer labels
//! (0 = background), at most [`MAX_LABEL`].

pub mod background;
pub mod components;
pub mod graph_cut;
pub mod kmeans;
pub mod region_grow;
pub mod watershed;

use ocellus_engine::value::{Channels, Image};

/// Largest label a label image can hold: f32 represents every integer up to 2^24 exactly.
pub const MAX_LABEL: usize = 1 << 24;

/// A gray f32 label image from its samples (`width × height` of them).
pub(crate) fn label_image(width: usize, height: usize, labels: Vec<f32>) -> Result<Image, String> {
    Image::from_f32(width, height, Channels::Gray, labels).map_err(|e| e.to_string())
}
