//! Planar homography estimation: normalized DLT (4-point minimal and least-squares), symmetric
//! transfer error, and Levenberg–Marquardt refinement.
//!
//! A homography `H` maps left pixels to right pixels: `x₂ ~ H·[x₁, y₁, 1]ᵀ`.
//!
//! - Minimal fit (4 correspondences): Hartley-normalized coordinates (centroid at the origin,
//!   mean distance √2, per image and per sample), then the 8×8 linear system with `h₃₃ = 1`
//!   solved by LU, denormalized. Samples with three (nearly) collinear points in either image,
//!   or whose points do not all lie on the same side of the line at infinity (`w` of mixed
//!   signs, an impossible configuration for two views of a plane), are rejected.
//! - Non-minimal fit: the normalized DLT, the unit vector minimizing `‖A h‖` taken as the
//!   eigenvector of the 9×9 `AᵀA` with the smallest eigenvalue.
//! - Residual: the **symmetric transfer error**, the mean of the squared forward and backward
//!   transfer distances `(‖x₂ − H x₁‖² + ‖x₁ − H⁻¹ x₂‖²) / 2`, pixels². Unlike the forward error
//!   OpenCV scores with, it penalizes errors in both images alike and does not favour models
//!   that shrink the left image; being a mean, a threshold `t` keeps the scale of a one-image
//!   reprojection threshold.
//! - Refinement: LM on the same symmetric transfer error over the inliers, 8 parameters
//!   (`h₃₃ = 1` in normalized coordinates), see [`refine_homography`].
//!
//! Reference: Hartley & Zisserman, "Multiple View Geometry", 2nd ed., §4.1–4.2 (DLT, Hartley
//! normalization), §4.2.2 (symmetric transfer error); OpenCV `cv::findHomography`.

use nalgebra::{Matrix3, SMatrix, SVector, SymmetricEigen, Vector3};

use super::lm::{self, LmOptions, Problem};
use super::robust::Estimator;

/// One correspondence: `[left, right]`, pixels.
pub type Correspondence = [[f64; 2]; 2];

/// The similarity moving `points` to centroid 0 and mean distance √2 (Hartley 1997), or `None`
/// if all points coincide or a coordinate is not finite.
pub fn hartley_normalization<'a>(
    points: impl Iterator<Item = &'a [f64; 2]> + Clone,
) -> Option<Matrix3<f64>> {
    let mut n = 0usize;
    let (mut cx, mut cy) = (0.0, 0.0);
    for p in points.clone() {
        cx += p[0];
        cy += p[1];
        n += 1;
    }
    if n == 0 {
        return None;
    }
    cx /= n as f64;
    cy /= n as f64;
    let mean = points.map(|p| (p[0] - cx).hypot(p[1] - cy)).sum::<f64>() / n as f64;
    if !(mean.is_finite() && mean > 0.0) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean;
    Some(Matrix3::new(
        s,
        0.0,
        -s * cx,
        0.0,
        s,
        -s * cy,
        0.0,
        0.0,
        1.0,
    ))
}

/// Applies a normalization (scale + translation) to a point.
#[inline]
pub(crate) fn apply_similarity(t: &Matrix3<f64>, p: &[f64; 2]) -> [f64; 2] {
    [t[(0, 0)] * p[0] + t[(0, 2)], t[(1, 1)] * p[1] + t[(1, 2)]]
}

/// The inverse of a normalization matrix.
pub(crate) fn inverse_similarity(t: &Matrix3<f64>) -> Matrix3<f64> {
    let s = t[(0, 0)];
    Matrix3::new(
        1.0 / s,
        0.0,
        -t[(0, 2)] / s,
        0.0,
        1.0 / s,
        -t[(1, 2)] / s,
        0.0,
        0.0,
        1.0,
    )
}

/// Scales `h` to unit Frobenius norm with `h₃₃ ≥ 0` (a canonical representative), or `None` if
/// it is zero or not finite.
pub fn normalize_homography(h: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let norm = h.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return None;
    }
    let sign = if h[(2, 2)] < 0.0 { -1.0 } else { 1.0 };
    Some(h * (sign / norm))
}

/// Maps a point through `h`; `None` at (or numerically at) infinity.
#[inline]
pub fn transfer(h: &Matrix3<f64>, p: &[f64; 2]) -> Option<[f64; 2]> {
    let w = h[(2, 0)] * p[0] + h[(2, 1)] * p[1] + h[(2, 2)];
    let x = h[(0, 0)] * p[0] + h[(0, 1)] * p[1] + h[(0, 2)];
    let y = h[(1, 0)] * p[0] + h[(1, 1)] * p[1] + h[(1, 2)];
    let (u, v) = (x / w, y / w);
    (u.is_finite() && v.is_finite()).then_some([u, v])
}

/// Squared symmetric transfer error of one correspondence (see the module doc).
#[inline]
pub fn symmetric_transfer_error2(
    h: &Matrix3<f64>,
    h_inv: &Matrix3<f64>,
    c: &Correspondence,
) -> f64 {
    match (transfer(h, &c[0]), transfer(h_inv, &c[1])) {
        (Some(f), Some(b)) => {
            let df = (f[0] - c[1][0]).powi(2) + (f[1] - c[1][1]).powi(2);
            let db = (b[0] - c[0][0]).powi(2) + (b[1] - c[0][1]).powi(2);
            0.5 * (df + db)
        }
        _ => f64::INFINITY,
    }
}

/// Twice the signed area of triangle `abc`, relative to the product of two side lengths (the
/// sine of the angle at `a`).
fn collinearity(a: &[f64; 2], b: &[f64; 2], c: &[f64; 2]) -> f64 {
    let (ux, uy) = (b[0] - a[0], b[1] - a[1]);
    let (vx, vy) = (c[0] - a[0], c[1] - a[1]);
    let cross = ux * vy - uy * vx;
    let scale = ux.hypot(uy) * vx.hypot(vy);
    if scale > 0.0 { cross / scale } else { 0.0 }
}

/// Whether any three of `points` are collinear within `|sin| ≤ 1e-7`.
pub(crate) fn has_collinear_triple(points: &[[f64; 2]]) -> bool {
    let n = points.len();
    for i in 0..n {
        for j in i + 1..n {
            for k in j + 1..n {
                if collinearity(&points[i], &points[j], &points[k]).abs() <= 1e-7 {
                    return true;
                }
            }
        }
    }
    false
}

/// The normalized DLT over `data` (≥ 4 correspondences, least squares), or `None`.
pub fn dlt(data: &[Correspondence]) -> Option<Matrix3<f64>> {
    if data.len() < 4 {
        return None;
    }
    let t1 = hartley_normalization(data.iter().map(|c| &c[0]))?;
    let t2 = hartley_normalization(data.iter().map(|c| &c[1]))?;
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for c in data {
        let [x, y] = apply_similarity(&t1, &c[0]);
        let [u, v] = apply_similarity(&t2, &c[1]);
        let r1 = SVector::<f64, 9>::from([x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]);
        let r2 = SVector::<f64, 9>::from([0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y, -v]);
        ata.syger(1.0, &r1, &r1, 1.0);
        ata.syger(1.0, &r2, &r2, 1.0);
    }
    ata.fill_upper_triangle_with_lower_triangle();
    let eigen = SymmetricEigen::new(ata);
    let (k, _) =
        eigen
            .eigenvalues
            .iter()
            .enumerate()
            .fold(
                (0, f64::INFINITY),
                |(bk, bv), (k, &v)| if v < bv { (k, v) } else { (bk, bv) },
            );
    let h = eigen.eigenvectors.column(k);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let out = inverse_similarity(&t2) * hn * t1;
    normalize_homography(&out)
}

/// The exact homography of 4 correspondences (normalized, `h₃₃ = 1`), or `None` if singular.
pub fn four_point(data: &[Correspondence]) -> Option<Matrix3<f64>> {
    if data.len() != 4 {
        return None;
    }
    let t1 = hartley_normalization(data.iter().map(|c| &c[0]))?;
    let t2 = hartley_normalization(data.iter().map(|c| &c[1]))?;
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut b = SVector::<f64, 8>::zeros();
    for (i, c) in data.iter().enumerate() {
        let [x, y] = apply_similarity(&t1, &c[0]);
        let [u, v] = apply_similarity(&t2, &c[1]);
        let r = 2 * i;
        a.row_mut(r)
            .copy_from_slice(&[x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]);
        a.row_mut(r + 1)
            .copy_from_slice(&[0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]);
        b[r] = u;
        b[r + 1] = v;
    }
    let h = a.lu().solve(&b)?;
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0);
    let out = inverse_similarity(&t2) * hn * t1;
    let out = normalize_homography(&out)?;
    // Every sample point must map with the same sign of w (same side of the horizon).
    let signs = data
        .iter()
        .map(|c| out[(2, 0)] * c[0][0] + out[(2, 1)] * c[0][1] + out[(2, 2)]);
    let (mut pos, mut neg) = (0, 0);
    for w in signs {
        if w > 0.0 {
            pos += 1;
        } else if w < 0.0 {
            neg += 1;
        }
    }
    (pos == 4 || neg == 4).then_some(out)
}

/// Homography estimator for the robust loops (datum: [`Correspondence`], residual: squared
/// symmetric transfer error in pixels²).
#[derive(Debug, Clone, Copy, Default)]
pub struct HomographyEstimator;

impl Estimator for HomographyEstimator {
    type Datum = Correspondence;
    type Model = Matrix3<f64>;
    const MIN_SAMPLES: usize = 4;

    fn fit(&self, sample: &[Correspondence]) -> Vec<Matrix3<f64>> {
        let h = if sample.len() == 4 {
            four_point(sample)
        } else {
            dlt(sample)
        };
        h.into_iter().collect()
    }

    fn fit_nonminimal(&self, data: &[Correspondence]) -> Vec<Matrix3<f64>> {
        dlt(data).into_iter().collect()
    }

    fn residuals(&self, model: &Matrix3<f64>, data: &[Correspondence], residuals: &mut [f64]) {
        let Some(inverse) = model.try_inverse() else {
            residuals.fill(f64::INFINITY);
            return;
        };
        for (r, c) in residuals.iter_mut().zip(data) {
            *r = symmetric_transfer_error2(model, &inverse, c);
        }
    }

    fn is_degenerate(&self, sample: &[Correspondence]) -> bool {
        let left: Vec<[f64; 2]> = sample.iter().map(|c| c[0]).collect();
        let right: Vec<[f64; 2]> = sample.iter().map(|c| c[1]).collect();
        has_collinear_triple(&left) || has_collinear_triple(&right)
    }

    fn datum_is_finite(&self, c: &Correspondence) -> bool {
        c.iter().flatten().all(|v| v.is_finite())
    }
}

/// LM problem: symmetric transfer error over inliers, 8 parameters of the normalized
/// homography (`h₃₃ = 1`).
struct HomographyProblem<'a> {
    data: &'a [Correspondence],
    t1: Matrix3<f64>,
    t2_inv: Matrix3<f64>,
}

impl HomographyProblem<'_> {
    fn matrix(&self, x: &[f64]) -> Matrix3<f64> {
        let hn = Matrix3::new(x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], 1.0);
        self.t2_inv * hn * self.t1
    }
}

impl Problem for HomographyProblem<'_> {
    fn num_params(&self) -> usize {
        8
    }
    fn num_residuals(&self) -> usize {
        4 * self.data.len()
    }
    fn residuals(&self, x: &[f64], r: &mut [f64]) {
        let h = self.matrix(x);
        let inverse = h
            .try_inverse()
            .unwrap_or_else(|| Matrix3::from_element(f64::NAN));
        let k = std::f64::consts::FRAC_1_SQRT_2;
        for (c, out) in self.data.iter().zip(r.chunks_exact_mut(4)) {
            let f = transfer(&h, &c[0]).unwrap_or([f64::NAN; 2]);
            let b = transfer(&inverse, &c[1]).unwrap_or([f64::NAN; 2]);
            out[0] = k * (f[0] - c[1][0]);
            out[1] = k * (f[1] - c[1][1]);
            out[2] = k * (b[0] - c[0][0]);
            out[3] = k * (b[1] - c[0][1]);
        }
    }
}

/// Refines `h` by Levenberg–Marquardt on the symmetric transfer error of `data` (the inliers).
/// Returns the refined homography (unit norm) and the RMS of the LM residual before and after
/// (pixels; √(mean symmetric transfer error²)). Returns `h` unchanged if it cannot be refined.
pub fn refine_homography(h: &Matrix3<f64>, data: &[Correspondence]) -> (Matrix3<f64>, f64, f64) {
    let fallback = (*h, f64::NAN, f64::NAN);
    if data.len() < 4 {
        return fallback;
    }
    let (Some(t1), Some(t2)) = (
        hartley_normalization(data.iter().map(|c| &c[0])),
        hartley_normalization(data.iter().map(|c| &c[1])),
    ) else {
        return fallback;
    };
    let t2_inv = inverse_similarity(&t2);
    let hn = t2 * h * inverse_similarity(&t1);
    if hn[(2, 2)].is_nan() || hn[(2, 2)].abs() <= 1e-8 * hn.norm() {
        return fallback;
    }
    let hn = hn / hn[(2, 2)];
    let x0: Vec<f64> = (0..8).map(|i| hn[(i / 3, i % 3)]).collect();
    let problem = HomographyProblem { data, t1, t2_inv };
    let report = lm::levenberg_marquardt(
        &problem,
        &x0,
        &LmOptions {
            max_iterations: 50,
            ..LmOptions::default()
        },
    );
    let rms = |cost: f64| (cost / data.len() as f64).sqrt();
    match normalize_homography(&problem.matrix(&report.x)) {
        Some(refined) => (refined, rms(report.initial_cost), rms(report.final_cost)),
        None => fallback,
    }
}

/// `H · [p, 1]ᵀ` as a homogeneous vector.
pub fn apply_homogeneous(h: &Matrix3<f64>, p: &[f64; 2]) -> Vector3<f64> {
    h * Vector3::new(p[0], p[1], 1.0)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::geometry::ransac::{Method, RobustError, RobustOptions, estimate};

    pub(crate) fn h_true() -> Matrix3<f64> {
        Matrix3::new(
            0.872604473,
            -0.213507943,
            94.5686077,
            0.204034258,
            0.811550358,
            -18.1429492,
            0.0001078977,
            -0.000110528542,
            1.0,
        )
    }

    /// Relative distance between two homographies up to scale.
    pub(crate) fn h_distance(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
        let a = normalize_homography(a).unwrap();
        let b = normalize_homography(b).unwrap();
        (a - b).norm().min((a + b).norm())
    }

    /// `n` correspondences of `h` on a `w × h` image, scaled by `scale`.
    pub(crate) fn make_data(
        h: &Matrix3<f64>,
        n: usize,
        scale: f64,
        seed: u64,
    ) -> Vec<Correspondence> {
        let s = Matrix3::new(scale, 0.0, 0.0, 0.0, scale, 0.0, 0.0, 0.0, 1.0);
        let hs = s * h * s.try_inverse().unwrap();
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                let p = [640.0 * rng.uniform() * scale, 480.0 * rng.uniform() * scale];
                [p, transfer(&hs, &p).unwrap()]
            })
            .collect()
    }

    #[test]
    fn four_point_and_dlt_recover_exact_homography() {
        let h = h_true();
        let data = make_data(&h, 4, 1.0, 1);
        let four = four_point(&data).unwrap();
        assert!(h_distance(&four, &h) < 1e-9, "{}", h_distance(&four, &h));
        let data = make_data(&h, 50, 1.0, 2);
        let all = dlt(&data).unwrap();
        assert!(h_distance(&all, &h) < 1e-9, "{}", h_distance(&all, &h));
        let mut r = vec![0.0; data.len()];
        HomographyEstimator.residuals(&all, &data, &mut r);
        assert!(r.iter().all(|&e| e < 1e-16));
    }

    #[test]
    fn recovery_is_scale_invariant() {
        let h = h_true();
        for scale in [1e-3, 1.0, 1e3, 1e6] {
            let s = Matrix3::new(scale, 0.0, 0.0, 0.0, scale, 0.0, 0.0, 0.0, 1.0);
            let hs = s * h * s.try_inverse().unwrap();
            let data = make_data(&h, 20, scale, 3);
            for fit in [four_point(&data[..4]).unwrap(), dlt(&data).unwrap()] {
                let d = h_distance(&fit, &hs);
                assert!(d < 1e-8, "scale {scale}: {d}");
            }
        }
    }

    #[test]
    fn near_collinear_points_still_recover_or_are_rejected() {
        let h = h_true();
        // Points near one line (1e-3 px off), plus a few away from it.
        let mut data: Vec<Correspondence> = (0..20)
            .map(|i| {
                let x = 20.0 + 30.0 * i as f64;
                let p = [x, 100.0 + 0.5 * x + 1e-3 * ((i * 7 % 5) as f64 - 2.0)];
                [p, transfer(&h, &p).unwrap()]
            })
            .collect();
        assert!(HomographyEstimator.is_degenerate(&data[..4]) || four_point(&data[..4]).is_some());
        for p in [[300.0, 400.0], [50.0, 450.0]] {
            data.push([p, transfer(&h, &p).unwrap()]);
        }
        let fit = dlt(&data).unwrap();
        assert!(h_distance(&fit, &h) < 1e-7, "{}", h_distance(&fit, &h));
        // Exactly collinear samples are degenerate.
        let line: Vec<Correspondence> = (0..4)
            .map(|i| {
                let p = [10.0 * i as f64, 5.0 * i as f64];
                [p, transfer(&h, &p).unwrap()]
            })
            .collect();
        assert!(HomographyEstimator.is_degenerate(&line));
    }

    fn with_outliers(
        h: &Matrix3<f64>,
        n: usize,
        outlier_share: f64,
        noise: f64,
        seed: u64,
    ) -> (Vec<Correspondence>, Vec<bool>) {
        let mut rng = SplitMix64::new(seed);
        let mut data = make_data(h, n, 1.0, seed + 1);
        let mut truth = vec![true; n];
        for (c, t) in data.iter_mut().zip(&mut truth) {
            if rng.uniform() < outlier_share {
                c[1] = [640.0 * rng.uniform(), 480.0 * rng.uniform()];
                *t = false;
            } else {
                c[1][0] += noise * rng.normal();
                c[1][1] += noise * rng.normal();
            }
        }
        (data, truth)
    }

    /// `n` correspondences of `h` of which the first `inliers` are true (noise σ = 0.3 px on
    /// the second point) and the rest have a uniformly random second point.
    fn with_outliers_exactly(
        h: &Matrix3<f64>,
        n: usize,
        inliers: usize,
        seed: u64,
    ) -> (Vec<Correspondence>, Vec<bool>) {
        let mut rng = SplitMix64::new(seed);
        let mut data = make_data(h, n, 1.0, seed + 1);
        for (i, c) in data.iter_mut().enumerate() {
            if i < inliers {
                c[1][0] += 0.3 * rng.normal();
                c[1][1] += 0.3 * rng.normal();
            } else {
                c[1] = [640.0 * rng.uniform(), 480.0 * rng.uniform()];
            }
        }
        (data, (0..n).map(|i| i < inliers).collect())
    }

    /// Largest transfer distance between `truth` and `estimate` over the 640×480 image's
    /// corners (infinite where the estimate sends a corner to infinity).
    fn max_corner_error(truth: &Matrix3<f64>, estimate: &Matrix3<f64>) -> f64 {
        [[0.0, 0.0], [640.0, 0.0], [0.0, 480.0], [640.0, 480.0]]
            .iter()
            .map(|p| match (transfer(truth, p), transfer(estimate, p)) {
                (Some(a), Some(b)) => (a[0] - b[0]).hypot(a[1] - b[1]),
                _ => f64::INFINITY,
            })
            .fold(0.0f64, f64::max)
    }

    #[test]
    fn ransac_finds_the_model_among_90_percent_outliers() {
        let h = h_true();
        let (data, truth) = with_outliers(&h, 600, 0.92, 0.3, 11);
        let true_inliers = truth.iter().filter(|&&t| t).count();
        assert!(true_inliers >= 30, "{true_inliers}");
        for method in [Method::Ransac, Method::Msac, Method::LoRansac] {
            let options = RobustOptions {
                method,
                threshold: 2.0,
                max_trials: 100_000,
                seed: 5,
                ..RobustOptions::default()
            };
            let report = estimate(&HomographyEstimator, &data, &options).unwrap();
            let found = crate::geometry::ransac::tests::true_positives(&report.inlier_mask, &truth);
            assert!(
                found + 2 >= true_inliers,
                "{method:?}: {found}/{true_inliers}"
            );
            let corner_error = max_corner_error(&h, &report.model);
            assert!(corner_error < 1.5, "{method:?}: {corner_error}");
        }
    }

    /// 95 % outliers (50 true of 1000), ordered as a matcher would rank them: each datum's
    /// quality is a unit normal, shifted by +1.5 for the true ones, and the data are sorted by
    /// decreasing quality. PROSAC finds the model within 5000 trials; uniform sampling with
    /// the same budget draws an all-inlier 4-sample with probability 1 − (1 − 0.05⁴)⁵⁰⁰⁰ ≈ 3 %,
    /// and does not.
    #[test]
    fn prosac_finds_h_among_95_percent_outliers_ranked_by_quality() {
        let h = h_true();
        let (data, truth) = with_outliers_exactly(&h, 1000, 50, 23);
        let (data, truth) =
            crate::geometry::ransac::tests::ranked_by_quality(&data, &truth, 1.5, 24);
        let options = |method| RobustOptions {
            method,
            threshold: 2.0,
            max_trials: 5000,
            seed: 3,
            ..RobustOptions::default()
        };
        let report = estimate(&HomographyEstimator, &data, &options(Method::Prosac)).unwrap();
        let found = crate::geometry::ransac::tests::true_positives(&report.inlier_mask, &truth);
        assert!(found >= 48, "PROSAC: {found}/50");
        assert!(
            report.num_inliers <= 55,
            "PROSAC: {} inliers",
            report.num_inliers
        );
        assert!(
            max_corner_error(&h, &report.model) < 1.0,
            "PROSAC: {}",
            max_corner_error(&h, &report.model)
        );
        match estimate(&HomographyEstimator, &data, &options(Method::LoRansac)) {
            Err(_) => {}
            Ok(uniform) => {
                let found =
                    crate::geometry::ransac::tests::true_positives(&uniform.inlier_mask, &truth);
                assert!(found < 25, "uniform sampling found {found}/50");
            }
        }
    }

    #[test]
    fn f32_rounded_input_and_refinement() {
        let h = h_true();
        let data: Vec<Correspondence> = make_data(&h, 100, 1.0, 9)
            .into_iter()
            .map(|c| c.map(|p| p.map(|v| f64::from(v as f32))))
            .collect();
        let fit = dlt(&data).unwrap();
        assert!(h_distance(&fit, &h) < 1e-6, "{}", h_distance(&fit, &h));
        let (refined, before, after) = refine_homography(&fit, &data);
        assert!(after <= before + 1e-12);
        assert!(after < 1e-4, "{after}");
        assert!(h_distance(&refined, &h) < 1e-6);
    }

    #[test]
    fn degenerate_input_is_an_error() {
        let options = RobustOptions {
            max_trials: 100,
            ..RobustOptions::default()
        };
        let h = h_true();
        let few = make_data(&h, 3, 1.0, 1);
        assert!(matches!(
            estimate(&HomographyEstimator, &few, &options),
            Err(RobustError::TooFewData { .. })
        ));
        let same = vec![[[1.0, 2.0], [3.0, 4.0]]; 10];
        assert!(estimate(&HomographyEstimator, &same, &options).is_err());
        let mut nan = make_data(&h, 10, 1.0, 1);
        nan[3][1][0] = f64::NAN;
        assert_eq!(
            estimate(&HomographyEstimator, &nan, &options),
            Err(RobustError::NonFinite { index: 3 })
        );
    }
}
