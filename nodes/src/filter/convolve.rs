//! `filter.convolve`: correlation or convolution of an image with any 2-D kernel.
//!
//! How it runs:
//! - The kernel is tested for rank 1 ([`separate`]): a kernel that is the outer product of a
//!   column and a row (within 10⁻¹² of its largest weight) runs as two 1-D passes on
//!   [`separable_filter`], O(kw + kh) per pixel instead of O(kw · kh).
//! - Other kernels run as a direct 2-D correlation ([`correlate_dense`]): bands of output rows in
//!   parallel (fixed size), each source row widened to f32 and padded once through a
//!   [`BorderTable`] into a ring of `kh` rows, and every non-zero tap added to an f32 row
//!   accumulator over contiguous slices (zero taps cost nothing). Only the rows and columns the
//!   stride keeps are produced.
//! - Integer outputs are rounded to nearest (ties to even) and saturated.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};
use super::gaussian::{Sample, separable_filter};
use super::sobel::to_f32;

/// Largest kernel side, in taps.
pub const MAX_KERNEL_SIDE: usize = 255;

/// Relative tolerance of the rank-1 test: every weight must match the outer product within
/// this fraction of the largest weight.
pub const SEPARABLE_TOLERANCE: f64 = 1e-12;

/// Output rows per parallel band of the dense path.
const BAND_ROWS: usize = 16;

param_enum! {
    /// Sample type of a filter's output.
    pub enum OutputDepth {
        /// The input's sample type; integer results are rounded and saturated (OpenCV's
        /// `ddepth = -1`).
        Same = "same",
        /// 32-bit float, unrounded (OpenCV's `CV_32F`).
        F32 = "f32",
    }
}

impl Default for OutputDepth {
    /// `same`.
    fn default() -> Self {
        OutputDepth::Same
    }
}

params! {
    /// Parameters of `filter.convolve`.
    pub struct ConvolveParams {
        /// The kernel, as rows of weights (all rows the same length, at most 255 × 255, finite).
        kernel: Vec<Vec<f64>> = vec![vec![1.0]],
        /// false: correlation, `Σ K[j][i] · I(x + i − ax, y + j − ay)` (as OpenCV's `filter2D`);
        /// true: convolution, the same with the kernel rotated by 180° (and the anchor with it).
        flip: bool = false,
        /// Anchor `[x, y]` in kernel taps, the tap that lies over the output pixel; `None` is the
        /// centre `[⌊kw/2⌋, ⌊kh/2⌋]` (OpenCV's `(-1, -1)`).
        anchor: Option<[i64; 2]> = None,
        /// Step `[sx, sy]` in px between output pixels: the output is `⌈w/sx⌉ × ⌈h/sy⌉` and its
        /// pixel (x, y) is the full-resolution result at (x·sx, y·sy). Default [1, 1].
        stride: [u32; 2] = [1, 1] => [min = 1, max = 65535, unit = "px"],
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units
        /// (rounded and saturated for integer images).
        border_value: f64 = 0.0,
        /// Value added to every result, in output units. Default 0.
        delta: f64 = 0.0,
        /// Output sample type: "same" as the input (rounded, saturated) or "f32".
        depth: OutputDepth = OutputDepth::Same,
    }
}

/// Options of [`convolve`], in the form the algorithm takes them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConvolveOptions {
    /// Anchor `[x, y]` inside the kernel (taps).
    pub anchor: [usize; 2],
    /// Output step `[sx, sy]`, each at least 1.
    pub stride: [usize; 2],
    /// Border mode.
    pub border: BorderMode,
    /// Constant read outside the image with [`BorderMode::Constant`].
    pub border_value: f64,
    /// Added to every result.
    pub delta: f64,
    /// Output sample type.
    pub depth: OutputDepth,
}

impl ConvolveOptions {
    /// Centred anchor, stride 1, border reflect_101, no delta, same depth.
    pub fn centred(kernel: &Kernel) -> ConvolveOptions {
        ConvolveOptions {
            anchor: [kernel.width / 2, kernel.height / 2],
            stride: [1, 1],
            border: BorderMode::Reflect101,
            border_value: 0.0,
            delta: 0.0,
            depth: OutputDepth::Same,
        }
    }
}

/// A dense 2-D kernel, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    /// Taps per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `width · height` weights, row by row.
    pub weights: Vec<f64>,
}

impl Kernel {
    /// From rows of equal length: at least one tap, at most [`MAX_KERNEL_SIDE`] per side, all
    /// finite.
    pub fn from_rows(rows: &[Vec<f64>]) -> Result<Kernel, String> {
        let height = rows.len();
        let width = rows.first().map_or(0, Vec::len);
        if width == 0 || height == 0 {
            return Err("`kernel` must have at least one row and one column".into());
        }
        if width > MAX_KERNEL_SIDE || height > MAX_KERNEL_SIDE {
            return Err(format!(
                "`kernel` is {width}×{height}; each side must be at most {MAX_KERNEL_SIDE}"
            ));
        }
        if let Some(j) = rows.iter().position(|r| r.len() != width) {
            return Err(format!(
                "`kernel` rows must have equal lengths: row 0 has {width}, row {j} has {}",
                rows[j].len()
            ));
        }
        let weights: Vec<f64> = rows.iter().flatten().copied().collect();
        if let Some(w) = weights.iter().find(|w| !w.is_finite()) {
            return Err(format!("`kernel` weights must be finite, got {w}"));
        }
        Ok(Kernel {
            width,
            height,
            weights,
        })
    }

    /// The weight at row `j`, column `i`.
    pub fn at(&self, j: usize, i: usize) -> f64 {
        self.weights[j * self.width + i]
    }

    /// The kernel rotated by 180°.
    pub fn flipped(&self) -> Kernel {
        let mut weights = self.weights.clone();
        weights.reverse();
        Kernel {
            weights,
            ..self.clone()
        }
    }
}

/// The kernel as `(column, row)` with `K[j][i] = column[j] · row[i]` when it has rank 1 (every
/// weight within [`SEPARABLE_TOLERANCE`] of the largest), else `None`. An all-zero kernel gives
/// zero vectors.
pub fn separate(kernel: &Kernel) -> Option<(Vec<f64>, Vec<f64>)> {
    let (w, h) = (kernel.width, kernel.height);
    let (pivot, largest) =
        kernel
            .weights
            .iter()
            .enumerate()
            .fold((0, 0.0f64), |(best, m), (k, &v)| {
                if v.abs() > m { (k, v.abs()) } else { (best, m) }
            });
    if largest == 0.0 {
        return Some((vec![0.0; h], vec![0.0; w]));
    }
    let (pj, pi) = (pivot / w, pivot % w);
    let row: Vec<f64> = (0..w).map(|i| kernel.at(pj, i)).collect();
    let p = kernel.at(pj, pi);
    let column: Vec<f64> = (0..h).map(|j| kernel.at(j, pi) / p).collect();
    let tolerance = SEPARABLE_TOLERANCE * largest;
    let matches = kernel
        .weights
        .chunks_exact(w)
        .zip(&column)
        .all(|(line, &c)| {
            line.iter()
                .zip(&row)
                .all(|(&k, &r)| (k - c * r).abs() <= tolerance)
        });
    if !matches {
        return None;
    }
    Some((column, row))
}

/// Linear filter (`filter.convolve`). See [`convolve`].
#[derive(Debug, Clone, PartialEq)]
pub struct Convolve {
    /// The kernel to correlate with (already rotated when `flip` was set).
    kernel: Kernel,
    options: ConvolveOptions,
}

impl Op for Convolve {
    type Params = ConvolveParams;
    const ID: &'static str = "filter.convolve";
    const SUMMARY: &'static str =
        "Correlates or convolves an image with any 2-D kernel, separably when it can.";
    const DOC: &'static str = r#"
Computes `out(x, y) = Σ_j Σ_i K[j][i] · I(x·sx + i − ax, y·sy + j − ay) + delta` for every
channel (correlation, like OpenCV's `filter2D`), or with `flip: true` the true convolution
(the kernel rotated by 180°, the anchor with it). The anchor defaults to the kernel centre.

Method: a kernel of rank 1 (the outer product of a column and a row, detected exactly up to
10⁻¹² relative) runs as two 1-D passes, a row pass and a column pass (as `sepFilter2D`); any
other kernel as a direct 2-D correlation over border-padded rows, skipping zero taps. Both
accumulate in f32 (a u8 image with a smoothing kernel — symmetric, non-negative, summing to 1
— on the separable path uses 16-bit fixed point, within half a gray level of exact). Integer
outputs are rounded to nearest and saturated. With a stride only the kept pixels are computed
on the dense path. Works on every pixel format, channels independent.

Differences from OpenCV: no DFT path for large kernels (OpenCV switches to it from 11×11), so
large dense kernels cost kw·kh multiply-adds per pixel; results agree with `filter2D` /
`sepFilter2D` within one gray level for u8. OpenCV has no stride.

Reference: OpenCV `cv::filter2D`, `cv::sepFilter2D`, `cv::BorderTypes`.

Example:
    "edges": (op: "filter.convolve", inputs: { "image": "gray.image" },
              params: (kernel: [[0, -1, 0], [-1, 4, -1], [0, -1, 0]], depth: "f32")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to filter, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The filtered image: ⌈w/sx⌉ × ⌈h/sy⌉, the input's channels, depth per `depth`.",
        )]
    }

    fn new(params: ConvolveParams) -> Result<Self, String> {
        let ConvolveParams {
            kernel,
            flip,
            anchor,
            stride,
            border,
            border_value,
            delta,
            depth,
        } = params;
        let kernel = Kernel::from_rows(&kernel)?;
        let anchor = match anchor {
            None => [kernel.width / 2, kernel.height / 2],
            Some([ax, ay]) => {
                let inside = |a: i64, len: usize| usize::try_from(a).ok().filter(|&a| a < len);
                match (inside(ax, kernel.width), inside(ay, kernel.height)) {
                    (Some(ax), Some(ay)) => [ax, ay],
                    _ => {
                        return Err(format!(
                            "`anchor` [{ax}, {ay}] must lie inside the {}×{} kernel",
                            kernel.width, kernel.height
                        ));
                    }
                }
            }
        };
        if stride.contains(&0) {
            return Err(format!("`stride` must be at least 1 px, got {stride:?}"));
        }
        if !delta.is_finite() {
            return Err(format!("`delta` must be finite, got {delta}"));
        }
        check_border_value(border, border_value)?;
        let (kernel, anchor) = if flip {
            (
                kernel.flipped(),
                [kernel.width - 1 - anchor[0], kernel.height - 1 - anchor[1]],
            )
        } else {
            (kernel, anchor)
        };
        Ok(Convolve {
            kernel,
            options: ConvolveOptions {
                anchor,
                stride: [stride[0] as usize, stride[1] as usize],
                border,
                border_value,
                delta,
                depth,
            },
        })
    }
}

impl Operator for Convolve {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let filtered = convolve(image, &self.kernel, &self.options);
        Ok(Outputs::new().with("image", Value::image(filtered)))
    }
}

/// Correlates `image` with `kernel` (see [`Convolve`]'s documentation for the formula), through
/// the separable path when the kernel has rank 1 and the dense path otherwise.
///
/// `options.anchor` must lie inside the kernel and each stride be at least 1 (out-of-range
/// values are clamped).
pub fn convolve(image: &Image, kernel: &Kernel, options: &ConvolveOptions) -> Image {
    match separate(kernel) {
        Some((column, row)) => correlate_separable(image, &row, &column, options),
        None => correlate_dense(image, kernel, options),
    }
}

/// The options with the anchor inside a `width × height` kernel and strides of at least 1.
fn sanitized(options: &ConvolveOptions, width: usize, height: usize) -> ConvolveOptions {
    ConvolveOptions {
        anchor: [
            options.anchor[0].min(width.saturating_sub(1)),
            options.anchor[1].min(height.saturating_sub(1)),
        ],
        stride: options.stride.map(|s| s.max(1)),
        ..*options
    }
}

/// `kernel` extended with zeros so that its centre `⌊len/2⌋` is the tap `anchor`.
fn centre_on(kernel: &[f64], anchor: usize) -> Vec<f64> {
    let len = kernel.len();
    let after = len - 1 - anchor;
    let (before_zeros, after_zeros) = if anchor >= after {
        // Keep an odd length so that ⌊len/2⌋ is the middle: `anchor` taps before it.
        (0, anchor - after)
    } else {
        (after - anchor, 0)
    };
    let mut out = vec![0.0; before_zeros];
    out.extend_from_slice(kernel);
    out.extend(std::iter::repeat_n(0.0, after_zeros));
    out
}

/// Output size for a stride: `⌈len / step⌉`.
fn strided(len: usize, step: usize) -> usize {
    len.div_ceil(step.max(1))
}

/// Separable correlation: every row with `row`, every column with `column`, then `options`.
/// [`separable_filter`] runs it directly where it can (stride 1, no delta, centred anchor, same
/// depth); otherwise on an f32 copy, followed by the stride, delta and output conversion.
pub fn correlate_separable(
    image: &Image,
    row: &[f64],
    column: &[f64],
    options: &ConvolveOptions,
) -> Image {
    let options = sanitized(options, row.len(), column.len());
    let row = centre_on(row, options.anchor[0]);
    let column = centre_on(column, options.anchor[1]);
    let same_depth = options.depth == OutputDepth::Same || image.as_f32().is_some();
    if options.stride == [1, 1] && options.delta == 0.0 && same_depth {
        return separable_filter(image, &row, &column, options.border, options.border_value);
    }
    // The constant in the input's units, as the direct path would read it.
    let constant = match image.data() {
        PixelData::U8(_) => f64::from(u8::from_f64(options.border_value)),
        PixelData::U16(_) => f64::from(u16::from_f64(options.border_value)),
        PixelData::F32(_) => options.border_value,
    };
    let float = to_f32(image);
    let full = separable_filter(&float, &row, &column, options.border, constant);
    let values = full.as_f32().unwrap_or(&[]);
    let (width, height, c) = (image.width(), image.height(), image.channels().count());
    let [sx, sy] = options.stride;
    let (ow, oh) = (strided(width, sx), strided(height, sy));
    let mut out = Vec::with_capacity(ow * oh * c);
    for y in (0..height).step_by(sy) {
        for x in (0..width).step_by(sx) {
            let at = (y * width + x) * c;
            if let Some(pixel) = values.get(at..at + c) {
                out.extend(pixel.iter().map(|&v| v + options.delta as f32));
            }
        }
    }
    finish(image, ow, oh, out, options.depth)
}

/// An f32 image of the given size holding `values`, converted to the output depth: the input's
/// sample type (rounded, saturated) or f32.
fn finish(
    image: &Image,
    width: usize,
    height: usize,
    values: Vec<f32>,
    depth: OutputDepth,
) -> Image {
    let channels = image.channels();
    let data = match (depth, image.data()) {
        (OutputDepth::Same, PixelData::U8(_)) => {
            PixelData::U8(values.iter().map(|&v| u8::from_f32(v)).collect())
        }
        (OutputDepth::Same, PixelData::U16(_)) => {
            PixelData::U16(values.iter().map(|&v| u16::from_f32(v)).collect())
        }
        _ => PixelData::F32(values),
    };
    Image::new(width, height, channels, data).unwrap_or_else(|_| image.clone())
}

/// A sample type of the dense path.
/// Direct 2-D correlation with any kernel (module docs), producing only the pixels the stride
/// keeps.
pub fn correlate_dense(image: &Image, kernel: &Kernel, options: &ConvolveOptions) -> Image {
    let options = sanitized(options, kernel.width, kernel.height);
    let values = match image.data() {
        PixelData::U8(src) => dense_bands(image, src, kernel, &options),
        PixelData::U16(src) => dense_bands(image, src, kernel, &options),
        PixelData::F32(src) => dense_bands(image, src, kernel, &options),
    };
    let [sx, sy] = options.stride;
    finish(
        image,
        strided(image.width(), sx),
        strided(image.height(), sy),
        values,
        options.depth,
    )
}

/// The dense correlation of `src` (`image`'s samples) as f32 values, `delta` included.
fn dense_bands<T: Sample>(
    image: &Image,
    src: &[T],
    kernel: &Kernel,
    options: &ConvolveOptions,
) -> Vec<f32> {
    let (width, height, c) = (image.width(), image.height(), image.channels().count());
    let [sx, sy] = options.stride;
    let (ow, oh) = (strided(width, sx), strided(height, sy));
    let (kw, kh) = (kernel.width, kernel.height);
    let [ax, ay] = options.anchor;
    let n = width * c;
    let on = ow * c;
    let mut dst = ocellus_engine::buffer::zeroed::<f32>(on * oh);
    if n == 0 || height == 0 || on == 0 {
        return dst;
    }
    let columns = BorderTable::new(width, ax, kw - 1 - ax, options.border);
    let rows = BorderTable::new(height, ay, kh - 1 - ay, options.border);
    let constant = T::from_f64(options.border_value).to_f32();
    let padded_len = (width + kw - 1) * c;
    // Non-zero taps, grouped by kernel row: (row, [(column offset in samples, weight)]).
    let taps: Vec<(usize, Vec<(usize, f32)>)> = (0..kh)
        .map(|j| {
            let row = (0..kw)
                .filter(|&i| kernel.at(j, i) != 0.0)
                .map(|i| (i * c, kernel.at(j, i) as f32))
                .collect::<Vec<_>>();
            (j, row)
        })
        .filter(|(_, row)| !row.is_empty())
        .collect();
    let delta = options.delta as f32;
    dst.par_chunks_mut(BAND_ROWS * on)
        .enumerate()
        .for_each(|(band, out)| {
            let mut ring = vec![constant; kh * padded_len];
            // Which extended row each ring slot holds.
            let mut held = vec![usize::MAX; kh];
            // Full-resolution sums of one output row (only every sx-th pixel is kept).
            let mut acc = vec![0.0f32; n];
            for (r, line) in out.chunks_exact_mut(on).enumerate() {
                let y = (band * BAND_ROWS + r) * sy;
                // Output row y reads extended rows y .. y + kh − 1 (extended q = source q − ay).
                for &(j, _) in &taps {
                    let q = y + j;
                    let slot = q % kh;
                    if held[slot] != q {
                        held[slot] = q;
                        let padded = &mut ring[slot * padded_len..(slot + 1) * padded_len];
                        match rows.source(q).and_then(|s| src.get(s * n..(s + 1) * n)) {
                            Some(source) => {
                                columns.pad_row_with(source, c, constant, padded, T::to_f32)
                            }
                            None => padded.fill(constant),
                        }
                    }
                }
                acc.fill(delta);
                for (j, row_taps) in &taps {
                    let slot = (y + j) % kh;
                    let padded = &ring[slot * padded_len..(slot + 1) * padded_len];
                    for group in row_taps.chunks(4) {
                        accumulate_taps(&mut acc, padded, group);
                    }
                }
                if sx == 1 {
                    line.copy_from_slice(&acc);
                } else {
                    for (o, pixel) in line.chunks_exact_mut(c).zip(acc.chunks(c * sx)) {
                        o.copy_from_slice(&pixel[..c]);
                    }
                }
            }
        });
    dst
}

/// `acc[x] += w₀·row[x + o₀] + w₁·row[x + o₁] + …` for up to four `(offset, weight)` taps in
/// one pass (the sums are added to `acc` left to right, tap by tap, exactly as one pass per
/// tap would).
fn accumulate_taps(acc: &mut [f32], row: &[f32], taps: &[(usize, f32)]) {
    let n = acc.len();
    let tap = |k: usize| {
        taps.get(k)
            .and_then(|&(offset, w)| Some((row.get(offset..offset + n)?, w)))
    };
    match (tap(0), tap(1), tap(2), tap(3)) {
        (Some((r0, w0)), Some((r1, w1)), Some((r2, w2)), Some((r3, w3))) => {
            for ((((a, &x0), &x1), &x2), &x3) in acc.iter_mut().zip(r0).zip(r1).zip(r2).zip(r3) {
                *a = *a + w0 * x0 + w1 * x1 + w2 * x2 + w3 * x3;
            }
        }
        (Some((r0, w0)), Some((r1, w1)), Some((r2, w2)), None) => {
            for (((a, &x0), &x1), &x2) in acc.iter_mut().zip(r0).zip(r1).zip(r2) {
                *a = *a + w0 * x0 + w1 * x1 + w2 * x2;
            }
        }
        (Some((r0, w0)), Some((r1, w1)), None, None) => {
            for ((a, &x0), &x1) in acc.iter_mut().zip(r0).zip(r1) {
                *a = *a + w0 * x0 + w1 * x1;
            }
        }
        _ => {
            for &(offset, w) in taps {
                if let Some(shifted) = row.get(offset..offset + n) {
                    for (a, &x) in acc.iter_mut().zip(shifted) {
                        *a += w * x;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::map_index;
    use crate::filter::test_support::{MODES, random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    fn random_f32(w: usize, h: usize, channels: Channels, seed: u64) -> Image {
        let n = w * h * channels.count();
        let data = randoms(seed, n)
            .iter()
            .map(|&r| (r * 2.0 - 0.5) as f32)
            .collect();
        Image::from_f32(w, h, channels, data).unwrap()
    }

    fn samples(image: &Image) -> Vec<f64> {
        match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    fn kernel(rows: &[&[f64]]) -> Kernel {
        Kernel::from_rows(&rows.iter().map(|r| r.to_vec()).collect::<Vec<_>>()).unwrap()
    }

    fn random_kernel(w: usize, h: usize, seed: u64) -> Kernel {
        let weights = randoms(seed, w * h).iter().map(|r| r * 2.0 - 1.0).collect();
        Kernel {
            width: w,
            height: h,
            weights,
        }
    }

    fn options(kernel: &Kernel, border: BorderMode, value: f64) -> ConvolveOptions {
        ConvolveOptions {
            border,
            border_value: value,
            depth: OutputDepth::F32,
            ..ConvolveOptions::centred(kernel)
        }
    }

    /// Direct correlation through `map_index`, in f64, stride and anchor included.
    fn reference(image: &Image, kernel: &Kernel, o: &ConvolveOptions) -> Vec<f64> {
        let (w, h, c) = (image.width(), image.height(), image.channels().count());
        let src = samples(image);
        let [sx, sy] = o.stride;
        let mut out = Vec::new();
        for y in (0..h).step_by(sy) {
            for x in (0..w).step_by(sx) {
                for ch in 0..c {
                    let mut acc = o.delta;
                    for j in 0..kernel.height {
                        let yy =
                            map_index(y as isize + j as isize - o.anchor[1] as isize, h, o.border);
                        for i in 0..kernel.width {
                            let xx = map_index(
                                x as isize + i as isize - o.anchor[0] as isize,
                                w,
                                o.border,
                            );
                            let v = match (xx, yy) {
                                (Some(xx), Some(yy)) => src[(yy * w + xx) * c + ch],
                                _ => o.border_value,
                            };
                            acc += kernel.at(j, i) * v;
                        }
                    }
                    out.push(acc);
                }
            }
        }
        out
    }

    fn assert_close(got: &[f64], expected: &[f64], tolerance: f64, what: &str) {
        assert_eq!(got.len(), expected.len(), "{what}: length");
        for (k, (a, b)) in got.iter().zip(expected).enumerate() {
            assert!((a - b).abs() <= tolerance, "{what}: sample {k}: {a} vs {b}");
        }
    }

    #[test]
    fn hand_computed_dense_case() {
        // 3×3 image, Laplacian-like cross, reflect_101 and constant borders.
        let image = Image::from_u8(3, 3, Channels::Gray, vec![1, 2, 3, 4, 5, 6, 7, 8, 9]).unwrap();
        let k = kernel(&[&[0.0, 1.0, 0.0], &[1.0, -4.0, 1.0], &[0.0, 1.0, 0.0]]);
        assert!(separate(&k).is_none());
        let o = options(&k, BorderMode::Constant, 0.0);
        let out = convolve(&image, &k, &o);
        // Centre: 2 + 4 + 6 + 8 − 20 = 0. Corner (0,0): 2 + 4 − 4 = 2. (1,0): 1 + 3 + 5 − 8 = 1.
        assert_eq!(
            out.as_f32().unwrap(),
            &[2.0, 1.0, -4.0, -3.0, 0.0, -7.0, -16.0, -11.0, -22.0]
        );
        // reflect_101: the centre pixel still has the same neighbours.
        let o = options(&k, BorderMode::Reflect101, 0.0);
        let out = convolve(&image, &k, &o);
        // (0,0): up reads row 1 (4), left reads column 1 (2): 4 + 2 + 2 + 4 − 4 = 8.
        assert_eq!(out.as_f32().unwrap()[0], 8.0);
        assert_eq!(out.as_f32().unwrap()[4], 0.0);
    }

    #[test]
    fn hand_computed_separable_case_u8() {
        let image = Image::from_u8(4, 1, Channels::Gray, vec![10, 20, 30, 40]).unwrap();
        let k = kernel(&[&[1.0, 1.0, 1.0]]);
        let o = ConvolveOptions {
            border: BorderMode::Clamp,
            ..ConvolveOptions::centred(&k)
        };
        let out = convolve(&image, &k, &o);
        assert_eq!(out.as_u8().unwrap(), &[40, 60, 90, 110]);
        // Saturation and delta: 3 × 100 − 10 would be 290.
        let o = ConvolveOptions { delta: -10.0, ..o };
        let image = Image::from_u8(2, 1, Channels::Gray, vec![100, 100]).unwrap();
        assert_eq!(convolve(&image, &k, &o).as_u8().unwrap(), &[255, 255]);
        let o = ConvolveOptions { delta: -400.0, ..o };
        assert_eq!(convolve(&image, &k, &o).as_u8().unwrap(), &[0, 0]);
    }

    #[test]
    fn matches_opencv_values() {
        // cv2.filter2D / cv2.sepFilter2D (ddepth -1) on img = (37x + 11y² + 5xy) mod 256, 7×5.
        let image = Image::from_u8(
            7,
            5,
            Channels::Gray,
            (0..35)
                .map(|k| {
                    let (x, y) = (k % 7, k / 7);
                    ((37 * x + 11 * y * y + 5 * x * y) % 256) as u8
                })
                .collect(),
        )
        .unwrap();
        let k = kernel(&[&[0.1, -0.2, 0.3], &[0.25, 0.5, -0.15], &[0.05, 0.1, 0.05]]);
        let check = |got: &Image, expected: &[u8]| {
            for (a, &b) in got.as_u8().unwrap().iter().zip(expected) {
                assert!((i32::from(*a) - i32::from(b)).abs() <= 1, "{a} vs {b}");
            }
        };
        let expected = [
            29, 37, 76, 115, 154, 103, 239, 39, 48, 90, 132, 161, 216, 65, 75, 85, 132, 166, 226,
            55, 150, 133, 131, 158, 235, 82, 109, 104, 177, 226, 153, 55, 135, 190, 60,
        ];
        check(
            &convolve(&image, &k, &ConvolveOptions::centred(&k)),
            &expected,
        );
        let o = ConvolveOptions {
            anchor: [0, 2],
            delta: 7.0,
            border: BorderMode::Clamp,
            ..ConvolveOptions::centred(&k)
        };
        let expected = [
            37, 74, 111, 148, 185, 214, 229, 40, 78, 116, 154, 179, 184, 186, 55, 97, 139, 168,
            223, 117, 70, 92, 139, 173, 233, 62, 88, 81, 138, 165, 242, 89, 116, 107, 115,
        ];
        check(&convolve(&image, &k, &o), &expected);
        // sepFilter2D(kernelX = [−1 3 −1], kernelY = [¼ ½ ¼]), border reflect.
        let k = kernel(&[
            &[-0.25, 0.75, -0.25],
            &[-0.5, 1.5, -0.5],
            &[-0.25, 0.75, -0.25],
        ]);
        assert!(separate(&k).is_some());
        let o = ConvolveOptions {
            border: BorderMode::Reflect,
            ..ConvolveOptions::centred(&k)
        };
        let expected = [
            0, 41, 79, 118, 156, 255, 142, 0, 58, 100, 142, 248, 226, 0, 2, 96, 144, 254, 238, 28,
            58, 52, 220, 80, 255, 56, 108, 84, 101, 255, 0, 196, 60, 255, 0,
        ];
        check(&convolve(&image, &k, &o), &expected);
    }

    #[test]
    fn rank_one_detection() {
        let (col, row) = separate(&kernel(&[&[1.0, 2.0, 1.0], &[2.0, 4.0, 2.0]])).unwrap();
        assert_eq!(col, [0.5, 1.0]);
        assert_eq!(row, [2.0, 4.0, 2.0]);
        assert!(separate(&kernel(&[&[1.0, 2.0], &[2.0, 4.0 + 1e-9]])).is_none());
        assert!(separate(&kernel(&[&[1.0, 2.0], &[2.0, 4.0 + 1e-15]])).is_some());
        assert!(separate(&kernel(&[&[0.0, 0.0], &[0.0, 0.0]])).is_some());
        assert!(separate(&kernel(&[&[1.0, 0.0], &[0.0, 1.0]])).is_none());
    }

    #[test]
    fn impulse_response_is_the_kernel() {
        let (w, h) = (9, 8);
        let mut data = vec![0.0f32; w * h];
        data[3 * w + 4] = 1.0;
        let image = Image::from_f32(w, h, Channels::Gray, data).unwrap();
        for k in [
            random_kernel(3, 5, 1),
            random_kernel(4, 2, 2),
            random_kernel(1, 3, 3),
        ] {
            let [ax, ay] = [k.width / 2, k.height / 2];
            let corr = samples(&convolve(
                &image,
                &k,
                &options(&k, BorderMode::Constant, 0.0),
            ));
            let flipped = k.flipped();
            let conv_options = ConvolveOptions {
                anchor: [k.width - 1 - ax, k.height - 1 - ay],
                ..options(&k, BorderMode::Constant, 0.0)
            };
            let conv = samples(&convolve(&image, &flipped, &conv_options));
            for j in 0..k.height {
                for i in 0..k.width {
                    // Correlation: the kernel rotated by 180° around the anchor.
                    let at = |x: usize, y: usize| y * w + x;
                    let c = corr[at(4 + ax - i, 3 + ay - j)];
                    assert!((c - k.at(j, i)).abs() < 1e-6, "correlation {i},{j}");
                    // Convolution: the kernel itself, anchored at the impulse.
                    let v = conv[at(4 + i - ax, 3 + j - ay)];
                    assert!((v - k.at(j, i)).abs() < 1e-6, "convolution {i},{j}");
                }
            }
        }
    }

    #[test]
    fn flip_param_rotates_kernel_and_anchor() {
        let params = ConvolveParams {
            kernel: vec![vec![1.0, 2.0], vec![3.0, 4.0]],
            flip: true,
            anchor: Some([0, 1]),
            ..ConvolveParams::default()
        };
        let op = Convolve::new(params).unwrap();
        assert_eq!(op.kernel.weights, [4.0, 3.0, 2.0, 1.0]);
        assert_eq!(op.options.anchor, [1, 0]);
    }

    #[test]
    fn every_border_mode_matches_reference() {
        for (w, h) in [(9, 7), (2, 3), (1, 1), (5, 1)] {
            let image = random_u8(w, h, Channels::Rgb, (w * h) as u64);
            for mode in MODES {
                let value = if mode == BorderMode::Constant {
                    77.0
                } else {
                    0.0
                };
                for (k, anchor) in [
                    (random_kernel(3, 3, 5), None),
                    (random_kernel(5, 4, 6), Some([0, 3])),
                    (
                        kernel(&[&[1.0, -2.0, 3.0], &[2.0, -4.0, 6.0]]),
                        Some([2, 0]),
                    ),
                    (random_kernel(7, 1, 7), None),
                ] {
                    let mut o = options(&k, mode, value);
                    if let Some(a) = anchor {
                        o.anchor = a;
                    }
                    let got = samples(&convolve(&image, &k, &o));
                    assert_close(
                        &got,
                        &reference(&image, &k, &o),
                        1e-3,
                        &format!("{w}×{h} {mode:?}"),
                    );
                }
            }
        }
    }

    #[test]
    fn stride_subsamples_the_full_output() {
        let image = random_u8(23, 17, Channels::Gray, 9);
        for k in [
            random_kernel(3, 3, 1),
            kernel(&[&[1.0, 2.0, 1.0], &[2.0, 4.0, 2.0]]),
        ] {
            let full_options = options(&k, BorderMode::Reflect, 0.0);
            let full = samples(&convolve(&image, &k, &full_options));
            for stride in [[2, 1], [3, 4], [1, 5], [30, 30]] {
                let o = ConvolveOptions {
                    stride,
                    ..full_options
                };
                let out = convolve(&image, &k, &o);
                let (ow, oh) = (23usize.div_ceil(stride[0]), 17usize.div_ceil(stride[1]));
                assert_eq!((out.width(), out.height()), (ow, oh));
                let got = samples(&out);
                for y in 0..oh {
                    for x in 0..ow {
                        let e = full[y * stride[1] * 23 + x * stride[0]];
                        assert!((got[y * ow + x] - e).abs() <= 1e-4, "{stride:?} {x},{y}");
                    }
                }
            }
        }
    }

    #[test]
    fn depths_and_formats() {
        let k = random_kernel(3, 3, 4);
        for image in [
            random_u8(6, 5, Channels::Rgba, 1),
            Image::from_u16(6, 5, Channels::Gray, (0..30).map(|v| v * 2000).collect()).unwrap(),
            random_f32(6, 5, Channels::Rgb, 2),
        ] {
            let f = options(&k, BorderMode::Wrap, 0.0);
            let exact = samples(&convolve(&image, &k, &f));
            let same = convolve(
                &image,
                &k,
                &ConvolveOptions {
                    depth: OutputDepth::Same,
                    ..f
                },
            );
            assert_eq!(same.format(), image.format());
            let max = match image.data() {
                PixelData::U8(_) => 255.0,
                PixelData::U16(_) => 65535.0,
                PixelData::F32(_) => f64::INFINITY,
            };
            for (a, b) in samples(&same).iter().zip(&exact) {
                let expected = if max.is_finite() {
                    b.round().clamp(0.0, max)
                } else {
                    *b
                };
                assert!((a - expected).abs() <= 1e-3, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn tiny_and_empty_images() {
        let k = random_kernel(3, 3, 1);
        for (w, h) in [(0, 0), (0, 3), (3, 0)] {
            let empty = Image::from_u8(w, h, Channels::Gray, vec![]).unwrap();
            let out = convolve(&empty, &k, &ConvolveOptions::centred(&k));
            assert_eq!((out.width(), out.height()), (w, h));
            let strided = ConvolveOptions {
                stride: [2, 2],
                ..ConvolveOptions::centred(&k)
            };
            let out = convolve(&empty, &k, &strided);
            assert_eq!((out.width(), out.height()), (w.div_ceil(2), h.div_ceil(2)));
        }
        let one = Image::from_f32(1, 1, Channels::Gray, vec![2.0]).unwrap();
        let sum: f64 = k.weights.iter().sum();
        let out = convolve(&one, &k, &ConvolveOptions::centred(&k));
        assert!((f64::from(out.as_f32().unwrap()[0]) - 2.0 * sum).abs() < 1e-5);
    }

    #[test]
    fn constant_image_scales_by_kernel_sum() {
        let image = Image::from_u16(13, 11, Channels::Gray, vec![1000; 143]).unwrap();
        let k = kernel(&[&[0.0, 0.25, 0.0], &[0.25, -0.5, 0.25], &[0.0, 0.25, 0.1]]);
        let out = convolve(&image, &k, &options(&k, BorderMode::Reflect101, 0.0));
        assert!(
            out.as_f32()
                .unwrap()
                .iter()
                .all(|&v| (v - 600.0).abs() < 1e-3)
        );
    }

    #[test]
    fn new_checks_params() {
        let ok = |kernel: Vec<Vec<f64>>| ConvolveParams {
            kernel,
            ..ConvolveParams::default()
        };
        assert!(Convolve::new(ok(vec![vec![1.0, 2.0]])).is_ok());
        assert!(Convolve::new(ok(vec![])).is_err());
        assert!(Convolve::new(ok(vec![vec![]])).is_err());
        assert!(Convolve::new(ok(vec![vec![1.0, 2.0], vec![1.0]])).is_err());
        assert!(Convolve::new(ok(vec![vec![f64::NAN]])).is_err());
        assert!(Convolve::new(ok(vec![vec![0.0; 256]])).is_err());
        assert!(Convolve::new(ok(vec![vec![0.0; 255]; 255])).is_ok());
        let mut p = ok(vec![vec![1.0, 2.0]]);
        p.anchor = Some([2, 0]);
        assert!(Convolve::new(p.clone()).is_err());
        p.anchor = Some([-1, 0]);
        assert!(Convolve::new(p.clone()).is_err());
        p.anchor = Some([1, 0]);
        assert!(Convolve::new(p.clone()).is_ok());
        p.stride = [0, 1];
        assert!(Convolve::new(p.clone()).is_err());
        p.stride = [1, 1];
        p.delta = f64::INFINITY;
        assert!(Convolve::new(p.clone()).is_err());
        p.delta = 0.0;
        p.border_value = 3.0;
        assert!(Convolve::new(p).is_err());
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let image = random_u8(157, 301, Channels::Rgb, 8);
        let k = random_kernel(5, 5, 3);
        let run = || convolve(&image, &k, &ConvolveOptions::centred(&k));
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn separable_path_equals_dense_path(
            w in 1usize..16,
            h in 1usize..16,
            kw in 1usize..8,
            kh in 1usize..8,
            seed in 0u64..10_000,
            mode in 0usize..5,
            ax in 0usize..8,
            ay in 0usize..8,
            sx in 1usize..4,
            sy in 1usize..4,
        ) {
            let image = random_f32(w, h, Channels::Rgb, seed);
            let row: Vec<f64> = randoms(seed + 1, kw).iter().map(|r| r * 2.0 - 1.0).collect();
            let column: Vec<f64> = randoms(seed + 2, kh).iter().map(|r| r * 2.0 - 1.0).collect();
            let weights = column.iter().flat_map(|c| row.iter().map(move |r| c * r)).collect();
            let k = Kernel { width: kw, height: kh, weights };
            prop_assert!(separate(&k).is_some());
            let border = MODES[mode];
            let o = ConvolveOptions {
                anchor: [ax % kw, ay % kh],
                stride: [sx, sy],
                border,
                border_value: if border == BorderMode::Constant { 0.25 } else { 0.0 },
                delta: 0.5,
                depth: OutputDepth::F32,
            };
            let separable = samples(&convolve(&image, &k, &o));
            let dense = samples(&correlate_dense(&image, &k, &o));
            prop_assert_eq!(separable.len(), dense.len());
            for (a, b) in separable.iter().zip(&dense) {
                prop_assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()) * (kw * kh) as f64, "{} vs {}", a, b);
            }
        }

        #[test]
        fn linear_in_the_image(
            seed in 0u64..10_000,
            a in -3.0f64..3.0,
            b in -3.0f64..3.0,
            separable in proptest::bool::ANY,
        ) {
            let (w, h) = (11, 9);
            let i = random_f32(w, h, Channels::Gray, seed);
            let j = random_f32(w, h, Channels::Gray, seed + 7);
            let mix: Vec<f32> = samples(&i)
                .iter()
                .zip(samples(&j))
                .map(|(x, y)| (a * x + b * y) as f32)
                .collect();
            let mix = Image::from_f32(w, h, Channels::Gray, mix).unwrap();
            let k = if separable {
                kernel(&[&[1.0, 2.0, -1.0], &[0.5, 1.0, -0.5]])
            } else {
                random_kernel(3, 4, seed)
            };
            let o = options(&k, BorderMode::Reflect, 0.0);
            let (ci, cj, cm) = (
                samples(&convolve(&i, &k, &o)),
                samples(&convolve(&j, &k, &o)),
                samples(&convolve(&mix, &k, &o)),
            );
            for t in 0..cm.len() {
                prop_assert!((cm[t] - (a * ci[t] + b * cj[t])).abs() <= 1e-4);
            }
        }
    }
}
