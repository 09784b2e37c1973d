//! `analyze.face_set`: a generated set of small procedural face images with known parameters,
//! the test data for eigenfaces ([`super::pca`]).
//!
//! [`draw_face`] renders one face from a [`FaceShape`]; [`face_set`] draws the shapes from a
//! seeded generator. Rendering averages 3 × 3 samples per pixel so edges are antialiased.
//!
//! Determinism: every random number comes from one [`SplitMix64`] used sequentially (shapes
//! and a noise seed per face, in face order); faces are then rendered in parallel, each from its
//! own values only, so the set is bit-identical for any thread count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Value};
use rayon::prelude::*;

use crate::video::filters::SplitMix64;

/// Samples per pixel side (3 × 3 per pixel).
const SUPERSAMPLE: usize = 3;

/// Largest image side, px.
pub const MAX_SIDE: u32 = 1024;

/// Largest number of faces.
pub const MAX_FACES: u32 = 4096;

/// Number of generating parameters per face (columns of the `parameters` output).
pub const FACE_PARAMETERS: usize = 12;

params! {
    /// Parameters of `analyze.face_set`.
    pub struct FaceSetParams {
        /// Number of faces, 1..=4096. Default 40.
        count: u32 = 40 => [min = 1, max = 4096],
        /// Image width, px, 8..=1024. Default 32.
        width: u32 = 32 => [min = 8, max = 1024, unit = "px"],
        /// Image height, px, 8..=1024. Default 32.
        height: u32 = 32 => [min = 8, max = 1024, unit = "px"],
        /// Standard deviation of the Gaussian noise added to every pixel, in intensity units
        /// (the image spans 0–1), ≥ 0. Default 0.
        noise_sigma: f64 = 0.0 => [min = 0.0],
        /// Seed of the random shapes and noise. Default 0.
        seed: u64 = 0,
    }
}

/// The shape and lighting of one face, in normalised coordinates: u from −1 (left edge) to 1
/// (right edge), v from −1 (top) to 1 (bottom).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaceShape {
    /// Head ellipse half-width, normalised units.
    pub head_rx: f64,
    /// Head ellipse half-height, normalised units.
    pub head_ry: f64,
    /// Skin brightness at the head centre, 0–1.
    pub skin: f64,
    /// Horizontal lighting slope: brightness is multiplied by 1 + `light`·u.
    pub light: f64,
    /// Height of the eye centres, normalised v.
    pub eye_v: f64,
    /// Distance of each eye from the vertical midline, normalised u.
    pub eye_separation: f64,
    /// Eye half-width, normalised units (half-height is 0.6 of it).
    pub eye_radius: f64,
    /// Eyebrow tilt, radians (positive raises the outer ends).
    pub brow_tilt_rad: f64,
    /// Nose length, normalised v.
    pub nose_length: f64,
    /// Mouth half-width, normalised u.
    pub mouth_half_width: f64,
    /// Mouth curvature: how much lower the mouth centre is than its corners, normalised v.
    pub smile: f64,
    /// Background brightness, 0–1.
    pub background: f64,
}

impl FaceShape {
    /// A random face: every field uniform in its range (see the operator's DOC).
    pub fn random(rng: &mut SplitMix64) -> FaceShape {
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        FaceShape {
            head_rx: u(0.55, 0.75),
            head_ry: u(0.70, 0.90),
            skin: u(0.55, 0.85),
            light: u(-0.3, 0.3),
            eye_v: u(-0.25, -0.10),
            eye_separation: u(0.25, 0.38),
            eye_radius: u(0.07, 0.11),
            brow_tilt_rad: u(-0.3, 0.3),
            nose_length: u(0.10, 0.25),
            mouth_half_width: u(0.18, 0.32),
            smile: u(-0.08, 0.12),
            background: u(0.10, 0.30),
        }
    }

    /// The fields in the column order of the `parameters` output.
    pub fn to_array(&self) -> [f64; FACE_PARAMETERS] {
        [
            self.head_rx,
            self.head_ry,
            self.skin,
            self.light,
            self.eye_v,
            self.eye_separation,
            self.eye_radius,
            self.brow_tilt_rad,
            self.nose_length,
            self.mouth_half_width,
            self.smile,
            self.background,
        ]
    }

    /// Brightness of the face at normalised point (u, v), before noise.
    pub fn intensity(&self, u: f64, v: f64) -> f64 {
        const HEAD_CENTRE_V: f64 = 0.05;
        const FEATURE_HALF_THICKNESS: f64 = 0.035;
        const MOUTH_V: f64 = 0.45;
        let hv = (v - HEAD_CENTRE_V) / self.head_ry;
        let hu = u / self.head_rx;
        if hu * hu + hv * hv > 1.0 {
            return self.background;
        }
        let skin = (self.skin * (1.0 + self.light * u)).clamp(0.0, 1.0);
        // Eyes: dark ellipses.
        for side in [-1.0, 1.0] {
            let eu = (u - side * self.eye_separation) / self.eye_radius;
            let ev = (v - self.eye_v) / (0.6 * self.eye_radius);
            if eu * eu + ev * ev <= 1.0 {
                return 0.08;
            }
        }
        // Brows: tilted bars above the eyes.
        for side in [-1.0, 1.0] {
            let cu = side * self.eye_separation;
            let cv = self.eye_v - 2.0 * self.eye_radius;
            let angle = side * self.brow_tilt_rad;
            let (s, c) = angle.sin_cos();
            let (du, dv) = (u - cu, v - cv);
            // Along the bar (positive outward), and across it.
            let along = du * c - dv * s;
            let across = du * s + dv * c;
            if along.abs() <= 1.3 * self.eye_radius && across.abs() <= FEATURE_HALF_THICKNESS {
                return 0.15 * skin;
            }
        }
        // Nose: a shadowed vertical bar below the eyes.
        let nose_top = self.eye_v + self.eye_radius;
        if u.abs() <= FEATURE_HALF_THICKNESS && v >= nose_top && v <= nose_top + self.nose_length {
            return 0.7 * skin;
        }
        // Mouth: a parabolic arc.
        if u.abs() <= self.mouth_half_width {
            let t = u / self.mouth_half_width;
            let curve = MOUTH_V + self.smile * (1.0 - t * t);
            if (v - curve).abs() <= FEATURE_HALF_THICKNESS {
                return 0.2 * skin;
            }
        }
        skin
    }
}

/// Renders `shape` as a `width × height` gray f32 image (3 × 3 samples per pixel) and adds
/// Gaussian noise of `noise_sigma` drawn from `noise`.
pub fn draw_face(
    shape: &FaceShape,
    width: usize,
    height: usize,
    noise_sigma: f64,
    noise: &mut SplitMix64,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(width * height);
    let n = SUPERSAMPLE as f64;
    for y in 0..height {
        for x in 0..width {
            let mut sum = 0.0;
            for sy in 0..SUPERSAMPLE {
                for sx in 0..SUPERSAMPLE {
                    let u = (x as f64 + (sx as f64 + 0.5) / n) / width as f64 * 2.0 - 1.0;
                    let v = (y as f64 + (sy as f64 + 0.5) / n) / height as f64 * 2.0 - 1.0;
                    sum += shape.intensity(u, v);
                }
            }
            let mut value = sum / (n * n);
            if noise_sigma > 0.0 {
                value += noise.normal(0.0, noise_sigma);
            }
            out.push(value as f32);
        }
    }
    out
}

/// `count` random faces of `width × height` px with their shapes; see [`FaceSet`].
pub fn face_set(
    count: usize,
    width: usize,
    height: usize,
    noise_sigma: f64,
    seed: u64,
) -> Vec<(FaceShape, Vec<f32>)> {
    let mut rng = SplitMix64::new(seed);
    let drawn: Vec<(FaceShape, u64)> = (0..count)
        .map(|_| (FaceShape::random(&mut rng), rng.next_u64()))
        .collect();
    drawn
        .into_par_iter()
        .map(|(shape, noise_seed)| {
            let mut noise = SplitMix64::new(noise_seed);
            let pixels = draw_face(&shape, width, height, noise_sigma, &mut noise);
            (shape, pixels)
        })
        .collect()
}

/// Generated face images (`analyze.face_set`). See [`face_set`].
#[derive(Debug, Clone, PartialEq)]
pub struct FaceSet {
    count: usize,
    width: usize,
    height: usize,
    noise_sigma: f64,
    seed: u64,
}

impl Op for FaceSet {
    type Params = FaceSetParams;
    const ID: &'static str = "analyze.face_set";
    const SUMMARY: &'static str =
        "Generates small procedural face images with known shape parameters (eigenface data).";
    const DOC: &'static str = r#"
Draws `count` gray f32 images (0–1) of cartoon faces, each from its own random shape: an
elliptic head on a flat background, lit by a horizontal brightness slope, two elliptic eyes,
two tilted eyebrows, a nose shadow and a parabolic mouth. Pixels average 3 × 3 samples
(antialiased edges); Gaussian noise of `noise_sigma` is added last.

The shape parameters, each uniform in its range, are the columns of `parameters` (one row per
face), in normalised coordinates (u, v from −1 to 1 across the image, v downwards):
head_rx [0.55, 0.75], head_ry [0.70, 0.90], skin [0.55, 0.85], light [−0.3, 0.3],
eye_v [−0.25, −0.10], eye_separation [0.25, 0.38], eye_radius [0.07, 0.11],
brow_tilt_rad [−0.3, 0.3], nose_length [0.10, 0.25], mouth_half_width [0.18, 0.32],
smile [−0.08, 0.12], background [0.10, 0.30].

Twelve parameters drive the whole set, so a few principal components explain most of its
variance — the premise of eigenfaces (M. Turk and A. Pentland, "Eigenfaces for recognition",
J. Cognitive Neuroscience 3(1), 1991), here on data whose generating factors are known.
Deterministic for a given `seed` (SplitMix64, Steele, Lea and Flood, OOPSLA 2014) at any thread
count.

Example:
    "faces": (op: "analyze.face_set", params: (count: 40, width: 32, height: 32, seed: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "faces",
                PortType::Image.list_of(),
                "The faces, gray f32, 0–1 before noise.",
            ),
            PortSpec::new(
                "parameters",
                PortType::Matrix,
                "count × 12: the generating shape parameters of every face (see DOC).",
            ),
        ]
    }

    fn new(params: FaceSetParams) -> Result<Self, String> {
        let FaceSetParams {
            count,
            width,
            height,
            noise_sigma,
            seed,
        } = params;
        if !(1..=MAX_FACES).contains(&count) {
            return Err(format!("`count` must be in 1..={MAX_FACES}, got {count}"));
        }
        for (name, side) in [("width", width), ("height", height)] {
            if !(8..=MAX_SIDE).contains(&side) {
                return Err(format!("`{name}` must be in 8..={MAX_SIDE} px, got {side}"));
            }
        }
        if !(noise_sigma.is_finite() && noise_sigma >= 0.0) {
            return Err(format!(
                "`noise_sigma` must be finite and ≥ 0, got {noise_sigma}"
            ));
        }
        Ok(FaceSet {
            count: count as usize,
            width: width as usize,
            height: height as usize,
            noise_sigma,
            seed,
        })
    }
}

impl Operator for FaceSet {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let faces = face_set(
            self.count,
            self.width,
            self.height,
            self.noise_sigma,
            self.seed,
        );
        let mut parameters = Vec::with_capacity(self.count * FACE_PARAMETERS);
        let mut images = Vec::with_capacity(self.count);
        for (shape, pixels) in faces {
            parameters.extend(shape.to_array());
            let image = Image::from_f32(self.width, self.height, Channels::Gray, pixels)
                .map_err(|e| OpError::failed(e.to_string()))?;
            images.push(Value::image(image));
        }
        let parameters = Matrix::new(self.count, FACE_PARAMETERS, parameters)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("faces", Value::list(PortType::Image, images))
            .with("parameters", Value::Matrix(Arc::new(parameters))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyze::pca::{ComponentSelection, pca};

    #[test]
    fn faces_have_their_features_where_the_parameters_say() {
        let shape = FaceShape {
            head_rx: 0.7,
            head_ry: 0.8,
            skin: 0.8,
            light: 0.0,
            eye_v: -0.2,
            eye_separation: 0.3,
            eye_radius: 0.1,
            brow_tilt_rad: 0.0,
            nose_length: 0.2,
            mouth_half_width: 0.3,
            smile: 0.0,
            background: 0.2,
        };
        assert_eq!(shape.intensity(-0.95, -0.95), 0.2);
        assert_eq!(shape.intensity(0.3, -0.2), 0.08);
        assert_eq!(shape.intensity(-0.3, -0.2), 0.08);
        assert!((shape.intensity(0.3, -0.4) - 0.12).abs() < 1e-12);
        assert!((shape.intensity(0.0, 0.0) - 0.56).abs() < 1e-12);
        assert!((shape.intensity(0.1, 0.45) - 0.16).abs() < 1e-12);
        assert_eq!(shape.intensity(0.5, 0.3), 0.8);
        let mut rng = SplitMix64::new(0);
        let img = draw_face(&shape, 16, 16, 0.0, &mut rng);
        assert!(img.iter().all(|v| (0.0..=1.0).contains(v)));
        // Symmetric face without lighting: the image is mirror-symmetric.
        for y in 0..16 {
            for x in 0..8 {
                assert!((img[y * 16 + x] - img[y * 16 + 15 - x]).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn deterministic_for_any_thread_count() {
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let three = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        let a = one.install(|| face_set(9, 20, 24, 0.05, 4));
        let b = three.install(|| face_set(9, 20, 24, 0.05, 4));
        assert_eq!(a, b);
        assert_ne!(a, face_set(9, 20, 24, 0.05, 5));
    }

    /// Twelve generating parameters: a handful of components explain most of the variance,
    /// far fewer than for the same number of white-noise images.
    #[test]
    fn few_components_explain_most_variance() {
        let faces = face_set(60, 32, 32, 0.0, 1);
        let data: Vec<Vec<f64>> = faces
            .iter()
            .map(|(_, p)| p.iter().map(|&v| f64::from(v)).collect())
            .collect();
        let model = pca(&data).unwrap();
        assert!(model.used_gram);
        let k90 = model.select(ComponentSelection::VarianceShare(0.9));
        let k50 = model.select(ComponentSelection::VarianceShare(0.5));
        let mut rng = SplitMix64::new(2);
        let noise: Vec<Vec<f64>> = (0..60)
            .map(|_| (0..1024).map(|_| rng.uniform()).collect())
            .collect();
        let noise_model = pca(&noise).unwrap();
        let noise_k90 = noise_model.select(ComponentSelection::VarianceShare(0.9));
        eprintln!("k50 {k50}, k90 {k90}, noise k90 {noise_k90}");
        assert!(k50 <= 4, "k50 = {k50}");
        assert!(k90 <= 20, "k90 = {k90}");
        assert!(noise_k90 >= 45, "noise k90 = {noise_k90}");
        // Brightness dominates: the first component correlates with skin brightness.
        let coefficients = model.project(&data, 1);
        let skin: Vec<f64> = faces.iter().map(|(s, _)| s.skin).collect();
        let c: Vec<f64> = coefficients.iter().map(|c| c[0]).collect();
        let r = correlation(&c, &skin).abs();
        eprintln!("|corr(pc1, skin)| = {r}");
        // Measured 0.65 (seed 1): background, lighting and head size share the first component.
        assert!(r > 0.5, "|corr(pc1, skin)| = {r}");
    }

    fn correlation(a: &[f64], b: &[f64]) -> f64 {
        let n = a.len() as f64;
        let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
        let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
        let va: f64 = a.iter().map(|x| (x - ma) * (x - ma)).sum();
        let vb: f64 = b.iter().map(|y| (y - mb) * (y - mb)).sum();
        cov / (va * vb).sqrt()
    }

    #[test]
    fn rejects_bad_params() {
        let bad = |p: FaceSetParams| FaceSet::new(p).is_err();
        assert!(bad(FaceSetParams {
            count: 0,
            ..FaceSetParams::default()
        }));
        assert!(bad(FaceSetParams {
            width: 4,
            ..FaceSetParams::default()
        }));
        assert!(bad(FaceSetParams {
            noise_sigma: f64::NAN,
            ..FaceSetParams::default()
        }));
    }
}
