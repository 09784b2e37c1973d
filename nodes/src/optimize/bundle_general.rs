//! Bundle adjustment of reconstructions with any engine camera model, on the general sparse
//! least-squares solver of [`super::nlls`].
//!
//! [`super::bundle_adjust`] sends the BAL family (`SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`
//! with one camera per image) to the specialised Schur-complement adjuster of [`super::ba`];
//! everything else comes here: `PINHOLE`, `OPENCV`, `FULL_OPENCV` (radial–tangential with
//! skew), `OPENCV_FISHEYE`, and cameras whose intrinsics several images share.
//!
//! Parameter blocks: per image a rotation (angle-axis on SO(3), left increments as in
//! [`super::ba`]) and a translation (`camera_from_world`); per camera its parameters in the
//! model's order, with the principal point and the skew held constant (a
//! [`SubsetManifold`]), or all constant without `refine_intrinsics`; per observed point its
//! position. One residual block per observation, `π(camera, R X + t) − x` in pixels, with
//! analytic Jacobians from [`super::camera_model`]. Observations the model cannot see at the
//! start (a point behind a pinhole camera) are left out of the problem and counted in the
//! report; a trial step that moves a point behind a camera it is observed by is rejected.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use ocellus_engine::value::{CameraModel, Metrics, Pose, Reconstruction};

use super::bundle_adjust::Mode;
use super::camera_model::project;
use super::loss::RobustLoss;
use super::manifold::{AngleAxisManifold, SubsetManifold};
use super::nlls::{BlockId, CostFunction, LinearSolverType, Problem, SolverOptions, Summary};
use super::solve_report::{SolveTotals, history_metrics, totals_metrics};
use crate::geometry::pose_util::{angle_axis, rodrigues, skew};

/// Settings of [`bundle_adjust_general`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeneralBaOptions {
    /// Solver settings.
    pub solver: SolverOptions,
    /// Robust loss on each observation's squared reprojection error.
    pub loss: RobustLoss,
    /// Which blocks are refined.
    pub mode: Mode,
    /// Refine the camera parameters other than the principal point and skew.
    pub refine_intrinsics: bool,
    /// Hold the first image's pose and its camera's parameters constant.
    pub fix_first_camera: bool,
}

/// The left Jacobian of SO(3), `J_l(φ) = I + (1 − cos θ)/θ² [φ]× + (θ − sin θ)/θ³ [φ]×²`:
/// `exp([φ + dφ]×) ≈ exp([J_l(φ) dφ]×) exp([φ]×)`.
fn so3_left_jacobian(phi: [f64; 3]) -> nalgebra::Matrix3<f64> {
    let v = nalgebra::Vector3::new(phi[0], phi[1], phi[2]);
    let t2 = v.norm_squared();
    let theta = t2.sqrt();
    let (a, b) = if theta < 1e-4 {
        (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        (
            (1.0 - theta.cos()) / t2,
            (theta - theta.sin()) / (t2 * theta),
        )
    };
    let k = skew(&v);
    nalgebra::Matrix3::identity() + k * a + k * k * b
}

/// The reprojection residual of one observation: blocks `[rotation (angle-axis, 3),
/// translation (3), camera parameters (model's count), point (3)]`, 2 residuals in pixels.
pub struct ReprojectionCost {
    model: CameraModel,
    observed: [f64; 2],
    sizes: [usize; 4],
}

impl ReprojectionCost {
    /// The residual of `model` observing a point at pixel `observed`.
    pub fn new(model: CameraModel, observed: [f64; 2]) -> ReprojectionCost {
        ReprojectionCost {
            model,
            observed,
            sizes: [3, 3, model.param_count(), 3],
        }
    }
}

impl CostFunction for ReprojectionCost {
    fn num_residuals(&self) -> usize {
        2
    }

    fn parameter_block_sizes(&self) -> &[usize] {
        &self.sizes
    }

    fn evaluate(
        &self,
        parameters: &[&[f64]],
        residuals: &mut [f64],
        jacobians: Option<&mut [Option<&mut [f64]>]>,
    ) -> bool {
        let (w, t, intrinsics, x) = (parameters[0], parameters[1], parameters[2], parameters[3]);
        let r = rodrigues([w[0], w[1], w[2]]);
        let world = nalgebra::Vector3::new(x[0], x[1], x[2]);
        let rx = r * world;
        let p = [rx.x + t[0], rx.y + t[1], rx.z + t[2]];
        let Some(proj) = project(self.model, intrinsics, p) else {
            return false;
        };
        residuals[0] = proj.pixel[0] - self.observed[0];
        residuals[1] = proj.pixel[1] - self.observed[1];
        let Some(jacobians) = jacobians else {
            return true;
        };
        let dp = nalgebra::Matrix2x3::from_row_slice(&proj.d_point);
        if let Some(j) = jacobians[0].as_deref_mut() {
            // ∂P/∂φ = −[R X]× J_l(φ).
            let d = dp * (-skew(&rx)) * so3_left_jacobian([w[0], w[1], w[2]]);
            for row in 0..2 {
                for col in 0..3 {
                    j[3 * row + col] = d[(row, col)];
                }
            }
        }
        if let Some(j) = jacobians[1].as_deref_mut() {
            j[..6].copy_from_slice(&proj.d_point);
        }
        if let Some(j) = jacobians[2].as_deref_mut() {
            let n = self.sizes[2];
            j[..2 * n].copy_from_slice(&proj.d_params[..2 * n]);
        }
        if let Some(j) = jacobians[3].as_deref_mut() {
            let d = dp * r;
            for row in 0..2 {
                for col in 0..3 {
                    j[3 * row + col] = d[(row, col)];
                }
            }
        }
        true
    }
}

/// Indices of the principal point and skew in a model's parameters (held constant).
fn constant_intrinsics(model: CameraModel) -> &'static [usize] {
    match model {
        CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial => &[1, 2],
        CameraModel::Pinhole | CameraModel::OpenCv => &[2, 3],
        CameraModel::RadialTangential | CameraModel::Fisheye => &[2, 3, 4],
    }
}

/// Squared reprojection errors of the observations the model sees, per point.
fn point_errors(rec: &Reconstruction) -> (Vec<f64>, Vec<usize>, f64, usize) {
    let index: HashMap<u64, usize> = rec
        .points
        .iter()
        .enumerate()
        .map(|(j, p)| (p.id, j))
        .collect();
    let mut sum = vec![0.0; rec.points.len()];
    let mut count = vec![0usize; rec.points.len()];
    let (mut sq, mut n) = (0.0, 0usize);
    for im in &rec.images {
        let Some(cam) = rec.cameras.get(&im.camera_id) else {
            continue;
        };
        let r = im.camera_from_world.rotation_matrix();
        let t = im.camera_from_world.translation;
        for (xy, id) in &im.points2d {
            let Some(j) = id.and_then(|id| index.get(&id).copied()) else {
                continue;
            };
            let x = rec.points[j].position;
            let p = camera_point(&r, &t, &x);
            if let Some(proj) = project(cam.model, &cam.params, p) {
                let e2 = (proj.pixel[0] - xy[0]).powi(2) + (proj.pixel[1] - xy[1]).powi(2);
                sum[j] += e2.sqrt();
                count[j] += 1;
                sq += e2;
                n += 1;
            }
        }
    }
    (sum, count, sq, n)
}

/// `R X + t` for a row-major `R`.
fn camera_point(r: &[f64; 9], t: &[f64; 3], x: &[f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| r[3 * i] * x[0] + r[3 * i + 1] * x[1] + r[3 * i + 2] * x[2] + t[i])
}

fn rms(sq: f64, n: usize) -> f64 {
    if n > 0 { (sq / n as f64).sqrt() } else { 0.0 }
}

/// Bundle-adjusts a reconstruction of any camera models: the refined reconstruction, the
/// report (the keys of [`super::bundle_adjust::report`], plus `observations_not_visible`) and
/// the history ([`history_metrics`]).
pub fn bundle_adjust_general(
    rec: &Reconstruction,
    options: &GeneralBaOptions,
) -> Result<(Reconstruction, Metrics, Metrics), String> {
    let mut problem = Problem::new();
    // Cameras, in id order (BTreeMap) so the problem's layout is deterministic.
    let used: BTreeMap<u32, ()> = rec.images.iter().map(|im| (im.camera_id, ())).collect();
    let first_camera = rec.images.first().map(|im| im.camera_id);
    let mut camera_blocks: HashMap<u32, BlockId> = HashMap::new();
    for &id in used.keys() {
        let cam = rec
            .cameras
            .get(&id)
            .ok_or_else(|| format!("an image refers to missing camera {id}"))?;
        if cam.params.len() != cam.model.param_count() {
            return Err(format!(
                "{} camera {id} has {} parameters, expected {}",
                cam.model.colmap_name(),
                cam.params.len(),
                cam.model.param_count()
            ));
        }
        if !cam.params.iter().all(|v| v.is_finite()) {
            return Err(format!("camera {id} has non-finite parameters"));
        }
        let block = problem.add_parameter_block(&cam.params);
        let fixed = !options.refine_intrinsics
            || options.mode == Mode::StructureOnly
            || (options.fix_first_camera && first_camera == Some(id));
        if fixed {
            problem.set_constant(block).map_err(|e| e.to_string())?;
        } else {
            let manifold = SubsetManifold::new(cam.params.len(), constant_intrinsics(cam.model))
                .ok_or_else(|| "internal: bad intrinsics subset".to_string())?;
            problem
                .set_manifold(block, Arc::new(manifold))
                .map_err(|e| e.to_string())?;
        }
        camera_blocks.insert(id, block);
    }
    let mut pose_blocks = Vec::with_capacity(rec.images.len());
    for (k, im) in rec.images.iter().enumerate() {
        let pose = &im.camera_from_world;
        if !pose
            .rotation
            .iter()
            .chain(&pose.translation)
            .all(|v| v.is_finite())
        {
            return Err(format!("image {} has a non-finite pose", im.id));
        }
        let rm = pose.rotation_matrix();
        let r = nalgebra::Matrix3::from_row_slice(&rm);
        let w = problem.add_parameter_block(&angle_axis(&r));
        let t = problem.add_parameter_block(&pose.translation);
        problem
            .set_manifold(w, Arc::new(AngleAxisManifold))
            .map_err(|e| e.to_string())?;
        if options.mode == Mode::StructureOnly || (options.fix_first_camera && k == 0) {
            problem.set_constant(w).map_err(|e| e.to_string())?;
            problem.set_constant(t).map_err(|e| e.to_string())?;
        }
        pose_blocks.push((w, t));
    }
    let mut point_index: HashMap<u64, usize> = HashMap::with_capacity(rec.points.len());
    for (j, p) in rec.points.iter().enumerate() {
        if point_index.insert(p.id, j).is_some() {
            return Err(format!("point id {} appears twice", p.id));
        }
        if !p.position.iter().all(|v| v.is_finite()) {
            return Err(format!("point {} has a non-finite position", p.id));
        }
    }
    let mut point_blocks: Vec<Option<BlockId>> = vec![None; rec.points.len()];
    let mut not_visible = 0usize;
    for (k, im) in rec.images.iter().enumerate() {
        let cam = &rec.cameras[&im.camera_id];
        let r = im.camera_from_world.rotation_matrix();
        let t = im.camera_from_world.translation;
        for (xy, id) in &im.points2d {
            let Some(id) = id else { continue };
            let j = *point_index
                .get(id)
                .ok_or_else(|| format!("image {} observes missing point {id}", im.id))?;
            if !xy.iter().all(|v| v.is_finite()) {
                return Err(format!("image {} has a non-finite keypoint", im.id));
            }
            let x = rec.points[j].position;
            let p = camera_point(&r, &t, &x);
            if project(cam.model, &cam.params, p).is_none() {
                not_visible += 1;
                continue;
            }
            let point_block = match point_blocks[j] {
                Some(b) => b,
                None => {
                    let b = problem.add_parameter_block(&x);
                    if options.mode == Mode::MotionOnly {
                        problem.set_constant(b).map_err(|e| e.to_string())?;
                    }
                    point_blocks[j] = Some(b);
                    b
                }
            };
            let (w, tb) = pose_blocks[k];
            problem
                .add_residual_block(
                    Arc::new(ReprojectionCost::new(cam.model, *xy)),
                    options.loss,
                    &[w, tb, camera_blocks[&im.camera_id], point_block],
                )
                .map_err(|e| e.to_string())?;
        }
    }
    let (_, _, sq0, n0) = point_errors(rec);
    let summary: Summary = problem.solve(&options.solver).map_err(|e| e.to_string())?;
    // Write back.
    let mut out = rec.clone();
    for (&id, &block) in &camera_blocks {
        if let Some(c) = out.cameras.get_mut(&id) {
            c.params = problem
                .parameters(block)
                .map_err(|e| e.to_string())?
                .to_vec();
        }
    }
    for (im, &(w, t)) in out.images.iter_mut().zip(&pose_blocks) {
        if problem.is_constant(w).map_err(|e| e.to_string())? {
            // Held fixed: keep the input pose bit for bit (no angle-axis round trip).
            continue;
        }
        let w = problem.parameters(w).map_err(|e| e.to_string())?;
        let t = problem.parameters(t).map_err(|e| e.to_string())?;
        let r = rodrigues([w[0], w[1], w[2]]);
        let mut rm = [0.0; 9];
        for a in 0..3 {
            for b in 0..3 {
                rm[3 * a + b] = r[(a, b)];
            }
        }
        im.camera_from_world = Pose::from_rotation_matrix(&rm, [t[0], t[1], t[2]]);
    }
    for (p, block) in out.points.iter_mut().zip(&point_blocks) {
        if let Some(b) = block {
            let x = problem.parameters(*b).map_err(|e| e.to_string())?;
            p.position = [x[0], x[1], x[2]];
        }
    }
    let (sum, count, sq, n) = point_errors(&out);
    for ((p, s), c) in out.points.iter_mut().zip(&sum).zip(&count) {
        p.error_px = if *c > 0 { s / *c as f64 } else { 0.0 };
    }
    let mut m = totals_metrics(&SolveTotals {
        initial_cost: summary.initial_cost,
        final_cost: summary.final_cost,
        iterations: summary.iterations,
        successful_steps: summary.successful_steps,
        unsuccessful_steps: summary.unsuccessful_steps,
        termination: summary.termination,
        dense_solver: summary.linear_solver == LinearSolverType::DenseCholesky,
    });
    m.insert("reprojection_rms_px".into(), rms(sq, n));
    m.insert("initial_reprojection_rms_px".into(), rms(sq0, n0));
    m.insert("cameras".into(), rec.images.len() as f64);
    m.insert("points".into(), rec.points.len() as f64);
    m.insert("observations".into(), problem.num_residual_blocks() as f64);
    m.insert("observations_not_visible".into(), not_visible as f64);
    Ok((out, m, history_metrics(&summary.history)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::bundle_adjust::problem_to_reconstruction;
    use crate::optimize::synthetic::{SyntheticOptions, synthetic_problem};
    use ocellus_engine::value::Camera;

    /// Ground-truth reconstruction of the synthetic scene re-expressed with `model` cameras
    /// (one shared camera when `shared`), observations re-rendered through the model, plus a
    /// perturbed start.
    fn scene(model: CameraModel, params: &[f64], shared: bool) -> (Reconstruction, Reconstruction) {
        let (truth, _) = synthetic_problem(&SyntheticOptions {
            cameras: 6,
            points: 80,
            seed: 7,
            ..SyntheticOptions::default()
        })
        .unwrap();
        let mut rec = problem_to_reconstruction(&truth, [640, 480]);
        let ids: Vec<u32> = rec.cameras.keys().copied().collect();
        for id in ids {
            rec.cameras.insert(
                id,
                Camera {
                    model,
                    width: 640,
                    height: 480,
                    params: params.to_vec(),
                },
            );
        }
        if shared {
            for im in &mut rec.images {
                im.camera_id = 1;
            }
        }
        // Re-render the observations through the model.
        let positions: HashMap<u64, [f64; 3]> =
            rec.points.iter().map(|p| (p.id, p.position)).collect();
        for im in &mut rec.images {
            let r = im.camera_from_world.rotation_matrix();
            let t = im.camera_from_world.translation;
            for (xy, id) in &mut im.points2d {
                let x = positions[&id.unwrap()];
                let p = camera_point(&r, &t, &x);
                *xy = project(model, params, p).unwrap().pixel;
            }
        }
        let mut start = rec.clone();
        let mut s = 12345u64;
        let mut noise = |scale: f64| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * scale
        };
        for p in &mut start.points {
            for v in &mut p.position {
                *v += noise(0.05);
            }
        }
        for im in start.images.iter_mut().skip(1) {
            for v in &mut im.camera_from_world.translation {
                *v += noise(0.02);
            }
        }
        // Perturb the focal length of every camera but the first image's (held fixed with
        // `fix_first_camera`), or of the one shared camera.
        let first = start.images[0].camera_id;
        for (&id, c) in start.cameras.iter_mut() {
            if shared || id != first {
                c.params[0] *= 1.02;
            }
        }
        (rec, start)
    }

    fn options() -> GeneralBaOptions {
        GeneralBaOptions {
            solver: SolverOptions {
                function_tolerance: 1e-12,
                gradient_tolerance: 1e-14,
                parameter_tolerance: 1e-12,
                max_iterations: 200,
                ..SolverOptions::default()
            },
            loss: RobustLoss::Trivial,
            mode: Mode::Full,
            refine_intrinsics: true,
            fix_first_camera: true,
        }
    }

    #[test]
    fn reprojection_jacobians_match_central_differences() {
        let model = CameraModel::RadialTangential;
        let intr = [
            800.0, 790.0, 320.0, 240.0, 0.3, -0.2, 0.05, 1e-3, -2e-3, 0.01,
        ];
        let cost = ReprojectionCost::new(model, [300.0, 200.0]);
        let blocks: [Vec<f64>; 4] = [
            vec![0.3, -0.2, 0.1],
            vec![0.1, 0.2, 3.0],
            intr.to_vec(),
            vec![0.4, -0.3, 1.0],
        ];
        let params: Vec<&[f64]> = blocks.iter().map(Vec::as_slice).collect();
        let mut jac: Vec<Vec<f64>> = blocks.iter().map(|b| vec![0.0; 2 * b.len()]).collect();
        let mut r = [0.0; 2];
        {
            let mut views: Vec<Option<&mut [f64]>> =
                jac.iter_mut().map(|j| Some(j.as_mut_slice())).collect();
            assert!(cost.evaluate(&params, &mut r, Some(&mut views)));
        }
        for b in 0..4 {
            for k in 0..blocks[b].len() {
                let h = 1e-6 * blocks[b][k].abs().max(1e-2);
                let eval = |d: f64| {
                    let mut moved = blocks.clone();
                    moved[b][k] += d;
                    let p: Vec<&[f64]> = moved.iter().map(Vec::as_slice).collect();
                    let mut out = [0.0; 2];
                    assert!(cost.evaluate(&p, &mut out, None));
                    out
                };
                let (a, c) = (eval(h), eval(-h));
                let n = blocks[b].len();
                for row in 0..2 {
                    let fd = (a[row] - c[row]) / (2.0 * h);
                    let an = jac[b][row * n + k];
                    assert!(
                        (fd - an).abs() <= 1e-5 * (1.0 + an.abs()),
                        "block {b} coord {k} row {row}: {an} vs {fd}"
                    );
                }
            }
        }
    }

    #[test]
    fn recovers_exact_scenes_for_every_model_and_shared_intrinsics() {
        let cases: [(CameraModel, &[f64]); 4] = [
            (CameraModel::Pinhole, &[500.0, 505.0, 320.0, 240.0]),
            (
                CameraModel::OpenCv,
                &[500.0, 505.0, 320.0, 240.0, -0.1, 0.02, 1e-3, -1e-3],
            ),
            (
                CameraModel::RadialTangential,
                &[
                    500.0, 505.0, 320.0, 240.0, 0.0, -0.1, 0.02, 1e-3, -1e-3, 0.0,
                ],
            ),
            (
                CameraModel::Fisheye,
                &[400.0, 402.0, 320.0, 240.0, 0.0, 0.01, -0.005, 0.0, 0.0],
            ),
        ];
        for (model, params) in cases {
            for shared in [false, true] {
                let (truth, start) = scene(model, params, shared);
                let opts = GeneralBaOptions {
                    // A shared camera is the first image's too: leave the gauge free instead.
                    fix_first_camera: !shared,
                    ..options()
                };
                let (out, report, history) = bundle_adjust_general(&start, &opts).unwrap();
                assert!(
                    report["final_cost"] < 1e-12 * report["initial_cost"].max(1.0),
                    "{model:?} shared {shared}: {report:?}"
                );
                assert!(report["reprojection_rms_px"] < 1e-5, "{report:?}");
                assert_eq!(report["observations_not_visible"], 0.0);
                assert_eq!(
                    history.keys().filter(|k| k.ends_with(".cost")).count() as f64,
                    report["iterations"]
                );
                // The principal point (and skew) never move; focal lengths are recovered.
                let used: Vec<u32> = out.images.iter().map(|im| im.camera_id).collect();
                for (id, c) in out.cameras.iter().filter(|(id, _)| used.contains(id)) {
                    for &i in constant_intrinsics(model) {
                        assert_eq!(c.params[i], params[i]);
                    }
                    let f_true = truth.cameras[id].params[0];
                    assert!(
                        (c.params[0] - f_true).abs() < 1e-6 * f_true,
                        "{model:?} shared {shared}: f {} vs {f_true}",
                        c.params[0]
                    );
                }
                if !shared {
                    assert_eq!(
                        out.images[0].camera_from_world,
                        start.images[0].camera_from_world
                    );
                }
            }
        }
    }
}
