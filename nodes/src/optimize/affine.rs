//! Tomasi–Kanade affine factorization: cameras and points from tracks seen in every view,
//! under a scaled orthographic (weak-perspective) camera — an initializer for bundle adjustment.
//!
//! Method: subtract each view's centroid from its observations, stack them into the 2F × P
//! measurement matrix `W`, take its best rank-3 approximation `W ≈ M S` (the top three
//! eigenvectors `U₃` of `W Wᵀ`, which are `W`'s left singular vectors: `M = U₃ Σ₃^½`,
//! `S = Σ₃^-½ U₃ᵀ W`), then upgrade the affine solution to a metric one: find the
//! symmetric `L = Q Qᵀ` with `iᵀ L i = jᵀ L j`, `iᵀ L j = 0` for each view's rows `i`, `j` and
//! `iᵀ L i = 1` for the first view (linear least squares in L's 6 entries), factor it by
//! Cholesky and use `M Q`, `Q⁻¹ S`. The result is defined up to a global rotation and a
//! reflection (the depth-reversal ambiguity of affine cameras).
//!
//! Reference: Tomasi & Kanade, "Shape and motion from image streams under orthography: a
//! factorization method", IJCV 9(2), 1992; Hartley & Zisserman, 2nd ed., §18.2.

use nalgebra::{DMatrix, DVector, Matrix3};

/// The factorization: per view a 2×3 affine camera and a translation, and the points, with
/// `x ≈ motion · X + translation`.
#[derive(Debug, Clone, PartialEq)]
pub struct AffineFactorization {
    /// Per view, the camera's two rows.
    pub motion: Vec<[[f64; 3]; 2]>,
    /// Per view, the centroid of its observations (the image of the points' centroid).
    pub translation: Vec<[f64; 2]>,
    /// Points, centred at their centroid.
    pub points: Vec<[f64; 3]>,
}

impl AffineFactorization {
    /// Image of point `j` in view `f`.
    pub fn project(&self, f: usize, j: usize) -> [f64; 2] {
        let (m, t, x) = (&self.motion[f], &self.translation[f], &self.points[j]);
        [
            m[0][0] * x[0] + m[0][1] * x[1] + m[0][2] * x[2] + t[0],
            m[1][0] * x[0] + m[1][1] * x[1] + m[1][2] * x[2] + t[1],
        ]
    }
}

/// Factorizes `views[f][j]`, the observation of point `j` in view `f` (every point in every
/// view). Needs at least 2 views and 4 points; errors on non-finite input, ragged views, or
/// when no metric upgrade exists (degenerate motion).
pub fn affine_factorization(views: &[Vec<[f64; 2]>]) -> Result<AffineFactorization, String> {
    let n_views = views.len();
    let n_points = views.first().map_or(0, Vec::len);
    if n_views < 2 || n_points < 4 {
        return Err(format!(
            "need at least 2 views and 4 points, got {n_views} views and {n_points} points"
        ));
    }
    if let Some(f) = views.iter().position(|v| v.len() != n_points) {
        return Err(format!(
            "view {f} has {} points, view 0 has {n_points}",
            views[f].len()
        ));
    }
    if views.iter().flatten().flatten().any(|v| !v.is_finite()) {
        return Err("observations must be finite".into());
    }
    let mut w = DMatrix::<f64>::zeros(2 * n_views, n_points);
    let mut translation = Vec::with_capacity(n_views);
    for (f, v) in views.iter().enumerate() {
        let n = n_points as f64;
        let c = [
            v.iter().map(|p| p[0]).sum::<f64>() / n,
            v.iter().map(|p| p[1]).sum::<f64>() / n,
        ];
        for (j, p) in v.iter().enumerate() {
            w[(2 * f, j)] = p[0] - c[0];
            w[(2 * f + 1, j)] = p[1] - c[1];
        }
        translation.push(c);
    }
    // Rank-3 factorization from the eigenvectors of the small Gram matrix W Wᵀ (2F × 2F):
    // W ≈ U₃ U₃ᵀ W, M = U₃ Σ₃^½, S = Σ₃^-½ U₃ᵀ W. (nalgebra 0.35's SVD with singular vectors
    // returns wrong values for some exactly low-rank inputs, dimforge/nalgebra#1172, so it is
    // not used here; the Gram route squares the condition number, which only matters for
    // singular values below ≈ 1e-8 of the largest — far below the rank-3 gap.)
    let gram = &w * w.transpose();
    let eig = nalgebra::SymmetricEigen::new(gram);
    let mut order: Vec<usize> = (0..eig.eigenvalues.len()).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let top = eig.eigenvalues[order[0]].max(0.0);
    if order.len() < 3 || eig.eigenvalues[order[2]] <= 1e-12 * top || top == 0.0 {
        return Err("the measurements have rank below 3 (planar or degenerate scene)".into());
    }
    let mut m = DMatrix::<f64>::zeros(2 * n_views, 3);
    let mut u3t = DMatrix::<f64>::zeros(3, 2 * n_views);
    for (k, &o) in order.iter().take(3).enumerate() {
        let sigma = eig.eigenvalues[o].sqrt();
        for i in 0..2 * n_views {
            let u = eig.eigenvectors[(i, o)];
            m[(i, k)] = u * sigma.sqrt();
            u3t[(k, i)] = u / sigma.sqrt();
        }
    }
    let s = &u3t * &w;
    // Metric upgrade: a(i, j) · l = value, l = (L00, L01, L02, L11, L12, L22).
    let coeffs = |a: [f64; 3], b: [f64; 3]| {
        [
            a[0] * b[0],
            a[0] * b[1] + a[1] * b[0],
            a[0] * b[2] + a[2] * b[0],
            a[1] * b[1],
            a[1] * b[2] + a[2] * b[1],
            a[2] * b[2],
        ]
    };
    let rows = 2 * n_views + 1;
    let mut a = DMatrix::<f64>::zeros(rows, 6);
    let mut b = DVector::<f64>::zeros(rows);
    for f in 0..n_views {
        let i = [m[(2 * f, 0)], m[(2 * f, 1)], m[(2 * f, 2)]];
        let j = [m[(2 * f + 1, 0)], m[(2 * f + 1, 1)], m[(2 * f + 1, 2)]];
        let (ii, jj, ij) = (coeffs(i, i), coeffs(j, j), coeffs(i, j));
        for k in 0..6 {
            a[(2 * f, k)] = ii[k] - jj[k];
            a[(2 * f + 1, k)] = ij[k];
        }
        if f == 0 {
            for k in 0..6 {
                a[(rows - 1, k)] = ii[k];
            }
            b[rows - 1] = 1.0;
        }
    }
    // Least squares by the 6×6 normal equations (well conditioned here: the rows are
    // products of unit-scale motion entries).
    let ata =
        nalgebra::Matrix6::<f64>::from_fn(|r, c| (0..rows).map(|i| a[(i, r)] * a[(i, c)]).sum());
    let atb = nalgebra::Vector6::<f64>::from_fn(|r, _| (0..rows).map(|i| a[(i, r)] * b[i]).sum());
    let l = ata
        .lu()
        .solve(&atb)
        .filter(|l| l.iter().all(|v| v.is_finite()))
        .ok_or("metric upgrade failed: the motion constraints are degenerate")?;
    let big_l = Matrix3::new(l[0], l[1], l[2], l[1], l[3], l[4], l[2], l[4], l[5]);
    let q = big_l
        .cholesky()
        .ok_or("no metric upgrade: the motion constraints give an indefinite metric")?
        .l();
    let q_inv = q.try_inverse().ok_or("singular metric upgrade")?;
    let mut motion = Vec::with_capacity(n_views);
    for f in 0..n_views {
        let mut rows2 = [[0.0; 3]; 2];
        for (r, row) in rows2.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|k| m[(2 * f + r, k)] * q[(k, c)]).sum();
            }
        }
        motion.push(rows2);
    }
    let points = (0..n_points)
        .map(|j| std::array::from_fn(|r| (0..3).map(|k| q_inv[(r, k)] * s[(k, j)]).sum::<f64>()))
        .collect();
    Ok(AffineFactorization {
        motion,
        translation,
        points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::geometry::camera::rodrigues;

    #[test]
    fn recovers_weak_perspective_views() {
        let mut rng = SplitMix64::new(5);
        let points: Vec<[f64; 3]> = (0..30)
            .map(|_| std::array::from_fn(|_| 2.0 * rng.uniform() - 1.0))
            .collect();
        let mut views = Vec::new();
        for f in 0..5 {
            let r = rodrigues([0.3 * rng.normal(), 0.4 * f as f64, 0.2 * rng.normal()]);
            let scale = 100.0 + 20.0 * rng.uniform();
            let t = [320.0 + 10.0 * f as f64, 240.0];
            views.push(
                points
                    .iter()
                    .map(|x| {
                        let p = r * nalgebra::Vector3::new(x[0], x[1], x[2]);
                        [scale * p[0] + t[0], scale * p[1] + t[1]]
                    })
                    .collect::<Vec<_>>(),
            );
        }
        let fac = affine_factorization(&views).unwrap();
        for (f, v) in views.iter().enumerate() {
            for (j, x) in v.iter().enumerate() {
                let p = fac.project(f, j);
                assert!(
                    (p[0] - x[0]).abs() < 1e-8 && (p[1] - x[1]).abs() < 1e-8,
                    "view {f} point {j}: {p:?} vs {x:?}; sv {:?}",
                    fac.motion[f]
                );
            }
            // Metric: rows orthogonal with equal norms.
            let [i, j] = fac.motion[f];
            let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
            let (ii, jj) = (dot(i, i), dot(j, j));
            assert!((ii - jj).abs() < 1e-6 * ii, "view {f}: {ii} vs {jj}");
            assert!(dot(i, j).abs() < 1e-6 * ii);
        }
        // Shape up to scale and a rotation/reflection: pairwise distance ratios match.
        let d = |p: &[[f64; 3]], a: usize, b: usize| {
            ((p[a][0] - p[b][0]).powi(2)
                + (p[a][1] - p[b][1]).powi(2)
                + (p[a][2] - p[b][2]).powi(2))
            .sqrt()
        };
        let ratio = d(&fac.points, 0, 1) / d(&points, 0, 1);
        for (a, b) in [(2, 3), (4, 9), (7, 20)] {
            let r = d(&fac.points, a, b) / d(&points, a, b);
            assert!((r - ratio).abs() < 1e-6 * ratio);
        }
    }

    #[test]
    fn planar_points_are_rejected_not_factored() {
        // Points on a plane give a rank-2 measurement matrix: no unique affine shape.
        let points: Vec<[f64; 3]> = (0..20)
            .map(|i| [f64::from(i % 5), f64::from(i / 5), 0.0])
            .collect();
        let views: Vec<Vec<[f64; 2]>> = (0..4)
            .map(|f| {
                let r = rodrigues([0.2, 0.3 * f as f64, 0.1]);
                points
                    .iter()
                    .map(|x| {
                        let p = r * nalgebra::Vector3::new(x[0], x[1], x[2]);
                        [50.0 * p[0] + 300.0, 50.0 * p[1] + 200.0]
                    })
                    .collect()
            })
            .collect();
        let err = affine_factorization(&views).unwrap_err();
        assert!(err.contains("rank below 3"), "{err}");
    }

    #[test]
    fn noisy_views_reproject_at_the_noise_level() {
        let mut rng = SplitMix64::new(11);
        let points: Vec<[f64; 3]> = (0..60)
            .map(|_| std::array::from_fn(|_| 2.0 * rng.uniform() - 1.0))
            .collect();
        let views: Vec<Vec<[f64; 2]>> = (0..6)
            .map(|f| {
                let r = rodrigues([0.2 * rng.normal(), 0.25 * f as f64, 0.1 * rng.normal()]);
                points
                    .iter()
                    .map(|x| {
                        let p = r * nalgebra::Vector3::new(x[0], x[1], x[2]);
                        [
                            120.0 * p[0] + 320.0 + 0.5 * rng.normal(),
                            120.0 * p[1] + 240.0 + 0.5 * rng.normal(),
                        ]
                    })
                    .collect()
            })
            .collect();
        let fac = affine_factorization(&views).unwrap();
        let (mut sum, mut n) = (0.0, 0.0);
        for (f, v) in views.iter().enumerate() {
            for (j, x) in v.iter().enumerate() {
                let p = fac.project(f, j);
                sum += (p[0] - x[0]).powi(2) + (p[1] - x[1]).powi(2);
                n += 2.0;
            }
        }
        let rms = (sum / n).sqrt();
        // The rank-3 fit absorbs some noise: below σ = 0.5 px, but not far below.
        assert!(rms < 0.5 && rms > 0.3, "rms {rms}");
    }

    #[test]
    fn rejects_bad_input() {
        assert!(affine_factorization(&[]).is_err());
        let v = vec![[0.0, 0.0]; 5];
        assert!(affine_factorization(&[v.clone(), v[..4].to_vec()]).is_err());
        // All points identical: rank 0.
        assert!(affine_factorization(&[v.clone(), v]).is_err());
    }
}
