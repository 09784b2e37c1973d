//! `optimize.affine_init`: poses and points of a reconstruction from its 2-D tracks alone, by
//! Tomasi–Kanade factorization ([`super::affine`]) — the starting point for
//! `optimize.bundle_adjust`.
//!
//! Method: each observation is taken to normalized camera coordinates through its camera (the
//! intrinsics and distortion are known and kept); the tracks seen in every image are factorized
//! under a scaled orthographic camera `x ≈ s_f (R_f X)_xy + c_f`; each view's motion rows give
//! its rotation `R_f = [r₁; r₂; r₁ × r₂]` (orthonormalized) and its mean depth `Z̄_f = 1/s_f`,
//! its translation is `t_f = Z̄_f (c_f, 1)`. The factorization leaves a depth reversal
//! (`X → diag(1, 1, −1) X`) open: both are built and the one with the smaller perspective
//! reprojection error (points behind a camera count as failures) is kept. Points not seen in
//! every image are triangulated from their views by linear DLT with the recovered poses. The
//! world frame is the points' centroid, scaled so that the first view's mean depth is its
//! weak-perspective depth; the result is defined up to that similarity.
//!
//! Reference: Tomasi & Kanade, IJCV 9(2), 1992; Hartley & Zisserman, 2nd ed., §18.2.

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Matrix3, Vector3};
use ocellus_engine::params::NoParams;
use ocellus_engine::value::{Metrics, Pose, Reconstruction};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use super::affine::affine_factorization;
use super::camera_model::project;
use crate::geometry::camera::Lens;
use crate::geometry::pose_util::{Intrinsics, nearest_rotation};
use crate::geometry::triangulate::{View, triangulate_dlt};

/// Unit intrinsics: triangulation works in normalized coordinates.
const UNIT: Intrinsics = Intrinsics {
    fx: 1.0,
    fy: 1.0,
    cx: 0.0,
    cy: 0.0,
};

/// One candidate: poses (`R`, `t`) per image and positions per point (`None`: not placed).
type Candidate = (Vec<(Matrix3<f64>, Vector3<f64>)>, Vec<Option<[f64; 3]>>);

/// Normalized (undistorted) coordinates of every observation, per image: `(point index,
/// normalized xy, pixel)`.
type Observations = Vec<Vec<(usize, [f64; 2], [f64; 2])>>;

fn observations(rec: &Reconstruction) -> Result<Observations, String> {
    let index: HashMap<u64, usize> = rec
        .points
        .iter()
        .enumerate()
        .map(|(j, p)| (p.id, j))
        .collect();
    let mut out = Vec::with_capacity(rec.images.len());
    for im in &rec.images {
        let cam = rec
            .cameras
            .get(&im.camera_id)
            .ok_or_else(|| format!("image {} refers to missing camera {}", im.id, im.camera_id))?;
        if cam.params.len() != cam.model.param_count() {
            return Err(format!(
                "camera {} has the wrong parameter count",
                im.camera_id
            ));
        }
        let lens = Lens::from_camera(cam);
        let mut seen = Vec::new();
        for (xy, id) in &im.points2d {
            let Some(id) = id else { continue };
            let j = *index
                .get(id)
                .ok_or_else(|| format!("image {} observes missing point {id}", im.id))?;
            if !xy.iter().all(|v| v.is_finite()) {
                return Err(format!("image {} has a non-finite keypoint", im.id));
            }
            let n = lens.undistort(lens.from_pixel(*xy)).ok_or_else(|| {
                format!("image {}: keypoint {xy:?} outside the lens' field", im.id)
            })?;
            seen.push((j, n, *xy));
        }
        out.push(seen);
    }
    Ok(out)
}

/// Perspective reprojection error of a candidate: (sum of squared pixel errors, observations
/// the candidate cannot explain — a point behind its camera or not placed).
fn score(rec: &Reconstruction, obs: &Observations, cand: &Candidate) -> (f64, usize) {
    let (mut sq, mut failures) = (0.0, 0usize);
    for ((im, seen), (r, t)) in rec.images.iter().zip(obs).zip(&cand.0) {
        let cam = &rec.cameras[&im.camera_id];
        for &(j, _, px) in seen {
            let Some(x) = cand.1[j] else {
                failures += 1;
                continue;
            };
            let p = r * Vector3::new(x[0], x[1], x[2]) + t;
            match project(cam.model, &cam.params, [p.x, p.y, p.z]) {
                Some(proj) if p.z > 0.0 => {
                    sq += (proj.pixel[0] - px[0]).powi(2) + (proj.pixel[1] - px[1]).powi(2);
                }
                _ => failures += 1,
            }
        }
    }
    (sq, failures)
}

/// Builds the candidate of one depth-reversal sign.
fn candidate(
    obs: &Observations,
    complete: &[usize],
    fact: &super::affine::AffineFactorization,
    reflect: bool,
    n_points: usize,
) -> Candidate {
    let d = if reflect { -1.0 } else { 1.0 };
    let mut poses = Vec::with_capacity(obs.len());
    for (m, c) in fact.motion.iter().zip(&fact.translation) {
        let r1 = Vector3::new(m[0][0], m[0][1], d * m[0][2]);
        let r2 = Vector3::new(m[1][0], m[1][1], d * m[1][2]);
        let s = 0.5 * (r1.norm() + r2.norm());
        let raw = Matrix3::from_rows(&[
            (r1 / s).transpose(),
            (r2 / s).transpose(),
            (r1.cross(&r2) / (s * s)).transpose(),
        ]);
        let r = nearest_rotation(&raw).unwrap_or(raw);
        let depth = 1.0 / s;
        poses.push((r, Vector3::new(c[0] * depth, c[1] * depth, depth)));
    }
    let mut points: Vec<Option<[f64; 3]>> = vec![None; n_points];
    for (k, &j) in complete.iter().enumerate() {
        let x = fact.points[k];
        points[j] = Some([x[0], x[1], d * x[2]]);
    }
    // Points outside the complete tracks: linear triangulation from their views.
    let mut views_of: HashMap<usize, (Vec<View>, Vec<[f64; 2]>)> = HashMap::new();
    for (f, seen) in obs.iter().enumerate() {
        for &(j, n, _) in seen {
            if points[j].is_none() {
                let e = views_of.entry(j).or_default();
                e.0.push(View {
                    r: poses[f].0,
                    t: poses[f].1,
                    k: UNIT,
                });
                e.1.push(n);
            }
        }
    }
    let mut order: Vec<usize> = views_of.keys().copied().collect();
    order.sort_unstable();
    for j in order {
        let (views, xs) = &views_of[&j];
        if let Some(h) = triangulate_dlt(views, xs)
            && h[3].abs() > f64::EPSILON * h.xyz().norm()
        {
            let x = h.xyz() / h[3];
            if x.iter().all(|v| v.is_finite()) {
                points[j] = Some([x.x, x.y, x.z]);
            }
        }
    }
    (poses, points)
}

/// Initializes the poses and points of `rec` from its tracks; the report has
/// `complete_tracks`, `placed_points`, `reprojection_rms_px` (perspective, over the
/// observations explained) and `unexplained_observations`.
pub fn affine_init(rec: &Reconstruction) -> Result<(Reconstruction, Metrics), String> {
    if rec.images.len() < 2 {
        return Err(format!("need at least 2 images, got {}", rec.images.len()));
    }
    let obs = observations(rec)?;
    // Tracks seen exactly once in every image.
    let mut per_point: Vec<Vec<usize>> = vec![Vec::new(); rec.points.len()];
    for (f, seen) in obs.iter().enumerate() {
        for &(j, _, _) in seen {
            if per_point[j].last().is_none_or(|&g| g != f) {
                per_point[j].push(f);
            } else {
                // Seen twice in one image: not a usable track for the factorization.
                per_point[j].push(usize::MAX);
            }
        }
    }
    let complete: Vec<usize> = (0..rec.points.len())
        .filter(|&j| {
            per_point[j].len() == obs.len() && per_point[j].iter().all(|&f| f != usize::MAX)
        })
        .collect();
    if complete.len() < 4 {
        return Err(format!(
            "the factorization needs at least 4 points seen in every image, found {}",
            complete.len()
        ));
    }
    let slot: HashMap<usize, usize> = complete.iter().enumerate().map(|(k, &j)| (j, k)).collect();
    let mut views = vec![vec![[0.0; 2]; complete.len()]; obs.len()];
    for (f, seen) in obs.iter().enumerate() {
        for &(j, n, _) in seen {
            if let Some(&k) = slot.get(&j) {
                views[f][k] = n;
            }
        }
    }
    let fact = affine_factorization(&views)?;
    let candidates = [false, true].map(|reflect| {
        let c = candidate(&obs, &complete, &fact, reflect, rec.points.len());
        let s = score(rec, &obs, &c);
        (c, s)
    });
    // Fewer unexplained observations first, then the smaller error.
    let best = if (candidates[1].1.1, candidates[1].1.0) < (candidates[0].1.1, candidates[0].1.0) {
        1
    } else {
        0
    };
    let ((poses, points), (sq, failures)) = &candidates[best];
    let mut out = rec.clone();
    for (im, (r, t)) in out.images.iter_mut().zip(poses) {
        let mut rm = [0.0; 9];
        for a in 0..3 {
            for b in 0..3 {
                rm[3 * a + b] = r[(a, b)];
            }
        }
        im.camera_from_world = Pose::from_rotation_matrix(&rm, [t.x, t.y, t.z]);
    }
    let mut placed = 0usize;
    for (p, x) in out.points.iter_mut().zip(points) {
        if let Some(x) = x {
            p.position = *x;
            placed += 1;
        }
    }
    let total: usize = obs.iter().map(Vec::len).sum();
    let explained = total - failures;
    let mut m = Metrics::new();
    m.insert("complete_tracks".into(), complete.len() as f64);
    m.insert("placed_points".into(), placed as f64);
    m.insert(
        "reprojection_rms_px".into(),
        if explained > 0 {
            (sq / explained as f64).sqrt()
        } else {
            0.0
        },
    );
    m.insert("unexplained_observations".into(), *failures as f64);
    m.insert("depth_reversed".into(), best as f64);
    Ok((out, m))
}

/// `optimize.affine_init`. See the module doc.
pub struct AffineInit;

impl Op for AffineInit {
    type Params = NoParams;
    const ID: &'static str = "optimize.affine_init";
    const SUMMARY: &'static str =
        "Initializes poses and points from 2-D tracks by Tomasi–Kanade affine factorization.";
    const DOC: &'static str = r#"
Recovers every image's pose and the 3-D points of a reconstruction from its tracks alone (the
cameras' intrinsics and distortion are known and kept; the input poses and positions are
ignored). The tracks seen in every image are factorized under a scaled orthographic camera
(Tomasi & Kanade 1992, with the metric upgrade), each view's rotation and mean depth are read
from its motion rows, the depth-reversal ambiguity is settled by the perspective reprojection
error, and points seen in only some images are triangulated (linear DLT). Needs ≥ 2 images and
≥ 4 points seen in every image. The result is a weak-perspective approximation meant as the
start of optimize.bundle_adjust; its world frame is the tracks' centroid, up to a similarity.

Report: complete_tracks, placed_points, reprojection_rms_px (perspective, over the explained
observations), unexplained_observations (behind a camera or not triangulable), depth_reversed
(1 when the reflected solution was kept).

Reference: Tomasi & Kanade, "Shape and motion from image streams under orthography: a
factorization method", IJCV 9(2), 1992.

Example:
    "init": (op: "optimize.affine_init", inputs: { "reconstruction": "tracks.reconstruction" }),
    "ba":   (op: "optimize.bundle_adjust", inputs: { "reconstruction": "init.reconstruction" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "reconstruction",
            PortType::Reconstruction,
            "Cameras, images and their 2-D observations linked to point ids.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "The reconstruction with initialized poses and points.",
            ),
            PortSpec::new(
                "report",
                PortType::Metrics,
                "complete_tracks, placed_points, reprojection_rms_px, unexplained_observations.",
            ),
        ]
    }

    fn new(_: NoParams) -> Result<Self, String> {
        Ok(AffineInit)
    }
}

impl Operator for AffineInit {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let rec = match inputs.require("reconstruction")? {
            Value::Reconstruction(r) => r,
            _ => {
                return Err(OpError::input(
                    "reconstruction",
                    "expected a Reconstruction",
                ));
            }
        };
        let (out, report) = affine_init(rec).map_err(|e| OpError::input("reconstruction", e))?;
        Ok(Outputs::new()
            .with("reconstruction", Value::Reconstruction(Arc::new(out)))
            .with("report", Value::metrics(report)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::ba::BaOptions;
    use crate::optimize::bundle_adjust::{Mode, bundle_adjust, problem_to_reconstruction};
    use crate::optimize::synthetic::{SyntheticOptions, synthetic_problem};

    /// A distant ring scene (nearly affine) with every point seen by every camera.
    fn scene() -> Reconstruction {
        let (truth, _) = synthetic_problem(&SyntheticOptions {
            cameras: 5,
            points: 60,
            seed: 3,
            noise_px: 0.0,
            visibility: 1.0,
            ..SyntheticOptions::default()
        })
        .unwrap();
        problem_to_reconstruction(&truth, [640, 480])
    }

    #[test]
    fn initializes_a_scene_that_bundle_adjustment_finishes() {
        let truth = scene();
        // Scramble the poses and points: the initializer must not read them.
        let mut scrambled = truth.clone();
        for im in &mut scrambled.images {
            im.camera_from_world = Pose::from_rotation_matrix(
                &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                [0.0, 0.0, 0.0],
            );
        }
        for p in &mut scrambled.points {
            p.position = [0.0; 3];
        }
        let (init, report) = affine_init(&scrambled).unwrap();
        assert_eq!(report["placed_points"], truth.points.len() as f64);
        assert!(report["complete_tracks"] >= 4.0);
        // Weak perspective on this ring: a rough but usable start.
        let rms0 = report["reprojection_rms_px"];
        assert!(rms0.is_finite() && rms0 < 60.0, "{report:?}");
        let (refined, ba, _) = bundle_adjust(
            &init,
            &BaOptions {
                max_iterations: 200,
                ..BaOptions::default()
            },
            Mode::Full,
            false,
            false,
        )
        .unwrap();
        assert!(
            ba["reprojection_rms_px"] < 1e-3 * rms0.max(1.0),
            "{ba:?} from {report:?}"
        );
        // Up to a similarity: relative camera distances match the truth's.
        let centre = |rec: &Reconstruction, i: usize| {
            let p = &rec.images[i].camera_from_world;
            let r = Matrix3::from_row_slice(&p.rotation_matrix());
            -(r.transpose() * Vector3::from(p.translation))
        };
        let ratio = |rec: &Reconstruction| {
            (centre(rec, 0) - centre(rec, 1)).norm() / (centre(rec, 0) - centre(rec, 2)).norm()
        };
        assert!(
            (ratio(&refined) - ratio(&truth)).abs() < 1e-4 * ratio(&truth),
            "{} vs {}",
            ratio(&refined),
            ratio(&truth)
        );
    }

    #[test]
    fn too_few_images_or_tracks_are_errors() {
        let truth = scene();
        let mut one = truth.clone();
        one.images.truncate(1);
        assert!(affine_init(&one).is_err());
        let mut sparse = truth.clone();
        // The first image keeps 3 of its tracks: 3 complete tracks at most.
        for (_, id) in sparse.images[0].points2d.iter_mut().skip(3) {
            *id = None;
        }
        let err = affine_init(&sparse).unwrap_err();
        assert!(err.contains("at least 4 points"), "{err}");
        let mut bad = truth;
        bad.images[0].points2d[0].0 = [f64::NAN, 0.0];
        assert!(affine_init(&bad).is_err());
    }
}
