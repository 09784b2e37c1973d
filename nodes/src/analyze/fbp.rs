//! `analyze.fbp`: filtered back-projection, the inverse of the parallel-beam Radon transform.
//!
//! [`ramp_filter`] builds the frequency response (the band-limited ramp of Ramachandran and
//! Lakshminarayanan, times an apodising window), [`filter_projections`] applies it with rustfft
//! and [`back_project`] smears the filtered projections over the image.
//!
//! Determinism: projections are filtered one per task (each with its own FFT buffers) and every
//! output pixel sums its angles sequentially in angle order, so the result is bit-identical for
//! any thread count.

use std::f64::consts::PI;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;
use rustfft::algorithm::Radix4;
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftDirection};

use super::radon::{Geometry, gray_samples};

/// Largest reconstructed image side, px.
pub const MAX_SIZE: u32 = 8192;

/// Shortest FFT length used for filtering.
const MIN_FFT_LEN: usize = 64;

param_enum! {
    /// Apodising windows multiplied onto the ramp filter |f| (f in cycles per bin, |f| ≤ ½).
    pub enum RampWindow {
        /// No window: the plain band-limited ramp (Ramachandran and Lakshminarayanan 1971).
        RamLak = "ram_lak",
        /// sinc(f) = sin(πf)/(πf) (Shepp and Logan 1974).
        SheppLogan = "shepp_logan",
        /// cos(πf).
        Cosine = "cosine",
        /// 0.54 + 0.46·cos(2πf).
        Hamming = "hamming",
        /// 0.5 + 0.5·cos(2πf).
        Hann = "hann",
    }
}

impl RampWindow {
    /// The window's gain at frequency `f`, cycles per bin (|f| ≤ ½).
    pub fn gain(self, f: f64) -> f64 {
        match self {
            RampWindow::RamLak => 1.0,
            RampWindow::SheppLogan => {
                if f == 0.0 {
                    1.0
                } else {
                    (PI * f).sin() / (PI * f)
                }
            }
            RampWindow::Cosine => (PI * f).cos(),
            RampWindow::Hamming => 0.54 + 0.46 * (2.0 * PI * f).cos(),
            RampWindow::Hann => 0.5 + 0.5 * (2.0 * PI * f).cos(),
        }
    }
}

/// FFT length used to filter projections of `bins` samples: the next power of two at least
/// 2·bins (so the circular convolution does not wrap), at least [`MIN_FFT_LEN`].
pub fn fft_len(bins: usize) -> usize {
    (2 * bins).max(MIN_FFT_LEN).next_power_of_two()
}

/// The frequency response (length `len`, FFT order) of the ramp filter times `window`. The ramp
/// is the transform of the band-limited spatial kernel h(0) = ¼, h(n) = −1/(πn)² for odd n, 0
/// for even n ≠ 0 (Kak and Slaney, "Principles of Computerized Tomographic Imaging", eq. 3.61),
/// which, unlike sampling |f| directly, has the right zero-frequency response for a finite
/// detector.
pub fn ramp_filter(len: usize, window: RampWindow) -> Vec<f64> {
    let mut kernel = vec![Complex64::new(0.0, 0.0); len];
    kernel[0].re = 0.25;
    for n in (1..len / 2).step_by(2) {
        let v = -1.0 / (PI * n as f64).powi(2);
        kernel[n].re = v;
        kernel[len - n].re = v;
    }
    Radix4::new(len, FftDirection::Forward).process(&mut kernel);
    kernel
        .iter()
        .enumerate()
        .map(|(k, h)| {
            let f = if k <= len / 2 {
                k as f64 / len as f64
            } else {
                (k as f64 - len as f64) / len as f64
            };
            h.re * window.gain(f)
        })
        .collect()
}

/// Every projection (row of `angles × bins`) convolved with the windowed ramp filter.
pub fn filter_projections(sinogram: &[f64], bins: usize, window: RampWindow) -> Vec<f64> {
    let len = fft_len(bins);
    let response = ramp_filter(len, window);
    // `len` is a power of two: rustfft's radix-4 algorithm directly, not its planner, which would
    // compile every algorithm and SIMD kernel of rustfft a second time, for f64 (about 7 % of
    // this crate's code; the f32 planner of `filter::frequency` stays).
    let forward = Radix4::new(len, FftDirection::Forward);
    let inverse = Radix4::new(len, FftDirection::Inverse);
    let scratch_len = forward
        .get_inplace_scratch_len()
        .max(inverse.get_inplace_scratch_len());
    let bins = bins.max(1);
    let zero = Complex64::new(0.0, 0.0);
    let mut out = vec![0.0; sinogram.len()];
    // Two projections per complex FFT, a in the real part and b in the imaginary: the response
    // is real and even, so filtering keeps the two apart (the filtered a stays real, b
    // imaginary). Fixed pairs (rows 2k, 2k + 1), so the result does not depend on the threads.
    out.par_chunks_mut(2 * bins)
        .zip(sinogram.par_chunks(2 * bins))
        .for_each_init(
            || (vec![zero; len], vec![zero; scratch_len]),
            |(buffer, scratch), (filtered, pair)| {
                buffer.fill(zero);
                let (a, b) = pair.split_at(bins.min(pair.len()));
                for (z, &p) in buffer.iter_mut().zip(a) {
                    z.re = p;
                }
                for (z, &p) in buffer.iter_mut().zip(b) {
                    z.im = p;
                }
                forward.process_with_scratch(buffer, scratch);
                for (z, &r) in buffer.iter_mut().zip(&response) {
                    *z *= r;
                }
                inverse.process_with_scratch(buffer, scratch);
                let (fa, fb) = filtered.split_at_mut(bins.min(filtered.len()));
                for (f, z) in fa.iter_mut().zip(buffer.iter()) {
                    *f = z.re / len as f64;
                }
                for (f, z) in fb.iter_mut().zip(buffer.iter()) {
                    *f = z.im / len as f64;
                }
            },
        );
    out
}

/// Back-projects filtered projections onto a `size × size` image (row-major, centred pixel
/// coordinates as in [`super::radon::radon`]): f(x, y) = (π/angles)·Σᵢ qᵢ(x·cos θᵢ + y·sin θᵢ),
/// with linear interpolation between bins and zero beyond the detector.
pub fn back_project(filtered: &[f64], geometry: &Geometry, size: usize) -> Vec<f64> {
    let trig: Vec<(f64, f64)> = (0..geometry.angles)
        .map(|i| geometry.theta_rad(i).sin_cos())
        .collect();
    let scale = PI / geometry.angles as f64;
    let centre = (size as f64 - 1.0) / 2.0;
    let bins = geometry.bins;
    let mut out = vec![0.0; size * size];
    out.par_chunks_mut(size.max(1))
        .enumerate()
        .for_each(|(row, line)| {
            let y = centre - row as f64;
            for (col, value) in line.iter_mut().enumerate() {
                let x = col as f64 - centre;
                let mut sum = 0.0;
                for (i, &(st, ct)) in trig.iter().enumerate() {
                    let u = geometry.bin_at(x * ct + y * st);
                    let j = u.floor();
                    let frac = u - j;
                    let projection = &filtered[i * bins..(i + 1) * bins];
                    let at = |k: f64| -> f64 {
                        if k < 0.0 || k >= bins as f64 {
                            0.0
                        } else {
                            projection[k as usize]
                        }
                    };
                    sum += (1.0 - frac) * at(j) + frac * at(j + 1.0);
                }
                *value = sum * scale;
            }
        });
    out
}

/// Filtered back-projection of an `angles × bins` sinogram onto a `size × size` image.
pub fn fbp(sinogram: &[f64], geometry: &Geometry, window: RampWindow, size: usize) -> Vec<f64> {
    let filtered = filter_projections(sinogram, geometry.bins, window);
    back_project(&filtered, geometry, size)
}

params! {
    /// Parameters of `analyze.fbp`.
    pub struct FbpParams {
        /// Angular range the sinogram's rows cover, degrees, in (0, 360] (as given to
        /// `analyze.radon`). Default 180.
        angle_range_deg: f64 = 180.0 => [above = 0.0, max = 360.0, unit = "deg"],
        /// Window on the ramp filter: "ram_lak" (none, sharpest), "shepp_logan", "cosine",
        /// "hamming" or "hann" (smoothest). Default "ram_lak".
        filter: RampWindow = RampWindow::RamLak,
        /// Side of the square reconstruction, px; 0 = ⌊bins/√2⌋, the largest square whose
        /// diagonal the detector covers. Default 0.
        size: u32 = 0 => [max = 8192, unit = "px"],
    }
}

/// Filtered back-projection (`analyze.fbp`). See [`fbp`].
#[derive(Debug, Clone, PartialEq)]
pub struct Fbp {
    range_deg: f64,
    window: RampWindow,
    size: Option<usize>,
}

impl Op for Fbp {
    type Params = FbpParams;
    const ID: &'static str = "analyze.fbp";
    const SUMMARY: &'static str =
        "Reconstructs an image from its sinogram by filtered back-projection.";
    const DOC: &'static str = r#"
Inverts the parallel-beam Radon transform of `analyze.radon` (same geometry: row i of the
sinogram is the projection at θᵢ = i·range/angles, column j the 1-px detector bin centred
j − (bins − 1)/2 px from the rotation centre).

Method (A. C. Kak and M. Slaney, "Principles of Computerized Tomographic Imaging", IEEE Press
1988, ch. 3): every projection is zero-padded to the next power of two ≥ 2·bins and filtered
in the frequency domain (rustfft radix-4, f64) by the band-limited ramp — the transform of the spatial
kernel h(0) = ¼, h(odd n) = −1/(πn)² of G. N. Ramachandran and A. V. Lakshminarayanan (PNAS
68, 1971) — times the window `filter`: "ram_lak" none, "shepp_logan" sinc(f) (L. A. Shepp and
B. F. Logan 1974), "cosine" cos(πf), "hamming" 0.54 + 0.46·cos(2πf), "hann"
0.5 + 0.5·cos(2πf) (f in cycles per bin). Then back-projection:
f(x, y) = (π/angles)·Σᵢ qᵢ(x·cos θᵢ + y·sin θᵢ), linear interpolation between bins.

Output: `image`, gray f32, `size` × `size` (default ⌊bins/√2⌋), in the units of the image
that was projected.

Speed–accuracy: cost ∝ angles × size²; more angles remove streaks (the angular sampling
needs about π/2·size angles for full resolution); smoother windows trade resolution for
noise and ringing.

Example:
    "recon": (op: "analyze.fbp", inputs: { "sinogram": "sino.sinogram" }, params: (filter: "hann")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "sinogram",
            PortType::Image,
            "Gray sinogram: one row per angle, one column per detector bin.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Reconstruction, gray f32.",
        )]
    }

    fn new(params: FbpParams) -> Result<Self, String> {
        let FbpParams {
            angle_range_deg,
            filter,
            size,
        } = params;
        if !(angle_range_deg.is_finite() && angle_range_deg > 0.0 && angle_range_deg <= 360.0) {
            return Err(format!(
                "`angle_range_deg` must be in (0, 360], got {angle_range_deg}"
            ));
        }
        if size > MAX_SIZE {
            return Err(format!("`size` must be at most {MAX_SIZE} px, got {size}"));
        }
        Ok(Fbp {
            range_deg: angle_range_deg,
            window: filter,
            size: (size > 0).then_some(size as usize),
        })
    }
}

impl Operator for Fbp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let sinogram = inputs.image("sinogram")?;
        let samples = gray_samples(sinogram, "sinogram")?;
        let geometry = Geometry {
            angles: sinogram.height(),
            range_deg: self.range_deg,
            bins: sinogram.width(),
        };
        let size = self
            .size
            .unwrap_or_else(|| ((geometry.bins as f64 / 2f64.sqrt()).floor() as usize).max(1));
        let image = fbp(&samples, &geometry, self.window, size);
        let image = Image::from_f32(
            size,
            size,
            Channels::Gray,
            image.iter().map(|&v| v as f32).collect(),
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyze::phantom::{MODIFIED_SHEPP_LOGAN, phantom};
    use crate::analyze::quality::psnr_db;
    use crate::analyze::radon::{covering_bins, radon};

    /// PSNR (peak 1) of the FBP of the n-px phantom's sinogram at `angles` angles.
    fn phantom_psnr(n: usize, angles: usize, window: RampWindow) -> f64 {
        let truth: Vec<f64> = phantom(&MODIFIED_SHEPP_LOGAN, n)
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        let g = Geometry {
            angles,
            range_deg: 180.0,
            bins: covering_bins(n, n),
        };
        let sino = radon(&truth, n, n, &g, 0.5);
        let recon = fbp(&sino, &g, window, n);
        let mse = truth
            .iter()
            .zip(&recon)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            / (n * n) as f64;
        psnr_db(mse, 1.0).unwrap_or(f64::INFINITY)
    }

    #[test]
    fn projections_filtered_in_pairs_equal_each_filtered_alone() {
        // Five projections (the last one unpaired) of pseudo-random values: every row of the
        // batch equals that row filtered on its own (then the FFT holds it alone, in the real
        // part), so the pairs do not leak into each other.
        let bins = 37;
        let sinogram: Vec<f64> = (0..5 * bins)
            .map(|i| ((i * 7919 % 1013) as f64 / 1013.0 - 0.3) * 4.0)
            .collect();
        for window in [RampWindow::RamLak, RampWindow::Hann] {
            let batch = filter_projections(&sinogram, bins, window);
            for (row, projection) in sinogram.chunks(bins).enumerate() {
                let alone = filter_projections(projection, bins, window);
                for (a, b) in batch[row * bins..(row + 1) * bins].iter().zip(&alone) {
                    assert!((a - b).abs() <= 1e-12, "row {row}: {a} against {b}");
                }
            }
            assert!(batch.iter().any(|v| v.abs() > 0.1));
        }
    }

    #[test]
    fn phantom_reconstruction_quality_and_angle_convergence() {
        let n = 64;
        let p8 = phantom_psnr(n, 8, RampWindow::RamLak);
        let p32 = phantom_psnr(n, 32, RampWindow::RamLak);
        let p100 = phantom_psnr(n, 100, RampWindow::RamLak);
        eprintln!("PSNR 8: {p8:.2}, 32: {p32:.2}, 100: {p100:.2}");
        assert!(p100 >= 20.0, "{p100}");
        assert!(p100 > p32 && p32 > p8, "{p8} {p32} {p100}");
        for w in [
            RampWindow::SheppLogan,
            RampWindow::Cosine,
            RampWindow::Hamming,
            RampWindow::Hann,
        ] {
            let p = phantom_psnr(n, 100, w);
            eprintln!("{w:?}: {p:.2}");
            assert!(p > 15.0, "{w:?}: {p}");
        }
    }

    #[test]
    fn constant_disc_recovers_its_value() {
        // A centred disc of value 1 (radius 12 px in 48 px): inside, away from the rim, the
        // reconstruction is 1 within a few percent.
        let n = 48;
        let c = (n as f64 - 1.0) / 2.0;
        let truth: Vec<f64> = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f64 - c, (i / n) as f64 - c);
                f64::from(u8::from(x * x + y * y <= 144.0))
            })
            .collect();
        let g = Geometry {
            angles: 90,
            range_deg: 180.0,
            bins: covering_bins(n, n),
        };
        let recon = fbp(&radon(&truth, n, n, &g, 0.5), &g, RampWindow::RamLak, n);
        for (i, &value) in recon.iter().enumerate() {
            let (x, y) = ((i % n) as f64 - c, (i / n) as f64 - c);
            let r2 = x * x + y * y;
            if r2 <= 64.0 {
                assert!((value - 1.0).abs() < 0.05, "inside {x},{y}: {value}");
            } else if r2 >= 20.0 * 20.0 {
                assert!(value.abs() < 0.05, "outside {x},{y}: {value}");
            }
        }
    }

    #[test]
    fn ramp_filter_shape() {
        let h = ramp_filter(128, RampWindow::RamLak);
        // Zero-frequency gain of the band-limited kernel: ¼ − 2·Σ_odd 1/(πn)² ≈ small, positive.
        assert!(h[0] >= 0.0 && h[0] < 0.01, "{}", h[0]);
        // Close to |f| at mid frequencies, 0.5 at Nyquist, symmetric.
        assert!((h[32] - 0.25).abs() < 0.01, "{}", h[32]);
        assert!((h[64] - 0.5).abs() < 0.01, "{}", h[64]);
        assert!((h[10] - h[118]).abs() < 1e-12);
        let hann = ramp_filter(128, RampWindow::Hann);
        assert!(hann[64].abs() < 1e-12);
        assert!(RampWindow::SheppLogan.gain(0.5) > 0.63 && RampWindow::SheppLogan.gain(0.5) < 0.64);
    }

    #[test]
    fn deterministic_for_any_thread_count() {
        let n = 32;
        let truth: Vec<f64> = phantom(&MODIFIED_SHEPP_LOGAN, n)
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        let g = Geometry {
            angles: 30,
            range_deg: 180.0,
            bins: covering_bins(n, n),
        };
        let run = || fbp(&radon(&truth, n, n, &g, 0.5), &g, RampWindow::Hamming, n);
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let three = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        assert_eq!(one.install(run), three.install(run));
    }

    #[test]
    fn rejects_bad_params() {
        assert!(
            Fbp::new(FbpParams {
                angle_range_deg: 0.0,
                ..FbpParams::default()
            })
            .is_err()
        );
        assert!(
            Fbp::new(FbpParams {
                size: 10_000,
                ..FbpParams::default()
            })
            .is_err()
        );
    }
}
