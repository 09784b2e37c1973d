//! `filter.integral`: integral (summed-area) and squared-integral images.
//!
//! [`integral`] computes, per channel, `S(x, y) = Σ_{i<x, j<y} I(i, j)` on a `(w + 1) × (h + 1)`
//! grid whose first row and column are zero (OpenCV's `cv::integral` layout), so the sum over any
//! rectangle takes four lookups ([`IntegralImage::box_sum`]). Sums are f64: exact for u8 and u16
//! images (and their squares) up to 2⁵³, far beyond any image size here.
//!
//! How it runs: one pass, row by row: a running sum along the row plus the row above. The pass is
//! sequential (each row depends on the previous one), so the result does not depend on the thread
//! count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params::NoParams;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Matrix, PixelData, Value};

/// Integral and squared-integral images (`filter.integral`). See [`integral`].
#[derive(Debug, Clone, PartialEq)]
pub struct Integral;

impl Op for Integral {
    type Params = NoParams;
    const ID: &'static str = "filter.integral";
    const SUMMARY: &'static str =
        "Computes the integral (summed-area) and squared-integral images.";
    const DOC: &'static str = r#"
Computes the integral image S(x, y) = Σ_{i<x, j<y} I(i, j) and the squared integral
Q(x, y) = Σ_{i<x, j<y} I(i, j)², per channel, as OpenCV's `cv::integral` (with a zero first row
and column). Both are Matrix values of (h + 1) rows and (w + 1)·channels columns of f64,
channels interleaved: entry (y, x·channels + c) is S(x, y) of channel c. The sum over the
rectangle [x0, x1) × [y0, y1) is S(x1, y1) − S(x0, y1) − S(x1, y0) + S(x0, y0).

Numerics: f64 accumulation, exact for u8 and u16 images (sums stay far below 2⁵³); f32
images accumulate their f32 samples in f64. OpenCV's default output depth for u8 is 32-bit
int (sum) and f64 (squared); here both are f64.

Reference: F. Crow, "Summed-area tables for texture mapping", SIGGRAPH 1984; P. Viola and
M. Jones, "Rapid object detection using a boosted cascade of simple features", CVPR 2001;
OpenCV `cv::integral`.

Example:
    "sat": (op: "filter.integral", inputs: { "image": "card.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to integrate, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "sum",
                PortType::Matrix,
                "Integral image, (h + 1) × (w + 1)·channels f64, zero first row and column.",
            ),
            PortSpec::new(
                "squared",
                PortType::Matrix,
                "Integral of squared samples, same layout as `sum`.",
            ),
        ]
    }

    fn new(_: NoParams) -> Result<Self, String> {
        Ok(Integral)
    }
}

impl Operator for Integral {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let sum = integral(image)
            .into_matrix()
            .map_err(|e| OpError::failed(e.to_string()))?;
        let squared = squared_integral(image)
            .into_matrix()
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("sum", Value::Matrix(sum.into()))
            .with("squared", Value::Matrix(squared.into())))
    }
}

/// A summed-area table: `(width + 1) × (height + 1)` entries per channel, interleaved, with a
/// zero first row and column.
#[derive(Debug, Clone, PartialEq)]
pub struct IntegralImage {
    /// Width of the integrated image (the table has one more column).
    pub width: usize,
    /// Height of the integrated image (the table has one more row).
    pub height: usize,
    /// Channels, interleaved.
    pub channels: usize,
    /// Row-major entries: `sum[(y·(width + 1) + x)·channels + c]` = S(x, y) of channel c.
    pub sum: Vec<f64>,
}

impl IntegralImage {
    /// The table entry S(x, y) of channel `c` (x ≤ width, y ≤ height), or `None` out of range.
    pub fn at(&self, x: usize, y: usize, c: usize) -> Option<f64> {
        if x > self.width || y > self.height || c >= self.channels {
            return None;
        }
        self.sum
            .get((y * (self.width + 1) + x) * self.channels + c)
            .copied()
    }

    /// Sum of channel `c` over the rectangle `[x0, x1) × [y0, y1)` (corners clipped to the
    /// image; an empty rectangle sums to 0), by four lookups.
    pub fn box_sum(&self, x0: usize, y0: usize, x1: usize, y1: usize, c: usize) -> f64 {
        let (x1, y1) = (x1.min(self.width), y1.min(self.height));
        let (x0, y0) = (x0.min(x1), y0.min(y1));
        let get = |x, y| self.at(x, y, c).unwrap_or(0.0);
        get(x1, y1) - get(x0, y1) - get(x1, y0) + get(x0, y0)
    }

    /// The table as a Matrix of `height + 1` rows and `(width + 1)·channels` columns.
    pub fn into_matrix(self) -> Result<Matrix, ocellus_engine::value::ValueError> {
        Matrix::new(self.height + 1, (self.width + 1) * self.channels, self.sum)
    }
}

/// The integral image of `image`: S(x, y) = Σ_{i<x, j<y} I(i, j) per channel.
pub fn integral(image: &Image) -> IntegralImage {
    // Integer rows run their sums in i64 (exact, one-cycle adds, and one instruction to
    // convert, where u64 → f64 takes several), f32 rows in f64.
    match image.data() {
        PixelData::U8(v) => table(image, v, i64::from, |s: i64| s as f64),
        PixelData::U16(v) => table(image, v, i64::from, |s: i64| s as f64),
        PixelData::F32(v) => table(image, v, f64::from, |s: f64| s),
    }
}

/// The squared integral image of `image`: Q(x, y) = Σ_{i<x, j<y} I(i, j)² per channel.
pub fn squared_integral(image: &Image) -> IntegralImage {
    match image.data() {
        PixelData::U8(v) => table(
            image,
            v,
            |s| i64::from(u32::from(s) * u32::from(s)),
            |s: i64| s as f64,
        ),
        PixelData::U16(v) => table(image, v, |s| i64::from(s) * i64::from(s), |s: i64| s as f64),
        PixelData::F32(v) => table(
            image,
            v,
            |s| {
                let s = f64::from(s);
                s * s
            },
            |s: f64| s,
        ),
    }
}

fn table<T: Copy, A: Copy + Default + std::ops::AddAssign>(
    image: &Image,
    src: &[T],
    value: impl Fn(T) -> A,
    to_f64: impl Fn(A) -> f64,
) -> IntegralImage {
    let (w, h, c) = (image.width(), image.height(), image.channels().count());
    let stride = (w + 1) * c;
    let mut sum = ocellus_engine::buffer::zeroed::<f64>(stride * (h + 1));
    if w > 0 {
        for (y, row) in src.chunks_exact(w * c).take(h).enumerate() {
            let (above, below) = sum.split_at_mut((y + 1) * stride);
            let above = &above[y * stride..];
            let below = &mut below[..stride];
            match c {
                1 => integrate_row::<T, A, 1>(row, &above[1..], &mut below[1..], &value, &to_f64),
                3 => integrate_row::<T, A, 3>(row, &above[3..], &mut below[3..], &value, &to_f64),
                4 => integrate_row::<T, A, 4>(row, &above[4..], &mut below[4..], &value, &to_f64),
                _ => {}
            }
        }
    }
    IntegralImage {
        width: w,
        height: h,
        channels: c,
        sum,
    }
}

/// `below[x] = above[x] + Σ_{i ≤ x} row[i]` per channel.
#[inline]
fn integrate_row<T: Copy, A: Copy + Default + std::ops::AddAssign, const C: usize>(
    row: &[T],
    above: &[f64],
    below: &mut [f64],
    value: &impl Fn(T) -> A,
    to_f64: &impl Fn(A) -> f64,
) {
    let mut run = [A::default(); C];
    for ((o, a), p) in below
        .chunks_exact_mut(C)
        .zip(above.chunks_exact(C))
        .zip(row.chunks_exact(C))
    {
        for ch in 0..C {
            run[ch] += value(p[ch]);
            o[ch] = a[ch] + to_f64(run[ch]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::BorderMode;
    use crate::filter::box_filter::box_filter;
    use crate::filter::test_support::random_u8;
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    #[test]
    fn hand_computed() {
        // 1 2
        // 3 4 → zero row/column, then 1 3 / 4 10.
        let image = Image::from_u8(2, 2, Channels::Gray, vec![1, 2, 3, 4]).unwrap();
        let s = integral(&image);
        assert_eq!(s.sum, [0.0, 0.0, 0.0, 0.0, 1.0, 3.0, 0.0, 4.0, 10.0]);
        let q = squared_integral(&image);
        assert_eq!(q.sum, [0.0, 0.0, 0.0, 0.0, 1.0, 5.0, 0.0, 10.0, 30.0]);
        assert_eq!(s.box_sum(1, 0, 2, 2, 0), 6.0);
        assert_eq!(s.box_sum(0, 1, 2, 2, 0), 7.0);
        assert_eq!(s.box_sum(1, 1, 1, 2, 0), 0.0);
        let m = s.into_matrix().unwrap();
        assert_eq!((m.rows, m.cols), (3, 3));
        assert_eq!(m.get(2, 2), Some(10.0));
    }

    #[test]
    fn channels_are_interleaved() {
        let image = Image::from_u8(2, 1, Channels::Rgb, vec![1, 2, 3, 10, 20, 30]).unwrap();
        let s = integral(&image);
        assert_eq!(s.at(2, 1, 0), Some(11.0));
        assert_eq!(s.at(2, 1, 2), Some(33.0));
        assert_eq!(s.at(1, 1, 1), Some(2.0));
        assert_eq!(s.at(3, 1, 0), None);
    }

    #[test]
    fn extremes() {
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(integral(&empty).sum, [0.0]);
        let tall = Image::from_u8(0, 3, Channels::Rgb, vec![]).unwrap();
        assert_eq!(integral(&tall).sum.len(), 12);
        let one = Image::from_u16(1, 1, Channels::Gray, vec![65535]).unwrap();
        assert_eq!(squared_integral(&one).at(1, 1, 0), Some(65535.0 * 65535.0));
        // A large white u16 image stays exact.
        let big = Image::from_u16(300, 200, Channels::Gray, vec![65535; 60_000]).unwrap();
        let q = squared_integral(&big);
        assert_eq!(q.at(300, 200, 0), Some(60_000.0 * 65535.0 * 65535.0));
        let f = Image::from_f32(2, 1, Channels::Gray, vec![-1.5, f32::MAX]).unwrap();
        assert_eq!(integral(&f).at(2, 1, 0), Some(-1.5 + f64::from(f32::MAX)));
    }

    #[test]
    fn box_sums_match_box_filter() {
        let image = random_u8(41, 29, Channels::Rgb, 12);
        let s = integral(&image);
        for (k, kk) in [(3usize, 5usize), (7, 7), (1, 4)] {
            let sums = box_filter(&image, k, kk, false, BorderMode::Constant, 0.0);
            let sums = sums.as_f32().unwrap();
            for y in 0..29usize {
                for x in 0..41usize {
                    for ch in 0..3 {
                        let x0 = x.saturating_sub(k / 2);
                        let y0 = y.saturating_sub(kk / 2);
                        let x1 = x + k - k / 2;
                        let y1 = y + kk - kk / 2;
                        let ours = s.box_sum(x0, y0, x1, y1, ch);
                        assert_eq!(ours, f64::from(sums[(y * 41 + x) * 3 + ch]), "{x},{y}");
                    }
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]

        #[test]
        fn box_sums_match_direct_sums(
            w in 1usize..20, h in 1usize..20, seed in 0u64..1000,
            x0 in 0usize..20, y0 in 0usize..20, dx in 0usize..20, dy in 0usize..20,
        ) {
            let image = random_u8(w, h, Channels::Rgba, seed);
            let s = integral(&image);
            let q = squared_integral(&image);
            let v = image.as_u8().unwrap();
            for ch in 0..4 {
                let (mut direct, mut direct_sq) = (0.0, 0.0);
                for y in y0..(y0 + dy).min(h) {
                    for x in x0..(x0 + dx).min(w) {
                        let p = f64::from(v[(y * w + x) * 4 + ch]);
                        direct += p;
                        direct_sq += p * p;
                    }
                }
                prop_assert_eq!(s.box_sum(x0, y0, x0 + dx, y0 + dy, ch), direct);
                prop_assert_eq!(q.box_sum(x0, y0, x0 + dx, y0 + dy, ch), direct_sq);
            }
        }
    }
}
