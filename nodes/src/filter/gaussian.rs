//! `filter.gaussian`: separable Gaussian blur, plus the separable-filter engine it runs on.
//!
//! [`separable_filter`] correlates every row with one kernel and every column of the result with
//! another, for u8, u16 and f32 images with interleaved channels, under any [`BorderMode`]. Other
//! linear filters (box, Sobel, pyramids) reuse it with their own kernels.
//!
//! How it runs:
//! - The image is cut into fixed bands of rows processed in parallel (`par_chunks_mut`). Every
//!   output row is computed by the same arithmetic in the same order whatever band or thread it
//!   falls in, so results are bit-identical for any thread count.
//! - Inside a band, each source row is copied (and widened to the pass's arithmetic type) into a
//!   padded scratch row through a [`BorderTable`], so the horizontal pass runs over contiguous
//!   memory with no border branch; its result goes into a ring of `ksize_y` rows, and each
//!   output row is the weighted sum of the ring's rows. Both passes are "weighted sum of K
//!   shifted slices" loops, unrolled for kernels of up to 15 taps, which LLVM vectorizes with
//!   SSE2 alone (no `-C target-cpu`).
//! - u8 images with a smoothing kernel (odd, symmetric, non-negative, summing to 1, at most
//!   [`MAX_FIXED_POINT_TAPS`] taps) use 16-bit fixed-point weights in 16-bit lanes, and run the
//!   column pass first: each output row is the column pass over the source rows it reads,
//!   straight from the image (a row outside it is read through the border table; no padded copy
//!   of the source), into one u16 row that is then padded in place and filtered along the row
//!   into the output. Samples are taken as `256·v`, a product is `⌊x·w / 2¹⁶⌋` (`pmulhuw`),
//!   the column result keeps 8 fractional bits, and symmetric taps are averaged (`pavgw`)
//!   before one multiply by twice their weight. A bias of half a unit per product centres the
//!   truncation error. The result is within `0.5 + (ksize_x + ksize_y + 2)/512` gray levels of
//!   the exact blur, so constant images stay constant. On CPUs with AVX2 both passes run as
//!   intrinsics (`avx2`; LLVM vectorizes a portable high multiply in 32-bit lanes, at
//!   twice the cost), bit-identical to the portable kernels that handle the row tails and
//!   other CPUs. OpenCV instead rounds u8 weights to 8 bits, so the two agree within one level
//!   except, for large kernels on noisy data, a few pixels in 10⁴ (measured: σ = 12 on uniform
//!   noise, up to 0.1 % of pixels differ by 2, OpenCV being 2.4 levels off the exact value
//!   there while this path stays within 0.55).
//! - Other u8 kernels, and u16 and f32 images, accumulate in f32; integer outputs are rounded to
//!   nearest (ties to even) and saturated.

use std::marker::PhantomData;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};

/// Largest explicit kernel size.
pub const MAX_KSIZE: u32 = 4095;

/// Longest kernel the u8 fixed-point path takes; its error bound grows with the tap count, and
/// longer kernels go through f32.
pub const MAX_FIXED_POINT_TAPS: usize = 127;

/// Output rows per parallel band (at least; long kernels get taller bands so that recomputing
/// `ksize_y − 1` rows of overlap per band stays cheap).
const BAND_ROWS: usize = 64;

/// Fixed-point one: kernel weights are multiples of 2⁻¹⁶.
const FIXED_ONE: u32 = 1 << 16;

/// OpenCV's fixed kernels for sizes 1, 3, 5, 7 and 9 when no positive sigma is given
/// (`getGaussianKernel`, which since OpenCV 4 goes through `getGaussianKernelBitExact`).
const SMALL_KERNELS: [&[f64]; 5] = [
    &[1.0],
    &[0.25, 0.5, 0.25],
    &[0.0625, 0.25, 0.375, 0.25, 0.0625],
    &[
        0.03125, 0.109375, 0.21875, 0.28125, 0.21875, 0.109375, 0.03125,
    ],
    // [4 13 30 51 60 51 30 13 4] / 256
    &[
        0.015625, 0.05078125, 0.1171875, 0.19921875, 0.234375, 0.19921875, 0.1171875, 0.05078125,
        0.015625,
    ],
];

params! {
    /// Parameters of `filter.gaussian`.
    pub struct GaussianParams {
        /// Standard deviation along x. 0 derives it from `ksize` as OpenCV does:
        /// `0.3·((ksize − 1)/2 − 1) + 0.8`.
        sigma: f64 = 1.0 => [min = 0.0, max = 1000.0, unit = "px"],
        /// Standard deviation along y; `None` uses `sigma`, 0 derives it from `ksize`.
        sigma_y: Option<f64> = None => [min = 0.0, max = 1000.0, unit = "px"],
        /// Kernel size, odd, the same along both axes; 0 chooses `round(6σ + 1) | 1` per axis
        /// (OpenCV's choice for u8 images).
        ksize: u32 = 0 => [max = 4095, unit = "px"],
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units
        /// (0–255 for u8, 0–65535 for u16; rounded and saturated for integer images).
        border_value: f64 = 0.0,
    }
}

/// Gaussian blur (`filter.gaussian`). See [`gaussian_blur`].
#[derive(Debug, Clone, PartialEq)]
pub struct Gaussian {
    sigma_x: f64,
    sigma_y: f64,
    ksize_x: usize,
    ksize_y: usize,
    border: BorderMode,
    border_value: f64,
}

impl Op for Gaussian {
    type Params = GaussianParams;
    const ID: &'static str = "filter.gaussian";
    const SUMMARY: &'static str = "Blurs an image with a separable Gaussian kernel.";
    const DOC: &'static str = r#"
Blurs an image with a Gaussian kernel, separably: each row is correlated with the x kernel, then
each column with the y kernel. Works on every pixel format; the output has the input's format.

Method: separable Gaussian convolution with kernels as OpenCV's `getGaussianKernel` (samples of
exp(−x²/2σ²) normalised to sum 1; for sigma 0 and ksize ≤ 9 OpenCV's fixed kernels, e.g.
[1 4 6 4 1]/16 for ksize 5). Kernel size 0 means round(6σ + 1) | 1 for every sample type
(OpenCV uses this rule for u8 only, round(8σ + 1) | 1 for u16 and f32). Border modes are
OpenCV's border types. u8 images use 16-bit fixed-point weights: within about half a gray level
of the exact result, and within one level of OpenCV's `GaussianBlur`, which rounds its u8
weights to 8 bits (for σ ≳ 5 on noise, a few pixels in 10⁴ differ by 2). u16 and f32 images
accumulate in f32 (with an explicit ksize, within 1 of OpenCV for u16 and 3·10⁻⁷ for f32 in
0..1). NaN in f32 input spreads to the outputs whose window contains it.

Reference: OpenCV `cv::GaussianBlur`, `cv::getGaussianKernel`, `cv::BorderTypes`.

Example:
    "blur": (op: "filter.gaussian", inputs: { "image": "card.image" }, params: (sigma: 1.5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to blur, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The blurred image, same size and pixel format as the input.",
        )]
    }

    fn new(params: GaussianParams) -> Result<Self, String> {
        let GaussianParams {
            sigma,
            sigma_y,
            ksize,
            border,
            border_value,
        } = params;
        check_sigma("sigma", sigma)?;
        if let Some(s) = sigma_y {
            check_sigma("sigma_y", s)?;
        }
        if ksize > MAX_KSIZE {
            return Err(format!("`ksize` must be ≤ {MAX_KSIZE}, got {ksize}"));
        }
        if ksize % 2 == 0 && ksize != 0 {
            return Err(format!(
                "`ksize` must be odd (or 0 to derive it from sigma), got {ksize}"
            ));
        }
        let sigma_x = sigma;
        let sigma_y = sigma_y.unwrap_or(sigma);
        if ksize == 0 && sigma_x == 0.0 {
            return Err("`sigma` = 0 needs an explicit odd `ksize` to derive sigma from".into());
        }
        if ksize == 0 && sigma_y == 0.0 {
            return Err("`sigma_y` = 0 needs an explicit odd `ksize` to derive sigma from".into());
        }
        check_border_value(border, border_value)?;
        let size = |sigma: f64| {
            if ksize == 0 {
                auto_ksize(sigma)
            } else {
                ksize as usize
            }
        };
        Ok(Gaussian {
            sigma_x,
            sigma_y,
            ksize_x: size(sigma_x),
            ksize_y: size(sigma_y),
            border,
            border_value,
        })
    }
}

fn check_sigma(name: &str, sigma: f64) -> Result<(), String> {
    if (0.0..=1000.0).contains(&sigma) {
        Ok(())
    } else {
        Err(format!(
            "`{name}` must be between 0 and 1000 px, got {sigma}"
        ))
    }
}

impl Operator for Gaussian {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let blurred = gaussian_blur(
            image,
            self.sigma_x,
            self.sigma_y,
            self.ksize_x,
            self.ksize_y,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(blurred)))
    }
}

/// The sigma OpenCV uses for kernel size `ksize` when none is given:
/// `0.3·((ksize − 1)/2 − 1) + 0.8`.
pub fn sigma_for_ksize(ksize: usize) -> f64 {
    0.3 * ((ksize as f64 - 1.0) * 0.5 - 1.0) + 0.8
}

/// The kernel size chosen for `sigma` when none is given: `round(6σ + 1) | 1` (OpenCV's
/// `GaussianBlur` rule for u8 images); 1 for sigma ≤ 0.
pub fn auto_ksize(sigma: f64) -> usize {
    if sigma > 0.0 {
        ((sigma * 6.0 + 1.0).round() as usize) | 1
    } else {
        1
    }
}

/// The 1-D Gaussian kernel of `ksize` taps, as OpenCV's `getGaussianKernel`: for sigma ≤ 0 and
/// odd `ksize` ≤ 9 a fixed kernel (binomial up to 7 taps, e.g. [1 4 6 4 1]/16, and
/// [4 13 30 51 60 51 30 13 4]/256); otherwise samples of `exp(−x²/2σ²)` at
/// `x = i − (ksize − 1)/2`, with sigma ≤ 0 replaced by [`sigma_for_ksize`], scaled to sum 1.
pub fn gaussian_kernel(ksize: usize, sigma: f64) -> Vec<f64> {
    // `sigma <= 0.0` would let NaN through to the formula; NaN counts as "no sigma" here.
    let no_sigma = sigma.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater);
    if ksize % 2 == 1
        && no_sigma
        && let Some(fixed) = SMALL_KERNELS.get(ksize / 2)
    {
        return fixed.to_vec();
    }
    let sigma = if sigma > 0.0 {
        sigma
    } else {
        sigma_for_ksize(ksize)
    };
    let scale = -0.5 / (sigma * sigma);
    let centre = (ksize as f64 - 1.0) * 0.5;
    let mut kernel: Vec<f64> = (0..ksize)
        .map(|i| {
            let x = i as f64 - centre;
            (scale * x * x).exp()
        })
        .collect();
    let inverse_sum = 1.0 / kernel.iter().sum::<f64>();
    for w in &mut kernel {
        *w *= inverse_sum;
    }
    kernel
}

/// Gaussian blur of `image` with standard deviations `sigma_x`, `sigma_y` (px) and kernel sizes
/// `ksize_x`, `ksize_y` (odd; 0 chooses [`auto_ksize`]; a sigma ≤ 0 is derived from the size).
/// `border_value` is the sample read outside the image with [`BorderMode::Constant`].
///
/// The output has the input's size and pixel format; see the module docs for the arithmetic.
pub fn gaussian_blur(
    image: &Image,
    sigma_x: f64,
    sigma_y: f64,
    ksize_x: usize,
    ksize_y: usize,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let ksize_x = if ksize_x == 0 {
        auto_ksize(sigma_x)
    } else {
        ksize_x
    };
    let ksize_y = if ksize_y == 0 {
        auto_ksize(sigma_y)
    } else {
        ksize_y
    };
    if ksize_x == 1 && ksize_y == 1 {
        return image.clone();
    }
    separable_filter(
        image,
        &gaussian_kernel(ksize_x, sigma_x),
        &gaussian_kernel(ksize_y, sigma_y),
        border,
        border_value,
    )
}

/// Correlates every row of `image` with `row_kernel` and then every column with
/// `column_kernel` (OpenCV's `sepFilter2D` with the anchor at `len / 2`):
///
/// `out(x, y) = Σ_j column_kernel[j] · Σ_i row_kernel[i] · in(x + i − ⌊kx/2⌋, y + j − ⌊ky/2⌋)`
///
/// Pixels outside the image are read through `border`; `border_value` is the constant for
/// [`BorderMode::Constant`] (rounded and saturated for integer images). Channels are filtered
/// independently. Integer outputs are rounded and saturated. An empty kernel gives zeros.
pub fn separable_filter(
    image: &Image,
    row_kernel: &[f64],
    column_kernel: &[f64],
    border: BorderMode,
    border_value: f64,
) -> Image {
    if image.is_empty() {
        return image.clone();
    }
    let width = image.width();
    let height = image.height();
    let channels = image.channels().count();
    if row_kernel.is_empty() || column_kernel.is_empty() {
        let zeros = match image.data() {
            PixelData::U8(v) => PixelData::U8(vec![0; v.len()]),
            PixelData::U16(v) => PixelData::U16(vec![0; v.len()]),
            PixelData::F32(v) => PixelData::F32(vec![0.0; v.len()]),
        };
        return same_shape(image, zeros);
    }
    let kx = row_kernel.len();
    let ky = column_kernel.len();
    let geometry = Geometry {
        width,
        channels,
        columns: BorderTable::new(width, kx / 2, kx - 1 - kx / 2, border),
        rows: BorderTable::new(height, ky / 2, ky - 1 - ky / 2, border),
    };
    let data = match image.data() {
        PixelData::U8(src) => {
            let constant = u8::from_f64(border_value);
            let dst = match FixedU8::new(row_kernel, column_kernel, channels) {
                Some(fixed) => fixed_u8_bands(&fixed, src, &geometry, constant),
                None => float_bands(row_kernel, column_kernel, src, &geometry, constant),
            };
            PixelData::U8(dst)
        }
        PixelData::U16(src) => PixelData::U16(float_bands(
            row_kernel,
            column_kernel,
            src,
            &geometry,
            u16::from_f64(border_value),
        )),
        PixelData::F32(src) => PixelData::F32(float_bands(
            row_kernel,
            column_kernel,
            src,
            &geometry,
            f32::from_f64(border_value),
        )),
    };
    same_shape(image, data)
}

/// An image of `image`'s size and channels holding `data` (which has the same sample count).
fn same_shape(image: &Image, data: PixelData) -> Image {
    Image::new(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

/// 16-bit fixed-point weights for the u8 path, summing to exactly 2¹⁶, or `None` when the kernel
/// is not a smoothing kernel the path handles (odd length 3..=[`MAX_FIXED_POINT_TAPS`],
/// symmetric, non-negative, summing to 1, every weight below 1).
///
/// Rounding errors are diffused from both ends towards the centre tap, which takes the
/// remainder (the scheme of OpenCV's `getGaussianKernelFixedPoint_ED`), so the weights stay
/// symmetric and sum exactly to one.
fn fixed_point_weights(kernel: &[f64]) -> Option<Vec<u16>> {
    let n = kernel.len();
    if n.is_multiple_of(2) || !(3..=MAX_FIXED_POINT_TAPS).contains(&n) {
        return None;
    }
    let symmetric = kernel.iter().eq(kernel.iter().rev());
    let non_negative = kernel.iter().all(|&w| w >= 0.0);
    let sum: f64 = kernel.iter().sum();
    if !symmetric || !non_negative || (sum - 1.0).abs() > 1e-9 {
        return None;
    }
    let one = f64::from(FIXED_ONE);
    let mut weights = vec![0u16; n];
    let mut error = 0.0;
    let mut outer_sum = 0u32;
    for i in 0..n / 2 {
        let exact = kernel[i] * one + error;
        let rounded = exact.round_ties_even().max(0.0);
        error = exact - rounded;
        let w = u16::try_from(rounded as u32).ok()?;
        weights[i] = w;
        weights[n - 1 - i] = w;
        outer_sum += 2 * u32::from(w);
    }
    weights[n / 2] = u16::try_from(FIXED_ONE.checked_sub(outer_sum)?).ok()?;
    Some(weights)
}

/// Image geometry and border tables shared by the bands.
struct Geometry {
    width: usize,
    channels: usize,
    /// Border mapping along a row, reach `⌊kx/2⌋` before and the rest after.
    columns: BorderTable,
    /// Border mapping along a column.
    rows: BorderTable,
}

/// A sample type: conversion to and from the f32 accumulators.
pub(crate) trait Sample: Copy + Default + Send + Sync + 'static {
    fn to_f32(self) -> f32;
    /// Nearest value, ties to even, saturated (NaN gives 0 for integer types).
    fn from_f32(x: f32) -> Self;
    /// The border constant: nearest value, saturated.
    fn from_f64(x: f64) -> Self;
}

/// Adding and subtracting 1.5·2²³ rounds an f32 to an integer, ties to even, for |x| < 2²²;
/// beyond that the value saturates in the integer conversion anyway. Unlike `round_ties_even`
/// this vectorizes with SSE2.
fn round_small(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC) - MAGIC
}

impl Sample for u8 {
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
    fn from_f32(x: f32) -> Self {
        round_small(x) as u8
    }
    fn from_f64(x: f64) -> Self {
        x.round_ties_even() as u8
    }
}

impl Sample for u16 {
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
    fn from_f32(x: f32) -> Self {
        round_small(x) as u16
    }
    fn from_f64(x: f64) -> Self {
        x.round_ties_even() as u16
    }
}

impl Sample for f32 {
    fn to_f32(self) -> f32 {
        self
    }
    fn from_f32(x: f32) -> Self {
        x
    }
    fn from_f64(x: f64) -> Self {
        x as f32
    }
}

/// The floating-point separable filter (any sample type, f32 arithmetic), vertical pass first
/// as [`fixed_u8_bands`]: each output row is the column pass over the `ksize_y` source rows it
/// reads, straight from the image, into one f32 row padded through the column border table,
/// then the row pass of that row into the output. The temporary row stays in L1 cache and every
/// source row is read from cache by the `ksize_y` output rows that need it.
fn float_bands<T: Sample>(
    row_kernel: &[f64],
    column_kernel: &[f64],
    src: &[T],
    geometry: &Geometry,
    constant: T,
) -> Vec<T> {
    let channels = geometry.channels;
    let row_weights: Vec<f32> = row_kernel.iter().map(|&w| w as f32).collect();
    let column_weights: Vec<f32> = column_kernel.iter().map(|&w| w as f32).collect();
    let row_offsets: Vec<usize> = (0..row_kernel.len()).map(|i| i * channels).collect();
    // Outside the columns every extended sample is the constant, so the column pass there gives
    // the constant times the column weights, summed in the column pass's order.
    let c = constant.to_f32();
    let wide_constant = column_weights.iter().fold(0.0f32, |acc, &w| acc + w * c);
    column_first_bands(
        src,
        geometry,
        constant,
        wide_constant,
        |taps, inside| float_column(taps, &column_weights, inside),
        |padded, line| float_row::<T>(padded, &row_offsets, &row_weights, line),
    )
}

/// The band loop shared by both separable paths: each output row is `column` over the
/// `ksize_y` source rows it reads (straight from the image; rows outside it are the constant)
/// into the inside of one row of `W`, padded in place through the column border table (with
/// `wide_constant` outside), then `row` of that padded row into the output row. Bands of
/// output rows run in parallel; each output row depends only on its source rows.
fn column_first_bands<T: Sample, W: Copy + Send + Sync>(
    src: &[T],
    geometry: &Geometry,
    constant: T,
    wide_constant: W,
    column: impl Fn(&[&[T]], &mut [W]) + Sync,
    row: impl Fn(&[W], &mut [T]) + Sync,
) -> Vec<T> {
    // Zeros come from the allocator without a memset; every sample is overwritten.
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
    let Geometry {
        width,
        channels,
        columns,
        rows,
    } = geometry;
    let (width, channels) = (*width, *channels);
    let n = width * channels;
    if n == 0 || src.is_empty() {
        return dst;
    }
    let taps_y = rows.before() + 1 + rows.after();
    let band_rows = BAND_ROWS.max(4 * taps_y);
    let before_x = columns.before();
    let padded_len = columns.padded_len() * channels;
    let constant_row = vec![constant; n];
    dst.par_chunks_mut(band_rows * n)
        .enumerate()
        .for_each(|(band, out)| {
            let y0 = band * band_rows;
            let mut padded = vec![wide_constant; padded_len];
            let mut taps: Vec<&[T]> = vec![&[]; taps_y];
            for (i, line) in out.chunks_exact_mut(n).enumerate() {
                // Output row y reads extended rows y .. y + taps_y − 1.
                for (j, tap) in taps.iter_mut().enumerate() {
                    *tap = rows
                        .source(y0 + i + j)
                        .and_then(|r| src.get(r * n..(r + 1) * n))
                        .unwrap_or(&constant_row);
                }
                let Some(inside) = padded.get_mut(before_x * channels..before_x * channels + n)
                else {
                    return;
                };
                column(&taps, inside);
                pad_in_place(columns, channels, wide_constant, &mut padded);
                row(&padded, line);
            }
        });
    dst
}

/// The column pass of [`float_bands`]: `out[i] = Σ_j weights[j] · rows[j][i]` in f32, taps in
/// order of `j`, compiled for the CPU's vector extensions (no fused multiply-add, so the
/// results do not depend on the path).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn float_column<T: Sample>(rows: &[&[T]], weights: &[f32], out: &mut [f32]) {
    match weights.len() {
        3 => float_column_unrolled::<T, 3>(rows, weights, out),
        5 => float_column_unrolled::<T, 5>(rows, weights, out),
        7 => float_column_unrolled::<T, 7>(rows, weights, out),
        9 => float_column_unrolled::<T, 9>(rows, weights, out),
        11 => float_column_unrolled::<T, 11>(rows, weights, out),
        13 => float_column_unrolled::<T, 13>(rows, weights, out),
        15 => float_column_unrolled::<T, 15>(rows, weights, out),
        _ => {
            const BLOCK: usize = 64;
            for (block, out) in out.chunks_mut(BLOCK).enumerate() {
                let start = block * BLOCK;
                let mut acc = [0.0f32; BLOCK];
                let acc = &mut acc[..out.len()];
                for (row, &w) in rows.iter().zip(weights) {
                    if let Some(s) = row.get(start..start + acc.len()) {
                        for (a, &x) in acc.iter_mut().zip(s) {
                            *a += w * x.to_f32();
                        }
                    }
                }
                out.copy_from_slice(acc);
            }
        }
    }
}

#[inline(always)]
fn float_column_unrolled<T: Sample, const K: usize>(
    rows: &[&[T]],
    weights: &[f32],
    out: &mut [f32],
) {
    let Ok(weights) = <[f32; K]>::try_from(weights) else {
        return;
    };
    let mut taps: [&[T]; K] = [&[]; K];
    for (tap, row) in taps.iter_mut().zip(rows) {
        *tap = row;
    }
    // Looping to the shortest length lets LLVM drop every bounds check.
    let n = taps.iter().fold(out.len(), |n, tap| n.min(tap.len()));
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let mut acc = 0.0f32;
        for k in 0..K {
            acc += weights[k] * taps[k][i].to_f32();
        }
        *o = acc;
    }
}

/// The multiply-accumulate arithmetic of one pass.
trait Mac {
    /// Source samples.
    type In: Copy;
    /// Kernel weights.
    type Weight: Copy;
    /// Accumulator.
    type Acc: Copy;
    /// Results.
    type Out;
    /// The accumulator before the first tap.
    fn start(&self) -> Self::Acc;
    /// `acc + w · x`.
    fn mac(acc: Self::Acc, x: Self::In, w: Self::Weight) -> Self::Acc;
    /// The result from the accumulator.
    fn finish(&self, acc: Self::Acc) -> Self::Out;
}

/// `out[i] = finish(start + Σ_j weights[j] · src[offsets[j] + i])`, taps in order of `j`.
///
/// Common kernel lengths get a version with the taps unrolled and the weights in registers;
/// the others accumulate blocks of outputs in a small array. Both give the same results.
#[inline(always)]
fn weighted_sum<M: Mac>(
    mac: &M,
    src: &[M::In],
    offsets: &[usize],
    weights: &[M::Weight],
    out: &mut [M::Out],
) {
    match weights.len() {
        3 => unrolled::<M, 3>(mac, src, offsets, weights, out),
        5 => unrolled::<M, 5>(mac, src, offsets, weights, out),
        7 => unrolled::<M, 7>(mac, src, offsets, weights, out),
        9 => unrolled::<M, 9>(mac, src, offsets, weights, out),
        11 => unrolled::<M, 11>(mac, src, offsets, weights, out),
        13 => unrolled::<M, 13>(mac, src, offsets, weights, out),
        15 => unrolled::<M, 15>(mac, src, offsets, weights, out),
        _ => blocked(mac, src, offsets, weights, out),
    }
}

#[inline(always)]
fn unrolled<M: Mac, const K: usize>(
    mac: &M,
    src: &[M::In],
    offsets: &[usize],
    weights: &[M::Weight],
    out: &mut [M::Out],
) {
    let Ok(weights) = <[M::Weight; K]>::try_from(weights) else {
        return;
    };
    let n = out.len();
    let mut taps: [&[M::In]; K] = [&[]; K];
    for (tap, &offset) in taps.iter_mut().zip(offsets) {
        *tap = src.get(offset..offset + n).unwrap_or(&[]);
    }
    // Looping to the shortest length lets LLVM drop every bounds check.
    let n = taps.iter().fold(n, |n, tap| n.min(tap.len()));
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let mut acc = mac.start();
        for k in 0..K {
            acc = M::mac(acc, taps[k][i], weights[k]);
        }
        *o = mac.finish(acc);
    }
}

#[inline(always)]
fn blocked<M: Mac>(
    mac: &M,
    src: &[M::In],
    offsets: &[usize],
    weights: &[M::Weight],
    out: &mut [M::Out],
) {
    const BLOCK: usize = 64;
    for (block, out) in out.chunks_mut(BLOCK).enumerate() {
        let start = block * BLOCK;
        let mut acc = [mac.start(); BLOCK];
        let acc = &mut acc[..out.len()];
        for (&offset, &w) in offsets.iter().zip(weights) {
            let from = offset + start;
            if let Some(s) = src.get(from..from + acc.len()) {
                for (a, &x) in acc.iter_mut().zip(s) {
                    *a = M::mac(*a, x, w);
                }
            }
        }
        for (o, &a) in out.iter_mut().zip(acc.iter()) {
            *o = mac.finish(a);
        }
    }
}

/// f32 multiply-add, converted to `O` at the end.
struct FloatMac<O>(PhantomData<fn() -> O>);

impl<O: Sample> Mac for FloatMac<O> {
    type In = f32;
    type Weight = f32;
    type Acc = f32;
    type Out = O;
    fn start(&self) -> f32 {
        0.0
    }
    #[inline(always)]
    fn mac(acc: f32, x: f32, w: f32) -> f32 {
        acc + w * x
    }
    #[inline(always)]
    fn finish(&self, acc: f32) -> O {
        O::from_f32(acc)
    }
}

/// One row of an f32 pass ([`weighted_sum`] with [`FloatMac`]), compiled for the CPU's vector
/// extensions; the arithmetic (no fused multiply-add) and so the results do not change.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn float_row<O: Sample>(src: &[f32], offsets: &[usize], weights: &[f32], out: &mut [O]) {
    let mac = FloatMac::<O>(PhantomData);
    weighted_sum(&mac, src, offsets, weights, out);
}

/// The row pass of the u8 fixed-point filter ([`symmetric_sum`]) with the final rounding to u8,
/// compiled for the CPU's vector extensions (integer arithmetic: identical results).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn fixed_row_u8(src: &[u16], offsets: &[usize], kernel: &SymmetricQ16, bias: u16, out: &mut [u8]) {
    symmetric_sum(src, offsets, kernel, bias, out, |a| (a >> 8) as u8);
}

/// u8 fixed point: 16-bit weights, column-pass results with 8 fractional bits in u16.
///
/// Kernels are symmetric, so each pair of taps at equal distance from the centre is averaged
/// first (`pavgw`) and multiplied once by twice their weight. In the column pass (first) that
/// is exact (the samples are multiples of 256, so their sum is even); in the row pass the
/// average rounds up by at most ½ unit. Each product truncates once; the bias, half a unit per
/// product, centres the error.
struct FixedU8 {
    row: SymmetricQ16,
    column: SymmetricQ16,
    row_offsets: Vec<usize>,
    /// The column pass's bias (it runs first).
    column_bias_first: u16,
    /// The row pass's bias (it runs second): includes ½ for rounding the final shift by 8.
    row_bias_second: u16,
}

/// A symmetric kernel of `2·pairs.len() + 1` taps in 16-bit fixed point.
struct SymmetricQ16 {
    /// `2·w_j` for the outer taps `j < len/2`, outermost first.
    pairs: Vec<u16>,
    /// The centre weight.
    centre: u16,
}

impl SymmetricQ16 {
    /// From a smoothing kernel ([`fixed_point_weights`]); `None` when it does not qualify or an
    /// outer weight is ½ or more (twice it would not fit in 16 bits).
    fn new(kernel: &[f64]) -> Option<SymmetricQ16> {
        let weights = fixed_point_weights(kernel)?;
        let half = weights.len() / 2;
        let pairs = weights[..half]
            .iter()
            .map(|&w| w.checked_mul(2))
            .collect::<Option<Vec<u16>>>()?;
        Some(SymmetricQ16 {
            pairs,
            centre: weights[half],
        })
    }

    /// Bias compensating the truncation of `pairs + 1` products: half a unit each.
    fn bias(&self) -> u16 {
        u16::try_from(self.pairs.len().div_ceil(2)).unwrap_or(u16::MAX)
    }
}

impl FixedU8 {
    fn new(row: &[f64], column: &[f64], channels: usize) -> Option<FixedU8> {
        let row = SymmetricQ16::new(row)?;
        let column = SymmetricQ16::new(column)?;
        Some(FixedU8 {
            row_offsets: (0..2 * row.pairs.len() + 1).map(|i| i * channels).collect(),
            column_bias_first: column.bias(),
            row_bias_second: row.bias().saturating_add(128),
            row,
            column,
        })
    }
}

/// `⌊a · b / 2¹⁶⌋`, which LLVM lowers to `pmulhuw`.
#[inline(always)]
fn mul_high(a: u16, b: u16) -> u16 {
    ((u32::from(a) * u32::from(b)) >> 16) as u16
}

/// `⌈(a + b) / 2⌉` in 16-bit operations only. (The form through u32 lowers to `pavgw`, but its
/// result is then a truncated u32, and LLVM multiplies that in 32-bit lanes instead of with
/// `pmulhuw`.)
#[inline(always)]
fn average(a: u16, b: u16) -> u16 {
    (a | b) - ((a ^ b) >> 1)
}
/// `out[i] = finish(bias + ⌊src[offsets[h] + i] · w_c / 2¹⁶⌋ +
/// Σ_j ⌊avg(src[offsets[j] + i], src[offsets[2h − j] + i]) · 2w_j / 2¹⁶⌋)` for a kernel of
/// `2h + 1` taps. Sums stay below 2¹⁶ (module docs), so the wrapping adds are exact.
#[inline(always)]
fn symmetric_sum<O>(
    src: &[u16],
    offsets: &[usize],
    kernel: &SymmetricQ16,
    bias: u16,
    out: &mut [O],
    finish: impl Fn(u16) -> O,
) {
    let f = &finish;
    match kernel.pairs.len() {
        1 => symmetric_unrolled::<O, 1>(src, offsets, kernel, bias, out, f),
        2 => symmetric_unrolled::<O, 2>(src, offsets, kernel, bias, out, f),
        3 => symmetric_unrolled::<O, 3>(src, offsets, kernel, bias, out, f),
        4 => symmetric_unrolled::<O, 4>(src, offsets, kernel, bias, out, f),
        5 => symmetric_unrolled::<O, 5>(src, offsets, kernel, bias, out, f),
        6 => symmetric_unrolled::<O, 6>(src, offsets, kernel, bias, out, f),
        7 => symmetric_unrolled::<O, 7>(src, offsets, kernel, bias, out, f),
        _ => symmetric_blocked(src, offsets, kernel, bias, out, f),
    }
}

#[inline(always)]
fn symmetric_unrolled<O, const H: usize>(
    src: &[u16],
    offsets: &[usize],
    kernel: &SymmetricQ16,
    bias: u16,
    out: &mut [O],
    finish: &impl Fn(u16) -> O,
) {
    let Ok(pairs) = <[u16; H]>::try_from(kernel.pairs.as_slice()) else {
        return;
    };
    let n = out.len();
    let tap = |k: usize| {
        offsets
            .get(k)
            .and_then(|&offset| src.get(offset..offset + n))
            .unwrap_or(&[])
    };
    let left: [&[u16]; H] = std::array::from_fn(tap);
    let right: [&[u16]; H] = std::array::from_fn(|j| tap(2 * H - j));
    let centre = tap(H);
    // Looping to the shortest length lets LLVM drop every bounds check.
    let n = left
        .iter()
        .chain(&right)
        .fold(n.min(centre.len()), |n, tap| n.min(tap.len()));
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let mut acc = bias.wrapping_add(mul_high(centre[i], kernel.centre));
        for j in 0..H {
            acc = acc.wrapping_add(mul_high(average(left[j][i], right[j][i]), pairs[j]));
        }
        *o = finish(acc);
    }
}

#[inline(always)]
fn symmetric_blocked<O>(
    src: &[u16],
    offsets: &[usize],
    kernel: &SymmetricQ16,
    bias: u16,
    out: &mut [O],
    finish: &impl Fn(u16) -> O,
) {
    const BLOCK: usize = 64;
    let taps = 2 * kernel.pairs.len() + 1;
    let h = kernel.pairs.len();
    let tap = |k: usize, from: usize, len: usize| {
        offsets
            .get(k)
            .and_then(|&offset| src.get(offset + from..offset + from + len))
    };
    for (block, out) in out.chunks_mut(BLOCK).enumerate() {
        let start = block * BLOCK;
        let len = out.len();
        let mut acc = [bias; BLOCK];
        let acc = &mut acc[..len];
        if let Some(c) = tap(h, start, len) {
            for (a, &x) in acc.iter_mut().zip(c) {
                *a = a.wrapping_add(mul_high(x, kernel.centre));
            }
        }
        for (j, &w) in kernel.pairs.iter().enumerate() {
            if let (Some(l), Some(r)) = (tap(j, start, len), tap(taps - 1 - j, start, len)) {
                for ((a, &x), &y) in acc.iter_mut().zip(l).zip(r) {
                    *a = a.wrapping_add(mul_high(average(x, y), w));
                }
            }
        }
        for (o, &a) in out.iter_mut().zip(acc.iter()) {
            *o = finish(a);
        }
    }
}

/// The u8 fixed-point filter, vertical pass first: each output row is the column pass over the
/// `ksize_y` source rows it reads, straight from the image (no padded copy of the source), into
/// one u16 row padded through the column border table, then the row pass of that row into the
/// output. Both temporaries stay in L1 cache and every source row is read from cache by the
/// `ksize_y` output rows that need it.
fn fixed_u8_bands(fixed: &FixedU8, src: &[u8], geometry: &Geometry, constant: u8) -> Vec<u8> {
    column_first_bands(
        src,
        geometry,
        constant,
        u16::from(constant) << 8,
        |taps, inside| column_pass_u8(taps, &fixed.column, fixed.column_bias_first, inside),
        |padded, line| {
            row_pass_u8(
                padded,
                &fixed.row_offsets,
                &fixed.row,
                fixed.row_bias_second,
                line,
            )
        },
    )
}

/// The column pass of [`fixed_u8_bands`]: AVX2 intrinsics for whole vectors where the CPU has
/// them (bit-identical, see `avx2`), the portable kernel for the rest.
fn column_pass_u8(rows: &[&[u8]], kernel: &SymmetricQ16, bias: u16, out: &mut [u16]) {
    #[cfg(target_arch = "x86_64")]
    let done = super::avx2::column_u8(rows, &kernel.pairs, kernel.centre, bias, out).unwrap_or(0);
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    if let Some(rest) = out.get_mut(done..)
        && !rest.is_empty()
    {
        fixed_column_u8(rows, done, kernel, bias, 256, rest);
    }
}

/// The row pass of [`fixed_u8_bands`], AVX2 where available as [`column_pass_u8`].
fn row_pass_u8(
    padded: &[u16],
    offsets: &[usize],
    kernel: &SymmetricQ16,
    bias: u16,
    out: &mut [u8],
) {
    #[cfg(target_arch = "x86_64")]
    let done = super::avx2::row_to_u8(padded, offsets, &kernel.pairs, kernel.centre, bias, out)
        .unwrap_or(0);
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    if let (Some(src), Some(rest)) = (padded.get(done..), out.get_mut(done..))
        && !rest.is_empty()
    {
        fixed_row_u8(src, offsets, kernel, bias, rest);
    }
}

/// Fills the border positions of an extended row whose inside is already written.
fn pad_in_place<T: Copy>(columns: &BorderTable, channels: usize, constant: T, padded: &mut [T]) {
    let before = columns.before();
    let inside_end = before + columns.len();
    let extended = padded.len() / channels;
    for k in (0..before).chain(inside_end..extended) {
        let dst = k * channels;
        match columns.source(k) {
            Some(s) => {
                let from = (before + s) * channels;
                padded.copy_within(from..from + channels, dst);
            }
            None => {
                if let Some(d) = padded.get_mut(dst..dst + channels) {
                    d.fill(constant);
                }
            }
        }
    }
}

/// The column pass of the u8 fixed-point filter over `rows` (the `2h + 1` source rows, top
/// first), from sample `start` of each row on, straight from u8: each sample is taken as
/// `256·v` (see [`FixedU8`]).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn fixed_column_u8(
    rows: &[&[u8]],
    start: usize,
    kernel: &SymmetricQ16,
    bias: u16,
    unit: u16,
    out: &mut [u16],
) {
    let s = Scale(unit);
    match kernel.pairs.len() {
        1 => column_u8_unrolled::<1>(rows, start, kernel, bias, s, out),
        2 => column_u8_unrolled::<2>(rows, start, kernel, bias, s, out),
        3 => column_u8_unrolled::<3>(rows, start, kernel, bias, s, out),
        4 => column_u8_unrolled::<4>(rows, start, kernel, bias, s, out),
        5 => column_u8_unrolled::<5>(rows, start, kernel, bias, s, out),
        6 => column_u8_unrolled::<6>(rows, start, kernel, bias, s, out),
        7 => column_u8_unrolled::<7>(rows, start, kernel, bias, s, out),
        _ => column_u8_blocked(rows, start, kernel, bias, s, out),
    }
}

/// Widens u8 samples to `256·v` by multiplying with `unit` (256), a run-time value: with a
/// constant shift LLVM folds `256·v · w / 2¹⁶` into `v · w / 2⁸`, which needs 32-bit lanes.
#[derive(Clone, Copy)]
struct Scale(u16);

impl Scale {
    /// `256·v`.
    #[inline(always)]
    fn one(self, v: u8) -> u16 {
        u16::from(v).wrapping_mul(self.0)
    }
    /// `⌈(256·a + 256·b) / 2⌉ = 128·(a + b)`, exactly.
    #[inline(always)]
    fn pair(self, a: u8, b: u8) -> u16 {
        (u16::from(a) + u16::from(b)).wrapping_mul(self.0 >> 1)
    }
}

#[inline(always)]
fn column_u8_unrolled<const H: usize>(
    rows: &[&[u8]],
    start: usize,
    kernel: &SymmetricQ16,
    bias: u16,
    scale: Scale,
    out: &mut [u16],
) {
    let Ok(pairs) = <[u16; H]>::try_from(kernel.pairs.as_slice()) else {
        return;
    };
    let n = out.len();
    let tap = |k: usize| {
        rows.get(k)
            .and_then(|r| r.get(start..start + n))
            .unwrap_or(&[])
    };
    let left: [&[u8]; H] = std::array::from_fn(tap);
    let right: [&[u8]; H] = std::array::from_fn(|j| tap(2 * H - j));
    let centre = tap(H);
    let n = left
        .iter()
        .chain(&right)
        .fold(n.min(centre.len()), |n, tap| n.min(tap.len()));
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let mut acc = bias.wrapping_add(mul_high(scale.one(centre[i]), kernel.centre));
        for j in 0..H {
            let pair = scale.pair(left[j][i], right[j][i]);
            acc = acc.wrapping_add(mul_high(pair, pairs[j]));
        }
        *o = acc;
    }
}

#[inline(always)]
fn column_u8_blocked(
    rows: &[&[u8]],
    start: usize,
    kernel: &SymmetricQ16,
    bias: u16,
    scale: Scale,
    out: &mut [u16],
) {
    const BLOCK: usize = 64;
    let taps = 2 * kernel.pairs.len() + 1;
    let h = kernel.pairs.len();
    let tap = |k: usize, from: usize, len: usize| {
        rows.get(k)
            .and_then(|r| r.get(start + from..start + from + len))
    };
    for (block, out) in out.chunks_mut(BLOCK).enumerate() {
        let start = block * BLOCK;
        let len = out.len();
        let mut acc = [bias; BLOCK];
        let acc = &mut acc[..len];
        if let Some(c) = tap(h, start, len) {
            for (a, &x) in acc.iter_mut().zip(c) {
                *a = a.wrapping_add(mul_high(scale.one(x), kernel.centre));
            }
        }
        for (j, &w) in kernel.pairs.iter().enumerate() {
            if let (Some(l), Some(r)) = (tap(j, start, len), tap(taps - 1 - j, start, len)) {
                for ((a, &x), &y) in acc.iter_mut().zip(l).zip(r) {
                    *a = a.wrapping_add(mul_high(scale.pair(x, y), w));
                }
            }
        }
        out.copy_from_slice(acc);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::map_index;
    use crate::filter::test_support::{MODES, random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    /// The AVX2 kernels and the portable ones agree bit for bit, for every kernel length the
    /// intrinsics take and row lengths around the vector width.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_kernels_equal_portable_ones() {
        for (case, ksize) in [3usize, 5, 7, 9, 11, 13, 15].into_iter().enumerate() {
            let sigma = 0.4 + 0.35 * case as f64;
            let Some(kernel) = SymmetricQ16::new(&gaussian_kernel(ksize, sigma)) else {
                panic!("ksize {ksize}: no fixed-point kernel");
            };
            for n in [1usize, 15, 16, 17, 31, 32, 33, 100] {
                let seed = (case * 1000 + n) as u64;
                let rows: Vec<Vec<u8>> = (0..ksize)
                    .map(|r| {
                        randoms(seed + r as u64, n)
                            .iter()
                            .map(|&x| (x * 256.0) as u8)
                            .collect()
                    })
                    .collect();
                let views: Vec<&[u8]> = rows.iter().map(Vec::as_slice).collect();
                let mut fast = vec![0u16; n];
                column_pass_u8(&views, &kernel, kernel.bias(), &mut fast);
                let mut portable = vec![0u16; n];
                fixed_column_u8(&views, 0, &kernel, kernel.bias(), 256, &mut portable);
                assert_eq!(fast, portable, "column ksize {ksize} n {n}");
                // Row pass inputs: column results (at most 255·256 + a few units).
                let padded: Vec<u16> = randoms(seed, n + ksize - 1)
                    .iter()
                    .map(|&x| (x * (255.0 * 256.0 + 4.0)) as u16)
                    .collect();
                let offsets: Vec<usize> = (0..ksize).collect();
                let bias = kernel.bias() + 128;
                let mut fast = vec![0u8; n];
                row_pass_u8(&padded, &offsets, &kernel, bias, &mut fast);
                let mut portable = vec![0u8; n];
                fixed_row_u8(&padded, &offsets, &kernel, bias, &mut portable);
                assert_eq!(fast, portable, "row ksize {ksize} n {n}");
            }
        }
    }

    fn to_f32(image: &Image) -> Image {
        let data: Vec<f32> = match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f32::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f32::from(x)).collect(),
            PixelData::F32(v) => v.clone(),
        };
        Image::from_f32(image.width(), image.height(), image.channels(), data).unwrap()
    }

    fn samples(image: &Image) -> Vec<f64> {
        match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    /// Direct 2-D correlation in f64 through `map_index`: the definition, no tricks.
    fn reference(
        image: &Image,
        kx: &[f64],
        ky: &[f64],
        border: BorderMode,
        value: f64,
    ) -> Vec<f64> {
        let (w, h, c) = (image.width(), image.height(), image.channels().count());
        let src = samples(image);
        let mut out = vec![0.0; src.len()];
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let mut acc = 0.0;
                    for (j, wy) in ky.iter().enumerate() {
                        let sy =
                            map_index(y as isize + j as isize - (ky.len() / 2) as isize, h, border);
                        for (i, wx) in kx.iter().enumerate() {
                            let sx = map_index(
                                x as isize + i as isize - (kx.len() / 2) as isize,
                                w,
                                border,
                            );
                            let v = match (sx, sy) {
                                (Some(sx), Some(sy)) => src[(sy * w + sx) * c + ch],
                                _ => value,
                            };
                            acc += wx * wy * v;
                        }
                    }
                    out[(y * w + x) * c + ch] = acc;
                }
            }
        }
        out
    }

    fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn kernels_sum_to_one_and_are_symmetric() {
        for ksize in [1, 2, 3, 5, 7, 9, 15, 31, 121] {
            for sigma in [0.0, 0.3, 1.5, 3.0, 40.0] {
                let k = gaussian_kernel(ksize, sigma);
                assert_eq!(k.len(), ksize);
                assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-12);
                assert!(k.iter().eq(k.iter().rev()), "ksize {ksize} sigma {sigma}");
                assert!(k.iter().all(|&w| w >= 0.0));
                // Peak in the middle, falling off outwards.
                let half = &k[..ksize.div_ceil(2)];
                assert!(half.windows(2).all(|p| p[0] <= p[1]));
            }
        }
    }

    #[test]
    fn kernels_match_opencv() {
        // cv2.getGaussianKernel(5, 1.5)
        let cv = [0.12007838, 0.23388076, 0.29208172, 0.23388076, 0.12007838];
        for (a, b) in gaussian_kernel(5, 1.5).iter().zip(cv) {
            assert!((a - b).abs() < 1e-8);
        }
        // The fixed small kernels for sigma ≤ 0.
        assert_eq!(gaussian_kernel(1, 0.0), [1.0]);
        assert_eq!(gaussian_kernel(3, 0.0), [0.25, 0.5, 0.25]);
        assert_eq!(
            gaussian_kernel(5, -1.0),
            [1.0, 4.0, 6.0, 4.0, 1.0].map(|w| w / 16.0)
        );
        assert_eq!(gaussian_kernel(7, 0.0)[3], 0.28125);
        assert_eq!(
            gaussian_kernel(9, 0.0)[..5],
            [4.0, 13.0, 30.0, 51.0, 60.0].map(|w| w / 256.0)
        );
        // From 11 taps on, sigma comes from the size; cv2.getGaussianKernel(11, 0) gives:
        let cv11 = [
            0.00881223, 0.02714358, 0.06511406, 0.12164907, 0.17699836, 0.20056541,
        ];
        for (a, b) in gaussian_kernel(11, 0.0).iter().zip(cv11) {
            assert!((a - b).abs() < 1e-8);
        }
    }

    #[test]
    fn size_and_sigma_rules() {
        assert_eq!(auto_ksize(1.5), 11); // round(10) | 1
        assert_eq!(auto_ksize(1.0), 7);
        assert_eq!(auto_ksize(0.5), 5);
        assert_eq!(auto_ksize(2.0), 13);
        assert_eq!(auto_ksize(0.1), 3); // round(1.6) = 2, | 1
        assert_eq!(auto_ksize(0.0), 1);
        assert!((sigma_for_ksize(3) - 0.8).abs() < 1e-12);
        assert!((sigma_for_ksize(5) - 1.1).abs() < 1e-12);
        assert!((sigma_for_ksize(9) - 1.7).abs() < 1e-12);
        assert!((sigma_for_ksize(21) - 3.5).abs() < 1e-12);
    }

    #[test]
    fn fixed_point_weights_sum_to_one_and_stay_symmetric() {
        for ksize in [3, 5, 11, 61, 127] {
            for sigma in [0.0, 1.5, 8.0, 30.0] {
                let k = gaussian_kernel(ksize, sigma);
                let w = fixed_point_weights(&k).unwrap();
                assert_eq!(w.iter().map(|&x| u32::from(x)).sum::<u32>(), 1 << 16);
                assert!(w.iter().eq(w.iter().rev()));
                for (q, exact) in w.iter().zip(&k) {
                    assert!((f64::from(*q) / 65536.0 - exact).abs() < 1.5 / 65536.0);
                }
            }
        }
        assert_eq!(fixed_point_weights(&gaussian_kernel(129, 30.0)), None);
        assert_eq!(fixed_point_weights(&[-1.0, 0.0, 1.0]), None);
        assert_eq!(fixed_point_weights(&[0.2, 0.5, 0.3]), None);
        assert_eq!(fixed_point_weights(&[1.0]), None);
    }

    #[test]
    fn constant_images_stay_constant() {
        let cases = [(5, 1.5), (3, 0.0), (0, 2.0), (31, 5.0), (0, 25.0)];
        for border in MODES.into_iter().filter(|&m| m != BorderMode::Constant) {
            for (ksize, sigma) in cases {
                for (w, h) in [(1, 1), (2, 3), (40, 7), (70, 150)] {
                    for &v in &[0u8, 1, 77, 254, 255] {
                        let img = Image::from_u8(w, h, Channels::Rgb, vec![v; w * h * 3]).unwrap();
                        let out = gaussian_blur(&img, sigma, sigma, ksize, ksize, border, 0.0);
                        assert!(
                            out.as_u8().unwrap().iter().all(|&x| x == v),
                            "{border:?} {ksize} {sigma} {v}"
                        );
                    }
                    for &v in &[0u16, 12345, 65535] {
                        let img = Image::from_u16(w, h, Channels::Gray, vec![v; w * h]).unwrap();
                        let out = gaussian_blur(&img, sigma, sigma, ksize, ksize, border, 0.0);
                        assert!(out.as_u16().unwrap().iter().all(|&x| x == v));
                    }
                    for &v in &[0.3f32, -2.5, 1e6] {
                        let img =
                            Image::from_f32(w, h, Channels::Rgba, vec![v; w * h * 4]).unwrap();
                        let out = gaussian_blur(&img, sigma, sigma, ksize, ksize, border, 0.0);
                        assert!(
                            out.as_f32()
                                .unwrap()
                                .iter()
                                .all(|&x| ((x - v) / v).abs() < 1e-5)
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn impulse_response_is_the_outer_product_of_the_kernels() {
        let (w, h) = (41, 37);
        let (cx, cy) = (20, 18);
        let mut data = vec![0.0f32; w * h];
        data[cy * w + cx] = 1.0;
        let img = Image::from_f32(w, h, Channels::Gray, data).unwrap();
        let (sx, sy) = (2.0, 1.2);
        let out = gaussian_blur(&img, sx, sy, 0, 0, BorderMode::Reflect101, 0.0);
        let kx = gaussian_kernel(auto_ksize(sx), sx);
        let ky = gaussian_kernel(auto_ksize(sy), sy);
        assert_eq!((kx.len(), ky.len()), (13, 9));
        let got = out.as_f32().unwrap();
        for y in 0..h {
            for x in 0..w {
                let i = (x + kx.len() / 2).checked_sub(cx).filter(|&i| i < kx.len());
                let j = (y + ky.len() / 2).checked_sub(cy).filter(|&j| j < ky.len());
                let expected = match (i, j) {
                    (Some(i), Some(j)) => kx[i] * ky[j],
                    _ => 0.0,
                };
                let g = f64::from(got[y * w + x]);
                assert!((g - expected).abs() < 1e-7, "({x}, {y}): {g} vs {expected}");
            }
        }
    }

    #[test]
    fn f32_blur_is_linear() {
        let (w, h) = (53, 29);
        let x: Vec<f32> = randoms(1, w * h * 3).iter().map(|&r| r as f32).collect();
        let y: Vec<f32> = randoms(2, w * h * 3).iter().map(|&r| r as f32).collect();
        let a = 2.5f32;
        let mixed: Vec<f32> = x.iter().zip(&y).map(|(&x, &y)| a * x + y).collect();
        let img = |d: Vec<f32>| Image::from_f32(w, h, Channels::Rgb, d).unwrap();
        for border in MODES {
            let blur = |i: Image| {
                gaussian_blur(&i, 1.7, 0.9, 0, 0, border, 0.0)
                    .as_f32()
                    .unwrap()
                    .to_vec()
            };
            let (bx, by, bm) = (
                blur(img(x.clone())),
                blur(img(y.clone())),
                blur(img(mixed.clone())),
            );
            for i in 0..bm.len() {
                assert!(
                    (bm[i] - (a * bx[i] + by[i])).abs() < 1e-5,
                    "{border:?} at {i}"
                );
            }
        }
    }

    #[test]
    fn u8_is_within_one_level_of_the_f32_path() {
        // (ksize, sigma); 151 taps takes the f32 path for u8 too.
        let cases = [
            (5, 1.5),
            (3, 0.0),
            (5, 0.0),
            (0, 2.0),
            (0, 0.6),
            (31, 5.0),
            (121, 20.0),
            (151, 25.0),
        ];
        for (k, (ksize, sigma)) in cases.into_iter().enumerate() {
            let img = random_u8(97, 61, Channels::Rgb, k as u64);
            let fixed = samples(&gaussian_blur(
                &img,
                sigma,
                sigma,
                ksize,
                ksize,
                BorderMode::Reflect101,
                0.0,
            ));
            let float = samples(&gaussian_blur(
                &to_f32(&img),
                sigma,
                sigma,
                ksize,
                ksize,
                BorderMode::Reflect101,
                0.0,
            ));
            let diff = max_abs_diff(&fixed, &float);
            let taps = if ksize == 0 { auto_ksize(sigma) } else { ksize } as f64;
            // Rounding plus the fixed-point bound of the module docs.
            let bound = 0.5 + (2.0 * taps + 2.0) / 512.0;
            assert!(
                diff <= bound.min(1.0),
                "ksize {ksize} sigma {sigma}: {diff}"
            );
        }
    }

    #[test]
    fn matches_direct_correlation_for_every_border_and_depth() {
        // Kernel longer than the image on one axis, shorter on the other.
        let img = random_u8(23, 4, Channels::Rgb, 9);
        let kx = gaussian_kernel(7, 1.3);
        let ky = gaussian_kernel(11, 2.5);
        for border in MODES {
            let value = if border == BorderMode::Constant {
                200.0
            } else {
                0.0
            };
            let expected = reference(&img, &kx, &ky, border, value);
            let got = samples(&separable_filter(&img, &kx, &ky, border, value));
            assert!(max_abs_diff(&got, &expected) <= 0.52, "u8 {border:?}");
            let got = samples(&separable_filter(&to_f32(&img), &kx, &ky, border, value));
            assert!(max_abs_diff(&got, &expected) < 1e-3, "f32 {border:?}");
            let wide: Vec<u16> = img
                .as_u8()
                .unwrap()
                .iter()
                .map(|&v| u16::from(v) * 257)
                .collect();
            let img16 = Image::from_u16(23, 4, Channels::Rgb, wide).unwrap();
            let expected16: Vec<f64> = reference(&img16, &kx, &ky, border, value * 257.0);
            let got = samples(&separable_filter(&img16, &kx, &ky, border, value * 257.0));
            assert!(max_abs_diff(&got, &expected16) <= 0.51, "u16 {border:?}");
        }
    }

    #[test]
    fn wide_images_match_the_definition_across_strips() {
        // Wide rows are filtered in several vertical strips; the seams must not show.
        let img = random_u8(1500, 3, Channels::Rgb, 4);
        let k = gaussian_kernel(15, 2.5);
        for border in [BorderMode::Reflect101, BorderMode::Constant] {
            let expected = reference(&img, &k, &k, border, 9.0);
            let got = samples(&separable_filter(&img, &k, &k, border, 9.0));
            assert!(max_abs_diff(&got, &expected) <= 0.5 + 32.0 / 512.0);
            let got = samples(&separable_filter(&to_f32(&img), &k, &k, border, 9.0));
            assert!(max_abs_diff(&got, &expected) < 1e-3);
        }
    }

    #[test]
    fn asymmetric_kernels_correlate() {
        // A derivative kernel takes the f32 path; correlation: out(x) = in(x + 1) − in(x − 1).
        let img = Image::from_f32(5, 1, Channels::Gray, vec![0.0, 1.0, 4.0, 9.0, 16.0]).unwrap();
        let out = separable_filter(&img, &[-1.0, 0.0, 1.0], &[1.0], BorderMode::Clamp, 0.0);
        assert_eq!(out.as_f32().unwrap(), [1.0, 4.0, 8.0, 12.0, 7.0]);
        // u8 saturates.
        let img = Image::from_u8(3, 1, Channels::Gray, vec![0, 100, 200]).unwrap();
        let out = separable_filter(&img, &[-1.0, 0.0, 1.0], &[1.0], BorderMode::Clamp, 0.0);
        assert_eq!(out.as_u8().unwrap(), [100, 200, 100]);
        let out = separable_filter(&img, &[1.0, 0.0, -1.0], &[1.0], BorderMode::Clamp, 0.0);
        assert_eq!(out.as_u8().unwrap(), [0, 0, 0]);
    }

    #[test]
    fn three_by_one_by_hand() {
        // Kernel [¼ ½ ¼] both ways; height 1, so every non-constant border makes the vertical
        // pass the identity.
        let expected = [
            (BorderMode::Reflect101, [50.0, 100.0, 150.0]), // 100 | 0 100 200 | 100
            (BorderMode::Reflect, [25.0, 100.0, 175.0]),    //   0 | 0 100 200 | 200
            (BorderMode::Clamp, [25.0, 100.0, 175.0]),      //   0 | 0 100 200 | 200
            (BorderMode::Wrap, [75.0, 100.0, 125.0]),       // 200 | 0 100 200 | 0
        ];
        for (border, values) in expected {
            let img = Image::from_u8(3, 1, Channels::Gray, vec![0, 100, 200]).unwrap();
            let out = gaussian_blur(&img, 0.0, 0.0, 3, 3, border, 0.0);
            assert_eq!(out.as_u8().unwrap(), values.map(|v| v as u8), "{border:?}");
            let out = gaussian_blur(&to_f32(&img), 0.0, 0.0, 3, 3, border, 0.0);
            assert_eq!(
                out.as_f32().unwrap(),
                values.map(|v| v as f32),
                "{border:?}"
            );
        }
        // Constant 40: horizontally 40 | 0 100 200 | 40 gives 35 100 135; the rows above and
        // below are all 40, so vertically ¼·40 + ½·h + ¼·40.
        let img = Image::from_f32(3, 1, Channels::Gray, vec![0.0, 100.0, 200.0]).unwrap();
        let out = gaussian_blur(&img, 0.0, 0.0, 3, 3, BorderMode::Constant, 40.0);
        assert_eq!(out.as_f32().unwrap(), [37.5, 70.0, 87.5]);
    }

    #[test]
    fn tiny_and_empty_images() {
        for border in MODES {
            let one = Image::from_u8(1, 1, Channels::Rgb, vec![10, 20, 30]).unwrap();
            let out = gaussian_blur(&one, 1.5, 1.5, 0, 0, border, 0.0);
            if border == BorderMode::Constant {
                // Only the centre tap of each kernel reads the pixel.
                let k = gaussian_kernel(11, 1.5)[5];
                let expected = [10.0, 20.0, 30.0].map(|v| (v * k * k).round() as u8);
                assert_eq!(out.as_u8().unwrap(), expected);
            } else {
                assert_eq!(out.as_u8().unwrap(), [10, 20, 30]);
            }
            for (w, h) in [(0, 0), (0, 7), (7, 0)] {
                let empty = Image::from_f32(w, h, Channels::Gray, vec![]).unwrap();
                let out = gaussian_blur(&empty, 2.0, 2.0, 0, 0, border, 0.0);
                assert_eq!(
                    (out.width(), out.height(), out.format()),
                    (w, h, empty.format())
                );
            }
        }
        let one = Image::from_u8(1, 1, Channels::Gray, vec![100]).unwrap();
        let out = gaussian_blur(&one, 0.0, 0.0, 3, 3, BorderMode::Constant, 0.0);
        assert_eq!(out.as_u8().unwrap(), [25]);
    }

    #[test]
    fn nan_spreads_without_panicking() {
        let mut data = vec![0.0f32; 81];
        data[4 * 9 + 4] = f32::NAN;
        let img = Image::from_f32(9, 9, Channels::Gray, data).unwrap();
        let out = gaussian_blur(&img, 0.0, 0.0, 3, 3, BorderMode::Reflect101, 0.0);
        for (i, v) in out.as_f32().unwrap().iter().enumerate() {
            let (x, y) = (i % 9, i / 9);
            let near = (3..=5).contains(&x) && (3..=5).contains(&y);
            assert_eq!(v.is_nan(), near, "({x}, {y})");
        }
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let rgb = random_u8(301, 257, Channels::Rgb, 5);
        let float = to_f32(&rgb);
        for (image, ksize, sigma) in [(&rgb, 5, 1.5), (&rgb, 0, 4.0), (&float, 0, 2.0)] {
            let blur = || {
                gaussian_blur(
                    image,
                    sigma,
                    sigma,
                    ksize,
                    ksize,
                    BorderMode::Reflect101,
                    0.0,
                )
            };
            assert_eq!(pool(1).install(blur), pool(3).install(blur));
        }
    }

    #[test]
    fn agrees_with_opencv() {
        // cv2.GaussianBlur(img, (5, 5), 1.5) (OpenCV 5.0, default border) on
        // img[y, x] = (x·37 + y·91 + x·y·13) mod 256, 10×6 gray u8.
        let (w, h) = (10, 6);
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91 + x * y * 13) % 256) as u8))
            .collect();
        let img = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        let cv: [u8; 60] = OPENCV_5X5;
        let out = gaussian_blur(&img, 1.5, 1.5, 5, 5, BorderMode::Reflect101, 0.0);
        for (i, (&a, &b)) in out.as_u8().unwrap().iter().zip(&cv).enumerate() {
            assert!(a.abs_diff(b) <= 1, "pixel {i}: {a} vs OpenCV {b}");
        }
    }

    #[rustfmt::skip]
    const OPENCV_5X5: [u8; 60] = [
        119, 126, 131, 138, 137, 135, 135, 134, 133, 131,
        118, 127, 133, 140, 140, 136, 134, 134, 134, 132,
        126, 132, 135, 141, 141, 138, 133, 134, 136, 136,
        129, 136, 139, 144, 141, 137, 132, 136, 141, 144,
        123, 129, 134, 140, 139, 137, 131, 134, 137, 139,
        116, 124, 133, 139, 137, 136, 130, 133, 134, 135,
    ];

    #[test]
    fn operator_params_are_checked() {
        let p = |f: fn(&mut GaussianParams)| {
            let mut p = GaussianParams::default();
            f(&mut p);
            Gaussian::new(p)
        };
        assert!(p(|_| ()).is_ok());
        let e = p(|p| p.ksize = 4).unwrap_err();
        assert!(e.contains("odd"), "{e}");
        let e = p(|p| p.sigma = 0.0).unwrap_err();
        assert!(e.contains("`sigma` = 0"), "{e}");
        let e = p(|p| p.sigma_y = Some(0.0)).unwrap_err();
        assert!(e.contains("`sigma_y` = 0"), "{e}");
        let e = p(|p| p.border_value = 3.0).unwrap_err();
        assert!(e.contains("applies only to border \"constant\""), "{e}");
        let e = p(|p| p.ksize = 4097).unwrap_err();
        assert!(e.contains("4095"), "{e}");
        assert!(p(|p| p.sigma = f64::NAN).is_err());
        assert!(
            p(|p| {
                p.border = BorderMode::Constant;
                p.border_value = 3.0;
            })
            .is_ok()
        );
        let g = p(|p| {
            p.sigma = 0.0;
            p.ksize = 5;
        })
        .unwrap();
        assert_eq!((g.ksize_x, g.ksize_y, g.sigma_x), (5, 5, 0.0));
        let g = p(|p| {
            p.sigma = 1.5;
            p.sigma_y = Some(0.5);
        })
        .unwrap();
        assert_eq!((g.ksize_x, g.ksize_y), (11, 5));
    }

    #[test]
    fn operator_runs() {
        let op = Gaussian::new(GaussianParams::default()).unwrap();
        let img = random_u8(20, 10, Channels::Rgb, 3);
        let specs = Gaussian::inputs();
        let values = [Some(Value::image(img.clone()))];
        let ctx = RunContext {
            node: "g".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(got)) = out.take("image") else {
            panic!("expected an image");
        };
        assert_eq!(
            *got,
            gaussian_blur(&img, 1.0, 1.0, 7, 7, BorderMode::Reflect101, 0.0)
        );
        let err = op.run(&ctx, &Inputs::new(&specs, &[None])).unwrap_err();
        assert!(err.to_string().contains("not connected"));
    }

    fn any_mode() -> impl Strategy<Value = BorderMode> {
        prop::sample::select(MODES.to_vec())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn output_stays_within_the_input_range(
            w in 1usize..14,
            h in 1usize..14,
            rgb in any::<bool>(),
            sigma in 0.1f64..5.0,
            ksize in prop::sample::select(vec![0usize, 1, 3, 5, 9, 15]),
            border in any_mode(),
            seed in any::<u64>(),
        ) {
            let channels = if rgb { Channels::Rgb } else { Channels::Gray };
            let img = random_u8(w, h, channels, seed);
            let s = samples(&img);
            let (lo, hi) = s.iter().fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
            // A constant border inside the range keeps the bound.
            let value = lo;
            let out = samples(&gaussian_blur(&img, sigma, sigma * 0.7, ksize, ksize, border, value));
            prop_assert!(out.iter().all(|&v| v >= lo && v <= hi));
            let out = samples(&gaussian_blur(&to_f32(&img), sigma, sigma * 0.7, ksize, ksize, border, value));
            let tol = 1e-4 * hi.max(1.0);
            prop_assert!(out.iter().all(|&v| v >= lo - tol && v <= hi + tol));
        }

        #[test]
        fn fast_path_matches_the_definition(
            w in 1usize..20,
            h in 1usize..20,
            sigma in 0.3f64..4.0,
            border in any_mode(),
            seed in any::<u64>(),
        ) {
            let img = random_u8(w, h, Channels::Gray, seed);
            let k = gaussian_kernel(auto_ksize(sigma), sigma);
            let expected = reference(&img, &k, &k, border, 17.0);
            let got = samples(&separable_filter(&img, &k, &k, border, 17.0));
            // Rounding plus the fixed-point bound of the module docs.
            let bound = 0.5 + (2.0 * k.len() as f64 + 2.0) / 512.0;
            prop_assert!(max_abs_diff(&got, &expected) <= bound);
        }
    }
}
