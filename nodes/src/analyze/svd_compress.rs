//! `analyze.svd_compress`: rank-k approximation of an image by its truncated singular value
//! decomposition, channel by channel.
//!
//! [`low_rank`] computes the SVD of one channel (an h × w matrix, f64, nalgebra) and keeps its
//! k largest singular triplets; [`SvdCompress`] is the thin operator around it.
//!
//! Determinism: channels are decomposed in parallel, each by nalgebra's sequential SVD, and the
//! results are gathered in channel order, so the output is bit-identical for any thread count.

use std::sync::Arc;

use nalgebra::DMatrix;
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};
use rayon::prelude::*;

use super::pca::{image_from_f64, image_samples_f64};
use super::quality::{default_range, error_stats, psnr_db};

/// Largest image side the SVD accepts, px (the decomposition is O(w·h·min(w, h))).
pub const MAX_SIDE: usize = 4096;

params! {
    /// Parameters of `analyze.svd_compress`.
    pub struct SvdCompressParams {
        /// Singular values kept per channel (k ≥ 1); capped at min(width, height). Default 8.
        rank: u32 = 8 => [min = 1],
    }
}

/// Truncated-SVD image compression (`analyze.svd_compress`). See [`low_rank`].
#[derive(Debug, Clone, PartialEq)]
pub struct SvdCompress {
    rank: usize,
}

impl Op for SvdCompress {
    type Params = SvdCompressParams;
    const ID: &'static str = "analyze.svd_compress";
    const SUMMARY: &'static str =
        "Rank-k approximation of an image by its truncated SVD, per channel.";
    const DOC: &'static str = r#"
Treats every channel of the image as an h × w matrix A (samples in f64), computes its singular
value decomposition A = U·Σ·Vᵀ (nalgebra, f64) and keeps the k = min(`rank`, w, h) largest
singular values: A_k = Σ_{i<k} σᵢ·uᵢ·vᵢᵀ. By the Eckart–Young–Mirsky theorem (C. Eckart and
G. Young, "The approximation of one matrix by another of lower rank", Psychometrika 1, 1936)
A_k is the best rank-k approximation in the Frobenius norm, with
‖A − A_k‖_F = √(Σ_{i≥k} σᵢ²).

Outputs: `image`, the reconstruction in the input's format (rounded and saturated for integer
depths); `singular_values`, a channels × min(w, h) Matrix (row c: channel c's σ, decreasing);
`metrics`: rank (k), storage_ratio = k·(w + h + 1)/(w·h) (numbers stored over samples),
frobenius_error = ‖A − A_k‖_F over all channels before rounding, eckart_young_error =
√(Σ discarded σ²) (equal to it up to rounding), relative_frobenius_error = ‖A − A_k‖_F/‖A‖_F,
energy_kept = Σ kept σ² / Σ σ², and mse, psnr_db of the output image against the input (peak
255 / 65535 / 1 by depth).

Speed–accuracy: the SVD costs O(w·h·min(w, h)) whatever k; k trades storage for error.

Example:
    "low_rank": (op: "analyze.svd_compress", inputs: { "image": "gray.image" }, params: (rank: 16)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to approximate, any pixel format, finite samples.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "image",
                PortType::Image,
                "Rank-k reconstruction, the input's format.",
            ),
            PortSpec::new(
                "singular_values",
                PortType::Matrix,
                "channels × min(w, h): singular values of every channel, decreasing.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "rank, storage_ratio, frobenius_error, eckart_young_error, relative_frobenius_error, energy_kept, mse, psnr_db.",
            ),
        ]
    }

    fn new(params: SvdCompressParams) -> Result<Self, String> {
        if params.rank == 0 {
            return Err("`rank` must be at least 1".into());
        }
        Ok(SvdCompress {
            rank: params.rank as usize,
        })
    }
}

impl Operator for SvdCompress {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (w, h) = (image.width(), image.height());
        if w == 0 || h == 0 {
            return Err(OpError::input("image", "is empty (0 pixels)"));
        }
        if w > MAX_SIDE || h > MAX_SIDE {
            return Err(OpError::input(
                "image",
                format!("is {w}×{h}; sides up to {MAX_SIDE} px are supported"),
            ));
        }
        let samples = image_samples_f64(image);
        if samples.iter().any(|v| !v.is_finite()) {
            return Err(OpError::input("image", "contains NaN or infinite samples"));
        }
        let c = image.channels().count();
        let planes: Vec<Vec<f64>> = (0..c)
            .map(|ch| samples.iter().skip(ch).step_by(c).copied().collect())
            .collect();
        let results: Vec<LowRank> = planes
            .par_iter()
            .map(|p| low_rank(p, w, h, self.rank))
            .collect();
        let k = self.rank.min(w).min(h);
        let mut rebuilt = vec![0.0; samples.len()];
        let (mut discarded, mut total, mut err2) = (0.0, 0.0, 0.0);
        let mut sigmas = Vec::with_capacity(c * w.min(h));
        for (ch, r) in results.iter().enumerate() {
            for (i, &v) in r.approximation.iter().enumerate() {
                rebuilt[i * c + ch] = v;
                let d = v - planes[ch][i];
                err2 += d * d;
            }
            total += r.singular_values.iter().map(|s| s * s).sum::<f64>();
            discarded += r.singular_values.iter().skip(k).map(|s| s * s).sum::<f64>();
            sigmas.extend(&r.singular_values);
        }
        let output = image_from_f64(w, h, image.channels(), image.depth(), &rebuilt)
            .map_err(OpError::failed)?;
        let errors = error_stats(&output, image);
        let norm2: f64 = samples.iter().map(|v| v * v).sum();
        let mut metrics = Metrics::new();
        metrics.insert("rank".into(), k as f64);
        metrics.insert(
            "storage_ratio".into(),
            (k * (w + h + 1)) as f64 / (w * h) as f64,
        );
        metrics.insert("frobenius_error".into(), err2.sqrt());
        metrics.insert("eckart_young_error".into(), discarded.sqrt());
        metrics.insert(
            "relative_frobenius_error".into(),
            if norm2 > 0.0 {
                (err2 / norm2).sqrt()
            } else {
                0.0
            },
        );
        metrics.insert(
            "energy_kept".into(),
            if total > 0.0 {
                1.0 - discarded / total
            } else {
                1.0
            },
        );
        metrics.insert("mse".into(), errors.mse);
        if let Some(p) = psnr_db(errors.mse, default_range(image)) {
            metrics.insert("psnr_db".into(), p);
        }
        let singular_values =
            Matrix::new(c, w.min(h), sigmas).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("image", Value::image(output))
            .with("singular_values", Value::Matrix(Arc::new(singular_values)))
            .with("metrics", Value::metrics(metrics)))
    }
}

/// A rank-k approximation of one channel.
#[derive(Debug, Clone, PartialEq)]
pub struct LowRank {
    /// All min(w, h) singular values, decreasing.
    pub singular_values: Vec<f64>,
    /// The rank-k approximation, row-major h × w.
    pub approximation: Vec<f64>,
}

/// The best rank-`rank` approximation (Frobenius norm) of the row-major `height × width`
/// matrix `plane` (finite samples, both sides ≥ 1; `rank` is capped at min(width, height)).
pub fn low_rank(plane: &[f64], width: usize, height: usize, rank: usize) -> LowRank {
    let a = DMatrix::from_row_slice(height, width, plane);
    let frobenius2 = a.norm_squared();
    let svd = a.clone().svd(true, true);
    // nalgebra 0.35's SVD with singular vectors returns wrong values for some exactly
    // low-rank inputs (dimforge/nalgebra#1172), and images often are: check Σσ² = ‖A‖²_F and
    // fall back to the Gram route when it fails.
    let sum2: f64 = svd.singular_values.iter().map(|s| s * s).sum();
    let trusted = (sum2 - frobenius2).abs() <= 1e-9 * frobenius2.max(f64::MIN_POSITIVE)
        && svd.u.is_some()
        && svd.v_t.is_some();
    if !trusted {
        return low_rank_by_gram(&a, rank);
    }
    // nalgebra sorts the singular values in decreasing order.
    let singular_values: Vec<f64> = svd.singular_values.iter().copied().collect();
    let mut approximation = vec![0.0; width * height];
    if let (Some(u), Some(v_t)) = (&svd.u, &svd.v_t) {
        for (i, &s) in singular_values.iter().enumerate().take(rank) {
            for y in 0..height {
                let us = u[(y, i)] * s;
                let row = &mut approximation[y * width..(y + 1) * width];
                for (x, out) in row.iter_mut().enumerate() {
                    *out += us * v_t[(i, x)];
                }
            }
        }
    }
    LowRank {
        singular_values,
        approximation,
    }
}

/// [`low_rank`] from the eigenvectors of AᵀA: A·V_k·V_kᵀ is the best rank-k approximation and
/// the singular values are √λ (the Gram matrix squares the condition number, which only costs
/// accuracy in singular values below ≈ 1e-8 of the largest).
fn low_rank_by_gram(a: &DMatrix<f64>, rank: usize) -> LowRank {
    let (height, width) = a.shape();
    let eig = nalgebra::SymmetricEigen::new(a.transpose() * a);
    let mut order: Vec<usize> = (0..eig.eigenvalues.len()).collect();
    order.sort_by(|&i, &j| {
        eig.eigenvalues[j]
            .total_cmp(&eig.eigenvalues[i])
            .then(i.cmp(&j))
    });
    order.truncate(width.min(height));
    let singular_values: Vec<f64> = order
        .iter()
        .map(|&i| eig.eigenvalues[i].max(0.0).sqrt())
        .collect();
    let k = rank.min(order.len());
    let v_k = DMatrix::from_fn(width, k, |r, c| eig.eigenvectors[(r, order[c])]);
    let approx = a * &v_k * v_k.transpose();
    let mut approximation = vec![0.0; width * height];
    for y in 0..height {
        for x in 0..width {
            approximation[y * width + x] = approx[(y, x)];
        }
    }
    LowRank {
        singular_values,
        approximation,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::filters::SplitMix64;
    use ocellus_engine::value::{Channels, Image};
    use proptest::prelude::*;

    fn frobenius(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt()
    }

    /// The fallback for nalgebra's low-rank SVD bug gives the same singular values and
    /// approximations as a trusted SVD.
    #[test]
    fn gram_route_agrees_with_the_svd() {
        let (w, h) = (7, 5);
        let plane: Vec<f64> = (0..w * h)
            .map(|i| ((i * 37 % 11) as f64) - 3.0 + (i as f64 * 0.1).sin())
            .collect();
        let a = DMatrix::from_row_slice(h, w, &plane);
        for rank in [1, 3, 5] {
            let svd = low_rank(&plane, w, h, rank);
            let gram = low_rank_by_gram(&a, rank);
            assert_eq!(svd.singular_values.len(), gram.singular_values.len());
            for (x, y) in svd.singular_values.iter().zip(&gram.singular_values) {
                assert!((x - y).abs() < 1e-9 * svd.singular_values[0], "{x} vs {y}");
            }
            for (x, y) in svd.approximation.iter().zip(&gram.approximation) {
                assert!((x - y).abs() < 1e-8, "rank {rank}: {x} vs {y}");
            }
        }
    }

    #[test]
    fn rank_one_outer_product() {
        // A = u·vᵀ has one singular value ‖u‖·‖v‖ and is rebuilt exactly at rank 1.
        let u = [1.0, 2.0, 2.0];
        let v = [3.0, 0.0, 4.0, 0.0];
        let a: Vec<f64> = u
            .iter()
            .flat_map(|&x| v.iter().map(move |&y| x * y))
            .collect();
        let r = low_rank(&a, 4, 3, 1);
        assert!((r.singular_values[0] - 15.0).abs() < 1e-12);
        assert!(r.singular_values[1..].iter().all(|s| s.abs() < 1e-12));
        assert!(frobenius(&a, &r.approximation) < 1e-12);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(16))]

        /// Eckart–Young: ‖A − A_k‖_F = √(Σ_{i≥k} σᵢ²), for any k, including 0 < k < rank and
        /// k beyond the smaller side (exact reconstruction).
        #[test]
        fn eckart_young(seed in 0u64..10_000, w in 1usize..24, h in 1usize..24, k in 1usize..30) {
            let mut rng = SplitMix64::new(seed);
            let a: Vec<f64> = (0..w * h).map(|_| rng.normal(0.0, 10.0)).collect();
            let r = low_rank(&a, w, h, k);
            prop_assert_eq!(r.singular_values.len(), w.min(h));
            prop_assert!(r.singular_values.windows(2).all(|p| p[0] >= p[1]));
            let discarded: f64 = r.singular_values.iter().skip(k).map(|s| s * s).sum();
            let err = frobenius(&a, &r.approximation);
            let norm = a.iter().map(|x| x * x).sum::<f64>().sqrt();
            prop_assert!((err - discarded.sqrt()).abs() <= 1e-9 * norm, "{} vs {}", err, discarded.sqrt());
        }
    }

    #[test]
    fn error_decreases_with_rank_and_operator_metrics() {
        let (w, h) = (48, 40);
        // A smooth image plus a little noise: the error falls quickly with k.
        let mut rng = SplitMix64::new(3);
        let data: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let v = 128.0
                    + 60.0 * (x / 7.0).sin() * (y / 9.0).cos()
                    + 30.0 * (x * y / 300.0).cos()
                    + rng.normal(0.0, 2.0);
                v.round().clamp(0.0, 255.0) as u8
            })
            .collect();
        let image = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        let specs = SvdCompress::inputs();
        let values = [Some(Value::image(image))];
        let ctx = RunContext {
            node: "svd".into(),
            threads: 1,
            element: None,
        };
        let mut last = f64::INFINITY;
        for rank in [1, 2, 4, 8, 40] {
            let op = SvdCompress::new(SvdCompressParams { rank }).unwrap();
            let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
            let Some(Value::Metrics(m)) = out.take("metrics") else {
                panic!("metrics")
            };
            let err = m["frobenius_error"];
            assert!((err - m["eckart_young_error"]).abs() < 1e-6 * (1.0 + err));
            assert!(err < last, "rank {rank}: {err} ≥ {last}");
            last = err;
            assert!(
                (m["storage_ratio"] - (rank as f64 * 89.0 / 1920.0)).abs() < 1e-12,
                "{}",
                m["storage_ratio"]
            );
            if rank == 40 {
                assert!(err < 1e-6);
                assert!(!m.contains_key("psnr_db"), "lossless at full rank");
            }
        }
        assert!(SvdCompress::new(SvdCompressParams { rank: 0 }).is_err());
        let nan = [Some(Value::image(
            Image::from_f32(2, 2, Channels::Gray, vec![f32::NAN; 4]).unwrap(),
        ))];
        let op = SvdCompress::new(SvdCompressParams { rank: 1 }).unwrap();
        assert!(op.run(&ctx, &Inputs::new(&specs, &nan)).is_err());
    }
}
