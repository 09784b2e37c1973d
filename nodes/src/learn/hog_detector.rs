//! `learn.hog_detector`: Dalal–Triggs style detection — HOG descriptors of training windows,
//! a linear classifier (L2-regularised logistic regression from [`super::logistic`]), a
//! multi-scale sliding window over an image pyramid, greedy non-maximum suppression and a
//! PASCAL VOC evaluation against ground-truth boxes.
//!
//! The scene's HOG is computed once per pyramid level (dense blocks at a one-cell stride, from
//! [`crate::describe::hog::hog`]) and every window's descriptor is gathered from its blocks, as
//! OpenCV's `HOGDescriptor::detectMultiScale` does. Windows of a level are scored in parallel
//! into disjoint slots; NMS and evaluation are sequential: bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Descriptors, Image, Matrix, Metrics, PixelData, Value};
use rayon::prelude::*;

use super::logistic::{LogisticConfig, LogisticSolver, fit_binary, sigmoid};
use super::{Design, dot, matrix_value, single_column};
use crate::analyze::track_error::input_matrix;
use crate::describe::hog::{HogParams, hog};
use crate::filter::resize::{Interpolation, Target, resize};

/// IoU at which a detection matches a ground-truth box (PASCAL VOC).
pub const MATCH_IOU: f64 = 0.5;

/// Windows scoring below this probability are dropped before NMS; the average precision is
/// computed over the remaining ranked detections.
pub const CANDIDATE_SCORE: f64 = 0.05;

/// Most pyramid levels.
pub const MAX_LEVELS: usize = 64;

params! {
    /// Parameters of `learn.hog_detector`.
    pub struct HogDetectorParams {
        /// Detection window `[width, height]`, px: the training tile size (each a multiple of
        /// `cell_size`, at least two cells). Default (32, 64).
        window: [u32; 2] = [32, 64],
        /// HOG cell side, px (2..=32); blocks are 2×2 cells, 9 unsigned bins. Default 8.
        cell_size: u32 = 8 => [min = 2, max = 32],
        /// Window stride in cells (≥ 1): stride_cells × cell_size px at every level. Default 1.
        stride_cells: u32 = 1 => [min = 1, max = 64],
        /// Ratio between successive pyramid scales (> 1); the scene is shrunk by it until the
        /// window no longer fits. Default 1.2.
        scale_step: f64 = 1.2 => [min = 1.0],
        /// Probability at or above which a window is reported (0..1). Default 0.5.
        score_threshold: f64 = 0.5 => [min = 0.0, max = 1.0],
        /// NMS: a box overlapping a higher-scoring kept box by more than this IoU is
        /// suppressed (0..1). Default 0.3.
        nms_iou: f64 = 0.3 => [min = 0.0, max = 1.0],
        /// Solver of the classifier: gd, newton or lbfgs. Default lbfgs.
        solver: LogisticSolver = LogisticSolver::Lbfgs,
        /// Ridge strength λ of the classifier (standardised HOG features). Default 0.01.
        l2: f64 = 0.01 => [min = 0.0],
        /// Most classifier iterations. Default 200.
        max_iterations: u32 = 200 => [min = 1, max = 100000],
    }
}

/// Settings of [`train_detector`] and [`detect`] (see [`HogDetectorParams`]).
#[derive(Debug, Clone, PartialEq)]
pub struct DetectorConfig {
    /// Window width, px.
    pub window_w: usize,
    /// Window height, px.
    pub window_h: usize,
    /// HOG settings.
    pub hog: HogParams,
    /// Window stride, cells.
    pub stride_cells: usize,
    /// Pyramid ratio.
    pub scale_step: f64,
    /// Reporting threshold (probability).
    pub score_threshold: f64,
    /// NMS IoU.
    pub nms_iou: f64,
    /// Classifier settings.
    pub classifier: LogisticConfig,
}

impl DetectorConfig {
    fn blocks(&self) -> (usize, usize) {
        let c = self.hog.cell_size as usize;
        (self.window_w / c - 1, self.window_h / c - 1)
    }
}

/// A trained linear window classifier.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearDetector {
    /// `[bias, w]` on raw HOG features: P(figure) = σ(bias + w·h).
    pub weights: Vec<f64>,
    /// Training accuracy at probability 0.5.
    pub train_accuracy: f64,
    /// Classifier iterations.
    pub iterations: usize,
}

fn gray_f32(image: &Image) -> Vec<f32> {
    let c = image.channels().count();
    let take = |v: &dyn Fn(usize) -> f32, n: usize| -> Vec<f32> {
        (0..n)
            .map(|i| {
                if c >= 3 {
                    0.299 * v(i * c) + 0.587 * v(i * c + 1) + 0.114 * v(i * c + 2)
                } else {
                    v(i * c)
                }
            })
            .collect()
    };
    let n = image.width() * image.height();
    match image.data() {
        PixelData::U8(s) => take(&|i| f32::from(s[i]) / 255.0, n),
        PixelData::U16(s) => take(&|i| f32::from(s[i]) / 65535.0, n),
        PixelData::F32(s) => take(&|i| s[i], n),
    }
}

/// The HOG descriptor of one window-sized image, blocks column-major as [`hog`] lays them.
fn window_descriptor(tile: &Image, hog_params: &HogParams) -> Result<Vec<f64>, String> {
    let (_, _, d) = hog(tile, hog_params)?;
    match d {
        Descriptors::Float { data, .. } => Ok(data.iter().map(|&v| f64::from(v)).collect()),
        Descriptors::Binary { .. } => Err("HOG returned binary descriptors".into()),
    }
}

/// Trains the window classifier on a mosaic of window tiles (`tiles_per_row` tiles per row,
/// row-major, one label per tile: nonzero = figure). Errors when the mosaic and the labels
/// disagree or a class is missing.
pub fn train_detector(
    mosaic: &Image,
    labels: &[f64],
    config: &DetectorConfig,
) -> Result<LinearDetector, String> {
    let (ww, wh) = (config.window_w, config.window_h);
    if mosaic.width() < ww
        || !mosaic.width().is_multiple_of(ww)
        || !mosaic.height().is_multiple_of(wh)
    {
        return Err(format!(
            "`training` ({}×{}) is not a mosaic of {ww}×{wh} windows",
            mosaic.width(),
            mosaic.height()
        ));
    }
    let cols = mosaic.width() / ww;
    let capacity = cols * (mosaic.height() / wh);
    if labels.is_empty() || labels.len() > capacity {
        return Err(format!(
            "`labels` has {} rows but the mosaic holds {capacity} windows",
            labels.len()
        ));
    }
    let gray = gray_f32(mosaic);
    let mw = mosaic.width();
    let rows: Vec<Vec<f64>> = (0..labels.len())
        .into_par_iter()
        .map(|i| {
            let (tx, ty) = ((i % cols) * ww, (i / cols) * wh);
            let px: Vec<f32> = (0..wh)
                .flat_map(|y| {
                    gray[(ty + y) * mw + tx..(ty + y) * mw + tx + ww]
                        .iter()
                        .copied()
                })
                .collect();
            let tile = Image::from_f32(ww, wh, Channels::Gray, px).map_err(|e| e.to_string())?;
            window_descriptor(&tile, &config.hog)
        })
        .collect::<Result<_, _>>()?;
    let dim = rows.first().map_or(0, Vec::len);
    let x = Matrix::new(labels.len(), dim, rows.concat()).map_err(|e| e.to_string())?;
    let y: Vec<f64> = labels
        .iter()
        .map(|&l| f64::from(u8::from(l != 0.0)))
        .collect();
    let positives = y.iter().filter(|&&v| v == 1.0).count();
    if positives == 0 || positives == y.len() {
        return Err("`labels` needs both figure (nonzero) and background (0) windows".into());
    }
    let design = Design::new(&x, config.classifier.scale_features, "training")?;
    let fit = fit_binary(&design, &y, &config.classifier)?;
    let correct = (0..design.n)
        .filter(|&i| (sigmoid(dot(design.row(i), &fit.theta)) >= 0.5) == (y[i] == 1.0))
        .count();
    Ok(LinearDetector {
        weights: design.to_original(&fit.theta),
        train_accuracy: correct as f64 / design.n as f64,
        iterations: fit.iterations,
    })
}

/// One detection: box (x, y, width, height) in scene pixels and its probability.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    /// (x, y, width, height), px.
    pub bbox: [f64; 4],
    /// P(figure).
    pub score: f64,
}

/// Detections after NMS and the work done.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectionReport {
    /// Kept detections with probability ≥ [`CANDIDATE_SCORE`], by decreasing score.
    pub candidates: Vec<Detection>,
    /// Windows scored over all levels.
    pub windows: usize,
    /// Pyramid levels.
    pub levels: usize,
}

/// Intersection over union of two (x, y, width, height) boxes.
pub fn iou(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let iw = ((a[0] + a[2]).min(b[0] + b[2]) - a[0].max(b[0])).max(0.0);
    let ih = ((a[1] + a[3]).min(b[1] + b[3]) - a[1].max(b[1])).max(0.0);
    let inter = iw * ih;
    let union = a[2] * a[3] + b[2] * b[3] - inter;
    if union > 0.0 { inter / union } else { 0.0 }
}

/// Greedy NMS: by decreasing score (stable for ties), keep a box unless it overlaps a kept box
/// by more than `max_iou`.
pub fn non_maximum_suppression(mut dets: Vec<Detection>, max_iou: f64) -> Vec<Detection> {
    dets.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut kept: Vec<Detection> = Vec::new();
    for d in dets {
        if kept.iter().all(|k| iou(&k.bbox, &d.bbox) <= max_iou) {
            kept.push(d);
        }
    }
    kept
}

/// Slides the window over a pyramid of `scene` (scales 1, 1/step, 1/step², … while the
/// window fits; area resampling), scores every window with `detector` and suppresses
/// overlaps.
pub fn detect(
    scene: &Image,
    detector: &LinearDetector,
    config: &DetectorConfig,
) -> Result<DetectionReport, String> {
    let (sw, sh) = (scene.width(), scene.height());
    if sw < config.window_w || sh < config.window_h {
        return Err(format!(
            "`scene` ({sw}×{sh}) is smaller than the window ({}×{})",
            config.window_w, config.window_h
        ));
    }
    let base =
        Image::from_f32(sw, sh, Channels::Gray, gray_f32(scene)).map_err(|e| e.to_string())?;
    let cell = config.hog.cell_size as usize;
    let (wbx, wby) = config.blocks();
    let stride = config.stride_cells;
    let mut all = Vec::new();
    let (mut windows, mut levels) = (0, 0);
    let mut scale = 1.0f64;
    while levels < MAX_LEVELS {
        let (lw, lh) = (
            (sw as f64 * scale).round() as usize,
            (sh as f64 * scale).round() as usize,
        );
        if lw < config.window_w || lh < config.window_h {
            break;
        }
        let level = if levels == 0 {
            base.clone()
        } else {
            resize(&base, Target::Size(lw, lh), Interpolation::Area)?
        };
        let (sx, sy) = (sw as f64 / lw as f64, sh as f64 / lh as f64);
        let (nbx, nby, desc) = hog(&level, &config.hog)?;
        let Descriptors::Float { dim, data } = desc else {
            return Err("HOG returned binary descriptors".into());
        };
        let (ox_n, oy_n) = ((nbx - wbx) / stride + 1, (nby - wby) / stride + 1);
        let w = &detector.weights;
        let scored: Vec<Detection> = (0..ox_n * oy_n)
            .into_par_iter()
            .map(|k| {
                let (ox, oy) = ((k / oy_n) * stride, (k % oy_n) * stride);
                let mut z = w[0];
                let mut j = 1;
                for bx in 0..wbx {
                    let start = ((ox + bx) * nby + oy) * dim;
                    for &v in &data[start..start + wby * dim] {
                        z += w[j] * f64::from(v);
                        j += 1;
                    }
                }
                Detection {
                    bbox: [
                        (ox * cell) as f64 * sx,
                        (oy * cell) as f64 * sy,
                        config.window_w as f64 * sx,
                        config.window_h as f64 * sy,
                    ],
                    score: sigmoid(z),
                }
            })
            .collect();
        windows += scored.len();
        all.extend(scored.into_iter().filter(|d| d.score >= CANDIDATE_SCORE));
        levels += 1;
        scale /= config.scale_step;
    }
    Ok(DetectionReport {
        candidates: non_maximum_suppression(all, config.nms_iou),
        windows,
        levels,
    })
}

/// PASCAL VOC scores of ranked detections against truth boxes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectionScores {
    /// TP / reported detections (1 when none is reported).
    pub precision: f64,
    /// TP / truth boxes (1 when there are none).
    pub recall: f64,
    /// Area under the all-point interpolated precision–recall curve (VOC 2010+) of every
    /// candidate.
    pub average_precision: f64,
    /// Detections at or above the threshold.
    pub reported: usize,
}

/// Matches `ranked` (decreasing score) to `truth` greedily — each detection to the unmatched
/// truth box of highest IoU ≥ [`MATCH_IOU`] — and measures precision and recall of those
/// scoring ≥ `threshold` and the average precision of all.
pub fn evaluate_detections(
    ranked: &[Detection],
    truth: &[[f64; 4]],
    threshold: f64,
) -> DetectionScores {
    let mut used = vec![false; truth.len()];
    let tp: Vec<bool> = ranked
        .iter()
        .map(|d| {
            let best = (0..truth.len())
                .filter(|&t| !used[t])
                .map(|t| (t, iou(&d.bbox, &truth[t])))
                .filter(|&(_, o)| o >= MATCH_IOU)
                .fold(None, |b: Option<(usize, f64)>, c| match b {
                    Some(bb) if bb.1 >= c.1 => Some(bb),
                    _ => Some(c),
                });
            if let Some((t, _)) = best {
                used[t] = true;
                true
            } else {
                false
            }
        })
        .collect();
    let reported = ranked.iter().filter(|d| d.score >= threshold).count();
    let tp_reported = tp[..reported].iter().filter(|&&t| t).count();
    let n_truth = truth.len();
    let ratio = |a: usize, b: usize| if b > 0 { a as f64 / b as f64 } else { 1.0 };
    // Precision envelope, then Σ ΔR · P.
    let mut prec = Vec::with_capacity(tp.len());
    let mut rec = Vec::with_capacity(tp.len());
    let mut hits = 0;
    for (k, &t) in tp.iter().enumerate() {
        hits += usize::from(t);
        prec.push(hits as f64 / (k + 1) as f64);
        rec.push(ratio(hits, n_truth));
    }
    for k in (0..prec.len().saturating_sub(1)).rev() {
        prec[k] = prec[k].max(prec[k + 1]);
    }
    let mut ap = 0.0;
    let mut last_recall = 0.0;
    for (p, r) in prec.iter().zip(&rec) {
        ap += (r - last_recall) * p;
        last_recall = *r;
    }
    DetectionScores {
        precision: ratio(tp_reported, reported),
        recall: ratio(tp_reported, n_truth),
        average_precision: if n_truth == 0 { 1.0 } else { ap },
        reported,
    }
}

/// Draws the scene in grey with truth boxes (blue) and reported detections (green) as an RGB
/// u8 image.
fn overlay(scene: &Image, truth: &[[f64; 4]], dets: &[Detection]) -> Result<Image, String> {
    let (w, h) = (scene.width(), scene.height());
    let gray = gray_f32(scene);
    let mut rgb: Vec<u8> = gray
        .iter()
        .flat_map(|&v| {
            let b = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            [b, b, b]
        })
        .collect();
    let mut rect = |b: &[f64; 4], colour: [u8; 3]| {
        let x0 = (b[0].round().max(0.0) as usize).min(w - 1);
        let y0 = (b[1].round().max(0.0) as usize).min(h - 1);
        let x1 = ((b[0] + b[2]).round().max(0.0) as usize).clamp(1, w) - 1;
        let y1 = ((b[1] + b[3]).round().max(0.0) as usize).clamp(1, h) - 1;
        let mut put =
            |x: usize, y: usize| rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&colour);
        for x in x0..=x1.max(x0) {
            put(x, y0);
            put(x, y1.max(y0));
        }
        for y in y0..=y1.max(y0) {
            put(x0, y);
            put(x1.max(x0), y);
        }
    };
    for t in truth {
        rect(t, [40, 90, 255]);
    }
    for d in dets {
        rect(&d.bbox, [0, 220, 0]);
    }
    Image::from_u8(w, h, Channels::Rgb, rgb).map_err(|e| e.to_string())
}

/// HOG + linear classifier detector (`learn.hog_detector`). See [`train_detector`], [`detect`]
/// and [`evaluate_detections`].
#[derive(Debug, Clone, PartialEq)]
pub struct HogDetector {
    config: DetectorConfig,
}

impl Op for HogDetector {
    type Params = HogDetectorParams;
    const ID: &'static str = "learn.hog_detector";
    const SUMMARY: &'static str = "Trains a HOG + logistic-regression window classifier and detects at multiple scales with NMS.";
    const DOC: &'static str = r#"
The Dalal–Triggs detector (N. Dalal, B. Triggs, "Histograms of Oriented Gradients for Human
Detection", CVPR 2005) with logistic regression in place of the linear SVM:

1. Training: every `window`-sized tile of the `training` mosaic (tiles row-major, as many as
   `labels` has rows; labels nonzero = object) is described by HOG (`describe.hog`: `cell_size`
   cells, 2×2-cell blocks at a one-cell stride, 9 unsigned bins, L2-Hys) and an L2-regularised
   logistic regression (`solver`, `l2`, `max_iterations`; features standardised) is fitted.
2. Detection: the `scene` (gray, or RGB as luma) is shrunk by `scale_step` per level (area
   resampling) while the window fits; each level's dense HOG is computed once and every window
   at a `stride_cells`-cell stride is scored as σ(b + w·h) from its blocks.
3. Windows with P ≥ 0.05 go through greedy non-maximum suppression (decreasing score, drop a
   box whose IoU with a kept box exceeds `nms_iou`); those with P ≥ `score_threshold` are
   reported.
4. Evaluation (when `truth` is connected; PASCAL VOC, Everingham et al. 2010): detections by
   decreasing score are matched to the unmatched truth box of highest IoU ≥ 0.5. `precision`
   and `recall` are those of the reported boxes; `average_precision` is the area under the
   all-point interpolated precision–recall curve of all NMS survivors (P ≥ 0.05).

Outputs: `boxes` (k × 5: x, y, width, height, score; scene pixels, decreasing score),
`metrics` (`detections`, `windows`, `levels`, `train_accuracy`, `train_iterations`, and with
`truth`: `precision`, `recall`, `average_precision`, `truth_boxes`), `overlay` (RGB u8: the
scene with truth boxes in blue and detections in green).

Deterministic for any thread count. Speed–accuracy knobs: `stride_cells` and `scale_step`
(fewer windows and levels: faster, coarser localisation).

Example:
    "detector": (op: "learn.hog_detector",
                 inputs: { "training": "people.training", "labels": "people.labels",
                           "scene": "people.scene", "truth": "people.truth" },
                 params: (scale_step: 1.2, score_threshold: 0.6)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "training",
                PortType::Image,
                "Mosaic of window-sized training tiles, row-major.",
            ),
            PortSpec::new(
                "labels",
                PortType::Matrix,
                "n × 1 tile labels: nonzero = object, 0 = background.",
            ),
            PortSpec::new("scene", PortType::Image, "Image to search, gray or RGB."),
            PortSpec::new(
                "truth",
                PortType::Matrix,
                "m × 4 ground-truth boxes (x, y, width, height), px.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "boxes",
                PortType::Matrix,
                "k × 5 detections: x, y, width, height (px), score.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "detections, windows, levels, train_accuracy, train_iterations; precision, recall, average_precision, truth_boxes with truth.",
            ),
            PortSpec::new(
                "overlay",
                PortType::Image,
                "RGB u8 scene with truth (blue) and detection (green) boxes.",
            ),
        ]
    }

    fn new(p: HogDetectorParams) -> Result<Self, String> {
        let cell = p.cell_size;
        if !(2..=32).contains(&cell) {
            return Err(format!("`cell_size` must be between 2 and 32, got {cell}"));
        }
        if p.window
            .iter()
            .any(|&v| v % cell != 0 || v < 2 * cell || v > 1024)
        {
            return Err(format!(
                "`window` sides must be multiples of `cell_size` ({cell}), at least two cells and at most 1024 px, got {:?}",
                p.window
            ));
        }
        if p.stride_cells == 0 {
            return Err("`stride_cells` must be at least 1".into());
        }
        if !(p.scale_step.is_finite() && p.scale_step > 1.0) {
            return Err(format!("`scale_step` must be > 1, got {}", p.scale_step));
        }
        for (name, v) in [
            ("score_threshold", p.score_threshold),
            ("nms_iou", p.nms_iou),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(format!("`{name}` must be in [0, 1], got {v}"));
            }
        }
        if !(p.l2.is_finite() && p.l2 >= 0.0) {
            return Err(format!("`l2` must be finite and ≥ 0, got {}", p.l2));
        }
        if p.max_iterations == 0 {
            return Err("`max_iterations` must be at least 1".into());
        }
        Ok(HogDetector {
            config: DetectorConfig {
                window_w: p.window[0] as usize,
                window_h: p.window[1] as usize,
                hog: HogParams {
                    cell_size: cell,
                    ..HogParams::default()
                },
                stride_cells: p.stride_cells as usize,
                scale_step: p.scale_step,
                score_threshold: p.score_threshold,
                nms_iou: p.nms_iou,
                classifier: LogisticConfig {
                    solver: p.solver,
                    l2: p.l2,
                    max_iterations: p.max_iterations as usize,
                    tolerance: 1e-6,
                    ..LogisticConfig::default()
                },
            },
        })
    }
}

impl Operator for HogDetector {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let training = inputs.image("training")?;
        let labels = single_column(input_matrix(inputs, "labels")?, "labels")
            .map_err(|e| OpError::input("labels", e))?;
        let scene = inputs.image("scene")?;
        let truth: Option<Vec<[f64; 4]>> = match inputs.get("truth") {
            None => None,
            Some(_) => {
                let m = input_matrix(inputs, "truth")?;
                if m.cols != 4 || m.data.iter().any(|v| !v.is_finite()) {
                    return Err(OpError::input(
                        "truth",
                        format!("must be a finite m × 4 matrix, got {}×{}", m.rows, m.cols),
                    ));
                }
                Some(
                    m.data
                        .chunks_exact(4)
                        .map(|r| [r[0], r[1], r[2], r[3]])
                        .collect(),
                )
            }
        };
        let detector = train_detector(training, &labels, &self.config)
            .map_err(|e| OpError::input("training", e))?;
        let report =
            detect(scene, &detector, &self.config).map_err(|e| OpError::input("scene", e))?;
        let reported: Vec<Detection> = report
            .candidates
            .iter()
            .copied()
            .filter(|d| d.score >= self.config.score_threshold)
            .collect();
        let mut m = Metrics::new();
        m.insert("detections".into(), reported.len() as f64);
        m.insert("windows".into(), report.windows as f64);
        m.insert("levels".into(), report.levels as f64);
        m.insert("train_accuracy".into(), detector.train_accuracy);
        m.insert("train_iterations".into(), detector.iterations as f64);
        if let Some(t) = &truth {
            let s = evaluate_detections(&report.candidates, t, self.config.score_threshold);
            m.insert("precision".into(), s.precision);
            m.insert("recall".into(), s.recall);
            m.insert("average_precision".into(), s.average_precision);
            m.insert("truth_boxes".into(), t.len() as f64);
        }
        let rows: Vec<f64> = reported
            .iter()
            .flat_map(|d| [d.bbox[0], d.bbox[1], d.bbox[2], d.bbox[3], d.score])
            .collect();
        let image =
            overlay(scene, truth.as_deref().unwrap_or(&[]), &reported).map_err(OpError::failed)?;
        Ok(Outputs::new()
            .with("boxes", matrix_value(reported.len(), 5, rows)?)
            .with("metrics", Value::metrics(m))
            .with("overlay", Value::image(image)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::pedestrians::{PedestrianParams, pedestrian_set};

    #[test]
    fn iou_and_nms_by_hand() {
        let a = [0.0, 0.0, 10.0, 10.0];
        let b = [5.0, 0.0, 10.0, 10.0];
        assert!((iou(&a, &b) - 50.0 / 150.0).abs() < 1e-12);
        assert_eq!(iou(&a, &[20.0, 20.0, 1.0, 1.0]), 0.0);
        let dets = vec![
            Detection {
                bbox: a,
                score: 0.6,
            },
            Detection {
                bbox: b,
                score: 0.9,
            },
            Detection {
                bbox: [30.0, 0.0, 10.0, 10.0],
                score: 0.7,
            },
        ];
        let kept = non_maximum_suppression(dets.clone(), 0.3);
        assert_eq!(
            kept.iter().map(|d| d.score).collect::<Vec<_>>(),
            vec![0.9, 0.7]
        );
        // IoU 1/3 is not above 0.4: all kept.
        assert_eq!(non_maximum_suppression(dets, 0.4).len(), 3);
    }

    #[test]
    fn voc_evaluation_by_hand() {
        let truth = [[0.0, 0.0, 10.0, 10.0], [50.0, 0.0, 10.0, 10.0]];
        let d = |x: f64, s: f64| Detection {
            bbox: [x, 0.0, 10.0, 10.0],
            score: s,
        };
        // Ranked: hit, miss, hit → precisions 1, ½, ⅔ at recalls ½, ½, 1: AP = ½·1 + ½·⅔.
        let ranked = [d(0.0, 0.9), d(25.0, 0.8), d(51.0, 0.4)];
        let s = evaluate_detections(&ranked, &truth, 0.5);
        assert_eq!(s.reported, 2);
        assert_eq!((s.precision, s.recall), (0.5, 0.5));
        assert!((s.average_precision - (0.5 + 0.5 * 2.0 / 3.0)).abs() < 1e-12);
        // A duplicate of a matched box is a false positive.
        let s = evaluate_detections(&[d(0.0, 0.9), d(1.0, 0.8)], &truth[..1], 0.0);
        assert_eq!(s.precision, 0.5);
    }

    #[test]
    fn finds_the_figures_in_the_generated_scene() {
        let set = pedestrian_set(&PedestrianParams {
            positives: 150,
            negatives: 300,
            scene: [192, 128],
            figures: 3,
            seed: 3,
            ..PedestrianParams::default()
        })
        .unwrap();
        let op = HogDetector::new(HogDetectorParams::default()).unwrap();
        let det = train_detector(&set.training, &set.labels, &op.config).unwrap();
        assert!(det.train_accuracy > 0.97, "{}", det.train_accuracy);
        let report = detect(&set.scene, &det, &op.config).unwrap();
        let s = evaluate_detections(&report.candidates, &set.truth, 0.5);
        assert!(s.recall >= 0.66, "{s:?}");
        assert!(s.precision >= 0.5, "{s:?}");
        assert!(s.average_precision >= 0.6, "{s:?}");
    }

    #[test]
    fn mismatched_mosaic_is_an_error() {
        let op = HogDetector::new(HogDetectorParams::default()).unwrap();
        let img = Image::from_f32(40, 64, Channels::Gray, vec![0.0; 40 * 64]).unwrap();
        assert!(
            train_detector(&img, &[1.0], &op.config)
                .unwrap_err()
                .contains("mosaic")
        );
        assert!(
            HogDetector::new(HogDetectorParams {
                window: [30, 64],
                ..Default::default()
            })
            .is_err()
        );
    }
}
