//! Sparse bundle adjustment: Levenberg–Marquardt over camera and point blocks with the Schur
//! complement on the points.
//!
//! Model (the BAL / COLMAP `RADIAL` camera): a camera maps a world point `X` to `P = R X + t`,
//! `(x, y) = (P.x/P.z, P.y/P.z)`, `r² = x² + y²`, and to the pixel
//! `f (1 + k1 r² + k2 r⁴) (x, y) + (cx, cy)`. There is no cheirality test: a point behind its
//! camera keeps its residual (BAL's cost). Each camera block has 9 degrees of freedom — a
//! rotation increment `ω` (`R ← exp([ω]×) R`, the SO(3) manifold), `t`, `f`, `k1`, `k2` — and
//! each point block 3; any degree of freedom can be held fixed (gauge, modes, unrefined
//! intrinsics). The principal point is constant.
//!
//! Method, as Ceres' trust-region minimizer with its defaults:
//! - Residuals `r` and analytic Jacobians per observation, optionally through a robust loss
//!   (Triggs' correction, see [`super::loss`]) and per-observation weights; cost `½ Σ ρ(‖r‖²)`.
//! - Levenberg–Marquardt step `(JᵀJ + D/Δ) δ = −Jᵀr` with `D` the diagonal of `JᵀJ` in Jacobi
//!   scaled columns (scales `1/(1 + ‖J_col‖)` from the first Jacobian, as Ceres), clamped to
//!   `[1e-6, 1e32]`; trust radius `Δ` starts at 1e4; gain ratio `ρ = actual / predicted` decrease;
//!   a step is accepted when `ρ > 1e-3`, then `Δ ← Δ / max(1/3, 1 − (2ρ − 1)³)` (Nielsen), else
//!   `Δ` shrinks by a doubling factor.
//! - The linear system is reduced to the cameras by eliminating the 3×3 point blocks (Schur
//!   complement `S = U − W V⁻¹ Wᵀ`). `S` is solved by a dense Cholesky (few cameras), by a
//!   sparse Cholesky (faer, AMD ordering; only camera pairs sharing a point have a block; the
//!   symbolic factorization is done once per solve) or by conjugate gradients on the implicit
//!   `S` with a block-Jacobi preconditioner (very large or dense reduced systems).
//! - Stops like Ceres: relative cost change of a trial step `≤ function_tolerance` (the trial is
//!   not applied), max gradient `≤ gradient_tolerance`, `‖δ‖ ≤ parameter_tolerance (‖x‖ +
//!   parameter_tolerance)`, the iteration limit, or a collapsed trust region.
//!
//! Determinism: every parallel loop runs over fixed-size chunks of observations, points or
//! cameras and writes disjoint outputs; sums over chunks are taken in chunk order, so results
//! are bit-identical for any thread count.
//!
//! References: Triggs, McLauchlan, Hartley & Fitzgibbon, "Bundle adjustment — a modern
//! synthesis" (1999); Agarwal, Snavely, Seitz & Szeliski, "Bundle adjustment in the large"
//! (ECCV 2010); Nielsen, "Damping parameter in Marquardt's method" (1999); Ceres Solver's
//! trust-region minimizer.

use std::time::Instant;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{
    SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, MatMut, Par, Side};
use rayon::prelude::*;

use super::loss::RobustLoss;
pub use super::solve_report::{IterationRecord, Termination};
use crate::geometry::camera::rodrigues;

/// Degrees of freedom of a camera block: `ω` (3), `t` (3), `f`, `k1`, `k2`.
pub const CAMERA_DOF: usize = 9;

/// Observations per parallel chunk.
const OBS_CHUNK: usize = 4096;
/// Points per parallel chunk.
const POINT_CHUNK: usize = 1024;

/// A camera of the problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaCamera {
    /// Row-major rotation `R` (camera from world).
    pub rotation: [f64; 9],
    /// Translation `t` (camera from world).
    pub translation: [f64; 3],
    /// `[f, k1, k2]`.
    pub intrinsics: [f64; 3],
    /// Principal point `(cx, cy)`, constant.
    pub principal_point: [f64; 2],
}

/// One observation: camera `camera` sees point `point` at pixel `xy`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaObservation {
    /// Camera index.
    pub camera: u32,
    /// Point index.
    pub point: u32,
    /// Observed pixel.
    pub xy: [f64; 2],
}

/// A bundle-adjustment problem.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BaProblem {
    /// Cameras.
    pub cameras: Vec<BaCamera>,
    /// World points.
    pub points: Vec<[f64; 3]>,
    /// Observations.
    pub observations: Vec<BaObservation>,
    /// Free degrees of freedom per camera, `[ω ω ω t t t f k1 k2]`; empty = all free.
    pub camera_free: Vec<[bool; CAMERA_DOF]>,
    /// Free points; empty = all free.
    pub point_free: Vec<bool>,
    /// Residual weight per observation (the residual is multiplied by it); empty = all 1.
    pub weights: Vec<f64>,
}

/// How the reduced camera system is solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearSolver {
    /// Dense Schur up to [`DENSE_MAX_CAMERAS`] cameras; beyond, sparse Schur while the reduced
    /// matrix and its Cholesky factor stay within [`SPARSE_MAX_FACTOR_ENTRIES`] entries and one
    /// factorization within [`SPARSE_MAX_FACTOR_FLOPS`] (the symbolic factorization is computed
    /// to decide); iterative Schur otherwise (very large or very dense reduced systems). The
    /// bounds come from a timing sweep on 2 cores (BENCHMARKS.md, "Bundle adjustment: choosing
    /// the linear solver"): sparse is as fast as dense at 10 cameras and faster from 20 on,
    /// even when every camera pair shares points; iterative is 2–10× faster than sparse on
    /// well-conditioned problems past ~1e10 factorization flops but 17× slower on Ladybug, so
    /// it takes over only where one factorization would cost seconds.
    Auto,
    /// Dense Cholesky of the reduced camera matrix.
    DenseSchur,
    /// Block-Jacobi preconditioned conjugate gradients on the implicit reduced camera matrix.
    IterativeSchur,
    /// Sparse Cholesky (faer, AMD ordering, sequential) of the reduced camera matrix over the
    /// free camera degrees of freedom: only camera pairs that share a point have a nonzero
    /// block. The symbolic factorization is computed once per solve.
    SparseSchur,
}

/// Most cameras [`LinearSolver::Auto`] solves densely.
pub const DENSE_MAX_CAMERAS: usize = 16;

/// Most stored entries of the reduced camera matrix's upper triangle, and of its sparse
/// Cholesky factor, for which [`LinearSolver::Auto`] picks the sparse solver (8 bytes each).
pub const SPARSE_MAX_FACTOR_ENTRIES: usize = 50_000_000;

/// Most floating-point operations (`Σ_j c_j²` over the factor's column counts) of one sparse
/// numeric factorization for which [`LinearSolver::Auto`] picks the sparse solver.
pub const SPARSE_MAX_FACTOR_FLOPS: f64 = 3e10;

/// Solver settings; the defaults are Ceres'.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaOptions {
    /// Most iterations, Ceres' count (the initial evaluation is iteration 0).
    pub max_iterations: usize,
    /// Stop when a trial step changes the cost by at most this fraction.
    pub function_tolerance: f64,
    /// Stop when the largest gradient component is at most this.
    pub gradient_tolerance: f64,
    /// Stop when `‖δ‖ ≤ parameter_tolerance · (‖x‖ + parameter_tolerance)`.
    pub parameter_tolerance: f64,
    /// Linear solver.
    pub linear_solver: LinearSolver,
    /// Robust loss on each observation's squared residual norm.
    pub loss: RobustLoss,
    /// Initial trust-region radius.
    pub initial_trust_region_radius: f64,
    /// Relative residual at which conjugate gradients stop.
    pub cg_tolerance: f64,
    /// Most conjugate-gradient iterations per step.
    pub cg_max_iterations: usize,
}

impl Default for BaOptions {
    fn default() -> BaOptions {
        BaOptions {
            max_iterations: 50,
            function_tolerance: 1e-6,
            gradient_tolerance: 1e-10,
            parameter_tolerance: 1e-8,
            linear_solver: LinearSolver::Auto,
            loss: RobustLoss::Trivial,
            initial_trust_region_radius: 1e4,
            cg_tolerance: 1e-3,
            cg_max_iterations: 500,
        }
    }
}

/// Result of [`solve`].
#[derive(Debug, Clone, PartialEq)]
pub struct BaSummary {
    /// Cost `½ Σ ρ(‖r‖²)` at the start.
    pub initial_cost: f64,
    /// Cost at the end.
    pub final_cost: f64,
    /// Ceres' iteration count (iteration 0 included, the terminating trial step not).
    pub iterations: usize,
    /// Accepted steps.
    pub successful_steps: usize,
    /// Rejected steps.
    pub unsuccessful_steps: usize,
    /// Why it stopped.
    pub termination: Termination,
    /// The linear solver used.
    pub linear_solver: LinearSolver,
    /// Per-iteration history (iteration 0 first).
    pub history: Vec<IterationRecord>,
    /// Seconds in the solver.
    pub time_s: f64,
}

// ------------------------------------------------------------------ model

/// Rotates, translates and projects `x`: the pixel and `P = R X + t`.
#[inline]
pub fn project(cam: &BaCamera, x: &[f64; 3]) -> [f64; 2] {
    let r = &cam.rotation;
    let p = [
        r[0] * x[0] + r[1] * x[1] + r[2] * x[2] + cam.translation[0],
        r[3] * x[0] + r[4] * x[1] + r[5] * x[2] + cam.translation[1],
        r[6] * x[0] + r[7] * x[1] + r[8] * x[2] + cam.translation[2],
    ];
    let iz = 1.0 / p[2];
    let (u, v) = (p[0] * iz, p[1] * iz);
    let r2 = u * u + v * v;
    let [f, k1, k2] = cam.intrinsics;
    let d = f * (1.0 + r2 * (k1 + k2 * r2));
    [
        d * u + cam.principal_point[0],
        d * v + cam.principal_point[1],
    ]
}

/// Residual (projection − observation) and its Jacobians: row-major 2×9 for the camera block
/// and 2×3 for the point block.
#[inline]
pub fn residual_jacobians(
    cam: &BaCamera,
    x: &[f64; 3],
    obs: &[f64; 2],
) -> ([f64; 2], [f64; 18], [f64; 6]) {
    let r = &cam.rotation;
    let rx = [
        r[0] * x[0] + r[1] * x[1] + r[2] * x[2],
        r[3] * x[0] + r[4] * x[1] + r[5] * x[2],
        r[6] * x[0] + r[7] * x[1] + r[8] * x[2],
    ];
    let p = [
        rx[0] + cam.translation[0],
        rx[1] + cam.translation[1],
        rx[2] + cam.translation[2],
    ];
    let iz = 1.0 / p[2];
    let (u, v) = (p[0] * iz, p[1] * iz);
    let r2 = u * u + v * v;
    let [f, k1, k2] = cam.intrinsics;
    let dist = 1.0 + r2 * (k1 + k2 * r2);
    let ddist = k1 + 2.0 * k2 * r2;
    let res = [
        f * dist * u + cam.principal_point[0] - obs[0],
        f * dist * v + cam.principal_point[1] - obs[1],
    ];
    // d(pixel)/d(u, v).
    let a00 = f * (dist + 2.0 * u * u * ddist);
    let a01 = f * 2.0 * u * v * ddist;
    let a11 = f * (dist + 2.0 * v * v * ddist);
    // d(pixel)/dP = d(pixel)/d(u,v) · d(u,v)/dP.
    let b = [
        a00 * iz,
        a01 * iz,
        -(a00 * u + a01 * v) * iz,
        a01 * iz,
        a11 * iz,
        -(a01 * u + a11 * v) * iz,
    ];
    let mut jc = [0.0; 18];
    let mut jp = [0.0; 6];
    for i in 0..2 {
        let (b0, b1, b2) = (b[3 * i], b[3 * i + 1], b[3 * i + 2]);
        // dP/dω = −[R X]×.
        jc[9 * i] = b1 * (-rx[2]) + b2 * rx[1];
        jc[9 * i + 1] = b0 * rx[2] + b2 * (-rx[0]);
        jc[9 * i + 2] = b0 * (-rx[1]) + b1 * rx[0];
        jc[9 * i + 3] = b0;
        jc[9 * i + 4] = b1;
        jc[9 * i + 5] = b2;
        let uv = if i == 0 { u } else { v };
        jc[9 * i + 6] = dist * uv;
        jc[9 * i + 7] = f * uv * r2;
        jc[9 * i + 8] = f * uv * r2 * r2;
        for k in 0..3 {
            jp[3 * i + k] = b0 * r[k] + b1 * r[3 + k] + b2 * r[6 + k];
        }
    }
    (res, jc, jp)
}

/// `exp([ω]×) R`.
fn rotate(rotation: &[f64; 9], w: &[f64]) -> [f64; 9] {
    let e = rodrigues([w[0], w[1], w[2]]);
    let mut out = [0.0; 9];
    for i in 0..3 {
        for j in 0..3 {
            out[3 * i + j] = (0..3).map(|k| e[(i, k)] * rotation[3 * k + j]).sum();
        }
    }
    out
}

// ------------------------------------------------------------------ problem layout

/// Observations sorted by point, with per-camera index lists.
struct Layout {
    /// Observations sorted by point (stable).
    obs: Vec<BaObservation>,
    /// Weight per sorted observation.
    weight: Vec<f64>,
    /// `point_start[j]..point_start[j + 1]`: observations of point `j`.
    point_start: Vec<usize>,
    /// Sorted observation indices per camera (ascending).
    camera_obs: Vec<Vec<u32>>,
    camera_free: Vec<[bool; CAMERA_DOF]>,
    point_free: Vec<bool>,
}

impl Layout {
    fn new(problem: &BaProblem) -> Layout {
        let n_points = problem.points.len();
        let mut order: Vec<usize> = (0..problem.observations.len()).collect();
        order.sort_by_key(|&i| problem.observations[i].point);
        let obs: Vec<BaObservation> = order.iter().map(|&i| problem.observations[i]).collect();
        let weight: Vec<f64> = order
            .iter()
            .map(|&i| problem.weights.get(i).copied().unwrap_or(1.0))
            .collect();
        let mut point_start = vec![0usize; n_points + 1];
        for o in &obs {
            point_start[o.point as usize + 1] += 1;
        }
        for j in 0..n_points {
            point_start[j + 1] += point_start[j];
        }
        let mut camera_obs = vec![Vec::new(); problem.cameras.len()];
        for (i, o) in obs.iter().enumerate() {
            camera_obs[o.camera as usize].push(i as u32);
        }
        let camera_free = if problem.camera_free.is_empty() {
            vec![[true; CAMERA_DOF]; problem.cameras.len()]
        } else {
            problem.camera_free.clone()
        };
        let point_free = if problem.point_free.is_empty() {
            vec![true; n_points]
        } else {
            problem.point_free.clone()
        };
        Layout {
            obs,
            weight,
            point_start,
            camera_obs,
            camera_free,
            point_free,
        }
    }
}

/// Checks indices, sizes and finiteness.
pub fn validate(problem: &BaProblem) -> Result<(), String> {
    let (nc, np) = (problem.cameras.len(), problem.points.len());
    if nc > u32::MAX as usize || np > u32::MAX as usize {
        return Err("too many cameras or points".into());
    }
    if !problem.camera_free.is_empty() && problem.camera_free.len() != nc {
        return Err(format!(
            "camera_free has {} entries for {nc} cameras",
            problem.camera_free.len()
        ));
    }
    if !problem.point_free.is_empty() && problem.point_free.len() != np {
        return Err(format!(
            "point_free has {} entries for {np} points",
            problem.point_free.len()
        ));
    }
    if !problem.weights.is_empty() && problem.weights.len() != problem.observations.len() {
        return Err(format!(
            "{} weights for {} observations",
            problem.weights.len(),
            problem.observations.len()
        ));
    }
    if let Some(w) = problem.weights.iter().find(|w| !w.is_finite() || **w < 0.0) {
        return Err(format!("observation weight {w} is not a finite number ≥ 0"));
    }
    for (i, c) in problem.cameras.iter().enumerate() {
        let finite = c
            .rotation
            .iter()
            .chain(&c.translation)
            .chain(&c.intrinsics)
            .chain(&c.principal_point)
            .all(|v| v.is_finite());
        if !finite {
            return Err(format!("camera {i} has a non-finite parameter"));
        }
    }
    if let Some(j) = problem
        .points
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(format!("point {j} is not finite"));
    }
    for (k, o) in problem.observations.iter().enumerate() {
        if o.camera as usize >= nc || o.point as usize >= np {
            return Err(format!(
                "observation {k} refers to camera {} / point {} of {nc} / {np}",
                o.camera, o.point
            ));
        }
        if !o.xy.iter().all(|v| v.is_finite()) {
            return Err(format!("observation {k} is not finite"));
        }
    }
    Ok(())
}

// ------------------------------------------------------------------ evaluation

/// `½ Σ ρ(w² ‖r‖²)` with chunked, ordered summation.
fn cost(layout: &Layout, cameras: &[BaCamera], points: &[[f64; 3]], loss: RobustLoss) -> f64 {
    let partial: Vec<f64> = layout
        .obs
        .par_chunks(OBS_CHUNK)
        .zip(layout.weight.par_chunks(OBS_CHUNK))
        .map(|(obs, weight)| {
            let mut sum = 0.0;
            for (o, w) in obs.iter().zip(weight) {
                let p = project(&cameras[o.camera as usize], &points[o.point as usize]);
                let (dx, dy) = ((p[0] - o.xy[0]) * w, (p[1] - o.xy[1]) * w);
                sum += loss.evaluate(dx * dx + dy * dy)[0];
            }
            sum
        })
        .collect();
    0.5 * partial.iter().sum::<f64>()
}

/// Plain squared residual norms `‖r‖²` per observation, in the problem's order.
pub fn squared_errors(problem: &BaProblem) -> Vec<f64> {
    problem
        .observations
        .par_iter()
        .with_min_len(OBS_CHUNK)
        .map(|o| {
            let p = project(
                &problem.cameras[o.camera as usize],
                &problem.points[o.point as usize],
            );
            let (dx, dy) = (p[0] - o.xy[0], p[1] - o.xy[1]);
            dx * dx + dy * dy
        })
        .collect()
}

/// The problem's cost `½ Σ ρ(w² ‖r‖²)`.
pub fn problem_cost(problem: &BaProblem, loss: RobustLoss) -> Result<f64, String> {
    validate(problem)?;
    let layout = Layout::new(problem);
    Ok(cost(&layout, &problem.cameras, &problem.points, loss))
}

/// Linearization at the current point: corrected residuals and Jacobians per (sorted)
/// observation, normal-equation blocks per camera and point.
struct Linearization {
    cost: f64,
    res: Vec<[f64; 2]>,
    jc: Vec<[f64; 18]>,
    jp: Vec<[f64; 6]>,
    /// `Σ Jcᵀ Jc` per camera, row-major 9×9.
    u: Vec<[f64; 81]>,
    /// `Jcᵀ r` per camera.
    gc: Vec<[f64; CAMERA_DOF]>,
    /// `Σ Jpᵀ Jp` per point, row-major 3×3.
    v: Vec<[f64; 9]>,
    /// `Jpᵀ r` per point.
    gp: Vec<[f64; 3]>,
}

fn linearize(
    layout: &Layout,
    cameras: &[BaCamera],
    points: &[[f64; 3]],
    loss: RobustLoss,
) -> Linearization {
    let n = layout.obs.len();
    let mut res = vec![[0.0; 2]; n];
    let mut jc = vec![[0.0; 18]; n];
    let mut jp = vec![[0.0; 6]; n];
    let partial: Vec<f64> = res
        .par_chunks_mut(OBS_CHUNK)
        .zip(jc.par_chunks_mut(OBS_CHUNK))
        .zip(jp.par_chunks_mut(OBS_CHUNK))
        .enumerate()
        .map(|(chunk, ((res, jc), jp))| {
            let base = chunk * OBS_CHUNK;
            let mut sum = 0.0;
            for k in 0..res.len() {
                let o = &layout.obs[base + k];
                let w = layout.weight[base + k];
                let (c, p) = (o.camera as usize, o.point as usize);
                let (mut r, mut a, mut b) = residual_jacobians(&cameras[c], &points[p], &o.xy);
                if w != 1.0 {
                    r.iter_mut().for_each(|v| *v *= w);
                    a.iter_mut().for_each(|v| *v *= w);
                    b.iter_mut().for_each(|v| *v *= w);
                }
                let s = r[0] * r[0] + r[1] * r[1];
                sum += loss.evaluate(s)[0];
                if loss != RobustLoss::Trivial {
                    let corr = loss.correction(s);
                    if corr.alpha_sq_norm != 0.0 {
                        // J ← J − (α/‖r‖²) r (rᵀ J).
                        let mut rta = [0.0; 9];
                        for (k, v) in rta.iter_mut().enumerate() {
                            *v = r[0] * a[k] + r[1] * a[9 + k];
                        }
                        let mut rtb = [0.0; 3];
                        for (k, v) in rtb.iter_mut().enumerate() {
                            *v = r[0] * b[k] + r[1] * b[3 + k];
                        }
                        for i in 0..2 {
                            for k in 0..9 {
                                a[9 * i + k] -= corr.alpha_sq_norm * r[i] * rta[k];
                            }
                            for k in 0..3 {
                                b[3 * i + k] -= corr.alpha_sq_norm * r[i] * rtb[k];
                            }
                        }
                    }
                    a.iter_mut().for_each(|v| *v *= corr.jacobian_scale);
                    b.iter_mut().for_each(|v| *v *= corr.jacobian_scale);
                    r.iter_mut().for_each(|v| *v *= corr.residual_scale);
                }
                let free = &layout.camera_free[c];
                for k in 0..CAMERA_DOF {
                    if !free[k] {
                        a[k] = 0.0;
                        a[9 + k] = 0.0;
                    }
                }
                if !layout.point_free[p] {
                    b = [0.0; 6];
                }
                res[k] = r;
                jc[k] = a;
                jp[k] = b;
            }
            sum
        })
        .collect();
    let cost = 0.5 * partial.iter().sum::<f64>();

    let n_cam = cameras.len();
    let mut u = vec![[0.0; 81]; n_cam];
    let mut gc = vec![[0.0; CAMERA_DOF]; n_cam];
    u.par_iter_mut()
        .zip(gc.par_iter_mut())
        .zip(layout.camera_obs.par_iter())
        .for_each(|((u, g), list)| {
            for &i in list {
                let i = i as usize;
                let (a, r) = (&jc[i], &res[i]);
                for p in 0..9 {
                    g[p] += a[p] * r[0] + a[9 + p] * r[1];
                    for q in 0..=p {
                        u[9 * p + q] += a[p] * a[q] + a[9 + p] * a[9 + q];
                    }
                }
            }
            for p in 0..9 {
                for q in 0..p {
                    u[9 * q + p] = u[9 * p + q];
                }
            }
        });
    let n_pts = points.len();
    let mut v = vec![[0.0; 9]; n_pts];
    let mut gp = vec![[0.0; 3]; n_pts];
    v.par_chunks_mut(POINT_CHUNK)
        .zip(gp.par_chunks_mut(POINT_CHUNK))
        .enumerate()
        .for_each(|(chunk, (v, gp))| {
            for k in 0..v.len() {
                let j = chunk * POINT_CHUNK + k;
                let mut vv = [0.0; 9];
                let mut g = [0.0; 3];
                for i in layout.point_start[j]..layout.point_start[j + 1] {
                    let (b, r) = (&jp[i], &res[i]);
                    for p in 0..3 {
                        g[p] += b[p] * r[0] + b[3 + p] * r[1];
                        for q in 0..3 {
                            vv[3 * p + q] += b[p] * b[q] + b[3 + p] * b[3 + q];
                        }
                    }
                }
                v[k] = vv;
                gp[k] = g;
            }
        });
    Linearization {
        cost,
        res,
        jc,
        jp,
        u,
        gc,
        v,
        gp,
    }
}

// ------------------------------------------------------------------ linear algebra

/// Dot product with four interleaved partial sums (vectorizes; fixed order).
#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut s = (acc[0] + acc[2]) + (acc[1] + acc[3]);
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// In-place Cholesky of a symmetric positive-definite n×n row-major matrix (lower triangle
/// read and written). False if not positive definite.
fn cholesky(a: &mut [f64], n: usize) -> bool {
    for i in 0..n {
        for j in 0..=i {
            let (ri, rj) = (i * n, j * n);
            let mut s = a[ri + j];
            let li = &a[ri..ri + j];
            let lj = &a[rj..rj + j];
            s -= dot(li, lj);
            if i == j {
                if s <= 0.0 || !s.is_finite() {
                    return false;
                }
                a[ri + i] = s.sqrt();
            } else {
                a[ri + j] = s / a[rj + j];
            }
        }
    }
    true
}

/// Solves `L Lᵀ x = b` in place with the factor from [`cholesky`].
fn cholesky_solve(l: &[f64], n: usize, b: &mut [f64]) {
    for i in 0..n {
        let s: f64 = (0..i).map(|k| l[i * n + k] * b[k]).sum();
        b[i] = (b[i] - s) / l[i * n + i];
    }
    for i in (0..n).rev() {
        let s: f64 = (i + 1..n).map(|k| l[k * n + i] * b[k]).sum();
        b[i] = (b[i] - s) / l[i * n + i];
    }
}

/// Forward substitution `L⁻¹ b` for a 3×3 lower factor.
#[inline]
fn lower3_solve(l: &[f64; 9], b: [f64; 3]) -> [f64; 3] {
    let y0 = b[0] / l[0];
    let y1 = (b[1] - l[3] * y0) / l[4];
    let y2 = (b[2] - l[6] * y0 - l[7] * y1) / l[8];
    [y0, y1, y2]
}

/// Back substitution `L⁻ᵀ b` for a 3×3 lower factor.
#[inline]
fn upper3_solve(l: &[f64; 9], b: [f64; 3]) -> [f64; 3] {
    let x2 = b[2] / l[8];
    let x1 = (b[1] - l[7] * x2) / l[4];
    let x0 = (b[0] - l[3] * x1 - l[6] * x2) / l[0];
    [x0, x1, x2]
}

/// The damping added to each diagonal entry: Ceres' LM diagonal in Jacobi-scaled columns.
#[inline]
fn damping(diag: f64, scale: f64, radius: f64) -> f64 {
    let s2 = scale * scale;
    (diag * s2).clamp(1e-6, 1e32) / s2 / radius
}

/// A computed step and its predicted decrease.
struct Step {
    dc: Vec<[f64; CAMERA_DOF]>,
    dp: Vec<[f64; 3]>,
    cg_iterations: usize,
}

/// Point elimination at a damping: per-point factor `L` of `V + D`, `q = L⁻¹ gp` and per
/// observation `G = W L⁻ᵀ` (row-major 9×3) with `W = Jcᵀ Jp`.
struct Elimination {
    l: Vec<[f64; 9]>,
    q: Vec<[f64; 3]>,
    g: Vec<[f64; 27]>,
    /// Damped camera diagonal blocks `U + D` (identity rows for fixed degrees of freedom).
    u: Vec<[f64; 81]>,
    /// Right-hand side `−gc + Σ G q`.
    rhs: Vec<[f64; CAMERA_DOF]>,
}

fn eliminate(
    layout: &Layout,
    lin: &Linearization,
    scale_c: &[[f64; CAMERA_DOF]],
    scale_p: &[[f64; 3]],
    radius: f64,
) -> Option<Elimination> {
    let n_pts = lin.v.len();
    let n_obs = lin.res.len();
    let mut l = vec![[0.0; 9]; n_pts];
    let mut q = vec![[0.0; 3]; n_pts];
    let mut g = vec![[0.0; 27]; n_obs];
    // Points: factor, q and G for their observations. G is written per point chunk; the chunk's
    // observations are a contiguous range, split off sequentially below.
    let mut g_parts: Vec<&mut [[f64; 27]]> = Vec::new();
    {
        let mut rest: &mut [[f64; 27]] = &mut g;
        let mut start = 0;
        for chunk_start in (0..n_pts).step_by(POINT_CHUNK) {
            let end = layout.point_start[(chunk_start + POINT_CHUNK).min(n_pts)];
            let (head, tail) = rest.split_at_mut(end - start);
            g_parts.push(head);
            rest = tail;
            start = end;
        }
    }
    let ok = l
        .par_chunks_mut(POINT_CHUNK)
        .zip(q.par_chunks_mut(POINT_CHUNK))
        .zip(g_parts.into_par_iter())
        .enumerate()
        .map(|(chunk, ((l, q), g))| {
            let first = chunk * POINT_CHUNK;
            let obs_base = layout.point_start[first];
            for k in 0..l.len() {
                let j = first + k;
                let mut m = lin.v[j];
                if layout.point_free[j] {
                    for d in 0..3 {
                        m[4 * d] += damping(m[4 * d], scale_p[j][d], radius);
                    }
                } else {
                    m = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
                }
                if !cholesky(&mut m, 3) {
                    return false;
                }
                l[k] = m;
                q[k] = lower3_solve(&m, lin.gp[j]);
                for i in layout.point_start[j]..layout.point_start[j + 1] {
                    let (a, b) = (&lin.jc[i], &lin.jp[i]);
                    let gi = &mut g[i - obs_base];
                    for p in 0..9 {
                        let w = [
                            a[p] * b[0] + a[9 + p] * b[3],
                            a[p] * b[1] + a[9 + p] * b[4],
                            a[p] * b[2] + a[9 + p] * b[5],
                        ];
                        let row = lower3_solve(&m, w);
                        gi[p] = row[0];
                        gi[9 + p] = row[1];
                        gi[18 + p] = row[2];
                    }
                }
            }
            true
        })
        .collect::<Vec<bool>>()
        .into_iter()
        .all(|x| x);
    if !ok {
        return None;
    }
    // Cameras: damped diagonal blocks and the reduced right-hand side.
    let mut u = lin.u.clone();
    let mut rhs = vec![[0.0; CAMERA_DOF]; u.len()];
    u.par_iter_mut()
        .zip(rhs.par_iter_mut())
        .enumerate()
        .for_each(|(c, (u, rhs))| {
            let free = &layout.camera_free[c];
            let mut b = lin.gc[c].map(|v| -v);
            for &i in &layout.camera_obs[c] {
                let i = i as usize;
                let j = layout.obs[i].point as usize;
                let (gi, qj) = (&g[i], &q[j]);
                for p in 0..9 {
                    b[p] += gi[p] * qj[0] + gi[9 + p] * qj[1] + gi[18 + p] * qj[2];
                }
            }
            for d in 0..9 {
                if free[d] {
                    u[10 * d] += damping(u[10 * d], scale_c[c][d], radius);
                } else {
                    for e in 0..9 {
                        u[9 * d + e] = 0.0;
                        u[9 * e + d] = 0.0;
                    }
                    u[10 * d] = 1.0;
                    b[d] = 0.0;
                }
            }
            *rhs = b;
        });
    Some(Elimination { l, q, g, u, rhs })
}

/// Dense reduced camera matrix (lower triangle, row-major n×n, n = 9·cameras).
fn dense_schur(layout: &Layout, el: &Elimination) -> Vec<f64> {
    let n_cam = el.u.len();
    let n = CAMERA_DOF * n_cam;
    let mut s = vec![0.0; n * n];
    s.par_chunks_mut(CAMERA_DOF * n)
        .enumerate()
        .for_each(|(a, rows)| {
            for p in 0..9 {
                for q in 0..9 {
                    rows[p * n + 9 * a + q] = el.u[a][9 * p + q];
                }
            }
            for &i in &layout.camera_obs[a] {
                let i = i as usize;
                let j = layout.obs[i].point as usize;
                let gi = &el.g[i];
                for k in layout.point_start[j]..layout.point_start[j + 1] {
                    let b = layout.obs[k].camera as usize;
                    if b > a {
                        continue;
                    }
                    // Rows of fixed degrees of freedom of G are zero: no masking needed.
                    let gk = &el.g[k];
                    let (g0, g1, g2) = (&gk[0..9], &gk[9..18], &gk[18..27]);
                    for p in 0..9 {
                        let (x0, x1, x2) = (gi[p], gi[9 + p], gi[18 + p]);
                        let row = &mut rows[p * n + 9 * b..p * n + 9 * b + 9];
                        for q in 0..9 {
                            row[q] -= x0 * g0[q] + x1 * g1[q] + x2 * g2[q];
                        }
                    }
                }
            }
        });
    s
}

// ------------------------------------------------------------------ sparse Schur

/// A camera without a slot in the current neighbour list of [`sparse_schur_solve`].
const NO_SLOT: u32 = u32::MAX;

/// Whether camera `c` has at least one free degree of freedom.
#[inline]
fn camera_has_free_dof(layout: &Layout, c: usize) -> bool {
    layout.camera_free[c].iter().any(|&f| f)
}

/// Per camera `a` with a free degree of freedom: the cameras `b < a` with a free degree of
/// freedom that share a free point with `a`, ascending, then `a` itself; empty for cameras
/// without free degrees of freedom. These are the nonzero 9×9 blocks of the upper triangle of
/// the reduced camera matrix (column block `a`); fixed points do not couple cameras (their `G`
/// is zero).
fn camera_neighbours(layout: &Layout) -> Vec<Vec<u32>> {
    let n_cam = layout.camera_obs.len();
    (0..n_cam)
        .into_par_iter()
        .map_init(
            || vec![NO_SLOT; n_cam],
            |mark, a| {
                if !camera_has_free_dof(layout, a) {
                    return Vec::new();
                }
                let mut list = Vec::new();
                for &i in &layout.camera_obs[a] {
                    let j = layout.obs[i as usize].point as usize;
                    if !layout.point_free[j] {
                        continue;
                    }
                    for k in layout.point_start[j]..layout.point_start[j + 1] {
                        let b = layout.obs[k].camera;
                        // `mark[b] == a` means "already listed for a"; each a is visited once.
                        if (b as usize) < a
                            && mark[b as usize] != a as u32
                            && camera_has_free_dof(layout, b as usize)
                        {
                            mark[b as usize] = a as u32;
                            list.push(b);
                        }
                    }
                }
                list.sort_unstable();
                list.push(a as u32);
                list
            },
        )
        .collect()
}

/// Sparsity pattern of the reduced camera matrix over the free camera degrees of freedom (the
/// upper triangle in compressed sparse columns) and its symbolic Cholesky factorization with
/// an AMD fill-reducing ordering. The pattern depends only on which cameras share a point, so
/// it is computed once per solve and every iteration reuses it for the numeric factorization.
struct SparseSchurPattern {
    /// Order of the reduced system: the number of free camera degrees of freedom.
    n: usize,
    /// [`camera_neighbours`].
    neighbours: Vec<Vec<u32>>,
    /// `value_start[a]..value_start[a + 1]`: the entries of camera `a`'s columns.
    value_start: Vec<usize>,
    /// Upper-triangle pattern (rows ascending in each column).
    matrix: SymbolicSparseColMat<usize>,
    /// Symbolic factorization of `matrix`.
    symbolic: SymbolicCholesky<usize>,
}

/// Free degrees of freedom of a camera, ascending.
fn free_dofs(free: &[bool; CAMERA_DOF]) -> impl Iterator<Item = usize> + Clone + '_ {
    (0..CAMERA_DOF).filter(|&d| free[d])
}

/// Number of stored upper-triangle entries of the reduced camera matrix for `neighbours`.
fn sparse_schur_entries(layout: &Layout, neighbours: &[Vec<u32>]) -> usize {
    neighbours
        .iter()
        .enumerate()
        .map(|(a, list)| {
            let fa = free_dofs(&layout.camera_free[a]).count();
            let off: usize = list
                .iter()
                .filter(|&&b| b as usize != a)
                .map(|&b| free_dofs(&layout.camera_free[b as usize]).count())
                .sum();
            if list.is_empty() {
                0
            } else {
                fa * off + fa * (fa + 1) / 2
            }
        })
        .sum()
}

impl SparseSchurPattern {
    /// The pattern for `neighbours` (from [`camera_neighbours`]) and its symbolic
    /// factorization; an error if faer runs out of memory or index range.
    fn new(layout: &Layout, neighbours: Vec<Vec<u32>>) -> Result<SparseSchurPattern, String> {
        let n_cam = layout.camera_obs.len();
        // Row/column of each free degree of freedom, cameras in order.
        let mut index = vec![[usize::MAX; CAMERA_DOF]; n_cam];
        let mut n = 0;
        for (c, idx) in index.iter_mut().enumerate() {
            for d in free_dofs(&layout.camera_free[c]) {
                idx[d] = n;
                n += 1;
            }
        }
        let entries = sparse_schur_entries(layout, &neighbours);
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(entries);
        let mut value_start = Vec::with_capacity(n_cam + 1);
        col_ptr.push(0);
        for (a, list) in neighbours.iter().enumerate() {
            value_start.push(row_idx.len());
            for p in free_dofs(&layout.camera_free[a]) {
                for &b in list {
                    let b = b as usize;
                    for q in free_dofs(&layout.camera_free[b]) {
                        if b == a && q > p {
                            break;
                        }
                        row_idx.push(index[b][q]);
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        value_start.push(row_idx.len());
        let matrix = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        let symbolic = factorize_symbolic_cholesky(
            matrix.as_ref(),
            Side::Upper,
            SymmetricOrdering::Amd,
            Default::default(),
        )
        .map_err(|e| format!("sparse Schur: symbolic Cholesky failed: {e:?}"))?;
        Ok(SparseSchurPattern {
            n,
            neighbours,
            value_start,
            matrix,
            symbolic,
        })
    }

    /// Stored entries of the Cholesky factor.
    fn factor_entries(&self) -> usize {
        self.symbolic.len_val()
    }

    /// Floating-point operations of one numeric factorization, `Σ_j c_j²` over the factor's
    /// column counts `c_j` (an estimate within a small constant factor).
    fn factor_flops(&self) -> f64 {
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(s) => s
                .col_ptr()
                .windows(2)
                .map(|w| {
                    let c = (w[1] - w[0]) as f64;
                    c * c
                })
                .sum(),
            SymbolicCholeskyRaw::Supernodal(s) => {
                let (begin, end) = (s.supernode_begin(), s.supernode_end());
                let rows = s.col_ptr_for_row_idx();
                (0..s.n_supernodes())
                    .map(|k| {
                        let below = (rows[k + 1] - rows[k]) as f64;
                        // Σ_{c=1..width} (c + below)².
                        (1..=end[k] - begin[k])
                            .map(|c| {
                                let h = c as f64 + below;
                                h * h
                            })
                            .sum::<f64>()
                    })
                    .sum()
            }
        }
    }
}

/// Solves the reduced camera system with a sparse Cholesky (faer, sequential) of `S` over the
/// free camera degrees of freedom; fixed ones get a zero step, as in the dense path. `None`
/// when `S` is not numerically positive definite (or the solution is not finite).
fn sparse_schur_solve(
    layout: &Layout,
    el: &Elimination,
    pattern: &SparseSchurPattern,
) -> Option<Vec<[f64; CAMERA_DOF]>> {
    let n_cam = el.u.len();
    let n = pattern.n;
    let mut dc = vec![[0.0; CAMERA_DOF]; n_cam];
    if n == 0 {
        return Some(dc);
    }
    let mut values = vec![0.0; pattern.value_start[n_cam]];
    let mut parts: Vec<&mut [f64]> = Vec::with_capacity(n_cam);
    {
        let mut rest: &mut [f64] = &mut values;
        for a in 0..n_cam {
            let (head, tail) =
                rest.split_at_mut(pattern.value_start[a + 1] - pattern.value_start[a]);
            parts.push(head);
            rest = tail;
        }
    }
    // Each camera's columns: the same 9×9 block sums as `dense_schur`, in the same order, then
    // scattered to the free entries.
    parts.into_par_iter().enumerate().for_each_init(
        || vec![NO_SLOT; n_cam],
        |slot, (a, vals)| {
            let list = &pattern.neighbours[a];
            if list.is_empty() {
                return;
            }
            for (k, &b) in list.iter().enumerate() {
                slot[b as usize] = k as u32;
            }
            let mut blocks = vec![[0.0; 81]; list.len()];
            blocks[list.len() - 1] = el.u[a];
            for &i in &layout.camera_obs[a] {
                let i = i as usize;
                let j = layout.obs[i].point as usize;
                if !layout.point_free[j] {
                    continue;
                }
                let gi = &el.g[i];
                for k in layout.point_start[j]..layout.point_start[j + 1] {
                    let b = layout.obs[k].camera as usize;
                    if b > a || slot[b] == NO_SLOT {
                        continue;
                    }
                    let block = &mut blocks[slot[b] as usize];
                    let gk = &el.g[k];
                    let (g0, g1, g2) = (&gk[0..9], &gk[9..18], &gk[18..27]);
                    for p in 0..9 {
                        let (x0, x1, x2) = (gi[p], gi[9 + p], gi[18 + p]);
                        let row = &mut block[9 * p..9 * p + 9];
                        for q in 0..9 {
                            row[q] -= x0 * g0[q] + x1 * g1[q] + x2 * g2[q];
                        }
                    }
                }
            }
            let mut pos = 0;
            for p in free_dofs(&layout.camera_free[a]) {
                for (k, &b) in list.iter().enumerate() {
                    let b = b as usize;
                    for q in free_dofs(&layout.camera_free[b]) {
                        if b == a && q > p {
                            break;
                        }
                        vals[pos] = blocks[k][9 * p + q];
                        pos += 1;
                    }
                }
            }
            for &b in list {
                slot[b as usize] = NO_SLOT;
            }
        },
    );
    let symbolic = &pattern.symbolic;
    let mut factor = vec![0.0; symbolic.len_val()];
    let scratch = symbolic
        .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
        .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq));
    let mut memory = MemBuffer::try_new(scratch).ok()?;
    let stack = MemStack::new(&mut memory);
    let s = SparseColMatRef::new(pattern.matrix.as_ref(), &values);
    let llt = symbolic
        .factorize_numeric_llt::<f64>(
            &mut factor,
            s,
            Side::Upper,
            Default::default(),
            Par::Seq,
            stack,
            Default::default(),
        )
        .ok()?;
    let mut b: Vec<f64> = el
        .rhs
        .iter()
        .zip(&layout.camera_free)
        .flat_map(|(r, free)| free_dofs(free).map(move |d| r[d]))
        .collect();
    llt.solve_in_place_with_conj(
        Conj::No,
        MatMut::from_column_major_slice_mut(&mut b, n, 1),
        Par::Seq,
        stack,
    );
    if !b.iter().all(|v| v.is_finite()) {
        return None;
    }
    let mut next = b.iter();
    for (d, free) in dc.iter_mut().zip(&layout.camera_free) {
        for k in free_dofs(free) {
            d[k] = *next.next()?;
        }
    }
    Some(dc)
}

/// `y = S x` for the implicit reduced camera matrix.
fn schur_apply(
    layout: &Layout,
    el: &Elimination,
    x: &[[f64; CAMERA_DOF]],
    z: &mut [[f64; 3]],
    y: &mut [[f64; CAMERA_DOF]],
) {
    z.par_chunks_mut(POINT_CHUNK)
        .enumerate()
        .for_each(|(chunk, z)| {
            for (k, zj) in z.iter_mut().enumerate() {
                let j = chunk * POINT_CHUNK + k;
                let mut acc = [0.0; 3];
                for i in layout.point_start[j]..layout.point_start[j + 1] {
                    let c = layout.obs[i].camera as usize;
                    let (gi, xc) = (&el.g[i], &x[c]);
                    for p in 0..9 {
                        acc[0] += gi[p] * xc[p];
                        acc[1] += gi[9 + p] * xc[p];
                        acc[2] += gi[18 + p] * xc[p];
                    }
                }
                *zj = acc;
            }
        });
    y.par_iter_mut().enumerate().for_each(|(c, yc)| {
        let u = &el.u[c];
        let xc = &x[c];
        let mut acc = [0.0; 9];
        for p in 0..9 {
            acc[p] = (0..9).map(|q| u[9 * p + q] * xc[q]).sum();
        }
        for &i in &layout.camera_obs[c] {
            let i = i as usize;
            let j = layout.obs[i].point as usize;
            let (gi, zj) = (&el.g[i], &z[j]);
            for p in 0..9 {
                acc[p] -= gi[p] * zj[0] + gi[9 + p] * zj[1] + gi[18 + p] * zj[2];
            }
        }
        *yc = acc;
    });
}

fn dot9(a: &[[f64; CAMERA_DOF]], b: &[[f64; CAMERA_DOF]]) -> f64 {
    let partial: Vec<f64> = a
        .par_chunks(POINT_CHUNK)
        .zip(b.par_chunks(POINT_CHUNK))
        .map(|(a, b)| {
            a.iter()
                .zip(b)
                .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>())
                .sum::<f64>()
        })
        .collect();
    partial.iter().sum()
}

/// Block-Jacobi preconditioned conjugate gradients on `S x = rhs`; `None` if a preconditioner
/// block is not positive definite.
fn iterative_schur(
    layout: &Layout,
    el: &Elimination,
    tolerance: f64,
    max_iterations: usize,
) -> Option<(Vec<[f64; CAMERA_DOF]>, usize)> {
    let n_cam = el.u.len();
    // Preconditioner blocks: U_aa + D − Σ G Gᵀ over camera a's observations.
    let blocks: Vec<Option<[f64; 81]>> = (0..n_cam)
        .into_par_iter()
        .map(|a| {
            let mut m = el.u[a];
            let free = &layout.camera_free[a];
            for &i in &layout.camera_obs[a] {
                let gi = &el.g[i as usize];
                for p in 0..9 {
                    for q in 0..=p {
                        if free[p] && free[q] {
                            m[9 * p + q] -=
                                gi[p] * gi[q] + gi[9 + p] * gi[9 + q] + gi[18 + p] * gi[18 + q];
                        }
                    }
                }
            }
            cholesky(&mut m, 9).then_some(m)
        })
        .collect();
    let blocks: Vec<[f64; 81]> = blocks.into_iter().collect::<Option<Vec<_>>>()?;
    let precondition = |r: &[[f64; CAMERA_DOF]], out: &mut [[f64; CAMERA_DOF]]| {
        out.par_iter_mut().enumerate().for_each(|(c, o)| {
            let mut v = r[c];
            cholesky_solve(&blocks[c], 9, &mut v);
            *o = v;
        });
    };
    let b = &el.rhs;
    let b_norm = dot9(b, b).sqrt();
    let mut x = vec![[0.0; CAMERA_DOF]; n_cam];
    if b_norm == 0.0 {
        return Some((x, 0));
    }
    let mut r = b.clone();
    let mut zp = vec![[0.0; CAMERA_DOF]; n_cam];
    precondition(&r, &mut zp);
    let mut p = zp.clone();
    let mut rz = dot9(&r, &zp);
    let mut sp = vec![[0.0; CAMERA_DOF]; n_cam];
    let mut zpts = vec![[0.0; 3]; el.l.len()];
    let mut iterations = 0;
    while iterations < max_iterations {
        iterations += 1;
        schur_apply(layout, el, &p, &mut zpts, &mut sp);
        let psp = dot9(&p, &sp);
        if psp <= 0.0 || !psp.is_finite() {
            break;
        }
        let alpha = rz / psp;
        x.par_iter_mut()
            .zip(r.par_iter_mut())
            .zip(p.par_iter().zip(sp.par_iter()))
            .for_each(|((x, r), (p, sp))| {
                for k in 0..9 {
                    x[k] += alpha * p[k];
                    r[k] -= alpha * sp[k];
                }
            });
        if dot9(&r, &r).sqrt() <= tolerance * b_norm {
            break;
        }
        precondition(&r, &mut zp);
        let rz_new = dot9(&r, &zp);
        let beta = rz_new / rz;
        rz = rz_new;
        p.par_iter_mut().zip(zp.par_iter()).for_each(|(p, z)| {
            for k in 0..9 {
                p[k] = z[k] + beta * p[k];
            }
        });
    }
    Some((x, iterations))
}

/// The reduced camera system's solver as resolved for a solve.
enum ReducedSolver {
    /// [`LinearSolver::DenseSchur`].
    Dense,
    /// [`LinearSolver::SparseSchur`] with the solve's pattern.
    Sparse(Box<SparseSchurPattern>),
    /// [`LinearSolver::IterativeSchur`].
    Iterative,
}

impl ReducedSolver {
    /// The public name.
    fn kind(&self) -> LinearSolver {
        match self {
            ReducedSolver::Dense => LinearSolver::DenseSchur,
            ReducedSolver::Sparse(_) => LinearSolver::SparseSchur,
            ReducedSolver::Iterative => LinearSolver::IterativeSchur,
        }
    }

    /// Resolves `requested` for the problem ([`LinearSolver::Auto`]'s rule is documented
    /// there).
    fn resolve(layout: &Layout, requested: LinearSolver) -> Result<ReducedSolver, String> {
        let n_cam = layout.camera_obs.len();
        Ok(match requested {
            LinearSolver::DenseSchur => ReducedSolver::Dense,
            LinearSolver::IterativeSchur => ReducedSolver::Iterative,
            LinearSolver::SparseSchur => ReducedSolver::Sparse(Box::new(SparseSchurPattern::new(
                layout,
                camera_neighbours(layout),
            )?)),
            LinearSolver::Auto if n_cam <= DENSE_MAX_CAMERAS => ReducedSolver::Dense,
            LinearSolver::Auto => {
                let neighbours = camera_neighbours(layout);
                if sparse_schur_entries(layout, &neighbours) > SPARSE_MAX_FACTOR_ENTRIES {
                    ReducedSolver::Iterative
                } else {
                    match SparseSchurPattern::new(layout, neighbours) {
                        Ok(pattern)
                            if pattern.factor_entries() <= SPARSE_MAX_FACTOR_ENTRIES
                                && pattern.factor_flops() <= SPARSE_MAX_FACTOR_FLOPS =>
                        {
                            ReducedSolver::Sparse(Box::new(pattern))
                        }
                        _ => ReducedSolver::Iterative,
                    }
                }
            }
        })
    }
}

fn compute_step(
    layout: &Layout,
    lin: &Linearization,
    scale_c: &[[f64; CAMERA_DOF]],
    scale_p: &[[f64; 3]],
    radius: f64,
    solver: &ReducedSolver,
    options: &BaOptions,
) -> Option<Step> {
    let el = eliminate(layout, lin, scale_c, scale_p, radius)?;
    let n_cam = el.u.len();
    let (dc, cg_iterations) = match solver {
        ReducedSolver::Iterative => {
            iterative_schur(layout, &el, options.cg_tolerance, options.cg_max_iterations)?
        }
        ReducedSolver::Sparse(pattern) => (sparse_schur_solve(layout, &el, pattern)?, 0),
        ReducedSolver::Dense => {
            let n = CAMERA_DOF * n_cam;
            let mut s = dense_schur(layout, &el);
            if !cholesky(&mut s, n) {
                return None;
            }
            let mut b: Vec<f64> = el.rhs.iter().flatten().copied().collect();
            cholesky_solve(&s, n, &mut b);
            let dc = b
                .chunks_exact(CAMERA_DOF)
                .map(|c| {
                    let mut a = [0.0; CAMERA_DOF];
                    a.copy_from_slice(c);
                    a
                })
                .collect();
            (dc, 0)
        }
    };
    // Back-substitution: δp = L⁻ᵀ (−q − Σ Gᵀ δc).
    let mut dp = vec![[0.0; 3]; el.l.len()];
    dp.par_chunks_mut(POINT_CHUNK)
        .enumerate()
        .for_each(|(chunk, dp)| {
            for (k, d) in dp.iter_mut().enumerate() {
                let j = chunk * POINT_CHUNK + k;
                let mut y = el.q[j].map(|v| -v);
                for i in layout.point_start[j]..layout.point_start[j + 1] {
                    let c = layout.obs[i].camera as usize;
                    let (gi, x): (&[f64; 27], &[f64; CAMERA_DOF]) = (&el.g[i], &dc[c]);
                    for p in 0..9 {
                        y[0] -= gi[p] * x[p];
                        y[1] -= gi[9 + p] * x[p];
                        y[2] -= gi[18 + p] * x[p];
                    }
                }
                *d = if layout.point_free[j] {
                    upper3_solve(&el.l[j], y)
                } else {
                    [0.0; 3]
                };
            }
        });
    Some(Step {
        dc,
        dp,
        cg_iterations,
    })
}

/// Predicted decrease `−(gᵀδ + ½‖Jδ‖²)`.
fn model_decrease(layout: &Layout, lin: &Linearization, step: &Step) -> f64 {
    let partial: Vec<f64> = (0..lin.res.len().div_ceil(OBS_CHUNK))
        .into_par_iter()
        .map(|chunk| {
            let end = ((chunk + 1) * OBS_CHUNK).min(lin.res.len());
            let mut sum = 0.0;
            for i in chunk * OBS_CHUNK..end {
                let o = &layout.obs[i];
                let (dc, dp) = (&step.dc[o.camera as usize], &step.dp[o.point as usize]);
                let (a, b) = (&lin.jc[i], &lin.jp[i]);
                let mut e = [0.0; 2];
                for (r, e) in e.iter_mut().enumerate() {
                    *e = (0..9).map(|k| a[9 * r + k] * dc[k]).sum::<f64>()
                        + (0..3).map(|k| b[3 * r + k] * dp[k]).sum::<f64>();
                }
                sum += e[0] * e[0] + e[1] * e[1];
            }
            sum
        })
        .collect();
    let jd2: f64 = partial.iter().sum();
    let gc: f64 = lin
        .gc
        .iter()
        .zip(&step.dc)
        .map(|(g, d)| g.iter().zip(d).map(|(a, b)| a * b).sum::<f64>())
        .sum();
    let gp: f64 = lin
        .gp
        .iter()
        .zip(&step.dp)
        .map(|(g, d)| g.iter().zip(d).map(|(a, b)| a * b).sum::<f64>())
        .sum();
    -(gc + gp + 0.5 * jd2)
}

fn apply_step(
    cameras: &[BaCamera],
    points: &[[f64; 3]],
    step: &Step,
) -> (Vec<BaCamera>, Vec<[f64; 3]>) {
    let cams: Vec<BaCamera> = cameras
        .par_iter()
        .zip(step.dc.par_iter())
        .map(|(c, d)| BaCamera {
            rotation: rotate(&c.rotation, &d[0..3]),
            translation: [
                c.translation[0] + d[3],
                c.translation[1] + d[4],
                c.translation[2] + d[5],
            ],
            intrinsics: [
                c.intrinsics[0] + d[6],
                c.intrinsics[1] + d[7],
                c.intrinsics[2] + d[8],
            ],
            principal_point: c.principal_point,
        })
        .collect();
    let pts: Vec<[f64; 3]> = points
        .par_iter()
        .zip(step.dp.par_iter())
        .with_min_len(POINT_CHUNK)
        .map(|(p, d)| [p[0] + d[0], p[1] + d[1], p[2] + d[2]])
        .collect();
    (cams, pts)
}

fn max_gradient(lin: &Linearization) -> f64 {
    let c = lin.gc.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    lin.gp.iter().flatten().fold(c, |m, v| m.max(v.abs()))
}

fn state_norm(cameras: &[BaCamera], points: &[[f64; 3]]) -> f64 {
    // Unit quaternions contribute 1 each (Ceres' ambient norm for quaternion rotations).
    let c: f64 = cameras
        .iter()
        .map(|c| {
            1.0 + c.translation.iter().map(|v| v * v).sum::<f64>()
                + c.intrinsics.iter().map(|v| v * v).sum::<f64>()
        })
        .sum();
    let p: f64 = points.iter().flatten().map(|v| v * v).sum();
    (c + p).sqrt()
}

fn step_norm(step: &Step) -> f64 {
    let c: f64 = step.dc.iter().flatten().map(|v| v * v).sum();
    let p: f64 = step.dp.iter().flatten().map(|v| v * v).sum();
    (c + p).sqrt()
}

/// Minimizes the problem's cost; `problem`'s cameras and points are replaced by the solution.
pub fn solve(problem: &mut BaProblem, options: &BaOptions) -> Result<BaSummary, String> {
    validate(problem)?;
    let start = Instant::now();
    let layout = Layout::new(problem);
    let solver = ReducedSolver::resolve(&layout, options.linear_solver)?;
    let mut cameras = problem.cameras.clone();
    let mut points = problem.points.clone();
    let mut lin = linearize(&layout, &cameras, &points, options.loss);
    let initial_cost = lin.cost;
    let mut history = vec![IterationRecord {
        cost: initial_cost,
        step_norm: 0.0,
        radius: options.initial_trust_region_radius,
        accepted: true,
        time_s: start.elapsed().as_secs_f64(),
        cg_iterations: 0,
    }];
    let mut summary = BaSummary {
        initial_cost,
        final_cost: initial_cost,
        iterations: 1,
        successful_steps: 1,
        unsuccessful_steps: 0,
        termination: Termination::MaxIterations,
        linear_solver: solver.kind(),
        history: Vec::new(),
        time_s: 0.0,
    };
    let any_free =
        layout.camera_free.iter().flatten().any(|&f| f) || layout.point_free.iter().any(|&f| f);
    if layout.obs.is_empty() || !any_free {
        summary.termination = Termination::Trivial;
        summary.history = history;
        summary.time_s = start.elapsed().as_secs_f64();
        return Ok(summary);
    }
    // Jacobi scaling from the first Jacobian: 1 / (1 + ‖column‖).
    let scale_c: Vec<[f64; CAMERA_DOF]> = lin
        .u
        .iter()
        .map(|u| std::array::from_fn(|d| 1.0 / (1.0 + u[10 * d].sqrt())))
        .collect();
    let scale_p: Vec<[f64; 3]> = lin
        .v
        .iter()
        .map(|v| std::array::from_fn(|d| 1.0 / (1.0 + v[4 * d].sqrt())))
        .collect();
    let mut radius = options.initial_trust_region_radius;
    let mut decrease_factor = 2.0;
    if max_gradient(&lin) <= options.gradient_tolerance {
        summary.termination = Termination::GradientTolerance;
    } else {
        loop {
            if summary.iterations >= options.max_iterations {
                summary.termination = Termination::MaxIterations;
                break;
            }
            let step = compute_step(&layout, &lin, &scale_c, &scale_p, radius, &solver, options);
            let mut record = IterationRecord {
                cost: lin.cost,
                step_norm: 0.0,
                radius,
                accepted: false,
                time_s: 0.0,
                cg_iterations: 0,
            };
            let mut accepted = None;
            if let Some(step) = step {
                record.step_norm = step_norm(&step);
                record.cg_iterations = step.cg_iterations;
                let predicted = model_decrease(&layout, &lin, &step);
                let (cams, pts) = apply_step(&cameras, &points, &step);
                let new_cost = cost(&layout, &cams, &pts, options.loss);
                let x_norm = state_norm(&cameras, &points);
                if record.step_norm
                    <= options.parameter_tolerance * (x_norm + options.parameter_tolerance)
                {
                    summary.termination = Termination::ParameterTolerance;
                    break;
                }
                if new_cost.is_finite()
                    && (lin.cost - new_cost).abs() <= options.function_tolerance * lin.cost
                {
                    summary.termination = Termination::FunctionTolerance;
                    break;
                }
                let rho = (lin.cost - new_cost) / predicted;
                if new_cost.is_finite() && predicted > 0.0 && rho > 1e-3 {
                    accepted = Some((cams, pts, rho));
                }
            }
            summary.iterations += 1;
            if let Some((cams, pts, rho)) = accepted {
                cameras = cams;
                points = pts;
                lin = linearize(&layout, &cameras, &points, options.loss);
                summary.successful_steps += 1;
                let factor = 1.0 - (2.0 * rho - 1.0).powi(3);
                radius = (radius / factor.max(1.0 / 3.0)).min(1e16);
                decrease_factor = 2.0;
                record.cost = lin.cost;
                record.accepted = true;
                record.time_s = start.elapsed().as_secs_f64();
                history.push(record);
                if max_gradient(&lin) <= options.gradient_tolerance {
                    summary.termination = Termination::GradientTolerance;
                    break;
                }
            } else {
                summary.unsuccessful_steps += 1;
                radius /= decrease_factor;
                decrease_factor *= 2.0;
                record.time_s = start.elapsed().as_secs_f64();
                history.push(record);
                if radius < 1e-32 {
                    summary.termination = Termination::TrustRegionCollapsed;
                    break;
                }
            }
        }
    }
    summary.final_cost = lin.cost;
    summary.history = history;
    summary.time_s = start.elapsed().as_secs_f64();
    problem.cameras = cameras;
    problem.points = points;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::synthetic::{SyntheticOptions, synthetic_problem};

    fn small(noise_px: f64, outliers: f64, seed: u64) -> (BaProblem, BaProblem) {
        synthetic_problem(&SyntheticOptions {
            cameras: 6,
            points: 80,
            noise_px,
            outlier_fraction: outliers,
            seed,
            ..SyntheticOptions::default()
        })
        .unwrap()
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let (_, start) = small(0.5, 0.0, 3);
        for o in start.observations.iter().take(40) {
            let mut cam = start.cameras[o.camera as usize];
            cam.intrinsics = [cam.intrinsics[0], -0.2, 0.05];
            cam.principal_point = [3.0, -2.0];
            let x = start.points[o.point as usize];
            let (r, jc, jp) = residual_jacobians(&cam, &x, &o.xy);
            let p0 = project(&cam, &x);
            assert!((r[0] - (p0[0] - o.xy[0])).abs() < 1e-12);
            for d in 0..9 {
                let h = 1e-6;
                let shifted = |s: f64| {
                    let mut c = cam;
                    let mut delta = [0.0; 9];
                    delta[d] = s;
                    c.rotation = rotate(&cam.rotation, &delta[0..3]);
                    for k in 0..3 {
                        c.translation[k] += delta[3 + k];
                        c.intrinsics[k] += delta[6 + k];
                    }
                    project(&c, &x)
                };
                let (a, b) = (shifted(h), shifted(-h));
                for i in 0..2 {
                    let fd = (a[i] - b[i]) / (2.0 * h);
                    let an = jc[9 * i + d];
                    assert!(
                        (fd - an).abs() <= 1e-5 * (1.0 + an.abs()),
                        "camera dof {d} row {i}: fd {fd} analytic {an}"
                    );
                }
            }
            for d in 0..3 {
                let h = 1e-6;
                let mut xa = x;
                let mut xb = x;
                xa[d] += h;
                xb[d] -= h;
                let (a, b) = (project(&cam, &xa), project(&cam, &xb));
                for i in 0..2 {
                    let fd = (a[i] - b[i]) / (2.0 * h);
                    let an = jp[3 * i + d];
                    assert!((fd - an).abs() <= 1e-5 * (1.0 + an.abs()), "point dof {d}");
                }
            }
        }
    }

    #[test]
    fn noise_free_problem_converges_to_zero_cost() {
        let (truth, mut start) = small(0.0, 0.0, 5);
        assert!(problem_cost(&truth, RobustLoss::Trivial).unwrap() < 1e-20);
        let options = BaOptions {
            function_tolerance: 1e-12,
            max_iterations: 100,
            ..BaOptions::default()
        };
        let s = solve(&mut start, &options).unwrap();
        assert!(
            s.initial_cost > 1e3,
            "start is perturbed: {}",
            s.initial_cost
        );
        assert!(s.final_cost < 1e-8, "final cost {}", s.final_cost);
        assert_eq!(s.linear_solver, LinearSolver::DenseSchur);
        assert_eq!(s.iterations, s.successful_steps + s.unsuccessful_steps);
        assert_eq!(s.history.len(), s.iterations);
        // Costs in the history never increase.
        for w in s.history.windows(2) {
            assert!(w[1].cost <= w[0].cost);
        }
    }

    #[test]
    fn noisy_problem_reaches_at_most_the_true_cost() {
        let (truth, mut start) = small(0.5, 0.0, 7);
        let true_cost = problem_cost(&truth, RobustLoss::Trivial).unwrap();
        let s = solve(&mut start, &BaOptions::default()).unwrap();
        assert!(s.final_cost <= true_cost, "{} > {true_cost}", s.final_cost);
        // ML estimate: cost about ½σ²(2n − dof) — well below the truth but the same order.
        assert!(
            s.final_cost > 0.3 * true_cost,
            "{} vs {true_cost}",
            s.final_cost
        );
        assert_eq!(s.termination, Termination::FunctionTolerance);
    }

    #[test]
    fn iterative_and_dense_schur_agree() {
        let (_, start) = small(0.5, 0.0, 11);
        let mut a = start.clone();
        let mut b = start;
        let options = BaOptions {
            function_tolerance: 1e-10,
            ..BaOptions::default()
        };
        let sa = solve(&mut a, &options).unwrap();
        let sb = solve(
            &mut b,
            &BaOptions {
                linear_solver: LinearSolver::IterativeSchur,
                cg_tolerance: 1e-10,
                ..options
            },
        )
        .unwrap();
        assert_eq!(sb.linear_solver, LinearSolver::IterativeSchur);
        assert!(sb.history.iter().skip(1).any(|h| h.cg_iterations > 0));
        assert!(
            (sa.final_cost - sb.final_cost).abs() <= 1e-6 * sa.final_cost,
            "{} vs {}",
            sa.final_cost,
            sb.final_cost
        );
    }

    #[test]
    fn bit_identical_for_any_thread_count() {
        let (_, start) = synthetic_problem(&SyntheticOptions {
            cameras: 10,
            points: 3000,
            seed: 13,
            ..SyntheticOptions::default()
        })
        .unwrap();
        assert!(start.observations.len() > 2 * OBS_CHUNK);
        let run = |threads: usize, solver: LinearSolver| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut p = start.clone();
            let options = BaOptions {
                max_iterations: 6,
                linear_solver: solver,
                ..BaOptions::default()
            };
            let s = pool.install(|| solve(&mut p, &options)).unwrap();
            (p, s.final_cost.to_bits())
        };
        for solver in [
            LinearSolver::DenseSchur,
            LinearSolver::SparseSchur,
            LinearSolver::IterativeSchur,
        ] {
            let one = run(1, solver);
            for threads in [2, 3] {
                let many = run(threads, solver);
                assert_eq!(one.1, many.1, "{solver:?}, {threads} threads");
                assert_eq!(one.0, many.0, "{solver:?}, {threads} threads");
            }
        }
    }

    /// Steps of two resolved solvers at the start of `problem`, at `radius`.
    fn first_steps(
        problem: &BaProblem,
        radius: f64,
        solvers: [LinearSolver; 2],
    ) -> [Option<Step>; 2] {
        let layout = Layout::new(problem);
        let lin = linearize(
            &layout,
            &problem.cameras,
            &problem.points,
            RobustLoss::Trivial,
        );
        let scale_c: Vec<[f64; CAMERA_DOF]> = lin
            .u
            .iter()
            .map(|u| std::array::from_fn(|d| 1.0 / (1.0 + u[10 * d].sqrt())))
            .collect();
        let scale_p: Vec<[f64; 3]> = lin
            .v
            .iter()
            .map(|v| std::array::from_fn(|d| 1.0 / (1.0 + v[4 * d].sqrt())))
            .collect();
        solvers.map(|kind| {
            let solver = ReducedSolver::resolve(&layout, kind).unwrap();
            assert_eq!(solver.kind(), kind);
            let options = BaOptions::default();
            compute_step(&layout, &lin, &scale_c, &scale_p, radius, &solver, &options)
        })
    }

    fn relative_difference(a: &Step, b: &Step) -> f64 {
        let flat = |s: &Step| -> Vec<f64> {
            s.dc.iter()
                .flatten()
                .chain(s.dp.iter().flatten())
                .copied()
                .collect()
        };
        let (a, b) = (flat(a), flat(b));
        let diff: f64 = a.iter().zip(&b).map(|(x, y)| (x - y) * (x - y)).sum();
        let norm: f64 = a.iter().map(|x| x * x).sum();
        (diff / norm).sqrt()
    }

    #[test]
    fn sparse_step_equals_dense_step() {
        let (_, start) = synthetic_problem(&SyntheticOptions {
            cameras: 12,
            points: 200,
            visibility: 0.4,
            seed: 31,
            ..SyntheticOptions::default()
        })
        .unwrap();
        let mut fixed = start.clone();
        // First camera fixed (gauge), some intrinsics fixed on others, a few points fixed.
        fixed.camera_free = vec![[true; CAMERA_DOF]; fixed.cameras.len()];
        fixed.camera_free[0] = [false; CAMERA_DOF];
        fixed.camera_free[3][7] = false;
        fixed.camera_free[3][8] = false;
        fixed.camera_free[5][6] = false;
        fixed.point_free = (0..fixed.points.len()).map(|j| j % 7 != 0).collect();
        for problem in [&start, &fixed] {
            for radius in [1e4, 1.0, 1e-3] {
                let [dense, sparse] = first_steps(
                    problem,
                    radius,
                    [LinearSolver::DenseSchur, LinearSolver::SparseSchur],
                );
                let (dense, sparse) = (dense.unwrap(), sparse.unwrap());
                let rel = relative_difference(&dense, &sparse);
                assert!(rel < 1e-9, "radius {radius}: relative difference {rel}");
                assert!(step_norm(&dense) > 0.0);
                if !problem.camera_free.is_empty() {
                    assert_eq!(sparse.dc[0], [0.0; CAMERA_DOF]);
                    assert_eq!(sparse.dc[3][7], 0.0);
                    assert_eq!(sparse.dc[5][6], 0.0);
                    assert_eq!(sparse.dp[0], [0.0; 3]);
                }
            }
        }
        // The pattern leaves out camera pairs without a common point: a strict subset of the
        // dense matrix for a sparse visibility graph.
        let (_, sparse_graph) = synthetic_problem(&SyntheticOptions {
            cameras: 40,
            points: 400,
            visibility: 0.05,
            seed: 37,
            ..SyntheticOptions::default()
        })
        .unwrap();
        let layout = Layout::new(&sparse_graph);
        let neighbours = camera_neighbours(&layout);
        let blocks: usize = neighbours.iter().map(Vec::len).sum();
        assert!(blocks < 40 * 41 / 2, "{blocks} blocks");
        let [dense, sparse] = first_steps(
            &sparse_graph,
            1e4,
            [LinearSolver::DenseSchur, LinearSolver::SparseSchur],
        );
        let rel = relative_difference(&dense.unwrap(), &sparse.unwrap());
        assert!(
            rel < 1e-9,
            "sparse visibility graph: relative difference {rel}"
        );
    }

    #[test]
    fn sparse_and_dense_schur_reach_the_same_cost() {
        let (truth, start) = small(0.5, 0.0, 41);
        let true_cost = problem_cost(&truth, RobustLoss::Trivial).unwrap();
        let options = BaOptions {
            function_tolerance: 1e-10,
            ..BaOptions::default()
        };
        let run = |solver| {
            let mut p = start.clone();
            let s = solve(
                &mut p,
                &BaOptions {
                    linear_solver: solver,
                    ..options
                },
            )
            .unwrap();
            (p, s)
        };
        let (_, dense) = run(LinearSolver::DenseSchur);
        let (_, sparse) = run(LinearSolver::SparseSchur);
        assert_eq!(sparse.linear_solver, LinearSolver::SparseSchur);
        assert!(sparse.final_cost < 0.01 * sparse.initial_cost);
        assert!(sparse.final_cost <= true_cost);
        assert!(
            (dense.final_cost - sparse.final_cost).abs() <= 1e-9 * dense.final_cost,
            "{} vs {}",
            dense.final_cost,
            sparse.final_cost
        );
        // With a fixed first camera too.
        let mut gauge = start.clone();
        gauge.camera_free = vec![[true; CAMERA_DOF]; gauge.cameras.len()];
        gauge.camera_free[0] = [false; CAMERA_DOF];
        let mut a = gauge.clone();
        let mut b = gauge;
        let sa = solve(&mut a, &options).unwrap();
        let sb = solve(
            &mut b,
            &BaOptions {
                linear_solver: LinearSolver::SparseSchur,
                ..options
            },
        )
        .unwrap();
        assert_eq!(b.cameras[0], start.cameras[0]);
        assert!(
            (sa.final_cost - sb.final_cost).abs() <= 1e-9 * sa.final_cost,
            "{} vs {}",
            sa.final_cost,
            sb.final_cost
        );
    }

    #[test]
    fn singular_sparse_system_rejects_the_step_without_panicking() {
        // A camera that sees nothing, a point seen once and a free gauge: damping keeps S
        // definite, so the solve proceeds.
        let (_, mut p) = small(0.5, 0.0, 43);
        p.cameras.push(p.cameras[0]);
        let s = solve(
            &mut p,
            &BaOptions {
                linear_solver: LinearSolver::SparseSchur,
                ..BaOptions::default()
            },
        )
        .unwrap();
        assert!(s.final_cost < s.initial_cost);
        // An indefinite reduced matrix: the factorization fails and the step is rejected, as in
        // the dense path.
        let (_, start) = small(0.5, 0.0, 47);
        let layout = Layout::new(&start);
        let lin = linearize(&layout, &start.cameras, &start.points, RobustLoss::Trivial);
        let ones_c = vec![[1.0; CAMERA_DOF]; start.cameras.len()];
        let ones_p = vec![[1.0; 3]; start.points.len()];
        let mut el = eliminate(&layout, &lin, &ones_c, &ones_p, 1.0).unwrap();
        el.u[2][10 * 4] = -1e12;
        let pattern = SparseSchurPattern::new(&layout, camera_neighbours(&layout)).unwrap();
        assert!(sparse_schur_solve(&layout, &el, &pattern).is_none());
        el.u[2][10 * 4] = f64::NAN;
        assert!(sparse_schur_solve(&layout, &el, &pattern).is_none());
        // A point at a camera's centre makes the linearization non-finite: every step is
        // rejected until the trust region collapses, and nothing panics.
        let mut p = start.clone();
        let (o, r) = (
            p.observations[0],
            p.cameras[p.observations[0].camera as usize].rotation,
        );
        let x = p.points[o.point as usize];
        p.cameras[o.camera as usize].translation =
            std::array::from_fn(|i| -(r[3 * i] * x[0] + r[3 * i + 1] * x[1] + r[3 * i + 2] * x[2]));
        let s = solve(
            &mut p,
            &BaOptions {
                linear_solver: LinearSolver::SparseSchur,
                ..BaOptions::default()
            },
        )
        .unwrap();
        assert!(!s.initial_cost.is_finite());
        assert_eq!(s.successful_steps, 1, "{s:?}");
        assert_eq!(s.termination, Termination::TrustRegionCollapsed);
    }

    #[test]
    fn auto_picks_dense_for_few_cameras_and_sparse_beyond() {
        let (_, p) = small(0.5, 0.0, 53);
        let layout = Layout::new(&p);
        assert_eq!(
            ReducedSolver::resolve(&layout, LinearSolver::Auto)
                .unwrap()
                .kind(),
            LinearSolver::DenseSchur
        );
        let (_, p) = synthetic_problem(&SyntheticOptions {
            cameras: DENSE_MAX_CAMERAS + 1,
            points: 2000,
            visibility: 0.02,
            seed: 59,
            ..SyntheticOptions::default()
        })
        .unwrap();
        let layout = Layout::new(&p);
        assert_eq!(
            ReducedSolver::resolve(&layout, LinearSolver::Auto)
                .unwrap()
                .kind(),
            LinearSolver::SparseSchur
        );
    }

    #[test]
    fn robust_losses_resist_outliers() {
        let (truth, start) = small(0.5, 0.05, 17);
        // Inlier observations: those within 5 px of the truth.
        let inlier: Vec<bool> = squared_errors(&truth).iter().map(|&e| e < 25.0).collect();
        let n_out = inlier.iter().filter(|&&i| !i).count();
        assert!(n_out > 5, "{n_out} outliers");
        let inlier_rms = |p: &BaProblem| {
            let e = squared_errors(p);
            let (s, n) = e
                .iter()
                .zip(&inlier)
                .filter(|(_, i)| **i)
                .fold((0.0, 0), |(s, n), (e, _)| (s + e, n + 1));
            (s / n as f64).sqrt()
        };
        let run = |loss| {
            let mut p = start.clone();
            solve(
                &mut p,
                &BaOptions {
                    loss,
                    max_iterations: 100,
                    ..BaOptions::default()
                },
            )
            .unwrap();
            inlier_rms(&p)
        };
        let plain = run(RobustLoss::Trivial);
        let truth_rms = inlier_rms(&truth);
        let results: Vec<(RobustLoss, f64)> = [
            RobustLoss::Huber(2.0),
            RobustLoss::Cauchy(2.0),
            RobustLoss::SoftL1(2.0),
            RobustLoss::Tukey(10.0),
        ]
        .into_iter()
        .map(|loss| (loss, run(loss)))
        .collect();
        for &(loss, robust) in &results {
            // Bounded influence for all; Cauchy's redescending influence reaches the noise level.
            let cauchy = matches!(loss, RobustLoss::Cauchy(_));
            let ok = robust < 0.5 * plain && (!cauchy || robust < 1.5 * truth_rms);
            assert!(
                ok,
                "{loss:?}: inlier RMS {robust}; all: {results:?} (truth {truth_rms}, plain {plain})"
            );
        }
    }

    #[test]
    fn fixed_blocks_stay_put() {
        let (_, start) = small(0.5, 0.0, 19);
        // Motion only: points fixed.
        let mut p = start.clone();
        p.point_free = vec![false; p.points.len()];
        let s = solve(&mut p, &BaOptions::default()).unwrap();
        assert_eq!(p.points, start.points);
        assert!(s.final_cost < s.initial_cost);
        // Structure only: cameras fixed.
        let mut p = start.clone();
        p.camera_free = vec![[false; CAMERA_DOF]; p.cameras.len()];
        let s = solve(&mut p, &BaOptions::default()).unwrap();
        assert_eq!(p.cameras, start.cameras);
        assert!(s.final_cost < s.initial_cost);
        // Gauge: first camera fixed, the others move.
        let mut p = start.clone();
        p.camera_free = vec![[true; CAMERA_DOF]; p.cameras.len()];
        p.camera_free[0] = [false; CAMERA_DOF];
        solve(&mut p, &BaOptions::default()).unwrap();
        assert_eq!(p.cameras[0], start.cameras[0]);
        assert_ne!(p.cameras[1], start.cameras[1]);
        // Nothing free: trivial.
        let mut p = start.clone();
        p.camera_free = vec![[false; CAMERA_DOF]; p.cameras.len()];
        p.point_free = vec![false; p.points.len()];
        let s = solve(&mut p, &BaOptions::default()).unwrap();
        assert_eq!(s.termination, Termination::Trivial);
    }

    #[test]
    fn invalid_problems_are_rejected() {
        let (_, start) = small(0.5, 0.0, 23);
        let mut p = start.clone();
        p.observations[0].camera = 99;
        assert!(solve(&mut p, &BaOptions::default()).is_err());
        let mut p = start.clone();
        p.points[0][1] = f64::NAN;
        assert!(solve(&mut p, &BaOptions::default()).is_err());
        let mut p = start;
        p.weights = vec![1.0];
        assert!(solve(&mut p, &BaOptions::default()).is_err());
        let mut empty = BaProblem::default();
        let s = solve(&mut empty, &BaOptions::default()).unwrap();
        assert_eq!(s.termination, Termination::Trivial);
        assert_eq!(s.final_cost, 0.0);
    }

    #[test]
    fn weights_scale_the_cost() {
        let (_, start) = small(0.5, 0.0, 29);
        let base = problem_cost(&start, RobustLoss::Trivial).unwrap();
        let mut p = start;
        p.weights = vec![2.0; p.observations.len()];
        let weighted = problem_cost(&p, RobustLoss::Trivial).unwrap();
        assert!((weighted - 4.0 * base).abs() <= 1e-9 * weighted);
    }

    #[test]
    fn dense_cholesky_solves() {
        // A = [[4, 2, 0], [2, 5, 1], [0, 1, 3]], b = A·[1, −1, 2].
        let mut a = [4.0, 2.0, 0.0, 2.0, 5.0, 1.0, 0.0, 1.0, 3.0];
        let mut b = [2.0, -1.0, 5.0];
        assert!(cholesky(&mut a, 3));
        cholesky_solve(&a, 3, &mut b);
        for (x, e) in b.iter().zip([1.0, -1.0, 2.0]) {
            assert!((x - e).abs() < 1e-12);
        }
        let mut not_pd = [1.0, 2.0, 2.0, 1.0];
        assert!(!cholesky(&mut not_pd, 2));
    }
}
