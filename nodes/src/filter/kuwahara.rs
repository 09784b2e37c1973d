//! `filter.kuwahara`: edge-preserving smoothing by choosing (or weighting) the most homogeneous
//! part of each window: the generalized Kuwahara filter of Papari, Petkov & Campisi (2007) and
//! the classic four-quadrant filter of Kuwahara et al. (1976).
//!
//! How it runs:
//! - The window is described once as a list of taps `(dy, dx, sector, weight)`: a pixel of the
//!   window appears once per sector it belongs to.
//! - Samples are converted to f32 in 8-bit units (u16 / 257, f32 · 255) while each band of rows
//!   is padded through the border table, so the sharpness exponent acts the same on every depth.
//! - Per pixel, every sector accumulates its weight, and the weighted sums of the samples and of
//!   their squares per channel (f32); means, variances and the final combination use f64.
//! - Bands of output rows have a fixed height and are processed in parallel: results are
//!   bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable, check_border_value};

/// Largest radius, px.
pub const MAX_RADIUS: u32 = 64;

/// Most sectors of the generalized filter.
pub const MAX_SECTORS: u32 = 16;

/// Output rows per parallel band.
const BAND_ROWS: usize = 16;

param_enum! {
    /// Which Kuwahara filter.
    pub enum KuwaharaMethod {
        /// Papari et al.'s generalized filter: N smooth sectors of a disc, weighted by their
        /// homogeneity.
        Generalized = "generalized",
        /// Kuwahara's original: the mean of the least varying of four square quadrants.
        Classic = "classic",
    }
}

params! {
    /// Parameters of `filter.kuwahara`.
    pub struct KuwaharaParams {
        /// "generalized" (Papari et al. 2007, default) or "classic" (four quadrants, 1976).
        method: KuwaharaMethod = KuwaharaMethod::Generalized,
        /// Window radius, 1..=64 px: the disc of that radius (generalized) or quadrants of
        /// (radius + 1) × (radius + 1) pixels sharing the centre row and column (classic).
        radius: u32 = 5 => [min = 1, max = 64, unit = "px"],
        /// Number of sectors of the generalized filter, 3..=16 (ignored by "classic", which
        /// always has 4 quadrants; any value is accepted then).
        sectors: u32 = 8 => [min = 3, max = 16],
        /// Sharpness exponent q of the generalized filter, 1..=32: sector weights are
        /// 1 / (1 + σᵢ^q) with σᵢ in gray levels; larger q follows the most homogeneous sector
        /// more strictly.
        sharpness: u32 = 8 => [min = 1, max = 32],
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Kuwahara filter (`filter.kuwahara`). See [`kuwahara`].
#[derive(Debug, Clone, PartialEq)]
pub struct Kuwahara {
    method: KuwaharaMethod,
    radius: usize,
    sectors: usize,
    sharpness: u32,
    border: BorderMode,
    border_value: f64,
}

impl Op for Kuwahara {
    type Params = KuwaharaParams;
    const ID: &'static str = "filter.kuwahara";
    const SUMMARY: &'static str = "Edge-preserving smoothing: each pixel takes the mean of the most homogeneous parts of its window.";
    const DOC: &'static str = r#"
Painterly, edge-preserving smoothing. Works per pixel on every pixel format; the output has the
input's format. Channels share the sector weights (so colours are not mixed independently).

"generalized" (default; Papari, Petkov & Campisi 2007): the disc of radius r is divided into N
sectors with smooth weights wᵢ(x) = a_i(angle of x) · exp(−|x|²/(2(r/2)²)), where a_i is a
raised-cosine (cos²) angular window centred on sector i and reaching the centres of its two
neighbours, so that the a_i sum to 1 everywhere (the centre pixel belongs 1/N to every
sector). For each sector the weighted mean mᵢ and standard deviation σᵢ are computed, with
σᵢ = √(Σ_c varᵢ,c) the Euclidean norm over the channels of the per-channel deviations, in
8-bit gray levels (u16 samples are divided by 257 and f32 samples, assumed in 0..1, multiplied
by 255 for σ only). The output is Σ mᵢ αᵢ / Σ αᵢ with αᵢ = 1/(1 + σᵢ^q) (q = `sharpness`).
Difference from the paper: the cos² angular windows replace the Gaussian-smoothed sector
indicator functions (both are smooth partitions of unity; ours is computed in closed form).

"classic" (Kuwahara et al. 1976): four (r+1)×(r+1) squares whose corner is the pixel (above
left, above right, below left, below right); the output is the mean of the square with the
smallest σ (the first in that order on ties).

Numerics: f32 sums per sector and channel (in 8-bit units), f64 for means, deviations and
weights; u8/u16 outputs rounded to nearest. Every output lies between the minimum and maximum of
its window. Cost is O(r²) per pixel (each window pixel feeds at most two sectors).

References: G. Papari, N. Petkov and P. Campisi, "Artistic edge and corner enhancing smoothing",
IEEE Trans. Image Processing 16(10), 2007; M. Kuwahara, K. Hachimura, S. Eiho and M. Kinoshita,
"Processing of RI-angiocardiographic images", Digital Processing of Biomedical Images, 1976.
OpenCV has no Kuwahara filter.

Example:
    "paint": (op: "filter.kuwahara", inputs: { "image": "photo.image" }, params: (radius: 6, sectors: 8, sharpness: 8)),
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

    fn new(params: KuwaharaParams) -> Result<Self, String> {
        let KuwaharaParams {
            method,
            radius,
            sectors,
            sharpness,
            border,
            border_value,
        } = params;
        if !(1..=MAX_RADIUS).contains(&radius) {
            return Err(format!(
                "`radius` must be between 1 and {MAX_RADIUS} px, got {radius}"
            ));
        }
        if method == KuwaharaMethod::Generalized && !(3..=MAX_SECTORS).contains(&sectors) {
            return Err(format!(
                "`sectors` must be between 3 and {MAX_SECTORS}, got {sectors}"
            ));
        }
        if !(1..=32).contains(&sharpness) {
            return Err(format!(
                "`sharpness` must be between 1 and 32, got {sharpness}"
            ));
        }
        check_border_value(border, border_value)?;
        Ok(Kuwahara {
            method,
            radius: radius as usize,
            sectors: sectors as usize,
            sharpness,
            border,
            border_value,
        })
    }
}

impl Operator for Kuwahara {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = kuwahara(
            image,
            self.method,
            self.radius,
            self.sectors,
            self.sharpness,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// One window pixel's membership of one sector.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Tap {
    dy: usize,
    dx: usize,
    sector: usize,
    weight: f32,
}

/// Taps of the generalized filter: the disc of radius `r`, `n` sectors (offsets from the
/// window's corner at `(−r, −r)`).
fn generalized_taps(r: usize, n: usize) -> Vec<Tap> {
    let ri = r as i64;
    let sigma = r as f64 / 2.0;
    let width = std::f64::consts::TAU / n as f64;
    let mut taps = Vec::new();
    for i in -ri..=ri {
        for j in -ri..=ri {
            let rho2 = (i * i + j * j) as f64;
            if rho2 > (ri * ri) as f64 {
                continue;
            }
            let radial = (-rho2 / (2.0 * sigma * sigma)).exp();
            let (dy, dx) = ((i + ri) as usize, (j + ri) as usize);
            if i == 0 && j == 0 {
                for sector in 0..n {
                    taps.push(Tap {
                        dy,
                        dx,
                        sector,
                        weight: (radial / n as f64) as f32,
                    });
                }
                continue;
            }
            // Angle in units of the sector width, in [0, n).
            let u = (i as f64).atan2(j as f64).rem_euclid(std::f64::consts::TAU) / width;
            let below = (u.floor() as usize).min(n - 1);
            let t = u - below as f64;
            let c = (std::f64::consts::FRAC_PI_2 * t).cos();
            for (sector, a) in [(below, c * c), ((below + 1) % n, 1.0 - c * c)] {
                if a > 0.0 {
                    taps.push(Tap {
                        dy,
                        dx,
                        sector,
                        weight: (radial * a) as f32,
                    });
                }
            }
        }
    }
    taps
}

/// Taps of the classic filter: four `(r+1)²` quadrants with weight 1, in the order above left,
/// above right, below left, below right.
fn classic_taps(r: usize) -> Vec<Tap> {
    let mut taps = Vec::new();
    for (sector, (y0, x0)) in [(0, 0), (0, r), (r, 0), (r, r)].into_iter().enumerate() {
        for dy in y0..=y0 + r {
            for dx in x0..=x0 + r {
                taps.push(Tap {
                    dy,
                    dx,
                    sector,
                    weight: 1.0,
                });
            }
        }
    }
    taps
}

/// Kuwahara filter of `image` (see the module and operator docs): `method`, window `radius`
/// (px, at least 1), `sectors` (generalized only, 3..=16), sharpness exponent `sharpness`;
/// pixels outside the image are read through `border` (`border_value` for the constant mode, in
/// the image's units).
pub fn kuwahara(
    image: &Image,
    method: KuwaharaMethod,
    radius: usize,
    sectors: usize,
    sharpness: u32,
    border: BorderMode,
    border_value: f64,
) -> Image {
    if image.is_empty() {
        return image.clone();
    }
    let r = radius.clamp(1, MAX_RADIUS as usize);
    let (taps, n) = match method {
        KuwaharaMethod::Generalized => {
            let n = sectors.clamp(3, MAX_SECTORS as usize);
            (generalized_taps(r, n), n)
        }
        KuwaharaMethod::Classic => (classic_taps(r), 4),
    };
    let g = Geometry {
        width: image.width(),
        radius: r,
        columns: BorderTable::symmetric(image.width(), r, border),
        rows: BorderTable::symmetric(image.height(), r, border),
        taps,
        sectors: n,
        method,
        sharpness: sharpness.max(1) as i32,
    };
    let c = image.channels().count();
    let integer = |max: f64| border_value.round_ties_even().clamp(0.0, max);
    let data = match image.data() {
        PixelData::U8(src) => PixelData::U8(by_channels(src, &g, c, integer(255.0), 1.0, |x| {
            x.round().clamp(0.0, 255.0) as u8
        })),
        PixelData::U16(src) => {
            PixelData::U16(by_channels(src, &g, c, integer(65535.0), 257.0, |x| {
                (x * 257.0).round().clamp(0.0, 65535.0) as u16
            }))
        }
        PixelData::F32(src) => {
            PixelData::F32(by_channels(src, &g, c, border_value, 1.0 / 255.0, |x| {
                (x / 255.0) as f32
            }))
        }
    };
    Image::new(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

struct Geometry {
    width: usize,
    radius: usize,
    columns: BorderTable,
    rows: BorderTable,
    taps: Vec<Tap>,
    sectors: usize,
    method: KuwaharaMethod,
    sharpness: i32,
}

/// Samples convertible to f32.
trait Sample: Copy + Default + Send + Sync + 'static {
    fn to_f32(self) -> f32;
}

impl Sample for u8 {
    fn to_f32(self) -> f32 {
        self as f32
    }
}

impl Sample for u16 {
    fn to_f32(self) -> f32 {
        self as f32
    }
}

impl Sample for f32 {
    fn to_f32(self) -> f32 {
        self
    }
}

/// Dispatches on the channel count; `unit` is one 8-bit gray level in sample units.
fn by_channels<T: Sample, O: Copy + Default + Send>(
    src: &[T],
    g: &Geometry,
    c: usize,
    border_value: f64,
    unit: f32,
    finish: impl Fn(f64) -> O + Sync,
) -> Vec<O> {
    let constant = (border_value / unit as f64) as f32;
    let scale = 1.0 / unit;
    // (`border_value` arrives rounded and saturated for integer images.)
    match c {
        1 => bands::<T, O, 1>(src, g, constant, scale, finish),
        3 => bands::<T, O, 3>(src, g, constant, scale, finish),
        _ => bands::<T, O, 4>(src, g, constant, scale, finish),
    }
}

fn bands<T: Sample, O: Copy + Default + Send, const C: usize>(
    src: &[T],
    g: &Geometry,
    constant: f32,
    scale: f32,
    finish: impl Fn(f64) -> O + Sync,
) -> Vec<O> {
    let n = g.width * C;
    let mut dst = ocellus_engine::buffer::zeroed::<O>(src.len());
    if n == 0 {
        return dst;
    }
    let stride = g.columns.padded_len() * C;
    let r = g.radius;
    dst.par_chunks_mut(BAND_ROWS * n)
        .enumerate()
        .for_each(|(b, out)| {
            let rows = out.len() / n;
            let y0 = b * BAND_ROWS;
            let mut padded = vec![constant; (rows + 2 * r) * stride];
            for (j, line) in padded.chunks_exact_mut(stride).enumerate() {
                match g
                    .rows
                    .source(y0 + j)
                    .and_then(|s| src.get(s * n..(s + 1) * n))
                {
                    Some(row) => g
                        .columns
                        .pad_row_with(row, C, constant, line, |x| x.to_f32() * scale),
                    None => line.fill(constant),
                }
            }
            // Tap offsets relative to the window corner of the first pixel of a row.
            let offsets: Vec<(usize, usize, f32)> = g
                .taps
                .iter()
                .map(|t| (t.dy * stride + t.dx * C, t.sector, t.weight))
                .collect();
            for (i, line) in out.chunks_exact_mut(n).enumerate() {
                for (x, pixel) in line.chunks_exact_mut(C).enumerate() {
                    let corner = i * stride + x * C;
                    let mut weight = [0.0f32; MAX_SECTORS as usize];
                    let mut sum = [[0.0f32; C]; MAX_SECTORS as usize];
                    let mut squares = [[0.0f32; C]; MAX_SECTORS as usize];
                    for &(offset, sector, w) in &offsets {
                        let (Some(v), Some(ws), Some(s), Some(q)) = (
                            padded.get(corner + offset..corner + offset + C),
                            weight.get_mut(sector),
                            sum.get_mut(sector),
                            squares.get_mut(sector),
                        ) else {
                            continue;
                        };
                        *ws += w;
                        for ch in 0..C {
                            s[ch] += w * v[ch];
                            q[ch] += w * v[ch] * v[ch];
                        }
                    }
                    let mean = combine::<C>(g, &weight, &sum, &squares);
                    for (o, m) in pixel.iter_mut().zip(mean) {
                        *o = finish(m);
                    }
                }
            }
        });
    dst
}

/// The output pixel (8-bit units) from the per-sector sums.
fn combine<const C: usize>(
    g: &Geometry,
    weight: &[f32],
    sum: &[[f32; C]],
    squares: &[[f32; C]],
) -> [f64; C] {
    let mut total = [0.0f64; C];
    let mut alpha_sum = 0.0f64;
    let mut best: Option<(f64, [f64; C])> = None;
    for ((&w, s), q) in weight.iter().zip(sum).zip(squares).take(g.sectors) {
        if w <= 0.0 {
            continue;
        }
        let w = w as f64;
        let mut mean = [0.0f64; C];
        let mut variance = 0.0f64;
        for ch in 0..C {
            let m = s[ch] as f64 / w;
            mean[ch] = m;
            variance += (q[ch] as f64 / w - m * m).max(0.0);
        }
        let sigma = variance.sqrt();
        match g.method {
            KuwaharaMethod::Classic => {
                if best.is_none_or(|(v, _)| variance < v) {
                    best = Some((variance, mean));
                }
            }
            KuwaharaMethod::Generalized => {
                let alpha = 1.0 / (1.0 + sigma.powi(g.sharpness));
                alpha_sum += alpha;
                for ch in 0..C {
                    total[ch] += alpha * mean[ch];
                }
            }
        }
    }
    match g.method {
        KuwaharaMethod::Classic => best.map(|(_, m)| m).unwrap_or(total),
        KuwaharaMethod::Generalized => {
            if alpha_sum > 0.0 {
                for t in &mut total {
                    *t /= alpha_sum;
                }
            }
            total
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

    const G: KuwaharaMethod = KuwaharaMethod::Generalized;
    const K: KuwaharaMethod = KuwaharaMethod::Classic;

    fn samples(img: &Image) -> Vec<f64> {
        match img.data() {
            PixelData::U8(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::U16(d) => d.iter().map(|&x| x as f64).collect(),
            PixelData::F32(d) => d.iter().map(|&x| x as f64).collect(),
        }
    }

    #[test]
    fn classic_by_hand() {
        // Centre pixel, radius 1: the quadrant above left {10, 10, 10, 13} varies least; its
        // mean 10.75 rounds to 11.
        let img = Image::from_u8(
            3,
            3,
            Channels::Gray,
            vec![10, 10, 90, 10, 13, 80, 70, 60, 50],
        )
        .unwrap();
        let out = kuwahara(&img, K, 1, 4, 8, BorderMode::Reflect101, 0.0);
        assert_eq!(out.as_u8().unwrap()[4], 11);
    }

    #[test]
    fn sector_weights_partition_the_disc() {
        for n in [3, 4, 8, 16] {
            let taps = generalized_taps(4, n);
            let mut per_pixel = std::collections::BTreeMap::new();
            for t in &taps {
                assert!(t.sector < n && t.weight > 0.0);
                *per_pixel.entry((t.dy, t.dx)).or_insert(0.0f64) += t.weight as f64;
            }
            for (&(dy, dx), &w) in &per_pixel {
                let rho2 = (dy as f64 - 4.0).powi(2) + (dx as f64 - 4.0).powi(2);
                assert!((w - (-rho2 / 8.0).exp()).abs() < 1e-6, "n {n} ({dy}, {dx})");
            }
            // Every sector gets pixels.
            for s in 0..n {
                assert!(taps.iter().any(|t| t.sector == s && (t.dy, t.dx) != (4, 4)));
            }
        }
        assert_eq!(classic_taps(2).len(), 4 * 9);
    }

    #[test]
    fn constant_images_are_unchanged() {
        let u8c = Image::from_u8(17, 9, Channels::Rgb, vec![201; 17 * 9 * 3]).unwrap();
        let u16c = Image::from_u16(17, 9, Channels::Gray, vec![31337; 17 * 9]).unwrap();
        for method in [G, K] {
            for border in MODES.into_iter().filter(|&b| b != BorderMode::Constant) {
                assert_eq!(kuwahara(&u8c, method, 4, 8, 8, border, 0.0), u8c);
                assert_eq!(kuwahara(&u16c, method, 3, 5, 8, border, 0.0), u16c);
            }
        }
        let f = Image::from_f32(9, 9, Channels::Rgba, vec![0.3; 9 * 9 * 4]).unwrap();
        let out = kuwahara(&f, G, 3, 8, 8, BorderMode::Clamp, 0.0);
        assert!(
            out.as_f32()
                .unwrap()
                .iter()
                .all(|&x| (x - 0.3).abs() < 1e-5)
        );
    }

    #[test]
    fn step_edges_are_not_blurred() {
        let (w, h) = (30, 12);
        let data: Vec<u8> = (0..h)
            .flat_map(|_| (0..w).map(|x| if x < 15 { 20 } else { 220 }))
            .collect();
        let img = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        for method in [G, K] {
            assert_eq!(
                kuwahara(&img, method, 5, 8, 8, BorderMode::Reflect101, 0.0),
                img
            );
        }
        // A Gaussian-like mean would mix the two sides.
        let vertical: Vec<u8> = (0..20)
            .flat_map(|y| (0..10).map(move |_| if y < 7 { 0 } else { 255 }))
            .collect();
        let img = Image::from_u8(10, 20, Channels::Gray, vertical).unwrap();
        assert_eq!(kuwahara(&img, G, 4, 6, 8, BorderMode::Clamp, 0.0), img);
    }

    #[test]
    fn smooths_noise() {
        let n = 40 * 40;
        let noisy: Vec<u8> = randoms(5, n)
            .iter()
            .map(|r| 100 + (r * 40.0) as u8)
            .collect();
        let img = Image::from_u8(40, 40, Channels::Gray, noisy).unwrap();
        let out = kuwahara(&img, G, 4, 8, 8, BorderMode::Reflect101, 0.0);
        let var = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64
        };
        assert!(var(&samples(&out)) < var(&samples(&img)) / 4.0);
    }

    #[test]
    fn params_tiny_images_and_threads() {
        let p = |f: fn(&mut KuwaharaParams)| {
            let mut p = KuwaharaParams::default();
            f(&mut p);
            Kuwahara::new(p)
        };
        assert!(p(|_| ()).is_ok());
        assert!(p(|p| p.radius = 0).unwrap_err().contains("radius"));
        assert!(p(|p| p.radius = 65).is_err());
        assert!(p(|p| p.sectors = 2).unwrap_err().contains("sectors"));
        assert!(
            p(|p| {
                p.sectors = 2;
                p.method = KuwaharaMethod::Classic
            })
            .is_ok()
        );
        assert!(p(|p| p.sharpness = 0).unwrap_err().contains("sharpness"));
        assert!(p(|p| p.border_value = f64::NAN).is_err());
        let one = Image::from_u16(1, 1, Channels::Rgb, vec![1, 2, 3]).unwrap();
        for border in MODES {
            let out = kuwahara(&one, G, 3, 8, 8, border, 0.0);
            assert_eq!(out.format(), one.format());
        }
        assert_eq!(kuwahara(&one, K, 3, 8, 8, BorderMode::Clamp, 0.0), one);
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(kuwahara(&empty, G, 3, 8, 8, BorderMode::Clamp, 0.0), empty);
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_u8(41, 53, Channels::Rgb, 3);
        let run = || kuwahara(&img, G, 4, 8, 8, BorderMode::Reflect101, 0.0);
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn output_lies_within_the_window(
            w in 1usize..16,
            h in 1usize..16,
            r in 1usize..5,
            n in 3usize..=16,
            q in 1u32..=32,
            classic in any::<bool>(),
            channels in prop::sample::select(vec![Channels::Gray, Channels::Rgb, Channels::Rgba]),
            border in prop::sample::select(MODES.to_vec()),
            seed in any::<u64>(),
        ) {
            let img = random_u8(w, h, channels, seed);
            let method = if classic { K } else { G };
            let value = if border == BorderMode::Constant { 77.0 } else { 0.0 };
            let out = samples(&kuwahara(&img, method, r, n, q, border, value));
            let s = samples(&img);
            let c = channels.count();
            let ri = r as isize;
            for y in 0..h {
                for x in 0..w {
                    for ch in 0..c {
                        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                        for dy in -ri..=ri {
                            for dx in -ri..=ri {
                                let v = match (map_index(x as isize + dx, w, border), map_index(y as isize + dy, h, border)) {
                                    (Some(xx), Some(yy)) => s[(yy * w + xx) * c + ch],
                                    _ => value,
                                };
                                lo = lo.min(v);
                                hi = hi.max(v);
                            }
                        }
                        let o = out[(y * w + x) * c + ch];
                        prop_assert!(lo <= o && o <= hi, "{} not in [{}, {}]", o, lo, hi);
                    }
                }
            }
        }
    }
}
