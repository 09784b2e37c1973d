//! Small helpers shared by the calibrated solvers: intrinsics from a [`Camera`], the rotation
//! conversions of the geometry module (angle-axis ↔ matrix ↔ pose quaternion), the nearest
//! rotation, and reading matrices, points and poses from values.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};
use ocellus_engine::op::{Inputs, OpError};
use ocellus_engine::value::{Camera, Distortion, Matrix, Pose, Value};

/// Pinhole intrinsics `fx, fy, cx, cy` (pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, px.
    pub fx: f64,
    /// Focal length along y, px.
    pub fy: f64,
    /// Principal point x, px.
    pub cx: f64,
    /// Principal point y, px.
    pub cy: f64,
}

impl Intrinsics {
    /// Intrinsics with positive finite focal lengths and a finite principal point.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Intrinsics, String> {
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(format!(
                "focal lengths must be finite and > 0, got {fx}, {fy}"
            ));
        }
        if !(cx.is_finite() && cy.is_finite()) {
            return Err(format!("principal point must be finite, got {cx}, {cy}"));
        }
        Ok(Intrinsics { fx, fy, cx, cy })
    }

    /// The pinhole part of a camera. Skew and distortion terms must be zero (undistort the
    /// points first, e.g. with `geometry.undistort`).
    pub fn from_camera(camera: &Camera) -> Result<Intrinsics, String> {
        let p = &camera.params;
        if p.len() != camera.model.param_count() {
            return Err(format!(
                "camera model {} takes {} parameters, got {}",
                camera.model.colmap_name(),
                camera.model.param_count(),
                p.len()
            ));
        }
        let k = camera.intrinsics();
        if k.skew != 0.0 {
            return Err(format!(
                "camera has skew {}; these solvers take a zero-skew pinhole camera",
                k.skew
            ));
        }
        let distorted = match camera.distortion() {
            Distortion::None => false,
            Distortion::RadialTangential(d) => d.iter().any(|&v| v != 0.0),
            Distortion::Fisheye(d) => d.iter().any(|&v| v != 0.0),
        };
        if distorted {
            return Err(format!(
                "camera model {} has non-zero distortion terms; undistort the points first",
                camera.model.colmap_name()
            ));
        }
        Intrinsics::new(k.fx, k.fy, k.cx, k.cy)
    }

    /// The calibration matrix `K`.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// Pixel → normalized image coordinates (`K⁻¹x`).
    #[inline]
    pub fn normalize(&self, p: [f64; 2]) -> Vector2<f64> {
        Vector2::new((p[0] - self.cx) / self.fx, (p[1] - self.cy) / self.fy)
    }

    /// Normalized image coordinates → pixels.
    #[inline]
    pub fn denormalize(&self, x: &Vector2<f64>) -> [f64; 2] {
        [self.fx * x.x + self.cx, self.fy * x.y + self.cy]
    }

    /// Projects a point in camera coordinates to pixels (no depth check).
    #[inline]
    pub fn project(&self, xc: &Vector3<f64>) -> [f64; 2] {
        [
            self.fx * xc.x / xc.z + self.cx,
            self.fy * xc.y / xc.z + self.cy,
        ]
    }

    /// Geometric mean of the focal lengths: converts normalized distances to pixels.
    pub fn focal(&self) -> f64 {
        (self.fx * self.fy).sqrt()
    }
}

/// The rotation closest to `m` in the Frobenius norm (SVD, determinant forced to +1).
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = m.svd(true, true);
    let u = svd.u?;
    let vt = svd.v_t?;
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    Some(u * d * vt)
}

/// `a > b`, false when either is NaN (reads better than a negated comparison in guards).
#[inline]
pub fn gt(a: f64, b: f64) -> bool {
    a > b
}

/// `[v]×`, the cross-product matrix.
#[inline]
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// A pose from a rotation matrix and a translation.
pub fn pose_from_rt(r: &Matrix3<f64>, t: &Vector3<f64>) -> Pose {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    let q = if q.w < 0.0 {
        -q.into_inner()
    } else {
        q.into_inner()
    };
    Pose {
        rotation: [q.w, q.i, q.j, q.k],
        translation: [t.x, t.y, t.z],
    }
}

/// Rotation matrix of an angle-axis vector (Rodrigues' formula); Taylor series below 1e-4 rad,
/// so tiny and zero angles are exact to rounding.
pub fn rodrigues(w: [f64; 3]) -> Matrix3<f64> {
    let t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    let theta = t2.sqrt();
    let (a, b) = if theta < 1e-4 {
        (1.0 - t2 / 6.0, 0.5 - t2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / t2)
    };
    let k = skew(&Vector3::from(w));
    Matrix3::identity() + k * a + k * k * b
}

/// Angle-axis vector of a rotation matrix (inverse of [`rodrigues`], angle in [0, π]); goes
/// through the quaternion of [`pose_from_rt`] (`w ≥ 0`), so it is stable near 0 and near π.
pub fn angle_axis(r: &Matrix3<f64>) -> [f64; 3] {
    let q = pose_from_rt(r, &Vector3::zeros()).rotation;
    let v = Vector3::new(q[1], q[2], q[3]);
    let s = v.norm();
    if s < 1e-300 {
        return [0.0; 3];
    }
    // angle = 2·atan2(|v|, w); w ≥ 0 here.
    let angle = 2.0 * s.atan2(q[0]);
    let f = if s < 1e-8 { 2.0 / q[0] } else { angle / s };
    [v[0] * f, v[1] * f, v[2] * f]
}

/// Rotation matrix and translation of a pose (the quaternion is normalized).
pub fn rt_from_pose(pose: &Pose) -> Result<(Matrix3<f64>, Vector3<f64>), String> {
    let [w, x, y, z] = pose.rotation;
    let n = (w * w + x * x + y * y + z * z).sqrt();
    if !n.is_finite() || n < 1e-12 || !pose.translation.iter().all(|v| v.is_finite()) {
        return Err("pose has a zero or non-finite quaternion or translation".into());
    }
    let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
    Ok((
        *q.to_rotation_matrix().matrix(),
        Vector3::from(pose.translation),
    ))
}

/// Angle of the rotation `a⁻¹b`, degrees.
pub fn rotation_angle_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    // atan2(sin θ, cos θ) stays accurate for small angles, where acos loses half the digits.
    let m = a.transpose() * b;
    let s = 0.5
        * Vector3::new(
            m[(2, 1)] - m[(1, 2)],
            m[(0, 2)] - m[(2, 0)],
            m[(1, 0)] - m[(0, 1)],
        )
        .norm();
    let c = (m.trace() - 1.0) / 2.0;
    s.atan2(c).to_degrees()
}

/// Angle between two vectors, degrees (0 when either is zero).
pub fn vector_angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let n = a.norm() * b.norm();
    if n == 0.0 {
        return 0.0;
    }
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

/// A 3×3 matrix from a `Matrix` value.
pub fn matrix3(m: &Matrix) -> Result<Matrix3<f64>, String> {
    if m.rows != 3 || m.cols != 3 {
        return Err(format!("expected a 3×3 matrix, got {}×{}", m.rows, m.cols));
    }
    if !m.data.iter().all(|v| v.is_finite()) {
        return Err("matrix has non-finite entries".into());
    }
    Ok(Matrix3::from_row_slice(&m.data))
}

/// The 3×3 matrix on port `name`.
pub fn input_matrix3(inputs: &Inputs<'_>, name: &str) -> Result<Matrix3<f64>, OpError> {
    match inputs.require(name)? {
        Value::Matrix(m) => matrix3(m).map_err(|e| OpError::input(name, e)),
        other => Err(OpError::input(
            name,
            format!("expected Matrix, got {}", other.port_type()),
        )),
    }
}

/// The camera intrinsics on port `name`.
pub fn input_intrinsics(inputs: &Inputs<'_>, name: &str) -> Result<Intrinsics, OpError> {
    match inputs.require(name)? {
        Value::Camera(c) => Intrinsics::from_camera(c).map_err(|e| OpError::input(name, e)),
        other => Err(OpError::input(
            name,
            format!("expected Camera, got {}", other.port_type()),
        )),
    }
}

/// The 2-D points on port `name` (all finite).
pub fn input_points2(inputs: &Inputs<'_>, name: &str) -> Result<Vec<[f64; 2]>, OpError> {
    match inputs.require(name)? {
        Value::Points2D(p) => {
            if p.iter().any(|q| !q[0].is_finite() || !q[1].is_finite()) {
                return Err(OpError::input(name, "non-finite point"));
            }
            Ok(p.to_vec())
        }
        other => Err(OpError::input(
            name,
            format!("expected Points2D, got {}", other.port_type()),
        )),
    }
}

/// The 3-D points on port `name`: a PointCloud or an N×3 Matrix (all finite).
pub fn input_points3(inputs: &Inputs<'_>, name: &str) -> Result<Vec<[f64; 3]>, OpError> {
    let pts: Vec<[f64; 3]> = match inputs.require(name)? {
        Value::PointCloud(c) => c
            .positions
            .iter()
            .map(|p| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])])
            .collect(),
        Value::Matrix(m) => {
            if m.cols != 3 {
                return Err(OpError::input(
                    name,
                    format!("expected an N×3 matrix, got {}×{}", m.rows, m.cols),
                ));
            }
            m.data.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        }
        other => {
            return Err(OpError::input(
                name,
                format!("expected PointCloud or Matrix, got {}", other.port_type()),
            ));
        }
    };
    if pts.iter().flatten().any(|v| !v.is_finite()) {
        return Err(OpError::input(name, "non-finite point"));
    }
    Ok(pts)
}

/// The pose on port `name` as `(R, t)`.
pub fn input_pose(
    inputs: &Inputs<'_>,
    name: &str,
) -> Result<(Matrix3<f64>, Vector3<f64>), OpError> {
    match inputs.require(name)? {
        Value::Pose(p) => rt_from_pose(p).map_err(|e| OpError::input(name, e)),
        other => Err(OpError::input(
            name,
            format!("expected Pose, got {}", other.port_type()),
        )),
    }
}

/// A `Matrix` value from rows of equal length.
pub fn matrix_value(rows: usize, cols: usize, data: Vec<f64>) -> Result<Value, OpError> {
    Matrix::new(rows, cols, data)
        .map(|m| Value::Matrix(std::sync::Arc::new(m)))
        .map_err(|e| OpError::failed(e.to_string()))
}

/// Least-squares solution of the small dense system `a x ≈ b` (at most a few dozen columns).
///
/// Uses nalgebra's SVD but checks it: nalgebra 0.35's `DMatrix::svd` with singular vectors
/// returns wrong singular values for some inputs (dimforge/nalgebra#1172), which the identity
/// `Σσ² = ‖a‖²_F` exposes; then the normal equations (Cholesky of `aᵀa`) are solved instead.
/// `None` when neither gives a finite solution.
pub fn least_squares(
    a: &nalgebra::DMatrix<f64>,
    b: &nalgebra::DVector<f64>,
) -> Option<nalgebra::DVector<f64>> {
    let frobenius2 = a.norm_squared();
    let svd = a.clone().svd(true, true);
    let sum2: f64 = svd.singular_values.iter().map(|s| s * s).sum();
    if (sum2 - frobenius2).abs() <= 1e-9 * frobenius2.max(f64::MIN_POSITIVE)
        && let Ok(x) = svd.solve(b, 1e-12)
        && x.iter().all(|v| v.is_finite())
    {
        return Some(x);
    }
    let x = (a.transpose() * a).cholesky()?.solve(&(a.transpose() * b));
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::CameraModel;

    #[test]
    fn rodrigues_round_trip_and_small_angles() {
        for w in [
            [0.0, 0.0, 0.0],
            [1e-12, -2e-12, 3e-12],
            [1e-5, 2e-5, -1e-5],
            [0.3, -0.2, 0.1],
            [0.0, 0.0, std::f64::consts::PI - 1e-9],
            [2.0, 1.0, -0.5],
        ] {
            let r = rodrigues(w);
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            assert!((r * r.transpose() - Matrix3::identity()).norm() < 1e-12);
            let back = angle_axis(&r);
            let r2 = rodrigues(back);
            assert!((r - r2).norm() < 1e-9, "{w:?}");
        }
        let w = [1e-9, 0.0, 0.0];
        let back = angle_axis(&rodrigues(w));
        assert!((back[0] - 1e-9).abs() < 1e-20);
    }

    #[test]
    fn pose_round_trip_and_camera() {
        let r = *Rotation3::from_scaled_axis(Vector3::new(0.3, -1.2, 2.9)).matrix();
        let t = Vector3::new(1.0, -2.0, 3.0);
        let (r2, t2) = rt_from_pose(&pose_from_rt(&r, &t)).unwrap();
        assert!((r - r2).norm() < 1e-14 && (t - t2).norm() == 0.0);
        let cam = Camera {
            model: CameraModel::OpenCv,
            width: 640,
            height: 480,
            params: vec![500.0, 510.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0],
        };
        let k = Intrinsics::from_camera(&cam).unwrap();
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (500.0, 510.0, 320.0, 240.0));
        let p = k.denormalize(&k.normalize([17.0, 3.0]));
        assert!((p[0] - 17.0).abs() < 1e-12 && (p[1] - 3.0).abs() < 1e-12);
        let distorted = Camera {
            params: vec![500.0, 510.0, 320.0, 240.0, 0.1, 0.0, 0.0, 0.0],
            ..cam
        };
        assert!(Intrinsics::from_camera(&distorted).is_err());
        assert!(Intrinsics::new(0.0, 1.0, 0.0, 0.0).is_err());
        let m = Matrix3::new(1.0, 0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
        let r = nearest_rotation(&m).unwrap();
        assert!((r.determinant() - 1.0).abs() < 1e-12);
        assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-12);
        assert!(nearest_rotation(&Matrix3::from_element(f64::NAN)).is_none());
    }

    #[test]
    fn least_squares_survives_the_nalgebra_svd_failure() {
        // nalgebra 0.35's dynamic SVD returns Σσ² = 21.0437 for this matrix (‖a‖²_F = 21), so
        // its solve is wrong; the checked solver must still return the exact solution.
        let a = nalgebra::DMatrix::from_row_slice(
            3,
            3,
            &[1.0, 2.0, 2.0, 2.0, -1.0, -1.0, 2.0, 1.0, -1.0],
        );
        let x_true = nalgebra::DVector::from_column_slice(&[1.5, -0.25, 2.0]);
        let x = least_squares(&a, &(&a * &x_true)).unwrap();
        assert!((&x - &x_true).norm() < 1e-12, "{x}");
        // A well-posed case: recovers the exact solution.
        let a = nalgebra::DMatrix::from_row_slice(
            6,
            3,
            &[
                1.0, 2.0, 2.0, 2.0, -1.0, -1.0, 2.0, 1.0, -1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 3.0, 1.0,
                0.0, 0.0,
            ],
        );
        let x_true = nalgebra::DVector::from_column_slice(&[0.5, -2.0, 1.25]);
        let x = least_squares(&a, &(&a * &x_true)).unwrap();
        assert!((x - x_true).norm() < 1e-12);
    }
}
