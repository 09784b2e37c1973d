//! `render.points`: a point cloud drawn as z-buffered splats, from an orbit camera that frames it
//! or from a camera flying along a reconstruction's capture path — how a graph looks at a
//! sparse or dense reconstruction (Open3D's and COLMAP's point views).
//!
//! The algorithm is [`render_points`]; [`RenderPoints`] is the thin operator.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, PointCloud, Pose, Reconstruction, Value};
use ocellus_engine::{param_enum, params};

use super::mesh_scene::{orbit_direction, orbit_frame};

param_enum! {
    /// Where the camera is.
    pub enum PointView {
        /// On a sphere around the cloud, framing it.
        Orbit = "orbit",
        /// On the capture path of the `path` reconstruction, at parameter `t`.
        Path = "path",
    }
}

params! {
    /// Parameters of `render.points`.
    pub struct RenderPointsParams {
        /// Image width, px (1..=8192).
        width: u32 = 480 => [min = 1, max = 8192, unit = "px"],
        /// Image height, px (1..=8192).
        height: u32 = 360 => [min = 1, max = 8192, unit = "px"],
        /// Vertical field of view, degrees, in (0, 180).
        fov_y_deg: f64 = 50.0 => [min = 0.0, max = 180.0, unit = "degrees"],
        /// "orbit" (around the cloud) or "path" (along the `path` reconstruction's cameras).
        view: PointView = PointView::Orbit,
        /// Orbit: azimuth about `up`, degrees (as `render.mesh_scene`).
        azimuth_deg: f64 = 30.0 => [unit = "degrees"],
        /// Orbit: elevation above the plane perpendicular to `up`, degrees, in [−89, 89].
        elevation_deg: f64 = 20.0 => [min = -89.0, max = 89.0, unit = "degrees"],
        /// Orbit: the world's up axis (a reconstruction in OpenCV camera axes has up = −y).
        up: [f64; 3] = [0.0, 1.0, 0.0],
        /// Orbit: the robust radius of the cloud fills the narrower half field of view to
        /// 1 / margin (> 0).
        margin: f64 = 1.2 => [above = 0.0],
        /// Path: position along the capture path, 0 (first registered image) to 1 (last).
        t: f64 = 0.0 => [min = 0.0, max = 1.0],
        /// Path: the camera backs away from the path along its viewing direction by this many
        /// robust cloud radii (0: the capture cameras' own viewpoints).
        back_off: f64 = 0.0 => [min = 0.0],
        /// Splat radius, px (the disc drawn for every point, whatever its depth).
        point_radius_px: f64 = 1.5 => [min = 0.0, max = 64.0, unit = "px"],
        /// Background colour, sRGB in [0, 1].
        background: [f64; 3] = [0.08, 0.09, 0.11],
    }
}

/// The point renderer (`render.points`). See [`render_points`].
#[derive(Debug, Clone, PartialEq)]
pub struct RenderPoints {
    params: RenderPointsParams,
}

impl Op for RenderPoints {
    type Params = RenderPointsParams;
    const ID: &'static str = "render.points";
    const SUMMARY: &'static str = "Draws a point cloud as z-buffered splats from an orbit camera or along a reconstruction's capture path.";
    const DOC: &'static str = r#"
Projects every point through a pinhole camera (fov `fov_y_deg`, centred principal point) and
draws it as a disc of `point_radius_px` with a z-buffer: the nearest point wins each pixel, and
of equally near points the first, so the image does not depend on the thread count. Points keep
their colours (sRGB); a cloud without colours is drawn light grey, darker with depth.

The camera:
- "orbit": on a sphere around the cloud's robust centre (the per-axis median) at `azimuth_deg`
  and `elevation_deg` about `up`, at the distance where the robust radius (the 90th percentile
  of the points' distances to the centre: stray points do not shrink the view) fills the
  narrower half field of view to 1 / `margin`.
- "path": along the capture path of the `path` reconstruction: its registered images sorted by
  id, the camera centre on the Catmull–Rom spline through their centres and the orientation
  slerped between theirs, at parameter `t` (0 = first image, 1 = last); `back_off` moves the
  camera back along its viewing direction by that many robust radii. An animation track on `t`
  flies through the reconstruction (`graphs/tour.ron`).

Outputs: `image` (RGB u8), `depth` (f32, the camera-z of the drawn point, +inf where none) and
`metrics`: points, drawn (in front of the camera and inside the image), coverage (share of
pixels drawn), radius (the robust radius, scene units).

Example:
    "view": (op: "render.points", inputs: { "points": "cloud.points" },
             params: (azimuth_deg: 40, elevation_deg: 25, point_radius_px: 2)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("points", PortType::PointCloud, "The points to draw."),
            PortSpec::new(
                "path",
                PortType::Reconstruction,
                "For view \"path\": the reconstruction whose cameras give the path.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "RGB u8 rendering."),
            PortSpec::new(
                "depth",
                PortType::Image,
                "f32 camera-z of the drawn point, +inf where none.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "points, drawn, coverage, radius.",
            ),
        ]
    }

    fn new(params: RenderPointsParams) -> Result<Self, String> {
        if orbit_frame(params.up).is_none() {
            return Err("`up` must be a finite non-zero vector".into());
        }
        if !(params.fov_y_deg > 0.0 && params.fov_y_deg < 180.0) {
            return Err(format!(
                "`fov_y_deg` must be in (0, 180), got {}",
                params.fov_y_deg
            ));
        }
        if params.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return Err("`background` must be three numbers in [0, 1]".into());
        }
        Ok(RenderPoints { params })
    }
}

impl Operator for RenderPoints {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = match inputs.require("points")? {
            Value::PointCloud(c) => Arc::clone(c),
            other => {
                return Err(OpError::input(
                    "points",
                    format!("expected PointCloud, got {}", other.port_type()),
                ));
            }
        };
        let path = match inputs.get("path") {
            Some(Value::Reconstruction(r)) => Some(Arc::clone(r)),
            Some(other) => {
                return Err(OpError::input(
                    "path",
                    format!("expected Reconstruction, got {}", other.port_type()),
                ));
            }
            None => None,
        };
        let p = &self.params;
        let (center, radius) = robust_frame(&cloud.positions)
            .ok_or_else(|| OpError::input("points", "no finite points to frame"))?;
        let camera = match p.view {
            PointView::Orbit => {
                let frame = orbit_frame(p.up)
                    .ok_or_else(|| OpError::failed("`up` must be a finite non-zero vector"))?;
                let half_y = 0.5 * p.fov_y_deg.to_radians();
                let aspect = f64::from(p.width) / f64::from(p.height);
                let half = half_y.min((half_y.tan() * aspect).atan());
                let distance = p.margin * radius / half.sin();
                let towards_eye = orbit_direction(&frame, p.azimuth_deg, p.elevation_deg);
                let eye = [0, 1, 2].map(|k| center[k] + distance * towards_eye[k]);
                look_at(eye, center, p.up)
                    .ok_or_else(|| OpError::failed("the view direction is parallel to `up`"))?
            }
            PointView::Path => {
                let Some(rec) = path else {
                    return Err(OpError::input(
                        "path",
                        "view \"path\" needs a reconstruction connected to `path`",
                    ));
                };
                let (rotation, centre) =
                    path_camera(&rec, p.t).map_err(|e| OpError::input("path", e))?;
                let back = p.back_off * radius;
                let forward = [rotation[6], rotation[7], rotation[8]];
                let eye = [0, 1, 2].map(|k| centre[k] - back * forward[k]);
                camera_from(rotation, eye)
            }
        };
        let view = PointCamera {
            width: p.width as usize,
            height: p.height as usize,
            fov_y_deg: p.fov_y_deg,
            camera_from_world: camera,
        };
        let out = render_points(&cloud, &view, p.point_radius_px, p.background);
        let image = Image::from_u8(view.width, view.height, Channels::Rgb, out.rgb)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let depth = Image::from_f32(view.width, view.height, Channels::Gray, out.depth)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let mut metrics = Metrics::new();
        metrics.insert("points".into(), cloud.positions.len() as f64);
        metrics.insert("drawn".into(), out.drawn as f64);
        metrics.insert("coverage".into(), out.coverage);
        metrics.insert("radius".into(), radius);
        Ok(Outputs::new()
            .with("image", Value::image(image))
            .with("depth", Value::image(depth))
            .with("metrics", Value::metrics(metrics)))
    }
}

/// Robust centre (per-axis median) and radius (90th percentile of distances to it) of the
/// finite points; None without any. A radius of 0 (one point) becomes 1.
pub fn robust_frame(positions: &[[f32; 3]]) -> Option<([f64; 3], f64)> {
    let finite: Vec<[f64; 3]> = positions
        .iter()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .map(|p| p.map(f64::from))
        .collect();
    if finite.is_empty() {
        return None;
    }
    let median = |k: usize| {
        let mut v: Vec<f64> = finite.iter().map(|p| p[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let center = [median(0), median(1), median(2)];
    let mut d: Vec<f64> = finite
        .iter()
        .map(|p| {
            ((p[0] - center[0]).powi(2) + (p[1] - center[1]).powi(2) + (p[2] - center[2]).powi(2))
                .sqrt()
        })
        .collect();
    d.sort_by(f64::total_cmp);
    let radius = d[((d.len() - 1) as f64 * 0.9).round() as usize];
    Some((center, if radius > 0.0 { radius } else { 1.0 }))
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn unit(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (n > 1e-300 && n.is_finite()).then(|| v.map(|x| x / n))
}

/// `camera_from_world` of a rotation (rows: image right, image down, forward) and a centre.
fn camera_from(rotation: [f64; 9], eye: [f64; 3]) -> Pose {
    let t = [0, 1, 2].map(|i| {
        -(rotation[3 * i] * eye[0] + rotation[3 * i + 1] * eye[1] + rotation[3 * i + 2] * eye[2])
    });
    Pose::from_rotation_matrix(&rotation, t)
}

/// The OpenCV-axes camera (x right, y down, z forward) at `eye` looking at `target`, `up`
/// pointing up in the image.
pub fn look_at(eye: [f64; 3], target: [f64; 3], up: [f64; 3]) -> Option<Pose> {
    let forward = unit([0, 1, 2].map(|k| target[k] - eye[k]))?;
    let right = unit(cross(forward, up))?;
    let down = cross(forward, right);
    Some(camera_from(
        [
            right[0], right[1], right[2], down[0], down[1], down[2], forward[0], forward[1],
            forward[2],
        ],
        eye,
    ))
}

/// Rotation (row-major, camera_from_world) and centre of the capture path at `t` ∈ [0, 1]:
/// the registered images by id, Catmull–Rom through the centres, slerp between rotations.
pub fn path_camera(rec: &Reconstruction, t: f64) -> Result<([f64; 9], [f64; 3]), String> {
    let mut images: Vec<_> = rec.images.iter().collect();
    images.sort_by_key(|i| i.id);
    if images.is_empty() {
        return Err("the reconstruction has no registered images".into());
    }
    let poses: Vec<([f64; 4], [f64; 3])> = images
        .iter()
        .map(|i| {
            let pose = &i.camera_from_world;
            let r = pose.rotation_matrix();
            let tr = pose.translation;
            // C = −Rᵀ t.
            let c = [0, 1, 2].map(|k| -(r[k] * tr[0] + r[3 + k] * tr[1] + r[6 + k] * tr[2]));
            (pose.rotation, c)
        })
        .collect();
    if poses
        .iter()
        .any(|(q, c)| q.iter().chain(c).any(|v| !v.is_finite()))
    {
        return Err("a registered image has a non-finite pose".into());
    }
    let s = t.clamp(0.0, 1.0) * (poses.len() - 1) as f64;
    let k = (s.floor() as usize).min(poses.len().saturating_sub(2));
    let f = if poses.len() == 1 { 0.0 } else { s - k as f64 };
    let at = |i: isize| poses[i.clamp(0, poses.len() as isize - 1) as usize].1;
    let (p0, p1, p2, p3) = (
        at(k as isize - 1),
        at(k as isize),
        at(k as isize + 1),
        at(k as isize + 2),
    );
    let centre = [0, 1, 2].map(|d| {
        0.5 * (2.0 * p1[d]
            + (-p0[d] + p2[d]) * f
            + (2.0 * p0[d] - 5.0 * p1[d] + 4.0 * p2[d] - p3[d]) * f * f
            + (-p0[d] + 3.0 * p1[d] - 3.0 * p2[d] + p3[d]) * f * f * f)
    });
    let q0 = poses[k].0;
    let q1 = poses[(k + 1).min(poses.len() - 1)].0;
    let pose = Pose {
        rotation: ocellus_engine::curves::slerp(q0, q1, f),
        translation: [0.0; 3],
    };
    Ok((pose.rotation_matrix(), centre))
}

/// A pinhole camera for [`render_points`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointCamera {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Vertical field of view, degrees.
    pub fov_y_deg: f64,
    /// World → camera (x right, y down, z forward).
    pub camera_from_world: Pose,
}

/// The result of [`render_points`].
#[derive(Debug, Clone, PartialEq)]
pub struct PointImage {
    /// RGB u8, row-major.
    pub rgb: Vec<u8>,
    /// Camera z of the drawn point, +inf where none.
    pub depth: Vec<f32>,
    /// Points in front of the camera whose centre falls inside the image.
    pub drawn: usize,
    /// Share of pixels drawn.
    pub coverage: f64,
}

/// Draws `cloud` as discs of `radius_px` seen by `camera` (see `render.points`).
pub fn render_points(
    cloud: &PointCloud,
    camera: &PointCamera,
    radius_px: f64,
    background: [f64; 3],
) -> PointImage {
    let (w, h) = (camera.width, camera.height);
    let f = 0.5 * h as f64 / (0.5 * camera.fov_y_deg.to_radians()).tan();
    let (cx, cy) = (0.5 * w as f64 - 0.5, 0.5 * h as f64 - 0.5);
    let r = camera.camera_from_world.rotation_matrix();
    let t = camera.camera_from_world.translation;
    // Camera-space points in front of the camera, with their index.
    let mut depth = vec![f32::INFINITY; w * h];
    let mut owner = vec![u32::MAX; w * h];
    let mut z_range = (f64::INFINITY, f64::NEG_INFINITY);
    let mut projected = Vec::with_capacity(cloud.positions.len());
    for (i, p) in cloud.positions.iter().enumerate() {
        let p = p.map(f64::from);
        let x = r[0] * p[0] + r[1] * p[1] + r[2] * p[2] + t[0];
        let y = r[3] * p[0] + r[4] * p[1] + r[5] * p[2] + t[1];
        let z = r[6] * p[0] + r[7] * p[1] + r[8] * p[2] + t[2];
        if !(z > 1e-9 && x.is_finite() && y.is_finite() && z.is_finite()) {
            continue;
        }
        let (u, v) = (f * x / z + cx, f * y / z + cy);
        if u < -0.5 || v < -0.5 || u >= w as f64 - 0.5 || v >= h as f64 - 0.5 {
            continue;
        }
        z_range = (z_range.0.min(z), z_range.1.max(z));
        projected.push((i, u, v, z));
    }
    let reach = radius_px.ceil() as i64;
    let r2 = radius_px * radius_px;
    for &(i, u, v, z) in &projected {
        let (pu, pv) = (u.round() as i64, v.round() as i64);
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let (x, y) = (pu + dx, pv + dy);
                if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                    continue;
                }
                let (ex, ey) = (x as f64 - u, y as f64 - v);
                // The pixel nearest the centre always; the others inside the disc.
                if (dx, dy) != (0, 0) && ex * ex + ey * ey > r2 {
                    continue;
                }
                let k = y as usize * w + x as usize;
                let zf = z as f32;
                if zf < depth[k] {
                    depth[k] = zf;
                    owner[k] = i as u32;
                }
            }
        }
    }
    let background = background.map(|c| (c * 255.0).round() as u8);
    let mut rgb = Vec::with_capacity(w * h * 3);
    let mut covered = 0usize;
    for (k, &o) in owner.iter().enumerate() {
        if o == u32::MAX {
            rgb.extend_from_slice(&background);
            continue;
        }
        covered += 1;
        let colour = match &cloud.colors {
            Some(c) => c[o as usize],
            None => {
                let span = (z_range.1 - z_range.0).max(1e-12);
                let near = 1.0 - 0.6 * (f64::from(depth[k]) - z_range.0) / span;
                let g = (215.0 * near).round() as u8;
                [g, g, g]
            }
        };
        rgb.extend_from_slice(&colour);
    }
    PointImage {
        rgb,
        depth,
        drawn: projected.len(),
        coverage: covered as f64 / (w * h) as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::ReconImage;

    fn cloud(points: Vec<[f32; 3]>, colors: Option<Vec<[u8; 3]>>) -> PointCloud {
        PointCloud {
            positions: points,
            colors,
            normals: None,
        }
    }

    fn camera(pose: Pose) -> PointCamera {
        PointCamera {
            width: 64,
            height: 48,
            fov_y_deg: 60.0,
            camera_from_world: pose,
        }
    }

    /// A point on the optical axis lands on the image centre, one to the right (+x) and down
    /// (+y) lands right of and below it by f·x/z.
    #[test]
    fn points_project_like_a_pinhole() {
        let pose = Pose::IDENTITY;
        let f = 24.0 / (30.0f64.to_radians()).tan();
        let c = cloud(
            vec![[0.0, 0.0, 2.0], [0.5, 0.25, 2.0], [0.0, 0.0, -1.0]],
            Some(vec![[255, 0, 0], [0, 255, 0], [0, 0, 255]]),
        );
        let out = render_points(&c, &camera(pose), 0.0, [0.0; 3]);
        assert_eq!(out.drawn, 2, "the point behind is not drawn");
        let at = |x: usize, y: usize| &out.rgb[(y * 64 + x) * 3..][..3];
        // Centre (31.5, 23.5) rounds to (32, 24).
        assert_eq!(at(32, 24), [255, 0, 0]);
        let (u, v) = (f * 0.25 + 31.5, f * 0.125 + 23.5);
        assert_eq!(at(u.round() as usize, v.round() as usize), [0, 255, 0]);
        assert_eq!(out.depth[24 * 64 + 32], 2.0);
        assert!(out.depth[0].is_infinite());
    }

    /// The nearer of two overlapping points wins whatever their order.
    #[test]
    fn the_z_buffer_keeps_the_nearest() {
        for order in [[1.0f32, 3.0], [3.0, 1.0]] {
            let c = cloud(
                vec![[0.0, 0.0, order[0]], [0.0, 0.0, order[1]]],
                Some(vec![[10, 10, 10], [200, 200, 200]]),
            );
            let out = render_points(&c, &camera(Pose::IDENTITY), 2.0, [0.0; 3]);
            let near = if order[0] < order[1] { 10 } else { 200 };
            assert_eq!(out.rgb[(24 * 64 + 32) * 3], near);
            assert_eq!(out.depth[24 * 64 + 32], 1.0);
        }
    }

    #[test]
    fn look_at_points_the_camera_at_the_target() {
        let pose = look_at([3.0, 1.0, -2.0], [0.5, 0.0, 1.0], [0.0, 1.0, 0.0]).unwrap();
        let r = pose.rotation_matrix();
        let t = pose.translation;
        let target = [0.5, 0.0, 1.0];
        let cam = [0, 1, 2].map(|i| {
            r[3 * i] * target[0] + r[3 * i + 1] * target[1] + r[3 * i + 2] * target[2] + t[i]
        });
        assert!(
            cam[0].abs() < 1e-12 && cam[1].abs() < 1e-12 && cam[2] > 0.0,
            "{cam:?}"
        );
        // World up projects upwards (negative image y).
        let above = [0.5, 1.0, 1.0];
        let y = r[3] * above[0] + r[4] * above[1] + r[5] * above[2] + t[1];
        assert!(y < 0.0);
        assert!(look_at([0.0; 3], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]).is_none());
    }

    fn rec_with(poses: &[Pose]) -> Reconstruction {
        Reconstruction {
            cameras: Default::default(),
            images: poses
                .iter()
                .enumerate()
                .map(|(k, p)| ReconImage {
                    id: k as u32 + 1,
                    camera_id: 1,
                    name: format!("{k}.png"),
                    camera_from_world: *p,
                    points2d: Vec::new(),
                })
                .collect(),
            points: Vec::new(),
        }
    }

    /// The path passes through every capture camera at its knot, and halfway between two
    /// cameras on a straight line it is halfway between them.
    #[test]
    fn the_path_interpolates_the_capture_cameras() {
        let poses: Vec<Pose> = (0..4)
            .map(|k| {
                look_at(
                    [k as f64, 0.0, -5.0],
                    [k as f64, 0.0, 0.0],
                    [0.0, -1.0, 0.0],
                )
                .unwrap()
            })
            .collect();
        let rec = rec_with(&poses);
        for (k, p) in poses.iter().enumerate() {
            let (r, c) = path_camera(&rec, k as f64 / 3.0).unwrap();
            assert!(
                (c[0] - k as f64).abs() < 1e-9 && (c[2] + 5.0).abs() < 1e-9,
                "{c:?}"
            );
            let expected = p.rotation_matrix();
            assert!(r.iter().zip(&expected).all(|(a, b)| (a - b).abs() < 1e-9));
        }
        let (_, mid) = path_camera(&rec, 0.5).unwrap();
        assert!((mid[0] - 1.5).abs() < 1e-9, "{mid:?}");
        assert!(path_camera(&rec_with(&[]), 0.5).is_err());
        // One image: the path is that camera.
        let (_, one) = path_camera(&rec_with(&poses[2..3]), 0.7).unwrap();
        assert!((one[0] - 2.0).abs() < 1e-9);
    }

    #[test]
    fn robust_frame_ignores_strays_and_nans() {
        let mut pts: Vec<[f32; 3]> = (0..100).map(|i| [i as f32 / 100.0, 0.0, 0.0]).collect();
        pts.push([1e6, 0.0, 0.0]);
        pts.push([f32::NAN, 0.0, 0.0]);
        let (c, r) = robust_frame(&pts).unwrap();
        assert!((c[0] - 0.5).abs() < 0.02 && r < 0.5, "{c:?} {r}");
        assert!(robust_frame(&[[f32::NAN; 3]]).is_none());
        assert_eq!(robust_frame(&[[1.0, 2.0, 3.0]]).unwrap().1, 1.0);
    }
}
