//! Geometry: robust estimation, minimal solvers, multi-view relations, triangulation, cameras and
//! calibration.
//!
//! Every estimator implements [`robust::Estimator`] (`MIN_SAMPLES`, `fit`, `residuals`), the way
//! COLMAP's estimators do, so one RANSAC family (RANSAC, MSAC, LO-RANSAC, PROSAC) drives them all.

pub mod calibrate;
pub mod camera;
pub mod decompose;
pub mod essential;
#[cfg(test)]
mod extremes;
pub mod fundamental;
pub mod homography;
pub mod lm;
pub mod pnp;
pub mod pose_util;
pub mod projection;
pub mod ransac;
pub mod rectify;
pub mod relative_pose;
pub mod robust;
pub mod servo;
pub mod shapes;
pub mod stitch;
pub mod synthetic;
pub mod transforms;
pub mod triangulate;
pub mod two_view;
