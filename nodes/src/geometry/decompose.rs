//! Planar geometry from homographies: decomposition of a calibrated homography into
//! `(R, t/d, n)` candidates with visibility filtering, and the pose of a square marker from its
//! homography (or its four corners); operator `geometry.decompose_homography`.
//!
//! Decomposition (Faugeras & Lustman 1988, in the SVD form of Ma, Soatto, Košecká & Sastry, "An
//! Invitation to 3-D Vision", §5.3.3): `Ĥ = K⁻¹HK` is scaled so that its middle singular value
//! is 1 and its determinant is positive (both cameras on the same side of the plane), so
//! `Ĥ = R + t nᵀ` with `(R, t)` camera2_from_camera1, `n` the plane's unit normal in camera 1
//! and `t` the translation divided by the plane's distance `d` from camera 1. With `ĤᵀĤ =
//! V diag(σ₁², 1, σ₃²) Vᵀ`, the vectors `u± = (√(1−σ₃²) v₁ ± √(σ₁²−1) v₃)/√(σ₁²−σ₃²)` keep their
//! length under `Ĥ`; each gives `R = [Ĥv₂, Ĥu, Ĥv₂×Ĥu][v₂, u, v₂×u]ᵀ`, `n = v₂×u`, `t = (Ĥ−R)n`,
//! and `(R, −t, −n)` is the twin: four candidates, as OpenCV's `decomposeHomographyMat`
//! (which uses Malis & Vargas' closed form; the set of solutions is the same). A homography
//! with three equal singular values is a pure rotation: one candidate with `t = 0` and
//! `n = (0, 0, 1)` (undetermined).
//!
//! Visibility (OpenCV's `filterHomographyDecompByVisibleRefpoints`): a candidate survives when
//! the reference points lie in front of both cameras, `nᵀ(K⁻¹x₁) > 0` and `(Rn)ᵀ(K⁻¹x₂) > 0`.

use nalgebra::{Matrix3, Vector2, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::Value;

use super::pnp::{CameraPose, refine_pose};
use super::pose_util::{
    Intrinsics, gt, input_intrinsics, input_matrix3, input_points2, matrix_value, nearest_rotation,
    pose_from_rt,
};

/// One decomposition candidate of a calibrated homography.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomographySolution {
    /// Rotation camera2_from_camera1.
    pub r: Matrix3<f64>,
    /// Translation camera2_from_camera1 divided by the plane's distance from camera 1.
    pub t: Vector3<f64>,
    /// Unit plane normal in camera 1.
    pub n: Vector3<f64>,
}

/// Decomposes a pixel homography `H` (`x2 ∼ H x1`) of a plane seen by two cameras with
/// intrinsics `k1`, `k2` into up to four `(R, t/d, n)` candidates. Errors on a non-finite or
/// rank-deficient `H`.
pub fn decompose_homography(
    h: &Matrix3<f64>,
    k1: &Intrinsics,
    k2: &Intrinsics,
) -> Result<Vec<HomographySolution>, String> {
    if !h.iter().all(|v| v.is_finite()) {
        return Err("homography has non-finite entries".into());
    }
    let k2i = k2.matrix().try_inverse().ok_or("intrinsics are singular")?;
    let mut hn = k2i * h * k1.matrix();
    let svd = hn.svd(false, true);
    let s = svd.singular_values;
    let vt = svd.v_t.ok_or("SVD failed")?;
    let mut ord = [0usize, 1, 2];
    ord.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
    let (s1, s2, s3) = (s[ord[0]], s[ord[1]], s[ord[2]]);
    if !gt(s3, 1e-12 * s1) || !s1.is_finite() {
        return Err("homography is rank-deficient".into());
    }
    hn /= s2;
    if hn.determinant() < 0.0 {
        hn = -hn;
    }
    let (s1, s3) = (s1 / s2, s3 / s2);
    if s1 - s3 <= 1e-9 * s1 {
        let r = nearest_rotation(&hn).ok_or("homography is not a rotation")?;
        return Ok(vec![HomographySolution {
            r,
            t: Vector3::zeros(),
            n: Vector3::z(),
        }]);
    }
    let v = |i: usize| -> Vector3<f64> { vt.row(ord[i]).transpose() };
    let (v1, v2, v3) = (v(0), v(1), v(2));
    let a = (1.0 - s3 * s3).max(0.0).sqrt();
    let b = (s1 * s1 - 1.0).max(0.0).sqrt();
    let c = (s1 * s1 - s3 * s3).sqrt();
    let mut out = Vec::with_capacity(4);
    for u in [(v1 * a + v3 * b) / c, (v1 * a - v3 * b) / c] {
        let hv2 = hn * v2;
        let hu = hn * u;
        let um = Matrix3::from_columns(&[v2, u, v2.cross(&u)]);
        let wm = Matrix3::from_columns(&[hv2, hu, hv2.cross(&hu)]);
        let r = wm * um.transpose();
        let r = if (r.transpose() * r - Matrix3::identity()).norm() > 1e-9 {
            nearest_rotation(&r).ok_or("SVD failed")?
        } else {
            r
        };
        let n = v2.cross(&u).normalize();
        let t = (hn - r) * n;
        if !(r
            .iter()
            .chain(t.iter())
            .chain(n.iter())
            .all(|x| x.is_finite()))
        {
            continue;
        }
        out.push(HomographySolution { r, t, n });
        out.push(HomographySolution { r, t: -t, n: -n });
    }
    Ok(out)
}

/// Indices of the candidates for which at least `min_fraction` of the reference points
/// (pixels) lie in front of both cameras (`nᵀK₁⁻¹x₁ > 0` and `(Rn)ᵀK₂⁻¹x₂ > 0`).
pub fn visible_solutions(
    sols: &[HomographySolution],
    k1: &Intrinsics,
    k2: &Intrinsics,
    points1: &[[f64; 2]],
    points2: &[[f64; 2]],
    min_fraction: f64,
) -> Vec<usize> {
    let n = points1.len().min(points2.len());
    let need = (min_fraction * n as f64).ceil() as usize;
    let m1: Vec<Vector3<f64>> = points1[..n]
        .iter()
        .map(|p| {
            let q = k1.normalize(*p);
            Vector3::new(q.x, q.y, 1.0)
        })
        .collect();
    let m2: Vec<Vector3<f64>> = points2[..n]
        .iter()
        .map(|p| {
            let q = k2.normalize(*p);
            Vector3::new(q.x, q.y, 1.0)
        })
        .collect();
    (0..sols.len())
        .filter(|&i| {
            let s = &sols[i];
            let n2 = s.r * s.n;
            let ok = m1
                .iter()
                .zip(&m2)
                .filter(|(a, b)| s.n.dot(a) > 0.0 && n2.dot(b) > 0.0)
                .count();
            ok >= need.max(1)
        })
        .collect()
}

/// Pose of a plane (`camera_from_plane`) from the homography `H` mapping plane coordinates
/// `(X, Y)` (`Z = 0`) to pixels: `K⁻¹H ∼ [r₁ r₂ t]`, scaled by the mean length of the first two
/// columns, signed so the plane is in front (`t_z > 0`), and `[r₁ r₂ r₁×r₂]` projected onto
/// SO(3) (Zhang 2000, §3.1). Errors on a degenerate `H`.
pub fn plane_pose_from_homography(h: &Matrix3<f64>, k: &Intrinsics) -> Result<CameraPose, String> {
    if !h.iter().all(|v| v.is_finite()) {
        return Err("homography has non-finite entries".into());
    }
    let m = k.matrix().try_inverse().ok_or("intrinsics are singular")? * h;
    let (c1, c2, c3) = (
        m.column(0).into_owned(),
        m.column(1).into_owned(),
        m.column(2).into_owned(),
    );
    let norm = 0.5 * (c1.norm() + c2.norm());
    if !gt(norm, 0.0) || !norm.is_finite() {
        return Err("homography is degenerate".into());
    }
    let mut lambda = 1.0 / norm;
    if c3.z < 0.0 {
        lambda = -lambda;
    }
    let (r1, r2) = (c1 * lambda, c2 * lambda);
    let r3 = r1.cross(&r2);
    if !gt(r3.norm(), 1e-9) {
        return Err("homography is degenerate (columns parallel)".into());
    }
    let r = nearest_rotation(&Matrix3::from_columns(&[r1, r2, r3])).ok_or("SVD failed")?;
    Ok(CameraPose { r, t: c3 * lambda })
}

/// Homography (`x2 ∼ H x1`) from four or more point pairs by the normalized DLT. `None` for
/// degenerate configurations.
pub fn homography_dlt(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    if x1.len() != x2.len() {
        return None;
    }
    let pairs: Vec<_> = x1
        .iter()
        .zip(x2)
        .map(|(a, b)| [[a.x, a.y], [b.x, b.y]])
        .collect();
    crate::geometry::homography::dlt(&pairs)
}

/// Pose `camera_from_marker` of a square marker of side `side` from its four corners in
/// pixels, ordered top-left, top-right, bottom-right, bottom-left with marker coordinates
/// `(−s/2, s/2)`, `(s/2, s/2)`, `(s/2, −s/2)`, `(−s/2, −s/2)` (OpenCV's ArUco convention):
/// homography, planar pose, then (with `refine`) Levenberg–Marquardt on the corners'
/// reprojection error.
pub fn marker_pose(
    corners: &[[f64; 2]; 4],
    side: f64,
    k: &Intrinsics,
    refine: bool,
) -> Result<CameraPose, String> {
    if !gt(side, 0.0) || !side.is_finite() {
        return Err(format!("marker side must be finite and > 0, got {side}"));
    }
    let h = side / 2.0;
    let obj = [[-h, h], [h, h], [h, -h], [-h, -h]];
    let x1: Vec<Vector2<f64>> = obj.iter().map(|p| Vector2::new(p[0], p[1])).collect();
    let x2: Vec<Vector2<f64>> = corners.iter().map(|p| Vector2::new(p[0], p[1])).collect();
    let hm = homography_dlt(&x1, &x2).ok_or("marker corners are degenerate")?;
    let pose = plane_pose_from_homography(&hm, k)?;
    if !refine {
        return Ok(pose);
    }
    let world: Vec<[f64; 3]> = obj.iter().map(|p| [p[0], p[1], 0.0]).collect();
    Ok(refine_pose(k, corners, &world, &pose, 30))
}

params! {
    /// Parameters of `geometry.decompose_homography`.
    pub struct DecomposeHomographyParams {
        /// With reference points connected: the fraction of points, 0..=1, that must lie in
        /// front of both cameras for a candidate to be kept (OpenCV requires all). Default 1.
        min_visible_fraction: f64 = 1.0 => [min = 0.0, max = 1.0],
    }
}

/// Homography decomposition (`geometry.decompose_homography`). See [`decompose_homography`].
#[derive(Debug, Clone, PartialEq)]
pub struct DecomposeHomography {
    min_visible_fraction: f64,
}

impl Op for DecomposeHomography {
    type Params = DecomposeHomographyParams;
    const ID: &'static str = "geometry.decompose_homography";
    const SUMMARY: &'static str = "Decomposes a plane-induced homography into rotation, scaled translation and normal candidates.";
    const DOC: &'static str = r#"
Decomposes `homography` (pixels, `x2 ∼ H x1`, induced by a plane seen from two cameras with
intrinsics `camera`, and `camera2` for the second view when different) into up to four
candidates `(R, t/d, n)`: `K₂⁻¹HK₁ ∼ R + (t/d) nᵀ` with (R, t) camera2_from_camera1, `n` the
plane normal in camera 1 and `d` the plane's distance from camera 1. Method: Faugeras & Lustman
(1988) in the SVD form of Ma et al. ("An Invitation to 3-D Vision" §5.3.3), with the
homography scaled to a unit middle singular value and a positive determinant; OpenCV's
`decomposeHomographyMat` uses Malis & Vargas' closed form and returns the same set. A pure
rotation gives one candidate with t = 0 and n = (0, 0, 1).

When `points1`/`points2` are connected, only candidates that put at least
`min_visible_fraction` of the points in front of both cameras are kept (OpenCV's
`filterHomographyDecompByVisibleRefpoints`); usually two survive, and a third view or prior
knowledge of the normal picks one.

Outputs: `poses` (list of Pose, translation = t/d), `normals` (k×3 matrix, row i for pose i).

Example:
    "cands": (op: "geometry.decompose_homography", inputs: { "homography": "h.matrix", "camera": "cam.camera", "points1": "m.points1", "points2": "m.points2" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("homography", PortType::Matrix, "3×3 homography, pixels."),
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
                "Reference points in image 1, px.",
            )
            .optional(),
            PortSpec::new(
                "points2",
                PortType::Points2D,
                "Matching points in image 2, px.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "Candidates camera2_from_camera1 (translation divided by the plane distance).",
            ),
            PortSpec::new(
                "normals",
                PortType::Matrix,
                "k×3 plane normals in camera 1.",
            ),
        ]
    }

    fn new(params: DecomposeHomographyParams) -> Result<Self, String> {
        let f = params.min_visible_fraction;
        if !f.is_finite() || !(0.0..=1.0).contains(&f) {
            return Err(format!("`min_visible_fraction` must be in [0, 1], got {f}"));
        }
        Ok(DecomposeHomography {
            min_visible_fraction: f,
        })
    }
}

impl Operator for DecomposeHomography {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let h = input_matrix3(inputs, "homography")?;
        let k1 = input_intrinsics(inputs, "camera")?;
        let k2 = if inputs.get("camera2").is_some() {
            input_intrinsics(inputs, "camera2")?
        } else {
            k1
        };
        let mut sols = decompose_homography(&h, &k1, &k2).map_err(OpError::failed)?;
        match (inputs.get("points1"), inputs.get("points2")) {
            (Some(_), Some(_)) => {
                let p1 = input_points2(inputs, "points1")?;
                let p2 = input_points2(inputs, "points2")?;
                if p1.len() != p2.len() {
                    return Err(OpError::input(
                        "points2",
                        format!("{} points vs {} in points1", p2.len(), p1.len()),
                    ));
                }
                if !p1.is_empty() {
                    let keep =
                        visible_solutions(&sols, &k1, &k2, &p1, &p2, self.min_visible_fraction);
                    sols = keep.into_iter().map(|i| sols[i]).collect();
                }
            }
            (None, None) => {}
            _ => {
                return Err(OpError::input(
                    "points2",
                    "connect both points1 and points2, or neither",
                ));
            }
        }
        let poses: Vec<Value> = sols
            .iter()
            .map(|s| Value::Pose(pose_from_rt(&s.r, &s.t)))
            .collect();
        let normals: Vec<f64> = sols.iter().flat_map(|s| [s.n.x, s.n.y, s.n.z]).collect();
        Ok(Outputs::new()
            .with("poses", Value::list(PortType::Pose, poses))
            .with("normals", matrix_value(sols.len(), 3, normals)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use ocellus_engine::value::{Camera, CameraModel, Matrix};
    use proptest::prelude::*;
    use std::sync::Arc;

    use crate::geometry::pose_util::rotation_angle_deg;

    fn k() -> Intrinsics {
        Intrinsics::new(700.0, 720.0, 320.0, 240.0).unwrap()
    }

    /// Plane nᵀX = d in camera 1, relative pose (R, t); returns H (pixels) and points.
    fn setup(
        r: Matrix3<f64>,
        t: Vector3<f64>,
        n: Vector3<f64>,
        d: f64,
    ) -> (Matrix3<f64>, Vec<[f64; 2]>, Vec<[f64; 2]>) {
        let kk = k();
        let hn = r + t * n.transpose() / d;
        let h = kk.matrix() * hn * kk.matrix().try_inverse().unwrap();
        // Points on the plane in front of camera 1.
        let (mut p1, mut p2) = (Vec::new(), Vec::new());
        for i in 0..5 {
            for j in 0..5 {
                let ray = Vector3::new(-0.3 + 0.15 * i as f64, -0.2 + 0.1 * j as f64, 1.0);
                let lam = d / n.dot(&ray);
                let x = ray * lam;
                let x2 = r * x + t;
                p1.push(kk.project(&x));
                p2.push(kk.project(&x2));
            }
        }
        (h, p1, p2)
    }

    #[test]
    fn recovers_ground_truth_among_candidates() {
        let r = *Rotation3::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)).matrix();
        let t = Vector3::new(0.5, 0.1, -0.2);
        let n = Vector3::new(0.1, -0.2, 1.0).normalize();
        let d = 4.0;
        let (h, p1, p2) = setup(r, t, n, d);
        let kk = k();
        for scale in [1.0, -3.0, 1e-4] {
            let sols = decompose_homography(&(h * scale), &kk, &kk).unwrap();
            assert_eq!(sols.len(), 4);
            let hit = sols.iter().any(|s| {
                rotation_angle_deg(&s.r, &r) < 1e-8
                    && (s.t - t / d).norm() < 1e-10
                    && (s.n - n).norm() < 1e-10
            });
            assert!(hit, "{sols:?}");
            let vis = visible_solutions(&sols, &kk, &kk, &p1, &p2, 1.0);
            assert!(!vis.is_empty() && vis.len() <= 2, "{vis:?}");
            assert!(vis.iter().any(|&i| (sols[i].n - n).norm() < 1e-10));
        }
    }

    #[test]
    fn matches_opencv_decomposition_and_visibility() {
        // cv2.decomposeHomographyMat and cv2.filterHomographyDecompByVisibleRefpoints (OpenCV 5)
        // on the `recovers_ground_truth_among_candidates` setup: (t, n, Rodrigues r) per
        // solution, and OpenCV keeps solutions 1 and 3.
        let cv: [([f64; 3], [f64; 3], [f64; 3]); 4] = [
            (
                [-0.125, -0.025, 0.05],
                [-0.097590007294853, 0.195180014589681, -0.975900072948539],
                [0.1, -0.2, 0.05],
            ),
            (
                [0.125, 0.025, -0.05],
                [0.097590007294853, -0.195180014589681, 0.975900072948539],
                [0.1, -0.2, 0.05],
            ),
            (
                [-0.003024303696523, -0.039447246313201, 0.131090687485637],
                [0.860715569428111, 0.0818882223319, -0.502456990783653],
                [0.096706513123142, -0.079457139886314, 0.080129510628724],
            ),
            (
                [0.003024303696523, 0.039447246313201, -0.131090687485637],
                [-0.860715569428111, -0.0818882223319, 0.502456990783653],
                [0.096706513123142, -0.079457139886314, 0.080129510628724],
            ),
        ];
        let r = *Rotation3::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)).matrix();
        let n = Vector3::new(0.1, -0.2, 1.0).normalize();
        let (h, p1, p2) = setup(r, Vector3::new(0.5, 0.1, -0.2), n, 4.0);
        let kk = k();
        let sols = decompose_homography(&h, &kk, &kk).unwrap();
        let find = |c: &([f64; 3], [f64; 3], [f64; 3])| {
            let rc = *Rotation3::from_scaled_axis(Vector3::from(c.2)).matrix();
            sols.iter().position(|s| {
                (s.t - Vector3::from(c.0)).norm() < 1e-9
                    && (s.n - Vector3::from(c.1)).norm() < 1e-9
                    && (s.r - rc).norm() < 1e-9
            })
        };
        let idx: Vec<usize> = cv.iter().map(|c| find(c).unwrap()).collect();
        let mut vis = visible_solutions(&sols, &kk, &kk, &p1, &p2, 1.0);
        vis.sort_unstable();
        let mut expect = vec![idx[1], idx[3]];
        expect.sort_unstable();
        assert_eq!(vis, expect);
    }

    #[test]
    fn pure_rotation_and_degenerate() {
        let r = *Rotation3::from_scaled_axis(Vector3::new(0.1, 0.3, -0.05)).matrix();
        let kk = k();
        let h = kk.matrix() * r * kk.matrix().try_inverse().unwrap();
        let sols = decompose_homography(&h, &kk, &kk).unwrap();
        assert_eq!(sols.len(), 1);
        assert!(rotation_angle_deg(&sols[0].r, &r) < 1e-8 && sols[0].t.norm() == 0.0);
        assert!(decompose_homography(&Matrix3::zeros(), &kk, &kk).is_err());
        let mut rank2 = Matrix3::identity();
        rank2[(2, 2)] = 0.0;
        assert!(decompose_homography(&rank2, &kk, &kk).is_err());
        assert!(decompose_homography(&Matrix3::from_element(f64::NAN), &kk, &kk).is_err());
    }

    #[test]
    fn marker_pose_from_corners_and_homography() {
        let kk = k();
        let r = *Rotation3::from_scaled_axis(Vector3::new(0.4, -0.3, 0.2)).matrix();
        let t = Vector3::new(0.05, -0.02, 0.6);
        let s = 0.1;
        let obj = [
            [-s / 2.0, s / 2.0],
            [s / 2.0, s / 2.0],
            [s / 2.0, -s / 2.0],
            [-s / 2.0, -s / 2.0],
        ];
        let corners: [[f64; 2]; 4] =
            std::array::from_fn(|i| kk.project(&(r * Vector3::new(obj[i][0], obj[i][1], 0.0) + t)));
        for refine in [false, true] {
            let p = marker_pose(&corners, s, &kk, refine).unwrap();
            assert!(rotation_angle_deg(&p.r, &r) < 1e-7, "{refine}");
            assert!((p.t - t).norm() < 1e-9);
        }
        // Homography form: H = K [r1 r2 t], any scale.
        let h = kk.matrix()
            * Matrix3::from_columns(&[r.column(0).into_owned(), r.column(1).into_owned(), t])
            * -2.5;
        let p = plane_pose_from_homography(&h, &kk).unwrap();
        assert!(rotation_angle_deg(&p.r, &r) < 1e-9 && (p.t - t).norm() < 1e-12);
        assert!(marker_pose(&[[0.0, 0.0]; 4], s, &kk, true).is_err());
        assert!(marker_pose(&corners, 0.0, &kk, true).is_err());
        assert!(plane_pose_from_homography(&Matrix3::zeros(), &kk).is_err());
    }

    proptest! {
        #[test]
        fn random_planes_never_nan(ax in -1.0f64..1.0, ay in -1.0f64..1.0, tx in -1.0f64..1.0, tz in -0.5f64..0.5, nx in -0.5f64..0.5, d in 0.5f64..20.0, f32_round in any::<bool>()) {
            let r = *Rotation3::from_scaled_axis(Vector3::new(ax, ay, 0.1) * 0.3).matrix();
            let t = Vector3::new(tx, 0.1, tz);
            let n = Vector3::new(nx, 0.1, 1.0).normalize();
            // Both cameras on the same side of the plane (det H > 0 before scaling): otherwise
            // no point of the plane is in front of both and no decomposition can be visible.
            prop_assume!(1.0 + n.dot(&(r.transpose() * t)) / d > 0.05);
            let (mut h, _, _) = setup(r, t, n, d);
            if f32_round { h = h.map(|v| f64::from(v as f32)); }
            let kk = k();
            if let Ok(sols) = decompose_homography(&h, &kk, &kk) {
                for s in &sols {
                    prop_assert!(s.r.iter().chain(s.t.iter()).chain(s.n.iter()).all(|v| v.is_finite()));
                }
                // Exact data: the true motion is among the solutions. The SVD's accuracy falls
                // as two singular values of H approach each other, hence 1e-4° and 1e-6 rather
                // than machine precision.
                if !f32_round && t.norm() > 1e-3 {
                    let errors: Vec<(f64, f64)> = sols
                        .iter()
                        .map(|s| (rotation_angle_deg(&s.r, &r), (s.t - t / d).norm()))
                        .collect();
                    prop_assert!(
                        errors.iter().any(|&(dr, dt)| dr < 1e-4 && dt < 1e-6),
                        "errors {:?}",
                        errors
                    );
                }
            }
        }
    }

    #[test]
    fn operator_runs() {
        let r = *Rotation3::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)).matrix();
        let t = Vector3::new(0.5, 0.1, -0.2);
        let n = Vector3::new(0.1, -0.2, 1.0).normalize();
        let (h, p1, p2) = setup(r, t, n, 4.0);
        let op = DecomposeHomography::new(DecomposeHomographyParams::default()).unwrap();
        let specs = DecomposeHomography::inputs();
        let cam = Camera {
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![700.0, 720.0, 320.0, 240.0],
        };
        let hv = Value::Matrix(Arc::new(
            Matrix::new(3, 3, h.transpose().as_slice().to_vec()).unwrap(),
        ));
        let ctx = RunContext {
            node: "h".into(),
            threads: 1,
            element: None,
        };
        let values = vec![
            Some(hv.clone()),
            Some(Value::Camera(Arc::new(cam.clone()))),
            None,
            None,
            None,
        ];
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::List(l)) = out.take("poses") else {
            panic!()
        };
        assert_eq!(l.items.len(), 4);
        let values = vec![
            Some(hv),
            Some(Value::Camera(Arc::new(cam))),
            None,
            Some(Value::Points2D(Arc::new(p1))),
            Some(Value::Points2D(Arc::new(p2))),
        ];
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Matrix(m)) = out.take("normals") else {
            panic!()
        };
        assert!(m.rows >= 1 && m.rows <= 2);
    }
}
