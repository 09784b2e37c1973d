//! `analyze.match_accuracy`: how many matches agree with a known homography between the views.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Keypoint, Match, Matrix, Metrics, Value};

use crate::matching::{keypoints, matches};

params! {
    /// Parameters of `analyze.match_accuracy`.
    pub struct MatchAccuracyParams {
        /// A match is correct if the right keypoint lies within this distance of the
        /// homography's image of the left keypoint, px. Default 3.
        threshold_px: f64 = 3.0 => [min = 0.0, unit = "px"],
    }
}

/// Match accuracy against a homography (`analyze.match_accuracy`). See [`match_accuracy`].
#[derive(Debug, Clone, PartialEq)]
pub struct MatchAccuracy {
    threshold_px: f64,
}

impl Op for MatchAccuracy {
    type Params = MatchAccuracyParams;
    const ID: &'static str = "analyze.match_accuracy";
    const SUMMARY: &'static str =
        "Counts the matches consistent with a ground-truth homography and their errors.";
    const DOC: &'static str = r#"
For each match, maps the left keypoint through the homography H (3×3, left → right, as in the
Oxford affine-covariant data sets' `H1to3p`): `p' = (H [x, y, 1]ᵀ)` dehomogenized, and measures
the reprojection error ‖p' − right keypoint‖ (px). A match is correct if the error is at most
`threshold_px` (points mapped to infinity are never correct).

Metrics: `matches` (count), `correct`, `correct_ratio` = correct / matches (left out without
matches), `mean_error_px` and `median_error_px` of the correct matches (left out if none; the
median of an even count is the mean of the two middle values).

Reference: K. Mikolajczyk, C. Schmid, "A performance evaluation of local descriptors", PAMI
2005 (matching precision on the graf / boat / ... pairs).

Example:
    "acc": (op: "analyze.match_accuracy", inputs: { "keypoints_left": "orb1.keypoints",
            "keypoints_right": "orb2.keypoints", "matches": "match.matches",
            "homography": "h.matrix" }, params: (threshold_px: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints_left",
                PortType::Keypoints,
                "Keypoints of the first view (match.query).",
            ),
            PortSpec::new(
                "keypoints_right",
                PortType::Keypoints,
                "Keypoints of the second view (match.train).",
            ),
            PortSpec::new("matches", PortType::Matches, "Matches to evaluate."),
            PortSpec::new(
                "homography",
                PortType::Matrix,
                "3×3 homography mapping first-view pixels to second-view pixels.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "matches, correct, correct_ratio, mean_error_px, median_error_px.",
        )]
    }

    fn new(params: MatchAccuracyParams) -> Result<Self, String> {
        let t = params.threshold_px;
        if !(t.is_finite() && t >= 0.0) {
            return Err(format!("`threshold_px` must be finite and ≥ 0, got {t}"));
        }
        Ok(MatchAccuracy { threshold_px: t })
    }
}

impl Operator for MatchAccuracy {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let kl = keypoints(inputs, "keypoints_left")?;
        let kr = keypoints(inputs, "keypoints_right")?;
        let m = matches(inputs, "matches")?;
        let h = match inputs.require("homography")? {
            Value::Matrix(h) => homography_of(h, "homography")?,
            other => {
                return Err(OpError::input(
                    "homography",
                    format!("expected Matrix, got {}", other.port_type()),
                ));
            }
        };
        let metrics = match_accuracy(kl, kr, m, &h, self.threshold_px)?;
        Ok(Outputs::new().with("metrics", Value::metrics(metrics)))
    }
}

/// A finite 3×3 homography from a Matrix input; errors name `port`.
pub(crate) fn homography_of(m: &Matrix, port: &str) -> Result<[f64; 9], OpError> {
    if m.rows != 3 || m.cols != 3 || m.data.len() != 9 {
        return Err(OpError::input(
            port,
            format!("must be 3×3, got {}×{}", m.rows, m.cols),
        ));
    }
    if m.data.iter().any(|v| !v.is_finite()) {
        return Err(OpError::input(port, "holds a non-finite entry"));
    }
    let mut h = [0.0; 9];
    h.copy_from_slice(&m.data);
    Ok(h)
}

/// Reprojection error of one match under `h` (px); infinite where the point maps to infinity.
pub fn reprojection_error(left: &Keypoint, right: &Keypoint, h: &[f64; 9]) -> f64 {
    let (x, y) = (f64::from(left.x), f64::from(left.y));
    let w = h[6] * x + h[7] * y + h[8];
    if w.abs() < 1e-12 || !w.is_finite() {
        return f64::INFINITY;
    }
    let px = (h[0] * x + h[1] * y + h[2]) / w;
    let py = (h[3] * x + h[4] * y + h[5]) / w;
    let e = (px - f64::from(right.x)).hypot(py - f64::from(right.y));
    if e.is_nan() { f64::INFINITY } else { e }
}

/// The metrics of `analyze.match_accuracy` (see its doc). Errors on match indices outside the
/// keypoint lists.
pub fn match_accuracy(
    keypoints_left: &[Keypoint],
    keypoints_right: &[Keypoint],
    matches: &[Match],
    h: &[f64; 9],
    threshold_px: f64,
) -> Result<Metrics, OpError> {
    let mut errors = Vec::new();
    for m in matches {
        let (Some(a), Some(b)) = (
            keypoints_left.get(m.query as usize),
            keypoints_right.get(m.train as usize),
        ) else {
            return Err(OpError::input(
                "matches",
                format!(
                    "match ({}, {}) indexes past the keypoints ({} left, {} right)",
                    m.query,
                    m.train,
                    keypoints_left.len(),
                    keypoints_right.len()
                ),
            ));
        };
        let e = reprojection_error(a, b, h);
        if e <= threshold_px {
            errors.push(e);
        }
    }
    let mut out = Metrics::new();
    out.insert("matches".into(), matches.len() as f64);
    out.insert("correct".into(), errors.len() as f64);
    if !matches.is_empty() {
        out.insert(
            "correct_ratio".into(),
            errors.len() as f64 / matches.len() as f64,
        );
    }
    if !errors.is_empty() {
        let n = errors.len();
        out.insert(
            "mean_error_px".into(),
            errors.iter().sum::<f64>() / n as f64,
        );
        errors.sort_by(f64::total_cmp);
        let median = if n % 2 == 1 {
            errors[n / 2]
        } else {
            0.5 * (errors[n / 2 - 1] + errors[n / 2])
        };
        out.insert("median_error_px".into(), median);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 1.0,
            angle: -1.0,
            response: 0.0,
            octave: 0,
        }
    }

    fn m(query: u32, train: u32) -> Match {
        Match {
            query,
            train,
            distance: 0.0,
        }
    }

    #[test]
    fn hand_computed() {
        // H: scale 2 and shift (10, 0): (1, 1) → (12, 2), (2, 3) → (14, 6), (0, 0) → (10, 0).
        let h = [2.0, 0.0, 10.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0];
        let kl = [kp(1.0, 1.0), kp(2.0, 3.0), kp(0.0, 0.0)];
        // Errors: 0; (14, 9) vs (14, 6): 3; (13, 4) vs (10, 0): √(9 + 16) = 5.
        let kr = [kp(12.0, 2.0), kp(14.0, 9.0), kp(13.0, 4.0)];
        let matches = [m(0, 0), m(1, 1), m(2, 2)];
        let r = match_accuracy(&kl, &kr, &matches, &h, 3.0).unwrap();
        assert_eq!(r["matches"], 3.0);
        assert_eq!(r["correct"], 2.0);
        assert!((r["correct_ratio"] - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(r["mean_error_px"], 1.5);
        assert_eq!(r["median_error_px"], 1.5);
        let r = match_accuracy(&kl, &kr, &matches, &h, 5.0).unwrap();
        assert_eq!(r["correct"], 3.0);
        assert_eq!(r["median_error_px"], 3.0);
        assert!((r["mean_error_px"] - 8.0 / 3.0).abs() < 1e-12);
        // Perspective: w = 0.5 x + 1 at (2, 0) is 2: (2, 0) → (1, 0).
        let hp = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.5, 0.0, 1.0];
        assert!((reprojection_error(&kp(2.0, 0.0), &kp(1.0, 0.0), &hp)).abs() < 1e-12);
        // Point at infinity (w = 0 at x = −2) is never correct.
        assert!(reprojection_error(&kp(-2.0, 0.0), &kp(1.0, 0.0), &hp).is_infinite());
    }

    #[test]
    fn empty_and_bad_indices() {
        let h = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let r = match_accuracy(&[], &[], &[], &h, 3.0).unwrap();
        assert_eq!(r["matches"], 0.0);
        assert!(!r.contains_key("correct_ratio") && !r.contains_key("median_error_px"));
        assert!(match_accuracy(&[kp(0.0, 0.0)], &[], &[m(0, 0)], &h, 3.0).is_err());
        assert!(
            MatchAccuracy::new(MatchAccuracyParams {
                threshold_px: f64::NAN
            })
            .is_err()
        );
        let bad = Matrix::new(2, 2, vec![0.0; 4]).unwrap();
        assert!(homography_of(&bad, "homography").is_err());
    }
}
