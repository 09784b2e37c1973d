//! Geometry: robust estimation, minimal solvers, multi-view relations, triangulation, cameras and
//! calibration.
//!
//! Every estimator implements [`robust::Estimator`] (`MIN_SAMPLES`, `fit`, `residuals`), the way
//! COLMAP's estimators do, so one RANSAC family (RANSAC, MSAC, LO-RANSAC, PROSAC) drives them all.

pub mod decompose;
pub mod essential;
pub mod pnp;
pub mod pose_util;
pub mod robust;
pub mod servo;
pub mod triangulate;
