//! Camera models: pinhole intrinsics with skew and OpenCV's two lens models, projection,
//! unprojection and point undistortion (the angle-axis helpers are re-exported from
//! [`super::pose_util`]).
//!
//! A [`Lens`] is the pinhole matrix `K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]` plus a
//! [`Distortion`]:
//! - radial–tangential (Brown–Conrady, OpenCV's `k1, k2, p1, p2, k3`): a camera-frame point
//!   `(X, Y, Z)`, `Z > 0`, has normalized coordinates `x = X/Z, y = Y/Z`, `r² = x² + y²`,
//!   `x' = x(1 + k1r² + k2r⁴ + k3r⁶) + 2p1xy + p2(r² + 2x²)`,
//!   `y' = y(1 + k1r² + k2r⁴ + k3r⁶) + p1(r² + 2y²) + 2p2xy`;
//! - fisheye (Kannala–Brandt equidistant, OpenCV's `cv::fisheye`): `θ = atan2(√(X²+Y²), Z)`,
//!   `θd = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸)`, `(x', y') = θd · (X, Y)/√(X²+Y²)`; points at or
//!   beyond 90° off axis (`Z ≤ 0`) still project while `θd` grows with `θ`;
//!
//! then pixels `u = fx·x' + s·y' + cx`, `v = fy·y' + cy` (pixel centres at integers, OpenCV's
//! convention). OpenCV's fisheye skew `alpha` is `s / fx` here.
//!
//! Undistortion inverts the lens model by Newton's method on the 2×2 (radial–tangential) or 1-D
//! (fisheye) system, started from three of OpenCV's fixed-point steps, and reports failure
//! (`None`) when it does not converge to 1e-12 (normalized units) or the solution lies beyond
//! the first fold of the radial model (`d(r·radial)/dr ≤ 0` somewhere between the centre and
//! the point; fisheye: `dθd/dθ ≤ 0`): the "valid field". OpenCV's `undistortPoints` runs a fixed 5-step fixed-point iteration by
//! default and returns whatever it reached.

use nalgebra::Matrix3;
use ocellus_engine::value::{Camera, Distortion, Intrinsics};

/// Newton iterations allowed when undistorting.
const MAX_NEWTON: usize = 60;

/// A pinhole matrix and a lens distortion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lens {
    /// Pinhole intrinsics.
    pub k: Intrinsics,
    /// Distortion.
    pub distortion: Distortion,
}

impl Lens {
    /// The lens of an engine camera (COLMAP radial models map to radial–tangential).
    pub fn from_camera(camera: &Camera) -> Lens {
        Lens {
            k: camera.intrinsics(),
            distortion: camera.distortion(),
        }
    }

    /// An engine camera of this lens and image size.
    pub fn to_camera(&self, width: u32, height: u32) -> Camera {
        Camera::from_parts(width, height, self.k, self.distortion)
    }

    /// A lens without distortion.
    pub fn pinhole(k: Intrinsics) -> Lens {
        Lens {
            k,
            distortion: Distortion::None,
        }
    }

    /// True for an ideal pinhole (no distortion, or all coefficients zero).
    pub fn is_pinhole(&self) -> bool {
        match self.distortion {
            Distortion::None => true,
            Distortion::RadialTangential(d) => d.iter().all(|&v| v == 0.0),
            Distortion::Fisheye(_) => false,
        }
    }

    /// `K` as a row-major 3×3 matrix.
    pub fn k_matrix(&self) -> [f64; 9] {
        k_matrix(&self.k)
    }

    /// Distorted normalized coordinates → pixels.
    #[inline]
    pub fn to_pixel(&self, d: [f64; 2]) -> [f64; 2] {
        [
            self.k.fx * d[0] + self.k.skew * d[1] + self.k.cx,
            self.k.fy * d[1] + self.k.cy,
        ]
    }

    /// Pixels → distorted normalized coordinates (inverse of [`Lens::to_pixel`]).
    #[inline]
    pub fn from_pixel(&self, p: [f64; 2]) -> [f64; 2] {
        let y = (p[1] - self.k.cy) / self.k.fy;
        let x = (p[0] - self.k.cx - self.k.skew * y) / self.k.fx;
        [x, y]
    }

    /// Projects a camera-frame point to pixels. `None` behind a pinhole or radial–tangential
    /// camera (`Z ≤ 0`), at the camera centre, or for a non-finite result.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        let d = match self.distortion {
            Distortion::Fisheye(k) => {
                let r = p[0].hypot(p[1]);
                if r == 0.0 && p[2] <= 0.0 {
                    return None;
                }
                let theta = r.atan2(p[2]);
                let td = fisheye_theta_d(&k, theta);
                let s = if r > 0.0 { td / r } else { 1.0 / p[2] };
                [p[0] * s, p[1] * s]
            }
            _ => {
                if p[2] <= 0.0 {
                    return None;
                }
                self.distort([p[0] / p[2], p[1] / p[2]])
            }
        };
        let px = self.to_pixel(d);
        (px[0].is_finite() && px[1].is_finite()).then_some(px)
    }

    /// Applies the distortion to pinhole-normalized coordinates `(X/Z, Y/Z)`.
    #[inline]
    pub fn distort(&self, n: [f64; 2]) -> [f64; 2] {
        match self.distortion {
            Distortion::None => n,
            Distortion::RadialTangential(d) => distort_rt(&d, n),
            Distortion::Fisheye(k) => {
                let r = n[0].hypot(n[1]);
                if r == 0.0 {
                    return n;
                }
                let td = fisheye_theta_d(&k, r.atan());
                [n[0] * td / r, n[1] * td / r]
            }
        }
    }

    /// Inverts [`Lens::distort`]: distorted normalized coordinates → pinhole-normalized ones.
    /// `None` outside the valid field (no convergence, or a fisheye ray at ≥ 90°).
    pub fn undistort(&self, d: [f64; 2]) -> Option<[f64; 2]> {
        match self.distortion {
            Distortion::None => Some(d),
            Distortion::RadialTangential(c) => undistort_rt(&c, d),
            Distortion::Fisheye(k) => {
                let td = d[0].hypot(d[1]);
                if td == 0.0 {
                    return Some(d);
                }
                let theta = fisheye_theta(&k, td)?;
                if theta >= std::f64::consts::FRAC_PI_2 {
                    return None;
                }
                let s = theta.tan() / td;
                Some([d[0] * s, d[1] * s])
            }
        }
    }

    /// The unit ray (camera frame) seen at a pixel; fisheye rays may point backwards (beyond
    /// 90°). `None` outside the valid field.
    pub fn unproject(&self, p: [f64; 2]) -> Option<[f64; 3]> {
        let d = self.from_pixel(p);
        let ray = match self.distortion {
            Distortion::Fisheye(k) => {
                let td = d[0].hypot(d[1]);
                if td == 0.0 {
                    [0.0, 0.0, 1.0]
                } else {
                    let theta = fisheye_theta(&k, td)?;
                    let s = theta.sin() / td;
                    [d[0] * s, d[1] * s, theta.cos()]
                }
            }
            _ => {
                let n = self.undistort(d)?;
                [n[0], n[1], 1.0]
            }
        };
        let len = (ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2]).sqrt();
        Some(ray.map(|v| v / len))
    }
}

/// `K` of intrinsics, row-major.
pub fn k_matrix(k: &Intrinsics) -> [f64; 9] {
    [k.fx, k.skew, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]
}

/// Brown–Conrady distortion of normalized coordinates, OpenCV's formula.
#[inline]
pub fn distort_rt(c: &[f64; 5], n: [f64; 2]) -> [f64; 2] {
    let [k1, k2, p1, p2, k3] = *c;
    let [x, y] = n;
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    [
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    ]
}

/// Inverse of [`distort_rt`] by Newton's method; `None` if it does not converge or the
/// Jacobian is singular or flips orientation (the fold of a strong barrel model).
pub fn undistort_rt(c: &[f64; 5], d: [f64; 2]) -> Option<[f64; 2]> {
    let [k1, k2, p1, p2, k3] = *c;
    let (mut x, mut y) = (d[0], d[1]);
    // A fixed-point start (OpenCV's iteration) is closer than the distorted point itself.
    for _ in 0..3 {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        if radial <= 0.0 || !radial.is_finite() {
            x = d[0];
            y = d[1];
            break;
        }
        let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        x = (d[0] - dx) / radial;
        y = (d[1] - dy) / radial;
    }
    let scale = 1.0 + d[0].abs().max(d[1].abs());
    for _ in 0..MAX_NEWTON {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2); // d radial / d r²
        let fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - d[0];
        let fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - d[1];
        let a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x;
        let b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y;
        let cc = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y;
        let dd = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x;
        let det = a * dd - b * cc;
        if det <= 0.0 || !det.is_finite() {
            return None;
        }
        let sx = (dd * fx - b * fy) / det;
        let sy = (a * fy - cc * fx) / det;
        x -= sx;
        y -= sy;
        if !(x.is_finite() && y.is_finite()) {
            return None;
        }
        if sx.abs().max(sy.abs()) <= 1e-15 * scale {
            break;
        }
    }
    let back = distort_rt(c, [x, y]);
    let err = (back[0] - d[0]).abs().max((back[1] - d[1]).abs());
    (err <= 1e-12 * scale && radial_monotone(k1, k2, k3, x * x + y * y)).then_some([x, y])
}

/// True when `r ↦ r(1 + k1r² + k2r⁴ + k3r⁶)` increases on `[0, √r2]`: the point lies in the
/// valid field, not on an outer branch beyond a fold of the model (checked on 64 samples of
/// `d/dr = 1 + 3k1u + 5k2u² + 7k3u³`, `u = r²`, and at the end point).
fn radial_monotone(k1: f64, k2: f64, k3: f64, r2: f64) -> bool {
    (0..=64).all(|i| {
        let u = r2 * f64::from(i) / 64.0;
        1.0 + u * (3.0 * k1 + u * (5.0 * k2 + u * 7.0 * k3)) > 0.0
    })
}

/// `θd(θ) = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸)`.
#[inline]
pub fn fisheye_theta_d(k: &[f64; 4], theta: f64) -> f64 {
    let t2 = theta * theta;
    theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
}

/// Solves `θd(θ) = td` for θ ∈ [0, π) by Newton's method; `None` if it does not converge or
/// `θd` is not increasing there.
pub fn fisheye_theta(k: &[f64; 4], td: f64) -> Option<f64> {
    let mut theta = td.min(3.0);
    for _ in 0..MAX_NEWTON {
        let t2 = theta * theta;
        let f = fisheye_theta_d(k, theta) - td;
        let df = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
        if df <= 0.0 || !df.is_finite() {
            return None;
        }
        let step = f / df;
        theta -= step;
        if !theta.is_finite() || !(0.0..std::f64::consts::PI).contains(&theta) {
            return None;
        }
        if step.abs() <= 1e-15 * (1.0 + theta) {
            break;
        }
    }
    let err = (fisheye_theta_d(k, theta) - td).abs();
    let t2 = theta * theta;
    let slope = 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
    (err <= 1e-12 * (1.0 + td) && slope > 0.0).then_some(theta)
}

/// OpenCV's `undistortPoints`: pixels of `lens` → ideal points. Each pixel is undistorted to
/// pinhole-normalized coordinates, rotated by `r` (row-major 3×3, e.g. a rectification
/// rotation; identity if `None`) and, if `p` is given (the left 3×3 of a projection matrix),
/// projected by it; otherwise the normalized coordinates are returned. Points outside the
/// valid field (or behind the rotated camera) give NaN.
pub fn undistort_points(
    lens: &Lens,
    points: &[[f64; 2]],
    r: Option<&[f64; 9]>,
    p: Option<&[f64; 9]>,
) -> Vec<[f64; 2]> {
    points
        .iter()
        .map(|&px| {
            let Some(n) = lens.undistort(lens.from_pixel(px)) else {
                return [f64::NAN; 2];
            };
            let mut v = [n[0], n[1], 1.0];
            if let Some(r) = r {
                v = mat3_vec(r, v);
            }
            if let Some(p) = p {
                v = mat3_vec(p, v);
            }
            if v[2] <= 0.0 && (r.is_some() || p.is_some()) {
                return [f64::NAN; 2];
            }
            [v[0] / v[2], v[1] / v[2]]
        })
        .collect()
}

/// Row-major 3×3 times a vector.
#[inline]
pub fn mat3_vec(m: &[f64; 9], v: [f64; 3]) -> [f64; 3] {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    ]
}

/// Row-major array → nalgebra matrix.
pub fn to_na(m: &[f64; 9]) -> Matrix3<f64> {
    Matrix3::from_row_slice(m)
}

/// nalgebra matrix → row-major array.
pub fn from_na(m: &Matrix3<f64>) -> [f64; 9] {
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}

// Rotation helpers live in `pose_util`; re-exported here for the lens and calibration code.
pub use super::pose_util::{angle_axis, rodrigues};

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 500.0,
            fy: 480.0,
            cx: 320.0,
            cy: 240.0,
            skew: 1.5,
        }
    }

    #[test]
    fn pinhole_projection_by_hand() {
        let lens = Lens::pinhole(k());
        // X/Z = 0.1, Y/Z = -0.2: u = 500·0.1 + 1.5·(−0.2) + 320 = 369.7, v = 480·(−0.2) + 240.
        let p = lens.project([0.2, -0.4, 2.0]).unwrap();
        assert!((p[0] - 369.7).abs() < 1e-12 && (p[1] - 144.0).abs() < 1e-12);
        assert!(lens.project([0.0, 0.0, -1.0]).is_none());
        let ray = lens.unproject(p).unwrap();
        let z = 2.0 / ray[2];
        assert!((ray[0] * z - 0.2).abs() < 1e-12 && (ray[1] * z + 0.4).abs() < 1e-12);
    }

    #[test]
    fn radial_tangential_matches_opencv() {
        // cv2.projectPoints([[0.3, -0.2, 1.5]], 0, 0, K (fx 500, fy 480, cx 320, cy 240),
        // [-0.3, 0.1, 0.001, -0.002, 0.02]) = (418.13599069, 177.18372151) (skew 0).
        let lens = Lens {
            k: Intrinsics { skew: 0.0, ..k() },
            distortion: Distortion::RadialTangential([-0.3, 0.1, 0.001, -0.002, 0.02]),
        };
        let p = lens.project([0.3, -0.2, 1.5]).unwrap();
        // Hand computation of OpenCV's formula.
        let (x, y) = (0.2f64, -0.2 / 1.5);
        let r2 = x * x + y * y;
        let rad = 1.0 - 0.3 * r2 + 0.1 * r2 * r2 + 0.02 * r2 * r2 * r2;
        let xd = x * rad + 2.0 * 0.001 * x * y - 0.002 * (r2 + 2.0 * x * x);
        let yd = y * rad + 0.001 * (r2 + 2.0 * y * y) - 2.0 * 0.002 * x * y;
        assert!((p[0] - (500.0 * xd + 320.0)).abs() < 1e-12);
        assert!((p[1] - (480.0 * yd + 240.0)).abs() < 1e-12);
        assert!((p[0] - 418.13599069).abs() < 1e-7 && (p[1] - 177.18372151).abs() < 1e-7);
    }

    #[test]
    fn fisheye_matches_opencv() {
        // cv2.fisheye.projectPoints([[[0.3, -0.2, 1.5]]], 0, 0, K (fx 500, fy 480, cx 320,
        // cy 240), [-0.01, 0.002, -0.0003, 0.00001], alpha = 1.5/500) = (417.8880263, 177.2261154).
        let lens = Lens {
            k: k(),
            distortion: Distortion::Fisheye([-0.01, 0.002, -0.0003, 0.00001]),
        };
        let p = lens.project([0.3, -0.2, 1.5]).unwrap();
        assert!(
            (p[0] - 417.8880263).abs() < 1e-6 && (p[1] - 177.2261154).abs() < 1e-6,
            "{p:?}"
        );
    }

    #[test]
    fn fisheye_near_and_beyond_ninety_degrees() {
        let lens = Lens {
            k: k(),
            distortion: Distortion::Fisheye([-0.01, 0.002, -0.0003, 0.00001]),
        };
        for deg in [0.0f64, 1e-6, 10.0, 45.0, 80.0, 89.9, 90.0, 100.0] {
            let t = deg.to_radians();
            let ray = [t.sin() * 0.6, t.sin() * 0.8, t.cos()];
            let p = lens.project(ray).unwrap();
            let back = lens.unproject(p).unwrap();
            for i in 0..3 {
                assert!(
                    (back[i] - ray[i]).abs() < 1e-9,
                    "{deg}: {back:?} vs {ray:?}"
                );
            }
        }
    }

    #[test]
    fn undistort_points_with_projection() {
        let lens = Lens {
            k: k(),
            distortion: Distortion::RadialTangential([-0.2, 0.05, 0.001, 0.0005, 0.0]),
        };
        let pts: Vec<[f64; 2]> = [[0.1, 0.2], [-0.3, 0.25], [0.0, 0.0]]
            .iter()
            .map(|&n| lens.to_pixel(lens.distort(n)))
            .collect();
        let out = undistort_points(&lens, &pts, None, Some(&lens.k_matrix()));
        for (o, n) in out.iter().zip([[0.1, 0.2], [-0.3, 0.25], [0.0, 0.0]]) {
            let want = Lens::pinhole(k()).to_pixel(n);
            assert!((o[0] - want[0]).abs() < 1e-9 && (o[1] - want[1]).abs() < 1e-9);
        }
    }

    proptest! {
        #[test]
        fn rt_round_trip_in_the_field(
            x in -0.9f64..0.9, y in -0.7f64..0.7,
            k1 in -0.4f64..0.4, k2 in -0.1f64..0.1, p1 in -0.01f64..0.01,
            p2 in -0.01f64..0.01, k3 in -0.02f64..0.02,
        ) {
            let c = [k1, k2, p1, p2, k3];
            let d = distort_rt(&c, [x, y]);
            // The valid field: the model must be locally invertible between the origin and
            // the point (radial factor and Jacobian positive).
            let r2 = x * x + y * y;
            let rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let drad = rad + 2.0 * r2 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2));
            prop_assume!(rad > 0.3 && drad > 0.3);
            if let Some(u) = undistort_rt(&c, d) {
                prop_assert!((u[0] - x).abs() < 1e-9 && (u[1] - y).abs() < 1e-9,
                    "{u:?} vs {x} {y}");
            } else {
                prop_assert!(false, "no convergence at {x} {y} with {c:?}");
            }
        }

        #[test]
        fn strong_barrel_at_image_corners(k1 in -0.5f64..-0.2, sx in 0.0f64..1.0,
                                          sy in 0.0f64..1.0) {
            // A 640×480 camera with f = 400 and strong barrel distortion. Inside the valid
            // field (distorted radius below the maximum of r(1 + k1r² + k2r⁴)) every pixel
            // undistorts and distorts back to itself; beyond it there is no undistorted point
            // and undistortion must say so rather than return a wrong one.
            let (k2, f) = (0.08, 400.0);
            let lens = Lens {
                k: Intrinsics { fx: f, fy: f, cx: 319.5, cy: 239.5, skew: 0.0 },
                distortion: Distortion::RadialTangential([k1, k2, 0.0, 0.0, 0.0]),
            };
            let mut rd_max = f64::INFINITY;
            let mut prev = 0.0;
            for i in 1..30000 {
                let r = i as f64 * 1e-4;
                let rd = r * (1.0 + k1 * r * r + k2 * r.powi(4));
                if rd < prev {
                    rd_max = prev;
                    break;
                }
                prev = rd;
            }
            let px = [sx * 639.0, sy * 479.0];
            let d = lens.from_pixel(px);
            let rd = d[0].hypot(d[1]);
            let n = lens.undistort(d);
            if rd < 0.999 * rd_max {
                prop_assert!(n.is_some(), "rd {rd} < max {rd_max}");
                let back = lens.to_pixel(lens.distort(n.unwrap_or([0.0; 2])));
                prop_assert!((back[0] - px[0]).abs() < 1e-9 && (back[1] - px[1]).abs() < 1e-9);
            } else if rd > 1.001 * rd_max {
                prop_assert!(n.is_none());
            }
            // The image corner (0, 0) with the milder k1 = -0.2 is inside the field.
            let mild = Lens {
                distortion: Distortion::RadialTangential([-0.2, k2, 0.0, 0.0, 0.0]),
                ..lens
            };
            prop_assert!(mild.undistort(mild.from_pixel([0.0, 0.0])).is_some());
        }

        #[test]
        fn fisheye_round_trip(theta in 0.0f64..1.56, phi in 0.0f64..std::f64::consts::TAU,
                              k1 in -0.05f64..0.05, k2 in -0.01f64..0.01) {
            let lens = Lens { k: k(), distortion: Distortion::Fisheye([k1, k2, 0.001, -0.0005]) };
            let ray = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
            let p = lens.project(ray).unwrap_or([f64::NAN; 2]);
            let back = lens.unproject(p);
            prop_assert!(back.is_some());
            let b = back.unwrap_or([0.0; 3]);
            for i in 0..3 {
                prop_assert!((b[i] - ray[i]).abs() < 1e-9);
            }
            // Through normalized coordinates too, below 90°.
            let n = [ray[0] / ray[2], ray[1] / ray[2]];
            let d = lens.distort(n);
            let u = lens.undistort(d).unwrap_or([f64::NAN; 2]);
            prop_assert!((u[0] - n[0]).abs() < 1e-9 * (1.0 + n[0].abs())
                && (u[1] - n[1]).abs() < 1e-9 * (1.0 + n[1].abs()));
        }
    }
}
