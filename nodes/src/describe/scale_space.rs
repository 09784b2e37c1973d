//! Gaussian scale space and difference-of-Gaussians (DoG) pyramid, as used by SIFT (Lowe 2004,
//! §3) and reusable by any blob / scale-invariant detector.
//!
//! Planes are gray f32 [`Image`]s. An octave holds `layers + 3` Gaussian images whose blur grows
//! by a factor `k = 2^(1/layers)` from one to the next (`σ_i = σ·k^i` relative to the octave's
//! sampling), obtained by *incremental* blurring: image `i` is image `i − 1` blurred with
//! `√(σ_i² − σ_{i−1}²)`. The first image of the next octave is image `layers` (blur `2σ`) of the
//! previous one sampled at every second pixel, so every octave starts at blur `σ` in its own
//! pixels. DoG image `i` is Gaussian `i + 1` minus Gaussian `i`.
//!
//! Blurs run on the separable engine of `filter.gaussian` (f32 accumulation, reflect-101 border
//! like OpenCV's `GaussianBlur` default) with kernels of `round(8σ + 1) | 1` taps, OpenCV's size
//! for float images; the DoG subtraction runs over fixed row bands in parallel. All of it is
//! bit-identical for any thread count.
//!
//! Reference: D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV
//! 60(2), 2004; OpenCV `SIFT_Impl::buildGaussianPyramid`, `buildDoGPyramid`.

use ocellus_engine::value::{Channels, Image, PixelData};
use rayon::prelude::*;

use crate::filter::border::BorderMode;
use crate::filter::gaussian::{gaussian_kernel, separable_filter};

/// Rows per parallel band of the plane-wise loops.
const BAND_ROWS: usize = 32;

/// A gray f32 plane: `width × height` samples, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Samples, row-major, `width · height` long.
    pub data: Vec<f32>,
}

impl Plane {
    /// A plane of `data` (must be `width · height` long).
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Plane {
        debug_assert_eq!(data.len(), width * height);
        Plane {
            width,
            height,
            data,
        }
    }

    /// Sample at column `x`, row `y` (no bounds check beyond the slice's).
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Row `y`.
    #[inline]
    pub fn row(&self, y: usize) -> &[f32] {
        &self.data[y * self.width..(y + 1) * self.width]
    }
}

/// The kernel size used for a blur of `sigma`: `round(8σ + 1) | 1` (OpenCV's rule for float
/// images), at least 3.
pub fn kernel_size(sigma: f64) -> usize {
    (((sigma * 8.0 + 1.0).round() as usize) | 1).max(3)
}

/// Gaussian blur of a plane by `sigma` (px), reflect-101 border. `sigma ≤ 0` copies.
pub fn blur(plane: &Plane, sigma: f64) -> Plane {
    if !(sigma > 0.0) || plane.data.is_empty() {
        return plane.clone();
    }
    let kernel = gaussian_kernel(kernel_size(sigma), sigma);
    let image = match Image::new(
        plane.width,
        plane.height,
        Channels::Gray,
        PixelData::F32(plane.data.clone()),
    ) {
        Ok(image) => image,
        Err(_) => return plane.clone(),
    };
    let out = separable_filter(&image, &kernel, &kernel, BorderMode::Reflect101, 0.0);
    match out.into_data() {
        PixelData::F32(data) => Plane::new(plane.width, plane.height, data),
        _ => plane.clone(),
    }
}

/// Bilinear ×2 upsampling with pixel-centre alignment (OpenCV's `resize` `INTER_LINEAR` to twice
/// the size): output sample `X` reads the input at `X/2 − 0.25`, edges replicated. So output
/// pixel `X` covers input position `X/2 − 0.25`, and input position `x` is output `2x + 0.5`.
pub fn upsample2(plane: &Plane) -> Plane {
    let (w, h) = (plane.width, plane.height);
    let (ow, oh) = (w * 2, h * 2);
    if w == 0 || h == 0 {
        return Plane::new(ow, oh, Vec::new());
    }
    // Horizontal pass for one input row into a 2w row: out[2x] = .75 s[x] + .25 s[x−1],
    // out[2x+1] = .75 s[x] + .25 s[x+1] (indices clamped).
    let horizontal = |src: &[f32], dst: &mut [f32]| {
        for x in 0..w {
            let left = src[x.saturating_sub(1)];
            let right = src[(x + 1).min(w - 1)];
            let c = src[x];
            dst[2 * x] = 0.75 * c + 0.25 * left;
            dst[2 * x + 1] = 0.75 * c + 0.25 * right;
        }
    };
    let mut data = vec![0f32; ow * oh];
    data.par_chunks_mut(ow * BAND_ROWS)
        .enumerate()
        .for_each(|(band, chunk)| {
            let y0 = band * BAND_ROWS;
            let mut a = vec![0f32; ow];
            let mut b = vec![0f32; ow];
            for (k, out) in chunk.chunks_exact_mut(ow).enumerate() {
                let oy = y0 + k;
                let y = oy / 2;
                // Output row 2y reads rows y and y − 1; 2y + 1 reads y and y + 1.
                let other = if oy % 2 == 0 {
                    y.saturating_sub(1)
                } else {
                    (y + 1).min(h - 1)
                };
                horizontal(plane.row(y), &mut a);
                horizontal(plane.row(other), &mut b);
                for ((o, &p), &q) in out.iter_mut().zip(&a).zip(&b) {
                    *o = 0.75 * p + 0.25 * q;
                }
            }
        });
    Plane::new(ow, oh, data)
}

/// Every second sample of every second row, starting at (0, 0): `⌊w/2⌋ × ⌊h/2⌋` (OpenCV's
/// `resize` `INTER_NEAREST` to half size, used between SIFT octaves).
pub fn downsample2(plane: &Plane) -> Plane {
    let (ow, oh) = (plane.width / 2, plane.height / 2);
    let mut data = Vec::with_capacity(ow * oh);
    for y in 0..oh {
        let row = plane.row(2 * y);
        data.extend(row.iter().step_by(2).take(ow));
    }
    Plane::new(ow, oh, data)
}

/// `a − b` sample-wise (same sizes), in parallel row bands.
pub fn difference(a: &Plane, b: &Plane) -> Plane {
    let w = a.width.max(1);
    let mut data = vec![0f32; a.data.len()];
    data.par_chunks_mut(w * BAND_ROWS)
        .zip(a.data.par_chunks(w * BAND_ROWS))
        .zip(b.data.par_chunks(w * BAND_ROWS))
        .for_each(|((d, x), y)| {
            for ((d, &x), &y) in d.iter_mut().zip(x).zip(y) {
                *d = x - y;
            }
        });
    Plane::new(a.width, a.height, data)
}

/// The incremental blurs of one octave: `sigmas[0] = σ` (the blur the octave's first image is
/// assumed to have) and `sigmas[i] = √((σk^i)² − (σk^(i−1))²)` for `i = 1..layers + 3`.
pub fn incremental_sigmas(sigma: f64, layers: usize) -> Vec<f64> {
    let k = 2f64.powf(1.0 / layers as f64);
    let mut sig = vec![sigma];
    for i in 1..layers + 3 {
        let prev = k.powi(i as i32 - 1) * sigma;
        let total = prev * k;
        sig.push((total * total - prev * prev).sqrt());
    }
    sig
}

/// A Gaussian scale space and its DoG.
#[derive(Debug, Clone)]
pub struct ScaleSpace {
    /// DoG layers per octave (`s`); an octave holds `s + 3` Gaussians and `s + 2` DoGs.
    pub layers: usize,
    /// `gaussians[o][i]`: octave `o`, blur `σ·k^i` in the octave's pixels.
    pub gaussians: Vec<Vec<Plane>>,
    /// `dogs[o][i] = gaussians[o][i + 1] − gaussians[o][i]`.
    pub dogs: Vec<Vec<Plane>>,
}

/// Builds `octaves` octaves of `layers + 3` Gaussians from `base`, which must already have blur
/// `sigma`. Stops early when an octave would be empty.
pub fn build(base: Plane, octaves: usize, layers: usize, sigma: f64) -> ScaleSpace {
    let sig = incremental_sigmas(sigma, layers);
    let mut gaussians: Vec<Vec<Plane>> = Vec::with_capacity(octaves);
    let mut first = base;
    for o in 0..octaves {
        if o > 0 {
            let Some(prev) = gaussians.last() else { break };
            first = downsample2(&prev[layers]);
        }
        if first.width == 0 || first.height == 0 {
            break;
        }
        let mut octave = Vec::with_capacity(layers + 3);
        octave.push(first.clone());
        for &s in &sig[1..] {
            let Some(last) = octave.last() else { break };
            let next = blur(last, s);
            octave.push(next);
        }
        gaussians.push(octave);
    }
    let dogs = gaussians
        .iter()
        .map(|oct| oct.windows(2).map(|p| difference(&p[1], &p[0])).collect())
        .collect();
    ScaleSpace {
        layers,
        gaussians,
        dogs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sigmas_compose_to_octave_doubling() {
        let s = incremental_sigmas(1.6, 3);
        assert_eq!(s.len(), 6);
        // Blurring incrementally reaches σ·k^i: total² = σ² + Σ increments².
        let mut total2 = 1.6f64 * 1.6;
        for (i, &inc) in s.iter().enumerate().skip(1) {
            total2 += inc * inc;
            let want = 1.6 * 2f64.powf(i as f64 / 3.0);
            assert!((total2.sqrt() - want).abs() < 1e-12, "{i}");
        }
        // Image `layers` has twice the base blur.
        let t3: f64 = 1.6f64.powi(2) + s[1..4].iter().map(|v| v * v).sum::<f64>();
        assert!((t3.sqrt() - 3.2).abs() < 1e-12);
    }

    #[test]
    fn upsample_hand_case() {
        let p = Plane::new(2, 1, vec![0.0, 4.0]);
        let u = upsample2(&p);
        assert_eq!((u.width, u.height), (4, 2));
        assert_eq!(&u.data[..4], &[0.0, 1.0, 3.0, 4.0]);
        assert_eq!(&u.data[4..], &[0.0, 1.0, 3.0, 4.0]);
        let v = upsample2(&Plane::new(1, 2, vec![0.0, 8.0]));
        assert_eq!(v.data, vec![0.0, 0.0, 2.0, 2.0, 6.0, 6.0, 8.0, 8.0]);
    }

    #[test]
    fn downsample_and_difference() {
        let p = Plane::new(5, 3, (0..15).map(|v| v as f32).collect());
        let d = downsample2(&p);
        assert_eq!((d.width, d.height), (2, 1));
        assert_eq!(d.data, vec![0.0, 2.0]);
        let z = difference(&p, &p);
        assert!(z.data.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn constant_stays_constant_and_dog_is_zero() {
        let p = Plane::new(40, 30, vec![7.5; 1200]);
        let s = build(p, 3, 3, 1.6);
        assert_eq!(s.gaussians.len(), 3);
        assert_eq!(s.gaussians[2][0].width, 10);
        for oct in &s.dogs {
            assert_eq!(oct.len(), 5);
            for d in oct {
                assert!(d.data.iter().all(|&v| v.abs() < 1e-5));
            }
        }
    }

    #[test]
    fn blur_preserves_mean_of_smooth_ramp_interior() {
        // A linear ramp is a fixed point of a symmetric normalised kernel (away from borders).
        let w = 64;
        let p = Plane::new(w, 8, (0..w * 8).map(|i| (i % w) as f32).collect());
        let b = blur(&p, 2.0);
        for x in 20..44 {
            assert!((b.at(x, 4) - x as f32).abs() < 1e-3);
        }
    }

    #[test]
    fn tiny_octaves_stop() {
        let s = build(Plane::new(3, 3, vec![1.0; 9]), 5, 3, 1.6);
        assert_eq!(s.gaussians.len(), 2); // 3×3, 1×1; 0×0 stops.
        let e = build(Plane::new(0, 0, vec![]), 3, 3, 1.6);
        assert!(e.gaussians.is_empty());
    }
}
