//! `analyze.histogram`: per-channel histograms with uniform bins, as OpenCV's `calcHist`, and a
//! bar plot of them.
//!
//! [`channel_histograms`] counts every channel's samples into `bins` uniform bins over a range
//! `[lo, hi)`; [`histogram_u8`] and [`histogram_u16`] are the plain full-range counts the
//! threshold and equalization filters build on.
//!
//! How it runs: samples are counted in fixed-size chunks in parallel and the chunk counts are
//! added in chunk order (integer sums, so any order gives the same result anyway). u8 counts
//! go through four interleaved sub-histograms, so consecutive equal samples do not stall on
//! the same counter; u8 and u16 samples map to bins through a lookup table built with the
//! same `⌊v·a + b⌋` formula as OpenCV (`a = bins / (hi − lo)`, `b = −lo·a`).

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, PixelData, Value, ValueError};
use rayon::prelude::*;

/// Samples per parallel counting chunk.
const CHUNK: usize = 1 << 18;

/// Largest bin count.
pub const MAX_BINS: u32 = 65536;

/// Plot size, pixels.
pub const PLOT_WIDTH: usize = 512;
/// Plot height, pixels.
pub const PLOT_HEIGHT: usize = 256;

params! {
    /// Parameters of `analyze.histogram`.
    pub struct HistogramParams {
        /// Number of uniform bins, 1..=65536. Default 256.
        bins: u32 = 256 => [min = 1.0, max = 65536.0],
        /// Range `[lo, hi)` of sample values counted, in the image's units; samples outside are
        /// not counted. `None`: [0, 256) for u8, [0, 65536) for u16, [min, max] of the finite
        /// samples for f32 (the maximum counts in the last bin).
        range: Option<[f64; 2]> = None,
        /// true: each channel's counts are divided by its number of samples (the rows sum to 1
        /// when every sample is in range). false: plain counts.
        normalize: bool = false,
    }
}

/// Histogram (`analyze.histogram`). See [`channel_histograms`].
#[derive(Debug, Clone, PartialEq)]
pub struct Histogram {
    bins: usize,
    range: Option<[f64; 2]>,
    normalize: bool,
}

impl Op for Histogram {
    type Params = HistogramParams;
    const ID: &'static str = "analyze.histogram";
    const SUMMARY: &'static str = "Counts each channel's samples into uniform bins and plots them.";
    const DOC: &'static str = r#"
Per-channel histogram with `bins` uniform bins over `[lo, hi)`: sample v goes to bin
⌊v·a + b⌋ with a = bins / (hi − lo), b = −lo·a (clamped to the last bin against rounding), and
is not counted outside the range; NaN is never counted. These are OpenCV's `calcHist`
semantics for uniform ranges (upper bound exclusive). The default range is the full sample
range for u8 and u16, and [min, max] of the finite samples for f32 with the maximum counted in
the last bin.

Outputs the counts as a `channels × bins` matrix (f64; divided by the channel's sample count
with `normalize`) and a 512×256 RGB u8 bar plot: one bar colour per channel (red, green, blue,
added where they overlap; white for gray; the alpha channel of RGBA is not plotted), heights
scaled to the largest plotted count.

Reference: OpenCV `cv::calcHist`.

Example:
    "hist": (op: "analyze.histogram", inputs: { "image": "card.image" }, params: (bins: 64)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to measure, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "histogram",
                PortType::Matrix,
                "Counts (or fractions), one row per channel, one column per bin.",
            ),
            PortSpec::new(
                "plot",
                PortType::Image,
                "512×256 RGB u8 bar plot of the histogram.",
            ),
        ]
    }

    fn new(params: HistogramParams) -> Result<Self, String> {
        let HistogramParams {
            bins,
            range,
            normalize,
        } = params;
        if !(1..=MAX_BINS).contains(&bins) {
            return Err(format!(
                "`bins` must be between 1 and {MAX_BINS}, got {bins}"
            ));
        }
        if let Some([lo, hi]) = range
            && !(lo.is_finite() && hi.is_finite() && lo < hi)
        {
            return Err(format!(
                "`range` must be finite with lo < hi, got [{lo}, {hi}]"
            ));
        }
        Ok(Histogram {
            bins: bins as usize,
            range,
            normalize,
        })
    }
}

impl Operator for Histogram {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let counts = channel_histograms(image, self.bins, self.range);
        let plot = plot_histograms(&counts, image.channels().count())
            .map_err(|e| OpError::failed(e.to_string()))?;
        let channels = counts.len();
        let pixels = (image.width() * image.height()) as f64;
        let mut data: Vec<f64> = counts.into_iter().flatten().map(|c| c as f64).collect();
        if self.normalize && pixels > 0.0 {
            for v in &mut data {
                *v /= pixels;
            }
        }
        let matrix =
            Matrix::new(channels, self.bins, data).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("histogram", Value::Matrix(std::sync::Arc::new(matrix)))
            .with("plot", Value::image(plot)))
    }
}

/// Counts of every u8 value (256 bins).
pub fn histogram_u8(samples: &[u8]) -> [u64; 256] {
    let partial: Vec<[u32; 256]> = samples
        .par_chunks(CHUNK)
        .map(|chunk| {
            let mut h = [[0u32; 256]; 4];
            let mut quads = chunk.chunks_exact(4);
            for q in &mut quads {
                h[0][q[0] as usize] += 1;
                h[1][q[1] as usize] += 1;
                h[2][q[2] as usize] += 1;
                h[3][q[3] as usize] += 1;
            }
            for &v in quads.remainder() {
                h[0][v as usize] += 1;
            }
            let mut sum = [0u32; 256];
            for (i, s) in sum.iter_mut().enumerate() {
                *s = h[0][i] + h[1][i] + h[2][i] + h[3][i];
            }
            sum
        })
        .collect();
    let mut total = [0u64; 256];
    for p in &partial {
        for (t, &c) in total.iter_mut().zip(p) {
            *t += u64::from(c);
        }
    }
    total
}

/// Counts of every u16 value (65536 bins).
pub fn histogram_u16(samples: &[u16]) -> Vec<u64> {
    let partial: Vec<Vec<u32>> = samples
        .par_chunks(CHUNK)
        .map(|chunk| {
            let mut h = vec![0u32; 65536];
            for &v in chunk {
                h[v as usize] += 1;
            }
            h
        })
        .collect();
    let mut total = vec![0u64; 65536];
    for p in &partial {
        for (t, &c) in total.iter_mut().zip(p) {
            *t += u64::from(c);
        }
    }
    total
}

/// The bin of every value `0..n` as OpenCV's uniform lookup: `⌊v·a + b⌋` clamped, `None` out of
/// `[lo, hi)`.
fn bin_table(n: usize, bins: usize, lo: f64, hi: f64) -> Vec<u32> {
    let a = bins as f64 / (hi - lo);
    let b = -lo * a;
    (0..n)
        .map(|v| {
            let v = v as f64;
            if v >= lo && v < hi {
                ((v * a + b).floor().clamp(0.0, bins as f64 - 1.0)) as u32
            } else {
                u32::MAX
            }
        })
        .collect()
}

/// Per-channel counts of `image`'s samples in `bins` uniform bins over `range` (see
/// [`Histogram`]'s doc for the defaults and bin rule): one `Vec` of `bins` counts per channel.
pub fn channel_histograms(image: &Image, bins: usize, range: Option<[f64; 2]>) -> Vec<Vec<u64>> {
    let c = image.channels().count();
    let bins = bins.max(1);
    match image.data() {
        PixelData::U8(src) => {
            let [lo, hi] = range.unwrap_or([0.0, 256.0]);
            let table = bin_table(256, bins, lo, hi);
            count_with(src, c, bins, |v| table[v as usize])
        }
        PixelData::U16(src) => {
            let [lo, hi] = range.unwrap_or([0.0, 65536.0]);
            let table = bin_table(65536, bins, lo, hi);
            count_with(src, c, bins, |v| table[v as usize])
        }
        PixelData::F32(src) => {
            let (lo, hi, closed) = match range {
                Some([lo, hi]) => (lo, hi, false),
                None => {
                    let (lo, hi) = src
                        .iter()
                        .filter(|v| v.is_finite())
                        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                            (lo.min(f64::from(v)), hi.max(f64::from(v)))
                        });
                    if lo > hi {
                        return vec![vec![0; bins]; c];
                    }
                    // A constant image still gets a non-empty range.
                    let hi = if hi > lo { hi } else { lo + 1.0 };
                    (lo, hi, true)
                }
            };
            let a = bins as f64 / (hi - lo);
            let b = -lo * a;
            let last = bins as f64 - 1.0;
            count_with(src, c, bins, |v| {
                let v = f64::from(v);
                if v >= lo && (v < hi || (closed && v == hi)) {
                    (v * a + b).floor().clamp(0.0, last) as u32
                } else {
                    u32::MAX
                }
            })
        }
    }
}

/// Counts of interleaved `c`-channel samples by `bin(v)` (`u32::MAX`: not counted).
fn count_with<T: Copy + Sync>(
    src: &[T],
    c: usize,
    bins: usize,
    bin: impl Fn(T) -> u32 + Sync,
) -> Vec<Vec<u64>> {
    let c = c.max(1);
    let chunk = (CHUNK / c) * c;
    let partial: Vec<Vec<u32>> = src
        .par_chunks(chunk)
        .map(|part| {
            let mut h = vec![0u32; bins * c];
            for px in part.chunks_exact(c) {
                for (ch, &v) in px.iter().enumerate() {
                    let b = bin(v);
                    if b != u32::MAX {
                        h[ch * bins + b as usize] += 1;
                    }
                }
            }
            h
        })
        .collect();
    let mut total = vec![vec![0u64; bins]; c];
    for p in &partial {
        for (ch, row) in total.iter_mut().enumerate() {
            for (t, &n) in row.iter_mut().zip(&p[ch * bins..(ch + 1) * bins]) {
                *t += u64::from(n);
            }
        }
    }
    total
}

/// A [`PLOT_WIDTH`]×[`PLOT_HEIGHT`] RGB u8 bar plot of per-channel counts: channel k of a
/// colour image adds to colour k (the fourth, alpha, is not drawn); a single channel draws
/// white. Heights are scaled to the largest drawn count.
pub fn plot_histograms(counts: &[Vec<u64>], channels: usize) -> Result<Image, ValueError> {
    let drawn = if channels == 1 { 1 } else { channels.min(3) };
    let mut data = vec![0u8; PLOT_WIDTH * PLOT_HEIGHT * 3];
    let peak = counts
        .iter()
        .take(drawn)
        .flat_map(|row| row.iter().copied())
        .max()
        .unwrap_or(0);
    if peak > 0 {
        for (ch, row) in counts.iter().take(drawn).enumerate() {
            let bins = row.len();
            for x in 0..PLOT_WIDTH {
                let count = row.get(x * bins / PLOT_WIDTH).copied().unwrap_or(0);
                let height = ((count as f64 / peak as f64) * PLOT_HEIGHT as f64).round() as usize;
                for y in PLOT_HEIGHT - height.min(PLOT_HEIGHT)..PLOT_HEIGHT {
                    let px = (y * PLOT_WIDTH + x) * 3;
                    if drawn == 1 {
                        data[px..px + 3].fill(255);
                    } else {
                        data[px + ch] = 255;
                    }
                }
            }
        }
    }
    Image::from_u8(PLOT_WIDTH, PLOT_HEIGHT, Channels::Rgb, data)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn bins_by_hand() {
        let image = Image::from_u8(6, 1, Channels::Gray, vec![0, 63, 64, 128, 255, 255]).unwrap();
        assert_eq!(channel_histograms(&image, 4, None), vec![vec![2, 1, 1, 2]]);
        // [20, 200): 10 bins of 18 levels; 0, 255 and 200 itself are outside.
        let image = Image::from_u8(5, 1, Channels::Gray, vec![0, 20, 37, 38, 200]).unwrap();
        let counts = channel_histograms(&image, 10, Some([20.0, 200.0]));
        assert_eq!(counts[0][0], 2);
        assert_eq!(counts[0][1], 1);
        assert_eq!(counts[0].iter().sum::<u64>(), 3);
        let full = histogram_u8(&[5, 5, 7]);
        assert_eq!((full[5], full[7], full.iter().sum::<u64>()), (2, 1, 3));
    }

    #[test]
    fn channels_u16_and_f32() {
        let rgb = Image::from_u8(2, 1, Channels::Rgb, vec![0, 128, 255, 0, 0, 0]).unwrap();
        assert_eq!(
            channel_histograms(&rgb, 2, None),
            vec![vec![2, 0], vec![1, 1], vec![1, 1]]
        );
        let wide = Image::from_u16(3, 1, Channels::Gray, vec![0, 32767, 65535]).unwrap();
        assert_eq!(channel_histograms(&wide, 2, None), vec![vec![2, 1]]);
        // f32 default range: [min, max], the maximum in the last bin; NaN and ∞ not counted.
        let data = vec![-1.0, 0.0, 0.999, 1.0, f32::NAN, f32::INFINITY];
        let float = Image::from_f32(6, 1, Channels::Gray, data).unwrap();
        assert_eq!(channel_histograms(&float, 2, None), vec![vec![1, 3]]);
        assert_eq!(
            channel_histograms(&float, 2, Some([0.0, 1.0])),
            vec![vec![1, 1]]
        );
        let flat = Image::from_f32(2, 1, Channels::Gray, vec![3.0, 3.0]).unwrap();
        assert_eq!(channel_histograms(&flat, 3, None), vec![vec![2, 0, 0]]);
        let empty = Image::from_f32(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(channel_histograms(&empty, 3, None), vec![vec![0, 0, 0]]);
    }

    #[test]
    fn plot_draws_one_colour_per_channel() {
        let rgb = Image::from_u8(1, 1, Channels::Rgb, vec![0, 255, 0]).unwrap();
        let counts = channel_histograms(&rgb, 256, None);
        let plot = plot_histograms(&counts, 3).unwrap();
        assert_eq!(
            (plot.width(), plot.height(), plot.channels()),
            (512, 256, Channels::Rgb)
        );
        let px = |x: usize, y: usize| {
            let i = (y * 512 + x) * 3;
            plot.as_u8().unwrap()[i..i + 3].to_vec()
        };
        // Bin 0 holds red and blue (full height), bin 255 green; columns 0 and 511.
        assert_eq!(px(0, 0), [255, 0, 255]);
        assert_eq!(px(511, 0), [0, 255, 0]);
        assert_eq!(px(256, 255), [0, 0, 0]);
        let gray = plot_histograms(&[vec![1, 0]], 1).unwrap();
        assert_eq!(&gray.as_u8().unwrap()[..3], &[255, 255, 255]);
    }

    #[test]
    fn new_checks_params() {
        let p = |bins: u32, range: Option<[f64; 2]>| {
            Histogram::new(HistogramParams {
                bins,
                range,
                normalize: false,
            })
        };
        assert!(p(256, None).is_ok());
        assert!(p(0, None).is_err());
        assert!(p(70_000, None).is_err());
        assert!(p(16, Some([1.0, 1.0])).is_err());
        assert!(p(16, Some([0.0, f64::NAN])).is_err());
        assert!(p(16, Some([0.0, 1.0])).is_ok());
    }

    proptest! {
        #[test]
        fn counts_sum_to_the_sample_count(
            data in proptest::collection::vec(any::<u8>(), 0..600),
            bins in 1usize..300,
        ) {
            let n = data.len() / 3;
            let image = Image::from_u8(n, 1, Channels::Rgb, data[..n * 3].to_vec()).unwrap();
            let counts = channel_histograms(&image, bins, None);
            prop_assert_eq!(counts.len(), 3);
            for (ch, row) in counts.iter().enumerate() {
                prop_assert_eq!(row.iter().sum::<u64>(), n as u64);
                // Each sample lands in bin ⌊v·bins/256⌋.
                for px in data[..n * 3].chunks_exact(3) {
                    prop_assert!(row[px[ch] as usize * bins / 256] > 0);
                }
            }
        }
    }
}
