//! `capture.moving_camera`: a simulated eye-in-hand camera. Renders a [`Scene`] from one of its
//! cameras while that camera moves by a 6-DoF velocity twist expressed in its own frame — the
//! commanded velocity of a visual-servoing loop, fed back from later in a stream, or a constant
//! velocity (an animated camera) in a batch run.
//!
//! Motion: with `ξ = (v, ω)` the twist in force (camera frame: x right, y down, z forward;
//! translation in scene units per second, rotation in rad per second), frame `k + 1` is seen
//! from `world_from_camera_{k+1} = world_from_camera_k · exp(dt·ξ)`, `dt = 1/fps`, with the
//! exact SE(3) exponential of [`se3_exp`]. Each frame is rendered by the rasterizer exactly as
//! `capture.render` renders the scene camera placed at that pose.

use std::sync::Arc;

use nalgebra::{Matrix3, Vector3};
use ocellus_engine::op::{
    FrameSource, Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext,
};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Pose, Scene, SceneCamera, Value};

use super::moving::MAX_FRAMES;
use crate::geometry::camera::{from_na, to_na};
use crate::geometry::pose_util::skew;
use crate::render::raster::{Cull, RasterOptions, rasterize_view};
use crate::render::scene::View;

/// Below this rotation angle (rad) the coefficients of [`se3_exp`] come from their Taylor
/// series (the closed forms lose digits to cancellation near 0).
const SMALL_ANGLE: f64 = 1e-2;

/// The coefficients `(sin θ / θ, (1 − cos θ) / θ², (θ − sin θ) / θ³)` of the SE(3)
/// exponential for `θ² = theta2`: Taylor series through θ⁶ below [`SMALL_ANGLE`] (truncation
/// below 1e-20), closed forms above (`1 − cos θ` as `2 sin²(θ/2)`, free of cancellation).
fn exp_coefficients(theta2: f64) -> (f64, f64, f64) {
    let theta = theta2.sqrt();
    if theta < SMALL_ANGLE {
        let t4 = theta2 * theta2;
        let t6 = t4 * theta2;
        (
            1.0 - theta2 / 6.0 + t4 / 120.0 - t6 / 5040.0,
            0.5 - theta2 / 24.0 + t4 / 720.0 - t6 / 40_320.0,
            1.0 / 6.0 - theta2 / 120.0 + t4 / 5040.0 - t6 / 362_880.0,
        )
    } else {
        let half = (0.5 * theta).sin();
        (
            theta.sin() / theta,
            2.0 * half * half / theta2,
            (theta - theta.sin()) / (theta2 * theta),
        )
    }
}

/// The SE(3) exponential of the twist `xi = (vx, vy, vz, ωx, ωy, ωz)`: the rigid motion
/// `(R, t)` (`x ↦ R x + t`) reached by moving with the constant body velocity `xi` for unit
/// time.
///
/// With `θ = |ω|` and `K = [ω]×`: `R = I + (sin θ/θ) K + ((1 − cos θ)/θ²) K²` (Rodrigues) and
/// `t = V v`, `V = I + ((1 − cos θ)/θ²) K + ((θ − sin θ)/θ³) K²`. The coefficients switch to
/// their Taylor series below θ = 0.01 rad, so small and zero rotations are exact to rounding
/// (`θ = 0` gives `R = I`, `t = v`).
pub fn se3_exp(xi: [f64; 6]) -> (Matrix3<f64>, Vector3<f64>) {
    let v = Vector3::new(xi[0], xi[1], xi[2]);
    let w = Vector3::new(xi[3], xi[4], xi[5]);
    let (a, b, c) = exp_coefficients(w.norm_squared());
    let k = skew(&w);
    let k2 = k * k;
    let r = Matrix3::identity() + k * a + k2 * b;
    let vm = Matrix3::identity() + k * b + k2 * c;
    (r, vm * v)
}

/// One step of the motion, `dt` seconds at the body velocity `xi`:
/// `world_from_camera ← world_from_camera · exp(dt·xi)`, computed on the `camera_from_world`
/// pose as `camera_from_world ← exp(−dt·xi) · camera_from_world` (the same motion, without
/// inverting the pose). The result's quaternion is normalized
/// ([`Pose::from_rotation_matrix`]), so rounding never accumulates into a non-rotation however
/// many steps are taken; a zero twist leaves the pose bit-identical.
pub fn step_pose(camera_from_world: &Pose, xi: [f64; 6], dt: f64) -> Pose {
    let motion = xi.map(|x| -x * dt);
    if motion.iter().all(|&x| x == 0.0) {
        return *camera_from_world;
    }
    let (dr, dtrans) = se3_exp(motion);
    let r = dr * to_na(&camera_from_world.rotation_matrix());
    let t = dr * Vector3::from(camera_from_world.translation) + dtrans;
    Pose::from_rotation_matrix(&from_na(&r), [t.x, t.y, t.z])
}

params! {
    /// Parameters of `capture.moving_camera`.
    pub struct MovingCameraParams {
        /// Index of the scene camera that gives the intrinsics, the image size and the start
        /// pose (frame 0). Default 0.
        camera: u32 = 0 => [max = 65535],
        /// Number of frames. Default 100.
        frames: u32 = 100 => [min = 1, max = 10000],
        /// Frame rate: frame k is at k / fps seconds, and the camera moves for dt = 1/fps
        /// between frames. Default 30.
        fps: f64 = 30.0 => [above = 0.0, max = 10000.0, unit = "frames/s"],
        /// Velocity twist (vx, vy, vz, ωx, ωy, ωz) in the camera frame (x right, y down,
        /// z forward), scene units/s and rad/s, used until a velocity is fed back (always, in
        /// a batch run). Default all 0: a still camera.
        velocity: [f64; 6] = [0.0; 6] => [unit = "scene units/s, rad/s"],
        /// Rasterizer samples per pixel, 1 or 4 (rotated-grid MSAA), as in capture.render.
        /// Default 4.
        samples: u32 = 4 => [min = 1, max = 4],
    }
}

/// The configuration of a moving camera (`capture.moving_camera`), without its scene.
#[derive(Debug, Clone, PartialEq)]
pub struct MovingCamera {
    camera: usize,
    frames: usize,
    fps: f64,
    velocity: [f64; 6],
    samples: u32,
}

/// A rendered frame of [`MovingCameraSource`].
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFrame {
    /// Linear RGB f32 radiance.
    pub color: Image,
    /// Gray f32: distance along each pixel-centre unit ray, +∞ on a miss.
    pub depth: Image,
    /// The camera's `camera_from_world` at this frame.
    pub camera_from_world: Pose,
}

/// Renders `scene` as its camera `camera` sees it from `camera_from_world`, with the
/// rasterizer options of `capture.render` (no culling, `samples` per pixel): the same pixels as
/// `capture.render` of the scene with that camera moved to that pose.
pub fn render_posed(
    scene: &Scene,
    camera: usize,
    camera_from_world: Pose,
    samples: u32,
) -> Result<(Image, Image), String> {
    let base = scene.cameras.get(camera).ok_or_else(|| {
        format!(
            "camera index {camera} is out of range: the scene has {} camera(s)",
            scene.cameras.len()
        )
    })?;
    let posed = SceneCamera {
        camera_from_world,
        ..base.clone()
    };
    let view = View::new(&posed)?;
    let options = RasterOptions {
        cull: Cull::None,
        samples,
        ..RasterOptions::default()
    };
    let out = rasterize_view(scene, &view, &options)?;
    let color = Image::new(
        out.width,
        out.height,
        Channels::Rgb,
        PixelData::F32(out.color),
    )
    .map_err(|e| e.to_string())?;
    let depth = Image::new(
        out.width,
        out.height,
        Channels::Gray,
        PixelData::F32(out.depth),
    )
    .map_err(|e| e.to_string())?;
    Ok((color, depth))
}

/// Checks that `value` is a finite 6×1 matrix and returns it as a twist.
pub fn twist_from_value(value: &Value) -> Result<[f64; 6], String> {
    let Value::Matrix(m) = value else {
        return Err(format!(
            "expected a 6×1 Matrix (vx, vy, vz, ωx, ωy, ωz), got {}",
            value.port_type()
        ));
    };
    if (m.rows, m.cols) != (6, 1) || m.data.len() != 6 {
        return Err(format!(
            "expected a 6×1 Matrix (vx, vy, vz, ωx, ωy, ωz), got {}×{}",
            m.rows, m.cols
        ));
    }
    if let Some(bad) = m.data.iter().find(|v| !v.is_finite()) {
        return Err(format!("velocity has a non-finite component ({bad})"));
    }
    let mut xi = [0.0; 6];
    xi.copy_from_slice(&m.data);
    Ok(xi)
}

/// The camera path and renderer state of `capture.moving_camera`: the pose of the last frame
/// asked for and the velocity in force.
pub struct MovingCameraSource {
    scene: Arc<Scene>,
    config: MovingCamera,
    /// `camera_from_world` of the scene camera: frame 0.
    start: Pose,
    /// Frame whose pose is `camera_from_world`.
    at: usize,
    camera_from_world: Pose,
    /// The twist that moves the camera to the next frame.
    velocity: [f64; 6],
    /// Whether a velocity was fed back (the path then depends on the feedback history and
    /// cannot be replayed).
    fed: bool,
}

impl MovingCameraSource {
    /// A source at frame 0, or why the scene cannot be rendered from camera `config.camera`.
    pub fn new(scene: Arc<Scene>, config: MovingCamera) -> Result<MovingCameraSource, String> {
        let base = scene.cameras.get(config.camera).ok_or_else(|| {
            format!(
                "`camera` {} is out of range: the scene has {} camera(s)",
                config.camera,
                scene.cameras.len()
            )
        })?;
        // Checks the intrinsics, the size and the start pose as the renderers will.
        View::new(base).map_err(|e| format!("camera {}: {e}", config.camera))?;
        let start = base.camera_from_world;
        Ok(MovingCameraSource {
            camera_from_world: start,
            at: 0,
            velocity: config.velocity,
            fed: false,
            start,
            scene,
            config,
        })
    }

    /// Back to frame 0 with the parameter velocity.
    fn restart(&mut self) {
        self.at = 0;
        self.camera_from_world = self.start;
        self.velocity = self.config.velocity;
    }

    /// Moves the camera to frame `index` (forward, one `dt` step per frame with the velocity
    /// in force) and returns its `camera_from_world`. Going back is only possible while
    /// nothing was fed back: the path is then replayed from frame 0.
    pub fn pose_at(&mut self, index: usize) -> Result<Pose, String> {
        if index >= self.config.frames {
            return Err(format!(
                "frame {index} is outside a sequence of {} frames",
                self.config.frames
            ));
        }
        if index < self.at {
            if self.fed {
                return Err(format!(
                    "frame {index} was asked for after frame {}: a camera driven by feedback \
                     only moves forward",
                    self.at
                ));
            }
            self.restart();
        }
        let dt = 1.0 / self.config.fps;
        while self.at < index {
            self.camera_from_world = step_pose(&self.camera_from_world, self.velocity, dt);
            self.at += 1;
        }
        Ok(self.camera_from_world)
    }

    /// Frame `index`: the camera moved there ([`MovingCameraSource::pose_at`]) and rendered.
    pub fn render(&mut self, index: usize) -> Result<CameraFrame, String> {
        let camera_from_world = self.pose_at(index)?;
        let (color, depth) = render_posed(
            &self.scene,
            self.config.camera,
            camera_from_world,
            self.config.samples,
        )
        .map_err(|e| format!("frame {index}: {e}"))?;
        Ok(CameraFrame {
            color,
            depth,
            camera_from_world,
        })
    }

    /// Sets the velocity that moves the camera to the next frame.
    pub fn set_velocity(&mut self, xi: [f64; 6]) {
        self.velocity = xi;
        self.fed = true;
    }

    /// The scene camera's intrinsics (the `camera` output).
    fn camera_value(&self) -> Result<Value, String> {
        self.scene
            .cameras
            .get(self.config.camera)
            .map(|c| Value::Camera(Arc::new(c.camera.clone())))
            .ok_or_else(|| format!("no camera {}", self.config.camera))
    }
}

impl FrameSource for MovingCameraSource {
    fn frames(&self) -> usize {
        self.config.frames
    }

    fn timestamp_us(&self, index: usize) -> i64 {
        (index as f64 * 1e6 / self.config.fps).round() as i64
    }

    fn frame(&mut self, _ctx: &RunContext, index: usize) -> Result<Outputs, OpError> {
        let frame = self.render(index).map_err(OpError::failed)?;
        Ok(Outputs::new()
            .with("frames", Value::image(frame.color))
            .with("depths", Value::image(frame.depth))
            .with("poses", Value::Pose(frame.camera_from_world)))
    }

    fn statics(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("camera", self.camera_value().map_err(OpError::failed)?))
    }

    fn feed(
        &mut self,
        _ctx: &RunContext,
        index: usize,
        port: &str,
        value: &Value,
    ) -> Result<(), OpError> {
        if port != "velocity" {
            return Err(OpError::failed(format!(
                "capture.moving_camera takes feedback on `velocity` only, not `{port}`"
            )));
        }
        let xi = twist_from_value(value).map_err(|e| {
            OpError::input("velocity", format!("fed back before frame {index}: {e}"))
        })?;
        self.set_velocity(xi);
        Ok(())
    }
}

impl MovingCamera {
    /// The source for the node's inputs.
    fn source(&self, inputs: &Inputs<'_>) -> Result<MovingCameraSource, OpError> {
        let scene = match inputs.require("scene")? {
            Value::Scene(s) => Arc::clone(s),
            other => {
                return Err(OpError::input(
                    "scene",
                    format!("expected Scene, got {}", other.port_type()),
                ));
            }
        };
        MovingCameraSource::new(scene, self.clone()).map_err(|e| OpError::input("scene", e))
    }
}

impl Op for MovingCamera {
    type Params = MovingCameraParams;
    const ID: &'static str = "capture.moving_camera";
    const SUMMARY: &'static str = "Renders a scene from a camera moving by a 6-DoF velocity in its own frame (fed back in a stream): a simulated eye-in-hand camera.";
    const DOC: &'static str = r#"
A simulated eye-in-hand camera for closed-loop vision (visual servoing): renders `scene` from
its camera `camera` (intrinsics, image size and start pose) while that camera moves by a
velocity twist ξ = (vx, vy, vz, ωx, ωy, ωz) expressed in the camera frame (x right, y down,
z forward; scene units/s and rad/s) — the convention of geometry.visual_servo_step's
`velocity`.

Motion: frame 0 is rendered at the scene camera's pose. Between frames the velocity in force
is held for dt = 1/`fps` seconds:
    world_from_camera(k+1) = world_from_camera(k) · exp(dt·ξ)
(equivalently camera_from_world(k+1) = exp(−dt·ξ) · camera_from_world(k)), with the exact
SE(3) exponential: R = I + (sin θ/θ) K + ((1 − cos θ)/θ²) K² (Rodrigues) and t = V v,
V = I + ((1 − cos θ)/θ²) K + ((θ − sin θ)/θ³) K², θ = |ω|, K = [ω]× (Taylor series below
θ = 0.01 rad, so small rotations are exact to rounding; a zero velocity leaves the pose
bit-identical). A constant ξ therefore moves the camera along a screw; e.g. vz alone advances
it vz·k·dt along its optical axis, ωz alone rolls it by ωz·k·dt about that axis.

The velocity in force is the last one fed back on `velocity`, else the `velocity` parameter.
`velocity` is a feedback input: it is never wired in `inputs`; a stream section's `feedback`
delivers the value a later node computed for frame k before frame k+1 is rendered (frame 0
gets nothing), closing the loop:
    stream: (feedback: { "eye.velocity": "servo.velocity" })
A batch run receives no feedback: every frame uses the parameter velocity (an open-loop,
constantly moving camera), and gives exactly the frames a stream gives without feedback. A
fed-back value that is not a finite 6×1 matrix is an error.

Each frame is rendered by the rasterizer exactly as capture.render renders the scene with its
camera `camera` moved to that pose (`samples` per pixel, no culling).

Outputs per frame: `frames` (linear RGB f32), `depths` (gray f32, distance along each
pixel-centre unit ray, +inf on a miss) and `poses` (the camera_from_world of each frame, the
scene cameras' convention). `camera` (the intrinsics, e.g. for geometry.visual_servo_step) is
known before the first frame. Timestamps: frame k at k/`fps` s.

Errors: `camera` beyond the scene's cameras, a camera the renderers refuse (distortion, bad
size), `frames` < 1, `fps` ≤ 0, a non-finite `velocity`, `samples` other than 1 or 4.

Example:
    "eye": (op: "capture.moving_camera", inputs: { "scene": "scene.scene" },
            params: (camera: 0, frames: 90, fps: 30.0, samples: 4)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "scene",
                PortType::Scene,
                "The scene; camera `camera` gives the intrinsics and the start pose.",
            ),
            PortSpec::new(
                "velocity",
                PortType::Matrix,
                "Fed back: 6×1 velocity twist (vx, vy, vz, ωx, ωy, ωz), camera frame.",
            )
            .feedback(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "The rendered frames, linear RGB f32.",
            )
            .per_frame(),
            PortSpec::new(
                "depths",
                PortType::Image.list_of(),
                "Depth per frame, gray f32 (distance along each ray, +inf on a miss).",
            )
            .per_frame(),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "camera_from_world of each frame.",
            )
            .per_frame(),
            PortSpec::new(
                "camera",
                PortType::Camera,
                "The intrinsics of scene camera `camera`.",
            ),
        ]
    }

    fn new(params: MovingCameraParams) -> Result<Self, String> {
        let MovingCameraParams {
            camera,
            frames,
            fps,
            velocity,
            samples,
        } = params;
        if !(1..=MAX_FRAMES).contains(&frames) {
            return Err(format!("`frames` must be 1..={MAX_FRAMES}, got {frames}"));
        }
        if !(fps.is_finite() && fps > 0.0) {
            return Err(format!("`fps` must be finite and positive, got {fps}"));
        }
        if velocity.iter().any(|v| !v.is_finite()) {
            return Err(format!("`velocity` must be finite, got {velocity:?}"));
        }
        if samples != 1 && samples != 4 {
            return Err(format!("`samples` must be 1 or 4, got {samples}"));
        }
        Ok(MovingCamera {
            camera: camera as usize,
            frames: frames as usize,
            fps,
            velocity,
            samples,
        })
    }
}

impl Operator for MovingCamera {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mut source = self.source(inputs)?;
        let n = self.frames;
        let (mut frames, mut depths, mut poses) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
        for k in 0..n {
            let mut one = source.frame(ctx, k)?;
            let mut take = |name: &str| {
                one.take(name)
                    .ok_or_else(|| OpError::failed(format!("frame {k}: no `{name}`")))
            };
            frames.push(take("frames")?);
            depths.push(take("depths")?);
            poses.push(take("poses")?);
        }
        let mut statics = source.statics(ctx)?;
        let camera = statics
            .take("camera")
            .ok_or_else(|| OpError::failed("no `camera`"))?;
        Ok(Outputs::new()
            .with("frames", Value::list(PortType::Image, frames))
            .with("depths", Value::list(PortType::Image, depths))
            .with("poses", Value::list(PortType::Pose, poses))
            .with("camera", camera))
    }

    fn frame_source(
        &self,
        _ctx: &RunContext,
        inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn FrameSource>, OpError>> {
        Some(
            self.source(inputs)
                .map(|s| Box::new(s) as Box<dyn FrameSource>),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::render::{CaptureRenderParams, Renderer, render_frame};
    use crate::geometry::pose_util::rotation_angle_deg;
    use crate::io::read_scene::parse_scene;
    use ocellus_engine::value::Matrix;

    /// A small textured scene: a checker plane and a sphere, seen by two 64×48 cameras.
    fn scene() -> Arc<Scene> {
        let scene = parse_scene(
            r#"(materials: [(name: "floor", albedo: (1, 1, 1),
                             albedo_texture: Some((checker: (cells: 8, size: 64, a: (0.9, 0.9, 0.9),
                                                             b: (0.1, 0.1, 0.1))))),
                            (name: "ball", albedo: (0.8, 0.4, 0.2))],
                objects: [(shape: Plane(point: (0, 0, 0), normal: (0, 0, 1), half_extent: 2.0),
                           material: "floor"),
                          (shape: Sphere(center: (0.3, 0.2, 0.4), radius: 0.3), material: "ball")],
                lights: [Directional(direction: (0.2, -0.3, -1), irradiance: (1, 1, 1)),
                         Environment(radiance: (0.5, 0.5, 0.5))],
                cameras: [(width: 64, height: 48, eye: (0.2, -0.1, 3), target: (0, 0, 0)),
                          (width: 40, height: 30, eye: (1, 1, 2), target: (0, 0, 0))])"#,
            std::path::Path::new("scene.ron"),
        )
        .unwrap()
        .scene;
        Arc::new(scene)
    }

    fn config(frames: usize, velocity: [f64; 6]) -> MovingCamera {
        MovingCamera::new(MovingCameraParams {
            frames: frames as u32,
            fps: 20.0,
            velocity,
            samples: 1,
            ..MovingCameraParams::default()
        })
        .unwrap()
    }

    fn ctx() -> RunContext {
        RunContext {
            node: "eye".into(),
            threads: 1,
            element: None,
        }
    }

    fn max_abs(m: &Matrix3<f64>) -> f64 {
        m.iter().fold(0.0f64, |a, &v| a.max(v.abs()))
    }

    fn rt(pose: &Pose) -> (Matrix3<f64>, Vector3<f64>) {
        (
            to_na(&pose.rotation_matrix()),
            Vector3::from(pose.translation),
        )
    }

    /// Camera centre `−Rᵀ t` and optical axis (third row of R) of a camera_from_world pose.
    fn centre_and_axis(pose: &Pose) -> (Vector3<f64>, Vector3<f64>) {
        let (r, t) = rt(pose);
        (-(r.transpose() * t), r.row(2).transpose())
    }

    #[test]
    fn se3_exp_of_a_pure_translation_is_that_translation() {
        let (r, t) = se3_exp([0.1, -0.2, 0.3, 0.0, 0.0, 0.0]);
        assert_eq!(r, Matrix3::identity());
        assert_eq!(t, Vector3::new(0.1, -0.2, 0.3));
    }

    #[test]
    fn se3_exp_of_a_rotation_about_z() {
        // 60° about z: R = [[c, −s, 0], [s, c, 0], [0, 0, 1]], c = 1/2, s = √3/2.
        let theta = std::f64::consts::FRAC_PI_3;
        let (r, t) = se3_exp([0.0, 0.0, 0.0, 0.0, 0.0, theta]);
        let s3 = 3f64.sqrt() / 2.0;
        let expected = Matrix3::new(0.5, -s3, 0.0, s3, 0.5, 0.0, 0.0, 0.0, 1.0);
        assert!(max_abs(&(r - expected)) < 1e-15, "{r}");
        assert_eq!(t, Vector3::zeros());
        // With vx = a the origin runs along a circle: t = (a sin θ/θ, a (1 − cos θ)/θ, 0);
        // for θ = π/2, (2a/π, 2a/π, 0).
        let a = 0.7;
        let half_pi = std::f64::consts::FRAC_PI_2;
        let (r, t) = se3_exp([a, 0.0, 0.0, 0.0, 0.0, half_pi]);
        let expected = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        assert!(max_abs(&(r - expected)) < 1e-15, "{r}");
        let arc = 2.0 * a / std::f64::consts::PI;
        assert!((t - Vector3::new(arc, arc, 0.0)).norm() < 1e-15, "{t}");
        // A screw: translation along the rotation axis is unchanged.
        let (_, t) = se3_exp([0.0, 0.0, 0.4, 0.0, 0.0, 1.3]);
        assert!((t - Vector3::new(0.0, 0.0, 0.4)).norm() < 1e-15, "{t}");
    }

    /// The exponential of the 4×4 twist matrix `[[K, v], [0, 0]]` by its Taylor series
    /// (40 terms: exact to rounding for |ξ| ≲ 2), an independent reference.
    fn series_exp(xi: [f64; 6]) -> (Matrix3<f64>, Vector3<f64>) {
        let mut a = nalgebra::Matrix4::<f64>::zeros();
        let k = skew(&Vector3::new(xi[3], xi[4], xi[5]));
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&k);
        a[(0, 3)] = xi[0];
        a[(1, 3)] = xi[1];
        a[(2, 3)] = xi[2];
        let mut sum = nalgebra::Matrix4::<f64>::identity();
        let mut term = nalgebra::Matrix4::<f64>::identity();
        for n in 1..40 {
            term = term * a / n as f64;
            sum += term;
        }
        (
            sum.fixed_view::<3, 3>(0, 0).into_owned(),
            sum.fixed_view::<3, 1>(0, 3).into_owned(),
        )
    }

    #[test]
    fn se3_exp_small_angles_are_exact_and_continuous() {
        // θ = 0: exactly the identity and the translation.
        let (r, t) = se3_exp([0.3, 0.2, 0.1, 0.0, 0.0, 0.0]);
        assert_eq!((r, t), (Matrix3::identity(), Vector3::new(0.3, 0.2, 0.1)));
        // Every angle, from tiny ones through both sides of the switch to the series, against
        // the series of the matrix exponential.
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        for theta in [
            1e-12,
            1e-9,
            1e-6,
            1e-4,
            1e-3,
            SMALL_ANGLE * (1.0 - 1e-12),
            SMALL_ANGLE,
            SMALL_ANGLE * (1.0 + 1e-12),
            0.1,
            1.0,
            2.0,
        ] {
            let w = axis * theta;
            let xi = [0.2, 0.1, -0.3, w.x, w.y, w.z];
            let (r, t) = se3_exp(xi);
            let (r_ref, t_ref) = series_exp(xi);
            assert!(
                max_abs(&(r - r_ref)) < 1e-15,
                "θ {theta}: {}",
                max_abs(&(r - r_ref))
            );
            assert!(
                (t - t_ref).norm() < 1e-15,
                "θ {theta}: {}",
                (t - t_ref).norm()
            );
        }
        // To first order in a tiny rotation: R = I + K, t = v + ½ ω × v.
        let v = Vector3::new(0.3, -0.2, 0.5);
        let w = Vector3::new(1e-7, 2e-7, -1e-7);
        let (r, t) = se3_exp([v.x, v.y, v.z, w.x, w.y, w.z]);
        assert!(max_abs(&(r - Matrix3::identity() - skew(&w))) < 1e-13);
        assert!((t - v - w.cross(&v) * 0.5).norm() < 1e-14);
        // The series agree with the closed forms where both are accurate.
        let theta: f64 = 0.009;
        let (a, b, c) = exp_coefficients(theta * theta);
        assert!((a - theta.sin() / theta).abs() < 4e-16);
        assert!((b - (1.0 - theta.cos()) / (theta * theta)).abs() < 1e-9);
        assert!((c - (theta - theta.sin()) / theta.powi(3)).abs() < 1e-7);
    }

    #[test]
    fn se3_exp_of_the_opposite_twist_is_the_inverse() {
        for xi in [
            [0.1, -0.2, 0.3, 0.4, -0.5, 0.6],
            [1.0, 2.0, -3.0, 2.0, 1.0, -0.5],
            [0.0, 0.5, 0.0, 1e-5, 0.0, -2e-5],
            [0.2, 0.0, 0.0, 0.0, 0.0, 3.0],
        ] {
            let (r1, t1) = se3_exp(xi);
            let (r2, t2) = se3_exp(xi.map(|x| -x));
            assert!(max_abs(&(r1 * r2 - Matrix3::identity())) < 1e-14, "{xi:?}");
            assert!((r1 * t2 + t1).norm() < 1e-14, "{xi:?}");
            // R is a rotation.
            assert!(max_abs(&(r1.transpose() * r1 - Matrix3::identity())) < 1e-14);
            assert!((r1.determinant() - 1.0).abs() < 1e-14);
        }
    }

    #[test]
    fn constant_forward_velocity_advances_along_the_optical_axis() {
        let (vz, dt) = (0.3, 1.0 / 20.0);
        let mut source =
            MovingCameraSource::new(scene(), config(30, [0.0, 0.0, vz, 0.0, 0.0, 0.0])).unwrap();
        let start = source.pose_at(0).unwrap();
        let (c0, axis0) = centre_and_axis(&start);
        for k in [1, 7, 29] {
            let pose = source.pose_at(k).unwrap();
            let (c, axis) = centre_and_axis(&pose);
            let expected = c0 + axis0 * (vz * k as f64 * dt);
            assert!(
                (c - expected).norm() < 1e-13,
                "frame {k}: {c} vs {expected}"
            );
            assert!((axis - axis0).norm() < 1e-13);
        }
    }

    #[test]
    fn constant_roll_rate_rotates_about_the_optical_axis() {
        let (wz, dt) = (0.5, 1.0 / 20.0);
        let mut source =
            MovingCameraSource::new(scene(), config(40, [0.0, 0.0, 0.0, 0.0, 0.0, wz])).unwrap();
        let start = source.pose_at(0).unwrap();
        let (c0, axis0) = centre_and_axis(&start);
        let (r0, _) = rt(&start);
        for k in [1, 10, 39] {
            let pose = source.pose_at(k).unwrap();
            let (c, axis) = centre_and_axis(&pose);
            let (r, _) = rt(&pose);
            assert!((c - c0).norm() < 1e-13, "frame {k}: the centre moved");
            assert!((axis - axis0).norm() < 1e-13, "frame {k}: the axis moved");
            let angle = rotation_angle_deg(&r0, &r).to_radians();
            assert!(
                (angle - wz * k as f64 * dt).abs() < 1e-12,
                "frame {k}: {angle}"
            );
            // Camera x turns toward camera y (ωz > 0 in a y-down frame): the new x axis,
            // in the old camera frame, is (cos, sin, 0).
            let x_in_old = r0 * r.row(0).transpose();
            let a = wz * k as f64 * dt;
            assert!((x_in_old - Vector3::new(a.cos(), a.sin(), 0.0)).norm() < 1e-12);
        }
    }

    #[test]
    fn frames_are_capture_render_at_each_pose() {
        let scene = scene();
        let xi = [0.2, -0.1, 0.3, 0.05, 0.1, -0.2];
        let mut source = MovingCameraSource::new(Arc::clone(&scene), config(12, xi)).unwrap();
        let params = CaptureRenderParams {
            renderer: Renderer::Rasterize,
            samples: 1,
            ..CaptureRenderParams::default()
        };
        for k in [0, 5, 11] {
            let frame = source.render(k).unwrap();
            let mut moved = (*scene).clone();
            moved.cameras[0].camera_from_world = frame.camera_from_world;
            let reference = render_frame(&moved, 0, &params).unwrap();
            assert_eq!(frame.color, reference.color, "frame {k}");
            assert_eq!(frame.depth, reference.depth, "frame {k}");
            if k == 0 {
                // Frame 0 is the scene camera itself.
                assert_eq!(frame.camera_from_world, scene.cameras[0].camera_from_world);
                assert_eq!(frame.color, render_frame(&scene, 0, &params).unwrap().color);
            } else {
                assert_ne!(frame.camera_from_world, scene.cameras[0].camera_from_world);
            }
        }
    }

    fn twist(xi: [f64; 6]) -> Value {
        Value::Matrix(Arc::new(Matrix::new(6, 1, xi.to_vec()).unwrap()))
    }

    #[test]
    fn feedback_changes_the_next_pose() {
        let ctx = ctx();
        let dt = 1.0 / 20.0;
        let mut fed = MovingCameraSource::new(scene(), config(5, [0.0; 6])).unwrap();
        let mut still = MovingCameraSource::new(scene(), config(5, [0.0; 6])).unwrap();
        let p0 = fed.pose_at(0).unwrap();
        let (c0, axis0) = centre_and_axis(&p0);
        fed.feed(&ctx, 1, "velocity", &twist([0.0, 0.0, 0.4, 0.0, 0.0, 0.0]))
            .unwrap();
        let p1 = fed.pose_at(1).unwrap();
        let (c1, _) = centre_and_axis(&p1);
        assert!((c1 - (c0 + axis0 * (0.4 * dt))).norm() < 1e-14);
        assert_eq!(
            still.pose_at(1).unwrap(),
            p0,
            "no feedback: the camera stays"
        );
        // The fed velocity stays in force until the next one.
        let (c2, _) = centre_and_axis(&fed.pose_at(2).unwrap());
        assert!((c2 - (c0 + axis0 * (0.8 * dt))).norm() < 1e-14);
        fed.feed(&ctx, 3, "velocity", &twist([0.0; 6])).unwrap();
        let (c3, _) = centre_and_axis(&fed.pose_at(3).unwrap());
        assert!((c3 - c2).norm() < 1e-15);
        // After feedback the path cannot be replayed.
        assert!(fed.pose_at(1).is_err());
        assert!(fed.pose_at(5).is_err());
    }

    #[test]
    fn bad_feedback_and_inputs_are_errors() {
        let ctx = ctx();
        let mut source = MovingCameraSource::new(scene(), config(5, [0.0; 6])).unwrap();
        let bad = [
            Value::Matrix(Arc::new(Matrix::new(3, 1, vec![0.0; 3]).unwrap())),
            Value::Matrix(Arc::new(Matrix::new(1, 6, vec![0.0; 6]).unwrap())),
            twist([0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0]),
            twist([0.0, 0.0, 0.0, f64::INFINITY, 0.0, 0.0]),
            Value::Scalar(1.0),
        ];
        for value in &bad {
            let e = source.feed(&ctx, 1, "velocity", value).unwrap_err();
            assert!(e.to_string().contains("velocity"), "{e}");
        }
        assert!(source.feed(&ctx, 1, "speed", &twist([0.0; 6])).is_err());
        // Rejected values leave the camera as it was.
        assert_eq!(source.pose_at(1).unwrap(), source.pose_at(0).unwrap());

        // A camera the scene does not have, a missing or mistyped scene.
        let op = MovingCamera::new(MovingCameraParams {
            camera: 2,
            ..MovingCameraParams::default()
        })
        .unwrap();
        let specs = MovingCamera::inputs();
        let values = [Some(Value::Scene(scene())), None];
        let inputs = Inputs::new(&specs, &values);
        assert!(op.run(&ctx, &inputs).is_err());
        assert!(matches!(op.frame_source(&ctx, &inputs), Some(Err(_))));
        let op = MovingCamera::new(MovingCameraParams::default()).unwrap();
        for values in [[None, None], [Some(Value::Scalar(1.0)), None]] {
            let inputs = Inputs::new(&specs, &values);
            assert!(op.run(&ctx, &inputs).is_err());
            assert!(matches!(op.frame_source(&ctx, &inputs), Some(Err(_))));
        }

        // Parameters.
        for params in [
            MovingCameraParams {
                frames: 0,
                ..MovingCameraParams::default()
            },
            MovingCameraParams {
                fps: 0.0,
                ..MovingCameraParams::default()
            },
            MovingCameraParams {
                fps: f64::NAN,
                ..MovingCameraParams::default()
            },
            MovingCameraParams {
                samples: 2,
                ..MovingCameraParams::default()
            },
            MovingCameraParams {
                velocity: [0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0],
                ..MovingCameraParams::default()
            },
        ] {
            assert!(MovingCamera::new(params).is_err());
        }
    }

    #[test]
    fn stream_source_frames_equal_the_batch_lists() {
        let ctx = ctx();
        let op = config(6, [0.1, 0.05, -0.2, 0.02, -0.03, 0.3]);
        let specs = MovingCamera::inputs();
        let values = [Some(Value::Scene(scene())), None];
        let inputs = Inputs::new(&specs, &values);
        let mut source = op.frame_source(&ctx, &inputs).unwrap().unwrap();
        assert_eq!(source.frames(), 6);
        assert_eq!(
            (0..3).map(|k| source.timestamp_us(k)).collect::<Vec<_>>(),
            [0, 50_000, 100_000]
        );
        let mut batch = op.run(&ctx, &inputs).unwrap();
        let mut statics = source.statics(&ctx).unwrap();
        let camera = statics.take("camera").unwrap();
        assert_eq!(batch.take("camera").as_ref(), Some(&camera));
        let Value::Camera(c) = camera else {
            panic!("camera is not a Camera")
        };
        assert_eq!((c.width, c.height), (64, 48));
        for name in ["frames", "depths", "poses"] {
            let Some(Value::List(list)) = batch.take(name) else {
                panic!("no list {name}");
            };
            assert_eq!(list.items.len(), 6);
            // Asked again from frame 0, the source replays the path (no feedback).
            for (k, item) in list.items.iter().enumerate() {
                let mut one = source.frame(&ctx, k).unwrap();
                assert_eq!(one.take(name).as_ref(), Some(item), "{name} {k}");
            }
        }
        assert!(source.frame(&ctx, 6).is_err());
        let specs_out = MovingCamera::outputs();
        for p in &specs_out {
            assert_eq!(p.per_frame, p.name != "camera", "{}", p.name);
        }
        let velocity = &MovingCamera::inputs()[1];
        assert!(velocity.feedback && velocity.optional);
    }
}
