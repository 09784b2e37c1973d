//! `learn.logistic_regression`: L2-regularised logistic regression, binary or one-vs-all,
//! by gradient descent, Newton's method (IRLS) or L-BFGS.
//!
//! Every binary model minimises, on the design Z = [1, x] (standardised when asked),
//!
//! f(θ) = 1/n Σᵢ [softplus(zᵢ) − yᵢ zᵢ] + λ/2 ‖w‖²,  zᵢ = Zᵢθ,  softplus(z) = ln(1 + eᶻ),
//!
//! which is the mean log-loss plus ridge on the weights (not the bias). softplus and the
//! sigmoid are evaluated in forms that never overflow (`max(z, 0) + ln1p(e^{−|z|})`), so huge
//! scores give exact, finite losses. Determinism: chunked sums reduced in order; models of the
//! classes are fitted independently and collected in class order.

use nalgebra::{DMatrix, DVector};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::lbfgs::{LbfgsConfig, lbfgs};
use super::{CHUNK, Design, chunked_sum, dot, loss_curve_value, matrix_value, norm, single_column};
use crate::analyze::evaluate::roc_curve;
use crate::analyze::track_error::input_matrix;

/// Most classes.
pub const MAX_CLASSES: usize = 256;

/// Correction pairs of the L-BFGS solver.
pub const LBFGS_MEMORY: usize = 10;

/// Armijo constant of Newton's backtracking line search.
const NEWTON_C1: f64 = 1e-4;

/// Smallest probability in the log-loss (−ln of it ≈ 34.5), as scikit-learn clips.
const MIN_PROBABILITY: f64 = 1e-15;

param_enum! {
    /// Solver of `learn.logistic_regression`.
    pub enum LogisticSolver {
        /// Gradient descent with a constant step.
        Gd = "gd",
        /// Newton's method (iteratively reweighted least squares) with Armijo backtracking.
        Newton = "newton",
        /// L-BFGS, memory 10, Armijo backtracking.
        Lbfgs = "lbfgs",
    }
}

params! {
    /// Parameters of `learn.logistic_regression`.
    pub struct LogisticParams {
        /// Solver: gd, newton or lbfgs. Default lbfgs.
        solver: LogisticSolver = LogisticSolver::Lbfgs,
        /// Step size of gd (> 0). Default 1.
        learning_rate: f64 = 1.0 => [min = 0.0],
        /// Most iterations per binary model, 1..=1000000. Default 200.
        max_iterations: u32 = 200 => [min = 1, max = 1000000],
        /// Ridge strength λ ≥ 0 on the weights (not the bias), per the objective
        /// mean log-loss + λ/2‖w‖² (on standardised weights with `scale_features`). Default 1e-3.
        l2: f64 = 1e-3 => [min = 0.0],
        /// Standardise every feature before fitting; weights are reported in the original
        /// units either way. Default true.
        scale_features: bool = true,
        /// Stop once the gradient norm falls below this (≥ 0). Default 1e-8.
        tolerance: f64 = 1e-8 => [min = 0.0],
        /// Thresholds of the ROC curve, 2..=65536. Default 101.
        roc_steps: u32 = 101 => [min = 2, max = 65536],
    }
}

/// Settings of [`logistic_regression`] (see [`LogisticParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogisticConfig {
    /// Solver.
    pub solver: LogisticSolver,
    /// GD step.
    pub learning_rate: f64,
    /// Most iterations per model.
    pub max_iterations: usize,
    /// Ridge λ.
    pub l2: f64,
    /// Standardise features.
    pub scale_features: bool,
    /// Gradient-norm stop.
    pub tolerance: f64,
}

impl Default for LogisticConfig {
    fn default() -> Self {
        let p = LogisticParams::default();
        LogisticConfig {
            solver: p.solver,
            learning_rate: p.learning_rate,
            max_iterations: p.max_iterations as usize,
            l2: p.l2,
            scale_features: p.scale_features,
            tolerance: p.tolerance,
        }
    }
}

/// σ(z) = 1 / (1 + e^{−z}) without overflow for any finite z.
#[inline]
pub fn sigmoid(z: f64) -> f64 {
    if z >= 0.0 {
        1.0 / (1.0 + (-z).exp())
    } else {
        let e = z.exp();
        e / (1.0 + e)
    }
}

/// ln(1 + eᶻ) without overflow: max(z, 0) + ln1p(e^{−|z|}).
#[inline]
pub fn softplus(z: f64) -> f64 {
    z.max(0.0) + (-z.abs()).exp().ln_1p()
}

/// One binary model: θ on the design's coordinates and its fitting report.
#[derive(Debug, Clone, PartialEq)]
pub struct BinaryFit {
    /// Parameters on the (possibly standardised) design, bias first.
    pub theta: Vec<f64>,
    /// Iterations run.
    pub iterations: usize,
    /// ‖∇f‖ at θ.
    pub gradient_norm: f64,
    /// f before the first iteration and after every one.
    pub curve: Vec<f64>,
}

/// f(θ), ∇f(θ) of the binary objective (module docs) for targets `y` ∈ {0, 1}.
pub fn binary_objective(design: &Design, y: &[f64], theta: &[f64], l2: f64) -> (f64, Vec<f64>) {
    let n = design.n as f64;
    let (sum, mut grad) = chunked_sum(design, |i, row, g| {
        let z = dot(row, theta);
        let r = sigmoid(z) - y[i];
        for (gj, zj) in g.iter_mut().zip(row) {
            *gj += r * zj;
        }
        softplus(z) - y[i] * z
    });
    let mut loss = sum / n;
    for (j, gj) in grad.iter_mut().enumerate() {
        *gj /= n;
        if j > 0 {
            *gj += l2 * theta[j];
            loss += 0.5 * l2 * theta[j] * theta[j];
        }
    }
    (loss, grad)
}

/// ∇²f(θ) = 1/n Zᵀ diag(σ(1−σ)) Z + λ·diag(0, 1, …, 1), summed in chunks in order.
fn hessian(design: &Design, theta: &[f64], l2: f64) -> DMatrix<f64> {
    let p = design.p;
    let parts: Vec<Vec<f64>> = design
        .z
        .par_chunks(CHUNK * p)
        .map(|rows| {
            let mut h = vec![0.0; p * p];
            for row in rows.chunks_exact(p) {
                let s = sigmoid(dot(row, theta));
                let wgt = s * (1.0 - s);
                for a in 0..p {
                    let wa = wgt * row[a];
                    if wa == 0.0 {
                        continue;
                    }
                    let ha = &mut h[a * p..a * p + a + 1];
                    for (hb, zb) in ha.iter_mut().zip(row) {
                        *hb += wa * zb;
                    }
                }
            }
            h
        })
        .collect();
    let mut h = vec![0.0; p * p];
    for part in parts {
        h.iter_mut().zip(part).for_each(|(a, b)| *a += b);
    }
    let n = design.n as f64;
    DMatrix::from_fn(p, p, |a, b| {
        let v = if b <= a { h[a * p + b] } else { h[b * p + a] } / n;
        if a == b && a > 0 { v + l2 } else { v }
    })
}

/// Fits one binary model (targets 0/1) with the configured solver.
pub fn fit_binary(
    design: &Design,
    y: &[f64],
    config: &LogisticConfig,
) -> Result<BinaryFit, String> {
    let p = design.p;
    let l2 = config.l2;
    let objective = |t: &[f64]| binary_objective(design, y, t, l2);
    match config.solver {
        LogisticSolver::Lbfgs => {
            let m = lbfgs(
                objective,
                vec![0.0; p],
                &LbfgsConfig {
                    memory: LBFGS_MEMORY,
                    max_iterations: config.max_iterations,
                    tolerance: config.tolerance,
                },
            )?;
            Ok(BinaryFit {
                theta: m.x,
                iterations: m.iterations,
                gradient_norm: m.gradient_norm,
                curve: m.curve,
            })
        }
        LogisticSolver::Gd => {
            let mut theta = vec![0.0; p];
            let (f0, mut g) = objective(&theta);
            let mut curve = vec![f0];
            let mut iterations = 0;
            while iterations < config.max_iterations && norm(&g) >= config.tolerance {
                for (t, gj) in theta.iter_mut().zip(&g) {
                    *t -= config.learning_rate * gj;
                }
                let (f, gn) = objective(&theta);
                if !f.is_finite() {
                    return Err(format!(
                        "gradient descent diverged at learning_rate {}",
                        config.learning_rate
                    ));
                }
                g = gn;
                curve.push(f);
                iterations += 1;
            }
            Ok(BinaryFit {
                gradient_norm: norm(&g),
                theta,
                iterations,
                curve,
            })
        }
        LogisticSolver::Newton => {
            let mut theta = vec![0.0; p];
            let (mut fx, mut g) = objective(&theta);
            let mut curve = vec![fx];
            let mut iterations = 0;
            while iterations < config.max_iterations && norm(&g) >= config.tolerance {
                let h = hessian(design, &theta, l2);
                let rhs = DVector::from_column_slice(&g);
                // Without ridge the Hessian can be singular (separable data, constant
                // features): add Levenberg damping until the Cholesky factorisation exists.
                let scale = (0..p).map(|i| h[(i, i)]).fold(0.0, f64::max).max(1e-300);
                let mut damping = 0.0;
                let step = loop {
                    let mut hd = h.clone();
                    for i in 0..p {
                        hd[(i, i)] += damping;
                    }
                    if let Some(c) = hd.cholesky() {
                        break c.solve(&rhs);
                    }
                    damping = if damping == 0.0 {
                        1e-12 * scale
                    } else {
                        damping * 10.0
                    };
                    if damping > 1e12 * scale {
                        return Err("Newton: the Hessian could not be factorised".into());
                    }
                };
                let dir: Vec<f64> = step.iter().map(|v| -v).collect();
                let slope = dot(&g, &dir);
                let mut alpha = 1.0;
                let mut accepted = None;
                for _ in 0..50 {
                    let tn: Vec<f64> = theta.iter().zip(&dir).map(|(t, d)| t + alpha * d).collect();
                    let (fnew, gnew) = objective(&tn);
                    if fnew <= fx + NEWTON_C1 * alpha * slope {
                        accepted = Some((tn, fnew, gnew));
                        break;
                    }
                    alpha *= 0.5;
                }
                let Some((tn, fnew, gnew)) = accepted else {
                    break;
                };
                theta = tn;
                fx = fnew;
                g = gnew;
                curve.push(fx);
                iterations += 1;
            }
            Ok(BinaryFit {
                gradient_norm: norm(&g),
                theta,
                iterations,
                curve,
            })
        }
    }
}

/// The result of [`logistic_regression`].
#[derive(Debug, Clone, PartialEq)]
pub struct LogisticFit {
    /// Number of classes K.
    pub classes: usize,
    /// One `[bias, w_1..w_d]` per binary model (original units): one model (class 1 vs 0)
    /// for K = 2, K one-vs-all models otherwise.
    pub weights: Vec<Vec<f64>>,
    /// n × K class probabilities, row-major (rows sum to 1).
    pub probabilities: Vec<f64>,
    /// Predicted class of every sample (largest probability, lowest class on ties).
    pub predicted: Vec<usize>,
    /// Most iterations of any model.
    pub iterations: usize,
    /// Largest final gradient norm of any model.
    pub gradient_norm: f64,
    /// Mean over the models of their objective per iteration (a finished model keeps its
    /// final value).
    pub curve: Vec<f64>,
}

/// Class labels as indices: finite non-negative integers below [`MAX_CLASSES`], at least two
/// classes, every class 0..K−1 present. Returns `(labels, K)`.
pub fn class_labels(y: &[f64]) -> Result<(Vec<usize>, usize), String> {
    let mut out = Vec::with_capacity(y.len());
    for &v in y {
        if !(v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v < MAX_CLASSES as f64) {
            return Err(format!(
                "`y` labels must be integers 0..{}, got {v}",
                MAX_CLASSES - 1
            ));
        }
        out.push(v as usize);
    }
    let k = out.iter().max().map_or(0, |m| m + 1);
    if k < 2 {
        return Err("`y` needs at least two classes (labels 0 and 1)".into());
    }
    let mut counts = vec![0usize; k];
    out.iter().for_each(|&c| counts[c] += 1);
    if let Some(c) = counts.iter().position(|&c| c == 0) {
        return Err(format!(
            "`y` has no sample of class {c} (labels must be 0..{})",
            k - 1
        ));
    }
    Ok((out, k))
}

/// Fits logistic regression to samples `x` with integer labels `y`: one model for two
/// classes, one-vs-all for more (probabilities of the K models normalised to sum to 1, as
/// scikit-learn's one-vs-rest). Errors on bad labels, sizes or non-finite data.
pub fn logistic_regression(
    x: &Matrix,
    y: &[f64],
    config: &LogisticConfig,
) -> Result<LogisticFit, String> {
    if y.len() != x.rows {
        return Err(format!(
            "`y` has {} rows but `x` has {} samples",
            y.len(),
            x.rows
        ));
    }
    let (labels, k) = class_labels(y)?;
    let design = Design::new(x, config.scale_features, "x")?;
    let n = design.n;
    let positives: Vec<usize> = if k == 2 { vec![1] } else { (0..k).collect() };
    let fits: Vec<BinaryFit> = positives
        .par_iter()
        .map(|&c| {
            let t: Vec<f64> = labels
                .iter()
                .map(|&l| f64::from(u8::from(l == c)))
                .collect();
            fit_binary(&design, &t, config)
        })
        .collect::<Result<_, _>>()?;
    let mut probabilities = vec![0.0; n * k];
    for (i, row) in probabilities.chunks_exact_mut(k).enumerate() {
        let z = design.row(i);
        if k == 2 {
            let p1 = sigmoid(dot(z, &fits[0].theta));
            row[0] = 1.0 - p1;
            row[1] = p1;
        } else {
            for (r, f) in row.iter_mut().zip(&fits) {
                *r = sigmoid(dot(z, &f.theta));
            }
            let s: f64 = row.iter().sum();
            if s > 0.0 {
                row.iter_mut().for_each(|v| *v /= s);
            } else {
                row.iter_mut().for_each(|v| *v = 1.0 / k as f64);
            }
        }
    }
    let predicted = probabilities
        .chunks_exact(k)
        .map(|row| (0..k).fold(0, |best, c| if row[c] > row[best] { c } else { best }))
        .collect();
    let longest = fits.iter().map(|f| f.curve.len()).max().unwrap_or(1);
    let curve = (0..longest)
        .map(|it| {
            fits.iter()
                .map(|f| f.curve[it.min(f.curve.len() - 1)])
                .sum::<f64>()
                / fits.len() as f64
        })
        .collect();
    Ok(LogisticFit {
        classes: k,
        weights: fits.iter().map(|f| design.to_original(&f.theta)).collect(),
        probabilities,
        predicted,
        iterations: fits.iter().map(|f| f.iterations).max().unwrap_or(0),
        gradient_norm: fits.iter().map(|f| f.gradient_norm).fold(0.0, f64::max),
        curve,
    })
}

/// Accuracy, mean log-loss (probabilities clipped at 1e-15) and per-class precision and
/// recall (`precision_c` left out when class c is never predicted).
pub fn classification_metrics(fit: &LogisticFit, labels: &[usize]) -> Metrics {
    let k = fit.classes;
    let n = labels.len();
    let mut m = Metrics::new();
    let correct = fit
        .predicted
        .iter()
        .zip(labels)
        .filter(|(a, b)| a == b)
        .count();
    m.insert("accuracy".into(), correct as f64 / n as f64);
    let log_loss = labels
        .iter()
        .enumerate()
        .map(|(i, &l)| -fit.probabilities[i * k + l].max(MIN_PROBABILITY).ln())
        .sum::<f64>()
        / n as f64;
    m.insert("log_loss".into(), log_loss);
    for c in 0..k {
        let tp = (0..n)
            .filter(|&i| fit.predicted[i] == c && labels[i] == c)
            .count() as f64;
        let predicted = fit.predicted.iter().filter(|&&p| p == c).count() as f64;
        let actual = labels.iter().filter(|&&l| l == c).count() as f64;
        if predicted > 0.0 {
            m.insert(format!("precision_{c}"), tp / predicted);
        }
        m.insert(format!("recall_{c}"), tp / actual);
    }
    m
}

/// Logistic regression (`learn.logistic_regression`). See [`logistic_regression`].
#[derive(Debug, Clone, PartialEq)]
pub struct LogisticRegression {
    config: LogisticConfig,
    roc_steps: usize,
}

impl Op for LogisticRegression {
    type Params = LogisticParams;
    const ID: &'static str = "learn.logistic_regression";
    const SUMMARY: &'static str =
        "L2-regularised logistic regression (binary or one-vs-all) by GD, Newton or L-BFGS.";
    const DOC: &'static str = r#"
Fits P(class | x) to samples `x` (n × d) with integer labels `y` (n × 1, 0..K−1, every class
present). K = 2: one model P(1 | x) = σ(b + x·w). K > 2: one-vs-all, K binary models (class c
against the rest) whose probabilities are normalised to sum to 1.

Every binary model minimises the mean log-loss plus λ/2‖w‖² (the bias is not penalised) on
the design [1, x] (features standardised when `scale_features`; weights are reported in the
original units). Solvers:
- `gd`: θ ← θ − η∇f (constant step `learning_rate`).
- `newton`: Newton's method / IRLS (McCullagh & Nelder 1989) — the Hessian
  Zᵀdiag(σ(1−σ))Z/n + λI is Cholesky-factorised (with Levenberg damping when singular) and the
  step backtracked until Armijo's condition holds.
- `lbfgs`: L-BFGS (Liu & Nocedal 1989), memory 10, two-loop recursion, backtracking Armijo.
All stop when ‖∇f‖ < `tolerance` or after `max_iterations`. σ and ln(1 + eᶻ) are computed in
overflow-free forms, so huge feature values give finite losses even without scaling.

Outputs:
- `weights`: (d+1) × M, column m = [bias, w] of model m (M = 1 for K = 2, else K).
- `probabilities`: n × K, row i = class probabilities of sample i.
- `metrics`: `accuracy`, `log_loss` (mean −ln p(true class), p clipped at 1e-15), `iterations`
  (largest over models), `gradient_norm` (largest), `precision_c` / `recall_c` per class c,
  `auc` and `average_precision` of the ROC curve.
- `roc`: steps × 5 [threshold, TPR, FPR, precision, recall] as `analyze.roc`: of P(class 1)
  for K = 2, micro-averaged over all (sample, class) pairs for K > 2.
- `loss_curve`: k × 2 (iteration, objective averaged over the models).

Deterministic for any thread count.

Example:
    "clf": (op: "learn.logistic_regression", inputs: { "x": "blobs.x", "y": "blobs.y" },
            params: (solver: "newton", l2: 0.01)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("x", PortType::Matrix, "n × d features, one row per sample."),
            PortSpec::new("y", PortType::Matrix, "n × 1 integer class labels 0..K−1."),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "weights",
                PortType::Matrix,
                "(d+1) × M: column m = bias and weights of binary model m.",
            ),
            PortSpec::new(
                "probabilities",
                PortType::Matrix,
                "n × K class probabilities.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "accuracy, log_loss, iterations, gradient_norm, precision_c, recall_c, auc, average_precision.",
            ),
            PortSpec::new(
                "roc",
                PortType::Matrix,
                "steps × 5: threshold, TPR, FPR, precision, recall.",
            ),
            PortSpec::new(
                "loss_curve",
                PortType::Matrix,
                "k × 2: iteration, mean objective.",
            ),
        ]
    }

    fn new(p: LogisticParams) -> Result<Self, String> {
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
        if p.max_iterations == 0 {
            return Err("`max_iterations` must be at least 1".into());
        }
        if !(2..=65536).contains(&p.roc_steps) {
            return Err(format!(
                "`roc_steps` must be between 2 and 65536, got {}",
                p.roc_steps
            ));
        }
        Ok(LogisticRegression {
            config: LogisticConfig {
                solver: p.solver,
                learning_rate: p.learning_rate,
                max_iterations: p.max_iterations as usize,
                l2: p.l2,
                scale_features: p.scale_features,
                tolerance: p.tolerance,
            },
            roc_steps: p.roc_steps as usize,
        })
    }
}

impl Operator for LogisticRegression {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let x = input_matrix(inputs, "x")?;
        let y =
            single_column(input_matrix(inputs, "y")?, "y").map_err(|e| OpError::input("y", e))?;
        let fit = logistic_regression(x, &y, &self.config).map_err(|e| OpError::input("x", e))?;
        let (labels, k) = class_labels(&y).map_err(|e| OpError::input("y", e))?;
        let mut metrics = classification_metrics(&fit, &labels);
        metrics.insert("iterations".into(), fit.iterations as f64);
        metrics.insert("gradient_norm".into(), fit.gradient_norm);
        let (scores, truth): (Vec<f64>, Vec<bool>) = if k == 2 {
            (
                fit.probabilities.chunks_exact(2).map(|r| r[1]).collect(),
                labels.iter().map(|&l| l == 1).collect(),
            )
        } else {
            (
                fit.probabilities.clone(),
                labels
                    .iter()
                    .flat_map(|&l| (0..k).map(move |c| c == l))
                    .collect(),
            )
        };
        let roc = roc_curve(&scores, &truth, self.roc_steps).map_err(OpError::failed)?;
        metrics.insert("auc".into(), roc.auc);
        metrics.insert("average_precision".into(), roc.average_precision);
        let roc_rows: Vec<f64> = roc
            .points
            .iter()
            .flat_map(|q| [q.threshold, q.tpr, q.fpr, q.precision, q.recall])
            .collect();
        let models = fit.weights.len();
        let p = x.cols + 1;
        let weights: Vec<f64> = (0..p)
            .flat_map(|r| fit.weights.iter().map(move |w| w[r]))
            .collect();
        let n = labels.len();
        Ok(Outputs::new()
            .with("weights", matrix_value(p, models, weights)?)
            .with("probabilities", matrix_value(n, k, fit.probabilities)?)
            .with("metrics", Value::metrics(metrics))
            .with("roc", matrix_value(roc.points.len(), 5, roc_rows)?)
            .with("loss_curve", loss_curve_value(&fit.curve)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::dataset::blobs;

    fn config(solver: LogisticSolver) -> LogisticConfig {
        LogisticConfig {
            solver,
            l2: 0.01,
            tolerance: 1e-10,
            ..LogisticConfig::default()
        }
    }

    #[test]
    fn stable_sigmoid_and_softplus() {
        assert_eq!(sigmoid(1000.0), 1.0);
        assert_eq!(sigmoid(-1000.0), 0.0);
        assert!((sigmoid(0.3) + sigmoid(-0.3) - 1.0).abs() < 1e-15);
        assert_eq!(softplus(1000.0), 1000.0);
        assert_eq!(softplus(-1000.0), 0.0);
        assert!((softplus(0.0) - std::f64::consts::LN_2).abs() < 1e-15);
        assert!((softplus(2.0) - (1.0 + 2f64.exp()).ln()).abs() < 1e-14);
    }

    #[test]
    fn newton_and_lbfgs_reach_the_same_optimum() {
        // Overlapping blobs: a unique, finite optimum.
        let (x, y, _) = blobs(300, 2, 3, 1.0, 1.0, 11);
        let newton = logistic_regression(&x, &y, &config(LogisticSolver::Newton)).unwrap();
        let lbfgs = logistic_regression(&x, &y, &config(LogisticSolver::Lbfgs)).unwrap();
        assert!(newton.gradient_norm < 1e-10 && lbfgs.gradient_norm < 1e-10);
        assert!(newton.iterations < 15, "{}", newton.iterations);
        for (a, b) in newton.weights[0].iter().zip(&lbfgs.weights[0]) {
            assert!(
                (a - b).abs() < 1e-7,
                "{:?} vs {:?}",
                newton.weights,
                lbfgs.weights
            );
        }
        let gd = logistic_regression(
            &x,
            &y,
            &LogisticConfig {
                max_iterations: 3000,
                tolerance: 1e-7,
                ..config(LogisticSolver::Gd)
            },
        )
        .unwrap();
        for (a, b) in gd.weights[0].iter().zip(&newton.weights[0]) {
            assert!((a - b).abs() < 1e-5);
        }
        // Every objective curve decreases.
        for f in [&newton, &lbfgs, &gd] {
            assert!(f.curve.windows(2).all(|w| w[1] <= w[0]));
        }
    }

    #[test]
    fn separable_blobs_are_classified_with_valid_probabilities() {
        let (x, y, _) = blobs(200, 2, 2, 4.0, 0.5, 3);
        let fit = logistic_regression(&x, &y, &config(LogisticSolver::Lbfgs)).unwrap();
        let (labels, _) = class_labels(&y).unwrap();
        let m = classification_metrics(&fit, &labels);
        assert_eq!(m["accuracy"], 1.0);
        assert!(m["log_loss"] < 0.1);
        for row in fit.probabilities.chunks_exact(2) {
            assert!(row.iter().all(|p| (0.0..=1.0).contains(p)));
            assert!((row[0] + row[1] - 1.0).abs() < 1e-12);
        }
        // The boundary separates the means: class 1's mean lies at angle π.
        let w = &fit.weights[0];
        assert!(w[1] < 0.0, "{w:?}");
    }

    #[test]
    fn huge_feature_values_stay_finite() {
        let (mut x, y, _) = blobs(200, 2, 2, 2.0, 1.0, 5);
        x.data.iter_mut().for_each(|v| *v = *v * 1e8 + 1e12);
        for (scale, solver) in [
            (true, LogisticSolver::Newton),
            (true, LogisticSolver::Lbfgs),
            (false, LogisticSolver::Lbfgs),
        ] {
            let c = LogisticConfig {
                scale_features: scale,
                ..config(solver)
            };
            let fit = logistic_regression(&x, &y, &c).unwrap();
            assert!(
                fit.probabilities
                    .iter()
                    .all(|p| p.is_finite() && (0.0..=1.0).contains(p))
            );
            assert!(
                fit.curve.iter().all(|v| v.is_finite()),
                "{scale} {solver:?}"
            );
            if scale {
                let (labels, _) = class_labels(&y).unwrap();
                assert!(classification_metrics(&fit, &labels)["accuracy"] > 0.9);
            }
        }
    }

    #[test]
    fn one_vs_all_on_three_blobs() {
        let (x, y, means) = blobs(300, 3, 2, 5.0, 0.7, 8);
        for solver in [LogisticSolver::Newton, LogisticSolver::Lbfgs] {
            let fit = logistic_regression(&x, &y, &config(solver)).unwrap();
            assert_eq!(fit.weights.len(), 3);
            let (labels, _) = class_labels(&y).unwrap();
            let m = classification_metrics(&fit, &labels);
            assert!(m["accuracy"] > 0.98, "{m:?}");
            for c in 0..3 {
                assert!(m[&format!("recall_{c}")] > 0.95);
            }
            // Each model scores its own class's mean highest.
            for (c, w) in fit.weights.iter().enumerate() {
                let score =
                    |k: usize| w[0] + w[1] * means.data[2 * k] + w[2] * means.data[2 * k + 1];
                assert!((0..3).all(|k| k == c || score(c) > score(k)));
            }
            for row in fit.probabilities.chunks_exact(3) {
                assert!((row.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn bad_labels_are_errors() {
        let x = Matrix::new(3, 1, vec![0.0, 1.0, 2.0]).unwrap();
        assert!(logistic_regression(&x, &[0.0, 0.5, 1.0], &LogisticConfig::default()).is_err());
        assert!(logistic_regression(&x, &[0.0, 0.0, 0.0], &LogisticConfig::default()).is_err());
        let e = logistic_regression(&x, &[0.0, 2.0, 2.0], &LogisticConfig::default()).unwrap_err();
        assert!(e.contains("class 1"), "{e}");
    }
}
