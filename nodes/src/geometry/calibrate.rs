//! `geometry.calibrate`: camera calibration from views of a planar chessboard (Zhang's method
//! refined by Levenberg–Marquardt), and a renderer of synthetic chessboard views.
//!
//! [`calibrate_planar`] follows Z. Zhang, "A flexible new technique for camera calibration",
//! IEEE TPAMI 22(11), 2000:
//! 1. one homography per view (board plane → pixels) by the normalized DLT
//!    ([`calib_homography_dlt`]: the shared [`super::homography::dlt`], Hartley's normalization);
//! 2. the closed-form intrinsics from `B = K⁻ᵀK⁻¹`: each homography gives `h1ᵀBh2 = 0` and
//!    `h1ᵀBh1 = h2ᵀBh2`; with the zero-skew row `B12 = 0` (OpenCV's model has no skew) the
//!    stacked system's null vector is `B` (the homographies are first scaled to the unit square
//!    around the image centre for conditioning); a second near-null direction means the views
//!    do not constrain `K` (e.g. all boards parallel to the image plane) and is an error;
//! 3. closed-form extrinsics `r1 = λK⁻¹h1, r2 = λK⁻¹h2, r3 = r1 × r2, t = λK⁻¹h3`, projected to
//!    the nearest rotation;
//! 4. radial distortion `k1, k2` by Zhang's linear least squares;
//! 5. Levenberg–Marquardt ([`lm_calibration`]) over the intrinsics, the chosen distortion
//!    terms and the per-view poses (angle-axis + translation), minimizing the reprojection
//!    error, with the shared solver [`super::lm`] (dense normal equations, Marquardt's diagonal
//!    scaling); the Jacobian is by central differences (per-view columns only touch that view's
//!    rows).
//!
//! The RMS error is OpenCV's: `sqrt(Σ‖r‖² / N)` over the N points of all views.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Distortion, Image, Intrinsics, Metrics, Pose, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::camera::{Lens, to_na};
use super::homography::{Correspondence, dlt};
use super::lm::{self, LmOptions, Problem};
use super::pose_util::{angle_axis, nearest_rotation, pose_from_rt, rodrigues};

param_enum! {
    /// Which distortion coefficients `geometry.calibrate` estimates (the others stay 0).
    pub enum CalibDistortion {
        /// No distortion: a pinhole camera.
        None = "none",
        /// `k1`.
        K1 = "k1",
        /// `k1, k2`.
        K1K2 = "k1k2",
        /// `k1, k2, p1, p2`.
        K1K2P1P2 = "k1k2p1p2",
        /// `k1, k2, p1, p2, k3` (OpenCV's default).
        Full = "full",
    }
}

params! {
    /// Parameters of `geometry.calibrate`.
    pub struct CalibrateParams {
        /// Inner corners per board row (OpenCV's `patternSize.width`, `cols` of
        /// `detect.chessboard`), ≥ 2. Default: none, inferred from the corners (see DOC).
        cols: Option<u32> = None,
        /// Inner corners per board column (`patternSize.height`), ≥ 2. Default: none,
        /// inferred.
        rows: Option<u32> = None,
        /// Side of a board square, in the unit the poses' translations should have. Default 1.
        square_size: f64 = 1.0,
        /// Distortion terms to estimate: "none", "k1", "k1k2", "k1k2p1p2" or "full"
        /// (k1, k2, p1, p2, k3). Default "full", as OpenCV.
        distortion: CalibDistortion = CalibDistortion::Full,
        /// true: fx = fy (OpenCV's `CALIB_FIX_ASPECT_RATIO` with an identity initial matrix).
        /// Default false.
        fix_aspect_ratio: bool = false,
        /// true: p1 = p2 = 0 (OpenCV's `CALIB_ZERO_TANGENT_DIST`). Default false.
        zero_tangent: bool = false,
        /// Image size `[width, height]` in pixels, when no image is connected to port `image`.
        /// Default: none (then `image` is required).
        image_size: Option<[u32; 2]> = None,
        /// Levenberg–Marquardt iterations at most. Default 100.
        max_iterations: u32 = 100 => [min = 1, max = 10000],
    }
}

/// Options of [`calibrate_planar`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibrationOptions {
    /// Distortion terms to estimate.
    pub distortion: CalibDistortion,
    /// fx = fy.
    pub fix_aspect_ratio: bool,
    /// p1 = p2 = 0.
    pub zero_tangent: bool,
    /// LM iterations at most.
    pub max_iterations: usize,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        CalibrationOptions {
            distortion: CalibDistortion::Full,
            fix_aspect_ratio: false,
            zero_tangent: false,
            max_iterations: 100,
        }
    }
}

/// Result of [`calibrate_planar`].
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Intrinsics (skew 0) and radial–tangential distortion.
    pub lens: Lens,
    /// `camera_from_board` of every view.
    pub poses: Vec<Pose>,
    /// OpenCV's RMS reprojection error, pixels.
    pub rms: f64,
    /// RMS error of each view, pixels.
    pub view_rms: Vec<f64>,
    /// LM iterations run.
    pub iterations: usize,
}

/// Board-plane coordinates of a `cols × rows` chessboard's inner corners, row-major (the order
/// of `detect.chessboard`): corner `r·cols + c` is at `(c·square, r·square)`.
pub fn board_points(cols: usize, rows: usize, square: f64) -> Vec<[f64; 2]> {
    (0..rows)
        .flat_map(|r| (0..cols).map(move |c| [c as f64 * square, r as f64 * square]))
        .collect()
}

/// Whether `pts` span the plane: the smaller eigenvalue of their 2×2 scatter matrix is above
/// 1e-12 of the larger (false for collinear, repeated or non-finite points).
fn spans_plane(pts: &[[f64; 2]]) -> bool {
    let n = pts.len() as f64;
    let (mx, my) = pts
        .iter()
        .fold((0.0, 0.0), |(a, b), p| (a + p[0] / n, b + p[1] / n));
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p[0] - mx, p[1] - my);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    let half_trace = 0.5 * (sxx + syy);
    let root = (0.25 * (sxx - syy).powi(2) + sxy * sxy).sqrt();
    let (small, large) = (half_trace - root, half_trace + root);
    large.is_finite() && large > 0.0 && small > 1e-12 * large
}

/// Homography `H` (`H[2][2] = 1` where possible) with `dst ~ H·src`: the shared normalized DLT
/// ([`super::homography::dlt`], Hartley & Zisserman Alg. 4.2). Needs ≥ 4 points; `None` when
/// either point set is collinear or degenerate.
pub fn calib_homography_dlt(src: &[[f64; 2]], dst: &[[f64; 2]]) -> Option<Matrix3<f64>> {
    if src.len() != dst.len() || src.len() < 4 || !spans_plane(src) || !spans_plane(dst) {
        return None;
    }
    let pairs: Vec<Correspondence> = src.iter().zip(dst).map(|(s, d)| [*s, *d]).collect();
    let hm = dlt(&pairs)?;
    let scale = if hm[(2, 2)].abs() > 1e-12 {
        hm[(2, 2)]
    } else {
        hm.norm()
    };
    let hm = hm / scale;
    hm.iter().all(|v| v.is_finite()).then_some(hm)
}

/// The null vector and `σ_second_smallest / σ_max` (how well determined it is).
fn null_space_with_gap(a: &DMatrix<f64>) -> Option<(DVector<f64>, f64)> {
    let cols = a.ncols();
    // Pad to at least as many rows as columns so the thin SVD has all right vectors.
    let m = if a.nrows() < cols {
        let mut p = DMatrix::zeros(cols, cols);
        p.rows_mut(0, a.nrows()).copy_from(a);
        p
    } else {
        a.clone()
    };
    let svd = m.svd(false, true);
    let vt = svd.v_t?;
    let s = &svd.singular_values;
    let mut order: Vec<usize> = (0..s.len()).collect();
    order.sort_by(|&i, &j| s[i].total_cmp(&s[j]));
    let smallest = order[0];
    let second = s[order[1]];
    let max = s[order[order.len() - 1]];
    let v = vt.row(smallest).transpose();
    Some((v, if max > 0.0 { second / max } else { 0.0 }))
}

/// Zhang's `v_ij` row for homography `h` (columns h1, h2, h3).
fn v_row(h: &Matrix3<f64>, i: usize, j: usize) -> [f64; 6] {
    let hi = h.column(i);
    let hj = h.column(j);
    [
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    ]
}

/// Zhang's closed-form intrinsics (zero skew) from board → image homographies.
pub fn zhang_intrinsics(
    homographies: &[Matrix3<f64>],
    width: usize,
    height: usize,
) -> Result<Intrinsics, String> {
    if homographies.len() < 3 {
        return Err(format!("need at least 3 views, got {}", homographies.len()));
    }
    let s = width.max(height).max(1) as f64;
    let (c0x, c0y) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
    let norm = Matrix3::new(
        1.0 / s,
        0.0,
        -c0x / s,
        0.0,
        1.0 / s,
        -c0y / s,
        0.0,
        0.0,
        1.0,
    );
    let m = homographies.len();
    let mut v = DMatrix::<f64>::zeros(2 * m + 1, 6);
    for (k, h) in homographies.iter().enumerate() {
        let mut hn = norm * h;
        hn /= hn.norm();
        let v12 = v_row(&hn, 0, 1);
        let v11 = v_row(&hn, 0, 0);
        let v22 = v_row(&hn, 1, 1);
        for j in 0..6 {
            v[(2 * k, j)] = v12[j];
            v[(2 * k + 1, j)] = v11[j] - v22[j];
        }
    }
    // Zero skew: B12 = 0.
    v[(2 * m, 1)] = 1.0;
    let (b, gap) = null_space_with_gap(&v).ok_or("the intrinsics system has no solution")?;
    if gap < 1e-9 {
        return Err(
            "the views do not constrain the intrinsics (boards parallel to each other, e.g. all \
             facing the camera): tilt the board differently in each view"
                .into(),
        );
    }
    let sign = if b[0] < 0.0 { -1.0 } else { 1.0 };
    let [b11, b12, b22, b13, b23, b33] = [b[0], b[1], b[2], b[3], b[4], b[5]].map(|x| x * sign);
    let den = b11 * b22 - b12 * b12;
    let bad = || {
        "the views give no positive-definite image of the absolute conic (too few or degenerate \
         views)"
            .to_string()
    };
    if !(b11 > 0.0 && den > 0.0) {
        return Err(bad());
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    if lambda / b11 <= 0.0 || (lambda / b11).is_nan() {
        return Err(bad());
    }
    let alpha = (lambda / b11).sqrt();
    let beta = (lambda * b11 / den).sqrt();
    let gamma = -b12 * alpha * alpha * beta / lambda;
    let u0 = gamma * v0 / beta - b13 * alpha * alpha / lambda;
    let kn = Matrix3::new(alpha, gamma, u0, 0.0, beta, v0, 0.0, 0.0, 1.0);
    let k = norm.try_inverse().ok_or_else(bad)? * kn;
    let out = Intrinsics {
        fx: k[(0, 0)],
        fy: k[(1, 1)],
        cx: k[(0, 2)],
        cy: k[(1, 2)],
        skew: 0.0,
    };
    if [out.fx, out.fy, out.cx, out.cy]
        .iter()
        .all(|v| v.is_finite())
        && out.fx > 0.0
        && out.fy > 0.0
    {
        Ok(out)
    } else {
        Err(bad())
    }
}

/// Zhang's closed-form extrinsics of one view: `camera_from_board` rotation and translation.
pub fn zhang_extrinsics(k: &Intrinsics, h: &Matrix3<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    let kinv = to_na(&super::camera::k_matrix(k)).try_inverse()?;
    let a = kinv * h;
    let n1 = a.column(0).norm();
    if n1 == 0.0 {
        return None;
    }
    let mut lambda = 1.0 / n1;
    if (a[(2, 2)] * lambda) < 0.0 {
        lambda = -lambda; // the board is in front of the camera
    }
    let r1 = a.column(0) * lambda;
    let r2 = a.column(1) * lambda;
    let r3 = r1.cross(&r2);
    let t = a.column(2) * lambda;
    let r = Matrix3::from_columns(&[r1, r2, r3]);
    Some((nearest_rotation(&r)?, Vector3::new(t[0], t[1], t[2])))
}

/// The parameter layout of [`lm_calibration`].
#[derive(Debug, Clone, Copy)]
struct Layout {
    fix_aspect: bool,
    /// Which of k1, k2, p1, p2, k3 are free.
    free: [bool; 5],
    views: usize,
}

impl Layout {
    fn intrinsic_count(&self) -> usize {
        if self.fix_aspect { 3 } else { 4 }
    }
    fn global_count(&self) -> usize {
        self.intrinsic_count() + self.free.iter().filter(|&&f| f).count()
    }
    fn len(&self) -> usize {
        self.global_count() + 6 * self.views
    }

    fn pack(&self, k: &Intrinsics, d: &[f64; 5], poses: &[([f64; 3], [f64; 3])]) -> Vec<f64> {
        let mut p = if self.fix_aspect {
            vec![k.fy, k.cx, k.cy]
        } else {
            vec![k.fx, k.fy, k.cx, k.cy]
        };
        p.extend((0..5).filter(|&i| self.free[i]).map(|i| d[i]));
        for (w, t) in poses {
            p.extend_from_slice(w);
            p.extend_from_slice(t);
        }
        p
    }

    fn lens(&self, p: &[f64]) -> (Intrinsics, [f64; 5]) {
        let k = if self.fix_aspect {
            Intrinsics {
                fx: p[0],
                fy: p[0],
                cx: p[1],
                cy: p[2],
                skew: 0.0,
            }
        } else {
            Intrinsics {
                fx: p[0],
                fy: p[1],
                cx: p[2],
                cy: p[3],
                skew: 0.0,
            }
        };
        let mut d = [0.0; 5];
        let mut at = self.intrinsic_count();
        for (i, di) in d.iter_mut().enumerate() {
            if self.free[i] {
                *di = p[at];
                at += 1;
            }
        }
        (k, d)
    }

    fn view(&self, p: &[f64], v: usize) -> ([f64; 3], [f64; 3]) {
        let at = self.global_count() + 6 * v;
        (
            [p[at], p[at + 1], p[at + 2]],
            [p[at + 3], p[at + 4], p[at + 5]],
        )
    }
}

/// Residuals (projected − observed, x then y) of one view.
fn view_residuals(
    k: &Intrinsics,
    d: &[f64; 5],
    w: [f64; 3],
    t: [f64; 3],
    object: &[[f64; 2]],
    observed: &[[f64; 2]],
    out: &mut [f64],
) {
    let r = rodrigues(w);
    let lens = Lens {
        k: *k,
        distortion: Distortion::RadialTangential(*d),
    };
    for ((o, im), res) in object.iter().zip(observed).zip(out.chunks_exact_mut(2)) {
        let x = r[(0, 0)] * o[0] + r[(0, 1)] * o[1] + t[0];
        let y = r[(1, 0)] * o[0] + r[(1, 1)] * o[1] + t[1];
        let z = r[(2, 0)] * o[0] + r[(2, 1)] * o[1] + t[2];
        let px = lens.to_pixel(lens.distort([x / z, y / z]));
        res[0] = px[0] - im[0];
        res[1] = px[1] - im[1];
    }
}

fn all_residuals(l: &Layout, p: &[f64], object: &[[f64; 2]], views: &[Vec<[f64; 2]>]) -> Vec<f64> {
    let (k, d) = l.lens(p);
    let n = object.len();
    let mut r = vec![0.0; 2 * n * views.len()];
    for (v, (obs, out)) in views.iter().zip(r.chunks_exact_mut(2 * n)).enumerate() {
        let (w, t) = l.view(p, v);
        view_residuals(&k, &d, w, t, object, obs, out);
    }
    r
}

/// Central-difference step for parameter value `x`.
fn step_for(x: f64) -> f64 {
    1e-6 * x.abs().max(1e-2)
}

/// The calibration as a least-squares problem for [`lm::levenberg_marquardt`]: intrinsics, the
/// free distortion terms and the per-view poses, residuals the reprojection errors.
struct CalibrationProblem<'a> {
    layout: Layout,
    object: &'a [[f64; 2]],
    views: &'a [Vec<[f64; 2]>],
}

impl Problem for CalibrationProblem<'_> {
    fn num_params(&self) -> usize {
        self.layout.len()
    }

    fn num_residuals(&self) -> usize {
        2 * self.object.len() * self.views.len()
    }

    fn residuals(&self, p: &[f64], r: &mut [f64]) {
        let (k, d) = self.layout.lens(p);
        let n = self.object.len();
        for (v, (obs, out)) in self.views.iter().zip(r.chunks_exact_mut(2 * n)).enumerate() {
            let (w, t) = self.layout.view(p, v);
            view_residuals(&k, &d, w, t, self.object, obs, out);
        }
    }

    /// Central differences exploiting the block structure: a global parameter (intrinsics,
    /// distortion) moves every residual, a pose parameter only its own view's. Columns are
    /// filled in parallel, each by a fixed computation: deterministic.
    fn jacobian(&self, p: &[f64], jacobian: &mut DMatrix<f64>) {
        let l = &self.layout;
        let (object, views) = (self.object, self.views);
        let n = object.len();
        let rows = 2 * n * views.len();
        let g = l.global_count();
        jacobian.fill(0.0);
        // Column-major storage: one contiguous column per parameter.
        jacobian
            .as_mut_slice()
            .par_chunks_mut(rows)
            .enumerate()
            .for_each(|(j, col)| {
                let h = step_for(p[j]);
                let mut pp = p.to_vec();
                pp[j] = p[j] + h;
                if j < g {
                    let plus = all_residuals(l, &pp, object, views);
                    pp[j] = p[j] - h;
                    let minus = all_residuals(l, &pp, object, views);
                    for ((c, a), b) in col.iter_mut().zip(&plus).zip(&minus) {
                        *c = (a - b) / (2.0 * h);
                    }
                } else {
                    let v = (j - g) / 6;
                    let (k, d) = l.lens(p);
                    let mut plus = vec![0.0; 2 * n];
                    let mut minus = vec![0.0; 2 * n];
                    let (w, t) = l.view(&pp, v);
                    view_residuals(&k, &d, w, t, object, &views[v], &mut plus);
                    pp[j] = p[j] - h;
                    let (w, t) = l.view(&pp, v);
                    view_residuals(&k, &d, w, t, object, &views[v], &mut minus);
                    let at = 2 * n * v;
                    for ((c, a), b) in col[at..at + 2 * n].iter_mut().zip(&plus).zip(&minus) {
                        *c = (a - b) / (2.0 * h);
                    }
                }
            });
    }
}

/// Levenberg–Marquardt refinement of a planar calibration (the shared solver of [`lm`]):
/// intrinsics, the free distortion terms and the per-view poses, minimizing the summed squared
/// reprojection error; stops when the cost drops by less than 1e-15 relative or the step is
/// below 1e-12 relative. Returns the parameters and the iterations run.
fn lm_calibration(
    l: &Layout,
    p: Vec<f64>,
    object: &[[f64; 2]],
    views: &[Vec<[f64; 2]>],
    max_iterations: usize,
) -> (Vec<f64>, usize) {
    let problem = CalibrationProblem {
        layout: *l,
        object,
        views,
    };
    let report = lm::levenberg_marquardt(
        &problem,
        &p,
        &LmOptions {
            max_iterations,
            cost_tolerance: 1e-15,
            step_tolerance: 1e-12,
            ..LmOptions::default()
        },
    );
    (report.x, report.iterations)
}

/// Zhang's planar calibration: `object` are board-plane points (z = 0) and `views` their
/// detected pixels in each view (same order and count). See the module docs.
pub fn calibrate_planar(
    object: &[[f64; 2]],
    views: &[Vec<[f64; 2]>],
    width: usize,
    height: usize,
    opts: &CalibrationOptions,
) -> Result<Calibration, String> {
    if views.len() < 3 {
        return Err(format!(
            "calibration needs at least 3 views of the board, got {}",
            views.len()
        ));
    }
    if object.len() < 4 {
        return Err("the board needs at least 4 points".into());
    }
    for (i, v) in views.iter().enumerate() {
        if v.len() != object.len() {
            return Err(format!(
                "view {i} has {} points, the board has {}",
                v.len(),
                object.len()
            ));
        }
        if v.iter().flatten().any(|x| !x.is_finite()) {
            return Err(format!("view {i} has a non-finite point"));
        }
    }
    let homographies: Vec<Matrix3<f64>> = views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            calib_homography_dlt(object, v)
                .ok_or_else(|| format!("view {i}: the points are degenerate (collinear?)"))
        })
        .collect::<Result<_, _>>()?;
    let mut k = zhang_intrinsics(&homographies, width, height)?;
    if opts.fix_aspect_ratio {
        let f = 0.5 * (k.fx + k.fy);
        k.fx = f;
        k.fy = f;
    }
    let mut poses = Vec::with_capacity(views.len());
    for (i, h) in homographies.iter().enumerate() {
        let (r, t) =
            zhang_extrinsics(&k, h).ok_or_else(|| format!("view {i}: no pose from homography"))?;
        poses.push((angle_axis(&r), [t[0], t[1], t[2]]));
    }
    let free = match opts.distortion {
        CalibDistortion::None => [false; 5],
        CalibDistortion::K1 => [true, false, false, false, false],
        CalibDistortion::K1K2 => [true, true, false, false, false],
        CalibDistortion::K1K2P1P2 => [true, true, true, true, false],
        CalibDistortion::Full => [true; 5],
    };
    let free = if opts.zero_tangent {
        [free[0], free[1], false, false, free[4]]
    } else {
        free
    };
    let mut dist = [0.0; 5];
    if free[0] {
        let [k1, k2] = zhang_radial(&k, &poses, object, views);
        if k1.is_finite() && k2.is_finite() && k1.abs() < 1.0 && k2.abs() < 1.0 {
            dist[0] = k1;
            if free[1] {
                dist[1] = k2;
            }
        }
    }
    let layout = Layout {
        fix_aspect: opts.fix_aspect_ratio,
        free,
        views: views.len(),
    };
    let p0 = layout.pack(&k, &dist, &poses);
    let (p, iterations) = lm_calibration(&layout, p0, object, views, opts.max_iterations);
    let (k, d) = layout.lens(&p);
    let r = all_residuals(&layout, &p, object, views);
    let n = object.len();
    let total: f64 = r.iter().map(|v| v * v).sum();
    let rms = (total / (n * views.len()) as f64).sqrt();
    let view_rms = r
        .chunks_exact(2 * n)
        .map(|c| (c.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt())
        .collect();
    let poses = (0..views.len())
        .map(|v| {
            let (w, t) = layout.view(&p, v);
            pose_from_rt(&rodrigues(w), &Vector3::new(t[0], t[1], t[2]))
        })
        .collect();
    if !(rms.is_finite() && k.fx > 0.0 && k.fy > 0.0) {
        return Err("calibration diverged".into());
    }
    Ok(Calibration {
        lens: Lens {
            k,
            distortion: Distortion::RadialTangential(d),
        },
        poses,
        rms,
        view_rms,
        iterations,
    })
}

/// Zhang's linear least squares for `k1, k2` given the pinhole model.
fn zhang_radial(
    k: &Intrinsics,
    poses: &[([f64; 3], [f64; 3])],
    object: &[[f64; 2]],
    views: &[Vec<[f64; 2]>],
) -> [f64; 2] {
    let mut ata = nalgebra::Matrix2::<f64>::zeros();
    let mut atb = nalgebra::Vector2::<f64>::zeros();
    let lens = Lens::pinhole(*k);
    for ((w, t), obs) in poses.iter().zip(views) {
        let r = rodrigues(*w);
        for (o, im) in object.iter().zip(obs) {
            let pc = r * Vector3::new(o[0], o[1], 0.0) + Vector3::new(t[0], t[1], t[2]);
            let (x, y) = (pc[0] / pc[2], pc[1] / pc[2]);
            let r2 = x * x + y * y;
            let ideal = lens.to_pixel([x, y]);
            for (c, (du, obs_c)) in [(ideal[0] - k.cx, im[0]), (ideal[1] - k.cy, im[1])]
                .into_iter()
                .enumerate()
            {
                let row = nalgebra::Vector2::new(du * r2, du * r2 * r2);
                ata += row * row.transpose();
                atb += row * (obs_c - ideal[c]);
            }
        }
    }
    match ata.try_inverse() {
        Some(inv) => {
            let s = inv * atb;
            [s[0], s[1]]
        }
        None => [0.0, 0.0],
    }
}

/// Board layout and shading of [`render_board_view`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardRender {
    /// Inner corners per row.
    pub cols: usize,
    /// Inner corners per column.
    pub rows: usize,
    /// Square side (board units).
    pub square: f64,
    /// Gray level of dark squares.
    pub dark: f64,
    /// Gray level of light squares and of the one-square quiet zone around the board.
    pub light: f64,
    /// Gray level beyond the quiet zone (and where the ray misses the plane).
    pub background: f64,
    /// Samples per pixel side (antialiasing: `supersample²` rays per pixel).
    pub supersample: usize,
}

/// Renders a chessboard plane through a distorted camera: gray u8, `width × height`. The board
/// lies in its plane z = 0 with inner corners at [`board_points`]; squares `(i, j)` (with
/// `i = ⌊x/square⌋`, `j = ⌊y/square⌋`, `-1 ≤ i < cols`, `-1 ≤ j < rows`) are dark when `i + j` is
/// even. Each output pixel averages `supersample²` rays, each found by inverse mapping:
/// sub-pixel position → [`Lens::unproject`] (undistortion) → ray → intersection with the plane
/// (`pose` is `camera_from_board`) → board colour. Deterministic (rows in parallel, each pixel
/// computed alone), so the output is bit-identical for any thread count.
pub fn render_board_view(
    lens: &Lens,
    pose: &Pose,
    board: &BoardRender,
    width: usize,
    height: usize,
) -> Result<Image, String> {
    let s = board.supersample.max(1);
    let r = to_na(&pose.rotation_matrix());
    let t = Vector3::from(pose.translation);
    let rt = r.transpose();
    let centre = -(rt * t); // camera centre in board coordinates
    let (cols, rows, sq) = (board.cols as f64, board.rows as f64, board.square);
    let shade = |ray: [f64; 3]| -> f64 {
        let d = rt * Vector3::from(ray);
        if d[2] == 0.0 {
            return board.background;
        }
        let lambda = -centre[2] / d[2];
        if lambda <= 0.0 || lambda.is_nan() {
            return board.background;
        }
        let (bx, by) = (
            (centre[0] + lambda * d[0]) / sq,
            (centre[1] + lambda * d[1]) / sq,
        );
        let (i, j) = (bx.floor(), by.floor());
        if i >= -1.0 && i < cols && j >= -1.0 && j < rows {
            if (i as i64 + j as i64).rem_euclid(2) == 0 {
                board.dark
            } else {
                board.light
            }
        } else if i >= -2.0 && i < cols + 1.0 && j >= -2.0 && j < rows + 1.0 {
            board.light
        } else {
            board.background
        }
    };
    let mut out = vec![0u8; width * height];
    if width > 0 {
        out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
            for (x, px) in row.iter_mut().enumerate() {
                let mut acc = 0.0;
                for j in 0..s {
                    for i in 0..s {
                        let u = x as f64 - 0.5 + (i as f64 + 0.5) / s as f64;
                        let v = y as f64 - 0.5 + (j as f64 + 0.5) / s as f64;
                        acc += match lens.unproject([u, v]) {
                            Some(ray) => shade(ray),
                            None => board.background,
                        };
                    }
                }
                *px = (acc / (s * s) as f64).round().clamp(0.0, 255.0) as u8;
            }
        });
    }
    Image::from_u8(width, height, Channels::Gray, out).map_err(|e| e.to_string())
}

/// The `(cols, rows)` of a row-major grid of corners: among the factorizations `n = cols·rows`
/// (both ≥ 2), the one whose board → image homography fits the points best (a wrong layout
/// breaks the rows apart and fits far worse). `None` when no factorization fits within 2 px RMS
/// per point relative to the grid spacing.
pub fn infer_layout(points: &[[f64; 2]]) -> Option<(usize, usize)> {
    let n = points.len();
    let mut best: Option<(f64, (usize, usize))> = None;
    for cols in 2..=n / 2 {
        if !n.is_multiple_of(cols) || n / cols < 2 {
            continue;
        }
        let rows = n / cols;
        let object = board_points(cols, rows, 1.0);
        let Some(h) = calib_homography_dlt(&object, points) else {
            continue;
        };
        let err = object
            .iter()
            .zip(points)
            .map(|(o, p)| {
                let v = h * Vector3::new(o[0], o[1], 1.0);
                (v[0] / v[2] - p[0]).powi(2) + (v[1] / v[2] - p[1]).powi(2)
            })
            .sum::<f64>()
            / n as f64;
        if err.is_finite() && best.is_none_or(|(e, _)| err < e) {
            best = Some((err, (cols, rows)));
        }
    }
    let (err, layout) = best?;
    // Grid spacing in pixels: mean distance between neighbours within rows.
    let (cols, _) = layout;
    let spacing = points
        .windows(2)
        .enumerate()
        .filter(|(i, _)| (i + 1) % cols != 0)
        .map(|(_, w)| (w[0][0] - w[1][0]).hypot(w[0][1] - w[1][1]))
        .sum::<f64>()
        / (n - n / cols) as f64;
    (err.sqrt() < 0.2 * spacing).then_some(layout)
}

/// Planar camera calibration (`geometry.calibrate`). See [`calibrate_planar`].
#[derive(Debug, Clone, PartialEq)]
pub struct Calibrate {
    cols: Option<usize>,
    rows: Option<usize>,
    square: f64,
    image_size: Option<[u32; 2]>,
    options: CalibrationOptions,
}

impl Op for Calibrate {
    type Params = CalibrateParams;
    const ID: &'static str = "geometry.calibrate";
    const SUMMARY: &'static str = "Calibrates a camera (intrinsics and radial–tangential distortion) from chessboard corners seen in several views (Zhang's method + Levenberg–Marquardt).";
    const DOC: &'static str = r#"
Estimates the pinhole intrinsics (fx, fy, cx, cy; skew 0) and the distortion k1, k2, p1, p2, k3
of a camera from the inner corners of a planar chessboard seen in several views, like OpenCV's
`calibrateCamera`.

Input `corners`: a List of corner sets, one per view, each `cols × rows` points row-major (the
output of `detect.chessboard` mapped over the frames of `capture.sequence`). Views where the board
was not found (empty sets) are skipped; at least 3 views must remain. Without `cols`/`rows` the
layout is inferred from the first set: of the factorizations of its size, the one whose
board → image homography fits best (wrong layouts break rows apart and fit far worse). Input `image` (optional):
any image of the camera, for its size (or set `image_size`).

Method (Z. Zhang, "A flexible new technique for camera calibration", TPAMI 2000):
1. A homography per view (board plane → image) by the normalized DLT.
2. Closed-form intrinsics from B = K⁻ᵀK⁻¹ (h1ᵀBh2 = 0, h1ᵀBh1 = h2ᵀBh2 per view, plus B12 = 0 for
   zero skew), solved as the SVD null vector of the stacked system. Boards all parallel to one
   another (e.g. all facing the camera) leave it underdetermined: an error.
3. Closed-form poses r1 = λK⁻¹h1, r2 = λK⁻¹h2, r3 = r1 × r2, t = λK⁻¹h3, snapped to a rotation.
4. k1, k2 by Zhang's linear least squares.
5. Levenberg–Marquardt over intrinsics, the chosen distortion terms and the per-view poses
   (angle-axis + translation), minimizing the reprojection error.

Outputs: `camera` (radial–tangential camera with skew 0), `rms_px` (OpenCV's RMS reprojection
error sqrt(Σ‖r‖²/N) over all N corners, pixels), `poses` (camera_from_board of each used view,
translations in `square_size` units) and `metrics` (views_used, views_skipped, iterations,
rms_px).

Differences from OpenCV: OpenCV initializes with the principal point at the image centre and
solves only fx, fy linearly (then LM); this operator uses Zhang's full closed form. Its LM uses
a numerical (central-difference) Jacobian. `fix_aspect_ratio` means fx = fy.

Example (a node of a graph):
    "calib": (op: "geometry.calibrate", inputs: { "corners": "corners.corners", "image": "views.frames[0]" },
              params: (cols: 9, rows: 6, square_size: 0.025)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "corners",
                PortType::Points2D.list_of(),
                "chessboard corners of each view, cols × rows row-major (empty = not found)",
            ),
            PortSpec::new(
                "image",
                PortType::Image,
                "an image of the camera, for its size",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("camera", PortType::Camera, "intrinsics and distortion"),
            PortSpec::new("rms_px", PortType::Scalar, "RMS reprojection error, pixels"),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "camera_from_board of each used view",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "views_used, views_skipped, iterations, rms_px",
            ),
        ]
    }

    fn new(p: CalibrateParams) -> Result<Self, String> {
        for (name, v) in [("cols", p.cols), ("rows", p.rows)] {
            if let Some(v) = v
                && v < 2
            {
                return Err(format!("`{name}` must be at least 2, got {v}"));
            }
        }
        if !(p.square_size.is_finite() && p.square_size > 0.0) {
            return Err(format!(
                "`square_size` must be positive and finite, got {}",
                p.square_size
            ));
        }
        if let Some([w, h]) = p.image_size
            && (w == 0 || h == 0)
        {
            return Err(format!("`image_size` must be positive, got {w} × {h}"));
        }
        if !(1..=10000).contains(&p.max_iterations) {
            return Err(format!(
                "`max_iterations` must be in 1..=10000, got {}",
                p.max_iterations
            ));
        }
        Ok(Calibrate {
            cols: p.cols.map(|v| v as usize),
            rows: p.rows.map(|v| v as usize),
            square: p.square_size,
            image_size: p.image_size,
            options: CalibrationOptions {
                distortion: p.distortion,
                fix_aspect_ratio: p.fix_aspect_ratio,
                zero_tangent: p.zero_tangent,
                max_iterations: p.max_iterations as usize,
            },
        })
    }
}

impl Operator for Calibrate {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let (width, height) = match (inputs.get("image"), self.image_size) {
            (Some(Value::Image(img)), _) => (img.width(), img.height()),
            (_, Some([w, h])) => (w as usize, h as usize),
            _ => {
                return Err(OpError::input(
                    "image",
                    "connect an image (for the image size) or set `image_size`",
                ));
            }
        };
        let Value::List(list) = inputs.require("corners")? else {
            return Err(OpError::input("corners", "expected a List of Points2D"));
        };
        let mut sets = Vec::new();
        for item in &list.items {
            let Value::Points2D(pts) = item else {
                return Err(OpError::input("corners", "expected a List of Points2D"));
            };
            sets.push(pts);
        }
        let skipped = sets.iter().filter(|p| p.is_empty()).count();
        let first = sets.iter().find(|p| !p.is_empty()).ok_or_else(|| {
            OpError::failed("the board was found in no view (every corner set is empty)")
        })?;
        let (cols, rows) = match (self.cols, self.rows) {
            (Some(c), Some(r)) => (c, r),
            (Some(c), None) if c > 0 && first.len() % c == 0 => (c, first.len() / c),
            (None, Some(r)) if r > 0 && first.len() % r == 0 => (first.len() / r, r),
            (None, None) => infer_layout(first).ok_or_else(|| {
                OpError::input(
                    "corners",
                    format!(
                        "cannot tell the board layout of {} corners: set `cols` and `rows`",
                        first.len()
                    ),
                )
            })?,
            (c, r) => {
                return Err(OpError::input(
                    "corners",
                    format!("{} corners do not fit cols {c:?} × rows {r:?}", first.len()),
                ));
            }
        };
        let object = board_points(cols, rows, self.square);
        let mut views = Vec::new();
        for (i, pts) in sets.iter().enumerate() {
            if pts.is_empty() {
                continue;
            }
            if pts.len() != object.len() {
                return Err(OpError::input(
                    "corners",
                    format!(
                        "view {i} has {} corners, but cols × rows = {cols} × {rows} = {}",
                        pts.len(),
                        object.len()
                    ),
                ));
            }
            views.push(pts.to_vec());
        }
        let cal = calibrate_planar(&object, &views, width, height, &self.options)
            .map_err(OpError::failed)?;
        let mut metrics = Metrics::new();
        metrics.insert("views_used".into(), views.len() as f64);
        metrics.insert("views_skipped".into(), skipped as f64);
        metrics.insert("iterations".into(), cal.iterations as f64);
        metrics.insert("rms_px".into(), cal.rms);
        let camera = cal.lens.to_camera(width as u32, height as u32);
        Ok(Outputs::new()
            .with("camera", Value::Camera(Arc::new(camera)))
            .with("rms_px", Value::Scalar(cal.rms))
            .with(
                "poses",
                Value::list(
                    PortType::Pose,
                    cal.poses.into_iter().map(Value::Pose).collect(),
                ),
            )
            .with("metrics", Value::metrics(metrics)))
    }
}

/// The synthetic calibration scene of `graphs/data/calibration/`: a known camera, board and
/// poses. Rendered by [`render_board_view`]; the fixture test checks the committed PNGs are
/// reproduced bit-exactly.
pub mod fixture {
    use super::*;

    /// Image width of the views.
    pub const WIDTH: usize = 320;
    /// Image height of the views.
    pub const HEIGHT: usize = 240;
    /// Inner corners per row.
    pub const COLS: usize = 7;
    /// Inner corners per column.
    pub const ROWS: usize = 5;

    /// The true camera.
    pub fn lens() -> Lens {
        Lens {
            k: Intrinsics {
                fx: 300.0,
                fy: 298.0,
                cx: 162.5,
                cy: 118.0,
                skew: 0.0,
            },
            distortion: Distortion::RadialTangential([-0.22, 0.06, 0.0008, -0.0005, 0.0]),
        }
    }

    /// Board and shading.
    pub fn board() -> BoardRender {
        BoardRender {
            cols: COLS,
            rows: ROWS,
            square: 1.0,
            dark: 35.0,
            light: 215.0,
            background: 110.0,
            supersample: 4,
        }
    }

    /// `camera_from_board` of each view: the board centre at `(ox, oy, depth)` in the camera
    /// frame, turned by the angle-axis vector.
    pub fn poses() -> Vec<Pose> {
        let views: [([f64; 3], [f64; 3]); 10] = [
            ([0.45, 0.0, 0.05], [-0.6, -0.4, 12.5]),
            ([-0.5, 0.1, -0.05], [0.6, 0.4, 12.5]),
            ([0.0, 0.55, 0.1], [-0.9, 0.5, 13.0]),
            ([0.1, -0.55, 0.0], [0.9, -0.4, 13.0]),
            ([0.35, 0.35, 0.3], [0.3, 0.3, 12.5]),
            ([-0.3, -0.4, -0.2], [-0.3, -0.3, 13.5]),
            ([0.3, -0.3, -0.4], [-1.2, -0.8, 14.0]),
            ([-0.35, 0.3, 0.5], [1.0, 0.4, 14.5]),
            ([0.6, 0.2, 0.0], [0.0, 0.8, 13.5]),
            ([-0.2, -0.6, 0.2], [1.0, -0.6, 14.0]),
        ];
        let centre = Vector3::new((COLS as f64 - 1.0) / 2.0, (ROWS as f64 - 1.0) / 2.0, 0.0);
        views
            .iter()
            .map(|(w, o)| {
                let r = rodrigues(*w);
                let t = Vector3::from(*o) - r * centre;
                // The engine's own conversion: the rendered fixtures depend on these bits.
                Pose::from_rotation_matrix(&super::super::camera::from_na(&r), [t[0], t[1], t[2]])
            })
            .collect()
    }

    /// The views, in order.
    pub fn render_all() -> Result<Vec<Image>, String> {
        let lens = lens();
        poses()
            .iter()
            .map(|p| render_board_view(&lens, p, &board(), WIDTH, HEIGHT))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::image_io::{DecodeLimits, read_image, write_image};
    use std::path::PathBuf;

    fn project_board(lens: &Lens, pose: &Pose, object: &[[f64; 2]]) -> Vec<[f64; 2]> {
        let r = to_na(&pose.rotation_matrix());
        let t = Vector3::from(pose.translation);
        object
            .iter()
            .map(|o| {
                let p = r * Vector3::new(o[0], o[1], 0.0) + t;
                lens.project([p[0], p[1], p[2]]).unwrap()
            })
            .collect()
    }

    /// The fixture camera, its board, and the board's exact projection in every view.
    type FixtureViews = (Lens, Vec<[f64; 2]>, Vec<Vec<[f64; 2]>>);

    /// The fixture camera, its board and the exact projections of the board in every view.
    fn fixture_views() -> FixtureViews {
        let lens = fixture::lens();
        let object = board_points(fixture::COLS, fixture::ROWS, 1.0);
        let views = fixture::poses()
            .iter()
            .map(|p| project_board(&lens, p, &object))
            .collect();
        (lens, object, views)
    }

    fn fixture_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/data/calibration")
    }

    #[test]
    fn homography_dlt_exact() {
        let h = Matrix3::new(1.2, 0.1, 30.0, -0.05, 0.9, 20.0, 1e-3, -2e-3, 1.0);
        let src: Vec<[f64; 2]> = board_points(5, 4, 10.0);
        let dst: Vec<[f64; 2]> = src
            .iter()
            .map(|s| {
                let v = h * Vector3::new(s[0], s[1], 1.0);
                [v[0] / v[2], v[1] / v[2]]
            })
            .collect();
        let est = calib_homography_dlt(&src, &dst).unwrap();
        assert!((est - h).norm() < 1e-9, "{est}");
        let line: Vec<[f64; 2]> = (0..6).map(|i| [i as f64, 2.0 * i as f64]).collect();
        assert!(calib_homography_dlt(&line, &line).is_none());
    }

    #[test]
    fn exact_projections_give_the_exact_camera() {
        let (_, object, views) = fixture_views();
        let cal = calibrate_planar(
            &object,
            &views,
            fixture::WIDTH,
            fixture::HEIGHT,
            &CalibrationOptions::default(),
        )
        .unwrap();
        let k = cal.lens.k;
        assert!((k.fx - 300.0).abs() < 1e-6, "{k:?}");
        assert!((k.fy - 298.0).abs() < 1e-6);
        assert!((k.cx - 162.5).abs() < 1e-6);
        assert!((k.cy - 118.0).abs() < 1e-6);
        let Distortion::RadialTangential(d) = cal.lens.distortion else {
            panic!()
        };
        let want = [-0.22, 0.06, 0.0008, -0.0005, 0.0];
        for i in 0..5 {
            assert!((d[i] - want[i]).abs() < 1e-7, "{d:?}");
        }
        assert!(cal.rms < 1e-8, "{}", cal.rms);
        for (p, q) in cal.poses.iter().zip(fixture::poses()) {
            for i in 0..3 {
                assert!((p.translation[i] - q.translation[i]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn pinhole_without_distortion_and_options() {
        let lens = Lens::pinhole(Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            skew: 0.0,
        });
        let object = board_points(9, 6, 0.5);
        let views: Vec<Vec<[f64; 2]>> = [
            [0.4, 0.1, 0.0],
            [-0.3, 0.4, 0.2],
            [0.1, -0.5, -0.1],
            [0.3, 0.3, 1.0],
        ]
        .iter()
        .map(|w| {
            let r = rodrigues(*w);
            let t = Vector3::new(0.0, 0.0, 8.0) - r * Vector3::new(2.0, 1.25, 0.0);
            project_board(&lens, &pose_from_rt(&r, &t), &object)
        })
        .collect();
        for distortion in [
            CalibDistortion::None,
            CalibDistortion::K1,
            CalibDistortion::K1K2,
        ] {
            let opts = CalibrationOptions {
                distortion,
                fix_aspect_ratio: true,
                zero_tangent: true,
                max_iterations: 50,
            };
            let cal = calibrate_planar(&object, &views, 640, 480, &opts).unwrap();
            assert_eq!(cal.lens.k.fx, cal.lens.k.fy);
            assert!((cal.lens.k.fx - 500.0).abs() < 1e-6);
            assert!(cal.rms < 1e-8);
        }
    }

    #[test]
    fn layout_is_inferred() {
        let lens = fixture::lens();
        for (c, r) in [(7, 5), (5, 7), (9, 6), (6, 4)] {
            let object = board_points(c, r, 1.0);
            for pose in fixture::poses() {
                let pts = project_board(&lens, &pose, &object);
                assert_eq!(infer_layout(&pts), Some((c, r)));
            }
        }
        assert_eq!(infer_layout(&[[0.0, 0.0]; 7]), None);
    }

    #[test]
    fn too_few_or_parallel_views_are_errors() {
        let (lens, object, views) = fixture_views();
        let opts = CalibrationOptions::default();
        let err = calibrate_planar(&object, &views[..2], 320, 240, &opts).unwrap_err();
        assert!(err.contains("at least 3"), "{err}");
        // Boards all facing the camera (rotations about the optical axis only).
        let flat: Vec<Vec<[f64; 2]>> = [0.0, 0.3, -0.5, 1.0]
            .iter()
            .map(|&a| {
                let r = rodrigues([0.0, 0.0, a]);
                let t = Vector3::new(0.0, 0.0, 15.0) - r * Vector3::new(3.0, 2.0, 0.0);
                project_board(&Lens::pinhole(lens.k), &pose_from_rt(&r, &t), &object)
            })
            .collect();
        let err = calibrate_planar(&object, &flat, 320, 240, &opts).unwrap_err();
        assert!(err.contains("do not constrain"), "{err}");
        let mut short = views.clone();
        short[1].pop();
        assert!(calibrate_planar(&object, &short, 320, 240, &opts).is_err());
    }

    /// Writes the fixtures (run once with `--ignored` after changing the scene).
    #[test]
    #[ignore]
    fn write_calibration_fixtures() {
        let dir = fixture_dir();
        std::fs::create_dir_all(&dir).unwrap();
        for (i, img) in fixture::render_all().unwrap().iter().enumerate() {
            write_image(&dir.join(format!("view_{i:02}.png")), img).unwrap();
        }
    }

    #[test]
    fn fixtures_are_reproduced_bit_exactly() {
        let dir = fixture_dir();
        for (i, img) in fixture::render_all().unwrap().iter().enumerate() {
            let path = dir.join(format!("view_{i:02}.png"));
            let stored = read_image(&path, &DecodeLimits::default()).unwrap();
            assert_eq!(
                &stored,
                img,
                "{} differs from the generator",
                path.display()
            );
        }
    }

    #[test]
    fn calibrating_the_rendered_views_recovers_the_camera() {
        use crate::detect::chessboard::{ChessboardSettings, find_chessboard};
        let settings = ChessboardSettings {
            columns: fixture::COLS,
            rows: fixture::ROWS,
            sigma: 2.0,
            min_response: 0.03,
            refine_window: 5,
            refine_iterations: 40,
            refine_epsilon: 0.001,
        };
        let views: Vec<Vec<[f64; 2]>> = fixture::render_all()
            .unwrap()
            .iter()
            .map(|img| {
                let g: Vec<f32> = img.as_u8().unwrap().iter().map(|&v| f32::from(v)).collect();
                find_chessboard(&g, img.width(), img.height(), &settings)
                    .unwrap()
                    .corners
            })
            .collect();
        let object = board_points(fixture::COLS, fixture::ROWS, 1.0);
        let cal = calibrate_planar(
            &object,
            &views,
            fixture::WIDTH,
            fixture::HEIGHT,
            &CalibrationOptions::default(),
        )
        .unwrap();
        // Detection error against the true projections.
        let lens = fixture::lens();
        let mut err = Vec::new();
        for (pose, v) in fixture::poses().iter().zip(&views) {
            for (a, b) in project_board(&lens, pose, &object).iter().zip(v) {
                err.push((a[0] - b[0]).hypot(a[1] - b[1]));
            }
        }
        let mean_err = err.iter().sum::<f64>() / err.len() as f64;
        let k = cal.lens.k;
        let t = fixture::lens().k;
        let msg = format!(
            "{k:?} {:?} rms {} corner error mean {mean_err} max {}",
            cal.lens.distortion,
            cal.rms,
            err.iter().fold(0.0f64, |a, &b| a.max(b))
        );
        for (got, want) in [(k.fx, t.fx), (k.fy, t.fy), (k.cx, t.cx), (k.cy, t.cy)] {
            assert!((got - want).abs() < 0.005 * want, "{msg}");
        }
        let Distortion::RadialTangential(d) = cal.lens.distortion else {
            panic!()
        };
        assert!((d[0] + 0.22).abs() < 0.03, "k1 {}", d[0]);
        assert!(cal.rms < 0.2, "rms {}", cal.rms);
    }
}
