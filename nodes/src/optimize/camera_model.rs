//! Projection of a camera-frame point through every [`CameraModel`] of the engine, with
//! analytic Jacobians with respect to the model's parameters (in the model's own order, the
//! order of [`Camera::params`](ocellus_engine::value::Camera)) and to the point.
//!
//! The chain is `P → n = (X/Z, Y/Z) → d = distort(n) → pixel = K d`:
//! - `SIMPLE_PINHOLE` `[f, cx, cy]`, `PINHOLE` `[fx, fy, cx, cy]`: `d = n`;
//! - `SIMPLE_RADIAL` `[f, cx, cy, k]` and `RADIAL` `[f, cx, cy, k1, k2]`: `d = n (1 + k1 r² + k2
//!   r⁴)`, COLMAP's models;
//! - `OPENCV` `[fx, fy, cx, cy, k1, k2, p1, p2]` and `FULL_OPENCV` (radial–tangential)
//!   `[fx, fy, cx, cy, skew, k1, k2, p1, p2, k3]`: Brown–Conrady as OpenCV's `projectPoints`
//!   (see [`crate::geometry::camera`]);
//! - `OPENCV_FISHEYE` `[fx, fy, cx, cy, skew, k1, k2, k3, k4]`: Kannala–Brandt, `θ = atan2(√(X² +
//!   Y²), Z)`, `θd = θ (1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸)`, `d = θd (X, Y) / √(X² + Y²)`;
//!
//! then `u = fx d.x + skew d.y + cx`, `v = fy d.y + cy`. A pinhole-family camera cannot see a
//! point with `Z ≤ 0` (the projection is `None`); a fisheye sees every direction but straight
//! back.
//!
//! References: Brown, "Decentering distortion of lenses" (1966); Kannala & Brandt, "A generic
//! camera model and calibration method for conventional, wide-angle, and fish-eye lenses"
//! (PAMI 2006); COLMAP's `camera_models.h` for the parameter orders.

use ocellus_engine::value::CameraModel;

/// Most parameters any model has.
pub const MAX_CAMERA_PARAMS: usize = 10;

/// Below this radius (normalized units) the fisheye model is evaluated by its series at the
/// axis, where `θd / r → 1 / Z`.
const FISHEYE_AXIS_RADIUS: f64 = 1e-12;

/// A projection and its Jacobians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projection {
    /// The pixel.
    pub pixel: [f64; 2],
    /// `∂pixel / ∂params`, row-major 2 × `param_count` (the first `2 · param_count` entries).
    pub d_params: [f64; 2 * MAX_CAMERA_PARAMS],
    /// `∂pixel / ∂P`, row-major 2 × 3.
    pub d_point: [f64; 6],
}

impl Projection {
    /// `∂pixel_row / ∂params[col]`.
    pub fn d_param(&self, row: usize, col: usize, param_count: usize) -> f64 {
        self.d_params[row * param_count + col]
    }
}

/// Where the model keeps `fx, fy, cx, cy, skew` (`fy` equals `fx` for one-focal models, `skew`
/// absent for models without it).
struct PinholeLayout {
    fx: usize,
    fy: Option<usize>,
    cx: usize,
    cy: usize,
    skew: Option<usize>,
    /// Index of the first distortion parameter.
    distortion: usize,
}

fn layout(model: CameraModel) -> PinholeLayout {
    match model {
        CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial => {
            PinholeLayout {
                fx: 0,
                fy: None,
                cx: 1,
                cy: 2,
                skew: None,
                distortion: 3,
            }
        }
        CameraModel::Pinhole | CameraModel::OpenCv => PinholeLayout {
            fx: 0,
            fy: Some(1),
            cx: 2,
            cy: 3,
            skew: None,
            distortion: 4,
        },
        CameraModel::RadialTangential | CameraModel::Fisheye => PinholeLayout {
            fx: 0,
            fy: Some(1),
            cx: 2,
            cy: 3,
            skew: Some(4),
            distortion: 5,
        },
    }
}

/// Distorted normalized coordinates `d`, `∂d/∂P` (2 × 3) and `∂d/∂coefficients` (2 × up to 5,
/// in the model's order) of a camera-frame point. `None` where the model cannot project it.
fn distort(model: CameraModel, c: &[f64], p: [f64; 3]) -> Option<([f64; 2], [f64; 6], [f64; 10])> {
    let [x3, y3, z3] = p;
    let mut dk = [0.0; 10];
    if model == CameraModel::Fisheye {
        let r2 = x3 * x3 + y3 * y3;
        let r = r2.sqrt();
        if r < FISHEYE_AXIS_RADIUS * z3.abs().max(f64::MIN_POSITIVE) {
            // On the axis: θd ≈ θ ≈ r / Z, d ≈ (X, Y) / Z.
            if z3 <= 0.0 {
                return None;
            }
            let iz = 1.0 / z3;
            return Some((
                [x3 * iz, y3 * iz],
                [iz, 0.0, -x3 * iz * iz, 0.0, iz, -y3 * iz * iz],
                dk,
            ));
        }
        let theta = r.atan2(z3);
        let t2 = theta * theta;
        let [k1, k2, k3, k4] = [c[0], c[1], c[2], c[3]];
        let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
        let theta_d = theta * poly;
        let dtheta_d = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
        // θ = atan2(r, Z): ∂θ/∂X = Z X / (r ρ²), ∂θ/∂Y = Z Y / (r ρ²), ∂θ/∂Z = −r / ρ².
        let rho2 = r2 + z3 * z3;
        let dth = [z3 * x3 / (r * rho2), z3 * y3 / (r * rho2), -r / rho2];
        let s = theta_d / r;
        // s = θd / r: ∂s/∂X = θd' ∂θ/∂X / r − θd X / r³.
        let r3 = r2 * r;
        let ds = [
            dtheta_d * dth[0] / r - theta_d * x3 / r3,
            dtheta_d * dth[1] / r - theta_d * y3 / r3,
            dtheta_d * dth[2] / r,
        ];
        let d = [x3 * s, y3 * s];
        let jp = [
            s + x3 * ds[0],
            x3 * ds[1],
            x3 * ds[2],
            y3 * ds[0],
            s + y3 * ds[1],
            y3 * ds[2],
        ];
        // ∂d/∂kᵢ = (X, Y)/r · θ^(2i+1).
        let mut tp = theta * t2;
        for i in 0..4 {
            dk[i] = x3 / r * tp;
            dk[4 + i] = y3 / r * tp;
            tp *= t2;
        }
        return Some((d, jp, dk));
    }
    if z3 <= 0.0 {
        return None;
    }
    let iz = 1.0 / z3;
    let (x, y) = (x3 * iz, y3 * iz);
    // ∂n/∂P.
    let dn = [iz, 0.0, -x * iz, 0.0, iz, -y * iz];
    let r2 = x * x + y * y;
    // d = (x, y) radial + tangential; a = ∂d/∂n (2 × 2).
    let (d, a) = match model {
        CameraModel::SimplePinhole | CameraModel::Pinhole => ([x, y], [1.0, 0.0, 0.0, 1.0]),
        CameraModel::SimpleRadial | CameraModel::Radial => {
            let k1 = c[0];
            let k2 = if model == CameraModel::Radial {
                c[1]
            } else {
                0.0
            };
            let radial = 1.0 + r2 * (k1 + k2 * r2);
            let dradial = 2.0 * (k1 + 2.0 * k2 * r2); // ∂radial/∂(x or y) = dradial · (x or y)
            dk[0] = x * r2;
            dk[5] = y * r2;
            if model == CameraModel::Radial {
                dk[1] = x * r2 * r2;
                dk[6] = y * r2 * r2;
            }
            (
                [x * radial, y * radial],
                [
                    radial + x * dradial * x,
                    x * dradial * y,
                    y * dradial * x,
                    radial + y * dradial * y,
                ],
            )
        }
        _ => {
            // OPENCV [k1 k2 p1 p2], FULL_OPENCV [k1 k2 p1 p2 k3].
            let (k1, k2, p1, p2) = (c[0], c[1], c[2], c[3]);
            let k3 = if model == CameraModel::RadialTangential {
                c[4]
            } else {
                0.0
            };
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dradial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2));
            let d = [
                x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            ];
            let a = [
                radial + x * dradial * x + 2.0 * p1 * y + 6.0 * p2 * x,
                x * dradial * y + 2.0 * p1 * x + 2.0 * p2 * y,
                y * dradial * x + 2.0 * p1 * x + 2.0 * p2 * y,
                radial + y * dradial * y + 6.0 * p1 * y + 2.0 * p2 * x,
            ];
            // Rows of 5: [k1 k2 p1 p2 k3].
            dk[0] = x * r2;
            dk[1] = x * r2 * r2;
            dk[2] = 2.0 * x * y;
            dk[3] = r2 + 2.0 * x * x;
            dk[4] = x * r2 * r2 * r2;
            dk[5] = y * r2;
            dk[6] = y * r2 * r2;
            dk[7] = r2 + 2.0 * y * y;
            dk[8] = 2.0 * x * y;
            dk[9] = y * r2 * r2 * r2;
            (d, a)
        }
    };
    let jp = [
        a[0] * dn[0] + a[1] * dn[3],
        a[0] * dn[1] + a[1] * dn[4],
        a[0] * dn[2] + a[1] * dn[5],
        a[2] * dn[0] + a[3] * dn[3],
        a[2] * dn[1] + a[3] * dn[4],
        a[2] * dn[2] + a[3] * dn[5],
    ];
    Some((d, jp, dk))
}

/// Number of distortion coefficients of a model, and the row stride `distort` uses for them.
fn distortion_shape(model: CameraModel) -> (usize, usize) {
    match model {
        CameraModel::SimplePinhole | CameraModel::Pinhole => (0, 5),
        CameraModel::SimpleRadial => (1, 5),
        CameraModel::Radial => (2, 5),
        CameraModel::OpenCv => (4, 5),
        CameraModel::RadialTangential => (5, 5),
        CameraModel::Fisheye => (4, 4),
    }
}

/// Projects the camera-frame point `p` through `model` with `params` (the model's parameter
/// order), with the Jacobians. `None` when the parameter count is wrong, the model cannot see
/// the point, or the result is not finite.
pub fn project(model: CameraModel, params: &[f64], p: [f64; 3]) -> Option<Projection> {
    let n = model.param_count();
    if params.len() != n {
        return None;
    }
    let l = layout(model);
    let (nk, stride) = distortion_shape(model);
    let (d, jd, dk) = distort(model, &params[l.distortion..], p)?;
    let fx = params[l.fx];
    let fy = l.fy.map_or(fx, |i| params[i]);
    let skew = l.skew.map_or(0.0, |i| params[i]);
    let pixel = [
        fx * d[0] + skew * d[1] + params[l.cx],
        fy * d[1] + params[l.cy],
    ];
    let mut out = Projection {
        pixel,
        d_params: [0.0; 2 * MAX_CAMERA_PARAMS],
        d_point: [0.0; 6],
    };
    // ∂pixel/∂P = [[fx, skew], [0, fy]] · ∂d/∂P.
    for k in 0..3 {
        out.d_point[k] = fx * jd[k] + skew * jd[3 + k];
        out.d_point[3 + k] = fy * jd[3 + k];
    }
    let dp = &mut out.d_params;
    // Pinhole parameters.
    if let Some(fy_index) = l.fy {
        dp[l.fx] = d[0];
        dp[n + fy_index] = d[1];
    } else {
        dp[l.fx] = d[0];
        dp[n + l.fx] = d[1];
    }
    dp[l.cx] = 1.0;
    dp[n + l.cy] = 1.0;
    if let Some(s) = l.skew {
        dp[s] = d[1];
    }
    // Distortion: ∂pixel/∂k = [[fx, skew], [0, fy]] · ∂d/∂k.
    for i in 0..nk {
        let (a, b) = (dk[i], dk[stride + i]);
        dp[l.distortion + i] = fx * a + skew * b;
        dp[n + l.distortion + i] = fy * b;
    }
    let finite = pixel.iter().all(|v| v.is_finite())
        && out.d_point.iter().all(|v| v.is_finite())
        && out.d_params[..2 * n].iter().all(|v| v.is_finite());
    finite.then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::camera::Lens;
    use ocellus_engine::value::Camera;

    const MODELS: [(CameraModel, &[f64]); 7] = [
        (CameraModel::SimplePinhole, &[800.0, 320.0, 240.0]),
        (CameraModel::Pinhole, &[800.0, 790.0, 320.0, 240.0]),
        (CameraModel::SimpleRadial, &[800.0, 320.0, 240.0, -0.12]),
        (CameraModel::Radial, &[800.0, 320.0, 240.0, -0.12, 0.03]),
        (
            CameraModel::OpenCv,
            &[800.0, 790.0, 320.0, 240.0, -0.2, 0.05, 1e-3, -2e-3],
        ),
        (
            CameraModel::RadialTangential,
            &[
                800.0, 790.0, 320.0, 240.0, 0.5, -0.2, 0.05, 1e-3, -2e-3, 0.01,
            ],
        ),
        (
            CameraModel::Fisheye,
            &[300.0, 298.0, 320.0, 240.0, 0.2, 0.02, -0.01, 0.003, -0.0005],
        ),
    ];

    const POINTS: [[f64; 3]; 4] = [
        [0.3, -0.2, 2.0],
        [-1.1, 0.7, 3.5],
        [0.0, 0.0, 1.0],
        [1e-3, 2e-3, 0.5],
    ];

    #[test]
    fn pixels_agree_with_the_geometry_lens_models() {
        for (model, params) in MODELS {
            let camera = Camera {
                model,
                width: 640,
                height: 480,
                params: params.to_vec(),
            };
            let lens = Lens::from_camera(&camera);
            for p in POINTS {
                let ours = project(model, params, p).unwrap().pixel;
                let theirs = lens.project(p).unwrap();
                for k in 0..2 {
                    assert!(
                        (ours[k] - theirs[k]).abs() < 1e-9,
                        "{model:?} {p:?}: {ours:?} vs {theirs:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn jacobians_match_central_differences() {
        for (model, params) in MODELS {
            let n = params.len();
            for p in POINTS {
                let proj = project(model, params, p).unwrap();
                for k in 0..3 {
                    let h = 1e-6 * p[k].abs().max(0.1);
                    let (mut a, mut b) = (p, p);
                    a[k] += h;
                    b[k] -= h;
                    let (pa, pb) = (
                        project(model, params, a).unwrap().pixel,
                        project(model, params, b).unwrap().pixel,
                    );
                    for row in 0..2 {
                        let fd = (pa[row] - pb[row]) / (2.0 * h);
                        let an = proj.d_point[3 * row + k];
                        assert!(
                            (fd - an).abs() <= 1e-5 * (1.0 + an.abs()),
                            "{model:?} {p:?} d/dP{k} row {row}: {an} vs {fd}"
                        );
                    }
                }
                for k in 0..n {
                    let h = 1e-6 * params[k].abs().max(1.0);
                    let (mut a, mut b) = (params.to_vec(), params.to_vec());
                    a[k] += h;
                    b[k] -= h;
                    let (pa, pb) = (
                        project(model, &a, p).unwrap().pixel,
                        project(model, &b, p).unwrap().pixel,
                    );
                    for row in 0..2 {
                        let fd = (pa[row] - pb[row]) / (2.0 * h);
                        let an = proj.d_param(row, k, n);
                        assert!(
                            (fd - an).abs() <= 1e-5 * (1.0 + an.abs()),
                            "{model:?} {p:?} d/dparam{k} row {row}: {an} vs {fd}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn points_the_model_cannot_see_and_bad_parameter_counts_are_none() {
        for (model, params) in MODELS {
            assert!(project(model, &params[1..], [0.0, 0.0, 1.0]).is_none());
            if model != CameraModel::Fisheye {
                assert!(project(model, params, [0.1, 0.2, 0.0]).is_none());
                assert!(project(model, params, [0.1, 0.2, -1.0]).is_none());
            }
            assert!(project(model, params, [f64::NAN, 0.0, 1.0]).is_none());
        }
        // A fisheye sees a point beside the camera (90° off axis) but not straight back.
        let (model, params) = MODELS[6];
        assert!(project(model, params, [1.0, 0.0, 0.0]).is_some());
        assert!(project(model, params, [0.0, 0.0, -1.0]).is_none());
    }
}
