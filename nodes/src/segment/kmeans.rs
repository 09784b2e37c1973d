//! `segment.kmeans`: k-means clustering of pixel colours, as OpenCV's `cv::kmeans`.
//!
//! [`kmeans`] seeds centres with k-means++, runs Lloyd iterations until the centres stop moving,
//! repeats for several attempts and keeps the most compact clustering.
//!
//! Determinism: pixels are processed in fixed chunks of [`CHUNK`] pixels in parallel; every
//! chunk's partial sums (per-cluster sums and counts, squared distances) are added in chunk
//! order in f64. The random numbers come from a seeded generator used only sequentially, so
//! the result is bit-identical for any thread count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Depth, Image, Matrix, Metrics, PixelData, Value};
use rayon::prelude::*;

use super::label_image;

/// Pixels per parallel chunk: a constant, never derived from the thread count.
pub const CHUNK: usize = 8192;

/// Largest number of clusters.
pub const MAX_K: u32 = 256;

/// Candidates tried per k-means++ centre (OpenCV's value).
const PP_TRIALS: usize = 3;

params! {
    /// Parameters of `segment.kmeans`.
    pub struct KmeansParams {
        /// Number of clusters, 1..=256. Default 4.
        k: u32 = 4,
        /// Most Lloyd iterations per attempt (≥ 1). Default 20.
        max_iterations: u32 = 20,
        /// Stop an attempt once no centre moves farther than this, in sample units (≥ 0).
        /// Default 0.5.
        epsilon: f64 = 0.5,
        /// Clusterings tried from different seedings; the most compact is kept (≥ 1).
        /// Default 3.
        attempts: u32 = 3,
        /// Seed of the random generator used by k-means++. Default 0.
        seed: u64 = 0,
    }
}

/// K-means colour clustering (`segment.kmeans`). See [`kmeans`].
#[derive(Debug, Clone, PartialEq)]
pub struct Kmeans {
    config: KmeansConfig,
}

/// Settings of [`kmeans`] (see [`KmeansParams`] for their meaning).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KmeansConfig {
    /// Number of clusters.
    pub k: usize,
    /// Most Lloyd iterations per attempt.
    pub max_iterations: usize,
    /// Centre-shift stopping distance, sample units.
    pub epsilon: f64,
    /// Attempts.
    pub attempts: usize,
    /// Random seed.
    pub seed: u64,
}

impl Op for Kmeans {
    type Params = KmeansParams;
    const ID: &'static str = "segment.kmeans";
    const SUMMARY: &'static str =
        "Clusters pixel colours with k-means and replaces each pixel by its cluster's centre.";
    const DOC: &'static str = r#"
Clusters the pixels of an image (gray, RGB or RGBA: every channel is a coordinate; u8, u16 or
f32, in sample units) into `k` clusters by colour alone. Outputs `labels` (gray f32, cluster
index 0..k−1), `quantized` (the input's format, every pixel replaced by its cluster's centre,
rounded and saturated for integer depths), `centers` (a k × channels Matrix, row i = centre of
cluster i) and `compactness` (Metrics: `compactness` = Σ‖pixel − centre‖², `iterations` of the
kept attempt, `attempt` = its index).

Method (as `cv::kmeans` with `KMEANS_PP_CENTERS`): k-means++ seeding (Arthur and Vassilvitskii
2007; first centre uniform, every further centre drawn with probability ∝ squared distance to
the nearest centre, best of 3 draws by total potential, as OpenCV), then Lloyd iterations:
centres = means of their pixels (an empty cluster takes the pixel farthest from its centre in
the largest cluster), stop when no centre moved more than `epsilon` or after `max_iterations`;
then pixels are reassigned to the nearest centre (ties to the lower index). The attempt with the
lowest compactness is kept (first on ties). The final labels are those of the last assignment
and the centres their means; compactness is computed with those centres.

Differences from OpenCV: the random generator differs (so do the seedings and possibly the
local optimum found, and the order of the clusters); distances are f32, sums f64. Deterministic
for a given `seed` with any thread count (fixed chunks, partial sums reduced in order).

Reference: S. Lloyd, "Least squares quantization in PCM", 1982; OpenCV `cv::kmeans`.

Example:
    "palette": (op: "segment.kmeans", inputs: { "image": "photo.image" }, params: (k: 8, seed: 1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image whose pixel colours are clustered, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "labels",
                PortType::Image,
                "Gray f32: cluster index 0..k−1 of every pixel.",
            ),
            PortSpec::new(
                "quantized",
                PortType::Image,
                "The input's format: every pixel replaced by its cluster's centre.",
            ),
            PortSpec::new(
                "centers",
                PortType::Matrix,
                "k × channels: row i is the centre of cluster i, sample units.",
            ),
            PortSpec::new(
                "compactness",
                PortType::Metrics,
                "compactness (Σ squared distances to centres), iterations, attempt.",
            ),
        ]
    }

    fn new(params: KmeansParams) -> Result<Self, String> {
        let KmeansParams {
            k,
            max_iterations,
            epsilon,
            attempts,
            seed,
        } = params;
        if !(1..=MAX_K).contains(&k) {
            return Err(format!("`k` must be between 1 and {MAX_K}, got {k}"));
        }
        if max_iterations == 0 {
            return Err("`max_iterations` must be at least 1".into());
        }
        if !epsilon.is_finite() || epsilon < 0.0 {
            return Err(format!("`epsilon` must be finite and ≥ 0, got {epsilon}"));
        }
        if attempts == 0 {
            return Err("`attempts` must be at least 1".into());
        }
        Ok(Kmeans {
            config: KmeansConfig {
                k: k as usize,
                max_iterations: max_iterations as usize,
                epsilon,
                attempts: attempts as usize,
                seed,
            },
        })
    }
}

impl Operator for Kmeans {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let result = kmeans(image, &self.config).map_err(|e| OpError::input("image", e))?;
        let c = image.channels().count();
        let (w, h) = (image.width(), image.height());
        let quantized = quantize(image, &result).map_err(OpError::failed)?;
        let labels = label_image(w, h, result.labels.iter().map(|&l| l as f32).collect())
            .map_err(OpError::failed)?;
        let centers = Matrix::new(
            self.config.k,
            c,
            result.centers.iter().map(|&v| v as f64).collect(),
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        let mut metrics = Metrics::new();
        metrics.insert("compactness".into(), result.compactness);
        metrics.insert("iterations".into(), result.iterations as f64);
        metrics.insert("attempt".into(), result.attempt as f64);
        Ok(Outputs::new()
            .with("labels", Value::image(labels))
            .with("quantized", Value::image(quantized))
            .with("centers", Value::Matrix(Arc::new(centers)))
            .with("compactness", Value::metrics(metrics)))
    }
}

/// The result of [`kmeans`].
#[derive(Debug, Clone, PartialEq)]
pub struct Clustering {
    /// Cluster index of every pixel, row-major.
    pub labels: Vec<u32>,
    /// `k × channels` centres, row-major.
    pub centers: Vec<f32>,
    /// Σ over pixels of the squared distance to their centre.
    pub compactness: f64,
    /// Lloyd iterations of the kept attempt.
    pub iterations: usize,
    /// Index of the kept attempt.
    pub attempt: usize,
}

/// splitmix64: a small, seedable generator used only sequentially.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in 0..n (n ≥ 1).
    fn below(&mut self, n: usize) -> usize {
        ((self.uniform() * n as f64) as usize).min(n - 1)
    }
}

#[inline(always)]
fn dist2(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(&x, &y)| (x - y) * (x - y)).sum()
}

/// The samples of `image` as f32, interleaved.
fn samples_f32(image: &Image) -> Vec<f32> {
    match image.data() {
        PixelData::U8(s) => s.iter().map(|&v| v as f32).collect(),
        PixelData::U16(s) => s.iter().map(|&v| v as f32).collect(),
        PixelData::F32(s) => s.clone(),
    }
}

/// Clusters the pixel colours of `image` (every channel a coordinate) into `config.k`
/// clusters; see the operator's DOC. Errors when the image has fewer pixels than clusters or
/// non-finite samples.
pub fn kmeans(image: &Image, config: &KmeansConfig) -> Result<Clustering, String> {
    let c = image.channels().count();
    let n = image.width() * image.height();
    let k = config.k.max(1);
    if n < k {
        return Err(format!("{n} pixels cannot form {k} clusters"));
    }
    let data = samples_f32(image);
    if data.iter().any(|v| !v.is_finite()) {
        return Err("samples must be finite".into());
    }
    let mut rng = Rng(config.seed);
    let eps2 = config.epsilon * config.epsilon;
    let mut best: Option<Clustering> = None;
    for attempt in 0..config.attempts.max(1) {
        let mut centers = seed_centers(&data, c, k, &mut rng);
        let mut labels = vec![0u32; n];
        assign(&data, c, &centers, &mut labels);
        let mut iterations = 1;
        loop {
            let mut next = mean_centers(&data, c, k, &mut labels, &centers);
            let shift = centers
                .chunks_exact(c)
                .zip(next.chunks_exact(c))
                .map(|(a, b)| dist2(a, b) as f64)
                .fold(0.0, f64::max);
            std::mem::swap(&mut centers, &mut next);
            if iterations >= config.max_iterations || shift <= eps2 {
                break;
            }
            assign(&data, c, &centers, &mut labels);
            iterations += 1;
        }
        let compactness = compactness(&data, c, &centers, &labels);
        if best.as_ref().is_none_or(|b| compactness < b.compactness) {
            best = Some(Clustering {
                labels,
                centers,
                compactness,
                iterations,
                attempt,
            });
        }
    }
    best.ok_or_else(|| "no attempt ran".to_string())
}

/// k-means++ seeding (best of [`PP_TRIALS`] draws per centre, as OpenCV's
/// `generateCentersPP`).
fn seed_centers(data: &[f32], c: usize, k: usize, rng: &mut Rng) -> Vec<f32> {
    let n = data.len() / c;
    let mut centers = Vec::with_capacity(k * c);
    let first = rng.below(n);
    centers.extend_from_slice(&data[first * c..first * c + c]);
    let mut dist: Vec<f32> = vec![0.0; n];
    let mut total = update_distances(data, c, &centers[..c], None, &mut dist);
    let mut trial = vec![0f32; n];
    let mut best_dist = vec![0f32; n];
    for _ in 1..k {
        let mut best_sum = f64::INFINITY;
        let mut best_index = 0;
        for _ in 0..PP_TRIALS {
            let mut p = rng.uniform() * total;
            let mut index = n - 1;
            for (i, &d) in dist.iter().enumerate() {
                p -= d as f64;
                if p <= 0.0 {
                    index = i;
                    break;
                }
            }
            let candidate = &data[index * c..index * c + c];
            let sum = update_distances(data, c, candidate, Some(&dist), &mut trial);
            if sum < best_sum {
                best_sum = sum;
                best_index = index;
                std::mem::swap(&mut trial, &mut best_dist);
            }
        }
        centers.extend_from_slice(&data[best_index * c..best_index * c + c]);
        total = best_sum;
        std::mem::swap(&mut dist, &mut best_dist);
    }
    centers
}

/// `out[i] = min(‖x_i − center‖², previous[i])` for every pixel; returns Σ out in f64, summed
/// per fixed chunk and then in chunk order.
fn update_distances(
    data: &[f32],
    c: usize,
    center: &[f32],
    previous: Option<&[f32]>,
    out: &mut [f32],
) -> f64 {
    let partials: Vec<f64> = out
        .par_chunks_mut(CHUNK)
        .enumerate()
        .map(|(ci, chunk)| {
            let base = ci * CHUNK;
            let mut s = 0f64;
            for (j, o) in chunk.iter_mut().enumerate() {
                let i = base + j;
                let mut d = dist2(&data[i * c..i * c + c], center);
                if let Some(prev) = previous {
                    d = d.min(prev[i]);
                }
                *o = d;
                s += d as f64;
            }
            s
        })
        .collect();
    partials.iter().sum()
}

/// Index of the nearest centre (ties to the lower index).
#[inline(always)]
fn nearest(x: &[f32], centers: &[f32], c: usize) -> u32 {
    let mut best = f32::INFINITY;
    let mut label = 0;
    for (j, center) in centers.chunks_exact(c).enumerate() {
        let d = dist2(x, center);
        if d < best {
            best = d;
            label = j as u32;
        }
    }
    label
}

/// Assigns every pixel to its nearest centre.
fn assign(data: &[f32], c: usize, centers: &[f32], labels: &mut [u32]) {
    labels
        .par_chunks_mut(CHUNK)
        .zip(data.par_chunks(CHUNK * c))
        .for_each(|(l, d)| {
            for (label, x) in l.iter_mut().zip(d.chunks_exact(c)) {
                *label = nearest(x, centers, c);
            }
        });
}

/// The mean of every cluster. An empty cluster takes the pixel farthest from its centre in the
/// largest cluster (relabelled), as OpenCV does.
fn mean_centers(data: &[f32], c: usize, k: usize, labels: &mut [u32], old: &[f32]) -> Vec<f32> {
    let partials: Vec<(Vec<f64>, Vec<u64>)> = labels
        .par_chunks(CHUNK)
        .zip(data.par_chunks(CHUNK * c))
        .map(|(l, d)| {
            let mut sums = vec![0f64; k * c];
            let mut counts = vec![0u64; k];
            for (&label, x) in l.iter().zip(d.chunks_exact(c)) {
                let j = label as usize;
                counts[j] += 1;
                for (s, &v) in sums[j * c..j * c + c].iter_mut().zip(x) {
                    *s += v as f64;
                }
            }
            (sums, counts)
        })
        .collect();
    let mut sums = vec![0f64; k * c];
    let mut counts = vec![0u64; k];
    for (s, n) in &partials {
        for (a, b) in sums.iter_mut().zip(s) {
            *a += b;
        }
        for (a, b) in counts.iter_mut().zip(n) {
            *a += b;
        }
    }
    for empty in 0..k {
        if counts[empty] != 0 {
            continue;
        }
        let mut largest = 0;
        for j in 1..k {
            if counts[j] > counts[largest] {
                largest = j;
            }
        }
        if counts[largest] <= 1 {
            continue;
        }
        let center = &old[largest * c..largest * c + c];
        let mut far = usize::MAX;
        let mut far_d = -1f32;
        for (i, x) in data.chunks_exact(c).enumerate() {
            if labels[i] as usize == largest {
                let d = dist2(x, center);
                if d > far_d {
                    far_d = d;
                    far = i;
                }
            }
        }
        if far == usize::MAX {
            continue;
        }
        labels[far] = empty as u32;
        counts[largest] -= 1;
        counts[empty] = 1;
        for ch in 0..c {
            let v = data[far * c + ch] as f64;
            sums[largest * c + ch] -= v;
            sums[empty * c + ch] = v;
        }
    }
    let mut centers = vec![0f32; k * c];
    for j in 0..k {
        for ch in 0..c {
            centers[j * c + ch] = if counts[j] == 0 {
                old[j * c + ch]
            } else {
                (sums[j * c + ch] / counts[j] as f64) as f32
            };
        }
    }
    centers
}

/// Σ ‖x_i − centre(label_i)‖², per fixed chunk then in chunk order.
fn compactness(data: &[f32], c: usize, centers: &[f32], labels: &[u32]) -> f64 {
    let partials: Vec<f64> = labels
        .par_chunks(CHUNK)
        .zip(data.par_chunks(CHUNK * c))
        .map(|(l, d)| {
            l.iter()
                .zip(d.chunks_exact(c))
                .map(|(&j, x)| {
                    let j = j as usize;
                    dist2(x, &centers[j * c..j * c + c]) as f64
                })
                .sum::<f64>()
        })
        .collect();
    partials.iter().sum()
}

/// `image` with every pixel replaced by its cluster's centre (rounded and saturated for integer
/// depths).
pub fn quantize(image: &Image, clustering: &Clustering) -> Result<Image, String> {
    let c = image.channels().count();
    let centers = &clustering.centers;
    let data = match image.depth() {
        Depth::U8 => PixelData::U8(
            clustering
                .labels
                .iter()
                .flat_map(|&j| {
                    centers[j as usize * c..j as usize * c + c]
                        .iter()
                        .map(|&v| v.round().clamp(0.0, 255.0) as u8)
                })
                .collect(),
        ),
        Depth::U16 => PixelData::U16(
            clustering
                .labels
                .iter()
                .flat_map(|&j| {
                    centers[j as usize * c..j as usize * c + c]
                        .iter()
                        .map(|&v| v.round().clamp(0.0, 65535.0) as u16)
                })
                .collect(),
        ),
        Depth::F32 => PixelData::F32(
            clustering
                .labels
                .iter()
                .flat_map(|&j| centers[j as usize * c..j as usize * c + c].iter().copied())
                .collect(),
        ),
    };
    Image::new(image.width(), image.height(), image.channels(), data).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    fn config(k: usize, seed: u64) -> KmeansConfig {
        KmeansConfig {
            k,
            max_iterations: 30,
            epsilon: 0.01,
            attempts: 3,
            seed,
        }
    }

    /// An image of `colours.len()` flat vertical stripes of random widths plus uniform noise of
    /// ±`noise`, with the ground-truth stripe index of every pixel.
    fn stripes(
        colours: &[[f32; 3]],
        w: usize,
        h: usize,
        noise: f32,
        seed: u64,
    ) -> (Image, Vec<u32>) {
        let r = randoms(seed, w * h * 3);
        let mut data = Vec::with_capacity(w * h * 3);
        let mut truth = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let s = ((x * 7 + y * 3) / 5) % colours.len();
                truth.push(s as u32);
                for (ch, &colour) in colours[s].iter().enumerate() {
                    let i = (y * w + x) * 3 + ch;
                    let v = colour + (r[i] as f32 * 2.0 - 1.0) * noise;
                    data.push(v.round().clamp(0.0, 255.0) as u8);
                }
            }
        }
        (Image::from_u8(w, h, Channels::Rgb, data).unwrap(), truth)
    }

    /// Checks that `labels` equals `truth` up to a permutation, returning the permutation
    /// (cluster → truth index).
    fn permutation(labels: &[u32], truth: &[u32], k: usize) -> Option<Vec<u32>> {
        let mut map = vec![u32::MAX; k];
        for (&l, &t) in labels.iter().zip(truth) {
            let m = &mut map[l as usize];
            if *m == u32::MAX {
                *m = t;
            } else if *m != t {
                return None;
            }
        }
        let mut seen = map.clone();
        seen.sort_unstable();
        seen.dedup();
        (seen.len() == k).then_some(map)
    }

    #[test]
    fn recovers_flat_colours_and_labels() {
        let colours = [
            [200.0, 30.0, 30.0],
            [20.0, 180.0, 40.0],
            [30.0, 40.0, 220.0],
            [240.0, 240.0, 240.0],
            [10.0, 10.0, 10.0],
        ];
        let (img, truth) = stripes(&colours, 61, 37, 6.0, 3);
        for seed in 0..4 {
            let r = kmeans(&img, &config(5, seed)).unwrap();
            let map = permutation(&r.labels, &truth, 5).expect("labels match up to permutation");
            for (j, &t) in map.iter().enumerate() {
                for ch in 0..3 {
                    let got = r.centers[j * 3 + ch];
                    assert!(
                        (got - colours[t as usize][ch]).abs() < 1.0,
                        "{got} vs {colours:?}"
                    );
                }
            }
            // Noise is uniform in ±6 per channel: variance 12 each, ≈ 36 per pixel.
            let per_pixel = r.compactness / (61.0 * 37.0);
            assert!(per_pixel > 25.0 && per_pixel < 45.0, "{per_pixel}");
        }
    }

    #[test]
    fn hand_computed_gray_two_clusters() {
        let img = Image::from_u16(6, 1, Channels::Gray, vec![0, 2, 4, 100, 102, 104]).unwrap();
        let r = kmeans(&img, &config(2, 9)).unwrap();
        let lo = r.labels[0] as usize;
        assert_eq!(&r.labels[..3], &[lo as u32; 3]);
        assert_eq!(&r.labels[3..], &[1 - lo as u32; 3]);
        assert_eq!(r.centers[lo], 2.0);
        assert_eq!(r.centers[1 - lo], 102.0);
        assert_eq!(r.compactness, 16.0);
        let q = quantize(&img, &r).unwrap();
        assert_eq!(q.as_u16().unwrap(), &[2, 2, 2, 102, 102, 102]);
    }

    #[test]
    fn extremes_and_errors() {
        let one = Image::from_f32(1, 1, Channels::Gray, vec![-3.5]).unwrap();
        let r = kmeans(&one, &config(1, 0)).unwrap();
        assert_eq!(
            (r.labels.clone(), r.centers.clone(), r.compactness),
            (vec![0], vec![-3.5], 0.0)
        );
        assert!(kmeans(&one, &config(2, 0)).is_err());
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(kmeans(&empty, &config(1, 0)).is_err());
        let nan = Image::from_f32(2, 1, Channels::Gray, vec![f32::NAN, 0.0]).unwrap();
        assert!(kmeans(&nan, &config(1, 0)).is_err());
        // Constant image with more clusters than colours: empty clusters stay valid.
        let flat = Image::from_u8(4, 4, Channels::Rgba, vec![7; 64]).unwrap();
        let r = kmeans(&flat, &config(3, 0)).unwrap();
        assert_eq!(r.compactness, 0.0);
        assert!(r.centers.iter().all(|&v| v == 7.0));
        assert!(
            Kmeans::new(KmeansParams {
                k: 0,
                ..KmeansParams::default()
            })
            .is_err()
        );
        assert!(
            Kmeans::new(KmeansParams {
                epsilon: f64::INFINITY,
                ..KmeansParams::default()
            })
            .is_err()
        );
    }

    #[test]
    fn operator_outputs() {
        let op = Kmeans::new(KmeansParams {
            k: 2,
            ..KmeansParams::default()
        })
        .unwrap();
        let img = Image::from_u8(4, 1, Channels::Gray, vec![10, 11, 200, 201]).unwrap();
        let specs = Kmeans::inputs();
        let values = [Some(Value::image(img))];
        let ctx = RunContext {
            node: "k".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(q)) = out.take("quantized") else {
            panic!("quantized")
        };
        // Centres 10.5 and 200.5 round half away from zero.
        assert_eq!(q.as_u8().unwrap(), &[11, 11, 201, 201]);
        let Some(Value::Matrix(m)) = out.take("centers") else {
            panic!("centers")
        };
        assert_eq!((m.rows, m.cols), (2, 1));
        let Some(Value::Metrics(c)) = out.take("compactness") else {
            panic!("compactness")
        };
        assert_eq!(c["compactness"], 1.0);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(12))]

        /// Same result with 1 and 3 threads, and the reported compactness is that of the
        /// returned labels and centres.
        #[test]
        fn deterministic_and_self_consistent(seed in 0u64..1000, k in 1usize..6) {
            let w = 150;
            let h = 120;
            let data: Vec<u8> = randoms(seed, w * h * 3).iter().map(|r| (r * 256.0) as u8).collect();
            let img = Image::from_u8(w, h, Channels::Rgb, data).unwrap();
            let cfg = config(k, seed);
            let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            let three = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
            let a = one.install(|| kmeans(&img, &cfg).unwrap());
            let b = three.install(|| kmeans(&img, &cfg).unwrap());
            prop_assert_eq!(&a, &b);
            let x = samples_f32(&img);
            let recomputed = compactness(&x, 3, &a.centers, &a.labels);
            prop_assert_eq!(recomputed, a.compactness);
        }
    }
}
