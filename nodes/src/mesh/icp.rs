//! Rigid registration of point clouds: `mesh.icp` (iterative closest point) and
//! `mesh.transform`.
//!
//! [`icp`] alternates two steps from an initial `target_from_source`:
//! 1. every source point, moved by the current transform, is paired with its nearest target
//!    point within `max_correspondence_distance`; with `trim_ratio < 1` only that fraction of the
//!    pairs, the nearest, is kept (trimmed ICP, Chetverikov, Svirko, Stepanov & Krsek, "The
//!    trimmed iterative closest point algorithm", ICPR 2002);
//! 2. the increment that best aligns the kept pairs is composed onto the transform:
//!    - point-to-point (Besl & McKay, PAMI 1992): the closed-form least-squares rotation of the
//!      centred pairs by SVD with the determinant fixed to +1 (Umeyama, PAMI 1991; Kabsch 1976);
//!    - point-to-plane (Chen & Medioni 1992): `Σ ((R y + t − q)·n_q)²` linearized about the
//!      identity, `R ≈ I + [ω]×`, a 6×6 least-squares system in `(ω, t)` (Low, "Linear
//!      least-squares optimization for point-to-plane ICP surface registration", UNC TR04-004,
//!      2004), solved by Cholesky; the rotation applied is the exact `exp([ω]×)`.
//!
//! All of it runs in f64 on coordinates centred on the target's centroid and divided by its RMS
//! radius, so a cloud a million units from the origin is conditioned as one at the origin. It
//! stops when the increment is below `transform_tolerance` (radians plus translation relative to
//! that radius), when the RMSE changes by a relative amount below `relative_rmse_tolerance`, or
//! after `max_iterations` increments.
//!
//! The nearest-neighbour searches run in parallel, one result per source point; the sums run in
//! source order, so results do not depend on the thread count.

use std::sync::Arc;

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, PointCloud, Pose, Value};
use ocellus_engine::{param_enum, params};

use super::kdtree::KdTree;
use super::pointcloud::{cloud_input, normals_f64, par_map, positions_f64};

/// Relative size under which the second singular value marks a collinear point set.
const COLLINEAR_RATIO: f64 = 1e-12;
/// Smallest eigenvalue, relative to the largest, of a well-posed point-to-plane system.
const PLANE_CONDITION: f64 = 1e-12;
/// RMSE (relative to the target's radius) treated as an exact fit.
const EXACT_RMSE: f64 = 1e-13;

param_enum! {
    /// The error `mesh.icp` minimizes.
    pub enum IcpMethod {
        /// Squared distances between paired points (closed-form SVD step).
        PointToPoint = "point_to_point",
        /// Squared distances from source points to the target's tangent planes.
        PointToPlane = "point_to_plane",
    }
}

/// Options of [`icp`].
#[derive(Debug, Clone, PartialEq)]
pub struct IcpOptions {
    /// The error minimized.
    pub method: IcpMethod,
    /// Pairs farther apart are dropped, scene units; `f64::INFINITY` keeps all.
    pub max_correspondence_distance: f64,
    /// Fraction of the pairs kept, the nearest, in (0, 1].
    pub trim_ratio: f64,
    /// Most increments.
    pub max_iterations: usize,
    /// Stop when `|rmseₖ₋₁ − rmseₖ| ≤ this · rmseₖ₋₁`.
    pub relative_rmse_tolerance: f64,
    /// Stop when the increment's angle (radians) plus its translation (relative to the
    /// target's RMS radius) is below this.
    pub transform_tolerance: f64,
}

impl Default for IcpOptions {
    fn default() -> IcpOptions {
        IcpOptions {
            method: IcpMethod::PointToPoint,
            max_correspondence_distance: f64::INFINITY,
            trim_ratio: 1.0,
            max_iterations: 100,
            relative_rmse_tolerance: 1e-10,
            transform_tolerance: 1e-10,
        }
    }
}

/// A rigid transform `x_to = R x_from + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rigid {
    /// Rotation.
    pub rotation: Matrix3<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
}

impl Rigid {
    /// The identity.
    pub fn identity() -> Rigid {
        Rigid {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// From a [`Pose`].
    pub fn from_pose(pose: &Pose) -> Rigid {
        let r = pose.rotation_matrix();
        Rigid {
            rotation: Matrix3::from_row_slice(&r),
            translation: Vector3::from(pose.translation),
        }
    }

    /// As a [`Pose`].
    pub fn to_pose(&self) -> Pose {
        let r = &self.rotation;
        let m = [
            r[(0, 0)],
            r[(0, 1)],
            r[(0, 2)],
            r[(1, 0)],
            r[(1, 1)],
            r[(1, 2)],
            r[(2, 0)],
            r[(2, 1)],
            r[(2, 2)],
        ];
        Pose::from_rotation_matrix(&m, self.translation.into())
    }

    /// Applies the transform to a point.
    pub fn apply(&self, p: &[f64; 3]) -> [f64; 3] {
        (self.rotation * Vector3::from(*p) + self.translation).into()
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Rigid {
        let rt = self.rotation.transpose();
        Rigid {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Rigid) -> Rigid {
        Rigid {
            rotation: self.rotation * other.rotation,
            translation: self.rotation * other.translation + self.translation,
        }
    }
}

/// The rotation angle of `r`, radians, accurate near 0 and π.
pub fn rotation_angle(r: &Matrix3<f64>) -> f64 {
    let s = Vector3::new(
        r[(2, 1)] - r[(1, 2)],
        r[(0, 2)] - r[(2, 0)],
        r[(1, 0)] - r[(0, 1)],
    )
    .norm()
        / 2.0;
    let c = (r.trace() - 1.0) / 2.0;
    s.atan2(c)
}

/// `exp([ω]×)` by Rodrigues' formula.
pub fn rotation_from_vector(w: &Vector3<f64>) -> Matrix3<f64> {
    let theta = w.norm();
    let k = Matrix3::new(0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0);
    if theta < 1e-8 {
        // Second-order series; the next term is below 1e-24.
        return Matrix3::identity() + k + k * k * 0.5;
    }
    Matrix3::identity()
        + k * (theta.sin() / theta)
        + k * k * ((1.0 - theta.cos()) / (theta * theta))
}

/// Why ICP failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IcpError {
    /// A cloud has too few points.
    #[error("the {cloud} cloud has {got} points, but at least {needed} are needed")]
    TooFewPoints {
        /// `source` or `target`.
        cloud: &'static str,
        /// Points given.
        got: usize,
        /// Points needed.
        needed: usize,
    },
    /// Point-to-plane needs target normals.
    #[error(
        "point_to_plane needs normals on the target cloud (run mesh.estimate_normals on it first)"
    )]
    MissingNormals,
    /// The target's points all coincide.
    #[error("the target points all coincide")]
    CoincidentTarget,
    /// Too few pairs within the correspondence distance.
    #[error(
        "iteration {iteration}: {pairs} correspondences within max_correspondence_distance, at least {needed} are needed"
    )]
    TooFewCorrespondences {
        /// Iteration (0-based).
        iteration: usize,
        /// Pairs found.
        pairs: usize,
        /// Pairs needed.
        needed: usize,
    },
    /// The pairs do not determine a rigid transform (collinear points, or a plane for
    /// point-to-plane).
    #[error(
        "iteration {iteration}: the correspondences do not determine a rigid transform (collinear points, or a single plane for point_to_plane)"
    )]
    Degenerate {
        /// Iteration (0-based).
        iteration: usize,
    },
    /// Options out of range.
    #[error("invalid options: {0}")]
    InvalidOptions(String),
}

/// The result of [`icp`].
#[derive(Debug, Clone, PartialEq)]
pub struct IcpReport {
    /// The estimated transform.
    pub target_from_source: Rigid,
    /// RMS distance of the kept pairs at the final transform (point-to-plane: of the
    /// point-to-plane distances), scene units.
    pub rmse: f64,
    /// Fraction of source points with a target point within the correspondence distance, at the
    /// final transform.
    pub fitness: f64,
    /// Pairs kept at the final transform.
    pub correspondences: usize,
    /// Increments applied.
    pub iterations: usize,
    /// Whether a tolerance stopped it (rather than `max_iterations`).
    pub converged: bool,
}

/// Checks option ranges.
pub fn check_options(o: &IcpOptions) -> Result<(), String> {
    if o.max_correspondence_distance.is_nan() || o.max_correspondence_distance <= 0.0 {
        return Err(format!(
            "`max_correspondence_distance` must be > 0 (or infinite), got {}",
            o.max_correspondence_distance
        ));
    }
    if !(o.trim_ratio > 0.0 && o.trim_ratio <= 1.0) {
        return Err(format!(
            "`trim_ratio` must be in (0, 1], got {}",
            o.trim_ratio
        ));
    }
    for (name, v) in [
        ("relative_rmse_tolerance", o.relative_rmse_tolerance),
        ("transform_tolerance", o.transform_tolerance),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
        }
    }
    Ok(())
}

/// One kept pair: source index, target index, residual (distance or plane distance).
#[derive(Debug, Clone, Copy)]
struct Pair {
    source: usize,
    target: usize,
    dist2: f64,
}

struct Pairs {
    kept: Vec<Pair>,
    within: usize,
}

/// Pairs of the moved source points `moved` with their nearest target within `max_dist2`,
/// trimmed to the nearest `trim_ratio`, in `(dist2, source)` order when trimmed and source
/// order otherwise.
fn correspond(tree: &KdTree, moved: &[[f64; 3]], max_dist2: f64, trim_ratio: f64) -> Pairs {
    let nearest = par_map(moved.len(), |i| tree.nearest(&moved[i], max_dist2));
    let mut kept: Vec<Pair> = nearest
        .iter()
        .enumerate()
        .filter_map(|(i, n)| {
            n.map(|n| Pair {
                source: i,
                target: n.index,
                dist2: n.dist2,
            })
        })
        .collect();
    let within = kept.len();
    if trim_ratio < 1.0 {
        let keep = ((trim_ratio * within as f64).ceil() as usize).min(within);
        kept.sort_unstable_by(|a, b| a.dist2.total_cmp(&b.dist2).then(a.source.cmp(&b.source)));
        kept.truncate(keep);
    }
    Pairs { kept, within }
}

/// The point-to-point increment: the rigid transform taking `moved[p.source]` to
/// `target[p.target]` in the least-squares sense, or `None` for a collinear set.
fn point_to_point_step(moved: &[[f64; 3]], target: &[[f64; 3]], pairs: &[Pair]) -> Option<Rigid> {
    let m = pairs.len() as f64;
    let (mut cy, mut cq) = (Vector3::zeros(), Vector3::zeros());
    for p in pairs {
        cy += Vector3::from(moved[p.source]);
        cq += Vector3::from(target[p.target]);
    }
    cy /= m;
    cq /= m;
    let mut h = Matrix3::zeros();
    for p in pairs {
        let y = Vector3::from(moved[p.source]) - cy;
        let q = Vector3::from(target[p.target]) - cq;
        h += y * q.transpose();
    }
    let svd = h.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let s = svd.singular_values;
    if s[1].is_nan() || s[1] <= COLLINEAR_RATIO * s[0] {
        return None;
    }
    let v = vt.transpose();
    // Singular values are in decreasing order: the determinant fix goes on the last.
    let d = (v * u.transpose()).determinant().signum();
    let rotation = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    Some(Rigid {
        rotation,
        translation: cq - rotation * cy,
    })
}

/// The point-to-plane increment (Low 2004), or `None` when the system is singular.
fn point_to_plane_step(
    moved: &[[f64; 3]],
    target: &[[f64; 3]],
    normals: &[[f64; 3]],
    pairs: &[Pair],
) -> Option<Rigid> {
    let mut ata = Matrix6::zeros();
    let mut atb = Vector6::zeros();
    for p in pairs {
        let y = Vector3::from(moved[p.source]);
        let q = Vector3::from(target[p.target]);
        let n = Vector3::from(normals[p.target]);
        let c = y.cross(&n);
        let a = Vector6::new(c[0], c[1], c[2], n[0], n[1], n[2]);
        let b = (q - y).dot(&n);
        ata += a * a.transpose();
        atb += a * b;
    }
    // A direction the planes do not constrain (a single plane, a cylinder's axis) leaves a
    // near-zero eigenvalue; refuse it rather than step arbitrarily far.
    let eigenvalues = nalgebra::SymmetricEigen::new(ata).eigenvalues;
    let (lo, hi) = eigenvalues
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if lo.is_nan() || lo <= PLANE_CONDITION * hi {
        return None;
    }
    let chol = ata.cholesky()?;
    let x = chol.solve(&atb);
    if !x.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(Rigid {
        rotation: rotation_from_vector(&Vector3::new(x[0], x[1], x[2])),
        translation: Vector3::new(x[3], x[4], x[5]),
    })
}

/// Iterative closest point (see the module documentation): the transform taking `source` onto
/// `target`, starting from `initial`. `target_normals` (unit, one per target point) are needed
/// for point-to-plane.
pub fn icp(
    source: &[[f64; 3]],
    target: &[[f64; 3]],
    target_normals: Option<&[[f64; 3]]>,
    initial: &Rigid,
    options: &IcpOptions,
) -> Result<IcpReport, IcpError> {
    check_options(options).map_err(IcpError::InvalidOptions)?;
    let needed = match options.method {
        IcpMethod::PointToPoint => 3,
        IcpMethod::PointToPlane => 6,
    };
    for (cloud, pts) in [("source", source), ("target", target)] {
        if pts.len() < needed {
            return Err(IcpError::TooFewPoints {
                cloud,
                got: pts.len(),
                needed,
            });
        }
    }
    let normals = match (options.method, target_normals) {
        (IcpMethod::PointToPlane, None) => return Err(IcpError::MissingNormals),
        (IcpMethod::PointToPlane, Some(n)) if n.len() != target.len() => {
            return Err(IcpError::MissingNormals);
        }
        (_, n) => n,
    };
    // Normalize: centre on the target's centroid, divide by its RMS radius.
    let mut c = Vector3::zeros();
    for p in target {
        c += Vector3::from(*p);
    }
    c /= target.len() as f64;
    let radius = (target
        .iter()
        .map(|p| (Vector3::from(*p) - c).norm_squared())
        .sum::<f64>()
        / target.len() as f64)
        .sqrt();
    if radius.is_nan() || radius <= 0.0 {
        return Err(IcpError::CoincidentTarget);
    }
    let normalize = |p: &[f64; 3]| -> [f64; 3] { ((Vector3::from(*p) - c) / radius).into() };
    let src: Vec<[f64; 3]> = source.iter().map(normalize).collect();
    let tree = KdTree::new(target.iter().map(normalize).collect());
    let tgt = tree.points();
    let max_d = options.max_correspondence_distance / radius;
    let max_dist2 = max_d * max_d;
    // Normalized frame: x' = (x − c)/radius for both clouds; R' = R, t' = (R c + t − c)/radius.
    let mut current = Rigid {
        rotation: initial.rotation,
        translation: (initial.rotation * c + initial.translation - c) / radius,
    };
    let pairs_at = |pose: &Rigid, iteration: usize| -> Result<(Vec<[f64; 3]>, Pairs), IcpError> {
        let moved: Vec<[f64; 3]> = src.iter().map(|p| pose.apply(p)).collect();
        let pairs = correspond(&tree, &moved, max_dist2, options.trim_ratio);
        if pairs.kept.len() < needed {
            return Err(IcpError::TooFewCorrespondences {
                iteration,
                pairs: pairs.kept.len(),
                needed,
            });
        }
        Ok((moved, pairs))
    };
    let residual2 = |moved: &[[f64; 3]], pairs: &[Pair]| -> f64 {
        let sum: f64 = match normals {
            Some(n) if options.method == IcpMethod::PointToPlane => pairs
                .iter()
                .map(|p| {
                    let d = (Vector3::from(moved[p.source]) - Vector3::from(tgt[p.target]))
                        .dot(&Vector3::from(n[p.target]));
                    d * d
                })
                .sum(),
            _ => pairs.iter().map(|p| p.dist2).sum(),
        };
        sum / pairs.len() as f64
    };
    let mut iterations = 0;
    let mut converged = false;
    let mut previous_rmse: Option<f64> = None;
    let (mut moved, mut pairs) = pairs_at(&current, 0)?;
    while iterations < options.max_iterations {
        let rmse = residual2(&moved, &pairs.kept).sqrt();
        if rmse <= EXACT_RMSE {
            converged = true;
            break;
        }
        if let Some(prev) = previous_rmse
            && (prev - rmse).abs() <= options.relative_rmse_tolerance * prev
        {
            converged = true;
            break;
        }
        previous_rmse = Some(rmse);
        let step = match (options.method, normals) {
            (IcpMethod::PointToPlane, Some(n)) => point_to_plane_step(&moved, tgt, n, &pairs.kept),
            _ => point_to_point_step(&moved, tgt, &pairs.kept),
        }
        .ok_or(IcpError::Degenerate {
            iteration: iterations,
        })?;
        current = step.compose(&current);
        iterations += 1;
        (moved, pairs) = pairs_at(&current, iterations)?;
        let size = rotation_angle(&step.rotation) + step.translation.norm();
        if size <= options.transform_tolerance {
            converged = true;
            break;
        }
    }
    let rmse = residual2(&moved, &pairs.kept).sqrt() * radius;
    let rotation = current.rotation;
    let target_from_source = Rigid {
        rotation,
        translation: current.translation * radius + c - rotation * c,
    };
    Ok(IcpReport {
        target_from_source,
        rmse,
        fitness: pairs.within as f64 / source.len() as f64,
        correspondences: pairs.kept.len(),
        iterations,
        converged,
    })
}

/// `cloud` moved by `pose`: positions `R p + t`, normals `R n`, colors unchanged.
pub fn transform_cloud(cloud: &PointCloud, pose: &Rigid) -> PointCloud {
    PointCloud {
        positions: cloud
            .positions
            .iter()
            .map(|p| pose.apply(&p.map(f64::from)).map(|v| v as f32))
            .collect(),
        colors: cloud.colors.clone(),
        normals: cloud.normals.as_ref().map(|ns| {
            ns.iter()
                .map(|n| {
                    let v: [f64; 3] = (pose.rotation * Vector3::from(n.map(f64::from))).into();
                    v.map(|x| x as f32)
                })
                .collect()
        }),
    }
}

params! {
    /// Parameters of `mesh.icp`.
    pub struct IcpParams {
        /// "point_to_point" or "point_to_plane" (needs target normals). Default "point_to_point".
        method: IcpMethod = IcpMethod::PointToPoint,
        /// Pairs farther apart are dropped, scene units; none: no limit. Default none.
        max_correspondence_distance: Option<f64> = None => [min = 0.0, unit = "scene units"],
        /// Fraction of the pairs kept, the nearest (trimmed ICP); 1 keeps all. Default 1.
        trim_ratio: f64 = 1.0 => [min = 0.0, max = 1.0],
        /// Most iterations. Default 100.
        max_iterations: u32 = 100 => [min = 1, max = 100000],
        /// Stop when the RMSE changes by less than this fraction. Default 1e-10.
        relative_rmse_tolerance: f64 = 1e-10 => [min = 0.0],
        /// Stop when an increment's angle (rad) plus translation (relative to the target's RMS
        /// radius) is below this. Default 1e-10.
        transform_tolerance: f64 = 1e-10 => [min = 0.0],
    }
}

/// Iterative closest point (`mesh.icp`). See [`icp`].
#[derive(Debug, Clone, PartialEq)]
pub struct Icp {
    options: IcpOptions,
}

impl Op for Icp {
    type Params = IcpParams;
    const ID: &'static str = "mesh.icp";
    const SUMMARY: &'static str = "Rigidly aligns a source point cloud to a target: ICP, point-to-point or point-to-plane, trimmed.";
    const DOC: &'static str = r#"
Estimates `target_from_source` (x_target = R·x_source + t) from `initial` (identity when not
connected) by alternating nearest-neighbour pairing and a least-squares update:
- "point_to_point": closed-form rotation of the centred pairs by SVD, det fixed to +1
  (Besl & McKay 1992; Umeyama 1991);
- "point_to_plane": Σ((R·y + t − q)·n_q)² linearized (Low 2004), solved as 6×6 least squares,
  then the exact rotation exp([ω]×) applied. It needs unit normals on the target (run
  mesh.estimate_normals first); a target without normals is an error.

Pairs farther than `max_correspondence_distance` are dropped; `trim_ratio < 1` keeps only that
fraction of the nearest pairs (trimmed ICP, Chetverikov et al., ICPR 2002), which is what makes
partial overlap work: set it a little below the expected overlap. Everything runs in f64 on
coordinates centred on the target's centroid and scaled by its RMS radius. It stops when an
increment is below `transform_tolerance`, when the RMSE changes by a relative amount below
`relative_rmse_tolerance`, or after `max_iterations` increments.

ICP converges to the nearest local minimum: start within a few tens of degrees.

Metrics: `rmse` (of the kept pairs at the result, scene units), `fitness` (fraction of source
points with a target point within the distance), `correspondences`, `iterations`, `converged`
(1 or 0).

Example:
    "align": (op: "mesh.icp", inputs: { "source": "scan.cloud", "target": "model.cloud" },
              params: (method: "point_to_plane", trim_ratio: 0.9)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("source", PortType::PointCloud, "The cloud to move."),
            PortSpec::new(
                "target",
                PortType::PointCloud,
                "The fixed cloud (with normals for point_to_plane).",
            ),
            PortSpec::new(
                "initial",
                PortType::Pose,
                "Initial target_from_source; identity when not connected.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "target_from_source",
                PortType::Pose,
                "The estimated transform, x_target = R·x_source + t.",
            ),
            PortSpec::new(
                "aligned",
                PortType::PointCloud,
                "The source moved by target_from_source.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "rmse, fitness, correspondences, iterations, converged.",
            ),
        ]
    }

    fn new(p: IcpParams) -> Result<Self, String> {
        let options = IcpOptions {
            method: p.method,
            max_correspondence_distance: p.max_correspondence_distance.unwrap_or(f64::INFINITY),
            trim_ratio: p.trim_ratio,
            max_iterations: p.max_iterations as usize,
            relative_rmse_tolerance: p.relative_rmse_tolerance,
            transform_tolerance: p.transform_tolerance,
        };
        check_options(&options)?;
        Ok(Icp { options })
    }
}

fn pose_input(inputs: &Inputs<'_>, port: &str) -> Result<Option<Rigid>, OpError> {
    match inputs.get(port) {
        None => Ok(None),
        Some(Value::Pose(p)) => {
            if p.rotation
                .iter()
                .chain(&p.translation)
                .all(|v| v.is_finite())
            {
                Ok(Some(Rigid::from_pose(p)))
            } else {
                Err(OpError::input(port, "the pose is not finite"))
            }
        }
        Some(other) => Err(OpError::input(
            port,
            format!("expected Pose, got {}", other.port_type()),
        )),
    }
}

impl Operator for Icp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let source_cloud = cloud_input(inputs, "source")?;
        let target_cloud = cloud_input(inputs, "target")?;
        let source = positions_f64(source_cloud).map_err(|e| e.at("source"))?;
        let target = positions_f64(target_cloud).map_err(|e| e.at("target"))?;
        let normals = normals_f64(target_cloud);
        let initial = pose_input(inputs, "initial")?.unwrap_or_else(Rigid::identity);
        let report = icp(
            &source,
            &target,
            normals.as_deref(),
            &initial,
            &self.options,
        )
        .map_err(|e| match e {
            IcpError::TooFewPoints { cloud, .. } => OpError::input(cloud, e.to_string()),
            IcpError::MissingNormals | IcpError::CoincidentTarget => {
                OpError::input("target", e.to_string())
            }
            _ => OpError::failed(e.to_string()),
        })?;
        let mut m = Metrics::new();
        m.insert("rmse".into(), report.rmse);
        m.insert("fitness".into(), report.fitness);
        m.insert("correspondences".into(), report.correspondences as f64);
        m.insert("iterations".into(), report.iterations as f64);
        m.insert("converged".into(), f64::from(u8::from(report.converged)));
        let aligned = transform_cloud(source_cloud, &report.target_from_source);
        Ok(Outputs::new()
            .with(
                "target_from_source",
                Value::Pose(report.target_from_source.to_pose()),
            )
            .with("aligned", Value::PointCloud(Arc::new(aligned)))
            .with("metrics", Value::metrics(m)))
    }
}

params! {
    /// Parameters of `mesh.transform`.
    pub struct TransformParams {
        /// Apply the inverse of the pose instead. Default false.
        invert: bool = false,
    }
}

/// Rigid transform of a point cloud (`mesh.transform`). See [`transform_cloud`].
#[derive(Debug, Clone, PartialEq)]
pub struct Transform {
    invert: bool,
}

impl Op for Transform {
    type Params = TransformParams;
    const ID: &'static str = "mesh.transform";
    const SUMMARY: &'static str = "Moves a point cloud by a rigid pose (positions and normals).";
    const DOC: &'static str = r#"
Maps every point by `pose` (x_to = R·x_from + t, or its inverse with `invert: true`), in f64,
and rotates normals by R; colors are unchanged. Builds test cases for mesh.icp and applies its
result.

Example:
    "moved": (op: "mesh.transform", inputs: { "cloud": "model.cloud", "pose": "align.target_from_source" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("cloud", PortType::PointCloud, "The points."),
            PortSpec::new("pose", PortType::Pose, "The rigid transform to apply."),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "cloud",
            PortType::PointCloud,
            "The moved points.",
        )]
    }

    fn new(p: TransformParams) -> Result<Self, String> {
        Ok(Transform { invert: p.invert })
    }
}

impl Operator for Transform {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        positions_f64(cloud).map_err(|e| e.at("cloud"))?;
        let pose =
            pose_input(inputs, "pose")?.ok_or_else(|| OpError::input("pose", "not connected"))?;
        let pose = if self.invert { pose.inverse() } else { pose };
        Ok(Outputs::new().with(
            "cloud",
            Value::PointCloud(Arc::new(transform_cloud(cloud, &pose))),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::pointcloud::{Orientation, oriented_normals};
    use ocellus_engine::op::{Inputs, Operator};

    /// A shape without symmetry: three offset, differently sized ellipsoids, sampled with a
    /// seeded RNG (points on each surface). Extent about 4.4 × 2.6 × 1.9.
    pub(crate) fn blob(n: usize, offset: [f64; 3], seed: u64) -> Vec<[f64; 3]> {
        let parts: [([f64; 3], [f64; 3]); 3] = [
            ([0.0, 0.0, 0.0], [2.0, 1.0, 0.6]),
            ([1.4, 0.7, 0.3], [0.6, 0.5, 0.4]),
            ([-1.3, -0.4, 0.5], [0.5, 0.3, 0.45]),
        ];
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|i| {
                let (c, r) = parts[[0, 0, 0, 1, 2][i % 5]];
                let z = 2.0 * rng.uniform() - 1.0;
                let phi = 2.0 * std::f64::consts::PI * rng.uniform();
                let s = (1.0 - z * z).max(0.0).sqrt();
                let u = [s * phi.cos(), s * phi.sin(), z];
                [0, 1, 2].map(|a| offset[a] + c[a] + r[a] * u[a])
            })
            .collect()
    }

    /// `angle_deg` about an oblique axis and a translation.
    fn pose(angle_deg: f64, t: [f64; 3]) -> Rigid {
        let axis = Vector3::new(1.0, -2.0, 0.7).normalize();
        Rigid {
            rotation: rotation_from_vector(&(axis * angle_deg.to_radians())),
            translation: Vector3::from(t),
        }
    }

    /// Rotation error (rad) and translation error relative to `size`, the latter measured at
    /// the scene's `center` (where a transform far from the origin is well conditioned: its
    /// `t` alone absorbs rotation noise times the distance to the origin).
    fn errors_at(got: &Rigid, want: &Rigid, size: f64, center: [f64; 3]) -> (f64, f64) {
        let (a, b) = (got.apply(&center), want.apply(&center));
        (
            rotation_angle(&(got.rotation * want.rotation.transpose())),
            (Vector3::from(a) - Vector3::from(b)).norm() / size,
        )
    }

    fn errors(got: &Rigid, want: &Rigid, size: f64) -> (f64, f64) {
        errors_at(got, want, size, [0.0; 3])
    }

    fn normals_of(points: &[[f64; 3]]) -> Vec<[f64; 3]> {
        let tree = KdTree::new(points.to_vec());
        oriented_normals(&tree, 12, None, Orientation::Consistent, [0.0; 3]).unwrap()
    }

    #[test]
    fn recovers_a_known_transform_from_30_degrees_both_methods() {
        for offset in [[0.0; 3], [1e6, -1e6, 2e6]] {
            let target = blob(3000, offset, 1);
            let normals = normals_of(&target);
            // 30° about the shape's own centre (conjugated by the offset), then a translation.
            let shift = Rigid {
                rotation: Matrix3::identity(),
                translation: Vector3::from(offset),
            };
            let truth = shift
                .compose(&pose(30.0, [0.3, -0.2, 0.5]))
                .compose(&shift.inverse());
            let source: Vec<[f64; 3]> = target.iter().map(|p| truth.inverse().apply(p)).collect();
            for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
                let options = IcpOptions {
                    method,
                    ..IcpOptions::default()
                };
                let r = icp(
                    &source,
                    &target,
                    Some(&normals),
                    &Rigid::identity(),
                    &options,
                )
                .unwrap_or_else(|e| panic!("{method:?} {offset:?}: {e}"));
                let (er, et) = errors_at(&r.target_from_source, &truth, 4.4, offset);
                assert!(
                    er < 1e-6 && et < 1e-6,
                    "{method:?} {offset:?}: {er} {et} {r:?}"
                );
                assert!(r.converged && r.fitness == 1.0, "{r:?}");
                assert!(r.rmse < 1e-6 * 4.4);
            }
        }
    }

    #[test]
    fn trimming_handles_30_percent_partial_overlap() {
        let full = blob(4000, [0.0; 3], 2);
        // The target lacks the 30 % of the shape with the largest x: those source points have
        // no counterpart.
        let mut xs: Vec<f64> = full.iter().map(|p| p[0]).collect();
        xs.sort_by(f64::total_cmp);
        let cut = xs[(0.7 * xs.len() as f64) as usize];
        let target: Vec<[f64; 3]> = full.iter().copied().filter(|p| p[0] < cut).collect();
        let normals = normals_of(&target);
        let truth = pose(20.0, [0.2, 0.1, -0.3]);
        let source: Vec<[f64; 3]> = full.iter().map(|p| truth.inverse().apply(p)).collect();
        for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
            let trimmed = IcpOptions {
                method,
                trim_ratio: 0.6,
                ..IcpOptions::default()
            };
            let r = icp(
                &source,
                &target,
                Some(&normals),
                &Rigid::identity(),
                &trimmed,
            )
            .unwrap_or_else(|e| panic!("{method:?}: {e}"));
            let (er, et) = errors(&r.target_from_source, &truth, 4.4);
            assert!(er < 1e-6 && et < 1e-6, "{method:?}: {er} {et} {r:?}");
            // Untrimmed, the unmatched 30 % pull the result away.
            let plain = IcpOptions {
                method,
                ..IcpOptions::default()
            };
            let r = icp(&source, &target, Some(&normals), &Rigid::identity(), &plain).unwrap();
            let (er, et) = errors(&r.target_from_source, &truth, 4.4);
            assert!(er > 1e-3 || et > 1e-3, "{method:?}: {er} {et}");
        }
    }

    #[test]
    fn steps_on_the_blob_are_well_posed() {
        let target = blob(3000, [0.0; 3], 1);
        let normals = normals_of(&target);
        let pairs: Vec<Pair> = (0..target.len())
            .map(|i| Pair {
                source: i,
                target: i,
                dist2: 0.0,
            })
            .collect();
        let truth = pose(5.0, [0.01, 0.0, 0.0]);
        let moved: Vec<[f64; 3]> = target.iter().map(|p| truth.inverse().apply(p)).collect();
        let p2p = point_to_point_step(&moved, &target, &pairs);
        let p2l = point_to_plane_step(&moved, &target, &normals, &pairs);
        assert!(p2p.is_some(), "point to point");
        assert!(p2l.is_some(), "point to plane");
        // Exact pairs: one point-to-point step is the transform.
        let (er, et) = errors(&p2p.unwrap_or_else(Rigid::identity), &truth, 4.4);
        assert!(er < 1e-12 && et < 1e-12, "{er} {et}");
    }

    #[test]
    fn errors_are_typed() {
        let target = blob(100, [0.0; 3], 3);
        let id = Rigid::identity();
        let o = IcpOptions::default();
        assert_eq!(
            icp(&[], &target, None, &id, &o),
            Err(IcpError::TooFewPoints {
                cloud: "source",
                got: 0,
                needed: 3
            })
        );
        let p2l = IcpOptions {
            method: IcpMethod::PointToPlane,
            ..IcpOptions::default()
        };
        assert_eq!(
            icp(&target, &target, None, &id, &p2l),
            Err(IcpError::MissingNormals)
        );
        assert_eq!(
            icp(&target, &[[1.0; 3]; 5], None, &id, &o),
            Err(IcpError::CoincidentTarget)
        );
        let near = IcpOptions {
            max_correspondence_distance: 1e-3,
            ..IcpOptions::default()
        };
        let far: Vec<[f64; 3]> = target.iter().map(|p| [p[0] + 100.0, p[1], p[2]]).collect();
        assert!(matches!(
            icp(&far, &target, None, &id, &near),
            Err(IcpError::TooFewCorrespondences { iteration: 0, .. })
        ));
        let line: Vec<[f64; 3]> = (0..10).map(|i| [i as f64, 0.0, 0.0]).collect();
        let shifted: Vec<[f64; 3]> = line.iter().map(|p| [p[0] + 0.3, 0.1, 0.0]).collect();
        assert!(matches!(
            icp(&shifted, &line, None, &id, &o),
            Err(IcpError::Degenerate { .. })
        ));
        let bad = IcpOptions {
            trim_ratio: 0.0,
            ..IcpOptions::default()
        };
        assert!(matches!(
            icp(&target, &target, None, &id, &bad),
            Err(IcpError::InvalidOptions(_))
        ));
    }

    #[test]
    fn result_does_not_depend_on_the_thread_count() {
        let target = blob(6000, [0.0; 3], 4);
        let truth = pose(10.0, [0.1, 0.0, 0.0]);
        let mut rng = SplitMix64::new(5);
        // Noisy source, so the iterations do real work to the end.
        let source: Vec<[f64; 3]> = target
            .iter()
            .map(|p| truth.inverse().apply(p).map(|v| v + 0.01 * rng.normal()))
            .collect();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    icp(
                        &source,
                        &target,
                        None,
                        &Rigid::identity(),
                        &IcpOptions::default(),
                    )
                    .unwrap()
                })
        };
        assert_eq!(run(1), run(4));
    }

    #[test]
    fn transform_op_moves_points_and_rotates_normals() {
        let cloud = PointCloud {
            positions: vec![[1.0, 0.0, 0.0]],
            colors: Some(vec![[1, 2, 3]]),
            normals: Some(vec![[0.0, 1.0, 0.0]]),
        };
        // 90° about z, then +1 in z.
        let pose = Rigid {
            rotation: rotation_from_vector(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2)),
            translation: Vector3::new(0.0, 0.0, 1.0),
        };
        let op = Transform { invert: false };
        let specs = Transform::inputs();
        let values = [
            Some(Value::PointCloud(Arc::new(cloud.clone()))),
            Some(Value::Pose(pose.to_pose())),
        ];
        let ctx = RunContext {
            node: "t".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::PointCloud(moved)) = out.take("cloud") else {
            panic!("no cloud")
        };
        let close = |a: [f32; 3], b: [f32; 3]| (0..3).all(|i| (a[i] - b[i]).abs() < 1e-6);
        assert!(close(moved.positions[0], [0.0, 1.0, 1.0]), "{moved:?}");
        assert!(close(moved.normals.as_ref().unwrap()[0], [-1.0, 0.0, 0.0]));
        assert_eq!(moved.colors, cloud.colors);
        let back = transform_cloud(&moved, &pose.inverse());
        assert!(close(back.positions[0], cloud.positions[0]));
    }
}
