//! `mesh.fit_primitive`: RANSAC fitting of a plane or a sphere to a point cloud.
//!
//! The estimators are [`PlaneEstimator`] and [`SphereEstimator`] of `geometry::shapes` and the
//! loop is the shared one of `geometry::ransac` ([`estimate`], LO-RANSAC by default), so this
//! file only converts clouds and splits inliers from outliers.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::pointcloud::{cloud_input, positions_f64, select};
use crate::geometry::ransac::{Method, RobustError, RobustOptions, estimate};
use crate::geometry::robust::Estimator;
use crate::geometry::shapes::{PlaneEstimator, SphereEstimator};

param_enum! {
    /// The shape `mesh.fit_primitive` fits.
    pub enum Primitive {
        /// `n·X + d = 0`, `‖n‖ = 1`.
        Plane = "plane",
        /// `‖X − c‖ = r`.
        Sphere = "sphere",
    }
}

/// A fitted primitive: its parameters, the inlier mask and the RANSAC trials.
#[derive(Debug, Clone, PartialEq)]
pub struct PrimitiveFit {
    /// Plane `[nx, ny, nz, d]` or sphere `[cx, cy, cz, r]`.
    pub model: [f64; 4],
    /// `true` for points within the threshold.
    pub inliers: Vec<bool>,
    /// Minimal samples drawn.
    pub trials: usize,
    /// RMS distance of the inliers to the primitive, scene units.
    pub inlier_rms: f64,
}

fn run_estimator<E>(
    estimator: &E,
    points: &[[f64; 3]],
    options: &RobustOptions,
    params: impl Fn(&E::Model) -> [f64; 4],
) -> Result<PrimitiveFit, RobustError>
where
    E: Estimator<Datum = [f64; 3]>,
{
    let report = estimate(estimator, points, options)?;
    let mut residuals = vec![0.0; points.len()];
    estimator.residuals(&report.model, points, &mut residuals);
    let sum: f64 = residuals
        .iter()
        .zip(&report.inlier_mask)
        .filter(|(_, k)| **k)
        .map(|(r, _)| *r)
        .sum();
    Ok(PrimitiveFit {
        model: params(&report.model),
        inlier_rms: (sum / report.num_inliers.max(1) as f64).sqrt(),
        inliers: report.inlier_mask,
        trials: report.trials,
    })
}

/// Fits `primitive` to `points` robustly with the shared RANSAC loop.
pub fn fit_primitive(
    points: &[[f64; 3]],
    primitive: Primitive,
    options: &RobustOptions,
) -> Result<PrimitiveFit, RobustError> {
    match primitive {
        Primitive::Plane => run_estimator(&PlaneEstimator, points, options, |m| {
            [m.normal[0], m.normal[1], m.normal[2], m.offset]
        }),
        Primitive::Sphere => run_estimator(&SphereEstimator, points, options, |m| {
            [m.center[0], m.center[1], m.center[2], m.radius]
        }),
    }
}

params! {
    /// Parameters of `mesh.fit_primitive`.
    pub struct FitPrimitiveParams {
        /// "plane" or "sphere". Default "plane".
        primitive: Primitive = Primitive::Plane,
        /// Inlier distance to the surface, scene units. Default 0.01.
        threshold: f64 = 0.01 => [min = 0.0, unit = "scene units"],
        /// Probability of drawing at least one all-inlier sample, in (0, 1). Default 0.999.
        confidence: f64 = 0.999 => [min = 0.0, max = 1.0],
        /// Most RANSAC trials. Default 10000.
        max_iterations: u32 = 10_000 => [min = 1, max = 10_000_000],
        /// Seed of the sampling stream. Default 0.
        seed: u64 = 0,
    }
}

/// Robust primitive fitting (`mesh.fit_primitive`). See [`fit_primitive`].
#[derive(Debug, Clone, PartialEq)]
pub struct FitPrimitive {
    primitive: Primitive,
    options: RobustOptions,
}

impl Op for FitPrimitive {
    type Params = FitPrimitiveParams;
    const ID: &'static str = "mesh.fit_primitive";
    const SUMMARY: &'static str =
        "Fits a plane or a sphere to a point cloud by RANSAC and splits inliers from outliers.";
    const DOC: &'static str = r#"
LO-RANSAC (Chum, Matas & Kittler 2003) over the shared estimator interface:
- "plane": three-point minimal samples, total-least-squares refit; model `[nx, ny, nz, d]` with
  n·X + d = 0, ‖n‖ = 1;
- "sphere": four-point circumsphere minimal samples, algebraic fit ‖X‖² + D·X + G = 0 refined by
  Levenberg–Marquardt on the geometric distances; model `[cx, cy, cz, r]`.

A point is an inlier when its distance to the surface is at most `threshold`. Trials adapt to
the inlier ratio w: log(1 − confidence) / log(1 − w^s), at most `max_iterations` (a sphere at
10 % inliers needs about 69,000 at 0.999). Sampling is seeded: the same cloud and seed give the
same result.

Outputs the model as a 1×4 Matrix, the inlier and outlier clouds (attributes kept) and Metrics
`inliers`, `outliers`, `inlier_ratio`, `trials`, `inlier_rms`.

Reference: Fischler & Bolles, "Random sample consensus", CACM 1981.

Example:
    "floor": (op: "mesh.fit_primitive", inputs: { "cloud": "scan.cloud" }, params: (primitive: "plane", threshold: 0.02)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("cloud", PortType::PointCloud, "The points.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "model",
                PortType::Matrix,
                "1×4: plane [nx, ny, nz, d] or sphere [cx, cy, cz, r].",
            ),
            PortSpec::new("inliers", PortType::PointCloud, "Points within threshold."),
            PortSpec::new("outliers", PortType::PointCloud, "The other points."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "inliers, outliers, inlier_ratio, trials, inlier_rms.",
            ),
        ]
    }

    fn new(p: FitPrimitiveParams) -> Result<Self, String> {
        if !(p.threshold.is_finite() && p.threshold > 0.0) {
            return Err(format!(
                "`threshold` must be finite and > 0, got {}",
                p.threshold
            ));
        }
        if !(p.confidence > 0.0 && p.confidence < 1.0) {
            return Err(format!(
                "`confidence` must be in (0, 1), got {}",
                p.confidence
            ));
        }
        Ok(FitPrimitive {
            primitive: p.primitive,
            options: RobustOptions {
                method: Method::LoRansac,
                threshold: p.threshold,
                confidence: p.confidence,
                max_trials: p.max_iterations as usize,
                seed: p.seed,
                ..RobustOptions::default()
            },
        })
    }
}

impl Operator for FitPrimitive {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        let points = positions_f64(cloud).map_err(|e| e.at("cloud"))?;
        let fit = fit_primitive(&points, self.primitive, &self.options).map_err(|e| match e {
            RobustError::TooFewData { .. } | RobustError::NonFinite { .. } => {
                OpError::input("cloud", e.to_string())
            }
            _ => OpError::failed(format!("no {} found: {e}", self.primitive.name())),
        })?;
        let n_in = fit.inliers.iter().filter(|k| **k).count();
        let outlier_mask: Vec<bool> = fit.inliers.iter().map(|k| !k).collect();
        let mut m = Metrics::new();
        m.insert("inliers".into(), n_in as f64);
        m.insert("outliers".into(), (points.len() - n_in) as f64);
        m.insert("inlier_ratio".into(), n_in as f64 / points.len() as f64);
        m.insert("trials".into(), fit.trials as f64);
        m.insert("inlier_rms".into(), fit.inlier_rms);
        let model =
            Matrix::new(1, 4, fit.model.to_vec()).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("model", Value::Matrix(Arc::new(model)))
            .with(
                "inliers",
                Value::PointCloud(Arc::new(select(cloud, &fit.inliers))),
            )
            .with(
                "outliers",
                Value::PointCloud(Arc::new(select(cloud, &outlier_mask))),
            )
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::pointcloud::tests::{cloud_of, sphere};
    use ocellus_engine::value::PointCloud;

    /// `inliers` surface points followed by uniform outliers in a 20³ box around `center`.
    fn with_outliers(
        surface: Vec<[f64; 3]>,
        outliers: usize,
        center: [f64; 3],
        seed: u64,
    ) -> Vec<[f64; 3]> {
        let mut rng = SplitMix64::new(seed);
        let mut pts = surface;
        for _ in 0..outliers {
            pts.push([0, 1, 2].map(|a| center[a] + 20.0 * rng.uniform() - 10.0));
        }
        pts
    }

    #[test]
    fn plane_with_50_and_90_percent_outliers() {
        for (offset, outlier_share) in [(0.0, 0.5), (0.0, 0.9), (1e6, 0.9)] {
            // Plane 2x − y + 2z = 3 + …: normal (2, −1, 2)/3 through `o`.
            let o = [offset, -offset, 0.5 * offset];
            let n = [2.0 / 3.0, -1.0 / 3.0, 2.0 / 3.0];
            // Two in-plane directions: u ⟂ n and v = n × u.
            let u = [1.0 / 2f64.sqrt(), 0.0, -1.0 / 2f64.sqrt()];
            let v = [
                n[1] * u[2] - n[2] * u[1],
                n[2] * u[0] - n[0] * u[2],
                n[0] * u[1] - n[1] * u[0],
            ];
            let mut rng = SplitMix64::new(9);
            let inliers = 300;
            let surface: Vec<[f64; 3]> = (0..inliers)
                .map(|_| {
                    let (a, b) = (8.0 * rng.uniform() - 4.0, 8.0 * rng.uniform() - 4.0);
                    let e = 0.001 * rng.normal();
                    [0, 1, 2].map(|k| o[k] + a * u[k] + b * v[k] + e * n[k])
                })
                .collect();
            let outliers =
                (inliers as f64 * outlier_share / (1.0 - outlier_share)).round() as usize;
            let pts = with_outliers(surface, outliers, o, 10);
            let options = RobustOptions {
                threshold: 0.01,
                max_trials: 20_000,
                ..RobustOptions::default()
            };
            let fit = fit_primitive(&pts, Primitive::Plane, &options).unwrap();
            let m = fit.model;
            let s = m[0].signum();
            for k in 0..3 {
                assert!(
                    (s * m[k] - n[k]).abs() < 1e-3,
                    "{offset} {outlier_share}: {m:?}"
                );
            }
            // The plane passes through `o` (the offset alone would amplify the normal's error).
            let at_o = m[0] * o[0] + m[1] * o[1] + m[2] * o[2] + m[3];
            assert!(at_o.abs() < 5e-3, "{m:?} {at_o}");
            assert!(fit.inliers[..inliers].iter().filter(|k| **k).count() >= 295);
        }
    }

    #[test]
    fn sphere_with_50_and_80_percent_outliers_through_the_op() {
        for (center, outlier_share) in [([1.0, 2.0, 3.0], 0.5f64), ([1e6, 1e6, 1e6], 0.8)] {
            let mut rng = SplitMix64::new(12);
            let surface: Vec<[f64; 3]> = sphere(400, center, 2.5, 13)
                .iter()
                .map(|p| p.map(|v| v + 0.002 * rng.normal()))
                .collect();
            let outliers = (400.0 * outlier_share / (1.0 - outlier_share)).round() as usize;
            let pts = with_outliers(surface, outliers, center, 14);
            let options = RobustOptions {
                threshold: 0.01,
                max_trials: 50_000,
                seed: 3,
                ..RobustOptions::default()
            };
            // f32 clouds lose precision a million units out: test the function in f64 there.
            let fit = fit_primitive(&pts, Primitive::Sphere, &options).unwrap();
            for (got, want) in fit.model.iter().zip(&center) {
                assert!((got - want).abs() < 2e-3, "{:?}", fit.model);
            }
            assert!((fit.model[3] - 2.5).abs() < 2e-3);
            assert!(fit.inliers[..400].iter().filter(|k| **k).count() >= 390);
            if center[0] < 10.0 {
                let op = FitPrimitive::new(FitPrimitiveParams {
                    primitive: Primitive::Sphere,
                    threshold: 0.01,
                    seed: 3,
                    max_iterations: 50_000,
                    ..FitPrimitiveParams::default()
                })
                .unwrap();
                let specs = FitPrimitive::inputs();
                let values = [Some(Value::PointCloud(Arc::new(cloud_of(&pts))))];
                let ctx = RunContext {
                    node: "fit".into(),
                    threads: 1,
                    element: None,
                };
                let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
                let Some(Value::PointCloud(inl)) = out.take("inliers") else {
                    panic!("no inliers")
                };
                let Some(Value::PointCloud(outl)) = out.take("outliers") else {
                    panic!("no outliers")
                };
                assert_eq!(inl.positions.len() + outl.positions.len(), pts.len());
                assert!(inl.positions.len() >= 390);
            }
        }
        // Empty cloud: a clear error.
        let op = FitPrimitive::new(FitPrimitiveParams::default()).unwrap();
        let specs = FitPrimitive::inputs();
        let values = [Some(Value::PointCloud(Arc::new(PointCloud::default())))];
        let ctx = RunContext {
            node: "fit".into(),
            threads: 1,
            element: None,
        };
        let err = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("at least 3"), "{err}");
    }
}
