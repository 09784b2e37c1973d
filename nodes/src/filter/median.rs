//! `filter.median`: the median of every square window, per channel, with OpenCV's `medianBlur`
//! semantics.
//!
//! Three methods, chosen by [`MedianMethod::auto`]:
//! - **Network** (ksize 3 and 5, every depth): a comparator network applied to many samples at
//!   once. For each output row the `k` source rows of the window are first sorted column-wise
//!   (3 or 9 comparators per column, shared by the `k` windows that contain the column); the
//!   median of the `k` sorted columns of a window is then selected by a network pruned for
//!   sorted columns: 10 comparators for 3×3 (max of the lows, median of the middles, min of the
//!   highs, then their median) and 85 for 5×5 (Batcher's odd-even merge network pruned, with
//!   the 0-1 principle over all sorted-column inputs, to the comparators that can swap and that
//!   reach the median). Each comparator is an element-wise min/max over an array of samples
//!   (32 u8, 16 u16 or 8 f32) so that it compiles to SIMD min/max instructions.
//! - **Histogram** (u8, ksize ≥ 7): the constant-time method of Perreault & Hébert: per-column
//!   histograms (updated by one row in and one row out per output row) and a kernel histogram
//!   (one column in and one column out per output pixel), both with 16 coarse bins of 16 fine
//!   bins. The coarse level finds the 16-level range of the median; the fine histogram of that
//!   range is brought up to date lazily from the column histograms (or rebuilt when it is older
//!   than the window). The cost per pixel does not depend on `ksize`.
//! - **Sort** (every other case: u16 and f32 with ksize ≥ 7): gathers each window and selects
//!   the middle sample (`select_nth_unstable`), O(k²) per sample.
//!
//! Crossover, measured on a 1080p gray u8 image, one thread (CPU time, rough): network 2 ms
//! (3×3) and 13 ms (5×5); histogram about 85 ms for every ksize from 3 to 15; sort 170 ms
//! (3×3), 390 ms (5×5), 650 ms (7×7). Hence networks for 3 and 5, histograms from 7 up for u8
//! (no network is generated for 7×7), and sorting only where neither applies.
//!
//! All three are exact and return the same value (the middle of the sorted window), so the
//! method never changes the result (f32 NaN excepted, see the operator docs). The image is cut
//! into fixed bands of rows processed in parallel; every band pads its own rows, so results are
//! bit-identical for any thread count.

use std::cmp::Ordering;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};

/// Largest window side, px (u8 kernel histograms count up to 255² < 2¹⁶ samples).
pub const MAX_KSIZE: u32 = 255;

/// Output rows per parallel band.
const BAND_ROWS: usize = 32;

params! {
    /// Parameters of `filter.median`.
    pub struct MedianParams {
        /// Window side, odd, 1..=255 (the window is `ksize × ksize`, centred).
        ksize: u32 = 5 => [min = 1, max = 255, unit = "px"],
        /// How pixels outside the image are read. Default "clamp" (repeat the edge pixel), which
        /// is what OpenCV's `medianBlur` always uses.
        border: BorderMode = BorderMode::Clamp,
        /// Sample value read outside the image with border "constant", in the image's units
        /// (0–255 for u8, 0–65535 for u16; rounded and saturated for integer images).
        border_value: f64 = 0.0,
    }
}

/// How the median of each window is found; every method gives the same result.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MedianMethod {
    /// Comparator network over arrays of samples (ksize 3 and 5 only).
    Network,
    /// Perreault & Hébert constant-time histograms (u8 only).
    Histogram,
    /// Gather and select, any ksize and depth.
    Sort,
}

impl MedianMethod {
    /// The fastest method for `ksize` on `image`: the network for 3 and 5, histograms for u8
    /// from 7 up, sorting otherwise.
    pub fn auto(image: &Image, ksize: usize) -> MedianMethod {
        match (ksize, image.data()) {
            (3 | 5, _) => MedianMethod::Network,
            (_, PixelData::U8(_)) if ksize >= 7 => MedianMethod::Histogram,
            _ => MedianMethod::Sort,
        }
    }
}

/// Median filter (`filter.median`). See [`median_blur`].
#[derive(Debug, Clone, PartialEq)]
pub struct Median {
    ksize: usize,
    border: BorderMode,
    border_value: f64,
}

impl Op for Median {
    type Params = MedianParams;
    const ID: &'static str = "filter.median";
    const SUMMARY: &'static str =
        "Replaces every sample by the median of the square window around it.";
    const DOC: &'static str = r#"
Replaces every sample by the median of the `ksize × ksize` window centred on it, per channel
(the middle value of the k² sorted samples; k is odd, so it is one of them: no rounding). Works
on every pixel format; the output has the input's format. Removes salt-and-pepper noise while
keeping edges.

Method, chosen automatically (all give the same result):
- ksize 3 and 5: a comparator network (element-wise min/max over many samples at once, which
  compiles to SIMD): columns of the window are sorted first and shared between neighbouring
  windows, then a network pruned for sorted columns selects the median (10 comparators for 3×3,
  85 for 5×5).
- u8 with ksize ≥ 7: Perreault & Hébert's constant-time median (column histograms and a kernel
  histogram with 16 coarse × 16 fine levels, fine levels updated lazily); the cost per pixel
  does not depend on ksize.
- u16 and f32 with ksize ≥ 7: gather and select, O(ksize²) per sample.

Differences from OpenCV: `cv::medianBlur` always replicates the edge pixel (border "clamp", the
default here), accepts u16 and f32 only for ksize 3 and 5, and u8 up to 255; here every depth
takes any odd ksize up to 255 and any border mode. With the default border the result is
identical to `medianBlur` for u8. f32: NaN makes the result of the windows containing it
unspecified (but deterministic).

References: S. Perreault and P. Hébert, "Median Filtering in Constant Time", IEEE Trans. Image
Processing 16(9), 2007; K. E. Batcher, "Sorting networks and their applications", AFIPS 1968;
OpenCV `cv::medianBlur`.

Example:
    "denoise": (op: "filter.median", inputs: { "image": "card.image" }, params: (ksize: 5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to filter, any pixel format (channels are filtered independently).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The window medians, same size and pixel format as the input.",
        )]
    }

    fn new(params: MedianParams) -> Result<Self, String> {
        let MedianParams {
            ksize,
            border,
            border_value,
        } = params;
        if !(1..=MAX_KSIZE).contains(&ksize) || ksize.is_multiple_of(2) {
            return Err(format!(
                "`ksize` must be odd and between 1 and {MAX_KSIZE} px, got {ksize}"
            ));
        }
        check_border_value(border, border_value)?;
        Ok(Median {
            ksize: ksize as usize,
            border,
            border_value,
        })
    }
}

impl Operator for Median {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = median_blur(image, self.ksize, self.border, self.border_value);
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Median of every `ksize × ksize` window of `image` (per channel), with the method chosen by
/// [`MedianMethod::auto`]. `ksize` is made odd (an even size is rounded up); pixels outside the
/// image are read through `border` (`border_value` for the constant mode).
pub fn median_blur(image: &Image, ksize: usize, border: BorderMode, border_value: f64) -> Image {
    let k = ksize.max(1) | 1;
    let method = MedianMethod::auto(image, k);
    median_blur_with(image, k, border, border_value, method).unwrap_or_else(|_| image.clone())
}

/// [`median_blur`] with an explicit method; an error when the method does not apply (network
/// for a ksize other than 3 or 5, histogram for a depth other than u8) or `ksize` is even.
pub fn median_blur_with(
    image: &Image,
    ksize: usize,
    border: BorderMode,
    border_value: f64,
    method: MedianMethod,
) -> Result<Image, String> {
    if ksize.is_multiple_of(2) {
        return Err(format!("`ksize` must be odd, got {ksize}"));
    }
    if image.is_empty() || ksize == 1 {
        return Ok(image.clone());
    }
    let geometry = Geometry {
        width: image.width(),
        channels: image.channels().count(),
        ksize,
        columns: BorderTable::symmetric(image.width(), ksize / 2, border),
        rows: BorderTable::symmetric(image.height(), ksize / 2, border),
    };
    let data = match (image.data(), method) {
        (PixelData::U8(src), MedianMethod::Network) => PixelData::U8(network::<u8, 32>(
            src,
            &geometry,
            u8::saturate(border_value),
        )?),
        (PixelData::U16(src), MedianMethod::Network) => PixelData::U16(network::<u16, 16>(
            src,
            &geometry,
            u16::saturate(border_value),
        )?),
        (PixelData::F32(src), MedianMethod::Network) => PixelData::F32(network::<f32, 8>(
            src,
            &geometry,
            f32::saturate(border_value),
        )?),
        (PixelData::U8(src), MedianMethod::Histogram) => PixelData::U8(bands(
            src,
            &geometry,
            u8::saturate(border_value),
            histogram_band,
        )),
        (_, MedianMethod::Histogram) => {
            return Err("the histogram median needs a u8 image".into());
        }
        (PixelData::U8(src), MedianMethod::Sort) => {
            PixelData::U8(bands(src, &geometry, u8::saturate(border_value), sort_band))
        }
        (PixelData::U16(src), MedianMethod::Sort) => PixelData::U16(bands(
            src,
            &geometry,
            u16::saturate(border_value),
            sort_band,
        )),
        (PixelData::F32(src), MedianMethod::Sort) => PixelData::F32(bands(
            src,
            &geometry,
            f32::saturate(border_value),
            sort_band,
        )),
    };
    Image::new(image.width(), image.height(), image.channels(), data).map_err(|e| e.to_string())
}

/// A sample type for the median.
pub trait Sample: Copy + Default + PartialOrd + Send + Sync + 'static {
    /// The smaller of two samples (branch-free select, vectorizes).
    #[inline(always)]
    fn lo(a: Self, b: Self) -> Self {
        if b < a { b } else { a }
    }
    /// The larger of two samples.
    #[inline(always)]
    fn hi(a: Self, b: Self) -> Self {
        if b < a { a } else { b }
    }
    /// A total order for selection.
    fn order(a: &Self, b: &Self) -> Ordering;
    /// A border value in the sample's units, rounded and saturated for integers.
    fn saturate(value: f64) -> Self;
}

impl Sample for u8 {
    fn order(a: &u8, b: &u8) -> Ordering {
        a.cmp(b)
    }
    fn saturate(value: f64) -> u8 {
        value.round_ties_even() as u8
    }
}

impl Sample for u16 {
    fn order(a: &u16, b: &u16) -> Ordering {
        a.cmp(b)
    }
    fn saturate(value: f64) -> u16 {
        value.round_ties_even() as u16
    }
}

impl Sample for f32 {
    fn order(a: &f32, b: &f32) -> Ordering {
        a.total_cmp(b)
    }
    fn saturate(value: f64) -> f32 {
        value as f32
    }
}

/// Image width, channels, window side and the border tables of both axes.
struct Geometry {
    width: usize,
    channels: usize,
    ksize: usize,
    columns: BorderTable,
    rows: BorderTable,
}

/// A band of padded source rows: `rows + ksize − 1` rows of `stride = padded width · channels`
/// samples each, plus `slack` samples at the end (for whole-array reads past the last row).
struct Padded<T> {
    data: Vec<T>,
    stride: usize,
}

/// Pads the source rows that output rows `y0 .. y0 + rows` read.
fn pad_band<T: Sample>(
    src: &[T],
    g: &Geometry,
    y0: usize,
    rows: usize,
    constant: T,
    slack: usize,
) -> Padded<T> {
    let n = g.width * g.channels;
    let stride = g.columns.padded_len() * g.channels;
    let total = rows + g.ksize - 1;
    let mut data = vec![constant; total * stride + slack];
    for (j, dst) in data.chunks_exact_mut(stride).take(total).enumerate() {
        match g
            .rows
            .source(y0 + j)
            .and_then(|r| src.get(r * n..(r + 1) * n))
        {
            Some(line) => g.columns.pad_row(line, g.channels, constant, dst),
            None => dst.fill(constant),
        }
    }
    Padded { data, stride }
}

/// Runs `band` over fixed bands of output rows in parallel: `band(padded, geometry, out)` fills
/// `out` (whole output rows) from the padded source rows.
fn bands<T: Sample>(
    src: &[T],
    g: &Geometry,
    constant: T,
    band: impl Fn(&Padded<T>, &Geometry, &mut [T]) + Sync,
) -> Vec<T> {
    let n = g.width * g.channels;
    let mut dst = vec![T::default(); src.len()];
    if n == 0 {
        return dst;
    }
    dst.par_chunks_mut(BAND_ROWS * n)
        .enumerate()
        .for_each(|(b, out)| {
            let rows = out.len() / n;
            let padded = pad_band(src, g, b * BAND_ROWS, rows, constant, 0);
            band(&padded, g, out);
        });
    dst
}

/// Gather-and-select median of one band (any ksize, any depth): the reference method.
fn sort_band<T: Sample>(padded: &Padded<T>, g: &Geometry, out: &mut [T]) {
    let (k, c) = (g.ksize, g.channels);
    let n = g.width * c;
    let mid = k * k / 2;
    let mut window = Vec::with_capacity(k * k);
    for (i, line) in out.chunks_exact_mut(n).enumerate() {
        for (s, o) in line.iter_mut().enumerate() {
            window.clear();
            for dy in 0..k {
                let start = (i + dy) * padded.stride + s;
                for dx in 0..k {
                    if let Some(&v) = padded.data.get(start + dx * c) {
                        window.push(v);
                    }
                }
            }
            if window.len() > mid {
                let (_, m, _) = window.select_nth_unstable_by(mid, T::order);
                *o = *m;
            }
        }
    }
}

/// Compare-exchange of lanes `a` and `b` of `v`: element-wise min into `a`, max into `b`.
#[inline(always)]
fn cas<T: Sample, const L: usize>(v: &mut [[T; L]], a: usize, b: usize) {
    if let (Some(&x), Some(&y)) = (v.get(a), v.get(b)) {
        let mut lo = [T::default(); L];
        let mut hi = [T::default(); L];
        for l in 0..L {
            lo[l] = T::lo(x[l], y[l]);
            hi[l] = T::hi(x[l], y[l]);
        }
        v[a] = lo;
        v[b] = hi;
    }
}

macro_rules! network {
    ($v:expr; $($a:literal $b:literal),* $(,)?) => {
        $( cas($v, $a, $b); )*
    };
}

/// Sorts 3 lanes.
#[inline(always)]
fn sort3<T: Sample, const L: usize>(v: &mut [[T; L]]) {
    network!(v; 0 1, 1 2, 0 1);
}

/// Sorts 5 lanes (9 comparators, optimal).
#[inline(always)]
fn sort5<T: Sample, const L: usize>(v: &mut [[T; L]]) {
    network!(v; 0 1, 3 4, 2 4, 2 3, 0 3, 0 2, 1 4, 1 3, 1 2);
}

/// Median (into lane 4) of 9 lanes made of 3 sorted columns (lane `3·dx + dy`).
#[inline(always)]
fn median9_sorted_columns<T: Sample, const L: usize>(v: &mut [[T; L]]) {
    // Max of the lows, median of the middles, min of the highs, then their median.
    network!(v; 0 3, 3 6, 2 5, 2 8, 1 4, 4 7, 1 4, 2 4, 4 6, 2 4);
}

/// Median (into lane 12) of 25 lanes made of 5 sorted columns (lane `5·dx + dy`): Batcher's
/// odd-even merge network for 32 inputs, restricted to 25 and pruned to the comparators that
/// can swap on sorted columns and that reach lane 12 (checked on all 6⁵ 0-1 inputs).
#[inline(always)]
fn median25_sorted_columns<T: Sample, const L: usize>(v: &mut [[T; L]]) {
    network!(v;
        4 5, 14 15, 5 7, 8 10, 9 11, 12 14, 5 6, 9 10, 13 14, 0 4, 1 5, 2 6, 8 12, 10 14, 11 15,
        16 20, 17 21, 18 22, 19 23, 2 4, 3 5, 10 12, 11 13, 18 20, 19 21, 1 2, 3 4, 5 6, 9 10,
        11 12, 13 14, 17 18, 19 20, 21 22, 0 8, 1 9, 2 10, 3 11, 4 12, 5 13, 6 14, 7 15, 4 8,
        5 9, 6 10, 7 11, 20 24, 2 4, 3 5, 6 8, 7 9, 10 12, 11 13, 22 24, 1 2, 3 4, 5 6, 7 8,
        9 10, 11 12, 13 14, 21 22, 23 24, 0 16, 1 17, 2 18, 3 19, 4 20, 5 21, 6 22, 7 23, 8 24,
        8 16, 9 17, 10 18, 11 19, 12 20, 13 21, 6 10, 7 11, 12 16, 13 17, 10 12, 11 13, 11 12,
    );
}

/// `L` samples of `data` from `start` (zeros past the end).
#[inline(always)]
fn load<T: Sample, const L: usize>(data: &[T], start: usize) -> [T; L] {
    let mut lane = [T::default(); L];
    if let Some(src) = data.get(start..start + L) {
        lane.copy_from_slice(src);
    }
    lane
}

/// Network median (ksize 3 or 5) of an image, `L` samples per comparator.
fn network<T: Sample, const L: usize>(
    src: &[T],
    g: &Geometry,
    constant: T,
) -> Result<Vec<T>, String> {
    match g.ksize {
        3 => Ok(network_bands::<T, L, 3, 9>(src, g, constant)),
        5 => Ok(network_bands::<T, L, 5, 25>(src, g, constant)),
        k => Err(format!("the network median takes ksize 3 or 5, got {k}")),
    }
}

fn network_bands<T: Sample, const L: usize, const K: usize, const KK: usize>(
    src: &[T],
    g: &Geometry,
    constant: T,
) -> Vec<T> {
    let c = g.channels;
    let n = g.width * c;
    let mut dst = vec![T::default(); src.len()];
    if n == 0 {
        return dst;
    }
    dst.par_chunks_mut(BAND_ROWS * n)
        .enumerate()
        .for_each(|(b, out)| {
            let rows = out.len() / n;
            let padded = pad_band(src, g, b * BAND_ROWS, rows, constant, L);
            let stride = padded.stride;
            // Column-sorted copies of the K rows of the current window, with slack for reads
            // past the end.
            let mut sorted = vec![vec![T::default(); stride + L]; K];
            for (i, line) in out.chunks_exact_mut(n).enumerate() {
                let base = i * stride;
                for s in (0..stride).step_by(L) {
                    let mut v = [[T::default(); L]; K];
                    for (dy, lane) in v.iter_mut().enumerate() {
                        *lane = load(&padded.data, base + dy * stride + s);
                    }
                    if K == 3 {
                        sort3(&mut v);
                    } else {
                        sort5(&mut v);
                    }
                    for (row, lane) in sorted.iter_mut().zip(&v) {
                        if let Some(dst) = row.get_mut(s..s + L) {
                            dst.copy_from_slice(lane);
                        }
                    }
                }
                for s in (0..n).step_by(L) {
                    let mut v = [[T::default(); L]; KK];
                    for dx in 0..K {
                        for dy in 0..K {
                            if let (Some(row), Some(lane)) =
                                (sorted.get(dy), v.get_mut(dx * K + dy))
                            {
                                *lane = load(row, s + dx * c);
                            }
                        }
                    }
                    let m = if K == 3 {
                        median9_sorted_columns(&mut v);
                        v[4]
                    } else {
                        median25_sorted_columns(&mut v);
                        v[12]
                    };
                    let end = (s + L).min(n);
                    if let Some(dst) = line.get_mut(s..end) {
                        dst.copy_from_slice(&m[..end - s]);
                    }
                }
            }
        });
    dst
}

/// Perreault & Hébert constant-time median of one band of a u8 image, channel by channel.
fn histogram_band(padded: &Padded<u8>, g: &Geometry, out: &mut [u8]) {
    let (k, c, w) = (g.ksize, g.channels, g.width);
    let n = w * c;
    let pw = w + k - 1;
    let rows = out.len() / n;
    let half = (k * k / 2) as u16;
    // Column histograms: coarse[x·16 + hi], fine[(hi·pw + x)·16 + lo] for sample 16·hi + lo.
    let mut coarse = vec![0u16; pw * 16];
    let mut fine = vec![0u16; 16 * pw * 16];
    for ch in 0..c {
        coarse.fill(0);
        fine.fill(0);
        for row in 0..k {
            update_columns(padded, c, ch, pw, row, true, &mut coarse, &mut fine);
        }
        for i in 0..rows {
            if i > 0 {
                update_columns(padded, c, ch, pw, i - 1, false, &mut coarse, &mut fine);
                update_columns(padded, c, ch, pw, i + k - 1, true, &mut coarse, &mut fine);
            }
            let line = &mut out[i * n..(i + 1) * n];
            let mut kc = [0u16; 16];
            for x in 0..k {
                add16(&mut kc, &coarse[x * 16..x * 16 + 16]);
            }
            let mut kf = [[0u16; 16]; 16];
            // Window start column each fine segment is valid for; usize::MAX: never built.
            let mut valid = [usize::MAX; 16];
            for x in 0..w {
                if x > 0 {
                    add16(&mut kc, &coarse[(x + k - 1) * 16..(x + k) * 16]);
                    sub16(&mut kc, &coarse[(x - 1) * 16..x * 16]);
                }
                let mut below = 0u16;
                let mut hi = 0;
                while hi < 15 && below + kc[hi] <= half {
                    below += kc[hi];
                    hi += 1;
                }
                let segment = &mut kf[hi];
                let columns = &fine[hi * pw * 16..(hi + 1) * pw * 16];
                let from = valid[hi];
                if from == usize::MAX || x - from >= k {
                    *segment = [0; 16];
                    for col in x..x + k {
                        add16(segment, &columns[col * 16..col * 16 + 16]);
                    }
                } else {
                    for col in from..x {
                        add16(segment, &columns[(col + k) * 16..(col + k + 1) * 16]);
                        sub16(segment, &columns[col * 16..col * 16 + 16]);
                    }
                }
                valid[hi] = x;
                let mut lo = 0;
                while lo < 15 && below + segment[lo] <= half {
                    below += segment[lo];
                    lo += 1;
                }
                line[x * c + ch] = (hi * 16 + lo) as u8;
            }
        }
    }
}

/// Adds (or removes) padded row `row` of channel `ch` to the column histograms.
#[allow(clippy::too_many_arguments)]
fn update_columns(
    padded: &Padded<u8>,
    c: usize,
    ch: usize,
    pw: usize,
    row: usize,
    add: bool,
    coarse: &mut [u16],
    fine: &mut [u16],
) {
    let stride = padded.stride;
    let Some(line) = padded.data.get(row * stride..(row + 1) * stride) else {
        return;
    };
    for (x, pixel) in line.chunks_exact(c).enumerate() {
        let v = pixel.get(ch).copied().unwrap_or(0) as usize;
        let (hi, lo) = (v >> 4, v & 15);
        if let (Some(cb), Some(fb)) = (
            coarse.get_mut(x * 16 + hi),
            fine.get_mut((hi * pw + x) * 16 + lo),
        ) {
            if add {
                *cb = cb.wrapping_add(1);
                *fb = fb.wrapping_add(1);
            } else {
                *cb = cb.wrapping_sub(1);
                *fb = fb.wrapping_sub(1);
            }
        }
    }
}

#[inline(always)]
fn add16(acc: &mut [u16; 16], x: &[u16]) {
    for (a, &b) in acc.iter_mut().zip(x) {
        *a = a.wrapping_add(b);
    }
}

#[inline(always)]
fn sub16(acc: &mut [u16; 16], x: &[u16]) {
    for (a, &b) in acc.iter_mut().zip(x) {
        *a = a.wrapping_sub(b);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::{MODES, random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    fn gray(w: usize, h: usize, data: Vec<u8>) -> Image {
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    /// The definition: sort the window (read through `map_index`), take the middle.
    fn naive(img: &Image, k: usize, border: BorderMode, value: f64) -> Vec<f64> {
        let (w, h, c) = (img.width(), img.height(), img.channels().count());
        let s: Vec<f64> = match img.data() {
            PixelData::U8(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::U16(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::F32(d) => d.iter().map(|&x| x as f64).collect(),
        };
        let constant = match img.data() {
            PixelData::U8(_) => u8::saturate(value) as f64,
            PixelData::U16(_) => u16::saturate(value) as f64,
            PixelData::F32(_) => value as f32 as f64,
        };
        let r = (k / 2) as isize;
        let mut out = vec![0.0; s.len()];
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let mut win = Vec::new();
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let yy = super::super::border::map_index(y as isize + dy, h, border);
                            let xx = super::super::border::map_index(x as isize + dx, w, border);
                            win.push(match (yy, xx) {
                                (Some(yy), Some(xx)) => s[(yy * w + xx) * c + ch],
                                _ => constant,
                            });
                        }
                    }
                    win.sort_by(f64::total_cmp);
                    out[(y * w + x) * c + ch] = win[win.len() / 2];
                }
            }
        }
        out
    }

    fn samples(img: &Image) -> Vec<f64> {
        match img.data() {
            PixelData::U8(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::U16(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::F32(d) => d.iter().map(|&x| x as f64).collect(),
        }
    }

    fn random_image(w: usize, h: usize, channels: Channels, depth: u8, seed: u64) -> Image {
        let n = w * h * channels.count();
        let r = randoms(seed, n);
        match depth {
            0 => random_u8(w, h, channels, seed),
            1 => Image::from_u16(
                w,
                h,
                channels,
                r.iter().map(|x| (x * 65536.0) as u16).collect(),
            )
            .unwrap(),
            _ => Image::from_f32(
                w,
                h,
                channels,
                r.iter().map(|x| (*x as f32) * 2.0 - 1.0).collect(),
            )
            .unwrap(),
        }
    }

    #[test]
    fn hand_made_3x3() {
        // The centre window holds 9 1 8 / 2 7 3 / 6 4 5: sorted 1..9, median 5.
        let img = gray(3, 3, vec![9, 1, 8, 2, 7, 3, 6, 4, 5]);
        let out = median_blur(&img, 3, BorderMode::Clamp, 0.0);
        assert_eq!(out.as_u8().unwrap()[4], 5);
        // Corner (0, 0) with clamp reads 9 9 1 / 9 9 1 / 2 2 7: sorted 1 1 2 2 7 9 9 9 9 → 7.
        assert_eq!(out.as_u8().unwrap()[0], 7);
        // Constant 0 border: corner window 0 0 0 / 0 9 1 / 0 2 7 → 0.
        let out = median_blur(&img, 3, BorderMode::Constant, 0.0);
        assert_eq!(out.as_u8().unwrap()[0], 0);
    }

    #[test]
    fn constant_image_is_unchanged() {
        for k in [3, 5, 7, 15] {
            for depth in 0..3 {
                let img = match depth {
                    0 => Image::from_u8(23, 17, Channels::Rgb, vec![77; 23 * 17 * 3]).unwrap(),
                    1 => Image::from_u16(23, 17, Channels::Rgb, vec![4000; 23 * 17 * 3]).unwrap(),
                    _ => Image::from_f32(23, 17, Channels::Rgb, vec![0.25; 23 * 17 * 3]).unwrap(),
                };
                for border in MODES.into_iter().filter(|&b| b != BorderMode::Constant) {
                    assert_eq!(median_blur(&img, k, border, 0.0), img, "k {k} {border:?}");
                }
            }
        }
    }

    #[test]
    fn monotone_ramp_rows_are_fixed_points() {
        // Each row is a monotone ramp and all rows are equal: every window's median is the
        // centre column's value.
        let w = 40;
        let data: Vec<u8> = (0..12)
            .flat_map(|_| (0..w).map(|x| (x * 6) as u8))
            .collect();
        let img = gray(w, 12, data);
        for k in [3, 5, 7, 9, 15] {
            assert_eq!(median_blur(&img, k, BorderMode::Clamp, 0.0), img, "k {k}");
        }
    }

    #[test]
    fn all_methods_match_the_definition() {
        for (channels, seed) in [(Channels::Gray, 1), (Channels::Rgb, 2), (Channels::Rgba, 3)] {
            for depth in 0..3 {
                let img = random_image(45, 38, channels, depth, seed);
                for k in [3, 5, 7, 9, 15] {
                    for border in MODES {
                        let value = if border == BorderMode::Constant {
                            100.0
                        } else {
                            0.0
                        };
                        let want = naive(&img, k, border, value);
                        let mut methods = vec![MedianMethod::Sort];
                        if k <= 5 {
                            methods.push(MedianMethod::Network);
                        }
                        if depth == 0 {
                            methods.push(MedianMethod::Histogram);
                        }
                        for m in methods {
                            let got = median_blur_with(&img, k, border, value, m).unwrap();
                            assert_eq!(
                                samples(&got),
                                want,
                                "{channels:?} d{depth} k{k} {border:?} {m:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn matches_opencv_median_blur() {
        // cv2.medianBlur on a 9×6 gray image with samples (x·37 + y·91 + x·y·13) mod 256.
        let (w, h) = (9, 6);
        let data: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91 + x * y * 13) % 256) as u8))
            .collect();
        let img = gray(w, h, data);
        let want3: [u8; 54] = OPENCV_K3;
        let want5: [u8; 54] = OPENCV_K5;
        assert_eq!(
            median_blur(&img, 3, BorderMode::Clamp, 0.0)
                .as_u8()
                .unwrap(),
            &want3
        );
        assert_eq!(
            median_blur(&img, 5, BorderMode::Clamp, 0.0)
                .as_u8()
                .unwrap(),
            &want5
        );
    }

    const OPENCV_K3: [u8; 54] = [
        37, 74, 111, 111, 148, 148, 185, 135, 40, 91, 91, 115, 115, 148, 148, 135, 135, 174, 93,
        141, 169, 169, 141, 135, 135, 135, 174, 108, 108, 119, 119, 141, 141, 130, 113, 113, 108,
        108, 147, 147, 141, 130, 141, 130, 113, 197, 147, 147, 147, 197, 95, 145, 145, 219,
    ];
    const OPENCV_K5: [u8; 54] = [
        52, 74, 111, 115, 148, 148, 148, 135, 48, 74, 91, 111, 141, 148, 141, 141, 135, 113, 91,
        108, 115, 141, 135, 135, 135, 130, 113, 108, 141, 141, 141, 135, 135, 135, 141, 145, 147,
        147, 147, 147, 141, 141, 141, 145, 145, 147, 147, 147, 147, 147, 145, 141, 145, 145,
    ];

    #[test]
    fn tiny_empty_and_errors() {
        let one = gray(1, 1, vec![9]);
        for k in [1, 3, 5, 7, 31] {
            assert_eq!(median_blur(&one, k, BorderMode::Reflect101, 0.0), one);
        }
        let empty = gray(0, 0, vec![]);
        assert_eq!(median_blur(&empty, 5, BorderMode::Clamp, 0.0), empty);
        let img = random_image(8, 8, Channels::Gray, 1, 4);
        assert!(median_blur_with(&img, 7, BorderMode::Clamp, 0.0, MedianMethod::Network).is_err());
        assert!(
            median_blur_with(&img, 7, BorderMode::Clamp, 0.0, MedianMethod::Histogram).is_err()
        );
        assert!(median_blur_with(&img, 4, BorderMode::Clamp, 0.0, MedianMethod::Sort).is_err());
        for (ksize, ok) in [(0, false), (2, false), (1, true), (255, true), (257, false)] {
            let p = MedianParams {
                ksize,
                ..MedianParams::default()
            };
            assert_eq!(Median::new(p).is_ok(), ok, "ksize {ksize}");
        }
        let p = MedianParams {
            border_value: f64::NAN,
            border: BorderMode::Constant,
            ..MedianParams::default()
        };
        assert!(Median::new(p).is_err());
    }

    #[test]
    fn identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_u8(97, 131, Channels::Rgb, 8);
        for k in [3, 5, 9] {
            let run = || median_blur(&img, k, BorderMode::Reflect, 0.0);
            assert_eq!(pool(1).install(run), pool(3).install(run));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn fast_paths_equal_sorting(
            w in 1usize..70,
            h in 1usize..40,
            k in prop::sample::select(vec![3usize, 5, 7, 11]),
            channels in prop::sample::select(vec![Channels::Gray, Channels::Rgb, Channels::Rgba]),
            depth in 0u8..3,
            border in prop::sample::select(MODES.to_vec()),
            seed in any::<u64>(),
        ) {
            let img = random_image(w, h, channels, depth, seed);
            let want = median_blur_with(&img, k, border, 0.0, MedianMethod::Sort).unwrap();
            prop_assert_eq!(median_blur(&img, k, border, 0.0), want);
        }
    }
}
