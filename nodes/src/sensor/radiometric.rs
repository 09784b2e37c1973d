//! `sensor.radiometric_correct`: digital numbers (a raw mosaic or a demosaiced image) back to
//! linear radiance — black level subtracted, divided by the gain, exposure, aperture and
//! quantum efficiency, and flat-fielded (vignetting undone).
//!
//! The algorithm is [`radiance_from_dn`]; [`RadiometricCorrect`] is the thin operator.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use rayon::prelude::*;

use super::{SensorResponse, Vignetting, gain_for_iso};

params! {
    /// Parameters of `sensor.radiometric_correct` (those of `sensor.raw_capture` that define
    /// the response).
    pub struct RadiometricCorrectParams {
        /// Exposure time of the capture.
        exposure_s: f64 = 0.01 => [above = 0.0, unit = "s"],
        /// Aperture f-number N of the capture.
        f_number: f64 = 2.8 => [above = 0.0],
        /// ISO of the capture.
        iso: f64 = 100.0 => [above = 0.0],
        /// Conversion gain at ISO 100, DN per electron.
        gain_at_iso100: f64 = 0.25 => [above = 0.0, unit = "DN/e-"],
        /// Photons per pixel per second per unit radiance at f/1.
        photons_per_unit: f64 = 1.0e7 => [above = 0.0, unit = "photons/s"],
        /// Quantum efficiency of the sensor, (0, 1].
        quantum_efficiency: f64 = 0.6 => [above = 0.0, max = 1.0],
        /// Black level subtracted first, DN.
        black_level_dn: f64 = 64.0 => [min = 0.0, unit = "DN"],
        /// Vignetting to undo (flat field): "none", "cos4" or "radial".
        vignetting: Vignetting = Vignetting::Cos4,
        /// Vignetting strength, as in `sensor.raw_capture`.
        vignetting_strength: f64 = 0.5 => [min = 0.0],
    }
}

/// Radiance from digital numbers (`sensor.radiometric_correct`). See [`radiance_from_dn`].
#[derive(Debug, Clone, PartialEq)]
pub struct RadiometricCorrect {
    response: SensorResponse,
    black_level_dn: f64,
}

/// Linear radiance estimated from the digital numbers of `image` (u8, u16 or f32; any channel
/// layout, alpha included, is treated per sample; f32 samples must be finite, checked by the
/// caller): L̂ = (DN − black) / (g · K · t / N² · QE · V(x, y)), f32, same size and channels.
/// Not clamped, so noise around black stays unbiased.
pub fn radiance_from_dn(image: &Image, response: &SensorResponse, black_level_dn: f64) -> Vec<f32> {
    let (width, height) = (image.width(), image.height());
    let stride = image.channels().count();
    let gain = response.gain_dn_per_e;
    let sample = |i: usize| -> f64 {
        match image.data() {
            PixelData::U8(v) => f64::from(v[i]),
            PixelData::U16(v) => f64::from(v[i]),
            PixelData::F32(v) => f64::from(v[i]),
        }
    };
    let mut out = vec![0.0f32; width * height * stride];
    out.par_chunks_mut((width * stride).max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(stride).enumerate() {
                let scale = 1.0 / (gain * response.electrons_per_unit_at(x, y, width, height));
                let first = (y * width + x) * stride;
                for (c, o) in px.iter_mut().enumerate() {
                    *o = ((sample(first + c) - black_level_dn) * scale) as f32;
                }
            }
        });
    out
}

impl Op for RadiometricCorrect {
    type Params = RadiometricCorrectParams;
    const ID: &'static str = "sensor.radiometric_correct";
    const SUMMARY: &'static str = "Turns raw or demosaiced digital numbers back into linear radiance: black level, gain, exposure, aperture and flat field undone.";
    const DOC: &'static str = r#"
Inverts the mean response of `sensor.raw_capture` (the photon-transfer model of the EMVA
1288 standard, release 4.0, 2021) sample by sample:

    L̂(x, y) = (DN(x, y) − black_level_dn) / (g · photons_per_unit · exposure_s / f_number² · quantum_efficiency · V(x, y))

with g = gain_at_iso100 · iso / 100 and V the vignetting of `sensor.raw_capture` (dividing by
it is flat-field correction). Use the capture's parameters; the estimate is then in the input
radiance's units. It is exact up to quantization (±0.5 DN) without noise, and unbiased with
noise below saturation; saturated or clipped pixels stay clipped (too dark). The result is
not clamped at 0. Works on the raw mosaic (gray) or on a demosaiced image (every channel the
same way).

Example:
    "linear": (op: "sensor.radiometric_correct", inputs: { "image": "rgb.image" }, params: (exposure_s: 0.02, iso: 400)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Digital numbers: the raw mosaic or a demosaiced image, u8, u16 or f32.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Estimated linear radiance, f32, same size and channels.",
        )]
    }

    fn new(params: RadiometricCorrectParams) -> Result<Self, String> {
        let RadiometricCorrectParams {
            exposure_s,
            f_number,
            iso,
            gain_at_iso100,
            photons_per_unit,
            quantum_efficiency,
            black_level_dn,
            vignetting,
            vignetting_strength,
        } = params;
        if !(iso.is_finite() && iso > 0.0) {
            return Err(format!("`iso` must be finite and > 0, got {iso}"));
        }
        if !(black_level_dn.is_finite() && black_level_dn >= 0.0) {
            return Err(format!(
                "`black_level_dn` must be finite and ≥ 0, got {black_level_dn}"
            ));
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
        Ok(RadiometricCorrect {
            response,
            black_level_dn,
        })
    }
}

impl Operator for RadiometricCorrect {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        if image.is_empty() {
            return Err(OpError::input("image", "is empty"));
        }
        if let Some(samples) = image.as_f32()
            && samples.iter().any(|s| !s.is_finite())
        {
            return Err(OpError::input("image", "contains NaN or infinite samples"));
        }
        let data = radiance_from_dn(image, &self.response, self.black_level_dn);
        let channels: Channels = image.channels();
        let out = Image::from_f32(image.width(), image.height(), channels, data)
            .map_err(|e| OpError::failed(format!("building the radiance image: {e}")))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::raw_capture::capture_raw;
    use crate::sensor::raw_capture::tests::model;

    /// A smooth RGB radiance field in 0.2..3.2 units.
    fn radiance(w: usize, h: usize) -> Image {
        let data = (0..h)
            .flat_map(|y| {
                (0..w).flat_map(move |x| {
                    let (u, v) = (x as f32 / w as f32, y as f32 / h as f32);
                    [0.2 + 3.0 * u, 0.2 + 3.0 * v, 0.2 + 1.5 * (u + v)]
                })
            })
            .collect();
        Image::from_f32(w, h, Channels::Rgb, data).unwrap()
    }

    /// The radiance sampled through the Bayer pattern (the truth of a raw pixel).
    fn mosaic_truth(img: &Image, m: &crate::sensor::raw_capture::CaptureModel) -> Vec<f64> {
        let w = img.width();
        let s = img.as_f32().unwrap();
        (0..img.width() * img.height())
            .map(|i| f64::from(s[i * 3 + m.pattern.color_at(i % w, i / w)]))
            .collect()
    }

    fn raw_image(raw: Vec<u16>, w: usize, h: usize) -> Image {
        Image::from_u16(w, h, Channels::Gray, raw).unwrap()
    }

    #[test]
    fn noiseless_round_trip_is_exact_up_to_quantization() {
        let (w, h) = (48, 40);
        let img = radiance(w, h);
        for vignetting in [Vignetting::None, Vignetting::Cos4, Vignetting::Radial] {
            let m = model(false, 0.0, vignetting);
            let (raw, _) = capture_raw(&img, &m, 0);
            let back = radiance_from_dn(&raw_image(raw, w, h), &m.response, m.black_level_dn);
            let truth = mosaic_truth(&img, &m);
            for (i, (&b, &t)) in back.iter().zip(&truth).enumerate() {
                // Half a DN, in radiance units at this pixel.
                let per_dn = 1.0
                    / (m.response.gain_dn_per_e
                        * m.response.electrons_per_unit_at(i % w, i / w, w, h));
                assert!(
                    (f64::from(b) - t).abs() <= 0.5 * per_dn + 1e-6,
                    "{vignetting:?} pixel {i}: {b} vs {t}"
                );
            }
        }
    }

    #[test]
    fn noisy_round_trip_is_unbiased_with_the_model_variance() {
        let (w, h) = (128, 128);
        let level = 1.5f32;
        let img = Image::from_f32(w, h, Channels::Gray, vec![level; w * h]).unwrap();
        let read = 4.0;
        let m = model(true, read, Vignetting::None);
        let (raw, _) = capture_raw(&img, &m, 5);
        let back = radiance_from_dn(&raw_image(raw, w, h), &m.response, m.black_level_dn);
        let n = back.len() as f64;
        let mean = back.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let var = back
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / (n - 1.0);
        // In electrons: μ = 1500, variance μ + σ_r² + 1/(12 g²).
        let k = m.response.electrons_per_unit();
        let g = m.response.gain_dn_per_e;
        let mu = f64::from(level) * k;
        let model_var = (mu + read * read + 1.0 / (12.0 * g * g)) / (k * k);
        let se_mean = (model_var / n).sqrt();
        assert!(
            (mean - f64::from(level)).abs() < 4.0 * se_mean,
            "mean {mean}, se {se_mean}"
        );
        // The sample variance's relative standard error is about √(2/n) ≈ 1.1 %.
        assert!(
            (var / model_var - 1.0).abs() < 0.05,
            "variance {var}, model {model_var}"
        );
    }

    #[test]
    fn params_are_checked_and_operator_runs() {
        let p = |f: fn(&mut RadiometricCorrectParams)| {
            let mut p = RadiometricCorrectParams::default();
            f(&mut p);
            RadiometricCorrect::new(p)
        };
        assert!(
            p(|p| p.exposure_s = -1.0)
                .unwrap_err()
                .contains("exposure_s")
        );
        assert!(p(|p| p.iso = f64::NAN).unwrap_err().contains("iso"));
        assert!(
            p(|p| p.black_level_dn = f64::INFINITY)
                .unwrap_err()
                .contains("black")
        );
        let op = p(|p| p.vignetting = Vignetting::None).unwrap();
        // Default response: 1e7 · 0.01 / 2.8² · 0.6 e⁻ per unit, gain 0.25.
        let per_unit = 1.0e7 * 0.01 / (2.8f64 * 2.8) * 0.6 * 0.25;
        let dn = 64.0 + per_unit;
        let img = Image::from_f32(1, 1, Channels::Gray, vec![dn as f32]).unwrap();
        let specs = RadiometricCorrect::inputs();
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let mut out = op
            .run(&ctx, &Inputs::new(&specs, &[Some(Value::image(img))]))
            .unwrap();
        let Some(Value::Image(got)) = out.take("image") else {
            panic!("expected an image");
        };
        assert!((got.as_f32().unwrap()[0] - 1.0).abs() < 1e-5);
        let bad = Image::from_f32(1, 1, Channels::Gray, vec![f32::NAN]).unwrap();
        assert!(
            op.run(&ctx, &Inputs::new(&specs, &[Some(Value::image(bad))]))
                .is_err()
        );
    }
}
