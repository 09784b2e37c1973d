//! `optimize.bundle_adjust`: bundle adjustment of a [`Reconstruction`] with the sparse
//! Schur-complement Levenberg–Marquardt solver of [`super::ba`].
//!
//! The reconstruction is mapped to a [`BaProblem`]: one camera block per posed image (its
//! `camera_from_world` pose and its camera's `f, k1, k2`), one point block per 3-D point, one
//! observation per 2-D point that names a 3-D point. That fast path takes `SIMPLE_PINHOLE`
//! (f), `SIMPLE_RADIAL` (f, k) and `RADIAL` (f, k1, k2) with one camera per image; the principal
//! point is held fixed. Every other reconstruction (`PINHOLE`, `OPENCV`, `FULL_OPENCV`,
//! `OPENCV_FISHEYE`, or intrinsics shared by several images) goes to the general sparse solver
//! of [`super::bundle_general`].

use std::collections::HashMap;
use std::sync::Arc;

use ocellus_engine::value::{
    Camera, CameraModel, Metrics, Pose, ReconImage, ReconPoint, Reconstruction,
};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use super::ba::{
    BaCamera, BaObservation, BaOptions, BaProblem, BaSummary, CAMERA_DOF, LinearSolver, solve,
    squared_errors,
};
use super::bundle_general::{GeneralBaOptions, bundle_adjust_general};
use super::loss::RobustLoss;
use super::nlls::{LinearSolverType, SolverOptions};
use super::solve_report::{SolveTotals, history_metrics, totals_metrics};

/// Which blocks are refined.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Cameras and points.
    Full,
    /// Camera poses (and intrinsics if refined) only; points fixed.
    MotionOnly,
    /// Points only; cameras fixed.
    StructureOnly,
}

/// The image index and keypoint index of each problem observation.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ObservationIndex {
    /// `(image index in reconstruction.images, index into its points2d)` per observation.
    pub keypoints: Vec<(usize, usize)>,
}

/// `[f, k1, k2]`, the principal point, and which of `f, k1, k2` the model has.
type CameraParts = ([f64; 3], [f64; 2], [bool; 3]);

fn camera_intrinsics(cam: &Camera) -> Result<CameraParts, String> {
    let p = |i: usize| cam.params.get(i).copied().unwrap_or(0.0);
    if cam.params.len() != cam.model.param_count() {
        return Err(format!(
            "{} camera has {} parameters, expected {}",
            cam.model.colmap_name(),
            cam.params.len(),
            cam.model.param_count()
        ));
    }
    match cam.model {
        CameraModel::SimplePinhole => Ok(([p(0), 0.0, 0.0], [p(1), p(2)], [true, false, false])),
        CameraModel::SimpleRadial => Ok(([p(0), p(3), 0.0], [p(1), p(2)], [true, true, false])),
        CameraModel::Radial => Ok(([p(0), p(3), p(4)], [p(1), p(2)], [true, true, true])),
        m => Err(format!(
            "camera model {} is not supported by bundle adjustment (supported: SIMPLE_PINHOLE, \
             SIMPLE_RADIAL, RADIAL)",
            m.colmap_name()
        )),
    }
}

/// Maps a reconstruction to a problem. With `refine_intrinsics`, each camera must be used by
/// one image only (shared intrinsics are not supported).
pub fn problem_from_reconstruction(
    rec: &Reconstruction,
    mode: Mode,
    refine_intrinsics: bool,
    fix_first_camera: bool,
) -> Result<(BaProblem, ObservationIndex), String> {
    let mut uses: HashMap<u32, usize> = HashMap::new();
    for im in &rec.images {
        *uses.entry(im.camera_id).or_default() += 1;
    }
    let mut problem = BaProblem::default();
    for (k, im) in rec.images.iter().enumerate() {
        let cam = rec
            .cameras
            .get(&im.camera_id)
            .ok_or_else(|| format!("image {} refers to missing camera {}", im.id, im.camera_id))?;
        let (intrinsics, principal_point, model_free) = camera_intrinsics(cam)?;
        if refine_intrinsics && uses.get(&im.camera_id).copied().unwrap_or(0) > 1 {
            return Err(format!(
                "camera {} is shared by several images; shared intrinsics cannot be refined \
                 (set refine_intrinsics: false)",
                im.camera_id
            ));
        }
        let pose = &im.camera_from_world;
        if !pose
            .rotation
            .iter()
            .chain(&pose.translation)
            .all(|v| v.is_finite())
        {
            return Err(format!("image {} has a non-finite pose", im.id));
        }
        problem.cameras.push(BaCamera {
            rotation: pose.rotation_matrix(),
            translation: pose.translation,
            intrinsics,
            principal_point,
        });
        let mut free = [true; CAMERA_DOF];
        for d in 0..3 {
            free[6 + d] = refine_intrinsics && model_free[d];
        }
        if mode == Mode::StructureOnly || (fix_first_camera && k == 0) {
            free = [false; CAMERA_DOF];
        }
        problem.camera_free.push(free);
    }
    let mut point_index: HashMap<u64, usize> = HashMap::with_capacity(rec.points.len());
    for (j, p) in rec.points.iter().enumerate() {
        if point_index.insert(p.id, j).is_some() {
            return Err(format!("point id {} appears twice", p.id));
        }
        problem.points.push(p.position);
    }
    problem.point_free = vec![mode != Mode::MotionOnly; rec.points.len()];
    let mut index = ObservationIndex::default();
    for (k, im) in rec.images.iter().enumerate() {
        for (kp, (xy, id)) in im.points2d.iter().enumerate() {
            let Some(id) = id else { continue };
            let j = *point_index
                .get(id)
                .ok_or_else(|| format!("image {} observes missing point {id}", im.id))?;
            problem.observations.push(BaObservation {
                camera: k as u32,
                point: j as u32,
                xy: *xy,
            });
            index.keypoints.push((k, kp));
        }
    }
    Ok((problem, index))
}

/// The reconstruction with the problem's cameras and points written back; each point's
/// `error_px` is its mean reprojection error.
pub fn apply_to_reconstruction(rec: &Reconstruction, problem: &BaProblem) -> Reconstruction {
    let mut out = rec.clone();
    for (im, cam) in out.images.iter_mut().zip(&problem.cameras) {
        im.camera_from_world = Pose::from_rotation_matrix(&cam.rotation, cam.translation);
        if let Some(c) = out.cameras.get_mut(&im.camera_id) {
            let [f, k1, k2] = cam.intrinsics;
            match c.model {
                CameraModel::SimplePinhole => c.params[0] = f,
                CameraModel::SimpleRadial => {
                    c.params[0] = f;
                    c.params[3] = k1;
                }
                CameraModel::Radial => {
                    c.params[0] = f;
                    c.params[3] = k1;
                    c.params[4] = k2;
                }
                _ => {}
            }
        }
    }
    let errors = squared_errors(problem);
    let mut sum = vec![0.0; problem.points.len()];
    let mut count = vec![0usize; problem.points.len()];
    for (o, e) in problem.observations.iter().zip(&errors) {
        sum[o.point as usize] += e.sqrt();
        count[o.point as usize] += 1;
    }
    for (j, p) in out.points.iter_mut().enumerate() {
        p.position = problem.points[j];
        p.error_px = if count[j] > 0 {
            sum[j] / count[j] as f64
        } else {
            0.0
        };
    }
    out
}

/// A reconstruction holding a problem: camera `i` becomes camera and image `i + 1` (a `RADIAL`
/// camera of size `size`), point `j` gets id `j`, observations keep their order per image.
pub fn problem_to_reconstruction(problem: &BaProblem, size: [u32; 2]) -> Reconstruction {
    let mut rec = Reconstruction::default();
    for (i, c) in problem.cameras.iter().enumerate() {
        let id = i as u32 + 1;
        let [f, k1, k2] = c.intrinsics;
        rec.cameras.insert(
            id,
            Camera {
                model: CameraModel::Radial,
                width: size[0],
                height: size[1],
                params: vec![f, c.principal_point[0], c.principal_point[1], k1, k2],
            },
        );
        rec.images.push(ReconImage {
            id,
            camera_id: id,
            name: format!("image{i:05}"),
            camera_from_world: Pose::from_rotation_matrix(&c.rotation, c.translation),
            points2d: Vec::new(),
        });
    }
    rec.points = problem
        .points
        .iter()
        .enumerate()
        .map(|(j, p)| ReconPoint {
            id: j as u64,
            position: *p,
            color: [128, 128, 128],
            error_px: 0.0,
            track: Vec::new(),
        })
        .collect();
    for o in &problem.observations {
        let im = &mut rec.images[o.camera as usize];
        let kp = im.points2d.len() as u32;
        im.points2d.push((o.xy, Some(o.point as u64)));
        rec.points[o.point as usize].track.push((im.id, kp));
    }
    let errors = squared_errors(problem);
    let mut count = vec![0usize; problem.points.len()];
    for (o, e) in problem.observations.iter().zip(&errors) {
        rec.points[o.point as usize].error_px += e.sqrt();
        count[o.point as usize] += 1;
    }
    for (p, n) in rec.points.iter_mut().zip(count) {
        if n > 0 {
            p.error_px /= n as f64;
        }
    }
    rec
}

ocellus_engine::param_enum! {
    /// Linear solver of the reduced camera system.
    pub enum SolverChoice {
        /// Dense Schur up to 16 cameras; beyond, sparse Schur while one factorization stays
        /// cheap (see `LinearSolver::Auto`), iterative Schur otherwise.
        Auto = "auto",
        /// Dense Cholesky of the reduced camera matrix.
        DenseSchur = "dense_schur",
        /// Block-Jacobi preconditioned conjugate gradients.
        IterativeSchur = "iterative_schur",
        /// Sparse Cholesky (faer) of the reduced camera matrix: only camera pairs that share a
        /// point have a nonzero block.
        SparseSchur = "sparse_schur",
    }
}

ocellus_engine::param_enum! {
    /// Robust loss on each observation's squared reprojection error.
    pub enum LossChoice {
        /// Plain least squares.
        None = "none",
        /// Huber.
        Huber = "huber",
        /// Cauchy (Lorentzian).
        Cauchy = "cauchy",
        /// Soft L1 (pseudo-Huber).
        SoftL1 = "soft_l1",
        /// Tukey's biweight.
        Tukey = "tukey",
    }
}

ocellus_engine::param_enum! {
    /// Which blocks are refined.
    pub enum ModeChoice {
        /// Cameras and points.
        Full = "full",
        /// Cameras only (points fixed).
        MotionOnly = "motion_only",
        /// Points only (cameras fixed).
        StructureOnly = "structure_only",
    }
}

ocellus_engine::params! {
    /// Parameters of [`BundleAdjust`].
    pub struct BundleAdjustParams {
        /// Most iterations, Ceres' count (iteration 0 is the initial evaluation), 1..=10000.
        /// Default 50 (Ceres' default).
        max_iterations: u32 = 50,
        /// Stop when a trial step changes the cost by at most this fraction of it. Default 1e-6.
        function_tolerance: f64 = 1e-6,
        /// Stop when the largest gradient component is at most this (px² per parameter unit).
        /// Default 1e-10.
        gradient_tolerance: f64 = 1e-10,
        /// Stop when ‖step‖ ≤ this · (‖x‖ + this). Default 1e-8.
        parameter_tolerance: f64 = 1e-8,
        /// Reduced camera system solver: "auto" (dense up to 16 cameras, then sparse while
        /// one factorization stays cheap, else iterative), "dense_schur", "sparse_schur", "iterative_schur".
        /// Default "auto".
        linear_solver: SolverChoice = SolverChoice::Auto,
        /// Robust loss: "none", "huber", "cauchy", "soft_l1", "tukey". Default "none".
        loss: LossChoice = LossChoice::None,
        /// Scale of the robust loss, px (where down-weighting starts), > 0. Default 1.
        loss_scale_px: f64 = 1.0,
        /// "full", "motion_only" (points fixed) or "structure_only" (cameras fixed).
        /// Default "full".
        mode: ModeChoice = ModeChoice::Full,
        /// Hold the first image's pose and intrinsics fixed (gauge fixing of rotation and
        /// translation; the scale stays free). Default false (as Ceres' BAL example).
        fix_first_camera: bool = false,
        /// Refine focal lengths and distortion (principal point and skew stay fixed). Default
        /// true.
        refine_intrinsics: bool = true,
    }
}

/// `optimize.bundle_adjust`. See [`super::ba`].
pub struct BundleAdjust {
    options: BaOptions,
    mode: Mode,
    fix_first_camera: bool,
    refine_intrinsics: bool,
}

impl Op for BundleAdjust {
    type Params = BundleAdjustParams;
    const ID: &'static str = "optimize.bundle_adjust";
    const SUMMARY: &'static str =
        "Refines the cameras and points of a reconstruction by sparse bundle adjustment.";
    const DOC: &'static str = r#"
Minimizes the reprojection cost ½ Σ ρ(‖π(camera, X) − x‖²) (pixels², the BAL / Ceres convention)
over the poses, the camera parameters (principal point and skew fixed) and the 3-D points of a
reconstruction. Cameras SIMPLE_PINHOLE, SIMPLE_RADIAL or RADIAL (f, k1, k2), one per image, take
the fast path below, where points behind a camera keep their residual (BAL's cost; COLMAP
zeroes them). Any other model (PINHOLE, OPENCV, FULL_OPENCV with skew, OPENCV_FISHEYE) or
intrinsics shared by several images are adjusted by the general sparse solver (parameter
blocks with SO(3) rotations, analytic Jacobians of each model, Cholesky of the normal
equations: "dense_schur" selects the dense factorization, "sparse_schur" / "iterative_schur"
the sparse one, "auto" by size); there, observations of points behind a pinhole camera at the
start are left out (counted in the report's observations_not_visible) and a step that moves a
point behind a camera is rejected.

Method: Levenberg–Marquardt with Ceres' trust-region strategy (Jacobi-scaled LM diagonal,
initial radius 1e4, gain-ratio update after Nielsen) on analytic Jacobians; rotations on SO(3)
(left increments); the points are eliminated by the Schur complement, and the reduced camera
system is solved by dense Cholesky (≤ 16 cameras in "auto"), sparse Cholesky (faer; beyond
16 cameras while one factorization stays under 3e10 flops) or block-Jacobi preconditioned conjugate gradients. Robust
losses use Triggs' correction as Ceres does. Stopping rules are Ceres' (function, gradient and parameter tolerance, iteration limit; the iteration count
includes iteration 0). Jacobians and Schur products run in parallel over fixed-size chunks with
ordered sums, so the result is the same for any thread count.

Outputs the refined reconstruction (each point's error_px = its mean reprojection error), a
report (initial_cost, final_cost, iterations, successful_steps, unsuccessful_steps,
reprojection_rms_px = √(Σ‖r‖²/n) over observations, initial_reprojection_rms_px, termination:
0 function tol., 1 gradient tol., 2 parameter tol., 3 iteration limit, 4 collapsed trust region,
5 nothing to do; cameras, points, observations, dense_solver 1/0) and the per-iteration
history as Metrics: for iteration i, zero-padded to five digits (00000 is the start), the keys
i.cost, i.step_norm, i.trust_radius, i.accepted (1/0), i.time_s (seconds since the start) and
i.cg_iterations.

Reference: Triggs et al., "Bundle adjustment — a modern synthesis" (1999); Agarwal et al.,
"Bundle adjustment in the large" (ECCV 2010); Ceres Solver (TrustRegionMinimizer, SchurComplement).

Example:
    "ba": (op: "optimize.bundle_adjust", inputs: { "reconstruction": "problem.reconstruction" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "reconstruction",
            PortType::Reconstruction,
            "Cameras, posed images and points with their observations.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "The refined reconstruction.",
            ),
            PortSpec::new(
                "report",
                PortType::Metrics,
                "Costs, iterations, RMS, termination.",
            ),
            PortSpec::new(
                "history",
                PortType::Metrics,
                "Per iteration i (00000 = the start): i.cost, i.step_norm, i.trust_radius, \
                 i.accepted, i.time_s, i.cg_iterations.",
            ),
        ]
    }

    fn new(p: BundleAdjustParams) -> Result<Self, String> {
        if !(1..=10_000).contains(&p.max_iterations) {
            return Err(format!(
                "`max_iterations` must be 1..=10000, got {}",
                p.max_iterations
            ));
        }
        for (name, v) in [
            ("function_tolerance", p.function_tolerance),
            ("gradient_tolerance", p.gradient_tolerance),
            ("parameter_tolerance", p.parameter_tolerance),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
            }
        }
        if !p.loss_scale_px.is_finite() || p.loss_scale_px <= 0.0 {
            return Err(format!(
                "`loss_scale_px` must be finite and > 0, got {}",
                p.loss_scale_px
            ));
        }
        let a = p.loss_scale_px;
        let loss = match p.loss {
            LossChoice::None => RobustLoss::Trivial,
            LossChoice::Huber => RobustLoss::Huber(a),
            LossChoice::Cauchy => RobustLoss::Cauchy(a),
            LossChoice::SoftL1 => RobustLoss::SoftL1(a),
            LossChoice::Tukey => RobustLoss::Tukey(a),
        };
        let linear_solver = match p.linear_solver {
            SolverChoice::Auto => LinearSolver::Auto,
            SolverChoice::DenseSchur => LinearSolver::DenseSchur,
            SolverChoice::IterativeSchur => LinearSolver::IterativeSchur,
            SolverChoice::SparseSchur => LinearSolver::SparseSchur,
        };
        let mode = match p.mode {
            ModeChoice::Full => Mode::Full,
            ModeChoice::MotionOnly => Mode::MotionOnly,
            ModeChoice::StructureOnly => Mode::StructureOnly,
        };
        Ok(BundleAdjust {
            options: BaOptions {
                max_iterations: p.max_iterations as usize,
                function_tolerance: p.function_tolerance,
                gradient_tolerance: p.gradient_tolerance,
                parameter_tolerance: p.parameter_tolerance,
                linear_solver,
                loss,
                ..BaOptions::default()
            },
            mode,
            fix_first_camera: p.fix_first_camera,
            refine_intrinsics: p.refine_intrinsics,
        })
    }
}

/// Report metrics of a solve.
pub fn report(summary: &BaSummary, problem: &BaProblem, initial_rms: f64) -> Metrics {
    let n = problem.observations.len();
    let rms = if n > 0 {
        (squared_errors(problem).iter().sum::<f64>() / n as f64).sqrt()
    } else {
        0.0
    };
    let mut m = totals_metrics(&SolveTotals {
        initial_cost: summary.initial_cost,
        final_cost: summary.final_cost,
        iterations: summary.iterations,
        successful_steps: summary.successful_steps,
        unsuccessful_steps: summary.unsuccessful_steps,
        termination: summary.termination,
        dense_solver: summary.linear_solver == LinearSolver::DenseSchur,
    });
    m.insert("reprojection_rms_px".into(), rms);
    m.insert("initial_reprojection_rms_px".into(), initial_rms);
    m.insert("cameras".into(), problem.cameras.len() as f64);
    m.insert("points".into(), problem.points.len() as f64);
    m.insert("observations".into(), n as f64);
    m
}

/// True when the reconstruction needs the general solver ([`super::bundle_general`]): a camera
/// model outside the BAL family (`SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`), or intrinsics
/// to refine that several images share. A missing camera stays on the fast path, which reports
/// it.
pub fn needs_general_solver(rec: &Reconstruction, refine_intrinsics: bool) -> bool {
    let mut uses: HashMap<u32, usize> = HashMap::new();
    for im in &rec.images {
        *uses.entry(im.camera_id).or_default() += 1;
    }
    uses.iter().any(|(id, &n)| {
        rec.cameras.get(id).is_some_and(|c| {
            !matches!(
                c.model,
                CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial
            ) || (refine_intrinsics && n > 1)
        })
    })
}

/// Bundle-adjusts a reconstruction: the refined reconstruction, the report and the history.
/// The BAL family with one camera per image goes to the Schur-complement adjuster of
/// [`super::ba`], every other reconstruction to [`super::bundle_general`].
pub fn bundle_adjust(
    rec: &Reconstruction,
    options: &BaOptions,
    mode: Mode,
    refine_intrinsics: bool,
    fix_first_camera: bool,
) -> Result<(Reconstruction, Metrics, Metrics), String> {
    if needs_general_solver(rec, refine_intrinsics) {
        let general = GeneralBaOptions {
            solver: SolverOptions {
                max_iterations: options.max_iterations,
                function_tolerance: options.function_tolerance,
                gradient_tolerance: options.gradient_tolerance,
                parameter_tolerance: options.parameter_tolerance,
                linear_solver: match options.linear_solver {
                    LinearSolver::Auto => LinearSolverType::Auto,
                    LinearSolver::DenseSchur => LinearSolverType::DenseCholesky,
                    _ => LinearSolverType::SparseCholesky,
                },
                initial_trust_region_radius: options.initial_trust_region_radius,
                ..SolverOptions::default()
            },
            loss: options.loss,
            mode,
            refine_intrinsics,
            fix_first_camera,
        };
        return bundle_adjust_general(rec, &general);
    }
    let (mut problem, _) =
        problem_from_reconstruction(rec, mode, refine_intrinsics, fix_first_camera)?;
    let n = problem.observations.len();
    let initial_rms = if n > 0 {
        (squared_errors(&problem).iter().sum::<f64>() / n as f64).sqrt()
    } else {
        0.0
    };
    let summary = solve(&mut problem, options)?;
    let refined = apply_to_reconstruction(rec, &problem);
    Ok((
        refined,
        report(&summary, &problem, initial_rms),
        history_metrics(&summary.history),
    ))
}

impl Operator for BundleAdjust {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let rec = match inputs.require("reconstruction")? {
            Value::Reconstruction(r) => r,
            _ => {
                return Err(OpError::input(
                    "reconstruction",
                    "expected a Reconstruction",
                ));
            }
        };
        let (refined, metrics, history) = bundle_adjust(
            rec,
            &self.options,
            self.mode,
            self.refine_intrinsics,
            self.fix_first_camera,
        )
        .map_err(|e| OpError::input("reconstruction", e))?;
        Ok(Outputs::new()
            .with("reconstruction", Value::Reconstruction(Arc::new(refined)))
            .with("report", Value::metrics(metrics))
            .with("history", Value::metrics(history)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::ba::problem_cost;
    use crate::optimize::synthetic::{SyntheticOptions, synthetic_problem};

    fn scene() -> (BaProblem, Reconstruction) {
        let (_, start) = synthetic_problem(&SyntheticOptions {
            cameras: 5,
            points: 60,
            seed: 31,
            ..SyntheticOptions::default()
        })
        .unwrap();
        let rec = problem_to_reconstruction(&start, [640, 480]);
        (start, rec)
    }

    #[test]
    fn reconstruction_round_trip_keeps_the_cost() {
        let (start, rec) = scene();
        let (p, index) = problem_from_reconstruction(&rec, Mode::Full, true, false).unwrap();
        assert_eq!(p.observations.len(), start.observations.len());
        assert_eq!(index.keypoints.len(), p.observations.len());
        let (a, b) = (
            problem_cost(&p, RobustLoss::Trivial).unwrap(),
            problem_cost(&start, RobustLoss::Trivial).unwrap(),
        );
        assert!((a - b).abs() <= 1e-9 * b, "{a} vs {b}");
    }

    #[test]
    fn operator_modes() {
        let (_, rec) = scene();
        let run = |params: BundleAdjustParams| {
            let op = BundleAdjust::new(params).unwrap();
            bundle_adjust(
                &rec,
                &op.options,
                op.mode,
                op.refine_intrinsics,
                op.fix_first_camera,
            )
            .unwrap()
        };
        let (full, report, history) = run(BundleAdjustParams::default());
        assert!(report["final_cost"] < 0.01 * report["initial_cost"]);
        assert!(report["reprojection_rms_px"] < 1.0);
        assert_eq!(
            history.keys().filter(|k| k.ends_with(".cost")).count() as f64,
            report["iterations"]
        );
        assert_eq!(report["dense_solver"], 1.0);
        assert!(full.points[0].error_px > 0.0);
        let (motion, report_m, _) = run(BundleAdjustParams {
            mode: ModeChoice::MotionOnly,
            ..BundleAdjustParams::default()
        });
        assert_eq!(
            motion.points,
            rec.points
                .iter()
                .zip(&motion.points)
                .map(|(a, b)| {
                    ReconPoint {
                        error_px: b.error_px,
                        ..a.clone()
                    }
                })
                .collect::<Vec<_>>()
        );
        assert!(report_m["final_cost"] < report_m["initial_cost"]);
        let (structure, _, _) = run(BundleAdjustParams {
            mode: ModeChoice::StructureOnly,
            ..BundleAdjustParams::default()
        });
        assert_eq!(structure.cameras, rec.cameras);
        for (a, b) in structure.images.iter().zip(&rec.images) {
            // Poses go through a rotation matrix and back.
            for (x, y) in a
                .camera_from_world
                .rotation
                .iter()
                .zip(&b.camera_from_world.rotation)
            {
                assert!((x - y).abs() < 1e-14);
            }
        }
        let (gauge, _, _) = run(BundleAdjustParams {
            fix_first_camera: true,
            refine_intrinsics: false,
            loss: LossChoice::Cauchy,
            linear_solver: SolverChoice::IterativeSchur,
            ..BundleAdjustParams::default()
        });
        assert_eq!(gauge.cameras, rec.cameras);
        assert_eq!(
            gauge.images[0].camera_from_world.translation,
            rec.images[0].camera_from_world.translation
        );
    }

    #[test]
    fn unsupported_inputs_are_errors() {
        let (_, mut rec) = scene();
        rec.cameras.get_mut(&1).unwrap().model = CameraModel::OpenCv;
        assert!(problem_from_reconstruction(&rec, Mode::Full, true, false).is_err());
        let (_, mut rec) = scene();
        rec.images[1].camera_id = 1;
        let err = problem_from_reconstruction(&rec, Mode::Full, true, false).unwrap_err();
        assert!(err.contains("shared"), "{err}");
        assert!(problem_from_reconstruction(&rec, Mode::Full, false, false).is_ok());
        let (_, mut rec) = scene();
        rec.images[0].points2d[0].1 = Some(9999);
        assert!(problem_from_reconstruction(&rec, Mode::Full, true, false).is_err());
        for bad in [
            BundleAdjustParams {
                max_iterations: 0,
                ..BundleAdjustParams::default()
            },
            BundleAdjustParams {
                loss_scale_px: 0.0,
                ..BundleAdjustParams::default()
            },
            BundleAdjustParams {
                function_tolerance: f64::NAN,
                ..BundleAdjustParams::default()
            },
        ] {
            assert!(BundleAdjust::new(bad).is_err());
        }
    }
}
