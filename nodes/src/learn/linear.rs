//! `learn.linear_regression`: least squares (optionally ridge) by Householder QR, batch
//! gradient descent or minibatch stochastic gradient descent.
//!
//! All three solvers minimise the same objective on the (optionally standardised) design
//! matrix Z = [1, x] with parameters θ = [b, w]:
//!
//! f(θ) = 1/(2n) ‖Zθ − y‖² + λ/2 ‖w‖²  (the bias is not penalised),
//!
//! so their results can be compared directly. Determinism: sums over samples run in fixed
//! chunks reduced in order ([`super::chunked_sum`]); SGD shuffles with a seeded SplitMix64 used
//! sequentially — bit-identical for any thread count.

use nalgebra::{DMatrix, DVector};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::{Design, chunked_sum, dot, loss_curve_value, matrix_value, norm, single_column};
use crate::analyze::track_error::input_matrix;
use crate::video::filters::SplitMix64;

/// A diagonal entry of R below this fraction of the largest one marks the design as rank
/// deficient (relative to f64 precision, with room for accumulated rounding).
const RANK_TOLERANCE: f64 = 1e-10;

param_enum! {
    /// Solver of `learn.linear_regression`.
    pub enum LinearSolver {
        /// Closed form: least squares by Householder QR of the design (ridge as extra rows).
        NormalEquation = "normal_equation",
        /// Full-batch gradient descent with a constant step.
        BatchGd = "batch_gd",
        /// Minibatch stochastic gradient descent, reshuffled every epoch.
        Sgd = "sgd",
    }
}

params! {
    /// Parameters of `learn.linear_regression`.
    pub struct LinearParams {
        /// Solver: normal_equation, batch_gd or sgd. Default normal_equation.
        solver: LinearSolver = LinearSolver::NormalEquation,
        /// Step size of batch_gd and sgd, in objective units⁻¹ (> 0). Default 0.1.
        learning_rate: f64 = 0.1 => [min = 0.0],
        /// Most gradient steps (batch_gd) or epochs (sgd), 1..=1000000. Default 500.
        iterations: u32 = 500 => [min = 1, max = 1000000],
        /// Samples per minibatch of sgd (≥ 1; capped at the sample count). Default 16.
        batch_size: u32 = 16 => [min = 1],
        /// Ridge strength λ ≥ 0 on the weights (not the bias), per the objective
        /// 1/(2n)‖Zθ − y‖² + λ/2‖w‖²; with `scale_features` it acts on standardised weights.
        /// Default 0.
        l2: f64 = 0.0 => [min = 0.0],
        /// Standardise every feature (zero mean, unit variance) before solving; the weights
        /// are reported in the original units either way. Default true.
        scale_features: bool = true,
        /// Seed of the SGD shuffles. Default 0.
        seed: u64 = 0,
        /// Stop batch_gd / sgd once the full gradient's norm falls below this (≥ 0; 0 never
        /// stops early). Default 1e-8.
        tolerance: f64 = 1e-8 => [min = 0.0],
    }
}

/// Settings of [`linear_regression`] (see [`LinearParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearConfig {
    /// Solver.
    pub solver: LinearSolver,
    /// Step size.
    pub learning_rate: f64,
    /// Most steps / epochs.
    pub iterations: usize,
    /// SGD minibatch size.
    pub batch_size: usize,
    /// Ridge λ.
    pub l2: f64,
    /// Standardise features.
    pub scale_features: bool,
    /// SGD seed.
    pub seed: u64,
    /// Gradient-norm stopping threshold.
    pub tolerance: f64,
}

impl Default for LinearConfig {
    fn default() -> Self {
        let p = LinearParams::default();
        LinearConfig {
            solver: p.solver,
            learning_rate: p.learning_rate,
            iterations: p.iterations as usize,
            batch_size: p.batch_size as usize,
            l2: p.l2,
            scale_features: p.scale_features,
            seed: p.seed,
            tolerance: p.tolerance,
        }
    }
}

/// The result of [`linear_regression`].
#[derive(Debug, Clone, PartialEq)]
pub struct LinearFit {
    /// `[bias, w_1..w_d]` in the original feature units.
    pub weights: Vec<f64>,
    /// Mean squared error of the predictions, target units².
    pub mse: f64,
    /// Coefficient of determination 1 − SSE/SST (1 for a perfect fit of a constant target,
    /// 0 for an imperfect one).
    pub r2: f64,
    /// Gradient steps / epochs run (1 for the normal equation).
    pub iterations: usize,
    /// Norm of the objective's gradient at the result (in the solved, possibly standardised,
    /// coordinates).
    pub gradient_norm: f64,
    /// Objective value before the first step and after every step / epoch.
    pub loss_curve: Vec<f64>,
}

/// f(θ) and ∇f(θ) of the ridge objective (see the module docs).
fn objective(design: &Design, y: &[f64], theta: &[f64], l2: f64) -> (f64, Vec<f64>) {
    let n = design.n as f64;
    let (sse, mut grad) = chunked_sum(design, |i, row, g| {
        let r = dot(row, theta) - y[i];
        for (gj, zj) in g.iter_mut().zip(row) {
            *gj += r * zj;
        }
        r * r
    });
    let mut loss = sse / (2.0 * n);
    for (j, gj) in grad.iter_mut().enumerate() {
        *gj /= n;
        if j > 0 {
            *gj += l2 * theta[j];
            loss += 0.5 * l2 * theta[j] * theta[j];
        }
    }
    (loss, grad)
}

/// Ridge least squares by Householder QR of [Z; √(nλ)·[0 I]] against [y; 0] (never forming
/// ZᵀZ, so the conditioning is that of Z, not its square). Errors when R has a diagonal entry
/// below [`RANK_TOLERANCE`] × the largest (collinear features, or fewer samples than
/// parameters without ridge).
fn solve_qr(design: &Design, y: &[f64], l2: f64) -> Result<Vec<f64>, String> {
    let (n, p) = (design.n, design.p);
    let extra = if l2 > 0.0 { p - 1 } else { 0 };
    let rows = n + extra;
    if rows < p {
        return Err(format!(
            "the normal equation needs at least {p} samples for {} features (got {n}); set `l2` > 0 or add samples",
            p - 1
        ));
    }
    let ridge = (n as f64 * l2).sqrt();
    let a = DMatrix::from_fn(rows, p, |i, j| {
        if i < n {
            design.z[i * p + j]
        } else if j == i - n + 1 {
            ridge
        } else {
            0.0
        }
    });
    let b = DVector::from_fn(rows, |i, _| if i < n { y[i] } else { 0.0 });
    let qr = a.qr();
    let r = qr.r();
    let largest = (0..p).map(|j| r[(j, j)].abs()).fold(0.0, f64::max);
    if let Some(j) = (0..p).find(|&j| {
        r[(j, j)].abs().partial_cmp(&(RANK_TOLERANCE * largest))
            != Some(std::cmp::Ordering::Greater)
    }) {
        let what = if j == 0 {
            "the bias".to_string()
        } else {
            format!("feature {}", j - 1)
        };
        return Err(format!(
            "`x` is rank deficient: {what} is (numerically) a linear combination of the columns before it; remove it or set `l2` > 0"
        ));
    }
    let qtb = qr.q().transpose() * b;
    let theta = r
        .solve_upper_triangular(&qtb)
        .ok_or("the triangular solve of the normal equation failed")?;
    Ok(theta.iter().copied().collect())
}

/// Fits `y ≈ b + x·w` (rows of `x` are samples, `y` one target per sample); see the module
/// docs for the objective and [`LinearSolver`] for the methods. Errors on mismatched sizes,
/// non-finite data, a rank-deficient normal equation or a diverging gradient descent.
pub fn linear_regression(
    x: &Matrix,
    y: &[f64],
    config: &LinearConfig,
) -> Result<LinearFit, String> {
    if y.len() != x.rows {
        return Err(format!(
            "`y` has {} rows but `x` has {} samples",
            y.len(),
            x.rows
        ));
    }
    if y.iter().any(|v| !v.is_finite()) {
        return Err("`y` holds a NaN or infinite entry".into());
    }
    let design = Design::new(x, config.scale_features, "x")?;
    let (n, p) = (design.n, design.p);
    let l2 = config.l2;
    let mut theta = vec![0.0; p];
    let mut curve = vec![objective(&design, y, &theta, l2).0];
    let mut iterations = 0;
    let diverged = || {
        format!(
            "gradient descent diverged (loss became non-finite) at learning_rate {}; lower it or set `scale_features`",
            config.learning_rate
        )
    };
    let lr = config.learning_rate;
    match config.solver {
        LinearSolver::NormalEquation => {
            theta = solve_qr(&design, y, l2)?;
            curve.push(objective(&design, y, &theta, l2).0);
            iterations = 1;
        }
        LinearSolver::BatchGd => {
            let (_, mut grad) = objective(&design, y, &theta, l2);
            while iterations < config.iterations && norm(&grad) >= config.tolerance {
                for (t, g) in theta.iter_mut().zip(&grad) {
                    *t -= lr * g;
                }
                let (loss, g) = objective(&design, y, &theta, l2);
                if !loss.is_finite() {
                    return Err(diverged());
                }
                grad = g;
                curve.push(loss);
                iterations += 1;
            }
        }
        LinearSolver::Sgd => {
            let batch = config.batch_size.clamp(1, n);
            let mut rng = SplitMix64::new(config.seed);
            let mut order: Vec<usize> = (0..n).collect();
            let mut g = vec![0.0; p];
            let (_, mut grad) = objective(&design, y, &theta, l2);
            while iterations < config.iterations && norm(&grad) >= config.tolerance {
                // Fisher–Yates with the seeded generator.
                for i in (1..n).rev() {
                    let j = ((rng.uniform() * (i + 1) as f64) as usize).min(i);
                    order.swap(i, j);
                }
                for idx in order.chunks(batch) {
                    g.iter_mut().for_each(|v| *v = 0.0);
                    for &i in idx {
                        let row = design.row(i);
                        let r = dot(row, &theta) - y[i];
                        for (gj, zj) in g.iter_mut().zip(row) {
                            *gj += r * zj;
                        }
                    }
                    let m = idx.len() as f64;
                    for (j, (t, gj)) in theta.iter_mut().zip(&g).enumerate() {
                        let reg = if j > 0 { l2 * *t } else { 0.0 };
                        *t -= lr * (gj / m + reg);
                    }
                }
                let (loss, gr) = objective(&design, y, &theta, l2);
                if !loss.is_finite() {
                    return Err(diverged());
                }
                grad = gr;
                curve.push(loss);
                iterations += 1;
            }
        }
    }
    let (_, grad) = objective(&design, y, &theta, l2);
    let weights = design.to_original(&theta);
    let (sse, sst) = {
        let mean = y.iter().sum::<f64>() / n as f64;
        let d = x.cols;
        let mut sse = 0.0;
        let mut sst = 0.0;
        for (xr, &yi) in x.data.chunks_exact(d).zip(y) {
            let pred = weights[0] + dot(&weights[1..], xr);
            sse += (pred - yi).powi(2);
            sst += (yi - mean).powi(2);
        }
        (sse, sst)
    };
    let r2 = if sst > 0.0 {
        1.0 - sse / sst
    } else if sse == 0.0 {
        1.0
    } else {
        0.0
    };
    Ok(LinearFit {
        weights,
        mse: sse / n as f64,
        r2,
        iterations,
        gradient_norm: norm(&grad),
        loss_curve: curve,
    })
}

/// Linear regression (`learn.linear_regression`). See [`linear_regression`].
#[derive(Debug, Clone, PartialEq)]
pub struct LinearRegression {
    config: LinearConfig,
}

impl Op for LinearRegression {
    type Params = LinearParams;
    const ID: &'static str = "learn.linear_regression";
    const SUMMARY: &'static str =
        "Fits y ≈ b + x·w by least squares (QR), batch gradient descent or SGD, optionally ridge.";
    const DOC: &'static str = r#"
Fits a linear model to samples `x` (n × d Matrix, one row per sample) and targets `y` (n × 1)
by minimising f(θ) = 1/(2n)‖Zθ − y‖² + λ/2‖w‖² with Z = [1, x] (standardised per feature
when `scale_features`) and θ = [b, w]; the bias is not penalised.

Solvers:
- `normal_equation`: least squares by Householder QR of [Z; √(nλ)·[0 I]] (Golub & Van Loan,
  "Matrix Computations", §5.3), which avoids squaring the condition number as a Cholesky of
  ZᵀZ + nλI would. A diagonal entry of R below 1e-10 × the largest is reported as a
  rank-deficient `x` (naming the feature) — set `l2` > 0 or drop the feature.
- `batch_gd`: θ ← θ − η∇f(θ) with the full gradient, at most `iterations` steps.
- `sgd`: minibatch SGD (Robbins & Monro 1951; Bottou 2010): every epoch reshuffles the samples
  (seeded) and steps once per `batch_size` samples; at most `iterations` epochs.
Gradient methods stop once ‖∇f‖ < `tolerance`; a non-finite loss is an error (step too large).

Outputs: `weights` ((d+1) × 1: bias first, then one weight per feature, in the original
units), `metrics` (`mse`, `r2`, `iterations`, `gradient_norm` = ‖∇f‖ at the result in the
solved coordinates, `loss` = final f), `loss_curve` (k × 2: iteration, f; row 0 is the start
θ = 0).

Deterministic for a given `seed` with any thread count (chunked sums reduced in order).

Example:
    "fit": (op: "learn.linear_regression", inputs: { "x": "data.x", "y": "data.y" },
            params: (solver: "sgd", learning_rate: 0.05, iterations: 50, batch_size: 8)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("x", PortType::Matrix, "n × d features, one row per sample."),
            PortSpec::new("y", PortType::Matrix, "n × 1 targets."),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "weights",
                PortType::Matrix,
                "(d+1) × 1: bias, then the weight of each feature (original units).",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "mse, r2, iterations, gradient_norm, loss.",
            ),
            PortSpec::new(
                "loss_curve",
                PortType::Matrix,
                "k × 2: iteration, objective value.",
            ),
        ]
    }

    fn new(p: LinearParams) -> Result<Self, String> {
        if !(p.learning_rate.is_finite() && p.learning_rate > 0.0) {
            return Err(format!(
                "`learning_rate` must be finite and > 0, got {}",
                p.learning_rate
            ));
        }
        if !p.l2.is_finite() || p.l2 < 0.0 {
            return Err(format!("`l2` must be finite and ≥ 0, got {}", p.l2));
        }
        if !p.tolerance.is_finite() || p.tolerance < 0.0 {
            return Err(format!(
                "`tolerance` must be finite and ≥ 0, got {}",
                p.tolerance
            ));
        }
        if p.iterations == 0 || p.batch_size == 0 {
            return Err("`iterations` and `batch_size` must be at least 1".into());
        }
        Ok(LinearRegression {
            config: LinearConfig {
                solver: p.solver,
                learning_rate: p.learning_rate,
                iterations: p.iterations as usize,
                batch_size: p.batch_size as usize,
                l2: p.l2,
                scale_features: p.scale_features,
                seed: p.seed,
                tolerance: p.tolerance,
            },
        })
    }
}

impl Operator for LinearRegression {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let x = input_matrix(inputs, "x")?;
        let y =
            single_column(input_matrix(inputs, "y")?, "y").map_err(|e| OpError::input("y", e))?;
        let fit = linear_regression(x, &y, &self.config).map_err(|e| OpError::input("x", e))?;
        let mut m = Metrics::new();
        m.insert("mse".into(), fit.mse);
        m.insert("r2".into(), fit.r2);
        m.insert("iterations".into(), fit.iterations as f64);
        m.insert("gradient_norm".into(), fit.gradient_norm);
        m.insert(
            "loss".into(),
            fit.loss_curve.last().copied().unwrap_or(f64::NAN),
        );
        Ok(Outputs::new()
            .with(
                "weights",
                matrix_value(fit.weights.len(), 1, fit.weights.clone())?,
            )
            .with("metrics", Value::metrics(m))
            .with("loss_curve", loss_curve_value(&fit.loss_curve)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::dataset::linear_data;

    fn config(solver: LinearSolver) -> LinearConfig {
        LinearConfig {
            solver,
            ..LinearConfig::default()
        }
    }

    #[test]
    fn normal_equation_recovers_noiseless_weights_exactly() {
        let truth = [3.0, -2.0, 0.5, 7.0];
        let (x, y) = linear_data(200, &truth[1..], truth[0], 0.0, 5.0, 1);
        for scale in [false, true] {
            let c = LinearConfig {
                scale_features: scale,
                ..config(LinearSolver::NormalEquation)
            };
            let fit = linear_regression(&x, &y, &c).unwrap();
            for (a, b) in fit.weights.iter().zip(truth) {
                assert!((a - b).abs() < 1e-9, "{:?}", fit.weights);
            }
            assert!(fit.mse < 1e-18 && (fit.r2 - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn gradient_methods_approach_the_least_squares_solution() {
        let truth = [1.0, 2.0, -3.0];
        let (x, y) = linear_data(400, &truth[1..], truth[0], 0.1, 1.0, 2);
        let exact = linear_regression(&x, &y, &config(LinearSolver::NormalEquation)).unwrap();
        let gd = linear_regression(
            &x,
            &y,
            &LinearConfig {
                iterations: 2000,
                ..config(LinearSolver::BatchGd)
            },
        )
        .unwrap();
        let sgd = linear_regression(
            &x,
            &y,
            &LinearConfig {
                learning_rate: 0.01,
                iterations: 100,
                ..config(LinearSolver::Sgd)
            },
        )
        .unwrap();
        for (a, b) in gd.weights.iter().zip(&exact.weights) {
            assert!(
                (a - b).abs() < 1e-6,
                "gd {:?} vs {:?}",
                gd.weights,
                exact.weights
            );
        }
        for (a, b) in sgd.weights.iter().zip(&exact.weights) {
            assert!(
                (a - b).abs() < 0.02,
                "sgd {:?} vs {:?}",
                sgd.weights,
                exact.weights
            );
        }
        // Known parameters recovered within the noise.
        for (a, b) in exact.weights.iter().zip(truth) {
            assert!((a - b).abs() < 0.05);
        }
        // Batch GD never increases the loss with a small enough step.
        assert!(gd.loss_curve.windows(2).all(|w| w[1] <= w[0] + 1e-15));
        assert!(gd.gradient_norm < 1e-6 && exact.gradient_norm < 1e-10);
    }

    #[test]
    fn ridge_shrinks_the_weight_norm_monotonically() {
        let (x, y) = linear_data(100, &[1.5, -2.0, 0.7], 4.0, 0.5, 1.0, 3);
        let mut last = f64::INFINITY;
        for l2 in [0.0, 0.01, 0.1, 1.0, 10.0, 100.0] {
            let fit = linear_regression(
                &x,
                &y,
                &LinearConfig {
                    l2,
                    ..config(LinearSolver::NormalEquation)
                },
            )
            .unwrap();
            let n = norm(&fit.weights[1..]);
            assert!(n < last, "λ = {l2}: ‖w‖ = {n} ≥ {last}");
            last = n;
            // The bias is not penalised: with standardised features it stays the mean of y.
            let mean = y.iter().sum::<f64>() / y.len() as f64;
            let xm: Vec<f64> = (0..3)
                .map(|j| (0..100).map(|i| x.data[i * 3 + j]).sum::<f64>() / 100.0)
                .collect();
            assert!((fit.weights[0] + dot(&fit.weights[1..], &xm) - mean).abs() < 1e-9);
        }
    }

    #[test]
    fn rank_deficiency_is_reported_and_ridge_fixes_it() {
        // Feature 1 = 2 × feature 0.
        let data: Vec<f64> = (0..20).flat_map(|i| [i as f64, 2.0 * i as f64]).collect();
        let x = Matrix::new(20, 2, data).unwrap();
        let y: Vec<f64> = (0..20).map(|i| i as f64).collect();
        let e = linear_regression(&x, &y, &config(LinearSolver::NormalEquation)).unwrap_err();
        assert!(
            e.contains("rank deficient") && e.contains("feature 1"),
            "{e}"
        );
        let c = LinearConfig {
            l2: 1e-3,
            ..config(LinearSolver::NormalEquation)
        };
        assert!(linear_regression(&x, &y, &c).is_ok());
    }

    #[test]
    fn divergence_and_bad_sizes_are_errors() {
        let (x, y) = linear_data(50, &[1e3], 0.0, 0.0, 100.0, 4);
        let c = LinearConfig {
            scale_features: false,
            learning_rate: 1.0,
            ..config(LinearSolver::BatchGd)
        };
        assert!(
            linear_regression(&x, &y, &c)
                .unwrap_err()
                .contains("diverged")
        );
        assert!(linear_regression(&x, &y[..10], &config(LinearSolver::BatchGd)).is_err());
    }

    #[test]
    fn sgd_is_deterministic_for_a_seed() {
        let (x, y) = linear_data(300, &[1.0, 1.0], 0.0, 0.2, 1.0, 5);
        let c = LinearConfig {
            iterations: 5,
            seed: 9,
            ..config(LinearSolver::Sgd)
        };
        let a = linear_regression(&x, &y, &c).unwrap();
        let b = linear_regression(&x, &y, &c).unwrap();
        assert_eq!(a, b);
        let other = linear_regression(&x, &y, &LinearConfig { seed: 10, ..c }).unwrap();
        assert_ne!(a.weights, other.weights);
    }
}
