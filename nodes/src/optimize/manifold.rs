//! Manifolds for parameter blocks of [`super::nlls`], Ceres' `Manifold` conventions: a block
//! lives in an ambient space of `ambient_size()` coordinates and is updated through a tangent
//! increment `δ` of `tangent_size()` coordinates by `x ⊞ δ` ([`Manifold::plus`]); the solver
//! linearizes through [`Manifold::plus_jacobian`], the ambient × tangent Jacobian of `x ⊞ δ`
//! at `δ = 0` (row-major).
//!
//! - [`Euclidean`]: `x + δ`.
//! - [`SubsetManifold`]: some coordinates held constant, `δ` moves the others.
//! - [`AngleAxisManifold`]: SO(3) stored as an angle-axis 3-vector, `x ⊞ δ = log(exp(δ) exp(x))`
//!   (a left increment, as the bundle adjuster's `R ← exp([ω]×) R`).
//! - [`QuaternionManifold`]: unit quaternion `[w, x, y, z]`, `x ⊞ δ = [cos‖δ‖, sin‖δ‖ δ/‖δ‖] ⊗ x`
//!   (Ceres' `QuaternionManifold`).
//! - [`SphereManifold`]: vectors of fixed norm (directions), moved along great circles in a
//!   Householder basis of the tangent space (Ceres' `SphereManifold`).

use std::fmt::Debug;

use nalgebra::{Matrix3, Vector3};

use crate::geometry::pose_util::{angle_axis, rodrigues, skew};

/// A manifold of a parameter block.
pub trait Manifold: Debug + Send + Sync {
    /// Coordinates of the stored block.
    fn ambient_size(&self) -> usize;
    /// Degrees of freedom (size of `δ`).
    fn tangent_size(&self) -> usize;
    /// Writes `x ⊞ δ` to `out` (all of length `ambient_size()` except `delta`).
    fn plus(&self, x: &[f64], delta: &[f64], out: &mut [f64]);
    /// Writes the row-major `ambient_size() × tangent_size()` Jacobian of `x ⊞ δ` at `δ = 0`.
    fn plus_jacobian(&self, x: &[f64], jacobian: &mut [f64]);
}

/// `ℝⁿ` with `x ⊞ δ = x + δ`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Euclidean(pub usize);

impl Manifold for Euclidean {
    fn ambient_size(&self) -> usize {
        self.0
    }
    fn tangent_size(&self) -> usize {
        self.0
    }
    fn plus(&self, x: &[f64], delta: &[f64], out: &mut [f64]) {
        for ((o, a), d) in out.iter_mut().zip(x).zip(delta) {
            *o = a + d;
        }
    }
    fn plus_jacobian(&self, _x: &[f64], jacobian: &mut [f64]) {
        let n = self.0;
        jacobian.iter_mut().for_each(|v| *v = 0.0);
        for i in 0..n {
            jacobian[i * n + i] = 1.0;
        }
    }
}

/// `ℝⁿ` with some coordinates held constant; `δ` moves the free coordinates in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SubsetManifold {
    size: usize,
    /// Free coordinates, ascending.
    free: Vec<usize>,
}

impl SubsetManifold {
    /// A block of `size` coordinates whose `constant` coordinates never move; `None` if a
    /// constant index is out of range.
    pub fn new(size: usize, constant: &[usize]) -> Option<SubsetManifold> {
        if constant.iter().any(|&c| c >= size) {
            return None;
        }
        let free = (0..size).filter(|i| !constant.contains(i)).collect();
        Some(SubsetManifold { size, free })
    }
}

impl Manifold for SubsetManifold {
    fn ambient_size(&self) -> usize {
        self.size
    }
    fn tangent_size(&self) -> usize {
        self.free.len()
    }
    fn plus(&self, x: &[f64], delta: &[f64], out: &mut [f64]) {
        out.copy_from_slice(&x[..self.size]);
        for (&i, d) in self.free.iter().zip(delta) {
            out[i] += d;
        }
    }
    fn plus_jacobian(&self, _x: &[f64], jacobian: &mut [f64]) {
        let t = self.free.len();
        jacobian.iter_mut().for_each(|v| *v = 0.0);
        for (k, &i) in self.free.iter().enumerate() {
            jacobian[i * t + k] = 1.0;
        }
    }
}

/// SO(3) as an angle-axis 3-vector `x` (rotation `exp([x]×)`), `x ⊞ δ = log(exp(δ) exp(x))`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AngleAxisManifold;

/// The inverse left Jacobian of SO(3), `J_l⁻¹(φ) = I − ½[φ]× + (1/θ² − (1 + cos θ)/(2θ sin θ))
/// [φ]×²`: the derivative of `log(exp(δ) exp(φ))` in `δ` at 0.
fn so3_inverse_left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let t2 = phi.norm_squared();
    let theta = t2.sqrt();
    // Series 1/12 + θ²/720 below 1e-4 rad.
    let c = if theta < 1e-4 {
        1.0 / 12.0 + t2 / 720.0
    } else {
        1.0 / t2 - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    let k = skew(phi);
    Matrix3::identity() - k * 0.5 + k * k * c
}

impl Manifold for AngleAxisManifold {
    fn ambient_size(&self) -> usize {
        3
    }
    fn tangent_size(&self) -> usize {
        3
    }
    fn plus(&self, x: &[f64], delta: &[f64], out: &mut [f64]) {
        let r = rodrigues([delta[0], delta[1], delta[2]]) * rodrigues([x[0], x[1], x[2]]);
        out[..3].copy_from_slice(&angle_axis(&r));
    }
    fn plus_jacobian(&self, x: &[f64], jacobian: &mut [f64]) {
        let j = so3_inverse_left_jacobian(&Vector3::new(x[0], x[1], x[2]));
        for r in 0..3 {
            for c in 0..3 {
                jacobian[3 * r + c] = j[(r, c)];
            }
        }
    }
}

/// Unit quaternion `[w, x, y, z]`, `q ⊞ δ = [cos‖δ‖, sin‖δ‖ δ/‖δ‖] ⊗ q` (renormalized).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct QuaternionManifold;

/// Hamilton product `a ⊗ b` of `[w, x, y, z]` quaternions.
pub fn quaternion_product(a: &[f64; 4], b: &[f64; 4]) -> [f64; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

impl Manifold for QuaternionManifold {
    fn ambient_size(&self) -> usize {
        4
    }
    fn tangent_size(&self) -> usize {
        3
    }
    fn plus(&self, x: &[f64], delta: &[f64], out: &mut [f64]) {
        let n = (delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2]).sqrt();
        let q = [x[0], x[1], x[2], x[3]];
        if n == 0.0 {
            out[..4].copy_from_slice(&q);
            return;
        }
        let s = n.sin() / n;
        let e = [n.cos(), s * delta[0], s * delta[1], s * delta[2]];
        let p = quaternion_product(&e, &q);
        let norm = p.iter().map(|v| v * v).sum::<f64>().sqrt();
        for (o, v) in out.iter_mut().zip(p) {
            *o = v / norm;
        }
    }
    fn plus_jacobian(&self, x: &[f64], jacobian: &mut [f64]) {
        let (w, a, b, c) = (x[0], x[1], x[2], x[3]);
        let j = [
            -a, -b, -c, //
            w, c, -b, //
            -c, w, a, //
            b, -a, w,
        ];
        jacobian[..12].copy_from_slice(&j);
    }
}

/// Vectors of `ℝⁿ` (n ≥ 2) with a fixed norm, e.g. a translation direction; `n − 1` degrees
/// of freedom. `x ⊞ δ = cos‖v‖ x + sin‖v‖ ‖x‖ v/‖v‖` with `v = B(x) δ`, `B(x)` an orthonormal
/// basis of the tangent space (the columns of the Householder reflection of `x/‖x‖` but the
/// last).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SphereManifold(pub usize);

impl SphereManifold {
    /// Row-major `n × (n − 1)` orthonormal basis orthogonal to `x`.
    fn tangent_basis(&self, x: &[f64]) -> Vec<f64> {
        let n = self.0;
        let norm = x[..n].iter().map(|v| v * v).sum::<f64>().sqrt();
        // v = x̂ + sign(x̂ₙ) eₙ, H = I − 2 v vᵀ / vᵀv maps x̂ to ∓eₙ.
        let mut v: Vec<f64> = x[..n].iter().map(|a| a / norm).collect();
        let sign = if v[n - 1] >= 0.0 { 1.0 } else { -1.0 };
        v[n - 1] += sign;
        let vv: f64 = v.iter().map(|a| a * a).sum();
        let mut basis = vec![0.0; n * (n - 1)];
        for r in 0..n {
            for c in 0..n - 1 {
                let id = if r == c { 1.0 } else { 0.0 };
                basis[r * (n - 1) + c] = id - 2.0 * v[r] * v[c] / vv;
            }
        }
        basis
    }
}

impl Manifold for SphereManifold {
    fn ambient_size(&self) -> usize {
        self.0
    }
    fn tangent_size(&self) -> usize {
        self.0.saturating_sub(1)
    }
    fn plus(&self, x: &[f64], delta: &[f64], out: &mut [f64]) {
        let n = self.0;
        let basis = self.tangent_basis(x);
        let v: Vec<f64> = (0..n)
            .map(|r| (0..n - 1).map(|c| basis[r * (n - 1) + c] * delta[c]).sum())
            .collect();
        let v_norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        if v_norm == 0.0 {
            out[..n].copy_from_slice(&x[..n]);
            return;
        }
        let x_norm = x[..n].iter().map(|a| a * a).sum::<f64>().sqrt();
        let (c, s) = (v_norm.cos(), v_norm.sin() * x_norm / v_norm);
        for ((o, a), b) in out[..n].iter_mut().zip(x).zip(&v) {
            *o = c * a + s * b;
        }
        // Restore the norm to rounding.
        let out_norm = out[..n].iter().map(|a| a * a).sum::<f64>().sqrt();
        out[..n].iter_mut().for_each(|a| *a *= x_norm / out_norm);
    }
    fn plus_jacobian(&self, x: &[f64], jacobian: &mut [f64]) {
        let n = self.0;
        let x_norm = x[..n].iter().map(|a| a * a).sum::<f64>().sqrt();
        for (j, b) in jacobian.iter_mut().zip(self.tangent_basis(x)) {
            *j = x_norm * b;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Checks `plus_jacobian` against central differences of `plus` at `δ = 0`.
    fn check_jacobian(m: &dyn Manifold, x: &[f64]) {
        let (a, t) = (m.ambient_size(), m.tangent_size());
        let mut analytic = vec![0.0; a * t];
        m.plus_jacobian(x, &mut analytic);
        let h = 1e-6;
        for c in 0..t {
            let mut d = vec![0.0; t];
            d[c] = h;
            let mut plus = vec![0.0; a];
            m.plus(x, &d, &mut plus);
            d[c] = -h;
            let mut minus = vec![0.0; a];
            m.plus(x, &d, &mut minus);
            for r in 0..a {
                let fd = (plus[r] - minus[r]) / (2.0 * h);
                let an = analytic[r * t + c];
                assert!(
                    (fd - an).abs() < 1e-7 * (1.0 + an.abs()),
                    "{m:?} at {x:?}: ({r}, {c}) fd {fd} analytic {an}"
                );
            }
        }
        // Zero increment is the identity.
        let mut same = vec![0.0; a];
        m.plus(x, &vec![0.0; t], &mut same);
        for (s, v) in same.iter().zip(x) {
            assert!((s - v).abs() < 1e-14, "{m:?}: x ⊞ 0 = {same:?} ≠ {x:?}");
        }
    }

    #[test]
    fn euclidean_and_subset_jacobians_and_fixed_coordinates() {
        check_jacobian(&Euclidean(3), &[1.0, -2.0, 0.5]);
        let subset = SubsetManifold::new(4, &[1, 3]).unwrap();
        assert_eq!(subset.tangent_size(), 2);
        check_jacobian(&subset, &[1.0, -2.0, 0.5, 7.0]);
        let x = [1.0, -2.0, 0.5, 7.0];
        let mut out = [0.0; 4];
        subset.plus(&x, &[0.3, -0.4], &mut out);
        assert_eq!([out[1], out[3]], [-2.0, 7.0]);
        assert!((out[0] - 1.3).abs() < 1e-15 && (out[2] - 0.1).abs() < 1e-15);
        assert!(SubsetManifold::new(3, &[3]).is_none());
    }

    #[test]
    fn angle_axis_jacobian_and_composition() {
        for x in [
            [0.0, 0.0, 0.0],
            [1e-6, -2e-6, 3e-7],
            [0.3, -0.2, 0.1],
            [1.2, 0.7, -1.9],
        ] {
            check_jacobian(&AngleAxisManifold, &x);
            let delta = [0.05, -0.1, 0.2];
            let mut out = [0.0; 3];
            AngleAxisManifold.plus(&x, &delta, &mut out);
            let expected = rodrigues(delta) * rodrigues(x);
            assert!((rodrigues(out) - expected).abs().max() < 1e-12);
            let angle = out.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!(angle <= std::f64::consts::PI + 1e-12);
        }
    }

    #[test]
    fn quaternion_jacobian_and_unit_norm() {
        let raw = [0.8, -0.3, 0.4, 0.2];
        let n = raw.iter().map(|v| v * v).sum::<f64>().sqrt();
        let q: Vec<f64> = raw.iter().map(|v| v / n).collect();
        check_jacobian(&QuaternionManifold, &q);
        check_jacobian(&QuaternionManifold, &[1.0, 0.0, 0.0, 0.0]);
        let mut out = [0.0; 4];
        QuaternionManifold.plus(&q, &[0.7, -1.1, 0.4], &mut out);
        let norm = out.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-15);
        assert!(
            out.iter().zip(&q).any(|(a, b)| (a - b).abs() > 0.1),
            "moved"
        );
    }

    #[test]
    fn sphere_jacobian_and_norm() {
        for x in [
            vec![0.0, 0.0, 1.0],
            vec![0.0, 0.0, -2.0],
            vec![0.6, -0.48, 0.64],
            vec![3.0, 4.0],
            vec![0.1, 0.2, -0.3, 0.9],
        ] {
            let m = SphereManifold(x.len());
            check_jacobian(&m, &x);
            let norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
            let mut basis = vec![0.0; x.len() * (x.len() - 1)];
            m.plus_jacobian(&x, &mut basis);
            // Tangent directions are orthogonal to x.
            for c in 0..x.len() - 1 {
                let dot: f64 = (0..x.len())
                    .map(|r| basis[r * (x.len() - 1) + c] * x[r])
                    .sum();
                assert!(dot.abs() < 1e-12);
            }
            let delta: Vec<f64> = (0..x.len() - 1).map(|k| 0.4 - 0.3 * k as f64).collect();
            let mut out = vec![0.0; x.len()];
            m.plus(&x, &delta, &mut out);
            let out_norm = out.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!((out_norm - norm).abs() < 1e-14 * norm);
            assert!(out.iter().zip(&x).any(|(a, b)| (a - b).abs() > 0.05));
        }
    }
}
