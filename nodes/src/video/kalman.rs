//! `video.kalman_filter`: a 2-D track (one position per frame, gaps allowed) filtered and
//! optionally smoothed by a linear Kalman filter with a constant-velocity or
//! constant-acceleration motion model — the batch form of the stateful tracker, the same
//! recursion a streaming graph runs frame by frame.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
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

Example:
    "kf": (op: "video.kalman_filter", inputs: { "measurements": "track.positions" },
           params: (model: "constant_velocity", measurement_std: 2.0, gate_chi2: Some(9.21))),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "measurements",
            PortType::Matrix,
            "N × 2 positions, one row per frame; NaN rows are missing.",
        )]
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
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let p = &self.params;
        let (frames, rows) = track_measurements(inputs)?;
        let n_state = match p.model {
            MotionModel::ConstantVelocity => 4,
            MotionModel::ConstantAcceleration => 6,
        };
        let mut states = vec![f64::NAN; frames * n_state];
        let mut metrics = Metrics::new();
        let (mut updates, mut rejected, mut chi2_sum, mut log_likelihood) =
            (0usize, 0usize, 0.0, 0.0);
        let missing = rows.iter().filter(|r| r.is_none()).count();
        if let Some(first) = rows.iter().position(Option::is_some) {
            let mut x0 = DVector::zeros(n_state);
            let mut p0 = DMatrix::zeros(n_state, n_state);
            if let Some(Some(z0)) = rows.get(first) {
                x0[0] = z0[0];
                x0[1] = z0[1];
            }
            for k in 0..n_state {
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
            let mut kf = built.map_err(|e| OpError::failed(e.to_string()))?;
            let transition = kf.transition().clone();
            let fail = |e: super::filters::FilterError| OpError::failed(e.to_string());
            let mut steps: Vec<FilteredStep> = Vec::with_capacity(frames - first);
            // The first measurement initialises the state: record it as an update-free step.
            steps.push(FilteredStep {
                predicted_state: kf.state().clone(),
                predicted_covariance: kf.covariance().clone(),
                filtered_state: kf.state().clone(),
                filtered_covariance: kf.covariance().clone(),
                innovation: None,
            });
            for row in rows.iter().skip(first + 1) {
                kf.predict().map_err(fail)?;
                let (predicted_state, predicted_covariance) =
                    (kf.state().clone(), kf.covariance().clone());
                let innovation = match (row, p.gate_chi2) {
                    (None, _) => None,
                    (Some(m), Some(gate)) => {
                        let i = kf.update_gated(m, gate).map_err(fail)?;
                        if i.is_none() {
                            rejected += 1;
                        }
                        i
                    }
                    (Some(m), None) => Some(kf.update(m).map_err(fail)?),
                };
                if let Some(i) = &innovation {
                    updates += 1;
                    chi2_sum += i.mahalanobis_squared;
                    log_likelihood += i.log_likelihood;
                }
                steps.push(FilteredStep {
                    predicted_state,
                    predicted_covariance,
                    filtered_state: kf.state().clone(),
                    filtered_covariance: kf.covariance().clone(),
                    innovation,
                });
            }
            let estimates: Vec<DVector<f64>> = if p.smooth {
                rts_smooth(&steps, &transition)
                    .map_err(fail)?
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
        metrics.insert("frames".into(), frames as f64);
        metrics.insert("updates".into(), updates as f64);
        metrics.insert("rejected".into(), rejected as f64);
        metrics.insert("missing".into(), missing as f64);
        metrics.insert("log_likelihood".into(), log_likelihood);
        if updates > 0 {
            metrics.insert("mean_innovation_chi2".into(), chi2_sum / updates as f64);
        }
        track_outputs(frames, n_state, states, metrics)
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
