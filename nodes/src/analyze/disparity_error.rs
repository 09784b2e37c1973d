//! `analyze.disparity_error`: a disparity map scored against ground truth — the share of
//! pixels with known truth whose disparity is missing or off by more than a threshold (the
//! "bad pixels" measure of the Middlebury benchmark, with missing counted as bad).
//!
//! The algorithm is [`disparity_error`]; [`DisparityError`] is the thin operator around it.
//! Counts are integers and the error sum runs in pixel order, so the result does not depend on
//! the thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Metrics, PixelData, Value};

params! {
    /// Parameters of `analyze.disparity_error`.
    pub struct DisparityErrorParams {
        /// A matched pixel is bad when `|disparity − truth| > bad_threshold_px`. Default 2.
        bad_threshold_px: f64 = 2.0 => [min = 0.0, unit = "px"],
        /// Truth samples are `disparity · truth_scale` (e.g. 256 for 16-bit KITTI maps, 1 for
        /// Middlebury 8-bit maps at full size). Default 1.
        truth_scale: f64 = 1.0 => [above = 0.0],
        /// The truth sample value meaning "unknown" (before scaling). Default 0.
        truth_invalid: f64 = 0.0,
    }
}

/// Counts of a disparity map against its truth; see [`disparity_error`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DisparityCounts {
    /// Pixels compared.
    pub pixels: u64,
    /// Pixels with known truth.
    pub known: u64,
    /// Known-truth pixels without a disparity (NaN or infinite).
    pub missing: u64,
    /// Known-truth pixels with a disparity off by more than the threshold.
    pub bad_matched: u64,
    /// Pixels (known truth or not) with a disparity.
    pub matched: u64,
    /// Σ |disparity − truth| over matched known-truth pixels, px.
    pub abs_error_sum: f64,
}

impl DisparityCounts {
    /// The metrics of the operator (shares are 0 when their denominator is 0).
    pub fn metrics(&self) -> Metrics {
        let share = |a: u64, b: u64| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        let matched_known = self.known - self.missing;
        let mut m = Metrics::new();
        m.insert(
            "bad".into(),
            share(self.missing + self.bad_matched, self.known),
        );
        m.insert("missing".into(), share(self.missing, self.known));
        m.insert("bad_matched".into(), share(self.bad_matched, matched_known));
        m.insert("density".into(), share(matched_known, self.known));
        m.insert(
            "mean_abs_error_px".into(),
            if matched_known == 0 {
                0.0
            } else {
                self.abs_error_sum / matched_known as f64
            },
        );
        m.insert("known".into(), self.known as f64);
        m
    }
}

/// Scores `disparity` (px, non-finite = missing) against `truth` (raw samples: known where
/// `≠ truth_invalid` and finite, in px after dividing by `truth_scale`).
pub fn disparity_error(
    disparity: &[f32],
    truth: &[f64],
    truth_scale: f64,
    truth_invalid: f64,
    bad_threshold_px: f64,
) -> DisparityCounts {
    let mut c = DisparityCounts {
        pixels: disparity.len().min(truth.len()) as u64,
        ..DisparityCounts::default()
    };
    for (&d, &t) in disparity.iter().zip(truth) {
        let has = d.is_finite();
        if has {
            c.matched += 1;
        }
        if !t.is_finite() || t == truth_invalid {
            continue;
        }
        c.known += 1;
        if !has {
            c.missing += 1;
            continue;
        }
        let e = (f64::from(d) - t / truth_scale).abs();
        c.abs_error_sum += e;
        if e > bad_threshold_px {
            c.bad_matched += 1;
        }
    }
    c
}

/// Disparity error against ground truth (`analyze.disparity_error`). See [`disparity_error`].
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityError {
    params: DisparityErrorParams,
}

impl Op for DisparityError {
    type Params = DisparityErrorParams;
    const ID: &'static str = "analyze.disparity_error";
    const SUMMARY: &'static str = "Scores a disparity map against ground truth: bad (missing or off by > threshold), density, error.";
    const DOC: &'static str = r#"
Compares `disparity` (gray f32, px, NaN where missing — the output of sfm.stereo) with
`truth` (gray u8, u16 or f32 ground-truth disparity of the same size; a sample is
`disparity · truth_scale`, and `truth_invalid` marks unknown truth).

Metrics, over the pixels with known truth:
- `bad`: share whose disparity is missing or off by more than bad_threshold_px (the headline
  number: Middlebury's bad-pixel rate with missing pixels counted as bad);
- `missing`: share without a disparity; `density` = 1 − missing;
- `bad_matched`: share of the matched ones off by more than bad_threshold_px;
- `mean_abs_error_px`: mean |disparity − truth| of the matched ones;
- `known`: their count.

Example:
    "error": (op: "analyze.disparity_error",
              inputs: { "disparity": "stereo.disparity", "truth": "truth.image" },
              params: (bad_threshold_px: 2.0, truth_scale: 1.0, truth_invalid: 0.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "disparity",
                PortType::Image,
                "Disparity, gray f32, px, NaN where missing.",
            ),
            PortSpec::new(
                "truth",
                PortType::Image,
                "Ground-truth disparity, gray u8/u16/f32, samples = px · truth_scale.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "bad, missing, bad_matched, density, mean_abs_error_px, known.",
        )]
    }

    fn new(params: DisparityErrorParams) -> Result<Self, String> {
        if !(params.bad_threshold_px.is_finite() && params.bad_threshold_px >= 0.0) {
            return Err(format!(
                "`bad_threshold_px` must be finite and ≥ 0, got {}",
                params.bad_threshold_px
            ));
        }
        if !(params.truth_scale.is_finite() && params.truth_scale > 0.0) {
            return Err(format!(
                "`truth_scale` must be finite and > 0, got {}",
                params.truth_scale
            ));
        }
        if !params.truth_invalid.is_finite() {
            return Err("`truth_invalid` must be finite".into());
        }
        Ok(DisparityError { params })
    }
}

impl Operator for DisparityError {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let d = inputs.image("disparity")?;
        let t = inputs.image("truth")?;
        let disp = match d.as_f32() {
            Some(s) if d.channels() == Channels::Gray => s,
            _ => {
                return Err(OpError::input(
                    "disparity",
                    format!(
                        "must be a gray f32 disparity map, got {} {}",
                        d.channels().name(),
                        d.depth().name()
                    ),
                ));
            }
        };
        if t.channels() != Channels::Gray {
            return Err(OpError::input(
                "truth",
                format!("must have one channel, got {}", t.channels().name()),
            ));
        }
        if (d.width(), d.height()) != (t.width(), t.height()) {
            return Err(OpError::input(
                "truth",
                format!(
                    "is {}×{}, but `disparity` is {}×{}",
                    t.width(),
                    t.height(),
                    d.width(),
                    d.height()
                ),
            ));
        }
        let truth: Vec<f64> = match t.data() {
            PixelData::U8(v) => v.iter().map(|&s| f64::from(s)).collect(),
            PixelData::U16(v) => v.iter().map(|&s| f64::from(s)).collect(),
            PixelData::F32(v) => v.iter().map(|&s| f64::from(s)).collect(),
        };
        let p = &self.params;
        let c = disparity_error(
            disp,
            &truth,
            p.truth_scale,
            p.truth_invalid,
            p.bad_threshold_px,
        );
        Ok(Outputs::new().with("metrics", Value::metrics(c.metrics())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_missing_and_bad_pixels_over_known_truth() {
        let nan = f32::NAN;
        // Truth ×2 (scale 2), 0 unknown.
        let truth = [0.0, 20.0, 20.0, 20.0, 20.0, 0.0, 40.0];
        let disp = [5.0, 10.0, 12.5, 7.0, nan, nan, 20.0];
        let c = disparity_error(&disp, &truth, 2.0, 0.0, 2.0);
        assert_eq!(c.pixels, 7);
        assert_eq!(c.known, 5);
        assert_eq!(c.missing, 1);
        // 12.5 vs 10 (off 2.5) and 7 vs 10 (off 3) are bad; 10 and 20 exact.
        assert_eq!(c.bad_matched, 2);
        assert_eq!(c.matched, 5);
        assert!((c.abs_error_sum - 5.5).abs() < 1e-12);
        let m = c.metrics();
        assert!((m["bad"] - 3.0 / 5.0).abs() < 1e-12);
        assert!((m["missing"] - 0.2).abs() < 1e-12);
        assert!((m["bad_matched"] - 0.5).abs() < 1e-12);
        assert!((m["density"] - 0.8).abs() < 1e-12);
        assert!((m["mean_abs_error_px"] - 5.5 / 4.0).abs() < 1e-12);
        assert_eq!(m["known"], 5.0);
        // A looser threshold keeps only the 3 px error bad.
        assert_eq!(disparity_error(&disp, &truth, 2.0, 0.0, 2.5).bad_matched, 1);
    }

    #[test]
    fn empty_and_all_unknown_truth_give_zero_shares() {
        let m = disparity_error(&[], &[], 1.0, 0.0, 2.0).metrics();
        assert_eq!((m["bad"], m["density"], m["known"]), (0.0, 0.0, 0.0));
        let c = disparity_error(&[1.0, f32::NAN], &[0.0, 0.0], 1.0, 0.0, 2.0);
        assert_eq!((c.known, c.matched), (0, 1));
    }
}
