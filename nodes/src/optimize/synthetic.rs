//! `optimize.synthetic_scene`: a generated bundle-adjustment problem with a known optimum.
//!
//! [`synthetic_problem`] places cameras on a ring looking at a cloud of points, projects the
//! points through BAL-style radial cameras (principal point 0), adds Gaussian pixel noise and
//! optional outliers to the observations, and perturbs the cameras and points to make a noisy
//! start. The same generator writes the BAL fixture of `graphs/bal.ron`.

use std::sync::Arc;

use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use super::ba::{BaCamera, BaObservation, BaProblem, project};
use super::bundle_adjust::problem_to_reconstruction;
use crate::describe::brief::SplitMix64;
use crate::geometry::camera::rodrigues;

/// Settings of [`synthetic_problem`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyntheticOptions {
    /// Number of cameras (≥ 2).
    pub cameras: usize,
    /// Number of points (≥ 1).
    pub points: usize,
    /// Probability that a camera observes a point inside its image (each point keeps ≥ 2).
    pub visibility: f64,
    /// Standard deviation of the pixel noise, px.
    pub noise_px: f64,
    /// Fraction of observations replaced by uniform random pixels.
    pub outlier_fraction: f64,
    /// Standard deviation of the start's rotation error, radians per axis.
    pub rotation_noise: f64,
    /// Standard deviation of the start's camera-centre and point error, scene units (the
    /// scene is a ball of radius 1 seen from distance 4).
    pub position_noise: f64,
    /// Relative standard deviation of the start's focal length error.
    pub focal_noise: f64,
    /// Random seed.
    pub seed: u64,
}

impl Default for SyntheticOptions {
    fn default() -> SyntheticOptions {
        SyntheticOptions {
            cameras: 8,
            points: 150,
            visibility: 0.7,
            noise_px: 0.5,
            outlier_fraction: 0.0,
            rotation_noise: 0.01,
            position_noise: 0.03,
            focal_noise: 0.01,
            seed: 1,
        }
    }
}

/// Image half-size of the generated cameras, px (the image is 640 × 480, centred at 0).
const HALF: [f64; 2] = [320.0, 240.0];

/// A generated problem: `(truth, start)`. Both share the observations (noisy, with outliers);
/// `truth` holds the cameras and points the noise-free observations were made with, `start`
/// the perturbed ones. Errors on out-of-range settings.
pub fn synthetic_problem(o: &SyntheticOptions) -> Result<(BaProblem, BaProblem), String> {
    if o.cameras < 2 || o.points < 1 {
        return Err("need at least 2 cameras and 1 point".into());
    }
    if o.cameras > 10_000 || o.points > 1_000_000 {
        return Err("at most 10 000 cameras and 10⁶ points".into());
    }
    let unit = |v: f64| (0.0..=1.0).contains(&v);
    if !unit(o.visibility) || o.visibility == 0.0 || !unit(o.outlier_fraction) {
        return Err("visibility must be in (0, 1] and outlier_fraction in [0, 1]".into());
    }
    for (name, v) in [
        ("noise_px", o.noise_px),
        ("rotation_noise", o.rotation_noise),
        ("position_noise", o.position_noise),
        ("focal_noise", o.focal_noise),
    ] {
        if !v.is_finite() || v < 0.0 {
            return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
        }
    }
    let mut rng = SplitMix64::new(o.seed);
    // Cameras on a ring of radius 4 around the y axis, heights ±0.5, looking at the origin.
    let mut cameras = Vec::with_capacity(o.cameras);
    for i in 0..o.cameras {
        let angle = std::f64::consts::TAU * i as f64 / o.cameras as f64;
        let centre = [
            4.0 * angle.sin(),
            0.5 * (rng.uniform() - 0.5),
            -4.0 * angle.cos(),
        ];
        // z axis towards the origin, x axis horizontal, y = z × x (image y down).
        let n = (centre[0] * centre[0] + centre[1] * centre[1] + centre[2] * centre[2]).sqrt();
        let z = [-centre[0] / n, -centre[1] / n, -centre[2] / n];
        let h = (z[0] * z[0] + z[2] * z[2]).sqrt();
        let x = [z[2] / h, 0.0, -z[0] / h];
        let y = [
            z[1] * x[2] - z[2] * x[1],
            z[2] * x[0] - z[0] * x[2],
            z[0] * x[1] - z[1] * x[0],
        ];
        let rotation = [x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2]];
        let translation = std::array::from_fn(|r| {
            -(rotation[3 * r] * centre[0]
                + rotation[3 * r + 1] * centre[1]
                + rotation[3 * r + 2] * centre[2])
        });
        let f = 500.0 * (1.0 + 0.1 * (rng.uniform() - 0.5));
        cameras.push(BaCamera {
            rotation,
            translation,
            intrinsics: [f, -0.05 * rng.uniform(), 0.01 * rng.uniform()],
            principal_point: [0.0, 0.0],
        });
    }
    // Points uniform in the unit ball.
    let mut points = Vec::with_capacity(o.points);
    while points.len() < o.points {
        let p = [
            2.0 * rng.uniform() - 1.0,
            2.0 * rng.uniform() - 1.0,
            2.0 * rng.uniform() - 1.0,
        ];
        if p[0] * p[0] + p[1] * p[1] + p[2] * p[2] <= 1.0 {
            points.push(p);
        }
    }
    let inside = |q: [f64; 2]| q[0].abs() < HALF[0] && q[1].abs() < HALF[1];
    let mut observations = Vec::new();
    for (j, p) in points.iter().enumerate() {
        let visible: Vec<usize> = (0..o.cameras)
            .filter(|&c| inside(project(&cameras[c], p)))
            .collect();
        let mut chosen: Vec<usize> = visible
            .iter()
            .copied()
            .filter(|_| rng.uniform() < o.visibility)
            .collect();
        if chosen.len() < 2 {
            chosen = visible.iter().copied().take(2).collect();
        }
        for c in chosen {
            let q = project(&cameras[c], p);
            let xy = if rng.uniform() < o.outlier_fraction {
                [
                    (2.0 * rng.uniform() - 1.0) * HALF[0],
                    (2.0 * rng.uniform() - 1.0) * HALF[1],
                ]
            } else {
                [
                    q[0] + o.noise_px * rng.normal(),
                    q[1] + o.noise_px * rng.normal(),
                ]
            };
            observations.push(BaObservation {
                camera: c as u32,
                point: j as u32,
                xy,
            });
        }
    }
    let truth = BaProblem {
        cameras: cameras.clone(),
        points: points.clone(),
        observations,
        ..BaProblem::default()
    };
    let mut start = truth.clone();
    for c in &mut start.cameras {
        let w = [
            o.rotation_noise * rng.normal(),
            o.rotation_noise * rng.normal(),
            o.rotation_noise * rng.normal(),
        ];
        let e = rodrigues(w);
        let r = c.rotation;
        c.rotation = std::array::from_fn(|k| {
            let (i, j) = (k / 3, k % 3);
            (0..3).map(|m| e[(i, m)] * r[3 * m + j]).sum()
        });
        for t in &mut c.translation {
            *t += o.position_noise * rng.normal();
        }
        c.intrinsics[0] *= 1.0 + o.focal_noise * rng.normal();
    }
    for p in &mut start.points {
        for v in p.iter_mut() {
            *v += o.position_noise * rng.normal();
        }
    }
    Ok((truth, start))
}

ocellus_engine::params! {
    /// Parameters of [`SyntheticScene`].
    pub struct SyntheticSceneParams {
        /// Number of cameras, 2..=10000. Default 8.
        cameras: u32 = 8,
        /// Number of points, 1..=10⁶. Default 150.
        points: u32 = 150,
        /// Probability that a camera observes a point inside its 640×480 image, (0, 1]; each
        /// point keeps at least two observations. Default 0.7.
        visibility: f64 = 0.7,
        /// Standard deviation of the observation noise, px. Default 0.5.
        noise_px: f64 = 0.5,
        /// Fraction of observations replaced by uniform random pixels, [0, 1]. Default 0.
        outlier_fraction: f64 = 0.0,
        /// Standard deviation of the start's rotation error, radians per axis. Default 0.01.
        rotation_noise: f64 = 0.01,
        /// Standard deviation of the start's translation and point error, scene units (a unit
        /// ball seen from distance 4). Default 0.03.
        position_noise: f64 = 0.03,
        /// Relative standard deviation of the start's focal-length error. Default 0.01.
        focal_noise: f64 = 0.01,
        /// Random seed. Default 1.
        seed: u64 = 1,
    }
}

/// `optimize.synthetic_scene`. See [`synthetic_problem`].
pub struct SyntheticScene {
    options: SyntheticOptions,
}

impl Op for SyntheticScene {
    type Params = SyntheticSceneParams;
    const ID: &'static str = "optimize.synthetic_scene";
    const SUMMARY: &'static str =
        "Generates a noisy bundle-adjustment problem with a known optimum (cameras on a ring).";
    const DOC: &'static str = r#"
Places `cameras` cameras on a ring of radius 4 around a unit ball of `points` random points, all
looking at its centre; each camera is a 640×480 `RADIAL` camera (f ≈ 500 px, small k1, k2,
principal point 0 as in BAL). A camera observes a point inside its image with probability
`visibility`; observations get Gaussian noise `noise_px` and a fraction `outlier_fraction` is
replaced by uniform random pixels. The output `reconstruction` is the perturbed start (rotation,
translation, point and focal noise); `truth` has the cameras and points the observations were
made with. Deterministic for a seed (SplitMix64).

Example:
    "scene": (op: "optimize.synthetic_scene", params: (cameras: 8, points: 150, noise_px: 0.5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "The noisy start: perturbed cameras and points with the noisy observations.",
            ),
            PortSpec::new(
                "truth",
                PortType::Reconstruction,
                "The true cameras and points, with the same observations.",
            ),
        ]
    }

    fn new(p: SyntheticSceneParams) -> Result<Self, String> {
        let options = SyntheticOptions {
            cameras: p.cameras as usize,
            points: p.points as usize,
            visibility: p.visibility,
            noise_px: p.noise_px,
            outlier_fraction: p.outlier_fraction,
            rotation_noise: p.rotation_noise,
            position_noise: p.position_noise,
            focal_noise: p.focal_noise,
            seed: p.seed,
        };
        if !p.visibility.is_finite() || !p.outlier_fraction.is_finite() {
            return Err("`visibility` and `outlier_fraction` must be finite".into());
        }
        // Validate everything but the (cheap) generation itself.
        let mut tiny = options;
        tiny.cameras = options.cameras.clamp(2, 10_000);
        tiny.points = 1;
        synthetic_problem(&tiny)?;
        if options.cameras < 2 || options.cameras > 10_000 {
            return Err(format!(
                "`cameras` must be 2..=10000, got {}",
                options.cameras
            ));
        }
        if options.points < 1 || options.points > 1_000_000 {
            return Err(format!(
                "`points` must be 1..=1000000, got {}",
                options.points
            ));
        }
        Ok(SyntheticScene { options })
    }
}

impl Operator for SyntheticScene {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let (truth, start) = synthetic_problem(&self.options).map_err(OpError::failed)?;
        let size = [2 * HALF[0] as u32, 2 * HALF[1] as u32];
        Ok(Outputs::new()
            .with(
                "reconstruction",
                Value::Reconstruction(Arc::new(problem_to_reconstruction(&start, size))),
            )
            .with(
                "truth",
                Value::Reconstruction(Arc::new(problem_to_reconstruction(&truth, size))),
            ))
    }
}
