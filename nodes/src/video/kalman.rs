//! `video.kalman_filter`: a 2-D track (one position per frame, gaps allowed) filtered and
//! optionally smoothed by a linear Kalman filter with a constant-velocity or
//! constant-acceleration motion model — the batch form of the stateful tracker, the same
//! recursion a streaming graph runs frame by frame.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};
use ocellus_engine::op::{
    Inputs, Op, OpError, Operator, Outputs, Packet, PortSpec, RunContext, SequenceState,
    run_sequence_batch,
};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::filters::{FilteredStep, KalmanFilter, rts_smooth};

param_enum! {
    /// Motion model of `video.kalman_filter`.
    pub enum MotionModel {
        /// State x, y, vx, vy; white-noise acceleration (Bar-Shalom et al. 2001, §6.3.2).
        ConstantVelocity = "constant_velocity",
        /// State x, y, vx, vy, ax, ay; Wiener-process acceleration (§6.3.3).
        ConstantAcceleration = "constant_acceleration",
    }
}

params! {
    /// Parameters of `video.kalman_filter`.
    pub struct KalmanParams {
        /// Motion model. Default constant_velocity.
        model: MotionModel = MotionModel::ConstantVelocity,
        /// Time between rows, seconds. Default 1 (units per frame).
        dt_s: f64 = 1.0 => [above = 0.0, unit = "s"],
        /// Process noise: acceleration std (constant velocity) or acceleration-increment std
        /// (constant acceleration), position units per s² (per s³). Default 0.5.
        process_std: f64 = 0.5 => [min = 0.0],
        /// Measurement noise std, position units (pixels for image tracks). Default 1.
        measurement_std: f64 = 1.0 => [above = 0.0],
        /// Prior std of the velocity (and acceleration) at the first measurement. Default 10.
        initial_velocity_std: f64 = 10.0 => [above = 0.0],
        /// Reject a measurement whose squared Mahalanobis distance to the prediction exceeds
        /// this (χ² with 2 dof: 9.21 keeps 99 %); none: accept all. Default none.
        gate_chi2: Option<f64> = None => [above = 0.0],
        /// Rauch–Tung–Striebel smoothing of the whole track (uses later frames). Default false.
        smooth: bool = false,
    }
}

/// `video.kalman_filter`. See the module documentation.
#[derive(Debug, Clone)]
pub struct KalmanTrack {
    params: KalmanParams,
}

impl Op for KalmanTrack {
    type Params = KalmanParams;
    const ID: &'static str = "video.kalman_filter";
    const SUMMARY: &'static str = "Filters (and smooths) a 2-D track with a constant-velocity or -acceleration Kalman filter.";
    const DOC: &'static str = r#"
Runs a linear Kalman filter (Kalman 1960; Joseph-form covariance update, Cholesky-factored
innovation) over `measurements`, an N × 2 matrix of positions, one row per frame, `dt_s` apart;
a row with a NaN is a frame without a measurement (the filter predicts through it). The model is
`constant_velocity` (state x, y, vx, vy) or `constant_acceleration` (x, y, vx, vy, ax, ay) from
Bar-Shalom, Li & Kirubarajan 2001 (§6.3), with `process_std` and `measurement_std`. The filter
starts at the first measurement with velocity std `initial_velocity_std`; earlier rows are NaN.
`gate_chi2` rejects outliers by their squared Mahalanobis distance; `smooth` runs the
Rauch–Tung–Striebel smoother (1965) backwards over the filtered track.

Outputs: `states`, N × n (filtered or smoothed state per frame); `positions`, N × 2; `metrics`:
`frames`, `updates`, `rejected` (gated out), `missing`, `log_likelihood` (sum over updates),
`mean_innovation_chi2` (mean squared Mahalanobis distance of accepted measurements; ≈ 2 when the
noise levels are right).

The track comes either as `measurements` (a whole N × 2 matrix) or as `points` (per frame a
Points2D whose first point is the measurement, e.g. a detector mapped over the frames). With
`points` the filter is a stateful operator: in a stream it runs the recursion frame by frame
(`estimates` per frame, the filtered position), and `states`, `positions` and `metrics` come
after the last frame (smoothed there when `smooth`) — the same values as on a list.

Example:
    "kf": (op: "video.kalman_filter", inputs: { "measurements": "track.positions" },
           params: (model: "constant_velocity", measurement_std: 2.0, gate_chi2: Some(9.21))),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "measurements",
                PortType::Matrix,
                "N × 2 positions, one row per frame; NaN rows are missing.",
            )
            .optional(),
            PortSpec::new(
                "points",
                PortType::Points2D.list_of(),
                "Instead of `measurements`: per frame, the measured position as the first \
                 point (no point or NaN: missing). Streams frame by frame.",
            )
            .accepts_non_finite()
            .optional()
            .per_frame(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("states", PortType::Matrix, "N × n state estimates."),
            PortSpec::new("positions", PortType::Matrix, "N × 2 position estimates."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "Counts and innovation statistics.",
            ),
            PortSpec::new(
                "estimates",
                PortType::Points2D.list_of(),
                "Per frame: the filtered position (never smoothed) as one point; no point \
                 before the first measurement.",
            )
            .per_frame(),
        ]
    }

    fn new(p: KalmanParams) -> Result<Self, String> {
        let finite = [
            p.dt_s,
            p.process_std,
            p.measurement_std,
            p.initial_velocity_std,
        ]
        .iter()
        .all(|v| v.is_finite());
        if !finite {
            return Err("noise levels and `dt_s` must be finite".into());
        }
        Ok(KalmanTrack { params: p })
    }
}

impl Operator for KalmanTrack {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        match (inputs.get("measurements"), inputs.get("points")) {
            (Some(_), Some(_)) => Err(OpError::input(
                "points",
                "connect `measurements` or `points`, not both",
            )),
            (Some(_), None) => {
                let (_, rows) = track_measurements(inputs)?;
                let mut state = KalmanState::new(self.params.clone());
                let mut estimates = Vec::with_capacity(rows.len());
                for (k, row) in rows.iter().enumerate() {
                    let e = state
                        .push(row.as_ref())
                        .map_err(|e| OpError::failed(format!("frame {k}: {e}")))?;
                    estimates.push(e);
                }
                let mut out = state.finish()?;
                out.set("estimates", Value::list(PortType::Points2D, estimates));
                Ok(out)
            }
            (None, _) => run_sequence_batch(self, ctx, inputs, &Self::outputs()),
        }
    }

    fn sequence(
        &self,
        _ctx: &RunContext,
        inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        if inputs.get("measurements").is_some() {
            return Some(Err(OpError::input(
                "measurements",
                "a streamed track reads `points`; leave `measurements` unconnected",
            )));
        }
        Some(Ok(Box::new(KalmanState::new(self.params.clone()))))
    }
}

/// The filter between frames: the recursion so far and what the outputs need at the end.
struct KalmanState {
    params: KalmanParams,
    n_state: usize,
    /// Frames seen, and the first one with a measurement.
    frames: usize,
    first: Option<usize>,
    filter: Option<KalmanFilter>,
    steps: Vec<FilteredStep>,
    updates: usize,
    rejected: usize,
    missing: usize,
    chi2_sum: f64,
    log_likelihood: f64,
}

impl KalmanState {
    fn new(params: KalmanParams) -> KalmanState {
        let n_state = match params.model {
            MotionModel::ConstantVelocity => 4,
            MotionModel::ConstantAcceleration => 6,
        };
        KalmanState {
            params,
            n_state,
            frames: 0,
            first: None,
            filter: None,
            steps: Vec::new(),
            updates: 0,
            rejected: 0,
            missing: 0,
            chi2_sum: 0.0,
            log_likelihood: 0.0,
        }
    }

    /// One frame's measurement (`None`: missing); returns the filtered position (no point
    /// before the first measurement).
    fn push(&mut self, row: Option<&DVector<f64>>) -> Result<Value, OpError> {
        let p = &self.params;
        self.frames += 1;
        if row.is_none() {
            self.missing += 1;
        }
        let fail = |e: super::filters::FilterError| OpError::failed(e.to_string());
        match (&mut self.filter, row) {
            (None, None) => return Ok(Value::Points2D(Arc::new(Vec::new()))),
            (None, Some(z0)) => {
                let mut x0 = DVector::zeros(self.n_state);
                let mut p0 = DMatrix::zeros(self.n_state, self.n_state);
                x0[0] = z0[0];
                x0[1] = z0[1];
                for k in 0..self.n_state {
                    p0[(k, k)] = if k < 2 {
                        p.measurement_std.powi(2)
                    } else {
                        p.initial_velocity_std.powi(2)
                    };
                }
                let built = match p.model {
                    MotionModel::ConstantVelocity => KalmanFilter::constant_velocity_2d(
                        p.dt_s,
                        p.process_std,
                        p.measurement_std,
                        x0,
                        p0,
                    ),
                    MotionModel::ConstantAcceleration => KalmanFilter::constant_acceleration_2d(
                        p.dt_s,
                        p.process_std,
                        p.measurement_std,
                        x0,
                        p0,
                    ),
                };
                let kf = built.map_err(fail)?;
                // The first measurement initialises the state: an update-free step.
                self.steps.push(FilteredStep {
                    predicted_state: kf.state().clone(),
                    predicted_covariance: kf.covariance().clone(),
                    filtered_state: kf.state().clone(),
                    filtered_covariance: kf.covariance().clone(),
                    innovation: None,
                });
                self.first = Some(self.frames - 1);
                self.filter = Some(kf);
            }
            (Some(kf), row) => {
                kf.predict().map_err(fail)?;
                let (predicted_state, predicted_covariance) =
                    (kf.state().clone(), kf.covariance().clone());
                let innovation = match (row, p.gate_chi2) {
                    (None, _) => None,
                    (Some(m), Some(gate)) => {
                        let i = kf.update_gated(m, gate).map_err(fail)?;
                        if i.is_none() {
                            self.rejected += 1;
                        }
                        i
                    }
                    (Some(m), None) => Some(kf.update(m).map_err(fail)?),
                };
                if let Some(i) = &innovation {
                    self.updates += 1;
                    self.chi2_sum += i.mahalanobis_squared;
                    self.log_likelihood += i.log_likelihood;
                }
                self.steps.push(FilteredStep {
                    predicted_state,
                    predicted_covariance,
                    filtered_state: kf.state().clone(),
                    filtered_covariance: kf.covariance().clone(),
                    innovation,
                });
            }
        }
        let x = self.filter.as_ref().map(|kf| kf.state());
        Ok(Value::Points2D(Arc::new(
            x.map(|x| vec![[x[0], x[1]]]).unwrap_or_default(),
        )))
    }

    /// `states`, `positions` (smoothed when asked) and `metrics`.
    fn finish(&mut self) -> Result<Outputs, OpError> {
        let (frames, n_state) = (self.frames, self.n_state);
        let mut states = vec![f64::NAN; frames * n_state];
        if let (Some(first), Some(kf)) = (self.first, &self.filter) {
            let steps = std::mem::take(&mut self.steps);
            let estimates: Vec<DVector<f64>> = if self.params.smooth {
                rts_smooth(&steps, kf.transition())
                    .map_err(|e| OpError::failed(e.to_string()))?
                    .into_iter()
                    .map(|s| s.state)
                    .collect()
            } else {
                steps.into_iter().map(|s| s.filtered_state).collect()
            };
            for (k, x) in estimates.iter().enumerate() {
                let row = first + k;
                states[row * n_state..(row + 1) * n_state].copy_from_slice(x.as_slice());
            }
        }
        let mut metrics = Metrics::new();
        metrics.insert("frames".into(), frames as f64);
        metrics.insert("updates".into(), self.updates as f64);
        metrics.insert("rejected".into(), self.rejected as f64);
        metrics.insert("missing".into(), self.missing as f64);
        metrics.insert("log_likelihood".into(), self.log_likelihood);
        if self.updates > 0 {
            metrics.insert(
                "mean_innovation_chi2".into(),
                self.chi2_sum / self.updates as f64,
            );
        }
        track_outputs(frames, n_state, states, metrics)
    }
}

impl SequenceState for KalmanState {
    fn push(
        &mut self,
        _ctx: &RunContext,
        _packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        let row = frame_point(inputs)?;
        let estimate = KalmanState::push(self, row.as_ref())?;
        Ok(Outputs::new().with("estimates", estimate))
    }

    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        KalmanState::finish(self)
    }
}

/// This frame's measurement from the `points` input: its first point, `None` when it has no
/// point or a NaN coordinate; an infinite coordinate is an input error.
pub(super) fn frame_point(inputs: &Inputs<'_>) -> Result<Option<DVector<f64>>, OpError> {
    let Value::Points2D(points) = inputs.require("points")? else {
        return Err(OpError::input("points", "expected Points2D"));
    };
    match points.first() {
        None => Ok(None),
        Some(p) if p.iter().any(|v| v.is_infinite()) => {
            Err(OpError::input("points", "infinite coordinate"))
        }
        Some(p) if p.iter().any(|v| v.is_nan()) => Ok(None),
        Some(p) => Ok(Some(DVector::from_column_slice(p))),
    }
}

/// One position per frame, `None` where the frame has no measurement.
pub(super) type TrackRows = Vec<Option<DVector<f64>>>;

/// The `measurements` input of a track filter: its row count and each row's position (`None`
/// for a row with a NaN). Not N × 2, or an infinite coordinate, is an input error.
pub(super) fn track_measurements(inputs: &Inputs<'_>) -> Result<(usize, TrackRows), OpError> {
    let Value::Matrix(z) = inputs.require("measurements")? else {
        return Err(OpError::input("measurements", "expected a Matrix"));
    };
    if z.cols != 2 {
        return Err(OpError::input(
            "measurements",
            format!("expected N × 2 positions, got {} columns", z.cols),
        ));
    }
    if z.data.iter().any(|v| v.is_infinite()) {
        return Err(OpError::input("measurements", "infinite coordinate"));
    }
    let rows = z
        .data
        .chunks_exact(2)
        .map(|r| (r[0].is_finite() && r[1].is_finite()).then(|| DVector::from_column_slice(r)))
        .collect();
    Ok((z.rows, rows))
}

/// The outputs of a track filter: `states` (frames × n), `positions` (its first two columns)
/// and `metrics`.
pub(super) fn track_outputs(
    frames: usize,
    n_state: usize,
    states: Vec<f64>,
    metrics: Metrics,
) -> Result<Outputs, OpError> {
    let positions: Vec<f64> = states
        .chunks_exact(n_state)
        .flat_map(|s| [s[0], s[1]])
        .collect();
    let matrix = |cols: usize, data: Vec<f64>| {
        Matrix::new(frames, cols, data)
            .map(|m| Value::Matrix(Arc::new(m)))
            .map_err(|e| OpError::failed(e.to_string()))
    };
    Ok(Outputs::new()
        .with("states", matrix(n_state, states)?)
        .with("positions", matrix(2, positions)?)
        .with("metrics", Value::metrics(metrics)))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use ocellus_engine::op::Op;

    use super::super::filters::SplitMix64;
    use super::*;

    fn run(params: KalmanParams, z: Matrix) -> Outputs {
        let op = KalmanTrack::new(params).unwrap();
        let specs = KalmanTrack::inputs();
        let values = [Some(Value::Matrix(Arc::new(z)))];
        op.run(
            &RunContext {
                node: "kf".into(),
                threads: 1,
                element: None,
            },
            &Inputs::new(&specs, &values),
        )
        .unwrap()
    }

    /// A target moving at constant velocity, measured with noise σ = 2; returns (truth, z).
    fn track(frames: usize, outliers: bool) -> (Vec<[f64; 2]>, Matrix) {
        let mut rng = SplitMix64::new(7);
        let truth: Vec<[f64; 2]> = (0..frames)
            .map(|k| [10.0 + 3.0 * k as f64, 50.0 - 1.5 * k as f64])
            .collect();
        let mut data = Vec::new();
        for (k, t) in truth.iter().enumerate() {
            if k % 17 == 5 {
                data.extend([f64::NAN, f64::NAN]);
            } else if outliers && k % 10 == 3 {
                data.extend([t[0] + 80.0, t[1] - 60.0]);
            } else {
                data.extend([t[0] + rng.normal(0.0, 2.0), t[1] + rng.normal(0.0, 2.0)]);
            }
        }
        (truth, Matrix::new(frames, 2, data).unwrap())
    }

    fn rmse(out: &Outputs, truth: &[[f64; 2]], skip: usize) -> f64 {
        let Some(Value::Matrix(p)) = out.get("positions") else {
            panic!()
        };
        let mut sum = 0.0;
        for (k, t) in truth.iter().enumerate().skip(skip) {
            sum += (p.get(k, 0).unwrap() - t[0]).powi(2) + (p.get(k, 1).unwrap() - t[1]).powi(2);
        }
        (sum / (truth.len() - skip) as f64).sqrt()
    }

    #[test]
    fn filtering_beats_the_measurements_and_smoothing_beats_filtering() {
        let (truth, z) = track(200, false);
        let params = KalmanParams {
            measurement_std: 2.0,
            process_std: 0.05,
            ..KalmanParams::default()
        };
        let filtered = run(params.clone(), z.clone());
        let smoothed = run(
            KalmanParams {
                smooth: true,
                ..params
            },
            z,
        );
        let (f, s) = (rmse(&filtered, &truth, 10), rmse(&smoothed, &truth, 10));
        println!("RMSE: measurements 2.83, filtered {f:.3}, smoothed {s:.3}");
        assert!(f < 2.0 * 2f64.sqrt() * 0.5, "{f}");
        assert!(s < f, "{s} vs {f}");
        let Some(Value::Metrics(m)) = filtered.get("metrics") else {
            panic!()
        };
        assert_eq!(m["missing"], 12.0);
        assert_eq!(m["updates"], 200.0 - 12.0 - 1.0);
        // Innovations are consistent: mean χ² near its 2 degrees of freedom.
        assert!(
            (m["mean_innovation_chi2"] - 2.0).abs() < 0.5,
            "{}",
            m["mean_innovation_chi2"]
        );
    }

    #[test]
    fn per_frame_points_give_the_matrix_results_and_the_filtered_estimates() {
        let (_, z) = track(60, true);
        let params = KalmanParams {
            measurement_std: 2.0,
            gate_chi2: Some(9.21),
            smooth: true,
            ..KalmanParams::default()
        };
        let from_matrix = run(params.clone(), z.clone());
        // The same track as one Points2D per frame (NaN rows: no point).
        let points: Vec<Value> = z
            .data
            .chunks_exact(2)
            .map(|r| {
                let p = if r[0].is_nan() {
                    vec![]
                } else {
                    vec![[r[0], r[1]]]
                };
                Value::Points2D(Arc::new(p))
            })
            .collect();
        let op = KalmanTrack::new(params.clone()).unwrap();
        let specs = KalmanTrack::inputs();
        let values = [None, Some(Value::list(PortType::Points2D, points))];
        let ctx = RunContext {
            node: "kf".into(),
            threads: 1,
            element: None,
        };
        let from_points = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        for name in ["states", "positions", "metrics", "estimates"] {
            assert_eq!(
                format!("{:?}", from_points.get(name)),
                format!("{:?}", from_matrix.get(name)),
                "{name}"
            );
        }
        // Estimates are the filtered (not smoothed) positions, one point per frame.
        let unsmoothed = run(
            KalmanParams {
                smooth: false,
                ..params
            },
            z,
        );
        let (Some(Value::List(estimates)), Some(Value::Matrix(filtered))) =
            (from_points.get("estimates"), unsmoothed.get("positions"))
        else {
            panic!()
        };
        assert_eq!(estimates.items.len(), 60);
        for (k, e) in estimates.items.iter().enumerate() {
            let Value::Points2D(p) = e else { panic!() };
            assert_eq!(
                p[0],
                [filtered.data[2 * k], filtered.data[2 * k + 1]],
                "frame {k}"
            );
        }
        // Both inputs at once is an input error.
        let both = [
            Some(Value::Matrix(Arc::new(Matrix::new(0, 2, vec![]).unwrap()))),
            values[1].clone(),
        ];
        assert!(op.run(&ctx, &Inputs::new(&specs, &both)).is_err());
    }

    #[test]
    fn gating_rejects_outliers() {
        let (truth, z) = track(200, true);
        let base = KalmanParams {
            measurement_std: 2.0,
            process_std: 0.05,
            ..KalmanParams::default()
        };
        let gated = run(
            KalmanParams {
                gate_chi2: Some(9.21),
                ..base.clone()
            },
            z.clone(),
        );
        let open = run(base, z);
        let (g, o) = (rmse(&gated, &truth, 10), rmse(&open, &truth, 10));
        println!("RMSE with 10 % outliers: gated {g:.3}, ungated {o:.3}");
        assert!(g < 1.5 && o > 3.0 * g, "{g} vs {o}");
        let Some(Value::Metrics(m)) = gated.get("metrics") else {
            panic!()
        };
        assert!(m["rejected"] >= 18.0, "{}", m["rejected"]);
    }

    #[test]
    fn rows_before_the_first_measurement_are_nan_and_bad_input_is_an_error() {
        let z = Matrix::new(3, 2, vec![f64::NAN, f64::NAN, 1.0, 2.0, 2.0, 3.0]).unwrap();
        let out = run(KalmanParams::default(), z);
        let Some(Value::Matrix(s)) = out.get("states") else {
            panic!()
        };
        assert_eq!((s.rows, s.cols), (3, 4));
        assert!(s.get(0, 0).unwrap().is_nan());
        assert_eq!(s.get(1, 0), Some(1.0));
        let op = KalmanTrack::new(KalmanParams::default()).unwrap();
        let specs = KalmanTrack::inputs();
        let values = [Some(Value::Matrix(Arc::new(
            Matrix::new(1, 3, vec![0.0; 3]).unwrap(),
        )))];
        let ctx = RunContext {
            node: "kf".into(),
            threads: 1,
            element: None,
        };
        assert!(op.run(&ctx, &Inputs::new(&specs, &values)).is_err());
    }
}
