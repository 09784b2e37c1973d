//! `render.mesh_scene`: a ready-to-render scene around one mesh — an orbit camera that frames
//! it, a key light and an ambient term — so a graph can look at what it built
//! (`… → mesh.simplify → render.mesh_scene → render.rasterize`) without writing a scene file.
//!
//! The camera sits on a sphere around `target` (default: the centre of the mesh's bounding
//! box) at azimuth/elevation about the world `up` axis, at the distance where the bounding
//! sphere about `target` fills the narrower field of view to `1 / margin`, the way a viewer's
//! "frame all" works (MeshLab, Blender's View Selected).

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Light, Material, Pose, Scene, SceneCamera, SceneObject, Shape, Value};

use super::raycast::LookAtCamera;
use super::scene::scene_camera_from_look_at;
use crate::mesh::halfedge::mesh_input;

params! {
    /// Parameters of `render.mesh_scene`.
    pub struct MeshSceneParams {
        /// Image width, pixels. Default 640.
        width: u32 = 640 => [min = 1, max = 16384],
        /// Image height, pixels. Default 480.
        height: u32 = 480 => [min = 1, max = 16384],
        /// Vertical field of view, degrees, in (0, 180). Default 40.
        fov_y_deg: f64 = 40.0 => [min = 0.0, max = 180.0, unit = "degrees"],
        /// Camera azimuth about `up`, degrees; 0 looks from the reference side (+z for a +y
        /// up axis, +x for +z up), 90 from `up × reference` (+x for +y up). Default 30.
        azimuth_deg: f64 = 30.0 => [unit = "degrees"],
        /// Camera elevation above the plane perpendicular to `up`, degrees, in (−90, 90).
        /// Default 20.
        elevation_deg: f64 = 20.0 => [min = -90.0, max = 90.0, unit = "degrees"],
        /// World up axis (any non-zero vector). Default +y.
        up: [f64; 3] = [0.0, 1.0, 0.0],
        /// Point the camera looks at, scene units; none: the centre of the bounding box.
        /// Default none.
        target: Option<[f64; 3]> = None => [unit = "scene units"],
        /// Bounding-sphere radius over half the narrower field of view (≥ 1; 1 touches the
        /// image border). Default 1.15.
        margin: f64 = 1.15 => [min = 1.0, max = 100.0],
        /// Camera distance from the target, scene units, instead of the framing distance (a
        /// fixed camera for a mesh that changes from frame to frame). Default none.
        distance: Option<f64> = None => [above = 0.0, unit = "scene units"],
        /// Surface albedo, linear RGB in [0, 1]. Default (0.8, 0.8, 0.8).
        albedo: [f64; 3] = [0.8, 0.8, 0.8],
        /// Key light azimuth relative to the camera's, degrees. Default −35 (to the left).
        light_azimuth_deg: f64 = -35.0 => [unit = "degrees"],
        /// Key light elevation, degrees, in [−90, 90]. Default 50.
        light_elevation_deg: f64 = 50.0 => [min = -90.0, max = 90.0, unit = "degrees"],
        /// Key light irradiance on a surface facing it, W·m⁻² (linear, all channels).
        /// Default 3.
        light_irradiance: f64 = 3.0 => [min = 0.0],
        /// Constant environment radiance (ambient), W·sr⁻¹·m⁻². Default 0.15.
        ambient: f64 = 0.15 => [min = 0.0],
    }
}

/// Unit vector, or `None` for zero/non-finite input.
fn unit(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (n > 0.0 && n.is_finite()).then(|| v.map(|c| c / n))
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The orthonormal frame `(reference, side, up)` of the orbit: `reference` is the first of +z,
/// +x, +y not within 30° of `up`, made perpendicular to it; `side = up × reference`.
pub fn orbit_frame(up: [f64; 3]) -> Option<[[f64; 3]; 3]> {
    let up = unit(up)?;
    let axis = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        .into_iter()
        .find(|a| dot(*a, up).abs() < 0.866)?;
    let d = dot(axis, up);
    let reference = unit([0, 1, 2].map(|k| axis[k] - d * up[k]))?;
    Some([reference, cross(up, reference), up])
}

/// The unit direction at `azimuth_deg`, `elevation_deg` in an orbit frame.
pub fn orbit_direction(frame: &[[f64; 3]; 3], azimuth_deg: f64, elevation_deg: f64) -> [f64; 3] {
    let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    let [r, s, u] = frame;
    [0, 1, 2].map(|k| el.cos() * (az.cos() * r[k] + az.sin() * s[k]) + el.sin() * u[k])
}

/// Target (bounding-box centre unless given) and bounding-sphere radius about it.
pub fn framing(positions: &[[f32; 3]], target: Option<[f64; 3]>) -> Option<([f64; 3], f64)> {
    if positions.is_empty() {
        return None;
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in positions {
        for k in 0..3 {
            let v = f64::from(p[k]);
            lo[k] = lo[k].min(v);
            hi[k] = hi[k].max(v);
        }
    }
    let centre = target.unwrap_or([0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k])));
    let radius = positions
        .iter()
        .map(|p| {
            let d = [0, 1, 2].map(|k| f64::from(p[k]) - centre[k]);
            dot(d, d).sqrt()
        })
        .fold(0.0, f64::max);
    (radius.is_finite() && centre.iter().all(|c| c.is_finite())).then_some((centre, radius))
}

/// The framing camera of `params` for a mesh with these positions.
pub fn framing_camera(
    positions: &[[f32; 3]],
    p: &MeshSceneParams,
) -> Result<(SceneCamera, [f64; 3]), String> {
    let frame = orbit_frame(p.up).ok_or("`up` must be a finite non-zero vector")?;
    let (target, radius) = framing(positions, p.target)
        .ok_or("the mesh has no vertices, or non-finite ones, to frame")?;
    // Half the narrower field of view: vertical, or horizontal for a portrait image.
    let half_y = 0.5 * p.fov_y_deg.to_radians();
    let aspect = f64::from(p.width) / f64::from(p.height);
    let half = half_y.min((half_y.tan() * aspect).atan());
    // A degenerate (single-point) mesh still gets a camera at a sensible distance.
    let radius = if radius > 0.0 {
        radius
    } else {
        1.0_f64.max(target.iter().fold(0.0, |m: f64, c| m.max(c.abs())) * 1e-6)
    };
    let distance = p.distance.unwrap_or(p.margin * radius / half.sin());
    let towards_eye = orbit_direction(&frame, p.azimuth_deg, p.elevation_deg);
    let eye = [0, 1, 2].map(|k| target[k] + distance * towards_eye[k]);
    // Straight up or down: the reference axis serves as the image's up.
    let image_up = if p.elevation_deg.abs() > 89.9 {
        frame[0]
    } else {
        frame[2]
    };
    let la = LookAtCamera::new(
        p.width as usize,
        p.height as usize,
        p.fov_y_deg,
        eye,
        target,
        image_up,
    )?;
    let to_light = orbit_direction(
        &frame,
        p.azimuth_deg + p.light_azimuth_deg,
        p.light_elevation_deg,
    );
    Ok((scene_camera_from_look_at(&la), to_light.map(|c| -c)))
}

/// `render.mesh_scene`. See the module documentation.
#[derive(Debug, Clone)]
pub struct MeshScene {
    params: MeshSceneParams,
}

impl Op for MeshScene {
    type Params = MeshSceneParams;
    const ID: &'static str = "render.mesh_scene";
    const SUMMARY: &'static str =
        "Wraps a mesh in a scene: a framing orbit camera, a key light and ambient light.";
    const DOC: &'static str = r#"
Builds a `Scene` holding `mesh` (one object, identity pose, a Lambert material of `albedo`),
one pinhole camera and two lights, ready for `render.rasterize` or `render.trace`.

The camera looks at `target` (default: the centre of the mesh's bounding box) from azimuth
`azimuth_deg` and elevation `elevation_deg` about the world `up` axis (azimuth 0 looks from +z
when up is +y, from +x when up is +z; positive azimuth turns towards up × that side), at the
distance where the bounding sphere about the target spans `1 / margin` of the narrower field of
view: the whole mesh is in the image from any direction. `fov_y_deg`, `width` and `height` set
the image; the principal point is the image centre, pixels square.

Lights: a directional key light from azimuth `azimuth_deg + light_azimuth_deg` and elevation
`light_elevation_deg` with irradiance `light_irradiance` (W·m⁻²), and a constant environment of
radiance `ambient` (the rasterizer's ambient term, the tracer's sky).

With a `scene` input, the mesh joins that scene: its objects, materials and lights are kept
(the key and ambient lights are added to them), its cameras are replaced by the orbit camera,
which still frames the mesh alone. `distance` fixes the camera distance instead of the framing
one, so a mesh that changes from frame to frame is seen by a camera that moves only when its
parameters do.

Errors: a mesh with no vertices or non-finite ones, a zero `up`, a field of view outside
(0, 180).

Example:
    "view": (op: "render.mesh_scene", inputs: { "mesh": "simplify.mesh" },
             params: (width: 320, height: 240, azimuth_deg: 30.0, elevation_deg: 20.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The triangle mesh to show."),
            PortSpec::new(
                "scene",
                PortType::Scene,
                "A stage around the mesh: its objects, materials and lights are kept, its cameras replaced.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "scene",
            PortType::Scene,
            "The mesh with a framing camera (index 0), a key light and ambient light.",
        )]
    }

    fn new(p: MeshSceneParams) -> Result<Self, String> {
        if !(p.fov_y_deg > 0.0 && p.fov_y_deg < 180.0) {
            return Err(format!(
                "`fov_y_deg` must be in (0, 180), got {}",
                p.fov_y_deg
            ));
        }
        if !(p.elevation_deg > -90.0 && p.elevation_deg < 90.0) {
            return Err(format!(
                "`elevation_deg` must be in (−90, 90), got {}",
                p.elevation_deg
            ));
        }
        if !(p.azimuth_deg.is_finite() && p.light_azimuth_deg.is_finite()) {
            return Err("`azimuth_deg` and `light_azimuth_deg` must be finite".into());
        }
        if !p.albedo.iter().all(|a| (0.0..=1.0).contains(a)) {
            return Err(format!(
                "`albedo` must lie in [0, 1] per channel, got {:?}",
                p.albedo
            ));
        }
        if !(p.light_irradiance.is_finite() && p.ambient.is_finite()) {
            return Err("`light_irradiance` and `ambient` must be finite".into());
        }
        if orbit_frame(p.up).is_none() {
            return Err("`up` must be a finite non-zero vector".into());
        }
        if let Some(t) = p.target
            && !t.iter().all(|c| c.is_finite())
        {
            return Err("`target` must be finite".into());
        }
        Ok(MeshScene { params: p })
    }
}

impl Operator for MeshScene {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = mesh_input(inputs, "mesh")?;
        let p = &self.params;
        let (camera, light_direction) =
            framing_camera(&mesh.positions, p).map_err(|e| OpError::input("mesh", e))?;
        let albedo = p.albedo.map(|a| a as f32);
        let stage = match inputs.get("scene") {
            Some(Value::Scene(s)) => Some(s),
            Some(other) => {
                return Err(OpError::input(
                    "scene",
                    format!("expected Scene, got {}", other.port_type()),
                ));
            }
            None => None,
        };
        let (mut materials, mut objects, mut lights) = match stage {
            Some(s) => (s.materials.clone(), s.objects.clone(), s.lights.clone()),
            None => (Vec::new(), Vec::new(), Vec::new()),
        };
        let material = u32::try_from(materials.len())
            .map_err(|_| OpError::input("scene", "too many materials"))?;
        materials.push(Material {
            name: "mesh".into(),
            albedo,
            ..Material::default()
        });
        objects.push(SceneObject {
            name: "mesh".into(),
            shape: Shape::Mesh(Arc::clone(mesh)),
            world_from_object: Pose::IDENTITY,
            scale: 1.0,
            material,
        });
        lights.push(Light::Directional {
            direction: light_direction,
            irradiance: [p.light_irradiance as f32; 3],
        });
        lights.push(Light::Environment {
            radiance: [p.ambient as f32; 3],
            map: None,
        });
        let scene = Scene {
            materials,
            objects,
            lights,
            cameras: vec![camera],
        };
        Ok(Outputs::new().with("scene", Value::Scene(Arc::new(scene))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::scene::View;

    fn params() -> MeshSceneParams {
        MeshSceneParams::default()
    }

    /// Corners of a box.
    fn box_corners(lo: [f32; 3], hi: [f32; 3]) -> Vec<[f32; 3]> {
        (0..8)
            .map(|i| {
                [
                    if i & 1 == 0 { lo[0] } else { hi[0] },
                    if i & 2 == 0 { lo[1] } else { hi[1] },
                    if i & 4 == 0 { lo[2] } else { hi[2] },
                ]
            })
            .collect()
    }

    #[test]
    fn orbit_frames_are_orthonormal_and_right_handed() {
        for up in [
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 2.0, -3.0],
            [0.0, 0.0, -5.0],
        ] {
            let [r, s, u] = orbit_frame(up).unwrap();
            for (a, b) in [(r, s), (s, u), (u, r)] {
                assert!(dot(a, b).abs() < 1e-12);
            }
            for a in [r, s, u] {
                assert!((dot(a, a) - 1.0).abs() < 1e-12);
            }
            let c = cross(r, s);
            assert!((dot(c, u) - 1.0).abs() < 1e-12, "right-handed");
        }
        // +y up: azimuth 0 looks from +z, azimuth 90 from +x, elevation 90 from +y.
        let f = orbit_frame([0.0, 1.0, 0.0]).unwrap();
        let near = |a: [f64; 3], b: [f64; 3]| (0..3).all(|k| (a[k] - b[k]).abs() < 1e-12);
        assert!(near(orbit_direction(&f, 0.0, 0.0), [0.0, 0.0, 1.0]));
        assert!(near(orbit_direction(&f, 90.0, 0.0), [1.0, 0.0, 0.0]));
        assert!(near(orbit_direction(&f, 17.0, 90.0), [0.0, 1.0, 0.0]));
        // +z up: azimuth 0 looks from +x.
        let f = orbit_frame([0.0, 0.0, 1.0]).unwrap();
        assert!(near(orbit_direction(&f, 0.0, 0.0), [1.0, 0.0, 0.0]));
        assert!(orbit_frame([0.0; 3]).is_none());
        assert!(orbit_frame([f64::NAN, 1.0, 0.0]).is_none());
    }

    #[test]
    fn the_camera_frames_the_whole_mesh_from_every_direction() {
        // A box far from the origin: every corner projects inside the image, the target
        // projects to the image centre, and with margin 1 the bounding sphere touches the
        // narrower image border.
        let pts = box_corners([1e3, 2e3 - 0.5, -7.0], [1e3 + 4.0, 2e3 + 0.5, -5.0]);
        for (w, h) in [(640, 480), (200, 400), (1, 1)] {
            for az in [-170.0, 0.0, 30.0, 95.0] {
                for el in [-80.0, 0.0, 20.0, 89.95] {
                    let p = MeshSceneParams {
                        width: w,
                        height: h,
                        azimuth_deg: az,
                        elevation_deg: el,
                        ..params()
                    };
                    let (camera, light) = framing_camera(&pts, &p).unwrap();
                    assert!((dot(light, light) - 1.0).abs() < 1e-12);
                    let view = View::new(&camera).unwrap();
                    let (target, _) = framing(&pts, None).unwrap();
                    let c = view.project(target).unwrap();
                    assert!((c[0] - 0.5 * (f64::from(w) - 1.0)).abs() < 1e-6);
                    assert!((c[1] - 0.5 * (f64::from(h) - 1.0)).abs() < 1e-6);
                    for q in &pts {
                        let q = q.map(f64::from);
                        let [u, v, z] = view.project(q).unwrap();
                        assert!(z > 0.0);
                        assert!(
                            u > -0.5 && u < f64::from(w) - 0.5,
                            "{w}×{h} {az} {el}: u {u}"
                        );
                        assert!(
                            v > -0.5 && v < f64::from(h) - 0.5,
                            "{w}×{h} {az} {el}: v {v}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn distance_follows_the_margin_and_the_narrower_field_of_view() {
        // Two points ±1 along x about the origin: radius 1; distance = margin / sin(half fov).
        let pts = vec![[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let p = MeshSceneParams {
            margin: 2.0,
            fov_y_deg: 60.0,
            width: 100,
            height: 100,
            azimuth_deg: 0.0,
            elevation_deg: 0.0,
            ..params()
        };
        let (camera, _) = framing_camera(&pts, &p).unwrap();
        let view = View::new(&camera).unwrap();
        assert!((view.eye[2] - 2.0 / 30f64.to_radians().sin()).abs() < 1e-9);
        assert!(view.eye[0].abs() < 1e-12 && view.eye[1].abs() < 1e-12);
        // Portrait: the horizontal half-angle is narrower and sets the distance.
        let p = MeshSceneParams { width: 50, ..p };
        let (camera, _) = framing_camera(&pts, &p).unwrap();
        let view = View::new(&camera).unwrap();
        let half_x = (30f64.to_radians().tan() * 0.5).atan();
        assert!((view.eye[2] - 2.0 / half_x.sin()).abs() < 1e-9);
    }

    #[test]
    fn bad_parameters_and_meshes_are_errors() {
        assert!(
            MeshScene::new(MeshSceneParams {
                fov_y_deg: 180.0,
                ..params()
            })
            .is_err()
        );
        assert!(
            MeshScene::new(MeshSceneParams {
                elevation_deg: 90.0,
                ..params()
            })
            .is_err()
        );
        assert!(
            MeshScene::new(MeshSceneParams {
                up: [0.0; 3],
                ..params()
            })
            .is_err()
        );
        assert!(
            MeshScene::new(MeshSceneParams {
                albedo: [1.5, 0.0, 0.0],
                ..params()
            })
            .is_err()
        );
        assert!(
            MeshScene::new(MeshSceneParams {
                target: Some([f64::NAN; 3]),
                ..params()
            })
            .is_err()
        );
        assert!(framing_camera(&[], &params()).is_err());
        assert!(framing_camera(&[[f32::INFINITY, 0.0, 0.0]], &params()).is_err());
        // One point: still a camera, looking at it.
        let (camera, _) = framing_camera(&[[3.0, 4.0, 5.0]], &params()).unwrap();
        let view = View::new(&camera).unwrap();
        assert!(view.project([3.0, 4.0, 5.0]).is_some());
    }
}
