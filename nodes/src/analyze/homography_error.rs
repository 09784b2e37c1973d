//! `analyze.homography_error`: how far an estimated homography is from the true one, measured
//! where it matters — on the image it maps.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, Value};

use super::match_accuracy::homography_of;

/// Largest error reported, px: a point the estimate sends to (or beyond) infinity counts as this.
pub const MAX_ERROR_PX: f64 = 1e6;

/// Grid points per side of the `grid_rms_px` metric.
pub const GRID_SIDE: usize = 16;

params! {
    /// Parameters of `analyze.homography_error`.
    pub struct HomographyErrorParams {
        /// The true homography, 3×3, first-view pixels → second-view pixels (row-major rows).
        truth: Vec<Vec<f64>> = vec![vec![1.0, 0.0, 0.0], vec![0.0, 1.0, 0.0], vec![0.0, 0.0, 1.0]],
        /// Width of the first view, px, over which the error is measured (≥ 1). Ignored when
        /// `image` is connected.
        width: u32 = 0 => [unit = "px"],
        /// Height of the first view, px (≥ 1). Ignored when `image` is connected.
        height: u32 = 0 => [unit = "px"],
    }
}

/// Homography error against the truth (`analyze.homography_error`). See [`homography_error`].
#[derive(Debug, Clone, PartialEq)]
pub struct HomographyError {
    truth: [f64; 9],
    size: Option<(u32, u32)>,
}

impl Op for HomographyError {
    type Params = HomographyErrorParams;
    const ID: &'static str = "analyze.homography_error";
    const SUMMARY: &'static str =
        "Scores an estimated homography against the true one by transfer errors over the image.";
    const DOC: &'static str = r#"
Maps points of the first view (`width` × `height`, or the size of `image` when connected)
through the estimated homography H and the true one, and measures how far apart the two images
of each point land (px):

- `corner_error_px`: the mean over the four image corners (0, 0), (w, 0), (w, h), (0, h) — the
  "average corner error" of D. DeTone, T. Malisiewicz, A. Rabinovich, "Deep Image Homography
  Estimation", RSS workshop 2016; `max_corner_error_px` the largest of the four;
- `grid_rms_px`: the RMS over a 16 × 16 grid of points spanning the image (pixel centres from
  0.5 to w − 0.5), which weighs the whole view rather than its corners.

Both are invariant to the scale (and sign) of H. A point that the estimate sends to infinity
or beyond it (its homogeneous w, with H oriented so that the view's centre has w > 0, changes
sign against the truth's) counts as 10⁶ px, the cap of every metric, so a degenerate estimate
scores as very bad rather than failing the run.

Example:
    "error": (op: "analyze.homography_error", inputs: { "H": "ransac.H", "image": "left.image" },
              params: (truth: [[0.87, -0.21, 94.6], [0.20, 0.81, -18.1], [0.0001, -0.0001, 1.0]])),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "H",
                PortType::Matrix,
                "Estimated 3×3 homography, first-view pixels → second-view pixels.",
            ),
            PortSpec::new(
                "image",
                PortType::Image,
                "The first view; only its size is used (else `width`, `height`).",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "corner_error_px, max_corner_error_px, grid_rms_px.",
        )]
    }

    fn new(params: HomographyErrorParams) -> Result<Self, String> {
        let rows = &params.truth;
        if rows.len() != 3 || rows.iter().any(|r| r.len() != 3) {
            return Err("`truth` must be a 3×3 matrix: three rows of three numbers".into());
        }
        let mut truth = [0.0; 9];
        for (k, v) in rows.iter().flatten().enumerate() {
            if !v.is_finite() {
                return Err(format!("`truth` holds a non-finite entry ({v})"));
            }
            truth[k] = *v;
        }
        if determinant(&truth).abs() < 1e-12 {
            return Err("`truth` is singular".into());
        }
        let size = (params.width > 0 && params.height > 0).then_some((params.width, params.height));
        Ok(HomographyError { truth, size })
    }
}

impl Operator for HomographyError {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let h = match inputs.require("H")? {
            Value::Matrix(m) => homography_of(m, "H")?,
            other => {
                return Err(OpError::input(
                    "H",
                    format!("expected Matrix, got {}", other.port_type()),
                ));
            }
        };
        let (width, height) = match inputs.get("image") {
            Some(Value::Image(image)) => (image.width() as f64, image.height() as f64),
            Some(other) => {
                return Err(OpError::input(
                    "image",
                    format!("expected Image, got {}", other.port_type()),
                ));
            }
            None => match self.size {
                Some((w, h)) => (f64::from(w), f64::from(h)),
                None => {
                    return Err(OpError::input(
                        "image",
                        "not connected: connect the first view or set `width` and `height`",
                    ));
                }
            },
        };
        if width < 1.0 || height < 1.0 {
            return Err(OpError::input("image", "the view is empty"));
        }
        let e = homography_error(&h, &self.truth, width, height);
        let mut metrics = Metrics::new();
        metrics.insert("corner_error_px".into(), e.corner_mean_px);
        metrics.insert("max_corner_error_px".into(), e.corner_max_px);
        metrics.insert("grid_rms_px".into(), e.grid_rms_px);
        Ok(Outputs::new().with("metrics", Value::metrics(metrics)))
    }
}

fn determinant(h: &[f64; 9]) -> f64 {
    h[0] * (h[4] * h[8] - h[5] * h[7]) - h[1] * (h[3] * h[8] - h[5] * h[6])
        + h[2] * (h[3] * h[7] - h[4] * h[6])
}

/// Transfer errors of an estimate against the truth (see [`homography_error`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransferErrors {
    /// Mean distance at the four corners, px.
    pub corner_mean_px: f64,
    /// Largest distance at the four corners, px.
    pub corner_max_px: f64,
    /// RMS distance over a [`GRID_SIDE`]² grid of pixel centres, px.
    pub grid_rms_px: f64,
}

/// Distance between the images of (x, y) under `h` and `truth`, capped at [`MAX_ERROR_PX`]; a
/// point `h` sends to infinity, or to the other side of it than `truth` does, gets the cap.
pub fn transfer_distance(h: &[f64; 9], truth: &[f64; 9], x: f64, y: f64) -> f64 {
    let map = |m: &[f64; 9]| {
        let w = m[6] * x + m[7] * y + m[8];
        (
            (m[0] * x + m[1] * y + m[2]) / w,
            (m[3] * x + m[4] * y + m[5]) / w,
            w,
        )
    };
    let (ex, ey, ew) = map(h);
    let (tx, ty, tw) = map(truth);
    let scale_h = h[6].abs().max(h[7].abs()).max(h[8].abs()).max(1e-300);
    if ew.abs() < 1e-12 * scale_h || (ew > 0.0) != (tw > 0.0) {
        return MAX_ERROR_PX;
    }
    let d = (ex - tx).hypot(ey - ty);
    if d.is_finite() {
        d.min(MAX_ERROR_PX)
    } else {
        MAX_ERROR_PX
    }
}

/// Corner and grid transfer errors of the estimate `h` against `truth` over a `width` ×
/// `height` first view (see `analyze.homography_error`).
pub fn homography_error(h: &[f64; 9], truth: &[f64; 9], width: f64, height: f64) -> TransferErrors {
    // H and −H are one homography: orient both so that the view's centre has w > 0; points
    // with w ≤ 0 then lie beyond the line at infinity.
    let oriented = |m: &[f64; 9]| {
        let w = m[6] * width / 2.0 + m[7] * height / 2.0 + m[8];
        if w < 0.0 { m.map(|v| -v) } else { *m }
    };
    let (h, truth) = (&oriented(h), &oriented(truth));
    let corners = [(0.0, 0.0), (width, 0.0), (width, height), (0.0, height)]
        .map(|(x, y)| transfer_distance(h, truth, x, y));
    let corner_mean_px = corners.iter().sum::<f64>() / 4.0;
    let corner_max_px = corners.iter().copied().fold(0.0, f64::max);
    let mut sum_sq = 0.0;
    for j in 0..GRID_SIDE {
        for i in 0..GRID_SIDE {
            let at = |k: usize, side: f64| 0.5 + (side - 1.0) * k as f64 / (GRID_SIDE - 1) as f64;
            let d = transfer_distance(h, truth, at(i, width), at(j, height));
            sum_sq += d * d;
        }
    }
    TransferErrors {
        corner_mean_px,
        corner_max_px,
        grid_rms_px: (sum_sq / (GRID_SIDE * GRID_SIDE) as f64).sqrt(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TRUTH: [f64; 9] = [
        0.872604473,
        -0.213507943,
        94.5686077,
        0.204034258,
        0.811550358,
        -18.1429492,
        0.0001078977,
        -0.000110528542,
        1.0,
    ];

    #[test]
    fn the_truth_itself_and_any_multiple_of_it_score_zero() {
        let e = homography_error(&TRUTH, &TRUTH, 640.0, 480.0);
        assert_eq!(e.corner_mean_px, 0.0);
        assert_eq!(e.grid_rms_px, 0.0);
        let scaled = TRUTH.map(|v| -2.5 * v);
        let e = homography_error(&scaled, &TRUTH, 640.0, 480.0);
        assert!(e.corner_mean_px < 1e-9 && e.grid_rms_px < 1e-9, "{e:?}");
    }

    /// A pure translation error of (3, 4) px moves every point by 5 px.
    #[test]
    fn a_translation_error_is_its_length_everywhere() {
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let shifted = [1.0, 0.0, 3.0, 0.0, 1.0, 4.0, 0.0, 0.0, 1.0];
        let e = homography_error(&shifted, &identity, 100.0, 50.0);
        assert!((e.corner_mean_px - 5.0).abs() < 1e-12);
        assert!((e.corner_max_px - 5.0).abs() < 1e-12);
        assert!((e.grid_rms_px - 5.0).abs() < 1e-12);
    }

    /// A 1 % scale about the origin: corner errors 0, w/100, |(w, h)|/100, h/100.
    #[test]
    fn a_scale_error_grows_with_the_distance_from_the_origin() {
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let scaled = [1.01, 0.0, 0.0, 0.0, 1.01, 0.0, 0.0, 0.0, 1.0];
        let e = homography_error(&scaled, &identity, 300.0, 400.0);
        let expected = (0.0 + 3.0 + 5.0 + 4.0) / 4.0;
        assert!((e.corner_mean_px - expected).abs() < 1e-9, "{e:?}");
        assert!((e.corner_max_px - 5.0).abs() < 1e-9);
        assert!(e.grid_rms_px > 0.0 && e.grid_rms_px < 5.0);
    }

    /// An estimate that sends part of the view through infinity scores the cap, not NaN.
    #[test]
    fn points_sent_to_infinity_get_the_cap() {
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        // w = 1 − x/50 vanishes at x = 50 and is negative beyond.
        let wild = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, -0.02, 0.0, 1.0];
        let e = homography_error(&wild, &identity, 100.0, 100.0);
        assert_eq!(e.corner_max_px, MAX_ERROR_PX);
        assert!(e.corner_mean_px.is_finite() && e.grid_rms_px.is_finite());
        assert_eq!(
            transfer_distance(&wild, &identity, 50.0, 10.0),
            MAX_ERROR_PX
        );
    }

    #[test]
    fn bad_params_are_rejected() {
        let p = |truth: Vec<Vec<f64>>| HomographyErrorParams {
            truth,
            width: 10,
            height: 10,
        };
        assert!(HomographyError::new(p(vec![vec![1.0, 0.0], vec![0.0, 1.0]])).is_err());
        assert!(HomographyError::new(p(vec![vec![0.0; 3]; 3])).is_err());
        assert!(
            HomographyError::new(p(vec![
                vec![1.0, 0.0, f64::NAN],
                vec![0.0, 1.0, 0.0],
                vec![0.0, 0.0, 1.0]
            ]))
            .is_err()
        );
    }
}
