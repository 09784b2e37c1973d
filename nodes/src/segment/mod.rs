//! Segmentation: splitting images into regions (foreground/background, labels).

pub mod background;
pub mod graph_cut;
