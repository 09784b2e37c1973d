//! `filter.fft` and `filter.ifft`: the 2-D discrete Fourier transform of an image and its
//! inverse, as pairs of f32 planes (`real`, `imaginary`).
//!
//! How it runs (any size; rustfft handles every length, with Bluestein/Rader for large primes):
//! - Real input, two rows at a time: rows `a` and `b` are packed as `a + i·b`, one complex FFT
//!   of length W gives both spectra (`A[k] = (Z[k] + conj Z[W−k])/2`,
//!   `B[k] = (Z[k] − conj Z[W−k])/2i`), and only the W/2 + 1 non-redundant columns are kept.
//! - The half spectrum is transposed in 32×32 tiles, so every column FFT runs over contiguous
//!   memory, and transposed back; the other half of the output follows from Hermitian symmetry
//!   `F[v][u] = conj F[(H−v) mod H][(W−u) mod W]`.
//! - All FFTs are in f32. Rows (and columns) are processed in parallel in fixed bands of rows;
//!   each row is transformed by the same plan and arithmetic whatever thread runs it, so the
//!   output is bit-identical for any thread count.
//!
//! `real_spectrum_half` and `real_from_spectrum_half` are the building blocks that
//! `filter.frequency_filter` reuses.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::Value;
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};

use super::{planes_image, to_planes};

/// Rows per parallel task (even, so pairs of rows never straddle two tasks).
const BAND_ROWS: usize = 16;

/// Side of the square tiles of the transposes, in complex samples (32×32×8 bytes = 8 KiB).
const TILE: usize = 32;

params! {
    /// Parameters of `filter.fft`.
    pub struct FftParams {
        /// true: swap quadrants (numpy's `fftshift`) so that frequency 0 lies at
        /// (⌊W/2⌋, ⌊H/2⌋) of every output; false: frequency 0 at (0, 0), as `cv2.dft`.
        centered: bool = false,
    }
}

/// Forward 2-D DFT (`filter.fft`). See [`fft2d`].
#[derive(Debug, Clone, PartialEq)]
pub struct FftOp {
    centered: bool,
}

impl Op for FftOp {
    type Params = FftParams;
    const ID: &'static str = "filter.fft";
    const SUMMARY: &'static str =
        "2-D discrete Fourier transform of an image, as real, imaginary and log-magnitude planes.";
    const DOC: &'static str = r#"
Computes the unnormalized forward 2-D DFT of every channel,
`F(u, v) = Σ_x Σ_y I(x, y) · exp(−2πi (u·x/W + v·y/H))`, the same as `cv2.dft` with
`DFT_COMPLEX_OUTPUT` (and numpy's `fft2`). Samples are taken as they are (u8 0–255, u16
0–65535, f32 unchanged). Outputs are f32 with the input's channels: `real` and `imaginary`, and
`magnitude` = ln(1 + |F|) for display. With `centered: true` all three are fftshift-ed (frequency
0 at (⌊W/2⌋, ⌊H/2⌋)); `filter.ifft` with the same `centered` undoes it.

Method: rustfft in f32, any size (mixed radix; Bluestein/Rader for primes). Pairs of rows go
through one complex FFT, only the W/2 + 1 non-redundant columns are transformed along y (after a
tiled transpose), and the rest comes from Hermitian symmetry. Relative error about 1e-6 of the
spectrum's largest value (f32). OpenCV's `dft` of a real CV_32F image computes the same values
(within f32 rounding); its default output is the packed CCS format, not the full planes.

Reference: J. W. Cooley, J. W. Tukey, "An algorithm for the machine calculation of complex
Fourier series", Math. Comp. 19 (1965); OpenCV `cv::dft`; numpy `fft.fft2`, `fft.fftshift`.

Example:
    "spectrum": (op: "filter.fft", inputs: { "image": "gray.image" }, params: (centered: true)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to transform, any pixel format (each channel on its own).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "real",
                PortType::Image,
                "Real part of the spectrum, f32, same size and channels as the input.",
            ),
            PortSpec::new(
                "imaginary",
                PortType::Image,
                "Imaginary part of the spectrum, f32, same size and channels as the input.",
            ),
            PortSpec::new(
                "magnitude",
                PortType::Image,
                "ln(1 + |F|), f32, same size and channels as the input.",
            ),
        ]
    }

    fn new(params: FftParams) -> Result<Self, String> {
        Ok(FftOp {
            centered: params.centered,
        })
    }
}

impl Operator for FftOp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (w, h, channels) = (image.width(), image.height(), image.channels());
        let mut re = Vec::new();
        let mut im = Vec::new();
        let mut mag = Vec::new();
        for plane in to_planes(image) {
            let (r, i) = fft2d(&plane, w, h, self.centered);
            mag.push(log_magnitude(&r, &i));
            re.push(r);
            im.push(i);
        }
        Ok(Outputs::new()
            .with("real", Value::image(planes_image(w, h, channels, re)?))
            .with("imaginary", Value::image(planes_image(w, h, channels, im)?))
            .with(
                "magnitude",
                Value::image(planes_image(w, h, channels, mag)?),
            ))
    }
}

params! {
    /// Parameters of `filter.ifft`.
    pub struct IfftParams {
        /// true: the inputs are centered (frequency 0 at (⌊W/2⌋, ⌊H/2⌋), as `filter.fft` with
        /// `centered: true` writes them); false: frequency 0 at (0, 0).
        centered: bool = false,
    }
}

/// Inverse 2-D DFT (`filter.ifft`). See [`ifft2d`].
#[derive(Debug, Clone, PartialEq)]
pub struct IfftOp {
    centered: bool,
}

impl Op for IfftOp {
    type Params = IfftParams;
    const ID: &'static str = "filter.ifft";
    const SUMMARY: &'static str =
        "Inverse 2-D discrete Fourier transform of a (real, imaginary) spectrum; real part out.";
    const DOC: &'static str = r#"
Computes `I(x, y) = 1/(W·H) · Σ_u Σ_v F(u, v) · exp(+2πi (u·x/W + v·y/H))` for every channel
and outputs its real part as f32, so `filter.ifft` of `filter.fft` (same `centered`) gives the
image back within f32 rounding (relative 1e-6 of the largest sample). The spectrum need not be
Hermitian; the imaginary part of the result is dropped. `real` and `imaginary` must have the
same size and channels; any depth is accepted (u8/u16 taken as they are).

Method: full complex rustfft in f32 (rows, tiled transpose, columns), scaled by 1/(W·H) at the
end: `cv2.idft(..., flags=DFT_SCALE | DFT_REAL_OUTPUT)` for Hermitian input, numpy's
`fft.ifft2(...).real` in general.

Reference: OpenCV `cv::idft`; numpy `fft.ifft2`, `fft.ifftshift`.

Example:
    "back": (op: "filter.ifft", inputs: { "real": "spectrum.real", "imaginary": "spectrum.imaginary" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "real",
                PortType::Image,
                "Real part of the spectrum, any pixel format.",
            ),
            PortSpec::new(
                "imaginary",
                PortType::Image,
                "Imaginary part, same size and channels as `real`.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Real part of the inverse transform, f32, same size and channels as the inputs.",
        )]
    }

    fn new(params: IfftParams) -> Result<Self, String> {
        Ok(IfftOp {
            centered: params.centered,
        })
    }
}

impl Operator for IfftOp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let real = inputs.image("real")?;
        let imaginary = inputs.image("imaginary")?;
        let (w, h, channels) = (real.width(), real.height(), real.channels());
        if (imaginary.width(), imaginary.height(), imaginary.channels()) != (w, h, channels) {
            return Err(OpError::input(
                "imaginary",
                format!(
                    "must match `real` ({w}×{h} {}), got {}×{} {}",
                    channels.name(),
                    imaginary.width(),
                    imaginary.height(),
                    imaginary.channels().name()
                ),
            ));
        }
        let planes = to_planes(real)
            .iter()
            .zip(&to_planes(imaginary))
            .map(|(re, im)| ifft2d(re, im, w, h, self.centered))
            .collect();
        Ok(Outputs::new().with("image", Value::image(planes_image(w, h, channels, planes)?)))
    }
}

/// ln(1 + √(re² + im²)) of every sample.
pub fn log_magnitude(re: &[f32], im: &[f32]) -> Vec<f32> {
    let mut out = ocellus_engine::buffer::zeroed::<f32>(re.len());
    out.par_chunks_mut(1 << 14)
        .zip(re.par_chunks(1 << 14).zip(im.par_chunks(1 << 14)))
        .for_each(|(o, (r, i))| {
            for ((o, &r), &i) in o.iter_mut().zip(r).zip(i) {
                *o = r.hypot(i).ln_1p();
            }
        });
    out
}

/// The unnormalized forward DFT of the real `width × height` plane `plane` (row-major), as
/// (real, imaginary) planes of the same size; with `centered`, fftshift-ed (frequency 0 at
/// (⌊W/2⌋, ⌊H/2⌋)).
///
/// # Panics
/// If `plane.len() != width · height`.
pub fn fft2d(plane: &[f32], width: usize, height: usize, centered: bool) -> (Vec<f32>, Vec<f32>) {
    assert_eq!(plane.len(), width * height, "plane size");
    let n = width * height;
    let mut re = vec![0.0f32; n];
    let mut im = vec![0.0f32; n];
    if n == 0 {
        return (re, im);
    }
    let mut planner = FftPlanner::<f32>::new();
    let half = width / 2 + 1;
    // Column spectra, one row per u in 0..=W/2 (row u holds F(u, 0..H)).
    let columns = real_spectrum_half(&mut planner, plane, width, height);
    // fftshift: output (ox, oy) holds frequency ((ox + sx) mod W, (oy + sy) mod H).
    let (sx, sy) = if centered {
        (width - width / 2, height - height / 2)
    } else {
        (0, 0)
    };
    // Transpose back while expanding by Hermitian symmetry, in bands of TILE output rows: for
    // each output column, TILE consecutive samples of one column spectrum (read forwards, or
    // backwards for the mirrored half) go down the band.
    re.par_chunks_mut(width * TILE)
        .zip(im.par_chunks_mut(width * TILE))
        .enumerate()
        .for_each(|(b, (re_band, im_band))| {
            let rows = re_band.len() / width;
            let mut ys = [0usize; TILE];
            let mut mirrored = [0usize; TILE];
            for (r, (y, m)) in ys
                .iter_mut()
                .zip(mirrored.iter_mut())
                .enumerate()
                .take(rows)
            {
                *y = (b * TILE + r + sy) % height;
                *m = (height - *y) % height;
            }
            // Each block of TILE output columns is gathered into a local tile first, so the
            // band is written row by row (no power-of-two strides on the output).
            let mut tile_re = [[0.0f32; TILE]; TILE];
            let mut tile_im = [[0.0f32; TILE]; TILE];
            let mut u = sx % width;
            for ox0 in (0..width).step_by(TILE) {
                let cols = (width - ox0).min(TILE);
                for c in 0..cols {
                    if u < half {
                        let src = &columns[u * height..(u + 1) * height];
                        for (r, &y) in ys[..rows].iter().enumerate() {
                            let f = src[y];
                            tile_re[r][c] = f.re;
                            tile_im[r][c] = f.im;
                        }
                    } else {
                        let src = &columns[(width - u) * height..(width - u + 1) * height];
                        for (r, &y) in mirrored[..rows].iter().enumerate() {
                            let f = src[y];
                            tile_re[r][c] = f.re;
                            tile_im[r][c] = -f.im;
                        }
                    }
                    u += 1;
                    if u == width {
                        u = 0;
                    }
                }
                for r in 0..rows {
                    let at = r * width + ox0;
                    re_band[at..at + cols].copy_from_slice(&tile_re[r][..cols]);
                    im_band[at..at + cols].copy_from_slice(&tile_im[r][..cols]);
                }
            }
        });
    (re, im)
}

/// The real part of the inverse DFT of (`re`, `im`), scaled by 1/(W·H); with `centered`, the
/// inputs are taken as fftshift-ed.
///
/// # Panics
/// If a plane's length is not `width · height`.
pub fn ifft2d(re: &[f32], im: &[f32], width: usize, height: usize, centered: bool) -> Vec<f32> {
    let n = width * height;
    assert!(re.len() == n && im.len() == n, "plane size");
    if n == 0 {
        return Vec::new();
    }
    let mut planner = FftPlanner::<f32>::new();
    // ifftshift: out[k] = in[(k + ⌊n/2⌋) mod n].
    let (sx, sy) = if centered {
        (width / 2, height / 2)
    } else {
        (0, 0)
    };
    let mut spectrum = vec![Complex32::default(); n];
    spectrum
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(y, row)| {
            let src = ((y + sy) % height) * width;
            let (re, im) = (&re[src..src + width], &im[src..src + width]);
            // Column x reads (x + sx) mod W: two contiguous runs.
            let shifted_re = re[sx..].iter().chain(&re[..sx]);
            let shifted_im = im[sx..].iter().chain(&im[..sx]);
            for ((z, &r), &i) in row.iter_mut().zip(shifted_re).zip(shifted_im) {
                *z = Complex32::new(r, i);
            }
        });
    fft_rows(&mut spectrum, width, &planner.plan_fft_inverse(width));
    let mut columns = transpose(&spectrum, height, width);
    drop(spectrum);
    fft_rows(&mut columns, height, &planner.plan_fft_inverse(height));
    let scale = 1.0 / n as f32;
    let mut out = ocellus_engine::buffer::zeroed::<f32>(n);
    // Transpose back, keeping the real part.
    out.par_chunks_mut(width * TILE)
        .enumerate()
        .for_each(|(b, band)| {
            let y0 = b * TILE;
            let rows = band.len() / width;
            let mut tile = [[0.0f32; TILE]; TILE];
            for x0 in (0..width).step_by(TILE) {
                let cols = (width - x0).min(TILE);
                for k in 0..cols {
                    let src = &columns[(x0 + k) * height + y0..(x0 + k) * height + y0 + rows];
                    for (r, z) in src.iter().enumerate() {
                        tile[r][k] = z.re * scale;
                    }
                }
                for (r, t) in tile.iter().enumerate().take(rows) {
                    band[r * width + x0..r * width + x0 + cols].copy_from_slice(&t[..cols]);
                }
            }
        });
    out
}

/// The forward DFT of a real `width × height` plane, non-redundant half only, transposed:
/// `W/2 + 1` rows of `height` samples, row u holding `F(u, 0..H)`.
pub(crate) fn real_spectrum_half(
    planner: &mut FftPlanner<f32>,
    plane: &[f32],
    width: usize,
    height: usize,
) -> Vec<Complex32> {
    let half = width / 2 + 1;
    let row_fft = planner.plan_fft_forward(width);
    let scratch_len = row_fft.get_inplace_scratch_len();
    let mut rows = vec![Complex32::default(); height * half];
    rows.par_chunks_mut(half * BAND_ROWS)
        .enumerate()
        .for_each_init(
            || {
                (
                    vec![Complex32::default(); width],
                    vec![Complex32::default(); scratch_len],
                )
            },
            |(z, scratch), (b, band)| {
                let y0 = b * BAND_ROWS;
                for (p, pair) in band.chunks_mut(2 * half).enumerate() {
                    let ya = y0 + 2 * p;
                    let a = &plane[ya * width..(ya + 1) * width];
                    if pair.len() == 2 * half {
                        let b = &plane[(ya + 1) * width..(ya + 2) * width];
                        for ((z, &a), &b) in z.iter_mut().zip(a).zip(b) {
                            *z = Complex32::new(a, b);
                        }
                    } else {
                        for (z, &a) in z.iter_mut().zip(a) {
                            *z = Complex32::new(a, 0.0);
                        }
                    }
                    row_fft.process_with_scratch(z, scratch);
                    let (spec_a, spec_b) = pair.split_at_mut(half);
                    // conj Z[(W − k) mod W]: Z[0] for k = 0, then Z[W − 1], Z[W − 2], …
                    let mirrored = std::iter::once(z[0]).chain(z[1..].iter().rev().copied());
                    if spec_b.is_empty() {
                        for ((sa, &zk), zn) in spec_a.iter_mut().zip(z.iter()).zip(mirrored) {
                            *sa = (zk + zn.conj()) * 0.5;
                        }
                    } else {
                        let pairs = spec_a.iter_mut().zip(spec_b.iter_mut());
                        for (((sa, sb), &zk), zn) in pairs.zip(z.iter()).zip(mirrored) {
                            let zn = zn.conj();
                            *sa = (zk + zn) * 0.5;
                            // (zk − zn) / 2i
                            let d = zk - zn;
                            *sb = Complex32::new(d.im * 0.5, -d.re * 0.5);
                        }
                    }
                }
            },
        );
    let mut columns = transpose(&rows, height, half);
    drop(rows);
    fft_rows(&mut columns, height, &planner.plan_fft_forward(height));
    columns
}

/// The inverse of [`real_spectrum_half`] without the 1/(W·H) scale: the real plane whose
/// half spectrum (transposed, `W/2 + 1` rows of `height`) is `columns`, which is consumed. The
/// spectrum is taken as Hermitian: the imaginary parts of columns 0 and W/2 (W even) of the
/// row spectra are ignored.
pub(crate) fn real_from_spectrum_half(
    planner: &mut FftPlanner<f32>,
    mut columns: Vec<Complex32>,
    width: usize,
    height: usize,
) -> Vec<f32> {
    let half = width / 2 + 1;
    fft_rows(&mut columns, height, &planner.plan_fft_inverse(height));
    let rows = transpose(&columns, half, height);
    drop(columns);
    let row_fft = planner.plan_fft_inverse(width);
    let scratch_len = row_fft.get_inplace_scratch_len();
    let mut out = ocellus_engine::buffer::zeroed::<f32>(width * height);
    out.par_chunks_mut(width * BAND_ROWS)
        .enumerate()
        .for_each_init(
            || {
                (
                    vec![Complex32::default(); width],
                    vec![Complex32::default(); scratch_len],
                )
            },
            |(z, scratch), (b, band)| {
                let y0 = b * BAND_ROWS;
                for (p, pair) in band.chunks_mut(2 * width).enumerate() {
                    let ya = y0 + 2 * p;
                    let a = &rows[ya * half..(ya + 1) * half];
                    let b = rows.get((ya + 1) * half..(ya + 2) * half);
                    let zero = Complex32::default();
                    let bk = |k: usize| b.map_or(zero, |b| b[k]);
                    // Z = A + iB over the full length, A and B Hermitian.
                    for k in 0..half.min(width) {
                        let (ak, bk) = (a[k], bk(k));
                        z[k] = Complex32::new(ak.re - bk.im, ak.im + bk.re);
                    }
                    for k in half..width {
                        let (am, bm) = (a[width - k], bk(width - k));
                        z[k] = Complex32::new(am.re + bm.im, bm.re - am.im);
                    }
                    // Real DC (and Nyquist) terms: drop their imaginary parts.
                    z[0] = Complex32::new(a[0].re, bk(0).re);
                    if width.is_multiple_of(2) && width > 1 {
                        z[width / 2] = Complex32::new(a[width / 2].re, bk(width / 2).re);
                    }
                    row_fft.process_with_scratch(z, scratch);
                    let (out_a, out_b) = pair.split_at_mut(width.min(pair.len()));
                    for (o, v) in out_a.iter_mut().zip(z.iter()) {
                        *o = v.re;
                    }
                    for (o, v) in out_b.iter_mut().zip(z.iter()) {
                        *o = v.im;
                    }
                }
            },
        );
    out
}

/// In-place FFT of every row (`len` samples) of `buf`, in parallel bands of [`BAND_ROWS`] rows.
pub(crate) fn fft_rows(buf: &mut [Complex32], len: usize, fft: &Arc<dyn Fft<f32>>) {
    if len == 0 || buf.is_empty() {
        return;
    }
    let scratch_len = fft.get_inplace_scratch_len();
    buf.par_chunks_mut(len * BAND_ROWS).for_each_init(
        || vec![Complex32::default(); scratch_len],
        |scratch, band| fft.process_with_scratch(band, scratch),
    );
}

/// The transpose (`cols × rows`) of the row-major `rows × cols` matrix `src`, by 32×32 tiles,
/// in parallel over bands of 32 output rows.
pub(crate) fn transpose<T: Copy + Default + Send + Sync>(
    src: &[T],
    rows: usize,
    cols: usize,
) -> Vec<T> {
    let mut dst = ocellus_engine::buffer::zeroed::<T>(rows * cols);
    if rows == 0 || cols == 0 {
        return dst;
    }
    dst.par_chunks_mut(rows * TILE)
        .enumerate()
        .for_each(|(b, band)| {
            let c0 = b * TILE;
            let band_cols = band.len() / rows;
            // Through a local tile: rows of `src` are read and rows of `dst` written
            // contiguously (no power-of-two strides).
            let mut tile = [[T::default(); TILE]; TILE];
            for r0 in (0..rows).step_by(TILE) {
                let tile_rows = (rows - r0).min(TILE);
                for (k, t) in tile.iter_mut().enumerate().take(tile_rows) {
                    let start = (r0 + k) * cols + c0;
                    t[..band_cols].copy_from_slice(&src[start..start + band_cols]);
                }
                for c in 0..band_cols {
                    let out = &mut band[c * rows + r0..c * rows + r0 + tile_rows];
                    for (o, t) in out.iter_mut().zip(&tile) {
                        *o = t[c];
                    }
                }
            }
        });
    dst
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use ocellus_engine::value::{Channels, Image};
    use proptest::prelude::*;

    /// Direct O(N²) DFT in f64: (re, im).
    fn naive_dft(plane: &[f32], w: usize, h: usize) -> (Vec<f64>, Vec<f64>) {
        let mut re = vec![0.0; w * h];
        let mut im = vec![0.0; w * h];
        for v in 0..h {
            for u in 0..w {
                let (mut sr, mut si) = (0.0, 0.0);
                for y in 0..h {
                    for x in 0..w {
                        let phase = -2.0
                            * std::f64::consts::PI
                            * ((u * x) as f64 / w as f64 + (v * y) as f64 / h as f64);
                        let p = f64::from(plane[y * w + x]);
                        sr += p * phase.cos();
                        si += p * phase.sin();
                    }
                }
                re[v * w + u] = sr;
                im[v * w + u] = si;
            }
        }
        (re, im)
    }

    fn random_plane(w: usize, h: usize, seed: u64) -> Vec<f32> {
        randoms(seed, w * h)
            .iter()
            .map(|&r| (r * 255.0) as f32)
            .collect()
    }

    fn max_abs(v: &[f32]) -> f32 {
        v.iter().fold(0.0, |m, &x| m.max(x.abs()))
    }

    #[test]
    fn hand_computed_small_cases() {
        // 2×2 [[1, 2], [3, 4]]: F = [[10, −2], [−4, 0]].
        let (re, im) = fft2d(&[1.0, 2.0, 3.0, 4.0], 2, 2, false);
        assert_eq!(re, [10.0, -2.0, -4.0, 0.0]);
        assert_eq!(im, [0.0; 4]);
        // 4×1 [1, 2, 3, 4]: F = [10, −2+2i, −2, −2−2i].
        let (re, im) = fft2d(&[1.0, 2.0, 3.0, 4.0], 4, 1, false);
        assert_eq!(re, [10.0, -2.0, -2.0, -2.0]);
        assert_eq!(im, [0.0, 2.0, 0.0, -2.0]);
        // 1×4 (a column) gives the same values down the column.
        let (re, im) = fft2d(&[1.0, 2.0, 3.0, 4.0], 1, 4, false);
        assert_eq!(re, [10.0, -2.0, -2.0, -2.0]);
        assert_eq!(im, [0.0, 2.0, 0.0, -2.0]);
        // Inverse of the 4×1 spectrum.
        let back = ifft2d(
            &[10.0, -2.0, -2.0, -2.0],
            &[0.0, 2.0, 0.0, -2.0],
            4,
            1,
            false,
        );
        assert_eq!(back, [1.0, 2.0, 3.0, 4.0]);
    }

    #[test]
    fn impulse_and_constant() {
        let (w, h) = (7, 6);
        let mut impulse = vec![0.0f32; w * h];
        impulse[0] = 3.0;
        let (re, im) = fft2d(&impulse, w, h, false);
        assert!(re.iter().all(|&v| (v - 3.0).abs() < 1e-6));
        assert!(im.iter().all(|&v| v.abs() < 1e-6));
        let constant = vec![2.0f32; w * h];
        let (re, im) = fft2d(&constant, w, h, false);
        assert!((re[0] - 84.0).abs() < 1e-4);
        assert!(re[1..].iter().all(|&v| v.abs() < 1e-4));
        assert!(im.iter().all(|&v| v.abs() < 1e-4));
        // Centered: DC at (⌊W/2⌋, ⌊H/2⌋) = (3, 3).
        let (re, _) = fft2d(&constant, w, h, true);
        assert!((re[3 * w + 3] - 84.0).abs() < 1e-4);
    }

    #[test]
    fn matches_the_naive_dft_for_odd_even_and_prime_sizes() {
        for (k, &(w, h)) in [
            (1, 1),
            (1, 5),
            (5, 1),
            (2, 3),
            (8, 8),
            (13, 7),
            (16, 11),
            (17, 4),
        ]
        .iter()
        .enumerate()
        {
            let plane = random_plane(w, h, k as u64);
            let (re, im) = fft2d(&plane, w, h, false);
            let (er, ei) = naive_dft(&plane, w, h);
            let scale = 255.0 * (w * h) as f64;
            for i in 0..w * h {
                assert!(
                    (f64::from(re[i]) - er[i]).abs() < 1e-6 * scale
                        && (f64::from(im[i]) - ei[i]).abs() < 1e-6 * scale,
                    "{w}×{h} at {i}: ({}, {}) vs ({}, {})",
                    re[i],
                    im[i],
                    er[i],
                    ei[i]
                );
            }
        }
    }

    #[test]
    fn centered_is_fftshift() {
        let (w, h) = (5, 4);
        let plane = random_plane(w, h, 3);
        let (re, im) = fft2d(&plane, w, h, false);
        let (cre, cim) = fft2d(&plane, w, h, true);
        for oy in 0..h {
            for ox in 0..w {
                // numpy: out[k] = in[(k − ⌊n/2⌋) mod n].
                let y = (oy + h - h / 2) % h;
                let x = (ox + w - w / 2) % w;
                assert_eq!(cre[oy * w + ox], re[y * w + x]);
                assert_eq!(cim[oy * w + ox], im[y * w + x]);
            }
        }
        let back = ifft2d(&cre, &cim, w, h, true);
        for (a, b) in back.iter().zip(&plane) {
            assert!((a - b).abs() < 1e-3);
        }
    }

    #[test]
    fn agrees_with_opencv() {
        // cv2.dft(img.astype(np.float32), flags=cv2.DFT_COMPLEX_OUTPUT) (OpenCV 5.0) on
        // img[y, x] = (x·37 + y·91 + x·y·13) mod 256, 6×4.
        let (w, h) = (6, 4);
        let plane: Vec<f32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91 + x * y * 13) % 256) as f32))
            .collect();
        let (re, im) = fft2d(&plane, w, h, false);
        for i in 0..w * h {
            assert!(
                (re[i] - OPENCV_RE[i]).abs() < 2e-3 && (im[i] - OPENCV_IM[i]).abs() < 2e-3,
                "at {i}: ({}, {}) vs OpenCV ({}, {})",
                re[i],
                im[i],
                OPENCV_RE[i],
                OPENCV_IM[i]
            );
        }
    }

    #[rustfmt::skip]
    const OPENCV_RE: [f32; 24] = [
        3082.0, -294.0, -38.0, -678.0, -38.0, -294.0,
        -458.0, -441.1, -95.033, 78.0, -4.967, -170.9,
        54.0, 462.0, -306.0, 78.0, -306.0, 462.0,
        -458.0, -170.9, -4.967, 78.0, -95.033, -441.1,
    ];
    #[rustfmt::skip]
    const OPENCV_IM: [f32; 24] = [
        0.0, 65.818, 169.741, 0.0, -169.741, -65.818,
        -54.0, 8.603, 98.669, -78.0, -254.669, -164.603,
        0.0, 530.008, -266.736, 0.0, 266.736, -530.008,
        54.0, 164.603, 254.669, 78.0, -98.669, -8.603,
    ];

    #[test]
    fn operators_run_and_check_inputs() {
        let img = Image::from_u8(4, 3, Channels::Rgb, (0..36).map(|v| v * 7).collect()).unwrap();
        let ctx = RunContext {
            node: "f".into(),
            threads: 1,
            element: None,
        };
        let op = FftOp::new(FftParams { centered: true }).unwrap();
        let specs = FftOp::inputs();
        let mut out = op
            .run(
                &ctx,
                &Inputs::new(&specs, &[Some(Value::image(img.clone()))]),
            )
            .unwrap();
        let take = |out: &mut Outputs, name: &str| match out.take(name) {
            Some(Value::Image(i)) => i,
            _ => panic!("expected an image on {name}"),
        };
        let re = take(&mut out, "real");
        let im = take(&mut out, "imaginary");
        let mag = take(&mut out, "magnitude");
        assert_eq!(
            (re.width(), re.height(), re.channels()),
            (4, 3, Channels::Rgb)
        );
        // Magnitude at the centered DC of channel 0: samples 0, 21, 42, … of channel 0.
        let dc: f32 = img
            .as_u8()
            .unwrap()
            .iter()
            .step_by(3)
            .map(|&v| f32::from(v))
            .sum();
        let centre = (4 + 2) * 3;
        assert!((mag.as_f32().unwrap()[centre] - dc.ln_1p()).abs() < 1e-5);
        let inv = IfftOp::new(IfftParams { centered: true }).unwrap();
        let specs = IfftOp::inputs();
        let values = [Some(Value::Image(re.clone())), Some(Value::Image(im))];
        let mut out = inv.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let back = take(&mut out, "image");
        for (a, &b) in back.as_f32().unwrap().iter().zip(img.as_u8().unwrap()) {
            assert!((a - f32::from(b)).abs() < 1e-3);
        }
        let gray = Image::from_f32(4, 3, Channels::Gray, vec![0.0; 12]).unwrap();
        let values = [Some(Value::Image(re)), Some(Value::image(gray))];
        let err = inv.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("must match"), "{err}");
        // Empty images pass through.
        let empty = Image::from_u8(0, 5, Channels::Gray, vec![]).unwrap();
        let specs = FftOp::inputs();
        let mut out = op
            .run(&ctx, &Inputs::new(&specs, &[Some(Value::image(empty))]))
            .unwrap();
        assert_eq!(take(&mut out, "real").height(), 5);
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let (w, h) = (333, 129);
        let plane = random_plane(w, h, 8);
        let run = || {
            let (re, im) = fft2d(&plane, w, h, true);
            let back = ifft2d(&re, &im, w, h, true);
            (re, im, back)
        };
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn round_trip_parseval_and_linearity(
            w in 1usize..40,
            h in 1usize..40,
            centered in any::<bool>(),
            seed in any::<u64>(),
        ) {
            let a = random_plane(w, h, seed);
            let b = random_plane(w, h, seed ^ 1);
            let (re, im) = fft2d(&a, w, h, centered);
            // Round trip.
            let back = ifft2d(&re, &im, w, h, centered);
            let top = max_abs(&a).max(1.0);
            for (x, y) in back.iter().zip(&a) {
                prop_assert!((x - y).abs() <= 1e-4 * top, "{x} vs {y}");
            }
            // Parseval: Σ|I|² = Σ|F|² / (W·H).
            let spatial: f64 = a.iter().map(|&v| f64::from(v).powi(2)).sum();
            let spectral: f64 = re.iter().zip(&im)
                .map(|(&r, &i)| f64::from(r).powi(2) + f64::from(i).powi(2))
                .sum::<f64>() / (w * h) as f64;
            prop_assert!((spatial - spectral).abs() <= 1e-5 * spatial.max(1.0));
            // Linearity: F(2a + b) = 2F(a) + F(b).
            let mixed: Vec<f32> = a.iter().zip(&b).map(|(&x, &y)| 2.0 * x + y).collect();
            let (mr, mi) = fft2d(&mixed, w, h, centered);
            let (br, bi) = fft2d(&b, w, h, centered);
            let tol = 2e-5 * 3.0 * 255.0 * (w * h) as f32;
            for i in 0..w * h {
                prop_assert!((mr[i] - (2.0 * re[i] + br[i])).abs() <= tol);
                prop_assert!((mi[i] - (2.0 * im[i] + bi[i])).abs() <= tol);
            }
        }

        #[test]
        fn real_half_spectrum_round_trips(w in 1usize..30, h in 1usize..30, seed in any::<u64>()) {
            let a = random_plane(w, h, seed);
            let mut planner = FftPlanner::new();
            let half = real_spectrum_half(&mut planner, &a, w, h);
            let back = real_from_spectrum_half(&mut planner, half, w, h);
            let n = (w * h) as f32;
            for (x, y) in back.iter().zip(&a) {
                prop_assert!((x / n - y).abs() <= 1e-4 * 255.0, "{x} vs {y}");
            }
        }
    }
}
