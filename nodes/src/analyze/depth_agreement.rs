//! `analyze.depth_agreement`: how well two depth maps agree on coverage (finite vs +∞) and on
//! depth where both cover — the check that two renderers (rasterizer and ray tracer) or a
//! reconstruction and its ground truth see the same surfaces.
//!
//! The algorithm is [`depth_agreement`]; [`DepthAgreement`] is the thin operator around it.
//! Counts are integers, so the result does not depend on the thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, Value};

params! {
    /// Parameters of `analyze.depth_agreement`.
    pub struct DepthAgreementParams {
        /// Two depths agree when `|a − b| ≤ relative_tolerance · max(a, b)` (dimensionless).
        relative_tolerance: f64 = 1e-4,
    }
}

/// Agreement counts of two depth maps; see [`depth_agreement`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct AgreementCounts {
    /// Pixels compared.
    pub pixels: u64,
    /// Pixels where both or neither depth is finite.
    pub coverage_agree: u64,
    /// Pixels finite in both.
    pub both_covered: u64,
    /// Pixels finite in both and within the tolerance.
    pub depth_agree: u64,
    /// Largest relative difference over the pixels both cover (0 when none).
    pub max_relative_error: f64,
}

/// Compares depth `a` with depth `b` pixel by pixel. A depth is "covered" when finite and
/// non-negative; +∞ (and NaN) is a miss. Relative error is `|a − b| / max(a, b)` (0 when
/// both are 0).
pub fn depth_agreement(a: &[f32], b: &[f32], relative_tolerance: f64) -> AgreementCounts {
    let mut c = AgreementCounts {
        pixels: a.len().min(b.len()) as u64,
        ..AgreementCounts::default()
    };
    for (&x, &y) in a.iter().zip(b) {
        let (cx, cy) = (x.is_finite() && x >= 0.0, y.is_finite() && y >= 0.0);
        if cx == cy {
            c.coverage_agree += 1;
        }
        if cx && cy {
            c.both_covered += 1;
            let (x, y) = (f64::from(x), f64::from(y));
            let scale = x.max(y);
            let rel = if scale > 0.0 {
                (x - y).abs() / scale
            } else {
                0.0
            };
            c.max_relative_error = c.max_relative_error.max(rel);
            if rel <= relative_tolerance {
                c.depth_agree += 1;
            }
        }
    }
    c
}

/// Depth-map agreement (`analyze.depth_agreement`). See [`depth_agreement`].
#[derive(Debug, Clone, PartialEq)]
pub struct DepthAgreement {
    relative_tolerance: f64,
}

impl Op for DepthAgreement {
    type Params = DepthAgreementParams;
    const ID: &'static str = "analyze.depth_agreement";
    const SUMMARY: &'static str =
        "Compares two depth maps: coverage agreement and depth agreement where both cover.";
    const DOC: &'static str = r#"
Compares `depth` with `reference` (gray f32 images of the same size, such as the `depth`
outputs of render.rasterize, render.trace and render.raycast: distance along each pixel's unit
ray, +inf where nothing is hit). A pixel is covered when its depth is finite and ≥ 0.

Metrics:
- `coverage_agreement`: fraction of pixels where both or neither image covers;
- `depth_agreement`: fraction of the pixels both cover whose depths satisfy
  |a − b| ≤ relative_tolerance · max(a, b) (1 when no pixel is covered by both);
- `agreement`: fraction of all pixels that agree on coverage and, where covered, on depth;
- `both_covered`, `covered`, `reference_covered`: pixel counts;
- `max_relative_error`: the largest |a − b| / max(a, b) over the pixels both cover.

Example:
    "agree": (op: "analyze.depth_agreement", inputs: { "depth": "raster.depth", "reference": "trace.depth" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "depth",
                PortType::Image,
                "Depth map, gray f32, +inf on a miss.",
            ),
            PortSpec::new(
                "reference",
                PortType::Image,
                "Reference depth map, same size and format.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "coverage_agreement, depth_agreement, agreement, both_covered, covered, reference_covered, max_relative_error.",
        )]
    }

    fn new(params: DepthAgreementParams) -> Result<Self, String> {
        let t = params.relative_tolerance;
        if !(t.is_finite() && t >= 0.0) {
            return Err(format!(
                "`relative_tolerance` must be finite and ≥ 0, got {t}"
            ));
        }
        Ok(DepthAgreement {
            relative_tolerance: t,
        })
    }
}

fn depth_samples<'a>(image: &'a Image, port: &str) -> Result<&'a [f32], OpError> {
    match image.as_f32() {
        Some(s) if image.channels() == Channels::Gray => Ok(s),
        _ => Err(OpError::input(
            port,
            format!(
                "must be a gray f32 depth map, got {} {}",
                image.channels().name(),
                image.depth().name()
            ),
        )),
    }
}

impl Operator for DepthAgreement {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let a = inputs.image("depth")?;
        let b = inputs.image("reference")?;
        let (da, db) = (depth_samples(a, "depth")?, depth_samples(b, "reference")?);
        if (a.width(), a.height()) != (b.width(), b.height()) {
            return Err(OpError::input(
                "reference",
                format!(
                    "is {}×{}, but `depth` is {}×{}",
                    b.width(),
                    b.height(),
                    a.width(),
                    a.height()
                ),
            ));
        }
        let c = depth_agreement(da, db, self.relative_tolerance);
        let covered = |d: &[f32]| d.iter().filter(|v| v.is_finite() && **v >= 0.0).count() as f64;
        let n = c.pixels.max(1) as f64;
        let mut m = Metrics::new();
        m.insert("coverage_agreement".into(), c.coverage_agree as f64 / n);
        m.insert(
            "depth_agreement".into(),
            if c.both_covered == 0 {
                1.0
            } else {
                c.depth_agree as f64 / c.both_covered as f64
            },
        );
        let disagree_depth = c.both_covered - c.depth_agree;
        m.insert(
            "agreement".into(),
            (c.coverage_agree - disagree_depth) as f64 / n,
        );
        m.insert("both_covered".into(), c.both_covered as f64);
        m.insert("covered".into(), covered(da));
        m.insert("reference_covered".into(), covered(db));
        m.insert("max_relative_error".into(), c.max_relative_error);
        Ok(Outputs::new().with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_coverage_and_depth_agreement() {
        let inf = f32::INFINITY;
        let a = [1.0, 2.0, inf, inf, 4.0, 0.0];
        let b = [1.0, 2.001, inf, 3.0, 4.0001, 0.0];
        let c = depth_agreement(&a, &b, 1e-4);
        assert_eq!(c.pixels, 6);
        assert_eq!(c.coverage_agree, 5);
        assert_eq!(c.both_covered, 4);
        // 2 vs 2.001 is 5e-4 apart; 4 vs 4.0001 is 2.5e-5.
        assert_eq!(c.depth_agree, 3);
        assert!((c.max_relative_error - 0.001 / 2.001).abs() < 1e-6);
        // Symmetric.
        let d = depth_agreement(&b, &a, 1e-4);
        assert_eq!((d.coverage_agree, d.both_covered, d.depth_agree), (5, 4, 3));
        // A looser tolerance accepts the 5e-4 pair.
        assert_eq!(depth_agreement(&a, &b, 1e-3).depth_agree, 4);
        // NaN counts as a miss.
        assert_eq!(depth_agreement(&[f32::NAN], &[inf], 0.0).coverage_agree, 1);
    }
}
