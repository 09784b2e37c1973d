//! `filter.threshold` and `filter.adaptive_threshold`: global and local thresholds with OpenCV's
//! `threshold` / `adaptiveThreshold` semantics.
//!
//! [`threshold`] compares every sample with one threshold, fixed or computed from the
//! histogram ([`otsu_threshold_u8`], [`triangle_threshold_u8`] and their u16 forms), and maps
//! it by one of OpenCV's five threshold types ([`ThresholdMode`]). [`adaptive_threshold`]
//! compares every sample with the mean (box or Gaussian) of its neighbourhood minus a constant.
//!
//! How it runs:
//! - Integer thresholds are `⌊thresh⌋`, as OpenCV. Thresholds outside the sample range collapse
//!   to a constant or a copy of the input (never a wrapped comparison); otherwise every mode is
//!   a branch-free compare-and-select per sample, which vectorizes (for u8 this is faster than
//!   the 256-entry table OpenCV uses, with the same result).
//! - Samples are processed in fixed-size chunks in parallel (`par_chunks_mut`), histograms are
//!   summed chunk by chunk in order: results are identical for any thread count.
//! - Otsu and triangle follow OpenCV's `getThreshVal_Otsu` / `getThreshVal_Triangle` step by
//!   step (same f64 arithmetic and the same tie rules), so the threshold is the one
//!   `cv2.threshold` returns.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::border::BorderMode;
use super::box_filter::box_filter;
use super::gaussian::{gaussian_kernel, separable_filter};
use crate::analyze::histogram::{histogram_u8, histogram_u16};

/// Samples per parallel chunk.
const CHUNK: usize = 1 << 16;

/// Largest adaptive block side, px.
pub const MAX_BLOCK: u32 = 1023;

param_enum! {
    /// How the threshold of `filter.threshold` is chosen.
    pub enum ThresholdMethod {
        /// The `thresh` parameter.
        Fixed = "fixed",
        /// Otsu's method on the 256-bin (u8) or 65536-bin (u16) histogram (`THRESH_OTSU`).
        Otsu = "otsu",
        /// Zack's triangle method on the histogram (`THRESH_TRIANGLE`).
        Triangle = "triangle",
    }
}

param_enum! {
    /// How a sample is mapped once compared with the threshold `t` (OpenCV's threshold types).
    pub enum ThresholdMode {
        /// `src > t ? max_value : 0` (`THRESH_BINARY`).
        Binary = "binary",
        /// `src > t ? 0 : max_value` (`THRESH_BINARY_INV`).
        BinaryInv = "binary_inv",
        /// `src > t ? t : src` (`THRESH_TRUNC`).
        Trunc = "trunc",
        /// `src > t ? src : 0` (`THRESH_TOZERO`).
        ToZero = "to_zero",
        /// `src > t ? 0 : src` (`THRESH_TOZERO_INV`).
        ToZeroInv = "to_zero_inv",
    }
}

params! {
    /// Parameters of `filter.threshold`.
    pub struct ThresholdParams {
        /// How the threshold is chosen: "fixed" (uses `thresh`), "otsu" or "triangle"
        /// (computed from the histogram of a gray u8 or u16 image; `thresh` is ignored).
        method: ThresholdMethod = ThresholdMethod::Fixed,
        /// How samples are mapped: "binary", "binary_inv", "trunc", "to_zero" or
        /// "to_zero_inv" (OpenCV's threshold types).
        mode: ThresholdMode = ThresholdMode::Binary,
        /// Threshold, in the image's units (gray levels 0–255 for u8, 0–65535 for u16, the
        /// sample values for f32); integer images use `⌊thresh⌋`. Default 127.
        thresh: f64 = 127.0,
        /// Value written for samples that pass in the binary modes, in the image's units
        /// (rounded and saturated for integer images). Default 255.
        max_value: f64 = 255.0,
    }
}

/// Global threshold (`filter.threshold`). See [`threshold`].
#[derive(Debug, Clone, PartialEq)]
pub struct Threshold {
    method: ThresholdMethod,
    mode: ThresholdMode,
    thresh: f64,
    max_value: f64,
}

impl Op for Threshold {
    type Params = ThresholdParams;
    const ID: &'static str = "filter.threshold";
    const SUMMARY: &'static str =
        "Thresholds every sample with a fixed, Otsu or triangle threshold.";
    const DOC: &'static str = r#"
Compares every sample with a threshold t and maps it by `mode` (OpenCV's threshold types):
binary `src > t ? max_value : 0`, binary_inv `src > t ? 0 : max_value`, trunc `min(src, t)`,
to_zero `src > t ? src : 0`, to_zero_inv `src > t ? 0 : src`. Colour images are thresholded per
channel with the same t. The output has the input's format; the `threshold` output is the t
used: `⌊thresh⌋` for u8/u16 with method fixed (as `cv2.threshold` returns), `thresh` for f32,
or the computed one.

Method "otsu" (Otsu 1979, "A threshold selection method from gray-level histograms") picks the
t maximizing the between-class variance q1·q2·(μ1 − μ2)² over the image's histogram, the
lowest such t on ties, with OpenCV's `getThreshVal_Otsu` arithmetic step by step: the same t as
`cv2.threshold(..., THRESH_OTSU)`. Method "triangle" (Zack, Rogers & Latt 1977) takes the
histogram level farthest from the line between the histogram's peak and its far end, as
OpenCV's `THRESH_TRIANGLE`. Both need a gray u8 image (256 bins) or gray u16 image (65536 bins,
as OpenCV 4.10+/5 for Otsu; triangle on u16 is an extension); f32 and colour images are
rejected (convert with filter.grayscale first).

Integer thresholds outside the sample range collapse to a constant or a copy, as in OpenCV.
NaN f32 samples compare false (binary gives 0, trunc keeps NaN).

Reference: OpenCV `cv::threshold`, `cv::ThresholdTypes`.

Example:
    "mask": (op: "filter.threshold", inputs: { "image": "gray.image" }, params: (method: otsu)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to threshold, any pixel format (gray u8/u16 for otsu and triangle).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "image",
                PortType::Image,
                "Thresholded image, the input's size and pixel format.",
            ),
            PortSpec::new(
                "threshold",
                PortType::Scalar,
                "The threshold used, in the image's units.",
            ),
        ]
    }

    fn new(params: ThresholdParams) -> Result<Self, String> {
        let ThresholdParams {
            method,
            mode,
            thresh,
            max_value,
        } = params;
        if !thresh.is_finite() {
            return Err(format!("`thresh` must be finite, got {thresh}"));
        }
        if !max_value.is_finite() {
            return Err(format!("`max_value` must be finite, got {max_value}"));
        }
        Ok(Threshold {
            method,
            mode,
            thresh,
            max_value,
        })
    }
}

impl Operator for Threshold {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (out, t) = threshold(image, self.method, self.mode, self.thresh, self.max_value)
            .map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new()
            .with("image", Value::image(out))
            .with("threshold", Value::Scalar(t)))
    }
}

/// Thresholds `image` (see [`ThresholdMode`]) and returns it with the threshold used (the
/// computed one for Otsu and triangle, `⌊thresh⌋` for integer images, `thresh` for f32).
///
/// Errors: Otsu and triangle on colour or f32 images.
pub fn threshold(
    image: &Image,
    method: ThresholdMethod,
    mode: ThresholdMode,
    thresh: f64,
    max_value: f64,
) -> Result<(Image, f64), String> {
    let thresh = match method {
        ThresholdMethod::Fixed => thresh,
        ThresholdMethod::Otsu | ThresholdMethod::Triangle => {
            let otsu = method == ThresholdMethod::Otsu;
            let name = method.name();
            if image.channels() != Channels::Gray {
                return Err(format!(
                    "{name} needs a gray image, got {} (convert with filter.grayscale first)",
                    image.channels().name()
                ));
            }
            match image.data() {
                PixelData::U8(v) if otsu => f64::from(otsu_threshold_u8(v)),
                PixelData::U8(v) => f64::from(triangle_threshold_u8(v)),
                PixelData::U16(v) if otsu => f64::from(otsu_threshold_u16(v)),
                PixelData::U16(v) => f64::from(triangle_threshold_u16(v)),
                PixelData::F32(_) => {
                    return Err(format!(
                        "{name} needs a u8 or u16 image, got f32 (use method fixed, or convert)"
                    ));
                }
            }
        }
    };
    let (data, t) = match image.data() {
        PixelData::U8(src) => {
            let t = thresh.floor();
            (PixelData::U8(threshold_int(src, mode, t, max_value)), t)
        }
        PixelData::U16(src) => {
            let t = thresh.floor();
            (PixelData::U16(threshold_int(src, mode, t, max_value)), t)
        }
        PixelData::F32(src) => {
            let out = map_chunks(src, |s, d| {
                threshold_slice(s, d, mode, thresh as f32, max_value as f32)
            });
            (PixelData::F32(out), thresh)
        }
    };
    let out = Image::new(image.width(), image.height(), image.channels(), data)
        .map_err(|e| e.to_string())?;
    Ok((out, t))
}

/// Integer sample types thresholded here.
trait Sample: Copy + Default + PartialOrd + Send + Sync + 'static {
    const MAX: f64;
    fn from_f64_saturating(v: f64) -> Self;
}

impl Sample for u8 {
    const MAX: f64 = 255.0;
    fn from_f64_saturating(v: f64) -> Self {
        v.round_ties_even() as u8
    }
}

impl Sample for u16 {
    const MAX: f64 = 65535.0;
    fn from_f64_saturating(v: f64) -> Self {
        v.round_ties_even() as u16
    }
}

/// Threshold of integer samples with the integer threshold `t` (already floored).
fn threshold_int<T: Sample>(src: &[T], mode: ThresholdMode, t: f64, max_value: f64) -> Vec<T> {
    let max = T::from_f64_saturating(max_value);
    let zero = T::default();
    if t < 0.0 || t >= T::MAX {
        // Every sample is above (t < 0) or none is (t ≥ MAX).
        let above = t < 0.0;
        let constant = match (mode, above) {
            (ThresholdMode::Binary, true) | (ThresholdMode::BinaryInv, false) => Some(max),
            (ThresholdMode::Binary, false)
            | (ThresholdMode::BinaryInv, true)
            | (ThresholdMode::Trunc, true)
            | (ThresholdMode::ToZero, false)
            | (ThresholdMode::ToZeroInv, true) => Some(zero),
            (ThresholdMode::Trunc, false)
            | (ThresholdMode::ToZero, true)
            | (ThresholdMode::ToZeroInv, false) => None,
        };
        return match constant {
            Some(c) => vec![c; src.len()],
            None => src.to_vec(),
        };
    }
    let t = T::from_f64_saturating(t);
    map_chunks(src, |s, d| threshold_slice(s, d, mode, t, max))
}

/// `dst = f(src)` by [`ThresholdMode`], with comparisons `src > t`.
#[inline]
fn threshold_slice<T: Copy + Default + PartialOrd>(
    src: &[T],
    dst: &mut [T],
    mode: ThresholdMode,
    t: T,
    max: T,
) {
    let zero = T::default();
    let pairs = dst.iter_mut().zip(src);
    match mode {
        ThresholdMode::Binary => pairs.for_each(|(d, &s)| *d = if s > t { max } else { zero }),
        ThresholdMode::BinaryInv => pairs.for_each(|(d, &s)| *d = if s > t { zero } else { max }),
        ThresholdMode::Trunc => pairs.for_each(|(d, &s)| *d = if s > t { t } else { s }),
        ThresholdMode::ToZero => pairs.for_each(|(d, &s)| *d = if s > t { s } else { zero }),
        ThresholdMode::ToZeroInv => pairs.for_each(|(d, &s)| *d = if s > t { zero } else { s }),
    }
}

/// Applies `f(src_chunk, dst_chunk)` over fixed-size chunks in parallel.
fn map_chunks<T, F>(src: &[T], f: F) -> Vec<T>
where
    T: Copy + Default + Send + Sync,
    F: Fn(&[T], &mut [T]) + Sync,
{
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
    dst.par_chunks_mut(CHUNK)
        .zip(src.par_chunks(CHUNK))
        .for_each(|(d, s)| f(s, d));
    dst
}

/// Otsu's threshold of u8 samples, as OpenCV's `getThreshVal_Otsu_8u`: the level `t` (0..=255)
/// maximizing `q1·q2·(μ1 − μ2)²` for the classes `≤ t` and `> t`, the first on ties; 0 for an
/// empty or constant image.
pub fn otsu_threshold_u8(samples: &[u8]) -> u8 {
    let hist = histogram_u8(samples);
    otsu_from_histogram(&hist, samples.len()) as u8
}

/// Otsu's threshold of u16 samples over the 65536-bin histogram (OpenCV's 16-bit Otsu).
pub fn otsu_threshold_u16(samples: &[u16]) -> u16 {
    let hist = histogram_u16(samples);
    otsu_from_histogram(&hist, samples.len()) as u16
}

/// Otsu's level on a histogram of `total` samples (OpenCV's loop, f64 throughout).
fn otsu_from_histogram(hist: &[u64], total: usize) -> usize {
    if total == 0 {
        return 0;
    }
    let scale = 1.0 / total as f64;
    let mu = hist
        .iter()
        .enumerate()
        .fold(0.0, |acc, (i, &h)| acc + i as f64 * h as f64)
        * scale;
    let eps = f64::from(f32::EPSILON);
    let (mut mu1, mut q1) = (0.0f64, 0.0f64);
    let (mut max_sigma, mut max_val) = (0.0f64, 0usize);
    for (i, &h) in hist.iter().enumerate() {
        let p = h as f64 * scale;
        mu1 *= q1;
        q1 += p;
        let q2 = 1.0 - q1;
        if q1.min(q2) < eps || q1.max(q2) > 1.0 - eps {
            continue;
        }
        mu1 = (mu1 + i as f64 * p) / q1;
        let mu2 = (mu - q1 * mu1) / q2;
        let sigma = q1 * q2 * (mu1 - mu2) * (mu1 - mu2);
        if sigma > max_sigma {
            max_sigma = sigma;
            max_val = i;
        }
    }
    max_val
}

/// The triangle threshold of u8 samples, as OpenCV's `getThreshVal_Triangle_8u`.
pub fn triangle_threshold_u8(samples: &[u8]) -> u8 {
    let hist = histogram_u8(samples);
    triangle_from_histogram(&hist) as u8
}

/// The triangle threshold of u16 samples over the 65536-bin histogram.
pub fn triangle_threshold_u16(samples: &[u16]) -> u16 {
    let hist = histogram_u16(samples);
    triangle_from_histogram(&hist) as u16
}

/// Zack's triangle level on a histogram (OpenCV's steps: bounds widened by one bin, the
/// histogram flipped when the peak is nearer its left bound, the last maximum of
/// `peak·i + (left − peak_index)·h[i]`, minus one).
fn triangle_from_histogram(hist: &[u64]) -> usize {
    let n = hist.len();
    if n == 0 {
        return 0;
    }
    let mut left = hist.iter().position(|&h| h > 0).unwrap_or(0);
    left = left.saturating_sub(1);
    // OpenCV's right-bound search stops before index 0.
    let mut right = (1..n).rev().find(|&i| hist[i] > 0).unwrap_or(0);
    if right < n - 1 {
        right += 1;
    }
    let (mut peak_index, mut peak) = (0usize, 0u64);
    for (i, &h) in hist.iter().enumerate() {
        if h > peak {
            peak = h;
            peak_index = i;
        }
    }
    let flipped = (peak_index as i64 - left as i64) < (right as i64 - peak_index as i64);
    let at = |i: usize| if flipped { hist[n - 1 - i] } else { hist[i] };
    if flipped {
        left = n - 1 - right;
        peak_index = n - 1 - peak_index;
    }
    let a = peak as f64;
    let b = left as f64 - peak_index as f64;
    let mut thresh = left as i64;
    let mut dist = 0.0;
    for i in left + 1..=peak_index {
        let d = a * i as f64 + b * at(i) as f64;
        if d > dist {
            dist = d;
            thresh = i as i64;
        }
    }
    thresh -= 1;
    if flipped {
        thresh = n as i64 - 1 - thresh;
    }
    thresh.clamp(0, n as i64 - 1) as usize
}

param_enum! {
    /// The local mean of `filter.adaptive_threshold`.
    pub enum AdaptiveMethod {
        /// Box mean of the block (`ADAPTIVE_THRESH_MEAN_C`).
        Mean = "mean",
        /// Gaussian-weighted mean (`ADAPTIVE_THRESH_GAUSSIAN_C`).
        Gaussian = "gaussian",
    }
}

param_enum! {
    /// Output mapping of `filter.adaptive_threshold`.
    pub enum AdaptiveMode {
        /// `src > T ? max_value : 0`.
        Binary = "binary",
        /// `src > T ? 0 : max_value`.
        BinaryInv = "binary_inv",
    }
}

params! {
    /// Parameters of `filter.adaptive_threshold`.
    pub struct AdaptiveParams {
        /// Local mean: "mean" (box) or "gaussian" (σ = 0.3·((block_size − 1)/2 − 1) + 0.8).
        method: AdaptiveMethod = AdaptiveMethod::Mean,
        /// Side of the square neighbourhood, px, odd, 3..=1023. Default 11.
        block_size: u32 = 11 => [min = 3.0, max = 1023.0, unit = "px"],
        /// Constant subtracted from the local mean, in the image's units (gray levels for
        /// integer images). Default 2.
        c: f64 = 2.0,
        /// "binary" (`src > T ? max_value : 0`) or "binary_inv".
        mode: AdaptiveMode = AdaptiveMode::Binary,
        /// Value written for passing samples, in the image's units (rounded and saturated for
        /// integer images). Default 255.
        max_value: f64 = 255.0,
    }
}

/// Adaptive threshold (`filter.adaptive_threshold`). See [`adaptive_threshold`].
#[derive(Debug, Clone, PartialEq)]
pub struct AdaptiveThreshold {
    method: AdaptiveMethod,
    block_size: usize,
    c: f64,
    mode: AdaptiveMode,
    max_value: f64,
}

impl Op for AdaptiveThreshold {
    type Params = AdaptiveParams;
    const ID: &'static str = "filter.adaptive_threshold";
    const SUMMARY: &'static str =
        "Thresholds every sample against the mean of its neighbourhood minus a constant.";
    const DOC: &'static str = r#"
Binary threshold with a threshold that varies over the image: T(x, y) = mean(x, y) − c, where
mean is the box mean ("mean") or the Gaussian-weighted mean ("gaussian", the kernel of
`getGaussianKernel(block_size, 0)`, i.e. σ = 0.3·((block_size − 1)/2 − 1) + 0.8) over the
`block_size × block_size` neighbourhood, border replicate (OpenCV's choice, not reflect-101).
Output binary: `src > T ? max_value : 0`; binary_inv the complement. Channels are thresholded
independently; the output has the input's format.

u8 follows OpenCV's `adaptiveThreshold` bit for bit: the mean is rounded to u8 first, and the
test is `src − mean > −⌈c⌉` (binary) or `src − mean ≤ −⌊c⌋` (binary_inv) in integers. The
Gaussian mean is computed in f32 and rounded; for block_size ≤ 9 its weights are dyadic and the
result is exact (identical to OpenCV), for larger blocks a mean within f32 rounding of a half
level can round the other way (measured on a 1080p photo-like image: at most 3 of 2 073 600
pixels differ for block sizes 11 and 25). u16 and f32 images (an extension; OpenCV takes u8 only) compare
`src > mean − c` on the f32 mean without rounding.

Reference: OpenCV `cv::adaptiveThreshold`.

Example:
    "binary": (op: "filter.adaptive_threshold", inputs: { "image": "gray.image" }, params: (block_size: 11, c: 2.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to threshold, any pixel format (usually gray u8).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "0 / max_value image, the input's size and pixel format.",
        )]
    }

    fn new(params: AdaptiveParams) -> Result<Self, String> {
        let AdaptiveParams {
            method,
            block_size,
            c,
            mode,
            max_value,
        } = params;
        if !(3..=MAX_BLOCK).contains(&block_size) || block_size % 2 == 0 {
            return Err(format!(
                "`block_size` must be odd and between 3 and {MAX_BLOCK} px, got {block_size}"
            ));
        }
        if !c.is_finite() {
            return Err(format!("`c` must be finite, got {c}"));
        }
        if !max_value.is_finite() {
            return Err(format!("`max_value` must be finite, got {max_value}"));
        }
        Ok(AdaptiveThreshold {
            method,
            block_size: block_size as usize,
            c,
            mode,
            max_value,
        })
    }
}

impl Operator for AdaptiveThreshold {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = adaptive_threshold(
            image,
            self.method,
            self.block_size,
            self.c,
            self.mode,
            self.max_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Adaptive threshold of `image` (see [`AdaptiveThreshold`]'s doc for the exact arithmetic):
/// `block_size` (odd px) sets the neighbourhood, `c` is subtracted from the local mean.
pub fn adaptive_threshold(
    image: &Image,
    method: AdaptiveMethod,
    block_size: usize,
    c: f64,
    mode: AdaptiveMode,
    max_value: f64,
) -> Image {
    if image.is_empty() {
        return image.clone();
    }
    let block = block_size.max(1) | 1;
    let inverse = mode == AdaptiveMode::BinaryInv;
    let data = match image.data() {
        PixelData::U8(src) => {
            let mean = match method {
                AdaptiveMethod::Mean => {
                    box_filter(image, block, block, true, BorderMode::Clamp, 0.0).into_data()
                }
                AdaptiveMethod::Gaussian => {
                    let blurred = gaussian_mean(&to_f32(image), block);
                    PixelData::U8(
                        blurred
                            .iter()
                            .map(|&m| round_small(m).clamp(0.0, 255.0) as u8)
                            .collect(),
                    )
                }
            };
            let PixelData::U8(mut mean) = mean else {
                return image.clone();
            };
            let max = max_value.round_ties_even().clamp(0.0, 255.0) as u8;
            // OpenCV: binary passes when src − mean > −⌈c⌉, binary_inv when src − mean ≤ −⌊c⌋.
            let limit = if inverse { -c.floor() } else { -c.ceil() };
            let limit = limit.clamp(-1024.0, 1024.0) as i16;
            // One loop per polarity, so each is a plain compare-and-select; the result
            // overwrites the mean in place.
            let (above, below) = if inverse { (0, max) } else { (max, 0) };
            mean.par_chunks_mut(CHUNK)
                .zip(src.par_chunks(CHUNK))
                .for_each(|(m, s)| {
                    for (m, &s) in m.iter_mut().zip(s) {
                        *m = if i16::from(s) - i16::from(*m) > limit {
                            above
                        } else {
                            below
                        };
                    }
                });
            PixelData::U8(mean)
        }
        PixelData::U16(src) => {
            let mean = float_mean(image, method, block);
            let max = max_value.round_ties_even().clamp(0.0, 65535.0) as u16;
            let c = c as f32;
            PixelData::U16(
                src.iter()
                    .zip(&mean)
                    .map(|(&s, &m)| {
                        if (f32::from(s) > m - c) != inverse {
                            max
                        } else {
                            0
                        }
                    })
                    .collect(),
            )
        }
        PixelData::F32(src) => {
            let mean = float_mean(image, method, block);
            let (max, c) = (max_value as f32, c as f32);
            PixelData::F32(
                src.iter()
                    .zip(&mean)
                    .map(|(&s, &m)| if (s > m - c) != inverse { max } else { 0.0 })
                    .collect(),
            )
        }
    };
    Image::new(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

/// Rounds to nearest, ties to even, for |x| < 2²² (adding and subtracting 1.5·2²³); unlike
/// `round_ties_even` it vectorizes without SSE4.1.
fn round_small(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC) - MAGIC
}

/// `image` as f32 samples (same units).
fn to_f32(image: &Image) -> Image {
    let data: Vec<f32> = match image.data() {
        PixelData::U8(v) => v.iter().map(|&x| f32::from(x)).collect(),
        PixelData::U16(v) => v.iter().map(|&x| f32::from(x)).collect(),
        PixelData::F32(v) => v.clone(),
    };
    Image::from_f32(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

/// Gaussian mean of an f32 image with OpenCV's sigma-0 kernel of `block` taps, border
/// replicate.
fn gaussian_mean(image: &Image, block: usize) -> Vec<f32> {
    let kernel = gaussian_kernel(block, 0.0);
    match separable_filter(image, &kernel, &kernel, BorderMode::Clamp, 0.0).into_data() {
        PixelData::F32(v) => v,
        _ => Vec::new(),
    }
}

/// The local mean of an image as f32 samples (box or Gaussian, border replicate).
fn float_mean(image: &Image, method: AdaptiveMethod, block: usize) -> Vec<f32> {
    let float = to_f32(image);
    match method {
        AdaptiveMethod::Mean => {
            match box_filter(&float, block, block, true, BorderMode::Clamp, 0.0).into_data() {
                PixelData::F32(v) => v,
                _ => Vec::new(),
            }
        }
        AdaptiveMethod::Gaussian => gaussian_mean(&float, block),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::filter::test_support::{random_u8, randoms};
    use proptest::prelude::*;

    /// Two clusters, 35 % in 40..100 and 65 % in 150..230 (the same formula as the OpenCV
    /// reference script, so the pasted thresholds apply).
    pub(crate) fn bimodal(w: usize, h: usize, seed: u64) -> Image {
        let r = randoms(seed, 2 * w * h);
        let data = (0..w * h)
            .map(|i| {
                if r[2 * i] < 0.35 {
                    (40.0 + r[2 * i + 1] * 60.0) as u8
                } else {
                    (150.0 + r[2 * i + 1] * 80.0) as u8
                }
            })
            .collect();
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    /// Ramps plus noise: `(7x + 3y) mod 97 + 40·r`.
    pub(crate) fn smooth(w: usize, h: usize, seed: u64) -> Image {
        let r = randoms(seed, w * h);
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                ((7 * x + 3 * y) % 97) as u8 + (r[i] * 40.0) as u8
            })
            .collect();
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    fn gray(data: Vec<u8>) -> Image {
        let n = data.len();
        Image::from_u8(n, 1, Channels::Gray, data).unwrap()
    }

    #[test]
    fn every_mode_by_hand() {
        let image = gray(vec![0, 100, 127, 128, 200, 255]);
        let run = |mode| {
            let (out, t) = threshold(&image, ThresholdMethod::Fixed, mode, 127.9, 250.0).unwrap();
            assert_eq!(t, 127.0);
            out.as_u8().unwrap().to_vec()
        };
        assert_eq!(run(ThresholdMode::Binary), [0, 0, 0, 250, 250, 250]);
        assert_eq!(run(ThresholdMode::BinaryInv), [250, 250, 250, 0, 0, 0]);
        assert_eq!(run(ThresholdMode::Trunc), [0, 100, 127, 127, 127, 127]);
        assert_eq!(run(ThresholdMode::ToZero), [0, 0, 0, 128, 200, 255]);
        assert_eq!(run(ThresholdMode::ToZeroInv), [0, 100, 127, 0, 0, 0]);
    }

    #[test]
    fn thresholds_outside_the_range() {
        let image = gray(vec![0, 9, 255]);
        let run = |mode, t| {
            let (out, _) = threshold(&image, ThresholdMethod::Fixed, mode, t, 300.0).unwrap();
            out.as_u8().unwrap().to_vec()
        };
        // Checked against cv2.threshold (max_value saturates to 255).
        assert_eq!(run(ThresholdMode::Binary, -1.0), [255, 255, 255]);
        assert_eq!(run(ThresholdMode::Binary, 255.0), [0, 0, 0]);
        assert_eq!(run(ThresholdMode::BinaryInv, 255.0), [255, 255, 255]);
        assert_eq!(run(ThresholdMode::Trunc, -5.0), [0, 0, 0]);
        assert_eq!(run(ThresholdMode::Trunc, 400.0), [0, 9, 255]);
        assert_eq!(run(ThresholdMode::ToZero, -5.0), [0, 9, 255]);
        assert_eq!(run(ThresholdMode::ToZeroInv, 255.0), [0, 9, 255]);
        assert_eq!(run(ThresholdMode::ToZeroInv, -0.5), [0, 0, 0]);
    }

    #[test]
    fn u16_and_f32() {
        let image = Image::from_u16(3, 1, Channels::Gray, vec![10, 1000, 60000]).unwrap();
        let (out, t) = threshold(
            &image,
            ThresholdMethod::Fixed,
            ThresholdMode::Binary,
            999.5,
            65535.0,
        )
        .unwrap();
        assert_eq!(t, 999.0);
        assert_eq!(out.as_u16().unwrap(), &[0, 65535, 65535]);
        let image = Image::from_f32(4, 1, Channels::Gray, vec![-1.0, 0.25, 0.5, f32::NAN]).unwrap();
        let (out, t) = threshold(
            &image,
            ThresholdMethod::Fixed,
            ThresholdMode::Binary,
            0.25,
            1.0,
        )
        .unwrap();
        assert_eq!(t, 0.25);
        assert_eq!(out.as_f32().unwrap(), &[0.0, 0.0, 1.0, 0.0]);
        let (out, _) = threshold(
            &image,
            ThresholdMethod::Fixed,
            ThresholdMode::Trunc,
            0.25,
            1.0,
        )
        .unwrap();
        let v = out.as_f32().unwrap();
        assert_eq!(&v[..3], &[-1.0, 0.25, 0.25]);
        assert!(v[3].is_nan());
    }

    #[test]
    fn colour_is_thresholded_per_channel() {
        let image = Image::from_u8(2, 1, Channels::Rgb, vec![10, 200, 130, 128, 127, 0]).unwrap();
        let (out, _) = threshold(
            &image,
            ThresholdMethod::Fixed,
            ThresholdMode::Binary,
            127.0,
            255.0,
        )
        .unwrap();
        assert_eq!(out.as_u8().unwrap(), &[0, 255, 255, 255, 0, 0]);
    }

    #[test]
    fn otsu_and_triangle_match_opencv() {
        // cv2.threshold(img, 0, 255, THRESH_OTSU / THRESH_TRIANGLE)[0] on the same images.
        let cases = [
            (bimodal(64, 48, 1), 99, 148),
            (bimodal(31, 17, 2), 99, 211),
            (bimodal(200, 100, 3), 99, 148),
            (random_u8(64, 48, Channels::Gray, 4), 128, 107),
            (smooth(64, 48, 4), 67, 52),
            (random_u8(33, 21, Channels::Gray, 5), 129, 24),
            (smooth(33, 21, 5), 64, 64),
        ];
        for (i, (image, otsu, triangle)) in cases.iter().enumerate() {
            let samples = image.as_u8().unwrap();
            assert_eq!(otsu_threshold_u8(samples), *otsu, "otsu case {i}");
            assert_eq!(
                triangle_threshold_u8(samples),
                *triangle,
                "triangle case {i}"
            );
            let (out, t) = threshold(
                image,
                ThresholdMethod::Otsu,
                ThresholdMode::Binary,
                0.0,
                255.0,
            )
            .unwrap();
            assert_eq!(t, f64::from(*otsu));
            for (&o, &s) in out.as_u8().unwrap().iter().zip(samples) {
                assert_eq!(o, if s > *otsu { 255 } else { 0 });
            }
        }
    }

    #[test]
    fn otsu_edge_cases() {
        assert_eq!(otsu_threshold_u8(&[]), 0);
        assert_eq!(otsu_threshold_u8(&[77; 50]), 0);
        // Two levels: the split lies at the lower one.
        assert_eq!(otsu_threshold_u8(&[10, 10, 200, 200]), 10);
        let u16s: Vec<u16> = [10u16, 10, 50_000, 50_000, 50_001].to_vec();
        assert_eq!(otsu_threshold_u16(&u16s), 10);
        let rgb = Image::from_u8(1, 1, Channels::Rgb, vec![1, 2, 3]).unwrap();
        let err = threshold(
            &rgb,
            ThresholdMethod::Otsu,
            ThresholdMode::Binary,
            0.0,
            255.0,
        );
        assert!(err.unwrap_err().contains("gray"));
        let f = Image::from_f32(1, 1, Channels::Gray, vec![0.5]).unwrap();
        let err = threshold(
            &f,
            ThresholdMethod::Triangle,
            ThresholdMode::Binary,
            0.0,
            1.0,
        );
        assert!(err.unwrap_err().contains("f32"));
    }

    #[test]
    fn empty_and_single_pixel() {
        for (w, h) in [(0, 0), (0, 3), (1, 1)] {
            let image = Image::from_u8(w, h, Channels::Gray, vec![9; w * h]).unwrap();
            for method in ThresholdMethod::ALL {
                let (out, _) =
                    threshold(&image, *method, ThresholdMode::Binary, 5.0, 255.0).unwrap();
                assert_eq!((out.width(), out.height()), (w, h));
            }
            let out = adaptive_threshold(
                &image,
                AdaptiveMethod::Gaussian,
                5,
                0.0,
                AdaptiveMode::Binary,
                255.0,
            );
            assert_eq!((out.width(), out.height()), (w, h));
        }
    }

    #[test]
    fn adaptive_matches_opencv() {
        // cv2.adaptiveThreshold(smooth(12, 10, 7), 255, method, THRESH_BINARY, 5, 2).
        let image = smooth(12, 10, 7);
        let expected = [
            (
                AdaptiveMethod::Mean,
                "001100100101111110111000110010101011010011000011111000101011001000111110001100111011001010100110011110001110111011111100",
            ),
            (
                AdaptiveMethod::Gaussian,
                "001000100101111010111000110010101011010011000011111000101011001010111100111100111011001010100110011110001110111011110100",
            ),
        ];
        for (method, bits) in expected {
            let out = adaptive_threshold(&image, method, 5, 2.0, AdaptiveMode::Binary, 255.0);
            let ours: String = out
                .as_u8()
                .unwrap()
                .iter()
                .map(|&v| if v == 255 { '1' } else { '0' })
                .collect();
            assert_eq!(ours, bits, "{method:?}");
        }
    }

    #[test]
    fn adaptive_by_hand() {
        // A 1-D step: the box mean (3×3, replicate) of a constant region is the value itself,
        // so with c = 0 nothing passes there; at the step the bright side passes.
        let row = [10u8, 10, 10, 90, 90, 90];
        let data: Vec<u8> = row.iter().cycle().take(18).copied().collect();
        let image = Image::from_u8(6, 3, Channels::Gray, data).unwrap();
        let out = adaptive_threshold(
            &image,
            AdaptiveMethod::Mean,
            3,
            0.0,
            AdaptiveMode::Binary,
            255.0,
        );
        assert_eq!(&out.as_u8().unwrap()[..6], &[0, 0, 0, 255, 0, 0]);
        // binary_inv with an integer c is the complement.
        let inv = adaptive_threshold(
            &image,
            AdaptiveMethod::Mean,
            3,
            0.0,
            AdaptiveMode::BinaryInv,
            255.0,
        );
        assert_eq!(&inv.as_u8().unwrap()[..6], &[255, 255, 255, 0, 255, 255]);
        // c = 1: a constant region passes (src − mean = 0 > −1).
        let out = adaptive_threshold(
            &image,
            AdaptiveMethod::Mean,
            3,
            1.0,
            AdaptiveMode::Binary,
            255.0,
        );
        assert_eq!(&out.as_u8().unwrap()[..6], &[255, 255, 0, 255, 255, 255]);
        // f32 follows the same rule without rounding.
        let f = Image::from_f32(
            6,
            3,
            Channels::Gray,
            image
                .as_u8()
                .unwrap()
                .iter()
                .map(|&v| f32::from(v))
                .collect(),
        )
        .unwrap();
        let out = adaptive_threshold(&f, AdaptiveMethod::Mean, 3, 1.0, AdaptiveMode::Binary, 1.0);
        assert_eq!(&out.as_f32().unwrap()[..6], &[1.0, 1.0, 0.0, 1.0, 1.0, 1.0]);
    }

    #[test]
    fn identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let image = random_u8(301, 257, Channels::Gray, 11);
        let run = || {
            (
                threshold(
                    &image,
                    ThresholdMethod::Otsu,
                    ThresholdMode::ToZero,
                    0.0,
                    255.0,
                )
                .unwrap(),
                adaptive_threshold(
                    &image,
                    AdaptiveMethod::Gaussian,
                    7,
                    1.5,
                    AdaptiveMode::Binary,
                    255.0,
                ),
            )
        };
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    #[test]
    fn new_checks_params() {
        let t = |thresh: f64, max_value: f64| {
            Threshold::new(ThresholdParams {
                thresh,
                max_value,
                ..ThresholdParams::default()
            })
        };
        assert!(t(127.0, 255.0).is_ok());
        assert!(t(f64::NAN, 255.0).is_err());
        assert!(t(1.0, f64::INFINITY).is_err());
        let a = |block_size: u32, c: f64| {
            AdaptiveThreshold::new(AdaptiveParams {
                block_size,
                c,
                ..AdaptiveParams::default()
            })
        };
        assert!(a(11, 2.0).is_ok());
        assert!(a(4, 2.0).is_err());
        assert!(a(1, 2.0).is_err());
        assert!(a(2047, 2.0).is_err());
        assert!(a(5, f64::NAN).is_err());
    }

    proptest! {
        #[test]
        fn binary_outputs_and_complements(
            data in proptest::collection::vec(any::<u8>(), 1..200),
            thresh in -10.0f64..270.0,
            max in 0u8..=255,
        ) {
            let image = gray(data.clone());
            let max_value = f64::from(max);
            let run = |mode| threshold(&image, ThresholdMethod::Fixed, mode, thresh, max_value).unwrap().0;
            let binary = run(ThresholdMode::Binary);
            let inverse = run(ThresholdMode::BinaryInv);
            for ((&b, &i), &s) in binary.as_u8().unwrap().iter().zip(inverse.as_u8().unwrap()).zip(&data) {
                prop_assert!(b == 0 || b == max);
                prop_assert_eq!(i, max - b);
                prop_assert_eq!(b == max && max > 0, f64::from(s) > thresh.floor() && max > 0);
            }
            // to_zero + to_zero_inv = src; trunc ≤ src.
            let zero = run(ThresholdMode::ToZero);
            let zero_inv = run(ThresholdMode::ToZeroInv);
            let trunc = run(ThresholdMode::Trunc);
            for (((&z, &zi), &t), &s) in zero.as_u8().unwrap().iter().zip(zero_inv.as_u8().unwrap()).zip(trunc.as_u8().unwrap()).zip(&data) {
                prop_assert_eq!(u16::from(z) + u16::from(zi), u16::from(s));
                prop_assert!(t <= s);
            }
        }

        #[test]
        fn otsu_maximizes_between_class_variance(data in proptest::collection::vec(any::<u8>(), 2..300)) {
            let t = otsu_threshold_u8(&data) as usize;
            let variance = |t: usize| {
                let lo: Vec<f64> = data.iter().map(|&v| f64::from(v)).filter(|&v| v <= t as f64).collect();
                let n = data.len() as f64;
                let hi: Vec<f64> = data.iter().map(|&v| f64::from(v)).filter(|&v| v > t as f64).collect();
                if lo.is_empty() || hi.is_empty() { return 0.0; }
                let (q1, q2) = (lo.len() as f64 / n, hi.len() as f64 / n);
                let m1 = lo.iter().sum::<f64>() / lo.len() as f64;
                let m2 = hi.iter().sum::<f64>() / hi.len() as f64;
                q1 * q2 * (m1 - m2) * (m1 - m2)
            };
            let best = (0..256).map(variance).fold(0.0, f64::max);
            prop_assert!(variance(t) >= best * (1.0 - 1e-9));
        }
    }
}
