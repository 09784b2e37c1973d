//! Truncated signed distance fusion of posed depth maps: `mesh.tsdf_fusion`.
//!
//! Curless & Levoy, "A volumetric method for building complex models from range images"
//! (SIGGRAPH 1996): every depth map votes, per voxel, a signed distance to the surface it sees,
//! truncated to `[−μ, μ]`, and the votes are averaged with weights; the fused surface is the
//! zero level set of the average. The projective form with truncation and a running weighted
//! average (capped to adapt to change) is KinectFusion's (Newcombe et al., "KinectFusion:
//! real-time dense surface mapping and tracking", ISMAR 2011).
//!
//! Per frame and voxel `X` (a node of a dense regular grid), `X_c = R X + t` is projected
//! through the lens (any distortion model of the engine) to the pixel `p`; the measured range
//! `r(p)` (distance from the centre of projection along the pixel's ray, bilinear between the
//! four nearest pixels when all are valid and within `μ` of each other, else the nearest pixel)
//! gives `sdf = r(p) − |X_c|`, positive in front of the surface. Voxels with `sdf < −μ`
//! (occluded, behind the surface) or whose projection misses the image or an invalid pixel are
//! left alone; the others get `d = min(1, sdf/μ)` averaged in with the frame's weight (1, or the
//! cosine between the viewing ray and the depth map's normal), the total weight capped at
//! `max_weight`. Colours are averaged the same way, from voxels within `|sdf| ≤ μ` only.
//!
//! Storage is dense within the bounds (8 bytes per voxel, 24 with colour), capped by
//! `max_voxels`. Frames are integrated in input order and every voxel's update depends only on
//! that voxel and the frame, computed in z slabs in parallel: the result is bit-identical for
//! any thread count.
//!
//! The surface is the project's watertight marching cubes (asymptotic decider) of the averaged
//! values, keeping only the triangles of cubes whose eight corners were all observed (weight
//! `> 0`), so no faces are made in unobserved space. Vertex normals are the normalized gradient
//! of the TSDF (central differences at the grid nodes, interpolated trilinearly over observed
//! nodes); vertex colours are the trilinear interpolation of the voxel colours.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Mesh, Metrics, PixelData, Pose, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::marching_cubes::{IsoSurface, MarchingCubesError, ScalarGrid, marching_cubes};
use super::normals::{cross, dot, norm, sub};
use crate::geometry::camera::Lens;
use crate::geometry::rectify::samples_f32;
use crate::sfm::depth::{DepthError, DepthKind, DepthOptions, depth_to_points};
use crate::sfm::pairs::{CalibratedViews, list_items};

param_enum! {
    /// Per-pixel weight of a frame's vote in `mesh.tsdf_fusion`.
    pub enum TsdfWeighting {
        /// Every valid pixel alike (weight 1): the plain running average.
        Constant = "constant",
        /// `|cos θ|`, θ between the pixel's ray and the depth map's normal there (estimated
        /// from the neighbouring pixels as in `sfm.depth_to_points`): grazing, less reliable
        /// measurements count less (Curless & Levoy's weighting).
        Cosine = "cosine",
    }
}

/// Why depth maps cannot be fused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TsdfError {
    /// Depth maps and poses (or colours) do not pair up.
    #[error("{depths} depth maps but {other} {what}")]
    Count {
        /// Depth maps given.
        depths: usize,
        /// Items of the other list.
        other: usize,
        /// What the other list holds (e.g. "poses").
        what: &'static str,
    },
    /// A pose with a non-finite or zero quaternion or a non-finite translation.
    #[error("pose {0} is not a finite rigid transform (quaternion non-zero, finite entries)")]
    Pose(usize),
    /// A buffer of a frame has the wrong size.
    #[error("frame {index}: {what}")]
    Frame {
        /// Frame index.
        index: usize,
        /// What is wrong.
        what: String,
    },
    /// The camera cannot back-project.
    #[error("frame {index}: {source}")]
    Camera {
        /// Frame index.
        index: usize,
        /// The back-projection error.
        source: DepthError,
    },
    /// The bounds are not finite or empty.
    #[error("bounds must be finite with min < max on every axis, got min {min:?}, max {max:?}")]
    Bounds {
        /// Lower corner.
        min: [f64; 3],
        /// Upper corner.
        max: [f64; 3],
    },
    /// No bounds given and no valid depth sample to derive them from.
    #[error("no valid depth sample in any frame, and no bounds given")]
    NoDepth,
    /// The voxel size cannot be derived.
    #[error("cannot derive a voxel size: {0}; set `voxel_size`")]
    VoxelSize(String),
    /// The grid exceeds the voxel cap.
    #[error(
        "the grid needs {nx}×{ny}×{nz} = {needed} voxels, more than max_voxels = {max}; \
         raise voxel_size (to about {suggested_voxel_size:.6} for this cap), shrink the bounds, \
         or raise max_voxels"
    )]
    TooManyVoxels {
        /// Nodes along x.
        nx: usize,
        /// Nodes along y.
        ny: usize,
        /// Nodes along z.
        nz: usize,
        /// `nx·ny·nz` (saturating).
        needed: u64,
        /// The cap.
        max: u64,
        /// A voxel size that would fit the cap for these bounds.
        suggested_voxel_size: f64,
    },
    /// Iso-surface extraction failed.
    #[error("marching cubes: {0}")]
    Extraction(#[from] MarchingCubesError),
}

/// One posed depth map.
#[derive(Debug, Clone, Copy)]
pub struct DepthFrame<'a> {
    /// Raw samples, row-major `width × height` (scaled by `depth_scale`; non-finite, ≤ 0 and
    /// out-of-range samples are invalid).
    pub depth: &'a [f32],
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Intrinsics and distortion.
    pub lens: Lens,
    /// World-to-camera transform.
    pub camera_from_world: Pose,
    /// Linear RGB per pixel, if colours are fused.
    pub color: Option<&'a [[f32; 3]]>,
}

/// Options of [`tsdf_fusion`].
#[derive(Debug, Clone, PartialEq)]
pub struct TsdfOptions {
    /// Voxel edge, scene units; `None` derives it from the bounds and `resolution`.
    pub voxel_size: Option<f64>,
    /// Grid nodes along the longest axis when `voxel_size` is `None`.
    pub resolution: usize,
    /// Truncation distance μ in voxels.
    pub truncation: f64,
    /// `[min, max]` corners, scene units; `None`: the back-projected points of all frames,
    /// padded by μ.
    pub bounds: Option<([f64; 3], [f64; 3])>,
    /// Scene units per depth sample.
    pub depth_scale: f64,
    /// Z or range depth.
    pub depth_kind: DepthKind,
    /// Valid depth range after scaling (Z or range, as read).
    pub min_depth: f64,
    /// See `min_depth`.
    pub max_depth: f64,
    /// Per-pixel weighting.
    pub weighting: TsdfWeighting,
    /// Cap on a voxel's accumulated weight (`f64::INFINITY`: none).
    pub max_weight: f64,
    /// Cap on `nx·ny·nz`.
    pub max_voxels: u64,
}

impl Default for TsdfOptions {
    fn default() -> Self {
        TsdfOptions {
            voxel_size: None,
            resolution: 256,
            truncation: 4.0,
            bounds: None,
            depth_scale: 1.0,
            depth_kind: DepthKind::Z,
            min_depth: 0.0,
            max_depth: f64::INFINITY,
            weighting: TsdfWeighting::Constant,
            max_weight: f64::INFINITY,
            max_voxels: DEFAULT_MAX_VOXELS,
        }
    }
}

/// 256³ voxels: 128 MiB of TSDF and weights (384 MiB with colours).
pub const DEFAULT_MAX_VOXELS: u64 = 256 * 256 * 256;

/// The geometry of a voxel grid: node `(i, j, k)` lies at `origin + voxel_size·(i, j, k)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelGrid {
    /// Nodes per axis.
    pub dims: [usize; 3],
    /// Position of node `(0, 0, 0)`.
    pub origin: [f64; 3],
    /// Node spacing, scene units.
    pub voxel_size: f64,
}

impl VoxelGrid {
    /// `nx·ny·nz`.
    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// True for a grid without nodes.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }
}

/// The TSDF and weight of one voxel.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Voxel {
    /// Averaged truncated distance, in units of μ, in `[−1, 1]` (meaningful where `weight > 0`).
    pub tsdf: f32,
    /// Accumulated weight; 0: never observed.
    pub weight: f32,
}

/// The colour of one voxel.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ColorVoxel {
    /// Averaged linear RGB.
    pub rgb: [f32; 3],
    /// Accumulated weight.
    pub weight: f32,
}

/// A dense TSDF volume.
#[derive(Debug, Clone, PartialEq)]
pub struct TsdfVolume {
    /// The grid.
    pub grid: VoxelGrid,
    /// Truncation distance μ, scene units.
    pub truncation: f64,
    /// Voxels, x fastest.
    pub voxels: Vec<Voxel>,
    /// Voxel colours, when fused.
    pub colors: Option<Vec<ColorVoxel>>,
    /// Frames integrated.
    pub frames: usize,
}

/// A frame ready to integrate: the range image in the camera frame and per-pixel weights.
struct PreparedFrame<'a> {
    width: usize,
    height: usize,
    lens: Lens,
    rotation: [f64; 9],
    translation: [f64; 3],
    /// Range along the pixel's ray, NaN where invalid.
    range: Vec<f32>,
    /// Per-pixel weight (empty: constant 1).
    weight: Vec<f32>,
    color: Option<&'a [[f32; 3]]>,
    /// For distorting lenses: the box of pinhole-normalized coordinates the image sees (a
    /// distortion polynomial folds back outside the field of view).
    field: Option<[f64; 4]>,
}

fn check_pose(index: usize, p: &Pose) -> Result<(), TsdfError> {
    let q = p.rotation;
    let n = q.iter().map(|v| v * v).sum::<f64>();
    if !(q.iter().chain(&p.translation).all(|v| v.is_finite()) && n > 0.0 && n.is_finite()) {
        return Err(TsdfError::Pose(index));
    }
    Ok(())
}

fn check_frame(index: usize, f: &DepthFrame<'_>) -> Result<(), TsdfError> {
    check_pose(index, &f.camera_from_world)?;
    let n = f.width.checked_mul(f.height);
    if n != Some(f.depth.len()) {
        return Err(TsdfError::Frame {
            index,
            what: format!(
                "a {}×{} depth map needs {} samples, got {}",
                f.width,
                f.height,
                f.width.saturating_mul(f.height),
                f.depth.len()
            ),
        });
    }
    if let Some(c) = f.color
        && c.len() != f.depth.len()
    {
        return Err(TsdfError::Frame {
            index,
            what: format!(
                "the colour image has {} pixels but the depth map {}",
                c.len(),
                f.depth.len()
            ),
        });
    }
    Ok(())
}

fn depth_options(o: &TsdfOptions, normals: bool) -> DepthOptions {
    DepthOptions {
        depth_scale: o.depth_scale,
        kind: o.depth_kind,
        min_depth: o.min_depth,
        max_depth: o.max_depth,
        stride: 1,
        normals,
        max_depth_jump: 0.05,
    }
}

fn prepare<'a>(
    index: usize,
    f: &DepthFrame<'a>,
    o: &TsdfOptions,
) -> Result<PreparedFrame<'a>, TsdfError> {
    let cosine = o.weighting == TsdfWeighting::Cosine;
    let points = depth_to_points(
        f.depth,
        f.width,
        f.height,
        &f.lens,
        None,
        None,
        &depth_options(o, false),
    )
    .map_err(|source| TsdfError::Camera { index, source })?;
    let norm = |p: &[f32; 3]| {
        let p = p.map(f64::from);
        (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
    };
    let range: Vec<f32> = points
        .xyz
        .iter()
        .map(|p| {
            let r = norm(p);
            if r.is_finite() && r > 0.0 {
                r as f32
            } else {
                f32::NAN
            }
        })
        .collect();
    let weight: Vec<f32> = if cosine {
        cosine_weights(&points.xyz, f.width, f.height)
    } else {
        Vec::new()
    };
    let field = if f.lens.is_pinhole() {
        None
    } else {
        // The pinhole-normalized coordinates of the border pixels, padded by a pixel.
        let mut b = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let (w, h) = (f.width as f64, f.height as f64);
        let steps = 64usize;
        for s in 0..=steps {
            let a = s as f64 / steps as f64;
            for px in [
                [a * w - 0.5, -1.5],
                [a * w - 0.5, h + 0.5],
                [-1.5, a * h - 0.5],
                [w + 0.5, a * h - 0.5],
            ] {
                if let Some(n) = f.lens.undistort(f.lens.from_pixel(px))
                    && n[0].is_finite()
                    && n[1].is_finite()
                {
                    b = [
                        b[0].min(n[0]),
                        b[1].max(n[0]),
                        b[2].min(n[1]),
                        b[3].max(n[1]),
                    ];
                }
            }
        }
        Some(b)
    };
    Ok(PreparedFrame {
        width: f.width,
        height: f.height,
        lens: f.lens,
        rotation: f.camera_from_world.rotation_matrix(),
        translation: f.camera_from_world.translation,
        range,
        weight,
        color: f.color,
        field,
    })
}

/// `|cos θ|` per pixel of an organized camera-frame cloud (NaN where invalid): θ between the
/// ray and the normal from the 4-neighbours (central differences, one-sided next to an invalid
/// neighbour or a depth jump over 5 %, as `sfm.depth_to_points`); 0 where no normal can be
/// estimated, so isolated samples and thin slivers do not vote.
fn cosine_weights(xyz: &[[f32; 3]], w: usize, h: usize) -> Vec<f32> {
    let at = |x: usize, y: usize| -> Option<[f64; 3]> {
        let p = xyz.get(y * w + x)?;
        p[2].is_finite().then(|| p.map(f64::from))
    };
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let Some(p) = at(x, y) else {
                return 0.0;
            };
            let near = |q: Option<[f64; 3]>| q.filter(|q| (q[2] - p[2]).abs() <= 0.05 * p[2]);
            let diff = |minus: Option<[f64; 3]>, plus: Option<[f64; 3]>| match (minus, plus) {
                (Some(a), Some(b)) => Some(sub(b, a)),
                (None, Some(b)) => Some(sub(b, p)),
                (Some(a), None) => Some(sub(p, a)),
                (None, None) => None,
            };
            let xm = x.checked_sub(1).and_then(|xx| near(at(xx, y)));
            let xp = (x + 1 < w).then(|| near(at(x + 1, y))).flatten();
            let ym = y.checked_sub(1).and_then(|yy| near(at(x, yy)));
            let yp = (y + 1 < h).then(|| near(at(x, y + 1))).flatten();
            let (Some(du), Some(dv)) = (diff(xm, xp), diff(ym, yp)) else {
                return 0.0;
            };
            let n = cross(du, dv);
            let (ln, lp) = (norm(n), norm(p));
            let c = dot(n, p).abs() / (ln * lp);
            if c.is_finite() { c as f32 } else { 0.0 }
        })
        .collect()
}

/// An axis-aligned box by its smallest and largest corners.
pub type Bounds = ([f64; 3], [f64; 3]);

/// The bounding box of every valid back-projected sample of `frames` (world coordinates).
pub fn depth_bounds(
    frames: &[DepthFrame<'_>],
    options: &TsdfOptions,
) -> Result<Option<Bounds>, TsdfError> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for (index, f) in frames.iter().enumerate() {
        check_frame(index, f)?;
        let points = depth_to_points(
            f.depth,
            f.width,
            f.height,
            &f.lens,
            Some(&f.camera_from_world),
            None,
            &depth_options(options, false),
        )
        .map_err(|source| TsdfError::Camera { index, source })?;
        for p in &points.cloud.positions {
            for k in 0..3 {
                let v = f64::from(p[k]);
                lo[k] = lo[k].min(v);
                hi[k] = hi[k].max(v);
            }
        }
    }
    Ok((lo[0] <= hi[0]).then_some((lo, hi)))
}

/// The voxel grid for `frames` under `options` (bounds, voxel size, the `max_voxels` cap).
pub fn plan_grid(frames: &[DepthFrame<'_>], options: &TsdfOptions) -> Result<VoxelGrid, TsdfError> {
    let tau = options.truncation;
    let (min, max, padded) = match options.bounds {
        Some((min, max)) => (min, max, false),
        None => {
            let (min, max) = depth_bounds(frames, options)?.ok_or(TsdfError::NoDepth)?;
            (min, max, true)
        }
    };
    if !(0..3).all(|k| min[k].is_finite() && max[k].is_finite() && min[k] <= max[k])
        || (!padded && !(0..3).all(|k| min[k] < max[k]))
    {
        return Err(TsdfError::Bounds { min, max });
    }
    let extent = (0..3).map(|k| max[k] - min[k]).fold(0.0, f64::max);
    let h = match options.voxel_size {
        Some(h) => h,
        None => {
            // Nodes along the longest axis: extent/h + 1 (+ 2τ of padding) = resolution.
            let cells = options.resolution as f64 - 1.0 - if padded { 2.0 * tau } else { 0.0 };
            if cells < 1.0 {
                return Err(TsdfError::VoxelSize(format!(
                    "resolution {} leaves no cells after 2 × {tau} voxels of padding",
                    options.resolution
                )));
            }
            if extent <= 0.0 {
                return Err(TsdfError::VoxelSize(
                    "the depth maps' points span no volume".into(),
                ));
            }
            extent / cells
        }
    };
    if !(h.is_finite() && h > 0.0) {
        return Err(TsdfError::VoxelSize(format!("voxel size {h}")));
    }
    // Nodes along axis k for voxel size s: the extent plus 2τ·s of padding (auto bounds).
    let pad_voxels = if padded { tau } else { 0.0 };
    let nodes = |k: usize, s: f64| {
        ((max[k] - min[k] + 2.0 * pad_voxels * s) / s - 1e-9)
            .ceil()
            .max(0.0)
            + 1.0
    };
    let count = |s: f64| nodes(0, s) * nodes(1, s) * nodes(2, s);
    let n = [nodes(0, h), nodes(1, h), nodes(2, h)];
    let needed_f = count(h);
    let cap = options.max_voxels;
    if needed_f > cap as f64 {
        // The smallest voxel size (to 2 %) that fits: the fixed +1 and padding nodes make the
        // cube-root estimate too small, so grow it until it fits.
        let mut s = h * (needed_f / cap.max(1) as f64).cbrt();
        for _ in 0..2000 {
            if count(s) <= cap as f64 {
                break;
            }
            s *= 1.02;
        }
        let dim = |v: f64| {
            if v < usize::MAX as f64 {
                v as usize
            } else {
                usize::MAX
            }
        };
        return Err(TsdfError::TooManyVoxels {
            nx: dim(n[0]),
            ny: dim(n[1]),
            nz: dim(n[2]),
            needed: if needed_f < u64::MAX as f64 {
                needed_f as u64
            } else {
                u64::MAX
            },
            max: cap,
            suggested_voxel_size: s,
        });
    }
    let pad = pad_voxels * h;
    let min = min.map(|v| v - pad);
    Ok(VoxelGrid {
        dims: n.map(|v| v as usize),
        origin: min,
        voxel_size: h,
    })
}

impl TsdfVolume {
    /// An empty (unobserved) volume over `grid` with truncation `truncation` (scene units).
    pub fn new(grid: VoxelGrid, truncation: f64, with_color: bool) -> TsdfVolume {
        let n = grid.len();
        TsdfVolume {
            grid,
            truncation,
            voxels: vec![Voxel::default(); n],
            colors: with_color.then(|| vec![ColorVoxel::default(); n]),
            frames: 0,
        }
    }

    /// Voxels with weight > 0.
    pub fn observed(&self) -> usize {
        self.voxels.iter().filter(|v| v.weight > 0.0).count()
    }

    fn integrate_prepared(&mut self, f: &PreparedFrame<'_>, options: &TsdfOptions) {
        let g = self.grid;
        let slab = g.dims[0] * g.dims[1];
        let mu = self.truncation;
        let max_weight = options.max_weight;
        if slab == 0 {
            return;
        }
        match self.colors.as_mut() {
            Some(colors) => self
                .voxels
                .par_chunks_mut(slab)
                .zip(colors.par_chunks_mut(slab))
                .enumerate()
                .for_each(|(k, (v, c))| integrate_slab(&g, k, v, Some(c), f, mu, max_weight)),
            None => self
                .voxels
                .par_chunks_mut(slab)
                .enumerate()
                .for_each(|(k, v)| integrate_slab(&g, k, v, None, f, mu, max_weight)),
        }
        self.frames += 1;
    }

    /// Integrates one frame (see the module documentation).
    pub fn integrate(
        &mut self,
        index: usize,
        frame: &DepthFrame<'_>,
        options: &TsdfOptions,
    ) -> Result<(), TsdfError> {
        check_frame(index, frame)?;
        let prepared = prepare(index, frame, options)?;
        self.integrate_prepared(&prepared, options);
        Ok(())
    }

    fn value(&self, i: usize, j: usize, k: usize) -> Option<f64> {
        let v = self.voxels.get(self.grid.index(i, j, k))?;
        (v.weight > 0.0).then_some(f64::from(v.tsdf))
    }

    /// The TSDF gradient at node `(i, j, k)`: central differences, one-sided next to an
    /// unobserved node or the border, zero along an axis without an observed neighbour.
    fn node_gradient(&self, n: [usize; 3]) -> Option<[f64; 3]> {
        let c = self.value(n[0], n[1], n[2])?;
        let mut g = [0.0; 3];
        for (a, ga) in g.iter_mut().enumerate() {
            let at = |d: isize| {
                let mut m = n;
                let x = m[a] as isize + d;
                if x < 0 || x as usize >= self.grid.dims[a] {
                    return None;
                }
                m[a] = x as usize;
                self.value(m[0], m[1], m[2])
            };
            *ga = match (at(-1), at(1)) {
                (Some(lo), Some(hi)) => 0.5 * (hi - lo),
                (None, Some(hi)) => hi - c,
                (Some(lo), None) => c - lo,
                (None, None) => 0.0,
            };
        }
        Some(g)
    }

    /// The cell containing grid coordinates `q` and the trilinear weights of its 8 corners.
    fn cell(&self, q: [f64; 3]) -> ([usize; 3], [f64; 8]) {
        let d = self.grid.dims;
        let mut base = [0usize; 3];
        let mut frac = [0.0; 3];
        for k in 0..3 {
            let hi = d[k].saturating_sub(2) as f64;
            let b = q[k].floor().clamp(0.0, hi);
            base[k] = b as usize;
            frac[k] = (q[k] - b).clamp(0.0, 1.0);
        }
        let w = std::array::from_fn(|c| {
            let s = |k: usize, bit: usize| if bit == 1 { frac[k] } else { 1.0 - frac[k] };
            s(0, c & 1) * s(1, (c >> 1) & 1) * s(2, c >> 2)
        });
        (base, w)
    }

    fn corner(&self, base: [usize; 3], c: usize) -> [usize; 3] {
        let d = self.grid.dims;
        [
            (base[0] + (c & 1)).min(d[0] - 1),
            (base[1] + ((c >> 1) & 1)).min(d[1] - 1),
            (base[2] + (c >> 2)).min(d[2] - 1),
        ]
    }

    /// The unit TSDF gradient (outward normal) at grid coordinates `q`.
    fn normal_at(&self, q: [f64; 3]) -> [f32; 3] {
        let (base, w) = self.cell(q);
        let mut s = [0.0; 3];
        for (c, wc) in w.iter().enumerate() {
            if *wc == 0.0 {
                continue;
            }
            if let Some(g) = self.node_gradient(self.corner(base, c)) {
                for k in 0..3 {
                    s[k] += wc * g[k];
                }
            }
        }
        let len = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        if len > 0.0 && len.is_finite() {
            s.map(|v| (v / len) as f32)
        } else {
            [0.0; 3]
        }
    }

    /// The colour at grid coordinates `q` (trilinear over corners with colour weight > 0).
    fn color_at(&self, colors: &[ColorVoxel], q: [f64; 3]) -> [f32; 3] {
        let (base, w) = self.cell(q);
        let (mut s, mut total) = ([0.0f64; 3], 0.0);
        for (c, wc) in w.iter().enumerate() {
            let n = self.corner(base, c);
            if let Some(v) = colors.get(self.grid.index(n[0], n[1], n[2]))
                && v.weight > 0.0
                && *wc > 0.0
            {
                for (sk, rk) in s.iter_mut().zip(v.rgb) {
                    *sk += wc * f64::from(rk);
                }
                total += wc;
            }
        }
        if total > 0.0 {
            s.map(|v| (v / total) as f32)
        } else {
            [0.0; 3]
        }
    }

    /// The zero level set over fully observed cubes (see the module documentation).
    pub fn extract(&self) -> Result<FusedSurface, TsdfError> {
        let g = self.grid;
        let values: Vec<f64> = self
            .voxels
            .par_iter()
            .map(|v| {
                if v.weight > 0.0 {
                    f64::from(v.tsdf)
                } else {
                    1.0
                }
            })
            .collect();
        let iso = marching_cubes(
            ScalarGrid {
                values: &values,
                dims: g.dims,
                origin: g.origin,
                spacing: g.voxel_size,
            },
            0.0,
        )?;
        drop(values);
        let h = g.voxel_size;
        let grid_coords = |p: [f64; 3]| [0, 1, 2].map(|k| (p[k] - g.origin[k]) / h);
        // A triangle lies in the closed cube containing its centroid (its vertices are on that
        // cube's edges, or its centre).
        let keep: Vec<bool> = iso
            .triangles
            .par_iter()
            .map(|t| {
                let mut c = [0.0; 3];
                for &v in t {
                    let p = iso.positions.get(v as usize).copied().unwrap_or([0.0; 3]);
                    for k in 0..3 {
                        c[k] += p[k] / 3.0;
                    }
                }
                let (base, _) = self.cell(grid_coords(c));
                (0..8).all(|corner| {
                    let n = self.corner(base, corner);
                    self.value(n[0], n[1], n[2]).is_some()
                })
            })
            .collect();
        let mut remap = vec![u32::MAX; iso.positions.len()];
        let mut used = vec![false; iso.positions.len()];
        for (t, k) in iso.triangles.iter().zip(&keep) {
            if *k {
                for &v in t {
                    if let Some(u) = used.get_mut(v as usize) {
                        *u = true;
                    }
                }
            }
        }
        let mut positions = Vec::new();
        for (i, p) in iso.positions.iter().enumerate() {
            if used[i] {
                remap[i] = positions.len() as u32;
                positions.push(*p);
            }
        }
        let triangles: Vec<[u32; 3]> = iso
            .triangles
            .iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(t, _)| t.map(|v| remap[v as usize]))
            .collect();
        let normals: Vec<[f32; 3]> = positions
            .par_iter()
            .map(|p| self.normal_at(grid_coords(*p)))
            .collect();
        let colors = self.colors.as_ref().map(|cv| {
            positions
                .par_iter()
                .map(|p| self.color_at(cv, grid_coords(*p)))
                .collect()
        });
        Ok(FusedSurface {
            surface: IsoSurface {
                positions,
                triangles,
            },
            normals,
            colors,
        })
    }
}

/// The extracted surface with per-vertex attributes.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedSurface {
    /// Positions (f64) and counter-clockwise triangles seen from outside (the observed free
    /// space).
    pub surface: IsoSurface,
    /// Unit normals from the TSDF gradient, pointing into free space.
    pub normals: Vec<[f32; 3]>,
    /// Vertex colours (linear RGB), when fused.
    pub colors: Option<Vec<[f32; 3]>>,
}

/// The range at sub-pixel `(x, y)`: bilinear over the 4 nearest pixels when all are valid and
/// within `mu` of each other, else the nearest pixel; `None` outside the image or invalid.
/// Also returns the nearest pixel's index.
fn sample_range(f: &PreparedFrame<'_>, x: f64, y: f64, mu: f64) -> Option<(f64, usize)> {
    let (w, h) = (f.width as f64, f.height as f64);
    if !((-0.5..w - 0.5).contains(&x) && (-0.5..h - 0.5).contains(&y)) {
        return None;
    }
    let nx = (x.round() as usize).min(f.width - 1);
    let ny = (y.round() as usize).min(f.height - 1);
    let nearest = ny * f.width + nx;
    let (x0, y0) = (x.floor(), y.floor());
    if x0 >= 0.0 && y0 >= 0.0 && x0 + 1.0 < w && y0 + 1.0 < h {
        let (ix, iy) = (x0 as usize, y0 as usize);
        let i = iy * f.width + ix;
        let r = [i, i + 1, i + f.width, i + f.width + 1]
            .map(|j| f64::from(f.range.get(j).copied().unwrap_or(f32::NAN)));
        let lo = r.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = r.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if r.iter().all(|v| v.is_finite()) && hi - lo <= mu {
            let (fx, fy) = (x - x0, y - y0);
            let top = r[0] + fx * (r[1] - r[0]);
            let bottom = r[2] + fx * (r[3] - r[2]);
            return Some((top + fy * (bottom - top), nearest));
        }
    }
    let r = f64::from(*f.range.get(nearest)?);
    r.is_finite().then_some((r, nearest))
}

#[allow(clippy::too_many_arguments)]
fn integrate_slab(
    g: &VoxelGrid,
    k: usize,
    voxels: &mut [Voxel],
    mut colors: Option<&mut [ColorVoxel]>,
    f: &PreparedFrame<'_>,
    mu: f64,
    max_weight: f64,
) {
    let r = &f.rotation;
    let h = g.voxel_size;
    let [nx, ny, _] = g.dims;
    let col = |c: usize| [r[c] * h, r[3 + c] * h, r[6 + c] * h];
    let dx = col(0);
    let z = g.origin[2] + h * k as f64;
    for j in 0..ny {
        let y = g.origin[1] + h * j as f64;
        let x0 = g.origin[0];
        // X_c of node (0, j, k); each step in i adds R·(h, 0, 0).
        let base = [0, 1, 2].map(|a| r[3 * a] * x0 + r[3 * a + 1] * y + r[3 * a + 2] * z);
        let base = [0, 1, 2].map(|a| base[a] + f.translation[a]);
        for i in 0..nx {
            let fi = i as f64;
            let xc = [0, 1, 2].map(|a| base[a] + fi * dx[a]);
            if xc[2] <= 0.0 || xc[2].is_nan() {
                continue;
            }
            let n = [xc[0] / xc[2], xc[1] / xc[2]];
            if let Some(b) = f.field
                && !((b[0]..=b[1]).contains(&n[0]) && (b[2]..=b[3]).contains(&n[1]))
            {
                continue;
            }
            let px = f.lens.to_pixel(f.lens.distort(n));
            let Some((range, nearest)) = sample_range(f, px[0], px[1], mu) else {
                continue;
            };
            let dist = (xc[0] * xc[0] + xc[1] * xc[1] + xc[2] * xc[2]).sqrt();
            let sdf = range - dist;
            if sdf < -mu || sdf.is_nan() {
                continue;
            }
            let wf = match f.weight.get(nearest) {
                Some(&w) => f64::from(w),
                None if f.weight.is_empty() => 1.0,
                None => 0.0,
            };
            if wf <= 0.0 || wf.is_nan() {
                continue;
            }
            let d = (sdf / mu).min(1.0);
            let at = i + nx * j;
            let Some(v) = voxels.get_mut(at) else {
                continue;
            };
            let w0 = f64::from(v.weight);
            let w1 = w0 + wf;
            v.tsdf = ((f64::from(v.tsdf) * w0 + d * wf) / w1) as f32;
            v.weight = w1.min(max_weight) as f32;
            if sdf <= mu
                && let (Some(cs), Some(image)) = (colors.as_deref_mut(), f.color)
                && let (Some(c), Some(rgb)) = (cs.get_mut(at), image.get(nearest))
            {
                let w0 = f64::from(c.weight);
                let w1 = w0 + wf;
                for (cm, im) in c.rgb.iter_mut().zip(rgb.iter()) {
                    *cm = ((f64::from(*cm) * w0 + f64::from(*im) * wf) / w1) as f32;
                }
                c.weight = w1.min(max_weight) as f32;
            }
        }
    }
}

/// The fused volume and its surface.
#[derive(Debug, Clone, PartialEq)]
pub struct TsdfResult {
    /// The volume.
    pub volume: TsdfVolume,
    /// Its zero level set.
    pub surface: FusedSurface,
}

/// Fuses `frames` in order into a dense TSDF volume and extracts its surface (see the module
/// documentation). Colours are fused when every frame has them.
pub fn tsdf_fusion(
    frames: &[DepthFrame<'_>],
    options: &TsdfOptions,
) -> Result<TsdfResult, TsdfError> {
    for (index, f) in frames.iter().enumerate() {
        check_frame(index, f)?;
    }
    let with_color = !frames.is_empty() && frames.iter().all(|f| f.color.is_some());
    if let Some(i) = frames.iter().position(|f| f.color.is_some() != with_color) {
        return Err(TsdfError::Frame {
            index: i,
            what: "colour given for some frames only".into(),
        });
    }
    let grid = plan_grid(frames, options)?;
    let mut volume = TsdfVolume::new(grid, options.truncation * grid.voxel_size, with_color);
    for (index, f) in frames.iter().enumerate() {
        let prepared = prepare(index, f, options)?;
        volume.integrate_prepared(&prepared, options);
    }
    let surface = volume.extract()?;
    Ok(TsdfResult { volume, surface })
}

params! {
    /// Parameters of `mesh.tsdf_fusion`.
    pub struct TsdfFusionParams {
        /// Voxel edge (grid node spacing). None (the default): the longest side of the bounds
        /// divided so that it has `resolution` nodes.
        voxel_size: Option<f64> = None => [above = 0.0, unit = "scene units"],
        /// Grid nodes along the longest axis of the bounds when `voxel_size` is not set
        /// (padding included). Default 256.
        resolution: u32 = 256 => [min = 4, max = 65536],
        /// Truncation distance μ, in voxels: signed distances are clamped to [−μ, μ] and
        /// voxels more than μ behind the measured surface are not updated. Default 4.
        truncation: f64 = 4.0 => [above = 0.0, max = 1000.0, unit = "voxels"],
        /// Lower corner of the volume. None (the default): the bounding box of all valid
        /// back-projected depth samples, padded by μ (give `max` too, or neither).
        min: Option<[f64; 3]> = None => [unit = "scene units"],
        /// Upper corner of the volume; see `min`.
        max: Option<[f64; 3]> = None => [unit = "scene units"],
        /// Scene units per depth sample (0.001 for millimetre u16 depth). Default 1.
        depth_scale: f64 = 1.0 => [above = 0.0],
        /// What a sample measures: "z" (along the optical axis, RGB-D cameras) or "range"
        /// (along the ray, `capture.render`'s depth). Default "z".
        depth_kind: DepthKind = DepthKind::Z,
        /// Nearest valid depth after scaling (0 is always "no data"). Default 0.
        min_depth: f64 = 0.0 => [min = 0.0, unit = "scene units"],
        /// Farthest valid depth after scaling; None (the default): no limit.
        max_depth: Option<f64> = None => [above = 0.0, unit = "scene units"],
        /// Per-pixel weight: "constant" (1) or "cosine" (|cos| between the ray and the depth
        /// map's normal). Default "constant".
        weighting: TsdfWeighting = TsdfWeighting::Constant,
        /// Cap on a voxel's accumulated weight (a running average that keeps adapting); None
        /// (the default): no cap, the plain weighted mean of all frames.
        max_weight: Option<f64> = None => [above = 0.0],
        /// Largest grid, nx·ny·nz nodes (8 bytes each, 24 with colour, plus 8 during
        /// extraction). Default 16777216 = 256³.
        max_voxels: u64 = 16777216 => [min = 1],
    }
}

/// `mesh.tsdf_fusion`. See [`tsdf_fusion`].
#[derive(Debug, Clone, PartialEq)]
pub struct TsdfFusion {
    params: TsdfFusionParams,
}

impl Op for TsdfFusion {
    type Params = TsdfFusionParams;
    const ID: &'static str = "mesh.tsdf_fusion";
    const SUMMARY: &'static str = "Fuses posed depth maps into a truncated signed distance volume and meshes its zero \
         level set (Curless & Levoy; KinectFusion).";
    const DOC: &'static str = r#"
Volumetric fusion of depth maps from known cameras (Curless & Levoy, "A volumetric method for
building complex models from range images", SIGGRAPH 1996; the projective TSDF with truncation
and weights of Newcombe et al., "KinectFusion", ISMAR 2011). Frame i is depth[i] seen by
cameras[i] (or the single camera, for every frame) at poses[i] (camera_from_world) — the lists
`capture.render` and `io.read_poses` output. Each grid node X is projected through the lens
(distortion included); the measured range r along that pixel's ray (bilinear between valid,
continuous neighbours) gives sdf = r − |X_c|, positive in front of the surface. Nodes more
than μ = truncation·voxel_size behind the surface, or seeing an invalid pixel (0, NaN, ±inf,
outside [min_depth, max_depth]) are not updated; the others average in min(1, sdf/μ) with
weight 1 ("constant") or |cos| of the ray and the depth normal ("cosine"), the weight capped at
`max_weight`. Frames are integrated in order; the result does not depend on the thread count.

Storage is a dense grid over the bounds (`min`/`max`, default: the back-projected points of all
frames padded by μ), 8 bytes per node (24 with colour), at most `max_voxels` nodes — a larger
grid is an error naming the node count needed and a voxel size that fits. The mesh is the
watertight marching cubes (asymptotic decider) of the averaged field, keeping only cubes whose
8 corners were all observed, so unobserved space makes no faces (holes stay open). Triangles
are counter-clockwise seen from free space; vertex normals are the TSDF gradient; vertex colours
(from `color`, linear RGB: f32 as is, u8/u16 scaled to [0, 1]) are averaged from nodes within μ
of the surface.

Metrics: `frames`, `voxels` (nx·ny·nz), `nx`, `ny`, `nz`, `observed_voxels`, `voxel_size`,
`truncation` (μ, scene units), `vertices`, `triangles`.

Example:
    "fused": (op: "mesh.tsdf_fusion",
              inputs: { "depth": "shots.depths", "cameras": "shots.cameras", "poses": "shots.poses" },
              params: (depth_kind: "range", voxel_size: Some(0.01), truncation: 4)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "depth",
                PortType::Image.list_of(),
                "Depth maps, one channel (u8, u16 or f32), scaled by depth_scale.",
            ),
            PortSpec::new(
                "cameras",
                PortType::Camera.list_of(),
                "One camera per depth map, or one for all; sizes must match the depth maps.",
            ),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "camera_from_world per depth map.",
            ),
            PortSpec::new(
                "color",
                PortType::Image.list_of(),
                "Colour per depth map, same sizes (gray, RGB or RGBA): vertex colours.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The fused surface with normals (and colours).",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "frames, voxels, nx, ny, nz, observed_voxels, voxel_size, truncation, vertices, \
                 triangles.",
            ),
        ]
    }

    fn new(p: TsdfFusionParams) -> Result<Self, String> {
        if let Some(h) = p.voxel_size
            && !(h.is_finite() && h > 0.0)
        {
            return Err(format!("`voxel_size` must be finite and > 0, got {h}"));
        }
        if !(p.truncation.is_finite() && p.truncation > 0.0) {
            return Err(format!(
                "`truncation` must be finite and > 0 (voxels), got {}",
                p.truncation
            ));
        }
        if p.voxel_size.is_none() && (f64::from(p.resolution) - 1.0 - 2.0 * p.truncation) < 1.0 {
            return Err(format!(
                "`resolution` {} is too small for 2 × {} voxels of truncation padding",
                p.resolution, p.truncation
            ));
        }
        match (p.min, p.max) {
            (Some(lo), Some(hi)) => {
                if !(0..3).all(|k| lo[k].is_finite() && hi[k].is_finite() && lo[k] < hi[k]) {
                    return Err(format!(
                        "`min` {lo:?} and `max` {hi:?} must be finite with min < max on every axis"
                    ));
                }
            }
            (None, None) => {}
            _ => return Err("give both `min` and `max`, or neither".into()),
        }
        crate::sfm::depth::check_depth_scaling(p.depth_scale, p.min_depth, p.max_depth)?;
        if let Some(w) = p.max_weight
            && !(w.is_finite() && w > 0.0)
        {
            return Err(format!("`max_weight` must be finite and > 0, got {w}"));
        }
        if p.max_voxels == 0 {
            return Err("`max_voxels` must be ≥ 1".into());
        }
        Ok(TsdfFusion { params: p })
    }
}

impl TsdfFusion {
    fn options(&self) -> TsdfOptions {
        let p = &self.params;
        TsdfOptions {
            voxel_size: p.voxel_size,
            resolution: p.resolution as usize,
            truncation: p.truncation,
            bounds: p.min.zip(p.max),
            depth_scale: p.depth_scale,
            depth_kind: p.depth_kind,
            min_depth: p.min_depth,
            max_depth: p.max_depth.unwrap_or(f64::INFINITY),
            weighting: p.weighting,
            max_weight: p.max_weight.unwrap_or(f64::INFINITY),
            max_voxels: p.max_voxels,
        }
    }
}

/// Linear RGB per pixel of a colour image: f32 as is, u8 and u16 scaled to [0, 1]; gray
/// replicated, alpha dropped.
fn rgb_of(image: &Image) -> Vec<[f32; 3]> {
    let ch = image.channels().count().max(1);
    let n = image.width() * image.height();
    let samples: Vec<f32> = match image.data() {
        PixelData::U8(v) => v.iter().map(|&x| f32::from(x) / 255.0).collect(),
        PixelData::U16(v) => v.iter().map(|&x| f32::from(x) / 65535.0).collect(),
        PixelData::F32(v) => v.clone(),
    };
    (0..n)
        .map(|i| {
            let at = |c: usize| samples.get(i * ch + c.min(ch - 1)).copied().unwrap_or(0.0);
            if ch >= 3 {
                [at(0), at(1), at(2)]
            } else {
                [at(0); 3]
            }
        })
        .collect()
}

impl Operator for TsdfFusion {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let views = CalibratedViews::read(inputs, "depth", "depth map")?;
        let colors = list_items(inputs, "color", PortType::Image, |v| match v {
            Value::Image(i) => Some(i.clone()),
            _ => None,
        })?;
        let n = views.len();
        if let Some(c) = &colors
            && c.len() != n
        {
            return Err(OpError::input(
                "color",
                TsdfError::Count {
                    depths: n,
                    other: c.len(),
                    what: "colour images",
                }
                .to_string(),
            ));
        }
        let mut samples = Vec::with_capacity(n);
        let mut rgb = Vec::new();
        for (i, d) in views.images.iter().enumerate() {
            if let Err(e) = check_pose(i, &views.poses[i]) {
                return Err(OpError::input("poses", e.to_string()));
            }
            if let Some(cs) = &colors {
                let c = &cs[i];
                if (c.width(), c.height()) != (d.width(), d.height()) {
                    return Err(OpError::input(
                        "color",
                        format!(
                            "colour image {i} is {}×{} but the depth map is {}×{}",
                            c.width(),
                            c.height(),
                            d.width(),
                            d.height()
                        ),
                    ));
                }
                rgb.push(rgb_of(c));
            }
            samples.push(samples_f32(d));
        }
        let frames: Vec<DepthFrame<'_>> = (0..n)
            .map(|i| DepthFrame {
                depth: &samples[i],
                width: views.images[i].width(),
                height: views.images[i].height(),
                lens: Lens::from_camera(views.camera(i)),
                camera_from_world: views.poses[i],
                color: rgb.get(i).map(|v| v.as_slice()),
            })
            .collect();
        let out = tsdf_fusion(&frames, &self.options()).map_err(|e| match e {
            TsdfError::Camera { .. } => OpError::input("cameras", e.to_string()),
            TsdfError::Extraction(_) => OpError::failed(e.to_string()),
            _ => OpError::input("depth", e.to_string()),
        })?;
        let s = &out.surface;
        let mesh = Mesh {
            positions: s
                .surface
                .positions
                .iter()
                .map(|p| p.map(|v| v as f32))
                .collect(),
            triangles: s.surface.triangles.clone(),
            normals: Some(s.normals.clone()),
            colors: s.colors.clone(),
            ..Mesh::default()
        };
        let g = out.volume.grid;
        let mut m = Metrics::new();
        m.insert("frames".into(), n as f64);
        m.insert("voxels".into(), g.len() as f64);
        m.insert("nx".into(), g.dims[0] as f64);
        m.insert("ny".into(), g.dims[1] as f64);
        m.insert("nz".into(), g.dims[2] as f64);
        m.insert("observed_voxels".into(), out.volume.observed() as f64);
        m.insert("voxel_size".into(), g.voxel_size);
        m.insert("truncation".into(), out.volume.truncation);
        m.insert("vertices".into(), mesh.positions.len() as f64);
        m.insert("triangles".into(), mesh.triangles.len() as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(mesh)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::marching_cubes::tests::{chamfer, closed_euler};
    use ocellus_engine::value::{Channels, Distortion, Intrinsics};
    use proptest::prelude::*;

    fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }
    fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }
    fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    }
    fn normalize(a: [f64; 3]) -> [f64; 3] {
        let n = dot(a, a).sqrt();
        a.map(|v| v / n)
    }

    /// An analytic scene for the ray caster.
    #[derive(Clone, Copy)]
    enum Shape {
        Sphere {
            c: [f64; 3],
            r: f64,
        },
        Box {
            lo: [f64; 3],
            hi: [f64; 3],
        },
        /// n·X = d, unit n.
        Plane {
            n: [f64; 3],
            d: f64,
        },
    }

    impl Shape {
        /// The nearest hit at t > 0 along the unit ray o + t·d.
        fn hit(&self, o: [f64; 3], d: [f64; 3]) -> Option<f64> {
            match *self {
                Shape::Sphere { c, r } => {
                    let oc = sub(o, c);
                    let b = dot(oc, d);
                    let disc = b * b - (dot(oc, oc) - r * r);
                    if disc < 0.0 {
                        return None;
                    }
                    let s = disc.sqrt();
                    [-b - s, -b + s].into_iter().find(|t| *t > 1e-9)
                }
                Shape::Box { lo, hi } => {
                    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
                    for k in 0..3 {
                        let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
                        t0 = t0.max(a.min(b));
                        t1 = t1.min(a.max(b));
                    }
                    (t0 <= t1 && t0 > 1e-9).then_some(t0)
                }
                Shape::Plane { n, d: off } => {
                    let den = dot(n, d);
                    let t = (off - dot(n, o)) / den;
                    (den != 0.0 && t > 1e-9).then_some(t)
                }
            }
        }

        /// Unsigned distance to the surface.
        fn distance(&self, p: [f64; 3]) -> f64 {
            match *self {
                Shape::Sphere { c, r } => (dot(sub(p, c), sub(p, c)).sqrt() - r).abs(),
                Shape::Box { lo, hi } => {
                    let q: [f64; 3] = std::array::from_fn(|k| {
                        (p[k] - 0.5 * (lo[k] + hi[k])).abs() - 0.5 * (hi[k] - lo[k])
                    });
                    let out = q.map(|v| v.max(0.0));
                    let inside = q[0].max(q[1]).max(q[2]).min(0.0);
                    (dot(out, out).sqrt() + inside).abs()
                }
                Shape::Plane { n, d } => (dot(n, p) - d).abs(),
            }
        }
    }

    fn intrinsics() -> Intrinsics {
        Intrinsics {
            fx: 160.0,
            fy: 160.0,
            cx: 79.5,
            cy: 59.5,
            skew: 0.0,
        }
    }
    const W: usize = 160;
    const H: usize = 120;

    /// camera_from_world of a camera at `eye` looking at `target` (x right, y down, z forward).
    fn look_at(eye: [f64; 3], target: [f64; 3]) -> Pose {
        let f = normalize(sub(target, eye));
        let up = if dot(f, [0.0, 0.0, 1.0]).abs() > 0.9 {
            [0.0, 1.0, 0.0]
        } else {
            [0.0, 0.0, 1.0]
        };
        let d = normalize(sub(f.map(|v| v * dot(up, f)), up));
        let r = cross(d, f);
        let rot = [r[0], r[1], r[2], d[0], d[1], d[2], f[0], f[1], f[2]];
        Pose::from_rotation_matrix(&rot, [-dot(r, eye), -dot(d, eye), -dot(f, eye)])
    }

    /// Ray-cast depth (Z or range; +inf on a miss) and the hit points (NaN on a miss).
    fn render(
        shape: &Shape,
        lens: &Lens,
        pose: &Pose,
        kind: DepthKind,
    ) -> (Vec<f32>, Vec<[f64; 3]>) {
        let r = pose.rotation_matrix();
        let t = pose.translation;
        let rt = |v: [f64; 3]| {
            [
                r[0] * v[0] + r[3] * v[1] + r[6] * v[2],
                r[1] * v[0] + r[4] * v[1] + r[7] * v[2],
                r[2] * v[0] + r[5] * v[1] + r[8] * v[2],
            ]
        };
        let eye = rt(t).map(|v| -v);
        let mut depth = Vec::with_capacity(W * H);
        let mut hits = Vec::with_capacity(W * H);
        for v in 0..H {
            for u in 0..W {
                let hit = lens.unproject([u as f64, v as f64]).and_then(|ray| {
                    let dw = rt(ray);
                    shape.hit(eye, dw).map(|s| (s, ray, dw))
                });
                match hit {
                    Some((s, ray, dw)) => {
                        depth.push(match kind {
                            DepthKind::Z => (s * ray[2]) as f32,
                            DepthKind::Range => s as f32,
                        });
                        hits.push([0, 1, 2].map(|k| eye[k] + s * dw[k]));
                    }
                    None => {
                        depth.push(f32::INFINITY);
                        hits.push([f64::NAN; 3]);
                    }
                }
            }
        }
        (depth, hits)
    }

    /// Cameras at `dist` from `c` along the 6 axes and 4 diagonals.
    fn ring(c: [f64; 3], dist: f64) -> Vec<Pose> {
        let dirs = [
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [1.0, 1.0, 1.0],
            [-1.0, -1.0, 1.0],
            [1.0, -1.0, -1.0],
            [-1.0, 1.0, -1.0],
        ];
        dirs.iter()
            .map(|d| {
                let d = normalize(*d);
                look_at([0, 1, 2].map(|k| c[k] + dist * d[k]), c)
            })
            .collect()
    }

    struct Shots {
        lens: Lens,
        poses: Vec<Pose>,
        depths: Vec<Vec<f32>>,
        colors: Vec<Vec<[f32; 3]>>,
    }

    /// Colour of a world point: a smooth function, so that vertex colours can be checked.
    fn paint(p: [f64; 3]) -> [f32; 3] {
        [
            (0.5 + 0.4 * p[0]) as f32,
            (0.5 + 0.4 * p[1]) as f32,
            (0.5 + 0.4 * p[2]) as f32,
        ]
    }

    fn shoot(shape: &Shape, lens: Lens, poses: Vec<Pose>, kind: DepthKind) -> Shots {
        let mut depths = Vec::new();
        let mut colors = Vec::new();
        for p in &poses {
            let (d, hits) = render(shape, &lens, p, kind);
            depths.push(d);
            colors.push(
                hits.iter()
                    .map(|h| {
                        if h[0].is_finite() {
                            paint(*h)
                        } else {
                            [0.0; 3]
                        }
                    })
                    .collect(),
            );
        }
        Shots {
            lens,
            poses,
            depths,
            colors,
        }
    }

    impl Shots {
        fn frames(&self, color: bool) -> Vec<DepthFrame<'_>> {
            (0..self.poses.len())
                .map(|i| DepthFrame {
                    depth: &self.depths[i],
                    width: W,
                    height: H,
                    lens: self.lens,
                    camera_from_world: self.poses[i],
                    color: color.then(|| self.colors[i].as_slice()),
                })
                .collect()
        }
    }

    fn sample_box(lo: [f64; 3], hi: [f64; 3], n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = SplitMix64::new(seed);
        let e = sub(hi, lo);
        let areas = [e[1] * e[2], e[0] * e[2], e[0] * e[1]];
        let total = 2.0 * (areas[0] + areas[1] + areas[2]);
        (0..n)
            .map(|_| {
                let mut a = rng.uniform() * total;
                let mut face = 0;
                while face < 5 && a >= areas[face / 2] {
                    a -= areas[face / 2];
                    face += 1;
                }
                let axis = face / 2;
                let mut p: [f64; 3] = std::array::from_fn(|k| lo[k] + rng.uniform() * e[k]);
                p[axis] = if face % 2 == 0 { lo[axis] } else { hi[axis] };
                p
            })
            .collect()
    }

    fn options(h: f64) -> TsdfOptions {
        TsdfOptions {
            voxel_size: Some(h),
            ..TsdfOptions::default()
        }
    }

    const SPHERE: Shape = Shape::Sphere {
        c: [0.1, -0.2, 0.3],
        r: 0.5,
    };

    #[test]
    fn a_sphere_from_ten_views_is_a_closed_sphere_within_half_a_voxel() {
        let (c, r, h) = ([0.1, -0.2, 0.3], 0.5, 0.02);
        let shots = shoot(
            &SPHERE,
            Lens::pinhole(intrinsics()),
            ring(c, 2.0),
            DepthKind::Z,
        );
        let out = tsdf_fusion(&shots.frames(false), &options(h)).unwrap();
        let s = &out.surface.surface;
        let truth = crate::mesh::pointcloud::tests::sphere(4000, c, r, 5);
        let [mean_a, max_a, mean_b, max_b] = chamfer(s, |p| SPHERE.distance(*p), &truth, 100_000);
        eprintln!(
            "sphere chamfer / h: {} {} {} {}",
            mean_a / h,
            max_a / h,
            mean_b / h,
            max_b / h
        );
        assert!(mean_a < 0.25 * h && mean_b < 0.25 * h, "{mean_a} {mean_b}");
        assert!(max_a < 0.5 * h && max_b < 0.5 * h, "{max_a} {max_b}");
        // Seen all round: closed, genus 0.
        assert_eq!(closed_euler(s), Ok(2));
        // Normals point out of the sphere.
        let mut cos_sum = 0.0;
        for (p, n) in s.positions.iter().zip(&out.surface.normals) {
            let radial = normalize(sub(*p, c));
            let cos = dot(radial, n.map(f64::from));
            assert!(cos > 0.5, "{p:?}: {n:?}");
            cos_sum += cos;
        }
        let mean_cos = cos_sum / s.positions.len() as f64;
        assert!(mean_cos > 0.98, "{mean_cos}"); // measured 0.9917 (mean angle ≈ 7°)
        // Triangles are counter-clockwise seen from outside.
        for t in &s.triangles {
            let [a, b, q] = t.map(|i| s.positions[i as usize]);
            let n = cross(sub(b, a), sub(q, a));
            assert!(dot(n, sub(a, c)) > 0.0);
        }
    }

    #[test]
    fn a_box_from_ten_views_is_within_a_voxel() {
        let (lo, hi, h) = ([-0.4, -0.3, -0.25], [0.4, 0.3, 0.25], 0.02);
        let shape = Shape::Box { lo, hi };
        let shots = shoot(
            &shape,
            Lens::pinhole(intrinsics()),
            ring([0.0; 3], 2.2),
            DepthKind::Z,
        );
        let o = TsdfOptions {
            weighting: TsdfWeighting::Cosine,
            ..options(h)
        };
        let out = tsdf_fusion(&shots.frames(false), &o).unwrap();
        let s = &out.surface.surface;
        let truth = sample_box(lo, hi, 4000, 7);
        let [mean_a, max_a, mean_b, max_b] = chamfer(s, |p| shape.distance(*p), &truth, 100_000);
        eprintln!(
            "box chamfer / h: {} {} {} {}",
            mean_a / h,
            max_a / h,
            mean_b / h,
            max_b / h
        );
        // Chamfer (sum of the two means) well under half a voxel (measured 0.31 h).
        assert!(mean_a + mean_b < 0.5 * h, "{mean_a} {mean_b}");
        // Every part of the box is there within a voxel (measured 0.94 h, at the corners).
        assert!(max_b < 1.25 * h, "{max_b}");
        // At the convex edges, the "shadow" votes of a face seen head-on (the band behind it,
        // outside the box next to the edge) pull the surface out by up to about μ/2: the
        // known bias of projective TSDF at sharp convex edges (measured 2.1 h; the faces are
        // exact).
        assert!(max_a < 2.5 * h, "{max_a}");
        // Not asserted: closedness. Measured: one border edge remains near a box edge (a cube
        // with an unobserved corner next to the surface).
    }

    #[test]
    fn a_tilted_plane_is_flat_with_normals_towards_the_camera() {
        let len = (0.3f64 * 0.3 + 0.2 * 0.2 + 1.0).sqrt();
        let n = [0.3 / len, -0.2 / len, 1.0 / len];
        let plane = Shape::Plane { n, d: 0.05 };
        let h = 0.02;
        let pose = look_at([0.4, -0.3, 1.5], [0.0, 0.0, 0.0]);
        let shots = shoot(
            &plane,
            Lens::pinhole(intrinsics()),
            vec![pose],
            DepthKind::Z,
        );
        let o = TsdfOptions {
            bounds: Some(([-0.4, -0.4, -0.3], [0.4, 0.4, 0.3])),
            ..options(h)
        };
        let out = tsdf_fusion(&shots.frames(false), &o).unwrap();
        let s = &out.surface.surface;
        assert!(s.triangles.len() > 1000);
        let mut area = 0.0;
        for t in &s.triangles {
            let [a, b, c] = t.map(|i| s.positions[i as usize]);
            let m = cross(sub(b, a), sub(c, a));
            area += 0.5 * dot(m, m).sqrt();
            assert!(dot(m, n) > 0.0, "a triangle faces away from the camera");
        }
        // The plane crosses the whole 0.8 × 0.8 box (all of it in view).
        assert!(area > 0.8 * 0.8 * 0.8 / n[2], "{area}");
        for (p, m) in s.positions.iter().zip(&out.surface.normals) {
            assert!(plane.distance(*p) < 0.05 * h, "{}", plane.distance(*p));
            assert!(dot(m.map(f64::from), n) > 0.999, "{m:?}");
        }
    }

    #[test]
    fn one_frame_gives_the_visible_cap_and_nothing_behind_it() {
        let (c, r, h) = ([0.1, -0.2, 0.3], 0.5, 0.02);
        let eye = [c[0], c[1], c[2] + 2.0];
        let shots = shoot(
            &SPHERE,
            Lens::pinhole(intrinsics()),
            vec![look_at(eye, c)],
            DepthKind::Z,
        );
        let out = tsdf_fusion(&shots.frames(false), &options(h)).unwrap();
        let s = &out.surface.surface;
        assert!(!s.triangles.is_empty());
        for p in &s.positions {
            assert!(SPHERE.distance(*p) < 0.5 * h, "{p:?}");
            // On the near side: (p − c)·e_z / r ≥ r/d = 0.25 on the visible cap, less a voxel.
            let cz = (p[2] - c[2]) / r;
            assert!(cz > 0.1, "a vertex behind the visible cap: {p:?}");
        }
        assert!(
            closed_euler(s).is_err(),
            "a single view cannot close the surface"
        );
        // The cap facing the camera is all there.
        let truth: Vec<[f64; 3]> = crate::mesh::pointcloud::tests::sphere(4000, c, r, 9)
            .into_iter()
            .filter(|p| (p[2] - c[2]) / r > 0.5)
            .collect();
        let [_, _, mean_b, max_b] = chamfer(s, |p| SPHERE.distance(*p), &truth, 20_000);
        assert!(mean_b < 0.25 * h && max_b < 0.5 * h, "{mean_b} {max_b}");
        // Observed: free space in front and the band behind the cap; the far side is not.
        let g = out.volume.grid;
        for (idx, v) in out.volume.voxels.iter().enumerate() {
            let (i, j, k) = (
                idx % g.dims[0],
                (idx / g.dims[0]) % g.dims[1],
                idx / (g.dims[0] * g.dims[1]),
            );
            let p = [i, j, k].map(|x| x as f64);
            let p = [0, 1, 2].map(|a| g.origin[a] + g.voxel_size * p[a]);
            let dp = sub(p, c);
            if dp[2] < -0.1 && dot(dp, dp).sqrt() < r + out.volume.truncation {
                assert_eq!(v.weight, 0.0, "{p:?}");
            }
        }
    }

    #[test]
    fn the_same_frame_twice_is_the_same_surface() {
        let c = [0.1, -0.2, 0.3];
        let shots = shoot(
            &SPHERE,
            Lens::pinhole(intrinsics()),
            ring(c, 2.0)[..2].to_vec(),
            DepthKind::Z,
        );
        let frames = shots.frames(false);
        let bounds = Some(([-0.6, -0.9, -0.4], [0.8, 0.5, 1.0]));
        let o = TsdfOptions {
            bounds,
            ..options(0.025)
        };
        let once = tsdf_fusion(&frames[..1], &o).unwrap();
        let twice = tsdf_fusion(&[frames[0], frames[0]], &o).unwrap();
        assert!(!once.surface.surface.triangles.is_empty());
        assert_eq!(once.surface, twice.surface);
        for (a, b) in once.volume.voxels.iter().zip(&twice.volume.voxels) {
            assert_eq!(a.tsdf.to_bits(), b.tsdf.to_bits());
            assert_eq!(2.0 * a.weight, b.weight);
        }
        // With a weight cap of 1 the second frame changes nothing either.
        let capped = TsdfOptions {
            max_weight: 1.0,
            ..o.clone()
        };
        let twice = tsdf_fusion(&[frames[0], frames[0]], &capped).unwrap();
        assert_eq!(once.volume.voxels, twice.volume.voxels);
        // And a different frame does change it.
        let two = tsdf_fusion(&frames, &o).unwrap();
        assert_ne!(once.surface, two.surface);
    }

    #[test]
    fn nan_pixels_leave_their_voxels_unobserved() {
        let c = [0.1, -0.2, 0.3];
        let pose = look_at([c[0], c[1], c[2] + 2.0], c);
        let lens = Lens::pinhole(intrinsics());
        let full = shoot(&SPHERE, lens, vec![pose], DepthKind::Z);
        let mut holed = shoot(&SPHERE, lens, vec![pose], DepthKind::Z);
        let hole = |u: f64, v: f64| (60.0..100.0).contains(&u) && (40.0..80.0).contains(&v);
        for (i, d) in holed.depths[0].iter_mut().enumerate() {
            if hole((i % W) as f64, (i / W) as f64) {
                *d = f32::NAN;
            }
        }
        let bounds = Some(([-0.5, -0.8, -0.3], [0.7, 0.4, 0.9]));
        let o = TsdfOptions {
            bounds,
            ..options(0.02)
        };
        let a = tsdf_fusion(&full.frames(false), &o).unwrap();
        let b = tsdf_fusion(&holed.frames(false), &o).unwrap();
        let g = a.volume.grid;
        let (mut inside, mut outside) = (0, 0);
        for (idx, (va, vb)) in a.volume.voxels.iter().zip(&b.volume.voxels).enumerate() {
            let (i, j, k) = (
                idx % g.dims[0],
                (idx / g.dims[0]) % g.dims[1],
                idx / (g.dims[0] * g.dims[1]),
            );
            let x = [0, 1, 2].map(|m| g.origin[m] + g.voxel_size * [i, j, k][m] as f64);
            let r = pose.rotation_matrix();
            let xc: [f64; 3] = std::array::from_fn(|m| {
                r[3 * m] * x[0] + r[3 * m + 1] * x[1] + r[3 * m + 2] * x[2] + pose.translation[m]
            });
            let Some(px) = lens.project(xc) else { continue };
            // Every pixel the sampler may read (the 2×2 around it and the nearest) in the hole,
            // or all of them outside it.
            let (fu, fv) = (px[0].floor(), px[1].floor());
            let reads = [
                (fu, fv),
                (fu + 1.0, fv),
                (fu, fv + 1.0),
                (fu + 1.0, fv + 1.0),
                (px[0].round(), px[1].round()),
            ];
            if reads.iter().all(|&(u, v)| hole(u, v)) {
                assert_eq!(vb.weight, 0.0);
                inside += usize::from(va.weight > 0.0);
            } else if reads.iter().all(|&(u, v)| !hole(u, v)) {
                assert_eq!(va, vb);
                outside += usize::from(va.weight > 0.0);
            }
        }
        assert!(inside > 1000 && outside > 1000, "{inside} {outside}");
        // No vertex projects well inside the hole; the full frame has many there.
        let in_hole = |s: &IsoSurface| {
            s.positions
                .iter()
                .filter(|p| {
                    let r = pose.rotation_matrix();
                    let xc: [f64; 3] = std::array::from_fn(|m| {
                        r[3 * m] * p[0]
                            + r[3 * m + 1] * p[1]
                            + r[3 * m + 2] * p[2]
                            + pose.translation[m]
                    });
                    lens.project(xc).is_some_and(|q| {
                        (63.0..97.0).contains(&q[0]) && (43.0..77.0).contains(&q[1])
                    })
                })
                .count()
        };
        assert_eq!(in_hole(&b.surface.surface), 0);
        assert!(in_hole(&a.surface.surface) > 100);
    }

    #[test]
    fn the_thread_count_does_not_matter() {
        let c = [0.1, -0.2, 0.3];
        let shots = shoot(
            &SPHERE,
            Lens::pinhole(intrinsics()),
            ring(c, 2.0),
            DepthKind::Z,
        );
        let frames = shots.frames(true);
        let o = TsdfOptions {
            weighting: TsdfWeighting::Cosine,
            max_weight: 6.0,
            ..options(0.025)
        };
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| tsdf_fusion(&frames, &o).unwrap())
        };
        let (a, b) = (run(1), run(4));
        let bits = |r: &TsdfResult| {
            let v: Vec<(u32, u32)> = r
                .volume
                .voxels
                .iter()
                .map(|v| (v.tsdf.to_bits(), v.weight.to_bits()))
                .collect();
            let p: Vec<u64> = r
                .surface
                .surface
                .positions
                .iter()
                .flat_map(|p| p.map(f64::to_bits))
                .collect();
            (v, p)
        };
        assert!(!a.surface.surface.triangles.is_empty());
        assert_eq!(bits(&a), bits(&b));
        assert_eq!(a, b);
    }

    fn run_op(
        params: TsdfFusionParams,
        depths: Vec<Value>,
        cameras: Vec<Value>,
        poses: Vec<Value>,
        colors: Option<Vec<Value>>,
    ) -> Result<Outputs, OpError> {
        let op = TsdfFusion::new(params).map_err(OpError::failed)?;
        let specs = TsdfFusion::inputs();
        let values = [
            Some(Value::list(PortType::Image, depths)),
            Some(Value::list(PortType::Camera, cameras)),
            Some(Value::list(PortType::Pose, poses)),
            colors.map(|c| Value::list(PortType::Image, c)),
        ];
        let ctx = RunContext {
            node: "fuse".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    fn depth_value(d: &[f32]) -> Value {
        Value::image(Image::from_f32(W, H, Channels::Gray, d.to_vec()).unwrap())
    }

    /// Through the operator: range depth from a distorting lens (as `capture.render` gives
    /// with a calibrated camera), colours, metrics.
    #[test]
    fn the_op_fuses_distorted_range_depth_with_colours() {
        let (c, r, h) = ([0.1, -0.2, 0.3], 0.5, 0.02);
        let lens = Lens {
            k: intrinsics(),
            distortion: Distortion::RadialTangential([-0.25, 0.08, 0.001, -0.001, 0.0]),
        };
        let shots = shoot(&SPHERE, lens, ring(c, 2.0), DepthKind::Range);
        let camera = Value::Camera(Arc::new(lens.to_camera(W as u32, H as u32)));
        let depths: Vec<Value> = shots
            .depths
            .iter()
            .map(|d| depth_value(d.as_slice()))
            .collect();
        let poses: Vec<Value> = shots.poses.iter().map(|p| Value::Pose(*p)).collect();
        let colors: Vec<Value> = shots
            .colors
            .iter()
            .map(|c| {
                let flat: Vec<f32> = c.iter().flatten().copied().collect();
                Value::image(Image::from_f32(W, H, Channels::Rgb, flat).unwrap())
            })
            .collect();
        let params = TsdfFusionParams {
            voxel_size: Some(h),
            depth_kind: DepthKind::Range,
            ..TsdfFusionParams::default()
        };
        let mut out = run_op(params, depths, vec![camera], poses, Some(colors)).unwrap();
        let Some(Value::Mesh(mesh)) = out.take("mesh") else {
            panic!("no mesh")
        };
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("no metrics")
        };
        let s = IsoSurface {
            positions: mesh.positions.iter().map(|p| p.map(f64::from)).collect(),
            triangles: mesh.triangles.clone(),
        };
        let truth = crate::mesh::pointcloud::tests::sphere(4000, c, r, 5);
        let [mean_a, max_a, mean_b, max_b] = chamfer(&s, |p| SPHERE.distance(*p), &truth, 50_000);
        eprintln!(
            "distorted chamfer / h: {} {} {} {}",
            mean_a / h,
            max_a / h,
            mean_b / h,
            max_b / h
        );
        assert!(mean_a < 0.25 * h && mean_b < 0.25 * h, "{mean_a} {mean_b}");
        // The distorting lens costs a little at the rim, where the barrel distortion squeezes
        // pixels (measured max 0.54 h, mean 0.07 h).
        assert!(max_a < 0.75 * h && max_b < 0.75 * h, "{max_a} {max_b}");
        assert_eq!(closed_euler(&s), Ok(2));
        // Vertex colours follow the painted function (averaged within μ of the surface).
        let colors = mesh.colors.as_ref().unwrap();
        let err: Vec<f64> = s
            .positions
            .iter()
            .zip(colors)
            .map(|(p, got)| {
                let want = paint(*p);
                (0..3)
                    .map(|k| f64::from((got[k] - want[k]).abs()))
                    .fold(0.0, f64::max)
            })
            .collect();
        let mean = err.iter().sum::<f64>() / err.len() as f64;
        let max = err.iter().copied().fold(0.0, f64::max);
        eprintln!("colour error mean {mean} max {max}");
        assert!(mean < 0.015 && max < 0.08, "{mean} {max}");
        assert_eq!(
            mesh.normals.as_ref().map(Vec::len),
            Some(mesh.positions.len())
        );
        assert_eq!(m["frames"], 10.0);
        assert_eq!(m["vertices"], mesh.positions.len() as f64);
        assert_eq!(m["triangles"], mesh.triangles.len() as f64);
        assert_eq!(m["voxels"], m["nx"] * m["ny"] * m["nz"]);
        assert!(m["observed_voxels"] > 0.0 && m["observed_voxels"] < m["voxels"]);
        assert_eq!(m["truncation"], 4.0 * h);
        // Default bounds: the points (the sphere's bounding box) padded by μ.
        assert!((m["nx"] - ((2.0 * r + 8.0 * h) / h).ceil() - 1.0).abs() <= 1.0);
    }

    #[test]
    fn bad_input_is_a_clear_error() {
        let c = [0.1, -0.2, 0.3];
        let lens = Lens::pinhole(intrinsics());
        let shots = shoot(&SPHERE, lens, ring(c, 2.0)[..2].to_vec(), DepthKind::Z);
        let camera = || Value::Camera(Arc::new(lens.to_camera(W as u32, H as u32)));
        let depths = || -> Vec<Value> {
            shots
                .depths
                .iter()
                .map(|d| depth_value(d.as_slice()))
                .collect()
        };
        let poses = || -> Vec<Value> { shots.poses.iter().map(|p| Value::Pose(*p)).collect() };
        let p = || TsdfFusionParams {
            voxel_size: Some(0.05),
            ..TsdfFusionParams::default()
        };
        assert!(run_op(p(), depths(), vec![camera()], poses(), None).is_ok());
        let err = |r: Result<Outputs, OpError>| r.err().map(|e| e.to_string()).unwrap_or_default();
        let e = err(run_op(
            p(),
            depths(),
            vec![camera()],
            poses()[..1].to_vec(),
            None,
        ));
        assert!(e.contains("2 depth maps but 1 poses"), "{e}");
        let e = err(run_op(p(), depths(), vec![camera(); 3], poses(), None));
        assert!(e.contains("one camera per depth map"), "{e}");
        let mut bad = poses();
        bad[1] = Value::Pose(Pose {
            rotation: [f64::NAN, 0.0, 0.0, 0.0],
            translation: [0.0; 3],
        });
        let e = err(run_op(p(), depths(), vec![camera()], bad, None));
        assert!(e.contains("pose 1"), "{e}");
        let rgb = Value::image(Image::from_f32(W, H, Channels::Rgb, vec![1.0; W * H * 3]).unwrap());
        let e = err(run_op(
            p(),
            vec![rgb.clone(), rgb],
            vec![camera()],
            poses(),
            None,
        ));
        assert!(e.contains("expected one channel"), "{e}");
        let small = Value::Camera(Arc::new(lens.to_camera(W as u32 / 2, H as u32)));
        let e = err(run_op(p(), depths(), vec![small], poses(), None));
        assert!(e.contains("80×120"), "{e}");
        let e = err(run_op(
            p(),
            depths(),
            vec![camera()],
            poses(),
            Some(depths()[..1].to_vec()),
        ));
        assert!(e.contains("colour"), "{e}");
        // A grid over the cap names the voxels it needs.
        let tiny = TsdfFusionParams {
            voxel_size: Some(0.001),
            max_voxels: 1_000_000,
            ..TsdfFusionParams::default()
        };
        let e = err(run_op(tiny, depths(), vec![camera()], poses(), None));
        assert!(e.contains("voxels, more than max_voxels = 1000000"), "{e}");
        // Nothing valid to bound.
        let empty: Vec<Value> = (0..2).map(|_| depth_value(&vec![0.0; W * H])).collect();
        let e = err(run_op(p(), empty, vec![camera()], poses(), None));
        assert!(e.contains("no valid depth"), "{e}");
        // Bad params.
        for bad in [
            TsdfFusionParams {
                min: Some([0.0; 3]),
                ..p()
            },
            TsdfFusionParams {
                min: Some([0.0; 3]),
                max: Some([1.0, 0.0, 1.0]),
                ..p()
            },
            TsdfFusionParams {
                voxel_size: None,
                resolution: 8,
                ..p()
            },
            TsdfFusionParams {
                max_weight: Some(0.0),
                ..p()
            },
        ] {
            assert!(TsdfFusion::new(bad).is_err());
        }
    }

    #[test]
    fn the_voxel_cap_error_suggests_a_size_that_fits() {
        let c = [0.1, -0.2, 0.3];
        let shots = shoot(
            &SPHERE,
            Lens::pinhole(intrinsics()),
            ring(c, 2.0),
            DepthKind::Z,
        );
        let o = TsdfOptions {
            max_voxels: 50_000,
            ..options(0.005)
        };
        let Err(TsdfError::TooManyVoxels {
            needed,
            suggested_voxel_size,
            ..
        }) = plan_grid(&shots.frames(false), &o)
        else {
            panic!("no cap error")
        };
        assert!(needed > 50_000);
        let g = plan_grid(
            &shots.frames(false),
            &TsdfOptions {
                voxel_size: Some(suggested_voxel_size),
                ..o.clone()
            },
        )
        .unwrap();
        assert!(g.len() <= 50_000 && g.len() > 25_000, "{}", g.len());
        // The derived voxel size gives `resolution` nodes along the longest axis.
        let g = plan_grid(
            &shots.frames(false),
            &TsdfOptions {
                voxel_size: None,
                resolution: 40,
                max_voxels: DEFAULT_MAX_VOXELS,
                ..o
            },
        )
        .unwrap();
        assert_eq!(g.dims.iter().max(), Some(&40));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(12))]
        /// Any plane in front of a camera fuses, from one frame, to that plane.
        #[test]
        fn planes_fuse_to_themselves(
            nx in -0.5f64..0.5,
            ny in -0.5f64..0.5,
            d in -0.2f64..0.2,
            ex in -0.5f64..0.5,
            ey in -0.5f64..0.5,
        ) {
            let n = normalize([nx, ny, 1.0]);
            let plane = Shape::Plane { n, d };
            let pose = look_at([ex, ey, 1.6], [0.0, 0.0, 0.0]);
            let shots = shoot(&plane, Lens::pinhole(intrinsics()), vec![pose], DepthKind::Z);
            let h = 0.03;
            let o = TsdfOptions {
                bounds: Some(([-0.3, -0.3, -0.5], [0.3, 0.3, 0.5])),
                ..options(h)
            };
            let out = tsdf_fusion(&shots.frames(false), &o).unwrap();
            let s = &out.surface.surface;
            prop_assert!(s.triangles.len() > 100);
            for p in &s.positions {
                prop_assert!(plane.distance(*p) < 0.1 * h, "{}", plane.distance(*p));
            }
        }
    }

    /// Timing: 10 frames of 640×480 into a 256³ grid. Run with
    /// `cargo test -p ocellus-nodes --lib mesh::tsdf::tests::timing -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn timing() {
        let c = [0.1, -0.2, 0.3];
        let k = Intrinsics {
            fx: 640.0,
            fy: 640.0,
            cx: 319.5,
            cy: 239.5,
            skew: 0.0,
        };
        let lens = Lens::pinhole(k);
        let (w, h) = (640usize, 480usize);
        let poses = ring(c, 2.0);
        let depths: Vec<Vec<f32>> = poses
            .iter()
            .map(|pose| {
                let r = pose.rotation_matrix();
                let t = pose.translation;
                let eye: [f64; 3] =
                    std::array::from_fn(|m| -(r[m] * t[0] + r[3 + m] * t[1] + r[6 + m] * t[2]));
                (0..w * h)
                    .map(|i| {
                        let ray = lens.unproject([(i % w) as f64, (i / w) as f64]).unwrap();
                        let dw: [f64; 3] = std::array::from_fn(|m| {
                            r[m] * ray[0] + r[3 + m] * ray[1] + r[6 + m] * ray[2]
                        });
                        SPHERE
                            .hit(eye, dw)
                            .map_or(f32::INFINITY, |s| (s * ray[2]) as f32)
                    })
                    .collect()
            })
            .collect();
        let frames: Vec<DepthFrame<'_>> = (0..poses.len())
            .map(|i| DepthFrame {
                depth: &depths[i],
                width: w,
                height: h,
                lens,
                camera_from_world: poses[i],
                color: None,
            })
            .collect();
        let o = TsdfOptions {
            resolution: 256,
            ..TsdfOptions::default()
        };
        let t0 = std::time::Instant::now();
        let grid = plan_grid(&frames, &o).unwrap();
        let t1 = std::time::Instant::now();
        let mut volume = TsdfVolume::new(grid, o.truncation * grid.voxel_size, false);
        for (i, f) in frames.iter().enumerate() {
            volume.integrate(i, f, &o).unwrap();
        }
        let t2 = std::time::Instant::now();
        let s = volume.extract().unwrap();
        let t3 = std::time::Instant::now();
        eprintln!(
            "grid {:?} voxel {:.5}: bounds {:?}, integrate {:?} ({:?}/frame), extract {:?}, {} threads, {} vertices {} triangles",
            grid.dims,
            grid.voxel_size,
            t1 - t0,
            t2 - t1,
            (t2 - t1) / frames.len() as u32,
            t3 - t2,
            rayon::current_num_threads(),
            s.surface.positions.len(),
            s.surface.triangles.len()
        );
    }
}
