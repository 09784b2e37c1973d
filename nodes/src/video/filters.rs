//! State estimators for tracking: a linear Kalman filter with a
//! Rauch–Tung–Striebel smoother, an extended Kalman filter, and a
//! sequential-importance-resampling particle filter.
//!
//! Everything works in `f64` on [`nalgebra`] dynamic matrices and vectors.
//!
//! # Methods and references
//!
//! * [`KalmanFilter`]: the linear discrete-time Kalman filter,
//!   R. E. Kalman, "A New Approach to Linear Filtering and Prediction
//!   Problems", *Trans. ASME J. Basic Engineering* 82 (1960). The covariance
//!   update uses the Joseph stabilised form (R. S. Bucy and P. D. Joseph,
//!   *Filtering for Stochastic Processes with Applications to Guidance*, 1968),
//!   and the innovation covariance is factorised by Cholesky rather than
//!   inverted.
//! * Tracking models ([`KalmanFilter::constant_velocity_2d`],
//!   [`KalmanFilter::constant_acceleration_2d`]): the discrete white-noise
//!   acceleration and discrete Wiener-process acceleration models of
//!   Y. Bar-Shalom, X. R. Li and T. Kirubarajan, *Estimation with Applications
//!   to Tracking and Navigation* (Wiley, 2001), section 6.3.
//! * [`rts_smooth`]: the fixed-interval smoother of H. E. Rauch, F. Tung and
//!   C. T. Striebel, "Maximum Likelihood Estimates of Linear Dynamic Systems",
//!   *AIAA Journal* 3(8) (1965).
//! * [`ExtendedKalmanFilter`]: first-order linearisation of nonlinear motion and
//!   measurement functions around the current estimate (Bar-Shalom et al. 2001,
//!   chapter 10), with a caller-supplied residual function for angular
//!   measurements.
//! * [`ParticleFilter`]: sequential importance resampling, N. J. Gordon,
//!   D. J. Salmond and A. F. M. Smith, "Novel approach to nonlinear/non-Gaussian
//!   Bayesian state estimation", *IEE Proceedings F* 140(2) (1993). Stratified
//!   and systematic resampling follow G. Kitagawa, *J. Comput. Graph. Statist.*
//!   5(1) (1996); residual resampling follows J. S. Liu and R. Chen,
//!   *J. Amer. Statist. Assoc.* 93 (1998).
//! * [`SplitMix64`]: the SplitMix64 generator of G. L. Steele, D. Lea and
//!   C. H. Flood, "Fast Splittable Pseudorandom Number Generators" (OOPSLA 2014),
//!   with normal variates by the Box–Muller transform (G. E. P. Box and
//!   M. E. Muller, *Ann. Math. Statist.* 29 (1958)).
//!
//! All computations are deterministic: the particle filter draws only from the
//! [`SplitMix64`] generator it owns, seeded explicitly by the caller.

use nalgebra::{DMatrix, DVector, Dyn, linalg::Cholesky};
use std::f64::consts::{PI, TAU};

/// Relative tolerance for the symmetry check of covariance inputs.
const SYMMETRY_RELATIVE_TOLERANCE: f64 = 1e-9;
/// Relative diagonal jitter used when checking positive semi-definiteness.
const PSD_RELATIVE_JITTER: f64 = 1e-9;

/// Errors reported by the filters in this module.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum FilterError {
    /// A matrix or vector does not have the shape the model requires.
    #[error(
        "dimension mismatch for {name}: expected {expected_rows}x{expected_cols}, got {actual_rows}x{actual_cols}"
    )]
    DimensionMismatch {
        /// Which input (for example `"H (measurement matrix)"`).
        name: &'static str,
        /// Rows the model requires.
        expected_rows: usize,
        /// Columns the model requires (1 for vectors).
        expected_cols: usize,
        /// Rows actually supplied.
        actual_rows: usize,
        /// Columns actually supplied (1 for vectors).
        actual_cols: usize,
    },
    /// An input or a result contains NaN or an infinity.
    #[error("{name} contains a non-finite value (NaN or infinity)")]
    NonFinite {
        /// Which input or result.
        name: &'static str,
    },
    /// A covariance input is not symmetric to the relative tolerance.
    #[error("{name} is not symmetric (largest relative asymmetry {relative_asymmetry:e})")]
    NotSymmetric {
        /// Which input.
        name: &'static str,
        /// max |M_ij - M_ji| / max |M_ij|.
        relative_asymmetry: f64,
    },
    /// A covariance input is not positive semi-definite.
    #[error("{name} is not positive semi-definite")]
    NotPositiveSemiDefinite {
        /// Which input.
        name: &'static str,
    },
    /// The innovation covariance S = H P Hᵀ + R has no Cholesky factor.
    #[error("innovation covariance S = H P H^T + R is not positive definite")]
    InnovationNotPositiveDefinite,
    /// A smoother input covariance (the predicted covariance) has no Cholesky factor.
    #[error("predicted covariance at step {step} is not positive definite")]
    PredictedCovarianceNotPositiveDefinite {
        /// Index of the offending step.
        step: usize,
    },
    /// Every particle has zero likelihood (all log-weights would be −∞).
    #[error("degenerate particle weights: every particle has zero likelihood")]
    Degenerate,
    /// A particle filter was given no particles.
    #[error("particle set is empty")]
    EmptyParticleSet,
    /// A scalar parameter is out of its valid range.
    #[error("invalid parameter {name}: {reason}")]
    InvalidParameter {
        /// Which parameter.
        name: &'static str,
        /// What is required of it.
        reason: &'static str,
    },
}

/// Result of a measurement update: the innovation and its statistics.
#[derive(Debug, Clone, PartialEq)]
pub struct Innovation {
    /// Measurement residual y = z − ẑ (after any residual function, e.g. angle wrapping).
    pub residual: DVector<f64>,
    /// Innovation covariance S = H P⁻ Hᵀ + R.
    pub covariance: DMatrix<f64>,
    /// Squared Mahalanobis distance yᵀ S⁻¹ y (chi-square with m dof if the model is right).
    pub mahalanobis_squared: f64,
    /// Gaussian log-likelihood log N(y; 0, S) of the measurement.
    pub log_likelihood: f64,
}

// ---------------------------------------------------------------------------
// Validation helpers
// ---------------------------------------------------------------------------

fn check_matrix_shape(
    name: &'static str,
    matrix: &DMatrix<f64>,
    rows: usize,
    cols: usize,
) -> Result<(), FilterError> {
    if matrix.nrows() != rows || matrix.ncols() != cols {
        return Err(FilterError::DimensionMismatch {
            name,
            expected_rows: rows,
            expected_cols: cols,
            actual_rows: matrix.nrows(),
            actual_cols: matrix.ncols(),
        });
    }
    Ok(())
}

fn check_vector_len(
    name: &'static str,
    vector: &DVector<f64>,
    len: usize,
) -> Result<(), FilterError> {
    if vector.len() != len {
        return Err(FilterError::DimensionMismatch {
            name,
            expected_rows: len,
            expected_cols: 1,
            actual_rows: vector.len(),
            actual_cols: 1,
        });
    }
    Ok(())
}

fn check_finite<'a>(
    name: &'static str,
    values: impl IntoIterator<Item = &'a f64>,
) -> Result<(), FilterError> {
    if values.into_iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(FilterError::NonFinite { name })
    }
}

/// Checks shape `dim × dim`, finiteness, symmetry to a relative tolerance and
/// positive semi-definiteness (a Cholesky factor of `M + εI` exists, with ε
/// relative to the largest entry).
fn check_covariance(
    name: &'static str,
    matrix: &DMatrix<f64>,
    dim: usize,
) -> Result<(), FilterError> {
    check_matrix_shape(name, matrix, dim, dim)?;
    check_finite(name, matrix.iter())?;
    let scale = matrix.amax();
    if scale > 0.0 {
        let asymmetry = (matrix - matrix.transpose()).amax() / scale;
        if asymmetry > SYMMETRY_RELATIVE_TOLERANCE {
            return Err(FilterError::NotSymmetric {
                name,
                relative_asymmetry: asymmetry,
            });
        }
    }
    let jitter = PSD_RELATIVE_JITTER * scale + f64::MIN_POSITIVE;
    let shifted = symmetrize(matrix) + DMatrix::identity(dim, dim) * jitter;
    if shifted.cholesky().is_none() {
        return Err(FilterError::NotPositiveSemiDefinite { name });
    }
    Ok(())
}

fn check_non_negative(name: &'static str, value: f64) -> Result<(), FilterError> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(FilterError::InvalidParameter {
            name,
            reason: "must be finite and non-negative",
        })
    }
}

fn check_positive(name: &'static str, value: f64) -> Result<(), FilterError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(FilterError::InvalidParameter {
            name,
            reason: "must be finite and positive",
        })
    }
}

/// (M + Mᵀ) / 2.
fn symmetrize(matrix: &DMatrix<f64>) -> DMatrix<f64> {
    (matrix + matrix.transpose()) * 0.5
}

// ---------------------------------------------------------------------------
// Shared Gaussian measurement update (Kalman and extended Kalman)
// ---------------------------------------------------------------------------

/// Innovation statistics together with the Cholesky factor of S.
struct InnovationWithFactor {
    innovation: Innovation,
    s_cholesky: Cholesky<f64, Dyn>,
}

/// Forms S = H P Hᵀ + R, factorises it, and computes yᵀS⁻¹y and log N(y; 0, S).
fn innovation_statistics(
    residual: DVector<f64>,
    covariance: &DMatrix<f64>,
    observation: &DMatrix<f64>,
    measurement_noise: &DMatrix<f64>,
) -> Result<InnovationWithFactor, FilterError> {
    let s = symmetrize(&(observation * covariance * observation.transpose() + measurement_noise));
    check_finite("innovation covariance S", s.iter())?;
    let s_cholesky = s
        .clone()
        .cholesky()
        .ok_or(FilterError::InnovationNotPositiveDefinite)?;
    let whitened = s_cholesky.solve(&residual);
    let mahalanobis_squared = residual.dot(&whitened).max(0.0);
    let log_det_s: f64 = s_cholesky
        .l_dirty()
        .diagonal()
        .iter()
        .map(|d| 2.0 * d.ln())
        .sum();
    let m = residual.len() as f64;
    let log_likelihood = -0.5 * (mahalanobis_squared + log_det_s + m * TAU.ln());
    if !mahalanobis_squared.is_finite() || !log_likelihood.is_finite() {
        return Err(FilterError::InnovationNotPositiveDefinite);
    }
    Ok(InnovationWithFactor {
        innovation: Innovation {
            residual,
            covariance: s,
            mahalanobis_squared,
            log_likelihood,
        },
        s_cholesky,
    })
}

/// Joseph-form update. Returns the posterior (x, P) without modifying inputs.
///
/// K = P Hᵀ S⁻¹ is obtained as Kᵀ = S⁻¹ (H P) by Cholesky solves, then
/// x⁺ = x + K y and P⁺ = (I − K H) P (I − K H)ᵀ + K R Kᵀ, symmetrised.
fn joseph_update(
    state: &DVector<f64>,
    covariance: &DMatrix<f64>,
    observation: &DMatrix<f64>,
    measurement_noise: &DMatrix<f64>,
    factored: &InnovationWithFactor,
) -> Result<(DVector<f64>, DMatrix<f64>), FilterError> {
    let n = state.len();
    let gain = factored
        .s_cholesky
        .solve(&(observation * covariance))
        .transpose();
    let new_state = state + &gain * &factored.innovation.residual;
    let i_minus_kh = DMatrix::identity(n, n) - &gain * observation;
    let joseph = &i_minus_kh * covariance * i_minus_kh.transpose()
        + &gain * measurement_noise * gain.transpose();
    let new_covariance = symmetrize(&joseph);
    check_finite("updated state", new_state.iter())?;
    check_finite("updated covariance", new_covariance.iter())?;
    Ok((new_state, new_covariance))
}

// ---------------------------------------------------------------------------
// Linear Kalman filter
// ---------------------------------------------------------------------------

/// Linear discrete-time Kalman filter (Kalman 1960).
///
/// Model: xₖ = F xₖ₋₁ + wₖ, wₖ ~ N(0, Q); zₖ = H xₖ + vₖ, vₖ ~ N(0, R).
/// The state x has dimension n and the measurement z dimension m.
///
/// The measurement update uses the Joseph form
/// P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ, which stays symmetric positive
/// semi-definite for any gain, and solves with a Cholesky factor of the
/// innovation covariance S instead of forming S⁻¹. P is symmetrised after
/// every prediction and update.
#[derive(Debug, Clone, PartialEq)]
pub struct KalmanFilter {
    state: DVector<f64>,
    covariance: DMatrix<f64>,
    transition: DMatrix<f64>,
    process_noise: DMatrix<f64>,
    observation: DMatrix<f64>,
    measurement_noise: DMatrix<f64>,
}

/// One filtering step recorded for smoothing: the prior after prediction and
/// the posterior after the (optional) measurement update.
#[derive(Debug, Clone, PartialEq)]
pub struct FilteredStep {
    /// x̂ₖ|ₖ₋₁, the predicted state.
    pub predicted_state: DVector<f64>,
    /// Pₖ|ₖ₋₁, the predicted covariance.
    pub predicted_covariance: DMatrix<f64>,
    /// x̂ₖ|ₖ, the filtered state (equal to the prediction when no measurement was given).
    pub filtered_state: DVector<f64>,
    /// Pₖ|ₖ, the filtered covariance.
    pub filtered_covariance: DMatrix<f64>,
    /// The innovation of the update, or `None` when the step had no measurement.
    pub innovation: Option<Innovation>,
}

/// A smoothed estimate x̂ₖ|N, Pₖ|N.
#[derive(Debug, Clone, PartialEq)]
pub struct SmoothedState {
    /// Smoothed state mean.
    pub state: DVector<f64>,
    /// Smoothed state covariance.
    pub covariance: DMatrix<f64>,
}

impl KalmanFilter {
    /// Creates a filter from the initial state `x0` (n), its covariance `p0`
    /// (n×n), the transition `f` (n×n), process noise `q` (n×n), measurement
    /// matrix `h` (m×n) and measurement noise `r` (m×m).
    ///
    /// All inputs must be finite; `p0`, `q` and `r` must be symmetric to a
    /// relative tolerance of 1e-9 and positive semi-definite (a Cholesky factor
    /// of M + εI exists with ε = 1e-9·max|Mᵢⱼ|).
    pub fn new(
        x0: DVector<f64>,
        p0: DMatrix<f64>,
        f: DMatrix<f64>,
        q: DMatrix<f64>,
        h: DMatrix<f64>,
        r: DMatrix<f64>,
    ) -> Result<Self, FilterError> {
        let n = x0.len();
        if n == 0 {
            return Err(FilterError::InvalidParameter {
                name: "x0",
                reason: "state dimension must be at least 1",
            });
        }
        let m = h.nrows();
        if m == 0 {
            return Err(FilterError::InvalidParameter {
                name: "H (measurement matrix)",
                reason: "measurement dimension must be at least 1",
            });
        }
        check_finite("x0 (initial state)", x0.iter())?;
        check_covariance("P0 (initial covariance)", &p0, n)?;
        check_matrix_shape("F (transition matrix)", &f, n, n)?;
        check_finite("F (transition matrix)", f.iter())?;
        check_covariance("Q (process noise)", &q, n)?;
        check_matrix_shape("H (measurement matrix)", &h, m, n)?;
        check_finite("H (measurement matrix)", h.iter())?;
        check_covariance("R (measurement noise)", &r, m)?;
        Ok(Self {
            state: x0,
            covariance: symmetrize(&p0),
            transition: f,
            process_noise: symmetrize(&q),
            observation: h,
            measurement_noise: symmetrize(&r),
        })
    }

    /// Planar constant-velocity target, state `[x, y, vx, vy]`, measurement `[x, y]`.
    ///
    /// Process noise follows the discrete white-noise acceleration model
    /// (Bar-Shalom, Li & Kirubarajan 2001, §6.3.2): each axis receives an
    /// acceleration aₖ ~ N(0, σₐ²) held constant over the interval, so with
    /// Γ = [dt²/2, dt]ᵀ the per-axis noise is Q = Γ Γᵀ σₐ². Measurements are
    /// the positions with independent noise of standard deviation
    /// `measurement_std`. `x0`/`p0` are the prior (4 and 4×4).
    pub fn constant_velocity_2d(
        dt: f64,
        process_accel_std: f64,
        measurement_std: f64,
        x0: DVector<f64>,
        p0: DMatrix<f64>,
    ) -> Result<Self, FilterError> {
        check_positive("dt", dt)?;
        check_non_negative("process_accel_std", process_accel_std)?;
        check_positive("measurement_std", measurement_std)?;
        let (f, q) = constant_velocity_2d_model(dt, process_accel_std);
        let mut h = DMatrix::zeros(2, 4);
        h[(0, 0)] = 1.0;
        h[(1, 1)] = 1.0;
        let r = DMatrix::identity(2, 2) * (measurement_std * measurement_std);
        Self::new(x0, p0, f, q, h, r)
    }

    /// Planar constant-acceleration target, state `[x, y, vx, vy, ax, ay]`,
    /// measurement `[x, y]`.
    ///
    /// Process noise follows the discrete Wiener-process acceleration model
    /// (Bar-Shalom, Li & Kirubarajan 2001, §6.3.3): the acceleration of each
    /// axis changes by an increment of standard deviation
    /// `accel_increment_std` per step, entering through Γ = [dt²/2, dt, 1]ᵀ,
    /// so per axis Q = Γ Γᵀ σ². `x0`/`p0` are the prior (6 and 6×6).
    pub fn constant_acceleration_2d(
        dt: f64,
        accel_increment_std: f64,
        measurement_std: f64,
        x0: DVector<f64>,
        p0: DMatrix<f64>,
    ) -> Result<Self, FilterError> {
        check_positive("dt", dt)?;
        check_non_negative("accel_increment_std", accel_increment_std)?;
        check_positive("measurement_std", measurement_std)?;
        let (f, q) = constant_acceleration_2d_model(dt, accel_increment_std);
        let mut h = DMatrix::zeros(2, 6);
        h[(0, 0)] = 1.0;
        h[(1, 1)] = 1.0;
        let r = DMatrix::identity(2, 2) * (measurement_std * measurement_std);
        Self::new(x0, p0, f, q, h, r)
    }

    /// Time update with the stored model: x ← F x, P ← F P Fᵀ + Q.
    pub fn predict(&mut self) -> Result<(), FilterError> {
        let (state, covariance) = predict_gaussian(
            &self.state,
            &self.covariance,
            &self.transition,
            &self.process_noise,
        )?;
        self.state = state;
        self.covariance = covariance;
        Ok(())
    }

    /// Time update with a one-off transition `f` and process noise `q` (for
    /// example a varying time step). The stored F and Q are not replaced.
    pub fn predict_with(&mut self, f: &DMatrix<f64>, q: &DMatrix<f64>) -> Result<(), FilterError> {
        let n = self.state.len();
        check_matrix_shape("F (transition matrix)", f, n, n)?;
        check_finite("F (transition matrix)", f.iter())?;
        check_covariance("Q (process noise)", q, n)?;
        let (state, covariance) = predict_gaussian(&self.state, &self.covariance, f, q)?;
        self.state = state;
        self.covariance = covariance;
        Ok(())
    }

    /// Measurement update with the stored H and R (Joseph form, Cholesky of S).
    ///
    /// On error the filter is unchanged.
    pub fn update(&mut self, z: &DVector<f64>) -> Result<Innovation, FilterError> {
        let factored = self.innovation_for(z, &self.observation, &self.measurement_noise)?;
        self.apply(&factored, None)?;
        Ok(factored.innovation)
    }

    /// Measurement update with a one-off measurement matrix `h` (m×n) and
    /// noise `r` (m×m); the stored H and R are not replaced.
    pub fn update_with(
        &mut self,
        z: &DVector<f64>,
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<Innovation, FilterError> {
        let m = z.len();
        check_matrix_shape("H (measurement matrix)", h, m, self.state.len())?;
        check_finite("H (measurement matrix)", h.iter())?;
        check_covariance("R (measurement noise)", r, m)?;
        let factored = self.innovation_for(z, h, r)?;
        self.apply(&factored, Some((h, r)))?;
        Ok(factored.innovation)
    }

    /// Validation-gated update: the measurement is applied only when its
    /// squared Mahalanobis distance yᵀ S⁻¹ y is at most `gate_chi2` (a
    /// chi-square quantile with m degrees of freedom, e.g. 13.82 for 99.9 %
    /// with m = 2). Returns `Ok(None)` and leaves the filter unchanged when
    /// the measurement is rejected.
    pub fn update_gated(
        &mut self,
        z: &DVector<f64>,
        gate_chi2: f64,
    ) -> Result<Option<Innovation>, FilterError> {
        check_non_negative("gate_chi2", gate_chi2)?;
        let factored = self.innovation_for(z, &self.observation, &self.measurement_noise)?;
        if factored.innovation.mahalanobis_squared > gate_chi2 {
            return Ok(None);
        }
        self.apply(&factored, None)?;
        Ok(Some(factored.innovation))
    }

    /// Predicts, then updates with `z` when given, and returns the record the
    /// [`rts_smooth`] smoother needs.
    pub fn step(&mut self, z: Option<&DVector<f64>>) -> Result<FilteredStep, FilterError> {
        let before = self.clone();
        self.predict()?;
        let predicted_state = self.state.clone();
        let predicted_covariance = self.covariance.clone();
        let innovation = match z {
            Some(z) => match self.update(z) {
                Ok(innovation) => Some(innovation),
                Err(error) => {
                    *self = before;
                    return Err(error);
                }
            },
            None => None,
        };
        Ok(FilteredStep {
            predicted_state,
            predicted_covariance,
            filtered_state: self.state.clone(),
            filtered_covariance: self.covariance.clone(),
            innovation,
        })
    }

    /// Current state estimate x̂.
    pub fn state(&self) -> &DVector<f64> {
        &self.state
    }

    /// Current state covariance P.
    pub fn covariance(&self) -> &DMatrix<f64> {
        &self.covariance
    }

    /// Stored transition matrix F.
    pub fn transition(&self) -> &DMatrix<f64> {
        &self.transition
    }

    /// Stored process noise covariance Q.
    pub fn process_noise(&self) -> &DMatrix<f64> {
        &self.process_noise
    }

    /// Stored measurement matrix H.
    pub fn observation(&self) -> &DMatrix<f64> {
        &self.observation
    }

    /// Stored measurement noise covariance R.
    pub fn measurement_noise(&self) -> &DMatrix<f64> {
        &self.measurement_noise
    }

    fn innovation_for(
        &self,
        z: &DVector<f64>,
        h: &DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<InnovationWithFactor, FilterError> {
        check_vector_len("z (measurement)", z, h.nrows())?;
        check_finite("z (measurement)", z.iter())?;
        let residual = z - h * &self.state;
        innovation_statistics(residual, &self.covariance, h, r)
    }

    fn apply(
        &mut self,
        factored: &InnovationWithFactor,
        model: Option<(&DMatrix<f64>, &DMatrix<f64>)>,
    ) -> Result<(), FilterError> {
        let (h, r) = model.unwrap_or((&self.observation, &self.measurement_noise));
        let (state, covariance) = joseph_update(&self.state, &self.covariance, h, r, factored)?;
        self.state = state;
        self.covariance = covariance;
        Ok(())
    }
}

fn predict_gaussian(
    state: &DVector<f64>,
    covariance: &DMatrix<f64>,
    transition: &DMatrix<f64>,
    process_noise: &DMatrix<f64>,
) -> Result<(DVector<f64>, DMatrix<f64>), FilterError> {
    let new_state = transition * state;
    let new_covariance =
        symmetrize(&(transition * covariance * transition.transpose() + process_noise));
    check_finite("predicted state", new_state.iter())?;
    check_finite("predicted covariance", new_covariance.iter())?;
    Ok((new_state, new_covariance))
}

/// Transition F and process noise Q of the planar constant-velocity model
/// with discrete white-noise acceleration (state `[x, y, vx, vy]`), as used by
/// [`KalmanFilter::constant_velocity_2d`].
pub fn constant_velocity_2d_model(dt: f64, process_accel_std: f64) -> (DMatrix<f64>, DMatrix<f64>) {
    let variance = process_accel_std * process_accel_std;
    let mut f = DMatrix::identity(4, 4);
    let mut q = DMatrix::zeros(4, 4);
    let gamma = [dt * dt / 2.0, dt];
    for axis in 0..2 {
        let idx = [axis, axis + 2];
        f[(axis, axis + 2)] = dt;
        for (a, &row) in idx.iter().enumerate() {
            for (b, &col) in idx.iter().enumerate() {
                q[(row, col)] = gamma[a] * gamma[b] * variance;
            }
        }
    }
    (f, q)
}

/// Transition F and process noise Q of the planar constant-acceleration model
/// with discrete Wiener-process acceleration (state `[x, y, vx, vy, ax, ay]`),
/// as used by [`KalmanFilter::constant_acceleration_2d`].
pub fn constant_acceleration_2d_model(
    dt: f64,
    accel_increment_std: f64,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let variance = accel_increment_std * accel_increment_std;
    let mut f = DMatrix::identity(6, 6);
    let mut q = DMatrix::zeros(6, 6);
    let gamma = [dt * dt / 2.0, dt, 1.0];
    for axis in 0..2 {
        let idx = [axis, axis + 2, axis + 4];
        f[(axis, axis + 2)] = dt;
        f[(axis, axis + 4)] = dt * dt / 2.0;
        f[(axis + 2, axis + 4)] = dt;
        for (a, &row) in idx.iter().enumerate() {
            for (b, &col) in idx.iter().enumerate() {
                q[(row, col)] = gamma[a] * gamma[b] * variance;
            }
        }
    }
    (f, q)
}

/// Rauch–Tung–Striebel fixed-interval smoother (Rauch, Tung & Striebel 1965)
/// for a constant transition matrix.
///
/// `steps[k]` holds the prediction x̂ₖ|ₖ₋₁, Pₖ|ₖ₋₁ and the filtered estimate
/// x̂ₖ|ₖ, Pₖ|ₖ of step k, as returned by [`KalmanFilter::step`]; step k+1 must
/// have been predicted from step k with `transition`. Going backwards,
/// Cₖ = Pₖ|ₖ Fᵀ Pₖ₊₁|ₖ⁻¹ (computed by a Cholesky solve),
/// x̂ₖ|N = x̂ₖ|ₖ + Cₖ (x̂ₖ₊₁|N − x̂ₖ₊₁|ₖ) and
/// Pₖ|N = Pₖ|ₖ + Cₖ (Pₖ₊₁|N − Pₖ₊₁|ₖ) Cₖᵀ. The last smoothed estimate equals
/// the last filtered one. An empty input gives an empty output.
pub fn rts_smooth(
    steps: &[FilteredStep],
    transition: &DMatrix<f64>,
) -> Result<Vec<SmoothedState>, FilterError> {
    rts_smooth_core(steps, |_| Some(transition))
}

/// Rauch–Tung–Striebel smoother with a time-varying transition:
/// `transitions[k]` is the F that predicted step k+1 from step k, so it has
/// `steps.len() − 1` entries. See [`rts_smooth`].
pub fn rts_smooth_time_varying(
    steps: &[FilteredStep],
    transitions: &[DMatrix<f64>],
) -> Result<Vec<SmoothedState>, FilterError> {
    let expected = steps.len().saturating_sub(1);
    if transitions.len() != expected {
        return Err(FilterError::DimensionMismatch {
            name: "transitions (one per consecutive step pair)",
            expected_rows: expected,
            expected_cols: 1,
            actual_rows: transitions.len(),
            actual_cols: 1,
        });
    }
    rts_smooth_core(steps, |k| transitions.get(k))
}

fn rts_smooth_core<'a>(
    steps: &[FilteredStep],
    transition_at: impl Fn(usize) -> Option<&'a DMatrix<f64>>,
) -> Result<Vec<SmoothedState>, FilterError> {
    let Some(last) = steps.last() else {
        return Ok(Vec::new());
    };
    let n = last.filtered_state.len();
    for step in steps {
        check_vector_len("filtered state", &step.filtered_state, n)?;
        check_vector_len("predicted state", &step.predicted_state, n)?;
        check_matrix_shape("filtered covariance", &step.filtered_covariance, n, n)?;
        check_matrix_shape("predicted covariance", &step.predicted_covariance, n, n)?;
    }
    let mut smoothed_reversed = Vec::with_capacity(steps.len());
    let mut next_smoothed = SmoothedState {
        state: last.filtered_state.clone(),
        covariance: last.filtered_covariance.clone(),
    };
    smoothed_reversed.push(next_smoothed.clone());
    for (k, pair) in steps.windows(2).enumerate().rev() {
        let [current, next] = pair else { continue };
        let transition = transition_at(k).ok_or(FilterError::DimensionMismatch {
            name: "transitions (one per consecutive step pair)",
            expected_rows: k + 1,
            expected_cols: 1,
            actual_rows: k,
            actual_cols: 1,
        })?;
        check_matrix_shape("F (transition matrix)", transition, n, n)?;
        let predicted_cholesky = symmetrize(&next.predicted_covariance)
            .cholesky()
            .ok_or(FilterError::PredictedCovarianceNotPositiveDefinite { step: k + 1 })?;
        // Cᵀ = P⁻ₖ₊₁⁻¹ F Pₖ|ₖ, since both covariances are symmetric.
        let gain = predicted_cholesky
            .solve(&(transition * &current.filtered_covariance))
            .transpose();
        let state =
            &current.filtered_state + &gain * (&next_smoothed.state - &next.predicted_state);
        let covariance = symmetrize(
            &(&current.filtered_covariance
                + &gain
                    * (&next_smoothed.covariance - &next.predicted_covariance)
                    * gain.transpose()),
        );
        check_finite("smoothed state", state.iter())?;
        check_finite("smoothed covariance", covariance.iter())?;
        next_smoothed = SmoothedState { state, covariance };
        smoothed_reversed.push(next_smoothed.clone());
    }
    smoothed_reversed.reverse();
    Ok(smoothed_reversed)
}

// ---------------------------------------------------------------------------
// Extended Kalman filter
// ---------------------------------------------------------------------------

/// Extended Kalman filter with user-supplied nonlinear motion and measurement
/// functions and their Jacobians (first-order EKF, Bar-Shalom et al. 2001, ch. 10).
///
/// Prediction: x ← f(x), P ← Fⱼ P Fⱼᵀ + Q with Fⱼ = ∂f/∂x at the prior mean.
/// Update: y = residual(z, h(x)), Hⱼ = ∂h/∂x at the predicted mean, then the
/// Joseph-form update as in [`KalmanFilter`]. Use [`numerical_jacobian`] when
/// no analytic Jacobian is available and [`wrap_angle`] in the residual
/// function for angular measurement components.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtendedKalmanFilter {
    state: DVector<f64>,
    covariance: DMatrix<f64>,
}

impl ExtendedKalmanFilter {
    /// Creates a filter with prior mean `x0` and covariance `p0` (finite,
    /// symmetric positive semi-definite).
    pub fn new(x0: DVector<f64>, p0: DMatrix<f64>) -> Result<Self, FilterError> {
        if x0.is_empty() {
            return Err(FilterError::InvalidParameter {
                name: "x0",
                reason: "state dimension must be at least 1",
            });
        }
        check_finite("x0 (initial state)", x0.iter())?;
        check_covariance("P0 (initial covariance)", &p0, x0.len())?;
        Ok(Self {
            state: x0,
            covariance: symmetrize(&p0),
        })
    }

    /// Time update with motion function `f`, its Jacobian `jacobian_f`
    /// (evaluated at the prior mean) and process noise `q`. On error the
    /// filter is unchanged.
    pub fn predict(
        &mut self,
        f: impl Fn(&DVector<f64>) -> DVector<f64>,
        jacobian_f: impl Fn(&DVector<f64>) -> DMatrix<f64>,
        q: &DMatrix<f64>,
    ) -> Result<(), FilterError> {
        let n = self.state.len();
        check_covariance("Q (process noise)", q, n)?;
        let jacobian = jacobian_f(&self.state);
        check_matrix_shape("jacobian of f", &jacobian, n, n)?;
        check_finite("jacobian of f", jacobian.iter())?;
        let predicted_state = f(&self.state);
        check_vector_len("f(x) (motion function output)", &predicted_state, n)?;
        check_finite("f(x) (motion function output)", predicted_state.iter())?;
        let predicted_covariance =
            symmetrize(&(&jacobian * &self.covariance * jacobian.transpose() + q));
        check_finite("predicted covariance", predicted_covariance.iter())?;
        self.state = predicted_state;
        self.covariance = predicted_covariance;
        Ok(())
    }

    /// Measurement update with measurement function `h`, its Jacobian
    /// `jacobian_h` (evaluated at the predicted mean) and noise `r`, using the
    /// plain residual z − h(x).
    pub fn update(
        &mut self,
        z: &DVector<f64>,
        h: impl Fn(&DVector<f64>) -> DVector<f64>,
        jacobian_h: impl Fn(&DVector<f64>) -> DMatrix<f64>,
        r: &DMatrix<f64>,
    ) -> Result<Innovation, FilterError> {
        self.update_with_residual(z, h, jacobian_h, r, |measured, predicted| {
            measured - predicted
        })
    }

    /// Measurement update with a custom residual `residual(z, h(x))`, e.g.
    /// wrapping bearing components with [`wrap_angle`]. Joseph form; on error
    /// the filter is unchanged.
    pub fn update_with_residual(
        &mut self,
        z: &DVector<f64>,
        h: impl Fn(&DVector<f64>) -> DVector<f64>,
        jacobian_h: impl Fn(&DVector<f64>) -> DMatrix<f64>,
        r: &DMatrix<f64>,
        residual: impl Fn(&DVector<f64>, &DVector<f64>) -> DVector<f64>,
    ) -> Result<Innovation, FilterError> {
        let n = self.state.len();
        let m = z.len();
        if m == 0 {
            return Err(FilterError::InvalidParameter {
                name: "z (measurement)",
                reason: "measurement dimension must be at least 1",
            });
        }
        check_finite("z (measurement)", z.iter())?;
        check_covariance("R (measurement noise)", r, m)?;
        let predicted_measurement = h(&self.state);
        check_vector_len(
            "h(x) (measurement function output)",
            &predicted_measurement,
            m,
        )?;
        check_finite(
            "h(x) (measurement function output)",
            predicted_measurement.iter(),
        )?;
        let jacobian = jacobian_h(&self.state);
        check_matrix_shape("jacobian of h", &jacobian, m, n)?;
        check_finite("jacobian of h", jacobian.iter())?;
        let y = residual(z, &predicted_measurement);
        check_vector_len("residual", &y, m)?;
        check_finite("residual", y.iter())?;
        let factored = innovation_statistics(y, &self.covariance, &jacobian, r)?;
        let (state, covariance) =
            joseph_update(&self.state, &self.covariance, &jacobian, r, &factored)?;
        self.state = state;
        self.covariance = covariance;
        Ok(factored.innovation)
    }

    /// Current state estimate.
    pub fn state(&self) -> &DVector<f64> {
        &self.state
    }

    /// Current state covariance.
    pub fn covariance(&self) -> &DMatrix<f64> {
        &self.covariance
    }
}

/// Central-difference Jacobian of `f` at `x`: column j is
/// (f(x + hⱼeⱼ) − f(x − hⱼeⱼ)) / (2hⱼ) with hⱼ = `step`·max(1, |xⱼ|), so
/// `step` is relative for large components and absolute for small ones
/// (1e-5 to 1e-6 suits smooth functions of order-one inputs). The error is
/// O(hⱼ²) from truncation plus O(ε/hⱼ) from rounding.
pub fn numerical_jacobian(
    f: impl Fn(&DVector<f64>) -> DVector<f64>,
    x: &DVector<f64>,
    step: f64,
) -> Result<DMatrix<f64>, FilterError> {
    check_positive("step", step)?;
    check_finite("x", x.iter())?;
    let n = x.len();
    let centre = f(x);
    let m = centre.len();
    let mut jacobian = DMatrix::zeros(m, n);
    for (j, &xj) in x.iter().enumerate() {
        let h = step * xj.abs().max(1.0);
        let mut forward = x.clone();
        let mut backward = x.clone();
        forward[j] = xj + h;
        backward[j] = xj - h;
        // Use the step that is actually representable.
        let width = forward[j] - backward[j];
        let f_forward = f(&forward);
        let f_backward = f(&backward);
        check_vector_len("f(x) (function output)", &f_forward, m)?;
        check_vector_len("f(x) (function output)", &f_backward, m)?;
        let column = (f_forward - f_backward) / width;
        check_finite("numerical jacobian", column.iter())?;
        jacobian.set_column(j, &column);
    }
    Ok(jacobian)
}

/// Wraps an angle in radians into [−π, π), e.g. for bearing residuals.
pub fn wrap_angle(angle: f64) -> f64 {
    (angle + PI).rem_euclid(TAU) - PI
}

// ---------------------------------------------------------------------------
// Random numbers
// ---------------------------------------------------------------------------

/// SplitMix64 pseudo-random generator (Steele, Lea & Flood 2014): a 64-bit
/// counter advanced by the golden-ratio increment and passed through a
/// bijective mixing function. Small, fast and fully deterministic for a given
/// seed; not cryptographically secure.
#[derive(Debug, Clone, PartialEq)]
pub struct SplitMix64 {
    state: u64,
    spare_normal: Option<f64>,
}

impl SplitMix64 {
    /// Creates a generator from an explicit seed.
    pub fn new(seed: u64) -> Self {
        Self {
            state: seed,
            spare_normal: None,
        }
    }

    /// Next 64 uniformly distributed bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform variate in [0, 1) with 53 random bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Standard normal variate by the Box–Muller transform; the second value
    /// of each pair is kept for the next call.
    pub fn standard_normal(&mut self) -> f64 {
        if let Some(spare) = self.spare_normal.take() {
            return spare;
        }
        let u1 = 1.0 - self.uniform(); // in (0, 1], so the logarithm is finite
        let u2 = self.uniform();
        let radius = (-2.0 * u1.ln()).sqrt();
        let angle = TAU * u2;
        self.spare_normal = Some(radius * angle.sin());
        radius * angle.cos()
    }

    /// Normal variate with the given mean and standard deviation.
    pub fn normal(&mut self, mean: f64, std_dev: f64) -> f64 {
        mean + std_dev * self.standard_normal()
    }
}

// ---------------------------------------------------------------------------
// Particle filter
// ---------------------------------------------------------------------------

/// Resampling scheme for [`ParticleFilter::resample`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Resampling {
    /// N independent draws from the weighted empirical distribution.
    Multinomial,
    /// One uniform offset u ~ U[0, 1/N), points u + i/N (Kitagawa 1996). Lowest variance in practice.
    #[default]
    Systematic,
    /// One uniform point in each stratum [i/N, (i+1)/N) (Kitagawa 1996).
    Stratified,
    /// ⌊N wᵢ⌋ deterministic copies, the remainder drawn multinomially from the
    /// residual weights (Liu & Chen 1998).
    Residual,
}

/// Sequential importance resampling particle filter (Gordon, Salmond & Smith 1993).
///
/// Particles are state vectors of a common dimension with log-weights kept
/// normalised (log-sum-exp equal to zero). The filter owns a [`SplitMix64`]
/// generator seeded by the caller, which motion models draw from; the same
/// seed and the same calls give bit-identical particles.
#[derive(Debug, Clone, PartialEq)]
pub struct ParticleFilter {
    particles: Vec<DVector<f64>>,
    log_weights: Vec<f64>,
    rng: SplitMix64,
}

impl ParticleFilter {
    /// Creates a filter from an initial particle set with uniform weights and
    /// a generator seeded with `seed`. The set must be non-empty, of one
    /// dimension and finite.
    pub fn new(particles: Vec<DVector<f64>>, seed: u64) -> Result<Self, FilterError> {
        let Some(first) = particles.first() else {
            return Err(FilterError::EmptyParticleSet);
        };
        let dim = first.len();
        for particle in &particles {
            check_vector_len("particle", particle, dim)?;
            check_finite("particle", particle.iter())?;
        }
        let count = particles.len();
        Ok(Self {
            particles,
            log_weights: vec![-(count as f64).ln(); count],
            rng: SplitMix64::new(seed),
        })
    }

    /// Propagates every particle through `motion(particle, rng)`, which should
    /// sample from the transition density. Weights are unchanged. On error
    /// (wrong dimension or non-finite output) the particles are unchanged.
    pub fn predict(
        &mut self,
        mut motion: impl FnMut(&DVector<f64>, &mut SplitMix64) -> DVector<f64>,
    ) -> Result<(), FilterError> {
        let dim = self.dimension();
        let mut moved = Vec::with_capacity(self.particles.len());
        for particle in &self.particles {
            let next = motion(particle, &mut self.rng);
            check_vector_len("motion model output", &next, dim)?;
            check_finite("motion model output", next.iter())?;
            moved.push(next);
        }
        self.particles = moved;
        Ok(())
    }

    /// Multiplies the weights by the likelihood: log wᵢ ← log wᵢ + ℓ(xᵢ), then
    /// normalises with log-sum-exp. `log_likelihood` may return −∞ for
    /// impossible states but not NaN or +∞. Returns the log of the
    /// measurement's marginal likelihood estimate, log Σ wᵢ exp ℓ(xᵢ).
    ///
    /// If every particle gets −∞ the weights are left unchanged and
    /// [`FilterError::Degenerate`] is returned.
    pub fn update(
        &mut self,
        log_likelihood: impl Fn(&DVector<f64>) -> f64,
    ) -> Result<f64, FilterError> {
        let mut new_log_weights = Vec::with_capacity(self.particles.len());
        for (particle, &log_weight) in self.particles.iter().zip(&self.log_weights) {
            let ell = log_likelihood(particle);
            if ell.is_nan() || ell == f64::INFINITY {
                return Err(FilterError::NonFinite {
                    name: "log-likelihood",
                });
            }
            new_log_weights.push(log_weight + ell);
        }
        let log_total = log_sum_exp(&new_log_weights).ok_or(FilterError::Degenerate)?;
        for log_weight in &mut new_log_weights {
            *log_weight -= log_total;
        }
        self.log_weights = new_log_weights;
        Ok(log_total)
    }

    /// Effective sample size 1 / Σ wᵢ², between 1 and N.
    pub fn effective_sample_size(&self) -> f64 {
        let weights = self.weights();
        let sum_of_squares: f64 = weights.iter().map(|w| w * w).sum();
        if sum_of_squares > 0.0 {
            1.0 / sum_of_squares
        } else {
            0.0
        }
    }

    /// Resamples N particles with the given scheme; afterwards the weights are uniform.
    pub fn resample(&mut self, scheme: Resampling) {
        let count = self.particles.len();
        let weights = self.weights();
        let indices = match scheme {
            Resampling::Multinomial => {
                let uniforms = self.sorted_uniforms(count);
                select_indices(&cumulative_sum(&weights), uniforms)
            }
            Resampling::Systematic => {
                let offset = self.rng.uniform();
                let points = (0..count).map(|i| (i as f64 + offset) / count as f64);
                select_indices(&cumulative_sum(&weights), points)
            }
            Resampling::Stratified => {
                let points: Vec<f64> = (0..count)
                    .map(|i| (i as f64 + self.rng.uniform()) / count as f64)
                    .collect();
                select_indices(&cumulative_sum(&weights), points)
            }
            Resampling::Residual => self.residual_indices(&weights),
        };
        let resampled: Vec<DVector<f64>> = indices
            .iter()
            .filter_map(|&i| self.particles.get(i).cloned())
            .collect();
        if resampled.len() == count {
            self.particles = resampled;
            self.log_weights = vec![-(count as f64).ln(); count];
        }
    }

    /// Resamples with the default ([`Resampling::Systematic`]) scheme when the
    /// effective sample size is below `ess_fraction`·N. Returns whether it
    /// resampled. `ess_fraction` must lie in [0, 1].
    pub fn resample_if(&mut self, ess_fraction: f64) -> Result<bool, FilterError> {
        self.resample_if_with(ess_fraction, Resampling::default())
    }

    /// As [`ParticleFilter::resample_if`] with an explicit scheme.
    pub fn resample_if_with(
        &mut self,
        ess_fraction: f64,
        scheme: Resampling,
    ) -> Result<bool, FilterError> {
        if !(0.0..=1.0).contains(&ess_fraction) {
            return Err(FilterError::InvalidParameter {
                name: "ess_fraction",
                reason: "must lie in [0, 1]",
            });
        }
        if self.effective_sample_size() < ess_fraction * self.particles.len() as f64 {
            self.resample(scheme);
            Ok(true)
        } else {
            Ok(false)
        }
    }

    /// Weighted mean Σ wᵢ xᵢ.
    pub fn mean(&self) -> DVector<f64> {
        let mut mean = DVector::zeros(self.dimension());
        for (particle, weight) in self.particles.iter().zip(self.weights()) {
            mean.axpy(weight, particle, 1.0);
        }
        mean
    }

    /// Weighted covariance Σ wᵢ (xᵢ − x̄)(xᵢ − x̄)ᵀ (no small-sample correction).
    pub fn covariance(&self) -> DMatrix<f64> {
        let mean = self.mean();
        let dim = self.dimension();
        let mut covariance = DMatrix::zeros(dim, dim);
        for (particle, weight) in self.particles.iter().zip(self.weights()) {
            let deviation = particle - &mean;
            covariance.ger(weight, &deviation, &deviation, 1.0);
        }
        symmetrize(&covariance)
    }

    /// The particle with the highest weight (the first one on ties).
    pub fn map_estimate(&self) -> DVector<f64> {
        let mut best: Option<(&DVector<f64>, f64)> = None;
        for (particle, &log_weight) in self.particles.iter().zip(&self.log_weights) {
            if best.is_none_or(|(_, best_weight)| log_weight > best_weight) {
                best = Some((particle, log_weight));
            }
        }
        best.map_or_else(|| DVector::zeros(self.dimension()), |(p, _)| p.clone())
    }

    /// The particles.
    pub fn particles(&self) -> &[DVector<f64>] {
        &self.particles
    }

    /// Normalised log-weights, one per particle.
    pub fn log_weights(&self) -> &[f64] {
        &self.log_weights
    }

    /// Normalised weights exp(log wᵢ), summing to one.
    pub fn weights(&self) -> Vec<f64> {
        let weights: Vec<f64> = self.log_weights.iter().map(|lw| lw.exp()).collect();
        let total: f64 = weights.iter().sum();
        if total > 0.0 {
            weights.iter().map(|w| w / total).collect()
        } else {
            weights
        }
    }

    /// Number of particles N (always at least one).
    pub fn particle_count(&self) -> usize {
        self.particles.len()
    }

    /// Dimension of every particle.
    pub fn dimension(&self) -> usize {
        self.particles.first().map_or(0, |p| p.len())
    }

    /// The filter's generator, e.g. to draw initial or auxiliary variates.
    pub fn rng_mut(&mut self) -> &mut SplitMix64 {
        &mut self.rng
    }

    fn sorted_uniforms(&mut self, count: usize) -> Vec<f64> {
        let mut uniforms: Vec<f64> = (0..count).map(|_| self.rng.uniform()).collect();
        uniforms.sort_by(f64::total_cmp);
        uniforms
    }

    fn residual_indices(&mut self, weights: &[f64]) -> Vec<usize> {
        let count = weights.len();
        let scaled: Vec<f64> = weights.iter().map(|w| w * count as f64).collect();
        let mut indices = Vec::with_capacity(count);
        for (i, s) in scaled.iter().enumerate() {
            let copies = s.floor() as usize;
            indices.extend(std::iter::repeat_n(i, copies));
        }
        indices.truncate(count);
        let remaining = count - indices.len();
        if remaining > 0 {
            let residual_weights: Vec<f64> = scaled.iter().map(|s| s - s.floor()).collect();
            let uniforms = self.sorted_uniforms(remaining);
            indices.extend(select_indices(&cumulative_sum(&residual_weights), uniforms));
        }
        indices
    }
}

/// log Σ exp(aᵢ), or `None` when every term is −∞ (or the slice is empty).
fn log_sum_exp(values: &[f64]) -> Option<f64> {
    let max = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY {
        return None;
    }
    let sum: f64 = values.iter().map(|v| (v - max).exp()).sum();
    Some(max + sum.ln())
}

fn cumulative_sum(weights: &[f64]) -> Vec<f64> {
    weights
        .iter()
        .scan(0.0, |running, w| {
            *running += w;
            Some(*running)
        })
        .collect()
}

/// For each point u (non-decreasing, in [0, 1)) the first index whose
/// cumulative weight exceeds u·total; a single forward pass.
fn select_indices(cumulative: &[f64], sorted_points: impl IntoIterator<Item = f64>) -> Vec<usize> {
    let last_index = cumulative.len().saturating_sub(1);
    let total = cumulative.last().copied().unwrap_or(0.0);
    let mut index = 0;
    let mut selected = Vec::with_capacity(cumulative.len());
    for point in sorted_points {
        let target = point * total;
        while index < last_index && cumulative.get(index).is_some_and(|&c| c <= target) {
            index += 1;
        }
        selected.push(index);
    }
    selected
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Chi-square quantile by the Wilson–Hilferty cube-root approximation
    /// (Wilson & Hilferty 1931): k (1 − 2/(9k) + z √(2/(9k)))³.
    fn chi_square_quantile(dof: f64, standard_normal_quantile: f64) -> f64 {
        let c = 2.0 / (9.0 * dof);
        dof * (1.0 - c + standard_normal_quantile * c.sqrt()).powi(3)
    }

    const Z_97_5: f64 = 1.959_963_984_540_054;

    fn vector(values: &[f64]) -> DVector<f64> {
        DVector::from_column_slice(values)
    }

    fn diagonal(values: &[f64]) -> DMatrix<f64> {
        DMatrix::from_diagonal(&vector(values))
    }

    /// Samples one step of the planar constant-velocity truth with the
    /// discrete white-noise acceleration model used by the filter.
    fn propagate_cv_truth(truth: &mut DVector<f64>, dt: f64, accel_std: f64, rng: &mut SplitMix64) {
        for axis in 0..2 {
            let accel = rng.normal(0.0, accel_std);
            truth[axis] += truth[axis + 2] * dt + 0.5 * accel * dt * dt;
            truth[axis + 2] += accel * dt;
        }
    }

    fn measure_position(
        truth: &DVector<f64>,
        measurement_std: f64,
        rng: &mut SplitMix64,
    ) -> DVector<f64> {
        vector(&[
            truth[0] + rng.normal(0.0, measurement_std),
            truth[1] + rng.normal(0.0, measurement_std),
        ])
    }

    /// Truth sampled from the prior N(mean, diag(variances)).
    fn sample_diagonal_gaussian(
        mean: &DVector<f64>,
        variances: &[f64],
        rng: &mut SplitMix64,
    ) -> DVector<f64> {
        DVector::from_iterator(
            mean.len(),
            mean.iter()
                .zip(variances)
                .map(|(m, v)| m + v.sqrt() * rng.standard_normal()),
        )
    }

    fn position_error_squared(estimate: &DVector<f64>, truth: &DVector<f64>) -> f64 {
        (estimate[0] - truth[0]).powi(2) + (estimate[1] - truth[1]).powi(2)
    }

    fn min_eigenvalue(matrix: &DMatrix<f64>) -> f64 {
        symmetrize(matrix)
            .symmetric_eigen()
            .eigenvalues
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
    }

    fn max_relative_asymmetry(matrix: &DMatrix<f64>) -> f64 {
        (matrix - matrix.transpose()).amax() / matrix.amax()
    }

    fn scalar_filter(x0: f64, p0: f64, q: f64, r: f64) -> KalmanFilter {
        KalmanFilter::new(
            vector(&[x0]),
            diagonal(&[p0]),
            diagonal(&[1.0]),
            diagonal(&[q]),
            diagonal(&[1.0]),
            diagonal(&[r]),
        )
        .unwrap()
    }

    #[test]
    fn scalar_random_walk_two_steps_match_hand_computation() {
        // x_k = x_{k-1} + w (q = 1), z_k = x_k + v (r = 2), x0 = 0, p0 = 3.
        // Step 1: p⁻ = 3 + 1 = 4, S = 4 + 2 = 6, K = 4/6 = 2/3, z = 3:
        //   x = 0 + 2/3·3 = 2, p = (1 − 2/3)·4 = 4/3, d² = 3²/6 = 1.5,
        //   log L = −½(1.5 + ln 6 + ln 2π).
        // Step 2: p⁻ = 4/3 + 1 = 7/3, S = 7/3 + 2 = 13/3, K = 7/13, z = 0:
        //   y = −2, x = 2 − 14/13 = 12/13, p = (6/13)·(7/3) = 14/13.
        let mut kf = scalar_filter(0.0, 3.0, 1.0, 2.0);
        kf.predict().unwrap();
        assert!((kf.covariance()[(0, 0)] - 4.0).abs() < 1e-14);
        let innovation = kf.update(&vector(&[3.0])).unwrap();
        println!(
            "step 1: x = {}, p = {}, S = {}, d² = {}, logL = {}",
            kf.state()[0],
            kf.covariance()[(0, 0)],
            innovation.covariance[(0, 0)],
            innovation.mahalanobis_squared,
            innovation.log_likelihood
        );
        assert!((kf.state()[0] - 2.0).abs() < 1e-14);
        assert!((kf.covariance()[(0, 0)] - 4.0 / 3.0).abs() < 1e-14);
        assert!((innovation.covariance[(0, 0)] - 6.0).abs() < 1e-14);
        assert!((innovation.mahalanobis_squared - 1.5).abs() < 1e-14);
        let expected_log_likelihood = -0.5 * (1.5 + 6f64.ln() + TAU.ln());
        assert!((innovation.log_likelihood - expected_log_likelihood).abs() < 1e-13);

        kf.predict().unwrap();
        assert!((kf.covariance()[(0, 0)] - 7.0 / 3.0).abs() < 1e-14);
        let innovation = kf.update(&vector(&[0.0])).unwrap();
        println!(
            "step 2: x = {}, p = {}",
            kf.state()[0],
            kf.covariance()[(0, 0)]
        );
        assert!((innovation.residual[0] + 2.0).abs() < 1e-14);
        assert!((kf.state()[0] - 12.0 / 13.0).abs() < 1e-14);
        assert!((kf.covariance()[(0, 0)] - 14.0 / 13.0).abs() < 1e-14);
    }

    #[test]
    fn scalar_posterior_variance_converges_to_riccati_solution() {
        // Constant-position model with F = H = 1: the posterior variance p solves
        // p = (p + q) r / (p + q + r), i.e. p² + q p − q r = 0, so
        // p = (−q + √(q² + 4 q r)) / 2.
        let (q, r): (f64, f64) = (0.5, 2.0);
        let riccati = (-q + (q * q + 4.0 * q * r).sqrt()) / 2.0;
        let mut kf = scalar_filter(0.0, 100.0, q, r);
        for _ in 0..200 {
            kf.predict().unwrap();
            kf.update(&vector(&[1.0])).unwrap();
        }
        let p = kf.covariance()[(0, 0)];
        println!(
            "steady-state p = {p:.15}, Riccati = {riccati:.15}, diff = {:e}",
            p - riccati
        );
        assert!((p - riccati).abs() < 1e-9);
    }

    #[test]
    fn constant_velocity_filter_is_consistent_and_beats_measurement_noise() {
        let (dt, accel_std, measurement_std) = (0.5, 0.5, 2.0);
        let (runs, steps) = (50usize, 500usize);
        let prior_mean = vector(&[0.0, 0.0, 1.0, 0.5]);
        let prior_variances = [4.0, 4.0, 1.0, 1.0];
        let mut rng = SplitMix64::new(20_240_601);
        let mut nees_per_step = vec![0.0; steps];
        let mut squared_position_error = 0.0;
        for _ in 0..runs {
            let mut truth = sample_diagonal_gaussian(&prior_mean, &prior_variances, &mut rng);
            let mut kf = KalmanFilter::constant_velocity_2d(
                dt,
                accel_std,
                measurement_std,
                prior_mean.clone(),
                diagonal(&prior_variances),
            )
            .unwrap();
            for nees in nees_per_step.iter_mut() {
                propagate_cv_truth(&mut truth, dt, accel_std, &mut rng);
                kf.predict().unwrap();
                kf.update(&measure_position(&truth, measurement_std, &mut rng))
                    .unwrap();
                let error = &truth - kf.state();
                let whitened = kf.covariance().clone().cholesky().unwrap().solve(&error);
                *nees += error.dot(&whitened) / runs as f64;
                squared_position_error += position_error_squared(kf.state(), &truth);
            }
        }
        let mean_nees = nees_per_step.iter().sum::<f64>() / steps as f64;
        // Bar-Shalom's M-run band: M·NEES ~ χ²(M·n) with M = 50, n = 4.
        let dof = (runs * 4) as f64;
        let lower = chi_square_quantile(dof, -Z_97_5) / runs as f64;
        let upper = chi_square_quantile(dof, Z_97_5) / runs as f64;
        let inside = nees_per_step
            .iter()
            .filter(|&&v| v >= lower && v <= upper)
            .count();
        let fraction_inside = inside as f64 / steps as f64;
        let position_rmse = (squared_position_error / (runs * steps) as f64 / 2.0).sqrt();
        println!(
            "mean NEES = {mean_nees:.4} (95% band [{lower:.4}, {upper:.4}]), \
             steps inside band = {:.1}%, position RMSE per axis = {position_rmse:.4} (measurement std {measurement_std})",
            100.0 * fraction_inside
        );
        assert!(mean_nees > lower && mean_nees < upper);
        assert!(fraction_inside >= 0.9);
        assert!(position_rmse < measurement_std);
    }

    #[test]
    fn joseph_form_keeps_covariance_positive_definite_with_ill_conditioned_noise() {
        let (dt, accel_std) = (1.0, 1.0);
        let (f, q) = constant_velocity_2d_model(dt, accel_std);
        let mut h = DMatrix::zeros(2, 4);
        h[(0, 0)] = 1.0;
        h[(1, 1)] = 1.0;
        let r = diagonal(&[1e-12, 1e6]);
        let p0 = diagonal(&[1e10, 1e10, 1e4, 1e4]);
        let mut kf = KalmanFilter::new(
            DVector::zeros(4),
            p0.clone(),
            f.clone(),
            q.clone(),
            h.clone(),
            r.clone(),
        )
        .unwrap();
        let mut rng = SplitMix64::new(99);
        let mut truth = vector(&[0.0, 0.0, 1.0, 1.0]);

        // The naive form P = (I − K H) P with K = P Hᵀ S⁻¹, without
        // symmetrisation, computed alongside on the same measurements. With the
        // diffuse prior (1e10) and the 1e-12 noise, P − K H P cancels
        // catastrophically in the first updates and the result is singular;
        // the Joseph form keeps the K R Kᵀ ≈ 1e-12 term and stays definite.
        let mut naive_p = p0;
        let mut naive_max_asymmetry: f64 = 0.0;
        let mut naive_min_eigenvalue = f64::INFINITY;
        let mut naive_failed_cholesky = 0usize;

        let mut joseph_min_eigenvalue = f64::INFINITY;
        for _ in 0..10_000 {
            propagate_cv_truth(&mut truth, dt, accel_std, &mut rng);
            let z = vector(&[
                truth[0] + rng.normal(0.0, 1e-6),
                truth[1] + rng.normal(0.0, 1e3),
            ]);
            kf.predict().unwrap();
            kf.update(&z).unwrap();
            let p = kf.covariance();
            assert_eq!(max_relative_asymmetry(p), 0.0);
            assert!(
                p.clone().cholesky().is_some(),
                "Joseph-form P lost definiteness"
            );
            joseph_min_eigenvalue = joseph_min_eigenvalue.min(min_eigenvalue(p));

            naive_p = &f * &naive_p * f.transpose() + &q;
            let s = &h * &naive_p * h.transpose() + &r;
            let gain = &naive_p * h.transpose() * s.try_inverse().unwrap();
            naive_p = (DMatrix::identity(4, 4) - &gain * &h) * &naive_p;
            naive_max_asymmetry = naive_max_asymmetry.max(max_relative_asymmetry(&naive_p));
            naive_min_eigenvalue = naive_min_eigenvalue.min(min_eigenvalue(&naive_p));
            if naive_p.clone().cholesky().is_none() {
                naive_failed_cholesky += 1;
            }
        }
        println!(
            "Joseph: min eigenvalue over 10000 steps = {joseph_min_eigenvalue:e}, final P[0,0] = {:e}; \
             naive: max relative asymmetry = {naive_max_asymmetry:e}, min eigenvalue = {naive_min_eigenvalue:e}, \
             steps with failed Cholesky = {naive_failed_cholesky}",
            kf.covariance()[(0, 0)]
        );
        assert!(joseph_min_eigenvalue > 0.0);
        assert!(
            naive_failed_cholesky > 0,
            "the naive form was expected to lose definiteness here"
        );
        assert!(kf.state().iter().all(|v| v.is_finite()));
    }

    fn cv_filter_at(
        truth: &DVector<f64>,
        dt: f64,
        accel_std: f64,
        measurement_std: f64,
    ) -> KalmanFilter {
        KalmanFilter::constant_velocity_2d(
            dt,
            accel_std,
            measurement_std,
            truth.clone(),
            diagonal(&[1.0, 1.0, 0.25, 0.25]),
        )
        .unwrap()
    }

    #[test]
    fn gate_rejects_hundred_sigma_outlier_and_accepts_normal_measurement() {
        let truth = vector(&[10.0, -5.0, 1.0, 0.0]);
        let mut kf = cv_filter_at(&truth, 1.0, 0.1, 1.0);
        kf.predict().unwrap();
        let gate = 13.8155; // χ²₂ 99.9 % quantile, −2 ln 0.001.
        let predicted = kf.state().clone();
        let s_xx = kf.covariance()[(0, 0)] + 1.0;
        let outlier = vector(&[predicted[0] + 100.0 * s_xx.sqrt(), predicted[1]]);
        let before = kf.clone();
        let rejected = kf.update_gated(&outlier, gate).unwrap();
        assert!(rejected.is_none());
        assert_eq!(
            kf, before,
            "a rejected measurement must leave the filter unchanged"
        );
        let normal = vector(&[predicted[0] + 0.5, predicted[1] - 0.7]);
        let accepted = kf.update_gated(&normal, gate).unwrap();
        let accepted = accepted.expect("normal measurement should pass the gate");
        // Distance² of the outlier would be 100² = 1e4.
        let mut probe = before.clone();
        let outlier_distance = probe.update(&outlier).unwrap().mahalanobis_squared;
        println!(
            "outlier d² = {outlier_distance:.1} (rejected), normal d² = {:.3} (accepted)",
            accepted.mahalanobis_squared
        );
        assert!((outlier_distance - 1e4).abs() < 1e-6 * 1e4);
        assert!(accepted.mahalanobis_squared < gate);
    }

    #[test]
    fn gating_keeps_rmse_low_with_ten_percent_outliers() {
        let (dt, accel_std, measurement_std) = (1.0, 0.2, 1.0);
        let mut rng = SplitMix64::new(4242);
        let mut truth = vector(&[0.0, 0.0, 1.0, -0.5]);
        let mut gated = cv_filter_at(&truth, dt, accel_std, measurement_std);
        let mut ungated = gated.clone();
        let (mut gated_sq, mut ungated_sq, mut outliers, mut rejected) = (0.0, 0.0, 0, 0);
        let steps = 1000;
        for _ in 0..steps {
            propagate_cv_truth(&mut truth, dt, accel_std, &mut rng);
            let mut z = measure_position(&truth, measurement_std, &mut rng);
            if rng.uniform() < 0.1 {
                outliers += 1;
                z[0] += rng.normal(0.0, 50.0);
                z[1] += rng.normal(0.0, 50.0);
            }
            gated.predict().unwrap();
            ungated.predict().unwrap();
            if gated.update_gated(&z, 13.8155).unwrap().is_none() {
                rejected += 1;
            }
            ungated.update(&z).unwrap();
            gated_sq += position_error_squared(gated.state(), &truth);
            ungated_sq += position_error_squared(ungated.state(), &truth);
        }
        let gated_rmse = (gated_sq / steps as f64 / 2.0).sqrt();
        let ungated_rmse = (ungated_sq / steps as f64 / 2.0).sqrt();
        println!(
            "outliers = {outliers}, rejected = {rejected}, RMSE gated = {gated_rmse:.4}, ungated = {ungated_rmse:.4}"
        );
        assert!(gated_rmse < measurement_std);
        assert!(gated_rmse < 0.3 * ungated_rmse);
    }

    #[test]
    fn rts_smoother_reduces_error_of_filter() {
        let (dt, accel_std, measurement_std) = (0.5, 0.5, 2.0);
        let mut rng = SplitMix64::new(777);
        let prior_mean = vector(&[0.0, 0.0, 1.0, 0.5]);
        let prior_variances = [4.0, 4.0, 1.0, 1.0];
        let mut truth = sample_diagonal_gaussian(&prior_mean, &prior_variances, &mut rng);
        let mut kf = KalmanFilter::constant_velocity_2d(
            dt,
            accel_std,
            measurement_std,
            prior_mean,
            diagonal(&prior_variances),
        )
        .unwrap();
        let mut truths = Vec::new();
        let mut records = Vec::new();
        for k in 0..500 {
            propagate_cv_truth(&mut truth, dt, accel_std, &mut rng);
            let z = measure_position(&truth, measurement_std, &mut rng);
            // Every 50th step without a measurement exercises the predict-only path.
            let measurement = (k % 50 != 49).then_some(&z);
            records.push(kf.step(measurement).unwrap());
            truths.push(truth.clone());
        }
        let smoothed = rts_smooth(&records, kf.transition()).unwrap();
        assert_eq!(smoothed.len(), records.len());
        let filtered_sq: f64 = records
            .iter()
            .zip(&truths)
            .map(|(r, t)| position_error_squared(&r.filtered_state, t))
            .sum();
        let smoothed_sq: f64 = smoothed
            .iter()
            .zip(&truths)
            .map(|(s, t)| position_error_squared(&s.state, t))
            .sum();
        let filtered_rmse = (filtered_sq / 1000.0).sqrt();
        let smoothed_rmse = (smoothed_sq / 1000.0).sqrt();
        println!(
            "position RMSE per axis: filtered = {filtered_rmse:.4}, smoothed = {smoothed_rmse:.4}"
        );
        assert!(smoothed_rmse < 0.9 * filtered_rmse);
        // Smoothed covariance never exceeds the filtered one (trace).
        for (s, r) in smoothed.iter().zip(&records) {
            assert!(s.covariance.trace() <= r.filtered_covariance.trace() * (1.0 + 1e-12));
        }
        let varying =
            rts_smooth_time_varying(&records, &vec![kf.transition().clone(); 499]).unwrap();
        assert_eq!(varying, smoothed);
        assert!(rts_smooth(&[], kf.transition()).unwrap().is_empty());
    }

    #[test]
    fn constant_acceleration_model_tracks_accelerating_target() {
        let (dt, measurement_std) = (0.1, 0.5);
        let mut rng = SplitMix64::new(5);
        let mut kf = KalmanFilter::constant_acceleration_2d(
            dt,
            0.01,
            measurement_std,
            DVector::zeros(6),
            diagonal(&[1.0, 1.0, 4.0, 4.0, 1.0, 1.0]),
        )
        .unwrap();
        let (mut sq, mut count) = (0.0, 0);
        for k in 1..=400 {
            let t = k as f64 * dt;
            let truth = vector(&[0.5 * 0.3 * t * t, 2.0 * t - 0.5 * 0.1 * t * t, 0.0, 0.0]);
            kf.predict().unwrap();
            kf.update(&measure_position(&truth, measurement_std, &mut rng))
                .unwrap();
            if k > 100 {
                sq += position_error_squared(kf.state(), &truth);
                count += 1;
            }
        }
        let rmse = (sq / count as f64 / 2.0).sqrt();
        println!(
            "constant-acceleration RMSE = {rmse:.4}; ax = {:.4} ± {:.4} (true 0.3), ay = {:.4} ± {:.4} (true -0.1)",
            kf.state()[4],
            kf.covariance()[(4, 4)].sqrt(),
            kf.state()[5],
            kf.covariance()[(5, 5)].sqrt(),
        );
        assert!(rmse < measurement_std);
        // Final acceleration estimates within 3 posterior standard deviations.
        assert!((kf.state()[4] - 0.3).abs() < 3.0 * kf.covariance()[(4, 4)].sqrt());
        assert!((kf.state()[5] + 0.1).abs() < 3.0 * kf.covariance()[(5, 5)].sqrt());
    }

    #[test]
    fn constructor_rejects_invalid_inputs_with_clear_errors() {
        let make = |p0: DMatrix<f64>, h: DMatrix<f64>, r: DMatrix<f64>| {
            KalmanFilter::new(
                DVector::zeros(2),
                p0,
                DMatrix::identity(2, 2),
                DMatrix::identity(2, 2),
                h,
                r,
            )
        };
        let error = make(
            DMatrix::identity(2, 2),
            DMatrix::identity(1, 3),
            DMatrix::identity(1, 1),
        )
        .unwrap_err();
        assert_eq!(
            error.to_string(),
            "dimension mismatch for H (measurement matrix): expected 1x2, got 1x3"
        );
        let error = make(
            DMatrix::identity(3, 3),
            DMatrix::identity(1, 2),
            DMatrix::identity(1, 1),
        )
        .unwrap_err();
        assert!(matches!(
            error,
            FilterError::DimensionMismatch {
                expected_rows: 2,
                actual_rows: 3,
                ..
            }
        ));
        let error = make(
            diagonal(&[1.0, f64::NAN]),
            DMatrix::identity(1, 2),
            DMatrix::identity(1, 1),
        )
        .unwrap_err();
        assert!(matches!(error, FilterError::NonFinite { .. }));
        let asymmetric = DMatrix::from_row_slice(2, 2, &[1.0, 0.5, 0.0, 1.0]);
        let error = make(asymmetric, DMatrix::identity(1, 2), DMatrix::identity(1, 1)).unwrap_err();
        assert!(matches!(error, FilterError::NotSymmetric { .. }));
        let indefinite = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]);
        let error = make(indefinite, DMatrix::identity(1, 2), DMatrix::identity(1, 1)).unwrap_err();
        println!("{error}");
        assert_eq!(
            error,
            FilterError::NotPositiveSemiDefinite {
                name: "P0 (initial covariance)"
            }
        );
        // A singular but PSD matrix (zero process noise) is accepted.
        assert!(
            make(
                DMatrix::zeros(2, 2),
                DMatrix::identity(1, 2),
                DMatrix::identity(1, 1)
            )
            .is_ok()
        );
        // Zero prior and zero noise make S singular.
        let mut kf = make(
            DMatrix::zeros(2, 2),
            DMatrix::identity(1, 2),
            DMatrix::zeros(1, 1),
        )
        .unwrap();
        assert_eq!(
            kf.update(&vector(&[1.0])),
            Err(FilterError::InnovationNotPositiveDefinite)
        );
        assert!(matches!(
            kf.update(&vector(&[1.0, 2.0])),
            Err(FilterError::DimensionMismatch {
                name: "z (measurement)",
                ..
            })
        ));
        assert!(
            KalmanFilter::constant_velocity_2d(
                0.0,
                1.0,
                1.0,
                DVector::zeros(4),
                DMatrix::identity(4, 4)
            )
            .is_err()
        );
    }

    /// Range and bearing of a planar target from a sensor at the origin.
    fn range_bearing(x: &DVector<f64>) -> DVector<f64> {
        vector(&[x[0].hypot(x[1]), x[1].atan2(x[0])])
    }

    fn range_bearing_jacobian(x: &DVector<f64>) -> DMatrix<f64> {
        let range_sq = x[0] * x[0] + x[1] * x[1];
        let range = range_sq.sqrt();
        DMatrix::from_row_slice(
            2,
            4,
            &[
                x[0] / range,
                x[1] / range,
                0.0,
                0.0,
                -x[1] / range_sq,
                x[0] / range_sq,
                0.0,
                0.0,
            ],
        )
    }

    #[test]
    fn ekf_range_bearing_tracks_target_through_bearing_cut() {
        let (dt, accel_std, range_std, bearing_std) = (0.1, 0.05, 0.2, 0.02);
        let (f, q) = constant_velocity_2d_model(dt, accel_std);
        let r = diagonal(&[range_std * range_std, bearing_std * bearing_std]);
        let mut rng = SplitMix64::new(31_415);
        let prior_variances = [1.0, 1.0, 0.25, 0.25];
        // Fixed truth so that the track crosses the negative x-axis (bearing ±π);
        // the prior mean is drawn around it from the prior covariance.
        let mut truth = vector(&[-20.0, 30.0, 0.3, -1.0]);
        let prior_mean = sample_diagonal_gaussian(&truth, &prior_variances, &mut rng);
        let mut wrapped =
            ExtendedKalmanFilter::new(prior_mean.clone(), diagonal(&prior_variances)).unwrap();
        let mut unwrapped = wrapped.clone();
        let motion = |x: &DVector<f64>| &f * x;
        let motion_jacobian = |_: &DVector<f64>| f.clone();
        let wrap_bearing = |z: &DVector<f64>, predicted: &DVector<f64>| {
            vector(&[z[0] - predicted[0], wrap_angle(z[1] - predicted[1])])
        };
        let (mut sq, mut previous_bearing, mut cut_crossings) = (0.0, f64::NAN, 0);
        let (mut max_wrapped_residual, mut max_unwrapped_residual): (f64, f64) = (0.0, 0.0);
        let (mut unwrapped_sq, mut steps_straddling_cut) = (0.0, 0);
        let mut max_normalized_residual: f64 = 0.0;
        let steps = 1000;
        for _ in 0..steps {
            propagate_cv_truth(&mut truth, dt, accel_std, &mut rng);
            let true_bearing = truth[1].atan2(truth[0]);
            if (true_bearing - previous_bearing).abs() > PI {
                cut_crossings += 1;
            }
            previous_bearing = true_bearing;
            let z = vector(&[
                truth[0].hypot(truth[1]) + rng.normal(0.0, range_std),
                wrap_angle(true_bearing + rng.normal(0.0, bearing_std)),
            ]);
            wrapped.predict(motion, motion_jacobian, &q).unwrap();
            if (z[1] - range_bearing(wrapped.state())[1]).abs() > PI {
                steps_straddling_cut += 1;
            }
            let innovation = wrapped
                .update_with_residual(&z, range_bearing, range_bearing_jacobian, &r, wrap_bearing)
                .unwrap();
            max_wrapped_residual = max_wrapped_residual.max(innovation.residual[1].abs());
            let bearing_sigma = innovation.covariance[(1, 1)].sqrt();
            max_normalized_residual =
                max_normalized_residual.max(innovation.residual[1].abs() / bearing_sigma);
            sq += position_error_squared(wrapped.state(), &truth);
            assert!(wrapped.state().iter().all(|v| v.is_finite()));

            if unwrapped.predict(motion, motion_jacobian, &q).is_ok()
                && let Ok(innovation) =
                    unwrapped.update(&z, range_bearing, range_bearing_jacobian, &r)
            {
                max_unwrapped_residual = max_unwrapped_residual.max(innovation.residual[1].abs());
            }
            unwrapped_sq += position_error_squared(unwrapped.state(), &truth);
        }
        let rmse = (sq / steps as f64 / 2.0).sqrt();
        let unwrapped_rmse = (unwrapped_sq / steps as f64 / 2.0).sqrt();
        println!(
            "bearing cut crossings = {cut_crossings}, steps with z and prediction on opposite sides = {steps_straddling_cut}; wrapped: RMSE = {rmse:.4}, max |bearing residual| = {max_wrapped_residual:.4} ({max_normalized_residual:.2} σ); \
             unwrapped: RMSE = {unwrapped_rmse:.4}, max |bearing residual| = {max_unwrapped_residual:.4}"
        );
        assert_eq!(cut_crossings, 1, "the target must pass through the ±π cut");
        assert!(max_normalized_residual < 6.0);
        assert!(
            steps_straddling_cut > 0,
            "the measurement noise must straddle the cut at least once"
        );
        assert!(
            max_unwrapped_residual > PI,
            "without wrapping the cut shows as a ~2π residual"
        );
        assert!(rmse < 0.5);
    }

    #[test]
    fn numerical_jacobian_matches_analytic_jacobians() {
        let x = vector(&[-11.0, 0.3, 0.4, -1.0]);
        let numeric = numerical_jacobian(range_bearing, &x, 1e-6).unwrap();
        let analytic = range_bearing_jacobian(&x);
        let range_bearing_error = (&numeric - &analytic).amax();
        // Coordinated turn, state [x, y, v, heading, turn rate], dt = 0.5.
        let dt = 0.5;
        let turn = |s: &DVector<f64>| {
            let (v, heading, omega) = (s[2], s[3], s[4]);
            vector(&[
                s[0] + v / omega * ((heading + omega * dt).sin() - heading.sin()),
                s[1] + v / omega * (heading.cos() - (heading + omega * dt).cos()),
                v,
                heading + omega * dt,
                omega,
            ])
        };
        let s = vector(&[1.0, 2.0, 3.0, 0.7, 0.2]);
        let (v, heading, omega) = (s[2], s[3], s[4]);
        let (sin0, cos0) = heading.sin_cos();
        let (sin1, cos1) = (heading + omega * dt).sin_cos();
        let mut turn_jacobian = DMatrix::identity(5, 5);
        turn_jacobian[(0, 2)] = (sin1 - sin0) / omega;
        turn_jacobian[(0, 3)] = v / omega * (cos1 - cos0);
        turn_jacobian[(0, 4)] = v * dt * cos1 / omega - v / (omega * omega) * (sin1 - sin0);
        turn_jacobian[(1, 2)] = (cos0 - cos1) / omega;
        turn_jacobian[(1, 3)] = v / omega * (sin1 - sin0);
        turn_jacobian[(1, 4)] = v * dt * sin1 / omega - v / (omega * omega) * (cos0 - cos1);
        turn_jacobian[(3, 4)] = dt;
        let turn_error = (numerical_jacobian(turn, &s, 1e-6).unwrap() - turn_jacobian).amax();
        println!(
            "max |numeric − analytic|: range–bearing = {range_bearing_error:e}, coordinated turn = {turn_error:e}"
        );
        assert!(range_bearing_error < 1e-6);
        assert!(turn_error < 1e-6);
        assert!(numerical_jacobian(range_bearing, &x, 0.0).is_err());
    }

    fn gaussian_particles(count: usize, mean: f64, std_dev: f64, seed: u64) -> Vec<DVector<f64>> {
        let mut rng = SplitMix64::new(seed);
        (0..count)
            .map(|_| vector(&[rng.normal(mean, std_dev)]))
            .collect()
    }

    #[test]
    fn particle_filter_agrees_with_exact_kalman_filter() {
        // x_k = 0.9 x_{k-1} + w, w ~ N(0, 1); z_k = x_k + v, v ~ N(0, 0.5).
        let (a, q, r, count) = (0.9, 1.0, 0.5, 2000usize);
        let mut kf = KalmanFilter::new(
            vector(&[0.0]),
            diagonal(&[1.0]),
            diagonal(&[a]),
            diagonal(&[q]),
            diagonal(&[1.0]),
            diagonal(&[r]),
        )
        .unwrap();
        let mut pf = ParticleFilter::new(gaussian_particles(count, 0.0, 1.0, 1), 2).unwrap();
        let mut data_rng = SplitMix64::new(3);
        let mut truth = data_rng.normal(0.0, 1.0);
        let mut worst_ratio: f64 = 0.0;
        let mut resamplings = 0;
        for step in 0..50 {
            truth = a * truth + data_rng.normal(0.0, q.sqrt());
            let z = truth + data_rng.normal(0.0, r.sqrt());
            kf.predict().unwrap();
            kf.update(&vector(&[z])).unwrap();
            pf.predict(|x, rng| vector(&[a * x[0] + rng.normal(0.0, q.sqrt())]))
                .unwrap();
            pf.update(|x| -0.5 * (z - x[0]).powi(2) / r).unwrap();
            let standard_error = (kf.covariance()[(0, 0)] / pf.effective_sample_size()).sqrt();
            let difference = pf.mean()[0] - kf.state()[0];
            let ratio = difference.abs() / standard_error;
            worst_ratio = worst_ratio.max(ratio);
            // 50 checks at once: 3.5 standard errors keeps the family-wise false-alarm rate
            // near 2 % (Bonferroni), where 3 would fail a correct filter for about 1 seed in 7.
            assert!(
                ratio < 3.5,
                "step {step}: |PF − KF| = {difference:e}, SE = {standard_error:e}"
            );
            if pf.resample_if(0.5).unwrap() {
                resamplings += 1;
            }
        }
        let pf_variance = pf.covariance()[(0, 0)];
        println!(
            "worst |PF mean − KF mean| / SE over 50 steps = {worst_ratio:.3}; resamplings = {resamplings}; \
             final variance PF = {pf_variance:.4}, KF = {:.4}",
            kf.covariance()[(0, 0)]
        );
        assert!((pf_variance / kf.covariance()[(0, 0)] - 1.0).abs() < 0.15);
    }

    #[test]
    fn every_resampling_scheme_preserves_the_weighted_mean() {
        let count = 2000;
        let mut pf = ParticleFilter::new(gaussian_particles(count, 0.0, 1.0, 11), 12).unwrap();
        pf.update(|x| -0.5 * (x[0] - 1.0).powi(2) / 0.25).unwrap();
        let weighted_mean = pf.mean()[0];
        let weighted_variance = pf.covariance()[(0, 0)];
        let standard_error = (weighted_variance / count as f64).sqrt();
        for scheme in [
            Resampling::Multinomial,
            Resampling::Systematic,
            Resampling::Stratified,
            Resampling::Residual,
        ] {
            let mut resampled = pf.clone();
            resampled.resample(scheme);
            assert_eq!(resampled.particle_count(), count);
            assert!((resampled.effective_sample_size() - count as f64).abs() < 1e-6);
            let mean = resampled.mean()[0];
            let ratio = (mean - weighted_mean).abs() / standard_error;
            println!(
                "{scheme:?}: weighted mean = {weighted_mean:.5}, resampled mean = {mean:.5}, |diff|/SE = {ratio:.3}"
            );
            assert!(ratio < 3.0);
        }
    }

    #[test]
    fn effective_sample_size_limits() {
        let count = 100;
        let mut pf = ParticleFilter::new(gaussian_particles(count, 0.0, 1.0, 21), 22).unwrap();
        println!("ESS uniform = {}", pf.effective_sample_size());
        assert!((pf.effective_sample_size() - count as f64).abs() < 1e-9);
        let chosen = pf.particles()[37].clone();
        pf.update(|x| if *x == chosen { 0.0 } else { f64::NEG_INFINITY })
            .unwrap();
        println!("ESS single = {}", pf.effective_sample_size());
        assert!((pf.effective_sample_size() - 1.0).abs() < 1e-12);
        assert_eq!(pf.map_estimate(), chosen);
        assert!(pf.resample_if(0.5).unwrap());
        assert!(pf.particles().iter().all(|p| *p == chosen));
        assert!(pf.resample_if(1.5).is_err());
    }

    #[test]
    fn degenerate_likelihood_is_an_error_and_keeps_weights() {
        let mut pf = ParticleFilter::new(gaussian_particles(50, 0.0, 1.0, 31), 32).unwrap();
        pf.update(|x| -x[0] * x[0]).unwrap();
        let before = pf.clone();
        assert_eq!(
            pf.update(|_| f64::NEG_INFINITY),
            Err(FilterError::Degenerate)
        );
        assert_eq!(pf, before);
        assert!(matches!(
            pf.update(|_| f64::NAN),
            Err(FilterError::NonFinite { .. })
        ));
        assert_eq!(pf, before);
        assert_eq!(
            ParticleFilter::new(Vec::new(), 1),
            Err(FilterError::EmptyParticleSet)
        );
        assert!(matches!(
            ParticleFilter::new(vec![vector(&[1.0]), vector(&[1.0, 2.0])], 1),
            Err(FilterError::DimensionMismatch {
                name: "particle",
                ..
            })
        ));
    }

    fn run_particle_filter(seed: u64, scheme: Resampling) -> ParticleFilter {
        let mut pf = ParticleFilter::new(gaussian_particles(500, 0.0, 1.0, 41), seed).unwrap();
        for step in 0..10 {
            let z = step as f64 * 0.3;
            pf.predict(|x, rng| vector(&[x[0] + rng.normal(0.0, 0.5)]))
                .unwrap();
            pf.update(|x| -0.5 * (z - x[0]).powi(2)).unwrap();
            pf.resample(scheme);
        }
        pf
    }

    #[test]
    fn same_seed_is_bit_identical_and_different_seed_differs() {
        for scheme in [
            Resampling::Multinomial,
            Resampling::Systematic,
            Resampling::Stratified,
            Resampling::Residual,
        ] {
            let first = run_particle_filter(7, scheme);
            let second = run_particle_filter(7, scheme);
            let other = run_particle_filter(8, scheme);
            let identical = first
                .particles()
                .iter()
                .zip(second.particles())
                .all(|(a, b)| a[0].to_bits() == b[0].to_bits());
            assert!(
                identical && first == second,
                "{scheme:?}: same seed must reproduce"
            );
            assert_ne!(
                first.particles(),
                other.particles(),
                "{scheme:?}: seeds must matter"
            );
        }
    }

    #[test]
    fn splitmix_normal_has_unit_moments() {
        let mut rng = SplitMix64::new(0);
        let samples: Vec<f64> = (0..200_000).map(|_| rng.standard_normal()).collect();
        let mean = samples.iter().sum::<f64>() / samples.len() as f64;
        let variance =
            samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / samples.len() as f64;
        println!("normal sample mean = {mean:.5}, variance = {variance:.5}");
        assert!(mean.abs() < 0.01 && (variance - 1.0).abs() < 0.01);
        let mut a = SplitMix64::new(123);
        let mut b = SplitMix64::new(123);
        assert!((0..100).all(|_| a.next_u64() == b.next_u64()));
        assert!((0..1000).all(|_| (0.0..1.0).contains(&a.uniform())));
        assert!((wrap_angle(PI + 0.1) - (-PI + 0.1)).abs() < 1e-15);
        assert!((wrap_angle(3.0 * TAU + 0.25) - 0.25).abs() < 1e-14);
        assert!((wrap_angle(-PI - 0.1) - (PI - 0.1)).abs() < 1e-15);
    }

    /// Symmetric positive definite matrix (A Aᵀ + 0.1 I) · 10^exponent.
    fn spd_from(entries: &[f64], dim: usize, exponent: i32) -> DMatrix<f64> {
        let a = DMatrix::from_iterator(dim, dim, entries.iter().copied().take(dim * dim));
        symmetrize(
            &((&a * a.transpose() + DMatrix::identity(dim, dim) * 0.1) * 10f64.powi(exponent)),
        )
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        #[test]
        fn predict_update_stay_finite_and_symmetric(
            n in 1usize..=6,
            m in 1usize..=6,
            p_exponent in -6i32..=6,
            q_exponent in -6i32..=6,
            r_exponent in -6i32..=6,
            p_entries in proptest::collection::vec(-1.0f64..1.0, 36),
            q_entries in proptest::collection::vec(-1.0f64..1.0, 36),
            r_entries in proptest::collection::vec(-1.0f64..1.0, 36),
            f_entries in proptest::collection::vec(-1.0f64..1.0, 36),
            h_entries in proptest::collection::vec(-1.0f64..1.0, 36),
            z_entries in proptest::collection::vec(-1e3f64..1e3, 6),
        ) {
            let p0 = spd_from(&p_entries, n, p_exponent);
            let q = spd_from(&q_entries, n, q_exponent);
            let r = spd_from(&r_entries, m, r_exponent);
            let f = DMatrix::from_iterator(n, n, f_entries.iter().copied().take(n * n));
            let h = DMatrix::from_iterator(m, n, h_entries.iter().copied().take(m * n));
            let z = DVector::from_iterator(m, z_entries.iter().copied().take(m));
            let mut kf = KalmanFilter::new(DVector::zeros(n), p0, f, q, h, r).unwrap();
            for _ in 0..5 {
                kf.predict().unwrap();
                let innovation = kf.update(&z).unwrap();
                prop_assert!(innovation.mahalanobis_squared.is_finite());
                prop_assert!(kf.state().iter().all(|v| v.is_finite()));
                let p = kf.covariance();
                prop_assert!(p.iter().all(|v| v.is_finite()));
                prop_assert!(max_relative_asymmetry(p) <= 1e-12);
                prop_assert!(min_eigenvalue(p) >= -1e-9 * p.amax());
            }
        }
    }
}
