//! `analyze.pca`: principal component analysis (Karhunen–Loève transform) of a set of images.
//!
//! [`pca`] centres the images on their mean and diagonalises their sample covariance in f64;
//! when there are fewer images than samples per image it diagonalises the N × N Gram matrix
//! instead (the "snapshot" method of Sirovich, used for eigenfaces by Turk and Pentland) and
//! maps its eigenvectors back to image space. [`Pca`] is the thin operator around it: it also
//! picks the number of components, projects every image on them and reconstructs it.
//!
//! # Determinism
//!
//! Every entry of the Gram (or covariance) matrix is one dot product summed sequentially in
//! index order; rows are computed in parallel but never split, so the matrix — and the
//! sequential nalgebra eigensolver after it — give bit-identical results for any thread count.
//! Eigenvector signs are fixed so that the entry of largest magnitude is positive.

use std::sync::Arc;

use nalgebra::{DMatrix, SymmetricEigen};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, Matrix, Metrics, PixelData, Value};
use rayon::prelude::*;

use super::quality::{default_range, psnr_db};

/// Eigenvalues below this fraction of the largest are treated as zero (numerical rank).
const RANK_RELATIVE_TOLERANCE: f64 = 1e-10;

/// Largest number of images when there are fewer images than samples (the Gram matrix is
/// N × N).
pub const MAX_IMAGES: usize = 4096;

/// Largest number of samples per image when there are more images than samples (the
/// covariance matrix is D × D).
pub const MAX_COVARIANCE_DIM: usize = 4096;

params! {
    /// Parameters of `analyze.pca`.
    pub struct PcaParams {
        /// Number of principal components kept. Default 0: the smallest number whose
        /// eigenvalues explain at least `keep_variance` of the total variance. Capped at the
        /// numerical rank of the data.
        components: u32 = 0,
        /// Share of the total variance the kept components must explain, in (0, 1]; used
        /// only when `components` is 0. Default 0.95.
        keep_variance: f64 = 0.95,
    }
}

/// Principal component analysis of an image set (`analyze.pca`). See [`pca`].
#[derive(Debug, Clone, PartialEq)]
pub struct Pca {
    selection: ComponentSelection,
}

/// How many components [`Pca`] keeps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ComponentSelection {
    /// A fixed number (capped at the rank).
    Fixed(usize),
    /// The fewest components explaining at least this share of the variance.
    VarianceShare(f64),
}

impl Op for Pca {
    type Params = PcaParams;
    const ID: &'static str = "analyze.pca";
    const SUMMARY: &'static str = "Principal component analysis (eigenimages) of an image set, with projection and reconstruction.";
    const DOC: &'static str = r#"
Principal component analysis — the Karhunen–Loève transform — of N images of the same size
and format (every sample of every channel is one coordinate, D = width·height·channels):

- mean image m = (1/N)·Σ xᵢ; centred data X (N × D, row i = xᵢ − m);
- sample covariance C = XᵀX / (N − 1), eigen-decomposed in f64 (nalgebra's symmetric
  eigensolver). When N ≤ D the N × N Gram matrix G = XXᵀ / (N − 1) is decomposed instead:
  G·v = λ·v gives C·(Xᵀv) = λ·(Xᵀv), so the eigenimage is u = Xᵀv / √((N − 1)·λ) (the
  snapshot method: L. Sirovich, "Turbulence and the dynamics of coherent structures", Q. Appl.
  Math. 45, 1987; M. Turk and A. Pentland, "Eigenfaces for recognition", J. Cognitive
  Neuroscience 3(1), 1991);
- components are ordered by decreasing eigenvalue; eigenvalues below 1e−10 of the largest
  count as zero, so at most min(N − 1, D) components exist (the rank);
- K = `components`, or when that is 0 the smallest K whose eigenvalues sum to at least
  `keep_variance` of the total;
- every image is projected, cᵢ = Uᵀ(xᵢ − m), and reconstructed, x̂ᵢ = m + U·cᵢ. On the
  training set the squared reconstruction error sums to (N − 1)·Σ_{j>K} λⱼ.

Outputs: `mean` (f32, the input's channels), `eigenimages` (K unit-norm f32 images, sign
fixed so the largest-magnitude sample is positive), `eigenvalues` (Matrix, one row per
component up to the rank: eigenvalue in squared sample units, its share of the variance, the
cumulative share), `coefficients` (N × K Matrix), `reconstructions` (the input's format,
rounded and saturated for integer depths) and `metrics`: images, samples, rank, components,
explained_variance (cumulative share at K), rmse (over all reconstructed samples, before
rounding, sample units), psnr_db (peak 255 / 65535 / 1 by depth), gram (1 when the Gram
matrix was used).

Speed–accuracy: the decomposition costs O(N²·D) whatever K is; K sets the reconstruction
error and the cost of projection and reconstruction, O(N·K·D), and the storage, K·D + N·K.

Errors: an empty list, images of different sizes or formats, NaN or infinite samples.

Example:
    "eigen": (op: "analyze.pca", inputs: { "images": "faces.faces" }, params: (keep_variance: 0.9)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "images",
            PortType::Image.list_of(),
            "Images of the same size and pixel format (at least one).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mean", PortType::Image, "Mean image, f32."),
            PortSpec::new(
                "eigenimages",
                PortType::Image.list_of(),
                "The K kept principal components as unit-norm f32 images, largest first.",
            ),
            PortSpec::new(
                "eigenvalues",
                PortType::Matrix,
                "rank × 3: eigenvalue, variance share, cumulative share.",
            ),
            PortSpec::new(
                "coefficients",
                PortType::Matrix,
                "N × K: projection of every image on the kept components.",
            ),
            PortSpec::new(
                "reconstructions",
                PortType::Image.list_of(),
                "Every image rebuilt from K components, the input's format.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "images, samples, rank, components, explained_variance, rmse, psnr_db, gram.",
            ),
        ]
    }

    fn new(params: PcaParams) -> Result<Self, String> {
        let PcaParams {
            components,
            keep_variance,
        } = params;
        let selection = if components > 0 {
            ComponentSelection::Fixed(components as usize)
        } else {
            if !(keep_variance.is_finite() && keep_variance > 0.0 && keep_variance <= 1.0) {
                return Err(format!(
                    "`keep_variance` must be in (0, 1], got {keep_variance}"
                ));
            }
            ComponentSelection::VarianceShare(keep_variance)
        };
        Ok(Pca { selection })
    }
}

impl Operator for Pca {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let images = image_list(inputs, "images")?;
        let first = images
            .first()
            .ok_or_else(|| OpError::input("images", "the list is empty"))?;
        let (w, h, channels) = (first.width(), first.height(), first.channels());
        let data = images
            .iter()
            .map(|img| image_samples_f64(img))
            .collect::<Vec<_>>();
        let model = pca(&data).map_err(|e| OpError::input("images", e))?;
        let k = model.select(self.selection);
        let coefficients = model.project(&data, k);
        let rebuilt = model.reconstruct(&coefficients, k);
        let (mut sq, mut count) = (0.0, 0usize);
        for (x, r) in data.iter().zip(&rebuilt) {
            sq += x.iter().zip(r).map(|(a, b)| (a - b) * (a - b)).sum::<f64>();
            count += x.len();
        }
        let mse = sq / count.max(1) as f64;

        let to_f32_image =
            |v: &[f64]| image_from_f64(w, h, channels, Depth::F32, v).map_err(OpError::failed);
        let mean = to_f32_image(&model.mean)?;
        let eigenimages = (0..k)
            .map(|j| to_f32_image(model.component(j)).map(Value::image))
            .collect::<Result<Vec<_>, _>>()?;
        let reconstructions = rebuilt
            .iter()
            .map(|r| image_from_f64(w, h, channels, first.depth(), r).map(Value::image))
            .collect::<Result<Vec<_>, _>>()
            .map_err(OpError::failed)?;
        let total: f64 = model.eigenvalues.iter().sum();
        let mut table = Vec::with_capacity(model.rank() * 3);
        let mut cumulative = 0.0;
        for &l in &model.eigenvalues {
            cumulative += l;
            table.extend([l, share(l, total), share(cumulative, total)]);
        }
        let eigenvalues =
            Matrix::new(model.rank(), 3, table).map_err(|e| OpError::failed(e.to_string()))?;
        let coefficients = Matrix::new(data.len(), k, coefficients.concat())
            .map_err(|e| OpError::failed(e.to_string()))?;

        let mut metrics = Metrics::new();
        metrics.insert("images".into(), data.len() as f64);
        metrics.insert("samples".into(), model.mean.len() as f64);
        metrics.insert("rank".into(), model.rank() as f64);
        metrics.insert("components".into(), k as f64);
        metrics.insert("explained_variance".into(), model.explained(k));
        metrics.insert("rmse".into(), mse.sqrt());
        if let Some(p) = psnr_db(mse, default_range(first)) {
            metrics.insert("psnr_db".into(), p);
        }
        metrics.insert("gram".into(), f64::from(u8::from(model.used_gram)));
        Ok(Outputs::new()
            .with("mean", Value::image(mean))
            .with("eigenimages", Value::list(PortType::Image, eigenimages))
            .with("eigenvalues", Value::Matrix(Arc::new(eigenvalues)))
            .with("coefficients", Value::Matrix(Arc::new(coefficients)))
            .with(
                "reconstructions",
                Value::list(PortType::Image, reconstructions),
            )
            .with("metrics", Value::metrics(metrics)))
    }
}

fn share(part: f64, total: f64) -> f64 {
    if total > 0.0 { part / total } else { 0.0 }
}

/// The images of list port `port`: all of the same size and format, finite samples, at least
/// one pixel.
pub(crate) fn image_list<'a>(
    inputs: &Inputs<'a>,
    port: &str,
) -> Result<Vec<&'a Arc<Image>>, OpError> {
    let Value::List(list) = inputs.require(port)? else {
        return Err(OpError::input(port, "expected a list of images"));
    };
    let mut images = Vec::with_capacity(list.items.len());
    for (i, item) in list.items.iter().enumerate() {
        let Value::Image(img) = item else {
            return Err(OpError::input(
                port,
                format!("element {i} is a {}, not an Image", item.port_type()),
            ));
        };
        images.push(img);
    }
    if let Some(first) = images.first() {
        if first.width() == 0 || first.height() == 0 {
            return Err(OpError::input(port, "images are empty (0 pixels)"));
        }
        for (i, img) in images.iter().enumerate() {
            if img.format() != first.format()
                || img.width() != first.width()
                || img.height() != first.height()
            {
                return Err(OpError::input(
                    port,
                    format!(
                        "image {i} is {}×{} {} {}, but image 0 is {}×{} {} {}",
                        img.width(),
                        img.height(),
                        img.channels().name(),
                        img.depth().name(),
                        first.width(),
                        first.height(),
                        first.channels().name(),
                        first.depth().name()
                    ),
                ));
            }
            if let Some(s) = img.as_f32()
                && s.iter().any(|v| !v.is_finite())
            {
                return Err(OpError::input(
                    port,
                    format!("image {i} contains NaN or infinite samples"),
                ));
            }
        }
    }
    Ok(images)
}

/// All samples of `image` (channels interleaved, row-major) as f64.
pub fn image_samples_f64(image: &Image) -> Vec<f64> {
    match image.data() {
        PixelData::U8(v) => v.iter().map(|&s| f64::from(s)).collect(),
        PixelData::U16(v) => v.iter().map(|&s| f64::from(s)).collect(),
        PixelData::F32(v) => v.iter().map(|&s| f64::from(s)).collect(),
    }
}

/// An image of the given layout from f64 samples: rounded and saturated for integer depths,
/// narrowed to f32 otherwise.
pub fn image_from_f64(
    width: usize,
    height: usize,
    channels: Channels,
    depth: Depth,
    samples: &[f64],
) -> Result<Image, String> {
    let data = match depth {
        Depth::U8 => PixelData::U8(
            samples
                .iter()
                .map(|&v| v.round().clamp(0.0, 255.0) as u8)
                .collect(),
        ),
        Depth::U16 => PixelData::U16(
            samples
                .iter()
                .map(|&v| v.round().clamp(0.0, 65535.0) as u16)
                .collect(),
        ),
        Depth::F32 => PixelData::F32(samples.iter().map(|&v| v as f32).collect()),
    };
    Image::new(width, height, channels, data).map_err(|e| e.to_string())
}

/// A fitted principal component model.
#[derive(Debug, Clone, PartialEq)]
pub struct PcaModel {
    /// Mean of the data, D samples.
    pub mean: Vec<f64>,
    /// Eigenvalues of the sample covariance, decreasing, only those above the rank tolerance.
    pub eigenvalues: Vec<f64>,
    /// Unit eigenvectors, one per eigenvalue, each D samples, concatenated.
    pub components: Vec<f64>,
    /// Whether the N × N Gram matrix was decomposed (N ≤ D) rather than the D × D covariance.
    pub used_gram: bool,
}

impl PcaModel {
    /// The numerical rank: the number of components.
    pub fn rank(&self) -> usize {
        self.eigenvalues.len()
    }

    /// Component `j` (unit norm, D samples).
    pub fn component(&self, j: usize) -> &[f64] {
        let d = self.mean.len();
        &self.components[j * d..(j + 1) * d]
    }

    /// Cumulative share of the variance explained by the first `k` components (1 when the data
    /// has no variance).
    pub fn explained(&self, k: usize) -> f64 {
        let total: f64 = self.eigenvalues.iter().sum();
        if total <= 0.0 {
            return 1.0;
        }
        self.eigenvalues.iter().take(k).sum::<f64>() / total
    }

    /// The number of components a selection keeps (never more than the rank).
    pub fn select(&self, selection: ComponentSelection) -> usize {
        match selection {
            ComponentSelection::Fixed(k) => k.min(self.rank()),
            ComponentSelection::VarianceShare(share) => {
                let total: f64 = self.eigenvalues.iter().sum();
                let mut cumulative = 0.0;
                for (j, &l) in self.eigenvalues.iter().enumerate() {
                    // The relative slack keeps a share of exactly 1 reachable despite rounding.
                    if cumulative >= share * total * (1.0 - 1e-12) {
                        return j;
                    }
                    cumulative += l;
                }
                self.rank()
            }
        }
    }

    /// Coefficients of every vector on the first `k` components: cᵢ = Uᵀ(xᵢ − m).
    pub fn project(&self, data: &[Vec<f64>], k: usize) -> Vec<Vec<f64>> {
        data.par_iter()
            .map(|x| {
                (0..k)
                    .map(|j| {
                        self.component(j)
                            .iter()
                            .zip(x.iter().zip(&self.mean))
                            .map(|(u, (v, m))| u * (v - m))
                            .sum()
                    })
                    .collect()
            })
            .collect()
    }

    /// Vectors rebuilt from their first `k` coefficients: x̂ = m + U·c.
    pub fn reconstruct(&self, coefficients: &[Vec<f64>], k: usize) -> Vec<Vec<f64>> {
        coefficients
            .par_iter()
            .map(|c| {
                let mut x = self.mean.clone();
                for (j, &cj) in c.iter().take(k).enumerate() {
                    for (xi, u) in x.iter_mut().zip(self.component(j)) {
                        *xi += cj * u;
                    }
                }
                x
            })
            .collect()
    }
}

/// Fits a principal component model to `data` (N vectors of D samples each, N ≥ 1, D ≥ 1,
/// finite). Uses the Gram matrix when N ≤ D, the covariance matrix otherwise; see [`Pca`].
pub fn pca(data: &[Vec<f64>]) -> Result<PcaModel, String> {
    let use_gram = data.len() <= data.first().map_or(0, Vec::len);
    pca_with(data, use_gram)
}

/// [`pca`] with the method chosen by the caller: the N × N Gram matrix (`use_gram`) or the
/// D × D covariance. Both give the same model up to rounding.
pub fn pca_with(data: &[Vec<f64>], use_gram: bool) -> Result<PcaModel, String> {
    let n = data.len();
    let d = data.first().map_or(0, Vec::len);
    if n == 0 || d == 0 {
        return Err("needs at least one vector of at least one sample".into());
    }
    if data.iter().any(|x| x.len() != d) {
        return Err("all vectors must have the same length".into());
    }
    if data.iter().flatten().any(|v| !v.is_finite()) {
        return Err("samples must be finite".into());
    }
    if use_gram && n > MAX_IMAGES {
        return Err(format!(
            "the Gram method needs at most {MAX_IMAGES} vectors, got {n}"
        ));
    }
    if !use_gram && d > MAX_COVARIANCE_DIM {
        return Err(format!(
            "the covariance method needs at most {MAX_COVARIANCE_DIM} samples per vector, got {d}"
        ));
    }
    let mut mean = vec![0.0; d];
    for x in data {
        for (m, v) in mean.iter_mut().zip(x) {
            *m += v;
        }
    }
    for m in &mut mean {
        *m /= n as f64;
    }
    let centred: Vec<Vec<f64>> = data
        .iter()
        .map(|x| x.iter().zip(&mean).map(|(v, m)| v - m).collect())
        .collect();
    let dof = (n.max(2) - 1) as f64;
    let mut eigenvalues = Vec::new();
    let mut components = Vec::new();
    if n == 1 {
        return Ok(PcaModel {
            mean,
            eigenvalues,
            components,
            used_gram: use_gram,
        });
    }
    let dim = if use_gram { n } else { d };
    let rows: Vec<Vec<f64>> = (0..dim)
        .into_par_iter()
        .map(|i| {
            (0..dim)
                .map(|j| {
                    if use_gram {
                        dot(&centred[i], &centred[j]) / dof
                    } else {
                        centred.iter().map(|x| x[i] * x[j]).sum::<f64>() / dof
                    }
                })
                .collect()
        })
        .collect();
    let matrix = DMatrix::from_fn(dim, dim, |i, j| rows[i][j]);
    let eigen = SymmetricEigen::new(matrix);
    let mut order: Vec<usize> = (0..dim).collect();
    order.sort_by(|&a, &b| {
        eigen.eigenvalues[b]
            .total_cmp(&eigen.eigenvalues[a])
            .then(a.cmp(&b))
    });
    let largest = order.first().map_or(0.0, |&i| eigen.eigenvalues[i]);
    let max_rank = (n - 1).min(d);
    for &i in order.iter().take(max_rank) {
        let lambda = eigen.eigenvalues[i];
        if !(lambda > largest * RANK_RELATIVE_TOLERANCE && lambda > 0.0) {
            break;
        }
        let v = eigen.eigenvectors.column(i);
        let mut u: Vec<f64> = if use_gram {
            // u = Xᵀv / √((N − 1)·λ), unit norm since vᵀXXᵀv = (N − 1)·λ.
            let scale = 1.0 / (dof * lambda).sqrt();
            (0..d)
                .map(|s| {
                    centred
                        .iter()
                        .zip(v.iter())
                        .map(|(x, vi)| x[s] * vi)
                        .sum::<f64>()
                        * scale
                })
                .collect()
        } else {
            v.iter().copied().collect()
        };
        fix_sign(&mut u);
        eigenvalues.push(lambda);
        components.extend(u);
    }
    Ok(PcaModel {
        mean,
        eigenvalues,
        components,
        used_gram: use_gram,
    })
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Flips `u` so its entry of largest magnitude (first on ties) is positive.
fn fix_sign(u: &mut [f64]) {
    let mut best = 0.0f64;
    let mut sign = 1.0;
    for &x in u.iter() {
        if x.abs() > best {
            best = x.abs();
            sign = x.signum();
        }
    }
    if sign < 0.0 {
        for x in u.iter_mut() {
            *x = -*x;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::filters::SplitMix64;

    /// Four vectors m ± a·e1, m ± b·e2 (e1, e2 orthonormal): eigenvalues 2a²/3 and 2b²/3.
    fn cross(d: usize, a: f64, b: f64) -> (Vec<Vec<f64>>, Vec<f64>, Vec<f64>) {
        let mean: Vec<f64> = (0..d).map(|i| 10.0 + i as f64 * 0.5).collect();
        let mut e1 = vec![0.0; d];
        let mut e2 = vec![0.0; d];
        // Two orthonormal vectors spread over all samples.
        for i in 0..d {
            e1[i] = if i % 2 == 0 { 1.0 } else { -1.0 } / (d as f64).sqrt();
            e2[i] = if (i / 2) % 2 == 0 { 1.0 } else { -1.0 } / (d as f64).sqrt();
        }
        let offset = |e: &[f64], s: f64| -> Vec<f64> {
            mean.iter().zip(e).map(|(m, v)| m + s * v).collect()
        };
        let data = vec![
            offset(&e1, a),
            offset(&e1, -a),
            offset(&e2, b),
            offset(&e2, -b),
        ];
        (data, e1, e2)
    }

    #[test]
    fn exact_eigen_structure_both_methods() {
        let (data, e1, e2) = cross(16, 6.0, 3.0);
        for use_gram in [true, false] {
            let m = pca_with(&data, use_gram).unwrap();
            assert_eq!(m.rank(), 2, "gram {use_gram}");
            assert!((m.eigenvalues[0] - 24.0).abs() < 1e-9);
            assert!((m.eigenvalues[1] - 6.0).abs() < 1e-9);
            assert!((dot(m.component(0), &e1).abs() - 1.0).abs() < 1e-9);
            assert!((dot(m.component(1), &e2).abs() - 1.0).abs() < 1e-9);
            // Rank-2 reconstruction is exact; rank 1 leaves (N − 1)·λ₂ = 2b² of squared error.
            let c = m.project(&data, 2);
            let r = m.reconstruct(&c, 2);
            for (x, y) in data.iter().zip(&r) {
                for (a, b) in x.iter().zip(y) {
                    assert!((a - b).abs() < 1e-9);
                }
            }
            let r1 = m.reconstruct(&m.project(&data, 1), 1);
            let err: f64 = data
                .iter()
                .zip(&r1)
                .map(|(x, y)| x.iter().zip(y).map(|(a, b)| (a - b) * (a - b)).sum::<f64>())
                .sum();
            assert!((err - 18.0).abs() < 1e-9, "{err}");
            assert_eq!(m.select(ComponentSelection::VarianceShare(0.8)), 1);
            assert_eq!(m.select(ComponentSelection::VarianceShare(0.81)), 2);
            assert_eq!(m.select(ComponentSelection::VarianceShare(1.0)), 2);
            assert_eq!(m.select(ComponentSelection::Fixed(9)), 2);
        }
    }

    #[test]
    fn gram_and_covariance_agree_on_random_data() {
        let mut rng = SplitMix64::new(5);
        let data: Vec<Vec<f64>> = (0..12)
            .map(|_| (0..20).map(|_| rng.standard_normal()).collect())
            .collect();
        let g = pca_with(&data, true).unwrap();
        let c = pca_with(&data, false).unwrap();
        assert_eq!(g.rank(), 11);
        assert_eq!(c.rank(), 11);
        for j in 0..11 {
            assert!((g.eigenvalues[j] - c.eigenvalues[j]).abs() < 1e-9 * g.eigenvalues[0]);
            assert!(
                (dot(g.component(j), c.component(j)) - 1.0).abs() < 1e-8,
                "{j}"
            );
        }
    }

    /// Gaussian vectors with a known covariance C = Q·diag(λ)·Qᵀ, rendered as 4 × 4 images:
    /// PCA recovers λ and the leading columns of Q.
    #[test]
    fn recovers_known_covariance() {
        let d = 16;
        let lambdas: Vec<f64> = (0..d).map(|i| 64.0 * 0.5f64.powi(i as i32)).collect();
        // Q: an orthonormal basis from the QR decomposition of a seeded random matrix.
        let mut rng = SplitMix64::new(11);
        let a = DMatrix::from_fn(d, d, |_, _| rng.standard_normal());
        let q = a.qr().q();
        let n = 6000;
        let images: Vec<Image> = (0..n)
            .map(|_| {
                let z: Vec<f64> = (0..d).map(|_| rng.standard_normal()).collect();
                let x: Vec<f32> = (0..d)
                    .map(|r| {
                        let v: f64 = (0..d).map(|c| q[(r, c)] * lambdas[c].sqrt() * z[c]).sum();
                        (100.0 + v) as f32
                    })
                    .collect();
                Image::from_f32(4, 4, Channels::Gray, x).unwrap()
            })
            .collect();
        let data: Vec<Vec<f64>> = images.iter().map(image_samples_f64).collect();
        let m = pca(&data).unwrap();
        assert!(!m.used_gram);
        assert_eq!(m.rank(), d);
        // Sample eigenvalues scatter by about √(2/N) ≈ 2 % around the true ones.
        for (got, want) in m.eigenvalues.iter().zip(&lambdas) {
            assert!((got / want - 1.0).abs() < 0.08, "{got} vs {want}");
        }
        for j in 0..4 {
            let qj: Vec<f64> = (0..d).map(|r| q[(r, j)]).collect();
            let cos = dot(m.component(j), &qj).abs();
            assert!(cos > 0.99, "component {j}: |cos| = {cos}");
        }
        for (i, &mi) in m.mean.iter().enumerate() {
            assert!((mi - 100.0).abs() < 0.5, "mean {i}: {mi}");
        }
    }

    #[test]
    fn errors_and_extremes() {
        assert!(pca(&[]).is_err());
        assert!(pca(&[vec![]]).is_err());
        assert!(pca(&[vec![1.0, 2.0], vec![1.0]]).is_err());
        assert!(pca(&[vec![f64::NAN, 2.0]]).is_err());
        // One image: no variance, no component; identical images likewise.
        let one = pca(&[vec![1.0, 2.0, 3.0]]).unwrap();
        assert_eq!((one.rank(), one.mean.clone()), (0, vec![1.0, 2.0, 3.0]));
        let same = pca(&[vec![4.0; 5], vec![4.0; 5], vec![4.0; 5]]).unwrap();
        assert_eq!(same.rank(), 0);
        assert_eq!(same.select(ComponentSelection::VarianceShare(0.9)), 0);
        assert_eq!(same.explained(0), 1.0);
        assert!(
            Pca::new(PcaParams {
                keep_variance: 0.0,
                ..PcaParams::default()
            })
            .is_err()
        );
        assert!(
            Pca::new(PcaParams {
                keep_variance: f64::NAN,
                ..PcaParams::default()
            })
            .is_err()
        );
    }

    fn run_op(op: &Pca, images: Vec<Value>) -> Result<Outputs, OpError> {
        let specs = Pca::inputs();
        let values = [Some(Value::list(PortType::Image, images))];
        let ctx = RunContext {
            node: "pca".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    #[test]
    fn operator_outputs_and_input_errors() {
        let (data, _, _) = cross(16, 6.0, 3.0);
        let images: Vec<Value> = data
            .iter()
            .map(|x| {
                Value::image(
                    Image::from_f32(4, 4, Channels::Gray, x.iter().map(|&v| v as f32).collect())
                        .unwrap(),
                )
            })
            .collect();
        let op = Pca::new(PcaParams {
            components: 1,
            ..PcaParams::default()
        })
        .unwrap();
        let mut out = run_op(&op, images.clone()).unwrap();
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("metrics")
        };
        assert_eq!(m["components"], 1.0);
        assert_eq!(m["rank"], 2.0);
        assert!((m["explained_variance"] - 0.8).abs() < 1e-12);
        // Squared error 2b² = 18 over 64 samples.
        assert!((m["rmse"] - (18.0f64 / 64.0).sqrt()).abs() < 1e-6);
        let Some(Value::Matrix(ev)) = out.take("eigenvalues") else {
            panic!("eigenvalues")
        };
        assert_eq!((ev.rows, ev.cols), (2, 3));
        assert!((ev.data[5] - 1.0).abs() < 1e-12);
        let Some(Value::List(recon)) = out.take("reconstructions") else {
            panic!("reconstructions")
        };
        assert_eq!(recon.items.len(), 4);

        assert!(run_op(&op, vec![]).is_err());
        let mut mixed = images;
        mixed.push(Value::image(
            Image::from_f32(2, 2, Channels::Gray, vec![0.0; 4]).unwrap(),
        ));
        let err = run_op(&op, mixed).unwrap_err().to_string();
        assert!(err.contains("image 4"), "{err}");
    }
}
