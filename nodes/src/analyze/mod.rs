//! Measurements on values.

pub mod depth_agreement;
pub mod disparity_error;
pub mod evaluate;
pub mod histogram;
pub mod match_accuracy;
pub mod quality;
pub mod reconstruction_error;
pub mod reconstruction_points;
pub mod running_stats;
pub mod stats;
pub mod track_error;
