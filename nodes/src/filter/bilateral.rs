//! `filter.bilateral`: edge-preserving smoothing with OpenCV's `bilateralFilter` semantics
//! (Tomasi & Manduchi 1998).
//!
//! Every output pixel is the weighted mean of the pixels `q` in a disc of radius `r` around it,
//! weighted by `exp(−|p − q|²/2σs²) · exp(−Δ²/2σc²)`, where Δ is the colour distance: the
//! absolute difference for one channel and, as OpenCV, the sum of the absolute channel
//! differences (L1) for several.
//!
//! How it runs:
//! - Window offsets and their space weights are computed once (the disc `dx² + dy² ≤ r²`).
//! - Colour weights come from a table: for integer images it is indexed by the exact integer
//!   L1 distance (0..=255·channels for u8, 0..=65535·channels for u16); for f32 it has 4096
//!   bins per channel over the image's range, linearly interpolated, as OpenCV does.
//! - Each band of output rows pads its source rows through the border table; each output row
//!   accumulates tap by tap over the whole row (f32 sums of weights and of weighted samples),
//!   so the inner loop runs over contiguous memory.
//! - Bands have a fixed height and are processed in parallel: results are bit-identical for
//!   any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};

/// Largest window radius, px.
pub const MAX_RADIUS: usize = 127;

/// Output rows per parallel band.
const BAND_ROWS: usize = 16;

/// Colour table bins per channel for f32 images (OpenCV's `kExpNumBinsPerChannel`).
const F32_BINS_PER_CHANNEL: usize = 1 << 12;

params! {
    /// Parameters of `filter.bilateral`.
    pub struct BilateralParams {
        /// Window diameter, px: the window is the disc of radius ⌊d/2⌋ (at least 1). d ≤ 0
        /// derives the radius from `sigma_space` as OpenCV: round(1.5·sigma_space).
        d: i32 = 9 => [max = 255, unit = "px"],
        /// Colour standard deviation, in sample units (gray levels for u8, 0–65535 for u16,
        /// the image's units for f32). For several channels it applies to the sum of the
        /// absolute channel differences. Must be > 0.
        sigma_color: f64 = 75.0 => [above = 0.0, unit = "sample units"],
        /// Spatial standard deviation, px. Must be > 0.
        sigma_space: f64 = 75.0 => [above = 0.0, unit = "px"],
        /// How pixels outside the image are read (OpenCV's default: "reflect_101").
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Bilateral filter (`filter.bilateral`). See [`bilateral_filter`].
#[derive(Debug, Clone, PartialEq)]
pub struct Bilateral {
    radius: usize,
    sigma_color: f64,
    sigma_space: f64,
    border: BorderMode,
    border_value: f64,
}

impl Op for Bilateral {
    type Params = BilateralParams;
    const ID: &'static str = "filter.bilateral";
    const SUMMARY: &'static str =
        "Edge-preserving smoothing: a Gaussian mean weighted by colour similarity.";
    const DOC: &'static str = r#"
Replaces every pixel by the mean of the pixels q in the disc of radius r = ⌊d/2⌋ around it,
weighted by exp(−‖p − q‖²/2σs²) · exp(−Δ²/2σc²), where ‖p − q‖ is the distance in pixels and Δ
the colour distance: |I(p) − I(q)| for gray images and, as OpenCV, the L1 distance Σ_c |I_c(p) −
I_c(q)| for colour (RGBA includes alpha). Pixels across a strong edge get tiny weights, so edges
stay sharp while flat regions are smoothed. Works on every pixel format; the output has the
input's format.

Method: brute force over the precomputed disc (offsets and space weights computed once), with
colour weights from a table: exact exp of every integer distance for u8 and u16 (float32
values of exp computed in double, as OpenCV), and for f32 a table of 4096 bins per channel over
the image's value range, linearly interpolated (OpenCV's method). Sums are accumulated in f32
tap by tap over whole rows; u8/u16 outputs are rounded to nearest. d ≤ 0 takes
r = round(1.5·sigma_space); r is at least 1 and at most 127. Agrees with OpenCV's
`bilateralFilter` within one gray level for u8 (the order of the f32 sums differs).

Differences from OpenCV: sigmas must be > 0 (OpenCV silently replaces ≤ 0 by 1); u16 and RGBA
images are accepted (OpenCV takes 8U and 32F with 1 or 3 channels).

Reference: C. Tomasi and R. Manduchi, "Bilateral filtering for gray and color images", ICCV
1998; OpenCV `cv::bilateralFilter`.

Example:
    "smooth": (op: "filter.bilateral", inputs: { "image": "photo.image" }, params: (d: 9, sigma_color: 75.0, sigma_space: 75.0)),
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
            "The filtered image, same size and pixel format as the input.",
        )]
    }

    fn new(params: BilateralParams) -> Result<Self, String> {
        let BilateralParams {
            d,
            sigma_color,
            sigma_space,
            border,
            border_value,
        } = params;
        for (name, sigma) in [("sigma_color", sigma_color), ("sigma_space", sigma_space)] {
            if !(sigma.is_finite() && sigma > 0.0) {
                return Err(format!("`{name}` must be finite and > 0, got {sigma}"));
            }
        }
        let radius = radius_for(d, sigma_space).ok_or_else(|| {
            format!(
                "the window radius (d = {d}, sigma_space = {sigma_space}) must be at most {MAX_RADIUS} px"
            )
        })?;
        check_border_value(border, border_value)?;
        Ok(Bilateral {
            radius,
            sigma_color,
            sigma_space,
            border,
            border_value,
        })
    }
}

/// The window radius OpenCV uses: ⌊d/2⌋, or round(1.5·sigma_space) for d ≤ 0; at least 1.
/// `None` beyond [`MAX_RADIUS`].
pub fn radius_for(d: i32, sigma_space: f64) -> Option<usize> {
    let r = if d <= 0 {
        (sigma_space * 1.5).round()
    } else {
        (d / 2) as f64
    };
    (r <= MAX_RADIUS as f64).then_some((r as usize).max(1))
}

impl Operator for Bilateral {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = bilateral_filter(
            image,
            self.radius,
            self.sigma_color,
            self.sigma_space,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Bilateral filter of `image` over the disc of radius `radius` (px, at least 1), with colour
/// and space standard deviations `sigma_color` (sample units) and `sigma_space` (px). Pixels
/// outside the image are read through `border` (`border_value` for the constant mode).
pub fn bilateral_filter(
    image: &Image,
    radius: usize,
    sigma_color: f64,
    sigma_space: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    if image.is_empty() {
        return image.clone();
    }
    let r = radius.clamp(1, MAX_RADIUS);
    let c = image.channels().count();
    let color_coeff = -0.5 / (sigma_color * sigma_color);
    let space_coeff = -0.5 / (sigma_space * sigma_space);
    let g = Geometry {
        width: image.width(),
        channels: c,
        radius: r,
        columns: BorderTable::symmetric(image.width(), r, border),
        rows: BorderTable::symmetric(image.height(), r, border),
        space: space_taps(r, space_coeff),
    };
    let integer_table = |levels: usize| -> Vec<f32> {
        (0..levels * c)
            .map(|i| ((i * i) as f64 * color_coeff).exp() as f32)
            .collect()
    };
    let data = match image.data() {
        PixelData::U8(src) => {
            let weights = U8Weights::new(&integer_table(256));
            let constant = border_value.round_ties_even() as u8;
            PixelData::U8(match c {
                1 => bands::<u8, _, 1>(src, &g, constant, &weights),
                3 => bands::<u8, _, 3>(src, &g, constant, &weights),
                _ => bands::<u8, _, 4>(src, &g, constant, &weights),
            })
        }
        PixelData::U16(src) => {
            let table = integer_table(65536);
            let constant = border_value.round_ties_even() as u16;
            PixelData::U16(match c {
                1 => bands::<u16, _, 1>(src, &g, constant, &IntegerWeights(&table)),
                3 => bands::<u16, _, 3>(src, &g, constant, &IntegerWeights(&table)),
                _ => bands::<u16, _, 4>(src, &g, constant, &IntegerWeights(&table)),
            })
        }
        PixelData::F32(src) => {
            let weights = FloatWeights::new(src, c, color_coeff, border, border_value as f32);
            let constant = border_value as f32;
            PixelData::F32(match c {
                1 => bands::<f32, _, 1>(src, &g, constant, &weights),
                3 => bands::<f32, _, 3>(src, &g, constant, &weights),
                _ => bands::<f32, _, 4>(src, &g, constant, &weights),
            })
        }
    };
    Image::new(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

/// The disc of radius `r`: `(dy, dx, weight)` with `dy, dx` in `0..2r+1` (offsets from the
/// window's corner), in row-major order, weight `exp(ρ²·coeff)` rounded to f32.
fn space_taps(r: usize, coeff: f64) -> Vec<(usize, usize, f32)> {
    let ri = r as i64;
    let mut taps = Vec::new();
    for i in -ri..=ri {
        for j in -ri..=ri {
            let rho2 = i * i + j * j;
            if rho2 > ri * ri {
                continue;
            }
            taps.push((
                (i + ri) as usize,
                (j + ri) as usize,
                (rho2 as f64 * coeff).exp() as f32,
            ));
        }
    }
    taps
}

struct Geometry {
    width: usize,
    channels: usize,
    radius: usize,
    columns: BorderTable,
    rows: BorderTable,
    space: Vec<(usize, usize, f32)>,
}

/// A sample type for the bilateral filter.
trait Sample: Copy + Default + Send + Sync + 'static {
    fn to_f32(self) -> f32;
    /// The output sample for a mean (rounded and saturated for integers).
    fn from_mean(x: f32) -> Self;
}

impl Sample for u8 {
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    fn from_mean(x: f32) -> u8 {
        x.round_ties_even() as u8
    }
}

impl Sample for u16 {
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    fn from_mean(x: f32) -> u16 {
        x.round_ties_even() as u16
    }
}

impl Sample for f32 {
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline(always)]
    fn from_mean(x: f32) -> f32 {
        x
    }
}

/// The colour weight of two pixels of `C` channels.
trait ColorWeights<T>: Sync {
    fn weight<const C: usize>(&self, a: &[T; C], b: &[T; C]) -> f32;
}

/// Exact table over the integer L1 distance.
struct IntegerWeights<'a>(&'a [f32]);

/// Exact table over the L1 distance of u8 pixels (at most 4 · 255 < 1024): a fixed size, so
/// lookups need no bounds checks.
struct U8Weights(Box<[f32; 1024]>);

impl U8Weights {
    fn new(table: &[f32]) -> Self {
        let mut fixed = Box::new([0.0f32; 1024]);
        for (f, &t) in fixed.iter_mut().zip(table) {
            *f = t;
        }
        U8Weights(fixed)
    }
}

impl ColorWeights<u8> for U8Weights {
    #[inline(always)]
    fn weight<const C: usize>(&self, a: &[u8; C], b: &[u8; C]) -> f32 {
        let mut d = 0usize;
        for ch in 0..C {
            d += a[ch].abs_diff(b[ch]) as usize;
        }
        self.0[d & 1023]
    }
}

impl ColorWeights<u16> for IntegerWeights<'_> {
    #[inline(always)]
    fn weight<const C: usize>(&self, a: &[u16; C], b: &[u16; C]) -> f32 {
        let mut d = 0usize;
        for ch in 0..C {
            d += a[ch].abs_diff(b[ch]) as usize;
        }
        self.0.get(d).copied().unwrap_or(0.0)
    }
}

/// Interpolated table for f32 images: `bins` per channel over the image's range.
struct FloatWeights {
    table: Vec<f32>,
    scale: f32,
}

impl FloatWeights {
    fn new(src: &[f32], c: usize, coeff: f64, border: BorderMode, border_value: f32) -> Self {
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for &x in src.iter().filter(|x| x.is_finite()) {
            lo = lo.min(x);
            hi = hi.max(x);
        }
        if border == BorderMode::Constant && border_value.is_finite() {
            lo = lo.min(border_value);
            hi = hi.max(border_value);
        }
        let bins = F32_BINS_PER_CHANNEL * c;
        let len = (hi - lo) * c as f32;
        let scale = if len.is_finite() && len > 0.0 {
            bins as f32 / len
        } else {
            0.0
        };
        let table = (0..bins + 2)
            .map(|i| {
                let v = if scale > 0.0 {
                    i as f64 / scale as f64
                } else {
                    0.0
                };
                (v * v * coeff).exp() as f32
            })
            .collect();
        FloatWeights { table, scale }
    }
}

impl ColorWeights<f32> for FloatWeights {
    #[inline(always)]
    fn weight<const C: usize>(&self, a: &[f32; C], b: &[f32; C]) -> f32 {
        let mut d = 0.0f32;
        for ch in 0..C {
            d += (a[ch] - b[ch]).abs();
        }
        let t = d * self.scale;
        // NaN and distances past the table read its last bins.
        let last = (self.table.len() - 2) as f32;
        let t = if t < last { t } else { last };
        let i = t as usize;
        let alpha = t - i as f32;
        match (self.table.get(i), self.table.get(i + 1)) {
            (Some(&w0), Some(&w1)) => w0 + alpha * (w1 - w0),
            _ => 0.0,
        }
    }
}

/// Pads the source rows of output rows `y0 .. y0 + rows` (row stride `padded width · C`).
fn pad_band<T: Sample>(src: &[T], g: &Geometry, y0: usize, rows: usize, constant: T) -> Vec<T> {
    let n = g.width * g.channels;
    let stride = g.columns.padded_len() * g.channels;
    let total = rows + 2 * g.radius;
    let mut data = vec![constant; total * stride];
    for (j, dst) in data.chunks_exact_mut(stride).enumerate() {
        match g
            .rows
            .source(y0 + j)
            .and_then(|r| src.get(r * n..(r + 1) * n))
        {
            Some(line) => g.columns.pad_row(line, g.channels, constant, dst),
            None => dst.fill(constant),
        }
    }
    data
}

fn bands<T: Sample, W: ColorWeights<T>, const C: usize>(
    src: &[T],
    g: &Geometry,
    constant: T,
    weights: &W,
) -> Vec<T> {
    let n = g.width * C;
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
    if n == 0 || g.channels != C {
        return dst;
    }
    let stride = g.columns.padded_len() * C;
    dst.par_chunks_mut(BAND_ROWS * n)
        .enumerate()
        .for_each(|(b, out)| {
            let rows = out.len() / n;
            let padded = pad_band(src, g, b * BAND_ROWS, rows, constant);
            let mut sums = vec![0.0f32; n];
            let mut wsum = vec![0.0f32; g.width];
            for (i, line) in out.chunks_exact_mut(n).enumerate() {
                filter_row::<T, W, C>(&padded, stride, i, g, weights, &mut sums, &mut wsum, line);
            }
        });
    dst
}

/// One output row `line` (band row `i`) from the padded band rows `padded` (row stride
/// `stride`), accumulating tap by tap over the whole row into `sums` and `wsum`.
#[allow(clippy::too_many_arguments)]
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn filter_row<T: Sample, W: ColorWeights<T>, const C: usize>(
    padded: &[T],
    stride: usize,
    i: usize,
    g: &Geometry,
    weights: &W,
    sums: &mut [f32],
    wsum: &mut [f32],
    line: &mut [T],
) {
    let n = line.len();
    let r = g.radius;
    sums.fill(0.0);
    wsum.fill(0.0);
    let centre_start = (i + r) * stride + r * C;
    let Some(centre) = padded.get(centre_start..centre_start + n) else {
        return;
    };
    for &(dy, dx, space) in &g.space {
        let start = (i + dy) * stride + dx * C;
        let Some(tap) = padded.get(start..start + n) else {
            continue;
        };
        accumulate::<T, W, C>(tap, centre, space, weights, sums, wsum);
    }
    for ((o, s), &w) in line
        .chunks_exact_mut(C)
        .zip(sums.chunks_exact(C))
        .zip(wsum.iter())
    {
        let inverse = 1.0 / w;
        for (o, &s) in o.iter_mut().zip(s) {
            *o = T::from_mean(s * inverse);
        }
    }
}

/// Adds one tap (the row `tap`, compared with `centre`) to the sums of one output row.
#[inline(always)]
fn accumulate<T: Sample, W: ColorWeights<T>, const C: usize>(
    tap: &[T],
    centre: &[T],
    space: f32,
    weights: &W,
    sums: &mut [f32],
    wsum: &mut [f32],
) {
    let (tap, _) = tap.as_chunks::<C>();
    let (centre, _) = centre.as_chunks::<C>();
    let (sums, _) = sums.as_chunks_mut::<C>();
    for (((p, q), s), ws) in tap.iter().zip(centre).zip(sums).zip(wsum) {
        let w = space * weights.weight(p, q);
        for ch in 0..C {
            s[ch] += p[ch].to_f32() * w;
        }
        *ws += w;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::map_index;
    use crate::filter::test_support::{MODES, random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    fn samples(img: &Image) -> Vec<f64> {
        match img.data() {
            PixelData::U8(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::U16(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::F32(d) => d.iter().map(|&x| x as f64).collect(),
        }
    }

    /// The definition in f64 (exact exponentials), before rounding.
    fn naive(img: &Image, r: usize, sc: f64, ss: f64, border: BorderMode, value: f64) -> Vec<f64> {
        let (w, h, c) = (img.width(), img.height(), img.channels().count());
        let s = samples(img);
        let ri = r as isize;
        let pixel = |x: isize, y: isize| -> Vec<f64> {
            match (map_index(x, w, border), map_index(y, h, border)) {
                (Some(x), Some(y)) => s[(y * w + x) * c..(y * w + x + 1) * c].to_vec(),
                _ => vec![value; c],
            }
        };
        let mut out = vec![0.0; s.len()];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let p = pixel(x, y);
                let mut acc = vec![0.0; c];
                let mut wsum = 0.0;
                for dy in -ri..=ri {
                    for dx in -ri..=ri {
                        if dx * dx + dy * dy > ri * ri {
                            continue;
                        }
                        let q = pixel(x + dx, y + dy);
                        let d: f64 = p.iter().zip(&q).map(|(a, b)| (a - b).abs()).sum();
                        let rho2 = (dx * dx + dy * dy) as f64;
                        let wt = (-rho2 / (2.0 * ss * ss)).exp() * (-d * d / (2.0 * sc * sc)).exp();
                        for ch in 0..c {
                            acc[ch] += q[ch] * wt;
                        }
                        wsum += wt;
                    }
                }
                let i = (y as usize * w + x as usize) * c;
                for ch in 0..c {
                    out[i + ch] = acc[ch] / wsum;
                }
            }
        }
        out
    }

    fn pattern(w: usize, h: usize, c: usize) -> Vec<u8> {
        (0..h)
            .flat_map(|y| {
                (0..w).flat_map(move |x| {
                    (0..c).map(move |ch| ((x * 37 + y * 91 + x * y * 13 + ch * 71) % 256) as u8)
                })
            })
            .collect()
    }

    #[test]
    fn matches_opencv_bilateral_filter() {
        // cv2.bilateralFilter(img, 5, sigma_color, 3) on 9×6 images (x·37 + y·91 + x·y·13 +
        // c·71) mod 256, gray with sigma_color 40 and RGB with 60.
        let gray = Image::from_u8(9, 6, Channels::Gray, pattern(9, 6, 1)).unwrap();
        let got = bilateral_filter(&gray, 2, 40.0, 3.0, BorderMode::Reflect101, 0.0);
        for (g, w) in got.as_u8().unwrap().iter().zip(OPENCV_GRAY) {
            assert!(g.abs_diff(w) <= 1, "{g} vs {w}");
        }
        let rgb = Image::from_u8(9, 6, Channels::Rgb, pattern(9, 6, 3)).unwrap();
        let got = bilateral_filter(&rgb, 2, 60.0, 3.0, BorderMode::Reflect101, 0.0);
        for (g, w) in got.as_u8().unwrap().iter().zip(OPENCV_RGB) {
            assert!(g.abs_diff(w) <= 1, "{g} vs {w}");
        }
    }

    const OPENCV_GRAY: [u8; 54] = [
        30, 51, 75, 112, 150, 178, 192, 15, 20, 91, 138, 186, 228, 56, 91, 138, 184, 212, 168, 222,
        67, 116, 178, 216, 66, 116, 169, 44, 90, 166, 230, 75, 147, 213, 52, 109, 97, 189, 46, 119,
        204, 56, 135, 217, 58, 189, 55, 152, 231, 89, 186, 53, 146, 225,
    ];
    const OPENCV_RGB: [u8; 162] = [
        10, 81, 152, 38, 109, 180, 65, 136, 207, 105, 176, 247, 158, 229, 44, 192, 7, 78, 210, 25,
        96, 6, 77, 148, 31, 102, 173, 90, 161, 232, 143, 214, 29, 193, 8, 79, 241, 56, 127, 40,
        111, 182, 81, 152, 223, 135, 206, 21, 188, 3, 74, 233, 48, 119, 175, 246, 61, 243, 58, 129,
        54, 125, 196, 118, 189, 4, 168, 239, 54, 233, 48, 119, 47, 118, 189, 111, 182, 253, 174,
        245, 60, 17, 88, 159, 94, 165, 236, 160, 231, 46, 243, 58, 129, 60, 131, 202, 140, 211, 26,
        222, 37, 108, 43, 114, 185, 111, 182, 253, 101, 172, 243, 198, 13, 84, 37, 108, 179, 122,
        193, 8, 209, 24, 95, 45, 116, 187, 136, 207, 22, 221, 36, 107, 46, 117, 188, 197, 12, 83,
        40, 111, 182, 147, 218, 33, 243, 58, 129, 83, 154, 225, 204, 19, 90, 42, 113, 184, 139,
        210, 25, 231, 46, 117,
    ];

    #[test]
    fn within_one_level_of_the_exact_definition() {
        for (channels, r, sc, ss) in [
            (Channels::Gray, 2, 30.0, 2.0),
            (Channels::Rgb, 4, 75.0, 75.0),
            (Channels::Rgba, 1, 200.0, 1.0),
        ] {
            let img = random_u8(23, 19, channels, 7);
            for border in MODES {
                let v = if border == BorderMode::Constant {
                    40.0
                } else {
                    0.0
                };
                let got = samples(&bilateral_filter(&img, r, sc, ss, border, v));
                let want = naive(&img, r, sc, ss, border, v);
                for (g, w) in got.iter().zip(&want) {
                    assert!(
                        (g - w).abs() <= 0.5 + 1e-3,
                        "{g} vs {w} ({channels:?} {border:?})"
                    );
                }
            }
        }
    }

    #[test]
    fn f32_and_u16_follow_the_definition() {
        let n = 17 * 13 * 3;
        let r = randoms(3, n);
        let f =
            Image::from_f32(17, 13, Channels::Rgb, r.iter().map(|&x| x as f32).collect()).unwrap();
        let got = samples(&bilateral_filter(&f, 3, 0.3, 2.0, BorderMode::Reflect, 0.0));
        let want = naive(&f, 3, 0.3, 2.0, BorderMode::Reflect, 0.0);
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 2e-4, "{g} vs {w}");
        }
        let u = Image::from_u16(
            17,
            13,
            Channels::Rgb,
            r.iter().map(|&x| (x * 65535.0) as u16).collect(),
        )
        .unwrap();
        let got = samples(&bilateral_filter(
            &u,
            2,
            9000.0,
            2.0,
            BorderMode::Clamp,
            0.0,
        ));
        let want = naive(&u, 2, 9000.0, 2.0, BorderMode::Clamp, 0.0);
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= 0.5 + 0.02, "{g} vs {w}");
        }
    }

    #[test]
    fn constant_images_and_tiny_sigma_color_are_unchanged() {
        let c = Image::from_u8(20, 11, Channels::Rgb, vec![93; 20 * 11 * 3]).unwrap();
        assert_eq!(
            bilateral_filter(&c, 4, 75.0, 75.0, BorderMode::Reflect101, 0.0),
            c
        );
        let c16 = Image::from_u16(20, 11, Channels::Gray, vec![40000; 20 * 11]).unwrap();
        assert_eq!(
            bilateral_filter(&c16, 3, 500.0, 5.0, BorderMode::Wrap, 0.0),
            c16
        );
        let cf = Image::from_f32(20, 11, Channels::Gray, vec![0.375; 20 * 11]).unwrap();
        // f32: the mean of equal samples is exact up to the rounding of the f32 sums.
        let out = bilateral_filter(&cf, 3, 0.1, 5.0, BorderMode::Clamp, 0.0);
        assert!(
            out.as_f32()
                .unwrap()
                .iter()
                .all(|&x| (x - 0.375).abs() < 1e-6)
        );
        // Neighbours that differ by at least one level get weight exp(−1/(2·0.05²)) = 0.
        let img = random_u8(31, 17, Channels::Gray, 2);
        let mut distinct = img.as_u8().unwrap().to_vec();
        for (i, v) in distinct.iter_mut().enumerate() {
            *v = (i % 2) as u8 * 100 + (i % 7) as u8;
        }
        let img = Image::from_u8(31, 17, Channels::Gray, distinct).unwrap();
        let out = bilateral_filter(&img, 3, 0.05, 3.0, BorderMode::Reflect101, 0.0);
        assert!(
            out.as_u8()
                .unwrap()
                .iter()
                .zip(img.as_u8().unwrap())
                .all(|(a, b)| a.abs_diff(*b) <= 7)
        );
    }

    #[test]
    fn step_edges_stay_sharp() {
        let (w, h) = (24, 8);
        let data: Vec<u8> = (0..h)
            .flat_map(|_| (0..w).map(|x| if x < 12 { 20 } else { 220 }))
            .collect();
        let img = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        let out = bilateral_filter(&img, 4, 30.0, 10.0, BorderMode::Reflect101, 0.0);
        assert_eq!(out, img);
    }

    #[test]
    fn radius_rules_and_params() {
        assert_eq!(radius_for(9, 75.0), Some(4));
        assert_eq!(radius_for(1, 75.0), Some(1));
        assert_eq!(radius_for(0, 3.0), Some(5));
        assert_eq!(radius_for(-1, 0.2), Some(1));
        assert_eq!(radius_for(0, 100.0), None);
        let p = |f: fn(&mut BilateralParams)| {
            let mut p = BilateralParams::default();
            f(&mut p);
            Bilateral::new(p)
        };
        assert!(p(|_| ()).is_ok());
        assert!(
            p(|p| p.sigma_color = 0.0)
                .unwrap_err()
                .contains("sigma_color")
        );
        assert!(
            p(|p| p.sigma_space = f64::NAN)
                .unwrap_err()
                .contains("sigma_space")
        );
        assert!(p(|p| p.sigma_color = f64::INFINITY).is_err());
        assert!(p(|p| p.d = 0).is_ok());
        assert!(
            p(|p| {
                p.d = 0;
                p.sigma_space = 1000.0
            })
            .unwrap_err()
            .contains("radius")
        );
        assert!(p(|p| p.border_value = 3.0).is_err());
    }

    #[test]
    fn tiny_and_empty_images() {
        let one = Image::from_u8(1, 1, Channels::Rgb, vec![1, 2, 3]).unwrap();
        for border in MODES {
            assert_eq!(bilateral_filter(&one, 3, 10.0, 3.0, border, 0.0).width(), 1);
        }
        assert_eq!(
            bilateral_filter(&one, 3, 10.0, 3.0, BorderMode::Clamp, 0.0),
            one
        );
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(
            bilateral_filter(&empty, 3, 10.0, 3.0, BorderMode::Clamp, 0.0),
            empty
        );
        let nan = Image::from_f32(
            3,
            2,
            Channels::Gray,
            vec![f32::NAN, 1.0, 2.0, f32::INFINITY, 0.0, 1.0],
        )
        .unwrap();
        assert_eq!(
            bilateral_filter(&nan, 1, 1.0, 1.0, BorderMode::Clamp, 0.0).width(),
            3
        );
    }

    #[test]
    fn identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_u8(67, 90, Channels::Rgb, 4);
        let run = || bilateral_filter(&img, 4, 50.0, 5.0, BorderMode::Reflect101, 0.0);
        assert_eq!(pool(1).install(run), pool(4).install(run));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        #[test]
        fn u8_within_rounding_of_the_definition(
            w in 1usize..20,
            h in 1usize..14,
            r in 1usize..4,
            sc in 1.0f64..300.0,
            ss in 0.5f64..20.0,
            channels in prop::sample::select(vec![Channels::Gray, Channels::Rgb]),
            border in prop::sample::select(MODES.to_vec()),
            seed in any::<u64>(),
        ) {
            let img = random_u8(w, h, channels, seed);
            let got = samples(&bilateral_filter(&img, r, sc, ss, border, 0.0));
            let want = naive(&img, r, sc, ss, border, 0.0);
            for (g, w) in got.iter().zip(&want) {
                prop_assert!((g - w).abs() <= 0.5 + 1e-3, "{} vs {}", g, w);
            }
        }
    }
}
