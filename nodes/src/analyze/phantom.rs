//! `analyze.phantom`: the modified Shepp–Logan head phantom, drawn from its analytic ellipses.
//!
//! [`MODIFIED_SHEPP_LOGAN`] lists the ten ellipses; [`phantom`] samples them on a square grid
//! and [`ellipse_projection`] gives the exact line integral of one ellipse (its Radon
//! transform), the ground truth for `analyze.radon` and `analyze.fbp`.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Value};
use rayon::prelude::*;

/// Largest phantom side, px.
pub const MAX_SIZE: u32 = 8192;

/// One ellipse of a phantom, in the unit square [−1, 1]² with y pointing up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ellipse {
    /// Intensity added inside the ellipse.
    pub intensity: f64,
    /// Semi-axis along the ellipse's own x axis.
    pub semi_x: f64,
    /// Semi-axis along the ellipse's own y axis.
    pub semi_y: f64,
    /// Centre x.
    pub centre_x: f64,
    /// Centre y.
    pub centre_y: f64,
    /// Rotation of the ellipse's x axis from the image x axis, counter-clockwise, degrees.
    pub angle_deg: f64,
}

const fn ellipse(
    intensity: f64,
    semi_x: f64,
    semi_y: f64,
    centre_x: f64,
    centre_y: f64,
    angle_deg: f64,
) -> Ellipse {
    Ellipse {
        intensity,
        semi_x,
        semi_y,
        centre_x,
        centre_y,
        angle_deg,
    }
}

/// The modified Shepp–Logan phantom of P. Toft ("The Radon Transform: Theory and
/// Implementation", PhD thesis, DTU 1996), with contrasts raised for display.
pub const MODIFIED_SHEPP_LOGAN: [Ellipse; 10] = [
    ellipse(1.0, 0.69, 0.92, 0.0, 0.0, 0.0),
    ellipse(-0.8, 0.6624, 0.874, 0.0, -0.0184, 0.0),
    ellipse(-0.2, 0.11, 0.31, 0.22, 0.0, -18.0),
    ellipse(-0.2, 0.16, 0.41, -0.22, 0.0, 18.0),
    ellipse(0.1, 0.21, 0.25, 0.0, 0.35, 0.0),
    ellipse(0.1, 0.046, 0.046, 0.0, 0.1, 0.0),
    ellipse(0.1, 0.046, 0.046, 0.0, -0.1, 0.0),
    ellipse(0.1, 0.046, 0.023, -0.08, -0.605, 0.0),
    ellipse(0.1, 0.023, 0.023, 0.0, -0.606, 0.0),
    ellipse(0.1, 0.023, 0.046, 0.06, -0.605, 0.0),
];

impl Ellipse {
    /// Whether the point (x, y) of the unit square lies inside (boundary included).
    pub fn contains(&self, x: f64, y: f64) -> bool {
        let (s, c) = self.angle_deg.to_radians().sin_cos();
        let (dx, dy) = (x - self.centre_x, y - self.centre_y);
        let u = (dx * c + dy * s) / self.semi_x;
        let v = (-dx * s + dy * c) / self.semi_y;
        u * u + v * v <= 1.0
    }
}

/// The phantom's value at (x, y) of the unit square: the sum of the intensities of the ellipses
/// containing the point.
pub fn phantom_value(ellipses: &[Ellipse], x: f64, y: f64) -> f64 {
    ellipses
        .iter()
        .filter(|e| e.contains(x, y))
        .map(|e| e.intensity)
        .sum()
}

/// The `size × size` phantom, row-major, sampled at pixel centres: pixel (col, row) is the point
/// x = 2·(col + ½)/size − 1, y = 1 − 2·(row + ½)/size.
pub fn phantom(ellipses: &[Ellipse], size: usize) -> Vec<f32> {
    let to_unit = |i: usize| 2.0 * (i as f64 + 0.5) / size as f64 - 1.0;
    let mut out = vec![0f32; size * size];
    out.par_chunks_mut(size.max(1))
        .enumerate()
        .for_each(|(row, line)| {
            let y = -to_unit(row);
            for (col, v) in line.iter_mut().enumerate() {
                *v = phantom_value(ellipses, to_unit(col), y) as f32;
            }
        });
    out
}

/// The exact line integral of `ellipse` along the line {p : p·(cos θ, sin θ) = s} (θ in
/// radians from the x axis, counter-clockwise; s in unit-square units): 2·A·a·b·√(α² − s'²)/α²
/// where α² = a²·cos²(θ − φ) + b²·sin²(θ − φ) and s' = s − (x₀·cos θ + y₀·sin θ), zero when
/// |s'| > α (Kak and Slaney, "Principles of Computerized Tomographic Imaging", eq. 3.10).
pub fn ellipse_projection(ellipse: &Ellipse, theta_rad: f64, s: f64) -> f64 {
    let (st, ct) = theta_rad.sin_cos();
    let shifted = s - (ellipse.centre_x * ct + ellipse.centre_y * st);
    let rel = theta_rad - ellipse.angle_deg.to_radians();
    let alpha2 = (ellipse.semi_x * rel.cos()).powi(2) + (ellipse.semi_y * rel.sin()).powi(2);
    if shifted * shifted > alpha2 {
        return 0.0;
    }
    2.0 * ellipse.intensity * ellipse.semi_x * ellipse.semi_y * (alpha2 - shifted * shifted).sqrt()
        / alpha2
}

params! {
    /// Parameters of `analyze.phantom`.
    pub struct PhantomParams {
        /// Side of the square image, px, 1..=8192. Default 128.
        size: u32 = 128 => [min = 1, max = 8192, unit = "px"],
    }
}

/// The modified Shepp–Logan phantom (`analyze.phantom`). See [`phantom`].
#[derive(Debug, Clone, PartialEq)]
pub struct Phantom {
    size: usize,
}

impl Op for Phantom {
    type Params = PhantomParams;
    const ID: &'static str = "analyze.phantom";
    const SUMMARY: &'static str =
        "Draws the modified Shepp–Logan head phantom (tomography test image).";
    const DOC: &'static str = r#"
Draws the modified Shepp–Logan phantom of Toft — the head phantom of L. A. Shepp and B. F.
Logan ("The Fourier reconstruction of a head section", IEEE Trans. Nucl. Sci. 21, 1974) with
the contrasts raised so that it is visible on screen (P. Toft, "The Radon Transform: Theory and
Implementation", PhD thesis, DTU 1996; MATLAB's `phantom('Modified Shepp-Logan')`): ten
ellipses whose intensities add up, skull 1.0, brain 0.2, ventricles 0.0, small tumours 0.3.

The image is `size` × `size` gray f32 covering the square [−1, 1]² (y up, so the three small
ellipses at y ≈ −0.6 are near the bottom), each pixel the phantom at its centre (no
antialiasing: edges are exact to the pixel, as in the reference implementations).

Example:
    "head": (op: "analyze.phantom", params: (size: 256)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The phantom, gray f32, values 0–1.",
        )]
    }

    fn new(params: PhantomParams) -> Result<Self, String> {
        if !(1..=MAX_SIZE).contains(&params.size) {
            return Err(format!(
                "`size` must be in 1..={MAX_SIZE} px, got {}",
                params.size
            ));
        }
        Ok(Phantom {
            size: params.size as usize,
        })
    }
}

impl Operator for Phantom {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let pixels = phantom(&MODIFIED_SHEPP_LOGAN, self.size);
        let image = Image::from_f32(self.size, self.size, Channels::Gray, pixels)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        let e = &MODIFIED_SHEPP_LOGAN;
        // Brain between the ventricles, ventricle, skull, outside, a small tumour.
        assert!((phantom_value(e, 0.0, -0.3) - 0.2).abs() < 1e-12);
        assert!((phantom_value(e, 0.22, 0.0) - 0.0).abs() < 1e-12);
        assert!((phantom_value(e, 0.0, 0.9) - 1.0).abs() < 1e-12);
        assert_eq!(phantom_value(e, 0.9, 0.9), 0.0);
        assert!((phantom_value(e, 0.0, -0.1) - 0.3).abs() < 1e-12);
        let img = phantom(e, 64);
        assert_eq!(img.len(), 64 * 64);
        // 1 − 0.8 − 0.2 rounds to −5.6e−17 in f64.
        assert!(img.iter().all(|&v| (-1e-6..=1.0 + 1e-6).contains(&v)));
        // Mirror symmetry of the outer ellipses: the top row is symmetric left to right.
        for col in 0..32 {
            assert_eq!(img[10 * 64 + col], img[10 * 64 + 63 - col]);
        }
    }

    #[test]
    fn ellipse_projection_matches_numerical_integral() {
        for e in MODIFIED_SHEPP_LOGAN.iter().take(4) {
            for &theta in &[0.0, 0.4, 1.3, 2.8] {
                for &s in &[-0.5, -0.1, 0.0, 0.2, 0.6] {
                    let exact = ellipse_projection(e, theta, s);
                    let (st, ct) = f64::sin_cos(theta);
                    let steps = 20_000;
                    let dt = 4.0 / steps as f64;
                    let numeric: f64 = (0..steps)
                        .map(|i| {
                            let t = -2.0 + (i as f64 + 0.5) * dt;
                            let (x, y) = (s * ct - t * st, s * st + t * ct);
                            if e.contains(x, y) {
                                e.intensity * dt
                            } else {
                                0.0
                            }
                        })
                        .sum();
                    assert!((exact - numeric).abs() < 1e-3, "{exact} vs {numeric}");
                }
            }
        }
    }

    #[test]
    fn rejects_zero_size() {
        assert!(Phantom::new(PhantomParams { size: 0 }).is_err());
    }
}
