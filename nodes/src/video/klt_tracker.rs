//! A stateful multi-frame KLT feature tracker: Shi–Tomasi corners followed frame to frame with
//! pyramidal Lucas–Kanade, re-detected as tracks are lost (the loop of OpenCV's `lk_track.py`
//! sample: `goodFeaturesToTrack` + `calcOpticalFlowPyrLK` with a forward–backward check).
//!
//! [`KltTracker::push`] takes one frame at a time:
//!
//! 1. The live tracks of the previous frame are followed into the new one with
//!    [`track_klt`] (J.-Y. Bouguet, "Pyramidal implementation of the Lucas Kanade feature
//!    tracker", Intel 2000, with the forward–backward check of Kalal et al. 2010). A track is
//!    lost when KLT fails (flat window, forward–backward error over the threshold, left the
//!    image) or when it ends closer than [`KltTrackerConfig::border_px`] to the image edge.
//!    Survivors keep their order.
//! 2. On the first frame, when fewer than [`KltTrackerConfig::min_points`] tracks survive, or
//!    every [`KltTrackerConfig::detect_every`] frames, new corners are detected: the
//!    Shi–Tomasi minimum-eigenvalue response (J. Shi, C. Tomasi, "Good features to track",
//!    CVPR 1994; [`corner_response`] with [`CornerMethod::ShiTomasi`], Sobel aperture 3) of the
//!    gray frame, with the pixels closer than `min_distance_px` to a live track or closer than
//!    `border_px` to the edge masked out, then `goodFeaturesToTrack` selection
//!    ([`select_corners`]: 3×3 maxima above `quality_level` × the largest unmasked response,
//!    strongest first, `min_distance_px` apart) up to `max_points` live tracks in total. New
//!    tracks are appended in that order and get consecutive ids.
//!
//! Coordinates: px, the centre of pixel (i, j) at (i, j) — the convention of [`track_klt`]
//! (sampling at an integer position reads that pixel) and of [`select_corners`] (corners at
//! integer pixel positions). The image spans [−0.5, w − 0.5) × [−0.5, h − 0.5); "distance to
//! the edge" is measured from the outermost pixel centres: a point is kept when
//! `border_px ≤ x ≤ w − 1 − border_px` and the same for y.
//!
//! Gray conversion (for detection; [`track_klt`] does the same internally) is [`gray_f32`]:
//! any pixel format, 0–255 scale, so the corner response is computed with range 255.
//!
//! Difference from OpenCV's masked `goodFeaturesToTrack`: masked pixels neither become corners
//! nor suppress unmasked neighbours in the 3×3 maximum test (OpenCV dilates the unmasked
//! response).
//!
//! Determinism: the only parallel work is inside [`track_klt`], [`corner_response`] and
//! [`select_corners`], which are bit-identical for any thread count; everything here is
//! sequential in a fixed order.

use std::sync::Arc;

use ocellus_engine::op::{
    Inputs, Op, OpError, Operator, Outputs, Packet, PortSpec, RunContext, SequenceState,
    run_sequence_batch,
};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Matrix, Metrics, Value};

use super::gray::gray_f32;
use super::klt::{KltSettings, MAX_LEVELS, MAX_WINDOW, track_klt};
use crate::detect::corners::{CornerMethod, corner_response, select_corners};

/// Largest corner block size, px (as `detect.corners`).
pub const MAX_BLOCK_SIZE: usize = 31;

/// Sobel aperture of the corner response.
const CORNER_KSIZE: usize = 3;

/// Settings of a [`KltTracker`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KltTrackerConfig {
    /// Frame-to-frame tracking settings (window, pyramid, forward–backward threshold…).
    pub klt: KltSettings,
    /// Most live tracks (`maxCorners`), ≥ 1. Default 500.
    pub max_points: usize,
    /// Re-detect when fewer live tracks than this survive, ≤ `max_points`. Default 250.
    pub min_points: usize,
    /// Also re-detect on every frame whose index (0-based) is a multiple of this; 0 = only on
    /// the first frame and when below `min_points`. Default 5 (as `lk_track.py`).
    pub detect_every: usize,
    /// `goodFeaturesToTrack` quality level: corners need a response above this fraction of the
    /// largest (unmasked) response, in (0, 1). Default 0.01.
    pub quality_level: f64,
    /// Smallest distance of a new corner to the other new corners and to live tracks, px,
    /// finite, ≥ 0. Default 8.
    pub min_distance_px: f64,
    /// Side of the window over which the corner response sums gradient products, px,
    /// 1..=31. Default 3.
    pub block_size: usize,
    /// Tracks closer than this to the image edge are dropped and no corners are detected
    /// there, px (from the outermost pixel centres), finite, ≥ 0. Default: half the KLT
    /// window (10 for the default 21).
    pub border_px: f64,
}

impl Default for KltTrackerConfig {
    fn default() -> Self {
        let klt = KltSettings::default();
        KltTrackerConfig {
            klt,
            max_points: 500,
            min_points: 250,
            detect_every: 5,
            quality_level: 0.01,
            min_distance_px: 8.0,
            block_size: 3,
            border_px: (klt.window / 2) as f64,
        }
    }
}

impl KltTrackerConfig {
    /// Checks every field; the error names the field out of range.
    pub fn check(&self) -> Result<(), String> {
        let k = &self.klt;
        let max_window = MAX_WINDOW as usize;
        if !(3..=max_window).contains(&k.window) || k.window.is_multiple_of(2) {
            return Err(format!(
                "`klt.window` must be odd and between 3 and {max_window}, got {}",
                k.window
            ));
        }
        if k.levels > MAX_LEVELS as usize {
            return Err(format!(
                "`klt.levels` must be at most {MAX_LEVELS}, got {}",
                k.levels
            ));
        }
        if !(1..=1000).contains(&k.max_iterations) {
            return Err(format!(
                "`klt.max_iterations` must be between 1 and 1000, got {}",
                k.max_iterations
            ));
        }
        for (name, v) in [
            ("klt.epsilon", k.epsilon),
            ("klt.min_eigen", k.min_eigen),
            ("klt.forward_backward", k.forward_backward),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
            }
        }
        if self.max_points == 0 {
            return Err("`max_points` must be at least 1, got 0".into());
        }
        if self.min_points > self.max_points {
            return Err(format!(
                "`min_points` must be at most `max_points` ({}), got {}",
                self.max_points, self.min_points
            ));
        }
        if !(self.quality_level > 0.0 && self.quality_level < 1.0) {
            return Err(format!(
                "`quality_level` must be in (0, 1), got {}",
                self.quality_level
            ));
        }
        for (name, v) in [
            ("min_distance_px", self.min_distance_px),
            ("border_px", self.border_px),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
            }
        }
        if !(1..=MAX_BLOCK_SIZE).contains(&self.block_size) {
            return Err(format!(
                "`block_size` must be between 1 and {MAX_BLOCK_SIZE}, got {}",
                self.block_size
            ));
        }
        Ok(())
    }
}

/// The live tracks after one frame, in a fixed order: the survivors of the previous frame in
/// their previous order, then the tracks born on this frame in detection order (decreasing
/// corner response).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTracks {
    /// Positions, px (pixel centres at integer coordinates; see the module docs).
    pub points: Vec<[f64; 2]>,
    /// Stable id per point: ids start at 0 and increase by 1 per new track.
    pub ids: Vec<u64>,
    /// Frames each track has been alive, counting this one (1 on the frame it was born).
    pub ages: Vec<u32>,
    /// Tracks started on this frame (the last `born` entries).
    pub born: usize,
    /// Tracks lost on this frame (KLT failure, forward–backward check, left the border).
    pub lost: usize,
}

/// Counts over all frames pushed into a [`KltTracker`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerSummary {
    /// Frames pushed.
    pub frames: usize,
    /// Tracks started.
    pub tracks_started: u64,
    /// Tracks lost (finished).
    pub tracks_lost: u64,
    /// Tracks alive after the last frame.
    pub live: usize,
    /// Mean length of all tracks, finished and live, frames (a track's length is its age when
    /// last alive); NaN when no track was started.
    pub mean_track_length: f64,
    /// Longest track, frames (0 when none).
    pub max_track_length: u32,
    /// Mean number of live tracks after each frame; NaN before the first frame.
    pub mean_live_per_frame: f64,
}

/// One live track.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Live {
    point: [f32; 2],
    id: u64,
    age: u32,
}

/// Multi-frame KLT tracker; see the module docs.
#[derive(Debug, Clone)]
pub struct KltTracker {
    config: KltTrackerConfig,
    /// Size of the first frame.
    size: Option<(usize, usize)>,
    previous: Option<Image>,
    live: Vec<Live>,
    next_id: u64,
    frames: usize,
    lost_total: u64,
    finished_length_sum: u64,
    finished_max: u32,
    live_sum: u64,
}

impl KltTracker {
    /// A tracker with no frames yet; errors when the configuration is out of range
    /// ([`KltTrackerConfig::check`]).
    pub fn new(config: KltTrackerConfig) -> Result<KltTracker, String> {
        config.check()?;
        Ok(KltTracker {
            config,
            size: None,
            previous: None,
            live: Vec::new(),
            next_id: 0,
            frames: 0,
            lost_total: 0,
            finished_length_sum: 0,
            finished_max: 0,
            live_sum: 0,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &KltTrackerConfig {
        &self.config
    }

    /// Tracks the live points from the previous frame into `frame`, drops the lost ones, then
    /// (on the first frame, when fewer than `min_points` survive, or every `detect_every`
    /// frames) detects new Shi–Tomasi corners at least `min_distance_px` from the live tracks
    /// and from each other, up to `max_points` live tracks in total. Any pixel format (colour is
    /// converted to gray luma). Errors, leaving the tracker unchanged, when the frame size
    /// differs from the first frame's. Empty or tiny frames (fewer than 3×3 pixels) give no
    /// tracks.
    pub fn push(&mut self, frame: &Image) -> Result<FrameTracks, String> {
        let (w, h) = (frame.width(), frame.height());
        if let Some((fw, fh)) = self.size
            && (fw, fh) != (w, h)
        {
            return Err(format!(
                "frame {} is {w}×{h} but the first frame was {fw}×{fh}",
                self.frames
            ));
        }
        // 1. Follow the live tracks.
        let mut survivors = Vec::with_capacity(self.live.len());
        let mut lost = 0usize;
        let (mut lost_length_sum, mut lost_max) = (0u64, 0u32);
        if let Some(previous) = &self.previous
            && !self.live.is_empty()
        {
            let pts: Vec<[f32; 2]> = self.live.iter().map(|t| t.point).collect();
            let tracks = track_klt(previous, frame, &pts, &self.config.klt)?;
            for (t, k) in self.live.iter().zip(&tracks) {
                let p = [f64::from(k.x), f64::from(k.y)];
                if k.tracked && self.inside_border(p, w, h) {
                    survivors.push(Live {
                        point: [k.x, k.y],
                        id: t.id,
                        age: t.age.saturating_add(1),
                    });
                } else {
                    lost += 1;
                    lost_length_sum += u64::from(t.age);
                    lost_max = lost_max.max(t.age);
                }
            }
        }
        // 2. Detect new corners.
        let c = &self.config;
        let due = self.frames == 0
            || survivors.len() < c.min_points
            || (c.detect_every > 0 && self.frames.is_multiple_of(c.detect_every));
        let room = c.max_points.saturating_sub(survivors.len());
        let corners = if due && room > 0 {
            self.detect(frame, &survivors, room)
        } else {
            Vec::new()
        };
        // 3. Commit.
        self.finished_length_sum += lost_length_sum;
        self.finished_max = self.finished_max.max(lost_max);
        let born = corners.len();
        for (x, y) in corners {
            survivors.push(Live {
                point: [x as f32, y as f32],
                id: self.next_id,
                age: 1,
            });
            self.next_id += 1;
        }
        self.size = Some((w, h));
        self.previous = Some(frame.clone());
        self.live = survivors;
        self.frames += 1;
        self.lost_total += lost as u64;
        self.live_sum += self.live.len() as u64;
        Ok(FrameTracks {
            points: self
                .live
                .iter()
                .map(|t| [f64::from(t.point[0]), f64::from(t.point[1])])
                .collect(),
            ids: self.live.iter().map(|t| t.id).collect(),
            ages: self.live.iter().map(|t| t.age).collect(),
            born,
            lost,
        })
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Counts over all frames so far.
    pub fn summary(&self) -> TrackerSummary {
        let live_lengths: u64 = self.live.iter().map(|t| u64::from(t.age)).sum();
        let live_max = self.live.iter().map(|t| t.age).max().unwrap_or(0);
        let started = self.next_id;
        TrackerSummary {
            frames: self.frames,
            tracks_started: started,
            tracks_lost: self.lost_total,
            live: self.live.len(),
            mean_track_length: if started == 0 {
                f64::NAN
            } else {
                (self.finished_length_sum + live_lengths) as f64 / started as f64
            },
            max_track_length: self.finished_max.max(live_max),
            mean_live_per_frame: if self.frames == 0 {
                f64::NAN
            } else {
                self.live_sum as f64 / self.frames as f64
            },
        }
    }

    /// Whether `p` is at least `border_px` from the outermost pixel centres of a `w × h` frame.
    fn inside_border(&self, p: [f64; 2], w: usize, h: usize) -> bool {
        let b = self.config.border_px;
        p[0].is_finite()
            && p[1].is_finite()
            && p[0] >= b
            && p[1] >= b
            && p[0] <= (w as f64 - 1.0) - b
            && p[1] <= (h as f64 - 1.0) - b
    }

    /// New corners `(x, y)` of `frame`, at most `room`, away from the border and from `live`.
    fn detect(&self, frame: &Image, live: &[Live], room: usize) -> Vec<(usize, usize)> {
        let (w, h) = (frame.width(), frame.height());
        if w < 3 || h < 3 {
            return Vec::new();
        }
        let c = &self.config;
        let gray = gray_f32(frame);
        let mut response = corner_response(
            &gray.data,
            w,
            h,
            c.block_size,
            CORNER_KSIZE,
            CornerMethod::ShiTomasi,
            0.0,
            255.0,
        );
        // Border mask: pixel (x, y) is kept when border ≤ x ≤ w − 1 − border, same for y.
        for (y, row) in response.chunks_exact_mut(w).enumerate() {
            for (x, r) in row.iter_mut().enumerate() {
                if !self.inside_border([x as f64, y as f64], w, h) {
                    *r = 0.0;
                }
            }
        }
        // Disc masks around the live tracks: pixels closer than min_distance_px.
        let d = c.min_distance_px;
        if d > 0.0 {
            let d2 = d * d;
            for t in live {
                let (px, py) = (f64::from(t.point[0]), f64::from(t.point[1]));
                let x0 = (px - d).floor().max(0.0) as usize;
                let y0 = (py - d).floor().max(0.0) as usize;
                let x1 = ((px + d).ceil().max(0.0) as usize).min(w - 1);
                let y1 = ((py + d).ceil().max(0.0) as usize).min(h - 1);
                for y in y0..=y1 {
                    let dy = y as f64 - py;
                    for x in x0..=x1 {
                        let dx = x as f64 - px;
                        if dx * dx + dy * dy < d2 {
                            response[y * w + x] = 0.0;
                        }
                    }
                }
            }
        }
        select_corners(&response, w, h, c.quality_level, d, room)
            .into_iter()
            .map(|(x, y, _)| (x, y))
            .collect()
    }
}

params! {
    /// Parameters of `video.klt_tracker`.
    pub struct KltTrackerParams {
        /// Side of the square tracking window, px, odd, 3..=255.
        window_px: u32 = 21,
        /// Pyramid levels above the full-resolution one (0 = no pyramid), 0..=16.
        levels: u32 = 3,
        /// Most Newton iterations per pyramid level, 1..=1000.
        max_iterations: u32 = 30,
        /// A level stops refining once a step is shorter than this, px, ≥ 0.
        epsilon_px: f64 = 0.01,
        /// A point is lost when the smallest normalised eigenvalue of its gradient matrix is
        /// below this (OpenCV's `minEigThreshold`), ≥ 0.
        min_eigen_threshold: f64 = 1e-4,
        /// Largest forward–backward error of a kept track, px; 0 disables the check.
        forward_backward_px: f64 = 1.0,
        /// Most live tracks (`maxCorners`), ≥ 1.
        max_points: u32 = 500 => [min = 1, max = 100000],
        /// Re-detect corners when fewer live tracks than this survive, ≤ `max_points`.
        min_points: u32 = 250 => [min = 0, max = 100000],
        /// Also re-detect on every frame whose index is a multiple of this; 0: only on the
        /// first frame and below `min_points`.
        detect_every: u32 = 5 => [min = 0, max = 1000000, unit = "frames"],
        /// Corners need a Shi–Tomasi response above this fraction of the largest, in (0, 1).
        quality_level: f64 = 0.01,
        /// Smallest distance of a new corner to other new corners and to live tracks, px.
        min_distance_px: f64 = 8.0 => [min = 0.0, max = 10000.0, unit = "px"],
        /// Side of the window of the corner response, px, 1..=31.
        block_size: u32 = 3 => [min = 1, max = 31, unit = "px"],
        /// Tracks closer than this to the image edge are dropped and no corners are detected
        /// there, px; None (the default): half the tracking window.
        border_px: Option<f64> = None => [min = 0.0, max = 10000.0, unit = "px"],
    }
}

/// Multi-frame feature tracking (`video.klt_tracker`): Shi–Tomasi corners (Shi & Tomasi,
/// "Good features to track", CVPR 1994) followed with pyramidal Lucas–Kanade (Bouguet 2000)
/// and a forward–backward check (Kalal et al. 2010), re-detected as tracks are lost. See the
/// module documentation.
#[derive(Debug, Clone, PartialEq)]
pub struct KltTrackerOp {
    config: KltTrackerConfig,
}

impl Op for KltTrackerOp {
    type Params = KltTrackerParams;
    const ID: &'static str = "video.klt_tracker";
    const SUMMARY: &'static str = "Tracks Shi–Tomasi corners across a frame sequence with pyramidal KLT, with stable ids and re-detection.";
    const DOC: &'static str = r#"
A stateful tracker, the loop of OpenCV's `lk_track.py` (`goodFeaturesToTrack` +
`calcOpticalFlowPyrLK`): on each frame the live tracks of the previous frame are followed with
pyramidal Lucas–Kanade (J.-Y. Bouguet, "Pyramidal implementation of the Lucas Kanade feature
tracker", 2000; `window_px`, `levels`, `max_iterations`, `epsilon_px`, `min_eigen_threshold`)
and kept when they pass the forward–backward check (Kalal et al., "Forward-backward error",
ICPR 2010; `forward_backward_px`) and stay `border_px` inside the image. On the first frame,
when fewer than `min_points` survive, and every `detect_every` frames, new Shi–Tomasi corners
(J. Shi, C. Tomasi, "Good features to track", CVPR 1994; minimum eigenvalue over `block_size`,
Sobel 3) above `quality_level` × the strongest response and `min_distance_px` away from live
tracks and each other are added, up to `max_points` live tracks.

Per frame: `points` (live tracks, px, pixel centres at integer coordinates: survivors in
their previous order, then the new ones, strongest first), `ids` (n×1, stable, consecutive
from 0), `ages` (n×1, frames alive counting this one) and `metrics` (`live`, `born`, `lost`).
After the last frame, `summary`: `frames`, `tracks_started`, `tracks_lost`, `live`,
`mean_track_length` and `max_track_length` (frames, finished and live tracks) and
`mean_live_per_frame`.

Colour frames are converted to luma. The same frames give the same tracks in a stream and on
a list, at any thread count. Frames must all have the first frame's size.

Example:
    "tracks": (op: "video.klt_tracker", inputs: { "frames": "gray.image" }, params: (max_points: 400)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "The frames in time order, all of one size.",
            )
            .per_frame(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "points",
                PortType::Points2D.list_of(),
                "Per frame: the live tracks' positions, px.",
            )
            .per_frame(),
            PortSpec::new(
                "ids",
                PortType::Matrix.list_of(),
                "Per frame: n×1 track ids, in the order of `points`.",
            )
            .per_frame(),
            PortSpec::new(
                "ages",
                PortType::Matrix.list_of(),
                "Per frame: n×1 frames each track has been alive, counting this one.",
            )
            .per_frame(),
            PortSpec::new(
                "metrics",
                PortType::Metrics.list_of(),
                "Per frame: `live`, `born`, `lost`.",
            )
            .per_frame(),
            PortSpec::new(
                "summary",
                PortType::Metrics,
                "Track counts and lengths over the whole sequence.",
            ),
        ]
    }

    fn new(params: KltTrackerParams) -> Result<Self, String> {
        let KltTrackerParams {
            window_px,
            levels,
            max_iterations,
            epsilon_px,
            min_eigen_threshold,
            forward_backward_px,
            max_points,
            min_points,
            detect_every,
            quality_level,
            min_distance_px,
            block_size,
            border_px,
        } = params;
        let klt = KltSettings {
            window: window_px as usize,
            levels: levels as usize,
            max_iterations: max_iterations as usize,
            epsilon: epsilon_px as f32,
            min_eigen: min_eigen_threshold as f32,
            forward_backward: forward_backward_px as f32,
        };
        let config = KltTrackerConfig {
            klt,
            max_points: max_points as usize,
            min_points: min_points as usize,
            detect_every: detect_every as usize,
            quality_level,
            min_distance_px,
            block_size: block_size as usize,
            border_px: border_px.unwrap_or((window_px / 2) as f64),
        };
        // The f32 settings must also be finite before narrowing.
        for (name, v) in [
            ("epsilon_px", epsilon_px),
            ("min_eigen_threshold", min_eigen_threshold),
            ("forward_backward_px", forward_backward_px),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
            }
        }
        config.check()?;
        Ok(KltTrackerOp { config })
    }
}

impl Operator for KltTrackerOp {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_sequence_batch(self, ctx, inputs, &Self::outputs())
    }

    fn sequence(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        Some(
            KltTracker::new(self.config)
                .map(|t| Box::new(t) as Box<dyn SequenceState>)
                .map_err(OpError::failed),
        )
    }
}

/// An n×1 matrix.
fn column(values: impl Iterator<Item = f64>) -> Result<Value, OpError> {
    let data: Vec<f64> = values.collect();
    let m = Matrix::new(data.len(), 1, data).map_err(|e| OpError::failed(e.to_string()))?;
    Ok(Value::Matrix(Arc::new(m)))
}

impl SequenceState for KltTracker {
    fn push(
        &mut self,
        _ctx: &RunContext,
        packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        let image = inputs.image("frames")?;
        let tracks = KltTracker::push(self, image)
            .map_err(|e| OpError::input("frames", format!("frame {}: {e}", packet.index)))?;
        let metrics: Metrics = [
            ("live".to_string(), tracks.points.len() as f64),
            ("born".to_string(), tracks.born as f64),
            ("lost".to_string(), tracks.lost as f64),
        ]
        .into_iter()
        .collect();
        Ok(Outputs::new()
            .with("ids", column(tracks.ids.iter().map(|&i| i as f64))?)
            .with("ages", column(tracks.ages.iter().map(|&a| f64::from(a)))?)
            .with("points", Value::Points2D(Arc::new(tracks.points)))
            .with("metrics", Value::metrics(metrics)))
    }

    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        let s = self.summary();
        let metrics: Metrics = [
            ("frames", s.frames as f64),
            ("tracks_started", s.tracks_started as f64),
            ("tracks_lost", s.tracks_lost as f64),
            ("live", s.live as f64),
            ("mean_track_length", s.mean_track_length),
            ("max_track_length", f64::from(s.max_track_length)),
            ("mean_live_per_frame", s.mean_live_per_frame),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        Ok(Outputs::new().with("summary", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::synth::blob_texture;
    use ocellus_engine::value::{Channels, PixelData};

    /// Frame `t` of a texture whose content moves by `d` px per frame.
    fn shifted(w: usize, h: usize, seed: u64, t: usize, d: [f64; 2]) -> Image {
        let (sx, sy) = (d[0] * t as f64, d[1] * t as f64);
        blob_texture(w, h, 3.0, seed, [1.0, 0.0, -sx, 0.0, 1.0, -sy]).unwrap()
    }

    /// Pixels of `img` (gray f32) with x in `x0..x1` set to `value`.
    fn flatten_columns(img: Image, x0: usize, x1: usize, value: f32) -> Image {
        let (w, h) = (img.width(), img.height());
        let PixelData::F32(mut data) = img.into_data() else {
            panic!("f32 expected")
        };
        for y in 0..h {
            data[y * w + x0..y * w + x1].fill(value);
        }
        Image::from_f32(w, h, Channels::Gray, data).unwrap()
    }

    fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
    }

    #[test]
    fn tracks_follow_a_subpixel_translation_with_stable_ids() {
        let d = [0.63, -0.41];
        let config = KltTrackerConfig {
            max_points: 120,
            min_points: 0,
            detect_every: 0,
            ..KltTrackerConfig::default()
        };
        let mut tracker = KltTracker::new(config).unwrap();
        // id → (birth frame, birth point).
        let mut birth = std::collections::BTreeMap::new();
        let mut prev: Option<FrameTracks> = None;
        let mut errors = Vec::new();
        let mut steps = Vec::new();
        for t in 0..10 {
            let frame = shifted(200, 160, 11, t, d);
            let out = tracker.push(&frame).unwrap();
            assert_eq!(out.points.len(), out.ids.len());
            assert_eq!(out.ages.len(), out.ids.len());
            if t == 0 {
                assert_eq!(out.born, 120, "the first frame fills up");
                assert_eq!(out.ids, (0..120).collect::<Vec<u64>>());
                assert!(out.ages.iter().all(|&a| a == 1));
            } else {
                assert_eq!(out.born, 0, "no re-detection configured");
            }
            for (i, (&id, &p)) in out.ids.iter().zip(&out.points).enumerate() {
                let &mut (t0, p0) = birth.entry(id).or_insert((t, p));
                assert_eq!(out.ages[i] as usize, t - t0 + 1);
                let k = (t - t0) as f64;
                errors.push(dist(p, [p0[0] + k * d[0], p0[1] + k * d[1]]));
                if let Some(prev) = &prev {
                    let j = prev.ids.iter().position(|&q| q == id).unwrap();
                    let q = prev.points[j];
                    steps.push(dist([p[0] - q[0], p[1] - q[1]], d));
                }
            }
            // Survivors keep their order.
            if let Some(prev) = &prev {
                let kept: Vec<u64> = prev
                    .ids
                    .iter()
                    .copied()
                    .filter(|id| out.ids.contains(id))
                    .collect();
                assert_eq!(kept, out.ids);
                assert_eq!(prev.ids.len() - kept.len(), out.lost);
            }
            prev = Some(out);
        }
        let last = prev.unwrap();
        assert!(
            last.ids.len() >= 90,
            "only {} tracks survived",
            last.ids.len()
        );
        let mean = errors.iter().sum::<f64>() / errors.len() as f64;
        assert!(mean < 0.1, "mean end-point error {mean}");
        let step = steps.iter().sum::<f64>() / steps.len() as f64;
        let worst = steps.iter().cloned().fold(0.0, f64::max);
        assert!(
            step < 0.05 && worst < 0.5,
            "per-frame error {step}, worst {worst}"
        );
        let s = tracker.summary();
        assert_eq!(s.frames, 10);
        assert_eq!(tracker.frames(), 10);
        assert_eq!(s.tracks_started, 120);
        assert_eq!(s.live as u64 + s.tracks_lost, 120);
        assert_eq!(s.max_track_length, 10);
        assert!(s.mean_track_length > 8.0 && s.mean_track_length <= 10.0);
    }

    #[test]
    fn lost_tracks_are_replaced_up_to_max_points() {
        // Frame 1 turns the left half flat: tracks there fail and are replaced by corners in
        // the textured right half.
        let config = KltTrackerConfig {
            max_points: 40,
            min_points: 40,
            detect_every: 0,
            min_distance_px: 10.0,
            ..KltTrackerConfig::default()
        };
        let mut tracker = KltTracker::new(config).unwrap();
        let f0 = shifted(200, 160, 3, 0, [0.0, 0.0]);
        let out0 = tracker.push(&f0).unwrap();
        assert_eq!(out0.points.len(), 40);
        let left = out0.points.iter().filter(|p| p[0] < 90.0).count();
        assert!(left >= 5, "{left} tracks on the left half");
        let f1 = flatten_columns(shifted(200, 160, 3, 1, [0.5, 0.0]), 0, 100, 0.2);
        let out1 = tracker.push(&f1).unwrap();
        assert!(out1.lost >= left, "lost {} of {left}", out1.lost);
        assert_eq!(out1.born, out1.lost, "detections fill the gap");
        assert_eq!(out1.points.len(), 40);
        assert_eq!(out1.born + (40 - out1.lost), 40);
        let new = &out1.points[40 - out1.born..];
        // (The step at x = 100 itself gives responses up to 2 px to its left.)
        assert!(
            new.iter().all(|p| p[0] >= 97.0),
            "no corners on the flat half: {new:?}"
        );
        assert_eq!(
            out1.ids[40 - out1.born],
            40,
            "new ids continue the sequence"
        );
        assert!(out1.ages[40 - out1.born..].iter().all(|&a| a == 1));
        assert!(out1.ages[..40 - out1.born].iter().all(|&a| a == 2));
    }

    #[test]
    fn points_leaving_the_frame_are_lost_and_replaced() {
        // Content moves 3 px left per frame; tracks cross the left border.
        let config = KltTrackerConfig {
            max_points: 60,
            min_points: 60,
            detect_every: 0,
            ..KltTrackerConfig::default()
        };
        let mut tracker = KltTracker::new(config).unwrap();
        let mut lost = 0;
        for t in 0..12 {
            let out = tracker.push(&shifted(160, 120, 8, t, [-3.0, 0.0])).unwrap();
            lost += out.lost;
            assert_eq!(out.points.len(), 60, "frame {t}");
            let b = config.border_px;
            assert!(
                out.points
                    .iter()
                    .all(|p| p[0] >= b && p[1] >= b && p[0] <= 159.0 - b && p[1] <= 119.0 - b)
            );
            if t > 0 {
                assert_eq!(out.born, out.lost);
            }
        }
        assert!(lost > 10, "lost {lost}");
        let s = tracker.summary();
        assert_eq!(s.tracks_started, 60 + lost as u64);
        assert_eq!(s.tracks_lost, lost as u64);
        assert!((s.mean_live_per_frame - 60.0).abs() < 1e-12);
    }

    #[test]
    fn detections_keep_min_distance() {
        let config = KltTrackerConfig {
            max_points: 10_000,
            min_points: 0,
            detect_every: 2,
            min_distance_px: 12.0,
            ..KltTrackerConfig::default()
        };
        let mut tracker = KltTracker::new(config).unwrap();
        for t in 0..5 {
            let out = tracker.push(&shifted(200, 160, 5, t, [0.8, 0.3])).unwrap();
            let n = out.points.len();
            if t % 2 == 1 {
                assert_eq!(out.born, 0, "detection only every second frame");
            }
            // Every new point is ≥ 12 px from every other live point.
            for i in n - out.born..n {
                for j in 0..n {
                    if i != j {
                        let e = dist(out.points[i], out.points[j]);
                        assert!(e >= 12.0, "frame {t}: points {i}, {j} {e} px apart");
                    }
                }
            }
            if t == 0 {
                assert!(n > 20, "{n} corners");
            }
        }
        // Without the spacing the same frame has many more corners.
        let dense = KltTrackerConfig {
            min_distance_px: 0.0,
            ..config
        };
        let mut t2 = KltTracker::new(dense).unwrap();
        let n_dense = t2
            .push(&shifted(200, 160, 5, 0, [0.0; 2]))
            .unwrap()
            .points
            .len();
        let mut t3 = KltTracker::new(config).unwrap();
        let n_sparse = t3
            .push(&shifted(200, 160, 5, 0, [0.0; 2]))
            .unwrap()
            .points
            .len();
        assert!(n_dense > n_sparse, "{n_dense} vs {n_sparse}");
    }

    #[test]
    fn size_change_errors_and_tiny_frames_are_empty() {
        let mut tracker = KltTracker::new(KltTrackerConfig::default()).unwrap();
        let a = shifted(64, 48, 1, 0, [0.0; 2]);
        let first = tracker.push(&a).unwrap();
        assert!(!first.points.is_empty());
        let b = shifted(48, 64, 1, 0, [0.0; 2]);
        let e = tracker.push(&b).unwrap_err();
        assert!(e.contains("48×64") && e.contains("64×48"), "{e}");
        assert_eq!(tracker.frames(), 1, "a failed push changes nothing");
        let again = tracker.push(&a).unwrap();
        assert_eq!(again.lost, 0);
        assert_eq!(&again.ids[..first.ids.len()], &first.ids[..]);

        for side in [0usize, 1, 2] {
            let mut t = KltTracker::new(KltTrackerConfig::default()).unwrap();
            let img = Image::from_u8(side, side, Channels::Gray, vec![7; side * side]).unwrap();
            for _ in 0..3 {
                let out = t.push(&img).unwrap();
                assert!(out.points.is_empty() && out.ids.is_empty() && out.ages.is_empty());
                assert_eq!((out.born, out.lost), (0, 0));
            }
            let s = t.summary();
            assert_eq!((s.frames, s.tracks_started, s.max_track_length), (3, 0, 0));
            assert!(s.mean_track_length.is_nan());
        }
        let empty = KltTracker::new(KltTrackerConfig::default())
            .unwrap()
            .summary();
        assert!(empty.mean_live_per_frame.is_nan());
        // Colour frames are accepted.
        let rgb = crate::filter::test_support::random_u8(40, 30, Channels::Rgb, 9);
        let mut t = KltTracker::new(KltTrackerConfig::default()).unwrap();
        t.push(&rgb).unwrap();
        t.push(&rgb).unwrap();
    }

    #[test]
    fn bad_config_names_the_field() {
        let ok = KltTrackerConfig::default();
        assert!(ok.check().is_ok());
        let cases: Vec<(KltTrackerConfig, &str)> = vec![
            (
                KltTrackerConfig {
                    klt: KltSettings {
                        window: 20,
                        ..ok.klt
                    },
                    ..ok
                },
                "klt.window",
            ),
            (
                KltTrackerConfig {
                    klt: KltSettings {
                        levels: 17,
                        ..ok.klt
                    },
                    ..ok
                },
                "klt.levels",
            ),
            (
                KltTrackerConfig {
                    klt: KltSettings {
                        max_iterations: 0,
                        ..ok.klt
                    },
                    ..ok
                },
                "klt.max_iterations",
            ),
            (
                KltTrackerConfig {
                    klt: KltSettings {
                        forward_backward: f32::NAN,
                        ..ok.klt
                    },
                    ..ok
                },
                "klt.forward_backward",
            ),
            (
                KltTrackerConfig {
                    max_points: 0,
                    min_points: 0,
                    ..ok
                },
                "max_points",
            ),
            (
                KltTrackerConfig {
                    min_points: 501,
                    ..ok
                },
                "min_points",
            ),
            (
                KltTrackerConfig {
                    quality_level: 1.0,
                    ..ok
                },
                "quality_level",
            ),
            (
                KltTrackerConfig {
                    min_distance_px: -1.0,
                    ..ok
                },
                "min_distance_px",
            ),
            (
                KltTrackerConfig {
                    border_px: f64::INFINITY,
                    ..ok
                },
                "border_px",
            ),
            (
                KltTrackerConfig {
                    block_size: 0,
                    ..ok
                },
                "block_size",
            ),
        ];
        for (c, field) in cases {
            let e = c.check().unwrap_err();
            assert!(e.contains(&format!("`{field}`")), "{field}: {e}");
            assert!(KltTracker::new(c).is_err());
        }
    }

    #[test]
    fn deterministic_across_runs_and_thread_counts() {
        let config = KltTrackerConfig {
            max_points: 150,
            min_points: 100,
            detect_every: 3,
            ..KltTrackerConfig::default()
        };
        let frames: Vec<Image> = (0..8)
            .map(|t| {
                let f = shifted(180, 140, 21, t, [1.3, -0.7]);
                if t >= 4 {
                    flatten_columns(f, 0, 40, 0.0)
                } else {
                    f
                }
            })
            .collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut t = KltTracker::new(config).unwrap();
                let out: Vec<FrameTracks> = frames.iter().map(|f| t.push(f).unwrap()).collect();
                (out, t.summary())
            })
        };
        let (a, sa) = run(1);
        for threads in [1, 4] {
            let (b, sb) = run(threads);
            assert_eq!(sa.tracks_started, sb.tracks_started);
            assert_eq!(
                sa.mean_track_length.to_bits(),
                sb.mean_track_length.to_bits()
            );
            for (x, y) in a.iter().zip(&b) {
                assert_eq!(x.ids, y.ids);
                assert_eq!(x.ages, y.ages);
                assert_eq!((x.born, x.lost), (y.born, y.lost));
                for (p, q) in x.points.iter().zip(&y.points) {
                    assert_eq!(p[0].to_bits(), q[0].to_bits());
                    assert_eq!(p[1].to_bits(), q[1].to_bits());
                }
            }
        }
        assert!(a.iter().map(|f| f.lost).sum::<usize>() > 0);
        assert!(a.iter().skip(1).map(|f| f.born).sum::<usize>() > 0);
    }
}
