//! The estimator interface shared by every robust estimation method.
//!
//! An estimator knows how to fit models to a minimal sample and how to score data against a model.
//! The sampling loops (RANSAC, MSAC, LO-RANSAC, PROSAC) are written once against this trait.
//! Reference: Fischler & Bolles, "Random sample consensus", CACM 1981; COLMAP's
//! `estimators/` (Schönberger & Frahm, CVPR 2016).

/// A model estimator for robust fitting.
///
/// `Datum` is one observation (a 2-D point, a correspondence `(x1, x2)`, a 2-D/3-D pair, ...).
/// Residuals are **squared** distances in the data's units (pixels² for image data), so that
/// thresholds compare against `threshold²` and no square root is paid per datum.
pub trait Estimator {
    /// One observation.
    type Datum;
    /// The fitted model.
    type Model: Clone;

    /// Size of a minimal sample.
    const MIN_SAMPLES: usize;

    /// Fits every model consistent with a minimal sample (`sample.len() == MIN_SAMPLES`), or with
    /// more data in the least-squares sense. Minimal solvers may return several models (7-point F,
    /// 5-point E, P3P) or none (degenerate sample); they never return a model with NaN entries.
    fn fit(&self, sample: &[Self::Datum]) -> Vec<Self::Model>;

    /// Writes the squared residual of every datum under `model` into `residuals`
    /// (`residuals.len() == data.len()`).
    fn residuals(&self, model: &Self::Model, data: &[Self::Datum], residuals: &mut [f64]);

    /// Least-squares fit to a non-minimal set (all inliers), used by local optimization and the
    /// final refit. Defaults to [`Estimator::fit`], which must then accept any sample size
    /// `≥ MIN_SAMPLES`.
    fn fit_nonminimal(&self, data: &[Self::Datum]) -> Vec<Self::Model> {
        self.fit(data)
    }

    /// Whether a minimal sample is degenerate before fitting (e.g. three collinear points of a
    /// homography sample). Cheap checks only; defaults to never.
    fn is_degenerate(&self, _sample: &[Self::Datum]) -> bool {
        false
    }

    /// Whether a datum is usable (all coordinates finite). The robust loops reject data holding
    /// a datum for which this is false with a typed error instead of fitting garbage. Defaults
    /// to always true; estimators over floating-point data should override it.
    fn datum_is_finite(&self, _datum: &Self::Datum) -> bool {
        true
    }
}
