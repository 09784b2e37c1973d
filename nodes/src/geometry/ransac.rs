//! The robust sampling loops over any [`Estimator`]: RANSAC, MSAC, LO-RANSAC and PROSAC.
//!
//! [`estimate`] draws minimal samples with a seeded SplitMix64 stream, fits every model of each
//! sample, scores it on all data and keeps the best, stopping adaptively after
//! `T = log(1 − p) / log(1 − wˢ)` trials (`p` the confidence, `w` the best inlier ratio so far,
//! `s` the minimal sample size), clamped to `[min_trials, max_trials]` ([`required_trials`]).
//!
//! - RANSAC (Fischler & Bolles 1981) scores a model by its outlier count.
//! - MSAC (Torr & Zisserman 2000) scores it by the truncated quadratic `Σ min(rᵢ², t²)`, which
//!   prefers the model that fits its inliers more tightly among models with equal support.
//! - LO-RANSAC (Chum, Matas & Kittler 2003; the LO⁺ variant of Lebeda, Matas & Chum 2012) is
//!   MSAC plus a local optimisation each time the best model improves: an inner RANSAC draws
//!   non-minimal samples from the current inliers and fits them with
//!   [`Estimator::fit_nonminimal`], each followed by iterative least squares on the inliers of a
//!   threshold shrinking from `lo_threshold_multiplier · t` to `t`.
//! - PROSAC (Chum & Matas 2005) draws samples from a growing prefix of the data, which must be
//!   ordered best-first (e.g. matches by ascending descriptor distance); it reverts to uniform
//!   sampling once the prefix covers all data. It is scored and locally optimised as LO-RANSAC.
//!   The stopping rule is the standard one above (the paper's non-randomness test is not used).
//!
//! Every method ends with a least-squares refit on the best model's inliers, kept only if it
//! scores no worse. Everything is sequential and seeded: the same input and seed always give the
//! same result.

use super::robust::Estimator;
use crate::describe::brief::SplitMix64;

/// The sampling and scoring strategy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Uniform samples, outlier-count score.
    Ransac,
    /// Uniform samples, truncated quadratic score.
    Msac,
    /// MSAC with local optimisation of every new best model.
    LoRansac,
    /// Progressive samples from best-first ordered data, scored and optimised as LO-RANSAC.
    Prosac,
}

/// Options of the robust loops.
#[derive(Debug, Clone, PartialEq)]
pub struct RobustOptions {
    /// Sampling and scoring strategy.
    pub method: Method,
    /// Inlier threshold on the (unsquared) residual, in the data's units.
    pub threshold: f64,
    /// Probability of drawing at least one all-inlier sample, in (0, 1).
    pub confidence: f64,
    /// Fewest trials run even when the adaptive count is smaller.
    pub min_trials: usize,
    /// Most trials run.
    pub max_trials: usize,
    /// Seed of the sampling stream.
    pub seed: u64,
    /// Inner RANSAC repetitions per local optimisation.
    pub lo_inner_iterations: usize,
    /// Iterative least-squares steps per inner repetition.
    pub lo_ls_iterations: usize,
    /// Threshold multiplier of the first least-squares step.
    pub lo_threshold_multiplier: f64,
}

impl Default for RobustOptions {
    fn default() -> RobustOptions {
        RobustOptions {
            method: Method::LoRansac,
            threshold: 1.0,
            confidence: 0.999,
            min_trials: 0,
            max_trials: 10_000,
            seed: 0,
            lo_inner_iterations: 10,
            lo_ls_iterations: 4,
            lo_threshold_multiplier: 3.0,
        }
    }
}

/// Why no model was returned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RobustError {
    /// Fewer data than a minimal sample.
    #[error("{got} data, but at least {needed} are needed")]
    TooFewData {
        /// Minimal sample size.
        needed: usize,
        /// Data given.
        got: usize,
    },
    /// Fewer distinct data than a minimal sample (exact repeats count once).
    #[error("{got} distinct data among {total}, but at least {needed} are needed")]
    TooFewDistinct {
        /// Minimal sample size.
        needed: usize,
        /// Distinct data given.
        got: usize,
        /// Data given, repeats included.
        total: usize,
    },
    /// A datum holds NaN or an infinity.
    #[error("datum {index} is not finite")]
    NonFinite {
        /// Index of the first bad datum.
        index: usize,
    },
    /// Options out of range.
    #[error("invalid options: {0}")]
    InvalidOptions(String),
    /// Every sample was degenerate: no model could be fitted.
    #[error("no model could be fitted: every sample drawn was degenerate")]
    Degenerate,
    /// The best model is supported by fewer inliers than a minimal sample.
    #[error("the best model has {inliers} inliers, fewer than a minimal sample ({needed})")]
    NoConsensus {
        /// Inliers of the best model.
        inliers: usize,
        /// Minimal sample size.
        needed: usize,
    },
}

/// One improvement of the best model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Improvement {
    /// Trial (1-based) at which the model was found.
    pub trial: usize,
    /// Its score (lower is better).
    pub score: f64,
    /// Its inlier count.
    pub inliers: usize,
}

/// The result of a robust fit.
#[derive(Debug, Clone, PartialEq)]
pub struct RobustReport<M> {
    /// The best model, after the final least-squares refit.
    pub model: M,
    /// `true` for data within the threshold of `model`.
    pub inlier_mask: Vec<bool>,
    /// Number of `true` entries in `inlier_mask`.
    pub num_inliers: usize,
    /// Minimal samples drawn.
    pub trials: usize,
    /// Score of `model`: the outlier count (RANSAC) or `Σ min(r², t²)` (the others).
    pub score: f64,
    /// Every improvement of the best model, in order.
    pub history: Vec<Improvement>,
    /// Local optimisations run.
    pub local_optimizations: usize,
}

/// Trials needed to draw one all-inlier sample of size `sample_size` with probability
/// `confidence` when a share `inlier_ratio` of the data are inliers, clamped to
/// `[min_trials, max_trials]`.
pub fn required_trials(
    inlier_ratio: f64,
    sample_size: usize,
    confidence: f64,
    min_trials: usize,
    max_trials: usize,
) -> usize {
    let max_trials = max_trials.max(min_trials);
    let w_s = inlier_ratio.clamp(0.0, 1.0).powi(sample_size as i32);
    if w_s >= 1.0 {
        return min_trials.max(1).min(max_trials);
    }
    let denominator = (-w_s).ln_1p(); // log(1 − wˢ) < 0, exact for tiny wˢ
    if denominator == 0.0 || !denominator.is_finite() {
        return max_trials;
    }
    let trials = ((1.0 - confidence).ln() / denominator).ceil();
    if !trials.is_finite() || trials >= max_trials as f64 {
        max_trials
    } else {
        (trials.max(0.0) as usize).clamp(min_trials.max(1), max_trials)
    }
}

fn check_options(options: &RobustOptions) -> Result<(), RobustError> {
    let bad = |m: String| Err(RobustError::InvalidOptions(m));
    if !(options.threshold.is_finite() && options.threshold > 0.0) {
        return bad(format!("threshold must be > 0, got {}", options.threshold));
    }
    if !(options.confidence > 0.0 && options.confidence < 1.0) {
        return bad(format!(
            "confidence must be in (0, 1), got {}",
            options.confidence
        ));
    }
    if options.max_trials == 0 {
        return bad("max_trials must be at least 1".into());
    }
    if !(options.lo_threshold_multiplier.is_finite() && options.lo_threshold_multiplier >= 1.0) {
        return bad(format!(
            "lo_threshold_multiplier must be ≥ 1, got {}",
            options.lo_threshold_multiplier
        ));
    }
    Ok(())
}

/// Scores residuals: returns (score, inlier count).
fn score(method: Method, residuals: &[f64], t2: f64) -> (f64, usize) {
    let mut cost = 0.0;
    let mut inliers = 0;
    for &r in residuals {
        let inlier = r <= t2; // NaN residuals are outliers
        inliers += usize::from(inlier);
        cost += if inlier { r } else { t2 };
    }
    match method {
        Method::Ransac => ((residuals.len() - inliers) as f64, inliers),
        _ => (cost, inliers),
    }
}

/// Draws `k` distinct indices from `0..n` into `out` (rejection; `k ≤ n`, `k` small).
fn sample_indices(rng: &mut SplitMix64, n: usize, k: usize, out: &mut Vec<usize>) {
    out.clear();
    while out.len() < k {
        let i = rng.below(n);
        if !out.contains(&i) {
            out.push(i);
        }
    }
}

/// PROSAC's progressive sampling schedule (Chum & Matas 2005, section 2.3).
struct Prosac {
    n: usize,
    big_n: usize,
    m: usize,
    t_n: f64,
    t_n_prime: usize,
}

impl Prosac {
    /// Growth schedule for `big_n` data, samples of `m`, over `t_big_n` trials.
    fn new(big_n: usize, m: usize, t_big_n: usize) -> Prosac {
        let mut t_n = t_big_n as f64;
        for i in 0..m {
            t_n *= (m - i) as f64 / (big_n - i) as f64;
        }
        Prosac {
            n: m,
            big_n,
            m,
            t_n,
            t_n_prime: 1,
        }
    }

    /// The sample of trial `t` (1-based).
    fn sample(&mut self, t: usize, rng: &mut SplitMix64, out: &mut Vec<usize>) {
        while t > self.t_n_prime && self.n < self.big_n {
            let t_next = self.t_n * (self.n + 1) as f64 / (self.n + 1 - self.m) as f64;
            self.t_n_prime += (t_next - self.t_n).ceil().max(0.0) as usize;
            self.t_n = t_next;
            self.n += 1;
        }
        if self.n >= self.big_n || t > self.t_n_prime {
            // Prefix exhausted (or its schedule ran out): uniform from the prefix.
            sample_indices(rng, self.n, self.m, out);
        } else {
            // m − 1 from the first n − 1, plus the n-th.
            sample_indices(rng, self.n - 1, self.m - 1, out);
            out.push(self.n - 1);
        }
    }
}

/// Robustly fits `estimator` to `data`. For [`Method::Prosac`] the data must be ordered
/// best-first. See the module documentation.
pub fn estimate<E>(
    estimator: &E,
    data: &[E::Datum],
    options: &RobustOptions,
) -> Result<RobustReport<E::Model>, RobustError>
where
    E: Estimator,
    E::Datum: Clone,
{
    check_options(options)?;
    let s = E::MIN_SAMPLES;
    let n = data.len();
    if s == 0 || n < s {
        return Err(RobustError::TooFewData {
            needed: s.max(1),
            got: n,
        });
    }
    if let Some(index) = data.iter().position(|d| !estimator.datum_is_finite(d)) {
        return Err(RobustError::NonFinite { index });
    }
    let t2 = options.threshold * options.threshold;
    let method = options.method;
    let mut rng = SplitMix64::new(options.seed ^ 0x5DEE_CE66_D1CE_4E5B);
    let mut prosac = (method == Method::Prosac).then(|| Prosac::new(n, s, 200_000));
    let local = matches!(method, Method::LoRansac | Method::Prosac);

    let mut residuals = vec![0.0; n];
    let mut indices = Vec::with_capacity(s);
    let mut sample: Vec<E::Datum> = Vec::with_capacity(s);
    let mut best: Option<(E::Model, f64, usize)> = None;
    let mut history = Vec::new();
    let mut max_trials = options.max_trials.max(options.min_trials);
    let mut trials = 0;
    let mut local_optimizations = 0;
    // Consecutive degenerate draws; the loop gives up after many with no model at all.
    let mut fitted_any = false;

    while trials < max_trials {
        trials += 1;
        match prosac.as_mut() {
            Some(p) => p.sample(trials, &mut rng, &mut indices),
            None => sample_indices(&mut rng, n, s, &mut indices),
        }
        sample.clear();
        sample.extend(indices.iter().map(|&i| data[i].clone()));
        if estimator.is_degenerate(&sample) {
            continue;
        }
        let models = estimator.fit(&sample);
        for model in models {
            fitted_any = true;
            estimator.residuals(&model, data, &mut residuals);
            let (cost, inliers) = score(method, &residuals, t2);
            let better = best.as_ref().is_none_or(|b| cost < b.1);
            if !better {
                continue;
            }
            let (mut model, mut cost, mut inliers) = (model, cost, inliers);
            if local && inliers > s {
                local_optimizations += 1;
                if let Some(improved) = local_optimization(
                    estimator,
                    data,
                    &model,
                    cost,
                    options,
                    &mut rng,
                    &mut residuals,
                ) {
                    (model, cost, inliers) = improved;
                }
            }
            history.push(Improvement {
                trial: trials,
                score: cost,
                inliers,
            });
            best = Some((model, cost, inliers));
            let needed = required_trials(
                inliers as f64 / n as f64,
                s,
                options.confidence,
                options.min_trials,
                options.max_trials,
            );
            max_trials = needed.max(trials);
        }
    }

    let Some((mut model, mut cost, _)) = best else {
        debug_assert!(!fitted_any);
        return Err(RobustError::Degenerate);
    };
    // Final least-squares refit on the inliers, kept if no worse.
    for _ in 0..3 {
        estimator.residuals(&model, data, &mut residuals);
        let inliers: Vec<E::Datum> = data
            .iter()
            .zip(&residuals)
            .filter(|(_, r)| **r <= t2)
            .map(|(d, _)| d.clone())
            .collect();
        if inliers.len() <= s {
            break;
        }
        let mut improved = false;
        for candidate in estimator.fit_nonminimal(&inliers) {
            estimator.residuals(&candidate, data, &mut residuals);
            let (c, _) = score(method, &residuals, t2);
            if c <= cost {
                improved = c < cost;
                cost = c;
                model = candidate;
            }
        }
        if !improved {
            break;
        }
    }
    estimator.residuals(&model, data, &mut residuals);
    let inlier_mask: Vec<bool> = residuals.iter().map(|&r| r <= t2).collect();
    let num_inliers = inlier_mask.iter().filter(|&&b| b).count();
    if num_inliers < s {
        return Err(RobustError::NoConsensus {
            inliers: num_inliers,
            needed: s,
        });
    }
    let (score, _) = score(method, &residuals, t2);
    Ok(RobustReport {
        model,
        inlier_mask,
        num_inliers,
        trials,
        score,
        history,
        local_optimizations,
    })
}

/// LO⁺ local optimisation of `model` (score `cost`): returns a better (model, score, inliers).
fn local_optimization<E>(
    estimator: &E,
    data: &[E::Datum],
    model: &E::Model,
    cost: f64,
    options: &RobustOptions,
    rng: &mut SplitMix64,
    residuals: &mut [f64],
) -> Option<(E::Model, f64, usize)>
where
    E: Estimator,
    E::Datum: Clone,
{
    let s = E::MIN_SAMPLES;
    let t2 = options.threshold * options.threshold;
    let collect = |residuals: &[f64], limit: f64| -> Vec<E::Datum> {
        data.iter()
            .zip(residuals)
            .filter(|(_, r)| **r <= limit)
            .map(|(d, _)| d.clone())
            .collect()
    };
    let selected = |residuals: &[f64], limit: f64| -> Vec<usize> {
        (0..data.len()).filter(|&i| residuals[i] <= limit).collect()
    };
    let mut best: Option<(E::Model, f64, usize)> = None;
    let mut best_cost = cost;
    estimator.residuals(model, data, residuals);
    let inliers = collect(residuals, t2);
    if inliers.len() <= s {
        return None;
    }
    // Inner sample size as in LO⁺: 7·s, at most half the inliers (at least s + 1).
    let inner = (7 * s).min(inliers.len() / 2).max(s + 1).min(inliers.len());
    let mut indices = Vec::with_capacity(inner);
    let mut subset = Vec::with_capacity(inner);
    let consider = |candidate: E::Model,
                    residuals: &mut [f64],
                    best: &mut Option<(E::Model, f64, usize)>,
                    best_cost: &mut f64| {
        estimator.residuals(&candidate, data, residuals);
        let (c, k) = score(Method::Msac, residuals, t2);
        if c < *best_cost {
            *best_cost = c;
            *best = Some((candidate, c, k));
        }
    };
    let inlier_indices = selected(residuals, t2);
    for repetition in 0..options.lo_inner_iterations.max(1) {
        let seeds = if repetition == 0 {
            estimator.fit_nonminimal(&inliers)
        } else {
            sample_indices(rng, inliers.len(), inner, &mut indices);
            subset.clear();
            subset.extend(indices.iter().map(|&i| inliers[i].clone()));
            estimator.fit_nonminimal(&subset)
        };
        let single_seed = seeds.len() == 1;
        for seed_model in seeds {
            let mut current = seed_model;
            // The set of data `current` was fitted from (its first non-minimal model), when
            // known. Fitting that same set again would give the same model, so such a refit
            // and its scoring are skipped; the result is unchanged, bit for bit.
            let mut fitted_from: Option<Vec<usize>> =
                (repetition == 0 && single_seed).then(|| inlier_indices.clone());
            consider(current.clone(), residuals, &mut best, &mut best_cost);
            // Iterative least squares with a threshold shrinking to t.
            let steps = options.lo_ls_iterations;
            for step in 0..steps {
                estimator.residuals(&current, data, residuals);
                let m = options.lo_threshold_multiplier;
                let factor = if steps > 1 {
                    m - (m - 1.0) * step as f64 / (steps - 1) as f64
                } else {
                    1.0
                };
                let chosen = selected(residuals, t2 * factor * factor);
                if chosen.len() <= s {
                    break;
                }
                if fitted_from.as_ref() == Some(&chosen) {
                    continue;
                }
                let points: Vec<E::Datum> = chosen.iter().map(|&i| data[i].clone()).collect();
                let Some(next) = estimator.fit_nonminimal(&points).into_iter().next() else {
                    break;
                };
                current = next;
                fitted_from = Some(chosen);
                consider(current.clone(), residuals, &mut best, &mut best_cost);
            }
        }
    }
    best
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// How many data are flagged inliers both by `mask` and by the ground `truth`.
    pub(crate) fn true_positives(mask: &[bool], truth: &[bool]) -> usize {
        mask.iter().zip(truth).filter(|(m, t)| **m && **t).count()
    }

    /// The data ordered as a matcher would rank them for PROSAC: each datum's quality is a
    /// unit normal (drawn from `seed`), shifted by `shift` for the true ones (`truth`); sorted
    /// by decreasing quality. Returns the data and their truth in that order.
    pub(crate) fn ranked_by_quality<D: Copy>(
        data: &[D],
        truth: &[bool],
        shift: f64,
        seed: u64,
    ) -> (Vec<D>, Vec<bool>) {
        let mut rng = SplitMix64::new(seed);
        let mut ranked: Vec<(f64, D, bool)> = data
            .iter()
            .zip(truth)
            .map(|(d, &t)| (rng.normal() + if t { shift } else { 0.0 }, *d, t))
            .collect();
        ranked.sort_by(|a, b| b.0.total_cmp(&a.0));
        ranked.into_iter().map(|(_, d, t)| (d, t)).unzip()
    }

    /// A 1-D location model: the datum itself, MIN_SAMPLES 1, the mean as non-minimal fit.
    pub(crate) struct Location;

    impl Estimator for Location {
        type Datum = f64;
        type Model = f64;
        const MIN_SAMPLES: usize = 1;
        fn fit(&self, sample: &[f64]) -> Vec<f64> {
            vec![sample.iter().sum::<f64>() / sample.len() as f64]
        }
        fn residuals(&self, model: &f64, data: &[f64], residuals: &mut [f64]) {
            for (r, d) in residuals.iter_mut().zip(data) {
                *r = (d - model) * (d - model);
            }
        }
        fn datum_is_finite(&self, datum: &f64) -> bool {
            datum.is_finite()
        }
    }

    #[test]
    fn trial_count_matches_hand_values() {
        // log(0.01) / log(1 − 0.5⁴) = 71.36 → 72; log(0.001) / log(1 − 0.5⁸) = 1764.93 → 1765.
        assert_eq!(required_trials(0.5, 4, 0.99, 0, 100_000), 72);
        assert_eq!(required_trials(0.5, 8, 0.999, 0, 100_000), 1765);
        // w = 0.9, s = 2, p = 0.99: log(0.01)/log(0.19) = 2.77 → 3.
        assert_eq!(required_trials(0.9, 2, 0.99, 0, 100), 3);
        // Clamps.
        assert_eq!(required_trials(0.5, 8, 0.999, 0, 1000), 1000);
        assert_eq!(required_trials(0.9, 2, 0.99, 50, 100), 50);
        assert_eq!(required_trials(1.0, 4, 0.999, 0, 100), 1);
        assert_eq!(required_trials(0.0, 4, 0.999, 0, 100), 100);
        assert_eq!(required_trials(1e-6, 8, 0.999, 0, 7), 7);
    }

    /// Every fourth datum near 5.0 (50 of 200), the rest spread over [100, 1100].
    fn data_with_outliers() -> Vec<f64> {
        let mut rng = SplitMix64::new(3);
        (0..200)
            .map(|i| {
                if i % 4 == 0 {
                    5.0 + 0.1 * (rng.uniform() - 0.5)
                } else {
                    100.0 + 1000.0 * rng.uniform()
                }
            })
            .collect()
    }

    #[test]
    fn every_method_finds_the_inlier_cluster_deterministically() {
        let data = data_with_outliers();
        for method in [
            Method::Ransac,
            Method::Msac,
            Method::LoRansac,
            Method::Prosac,
        ] {
            let options = RobustOptions {
                method,
                threshold: 0.2,
                seed: 7,
                ..RobustOptions::default()
            };
            let a = estimate(&Location, &data, &options).unwrap();
            let b = estimate(&Location, &data, &options).unwrap();
            assert_eq!(a, b);
            assert!((a.model - 5.0).abs() < 0.02, "{method:?}: {}", a.model);
            assert_eq!(a.num_inliers, 50, "{method:?}");
            assert!(a.trials >= 1 && a.trials <= 10_000);
            assert!(!a.history.is_empty());
            assert!(a.history.windows(2).all(|w| w[1].score < w[0].score));
            assert!(a.history.windows(2).all(|w| w[1].trial >= w[0].trial));
        }
    }

    #[test]
    fn bad_input_is_a_typed_error() {
        let options = RobustOptions::default();
        assert_eq!(
            estimate(&Location, &[], &options),
            Err(RobustError::TooFewData { needed: 1, got: 0 })
        );
        assert_eq!(
            estimate(&Location, &[1.0, f64::NAN], &options),
            Err(RobustError::NonFinite { index: 1 })
        );
        let bad = RobustOptions {
            confidence: 1.0,
            ..RobustOptions::default()
        };
        assert!(matches!(
            estimate(&Location, &[1.0], &bad),
            Err(RobustError::InvalidOptions(_))
        ));
    }

    /// An estimator whose every sample is degenerate.
    struct Never;

    impl Estimator for Never {
        type Datum = f64;
        type Model = f64;
        const MIN_SAMPLES: usize = 2;
        fn fit(&self, _sample: &[f64]) -> Vec<f64> {
            Vec::new()
        }
        fn residuals(&self, _model: &f64, _data: &[f64], _residuals: &mut [f64]) {}
    }

    #[test]
    fn all_degenerate_samples_are_an_error() {
        let options = RobustOptions {
            max_trials: 50,
            ..RobustOptions::default()
        };
        assert_eq!(
            estimate(&Never, &[1.0, 2.0, 3.0], &options),
            Err(RobustError::Degenerate)
        );
    }

    #[test]
    fn prosac_schedule_grows_the_prefix_and_stays_in_range() {
        let mut p = Prosac::new(100, 4, 200_000);
        let mut rng = SplitMix64::new(1);
        let mut out = Vec::new();
        let mut last_n = p.n;
        for t in 1..5000 {
            p.sample(t, &mut rng, &mut out);
            assert_eq!(out.len(), 4);
            assert!(out.iter().all(|&i| i < p.n));
            let mut sorted = out.clone();
            sorted.sort_unstable();
            sorted.dedup();
            assert_eq!(sorted.len(), 4);
            assert!(p.n >= last_n);
            last_n = p.n;
        }
        assert!(last_n > 4);
    }
}
