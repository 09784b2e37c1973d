//! End-point error of feature tracks against the ground-truth motion of a synthetic sequence of
//! translating objects.
//!
//! The truth of each frame is a label image (gray u8 or u16: 0 = static background, `s + 1` =
//! object `s`, the object drawn on top where objects overlap) and the translation of every
//! object (`positions[s]`, px, the same number of objects on every frame). A track is assigned
//! to the object under it on the frame it first appears (its birth frame `t0`, at point `p0`):
//! `s = label(p0)`, with offset `p0 − positions[s](t0)`; its true position on a later frame `t`
//! is `positions[s](t) + offset`. On the background (label 0) the truth is `p0` (static).
//!
//! Pixel convention: px, the centre of pixel (i, j) at (i, j) — as `detect::corners::
//! select_corners` (integer corner positions) and `video::klt::track_klt`. Pixel (i, j) covers
//! [i − 0.5, i + 0.5) × [j − 0.5, j + 0.5), so the label under a point (x, y) is the one of the
//! nearest pixel `(⌊x + 0.5⌋, ⌊y + 0.5⌋)`; for integer positions that is pixel (x, y) itself.
//! A point outside [−0.5, w − 0.5) × [−0.5, h − 0.5) at birth is an error.
//!
//! The error of a track on a frame is the end-point error `‖p − truth‖₂`, px (Baker et al., "A
//! database and evaluation methodology for optical flow", IJCV 2011, the Middlebury flow
//! evaluation). The birth frame carries no measurement — the truth is defined from the tracked
//! point there, so its error is 0 by construction — and is left out of all error statistics; it
//! counts towards the track's length. An id that disappears and comes back later keeps its
//! birth assignment; its length counts the frames it was present.
//!
//! Statistics are accumulated in input order, and medians sort with `f64::total_cmp` (the mean
//! of the two middle values for even counts), so results are deterministic.

use std::collections::{BTreeMap, BTreeSet};

use ocellus_engine::op::{
    Inputs, Op, OpError, Operator, Outputs, Packet, PortSpec, RunContext, SequenceState,
    run_sequence_batch,
};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Metrics, PixelData, Value};

/// Error statistics of one frame. Means, medians, the maximum and the inlier fraction are NaN
/// when no track was evaluated (`tracks == 0`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameError {
    /// Tracks evaluated on this frame: the tracks present that were born on an earlier frame.
    pub tracks: usize,
    /// Tracks first seen on this frame (not evaluated).
    pub born: usize,
    /// Mean end-point error, px.
    pub mean_epe_px: f64,
    /// Median end-point error, px.
    pub median_epe_px: f64,
    /// Largest end-point error, px.
    pub max_epe_px: f64,
    /// Share of evaluated tracks with an end-point error ≤ the inlier threshold.
    pub inlier_fraction: f64,
}

/// Statistics over all frames so far. Values whose set is empty are NaN.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackErrorSummary {
    /// Distinct track ids seen.
    pub tracks: usize,
    /// Mean track length (frames present, birth included) over all ids.
    pub mean_track_length: f64,
    /// Median track length, frames.
    pub median_track_length: f64,
    /// Mean end-point error over all evaluated (track, frame) samples, px.
    pub mean_epe_px: f64,
    /// Median end-point error over all samples, px.
    pub median_epe_px: f64,
    /// Mean over tracks with at least one sample of their last end-point error, px.
    pub final_mean_epe_px: f64,
    /// Share of all samples with an end-point error ≤ the inlier threshold.
    pub inlier_fraction: f64,
}

/// What is known about one track id.
#[derive(Debug, Clone, Copy, PartialEq)]
struct TruthTrack {
    /// Object under the birth point (`None`: background).
    object: Option<usize>,
    /// Birth point minus the object's position at birth (the birth point for background).
    offset: [f64; 2],
    /// Frame index of the birth.
    birth_frame: usize,
    /// Frames the id was present, birth included.
    frames: usize,
    /// Last end-point error, px (`None` before the first evaluated frame).
    last_error: Option<f64>,
}

/// Accumulates the end-point errors of tracks over a sequence; see the module docs.
#[derive(Debug, Clone)]
pub struct TrackErrorState {
    inlier_px: f64,
    frames: usize,
    /// Object count, fixed by the first frame.
    objects: Option<usize>,
    tracks: BTreeMap<u64, TruthTrack>,
    /// Every evaluated end-point error, px, in push order.
    samples: Vec<f64>,
    inliers: u64,
}

impl TrackErrorState {
    /// An empty state; `inlier_px` (> 0, finite) is the largest end-point error of a "good"
    /// track sample.
    pub fn new(inlier_px: f64) -> Result<Self, String> {
        if !(inlier_px.is_finite() && inlier_px > 0.0) {
            return Err(format!(
                "`inlier_px` must be finite and > 0, got {inlier_px}"
            ));
        }
        Ok(TrackErrorState {
            inlier_px,
            frames: 0,
            objects: None,
            tracks: BTreeMap::new(),
            samples: Vec::new(),
            inliers: 0,
        })
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// One frame: the live tracks (`ids[i]` at `points[i]`, px) and the truth (the label image
    /// and the object positions, px). Tracks seen for the first time are assigned to the object
    /// under them; the others are scored. Errors, leaving the state unchanged, when `ids` and
    /// `points` differ in length, an id repeats, a point or position is not finite, the number
    /// of positions differs from the first frame's, the label image is not gray u8 / u16, a new
    /// point lies outside the label image, or its label names an object ≥ `positions.len()`.
    pub fn push(
        &mut self,
        ids: &[u64],
        points: &[[f64; 2]],
        labels: &Image,
        positions: &[[f64; 2]],
    ) -> Result<FrameError, String> {
        if ids.len() != points.len() {
            return Err(format!("{} ids but {} points", ids.len(), points.len()));
        }
        if let Some((i, p)) = points
            .iter()
            .enumerate()
            .find(|(_, p)| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(format!("point {i} (id {}) is not finite: {p:?}", ids[i]));
        }
        if let Some((s, p)) = positions
            .iter()
            .enumerate()
            .find(|(_, p)| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(format!("position of object {s} is not finite: {p:?}"));
        }
        if let Some(n) = self.objects
            && n != positions.len()
        {
            return Err(format!(
                "frame {} has {} object positions but the first frame had {n}",
                self.frames,
                positions.len()
            ));
        }
        let mut seen = BTreeSet::new();
        if let Some(id) = ids.iter().find(|&&id| !seen.insert(id)) {
            return Err(format!("track id {id} appears twice"));
        }
        if labels.channels() != Channels::Gray || matches!(labels.data(), PixelData::F32(_)) {
            return Err(format!(
                "the label image must be gray u8 or u16, got {}",
                labels.format()
            ));
        }
        // Births: assign each new id to the object under it.
        let mut births = Vec::new();
        for (&id, p) in ids.iter().zip(points) {
            if self.tracks.contains_key(&id) {
                continue;
            }
            let label = label_at(labels, *p).ok_or_else(|| {
                format!(
                    "track {id} is born at ({}, {}), outside the {}×{} label image",
                    p[0],
                    p[1],
                    labels.width(),
                    labels.height()
                )
            })?;
            let (object, offset) = if label == 0 {
                (None, *p)
            } else {
                let s = label - 1;
                let Some(o) = positions.get(s) else {
                    return Err(format!(
                        "track {id} is born on label {label} (object {s}) but there are only {} \
                         object positions",
                        positions.len()
                    ));
                };
                (Some(s), [p[0] - o[0], p[1] - o[1]])
            };
            births.push((
                id,
                TruthTrack {
                    object,
                    offset,
                    birth_frame: self.frames,
                    frames: 1,
                    last_error: None,
                },
            ));
        }
        // Score the other tracks (positions are checked above, so `get` cannot miss for a
        // track assigned on an earlier frame: the object count is fixed).
        let mut errors = Vec::with_capacity(ids.len() - births.len());
        for (id, p) in ids.iter().zip(points) {
            let Some(t) = self.tracks.get(id) else {
                continue;
            };
            let truth = match t.object {
                None => t.offset,
                Some(s) => {
                    let o = positions.get(s).ok_or_else(|| {
                        format!("track {id} sits on object {s}, which has no position")
                    })?;
                    [o[0] + t.offset[0], o[1] + t.offset[1]]
                }
            };
            errors.push(((p[0] - truth[0]).powi(2) + (p[1] - truth[1]).powi(2)).sqrt());
        }
        // Commit.
        let born = births.len();
        for (id, t) in births {
            self.tracks.insert(id, t);
        }
        let mut e = errors.iter();
        for id in ids {
            let Some(t) = self.tracks.get_mut(id) else {
                continue;
            };
            if t.birth_frame == self.frames {
                continue;
            }
            t.frames += 1;
            t.last_error = e.next().copied();
        }
        let inliers = errors.iter().filter(|&&x| x <= self.inlier_px).count();
        self.inliers += inliers as u64;
        self.samples.extend_from_slice(&errors);
        self.objects = Some(positions.len());
        self.frames += 1;
        let n = errors.len();
        let (mean, max, inlier_fraction) = if n == 0 {
            (f64::NAN, f64::NAN, f64::NAN)
        } else {
            (
                errors.iter().sum::<f64>() / n as f64,
                errors.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                inliers as f64 / n as f64,
            )
        };
        Ok(FrameError {
            tracks: n,
            born,
            mean_epe_px: mean,
            median_epe_px: median(&mut errors),
            max_epe_px: max,
            inlier_fraction,
        })
    }

    /// Statistics over all frames so far.
    pub fn summary(&self) -> TrackErrorSummary {
        let mut lengths: Vec<f64> = self.tracks.values().map(|t| t.frames as f64).collect();
        let last: Vec<f64> = self.tracks.values().filter_map(|t| t.last_error).collect();
        let mut samples = self.samples.clone();
        let n = samples.len();
        TrackErrorSummary {
            tracks: self.tracks.len(),
            mean_track_length: mean(&lengths),
            median_track_length: median(&mut lengths),
            mean_epe_px: mean(&samples),
            median_epe_px: median(&mut samples),
            final_mean_epe_px: mean(&last),
            inlier_fraction: if n == 0 {
                f64::NAN
            } else {
                self.inliers as f64 / n as f64
            },
        }
    }
}

params! {
    /// Parameters of `analyze.track_error`.
    pub struct TrackErrorParams {
        /// Largest end-point error of a "good" track sample (for `inlier_fraction`), px.
        inlier_px: f64 = 1.0 => [min = 0.000001, max = 1000000.0, unit = "px"],
    }
}

/// End-point error of feature tracks against the ground truth of a synthetic sequence of
/// translating objects (`analyze.track_error`); the Middlebury flow measure (Baker et al.,
/// IJCV 2011) applied along tracks. See the module documentation.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackError {
    inlier_px: f64,
}

impl Op for TrackError {
    type Params = TrackErrorParams;
    const ID: &'static str = "analyze.track_error";
    const SUMMARY: &'static str = "Scores feature tracks against the ground-truth motion of labelled translating objects: track length and end-point error.";
    const DOC: &'static str = r#"
A stateful metric. Each track id is assigned, on the frame it first appears, to the object
under it in `labels` (0 = static background, s + 1 = object s) with its offset from the
object's top-left corner in `positions` (row s: x, y, px); its true position on a later frame
is that object's position plus the offset (the birth point for the background). The error of
a track on a frame is the end-point error ‖p − truth‖, px; birth frames are not scored.

Per frame `metrics`: `tracks` (scored), `born`, `mean_epe_px`, `median_epe_px`,
`max_epe_px`, `inlier_fraction` (share with error ≤ `inlier_px`; NaN when none scored).
`summary` after the last frame: `tracks` (distinct ids), `mean_track_length` and
`median_track_length` (frames present, birth included), `mean_epe_px` and `median_epe_px`
over every scored (track, frame) sample, `final_mean_epe_px` (mean of each track's last
error), `inlier_fraction`, `frames`.

Points use the pixel-centre convention of `video.klt_tracker` (pixel (i, j) at (i, j)); only
translation is modelled, so `positions` may use any fixed origin (e.g. the top-left corners of
`capture.moving_shapes`).

Example:
    "score": (op: "analyze.track_error", inputs: { "points": "klt.points", "ids": "klt.ids", "labels": "clip.labels", "positions": "clip.positions" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "points",
                PortType::Points2D.list_of(),
                "Per frame: the tracked points, px.",
            )
            .per_frame(),
            PortSpec::new(
                "ids",
                PortType::Matrix.list_of(),
                "Per frame: n×1 track ids, in the order of `points`.",
            )
            .per_frame(),
            PortSpec::new(
                "labels",
                PortType::Image.list_of(),
                "Per frame: gray u8/u16 object labels (0 background, s + 1 object s).",
            )
            .per_frame(),
            PortSpec::new(
                "positions",
                PortType::Matrix.list_of(),
                "Per frame: objects × 2 positions (x, y), px.",
            )
            .per_frame(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "metrics",
                PortType::Metrics.list_of(),
                "Per frame: end-point error statistics of the scored tracks.",
            )
            .per_frame(),
            PortSpec::new(
                "summary",
                PortType::Metrics,
                "Track lengths and end-point errors over the whole sequence.",
            ),
        ]
    }

    fn new(params: TrackErrorParams) -> Result<Self, String> {
        TrackErrorState::new(params.inlier_px)?;
        Ok(TrackError {
            inlier_px: params.inlier_px,
        })
    }
}

impl Operator for TrackError {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_sequence_batch(self, ctx, inputs, &Self::outputs())
    }

    fn sequence(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        Some(
            TrackErrorState::new(self.inlier_px)
                .map(|s| Box::new(s) as Box<dyn SequenceState>)
                .map_err(OpError::failed),
        )
    }
}

/// Input `port` as a matrix.
pub(crate) fn input_matrix<'a>(inputs: &Inputs<'a>, port: &str) -> Result<&'a Matrix, OpError> {
    match inputs.require(port)? {
        Value::Matrix(m) => Ok(m),
        other => Err(OpError::input(
            port,
            format!("expected a Matrix, got {}", other.port_type()),
        )),
    }
}

/// The rows of an n×2 matrix as points.
fn matrix_points(port: &str, m: &Matrix) -> Result<Vec<[f64; 2]>, OpError> {
    if m.cols != 2 && !(m.rows == 0 && m.data.is_empty()) {
        return Err(OpError::input(
            port,
            format!("expected an n×2 matrix, got {}×{}", m.rows, m.cols),
        ));
    }
    Ok(m.data.chunks_exact(2).map(|r| [r[0], r[1]]).collect())
}

/// Track ids from an n×1 (or 1×n) matrix of non-negative integers.
fn matrix_ids(m: &Matrix) -> Result<Vec<u64>, OpError> {
    if m.rows != 1 && m.cols != 1 && !m.data.is_empty() {
        return Err(OpError::input(
            "ids",
            format!("expected an n×1 matrix, got {}×{}", m.rows, m.cols),
        ));
    }
    m.data
        .iter()
        .map(|&v| {
            if v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v < 9.0e15 {
                Ok(v as u64)
            } else {
                Err(OpError::input(
                    "ids",
                    format!("track ids must be non-negative integers, got {v}"),
                ))
            }
        })
        .collect()
}

impl SequenceState for TrackErrorState {
    fn push(
        &mut self,
        _ctx: &RunContext,
        packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        let points = match inputs.require("points")? {
            Value::Points2D(p) => p.clone(),
            other => {
                return Err(OpError::input(
                    "points",
                    format!("expected Points2D, got {}", other.port_type()),
                ));
            }
        };
        let ids = matrix_ids(input_matrix(inputs, "ids")?)?;
        let positions = matrix_points("positions", input_matrix(inputs, "positions")?)?;
        let labels = inputs.image("labels")?;
        let f = TrackErrorState::push(self, &ids, &points, labels, &positions)
            .map_err(|e| OpError::failed(format!("frame {}: {e}", packet.index)))?;
        let metrics: Metrics = [
            ("tracks", f.tracks as f64),
            ("born", f.born as f64),
            ("mean_epe_px", f.mean_epe_px),
            ("median_epe_px", f.median_epe_px),
            ("max_epe_px", f.max_epe_px),
            ("inlier_fraction", f.inlier_fraction),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        Ok(Outputs::new().with("metrics", Value::metrics(metrics)))
    }

    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        let s = self.summary();
        let metrics: Metrics = [
            ("frames", self.frames() as f64),
            ("tracks", s.tracks as f64),
            ("mean_track_length", s.mean_track_length),
            ("median_track_length", s.median_track_length),
            ("mean_epe_px", s.mean_epe_px),
            ("median_epe_px", s.median_epe_px),
            ("final_mean_epe_px", s.final_mean_epe_px),
            ("inlier_fraction", s.inlier_fraction),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        Ok(Outputs::new().with("summary", Value::metrics(metrics)))
    }
}

/// The label of the pixel nearest to `p` (pixel centres at integers), `None` outside.
fn label_at(labels: &Image, p: [f64; 2]) -> Option<usize> {
    let (w, h) = (labels.width(), labels.height());
    let x = (p[0] + 0.5).floor();
    let y = (p[1] + 0.5).floor();
    if !(x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64) {
        return None;
    }
    let i = y as usize * w + x as usize;
    match labels.data() {
        PixelData::U8(v) => v.get(i).map(|&l| usize::from(l)),
        PixelData::U16(v) => v.get(i).map(|&l| usize::from(l)),
        PixelData::F32(_) => None,
    }
}

/// Mean in slice order; NaN when empty.
fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// Median (mean of the two middle values for even counts); sorts `v` with `total_cmp`. NaN when
/// empty.
fn median(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    v.sort_unstable_by(f64::total_cmp);
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w × h` u8 label image with rectangles `(x0, y0, x1, y1, label)` drawn in order.
    fn labels(w: usize, h: usize, rects: &[(usize, usize, usize, usize, u8)]) -> Image {
        let mut data = vec![0u8; w * h];
        for &(x0, y0, x1, y1, l) in rects {
            for y in y0..y1 {
                data[y * w + x0..y * w + x1].fill(l);
            }
        }
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn two_objects_and_background_hand_computed() {
        // Object 0 at x 0..10, object 1 at x 10..20 of a 20×10 image.
        let l = labels(20, 10, &[(0, 0, 10, 10, 1), (10, 0, 20, 10, 2)]);
        let mut st = TrackErrorState::new(1.0).unwrap();
        let pos0 = [[2.0, 3.0], [12.0, 1.0]];
        // Frame 0: track 7 on object 0, 8 on object 1; nothing evaluated.
        let f0 = st
            .push(&[7, 8], &[[4.0, 5.0], [15.0, 2.0]], &l, &pos0)
            .unwrap();
        assert_eq!((f0.tracks, f0.born), (0, 2));
        assert!(f0.mean_epe_px.is_nan() && f0.median_epe_px.is_nan());
        assert!(f0.max_epe_px.is_nan() && f0.inlier_fraction.is_nan());
        // Frame 1: object 0 moves by (1, 0), object 1 by (0, 2). Truth: 7 → (5, 5),
        // 8 → (15, 4). Track 7 reported at (5, 5) (exact), 8 at (18, 8): EPE 5. Track 9 is
        // born at (3, 8.5): nearest pixel (3, 9), background in this frame's labels.
        let l1 = labels(20, 10, &[(0, 0, 10, 8, 1), (10, 0, 20, 10, 2)]);
        let pos1 = [[3.0, 3.0], [12.0, 3.0]];
        let f1 = st
            .push(
                &[7, 8, 9],
                &[[5.0, 5.0], [18.0, 8.0], [3.0, 8.5]],
                &l1,
                &pos1,
            )
            .unwrap();
        assert_eq!((f1.tracks, f1.born), (2, 1));
        assert!(close(f1.mean_epe_px, 2.5));
        assert!(close(f1.median_epe_px, 2.5));
        assert!(close(f1.max_epe_px, 5.0));
        assert!(close(f1.inlier_fraction, 0.5));
        // Frame 2: objects move again; track 9 (background, born at (3, 8.5)) is off by
        // (0, 1) → EPE 1 (an inlier: ≤ 1). Track 7 (truth (6, 5)) is off by (0, −0.5); 8 is
        // gone.
        let pos2 = [[4.0, 3.0], [12.0, 5.0]];
        let f2 = st
            .push(&[9, 7], &[[3.0, 9.5], [6.0, 4.5]], &l1, &pos2)
            .unwrap();
        assert_eq!((f2.tracks, f2.born), (2, 0));
        assert!(close(f2.mean_epe_px, 0.75), "{}", f2.mean_epe_px);
        assert!(close(f2.max_epe_px, 1.0));
        assert!(close(f2.inlier_fraction, 1.0));
        let s = st.summary();
        assert_eq!(s.tracks, 3);
        // Lengths: 7 → 3, 8 → 2, 9 → 2.
        assert!(close(s.mean_track_length, 7.0 / 3.0));
        assert!(close(s.median_track_length, 2.0));
        // Samples: 0, 5, 1, 0.5.
        assert!(close(s.mean_epe_px, 1.625));
        assert!(close(s.median_epe_px, 0.75));
        // Last errors: 7 → 0.5, 8 → 5, 9 → 1.
        assert!(close(s.final_mean_epe_px, 6.5 / 3.0));
        assert!(close(s.inlier_fraction, 0.75));
        assert_eq!(st.frames(), 3);
    }

    #[test]
    fn nearest_pixel_label_and_u16_labels() {
        // Label 1 only at pixel (3, 2); (2.6, 1.6) rounds to it, (2.4, 2.0) does not.
        let mut data = vec![0u16; 6 * 4];
        data[2 * 6 + 3] = 1;
        let l = Image::from_u16(6, 4, Channels::Gray, data).unwrap();
        let mut st = TrackErrorState::new(0.5).unwrap();
        st.push(&[0, 1], &[[2.6, 1.6], [2.4, 2.0]], &l, &[[0.0, 0.0]])
            .unwrap();
        // The object moves by (10, 0): track 0 follows it, track 1 stays.
        let f = st
            .push(&[0, 1], &[[12.6, 1.6], [2.4, 2.0]], &l, &[[10.0, 0.0]])
            .unwrap();
        assert_eq!(f.tracks, 2);
        assert!(f.max_epe_px < 1e-12);
        // Points just inside the image at birth (−0.5 rounds to pixel 0).
        st.push(&[2], &[[-0.5, 3.49]], &l, &[[10.0, 0.0]]).unwrap();
    }

    #[test]
    fn perfect_tracks_have_zero_error() {
        let l = labels(32, 32, &[(4, 4, 16, 16, 1), (10, 10, 28, 28, 2)]);
        let mut st = TrackErrorState::new(0.1).unwrap();
        let starts = [[5.0, 5.0], [20.0, 20.0], [12.0, 12.0], [30.0, 2.0]];
        // Object 0 moves (0.3, −0.2)/frame, object 1 (−1, 0.5); (12, 12) is on object 1
        // (drawn on top); (30, 2) is background.
        let vel = [[0.3, -0.2], [-1.0, 0.5]];
        let owner = [Some(0), Some(1), Some(1), None];
        for t in 0..6 {
            let k = t as f64;
            let pos = [
                [1.0 + k * vel[0][0], 2.0 + k * vel[0][1]],
                [-3.0 + k * vel[1][0], 7.0 + k * vel[1][1]],
            ];
            let pts: Vec<[f64; 2]> = starts
                .iter()
                .zip(owner)
                .map(|(p, o)| match o {
                    Some(s) => [p[0] + k * vel[s][0], p[1] + k * vel[s][1]],
                    None => *p,
                })
                .collect();
            let f = st.push(&[0, 1, 2, 3], &pts, &l, &pos).unwrap();
            if t > 0 {
                assert_eq!(f.tracks, 4);
                assert!(f.max_epe_px < 1e-12, "frame {t}: {}", f.max_epe_px);
                assert_eq!(f.inlier_fraction, 1.0);
            }
        }
        let s = st.summary();
        assert!(s.mean_epe_px < 1e-12 && s.final_mean_epe_px < 1e-12);
        assert!(close(s.mean_track_length, 6.0) && close(s.median_track_length, 6.0));
        assert_eq!(s.inlier_fraction, 1.0);
        // A track that stays put while its object moves has the object's displacement as
        // error: on object 1 (truth moves (−1, 0.5) per frame), after 2 frames √(4 + 1).
        let mut st = TrackErrorState::new(0.1).unwrap();
        let p = [[20.0, 20.0]];
        st.push(&[5], &p, &l, &[[0.0, 0.0], [0.0, 0.0]]).unwrap();
        st.push(&[5], &p, &l, &[[0.0, 0.0], [-1.0, 0.5]]).unwrap();
        let f = st.push(&[5], &p, &l, &[[0.0, 0.0], [-2.0, 1.0]]).unwrap();
        assert!(close(f.mean_epe_px, 5f64.sqrt()));
        assert_eq!(f.inlier_fraction, 0.0);
        let s = st.summary();
        assert!(close(s.final_mean_epe_px, 5f64.sqrt()));
        assert!(close(s.median_epe_px, (5f64.sqrt() + 1.25f64.sqrt()) / 2.0));
    }

    #[test]
    fn empty_state_and_frames() {
        let st = TrackErrorState::new(1.0).unwrap();
        let s = st.summary();
        assert_eq!(s.tracks, 0);
        assert!(s.mean_track_length.is_nan() && s.median_epe_px.is_nan());
        assert!(s.final_mean_epe_px.is_nan() && s.inlier_fraction.is_nan());
        let mut st = TrackErrorState::new(1.0).unwrap();
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        let f = st.push(&[], &[], &empty, &[]).unwrap();
        assert_eq!((f.tracks, f.born), (0, 0));
        assert!(f.mean_epe_px.is_nan());
        // A track born and never seen again has length 1 and no error sample.
        let l = labels(4, 4, &[]);
        let mut st = TrackErrorState::new(1.0).unwrap();
        st.push(&[3], &[[1.0, 1.0]], &l, &[]).unwrap();
        st.push(&[], &[], &l, &[]).unwrap();
        let s = st.summary();
        assert_eq!(s.tracks, 1);
        assert_eq!(s.mean_track_length, 1.0);
        assert!(s.mean_epe_px.is_nan() && s.final_mean_epe_px.is_nan());
    }

    #[test]
    fn median_definition() {
        assert!(median(&mut []).is_nan());
        assert_eq!(median(&mut [3.0]), 3.0);
        assert_eq!(median(&mut [4.0, 1.0]), 2.5);
        assert_eq!(median(&mut [5.0, -1.0, 2.0, 9.0]), 3.5);
        assert_eq!(median(&mut [5.0, -1.0, 2.0]), 2.0);
    }

    #[test]
    fn errors_leave_the_state_unchanged() {
        assert!(TrackErrorState::new(0.0).is_err());
        assert!(TrackErrorState::new(f64::NAN).is_err());
        assert!(TrackErrorState::new(-1.0).is_err());
        let l = labels(10, 10, &[(0, 0, 5, 10, 1), (5, 0, 10, 10, 3)]);
        let mut st = TrackErrorState::new(1.0).unwrap();
        st.push(&[0], &[[1.0, 1.0]], &l, &[[0.0, 0.0]; 3]).unwrap();
        let before = st.summary();
        let pos = [[0.0, 0.0]; 3];
        /// Track ids, points, label image, object positions, and the expected message part.
        type Case = (Vec<u64>, Vec<[f64; 2]>, Image, Vec<[f64; 2]>, &'static str);
        let cases: Vec<Case> = vec![
            (vec![0, 1], vec![[1.0, 1.0]], l.clone(), pos.to_vec(), "ids"),
            (
                vec![1],
                vec![[f64::NAN, 1.0]],
                l.clone(),
                pos.to_vec(),
                "not finite",
            ),
            (
                vec![0],
                vec![[1.0, 1.0]],
                l.clone(),
                vec![[0.0, 0.0]; 2],
                "positions",
            ),
            (
                vec![0],
                vec![[1.0, 1.0]],
                l.clone(),
                vec![[f64::INFINITY, 0.0]; 3],
                "object 0",
            ),
            (
                vec![1],
                vec![[10.5, 1.0]],
                l.clone(),
                pos.to_vec(),
                "outside",
            ),
            (
                vec![1],
                vec![[-0.51, 1.0]],
                l.clone(),
                pos.to_vec(),
                "outside",
            ),
            (
                vec![0, 0],
                vec![[1.0, 1.0]; 2],
                l.clone(),
                pos.to_vec(),
                "twice",
            ),
            (
                vec![1],
                vec![[1.0, 1.0]],
                Image::from_f32(10, 10, Channels::Gray, vec![0.0; 100]).unwrap(),
                pos.to_vec(),
                "u8 or u16",
            ),
            (
                vec![1],
                vec![[1.0, 1.0]],
                Image::from_u8(10, 10, Channels::Rgb, vec![0; 300]).unwrap(),
                pos.to_vec(),
                "u8 or u16",
            ),
        ];
        for (ids, pts, labels, pos, what) in cases {
            let e = st.push(&ids, &pts, &labels, &pos).unwrap_err();
            assert!(e.contains(what), "{what}: {e}");
            assert_eq!(st.frames(), 1);
        }
        // Label 3 names object 2, but this sequence has only 2 objects.
        let mut st2 = TrackErrorState::new(1.0).unwrap();
        let e = st2
            .push(&[4], &[[7.0, 1.0]], &l, &[[0.0, 0.0]; 2])
            .unwrap_err();
        assert!(e.contains("label 3"), "{e}");
        assert_eq!(st2.frames(), 0);
        // A failed frame added nothing.
        let after = st.summary();
        assert_eq!(before.tracks, after.tracks);
        assert_eq!(
            before.mean_track_length.to_bits(),
            after.mean_track_length.to_bits()
        );
        // A known id may move outside the label image later: only births are looked up.
        let f = st.push(&[0], &[[-3.0, 20.0]], &l, &pos).unwrap();
        assert!(close(f.mean_epe_px, (16.0f64 + 361.0).sqrt()));
    }
}
