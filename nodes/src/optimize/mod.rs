//! Nonlinear optimization: sparse bundle adjustment (Levenberg–Marquardt with the Schur
//! complement), robust losses and generated test problems.

pub mod affine;
pub mod affine_init;
pub mod ba;
pub mod bundle_adjust;
pub mod bundle_general;
pub mod camera_model;
pub mod loss;
pub mod manifold;
pub mod nlls;
pub mod solve_report;
pub mod synthetic;
