//! What both least-squares solvers ([`super::ba`] and [`super::nlls`]) report: why they stopped,
//! one record per iteration, and the operator-facing [`Metrics`] built from them.

use ocellus_engine::value::Metrics;

/// Why the solver stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    /// Relative cost change below `function_tolerance`.
    FunctionTolerance,
    /// Gradient below `gradient_tolerance`.
    GradientTolerance,
    /// Step below `parameter_tolerance`.
    ParameterTolerance,
    /// Iteration limit.
    MaxIterations,
    /// The trust region shrank below 1e-32.
    TrustRegionCollapsed,
    /// Nothing to optimize (no free parameters or no residuals).
    Trivial,
}

impl Termination {
    /// A numeric code for reports: 0 function, 1 gradient, 2 parameter tolerance, 3 iteration
    /// limit, 4 collapsed trust region, 5 trivial.
    pub fn code(self) -> f64 {
        match self {
            Termination::FunctionTolerance => 0.0,
            Termination::GradientTolerance => 1.0,
            Termination::ParameterTolerance => 2.0,
            Termination::MaxIterations => 3.0,
            Termination::TrustRegionCollapsed => 4.0,
            Termination::Trivial => 5.0,
        }
    }
}

/// One iteration of the history.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IterationRecord {
    /// Cost after the iteration.
    pub cost: f64,
    /// Norm of the trial step (0 for iteration 0 and failed solves).
    pub step_norm: f64,
    /// Trust-region radius used for the step.
    pub radius: f64,
    /// Whether the step was accepted.
    pub accepted: bool,
    /// Seconds since the start of the solve.
    pub time_s: f64,
    /// Conjugate-gradient iterations of the step's linear solve (0 for direct solvers).
    pub cg_iterations: usize,
}

/// The totals of a solve that every report carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveTotals {
    /// Cost `½ Σ ρ(‖r‖²)` at the start.
    pub initial_cost: f64,
    /// Cost at the end.
    pub final_cost: f64,
    /// Iterations, Ceres' count.
    pub iterations: usize,
    /// Accepted steps.
    pub successful_steps: usize,
    /// Rejected steps.
    pub unsuccessful_steps: usize,
    /// Why the solve stopped.
    pub termination: Termination,
    /// Whether the linear systems were solved by dense Cholesky.
    pub dense_solver: bool,
}

/// The report keys shared by every bundle-adjustment path: `initial_cost`, `final_cost`,
/// `iterations`, `successful_steps`, `unsuccessful_steps`, `termination` ([`Termination::code`])
/// and `dense_solver` (1/0).
pub fn totals_metrics(t: &SolveTotals) -> Metrics {
    let mut m = Metrics::new();
    m.insert("initial_cost".into(), t.initial_cost);
    m.insert("final_cost".into(), t.final_cost);
    m.insert("iterations".into(), t.iterations as f64);
    m.insert("successful_steps".into(), t.successful_steps as f64);
    m.insert("unsuccessful_steps".into(), t.unsuccessful_steps as f64);
    m.insert("termination".into(), t.termination.code());
    m.insert(
        "dense_solver".into(),
        if t.dense_solver { 1.0 } else { 0.0 },
    );
    m
}

/// Per-iteration fields, in the order [`history_metrics`] writes them.
pub const HISTORY_FIELDS: [&str; 6] = [
    "cost",
    "step_norm",
    "trust_radius",
    "accepted",
    "time_s",
    "cg_iterations",
];

/// The history as Metrics: for iteration `i` (zero-padded to five digits so the keys sort in
/// iteration order, iteration 0 being the start) the keys `i.cost`, `i.step_norm`,
/// `i.trust_radius`, `i.accepted` (1/0), `i.time_s` (seconds since the start) and
/// `i.cg_iterations`.
pub fn history_metrics(history: &[IterationRecord]) -> Metrics {
    let mut m = Metrics::new();
    for (i, h) in history.iter().enumerate() {
        let values = [
            h.cost,
            h.step_norm,
            h.radius,
            if h.accepted { 1.0 } else { 0.0 },
            h.time_s,
            h.cg_iterations as f64,
        ];
        for (field, v) in HISTORY_FIELDS.iter().zip(values) {
            m.insert(format!("{i:05}.{field}"), v);
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(cost: f64, accepted: bool) -> IterationRecord {
        IterationRecord {
            cost,
            step_norm: 0.5,
            radius: 1e4,
            accepted,
            time_s: 0.25,
            cg_iterations: 7,
        }
    }

    #[test]
    fn history_keys_sort_in_iteration_order_and_hold_every_field() {
        let history: Vec<IterationRecord> = (0..12)
            .map(|i| record(100.0 - i as f64, i % 3 != 1))
            .collect();
        let m = history_metrics(&history);
        assert_eq!(m.len(), 12 * HISTORY_FIELDS.len());
        let costs: Vec<f64> = m
            .iter()
            .filter(|(k, _)| k.ends_with(".cost"))
            .map(|(_, v)| *v)
            .collect();
        let expected: Vec<f64> = (0..12).map(|i| 100.0 - i as f64).collect();
        assert_eq!(
            costs, expected,
            "lexicographic key order is iteration order"
        );
        assert_eq!(m["00004.accepted"], 0.0);
        assert_eq!(m["00005.accepted"], 1.0);
        assert_eq!(m["00011.cg_iterations"], 7.0);
        assert_eq!(m["00000.trust_radius"], 1e4);
        assert_eq!(m["00003.time_s"], 0.25);
        assert_eq!(m["00003.step_norm"], 0.5);
    }

    #[test]
    fn termination_codes_are_distinct_and_totals_carry_them() {
        let all = [
            Termination::FunctionTolerance,
            Termination::GradientTolerance,
            Termination::ParameterTolerance,
            Termination::MaxIterations,
            Termination::TrustRegionCollapsed,
            Termination::Trivial,
        ];
        let codes: Vec<f64> = all.iter().map(|t| t.code()).collect();
        assert_eq!(codes, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        let m = totals_metrics(&SolveTotals {
            initial_cost: 10.0,
            final_cost: 2.0,
            iterations: 4,
            successful_steps: 3,
            unsuccessful_steps: 1,
            termination: Termination::GradientTolerance,
            dense_solver: false,
        });
        assert_eq!(m["termination"], 1.0);
        assert_eq!(m["dense_solver"], 0.0);
        assert_eq!(m["successful_steps"] + m["unsuccessful_steps"], 4.0);
        assert_eq!(m["initial_cost"], 10.0);
        assert_eq!(m["final_cost"], 2.0);
    }
}
