//! `geometry.visual_servo_step`: one step of image-based visual servoing (IBVS) with point
//! features.
//!
//! For a normalized image point `(x, y)` at depth `Z` the interaction matrix (Chaumette &
//! Hutchinson, "Visual servo control, Part I", IEEE RAM 2006, eq. 11) relates the feature
//! velocity to the camera's velocity screw `v = (vx, vy, vz, ωx, ωy, ωz)` (camera frame):
//!
//! ```text
//! L = [ −1/Z   0    x/Z   xy     −(1+x²)   y ]
//!     [  0   −1/Z   y/Z   1+y²   −xy      −x ]
//! ```
//!
//! Stacking the rows of all points, the control law is `v = −λ L⁺ e` with `e = s − s*` the
//! feature error and `L⁺` the Moore–Penrose pseudo-inverse (SVD). `L` can be evaluated at the
//! current features and depths, at the desired ones, or as the mean of both (eq. 16–19).

use nalgebra::{DMatrix, Vector6};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::Value;
use ocellus_engine::{param_enum, params};

use super::pose_util::{gt, input_intrinsics, input_points2, matrix_value};

/// The 2×6 interaction matrix of a normalized point `(x, y)` at depth `z`.
pub fn interaction_matrix(x: f64, y: f64, z: f64) -> [[f64; 6]; 2] {
    let iz = 1.0 / z;
    [
        [-iz, 0.0, x * iz, x * y, -(1.0 + x * x), y],
        [0.0, -iz, y * iz, 1.0 + y * y, -x * y, -x],
    ]
}

param_enum! {
    /// Where the interaction matrix is evaluated.
    pub enum InteractionAt {
        /// At the current features and depths.
        Current = "current",
        /// At the desired features and depths.
        Desired = "desired",
        /// The mean of both.
        Mean = "mean",
    }
}

/// One IBVS step: the camera velocity `(vx, vy, vz, ωx, ωy, ωz)` (camera frame; translation in
/// the depths' units per unit time, rotation in rad per unit time) that drives the normalized
/// features `current` toward `desired` with gain `gain`. `depths` and `desired_depths` give `Z`
/// per point. Errors on mismatched lengths, no points, non-positive or non-finite depths.
pub fn visual_servo_step(
    current: &[[f64; 2]],
    desired: &[[f64; 2]],
    depths: &[f64],
    desired_depths: &[f64],
    gain: f64,
    at: InteractionAt,
) -> Result<Vector6<f64>, String> {
    let n = current.len();
    if n == 0 {
        return Err("no feature points".into());
    }
    if desired.len() != n || depths.len() != n || desired_depths.len() != n {
        return Err(format!(
            "lengths differ: {n} current, {} desired points, {} depths, {} desired depths",
            desired.len(),
            depths.len(),
            desired_depths.len()
        ));
    }
    if current
        .iter()
        .chain(desired)
        .flatten()
        .any(|v| !v.is_finite())
    {
        return Err("non-finite feature".into());
    }
    if depths
        .iter()
        .chain(desired_depths)
        .any(|&z| !gt(z, 0.0) || !z.is_finite())
    {
        return Err("depths must be finite and > 0".into());
    }
    let mut l = DMatrix::<f64>::zeros(2 * n, 6);
    let mut e = DMatrix::<f64>::zeros(2 * n, 1);
    for i in 0..n {
        let lc = interaction_matrix(current[i][0], current[i][1], depths[i]);
        let ld = interaction_matrix(desired[i][0], desired[i][1], desired_depths[i]);
        for r in 0..2 {
            for c in 0..6 {
                l[(2 * i + r, c)] = match at {
                    InteractionAt::Current => lc[r][c],
                    InteractionAt::Desired => ld[r][c],
                    InteractionAt::Mean => 0.5 * (lc[r][c] + ld[r][c]),
                };
            }
            e[(2 * i + r, 0)] = current[i][r] - desired[i][r];
        }
    }
    let scale = l.amax();
    let pinv = l.pseudo_inverse(1e-12 * scale.max(1e-300))?;
    let v = pinv * e * (-gain);
    let out = Vector6::from_iterator(v.iter().copied());
    if out.iter().all(|x| x.is_finite()) {
        Ok(out)
    } else {
        Err("velocity is not finite".into())
    }
}

params! {
    /// Parameters of `geometry.visual_servo_step`.
    pub struct VisualServoParams {
        /// Control gain λ, per unit time, > 0. Default 0.5.
        gain: f64 = 0.5 => [min = 0.0],
        /// Where the interaction matrix is evaluated: "current", "desired" or "mean". Default
        /// "mean".
        interaction: InteractionAt = InteractionAt::Mean,
        /// Depth of every point (world units) when no `depths` input is connected, and of every
        /// desired point when no `desired_depths` is connected, > 0. Default 1.
        depth: f64 = 1.0 => [min = 0.0],
    }
}

/// Image-based visual servoing step (`geometry.visual_servo_step`). See [`visual_servo_step`].
#[derive(Debug, Clone, PartialEq)]
pub struct VisualServoStep {
    gain: f64,
    interaction: InteractionAt,
    depth: f64,
}

impl Op for VisualServoStep {
    type Params = VisualServoParams;
    const ID: &'static str = "geometry.visual_servo_step";
    const SUMMARY: &'static str =
        "Computes the camera velocity of one image-based visual-servoing step for point features.";
    const DOC: &'static str = r#"
Image-based visual servoing with point features (Chaumette & Hutchinson, "Visual servo control,
Part I: basic approaches", IEEE Robotics & Automation Magazine 2006). The pixel features
`current` and `desired` are normalized with `camera` (pinhole; distortion must be zero); each
point contributes the 2×6 interaction matrix `L` of its normalized coordinates and depth, and
the camera velocity is `v = −λ L⁺ (s − s*)` with `L⁺` the SVD pseudo-inverse. `interaction`
chooses `L` at the current features ("current", needs current depths), at the desired ones
("desired") or their mean ("mean", the usual choice). At least three non-collinear points make
`L` full rank; with fewer the minimum-norm velocity is returned.

Inputs `depths` / `desired_depths` are N×1 matrices of depths (world units); when absent, the
`depth` parameter is used for every point.

Outputs: `velocity` is a 6×1 matrix `(vx, vy, vz, ωx, ωy, ωz)` in the camera frame
(translation in depth units per unit time, rotation in rad per unit time); `error` is the norm
of `s − s*` in normalized image units.

Example:
    "v": (op: "geometry.visual_servo_step", inputs: { "current": "det.points", "desired": "goal.points", "camera": "cam.camera" }, params: (gain: 0.5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("current", PortType::Points2D, "Current feature points, px."),
            PortSpec::new("desired", PortType::Points2D, "Desired feature points, px."),
            PortSpec::new("camera", PortType::Camera, "Pinhole intrinsics."),
            PortSpec::new("depths", PortType::Matrix, "N×1 current depths.").optional(),
            PortSpec::new("desired_depths", PortType::Matrix, "N×1 desired depths.").optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "velocity",
                PortType::Matrix,
                "6×1 (vx, vy, vz, ωx, ωy, ωz).",
            ),
            PortSpec::new(
                "error",
                PortType::Scalar,
                "Feature error norm, normalized units.",
            ),
        ]
    }

    fn new(params: VisualServoParams) -> Result<Self, String> {
        let VisualServoParams {
            gain,
            interaction,
            depth,
        } = params;
        if !gain.is_finite() || gain <= 0.0 {
            return Err(format!("`gain` must be finite and > 0, got {gain}"));
        }
        if !depth.is_finite() || depth <= 0.0 {
            return Err(format!("`depth` must be finite and > 0, got {depth}"));
        }
        Ok(VisualServoStep {
            gain,
            interaction,
            depth,
        })
    }
}

fn depth_input(
    inputs: &Inputs<'_>,
    name: &str,
    n: usize,
    default: f64,
) -> Result<Vec<f64>, OpError> {
    match inputs.get(name) {
        None => Ok(vec![default; n]),
        Some(Value::Matrix(m)) if m.cols == 1 && m.rows == n => Ok(m.data.clone()),
        Some(Value::Matrix(m)) => Err(OpError::input(
            name,
            format!("expected a {n}×1 matrix, got {}×{}", m.rows, m.cols),
        )),
        Some(other) => Err(OpError::input(
            name,
            format!("expected Matrix, got {}", other.port_type()),
        )),
    }
}

impl Operator for VisualServoStep {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let k = input_intrinsics(inputs, "camera")?;
        let cur: Vec<[f64; 2]> = input_points2(inputs, "current")?
            .iter()
            .map(|p| k.normalize(*p).into())
            .collect();
        let des: Vec<[f64; 2]> = input_points2(inputs, "desired")?
            .iter()
            .map(|p| k.normalize(*p).into())
            .collect();
        let n = cur.len();
        let z = depth_input(inputs, "depths", n, self.depth)?;
        let zd = depth_input(inputs, "desired_depths", n, self.depth)?;
        let v = visual_servo_step(&cur, &des, &z, &zd, self.gain, self.interaction)
            .map_err(|e| OpError::input("current", e))?;
        let err = cur
            .iter()
            .zip(&des)
            .map(|(a, b)| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2))
            .sum::<f64>()
            .sqrt();
        Ok(Outputs::new()
            .with("velocity", matrix_value(6, 1, v.iter().copied().collect())?)
            .with("error", Value::Scalar(err)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use ocellus_engine::value::{Camera, CameraModel};
    use std::sync::Arc;

    #[test]
    fn interaction_matrix_hand_computed() {
        let l = interaction_matrix(0.5, -0.25, 2.0);
        assert_eq!(l[0], [-0.5, 0.0, 0.25, -0.125, -1.25, -0.25]);
        assert_eq!(l[1], [0.0, -0.5, -0.125, 1.0625, 0.125, -0.5]);
    }

    #[test]
    fn interaction_matrix_matches_finite_differences() {
        // Feature motion under a small camera motion equals L·v·dt.
        let x = Vector3::new(0.3, -0.2, 2.5);
        let v = [0.1, -0.05, 0.2, 0.03, -0.02, 0.04];
        let dt = 1e-6;
        let vel = Vector3::new(v[0], v[1], v[2]);
        let w = Vector3::new(v[3], v[4], v[5]);
        // Point in the camera frame: Ẋ = −v − ω × X.
        let x2 = x + (-vel - w.cross(&x)) * dt;
        let l = interaction_matrix(x.x / x.z, x.y / x.z, x.z);
        for r in 0..2 {
            let pred: f64 = (0..6).map(|c| l[r][c] * v[c]).sum::<f64>() * dt;
            let got = x2[r] / x2.z - x[r] / x.z;
            assert!((pred - got).abs() < 1e-11, "{pred} {got}");
        }
    }

    #[test]
    fn closed_loop_converges() {
        // Four points; the desired view is a rotated and translated camera.
        let world = [
            Vector3::new(-0.2, -0.2, 0.0),
            Vector3::new(0.2, -0.2, 0.0),
            Vector3::new(0.2, 0.2, 0.0),
            Vector3::new(-0.2, 0.2, 0.1),
        ];
        let proj = |r: &Rotation3<f64>, t: &Vector3<f64>| -> (Vec<[f64; 2]>, Vec<f64>) {
            world
                .iter()
                .map(|p| {
                    let c = r * p + t;
                    ([c.x / c.z, c.y / c.z], c.z)
                })
                .unzip()
        };
        let rd = Rotation3::identity();
        let td = Vector3::new(0.0, 0.0, 1.0);
        let (sd, zd) = proj(&rd, &td);
        let mut r = Rotation3::from_scaled_axis(Vector3::new(0.1, -0.1, 0.3));
        let mut t = Vector3::new(0.1, -0.05, 1.3);
        let (s0, _) = proj(&r, &t);
        let err = |s: &[[f64; 2]]| -> f64 {
            s.iter()
                .zip(&sd)
                .map(|(a, b)| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        let e0 = err(&s0);
        let dt = 0.05;
        for _ in 0..400 {
            let (s, z) = proj(&r, &t);
            let v = visual_servo_step(&s, &sd, &z, &zd, 1.0, InteractionAt::Mean).unwrap();
            // Camera moves by (v, ω) in its own frame: camera_from_world ← exp(−ω dt)·(·) − v dt.
            let dr = Rotation3::from_scaled_axis(-Vector3::new(v[3], v[4], v[5]) * dt);
            r = dr * r;
            t = dr * t - Vector3::new(v[0], v[1], v[2]) * dt;
        }
        let (s, _) = proj(&r, &t);
        assert!(err(&s) < 1e-6 * e0, "{} vs {}", err(&s), e0);
        assert!((t - td).norm() < 1e-4);
    }

    #[test]
    fn errors_and_operator() {
        assert!(visual_servo_step(&[], &[], &[], &[], 1.0, InteractionAt::Mean).is_err());
        assert!(
            visual_servo_step(
                &[[0.0, 0.0]],
                &[[0.0, 0.0]],
                &[0.0],
                &[1.0],
                1.0,
                InteractionAt::Mean
            )
            .is_err()
        );
        assert!(
            visual_servo_step(
                &[[0.0, 0.0]],
                &[[0.1, 0.0]],
                &[1.0],
                &[1.0],
                1.0,
                InteractionAt::Current
            )
            .is_ok()
        );
        assert!(
            VisualServoStep::new(VisualServoParams {
                gain: 0.0,
                ..Default::default()
            })
            .is_err()
        );
        let op = VisualServoStep::new(VisualServoParams::default()).unwrap();
        let specs = VisualServoStep::inputs();
        let cam = Camera {
            model: CameraModel::SimplePinhole,
            width: 640,
            height: 480,
            params: vec![500.0, 320.0, 240.0],
        };
        let cur = vec![[300.0, 200.0], [350.0, 210.0], [340.0, 260.0]];
        let values = vec![
            Some(Value::Points2D(Arc::new(cur.clone()))),
            Some(Value::Points2D(Arc::new(cur))),
            Some(Value::Camera(Arc::new(cam))),
            None,
            None,
        ];
        let ctx = RunContext {
            node: "v".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Matrix(v)) = out.take("velocity") else {
            panic!()
        };
        assert_eq!((v.rows, v.cols), (6, 1));
        assert!(v.data.iter().all(|x| x.abs() < 1e-15));
        assert!(matches!(out.take("error"), Some(Value::Scalar(e)) if e == 0.0));
    }
}
