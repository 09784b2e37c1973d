//! Limited-memory BFGS (Nocedal 1980; Liu & Nocedal 1989) with the two-loop recursion and a
//! backtracking Armijo line search, for smooth unconstrained minimisation.
//!
//! `optimize/` holds only Gauss–Newton / Levenberg–Marquardt least-squares solvers (no
//! quasi-Newton method for general objectives), so this is the family's own.

use std::collections::VecDeque;

use super::{dot, norm};

/// Sufficient-decrease constant c₁ of the Armijo condition (Nocedal & Wright's usual value).
const ARMIJO_C1: f64 = 1e-4;

/// Step halvings tried before the line search gives up.
const MAX_BACKTRACKS: usize = 50;

/// Settings of [`lbfgs`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LbfgsConfig {
    /// Correction pairs kept (m ≥ 1).
    pub memory: usize,
    /// Most iterations.
    pub max_iterations: usize,
    /// Stop once ‖∇f‖ falls below this.
    pub tolerance: f64,
}

/// The result of a minimisation.
#[derive(Debug, Clone, PartialEq)]
pub struct Minimum {
    /// The final point.
    pub x: Vec<f64>,
    /// f at the final point.
    pub value: f64,
    /// ‖∇f‖ at the final point.
    pub gradient_norm: f64,
    /// Iterations run.
    pub iterations: usize,
    /// f before the first iteration and after every one.
    pub curve: Vec<f64>,
}

/// Minimises `f` (returning value and gradient) from `x0` by L-BFGS: the search direction is
/// −H∇f with H the inverse-Hessian approximation of the last `memory` pairs (s = Δx, y = Δ∇f)
/// applied by the two-loop recursion (Nocedal & Wright, "Numerical Optimization", Alg. 7.4),
/// H₀ = (sᵀy / yᵀy)·I; steps by backtracking from α = 1 (first iteration 1/‖∇f‖) until
/// Armijo's condition holds. Pairs with sᵀy ≤ 1e-10·‖s‖‖y‖ (no positive curvature) are not
/// stored; a failed line search clears the memory and retries along −∇f, then stops. Errors
/// when f is not finite at `x0`.
pub fn lbfgs<F>(mut f: F, x0: Vec<f64>, config: &LbfgsConfig) -> Result<Minimum, String>
where
    F: FnMut(&[f64]) -> (f64, Vec<f64>),
{
    let mut x = x0;
    let (mut fx, mut g) = f(&x);
    if !fx.is_finite() {
        return Err("the objective is not finite at the start point".into());
    }
    let mut pairs: VecDeque<(Vec<f64>, Vec<f64>, f64)> = VecDeque::new();
    let mut curve = vec![fx];
    let mut iterations = 0;
    let memory = config.memory.max(1);
    while iterations < config.max_iterations && norm(&g) >= config.tolerance {
        let mut step = None;
        for attempt in 0..2 {
            let dir = if attempt == 0 {
                two_loop(&g, &pairs)
            } else {
                g.iter().map(|v| -v).collect()
            };
            let slope = dot(&g, &dir);
            if slope >= 0.0 {
                pairs.clear();
                continue;
            }
            let mut alpha = if pairs.is_empty() {
                (1.0 / norm(&g)).min(1.0)
            } else {
                1.0
            };
            for _ in 0..MAX_BACKTRACKS {
                let xn: Vec<f64> = x.iter().zip(&dir).map(|(a, d)| a + alpha * d).collect();
                let (fn_, gn) = f(&xn);
                if fn_.is_finite() && fn_ <= fx + ARMIJO_C1 * alpha * slope {
                    step = Some((xn, fn_, gn));
                    break;
                }
                alpha *= 0.5;
            }
            if step.is_some() {
                break;
            }
            pairs.clear();
        }
        let Some((xn, fn_, gn)) = step else { break };
        let s: Vec<f64> = xn.iter().zip(&x).map(|(a, b)| a - b).collect();
        let y: Vec<f64> = gn.iter().zip(&g).map(|(a, b)| a - b).collect();
        let sy = dot(&s, &y);
        if sy > 1e-10 * norm(&s) * norm(&y) {
            if pairs.len() == memory {
                pairs.pop_front();
            }
            pairs.push_back((s, y, 1.0 / sy));
        }
        x = xn;
        fx = fn_;
        g = gn;
        curve.push(fx);
        iterations += 1;
    }
    Ok(Minimum {
        gradient_norm: norm(&g),
        x,
        value: fx,
        iterations,
        curve,
    })
}

/// −H·g by the two-loop recursion over `pairs` (oldest first).
fn two_loop(g: &[f64], pairs: &VecDeque<(Vec<f64>, Vec<f64>, f64)>) -> Vec<f64> {
    let mut q = g.to_vec();
    let mut alphas = vec![0.0; pairs.len()];
    for (k, (s, y, rho)) in pairs.iter().enumerate().rev() {
        let a = rho * dot(s, &q);
        alphas[k] = a;
        q.iter_mut().zip(y).for_each(|(qi, yi)| *qi -= a * yi);
    }
    if let Some((s, y, _)) = pairs.back() {
        let gamma = dot(s, y) / dot(y, y);
        q.iter_mut().for_each(|v| *v *= gamma);
    }
    for (k, (s, y, rho)) in pairs.iter().enumerate() {
        let b = rho * dot(y, &q);
        q.iter_mut()
            .zip(s)
            .for_each(|(qi, si)| *qi += (alphas[k] - b) * si);
    }
    q.iter_mut().for_each(|v| *v = -*v);
    q
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rosenbrock(x: &[f64]) -> (f64, Vec<f64>) {
        let (a, b) = (x[0], x[1]);
        let f = (1.0 - a).powi(2) + 100.0 * (b - a * a).powi(2);
        let g = vec![
            -2.0 * (1.0 - a) - 400.0 * a * (b - a * a),
            200.0 * (b - a * a),
        ];
        (f, g)
    }

    #[test]
    fn finds_the_rosenbrock_minimum() {
        let c = LbfgsConfig {
            memory: 5,
            max_iterations: 500,
            tolerance: 1e-10,
        };
        let m = lbfgs(rosenbrock, vec![-1.2, 1.0], &c).unwrap();
        assert!(
            (m.x[0] - 1.0).abs() < 1e-8 && (m.x[1] - 1.0).abs() < 1e-8,
            "{m:?}"
        );
        assert!(m.gradient_norm < 1e-10);
        assert!(m.curve.windows(2).all(|w| w[1] <= w[0]));
        assert!(m.iterations < 100, "{} iterations", m.iterations);
    }

    #[test]
    fn minimises_a_quadratic_in_at_most_a_few_dimensions_of_steps() {
        // f = ½ xᵀAx − bᵀx with A diagonal: minimum at b / diag.
        let diag = [1.0, 10.0, 100.0, 3.0];
        let b = [1.0, 2.0, 3.0, 4.0];
        let f = |x: &[f64]| {
            let v: f64 = (0..4)
                .map(|i| 0.5 * diag[i] * x[i] * x[i] - b[i] * x[i])
                .sum();
            let g = (0..4).map(|i| diag[i] * x[i] - b[i]).collect();
            (v, g)
        };
        let c = LbfgsConfig {
            memory: 10,
            max_iterations: 100,
            tolerance: 1e-12,
        };
        let m = lbfgs(f, vec![0.0; 4], &c).unwrap();
        for i in 0..4 {
            assert!((m.x[i] - b[i] / diag[i]).abs() < 1e-10);
        }
    }
}
