//! `geometry.triangulate`: two-view triangulation (linear DLT, midpoint, optimal) with quality
//! checks and an uncertainty estimate per point.
//!
//! - [`triangulate_dlt`]: the homogeneous linear method (Hartley & Zisserman §12.2) for any
//!   number of views. The world frame is first centred on the mean camera centre and scaled by
//!   the camera spread, every equation row is scaled to unit norm, and the null vector of the
//!   stacked system is taken from an SVD (a 4×4 one-sided Jacobi SVD for two views), so scene scales from 1e-3 to 1e6 behave alike and a
//!   point at infinity comes back as `w ≈ 0` instead of a huge or NaN position.
//! - [`triangulate_midpoint`]: the midpoint of the shortest segment between the two rays;
//!   `None` for parallel rays.
//! - [`optimal_correction`]: Lindstrom's two-iteration correction ("Triangulation made easy",
//!   CVPR 2010, `niter2`), which moves both observations the least (in pixels) so that they
//!   satisfy the epipolar constraint exactly; the corrected rays then intersect and are
//!   triangulated linearly. It agrees with Hartley–Sturm's polynomial method to rounding in all
//!   but contrived configurations and costs a few dozen flops.
//!
//! Checks and uncertainty ([`Triangulated`]): triangulation angle (between the two rays at the
//! point), depth in both cameras, reprojection error in both images, and a first-order
//! covariance `σ² (JᵀJ)⁻¹` of the point from the 4×3 Jacobian `J` of the two projections (px per
//! world unit) and a pixel noise `σ`; `depth_std` is its standard deviation along camera 1's
//! viewing ray.

use std::sync::Arc;

use nalgebra::{Matrix3, Matrix4, Vector2, Vector3, Vector4};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, PointCloud, Value};
use ocellus_engine::{param_enum, params};

use super::pose_util::{
    Intrinsics, gt, input_intrinsics, input_points2, input_pose, matrix_value, skew,
};

/// A calibrated view: pose `camera_from_world` (`x_cam = R x_world + t`) and intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Rotation `camera_from_world`.
    pub r: Matrix3<f64>,
    /// Translation `camera_from_world`.
    pub t: Vector3<f64>,
    /// Pinhole intrinsics.
    pub k: Intrinsics,
}

impl View {
    /// Camera centre in world coordinates, `−Rᵀt`.
    pub fn center(&self) -> Vector3<f64> {
        -(self.r.transpose() * self.t)
    }
}

param_enum! {
    /// Triangulation method.
    pub enum TriangulationMethod {
        /// Linear homogeneous DLT (normalized).
        Dlt = "dlt",
        /// Midpoint of the common perpendicular of the two rays.
        Midpoint = "midpoint",
        /// Optimal two-view correction (Lindstrom 2010) followed by DLT.
        Optimal = "optimal",
    }
}

/// One triangulated point with its checks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulated {
    /// Homogeneous world point `(X, w)`, unit norm; `w ≈ 0` for a point at infinity.
    pub homogeneous: Vector4<f64>,
    /// Euclidean world point, `None` at infinity (or for parallel rays with the midpoint method).
    pub point: Option<Vector3<f64>>,
    /// Angle between the two viewing rays at the point, degrees (0 at infinity).
    pub angle_deg: f64,
    /// Depth (z) in camera 1 and camera 2, world units (0 when not finite).
    pub depths: [f64; 2],
    /// Largest reprojection error of the two observations, pixels (∞ when not finite).
    pub error_px: f64,
    /// First-order covariance of the point, world units² (∞ diagonal when undetermined).
    pub covariance: Matrix3<f64>,
    /// Standard deviation of the point along camera 1's viewing ray, world units.
    pub depth_std: f64,
}

impl Triangulated {
    /// Finite, in front of both cameras, and seen under at least `min_angle_deg`.
    pub fn is_valid(&self, min_angle_deg: f64) -> bool {
        self.point.is_some()
            && self.depths[0] > 0.0
            && self.depths[1] > 0.0
            && self.angle_deg >= min_angle_deg
    }
}

/// Homogeneous linear triangulation from any number of views (`views.len() == pixels.len() ≥ 2`).
/// Returns the unit-norm homogeneous world point, or `None` when the input is not finite or
/// there are fewer than two views.
pub fn triangulate_dlt(views: &[View], pixels: &[[f64; 2]]) -> Option<Vector4<f64>> {
    if views.len() < 2 || views.len() != pixels.len() {
        return None;
    }
    // Normalizing similarity: world = s·x' + c (no allocation: two passes over the views).
    let c = views.iter().map(View::center).sum::<Vector3<f64>>() / views.len() as f64;
    let spread = views
        .iter()
        .map(|v| (v.center() - c).norm())
        .fold(0.0, f64::max);
    let s = if spread > 0.0 && spread.is_finite() {
        spread
    } else {
        1.0
    };
    // Unit-norm rows; the first four are kept on the stack for the two-view case, more views
    // accumulate the normal matrix.
    let mut first = [Vector4::<f64>::zeros(); 4];
    let mut count = 0usize;
    let mut ata = Matrix4::<f64>::zeros();
    for (v, p) in views.iter().zip(pixels) {
        let x = v.k.normalize(*p);
        let tn = (v.r * c + v.t) / s;
        let r0 = Vector4::new(v.r[(0, 0)], v.r[(0, 1)], v.r[(0, 2)], tn.x);
        let r1 = Vector4::new(v.r[(1, 0)], v.r[(1, 1)], v.r[(1, 2)], tn.y);
        let r2 = Vector4::new(v.r[(2, 0)], v.r[(2, 1)], v.r[(2, 2)], tn.z);
        for row in [r0 - r2 * x.x, r1 - r2 * x.y] {
            let n = row.norm();
            if n > 0.0 && n.is_finite() {
                let row = row / n;
                if count < 4 {
                    first[count] = row;
                }
                if views.len() > 2 {
                    ata += row * row.transpose();
                }
                count += 1;
            }
        }
    }
    if count < 3 {
        return None;
    }
    let h = if count <= 4 {
        // Three or four rows (two views): the right singular vector of the smallest singular
        // value by one-sided Jacobi, which keeps the small singular values to full relative
        // accuracy (unlike the normal matrix, whose condition number is squared).
        null_vector4(&first)?
    } else {
        let eig = ata.symmetric_eigen();
        let i = eig.eigenvalues.imin();
        eig.eigenvectors.column(i).into_owned()
    };
    // Back to the world frame: (s·x' + c·w, w).
    let world = Vector4::new(
        s * h.x + c.x * h.w,
        s * h.y + c.y * h.w,
        s * h.z + c.z * h.w,
        h.w,
    );
    let n = world.norm();
    if !n.is_finite() || n == 0.0 {
        return None;
    }
    Some(world / n)
}

/// Right singular vector of the smallest singular value of the 4×4 matrix with rows `rows`
/// (unused rows zero), by Hestenes' one-sided Jacobi SVD: plane rotations `V` orthogonalize the
/// columns of `A·V`; then the column norms are the singular values and the columns of `V` the
/// right singular vectors. Sweeps in a fixed order until no pair is rotated (at most 30;
/// typically 3–4).
fn null_vector4(rows: &[Vector4<f64>; 4]) -> Option<Vector4<f64>> {
    // Columns of A (cols[j][i] = A[i][j]) and of V.
    let mut cols = [[0.0f64; 4]; 4];
    for (i, r) in rows.iter().enumerate() {
        for j in 0..4 {
            cols[j][i] = r[j];
        }
    }
    let mut v = [[0.0f64; 4]; 4];
    for (j, vj) in v.iter_mut().enumerate() {
        vj[j] = 1.0;
    }
    let dot = |a: &[f64; 4], b: &[f64; 4]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
    // Rotates rows p < q of `m` in their plane.
    let rotate = |m: &mut [[f64; 4]; 4], p: usize, q: usize, cs: f64, sn: f64| {
        let (head, tail) = m.split_at_mut(q);
        for (a, b) in head[p].iter_mut().zip(tail[0].iter_mut()) {
            let (x, y) = (*a, *b);
            *a = cs * x - sn * y;
            *b = sn * x + cs * y;
        }
    };
    for _ in 0..30 {
        let mut rotated = false;
        for p in 0..3 {
            for q in p + 1..4 {
                let alpha = dot(&cols[p], &cols[p]);
                let beta = dot(&cols[q], &cols[q]);
                let gamma = dot(&cols[p], &cols[q]);
                // Columns already orthogonal to working precision (squared test, no root).
                if gamma * gamma <= f64::EPSILON * f64::EPSILON * alpha * beta {
                    continue;
                }
                let zeta = (beta - alpha) / (2.0 * gamma);
                // tan of the rotation angle, the smaller root; 1/(2ζ) where ζ² would overflow.
                let t = if zeta.abs() < 1e150 {
                    zeta.signum() / (zeta.abs() + (1.0 + zeta * zeta).sqrt())
                } else {
                    0.5 / zeta
                };
                // A rotation by less than the rounding unit changes nothing (it also stops the
                // sweeps when a column is numerically zero and its product is pure rounding).
                if t.abs() <= f64::EPSILON {
                    continue;
                }
                let cs = 1.0 / (1.0 + t * t).sqrt();
                let sn = cs * t;
                rotate(&mut cols, p, q, cs, sn);
                rotate(&mut v, p, q, cs, sn);
                rotated = true;
            }
        }
        if !rotated {
            break;
        }
    }
    let norms = cols.map(|col| dot(&col, &col));
    let i = (0..4).fold(0, |best, j| if norms[j] < norms[best] { j } else { best });
    let out = Vector4::from(v[i]);
    out.iter().all(|x| x.is_finite()).then_some(out)
}

/// Midpoint of the shortest segment joining the two viewing rays; `None` when they are parallel
/// (relative to working precision).
pub fn triangulate_midpoint(
    v1: &View,
    v2: &View,
    p1: [f64; 2],
    p2: [f64; 2],
) -> Option<Vector3<f64>> {
    let (c1, c2) = (v1.center(), v2.center());
    let x1 = v1.k.normalize(p1);
    let x2 = v2.k.normalize(p2);
    let d1 = (v1.r.transpose() * Vector3::new(x1.x, x1.y, 1.0)).normalize();
    let d2 = (v2.r.transpose() * Vector3::new(x2.x, x2.y, 1.0)).normalize();
    let w = c1 - c2;
    let b = d1.dot(&d2);
    let denom = 1.0 - b * b;
    if denom <= 1e-14 {
        return None;
    }
    let (dw1, dw2) = (d1.dot(&w), d2.dot(&w));
    let s1 = (b * dw2 - dw1) / denom;
    let s2 = (dw2 - b * dw1) / denom;
    let m = (c1 + d1 * s1 + c2 + d2 * s2) * 0.5;
    m.iter().all(|v| v.is_finite()).then_some(m)
}

/// The fundamental matrix `F` (`x2ᵀ F x1 = 0`, pixels) of two views.
pub fn fundamental_from_views(v1: &View, v2: &View) -> Matrix3<f64> {
    let r = v2.r * v1.r.transpose();
    let t = v2.t - r * v1.t;
    let e = skew(&t) * r;
    let k1i =
        v1.k.matrix()
            .try_inverse()
            .unwrap_or_else(Matrix3::identity);
    let k2i =
        v2.k.matrix()
            .try_inverse()
            .unwrap_or_else(Matrix3::identity);
    k2i.transpose() * e * k1i
}

/// Lindstrom's optimal correction (niter2): the points `x̂1, x̂2` nearest (sum of squared pixel
/// distances) to `x1, x2` with `x̂2ᵀ F x̂1 = 0`. Returns the inputs unchanged when `F` gives no
/// constraint (zero gradient), e.g. for a zero baseline.
pub fn optimal_correction(f: &Matrix3<f64>, x1: [f64; 2], x2: [f64; 2]) -> ([f64; 2], [f64; 2]) {
    // Lindstrom's notation: x ᵀ E x' = 0 with x = x2 (rows), x' = x1 (columns).
    let e = f;
    let xh = Vector3::new(x2[0], x2[1], 1.0);
    let xph = Vector3::new(x1[0], x1[1], 1.0);
    let et = Matrix3::from_fn(|i, j| if i < 2 && j < 2 { e[(i, j)] } else { 0.0 });
    let ex = e * xph;
    let etx = e.transpose() * xh;
    let mut n = Vector2::new(ex.x, ex.y);
    let mut np = Vector2::new(etx.x, etx.y);
    let e2 = et.fixed_view::<2, 2>(0, 0).into_owned();
    let a = n.dot(&(e2 * np));
    let b = 0.5 * (n.norm_squared() + np.norm_squared());
    let c = xh.dot(&ex);
    let disc = b * b - a * c;
    if !gt(b, 0.0) || !disc.is_finite() || disc < 0.0 {
        return (x1, x2);
    }
    let d = disc.sqrt();
    let mut lambda = c / (b + d);
    let dx = n * lambda;
    let dxp = np * lambda;
    n -= e2 * dxp;
    np -= e2.transpose() * dx;
    let nn = n.norm_squared() + np.norm_squared();
    if nn > 0.0 {
        lambda *= 2.0 * d / nn;
    }
    let dx = n * lambda;
    let dxp = np * lambda;
    let c2 = [x2[0] - dx.x, x2[1] - dx.y];
    let c1 = [x1[0] - dxp.x, x1[1] - dxp.y];
    if c1.iter().chain(&c2).all(|v| v.is_finite()) {
        (c1, c2)
    } else {
        (x1, x2)
    }
}

/// Triangulates one correspondence (pixels) with `method` and evaluates the checks against the
/// original observations; `sigma_px` is the pixel noise for the covariance.
pub fn triangulate_pair(
    v1: &View,
    v2: &View,
    f: &Matrix3<f64>,
    p1: [f64; 2],
    p2: [f64; 2],
    method: TriangulationMethod,
    sigma_px: f64,
) -> Triangulated {
    let h = match method {
        TriangulationMethod::Dlt => triangulate_dlt(&[*v1, *v2], &[p1, p2]),
        TriangulationMethod::Midpoint => triangulate_midpoint(v1, v2, p1, p2)
            .map(|m| Vector4::new(m.x, m.y, m.z, 1.0).normalize()),
        TriangulationMethod::Optimal => {
            let (c1, c2) = optimal_correction(f, p1, p2);
            triangulate_dlt(&[*v1, *v2], &[c1, c2])
        }
    };
    evaluate(v1, v2, h, p1, p2, sigma_px)
}

/// Largest |w|/‖X‖ treated as a point at infinity.
const INFINITY_W: f64 = 1e-12;

/// Checks and covariance of a homogeneous point against the observations.
pub fn evaluate(
    v1: &View,
    v2: &View,
    h: Option<Vector4<f64>>,
    p1: [f64; 2],
    p2: [f64; 2],
    sigma_px: f64,
) -> Triangulated {
    let unknown = Triangulated {
        homogeneous: h.unwrap_or_else(Vector4::zeros),
        point: None,
        angle_deg: 0.0,
        depths: [0.0, 0.0],
        error_px: f64::INFINITY,
        covariance: Matrix3::from_diagonal_element(f64::INFINITY),
        depth_std: f64::INFINITY,
    };
    let Some(h) = h else {
        return unknown;
    };
    let xyz = Vector3::new(h.x, h.y, h.z);
    if h.w.abs() <= INFINITY_W * xyz.norm() {
        return unknown;
    }
    let x = xyz / h.w;
    if !x.iter().all(|v| v.is_finite()) {
        return unknown;
    }
    let (c1, c2) = (v1.center(), v2.center());
    let (a, b) = (x - c1, x - c2);
    let angle_deg = a.cross(&b).norm().atan2(a.dot(&b)).to_degrees();
    let mut error_px: f64 = 0.0;
    let mut jtj = Matrix3::<f64>::zeros();
    let mut depths = [0.0; 2];
    for (i, (v, p)) in [(v1, p1), (v2, p2)].into_iter().enumerate() {
        let xc = v.r * x + v.t;
        depths[i] = xc.z;
        if xc.z == 0.0 {
            error_px = f64::INFINITY;
            continue;
        }
        let q = v.k.project(&xc);
        error_px = error_px.max(((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt());
        let iz = 1.0 / xc.z;
        // d(u,v)/d(xc), then times R.
        let du = Vector3::new(v.k.fx * iz, 0.0, -v.k.fx * xc.x * iz * iz);
        let dv = Vector3::new(0.0, v.k.fy * iz, -v.k.fy * xc.y * iz * iz);
        let ju = v.r.transpose() * du;
        let jv = v.r.transpose() * dv;
        jtj += ju * ju.transpose() + jv * jv.transpose();
    }
    let (covariance, depth_std) = match jtj.try_inverse() {
        Some(inv) if inv.iter().all(|v| v.is_finite()) && error_px.is_finite() => {
            let cov = inv * (sigma_px * sigma_px);
            let ray = a.normalize();
            let var = (ray.transpose() * cov * ray)[(0, 0)].max(0.0);
            (cov, var.sqrt())
        }
        _ => (Matrix3::from_diagonal_element(f64::INFINITY), f64::INFINITY),
    };
    Triangulated {
        homogeneous: h,
        point: Some(x),
        angle_deg,
        depths,
        error_px,
        covariance,
        depth_std,
    }
}

/// Triangulates every correspondence of two views (see [`triangulate_pair`]).
pub fn triangulate_points(
    v1: &View,
    v2: &View,
    points1: &[[f64; 2]],
    points2: &[[f64; 2]],
    method: TriangulationMethod,
    sigma_px: f64,
) -> Result<Vec<Triangulated>, String> {
    if points1.len() != points2.len() {
        return Err(format!(
            "point lists differ in length: {} vs {}",
            points1.len(),
            points2.len()
        ));
    }
    if points1
        .iter()
        .chain(points2)
        .flatten()
        .any(|v| !v.is_finite())
    {
        return Err("non-finite point".into());
    }
    let f = fundamental_from_views(v1, v2);
    Ok(points1
        .iter()
        .zip(points2)
        .map(|(p1, p2)| triangulate_pair(v1, v2, &f, *p1, *p2, method, sigma_px))
        .collect())
}

params! {
    /// Parameters of `geometry.triangulate`.
    pub struct TriangulateParams {
        /// Method: "dlt" (linear, normalized), "midpoint", or "optimal" (Lindstrom's correction,
        /// then DLT). Default "optimal".
        method: TriangulationMethod = TriangulationMethod::Optimal,
        /// Smallest triangulation angle of a valid point, degrees, ≥ 0. Default 1.
        min_angle_deg: f64 = 1.0 => [min = 0.0, max = 180.0, unit = "deg"],
        /// Largest reprojection error of a valid point, px; none = no limit. Default none.
        max_error_px: Option<f64> = None => [min = 0.0, unit = "px"],
        /// Pixel noise standard deviation for the covariance, px, > 0. Default 1.
        sigma_px: f64 = 1.0 => [min = 0.0, unit = "px"],
    }
}

/// Two-view triangulation (`geometry.triangulate`). See [`triangulate_points`].
#[derive(Debug, Clone, PartialEq)]
pub struct Triangulate {
    method: TriangulationMethod,
    min_angle_deg: f64,
    max_error_px: Option<f64>,
    sigma_px: f64,
}

impl Op for Triangulate {
    type Params = TriangulateParams;
    const ID: &'static str = "geometry.triangulate";
    const SUMMARY: &'static str =
        "Triangulates 3-D points from two posed, calibrated views and flags weak ones.";
    const DOC: &'static str = r#"
Triangulates each correspondence `points1[i] ↔ points2[i]` (pixels) seen from two cameras with
poses `pose1`, `pose2` (camera_from_world) and pinhole intrinsics (`camera`, and `camera2` for
the second view when it differs; distortion terms must be zero — undistort first).

Methods: "dlt" is the homogeneous linear method (Hartley & Zisserman §12.2) in a world frame
centred on the cameras and scaled by the baseline, rows scaled to unit norm (OpenCV's
`triangulatePoints` is the same method without the normalization); "midpoint" is the midpoint of
the common perpendicular of the rays; "optimal" first moves both observations the least, in
pixels, onto the epipolar constraint (Lindstrom, "Triangulation made easy", CVPR 2010), which
is the maximum-likelihood point under Gaussian pixel noise like Hartley–Sturm 1997.

Outputs: `points` has every point in input order (invalid ones at their finite estimate, or at
the origin when the rays are parallel or the point is at infinity). `per_point` is an N×6
matrix with columns `angle_deg, error_px, depth1, depth2, depth_std, valid`: the triangulation
angle, the larger reprojection error of the two views, the depths in both cameras, the
first-order standard deviation along camera 1's ray from `σ² (JᵀJ)⁻¹` with σ = `sigma_px` (−1
when undetermined), and 1/0. A point is valid when finite, in front of both cameras, seen
under ≥ `min_angle_deg`, and within `max_error_px` when set. `metrics`: `count`, `valid`,
`median_angle_deg`, `mean_error_px` (over valid points; 0 when none).

Example:
    "cloud": (op: "geometry.triangulate", inputs: { "pose1": "p.pose1", "pose2": "p.pose2", "camera": "cam.camera", "points1": "m.points1", "points2": "m.points2" }, params: (method: "optimal")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("pose1", PortType::Pose, "Camera 1 pose, camera_from_world."),
            PortSpec::new("pose2", PortType::Pose, "Camera 2 pose, camera_from_world."),
            PortSpec::new(
                "camera",
                PortType::Camera,
                "Intrinsics of camera 1 (and 2).",
            ),
            PortSpec::new(
                "camera2",
                PortType::Camera,
                "Intrinsics of camera 2, if different.",
            )
            .optional(),
            PortSpec::new(
                "points1",
                PortType::Points2D,
                "Observations in image 1, px.",
            ),
            PortSpec::new(
                "points2",
                PortType::Points2D,
                "Observations in image 2, px.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "points",
                PortType::PointCloud,
                "Triangulated points, world frame.",
            ),
            PortSpec::new(
                "per_point",
                PortType::Matrix,
                "N×6: angle_deg, error_px, depth1, depth2, depth_std, valid.",
            ),
            PortSpec::new("metrics", PortType::Metrics, "Summary statistics."),
        ]
    }

    fn new(params: TriangulateParams) -> Result<Self, String> {
        let TriangulateParams {
            method,
            min_angle_deg,
            max_error_px,
            sigma_px,
        } = params;
        if !min_angle_deg.is_finite() || !(0.0..=180.0).contains(&min_angle_deg) {
            return Err(format!(
                "`min_angle_deg` must be in [0, 180], got {min_angle_deg}"
            ));
        }
        if let Some(e) = max_error_px
            && (!e.is_finite() || e < 0.0)
        {
            return Err(format!("`max_error_px` must be finite and ≥ 0, got {e}"));
        }
        if !sigma_px.is_finite() || sigma_px <= 0.0 {
            return Err(format!("`sigma_px` must be finite and > 0, got {sigma_px}"));
        }
        Ok(Triangulate {
            method,
            min_angle_deg,
            max_error_px,
            sigma_px,
        })
    }
}

impl Operator for Triangulate {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let (r1, t1) = input_pose(inputs, "pose1")?;
        let (r2, t2) = input_pose(inputs, "pose2")?;
        let k1 = input_intrinsics(inputs, "camera")?;
        let k2 = if inputs.get("camera2").is_some() {
            input_intrinsics(inputs, "camera2")?
        } else {
            k1
        };
        let p1 = input_points2(inputs, "points1")?;
        let p2 = input_points2(inputs, "points2")?;
        let v1 = View {
            r: r1,
            t: t1,
            k: k1,
        };
        let v2 = View {
            r: r2,
            t: t2,
            k: k2,
        };
        let tri = triangulate_points(&v1, &v2, &p1, &p2, self.method, self.sigma_px)
            .map_err(|e| OpError::input("points2", e))?;
        let n = tri.len();
        let mut positions = Vec::with_capacity(n);
        let mut table = Vec::with_capacity(n * 6);
        let mut angles = Vec::new();
        let mut err_sum = 0.0;
        for t in &tri {
            let valid =
                t.is_valid(self.min_angle_deg) && self.max_error_px.is_none_or(|m| t.error_px <= m);
            let p = t.point.unwrap_or_else(Vector3::zeros);
            positions.push([p.x as f32, p.y as f32, p.z as f32]);
            let finite_or = |v: f64| if v.is_finite() { v } else { -1.0 };
            table.extend_from_slice(&[
                t.angle_deg,
                finite_or(t.error_px),
                t.depths[0],
                t.depths[1],
                finite_or(t.depth_std),
                f64::from(u8::from(valid)),
            ]);
            if valid {
                angles.push(t.angle_deg);
                err_sum += t.error_px;
            }
        }
        let valid = angles.len();
        angles.sort_by(f64::total_cmp);
        let mut metrics = Metrics::new();
        metrics.insert("count".into(), n as f64);
        metrics.insert("valid".into(), valid as f64);
        metrics.insert(
            "median_angle_deg".into(),
            if valid > 0 { angles[valid / 2] } else { 0.0 },
        );
        metrics.insert(
            "mean_error_px".into(),
            if valid > 0 {
                err_sum / valid as f64
            } else {
                0.0
            },
        );
        Ok(Outputs::new()
            .with(
                "points",
                Value::PointCloud(Arc::new(PointCloud {
                    positions,
                    colors: None,
                    normals: None,
                })),
            )
            .with("per_point", matrix_value(n, 6, table)?)
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use ocellus_engine::value::{Camera, CameraModel};
    use proptest::prelude::*;

    use crate::geometry::pose_util::pose_from_rt;

    pub(crate) fn k() -> Intrinsics {
        Intrinsics::new(800.0, 780.0, 320.0, 240.0).unwrap()
    }

    pub(crate) fn views(scale: f64, baseline: f64) -> (View, View) {
        let r1 = *Rotation3::from_scaled_axis(Vector3::new(0.05, -0.1, 0.02)).matrix();
        let t1 = Vector3::new(0.1, -0.2, 0.3) * scale;
        let r2 = *Rotation3::from_scaled_axis(Vector3::new(-0.08, 0.2, 0.05)).matrix();
        let t2 = r2 * (r1.transpose() * t1) + Vector3::new(-1.0, 0.1, 0.05) * baseline * scale;
        // Camera 2 centre = camera 1 centre + R2ᵀ·(−b) offset.
        (
            View {
                r: r1,
                t: t1,
                k: k(),
            },
            View {
                r: r2,
                t: t2,
                k: k(),
            },
        )
    }

    fn project(v: &View, x: &Vector3<f64>) -> [f64; 2] {
        v.k.project(&(v.r * x + v.t))
    }

    fn rel(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
        (a - b).norm() / b.norm().max(1e-300)
    }

    #[test]
    fn exact_recovery_all_methods() {
        let (v1, v2) = views(1.0, 1.0);
        let f = fundamental_from_views(&v1, &v2);
        for x in [
            Vector3::new(0.3, -0.2, 5.0),
            Vector3::new(-1.0, 0.5, 8.0),
            Vector3::new(0.0, 0.0, 3.0),
        ] {
            let (p1, p2) = (project(&v1, &x), project(&v2, &x));
            for m in [
                TriangulationMethod::Dlt,
                TriangulationMethod::Midpoint,
                TriangulationMethod::Optimal,
            ] {
                let t = triangulate_pair(&v1, &v2, &f, p1, p2, m, 1.0);
                let p = t.point.unwrap();
                assert!(rel(&p, &x) < 1e-11, "{m:?} {p} {x}");
                assert!(t.error_px < 1e-8);
                assert!(t.is_valid(1.0));
                assert!(t.depth_std > 0.0 && t.depth_std.is_finite());
            }
        }
    }

    #[test]
    fn hand_computed_midpoint_and_angle() {
        // Two identity-rotation cameras 2 apart along x looking at (1, 0, 2).
        let kk = Intrinsics::new(1.0, 1.0, 0.0, 0.0).unwrap();
        let v1 = View {
            r: Matrix3::identity(),
            t: Vector3::zeros(),
            k: kk,
        };
        let v2 = View {
            r: Matrix3::identity(),
            t: Vector3::new(-2.0, 0.0, 0.0),
            k: kk,
        };
        let x = Vector3::new(1.0, 0.0, 2.0);
        let t = triangulate_pair(
            &v1,
            &v2,
            &fundamental_from_views(&v1, &v2),
            [0.5, 0.0],
            [-0.5, 0.0],
            TriangulationMethod::Midpoint,
            1.0,
        );
        assert!((t.point.unwrap() - x).norm() < 1e-15);
        // Rays (1,0,2) and (−1,0,2): angle 2·atan(1/2).
        assert!((t.angle_deg - 2.0 * 0.5f64.atan().to_degrees()).abs() < 1e-12);
        assert!((t.depths[0] - 2.0).abs() < 1e-15 && (t.depths[1] - 2.0).abs() < 1e-15);
    }

    #[test]
    fn optimal_correction_satisfies_constraint_and_beats_dlt() {
        let (v1, v2) = views(1.0, 1.0);
        let f = fundamental_from_views(&v1, &v2);
        let x = Vector3::new(0.4, 0.1, 6.0);
        let (mut p1, mut p2) = (project(&v1, &x), project(&v2, &x));
        p1[0] += 1.3;
        p1[1] -= 0.7;
        p2[0] -= 0.9;
        p2[1] += 1.1;
        let (c1, c2) = optimal_correction(&f, p1, p2);
        let h1 = Vector3::new(c1[0], c1[1], 1.0);
        let h2 = Vector3::new(c2[0], c2[1], 1.0);
        let scale = (f * h1).norm() * h2.norm();
        assert!((h2.dot(&(f * h1))).abs() < 1e-12 * scale);
        let cost = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
        let opt_cost = cost(c1, p1) + cost(c2, p2);
        let dlt = triangulate_pair(&v1, &v2, &f, p1, p2, TriangulationMethod::Dlt, 1.0);
        let q = dlt.point.unwrap();
        let dlt_cost = cost(project(&v1, &q), p1) + cost(project(&v2, &q), p2);
        assert!(opt_cost <= dlt_cost * (1.0 + 1e-9), "{opt_cost} {dlt_cost}");
        // Brute-force: no point on a grid around the optimum does better.
        let o = triangulate_pair(&v1, &v2, &f, p1, p2, TriangulationMethod::Optimal, 1.0)
            .point
            .unwrap();
        let o_cost = cost(project(&v1, &o), p1) + cost(project(&v2, &o), p2);
        assert!((o_cost - opt_cost).abs() < 1e-8);
        for dx in [-1e-3, 0.0, 1e-3] {
            for dy in [-1e-3, 0.0, 1e-3] {
                for dz in [-1e-2, 0.0, 1e-2] {
                    let y = o + Vector3::new(dx, dy, dz);
                    assert!(
                        cost(project(&v1, &y), p1) + cost(project(&v2, &y), p2) >= o_cost - 1e-9
                    );
                }
            }
        }
    }

    #[test]
    fn zero_baseline_is_flagged_not_garbage() {
        let (v1, _) = views(1.0, 1.0);
        let v2 = View { k: k(), ..v1 };
        let x = Vector3::new(0.3, 0.2, 4.0);
        let (p1, p2) = (project(&v1, &x), project(&v2, &x));
        for m in [
            TriangulationMethod::Dlt,
            TriangulationMethod::Midpoint,
            TriangulationMethod::Optimal,
        ] {
            let t = triangulate_points(&v1, &v2, &[p1], &[p2], m, 1.0).unwrap()[0];
            assert!(!t.is_valid(0.1), "{m:?} {t:?}");
            assert!(!t.angle_deg.is_nan() && !t.error_px.is_nan() && !t.depth_std.is_nan());
            assert!(t.homogeneous.iter().all(|v| !v.is_nan()));
        }
    }

    #[test]
    fn point_at_infinity_and_parallel_rays() {
        let (v1, v2) = views(1.0, 1.0);
        // A direction: both cameras see the same direction d (rotation only).
        let d = Vector3::new(0.1, -0.05, 1.0);
        let p1 = v1.k.project(&(v1.r * d));
        let p2 = v2.k.project(&(v2.r * d));
        let h = triangulate_dlt(&[v1, v2], &[p1, p2]).unwrap();
        let dir = Vector3::new(h.x, h.y, h.z);
        assert!(h.w.abs() < 1e-9 * dir.norm(), "{h}");
        assert!(dir.normalize().cross(&d.normalize()).norm() < 1e-9);
        let t = evaluate(&v1, &v2, Some(h), p1, p2, 1.0);
        assert!(t.point.is_none() || t.angle_deg < 1e-6);
        assert!(triangulate_midpoint(&v1, &v2, p1, p2).is_none_or(|m| m.norm() > 1e6));
    }

    #[test]
    fn dlt_rejects_bad_input() {
        let (v1, _) = views(1.0, 1.0);
        assert!(triangulate_dlt(&[v1], &[[0.0, 0.0]]).is_none());
        assert!(triangulate_dlt(&[v1, v1], &[[0.0, 0.0]]).is_none());
        assert!(
            triangulate_points(
                &v1,
                &v1,
                &[[0.0, f64::NAN]],
                &[[0.0, 0.0]],
                TriangulationMethod::Dlt,
                1.0
            )
            .is_err()
        );
        assert!(
            triangulate_points(&v1, &v1, &[], &[[0.0, 0.0]], TriangulationMethod::Dlt, 1.0)
                .is_err()
        );
    }

    #[test]
    fn covariance_scales_with_sigma_and_depth() {
        let (v1, v2) = views(1.0, 1.0);
        let f = fundamental_from_views(&v1, &v2);
        let near = Vector3::new(0.0, 0.0, 3.0);
        let far = Vector3::new(0.0, 0.0, 30.0);
        let tri = |x: &Vector3<f64>, s| {
            triangulate_pair(
                &v1,
                &v2,
                &f,
                project(&v1, x),
                project(&v2, x),
                TriangulationMethod::Dlt,
                s,
            )
        };
        let a = tri(&near, 1.0);
        let b = tri(&near, 2.0);
        assert!((b.depth_std / a.depth_std - 2.0).abs() < 1e-9);
        // Depth uncertainty grows roughly with depth² for a fixed baseline.
        let c = tri(&far, 1.0);
        assert!(c.depth_std > 50.0 * a.depth_std);
    }

    proptest! {
        #[test]
        fn scale_invariance(scale_exp in -3.0f64..6.0, px in -1.0f64..1.0, py in -1.0f64..1.0, z in 2.0f64..20.0) {
            let scale = 10f64.powf(scale_exp);
            let (v1, v2) = views(scale, 1.0);
            let x = v1.r.transpose() * (Vector3::new(px, py, 1.0) * z * scale - v1.t);
            let (p1, p2) = (project(&v1, &x), project(&v2, &x));
            let f = fundamental_from_views(&v1, &v2);
            for m in [TriangulationMethod::Dlt, TriangulationMethod::Midpoint, TriangulationMethod::Optimal] {
                let t = triangulate_pair(&v1, &v2, &f, p1, p2, m, 1.0);
                let p = t.point.unwrap();
                prop_assert!(rel(&p, &x) < 1e-9, "{:?} rel {}", m, rel(&p, &x));
                prop_assert!(t.is_valid(0.5));
            }
        }

        #[test]
        fn tiny_baselines_never_nan(b_exp in -16.0f64..-1.0, z in 2.0f64..50.0) {
            let (v1, v2) = views(1.0, 10f64.powf(b_exp));
            let x = v1.r.transpose() * (Vector3::new(0.1, 0.2, 1.0) * z - v1.t);
            let (p1, p2) = (project(&v1, &x), project(&v2, &x));
            let f = fundamental_from_views(&v1, &v2);
            for m in [TriangulationMethod::Dlt, TriangulationMethod::Midpoint, TriangulationMethod::Optimal] {
                let t = triangulate_pair(&v1, &v2, &f, p1, p2, m, 1.0);
                prop_assert!(!t.angle_deg.is_nan() && !t.error_px.is_nan() && !t.depth_std.is_nan());
                prop_assert!(t.homogeneous.iter().all(|v| !v.is_nan()));
                if let Some(p) = t.point { prop_assert!(p.iter().all(|v| v.is_finite())); }
                // Below ~1e-4 rad of parallax a valid flag at 1° is impossible.
                if b_exp < -4.0 { prop_assert!(!t.is_valid(1.0)); }
            }
        }

        #[test]
        fn f32_rounded_inputs(px in -1.0f64..1.0, py in -1.0f64..1.0, z in 2.0f64..20.0) {
            let (v1, v2) = views(1.0, 1.0);
            let x = v1.r.transpose() * (Vector3::new(px, py, 1.0) * z - v1.t);
            let r = |p: [f64; 2]| [f64::from(p[0] as f32), f64::from(p[1] as f32)];
            let (p1, p2) = (r(project(&v1, &x)), r(project(&v2, &x)));
            let f = fundamental_from_views(&v1, &v2);
            for m in [TriangulationMethod::Dlt, TriangulationMethod::Midpoint, TriangulationMethod::Optimal] {
                let t = triangulate_pair(&v1, &v2, &f, p1, p2, m, 1.0);
                prop_assert!(rel(&t.point.unwrap(), &x) < 1e-5);
                prop_assert!(t.error_px < 1e-3);
            }
        }
    }

    fn run_op(values: Vec<Option<Value>>, params: TriangulateParams) -> Result<Outputs, OpError> {
        let op = Triangulate::new(params).map_err(OpError::failed)?;
        let specs = Triangulate::inputs();
        let inputs = Inputs::new(&specs, &values);
        let ctx = RunContext {
            node: "t".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &inputs)
    }

    #[test]
    fn operator_runs() {
        let (v1, v2) = views(1.0, 1.0);
        let pts: Vec<Vector3<f64>> = (0..10)
            .map(|i| Vector3::new(0.1 * i as f64 - 0.5, 0.05 * i as f64, 4.0 + i as f64))
            .collect();
        let p1: Vec<[f64; 2]> = pts.iter().map(|x| project(&v1, x)).collect();
        let p2: Vec<[f64; 2]> = pts.iter().map(|x| project(&v2, x)).collect();
        let cam = Camera {
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![800.0, 780.0, 320.0, 240.0],
        };
        let values = vec![
            Some(Value::Pose(pose_from_rt(&v1.r, &v1.t))),
            Some(Value::Pose(pose_from_rt(&v2.r, &v2.t))),
            Some(Value::Camera(Arc::new(cam))),
            None,
            Some(Value::Points2D(Arc::new(p1))),
            Some(Value::Points2D(Arc::new(p2.clone()))),
        ];
        let mut out = run_op(values.clone(), TriangulateParams::default()).unwrap();
        let Some(Value::PointCloud(c)) = out.take("points") else {
            panic!()
        };
        for (a, b) in c.positions.iter().zip(&pts) {
            assert!((f64::from(a[2]) - b.z).abs() < 1e-4);
        }
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!()
        };
        assert_eq!(m["valid"], 10.0);
        let mut bad = values;
        bad[5] = Some(Value::Points2D(Arc::new(p2[..3].to_vec())));
        assert!(run_op(bad, TriangulateParams::default()).is_err());
        assert!(
            Triangulate::new(TriangulateParams {
                sigma_px: 0.0,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            Triangulate::new(TriangulateParams {
                min_angle_deg: f64::NAN,
                ..Default::default()
            })
            .is_err()
        );
    }
}
