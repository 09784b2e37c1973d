//! `detect.corners`: Harris and Shi–Tomasi corner responses, `goodFeaturesToTrack`-style
//! selection and optional `cornerSubPix`-style refinement.
//!
//! - [`corner_response`] computes the response image with OpenCV's `cornerHarris` /
//!   `cornerMinEigenVal` conventions: Sobel derivatives scaled by
//!   `1 / (2^(ksize−1) · block_size · 255)` (255 for u8 input, 65535 for u16, 1 for f32),
//!   products summed (unnormalized) over a `block_size` window anchored at `block_size/2`, border
//!   reflect101 on the image and on the products.
//! - [`select_corners`] keeps local maxima (3×3) above `quality_level · max`, strongest first,
//!   spaced at least `min_distance` apart, at most `max_corners`.
//! - [`refine_corners`] moves each corner to where the image gradients in a window are
//!   orthogonal to the vectors from the corner (Förstner's criterion, OpenCV `cornerSubPix`).
//!
//! Rows are processed in fixed bands of [`BAND_ROWS`] (each band recomputes the few rows of
//! derivatives it needs above and below), so the response is bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Keypoint, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use crate::filter::border::{BorderMode, BorderTable, map_index};
use crate::filter::sobel::deriv_kernel;

/// Output rows per parallel band.
const BAND_ROWS: usize = 32;

/// Largest Sobel aperture.
const MAX_KSIZE: u32 = 7;

/// Largest averaging block side.
const MAX_BLOCK: u32 = 31;

param_enum! {
    /// Which corner response to compute.
    pub enum CornerMethod {
        /// Harris–Stephens: `det(M) − k · trace(M)²` (OpenCV `cornerHarris`).
        Harris = "harris",
        /// Shi–Tomasi: the smaller eigenvalue of `M` (OpenCV `cornerMinEigenVal`).
        ShiTomasi = "shi_tomasi",
    }
}

#[allow(clippy::derivable_impls)]
impl Default for CornerMethod {
    fn default() -> Self {
        CornerMethod::Harris
    }
}

/// A gray image as an f32 plane plus the sample range (255, 65535 or 1) OpenCV's corner
/// functions divide by. Errors for colour images.
pub(crate) fn gray_plane(image: &Image, op: &str) -> Result<(Vec<f32>, f32), OpError> {
    if image.channels() != Channels::Gray {
        return Err(OpError::input(
            "image",
            format!(
                "{op} needs a gray image, got {}; convert it with filter.grayscale first",
                image.format()
            ),
        ));
    }
    Ok(match image.data() {
        PixelData::U8(v) => (v.iter().map(|&s| f32::from(s)).collect(), 255.0),
        PixelData::U16(v) => (v.iter().map(|&s| f32::from(s)).collect(), 65535.0),
        PixelData::F32(v) => (v.clone(), 1.0),
    })
}

/// Separable Sobel derivatives of one row `y` of `src` (`width` wide), border reflect101:
/// `dx` and `dy` (unscaled), using the scratch `vs` / `vd` (padded vertical sums).
struct DerivRows {
    smooth: Vec<f32>,
    deriv: Vec<f32>,
    /// Vertical smoothing sums, padded.
    vs: Vec<f32>,
    /// Vertical derivative sums, padded.
    vd: Vec<f32>,
    columns: BorderTable,
}

impl DerivRows {
    fn new(width: usize, ksize: usize) -> DerivRows {
        let deriv: Vec<f32> = deriv_kernel(ksize, 1).iter().map(|&v| v as f32).collect();
        // The smoothing kernel, centred in a kernel as long as `deriv` (ksize 1: [0, 1, 0]).
        let raw = deriv_kernel(ksize, 0);
        let offset = (deriv.len() - raw.len().min(deriv.len())) / 2;
        let mut smooth = vec![0.0f32; deriv.len()];
        for (s, &v) in smooth[offset..].iter_mut().zip(&raw) {
            *s = v as f32;
        }
        let r = deriv.len() / 2;
        let columns = BorderTable::symmetric(width, r, BorderMode::Reflect101);
        let padded = columns.padded_len();
        DerivRows {
            smooth,
            deriv,
            vs: vec![0.0; padded],
            vd: vec![0.0; padded],
            columns,
        }
    }

    fn row(&mut self, src: &[f32], width: usize, height: usize, y: usize, dx: &mut [f32]) {
        let (dx, dy) = dx.split_at_mut(width);
        let r = self.deriv.len() / 2;
        let pad = self.columns.before();
        // Vertical pass into the interior of vs (smooth, for dx) and vd (deriv, for dy).
        let vs_in = &mut self.vs[pad..pad + width];
        let vd_in = &mut self.vd[pad..pad + width];
        for (i, &kd) in self.deriv.iter().enumerate() {
            let sy = map_index(
                y as isize + i as isize - r as isize,
                height,
                BorderMode::Reflect101,
            )
            .unwrap_or(0);
            let row = &src[sy * width..(sy + 1) * width];
            taps_pair(vs_in, vd_in, row, row, self.smooth[i], kd, i == 0);
        }
        // Borders of the padded rows.
        for k in (0..pad).chain(pad + width..pad + width + self.columns.after()) {
            let s = self.columns.source(k).unwrap_or(0) + pad;
            self.vs[k] = self.vs[s];
            self.vd[k] = self.vd[s];
        }
        // Horizontal pass.
        for i in 0..self.deriv.len() {
            taps_pair(
                dx,
                dy,
                &self.vs[i..i + width],
                &self.vd[i..i + width],
                self.deriv[i],
                self.smooth[i],
                i == 0,
            );
        }
    }
}

/// One tap of two filters: `a[i] (+)= ka · pa[i]`, `b[i] (+)= kb · pb[i]` (assignment for the
/// first tap: the sums start at the first product, as `0 + p` is `p`).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn taps_pair(a: &mut [f32], b: &mut [f32], pa: &[f32], pb: &[f32], ka: f32, kb: f32, first: bool) {
    let n = a.len().min(b.len()).min(pa.len()).min(pb.len());
    let (a, b, pa, pb) = (&mut a[..n], &mut b[..n], &pa[..n], &pb[..n]);
    if first {
        for (((x, y), &p), &q) in a.iter_mut().zip(b.iter_mut()).zip(pa).zip(pb) {
            *x = ka * p;
            *y = kb * q;
        }
    } else {
        for (((x, y), &p), &q) in a.iter_mut().zip(b.iter_mut()).zip(pa).zip(pb) {
            *x += ka * p;
            *y += kb * q;
        }
    }
}

/// Scaled gradient products of one row into the interiors of three padded f64 rows
/// (`xx`, `xy`, `yy` from index `pad`): `(gx·s)²`, `(gx·s)(gy·s)`, `(gy·s)²` in f32.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn products(dx: &[f32], dy: &[f32], scale: f32, xx: &mut [f64], xy: &mut [f64], yy: &mut [f64]) {
    let n = dx
        .len()
        .min(dy.len())
        .min(xx.len())
        .min(xy.len())
        .min(yy.len());
    for i in 0..n {
        let gx = dx[i] * scale;
        let gy = dy[i] * scale;
        xx[i] = f64::from(gx * gx);
        xy[i] = f64::from(gx * gy);
        yy[i] = f64::from(gy * gy);
    }
}

/// Horizontal window sums: `out[x] = p[x] + p[x+1] + … + p[x+block−1]`, left to right.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn window_sums(p: &[f64], block: usize, out: &mut [f64]) {
    let n = out.len();
    out.copy_from_slice(&p[..n]);
    for i in 1..block {
        for (o, &v) in out.iter_mut().zip(&p[i..i + n]) {
            *o += v;
        }
    }
}

/// `acc[i] += v[i]`.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn add_to(acc: &mut [f64], v: &[f64]) {
    for (a, &b) in acc.iter_mut().zip(v) {
        *a += b;
    }
}

/// The corner response of a gray f32 plane (`width × height`, row-major), OpenCV's
/// `cornerHarris(src, block_size, ksize, k)` or `cornerMinEigenVal(src, block_size, ksize)`.
///
/// `range` is the sample range the derivatives are divided by (255 for 8-bit data). `ksize` is
/// 1, 3, 5 or 7, `block_size` ≥ 1. Bit-identical for any thread count.
#[allow(clippy::too_many_arguments)]
pub fn corner_response(
    src: &[f32],
    width: usize,
    height: usize,
    block_size: usize,
    ksize: usize,
    method: CornerMethod,
    k: f64,
    range: f32,
) -> Vec<f32> {
    let mut out = ocellus_engine::buffer::zeroed::<f32>(width * height);
    if width == 0 || height == 0 || src.len() != width * height {
        return out;
    }
    let block = block_size.max(1);
    let aperture = if ksize <= 1 { 3 } else { ksize };
    let scale = 1.0 / ((1u64 << (aperture.max(2) - 1).min(62)) as f64 * block as f64);
    let scale = if ksize <= 1 {
        1.0 / block as f64
    } else {
        scale
    };
    let scale = (scale / f64::from(range)) as f32;
    let before = block / 2;
    let after = block - 1 - before;
    let columns = BorderTable::new(width, before, after, BorderMode::Reflect101);
    let padded = columns.padded_len();
    out.par_chunks_mut(width * BAND_ROWS)
        .enumerate()
        .for_each(|(b, band)| {
            let y0 = b * BAND_ROWS;
            let rows = band.len() / width;
            let mut deriv = DerivRows::new(width, ksize);
            let mut d = vec![0.0f32; 2 * width];
            // Products, padded: xx, xy, yy planes.
            let mut prod = vec![0.0f64; 3 * padded];
            // Ring of horizontal sums, `block` rows of the xx, xy, yy planes (`width` each).
            let mut ring = vec![0.0f64; block * 3 * width];
            let mut sums = vec![0.0f64; 3 * width];
            let first = y0 as isize - before as isize;
            let last = (y0 + rows + after) as isize;
            for j in first..last {
                let sy = map_index(j, height, BorderMode::Reflect101).unwrap_or(0);
                deriv.row(src, width, height, sy, &mut d);
                let (dx, dy) = d.split_at(width);
                {
                    let (xx, rest) = prod.split_at_mut(padded);
                    let (xy, yy) = rest.split_at_mut(padded);
                    let inner = before..before + width;
                    products(
                        dx,
                        dy,
                        scale,
                        &mut xx[inner.clone()],
                        &mut xy[inner.clone()],
                        &mut yy[inner],
                    );
                }
                for kpos in (0..before).chain(before + width..padded) {
                    let s = columns.source(kpos).unwrap_or(0) + before;
                    for c in 0..3 {
                        prod[c * padded + kpos] = prod[c * padded + s];
                    }
                }
                let slot = (j - first) as usize % block;
                let hs = &mut ring[slot * 3 * width..(slot + 1) * 3 * width];
                for (c, h) in hs.chunks_exact_mut(width).enumerate() {
                    window_sums(&prod[c * padded..(c + 1) * padded], block, h);
                }
                let done = (j - first) as usize + 1;
                if done >= block {
                    let y = done - block; // output row within the band
                    let out_row = &mut band[y * width..(y + 1) * width];
                    // Column sums over the ring in slot order.
                    let n = 3 * width;
                    sums.copy_from_slice(&ring[..n]);
                    for r in 1..block {
                        add_to(&mut sums, &ring[r * n..(r + 1) * n]);
                    }
                    let (sxx, rest) = sums.split_at(width);
                    let (sxy, syy) = rest.split_at(width);
                    match method {
                        CornerMethod::Harris => harris_row(sxx, sxy, syy, k, out_row),
                        CornerMethod::ShiTomasi => min_eigen_row(sxx, sxy, syy, out_row),
                    }
                }
            }
        });
    out
}

/// Harris response of one row from the f64 window sums (rounded to f32 first, as OpenCV's
/// f32 covariance image): `a·c − b² − k·(a + c)²` in f64.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn harris_row(sxx: &[f64], sxy: &[f64], syy: &[f64], k: f64, out: &mut [f32]) {
    let n = out.len().min(sxx.len()).min(sxy.len()).min(syy.len());
    for i in 0..n {
        let a = f64::from(sxx[i] as f32);
        let b = f64::from(sxy[i] as f32);
        let c = f64::from(syy[i] as f32);
        out[i] = (a * c - b * b - k * (a + c) * (a + c)) as f32;
    }
}

/// Smaller eigenvalue of one row from the f64 window sums (rounded to f32), in f32.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn min_eigen_row(sxx: &[f64], sxy: &[f64], syy: &[f64], out: &mut [f32]) {
    let n = out.len().min(sxx.len()).min(sxy.len()).min(syy.len());
    for i in 0..n {
        let a = (sxx[i] as f32) * 0.5;
        let b = sxy[i] as f32;
        let c = (syy[i] as f32) * 0.5;
        out[i] = (a + c) - ((a - c) * (a - c) + b * b).sqrt();
    }
}

/// `goodFeaturesToTrack`-style selection on a response image: pixels (not on the image's outer
/// frame) that are 3×3 maxima and strictly above `quality_level · max`, in order of decreasing
/// response (equal responses: later in raster order first, as OpenCV), each kept only if no
/// kept corner lies closer than `min_distance` px; at most `max_corners` (0: no limit).
/// Returns `(x, y, response)` with integer pixel coordinates.
pub fn select_corners(
    response: &[f32],
    width: usize,
    height: usize,
    quality_level: f64,
    min_distance: f64,
    max_corners: usize,
) -> Vec<(usize, usize, f32)> {
    if width < 3 || height < 3 || response.len() != width * height {
        return Vec::new();
    }
    let max = max_ordered(response);
    let threshold = (f64::from(max) * quality_level) as f32;
    let keep = |v: f32| if v > threshold { v } else { 0.0 };
    // Rows in fixed bands; pixels above the threshold are rare, so a vector scan finds them
    // and the 3×3 test runs only there.
    let inner_rows = height - 2;
    let bands = inner_rows.div_ceil(SELECT_BAND_ROWS);
    let mut candidates: Vec<(f32, usize)> = (0..bands)
        .into_par_iter()
        .map(|b| {
            let y0 = 1 + b * SELECT_BAND_ROWS;
            let y1 = (y0 + SELECT_BAND_ROWS).min(height - 1);
            let mut found = Vec::new();
            let mut above = Vec::new();
            for y in y0..y1 {
                above.clear();
                above_threshold(
                    &response[y * width + 1..(y + 1) * width - 1],
                    threshold,
                    &mut above,
                );
                for &i in &above {
                    let x = i + 1;
                    let v = keep(response[y * width + x]);
                    if v == 0.0 || v.is_nan() {
                        continue;
                    }
                    let mut is_max = true;
                    // Dilation of the thresholded image (outside the image does not count).
                    'n: for yy in y - 1..=y + 1 {
                        let row = &response[yy * width..(yy + 1) * width];
                        for &r in &row[x - 1..=x + 1] {
                            if keep(r) > v {
                                is_max = false;
                                break 'n;
                            }
                        }
                    }
                    if is_max {
                        found.push((v, y * width + x));
                    }
                }
            }
            found
        })
        .flatten()
        .collect();
    candidates.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(b.1.cmp(&a.1)));
    let limit = if max_corners == 0 {
        usize::MAX
    } else {
        max_corners
    };
    let mut kept: Vec<(usize, usize, f32)> = Vec::new();
    if min_distance >= 1.0 {
        let cell = min_distance.round().max(1.0) as usize;
        let gw = width.div_ceil(cell);
        let gh = height.div_ceil(cell);
        let mut grid: Vec<Vec<(usize, usize)>> = vec![Vec::new(); gw * gh];
        let d2 = (min_distance * min_distance) as f32;
        for &(v, i) in &candidates {
            if kept.len() >= limit {
                break;
            }
            let (x, y) = (i % width, i / width);
            let (cx, cy) = (x / cell, y / cell);
            let mut good = true;
            'cells: for gy in cy.saturating_sub(1)..=(cy + 1).min(gh - 1) {
                for gx in cx.saturating_sub(1)..=(cx + 1).min(gw - 1) {
                    for &(px, py) in &grid[gy * gw + gx] {
                        let dx = px as f32 - x as f32;
                        let dy = py as f32 - y as f32;
                        if dx * dx + dy * dy < d2 {
                            good = false;
                            break 'cells;
                        }
                    }
                }
            }
            if good {
                grid[cy * gw + cx].push((x, y));
                kept.push((x, y, v));
            }
        }
    } else {
        kept.extend(
            candidates
                .iter()
                .take(limit)
                .map(|&(v, i)| (i % width, i / width, v)),
        );
    }
    kept
}

/// Rows per parallel band of the candidate search.
const SELECT_BAND_ROWS: usize = 64;

/// The largest non-NaN value (−∞ when there is none), in lanes.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn max_ordered(v: &[f32]) -> f32 {
    const L: usize = 16;
    let mut m = [f32::NEG_INFINITY; L];
    let chunks = v.chunks_exact(L);
    let rest = chunks.remainder();
    for c in chunks {
        for i in 0..L {
            // NaN compares false and is skipped.
            if c[i] > m[i] {
                m[i] = c[i];
            }
        }
    }
    let mut best = f32::NEG_INFINITY;
    for &x in m.iter().chain(rest) {
        if x > best {
            best = x;
        }
    }
    best
}

/// Pushes the indices `i` with `row[i] > threshold`, ascending.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn above_threshold(row: &[f32], threshold: f32, out: &mut Vec<usize>) {
    const L: usize = 16;
    let chunks = row.chunks_exact(L);
    let tail = chunks.remainder();
    for (ci, c) in chunks.enumerate() {
        let mut any = false;
        for &v in c {
            any |= v > threshold;
        }
        if any {
            for (j, &v) in c.iter().enumerate() {
                if v > threshold {
                    out.push(ci * L + j);
                }
            }
        }
    }
    let base = row.len() - tail.len();
    for (j, &v) in tail.iter().enumerate() {
        if v > threshold {
            out.push(base + j);
        }
    }
}

/// Bilinear sample of `src` at (x, y), coordinates clamped to the image (border replicate).
fn bilinear(src: &[f32], width: usize, height: usize, x: f64, y: f64) -> f64 {
    let x = x.clamp(0.0, (width - 1) as f64);
    let y = y.clamp(0.0, (height - 1) as f64);
    let x0 = x.floor() as usize;
    let y0 = y.floor() as usize;
    let x1 = (x0 + 1).min(width - 1);
    let y1 = (y0 + 1).min(height - 1);
    let fx = x - x0 as f64;
    let fy = y - y0 as f64;
    let p = |xx: usize, yy: usize| f64::from(src[yy * width + xx]);
    (p(x0, y0) * (1.0 - fx) + p(x1, y0) * fx) * (1.0 - fy)
        + (p(x0, y1) * (1.0 - fx) + p(x1, y1) * fx) * fy
}

/// Subpixel refinement of corner positions, OpenCV's `cornerSubPix` with `zeroZone = (−1, −1)`:
/// in a `(2·half_window + 1)²` window (Gaussian weights `exp(−(i² + j²)/half_window²)`), solve
/// `Σ w g gᵀ (q − p) = 0` for the point `q` where the gradients `g` at points `p` are orthogonal to
/// `q − p`, and iterate from the new point until it moves less than `epsilon` px or after
/// `iterations`. A point that would leave the window keeps its start position.
pub fn refine_corners(
    src: &[f32],
    width: usize,
    height: usize,
    points: &mut [(f64, f64)],
    half_window: usize,
    iterations: usize,
    epsilon: f64,
) {
    if width == 0 || height == 0 || half_window == 0 {
        return;
    }
    let win = half_window as isize;
    let side = 2 * half_window + 1;
    let coeff = 1.0 / (half_window * half_window) as f64;
    let mask_1d: Vec<f64> = (-win..=win)
        .map(|i| (-((i * i) as f64) * coeff).exp())
        .collect();
    let eps2 = epsilon * epsilon;
    points.par_iter_mut().for_each(|pt| {
        let start = *pt;
        let mut c = start;
        let mut patch = vec![0.0f64; (side + 2) * (side + 2)];
        for _ in 0..iterations.max(1) {
            // Bilinear window of (side + 2)² samples centred on c.
            for (j, row) in patch.chunks_exact_mut(side + 2).enumerate() {
                let yy = c.1 + j as f64 - (half_window + 1) as f64;
                for (i, v) in row.iter_mut().enumerate() {
                    let xx = c.0 + i as f64 - (half_window + 1) as f64;
                    *v = bilinear(src, width, height, xx, yy);
                }
            }
            let (mut a, mut b, mut cc, mut bb1, mut bb2) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for j in 0..side {
                let py = j as f64 - half_window as f64;
                for i in 0..side {
                    let px = i as f64 - half_window as f64;
                    let m = mask_1d[i] * mask_1d[j];
                    let at = |dx: usize, dy: usize| patch[(j + dy) * (side + 2) + i + dx];
                    let gx = at(2, 1) - at(0, 1);
                    let gy = at(1, 2) - at(1, 0);
                    let gxx = gx * gx * m;
                    let gxy = gx * gy * m;
                    let gyy = gy * gy * m;
                    a += gxx;
                    b += gxy;
                    cc += gyy;
                    bb1 += gxx * px + gxy * py;
                    bb2 += gxy * px + gyy * py;
                }
            }
            let det = a * cc - b * b;
            if det.abs() <= f64::EPSILON * f64::EPSILON {
                break;
            }
            let s = 1.0 / det;
            let nx = c.0 + cc * s * bb1 - b * s * bb2;
            let ny = c.1 - b * s * bb1 + a * s * bb2;
            let err = (nx - c.0).powi(2) + (ny - c.1).powi(2);
            c = (nx, ny);
            if c.0 < 0.0 || c.0 >= width as f64 || c.1 < 0.0 || c.1 >= height as f64 {
                break;
            }
            if err <= eps2 {
                break;
            }
        }
        if (c.0 - start.0).abs() > half_window as f64
            || (c.1 - start.1).abs() > half_window as f64
            || !c.0.is_finite()
            || !c.1.is_finite()
        {
            c = start;
        }
        *pt = c;
    });
}

params! {
    /// Parameters of `detect.corners`.
    pub struct CornersParams {
        /// Corner response: "harris" (det − k·trace²) or "shi_tomasi" (smaller eigenvalue).
        method: CornerMethod = CornerMethod::Harris,
        /// Side of the window (px) over which gradient products are summed, 1..=31. Default 3.
        block_size: u32 = 3,
        /// Sobel aperture for the derivatives: 1, 3, 5 or 7. Default 3.
        ksize: u32 = 3,
        /// Harris free parameter k (dimensionless, default 0.04); unused by shi_tomasi.
        k: f64 = 0.04,
        /// Minimal accepted response as a fraction of the image's largest response, 0..1
        /// (default 0.01).
        quality_level: f64 = 0.01,
        /// Minimal distance between kept corners, px (default 10; below 1 no spacing test).
        min_distance: f64 = 10.0,
        /// Largest number of corners returned, strongest first (0 = no limit). Default 1000.
        max_corners: u32 = 1000,
        /// Refine corner positions to subpixel accuracy (cornerSubPix). Default false.
        subpixel: bool = false,
        /// Half side of the refinement window, px (window is 2·n+1 square). Default 5.
        subpixel_window: u32 = 5,
        /// Largest number of refinement iterations. Default 40.
        subpixel_iterations: u32 = 40,
        /// Refinement stops when a step moves the corner less than this, px. Default 0.001.
        subpixel_epsilon: f64 = 0.001,
    }
}

/// Corner detector (`detect.corners`). See [`corner_response`], [`select_corners`],
/// [`refine_corners`].
#[derive(Debug, Clone)]
pub struct Corners {
    params: CornersParams,
}

impl Op for Corners {
    type Params = CornersParams;
    const ID: &'static str = "detect.corners";
    const SUMMARY: &'static str =
        "Harris or Shi–Tomasi corners with goodFeaturesToTrack selection and subpixel refinement.";
    const DOC: &'static str = r#"
Computes a corner response image and picks the strongest, well-separated corners.

Response (OpenCV `cornerHarris` / `cornerMinEigenVal` conventions): Sobel derivatives Ix, Iy of
aperture `ksize` (border reflect101) are scaled by 1/(2^(ksize−1) · block_size · R), R = 255 for
u8, 65535 for u16, 1 for f32 images; M = Σ [Ix², IxIy; IxIy, Iy²] over a block_size × block_size
window anchored at block_size/2 (unnormalized sums in f64, border reflect101). Harris:
det M − k (trace M)²; Shi–Tomasi: λ_min = (a+c) − √((a−c)² + b²) with a = M₀₀/2, b = M₀₁,
c = M₁₁/2. The `response` output is this f32 image.

Selection (OpenCV `goodFeaturesToTrack`): responses ≤ quality_level · max are dropped; a pixel
not on the outer 1-px frame is a candidate if it equals the 3×3 maximum; candidates sorted by
decreasing response (ties: later raster position first, as OpenCV), each kept only if no kept
corner is closer than min_distance (px), until max_corners.

Refinement (`subpixel`, OpenCV `cornerSubPix` with zeroZone (−1,−1)): iterates
q ← (Σ w g gᵀ)⁻¹ Σ w g gᵀ p over a (2·subpixel_window+1)² bilinearly resampled window with
Gaussian weights; a corner moving out of the window keeps its integer position.

Keypoints: x, y (px), size = block_size, angle −1, response, octave 0. Gray u8/u16/f32 only.
Differences from OpenCV: u16 is accepted (R = 65535); Harris is evaluated in f64 from the f32
sums (OpenCV uses f32 SIMD), so responses agree to ~1e-6 relative.

References: C. Harris, M. Stephens, "A combined corner and edge detector", 1988; J. Shi,
C. Tomasi, "Good features to track", CVPR 1994; W. Förstner, E. Gülch, 1987 (refinement);
OpenCV cornerHarris, cornerMinEigenVal, goodFeaturesToTrack, cornerSubPix.

Example:
    "corners": (op: "detect.corners", inputs: { "image": "gray.image" },
                params: (method: "harris", max_corners: 2000, min_distance: 10)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Gray image (u8, u16 or f32).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "Selected corners, strongest first.",
            ),
            PortSpec::new(
                "response",
                PortType::Image,
                "Corner response, gray f32, same size as the input.",
            ),
        ]
    }

    fn new(params: CornersParams) -> Result<Self, String> {
        if !matches!(params.ksize, 1 | 3 | 5 | 7) || params.ksize > MAX_KSIZE {
            return Err(format!(
                "`ksize` must be 1, 3, 5 or 7, got {}",
                params.ksize
            ));
        }
        if !(1..=MAX_BLOCK).contains(&params.block_size) {
            return Err(format!(
                "`block_size` must be between 1 and {MAX_BLOCK}, got {}",
                params.block_size
            ));
        }
        for (name, v) in [
            ("k", params.k),
            ("quality_level", params.quality_level),
            ("min_distance", params.min_distance),
            ("subpixel_epsilon", params.subpixel_epsilon),
        ] {
            if !v.is_finite() {
                return Err(format!("`{name}` must be finite, got {v}"));
            }
        }
        if !(params.quality_level > 0.0 && params.quality_level < 1.0) {
            return Err(format!(
                "`quality_level` must be in (0, 1), got {}",
                params.quality_level
            ));
        }
        if params.min_distance < 0.0 || params.subpixel_epsilon < 0.0 {
            return Err("`min_distance` and `subpixel_epsilon` must be ≥ 0".into());
        }
        if params.subpixel && params.subpixel_window == 0 {
            return Err("`subpixel_window` must be ≥ 1".into());
        }
        Ok(Corners { params })
    }
}

impl Operator for Corners {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (plane, range) = gray_plane(image, Self::ID)?;
        let (w, h) = (image.width(), image.height());
        let p = &self.params;
        let response = corner_response(
            &plane,
            w,
            h,
            p.block_size as usize,
            p.ksize as usize,
            p.method,
            p.k,
            range,
        );
        let selected = select_corners(
            &response,
            w,
            h,
            p.quality_level,
            p.min_distance,
            p.max_corners as usize,
        );
        let mut points: Vec<(f64, f64)> = selected
            .iter()
            .map(|&(x, y, _)| (x as f64, y as f64))
            .collect();
        if p.subpixel {
            refine_corners(
                &plane,
                w,
                h,
                &mut points,
                p.subpixel_window as usize,
                p.subpixel_iterations as usize,
                p.subpixel_epsilon,
            );
        }
        let keypoints: Vec<Keypoint> = points
            .iter()
            .zip(&selected)
            .map(|(&(x, y), &(_, _, r))| Keypoint {
                x: x as f32,
                y: y as f32,
                size: p.block_size as f32,
                angle: -1.0,
                response: r,
                octave: 0,
            })
            .collect();
        let response = Image::from_f32(w, h, Channels::Gray, response)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("keypoints", Value::Keypoints(keypoints.into()))
            .with("response", Value::image(response)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> Vec<f32> {
        (0..64).map(|i| ((i * 37) % 251) as f32).collect()
    }

    fn assert_rel(ours: &[f32], expected: &[f32]) {
        for (o, e) in ours.iter().zip(expected) {
            assert!(
                (o - e).abs() <= 1e-5 * e.abs().max(1e-3),
                "{ours:?} vs {expected:?}"
            );
        }
    }

    #[test]
    #[allow(clippy::excessive_precision)]
    fn harris_matches_opencv_small() {
        // cv2.cornerHarris(a, 2, 3, 0.04)[3, :] with a[i] = (37 i) mod 251, 8×8 u8.
        let r = corner_response(&small(), 8, 8, 2, 3, CornerMethod::Harris, 0.04, 255.0);
        let expected = [
            0.000801226532,
            0.000801226532,
            0.00124267885,
            0.000893793185,
            0.00206517195,
            -0.00263517397,
            -0.000571596785,
            0.000801226415,
        ];
        assert_rel(&r[24..32], &expected);
    }

    #[test]
    #[allow(clippy::excessive_precision)]
    fn min_eigen_matches_opencv_small() {
        // cv2.cornerMinEigenVal(a, 3, 3)[4, :].
        let r = corner_response(&small(), 8, 8, 3, 3, CornerMethod::ShiTomasi, 0.0, 255.0);
        let expected = [
            0.0290295929,
            0.0288723707,
            0.0249948055,
            0.0201478302,
            0.0144739822,
            0.00134204328,
            0.00997309759,
            0.00997310132,
        ];
        assert_rel(&r[32..40], &expected);
    }

    #[test]
    fn constant_image_has_zero_response_and_no_corners() {
        let img = vec![77.0f32; 20 * 15];
        for method in [CornerMethod::Harris, CornerMethod::ShiTomasi] {
            let r = corner_response(&img, 20, 15, 3, 3, method, 0.04, 255.0);
            assert!(r.iter().all(|&v| v == 0.0));
            assert!(select_corners(&r, 20, 15, 0.01, 1.0, 0).is_empty());
        }
    }

    #[test]
    fn tiny_images() {
        for (w, h) in [(0, 0), (1, 1), (2, 1), (1, 5)] {
            let img = vec![5.0f32; w * h];
            for k in [1, 3, 5, 7] {
                let r = corner_response(&img, w, h, 2, k, CornerMethod::Harris, 0.04, 255.0);
                assert_eq!(r.len(), w * h);
                assert!(r.iter().all(|v| v.is_finite()));
            }
        }
    }

    /// Antialiased checkerboard (16× supersampling): squares of `s` px, corner lattice at
    /// `origin + (i, j)·s`, dark 40 / light 210.
    fn checkerboard(w: usize, h: usize, s: f64, origin: (f64, f64)) -> Vec<f32> {
        let mut img = vec![0.0f32; w * h];
        let n = 16;
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for sy in 0..n {
                    for sx in 0..n {
                        // Pixel (x, y) covers [x − 0.5, x + 0.5).
                        let px = x as f64 - 0.5 + (sx as f64 + 0.5) / n as f64;
                        let py = y as f64 - 0.5 + (sy as f64 + 0.5) / n as f64;
                        let i = ((px - origin.0) / s).floor() as i64;
                        let j = ((py - origin.1) / s).floor() as i64;
                        acc += if (i + j).rem_euclid(2) == 0 {
                            210.0
                        } else {
                            40.0
                        };
                    }
                }
                img[y * w + x] = (acc / (n * n) as f64) as f32;
            }
        }
        img
    }

    #[test]
    fn checkerboard_corners_subpixel_within_0_1_px() {
        let (w, h, s) = (120, 100, 20.0);
        let origin = (10.37, 9.71);
        // A camera-like blur (σ = 1 px) on the antialiased board: cornerSubPix's estimate on a
        // 1-px ramp is biased by ~0.1 px (OpenCV's too); on a smooth edge the bias is ~0.06 px.
        let sharp = Image::from_f32(w, h, Channels::Gray, checkerboard(w, h, s, origin)).unwrap();
        let blurred = crate::filter::gaussian::gaussian_blur(
            &sharp,
            1.0,
            1.0,
            0,
            0,
            BorderMode::Reflect101,
            0.0,
        );
        let img = blurred.as_f32().unwrap().to_vec();
        let r = corner_response(&img, w, h, 3, 3, CornerMethod::Harris, 0.04, 255.0);
        let sel = select_corners(&r, w, h, 0.1, 10.0, 0);
        let mut pts: Vec<(f64, f64)> = sel.iter().map(|&(x, y, _)| (x as f64, y as f64)).collect();
        refine_corners(&img, w, h, &mut pts, 5, 40, 0.001);
        // Interior lattice corners at least 8 px inside.
        let mut checked = 0;
        let mut worst = 0.0f64;
        for i in 0..8 {
            for j in 0..8 {
                let tx = origin.0 + i as f64 * s;
                let ty = origin.1 + j as f64 * s;
                if tx < 8.0 || ty < 8.0 || tx > (w - 9) as f64 || ty > (h - 9) as f64 {
                    continue;
                }
                let best = pts
                    .iter()
                    .map(|p| ((p.0 - tx).powi(2) + (p.1 - ty).powi(2)).sqrt())
                    .fold(f64::INFINITY, f64::min);
                worst = worst.max(best);
                checked += 1;
            }
        }
        assert!(checked >= 20, "{checked}");
        assert!(worst < 0.1, "worst corner error {worst} px");
    }

    #[test]
    fn selection_respects_distance_and_count() {
        let (w, h) = (60, 50);
        let img = checkerboard(w, h, 10.0, (5.5, 5.5));
        let r = corner_response(&img, w, h, 3, 3, CornerMethod::ShiTomasi, 0.0, 255.0);
        let sel = select_corners(&r, w, h, 0.01, 8.0, 0);
        assert!(!sel.is_empty());
        for (i, a) in sel.iter().enumerate() {
            for b in &sel[i + 1..] {
                let d2 = (a.0 as f64 - b.0 as f64).powi(2) + (a.1 as f64 - b.1 as f64).powi(2);
                assert!(d2 >= 64.0);
            }
        }
        assert!(sel.windows(2).all(|p| p[0].2 >= p[1].2));
        assert_eq!(select_corners(&r, w, h, 0.01, 8.0, 3).len(), 3);
    }

    #[test]
    fn same_result_with_one_thread() {
        let img = checkerboard(90, 200, 13.0, (3.2, 4.9));
        let many = corner_response(&img, 90, 200, 2, 3, CornerMethod::Harris, 0.04, 255.0);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let one = pool
            .install(|| corner_response(&img, 90, 200, 2, 3, CornerMethod::Harris, 0.04, 255.0));
        assert_eq!(many, one);
    }

    fn run_op(params: CornersParams, image: Image) -> Result<Outputs, OpError> {
        let op = Corners::new(params).map_err(OpError::failed)?;
        let specs = Corners::inputs();
        let values = vec![Some(Value::image(image))];
        let inputs = Inputs::new(&specs, &values);
        let ctx = RunContext {
            node: "corners".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &inputs)
    }

    #[test]
    fn operator_formats() {
        let img = checkerboard(40, 40, 10.0, (5.5, 5.5));
        let u8img = Image::from_u8(
            40,
            40,
            Channels::Gray,
            img.iter().map(|&v| v as u8).collect(),
        )
        .unwrap();
        let mut out = run_op(CornersParams::default(), u8img).unwrap();
        match out.take("keypoints") {
            Some(Value::Keypoints(k)) => assert!(!k.is_empty()),
            other => panic!("{other:?}"),
        }
        let rgb = Image::from_u8(2, 2, Channels::Rgb, vec![0; 12]).unwrap();
        assert!(run_op(CornersParams::default(), rgb).is_err());
        let empty = Image::from_f32(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(run_op(CornersParams::default(), empty).is_ok());
        let one = Image::from_f32(1, 1, Channels::Gray, vec![1.0]).unwrap();
        assert!(
            run_op(
                CornersParams {
                    subpixel: true,
                    ..CornersParams::default()
                },
                one
            )
            .is_ok()
        );
    }

    #[test]
    fn rejects_bad_params() {
        let p = CornersParams::default();
        assert!(
            Corners::new(CornersParams {
                ksize: 4,
                ..p.clone()
            })
            .is_err()
        );
        assert!(
            Corners::new(CornersParams {
                k: f64::NAN,
                ..p.clone()
            })
            .is_err()
        );
        assert!(
            Corners::new(CornersParams {
                quality_level: 0.0,
                ..p.clone()
            })
            .is_err()
        );
        assert!(Corners::new(CornersParams { block_size: 0, ..p }).is_err());
    }

    // The straightforward implementation the vectorized one replaced (per-pixel interleaved
    // products, a fresh sum row per output row, a scalar scan of every pixel in the
    // selection), kept as the reference the fast path must equal bit for bit.
    /// Separable Sobel derivatives of one row `y` of `src` (`width` wide), border reflect101:
    /// `dx` and `dy` (unscaled), using the scratch `vs` / `vd` (padded vertical sums).
    struct RefDerivRows {
        smooth: Vec<f32>,
        deriv: Vec<f32>,
        /// Vertical smoothing sums, padded.
        vs: Vec<f32>,
        /// Vertical derivative sums, padded.
        vd: Vec<f32>,
        columns: BorderTable,
    }

    impl RefDerivRows {
        fn new(width: usize, ksize: usize) -> RefDerivRows {
            let deriv: Vec<f32> = deriv_kernel(ksize, 1).iter().map(|&v| v as f32).collect();
            // The smoothing kernel, centred in a kernel as long as `deriv` (ksize 1: [0, 1, 0]).
            let raw = deriv_kernel(ksize, 0);
            let offset = (deriv.len() - raw.len().min(deriv.len())) / 2;
            let mut smooth = vec![0.0f32; deriv.len()];
            for (s, &v) in smooth[offset..].iter_mut().zip(&raw) {
                *s = v as f32;
            }
            let r = deriv.len() / 2;
            let columns = BorderTable::symmetric(width, r, BorderMode::Reflect101);
            let padded = columns.padded_len();
            RefDerivRows {
                smooth,
                deriv,
                vs: vec![0.0; padded],
                vd: vec![0.0; padded],
                columns,
            }
        }

        fn row(&mut self, src: &[f32], width: usize, height: usize, y: usize, dx: &mut [f32]) {
            let (dx, dy) = dx.split_at_mut(width);
            let r = self.deriv.len() / 2;
            let pad = self.columns.before();
            // Vertical pass into the interior of vs (smooth, for dx) and vd (deriv, for dy).
            let vs_in = &mut self.vs[pad..pad + width];
            let vd_in = &mut self.vd[pad..pad + width];
            vs_in.fill(0.0);
            vd_in.fill(0.0);
            for (i, &kd) in self.deriv.iter().enumerate() {
                let sy = map_index(
                    y as isize + i as isize - r as isize,
                    height,
                    BorderMode::Reflect101,
                )
                .unwrap_or(0);
                let row = &src[sy * width..(sy + 1) * width];
                let ks = self.smooth[i];
                for ((s, d), &p) in vs_in.iter_mut().zip(vd_in.iter_mut()).zip(row) {
                    *s += ks * p;
                    *d += kd * p;
                }
            }
            // Borders of the padded rows.
            for k in (0..pad).chain(pad + width..pad + width + self.columns.after()) {
                let s = self.columns.source(k).unwrap_or(0) + pad;
                self.vs[k] = self.vs[s];
                self.vd[k] = self.vd[s];
            }
            // Horizontal pass.
            dx.fill(0.0);
            dy.fill(0.0);
            let taps = self.deriv.len();
            for i in 0..taps {
                let kd = self.deriv[i];
                let ks = self.smooth[i];
                let vs = &self.vs[i..i + width];
                let vd = &self.vd[i..i + width];
                for (((gx, gy), &s), &d) in dx.iter_mut().zip(dy.iter_mut()).zip(vs).zip(vd) {
                    *gx += kd * s;
                    *gy += ks * d;
                }
            }
        }
    }

    /// The corner response of a gray f32 plane (`width × height`, row-major), OpenCV's
    /// `cornerHarris(src, block_size, ksize, k)` or `cornerMinEigenVal(src, block_size, ksize)`.
    ///
    /// `range` is the sample range the derivatives are divided by (255 for 8-bit data). `ksize` is
    /// 1, 3, 5 or 7, `block_size` ≥ 1. Bit-identical for any thread count.
    #[allow(clippy::too_many_arguments)]
    fn reference_response(
        src: &[f32],
        width: usize,
        height: usize,
        block_size: usize,
        ksize: usize,
        method: CornerMethod,
        k: f64,
        range: f32,
    ) -> Vec<f32> {
        let mut out = vec![0.0f32; width * height];
        if width == 0 || height == 0 || src.len() != width * height {
            return out;
        }
        let block = block_size.max(1);
        let aperture = if ksize <= 1 { 3 } else { ksize };
        let scale = 1.0 / ((1u64 << (aperture.max(2) - 1).min(62)) as f64 * block as f64);
        let scale = if ksize <= 1 {
            1.0 / block as f64
        } else {
            scale
        };
        let scale = (scale / f64::from(range)) as f32;
        let before = block / 2;
        let after = block - 1 - before;
        let columns = BorderTable::new(width, before, after, BorderMode::Reflect101);
        let padded = columns.padded_len();
        out.par_chunks_mut(width * BAND_ROWS)
            .enumerate()
            .for_each(|(b, band)| {
                let y0 = b * BAND_ROWS;
                let rows = band.len() / width;
                let mut deriv = RefDerivRows::new(width, ksize);
                let mut d = vec![0.0f32; 2 * width];
                // Products, padded: xx, xy, yy interleaved.
                let mut prod = vec![0.0f32; 3 * padded];
                // Ring of horizontal sums, `block` rows of 3 × width f64.
                let mut ring = vec![0.0f64; block * 3 * width];
                let first = y0 as isize - before as isize;
                let last = (y0 + rows + after) as isize;
                for j in first..last {
                    let sy = map_index(j, height, BorderMode::Reflect101).unwrap_or(0);
                    deriv.row(src, width, height, sy, &mut d);
                    let (dx, dy) = d.split_at(width);
                    let inner = &mut prod[3 * before..3 * (before + width)];
                    for ((p, &gx), &gy) in inner.chunks_exact_mut(3).zip(dx).zip(dy) {
                        let gx = gx * scale;
                        let gy = gy * scale;
                        p[0] = gx * gx;
                        p[1] = gx * gy;
                        p[2] = gy * gy;
                    }
                    for kpos in (0..before).chain(before + width..padded) {
                        let s = columns.source(kpos).unwrap_or(0) + before;
                        for c in 0..3 {
                            prod[3 * kpos + c] = prod[3 * s + c];
                        }
                    }
                    let slot = (j - first) as usize % block;
                    let hs = &mut ring[slot * 3 * width..(slot + 1) * 3 * width];
                    if block == 2 {
                        for (x, h) in hs.chunks_exact_mut(3).enumerate() {
                            let p = &prod[3 * x..3 * x + 6];
                            h[0] = f64::from(p[0]) + f64::from(p[3]);
                            h[1] = f64::from(p[1]) + f64::from(p[4]);
                            h[2] = f64::from(p[2]) + f64::from(p[5]);
                        }
                    } else {
                        for (x, h) in hs.chunks_exact_mut(3).enumerate() {
                            let mut s = [0.0f64; 3];
                            for p in prod[3 * x..3 * (x + block)].chunks_exact(3) {
                                s[0] += f64::from(p[0]);
                                s[1] += f64::from(p[1]);
                                s[2] += f64::from(p[2]);
                            }
                            h.copy_from_slice(&s);
                        }
                    }
                    let done = (j - first) as usize + 1;
                    if done >= block {
                        let y = done - block; // output row within the band
                        let out_row = &mut band[y * width..(y + 1) * width];
                        reference_respond_row(&ring, block, width, method, k, out_row);
                    }
                }
            });
        out
    }

    /// Sums the `block` rows of horizontal sums and writes the response of one output row.
    fn reference_respond_row(
        ring: &[f64],
        block: usize,
        width: usize,
        method: CornerMethod,
        k: f64,
        out: &mut [f32],
    ) {
        let n = 3 * width;
        let mut sums = ring[..n].to_vec();
        for r in 1..block {
            for (s, &v) in sums.iter_mut().zip(&ring[r * n..(r + 1) * n]) {
                *s += v;
            }
        }
        match method {
            CornerMethod::Harris => {
                for (o, s) in out.iter_mut().zip(sums.chunks_exact(3)) {
                    let a = f64::from(s[0] as f32);
                    let b = f64::from(s[1] as f32);
                    let c = f64::from(s[2] as f32);
                    *o = (a * c - b * b - k * (a + c) * (a + c)) as f32;
                }
            }
            CornerMethod::ShiTomasi => {
                for (o, s) in out.iter_mut().zip(sums.chunks_exact(3)) {
                    let a = (s[0] as f32) * 0.5;
                    let b = s[1] as f32;
                    let c = (s[2] as f32) * 0.5;
                    *o = (a + c) - ((a - c) * (a - c) + b * b).sqrt();
                }
            }
        }
    }

    /// `goodFeaturesToTrack`-style selection on a response image: pixels (not on the image's outer
    /// frame) that are 3×3 maxima and strictly above `quality_level · max`, in order of decreasing
    /// response (equal responses: later in raster order first, as OpenCV), each kept only if no
    /// kept corner lies closer than `min_distance` px; at most `max_corners` (0: no limit).
    /// Returns `(x, y, response)` with integer pixel coordinates.
    fn reference_select(
        response: &[f32],
        width: usize,
        height: usize,
        quality_level: f64,
        min_distance: f64,
        max_corners: usize,
    ) -> Vec<(usize, usize, f32)> {
        if width < 3 || height < 3 || response.len() != width * height {
            return Vec::new();
        }
        let max = response
            .iter()
            .copied()
            .filter(|v| !v.is_nan())
            .fold(f32::NEG_INFINITY, f32::max);
        let threshold = (f64::from(max) * quality_level) as f32;
        let keep = |v: f32| if v > threshold { v } else { 0.0 };
        let mut candidates: Vec<(f32, usize)> = (1..height - 1)
            .into_par_iter()
            .map(|y| {
                let mut found = Vec::new();
                for x in 1..width - 1 {
                    let v = keep(response[y * width + x]);
                    if v == 0.0 || v.is_nan() {
                        continue;
                    }
                    let mut is_max = true;
                    // Dilation of the thresholded image (outside the image does not count).
                    'n: for yy in y - 1..=y + 1 {
                        let row = &response[yy * width..(yy + 1) * width];
                        for &r in &row[x - 1..=x + 1] {
                            if keep(r) > v {
                                is_max = false;
                                break 'n;
                            }
                        }
                    }
                    if is_max {
                        found.push((v, y * width + x));
                    }
                }
                found
            })
            .flatten()
            .collect();
        candidates.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(b.1.cmp(&a.1)));
        let limit = if max_corners == 0 {
            usize::MAX
        } else {
            max_corners
        };
        let mut kept: Vec<(usize, usize, f32)> = Vec::new();
        if min_distance >= 1.0 {
            let cell = min_distance.round().max(1.0) as usize;
            let gw = width.div_ceil(cell);
            let gh = height.div_ceil(cell);
            let mut grid: Vec<Vec<(usize, usize)>> = vec![Vec::new(); gw * gh];
            let d2 = (min_distance * min_distance) as f32;
            for &(v, i) in &candidates {
                if kept.len() >= limit {
                    break;
                }
                let (x, y) = (i % width, i / width);
                let (cx, cy) = (x / cell, y / cell);
                let mut good = true;
                'cells: for gy in cy.saturating_sub(1)..=(cy + 1).min(gh - 1) {
                    for gx in cx.saturating_sub(1)..=(cx + 1).min(gw - 1) {
                        for &(px, py) in &grid[gy * gw + gx] {
                            let dx = px as f32 - x as f32;
                            let dy = py as f32 - y as f32;
                            if dx * dx + dy * dy < d2 {
                                good = false;
                                break 'cells;
                            }
                        }
                    }
                }
                if good {
                    grid[cy * gw + cx].push((x, y));
                    kept.push((x, y, v));
                }
            }
        } else {
            kept.extend(
                candidates
                    .iter()
                    .take(limit)
                    .map(|&(v, i)| (i % width, i / width, v)),
            );
        }
        kept
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    fn lcg(seed: u64) -> impl FnMut() -> u64 {
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            s >> 33
        }
    }

    /// Random planes of u8-, u16- and f32-like values (with their ranges), and edge shapes.
    fn planes() -> Vec<(usize, usize, Vec<f32>, f32)> {
        let mut out = Vec::new();
        let sizes = [
            (1, 1),
            (1, 5),
            (5, 1),
            (2, 3),
            (3, 3),
            (7, 4),
            (17, 9),
            (40, 37),
            (67, 70),
        ];
        for (i, &(w, h)) in sizes.iter().enumerate() {
            let mut r = lcg(i as u64 + 7);
            out.push((
                w,
                h,
                (0..w * h).map(|_| (r() % 256) as f32).collect(),
                255.0,
            ));
            out.push((
                w,
                h,
                (0..w * h).map(|_| (r() % 65536) as f32).collect(),
                65535.0,
            ));
            out.push((
                w,
                h,
                (0..w * h)
                    .map(|_| (r() % 2_000_001) as f32 / 1e6 - 1.0)
                    .collect(),
                1.0,
            ));
            // Blocks with plateaus (many equal responses).
            out.push((
                w,
                h,
                (0..w * h)
                    .map(|p| (((p % w) / 4 * 31 + (p / w) / 4 * 17) % 5 * 60) as f32)
                    .collect(),
                255.0,
            ));
        }
        out
    }

    #[test]
    fn response_equals_reference_bit_for_bit() {
        for (w, h, img, range) in planes() {
            for ksize in [1, 3, 5, 7] {
                for block in [1, 2, 3, 4, 5, 7] {
                    for method in [CornerMethod::Harris, CornerMethod::ShiTomasi] {
                        let fast = corner_response(&img, w, h, block, ksize, method, 0.04, range);
                        let slow =
                            reference_response(&img, w, h, block, ksize, method, 0.04, range);
                        assert_eq!(
                            bits(&fast),
                            bits(&slow),
                            "{w}×{h} range {range} ksize {ksize} block {block} {method:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn selection_equals_reference() {
        for (w, h, img, range) in planes() {
            for method in [CornerMethod::Harris, CornerMethod::ShiTomasi] {
                let r = corner_response(&img, w, h, 3, 3, method, 0.04, range);
                for (q, d, n) in [
                    (0.01, 10.0, 2000),
                    (0.3, 0.0, 0),
                    (0.001, 3.0, 7),
                    (0.5, 1.0, 1),
                ] {
                    assert_eq!(
                        select_corners(&r, w, h, q, d, n),
                        reference_select(&r, w, h, q, d, n),
                        "{w}×{h} {method:?} q {q} d {d} n {n}"
                    );
                }
            }
        }
        // Responses with NaN, negative maxima and ties.
        let (w, h) = (37, 23);
        let mut r = lcg(99);
        let mut resp: Vec<f32> = (0..w * h).map(|_| (r() % 7) as f32 - 3.0).collect();
        for (q, d, n) in [(0.01, 0.0, 0), (0.5, 2.0, 5)] {
            assert_eq!(
                select_corners(&resp, w, h, q, d, n),
                reference_select(&resp, w, h, q, d, n)
            );
            let negative: Vec<f32> = resp.iter().map(|v| v - 10.0).collect();
            assert_eq!(
                select_corners(&negative, w, h, q, d, n),
                reference_select(&negative, w, h, q, d, n)
            );
        }
        resp[5 * w + 5] = f32::NAN;
        resp[7 * w + 9] = f32::INFINITY;
        assert_eq!(
            select_corners(&resp, w, h, 0.01, 0.0, 0),
            reference_select(&resp, w, h, 0.01, 0.0, 0)
        );
    }
}
