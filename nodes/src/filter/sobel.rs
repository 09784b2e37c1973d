//! `filter.sobel` and `filter.scharr`: image derivatives with separable derivative kernels.
//!
//! Both run on [`separable_filter`] over an f32 copy of the input, so u8 input gives exact
//! integer results (every product and partial sum is an integer far below 2²⁴), and the output
//! is always f32 with the input's channels, each filtered on its own.
//!
//! u8 images with 3-tap integer kernels (Sobel ksize 3, Scharr, Prewitt, the Laplacian
//! stencils) take an integer fast path instead: per output row, the vertical pass sums three
//! source rows into an i16 row, which is padded through the border table and correlated
//! horizontally in i16, converted straight to f32. The common kernels are compiled with their
//! weights as constants. Every intermediate is the same exact integer as in the f32 path (the
//! path is taken only when no result can leave i16), so the results are bit-identical.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};
use super::gaussian::separable_filter;

/// Kernel sizes `filter.sobel` accepts.
pub const SOBEL_KSIZES: [u32; 4] = [1, 3, 5, 7];

/// Smoothing taps of the 3-tap Scharr kernel (its derivative taps are [−1 0 1]).
const SCHARR_SMOOTHING: [f64; 3] = [3.0, 10.0, 3.0];

params! {
    /// Parameters of `filter.sobel`.
    pub struct SobelParams {
        /// Order of the derivative along x.
        dx: u32 = 1 => [max = 6],
        /// Order of the derivative along y; `dx + dy` must be at least 1.
        dy: u32 = 0 => [max = 6],
        /// Kernel size: 1, 3, 5 or 7 px. 1 means no smoothing across the derivative (the
        /// derivative axis then uses the 3-tap kernel, as OpenCV). Each order must be below the
        /// size (below 3 for size 1).
        ksize: u32 = 3 => [min = 1, max = 7, unit = "px"],
        /// Factor applied to the derivative (output units per input unit).
        scale: f64 = 1.0,
        /// Value added after scaling, in output units.
        delta: f64 = 0.0,
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Sobel derivative (`filter.sobel`). See [`sobel`].
#[derive(Debug, Clone, PartialEq)]
pub struct Sobel {
    dx: usize,
    dy: usize,
    ksize: usize,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
}

impl Op for Sobel {
    type Params = SobelParams;
    const ID: &'static str = "filter.sobel";
    const SUMMARY: &'static str = "Image derivative of order (dx, dy) with a Sobel kernel.";
    const DOC: &'static str = r#"
Computes `scale · ∂^(dx+dy) I / ∂x^dx ∂y^dy + delta` with Sobel's separable kernels: the x
kernel is the derivative kernel of order dx and the y kernel that of order dy, where the kernel
of order d and size k is the binomial smoothing kernel of k − d taps ([1 1] convolved with
itself) convolved d times with the difference [−1 1]: [−1 0 1] and [1 2 1] for k = 3, so the
x derivative of a ramp of slope s is 8·s. Size 1 uses [−1 0 1] (or [1 −2 1]) on the derivative
axis and no smoothing on the other. Channels are filtered independently.

The output is f32 with the input's channels for every input depth: it holds every result
exactly for u8 input (OpenCV users often ask for CV_16S, which this equals where CV_16S does not
saturate). Scale and delta are applied after the filter (OpenCV folds the scale into the
kernel), so they may differ from OpenCV in the last f32 bit.

Reference: OpenCV `cv::Sobel(src, dst, CV_32F, dx, dy, ksize, scale, delta, borderType)`,
`cv::getDerivKernels`.

Example:
    "gx": (op: "filter.sobel", inputs: { "image": "gray.image" }, params: (dx: 1, dy: 0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to differentiate, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The derivative as f32, same size and channels as the input.",
        )]
    }

    fn new(params: SobelParams) -> Result<Self, String> {
        let SobelParams {
            dx,
            dy,
            ksize,
            scale,
            delta,
            border,
            border_value,
        } = params;
        if !SOBEL_KSIZES.contains(&ksize) {
            return Err(format!("`ksize` must be 1, 3, 5 or 7, got {ksize}"));
        }
        if dx + dy == 0 {
            return Err("`dx` + `dy` must be at least 1".into());
        }
        let limit = ksize.max(3);
        for (name, order) in [("dx", dx), ("dy", dy)] {
            if order >= limit {
                return Err(format!(
                    "`{name}` = {order} needs a larger `ksize` (orders must be below {limit} for ksize {ksize})"
                ));
            }
        }
        check_common(scale, delta, border, border_value)?;
        Ok(Sobel {
            dx: dx as usize,
            dy: dy as usize,
            ksize: ksize as usize,
            scale,
            delta,
            border,
            border_value,
        })
    }
}

/// Checks shared by both operators: finite scale, delta and border value, and a border value
/// only with border "constant".
pub(crate) fn check_common(
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Result<(), String> {
    for (name, value) in [
        ("scale", scale),
        ("delta", delta),
        ("border_value", border_value),
    ] {
        if !value.is_finite() {
            return Err(format!("`{name}` must be finite, got {value}"));
        }
    }
    check_border_value(border, border_value)
}

impl Operator for Sobel {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let derivative = sobel(
            image,
            self.dx,
            self.dy,
            self.ksize,
            self.scale,
            self.delta,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(derivative)))
    }
}

/// The 1-D derivative kernel of order `order` for Sobel size `ksize`, as OpenCV's
/// `getDerivKernels` (unnormalized): the binomial kernel of `k − order` taps convolved `order`
/// times with [−1 1], where `k` is `ksize`, or 3 when `ksize` is 1 and `order` > 0. Order 0
/// gives the smoothing kernel (summing to 2^(k−1)); higher orders sum to 0. `order ≥ k` gives
/// an empty kernel.
pub fn deriv_kernel(ksize: usize, order: usize) -> Vec<f64> {
    let size = if ksize <= 1 && order > 0 {
        3
    } else {
        ksize.max(1)
    };
    if order >= size {
        return Vec::new();
    }
    let mut kernel = vec![1.0];
    for _ in 1..size - order {
        kernel = convolve_pair(&kernel, 1.0);
    }
    for _ in 0..order {
        kernel = convolve_pair(&kernel, -1.0);
    }
    kernel
}

/// `kernel` convolved with `[first 1]`: `out[i] = kernel[i − 1] + first · kernel[i]`.
fn convolve_pair(kernel: &[f64], first: f64) -> Vec<f64> {
    (0..=kernel.len())
        .map(|i| {
            let previous = if i > 0 { kernel[i - 1] } else { 0.0 };
            let current = kernel.get(i).copied().unwrap_or(0.0);
            previous + first * current
        })
        .collect()
}

/// Sobel derivative of order (`dx`, `dy`) with kernel size `ksize` (1, 3, 5 or 7; see
/// [`deriv_kernel`]), `scale · result + delta`, as an f32 image with `image`'s size and
/// channels. Pixels outside the image are read through `border` (`border_value` with
/// [`BorderMode::Constant`]). Orders the size cannot carry give zeros.
#[allow(clippy::too_many_arguments)]
pub fn sobel(
    image: &Image,
    dx: usize,
    dy: usize,
    ksize: usize,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    derivative(
        image,
        &deriv_kernel(ksize, dx),
        &deriv_kernel(ksize, dy),
        scale,
        delta,
        border,
        border_value,
    )
}

/// `scale · separable_filter(f32 copy of image, kx, ky) + delta`, through the integer path
/// ([`derivative_u8_3tap`]) where it applies.
pub(crate) fn derivative(
    image: &Image,
    kx: &[f64],
    ky: &[f64],
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    if let Some(fast) = derivative_u8_3tap(image, kx, ky, scale, delta, border, border_value) {
        return fast;
    }
    derivative_generic(image, kx, ky, scale, delta, border, border_value)
}

/// `scale · Σ_t separable_filter(f32 copy of image, kx_t, ky_t) + delta` over the `(kx, ky)`
/// terms (sums of separable derivatives, such as the Laplacian), in one pass through the integer
/// path where every term qualifies for it. Results are the same either way (exact integers for
/// u8 input).
pub(crate) fn derivative_sum(
    image: &Image,
    terms: &[(&[f64], &[f64])],
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    if let Some(fast) = sum_u8_3tap(image, terms, scale, delta, border, border_value) {
        return fast;
    }
    let mut total: Option<Vec<f32>> = None;
    for (kx, ky) in terms {
        let term = derivative_generic(image, kx, ky, 1.0, 0.0, border, border_value);
        let values = term.as_f32().unwrap_or(&[]);
        match total.as_mut() {
            None => total = Some(values.to_vec()),
            Some(sum) => {
                for (t, &v) in sum.iter_mut().zip(values) {
                    *t += v;
                }
            }
        }
    }
    let plain = scale == 1.0 && delta == 0.0;
    let mut values = total.unwrap_or_else(|| vec![0.0; image.data().len()]);
    if !plain {
        for v in &mut values {
            *v = (f64::from(*v) * scale + delta) as f32;
        }
    }
    Image::from_f32(image.width(), image.height(), image.channels(), values)
        .unwrap_or_else(|_| to_f32(image))
}

/// Output rows per parallel band of the integer path.
const BAND_ROWS: usize = 32;

/// The taps of a 3-tap kernel as integers when every weight is an integer.
fn integer_taps(kernel: &[f64]) -> Option<[i16; 3]> {
    let taps: [f64; 3] = kernel.try_into().ok()?;
    if taps.iter().any(|w| w.fract() != 0.0 || w.abs() > 255.0) {
        return None;
    }
    Some(taps.map(|w| w as i16))
}

/// `Σ|w|` of a kernel.
fn abs_sum(taps: [i16; 3]) -> i32 {
    taps.iter().map(|&w| i32::from(w).abs()).sum()
}

/// The exact integer path for u8 images and 3-tap integer kernels (module docs); `None` when
/// it does not apply (see [`sum_u8_3tap`]).
fn derivative_u8_3tap(
    image: &Image,
    kx: &[f64],
    ky: &[f64],
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Option<Image> {
    sum_u8_3tap(image, &[(kx, ky)], scale, delta, border, border_value)
}

/// The integer path for a sum of separable terms: per output row, each term's vertical pass
/// into an i16 row and its horizontal pass written (first term) or added (others) to the f32
/// output row. `None` when it does not apply: not u8, no terms, a kernel that is not 3 integer
/// taps, a term whose results could leave i16 (`255 · Σ|kx| · Σ|ky| > 32767`), or a constant
/// border value that is not an integer in 0..=255.
fn sum_u8_3tap(
    image: &Image,
    terms: &[(&[f64], &[f64])],
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Option<Image> {
    let src = image.as_u8()?;
    let mut kernels = Vec::with_capacity(terms.len());
    for (kx, ky) in terms {
        let (kx, ky) = (integer_taps(kx)?, integer_taps(ky)?);
        if 255 * abs_sum(kx) * abs_sum(ky) > i32::from(i16::MAX) {
            return None;
        }
        kernels.push((kx, ky));
    }
    if kernels.is_empty() {
        return None;
    }
    let constant = if border == BorderMode::Constant {
        if border_value.fract() != 0.0 || !(0.0..=255.0).contains(&border_value) {
            return None;
        }
        border_value as u8
    } else {
        0
    };
    let (width, height, channels) = (image.width(), image.height(), image.channels());
    let c = channels.count();
    let n = width * c;
    if n == 0 || height == 0 {
        return Image::from_f32(width, height, channels, vec![0.0; src.len()]).ok();
    }
    let rows = BorderTable::new(height, 1, 1, border);
    let columns = BorderTable::new(width, 1, 1, border);
    let constant_row = vec![constant; n];
    let row = |k: usize| {
        rows.source(k)
            .and_then(|r| src.get(r * n..(r + 1) * n))
            .unwrap_or(&constant_row)
    };
    let plain = scale == 1.0 && delta == 0.0;
    let scale_row = |line: &mut [f32]| {
        if !plain {
            for v in line.iter_mut() {
                *v = (f64::from(*v) * scale + delta) as f32;
            }
        }
    };
    // Output row y reads extended rows y, y + 1, y + 2 (source rows y − 1, y, y + 1). A column
    // outside the image reads the constant in all three rows.
    let vertical = |y: usize, ky: [i16; 3], sums: &mut [i16]| {
        vertical_3tap(row(y), row(y + 1), row(y + 2), ky, &mut sums[c..c + n]);
        let edge = i16::from(constant) * (ky[0] + ky[1] + ky[2]);
        pad_edges(sums, c, n, &columns, edge);
    };
    let dst = if rayon::current_num_threads() == 1 {
        // One thread: append row by row, which spares zero-filling the output first.
        let mut dst = Vec::with_capacity(src.len());
        let mut sums = vec![0i16; n + 2 * c];
        for y in 0..height {
            let start = dst.len();
            for (t, &(kx, ky)) in kernels.iter().enumerate() {
                vertical(y, ky, &mut sums);
                if t == 0 {
                    horizontal_3tap(&sums, c, kx, Output::Append(&mut dst));
                } else {
                    horizontal_3tap(&sums, c, kx, Output::Add(&mut dst[start..]));
                }
            }
            scale_row(&mut dst[start..]);
        }
        dst
    } else {
        let mut dst = ocellus_engine::buffer::zeroed::<f32>(src.len());
        dst.par_chunks_mut(BAND_ROWS * n)
            .enumerate()
            .for_each(|(band, out)| {
                let mut sums = vec![0i16; n + 2 * c];
                for (r, line) in out.chunks_exact_mut(n).enumerate() {
                    for (t, &(kx, ky)) in kernels.iter().enumerate() {
                        vertical(band * BAND_ROWS + r, ky, &mut sums);
                        let target = if t == 0 {
                            Output::Write(&mut *line)
                        } else {
                            Output::Add(&mut *line)
                        };
                        horizontal_3tap(&sums, c, kx, target);
                    }
                    scale_row(line);
                }
            });
        dst
    };
    Image::from_f32(width, height, channels, dst).ok()
}

/// Calls `$f::<A, B, C>` for the common 3-tap kernels (so that their weights are constants the
/// compiler folds into shifts and adds), `$general` otherwise.
macro_rules! dispatch_taps {
    ($k:expr, $f:ident, $general:expr, ($($arg:expr),*)) => {
        match $k {
            [1, 2, 1] => $f::<1, 2, 1>($($arg),*),
            [-1, 0, 1] => $f::<-1, 0, 1>($($arg),*),
            [1, -2, 1] => $f::<1, -2, 1>($($arg),*),
            [3, 10, 3] => $f::<3, 10, 3>($($arg),*),
            [1, 1, 1] => $f::<1, 1, 1>($($arg),*),
            [0, 1, 0] => $f::<0, 1, 0>($($arg),*),
            _ => $general,
        }
    };
}

/// `out[i] = k0·a[i] + k1·b[i] + k2·c[i]` in i16 (no overflow: see [`derivative_u8_3tap`]).
fn vertical_3tap(a: &[u8], b: &[u8], c: &[u8], k: [i16; 3], out: &mut [i16]) {
    dispatch_taps!(
        k,
        vertical_const,
        vertical_taps(a, b, c, k, out),
        (a, b, c, out)
    )
}

fn vertical_const<const K0: i16, const K1: i16, const K2: i16>(
    a: &[u8],
    b: &[u8],
    c: &[u8],
    out: &mut [i16],
) {
    vertical_taps(a, b, c, [K0, K1, K2], out);
}

#[inline(always)]
fn vertical_taps(a: &[u8], b: &[u8], c: &[u8], k: [i16; 3], out: &mut [i16]) {
    let n = out.len().min(a.len()).min(b.len()).min(c.len());
    let (a, b, c, out) = (&a[..n], &b[..n], &c[..n], &mut out[..n]);
    for i in 0..n {
        out[i] = k[0]
            .wrapping_mul(i16::from(a[i]))
            .wrapping_add(k[1].wrapping_mul(i16::from(b[i])))
            .wrapping_add(k[2].wrapping_mul(i16::from(c[i])));
    }
}

/// Fills the one-pixel margins of `sums` (`c` samples each side of the `n` inner samples)
/// through the column border table; pixels reading the constant get `edge`.
fn pad_edges(sums: &mut [i16], c: usize, n: usize, columns: &BorderTable, edge: i16) {
    let width = n / c.max(1);
    for (position, start) in [(0, 0), (width + 1, c + n)] {
        for ch in 0..c {
            let value = match columns.source(position) {
                Some(s) => sums.get(c + s * c + ch).copied().unwrap_or(edge),
                None => edge,
            };
            if let Some(slot) = sums.get_mut(start + ch) {
                *slot = value;
            }
        }
    }
}

/// Where the horizontal pass puts a row of results.
enum Output<'a> {
    /// Overwrite this row.
    Write(&'a mut [f32]),
    /// Append the row to the output built so far.
    Append(&'a mut Vec<f32>),
    /// Add to this row (exact: the sums of integers stay far below 2²⁴).
    Add(&'a mut [f32]),
}

/// `k0·s[i] + k1·s[i + c] + k2·s[i + 2c]` in i16 for the `sums.len() − 2c` samples of a row,
/// as f32 (exact: see [`derivative_u8_3tap`]).
fn horizontal_3tap(sums: &[i16], c: usize, k: [i16; 3], out: Output<'_>) {
    let n = sums.len().saturating_sub(2 * c);
    let (Some(a), Some(b), Some(d)) = (
        sums.get(..n),
        sums.get(c..c + n),
        sums.get(2 * c..2 * c + n),
    ) else {
        return;
    };
    dispatch_taps!(
        k,
        horizontal_const,
        horizontal_taps(a, b, d, k, out),
        (a, b, d, out)
    )
}

fn horizontal_const<const K0: i16, const K1: i16, const K2: i16>(
    a: &[i16],
    b: &[i16],
    c: &[i16],
    out: Output<'_>,
) {
    horizontal_taps(a, b, c, [K0, K1, K2], out);
}

#[inline(always)]
fn horizontal_taps(a: &[i16], b: &[i16], c: &[i16], k: [i16; 3], out: Output<'_>) {
    let tap = move |((&a, &b), &c): ((&i16, &i16), &i16)| {
        let v = k[0]
            .wrapping_mul(a)
            .wrapping_add(k[1].wrapping_mul(b))
            .wrapping_add(k[2].wrapping_mul(c));
        f32::from(v)
    };
    let values = a.iter().zip(b).zip(c).map(tap);
    match out {
        Output::Write(line) => {
            for (o, v) in line.iter_mut().zip(values) {
                *o = v;
            }
        }
        Output::Append(dst) => dst.extend(values),
        Output::Add(line) => {
            for (o, v) in line.iter_mut().zip(values) {
                *o += v;
            }
        }
    }
}

/// The general path: `scale · separable_filter(f32 copy of image, kx, ky) + delta`.
fn derivative_generic(
    image: &Image,
    kx: &[f64],
    ky: &[f64],
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let float = to_f32(image);
    let filtered = separable_filter(&float, kx, ky, border, border_value);
    if scale == 1.0 && delta == 0.0 {
        return filtered;
    }
    let (width, height, channels) = (filtered.width(), filtered.height(), filtered.channels());
    match filtered.into_data() {
        PixelData::F32(mut data) => {
            for v in &mut data {
                *v = (f64::from(*v) * scale + delta) as f32;
            }
            Image::from_f32(width, height, channels, data).unwrap_or(float)
        }
        // separable_filter keeps the f32 depth of its input.
        _ => float,
    }
}

/// The samples of `image` as f32 (exact for u8 and u16).
pub(crate) fn to_f32(image: &Image) -> Image {
    let data: Vec<f32> = match image.data() {
        PixelData::U8(v) => v.iter().map(|&x| f32::from(x)).collect(),
        PixelData::U16(v) => v.iter().map(|&x| f32::from(x)).collect(),
        PixelData::F32(v) => v.clone(),
    };
    Image::from_f32(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

params! {
    /// Parameters of `filter.scharr`.
    pub struct ScharrParams {
        /// Order of the derivative along x: (dx, dy) must be (1, 0) or (0, 1).
        dx: u32 = 1 => [max = 1],
        /// Order of the derivative along y.
        dy: u32 = 0 => [max = 1],
        /// Factor applied to the derivative (output units per input unit).
        scale: f64 = 1.0,
        /// Value added after scaling, in output units.
        delta: f64 = 0.0,
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Scharr derivative (`filter.scharr`). See [`scharr`].
#[derive(Debug, Clone, PartialEq)]
pub struct Scharr {
    dx: usize,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
}

impl Op for Scharr {
    type Params = ScharrParams;
    const ID: &'static str = "filter.scharr";
    const SUMMARY: &'static str = "First image derivative with the 3×3 Scharr kernel.";
    const DOC: &'static str = r#"
Computes `scale · ∂I/∂x + delta` (dx = 1) or `scale · ∂I/∂y + delta` (dy = 1) with the 3×3
Scharr kernel [−3 0 3; −10 0 10; −3 0 3] (separably: [−1 0 1] along the derivative, [3 10 3]
across it), which is more rotation-invariant than the 3×3 Sobel kernel. Output f32 with the
input's channels, exact for u8 input.

Reference: OpenCV `cv::Scharr(src, dst, CV_32F, dx, dy, scale, delta, borderType)`; H. Scharr,
"Optimale Operatoren in der digitalen Bildverarbeitung", PhD thesis, Heidelberg, 2000.

Example:
    "gy": (op: "filter.scharr", inputs: { "image": "gray.image" }, params: (dx: 0, dy: 1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to differentiate, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The derivative as f32, same size and channels as the input.",
        )]
    }

    fn new(params: ScharrParams) -> Result<Self, String> {
        let ScharrParams {
            dx,
            dy,
            scale,
            delta,
            border,
            border_value,
        } = params;
        if !matches!((dx, dy), (1, 0) | (0, 1)) {
            return Err(format!(
                "(`dx`, `dy`) must be (1, 0) or (0, 1), got ({dx}, {dy})"
            ));
        }
        check_common(scale, delta, border, border_value)?;
        Ok(Scharr {
            dx: dx as usize,
            scale,
            delta,
            border,
            border_value,
        })
    }
}

impl Operator for Scharr {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let derivative = scharr(
            image,
            self.dx == 1,
            self.scale,
            self.delta,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(derivative)))
    }
}

/// Scharr first derivative along x (`along_x`) or y, `scale · result + delta`, as an f32
/// image with `image`'s size and channels.
pub fn scharr(
    image: &Image,
    along_x: bool,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let difference = [-1.0, 0.0, 1.0];
    let (kx, ky) = if along_x {
        (&difference, &SCHARR_SMOOTHING)
    } else {
        (&SCHARR_SMOOTHING, &difference)
    };
    derivative(image, kx, ky, scale, delta, border, border_value)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::map_index;
    use crate::filter::test_support::{MODES, random_u8, randoms};
    use ocellus_engine::value::Channels;

    fn random_f32(w: usize, h: usize, seed: u64) -> Image {
        let data = randoms(seed, w * h).iter().map(|&r| r as f32).collect();
        Image::from_f32(w, h, Channels::Gray, data).unwrap()
    }

    fn samples(image: &Image) -> Vec<f64> {
        match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    fn transpose(image: &Image) -> Image {
        let (w, h) = (image.width(), image.height());
        let src = samples(image);
        let data = (0..w * h)
            .map(|k| {
                let (y, x) = (k / h, k % h);
                src[x * w + y] as f32
            })
            .collect();
        Image::from_f32(h, w, Channels::Gray, data).unwrap()
    }

    /// Direct 2-D correlation with the outer product `ky ⊗ kx` through `map_index`.
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
                        let sy = map_index((y + j) as isize - (ky.len() / 2) as isize, h, border);
                        for (i, wx) in kx.iter().enumerate() {
                            let sx =
                                map_index((x + i) as isize - (kx.len() / 2) as isize, w, border);
                            let v = match (sx, sy) {
                                (Some(sx), Some(sy)) => src[(sy * w + sx) * c + ch],
                                _ => value,
                            };
                            acc += wy * wx * v;
                        }
                    }
                    out[(y * w + x) * c + ch] = acc;
                }
            }
        }
        out
    }

    #[test]
    fn kernels_match_opencv() {
        assert_eq!(deriv_kernel(3, 0), [1.0, 2.0, 1.0]);
        assert_eq!(deriv_kernel(3, 1), [-1.0, 0.0, 1.0]);
        assert_eq!(deriv_kernel(3, 2), [1.0, -2.0, 1.0]);
        assert_eq!(deriv_kernel(5, 1), [-1.0, -2.0, 0.0, 2.0, 1.0]);
        assert_eq!(deriv_kernel(5, 2), [1.0, 0.0, -2.0, 0.0, 1.0]);
        assert_eq!(deriv_kernel(7, 1), [-1.0, -4.0, -5.0, 0.0, 5.0, 4.0, 1.0]);
        assert_eq!(deriv_kernel(1, 0), [1.0]);
        assert_eq!(deriv_kernel(1, 1), [-1.0, 0.0, 1.0]);
        assert_eq!(deriv_kernel(1, 2), [1.0, -2.0, 1.0]);
        assert!(deriv_kernel(3, 3).is_empty());
    }

    #[test]
    fn kernel_sums() {
        for k in [3usize, 5, 7] {
            let smoothing: f64 = deriv_kernel(k, 0).iter().sum();
            assert_eq!(smoothing, f64::from(1u32 << (k - 1)));
            for order in 1..k {
                let kernel = deriv_kernel(k, order);
                assert_eq!(kernel.len(), k);
                assert_eq!(kernel.iter().sum::<f64>(), 0.0, "k {k} order {order}");
            }
        }
    }

    #[test]
    fn ramp_derivative_is_eight_times_the_slope() {
        let (w, h, slope) = (12, 6, 3u8);
        let data = (0..w * h).map(|k| (k % w) as u8 * slope).collect();
        let ramp = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        let gx = sobel(&ramp, 1, 0, 3, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        let gy = sobel(&ramp, 0, 1, 3, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        let gx = gx.as_f32().unwrap();
        for y in 0..h {
            for x in 1..w - 1 {
                assert_eq!(gx[y * w + x], 8.0 * f32::from(slope));
            }
            // reflect_101 mirrors the ramp at the edges: the derivative there is 0.
            assert_eq!(gx[y * w], 0.0);
        }
        assert!(gy.as_f32().unwrap().iter().all(|&v| v == 0.0));
        let scaled = sobel(&ramp, 1, 0, 3, 0.125, 10.0, BorderMode::Reflect101, 0.0);
        assert_eq!(scaled.as_f32().unwrap()[w + 3], 13.0);
        // Scharr: (3 + 10 + 3) · 2 · slope.
        let sx = scharr(&ramp, true, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        assert_eq!(sx.as_f32().unwrap()[w + 3], 32.0 * f32::from(slope));
    }

    #[test]
    fn constant_image_has_zero_derivatives() {
        let image = Image::from_u16(9, 7, Channels::Rgb, vec![4321; 9 * 7 * 3]).unwrap();
        for mode in [
            BorderMode::Reflect101,
            BorderMode::Wrap,
            BorderMode::Clamp,
            BorderMode::Reflect,
        ] {
            for (dx, dy, k) in [(1, 0, 3), (0, 1, 5), (1, 1, 7), (2, 0, 1)] {
                let d = sobel(&image, dx, dy, k, 1.0, 0.0, mode, 0.0);
                assert_eq!(d.channels(), Channels::Rgb);
                assert!(d.as_f32().unwrap().iter().all(|&v| v == 0.0));
            }
        }
    }

    #[test]
    fn transpose_symmetry() {
        let image = random_f32(23, 17, 4);
        let t = transpose(&image);
        for k in [1, 3, 5, 7] {
            let gx = sobel(&image, 1, 0, k, 1.0, 0.0, BorderMode::Reflect, 0.0);
            let gy_t = sobel(&t, 0, 1, k, 1.0, 0.0, BorderMode::Reflect, 0.0);
            for (a, b) in samples(&transpose(&gx)).iter().zip(samples(&gy_t)) {
                assert!((a - b).abs() <= 1e-4, "ksize {k}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn linear_for_f32() {
        let a = random_f32(31, 19, 1);
        let b = random_f32(31, 19, 2);
        let sum: Vec<f32> = samples(&a)
            .iter()
            .zip(samples(&b))
            .map(|(x, y)| (2.0 * x - 3.0 * y) as f32)
            .collect();
        let sum = Image::from_f32(31, 19, Channels::Gray, sum).unwrap();
        let d = |image: &Image| {
            samples(&sobel(
                image,
                1,
                1,
                5,
                1.0,
                0.0,
                BorderMode::Reflect101,
                0.0,
            ))
        };
        let (da, db, ds) = (d(&a), d(&b), d(&sum));
        for i in 0..ds.len() {
            assert!((ds[i] - (2.0 * da[i] - 3.0 * db[i])).abs() <= 1e-4);
        }
    }

    #[test]
    fn every_border_mode_matches_direct_correlation() {
        for (w, h) in [(8, 6), (2, 3), (1, 5)] {
            let image = random_u8(w, h, Channels::Rgb, (w + h) as u64);
            for mode in MODES {
                let value = if mode == BorderMode::Constant {
                    99.0
                } else {
                    0.0
                };
                for (dx, dy, k) in [
                    (1, 0, 3),
                    (0, 2, 5),
                    (1, 1, 7),
                    (2, 1, 5),
                    (1, 0, 1),
                    (0, 1, 1),
                ] {
                    let expected = reference(
                        &image,
                        &deriv_kernel(k, dx),
                        &deriv_kernel(k, dy),
                        mode,
                        value,
                    );
                    let got = sobel(&image, dx, dy, k, 1.0, 0.0, mode, value);
                    assert_eq!(
                        samples(&got),
                        expected,
                        "{w}×{h} {mode:?} ({dx}, {dy}) k {k}"
                    );
                }
                let expected = reference(&image, &[3.0, 10.0, 3.0], &[-1.0, 0.0, 1.0], mode, value);
                let got = scharr(&image, false, 1.0, 0.0, mode, value);
                assert_eq!(samples(&got), expected, "scharr {w}×{h} {mode:?}");
            }
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
        let image = random_u8(157, 299, Channels::Rgb, 8);
        let run = || sobel(&image, 1, 1, 5, 0.5, 1.0, BorderMode::Reflect101, 0.0);
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    #[test]
    fn integer_path_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let image = random_u8(211, 150, Channels::Rgb, 5);
        let (kx, ky) = (deriv_kernel(3, 1), deriv_kernel(3, 0));
        let run =
            || derivative_u8_3tap(&image, &kx, &ky, 1.0, 0.0, BorderMode::Reflect, 0.0).unwrap();
        let one = pool(1).install(run);
        assert_eq!(one, pool(3).install(run));
        let generic = derivative_generic(&image, &kx, &ky, 1.0, 0.0, BorderMode::Reflect, 0.0);
        assert_eq!(one, generic);
    }

    #[test]
    fn tiny_and_empty_images() {
        let one = Image::from_u8(1, 1, Channels::Gray, vec![200]).unwrap();
        let d = sobel(&one, 1, 0, 3, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        assert_eq!(d.as_f32().unwrap(), &[0.0]);
        // Constant 0: the second difference of [0 200 0] is −400, times the centre weight 2.
        let d = sobel(&one, 2, 0, 3, 1.0, 0.0, BorderMode::Constant, 0.0);
        assert_eq!(d.as_f32().unwrap(), &[-800.0]);
        for (w, h) in [(0, 0), (0, 4), (4, 0)] {
            let empty = Image::from_u8(w, h, Channels::Gray, vec![]).unwrap();
            let d = sobel(&empty, 1, 0, 3, 1.0, 0.0, BorderMode::Reflect101, 0.0);
            assert_eq!((d.width(), d.height()), (w, h));
            assert!(d.as_f32().is_some());
        }
    }

    #[test]
    fn new_checks_params() {
        let params = |dx, dy, ksize| SobelParams {
            dx,
            dy,
            ksize,
            scale: 1.0,
            delta: 0.0,
            border: BorderMode::Reflect101,
            border_value: 0.0,
        };
        assert!(Sobel::new(params(1, 0, 3)).is_ok());
        assert!(Sobel::new(params(2, 0, 1)).is_ok());
        assert!(Sobel::new(params(0, 0, 3)).is_err());
        assert!(Sobel::new(params(3, 0, 3)).is_err());
        assert!(Sobel::new(params(1, 0, 4)).is_err());
        assert!(Sobel::new(params(6, 0, 7)).is_ok());
        let mut bad = params(1, 0, 3);
        bad.border_value = 3.0;
        assert!(Sobel::new(bad).is_err());
        let scharr = |dx, dy| ScharrParams {
            dx,
            dy,
            scale: 1.0,
            delta: 0.0,
            border: BorderMode::Reflect101,
            border_value: 0.0,
        };
        assert!(Scharr::new(scharr(1, 0)).is_ok());
        assert!(Scharr::new(scharr(0, 1)).is_ok());
        assert!(Scharr::new(scharr(1, 1)).is_err());
        assert!(Scharr::new(scharr(0, 0)).is_err());
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        #[test]
        fn integer_path_equals_float_path(
            w in 0usize..20,
            h in 0usize..20,
            rgb in proptest::bool::ANY,
            seed in 0u64..1000,
            kernel in 0usize..5,
            mode in 0usize..5,
            constant in 0u8..=255,
            scaled in proptest::bool::ANY,
        ) {
            let channels = if rgb { Channels::Rgb } else { Channels::Gray };
            let image = random_u8(w, h, channels, seed);
            let border = MODES[mode];
            let value = if border == BorderMode::Constant { f64::from(constant) } else { 0.0 };
            let (scale, delta) = if scaled { (0.37, -5.25) } else { (1.0, 0.0) };
            let (kx, ky) = match kernel {
                0 => (deriv_kernel(3, 1), deriv_kernel(3, 0)),
                1 => (deriv_kernel(3, 0), deriv_kernel(3, 1)),
                2 => (deriv_kernel(3, 2), deriv_kernel(3, 1)),
                3 => (vec![-1.0, 0.0, 1.0], SCHARR_SMOOTHING.to_vec()),
                _ => (SCHARR_SMOOTHING.to_vec(), vec![-1.0, 0.0, 1.0]),
            };
            let fast = derivative_u8_3tap(&image, &kx, &ky, scale, delta, border, value);
            proptest::prop_assert!(fast.is_some());
            let generic = derivative_generic(&image, &kx, &ky, scale, delta, border, value);
            proptest::prop_assert_eq!(fast.unwrap(), generic);
        }
    }

    #[test]
    fn integer_path_only_where_exact() {
        let image = random_u8(5, 4, Channels::Gray, 3);
        let (kx, ky) = (deriv_kernel(3, 1), deriv_kernel(3, 0));
        let run = |kx: &[f64], border, value| {
            derivative_u8_3tap(&image, kx, &ky, 1.0, 0.0, border, value).is_some()
        };
        assert!(run(&kx, BorderMode::Reflect101, 0.0));
        assert!(run(&kx, BorderMode::Constant, 255.0));
        assert!(!run(&kx, BorderMode::Constant, 99.5));
        assert!(!run(&kx, BorderMode::Constant, 256.0));
        assert!(!run(&deriv_kernel(5, 1), BorderMode::Reflect101, 0.0));
        assert!(!run(&[0.5, 0.0, -0.5], BorderMode::Reflect101, 0.0));
        // 255 · 200 · 4 would overflow i16.
        assert!(!run(&[-100.0, 0.0, 100.0], BorderMode::Reflect101, 0.0));
        assert!(run(&[-4.0, 0.0, 4.0], BorderMode::Reflect101, 0.0));
        let float = to_f32(&image);
        assert!(
            derivative_u8_3tap(&float, &kx, &ky, 1.0, 0.0, BorderMode::Reflect101, 0.0).is_none()
        );
    }
}
