//! Projection matrices: RQ decomposition into `K [R | t]` ([`decompose_projection`]) and camera
//! calibration from 3-D/2-D correspondences by the normalized DLT (`geometry.calibrate_dlt`).

use std::sync::Arc;

use nalgebra::{DMatrix, Matrix3, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Intrinsics, Matrix, Value};

use super::camera::{Lens, from_na};
use super::pose_util::pose_from_rt;

/// `P = K·[R | t]` split into its factors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Decomposition {
    /// Upper-triangular intrinsics, positive diagonal, `K[2][2] = 1` (row-major).
    pub k: [f64; 9],
    /// Rotation, det +1 (row-major): `camera_from_world`.
    pub r: [f64; 9],
    /// Translation: `x_cam = R·x_world + t`.
    pub t: [f64; 3],
    /// Camera centre in world coordinates, `−Rᵀt`.
    pub centre: [f64; 3],
}

/// RQ decomposition of a 3×3 matrix: `M = U·Q` with `U` upper triangular with a non-negative
/// diagonal and `Q` orthogonal (Householder QR of the row-reversed transpose). `None` when
/// `M` is not finite.
pub fn rq3(m: &Matrix3<f64>) -> Option<(Matrix3<f64>, Matrix3<f64>)> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    // P = row-reversal permutation; (P·M)ᵀ = Q̃·R̃ ⇒ M = (P·R̃ᵀ·P)·(P·Q̃ᵀ).
    let p = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
    let a = (p * m).transpose();
    let qr = a.qr();
    let (qt, rt) = (qr.q(), qr.r());
    let mut u = p * rt.transpose() * p;
    let mut q = p * qt.transpose();
    for i in 0..3 {
        if u[(i, i)] < 0.0 {
            // U·D and D·Q with D = diag(±1), D² = I.
            for r in 0..3 {
                u[(r, i)] = -u[(r, i)];
            }
            for c in 0..3 {
                q[(i, c)] = -q[(i, c)];
            }
        }
    }
    Some((u, q))
}

/// Splits a 3×4 projection matrix (row-major) into `K`, `R`, `t` (Hartley & Zisserman §6.2.4):
/// the overall sign is chosen so that `det R = +1`, `K` is scaled to `K[2][2] = 1`, with a
/// positive diagonal. `None` when the left 3×3 is singular or not finite.
pub fn decompose_projection(p: &[f64; 12]) -> Option<Decomposition> {
    let mut m = Matrix3::new(p[0], p[1], p[2], p[4], p[5], p[6], p[8], p[9], p[10]);
    let mut p4 = Vector3::new(p[3], p[7], p[11]);
    let det = m.determinant();
    if !(det.abs() > 0.0 && det.is_finite()) {
        return None;
    }
    if det < 0.0 {
        m = -m;
        p4 = -p4;
    }
    let (u, q) = rq3(&m)?;
    let s = u[(2, 2)];
    if s <= 0.0 || s.is_nan() {
        return None;
    }
    let k = u / s;
    let t = k.try_inverse()? * (p4 / s);
    let centre = -(q.transpose() * t);
    Some(Decomposition {
        k: from_na(&k),
        r: from_na(&q),
        t: [t[0], t[1], t[2]],
        centre: [centre[0], centre[1], centre[2]],
    })
}

/// Projection matrix (row-major 3×4) with `image ~ P·(X, 1)` by the normalized DLT
/// (Hartley & Zisserman Alg. 7.1, without the geometric refinement): ≥ 6 points in general
/// position (not coplanar). `None` for degenerate input.
pub fn projection_dlt(world: &[[f64; 3]], image: &[[f64; 2]]) -> Option<[f64; 12]> {
    let n = world.len();
    if n < 6 || image.len() != n {
        return None;
    }
    let nf = n as f64;
    let mw = world.iter().fold([0.0; 3], |a, p| {
        [a[0] + p[0] / nf, a[1] + p[1] / nf, a[2] + p[2] / nf]
    });
    let dw = world
        .iter()
        .map(|p| ((p[0] - mw[0]).powi(2) + (p[1] - mw[1]).powi(2) + (p[2] - mw[2]).powi(2)).sqrt())
        .sum::<f64>()
        / nf;
    let mi = image
        .iter()
        .fold([0.0; 2], |a, p| [a[0] + p[0] / nf, a[1] + p[1] / nf]);
    let di = image
        .iter()
        .map(|p| (p[0] - mi[0]).hypot(p[1] - mi[1]))
        .sum::<f64>()
        / nf;
    if !(dw > 0.0 && di > 0.0 && dw.is_finite() && di.is_finite()) {
        return None;
    }
    let sw = 3f64.sqrt() / dw;
    let si = 2f64.sqrt() / di;
    let mut a = DMatrix::<f64>::zeros(2 * n.max(6), 12);
    for (i, (w, im)) in world.iter().zip(image).enumerate() {
        let x = [
            (w[0] - mw[0]) * sw,
            (w[1] - mw[1]) * sw,
            (w[2] - mw[2]) * sw,
            1.0,
        ];
        let (u, v) = ((im[0] - mi[0]) * si, (im[1] - mi[1]) * si);
        for j in 0..4 {
            a[(2 * i, j)] = x[j];
            a[(2 * i, 8 + j)] = -u * x[j];
            a[(2 * i + 1, 4 + j)] = x[j];
            a[(2 * i + 1, 8 + j)] = -v * x[j];
        }
    }
    let svd = a.svd(false, true);
    let vt = svd.v_t?;
    let s = &svd.singular_values;
    let mut order: Vec<usize> = (0..s.len()).collect();
    order.sort_by(|&i, &j| s[i].total_cmp(&s[j]));
    // A second (near-)null direction: coplanar or otherwise degenerate points.
    if s[order[1]] <= 1e-10 * s[order[order.len() - 1]] {
        return None;
    }
    let h = vt.row(order[0]);
    let pn = nalgebra::Matrix3x4::from_row_slice(h.transpose().as_slice());
    let ti = Matrix3::new(1.0 / si, 0.0, mi[0], 0.0, 1.0 / si, mi[1], 0.0, 0.0, 1.0);
    let tw = nalgebra::Matrix4::new(
        sw,
        0.0,
        0.0,
        -sw * mw[0],
        0.0,
        sw,
        0.0,
        -sw * mw[1],
        0.0,
        0.0,
        sw,
        -sw * mw[2],
        0.0,
        0.0,
        0.0,
        1.0,
    );
    let p = ti * pn * tw;
    let norm = p.norm();
    let mut out = [0.0; 12];
    for r in 0..3 {
        for c in 0..4 {
            out[r * 4 + c] = p[(r, c)] / norm;
        }
    }
    out.iter().all(|v| v.is_finite()).then_some(out)
}

params! {
    /// Parameters of `geometry.calibrate_dlt`.
    pub struct CalibrateDltParams {
        /// Image size `[width, height]` of the camera written to `camera`, pixels. Default
        /// `[0, 0]` (unknown).
        image_size: [u32; 2] = [0, 0],
    }
}

/// Camera calibration from 3-D/2-D correspondences (`geometry.calibrate_dlt`).
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrateDlt {
    size: [u32; 2],
}

impl Op for CalibrateDlt {
    type Params = CalibrateDltParams;
    const ID: &'static str = "geometry.calibrate_dlt";
    const SUMMARY: &'static str = "Calibrates a pinhole camera (K with skew, R, t) from ≥ 6 non-coplanar 3-D points and their images by the DLT and an RQ decomposition.";
    const DOC: &'static str = r#"
The classical DLT calibration (Hartley & Zisserman, Multiple View Geometry, §7.1 and §6.2.4):
1. P (3×4) by the normalized DLT: world points moved to centroid 0 and mean distance √3, image
   points to mean distance √2, P the SVD null vector of the 2n×12 system, denormalized.
   At least 6 points, not all coplanar (a coplanar set is an error).
2. P = K·[R | t] by RQ decomposition of its left 3×3 (Householder QR of the row-reversed
   transpose), signs fixed so that K has a positive diagonal and det R = +1, K[2][2] = 1.

Inputs: `object` (PointCloud, world points) and `image` (Points2D, their pixels, same order).
Outputs: `camera` (pinhole with skew, no distortion), `pose` (camera_from_world), `projection`
(P, 3×4, scaled to unit Frobenius norm) and `rms_px` (RMS reprojection error, pixels).

No nonlinear refinement (minimize the geometric error with bundle adjustment afterwards); no
lens distortion. OpenCV has no direct equivalent (its `calibrateCamera` with a non-planar rig
needs an intrinsic guess); `decomposeProjectionMatrix` is the RQ step.

Example (a node of a graph):
    "dlt": (op: "geometry.calibrate_dlt", inputs: { "object": "rig.points", "image": "marks.points" },
            params: (image_size: [640, 480])),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("object", PortType::PointCloud, "3-D points (world frame)"),
            PortSpec::new("image", PortType::Points2D, "their pixels, same order"),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("camera", PortType::Camera, "K with skew, no distortion"),
            PortSpec::new("pose", PortType::Pose, "camera_from_world"),
            PortSpec::new("projection", PortType::Matrix, "P = K[R | t], 3×4"),
            PortSpec::new("rms_px", PortType::Scalar, "RMS reprojection error, pixels"),
        ]
    }

    fn new(p: CalibrateDltParams) -> Result<Self, String> {
        Ok(CalibrateDlt { size: p.image_size })
    }
}

impl Operator for CalibrateDlt {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let Value::PointCloud(cloud) = inputs.require("object")? else {
            return Err(OpError::input("object", "expected a PointCloud"));
        };
        let Value::Points2D(image) = inputs.require("image")? else {
            return Err(OpError::input("image", "expected Points2D"));
        };
        if cloud.positions.len() != image.len() {
            return Err(OpError::input(
                "image",
                format!(
                    "{} image points for {} object points",
                    image.len(),
                    cloud.positions.len()
                ),
            ));
        }
        if image.len() < 6 {
            return Err(OpError::input(
                "object",
                format!("the DLT needs at least 6 points, got {}", image.len()),
            ));
        }
        let world: Vec<[f64; 3]> = cloud.positions.iter().map(|p| p.map(f64::from)).collect();
        let p = projection_dlt(&world, image).ok_or_else(|| {
            OpError::failed("degenerate points (coplanar or collinear): no unique projection")
        })?;
        let d = decompose_projection(&p)
            .ok_or_else(|| OpError::failed("the projection matrix is singular"))?;
        let mut sq = 0.0;
        for (w, im) in world.iter().zip(image.iter()) {
            let x = [
                p[0] * w[0] + p[1] * w[1] + p[2] * w[2] + p[3],
                p[4] * w[0] + p[5] * w[1] + p[6] * w[2] + p[7],
                p[8] * w[0] + p[9] * w[1] + p[10] * w[2] + p[11],
            ];
            sq += (x[0] / x[2] - im[0]).powi(2) + (x[1] / x[2] - im[1]).powi(2);
        }
        let rms = (sq / world.len() as f64).sqrt();
        let k = Intrinsics {
            fx: d.k[0],
            fy: d.k[4],
            cx: d.k[2],
            cy: d.k[5],
            skew: d.k[1],
        };
        let camera = Lens::pinhole(k).to_camera(self.size[0], self.size[1]);
        let pose = pose_from_rt(&Matrix3::from_row_slice(&d.r), &Vector3::from(d.t));
        let projection =
            Matrix::new(3, 4, p.to_vec()).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("camera", Value::Camera(Arc::new(camera)))
            .with("pose", Value::Pose(pose))
            .with("projection", Value::Matrix(Arc::new(projection)))
            .with("rms_px", Value::Scalar(rms)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::camera::rodrigues;
    use proptest::prelude::*;

    fn compose(k: &Matrix3<f64>, r: &Matrix3<f64>, t: &Vector3<f64>) -> [f64; 12] {
        let m = k * r;
        let p4 = k * t;
        [
            m[(0, 0)],
            m[(0, 1)],
            m[(0, 2)],
            p4[0],
            m[(1, 0)],
            m[(1, 1)],
            m[(1, 2)],
            p4[1],
            m[(2, 0)],
            m[(2, 1)],
            m[(2, 2)],
            p4[2],
        ]
    }

    #[test]
    fn decomposes_a_known_camera_up_to_scale_and_sign() {
        let k = Matrix3::new(800.0, 2.0, 320.0, 0.0, 780.0, 240.0, 0.0, 0.0, 1.0);
        let r = rodrigues([0.3, -1.2, 0.5]);
        let t = Vector3::new(0.5, -0.2, 4.0);
        for scale in [1.0, -3.5, 1e-4] {
            let p = compose(&k, &r, &t).map(|v| v * scale);
            let d = decompose_projection(&p).unwrap();
            for i in 0..9 {
                assert!(
                    (d.k[i] - k.as_slice()[(i % 3) * 3 + i / 3]).abs() < 1e-8,
                    "K {i}"
                );
                assert!((d.r[i] - r[(i / 3, i % 3)]).abs() < 1e-12, "R {i}");
            }
            for i in 0..3 {
                assert!((d.t[i] - t[i]).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn dlt_recovers_a_camera_and_rejects_coplanar_points() {
        let k = Matrix3::new(600.0, 0.5, 330.0, 0.0, 610.0, 250.0, 0.0, 0.0, 1.0);
        let r = rodrigues([0.1, 0.2, -0.05]);
        let t = Vector3::new(-0.3, 0.1, 6.0);
        let world: Vec<[f64; 3]> = (0..20)
            .map(|i| {
                let f = i as f64;
                [
                    (f * 0.37).sin() * 2.0,
                    (f * 0.71).cos() * 1.5,
                    (f * 1.3).sin(),
                ]
            })
            .collect();
        let p = compose(&k, &r, &t);
        let image: Vec<[f64; 2]> = world
            .iter()
            .map(|w| {
                let x = [
                    p[0] * w[0] + p[1] * w[1] + p[2] * w[2] + p[3],
                    p[4] * w[0] + p[5] * w[1] + p[6] * w[2] + p[7],
                    p[8] * w[0] + p[9] * w[1] + p[10] * w[2] + p[11],
                ];
                [x[0] / x[2], x[1] / x[2]]
            })
            .collect();
        let est = projection_dlt(&world, &image).unwrap();
        let d = decompose_projection(&est).unwrap();
        assert!((d.k[0] - 600.0).abs() < 1e-6 && (d.k[1] - 0.5).abs() < 1e-6);
        assert!((d.k[4] - 610.0).abs() < 1e-6 && (d.k[5] - 250.0).abs() < 1e-6);
        assert!((d.t[2] - 6.0).abs() < 1e-8);
        let flat: Vec<[f64; 3]> = world.iter().map(|w| [w[0], w[1], 0.0]).collect();
        assert!(projection_dlt(&flat, &image).is_none());
        assert!(projection_dlt(&world[..5], &image[..5]).is_none());
    }

    proptest! {
        #[test]
        fn rq_gives_positive_diagonal_and_a_proper_rotation(
            w in prop::array::uniform3(-3.0f64..3.0),
            f in 100.0f64..2000.0, a in 0.5f64..2.0, s in -5.0f64..5.0,
            c in prop::array::uniform2(-500.0f64..500.0), scale in -10.0f64..10.0,
            t in prop::array::uniform3(-5.0f64..5.0),
        ) {
            prop_assume!(scale.abs() > 1e-3);
            let k = Matrix3::new(f, s, c[0], 0.0, f * a, c[1], 0.0, 0.0, 1.0);
            let r = rodrigues(w);
            let p = compose(&k, &r, &Vector3::from(t)).map(|v| v * scale);
            let d = decompose_projection(&p).unwrap();
            prop_assert!(d.k[0] > 0.0 && d.k[4] > 0.0 && d.k[8] > 0.0);
            let rd = Matrix3::from_row_slice(&d.r);
            prop_assert!((rd.determinant() - 1.0).abs() < 1e-9);
            prop_assert!((rd * rd.transpose() - Matrix3::identity()).norm() < 1e-9);
            prop_assert!((rd - r).norm() < 1e-8);
            prop_assert!((d.k[1] - s).abs() < 1e-6 * f);
        }
    }
}
