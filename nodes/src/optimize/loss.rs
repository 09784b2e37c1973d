//! Robust loss functions `ρ(s)` of a squared residual norm `s = ‖r‖²`, Ceres' conventions: the
//! cost of a residual block is `½ ρ(s)`, `ρ(s) ≈ s` near 0, and `a` (the scale, in residual
//! units, here pixels) is where the loss starts to down-weight.
//!
//! The solver uses them through [`RobustLoss::correction`], Triggs' second-order correction as in
//! Ceres' `Corrector`: the residual and its Jacobian are rescaled so that the Gauss–Newton model
//! of the rescaled block matches the second-order model of `½ ρ(‖r‖²)` at the current point.

/// A robust loss with its scale `a` (residual units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RobustLoss {
    /// `ρ(s) = s` (plain least squares).
    Trivial,
    /// `ρ(s) = s` for `s ≤ a²`, `2a√s − a²` beyond.
    Huber(f64),
    /// `ρ(s) = a² log(1 + s/a²)`.
    Cauchy(f64),
    /// `ρ(s) = 2a²(√(1 + s/a²) − 1)`.
    SoftL1(f64),
    /// `ρ(s) = a²/3 (1 − (1 − s/a²)³)` for `s ≤ a²`, `a²/3` beyond (Tukey's biweight).
    Tukey(f64),
}

/// How a residual block is rescaled for the Gauss–Newton model: `r' = residual_scale · r` and
/// `J' = jacobian_scale · (J − alpha_sq_norm · r (rᵀJ))`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correction {
    /// Factor on the residual.
    pub residual_scale: f64,
    /// Factor on the Jacobian.
    pub jacobian_scale: f64,
    /// `α / ‖r‖²` of the rank-one term (0 when there is none).
    pub alpha_sq_norm: f64,
}

impl RobustLoss {
    /// `[ρ(s), ρ'(s), ρ''(s)]`.
    pub fn evaluate(self, s: f64) -> [f64; 3] {
        match self {
            RobustLoss::Trivial => [s, 1.0, 0.0],
            RobustLoss::Huber(a) => {
                let b = a * a;
                if s > b {
                    let r = s.sqrt();
                    [2.0 * a * r - b, a / r, -0.5 * a / (s * r)]
                } else {
                    [s, 1.0, 0.0]
                }
            }
            RobustLoss::Cauchy(a) => {
                let b = a * a;
                let c = 1.0 / b;
                let sum = 1.0 + s * c;
                let inv = 1.0 / sum;
                [b * sum.ln(), inv, -c * inv * inv]
            }
            RobustLoss::SoftL1(a) => {
                let b = a * a;
                let c = 1.0 / b;
                let sum = 1.0 + s * c;
                let tmp = sum.sqrt();
                [2.0 * b * (tmp - 1.0), 1.0 / tmp, -0.5 * c / (sum * tmp)]
            }
            RobustLoss::Tukey(a) => {
                let b = a * a;
                if s <= b {
                    let v = 1.0 - s / b;
                    [b / 3.0 * (1.0 - v * v * v), v * v, -2.0 * v / b]
                } else {
                    [b / 3.0, 0.0, 0.0]
                }
            }
        }
    }

    /// Ceres' corrector for a residual block with squared norm `s`.
    pub fn correction(self, s: f64) -> Correction {
        let [_, rho1, rho2] = self.evaluate(s);
        if matches!(self, RobustLoss::Trivial) {
            return Correction {
                residual_scale: 1.0,
                jacobian_scale: 1.0,
                alpha_sq_norm: 0.0,
            };
        }
        let sqrt_rho1 = rho1.max(0.0).sqrt();
        if s == 0.0 || rho2 <= 0.0 || rho1 <= 0.0 {
            return Correction {
                residual_scale: sqrt_rho1,
                jacobian_scale: sqrt_rho1,
                alpha_sq_norm: 0.0,
            };
        }
        let d = 1.0 + 2.0 * s * rho2 / rho1;
        let alpha = 1.0 - d.max(0.0).sqrt();
        Correction {
            residual_scale: sqrt_rho1 / (1.0 - alpha),
            jacobian_scale: sqrt_rho1,
            alpha_sq_norm: alpha / s,
        }
    }

    /// The scale `a`, if the loss has one.
    pub fn scale(self) -> Option<f64> {
        match self {
            RobustLoss::Trivial => None,
            RobustLoss::Huber(a)
            | RobustLoss::Cauchy(a)
            | RobustLoss::SoftL1(a)
            | RobustLoss::Tukey(a) => Some(a),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOSSES: [RobustLoss; 5] = [
        RobustLoss::Trivial,
        RobustLoss::Huber(1.5),
        RobustLoss::Cauchy(1.5),
        RobustLoss::SoftL1(1.5),
        RobustLoss::Tukey(1.5),
    ];

    #[test]
    fn derivatives_match_finite_differences() {
        for loss in LOSSES {
            for s in [0.01, 0.5, 1.0, 2.0, 2.5, 7.0, 40.0] {
                let h = 1e-6;
                let [r, d1, d2] = loss.evaluate(s);
                let [rp, d1p, _] = loss.evaluate(s + h);
                let [rm, d1m, _] = loss.evaluate(s - h);
                assert!(
                    ((rp - rm) / (2.0 * h) - d1).abs() < 1e-6,
                    "{loss:?} ρ' at {s}"
                );
                assert!(
                    ((d1p - d1m) / (2.0 * h) - d2).abs() < 1e-5,
                    "{loss:?} ρ'' at {s}"
                );
                assert!(r <= s + 1e-12, "{loss:?}: ρ(s) ≤ s");
            }
            let [r0, d0, _] = loss.evaluate(0.0);
            assert_eq!(r0, 0.0);
            assert_eq!(d0, 1.0);
        }
    }

    #[test]
    fn hand_values() {
        // Huber a = 1: s = 4 → 2·1·2 − 1 = 3.
        assert_eq!(RobustLoss::Huber(1.0).evaluate(4.0)[0], 3.0);
        // Cauchy a = 1: s = e − 1 → log e = 1.
        let e = std::f64::consts::E;
        assert!((RobustLoss::Cauchy(1.0).evaluate(e - 1.0)[0] - 1.0).abs() < 1e-15);
        // Soft-L1 a = 1: s = 3 → 2(2 − 1) = 2.
        assert_eq!(RobustLoss::SoftL1(1.0).evaluate(3.0)[0], 2.0);
        // Tukey saturates at a²/3.
        assert_eq!(RobustLoss::Tukey(3.0).evaluate(100.0), [3.0, 0.0, 0.0]);
    }
}
