//! `analyze.evaluate` and `analyze.roc`: how well a binary mask or a score image matches a
//! ground-truth mask.
//!
//! [`confusion`] counts true/false positives/negatives and [`ConfusionCounts::metrics`] derives
//! the usual rates; [`roc_curve`] sweeps a threshold over a score image and [`plot_curves`]
//! rasterizes the ROC and precision–recall curves with a small anti-aliased line drawer.
//!
//! Counts are integers summed per fixed chunk of pixels, so results are identical for any
//! thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Metrics, PixelData, Value};
use rayon::prelude::*;

/// Pixels per parallel chunk (a constant, never derived from the thread count).
const CHUNK: usize = 1 << 16;

/// Largest number of thresholds `analyze.roc` sweeps.
pub const MAX_STEPS: u32 = 1 << 20;

/// Largest plot side, px.
pub const MAX_PLOT_SIDE: u32 = 8192;

/// Smallest plot side, px.
pub const MIN_PLOT_SIDE: u32 = 32;

/// Confusion counts of a binary prediction against a binary truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ConfusionCounts {
    /// Predicted positive, truly positive.
    pub tp: u64,
    /// Predicted positive, truly negative.
    pub fp: u64,
    /// Predicted negative, truly negative.
    pub tn: u64,
    /// Predicted negative, truly positive.
    pub fn_: u64,
}

impl ConfusionCounts {
    /// The counts (`tp`, `fp`, `tn`, `fn`) and the rates that are defined: `sensitivity` =
    /// `recall` = TP/(TP+FN), `specificity` = TN/(TN+FP), `precision` = TP/(TP+FP), `f1` =
    /// 2TP/(2TP+FP+FN), `iou` = TP/(TP+FP+FN), `accuracy` = (TP+TN)/total. A rate whose
    /// denominator is 0 is left out.
    pub fn metrics(&self) -> Metrics {
        let (tp, fp, tn, fn_) = (
            self.tp as f64,
            self.fp as f64,
            self.tn as f64,
            self.fn_ as f64,
        );
        let mut m = Metrics::new();
        m.insert("tp".into(), tp);
        m.insert("fp".into(), fp);
        m.insert("tn".into(), tn);
        m.insert("fn".into(), fn_);
        let mut ratio = |name: &str, num: f64, den: f64| {
            if den > 0.0 {
                m.insert(name.into(), num / den);
            }
        };
        ratio("sensitivity", tp, tp + fn_);
        ratio("recall", tp, tp + fn_);
        ratio("specificity", tn, tn + fp);
        ratio("precision", tp, tp + fp);
        ratio("f1", 2.0 * tp, 2.0 * tp + fp + fn_);
        ratio("iou", tp, tp + fp + fn_);
        ratio("accuracy", tp + tn, tp + tn + fp + fn_);
        m
    }
}

/// Positive flags of a gray mask: every nonzero sample is positive. Errors on a non-gray
/// image or NaN samples.
pub fn mask_flags(image: &Image) -> Result<Vec<bool>, String> {
    if image.channels() != Channels::Gray {
        return Err(format!(
            "must be a gray mask, got {}",
            image.channels().name()
        ));
    }
    Ok(match image.data() {
        PixelData::U8(v) => v.iter().map(|&s| s != 0).collect(),
        PixelData::U16(v) => v.iter().map(|&s| s != 0).collect(),
        PixelData::F32(v) => {
            if v.iter().any(|s| s.is_nan()) {
                return Err("contains NaN".into());
            }
            v.iter().map(|&s| s != 0.0).collect()
        }
    })
}

/// Confusion counts of `prediction` against `truth` (equal lengths).
pub fn confusion(prediction: &[bool], truth: &[bool]) -> ConfusionCounts {
    prediction
        .par_chunks(CHUNK)
        .zip(truth.par_chunks(CHUNK))
        .map(|(p, t)| {
            let mut c = ConfusionCounts::default();
            for (&p, &t) in p.iter().zip(t) {
                match (p, t) {
                    (true, true) => c.tp += 1,
                    (true, false) => c.fp += 1,
                    (false, false) => c.tn += 1,
                    (false, true) => c.fn_ += 1,
                }
            }
            c
        })
        .reduce(ConfusionCounts::default, |a, b| ConfusionCounts {
            tp: a.tp + b.tp,
            fp: a.fp + b.fp,
            tn: a.tn + b.tn,
            fn_: a.fn_ + b.fn_,
        })
}

fn check_same_size(a: &Image, b: &Image, port: &str, other: &str) -> Result<(), OpError> {
    if (a.width(), a.height()) != (b.width(), b.height()) {
        return Err(OpError::input(
            port,
            format!(
                "is {}×{}, but `{other}` is {}×{}",
                a.width(),
                a.height(),
                b.width(),
                b.height()
            ),
        ));
    }
    Ok(())
}

/// Mask evaluation (`analyze.evaluate`). See [`confusion`].
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluate;

impl Op for Evaluate {
    type Params = ocellus_engine::params::NoParams;
    const ID: &'static str = "analyze.evaluate";
    const SUMMARY: &'static str = "Compares a binary mask with a ground-truth mask: confusion counts, precision, recall, F1, IoU.";
    const DOC: &'static str = r#"
Counts, over all pixels, true positives (prediction and truth positive), false positives,
true negatives and false negatives, where a pixel is positive when its sample is nonzero. Both
masks are gray, of one size; their depths may differ (u8, u16, f32; NaN is an error).

Metrics: `tp`, `fp`, `tn`, `fn`; `sensitivity` = `recall` = TP/(TP+FN); `specificity` =
TN/(TN+FP); `precision` = TP/(TP+FP); `f1` = 2TP/(2TP+FP+FN) (the Dice coefficient); `iou` =
TP/(TP+FP+FN) (Jaccard); `accuracy` = (TP+TN)/(TP+FP+TN+FN). A rate whose denominator is zero
(e.g. precision with no predicted positives) is left out rather than reported as 0 or NaN.
These are scikit-learn's `confusion_matrix`, `precision_score`, `recall_score`, `f1_score`,
`jaccard_score` on the flattened masks.

Example:
    "score": (op: "analyze.evaluate", inputs: { "prediction": "cut.mask", "truth": "gt.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "prediction",
                PortType::Image,
                "Predicted mask, gray, nonzero = positive.",
            ),
            PortSpec::new(
                "truth",
                PortType::Image,
                "Ground-truth mask, gray, nonzero = positive, same size.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "tp, fp, tn, fn, sensitivity, specificity, precision, recall, f1, iou, accuracy.",
        )]
    }

    fn new(_: ocellus_engine::params::NoParams) -> Result<Self, String> {
        Ok(Evaluate)
    }
}

impl Operator for Evaluate {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let prediction = inputs.image("prediction")?;
        let truth = inputs.image("truth")?;
        check_same_size(truth, prediction, "truth", "prediction")?;
        let p = mask_flags(prediction).map_err(|e| OpError::input("prediction", e))?;
        let t = mask_flags(truth).map_err(|e| OpError::input("truth", e))?;
        let counts = confusion(&p, &t);
        Ok(Outputs::new().with("metrics", Value::metrics(counts.metrics())))
    }
}

/// One row of a threshold sweep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RocPoint {
    /// Threshold: a pixel is predicted positive when its score is ≥ this.
    pub threshold: f64,
    /// True-positive rate TP/P.
    pub tpr: f64,
    /// False-positive rate FP/N.
    pub fpr: f64,
    /// Precision TP/(TP+FP), 1 when nothing is predicted positive.
    pub precision: f64,
    /// Recall (= TPR).
    pub recall: f64,
}

/// A threshold sweep with its summary numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct RocCurve {
    /// Points by decreasing threshold.
    pub points: Vec<RocPoint>,
    /// Area under the ROC curve through (0, 0), the points and (1, 1), by the trapezoid rule.
    pub auc: f64,
    /// Average precision Σ (R_k − R_{k−1})·P_k, R_{−1} = 0.
    pub average_precision: f64,
    /// Positive pixels in the truth.
    pub positives: u64,
    /// Negative pixels in the truth.
    pub negatives: u64,
}

/// Sweeps `steps` (≥ 2) thresholds evenly from the largest score down to the smallest
/// (`t_k = max − k·(max − min)/(steps − 1)`, the last exactly `min`) and measures each
/// "score ≥ t_k" prediction against `truth`. Errors on NaN scores or when the truth has no
/// positive or no negative pixel.
pub fn roc_curve(scores: &[f64], truth: &[bool], steps: usize) -> Result<RocCurve, String> {
    if scores.iter().any(|s| s.is_nan()) {
        return Err("scores contain NaN".into());
    }
    let steps = steps.max(2);
    let (lo, hi) = scores
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &s| {
            (lo.min(s), hi.max(s))
        });
    let positives = truth.iter().filter(|&&t| t).count() as u64;
    let negatives = truth.len() as u64 - positives;
    if positives == 0 || negatives == 0 {
        return Err(format!(
            "the truth needs positive and negative pixels, has {positives} and {negatives}"
        ));
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return Err("scores must be finite".into());
    }
    let step = (hi - lo) / (steps - 1) as f64;
    let last = steps - 1;
    let thresholds: Vec<f64> = (0..steps)
        .map(|k| if k == last { lo } else { hi - k as f64 * step })
        .collect();
    let inv_step = if step > 0.0 { 1.0 / step } else { 0.0 };
    // First threshold index at which a score counts as positive: the estimate ⌊(hi − s)/step⌋
    // (a truncating conversion, no libm call), corrected against the thresholds themselves.
    let first_index = |s: f64| -> usize {
        let mut k = (((hi - s) * inv_step) as usize).min(last);
        while k > 0 && s >= thresholds[k - 1] {
            k -= 1;
        }
        while k < last && s < thresholds[k] {
            k += 1;
        }
        k
    };
    let hist = scores
        .par_chunks(CHUNK)
        .zip(truth.par_chunks(CHUNK))
        .map(|(s, t)| {
            let mut h = vec![0u64; 2 * steps];
            for (&s, &t) in s.iter().zip(t) {
                h[2 * first_index(s) + usize::from(t)] += 1;
            }
            h
        })
        .reduce(
            || vec![0u64; 2 * steps],
            |mut a, b| {
                for (a, b) in a.iter_mut().zip(b) {
                    *a += b;
                }
                a
            },
        );
    let (p, n) = (positives as f64, negatives as f64);
    let (mut tp, mut fp) = (0u64, 0u64);
    let mut points = Vec::with_capacity(steps);
    let (mut auc, mut ap) = (0.0, 0.0);
    let (mut prev_tpr, mut prev_fpr) = (0.0, 0.0);
    for k in 0..steps {
        fp += hist[2 * k];
        tp += hist[2 * k + 1];
        let tpr = tp as f64 / p;
        let fpr = fp as f64 / n;
        let precision = if tp + fp > 0 {
            tp as f64 / (tp + fp) as f64
        } else {
            1.0
        };
        auc += (fpr - prev_fpr) * (tpr + prev_tpr) * 0.5;
        ap += (tpr - prev_tpr) * precision;
        prev_tpr = tpr;
        prev_fpr = fpr;
        points.push(RocPoint {
            threshold: thresholds[k],
            tpr,
            fpr,
            precision,
            recall: tpr,
        });
    }
    Ok(RocCurve {
        points,
        auc,
        average_precision: ap,
        positives,
        negatives,
    })
}

/// Plot colours (linear 0–1 RGB).
const ROC_COLOR: [f32; 3] = [0.12, 0.47, 0.71];
const PR_COLOR: [f32; 3] = [0.84, 0.15, 0.16];
const GRID_COLOR: [f32; 3] = [0.88, 0.88, 0.88];
const AXIS_COLOR: [f32; 3] = [0.0, 0.0, 0.0];
const CHANCE_COLOR: [f32; 3] = [0.65, 0.65, 0.65];

/// An RGB canvas of f32 samples in 0..1 with anti-aliased line drawing.
struct Canvas {
    width: usize,
    height: usize,
    rgb: Vec<f32>,
}

impl Canvas {
    fn new(width: usize, height: usize) -> Canvas {
        Canvas {
            width,
            height,
            rgb: vec![1.0; width * height * 3],
        }
    }

    /// Draws the polyline through `points` (pixel coordinates, pixel centres at +0.5) with
    /// half-width `r` px: coverage per pixel is clamp(r + 0.5 − distance, 0, 1), the largest
    /// over the segments, blended over the canvas once.
    fn polyline(&mut self, points: &[[f64; 2]], r: f64, color: [f32; 3]) {
        if points.is_empty() || self.width == 0 || self.height == 0 {
            return;
        }
        let mut cover: Vec<(usize, f32)> = Vec::new();
        let mut seen = std::collections::HashMap::new();
        let segments: Vec<([f64; 2], [f64; 2])> = if points.len() == 1 {
            vec![(points[0], points[0])]
        } else {
            points.windows(2).map(|w| (w[0], w[1])).collect()
        };
        let (wmax, hmax) = ((self.width - 1) as f64, (self.height - 1) as f64);
        for (a, b) in segments {
            let x0 = (a[0].min(b[0]) - r - 1.0).floor().clamp(0.0, wmax) as usize;
            let x1 = (a[0].max(b[0]) + r + 1.0).ceil().clamp(0.0, wmax) as usize;
            let y0 = (a[1].min(b[1]) - r - 1.0).floor().clamp(0.0, hmax) as usize;
            let y1 = (a[1].max(b[1]) + r + 1.0).ceil().clamp(0.0, hmax) as usize;
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let len2 = dx * dx + dy * dy;
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                    let t = if len2 > 0.0 {
                        (((px - a[0]) * dx + (py - a[1]) * dy) / len2).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    let d = (px - a[0] - t * dx).hypot(py - a[1] - t * dy);
                    let c = (r + 0.5 - d).clamp(0.0, 1.0) as f32;
                    if c > 0.0 {
                        let idx = y * self.width + x;
                        let slot = seen.entry(idx).or_insert_with(|| {
                            cover.push((idx, 0.0));
                            cover.len() - 1
                        });
                        let entry = &mut cover[*slot];
                        entry.1 = entry.1.max(c);
                    }
                }
            }
        }
        for (idx, c) in cover {
            for (s, &col) in self.rgb[idx * 3..idx * 3 + 3].iter_mut().zip(&color) {
                *s += c * (col - *s);
            }
        }
    }

    fn into_image(self) -> Result<Image, String> {
        let data = self
            .rgb
            .iter()
            .map(|&s| (s * 255.0).round().clamp(0.0, 255.0) as u8)
            .collect();
        Image::from_u8(self.width, self.height, Channels::Rgb, data).map_err(|e| e.to_string())
    }
}

/// Draws the ROC curve (left panel: FPR across, TPR up, with the chance diagonal) and the
/// precision–recall curve (right panel: recall across, precision up) of `curve` on a white
/// `width × height` RGB u8 image, each panel with a 0.1 grid and axes.
pub fn plot_curves(curve: &RocCurve, width: usize, height: usize) -> Result<Image, String> {
    let mut canvas = Canvas::new(width, height);
    let panel = width as f64 / 2.0;
    let margin = (panel.min(height as f64) / 10.0).max(4.0);
    let roc: Vec<[f64; 2]> = std::iter::once([0.0, 0.0])
        .chain(curve.points.iter().map(|p| [p.fpr, p.tpr]))
        .collect();
    let pr: Vec<[f64; 2]> = curve
        .points
        .iter()
        .map(|p| [p.recall, p.precision])
        .collect();
    for (i, data, color) in [(0, &roc, ROC_COLOR), (1, &pr, PR_COLOR)] {
        let x0 = i as f64 * panel + margin;
        let x1 = (i + 1) as f64 * panel - margin / 2.0;
        let (y0, y1) = (margin / 2.0, height as f64 - margin);
        let map = |u: f64, v: f64| [x0 + u * (x1 - x0), y1 - v * (y1 - y0)];
        for g in 1..=10 {
            let u = g as f64 / 10.0;
            canvas.polyline(&[map(u, 0.0), map(u, 1.0)], 0.5, GRID_COLOR);
            canvas.polyline(&[map(0.0, u), map(1.0, u)], 0.5, GRID_COLOR);
        }
        if i == 0 {
            canvas.polyline(&[map(0.0, 0.0), map(1.0, 1.0)], 0.5, CHANCE_COLOR);
        }
        canvas.polyline(
            &[map(0.0, 1.0), map(0.0, 0.0), map(1.0, 0.0)],
            0.75,
            AXIS_COLOR,
        );
        let line: Vec<[f64; 2]> = data.iter().map(|p| map(p[0], p[1])).collect();
        canvas.polyline(&line, 1.25, color);
    }
    canvas.into_image()
}

/// Scores of a gray image as f64.
fn score_values(image: &Image) -> Result<Vec<f64>, String> {
    if image.channels() != Channels::Gray {
        return Err(format!(
            "must be a gray score image, got {}",
            image.channels().name()
        ));
    }
    Ok(match image.data() {
        PixelData::U8(v) => v.iter().map(|&s| f64::from(s)).collect(),
        PixelData::U16(v) => v.iter().map(|&s| f64::from(s)).collect(),
        PixelData::F32(v) => v.iter().map(|&s| f64::from(s)).collect(),
    })
}

params! {
    /// Parameters of `analyze.roc`.
    pub struct RocParams {
        /// Number of thresholds swept, 2..=1048576, evenly from the largest score to the
        /// smallest (256 covers every level of a full-range u8 score).
        steps: u32 = 256,
        /// Plot width, px (32..=8192); each of the two panels takes half.
        width: u32 = 640,
        /// Plot height, px (32..=8192).
        height: u32 = 320,
    }
}

/// ROC and precision–recall analysis (`analyze.roc`). See [`roc_curve`] and [`plot_curves`].
#[derive(Debug, Clone, PartialEq)]
pub struct Roc {
    steps: usize,
    width: usize,
    height: usize,
}

impl Op for Roc {
    type Params = RocParams;
    const ID: &'static str = "analyze.roc";
    const SUMMARY: &'static str = "Sweeps a threshold over a score image against a truth mask: ROC and precision-recall curves, AUC, AP.";
    const DOC: &'static str = r#"
Thresholds the gray `score` image (u8, u16 or f32, in its own units; NaN is an error) at
`steps` values t_k = max − k·(max − min)/(steps − 1), k = 0..steps−1 (decreasing, the last
exactly the smallest score), predicting positive where score ≥ t_k, and compares each
prediction with the `truth` mask (gray, nonzero = positive, same size; it must hold both
classes).

Outputs:
- `curve`: Matrix, one row per threshold in decreasing order, columns
  [threshold, TPR, FPR, precision, recall] (TPR = recall = TP/P, FPR = FP/N, precision =
  TP/(TP+FP), 1 where nothing is predicted positive). TPR and FPR never decrease down the rows;
  the last row is (1, 1).
- `metrics`: `auc` = area under the ROC polyline from (0, 0) through the rows (trapezoid rule;
  with a threshold at every distinct score it is the Mann–Whitney AUC, ties counted half),
  `average_precision` = Σ_k (R_k − R_{k−1})·P_k with R_{−1} = 0 (scikit-learn's
  `average_precision_score` when every distinct score is a threshold), `positives`,
  `negatives`.
- `plot`: RGB u8 image, white, `width × height`: the ROC curve (blue; FPR across, TPR up, grey
  chance diagonal) in the left half, the precision–recall curve (red; recall across, precision
  up) in the right half, each on [0, 1]² with a 0.1 grid and black axes, drawn with an
  anti-aliased line rasterizer (coverage = clamp(half-width + ½ − distance, 0, 1)). No text.

Reference: Fawcett, "An introduction to ROC analysis", Pattern Recognition Letters 27 (2006);
scikit-learn `roc_curve`, `roc_auc_score`, `average_precision_score`.

Example:
    "roc": (op: "analyze.roc", inputs: { "score": "edges.magnitude", "truth": "gt.image" }, params: (steps: 128)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "score",
                PortType::Image,
                "Gray score image, any depth: larger = more likely positive.",
            ),
            PortSpec::new(
                "truth",
                PortType::Image,
                "Ground-truth mask, gray, nonzero = positive, same size.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "curve",
                PortType::Matrix,
                "steps × 5: threshold, TPR, FPR, precision, recall; thresholds decreasing.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "auc, average_precision, positives, negatives.",
            ),
            PortSpec::new(
                "plot",
                PortType::Image,
                "RGB u8 plot: ROC (left) and precision–recall (right).",
            ),
        ]
    }

    fn new(params: RocParams) -> Result<Self, String> {
        let RocParams {
            steps,
            width,
            height,
        } = params;
        if !(2..=MAX_STEPS).contains(&steps) {
            return Err(format!("`steps` must be in 2..={MAX_STEPS}, got {steps}"));
        }
        for (name, v) in [("width", width), ("height", height)] {
            if !(MIN_PLOT_SIDE..=MAX_PLOT_SIDE).contains(&v) {
                return Err(format!(
                    "`{name}` must be {MIN_PLOT_SIDE}..={MAX_PLOT_SIDE} px, got {v}"
                ));
            }
        }
        Ok(Roc {
            steps: steps as usize,
            width: width as usize,
            height: height as usize,
        })
    }
}

impl Operator for Roc {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let score = inputs.image("score")?;
        let truth = inputs.image("truth")?;
        check_same_size(truth, score, "truth", "score")?;
        let scores = score_values(score).map_err(|e| OpError::input("score", e))?;
        let t = mask_flags(truth).map_err(|e| OpError::input("truth", e))?;
        let curve = roc_curve(&scores, &t, self.steps).map_err(|e| OpError::input("score", e))?;
        let data: Vec<f64> = curve
            .points
            .iter()
            .flat_map(|p| [p.threshold, p.tpr, p.fpr, p.precision, p.recall])
            .collect();
        let matrix =
            Matrix::new(curve.points.len(), 5, data).map_err(|e| OpError::failed(e.to_string()))?;
        let plot = plot_curves(&curve, self.width, self.height).map_err(OpError::failed)?;
        let mut metrics = Metrics::new();
        metrics.insert("auc".into(), curve.auc);
        metrics.insert("average_precision".into(), curve.average_precision);
        metrics.insert("positives".into(), curve.positives as f64);
        metrics.insert("negatives".into(), curve.negatives as f64);
        Ok(Outputs::new()
            .with("curve", Value::Matrix(std::sync::Arc::new(matrix)))
            .with("metrics", Value::metrics(metrics))
            .with("plot", Value::image(plot)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use proptest::prelude::*;

    fn ctx() -> RunContext {
        RunContext {
            node: "eval".into(),
            threads: 1,
            element: None,
        }
    }

    fn gray_u8(w: usize, h: usize, v: Vec<u8>) -> Image {
        Image::from_u8(w, h, Channels::Gray, v).unwrap()
    }

    #[test]
    fn hand_computed_confusion() {
        let pred = gray_u8(3, 2, vec![255, 255, 0, 0, 1, 0]);
        let truth =
            Image::from_f32(3, 2, Channels::Gray, vec![1.0, 0.0, 0.0, 0.5, 1.0, 0.0]).unwrap();
        let specs = Evaluate::inputs();
        let values = [Some(Value::image(pred)), Some(Value::image(truth))];
        let mut out = Evaluate.run(&ctx(), &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("no metrics");
        };
        assert_eq!((m["tp"], m["fp"], m["tn"], m["fn"]), (2.0, 1.0, 2.0, 1.0));
        assert_eq!(m["sensitivity"], 2.0 / 3.0);
        assert_eq!(m["recall"], 2.0 / 3.0);
        assert_eq!(m["specificity"], 2.0 / 3.0);
        assert_eq!(m["precision"], 2.0 / 3.0);
        assert_eq!(m["f1"], 4.0 / 6.0);
        assert_eq!(m["iou"], 0.5);
        assert_eq!(m["accuracy"], 4.0 / 6.0);
    }

    #[test]
    fn undefined_rates_are_left_out_and_errors_are_clear() {
        let m = confusion(&[false, false], &[false, false]).metrics();
        assert_eq!(m["tn"], 2.0);
        assert!(!m.contains_key("precision") && !m.contains_key("recall"));
        assert_eq!(m["specificity"], 1.0);
        let m = confusion(&[], &[]).metrics();
        assert_eq!(m.len(), 4);
        let specs = Evaluate::inputs();
        let values = [
            Some(Value::image(gray_u8(2, 1, vec![0, 1]))),
            Some(Value::image(gray_u8(1, 2, vec![0, 1]))),
        ];
        assert!(Evaluate.run(&ctx(), &Inputs::new(&specs, &values)).is_err());
        let rgb = Image::from_u8(1, 1, Channels::Rgb, vec![0, 0, 0]).unwrap();
        assert!(mask_flags(&rgb).is_err());
        let nan = Image::from_f32(1, 1, Channels::Gray, vec![f32::NAN]).unwrap();
        assert!(mask_flags(&nan).is_err());
    }

    proptest! {
        #[test]
        fn counts_add_up_and_f1_is_dice(seed in 0u64..10_000, n in 1usize..500) {
            let r = randoms(seed, 2 * n);
            let p: Vec<bool> = r[..n].iter().map(|v| *v < 0.4).collect();
            let t: Vec<bool> = r[n..].iter().map(|v| *v < 0.6).collect();
            let c = confusion(&p, &t);
            prop_assert_eq!(c.tp + c.fp + c.tn + c.fn_, n as u64);
            prop_assert_eq!(c.tp + c.fp, p.iter().filter(|&&x| x).count() as u64);
            prop_assert_eq!(c.tp + c.fn_, t.iter().filter(|&&x| x).count() as u64);
            let m = c.metrics();
            if let (Some(&pr), Some(&re), Some(&f1)) = (m.get("precision"), m.get("recall"), m.get("f1"))
                && pr + re > 0.0
            {
                prop_assert!((f1 - 2.0 * pr * re / (pr + re)).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn perfect_score_has_auc_one() {
        let n = 1000;
        let r = randoms(4, n);
        let truth: Vec<bool> = r.iter().map(|v| *v < 0.3).collect();
        let scores: Vec<f64> = truth
            .iter()
            .zip(&r)
            .map(|(&t, &v)| if t { 2.0 + v } else { v })
            .collect();
        let curve = roc_curve(&scores, &truth, 100).unwrap();
        assert_eq!(curve.auc, 1.0);
        assert_eq!(curve.average_precision, 1.0);
        // The truth itself as the score.
        let binary: Vec<f64> = truth.iter().map(|&t| f64::from(u8::from(t))).collect();
        let curve = roc_curve(&binary, &truth, 2).unwrap();
        assert_eq!((curve.auc, curve.average_precision), (1.0, 1.0));
    }

    #[test]
    fn random_score_has_auc_one_half() {
        let (w, h) = (512, 512);
        let n = w * h;
        let r = randoms(11, 2 * n);
        let scores: Vec<f64> = r[..n].iter().map(|v| (v * 256.0).floor()).collect();
        let truth: Vec<bool> = r[n..].iter().map(|v| *v < 0.25).collect();
        let curve = roc_curve(&scores, &truth, 256).unwrap();
        assert!((curve.auc - 0.5).abs() < 0.02, "{}", curve.auc);
        assert!((curve.average_precision - 0.25).abs() < 0.02);
        // Monotone: thresholds decrease, TPR and FPR never decrease, last point (1, 1).
        for w in curve.points.windows(2) {
            assert!(w[0].threshold > w[1].threshold);
            assert!(w[0].tpr <= w[1].tpr && w[0].fpr <= w[1].fpr);
        }
        let last = curve.points.last().unwrap();
        assert_eq!((last.tpr, last.fpr), (1.0, 1.0));
    }

    #[test]
    fn auc_equals_mann_whitney_when_every_level_is_a_threshold() {
        let n = 1500;
        let r = randoms(21, 2 * n);
        // Scores correlated with the truth, on 0..=255 with both extremes present.
        let truth: Vec<bool> = r[n..].iter().map(|v| *v < 0.4).collect();
        let mut scores: Vec<f64> = r[..n]
            .iter()
            .zip(&truth)
            .map(|(v, &t)| ((v * 200.0) + if t { 55.0 } else { 0.0 }).floor())
            .collect();
        scores[0] = 0.0;
        scores[1] = 255.0;
        let curve = roc_curve(&scores, &truth, 256).unwrap();
        let (mut wins, mut pairs) = (0.0, 0.0);
        for (i, &ti) in truth.iter().enumerate() {
            if !ti {
                continue;
            }
            for (j, &tj) in truth.iter().enumerate() {
                if tj {
                    continue;
                }
                pairs += 1.0;
                wins += if scores[i] > scores[j] {
                    1.0
                } else if scores[i] == scores[j] {
                    0.5
                } else {
                    0.0
                };
            }
        }
        assert!(
            (curve.auc - wins / pairs).abs() < 1e-12,
            "{} vs {}",
            curve.auc,
            wins / pairs
        );
        // The thresholds are exactly the levels 255, 254, ..., 0.
        for (k, p) in curve.points.iter().enumerate() {
            assert_eq!(p.threshold, 255.0 - k as f64);
        }
    }

    #[test]
    fn constant_score_and_bad_truth() {
        let curve = roc_curve(&[3.0; 4], &[true, false, true, false], 10).unwrap();
        assert_eq!(curve.auc, 0.5);
        assert!(roc_curve(&[1.0, 2.0], &[true, true], 10).is_err());
        assert!(roc_curve(&[f64::NAN, 2.0], &[true, false], 10).is_err());
    }

    #[test]
    fn roc_operator_outputs_curve_metrics_and_plot() {
        let (w, h) = (64, 64);
        let r = randoms(5, w * h);
        let truth: Vec<u8> = (0..w * h)
            .map(|p| if p % w < w / 2 { 255 } else { 0 })
            .collect();
        let score: Vec<f32> = truth
            .iter()
            .zip(&r)
            .map(|(&t, v)| *v as f32 * 0.5 + if t > 0 { 0.3 } else { 0.0 })
            .collect();
        let op = Roc::new(RocParams {
            steps: 64,
            width: 200,
            height: 100,
        })
        .unwrap();
        let specs = Roc::inputs();
        let values = [
            Some(Value::image(
                Image::from_f32(w, h, Channels::Gray, score).unwrap(),
            )),
            Some(Value::image(gray_u8(w, h, truth))),
        ];
        let mut out = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Matrix(m)) = out.take("curve") else {
            panic!("no curve");
        };
        assert_eq!((m.rows, m.cols), (64, 5));
        let Some(Value::Metrics(metrics)) = out.take("metrics") else {
            panic!("no metrics");
        };
        assert!(metrics["auc"] > 0.8 && metrics["auc"] < 1.0);
        let Some(Value::Image(plot)) = out.take("plot") else {
            panic!("no plot");
        };
        assert_eq!((plot.width(), plot.height()), (200, 100));
        assert_eq!(plot.channels(), Channels::Rgb);
        let px = plot.as_u8().unwrap();
        assert_eq!(&px[..3], &[255, 255, 255]);
        let blueish = px.chunks(3).filter(|p| p[2] > 150 && p[0] < 80).count();
        let reddish = px.chunks(3).filter(|p| p[0] > 180 && p[2] < 80).count();
        assert!(blueish > 50 && reddish > 50, "{blueish} {reddish}");
        // Anti-aliasing leaves intermediate levels.
        assert!(px.iter().any(|&v| v > 60 && v < 200));
        assert!(
            Roc::new(RocParams {
                steps: 1,
                ..RocParams::default()
            })
            .is_err()
        );
    }
}
