//! Undistortion and stereo rectification: `geometry.undistort`, `geometry.stereo_rectify`,
//! `geometry.disparity_to_depth`.
//!
//! - [`undistort_rectify_map`] builds OpenCV's `initUndistortRectifyMap` table: destination
//!   pixel `(u, v)` → ray `(P·R)⁻¹·(u, v, 1)` (P the new 3×3 camera matrix, R the rectifying
//!   rotation) → the source camera's lens model ([`Lens::project`], distortion included) →
//!   source pixel. The image is then resampled by the warps' sampler ([`remap`]).
//! - [`stereo_rectify`] is Bouguet's algorithm with OpenCV's `stereoRectify` arithmetic
//!   (`alpha = −1`: no extra scaling): each camera turns by half the relative rotation, then a
//!   common rotation takes the baseline onto the x axis (or y for vertical rigs); the new focal
//!   length is the mean of the two (fy for horizontal rigs), the principal points centre the
//!   undistorted image corners, and with `zero_disparity` both share one principal point.
//! - [`disparity_to_depth`]: `Z = f·B/d`.

use std::sync::Arc;

use nalgebra::{Matrix3, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Camera, Channels, Image, Matrix, PixelData, Pose, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::camera::{Lens, angle_axis, from_na, mat3_vec, rodrigues, to_na, undistort_points};
use crate::filter::border::{BorderMode, check_border_value};
use crate::filter::warp::{RemapTable, WarpInterpolation, WarpOptions, remap};

/// Rows per parallel band of the map.
const BAND_ROWS: usize = 16;

/// OpenCV's `initUndistortRectifyMap`: for every pixel of a `width × height` destination, the
/// source pixel of `lens` it shows, after the rectifying rotation `r` (row-major; identity if
/// `None`) and with new camera matrix `new_k` (row-major 3×3, e.g. the left 3×3 of a rectified
/// projection). Rays the lens cannot image map to (−1e6, −1e6), i.e. the border. `None` if
/// `new_k · r` is singular.
pub fn undistort_rectify_map(
    lens: &Lens,
    r: Option<&[f64; 9]>,
    new_k: &[f64; 9],
    width: usize,
    height: usize,
) -> Option<RemapTable> {
    let r = r.map_or_else(Matrix3::identity, to_na);
    let inv = from_na(&(to_na(new_k) * r).try_inverse()?);
    let n = width * height;
    let mut map_x = vec![0f32; n];
    let mut map_y = vec![0f32; n];
    if n > 0 {
        let band = BAND_ROWS * width;
        map_x
            .par_chunks_mut(band)
            .zip(map_y.par_chunks_mut(band))
            .enumerate()
            .for_each(|(b, (mx, my))| {
                for (i, (ox, oy)) in mx.iter_mut().zip(my.iter_mut()).enumerate() {
                    let at = b * band + i;
                    let (u, v) = ((at % width) as f64, (at / width) as f64);
                    let ray = mat3_vec(&inv, [u, v, 1.0]);
                    let p = lens.project(ray).unwrap_or([-1e6, -1e6]);
                    *ox = p[0] as f32;
                    *oy = p[1] as f32;
                }
            });
    }
    Some(RemapTable {
        width,
        height,
        map_x,
        map_y,
    })
}

/// Bouguet rectification of a calibrated stereo pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoRectification {
    /// Rectifying rotation of camera 1 (row-major).
    pub r1: [f64; 9],
    /// Rectifying rotation of camera 2.
    pub r2: [f64; 9],
    /// 3×4 projection of rectified camera 1 (row-major).
    pub p1: [f64; 12],
    /// 3×4 projection of rectified camera 2: `P2[0][3] = f·Tx` (or `P2[1][3] = f·Ty`).
    pub p2: [f64; 12],
    /// 4×4 disparity-to-depth matrix (row-major).
    pub q: [f64; 16],
}

/// OpenCV's `stereoRectify` (alpha −1, new size = image size) for cameras `lens1`, `lens2` of a
/// `width × height` image and the relative pose `x2 = R·x1 + T` (`r` row-major). See the
/// module docs. Errors when the baseline is zero.
pub fn stereo_rectify(
    lens1: &Lens,
    lens2: &Lens,
    width: usize,
    height: usize,
    r: &[f64; 9],
    t: [f64; 3],
    zero_disparity: bool,
) -> Result<StereoRectification, String> {
    let rm = to_na(r);
    let tv = Vector3::from(t);
    if tv.norm() == 0.0 || !tv.iter().all(|v| v.is_finite()) {
        return Err("the baseline (translation between the cameras) must be non-zero".into());
    }
    let om = angle_axis(&rm);
    let r_r = rodrigues(om.map(|v| -0.5 * v));
    let tt = r_r * tv;
    let idx = if tt[0].abs() > tt[1].abs() { 0 } else { 1 };
    let c = tt[idx];
    let nt = tt.norm();
    let mut uu = Vector3::zeros();
    uu[idx] = if c > 0.0 { 1.0 } else { -1.0 };
    let mut ww = tt.cross(&uu);
    let nw = ww.norm();
    if nw > 0.0 {
        ww *= (c.abs() / nt).clamp(-1.0, 1.0).acos() / nw;
    }
    let wr = rodrigues([ww[0], ww[1], ww[2]]);
    let r1 = wr * r_r.transpose();
    let r2 = wr * r_r;
    let t2 = r2 * tv;
    let k1 = lens1.k_matrix();
    let k2 = lens2.k_matrix();
    let d = if idx == 0 { 4 } else { 0 }; // K[idx^1][idx^1]
    let fc = (k1[d] + k2[d]) * 0.5;
    let (nx, ny) = (width as f64, height as f64);
    let corners = [
        [0.0, 0.0],
        [nx - 1.0, 0.0],
        [0.0, ny - 1.0],
        [nx - 1.0, ny - 1.0],
    ];
    let mut cc = [[0.0; 2]; 2];
    for (k, (lens, rk)) in [(lens1, &r1), (lens2, &r2)].into_iter().enumerate() {
        let und = undistort_points(lens, &corners, None, None);
        let mut avg = [0.0; 2];
        let mut count = 0.0;
        for p in &und {
            if !(p[0].is_finite() && p[1].is_finite()) {
                continue;
            }
            let v = rk * Vector3::new(p[0], p[1], 1.0);
            avg[0] += fc * v[0] / v[2];
            avg[1] += fc * v[1] / v[2];
            count += 1.0;
        }
        if count == 0.0 {
            return Err("the image corners of a camera do not undistort".into());
        }
        cc[k] = [
            (nx - 1.0) / 2.0 - avg[0] / count,
            (ny - 1.0) / 2.0 - avg[1] / count,
        ];
    }
    if zero_disparity {
        let m = [(cc[0][0] + cc[1][0]) * 0.5, (cc[0][1] + cc[1][1]) * 0.5];
        cc = [m, m];
    } else {
        let a = if idx == 0 { 1 } else { 0 };
        let m = (cc[0][a] + cc[1][a]) * 0.5;
        cc[0][a] = m;
        cc[1][a] = m;
    }
    let p1 = [
        fc, 0.0, cc[0][0], 0.0, 0.0, fc, cc[0][1], 0.0, 0.0, 0.0, 1.0, 0.0,
    ];
    let mut p2 = [
        fc, 0.0, cc[1][0], 0.0, 0.0, fc, cc[1][1], 0.0, 0.0, 0.0, 1.0, 0.0,
    ];
    p2[idx * 4 + 3] = t2[idx] * fc;
    let ti = t2[idx];
    let dc = if idx == 0 {
        cc[0][0] - cc[1][0]
    } else {
        cc[0][1] - cc[1][1]
    };
    let q = [
        1.0,
        0.0,
        0.0,
        -cc[0][0],
        0.0,
        1.0,
        0.0,
        -cc[0][1],
        0.0,
        0.0,
        0.0,
        fc,
        0.0,
        0.0,
        -1.0 / ti,
        dc / ti,
    ];
    Ok(StereoRectification {
        r1: from_na(&r1),
        r2: from_na(&r2),
        p1,
        p2,
        q,
    })
}

/// The left 3×3 of a row-major 3×4 matrix.
pub fn left3x3(p: &[f64; 12]) -> [f64; 9] {
    [p[0], p[1], p[2], p[4], p[5], p[6], p[8], p[9], p[10]]
}

param_enum! {
    /// Depth written where the disparity is not positive (no match).
    pub enum InvalidDepth {
        /// NaN.
        Nan = "nan",
        /// 0.
        Zero = "zero",
    }
}

/// The samples of a one-channel image as f32 (u8 and u16 widened exactly).
pub fn samples_f32(image: &Image) -> Vec<f32> {
    match image.data() {
        PixelData::U8(v) => v.iter().map(|&x| f32::from(x)).collect(),
        PixelData::U16(v) => v.iter().map(|&x| f32::from(x)).collect(),
        PixelData::F32(v) => v.clone(),
    }
}

/// Depth `Z = f·B / (scale·d)` of every disparity sample (`f` in pixels, `B` in the unit
/// wanted for Z); `d ≤ 0` or non-finite → `invalid`.
pub fn disparity_to_depth(
    disparity: &[f32],
    scale: f64,
    focal_baseline: f64,
    invalid: f32,
) -> Vec<f32> {
    disparity
        .par_chunks(1 << 14)
        .flat_map_iter(|c| {
            c.iter().map(move |&d| {
                let d = f64::from(d) * scale;
                if d > 0.0 && d.is_finite() {
                    (focal_baseline / d) as f32
                } else {
                    invalid
                }
            })
        })
        .collect()
}

params! {
    /// Parameters of `geometry.undistort`.
    pub struct UndistortParams {
        /// Resampling method. Default: bilinear.
        interpolation: WarpInterpolation = WarpInterpolation::Bilinear,
        /// How pixels outside the source are read. Default: constant (as OpenCV's `remap`
        /// after `initUndistortRectifyMap`).
        border: BorderMode = BorderMode::Constant,
        /// Sample value outside the source with border "constant", image units. Default 0.
        border_value: f64 = 0.0,
    }
}

/// Image undistortion / rectification (`geometry.undistort`).
#[derive(Debug, Clone, PartialEq)]
pub struct Undistort {
    options: WarpOptions,
}

/// A row-major 3×3 from a Matrix input (3×3, or the left 3×3 of a 3×4).
fn matrix3(inputs: &Inputs<'_>, port: &str) -> Result<Option<[f64; 9]>, OpError> {
    let Some(v) = inputs.get(port) else {
        return Ok(None);
    };
    let Value::Matrix(m) = v else {
        return Err(OpError::input(port, "expected a Matrix"));
    };
    if m.data.iter().any(|v| !v.is_finite()) {
        return Err(OpError::input(port, "the matrix has a non-finite entry"));
    }
    let d = &m.data;
    match (m.rows, m.cols) {
        (3, 3) => Ok(Some(std::array::from_fn(|i| d[i]))),
        (3, 4) => Ok(Some([
            d[0], d[1], d[2], d[4], d[5], d[6], d[8], d[9], d[10],
        ])),
        (r, c) => Err(OpError::input(
            port,
            format!("expected a 3×3 (or 3×4) matrix, got {r}×{c}"),
        )),
    }
}

fn camera_input(inputs: &Inputs<'_>, port: &str) -> Result<Arc<Camera>, OpError> {
    match inputs.require(port)? {
        Value::Camera(c) => {
            let lens = Lens::from_camera(c);
            let k = lens.k;
            if !(k.fx.is_finite() && k.fy.is_finite() && k.fx != 0.0 && k.fy != 0.0) {
                return Err(OpError::input(
                    port,
                    "the camera's focal lengths must be non-zero",
                ));
            }
            Ok(c.clone())
        }
        _ => Err(OpError::input(port, "expected a Camera")),
    }
}

impl Op for Undistort {
    type Params = UndistortParams;
    const ID: &'static str = "geometry.undistort";
    const SUMMARY: &'static str = "Removes lens distortion from an image (optionally rectifying it with a rotation and a new camera matrix).";
    const DOC: &'static str = r#"
Resamples an image of a distorted camera into the image an ideal pinhole camera would see:
OpenCV's `initUndistortRectifyMap` + `remap` (or `undistort` when only the camera is given).

For every destination pixel (u, v), the ray (P·R)⁻¹·(u, v, 1) is projected through the input
camera's full lens model (radial–tangential or fisheye, with skew) to a source pixel, which is
sampled with the warps' sampler (`filter.warp_perspective`'s arithmetic: f32 weights, rounding
and saturation for integer images; taps outside the image read through `border`). P is the
`projection` input (3×3 or 3×4: its left 3×3) or the camera's own K; R is the `rotation` input
(e.g. R1 of `geometry.stereo_rectify`) or the identity. Rays the lens cannot image (behind a
pinhole camera) read the border.

Accepts every pixel format; the output has the input's size and format (a camera calibrated at a
different size is used as is). Differences from OpenCV: the map is kept in f32 source
coordinates (OpenCV's `remap` with CV_32FC1 maps does the same; `undistort` uses 1/32-pixel
fixed-point maps), and fisheye cameras use the same operator (OpenCV has `cv::fisheye`).

Example (a node of a graph):
    "flat": (op: "geometry.undistort", inputs: { "image": "frame.image", "camera": "calib.camera" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "image of the camera, any format"),
            PortSpec::new(
                "camera",
                PortType::Camera,
                "the camera (intrinsics + distortion)",
            ),
            PortSpec::new("rotation", PortType::Matrix, "rectifying rotation R (3×3)").optional(),
            PortSpec::new(
                "projection",
                PortType::Matrix,
                "new camera matrix (3×3, or a 3×4 projection)",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "undistorted image, input size and format",
        )]
    }

    fn new(p: UndistortParams) -> Result<Self, String> {
        check_border_value(p.border, p.border_value)?;
        Ok(Undistort {
            options: WarpOptions {
                size: None,
                interpolation: p.interpolation,
                border: p.border,
                border_value: p.border_value,
            },
        })
    }
}

impl Operator for Undistort {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let camera = camera_input(inputs, "camera")?;
        let lens = Lens::from_camera(&camera);
        let r = matrix3(inputs, "rotation")?;
        let p = matrix3(inputs, "projection")?.unwrap_or_else(|| lens.k_matrix());
        let table = undistort_rectify_map(&lens, r.as_ref(), &p, image.width(), image.height())
            .ok_or_else(|| OpError::failed("projection · rotation is singular"))?;
        let out = remap(image, &table, &self.options).map_err(OpError::failed)?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

params! {
    /// Parameters of `geometry.stereo_rectify`.
    pub struct StereoRectifyParams {
        /// true: both rectified cameras share the principal point, so points at infinity
        /// have zero disparity (OpenCV's `CALIB_ZERO_DISPARITY`, its default). Default true.
        zero_disparity: bool = true,
        /// Image size `[width, height]`, pixels. Default: none, the size of camera 1.
        image_size: Option<[u32; 2]> = None,
    }
}

/// Bouguet stereo rectification (`geometry.stereo_rectify`).
#[derive(Debug, Clone, PartialEq)]
pub struct StereoRectify {
    zero_disparity: bool,
    image_size: Option<[u32; 2]>,
}

fn matrix_value(rows: usize, cols: usize, data: &[f64]) -> Result<Value, OpError> {
    Matrix::new(rows, cols, data.to_vec())
        .map(|m| Value::Matrix(Arc::new(m)))
        .map_err(|e| OpError::failed(e.to_string()))
}

impl Op for StereoRectify {
    type Params = StereoRectifyParams;
    const ID: &'static str = "geometry.stereo_rectify";
    const SUMMARY: &'static str = "Computes the rectifying rotations and projections of a calibrated stereo pair (Bouguet's method, OpenCV's stereoRectify).";
    const DOC: &'static str = r#"
Bouguet's stereo rectification with OpenCV's `stereoRectify` arithmetic (alpha = −1: no extra
scaling; new image size = image size). Inputs: the two cameras and `pose`, camera 2 from camera 1
(x2 = R·x1 + T, OpenCV's R, T from `stereoCalibrate`).

Method: each camera turns by half of the relative rotation (r_r = rodrigues(−rodrigues⁻¹(R)/2));
a common rotation then takes the baseline r_r·T onto the x axis (onto y when |Ty| ≥ |Tx|: a
vertical rig). R1 = W·r_rᵀ, R2 = W·r_r. The new focal length is the mean fy (fx for vertical
rigs) of the two cameras; each principal point centres that camera's four undistorted image
corners; with `zero_disparity` both take their mean, otherwise only the coordinate across the
baseline is shared. P1 = [K' | 0], P2 = [K' | K'·(Tx', 0, 0)ᵀ] with Tx' = (R2·T)ₓ, and
Q = [[1,0,0,−cx1],[0,1,0,−cy1],[0,0,0,f],[0,0,−1/Tx',(cx1−cx2)/Tx']].

Outputs R1, R2 (3×3), P1, P2 (3×4), Q (4×4) as matrices; feed R_k and P_k to
`geometry.undistort` to rectify the images.

Differences from OpenCV: alpha ≥ 0 (cropping/scaling to valid pixels), a different new image
size and the valid ROIs are not supported.

Example (a node of a graph):
    "rect": (op: "geometry.stereo_rectify",
             inputs: { "camera_left": "left.camera", "camera_right": "right.camera", "pose": "stereo.pose" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("camera_left", PortType::Camera, "camera 1"),
            PortSpec::new("camera_right", PortType::Camera, "camera 2"),
            PortSpec::new(
                "pose",
                PortType::Pose,
                "camera 2 from camera 1: x2 = R·x1 + T",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "r1",
                PortType::Matrix,
                "rectifying rotation of camera 1, 3×3",
            ),
            PortSpec::new(
                "r2",
                PortType::Matrix,
                "rectifying rotation of camera 2, 3×3",
            ),
            PortSpec::new(
                "p1",
                PortType::Matrix,
                "rectified projection of camera 1, 3×4",
            ),
            PortSpec::new(
                "p2",
                PortType::Matrix,
                "rectified projection of camera 2, 3×4",
            ),
            PortSpec::new("q", PortType::Matrix, "disparity-to-depth matrix, 4×4"),
        ]
    }

    fn new(p: StereoRectifyParams) -> Result<Self, String> {
        if let Some([w, h]) = p.image_size
            && (w == 0 || h == 0)
        {
            return Err(format!("`image_size` must be positive, got {w} × {h}"));
        }
        Ok(StereoRectify {
            zero_disparity: p.zero_disparity,
            image_size: p.image_size,
        })
    }
}

impl Operator for StereoRectify {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let c1 = camera_input(inputs, "camera_left")?;
        let c2 = camera_input(inputs, "camera_right")?;
        let Value::Pose(pose) = inputs.require("pose")? else {
            return Err(OpError::input("pose", "expected a Pose"));
        };
        let pose: &Pose = pose;
        let [w, h] = self.image_size.unwrap_or([c1.width, c1.height]);
        let s = stereo_rectify(
            &Lens::from_camera(&c1),
            &Lens::from_camera(&c2),
            w as usize,
            h as usize,
            &pose.rotation_matrix(),
            pose.translation,
            self.zero_disparity,
        )
        .map_err(OpError::failed)?;
        Ok(Outputs::new()
            .with("r1", matrix_value(3, 3, &s.r1)?)
            .with("r2", matrix_value(3, 3, &s.r2)?)
            .with("p1", matrix_value(3, 4, &s.p1)?)
            .with("p2", matrix_value(3, 4, &s.p2)?)
            .with("q", matrix_value(4, 4, &s.q)?))
    }
}

params! {
    /// Parameters of `geometry.disparity_to_depth`.
    pub struct DisparityToDepthParams {
        /// Focal length f, pixels (used when no `q` matrix is connected). Default 1.
        focal: f64 = 1.0,
        /// Baseline B, in the unit wanted for depth (used when no `q` is connected). Default 1.
        baseline: f64 = 1.0,
        /// Disparity units per pixel: the samples are multiplied by it (1/16 for OpenCV's
        /// fixed-point StereoBM/SGBM output). Default 1.
        scale: f64 = 1.0,
        /// Depth where the disparity is ≤ 0 or not finite: "nan" or "zero". Default "nan".
        invalid: InvalidDepth = InvalidDepth::Nan,
    }
}

/// Disparity → depth (`geometry.disparity_to_depth`).
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityToDepth {
    focal: f64,
    baseline: f64,
    scale: f64,
    invalid: InvalidDepth,
}

impl Op for DisparityToDepth {
    type Params = DisparityToDepthParams;
    const ID: &'static str = "geometry.disparity_to_depth";
    const SUMMARY: &'static str =
        "Converts a disparity map of a rectified stereo pair to depth, Z = f·B/d.";
    const DOC: &'static str = r#"
Depth of every pixel of a disparity map of a rectified pair: Z = f·B / d with d = scale·sample.
f and B come from the params, or from a connected `q` matrix (OpenCV's Q of
`geometry.stereo_rectify`): f = Q[2][3], B = −1/Q[3][2], i.e. the depth of
`cv::reprojectImageTo3D` when the principal points coincide (zero disparity). Disparities ≤ 0
(no match) and non-finite ones give `invalid` (NaN or 0).

Input: a one-channel disparity image (u8, u16 or f32). Output: an f32 depth image of the same
size, in the unit of B.

Example (a node of a graph):
    "depth": (op: "geometry.disparity_to_depth", inputs: { "disparity": "stereo.disparity" },
              params: (focal: 700.0, baseline: 0.12, scale: 0.0625)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "disparity",
                PortType::Image,
                "disparity, one channel, pixels",
            ),
            PortSpec::new(
                "q",
                PortType::Matrix,
                "OpenCV's 4×4 Q (replaces focal, baseline)",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "depth",
            PortType::Image,
            "depth, f32, unit of the baseline",
        )]
    }

    fn new(p: DisparityToDepthParams) -> Result<Self, String> {
        for (name, v) in [
            ("focal", p.focal),
            ("baseline", p.baseline),
            ("scale", p.scale),
        ] {
            if !(v.is_finite() && v != 0.0) {
                return Err(format!("`{name}` must be finite and non-zero, got {v}"));
            }
        }
        Ok(DisparityToDepth {
            focal: p.focal,
            baseline: p.baseline,
            scale: p.scale,
            invalid: p.invalid,
        })
    }
}

impl Operator for DisparityToDepth {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("disparity")?;
        if image.channels() != Channels::Gray {
            return Err(OpError::input(
                "disparity",
                format!("expected one channel, got {}", image.channels().name()),
            ));
        }
        let fb = match inputs.get("q") {
            Some(Value::Matrix(q)) => {
                if q.rows != 4 || q.cols != 4 {
                    return Err(OpError::input(
                        "q",
                        format!("expected 4×4, got {}×{}", q.rows, q.cols),
                    ));
                }
                let (f, inv_b) = (q.data[11], q.data[14]);
                if !(f.is_finite() && inv_b.is_finite() && inv_b != 0.0) {
                    return Err(OpError::input(
                        "q",
                        "Q[2][3] and Q[3][2] must be finite, Q[3][2] ≠ 0",
                    ));
                }
                f * (-1.0 / inv_b)
            }
            Some(_) => return Err(OpError::input("q", "expected a Matrix")),
            None => self.focal * self.baseline,
        };
        let invalid = match self.invalid {
            InvalidDepth::Nan => f32::NAN,
            InvalidDepth::Zero => 0.0,
        };
        let samples = samples_f32(image);
        let depth = disparity_to_depth(&samples, self.scale, fb, invalid);
        let out = Image::from_f32(image.width(), image.height(), Channels::Gray, depth)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("depth", Value::image(out)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::warp::{Transform, warp};
    use ocellus_engine::value::{Distortion, Intrinsics};
    use proptest::prelude::*;

    fn lens(k1: f64) -> Lens {
        Lens {
            k: Intrinsics {
                fx: 400.0,
                fy: 405.0,
                cx: 161.0,
                cy: 119.0,
                skew: 0.0,
            },
            distortion: Distortion::RadialTangential([k1, 0.05, 0.001, -0.0007, 0.0]),
        }
    }

    #[test]
    fn remap_equals_warp_for_an_exact_translation() {
        let img = crate::filter::test_support::random_u8(23, 17, Channels::Rgb, 5);
        let (w, h) = (20, 15);
        let table = RemapTable {
            width: w,
            height: h,
            map_x: (0..w * h).map(|i| (i % w) as f32 + 2.5).collect(),
            map_y: (0..w * h).map(|i| (i / w) as f32 - 1.25).collect(),
        };
        let o = WarpOptions {
            size: Some((w, h)),
            interpolation: WarpInterpolation::Bilinear,
            border: BorderMode::Reflect101,
            border_value: 0.0,
        };
        let a = remap(&img, &table, &o).unwrap();
        let b = warp(
            &img,
            &Transform::Affine([1.0, 0.0, 2.5, 0.0, 1.0, -1.25]),
            &o,
        )
        .unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn undistort_map_inverts_the_lens() {
        let l = lens(-0.3);
        let t = undistort_rectify_map(&l, None, &l.k_matrix(), 320, 240).unwrap();
        // Pixel (u, v) of the ideal image shows the ray through K⁻¹(u, v, 1).
        for &(u, v) in &[(0usize, 0usize), (319, 0), (160, 120), (10, 230)] {
            let s = [t.map_x[v * 320 + u] as f64, t.map_y[v * 320 + u] as f64];
            let n = l.undistort(l.from_pixel(s)).unwrap();
            let ideal = Lens::pinhole(l.k).to_pixel(n);
            assert!((ideal[0] - u as f64).abs() < 1e-3 && (ideal[1] - v as f64).abs() < 1e-3);
        }
    }

    #[test]
    fn undistort_op_on_formats_and_tiny_images() {
        let cam = lens(-0.2).to_camera(8, 6);
        for img in [
            Image::from_u8(8, 6, Channels::Gray, vec![7; 48]).unwrap(),
            Image::from_u16(8, 6, Channels::Rgb, vec![1000; 144]).unwrap(),
            Image::from_f32(8, 6, Channels::Rgba, vec![0.5; 192]).unwrap(),
            Image::from_u8(1, 1, Channels::Gray, vec![9]).unwrap(),
            Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap(),
        ] {
            let lens = Lens::from_camera(&cam);
            let table =
                undistort_rectify_map(&lens, None, &lens.k_matrix(), img.width(), img.height())
                    .unwrap();
            let o = WarpOptions {
                size: None,
                interpolation: WarpInterpolation::Bilinear,
                border: BorderMode::Constant,
                border_value: 0.0,
            };
            let out = remap(&img, &table, &o).unwrap();
            assert_eq!(out.format(), img.format());
            assert_eq!((out.width(), out.height()), (img.width(), img.height()));
        }
    }

    #[test]
    fn disparity_to_depth_by_hand() {
        let d = disparity_to_depth(
            &[0.0, -1.0, 10.0, 20.0, f32::NAN],
            1.0,
            700.0 * 0.1,
            f32::NAN,
        );
        assert!(d[0].is_nan() && d[1].is_nan() && d[4].is_nan());
        assert!((d[2] - 7.0).abs() < 1e-6 && (d[3] - 3.5).abs() < 1e-6);
        let z = disparity_to_depth(&[160.0, 0.0], 1.0 / 16.0, 70.0, 0.0);
        assert_eq!(z, vec![7.0, 0.0]);
    }

    fn rig() -> ([f64; 9], [f64; 3]) {
        let r = rodrigues([0.02, -0.05, 0.01]);
        (from_na(&r), [-0.12, 0.004, 0.002])
    }

    #[test]
    fn stereo_rectify_matches_opencv() {
        // cv2.stereoRectify(K1, D1, K2, D2, (320, 240), R, T, alpha=-1) with K1 = K2 = lens(0),
        // D = [0, 0.05, 0.001, -0.0007, 0], R = rodrigues([0.02, -0.05, 0.01]),
        // T = [-0.12, 0.004, 0.002]: the constants below. OpenCV undistorts the image corners
        // in f32, so its principal points agree to ~1e-5 px only.
        let (r, t) = rig();
        let l = lens(0.0);
        let s = stereo_rectify(&l, &l, 320, 240, &r, t, true).unwrap();
        let want_p1 = OPENCV_P1;
        let want_p2 = OPENCV_P2;
        for i in 0..12 {
            assert!(
                (s.p1[i] - want_p1[i]).abs() < 1e-4,
                "P1 {i}: {} {}",
                s.p1[i],
                want_p1[i]
            );
            assert!(
                (s.p2[i] - want_p2[i]).abs() < 1e-4,
                "P2 {i}: {} {}",
                s.p2[i],
                want_p2[i]
            );
        }
        assert!((s.q[14] - OPENCV_Q32).abs() < 1e-9);
        assert!((s.q[11] - 405.0).abs() < 1e-12);
        for i in 0..9 {
            assert!((s.r1[i] - OPENCV_R1[i]).abs() < 1e-9);
            assert!((s.r2[i] - OPENCV_R2[i]).abs() < 1e-9);
        }
    }

    const OPENCV_R1: [f64; 9] = [
        0.9968572160434206,
        -0.04411825186792299,
        -0.06579719351370097,
        0.04343269392860456,
        0.9989864988630563,
        -0.011814236642149069,
        0.06625173145107272,
        0.008919357681529141,
        0.9977630746516348,
    ];
    const OPENCV_R2: [f64; 9] = [
        0.9993062780989564,
        -0.03331020926996493,
        -0.01665510463498228,
        0.033481241738937094,
        0.9993883329877629,
        0.010097838360718201,
        0.0163085561479219,
        -0.010648466853565314,
        0.9998103025824642,
    ];
    const OPENCV_P1: [f64; 12] = [
        405.0,
        0.0,
        180.24484634399414,
        0.0,
        0.0,
        405.0,
        119.65785694122314,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
    ];
    const OPENCV_P2: [f64; 12] = [
        405.0,
        0.0,
        180.24484634399414,
        -48.633738289380965,
        0.0,
        405.0,
        119.65785694122314,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
    ];
    /// OpenCV's Q[3][2] for the rig.
    const OPENCV_Q32: f64 = 8.327552317491303;

    proptest! {
        #[test]
        fn rectified_correspondences_share_rows(
            x in -1.0f64..1.0, y in -0.8f64..0.8, z in 2.0f64..20.0,
            k1 in -0.3f64..0.1, zero in any::<bool>(),
        ) {
            let (r, t) = rig();
            let l1 = lens(k1);
            let l2 = lens(k1 * 0.8);
            let s = stereo_rectify(&l1, &l2, 320, 240, &r, t, zero).unwrap();
            let x1 = [x, y, z];
            let x2 = {
                let v = mat3_vec(&r, x1);
                [v[0] + t[0], v[1] + t[1], v[2] + t[2]]
            };
            let p1 = l1.project(x1).unwrap();
            let p2 = l2.project(x2).unwrap();
            prop_assume!(l1.undistort(l1.from_pixel(p1)).is_some());
            prop_assume!(l2.undistort(l2.from_pixel(p2)).is_some());
            let a = undistort_points(&l1, &[p1], Some(&s.r1), Some(&left3x3(&s.p1)))[0];
            let b = undistort_points(&l2, &[p2], Some(&s.r2), Some(&left3x3(&s.p2)))[0];
            prop_assert!((a[1] - b[1]).abs() < 1e-9, "{a:?} {b:?}");
            // Depth from disparity through Q.
            let d = a[0] - b[0];
            let w = s.q[14] * d + s.q[15];
            let depth = s.q[11] / w;
            let zr = mat3_vec(&s.r1, x1)[2];
            prop_assert!((depth - zr).abs() < 1e-6 * zr);
        }
    }
}
