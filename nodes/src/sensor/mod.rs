//! The `sensor` family: camera raw capture, demosaicing, radiometric correction, event cameras.
//!
//! - [`raw_capture`]: linear radiance → Bayer raw mosaic with a photon-transfer noise model;
//! - [`demosaic`]: Bayer mosaic → RGB (bilinear, Malvar–He–Cutler, Hamilton–Adams);
//! - [`radiometric`]: raw or demosaiced digital numbers → linear radiance (undoes the model);
//! - [`event_camera`]: a frame sequence → DVS events (ESIM-style interpolation).
//!
//! This module holds what the operators share: the colour-filter-array layout and the sensor
//! response (the factor from radiance to electrons, vignetting included).

use ocellus_engine::param_enum;

pub mod demosaic;
pub mod event_camera;
pub mod radiometric;
pub mod raw_capture;

/// Registers the `sensor` operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    registry.register::<raw_capture::RawCapture>()?;
    registry.register::<demosaic::Demosaic>()?;
    registry.register::<radiometric::RadiometricCorrect>()?;
    registry.register::<event_camera::EventCamera>()?;
    Ok(())
}

/// Index of the red channel in RGB.
pub const RED: usize = 0;
/// Index of the green channel in RGB.
pub const GREEN: usize = 1;
/// Index of the blue channel in RGB.
pub const BLUE: usize = 2;

param_enum! {
    /// Bayer colour-filter-array layout, named by the colours of the top-left 2×2 block read
    /// row by row.
    pub enum BayerPattern {
        /// Red at (0, 0), green at (1, 0) and (0, 1), blue at (1, 1).
        Rggb = "rggb",
        /// Blue at (0, 0), green at (1, 0) and (0, 1), red at (1, 1).
        Bggr = "bggr",
        /// Green at (0, 0) and (1, 1), red at (1, 0), blue at (0, 1).
        Grbg = "grbg",
        /// Green at (0, 0) and (1, 1), blue at (1, 0), red at (0, 1).
        Gbrg = "gbrg",
    }
}

impl BayerPattern {
    /// The RGB channel ([`RED`], [`GREEN`] or [`BLUE`]) sampled at pixel (x, y).
    #[inline]
    pub fn color_at(self, x: usize, y: usize) -> usize {
        let block = match self {
            BayerPattern::Rggb => [RED, GREEN, GREEN, BLUE],
            BayerPattern::Bggr => [BLUE, GREEN, GREEN, RED],
            BayerPattern::Grbg => [GREEN, RED, BLUE, GREEN],
            BayerPattern::Gbrg => [GREEN, BLUE, RED, GREEN],
        };
        block[(y & 1) * 2 + (x & 1)]
    }
}

param_enum! {
    /// Light fall-off towards the image corners.
    pub enum Vignetting {
        /// No fall-off: V = 1.
        None = "none",
        /// The cos⁴ law of a thin lens: V = cos⁴θ with tan θ = s·ρ, ρ the distance from the
        /// centre over the half diagonal and s = `vignetting_strength` the tangent of the
        /// half-diagonal field angle.
        Cos4 = "cos4",
        /// A radial polynomial: V = 1 − s·ρ², s = `vignetting_strength` in [0, 1).
        Radial = "radial",
    }
}

/// The sensor response shared by `sensor.raw_capture` and `sensor.radiometric_correct`: how
/// many electrons a unit of radiance produces at a pixel, and how electrons become digital
/// numbers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorResponse {
    /// Photons per pixel per second per unit radiance at f/1 (the optics' throughput).
    pub photons_per_unit: f64,
    /// Exposure time, s.
    pub exposure_s: f64,
    /// Aperture f-number N; irradiance ∝ 1/N².
    pub f_number: f64,
    /// Fraction of photons converted to electrons.
    pub quantum_efficiency: f64,
    /// Conversion gain, DN per electron.
    pub gain_dn_per_e: f64,
    /// Vignetting model.
    pub vignetting: Vignetting,
    /// Vignetting strength s (see [`Vignetting`]).
    pub vignetting_strength: f64,
}

impl SensorResponse {
    /// Electrons per unit radiance at the image centre (no vignetting):
    /// photons_per_unit · exposure_s / N² · QE.
    pub fn electrons_per_unit(&self) -> f64 {
        self.photons_per_unit * self.exposure_s / (self.f_number * self.f_number)
            * self.quantum_efficiency
    }

    /// Checks the ranges (each message names the parameter).
    pub fn check(&self) -> Result<(), String> {
        let positive = [
            ("photons_per_unit", self.photons_per_unit),
            ("exposure_s", self.exposure_s),
            ("f_number", self.f_number),
            ("gain", self.gain_dn_per_e),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("`{name}` must be finite and > 0, got {v}"));
            }
        }
        let qe = self.quantum_efficiency;
        if !(qe > 0.0 && qe <= 1.0) {
            return Err(format!("`quantum_efficiency` must be in (0, 1], got {qe}"));
        }
        let s = self.vignetting_strength;
        let ok = match self.vignetting {
            Vignetting::None | Vignetting::Cos4 => s.is_finite() && s >= 0.0,
            Vignetting::Radial => (0.0..1.0).contains(&s),
        };
        if !ok {
            return Err(format!(
                "`vignetting_strength` must be ≥ 0 (cos4) or in [0, 1) (radial), got {s}"
            ));
        }
        Ok(())
    }

    /// Relative illumination V(x, y) ∈ (0, 1] at the centre of pixel (x, y) of a
    /// `width` × `height` image.
    #[inline]
    pub fn vignetting_at(&self, x: usize, y: usize, width: usize, height: usize) -> f64 {
        if self.vignetting == Vignetting::None {
            return 1.0;
        }
        let (cx, cy) = (width as f64 * 0.5, height as f64 * 0.5);
        let half_diagonal_sq = (cx * cx + cy * cy).max(f64::MIN_POSITIVE);
        let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
        let rho_sq = (dx * dx + dy * dy) / half_diagonal_sq;
        let s = self.vignetting_strength;
        match self.vignetting {
            Vignetting::None => 1.0,
            // cos θ = 1/√(1 + tan²θ), so cos⁴θ = 1/(1 + tan²θ)².
            Vignetting::Cos4 => (1.0 + s * s * rho_sq).powi(-2),
            Vignetting::Radial => 1.0 - s * rho_sq,
        }
    }

    /// Electrons per unit radiance at pixel (x, y): [`Self::electrons_per_unit`] · V(x, y).
    #[inline]
    pub fn electrons_per_unit_at(&self, x: usize, y: usize, width: usize, height: usize) -> f64 {
        self.electrons_per_unit() * self.vignetting_at(x, y, width, height)
    }
}

/// The conversion gain in DN per electron at `iso`: `gain_at_iso100` · iso / 100 (gain is
/// proportional to ISO, ISO 100 the base).
pub fn gain_for_iso(gain_at_iso100: f64, iso: f64) -> f64 {
    gain_at_iso100 * iso / 100.0
}

/// Mirror index without repeating the edge sample (`…2 1 | 0 1 2 … n−1 | n−2 …`), which keeps
/// the parity of the index and so the Bayer colour; clamped for tiny sizes. `n` ≥ 1.
#[inline]
pub(crate) fn mirror(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - m }) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_place_two_greens_per_block() {
        for p in [
            BayerPattern::Rggb,
            BayerPattern::Bggr,
            BayerPattern::Grbg,
            BayerPattern::Gbrg,
        ] {
            let block: Vec<usize> = (0..4).map(|k| p.color_at(k & 1, k >> 1)).collect();
            assert_eq!(block.iter().filter(|&&c| c == GREEN).count(), 2, "{p:?}");
            assert!(block.contains(&RED) && block.contains(&BLUE), "{p:?}");
            // Greens sit on a diagonal, so red and blue never share a row with themselves.
            assert_eq!(p.color_at(0, 0) == GREEN, p.color_at(1, 1) == GREEN);
            // The pattern repeats every 2 px.
            assert_eq!(p.color_at(5, 7), p.color_at(1, 1));
        }
        assert_eq!(BayerPattern::Grbg.color_at(1, 0), RED);
        assert_eq!(BayerPattern::Gbrg.color_at(0, 1), RED);
    }

    #[test]
    fn mirror_keeps_parity() {
        assert_eq!(mirror(-1, 5), 1);
        assert_eq!(mirror(-2, 5), 2);
        assert_eq!(mirror(5, 5), 3);
        assert_eq!(mirror(6, 5), 2);
        assert_eq!(mirror(-3, 2), 1);
        assert_eq!(mirror(7, 1), 0);
        for n in 2..7usize {
            for i in -10isize..20 {
                let m = mirror(i, n);
                assert!(m < n);
                assert_eq!(m % 2, i.rem_euclid(2) as usize, "{i} {n}");
            }
        }
    }

    #[test]
    fn vignetting_models() {
        let mut r = SensorResponse {
            photons_per_unit: 1e6,
            exposure_s: 0.01,
            f_number: 2.0,
            quantum_efficiency: 0.5,
            gain_dn_per_e: 0.25,
            vignetting: Vignetting::Cos4,
            vignetting_strength: 1.0,
        };
        assert_eq!(r.electrons_per_unit(), 1e6 * 0.01 / 4.0 * 0.5);
        // Pixel centre (0.5, 0.5) of a 2×2 image: r² = 0.5 over a half diagonal² of 2, so
        // ρ² = 0.25; cos⁴ with tan²θ = 0.25 → 1/1.25².
        assert!((r.vignetting_at(0, 0, 2, 2) - 1.0 / 1.5625).abs() < 1e-12);
        r.vignetting = Vignetting::Radial;
        r.vignetting_strength = 0.4;
        assert!((r.vignetting_at(1, 1, 2, 2) - 0.9).abs() < 1e-12);
        r.vignetting = Vignetting::None;
        assert_eq!(r.vignetting_at(0, 0, 9, 9), 1.0);
        assert!(r.check().is_ok());
        r.vignetting = Vignetting::Radial;
        r.vignetting_strength = 1.0;
        assert!(r.check().unwrap_err().contains("vignetting_strength"));
        assert_eq!(gain_for_iso(0.25, 400.0), 1.0);
    }
}
