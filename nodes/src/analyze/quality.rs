//! `analyze.quality`: full-reference image-quality metrics — MSE, MAE, maximum error, PSNR and
//! SSIM — of an image against a reference of the same size and format.
//!
//! The algorithms are [`error_stats`] and [`ssim`]; [`Quality`] is the thin operator around them.
//!
//! # Determinism and accuracy
//!
//! Sums are taken in f64 over chunks of [`CHUNK_SAMPLES`] samples (a constant, never derived
//! from the thread count) and the chunk sums are added in chunk order, so every metric is
//! bit-identical for any number of threads. The SSIM statistics (local means, variances and
//! covariance) are Gaussian-filtered in f64, so `E[x²] − E[x]²` keeps its digits on 16-bit and
//! large-offset float data.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, PixelData, Value};
use rayon::prelude::*;

use crate::filter::border::{BorderMode, BorderTable};
use crate::filter::gaussian::gaussian_kernel;

/// Samples per reduction chunk (constant, so the reduction order never depends on threads).
pub const CHUNK_SAMPLES: usize = 1 << 16;

/// Rows per parallel band of the SSIM filter.
const BAND_ROWS: usize = 32;

params! {
    /// Parameters of `analyze.quality`.
    pub struct QualityParams {
        /// Dynamic range L of the samples, in the image's units: the PSNR peak and the scale
        /// of SSIM's stabilizing constants C1 = (k1·L)², C2 = (k2·L)². Default: 255 for u8,
        /// 65535 for u16, 1.0 for f32.
        data_range: Option<f64> = None,
        /// Standard deviation of SSIM's Gaussian window, pixels (Wang et al. use 1.5).
        ssim_sigma_px: f64 = 1.5,
        /// SSIM stabilizing constant k1 (dimensionless).
        k1: f64 = 0.01,
        /// SSIM stabilizing constant k2 (dimensionless).
        k2: f64 = 0.03,
    }
}

/// Full-reference quality metrics (`analyze.quality`). See [`error_stats`] and [`ssim`].
#[derive(Debug, Clone, PartialEq)]
pub struct Quality {
    data_range: Option<f64>,
    sigma_px: f64,
    k1: f64,
    k2: f64,
}

impl Op for Quality {
    type Params = QualityParams;
    const ID: &'static str = "analyze.quality";
    const SUMMARY: &'static str =
        "Compares an image with a reference: MSE, MAE, max error, PSNR and SSIM.";
    const DOC: &'static str = r#"
Measures how far `image` is from `reference` (same size, channels and depth):

- `mse` = mean of (image − reference)² over all samples of all channels; `mae` = mean |·|;
  `max_abs_error` = the largest |·|; all in the image's units (gray levels for u8).
- `psnr_db` = 10·log10(L² / mse) in decibels, with L = `data_range`; +inf is reported as the
  metric being absent when the images are identical (`identical` = 1).
- `ssim`: the structural similarity index of Wang, Bovik, Sheikh & Simoncelli (2004), "Image
  quality assessment: from error visibility to structural similarity", IEEE TIP 13(4):
  local statistics under a Gaussian window (σ = `ssim_sigma_px`, radius ⌊3.5σ + 0.5⌋, i.e.
  11×11 for σ = 1.5) with population (co)variances, C1 = (k1·L)², C2 = (k2·L)²,

      SSIM = (2·μx·μy + C1)(2·σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2)),

  filtered with border "reflect" and averaged over the pixels at least one window radius from
  the edge (the whole image when it is smaller than a window), and over channels. This is
  scikit-image's `structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=L, channel_axis=-1)`.
- `ssim_map`: the per-pixel SSIM (mean over channels), f32 gray, same size as the input.

NaN or infinite samples are rejected (the input port is named).

Example:
    "score": (op: "analyze.quality", inputs: { "image": "denoised.image", "reference": "clean.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "Image to measure."),
            PortSpec::new(
                "reference",
                PortType::Image,
                "Reference (ground truth), same size, channels and depth as `image`.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "mse, mae, max_abs_error, psnr_db, ssim, identical.",
            ),
            PortSpec::new(
                "ssim_map",
                PortType::Image,
                "Per-pixel SSIM averaged over channels, f32 gray.",
            ),
        ]
    }

    fn new(params: QualityParams) -> Result<Self, String> {
        let QualityParams {
            data_range,
            ssim_sigma_px,
            k1,
            k2,
        } = params;
        if let Some(range) = data_range
            && !(range.is_finite() && range > 0.0)
        {
            return Err(format!(
                "`data_range` must be a positive finite number, got {range}"
            ));
        }
        if !(ssim_sigma_px.is_finite() && ssim_sigma_px > 0.0 && ssim_sigma_px <= 100.0) {
            return Err(format!(
                "`ssim_sigma_px` must be in (0, 100] px, got {ssim_sigma_px}"
            ));
        }
        for (name, k) in [("k1", k1), ("k2", k2)] {
            if !(k.is_finite() && k > 0.0) {
                return Err(format!(
                    "`{name}` must be a positive finite number, got {k}"
                ));
            }
        }
        Ok(Quality {
            data_range,
            sigma_px: ssim_sigma_px,
            k1,
            k2,
        })
    }
}

impl Operator for Quality {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let reference = inputs.image("reference")?;
        check_pair(image, reference)?;
        for (port, img) in [("image", image), ("reference", reference)] {
            if let Some(samples) = img.as_f32()
                && samples.iter().any(|s| !s.is_finite())
            {
                return Err(OpError::input(port, "contains NaN or infinite samples"));
            }
        }
        let range = self.data_range.unwrap_or(default_range(image));
        let errors = error_stats(image, reference);
        let (mean_ssim, map) = ssim(image, reference, range, self.sigma_px, self.k1, self.k2);
        let mut metrics = Metrics::new();
        metrics.insert("mse".into(), errors.mse);
        metrics.insert("mae".into(), errors.mae);
        metrics.insert("max_abs_error".into(), errors.max_abs);
        metrics.insert("identical".into(), f64::from(u8::from(errors.mse == 0.0)));
        if let Some(psnr) = psnr_db(errors.mse, range) {
            metrics.insert("psnr_db".into(), psnr);
        }
        metrics.insert("ssim".into(), mean_ssim);
        Ok(Outputs::new()
            .with("metrics", Value::metrics(metrics))
            .with("ssim_map", Value::image(map)))
    }
}

/// Both images must have the same size, channels and depth.
fn check_pair(image: &Image, reference: &Image) -> Result<(), OpError> {
    if image.format() != reference.format()
        || image.width() != reference.width()
        || image.height() != reference.height()
    {
        return Err(OpError::input(
            "reference",
            format!(
                "is {}×{} {} {}, but `image` is {}×{} {} {}",
                reference.width(),
                reference.height(),
                reference.channels().name(),
                reference.depth().name(),
                image.width(),
                image.height(),
                image.channels().name(),
                image.depth().name()
            ),
        ));
    }
    Ok(())
}

/// The default dynamic range of an image's samples: 255 (u8), 65535 (u16), 1 (f32).
pub fn default_range(image: &Image) -> f64 {
    match image.data() {
        PixelData::U8(_) => 255.0,
        PixelData::U16(_) => 65535.0,
        PixelData::F32(_) => 1.0,
    }
}

/// Differences between two images, over all samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    /// Mean squared error, squared image units.
    pub mse: f64,
    /// Mean absolute error, image units.
    pub mae: f64,
    /// Largest absolute error, image units.
    pub max_abs: f64,
}

/// MSE, MAE and maximum absolute error of `image` against `reference` (same layout; the
/// caller checks). Empty images give zeros. Deterministic for any thread count.
pub fn error_stats(image: &Image, reference: &Image) -> ErrorStats {
    let partial = match (image.data(), reference.data()) {
        (PixelData::U8(a), PixelData::U8(b)) => chunk_errors(a, b, f64::from),
        (PixelData::U16(a), PixelData::U16(b)) => chunk_errors(a, b, f64::from),
        (PixelData::F32(a), PixelData::F32(b)) => chunk_errors(a, b, f64::from),
        _ => Vec::new(),
    };
    let n = image.data().len();
    let (mut sq, mut abs, mut max_abs) = (0.0, 0.0, 0.0f64);
    for (s, a, m) in partial {
        sq += s;
        abs += a;
        max_abs = max_abs.max(m);
    }
    if n == 0 {
        return ErrorStats {
            mse: 0.0,
            mae: 0.0,
            max_abs: 0.0,
        };
    }
    ErrorStats {
        mse: sq / n as f64,
        mae: abs / n as f64,
        max_abs,
    }
}

/// Per-chunk (Σd², Σ|d|, max |d|), in chunk order.
fn chunk_errors<T: Copy + Sync>(a: &[T], b: &[T], to_f64: fn(T) -> f64) -> Vec<(f64, f64, f64)> {
    a.par_chunks(CHUNK_SAMPLES)
        .zip(b.par_chunks(CHUNK_SAMPLES))
        .map(|(ca, cb)| {
            let (mut sq, mut abs, mut max_abs) = (0.0f64, 0.0f64, 0.0f64);
            for (&x, &y) in ca.iter().zip(cb) {
                let d = to_f64(x) - to_f64(y);
                sq += d * d;
                abs += d.abs();
                max_abs = max_abs.max(d.abs());
            }
            (sq, abs, max_abs)
        })
        .collect()
}

/// Peak signal-to-noise ratio in dB for a mean squared error and dynamic range; `None` when the
/// error is zero (infinite PSNR).
pub fn psnr_db(mse: f64, data_range: f64) -> Option<f64> {
    (mse > 0.0).then(|| 10.0 * (data_range * data_range / mse).log10())
}

/// Mean SSIM of `image` against `reference` (same layout; the caller checks) and the per-pixel
/// SSIM map averaged over channels (f32 gray). See [`Quality`] for the definition. Empty images
/// give 1 and an empty map.
pub fn ssim(
    image: &Image,
    reference: &Image,
    data_range: f64,
    sigma_px: f64,
    k1: f64,
    k2: f64,
) -> (f64, Image) {
    let (width, height) = (image.width(), image.height());
    let channels = image.channels().count();
    let to_planes = |img: &Image| -> Vec<Vec<f64>> {
        let samples: Vec<f64> = match img.data() {
            PixelData::U8(v) => v.iter().map(|&s| f64::from(s)).collect(),
            PixelData::U16(v) => v.iter().map(|&s| f64::from(s)).collect(),
            PixelData::F32(v) => v.iter().map(|&s| f64::from(s)).collect(),
        };
        (0..channels)
            .map(|c| samples.iter().skip(c).step_by(channels).copied().collect())
            .collect()
    };
    let empty_map = || {
        Image::from_f32(width, height, Channels::Gray, vec![0.0; width * height])
            .unwrap_or_else(|_| image.clone())
    };
    if width == 0 || height == 0 {
        return (1.0, empty_map());
    }
    let radius = (3.5 * sigma_px + 0.5) as usize;
    let kernel = gaussian_kernel(2 * radius + 1, sigma_px);
    let c1 = (k1 * data_range).powi(2);
    let c2 = (k2 * data_range).powi(2);
    let xs = to_planes(image);
    let ys = to_planes(reference);
    let mut map = vec![0.0f64; width * height];
    for (x, y) in xs.iter().zip(&ys) {
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * b).collect();
        let [mx, my, mxx, myy, mxy] =
            [x, y, &xx, &yy, &xy].map(|plane| gaussian_f64(plane, width, height, &kernel));
        map.par_chunks_mut(width)
            .enumerate()
            .for_each(|(row, out)| {
                let base = row * width;
                for (i, o) in out.iter_mut().enumerate() {
                    let k = base + i;
                    let (ux, uy) = (mx[k], my[k]);
                    let vx = mxx[k] - ux * ux;
                    let vy = myy[k] - uy * uy;
                    let vxy = mxy[k] - ux * uy;
                    let s = ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                        / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
                    *o += s;
                }
            });
    }
    let inv_channels = 1.0 / channels as f64;
    // Mean over the interior, or everything when the image is smaller than a window.
    let (x0, x1) = interior(width, radius);
    let (y0, y1) = interior(height, radius);
    let rows: Vec<f64> = (y0..y1)
        .into_par_iter()
        .map(|row| map[row * width + x0..row * width + x1].iter().sum::<f64>())
        .collect();
    let count = ((x1 - x0) * (y1 - y0)) as f64;
    let mean = rows.iter().sum::<f64>() / count * inv_channels;
    let map_f32 = map.iter().map(|&s| (s * inv_channels) as f32).collect();
    let map =
        Image::from_f32(width, height, Channels::Gray, map_f32).unwrap_or_else(|_| empty_map());
    (mean, map)
}

/// The index range at least `radius` from both ends, or the whole range when none is.
fn interior(len: usize, radius: usize) -> (usize, usize) {
    if len > 2 * radius {
        (radius, len - radius)
    } else {
        (0, len)
    }
}

/// Separable correlation of an f64 plane with `kernel` (odd length) along rows then columns,
/// border "reflect" (`dcba|abcd`). Rows run in parallel fixed bands.
fn gaussian_f64(plane: &[f64], width: usize, height: usize, kernel: &[f64]) -> Vec<f64> {
    let radius = kernel.len() / 2;
    let columns = BorderTable::symmetric(width, radius, BorderMode::Reflect);
    let rows = BorderTable::symmetric(height, radius, BorderMode::Reflect);
    let mut horizontal = vec![0.0f64; width * height];
    horizontal
        .par_chunks_mut(width * BAND_ROWS)
        .enumerate()
        .for_each(|(band, out)| {
            let mut padded = vec![0.0f64; columns.padded_len()];
            for (r, out_row) in out.chunks_mut(width).enumerate() {
                let row = band * BAND_ROWS + r;
                columns.pad_row(&plane[row * width..(row + 1) * width], 1, 0.0, &mut padded);
                for (x, o) in out_row.iter_mut().enumerate() {
                    *o = kernel
                        .iter()
                        .zip(&padded[x..x + kernel.len()])
                        .map(|(k, v)| k * v)
                        .sum();
                }
            }
        });
    let mut result = vec![0.0f64; width * height];
    result
        .par_chunks_mut(width * BAND_ROWS)
        .enumerate()
        .for_each(|(band, out)| {
            for (r, out_row) in out.chunks_mut(width).enumerate() {
                let row = band * BAND_ROWS + r;
                for (tap, &k) in kernel.iter().enumerate() {
                    let Some(src) = rows.source(row + tap) else {
                        continue;
                    };
                    let src_row = &horizontal[src * width..(src + 1) * width];
                    for (o, v) in out_row.iter_mut().zip(src_row) {
                        *o += k * v;
                    }
                }
            }
        });
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::random_u8;
    use proptest::prelude::*;

    fn gray_u8(w: usize, h: usize, data: Vec<u8>) -> Image {
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    #[test]
    fn hand_computed_errors() {
        let a = gray_u8(2, 2, vec![10, 20, 30, 40]);
        let b = gray_u8(2, 2, vec![12, 20, 27, 40]);
        let e = error_stats(&a, &b);
        assert_eq!(e.mse, (4.0 + 9.0) / 4.0);
        assert_eq!(e.mae, 5.0 / 4.0);
        assert_eq!(e.max_abs, 3.0);
        let psnr = psnr_db(e.mse, 255.0).unwrap();
        assert!((psnr - 10.0 * (65025.0f64 / 3.25).log10()).abs() < 1e-12);
    }

    #[test]
    fn identical_images_have_ssim_one_and_no_psnr() {
        let a = random_u8(40, 30, Channels::Rgb, 3);
        let e = error_stats(&a, &a);
        assert_eq!(e.mse, 0.0);
        assert_eq!(psnr_db(e.mse, 255.0), None);
        let (s, map) = ssim(&a, &a, 255.0, 1.5, 0.01, 0.03);
        assert!((s - 1.0).abs() < 1e-12, "{s}");
        assert!(
            map.as_f32()
                .unwrap()
                .iter()
                .all(|&v| (v - 1.0).abs() < 1e-6)
        );
    }

    /// Values from scikit-image 0.26 `structural_similarity(a, b, gaussian_weights=True,
    /// sigma=1.5, use_sample_covariance=False, data_range=255)` on these 16×16 images.
    #[test]
    fn ssim_matches_scikit_image_on_a_hand_made_pair() {
        let (w, h) = (16, 16);
        let a: Vec<u8> = (0..w * h).map(|i| ((i * 37) % 251) as u8).collect();
        let b: Vec<u8> = (0..w * h)
            .map(|i| (((i * 37) % 251) as i32 + ((i * 13) % 21) as i32 - 10).clamp(0, 255) as u8)
            .collect();
        let (s, _) = ssim(&gray_u8(w, h, a), &gray_u8(w, h, b), 255.0, 1.5, 0.01, 0.03);
        assert!((s - SKIMAGE_SSIM_16).abs() < 1e-9, "{s}");
    }

    const SKIMAGE_SSIM_16: f64 = 0.996_564_840_923_708_5;

    #[test]
    fn ssim_is_symmetric_and_at_most_one() {
        let a = random_u8(33, 17, Channels::Gray, 1);
        let b = random_u8(33, 17, Channels::Gray, 2);
        let (ab, _) = ssim(&a, &b, 255.0, 1.5, 0.01, 0.03);
        let (ba, _) = ssim(&b, &a, 255.0, 1.5, 0.01, 0.03);
        assert_eq!(ab, ba);
        assert!(ab < 0.2, "independent noise should be dissimilar: {ab}");
    }

    #[test]
    fn metrics_do_not_depend_on_threads() {
        let a = random_u8(300, 257, Channels::Rgb, 5);
        let b = random_u8(300, 257, Channels::Rgb, 6);
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| (error_stats(&a, &b), ssim(&a, &b, 255.0, 1.5, 0.01, 0.03)))
        };
        let (e1, (s1, m1)) = run(1);
        let (e3, (s3, m3)) = run(3);
        assert_eq!(e1, e3);
        assert_eq!(s1.to_bits(), s3.to_bits());
        assert_eq!(m1, m3);
    }

    #[test]
    fn mismatched_inputs_are_rejected() {
        let a = random_u8(4, 4, Channels::Gray, 1);
        let b = random_u8(4, 5, Channels::Gray, 1);
        assert!(check_pair(&a, &b).is_err());
        let c = random_u8(4, 4, Channels::Rgb, 1);
        assert!(check_pair(&a, &c).is_err());
    }

    #[test]
    fn tiny_and_empty_images() {
        let one = gray_u8(1, 1, vec![7]);
        let other = gray_u8(1, 1, vec![9]);
        let (s, map) = ssim(&one, &other, 255.0, 1.5, 0.01, 0.03);
        assert!(s.is_finite() && s < 1.0 && s > 0.9);
        assert_eq!((map.width(), map.height()), (1, 1));
        let empty = gray_u8(0, 0, vec![]);
        assert_eq!(error_stats(&empty, &empty).mse, 0.0);
        assert_eq!(ssim(&empty, &empty, 255.0, 1.5, 0.01, 0.03).0, 1.0);
    }

    proptest! {
        /// A constant offset d gives MSE d², MAE |d| and max error |d| exactly.
        #[test]
        fn offset_errors(seed in 0u64..1000, d in -50i32..50) {
            let a = random_u8(23, 11, Channels::Gray, seed);
            let shifted: Vec<u8> = a.as_u8().unwrap().iter()
                .map(|&v| (i32::from(v) / 2 + 60 + d) as u8).collect();
            let base: Vec<u8> = a.as_u8().unwrap().iter()
                .map(|&v| (i32::from(v) / 2 + 60) as u8).collect();
            let e = error_stats(&gray_u8(23, 11, shifted), &gray_u8(23, 11, base));
            let d = f64::from(d);
            prop_assert_eq!(e.mse, d * d);
            prop_assert_eq!(e.mae, d.abs());
            prop_assert_eq!(e.max_abs, d.abs());
        }
    }
}
