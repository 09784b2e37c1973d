//! Anisotropic Kuwahara filter.
//!
//! Implements the method of J. E. Kyprianidis, H. Kang and J. Döllner,
//! "Image and Video Abstraction by Anisotropic Kuwahara Filtering",
//! Computer Graphics Forum 28(7), 2009:
//!
//! 1. luminance (mean of the first three channels; the first channel for
//!    one- and two-channel images),
//! 2. Sobel gradients (clamped border) and the structure tensor
//!    `(E, F, G) = (gx², gx·gy, gy²)`, smoothed by a separable Gaussian,
//! 3. per pixel eigen-decomposition: orientation `φ` of the minor eigenvector
//!    (the local edge direction) and anisotropy `A = (λ1 − λ2) / (λ1 + λ2)`,
//! 4. an elliptical filter window with semi-axes `a = r·(α + A)/α` (along `φ`)
//!    and `b = r·α/(α + A)`, split into `N` sectors,
//! 5. per sector a weighted mean `m_i` and standard deviation `s_i`
//!    (norm over channels of the per-channel standard deviations) and the
//!    output `Σ m_i·w_i / Σ w_i` with `w_i = 1 / (1 + s_i^q)`.
//!
//! Simplifications with respect to the 2009 paper:
//!
//! * The sector weighting functions are the polynomial ("generalized")
//!   weights of Kyprianidis, Semmo, Kang and Döllner, "Anisotropic Kuwahara
//!   Filtering with Polynomial Weighting Functions" (TPCG 2010) instead of the
//!   paper's Gaussian-smoothed sector textures: in the unit-disk coordinates
//!   `v` of the ellipse, sector `i` (centred at angle `2πi/N`) has weight
//!   `max(0, (x' + ζ) − η·y'²)² · exp(−|v|²/(2·0.5²))`, where `(x', y')` is `v`
//!   rotated by `−2πi/N`, `ζ = 1/3` and `η = (ζ + cos(π/N)) / sin²(π/N)`.
//! * The semi-axes are clamped to `[0.5, 4·radius]` px and `radius` must not
//!   exceed 256 px, which bounds the sampling window.
//! * Samples are expected in `[0, 1]`. The deviation entering `w_i` is
//!   measured in 8-bit units (`s_i·255`, a choice of this implementation), so
//!   that `s_i^q ≫ 1` in textured regions and the weighting favours the most
//!   homogeneous sectors (for `s ≪ 1` the formula degenerates into plain
//!   averaging). For `s ≫ 1` the relative weights `∝ s_i^{−q}` do not depend
//!   on the intensity scale, so `[0, 255]` data work as well. The weights are
//!   evaluated in the log domain and normalised by the largest one, so they
//!   never underflow.
//!
//! The implementation is single-threaded and deterministic.

#![deny(clippy::unwrap_used, clippy::expect_used)]

use std::f32::consts::PI;
use std::sync::Mutex;

/// Parameters of [`anisotropic_kuwahara`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KuwaharaParams {
    /// Filter radius `r` in pixels (> 0, at most 256).
    pub radius: f32,
    /// Number of sectors `N` (4..=16, 8 typical).
    pub sectors: usize,
    /// Sharpness exponent `q` (≥ 0, 8 typical).
    pub sharpness: f32,
    /// Anisotropy tuning `α` (> 0, 1.0 typical); larger values give rounder windows.
    pub alpha: f32,
    /// Standard deviation in pixels of the Gaussian smoothing the structure tensor (≥ 0).
    pub tensor_sigma: f32,
}

impl Default for KuwaharaParams {
    fn default() -> Self {
        Self {
            radius: 6.0,
            sectors: 8,
            sharpness: 8.0,
            alpha: 1.0,
            tensor_sigma: 2.0,
        }
    }
}

impl KuwaharaParams {
    /// Checks the parameters.
    ///
    /// # Errors
    /// A description of the first invalid parameter: `radius` not in
    /// `(0, 256]`, `sectors` not in 4..=16, negative or non-finite
    /// `sharpness` / `tensor_sigma`, non-positive or non-finite `alpha`.
    pub fn validate(&self) -> Result<(), String> {
        if !self.radius.is_finite() || self.radius <= 0.0 || self.radius > MAX_RADIUS {
            return Err(format!(
                "radius must be finite and in (0, {MAX_RADIUS}], got {}",
                self.radius
            ));
        }
        if !(4..=16).contains(&self.sectors) {
            return Err(format!("sectors must be in 4..=16, got {}", self.sectors));
        }
        if !self.sharpness.is_finite() || self.sharpness < 0.0 {
            return Err(format!(
                "sharpness must be finite and >= 0, got {}",
                self.sharpness
            ));
        }
        if !self.alpha.is_finite() || self.alpha <= 0.0 {
            return Err(format!("alpha must be finite and > 0, got {}", self.alpha));
        }
        if !self.tensor_sigma.is_finite() || self.tensor_sigma < 0.0 {
            return Err(format!(
                "tensor_sigma must be finite and >= 0, got {}",
                self.tensor_sigma
            ));
        }
        Ok(())
    }
}

/// Largest accepted filter radius (bounds the sampling window).
const MAX_RADIUS: f32 = 256.0;
/// Factor applied to the sector deviations before the sharpness power:
/// deviations are measured in 8-bit units for `[0, 1]` data.
const DEVIATION_SCALE: f64 = 255.0;
/// Largest supported number of channels.
const MAX_CHANNELS: usize = 4;
/// Largest supported number of sectors.
const MAX_SECTORS: usize = 16;
/// Polynomial sector weight offset `ζ`.
const ZETA: f32 = 1.0 / 3.0;
/// Cap of the major semi-axis, in multiples of the radius.
const MAX_AXIS_FACTOR: f32 = 4.0;
/// Largest Gaussian kernel radius used for the tensor smoothing.
const MAX_KERNEL_RADIUS: usize = 256;

/// Applies the anisotropic Kuwahara filter.
///
/// `src` holds interleaved `f32` samples (`channels` in 1..=4; a fourth
/// channel, e.g. alpha, is filtered like the others), row-major, without
/// padding, so `src.len()` must equal `width * height * channels`.
/// Returns an image of the same layout. An empty image gives an empty output.
/// Samples are expected in `[0, 1]` (see the module docs on the sharpness
/// term); every output sample is a convex combination of input samples of
/// the same channel.
///
/// # Errors
/// Invalid parameters (see [`KuwaharaParams::validate`]), an unsupported
/// channel count or a buffer size mismatch.
pub fn anisotropic_kuwahara(
    src: &[f32],
    width: usize,
    height: usize,
    channels: usize,
    p: &KuwaharaParams,
) -> Result<Vec<f32>, String> {
    anisotropic_kuwahara_with(src, width, height, channels, p, &|n, body| {
        (0..n).for_each(body);
    })
}

/// Rows filtered by one task of [`anisotropic_kuwahara_with`].
pub const BAND_ROWS: usize = 16;

/// The body of one task: `body(i)` filters band `i`.
pub type BandBody<'a> = dyn Fn(usize) + Sync + 'a;

/// Runs `body(i)` for every `i < n`, in any order or concurrently.
pub type ParallelFor<'a> = dyn Fn(usize, &BandBody<'_>) + 'a;

/// [`anisotropic_kuwahara`] with the rows split into bands of [`BAND_ROWS`], run by
/// `parallel_for(n, body)`, which must call `body(i)` once for every `i < n`, in any order or
/// concurrently (e.g. the host's thread pool). Bands are independent and joined in order, so
/// the result does not depend on how they were scheduled.
///
/// # Errors
/// As [`anisotropic_kuwahara`], and if `parallel_for` skipped a band.
pub fn anisotropic_kuwahara_with(
    src: &[f32],
    width: usize,
    height: usize,
    channels: usize,
    p: &KuwaharaParams,
    parallel_for: &ParallelFor<'_>,
) -> Result<Vec<f32>, String> {
    p.validate()?;
    if !(1..=MAX_CHANNELS).contains(&channels) {
        return Err(format!("channels must be in 1..=4, got {channels}"));
    }
    let npx = width
        .checked_mul(height)
        .ok_or_else(|| "image size overflows".to_string())?;
    let len = npx
        .checked_mul(channels)
        .ok_or_else(|| "image size overflows".to_string())?;
    if src.len() != len {
        return Err(format!(
            "buffer size mismatch: expected {len} samples ({width}x{height}x{channels}), got {}",
            src.len()
        ));
    }
    if len == 0 {
        return Ok(Vec::new());
    }

    let luma: Vec<f32> = src
        .chunks_exact(channels)
        .map(|px| match px {
            [r, g, b, ..] => (r + g + b) / 3.0,
            [v, ..] => *v,
            [] => 0.0,
        })
        .collect();
    let tensor = structure_tensor(&luma, width, height, p.tensor_sigma);

    let n = p.sectors;
    let mut sec_cos = [0.0f32; MAX_SECTORS];
    let mut sec_sin = [0.0f32; MAX_SECTORS];
    for i in 0..n {
        let t = 2.0 * PI * i as f32 / n as f32;
        sec_cos[i] = t.cos();
        sec_sin[i] = t.sin();
    }
    let half = PI / n as f32;
    let eta = (ZETA + half.cos()) / (half.sin() * half.sin());
    let q = f64::from(p.sharpness);
    let paired = n.is_multiple_of(2);
    let rot_count = if paired { n / 2 } else { n };

    let xmax = (width - 1) as isize;
    let ymax = (height - 1) as isize;
    let amax = p.radius * MAX_AXIS_FACTOR;

    let bands = height.div_ceil(BAND_ROWS);
    let band_outputs: Vec<Mutex<Vec<f32>>> = (0..bands).map(|_| Mutex::new(Vec::new())).collect();
    let filter_band = |band: usize| {
        let rows = band * BAND_ROWS..((band + 1) * BAND_ROWS).min(height);
        let offset = rows.start * width * channels;
        let mut out = vec![0.0f32; rows.len() * width * channels];
        for y in rows {
            for x in 0..width {
                let idx = y * width + x;
                let t = tensor.get(idx).copied().unwrap_or([0.0; 3]);
                let (phi, aniso) = tensor_orientation(t);
                let a = (p.radius * (p.alpha + aniso) / p.alpha).clamp(0.5, amax);
                let b = (p.radius * p.alpha / (p.alpha + aniso)).clamp(0.5, amax);
                let (sphi, cphi) = phi.sin_cos();
                // Half extents of the bounding box of the rotated ellipse.
                let ex = ((a * cphi).powi(2) + (b * sphi).powi(2)).sqrt();
                let ey = ((a * sphi).powi(2) + (b * cphi).powi(2)).sqrt();
                let rx = ex.floor() as isize;
                let ry = ey.floor() as isize;
                let (ia, ib) = (1.0 / a, 1.0 / b);
                let qa = cphi * cphi * ia * ia + sphi * sphi * ib * ib;

                let base = idx * channels;
                let mut center = [0.0f32; MAX_CHANNELS];
                if let Some(px) = src.get(base..base + channels) {
                    center[..channels].copy_from_slice(px);
                }
                let mut s0 = [0.0f32; MAX_SECTORS];
                let mut s1 = [[0.0f32; MAX_CHANNELS]; MAX_SECTORS];
                let mut s2 = [[0.0f32; MAX_CHANNELS]; MAX_SECTORS];

                for dy in -ry..=ry {
                    let sy = (y as isize + dy).clamp(0, ymax) as usize;
                    let fdy = dy as f32;
                    // Columns of this row inside the ellipse: roots of a quadratic in dx.
                    let qb = 2.0 * fdy * cphi * sphi * (ia * ia - ib * ib);
                    let qc = fdy * fdy * (sphi * sphi * ia * ia + cphi * cphi * ib * ib) - 1.0;
                    let disc = qb * qb - 4.0 * qa * qc;
                    if disc < 0.0 {
                        continue;
                    }
                    let sq = disc.sqrt();
                    let lo = ((-qb - sq) / (2.0 * qa)).ceil().max(-(rx as f32)) as isize;
                    let hi = ((-qb + sq) / (2.0 * qa)).floor().min(rx as f32) as isize;
                    for dx in lo..=hi {
                        let fdx = dx as f32;
                        let vx = (fdx * cphi + fdy * sphi) * ia;
                        let vy = (-fdx * sphi + fdy * cphi) * ib;
                        let r2 = vx * vx + vy * vy;
                        if r2 > 1.0 {
                            continue;
                        }
                        let g = (-2.0 * r2).exp();
                        let sx = (x as isize + dx).clamp(0, xmax) as usize;
                        let sb = (sy * width + sx) * channels;
                        let Some(px) = src.get(sb..sb + channels) else {
                            continue;
                        };
                        let mut val = [0.0f32; MAX_CHANNELS];
                        for c in 0..channels {
                            val[c] = px[c] - center[c];
                        }
                        let mut accumulate = |i: usize, w: f32, val: &[f32; MAX_CHANNELS]| {
                            if let (Some(a0), Some(a1), Some(a2)) =
                                (s0.get_mut(i), s1.get_mut(i), s2.get_mut(i))
                            {
                                *a0 += w;
                                for c in 0..channels {
                                    let v = val[c];
                                    a1[c] += w * v;
                                    a2[c] += w * v * v;
                                }
                            }
                        };
                        // Sector i + N/2 is sector i mirrored through the centre, so for
                        // even N one rotation serves two sectors.
                        for i in 0..rot_count {
                            let xp = vx * sec_cos[i] + vy * sec_sin[i];
                            let yp = -vx * sec_sin[i] + vy * sec_cos[i];
                            let base = ZETA - eta * yp * yp;
                            let t1 = base + xp;
                            if t1 > 0.0 {
                                accumulate(i, t1 * t1 * g, &val);
                            }
                            if paired {
                                let t2 = base - xp;
                                if t2 > 0.0 {
                                    accumulate(i + rot_count, t2 * t2 * g, &val);
                                }
                            }
                        }
                    }
                }

                // Sector means and log-weights ln w_i = −ln(1 + (s_i·255)^q), normalised by
                // the largest weight so that no weight underflows.
                let mut means = [[0.0f64; MAX_CHANNELS]; MAX_SECTORS];
                let mut logw = [f64::NEG_INFINITY; MAX_SECTORS];
                let mut max_logw = f64::NEG_INFINITY;
                for i in 0..n {
                    if s0[i] <= 0.0 {
                        continue;
                    }
                    let inv = 1.0 / f64::from(s0[i]);
                    let mut var = 0.0f64;
                    for c in 0..channels {
                        let m = f64::from(s1[i][c]) * inv;
                        means[i][c] = m;
                        var += (f64::from(s2[i][c]) * inv - m * m).max(0.0);
                    }
                    let z = if q == 0.0 {
                        0.0
                    } else if var > 0.0 {
                        q * (DEVIATION_SCALE.ln() + 0.5 * var.ln())
                    } else {
                        f64::NEG_INFINITY
                    };
                    // −softplus(z) = −ln(1 + e^z)
                    let lw = if z > 40.0 { -z } else { -z.exp().ln_1p() };
                    logw[i] = lw;
                    max_logw = max_logw.max(lw);
                }
                let mut acc = [0.0f64; MAX_CHANNELS];
                let mut wsum = 0.0f64;
                for i in 0..n {
                    let w = (logw[i] - max_logw).exp();
                    if w.is_finite() && w > 0.0 {
                        wsum += w;
                        for c in 0..channels {
                            acc[c] += w * means[i][c];
                        }
                    }
                }
                if let Some(o) = out.get_mut(base - offset..base - offset + channels) {
                    for c in 0..channels {
                        let delta = if wsum > 0.0 { acc[c] / wsum } else { 0.0 };
                        o[c] = center[c] + delta as f32;
                    }
                }
            }
        }
        if let Some(Ok(mut slot)) = band_outputs.get(band).map(Mutex::lock) {
            *slot = out;
        }
    };
    parallel_for(bands, &filter_band);
    let mut out = Vec::with_capacity(len);
    for slot in band_outputs {
        out.extend(
            slot.into_inner()
                .map_err(|_| "a band of rows failed".to_string())?,
        );
    }
    if out.len() != len {
        return Err("a band of rows was not computed".to_string());
    }
    Ok(out)
}

/// Orientation and anisotropy of a structure tensor `(E, F, G)`.
///
/// Returns `(φ, A)`: `φ` is the angle (radians, `atan2` convention with `x`
/// to the right and `y` down) of the minor eigenvector, i.e. the local edge /
/// flow direction, defined modulo `π`; `A = (λ1 − λ2) / (λ1 + λ2)` is in
/// `[0, 1]` and 0 when `λ1 + λ2 == 0`.
pub fn tensor_orientation(t: [f32; 3]) -> (f32, f32) {
    let [e, f, g] = t;
    let tr = e + g;
    let disc = ((e - g) * (e - g) + 4.0 * f * f).sqrt();
    let l1 = 0.5 * (tr + disc);
    let l2 = 0.5 * (tr - disc);
    let aniso = if tr > 0.0 && tr.is_finite() {
        ((l1 - l2) / (l1 + l2)).clamp(0.0, 1.0)
    } else {
        0.0
    };
    // Major eigenvector, from the better conditioned row of (T − λ1 I) v = 0.
    let (mx, my) = if e >= g { (l1 - g, f) } else { (f, l1 - e) };
    let phi = if mx == 0.0 && my == 0.0 {
        0.0
    } else {
        // Minor eigenvector = major rotated by +90°.
        mx.atan2(-my)
    };
    let phi = if phi.is_finite() { phi } else { 0.0 };
    (phi, aniso)
}

/// Smoothed structure tensor `(E, F, G) = (gx², gx·gy, gy²)` per pixel.
///
/// Gradients are Sobel derivatives (normalised by 1/8, clamped border) of
/// `luma` (row-major, `width * height` values); the tensor components are
/// smoothed with a separable Gaussian of standard deviation `sigma` pixels
/// (no smoothing when `sigma` is not a positive finite number). Returns an
/// empty vector when `luma.len() != width * height`.
pub fn structure_tensor(luma: &[f32], width: usize, height: usize, sigma: f32) -> Vec<[f32; 3]> {
    let Some(n) = width.checked_mul(height) else {
        return Vec::new();
    };
    if n == 0 || luma.len() != n {
        return Vec::new();
    }
    let xmax = width - 1;
    let ymax = height - 1;
    let at = |x: usize, y: usize| luma.get(y * width + x).copied().unwrap_or(0.0);
    let mut t = vec![[0.0f32; 3]; n];
    for y in 0..height {
        let ym = y.saturating_sub(1);
        let yp = (y + 1).min(ymax);
        for x in 0..width {
            let xm = x.saturating_sub(1);
            let xp = (x + 1).min(xmax);
            let gx = (at(xp, ym) + 2.0 * at(xp, y) + at(xp, yp)
                - at(xm, ym)
                - 2.0 * at(xm, y)
                - at(xm, yp))
                / 8.0;
            let gy = (at(xm, yp) + 2.0 * at(x, yp) + at(xp, yp)
                - at(xm, ym)
                - 2.0 * at(x, ym)
                - at(xp, ym))
                / 8.0;
            if let Some(v) = t.get_mut(y * width + x) {
                *v = [gx * gx, gx * gy, gy * gy];
            }
        }
    }
    if sigma.is_finite() && sigma > 0.0 {
        let kernel = gaussian_kernel(sigma);
        t = convolve_separable(&t, width, height, &kernel);
    }
    t
}

/// Normalised 1-D Gaussian kernel of radius `ceil(3σ)` (capped).
fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    let r = ((3.0 * sigma).ceil() as usize).clamp(1, MAX_KERNEL_RADIUS);
    let mut k: Vec<f32> = (0..=2 * r)
        .map(|i| {
            let d = i as f32 - r as f32;
            (-d * d / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let s: f32 = k.iter().sum();
    if s > 0.0 {
        k.iter_mut().for_each(|v| *v /= s);
    }
    k
}

/// Separable convolution of a 3-component field with clamped borders.
fn convolve_separable(src: &[[f32; 3]], width: usize, height: usize, k: &[f32]) -> Vec<[f32; 3]> {
    let r = (k.len() / 2) as isize;
    let mut tmp = vec![[0.0f32; 3]; src.len()];
    for y in 0..height {
        for x in 0..width {
            let mut acc = [0.0f32; 3];
            for (j, w) in k.iter().enumerate() {
                let sx = (x as isize + j as isize - r).clamp(0, width as isize - 1) as usize;
                if let Some(v) = src.get(y * width + sx) {
                    for c in 0..3 {
                        acc[c] += w * v[c];
                    }
                }
            }
            if let Some(o) = tmp.get_mut(y * width + x) {
                *o = acc;
            }
        }
    }
    let mut out = vec![[0.0f32; 3]; src.len()];
    for y in 0..height {
        for x in 0..width {
            let mut acc = [0.0f32; 3];
            for (j, w) in k.iter().enumerate() {
                let sy = (y as isize + j as isize - r).clamp(0, height as isize - 1) as usize;
                if let Some(v) = tmp.get(sy * width + x) {
                    for c in 0..3 {
                        acc[c] += w * v[c];
                    }
                }
            }
            if let Some(o) = out.get_mut(y * width + x) {
                *o = acc;
            }
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Small deterministic xorshift generator returning values in [0, 1).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    fn std_dev(v: &[f32]) -> f32 {
        let m = v.iter().sum::<f32>() / v.len() as f32;
        (v.iter().map(|x| (x - m) * (x - m)).sum::<f32>() / v.len() as f32).sqrt()
    }

    #[test]
    fn constant_image_is_unchanged() {
        let (w, h, c) = (23, 17, 3);
        let src: Vec<f32> = (0..w * h * c).map(|i| [0.25, 0.5, 0.75][i % 3]).collect();
        let out = anisotropic_kuwahara(&src, w, h, c, &KuwaharaParams::default()).unwrap();
        for (a, b) in src.iter().zip(&out) {
            assert!((a - b).abs() <= 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn one_by_one_and_empty() {
        let p = KuwaharaParams::default();
        let out = anisotropic_kuwahara(&[0.1, 0.2, 0.3, 0.4], 1, 1, 4, &p).unwrap();
        for (a, b) in out.iter().zip([0.1, 0.2, 0.3, 0.4]) {
            assert!((a - b).abs() < 1e-6);
        }
        assert!(anisotropic_kuwahara(&[], 0, 5, 3, &p).unwrap().is_empty());
        assert!(anisotropic_kuwahara(&[], 0, 0, 1, &p).unwrap().is_empty());
    }

    #[test]
    fn invalid_params_are_rejected() {
        let src = vec![0.0f32; 12];
        let ok = KuwaharaParams::default();
        let bad = [
            KuwaharaParams { radius: 0.0, ..ok },
            KuwaharaParams { radius: -1.0, ..ok },
            KuwaharaParams {
                radius: f32::NAN,
                ..ok
            },
            KuwaharaParams {
                radius: 1000.0,
                ..ok
            },
            KuwaharaParams { sectors: 3, ..ok },
            KuwaharaParams { sectors: 17, ..ok },
            KuwaharaParams {
                sharpness: f32::INFINITY,
                ..ok
            },
            KuwaharaParams { alpha: 0.0, ..ok },
            KuwaharaParams {
                tensor_sigma: f32::NAN,
                ..ok
            },
        ];
        for p in bad {
            assert!(anisotropic_kuwahara(&src, 2, 2, 3, &p).is_err(), "{p:?}");
        }
        assert!(anisotropic_kuwahara(&src, 2, 2, 3, &ok).is_ok());
        // Size mismatch and bad channel counts.
        assert!(anisotropic_kuwahara(&src, 3, 2, 3, &ok).is_err());
        assert!(anisotropic_kuwahara(&src, 2, 2, 0, &ok).is_err());
        assert!(anisotropic_kuwahara(&src, 1, 2, 6, &ok).is_err());
        assert!(anisotropic_kuwahara(&src, usize::MAX, 2, 3, &ok).is_err());
    }

    #[test]
    fn step_edge_is_preserved_and_noise_reduced() {
        let (w, h) = (64, 48);
        let edge = 32; // columns < 32 dark, >= 32 bright; midpoint crossing at 31.5
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
        let src: Vec<f32> = (0..w * h)
            .map(|i| {
                let base = if i % w < edge { 0.2 } else { 0.8 };
                base + (rng.next() - 0.5) * 0.1
            })
            .collect();
        let p = KuwaharaParams {
            radius: 4.0,
            ..KuwaharaParams::default()
        };
        let out = anisotropic_kuwahara(&src, w, h, 1, &p).unwrap();
        for y in 4..h - 4 {
            let row = &out[y * w..(y + 1) * w];
            let cross = (1..w).find(|&x| row[x - 1] < 0.5 && row[x] >= 0.5).unwrap();
            // Crossing lies between cross-1 and cross, true edge at 31.5.
            let pos = cross as f32 - 0.5;
            assert!((pos - 31.5).abs() <= 1.0, "row {y}: crossing at {pos}");
            // The edge stays sharp: the 0.3..0.7 transition spans at most 3 px.
            let lo = (0..w).rev().find(|&x| row[x] <= 0.3).unwrap();
            let hi = (0..w).find(|&x| row[x] >= 0.7).unwrap();
            assert!(hi.saturating_sub(lo) <= 3, "row {y}: transition {lo}..{hi}");
        }
        let flat = |img: &[f32], x0: usize, x1: usize| -> Vec<f32> {
            (10..h - 10)
                .flat_map(|y| (x0..x1).map(move |x| (y, x)))
                .map(|(y, x)| img[y * w + x])
                .collect()
        };
        for (x0, x1) in [(4, 22), (42, 60)] {
            let before = std_dev(&flat(&src, x0, x1));
            let after = std_dev(&flat(&out, x0, x1));
            assert!(after * 2.0 <= before, "std {before} -> {after}");
        }
    }

    #[test]
    fn rotation_equivariance() {
        let (w, h) = (31, 22);
        let mut rng = Rng(12345);
        let src: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                let v = if x + 0.5 * y > 20.0 { 0.7 } else { 0.3 };
                v + 0.05 * rng.next()
            })
            .collect();
        // Rotate 90° clockwise: (x, y) -> (h - 1 - y, x); new size h x w.
        let rot = |img: &[f32], w: usize, h: usize| -> Vec<f32> {
            let mut r = vec![0.0; w * h];
            for y in 0..h {
                for x in 0..w {
                    r[x * h + (h - 1 - y)] = img[y * w + x];
                }
            }
            r
        };
        let p = KuwaharaParams {
            radius: 4.0,
            ..KuwaharaParams::default()
        };
        let a = rot(&anisotropic_kuwahara(&src, w, h, 1, &p).unwrap(), w, h);
        let b = anisotropic_kuwahara(&rot(&src, w, h), h, w, 1, &p).unwrap();
        let max_diff = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(max_diff < 1e-3, "max diff {max_diff}");
    }

    #[test]
    fn structure_tensor_of_vertical_stripes() {
        let (w, h) = (40, 30);
        let luma: Vec<f32> = (0..w * h).map(|i| ((i % w) as f32 * 0.7).sin()).collect();
        let t = structure_tensor(&luma, w, h, 2.0);
        assert_eq!(t.len(), w * h);
        for y in 5..h - 5 {
            for x in 5..w - 5 {
                let [e, f, g] = t[y * w + x];
                assert!(e > 0.01, "E = {e}");
                assert!(f.abs() < 1e-5 && g.abs() < 1e-5, "F = {f}, G = {g}");
                let (phi, a) = tensor_orientation(t[y * w + x]);
                // Gradient horizontal => edge (minor eigenvector) vertical.
                assert!((phi.abs() - PI / 2.0).abs() < 1e-3, "phi = {phi}");
                assert!((a - 1.0).abs() < 1e-3, "A = {a}");
            }
        }
        assert!(structure_tensor(&luma, w, h + 1, 2.0).is_empty());
        assert_eq!(tensor_orientation([0.0; 3]), (0.0, 0.0));
    }

    #[test]
    #[ignore = "timing, run with --release -- --ignored"]
    fn timing_640x480() {
        let (w, h) = (640, 480);
        let mut rng = Rng(7);
        let src: Vec<f32> = (0..w * h * 3).map(|_| rng.next()).collect();
        let t0 = std::time::Instant::now();
        let out = anisotropic_kuwahara(&src, w, h, 3, &KuwaharaParams::default()).unwrap();
        println!(
            "anisotropic_kuwahara 640x480x3 (defaults): {:?}",
            t0.elapsed()
        );
        assert_eq!(out.len(), src.len());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn output_within_input_range(
            w in 1usize..9,
            h in 1usize..9,
            c in 1usize..=4,
            seed in any::<u64>(),
            radius in 0.5f32..6.0,
            sectors in 4usize..=16,
        ) {
            let mut rng = Rng(seed | 1);
            let src: Vec<f32> = (0..w * h * c).map(|_| rng.next() * 4.0 - 2.0).collect();
            let p = KuwaharaParams { radius, sectors, ..KuwaharaParams::default() };
            let out = anisotropic_kuwahara(&src, w, h, c, &p).unwrap();
            prop_assert_eq!(out.len(), src.len());
            for ch in 0..c {
                let vals = src.iter().skip(ch).step_by(c);
                let lo = vals.clone().fold(f32::INFINITY, |a, &b| a.min(b));
                let hi = vals.fold(f32::NEG_INFINITY, |a, &b| a.max(b));
                for v in out.iter().skip(ch).step_by(c) {
                    prop_assert!(v.is_finite());
                    prop_assert!(*v >= lo - 1e-4 && *v <= hi + 1e-4, "{} not in [{}, {}]", v, lo, hi);
                }
            }
        }
    }

    #[test]
    fn banded_runs_do_not_depend_on_the_schedule() {
        let (w, h, c) = (23, 41, 3); // bands of unequal size: 41 = 2·16 + 9
        let mut seed = 0x9e37_79b9_u32;
        let src: Vec<f32> = (0..w * h * c)
            .map(|_| {
                seed ^= seed << 13;
                seed ^= seed >> 17;
                seed ^= seed << 5;
                (seed % 1000) as f32 / 999.0
            })
            .collect();
        let p = KuwaharaParams {
            radius: 3.0,
            ..KuwaharaParams::default()
        };
        let sequential = anisotropic_kuwahara(&src, w, h, c, &p).unwrap();
        let reversed = anisotropic_kuwahara_with(&src, w, h, c, &p, &|n, body| {
            (0..n).rev().for_each(body);
        })
        .unwrap();
        let threaded = anisotropic_kuwahara_with(&src, w, h, c, &p, &|n, body| {
            std::thread::scope(|scope| {
                for i in 0..n {
                    scope.spawn(move || body(i));
                }
            });
        })
        .unwrap();
        assert_eq!(sequential, reversed);
        assert_eq!(sequential, threaded);
        // A scheduler that skips a band is an error, not a partial image.
        let skipping = anisotropic_kuwahara_with(&src, w, h, c, &p, &|n, body| {
            (1..n).for_each(body);
        });
        assert!(skipping.is_err());
    }
}
