//! Visual hull by silhouette carving on a voxel grid: `sfm.visual_hull`.
//!
//! Laurentini, "The visual hull concept for silhouette-based image understanding" (IEEE PAMI
//! 16(2), 1994) defines the visual hull as the intersection of the viewing cones of an object's
//! silhouettes; volumetric carving (Martin & Aggarwal, "Volumetric descriptions of objects from
//! multiple views", IEEE PAMI 5(2), 1983; Szeliski, "Rapid octree construction from image
//! sequences", CVGIP 58(1), 1993) computes it on a grid: a voxel is kept when it projects inside
//! every silhouette.
//!
//! Here every grid node carries a signed distance instead of a bit, so the surface is placed
//! between nodes to sub-voxel accuracy rather than on the voxels' faces. For each view the
//! silhouette's signed distance map is computed once (exact Euclidean distance transforms of the
//! silhouette and of its complement, Felzenszwalb & Huttenlocher; the boundary half a pixel
//! between an inside and an outside pixel). A node `X` at depth `z` in view `v` reads that map
//! bilinearly at its projection and converts pixels to scene units at that depth
//! (`s · z / f`, `f` the mean focal length): to first order, the distance from `X` to the
//! boundary of the view's cone. The node's value is the largest of these outside distances
//! over the views (the intersection of the cones is the minimum of their inside distances),
//! clamped to `±truncation` voxels; a node stops being visited once a view puts it a full
//! truncation outside. The hull's surface is the zero level set, extracted by the project's
//! watertight marching cubes; nodes on the faces of the box are held outside, so the mesh is
//! always closed (the hull clipped to the box).
//!
//! A node that projects outside a view's image, or behind its camera, is carved by default
//! (`outside: "carve"`: the object is entirely in every image, as in a turntable capture) or
//! left to the other views (`outside: "ignore"`: partial views).
//!
//! Work is split in z slabs and each node's value depends only on that node and the views, in
//! view order: the result is bit-identical for any thread count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Mesh, Metrics, PixelData, Pose, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use crate::filter::distance::{Metric, distance_of_sites};
use crate::geometry::camera::Lens;
use crate::mesh::marching_cubes::{MarchingCubesError, ScalarGrid, marching_cubes};
use crate::mesh::metrics::{signed_volume, surface_area};
use crate::mesh::normals::{NormalWeighting, vertex_normals};
use crate::sfm::pairs::CalibratedViews;

param_enum! {
    /// What a node projecting outside an image (or behind the camera) means.
    pub enum Outside {
        /// Carve it: every view sees the whole object.
        Carve = "carve",
        /// Ignore that view for it: views may see part of the object.
        Ignore = "ignore",
    }
}

param_enum! {
    /// How a silhouette image marks the object.
    pub enum SilhouetteFrom {
        /// A mask: a pixel is inside when its value exceeds `threshold`.
        Mask = "mask",
        /// A depth or range map (`capture.render`'s `depths`): a pixel is inside when its
        /// depth is finite and positive.
        Depth = "depth",
    }
}

/// Why a visual hull cannot be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VisualHullError {
    /// No view was given.
    #[error("no views")]
    NoViews,
    /// A silhouette's size does not match its camera, or its buffer its size.
    #[error("view {index}: {what}")]
    View {
        /// View index.
        index: usize,
        /// What is wrong.
        what: String,
    },
    /// A pose is not a rigid transform.
    #[error("pose {0} is not a finite rigid transform (quaternion non-zero, finite entries)")]
    Pose(usize),
    /// The box is not finite or has no volume.
    #[error("the box must be finite with min < max on every axis, got min {min:?}, max {max:?}")]
    Bounds {
        /// Lower corner.
        min: [f64; 3],
        /// Upper corner.
        max: [f64; 3],
    },
    /// The grid exceeds the node cap.
    #[error(
        "the grid needs {needed} nodes, more than max_voxels = {max}; lower `resolution` or raise `max_voxels`"
    )]
    TooManyVoxels {
        /// Nodes needed.
        needed: u64,
        /// The cap.
        max: u64,
    },
    /// No node lies inside every silhouette.
    #[error(
        "the hull is empty: no grid node projects inside every silhouette (check the poses are \
         camera_from_world, the box holds the object, and `resolution` is fine enough for it)"
    )]
    Empty,
    /// Surface extraction failed.
    #[error("marching cubes: {0}")]
    Extraction(#[from] MarchingCubesError),
}

/// One calibrated silhouette.
#[derive(Debug, Clone)]
pub struct SilhouetteView<'a> {
    /// `true` inside the object, row-major `width × height`.
    pub inside: &'a [bool],
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Intrinsics and distortion.
    pub lens: Lens,
    /// World-to-camera transform.
    pub camera_from_world: Pose,
}

/// Options of [`visual_hull`].
#[derive(Debug, Clone, PartialEq)]
pub struct VisualHullOptions {
    /// Smallest corner of the box to carve, scene units.
    pub min: [f64; 3],
    /// Largest corner of the box to carve, scene units.
    pub max: [f64; 3],
    /// Grid nodes along the longest side of the box.
    pub resolution: usize,
    /// Clamp of the signed distance, voxels.
    pub truncation: f64,
    /// What a node outside an image means.
    pub outside: Outside,
    /// Cap on `nx·ny·nz`.
    pub max_voxels: u64,
}

/// The carved volume and its surface.
#[derive(Debug, Clone, PartialEq)]
pub struct VisualHull {
    /// Nodes per axis.
    pub dims: [usize; 3],
    /// Position of node `(0, 0, 0)`.
    pub origin: [f64; 3],
    /// Node spacing, scene units.
    pub voxel_size: f64,
    /// Per node: distance outside the hull, scene units (negative inside), clamped.
    pub field: Vec<f64>,
    /// Positions of the nodes inside the hull.
    pub inside_nodes: Vec<[f64; 3]>,
    /// Surface vertices.
    pub positions: Vec<[f64; 3]>,
    /// Surface triangles, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

/// A silhouette prepared for carving: its signed distance map and camera.
struct PreparedView {
    width: usize,
    height: usize,
    lens: Lens,
    rotation: [f64; 9],
    translation: [f64; 3],
    /// Signed distance to the silhouette's boundary, pixels, positive inside.
    signed_px: Vec<f32>,
    /// Mean focal length, pixels.
    focal_px: f64,
}

/// The signed distance to the boundary of the silhouette `inside` (`w × h`), pixels, positive
/// inside: an inside pixel's distance to the nearest outside pixel minus ½, an outside pixel's
/// distance to the nearest inside pixel minus ½, negated. Without any outside (inside) pixel the
/// distance is +∞ (−∞).
pub fn signed_distance(inside: &[bool], w: usize, h: usize) -> Vec<f32> {
    let outside: Vec<bool> = inside.iter().map(|&v| !v).collect();
    let any_out = outside.iter().any(|&v| v);
    let any_in = inside.iter().any(|&v| v);
    let to_outside = if any_out {
        distance_of_sites(&outside, w, h, Metric::Euclidean)
    } else {
        vec![f32::INFINITY; w * h]
    };
    let to_inside = if any_in {
        distance_of_sites(inside, w, h, Metric::Euclidean)
    } else {
        vec![f32::INFINITY; w * h]
    };
    inside
        .iter()
        .zip(to_outside.iter().zip(&to_inside))
        .map(|(&i, (&dout, &din))| if i { dout - 0.5 } else { -(din - 0.5) })
        .collect()
}

/// Bilinear sample of `map` (`w × h`) at pixel `(x, y)`, pixel centres at integer coordinates;
/// `None` outside `[−½, w − ½) × [−½, h − ½)`. Clamped at the border.
fn bilinear(map: &[f32], w: usize, h: usize, x: f64, y: f64) -> Option<f64> {
    if !(x >= -0.5 && y >= -0.5 && x < w as f64 - 0.5 && y < h as f64 - 0.5) {
        return None;
    }
    let xc = x.clamp(0.0, (w - 1) as f64);
    let yc = y.clamp(0.0, (h - 1) as f64);
    let x0 = xc.floor() as usize;
    let y0 = yc.floor() as usize;
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    let (fx, fy) = (xc - x0 as f64, yc - y0 as f64);
    let at = |xx: usize, yy: usize| f64::from(map[yy * w + xx]);
    let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
    // Infinite distances (a silhouette without boundary) stay infinite without NaN.
    if !(a.is_finite() && b.is_finite() && c.is_finite() && d.is_finite()) {
        return Some(a);
    }
    Some((a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy)
}

fn check_pose(index: usize, p: &Pose) -> Result<(), VisualHullError> {
    let q = p.rotation;
    let n = q.iter().map(|v| v * v).sum::<f64>();
    if !(q.iter().chain(&p.translation).all(|v| v.is_finite()) && n > 0.0 && n.is_finite()) {
        return Err(VisualHullError::Pose(index));
    }
    Ok(())
}

fn prepare(index: usize, v: &SilhouetteView<'_>) -> Result<PreparedView, VisualHullError> {
    check_pose(index, &v.camera_from_world)?;
    if v.width == 0 || v.height == 0 {
        return Err(VisualHullError::View {
            index,
            what: "empty silhouette image".into(),
        });
    }
    if v.width.checked_mul(v.height) != Some(v.inside.len()) {
        return Err(VisualHullError::View {
            index,
            what: format!(
                "a {}×{} silhouette needs {} pixels, got {}",
                v.width,
                v.height,
                v.width.saturating_mul(v.height),
                v.inside.len()
            ),
        });
    }
    let focal_px = 0.5 * (v.lens.k.fx.abs() + v.lens.k.fy.abs());
    if !(focal_px.is_finite() && focal_px > 0.0) {
        return Err(VisualHullError::View {
            index,
            what: format!("focal length {focal_px} px is not positive"),
        });
    }
    Ok(PreparedView {
        width: v.width,
        height: v.height,
        lens: v.lens,
        rotation: v.camera_from_world.rotation_matrix(),
        translation: v.camera_from_world.translation,
        signed_px: signed_distance(v.inside, v.width, v.height),
        focal_px,
    })
}

/// The grid over the box: `resolution` nodes along its longest side.
fn plan(options: &VisualHullOptions) -> Result<([usize; 3], f64), VisualHullError> {
    let (min, max) = (options.min, options.max);
    if !(0..3).all(|k| min[k].is_finite() && max[k].is_finite() && min[k] < max[k]) {
        return Err(VisualHullError::Bounds { min, max });
    }
    let extent = (0..3).map(|k| max[k] - min[k]).fold(0.0, f64::max);
    let h = extent / (options.resolution.max(2) - 1) as f64;
    let nodes = |k: usize| ((max[k] - min[k]) / h - 1e-9).ceil().max(1.0) + 1.0;
    let needed = nodes(0) * nodes(1) * nodes(2);
    if needed > options.max_voxels as f64 {
        return Err(VisualHullError::TooManyVoxels {
            needed: if needed < u64::MAX as f64 {
                needed as u64
            } else {
                u64::MAX
            },
            max: options.max_voxels,
        });
    }
    Ok(([nodes(0) as usize, nodes(1) as usize, nodes(2) as usize], h))
}

/// Distance of world point `x` outside view `v`'s cone, scene units (negative inside), or
/// `None` when the view cannot see `x` (outside the image, behind the camera).
fn outside_distance(v: &PreparedView, x: [f64; 3]) -> Option<f64> {
    let r = &v.rotation;
    let c = [
        r[0] * x[0] + r[1] * x[1] + r[2] * x[2] + v.translation[0],
        r[3] * x[0] + r[4] * x[1] + r[5] * x[2] + v.translation[1],
        r[6] * x[0] + r[7] * x[1] + r[8] * x[2] + v.translation[2],
    ];
    if c[2] <= 0.0 {
        return None;
    }
    let p = v.lens.project(c)?;
    let s = bilinear(&v.signed_px, v.width, v.height, p[0], p[1])?;
    Some(-s * c[2] / v.focal_px)
}

/// Carves the visual hull of `views` in the box of `options` and extracts its surface.
pub fn visual_hull(
    views: &[SilhouetteView<'_>],
    options: &VisualHullOptions,
) -> Result<VisualHull, VisualHullError> {
    if views.is_empty() {
        return Err(VisualHullError::NoViews);
    }
    let prepared = views
        .iter()
        .enumerate()
        .map(|(i, v)| prepare(i, v))
        .collect::<Result<Vec<_>, _>>()?;
    let (dims, h) = plan(options)?;
    let [nx, ny, nz] = dims;
    let origin = options.min;
    let trunc = options.truncation * h;
    let mut field = vec![0.0f64; nx * ny * nz];
    field
        .par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slab)| {
            let z = origin[2] + k as f64 * h;
            for j in 0..ny {
                let y = origin[1] + j as f64 * h;
                for i in 0..nx {
                    let on_face =
                        i == 0 || j == 0 || k == 0 || i + 1 == nx || j + 1 == ny || k + 1 == nz;
                    let x = [origin[0] + i as f64 * h, y, z];
                    let mut value = -trunc;
                    if on_face {
                        value = trunc;
                    } else {
                        for v in &prepared {
                            let d = match outside_distance(v, x) {
                                Some(d) => d,
                                None => match options.outside {
                                    Outside::Carve => trunc,
                                    Outside::Ignore => continue,
                                },
                            };
                            value = value.max(d);
                            if value >= trunc {
                                value = trunc;
                                break;
                            }
                        }
                    }
                    slab[j * nx + i] = value.clamp(-trunc, trunc);
                }
            }
        });
    let inside_nodes: Vec<[f64; 3]> = field
        .iter()
        .enumerate()
        .filter(|(_, v)| **v < 0.0)
        .map(|(n, _)| {
            let (i, j, k) = (n % nx, (n / nx) % ny, n / (nx * ny));
            [
                origin[0] + i as f64 * h,
                origin[1] + j as f64 * h,
                origin[2] + k as f64 * h,
            ]
        })
        .collect();
    if inside_nodes.is_empty() {
        return Err(VisualHullError::Empty);
    }
    let surface = marching_cubes(
        ScalarGrid {
            values: &field,
            dims,
            origin,
            spacing: h,
        },
        0.0,
    )?;
    Ok(VisualHull {
        dims,
        origin,
        voxel_size: h,
        field,
        inside_nodes,
        positions: surface.positions,
        triangles: surface.triangles,
    })
}

params! {
    /// Parameters of `sfm.visual_hull`.
    pub struct VisualHullParams {
        /// Smallest corner of the box to carve; it must hold the object. Required.
        min: Option<[f64; 3]> = None => [unit = "scene units"],
        /// Largest corner of the box to carve. Required.
        max: Option<[f64; 3]> = None => [unit = "scene units"],
        /// Grid nodes along the longest side of the box — the speed–accuracy knob: time and
        /// memory grow with its cube, the surface error shrinks with the voxel size. Default 96.
        resolution: u32 = 96 => [min = 4, max = 4096],
        /// Signed distances are clamped to ± this many voxels (only the values near the
        /// surface matter; a node stops being tested once a view puts it this far outside).
        /// Default 3.
        truncation: f64 = 3.0 => [above = 0.0, max = 1000.0, unit = "voxels"],
        /// How silhouettes mark the object: "mask" (value > threshold, the default) or
        /// "depth" (finite positive depth, as `capture.render` outputs).
        silhouette_from: SilhouetteFrom = SilhouetteFrom::Mask,
        /// With "mask": a pixel is inside when its value exceeds this. Default 0.
        threshold: f64 = 0.0,
        /// A node projecting outside an image or behind a camera: "carve" (default; every
        /// view sees the whole object) or "ignore" (that view says nothing about it).
        outside: Outside = Outside::Carve,
        /// Largest grid, nx·ny·nz nodes (8 bytes each). Default 16777216 = 256³.
        max_voxels: u64 = 16777216 => [min = 1],
    }
}

/// `sfm.visual_hull`. See [`visual_hull`].
#[derive(Debug, Clone, PartialEq)]
pub struct VisualHullOp {
    params: VisualHullParams,
    min: [f64; 3],
    max: [f64; 3],
}

impl Op for VisualHullOp {
    type Params = VisualHullParams;
    const ID: &'static str = "sfm.visual_hull";
    const SUMMARY: &'static str = "Carves the visual hull of calibrated silhouettes on a voxel grid and meshes it \
         (Laurentini 1994; Szeliski 1993).";
    const DOC: &'static str = r#"
Shape from silhouettes: the intersection of the viewing cones of the object's silhouettes
(Laurentini, "The visual hull concept for silhouette-based image understanding", IEEE PAMI 1994),
carved on a regular grid over the box `min`–`max` (Martin & Aggarwal 1983; Szeliski 1993).
View i is silhouettes[i] seen by cameras[i] (or the single camera) at poses[i]
(camera_from_world) — the lists `capture.render` outputs; with `silhouette_from: "depth"` its
depth maps are the silhouettes (finite positive depth = object).

Each grid node holds a signed distance rather than a bit: per view, the silhouette's exact
Euclidean signed distance map (pixels) is read bilinearly at the node's projection and scaled
to scene units at the node's depth (pixels · z / f); the node's value is the largest distance
outside any cone, clamped to ± `truncation` voxels. The surface is the zero level set by
marching cubes, so it lies between nodes with sub-voxel accuracy instead of on voxel faces;
nodes on the box's faces are held outside, so the mesh is closed (the hull clipped to the box).
A node outside an image or behind a camera is carved (`outside: "carve"`) or left to the other
views ("ignore"). The hull contains the object and is only as tight as the views allow: it
cannot see concavities. `resolution` trades time (∝ its cube) for accuracy; the result does not
depend on the thread count.

Outputs: `mesh` (closed, counter-clockwise seen from outside, area-weighted vertex normals),
`points` (the grid nodes inside the hull) and `metrics`: views, nx, ny, nz, voxels,
voxel_size, inside_nodes, volume (enclosed by the mesh), area, vertices, triangles.

Example:
    "hull": (op: "sfm.visual_hull",
             inputs: { "silhouettes": "shots.depths", "cameras": "shots.cameras", "poses": "shots.poses" },
             params: (silhouette_from: "depth", min: Some((-1, 0, -1)), max: Some((1, 2, 1)), resolution: 128)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "silhouettes",
                PortType::Image.list_of(),
                "One single-channel silhouette (mask or depth map) per view.",
            ),
            PortSpec::new(
                "cameras",
                PortType::Camera.list_of(),
                "One camera per view, or one for all; sizes must match the silhouettes.",
            ),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "camera_from_world per view.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The hull's surface, closed, with normals.",
            ),
            PortSpec::new(
                "points",
                PortType::PointCloud,
                "Grid nodes inside the hull.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "views, nx, ny, nz, voxels, voxel_size, inside_nodes, volume, area, vertices, \
                 triangles.",
            ),
        ]
    }

    fn new(p: VisualHullParams) -> Result<Self, String> {
        let (min, max) = match (p.min, p.max) {
            (Some(lo), Some(hi)) => {
                if !(0..3).all(|k| lo[k].is_finite() && hi[k].is_finite() && lo[k] < hi[k]) {
                    return Err(format!(
                        "`min` {lo:?} and `max` {hi:?} must be finite with min < max on every axis"
                    ));
                }
                (lo, hi)
            }
            _ => {
                return Err(
                    "give the box to carve, `min` and `max` (scene units); it must hold the object"
                        .into(),
                );
            }
        };
        if !(p.truncation.is_finite() && p.truncation > 0.0) {
            return Err(format!(
                "`truncation` must be finite and > 0 (voxels), got {}",
                p.truncation
            ));
        }
        if !p.threshold.is_finite() {
            return Err(format!("`threshold` must be finite, got {}", p.threshold));
        }
        if p.resolution < 4 {
            return Err(format!("`resolution` must be ≥ 4, got {}", p.resolution));
        }
        if p.max_voxels == 0 {
            return Err("`max_voxels` must be ≥ 1".into());
        }
        Ok(VisualHullOp {
            params: p,
            min,
            max,
        })
    }
}

/// The silhouette of one image: inside where `from` says so.
fn silhouette_mask(image: &Image, from: SilhouetteFrom, threshold: f64) -> Vec<bool> {
    let inside = |v: f64| match from {
        SilhouetteFrom::Mask => v > threshold,
        SilhouetteFrom::Depth => v.is_finite() && v > 0.0,
    };
    match image.data() {
        PixelData::U8(d) => d.iter().map(|&v| inside(f64::from(v))).collect(),
        PixelData::U16(d) => d.iter().map(|&v| inside(f64::from(v))).collect(),
        PixelData::F32(d) => d.iter().map(|&v| inside(f64::from(v))).collect(),
    }
}

impl Operator for VisualHullOp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let views = CalibratedViews::read(inputs, "silhouettes", "silhouette")?;
        let masks: Vec<Vec<bool>> = views
            .images
            .iter()
            .map(|image| silhouette_mask(image, self.params.silhouette_from, self.params.threshold))
            .collect();
        let silhouettes: Vec<SilhouetteView<'_>> = (0..views.len())
            .map(|i| SilhouetteView {
                inside: &masks[i],
                width: views.images[i].width(),
                height: views.images[i].height(),
                lens: Lens::from_camera(views.camera(i)),
                camera_from_world: views.poses[i],
            })
            .collect();
        let options = VisualHullOptions {
            min: self.min,
            max: self.max,
            resolution: self.params.resolution as usize,
            truncation: self.params.truncation,
            outside: self.params.outside,
            max_voxels: self.params.max_voxels,
        };
        let hull = visual_hull(&silhouettes, &options).map_err(|e| match e {
            VisualHullError::Pose(_) => OpError::input("poses", e.to_string()),
            VisualHullError::Extraction(_) => OpError::failed(e.to_string()),
            VisualHullError::Bounds { .. } | VisualHullError::TooManyVoxels { .. } => {
                OpError::failed(e.to_string())
            }
            _ => OpError::input("silhouettes", e.to_string()),
        })?;
        let (normals, _) = vertex_normals(&hull.positions, &hull.triangles, NormalWeighting::Area);
        let volume = signed_volume(&hull.positions, &hull.triangles);
        let area = surface_area(&hull.positions, &hull.triangles);
        let mesh = Mesh {
            positions: hull.positions.iter().map(|p| p.map(|v| v as f32)).collect(),
            triangles: hull.triangles.clone(),
            normals: Some(normals.iter().map(|p| p.map(|v| v as f32)).collect()),
            ..Mesh::default()
        };
        let points = ocellus_engine::value::PointCloud {
            positions: hull
                .inside_nodes
                .iter()
                .map(|p| p.map(|v| v as f32))
                .collect(),
            colors: None,
            normals: None,
        };
        let mut m = Metrics::new();
        m.insert("views".into(), views.len() as f64);
        m.insert("nx".into(), hull.dims[0] as f64);
        m.insert("ny".into(), hull.dims[1] as f64);
        m.insert("nz".into(), hull.dims[2] as f64);
        m.insert("voxels".into(), hull.field.len() as f64);
        m.insert("voxel_size".into(), hull.voxel_size);
        m.insert("inside_nodes".into(), hull.inside_nodes.len() as f64);
        m.insert("volume".into(), volume);
        m.insert("area".into(), area);
        m.insert("vertices".into(), mesh.positions.len() as f64);
        m.insert("triangles".into(), mesh.triangles.len() as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(mesh)))
            .with("points", Value::PointCloud(Arc::new(points)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::{Distortion, Intrinsics};

    /// A camera at `eye` looking at `target` (y up), as a camera_from_world pose.
    fn look_at(eye: [f64; 3], target: [f64; 3]) -> Pose {
        let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let unit = |a: [f64; 3]| {
            let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            [a[0] / n, a[1] / n, a[2] / n]
        };
        let f = unit(sub(target, eye));
        // Camera axes: x right, y down, z forward. Pick an up that is not parallel to f.
        let up = if f[1].abs() > 0.99 {
            [0.0, 0.0, 1.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let x = unit(cross(f, up));
        let y = cross(f, x);
        let r = nalgebra::Matrix3::new(x[0], x[1], x[2], y[0], y[1], y[2], f[0], f[1], f[2]);
        let q = nalgebra::UnitQuaternion::from_matrix(&r);
        let t = -(r * nalgebra::Vector3::from(eye));
        Pose {
            rotation: [q.w, q.i, q.j, q.k],
            translation: [t[0], t[1], t[2]],
        }
    }

    fn lens(w: usize, h: usize, f: f64) -> Lens {
        Lens {
            k: Intrinsics {
                fx: f,
                fy: f,
                cx: (w as f64 - 1.0) / 2.0,
                cy: (h as f64 - 1.0) / 2.0,
                skew: 0.0,
            },
            distortion: Distortion::None,
        }
    }

    /// The exact silhouette of a sphere: pixels whose centre ray hits it.
    fn sphere_silhouette(
        lens: &Lens,
        pose: &Pose,
        w: usize,
        h: usize,
        center: [f64; 3],
        radius: f64,
    ) -> Vec<bool> {
        let r = pose.rotation_matrix();
        let t = pose.translation;
        let c = [
            r[0] * center[0] + r[1] * center[1] + r[2] * center[2] + t[0],
            r[3] * center[0] + r[4] * center[1] + r[5] * center[2] + t[1],
            r[6] * center[0] + r[7] * center[1] + r[8] * center[2] + t[2],
        ];
        let mut out = vec![false; w * h];
        for y in 0..h {
            for x in 0..w {
                let d = [
                    (x as f64 - lens.k.cx) / lens.k.fx,
                    (y as f64 - lens.k.cy) / lens.k.fy,
                    1.0,
                ];
                let dn = (d[0] * d[0] + d[1] * d[1] + 1.0).sqrt();
                let u = [d[0] / dn, d[1] / dn, d[2] / dn];
                let along = u[0] * c[0] + u[1] * c[1] + u[2] * c[2];
                let cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
                out[y * w + x] = along > 0.0 && cc - along * along <= radius * radius;
            }
        }
        out
    }

    /// `n` cameras on a ring of radius 3 at height `y`, plus, when `top`, one above and one
    /// below.
    fn ring(n: usize, top: bool) -> Vec<Pose> {
        let mut poses: Vec<Pose> = (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                let y = if i % 2 == 0 { 0.8 } else { -0.6 };
                look_at([3.0 * a.cos(), y, 3.0 * a.sin()], [0.0; 3])
            })
            .collect();
        if top {
            poses.push(look_at([0.1, 3.0, 0.0], [0.0; 3]));
            poses.push(look_at([-0.1, -3.0, 0.0], [0.0; 3]));
        }
        poses
    }

    /// One view per pose, of the same `w × h` lens, each with its mask.
    fn views_of<'a>(
        poses: &[Pose],
        masks: &'a [Vec<bool>],
        w: usize,
        h: usize,
        lens: Lens,
    ) -> Vec<SilhouetteView<'a>> {
        poses
            .iter()
            .zip(masks)
            .map(|(p, m)| SilhouetteView {
                inside: m,
                width: w,
                height: h,
                lens,
                camera_from_world: *p,
            })
            .collect()
    }

    fn sphere_hull(poses: &[Pose], resolution: usize) -> VisualHull {
        let (w, h) = (96, 96);
        let lens = lens(w, h, 110.0);
        let masks: Vec<Vec<bool>> = poses
            .iter()
            .map(|p| sphere_silhouette(&lens, p, w, h, [0.0; 3], 0.5))
            .collect();
        let views = views_of(poses, &masks, w, h, lens);
        visual_hull(
            &views,
            &VisualHullOptions {
                min: [-0.8; 3],
                max: [0.8; 3],
                resolution,
                truncation: 3.0,
                outside: Outside::Carve,
                max_voxels: 1 << 24,
            },
        )
        .unwrap()
    }

    fn norm(p: [f64; 3]) -> f64 {
        (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
    }

    #[test]
    fn signed_distance_of_a_square() {
        // A 4×4 square inside a 10×10 image: inner pixels are farther from the boundary.
        let (w, h) = (10, 10);
        let inside: Vec<bool> = (0..w * h)
            .map(|i| (3..7).contains(&(i % w)) && (3..7).contains(&(i / w)))
            .collect();
        let s = signed_distance(&inside, w, h);
        assert_eq!(s[3 * w + 3], 0.5); // edge pixel: 1 px from the outside, minus ½
        assert_eq!(s[4 * w + 4], 1.5);
        assert_eq!(s[3 * w + 2], -0.5); // just outside
        assert_eq!(s[5 * w], -2.5); // 3 px left of the square
        // No boundary at all: ±∞.
        assert!(
            signed_distance(&[true; 4], 2, 2)
                .iter()
                .all(|v| *v == f32::INFINITY)
        );
        assert!(
            signed_distance(&[false; 4], 2, 2)
                .iter()
                .all(|v| *v == f32::NEG_INFINITY)
        );
    }

    /// The hull of a sphere contains the sphere and shrinks towards it with more views:
    /// every surface vertex is outside the sphere (to within the silhouettes' pixel and the
    /// grid's sub-voxel error), the volume is above the sphere's and falls as views are added.
    #[test]
    fn sphere_hull_contains_the_sphere_and_tightens_with_views() {
        let truth = 4.0 / 3.0 * std::f64::consts::PI * 0.125;
        let mut last = f64::INFINITY;
        for (views, top) in [(3, false), (6, false), (12, true)] {
            let hull = sphere_hull(&ring(views, top), 48);
            let volume = signed_volume(&hull.positions, &hull.triangles);
            let h = hull.voxel_size;
            // A pixel at 3 units with f = 110 px is 0.027 units; allow it and a tenth of a voxel.
            let tol = 0.03 + 0.1 * h;
            let nearest = hull
                .positions
                .iter()
                .map(|p| norm(*p))
                .fold(f64::INFINITY, f64::min);
            assert!(
                nearest > 0.5 - tol,
                "{views} views: a vertex at {nearest} cuts into the sphere"
            );
            assert!(
                volume > truth * 0.97,
                "{views} views: volume {volume} < sphere {truth}"
            );
            assert!(
                volume < last,
                "{views} views: volume {volume} did not shrink from {last}"
            );
            last = volume;
        }
        // With 14 views all around the hull is within a few per cent of the sphere.
        assert!(
            last < truth * 1.12,
            "14 views: volume {last} vs sphere {truth}"
        );
    }

    /// The surface sits on the hull to a fraction of a voxel even on a coarse grid (the field
    /// is a distance, not a bit), and the volume converges as the grid is refined.
    #[test]
    fn finer_grid_converges() {
        let poses = ring(12, true);
        let run = |res: usize| {
            let hull = sphere_hull(&poses, res);
            let n = hull.positions.len() as f64;
            let radius_err = hull
                .positions
                .iter()
                .map(|p| (norm(*p) - 0.5).abs())
                .sum::<f64>()
                / n;
            (signed_volume(&hull.positions, &hull.triangles), radius_err)
        };
        let (reference, _) = run(96);
        let (v16, e16) = run(16);
        let (v32, e32) = run(32);
        // 16 nodes over 1.6 units: a voxel of 0.107; the vertices are within a tenth of it.
        assert!(
            e16 < 0.01 && e32 < 0.01,
            "mean |r − 0.5|: {e16} at 16, {e32} at 32"
        );
        assert!(
            (v32 - reference).abs() < (v16 - reference).abs(),
            "volume {v16} at 16, {v32} at 32, {reference} at 96"
        );
    }

    /// The mesh is closed and consistently oriented: its signed volume is positive and every
    /// edge is shared by exactly two triangles in opposite directions.
    #[test]
    fn mesh_is_closed_even_when_the_hull_meets_the_box() {
        let poses = ring(6, false);
        let (w, h) = (64, 64);
        let lens = lens(w, h, 70.0);
        // A sphere larger than the box: the hull is clipped by the box's faces.
        let masks: Vec<Vec<bool>> = poses
            .iter()
            .map(|p| sphere_silhouette(&lens, p, w, h, [0.0; 3], 0.9))
            .collect();
        let views = views_of(&poses, &masks, w, h, lens);
        let hull = visual_hull(
            &views,
            &VisualHullOptions {
                min: [-0.5; 3],
                max: [0.5; 3],
                resolution: 24,
                truncation: 3.0,
                outside: Outside::Carve,
                max_voxels: 1 << 20,
            },
        )
        .unwrap();
        let mut edges = std::collections::HashMap::new();
        for t in &hull.triangles {
            for e in 0..3 {
                *edges.entry((t[e], t[(e + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &count) in &edges {
            assert_eq!(count, 1, "edge {a}→{b} used {count} times");
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}→{b} has no twin");
        }
        let volume = signed_volume(&hull.positions, &hull.triangles);
        // The box's interior between the outermost nodes minus a voxel: close to 1.
        assert!(volume > 0.6 && volume <= 1.0, "volume {volume}");
    }

    /// The field is the same whatever the order of the views (the maximum is symmetric) and
    /// whatever the number of threads.
    #[test]
    fn order_and_threads_do_not_change_the_result() {
        let poses = ring(5, false);
        let a = sphere_hull(&poses, 32);
        let mut reversed = poses.clone();
        reversed.reverse();
        let b = sphere_hull(&reversed, 32);
        assert_eq!(a.field, b.field);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let c = pool.install(|| sphere_hull(&poses, 32));
        assert_eq!(a, c);
    }

    #[test]
    fn bad_input_is_an_error() {
        let lens = lens(8, 8, 10.0);
        let mask = vec![true; 64];
        let view = |pose: Pose| SilhouetteView {
            inside: &mask,
            width: 8,
            height: 8,
            lens,
            camera_from_world: pose,
        };
        let options = VisualHullOptions {
            min: [-1.0; 3],
            max: [1.0; 3],
            resolution: 8,
            truncation: 3.0,
            outside: Outside::Carve,
            max_voxels: 1000,
        };
        assert_eq!(visual_hull(&[], &options), Err(VisualHullError::NoViews));
        let mut bad = look_at([0.0, 0.0, 3.0], [0.0; 3]);
        bad.translation[0] = f64::NAN;
        assert_eq!(
            visual_hull(&[view(bad)], &options),
            Err(VisualHullError::Pose(0))
        );
        let short = SilhouetteView {
            inside: &mask[..10],
            ..view(look_at([0.0, 0.0, 3.0], [0.0; 3]))
        };
        assert!(matches!(
            visual_hull(&[short], &options),
            Err(VisualHullError::View { index: 0, .. })
        ));
        let huge = VisualHullOptions {
            resolution: 200,
            ..options.clone()
        };
        assert!(matches!(
            visual_hull(&[view(look_at([0.0, 0.0, 3.0], [0.0; 3]))], &huge),
            Err(VisualHullError::TooManyVoxels { .. })
        ));
        // A camera looking away from the box: every node is behind it, so nothing is inside.
        let away = look_at([0.0, 0.0, 3.0], [0.0, 0.0, 6.0]);
        assert_eq!(
            visual_hull(&[view(away)], &options),
            Err(VisualHullError::Empty)
        );
        let flat = VisualHullOptions {
            max: [1.0, -1.0, 1.0],
            ..options
        };
        assert!(matches!(
            visual_hull(&[view(look_at([0.0, 0.0, 3.0], [0.0; 3]))], &flat),
            Err(VisualHullError::Bounds { .. })
        ));
    }

    /// "ignore" keeps what a view cannot see; "carve" removes it.
    #[test]
    fn outside_policy() {
        // One camera seeing only the +x half of the box (it looks at x = 0.6 from close by).
        let (w, h) = (32, 32);
        let lens = lens(w, h, 40.0);
        let pose = look_at([0.6, 0.0, 1.5], [0.6, 0.0, 0.0]);
        let mask = vec![true; w * h];
        let view = SilhouetteView {
            inside: &mask,
            width: w,
            height: h,
            lens,
            camera_from_world: pose,
        };
        let run = |outside| {
            visual_hull(
                std::slice::from_ref(&view),
                &VisualHullOptions {
                    min: [-1.0; 3],
                    max: [1.0; 3],
                    resolution: 16,
                    truncation: 2.0,
                    outside,
                    max_voxels: 1 << 16,
                },
            )
            .unwrap()
        };
        let carve = run(Outside::Carve);
        let ignore = run(Outside::Ignore);
        assert!(carve.inside_nodes.iter().all(|p| p[0] > -0.45));
        assert!(ignore.inside_nodes.len() > carve.inside_nodes.len());
        assert!(ignore.inside_nodes.iter().any(|p| p[0] < -0.5));
    }
}
