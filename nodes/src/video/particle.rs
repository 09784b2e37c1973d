//! `video.particle_filter`: a 2-D track (one position per frame, gaps allowed) estimated by a
//! sequential-importance-resampling particle filter (Gordon, Salmond & Smith 1993) with a
//! constant-velocity motion model and an outlier-tolerant measurement likelihood — where a
//! Kalman filter's Gaussian assumption breaks (clutter, gross detector errors).

use nalgebra::DVector;
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::Metrics;
use ocellus_engine::{param_enum, params};

use super::filters::{ParticleFilter, Resampling, SplitMix64};
use super::kalman::{track_measurements, track_outputs};

param_enum! {
    /// Resampling scheme of `video.particle_filter`.
    pub enum ResamplingName {
        /// Independent draws from the weights.
        Multinomial = "multinomial",
        /// One offset, evenly spaced points (Kitagawa 1996).
        Systematic = "systematic",
        /// One point per stratum (Kitagawa 1996).
        Stratified = "stratified",
        /// Deterministic copies plus multinomial remainder (Liu & Chen 1998).
        Residual = "residual",
    }
}

params! {
    /// Parameters of `video.particle_filter`.
    pub struct ParticleParams {
        /// Number of particles (more: lower Monte-Carlo error, linear cost). Default 1000.
        particles: u32 = 1000 => [min = 1, max = 10000000],
        /// Seed of the filter's random numbers. Default 1.
        seed: u64 = 1,
        /// Time between rows, seconds. Default 1.
        dt_s: f64 = 1.0 => [above = 0.0, unit = "s"],
        /// White-noise acceleration std of the constant-velocity motion, units per s². Default 0.5.
        process_std: f64 = 0.5 => [min = 0.0],
        /// Std of a good measurement, position units. Default 1.
        measurement_std: f64 = 1.0 => [above = 0.0],
        /// Prior std of the velocity at the first measurement. Default 10.
        initial_velocity_std: f64 = 10.0 => [above = 0.0],
        /// Share of measurements that are clutter, in [0, 1): the likelihood is
        /// (1 − ε)·N(z; x, σ²I) + ε / outlier_area. Default 0.05.
        outlier_fraction: f64 = 0.05 => [min = 0.0, max = 1.0],
        /// Area over which clutter is uniform, squared position units (e.g. the image area).
        /// Default 921600 (1280 × 720).
        outlier_area: f64 = 921600.0 => [above = 0.0],
        /// Resampling scheme. Default systematic.
        resampling: ResamplingName = ResamplingName::Systematic,
        /// Resample when the effective sample size drops below this share of the particles.
        /// Default 0.5.
        ess_fraction: f64 = 0.5 => [min = 0.0, max = 1.0],
    }
}

/// `video.particle_filter`. See the module documentation.
#[derive(Debug, Clone)]
pub struct ParticleTrack {
    params: ParticleParams,
}

impl Op for ParticleTrack {
    type Params = ParticleParams;
    const ID: &'static str = "video.particle_filter";
    const SUMMARY: &'static str =
        "Estimates a 2-D track with a particle filter robust to outlying measurements.";
    const DOC: &'static str = r#"
Sequential importance resampling (Gordon, Salmond & Smith 1993) over `measurements`, an N × 2
matrix of positions `dt_s` apart (a row with a NaN is a frame without a measurement). Each of
`particles` states (x, y, vx, vy) moves by constant velocity plus sampled white-noise
acceleration (`process_std`) and is weighted by the mixture likelihood
`(1 − outlier_fraction)·N(z; x, measurement_std²·I) + outlier_fraction / outlier_area`, so a
gross outlier barely moves the estimate; weights are kept in the log domain and the set is
resampled (`resampling`) when the effective sample size falls below `ess_fraction`·N. The
filter starts at the first measurement (velocity std `initial_velocity_std`); earlier rows are
NaN. Deterministic for a `seed`. The speed–accuracy knob is `particles`.

Outputs: `states`, N × 4 weighted means; `positions`, N × 2; `metrics`: `frames`, `updates`,
`missing`, `resamplings`, `mean_ess` (mean effective sample size after updates),
`log_likelihood` (sum of the log marginal likelihood estimates).

Example:
    "pf": (op: "video.particle_filter", inputs: { "measurements": "track.positions" },
           params: (particles: 2000, measurement_std: 2.0, outlier_fraction: 0.1, seed: 7)),
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
            PortSpec::new(
                "states",
                PortType::Matrix,
                "N × 4 state estimates (x, y, vx, vy).",
            ),
            PortSpec::new("positions", PortType::Matrix, "N × 2 position estimates."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "Counts and sample-size statistics.",
            ),
        ]
    }

    fn new(p: ParticleParams) -> Result<Self, String> {
        let finite = [
            p.dt_s,
            p.process_std,
            p.measurement_std,
            p.initial_velocity_std,
            p.outlier_area,
        ]
        .iter()
        .all(|v| v.is_finite());
        if !finite {
            return Err("noise levels, `dt_s` and `outlier_area` must be finite".into());
        }
        if p.outlier_fraction >= 1.0 {
            return Err("`outlier_fraction` must be below 1".into());
        }
        Ok(ParticleTrack { params: p })
    }
}

impl Operator for ParticleTrack {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let p = &self.params;
        let (frames, rows) = track_measurements(inputs)?;
        let missing = rows.iter().filter(|r| r.is_none()).count();
        let mut states = vec![f64::NAN; frames * 4];
        let (mut updates, mut resamplings, mut ess_sum, mut log_likelihood) =
            (0usize, 0usize, 0.0, 0.0);
        let scheme = match p.resampling {
            ResamplingName::Multinomial => Resampling::Multinomial,
            ResamplingName::Systematic => Resampling::Systematic,
            ResamplingName::Stratified => Resampling::Stratified,
            ResamplingName::Residual => Resampling::Residual,
        };
        let fail = |e: super::filters::FilterError| OpError::failed(e.to_string());
        if let Some((first, Some(z0))) = rows.iter().enumerate().find(|(_, r)| r.is_some()) {
            // Initial particles around the first measurement, from a seed of their own.
            let mut init = SplitMix64::new(p.seed ^ 0x9e37_79b9_7f4a_7c15);
            let particles = (0..p.particles)
                .map(|_| {
                    DVector::from_vec(vec![
                        init.normal(z0[0], p.measurement_std),
                        init.normal(z0[1], p.measurement_std),
                        init.normal(0.0, p.initial_velocity_std),
                        init.normal(0.0, p.initial_velocity_std),
                    ])
                })
                .collect();
            let mut pf = ParticleFilter::new(particles, p.seed).map_err(fail)?;
            let (dt, sa) = (p.dt_s, p.process_std);
            let variance = p.measurement_std * p.measurement_std;
            let log_gauss_norm = -(2.0 * std::f64::consts::PI * variance).ln();
            let log_inlier = (1.0 - p.outlier_fraction).ln();
            let log_clutter = if p.outlier_fraction > 0.0 {
                p.outlier_fraction.ln() - p.outlier_area.ln()
            } else {
                f64::NEG_INFINITY
            };
            for (k, row) in rows.iter().enumerate().skip(first) {
                if k > first {
                    pf.predict(|x, rng| {
                        let (ax, ay) = (rng.normal(0.0, sa), rng.normal(0.0, sa));
                        DVector::from_vec(vec![
                            x[0] + x[2] * dt + 0.5 * ax * dt * dt,
                            x[1] + x[3] * dt + 0.5 * ay * dt * dt,
                            x[2] + ax * dt,
                            x[3] + ay * dt,
                        ])
                    })
                    .map_err(fail)?;
                }
                if let Some(m) = row {
                    let ell = pf
                        .update(|x| {
                            let d2 = (m[0] - x[0]).powi(2) + (m[1] - x[1]).powi(2);
                            let inlier = log_inlier + log_gauss_norm - 0.5 * d2 / variance;
                            log_sum_exp(inlier, log_clutter)
                        })
                        .map_err(fail)?;
                    log_likelihood += ell;
                    updates += 1;
                    ess_sum += pf.effective_sample_size();
                }
                let mean = pf.mean();
                states[k * 4..k * 4 + 4].copy_from_slice(mean.as_slice());
                if pf.resample_if_with(p.ess_fraction, scheme).map_err(fail)? {
                    resamplings += 1;
                }
            }
        }
        let mut metrics = Metrics::new();
        metrics.insert("frames".into(), frames as f64);
        metrics.insert("updates".into(), updates as f64);
        metrics.insert("missing".into(), missing as f64);
        metrics.insert("resamplings".into(), resamplings as f64);
        metrics.insert("log_likelihood".into(), log_likelihood);
        if updates > 0 {
            metrics.insert("mean_ess".into(), ess_sum / updates as f64);
        }
        track_outputs(frames, 4, states, metrics)
    }
}

/// log(eᵃ + eᵇ) without overflow; −∞ terms drop out.
fn log_sum_exp(a: f64, b: f64) -> f64 {
    let hi = a.max(b);
    if hi == f64::NEG_INFINITY {
        return hi;
    }
    hi + ((a - hi).exp() + (b - hi).exp()).ln()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use std::sync::Arc;

    use ocellus_engine::op::Op;
    use ocellus_engine::value::{Matrix, Value};

    use super::super::kalman::{KalmanParams, KalmanTrack};
    use super::*;

    fn ctx() -> RunContext {
        RunContext {
            node: "pf".into(),
            threads: 1,
            element: None,
        }
    }

    fn run_op<O: Op + Operator>(op: &O, z: &Matrix) -> Outputs {
        let specs = O::inputs();
        let values = [Some(Value::Matrix(Arc::new(z.clone())))];
        op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap()
    }

    fn track(frames: usize, outliers: bool) -> (Vec<[f64; 2]>, Matrix) {
        let mut rng = SplitMix64::new(11);
        let truth: Vec<[f64; 2]> = (0..frames)
            .map(|k| [100.0 + 2.0 * k as f64, 300.0 - 1.0 * k as f64])
            .collect();
        let mut data = Vec::new();
        for (k, t) in truth.iter().enumerate() {
            if k % 13 == 4 {
                data.extend([f64::NAN, f64::NAN]);
            } else if outliers && k % 10 == 7 {
                data.extend([
                    t[0] + 150.0 * rng.normal(0.0, 1.0),
                    t[1] + 150.0 * rng.normal(0.0, 1.0),
                ]);
            } else {
                data.extend([t[0] + rng.normal(0.0, 2.0), t[1] + rng.normal(0.0, 2.0)]);
            }
        }
        (truth, Matrix::new(frames, 2, data).unwrap())
    }

    fn rmse(out: &Outputs, truth: &[[f64; 2]]) -> f64 {
        let Some(Value::Matrix(p)) = out.get("positions") else {
            panic!()
        };
        let skip = 10;
        let sum: f64 = truth
            .iter()
            .enumerate()
            .skip(skip)
            .map(|(k, t)| {
                (p.get(k, 0).unwrap() - t[0]).powi(2) + (p.get(k, 1).unwrap() - t[1]).powi(2)
            })
            .sum();
        (sum / (truth.len() - skip) as f64).sqrt()
    }

    #[test]
    fn matches_the_kalman_filter_on_clean_data_and_beats_it_with_outliers() {
        let pf_params = ParticleParams {
            particles: 2000,
            measurement_std: 2.0,
            process_std: 0.05,
            outlier_fraction: 0.1,
            ..ParticleParams::default()
        };
        let kf_params = KalmanParams {
            measurement_std: 2.0,
            process_std: 0.05,
            ..KalmanParams::default()
        };
        let pf = ParticleTrack::new(pf_params).unwrap();
        let kf = KalmanTrack::new(kf_params).unwrap();
        let (truth, clean) = track(150, false);
        let (pf_clean, kf_clean) = (
            rmse(&run_op(&pf, &clean), &truth),
            rmse(&run_op(&kf, &clean), &truth),
        );
        let (truth, dirty) = track(150, true);
        let (pf_dirty, kf_dirty) = (
            rmse(&run_op(&pf, &dirty), &truth),
            rmse(&run_op(&kf, &dirty), &truth),
        );
        println!(
            "RMSE clean: PF {pf_clean:.3}, KF {kf_clean:.3}; 10 % outliers: PF {pf_dirty:.3}, KF {kf_dirty:.3}"
        );
        assert!(pf_clean < 1.5 * kf_clean, "{pf_clean} vs {kf_clean}");
        assert!(pf_dirty < 0.5 * kf_dirty, "{pf_dirty} vs {kf_dirty}");
    }

    #[test]
    fn deterministic_for_a_seed_and_reports_counts() {
        let (_, z) = track(60, true);
        let op = ParticleTrack::new(ParticleParams {
            particles: 300,
            ..ParticleParams::default()
        })
        .unwrap();
        let a = run_op(&op, &z);
        let b = run_op(&op, &z);
        assert_eq!(a.get("states"), b.get("states"));
        let other = ParticleTrack::new(ParticleParams {
            particles: 300,
            seed: 2,
            ..ParticleParams::default()
        })
        .unwrap();
        assert_ne!(run_op(&other, &z).get("states"), a.get("states"));
        let Some(Value::Metrics(m)) = a.get("metrics") else {
            panic!()
        };
        assert_eq!(m["missing"], 5.0);
        assert_eq!(m["updates"], 55.0);
        assert!(m["mean_ess"] > 0.0 && m["mean_ess"] <= 300.0);
        assert!(
            ParticleTrack::new(ParticleParams {
                outlier_fraction: 1.0,
                ..ParticleParams::default()
            })
            .is_err()
        );
    }

    #[test]
    fn log_sum_exp_is_stable() {
        assert_eq!(
            log_sum_exp(f64::NEG_INFINITY, f64::NEG_INFINITY),
            f64::NEG_INFINITY
        );
        assert!((log_sum_exp(-1000.0, -1000.0) - (-1000.0 + 2f64.ln())).abs() < 1e-12);
        assert_eq!(log_sum_exp(0.0, f64::NEG_INFINITY), 0.0);
    }
}
