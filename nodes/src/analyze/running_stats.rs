//! `analyze.running_stats`: running mean, standard deviation, minimum and maximum of every key
//! of a per-frame Metrics sequence — a stateful operator, the same in a stream and on a list.
//!
//! Over the whole sequence so far the moments are Welford's updates (Welford 1962; Knuth, TAOCP
//! vol. 2, §4.2.2): `δ = x − mean`, `mean += δ/n`, `M2 += δ·(x − mean)`, accurate when the values
//! sit on a large offset, where `E[x²] − E[x]²` cancels. With `window: N` they are those of the
//! last N frames, recomputed by the two-pass formula from a ring of N values each frame (cost
//! O(N) per key and frame, no drift from adding and removing).

use std::collections::{BTreeMap, VecDeque};

use ocellus_engine::op::{
    Inputs, Op, OpError, Operator, Outputs, Packet, PortSpec, RunContext, SequenceState,
    run_sequence_batch,
};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, Value};

params! {
    /// Parameters of `analyze.running_stats`.
    pub struct RunningStatsParams {
        /// Statistics over the last `window` frames; None (the default): over every frame so
        /// far.
        window: Option<u32> = None => [min = 1, max = 1000000, unit = "frames"],
    }
}

/// Running statistics of one key.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Running {
    /// Finite values seen.
    pub count: u64,
    /// Their mean.
    pub mean: f64,
    /// Σ (x − mean)².
    pub m2: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
    /// NaN or infinite values seen (not in the moments).
    pub nonfinite: u64,
    /// The last `window` values (window mode only; non-finite ones as NaN).
    ring: VecDeque<f64>,
}

impl Running {
    /// Adds a value (Welford's update).
    pub fn push(&mut self, x: f64) {
        if !x.is_finite() {
            self.nonfinite += 1;
            return;
        }
        if self.count == 0 {
            self.min = x;
            self.max = x;
        } else {
            self.min = self.min.min(x);
            self.max = self.max.max(x);
        }
        self.count += 1;
        let delta = x - self.mean;
        self.mean += delta / self.count as f64;
        self.m2 += delta * (x - self.mean);
    }

    /// Sample standard deviation (n − 1 in the denominator); 0 for fewer than two values.
    pub fn std(&self) -> f64 {
        if self.count < 2 {
            0.0
        } else {
            (self.m2 / (self.count - 1) as f64).max(0.0).sqrt()
        }
    }

    /// The statistics of `values` by the two-pass formula.
    pub fn of(values: impl Iterator<Item = f64> + Clone) -> Running {
        let mut r = Running::default();
        let finite = values.clone().filter(|x| x.is_finite());
        let (n, sum) = finite.clone().fold((0u64, 0.0), |(n, s), x| (n + 1, s + x));
        r.nonfinite = values.filter(|x| !x.is_finite()).count() as u64;
        if n == 0 {
            return r;
        }
        r.count = n;
        r.mean = sum / n as f64;
        let mut first = true;
        for x in finite {
            let d = x - r.mean;
            r.m2 += d * d;
            if first {
                (r.min, r.max, first) = (x, x, false);
            } else {
                r.min = r.min.min(x);
                r.max = r.max.max(x);
            }
        }
        r
    }

    fn write(&self, key: &str, out: &mut Metrics) {
        let empty = self.count == 0;
        let or_nan = |x: f64| if empty { f64::NAN } else { x };
        out.insert(format!("{key}.count"), self.count as f64);
        out.insert(format!("{key}.mean"), or_nan(self.mean));
        out.insert(format!("{key}.std"), or_nan(self.std()));
        out.insert(format!("{key}.min"), or_nan(self.min));
        out.insert(format!("{key}.max"), or_nan(self.max));
        if self.nonfinite > 0 {
            out.insert(format!("{key}.nonfinite"), self.nonfinite as f64);
        }
    }
}

/// The state: one [`Running`] per key, in key order.
#[derive(Debug, Clone, Default)]
pub struct RunningStats {
    window: Option<usize>,
    keys: BTreeMap<String, Running>,
    frames: usize,
}

impl RunningStats {
    /// Over every frame (`None`) or the last `window` frames.
    pub fn new(window: Option<usize>) -> RunningStats {
        RunningStats {
            window,
            ..RunningStats::default()
        }
    }

    /// Adds one frame's metrics and returns the statistics after it. A key missing from a
    /// frame counts as a non-finite value for that frame in window mode and is skipped
    /// otherwise.
    pub fn push(&mut self, metrics: &Metrics) -> Metrics {
        self.frames += 1;
        for key in metrics.keys() {
            if !self.keys.contains_key(key) {
                self.keys.insert(key.clone(), Running::default());
            }
        }
        let mut out = Metrics::new();
        for (key, running) in &mut self.keys {
            let x = metrics.get(key).copied();
            match self.window {
                None => {
                    if let Some(x) = x {
                        running.push(x);
                    }
                    running.write(key, &mut out);
                }
                Some(w) => {
                    running.ring.push_back(x.unwrap_or(f64::NAN));
                    while running.ring.len() > w {
                        running.ring.pop_front();
                    }
                    let mut stats = Running::of(running.ring.iter().copied());
                    stats.nonfinite = running.ring.iter().filter(|v| !v.is_finite()).count() as u64;
                    stats.write(key, &mut out);
                }
            }
        }
        out
    }

    /// Statistics over the whole sequence (window mode: over the last window).
    pub fn summary(&self) -> Metrics {
        let mut out = Metrics::new();
        for (key, running) in &self.keys {
            match self.window {
                None => running.write(key, &mut out),
                Some(_) => Running::of(running.ring.iter().copied()).write(key, &mut out),
            }
        }
        out.insert("frames".into(), self.frames as f64);
        out
    }
}

/// Running statistics of per-frame metrics (`analyze.running_stats`). See the module
/// documentation.
#[derive(Debug, Clone, PartialEq)]
pub struct RunningStatsOp {
    window: Option<usize>,
}

impl Op for RunningStatsOp {
    type Params = RunningStatsParams;
    const ID: &'static str = "analyze.running_stats";
    const SUMMARY: &'static str =
        "Running mean, standard deviation, minimum and maximum of per-frame metrics.";
    const DOC: &'static str = r#"
For every key K of the per-frame metrics, outputs after each frame `K.count` (finite values
so far), `K.mean`, `K.std` (sample standard deviation, n − 1; 0 below two values), `K.min`,
`K.max` and, when some were NaN or infinite, `K.nonfinite` (those are left out of the
moments). Means of an empty set are NaN. `summary` holds the same over the whole sequence
plus `frames`.

Method: Welford's running update (1962; Knuth TAOCP 2, §4.2.2) over every frame, which stays
accurate on values with a large offset; with `window: N`, the two-pass formula over the last
N frames.

A stateful operator: in a stream it keeps its sums between frames; on a list it gives the
same values.

Example:
    "fps": (op: "analyze.running_stats", inputs: { "values": "track.metrics" }, params: (window: 30)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "values",
                PortType::Metrics.list_of(),
                "Metrics per frame, in time order.",
            )
            .per_frame(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "running",
                PortType::Metrics.list_of(),
                "Per frame: the statistics after that frame.",
            )
            .per_frame(),
            PortSpec::new(
                "summary",
                PortType::Metrics,
                "The statistics after the last frame, plus `frames`.",
            ),
        ]
    }

    fn new(params: RunningStatsParams) -> Result<Self, String> {
        Ok(RunningStatsOp {
            window: params.window.map(|w| w as usize),
        })
    }
}

impl Operator for RunningStatsOp {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_sequence_batch(self, ctx, inputs, &Self::outputs())
    }

    fn sequence(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        Some(Ok(Box::new(RunningStats::new(self.window))))
    }
}

impl SequenceState for RunningStats {
    fn push(
        &mut self,
        _ctx: &RunContext,
        _packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        let metrics = match inputs.require("values")? {
            Value::Metrics(m) => m,
            other => {
                return Err(OpError::input(
                    "values",
                    format!("expected Metrics, got {}", other.port_type()),
                ));
            }
        };
        Ok(Outputs::new().with("running", Value::metrics(RunningStats::push(self, metrics))))
    }

    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("summary", Value::metrics(self.summary())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(pairs: &[(&str, f64)]) -> Metrics {
        pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
    }

    #[test]
    fn hand_computed_mean_and_std() {
        let mut s = RunningStats::new(None);
        for x in [2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0] {
            s.push(&m(&[("x", x)]));
        }
        let out = s.summary();
        assert_eq!(out["x.mean"], 5.0);
        // Σ(x − 5)² = 32, n − 1 = 7.
        assert!((out["x.std"] - (32.0f64 / 7.0).sqrt()).abs() < 1e-15);
        assert_eq!(
            (out["x.min"], out["x.max"], out["x.count"]),
            (2.0, 9.0, 8.0)
        );
        assert_eq!(out["frames"], 8.0);
    }

    #[test]
    fn welford_survives_a_large_offset() {
        let mut s = RunningStats::new(None);
        for k in 0..1000 {
            s.push(&m(&[("x", 1e9 + f64::from(k % 2))]));
        }
        let out = s.summary();
        // Values alternate 1e9, 1e9 + 1: mean 1e9 + 0.5, sample variance 250/999.
        assert!((out["x.mean"] - (1e9 + 0.5)).abs() < 1e-6);
        assert!((out["x.std"] - (250.0f64 / 999.0).sqrt()).abs() < 1e-9);
    }

    #[test]
    fn window_keeps_the_last_frames() {
        let mut s = RunningStats::new(Some(3));
        let mut last = Metrics::new();
        for x in [1.0, 2.0, 3.0, 10.0, 20.0] {
            last = s.push(&m(&[("x", x)]));
        }
        assert_eq!(last["x.mean"], 11.0);
        assert_eq!((last["x.min"], last["x.max"]), (3.0, 20.0));
        assert_eq!(last["x.count"], 3.0);
    }

    #[test]
    fn non_finite_values_are_counted_not_averaged() {
        let mut s = RunningStats::new(None);
        s.push(&m(&[("x", 1.0)]));
        s.push(&m(&[("x", f64::NAN)]));
        let out = s.push(&m(&[("x", 3.0)]));
        assert_eq!(out["x.mean"], 2.0);
        assert_eq!(out["x.nonfinite"], 1.0);
        let empty = RunningStats::new(None).summary();
        assert_eq!(empty["frames"], 0.0);
        let mut only_nan = RunningStats::new(None);
        let out = only_nan.push(&m(&[("y", f64::INFINITY)]));
        assert!(out["y.mean"].is_nan());
    }

    #[test]
    fn running_matches_two_pass_on_every_prefix() {
        let xs: Vec<f64> = (0..50)
            .map(|k| ((k * 37) % 11) as f64 * 0.3 - 1.0)
            .collect();
        let mut s = RunningStats::new(None);
        for n in 1..=xs.len() {
            let out = s.push(&m(&[("x", xs[n - 1])]));
            let two = Running::of(xs[..n].iter().copied());
            assert!((out["x.mean"] - two.mean).abs() < 1e-12);
            assert!((out["x.std"] - two.std()).abs() < 1e-12);
        }
    }
}
