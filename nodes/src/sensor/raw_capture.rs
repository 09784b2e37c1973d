//! `sensor.raw_capture`: a camera model turning a linear radiance image into a Bayer raw
//! capture — exposure, aperture, vignetting, quantum efficiency, full-well saturation, Poisson
//! shot noise, Gaussian read noise, ISO gain, black level and quantization.
//!
//! The algorithm is [`capture_raw`]; [`RawCapture`] is the thin operator around it.
//!
//! # Determinism
//!
//! The random numbers of pixel `i = y·width + x` are counter-based hashes of `(seed, i)` (the
//! helpers of [`crate::filter::noise`]), rows are processed in parallel and the per-row sums
//! are added in row order, so the raw image and the metrics are bit-identical for any thread
//! count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, PixelData, Value};
use rayon::prelude::*;

use super::{BayerPattern, SensorResponse, Vignetting, gain_for_iso};
use crate::filter::noise::{SplitMix, gaussian_pairs, hash, mix, poisson};

/// Salt of the shot-noise stream.
const SALT_SHOT: u64 = 0x7368_6F74_6E6F_6973;
/// Salt of the read-noise stream.
const SALT_READ: u64 = 0x7265_6164_6E6F_6973;

params! {
    /// Parameters of `sensor.raw_capture`.
    pub struct RawCaptureParams {
        /// Exposure (integration) time.
        exposure_s: f64 = 0.01 => [above = 0.0, unit = "s"],
        /// Aperture f-number N; the irradiance on the sensor is ∝ 1/N².
        f_number: f64 = 2.8 => [above = 0.0],
        /// ISO setting; the conversion gain is `gain_at_iso100` · iso / 100.
        iso: f64 = 100.0 => [above = 0.0],
        /// Conversion gain at ISO 100, DN per electron.
        gain_at_iso100: f64 = 0.25 => [above = 0.0, unit = "DN/e-"],
        /// Photons reaching a pixel per second per unit of input radiance at f/1 (optics
        /// throughput × pixel area; converts the renderer's relative units to photons).
        photons_per_unit: f64 = 1.0e7 => [above = 0.0, unit = "photons/s"],
        /// Fraction of photons converted to electrons, (0, 1].
        quantum_efficiency: f64 = 0.6 => [above = 0.0, max = 1.0],
        /// Full-well capacity: electrons a pixel holds before saturating.
        full_well_e: f64 = 10000.0 => [above = 0.0, unit = "e-"],
        /// Standard deviation of the Gaussian read noise, electrons (0 turns it off).
        read_noise_e: f64 = 3.0 => [min = 0.0, unit = "e-"],
        /// Whether photon arrival is Poisson (shot noise); false gives the mean electron count.
        shot_noise: bool = true,
        /// Black level (offset added to every pixel), DN.
        black_level_dn: f64 = 64.0 => [min = 0.0, unit = "DN"],
        /// Bits of the analogue-to-digital converter: samples are clipped to 0..2^bits − 1.
        bit_depth: u32 = 12 => [min = 1, max = 16, unit = "bits"],
        /// Light fall-off: "none", "cos4" (cos⁴ law) or "radial" (1 − s·ρ²).
        vignetting: Vignetting = Vignetting::Cos4,
        /// Vignetting strength s: tan of the half-diagonal field angle for "cos4" (≥ 0), the
        /// corner fall-off for "radial" ([0, 1)).
        vignetting_strength: f64 = 0.5 => [min = 0.0],
        /// Bayer layout: "rggb", "bggr", "grbg" or "gbrg".
        pattern: BayerPattern = BayerPattern::Rggb,
        /// Seed of the shot and read noise.
        seed: u64 = 0,
    }
}

/// The full capture model: the response plus saturation, noise and the converter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CaptureModel {
    /// Radiance → electrons → DN.
    pub response: SensorResponse,
    /// Full-well capacity, e⁻.
    pub full_well_e: f64,
    /// Read-noise standard deviation, e⁻.
    pub read_noise_e: f64,
    /// Poisson shot noise on or off.
    pub shot_noise: bool,
    /// Black level, DN.
    pub black_level_dn: f64,
    /// ADC bits (1..=16).
    pub bit_depth: u32,
    /// Colour-filter layout.
    pub pattern: BayerPattern,
}

impl CaptureModel {
    /// The largest digital number, 2^bits − 1.
    pub fn max_dn(&self) -> f64 {
        f64::from((1u32 << self.bit_depth) - 1)
    }
}

/// Statistics of one capture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CaptureStats {
    /// Fraction of pixels at full well or at the largest DN.
    pub saturated_fraction: f64,
    /// Mean collected electrons per pixel (after shot noise and the full-well clip).
    pub mean_signal_e: f64,
    /// Model SNR at the mean signal: S / √(S + σ_read² + 1/(12·g²)), dB (20·log10); the last
    /// term is the quantization noise in electrons.
    pub snr_db: f64,
}

/// Captures `radiance` (f32, gray or RGB/RGBA — alpha ignored; finite and ≥ 0, checked by the
/// caller) through `model`: a `width` × `height` u16 Bayer mosaic and its statistics.
///
/// Pixel (x, y) of colour c = pattern(x, y) collects μ = L_c · K · t / N² · QE · V(x, y)
/// electrons on average; e = min(Poisson(μ), full_well) (or min(μ, full_well) without shot
/// noise); DN = clip(round(black + g·(e + σ_read·z)), 0, 2^bits − 1), z standard normal.
pub fn capture_raw(radiance: &Image, model: &CaptureModel, seed: u64) -> (Vec<u16>, CaptureStats) {
    let (width, height) = (radiance.width(), radiance.height());
    let stride = radiance.channels().count();
    let samples = radiance.as_f32().unwrap_or(&[]);
    let response = model.response;
    let gain = response.gain_dn_per_e;
    let max_dn = model.max_dn();
    let shot_key = mix(seed ^ SALT_SHOT);
    let read_key = mix(seed ^ SALT_READ);
    // Beyond this mean a Poisson count is below the full well with negligible probability
    // (more than 10 standard deviations), so no sample is drawn.
    let certain_saturation = model.full_well_e + 10.0 * model.full_well_e.sqrt() + 100.0;
    let mut raw = vec![0u16; width * height];
    let rows: Vec<(f64, usize)> = raw
        .par_chunks_mut(width.max(1))
        .enumerate()
        .map(|(y, out)| {
            let first = y * width;
            // Read-noise deviates come in Box–Muller pairs indexed by pixel / 2.
            let first_pair = first / 2;
            let pairs = (first + width).div_ceil(2) - first_pair;
            let mut z = vec![0.0f32; 2 * pairs];
            gaussian_pairs(read_key, first_pair, &mut z);
            let z = &z[first % 2..];
            let (mut electrons_sum, mut saturated) = (0.0f64, 0usize);
            for (x, o) in out.iter_mut().enumerate() {
                let index = first + x;
                let c = if stride == 1 {
                    0
                } else {
                    model.pattern.color_at(x, y)
                };
                let l = f64::from(samples[index * stride + c]);
                let mean = l * response.electrons_per_unit_at(x, y, width, height);
                let electrons = if !model.shot_noise {
                    mean
                } else if mean >= certain_saturation {
                    model.full_well_e
                } else if mean > 0.0 {
                    poisson(mean, &mut SplitMix(hash(shot_key, index as u64)))
                } else {
                    0.0
                };
                let electrons = electrons.min(model.full_well_e);
                let read = model.read_noise_e * f64::from(z[x]);
                let dn = (model.black_level_dn + gain * (electrons + read))
                    .round()
                    .clamp(0.0, max_dn);
                electrons_sum += electrons;
                if electrons >= model.full_well_e || dn >= max_dn {
                    saturated += 1;
                }
                *o = dn as u16;
            }
            (electrons_sum, saturated)
        })
        .collect();
    let pixels = (width * height).max(1) as f64;
    let (mut electrons, mut saturated) = (0.0, 0usize);
    for (e, s) in rows {
        electrons += e;
        saturated += s;
    }
    let mean_signal_e = electrons / pixels;
    let noise_e =
        (mean_signal_e + model.read_noise_e * model.read_noise_e + 1.0 / (12.0 * gain * gain))
            .sqrt();
    let stats = CaptureStats {
        saturated_fraction: saturated as f64 / pixels,
        mean_signal_e,
        snr_db: 20.0 * (mean_signal_e.max(f64::MIN_POSITIVE) / noise_e).log10(),
    };
    (raw, stats)
}

/// Checks that `image` on `port` is a non-empty f32 gray, RGB or RGBA image of finite,
/// non-negative samples.
pub(crate) fn check_radiance(image: &Image, port: &str) -> Result<(), OpError> {
    if image.is_empty() {
        return Err(OpError::input(port, "is empty"));
    }
    let Some(samples) = image.as_f32() else {
        return Err(OpError::input(
            port,
            format!("must be f32 linear radiance, got {}", image.depth().name()),
        ));
    };
    if let Some(bad) = samples.iter().find(|s| !(s.is_finite() && **s >= 0.0)) {
        return Err(OpError::input(
            port,
            format!("radiance must be finite and ≥ 0, found {bad}"),
        ));
    }
    Ok(())
}

/// Raw capture through a camera model (`sensor.raw_capture`). See [`capture_raw`].
#[derive(Debug, Clone, PartialEq)]
pub struct RawCapture {
    model: CaptureModel,
    seed: u64,
}

impl Op for RawCapture {
    type Params = RawCaptureParams;
    const ID: &'static str = "sensor.raw_capture";
    const SUMMARY: &'static str = "Simulates a camera's raw capture of a linear radiance image: exposure, aperture, vignetting, shot and read noise, gain, black level, Bayer mosaic, quantization.";
    const DOC: &'static str = r#"
The photon-transfer model of a CMOS/CCD pixel (EMVA 1288 standard, "Standard for
characterization of image sensors and cameras", release 4.0, 2021; J. Janesick, "Photon
Transfer", SPIE Press 2007). Pixel (x, y) sits under the colour filter c = `pattern`(x, y) and
sees the radiance L_c of the input (gray inputs feed every pixel):

    μ_e = L_c · photons_per_unit · exposure_s / f_number² · quantum_efficiency · V(x, y)
    e   = min(Poisson(μ_e), full_well_e)             (min(μ_e, full_well_e) without shot noise)
    DN  = clip(round(black_level_dn + g · (e + read_noise_e · z)), 0, 2^bit_depth − 1)

with z standard normal and g = gain_at_iso100 · iso / 100 DN/e⁻. Vignetting V: "cos4" is the
cos⁴ law, V = 1/(1 + s²ρ²)² (tan θ = s·ρ, ρ the distance of the pixel centre from the image
centre over the half diagonal, s = `vignetting_strength`); "radial" is V = 1 − s·ρ²; "none"
is 1. The variance of DN − black is g²·μ_e + g²·σ_read² + 1/12 below saturation, so a
photon-transfer curve (variance against mean) is a line of slope g.

Outputs: `raw`, the u16 gray mosaic; `metrics`: `saturated_fraction` (pixels at full well or
the largest DN), `mean_signal_e`, `snr_db` (S/√(S + σ_read² + 1/(12g²)) at the mean signal
S), `gain_dn_per_e`, `electrons_per_unit` (at the centre) and `max_dn`.
`sensor.radiometric_correct` with the same parameters inverts the model.

Noise is counter-based from (`seed`, pixel index): the same at any thread count. Poisson
samples: inversion below a mean of 10, Hörmann's PTRS above (as `filter.noise`).

Example:
    "raw": (op: "sensor.raw_capture", inputs: { "radiance": "scene.image" }, params: (exposure_s: 0.02, iso: 400, seed: 1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "radiance",
            PortType::Image,
            "Linear radiance, f32 RGB (or gray, or RGBA with alpha ignored), relative units, ≥ 0.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "raw",
                PortType::Image,
                "The Bayer mosaic, u16 gray, digital numbers 0..2^bit_depth − 1.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "saturated_fraction, mean_signal_e, snr_db, gain_dn_per_e, electrons_per_unit, max_dn.",
            ),
        ]
    }

    fn new(params: RawCaptureParams) -> Result<Self, String> {
        let RawCaptureParams {
            exposure_s,
            f_number,
            iso,
            gain_at_iso100,
            photons_per_unit,
            quantum_efficiency,
            full_well_e,
            read_noise_e,
            shot_noise,
            black_level_dn,
            bit_depth,
            vignetting,
            vignetting_strength,
            pattern,
            seed,
        } = params;
        if !(iso.is_finite() && iso > 0.0) {
            return Err(format!("`iso` must be finite and > 0, got {iso}"));
        }
        let response = SensorResponse {
            photons_per_unit,
            exposure_s,
            f_number,
            quantum_efficiency,
            gain_dn_per_e: gain_for_iso(gain_at_iso100, iso),
            vignetting,
            vignetting_strength,
        };
        response.check()?;
        if !(full_well_e.is_finite() && full_well_e > 0.0) {
            return Err(format!(
                "`full_well_e` must be finite and > 0, got {full_well_e}"
            ));
        }
        if !(read_noise_e.is_finite() && read_noise_e >= 0.0) {
            return Err(format!(
                "`read_noise_e` must be finite and ≥ 0, got {read_noise_e}"
            ));
        }
        if !(1..=16).contains(&bit_depth) {
            return Err(format!("`bit_depth` must be 1..=16, got {bit_depth}"));
        }
        let model = CaptureModel {
            response,
            full_well_e,
            read_noise_e,
            shot_noise,
            black_level_dn,
            bit_depth,
            pattern,
        };
        if !(black_level_dn.is_finite() && black_level_dn >= 0.0 && black_level_dn < model.max_dn())
        {
            return Err(format!(
                "`black_level_dn` must be in [0, 2^bit_depth − 1), got {black_level_dn}"
            ));
        }
        Ok(RawCapture { model, seed })
    }
}

impl Operator for RawCapture {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let radiance = inputs.image("radiance")?;
        check_radiance(radiance, "radiance")?;
        let (raw, stats) = capture_raw(radiance, &self.model, self.seed);
        let raw = Image::new(
            radiance.width(),
            radiance.height(),
            Channels::Gray,
            PixelData::U16(raw),
        )
        .map_err(|e| OpError::failed(format!("building the raw image: {e}")))?;
        let mut metrics = Metrics::new();
        metrics.insert("saturated_fraction".into(), stats.saturated_fraction);
        metrics.insert("mean_signal_e".into(), stats.mean_signal_e);
        metrics.insert("snr_db".into(), stats.snr_db);
        metrics.insert("gain_dn_per_e".into(), self.model.response.gain_dn_per_e);
        metrics.insert(
            "electrons_per_unit".into(),
            self.model.response.electrons_per_unit(),
        );
        metrics.insert("max_dn".into(), self.model.max_dn());
        Ok(Outputs::new()
            .with("raw", Value::image(raw))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A model with 1000 e⁻ per unit radiance at the centre and gain 0.5 DN/e⁻.
    pub(crate) fn model(
        shot_noise: bool,
        read_noise_e: f64,
        vignetting: Vignetting,
    ) -> CaptureModel {
        CaptureModel {
            response: SensorResponse {
                photons_per_unit: 1.0e6,
                exposure_s: 0.01,
                f_number: 2.0,
                quantum_efficiency: 0.4,
                gain_dn_per_e: 0.5,
                vignetting,
                vignetting_strength: 0.8,
            },
            full_well_e: 20_000.0,
            read_noise_e,
            shot_noise,
            black_level_dn: 64.0,
            bit_depth: 14,
            pattern: BayerPattern::Rggb,
        }
    }

    fn flat(w: usize, h: usize, level: f32) -> Image {
        Image::from_f32(w, h, Channels::Gray, vec![level; w * h]).unwrap()
    }

    fn mean_var(v: &[f64]) -> (f64, f64) {
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
        (mean, var)
    }

    #[test]
    fn noiseless_capture_is_the_hand_computed_number() {
        let m = model(false, 0.0, Vignetting::None);
        assert_eq!(m.response.electrons_per_unit(), 1000.0);
        // R = 1.0, G = 2.0, B = 0.5 per pixel; RGGB mosaic.
        let rgb: Vec<f32> = (0..16).flat_map(|_| [1.0, 2.0, 0.5]).collect();
        let img = Image::from_f32(4, 4, Channels::Rgb, rgb).unwrap();
        let (raw, stats) = capture_raw(&img, &m, 0);
        // R: 64 + 0.5·1000 = 564; G: 64 + 1000 = 1064; B: 64 + 250 = 314.
        assert_eq!(&raw[..4], &[564, 1064, 564, 1064]);
        assert_eq!(&raw[4..8], &[1064, 314, 1064, 314]);
        assert_eq!(stats.saturated_fraction, 0.0);
        assert!((stats.mean_signal_e - (1000.0 + 2.0 * 2000.0 + 500.0) / 4.0).abs() < 1e-9);
    }

    #[test]
    fn saturation_and_clipping() {
        let mut m = model(false, 0.0, Vignetting::None);
        // 30 units = 30 000 e⁻ > full well: e = 20 000, DN = 64 + 10 000.
        let (raw, stats) = capture_raw(&flat(3, 3, 30.0), &m, 0);
        assert!(raw.iter().all(|&v| v == 10_064));
        assert_eq!(stats.saturated_fraction, 1.0);
        // 10 bits: clipped at 1023.
        m.bit_depth = 10;
        let (raw, stats) = capture_raw(&flat(3, 3, 5.0), &m, 0);
        assert!(raw.iter().all(|&v| v == 1023));
        assert_eq!(stats.saturated_fraction, 1.0);
        // Shot noise far above the full well saturates without drawing.
        let (raw, _) = capture_raw(&flat(2, 2, 1.0e9), &model(true, 0.0, Vignetting::None), 0);
        assert!(raw.iter().all(|&v| v == 10_064));
    }

    #[test]
    fn photon_transfer_slope_is_the_gain() {
        // Variance of DN − black against its mean over flat fields is g·mean + g²σ_r² + 1/12.
        let read = 2.0;
        let m = model(true, read, Vignetting::None);
        let g = m.response.gain_dn_per_e;
        let mut points = Vec::new();
        for level in [0.5f32, 1.0, 2.0, 4.0, 8.0] {
            let (raw, _) = capture_raw(&flat(128, 128, level), &m, 3);
            let dn: Vec<f64> = raw.iter().map(|&v| f64::from(v) - 64.0).collect();
            points.push(mean_var(&dn));
        }
        // Least-squares line through (mean, variance).
        let n = points.len() as f64;
        let (sx, sy) = points
            .iter()
            .fold((0.0, 0.0), |(a, b), (x, y)| (a + x, b + y));
        let (mx, my) = (sx / n, sy / n);
        let sxy: f64 = points.iter().map(|(x, y)| (x - mx) * (y - my)).sum();
        let sxx: f64 = points.iter().map(|(x, _)| (x - mx).powi(2)).sum();
        let slope = sxy / sxx;
        let intercept = my - slope * mx;
        assert!((slope - g).abs() < 0.02 * g, "slope {slope}, gain {g}");
        let expected_intercept = g * g * read * read + 1.0 / 12.0;
        assert!(
            (intercept - expected_intercept).abs() < 3.0,
            "intercept {intercept}, expected {expected_intercept}"
        );
        // Means are unbiased: g·μ_e.
        for ((mean, _), level) in points.iter().zip([0.5, 1.0, 2.0, 4.0, 8.0]) {
            let expected = g * 1000.0 * level;
            assert!(
                (mean - expected).abs() < 0.01 * expected,
                "{mean} {expected}"
            );
        }
    }

    #[test]
    fn vignetting_darkens_corners() {
        let m = model(false, 0.0, Vignetting::Cos4);
        let (raw, _) = capture_raw(&flat(64, 64, 4.0), &m, 0);
        let centre = f64::from(raw[32 * 64 + 32]) - 64.0;
        let corner = f64::from(raw[0]) - 64.0;
        let v = m.response.vignetting_at(0, 0, 64, 64);
        assert!((corner - 2000.0 * v).abs() <= 0.5, "{corner}");
        assert!(corner < 0.6 * centre);
    }

    #[test]
    fn same_seed_same_raw_for_any_thread_count() {
        let rgb: Vec<f32> = (0..101 * 37 * 3).map(|i| (i % 97) as f32 / 30.0).collect();
        let img = Image::from_f32(101, 37, Channels::Rgb, rgb).unwrap();
        let m = model(true, 3.0, Vignetting::Radial);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| capture_raw(&img, &m, 9))
        };
        let (a, sa) = run(1);
        let (b, sb) = run(3);
        assert_eq!(a, b);
        assert_eq!(sa.mean_signal_e.to_bits(), sb.mean_signal_e.to_bits());
        assert_ne!(a, capture_raw(&img, &m, 10).0);
    }

    #[test]
    fn bad_params_and_inputs_are_rejected() {
        let p = |f: fn(&mut RawCaptureParams)| {
            let mut p = RawCaptureParams::default();
            f(&mut p);
            RawCapture::new(p)
        };
        assert!(p(|_| ()).is_ok());
        assert!(
            p(|p| p.exposure_s = 0.0)
                .unwrap_err()
                .contains("exposure_s")
        );
        assert!(
            p(|p| p.f_number = f64::NAN)
                .unwrap_err()
                .contains("f_number")
        );
        assert!(p(|p| p.iso = -1.0).unwrap_err().contains("iso"));
        assert!(
            p(|p| p.quantum_efficiency = 1.5)
                .unwrap_err()
                .contains("quantum")
        );
        assert!(
            p(|p| p.full_well_e = 0.0)
                .unwrap_err()
                .contains("full_well")
        );
        assert!(
            p(|p| p.read_noise_e = f64::INFINITY)
                .unwrap_err()
                .contains("read")
        );
        assert!(
            p(|p| p.black_level_dn = 5000.0)
                .unwrap_err()
                .contains("black")
        );
        assert!(p(|p| p.bit_depth = 17).unwrap_err().contains("bit_depth"));
        let u8img = Image::from_u8(2, 2, Channels::Rgb, vec![0; 12]).unwrap();
        assert!(check_radiance(&u8img, "radiance").is_err());
        let nan = Image::from_f32(1, 1, Channels::Gray, vec![f32::NAN]).unwrap();
        assert!(check_radiance(&nan, "radiance").is_err());
        let neg = Image::from_f32(1, 1, Channels::Gray, vec![-1.0]).unwrap();
        assert!(check_radiance(&neg, "radiance").is_err());
        let empty = Image::from_f32(0, 0, Channels::Rgb, vec![]).unwrap();
        assert!(check_radiance(&empty, "radiance").is_err());
    }
}
