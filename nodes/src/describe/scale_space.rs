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
//! Blurs use `filter.gaussian`'s kernels with `round(8σ + 1) | 1` taps (OpenCV's size for float
//! images) and reflect-101 borders (OpenCV's `GaussianBlur` default), in a dedicated separable
//! pass for symmetric kernels on f32 planes ([`blur`]); blurs and the DoG subtraction run over
//! fixed row bands in parallel. All of it is bit-identical for any thread count.
//!
//! Reference: D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV
//! 60(2), 2004; OpenCV `SIFT_Impl::buildGaussianPyramid`, `buildDoGPyramid`.

use rayon::prelude::*;

use crate::filter::gaussian::gaussian_kernel;

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
///
/// Kernel: `filter.gaussian`'s [`gaussian_kernel`] of [`kernel_size`] taps. The passes exploit
/// its symmetry (`k_j·(a + b)` per pair of taps, half the multiplies) and run column pass first,
/// straight from the source rows, then the row pass on a padded copy of that one row; both are
/// AVX2-compiled loops over whole rows. Bands of [`BAND_ROWS`] output rows run in parallel.
pub fn blur(plane: &Plane, sigma: f64) -> Plane {
    if sigma.is_nan() || sigma <= 0.0 || plane.data.is_empty() {
        return plane.clone();
    }
    let full = gaussian_kernel(kernel_size(sigma), sigma);
    let half: Vec<f32> = full[full.len() / 2..].iter().map(|&v| v as f32).collect();
    let (w, h) = (plane.width, plane.height);
    let mut data = vec![0f32; w * h];
    data.par_chunks_mut(w * BAND_ROWS)
        .enumerate()
        .for_each(|(band, out)| {
            let y0 = band * BAND_ROWS;
            blur_rows(&plane.data, w, h, &half, y0, out);
        });
    Plane::new(w, h, data)
}

/// Reflect-101 index of `i` (may be negative or ≥ n) for a length `n` ≥ 1.
fn reflect101(i: isize, n: usize) -> usize {
    if n <= 1 {
        return 0;
    }
    let n = n as isize;
    let period = 2 * (n - 1);
    let mut i = i.rem_euclid(period);
    if i >= n {
        i = period - i;
    }
    i as usize
}

/// `acc[x] = k[0]·c[x] + Σ_{j ≥ 1} k[j]·(a_j[x] + b_j[x])` for the row pairs `(a_j, b_j)`.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn symmetric_rows(k: &[f32], centre: &[f32], pairs: &[(&[f32], &[f32])], acc: &mut [f32]) {
    let n = acc.len().min(centre.len());
    let k0 = k[0];
    for (a, &c) in acc[..n].iter_mut().zip(&centre[..n]) {
        *a = k0 * c;
    }
    for (&(p, q), &w) in pairs.iter().zip(&k[1..]) {
        let n = n.min(p.len()).min(q.len());
        for ((a, &u), &v) in acc[..n].iter_mut().zip(&p[..n]).zip(&q[..n]) {
            *a += w * (u + v);
        }
    }
}

/// `out[x] = k[0]·p[x + R] + Σ_{j ≥ 1} k[j]·(p[x + R − j] + p[x + R + j])`, `R = k.len() − 1`.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn symmetric_cols(k: &[f32], padded: &[f32], out: &mut [f32]) {
    let r = k.len() - 1;
    let n = out.len();
    if padded.len() < n + 2 * r {
        return;
    }
    let k0 = k[0];
    for (o, &c) in out.iter_mut().zip(&padded[r..r + n]) {
        *o = k0 * c;
    }
    for (j, &w) in k.iter().enumerate().skip(1) {
        let left = &padded[r - j..r - j + n];
        let right = &padded[r + j..r + j + n];
        for ((o, &u), &v) in out.iter_mut().zip(left).zip(right) {
            *o += w * (u + v);
        }
    }
}

/// Output rows `y0..` of the blur of a `w × h` plane with half kernel `k` (centre first) into
/// `out` (whole rows).
fn blur_rows(src: &[f32], w: usize, h: usize, k: &[f32], y0: usize, out: &mut [f32]) {
    let r = k.len() - 1;
    let mut col = vec![0f32; w];
    let mut padded = vec![0f32; w + 2 * r];
    let row = |y: usize| &src[y * w..(y + 1) * w];
    let mut pairs: Vec<(&[f32], &[f32])> = Vec::with_capacity(r);
    for (y, dst) in (y0..).zip(out.chunks_exact_mut(w)) {
        pairs.clear();
        pairs.extend((1..=r).map(|j| {
            (
                row(reflect101(y as isize - j as isize, h)),
                row(reflect101((y + j) as isize, h)),
            )
        }));
        symmetric_rows(k, row(y), &pairs, &mut col);
        padded[r..r + w].copy_from_slice(&col);
        for j in 1..=r {
            padded[r - j] = col[reflect101(-(j as isize), w)];
            padded[r + w - 1 + j] = col[reflect101((w - 1 + j) as isize, w)];
        }
        symmetric_cols(k, &padded, dst);
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
                let other = if oy.is_multiple_of(2) {
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

/// Builds `octaves` octaves of `layers + 3` Gaussians and their DoGs from `base`, which must
/// already have blur `sigma`. Stops early when an octave would be empty.
pub fn build(base: Plane, octaves: usize, layers: usize, sigma: f64) -> ScaleSpace {
    let mut space = build_gaussians(base, octaves, layers, sigma);
    space.dogs = space
        .gaussians
        .iter()
        .map(|oct| oct.windows(2).map(|p| difference(&p[1], &p[0])).collect())
        .collect();
    space
}

/// As [`build`] without the DoG planes (`dogs` is empty), for callers that compute DoG samples
/// on the fly.
pub fn build_gaussians(base: Plane, octaves: usize, layers: usize, sigma: f64) -> ScaleSpace {
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
    ScaleSpace {
        layers,
        gaussians,
        dogs: Vec::new(),
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
    fn blur_matches_direct_2d_reflect101() {
        for &(w, h, sigma) in &[
            (37usize, 23usize, 1.2f64),
            (5, 4, 1.6),
            (1, 1, 0.8),
            (64, 3, 3.1),
        ] {
            let src: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 251) as f32).collect();
            let p = Plane::new(w, h, src.clone());
            let out = blur(&p, sigma);
            let k = gaussian_kernel(kernel_size(sigma), sigma);
            let r = (k.len() / 2) as isize;
            for y in 0..h {
                for x in 0..w {
                    let mut acc = 0f64;
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let yy = reflect101(y as isize + dy, h);
                            let xx = reflect101(x as isize + dx, w);
                            acc += k[(dy + r) as usize]
                                * k[(dx + r) as usize]
                                * f64::from(src[yy * w + xx]);
                        }
                    }
                    let d = (acc - f64::from(out.at(x, y))).abs();
                    assert!(d < 1e-3, "{w}×{h} σ {sigma} at ({x}, {y}): {d}");
                }
            }
        }
        assert_eq!(reflect101(-1, 5), 1);
        assert_eq!(reflect101(5, 5), 3);
        assert_eq!(reflect101(-7, 3), 1);
    }

    #[test]
    fn tiny_octaves_stop() {
        let s = build(Plane::new(3, 3, vec![1.0; 9]), 5, 3, 1.6);
        assert_eq!(s.gaussians.len(), 2); // 3×3, 1×1; 0×0 stops.
        let e = build(Plane::new(0, 0, vec![]), 3, 3, 1.6);
        assert!(e.gaussians.is_empty());
    }
}
