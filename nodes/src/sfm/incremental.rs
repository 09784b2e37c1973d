//! `sfm.incremental`: incremental structure from motion — initial pair, next-view
//! registration by PnP-RANSAC, triangulation, local and global bundle adjustment, outlier
//! filtering and re-triangulation — after Schönberger & Frahm, "Structure-from-motion
//! revisited" (CVPR 2016) and COLMAP's incremental mapper.
//!
//! 1. **Initial pair.** Candidate pairs share at least `init_min_points` tracks; pairs the
//!    two-view verification did not label planar or panoramic come first, then by shared
//!    tracks. For each candidate the relative pose is recovered with model selection (E vs H
//!    vs pure rotation by GRIC, [`relative_pose`]) and the shared tracks are triangulated; the
//!    pair is accepted when at least `init_min_points` points lie in front of both cameras
//!    within `max_reprojection_error_px` and their median triangulation angle reaches
//!    `init_min_tri_angle_deg`. When no candidate has that parallax the reconstruction fails
//!    with "not enough parallax" and no points.
//! 2. **Next view.** The unregistered image seeing the most reconstructed points is
//!    registered by P3P in LO-RANSAC (threshold `abs_pose_threshold_px`) and
//!    Levenberg–Marquardt refinement on the inliers; it needs `abs_pose_min_inliers` inliers
//!    and `abs_pose_min_inlier_ratio` of its 2-D–3-D correspondences. Images that fail are
//!    retried once the model has grown.
//! 3. **Triangulation.** Every track with two or more registered observations and no point is
//!    triangulated (multi-view DLT; when that fails, the best two-view DLT among its first
//!    observations, kept when it explains the most observations): observations within
//!    `max_reprojection_error_px` and in front of their camera are kept, and the point needs
//!    two of them seen under at least `min_tri_angle_deg`.
//! 4. **Bundle adjustment** ([`crate::optimize::ba`], Schur complement): after each
//!    registration a local adjustment of the new image and its `local_ba_images − 1` most
//!    connected registered images (the points they see free, the other cameras seeing those
//!    points fixed); a global adjustment whenever the number of registered images has grown by
//!    the factor `global_ba_ratio` since the last one, and at the end. Each is followed by
//!    filtering (observations beyond `max_reprojection_error_px` or behind their camera
//!    removed, points left with fewer than two observations or a triangulation angle below
//!    `min_tri_angle_deg` deleted), and a global one by re-triangulation of the tracks without
//!    a point and completion of every point's track in the registered images.
//!
//! Intrinsics: with `cameras`, each image's camera is used (keypoints undistorted into its
//! pinhole; non-square pixels are rescaled to square ones, an exact change of coordinates) and
//! held fixed. Without, one shared pinhole camera with the principal point at the image centre
//! and focal length `focal_px` (or 1.2 × the larger image side when 0, COLMAP's default prior)
//! is used; with `refine_focal` the global adjustments refine that shared focal length.
//!
//! Determinism: every step runs in a fixed order and the RANSAC streams are seeded by `seed`
//! and the image index; bundle adjustment is thread-count independent, so the reconstruction
//! is bit-identical for any thread count.

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{Matrix3, Vector3};
use ocellus_engine::value::{
    Camera, CameraModel, Image, Keypoint, Metrics, PixelData, ReconImage, ReconPoint,
    Reconstruction, TrackElement, Tracks, Value,
};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, params,
};

use super::pairs::{PairModel, camera_list, image_points, keypoint_lists, list_items, read_pairs};
use crate::geometry::pnp::{CameraPose, P3pEstimator, PnpPair, refine_pose};
use crate::geometry::pose_util::{Intrinsics, pose_from_rt};
use crate::geometry::ransac::{Method, RobustOptions, estimate};
use crate::geometry::relative_pose::{MotionModel, RelativePoseOptions, relative_pose};
use crate::geometry::triangulate::{View, triangulate_dlt};
use crate::optimize::ba::{BaCamera, BaObservation, BaOptions, BaProblem, CAMERA_DOF, solve};
use crate::optimize::bundle_adjust::{Mode, bundle_adjust};

const NONE: u32 = u32::MAX;

/// A triangulated position and the observations it explains.
type Candidate = Option<(Vector3<f64>, Vec<(u32, u32)>)>;

/// Settings of [`reconstruct`]; see the module documentation.
#[derive(Debug, Clone, PartialEq)]
pub struct SfmOptions {
    /// Focal length prior without cameras, pixels; 0 = 1.2 × the larger image side.
    pub focal_px: f64,
    /// Refine the shared focal length in global adjustments (without cameras only).
    pub refine_focal: bool,
    /// Fewest triangulated points of the initial pair.
    pub init_min_points: usize,
    /// Smallest median triangulation angle of the initial pair, degrees.
    pub init_min_tri_angle_deg: f64,
    /// Most candidate initial pairs tried.
    pub init_max_pairs: usize,
    /// Smallest triangulation angle of a point, degrees.
    pub min_tri_angle_deg: f64,
    /// Largest reprojection error of a kept observation, pixels.
    pub max_reprojection_error_px: f64,
    /// PnP-RANSAC inlier threshold, pixels.
    pub abs_pose_threshold_px: f64,
    /// Fewest PnP inliers of a registered image.
    pub abs_pose_min_inliers: usize,
    /// Smallest PnP inlier ratio of a registered image.
    pub abs_pose_min_inlier_ratio: f64,
    /// Images in a local adjustment (the new one included); 0 disables local adjustment.
    pub local_ba_images: usize,
    /// Growth factor of the registered image count between global adjustments.
    pub global_ba_ratio: f64,
    /// Most Levenberg–Marquardt iterations of an adjustment.
    pub ba_max_iterations: usize,
    /// Seed of the RANSAC streams.
    pub seed: u64,
}

impl Default for SfmOptions {
    fn default() -> Self {
        SfmOptions {
            focal_px: 0.0,
            refine_focal: true,
            init_min_points: 100,
            init_min_tri_angle_deg: 4.0,
            init_max_pairs: 30,
            min_tri_angle_deg: 1.5,
            max_reprojection_error_px: 4.0,
            abs_pose_threshold_px: 8.0,
            abs_pose_min_inliers: 30,
            abs_pose_min_inlier_ratio: 0.25,
            local_ba_images: 6,
            global_ba_ratio: 1.1,
            ba_max_iterations: 50,
            seed: 0,
        }
    }
}

/// Why a reconstruction could not be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SfmError {
    /// Inputs inconsistent with each other.
    #[error("{0}")]
    Input(String),
    /// No image pair shares enough tracks.
    #[error(
        "no image pair shares {needed} tracks (the most any pair shares is {best}); match more \
         features or lower init_min_points"
    )]
    TooFewCorrespondences {
        /// `init_min_points`.
        needed: usize,
        /// Most tracks any pair shares.
        best: usize,
    },
    /// No candidate pair has enough parallax to triangulate from.
    #[error(
        "not enough parallax: no image pair sees its shared points under a median \
         triangulation angle of {needed_deg}° (best {best_deg:.3}°); the views are too close \
         together (near-zero baseline or pure rotation)"
    )]
    NotEnoughParallax {
        /// `init_min_tri_angle_deg`.
        needed_deg: f64,
        /// The largest median angle found.
        best_deg: f64,
    },
    /// Initialization failed for another reason.
    #[error("no initial pair could be reconstructed: {0}")]
    NoInitialPair(String),
    /// A bundle adjustment failed.
    #[error("bundle adjustment failed: {0}")]
    Adjustment(String),
}

/// Inputs of [`reconstruct`].
#[derive(Debug, Clone)]
pub struct SfmInput<'a> {
    /// Keypoints per image.
    pub keypoints: Vec<&'a [Keypoint]>,
    /// Tracks over those keypoints.
    pub tracks: &'a Tracks,
    /// Image sizes (width, height), pixels.
    pub sizes: Vec<(u32, u32)>,
    /// Cameras per image, if calibrated.
    pub cameras: Option<Vec<Camera>>,
    /// Two-view configuration per pair, when known (ordering of the initial pairs).
    pub pair_models: Vec<(usize, usize, PairModel)>,
    /// Images for point colours, if given.
    pub images: Option<Vec<&'a Image>>,
    /// Image names.
    pub names: Vec<String>,
}

/// Counters of a run.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SfmStats {
    /// Initial pair.
    pub init_pair: (usize, usize),
    /// Median triangulation angle of the initial pair, degrees.
    pub init_angle_deg: f64,
    /// Local adjustments run.
    pub local_adjustments: usize,
    /// Global adjustments run.
    pub global_adjustments: usize,
    /// Registration attempts that failed.
    pub failed_registrations: usize,
}

#[derive(Debug, Clone)]
struct Point {
    x: Vector3<f64>,
    track: u32,
    /// (image, keypoint), sorted by image.
    obs: Vec<(u32, u32)>,
}

struct State<'a> {
    o: &'a SfmOptions,
    /// Square-pixel ideal pinhole pixels per image keypoint.
    pixels: Vec<Vec<[f64; 2]>>,
    k: Vec<Intrinsics>,
    tracks: &'a [Vec<TrackElement>],
    track_of: Vec<Vec<u32>>,
    poses: Vec<Option<CameraPose>>,
    points: Vec<Option<Point>>,
    point_of_track: Vec<u32>,
    stats: SfmStats,
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let c = a.dot(b) / (a.norm() * b.norm());
    if c.is_finite() {
        c.clamp(-1.0, 1.0).acos().to_degrees()
    } else {
        0.0
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

impl<'a> State<'a> {
    fn view(&self, img: usize) -> Option<View> {
        self.poses[img].map(|p| View {
            r: p.r,
            t: p.t,
            k: self.k[img],
        })
    }

    fn center(&self, img: usize) -> Option<Vector3<f64>> {
        self.poses[img].map(|p| -(p.r.transpose() * p.t))
    }

    /// Squared reprojection error of `x` in `img` at keypoint `kp`; ∞ behind the camera.
    fn error_sq(&self, img: usize, kp: usize, x: &Vector3<f64>) -> f64 {
        let Some(p) = self.poses[img] else {
            return f64::INFINITY;
        };
        let c = p.r * x + p.t;
        if c.z.is_nan() || c.z <= 0.0 {
            return f64::INFINITY;
        }
        let k = &self.k[img];
        let q = [k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy];
        let o = self.pixels[img][kp];
        (q[0] - o[0]).powi(2) + (q[1] - o[1]).powi(2)
    }

    /// Largest angle between the rays of two observations of `x`, degrees.
    fn max_angle(&self, x: &Vector3<f64>, obs: &[(u32, u32)]) -> f64 {
        let rays: Vec<Vector3<f64>> = obs
            .iter()
            .filter_map(|&(i, _)| self.center(i as usize).map(|c| c - x))
            .collect();
        let mut best = 0.0f64;
        for a in 0..rays.len() {
            for b in a + 1..rays.len() {
                best = best.max(angle_deg(&rays[a], &rays[b]));
            }
        }
        best
    }

    fn dlt(&self, obs: &[(u32, u32)]) -> Option<Vector3<f64>> {
        let views: Vec<View> = obs
            .iter()
            .filter_map(|&(i, _)| self.view(i as usize))
            .collect();
        let px: Vec<[f64; 2]> = obs
            .iter()
            .map(|&(i, k)| self.pixels[i as usize][k as usize])
            .collect();
        let h = triangulate_dlt(&views, &px)?;
        (h.w.abs() > 1e-12 * h.xyz().norm()).then(|| h.xyz() / h.w)
    }

    /// The observations of `obs` that `x` explains.
    fn inliers(&self, x: &Vector3<f64>, obs: &[(u32, u32)]) -> Vec<(u32, u32)> {
        let t2 = self.o.max_reprojection_error_px.powi(2);
        obs.iter()
            .copied()
            .filter(|&(i, k)| self.error_sq(i as usize, k as usize, x) <= t2)
            .collect()
    }

    /// Triangulates track `t` from its registered observations (see the module docs).
    fn triangulate_track(&self, t: usize) -> Option<Point> {
        let obs: Vec<(u32, u32)> = self.tracks[t]
            .iter()
            .filter(|e| self.poses[e.image as usize].is_some())
            .map(|e| (e.image, e.keypoint))
            .collect();
        if obs.len() < 2 {
            return None;
        }
        let mut best: Candidate = None;
        let consider = |best: &mut Candidate, x: Vector3<f64>| {
            if !x.iter().all(|v| v.is_finite()) {
                return;
            }
            let inl = self.inliers(&x, &obs);
            if inl.len() >= 2 && best.as_ref().is_none_or(|b| inl.len() > b.1.len()) {
                *best = Some((x, inl));
            }
        };
        if let Some(x) = self.dlt(&obs) {
            consider(&mut best, x);
        }
        if best.as_ref().is_none_or(|b| b.1.len() < obs.len()) {
            let m = obs.len().min(8);
            for a in 0..m {
                for b in a + 1..m {
                    if let Some(x) = self.dlt(&[obs[a], obs[b]]) {
                        consider(&mut best, x);
                    }
                }
            }
        }
        let (mut x, mut inl) = best?;
        // Re-fit on the inliers once.
        if inl.len() > 2
            && let Some(y) = self.dlt(&inl)
        {
            let again = self.inliers(&y, &obs);
            if again.len() >= inl.len() {
                x = y;
                inl = again;
            }
        }
        if inl.len() < 2 || self.max_angle(&x, &inl) < self.o.min_tri_angle_deg {
            return None;
        }
        Some(Point {
            x,
            track: t as u32,
            obs: inl,
        })
    }

    fn add_point(&mut self, p: Point) {
        self.point_of_track[p.track as usize] = self.points.len() as u32;
        self.points.push(Some(p));
    }

    fn delete_point(&mut self, id: usize) {
        if let Some(p) = self.points[id].take() {
            self.point_of_track[p.track as usize] = NONE;
        }
    }

    /// Triangulates every track with ≥ 2 registered observations and no point, among those
    /// seen by `image` (or all when `None`).
    fn triangulate_new(&mut self, image: Option<usize>) -> usize {
        let candidates: Vec<usize> = match image {
            Some(img) => {
                let mut v: Vec<usize> = self.track_of[img]
                    .iter()
                    .filter(|&&t| t != NONE)
                    .map(|&t| t as usize)
                    .collect();
                v.sort_unstable();
                v.dedup();
                v
            }
            None => (0..self.tracks.len()).collect(),
        };
        let mut made = 0;
        for t in candidates {
            if self.point_of_track[t] != NONE {
                continue;
            }
            if let Some(p) = self.triangulate_track(t) {
                self.add_point(p);
                made += 1;
            }
        }
        made
    }

    /// Adds to every point the registered observations of its track that it explains.
    fn complete_tracks(&mut self) {
        let t2 = self.o.max_reprojection_error_px.powi(2);
        for id in 0..self.points.len() {
            let Some(p) = &self.points[id] else { continue };
            let mut add = Vec::new();
            for e in &self.tracks[p.track as usize] {
                let (i, k) = (e.image as usize, e.keypoint as usize);
                if self.poses[i].is_some()
                    && !p.obs.iter().any(|o| o.0 == e.image)
                    && self.error_sq(i, k, &p.x) <= t2
                {
                    add.push((e.image, e.keypoint));
                }
            }
            if !add.is_empty()
                && let Some(p) = &mut self.points[id]
            {
                p.obs.extend(add);
                p.obs.sort_unstable();
            }
        }
    }

    /// Removes bad observations and points (see the module docs) among the points seen by
    /// `images` (all points when `None`). Returns the observations removed.
    fn filter(&mut self, images: Option<&[bool]>) -> usize {
        let t2 = self.o.max_reprojection_error_px.powi(2);
        let mut removed = 0;
        for id in 0..self.points.len() {
            let Some(p) = &self.points[id] else { continue };
            if let Some(sel) = images
                && !p.obs.iter().any(|o| sel[o.0 as usize])
            {
                continue;
            }
            let keep: Vec<(u32, u32)> = p
                .obs
                .iter()
                .copied()
                .filter(|&(i, k)| self.error_sq(i as usize, k as usize, &p.x) <= t2)
                .collect();
            removed += p.obs.len() - keep.len();
            let bad = keep.len() < 2 || self.max_angle(&p.x, &keep) < self.o.min_tri_angle_deg;
            if bad {
                removed += keep.len();
                self.delete_point(id);
            } else if let Some(p) = &mut self.points[id] {
                p.obs = keep;
            }
        }
        removed
    }

    fn registered(&self) -> usize {
        self.poses.iter().filter(|p| p.is_some()).count()
    }

    /// Bundle adjustment with the cameras `free` (registered images only) and every point
    /// seen by a free camera; other cameras seeing those points are held fixed. When every
    /// involved camera is free, `anchor` is held fixed (the gauge).
    fn adjust(&mut self, free: &[bool], anchor: usize) -> Result<(), SfmError> {
        let n = self.poses.len();
        let point_ids: Vec<usize> = (0..self.points.len())
            .filter(|&id| {
                self.points[id]
                    .as_ref()
                    .is_some_and(|p| p.obs.iter().any(|o| free[o.0 as usize]))
            })
            .collect();
        if point_ids.is_empty() {
            return Ok(());
        }
        let mut involved = vec![false; n];
        for &id in &point_ids {
            if let Some(p) = &self.points[id] {
                for o in &p.obs {
                    involved[o.0 as usize] = true;
                }
            }
        }
        let mut camera_index = vec![NONE; n];
        let mut problem = BaProblem::default();
        let mut images = Vec::new();
        let all_free = (0..n).all(|i| !involved[i] || free[i]);
        for i in 0..n {
            let Some(pose) = self.poses[i].filter(|_| involved[i]) else {
                continue;
            };
            camera_index[i] = problem.cameras.len() as u32;
            images.push(i);
            let r = pose.r;
            problem.cameras.push(BaCamera {
                rotation: [
                    r[(0, 0)],
                    r[(0, 1)],
                    r[(0, 2)],
                    r[(1, 0)],
                    r[(1, 1)],
                    r[(1, 2)],
                    r[(2, 0)],
                    r[(2, 1)],
                    r[(2, 2)],
                ],
                translation: [pose.t.x, pose.t.y, pose.t.z],
                intrinsics: [self.k[i].fx, 0.0, 0.0],
                principal_point: [self.k[i].cx, self.k[i].cy],
            });
            let mut dof = [false; CAMERA_DOF];
            if free[i] && !(all_free && i == anchor) {
                dof[..6].fill(true);
            }
            problem.camera_free.push(dof);
        }
        for (j, &id) in point_ids.iter().enumerate() {
            if let Some(p) = &self.points[id] {
                problem.points.push([p.x.x, p.x.y, p.x.z]);
                for &(i, k) in &p.obs {
                    problem.observations.push(BaObservation {
                        camera: camera_index[i as usize],
                        point: j as u32,
                        xy: self.pixels[i as usize][k as usize],
                    });
                }
            }
        }
        let options = BaOptions {
            max_iterations: self.o.ba_max_iterations,
            ..BaOptions::default()
        };
        solve(&mut problem, &options).map_err(SfmError::Adjustment)?;
        for (c, &i) in problem.cameras.iter().zip(&images) {
            if !free[i] {
                continue;
            }
            let r = Matrix3::from_row_slice(&c.rotation);
            self.poses[i] = Some(CameraPose {
                r,
                t: Vector3::from(c.translation),
            });
        }
        for (x, &id) in problem.points.iter().zip(&point_ids) {
            if let Some(p) = &mut self.points[id] {
                p.x = Vector3::from(*x);
            }
        }
        Ok(())
    }

    /// Registered points seen by each unregistered image.
    fn visible_points(&self, img: usize) -> Vec<(usize, usize)> {
        self.track_of[img]
            .iter()
            .enumerate()
            .filter(|(_, t)| **t != NONE && self.point_of_track[**t as usize] != NONE)
            .map(|(kp, t)| (kp, self.point_of_track[*t as usize] as usize))
            .collect()
    }

    /// Registers `img` by PnP-RANSAC; `true` on success.
    fn register(&mut self, img: usize) -> bool {
        let vis = self.visible_points(img);
        let o = self.o;
        if vis.len() < o.abs_pose_min_inliers.max(4) {
            return false;
        }
        let data: Vec<PnpPair> = vis
            .iter()
            .filter_map(|&(kp, id)| {
                self.points[id]
                    .as_ref()
                    .map(|p| (self.pixels[img][kp], [p.x.x, p.x.y, p.x.z]))
            })
            .collect();
        let options = RobustOptions {
            method: Method::LoRansac,
            threshold: o.abs_pose_threshold_px,
            confidence: 0.9999,
            max_trials: 10_000,
            seed: o.seed ^ (img as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            ..RobustOptions::default()
        };
        let Ok(report) = estimate(&P3pEstimator { k: self.k[img] }, &data, &options) else {
            return false;
        };
        if report.num_inliers < o.abs_pose_min_inliers
            || (report.num_inliers as f64) < o.abs_pose_min_inlier_ratio * data.len() as f64
        {
            return false;
        }
        let (px, world): (Vec<[f64; 2]>, Vec<[f64; 3]>) = data
            .iter()
            .zip(&report.inlier_mask)
            .filter(|(_, m)| **m)
            .map(|(d, _)| *d)
            .unzip();
        let pose = refine_pose(&self.k[img], &px, &world, &report.model, 50);
        if !(pose.r.iter().chain(pose.t.iter()).all(|v| v.is_finite())) {
            return false;
        }
        self.poses[img] = Some(pose);
        let t2 = o.max_reprojection_error_px.powi(2);
        for &(kp, id) in &vis {
            let ok = self.points[id]
                .as_ref()
                .is_some_and(|p| self.error_sq(img, kp, &p.x) <= t2);
            if ok && let Some(p) = &mut self.points[id] {
                p.obs.push((img as u32, kp as u32));
                p.obs.sort_unstable();
            }
        }
        true
    }

    /// The `local_ba_images − 1` registered images sharing most points with `img`, and `img`.
    fn local_set(&self, img: usize) -> Vec<bool> {
        let n = self.poses.len();
        let mut shared = vec![0usize; n];
        for p in self.points.iter().flatten() {
            if p.obs.iter().any(|o| o.0 as usize == img) {
                for o in &p.obs {
                    shared[o.0 as usize] += 1;
                }
            }
        }
        let mut order: Vec<usize> = (0..n)
            .filter(|&i| i != img && self.poses[i].is_some() && shared[i] > 0)
            .collect();
        order.sort_by(|&a, &b| shared[b].cmp(&shared[a]).then(a.cmp(&b)));
        let mut free = vec![false; n];
        free[img] = true;
        for &i in order.iter().take(self.o.local_ba_images.saturating_sub(1)) {
            free[i] = true;
        }
        free
    }
}

/// Tries the candidate initial pairs; see the module documentation.
fn initialize(
    st: &mut State<'_>,
    pair_models: &[(usize, usize, PairModel)],
) -> Result<(), SfmError> {
    let n = st.poses.len();
    // Tracks shared by each pair.
    let mut shared: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for t in st.tracks {
        for a in 0..t.len() {
            for b in a + 1..t.len() {
                let (i, j) = (t[a].image as usize, t[b].image as usize);
                *shared.entry((i.min(j), i.max(j))).or_default() += 1;
            }
        }
    }
    let planar: std::collections::BTreeSet<(usize, usize)> = pair_models
        .iter()
        .filter(|p| p.2 == PairModel::PlanarOrPanoramic)
        .map(|p| (p.0.min(p.1), p.0.max(p.1)))
        .collect();
    let best_shared = shared.values().copied().max().unwrap_or(0);
    let mut candidates: Vec<((usize, usize), usize)> = shared
        .iter()
        .filter(|(_, c)| **c >= st.o.init_min_points)
        .map(|(k, c)| (*k, *c))
        .collect();
    if candidates.is_empty() {
        return Err(SfmError::TooFewCorrespondences {
            needed: st.o.init_min_points,
            best: best_shared,
        });
    }
    candidates.sort_by(|a, b| {
        planar
            .contains(&a.0)
            .cmp(&planar.contains(&b.0))
            .then(b.1.cmp(&a.1))
            .then(a.0.cmp(&b.0))
    });
    let mut best_angle = 0.0f64;
    let mut last_error = String::new();
    let robust = |threshold: f64, salt: u64| RobustOptions {
        method: Method::LoRansac,
        threshold,
        confidence: 0.9999,
        max_trials: 10_000,
        seed: st.o.seed ^ salt,
        ..RobustOptions::default()
    };
    let rp_options = RelativePoseOptions {
        h: robust(4.0, 11),
        e: robust(st.o.max_reprojection_error_px.min(2.0), 13),
        sigma_px: 1.0,
        refine: true,
        rotation_px: 1.0,
        min_parallax_deg: 0.5,
    };
    for &((i, j), _) in candidates.iter().take(st.o.init_max_pairs) {
        // Correspondences of the tracks seen by both.
        let mut common = Vec::new();
        for (t, els) in st.tracks.iter().enumerate() {
            let a = els.iter().find(|e| e.image as usize == i);
            let b = els.iter().find(|e| e.image as usize == j);
            if let (Some(a), Some(b)) = (a, b) {
                common.push((t, a.keypoint as usize, b.keypoint as usize));
            }
        }
        let data: Vec<[[f64; 2]; 2]> = common
            .iter()
            .map(|&(_, a, b)| [st.pixels[i][a], st.pixels[j][b]])
            .collect();
        let rel = match relative_pose(&data, &st.k[i], &st.k[j], &rp_options) {
            Ok(r) => r,
            Err(e) => {
                last_error = format!("images {i} and {j}: {e}");
                continue;
            }
        };
        if rel.model == MotionModel::Rotation {
            continue;
        }
        st.poses[i] = Some(CameraPose {
            r: Matrix3::identity(),
            t: Vector3::zeros(),
        });
        st.poses[j] = Some(CameraPose { r: rel.r, t: rel.t });
        let mut made = Vec::new();
        let mut angles = Vec::new();
        for (&(t, a, b), &ok) in common.iter().zip(&rel.mask) {
            if !ok {
                continue;
            }
            let obs = [(i as u32, a as u32), (j as u32, b as u32)];
            let Some(x) = st.dlt(&obs) else { continue };
            if st.inliers(&x, &obs).len() < 2 {
                continue;
            }
            let angle = st.max_angle(&x, &obs);
            angles.push(angle);
            if angle >= st.o.min_tri_angle_deg {
                made.push(Point {
                    x,
                    track: t as u32,
                    obs: obs.to_vec(),
                });
            }
        }
        let angle = median(angles);
        best_angle = best_angle.max(angle);
        if made.len() >= st.o.init_min_points && angle >= st.o.init_min_tri_angle_deg {
            for p in made {
                st.add_point(p);
            }
            st.stats.init_pair = (i, j);
            st.stats.init_angle_deg = angle;
            let mut free = vec![false; n];
            free[i] = true;
            free[j] = true;
            st.adjust(&free, i)?;
            st.stats.global_adjustments += 1;
            st.filter(None);
            return Ok(());
        }
        st.poses[i] = None;
        st.poses[j] = None;
    }
    if best_angle < st.o.init_min_tri_angle_deg {
        Err(SfmError::NotEnoughParallax {
            needed_deg: st.o.init_min_tri_angle_deg,
            best_deg: best_angle,
        })
    } else {
        Err(SfmError::NoInitialPair(if last_error.is_empty() {
            format!(
                "no candidate pair kept {} points after triangulation",
                st.o.init_min_points
            )
        } else {
            last_error
        }))
    }
}

/// The result of [`reconstruct`].
#[derive(Debug, Clone, PartialEq)]
pub struct SfmResult {
    /// The reconstruction (registered images only, ids `index + 1`).
    pub reconstruction: Reconstruction,
    /// Counters.
    pub stats: SfmStats,
    /// Final shared focal length without cameras, pixels (NaN with cameras).
    pub focal_px: f64,
}

/// Runs incremental SfM; see the module documentation.
pub fn reconstruct(input: &SfmInput<'_>, o: &SfmOptions) -> Result<SfmResult, SfmError> {
    let n = input.keypoints.len();
    if input.sizes.len() != n || input.names.len() != n {
        return Err(SfmError::Input(format!(
            "{n} keypoint sets but {} image sizes and {} names",
            input.sizes.len(),
            input.names.len()
        )));
    }
    let (mut pixels, ks) =
        image_points(&input.keypoints, input.cameras.as_deref()).map_err(SfmError::Input)?;
    let (k, shared_focal): (Vec<Intrinsics>, Option<f64>) = match &ks {
        Some(ks) => {
            // Square pixels: y' = cy + (y − cy)·fx/fy.
            for (p, k) in pixels.iter_mut().zip(ks) {
                let s = k.fx / k.fy;
                if s != 1.0 {
                    for q in p.iter_mut() {
                        q[1] = k.cy + (q[1] - k.cy) * s;
                    }
                }
            }
            let square = ks.iter().map(|k| Intrinsics { fy: k.fx, ..*k }).collect();
            (square, None)
        }
        None => {
            let (w, h) = input.sizes.first().copied().unwrap_or((0, 0));
            if input.sizes.iter().any(|&s| s != (w, h)) {
                return Err(SfmError::Input(
                    "without cameras all images must have the same size (one shared camera)".into(),
                ));
            }
            let f = if o.focal_px > 0.0 {
                o.focal_px
            } else {
                1.2 * f64::from(w.max(h))
            };
            let k = Intrinsics {
                fx: f,
                fy: f,
                cx: f64::from(w) / 2.0 - 0.5,
                cy: f64::from(h) / 2.0 - 0.5,
            };
            (vec![k; n], Some(f))
        }
    };
    let tracks = &input.tracks.tracks;
    let mut track_of: Vec<Vec<u32>> = input
        .keypoints
        .iter()
        .map(|k| vec![NONE; k.len()])
        .collect();
    for (t, els) in tracks.iter().enumerate() {
        for e in els {
            let (i, kp) = (e.image as usize, e.keypoint as usize);
            if i >= n || kp >= track_of[i].len() {
                return Err(SfmError::Input(format!(
                    "track {t} observes keypoint {kp} of image {i}, which does not exist"
                )));
            }
            if track_of[i][kp] != NONE {
                return Err(SfmError::Input(format!(
                    "keypoint {kp} of image {i} is in tracks {} and {t}",
                    track_of[i][kp]
                )));
            }
            track_of[i][kp] = t as u32;
        }
    }
    let mut st = State {
        o,
        pixels,
        k,
        tracks,
        track_of,
        poses: vec![None; n],
        points: Vec::new(),
        point_of_track: vec![NONE; tracks.len()],
        stats: SfmStats::default(),
    };
    let mut focal = shared_focal;
    initialize(&mut st, &input.pair_models)?;
    let anchor = st.stats.init_pair.0;
    let mut last_global = st.registered();
    // Registered count when an image last failed.
    let mut failed_at: Vec<usize> = vec![0; n];
    loop {
        let mut order: Vec<(usize, usize)> = (0..n)
            .filter(|&i| st.poses[i].is_none() && failed_at[i] < st.registered())
            .map(|i| (st.visible_points(i).len(), i))
            .filter(|(c, _)| *c >= o.abs_pose_min_inliers.max(4))
            .collect();
        order.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut registered_one = None;
        for &(_, img) in &order {
            if st.register(img) {
                registered_one = Some(img);
                break;
            }
            failed_at[img] = st.registered();
            st.stats.failed_registrations += 1;
        }
        let Some(img) = registered_one else { break };
        st.triangulate_new(Some(img));
        if o.local_ba_images > 0 {
            let free = st.local_set(img);
            st.adjust(&free, anchor)?;
            st.stats.local_adjustments += 1;
            st.filter(Some(&free));
        }
        if st.registered() as f64 >= o.global_ba_ratio * last_global as f64 {
            global_round(&mut st, anchor, &mut focal, input)?;
            last_global = st.registered();
        }
    }
    global_round(&mut st, anchor, &mut focal, input)?;
    global_round(&mut st, anchor, &mut focal, input)?;
    Ok(SfmResult {
        reconstruction: to_reconstruction(&st, input, focal),
        stats: st.stats,
        focal_px: focal.unwrap_or(f64::NAN),
    })
}

/// Global adjustment (refining the shared focal length when asked), filtering,
/// re-triangulation and track completion.
fn global_round(
    st: &mut State<'_>,
    anchor: usize,
    focal: &mut Option<f64>,
    input: &SfmInput<'_>,
) -> Result<(), SfmError> {
    let free: Vec<bool> = st.poses.iter().map(|p| p.is_some()).collect();
    match focal {
        Some(f) if st.o.refine_focal => {
            let rec = to_reconstruction(st, input, Some(*f));
            let options = BaOptions {
                max_iterations: st.o.ba_max_iterations,
                ..BaOptions::default()
            };
            let (refined, _, _) = bundle_adjust(&rec, &options, Mode::Full, true, false)
                .map_err(SfmError::Adjustment)?;
            read_back(st, &refined, focal);
        }
        _ => st.adjust(&free, anchor)?,
    }
    st.stats.global_adjustments += 1;
    st.filter(None);
    st.triangulate_new(None);
    st.complete_tracks();
    st.filter(None);
    Ok(())
}

/// Writes a reconstruction made by [`to_reconstruction`] (and adjusted) back into the state.
fn read_back(st: &mut State<'_>, rec: &Reconstruction, focal: &mut Option<f64>) {
    for im in &rec.images {
        let i = im.id as usize - 1;
        let r = Matrix3::from_row_slice(&im.camera_from_world.rotation_matrix());
        st.poses[i] = Some(CameraPose {
            r,
            t: Vector3::from(im.camera_from_world.translation),
        });
    }
    // Point ids are 1, 2, ... over the live points in order.
    let live: Vec<usize> = (0..st.points.len())
        .filter(|&i| st.points[i].is_some())
        .collect();
    for p in &rec.points {
        let Some(&id) = (p.id as usize).checked_sub(1).and_then(|k| live.get(k)) else {
            continue;
        };
        if let Some(q) = &mut st.points[id] {
            q.x = Vector3::from(p.position);
        }
    }
    if let (Some(f), Some(c)) = (focal.as_mut(), rec.cameras.get(&1))
        && let Some(&nf) = c.params.first()
        && nf.is_finite()
        && nf > 0.0
    {
        *f = nf;
        for k in &mut st.k {
            k.fx = nf;
            k.fy = nf;
        }
    }
}

fn srgb_byte(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

/// sRGB colour of `image` at the nearest pixel to `(x, y)`: 8-bit samples as they are, 16-bit
/// scaled, float samples taken as linear and encoded.
fn colour_at(image: &Image, x: f64, y: f64) -> [u8; 3] {
    let (w, h) = (image.width(), image.height());
    if w == 0 || h == 0 {
        return [0; 3];
    }
    let xi = (x.round().max(0.0) as usize).min(w - 1);
    let yi = (y.round().max(0.0) as usize).min(h - 1);
    let c = image.channels().count();
    let at = (yi * w + xi) * c;
    let pick = |s: usize| if c >= 3 { at + s } else { at };
    match image.data() {
        PixelData::U8(d) => [d[pick(0)], d[pick(1)], d[pick(2)]],
        PixelData::U16(d) => [0, 1, 2].map(|s| (d[pick(s)] >> 8) as u8),
        PixelData::F32(d) => [0, 1, 2].map(|s| srgb_byte(d[pick(s)])),
    }
}

/// The state as a reconstruction: registered images (id = index + 1) with their keypoints in
/// the input's pixels, live points (ids 1, 2, ... in order), cameras as given or one shared
/// `SIMPLE_PINHOLE` camera.
fn to_reconstruction(st: &State<'_>, input: &SfmInput<'_>, focal: Option<f64>) -> Reconstruction {
    let n = st.poses.len();
    let mut cameras = BTreeMap::new();
    match (&input.cameras, focal) {
        (Some(cams), _) => {
            for (i, c) in cams.iter().enumerate() {
                if st.poses[i].is_some() {
                    cameras.insert(i as u32 + 1, c.clone());
                }
            }
        }
        (None, f) => {
            let (w, h) = input.sizes.first().copied().unwrap_or((0, 0));
            cameras.insert(
                1,
                Camera {
                    model: CameraModel::SimplePinhole,
                    width: w,
                    height: h,
                    params: vec![
                        f.unwrap_or(1.0),
                        f64::from(w) / 2.0 - 0.5,
                        f64::from(h) / 2.0 - 0.5,
                    ],
                },
            );
        }
    }
    let mut point_id_of = vec![0u64; st.points.len()];
    let mut next = 1u64;
    for (id, p) in st.points.iter().enumerate() {
        if p.is_some() {
            point_id_of[id] = next;
            next += 1;
        }
    }
    let mut images = Vec::new();
    for i in 0..n {
        let Some(pose) = st.poses[i] else { continue };
        let points2d = input.keypoints[i]
            .iter()
            .enumerate()
            .map(|(kp, k)| {
                let t = st.track_of[i][kp];
                let id = (t != NONE)
                    .then(|| st.point_of_track[t as usize])
                    .filter(|&p| p != NONE)
                    .and_then(|p| {
                        st.points[p as usize]
                            .as_ref()
                            .filter(|q| q.obs.iter().any(|o| o.0 as usize == i))
                            .map(|_| point_id_of[p as usize])
                    });
                ([f64::from(k.x), f64::from(k.y)], id)
            })
            .collect();
        images.push(ReconImage {
            id: i as u32 + 1,
            camera_id: if input.cameras.is_some() {
                i as u32 + 1
            } else {
                1
            },
            name: input.names[i].clone(),
            camera_from_world: pose_from_rt(&pose.r, &pose.t),
            points2d,
        });
    }
    let mut points = Vec::new();
    for (id, p) in st.points.iter().enumerate() {
        let Some(p) = p else { continue };
        let errors: Vec<f64> = p
            .obs
            .iter()
            .map(|&(i, k)| st.error_sq(i as usize, k as usize, &p.x).sqrt())
            .collect();
        let (i0, k0) = p.obs[0];
        let kp = &input.keypoints[i0 as usize][k0 as usize];
        let color = input
            .images
            .as_ref()
            .and_then(|ims| ims.get(i0 as usize))
            .map_or([128; 3], |im| {
                colour_at(im, f64::from(kp.x), f64::from(kp.y))
            });
        points.push(ReconPoint {
            id: point_id_of[id],
            position: [p.x.x, p.x.y, p.x.z],
            color,
            error_px: errors.iter().sum::<f64>() / errors.len().max(1) as f64,
            track: p.obs.iter().map(|&(i, k)| (i + 1, k)).collect(),
        });
    }
    Reconstruction {
        cameras,
        images,
        points,
    }
}

/// RMS reprojection error (pixels) and observation count of a reconstruction made by
/// [`reconstruct`].
pub fn reprojection_rms(result: &SfmResult, input: &SfmInput<'_>) -> (f64, usize) {
    let rec = &result.reconstruction;
    let mut sum = 0.0;
    let mut count = 0usize;
    let by_id: BTreeMap<u32, &ReconImage> = rec.images.iter().map(|i| (i.id, i)).collect();
    let (pixels, _) = match image_points(&input.keypoints, input.cameras.as_deref()) {
        Ok(p) => p,
        Err(_) => return (f64::NAN, 0),
    };
    for p in &rec.points {
        for &(img, kp) in &p.track {
            let Some(im) = by_id.get(&img) else { continue };
            let i = img as usize - 1;
            let (fx, fy, cx, cy) = match &input.cameras {
                Some(c) => {
                    let k = c[i].intrinsics();
                    (k.fx, k.fy, k.cx, k.cy)
                }
                None => {
                    let c = &rec.cameras[&1].params;
                    (c[0], c[0], c[1], c[2])
                }
            };
            let r = Matrix3::from_row_slice(&im.camera_from_world.rotation_matrix());
            let x = r * Vector3::from(p.position) + Vector3::from(im.camera_from_world.translation);
            let q = [fx * x.x / x.z + cx, fy * x.y / x.z + cy];
            let o = pixels[i][kp as usize];
            sum += (q[0] - o[0]).powi(2) + (q[1] - o[1]).powi(2);
            count += 1;
        }
    }
    ((sum / count.max(1) as f64).sqrt(), count)
}

params! {
    /// Parameters of `sfm.incremental`.
    pub struct IncrementalParams {
        /// Focal length prior without `cameras`, pixels; 0 = 1.2 × the larger image side.
        focal_px: f64 = 0.0 => [min = 0.0, unit = "px"],
        /// Refine the shared focal length in global adjustments (without `cameras` only).
        refine_focal: bool = true,
        /// Fewest triangulated points of the initial pair.
        init_min_points: u32 = 100 => [min = 8],
        /// Smallest median triangulation angle of the initial pair, degrees.
        init_min_tri_angle_deg: f64 = 4.0 => [min = 0.0, unit = "deg"],
        /// Most candidate initial pairs tried.
        init_max_pairs: u32 = 30 => [min = 1],
        /// Smallest triangulation angle of a point, degrees.
        min_tri_angle_deg: f64 = 1.5 => [min = 0.0, unit = "deg"],
        /// Largest reprojection error of a kept observation, pixels.
        max_reprojection_error_px: f64 = 4.0 => [min = 0.0, unit = "px"],
        /// PnP-RANSAC inlier threshold, pixels.
        abs_pose_threshold_px: f64 = 8.0 => [min = 0.0, unit = "px"],
        /// Fewest PnP inliers of a registered image.
        abs_pose_min_inliers: u32 = 30 => [min = 4],
        /// Smallest PnP inlier ratio of a registered image.
        abs_pose_min_inlier_ratio: f64 = 0.25 => [min = 0.0, max = 1.0],
        /// Images in a local bundle adjustment (the new one included); 0 disables it.
        local_ba_images: u32 = 6,
        /// Growth factor of the registered image count between global adjustments.
        global_ba_ratio: f64 = 1.1 => [min = 1.0],
        /// Most Levenberg–Marquardt iterations of an adjustment.
        ba_max_iterations: u32 = 50 => [min = 1],
        /// Seed of the RANSAC streams.
        seed: u64 = 0,
    }
}

/// `sfm.incremental`. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct Incremental {
    options: SfmOptions,
}

impl Op for Incremental {
    type Params = IncrementalParams;
    const ID: &'static str = "sfm.incremental";
    const SUMMARY: &'static str =
        "Incremental structure from motion: poses and points from feature tracks.";
    const DOC: &'static str = r#"
Incremental SfM after Schönberger & Frahm (CVPR 2016) and COLMAP's mapper: an initial pair
chosen by shared tracks and triangulation angle (relative pose with E/H/rotation model
selection), then repeatedly the image seeing most points registered by P3P LO-RANSAC and
refinement, new tracks triangulated, a local bundle adjustment of the new image and its
`local_ba_images − 1` best-connected neighbours, and a global adjustment (with
re-triangulation and track completion) whenever the model has grown by `global_ba_ratio`,
and at the end. Observations beyond `max_reprojection_error_px` and points under
`min_tri_angle_deg` are filtered after each adjustment.

Intrinsics: `cameras` (one per image, held fixed) or, without them, one shared pinhole camera
with its principal point at the image centre and focal length `focal_px` (0 = 1.2 × the larger
image side), refined in the global adjustments when `refine_focal`.

A set of views without parallax (near-zero baseline, pure rotation) fails with "not enough
parallax" instead of returning garbage.

Inputs: `keypoints` (List<Keypoints>), `tracks` (sfm.tracks), optional `pairs` (sfm.match_pairs:
planar or panoramic pairs are tried last for initialization), `cameras` (List<Camera>),
`images` (List<Image>: image sizes and point colours; needed without `cameras`) and `names`
(List<Text>, image names for the model; default image_0001, ...).

Outputs: `reconstruction` (registered images with ids index + 1; emitted as a COLMAP text
model) and `report`: views, registered, registered_fraction, points, observations,
mean_track_length, reprojection_rms_px, focal_px, init_image_a, init_image_b,
init_angle_deg, local_adjustments, global_adjustments, failed_registrations.

Example:
    "sfm": (op: "sfm.incremental",
            inputs: { "keypoints": "features.keypoints", "tracks": "tracks.tracks",
                      "pairs": "pairs.pairs", "images": "views.frames" },
            params: (focal_px: 1520.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints.list_of(),
                "Keypoints of every image.",
            ),
            PortSpec::new("tracks", PortType::Tracks, "Feature tracks (sfm.tracks)."),
            PortSpec::new(
                "pairs",
                PortType::Matrix,
                "Pair configurations from sfm.match_pairs (initial-pair order).",
            )
            .optional(),
            PortSpec::new(
                "cameras",
                PortType::Camera.list_of(),
                "Known cameras, one per image (held fixed).",
            )
            .optional(),
            PortSpec::new(
                "images",
                PortType::Image.list_of(),
                "The images: sizes and point colours.",
            )
            .optional(),
            PortSpec::new(
                "names",
                PortType::Text.list_of(),
                "Image names for the reconstruction.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "Cameras, registered images and points.",
            ),
            PortSpec::new(
                "report",
                PortType::Metrics,
                "registered, points, reprojection_rms_px, focal_px, ...",
            ),
        ]
    }

    fn new(p: IncrementalParams) -> Result<Self, String> {
        for (name, v) in [
            ("focal_px", p.focal_px),
            ("init_min_tri_angle_deg", p.init_min_tri_angle_deg),
            ("min_tri_angle_deg", p.min_tri_angle_deg),
            ("global_ba_ratio", p.global_ba_ratio),
        ] {
            if !v.is_finite() {
                return Err(format!("`{name}` must be finite, got {v}"));
            }
        }
        for (name, v) in [
            ("max_reprojection_error_px", p.max_reprojection_error_px),
            ("abs_pose_threshold_px", p.abs_pose_threshold_px),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("`{name}` must be finite and > 0, got {v}"));
            }
        }
        Ok(Incremental {
            options: SfmOptions {
                focal_px: p.focal_px,
                refine_focal: p.refine_focal,
                init_min_points: p.init_min_points as usize,
                init_min_tri_angle_deg: p.init_min_tri_angle_deg,
                init_max_pairs: p.init_max_pairs as usize,
                min_tri_angle_deg: p.min_tri_angle_deg,
                max_reprojection_error_px: p.max_reprojection_error_px,
                abs_pose_threshold_px: p.abs_pose_threshold_px,
                abs_pose_min_inliers: p.abs_pose_min_inliers as usize,
                abs_pose_min_inlier_ratio: p.abs_pose_min_inlier_ratio,
                local_ba_images: p.local_ba_images as usize,
                global_ba_ratio: p.global_ba_ratio,
                ba_max_iterations: p.ba_max_iterations as usize,
                seed: p.seed,
            },
        })
    }
}

impl Operator for Incremental {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let keypoints = keypoint_lists(inputs, "keypoints")?;
        let n = keypoints.len();
        let tracks = match inputs.require("tracks")? {
            Value::Tracks(t) => t,
            other => {
                return Err(OpError::input(
                    "tracks",
                    format!("expected Tracks, got {}", other.port_type()),
                ));
            }
        };
        let pair_models = match inputs.get("pairs") {
            None => Vec::new(),
            Some(Value::Matrix(m)) => read_pairs(m, n)
                .map_err(|e| OpError::input("pairs", e))?
                .into_iter()
                .map(|p| (p.i, p.j, p.model))
                .collect(),
            Some(other) => {
                return Err(OpError::input(
                    "pairs",
                    format!("expected Matrix, got {}", other.port_type()),
                ));
            }
        };
        let cameras = camera_list(inputs, "cameras")?;
        let images: Option<Vec<&Image>> =
            list_items(inputs, "images", PortType::Image, |v| match v {
                Value::Image(i) => Some(&**i),
                _ => None,
            })?;
        let names: Vec<String> = list_items(inputs, "names", PortType::Text, |v| match v {
            Value::Text(t) => Some(t.to_string()),
            _ => None,
        })?
        .unwrap_or_else(|| (1..=n).map(|i| format!("image_{i:04}")).collect());
        for (port, len) in [
            ("cameras", cameras.as_ref().map(Vec::len)),
            ("images", images.as_ref().map(Vec::len)),
            ("names", Some(names.len())),
        ] {
            if let Some(len) = len
                && len != n
            {
                return Err(OpError::input(
                    port,
                    format!("holds {len} entries but there are {n} keypoint sets"),
                ));
            }
        }
        let sizes: Vec<(u32, u32)> = match (&cameras, &images) {
            (Some(c), _) => c.iter().map(|c| (c.width, c.height)).collect(),
            (None, Some(ims)) => ims
                .iter()
                .map(|i| (i.width() as u32, i.height() as u32))
                .collect(),
            (None, None) => {
                return Err(OpError::input(
                    "images",
                    "without `cameras`, connect `images` (their sizes place the principal point)",
                ));
            }
        };
        let input = SfmInput {
            keypoints,
            tracks,
            sizes,
            cameras,
            pair_models,
            images,
            names,
        };
        let result =
            reconstruct(&input, &self.options).map_err(|e| OpError::failed(e.to_string()))?;
        let (rms, observations) = reprojection_rms(&result, &input);
        let rec = &result.reconstruction;
        let mut report = Metrics::new();
        report.insert("views".into(), n as f64);
        report.insert("registered".into(), rec.images.len() as f64);
        report.insert(
            "registered_fraction".into(),
            rec.images.len() as f64 / n.max(1) as f64,
        );
        report.insert("points".into(), rec.points.len() as f64);
        report.insert("observations".into(), observations as f64);
        report.insert(
            "mean_track_length".into(),
            observations as f64 / rec.points.len().max(1) as f64,
        );
        report.insert("reprojection_rms_px".into(), rms);
        report.insert("focal_px".into(), result.focal_px);
        report.insert("init_image_a".into(), result.stats.init_pair.0 as f64);
        report.insert("init_image_b".into(), result.stats.init_pair.1 as f64);
        report.insert("init_angle_deg".into(), result.stats.init_angle_deg);
        report.insert(
            "local_adjustments".into(),
            result.stats.local_adjustments as f64,
        );
        report.insert(
            "global_adjustments".into(),
            result.stats.global_adjustments as f64,
        );
        report.insert(
            "failed_registrations".into(),
            result.stats.failed_registrations as f64,
        );
        Ok(Outputs::new()
            .with(
                "reconstruction",
                Value::Reconstruction(Arc::new(result.reconstruction)),
            )
            .with("report", Value::metrics(report)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::geometry::pose_util::rotation_angle_deg;
    use crate::geometry::transforms::umeyama;
    use ocellus_engine::value::Distortion;

    /// Camera `k` of `n` on an arc of `span_deg` around the origin at `radius`, looking at it.
    fn ring_pose(k: usize, n: usize, span_deg: f64, radius: f64) -> CameraPose {
        let a = (span_deg * k as f64 / n as f64).to_radians();
        let eye = Vector3::new(radius * a.sin(), 0.3 * (3.0 * a).sin(), radius * a.cos());
        let forward = (-eye).normalize();
        let right = forward.cross(&Vector3::y()).normalize();
        let down = forward.cross(&right);
        let r = Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
        CameraPose { r, t: -(r * eye) }
    }

    struct Synthetic {
        keypoints: Vec<Vec<Keypoint>>,
        tracks: Tracks,
        poses: Vec<CameraPose>,
        camera: Camera,
    }

    /// `points` random points in a 2×1×2 box seen by `views` cameras (f 500, 640×480), pixel
    /// noise `noise_px`, and a share `outliers` of track observations replaced by random
    /// pixels.
    fn synthetic(
        views: usize,
        span_deg: f64,
        points: usize,
        noise_px: f64,
        outliers: f64,
    ) -> Synthetic {
        let k = Intrinsics::new(500.0, 500.0, 319.5, 239.5).unwrap();
        let ek = ocellus_engine::value::Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
            skew: 0.0,
        };
        let camera = Camera::from_parts(640, 480, ek, Distortion::None);
        let poses: Vec<CameraPose> = (0..views)
            .map(|i| ring_pose(i, views, span_deg, 4.0))
            .collect();
        let mut rng = SplitMix64::new(7);
        let mut keypoints = vec![Vec::new(); views];
        let mut tracks = Vec::new();
        for _ in 0..points {
            let x = Vector3::new(
                2.0 * rng.uniform() - 1.0,
                rng.uniform() - 0.5,
                2.0 * rng.uniform() - 1.0,
            );
            let mut track = Vec::new();
            for (i, p) in poses.iter().enumerate() {
                let c = p.r * x + p.t;
                let mut q = [k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy];
                if !(0.0..640.0).contains(&q[0]) || !(0.0..480.0).contains(&q[1]) {
                    continue;
                }
                if rng.uniform() < outliers {
                    q = [640.0 * rng.uniform(), 480.0 * rng.uniform()];
                } else {
                    q[0] += noise_px * rng.normal();
                    q[1] += noise_px * rng.normal();
                }
                track.push(TrackElement {
                    image: i as u32,
                    keypoint: keypoints[i].len() as u32,
                });
                keypoints[i].push(Keypoint {
                    x: q[0] as f32,
                    y: q[1] as f32,
                    size: 2.0,
                    angle: -1.0,
                    response: 1.0,
                    octave: 0,
                });
            }
            if track.len() >= 2 {
                tracks.push(track);
            }
        }
        Synthetic {
            keypoints,
            tracks: Tracks { tracks },
            poses,
            camera,
        }
    }

    fn input<'a>(s: &'a Synthetic, calibrated: bool) -> SfmInput<'a> {
        let n = s.poses.len();
        SfmInput {
            keypoints: s.keypoints.iter().map(Vec::as_slice).collect(),
            tracks: &s.tracks,
            sizes: vec![(640, 480); n],
            cameras: calibrated.then(|| vec![s.camera.clone(); n]),
            pair_models: Vec::new(),
            images: None,
            names: (0..n).map(|i| format!("v{i}")).collect(),
        }
    }

    /// Median and max rotation error (degrees) and max centre error (relative to the ring
    /// diameter) after a similarity alignment of the centres.
    fn errors(s: &Synthetic, rec: &Reconstruction) -> (f64, f64, f64) {
        let mut pairs = Vec::new();
        let mut rots = Vec::new();
        for im in &rec.images {
            let i = im.id as usize - 1;
            let r = Matrix3::from_row_slice(&im.camera_from_world.rotation_matrix());
            let c = -(r.transpose() * Vector3::from(im.camera_from_world.translation));
            let t = s.poses[i];
            let ct = -(t.r.transpose() * t.t);
            pairs.push([[c.x, c.y, c.z], [ct.x, ct.y, ct.z]]);
            rots.push((r, t.r));
        }
        let sim = umeyama(&pairs, true).unwrap();
        let mut rot_err: Vec<f64> = rots
            .iter()
            .map(|(r, rt)| rotation_angle_deg(&(r * sim.rotation.transpose()), rt))
            .collect();
        rot_err.sort_by(f64::total_cmp);
        let centre = pairs
            .iter()
            .map(|p| (sim.apply(&p[0]) - Vector3::from(p[1])).norm() / 8.0)
            .fold(0.0, f64::max);
        (
            rot_err[rot_err.len() / 2],
            rot_err[rot_err.len() - 1],
            centre,
        )
    }

    #[test]
    fn calibrated_ring_is_recovered_up_to_a_similarity() {
        let s = synthetic(10, 360.0, 1500, 0.3, 0.05);
        let inp = input(&s, true);
        let out = reconstruct(&inp, &SfmOptions::default()).unwrap();
        let rec = &out.reconstruction;
        assert_eq!(rec.images.len(), 10, "all views registered");
        let (median, max, centre) = errors(&s, rec);
        let (rms, obs) = reprojection_rms(&out, &inp);
        eprintln!(
            "ring: rotation median {median:.4}° max {max:.4}°, centre max {centre:.2e}, \
             rms {rms:.3} px over {obs} observations, {} points",
            rec.points.len()
        );
        assert!(median < 0.05 && max < 0.1, "{median} {max}");
        assert!(centre < 1e-3, "{centre}");
        assert!(rms < 0.5, "{rms}");
        assert!(rec.points.len() > 1000);
        // Outlier observations are filtered: every kept observation is within the threshold.
        assert!(rec.points.iter().all(|p| p.error_px <= 4.0));
    }

    #[test]
    fn uncalibrated_views_recover_the_focal_length() {
        let s = synthetic(8, 200.0, 1200, 0.2, 0.0);
        let inp = input(&s, false);
        let options = SfmOptions {
            focal_px: 450.0,
            ..SfmOptions::default()
        };
        let out = reconstruct(&inp, &options).unwrap();
        assert_eq!(out.reconstruction.images.len(), 8);
        eprintln!("focal 450 → {:.3} (true 500)", out.focal_px);
        assert!((out.focal_px - 500.0).abs() < 2.0, "{}", out.focal_px);
        let (median, _, _) = errors(&s, &out.reconstruction);
        assert!(median < 0.1, "{median}");
    }

    #[test]
    fn near_zero_baseline_is_not_enough_parallax() {
        // Two cameras 1e-6 apart, both looking at the points.
        let mut s = synthetic(2, 1e-4, 400, 0.2, 0.0);
        let base = ring_pose(0, 1, 0.0, 4.0);
        s.poses = vec![base, base];
        let e = reconstruct(&input(&s, true), &SfmOptions::default()).unwrap_err();
        assert!(
            matches!(e, SfmError::NotEnoughParallax { .. }),
            "expected not enough parallax, got {e}"
        );
        assert!(e.to_string().contains("not enough parallax"));
    }

    #[test]
    fn result_does_not_depend_on_the_thread_count() {
        let s = synthetic(6, 150.0, 600, 0.3, 0.05);
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| reconstruct(&input(&s, true), &SfmOptions::default()).unwrap())
        };
        let (a, b) = (run(1), run(3));
        assert!(
            a.reconstruction == b.reconstruction,
            "reconstructions differ"
        );
        assert_eq!(a.stats, b.stats);
    }

    #[test]
    fn inconsistent_tracks_are_an_error() {
        let mut s = synthetic(3, 60.0, 100, 0.0, 0.0);
        s.tracks.tracks.push(vec![
            TrackElement {
                image: 0,
                keypoint: 100_000,
            };
            2
        ]);
        let e = reconstruct(&input(&s, true), &SfmOptions::default()).unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
    }
}
