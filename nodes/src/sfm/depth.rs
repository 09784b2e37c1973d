//! `sfm.depth_to_points`: a depth image (RGB-D camera, rendered depth, or stereo disparity
//! converted by `geometry.disparity_to_depth`) back-projected through its camera into an
//! organized point cloud — OpenCV's `rgbd::depthTo3d` / `reprojectImageTo3D` and Open3D's
//! `PointCloud::CreateFromRGBDImage`.
//!
//! The algorithm is [`depth_to_points`]; [`DepthToPoints`] is the thin operator around it.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{
    Camera, Channels, Depth, Image, Metrics, PixelData, PointCloud, Pose, Value,
};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use crate::filter::convert::convert_type;
use crate::geometry::camera::Lens;
use crate::geometry::rectify::samples_f32;

param_enum! {
    /// What a depth sample measures.
    pub enum DepthKind {
        /// Distance along the optical axis, Z (RGB-D cameras, `geometry.disparity_to_depth`).
        Z = "z",
        /// Distance along the pixel's ray from the centre of projection (time-of-flight
        /// range, `capture.render`'s depth).
        Range = "range",
    }
}

params! {
    /// Parameters of `sfm.depth_to_points`.
    pub struct DepthToPointsParams {
        /// Depth units per sample: metres (or scene units) = sample × `depth_scale`, e.g.
        /// 0.001 for millimetre u16 depth, 0.0002 for TUM RGB-D's 5000 per metre. Default 1.
        depth_scale: f64 = 1.0 => [min = 0.0],
        /// What a sample measures: "z" (along the optical axis) or "range" (along the ray).
        /// Default "z".
        depth_kind: DepthKind = DepthKind::Z,
        /// Nearest valid depth after scaling; smaller samples (and 0, the usual "no data")
        /// are invalid. Default 0 (every positive depth).
        min_depth: f64 = 0.0 => [min = 0.0, unit = "scene units"],
        /// Farthest valid depth after scaling; None (the default) has no limit.
        max_depth: Option<f64> = None => [min = 0.0, unit = "scene units"],
        /// Focal lengths and principal point, pixels, used when no `camera` is connected
        /// (fx required then; fy defaults to fx; cx, cy to the image centre (w − 1)/2,
        /// (h − 1)/2, pixel centres being at integer coordinates).
        fx: Option<f64> = None => [unit = "px"],
        /// See `fx`.
        fy: Option<f64> = None => [unit = "px"],
        /// See `fx`.
        cx: Option<f64> = None => [unit = "px"],
        /// See `fx`.
        cy: Option<f64> = None => [unit = "px"],
        /// Back-project every `stride`-th pixel in x and y (the organized output is
        /// ⌈w/stride⌉ × ⌈h/stride⌉): the speed–density knob. Default 1.
        stride: u32 = 1 => [min = 1.0],
        /// Estimate a normal per point from its organized neighbours (cross product of
        /// central differences, oriented towards the camera). Default true.
        normals: bool = true,
        /// Largest relative depth jump, |Δz| / z, between neighbours used for a normal: wider
        /// jumps are depth discontinuities (occlusion edges), where no normal is estimated
        /// (the point is kept without one — its normal is then the ray direction towards the
        /// camera). Default 0.05.
        max_depth_jump: f64 = 0.05 => [min = 0.0],
    }
}

/// The back-projection of a depth image.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthPoints {
    /// Organized width (⌈w/stride⌉).
    pub width: usize,
    /// Organized height (⌈h/stride⌉).
    pub height: usize,
    /// Organized points, row-major, NaN where the depth is invalid.
    pub xyz: Vec<[f32; 3]>,
    /// Organized unit normals (NaN where the depth is invalid); empty when not asked for.
    pub normals: Vec<[f32; 3]>,
    /// Valid points in row-major order (the unorganized cloud), colours and normals if
    /// present.
    pub cloud: PointCloud,
    /// Points whose normal came from neighbours (the rest fall back to the viewing ray).
    pub normals_estimated: usize,
}

/// Options of [`depth_to_points`].
#[derive(Debug, Clone, PartialEq)]
pub struct DepthOptions {
    /// Scene units per sample.
    pub depth_scale: f64,
    /// What a sample measures.
    pub kind: DepthKind,
    /// Valid depth range after scaling, `[min, max]`, min > 0 implied (0 is "no data").
    pub min_depth: f64,
    /// See `min_depth`.
    pub max_depth: f64,
    /// Pixel stride.
    pub stride: usize,
    /// Estimate normals.
    pub normals: bool,
    /// Largest relative depth jump between neighbours used for a normal.
    pub max_depth_jump: f64,
}

/// Errors of [`depth_to_points`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DepthError {
    /// The colour image has another size than the depth image.
    #[error("the colour image is {0}×{1} but the depth image is {2}×{3}")]
    ColorSize(usize, usize, usize, usize),
    /// The camera cannot back-project (zero or non-finite focal length).
    #[error("the camera's focal lengths must be finite and non-zero (fx {0}, fy {1})")]
    Focal(f64, f64),
}

/// Back-projects every `stride`-th pixel (u, v) of `depth` (samples row-major, `width` ×
/// `height`) through `lens`: the ray r = (x, y, 1) with (x, y) the undistorted normalized
/// coordinates of the pixel, and the point X = z·r with z = sample·`depth_scale` for
/// [`DepthKind::Z`], or X = s·r/|r| for [`DepthKind::Range`]. Samples that are not finite,
/// ≤ 0, or outside `[min_depth, max_depth]` (checked on the scaled sample: Z or range) are
/// invalid. With `camera_from_world` the points (and normals) are returned in world
/// coordinates, X_w = Rᵀ(X_c − t).
///
/// Normals (Open3D's and PCL's organized estimate): n = (X(u+1) − X(u−1)) × (X(v+1) − X(v−1)),
/// falling back to one-sided differences at a grid edge or an invalid neighbour, skipped across
/// depth discontinuities (|Δz| > `max_depth_jump`·z), and oriented towards the camera; a point
/// without a usable neighbour pair gets the unit vector towards the camera. `colors` (u8,
/// `channels` per pixel, same size as the depth) colours the points (gray replicated; alpha
/// dropped).
///
/// Rows are processed in parallel, each row independently: the result is the same for any
/// thread count.
#[allow(clippy::too_many_arguments)]
pub fn depth_to_points(
    depth: &[f32],
    width: usize,
    height: usize,
    lens: &Lens,
    camera_from_world: Option<&Pose>,
    colors: Option<(&[u8], usize)>,
    options: &DepthOptions,
) -> Result<DepthPoints, DepthError> {
    let k = lens.k;
    if !(k.fx.is_finite() && k.fy.is_finite() && k.fx != 0.0 && k.fy != 0.0) {
        return Err(DepthError::Focal(k.fx, k.fy));
    }
    let stride = options.stride.max(1);
    let (ow, oh) = (width.div_ceil(stride), height.div_ceil(stride));
    // Camera-frame points, organized.
    let xyz_camera: Vec<[f64; 3]> = (0..oh)
        .into_par_iter()
        .flat_map_iter(|oy| {
            (0..ow).map(move |ox| {
                let (u, v) = (ox * stride, oy * stride);
                let s = depth
                    .get(v * width + u)
                    .map_or(f64::NAN, |&d| f64::from(d) * options.depth_scale);
                back_project(lens, [u as f64, v as f64], s, options)
            })
        })
        .collect();
    let nan3 = [f64::NAN; 3];
    let normals_camera: Vec<Option<[f64; 3]>> = if options.normals {
        (0..oh)
            .into_par_iter()
            .flat_map_iter(|oy| {
                let xyz = &xyz_camera;
                (0..ow).map(move |ox| organized_normal(xyz, ow, oh, ox, oy, options))
            })
            .collect()
    } else {
        Vec::new()
    };
    let (rotation, translation) = match camera_from_world {
        Some(p) => (p.rotation_matrix(), p.translation),
        None => ([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], [0.0; 3]),
    };
    // X_w = Rᵀ (X_c − t); n_w = Rᵀ n_c.
    let rt = |v: [f64; 3]| -> [f64; 3] {
        let r = &rotation;
        [
            r[0] * v[0] + r[3] * v[1] + r[6] * v[2],
            r[1] * v[0] + r[4] * v[1] + r[7] * v[2],
            r[2] * v[0] + r[5] * v[1] + r[8] * v[2],
        ]
    };
    let to_f32 = |v: [f64; 3]| v.map(|c| c as f32);
    let mut xyz = Vec::with_capacity(xyz_camera.len());
    let mut normals = Vec::with_capacity(normals_camera.len());
    let mut cloud = PointCloud {
        positions: Vec::new(),
        colors: colors.map(|_| Vec::new()),
        normals: options.normals.then(Vec::new),
    };
    let mut estimated = 0;
    for (i, &p) in xyz_camera.iter().enumerate() {
        let valid = p[2].is_finite();
        let world = if valid {
            rt([
                p[0] - translation[0],
                p[1] - translation[1],
                p[2] - translation[2],
            ])
        } else {
            nan3
        };
        xyz.push(to_f32(world));
        if options.normals {
            let n = match normals_camera.get(i).copied().flatten() {
                Some(n) if valid => {
                    estimated += 1;
                    n
                }
                _ if valid => {
                    let len = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                    [-p[0] / len, -p[1] / len, -p[2] / len]
                }
                _ => nan3,
            };
            let n = if valid { rt(n) } else { nan3 };
            normals.push(to_f32(n));
            if valid && let Some(out) = cloud.normals.as_mut() {
                out.push(to_f32(n));
            }
        }
        if !valid {
            continue;
        }
        cloud.positions.push(to_f32(world));
        if let (Some((data, channels)), Some(out)) = (colors, cloud.colors.as_mut()) {
            let (ox, oy) = (i % ow, i / ow);
            let at = ((oy * stride) * width + ox * stride) * channels;
            let c = |j: usize| data.get(at + j.min(channels - 1)).copied().unwrap_or(0);
            out.push(if channels >= 3 {
                [c(0), c(1), c(2)]
            } else {
                [c(0); 3]
            });
        }
    }
    Ok(DepthPoints {
        width: ow,
        height: oh,
        xyz,
        normals,
        cloud,
        normals_estimated: estimated,
    })
}

/// Whether a scaled sample is a depth: finite, > 0 and inside `[min_depth, max_depth]`.
fn valid_sample(s: f64, o: &DepthOptions) -> bool {
    s.is_finite() && s > 0.0 && s >= o.min_depth && s <= o.max_depth
}

/// The camera-frame point of pixel `pixel` with scaled sample `s`, NaN when invalid.
fn back_project(lens: &Lens, pixel: [f64; 2], s: f64, o: &DepthOptions) -> [f64; 3] {
    let nan = [f64::NAN; 3];
    if !valid_sample(s, o) {
        return nan;
    }
    let Some([x, y]) = lens.undistort(lens.from_pixel(pixel)) else {
        return nan;
    };
    match o.kind {
        DepthKind::Z => [x * s, y * s, s],
        DepthKind::Range => {
            let n = (x * x + y * y + 1.0).sqrt();
            [x * s / n, y * s / n, s / n]
        }
    }
}

/// The normal at organized (x, y) from its 4-neighbours, towards the camera; None when no
/// usable pair of directions exists.
fn organized_normal(
    xyz: &[[f64; 3]],
    w: usize,
    h: usize,
    x: usize,
    y: usize,
    o: &DepthOptions,
) -> Option<[f64; 3]> {
    let p = *xyz.get(y * w + x)?;
    if !p[2].is_finite() {
        return None;
    }
    let usable = |q: Option<&[f64; 3]>| {
        q.copied()
            .filter(|q| q[2].is_finite() && (q[2] - p[2]).abs() <= o.max_depth_jump * p[2])
    };
    let at = |xx: Option<usize>, yy: Option<usize>| match (xx, yy) {
        (Some(xx), Some(yy)) if xx < w && yy < h => usable(xyz.get(yy * w + xx)),
        _ => None,
    };
    // A difference along one axis: central where both neighbours are usable, else one-sided.
    let diff = |minus: Option<[f64; 3]>, plus: Option<[f64; 3]>| match (minus, plus) {
        (Some(a), Some(b)) => Some(sub(b, a)),
        (None, Some(b)) => Some(sub(b, p)),
        (Some(a), None) => Some(sub(p, a)),
        (None, None) => None,
    };
    let du = diff(at(x.checked_sub(1), Some(y)), at(Some(x + 1), Some(y)))?;
    let dv = diff(at(Some(x), y.checked_sub(1)), at(Some(x), Some(y + 1)))?;
    let n = [
        du[1] * dv[2] - du[2] * dv[1],
        du[2] * dv[0] - du[0] * dv[2],
        du[0] * dv[1] - du[1] * dv[0],
    ];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if !(len.is_finite() && len > 0.0) {
        return None;
    }
    // Towards the camera at the origin: n · (−p) > 0.
    let sign = if n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > 0.0 {
        -1.0
    } else {
        1.0
    };
    Some(n.map(|c| sign * c / len))
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The input ports of an operator that reads one depth image like `sfm.depth_to_points`:
/// `depth`, optional `color`, `camera` and `pose` (documented by `pose_doc`).
pub(crate) fn depth_image_ports(pose_doc: &'static str) -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "depth",
            PortType::Image,
            "Depth, one channel (u8, u16 or f32), scaled by depth_scale.",
        ),
        PortSpec::new(
            "color",
            PortType::Image,
            "Colour of the same size (gray, RGB or RGBA; u8, or f32 in [0, 1]).",
        )
        .optional(),
        PortSpec::new(
            "camera",
            PortType::Camera,
            "Intrinsics and lens (replaces fx, fy, cx, cy).",
        )
        .optional(),
        PortSpec::new("pose", PortType::Pose, pose_doc).optional(),
    ]
}

/// Checks the depth scaling shared by the depth-image operators: `depth_scale` finite and
/// positive, `min_depth` finite and ≥ 0, `max_depth` (if any) finite and above `min_depth`.
pub(crate) fn check_depth_scaling(
    depth_scale: f64,
    min_depth: f64,
    max_depth: Option<f64>,
) -> Result<(), String> {
    if !(depth_scale.is_finite() && depth_scale > 0.0) {
        return Err(format!(
            "`depth_scale` must be finite and > 0, got {depth_scale}"
        ));
    }
    if !(min_depth.is_finite() && min_depth >= 0.0) {
        return Err(format!(
            "`min_depth` must be finite and ≥ 0, got {min_depth}"
        ));
    }
    if let Some(max) = max_depth
        && !(max.is_finite() && max > min_depth)
    {
        return Err(format!(
            "`max_depth` must be finite and > min_depth ({min_depth}), got {max}"
        ));
    }
    Ok(())
}

/// `sfm.depth_to_points`. See [`depth_to_points`].
#[derive(Debug, Clone, PartialEq)]
pub struct DepthToPoints {
    params: DepthToPointsParams,
}

impl Op for DepthToPoints {
    type Params = DepthToPointsParams;
    const ID: &'static str = "sfm.depth_to_points";
    const SUMMARY: &'static str = "Back-projects a depth image (RGB-D, rendered, or from stereo) through its camera into an \
         organized point cloud with normals and colours.";
    const DOC: &'static str = r#"
Turns a depth image into 3-D points: pixel (u, v) with depth z lies at z·(x, y, 1), (x, y) the
undistorted normalized coordinates of the pixel through the connected `camera` (any lens model
of the engine) or the `fx`, `fy`, `cx`, `cy` params. `depth_kind: "range"` reads samples as
distances along the ray (time-of-flight cameras, `capture.render`'s depth). Samples are
multiplied by `depth_scale` (0.001 for millimetre u16 depth); 0, negative, non-finite and
out-of-range (`min_depth`, `max_depth`) samples are invalid. With a `pose` (camera_from_world)
the points come out in world coordinates, so scans of several posed views fuse directly.

Outputs: `xyz`, the organized cloud as a 3-channel f32 image (⌈w/stride⌉ × ⌈h/stride⌉, NaN
where invalid, like OpenCV's `reprojectImageTo3D`); `cloud`, the valid points in row-major order
(emitted as PLY) with colours from `color` (u8, or f32 in [0, 1]; gray is replicated) and, with
`normals: true`, normals from the organized neighbours (cross product of central differences,
not across depth jumps wider than `max_depth_jump`·z, oriented towards the camera); `metrics`.

Stereo: `sfm.stereo` → `geometry.disparity_to_depth` (Z = f·B/d) → this op with the rectified
camera gives the scene of a rectified pair in the left camera's frame.

Metrics: `valid_points`, `invalid_points`, `normals_estimated`, `min_depth`, `max_depth` (of
the valid samples, Z or range as read).

References: OpenCV `rgbd::depthTo3d`; Open3D `PointCloud::CreateFromRGBDImage`; Holzer et al.,
"Adaptive neighborhood selection for real-time surface normal estimation from organized point
cloud data using integral images" (IROS 2012) for organized normals.

Example:
    "points": (op: "sfm.depth_to_points",
               inputs: { "depth": "kinect.image", "color": "rgb.image", "camera": "intr.camera" },
               params: (depth_scale: 0.001, max_depth: Some(4.0))),
"#;

    fn inputs() -> Vec<PortSpec> {
        depth_image_ports("camera_from_world: points in world coordinates.")
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "xyz",
                PortType::Image,
                "Organized points, 3-channel f32, NaN where invalid.",
            ),
            PortSpec::new(
                "cloud",
                PortType::PointCloud,
                "Valid points, row-major, colours and normals if available.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "valid_points, invalid_points, normals_estimated, min_depth, max_depth.",
            ),
        ]
    }

    fn new(p: DepthToPointsParams) -> Result<Self, String> {
        check_depth_scaling(p.depth_scale, p.min_depth, p.max_depth)?;
        for (name, v) in [("fx", p.fx), ("fy", p.fy), ("cx", p.cx), ("cy", p.cy)] {
            if let Some(v) = v
                && !v.is_finite()
            {
                return Err(format!("`{name}` must be finite, got {v}"));
            }
        }
        for (name, v) in [("fx", p.fx), ("fy", p.fy)] {
            if v == Some(0.0) {
                return Err(format!("`{name}` must be non-zero"));
            }
        }
        if p.stride == 0 {
            return Err("`stride` must be ≥ 1".into());
        }
        if !(p.max_depth_jump.is_finite() && p.max_depth_jump > 0.0) {
            return Err(format!(
                "`max_depth_jump` must be finite and > 0, got {}",
                p.max_depth_jump
            ));
        }
        Ok(DepthToPoints { params: p })
    }
}

/// The optional `color` input as u8 samples and their channel count; it must be `w` × `h`.
pub(crate) fn color_input(
    inputs: &Inputs<'_>,
    w: usize,
    h: usize,
) -> Result<Option<(Vec<u8>, usize)>, OpError> {
    match inputs.get("color") {
        Some(Value::Image(c)) => {
            if (c.width(), c.height()) != (w, h) {
                return Err(OpError::input(
                    "color",
                    DepthError::ColorSize(c.width(), c.height(), w, h).to_string(),
                ));
            }
            let u8_image = if c.depth() == Depth::U8 {
                (**c).clone()
            } else {
                convert_type(c, Depth::U8, None, 0.0)
                    .map_err(|e| OpError::input("color", e.to_string()))?
            };
            let channels = u8_image.channels().count();
            match u8_image.into_data() {
                PixelData::U8(v) => Ok(Some((v, channels))),
                _ => Err(OpError::failed("colour conversion to u8 failed")),
            }
        }
        Some(_) => Err(OpError::input("color", "expected an Image")),
        None => Ok(None),
    }
}

/// The optional `pose` input (camera_from_world).
pub(crate) fn pose_input(inputs: &Inputs<'_>) -> Result<Option<Pose>, OpError> {
    match inputs.get("pose") {
        Some(Value::Pose(p)) => Ok(Some(*p)),
        Some(_) => Err(OpError::input("pose", "expected a Pose")),
        None => Ok(None),
    }
}

impl DepthToPoints {
    /// The lens of the `camera` input, or of the `fx`, `fy`, `cx`, `cy` params.
    pub(crate) fn lens(&self, inputs: &Inputs<'_>, w: usize, h: usize) -> Result<Lens, OpError> {
        match inputs.get("camera") {
            Some(Value::Camera(c)) => {
                let c: &Camera = c;
                if (c.width as usize, c.height as usize) != (w, h) {
                    return Err(OpError::input(
                        "camera",
                        format!(
                            "the camera is {}×{} but the depth image is {w}×{h}",
                            c.width, c.height
                        ),
                    ));
                }
                Ok(Lens::from_camera(c))
            }
            Some(_) => Err(OpError::input("camera", "expected a Camera")),
            None => {
                let p = &self.params;
                let Some(fx) = p.fx else {
                    return Err(OpError::input(
                        "camera",
                        "not connected, and the `fx` param is not set: give one of them",
                    ));
                };
                let k = ocellus_engine::value::Intrinsics {
                    fx,
                    fy: p.fy.unwrap_or(fx),
                    cx: p.cx.unwrap_or((w as f64 - 1.0) / 2.0),
                    cy: p.cy.unwrap_or((h as f64 - 1.0) / 2.0),
                    skew: 0.0,
                };
                Ok(Lens::pinhole(k))
            }
        }
    }
}

impl Operator for DepthToPoints {
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
        let color_u8 = color_input(inputs, w, h)?;
        let pose = pose_input(inputs)?;
        let lens = self.lens(inputs, w, h)?;
        let p = &self.params;
        let options = DepthOptions {
            depth_scale: p.depth_scale,
            kind: p.depth_kind,
            min_depth: p.min_depth,
            max_depth: p.max_depth.unwrap_or(f64::INFINITY),
            stride: p.stride as usize,
            normals: p.normals,
            max_depth_jump: p.max_depth_jump,
        };
        let out = depth_to_points(
            &samples,
            w,
            h,
            &lens,
            pose.as_ref(),
            color_u8.as_ref().map(|(v, c)| (v.as_slice(), *c)),
            &options,
        )
        .map_err(|e| OpError::input("camera", e.to_string()))?;
        // The samples that were back-projected (every `stride`-th pixel) and are depths.
        let stride = options.stride;
        let valid: Vec<f64> = (0..h)
            .step_by(stride)
            .flat_map(|y| (0..w).step_by(stride).map(move |x| y * w + x))
            .filter_map(|i| samples.get(i))
            .map(|&s| f64::from(s) * p.depth_scale)
            .filter(|&s| valid_sample(s, &options))
            .collect();
        let mut m = Metrics::new();
        let n_valid = out.cloud.positions.len();
        m.insert("valid_points".into(), n_valid as f64);
        m.insert(
            "invalid_points".into(),
            (out.width * out.height - n_valid) as f64,
        );
        m.insert("normals_estimated".into(), out.normals_estimated as f64);
        if !valid.is_empty() {
            m.insert(
                "min_depth".into(),
                valid.iter().copied().fold(f64::INFINITY, f64::min),
            );
            m.insert(
                "max_depth".into(),
                valid.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            );
        }
        let flat: Vec<f32> = out.xyz.iter().flatten().copied().collect();
        let xyz = Image::from_f32(out.width, out.height, Channels::Rgb, flat)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("xyz", Value::image(xyz))
            .with("cloud", Value::PointCloud(Arc::new(out.cloud)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::{Distortion, Intrinsics};

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 500.0,
            fy: 480.0,
            cx: 31.5,
            cy: 23.0,
            skew: 0.0,
        }
    }

    fn options() -> DepthOptions {
        DepthOptions {
            depth_scale: 1.0,
            kind: DepthKind::Z,
            min_depth: 0.0,
            max_depth: f64::INFINITY,
            stride: 1,
            normals: true,
            max_depth_jump: 0.05,
        }
    }

    /// Depth of the plane n·X = d seen by a pinhole camera: Z = d / (n·(x, y, 1)).
    fn plane_depth(k: &Intrinsics, w: usize, h: usize, n: [f64; 3], d: f64) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let x = ((i % w) as f64 - k.cx) / k.fx;
                let y = ((i / w) as f64 - k.cy) / k.fy;
                (d / (n[0] * x + n[1] * y + n[2])) as f32
            })
            .collect()
    }

    #[test]
    fn hand_computed_pixel() {
        // Pixel (41.5 → use 41, 33) at Z = 2: x = (41 − 31.5)/500 = 0.019, y = (33 − 23)/480.
        let (w, h) = (64, 48);
        let mut depth = vec![0.0f32; w * h];
        depth[33 * w + 41] = 2.0;
        let out =
            depth_to_points(&depth, w, h, &Lens::pinhole(k()), None, None, &options()).unwrap();
        assert_eq!(out.cloud.positions.len(), 1);
        let p = out.cloud.positions[0];
        assert!((p[0] - 0.038).abs() < 1e-6, "{p:?}");
        assert!((p[1] - (2.0 * 10.0 / 480.0) as f32).abs() < 1e-6);
        assert_eq!(p[2], 2.0);
        // The organized output keeps the grid: NaN everywhere else, the point at its pixel.
        assert_eq!(out.xyz[33 * w + 41], p);
        assert!(out.xyz[0][0].is_nan());
        // A lone point has no neighbours: its normal faces the camera along the ray.
        let n = out.cloud.normals.as_ref().unwrap()[0];
        let len = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        for c in 0..3 {
            assert!((n[c] + p[c] / len).abs() < 1e-6);
        }
        assert_eq!(out.normals_estimated, 0);
    }

    #[test]
    fn a_plane_back_projects_onto_itself_with_its_normal() {
        let (w, h) = (64, 48);
        let len = (0.2f64 * 0.2 + 0.1 * 0.1 + 1.0).sqrt();
        let n = [0.2 / len, -0.1 / len, -1.0 / len]; // faces the camera (n·X < 0 side)
        let d = -3.0;
        let depth = plane_depth(&k(), w, h, n, d);
        let out =
            depth_to_points(&depth, w, h, &Lens::pinhole(k()), None, None, &options()).unwrap();
        assert_eq!(out.cloud.positions.len(), w * h);
        assert_eq!(out.normals_estimated, w * h);
        for (p, m) in out
            .cloud
            .positions
            .iter()
            .zip(out.cloud.normals.as_ref().unwrap())
        {
            let on_plane = n[0] * f64::from(p[0]) + n[1] * f64::from(p[1]) + n[2] * f64::from(p[2]);
            assert!((on_plane - d).abs() < 1e-5, "{on_plane}");
            for c in 0..3 {
                assert!((f64::from(m[c]) - n[c]).abs() < 1e-4, "{m:?} vs {n:?}");
            }
        }
    }

    #[test]
    fn range_depth_and_z_depth_agree() {
        let (w, h) = (16, 12);
        let z: Vec<f32> = (0..w * h).map(|i| 1.0 + (i % 7) as f32 * 0.25).collect();
        let lens = Lens::pinhole(k());
        let range: Vec<f32> = (0..w * h)
            .map(|i| {
                let [x, y] = lens.from_pixel([(i % w) as f64, (i / w) as f64]);
                (f64::from(z[i]) * (x * x + y * y + 1.0).sqrt()) as f32
            })
            .collect();
        let a = depth_to_points(&z, w, h, &lens, None, None, &options()).unwrap();
        let o = DepthOptions {
            kind: DepthKind::Range,
            ..options()
        };
        let b = depth_to_points(&range, w, h, &lens, None, None, &o).unwrap();
        for (p, q) in a.cloud.positions.iter().zip(&b.cloud.positions) {
            for c in 0..3 {
                assert!((p[c] - q[c]).abs() < 1e-5 * p[2]);
            }
        }
    }

    #[test]
    fn pose_gives_world_points_that_reproject() {
        // A camera at world (1, 2, −5) looking along +z, rotated 10° about y.
        let a = 10f64.to_radians();
        let r = [a.cos(), 0.0, -a.sin(), 0.0, 1.0, 0.0, a.sin(), 0.0, a.cos()];
        let c = [1.0, 2.0, -5.0];
        // t = −R c.
        let t = [
            -(r[0] * c[0] + r[1] * c[1] + r[2] * c[2]),
            -(r[3] * c[0] + r[4] * c[1] + r[5] * c[2]),
            -(r[6] * c[0] + r[7] * c[1] + r[8] * c[2]),
        ];
        let pose = Pose::from_rotation_matrix(&r, t);
        let (w, h) = (20, 10);
        let depth: Vec<f32> = (0..w * h).map(|i| 3.0 + (i % 5) as f32).collect();
        let lens = Lens::pinhole(k());
        let out = depth_to_points(&depth, w, h, &lens, Some(&pose), None, &options()).unwrap();
        let rm = pose.rotation_matrix();
        for (i, p) in out.xyz.iter().enumerate() {
            let p = p.map(f64::from);
            let xc = [
                rm[0] * p[0] + rm[1] * p[1] + rm[2] * p[2] + pose.translation[0],
                rm[3] * p[0] + rm[4] * p[1] + rm[5] * p[2] + pose.translation[1],
                rm[6] * p[0] + rm[7] * p[1] + rm[8] * p[2] + pose.translation[2],
            ];
            let u = k().fx * xc[0] / xc[2] + k().cx;
            let v = k().fy * xc[1] / xc[2] + k().cy;
            assert!((u - (i % w) as f64).abs() < 1e-4 && (v - (i / w) as f64).abs() < 1e-4);
            assert!((xc[2] - f64::from(depth[i])).abs() < 1e-5);
        }
    }

    #[test]
    fn distortion_is_undone() {
        let lens = Lens {
            k: k(),
            distortion: Distortion::RadialTangential([-0.2, 0.05, 0.001, -0.002, 0.0]),
        };
        let (w, h) = (64, 48);
        let depth = vec![2.0f32; w * h];
        let out = depth_to_points(&depth, w, h, &lens, None, None, &options()).unwrap();
        // Projecting each point through the distorting lens gives its pixel back.
        for (i, p) in out.xyz.iter().enumerate() {
            let n = [f64::from(p[0] / p[2]), f64::from(p[1] / p[2])];
            let px = lens.to_pixel(lens.distort(n));
            assert!(
                (px[0] - (i % w) as f64).abs() < 1e-3 && (px[1] - (i / w) as f64).abs() < 1e-3,
                "{i}: {px:?}"
            );
        }
    }

    #[test]
    fn invalid_samples_stride_and_range_limits() {
        let (w, h) = (5, 4);
        let mut depth = vec![1.0f32; w * h];
        depth[0] = 0.0;
        depth[1] = f32::NAN;
        depth[2] = -1.0;
        depth[3] = f32::INFINITY;
        depth[5] = 9.0;
        let o = DepthOptions {
            max_depth: 5.0,
            ..options()
        };
        let lens = Lens::pinhole(k());
        let out = depth_to_points(&depth, w, h, &lens, None, None, &o).unwrap();
        assert_eq!(out.cloud.positions.len(), w * h - 5);
        assert!(
            out.cloud
                .positions
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
        );
        let o = DepthOptions { stride: 2, ..o };
        let out = depth_to_points(&depth, w, h, &lens, None, None, &o).unwrap();
        assert_eq!((out.width, out.height), (3, 2));
        // Pixels (0,0) (2,0) (4,0) (0,2) (2,2) (4,2): (0,0) and (2,0) invalid.
        assert_eq!(out.cloud.positions.len(), 4);
    }

    #[test]
    fn normals_stop_at_depth_discontinuities() {
        // Left half at Z = 1, right half at Z = 3: a fronto-parallel step.
        let (w, h) = (10, 6);
        let depth: Vec<f32> = (0..w * h)
            .map(|i| if i % w < 5 { 1.0 } else { 3.0 })
            .collect();
        let out =
            depth_to_points(&depth, w, h, &Lens::pinhole(k()), None, None, &options()).unwrap();
        // Every point has a usable neighbour on its own side: all normals are (0, 0, −1).
        assert_eq!(out.normals_estimated, w * h);
        for n in out.cloud.normals.as_ref().unwrap() {
            assert!((n[2] + 1.0).abs() < 1e-6 && n[0].abs() < 1e-6, "{n:?}");
        }
    }

    #[test]
    fn colors_follow_their_pixels() {
        let (w, h) = (4, 3);
        let depth = vec![1.0f32; w * h];
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| i as u8).collect();
        let out = depth_to_points(
            &depth,
            w,
            h,
            &Lens::pinhole(k()),
            None,
            Some((&rgb, 3)),
            &options(),
        )
        .unwrap();
        let colors = out.cloud.colors.unwrap();
        assert_eq!(colors[5], [15, 16, 17]);
        let gray: Vec<u8> = (0..w * h).map(|i| i as u8 * 10).collect();
        let out = depth_to_points(
            &depth,
            w,
            h,
            &Lens::pinhole(k()),
            None,
            Some((&gray, 1)),
            &options(),
        )
        .unwrap();
        assert_eq!(out.cloud.colors.unwrap()[7], [70, 70, 70]);
    }

    /// Ground truth from the renderer: two rendered views of a sphere, back-projected from
    /// their range depth with their exact cameras and poses, land on the sphere in world
    /// coordinates (|X − c| = r), with outward normals away from occlusion edges.
    #[test]
    fn rendered_views_back_project_onto_the_sphere() {
        use crate::capture::render::{CaptureRenderParams, Renderer, render_frame};
        use crate::io::read_scene::parse_scene;
        let (c, r) = ([0.3, 0.2, -0.1], 0.8);
        let scene = parse_scene(
            r#"(objects: [(shape: Sphere(center: (0.3, 0.2, -0.1), radius: 0.8))],
                lights: [Environment(radiance: (1, 1, 1))],
                cameras: [(width: 80, height: 60, eye: (0, 0, 4)),
                          (width: 64, height: 64, eye: (3, 1.5, 2), target: (0.3, 0.2, -0.1))])"#,
            std::path::Path::new("scene.ron"),
        )
        .unwrap()
        .scene;
        let params = CaptureRenderParams {
            renderer: Renderer::Rasterize,
            samples: 1,
            spp: 1,
            seed: 0,
        };
        for (i, cam) in scene.cameras.iter().enumerate() {
            let frame = render_frame(&scene, i, &params).unwrap();
            let (w, h) = (frame.depth.width(), frame.depth.height());
            let o = DepthOptions {
                kind: DepthKind::Range,
                ..options()
            };
            let out = depth_to_points(
                frame.depth.as_f32().unwrap(),
                w,
                h,
                &Lens::from_camera(&cam.camera),
                Some(&cam.camera_from_world),
                None,
                &o,
            )
            .unwrap();
            assert!(
                out.cloud.positions.len() > 200,
                "camera {i}: {}",
                out.cloud.positions.len()
            );
            let normals = out.cloud.normals.as_ref().unwrap();
            let mut checked = 0;
            for (p, n) in out.cloud.positions.iter().zip(normals) {
                let d = [0, 1, 2].map(|k| f64::from(p[k]) - c[k]);
                let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((dist - r).abs() < 1e-4, "camera {i}: |X − c| = {dist}");
                // Outward normal: n · (X − c)/r ≈ 1 where the surface faces the camera.
                let cos = (0..3).map(|k| f64::from(n[k]) * d[k] / dist).sum::<f64>();
                if cos > 0.9 {
                    checked += 1;
                }
            }
            // Most normals are accurate (the grazing rim is where neighbours are far apart).
            assert!(
                checked * 10 > out.cloud.positions.len() * 8,
                "camera {i}: {checked}"
            );
        }
    }

    /// Stereo: disparities of a slanted plane seen by a rectified pair (d = f·B/Z) →
    /// `geometry.disparity_to_depth` → points on that plane.
    #[test]
    fn disparity_to_depth_to_points_recovers_a_plane() {
        let (w, h, baseline) = (48, 32, 0.12);
        let kk = Intrinsics { fy: 500.0, ..k() };
        let len = (0.1f64 * 0.1 + 0.3 * 0.3 + 1.0).sqrt();
        let n = [0.1 / len, 0.3 / len, -1.0 / len];
        let z = plane_depth(&kk, w, h, n, -2.5);
        let disparity: Vec<f32> = z
            .iter()
            .map(|&z| (kk.fx * baseline / f64::from(z)) as f32)
            .collect();
        let depth = crate::geometry::rectify::disparity_to_depth(
            &disparity,
            1.0,
            kk.fx * baseline,
            f32::NAN,
        );
        let out =
            depth_to_points(&depth, w, h, &Lens::pinhole(kk), None, None, &options()).unwrap();
        assert_eq!(out.cloud.positions.len(), w * h);
        for p in &out.cloud.positions {
            let on = n[0] * f64::from(p[0]) + n[1] * f64::from(p[1]) + n[2] * f64::from(p[2]);
            assert!((on + 2.5).abs() < 1e-4, "{on}");
        }
    }

    #[test]
    fn zero_focal_is_an_error() {
        let mut kk = k();
        kk.fx = 0.0;
        let e = depth_to_points(&[1.0], 1, 1, &Lens::pinhole(kk), None, None, &options());
        assert!(matches!(e, Err(DepthError::Focal(..))));
    }

    #[test]
    fn empty_and_one_pixel_images() {
        let lens = Lens::pinhole(k());
        let out = depth_to_points(&[], 0, 0, &lens, None, None, &options()).unwrap();
        assert!(out.cloud.positions.is_empty() && out.xyz.is_empty());
        let out = depth_to_points(&[2.0], 1, 1, &lens, None, None, &options()).unwrap();
        assert_eq!(out.cloud.positions.len(), 1);
        assert_eq!(out.normals_estimated, 0);
    }
}
