//! 2.5-D meshing of a depth image: `mesh.from_depth`.
//!
//! The depth image is back-projected exactly as `sfm.depth_to_points` does (same camera, lens,
//! `depth_scale`, `depth_kind`, validity range and `stride`; see
//! [`crate::sfm::depth::depth_to_points`]), then [`triangulate_organized`] meshes the organized
//! grid: each 2×2 block of samples (a quad) with four valid samples is split along its shorter
//! diagonal in 3-D (the better-shaped pair of triangles; ties take the diagonal from the top-left
//! sample), a quad with three valid samples gives one triangle, and a triangle is dropped when
//! - an edge crosses a depth discontinuity: |z₁ − z₂| > `max_depth_jump` · min(z₁, z₂), z the
//!   camera-frame depth (occlusion boundaries are not bridged), or
//! - it is seen at a grazing angle: the angle between its normal and the ray from its centroid to
//!   the camera exceeds `max_angle_deg` (such triangles are almost always stretched across a
//!   silhouette), or it is degenerate or faces away.
//!
//! This is the organized-mesh construction of PCL's `OrganizedFastMesh` and Open3D's RGB-D
//! meshing (and of KinectFusion-style depth-map meshing; Holz & Behnke, "Fast range image
//! segmentation and smoothing using approximate surface reconstruction and region growing",
//! IAS 2012). Triangles are wound counter-clockwise seen from the camera (their normals point
//! towards it). Quad rows are meshed in parallel and concatenated in row order: the result does
//! not depend on the thread count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Mesh, Metrics, Pose, Value};
use rayon::prelude::*;

use super::normals::{NormalWeighting, cross, dot, norm, sub, vertex_normals};
use crate::geometry::camera::Lens;
use crate::geometry::rectify::samples_f32;
use crate::sfm::depth::{
    DepthKind, DepthOptions, DepthToPoints, DepthToPointsParams, color_input, depth_image_ports,
    depth_to_points, pose_input,
};

/// Options of [`triangulate_organized`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrganizedMeshOptions {
    /// Largest relative depth jump along a triangle edge, |Δz| / min(z).
    pub max_depth_jump: f64,
    /// Largest angle between a triangle's normal and its direction to the camera, degrees.
    pub max_angle_deg: f64,
    /// Wind the triangles the other way (a lens with fx·fy < 0 mirrors the image).
    pub mirrored: bool,
}

/// A mesh over an organized grid.
#[derive(Debug, Clone, PartialEq)]
pub struct OrganizedMesh {
    /// Grid indices (row-major) of the vertices, ascending: only samples used by a triangle.
    pub vertices: Vec<u32>,
    /// Triangles over `vertices` (indices into it), counter-clockwise seen from the camera.
    pub triangles: Vec<[u32; 3]>,
    /// Valid samples of the grid.
    pub valid_samples: usize,
    /// Triangles dropped for a depth discontinuity.
    pub dropped_discontinuity: usize,
    /// Triangles dropped for a grazing angle (or degenerate, or facing away).
    pub dropped_grazing: usize,
}

/// Why a triangle was not kept.
enum Verdict {
    Keep,
    Discontinuity,
    Grazing,
}

fn judge(p: [[f64; 3]; 3], o: &OrganizedMeshOptions, cos_max: f64) -> Verdict {
    for k in 0..3 {
        let (z1, z2) = (p[k][2], p[(k + 1) % 3][2]);
        if (z1 - z2).abs() > o.max_depth_jump * z1.min(z2) {
            return Verdict::Discontinuity;
        }
    }
    let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
    let m = [0, 1, 2].map(|k| (p[0][k] + p[1][k] + p[2][k]) / 3.0);
    let (ln, lm) = (norm(n), norm(m));
    if !(ln > 0.0 && lm > 0.0 && ln.is_finite()) {
        return Verdict::Grazing;
    }
    // Towards the camera at the origin: the normal against the centroid's direction.
    let cos = -dot(n, m) / (ln * lm);
    if cos < cos_max || cos <= 0.0 {
        Verdict::Grazing
    } else {
        Verdict::Keep
    }
}

/// Meshes the organized camera-frame points `xyz` (`width` × `height`, row-major; a sample is
/// valid when its z is finite and > 0), see the module documentation. Winding: image order
/// (x right, y down) seen from a camera looking along +z, i.e. counter-clockwise seen from the
/// camera for a lens with fx, fy > 0 (`mirrored` reverses it).
pub fn triangulate_organized(
    xyz: &[[f64; 3]],
    width: usize,
    height: usize,
    o: &OrganizedMeshOptions,
) -> OrganizedMesh {
    let valid = |i: usize| xyz.get(i).is_some_and(|p| p[2].is_finite() && p[2] > 0.0);
    let valid_samples = (0..width * height).filter(|&i| valid(i)).count();
    let cos_max = o.max_angle_deg.to_radians().cos();
    // Per row of quads: (triangles as grid indices, dropped for discontinuity, for grazing).
    let rows: Vec<(Vec<[u32; 3]>, usize, usize)> = (0..height.saturating_sub(1))
        .into_par_iter()
        .map(|y| {
            let mut tris = Vec::new();
            let (mut jump, mut grazing) = (0, 0);
            for x in 0..width.saturating_sub(1) {
                let (a, b) = (y * width + x, y * width + x + 1);
                let (c, d) = (a + width, b + width);
                let candidates: [Option<[usize; 3]>; 2] =
                    match (valid(a), valid(b), valid(c), valid(d)) {
                        (true, true, true, true) => {
                            let d2 = |i: usize, j: usize| {
                                let v = sub(xyz[i], xyz[j]);
                                dot(v, v)
                            };
                            if d2(a, d) <= d2(b, c) {
                                [Some([a, c, d]), Some([a, d, b])]
                            } else {
                                [Some([a, c, b]), Some([b, c, d])]
                            }
                        }
                        (false, true, true, true) => [Some([b, c, d]), None],
                        (true, false, true, true) => [Some([a, c, d]), None],
                        (true, true, false, true) => [Some([a, d, b]), None],
                        (true, true, true, false) => [Some([a, c, b]), None],
                        _ => [None, None],
                    };
                for t in candidates.into_iter().flatten() {
                    let t = if o.mirrored { [t[0], t[2], t[1]] } else { t };
                    match judge(t.map(|i| xyz[i]), o, cos_max) {
                        Verdict::Keep => tris.push(t.map(|i| i as u32)),
                        Verdict::Discontinuity => jump += 1,
                        Verdict::Grazing => grazing += 1,
                    }
                }
            }
            (tris, jump, grazing)
        })
        .collect();
    let mut grid_triangles = Vec::new();
    let (mut dropped_discontinuity, mut dropped_grazing) = (0, 0);
    for (t, j, g) in rows {
        grid_triangles.extend(t);
        dropped_discontinuity += j;
        dropped_grazing += g;
    }
    // Compact: only the samples a triangle uses, in grid order.
    let mut used = vec![u32::MAX; width * height];
    for t in &grid_triangles {
        for &i in t {
            used[i as usize] = 0;
        }
    }
    let mut vertices = Vec::new();
    for (i, u) in used.iter_mut().enumerate() {
        if *u == 0 {
            *u = vertices.len() as u32;
            vertices.push(i as u32);
        }
    }
    let triangles = grid_triangles
        .iter()
        .map(|t| t.map(|i| used[i as usize]))
        .collect();
    OrganizedMesh {
        vertices,
        triangles,
        valid_samples,
        dropped_discontinuity,
        dropped_grazing,
    }
}

/// sRGB-encoded byte → linear (the engine's mesh colours are linear).
fn srgb_to_linear(v: u8) -> f32 {
    let s = f64::from(v) / 255.0;
    let l = if s <= 0.04045 {
        s / 12.92
    } else {
        ((s + 0.055) / 1.055).powf(2.4)
    };
    l as f32
}

params! {
    /// Parameters of `mesh.from_depth`.
    pub struct FromDepthParams {
        /// Depth units per sample: scene units = sample × `depth_scale` (0.001 for millimetre
        /// u16 depth). Default 1.
        depth_scale: f64 = 1.0 => [min = 0.0],
        /// What a sample measures: "z" (along the optical axis) or "range" (along the ray).
        /// Default "z".
        depth_kind: DepthKind = DepthKind::Z,
        /// Nearest valid depth after scaling (0, the usual "no data", is always invalid).
        /// Default 0.
        min_depth: f64 = 0.0 => [min = 0.0, unit = "scene units"],
        /// Farthest valid depth after scaling; None (the default) has no limit.
        max_depth: Option<f64> = None => [min = 0.0, unit = "scene units"],
        /// Focal lengths and principal point used when no `camera` is connected (fx required
        /// then; fy defaults to fx; cx, cy to (w − 1)/2, (h − 1)/2).
        fx: Option<f64> = None => [unit = "px"],
        /// See `fx`.
        fy: Option<f64> = None => [unit = "px"],
        /// See `fx`.
        cx: Option<f64> = None => [unit = "px"],
        /// See `fx`.
        cy: Option<f64> = None => [unit = "px"],
        /// Mesh every `stride`-th pixel in x and y. Default 1.
        stride: u32 = 1 => [min = 1.0, unit = "px"],
        /// Largest relative depth jump |Δz| / min(z) along a triangle edge; wider jumps are
        /// occlusion boundaries and are not bridged. Default 0.05.
        max_depth_jump: f64 = 0.05 => [min = 0.0],
        /// Largest angle between a triangle's normal and its direction to the camera; steeper
        /// (grazing) triangles are dropped. 90 keeps every front-facing triangle. Default 85.
        max_angle_deg: f64 = 85.0 => [min = 0.0, max = 90.0, unit = "deg"],
        /// Output angle-weighted vertex normals. Default true.
        normals: bool = true,
    }
}

/// `mesh.from_depth`. See [`triangulate_organized`].
#[derive(Debug, Clone, PartialEq)]
pub struct FromDepth {
    params: FromDepthParams,
    points: DepthToPoints,
}

impl Op for FromDepth {
    type Params = FromDepthParams;
    const ID: &'static str = "mesh.from_depth";
    const SUMMARY: &'static str = "Meshes a depth image (RGB-D, rendered, or from stereo) into a 2.5-D triangle mesh, \
         not bridging depth discontinuities.";
    const DOC: &'static str = r#"
Back-projects the depth image like `sfm.depth_to_points` (same `camera` input or fx/fy/cx/cy
params, lens distortion, `depth_scale`, `depth_kind`, `min_depth`, `max_depth`, `stride`; 0,
negative and non-finite samples are holes) and triangulates the organized grid: every 2×2 block
of valid samples becomes two triangles split along its shorter 3-D diagonal, a block with three
valid samples one triangle. Triangles are dropped across depth discontinuities (an edge with
|Δz| > `max_depth_jump`·min(z)) and at grazing angles (normal more than `max_angle_deg` from the
direction to the camera), so occlusion boundaries are not bridged by "rubber sheet" triangles —
the organized meshing of PCL's OrganizedFastMesh and Open3D's RGB-D meshing.

Output: `mesh`, the samples used by a triangle (row-major) with triangles counter-clockwise
seen from the camera (normals towards it), vertex colours from `color` (u8 or f32 in [0, 1],
sRGB, stored linear) and, with `normals: true`, angle-weighted vertex normals; with a `pose`
(camera_from_world) the mesh is in world coordinates. An image with no 2×2 block of valid samples
(empty, 1×1, all invalid) gives an empty mesh, not an error.

Metrics: `valid_samples`, `vertices`, `triangles`, `dropped_discontinuity`, `dropped_grazing`.

Example:
    "surface": (op: "mesh.from_depth",
                inputs: { "depth": "kinect.image", "color": "rgb.image", "camera": "intr.camera" },
                params: (depth_scale: 0.001, max_depth: Some(4.0), max_depth_jump: 0.03)),
"#;

    fn inputs() -> Vec<PortSpec> {
        depth_image_ports("camera_from_world: the mesh in world coordinates.")
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The depth mesh, triangles counter-clockwise seen from the camera.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "valid_samples, vertices, triangles, dropped_discontinuity, dropped_grazing.",
            ),
        ]
    }

    fn new(p: FromDepthParams) -> Result<Self, String> {
        if !(p.max_angle_deg.is_finite() && p.max_angle_deg > 0.0 && p.max_angle_deg <= 90.0) {
            return Err(format!(
                "`max_angle_deg` must be in (0, 90], got {}",
                p.max_angle_deg
            ));
        }
        // The back-projection params are checked by `sfm.depth_to_points` itself.
        let points = DepthToPoints::new(DepthToPointsParams {
            depth_scale: p.depth_scale,
            depth_kind: p.depth_kind,
            min_depth: p.min_depth,
            max_depth: p.max_depth,
            fx: p.fx,
            fy: p.fy,
            cx: p.cx,
            cy: p.cy,
            stride: p.stride,
            normals: false,
            max_depth_jump: p.max_depth_jump,
        })?;
        Ok(FromDepth { params: p, points })
    }
}

/// `X_w = Rᵀ(X_c − t)` for a camera_from_world pose.
fn to_world(pose: &Pose) -> impl Fn([f64; 3]) -> [f64; 3] {
    let r = pose.rotation_matrix();
    let t = pose.translation;
    move |p| {
        let v = [p[0] - t[0], p[1] - t[1], p[2] - t[2]];
        [
            r[0] * v[0] + r[3] * v[1] + r[6] * v[2],
            r[1] * v[0] + r[4] * v[1] + r[7] * v[2],
            r[2] * v[0] + r[5] * v[1] + r[8] * v[2],
        ]
    }
}

/// The whole of `mesh.from_depth` on samples: the mesh and its metrics.
#[allow(clippy::too_many_arguments)]
pub fn depth_mesh(
    depth: &[f32],
    width: usize,
    height: usize,
    lens: &Lens,
    camera_from_world: Option<&Pose>,
    colors: Option<(&[u8], usize)>,
    depth_options: &DepthOptions,
    mesh_options: &OrganizedMeshOptions,
    normals: bool,
) -> Result<(Mesh, OrganizedMesh), crate::sfm::depth::DepthError> {
    let points = depth_to_points(
        depth,
        width,
        height,
        lens,
        None,
        None,
        &DepthOptions {
            normals: false,
            ..depth_options.clone()
        },
    )?;
    let xyz: Vec<[f64; 3]> = points.xyz.iter().map(|p| p.map(f64::from)).collect();
    let o = OrganizedMeshOptions {
        mirrored: mesh_options.mirrored != (lens.k.fx * lens.k.fy < 0.0),
        ..*mesh_options
    };
    let organized = triangulate_organized(&xyz, points.width, points.height, &o);
    let world = camera_from_world.map(to_world);
    let positions: Vec<[f64; 3]> = organized
        .vertices
        .iter()
        .map(|&i| {
            let p = xyz[i as usize];
            world.as_ref().map_or(p, |f| f(p))
        })
        .collect();
    let stride = depth_options.stride.max(1);
    let colors = colors.map(|(data, channels)| {
        organized
            .vertices
            .iter()
            .map(|&i| {
                let (ox, oy) = (i as usize % points.width, i as usize / points.width);
                let at = ((oy * stride) * width + ox * stride) * channels;
                let c = |j: usize| {
                    srgb_to_linear(data.get(at + j.min(channels - 1)).copied().unwrap_or(0))
                };
                if channels >= 3 {
                    [c(0), c(1), c(2)]
                } else {
                    [c(0); 3]
                }
            })
            .collect()
    });
    let normals = normals.then(|| {
        let (n, _) = vertex_normals(&positions, &organized.triangles, NormalWeighting::Angle);
        n.iter().map(|v| v.map(|x| x as f32)).collect()
    });
    let mesh = Mesh {
        positions: positions.iter().map(|p| p.map(|x| x as f32)).collect(),
        triangles: organized.triangles.clone(),
        normals,
        colors,
        ..Mesh::default()
    };
    Ok((mesh, organized))
}

impl Operator for FromDepth {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("depth")?;
        if image.channels() != Channels::Gray {
            return Err(OpError::input(
                "depth",
                format!("expected one channel, got {}", image.channels().name()),
            ));
        }
        let (w, h) = (image.width(), image.height());
        let samples = samples_f32(image);
        let color = color_input(inputs, w, h)?;
        let pose = pose_input(inputs)?;
        let lens = self.points.lens(inputs, w, h)?;
        let p = &self.params;
        let depth_options = DepthOptions {
            depth_scale: p.depth_scale,
            kind: p.depth_kind,
            min_depth: p.min_depth,
            max_depth: p.max_depth.unwrap_or(f64::INFINITY),
            stride: p.stride as usize,
            normals: false,
            max_depth_jump: p.max_depth_jump,
        };
        let mesh_options = OrganizedMeshOptions {
            max_depth_jump: p.max_depth_jump,
            max_angle_deg: p.max_angle_deg,
            mirrored: false,
        };
        let (mesh, organized) = depth_mesh(
            &samples,
            w,
            h,
            &lens,
            pose.as_ref(),
            color.as_ref().map(|(v, c)| (v.as_slice(), *c)),
            &depth_options,
            &mesh_options,
            p.normals,
        )
        .map_err(|e| OpError::input("camera", e.to_string()))?;
        let mut m = Metrics::new();
        m.insert("valid_samples".into(), organized.valid_samples as f64);
        m.insert("vertices".into(), organized.vertices.len() as f64);
        m.insert("triangles".into(), organized.triangles.len() as f64);
        m.insert(
            "dropped_discontinuity".into(),
            organized.dropped_discontinuity as f64,
        );
        m.insert("dropped_grazing".into(), organized.dropped_grazing as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(mesh)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::halfedge::HalfedgeMesh;
    use ocellus_engine::value::{Image, Intrinsics};

    fn k(w: usize, h: usize) -> Intrinsics {
        Intrinsics {
            fx: 60.0,
            fy: 55.0,
            cx: (w as f64 - 1.0) / 2.0 + 0.3,
            cy: (h as f64 - 1.0) / 2.0 - 0.2,
            skew: 0.0,
        }
    }

    fn depth_options() -> DepthOptions {
        DepthOptions {
            depth_scale: 1.0,
            kind: DepthKind::Z,
            min_depth: 0.0,
            max_depth: f64::INFINITY,
            stride: 1,
            normals: false,
            max_depth_jump: 0.05,
        }
    }

    fn mesh_options() -> OrganizedMeshOptions {
        OrganizedMeshOptions {
            max_depth_jump: 0.05,
            max_angle_deg: 85.0,
            mirrored: false,
        }
    }

    fn mesh_of(
        depth: &[f32],
        w: usize,
        h: usize,
        kk: Intrinsics,
        pose: Option<&Pose>,
        mo: &OrganizedMeshOptions,
    ) -> (Mesh, OrganizedMesh) {
        depth_mesh(
            depth,
            w,
            h,
            &Lens::pinhole(kk),
            pose,
            None,
            &depth_options(),
            mo,
            true,
        )
        .unwrap()
    }

    fn tri_normal(m: &Mesh, t: [u32; 3]) -> [f64; 3] {
        let [a, b, c] = t.map(|i| m.positions[i as usize].map(f64::from));
        let n = cross(sub(b, a), sub(c, a));
        let l = norm(n);
        n.map(|x| x / l)
    }

    #[test]
    fn fronto_parallel_plane() {
        let (w, h) = (17, 11);
        let depth = vec![2.5f32; w * h];
        let (m, o) = mesh_of(&depth, w, h, k(w, h), None, &mesh_options());
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1));
        assert_eq!(m.positions.len(), w * h);
        assert_eq!(o.valid_samples, w * h);
        assert!(m.positions.iter().all(|p| p[2] == 2.5));
        for &t in &m.triangles {
            let n = tri_normal(&m, t);
            assert!((n[2] + 1.0).abs() < 1e-9, "{n:?} does not face the camera");
        }
        for n in m.normals.as_ref().unwrap() {
            assert!((n[2] + 1.0).abs() < 1e-6);
        }
        // A disc: manifold, consistently oriented, one boundary.
        let p: Vec<[f64; 3]> = m.positions.iter().map(|p| p.map(f64::from)).collect();
        let half = HalfedgeMesh::from_triangles(p, &m.triangles).unwrap();
        half.validate().unwrap();
        assert_eq!(half.euler_characteristic(), 1);
        assert_eq!(half.boundary_loops().len(), 1);
        // Hand-computed first vertices: pixel (0, 0) and (1, 0) at Z = 2.5.
        let kk = k(w, h);
        assert!((f64::from(m.positions[0][0]) - 2.5 * (0.0 - kk.cx) / kk.fx).abs() < 1e-6);
        assert!((f64::from(m.positions[1][1]) - 2.5 * (0.0 - kk.cy) / kk.fy).abs() < 1e-6);
    }

    /// Z of the first intersection of the pixel's ray with the sphere, or `background`.
    fn sphere_depth(kk: &Intrinsics, w: usize, h: usize, c: [f64; 3], r: f64, bg: f32) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let d = [
                    ((i % w) as f64 - kk.cx) / kk.fx,
                    ((i / w) as f64 - kk.cy) / kk.fy,
                    1.0,
                ];
                // |t d − c|² = r²: (d·d) t² − 2 (d·c) t + c·c − r² = 0.
                let (a, b, cc) = (dot(d, d), dot(d, c), dot(c, c) - r * r);
                let disc = b * b - a * cc;
                if disc < 0.0 {
                    bg
                } else {
                    ((b - disc.sqrt()) / a) as f32
                }
            })
            .collect()
    }

    #[test]
    fn rendered_sphere_is_not_bridged_to_the_background() {
        let (w, h) = (80, 64);
        let kk = k(w, h);
        let (c, r, bg) = ([0.1, -0.05, 3.0], 1.0, 6.0f32);
        let depth = sphere_depth(&kk, w, h, c, r, bg);
        let (m, o) = mesh_of(&depth, w, h, kk, None, &mesh_options());
        let on_sphere = |p: [f32; 3]| {
            let d = sub(p.map(f64::from), c);
            (norm(d) - r).abs() < 1e-4 * r
        };
        let on_background = |p: [f32; 3]| (f64::from(p[2]) - f64::from(bg)).abs() < 1e-6;
        let mut sphere_tris = 0;
        for t in &m.triangles {
            let p = t.map(|i| m.positions[i as usize]);
            if p.iter().all(|&q| on_sphere(q)) {
                sphere_tris += 1;
                // Towards the camera: on the visible side of a sphere that is outward.
                let n = tri_normal(&m, *t);
                let centroid = [0, 1, 2]
                    .map(|k| (f64::from(p[0][k]) + f64::from(p[1][k]) + f64::from(p[2][k])) / 3.0);
                let out = sub(centroid, c);
                assert!(dot(n, out) > 0.0);
            } else {
                assert!(
                    p.iter().all(|&q| on_background(q)),
                    "triangle {p:?} bridges sphere and background"
                );
            }
        }
        // Every vertex is on one of the two surfaces.
        assert!(
            m.positions
                .iter()
                .all(|&p| on_sphere(p) || on_background(p))
        );
        // The silhouette was cut: some triangles were dropped.
        assert!(o.dropped_discontinuity > 0);
        // Most of the sphere's pixels are meshed (all but a rim of grazing samples).
        let sphere_pixels = depth.iter().filter(|&&z| z < bg).count();
        assert!(
            sphere_tris > sphere_pixels,
            "{sphere_tris} of {sphere_pixels}"
        );
        // The sphere part is a disc: manifold and consistently oriented.
        let p: Vec<[f64; 3]> = m.positions.iter().map(|p| p.map(f64::from)).collect();
        HalfedgeMesh::from_triangles(p, &m.triangles)
            .unwrap()
            .validate()
            .unwrap();
    }

    #[test]
    fn invalid_samples_leave_holes() {
        let (w, h) = (9, 7);
        let mut depth = vec![1.5f32; w * h];
        depth[3 * w + 4] = f32::NAN; // interior: its 4 quads keep one triangle each
        depth[0] = 0.0; // corner: its quad keeps one triangle
        depth[5 * w + 2] = -1.0;
        let (m, o) = mesh_of(&depth, w, h, k(w, h), None, &mesh_options());
        assert_eq!(o.valid_samples, w * h - 3);
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1) - 4 - 1 - 4);
        assert_eq!(m.positions.len(), w * h - 3);
        assert!(
            m.positions
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()) && p[2] == 1.5)
        );
        // A 2×2 block of NaN in the middle: 4 + 4·2 quads lose their triangles…
        let mut depth = vec![1.5f32; w * h];
        for (x, y) in [(3, 3), (4, 3), (3, 4), (4, 4)] {
            depth[y * w + x] = f32::NAN;
        }
        let (m, _) = mesh_of(&depth, w, h, k(w, h), None, &mesh_options());
        // Quads touching the block: 9 with ≥ 1 invalid; the 4 corner ones keep one triangle.
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1) - 2 * 9 + 4);
    }

    #[test]
    fn depth_steps_and_grazing_planes_are_cut() {
        // Left half at Z = 1, right half at Z = 3: the middle column of quads is dropped.
        let (w, h) = (10, 6);
        let depth: Vec<f32> = (0..w * h)
            .map(|i| if i % w < 5 { 1.0 } else { 3.0 })
            .collect();
        let (m, o) = mesh_of(&depth, w, h, k(w, h), None, &mesh_options());
        assert_eq!(m.triangles.len(), 2 * 8 * (h - 1));
        assert_eq!(o.dropped_discontinuity, 2 * (h - 1));
        // With a loose jump threshold and no angle limit the step is bridged (front-facing).
        let loose = OrganizedMeshOptions {
            max_depth_jump: 10.0,
            max_angle_deg: 90.0,
            ..mesh_options()
        };
        let (m, _) = mesh_of(&depth, w, h, k(w, h), None, &loose);
        assert_eq!(m.triangles.len(), 2 * 9 * (h - 1));
        // A plane at 80° to the optical axis: n = (sin 80°, 0, −cos 80°), n·X = −1.
        let (w, h) = (12, 10);
        let kk = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            ..k(w, h)
        };
        let th = 80f64.to_radians();
        let n = [th.sin(), 0.0, -th.cos()];
        let depth: Vec<f32> = (0..w * h)
            .map(|i| {
                let x = ((i % w) as f64 - kk.cx) / kk.fx;
                let y = ((i / w) as f64 - kk.cy) / kk.fy;
                (-1.0 / (n[0] * x + n[1] * y + n[2])) as f32
            })
            .collect();
        let wide = OrganizedMeshOptions {
            max_depth_jump: 1.0,
            ..mesh_options()
        };
        let (m, _) = mesh_of(&depth, w, h, kk, None, &wide);
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1));
        let strict = OrganizedMeshOptions {
            max_angle_deg: 70.0,
            ..wide
        };
        let (m, o) = mesh_of(&depth, w, h, kk, None, &strict);
        assert!(m.triangles.is_empty() && m.positions.is_empty());
        assert_eq!(o.dropped_grazing, 2 * (w - 1) * (h - 1));
    }

    #[test]
    fn pose_stride_colors_and_empty_images() {
        let (w, h) = (7, 5);
        let depth: Vec<f32> = (0..w * h).map(|i| 2.0 + 0.01 * (i % 3) as f32).collect();
        let a = 0.3f64;
        let r = [a.cos(), -a.sin(), 0.0, a.sin(), a.cos(), 0.0, 0.0, 0.0, 1.0];
        let pose = Pose::from_rotation_matrix(&r, [0.5, -1.0, 2.0]);
        let (cam, _) = mesh_of(&depth, w, h, k(w, h), None, &mesh_options());
        let (world, _) = mesh_of(&depth, w, h, k(w, h), Some(&pose), &mesh_options());
        assert_eq!(cam.triangles, world.triangles);
        let f = to_world(&pose);
        for (p, q) in cam.positions.iter().zip(&world.positions) {
            let e = f(p.map(f64::from));
            for c in 0..3 {
                assert!((e[c] - f64::from(q[c])).abs() < 1e-5);
            }
        }
        // Stride 2 on 7 × 5: a 4 × 3 grid, 12 triangles.
        let o = DepthOptions {
            stride: 2,
            ..depth_options()
        };
        let lens = Lens::pinhole(k(w, h));
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 256) as u8).collect();
        let (m, org) = depth_mesh(
            &depth,
            w,
            h,
            &lens,
            None,
            Some((&rgb, 3)),
            &o,
            &mesh_options(),
            false,
        )
        .unwrap();
        assert_eq!(m.triangles.len(), 12);
        assert_eq!(m.positions.len(), 12);
        assert!(m.normals.is_none());
        // Vertex 5 is grid (1, 1) = pixel (2, 2).
        assert_eq!(org.vertices[5], 5);
        let px = (2 * w + 2) * 3;
        let colors = m.colors.as_ref().unwrap();
        assert_eq!(colors[5], [0, 1, 2].map(|c| srgb_to_linear(rgb[px + c])));
        assert_eq!(srgb_to_linear(255), 1.0);
        assert_eq!(srgb_to_linear(0), 0.0);
        // Empty and 1 × 1 images: an empty mesh.
        for (w, h) in [(0, 0), (1, 1), (1, 5), (5, 1)] {
            let d = vec![1.0f32; w * h];
            let (m, o) = mesh_of(&d, w, h, k(w, h), None, &mesh_options());
            assert!(m.positions.is_empty() && m.triangles.is_empty());
            assert_eq!(o.valid_samples, w * h);
        }
    }

    #[test]
    fn mesh_does_not_depend_on_the_thread_count() {
        let (w, h) = (120, 90);
        let kk = k(w, h);
        let depth = sphere_depth(&kk, w, h, [0.0, 0.0, 2.5], 0.9, 0.0);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| mesh_of(&depth, w, h, kk, None, &mesh_options()))
        };
        let (a, b) = (run(1), run(4));
        assert_eq!(a, b);
        assert!(!a.0.triangles.is_empty());
    }

    #[test]
    fn op_runs_with_params_camera() {
        let (w, h) = (6, 4);
        let img = Image::from_f32(w, h, Channels::Gray, vec![1000.0; w * h]).unwrap();
        let op = FromDepth::new(FromDepthParams {
            depth_scale: 0.001,
            fx: Some(50.0),
            ..FromDepthParams::default()
        })
        .unwrap();
        let specs = FromDepth::inputs();
        let values = [Some(Value::image(img)), None, None, None];
        let ctx = RunContext {
            node: "surface".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Mesh(m)) = out.take("mesh") else {
            panic!("no mesh")
        };
        assert_eq!(m.triangles.len(), 2 * 5 * 3);
        assert!(m.positions.iter().all(|p| (p[2] - 1.0).abs() < 1e-6));
        let Some(Value::Metrics(metrics)) = out.take("metrics") else {
            panic!("no metrics")
        };
        assert_eq!(metrics["valid_samples"], 24.0);
        // No camera and no fx: a clear error.
        let op = FromDepth::new(FromDepthParams::default()).unwrap();
        let e = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(e.to_string().contains("fx"), "{e}");
        assert!(
            FromDepth::new(FromDepthParams {
                max_angle_deg: 0.0,
                ..FromDepthParams::default()
            })
            .is_err()
        );
        assert!(
            FromDepth::new(FromDepthParams {
                stride: 0,
                ..FromDepthParams::default()
            })
            .is_err()
        );
    }
}
