//! `filter.box`: box filter (mean or sum over a rectangular window) with running sums.
//!
//! [`box_filter`] sums every `ksize_x × ksize_y` window of an image, per channel, and divides
//! by the window's area unless asked for plain sums. Its cost does not depend on the kernel size.
//!
//! How it runs:
//! - The image is cut into fixed bands of rows processed in parallel (`par_chunks_mut`). Each
//!   band starts its sums afresh from its first row, so every output row is computed by the
//!   same arithmetic in the same order whatever thread it falls on: results are bit-identical
//!   for any thread count. Bands are at least `4·ksize_y` rows tall, so the `ksize_y − 1` rows
//!   of overlap a band recomputes stay a bounded fraction of the work.
//! - Each source row is padded (and widened to the accumulator type) through a [`BorderTable`],
//!   then a horizontal running sum adds the sample entering the window and subtracts the one
//!   leaving it. The row sums go into a ring of `ksize_y` rows, and a vertical running sum adds
//!   the newest ring row and subtracts the one it replaces.
//! - u8 samples accumulate in u32 and u16 samples in u64, so sums are exact; f32 samples
//!   accumulate in f64 (as OpenCV does), which keeps the running-sum drift far below f32
//!   precision.
//! - u8 means over windows of at most 257 pixels and 16 columns (7×7 among them) take a faster
//!   path with the same results: column sums first, in u16, straight from the source rows, then
//!   the row sums as shifted vector adds fused with the scaling, compiled for AVX2 where the CPU
//!   has it (`box_u8_fast`).

use std::ops::{Add, Sub};

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};

/// Largest kernel side; keeps u8 window sums (≤ 255 · 4095²) inside u32.
pub const MAX_KSIZE: u32 = 4095;

/// Largest window area whose u8 sums (≤ 255 · area) fit an i32.
const MAX_I32_AREA: usize = i32::MAX as usize / 255;

/// Largest window area whose u8 sums (≤ 255 · area) fit a u16: the fast u8 mean path.
const MAX_U16_AREA: usize = u16::MAX as usize / 255;

/// Widest window the fast u8 mean path sums as shifted row adds.
const MAX_FAST_TAPS: usize = 16;

/// Output rows per parallel band (at least; tall kernels get taller bands).
const BAND_ROWS: usize = 64;

params! {
    /// Parameters of `filter.box`.
    pub struct BoxParams {
        /// Window size `[width, height]` in pixels, each 1..=4095, odd or even. The window of
        /// output pixel (x, y) starts at (x − ⌊width/2⌋, y − ⌊height/2⌋), OpenCV's default
        /// anchor.
        ksize: [u32; 2] = [3, 3],
        /// true: the window mean (output has the input's format). false: the plain window sum,
        /// output as f32 for every input depth (u8 and u16 sums do not fit their depth).
        normalize: bool = true,
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units
        /// (0–255 for u8, 0–65535 for u16; rounded and saturated for integer images).
        border_value: f64 = 0.0,
    }
}

/// Box filter (`filter.box`). See [`box_filter`].
#[derive(Debug, Clone, PartialEq)]
pub struct BoxFilter {
    ksize_x: usize,
    ksize_y: usize,
    normalize: bool,
    border: BorderMode,
    border_value: f64,
}

impl Op for BoxFilter {
    type Params = BoxParams;
    const ID: &'static str = "filter.box";
    const SUMMARY: &'static str = "Averages (or sums) every rectangular window of an image.";
    const DOC: &'static str = r#"
Replaces every sample by the mean of the `ksize[0] × ksize[1]` window around it (per channel),
or with `normalize: false` by the plain sum. The mean keeps the input's pixel format; the sum is
f32 for every input depth (OpenCV keeps the depth you ask for, often CV_32F or CV_32S).

Method: separable running sums (a horizontal running sum along each padded row, then a vertical
running sum over the row sums), so the cost per pixel does not depend on the window size. u8
and u16 sums are exact integers; u8 means are `sum · (1/area)` rounded to nearest in f32 and
u16 means in f64, which agrees with OpenCV's `boxFilter` within one gray level (they can
differ only where the mean is within rounding error of a half level, i.e. for even areas).
f32 images accumulate in f64. Unnormalized u8 sums are exact in f32 up to an area of 65 793
pixels; u16 up to 256. Even sizes are allowed, with the anchor at ksize/2 as in OpenCV.

Reference: OpenCV `cv::boxFilter` (and `cv::blur`, which is `boxFilter` with normalize true),
`cv::BorderTypes`.

Example:
    "mean": (op: "filter.box", inputs: { "image": "card.image" }, params: (ksize: (7, 7))),
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
            "Window means (input's format) or sums (f32), same size and channels as the input.",
        )]
    }

    fn new(params: BoxParams) -> Result<Self, String> {
        let BoxParams {
            ksize,
            normalize,
            border,
            border_value,
        } = params;
        for (axis, k) in ["width", "height"].iter().zip(ksize) {
            if !(1..=MAX_KSIZE).contains(&k) {
                return Err(format!(
                    "`ksize` {axis} must be between 1 and {MAX_KSIZE} px, got {k}"
                ));
            }
        }
        check_border_value(border, border_value)?;
        Ok(BoxFilter {
            ksize_x: ksize[0] as usize,
            ksize_y: ksize[1] as usize,
            normalize,
            border,
            border_value,
        })
    }
}

impl Operator for BoxFilter {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let filtered = box_filter(
            image,
            self.ksize_x,
            self.ksize_y,
            self.normalize,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(filtered)))
    }
}

/// Box filter of `image` with a `ksize_x × ksize_y` window (px, anchor at `ksize/2`):
///
/// `sum(x, y) = Σ_{j<ksize_y} Σ_{i<ksize_x} in(x + i − ⌊ksize_x/2⌋, y + j − ⌊ksize_y/2⌋)`
///
/// With `normalize` the output is `sum / (ksize_x · ksize_y)` in the input's pixel format
/// (integers rounded to nearest and saturated); without it, `sum` as f32. Pixels outside the
/// image are read through `border`; `border_value` is the constant for [`BorderMode::Constant`]
/// (rounded and saturated for integer images). A size of 0 is treated as 1.
pub fn box_filter(
    image: &Image,
    ksize_x: usize,
    ksize_y: usize,
    normalize: bool,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let kx = ksize_x.max(1);
    let ky = ksize_y.max(1);
    let geometry = Geometry {
        width: image.width(),
        channels: image.channels().count(),
        columns: BorderTable::new(image.width(), kx / 2, kx - 1 - kx / 2, border),
        rows: BorderTable::new(image.height(), ky / 2, ky - 1 - ky / 2, border),
    };
    let area = (kx * ky) as f64;
    let data = match (image.data(), normalize) {
        (PixelData::U8(src), true) if kx <= MAX_FAST_TAPS && kx * ky <= MAX_U16_AREA => {
            PixelData::U8(box_u8_fast(
                src,
                &geometry,
                saturate_u8(border_value),
                (1.0 / area) as f32,
            ))
        }
        // i32 converts to f32 in SIMD (u32 does not); it holds the sums of all but the largest
        // windows.
        (PixelData::U8(src), true) if kx * ky <= MAX_I32_AREA => {
            let inverse = (1.0 / area) as f32;
            PixelData::U8(box_bands(
                src,
                &geometry,
                saturate_u8(border_value),
                i32::from,
                |s: i32| round_small(s as f32 * inverse) as i32 as u8,
            ))
        }
        (PixelData::U8(src), true) => {
            let inverse = (1.0 / area) as f32;
            PixelData::U8(box_bands(
                src,
                &geometry,
                saturate_u8(border_value),
                u32::from,
                |s: u32| round_small(s as f32 * inverse) as u8,
            ))
        }
        (PixelData::U8(src), false) if kx * ky <= MAX_I32_AREA => PixelData::F32(box_bands(
            src,
            &geometry,
            saturate_u8(border_value),
            i32::from,
            |s: i32| s as f32,
        )),
        (PixelData::U8(src), false) => PixelData::F32(box_bands(
            src,
            &geometry,
            saturate_u8(border_value),
            u32::from,
            |s: u32| s as f32,
        )),
        (PixelData::U16(src), true) => {
            let inverse = 1.0 / area;
            PixelData::U16(box_bands(
                src,
                &geometry,
                saturate_u16(border_value),
                u64::from,
                |s: u64| (s as f64 * inverse).round_ties_even() as u16,
            ))
        }
        (PixelData::U16(src), false) => PixelData::F32(box_bands(
            src,
            &geometry,
            saturate_u16(border_value),
            u64::from,
            |s: u64| s as f32,
        )),
        (PixelData::F32(src), true) => {
            let inverse = 1.0 / area;
            PixelData::F32(box_bands(
                src,
                &geometry,
                border_value as f32,
                f64::from,
                |s: f64| (s * inverse) as f32,
            ))
        }
        (PixelData::F32(src), false) => PixelData::F32(box_bands(
            src,
            &geometry,
            border_value as f32,
            f64::from,
            |s: f64| s as f32,
        )),
    };
    Image::new(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

/// `border_value` as a u8 sample: rounded to nearest (ties to even) and saturated.
fn saturate_u8(value: f64) -> u8 {
    value.round_ties_even() as u8
}

/// `border_value` as a u16 sample: rounded to nearest (ties to even) and saturated.
fn saturate_u16(value: f64) -> u16 {
    value.round_ties_even() as u16
}

/// Rounds an f32 to an integer, ties to even, for |x| < 2²² (adding and subtracting 1.5·2²³);
/// unlike `round_ties_even` it vectorizes with SSE2. Box means of u8 stay below 256.
fn round_small(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC) - MAGIC
}

/// Image width, channel count and the border tables of both axes.
struct Geometry {
    width: usize,
    channels: usize,
    columns: BorderTable,
    rows: BorderTable,
}

/// Running-sum box filter of `src` in parallel bands: samples are widened to the accumulator
/// type `A` with `widen` and each window sum goes through `finish`.
fn box_bands<T, A, O>(
    src: &[T],
    geometry: &Geometry,
    constant: T,
    widen: impl Fn(T) -> A + Sync,
    finish: impl Fn(A) -> O + Sync,
) -> Vec<O>
where
    T: Copy + Sync,
    A: Copy + Default + Send + Add<Output = A> + Sub<Output = A>,
    O: Copy + Default + Send,
{
    let mut dst = ocellus_engine::buffer::zeroed::<O>(src.len());
    let Geometry {
        width,
        channels,
        columns,
        rows,
    } = geometry;
    let (width, c) = (*width, *channels);
    let n = width * c;
    if n == 0 || src.is_empty() {
        return dst;
    }
    let taps_x = columns.before() + 1 + columns.after();
    let taps_y = rows.before() + 1 + rows.after();
    let band_rows = BAND_ROWS.max(4 * taps_y);
    dst.par_chunks_mut(band_rows * n)
        .enumerate()
        .for_each(|(band, out)| {
            let y0 = band * band_rows;
            let out_rows = out.len() / n;
            let wide_constant = widen(constant);
            let mut padded = vec![wide_constant; columns.padded_len() * c];
            let mut ring = vec![vec![A::default(); n]; taps_y];
            let mut fresh = vec![A::default(); n];
            let mut column_sums = vec![A::default(); n];
            for step in 0..out_rows + taps_y - 1 {
                // Extended row `y0 + step` reads source row `y0 + step − before`.
                match rows
                    .source(y0 + step)
                    .and_then(|r| src.get(r * n..(r + 1) * n))
                {
                    Some(line) => columns.pad_row_with(line, c, wide_constant, &mut padded, &widen),
                    None => padded.fill(wide_constant),
                }
                running_row_sum(&padded, c, taps_x, &mut fresh);
                // The new row sums take the ring slot of the row leaving the vertical window
                // (zeros while the window fills up), which `fresh` then holds.
                let Some(slot) = ring.get_mut(step % taps_y) else {
                    continue;
                };
                std::mem::swap(slot, &mut fresh);
                let (new, old) = (&*slot, &fresh);
                let line = match (step + 1).checked_sub(taps_y) {
                    Some(y) => out.get_mut(y * n..(y + 1) * n),
                    None => None,
                };
                // Two simple loops rather than one fused loop: each vectorizes.
                for ((s, &a), &b) in column_sums.iter_mut().zip(new).zip(old) {
                    // Adding first keeps unsigned sums from going below zero.
                    *s = *s + a - b;
                }
                if let Some(line) = line {
                    for (o, &s) in line.iter_mut().zip(&column_sums) {
                        *o = finish(s);
                    }
                }
            }
        });
    dst
}

/// u8 window means for windows of at most [`MAX_U16_AREA`] pixels and [`MAX_FAST_TAPS`]
/// columns, in parallel bands, bit-identical to the general path (the window sums are the same
/// exact integers and go through the same f32 rounding).
///
/// The vertical pass comes first, straight from the source rows: the column sums of the band's
/// current output row are kept in u16 (with wrapping adds, exact since the true sums fit) and
/// updated by adding the source row entering the window and subtracting the one leaving it. The
/// column sums live in a row padded for the horizontal pass: the border columns copy the sums of
/// the columns they map to (or `ky · constant`), since the vertical sum of a column does not
/// depend on its neighbours. The horizontal window sum is then `kx` shifted vector adds, fused
/// with the scaling and rounding.
fn box_u8_fast(src: &[u8], geometry: &Geometry, constant: u8, inverse: f32) -> Vec<u8> {
    let mut dst = ocellus_engine::buffer::zeroed::<u8>(src.len());
    let Geometry {
        width,
        channels,
        columns,
        rows,
    } = geometry;
    let (width, c) = (*width, *channels);
    let n = width * c;
    if n == 0 || src.is_empty() {
        return dst;
    }
    let before = columns.before();
    let taps_x = before + 1 + columns.after();
    let taps_y = rows.before() + 1 + rows.after();
    let band_rows = BAND_ROWS.max(4 * taps_y);
    // Both fit: taps_y · 255 ≤ area · 255 ≤ u16::MAX.
    let constant_column = (taps_y as u16).wrapping_mul(u16::from(constant));
    let constant_row = vec![constant; n];
    let source_row = |k: usize| -> &[u8] {
        rows.source(k)
            .and_then(|r| src.get(r * n..(r + 1) * n))
            .unwrap_or(&constant_row)
    };
    dst.par_chunks_mut(band_rows * n)
        .enumerate()
        .for_each(|(band, out)| {
            let y0 = band * band_rows;
            let mut padded = vec![0u16; columns.padded_len() * c];
            for (y, line) in out.chunks_exact_mut(n).enumerate() {
                let y = y0 + y;
                let Some(sums) = padded.get_mut(before * c..before * c + n) else {
                    return;
                };
                if y == y0 {
                    // Output row y reads extended rows y .. y + taps_y − 1.
                    sums.fill(0);
                    for k in y..y + taps_y {
                        add_row(sums, source_row(k));
                    }
                } else {
                    update_row(sums, source_row(y + taps_y - 1), source_row(y - 1));
                }
                pad_sums(&mut padded, columns, c, constant_column);
                box_row_u8(&padded, c, taps_x, inverse, line);
            }
        });
    dst
}

/// Fills the border columns of the padded column sums from the columns they map to.
fn pad_sums(padded: &mut [u16], columns: &BorderTable, c: usize, constant: u16) {
    let before = columns.before();
    let len = columns.len();
    for k in (0..before).chain(before + len..columns.padded_len()) {
        let source = columns.source(k);
        for ch in 0..c {
            let v = match source {
                Some(s) => padded.get((before + s) * c + ch).copied().unwrap_or(0),
                None => constant,
            };
            if let Some(d) = padded.get_mut(k * c + ch) {
                *d = v;
            }
        }
    }
}

/// `sums[i] += row[i]` (wrapping; the true sums fit).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn add_row(sums: &mut [u16], row: &[u8]) {
    for (s, &x) in sums.iter_mut().zip(row) {
        *s = s.wrapping_add(u16::from(x));
    }
}

/// `sums[i] += new[i] − old[i]` (wrapping; the true sums fit).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn update_row(sums: &mut [u16], new: &[u8], old: &[u8]) {
    let n = sums.len().min(new.len()).min(old.len());
    for ((s, &a), &b) in sums[..n].iter_mut().zip(&new[..n]).zip(&old[..n]) {
        *s = s.wrapping_add(u16::from(a)).wrapping_sub(u16::from(b));
    }
}

/// `out[i] = round(Σ_{t<taps} padded[i + t·c] · inverse)` for one row.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn box_row_u8(padded: &[u16], c: usize, taps: usize, inverse: f32, out: &mut [u8]) {
    match taps {
        3 => shifted_sums::<3>(padded, c, inverse, out),
        5 => shifted_sums::<5>(padded, c, inverse, out),
        7 => shifted_sums::<7>(padded, c, inverse, out),
        _ => blocked_sums(padded, c, taps, inverse, out),
    }
}

/// The mean of a u8 window sum, rounded as the general path rounds it: adding 1.5·2²³ leaves
/// the rounded integer `k` (0 ≤ k < 2²²) in the low mantissa bits, whose low byte is `k` for
/// the means of u8 samples. This equals `round_small(x) as i32 as u8` and avoids the
/// saturating float-to-integer conversion, which LLVM does not vectorize for AVX2.
#[inline(always)]
fn mean_u8(sum: u16, inverse: f32) -> u8 {
    const MAGIC: f32 = 12_582_912.0;
    (f32::from(sum) * inverse + MAGIC).to_bits() as u8
}

#[inline(always)]
fn shifted_sums<const K: usize>(padded: &[u16], c: usize, inverse: f32, out: &mut [u8]) {
    let n = out.len();
    let taps: [&[u16]; K] = std::array::from_fn(|t| padded.get(t * c..t * c + n).unwrap_or(&[]));
    // Looping to the shortest length lets LLVM drop every bounds check.
    let n = taps.iter().fold(n, |n, tap| n.min(tap.len()));
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let mut sum = taps[0][i];
        for tap in &taps[1..] {
            sum = sum.wrapping_add(tap[i]);
        }
        *o = mean_u8(sum, inverse);
    }
}

#[inline(always)]
fn blocked_sums(padded: &[u16], c: usize, taps: usize, inverse: f32, out: &mut [u8]) {
    const BLOCK: usize = 128;
    for (block, out) in out.chunks_mut(BLOCK).enumerate() {
        let start = block * BLOCK;
        let mut acc = [0u16; BLOCK];
        let acc = &mut acc[..out.len()];
        for t in 0..taps {
            let from = start + t * c;
            if let Some(s) = padded.get(from..from + acc.len()) {
                for (a, &x) in acc.iter_mut().zip(s) {
                    *a = a.wrapping_add(x);
                }
            }
        }
        for (o, &a) in out.iter_mut().zip(acc.iter()) {
            *o = mean_u8(a, inverse);
        }
    }
}

/// `out[x·c + ch] = Σ_{i<taps} padded[(x + i)·c + ch]` for every pixel `x` of `out`, by a
/// running sum: each step adds the sample entering the window before subtracting the one
/// leaving it, so unsigned accumulators never go below zero.
fn running_row_sum<A>(padded: &[A], c: usize, taps: usize, out: &mut [A])
where
    A: Copy + Default + Add<Output = A> + Sub<Output = A>,
{
    let n = out.len();
    if n < c || padded.len() < n + (taps - 1) * c {
        return;
    }
    for (ch, o) in out.iter_mut().take(c).enumerate() {
        *o = padded[ch..]
            .iter()
            .step_by(c)
            .take(taps)
            .fold(A::default(), |acc, &v| acc + v);
    }
    match c {
        1 => running_pixels::<A, 1>(padded, taps, out),
        3 => running_pixels::<A, 3>(padded, taps, out),
        4 => running_pixels::<A, 4>(padded, taps, out),
        _ => {
            let span = taps * c;
            let entering = &padded[span..span + n - c];
            let leaving = &padded[..n - c];
            for i in 0..n - c {
                out[i + c] = out[i] + entering[i] - leaving[i];
            }
        }
    }
}

/// The running part of [`running_row_sum`] for `C` channels, the `C` sums held in registers;
/// `out`'s first pixel already holds the first window's sums.
fn running_pixels<A, const C: usize>(padded: &[A], taps: usize, out: &mut [A])
where
    A: Copy + Default + Add<Output = A> + Sub<Output = A>,
{
    let mut sums = [A::default(); C];
    sums.copy_from_slice(&out[..C]);
    let entering = padded[taps * C..].chunks_exact(C);
    let leaving = padded.chunks_exact(C);
    for ((o, e), l) in out[C..].chunks_exact_mut(C).zip(entering).zip(leaving) {
        for ch in 0..C {
            sums[ch] = sums[ch] + e[ch] - l[ch];
            o[ch] = sums[ch];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::map_index;
    use crate::filter::gaussian::separable_filter;
    use crate::filter::test_support::{MODES, random_u8};
    use ocellus_engine::value::Channels;

    fn samples(image: &Image) -> Vec<f64> {
        match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    fn to_f32(image: &Image) -> Image {
        let data = samples(image).iter().map(|&x| x as f32).collect();
        Image::from_f32(image.width(), image.height(), image.channels(), data).unwrap()
    }

    /// Direct window sums in f64 through `map_index`: the definition.
    fn reference_sums(
        image: &Image,
        kx: usize,
        ky: usize,
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
                    for j in 0..ky {
                        let sy = map_index((y + j) as isize - (ky / 2) as isize, h, border);
                        for i in 0..kx {
                            let sx = map_index((x + i) as isize - (kx / 2) as isize, w, border);
                            acc += match (sx, sy) {
                                (Some(sx), Some(sy)) => src[(sy * w + sx) * c + ch],
                                _ => value,
                            };
                        }
                    }
                    out[(y * w + x) * c + ch] = acc;
                }
            }
        }
        out
    }

    #[test]
    fn hand_computed_3x3() {
        // 1 2 3
        // 4 5 6
        // 7 8 9, reflect_101: the centre is the mean of all nine samples, the corner (0, 0)
        // reads rows/columns [1 0 1]: 5 4 5 / 2 1 2 / 5 4 5 → 33.
        let image = Image::from_u8(3, 3, Channels::Gray, (1..=9).collect()).unwrap();
        let sums = box_filter(&image, 3, 3, false, BorderMode::Reflect101, 0.0);
        let sums = sums.as_f32().unwrap();
        assert_eq!(sums[4], 45.0);
        assert_eq!(sums[0], 33.0);
        let mean = box_filter(&image, 3, 3, true, BorderMode::Reflect101, 0.0);
        assert_eq!(mean.as_u8().unwrap()[4], 5);
        // 33 / 9 = 3.67 → 4.
        assert_eq!(mean.as_u8().unwrap()[0], 4);
        // Constant 0: the corner sums 1 + 2 + 4 + 5 = 12.
        let zero = box_filter(&image, 3, 3, false, BorderMode::Constant, 0.0);
        assert_eq!(zero.as_f32().unwrap()[0], 12.0);
    }

    #[test]
    fn constant_image_is_unchanged() {
        for mode in [BorderMode::Reflect101, BorderMode::Wrap, BorderMode::Clamp] {
            let image = Image::from_u8(40, 30, Channels::Rgb, vec![77; 40 * 30 * 3]).unwrap();
            assert_eq!(box_filter(&image, 7, 5, true, mode, 0.0), image);
            let image = Image::from_u16(9, 8, Channels::Gray, vec![60_001; 72]).unwrap();
            assert_eq!(box_filter(&image, 4, 6, true, mode, 0.0), image);
        }
    }

    #[test]
    fn matches_flat_separable_filter() {
        let image = random_u8(97, 75, Channels::Rgb, 3);
        for (kx, ky) in [(3, 3), (7, 7), (5, 1), (1, 9), (15, 11)] {
            let row = vec![1.0 / kx as f64; kx];
            let column = vec![1.0 / ky as f64; ky];
            let ours = box_filter(&image, kx, ky, true, BorderMode::Reflect101, 0.0);
            let theirs = separable_filter(&image, &row, &column, BorderMode::Reflect101, 0.0);
            for (a, b) in samples(&ours).iter().zip(samples(&theirs)) {
                assert!((a - b).abs() <= 1.0, "{kx}×{ky}: {a} vs {b}");
            }
            let float = to_f32(&image);
            let ours = box_filter(&float, kx, ky, true, BorderMode::Reflect101, 0.0);
            let theirs = separable_filter(&float, &row, &column, BorderMode::Reflect101, 0.0);
            for (a, b) in samples(&ours).iter().zip(samples(&theirs)) {
                assert!((a - b).abs() <= 1e-5 * 256.0, "{kx}×{ky} f32: {a} vs {b}");
            }
        }
    }

    #[test]
    fn every_border_mode_matches_direct_sums() {
        for (w, h) in [(7, 5), (2, 3), (1, 4)] {
            let image = random_u8(w, h, Channels::Rgb, (w * h) as u64);
            for mode in MODES {
                for (kx, ky) in [(3, 3), (5, 3), (4, 2), (9, 9), (2, 7)] {
                    let value = if mode == BorderMode::Constant {
                        17.0
                    } else {
                        0.0
                    };
                    let expected = reference_sums(&image, kx, ky, mode, value);
                    let sums = box_filter(&image, kx, ky, false, mode, value);
                    assert_eq!(samples(&sums), expected, "{w}×{h} {mode:?} {kx}×{ky}");
                    let means = box_filter(&image, kx, ky, true, mode, value);
                    let area = (kx * ky) as f64;
                    for (m, s) in samples(&means).iter().zip(&expected) {
                        assert!(
                            (m - s / area).abs() <= 0.5 + 1e-9,
                            "{mode:?} {m} vs {s}/{area}"
                        );
                    }
                    let float = box_filter(&to_f32(&image), kx, ky, true, mode, value);
                    for (m, s) in samples(&float).iter().zip(&expected) {
                        assert!(
                            (m - s / area).abs() <= 1e-4,
                            "{mode:?} f32 {m} vs {s}/{area}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn even_size_anchors_at_half() {
        // A single bright pixel at x = 5 in a row: a 4-wide window [x − 2, x + 1] covers it
        // for outputs x = 4..=7.
        let mut data = vec![0u8; 12];
        data[5] = 100;
        let image = Image::from_u8(12, 1, Channels::Gray, data).unwrap();
        let sums = box_filter(&image, 4, 1, false, BorderMode::Constant, 0.0);
        let expected: Vec<f32> = (0..12)
            .map(|x| if (4..=7).contains(&x) { 100.0 } else { 0.0 })
            .collect();
        assert_eq!(sums.as_f32().unwrap(), expected.as_slice());
    }

    #[test]
    fn tiny_and_empty_images() {
        let one = Image::from_u8(1, 1, Channels::Gray, vec![200]).unwrap();
        for mode in MODES {
            if mode != BorderMode::Constant {
                assert_eq!(box_filter(&one, 5, 5, true, mode, 0.0), one);
            }
        }
        let sums = box_filter(&one, 3, 3, false, BorderMode::Constant, 0.0);
        assert_eq!(sums.as_f32().unwrap(), &[200.0]);
        for (w, h) in [(0, 0), (0, 5), (5, 0)] {
            let empty = Image::from_u8(w, h, Channels::Rgb, vec![]).unwrap();
            let out = box_filter(&empty, 3, 3, true, BorderMode::Reflect101, 0.0);
            assert_eq!((out.width(), out.height()), (w, h));
            let out = box_filter(&empty, 3, 3, false, BorderMode::Reflect101, 0.0);
            assert!(out.as_f32().is_some_and(|v| v.is_empty()));
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
        let rgb = random_u8(131, 301, Channels::Rgb, 9);
        let float = to_f32(&rgb);
        for (image, k, normalize) in [(&rgb, 5, true), (&rgb, 40, false), (&float, 9, true)] {
            let run = || box_filter(image, k, k, normalize, BorderMode::Reflect, 0.0);
            assert_eq!(pool(1).install(run), pool(3).install(run));
        }
    }

    /// The general running-sum path for u8 means, which the fast path must reproduce exactly.
    fn general_u8_mean(
        image: &Image,
        kx: usize,
        ky: usize,
        mode: BorderMode,
        value: u8,
    ) -> Vec<u8> {
        let geometry = Geometry {
            width: image.width(),
            channels: image.channels().count(),
            columns: BorderTable::new(image.width(), kx / 2, kx - 1 - kx / 2, mode),
            rows: BorderTable::new(image.height(), ky / 2, ky - 1 - ky / 2, mode),
        };
        let inverse = (1.0 / (kx * ky) as f64) as f32;
        box_bands(
            image.as_u8().unwrap(),
            &geometry,
            value,
            i32::from,
            |s: i32| round_small(s as f32 * inverse) as i32 as u8,
        )
    }

    #[test]
    fn fast_u8_path_matches_the_general_path() {
        let sizes = [
            (1, 1),
            (3, 3),
            (7, 7),
            (5, 1),
            (1, 9),
            (4, 6),
            (16, 16),
            (9, 28),
            (2, 128),
        ];
        for (w, h, channels) in [
            (97, 150, Channels::Rgb),
            (5, 3, Channels::Gray),
            (300, 70, Channels::Gray),
            (1, 1, Channels::Rgba),
        ] {
            let image = random_u8(w, h, channels, (w * h) as u64);
            for mode in MODES {
                for (kx, ky) in sizes {
                    assert!(kx <= MAX_FAST_TAPS && kx * ky <= MAX_U16_AREA);
                    let value = if mode == BorderMode::Constant { 255 } else { 0 };
                    let fast = box_filter(&image, kx, ky, true, mode, f64::from(value));
                    let general = general_u8_mean(&image, kx, ky, mode, value);
                    assert_eq!(fast.as_u8().unwrap(), general, "{w}×{h} {mode:?} {kx}×{ky}");
                }
            }
        }
        // The rounding trick equals the general rounding for every sum of every fast size.
        for area in 1..=MAX_U16_AREA {
            let inverse = (1.0 / area as f64) as f32;
            for sum in 0..=(255 * area) as u16 {
                let general = round_small(f32::from(sum) * inverse) as i32 as u8;
                assert_eq!(mean_u8(sum, inverse), general, "{sum}/{area}");
            }
        }
        // All-255 images reach the largest sums.
        let white = Image::from_u8(40, 40, Channels::Gray, vec![255; 1600]).unwrap();
        let out = box_filter(&white, 16, 16, true, BorderMode::Constant, 255.0);
        assert!(out.as_u8().unwrap().iter().all(|&v| v == 255));
    }

    #[test]
    fn new_checks_params() {
        let params = |ksize: [u32; 2], border: BorderMode, border_value: f64| BoxParams {
            ksize,
            normalize: true,
            border,
            border_value,
        };
        assert!(BoxFilter::new(params([3, 3], BorderMode::Reflect101, 0.0)).is_ok());
        assert!(BoxFilter::new(params([0, 3], BorderMode::Reflect101, 0.0)).is_err());
        assert!(BoxFilter::new(params([3, 5000], BorderMode::Reflect101, 0.0)).is_err());
        assert!(BoxFilter::new(params([3, 3], BorderMode::Reflect101, 5.0)).is_err());
        assert!(BoxFilter::new(params([3, 3], BorderMode::Constant, 5.0)).is_ok());
        assert!(BoxFilter::new(params([3, 3], BorderMode::Constant, f64::NAN)).is_err());
    }
}
