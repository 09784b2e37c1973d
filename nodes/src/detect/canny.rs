//! `detect.canny`: Canny's edge detector with the behaviour of OpenCV's `cv::Canny`.
//!
//! The algorithm is a plain function, [`canny`], on a gray 8-bit buffer; [`Canny`] is the thin
//! operator around it. [`sobel_i16`] exposes the gradients it uses.
//!
//! # How the work is split
//!
//! Gradients, magnitudes and non-maximum suppression run on bands of [`BAND_ROWS`] rows in
//! parallel. A band recomputes the gradient rows just above and below it, so no band reads
//! another's results and every pixel's value is computed the same way whatever the thread count.
//! Hysteresis (the flood fill from strong pixels) is sequential. The output is therefore
//! bit-identical for any number of threads.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, Value};
use rayon::prelude::*;

/// Rows per parallel band. A constant (never derived from the thread count) so the split, and
/// with it the order of the hysteresis seeds, is the same on every machine.
pub const BAND_ROWS: usize = 64;

/// Fixed-point shift for the direction test: slopes are compared as `|dy| · 2^15` against
/// `|dx| · tan(θ) · 2^15`.
const CANNY_SHIFT: u32 = 15;

/// `tan(22.5°) · 2^15 = 0.4142135623730950488 · 32768 = 13573.0…`, rounded to nearest, as
/// OpenCV's `TG22`. `tan(67.5°) · 2^15` is taken as `TG22 + 2^16` (since `tan 67.5° = tan 22.5° +
/// 2`).
const TG22: i32 = 13573;

/// Largest supported Sobel aperture.
const MAX_APERTURE: usize = 7;

/// OpenCV's Canny divides 7×7 Sobel gradients (and the thresholds) by this so they fit `i16`.
const APERTURE7_SCALE: i32 = 16;

/// Map value: not an edge.
const NONE: u8 = 0;
/// Map value: a local maximum above `low` but not above `high`; an edge only if connected to a
/// strong pixel.
const WEAK: u8 = 1;
/// Map value: an edge (a local maximum above `high`, or a weak pixel reached from one).
const STRONG: u8 = 2;

/// Output value of an edge pixel.
const EDGE: u8 = 255;

/// Separable Sobel kernels of one aperture: `smooth` (binomial) and `deriv` (binomial convolved
/// with the central difference `[-1, 0, 1]`), the first `len` entries of each array used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct SobelKernels {
    smooth: [i32; MAX_APERTURE],
    deriv: [i32; MAX_APERTURE],
    len: usize,
}

impl SobelKernels {
    /// The kernels OpenCV's `getDerivKernels` returns for `ksize` 3, 5 or 7 (first derivative,
    /// unnormalised): `smooth = b ∗ [1, 2, 1]` and `deriv = b ∗ [-1, 0, 1]` where `b` is the
    /// binomial row of length `aperture − 2`. `None` for other sizes.
    fn new(aperture: usize) -> Option<SobelKernels> {
        if !matches!(aperture, 3 | 5 | 7) {
            return None;
        }
        // Binomial row of length `aperture − 2`: repeated convolution of [1] with [1, 1].
        let mut binomial = [0i32; MAX_APERTURE];
        binomial[0] = 1;
        for n in 1..aperture - 2 {
            for i in (1..=n).rev() {
                binomial[i] += binomial[i - 1];
            }
        }
        let base_len = aperture - 2;
        let mut smooth = [0i32; MAX_APERTURE];
        let mut deriv = [0i32; MAX_APERTURE];
        for (i, &b) in binomial[..base_len].iter().enumerate() {
            for (j, (&s, &d)) in [1, 2, 1].iter().zip(&[-1, 0, 1]).enumerate() {
                smooth[i + j] += b * s;
                deriv[i + j] += b * d;
            }
        }
        Some(SobelKernels {
            smooth,
            deriv,
            len: aperture,
        })
    }

    fn smooth(&self) -> &[i32] {
        &self.smooth[..self.len]
    }

    fn deriv(&self) -> &[i32] {
        &self.deriv[..self.len]
    }

    fn radius(&self) -> usize {
        self.len / 2
    }
}

/// `s / 16` rounded to nearest, ties to even: what OpenCV's float Sobel with `scale = 1/16`
/// followed by `saturate_cast<short>` (`cvRound`) gives for an exact integer sum `s`.
fn div16_round_even(s: i32) -> i32 {
    let q = s >> 4; // floor division
    let r = s & 15;
    if r > 8 || (r == 8 && q & 1 == 1) {
        q + 1
    } else {
        q
    }
}

/// A gray 8-bit image read with a replicated border.
#[derive(Clone, Copy)]
struct Source<'a> {
    pixels: &'a [u8],
    width: usize,
    height: usize,
}

impl Source<'_> {
    /// Row `y`, the index clamped into the image (border replicate).
    fn row(&self, y: isize) -> &[u8] {
        let y = y.clamp(0, self.height as isize - 1) as usize;
        &self.pixels[y * self.width..(y + 1) * self.width]
    }
}

/// Reusable per-band buffers for the separable passes of one row.
struct RowScratch {
    /// Vertically smoothed row, padded by the kernel radius on both sides (replicated).
    vs: Vec<i32>,
    /// Vertically differentiated row, padded the same way.
    vd: Vec<i32>,
    /// 16-bit versions for the 3×3 path, padded by one.
    vs16: Vec<i16>,
    vd16: Vec<i16>,
}

impl RowScratch {
    fn new(width: usize, kernels: &SobelKernels) -> RowScratch {
        let padded = width + 2 * kernels.radius();
        let (wide, narrow) = if kernels.len == 3 {
            (0, padded)
        } else {
            (padded, 0)
        };
        RowScratch {
            vs: vec![0; wide],
            vd: vec![0; wide],
            vs16: vec![0; narrow],
            vd16: vec![0; narrow],
        }
    }
}

/// Sobel `dx`, `dy` of row `y` (3×3, border replicate), all in `i16`: the vertical sums reach at
/// most `4 · 255`, the gradients `± 4 · 255 = ± 1020`.
fn gradient_row3(
    src: Source<'_>,
    y: usize,
    scratch: &mut RowScratch,
    dx: &mut [i16],
    dy: &mut [i16],
) {
    let width = src.width;
    let y = y as isize;
    let (up, mid, down) = (src.row(y - 1), src.row(y), src.row(y + 1));
    let vs = &mut scratch.vs16[..width + 2];
    let vd = &mut scratch.vd16[..width + 2];
    // Vertical pass: smoothing [1, 2, 1] (for dx) and difference [-1, 0, 1] (for dy).
    for ((((s, d), &a), &b), &c) in vs[1..=width]
        .iter_mut()
        .zip(vd[1..=width].iter_mut())
        .zip(up)
        .zip(mid)
        .zip(down)
    {
        let (a, b, c) = (i16::from(a), i16::from(b), i16::from(c));
        *s = a + 2 * b + c;
        *d = c - a;
    }
    // Replicated columns: the vertical sums at x = -1 and x = width equal those at the edges.
    vs[0] = vs[1];
    vs[width + 1] = vs[width];
    vd[0] = vd[1];
    vd[width + 1] = vd[width];
    // Horizontal pass: difference for dx, smoothing for dy.
    for ((gx, l), r) in dx.iter_mut().zip(&vs[..width]).zip(&vs[2..]) {
        *gx = r - l;
    }
    for (((gy, l), m), r) in dy
        .iter_mut()
        .zip(&vd[..width])
        .zip(&vd[1..=width])
        .zip(&vd[2..])
    {
        *gy = l + 2 * m + r;
    }
}

/// Sobel `dx`, `dy` of row `y` for apertures 5 and 7 (border replicate), computed exactly in
/// `i32`; aperture 7 is divided by 16 with OpenCV's rounding so it fits `i16`.
fn gradient_row_wide(
    src: Source<'_>,
    y: usize,
    kernels: &SobelKernels,
    scratch: &mut RowScratch,
    dx: &mut [i16],
    dy: &mut [i16],
) {
    let width = src.width;
    let r = kernels.radius();
    let vs = &mut scratch.vs[..width + 2 * r];
    let vd = &mut scratch.vd[..width + 2 * r];
    vs.fill(0);
    vd.fill(0);
    for (i, (&ks, &kd)) in kernels.smooth().iter().zip(kernels.deriv()).enumerate() {
        let row = src.row(y as isize + i as isize - r as isize);
        for ((s, d), &p) in vs[r..r + width]
            .iter_mut()
            .zip(vd[r..r + width].iter_mut())
            .zip(row)
        {
            let p = i32::from(p);
            *s += ks * p;
            *d += kd * p;
        }
    }
    for i in 0..r {
        vs[i] = vs[r];
        vd[i] = vd[r];
        vs[r + width + i] = vs[r + width - 1];
        vd[r + width + i] = vd[r + width - 1];
    }
    let scaled = kernels.len == 7;
    for (x, (gx, gy)) in dx.iter_mut().zip(dy.iter_mut()).enumerate() {
        let mut sx = 0i32;
        let mut sy = 0i32;
        for ((&ws, &wd), (&kd, &ks)) in vs[x..x + kernels.len]
            .iter()
            .zip(&vd[x..x + kernels.len])
            .zip(kernels.deriv().iter().zip(kernels.smooth()))
        {
            sx += kd * ws;
            sy += ks * wd;
        }
        if scaled {
            sx = div16_round_even(sx);
            sy = div16_round_even(sy);
        }
        // In range by construction (|sx|, |sy| ≤ 16 · 3 · 255 = 12240 for aperture 5, ≤ 64 ·
        // 10 · 255 / 16 = 10200 for 7 after scaling); the clamp only mirrors OpenCV's
        // saturating cast.
        *gx = sx.clamp(i32::from(i16::MIN), i32::from(i16::MAX)) as i16;
        *gy = sy.clamp(i32::from(i16::MIN), i32::from(i16::MAX)) as i16;
    }
}

/// Gradient of row `y` with the given kernels.
fn gradient_row(
    src: Source<'_>,
    y: usize,
    kernels: &SobelKernels,
    scratch: &mut RowScratch,
    dx: &mut [i16],
    dy: &mut [i16],
) {
    if kernels.len == 3 {
        gradient_row3(src, y, scratch, dx, dy);
    } else {
        gradient_row_wide(src, y, kernels, scratch, dx, dy);
    }
}

/// Sobel derivatives `(dx, dy)` of a gray image as `cv::Canny` computes them: `cv::Sobel(src,
/// CV_16S, 1, 0, aperture)` and `(0, 1)`, border replicate, correlation (so `dx > 0` where the
/// image brightens to the right, `dy > 0` where it brightens downwards), row-major.
///
/// `aperture` is 3, 5 or 7. As in `cv::Canny`, the 7×7 derivatives are divided by 16 (rounded to
/// nearest, ties to even) so they fit `i16`; 3×3 and 5×5 are exact (at most 1020 and 12240 in
/// magnitude).
///
/// Computed row-parallel in bands of [`BAND_ROWS`] rows; the result does not depend on the
/// thread count.
///
/// # Panics
///
/// If `gray.len() != width × height` or `aperture` is not 3, 5 or 7 (preconditions, checked by
/// the operator before it calls this).
pub fn sobel_i16(
    gray: &[u8],
    width: usize,
    height: usize,
    aperture: usize,
) -> (Vec<i16>, Vec<i16>) {
    let kernels = checked_kernels(gray, width, height, aperture);
    let src = Source {
        pixels: gray,
        width,
        height,
    };
    let n = width * height;
    let mut dx = vec![0i16; n];
    let mut dy = vec![0i16; n];
    if n == 0 {
        return (dx, dy);
    }
    let band = width * BAND_ROWS;
    dx.par_chunks_mut(band)
        .zip(dy.par_chunks_mut(band))
        .enumerate()
        .for_each(|(b, (dx_band, dy_band))| {
            let mut scratch = RowScratch::new(width, &kernels);
            for (i, (dx_row, dy_row)) in dx_band
                .chunks_exact_mut(width)
                .zip(dy_band.chunks_exact_mut(width))
                .enumerate()
            {
                let y = b * BAND_ROWS + i;
                gradient_row(src, y, &kernels, &mut scratch, dx_row, dy_row);
            }
        });
    (dx, dy)
}

/// The kernels for `aperture`, after checking the documented preconditions.
fn checked_kernels(gray: &[u8], width: usize, height: usize, aperture: usize) -> SobelKernels {
    assert_eq!(
        Some(gray.len()),
        width.checked_mul(height),
        "gray buffer must hold width × height samples"
    );
    match SobelKernels::new(aperture) {
        Some(k) => k,
        None => panic!("Sobel aperture must be 3, 5 or 7, got {aperture}"),
    }
}

/// The two thresholds as integers comparable with the integer magnitudes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Thresholds {
    low: i32,
    high: i32,
}

impl Thresholds {
    /// Derived exactly as `cv::Canny` does: swap if `low > high`; divide by 16 for aperture 7;
    /// for L2, clamp to 32767 and square (compared against `dx² + dy²`); then floor. A magnitude
    /// `m` passes a threshold `t` when `m > floor(t)`, which for integer `m` is `m > t`.
    fn new(low: f64, high: f64, aperture: usize, l2: bool) -> Thresholds {
        let (mut low, mut high) = if low > high { (high, low) } else { (low, high) };
        if aperture == 7 {
            low /= f64::from(APERTURE7_SCALE);
            high /= f64::from(APERTURE7_SCALE);
        }
        if l2 {
            const L2_CLAMP: f64 = 32767.0;
            low = low.min(L2_CLAMP);
            high = high.min(L2_CLAMP);
            if low > 0.0 {
                low *= low;
            }
            if high > 0.0 {
                high *= high;
            }
        }
        // `as` saturates (and maps NaN to 0), as a clamp to the `int` range would.
        Thresholds {
            low: low.floor() as i32,
            high: high.floor() as i32,
        }
    }
}

/// One row of gradients and magnitudes; `mag` is padded with a zero on both sides (OpenCV treats
/// magnitudes outside the image as 0).
struct GradRow {
    dx: Vec<i16>,
    dy: Vec<i16>,
    mag: Vec<i32>,
}

impl GradRow {
    fn new(width: usize) -> GradRow {
        GradRow {
            dx: vec![0; width],
            dy: vec![0; width],
            mag: vec![0; width + 2],
        }
    }

    /// Fills the row with image row `y`, or with zero magnitudes when `y` is outside the image.
    fn fill(
        &mut self,
        src: Source<'_>,
        y: isize,
        kernels: &SobelKernels,
        scratch: &mut RowScratch,
        l2: bool,
    ) {
        let Ok(y) = usize::try_from(y) else {
            self.mag.fill(0);
            return;
        };
        if y >= src.height {
            self.mag.fill(0);
            return;
        }
        gradient_row(src, y, kernels, scratch, &mut self.dx, &mut self.dy);
        let mag = &mut self.mag[1..=src.width];
        if l2 {
            // ≤ 2 · 12240² < 2^31.
            for ((m, &gx), &gy) in mag.iter_mut().zip(&self.dx).zip(&self.dy) {
                let (gx, gy) = (i32::from(gx), i32::from(gy));
                *m = gx * gx + gy * gy;
            }
        } else {
            for ((m, &gx), &gy) in mag.iter_mut().zip(&self.dx).zip(&self.dy) {
                *m = i32::from(gx).abs() + i32::from(gy).abs();
            }
        }
    }
}

/// Pixels classified together by [`suppress_block`].
const NMS_BLOCK: usize = 16;

/// Non-maximum suppression and double thresholding of the middle row of `rows` (above, at,
/// below). `map` is that row of the padded map (`width + 2`, border columns left at [`NONE`]).
/// Strong pixels are appended to `strong` as indices into the padded map, `map_base` being the
/// index of `map[0]`.
fn suppress_row(
    rows: &[GradRow; 3],
    thresholds: Thresholds,
    map: &mut [u8],
    map_base: usize,
    strong: &mut Vec<usize>,
) {
    let [prev, cur, next] = rows;
    let width = cur.dx.len();
    let mut start = 0;
    while start < width {
        let len = NMS_BLOCK.min(width - start);
        let mags = [&prev.mag, &cur.mag, &next.mag].map(|row| &row[start..start + len + 2]);
        let out = &mut map[start + 1..start + 1 + len];
        if !mags[1]
            .iter()
            .fold(false, |any, &m| any | (m > thresholds.low))
        {
            // Nothing above `low` (most of a natural image): no candidate.
            out.fill(NONE);
        } else {
            // Fixed-size copies give the classification constant bounds; the row's last block
            // is padded with zeros, whose results are dropped.
            let classes = suppress_block(
                [&fixed(mags[0]), &fixed(mags[1]), &fixed(mags[2])],
                &fixed(&cur.dx[start..start + len]),
                &fixed(&cur.dy[start..start + len]),
                thresholds,
            );
            out.copy_from_slice(&classes[..len]);
            push_strong(&classes[..len], map_base + start + 1, strong);
        }
        start += len;
    }
}

/// `values` as an array of `N` (at most `N` values), padded with `T::default()`. A full block is a
/// fixed-size copy; only the short last block of a row pays for a variable-length one.
#[inline(always)]
fn fixed<T: Copy + Default, const N: usize>(values: &[T]) -> [T; N] {
    match <[T; N]>::try_from(values) {
        Ok(block) => block,
        Err(_) => {
            let mut block = [T::default(); N];
            block[..values.len()].copy_from_slice(values);
            block
        }
    }
}

/// Classifies [`NMS_BLOCK`] pixels as [`NONE`], [`WEAK`] or [`STRONG`]. `mags` holds the
/// magnitudes above, at and below them with one extra column on each side; `gx`, `gy` are
/// their gradients.
///
/// Branch-free, so the compiler vectorises it, and textured images, where a branchy version
/// mispredicts at most pixels, cost no more than smooth ones.
#[inline(always)]
fn suppress_block(
    mags: [&[i32; NMS_BLOCK + 2]; 3],
    gx: &[i16; NMS_BLOCK],
    gy: &[i16; NMS_BLOCK],
    thresholds: Thresholds,
) -> [u8; NMS_BLOCK] {
    let [p, c, n] = mags;
    let mut out = [NONE; NMS_BLOCK];
    for i in 0..NMS_BLOCK {
        let m = c[i + 1];
        let (x, y) = (i32::from(gx[i]), i32::from(gy[i]));
        // |dx|, |dy| ≤ 12240 (aperture 5; 10200 for 7 after /16), so every product below fits
        // in i32: 12240 · (13573 + 2^16) < 2^30.
        let ax = x.abs();
        let ay = y.abs() << CANNY_SHIFT;
        let tg22x = ax * TG22;
        let tg67x = tg22x + (ax << (CANNY_SHIFT + 1));
        // Sector: within 22.5° of horizontal, of vertical, or on the diagonal the signs of dx,
        // dy point to.
        let horizontal = ay < tg22x;
        let vertical = ay > tg67x;
        let diagonal = !horizontal & !vertical;
        let same_sign = (x ^ y) >= 0;
        // Local maximum along each direction, with OpenCV's tie rule: strictly above the
        // neighbour before, at least the one after; strictly above both on diagonals. Every
        // test is computed and the sector picks one with bit operations: no branch, no
        // selected load, so the loop vectorises.
        let max_h = (m > c[i]) & (m >= c[i + 2]);
        let max_v = (m > p[i + 1]) & (m >= n[i + 1]);
        let max_down_right = (m > p[i]) & (m > n[i + 2]);
        let max_down_left = (m > p[i + 2]) & (m > n[i]);
        let is_max = (horizontal & max_h)
            | (vertical & max_v)
            | (diagonal & same_sign & max_down_right)
            | (diagonal & !same_sign & max_down_left);
        let keep = (m > thresholds.low) & is_max;
        out[i] = u8::from(keep) * (WEAK + u8::from(m > thresholds.high));
    }
    out
}

/// Appends the indices of the [`STRONG`] entries of `classes` (offset by `base`); strong pixels
/// are rare, so the block is tested as a whole first.
#[inline]
fn push_strong(classes: &[u8], base: usize, strong: &mut Vec<usize>) {
    if classes.iter().fold(false, |any, &v| any | (v == STRONG)) {
        for (i, &v) in classes.iter().enumerate() {
            if v == STRONG {
                strong.push(base + i);
            }
        }
    }
}

/// Canny edges of a gray 8-bit image, matching `cv::Canny(image, edges, low, high, aperture,
/// l2)`: 255 on edge pixels, 0 elsewhere, `width × height` bytes, row-major.
///
/// - Gradients: [`sobel_i16`] (border replicate; aperture 7 divided by 16, thresholds too).
/// - Magnitude: `|dx| + |dy|`, or `dx² + dy²` against squared thresholds when `l2`.
/// - Non-maximum suppression in four directions, sectors chosen with the integer test `|dy| ·
///   2^15 < |dx| · 13573` (within 22.5° of horizontal) and `|dy| · 2^15 > |dx| · (13573 + 2^16)`
///   (within 22.5° of vertical). Ties: a pixel survives if it is `>` its left/upper neighbour
///   and `>=` its right/lower one; on diagonals it must be `>` both. Magnitudes outside the
///   image count as 0.
/// - Thresholds: a surviving pixel with `m > high` is strong, with `m > low` weak (strict, as
///   OpenCV). `low > high` are swapped.
/// - Hysteresis: edges are the strong pixels and every weak pixel 8-connected to one through
///   weak pixels.
///
/// An empty image gives an empty output. Bit-identical for any thread count.
///
/// # Panics
///
/// If `gray.len() != width × height` or `aperture` is not 3, 5 or 7 (preconditions, checked by
/// the operator before it calls this).
pub fn canny(
    gray: &[u8],
    width: usize,
    height: usize,
    low: f64,
    high: f64,
    aperture: usize,
    l2: bool,
) -> Vec<u8> {
    let kernels = checked_kernels(gray, width, height, aperture);
    if width == 0 || height == 0 {
        return Vec::new();
    }
    let src = Source {
        pixels: gray,
        width,
        height,
    };
    let thresholds = Thresholds::new(low, high, aperture, l2);

    // The map is padded by one pixel on every side, left at NONE, so the flood fill needs no
    // bounds checks.
    let stride = width + 2;
    let mut map = vec![NONE; stride * (height + 2)];
    let interior = &mut map[stride..stride * (height + 1)];

    let strong_per_band: Vec<Vec<usize>> = interior
        .par_chunks_mut(stride * BAND_ROWS)
        .enumerate()
        .map(|(b, map_band)| {
            // Rows y0 - 1 and y0 first, then one new row per step: a ring of three.
            let y0 = b * BAND_ROWS;
            let mut scratch = RowScratch::new(width, &kernels);
            let mut rows = [
                GradRow::new(width),
                GradRow::new(width),
                GradRow::new(width),
            ];
            rows[0].fill(src, y0 as isize - 1, &kernels, &mut scratch, l2);
            rows[1].fill(src, y0 as isize, &kernels, &mut scratch, l2);
            let mut strong = Vec::new();
            for (i, map_row) in map_band.chunks_exact_mut(stride).enumerate() {
                let y = y0 + i;
                rows[2].fill(src, y as isize + 1, &kernels, &mut scratch, l2);
                suppress_row(&rows, thresholds, map_row, (y + 1) * stride, &mut strong);
                rows.rotate_left(1);
            }
            strong
        })
        .collect();

    hysteresis(&mut map, stride, strong_per_band);
    unpad_into_edges(map, width, height)
}

/// Turns the padded map into the output in place: row `y`'s interior moves to `y · width`
/// (never after where it was, so a forward pass reads every row before overwriting it) while
/// [`STRONG`] becomes [`EDGE`] and everything else 0. Reusing the buffer spares a second
/// image-sized allocation.
fn unpad_into_edges(mut map: Vec<u8>, width: usize, height: usize) -> Vec<u8> {
    let stride = width + 2;
    for y in 0..height {
        let from = (y + 1) * stride + 1;
        map.copy_within(from..from + width, y * width);
        for v in &mut map[y * width..(y + 1) * width] {
            *v = if *v == STRONG { EDGE } else { 0 };
        }
    }
    map.truncate(width * height);
    map
}

/// Promotes every weak pixel 8-connected (through weak pixels) to a strong one, by a depth-first
/// flood fill on an explicit stack. `map` is padded by one [`NONE`] pixel on every side. The
/// result (a union of connected components) does not depend on the order of the seeds.
fn hysteresis(map: &mut [u8], stride: usize, seeds: Vec<Vec<usize>>) {
    let mut stack: Vec<usize> = Vec::with_capacity(seeds.iter().map(Vec::len).sum());
    for band in seeds {
        stack.extend(band);
    }
    while let Some(p) = stack.pop() {
        // `p` is an interior pixel, so all eight neighbours are inside the padded map.
        let neighbours = [
            p - stride - 1,
            p - stride,
            p - stride + 1,
            p - 1,
            p + 1,
            p + stride - 1,
            p + stride,
            p + stride + 1,
        ];
        for q in neighbours {
            if map[q] == WEAK {
                map[q] = STRONG;
                stack.push(q);
            }
        }
    }
}

ocellus_engine::params! {
    /// Parameters of [`Canny`].
    pub struct CannyParams {
        /// Lower hysteresis threshold on the gradient magnitude (Sobel units: `|dx| + |dy|`,
        /// or `√(dx² + dy²)` with `l2_gradient`). Local maxima above it are kept if connected
        /// to a strong edge.
        low: f64 = 50.0 => [min = 0.0],
        /// Upper threshold, same units: local maxima above it start an edge. If `low > high`
        /// the two are swapped, as OpenCV does.
        high: f64 = 150.0 => [min = 0.0],
        /// Sobel aperture: 3, 5 or 7. Larger apertures smooth more and give larger magnitudes
        /// (4×, 48× and 640× the intensity step for 3, 5 and 7 on an ideal step edge), so
        /// thresholds must grow with it.
        aperture: u32 = 3 => [min = 3, max = 7],
        /// Use the Euclidean magnitude `√(dx² + dy²)` instead of `|dx| + |dy|`.
        l2_gradient: bool = false,
    }
}

/// Canny's edge detector (`detect.canny`), compatible with OpenCV's `cv::Canny`.
///
/// See [`canny`] for the algorithm and [`Canny::DOC`](Op::DOC) for the user-facing description.
#[derive(Debug, Clone)]
pub struct Canny {
    low: f64,
    high: f64,
    aperture: usize,
    l2: bool,
}

impl Op for Canny {
    type Params = CannyParams;
    const ID: &'static str = "detect.canny";
    const SUMMARY: &'static str =
        "Canny edge detector (OpenCV-compatible): 255 on thin edges of a gray 8-bit image.";
    const DOC: &'static str = r#"
Finds thin edges with Canny's method: Sobel gradients, non-maximum suppression along the
gradient direction, then hysteresis between two thresholds. Output is bit-identical to OpenCV's
`cv::Canny(image, edges, low, high, aperture, l2_gradient)` (checked against OpenCV 5.0 for
apertures 3, 5, 7, L1 and L2, swapped and zero thresholds, images from 1×1 to 1920×1080).

Algorithm:
1. Gradients dx, dy: Sobel of size `aperture`, border replicate. Kernels are binomial smoothing
   [1,2,1], [1,4,6,4,1], [1,6,15,20,15,6,1] times derivatives [-1,0,1], [-1,-2,0,2,1],
   [-1,-4,-5,0,5,4,1].
2. Magnitude m = |dx| + |dy|, or dx² + dy² compared with squared thresholds (`l2_gradient`).
3. Non-maximum suppression: the direction falls in one of four sectors by the integer tests
   |dy|·2^15 < |dx|·13573 (within 22.5° of horizontal: compare left and right) and
   |dy|·2^15 > |dx|·(13573 + 2^16) (within 22.5° of vertical: compare above and below); otherwise
   the diagonal given by the signs of dx, dy. A pixel is kept if m is greater than the neighbour
   before it (left / above) and at least the one after it (right / below); on diagonals, greater
   than both. A step between two columns thus gives one line, on the left column when both tie.
4. Hysteresis: kept pixels with m > high are edges; kept pixels with m > low become edges when
   8-connected to an edge through such pixels. Both comparisons are strict, as in OpenCV.

Units: thresholds are Sobel magnitudes. An ideal step of height h gives m = 4h with aperture 3,
48h with 5 and 640h with 7, so larger apertures need proportionally larger thresholds (the
defaults suit 3). With aperture 7, OpenCV divides gradients (rounded) and thresholds by 16 to
stay in 16 bits; so does this operator. `low > high` is accepted and the two are swapped, as in
OpenCV.

References: J. Canny, "A Computational Approach to Edge Detection", IEEE PAMI 8(6), 1986;
OpenCV, imgproc/src/canny.cpp (integer sector test, tie rule).

Example (a node of a graph):
    "edges": (op: "detect.canny", inputs: { "image": "blur.image" },
              params: (low: 50, high: 150)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "gray u8 image (convert colour with filter.grayscale)",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "edges",
            PortType::Image,
            "gray u8, same size: 255 on edge pixels, 0 elsewhere",
        )]
    }

    fn new(params: CannyParams) -> Result<Self, String> {
        let aperture = match params.aperture {
            3 => 3,
            5 => 5,
            7 => 7,
            other => return Err(format!("`aperture` must be 3, 5 or 7, got {other}")),
        };
        for (name, value) in [("low", params.low), ("high", params.high)] {
            if !value.is_finite() || value < 0.0 {
                return Err(format!("`{name}` must be a finite number ≥ 0, got {value}"));
            }
        }
        Ok(Canny {
            low: params.low,
            high: params.high,
            aperture,
            l2: params.l2_gradient,
        })
    }
}

impl Operator for Canny {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let gray = match (image.channels(), image.as_u8()) {
            (Channels::Gray, Some(samples)) => samples,
            _ => return Err(format_error(image)),
        };
        let (width, height) = (image.width(), image.height());
        let edges = canny(
            gray,
            width,
            height,
            self.low,
            self.high,
            self.aperture,
            self.l2,
        );
        let out = Image::from_u8(width, height, Channels::Gray, edges)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("edges", Value::image(out)))
    }
}

fn format_error(image: &Image) -> OpError {
    let got = image.format();
    let hint = match (image.channels(), image.depth()) {
        (Channels::Gray, _) => {
            "Canny's thresholds are defined on 8-bit samples: convert to u8 first"
        }
        (_, Depth::U8) => "convert it with filter.grayscale first",
        _ => "convert it with filter.grayscale (to one channel) and to u8 first",
    };
    OpError::input(
        "image",
        format!("detect.canny needs a gray_u8 image, got {got}; {hint}"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::VecDeque;

    use ocellus_engine::params::{ParamMap, ParamValue, Params};
    use proptest::prelude::*;

    // ---------------------------------------------------------------------------------------
    // A slow, direct reference: full 2-D kernels, clamped reads, magnitudes looked up with a
    // bounds check, breadth-first hysteresis. Shares only the specification with `canny`.

    fn reference_gradients(
        img: &[u8],
        w: usize,
        h: usize,
        aperture: usize,
    ) -> (Vec<i64>, Vec<i64>) {
        let k = SobelKernels::new(aperture).unwrap();
        let r = k.radius() as isize;
        let at = |x: isize, y: isize| -> i64 {
            let x = x.clamp(0, w as isize - 1) as usize;
            let y = y.clamp(0, h as isize - 1) as usize;
            i64::from(img[y * w + x])
        };
        let mut gx = vec![0i64; w * h];
        let mut gy = vec![0i64; w * h];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let (mut sx, mut sy) = (0i64, 0i64);
                for i in -r..=r {
                    for j in -r..=r {
                        let (iy, jx) = ((i + r) as usize, (j + r) as usize);
                        let p = at(x + j, y + i);
                        sx += i64::from(k.smooth[iy] * k.deriv[jx]) * p;
                        sy += i64::from(k.deriv[iy] * k.smooth[jx]) * p;
                    }
                }
                if aperture == 7 {
                    sx = (sx as f64 / 16.0).round_ties_even() as i64;
                    sy = (sy as f64 / 16.0).round_ties_even() as i64;
                }
                gx[y as usize * w + x as usize] = sx;
                gy[y as usize * w + x as usize] = sy;
            }
        }
        (gx, gy)
    }

    fn reference_canny(
        img: &[u8],
        w: usize,
        h: usize,
        low: f64,
        high: f64,
        aperture: usize,
        l2: bool,
    ) -> Vec<u8> {
        if w == 0 || h == 0 {
            return Vec::new();
        }
        let (gx, gy) = reference_gradients(img, w, h, aperture);
        let mag: Vec<i64> = gx
            .iter()
            .zip(&gy)
            .map(|(&a, &b)| if l2 { a * a + b * b } else { a.abs() + b.abs() })
            .collect();
        let t = Thresholds::new(low, high, aperture, l2);
        let (lo, hi) = (i64::from(t.low), i64::from(t.high));
        let m_at = |x: isize, y: isize| -> i64 {
            if x < 0 || y < 0 || x >= w as isize || y >= h as isize {
                0
            } else {
                mag[y as usize * w + x as usize]
            }
        };
        let tan22 = 0.414_213_562_373_095_05_f64;
        let tg22 = (tan22 * 32768.0 + 0.5) as i64;
        let mut class = vec![0u8; w * h];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let i = y as usize * w + x as usize;
                let m = mag[i];
                if m <= lo {
                    continue;
                }
                let (a, b) = (gx[i], gy[i]);
                let s = a.abs() * tg22;
                let t = b.abs() * 32768;
                let ((x1, y1), (x2, y2), strict2) = if t < s {
                    ((x - 1, y), (x + 1, y), false)
                } else if t > s + a.abs() * 65536 {
                    ((x, y - 1), (x, y + 1), false)
                } else if (a < 0) != (b < 0) && a != 0 && b != 0 {
                    ((x + 1, y - 1), (x - 1, y + 1), true)
                } else {
                    ((x - 1, y - 1), (x + 1, y + 1), true)
                };
                let second = if strict2 {
                    m > m_at(x2, y2)
                } else {
                    m >= m_at(x2, y2)
                };
                if m > m_at(x1, y1) && second {
                    class[i] = if m > hi { 2 } else { 1 };
                }
            }
        }
        let mut queue: VecDeque<usize> = (0..w * h).filter(|&i| class[i] == 2).collect();
        while let Some(i) = queue.pop_front() {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (nx, ny) = (x + dx, y + dy);
                    if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                        continue;
                    }
                    let j = ny as usize * w + nx as usize;
                    if class[j] == 1 {
                        class[j] = 2;
                        queue.push_back(j);
                    }
                }
            }
        }
        class
            .iter()
            .map(|&c| if c == 2 { 255 } else { 0 })
            .collect()
    }

    // ---------------------------------------------------------------------------------------
    // Test images.

    /// Deterministic pseudo-random bytes (xorshift64*).
    fn noise(n: usize, seed: u64) -> Vec<u8> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s ^= s >> 12;
                s ^= s << 25;
                s ^= s >> 27;
                (s.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 56) as u8
            })
            .collect()
    }

    /// A disc of radius `r` centred in a `size × size` image, anti-aliased by 4×4 supersampling:
    /// symmetric under transposition and both flips.
    fn disc(size: usize, r: f64, inside: u8, outside: u8) -> Vec<u8> {
        let c = (size as f64 - 1.0) / 2.0;
        let mut img = vec![0u8; size * size];
        for y in 0..size {
            for x in 0..size {
                let mut hits = 0;
                for sy in 0..4 {
                    for sx in 0..4 {
                        let px = x as f64 + (sx as f64 + 0.5) / 4.0 - 0.5 - c;
                        let py = y as f64 + (sy as f64 + 0.5) / 4.0 - 0.5 - c;
                        if px * px + py * py <= r * r {
                            hits += 1;
                        }
                    }
                }
                let v = (f64::from(inside) * hits as f64 + f64::from(outside) * (16 - hits) as f64)
                    / 16.0;
                img[y * size + x] = v.round() as u8;
            }
        }
        img
    }

    fn transpose<T: Copy + Default>(img: &[T], w: usize, h: usize) -> Vec<T> {
        let mut out = vec![T::default(); w * h];
        for y in 0..h {
            for x in 0..w {
                out[x * h + y] = img[y * w + x];
            }
        }
        out
    }

    /// Rotates a `w × h` image by 90° clockwise (result is `h × w`).
    fn rotate_cw(img: &[u8], w: usize, h: usize) -> Vec<u8> {
        let mut out = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                // (x, y) → (h − 1 − y, x) in an image of width h.
                out[x * h + (h - 1 - y)] = img[y * w + x];
            }
        }
        out
    }

    fn edge_count(edges: &[u8]) -> usize {
        edges.iter().filter(|&&e| e == 255).count()
    }

    fn step_image(w: usize, h: usize, step_x: usize, dark: u8, bright: u8) -> Vec<u8> {
        (0..w * h)
            .map(|i| if i % w < step_x { dark } else { bright })
            .collect()
    }

    // ---------------------------------------------------------------------------------------
    // Kernels and gradients.

    #[test]
    fn kernels_are_opencvs() {
        let k3 = SobelKernels::new(3).unwrap();
        assert_eq!((k3.smooth(), k3.deriv()), (&[1, 2, 1][..], &[-1, 0, 1][..]));
        let k5 = SobelKernels::new(5).unwrap();
        assert_eq!(k5.smooth(), &[1, 4, 6, 4, 1]);
        assert_eq!(k5.deriv(), &[-1, -2, 0, 2, 1]);
        let k7 = SobelKernels::new(7).unwrap();
        assert_eq!(k7.smooth(), &[1, 6, 15, 20, 15, 6, 1]);
        assert_eq!(k7.deriv(), &[-1, -4, -5, 0, 5, 4, 1]);
        for bad in [0, 1, 2, 4, 6, 8, 9] {
            assert!(SobelKernels::new(bad).is_none(), "aperture {bad}");
        }
    }

    #[test]
    fn rounding_matches_cv_round() {
        for s in -100_000..100_000 {
            let expected = (f64::from(s) / 16.0).round_ties_even() as i32;
            assert_eq!(div16_round_even(s), expected, "s = {s}");
        }
    }

    #[test]
    fn sobel_matches_reference_on_noise() {
        for (w, h) in [(1, 1), (1, 7), (7, 1), (2, 3), (37, 29), (70, 140)] {
            let img = noise(w * h, (w * 31 + h) as u64);
            for aperture in [3, 5, 7] {
                let (dx, dy) = sobel_i16(&img, w, h, aperture);
                let (rx, ry) = reference_gradients(&img, w, h, aperture);
                let dx: Vec<i64> = dx.iter().map(|&v| i64::from(v)).collect();
                let dy: Vec<i64> = dy.iter().map(|&v| i64::from(v)).collect();
                assert_eq!(dx, rx, "dx {w}×{h} aperture {aperture}");
                assert_eq!(dy, ry, "dy {w}×{h} aperture {aperture}");
            }
        }
    }

    #[test]
    fn step_response_is_the_sum_of_positive_taps() {
        // A 0 → 255 step is the largest response a u8 image can give: 255 × (sum of the smooth
        // taps) × (sum of the positive derivative taps) = 1020, 12240, and 163200 / 16 = 10200.
        for (aperture, expected) in [
            (3usize, 4 * 255),
            (5, 16 * 3 * 255),
            (7, 64 * 10 * 255 / 16),
        ] {
            let w = 32;
            let img = step_image(w, w, w / 2, 0, 255);
            let (dx, dy) = sobel_i16(&img, w, w, aperture);
            let max = dx.iter().map(|&v| i32::from(v)).max().unwrap();
            assert_eq!(max, expected, "aperture {aperture}");
            assert!(dy.iter().all(|&v| v == 0));
        }
    }

    #[test]
    fn sector_bounds_mirror_each_other_for_aperture_3() {
        // Transposition swaps |dx| and |dy|, so the "horizontal" test on (a, b) must agree with
        // the "vertical" test on (b, a). The two integer bounds (13573 and 13573 + 2^16 over
        // 2^15) are not exact reciprocals, but no pair within the 3×3 range (≤ 1020) falls in
        // the gap. Wider apertures do reach it, e.g. (1393, 577).
        let tg22 = i64::from(TG22);
        let horizontal = |a: i64, b: i64| (b << CANNY_SHIFT) < a * tg22;
        let vertical = |a: i64, b: i64| (b << CANNY_SHIFT) > a * tg22 + (a << (CANNY_SHIFT + 1));
        for a in 0..=1020 {
            for b in 0..=1020 {
                assert_eq!(horizontal(a, b), vertical(b, a), "({a}, {b})");
            }
        }
        assert_ne!(horizontal(1393, 577), vertical(577, 1393));
    }

    // ---------------------------------------------------------------------------------------
    // Hand-checkable cases.

    #[test]
    fn vertical_step_gives_one_line_on_the_dark_side() {
        // Step 0 → 100 between columns 7 and 8: dx = 4·100 = 400 at both x = 7 and x = 8, dy = 0.
        // The tie goes to the left pixel (m > left, m >= right), so the line is column 7.
        let (w, h) = (16, 16);
        let img = step_image(w, h, 8, 0, 100);
        let edges = canny(&img, w, h, 100.0, 300.0, 3, false);
        for y in 0..h {
            for x in 0..w {
                let expected = if x == 7 { 255 } else { 0 };
                assert_eq!(edges[y * w + x], expected, "({x}, {y})");
            }
        }
        // Strict thresholds: m = 400 must exceed `high`.
        assert_eq!(edge_count(&canny(&img, w, h, 100.0, 399.0, 3, false)), h);
        assert_eq!(edge_count(&canny(&img, w, h, 100.0, 399.99, 3, false)), h);
        assert_eq!(edge_count(&canny(&img, w, h, 100.0, 400.0, 3, false)), 0);
        assert_eq!(edge_count(&canny(&img, w, h, 100.0, 1000.0, 3, false)), 0);
        // A falling step puts the line on the left (now bright) column too.
        let falling = step_image(w, h, 8, 100, 0);
        let edges = canny(&falling, w, h, 100.0, 300.0, 3, false);
        assert!((0..h).all(|y| edges[y * w + 7] == 255));
        assert_eq!(edge_count(&edges), h);
    }

    #[test]
    fn filled_square_gives_a_closed_contour() {
        // Square of 200 on 20 covering [8, 24)². Sides: the tie rule keeps the left/upper pixel
        // of each step pair, so the left and top sides run one pixel outside the square (x, y =
        // 7) and the right and bottom sides one pixel inside (x, y = 23). At the corners the
        // gradient is diagonal and weaker (|dx| + |dy| = 360 at (7, 7) against 1080 at (8, 8)),
        // and the contour cuts each corner except the bottom-right one. Identical to OpenCV
        // 5.0's `cv::Canny` output for this image.
        let (w, h) = (32, 32);
        let mut img = vec![20u8; w * h];
        for y in 8..24 {
            for x in 8..24 {
                img[y * w + x] = 200;
            }
        }
        let edges = canny(&img, w, h, 50.0, 150.0, 3, false);
        let on = |x: isize, y: isize| {
            x >= 0
                && y >= 0
                && x < w as isize
                && y < h as isize
                && edges[y as usize * w + x as usize] == 255
        };
        let expected = |x: isize, y: isize| match y {
            7 => (9..=22).contains(&x),
            8 => x == 8 || x == 23,
            9..=22 => x == 7 || x == 23,
            23 => (8..=23).contains(&x),
            _ => false,
        };
        for y in 0..h as isize {
            for x in 0..w as isize {
                assert_eq!(on(x, y), expected(x, y), "({x}, {y})");
            }
        }
        assert_eq!(edge_count(&edges), 14 + 2 + 2 * 14 + 16);
        // No loose ends: every contour pixel has at least two 8-neighbours on the contour.
        for y in 0..h as isize {
            for x in 0..w as isize {
                if on(x, y) {
                    let n = (-1..=1)
                        .flat_map(|dy| (-1..=1).map(move |dx| (dx, dy)))
                        .filter(|&(dx, dy)| (dx, dy) != (0, 0) && on(x + dx, y + dy))
                        .count();
                    assert!(n >= 2, "({x}, {y}) has {n} neighbours");
                }
            }
        }
        // Closed: a 4-connected flood of non-edge pixels from the corner never reaches inside.
        let mut seen = vec![false; w * h];
        let mut stack = vec![(0isize, 0isize)];
        while let Some((x, y)) = stack.pop() {
            if x < 0 || y < 0 || x >= w as isize || y >= h as isize {
                continue;
            }
            let i = y as usize * w + x as usize;
            if seen[i] || edges[i] == 255 {
                continue;
            }
            seen[i] = true;
            stack.extend([(x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)]);
        }
        assert!(!seen[16 * w + 16]);
        assert!(seen[31 * w + 31]);
    }

    #[test]
    fn hysteresis_keeps_weak_pixels_connected_to_strong_ones() {
        // Left: a bar (x in 10..20) of height 100 above y = 20 and 30 below, so its left side
        // has magnitude 4·100 = 400 (strong) on top and 4·30 = 120 (weak) below, joined through
        // the bend. Right: an isolated patch of height 30 (magnitude 120 on its sides).
        let (w, h) = (40, 40);
        let img: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (10..20).contains(&x) {
                    if y < 20 { 100 } else { 30 }
                } else if x >= 30 && y >= 22 {
                    30
                } else {
                    0
                }
            })
            .collect();
        let column = |edges: &[u8], x: usize, ys: std::ops::Range<usize>| {
            ys.filter(|&y| edges[y * w + x] == 255).count()
        };
        let right_patch = |edges: &[u8]| {
            (0..w * h)
                .filter(|&i| i % w >= 25 && edges[i] == 255)
                .count()
        };
        let edges = canny(&img, w, h, 60.0, 200.0, 3, false);
        assert_eq!(column(&edges, 9, 0..19), 19, "strong part of the left side");
        assert_eq!(
            column(&edges, 9, 22..40),
            18,
            "weak part, connected through the bend"
        );
        assert_eq!(right_patch(&edges), 0, "weak and isolated: removed");
        // Raising `low` above 120 removes the weak part.
        let edges = canny(&img, w, h, 130.0, 200.0, 3, false);
        assert_eq!(column(&edges, 9, 0..19), 19);
        assert_eq!(column(&edges, 9, 22..40), 0);
        // Lowering `high` below 120 makes the isolated patch's outline strong.
        let edges = canny(&img, w, h, 60.0, 110.0, 3, false);
        assert_eq!(column(&edges, 29, 23..40), 17);
        assert!(right_patch(&edges) > 17);
    }

    #[test]
    fn l2_magnitude_is_smaller_on_a_diagonal_edge() {
        // Diagonal step: 100 where x > y. Away from the image border each row has two pixels
        // with dx = 300, dy = -300: L1 = 600, L2 = √(2·300²) ≈ 424.26. (At the top-left corner
        // the replicated border gives (400, -200): L2 ≈ 447, so rows 0..3 are left out, and
        // `low = high` keeps hysteresis from reaching them.)
        let n = 24;
        let img: Vec<u8> = (0..n * n)
            .map(|i| if i % n > i / n { 100 } else { 0 })
            .collect();
        let (dx, dy) = sobel_i16(&img, n, n, 3);
        let i = 12 * n + 12;
        assert_eq!((dx[i], dy[i]), (300, -300));
        let interior = |t: f64, l2: bool| {
            let edges = canny(&img, n, n, t, t, 3, l2);
            (3..n - 3)
                .flat_map(|y| (0..n).map(move |x| (x, y)))
                .filter(|&(x, y)| edges[y * n + x] == 255)
                .count()
        };
        let full = 2 * (n - 6);
        assert_eq!(interior(500.0, false), full, "L1 600 > 500");
        assert_eq!(interior(599.0, false), full);
        assert_eq!(interior(600.0, false), 0);
        assert_eq!(interior(500.0, true), 0, "L2 424.26 < 500");
        assert_eq!(interior(424.0, true), full, "L2 424.26 > 424");
        assert_eq!(interior(424.5, true), 0);
    }

    #[test]
    fn transposing_the_input_transposes_the_output() {
        // Exact for aperture 3: transposition swaps dx and dy, maps left/up and right/down onto
        // each other (so the tie rule is preserved), and no integer gradient pair with |dx| ≤
        // 1020 falls between the rounded 22.5° and 67.5° sector bounds (checked exhaustively in
        // `sector_bounds_mirror_each_other_for_aperture_3`).
        let size = 41;
        let img = disc(size, 12.3, 200, 40);
        let edges = canny(&img, size, size, 50.0, 150.0, 3, false);
        assert!(edge_count(&edges) > 40);
        assert_eq!(transpose(&img, size, size), img, "test image is symmetric");
        assert_eq!(transpose(&edges, size, size), edges);
        let (w, h) = (53, 31);
        let img = noise(w * h, 7);
        for l2 in [false, true] {
            let edges = canny(&img, w, h, 100.0, 400.0, 3, l2);
            let t = canny(&transpose(&img, w, h), h, w, 100.0, 400.0, 3, l2);
            assert_eq!(t, transpose(&edges, w, h), "l2 = {l2}");
        }
    }

    /// Candidates (`m > low`) in the vertical sector whose magnitude ties with the pixel above
    /// or below: the only places where a 90° rotation can change the result (see below).
    fn vertical_ties(img: &[u8], w: usize, h: usize, low: f64) -> usize {
        let (dx, dy) = sobel_i16(img, w, h, 3);
        let mag: Vec<i32> = dx
            .iter()
            .zip(&dy)
            .map(|(&a, &b)| i32::from(a).abs() + i32::from(b).abs())
            .collect();
        let mut ties = 0;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let (a, b) = (i64::from(dx[i]).abs(), i64::from(dy[i]).abs());
                let vertical = (b << CANNY_SHIFT) > a * i64::from(TG22) + (a << (CANNY_SHIFT + 1));
                let up = if y > 0 { mag[i - w] } else { 0 };
                let down = if y + 1 < h { mag[i + w] } else { 0 };
                if f64::from(mag[i]) > low && vertical && (mag[i] == up || mag[i] == down) {
                    ties += 1;
                }
            }
        }
        ties
    }

    #[test]
    fn rotating_the_input_rotates_the_output_unless_vertical_ties() {
        // A clockwise quarter turn preserves magnitudes (aperture 3), maps the sectors onto each
        // other exactly (see `sector_bounds_mirror_each_other_for_aperture_3`) and maps left →
        // up, right → down, so the horizontal tie rule (`>` left, `>=` right) becomes the
        // vertical one. But up → right and down → left: a tie between vertically adjacent
        // magnitudes is broken the other way after rotation. Without such ties the output
        // rotates exactly; with them it may differ (OpenCV behaves the same).
        let mut tie_free = 0;
        let mut with_ties_differing = 0;
        for (w, h) in [(33usize, 33usize), (40, 25)] {
            for seed in 0..12u64 {
                let img = noise(w * h, seed);
                let (low, high) = (300.0, 600.0);
                let edges = canny(&img, w, h, low, high, 3, false);
                let turned = canny(&rotate_cw(&img, w, h), h, w, low, high, 3, false);
                let same = turned == rotate_cw(&edges, w, h);
                if vertical_ties(&img, w, h, low) == 0 {
                    tie_free += 1;
                    assert!(same, "{w}×{h} seed {seed}: tie-free but not equivariant");
                } else if !same {
                    with_ties_differing += 1;
                }
            }
        }
        assert!(
            tie_free >= 3,
            "only {tie_free} tie-free images: the check is too weak"
        );
        assert!(
            with_ties_differing >= 1,
            "ties never mattered: the explanation is untested"
        );
    }

    #[test]
    fn low_above_high_is_swapped() {
        let img = disc(48, 15.0, 180, 30);
        let a = canny(&img, 48, 48, 60.0, 200.0, 3, false);
        let b = canny(&img, 48, 48, 200.0, 60.0, 3, false);
        assert_eq!(a, b);
        assert!(edge_count(&a) > 0);
    }

    #[test]
    fn wide_apertures_give_edges_at_scaled_thresholds() {
        let size = 64;
        let img = disc(size, 20.0, 160, 40);
        // Step height 120: magnitudes about 4·120, 48·120 and 640·120 for apertures 3, 5, 7
        // (aperture 7 divides gradients and thresholds by 16, which cancels).
        for (aperture, scale) in [(3usize, 4.0), (5, 48.0), (7, 640.0)] {
            let low = 0.25 * 120.0 * scale;
            let high = 0.6 * 120.0 * scale;
            let edges = canny(&img, size, size, low, high, aperture, false);
            let n = edge_count(&edges);
            assert!(
                (100..200).contains(&n),
                "aperture {aperture}: {n} edge pixels for a disc of perimeter ≈ 126"
            );
            // Far above the step's magnitude, nothing.
            let none = canny(&img, size, size, low, 2.0 * 120.0 * scale, aperture, false);
            assert_eq!(edge_count(&none), 0, "aperture {aperture}");
            assert_eq!(
                edges,
                reference_canny(&img, size, size, low, high, aperture, false)
            );
        }
    }

    #[test]
    fn output_is_independent_of_thread_count() {
        let (w, h) = (300, 3 * BAND_ROWS + 17);
        let mut img = noise(w * h, 3);
        // Smooth it a little so there are long connected edges crossing band boundaries.
        for _ in 0..2 {
            let copy = img.clone();
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    let s: u32 = (0..9)
                        .map(|k| u32::from(copy[(y + k / 3 - 1) * w + x + k % 3 - 1]))
                        .sum();
                    img[y * w + x] = (s / 9) as u8;
                }
            }
        }
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                [3, 5, 7]
                    .iter()
                    .flat_map(|&a| {
                        [false, true]
                            .map(|l2| canny(&img, w, h, 20.0 * a as f64, 60.0 * a as f64, a, l2))
                    })
                    .collect::<Vec<_>>()
            })
        };
        let one = run(1);
        let three = run(3);
        assert_eq!(one, three);
        assert!(one.iter().all(|e| edge_count(e) > 100));
    }

    #[test]
    fn empty_and_single_pixel() {
        assert!(canny(&[], 0, 0, 50.0, 150.0, 3, false).is_empty());
        assert!(canny(&[], 0, 5, 50.0, 150.0, 5, false).is_empty());
        assert!(canny(&[], 7, 0, 50.0, 150.0, 7, true).is_empty());
        for aperture in [3, 5, 7] {
            assert_eq!(canny(&[200], 1, 1, 0.0, 0.0, aperture, false), vec![0]);
        }
        let (dx, dy) = sobel_i16(&[], 0, 3, 3);
        assert!(dx.is_empty() && dy.is_empty());
    }

    #[test]
    fn matches_reference_on_varied_inputs() {
        let cases = [(1, 9), (9, 1), (2, 2), (5, 3), (64, 70), (129, 130)];
        for (k, &(w, h)) in cases.iter().enumerate() {
            let raw = noise(w * h, k as u64 + 11);
            // Quantise to few levels to create many ties.
            let img: Vec<u8> = raw.iter().map(|&v| (v / 64) * 60).collect();
            for aperture in [3usize, 5, 7] {
                let s = [4.0, 48.0, 640.0][aperture / 2 - 1];
                for l2 in [false, true] {
                    let (low, high) = (40.0 * s, 90.0 * s);
                    assert_eq!(
                        canny(&img, w, h, low, high, aperture, l2),
                        reference_canny(&img, w, h, low, high, aperture, l2),
                        "{w}×{h} aperture {aperture} l2 {l2}"
                    );
                }
            }
        }
    }

    // ---------------------------------------------------------------------------------------
    // The operator.

    fn run_op(params: ParamMap, image: Image) -> Result<Outputs, OpError> {
        let op = Canny::new(CannyParams::from_map(&params).map_err(OpError::failed)?)
            .map_err(OpError::failed)?;
        let specs = Canny::inputs();
        let values = [Some(Value::image(image))];
        let ctx = RunContext {
            node: "edges".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    #[test]
    fn operator_runs_on_gray_u8() {
        let (w, h) = (16, 16);
        let img = Image::from_u8(w, h, Channels::Gray, step_image(w, h, 8, 0, 100)).unwrap();
        let mut params = CannyParams::default().to_map();
        params.insert("low".into(), ParamValue::Float(100.0));
        params.insert("high".into(), ParamValue::Float(300.0));
        let mut out = run_op(params, img).unwrap();
        let Some(Value::Image(edges)) = out.take("edges") else {
            panic!("no edges output");
        };
        assert_eq!((edges.width(), edges.height()), (w, h));
        assert_eq!(edges.channels(), Channels::Gray);
        assert_eq!(edge_count(edges.as_u8().unwrap()), h);
    }

    #[test]
    fn operator_rejects_other_formats_clearly() {
        let rgb = Image::from_u8(4, 4, Channels::Rgb, vec![0; 48]).unwrap();
        let err = run_op(CannyParams::default().to_map(), rgb)
            .unwrap_err()
            .to_string();
        assert!(err.contains("image"), "{err}");
        assert!(err.contains("got rgb_u8"), "{err}");
        assert!(err.contains("filter.grayscale"), "{err}");
        let f32_gray = Image::from_f32(4, 4, Channels::Gray, vec![0.0; 16]).unwrap();
        let err = run_op(CannyParams::default().to_map(), f32_gray)
            .unwrap_err()
            .to_string();
        assert!(err.contains("got gray_f32"), "{err}");
        let u16_rgba = Image::from_u16(2, 2, Channels::Rgba, vec![0; 16]).unwrap();
        let err = run_op(CannyParams::default().to_map(), u16_rgba)
            .unwrap_err()
            .to_string();
        assert!(err.contains("got rgba_u16"), "{err}");
    }

    #[test]
    fn operator_checks_params() {
        for bad in [1u32, 2, 4, 6, 9] {
            let params = CannyParams {
                aperture: bad,
                ..CannyParams::default()
            };
            let err = Canny::new(params).unwrap_err();
            assert!(
                err.contains("aperture") && err.contains(&bad.to_string()),
                "{err}"
            );
        }
        let nan = CannyParams {
            low: f64::NAN,
            ..CannyParams::default()
        };
        assert!(Canny::new(nan).is_err());
        let swapped = CannyParams {
            low: 200.0,
            high: 10.0,
            ..CannyParams::default()
        };
        assert!(
            Canny::new(swapped).is_ok(),
            "swapped like OpenCV, not an error"
        );
        let schema = CannyParams::schema();
        assert_eq!(schema[0].min, Some(0.0));
        assert_eq!(schema[2].min, Some(3.0));
        assert_eq!(schema[2].max, Some(7.0));
    }

    #[test]
    fn operator_handles_empty_images() {
        let img = Image::from_u8(0, 3, Channels::Gray, vec![]).unwrap();
        let mut out = run_op(CannyParams::default().to_map(), img).unwrap();
        let Some(Value::Image(edges)) = out.take("edges") else {
            panic!("no edges output");
        };
        assert_eq!((edges.width(), edges.height()), (0, 3));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn output_is_binary_and_matches_reference(
            w in 1usize..40,
            h in 1usize..40,
            seed in any::<u64>(),
            levels in 1u8..8,
            low in 0.0f64..600.0,
            span in 0.0f64..600.0,
            aperture in prop::sample::select(vec![3usize, 5, 7]),
            l2 in any::<bool>(),
        ) {
            let step = 255 / levels;
            let img: Vec<u8> = noise(w * h, seed)
                .iter()
                .map(|&v| (v / step.max(1)) * step)
                .collect();
            let scale = [1.0, 12.0, 160.0][aperture / 2 - 1];
            let (low, high) = (low * scale, (low + span) * scale);
            let edges = canny(&img, w, h, low, high, aperture, l2);
            prop_assert_eq!(edges.len(), w * h);
            prop_assert!(edges.iter().all(|&e| e == 0 || e == 255));
            prop_assert_eq!(&edges, &reference_canny(&img, w, h, low, high, aperture, l2));
        }

        #[test]
        fn constant_images_have_no_edges(
            w in 1usize..50,
            h in 1usize..50,
            value in any::<u8>(),
            low in 0.0f64..100.0,
            high in 0.0f64..100.0,
            aperture in prop::sample::select(vec![3usize, 5, 7]),
            l2 in any::<bool>(),
        ) {
            let edges = canny(&vec![value; w * h], w, h, low, high, aperture, l2);
            prop_assert!(edges.iter().all(|&e| e == 0));
        }
    }
}
