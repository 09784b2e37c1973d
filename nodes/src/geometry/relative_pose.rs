//! Calibrated two-view motion: `geometry.find_essential` (robust essential matrix and the
//! relative pose it implies) and `geometry.relative_pose` (chooses between a homography and an
//! essential matrix by GRIC and recovers the motion from the winner, or reports a pure
//! rotation).
//!
//! [`find_essential`] normalizes the pixels with the intrinsics (after undistorting them when the
//! camera has lens distortion), runs the shared robust loops of [`super::ransac`] over Nistér's
//! five-point [`EssentialEstimator`] with residuals in pixels, refines `E` on its inliers by
//! Levenberg–Marquardt over `(R, t)` (5 degrees of freedom) on the Sampson distance, and picks
//! the `(R, t)` candidate by the cheirality test of [`decompose_essential`].
//!
//! [`relative_pose`] fits both a homography and an essential matrix and compares them with
//! Torr's GRIC ([`gric`]); the simpler model wins unless the data clearly need the general one.

use nalgebra::{Matrix3, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Camera, Distortion, Metrics, Pose, Value};

use super::camera::{Lens, k_matrix, undistort_points};
use super::decompose::decompose_homography;
use super::essential::{
    EssentialEstimator, NormalizedPair, decompose_essential, depths_and_parallax,
    essential_candidates,
};
use super::homography::{Correspondence, HomographyEstimator};
use super::lm::{self, LmOptions, Problem};
use super::pose_util::{Intrinsics, input_points2, nearest_rotation, pose_from_rt, skew};
use super::ransac::{RobustOptions, estimate};
use super::robust::Estimator;
use super::two_view::{
    RobustMethod, TwoViewEstimate, check_robust, distinct_checked, find_homography, gric,
    h33_normalized, mask_value, matrix_value, msac, options, refine_rounds,
};

/// A calibrated view of the correspondences: pinhole intrinsics and the points in ideal
/// (undistorted) pixels of that pinhole camera.
#[derive(Debug, Clone, PartialEq)]
pub struct IdealPoints {
    /// Pinhole intrinsics.
    pub k: Intrinsics,
    /// Points in undistorted pixels (`K · normalized`).
    pub points: Vec<[f64; 2]>,
}

/// The pinhole part of `camera` and `points` undistorted into it. Errors on skew, invalid
/// intrinsics, non-finite points, or points the distortion model cannot invert.
pub fn ideal_points(camera: &Camera, points: &[[f64; 2]]) -> Result<IdealPoints, String> {
    let p = camera.intrinsics();
    if p.skew != 0.0 {
        return Err(format!(
            "camera has skew {}; a zero-skew camera is required",
            p.skew
        ));
    }
    let k = Intrinsics::new(p.fx, p.fy, p.cx, p.cy)?;
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err("non-finite point".into());
    }
    let distorted = match camera.distortion() {
        Distortion::None => false,
        Distortion::RadialTangential(d) => d.iter().any(|&v| v != 0.0),
        Distortion::Fisheye(_) => true,
    };
    if !distorted {
        return Ok(IdealPoints {
            k,
            points: points.to_vec(),
        });
    }
    let lens = Lens::from_camera(camera);
    let kk = k_matrix(&p);
    let ideal = undistort_points(&lens, points, None, Some(&kk));
    if let Some(i) = ideal.iter().position(|q| !q.iter().all(|v| v.is_finite())) {
        return Err(format!(
            "point {i} ({}, {}) cannot be undistorted (outside the lens model's valid field)",
            points[i][0], points[i][1]
        ));
    }
    Ok(IdealPoints { k, points: ideal })
}

/// A robustly estimated essential matrix and the relative pose it implies.
#[derive(Debug, Clone, PartialEq)]
pub struct EssentialEstimate {
    /// `E` (unit Frobenius norm), `x2ᵀ E x1 = 0` in normalized coordinates.
    pub e: Matrix3<f64>,
    /// Rotation camera2_from_camera1.
    pub r: Matrix3<f64>,
    /// Unit translation camera2_from_camera1.
    pub t: Vector3<f64>,
    /// Inliers of `E` (Sampson distance within the threshold).
    pub inlier_mask: Vec<bool>,
    /// Number of inliers.
    pub inliers: usize,
    /// Inliers that are in front of both cameras for `(r, t)` (any parallax).
    pub front_mask: Vec<bool>,
    /// Inliers voting for `(r, t)` in the cheirality test (parallax ≥ the minimum).
    pub points_in_front: usize,
    /// Votes of the runner-up candidate.
    pub runner_up: usize,
    /// Median parallax angle of the voting points, degrees.
    pub median_parallax_deg: f64,
    /// Robust-loop statistics, with `score` and `rms_px` of the final `E`.
    pub stats: TwoViewEstimate,
}

/// Sampson-distance refinement of `E = [t]× R` over `(R, t)`: state `R` (row-major, 9) and
/// unit `t` (3); steps are a rotation vector applied on the right and two coordinates in the
/// tangent plane of `t`.
struct EssentialProblem<'a> {
    data: &'a [NormalizedPair],
    focal: f64,
}

fn state_rt(x: &[f64]) -> (Matrix3<f64>, Vector3<f64>) {
    (
        Matrix3::from_row_slice(&x[..9]),
        Vector3::new(x[9], x[10], x[11]),
    )
}

fn tangent_basis(t: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let a = if t.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let b1 = t.cross(&a).normalize();
    let b2 = t.cross(&b1).normalize();
    (b1, b2)
}

impl Problem for EssentialProblem<'_> {
    fn num_params(&self) -> usize {
        5
    }
    fn num_residuals(&self) -> usize {
        self.data.len()
    }
    fn residuals(&self, x: &[f64], r: &mut [f64]) {
        let (rot, t) = state_rt(x);
        let e = skew(&t) * rot;
        for (ri, (a, b)) in r.iter_mut().zip(self.data) {
            let ex1 = e * Vector3::new(a[0], a[1], 1.0);
            let etx2 = e.transpose() * Vector3::new(b[0], b[1], 1.0);
            let c = b[0] * ex1.x + b[1] * ex1.y + ex1.z;
            let den = ex1.x * ex1.x + ex1.y * ex1.y + etx2.x * etx2.x + etx2.y * etx2.y;
            *ri = if den > 0.0 {
                self.focal * c / den.sqrt()
            } else {
                0.0
            };
        }
    }
    fn retract(&self, x: &[f64], delta: &[f64]) -> Vec<f64> {
        let (rot, t) = state_rt(x);
        let rot =
            rot * nalgebra::Rotation3::new(Vector3::new(delta[0], delta[1], delta[2])).into_inner();
        let (b1, b2) = tangent_basis(&t);
        let t = (t + b1 * delta[3] + b2 * delta[4]).normalize();
        let mut out: Vec<f64> = (0..9).map(|i| rot[(i / 3, i % 3)]).collect();
        out.extend_from_slice(t.as_slice());
        out
    }
}

/// Refines `e` by Levenberg–Marquardt on the Sampson distances (pixels, via `focal`) of `data`
/// (the inliers, normalized coordinates), staying on the essential manifold. Returns the refined
/// `E` (unit norm), or `e` unchanged when it cannot be refined (fewer than 6 data, rank < 2).
pub fn refine_essential(e: &Matrix3<f64>, data: &[NormalizedPair], focal: f64) -> Matrix3<f64> {
    if data.len() < 6 {
        return *e;
    }
    let Some(cands) = essential_candidates(e) else {
        return *e;
    };
    let (r0, t0) = cands[0];
    let mut x0: Vec<f64> = (0..9).map(|i| r0[(i / 3, i % 3)]).collect();
    x0.extend_from_slice(t0.as_slice());
    let problem = EssentialProblem { data, focal };
    let report = lm::levenberg_marquardt(
        &problem,
        &x0,
        &LmOptions {
            max_iterations: 50,
            ..LmOptions::default()
        },
    );
    let (r, t) = state_rt(&report.x);
    let Some(r) = nearest_rotation(&r) else {
        return *e;
    };
    let refined = skew(&t) * r;
    let n = refined.norm();
    if n.is_finite() && n > 0.0 {
        refined / n
    } else {
        *e
    }
}

/// Robust essential matrix from pixel correspondences `(x1, x2)` of two pinhole cameras `k1`,
/// `k2` (undistorted pixels). `options.threshold` is in pixels (Sampson distance scaled by the
/// geometric mean of the focal lengths). With `refine`, `E` is refined on its inliers in the
/// rounds of [`refine_rounds`], each kept only if it lowers the MSAC score. Exact repeats of a
/// correspondence count once in sampling and fitting
/// ([`super::two_view::distinct_correspondences`]). The pose is the cheirality winner among the
/// inliers, voting with parallax ≥ `min_parallax_deg`.
pub fn find_essential(
    data: &[Correspondence],
    k1: &Intrinsics,
    k2: &Intrinsics,
    options: &RobustOptions,
    refine: bool,
    min_parallax_deg: f64,
) -> Result<EssentialEstimate, String> {
    if let Some(i) = data
        .iter()
        .position(|c| !c.iter().flatten().all(|v| v.is_finite()))
    {
        return Err(format!("correspondence {i} is not finite"));
    }
    let normalize = |c: &Correspondence| -> NormalizedPair {
        (k1.normalize(c[0]).into(), k2.normalize(c[1]).into())
    };
    let distinct: Vec<NormalizedPair> = distinct_checked(data, EssentialEstimator::MIN_SAMPLES)
        .map_err(|e| e.to_string())?
        .iter()
        .map(normalize)
        .collect();
    let normalized: Vec<NormalizedPair> = data.iter().map(normalize).collect();
    let focal = (k1.focal() * k2.focal()).sqrt();
    let estimator = EssentialEstimator { focal_px: focal };
    let report = estimate(&estimator, &distinct, options).map_err(|e| e.to_string())?;
    let t2 = options.threshold * options.threshold;
    let (model, distinct_residuals, _, refined) = refine_rounds(
        &estimator,
        &distinct,
        report.model,
        t2,
        refine,
        |m, inliers| refine_essential(m, inliers, focal),
    );
    let distinct_inliers = distinct_residuals.iter().filter(|&&r| r <= t2).count();
    if distinct_inliers < EssentialEstimator::MIN_SAMPLES {
        return Err(format!(
            "the best essential matrix has {distinct_inliers} distinct inliers, fewer than a \
             minimal sample (5)"
        ));
    }
    let mut residuals = vec![0.0; normalized.len()];
    estimator.residuals(&model, &normalized, &mut residuals);
    let score = msac(&residuals, t2);
    let inlier_mask: Vec<bool> = residuals.iter().map(|&r| r <= t2).collect();
    let inliers = inlier_mask.iter().filter(|&&b| b).count();
    let (x1, x2): (Vec<[f64; 2]>, Vec<[f64; 2]>) = normalized
        .iter()
        .zip(&inlier_mask)
        .filter(|(_, m)| **m)
        .map(|(c, _)| *c)
        .unzip();
    let pose = decompose_essential(&model, &x1, &x2, min_parallax_deg)?;
    let front_mask: Vec<bool> = normalized
        .iter()
        .zip(&inlier_mask)
        .map(|((a, b), &m)| {
            m && matches!(depths_and_parallax(&pose.r, &pose.t, *a, *b),
                Some((z1, z2, _)) if z1 > 0.0 && z2 > 0.0)
        })
        .collect();
    let sum: f64 = residuals.iter().filter(|&&r| r <= t2).sum();
    // Sign convention: the E reported is the one of the chosen pose, `[t]× R`.
    let e = skew(&pose.t) * pose.r;
    let e = e / e.norm();
    Ok(EssentialEstimate {
        e,
        r: pose.r,
        t: pose.t,
        inlier_mask: inlier_mask.clone(),
        inliers,
        front_mask,
        points_in_front: pose.n_front,
        runner_up: pose.n_second,
        median_parallax_deg: pose.median_parallax_deg,
        stats: TwoViewEstimate {
            matrix: e,
            inlier_mask,
            inliers,
            trials: report.trials,
            improvements: report.history.len(),
            local_optimizations: report.local_optimizations,
            score,
            rms_px: (sum / inliers as f64).sqrt(),
            refined,
        },
    })
}

/// The model `geometry.relative_pose` chose.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionModel {
    /// General motion of a scene with depth: essential matrix.
    Essential,
    /// A plane seen under general motion: homography decomposed into `(R, t, n)`.
    Homography,
    /// Pure rotation (or a translation too small to see): `t = 0`.
    Rotation,
}

impl MotionModel {
    /// The name reported on the `model` port.
    pub fn name(self) -> &'static str {
        match self {
            MotionModel::Essential => "essential",
            MotionModel::Homography => "homography",
            MotionModel::Rotation => "rotation",
        }
    }
}

/// Options of [`relative_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct RelativePoseOptions {
    /// Robust options of the homography fit (threshold: symmetric transfer error, px).
    pub h: RobustOptions,
    /// Robust options of the essential fit (threshold: Sampson distance, px).
    pub e: RobustOptions,
    /// Point noise assumed by GRIC, px.
    pub sigma_px: f64,
    /// LM refinement of both models.
    pub refine: bool,
    /// Largest median reprojection error, px, of the homography inliers under the best pure
    /// rotation for the motion to count as a rotation.
    pub rotation_px: f64,
    /// Smallest parallax of a cheirality vote, degrees.
    pub min_parallax_deg: f64,
}

/// The recovered two-view motion.
#[derive(Debug, Clone, PartialEq)]
pub struct RelativePose {
    /// The winning model.
    pub model: MotionModel,
    /// Its matrix: `E` (unit norm) or the pixel homography (`h₃₃ = 1`).
    pub matrix: Matrix3<f64>,
    /// Rotation camera2_from_camera1.
    pub r: Matrix3<f64>,
    /// Translation camera2_from_camera1: unit, or zero for a rotation.
    pub t: Vector3<f64>,
    /// Correspondences supporting the pose: inliers of the model in front of both cameras
    /// (for a rotation: the homography inliers).
    pub mask: Vec<bool>,
    /// Statistics (see the operator's `report` port).
    pub report: Metrics,
}

/// Least-squares rotation `R` with `b2 ≈ R b1` for unit bearing pairs (Kabsch / Horn: SVD of
/// `Σ b2 b1ᵀ`).
pub fn rotation_between(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<Matrix3<f64>> {
    if pairs.len() < 2 {
        return None;
    }
    let m: Matrix3<f64> = pairs.iter().map(|(a, b)| b * a.transpose()).sum();
    nearest_rotation(&m)
}

fn bearing(k: &Intrinsics, p: [f64; 2]) -> Vector3<f64> {
    let n = k.normalize(p);
    Vector3::new(n.x, n.y, 1.0).normalize()
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Chooses the motion model for correspondences of two pinhole cameras (undistorted pixels) and
/// recovers the relative pose. See the `geometry.relative_pose` operator documentation.
pub fn relative_pose(
    data: &[Correspondence],
    k1: &Intrinsics,
    k2: &Intrinsics,
    o: &RelativePoseOptions,
) -> Result<RelativePose, String> {
    if let Some(i) = data
        .iter()
        .position(|c| !c.iter().flatten().all(|v| v.is_finite()))
    {
        return Err(format!("correspondence {i} is not finite"));
    }
    let n = data.len();
    let homography =
        find_homography(data, &o.h, o.refine).map_err(|e| format!("no homography: {e}"))?;
    let essential = find_essential(data, k1, k2, &o.e, o.refine, o.min_parallax_deg).ok();
    let mut hr = vec![0.0; n];
    HomographyEstimator.residuals(&homography.matrix, data, &mut hr);
    let h_errors: Vec<f64> = hr.iter().map(|e| 0.5 * e).collect();
    let gric_h = gric(&h_errors, o.sigma_px, 2.0, 8.0);
    let focal = (k1.focal() * k2.focal()).sqrt();
    let mut report = Metrics::new();
    report.insert("correspondences".into(), n as f64);
    report.insert("gric_h".into(), gric_h);
    report.insert("inliers_h".into(), homography.inliers as f64);
    let gric_e = match &essential {
        Some(est) => {
            let normalized: Vec<NormalizedPair> = data
                .iter()
                .map(|c| (k1.normalize(c[0]).into(), k2.normalize(c[1]).into()))
                .collect();
            let mut er = vec![0.0; n];
            EssentialEstimator { focal_px: focal }.residuals(&est.e, &normalized, &mut er);
            let transfer: Vec<f64> = hr
                .iter()
                .zip(&est.inlier_mask)
                .filter(|(_, m)| **m)
                .map(|(e, _)| e.sqrt())
                .collect();
            report.insert("parallax_px".into(), median(transfer));
            report.insert("inliers_e".into(), est.inliers as f64);
            gric(&er, o.sigma_px, 3.0, 5.0)
        }
        None => {
            report.insert("inliers_e".into(), 0.0);
            f64::INFINITY
        }
    };
    report.insert("gric_e".into(), gric_e);
    let count = |m: &[bool]| m.iter().filter(|&&b| b).count();
    if let Some(est) = essential.filter(|_| gric_e < gric_h) {
        report.insert("planar_or_rotation".into(), 0.0);
        report.insert("points_in_front".into(), count(&est.front_mask) as f64);
        report.insert("cheirality_votes".into(), est.points_in_front as f64);
        report.insert("cheirality_runner_up".into(), est.runner_up as f64);
        report.insert("median_parallax_deg".into(), est.median_parallax_deg);
        insert_stats(&mut report, &est.stats, o.e.threshold);
        return Ok(RelativePose {
            model: MotionModel::Essential,
            matrix: est.e,
            r: est.r,
            t: est.t,
            mask: est.front_mask,
            report,
        });
    }
    report.insert("planar_or_rotation".into(), 1.0);
    insert_stats(&mut report, &homography, o.h.threshold);
    let h_matrix = h33_normalized(&homography.matrix);
    // Pure rotation: the best rotation explains the homography inliers.
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = data
        .iter()
        .zip(&homography.inlier_mask)
        .filter(|(_, m)| **m)
        .map(|(c, _)| (bearing(k1, c[0]), bearing(k2, c[1])))
        .collect();
    let r_rot = rotation_between(&pairs).ok_or("homography inliers are degenerate")?;
    let rot_errors: Vec<f64> = data
        .iter()
        .zip(&homography.inlier_mask)
        .filter(|(_, m)| **m)
        .map(|(c, _)| {
            let q = r_rot * bearing(k1, c[0]);
            if q.z <= 0.0 {
                return f64::INFINITY;
            }
            let p = k2.project(&q);
            (p[0] - c[1][0]).hypot(p[1] - c[1][1])
        })
        .collect();
    let rot_median = median(rot_errors);
    report.insert("rotation_median_px".into(), rot_median);
    if rot_median <= o.rotation_px {
        report.insert("points_in_front".into(), 0.0);
        return Ok(RelativePose {
            model: MotionModel::Rotation,
            matrix: h_matrix,
            r: r_rot,
            t: Vector3::zeros(),
            mask: homography.inlier_mask.clone(),
            report,
        });
    }
    // Planar scene: decompose H, keep the candidate with the most homography inliers in front of
    // both cameras, then the best epipolar (MSAC) fit of all data (off-plane points decide
    // between the two physical solutions), then the normal facing camera 1 most.
    let sols = decompose_homography(&homography.matrix, k1, k2)?;
    let normalized: Vec<NormalizedPair> = data
        .iter()
        .map(|c| (k1.normalize(c[0]).into(), k2.normalize(c[1]).into()))
        .collect();
    let t2 = o.e.threshold * o.e.threshold;
    let mut best: Option<(usize, f64, f64, usize, Vec<bool>)> = None;
    for (i, s) in sols.iter().enumerate() {
        if s.t.norm() < 1e-12 {
            continue;
        }
        let n2 = s.r * s.n;
        let mask: Vec<bool> = normalized
            .iter()
            .zip(&homography.inlier_mask)
            .map(|((a, b), &m)| {
                m && s.n.dot(&Vector3::new(a[0], a[1], 1.0)) > 0.0
                    && n2.dot(&Vector3::new(b[0], b[1], 1.0)) > 0.0
            })
            .collect();
        let front = count(&mask);
        let e = skew(&s.t) * s.r;
        let mut r = vec![0.0; n];
        EssentialEstimator { focal_px: focal }.residuals(&(e / e.norm()), &normalized, &mut r);
        let score = msac(&r, t2);
        let better = match &best {
            None => true,
            Some((f, sc, nz, _, _)) => {
                front > *f || (front == *f && (score < *sc || (score == *sc && s.n.z > *nz)))
            }
        };
        if better {
            best = Some((front, score, s.n.z, i, mask));
        }
    }
    let Some((front, _, _, i, mask)) = best.filter(|b| b.0 > 0) else {
        return Err("no homography decomposition puts the points in front of both cameras".into());
    };
    let s = sols[i];
    let scale = s.t.norm();
    report.insert("points_in_front".into(), front as f64);
    report.insert("plane_distance".into(), 1.0 / scale);
    report.insert("plane_normal_z".into(), s.n.z);
    Ok(RelativePose {
        model: MotionModel::Homography,
        matrix: h_matrix,
        r: s.r,
        t: s.t / scale,
        mask,
        report,
    })
}

fn insert_stats(report: &mut Metrics, s: &TwoViewEstimate, threshold: f64) {
    report.insert("inliers".into(), s.inliers as f64);
    report.insert("trials".into(), s.trials as f64);
    report.insert("score".into(), s.score);
    report.insert("rms_px".into(), s.rms_px);
    report.insert("threshold_px".into(), threshold);
}

fn camera_input<'a>(inputs: &Inputs<'a>, name: &str) -> Result<&'a Camera, OpError> {
    match inputs.require(name)? {
        Value::Camera(c) => Ok(c),
        other => Err(OpError::input(
            name,
            format!("expected Camera, got {}", other.port_type()),
        )),
    }
}

/// Reads the points and cameras, undistorts, and pairs the points.
fn calibrated_inputs(
    inputs: &Inputs<'_>,
) -> Result<(Intrinsics, Intrinsics, Vec<Correspondence>), OpError> {
    let left = input_points2(inputs, "points_left")?;
    let right = input_points2(inputs, "points_right")?;
    if left.len() != right.len() {
        return Err(OpError::input(
            "points_right",
            format!(
                "holds {} points but points_left holds {}",
                right.len(),
                left.len()
            ),
        ));
    }
    let c1 = camera_input(inputs, "camera")?;
    let c2 = if inputs.get("camera2").is_some() {
        camera_input(inputs, "camera2")?
    } else {
        c1
    };
    let a = ideal_points(c1, &left).map_err(|e| OpError::input("camera", e))?;
    let b = ideal_points(c2, &right).map_err(|e| OpError::input("camera2", e))?;
    let data = a
        .points
        .iter()
        .zip(&b.points)
        .map(|(p, q)| [*p, *q])
        .collect();
    Ok((a.k, b.k, data))
}

fn calibrated_input_specs() -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "points_left",
            PortType::Points2D,
            "Left points, pixels (for `prosac`: ordered best match first).",
        ),
        PortSpec::new(
            "points_right",
            PortType::Points2D,
            "Right points, pixels, one per left point.",
        ),
        PortSpec::new(
            "camera",
            PortType::Camera,
            "Intrinsics of the left camera (and the right one unless `camera2` is given).",
        ),
        PortSpec::new(
            "camera2",
            PortType::Camera,
            "Intrinsics of the right camera, if different.",
        )
        .optional(),
    ]
}

fn check_parallax(m: f64) -> Result<(), String> {
    if !m.is_finite() || !(0.0..=90.0).contains(&m) {
        return Err(format!("`min_parallax_deg` must be in [0, 90], got {m}"));
    }
    Ok(())
}

ocellus_engine::params! {
    /// Parameters of `geometry.find_essential`.
    pub struct FindEssentialParams {
        /// Sampling strategy: ransac, msac, lo_ransac or prosac. Default lo_ransac.
        method: RobustMethod = RobustMethod::LoRansac,
        /// Inlier threshold on the Sampson distance, pixels (normalized distance times the
        /// geometric mean focal length). Default 1.
        threshold_px: f64 = 1.0 => [min = 0.0, unit = "px"],
        /// Probability that at least one all-inlier sample is drawn (adaptive stop), in
        /// (0, 1). Default 0.999.
        confidence: f64 = 0.999 => [min = 0.0, max = 1.0],
        /// Most minimal samples drawn. Default 10000.
        max_trials: u32 = 10_000 => [min = 1],
        /// Seed of the sampling stream; the same seed gives the same result. Default 0.
        seed: u64 = 0,
        /// Refine E on its inliers with Levenberg–Marquardt (Sampson distance). Default true.
        refine: bool = true,
        /// Smallest parallax angle of an inlier that votes in the cheirality test, degrees,
        /// 0..=90. Default 0.5.
        min_parallax_deg: f64 = 0.5 => [min = 0.0, max = 90.0, unit = "deg"],
    }
}

/// `geometry.find_essential`. See [`find_essential`].
#[derive(Debug, Clone)]
pub struct FindEssential {
    options: RobustOptions,
    refine: bool,
    min_parallax_deg: f64,
}

fn unit_pose_outputs() -> [PortSpec; 1] {
    [PortSpec::new(
        "pose",
        PortType::Pose,
        "camera2_from_camera1 (x₂ = R x₁ + t), unit translation.",
    )]
}

impl Op for FindEssential {
    type Params = FindEssentialParams;
    const ID: &'static str = "geometry.find_essential";
    const SUMMARY: &'static str =
        "Robustly estimates the essential matrix and relative pose of two calibrated views.";
    const DOC: &'static str = r#"
Finds the essential matrix `E` (`x₂ᵀ E x₁ = 0` for normalized coordinates `x = K⁻¹·pixel`) of
pixel correspondences with outliers, and the relative pose it implies, like OpenCV's
`findEssentialMat` followed by `recoverPose`.

Points are normalized with `camera` (left) and `camera2` (right; `camera` when absent). A camera
with lens distortion is handled by undistorting the points first (Newton inversion of OpenCV's
model); skew must be 0. Method: Nistér's five-point solver in minimal samples of 5 inside the
shared robust loop (`method`: RANSAC, MSAC, LO-RANSAC (default; local optimisation with the
normalized eight-point fit projected onto the essential manifold) or PROSAC), residual = the
Sampson distance times the geometric-mean focal length, so `threshold_px` is in pixels
(OpenCV's `threshold` is the same quantity). With `refine`, `E = [t]×R` is polished by
Levenberg–Marquardt over (R, t) (5 degrees of freedom) on the inliers' Sampson distances, in
up to four rounds, each refitting the inlier set at the threshold and, while that does not lower
the MSAC score, the wider sets at 1.25, 1.5 and 2 times it, keeping the first refit that does
(OpenCV does not refine). Exact repeats of a correspondence count once in sampling and
fitting. The four (R, ±t) candidates are scored by the cheirality test (points triangulated by
the midpoint method must lie in front of both cameras; only inliers with parallax ≥
`min_parallax_deg` vote). `E` is reported as `[t]×R` of the chosen pose, unit norm.

Outputs: `E` (3×3), `pose` (camera2_from_camera1, unit t), `inlier_mask` (N×1, 1 = inlier of
E), `inliers`, `report`: trials, inliers, correspondences, inlier_ratio, score (Σ min(r², t²),
px²), rms_px, threshold_px, improvements, local_optimizations, refined, points_in_front
(cheirality votes of the chosen pose), runner_up (votes of the second candidate — close to
points_in_front means the pose is ambiguous), median_parallax_deg. Fewer than 5
correspondences, non-finite points, no consensus or no point in front are errors.

Reference: D. Nistér, "An efficient solution to the five-point relative pose problem", PAMI
2004; Hartley & Zisserman §9.6; OpenCV `cv::findEssentialMat`, `cv::recoverPose`.

Example:
    "essential": (op: "geometry.find_essential",
                  inputs: { "points_left": "pairs.points_left", "points_right": "pairs.points_right",
                            "camera": "camera.camera" },
                  params: (threshold_px: 1.0, seed: 0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        calibrated_input_specs()
    }

    fn outputs() -> Vec<PortSpec> {
        let [pose] = unit_pose_outputs();
        vec![
            PortSpec::new(
                "E",
                PortType::Matrix,
                "3×3 essential matrix, x₂ᵀ E x₁ = 0 in normalized coordinates, unit norm.",
            ),
            pose,
            PortSpec::new(
                "inlier_mask",
                PortType::Matrix,
                "N×1 matrix, 1 for inliers of E, 0 for outliers (input order).",
            ),
            PortSpec::new("inliers", PortType::Integer, "Number of inliers."),
            PortSpec::new(
                "report",
                PortType::Metrics,
                "trials, inliers, correspondences, inlier_ratio, score, rms_px, threshold_px, \
                 improvements, local_optimizations, refined, points_in_front, runner_up, \
                 median_parallax_deg.",
            ),
        ]
    }

    fn new(p: FindEssentialParams) -> Result<Self, String> {
        check_robust(p.threshold_px, p.confidence, p.max_trials)?;
        check_parallax(p.min_parallax_deg)?;
        Ok(FindEssential {
            options: options(p.method, p.threshold_px, p.confidence, p.max_trials, p.seed),
            refine: p.refine,
            min_parallax_deg: p.min_parallax_deg,
        })
    }
}

impl Operator for FindEssential {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let (k1, k2, data) = calibrated_inputs(inputs)?;
        let est = find_essential(
            &data,
            &k1,
            &k2,
            &self.options,
            self.refine,
            self.min_parallax_deg,
        )
        .map_err(|e| OpError::failed(format!("no essential matrix: {e}")))?;
        let mut report = est.stats.metrics(data.len(), self.options.threshold);
        report.insert("points_in_front".into(), est.points_in_front as f64);
        report.insert("runner_up".into(), est.runner_up as f64);
        report.insert("median_parallax_deg".into(), est.median_parallax_deg);
        Ok(Outputs::new()
            .with("E", matrix_value(&est.e))
            .with("pose", Value::Pose(pose_from_rt(&est.r, &est.t)))
            .with("inlier_mask", mask_value(&est.inlier_mask))
            .with("inliers", Value::Integer(est.inliers as i64))
            .with("report", Value::metrics(report)))
    }
}

ocellus_engine::params! {
    /// Parameters of `geometry.relative_pose`.
    pub struct RelativePoseParams {
        /// Sampling strategy of both fits: ransac, msac, lo_ransac or prosac. Default
        /// lo_ransac.
        method: RobustMethod = RobustMethod::LoRansac,
        /// Inlier threshold of the homography fit (symmetric transfer error), pixels.
        /// Default 3.
        threshold_h_px: f64 = 3.0 => [min = 0.0, unit = "px"],
        /// Inlier threshold of the essential fit (Sampson distance), pixels. Default 1.
        threshold_e_px: f64 = 1.0 => [min = 0.0, unit = "px"],
        /// Standard deviation of the point noise assumed by GRIC, pixels. Default 1.
        sigma_px: f64 = 1.0 => [min = 0.0, unit = "px"],
        /// Largest median reprojection error of the homography inliers under the best pure
        /// rotation for the motion to be reported as a rotation, pixels. Default 1.
        rotation_px: f64 = 1.0 => [min = 0.0, unit = "px"],
        /// Smallest parallax angle of a point that votes in the cheirality test, degrees,
        /// 0..=90. Default 0.5.
        min_parallax_deg: f64 = 0.5 => [min = 0.0, max = 90.0, unit = "deg"],
        /// Confidence of the adaptive stop, in (0, 1). Default 0.999.
        confidence: f64 = 0.999 => [min = 0.0, max = 1.0],
        /// Most minimal samples per fit. Default 10000.
        max_trials: u32 = 10_000 => [min = 1],
        /// Seed of the sampling streams. Default 0.
        seed: u64 = 0,
        /// Refine both models on their inliers with Levenberg–Marquardt. Default true.
        refine: bool = true,
    }
}

/// `geometry.relative_pose`. See [`relative_pose`].
#[derive(Debug, Clone)]
pub struct RelativePoseOp {
    options: RelativePoseOptions,
}

impl Op for RelativePoseOp {
    type Params = RelativePoseParams;
    const ID: &'static str = "geometry.relative_pose";
    const SUMMARY: &'static str =
        "Recovers two-view motion with the simplest model the data support (E, H or rotation).";
    const DOC: &'static str = r#"
Chooses the motion model of two calibrated views from pixel correspondences and recovers the
relative pose, ready for `geometry.triangulate`.

1. Fits a homography (as `geometry.find_homography`, threshold `threshold_h_px`) and an
   essential matrix (as `geometry.find_essential`, threshold `threshold_e_px`), both refined
   when `refine`. Cameras with distortion have their points undistorted first.
2. Compares them with Torr's GRIC, `Σ min(e²/σ², 2(4 − d)) + ln(4)·d·n + ln(4n)·k` with
   σ = `sigma_px`: H has d = 2, k = 8 (e² = half the symmetric transfer error); E has d = 3,
   k = 5 (e² = squared Sampson distance in pixels). For calibrated cameras this compares H
   with E rather than with F (as `geometry.select_model` does): E has 5 parameters against
   F's 7, so general motion wins a little sooner. The lower GRIC wins.
3. E wins ("essential"): the pose is E's cheirality winner (see `geometry.find_essential`).
   H wins: the homography inliers are fitted by the best pure rotation (Kabsch on the bearing
   vectors); if their median reprojection error is ≤ `rotation_px`, the motion is a rotation
   ("rotation", t = 0) — nothing can be triangulated, so `points_left`/`points_right` are
   empty. Otherwise ("homography", a planar scene) H is decomposed (Faugeras–Lustman, as
   `geometry.decompose_homography`) and the candidate with the most homography inliers in
   front of both cameras is kept; ties (there are always two physical solutions) go to the
   better epipolar fit of all correspondences (points off the plane decide), then to the
   normal facing camera 1 most. The translation is scaled to unit length (its plane-relative
   scale is reported as `plane_distance`, the plane's distance from camera 1 in baselines).

Outputs: `model` ("essential", "homography" or "rotation"), `matrix` (E with unit norm, or H
with h₃₃ = 1), `pose1` (identity) and `pose2` (camera_from_world of both views with the world
in camera 1, i.e. camera2_from_camera1, unit or zero translation), `inlier_mask` (N×1: inliers
of the chosen model in front of both cameras; for a rotation, the homography inliers),
`inliers` (their count), `points_left`/`points_right` (those inliers, undistorted pixels; empty
for a rotation), `report`: correspondences, gric_h, gric_e, inliers_h, inliers_e, parallax_px
(median transfer distance of E's inliers under H), planar_or_rotation (1 when H won), inliers,
trials, score, rms_px, threshold_px of the chosen fit, points_in_front, and per model:
cheirality_votes, cheirality_runner_up, median_parallax_deg (essential); rotation_median_px
(homography, rotation); plane_distance, plane_normal_z (homography).

Reference: P. H. S. Torr, "An assessment of information criteria for motion model selection",
CVPR 1997, and Phil. Trans. R. Soc. A 1998; Nistér 2004; Faugeras & Lustman 1988; ORB-SLAM's
initializer (Mur-Artal et al. 2015) makes the same H-versus-epipolar choice.

Example:
    "motion": (op: "geometry.relative_pose",
               inputs: { "points_left": "pairs.points_left", "points_right": "pairs.points_right",
                         "camera": "camera.camera" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        calibrated_input_specs()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "model",
                PortType::Text,
                "\"essential\", \"homography\" or \"rotation\".",
            ),
            PortSpec::new(
                "matrix",
                PortType::Matrix,
                "The chosen model's 3×3 matrix: E (unit norm) or H (pixels, h₃₃ = 1).",
            ),
            PortSpec::new("pose1", PortType::Pose, "Camera 1: identity."),
            PortSpec::new(
                "pose2",
                PortType::Pose,
                "Camera 2, camera_from_world = camera2_from_camera1; unit t (0 for a rotation).",
            ),
            PortSpec::new(
                "inlier_mask",
                PortType::Matrix,
                "N×1, 1 for the correspondences supporting the pose.",
            ),
            PortSpec::new("inliers", PortType::Integer, "Number of supporting points."),
            PortSpec::new(
                "points_left",
                PortType::Points2D,
                "Supporting left points (undistorted pixels); empty for a rotation.",
            ),
            PortSpec::new(
                "points_right",
                PortType::Points2D,
                "Supporting right points (undistorted pixels); empty for a rotation.",
            ),
            PortSpec::new("report", PortType::Metrics, "See the description."),
        ]
    }

    fn new(p: RelativePoseParams) -> Result<Self, String> {
        check_robust(p.threshold_h_px, p.confidence, p.max_trials)?;
        check_robust(p.threshold_e_px, p.confidence, p.max_trials)?;
        check_parallax(p.min_parallax_deg)?;
        if !(p.sigma_px.is_finite() && p.sigma_px > 0.0) {
            return Err(format!("`sigma_px` must be > 0, got {}", p.sigma_px));
        }
        if !(p.rotation_px.is_finite() && p.rotation_px >= 0.0) {
            return Err(format!("`rotation_px` must be ≥ 0, got {}", p.rotation_px));
        }
        let o = |t| options(p.method, t, p.confidence, p.max_trials, p.seed);
        Ok(RelativePoseOp {
            options: RelativePoseOptions {
                h: o(p.threshold_h_px),
                e: o(p.threshold_e_px),
                sigma_px: p.sigma_px,
                refine: p.refine,
                rotation_px: p.rotation_px,
                min_parallax_deg: p.min_parallax_deg,
            },
        })
    }
}

impl Operator for RelativePoseOp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let (k1, k2, data) = calibrated_inputs(inputs)?;
        let rp = relative_pose(&data, &k1, &k2, &self.options)
            .map_err(|e| OpError::failed(format!("no relative pose: {e}")))?;
        let keep = rp.model != MotionModel::Rotation;
        let (left, right): (Vec<[f64; 2]>, Vec<[f64; 2]>) = data
            .iter()
            .zip(&rp.mask)
            .filter(|(_, m)| keep && **m)
            .map(|(c, _)| (c[0], c[1]))
            .unzip();
        let inliers = rp.mask.iter().filter(|&&b| b).count();
        Ok(Outputs::new()
            .with("model", Value::Text(rp.model.name().into()))
            .with("matrix", matrix_value(&rp.matrix))
            .with("pose1", Value::Pose(Pose::IDENTITY))
            .with("pose2", Value::Pose(pose_from_rt(&rp.r, &rp.t)))
            .with("inlier_mask", mask_value(&rp.mask))
            .with("inliers", Value::Integer(inliers as i64))
            .with("points_left", Value::Points2D(left.into()))
            .with("points_right", Value::Points2D(right.into()))
            .with("report", Value::metrics(rp.report)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::geometry::camera::distort_rt;
    use crate::geometry::pose_util::{rotation_angle_deg, vector_angle_deg};
    use nalgebra::Rotation3;
    use ocellus_engine::value::CameraModel;
    use std::sync::Arc;

    const K: Intrinsics = Intrinsics {
        fx: 500.0,
        fy: 500.0,
        cx: 320.0,
        cy: 240.0,
    };

    struct Truth {
        r: Matrix3<f64>,
        t: Vector3<f64>,
        data: Vec<Correspondence>,
        inlier: Vec<bool>,
    }

    /// Points seen by `K[I|0]` and `K[R|t]`: depths 4–10 (or on the plane z = 6 + 0.3x when
    /// `planar`), pixel noise `sigma`, a share `outliers` of random right points.
    fn scene(
        t: Vector3<f64>,
        planar: bool,
        n: usize,
        sigma: f64,
        outliers: f64,
        seed: u64,
    ) -> Truth {
        let r = *Rotation3::from_euler_angles(0.03, -0.12, 0.02).matrix();
        let mut rng = SplitMix64::new(seed);
        let (mut data, mut inlier) = (Vec::new(), Vec::new());
        while data.len() < n {
            let (u, v) = (rng.uniform() * 640.0, rng.uniform() * 480.0);
            let ray = Vector3::new((u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0);
            let z = if planar {
                6.0 / (1.0 - 0.3 * ray.x)
            } else {
                4.0 + 6.0 * rng.uniform()
            };
            let x = ray * z;
            let y = r * x + t;
            let q = K.project(&y);
            if y.z <= 0.0 || !(0.0..640.0).contains(&q[0]) || !(0.0..480.0).contains(&q[1]) {
                continue;
            }
            let out = rng.uniform() < outliers;
            let q = if out {
                [rng.uniform() * 640.0, rng.uniform() * 480.0]
            } else {
                [q[0] + sigma * rng.normal(), q[1] + sigma * rng.normal()]
            };
            data.push([[u + sigma * rng.normal(), v + sigma * rng.normal()], q]);
            inlier.push(!out);
        }
        Truth { r, t, data, inlier }
    }

    fn opts(threshold: f64) -> RobustOptions {
        RobustOptions {
            threshold,
            ..RobustOptions::default()
        }
    }

    fn rp_options() -> RelativePoseOptions {
        RelativePoseOptions {
            h: opts(3.0),
            e: opts(1.0),
            sigma_px: 1.0,
            refine: true,
            rotation_px: 1.0,
            min_parallax_deg: 0.5,
        }
    }

    #[test]
    fn essential_exact_data_and_outliers() {
        // Noise-free: the pose is exact and every point is an inlier in front.
        let s = scene(Vector3::new(1.0, 0.1, 0.2), false, 60, 0.0, 0.0, 1);
        let est = find_essential(&s.data, &K, &K, &opts(1.0), true, 0.5).unwrap();
        assert!(rotation_angle_deg(&est.r, &s.r) < 1e-6);
        assert!(vector_angle_deg(&est.t, &s.t) < 1e-5);
        assert_eq!(est.inliers, 60);
        assert!(est.front_mask.iter().all(|&b| b));
        assert!((est.t.norm() - 1.0).abs() < 1e-12 && (est.e.norm() - 1.0).abs() < 1e-12);
        // E = [t]× R of the reported pose.
        let e = skew(&est.t) * est.r;
        assert!((e / e.norm() - est.e).norm() < 1e-12);
        // Noise and 40 % outliers.
        let s = scene(Vector3::new(-0.8, 0.2, 0.3), false, 300, 0.5, 0.4, 2);
        let est = find_essential(&s.data, &K, &K, &opts(1.5), true, 0.5).unwrap();
        assert!(
            rotation_angle_deg(&est.r, &s.r) < 0.2,
            "{}",
            rotation_angle_deg(&est.r, &s.r)
        );
        assert!(
            vector_angle_deg(&est.t, &s.t) < 2.0,
            "{}",
            vector_angle_deg(&est.t, &s.t)
        );
        let true_in = s.inlier.iter().filter(|&&b| b).count();
        let found_true = est
            .inlier_mask
            .iter()
            .zip(&s.inlier)
            .filter(|(a, b)| **a && **b)
            .count();
        assert!(
            found_true as f64 >= 0.95 * true_in as f64,
            "{found_true}/{true_in}"
        );
        assert!(est.inliers <= true_in + 10, "{} > {true_in}", est.inliers);
        assert!(est.runner_up < est.points_in_front / 2);
    }

    #[test]
    fn refinement_lowers_the_sampson_error() {
        let s = scene(Vector3::new(1.0, 0.0, 0.1), false, 100, 0.5, 0.0, 3);
        let normalized: Vec<NormalizedPair> = s
            .data
            .iter()
            .map(|c| (K.normalize(c[0]).into(), K.normalize(c[1]).into()))
            .collect();
        let est = EssentialEstimator { focal_px: 500.0 };
        let rough = skew(&Vector3::new(1.0, 0.05, 0.1).normalize())
            * Rotation3::from_euler_angles(0.035, -0.115, 0.02).into_inner();
        let cost = |e: &Matrix3<f64>| {
            let mut r = vec![0.0; normalized.len()];
            est.residuals(e, &normalized, &mut r);
            r.iter().sum::<f64>()
        };
        let refined = refine_essential(&rough, &normalized, 500.0);
        assert!(
            cost(&refined) < 0.5 * cost(&rough),
            "{} {}",
            cost(&refined),
            cost(&rough)
        );
        // The truth's cost is near the refined one (noise only).
        let truth = skew(&s.t) * s.r;
        assert!(cost(&refined) <= cost(&(truth / truth.norm())) * 1.0001);
        // Too few data: unchanged.
        assert_eq!(refine_essential(&rough, &normalized[..5], 500.0), rough);
    }

    #[test]
    fn model_selection_general_planar_rotation() {
        let o = rp_options();
        let general = scene(Vector3::new(1.0, 0.1, 0.2), false, 200, 0.3, 0.2, 4);
        let p = relative_pose(&general.data, &K, &K, &o).unwrap();
        assert_eq!(p.model, MotionModel::Essential);
        assert!(rotation_angle_deg(&p.r, &general.r) < 0.2);
        assert!(vector_angle_deg(&p.t, &general.t) < 2.0);
        assert_eq!(p.report.get("planar_or_rotation"), Some(&0.0));

        let planar = scene(Vector3::new(1.0, 0.1, 0.2), true, 200, 0.3, 0.2, 5);
        let p = relative_pose(&planar.data, &K, &K, &o).unwrap();
        assert_eq!(p.model, MotionModel::Homography);
        assert_eq!(p.report.get("planar_or_rotation"), Some(&1.0));
        // Both cameras see the plane from the front: one of the two physical solutions.
        assert!((p.t.norm() - 1.0).abs() < 1e-9);
        assert!(p.mask.iter().filter(|&&b| b).count() >= 140);

        let rotation = scene(Vector3::zeros(), false, 200, 0.3, 0.2, 6);
        let p = relative_pose(&rotation.data, &K, &K, &o).unwrap();
        assert_eq!(p.model, MotionModel::Rotation);
        assert_eq!(p.t, Vector3::zeros());
        assert!(rotation_angle_deg(&p.r, &rotation.r) < 0.1);
        assert!(p.report["rotation_median_px"] < 1.0);
    }

    #[test]
    fn planar_scene_with_off_plane_points_picks_the_true_solution() {
        // Mostly a plane, a few points off it: GRIC still prefers H, and the off-plane points
        // decide between the two decompositions.
        let mut s = scene(Vector3::new(1.0, 0.1, 0.2), true, 200, 0.2, 0.0, 7);
        let off = scene(Vector3::new(1.0, 0.1, 0.2), false, 12, 0.2, 0.0, 8);
        s.data.extend(off.data);
        let p = relative_pose(&s.data, &K, &K, &rp_options()).unwrap();
        assert_eq!(p.model, MotionModel::Homography);
        assert!(
            rotation_angle_deg(&p.r, &s.r) < 0.5,
            "{}",
            rotation_angle_deg(&p.r, &s.r)
        );
        assert!(
            vector_angle_deg(&p.t, &s.t) < 3.0,
            "{}",
            vector_angle_deg(&p.t, &s.t)
        );
    }

    #[test]
    fn degenerate_input_is_an_error_not_nan() {
        let o = rp_options();
        assert!(relative_pose(&[], &K, &K, &o).is_err());
        let same = vec![[[100.0, 100.0], [120.0, 90.0]]; 30];
        assert!(relative_pose(&same, &K, &K, &o).is_err());
        assert!(find_essential(&same, &K, &K, &opts(1.0), true, 0.5).is_err());
        let few = scene(Vector3::x(), false, 4, 0.0, 0.0, 9);
        assert!(find_essential(&few.data, &K, &K, &opts(1.0), true, 0.5).is_err());
        let mut nan = scene(Vector3::x(), false, 20, 0.0, 0.0, 10).data;
        nan[3][1][0] = f64::NAN;
        assert!(find_essential(&nan, &K, &K, &opts(1.0), true, 0.5).is_err());
        assert!(relative_pose(&nan, &K, &K, &o).is_err());
    }

    #[test]
    fn distorted_points_are_undistorted_and_skew_is_rejected() {
        let d = [-0.2, 0.05, 0.001, -0.002, 0.0];
        let camera = Camera::from_parts(
            640,
            480,
            ocellus_engine::value::Intrinsics {
                fx: 500.0,
                fy: 500.0,
                cx: 320.0,
                cy: 240.0,
                skew: 0.0,
            },
            Distortion::RadialTangential(d),
        );
        let ideal = [[100.0, 80.0], [320.0, 240.0], [600.0, 400.0]];
        let distorted: Vec<[f64; 2]> = ideal
            .iter()
            .map(|p| {
                let n = K.normalize(*p);
                K.denormalize(&distort_rt(&d, [n.x, n.y]).into())
            })
            .collect();
        let back = ideal_points(&camera, &distorted).unwrap();
        for (a, b) in back.points.iter().zip(&ideal) {
            assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6);
        }
        let skewed = Camera {
            params: vec![500.0, 500.0, 320.0, 240.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0],
            ..camera
        };
        assert!(ideal_points(&skewed, &ideal).unwrap_err().contains("skew"));
    }

    fn run_op<O: Operator>(op: &O, specs: &[PortSpec], values: &[Option<Value>]) -> Outputs {
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(specs, values)).unwrap()
    }

    #[test]
    fn operators_run_and_reject_bad_params() {
        let s = scene(Vector3::new(1.0, 0.1, 0.2), false, 120, 0.3, 0.1, 11);
        let left: Vec<[f64; 2]> = s.data.iter().map(|c| c[0]).collect();
        let right: Vec<[f64; 2]> = s.data.iter().map(|c| c[1]).collect();
        let camera = Camera {
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![500.0, 500.0, 320.0, 240.0],
        };
        let values = vec![
            Some(Value::Points2D(Arc::new(left.clone()))),
            Some(Value::Points2D(Arc::new(right.clone()))),
            Some(Value::Camera(Arc::new(camera.clone()))),
            None,
        ];
        let op = FindEssential::new(FindEssentialParams::default()).unwrap();
        let mut out = run_op(&op, &FindEssential::inputs(), &values);
        let Some(Value::Pose(pose)) = out.take("pose") else {
            panic!("no pose")
        };
        let (r, t) = crate::geometry::pose_util::rt_from_pose(&pose).unwrap();
        assert!(rotation_angle_deg(&r, &s.r) < 0.3 && vector_angle_deg(&t, &s.t) < 3.0);
        assert!(matches!(out.take("E"), Some(Value::Matrix(m)) if m.rows == 3 && m.cols == 3));
        let op = RelativePoseOp::new(RelativePoseParams::default()).unwrap();
        let mut out = run_op(&op, &RelativePoseOp::inputs(), &values);
        assert_eq!(out.take("model"), Some(Value::Text("essential".into())));
        let Some(Value::Integer(n)) = out.take("inliers") else {
            panic!()
        };
        let Some(Value::Points2D(pl)) = out.take("points_left") else {
            panic!()
        };
        assert_eq!(pl.len() as i64, n);
        assert!(n >= 90);
        // A rotation gives empty point lists (nothing to triangulate).
        let rot = scene(Vector3::zeros(), false, 120, 0.3, 0.1, 12);
        let rvalues = vec![
            Some(Value::Points2D(Arc::new(
                rot.data.iter().map(|c| c[0]).collect(),
            ))),
            Some(Value::Points2D(Arc::new(
                rot.data.iter().map(|c| c[1]).collect(),
            ))),
            Some(Value::Camera(Arc::new(camera))),
            None,
        ];
        let mut out = run_op(&op, &RelativePoseOp::inputs(), &rvalues);
        assert_eq!(out.take("model"), Some(Value::Text("rotation".into())));
        assert!(matches!(out.take("points_left"), Some(Value::Points2D(p)) if p.is_empty()));
        assert!(matches!(out.take("pose2"), Some(Value::Pose(p)) if p.translation == [0.0; 3]));
        // Bad parameters.
        let bad = [
            FindEssentialParams {
                threshold_px: 0.0,
                ..FindEssentialParams::default()
            },
            FindEssentialParams {
                min_parallax_deg: f64::NAN,
                ..FindEssentialParams::default()
            },
            FindEssentialParams {
                confidence: 1.0,
                ..FindEssentialParams::default()
            },
        ];
        for p in bad {
            assert!(FindEssential::new(p).is_err());
        }
        assert!(
            RelativePoseOp::new(RelativePoseParams {
                sigma_px: 0.0,
                ..RelativePoseParams::default()
            })
            .is_err()
        );
        assert!(
            RelativePoseOp::new(RelativePoseParams {
                rotation_px: f64::INFINITY,
                ..RelativePoseParams::default()
            })
            .is_err()
        );
        // Mismatched lengths are an input error.
        let mismatched = vec![
            Some(Value::Points2D(Arc::new(left))),
            Some(Value::Points2D(Arc::new(right[..5].to_vec()))),
            values[2].clone(),
            None,
        ];
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let specs = RelativePoseOp::inputs();
        assert!(op.run(&ctx, &Inputs::new(&specs, &mismatched)).is_err());
    }
}
