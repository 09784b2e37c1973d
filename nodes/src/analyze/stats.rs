//! `analyze.stats`: per-channel minimum, maximum, mean, standard deviation and non-zero count
//! of an image or a rectangle of it.
//!
//! The algorithm is [`channel_stats`]; [`Stats`] is the thin operator around it.
//!
//! # Determinism and accuracy
//!
//! The measured pixels are cut into chunks of [`CHUNK_PIXELS`] (a constant, never derived from
//! the thread count), reduced in parallel, and the chunk results are combined in chunk order, so
//! the result is bit-identical for any number of threads.
//!
//! - Integer images (u8, u16): sums and sums of squares are exact integers, so the mean and the
//!   variance `(n·Σx² − (Σx)²) / n²` are rounded once, at the end.
//! - f32 images: each chunk makes two passes in f64, the mean and then the corrected two-pass
//!   sum of squared deviations `Σd² − (Σd)²/n` with `d = x − mean` (Chan, Golub & LeVeque 1983);
//!   chunks are merged with Chan et al.'s pairwise update. This stays accurate when the values
//!   sit on a large offset (e.g. 10⁶ + noise), where the one-pass `E[x²] − E[x]²` loses every
//!   digit.

use std::ops::Range;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, PixelData, Value};
use rayon::prelude::*;

/// Pixels per reduction chunk. A constant so the split (and with it every floating-point
/// rounding) is the same whatever the thread count.
pub const CHUNK_PIXELS: usize = 1 << 16;

/// Lanes of the 32-bit and narrower accumulators: sample `i` of a run goes to lane `i % LANES`.
/// A multiple of 1, 3 and 4, so lane `j` always holds channel `j % channels` (runs start on a
/// pixel boundary).
const LANES: usize = 48;

/// Lanes of the f64 accumulators: fewer, so they fit in registers. Also a multiple of 1, 3, 4.
const WIDE_LANES: usize = 12;

/// A rectangle of pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    /// Column of the left edge, pixels.
    pub x: usize,
    /// Row of the top edge, pixels.
    pub y: usize,
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
}

impl Roi {
    /// The whole of a `width × height` image.
    pub fn full(width: usize, height: usize) -> Roi {
        Roi {
            x: 0,
            y: 0,
            width,
            height,
        }
    }

    /// True when the rectangle lies inside a `width × height` image (an empty rectangle on the
    /// image's edge counts as inside).
    pub fn fits(&self, width: usize, height: usize) -> bool {
        self.x.checked_add(self.width).is_some_and(|r| r <= width)
            && self.y.checked_add(self.height).is_some_and(|b| b <= height)
    }
}

/// Errors measuring an image.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StatsError {
    /// The region reaches outside the image.
    #[error(
        "roi [{x}, {y}, {w}, {h}] (x, y, width, height) does not fit in the {width}×{height} image",
        x = roi.x, y = roi.y, w = roi.width, h = roi.height
    )]
    RoiOutside {
        /// The region asked for.
        roi: Roi,
        /// Image width, pixels.
        width: usize,
        /// Image height, pixels.
        height: usize,
    },
}

/// Minimum, maximum, mean and population standard deviation of a channel's samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Summary {
    /// Smallest sample.
    pub min: f64,
    /// Largest sample.
    pub max: f64,
    /// Arithmetic mean.
    pub mean: f64,
    /// Population standard deviation `√(Σ(x − mean)² / n)`.
    pub std: f64,
}

/// Statistics of one channel, in the image's native units (0..255 for u8, 0..65535 for u16).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelStats {
    /// Samples that entered [`Summary`]: all of them for integer images, the finite ones for f32.
    pub count: u64,
    /// Samples `≠ 0` (for f32, NaN and ±∞ count as non-zero, as `x != 0.0` says).
    pub nonzero: u64,
    /// NaN samples (always 0 for integer images).
    pub nan: u64,
    /// +∞ and −∞ samples (always 0 for integer images).
    pub inf: u64,
    /// `None` when `count == 0` (empty region, or only NaN/∞ samples).
    pub summary: Option<Summary>,
}

/// Per-channel statistics of `image` inside `roi` (the whole image when `None`), in channel
/// order. Deterministic for any thread count (see the module docs).
pub fn channel_stats(image: &Image, roi: Option<Roi>) -> Result<Vec<ChannelStats>, StatsError> {
    let (width, height) = (image.width(), image.height());
    let roi = roi.unwrap_or(Roi::full(width, height));
    if !roi.fits(width, height) {
        return Err(StatsError::RoiOutside { roi, width, height });
    }
    let region = Region {
        roi,
        image_width: width,
        channels: image.channels().count(),
    };
    Ok(match image.data() {
        PixelData::U8(samples) => integer_stats(samples, &region),
        PixelData::U16(samples) => integer_stats(samples, &region),
        PixelData::F32(samples) => float_stats(samples, &region),
    })
}

/// Channel names used in metric keys: `gray`, or `r`, `g`, `b`, `a`.
pub fn channel_names(channels: Channels) -> &'static [&'static str] {
    match channels {
        Channels::Gray => &["gray"],
        Channels::Rgb => &["r", "g", "b"],
        Channels::Rgba => &["r", "g", "b", "a"],
    }
}

/// The statistics as metrics (see [`Stats`] for the keys).
pub fn stats_metrics(image: &Image, roi: Option<Roi>) -> Result<Metrics, StatsError> {
    let stats = channel_stats(image, roi)?;
    let roi = roi.unwrap_or(Roi::full(image.width(), image.height()));
    let mut metrics = Metrics::new();
    metrics.insert("width".into(), roi.width as f64);
    metrics.insert("height".into(), roi.height as f64);
    metrics.insert("channels".into(), image.channels().count() as f64);
    for (name, s) in channel_names(image.channels()).iter().zip(&stats) {
        metrics.insert(format!("{name}.nonzero"), s.nonzero as f64);
        if let Some(summary) = s.summary {
            metrics.insert(format!("{name}.min"), summary.min);
            metrics.insert(format!("{name}.max"), summary.max);
            metrics.insert(format!("{name}.mean"), summary.mean);
            metrics.insert(format!("{name}.std"), summary.std);
        }
    }
    if matches!(image.data(), PixelData::F32(_)) {
        let nan: u64 = stats.iter().map(|s| s.nan).sum();
        let inf: u64 = stats.iter().map(|s| s.inf).sum();
        metrics.insert("nan_count".into(), nan as f64);
        metrics.insert("inf_count".into(), inf as f64);
    }
    Ok(metrics)
}

/// The measured rectangle and how it sits in the sample buffer.
struct Region {
    roi: Roi,
    image_width: usize,
    channels: usize,
}

impl Region {
    fn pixels(&self) -> usize {
        self.roi.width * self.roi.height
    }

    fn chunks(&self) -> usize {
        self.pixels().div_ceil(CHUNK_PIXELS)
    }

    /// Calls `f` with each contiguous run of samples of the region's pixels `start..end`
    /// (counted row-major inside the region), in order.
    fn for_each_run(&self, pixels: Range<usize>, mut f: impl FnMut(Range<usize>)) {
        let c = self.channels;
        let Roi { x, y, width, .. } = self.roi;
        if width == self.image_width {
            // Whole rows: the region is one contiguous block.
            let base = y * self.image_width * c;
            f(base + pixels.start * c..base + pixels.end * c);
            return;
        }
        let mut p = pixels.start;
        while p < pixels.end {
            let (row, col) = (p / width, p % width);
            let len = (width - col).min(pixels.end - p);
            let first = ((y + row) * self.image_width + x + col) * c;
            f(first..first + len * c);
            p += len;
        }
    }
}

// A lane receives at most one sample per pixel of a chunk (lane `j` holds one channel), so
// 32-bit lanes hold the sums of u8 and u16 samples and the squares of u8 samples.
const _: () = assert!(CHUNK_PIXELS as u64 * 65535 <= u32::MAX as u64);
const _: () = assert!(CHUNK_PIXELS as u64 * 255 * 255 <= u32::MAX as u64);

/// Integer sample types.
trait IntSample: Copy + Ord + Send + Sync + Into<u64> {
    /// Per-lane accumulator of squares over a chunk.
    type Square: Copy + Default + Send + std::ops::AddAssign + Into<u64>;
    const MAX: Self;
    const MIN: Self;
    fn is_zero(self) -> bool;
    fn square(self) -> Self::Square;
    fn widen(self) -> u32;
}

impl IntSample for u8 {
    type Square = u32;
    const MAX: u8 = u8::MAX;
    const MIN: u8 = 0;
    fn is_zero(self) -> bool {
        self == 0
    }
    fn square(self) -> u32 {
        u32::from(self) * u32::from(self)
    }
    fn widen(self) -> u32 {
        u32::from(self)
    }
}

impl IntSample for u16 {
    type Square = u64;
    const MAX: u16 = u16::MAX;
    const MIN: u16 = 0;
    fn is_zero(self) -> bool {
        self == 0
    }
    fn square(self) -> u64 {
        u64::from(self) * u64::from(self)
    }
    fn widen(self) -> u32 {
        u32::from(self)
    }
}

/// Exact moments of one channel over some samples.
#[derive(Debug, Clone, Copy)]
struct IntMoments<T> {
    count: u64,
    nonzero: u64,
    sum: u128,
    sum_sq: u128,
    min: T,
    max: T,
}

impl<T: IntSample> IntMoments<T> {
    fn empty() -> Self {
        IntMoments {
            count: 0,
            nonzero: 0,
            sum: 0,
            sum_sq: 0,
            min: T::MAX,
            max: T::MIN,
        }
    }

    /// Exact, so the order of merging does not matter; chunks are still merged in order.
    fn merge(&mut self, other: &Self) {
        self.count += other.count;
        self.nonzero += other.nonzero;
        self.sum += other.sum;
        self.sum_sq += other.sum_sq;
        self.min = self.min.min(other.min);
        self.max = self.max.max(other.max);
    }

    fn finish(&self) -> ChannelStats {
        let summary = (self.count > 0).then(|| {
            let n = u128::from(self.count);
            // n·Σx² − (Σx)² = n·Σ(x − mean)² ≥ 0, exactly.
            let spread = n * self.sum_sq - self.sum * self.sum;
            let n = self.count as f64;
            let (min, max): (u64, u64) = (self.min.into(), self.max.into());
            Summary {
                min: min as f64,
                max: max as f64,
                mean: self.sum as f64 / n,
                std: (spread as f64).sqrt() / n,
            }
        });
        ChannelStats {
            count: self.count,
            nonzero: self.nonzero,
            nan: 0,
            inf: 0,
            summary,
        }
    }
}

fn integer_stats<T: IntSample>(samples: &[T], region: &Region) -> Vec<ChannelStats> {
    let c = region.channels;
    let chunks: Vec<Vec<IntMoments<T>>> = (0..region.chunks())
        .into_par_iter()
        .map(|k| integer_chunk(samples, region, k))
        .collect();
    let mut total = vec![IntMoments::<T>::empty(); c];
    for chunk in &chunks {
        for (t, m) in total.iter_mut().zip(chunk) {
            t.merge(m);
        }
    }
    total.iter().map(IntMoments::finish).collect()
}

/// Per-lane accumulators of a chunk (lane `j` holds channel `j % channels`).
struct IntLanes<T: IntSample> {
    sum: [u32; LANES],
    sum_sq: [T::Square; LANES],
    nonzero: [u32; LANES],
    min: [T; LANES],
    max: [T; LANES],
}

impl<T: IntSample> IntLanes<T> {
    fn new() -> Self {
        IntLanes {
            sum: [0; LANES],
            sum_sq: [T::Square::default(); LANES],
            nonzero: [0; LANES],
            min: [T::MAX; LANES],
            max: [T::MIN; LANES],
        }
    }

    /// One pass per accumulator over the run: each keeps its lanes in registers and vectorises
    /// (measured faster than one fused loop, whose lanes spill to the stack).
    fn add_run(&mut self, run: &[T]) {
        lane_pass(run, &mut self.sum, |s, v| *s += v.widen());
        lane_pass(run, &mut self.sum_sq, |s, v| *s += v.square());
        lane_pass(run, &mut self.nonzero, |s, v| *s += u32::from(!v.is_zero()));
        lane_pass(run, &mut self.min, |s, v| *s = (*s).min(v));
        lane_pass(run, &mut self.max, |s, v| *s = (*s).max(v));
    }
}

/// Moments of chunk `k`, one entry per channel.
fn integer_chunk<T: IntSample>(samples: &[T], region: &Region, k: usize) -> Vec<IntMoments<T>> {
    let c = region.channels;
    let pixels = k * CHUNK_PIXELS..((k + 1) * CHUNK_PIXELS).min(region.pixels());
    let mut acc = IntLanes::<T>::new();
    region.for_each_run(pixels.clone(), |run| {
        acc.add_run(&samples[run]);
    });
    let IntLanes {
        sum,
        sum_sq,
        nonzero,
        min,
        max,
    } = acc;
    let mut out = vec![IntMoments::<T>::empty(); c];
    for lane in 0..LANES {
        let m = &mut out[lane % c];
        m.nonzero += u64::from(nonzero[lane]);
        m.sum += u128::from(sum[lane]);
        let sq: u64 = sum_sq[lane].into();
        m.sum_sq += u128::from(sq);
        m.min = m.min.min(min[lane]);
        m.max = m.max.max(max[lane]);
    }
    let count = pixels.len() as u64;
    for m in &mut out {
        m.count = count;
    }
    out
}

/// Moments of one f32 channel: mean and sum of squared deviations (`m2`) over the finite
/// samples, plus counts.
#[derive(Debug, Clone, Copy)]
struct FloatMoments {
    count: u64,
    mean: f64,
    m2: f64,
    min: f32,
    max: f32,
    nonzero: u64,
    nan: u64,
    inf: u64,
}

impl FloatMoments {
    fn empty() -> Self {
        FloatMoments {
            count: 0,
            mean: 0.0,
            m2: 0.0,
            min: f32::INFINITY,
            max: f32::NEG_INFINITY,
            nonzero: 0,
            nan: 0,
            inf: 0,
        }
    }

    /// Chan, Golub & LeVeque's pairwise combination of (count, mean, M2).
    fn merge(&mut self, other: &Self) {
        self.nonzero += other.nonzero;
        self.nan += other.nan;
        self.inf += other.inf;
        if other.count == 0 {
            return;
        }
        if self.count == 0 {
            self.count = other.count;
            self.mean = other.mean;
            self.m2 = other.m2;
            self.min = other.min;
            self.max = other.max;
            return;
        }
        let (na, nb) = (self.count as f64, other.count as f64);
        let n = na + nb;
        let delta = other.mean - self.mean;
        self.mean += delta * (nb / n);
        self.m2 += other.m2 + delta * delta * (na * nb / n);
        self.count += other.count;
        self.min = self.min.min(other.min);
        self.max = self.max.max(other.max);
    }

    fn finish(&self) -> ChannelStats {
        let summary = (self.count > 0).then(|| Summary {
            min: f64::from(self.min),
            max: f64::from(self.max),
            mean: self.mean,
            std: (self.m2.max(0.0) / self.count as f64).sqrt(),
        });
        ChannelStats {
            count: self.count,
            nonzero: self.nonzero,
            nan: self.nan,
            inf: self.inf,
            summary,
        }
    }
}

fn float_stats(samples: &[f32], region: &Region) -> Vec<ChannelStats> {
    let c = region.channels;
    let chunks: Vec<Vec<FloatMoments>> = (0..region.chunks())
        .into_par_iter()
        .map(|k| float_chunk(samples, region, k))
        .collect();
    let mut total = vec![FloatMoments::empty(); c];
    for chunk in &chunks {
        for (t, m) in total.iter_mut().zip(chunk) {
            t.merge(m);
        }
    }
    total.iter().map(FloatMoments::finish).collect()
}

/// First-pass per-lane accumulators of an f32 chunk. The finite count is not kept: it is the
/// sample count minus `nan` and `inf`.
struct FloatLanes {
    sum: [f64; WIDE_LANES],
    min: [f32; LANES],
    max: [f32; LANES],
    nonzero: [u32; LANES],
    nan: [u32; LANES],
    inf: [u32; LANES],
}

impl FloatLanes {
    fn new() -> Self {
        FloatLanes {
            sum: [0.0; WIDE_LANES],
            min: [f32::INFINITY; LANES],
            max: [f32::NEG_INFINITY; LANES],
            nonzero: [0; LANES],
            nan: [0; LANES],
            inf: [0; LANES],
        }
    }
}

impl FloatLanes {
    /// Runs of finite samples (the usual case) take branch-free passes, one per accumulator;
    /// a run holding a NaN or ∞ goes sample by sample.
    fn add_run(&mut self, run: &[f32]) {
        if all_finite(run) {
            lane_pass(run, &mut self.sum, |s, v| *s += f64::from(v));
            lane_pass(run, &mut self.min, |s, v| *s = if v < *s { v } else { *s });
            lane_pass(run, &mut self.max, |s, v| *s = if v > *s { v } else { *s });
            lane_pass(run, &mut self.nonzero, |s, v| *s += u32::from(v != 0.0));
            return;
        }
        for (i, &v) in run.iter().enumerate() {
            // The same lanes as the passes above use.
            let lane = i % LANES;
            self.nonzero[lane] += u32::from(v != 0.0);
            if v.is_finite() {
                self.sum[i % WIDE_LANES] += f64::from(v);
                self.min[lane] = self.min[lane].min(v);
                self.max[lane] = self.max[lane].max(v);
            } else if v.is_nan() {
                self.nan[lane] += 1;
            } else {
                self.inf[lane] += 1;
            }
        }
    }
}

fn all_finite(run: &[f32]) -> bool {
    let mut finite = [true; LANES];
    lane_pass(run, &mut finite, |f, v| *f &= v.abs() < f32::INFINITY);
    finite.iter().all(|&f| f)
}

/// Second-pass accumulators: deviations of the finite samples from their channel's chunk mean.
struct DeviationLanes {
    mean: [f64; WIDE_LANES],
    squares: [f64; WIDE_LANES],
    sum: [f64; WIDE_LANES],
}

impl DeviationLanes {
    fn add_run(&mut self, run: &[f32]) {
        deviation_pass(run, &self.mean, &mut self.squares, &mut self.sum);
    }
}

/// Adds `d²` and `d` for `d = x − mean[lane]` over the finite samples of a run (NaN and ∞
/// contribute nothing, through a select so the loop stays branch-free). Not inlined, for the
/// same reason as [`lane_pass`].
#[inline(never)]
fn deviation_pass(
    run: &[f32],
    mean: &[f64; WIDE_LANES],
    squares: &mut [f64; WIDE_LANES],
    sum: &mut [f64; WIDE_LANES],
) {
    let mut add = |block: &[f32]| {
        for (((sq, s), &m), &v) in squares.iter_mut().zip(sum.iter_mut()).zip(mean).zip(block) {
            let d = if v.abs() < f32::INFINITY {
                f64::from(v) - m
            } else {
                0.0
            };
            *sq += d * d;
            *s += d;
        }
    };
    let mut blocks = run.chunks_exact(WIDE_LANES);
    for block in &mut blocks {
        if let Ok(block) = <&[f32; WIDE_LANES]>::try_from(block) {
            add(block);
        }
    }
    add(blocks.remainder());
}

/// Moments of chunk `k` of an f32 image: a pass for counts, extremes and the mean, then a pass
/// for the deviations from that mean.
fn float_chunk(samples: &[f32], region: &Region, k: usize) -> Vec<FloatMoments> {
    let c = region.channels;
    let pixels = k * CHUNK_PIXELS..((k + 1) * CHUNK_PIXELS).min(region.pixels());

    let mut first = FloatLanes::new();
    region.for_each_run(pixels.clone(), |run| first.add_run(&samples[run]));
    let mut out = vec![FloatMoments::empty(); c];
    let mut sums = vec![0f64; c];
    for lane in 0..LANES {
        let m = &mut out[lane % c];
        m.nonzero += u64::from(first.nonzero[lane]);
        m.nan += u64::from(first.nan[lane]);
        m.inf += u64::from(first.inf[lane]);
        m.min = m.min.min(first.min[lane]);
        m.max = m.max.max(first.max[lane]);
    }
    for (lane, s) in first.sum.iter().enumerate() {
        sums[lane % c] += s;
    }
    for (m, s) in out.iter_mut().zip(&sums) {
        m.count = pixels.len() as u64 - m.nan - m.inf;
        if m.count > 0 {
            m.mean = s / m.count as f64;
        }
    }

    let mut second = DeviationLanes {
        mean: std::array::from_fn(|lane| out[lane % c].mean),
        squares: [0.0; WIDE_LANES],
        sum: [0.0; WIDE_LANES],
    };
    region.for_each_run(pixels, |run| second.add_run(&samples[run]));
    let mut squares = vec![0f64; c];
    let mut deviations = vec![0f64; c];
    for lane in 0..WIDE_LANES {
        squares[lane % c] += second.squares[lane];
        deviations[lane % c] += second.sum[lane];
    }
    for ((m, sq), d) in out.iter_mut().zip(&squares).zip(&deviations) {
        if m.count > 0 {
            // Corrected two-pass: removes the first-order effect of rounding in the mean.
            m.m2 = (sq - d * d / m.count as f64).max(0.0);
        }
    }
    out
}

/// Applies `f` to every sample of a run and the accumulator of its lane, sample `i` going to
/// lane `i % N`: full blocks of `N` (fixed length, so the loop vectorises), then the remainder. A
/// run starts on a pixel boundary and `N` is a multiple of the channel count, so every lane
/// keeps its channel.
// Not inlined: as a small function of its own each pass keeps its lanes in registers and
// vectorises; inlined into the chunk loop, the compiler was seen to fall back to scalar code.
#[inline(never)]
fn lane_pass<T: Copy, A, const N: usize>(run: &[T], acc: &mut [A; N], f: impl Fn(&mut A, T)) {
    let mut blocks = run.chunks_exact(N);
    for block in &mut blocks {
        if let Ok(block) = <&[T; N]>::try_from(block) {
            for (a, &v) in acc.iter_mut().zip(block) {
                f(a, v);
            }
        }
    }
    for (a, &v) in acc.iter_mut().zip(blocks.remainder()) {
        f(a, v);
    }
}

ocellus_engine::params! {
    /// Parameters of [`Stats`].
    pub struct StatsParams {
        /// Region to measure, `[x, y, width, height]` in pixels (top-left corner and size);
        /// the whole image when absent. Must lie inside the image (checked when the node
        /// runs). A zero-sized region gives counts only.
        roi: Option<[u32; 4]> = None => [unit = "px"],
    }
}

/// Image statistics (`analyze.stats`): per-channel min, max, mean, std and non-zero count.
#[derive(Debug, Clone)]
pub struct Stats {
    roi: Option<Roi>,
}

impl Op for Stats {
    type Params = StatsParams;
    const ID: &'static str = "analyze.stats";
    const SUMMARY: &'static str =
        "Per-channel min, max, mean, std and non-zero count of an image or a region of it.";
    const DOC: &'static str = r#"
Measures an image (any layout, any sample type), or the rectangle `roi` of it, and emits the
numbers as metrics. Values are in the image's native units: 0..255 for u8, 0..65535 for u16, the
stored floats for f32 (nothing is normalised).

Keys:
- `width`, `height`: size of the measured region (the ROI when given), pixels;
  `channels`: samples per pixel.
- Per channel `c` (`gray`, or `r`, `g`, `b`, `a`): `c.min`, `c.max`, `c.mean`, `c.std`
  (population standard deviation, `√(Σ(x − mean)²/n)`) and `c.nonzero` (samples `≠ 0`).
- f32 images also get `nan_count` and `inf_count` (all channels together). NaN and ±∞ samples
  are left out of min, max, mean and std; they do count as non-zero.
- An empty region (or an f32 channel with no finite sample) has no `min`/`max`/`mean`/`std`
  keys, only the sizes and counts.

Method: pixels are split into fixed chunks of 65536, reduced in parallel and merged in chunk
order, so results are bit-identical for any thread count. Integer images use exact integer
sums (the variance `(n·Σx² − (Σx)²)/n²` is rounded once); f32 images use a corrected two-pass
mean/deviation per chunk and Chan et al.'s pairwise merge, which stays accurate for data on a
large offset.

References: T. F. Chan, G. H. Golub, R. J. LeVeque, "Algorithms for computing the sample
variance: analysis and recommendations", The American Statistician 37(3), 1983.

Example (a node of a graph):
    "stats": (op: "analyze.stats", inputs: { "image": "card.image" },
              params: (roi: [0, 0, 640, 480])),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "any image: gray/rgb/rgba × u8/u16/f32",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "stats",
            PortType::Metrics,
            "width, height, channels; per channel c: c.min, c.max, c.mean, c.std, c.nonzero \
             (native units); nan_count, inf_count for f32",
        )]
    }

    fn new(params: StatsParams) -> Result<Self, String> {
        let roi = params.roi.map(|[x, y, width, height]| Roi {
            x: x as usize,
            y: y as usize,
            width: width as usize,
            height: height as usize,
        });
        Ok(Stats { roi })
    }
}

impl Operator for Stats {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let metrics =
            stats_metrics(image, self.roi).map_err(|e| OpError::input("image", e.to_string()))?;
        Ok(Outputs::new().with("stats", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use ocellus_engine::params::{ParamValue, Params};

    fn metrics(image: &Image, roi: Option<Roi>) -> Metrics {
        stats_metrics(image, roi).unwrap()
    }

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * b.abs().max(1.0)
    }

    /// Deterministic pseudo-random u64s (splitmix64).
    fn rng(seed: u64) -> impl FnMut() -> u64 {
        let mut s = seed;
        move || {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
    }

    #[test]
    fn hand_computed_rgb_u8() {
        // 2×2 RGB: r = {0, 10, 20, 30}, g = {255, 255, 255, 255}, b = {0, 0, 0, 4}.
        let img = Image::from_u8(
            2,
            2,
            Channels::Rgb,
            vec![0, 255, 0, 10, 255, 0, 20, 255, 0, 30, 255, 4],
        )
        .unwrap();
        let m = metrics(&img, None);
        let expect = [
            ("width", 2.0),
            ("height", 2.0),
            ("channels", 3.0),
            ("r.min", 0.0),
            ("r.max", 30.0),
            ("r.mean", 15.0),
            // deviations -15, -5, 5, 15: Σd² = 500, /4 = 125.
            ("r.std", 125f64.sqrt()),
            ("r.nonzero", 3.0),
            ("g.min", 255.0),
            ("g.max", 255.0),
            ("g.mean", 255.0),
            ("g.std", 0.0),
            ("g.nonzero", 4.0),
            ("b.min", 0.0),
            ("b.max", 4.0),
            ("b.mean", 1.0),
            // deviations -1, -1, -1, 3: Σd² = 12, /4 = 3.
            ("b.std", 3f64.sqrt()),
            ("b.nonzero", 1.0),
        ];
        for (key, value) in expect {
            assert_eq!(m.get(key), Some(&value), "{key}");
        }
        assert_eq!(m.len(), expect.len(), "no other keys for u8: {m:?}");
    }

    #[test]
    fn gray_u16_and_rgba_names() {
        let img = Image::from_u16(3, 1, Channels::Gray, vec![1000, 65535, 0]).unwrap();
        let m = metrics(&img, None);
        assert_eq!(m["gray.max"], 65535.0);
        assert_eq!(m["gray.min"], 0.0);
        assert_eq!(m["gray.nonzero"], 2.0);
        assert_eq!(m["gray.mean"], 66535.0 / 3.0);
        let rgba = Image::from_u8(1, 1, Channels::Rgba, vec![1, 2, 3, 4]).unwrap();
        let m = metrics(&rgba, None);
        for (c, v) in ["r", "g", "b", "a"].iter().zip(1..) {
            assert_eq!(m[&format!("{c}.mean")], f64::from(v));
        }
    }

    #[test]
    fn roi_selects_a_rectangle() {
        // 4×3 gray with value 10·y + x; ROI x 1..3, y 1..3 → {11, 12, 21, 22}.
        let data: Vec<u8> = (0..3)
            .flat_map(|y| (0..4).map(move |x| 10 * y + x))
            .collect();
        let img = Image::from_u8(4, 3, Channels::Gray, data).unwrap();
        let roi = Roi {
            x: 1,
            y: 1,
            width: 2,
            height: 2,
        };
        let m = metrics(&img, Some(roi));
        assert_eq!(m["width"], 2.0);
        assert_eq!(m["height"], 2.0);
        assert_eq!(m["gray.min"], 11.0);
        assert_eq!(m["gray.max"], 22.0);
        assert_eq!(m["gray.mean"], 16.5);
        assert_eq!(m["gray.std"], 5.024_937_810_560_445); // √((5.5² + 4.5²)·2 / 4)
        // Full-width ROI (the contiguous path) on rows 1..3.
        let rows = Roi {
            x: 0,
            y: 1,
            width: 4,
            height: 2,
        };
        let m = metrics(&img, Some(rows));
        assert_eq!(m["gray.min"], 10.0);
        assert_eq!(m["gray.max"], 23.0);
        assert_eq!(m["gray.mean"], 16.5);
        // Outside: a clear error naming the rectangle and the image size.
        for bad in [
            Roi {
                x: 3,
                y: 0,
                width: 2,
                height: 1,
            },
            Roi {
                x: 0,
                y: 0,
                width: 4,
                height: 4,
            },
            Roi {
                x: usize::MAX,
                y: 0,
                width: 2,
                height: 1,
            },
        ] {
            let err = stats_metrics(&img, Some(bad)).unwrap_err().to_string();
            assert!(err.contains("does not fit in the 4×3 image"), "{err}");
            assert!(err.contains(&format!("[{}, ", bad.x)), "{err}");
        }
    }

    #[test]
    fn lanes_do_not_overflow_on_extreme_values() {
        // A one-pixel-wide ROI sends every sample of a channel to the same lane: 70000 rows
        // (more than a chunk) of the largest sample value.
        let h = 70_000;
        let img = Image::from_u16(2, h, Channels::Gray, vec![u16::MAX; 2 * h]).unwrap();
        let column = Roi {
            x: 1,
            y: 0,
            width: 1,
            height: h,
        };
        let m = metrics(&img, Some(column));
        assert_eq!((m["gray.mean"], m["gray.std"]), (65535.0, 0.0));
        assert_eq!(m["gray.nonzero"], h as f64);
        let img = Image::from_u8(2, h, Channels::Rgb, vec![u8::MAX; 6 * h]).unwrap();
        let m = metrics(&img, Some(column));
        for c in ["r", "g", "b"] {
            assert_eq!(
                (m[&format!("{c}.mean")], m[&format!("{c}.std")]),
                (255.0, 0.0)
            );
        }
    }

    #[test]
    fn roi_matches_a_cropped_copy_on_large_images() {
        // Several chunks, a ROI that is not full width: compare with stats of the cropped copy.
        let (w, h) = (701, 389);
        let mut next = rng(4);
        let data: Vec<u8> = (0..w * h * 3).map(|_| next() as u8).collect();
        let img = Image::from_u8(w, h, Channels::Rgb, data.clone()).unwrap();
        let roi = Roi {
            x: 13,
            y: 7,
            width: 600,
            height: 300,
        };
        let mut crop = Vec::new();
        for y in roi.y..roi.y + roi.height {
            crop.extend_from_slice(&data[(y * w + roi.x) * 3..(y * w + roi.x + roi.width) * 3]);
        }
        let cropped = Image::from_u8(roi.width, roi.height, Channels::Rgb, crop).unwrap();
        assert_eq!(metrics(&img, Some(roi)), metrics(&cropped, None));
    }

    #[test]
    fn integer_results_are_exact_against_a_naive_computation() {
        let (w, h) = (517, 301);
        let mut next = rng(9);
        let data: Vec<u16> = (0..w * h * 4).map(|_| (next() % 60000) as u16).collect();
        let img = Image::from_u16(w, h, Channels::Rgba, data.clone()).unwrap();
        let stats = channel_stats(&img, None).unwrap();
        for (c, s) in stats.iter().enumerate() {
            let xs: Vec<f64> = data
                .iter()
                .skip(c)
                .step_by(4)
                .map(|&v| f64::from(v))
                .collect();
            let n = xs.len() as f64;
            let mean = xs.iter().sum::<f64>() / n;
            let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
            let summary = s.summary.unwrap();
            assert!(
                close(summary.mean, mean, 1e-14),
                "{} vs {mean}",
                summary.mean
            );
            assert!(close(summary.std, var.sqrt(), 1e-12));
            assert_eq!(s.count, (w * h) as u64);
            assert_eq!(s.nonzero, xs.iter().filter(|&&x| x != 0.0).count() as u64);
        }
    }

    #[test]
    fn f32_nan_and_inf_are_counted_and_excluded() {
        let v = [
            1.0,
            f32::NAN,
            3.0,
            f32::INFINITY,
            0.0,
            f32::NEG_INFINITY,
            f32::NAN,
            5.0,
        ];
        let img = Image::from_f32(4, 2, Channels::Gray, v.to_vec()).unwrap();
        let m = metrics(&img, None);
        assert_eq!(m["nan_count"], 2.0);
        assert_eq!(m["inf_count"], 2.0);
        assert_eq!(m["gray.min"], 0.0);
        assert_eq!(m["gray.max"], 5.0);
        // Finite samples {1, 3, 0, 5}: mean 2.25, Σd² = 1.5625 + 0.5625 + 5.0625 + 7.5625 = 14.75.
        assert_eq!(m["gray.mean"], 2.25);
        assert!(close(m["gray.std"], (14.75f64 / 4.0).sqrt(), 1e-15));
        // x != 0 for everything but the single 0.0 sample.
        assert_eq!(m["gray.nonzero"], 7.0);
        // Only non-finite samples: counts, no summary.
        let img = Image::from_f32(2, 1, Channels::Gray, vec![f32::NAN, f32::INFINITY]).unwrap();
        let m = metrics(&img, None);
        assert_eq!(m["nan_count"], 1.0);
        assert_eq!(m["inf_count"], 1.0);
        assert!(!m.contains_key("gray.mean") && !m.contains_key("gray.min"));
    }

    #[test]
    fn variance_survives_a_huge_offset() {
        // f32 values 10⁶ + k/16 (exactly representable: f32 spacing at 10⁶ is 1/16), k uniform
        // in 0..16, over several chunks. The exact variance follows from the integers k.
        let n = 1_000_003;
        let mut next = rng(1);
        let ks: Vec<u64> = (0..n).map(|_| next() % 16).collect();
        let xs: Vec<f32> = ks.iter().map(|&k| 1.0e6 + k as f32 / 16.0).collect();
        assert!(
            xs.iter()
                .zip(&ks)
                .all(|(&x, &k)| f64::from(x) == 1.0e6 + k as f64 / 16.0)
        );
        let (sk, skk) = ks.iter().fold((0u128, 0u128), |(s, q), &k| {
            (s + u128::from(k), q + u128::from(k * k))
        });
        let nn = n as u128;
        let exact_var = (nn * skk - sk * sk) as f64 / (nn * nn) as f64 / 256.0;
        let exact_mean = 1.0e6 + sk as f64 / nn as f64 / 16.0;

        let img = Image::from_f32(n, 1, Channels::Gray, xs.clone()).unwrap();
        let m = metrics(&img, None);
        assert!(close(m["gray.mean"], exact_mean, 1e-15));
        let var = m["gray.std"] * m["gray.std"];
        assert!(
            (var - exact_var).abs() <= 1e-9 * exact_var,
            "variance {var} vs exact {exact_var}"
        );

        // The one-pass formula on the same data, in f64, is badly wrong: the data are hard.
        let (s, q) = xs.iter().fold((0f64, 0f64), |(s, q), &x| {
            let x = f64::from(x);
            (s + x, q + x * x)
        });
        let naive = q / n as f64 - (s / n as f64).powi(2);
        assert!(
            (naive - exact_var).abs() > 0.05 * exact_var,
            "naive {naive} vs exact {exact_var}: not a hard case"
        );
        // A plain two-pass in f64 agrees with the exact value, confirming the reference.
        let mean = s / n as f64;
        let two_pass = xs
            .iter()
            .map(|&x| (f64::from(x) - mean).powi(2))
            .sum::<f64>()
            / n as f64;
        assert!((two_pass - exact_var).abs() <= 1e-6 * exact_var);
    }

    #[test]
    fn chunks_with_different_means_merge_exactly() {
        // Each chunk sits on its own offset (10⁶ + 3·chunk) with noise j/16, so the merge's
        // between-chunk term δ²·na·nb/n carries most of the variance. The exact value comes from
        // the integers 16·x.
        let n = 5 * CHUNK_PIXELS + 1234;
        let mut next = rng(5);
        let sixteenths: Vec<u64> = (0..n)
            .map(|i| 16 * (1_000_000 + 3 * (i / CHUNK_PIXELS) as u64) + next() % 16)
            .collect();
        let xs: Vec<f32> = sixteenths.iter().map(|&v| v as f32 / 16.0).collect();
        assert!(
            xs.iter()
                .zip(&sixteenths)
                .all(|(&x, &v)| f64::from(x) * 16.0 == v as f64)
        );
        let (s, q) = sixteenths.iter().fold((0u128, 0u128), |(s, q), &v| {
            (s + u128::from(v), q + u128::from(v) * u128::from(v))
        });
        let nn = n as u128;
        let exact_var = (nn * q - s * s) as f64 / (nn * nn) as f64 / 256.0;
        let exact_mean = s as f64 / nn as f64 / 16.0;
        // Two rows, so the chunks also cut across rows.
        let img = Image::from_f32(n / 2, 2, Channels::Gray, xs[..n / 2 * 2].to_vec()).unwrap();
        assert_eq!(n % 2, 0);
        let m = metrics(&img, None);
        assert!(close(m["gray.mean"], exact_mean, 1e-15));
        let var = m["gray.std"] * m["gray.std"];
        assert!(
            (var - exact_var).abs() <= 1e-9 * exact_var,
            "variance {var} vs exact {exact_var}"
        );
        assert_eq!(m["gray.min"], 1.0e6);
        assert_eq!(m["gray.max"], 1.0e6 + 15.0 + 15.0 / 16.0);
    }

    #[test]
    fn results_are_independent_of_thread_count() {
        let (w, h) = (1000, 700);
        let mut next = rng(77);
        let floats: Vec<f32> = (0..w * h * 3)
            .map(|_| (next() % 1_000_000) as f32 * 1e-3 + 12345.0)
            .collect();
        let bytes: Vec<u8> = (0..w * h * 3).map(|_| next() as u8).collect();
        let images = [
            Image::from_f32(w, h, Channels::Rgb, floats).unwrap(),
            Image::from_u8(w, h, Channels::Rgb, bytes).unwrap(),
        ];
        let roi = Some(Roi {
            x: 3,
            y: 5,
            width: 900,
            height: 600,
        });
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                images
                    .iter()
                    .flat_map(|img| [metrics(img, None), metrics(img, roi)])
                    .map(|m| {
                        m.into_iter()
                            .map(|(k, v)| (k, v.to_bits()))
                            .collect::<Vec<_>>()
                    })
                    .collect::<Vec<_>>()
            })
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn empty_images_and_regions_give_counts_only() {
        let img = Image::from_u8(0, 4, Channels::Rgb, vec![]).unwrap();
        let m = metrics(&img, None);
        let keys: Vec<&str> = m.keys().map(String::as_str).collect();
        assert_eq!(
            keys,
            [
                "b.nonzero",
                "channels",
                "g.nonzero",
                "height",
                "r.nonzero",
                "width"
            ]
        );
        assert_eq!((m["width"], m["height"], m["r.nonzero"]), (0.0, 4.0, 0.0));
        let img = Image::from_f32(3, 3, Channels::Gray, vec![1.0; 9]).unwrap();
        let empty = Roi {
            x: 3,
            y: 1,
            width: 0,
            height: 2,
        };
        let m = metrics(&img, Some(empty));
        assert_eq!(m["width"], 0.0);
        assert_eq!(m["nan_count"], 0.0);
        assert!(!m.contains_key("gray.min"));
    }

    #[test]
    fn operator_reads_roi_param_and_reports_errors_on_the_image() {
        let img = Image::from_u8(4, 4, Channels::Gray, (0..16).collect()).unwrap();
        let run = |roi: ParamValue| {
            let mut params = StatsParams::default().to_map();
            params.insert("roi".into(), roi);
            let op = Stats::new(StatsParams::from_map(&params)?)?;
            let specs = Stats::inputs();
            let values = [Some(Value::image(img.clone()))];
            let ctx = RunContext {
                node: "s".into(),
                threads: 1,
                element: None,
            };
            op.run(&ctx, &Inputs::new(&specs, &values))
                .map_err(|e| e.to_string())
        };
        let roi = |v: [i64; 4]| ParamValue::List(v.iter().map(|&i| ParamValue::Int(i)).collect());
        let mut out = run(roi([2, 2, 2, 2])).unwrap();
        let Some(Value::Metrics(m)) = out.take("stats") else {
            panic!("no stats output");
        };
        assert_eq!(m["gray.min"], 10.0);
        assert_eq!(m["gray.max"], 15.0);
        let mut out = run(ParamValue::None).unwrap();
        let Some(Value::Metrics(m)) = out.take("stats") else {
            panic!("no stats output");
        };
        assert_eq!(m["gray.mean"], 7.5);
        let err = run(roi([2, 2, 3, 1])).unwrap_err();
        assert!(err.starts_with("input `image`: roi [2, 2, 3, 1]"), "{err}");
        assert!(err.contains("4×4"), "{err}");
    }
}
