//! The `learn` family: regression, classification and a sliding-window detector.
//!
//! Shared pieces: the design matrix with optional standardisation ([`Design`]), the
//! deterministic chunked sums every solver uses, and Matrix port helpers.

pub mod dataset;
pub mod hog_detector;
pub mod lbfgs;
pub mod linear;
pub mod logistic;
pub mod pedestrians;

use std::sync::Arc;

use ocellus_engine::op::OpError;
use ocellus_engine::value::{Matrix, Value};
use rayon::prelude::*;

/// Samples per parallel chunk of every sum over samples: a constant, never derived from the
/// thread count, so partial sums (added in chunk order) are bit-identical for any thread count.
pub const CHUNK: usize = 2048;

/// Registers the `learn` operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    registry.register::<dataset::Dataset>()?;
    registry.register::<linear::LinearRegression>()?;
    registry.register::<logistic::LogisticRegression>()?;
    registry.register::<pedestrians::Pedestrians>()?;
    registry.register::<hog_detector::HogDetector>()?;
    Ok(())
}

/// Samples as rows with a leading 1 (the bias column), optionally standardised: column j is
/// `(x_j − mean_j) / scale_j`. Parameters fitted on it map back to the original units with
/// [`Design::to_original`].
#[derive(Debug, Clone, PartialEq)]
pub struct Design {
    /// Samples.
    pub n: usize,
    /// Columns including the bias: features + 1.
    pub p: usize,
    /// Row-major `n × p`, first column all ones.
    pub z: Vec<f64>,
    /// Mean of every feature (zeros without standardisation).
    pub mean: Vec<f64>,
    /// Standard deviation of every feature (ones without standardisation; 1 for a constant
    /// feature).
    pub scale: Vec<f64>,
}

impl Design {
    /// Builds the design matrix of `x` (rows = samples). Errors on an empty matrix or
    /// non-finite entries, naming `port`.
    pub fn new(x: &Matrix, standardise: bool, port: &str) -> Result<Design, String> {
        let (n, d) = (x.rows, x.cols);
        if n == 0 || d == 0 {
            return Err(format!("`{port}` is empty ({n}×{d})"));
        }
        if x.data.iter().any(|v| !v.is_finite()) {
            return Err(format!("`{port}` holds a NaN or infinite entry"));
        }
        let mut mean = vec![0.0; d];
        let mut scale = vec![1.0; d];
        if standardise {
            for (j, (m, s)) in mean.iter_mut().zip(scale.iter_mut()).enumerate() {
                let mu = (0..n).map(|i| x.data[i * d + j]).sum::<f64>() / n as f64;
                let var = (0..n)
                    .map(|i| (x.data[i * d + j] - mu).powi(2))
                    .sum::<f64>()
                    / n as f64;
                *m = mu;
                let sd = var.sqrt();
                *s = if sd > 0.0 && sd.is_finite() { sd } else { 1.0 };
            }
        }
        let p = d + 1;
        let mut z = vec![0.0; n * p];
        for (row, xr) in z.chunks_exact_mut(p).zip(x.data.chunks_exact(d)) {
            row[0] = 1.0;
            for (((out, v), m), s) in row[1..].iter_mut().zip(xr).zip(&mean).zip(&scale) {
                *out = (v - m) / s;
            }
        }
        Ok(Design {
            n,
            p,
            z,
            mean,
            scale,
        })
    }

    /// Parameters `[bias, w_1..w_d]` of the standardised problem in the original units:
    /// `w_j / scale_j` and `bias − Σ w_j·mean_j / scale_j`.
    pub fn to_original(&self, theta: &[f64]) -> Vec<f64> {
        let mut out = theta.to_vec();
        let mut bias = theta[0];
        for (((o, t), s), m) in out[1..]
            .iter_mut()
            .zip(&theta[1..])
            .zip(&self.scale)
            .zip(&self.mean)
        {
            *o = t / s;
            bias -= *o * m;
        }
        out[0] = bias;
        out
    }

    /// Row `i`.
    pub fn row(&self, i: usize) -> &[f64] {
        &self.z[i * self.p..(i + 1) * self.p]
    }
}

/// Dot product.
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Euclidean norm.
pub fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

/// Σ over samples of `per_sample(i, row, grad)` returning a loss term and adding into a
/// `p`-vector: computed in chunks of [`CHUNK`] samples in parallel and reduced in chunk order,
/// so the sums are bit-identical for any thread count. Returns `(Σ loss, Σ grad)`.
pub fn chunked_sum<F>(design: &Design, per_sample: F) -> (f64, Vec<f64>)
where
    F: Fn(usize, &[f64], &mut [f64]) -> f64 + Sync,
{
    let p = design.p;
    let parts: Vec<(f64, Vec<f64>)> = design
        .z
        .par_chunks(CHUNK * p)
        .enumerate()
        .map(|(c, rows)| {
            let mut g = vec![0.0; p];
            let mut loss = 0.0;
            for (k, row) in rows.chunks_exact(p).enumerate() {
                loss += per_sample(c * CHUNK + k, row, &mut g);
            }
            (loss, g)
        })
        .collect();
    let mut loss = 0.0;
    let mut grad = vec![0.0; p];
    for (l, g) in parts {
        loss += l;
        for (a, b) in grad.iter_mut().zip(g) {
            *a += b;
        }
    }
    (loss, grad)
}

/// A Matrix value, or a failure naming the output.
pub fn matrix_value(rows: usize, cols: usize, data: Vec<f64>) -> Result<Value, OpError> {
    Matrix::new(rows, cols, data)
        .map(|m| Value::Matrix(Arc::new(m)))
        .map_err(|e| OpError::failed(e.to_string()))
}

/// The single column of `m` (port `port`), checked finite.
pub fn single_column(m: &Matrix, port: &str) -> Result<Vec<f64>, String> {
    if m.cols != 1 {
        return Err(format!(
            "`{port}` must have one column, got {}×{}",
            m.rows, m.cols
        ));
    }
    if m.data.iter().any(|v| !v.is_finite()) {
        return Err(format!("`{port}` holds a NaN or infinite entry"));
    }
    Ok(m.data.clone())
}

/// A loss curve as a `k × 2` matrix (iteration, loss).
pub fn loss_curve_value(curve: &[f64]) -> Result<Value, OpError> {
    let data = curve
        .iter()
        .enumerate()
        .flat_map(|(i, &l)| [i as f64, l])
        .collect();
    matrix_value(curve.len(), 2, data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn standardised_parameters_map_back_to_original_units() {
        let x = Matrix::new(4, 2, vec![1.0, 10.0, 2.0, 30.0, 3.0, 20.0, 4.0, 60.0]).unwrap();
        let d = Design::new(&x, true, "x").unwrap();
        let theta = [0.5, 2.0, -1.0];
        let w = d.to_original(&theta);
        for i in 0..4 {
            let standardised = dot(d.row(i), &theta);
            let original = w[0] + w[1] * x.data[2 * i] + w[2] * x.data[2 * i + 1];
            assert!((standardised - original).abs() < 1e-12);
        }
        // Standardised columns have mean 0 and variance 1.
        let m: f64 = (0..4).map(|i| d.row(i)[1]).sum::<f64>() / 4.0;
        let v: f64 = (0..4).map(|i| d.row(i)[1].powi(2)).sum::<f64>() / 4.0;
        assert!(m.abs() < 1e-12 && (v - 1.0).abs() < 1e-12);
    }

    #[test]
    fn design_rejects_nan_and_empty() {
        let x = Matrix::new(2, 1, vec![1.0, f64::NAN]).unwrap();
        assert!(Design::new(&x, false, "x").unwrap_err().contains("`x`"));
        let e = Matrix::new(0, 3, vec![]).unwrap();
        assert!(Design::new(&e, false, "x").is_err());
    }
}
