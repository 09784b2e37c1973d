//! `sfm.match_pairs`: which image pairs to match, descriptor matching per pair, and two-view
//! geometric verification with model selection — the correspondence search of incremental
//! structure from motion (Schönberger & Frahm, "Structure-from-motion revisited", CVPR 2016,
//! §4.1; COLMAP's exhaustive, sequential and retrieval-based matchers).
//!
//! Pair selection: every pair (`exhaustive`), each image with the next `window` images
//! (`sequential`, for video and ordered captures), or each image with the `neighbors` images
//! whose descriptors it matches most (`similarity`: the `retrieval_features` strongest
//! features of every image matched against those of every other image with the ratio test, a
//! cheap stand-in for a vocabulary tree that is exact on small sets).
//!
//! Verification: the putative matches (Lowe's ratio test, optionally mutual) are fitted by
//! LO-RANSAC with an essential matrix when the views are calibrated (cameras given) and a
//! fundamental matrix otherwise, and by a homography. The pair is labelled by the model that
//! explains it (COLMAP's two-view configurations): `calibrated` (E), `uncalibrated` (F),
//! `planar_or_panoramic` when the homography explains at least `planar_ratio` of the epipolar
//! inliers (little parallax: a plane, a pure rotation or a tiny baseline), or `failed` when
//! fewer than `min_inliers` survive. The pair's verified matches are the epipolar inliers.

use std::sync::Arc;

use ocellus_engine::value::{
    Camera, Channels, Descriptors, Image, Keypoint, Match, Matrix, Metrics, Pose, Value,
};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, param_enum, params,
};
use rayon::prelude::*;

use crate::geometry::homography::Correspondence;
use crate::geometry::pose_util::Intrinsics;
use crate::geometry::ransac::{Method, RobustOptions};
use crate::geometry::relative_pose::{find_essential, ideal_points};
use crate::geometry::two_view::{find_fundamental, find_homography};
use crate::matching::brute_force::{MatchOptions, brute_force_match, select_rows};
use crate::matching::{DescriptorRows, Metric, Norm, prepare};

param_enum! {
    /// Which image pairs are matched.
    pub enum PairSelection {
        /// Every pair `(i, j)`, `i < j`.
        Exhaustive = "exhaustive",
        /// Each image with the next `window` images (ordered captures, video).
        Sequential = "sequential",
        /// Each image with its `neighbors` most similar images by descriptor matching.
        Similarity = "similarity",
    }
}

/// The two-view configuration of a verified pair (the `model` column of `pairs`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairModel {
    /// Too few inliers: not a pair.
    Failed = 0,
    /// Essential matrix of calibrated views.
    Calibrated = 1,
    /// Fundamental matrix of uncalibrated views.
    Uncalibrated = 2,
    /// A homography explains the epipolar inliers: plane, pure rotation or tiny baseline.
    PlanarOrPanoramic = 3,
}

impl PairModel {
    /// The model from its code in the `pairs` matrix.
    pub fn from_code(code: f64) -> PairModel {
        match code as i64 {
            1 => PairModel::Calibrated,
            2 => PairModel::Uncalibrated,
            3 => PairModel::PlanarOrPanoramic,
            _ => PairModel::Failed,
        }
    }
}

/// Settings of [`match_pairs`].
#[derive(Debug, Clone, PartialEq)]
pub struct PairOptions {
    /// Pair selection.
    pub selection: PairSelection,
    /// Sequential window, images.
    pub window: usize,
    /// Similar images kept per image.
    pub neighbors: usize,
    /// Features per image used to rank similarity.
    pub retrieval_features: usize,
    /// Lowe's ratio.
    pub ratio: f64,
    /// Mutual nearest neighbours only.
    pub cross_check: bool,
    /// Epipolar inlier threshold (Sampson distance), pixels.
    pub threshold_px: f64,
    /// Homography inlier threshold (symmetric transfer), pixels.
    pub homography_threshold_px: f64,
    /// Fewest epipolar inliers of a verified pair.
    pub min_inliers: usize,
    /// Homography-to-epipolar inlier ratio above which a pair is planar or panoramic.
    pub planar_ratio: f64,
    /// RANSAC confidence.
    pub confidence: f64,
    /// Most RANSAC trials per model.
    pub max_trials: usize,
    /// Seed; pair `(i, j)` uses a stream derived from it and the pair.
    pub seed: u64,
}

impl Default for PairOptions {
    fn default() -> Self {
        PairOptions {
            selection: PairSelection::Exhaustive,
            window: 5,
            neighbors: 10,
            retrieval_features: 256,
            ratio: 0.8,
            cross_check: true,
            threshold_px: 2.0,
            homography_threshold_px: 4.0,
            min_inliers: 15,
            planar_ratio: 0.8,
            confidence: 0.9999,
            max_trials: 10_000,
            seed: 0,
        }
    }
}

/// One matched and verified pair.
#[derive(Debug, Clone, PartialEq)]
pub struct VerifiedPair {
    /// First image.
    pub i: usize,
    /// Second image (`j > i`).
    pub j: usize,
    /// Putative matches (after the ratio test and cross-check).
    pub putative: usize,
    /// Epipolar inliers (query = keypoint of `i`, train = keypoint of `j`); empty when failed.
    pub inliers: Vec<Match>,
    /// Homography inliers.
    pub homography_inliers: usize,
    /// Configuration.
    pub model: PairModel,
}

/// Image pairs `(i, j)`, `i < j`, chosen by `options` for `n` images. `descriptors` are needed
/// only for [`PairSelection::Similarity`].
pub fn select_pairs(
    descriptors: &[&Descriptors],
    keypoints: &[&[Keypoint]],
    options: &PairOptions,
) -> Result<Vec<(usize, usize)>, String> {
    let n = descriptors.len();
    let mut pairs = Vec::new();
    match options.selection {
        PairSelection::Exhaustive => {
            for i in 0..n {
                for j in i + 1..n {
                    pairs.push((i, j));
                }
            }
        }
        PairSelection::Sequential => {
            for i in 0..n {
                for j in i + 1..n.min(i + 1 + options.window) {
                    pairs.push((i, j));
                }
            }
        }
        PairSelection::Similarity => {
            let subsets: Vec<DescriptorRows<'static>> = descriptors
                .iter()
                .zip(keypoints)
                .map(|(d, k)| strongest_rows(d, k, options.retrieval_features))
                .collect::<Result<_, _>>()?;
            let metric = match descriptors.first() {
                Some(Descriptors::Binary { .. }) => Metric::Hamming,
                _ => Metric::L2,
            };
            let match_options = MatchOptions {
                ratio: options.ratio,
                cross_check: false,
                max_distance: None,
            };
            // Similarity score of every ordered pair, then each image's best `neighbors`.
            let scores: Vec<Vec<usize>> = (0..n)
                .into_par_iter()
                .map(|i| {
                    (0..n)
                        .map(|j| {
                            if i == j {
                                0
                            } else {
                                brute_force_match(
                                    &subsets[i],
                                    &subsets[j],
                                    metric,
                                    &match_options,
                                    None,
                                )
                                .len()
                            }
                        })
                        .collect()
                })
                .collect();
            let mut chosen = vec![false; n * n];
            for (i, row) in scores.iter().enumerate() {
                let mut order: Vec<usize> = (0..n).filter(|&j| j != i).collect();
                order.sort_by(|&a, &b| row[b].cmp(&row[a]).then(a.cmp(&b)));
                for &j in order.iter().take(options.neighbors) {
                    let (a, b) = (i.min(j), i.max(j));
                    chosen[a * n + b] = true;
                }
            }
            for i in 0..n {
                for j in i + 1..n {
                    if chosen[i * n + j] {
                        pairs.push((i, j));
                    }
                }
            }
        }
    }
    Ok(pairs)
}

/// The rows of the `count` strongest keypoints (by response, ties by index), in matcher form.
fn strongest_rows(
    d: &Descriptors,
    k: &[Keypoint],
    count: usize,
) -> Result<DescriptorRows<'static>, String> {
    let (_, rows, _) = prepare(d, d, Norm::Auto).map_err(|e| e.to_string())?;
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by(|&a, &b| {
        let (ra, rb) = (
            k.get(a).map_or(0.0, |p| p.response),
            k.get(b).map_or(0.0, |p| p.response),
        );
        rb.total_cmp(&ra).then(a.cmp(&b))
    });
    order.truncate(count);
    order.sort_unstable();
    Ok(select_rows(&rows, &order))
}

/// Seed of pair `(i, j)`'s RANSAC streams.
fn pair_seed(seed: u64, i: usize, j: usize) -> u64 {
    let mut z = seed ^ ((i as u64) << 32 | j as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Verifies putative `matches` between keypoints `a` and `b` (ideal pixels when `cameras` are
/// given, raw pixels otherwise); see the module documentation.
pub fn verify_pair(
    a: &[[f64; 2]],
    b: &[[f64; 2]],
    matches: &[Match],
    cameras: Option<(&Intrinsics, &Intrinsics)>,
    options: &PairOptions,
    seed: u64,
) -> (Vec<Match>, usize, PairModel) {
    let data: Vec<Correspondence> = matches
        .iter()
        .map(|m| [a[m.query as usize], b[m.train as usize]])
        .collect();
    let robust = |threshold: f64, salt: u64| RobustOptions {
        method: Method::LoRansac,
        threshold,
        confidence: options.confidence,
        max_trials: options.max_trials,
        seed: seed ^ salt,
        ..RobustOptions::default()
    };
    if data.len() < options.min_inliers.max(8) {
        return (Vec::new(), 0, PairModel::Failed);
    }
    let epipolar: Option<(Vec<bool>, usize)> = match cameras {
        Some((k1, k2)) => {
            find_essential(&data, k1, k2, &robust(options.threshold_px, 1), true, 0.0)
                .ok()
                .map(|e| (e.inlier_mask, e.inliers))
        }
        None => find_fundamental(&data, &robust(options.threshold_px, 1), true)
            .ok()
            .map(|f| (f.inlier_mask, f.inliers)),
    };
    let homography_inliers =
        find_homography(&data, &robust(options.homography_threshold_px, 2), false)
            .map(|h| h.inliers)
            .unwrap_or(0);
    let Some((mask, inliers)) = epipolar else {
        return (Vec::new(), homography_inliers, PairModel::Failed);
    };
    if inliers < options.min_inliers {
        return (Vec::new(), homography_inliers, PairModel::Failed);
    }
    let kept: Vec<Match> = matches
        .iter()
        .zip(&mask)
        .filter(|(_, m)| **m)
        .map(|(m, _)| *m)
        .collect();
    let model = if homography_inliers as f64 >= options.planar_ratio * inliers as f64 {
        PairModel::PlanarOrPanoramic
    } else if cameras.is_some() {
        PairModel::Calibrated
    } else {
        PairModel::Uncalibrated
    };
    (kept, homography_inliers, model)
}

/// Keypoint positions per image, and the pinhole intrinsics they are in (when calibrated).
pub type ImagePoints = (Vec<Vec<[f64; 2]>>, Option<Vec<Intrinsics>>);

/// Keypoint positions of every image in the pixels verification works in: undistorted pinhole
/// pixels of each camera when `cameras` are given, raw keypoint positions otherwise.
pub fn image_points(
    keypoints: &[&[Keypoint]],
    cameras: Option<&[Camera]>,
) -> Result<ImagePoints, String> {
    let raw: Vec<Vec<[f64; 2]>> = keypoints
        .iter()
        .map(|k| k.iter().map(|p| [f64::from(p.x), f64::from(p.y)]).collect())
        .collect();
    let Some(cameras) = cameras else {
        return Ok((raw, None));
    };
    let mut points = Vec::with_capacity(raw.len());
    let mut ks = Vec::with_capacity(raw.len());
    for (i, (p, c)) in raw.iter().zip(cameras).enumerate() {
        let ideal = ideal_points(c, p).map_err(|e| format!("image {i}: {e}"))?;
        points.push(ideal.points);
        ks.push(ideal.k);
    }
    Ok((points, Some(ks)))
}

/// Matches and verifies the selected pairs of `keypoints`/`descriptors` (one set per image).
/// Pairs run in parallel; each is independent and seeded by its indices, so the result does
/// not depend on the thread count.
pub fn match_pairs(
    keypoints: &[&[Keypoint]],
    descriptors: &[&Descriptors],
    cameras: Option<&[Camera]>,
    options: &PairOptions,
) -> Result<Vec<VerifiedPair>, String> {
    if keypoints.len() != descriptors.len() {
        return Err(format!(
            "{} keypoint sets but {} descriptor sets",
            keypoints.len(),
            descriptors.len()
        ));
    }
    if let Some(c) = cameras
        && c.len() != keypoints.len()
    {
        return Err(format!(
            "{} cameras but {} images",
            c.len(),
            keypoints.len()
        ));
    }
    for (i, (k, d)) in keypoints.iter().zip(descriptors).enumerate() {
        let rows = match d {
            Descriptors::Float { dim, data } => data.len() / (*dim).max(1),
            Descriptors::Binary { bytes, data } => data.len() / (*bytes).max(1),
        };
        if rows != k.len() {
            return Err(format!(
                "image {i}: {} keypoints but {rows} descriptors",
                k.len()
            ));
        }
    }
    let (points, ks) = image_points(keypoints, cameras)?;
    let pairs = select_pairs(descriptors, keypoints, options)?;
    let match_options = MatchOptions {
        ratio: options.ratio,
        cross_check: options.cross_check,
        max_distance: None,
    };
    pairs
        .par_iter()
        .map(|&(i, j)| {
            let matches = if keypoints[i].is_empty() || keypoints[j].is_empty() {
                Vec::new()
            } else {
                let (metric, q, t) = prepare(descriptors[i], descriptors[j], Norm::Auto)
                    .map_err(|e| format!("images {i} and {j}: {e}"))?;
                brute_force_match(&q, &t, metric, &match_options, None)
            };
            let cams = ks.as_ref().map(|k| (&k[i], &k[j]));
            let (inliers, homography_inliers, model) = verify_pair(
                &points[i],
                &points[j],
                &matches,
                cams,
                options,
                pair_seed(options.seed, i, j),
            );
            Ok(VerifiedPair {
                i,
                j,
                putative: matches.len(),
                inliers,
                homography_inliers,
                model,
            })
        })
        .collect()
}

/// Columns of the `pairs` matrix.
pub const PAIR_COLUMNS: usize = 6;

/// The `pairs` matrix: one row `[i, j, putative, inliers, homography_inliers, model]` per pair.
pub fn pairs_matrix(pairs: &[VerifiedPair]) -> Matrix {
    let mut data = Vec::with_capacity(pairs.len() * PAIR_COLUMNS);
    for p in pairs {
        data.extend([
            p.i as f64,
            p.j as f64,
            p.putative as f64,
            p.inliers.len() as f64,
            p.homography_inliers as f64,
            p.model as i64 as f64,
        ]);
    }
    Matrix {
        rows: pairs.len(),
        cols: PAIR_COLUMNS,
        data,
    }
}

/// A pair row read back from a `pairs` matrix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairRow {
    /// First image.
    pub i: usize,
    /// Second image.
    pub j: usize,
    /// Epipolar inliers.
    pub inliers: usize,
    /// Homography inliers.
    pub homography_inliers: usize,
    /// Configuration.
    pub model: PairModel,
}

/// Reads a `pairs` matrix, checking its shape and image indices (`< images`).
pub fn read_pairs(m: &Matrix, images: usize) -> Result<Vec<PairRow>, String> {
    if m.cols != PAIR_COLUMNS || m.data.len() != m.rows * m.cols {
        return Err(format!(
            "pairs must be an N×{PAIR_COLUMNS} matrix (as sfm.match_pairs writes), got {}×{}",
            m.rows, m.cols
        ));
    }
    let mut out = Vec::with_capacity(m.rows);
    for r in m.data.chunks_exact(PAIR_COLUMNS) {
        let ok = r
            .iter()
            .all(|v| v.is_finite() && *v >= 0.0 && v.fract() == 0.0);
        let (i, j) = (r[0] as usize, r[1] as usize);
        if !ok || i >= images || j >= images || i == j {
            return Err(format!(
                "pairs row {:?} is not a pair of image indices below {images}",
                r
            ));
        }
        out.push(PairRow {
            i,
            j,
            inliers: r[3] as usize,
            homography_inliers: r[4] as usize,
            model: PairModel::from_code(r[5]),
        });
    }
    Ok(out)
}

/// The elements of an optional `List<T>` input (`ty` = `T`), each taken by `pick`; `None` when
/// the port is not connected. An element `pick` rejects is an error naming the port.
pub fn list_items<'a, T>(
    inputs: &Inputs<'a>,
    name: &str,
    ty: PortType,
    pick: impl Fn(&'a Value) -> Option<T>,
) -> Result<Option<Vec<T>>, OpError> {
    let items = match inputs.get(name) {
        None => return Ok(None),
        Some(Value::List(l)) if l.element == ty => &l.items,
        Some(other) => {
            return Err(OpError::input(
                name,
                format!("expected {}, got {}", ty.list_of(), other.port_type()),
            ));
        }
    };
    items
        .iter()
        .map(|v| {
            pick(v).ok_or_else(|| OpError::input(name, format!("list holds {}", v.port_type())))
        })
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

/// The elements of a required `List<T>` input; see [`list_items`].
pub fn required_list<'a, T>(
    inputs: &Inputs<'a>,
    name: &str,
    ty: PortType,
    pick: impl Fn(&'a Value) -> Option<T>,
) -> Result<Vec<T>, OpError> {
    list_items(inputs, name, ty, pick)?.ok_or_else(|| OpError::input(name, "not connected"))
}

/// Single-channel per-view images (depth maps, silhouettes) with their cameras (one per view,
/// or one for all) and `camera_from_world` poses, as `capture.render` lists them: read from the
/// ports `images`, `"cameras"` and `"poses"`, and checked for counts, channels and sizes.
#[derive(Debug, Clone)]
pub struct CalibratedViews {
    /// One single-channel image per view.
    pub images: Vec<Arc<Image>>,
    /// One camera per view, or one for all (see [`CalibratedViews::camera`]).
    pub cameras: Vec<Arc<Camera>>,
    /// `camera_from_world` of every view.
    pub poses: Vec<Pose>,
}

impl CalibratedViews {
    /// Reads and checks the views; `what` names one image in the messages ("depth map",
    /// "silhouette"), and errors name the port at fault.
    pub fn read(inputs: &Inputs<'_>, images: &str, what: &str) -> Result<Self, OpError> {
        let image_list = required_list(inputs, images, PortType::Image, |v| match v {
            Value::Image(i) => Some(Arc::clone(i)),
            _ => None,
        })?;
        let cameras = required_list(inputs, "cameras", PortType::Camera, |v| match v {
            Value::Camera(c) => Some(Arc::clone(c)),
            _ => None,
        })?;
        let poses = required_list(inputs, "poses", PortType::Pose, |v| match v {
            Value::Pose(p) => Some(*p),
            _ => None,
        })?;
        let n = image_list.len();
        if n == 0 {
            return Err(OpError::input(images, format!("no {what}s")));
        }
        if poses.len() != n {
            return Err(OpError::input(
                "poses",
                format!("{n} {what}s but {} poses", poses.len()),
            ));
        }
        if cameras.len() != n && cameras.len() != 1 {
            return Err(OpError::input(
                "cameras",
                format!(
                    "{n} {what}s but {} cameras; give one camera per {what} or one for all",
                    cameras.len()
                ),
            ));
        }
        let views = CalibratedViews {
            images: image_list,
            cameras,
            poses,
        };
        for (i, image) in views.images.iter().enumerate() {
            if image.channels() != Channels::Gray {
                return Err(OpError::input(
                    images,
                    format!(
                        "{what} {i}: expected one channel, got {}",
                        image.channels().name()
                    ),
                ));
            }
            let cam = views.camera(i);
            if (cam.width as usize, cam.height as usize) != (image.width(), image.height()) {
                return Err(OpError::input(
                    "cameras",
                    format!(
                        "camera of {what} {i} is {}×{} but the {what} is {}×{}",
                        cam.width,
                        cam.height,
                        image.width(),
                        image.height()
                    ),
                ));
            }
        }
        Ok(views)
    }

    /// Number of views.
    pub fn len(&self) -> usize {
        self.images.len()
    }

    /// Whether there is no view (never, once read).
    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }

    /// The camera of view `i`: its own, or the one shared by all.
    pub fn camera(&self, i: usize) -> &Camera {
        self.cameras.get(i).unwrap_or(&self.cameras[0])
    }
}

/// The keypoint sets of a `List<Keypoints>` input.
pub fn keypoint_lists<'a>(inputs: &Inputs<'a>, name: &str) -> Result<Vec<&'a [Keypoint]>, OpError> {
    required_list(inputs, name, PortType::Keypoints, |v| match v {
        Value::Keypoints(k) => Some(k.as_slice()),
        _ => None,
    })
}

/// The cameras of an optional `List<Camera>` input.
pub fn camera_list(inputs: &Inputs<'_>, name: &str) -> Result<Option<Vec<Camera>>, OpError> {
    list_items(inputs, name, PortType::Camera, |v| match v {
        Value::Camera(c) => Some((**c).clone()),
        _ => None,
    })
}

params! {
    /// Parameters of `sfm.match_pairs`.
    pub struct MatchPairsParams {
        /// Which pairs are matched: "exhaustive", "sequential" or "similarity".
        selection: PairSelection = PairSelection::Exhaustive,
        /// Sequential selection: each image is paired with the next `window` images.
        window: u32 = 5 => [min = 1],
        /// Similarity selection: similar images kept per image.
        neighbors: u32 = 10 => [min = 1],
        /// Similarity selection: strongest features per image used to rank similarity.
        retrieval_features: u32 = 256 => [min = 1],
        /// Lowe's ratio test (≥ 1 disables).
        ratio: f64 = 0.8 => [min = 0.0],
        /// Keep mutual nearest neighbours only.
        cross_check: bool = true,
        /// Epipolar inlier threshold (Sampson distance), pixels.
        threshold_px: f64 = 2.0 => [min = 0.0, unit = "px"],
        /// Homography inlier threshold (symmetric transfer error), pixels.
        homography_threshold_px: f64 = 4.0 => [min = 0.0, unit = "px"],
        /// Fewest epipolar inliers of a verified pair.
        min_inliers: u32 = 15 => [min = 8],
        /// A pair whose homography inliers reach this share of its epipolar inliers is
        /// labelled planar or panoramic (too little parallax to initialize from).
        planar_ratio: f64 = 0.8 => [min = 0.0],
        /// RANSAC confidence, in (0, 1).
        confidence: f64 = 0.9999 => [min = 0.0, max = 1.0],
        /// Most RANSAC trials per model.
        max_trials: u32 = 10_000 => [min = 1],
        /// Seed of the RANSAC streams.
        seed: u64 = 0,
    }
}

/// `sfm.match_pairs`. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct MatchPairs {
    options: PairOptions,
}

impl Op for MatchPairs {
    type Params = MatchPairsParams;
    const ID: &'static str = "sfm.match_pairs";
    const SUMMARY: &'static str =
        "Selects image pairs, matches their descriptors and verifies them by two-view geometry.";
    const DOC: &'static str = r#"
The correspondence search of incremental SfM (Schönberger & Frahm, CVPR 2016, §4.1).

Pairs: `selection: "exhaustive"` (every pair), `"sequential"` (each image with the next
`window`), or `"similarity"` (each image with the `neighbors` images its `retrieval_features`
strongest features match most often).

Each pair's descriptors are matched exactly (nearest neighbours with Lowe's `ratio` test and,
with `cross_check`, mutual nearest neighbours) and verified by LO-RANSAC: an essential matrix
when `cameras` are given (keypoints undistorted by them), a fundamental matrix otherwise, with
`threshold_px` on the Sampson distance, and a homography with `homography_threshold_px`. A pair
with fewer than `min_inliers` epipolar inliers fails; one whose homography inliers reach
`planar_ratio` of them is labelled planar or panoramic (little parallax).

Outputs: `matches`, the epipolar inliers of every pair (query = keypoint of image i, train =
keypoint of image j; empty for failed pairs), in the order of the rows of `pairs`, an N×6
matrix `[i, j, putative, inliers, homography_inliers, model]` with model 0 failed,
1 calibrated (E), 2 uncalibrated (F), 3 planar or panoramic; `report`: pairs, verified,
planar, mean_inliers.

Example:
    "pairs": (op: "sfm.match_pairs",
              inputs: { "keypoints": "features.keypoints", "descriptors": "features.descriptors",
                        "cameras": "capture.cameras" },
              params: (selection: "exhaustive", threshold_px: 2.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints.list_of(),
                "Keypoints of every image.",
            ),
            PortSpec::new(
                "descriptors",
                PortType::Descriptors.list_of(),
                "Descriptors of every image, one per keypoint.",
            ),
            PortSpec::new(
                "cameras",
                PortType::Camera.list_of(),
                "Cameras of the images (calibrated verification); without them, F is fitted.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "matches",
                PortType::Matches.list_of(),
                "Verified matches per pair, in the order of `pairs`.",
            ),
            PortSpec::new(
                "pairs",
                PortType::Matrix,
                "N×6: i, j, putative, inliers, homography_inliers, model.",
            ),
            PortSpec::new(
                "report",
                PortType::Metrics,
                "pairs, verified, planar, mean_inliers.",
            ),
        ]
    }

    fn new(p: MatchPairsParams) -> Result<Self, String> {
        if !(p.confidence > 0.0 && p.confidence < 1.0) {
            return Err(format!(
                "`confidence` must be in (0, 1), got {}",
                p.confidence
            ));
        }
        for (name, v) in [
            ("ratio", p.ratio),
            ("threshold_px", p.threshold_px),
            ("homography_threshold_px", p.homography_threshold_px),
            ("planar_ratio", p.planar_ratio),
        ] {
            if !v.is_finite() || v <= 0.0 {
                return Err(format!("`{name}` must be finite and > 0, got {v}"));
            }
        }
        Ok(MatchPairs {
            options: PairOptions {
                selection: p.selection,
                window: p.window as usize,
                neighbors: p.neighbors as usize,
                retrieval_features: p.retrieval_features as usize,
                ratio: p.ratio,
                cross_check: p.cross_check,
                threshold_px: p.threshold_px,
                homography_threshold_px: p.homography_threshold_px,
                min_inliers: p.min_inliers as usize,
                planar_ratio: p.planar_ratio,
                confidence: p.confidence,
                max_trials: p.max_trials as usize,
                seed: p.seed,
            },
        })
    }
}

impl Operator for MatchPairs {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let keypoints = keypoint_lists(inputs, "keypoints")?;
        let descriptors: Vec<&Descriptors> =
            required_list(inputs, "descriptors", PortType::Descriptors, |v| match v {
                Value::Descriptors(d) => Some(&**d),
                _ => None,
            })?;
        let cameras = camera_list(inputs, "cameras")?;
        let pairs = match_pairs(&keypoints, &descriptors, cameras.as_deref(), &self.options)
            .map_err(OpError::failed)?;
        let verified: Vec<&VerifiedPair> = pairs
            .iter()
            .filter(|p| p.model != PairModel::Failed)
            .collect();
        let mut report = Metrics::new();
        report.insert("pairs".into(), pairs.len() as f64);
        report.insert("verified".into(), verified.len() as f64);
        report.insert(
            "planar".into(),
            verified
                .iter()
                .filter(|p| p.model == PairModel::PlanarOrPanoramic)
                .count() as f64,
        );
        report.insert(
            "mean_inliers".into(),
            if verified.is_empty() {
                0.0
            } else {
                verified.iter().map(|p| p.inliers.len()).sum::<usize>() as f64
                    / verified.len() as f64
            },
        );
        let matches = pairs
            .iter()
            .map(|p| Value::Matches(Arc::new(p.inliers.clone())))
            .collect();
        Ok(Outputs::new()
            .with("matches", Value::list(PortType::Matches, matches))
            .with("pairs", Value::Matrix(Arc::new(pairs_matrix(&pairs))))
            .with("report", Value::metrics(report)))
    }
}
