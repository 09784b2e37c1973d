//! Property tests at the extremes for the estimators that otherwise have only fixed-case tests:
//! homography, fundamental matrix, the shapes (line, circle, plane) and the 2-D/3-D transforms.
//!
//! Every property draws a coordinate **frame**: a log-uniform scale `s ∈ [1e-3, 1e6]` and an
//! offset of up to `10·s` per axis, and builds its data as `s·u + o` from a unit-frame
//! configuration `u` (points in `[0, 1]²` or `[0, 1]³`). Errors are measured geometrically
//! (transfer of probe points, distances of held-out true data, parameter differences) and
//! divided by `s`, so every tolerance is scale-relative:
//!
//! - exact data: every solver recovers the truth to ~1e-9 of the data's extent;
//! - 50–95 % outliers with small noise `σ = 1e-3·s`: LO-RANSAC with a fixed seed and confidence
//!   `1 − 1e-6` recovers a model within a few `σ` of the truth and finds ≥ 90 % of the true
//!   inliers (the outlier range per estimator is bounded by the trial count `∝ 1/wˢ`, so that
//!   each property stays within a second or two);
//! - f32-rounded data: the models move from the f64 ones by a small multiple of the rounding
//!   (f32 ε times the coordinates' magnitude relative to the extent);
//! - near-degenerate configurations (almost collinear for H/affine, almost planar or tiny
//!   baselines and points at infinity for F, points near the horizon for H, coincident points):
//!   the result is a typed error or a finite model that explains the data it claims as inliers.
//!
//! The number of cases of each property is moderate; `PROPTEST_CASES` overrides it, as it
//! overrides the default configuration of the other `proptest!` blocks.

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use proptest::prelude::*;

use super::fundamental::tests::Scene;
use super::fundamental::{FundamentalEstimator, eight_point, sampson_error2, seven_point};
use super::homography::{Correspondence, HomographyEstimator, dlt, four_point, transfer};
use super::ransac::{Method, RobustError, RobustOptions, RobustReport, estimate};
use super::robust::Estimator;
use super::shapes::{Circle, CircleEstimator, Line2, LineEstimator, Plane, PlaneEstimator};
use super::transforms::{
    Affine2, Affine2Estimator, Pair2, Pair3, Rigid3Estimator, Similarity2Estimator, Similarity3,
    Similarity3Estimator, fit_affine2, fit_similarity2, umeyama,
};
use crate::describe::brief::SplitMix64;

/// `cases`, unless `PROPTEST_CASES` is set (which then wins, as for the default config).
/// The properties' cases: `cases` of them (`PROPTEST_CASES` overrides), drawn from a fixed seed
/// (`PROPTEST_RNG_SEED` overrides) so a run is reproducible — several properties bound noisy
/// estimates by a multiple of σ, which a long enough random run exceeds by chance; stress them
/// with other seeds and more cases.
fn config(cases: u32) -> ProptestConfig {
    let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse().ok());
    ProptestConfig {
        cases: env("PROPTEST_CASES").map_or(cases, |c: u64| c as u32),
        rng_seed: proptest::test_runner::RngSeed::Fixed(
            env("PROPTEST_RNG_SEED").unwrap_or(20_261_201),
        ),
        ..ProptestConfig::default()
    }
}

const F32_EPS: f64 = f32::EPSILON as f64;

/// A data frame: `x = scale·u + offset`.
#[derive(Debug, Clone, Copy)]
struct Frame {
    scale: f64,
    offset: [f64; 3],
}

impl Frame {
    /// `log_scale` in [-3, 6]; `offset` in units of the scale.
    fn new(log_scale: f64, offset: [f64; 3]) -> Frame {
        let scale = 10f64.powf(log_scale);
        Frame {
            scale,
            offset: offset.map(|o| o * scale),
        }
    }
    fn p2(&self, u: [f64; 2]) -> [f64; 2] {
        [
            self.scale * u[0] + self.offset[0],
            self.scale * u[1] + self.offset[1],
        ]
    }
    fn p3(&self, u: [f64; 3]) -> [f64; 3] {
        [
            self.scale * u[0] + self.offset[0],
            self.scale * u[1] + self.offset[1],
            self.scale * u[2] + self.offset[2],
        ]
    }
    fn back2(&self, p: [f64; 2]) -> [f64; 2] {
        [
            (p[0] - self.offset[0]) / self.scale,
            (p[1] - self.offset[1]) / self.scale,
        ]
    }
    /// Largest coordinate magnitude of the unit box's image, relative to the scale (how much
    /// larger the coordinates are than the extent: the f32 rounding factor).
    fn magnitude(&self) -> f64 {
        1.0 + self.offset.iter().fold(0.0f64, |a, o| a.max(o.abs())) / self.scale
    }
}

fn frame() -> impl Strategy<Value = Frame> {
    (-3.0f64..6.0, prop::array::uniform3(-10.0f64..10.0)).prop_map(|(e, o)| Frame::new(e, o))
}

fn f32_round(v: f64) -> f64 {
    f64::from(v as f32)
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

fn finite(m: &[f64]) -> bool {
    m.iter().all(|v| v.is_finite())
}

fn shuffle<T>(rng: &mut SplitMix64, data: &mut [T], truth: &mut [bool]) {
    for i in (1..data.len()).rev() {
        let j = rng.below(i + 1);
        data.swap(i, j);
        truth.swap(i, j);
    }
}

/// A random unit-frame homography: a rotation–zoom with some shear, a translation and
/// perspective terms small enough that `w ∈ [0.4, 1.6]` over `[0, 1]²`.
fn random_h(rng: &mut SplitMix64) -> Matrix3<f64> {
    let a = (rng.uniform() - 0.5) * 1.5;
    let z = 0.7 + 0.6 * rng.uniform();
    let mut m = [0.0; 4];
    for v in &mut m {
        *v = 0.2 * (rng.uniform() - 0.5);
    }
    let (c, s) = (z * a.cos(), z * a.sin());
    Matrix3::new(
        c + m[0],
        -s + m[1],
        0.3 * (rng.uniform() - 0.5),
        s + m[2],
        c + m[3],
        0.3 * (rng.uniform() - 0.5),
        0.6 * (rng.uniform() - 0.5),
        0.6 * (rng.uniform() - 0.5),
        1.0,
    )
}

/// Largest distance (unit frame) between the truth `h_u` and the estimate `h` over a 5×5
/// grid of `[0, 1]²`; infinite if a probe does not transfer.
fn h_probe_error(h: &Matrix3<f64>, h_u: &Matrix3<f64>, f1: &Frame, f2: &Frame) -> f64 {
    let mut worst = 0.0f64;
    for i in 0..5 {
        for j in 0..5 {
            let u = [i as f64 / 4.0, j as f64 / 4.0];
            let (Some(truth), Some(got)) = (transfer(h_u, &u), transfer(h, &f1.p2(u))) else {
                return f64::INFINITY;
            };
            worst = worst.max(dist2(f2.back2(got), truth));
        }
    }
    worst
}

/// One unit-frame point per corner box of `[0, 1]²` (no three nearly collinear).
fn spread_quad(rng: &mut SplitMix64) -> [[f64; 2]; 4] {
    let mut c = |lo: bool| {
        let base = if lo { 0.05 } else { 0.7 };
        base + 0.25 * rng.uniform()
    };
    [
        [c(true), c(true)],
        [c(false), c(true)],
        [c(true), c(false)],
        [c(false), c(false)],
    ]
}

fn h_pair(h_u: &Matrix3<f64>, u: [f64; 2], f1: &Frame, f2: &Frame) -> Option<Correspondence> {
    transfer(h_u, &u).map(|v| [f1.p2(u), f2.p2(v)])
}

/// A random two-view scene in pixels (640 × 480, f = 500) with a baseline of `baseline`.
fn random_scene(rng: &mut SplitMix64, baseline: f64) -> Scene {
    let mut scene = Scene::new();
    let mut r = || (rng.uniform() - 0.5) * 0.4;
    scene.r = Rotation3::from_euler_angles(r(), r(), r()).into_inner();
    let t = Vector3::new(1.0, r(), r());
    scene.t = t.normalize() * baseline;
    scene
}

/// A scene point in front of both cameras at depth `7 ± spread/2`.
fn scene_point(rng: &mut SplitMix64, spread: f64) -> Vector3<f64> {
    let z = 7.0 + spread * (rng.uniform() - 0.5);
    Vector3::new(
        (rng.uniform() - 0.5) * z * 1.2,
        (rng.uniform() - 0.5) * z * 0.9,
        z,
    )
}

/// A pixel correspondence mapped to the frames (pixels / 640 is the unit frame).
fn f_pair(c: Correspondence, f1: &Frame, f2: &Frame) -> Correspondence {
    let u = |p: [f64; 2]| [p[0] / 640.0, p[1] / 640.0];
    [f1.p2(u(c[0])), f2.p2(u(c[1]))]
}

/// Largest Sampson distance (unit frame) of `held_out` under `f`.
fn f_held_out_error(f: &Matrix3<f64>, held_out: &[Correspondence], scale: f64) -> f64 {
    held_out
        .iter()
        .map(|c| sampson_error2(f, c).sqrt() / scale)
        .fold(0.0f64, f64::max)
}

/// σ₃ / σ₁ of `f` (0 for rank 2).
fn rank2_ratio(f: &Matrix3<f64>) -> f64 {
    let s = f.singular_values();
    let (mx, mn) = s
        .iter()
        .fold((0.0f64, f64::INFINITY), |(a, b), &v| (a.max(v), b.min(v)));
    mn / mx
}

/// Checks what every successful robust report guarantees: a finite model, a mask that is
/// exactly `residual ≤ t²` on the data, at least a minimal sample of inliers.
fn check_report<E: Estimator>(
    estimator: &E,
    data: &[E::Datum],
    threshold: f64,
    report: &RobustReport<E::Model>,
    model_is_finite: impl Fn(&E::Model) -> bool,
) -> Result<(), TestCaseError> {
    prop_assert!(model_is_finite(&report.model), "non-finite model");
    let mut r = vec![0.0; data.len()];
    estimator.residuals(&report.model, data, &mut r);
    let t2 = threshold * threshold;
    for (i, (&ri, &m)) in r.iter().zip(&report.inlier_mask).enumerate() {
        prop_assert_eq!(m, ri <= t2, "mask of datum {} (residual {})", i, ri);
    }
    let count = report.inlier_mask.iter().filter(|&&m| m).count();
    prop_assert_eq!(count, report.num_inliers);
    prop_assert!(report.num_inliers >= E::MIN_SAMPLES);
    prop_assert!(report.score.is_finite());
    Ok(())
}

fn lo_options(threshold: f64, seed: u64) -> RobustOptions {
    RobustOptions {
        method: Method::LoRansac,
        threshold,
        confidence: 1.0 - 1e-6,
        max_trials: 2_000_000,
        seed,
        ..RobustOptions::default()
    }
}

fn true_positives(mask: &[bool], truth: &[bool]) -> usize {
    crate::geometry::ransac::tests::true_positives(mask, truth)
}

fn h_finite(h: &Matrix3<f64>) -> bool {
    finite(h.as_slice())
}

// ----- shapes -----

fn line_distance(m: &Line2, p: [f64; 2]) -> f64 {
    (m.normal[0] * p[0] + m.normal[1] * p[1] + m.offset).abs()
}

fn line_finite(m: &Line2) -> bool {
    finite(&m.normal) && m.offset.is_finite()
}

fn circle_finite(m: &Circle) -> bool {
    finite(&m.center) && m.radius.is_finite() && m.radius > 0.0
}

fn plane_distance(m: &Plane, p: [f64; 3]) -> f64 {
    (m.normal[0] * p[0] + m.normal[1] * p[1] + m.normal[2] * p[2] + m.offset).abs()
}

fn plane_finite(m: &Plane) -> bool {
    finite(&m.normal) && m.offset.is_finite()
}

/// A unit-frame line: a point in `[0, 1]²` and a unit direction.
fn random_line(rng: &mut SplitMix64) -> ([f64; 2], [f64; 2]) {
    let a = std::f64::consts::PI * rng.uniform();
    ([rng.uniform(), rng.uniform()], [a.cos(), a.sin()])
}

fn on_line(c: [f64; 2], d: [f64; 2], tau: f64) -> [f64; 2] {
    [c[0] + tau * d[0], c[1] + tau * d[1]]
}

/// Unit-frame circle: centre, radius, first angle, arc span in [π/3, 2π].
fn random_circle(rng: &mut SplitMix64) -> ([f64; 2], f64, f64, f64) {
    let pi = std::f64::consts::PI;
    (
        [rng.uniform(), rng.uniform()],
        0.2 + 0.8 * rng.uniform(),
        2.0 * pi * rng.uniform(),
        pi / 3.0 + 5.0 * pi / 3.0 * rng.uniform(),
    )
}

/// Unit-frame plane: a point in `[0, 1]³`, its unit normal and two in-plane unit axes.
fn random_plane(rng: &mut SplitMix64) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    let c = Vector3::new(rng.uniform(), rng.uniform(), rng.uniform());
    let n = loop {
        let v = Vector3::new(rng.normal(), rng.normal(), rng.normal());
        if v.norm() > 1e-3 {
            break v.normalize();
        }
    };
    let helper = if n.x.abs() < 0.6 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = n.cross(&helper).normalize();
    let e2 = n.cross(&e1);
    (c, n, e1, e2)
}

fn v3(v: Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

// ----- transforms -----

fn apply_affine(m: &Affine2, p: [f64; 2]) -> [f64; 2] {
    [
        m[0] * p[0] + m[1] * p[1] + m[2],
        m[3] * p[0] + m[4] * p[1] + m[5],
    ]
}

/// A random well-conditioned affine map in the data frame (translation up to `10·s`).
fn random_affine(rng: &mut SplitMix64, scale: f64) -> Affine2 {
    let a = (rng.uniform() - 0.5) * 6.0;
    let z = 0.5 + rng.uniform();
    let mut sh = || 0.3 * (rng.uniform() - 0.5);
    let (c, s) = (z * a.cos(), z * a.sin());
    let m = [c + sh(), -s + sh(), 0.0, s + sh(), c + sh(), 0.0];
    let mut t = || 20.0 * (rng.uniform() - 0.5) * scale;
    [m[0], m[1], t(), m[3], m[4], t()]
}

fn random_similarity2(rng: &mut SplitMix64, scale: f64) -> Affine2 {
    let a = (rng.uniform() - 0.5) * 6.0;
    let z = (2.0 * (rng.uniform() - 0.5)).exp();
    let (c, s) = (z * a.cos(), z * a.sin());
    let mut t = || 20.0 * (rng.uniform() - 0.5) * scale;
    [c, -s, t(), s, c, t()]
}

fn random_similarity3(rng: &mut SplitMix64, scale: f64, with_scale: bool) -> Similarity3 {
    let axis = Vector3::new(rng.normal(), rng.normal(), rng.normal());
    let angle = std::f64::consts::PI * rng.uniform();
    let rotation = Rotation3::new(axis.normalize() * angle).into_inner();
    let mut t = || 20.0 * (rng.uniform() - 0.5) * scale;
    Similarity3 {
        rotation,
        translation: Vector3::new(t(), t(), t()),
        scale: if with_scale {
            (2.0 * (rng.uniform() - 0.5)).exp()
        } else {
            1.0
        },
    }
}

/// Largest probe distance (unit frame) between two 2-D affine maps over the frame's unit box.
fn affine_probe_error(a: &Affine2, b: &Affine2, f: &Frame) -> f64 {
    let mut worst = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let p = f.p2([i as f64 / 2.0, j as f64 / 2.0]);
            worst = worst.max(dist2(apply_affine(a, p), apply_affine(b, p)) / f.scale);
        }
    }
    worst
}

/// Largest probe distance (unit frame) between two 3-D similarities over the frame's unit cube.
fn sim3_probe_error(a: &Similarity3, b: &Similarity3, f: &Frame) -> f64 {
    let mut worst = 0.0f64;
    for k in 0..8 {
        let u = [(k & 1) as f64, ((k >> 1) & 1) as f64, ((k >> 2) & 1) as f64];
        let p = f.p3(u);
        worst = worst.max((a.apply(&p) - b.apply(&p)).norm() / f.scale);
    }
    worst
}

fn sim3_finite(m: &Similarity3) -> bool {
    finite(m.rotation.as_slice()) && finite(m.translation.as_slice()) && m.scale.is_finite()
}

fn sim3_pair(m: &Similarity3, x: [f64; 3]) -> Pair3 {
    [x, v3(m.apply(&x))]
}

proptest! {
    #![proptest_config(config(128))]

    /// Exact data at any scale and offset: the 4-point and the least-squares DLT, and LO-RANSAC
    /// over them, recover the homography to 1e-9 of the extent.
    #[test]
    fn homography_exact_at_any_scale(seed in any::<u64>(), f1 in frame(), f2 in frame()) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let h_u = random_h(&mut rng);
        let quad = spread_quad(&mut rng);
        let mut data: Vec<Correspondence> =
            quad.iter().filter_map(|&u| h_pair(&h_u, u, &f1, &f2)).collect();
        prop_assert_eq!(data.len(), 4);
        let four = four_point(&data);
        prop_assert!(four.is_some(), "well-spread quad rejected");
        let e4 = h_probe_error(&four.unwrap(), &h_u, &f1, &f2);
        prop_assert!(e4 < 1e-9, "four-point error {}", e4);
        for _ in 0..36 {
            let u = [rng.uniform(), rng.uniform()];
            data.extend(h_pair(&h_u, u, &f1, &f2));
        }
        let all = dlt(&data);
        prop_assert!(all.is_some());
        let ed = h_probe_error(&all.unwrap(), &h_u, &f1, &f2);
        prop_assert!(ed < 1e-9, "DLT error {}", ed);
        let t = 1e-7 * f1.scale;
        let report = estimate(&HomographyEstimator, &data, &lo_options(t, 1));
        prop_assert!(report.is_ok(), "{:?}", report.err());
        let report = report.unwrap();
        check_report(&HomographyEstimator, &data, t, &report, h_finite)?;
        prop_assert_eq!(report.num_inliers, data.len());
        let er = h_probe_error(&report.model, &h_u, &f1, &f2);
        prop_assert!(er < 1e-9, "LO-RANSAC error {}", er);
    }

    /// Exact data at any scale and offset: the 8-point fit and one of the 7-point solutions
    /// explain held-out true correspondences to 1e-9 of the extent; every 7-point solution is
    /// rank 2 and satisfies its seven constraints.
    #[test]
    fn fundamental_exact_at_any_scale(seed in any::<u64>(), f1 in frame(), f2 in frame()) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let scene = random_scene(&mut rng, 1.0);
        let mut pairs = |n: usize| -> Vec<Correspondence> {
            (0..n).map(|_| f_pair(scene.project(&scene_point(&mut rng, 6.0)), &f1, &f2)).collect()
        };
        let data = pairs(30);
        let held_out = pairs(20);
        let eight = eight_point(&data);
        prop_assert!(eight.is_some());
        let eight = eight.unwrap();
        prop_assert!(h_finite(&eight));
        let e8 = f_held_out_error(&eight, &held_out, f1.scale);
        prop_assert!(e8 < 1e-9, "8-point held-out error {}", e8);
        let sols = seven_point(&data[..7]);
        prop_assert!(!sols.is_empty() && sols.len() <= 3);
        let mut best = f64::INFINITY;
        for f in &sols {
            prop_assert!(h_finite(f));
            prop_assert!(rank2_ratio(f) < 1e-9, "rank ratio {}", rank2_ratio(f));
            let own = f_held_out_error(f, &data[..7], f1.scale);
            prop_assert!(own < 1e-9, "7-point sample residual {}", own);
            best = best.min(f_held_out_error(f, &held_out, f1.scale));
        }
        prop_assert!(best < 1e-7, "7-point best held-out error {}", best);
    }

    /// Exact data at any scale and offset: minimal and least-squares line, circle and plane fits
    /// recover the truth to 1e-9 of the extent (probe distances, centre and radius).
    #[test]
    fn shapes_exact_at_any_scale(seed in any::<u64>(), f in frame()) {
        let mut rng = SplitMix64::new(seed);
        let s = f.scale;
        // Line.
        let (c, d) = random_line(&mut rng);
        let pts: Vec<[f64; 2]> =
            (0..20).map(|_| f.p2(on_line(c, d, rng.uniform() - 0.5))).collect();
        let ends = [f.p2(on_line(c, d, -0.5)), f.p2(on_line(c, d, 0.5))];
        for sample in [&pts[..2], &pts[..]] {
            let fits = LineEstimator.fit(sample);
            // Two points a hair apart make a legitimately ill-conditioned minimal line.
            if sample.len() == 2 && dist2(sample[0], sample[1]) < 0.05 * s {
                continue;
            }
            prop_assert_eq!(fits.len(), 1);
            prop_assert!(line_finite(&fits[0]));
            for p in ends {
                let e = line_distance(&fits[0], p) / s;
                prop_assert!(e < 1e-9, "line error {} (n = {})", e, sample.len());
            }
        }
        // Circle.
        let (cc, r, a0, span) = random_circle(&mut rng);
        let angles: Vec<f64> = (0..12).map(|i| a0 + span * i as f64 / 11.0).collect();
        let pts: Vec<[f64; 2]> =
            angles.iter().map(|a| f.p2([cc[0] + r * a.cos(), cc[1] + r * a.sin()])).collect();
        let centre = f.p2(cc);
        for sample in [vec![pts[0], pts[5], pts[11]], pts.clone()] {
            let fits = CircleEstimator.fit(&sample);
            prop_assert_eq!(fits.len(), 1);
            let m = fits[0];
            prop_assert!(circle_finite(&m));
            let e = dist2(m.center, centre) / s + (m.radius - r * s).abs() / s;
            prop_assert!(e < 1e-9, "circle error {} (n = {})", e, sample.len());
        }
        // Plane.
        let (c, n, e1, e2) = random_plane(&mut rng);
        let at = |a: f64, b: f64| f.p3(v3(c + e1 * a + e2 * b));
        let corners = [at(-0.5, -0.5), at(0.5, -0.5), at(-0.5, 0.5), at(0.5, 0.5)];
        let mut pts: Vec<[f64; 3]> = vec![at(-0.4, -0.4), at(0.4, -0.3), at(0.0, 0.45)];
        pts.extend((0..15).map(|_| at(rng.uniform() - 0.5, rng.uniform() - 0.5)));
        for sample in [&pts[..3], &pts[..]] {
            let fits = PlaneEstimator.fit(sample);
            prop_assert_eq!(fits.len(), 1);
            let m = fits[0];
            prop_assert!(plane_finite(&m));
            let cos = (Vector3::from(m.normal).dot(&n)).abs();
            prop_assert!(1.0 - cos < 1e-12, "normal off by {}", 1.0 - cos);
            for p in corners {
                let e = plane_distance(&m, p) / s;
                prop_assert!(e < 1e-9, "plane error {} (n = {})", e, sample.len());
            }
        }
    }

    /// Exact data at any scale and offset: minimal and least-squares affine, similarity, rigid
    /// and similarity-3D fits recover the truth to 1e-9 of the extent.
    #[test]
    fn transforms_exact_at_any_scale(seed in any::<u64>(), f in frame()) {
        let mut rng = SplitMix64::new(seed);
        let s = f.scale;
        let aff = random_affine(&mut rng, s);
        let sim = random_similarity2(&mut rng, s);
        let src: Vec<[f64; 2]> = [[0.1, 0.1], [0.9, 0.2], [0.3, 0.9]]
            .into_iter()
            .chain((0..17).map(|_| [rng.uniform(), rng.uniform()]))
            .map(|u| f.p2(u))
            .collect();
        for (truth, is_affine) in [(aff, true), (sim, false)] {
            let data: Vec<Pair2> = src.iter().map(|&p| [p, apply_affine(&truth, p)]).collect();
            let k = if is_affine { 3 } else { 2 };
            for sample in [&data[..k], &data[..]] {
                let m = if is_affine { fit_affine2(sample) } else { fit_similarity2(sample) };
                prop_assert!(m.is_some(), "affine {}: no fit", is_affine);
                let m = m.unwrap();
                prop_assert!(finite(&m));
                let e = affine_probe_error(&m, &truth, &f);
                prop_assert!(e < 1e-9, "affine {} n {}: error {}", is_affine, sample.len(), e);
            }
        }
        for with_scale in [false, true] {
            let truth = random_similarity3(&mut rng, s, with_scale);
            let src: Vec<[f64; 3]> = [[0.1, 0.1, 0.2], [0.9, 0.2, 0.5], [0.3, 0.9, 0.8]]
                .into_iter()
                .chain((0..17).map(|_| [rng.uniform(), rng.uniform(), rng.uniform()]))
                .map(|u| f.p3(u))
                .collect();
            let data: Vec<Pair3> = src.iter().map(|&x| sim3_pair(&truth, x)).collect();
            for sample in [&data[..3], &data[..]] {
                let m = umeyama(sample, with_scale);
                prop_assert!(m.is_some());
                let m = m.unwrap();
                prop_assert!(sim3_finite(&m));
                prop_assert!((m.rotation.determinant() - 1.0).abs() < 1e-12);
                let e = sim3_probe_error(&m, &truth, &f);
                prop_assert!(e < 1e-9, "scale {} n {}: error {}", with_scale, sample.len(), e);
            }
        }
    }
}

/// σ of the noise of the robust properties, relative to the scale.
const NOISE: f64 = 1e-3;

proptest! {
    #![proptest_config(config(64))]

    /// 50–95 % outliers, 40 inliers with noise σ = 1e-3·s: LO-RANSAC (t = 5σ) finds ≥ 90 % of
    /// the true inliers and a line, circle and plane within 3σ of the truth (the least-squares
    /// error over 40 inliers is ~σ/√10; a wrong model is off by ~s = 1000σ).
    #[test]
    fn shapes_among_outliers(seed in any::<u64>(), f in frame(), outliers in 0.5f64..0.95) {
        let mut rng = SplitMix64::new(seed);
        let s = f.scale;
        let sigma = NOISE * s;
        let t = 5.0 * sigma;
        let k = 40;
        let n = (k as f64 / (1.0 - outliers)).round() as usize;
        let noise = |rng: &mut SplitMix64| sigma * rng.normal();
        let junk2 = |rng: &mut SplitMix64| f.p2([2.0 * rng.uniform() - 0.5, 2.0 * rng.uniform() - 0.5]);
        // Line.
        let (c, d) = random_line(&mut rng);
        let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
        let mut data: Vec<[f64; 2]> = (0..n)
            .map(|i| {
                if i < k {
                    let p = f.p2(on_line(c, d, rng.uniform() - 0.5));
                    [p[0] + noise(&mut rng), p[1] + noise(&mut rng)]
                } else {
                    junk2(&mut rng)
                }
            })
            .collect();
        shuffle(&mut rng, &mut data, &mut truth);
        let report = estimate(&LineEstimator, &data, &lo_options(t, 3));
        prop_assert!(report.is_ok(), "line: {:?}", report.err());
        let report = report.unwrap();
        check_report(&LineEstimator, &data, t, &report, line_finite)?;
        let found = true_positives(&report.inlier_mask, &truth);
        prop_assert!(found * 10 >= 9 * k, "line found {}/{}", found, k);
        for tau in [-0.5, 0.5] {
            let e = line_distance(&report.model, f.p2(on_line(c, d, tau))) / sigma;
            prop_assert!(e < 6.0, "line error {} σ", e);
        }
        // Circle.
        let (cc, r, a0, span) = random_circle(&mut rng);
        let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
        let mut data: Vec<[f64; 2]> = (0..n)
            .map(|i| {
                if i < k {
                    let a = a0 + span * rng.uniform();
                    let p = f.p2([cc[0] + r * a.cos(), cc[1] + r * a.sin()]);
                    [p[0] + noise(&mut rng), p[1] + noise(&mut rng)]
                } else {
                    junk2(&mut rng)
                }
            })
            .collect();
        shuffle(&mut rng, &mut data, &mut truth);
        let report = estimate(&CircleEstimator, &data, &lo_options(t, 3));
        prop_assert!(report.is_ok(), "circle: {:?}", report.err());
        let report = report.unwrap();
        check_report(&CircleEstimator, &data, t, &report, circle_finite)?;
        let found = true_positives(&report.inlier_mask, &truth);
        prop_assert!(found * 10 >= 9 * k, "circle found {}/{}", found, k);
        // On the arc, the fitted circle stays within 3σ of the true one.
        let m = report.model;
        for i in 0..=8 {
            let a = a0 + span * i as f64 / 8.0;
            let p = f.p2([cc[0] + r * a.cos(), cc[1] + r * a.sin()]);
            let e = (dist2(p, m.center) - m.radius).abs() / sigma;
            prop_assert!(e < 6.0, "circle error {} σ at angle {}", e, a);
        }
        // Plane.
        let (c, _, e1, e2) = random_plane(&mut rng);
        let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
        let mut data: Vec<[f64; 3]> = (0..n)
            .map(|i| {
                if i < k {
                    let p = c + e1 * (rng.uniform() - 0.5) + e2 * (rng.uniform() - 0.5);
                    let p = f.p3(v3(p));
                    [p[0] + noise(&mut rng), p[1] + noise(&mut rng), p[2] + noise(&mut rng)]
                } else {
                    f.p3([2.0 * rng.uniform() - 0.5, 2.0 * rng.uniform() - 0.5, 2.0 * rng.uniform() - 0.5])
                }
            })
            .collect();
        shuffle(&mut rng, &mut data, &mut truth);
        let report = estimate(&PlaneEstimator, &data, &lo_options(t, 3));
        prop_assert!(report.is_ok(), "plane: {:?}", report.err());
        let report = report.unwrap();
        check_report(&PlaneEstimator, &data, t, &report, plane_finite)?;
        let found = true_positives(&report.inlier_mask, &truth);
        prop_assert!(found * 10 >= 9 * k, "plane found {}/{}", found, k);
        for (a, b) in [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)] {
            let p = f.p3(v3(c + e1 * a + e2 * b));
            let e = plane_distance(&report.model, p) / sigma;
            prop_assert!(e < 6.0, "plane error {} σ", e);
        }
    }

    /// 50–95 % outliers (similarity: 2-point samples) and 50–90 % (affine, rigid, similarity-3D:
    /// 3-point samples), 40 inliers with target noise σ = 1e-3·s: LO-RANSAC (t = 5σ) finds ≥ 90 %
    /// of the true inliers and a transform within 3σ of the truth over the data's extent.
    #[test]
    fn transforms_among_outliers(seed in any::<u64>(), f in frame(), outliers in 0.5f64..0.95) {
        let mut rng = SplitMix64::new(seed);
        let s = f.scale;
        let sigma = NOISE * s;
        let t = 5.0 * sigma;
        let k = 40;
        let n2 = (k as f64 / (1.0 - outliers)).round() as usize;
        let n3 = (k as f64 / (1.0 - outliers.min(0.9))).round() as usize;
        for is_affine in [false, true] {
            let n = if is_affine { n3 } else { n2 };
            let truth_m = if is_affine { random_affine(&mut rng, s) } else { random_similarity2(&mut rng, s) };
            let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
            let mut data: Vec<Pair2> = (0..n)
                .map(|i| {
                    let x = f.p2([rng.uniform(), rng.uniform()]);
                    let y = if i < k {
                        let y = apply_affine(&truth_m, x);
                        [y[0] + sigma * rng.normal(), y[1] + sigma * rng.normal()]
                    } else {
                        apply_affine(&truth_m, f.p2([rng.uniform(), rng.uniform()]))
                    };
                    [x, y]
                })
                .collect();
            shuffle(&mut rng, &mut data, &mut truth);
            let options = lo_options(t, 4);
            let report = if is_affine {
                estimate(&Affine2Estimator, &data, &options)
            } else {
                estimate(&Similarity2Estimator, &data, &options)
            };
            prop_assert!(report.is_ok(), "affine {}: {:?}", is_affine, report.err());
            let report = report.unwrap();
            if is_affine {
                check_report(&Affine2Estimator, &data, t, &report, |m| finite(m))?;
            } else {
                check_report(&Similarity2Estimator, &data, t, &report, |m| finite(m))?;
            }
            let found = true_positives(&report.inlier_mask, &truth);
            prop_assert!(found * 10 >= 9 * k, "affine {} found {}/{}", is_affine, found, k);
            let e = affine_probe_error(&report.model, &truth_m, &f) * s / sigma;
            prop_assert!(e < 6.0, "affine {}: error {} σ", is_affine, e);
        }
        for with_scale in [false, true] {
            let truth_m = random_similarity3(&mut rng, s, with_scale);
            let n = n3;
            let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
            let mut data: Vec<Pair3> = (0..n)
                .map(|i| {
                    let x = f.p3([rng.uniform(), rng.uniform(), rng.uniform()]);
                    let y = if i < k {
                        truth_m.apply(&x) + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma
                    } else {
                        truth_m.apply(&f.p3([rng.uniform(), rng.uniform(), rng.uniform()]))
                    };
                    [x, v3(y)]
                })
                .collect();
            shuffle(&mut rng, &mut data, &mut truth);
            let options = lo_options(t, 4);
            let report = if with_scale {
                estimate(&Similarity3Estimator, &data, &options)
            } else {
                estimate(&Rigid3Estimator, &data, &options)
            };
            prop_assert!(report.is_ok(), "3-D {}: {:?}", with_scale, report.err());
            let report = report.unwrap();
            if with_scale {
                check_report(&Similarity3Estimator, &data, t, &report, sim3_finite)?;
            } else {
                check_report(&Rigid3Estimator, &data, t, &report, sim3_finite)?;
            }
            let found = true_positives(&report.inlier_mask, &truth);
            prop_assert!(found * 10 >= 9 * k, "3-D {} found {}/{}", with_scale, found, k);
            let e = sim3_probe_error(&report.model, &truth_m, &f) * s / sigma;
            prop_assert!(e < 6.0, "3-D {}: error {} σ", with_scale, e);
        }
    }

    /// 50–90 % outliers, 40 inliers with noise σ = 1e-3·s in both images: LO-RANSAC (t = 8σ on
    /// the symmetric transfer error, whose forward and backward terms each sum two noises)
    /// finds ≥ 90 % of the true inliers and a homography within 4σ of the truth over the image.
    #[test]
    fn homography_among_outliers(seed in any::<u64>(), f1 in frame(), f2 in frame(), outliers in 0.5f64..0.9) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let s = f1.scale;
        let sigma = NOISE * s;
        let t = 8.0 * sigma;
        let k = 40;
        let n = (k as f64 / (1.0 - outliers)).round() as usize;
        let h_u = random_h(&mut rng);
        let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
        let mut data: Vec<Correspondence> = Vec::with_capacity(n);
        while data.len() < n {
            let u = [rng.uniform(), rng.uniform()];
            let v = if data.len() < k { u } else { [rng.uniform(), rng.uniform()] };
            if let Some(mut c) = h_pair(&h_u, v, &f1, &f2) {
                c[0] = f1.p2(u);
                if data.len() < k {
                    for p in c.iter_mut() {
                        p[0] += sigma * rng.normal();
                        p[1] += sigma * rng.normal();
                    }
                }
                data.push(c);
            }
        }
        shuffle(&mut rng, &mut data, &mut truth);
        let report = estimate(&HomographyEstimator, &data, &lo_options(t, 5));
        prop_assert!(report.is_ok(), "{:?}", report.err());
        let report = report.unwrap();
        check_report(&HomographyEstimator, &data, t, &report, h_finite)?;
        let found = true_positives(&report.inlier_mask, &truth);
        prop_assert!(found * 10 >= 9 * k, "found {}/{}", found, k);
        let e = h_probe_error(&report.model, &h_u, &f1, &f2) * s / sigma;
        prop_assert!(e < 8.0, "error {} σ", e);
    }

    /// 30–60 % outliers (7-point samples make higher rates cost ~1/w⁷ trials), 40 inliers with
    /// noise σ = 1e-3·s in both images: LO-RANSAC (t = 5σ on the Sampson distance, a 1-D
    /// normal error) finds ≥ 90 % of the true inliers, and held-out noise-free correspondences
    /// lie within 3σ (Sampson distance) of the estimate.
    #[test]
    fn fundamental_among_outliers(seed in any::<u64>(), f1 in frame(), f2 in frame(), outliers in 0.3f64..0.6) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let s = f1.scale;
        let sigma = NOISE * s;
        let t = 5.0 * sigma;
        let k = 40;
        let n = (k as f64 / (1.0 - outliers)).round() as usize;
        let scene = random_scene(&mut rng, 1.0);
        let mut truth: Vec<bool> = (0..n).map(|i| i < k).collect();
        let mut data: Vec<Correspondence> = (0..n)
            .map(|i| {
                let mut c = f_pair(scene.project(&scene_point(&mut rng, 6.0)), &f1, &f2);
                if i < k {
                    for p in c.iter_mut() {
                        p[0] += sigma * rng.normal();
                        p[1] += sigma * rng.normal();
                    }
                } else {
                    c[1] = f_pair(scene.project(&scene_point(&mut rng, 6.0)), &f1, &f2)[1];
                }
                c
            })
            .collect();
        shuffle(&mut rng, &mut data, &mut truth);
        let held_out: Vec<Correspondence> = (0..30)
            .map(|_| f_pair(scene.project(&scene_point(&mut rng, 6.0)), &f1, &f2))
            .collect();
        let report = estimate(&FundamentalEstimator, &data, &lo_options(t, 6));
        prop_assert!(report.is_ok(), "{:?}", report.err());
        let report = report.unwrap();
        check_report(&FundamentalEstimator, &data, t, &report, h_finite)?;
        let found = true_positives(&report.inlier_mask, &truth);
        prop_assert!(found * 10 >= 9 * k, "found {}/{}", found, k);
        let e = f_held_out_error(&report.model, &held_out, s) * s / sigma;
        // The worst of 30 held-out matches, extrapolated in depth (up to 6× the inliers'
        // range) from a fit to 40 noisy matches: 25σ was seen; a wrong model is off by
        // thousands of σ.
        prop_assert!(e < 50.0, "held-out error {} σ", e);
    }
}

proptest! {
    #![proptest_config(config(128))]

    /// Data rounded to f32: every least-squares fit moves from the f64 one by at most
    /// `C · ε₃₂ · m` of the extent, `m` the coordinates' magnitude relative to the extent (the
    /// rounding is `ε₃₂/2 · m` of the extent per coordinate) and `C` a conditioning factor of
    /// these well-spread configurations (100, about 10× what is observed).
    #[test]
    fn f32_rounded_inputs(seed in any::<u64>(), f1 in frame(), f2 in frame()) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let s = f1.scale;
        let m = f1.magnitude().max(f2.magnitude()) + 2.0;
        let tol = 100.0 * F32_EPS * m;
        let round2 = |c: &Correspondence| c.map(|p| p.map(f32_round));
        // Homography (DLT on 40 points).
        let h_u = random_h(&mut rng);
        let data: Vec<Correspondence> = (0..40)
            .filter_map(|_| h_pair(&h_u, [rng.uniform(), rng.uniform()], &f1, &f2))
            .collect();
        let rounded: Vec<Correspondence> = data.iter().map(round2).collect();
        let (a, b) = (dlt(&data), dlt(&rounded));
        prop_assert!(a.is_some() && b.is_some());
        let (a, b) = (a.unwrap(), b.unwrap());
        let ea = h_probe_error(&a, &h_u, &f1, &f2);
        let eb = h_probe_error(&b, &h_u, &f1, &f2);
        prop_assert!(ea < 1e-9 && eb < tol, "H: f64 {} f32 {} (tol {})", ea, eb, tol);
        // Fundamental (8-point on 40 points): held-out Sampson distances of the f64 truth.
        let scene = random_scene(&mut rng, 1.0);
        let mut pairs = |n: usize| -> Vec<Correspondence> {
            (0..n).map(|_| f_pair(scene.project(&scene_point(&mut rng, 6.0)), &f1, &f2)).collect()
        };
        let data = pairs(40);
        let held_out = pairs(20);
        let rounded: Vec<Correspondence> = data.iter().map(round2).collect();
        let (a, b) = (eight_point(&data), eight_point(&rounded));
        prop_assert!(a.is_some() && b.is_some());
        let ea = f_held_out_error(&a.unwrap(), &held_out, s);
        let eb = f_held_out_error(&b.unwrap(), &held_out, s);
        prop_assert!(ea < 1e-9 && eb < tol, "F: f64 {} f32 {} (tol {})", ea, eb, tol);
        // Shapes (least squares over 20 points).
        let m1 = f1.magnitude() + 2.0;
        let tol1 = 100.0 * F32_EPS * m1;
        let (c, d) = random_line(&mut rng);
        let pts: Vec<[f64; 2]> = (0..20).map(|_| f1.p2(on_line(c, d, rng.uniform() - 0.5))).collect();
        let rpts: Vec<[f64; 2]> = pts.iter().map(|p| p.map(f32_round)).collect();
        let (la, lb) = (LineEstimator.fit(&pts), LineEstimator.fit(&rpts));
        prop_assert!(la.len() == 1 && lb.len() == 1);
        for tau in [-0.5, 0.5] {
            let p = f1.p2(on_line(c, d, tau));
            let e = line_distance(&lb[0], p) / s;
            prop_assert!(e < tol1, "line: {} (tol {})", e, tol1);
        }
        let (cc, r, a0, span) = random_circle(&mut rng);
        let pts: Vec<[f64; 2]> = (0..20)
            .map(|_| {
                let a = a0 + span * rng.uniform();
                f1.p2([cc[0] + r * a.cos(), cc[1] + r * a.sin()])
            })
            .collect();
        let rpts: Vec<[f64; 2]> = pts.iter().map(|p| p.map(f32_round)).collect();
        let (ca, cb) = (CircleEstimator.fit(&pts), CircleEstimator.fit(&rpts));
        prop_assert!(ca.len() == 1 && cb.len() == 1);
        // The arc's points stay within the tolerance of the rounded fit (the centre of a short
        // arc is ill-conditioned along the arc's axis; the arc itself is not).
        for i in 0..=8 {
            let a = a0 + span * i as f64 / 8.0;
            let p = f1.p2([cc[0] + r * a.cos(), cc[1] + r * a.sin()]);
            let e = (dist2(p, cb[0].center) - cb[0].radius).abs() / s;
            prop_assert!(e < tol1, "circle: {} (tol {})", e, tol1);
        }
        let (c, _, e1, e2) = random_plane(&mut rng);
        let pts: Vec<[f64; 3]> = (0..20)
            .map(|_| f1.p3(v3(c + e1 * (rng.uniform() - 0.5) + e2 * (rng.uniform() - 0.5))))
            .collect();
        let rpts: Vec<[f64; 3]> = pts.iter().map(|p| p.map(f32_round)).collect();
        let pb = PlaneEstimator.fit(&rpts);
        prop_assert!(pb.len() == 1);
        for (a, b) in [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)] {
            let e = plane_distance(&pb[0], f1.p3(v3(c + e1 * a + e2 * b))) / s;
            prop_assert!(e < tol1, "plane: {} (tol {})", e, tol1);
        }
        // Transforms (least squares over 20 pairs); the targets are up to ~25 extents away.
        let tol2 = 100.0 * F32_EPS * (m1 + 30.0);
        let aff = random_affine(&mut rng, s);
        let sim = random_similarity2(&mut rng, s);
        for (truth, is_affine) in [(aff, true), (sim, false)] {
            let data: Vec<Pair2> = (0..20)
                .map(|_| {
                    let x = f1.p2([rng.uniform(), rng.uniform()]);
                    [x, apply_affine(&truth, x)]
                })
                .collect();
            let rounded: Vec<Pair2> = data.iter().map(|c| c.map(|p| p.map(f32_round))).collect();
            let fit = if is_affine { fit_affine2(&rounded) } else { fit_similarity2(&rounded) };
            prop_assert!(fit.is_some());
            let e = affine_probe_error(&fit.unwrap(), &truth, &f1);
            prop_assert!(e < tol2, "affine {}: {} (tol {})", is_affine, e, tol2);
        }
        for with_scale in [false, true] {
            let truth = random_similarity3(&mut rng, s, with_scale);
            let rounded: Vec<Pair3> = (0..20)
                .map(|_| sim3_pair(&truth, f1.p3([rng.uniform(), rng.uniform(), rng.uniform()])))
                .map(|c| c.map(|p| p.map(f32_round)))
                .collect();
            let fit = umeyama(&rounded, with_scale);
            prop_assert!(fit.is_some());
            let e = sim3_probe_error(&fit.unwrap(), &truth, &f1);
            prop_assert!(e < tol2, "3-D {}: {} (tol {})", with_scale, e, tol2);
        }
    }
}

/// A 2×2 unit-frame helper: the perpendicular of a direction.
fn perp(d: [f64; 2]) -> [f64; 2] {
    [-d[1], d[0]]
}

proptest! {
    #![proptest_config(config(256))]

    /// Almost collinear points (perpendicular jitter 1e-14…1e-1 of the extent) with 0–2 points
    /// off the line, exact H and affine data: the minimal and least-squares solvers return no
    /// model or a finite one that maps its own data, and the robust loops return a typed error
    /// or a finite model whose inliers are exactly the data within the threshold.
    #[test]
    fn near_collinear_h_and_affine(
        seed in any::<u64>(),
        f1 in frame(),
        f2 in frame(),
        jitter_exp in -14.0f64..-1.0,
        off_line in 0usize..3,
    ) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let s = f1.scale;
        let jitter = 10f64.powf(jitter_exp);
        let (c, d) = random_line(&mut rng);
        let c = [0.25 + 0.5 * c[0], 0.25 + 0.5 * c[1]];
        let q = perp(d);
        let mut units: Vec<[f64; 2]> = (0..16)
            .map(|_| {
                let p = on_line(c, d, rng.uniform() - 0.5);
                let e = jitter * rng.normal();
                [p[0] + e * q[0], p[1] + e * q[1]]
            })
            .collect();
        units.extend((0..off_line).map(|i| {
            let side = if i == 0 { 0.3 } else { -0.3 };
            on_line(on_line(c, q, side), d, 0.4 * (rng.uniform() - 0.5))
        }));
        // Homography.
        let h_u = random_h(&mut rng);
        let data: Vec<Correspondence> = units.iter().filter_map(|&u| h_pair(&h_u, u, &f1, &f2)).collect();
        prop_assert_eq!(data.len(), units.len());
        if let Some(h) = four_point(&data[..4]) {
            prop_assert!(h_finite(&h));
            // The four solved correspondences map forward onto their targets.
            for c in &data[..4] {
                let e = transfer(&h, &c[0]).map_or(f64::INFINITY, |p| dist2(p, c[1]) / s);
                prop_assert!(e < 1e-6, "four-point own transfer error {}", e);
            }
        }
        if let Some(h) = dlt(&data) {
            prop_assert!(h_finite(&h));
        }
        let t = 1e-6 * s;
        match estimate(&HomographyEstimator, &data, &lo_options(t, 7)) {
            Ok(report) => {
                check_report(&HomographyEstimator, &data, t, &report, h_finite)?;
                prop_assert!(report.model.try_inverse().is_some());
            }
            Err(e) => prop_assert!(
                matches!(e, RobustError::Degenerate | RobustError::NoConsensus { .. }),
                "{:?}", e
            ),
        }
        // Affine.
        let aff = random_affine(&mut rng, s);
        let data: Vec<Pair2> = units.iter().map(|&u| {
            let x = f1.p2(u);
            [x, apply_affine(&aff, x)]
        }).collect();
        let mut r = vec![0.0; data.len()];
        for sample in [&data[..3], &data[..]] {
            if let Some(m) = fit_affine2(sample) {
                prop_assert!(finite(&m));
                // Exact data are consistent: the fit maps its own data (the ill-conditioned
                // direction is the one the data do not span).
                Affine2Estimator.residuals(&m, sample, &mut r[..sample.len()]);
                let worst = r[..sample.len()].iter().fold(0.0f64, |a, &v| a.max(v)).sqrt() / s;
                prop_assert!(worst < 1e-4, "affine own residual {} (n = {})", worst, sample.len());
            }
        }
        match estimate(&Affine2Estimator, &data, &lo_options(t, 7)) {
            Ok(report) => check_report(&Affine2Estimator, &data, t, &report, |m| finite(m))?,
            Err(e) => prop_assert!(
                matches!(e, RobustError::Degenerate | RobustError::NoConsensus { .. }),
                "{:?}", e
            ),
        }
    }

    /// Almost planar scenes (depth spread 1e-9…1 of the depth), baselines down to 1e-9, and some
    /// points at (nearly) infinite depth, exact data: the 8- and 7-point solvers return no model
    /// or finite ones that satisfy the data's epipolar constraints, and LO-RANSAC returns a
    /// typed error or a finite model whose inliers are exactly the data within the threshold.
    #[test]
    fn near_degenerate_fundamental(
        seed in any::<u64>(),
        f1 in frame(),
        f2 in frame(),
        spread_exp in -9.0f64..0.8,
        baseline_exp in -9.0f64..0.0,
        far in 0usize..4,
    ) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let s = f1.scale;
        let scene = random_scene(&mut rng, 10f64.powf(baseline_exp));
        let spread = 7.0 * 10f64.powf(spread_exp);
        let mut data: Vec<Correspondence> = (0..30)
            .map(|_| f_pair(scene.project(&scene_point(&mut rng, spread)), &f1, &f2))
            .collect();
        for _ in 0..far {
            let mut p = scene_point(&mut rng, 0.0);
            p *= 10f64.powf(3.0 + 9.0 * rng.uniform());
            data.push(f_pair(scene.project(&p), &f1, &f2));
        }
        if let Some(f) = eight_point(&data) {
            prop_assert!(h_finite(&f));
            prop_assert!(rank2_ratio(&f) < 1e-9, "rank ratio {}", rank2_ratio(&f));
            let e = f_held_out_error(&f, &data, s);
            prop_assert!(e < 1e-6, "8-point residual on its data {}", e);
        }
        for f in seven_point(&data[..7]) {
            prop_assert!(h_finite(&f));
            let e = f_held_out_error(&f, &data[..7], s);
            prop_assert!(e < 1e-6, "7-point residual on its sample {}", e);
        }
        let t = 1e-6 * s;
        match estimate(&FundamentalEstimator, &data, &lo_options(t, 8)) {
            Ok(report) => check_report(&FundamentalEstimator, &data, t, &report, h_finite)?,
            Err(e) => prop_assert!(
                matches!(e, RobustError::Degenerate | RobustError::NoConsensus { .. }),
                "{:?}", e
            ),
        }
    }

    /// Exact H data with well-spread points plus up to three left points next to the horizon
    /// of H (`w = ±1e-12…1e-3`, so their right points lie up to 1e12 extents away): LO-RANSAC
    /// still returns the homography of the regular points, every regular point an inlier.
    #[test]
    fn homography_points_near_the_horizon(
        seed in any::<u64>(),
        f1 in frame(),
        f2 in frame(),
        near in 0usize..4,
        w_exp in -12.0f64..-3.0,
    ) {
        let f2 = Frame { scale: f1.scale, offset: f2.offset.map(|o| o / f2.scale * f1.scale) };
        let mut rng = SplitMix64::new(seed);
        let h_u = random_h(&mut rng);
        let mut data: Vec<Correspondence> = (0..30)
            .filter_map(|_| h_pair(&h_u, [rng.uniform(), rng.uniform()], &f1, &f2))
            .collect();
        let regular = data.len();
        let g = Vector2::new(h_u[(2, 0)], h_u[(2, 1)]);
        if g.norm() > 1e-2 {
            for i in 0..near {
                // w(u) = 1 + g·u = δ on the point u = −(1 − δ) g / |g|² + τ g⊥.
                let delta = if i % 2 == 0 { 1.0 } else { -1.0 } * 10f64.powf(w_exp);
                let base = -g * ((1.0 - delta) / g.norm_squared());
                let u = base + Vector2::new(-g.y, g.x).normalize() * (rng.uniform() - 0.5);
                data.extend(h_pair(&h_u, [u.x, u.y], &f1, &f2));
            }
        }
        let t = 1e-6 * f1.scale;
        let report = estimate(&HomographyEstimator, &data, &lo_options(t, 9));
        prop_assert!(report.is_ok(), "{:?}", report.err());
        let report = report.unwrap();
        check_report(&HomographyEstimator, &data, t, &report, h_finite)?;
        prop_assert!(report.inlier_mask[..regular].iter().all(|&m| m));
        let e = h_probe_error(&report.model, &h_u, &f1, &f2);
        prop_assert!(e < 1e-8, "probe error {}", e);
    }
}

proptest! {
    #![proptest_config(config(64))]

    /// Coincident data (one point repeated, at any scale and offset) is an error for every
    /// estimator; nearly coincident data (spread 1e-15…1e-9 of the scale) is an error or a
    /// finite model whose inliers are exactly the data within the threshold.
    #[test]
    fn coincident_points(seed in any::<u64>(), f in frame(), spread_exp in -15.0f64..-9.0) {
        let mut rng = SplitMix64::new(seed);
        let s = f.scale;
        let options = RobustOptions { max_trials: 200, ..lo_options(1e-3 * s, 10) };
        let u = [rng.uniform(), rng.uniform(), rng.uniform()];
        let p2 = f.p2([u[0], u[1]]);
        let p3 = f.p3(u);
        let q2 = f.p2([u[2], u[0]]);
        let q3 = f.p3([u[2], u[0], u[1]]);
        let spread = 10f64.powf(spread_exp) * s;
        for jitter in [0.0, spread] {
            let j = |rng: &mut SplitMix64| jitter * rng.normal();
            let pts2: Vec<[f64; 2]> = (0..12).map(|_| [p2[0] + j(&mut rng), p2[1] + j(&mut rng)]).collect();
            let pts3: Vec<[f64; 3]> = (0..12)
                .map(|_| [p3[0] + j(&mut rng), p3[1] + j(&mut rng), p3[2] + j(&mut rng)])
                .collect();
            let pairs2: Vec<Pair2> = pts2.iter().map(|&p| [p, [q2[0] + j(&mut rng), q2[1] + j(&mut rng)]]).collect();
            let pairs3: Vec<Pair3> = pts3.iter().map(|&p| [p, [q3[0] + j(&mut rng), q3[1] + j(&mut rng), q3[2] + j(&mut rng)]]).collect();
            let t = options.threshold;
            macro_rules! check {
                ($est:expr, $data:expr, $finite:expr) => {
                    match estimate(&$est, &$data, &options) {
                        Ok(report) => {
                            prop_assert!(jitter > 0.0, "{} coincident data gave a model", stringify!($est));
                            check_report(&$est, &$data, t, &report, $finite)?;
                        }
                        Err(e) => prop_assert!(
                            matches!(e, RobustError::Degenerate | RobustError::NoConsensus { .. }),
                            "{}: {:?}", stringify!($est), e
                        ),
                    }
                };
            }
            check!(HomographyEstimator, pairs2, h_finite);
            check!(FundamentalEstimator, pairs2, h_finite);
            check!(LineEstimator, pts2, line_finite);
            check!(CircleEstimator, pts2, circle_finite);
            check!(PlaneEstimator, pts3, plane_finite);
            check!(Affine2Estimator, pairs2, |m: &Affine2| finite(m));
            check!(Similarity2Estimator, pairs2, |m: &Affine2| finite(m));
            check!(Rigid3Estimator, pairs3, sim3_finite);
            check!(Similarity3Estimator, pairs3, sim3_finite);
        }
    }
}

#[test]
fn helpers_measure_what_they_claim() {
    // The probe error of the truth is zero and that of a perturbed model is not.
    let f1 = Frame::new(2.0, [5.0, -3.0, 0.0]);
    let f2 = Frame::new(2.0, [-7.0, 1.0, 0.0]);
    let mut rng = SplitMix64::new(1);
    let h_u = random_h(&mut rng);
    let a1 = Matrix3::new(
        f1.scale,
        0.0,
        f1.offset[0],
        0.0,
        f1.scale,
        f1.offset[1],
        0.0,
        0.0,
        1.0,
    );
    let a2 = Matrix3::new(
        f2.scale,
        0.0,
        f2.offset[0],
        0.0,
        f2.scale,
        f2.offset[1],
        0.0,
        0.0,
        1.0,
    );
    let h = a2 * h_u * a1.try_inverse().unwrap_or_else(Matrix3::identity);
    assert!(h_probe_error(&h, &h_u, &f1, &f2) < 1e-12);
    let mut bad = h;
    bad[(0, 2)] += 0.01 * f2.scale;
    assert!(h_probe_error(&bad, &h_u, &f1, &f2) > 1e-3);
    assert!(rank2_ratio(&Matrix3::identity()) == 1.0);
    assert!(rank2_ratio(&Matrix3::from_diagonal(&Vector3::new(2.0, 1.0, 0.0))) == 0.0);
}
