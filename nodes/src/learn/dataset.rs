//! `learn.dataset`: seeded synthetic data sets with known parameters — a noisy linear model
//! (regression) or Gaussian blobs (classification).
//!
//! Everything is drawn sequentially from one SplitMix64 stream, so a seed gives the same data
//! on every machine and thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::Matrix;
use ocellus_engine::{param_enum, params};

use super::matrix_value;
use crate::video::filters::SplitMix64;

/// Most samples.
pub const MAX_SAMPLES: u32 = 1 << 22;

/// Most classes of the blobs.
pub const MAX_CLASSES: u32 = 16;

param_enum! {
    /// What `learn.dataset` generates.
    pub enum DatasetKind {
        /// y = b + x·w + noise.
        Linear = "linear",
        /// One isotropic Gaussian blob per class.
        Blobs = "blobs",
    }
}

params! {
    /// Parameters of `learn.dataset`.
    pub struct DatasetParams {
        /// linear or blobs. Default linear.
        kind: DatasetKind = DatasetKind::Linear,
        /// Number of samples, 1..=4194304. Default 200.
        samples: u32 = 200 => [min = 1, max = 4194304],
        /// linear: the true weights, one per feature (at least one). Default (2, −1).
        weights: Vec<f64> = vec![2.0, -1.0],
        /// linear: the true bias. Default 0.5.
        bias: f64 = 0.5,
        /// linear: standard deviation of the Gaussian target noise, target units (≥ 0).
        /// Default 0.1.
        noise_sigma: f64 = 0.1 => [min = 0.0],
        /// Standard deviation of the features: linear — of every feature (zero mean);
        /// blobs — of every blob around its mean (> 0). Default 1.
        feature_sigma: f64 = 1.0 => [min = 0.0],
        /// blobs: number of classes, 2..=16. Default 2.
        classes: u32 = 2 => [min = 2, max = 16],
        /// blobs: number of features (≥ 2). Default 2.
        features: u32 = 2 => [min = 2, max = 1024],
        /// blobs: radius of the circle (in the first two features) the class means lie on,
        /// evenly spaced, feature units. Default 3.
        separation: f64 = 3.0 => [min = 0.0],
        /// Random seed. Default 0.
        seed: u64 = 0,
    }
}

/// `n` samples of `y = bias + x·weights + N(0, noise_sigma²)` with features
/// `x_j ~ N(0, feature_sigma²)`: `(x (n × d), y)`.
pub fn linear_data(
    n: usize,
    weights: &[f64],
    bias: f64,
    noise_sigma: f64,
    feature_sigma: f64,
    seed: u64,
) -> (Matrix, Vec<f64>) {
    let d = weights.len();
    let mut rng = SplitMix64::new(seed);
    let mut x = Vec::with_capacity(n * d);
    let mut y = Vec::with_capacity(n);
    for _ in 0..n {
        let mut t = bias;
        for w in weights {
            let v = rng.normal(0.0, feature_sigma);
            x.push(v);
            t += w * v;
        }
        y.push(t + rng.normal(0.0, noise_sigma));
    }
    (
        Matrix {
            rows: n,
            cols: d,
            data: x,
        },
        y,
    )
}

/// `n` samples of `classes` isotropic Gaussian blobs in `features` dimensions (σ =
/// `sigma`); class c's mean lies at angle 2πc/classes on a circle of radius `separation` in
/// the first two features (zero in the others). Sample i belongs to class i mod classes.
/// Returns `(x (n × features), labels, means (classes × features))`.
pub fn blobs(
    n: usize,
    classes: usize,
    features: usize,
    separation: f64,
    sigma: f64,
    seed: u64,
) -> (Matrix, Vec<f64>, Matrix) {
    let mut means = vec![0.0; classes * features];
    for c in 0..classes {
        let a = std::f64::consts::TAU * c as f64 / classes as f64;
        means[c * features] = separation * a.cos();
        means[c * features + 1] = separation * a.sin();
    }
    let mut rng = SplitMix64::new(seed);
    let mut x = Vec::with_capacity(n * features);
    let mut y = Vec::with_capacity(n);
    for i in 0..n {
        let c = i % classes;
        for j in 0..features {
            x.push(rng.normal(means[c * features + j], sigma));
        }
        y.push(c as f64);
    }
    (
        Matrix {
            rows: n,
            cols: features,
            data: x,
        },
        y,
        Matrix {
            rows: classes,
            cols: features,
            data: means,
        },
    )
}

/// Synthetic learning data (`learn.dataset`). See [`linear_data`] and [`blobs`].
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset(DatasetParams);

impl Op for Dataset {
    type Params = DatasetParams;
    const ID: &'static str = "learn.dataset";
    const SUMMARY: &'static str =
        "Generates seeded data with known parameters: a noisy linear model or Gaussian blobs.";
    const DOC: &'static str = r#"
Generates a data set whose true parameters are known, for testing regression and
classification.

- `linear`: x_ij ~ N(0, feature_sigma²) for every feature j of `weights`, y_i = bias + x_i·w +
  N(0, noise_sigma²). `truth` is the (d+1) × 1 column [bias, w_1..w_d] — the layout
  `learn.linear_regression` outputs its weights in.
- `blobs`: `classes` isotropic Gaussian clusters (σ = feature_sigma) in `features` dimensions
  with means evenly spaced on a circle of radius `separation` in the first two features
  (as scikit-learn's `make_blobs` with fixed centres); sample i has label i mod classes.
  `truth` is the classes × features matrix of means.

Outputs `x` (n × d), `y` (n × 1: targets or integer labels) and `truth`. Drawn sequentially
from a SplitMix64 stream seeded by `seed` (Box–Muller normals): identical on every run.

Example:
    "data": (op: "learn.dataset", params: (kind: "blobs", samples: 300, classes: 3, seed: 2)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("x", PortType::Matrix, "n × d features."),
            PortSpec::new(
                "y",
                PortType::Matrix,
                "n × 1 targets (linear) or class labels 0..classes−1 (blobs).",
            ),
            PortSpec::new(
                "truth",
                PortType::Matrix,
                "linear: (d+1) × 1 [bias, weights]; blobs: classes × features means.",
            ),
        ]
    }

    fn new(p: DatasetParams) -> Result<Self, String> {
        if p.samples == 0 || p.samples > MAX_SAMPLES {
            return Err(format!(
                "`samples` must be between 1 and {MAX_SAMPLES}, got {}",
                p.samples
            ));
        }
        let finite = |name: &str, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(format!("`{name}` must be finite, got {v}"))
            }
        };
        finite("bias", p.bias)?;
        finite("separation", p.separation)?;
        if !(p.noise_sigma.is_finite() && p.noise_sigma >= 0.0) {
            return Err(format!("`noise_sigma` must be ≥ 0, got {}", p.noise_sigma));
        }
        if !(p.feature_sigma.is_finite() && p.feature_sigma > 0.0) {
            return Err(format!(
                "`feature_sigma` must be > 0, got {}",
                p.feature_sigma
            ));
        }
        if p.kind == DatasetKind::Linear {
            if p.weights.is_empty() {
                return Err("`weights` needs at least one weight".into());
            }
            if let Some(w) = p.weights.iter().find(|w| !w.is_finite()) {
                return Err(format!("`weights` must be finite, got {w}"));
            }
        }
        if !(2..=MAX_CLASSES).contains(&p.classes) {
            return Err(format!(
                "`classes` must be between 2 and {MAX_CLASSES}, got {}",
                p.classes
            ));
        }
        if p.features < 2 {
            return Err(format!("`features` must be at least 2, got {}", p.features));
        }
        Ok(Dataset(p))
    }
}

impl Operator for Dataset {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let p = &self.0;
        let n = p.samples as usize;
        let (x, y, truth) = match p.kind {
            DatasetKind::Linear => {
                let (x, y) = linear_data(
                    n,
                    &p.weights,
                    p.bias,
                    p.noise_sigma,
                    p.feature_sigma,
                    p.seed,
                );
                let mut t = vec![p.bias];
                t.extend_from_slice(&p.weights);
                let rows = t.len();
                (
                    x,
                    y,
                    Matrix {
                        rows,
                        cols: 1,
                        data: t,
                    },
                )
            }
            DatasetKind::Blobs => blobs(
                n,
                p.classes as usize,
                p.features as usize,
                p.separation,
                p.feature_sigma,
                p.seed,
            ),
        };
        Ok(Outputs::new()
            .with("x", matrix_value(x.rows, x.cols, x.data)?)
            .with("y", matrix_value(n, 1, y)?)
            .with("truth", matrix_value(truth.rows, truth.cols, truth.data)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_data_follows_the_model() {
        let (x, y) = linear_data(1000, &[2.0, -1.0], 0.5, 0.0, 1.0, 1);
        for (i, &yi) in y.iter().enumerate() {
            let t = 0.5 + 2.0 * x.data[2 * i] - x.data[2 * i + 1];
            assert!((yi - t).abs() < 1e-12);
        }
        let var = x.data.iter().map(|v| v * v).sum::<f64>() / 2000.0;
        assert!((var - 1.0).abs() < 0.1, "{var}");
    }

    #[test]
    fn blobs_centre_on_their_means() {
        let (x, y, means) = blobs(3000, 3, 2, 4.0, 0.5, 2);
        for c in 0..3 {
            let idx: Vec<usize> = (0..3000).filter(|&i| y[i] == c as f64).collect();
            assert_eq!(idx.len(), 1000);
            for j in 0..2 {
                let m = idx.iter().map(|&i| x.data[2 * i + j]).sum::<f64>() / 1000.0;
                assert!((m - means.data[2 * c + j]).abs() < 0.05);
            }
            let r = means.data[2 * c].hypot(means.data[2 * c + 1]);
            assert!((r - 4.0).abs() < 1e-12);
        }
    }

    #[test]
    fn bad_params_are_rejected() {
        let p = DatasetParams {
            weights: vec![],
            ..DatasetParams::default()
        };
        assert!(Dataset::new(p).unwrap_err().contains("weights"));
        let p = DatasetParams {
            feature_sigma: 0.0,
            ..DatasetParams::default()
        };
        assert!(Dataset::new(p).is_err());
    }
}
