//! Shape estimators for the robust loops: 2-D lines, circles and 3-D planes.
//!
//! - [`LineEstimator`]: `n·x + c = 0` with `‖n‖ = 1`; two points (minimal) or total least
//!   squares (the centroid and the smallest-eigenvalue eigenvector of the 2×2 scatter matrix);
//!   residual: squared perpendicular distance.
//! - [`CircleEstimator`]: centre and radius; the circumcircle of three points (minimal), or the
//!   algebraic Kåsa fit `x² + y² + D x + E y + F = 0` (least squares, on centred and scaled
//!   coordinates) refined by Levenberg–Marquardt on the geometric distances `‖x − c‖ − r`;
//!   residual: squared geometric distance. Kåsa alone is biased towards small circles on short
//!   arcs; the geometric refinement removes that bias.
//! - [`PlaneEstimator`]: `n·X + d = 0`; three points (cross product) or total least squares
//!   (3×3 scatter matrix); residual: squared perpendicular distance.
//! - [`SphereEstimator`]: centre and radius; the circumsphere of four points (minimal), or the
//!   algebraic fit `‖X‖² + D·X + G = 0` (on centred, scaled coordinates) refined by
//!   Levenberg–Marquardt on the geometric distances `‖X − c‖ − r` — the 3-D analogue of the
//!   circle; residual: squared geometric distance.
//!
//! Reference: Kåsa, "A circle fitting procedure and its error analysis", IEEE TIM 1976; Chernov,
//! "Circular and linear regression" (2010), ch. 5; Hartley & Zisserman appendix A5 (TLS).

use nalgebra::{Matrix2, Matrix3, SymmetricEigen, Vector3};

use super::lm::{self, LmOptions, Problem};
use super::robust::Estimator;

/// A 2-D line `normal · x + offset = 0`, `‖normal‖ = 1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Line2 {
    /// Unit normal.
    pub normal: [f64; 2],
    /// Offset.
    pub offset: f64,
}

/// 2-D line estimator (total least squares).
#[derive(Debug, Clone, Copy, Default)]
pub struct LineEstimator;

impl Estimator for LineEstimator {
    type Datum = [f64; 2];
    type Model = Line2;
    const MIN_SAMPLES: usize = 2;

    fn fit(&self, sample: &[[f64; 2]]) -> Vec<Line2> {
        if sample.len() < 2 {
            return Vec::new();
        }
        let n = sample.len() as f64;
        let cx = sample.iter().map(|p| p[0]).sum::<f64>() / n;
        let cy = sample.iter().map(|p| p[1]).sum::<f64>() / n;
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for p in sample {
            let (dx, dy) = (p[0] - cx, p[1] - cy);
            sxx += dx * dx;
            sxy += dx * dy;
            syy += dy * dy;
        }
        if sxx + syy == 0.0 {
            return Vec::new();
        }
        let eigen = SymmetricEigen::new(Matrix2::new(sxx, sxy, sxy, syy));
        let k = if eigen.eigenvalues[0] <= eigen.eigenvalues[1] {
            0
        } else {
            1
        };
        let v = eigen.eigenvectors.column(k);
        let norm = v.norm();
        let normal = [v[0] / norm, v[1] / norm];
        let offset = -(normal[0] * cx + normal[1] * cy);
        vec![Line2 { normal, offset }]
    }

    fn residuals(&self, m: &Line2, data: &[[f64; 2]], residuals: &mut [f64]) {
        for (r, p) in residuals.iter_mut().zip(data) {
            let d = m.normal[0] * p[0] + m.normal[1] * p[1] + m.offset;
            *r = d * d;
        }
    }

    fn is_degenerate(&self, sample: &[[f64; 2]]) -> bool {
        sample.len() == 2 && sample[0] == sample[1]
    }

    fn datum_is_finite(&self, p: &[f64; 2]) -> bool {
        p.iter().all(|v| v.is_finite())
    }
}

/// A circle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Circle {
    /// Centre.
    pub center: [f64; 2],
    /// Radius (> 0).
    pub radius: f64,
}

/// Circle estimator (circumcircle / Kåsa + geometric LM).
#[derive(Debug, Clone, Copy, Default)]
pub struct CircleEstimator;

fn circumcircle(a: &[f64; 2], b: &[f64; 2], c: &[f64; 2]) -> Option<Circle> {
    // Relative to a, for precision.
    let (bx, by) = (b[0] - a[0], b[1] - a[1]);
    let (cx, cy) = (c[0] - a[0], c[1] - a[1]);
    let d = 2.0 * (bx * cy - by * cx);
    let scale = (bx * bx + by * by) * (cx * cx + cy * cy);
    if d == 0.0 || d * d <= 1e-24 * scale {
        return None;
    }
    let b2 = bx * bx + by * by;
    let c2 = cx * cx + cy * cy;
    let ux = (cy * b2 - by * c2) / d;
    let uy = (bx * c2 - cx * b2) / d;
    let radius = ux.hypot(uy);
    (radius.is_finite() && radius > 0.0).then_some(Circle {
        center: [a[0] + ux, a[1] + uy],
        radius,
    })
}

/// The algebraic Kåsa fit on centred, scaled coordinates.
fn kasa(data: &[[f64; 2]]) -> Option<Circle> {
    let n = data.len() as f64;
    let mx = data.iter().map(|p| p[0]).sum::<f64>() / n;
    let my = data.iter().map(|p| p[1]).sum::<f64>() / n;
    let s = data
        .iter()
        .map(|p| (p[0] - mx).hypot(p[1] - my))
        .sum::<f64>()
        / n;
    if s.is_nan() || s <= 0.0 {
        return None;
    }
    // Solve [x y 1]·[D E F]ᵀ = −(x² + y²) in the least-squares sense.
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for p in data {
        let (x, y) = ((p[0] - mx) / s, (p[1] - my) / s);
        let row = Vector3::new(x, y, 1.0);
        ata += row * row.transpose();
        atb -= row * (x * x + y * y);
    }
    let sol = ata.cholesky()?.solve(&atb);
    let (cx, cy) = (-sol[0] / 2.0, -sol[1] / 2.0);
    let r2 = cx * cx + cy * cy - sol[2];
    (r2 > 0.0).then(|| Circle {
        center: [mx + s * cx, my + s * cy],
        radius: s * r2.sqrt(),
    })
}

struct CircleProblem<'a>(&'a [[f64; 2]]);

impl Problem for CircleProblem<'_> {
    fn num_params(&self) -> usize {
        3
    }
    fn num_residuals(&self) -> usize {
        self.0.len()
    }
    fn residuals(&self, x: &[f64], r: &mut [f64]) {
        for (ri, p) in r.iter_mut().zip(self.0) {
            *ri = (p[0] - x[0]).hypot(p[1] - x[1]) - x[2];
        }
    }
    fn jacobian(&self, x: &[f64], j: &mut nalgebra::DMatrix<f64>) {
        for (i, p) in self.0.iter().enumerate() {
            let (dx, dy) = (p[0] - x[0], p[1] - x[1]);
            let d = dx.hypot(dy).max(1e-300);
            j[(i, 0)] = -dx / d;
            j[(i, 1)] = -dy / d;
            j[(i, 2)] = -1.0;
        }
    }
}

/// Least-squares circle: Kåsa, then geometric refinement.
pub fn fit_circle(data: &[[f64; 2]]) -> Option<Circle> {
    if data.len() < 3 {
        return None;
    }
    let init = kasa(data)?;
    let report = lm::levenberg_marquardt(
        &CircleProblem(data),
        &[init.center[0], init.center[1], init.radius],
        &LmOptions::default(),
    );
    let x = report.x;
    (x.iter().all(|v| v.is_finite()) && x[2] > 0.0)
        .then(|| Circle {
            center: [x[0], x[1]],
            radius: x[2],
        })
        .or(Some(init))
}

impl Estimator for CircleEstimator {
    type Datum = [f64; 2];
    type Model = Circle;
    const MIN_SAMPLES: usize = 3;

    fn fit(&self, sample: &[[f64; 2]]) -> Vec<Circle> {
        if sample.len() == 3 {
            circumcircle(&sample[0], &sample[1], &sample[2])
                .into_iter()
                .collect()
        } else {
            fit_circle(sample).into_iter().collect()
        }
    }

    fn residuals(&self, m: &Circle, data: &[[f64; 2]], residuals: &mut [f64]) {
        for (r, p) in residuals.iter_mut().zip(data) {
            let d = (p[0] - m.center[0]).hypot(p[1] - m.center[1]) - m.radius;
            *r = d * d;
        }
    }

    fn datum_is_finite(&self, p: &[f64; 2]) -> bool {
        p.iter().all(|v| v.is_finite())
    }
}

/// A plane `normal · X + offset = 0`, `‖normal‖ = 1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Unit normal.
    pub normal: [f64; 3],
    /// Offset.
    pub offset: f64,
}

/// 3-D plane estimator (total least squares).
#[derive(Debug, Clone, Copy, Default)]
pub struct PlaneEstimator;

impl Estimator for PlaneEstimator {
    type Datum = [f64; 3];
    type Model = Plane;
    const MIN_SAMPLES: usize = 3;

    fn fit(&self, sample: &[[f64; 3]]) -> Vec<Plane> {
        if sample.len() < 3 {
            return Vec::new();
        }
        let n = sample.len() as f64;
        let mut c = Vector3::zeros();
        for p in sample {
            c += Vector3::from(*p);
        }
        c /= n;
        let mut scatter = Matrix3::zeros();
        for p in sample {
            let d = Vector3::from(*p) - c;
            scatter += d * d.transpose();
        }
        let eigen = SymmetricEigen::new(scatter);
        let mut order = [0, 1, 2];
        order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
        // Degenerate (collinear or coincident): the two smallest eigenvalues both ~0.
        let largest = eigen.eigenvalues[order[2]];
        if largest.is_nan() || largest <= 0.0 || eigen.eigenvalues[order[1]] <= 1e-20 * largest {
            return Vec::new();
        }
        let v = eigen.eigenvectors.column(order[0]).normalize();
        vec![Plane {
            normal: [v[0], v[1], v[2]],
            offset: -v.dot(&c),
        }]
    }

    fn residuals(&self, m: &Plane, data: &[[f64; 3]], residuals: &mut [f64]) {
        for (r, p) in residuals.iter_mut().zip(data) {
            let d = m.normal[0] * p[0] + m.normal[1] * p[1] + m.normal[2] * p[2] + m.offset;
            *r = d * d;
        }
    }

    fn datum_is_finite(&self, p: &[f64; 3]) -> bool {
        p.iter().all(|v| v.is_finite())
    }
}

/// A sphere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sphere {
    /// Centre.
    pub center: [f64; 3],
    /// Radius (> 0).
    pub radius: f64,
}

/// Sphere estimator (circumsphere / algebraic + geometric LM).
#[derive(Debug, Clone, Copy, Default)]
pub struct SphereEstimator;

/// The sphere through four points, or `None` when they are (nearly) coplanar.
fn circumsphere(p: &[[f64; 3]]) -> Option<Sphere> {
    // Relative to the first point: 2 (pᵢ − p₀)·u = ‖pᵢ − p₀‖², u = centre − p₀.
    let a = Vector3::from(p[0]);
    let rows: Vec<Vector3<f64>> = p[1..4].iter().map(|q| Vector3::from(*q) - a).collect();
    let m = Matrix3::from_rows(&[
        rows[0].transpose() * 2.0,
        rows[1].transpose() * 2.0,
        rows[2].transpose() * 2.0,
    ]);
    let scale = 8.0 * rows[0].norm() * rows[1].norm() * rows[2].norm();
    let det = m.determinant();
    if det.is_nan() || det.abs() <= 1e-10 * scale {
        return None;
    }
    let b = Vector3::new(
        rows[0].norm_squared(),
        rows[1].norm_squared(),
        rows[2].norm_squared(),
    );
    let u = m.lu().solve(&b)?;
    let radius = u.norm();
    (radius.is_finite() && radius > 0.0).then(|| Sphere {
        center: (a + u).into(),
        radius,
    })
}

/// The algebraic sphere fit on centred, scaled coordinates.
fn algebraic_sphere(data: &[[f64; 3]]) -> Option<Sphere> {
    let n = data.len() as f64;
    let mut mean = Vector3::zeros();
    for p in data {
        mean += Vector3::from(*p);
    }
    mean /= n;
    let s = data
        .iter()
        .map(|p| (Vector3::from(*p) - mean).norm())
        .sum::<f64>()
        / n;
    if s.is_nan() || s <= 0.0 {
        return None;
    }
    // [x y z 1]·[D E F G]ᵀ = −(x² + y² + z²).
    let mut ata = nalgebra::Matrix4::zeros();
    let mut atb = nalgebra::Vector4::zeros();
    for p in data {
        let q = (Vector3::from(*p) - mean) / s;
        let row = nalgebra::Vector4::new(q[0], q[1], q[2], 1.0);
        ata += row * row.transpose();
        atb -= row * q.norm_squared();
    }
    let sol = ata.cholesky()?.solve(&atb);
    let c = Vector3::new(-sol[0] / 2.0, -sol[1] / 2.0, -sol[2] / 2.0);
    let r2 = c.norm_squared() - sol[3];
    (r2 > 0.0).then(|| Sphere {
        center: (mean + c * s).into(),
        radius: s * r2.sqrt(),
    })
}

struct SphereProblem<'a>(&'a [[f64; 3]]);

impl Problem for SphereProblem<'_> {
    fn num_params(&self) -> usize {
        4
    }
    fn num_residuals(&self) -> usize {
        self.0.len()
    }
    fn residuals(&self, x: &[f64], r: &mut [f64]) {
        for (ri, p) in r.iter_mut().zip(self.0) {
            let d = Vector3::new(p[0] - x[0], p[1] - x[1], p[2] - x[2]);
            *ri = d.norm() - x[3];
        }
    }
    fn jacobian(&self, x: &[f64], j: &mut nalgebra::DMatrix<f64>) {
        for (i, p) in self.0.iter().enumerate() {
            let d = Vector3::new(p[0] - x[0], p[1] - x[1], p[2] - x[2]);
            let norm = d.norm().max(1e-300);
            for a in 0..3 {
                j[(i, a)] = -d[a] / norm;
            }
            j[(i, 3)] = -1.0;
        }
    }
}

/// Least-squares sphere: the algebraic fit, then geometric refinement. The refinement runs on
/// coordinates relative to the algebraic centre, so far-off spheres keep their precision.
pub fn fit_sphere(data: &[[f64; 3]]) -> Option<Sphere> {
    if data.len() < 4 {
        return None;
    }
    let init = algebraic_sphere(data)?;
    let c = init.center;
    let local: Vec<[f64; 3]> = data
        .iter()
        .map(|p| [p[0] - c[0], p[1] - c[1], p[2] - c[2]])
        .collect();
    let report = lm::levenberg_marquardt(
        &SphereProblem(&local),
        &[0.0, 0.0, 0.0, init.radius],
        &LmOptions::default(),
    );
    let x = report.x;
    (x.iter().all(|v| v.is_finite()) && x[3] > 0.0)
        .then(|| Sphere {
            center: [c[0] + x[0], c[1] + x[1], c[2] + x[2]],
            radius: x[3],
        })
        .or(Some(init))
}

impl Estimator for SphereEstimator {
    type Datum = [f64; 3];
    type Model = Sphere;
    const MIN_SAMPLES: usize = 4;

    fn fit(&self, sample: &[[f64; 3]]) -> Vec<Sphere> {
        if sample.len() == 4 {
            circumsphere(sample).into_iter().collect()
        } else {
            fit_sphere(sample).into_iter().collect()
        }
    }

    fn residuals(&self, m: &Sphere, data: &[[f64; 3]], residuals: &mut [f64]) {
        for (r, p) in residuals.iter_mut().zip(data) {
            let d = Vector3::new(p[0] - m.center[0], p[1] - m.center[1], p[2] - m.center[2]).norm()
                - m.radius;
            *r = d * d;
        }
    }

    fn datum_is_finite(&self, p: &[f64; 3]) -> bool {
        p.iter().all(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::geometry::ransac::{RobustError, RobustOptions, estimate};

    #[test]
    fn line_exact_scaled_and_with_outliers() {
        for scale in [1e-3, 1.0, 1e6] {
            // 3x − 4y + 5·scale = 0.
            let pts: Vec<[f64; 2]> = (0..20)
                .map(|i| {
                    let x = (i as f64 - 7.0) * scale;
                    [x, (3.0 * x + 5.0 * scale) / 4.0]
                })
                .collect();
            let m = LineEstimator.fit(&pts)[0];
            let s = m.normal[0].signum() * 0.2;
            assert!((m.normal[0] - 3.0 * s).abs() < 1e-12);
            assert!((m.normal[1] + 4.0 * s).abs() < 1e-12);
            assert!((m.offset / scale - 5.0 * s).abs() < 1e-9, "{scale}");
        }
        let mut rng = SplitMix64::new(2);
        let pts: Vec<[f64; 2]> = (0..400)
            .map(|i| {
                if i % 10 == 0 {
                    let x = rng.uniform() * 100.0;
                    [x, 0.5 * x + 2.0 + 0.01 * rng.normal()]
                } else {
                    [rng.uniform() * 100.0, rng.uniform() * 100.0]
                }
            })
            .collect();
        let r = estimate(
            &LineEstimator,
            &pts,
            &RobustOptions {
                threshold: 0.05,
                ..RobustOptions::default()
            },
        )
        .unwrap();
        let m = r.model;
        assert!((m.normal[1] / m.normal[0] + 2.0).abs() < 1e-2, "{m:?}");
        assert!(r.num_inliers >= 40);
        assert!(matches!(
            estimate(
                &LineEstimator,
                &[[1.0, 1.0], [1.0, 1.0]],
                &RobustOptions::default()
            ),
            Err(RobustError::Degenerate)
        ));
    }

    #[test]
    fn circle_exact_arc_and_scale() {
        for scale in [1e-3, 1.0, 1e6] {
            let (cx, cy, r) = (3.0 * scale, -2.0 * scale, 5.0 * scale);
            // A 60° arc: Kåsa alone is biased with noise, exact here.
            let pts: Vec<[f64; 2]> = (0..12)
                .map(|i| {
                    let a = 0.3 + i as f64 * 0.09;
                    [cx + r * a.cos(), cy + r * a.sin()]
                })
                .collect();
            let c3 = CircleEstimator.fit(&pts[..3])[0];
            let c = CircleEstimator.fit(&pts)[0];
            for m in [c3, c] {
                assert!((m.center[0] - cx).abs() < 1e-8 * scale, "{scale} {m:?}");
                assert!((m.center[1] - cy).abs() < 1e-8 * scale);
                assert!((m.radius - r).abs() < 1e-8 * scale);
            }
        }
        assert!(
            CircleEstimator
                .fit(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
                .is_empty()
        );
    }

    #[test]
    fn circle_geometric_fit_beats_kasa_on_a_noisy_arc() {
        let mut rng = SplitMix64::new(8);
        let pts: Vec<[f64; 2]> = (0..200)
            .map(|i| {
                let a = i as f64 * 0.005;
                let rr = 50.0 + 0.5 * rng.normal();
                [rr * a.cos(), rr * a.sin()]
            })
            .collect();
        let k = kasa(&pts).unwrap();
        let g = fit_circle(&pts).unwrap();
        let mut rk = vec![0.0; pts.len()];
        let mut rg = vec![0.0; pts.len()];
        CircleEstimator.residuals(&k, &pts, &mut rk);
        CircleEstimator.residuals(&g, &pts, &mut rg);
        assert!(rg.iter().sum::<f64>() <= rk.iter().sum::<f64>());
    }

    #[test]
    fn plane_exact_and_degenerate() {
        for scale in [1e-3, 1.0, 1e6] {
            // 2x + y − 2z + 3·scale = 0, normal (2, 1, −2)/3.
            let pts: Vec<[f64; 3]> = (0..15)
                .map(|i| {
                    let (x, y) = ((i % 4) as f64 * scale, (i / 4) as f64 * scale);
                    [x, y, (2.0 * x + y + 3.0 * scale) / 2.0]
                })
                .collect();
            let triple = [pts[0], pts[1], pts[5]];
            for m in [PlaneEstimator.fit(&triple), PlaneEstimator.fit(&pts)] {
                let m = m[0];
                let s = m.normal[0].signum() / 3.0;
                assert!((m.normal[0] - 2.0 * s).abs() < 1e-12);
                assert!((m.normal[1] - s).abs() < 1e-12);
                assert!((m.normal[2] + 2.0 * s).abs() < 1e-12);
                assert!((m.offset / scale - 3.0 * s).abs() < 1e-9);
            }
        }
        let line = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]];
        assert!(PlaneEstimator.fit(&line).is_empty());
        assert_eq!(
            estimate(
                &PlaneEstimator,
                &[[0.0, 0.0, f64::NAN]; 4],
                &RobustOptions::default()
            ),
            Err(RobustError::NonFinite { index: 0 })
        );
    }

    #[test]
    fn sphere_exact_scaled_and_coplanar() {
        for (scale, offset) in [(1e-3, 0.0), (1.0, 0.0), (1e3, 0.0), (1.0, 1e6)] {
            let (c, r) = (
                [1.0 * scale + offset, -2.0 * scale, 0.5 * scale],
                3.0 * scale,
            );
            // A cap of directions (within 60° of +z): short arcs bias algebraic fits.
            let pts: Vec<[f64; 3]> = (0..30)
                .map(|i| {
                    let (t, p) = (0.2 + 0.03 * i as f64, 0.7 * i as f64);
                    [
                        c[0] + r * t.sin() * p.cos(),
                        c[1] + r * t.sin() * p.sin(),
                        c[2] + r * t.cos(),
                    ]
                })
                .collect();
            let m4 = SphereEstimator.fit(&pts[..4]);
            let all = SphereEstimator.fit(&pts);
            for m in [m4, all] {
                let m = m[0];
                for (got, want) in m.center.iter().zip(&c) {
                    assert!((got - want).abs() < 1e-7 * scale.max(1.0), "{scale} {m:?}");
                }
                assert!((m.radius - r).abs() < 1e-7 * scale.max(1.0));
            }
        }
        let coplanar = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
        ];
        assert!(SphereEstimator.fit(&coplanar).is_empty());
        assert!(SphereEstimator.fit(&[[2.0; 3]; 4]).is_empty());
    }
}
