//! Transform estimators for the robust loops: 2-D affine and similarity, 3-D rigid and
//! similarity alignment. Every residual is the squared forward transfer distance
//! `‖y − T(x)‖²` in the data's units.
//!
//! - [`Affine2Estimator`]: `y = A x + t` (6 parameters); 3 correspondences (exact) or linear
//!   least squares, on centred and scaled coordinates (Hartley-style normalization, so the
//!   fit is scale-invariant).
//! - [`Similarity2Estimator`]: `y = s R x + t`; the closed-form least-squares solution (Umeyama
//!   1991 in 2-D: with centred points as complex numbers, `s·e^{iθ} = Σ conj(aᵢ) bᵢ / Σ |aᵢ|²`).
//! - [`Rigid3Estimator`] / [`Similarity3Estimator`]: `y = R x + t` / `y = s R x + t`; Kabsch /
//!   Umeyama: SVD of the 3×3 cross-covariance `U Σ Vᵀ`, `R = U·diag(1, 1, det(UVᵀ))·Vᵀ` (the
//!   sign fix that rules out reflections), `s = tr(Σ·diag(1, 1, ±1)) / σₓ²`.
//!
//! Reference: S. Umeyama, "Least-squares estimation of transformation parameters between two
//! point patterns", PAMI 1991; W. Kabsch, Acta Cryst. 1976; OpenCV `estimateAffine2D`,
//! `estimateAffinePartial2D`.

use nalgebra::{Matrix3, Vector3};

use super::robust::Estimator;

/// One 2-D correspondence `[x, y]` (source, target).
pub type Pair2 = [[f64; 2]; 2];
/// One 3-D correspondence `[x, y]` (source, target).
pub type Pair3 = [[f64; 3]; 2];

/// A 2-D affine map `y = [[a, b, c], [d, e, f]] · [x, 1]ᵀ`, row-major.
pub type Affine2 = [f64; 6];

#[inline]
fn apply_affine(m: &Affine2, p: &[f64; 2]) -> [f64; 2] {
    [
        m[0] * p[0] + m[1] * p[1] + m[2],
        m[3] * p[0] + m[4] * p[1] + m[5],
    ]
}

fn pair2_residuals(m: &Affine2, data: &[Pair2], residuals: &mut [f64]) {
    for (r, c) in residuals.iter_mut().zip(data) {
        let q = apply_affine(m, &c[0]);
        *r = (q[0] - c[1][0]).powi(2) + (q[1] - c[1][1]).powi(2);
    }
}

/// Centroid and mean distance of one side of the pairs.
fn centre_scale(data: &[Pair2], side: usize) -> Option<([f64; 2], f64)> {
    let n = data.len() as f64;
    let cx = data.iter().map(|c| c[side][0]).sum::<f64>() / n;
    let cy = data.iter().map(|c| c[side][1]).sum::<f64>() / n;
    let s = data
        .iter()
        .map(|c| (c[side][0] - cx).hypot(c[side][1] - cy))
        .sum::<f64>()
        / n;
    (s.is_finite() && s > 0.0).then_some(([cx, cy], s))
}

/// Least-squares affine fit (≥ 3 pairs), or `None` if the sources are collinear.
pub fn fit_affine2(data: &[Pair2]) -> Option<Affine2> {
    if data.len() < 3 {
        return None;
    }
    let (c1, s1) = centre_scale(data, 0)?;
    let (c2, s2) = centre_scale(data, 1).unwrap_or(([0.0, 0.0], 1.0));
    // Centred data: the translation decouples; solve the 2×2 normal equations.
    let mut sxx = nalgebra::Matrix2::zeros();
    let mut sxy = nalgebra::Matrix2::zeros();
    for c in data {
        let x = nalgebra::Vector2::new((c[0][0] - c1[0]) / s1, (c[0][1] - c1[1]) / s1);
        let y = nalgebra::Vector2::new((c[1][0] - c2[0]) / s2, (c[1][1] - c2[1]) / s2);
        sxx += x * x.transpose();
        sxy += y * x.transpose();
    }
    if sxx.determinant().abs() <= 1e-12 * sxx.norm_squared() {
        return None;
    }
    let a = sxy * sxx.try_inverse()?; // normalized linear part
    let lin = a * (s2 / s1);
    let t = nalgebra::Vector2::new(c2[0], c2[1]) - lin * nalgebra::Vector2::new(c1[0], c1[1]);
    let m = [
        lin[(0, 0)],
        lin[(0, 1)],
        t[0],
        lin[(1, 0)],
        lin[(1, 1)],
        t[1],
    ];
    m.iter().all(|v| v.is_finite()).then_some(m)
}

/// 2-D affine estimator.
#[derive(Debug, Clone, Copy, Default)]
pub struct Affine2Estimator;

impl Estimator for Affine2Estimator {
    type Datum = Pair2;
    type Model = Affine2;
    const MIN_SAMPLES: usize = 3;

    fn fit(&self, sample: &[Pair2]) -> Vec<Affine2> {
        fit_affine2(sample).into_iter().collect()
    }

    fn residuals(&self, m: &Affine2, data: &[Pair2], residuals: &mut [f64]) {
        pair2_residuals(m, data, residuals);
    }

    fn datum_is_finite(&self, c: &Pair2) -> bool {
        c.iter().flatten().all(|v| v.is_finite())
    }
}

/// Least-squares 2-D similarity (≥ 2 pairs) as an affine matrix `[[s cos, −s sin, tx],
/// [s sin, s cos, ty]]`, or `None` if the sources coincide.
pub fn fit_similarity2(data: &[Pair2]) -> Option<Affine2> {
    if data.len() < 2 {
        return None;
    }
    let n = data.len() as f64;
    let mean = |side: usize, k: usize| data.iter().map(|c| c[side][k]).sum::<f64>() / n;
    let (ax, ay, bx, by) = (mean(0, 0), mean(0, 1), mean(1, 0), mean(1, 1));
    let (mut re, mut im, mut norm) = (0.0, 0.0, 0.0);
    for c in data {
        let (x, y) = (c[0][0] - ax, c[0][1] - ay);
        let (u, v) = (c[1][0] - bx, c[1][1] - by);
        // conj(x + iy)·(u + iv)
        re += x * u + y * v;
        im += x * v - y * u;
        norm += x * x + y * y;
    }
    if norm.is_nan() || norm <= 0.0 {
        return None;
    }
    let (p, q) = (re / norm, im / norm);
    let m = [p, -q, bx - (p * ax - q * ay), q, p, by - (q * ax + p * ay)];
    m.iter().all(|v| v.is_finite()).then_some(m)
}

/// 2-D similarity estimator (rotation, uniform scale, translation).
#[derive(Debug, Clone, Copy, Default)]
pub struct Similarity2Estimator;

impl Estimator for Similarity2Estimator {
    type Datum = Pair2;
    type Model = Affine2;
    const MIN_SAMPLES: usize = 2;

    fn fit(&self, sample: &[Pair2]) -> Vec<Affine2> {
        fit_similarity2(sample).into_iter().collect()
    }

    fn residuals(&self, m: &Affine2, data: &[Pair2], residuals: &mut [f64]) {
        pair2_residuals(m, data, residuals);
    }

    fn datum_is_finite(&self, c: &Pair2) -> bool {
        c.iter().flatten().all(|v| v.is_finite())
    }
}

/// A 3-D similarity `y = scale · rotation · x + translation` (scale 1 for rigid motions).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity3 {
    /// Rotation (det +1).
    pub rotation: Matrix3<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
    /// Uniform scale.
    pub scale: f64,
}

impl Similarity3 {
    /// Maps a point.
    pub fn apply(&self, p: &[f64; 3]) -> Vector3<f64> {
        self.rotation * Vector3::from(*p) * self.scale + self.translation
    }
}

/// Umeyama's least-squares alignment (≥ 3 non-collinear pairs); `with_scale` false gives
/// Kabsch's rigid alignment.
pub fn umeyama(data: &[Pair3], with_scale: bool) -> Option<Similarity3> {
    if data.len() < 3 {
        return None;
    }
    let n = data.len() as f64;
    let mut mx = Vector3::zeros();
    let mut my = Vector3::zeros();
    for c in data {
        mx += Vector3::from(c[0]);
        my += Vector3::from(c[1]);
    }
    mx /= n;
    my /= n;
    let mut cov = Matrix3::zeros();
    let mut var_x = 0.0;
    for c in data {
        let x = Vector3::from(c[0]) - mx;
        let y = Vector3::from(c[1]) - my;
        cov += y * x.transpose();
        var_x += x.norm_squared();
    }
    cov /= n;
    var_x /= n;
    if var_x.is_nan() || var_x <= 0.0 {
        return None;
    }
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let sv = svd.singular_values;
    // Rank < 2 (collinear points): the rotation about the line is undetermined.
    let mut sorted = [sv[0], sv[1], sv[2]];
    sorted.sort_by(|a, b| b.total_cmp(a));
    if sorted[1].is_nan() || sorted[1] <= 1e-12 * sorted[0] {
        return None;
    }
    let d = if (u * v_t).determinant() < 0.0 {
        -1.0
    } else {
        1.0
    };
    // Flip the direction of the smallest singular value.
    let smallest = (0..3).min_by(|&a, &b| sv[a].total_cmp(&sv[b])).unwrap_or(2);
    let mut diag = Vector3::new(1.0, 1.0, 1.0);
    diag[smallest] = d;
    let rotation = u * Matrix3::from_diagonal(&diag) * v_t;
    let scale = if with_scale {
        sv.component_mul(&diag).sum() / var_x
    } else {
        1.0
    };
    let translation = my - rotation * mx * scale;
    let ok = rotation.iter().all(|v| v.is_finite()) && scale.is_finite() && scale > 0.0;
    ok.then_some(Similarity3 {
        rotation,
        translation,
        scale,
    })
}

fn pair3_residuals(m: &Similarity3, data: &[Pair3], residuals: &mut [f64]) {
    for (r, c) in residuals.iter_mut().zip(data) {
        *r = (m.apply(&c[0]) - Vector3::from(c[1])).norm_squared();
    }
}

/// Rigid 3-D alignment estimator (Kabsch).
#[derive(Debug, Clone, Copy, Default)]
pub struct Rigid3Estimator;

impl Estimator for Rigid3Estimator {
    type Datum = Pair3;
    type Model = Similarity3;
    const MIN_SAMPLES: usize = 3;

    fn fit(&self, sample: &[Pair3]) -> Vec<Similarity3> {
        umeyama(sample, false).into_iter().collect()
    }

    fn residuals(&self, m: &Similarity3, data: &[Pair3], residuals: &mut [f64]) {
        pair3_residuals(m, data, residuals);
    }

    fn datum_is_finite(&self, c: &Pair3) -> bool {
        c.iter().flatten().all(|v| v.is_finite())
    }
}

/// 3-D similarity alignment estimator (Umeyama).
#[derive(Debug, Clone, Copy, Default)]
pub struct Similarity3Estimator;

impl Estimator for Similarity3Estimator {
    type Datum = Pair3;
    type Model = Similarity3;
    const MIN_SAMPLES: usize = 3;

    fn fit(&self, sample: &[Pair3]) -> Vec<Similarity3> {
        umeyama(sample, true).into_iter().collect()
    }

    fn residuals(&self, m: &Similarity3, data: &[Pair3], residuals: &mut [f64]) {
        pair3_residuals(m, data, residuals);
    }

    fn datum_is_finite(&self, c: &Pair3) -> bool {
        c.iter().flatten().all(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::geometry::ransac::{RobustError, RobustOptions, estimate};
    use nalgebra::Rotation3;

    fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
        a.iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= tol * (1.0 + y.abs()))
    }

    #[test]
    fn affine_and_similarity_exact_at_every_scale() {
        let aff = [1.2, 0.3, 5.0, -0.4, 0.9, -7.0];
        let (c, s) = (0.8f64.cos() * 1.7, 0.8f64.sin() * 1.7);
        let sim = [c, -s, 3.0, s, c, 4.0];
        for scale in [1e-3, 1.0, 1e6] {
            let scaled = |m: &Affine2| [m[0], m[1], m[2] * scale, m[3], m[4], m[5] * scale];
            let mut rng = SplitMix64::new(4);
            let pts: Vec<[f64; 2]> = (0..10)
                .map(|_| [rng.uniform() * 100.0 * scale, rng.uniform() * 100.0 * scale])
                .collect();
            for (est_aff, truth) in [(true, scaled(&aff)), (false, scaled(&sim))] {
                let data: Vec<Pair2> = pts.iter().map(|p| [*p, apply_affine(&truth, p)]).collect();
                let k = if est_aff { 3 } else { 2 };
                for subset in [&data[..k], &data[..]] {
                    let m = if est_aff {
                        fit_affine2(subset).unwrap()
                    } else {
                        fit_similarity2(subset).unwrap()
                    };
                    assert!(close(&m, &truth, 1e-9), "{scale}: {m:?} vs {truth:?}");
                }
            }
        }
        let collinear: Vec<Pair2> = (0..3)
            .map(|i| [[i as f64, 2.0 * i as f64], [0.0, 0.0]])
            .collect();
        assert!(fit_affine2(&collinear).is_none());
        assert!(fit_similarity2(&[[[1.0, 1.0], [0.0, 0.0]]; 2]).is_none());
    }

    #[test]
    fn affine_ransac_with_outliers_and_f32_input() {
        let aff = [1.2, 0.3, 5.0, -0.4, 0.9, -7.0];
        let mut rng = SplitMix64::new(5);
        let data: Vec<Pair2> = (0..300)
            .map(|i| {
                let p = [rng.uniform() * 500.0, rng.uniform() * 500.0];
                let q = if i % 10 == 0 {
                    apply_affine(&aff, &p)
                } else {
                    [rng.uniform() * 500.0, rng.uniform() * 500.0]
                };
                [p, q].map(|v| v.map(|x| f64::from(x as f32)))
            })
            .collect();
        let r = estimate(
            &Affine2Estimator,
            &data,
            &RobustOptions {
                threshold: 0.01,
                ..RobustOptions::default()
            },
        )
        .unwrap();
        assert_eq!(r.num_inliers, 30);
        assert!(close(&r.model, &aff, 1e-5), "{:?}", r.model);
    }

    #[test]
    fn umeyama_exact_with_reflection_guard() {
        let rot = Rotation3::from_euler_angles(0.3, -0.5, 1.1).into_inner();
        let t = Vector3::new(1.0, -2.0, 3.0);
        for scale in [1e-3, 1.0, 1e6] {
            let mut rng = SplitMix64::new(6);
            let data: Vec<Pair3> = (0..10)
                .map(|_| {
                    let x = [
                        rng.uniform() * scale,
                        rng.uniform() * scale,
                        rng.uniform() * scale,
                    ];
                    let y = rot * Vector3::from(x) * 2.5 + t * scale;
                    [x, [y[0], y[1], y[2]]]
                })
                .collect();
            for subset in [&data[..3], &data[..]] {
                let m = umeyama(subset, true).unwrap();
                assert!((m.rotation - rot).norm() < 1e-9, "{scale}");
                assert!((m.scale - 2.5).abs() < 1e-9);
                assert!((m.translation / scale - t).norm() < 1e-8);
                let rigid = umeyama(subset, false).unwrap();
                assert!((rigid.rotation.determinant() - 1.0).abs() < 1e-12);
                assert_eq!(rigid.scale, 1.0);
            }
        }
        // A mirrored target: the result must still be a rotation (det +1).
        let data: Vec<Pair3> = [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 1.0, 1.0],
        ]
        .iter()
        .map(|p| [*p, [-p[0], p[1], p[2]]])
        .collect();
        let m = umeyama(&data, false).unwrap();
        assert!((m.rotation.determinant() - 1.0).abs() < 1e-12);
        // Collinear sources are degenerate.
        let line: Vec<Pair3> = (0..4)
            .map(|i| [[i as f64, i as f64, i as f64], [i as f64, 0.0, 0.0]])
            .collect();
        assert!(umeyama(&line, true).is_none());
        assert_eq!(
            estimate(&Rigid3Estimator, &line, &RobustOptions::default()),
            Err(RobustError::Degenerate)
        );
    }

    #[test]
    fn rigid_ransac_with_outliers() {
        let rot = Rotation3::from_euler_angles(0.1, 0.2, 0.3).into_inner();
        let t = Vector3::new(0.5, 0.0, -1.0);
        let mut rng = SplitMix64::new(9);
        let data: Vec<Pair3> = (0..200)
            .map(|i| {
                let x = [rng.uniform(), rng.uniform(), rng.uniform()];
                let y = if i % 10 < 1 {
                    rot * Vector3::from(x) + t
                } else {
                    Vector3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 3.0
                };
                [x, [y[0], y[1], y[2]]]
            })
            .collect();
        for est in [true, false] {
            let opts = RobustOptions {
                threshold: 1e-6,
                ..RobustOptions::default()
            };
            let m = if est {
                estimate(&Rigid3Estimator, &data, &opts).unwrap().model
            } else {
                estimate(&Similarity3Estimator, &data, &opts).unwrap().model
            };
            assert!((m.rotation - rot).norm() < 1e-9);
            assert!((m.translation - t).norm() < 1e-9);
        }
    }
}
