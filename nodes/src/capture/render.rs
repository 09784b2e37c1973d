//! `capture.render`: a capture source that renders every camera of a [`Scene`] and yields the
//! images together with their exact cameras and poses (and depth) — ground truth for stereo,
//! structure from motion and bundle adjustment.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Scene, Value};
use ocellus_engine::{param_enum, params};

use crate::render::raster::{Cull, RasterOptions, RasterOutput, SceneRaster, rasterize};
use crate::render::scene::View;
use crate::render::trace::{Integrator, TraceOptions, trace_scene};

param_enum! {
    /// Which renderer draws the frames.
    pub enum Renderer {
        /// render.rasterize: fast, shadow maps, no interreflection.
        Rasterize = "rasterize",
        /// render.trace with the path integrator: global illumination, seeded noise.
        Trace = "trace",
    }
}

params! {
    /// Parameters of [`CaptureRender`].
    pub struct CaptureRenderParams {
        /// `rasterize` (default) or `trace`.
        renderer: Renderer = Renderer::Rasterize,
        /// Rasterizer samples per pixel, 1 or 4 (rotated-grid MSAA); used with `rasterize`.
        samples: u32 = 4,
        /// Path-tracer samples per pixel, 1..=65536; used with `trace`.
        spp: u32 = 16,
        /// Seed of the path tracer's random streams (camera `i` uses `seed + i`); used with
        /// `trace`.
        seed: u64 = 0,
    }
}

/// One rendered frame: colour (RGB f32) and depth (gray f32).
pub struct Frame {
    /// Linear RGB radiance.
    pub color: Image,
    /// Distance along each pixel-centre unit ray, +∞ on a miss.
    pub depth: Image,
}

fn image(width: usize, height: usize, channels: Channels, data: Vec<f32>) -> Result<Image, String> {
    Image::new(width, height, channels, PixelData::F32(data)).map_err(|e| e.to_string())
}

/// The rasterizer's settings for `capture.render`.
fn raster_options(params: &CaptureRenderParams) -> RasterOptions {
    RasterOptions {
        cull: Cull::None,
        samples: params.samples,
        ..RasterOptions::default()
    }
}

/// A rasterized view as a frame.
fn raster_frame(out: RasterOutput) -> Result<Frame, String> {
    Ok(Frame {
        color: image(out.width, out.height, Channels::Rgb, out.color)?,
        depth: image(out.width, out.height, Channels::Gray, out.depth)?,
    })
}

/// Renders camera `camera` of `scene` with the chosen renderer.
pub fn render_frame(
    scene: &Scene,
    camera: usize,
    params: &CaptureRenderParams,
) -> Result<Frame, String> {
    match params.renderer {
        Renderer::Rasterize => raster_frame(rasterize(scene, camera, &raster_options(params))?),
        Renderer::Trace => {
            let options = TraceOptions {
                integrator: Integrator::Path,
                spp: params.spp,
                seed: params.seed.wrapping_add(camera as u64),
                ..TraceOptions::default()
            };
            let out = trace_scene(scene, camera, [0.0; 3], &options)?;
            Ok(Frame {
                color: image(out.width, out.height, Channels::Rgb, out.color)?,
                depth: image(out.width, out.height, Channels::Gray, out.depth)?,
            })
        }
    }
}

/// Every camera of `scene` in order, as [`render_frame`] renders each; the rasterizer prepares
/// the scene (textures, shadow maps, environment) once for all cameras. An error names the
/// camera it came from (scene-wide problems are reported at camera 0).
pub fn render_frames(
    scene: &Scene,
    params: &CaptureRenderParams,
) -> Result<Vec<Frame>, (usize, String)> {
    if params.renderer != Renderer::Rasterize || scene.cameras.is_empty() {
        return (0..scene.cameras.len())
            .map(|i| render_frame(scene, i, params).map_err(|e| (i, e)))
            .collect();
    }
    let prepared = SceneRaster::new(scene, &raster_options(params)).map_err(|e| (0, e))?;
    scene
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            View::new(c)
                .and_then(|view| prepared.render(&view))
                .and_then(raster_frame)
                .map_err(|e| (i, e))
        })
        .collect()
}

/// `capture.render`. See [`render_frame`].
pub struct CaptureRender {
    params: CaptureRenderParams,
}

impl Op for CaptureRender {
    type Params = CaptureRenderParams;
    const ID: &'static str = "capture.render";
    const SUMMARY: &'static str =
        "Render every camera of a scene: images with their exact cameras, poses and depth.";
    const DOC: &'static str = r#"
A capture source backed by the renderers: for each camera of `scene`, in order, renders a
linear RGB f32 image (render.rasterize with `samples`, or render.trace's path integrator with
`spp` and seed `seed + i` for camera i) and its depth map (distance along each pixel-centre
unit ray, +inf on a miss), and outputs them with the cameras' intrinsics and
camera_from_world poses — exact ground truth for stereo, SfM and bundle adjustment tests.
Pixel centres are at integer coordinates, as everywhere in Ocellus. Convert the images to
gray or u8 with the filter family's conversions when a detector needs them.

Example:
    "shots": (op: "capture.render", inputs: { "scene": "scene.scene" }, params: (renderer: "rasterize")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "scene",
            PortType::Scene,
            "The scene; one frame per camera.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "images",
                PortType::Image.list_of(),
                "Colour per camera, RGB f32.",
            ),
            PortSpec::new(
                "depths",
                PortType::Image.list_of(),
                "Depth per camera, gray f32.",
            ),
            PortSpec::new(
                "cameras",
                PortType::Camera.list_of(),
                "Intrinsics per camera.",
            ),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "camera_from_world per camera.",
            ),
        ]
    }

    fn new(params: CaptureRenderParams) -> Result<Self, String> {
        if params.samples != 1 && params.samples != 4 {
            return Err(format!("`samples` must be 1 or 4, got {}", params.samples));
        }
        if !(1..=65_536).contains(&params.spp) {
            return Err(format!("`spp` must be 1..=65536, got {}", params.spp));
        }
        Ok(CaptureRender { params })
    }
}

impl Operator for CaptureRender {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let scene = match inputs.require("scene")? {
            Value::Scene(s) => s,
            other => {
                return Err(OpError::input(
                    "scene",
                    format!("expected Scene, got {}", other.port_type()),
                ));
            }
        };
        let mut images = Vec::with_capacity(scene.cameras.len());
        let mut depths = Vec::with_capacity(scene.cameras.len());
        let frames = render_frames(scene, &self.params)
            .map_err(|(i, e)| OpError::failed(format!("camera {i}: {e}")))?;
        for frame in frames {
            images.push(Value::image(frame.color));
            depths.push(Value::image(frame.depth));
        }
        let cameras = scene
            .cameras
            .iter()
            .map(|c| Value::Camera(Arc::new(c.camera.clone())))
            .collect();
        let poses = scene
            .cameras
            .iter()
            .map(|c| Value::Pose(c.camera_from_world))
            .collect();
        Ok(Outputs::new()
            .with("images", Value::list(PortType::Image, images))
            .with("depths", Value::list(PortType::Image, depths))
            .with("cameras", Value::list(PortType::Camera, cameras))
            .with("poses", Value::list(PortType::Pose, poses)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::read_scene::parse_scene;
    use crate::render::scene::View;

    /// Rendering all cameras from one prepared scene gives each camera's frame bit for bit as
    /// rendering it alone (textured materials, a shadow-mapped light, an environment).
    #[test]
    fn shared_preparation_equals_one_camera_at_a_time() {
        let scene = parse_scene(
            r#"(materials: [(name: "noise", shading: lambert,
                    albedo_texture: Some((noise: (cells: 16, size: 128, octaves: 2, seed: 3,
                        a: (0.9, 0.8, 0.7), b: (0.1, 0.2, 0.3)), filter: anisotropic)))],
                objects: [
                    (shape: Plane(point: (0, 0, 0), normal: (0, 1, 0), half_extent: 2.0), material: "noise"),
                    (shape: Sphere(center: (0.3, 0.5, 0), radius: 0.5), material: "noise")],
                lights: [Directional(direction: (0.3, -1.0, -0.4), irradiance: (2, 2, 2)),
                         Environment(radiance: (0.5, 0.5, 0.5))],
                cameras: [(width: 48, height: 32, eye: (0, 1.5, 3), target: (0, 0.3, 0)),
                          (width: 40, height: 40, eye: (3, 1, 2), target: (0, 0.3, 0)),
                          (width: 24, height: 30, eye: (-2, 2, -1), target: (0, 0.3, 0))])"#,
            std::path::Path::new("scene.ron"),
        )
        .unwrap()
        .scene;
        let params = CaptureRenderParams {
            renderer: Renderer::Rasterize,
            samples: 4,
            spp: 1,
            seed: 0,
        };
        let frames = render_frames(&scene, &params).unwrap();
        assert_eq!(frames.len(), 3);
        for (i, frame) in frames.iter().enumerate() {
            let alone = render_frame(&scene, i, &params).unwrap();
            assert_eq!(frame.color.as_f32(), alone.color.as_f32(), "camera {i}");
            assert_eq!(frame.depth.as_f32(), alone.depth.as_f32(), "camera {i}");
        }
        // The scene is textured and lit: the frames are not uniform.
        let c = frames[0].color.as_f32().unwrap();
        assert!(c.iter().any(|&v| (v - c[c.len() / 2]).abs() > 0.05));
    }

    /// Rendered frames come with cameras that project the scene where it appears: the
    /// sphere's centre projects to the centre of its image disk, and the depth at that pixel
    /// is the distance to the sphere's near side.
    #[test]
    fn frames_carry_their_exact_cameras() {
        let scene = parse_scene(
            r#"(objects: [(shape: Sphere(center: (0.3, 0.2, 0), radius: 0.5))],
                lights: [Environment(radiance: (1, 1, 1))],
                cameras: [(width: 64, height: 48, eye: (0, 0, 4)), (width: 40, height: 40, eye: (3, 1, 2))])"#,
            std::path::Path::new("scene.ron"),
        )
        .unwrap()
        .scene;
        for renderer in [Renderer::Rasterize, Renderer::Trace] {
            let params = CaptureRenderParams {
                renderer,
                samples: 1,
                spp: 1,
                seed: 0,
            };
            for (i, c) in scene.cameras.iter().enumerate() {
                let frame = render_frame(&scene, i, &params).unwrap();
                let view = View::new(c).unwrap();
                let [u, v, _] = view.project([0.3, 0.2, 0.0]).unwrap();
                let (x, y) = (u.round() as usize, v.round() as usize);
                let depth = frame.depth.as_f32().unwrap()[y * view.width + x];
                // The ray through pixel (x, y) hits the sphere at the analytic distance.
                let d = view.ray_direction(x as f64, y as f64);
                let oc = [0, 1, 2].map(|k| view.eye[k] - [0.3, 0.2, 0.0][k]);
                let b: f64 = (0..3).map(|k| oc[k] * d[k]).sum();
                let cc: f64 = (0..3).map(|k| oc[k] * oc[k]).sum::<f64>() - 0.25;
                let t = -b - (b * b - cc).sqrt();
                assert!(
                    (f64::from(depth) - t).abs() < 1e-4 * t,
                    "{renderer:?} camera {i}: {depth} vs {t}"
                );
                // A corner pixel misses.
                assert!(frame.depth.as_f32().unwrap()[0].is_infinite());
            }
        }
    }
}
