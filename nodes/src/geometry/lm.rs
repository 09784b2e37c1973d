//! A small dense Levenberg–Marquardt solver for nonlinear least squares `min ½‖r(x)‖²`.
//!
//! Problems implement [`Problem`]: residuals of a state `x`, and optionally an analytic
//! Jacobian (the default takes central differences) and a retraction `x ⊕ δ` for states on a
//! manifold (rotations, unit vectors, rank-2 matrices); the step `δ` lives in the tangent space
//! of dimension [`Problem::num_params`].
//!
//! Method: Marquardt's damped normal equations `(JᵀJ + λ·diag(JᵀJ)) δ = −Jᵀr`, solved by
//! Cholesky, with Nielsen's damping update (λ shrinks by `max(1/3, 1 − (2ρ − 1)³)` on success
//! and doubles geometrically on failure), stopping on small relative cost decrease, small step
//! or small gradient. Reference: Madsen, Nielsen & Tingleff, "Methods for non-linear least
//! squares problems" (2004), algorithm 3.16; Marquardt 1963.
//!
//! Dense and sequential: meant for problems of up to a few dozen parameters and thousands of
//! residuals (homography and fundamental refinement, circle fits, small calibrations).

use nalgebra::{DMatrix, DVector};

/// A nonlinear least-squares problem.
pub trait Problem {
    /// Dimension of the step (tangent space).
    fn num_params(&self) -> usize;
    /// Number of residuals.
    fn num_residuals(&self) -> usize;
    /// Writes `r(x)` (`r.len() == num_residuals()`).
    fn residuals(&self, x: &[f64], r: &mut [f64]);
    /// `x ⊕ δ`; plain addition by default (then `x.len() == num_params()`).
    fn retract(&self, x: &[f64], delta: &[f64]) -> Vec<f64> {
        x.iter().zip(delta).map(|(a, b)| a + b).collect()
    }
    /// Writes the Jacobian `∂r(x ⊕ δ)/∂δ` at `δ = 0` (`num_residuals × num_params`). Defaults to
    /// central differences with steps `1e-6·max(1, |x|)`-scaled.
    fn jacobian(&self, x: &[f64], jacobian: &mut DMatrix<f64>) {
        let p = self.num_params();
        let m = self.num_residuals();
        let scale = x.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1.0);
        let h = 1e-6 * scale.min(1e6);
        let mut plus = vec![0.0; m];
        let mut minus = vec![0.0; m];
        let mut delta = vec![0.0; p];
        for k in 0..p {
            delta[k] = h;
            self.residuals(&self.retract(x, &delta), &mut plus);
            delta[k] = -h;
            self.residuals(&self.retract(x, &delta), &mut minus);
            delta[k] = 0.0;
            for i in 0..m {
                jacobian[(i, k)] = (plus[i] - minus[i]) / (2.0 * h);
            }
        }
    }
}

/// Stopping rules.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmOptions {
    /// Most iterations (accepted or rejected steps).
    pub max_iterations: usize,
    /// Stop when the cost decreases by less than this fraction.
    pub cost_tolerance: f64,
    /// Stop when ‖δ‖ ≤ this · (‖x‖ + tolerance).
    pub step_tolerance: f64,
    /// Stop when ‖Jᵀr‖∞ falls below this.
    pub gradient_tolerance: f64,
    /// Initial damping relative to max diag(JᵀJ).
    pub initial_damping: f64,
}

impl Default for LmOptions {
    fn default() -> LmOptions {
        LmOptions {
            max_iterations: 100,
            cost_tolerance: 1e-12,
            step_tolerance: 1e-12,
            gradient_tolerance: 1e-14,
            initial_damping: 1e-4,
        }
    }
}

/// Why the solver stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    /// Relative cost decrease below tolerance.
    Cost,
    /// Step below tolerance.
    Step,
    /// Gradient below tolerance.
    Gradient,
    /// Iteration limit.
    MaxIterations,
    /// Non-finite residuals at the start, or no descent possible.
    Failed,
}

/// The solver's result.
#[derive(Debug, Clone, PartialEq)]
pub struct LmReport {
    /// Final state.
    pub x: Vec<f64>,
    /// `½‖r‖²` at the start.
    pub initial_cost: f64,
    /// `½‖r‖²` at the end (never above `initial_cost`).
    pub final_cost: f64,
    /// Iterations run.
    pub iterations: usize,
    /// Why it stopped.
    pub termination: Termination,
}

fn half_norm2(r: &[f64]) -> f64 {
    0.5 * r.iter().map(|v| v * v).sum::<f64>()
}

/// Minimises `½‖r(x)‖²` from `x0`. The returned state never costs more than `x0`.
pub fn levenberg_marquardt<P: Problem + ?Sized>(
    problem: &P,
    x0: &[f64],
    options: &LmOptions,
) -> LmReport {
    let p = problem.num_params();
    let m = problem.num_residuals();
    let mut x = x0.to_vec();
    let mut r = vec![0.0; m];
    problem.residuals(&x, &mut r);
    let mut cost = half_norm2(&r);
    let initial_cost = cost;
    let mut report = LmReport {
        x: x.clone(),
        initial_cost,
        final_cost: cost,
        iterations: 0,
        termination: Termination::Failed,
    };
    if !cost.is_finite() || p == 0 || m == 0 {
        return report;
    }
    let mut jacobian = DMatrix::zeros(m, p);
    let mut r_new = vec![0.0; m];
    let mut lambda = -1.0;
    let mut nu = 2.0;
    let mut need_jacobian = true;
    let mut jtj = DMatrix::zeros(p, p);
    let mut jtr = DVector::zeros(p);
    let mut termination = Termination::MaxIterations;
    let mut iterations = 0;
    while iterations < options.max_iterations {
        if need_jacobian {
            problem.jacobian(&x, &mut jacobian);
            jtj = jacobian.tr_mul(&jacobian);
            jtr = jacobian.tr_mul(&DVector::from_column_slice(&r));
            need_jacobian = false;
            if jtr.amax() <= options.gradient_tolerance {
                termination = Termination::Gradient;
                break;
            }
            if !jtj.iter().all(|v| v.is_finite()) {
                termination = Termination::Failed;
                break;
            }
        }
        let max_diag = (0..p).map(|i| jtj[(i, i)]).fold(0.0f64, f64::max);
        if lambda < 0.0 {
            lambda = options.initial_damping;
        }
        iterations += 1;
        let mut a = jtj.clone();
        for i in 0..p {
            a[(i, i)] += lambda * jtj[(i, i)].max(1e-12 * max_diag.max(1e-300));
        }
        let Some(cholesky) = a.cholesky() else {
            lambda *= nu;
            nu *= 2.0;
            continue;
        };
        let delta = -cholesky.solve(&jtr);
        let step_norm = delta.norm();
        let x_norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        if step_norm <= options.step_tolerance * (x_norm + options.step_tolerance) {
            termination = Termination::Step;
            break;
        }
        let x_new = problem.retract(&x, delta.as_slice());
        problem.residuals(&x_new, &mut r_new);
        let cost_new = half_norm2(&r_new);
        // Predicted decrease: ½ δᵀ(λ D δ − Jᵀr).
        let mut predicted = 0.0;
        for i in 0..p {
            predicted += 0.5
                * delta[i]
                * (lambda * jtj[(i, i)].max(1e-12 * max_diag.max(1e-300)) * delta[i] - jtr[i]);
        }
        let rho = if predicted > 0.0 {
            (cost - cost_new) / predicted
        } else {
            -1.0
        };
        if cost_new.is_finite() && cost_new < cost && rho > 0.0 {
            let decrease = (cost - cost_new) / cost.max(1e-300);
            x = x_new;
            std::mem::swap(&mut r, &mut r_new);
            cost = cost_new;
            need_jacobian = true;
            lambda *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
            nu = 2.0;
            if decrease <= options.cost_tolerance {
                termination = Termination::Cost;
                break;
            }
        } else {
            lambda *= nu;
            nu *= 2.0;
            if lambda > 1e32 {
                termination = Termination::Step;
                break;
            }
        }
    }
    report.x = x;
    report.final_cost = cost;
    report.iterations = iterations;
    report.termination = termination;
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rosenbrock as least squares: r = (10(y − x²), 1 − x).
    struct Rosenbrock;

    impl Problem for Rosenbrock {
        fn num_params(&self) -> usize {
            2
        }
        fn num_residuals(&self) -> usize {
            2
        }
        fn residuals(&self, x: &[f64], r: &mut [f64]) {
            r[0] = 10.0 * (x[1] - x[0] * x[0]);
            r[1] = 1.0 - x[0];
        }
    }

    #[test]
    fn solves_rosenbrock() {
        let report = levenberg_marquardt(&Rosenbrock, &[-1.2, 1.0], &LmOptions::default());
        assert!((report.x[0] - 1.0).abs() < 1e-9, "{report:?}");
        assert!((report.x[1] - 1.0).abs() < 1e-9, "{report:?}");
        assert!(report.final_cost < 1e-20);
    }

    /// Exponential decay y = a·exp(−b t) fitted to exact samples.
    struct Decay(Vec<(f64, f64)>);

    impl Problem for Decay {
        fn num_params(&self) -> usize {
            2
        }
        fn num_residuals(&self) -> usize {
            self.0.len()
        }
        fn residuals(&self, x: &[f64], r: &mut [f64]) {
            for (ri, (t, y)) in r.iter_mut().zip(&self.0) {
                *ri = x[0] * (-x[1] * t).exp() - y;
            }
        }
    }

    #[test]
    fn fits_exact_exponential_and_never_increases_cost() {
        let data: Vec<(f64, f64)> = (0..20)
            .map(|i| {
                let t = i as f64 * 0.25;
                (t, 3.0 * (-0.7 * t).exp())
            })
            .collect();
        let report = levenberg_marquardt(&Decay(data), &[1.0, 0.1], &LmOptions::default());
        assert!((report.x[0] - 3.0).abs() < 1e-9 && (report.x[1] - 0.7).abs() < 1e-9);
        assert!(report.final_cost <= report.initial_cost);
    }

    #[test]
    fn non_finite_start_returns_the_start() {
        struct Bad;
        impl Problem for Bad {
            fn num_params(&self) -> usize {
                1
            }
            fn num_residuals(&self) -> usize {
                1
            }
            fn residuals(&self, _x: &[f64], r: &mut [f64]) {
                r[0] = f64::NAN;
            }
        }
        let report = levenberg_marquardt(&Bad, &[2.0], &LmOptions::default());
        assert_eq!(report.x, vec![2.0]);
        assert_eq!(report.termination, Termination::Failed);
    }
}
