//! `filter.median`: the median of every square window, per channel, with OpenCV's `medianBlur`
//! semantics.
//!
//! Three methods, chosen by [`MedianMethod::auto`]:
//! - **Network** (ksize 3 and 5, every depth): comparator networks applied to many samples at
//!   once. 3×3: for each output row the 3 source rows are sorted column-wise (3 comparators per
//!   column, shared by the 3 windows that contain the column), then 10 comparators select the
//!   median of a window's 3 sorted columns (max of the lows, median of the middles, min of the
//!   highs, then their median). 5×5: every source row is sorted horizontally in runs of 5
//!   (9 comparators, once per row); two vertically adjacent windows share 4 of their 5 runs, a
//!   network of 51 comparators finds the only 6 ranks of those 20 samples that can be a median,
//!   and each window's median then takes 10 more comparators with its own run (see
//!   `network_band5`): 71 comparators per two outputs where a plain pruned 25-input network
//!   needs 85 per output. The networks are Batcher's odd-even merge sort pruned with the 0-1
//!   principle over all sorted-run inputs to the comparators that can swap and that reach the
//!   wanted ranks. Each comparator is an element-wise min/max over an array of samples (32 u8,
//!   16 u16 or 8 f32) so that it compiles to SIMD min/max instructions. The lanes of a network
//!   are built from an array literal and indexed by constants only, so the compiler keeps them
//!   in registers; the band kernels are compiled for AVX2 and SSE4.1 as well and picked at run
//!   time. Interleaved channels need no special case: the neighbours of a sample are `c`
//!   samples apart, so each lane holds consecutive samples of a row and the shifted loads are
//!   offsets of `c`.
//! - **Histogram** (u8, ksize ≥ 7): the constant-time method of Perreault & Hébert: per-column
//!   histograms (updated by one row in and one row out per output row) and a kernel histogram
//!   (one column in and one column out per output pixel), both with 16 coarse bins of 16 fine
//!   bins. The coarse level finds the 16-level range of the median; the fine histogram of that
//!   range is brought up to date lazily from the column histograms (or rebuilt when it is older
//!   than the window). The cost per pixel does not depend on `ksize`.
//! - **Sort** (every other case: u16 and f32 with ksize ≥ 7): gathers each window and selects
//!   the middle sample (`select_nth_unstable`), O(k²) per sample.
//!
//! Crossover, measured on a 1080p gray u8 image, one thread (rough): network 1.6 ms (5×5, the
//! `opencv_table` bench; OpenCV's `medianBlur` takes 1.7 ms there); histogram about 85 ms for every ksize from 3 to 15; sort 170 ms
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
    pad_band_into(src, g, y0, rows, constant, slack, Vec::new())
}

/// [`pad_band`] into a reused buffer.
fn pad_band_into<T: Sample>(
    src: &[T],
    g: &Geometry,
    y0: usize,
    rows: usize,
    constant: T,
    slack: usize,
    mut data: Vec<T>,
) -> Padded<T> {
    let n = g.width * g.channels;
    let stride = g.columns.padded_len() * g.channels;
    let total = rows + g.ksize - 1;
    // Every row is written below; a reused buffer of the right length keeps its slack, which
    // only feeds lanes past the row ends that are never stored.
    if data.len() != total * stride + slack {
        data.clear();
        data.resize(total * stride + slack, constant);
    }
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
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
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
///
/// `v` is a fixed-size array indexed by constants only (the networks below) and built from an
/// array literal, so that the compiler keeps its lanes in SIMD registers rather than in memory.
/// The element loops (not `array::from_fn`) are what LLVM turns into one SIMD min and max.
#[inline(always)]
fn cas<T: Sample, const L: usize, const N: usize>(v: &mut [[T; L]; N], a: usize, b: usize) {
    let (x, y) = (v[a], v[b]);
    v[a] = lane_min(x, y);
    v[b] = lane_max(x, y);
}

/// Element-wise minimum of two lanes.
#[inline(always)]
fn lane_min<T: Sample, const L: usize>(x: [T; L], y: [T; L]) -> [T; L] {
    let mut out = [T::default(); L];
    for ((o, &a), &b) in out.iter_mut().zip(&x).zip(&y) {
        *o = T::lo(a, b);
    }
    out
}

/// Element-wise maximum of two lanes.
#[inline(always)]
fn lane_max<T: Sample, const L: usize>(x: [T; L], y: [T; L]) -> [T; L] {
    let mut out = [T::default(); L];
    for ((o, &a), &b) in out.iter_mut().zip(&x).zip(&y) {
        *o = T::hi(a, b);
    }
    out
}

macro_rules! network {
    ($v:expr; $($a:literal $b:literal),* $(,)?) => {
        $( cas($v, $a, $b); )*
    };
}

/// Sorts 3 lanes.
#[inline(always)]
fn sort3<T: Sample, const L: usize>(v: &mut [[T; L]; 3]) {
    network!(v; 0 1, 1 2, 0 1);
}

/// Sorts 5 lanes (9 comparators, optimal).
#[inline(always)]
fn sort5<T: Sample, const L: usize>(v: &mut [[T; L]; 5]) {
    network!(v; 0 1, 3 4, 2 4, 2 3, 0 3, 0 2, 1 4, 1 3, 1 2);
}

/// Median (into lane 4) of 9 lanes made of 3 sorted columns (lane `3·dx + dy`).
#[inline(always)]
fn median9_sorted_columns<T: Sample, const L: usize>(v: &mut [[T; L]; 9]) {
    // Max of the lows, median of the middles, min of the highs, then their median.
    network!(v; 0 3, 3 6, 2 5, 2 8, 1 4, 4 7, 1 4, 2 4, 4 6, 2 4);
}

/// `L` samples of `data` from `start` (zeros past the end; the callers' slices are long
/// enough, so the fallback is never taken and compiles away).
#[inline(always)]
fn load<T: Sample, const L: usize>(data: &[T], start: usize) -> [T; L] {
    match data.get(start..start + L).map(<[T; L]>::try_from) {
        Some(Ok(lane)) => lane,
        _ => [T::default(); L],
    }
}

/// Network median (ksize 3 or 5) of an image, `L` samples per comparator.
fn network<T: Sample, const L: usize>(
    src: &[T],
    g: &Geometry,
    constant: T,
) -> Result<Vec<T>, String> {
    if g.ksize != 3 && g.ksize != 5 {
        return Err(format!(
            "the network median takes ksize 3 or 5, got {}",
            g.ksize
        ));
    }
    let c = g.channels;
    let n = g.width * c;
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
    if n == 0 {
        return Ok(dst);
    }
    // Scratch buffers (padded rows, sorted runs) are reused across the bands a worker takes.
    dst.par_chunks_mut(BAND_ROWS * n).enumerate().for_each_init(
        || (Vec::new(), Vec::new()),
        |(pad_buffer, runs), (b, out)| {
            let rows = out.len() / n;
            if g.ksize == 3 {
                let buffer = std::mem::take(pad_buffer);
                let padded = pad_band_into(src, g, b * BAND_ROWS, rows, constant, L, buffer);
                network_band3::<T, L>(&padded, c, n, out);
                *pad_buffer = padded.data;
            } else {
                let source = SourceRows {
                    src,
                    g,
                    y0: b * BAND_ROWS,
                    constant,
                };
                network_band5::<T, L>(&source, n, out, pad_buffer, runs);
            }
        },
    );
    Ok(dst)
}

/// 3×3 network median of one band: for each output row the 3 source rows are sorted
/// column-wise into `sorted` (shared by the 3 windows containing each column), then the median
/// of every window's 3 sorted columns is selected.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn network_band3<T: Sample, const L: usize>(padded: &Padded<T>, c: usize, n: usize, out: &mut [T]) {
    let stride = padded.stride;
    let width = stride + L;
    let mut sorted = vec![T::default(); 3 * width];
    for (i, line) in out.chunks_exact_mut(n).enumerate() {
        let Some(rows) = padded.data.get(i * stride..) else {
            return;
        };
        {
            let (s0, rest) = sorted.split_at_mut(width);
            let (s1, s2) = rest.split_at_mut(width);
            for (s, ((d0, d1), d2)) in (0..stride).step_by(L).zip(
                s0.chunks_exact_mut(L)
                    .zip(s1.chunks_exact_mut(L))
                    .zip(s2.chunks_exact_mut(L)),
            ) {
                let mut v: [[T; L]; _] = [
                    load(rows, s),
                    load(rows, stride + s),
                    load(rows, 2 * stride + s),
                ];
                sort3(&mut v);
                d0.copy_from_slice(&v[0]);
                d1.copy_from_slice(&v[1]);
                d2.copy_from_slice(&v[2]);
            }
        }
        let span = L + 2 * c;
        for (s, o) in (0..n).step_by(L).zip(line.chunks_mut(L)) {
            let (Some(r0), Some(r1), Some(r2)) = (
                sorted.get(s..s + span),
                sorted.get(width + s..width + s + span),
                sorted.get(2 * width + s..2 * width + s + span),
            ) else {
                return;
            };
            let mut v: [[T; L]; _] = [
                load(r0, 0),
                load(r1, 0),
                load(r2, 0),
                load(r0, c),
                load(r1, c),
                load(r2, c),
                load(r0, 2 * c),
                load(r1, 2 * c),
                load(r2, 2 * c),
            ];
            median9_sorted_columns(&mut v);
            let k = o.len();
            o.copy_from_slice(&v[4][..k]);
        }
    }
}

/// 5×5 network median of one band, two output rows at a time.
///
/// Every padded source row is first sorted horizontally: the 5 samples `x, x+c, …, x+4c` of
/// each output position go, sorted, into 5 planes (9 comparators, once per source row). The
/// windows of output rows `y` and `y+1` share the sorted runs of source rows `y+1 … y+4`; of
/// their 20 samples only ranks 7 to 12 can be the median of a window that adds 5 more, and a
/// network of 51 comparators (Batcher's odd-even merge sort on 4 padded runs of 5, pruned with
/// the 0-1 principle over all sorted-run inputs to the comparators that can swap and that reach
/// those ranks) finds them. Each window's median is then rank 12 of those 6 (`m`) and its own
/// sorted run `r` of 5: `max(m₇, min(m₈, r₄), min(m₉, r₃), …, min(m₁₂, r₀))` (the k-th of two
/// sorted lists is the largest `min(mᵢ, rⱼ)` with `i + j = k`). 51 + 2·10 comparators for two
/// outputs instead of 2·85.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn network_band5<T: Sample, const L: usize>(
    source: &SourceRows<'_, T>,
    n: usize,
    out: &mut [T],
    line: &mut Vec<T>,
    runs: &mut Vec<T>,
) {
    let c = source.g.channels;
    let source_rows = out.len() / n + 4;
    // The band is processed in vertical strips of `STRIP_PX` output pixels so that the ring of
    // sorted runs and the padded row stay in the first-level caches.
    let strip = STRIP_PX * c;
    // Sorted runs of the last 6 source rows (a ring): source row `j`, rank `k` at
    // `(5·(j mod 6) + k)·plane`, with slack for whole-lane reads.
    let plane = strip + L;
    let row = 5 * plane;
    // Every slot is written before it is read; only a new buffer needs initializing.
    if runs.len() != 6 * row + L {
        runs.clear();
        runs.resize(6 * row + L, T::default());
    }
    // One padded strip of a source row at a time (its halo included), with slack for
    // whole-lane reads; the slack only feeds lanes that are never stored.
    if line.len() != strip + 4 * c + L {
        line.clear();
        line.resize(strip + 4 * c + L, source.constant);
    }
    for x0 in (0..n).step_by(strip) {
        let width = strip.min(n - x0);
        let padded_len = width + 4 * c;
        let mut sorted_rows = 0;
        for (pair, rows) in out.chunks_mut(2 * n).enumerate() {
            let y = 2 * pair;
            while sorted_rows < (y + 6).min(source_rows) {
                let slot = (sorted_rows % 6) * row;
                if let (Some(padded), Some(dst)) =
                    (line.get_mut(..padded_len), runs.get_mut(slot..slot + row))
                {
                    source.pad(sorted_rows, x0 / c, padded);
                    sort_runs5::<T, L>(line, c, width, dst, plane);
                }
                sorted_rows += 1;
            }
            let offsets: [usize; 6] = std::array::from_fn(|j| ((y + j) % 6) * row);
            let (first, second) = rows.split_at_mut(n.min(rows.len()));
            let first = first.get_mut(x0..x0 + width).unwrap_or_default();
            let second = second.get_mut(x0..x0 + width).unwrap_or_default();
            median_rows5::<T, L>(runs, offsets, plane, first, second);
        }
    }
}

/// Output pixels per vertical strip of the 5×5 network median.
const STRIP_PX: usize = 512;

/// The source rows a band reads, padded one strip at a time.
struct SourceRows<'a, T> {
    src: &'a [T],
    g: &'a Geometry,
    /// First output row of the band.
    y0: usize,
    constant: T,
}

impl<T: Sample> SourceRows<'_, T> {
    /// Pads the `j`-th source row of the band (image row `y0 + j − ksize/2`, through the row
    /// border table) into `dst`, from extended column `start` (pixels) on.
    #[inline]
    fn pad(&self, j: usize, start: usize, dst: &mut [T]) {
        let n = self.g.width * self.g.channels;
        match self
            .g
            .rows
            .source(self.y0 + j)
            .and_then(|r| self.src.get(r * n..(r + 1) * n))
        {
            Some(row) => self.g.columns.pad_range_with(
                row,
                self.g.channels,
                start,
                self.constant,
                dst,
                |v| v,
            ),
            None => dst.fill(self.constant),
        }
    }
}

/// Sorts the 5-sample horizontal runs (`c` apart) starting at each of the first `n` samples of
/// `row` into the 5 planes of `dst` (`plane` apart, smallest first).
#[inline(always)]
fn sort_runs5<T: Sample, const L: usize>(
    row: &[T],
    c: usize,
    n: usize,
    dst: &mut [T],
    plane: usize,
) {
    for s in (0..n).step_by(L) {
        let mut v: [[T; L]; 5] = [
            load(row, s),
            load(row, s + c),
            load(row, s + 2 * c),
            load(row, s + 3 * c),
            load(row, s + 4 * c),
        ];
        sort5(&mut v);
        for (k, lane) in v.iter().enumerate() {
            if let Some(d) = dst.get_mut(k * plane + s..k * plane + s + L) {
                d.copy_from_slice(lane);
            }
        }
    }
}

/// The 5×5 medians of output rows `y` (`first`) and `y + 1` (`second`, empty for the last row
/// of an odd band) from the sorted runs of source rows `y … y + 5`, at `offsets` in `runs`.
#[inline(always)]
fn median_rows5<T: Sample, const L: usize>(
    runs: &[T],
    offsets: [usize; 6],
    plane: usize,
    first: &mut [T],
    second: &mut [T],
) {
    let n = first.len();
    for s in (0..n).step_by(L) {
        let at = |j: usize, k: usize| load::<T, L>(runs, offsets[j] + k * plane + s);
        let mut v: [[T; L]; 20] = [
            at(1, 0),
            at(1, 1),
            at(1, 2),
            at(1, 3),
            at(1, 4),
            at(2, 0),
            at(2, 1),
            at(2, 2),
            at(2, 3),
            at(2, 4),
            at(3, 0),
            at(3, 1),
            at(3, 2),
            at(3, 3),
            at(3, 4),
            at(4, 0),
            at(4, 1),
            at(4, 2),
            at(4, 3),
            at(4, 4),
        ];
        ranks_7_to_12_of_four_runs(&mut v);
        let m = [v[8], v[5], v[9], v[12], v[13], v[14]];
        let k = (n - s).min(L);
        let own = [at(0, 0), at(0, 1), at(0, 2), at(0, 3), at(0, 4)];
        if let Some(d) = first.get_mut(s..s + k) {
            d.copy_from_slice(&rank12_of_six_and_run(&m, &own)[..k]);
        }
        if let Some(d) = second.get_mut(s..s + k) {
            let own = [at(5, 0), at(5, 1), at(5, 2), at(5, 3), at(5, 4)];
            d.copy_from_slice(&rank12_of_six_and_run(&m, &own)[..k]);
        }
    }
}

/// Ranks 7 to 12 of 20 lanes made of 4 sorted runs of 5 (lane `5·run + rank`), left in lanes
/// 8, 5, 9, 12, 13 and 14 (in that order; the network relabels instead of swapping wires).
#[inline(always)]
fn ranks_7_to_12_of_four_runs<T: Sample, const L: usize>(v: &mut [[T; L]; 20]) {
    network!(v;
        0 5, 1 6, 2 7, 3 8, 4 9, 10 15, 11 16, 12 17, 13 18, 14 19, 4 5, 14 15, 2 4, 3 6, 7 5,
        12 14, 13 16, 17 15, 1 2, 3 4, 6 7, 8 5, 11 12, 13 14, 16 17, 18 15, 0 10, 1 11, 2 12,
        3 13, 4 14, 6 16, 7 17, 8 18, 5 15, 9 19, 5 10, 9 11, 4 5, 6 9, 7 12, 8 13, 14 10, 16 11,
        7 5, 8 9, 12 14, 13 16, 8 5, 9 12, 13 14,
    );
}

/// Rank 12 (the median of 25) of the union of `m` (ranks 7 to 12 of 20 samples, sorted) and a
/// sorted run `r` of 5 more.
#[inline(always)]
fn rank12_of_six_and_run<T: Sample, const L: usize>(m: &[[T; L]; 6], r: &[[T; L]; 5]) -> [T; L] {
    let a = lane_max(m[0], lane_min(m[1], r[4]));
    let b = lane_max(lane_min(m[2], r[3]), lane_min(m[3], r[2]));
    let d = lane_max(lane_min(m[4], r[1]), lane_min(m[5], r[0]));
    lane_max(lane_max(a, b), d)
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
