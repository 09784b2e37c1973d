//! Runtime values that flow along edges. Heavy payloads sit behind `Arc`, so a value is shared
//! between all its consumers without copying.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::types::PortType;

/// Errors building a value from raw parts.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ValueError {
    /// The pixel buffer does not hold `width × height × channels` samples.
    #[error(
        "image buffer holds {actual} samples, but {width}×{height}×{channels} needs {expected}"
    )]
    ImageSize {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
        /// Channels per pixel.
        channels: usize,
        /// Samples expected.
        expected: usize,
        /// Samples present.
        actual: usize,
    },
    /// The matrix buffer does not hold `rows × cols` entries.
    #[error("matrix buffer holds {actual} entries, but {rows}×{cols} needs {}", rows * cols)]
    MatrixSize {
        /// Rows.
        rows: usize,
        /// Columns.
        cols: usize,
        /// Entries present.
        actual: usize,
    },
    /// Image dimensions overflow memory addressing.
    #[error("image dimensions {width}×{height}×{channels} overflow")]
    TooLarge {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
        /// Channels per pixel.
        channels: usize,
    },
}

/// Channel layout of an image, interleaved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Channels {
    /// One luminance channel.
    Gray,
    /// Red, green, blue.
    Rgb,
    /// Red, green, blue, alpha (straight, not premultiplied).
    Rgba,
}

impl Channels {
    /// Samples per pixel.
    pub fn count(self) -> usize {
        match self {
            Channels::Gray => 1,
            Channels::Rgb => 3,
            Channels::Rgba => 4,
        }
    }

    /// Lower-case name (`gray`, `rgb`, `rgba`).
    pub fn name(self) -> &'static str {
        match self {
            Channels::Gray => "gray",
            Channels::Rgb => "rgb",
            Channels::Rgba => "rgba",
        }
    }
}

/// Sample type of an image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Depth {
    /// 8-bit unsigned, 0..=255.
    U8,
    /// 16-bit unsigned, 0..=65535.
    U16,
    /// 32-bit float; by convention 0.0..=1.0 for display, but any finite value is allowed.
    F32,
}

impl Depth {
    /// Lower-case name (`u8`, `u16`, `f32`).
    pub fn name(self) -> &'static str {
        match self {
            Depth::U8 => "u8",
            Depth::U16 => "u16",
            Depth::F32 => "f32",
        }
    }

    /// Bytes per sample.
    pub fn bytes(self) -> usize {
        match self {
            Depth::U8 => 1,
            Depth::U16 => 2,
            Depth::F32 => 4,
        }
    }
}

/// Pixel format: channel layout × sample type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PixelFormat {
    /// Channel layout.
    pub channels: Channels,
    /// Sample type.
    pub depth: Depth,
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}_{}", self.channels.name(), self.depth.name())
    }
}

/// Interleaved samples of an image, row-major, no padding between rows.
#[derive(Debug, Clone, PartialEq)]
pub enum PixelData {
    /// 8-bit samples.
    U8(Vec<u8>),
    /// 16-bit samples.
    U16(Vec<u16>),
    /// 32-bit float samples.
    F32(Vec<f32>),
}

impl PixelData {
    /// Number of samples.
    pub fn len(&self) -> usize {
        match self {
            PixelData::U8(v) => v.len(),
            PixelData::U16(v) => v.len(),
            PixelData::F32(v) => v.len(),
        }
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The sample type.
    pub fn depth(&self) -> Depth {
        match self {
            PixelData::U8(_) => Depth::U8,
            PixelData::U16(_) => Depth::U16,
            PixelData::F32(_) => Depth::F32,
        }
    }
}

/// A raster image: `width × height` pixels of `channels`, interleaved, row-major, row stride
/// `width × channels` samples. Zero-sized images (0×N, N×0) are valid values.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    width: usize,
    height: usize,
    channels: Channels,
    data: PixelData,
}

impl Image {
    /// Builds an image, checking that `data` holds exactly `width × height × channels` samples.
    pub fn new(
        width: usize,
        height: usize,
        channels: Channels,
        data: PixelData,
    ) -> Result<Image, ValueError> {
        let expected = Self::sample_count(width, height, channels)?;
        if data.len() != expected {
            return Err(ValueError::ImageSize {
                width,
                height,
                channels: channels.count(),
                expected,
                actual: data.len(),
            });
        }
        Ok(Image {
            width,
            height,
            channels,
            data,
        })
    }

    /// Samples needed for the given size, or an overflow error.
    pub fn sample_count(
        width: usize,
        height: usize,
        channels: Channels,
    ) -> Result<usize, ValueError> {
        width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(channels.count()))
            .filter(|n| n.checked_mul(4).is_some())
            .ok_or(ValueError::TooLarge {
                width,
                height,
                channels: channels.count(),
            })
    }

    /// A zero-filled image of the given format.
    pub fn zeros(width: usize, height: usize, format: PixelFormat) -> Result<Image, ValueError> {
        let n = Self::sample_count(width, height, format.channels)?;
        let data = match format.depth {
            Depth::U8 => PixelData::U8(vec![0; n]),
            Depth::U16 => PixelData::U16(vec![0; n]),
            Depth::F32 => PixelData::F32(vec![0.0; n]),
        };
        Self::new(width, height, format.channels, data)
    }

    /// 8-bit image from samples.
    pub fn from_u8(
        width: usize,
        height: usize,
        channels: Channels,
        data: Vec<u8>,
    ) -> Result<Image, ValueError> {
        Self::new(width, height, channels, PixelData::U8(data))
    }

    /// 16-bit image from samples.
    pub fn from_u16(
        width: usize,
        height: usize,
        channels: Channels,
        data: Vec<u16>,
    ) -> Result<Image, ValueError> {
        Self::new(width, height, channels, PixelData::U16(data))
    }

    /// Float image from samples.
    pub fn from_f32(
        width: usize,
        height: usize,
        channels: Channels,
        data: Vec<f32>,
    ) -> Result<Image, ValueError> {
        Self::new(width, height, channels, PixelData::F32(data))
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Channel layout.
    pub fn channels(&self) -> Channels {
        self.channels
    }

    /// Sample type.
    pub fn depth(&self) -> Depth {
        self.data.depth()
    }

    /// Pixel format.
    pub fn format(&self) -> PixelFormat {
        PixelFormat {
            channels: self.channels,
            depth: self.depth(),
        }
    }

    /// The samples.
    pub fn data(&self) -> &PixelData {
        &self.data
    }

    /// Consumes the image, returning its samples.
    pub fn into_data(self) -> PixelData {
        self.data
    }

    /// Samples per row.
    pub fn row_stride(&self) -> usize {
        self.width * self.channels.count()
    }

    /// True for a zero-area image.
    pub fn is_empty(&self) -> bool {
        self.width == 0 || self.height == 0
    }

    /// 8-bit samples, if this is a u8 image.
    pub fn as_u8(&self) -> Option<&[u8]> {
        match &self.data {
            PixelData::U8(v) => Some(v),
            _ => None,
        }
    }

    /// 16-bit samples, if this is a u16 image.
    pub fn as_u16(&self) -> Option<&[u16]> {
        match &self.data {
            PixelData::U16(v) => Some(v),
            _ => None,
        }
    }

    /// Float samples, if this is an f32 image.
    pub fn as_f32(&self) -> Option<&[f32]> {
        match &self.data {
            PixelData::F32(v) => Some(v),
            _ => None,
        }
    }

    /// Bytes held by the samples.
    pub fn byte_size(&self) -> usize {
        self.data.len() * self.depth().bytes()
    }
}

/// An image keypoint, OpenCV's `KeyPoint` fields.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Keypoint {
    /// Column, pixels (0 = centre of the left-most pixel).
    pub x: f32,
    /// Row, pixels.
    pub y: f32,
    /// Diameter of the meaningful neighbourhood, pixels.
    pub size: f32,
    /// Orientation in degrees, 0..360, or -1 if not computed.
    pub angle: f32,
    /// Detector response (larger is stronger).
    pub response: f32,
    /// Pyramid octave the keypoint was found in.
    pub octave: i32,
}

/// Feature descriptors, one row per keypoint.
#[derive(Debug, Clone, PartialEq)]
pub enum Descriptors {
    /// Float descriptors (SIFT-like), `dim` floats per row.
    Float {
        /// Floats per descriptor.
        dim: usize,
        /// Row-major rows.
        data: Vec<f32>,
    },
    /// Binary descriptors (ORB-like), `bytes` bytes per row, compared by Hamming distance.
    Binary {
        /// Bytes per descriptor.
        bytes: usize,
        /// Row-major rows.
        data: Vec<u8>,
    },
}

impl Descriptors {
    /// Number of descriptors.
    pub fn len(&self) -> usize {
        match self {
            Descriptors::Float { dim, data } => data.len().checked_div(*dim).unwrap_or(0),
            Descriptors::Binary { bytes, data } => data.len().checked_div(*bytes).unwrap_or(0),
        }
    }

    /// True when there are no descriptors.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A correspondence between descriptor `query` of the first set and `train` of the second.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Match {
    /// Index into the first (query) set.
    pub query: u32,
    /// Index into the second (train) set.
    pub train: u32,
    /// Descriptor distance (L2 or Hamming).
    pub distance: f32,
}

/// A dense row-major matrix of f64.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Matrix {
    /// Number of rows.
    pub rows: usize,
    /// Number of columns.
    pub cols: usize,
    /// Row-major entries, `rows × cols` of them.
    pub data: Vec<f64>,
}

impl Matrix {
    /// Builds a matrix, checking the buffer size.
    pub fn new(rows: usize, cols: usize, data: Vec<f64>) -> Result<Matrix, ValueError> {
        if rows.checked_mul(cols) != Some(data.len()) {
            return Err(ValueError::MatrixSize {
                rows,
                cols,
                actual: data.len(),
            });
        }
        Ok(Matrix { rows, cols, data })
    }

    /// Entry at (row, col), if in range.
    pub fn get(&self, row: usize, col: usize) -> Option<f64> {
        if row < self.rows && col < self.cols {
            self.data.get(row * self.cols + col).copied()
        } else {
            None
        }
    }
}

/// Camera projection models. The COLMAP ones keep COLMAP's parameter orders; the last two carry
/// a full pinhole matrix with skew and OpenCV's distortion models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum CameraModel {
    /// `f, cx, cy`.
    SimplePinhole,
    /// `fx, fy, cx, cy`.
    Pinhole,
    /// `f, cx, cy, k`.
    SimpleRadial,
    /// `f, cx, cy, k1, k2`.
    Radial,
    /// `fx, fy, cx, cy, k1, k2, p1, p2` (OpenCV's first four distortion terms).
    OpenCv,
    /// `fx, fy, cx, cy, skew, k1, k2, p1, p2, k3`: pinhole `K = [[fx, skew, cx], [0, fy, cy],
    /// [0, 0, 1]]` and Brown–Conrady radial–tangential distortion in OpenCV's order and formulas
    /// (`cv::projectPoints` with 5 coefficients). COLMAP export: `FULL_OPENCV` (no skew there).
    RadialTangential,
    /// `fx, fy, cx, cy, skew, k1, k2, k3, k4`: pinhole K with skew and Kannala–Brandt equidistant
    /// distortion `θd = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸)` (OpenCV's `cv::fisheye`). COLMAP export:
    /// `OPENCV_FISHEYE` (no skew there).
    Fisheye,
}

impl CameraModel {
    /// COLMAP's model name (`PINHOLE`, `OPENCV`, ...). [`CameraModel::RadialTangential`] is
    /// `FULL_OPENCV` and [`CameraModel::Fisheye`] `OPENCV_FISHEYE`.
    pub fn colmap_name(self) -> &'static str {
        match self {
            CameraModel::SimplePinhole => "SIMPLE_PINHOLE",
            CameraModel::Pinhole => "PINHOLE",
            CameraModel::SimpleRadial => "SIMPLE_RADIAL",
            CameraModel::Radial => "RADIAL",
            CameraModel::OpenCv => "OPENCV",
            CameraModel::RadialTangential => "FULL_OPENCV",
            CameraModel::Fisheye => "OPENCV_FISHEYE",
        }
    }

    /// Number of parameters the model takes.
    pub fn param_count(self) -> usize {
        match self {
            CameraModel::SimplePinhole => 3,
            CameraModel::Pinhole => 4,
            CameraModel::SimpleRadial => 4,
            CameraModel::Radial => 5,
            CameraModel::OpenCv => 8,
            CameraModel::RadialTangential => 10,
            CameraModel::Fisheye => 9,
        }
    }
}

/// Lens distortion of a camera, in OpenCV's conventions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Distortion {
    /// An ideal pinhole.
    None,
    /// Brown–Conrady `[k1, k2, p1, p2, k3]` (OpenCV's first five coefficients).
    RadialTangential([f64; 5]),
    /// Kannala–Brandt equidistant `[k1, k2, k3, k4]` (OpenCV's `cv::fisheye`).
    Fisheye([f64; 4]),
}

/// Pinhole intrinsics: `K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`, pixels (pixel centres
/// at integers).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Skew (K\[0\]\[1\]), pixels; 0 for square pixel grids.
    pub skew: f64,
}

/// Camera intrinsics: model, image size and parameters in the model's order.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Camera {
    /// Projection model.
    pub model: CameraModel,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Parameters, `model.param_count()` of them.
    pub params: Vec<f64>,
}

impl Camera {
    /// A [`CameraModel::RadialTangential`] camera, or [`CameraModel::Fisheye`] for fisheye
    /// distortion; no distortion gives the radial–tangential model with zero coefficients.
    pub fn from_parts(width: u32, height: u32, k: Intrinsics, distortion: Distortion) -> Camera {
        let base = [k.fx, k.fy, k.cx, k.cy, k.skew];
        let (model, extra): (CameraModel, Vec<f64>) = match distortion {
            Distortion::None => (CameraModel::RadialTangential, vec![0.0; 5]),
            Distortion::RadialTangential(d) => (CameraModel::RadialTangential, d.to_vec()),
            Distortion::Fisheye(d) => (CameraModel::Fisheye, d.to_vec()),
        };
        let mut params = base.to_vec();
        params.extend(extra);
        Camera {
            model,
            width,
            height,
            params,
        }
    }

    fn param(&self, i: usize) -> f64 {
        self.params.get(i).copied().unwrap_or(0.0)
    }

    /// The pinhole matrix's entries (missing parameters read as 0).
    pub fn intrinsics(&self) -> Intrinsics {
        let p = |i| self.param(i);
        let (fx, fy, cx, cy, skew) = match self.model {
            CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial => {
                (p(0), p(0), p(1), p(2), 0.0)
            }
            CameraModel::Pinhole | CameraModel::OpenCv => (p(0), p(1), p(2), p(3), 0.0),
            CameraModel::RadialTangential | CameraModel::Fisheye => (p(0), p(1), p(2), p(3), p(4)),
        };
        Intrinsics {
            fx,
            fy,
            cx,
            cy,
            skew,
        }
    }

    /// The lens distortion (COLMAP's radial models map `k` to `k1`, `k2` with no tangential
    /// terms).
    pub fn distortion(&self) -> Distortion {
        let p = |i| self.param(i);
        match self.model {
            CameraModel::SimplePinhole | CameraModel::Pinhole => Distortion::None,
            CameraModel::SimpleRadial => Distortion::RadialTangential([p(3), 0.0, 0.0, 0.0, 0.0]),
            CameraModel::Radial => Distortion::RadialTangential([p(3), p(4), 0.0, 0.0, 0.0]),
            CameraModel::OpenCv => Distortion::RadialTangential([p(4), p(5), p(6), p(7), 0.0]),
            CameraModel::RadialTangential => {
                Distortion::RadialTangential([p(5), p(6), p(7), p(8), p(9)])
            }
            CameraModel::Fisheye => Distortion::Fisheye([p(5), p(6), p(7), p(8)]),
        }
    }

    /// Parameters in COLMAP's order for [`CameraModel::colmap_name`]. COLMAP has no skew: the
    /// skew of [`CameraModel::RadialTangential`] and [`CameraModel::Fisheye`] is dropped (exact
    /// only when it is 0); `FULL_OPENCV`'s `k4, k5, k6` are written as 0.
    pub fn colmap_params(&self) -> Vec<f64> {
        let k = self.intrinsics();
        match (self.model, self.distortion()) {
            (CameraModel::RadialTangential, Distortion::RadialTangential(d)) => {
                let mut v = vec![k.fx, k.fy, k.cx, k.cy];
                v.extend(d[..4].iter().copied());
                v.extend([d[4], 0.0, 0.0, 0.0]);
                v
            }
            (CameraModel::Fisheye, Distortion::Fisheye(d)) => {
                let mut v = vec![k.fx, k.fy, k.cx, k.cy];
                v.extend(d);
                v
            }
            _ => self.params.clone(),
        }
    }
}

/// A rigid transform `x_to = R · x_from + t`. Its name at the use site says which frames it maps
/// (e.g. `camera_from_world`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    /// Unit quaternion `[w, x, y, z]`.
    pub rotation: [f64; 4],
    /// Translation.
    pub translation: [f64; 3],
}

impl Pose {
    /// The identity transform.
    pub const IDENTITY: Pose = Pose {
        rotation: [1.0, 0.0, 0.0, 0.0],
        translation: [0.0, 0.0, 0.0],
    };

    /// The rotation as a 3×3 row-major matrix (the quaternion is normalized first; a zero
    /// quaternion gives the identity).
    pub fn rotation_matrix(&self) -> [f64; 9] {
        let [w, x, y, z] = self.rotation;
        let n = (w * w + x * x + y * y + z * z).sqrt();
        if n == 0.0 || !n.is_finite() {
            return [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        }
        let (w, x, y, z) = (w / n, x / n, y / n, z / n);
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ]
    }

    /// A pose from a row-major rotation matrix (assumed orthonormal, det +1) and a translation;
    /// the quaternion has `w ≥ 0` (Shepperd's method, stable for every rotation).
    pub fn from_rotation_matrix(r: &[f64; 9], translation: [f64; 3]) -> Pose {
        let tr = r[0] + r[4] + r[8];
        let q = if tr > 0.0 {
            let s = (tr + 1.0).sqrt() * 2.0;
            [
                s / 4.0,
                (r[7] - r[5]) / s,
                (r[2] - r[6]) / s,
                (r[3] - r[1]) / s,
            ]
        } else if r[0] > r[4] && r[0] > r[8] {
            let s = (1.0 + r[0] - r[4] - r[8]).sqrt() * 2.0;
            [
                (r[7] - r[5]) / s,
                s / 4.0,
                (r[1] + r[3]) / s,
                (r[2] + r[6]) / s,
            ]
        } else if r[4] > r[8] {
            let s = (1.0 + r[4] - r[0] - r[8]).sqrt() * 2.0;
            [
                (r[2] - r[6]) / s,
                (r[1] + r[3]) / s,
                s / 4.0,
                (r[5] + r[7]) / s,
            ]
        } else {
            let s = (1.0 + r[8] - r[0] - r[4]).sqrt() * 2.0;
            [
                (r[3] - r[1]) / s,
                (r[2] + r[6]) / s,
                (r[5] + r[7]) / s,
                s / 4.0,
            ]
        };
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
        let rotation = if n > 0.0 && n.is_finite() {
            q.map(|v| sign * v / n)
        } else {
            [1.0, 0.0, 0.0, 0.0]
        };
        Pose {
            rotation,
            translation,
        }
    }
}

/// 3-D points with optional per-point colors and normals.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct PointCloud {
    /// Positions.
    pub positions: Vec<[f32; 3]>,
    /// sRGB colors, one per point, if present.
    pub colors: Option<Vec<[u8; 3]>>,
    /// Unit normals, one per point, if present.
    pub normals: Option<Vec<[f32; 3]>>,
}

/// One observation in a track: keypoint `keypoint` of image `image`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct TrackElement {
    /// Image index.
    pub image: u32,
    /// Keypoint index in that image.
    pub keypoint: u32,
}

/// Feature tracks: each is the set of observations of one scene point.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Tracks {
    /// The tracks.
    pub tracks: Vec<Vec<TrackElement>>,
}

/// A posed image of a reconstruction.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReconImage {
    /// Image id (COLMAP `IMAGE_ID`).
    pub id: u32,
    /// Camera id (COLMAP `CAMERA_ID`).
    pub camera_id: u32,
    /// Image name.
    pub name: String,
    /// World-to-camera transform.
    pub camera_from_world: Pose,
    /// 2-D observations: position and the id of the 3-D point it sees, if any.
    pub points2d: Vec<([f64; 2], Option<u64>)>,
}

/// A triangulated 3-D point of a reconstruction.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReconPoint {
    /// Point id (COLMAP `POINT3D_ID`).
    pub id: u64,
    /// Position in world coordinates.
    pub position: [f64; 3],
    /// sRGB color.
    pub color: [u8; 3],
    /// Mean reprojection error, pixels.
    pub error_px: f64,
    /// Observations: (image id, index into that image's `points2d`).
    pub track: Vec<(u32, u32)>,
}

/// A sparse reconstruction, COLMAP's model.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Reconstruction {
    /// Cameras by id.
    pub cameras: BTreeMap<u32, Camera>,
    /// Posed images.
    pub images: Vec<ReconImage>,
    /// 3-D points.
    pub points: Vec<ReconPoint>,
}

/// An indexed triangle mesh.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Triangles as counter-clockwise vertex index triples.
    pub triangles: Vec<[u32; 3]>,
    /// Per-vertex unit normals, if present.
    pub normals: Option<Vec<[f32; 3]>>,
    /// Per-vertex texture coordinates, if present.
    pub uvs: Option<Vec<[f32; 2]>>,
    /// Per-vertex linear RGB colors, if present.
    pub colors: Option<Vec<[f32; 3]>>,
    /// Per-vertex tangents, if present: `xyz` a unit tangent orthogonal to the normal (along
    /// increasing `u`), `w` = ±1 the handedness, so that the bitangent is `w · (n × t)` (the
    /// MikkTSpace / glTF convention). Left out of JSON when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tangents: Option<Vec<[f32; 4]>>,
}

/// One node of a [`Bvh`]: an axis-aligned box and either two children or a run of triangles
/// (32 bytes).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct BvhNode {
    /// Box corner with the smallest coordinates.
    pub min: [f32; 3],
    /// Inner node: index of its first child; the second child is the node after it (siblings
    /// are adjacent). Leaf: index of its first triangle in [`Bvh::primitives`].
    pub offset: u32,
    /// Box corner with the largest coordinates.
    pub max: [f32; 3],
    /// Triangles of a leaf; 0 for an inner node.
    pub count: u32,
}

impl BvhNode {
    /// Whether the node is a leaf.
    pub fn is_leaf(&self) -> bool {
        self.count > 0
    }
}

/// A bounding-volume hierarchy over a mesh's triangles: the root at 0, then the children of
/// each inner node as an adjacent pair (an empty mesh has no nodes).
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Bvh {
    /// Nodes, root at 0, siblings adjacent.
    pub nodes: Vec<BvhNode>,
    /// Triangle indices into `mesh.triangles`, in leaf order.
    pub primitives: Vec<u32>,
    /// The three corners of `primitives[i]`, in leaf order (intersection reads these without
    /// indirection).
    pub corners: Vec<[[f32; 3]; 3]>,
    /// The mesh it was built over.
    pub mesh: Arc<Mesh>,
}

/// Shape of a [`Bvh`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BvhStats {
    /// Nodes.
    pub nodes: usize,
    /// Leaves.
    pub leaves: usize,
    /// Longest root-to-leaf path in edges (0 for a lone leaf).
    pub max_depth: usize,
    /// Most triangles in one leaf.
    pub max_leaf_size: usize,
}

impl Bvh {
    /// Node, leaf and depth counts (iterative walk; a malformed tree stops at the first bad
    /// index instead of panicking).
    pub fn stats(&self) -> BvhStats {
        let mut stats = BvhStats {
            nodes: self.nodes.len(),
            ..BvhStats::default()
        };
        if self.nodes.is_empty() {
            return stats;
        }
        let mut stack = vec![(0usize, 0usize)];
        let mut visited = 0usize;
        while let Some((i, depth)) = stack.pop() {
            let Some(node) = self.nodes.get(i) else {
                break;
            };
            visited += 1;
            if visited > self.nodes.len() {
                break;
            }
            stats.max_depth = stats.max_depth.max(depth);
            if node.is_leaf() {
                stats.leaves += 1;
                stats.max_leaf_size = stats.max_leaf_size.max(node.count as usize);
            } else {
                stack.push((node.offset as usize + 1, depth + 1));
                stack.push((node.offset as usize, depth + 1));
            }
        }
        stats
    }
}

/// How texture coordinates outside `[0, 1]` are mapped (the OpenGL/Vulkan sampler address modes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TextureWrap {
    /// Tile: `u − floor(u)`.
    #[default]
    Repeat,
    /// Tile, mirroring every other copy.
    MirroredRepeat,
    /// Clamp to the outermost texel centres.
    ClampToEdge,
    /// Outside `[0, 1]` read the texture's border colour.
    ClampToBorder,
}

/// How a texture is filtered when sampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TextureFilter {
    /// The texel whose footprint holds the sample point.
    Nearest,
    /// Bilinear interpolation of the four nearest texels (level 0 only).
    Bilinear,
    /// Trilinear: bilinear in the two mip levels around the pixel footprint, blended
    /// (Williams 1983).
    #[default]
    Trilinear,
    /// Anisotropic: several trilinear probes along the footprint's major axis, up to
    /// [`Texture::max_anisotropy`] of them.
    Anisotropic,
}

/// An image bound to a sampler: how a material reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    /// Texels; gray, RGB or RGBA, u8 (read as `v / 255`), u16 (`v / 65535`) or f32. Colour
    /// textures hold linear values (no sRGB decoding is applied).
    pub image: Arc<Image>,
    /// Address mode for coordinates outside `[0, 1]`.
    pub wrap: TextureWrap,
    /// Filter.
    pub filter: TextureFilter,
    /// Colour read outside `[0, 1]` with [`TextureWrap::ClampToBorder`], RGBA.
    pub border: [f32; 4],
    /// Most probes along the footprint for [`TextureFilter::Anisotropic`] (1–16).
    pub max_anisotropy: u32,
    /// Texture coordinates are multiplied by this before sampling (tiling).
    pub uv_scale: [f32; 2],
}

/// Surface appearance. One parameter set serves both renderers: the rasterizer shades with
/// [`Material::shading`]; the path tracer reads the physical parameters (Lambertian base,
/// GGX specular lobe by `roughness`/`metalness`, dielectric by `transmission`/`ior`).
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    /// Name, for diagnostics.
    pub name: String,
    /// Base colour (diffuse albedo; specular colour of metals), linear RGB in `[0, 1]`.
    pub albedo: [f32; 3],
    /// Multiplies `albedo` (RGB; a gray texture scales all three).
    pub albedo_texture: Option<Texture>,
    /// Tangent-space normal map (RGB, `n = 2·rgb − 1`, +z out of the surface).
    pub normal_texture: Option<Texture>,
    /// GGX roughness `α = roughness²`, in `[0, 1]`.
    pub roughness: f32,
    /// Multiplies `roughness` (first channel).
    pub roughness_texture: Option<Texture>,
    /// Metalness in `[0, 1]`: 0 dielectric, 1 metal.
    pub metalness: f32,
    /// Multiplies `metalness` (first channel).
    pub metalness_texture: Option<Texture>,
    /// Emitted radiance, linear RGB, W·sr⁻¹·m⁻² per unit.
    pub emission: [f32; 3],
    /// Multiplies `emission` (RGB).
    pub emission_texture: Option<Texture>,
    /// Specular weight of the Phong and Blinn–Phong models.
    pub specular: f32,
    /// Specular exponent of the Phong and Blinn–Phong models.
    pub shininess: f32,
    /// 0 opaque; 1 a clear dielectric that refracts (path tracer, Whitted).
    pub transmission: f32,
    /// Index of refraction of a transmissive material (glass ≈ 1.5).
    pub ior: f32,
    /// Coverage for alpha blending in the rasterizer, `[0, 1]` (1 opaque).
    pub opacity: f32,
    /// Rasterizer shading model.
    pub shading: Shading,
}

impl Default for Material {
    fn default() -> Self {
        Material {
            name: String::new(),
            albedo: [0.8, 0.8, 0.8],
            albedo_texture: None,
            normal_texture: None,
            roughness: 0.5,
            roughness_texture: None,
            metalness: 0.0,
            metalness_texture: None,
            emission: [0.0; 3],
            emission_texture: None,
            specular: 0.0,
            shininess: 32.0,
            transmission: 0.0,
            ior: 1.5,
            opacity: 1.0,
            shading: Shading::Lambert,
        }
    }
}

impl Material {
    /// The material's textures, in field order.
    pub fn textures(&self) -> impl Iterator<Item = &Texture> {
        [
            &self.albedo_texture,
            &self.normal_texture,
            &self.roughness_texture,
            &self.metalness_texture,
            &self.emission_texture,
        ]
        .into_iter()
        .flatten()
    }
}

/// Rasterizer shading models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Shading {
    /// Albedo only, no lighting.
    Unlit,
    /// One normal per triangle (the geometric normal), Lambert + Blinn–Phong specular.
    Flat,
    /// Lighting evaluated at the vertices and interpolated (Gouraud 1971).
    Gouraud,
    /// Lambertian diffuse with interpolated normals.
    #[default]
    Lambert,
    /// Phong's reflection model with interpolated normals (Phong 1975).
    Phong,
    /// Blinn–Phong (half-vector) model with interpolated normals (Blinn 1977).
    BlinnPhong,
    /// Metallic–roughness PBR: Lambert + GGX/Smith/Schlick (Walter et al. 2007; Karis 2013).
    Pbr,
}

/// Geometry of a scene object, in object coordinates.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Shape {
    /// A triangle mesh.
    Mesh(Arc<Mesh>),
    /// A sphere; texture coordinates are longitude/latitude in `[0, 1]`.
    Sphere {
        /// Centre.
        center: [f64; 3],
        /// Radius (> 0).
        radius: f64,
    },
    /// A square piece of a plane (infinite when `half_extent` is +∞); texture coordinates are
    /// the in-plane coordinates in world units.
    Plane {
        /// A point on the plane, the square's centre.
        point: [f64; 3],
        /// Normal (the front side).
        normal: [f64; 3],
        /// Half the square's side.
        half_extent: f64,
    },
    /// The implicit quadric `xᵀ Q x = 0` with `Q` symmetric 4×4 given by its upper triangle
    /// `[q00, q01, q02, q03, q11, q12, q13, q22, q23, q33]` on homogeneous `(x, y, z, 1)`,
    /// clipped to the box `min`–`max` (ellipsoids, cylinders, cones, paraboloids, hyperboloids).
    Quadric {
        /// Upper triangle of `Q`, row by row.
        coefficients: [f64; 10],
        /// Clip box, smallest corner.
        min: [f64; 3],
        /// Clip box, largest corner.
        max: [f64; 3],
    },
}

/// An object placed in a scene.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneObject {
    /// Object name.
    pub name: String,
    /// Geometry.
    pub shape: Shape,
    /// Object-to-world rigid transform, applied after `scale`.
    pub world_from_object: Pose,
    /// Uniform scale applied in object coordinates (> 0).
    pub scale: f64,
    /// Index into [`Scene::materials`].
    pub material: u32,
}

/// A light source.
#[derive(Debug, Clone, PartialEq)]
pub enum Light {
    /// A point light at `position` with radiant intensity `intensity` (W·sr⁻¹, linear RGB).
    Point {
        /// Position in world coordinates.
        position: [f64; 3],
        /// Intensity per channel.
        intensity: [f32; 3],
    },
    /// A directional light travelling along `direction`.
    Directional {
        /// Direction of travel (unit).
        direction: [f64; 3],
        /// Irradiance per channel on a surface facing the light (W·m⁻²).
        irradiance: [f32; 3],
    },
    /// A parallelogram emitter `corner + s·edge_u + t·edge_v`, `s, t ∈ [0, 1]`, radiating
    /// `radiance` from the side `edge_u × edge_v` points to.
    Area {
        /// One corner.
        corner: [f64; 3],
        /// First edge.
        edge_u: [f64; 3],
        /// Second edge.
        edge_v: [f64; 3],
        /// Emitted radiance (W·sr⁻¹·m⁻²).
        radiance: [f32; 3],
    },
    /// Light arriving from infinitely far away in every direction: `radiance`, times the
    /// equirectangular `map` when given (u = longitude about +y, v = polar angle from +y).
    Environment {
        /// Constant radiance (W·sr⁻¹·m⁻²).
        radiance: [f32; 3],
        /// Optional latitude–longitude map.
        map: Option<Texture>,
    },
}

/// A viewing camera: intrinsics, pose, and a thin lens.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneCamera {
    /// Intrinsics and image size (x right, y down, z forward).
    pub camera: Camera,
    /// World-to-camera transform.
    pub camera_from_world: Pose,
    /// Lens aperture radius in world units; 0 is a pinhole.
    pub aperture_radius: f64,
    /// Distance along the optical axis that is in focus (world units; used when
    /// `aperture_radius > 0`).
    pub focus_distance: f64,
}

/// A renderable scene: materials, objects, lights and viewing cameras.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scene {
    /// Materials, referenced by index from [`SceneObject::material`].
    pub materials: Vec<Material>,
    /// Objects.
    pub objects: Vec<SceneObject>,
    /// Lights.
    pub lights: Vec<Light>,
    /// Cameras.
    pub cameras: Vec<SceneCamera>,
}

impl Scene {
    /// Vertices and triangles over the scene's mesh objects.
    pub fn mesh_counts(&self) -> (usize, usize) {
        self.objects
            .iter()
            .filter_map(|o| match &o.shape {
                Shape::Mesh(m) => Some((m.positions.len(), m.triangles.len())),
                _ => None,
            })
            .fold((0, 0), |(v, t), (a, b)| (v + a, t + b))
    }
}

/// One animated property: keyframe times and values (`values.len() == times.len() × width`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AnimationChannel {
    /// What is animated, e.g. `joint3.rotation`.
    pub target: String,
    /// Keyframe times, seconds, increasing.
    pub times: Vec<f64>,
    /// Numbers per keyframe (3 for translation, 4 for a quaternion).
    pub width: usize,
    /// Keyframe values, `width` per time.
    pub values: Vec<f64>,
}

/// Animation channels with a shared duration.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Animation {
    /// Duration, seconds.
    pub duration: f64,
    /// Channels.
    pub channels: Vec<AnimationChannel>,
}

/// Named numbers, ordered by name.
pub type Metrics = BTreeMap<String, f64>;

/// A list of values of one element type.
#[derive(Debug, Clone, PartialEq)]
pub struct ValueList {
    /// Element type (known even for an empty list).
    pub element: PortType,
    /// Elements.
    pub items: Vec<Value>,
}

/// A value on an edge.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// See [`Image`].
    Image(Arc<Image>),
    /// See [`Keypoint`].
    Keypoints(Arc<Vec<Keypoint>>),
    /// See [`Descriptors`].
    Descriptors(Arc<Descriptors>),
    /// See [`Match`].
    Matches(Arc<Vec<Match>>),
    /// See [`Matrix`].
    Matrix(Arc<Matrix>),
    /// See [`Camera`].
    Camera(Arc<Camera>),
    /// See [`Pose`].
    Pose(Pose),
    /// 2-D points, pixels.
    Points2D(Arc<Vec<[f64; 2]>>),
    /// See [`PointCloud`].
    PointCloud(Arc<PointCloud>),
    /// See [`Tracks`].
    Tracks(Arc<Tracks>),
    /// See [`Reconstruction`].
    Reconstruction(Arc<Reconstruction>),
    /// See [`Mesh`].
    Mesh(Arc<Mesh>),
    /// See [`Scene`].
    Scene(Arc<Scene>),
    /// See [`Animation`].
    Animation(Arc<Animation>),
    /// A real number.
    Scalar(f64),
    /// An integer.
    Integer(i64),
    /// A boolean.
    Bool(bool),
    /// Text.
    Text(Arc<str>),
    /// See [`Metrics`].
    Metrics(Arc<Metrics>),
    /// See [`Bvh`].
    Bvh(Arc<Bvh>),
    /// See [`ValueList`].
    List(Arc<ValueList>),
}

/// The index of the first entry of `items` with a non-finite component.
fn first_bad<T>(items: &[T], finite: impl Fn(&T) -> bool) -> Option<usize> {
    items.iter().position(|x| !finite(x))
}

fn all_finite<const N: usize, F: Into<f64> + Copy>(v: &[F; N]) -> bool {
    v.iter().all(|&x| x.into().is_finite())
}

impl Value {
    /// Where a geometric value holds a NaN or an infinity, described for an error message
    /// (`"point 17"`, `"element 2: camera 1's parameters"`), or `None` when it is finite or not
    /// geometric. Geometric values are keypoints, matches, cameras, poses, 2-D points, point
    /// clouds (positions, normals), reconstructions (cameras, poses, 2-D and 3-D points) and
    /// meshes (positions, normals, uvs, tangents), and lists of them. Images, matrices, scalars
    /// and metrics are not: depth maps use +inf for "no surface", a matrix of measurements
    /// marks a missing row with NaN (`video.kalman_filter`), and a PSNR of identical images is
    /// +inf.
    pub fn non_finite_at(&self) -> Option<String> {
        let at = |what: &str, i: Option<usize>| i.map(|i| format!("{what} {i}"));
        match self {
            Value::Keypoints(k) => at(
                "keypoint",
                first_bad(k, |k| {
                    [k.x, k.y, k.size, k.angle, k.response]
                        .iter()
                        .all(|v| v.is_finite())
                }),
            ),
            Value::Matches(m) => at("match", first_bad(m, |m| m.distance.is_finite())),
            Value::Camera(c) => {
                first_bad(&c.params, |x| x.is_finite()).map(|i| format!("camera parameter {i}"))
            }
            Value::Pose(p) => (!(all_finite(&p.rotation) && all_finite(&p.translation)))
                .then(|| "the pose".to_string()),
            Value::Points2D(p) => at("point", first_bad(p, all_finite)),
            Value::PointCloud(c) => {
                at("point", first_bad(&c.positions, all_finite)).or_else(|| {
                    c.normals
                        .as_ref()
                        .and_then(|n| at("normal", first_bad(n, all_finite)))
                })
            }
            Value::Reconstruction(r) => {
                for (id, camera) in &r.cameras {
                    if camera.params.iter().any(|x| !x.is_finite()) {
                        return Some(format!("camera {id}'s parameters"));
                    }
                }
                for image in &r.images {
                    let pose = &image.camera_from_world;
                    if !(all_finite(&pose.rotation) && all_finite(&pose.translation)) {
                        return Some(format!("image {}'s pose", image.id));
                    }
                    if let Some(i) = first_bad(&image.points2d, |(p, _)| all_finite(p)) {
                        return Some(format!("image {}'s 2-D point {i}", image.id));
                    }
                }
                first_bad(&r.points, |p| all_finite(&p.position))
                    .map(|i| format!("3-D point {}", r.points[i].id))
            }
            Value::Mesh(m) => at("vertex", first_bad(&m.positions, all_finite))
                .or_else(|| {
                    m.normals
                        .as_ref()
                        .and_then(|n| at("normal", first_bad(n, all_finite)))
                })
                .or_else(|| {
                    m.uvs
                        .as_ref()
                        .and_then(|n| at("uv", first_bad(n, all_finite)))
                })
                .or_else(|| {
                    m.tangents
                        .as_ref()
                        .and_then(|n| at("tangent", first_bad(n, all_finite)))
                }),
            Value::List(list) => list
                .items
                .iter()
                .enumerate()
                .find_map(|(k, item)| item.non_finite_at().map(|w| format!("element {k}: {w}"))),
            _ => None,
        }
    }

    /// Wraps an image.
    pub fn image(image: Image) -> Value {
        Value::Image(Arc::new(image))
    }

    /// Wraps metrics.
    pub fn metrics(metrics: Metrics) -> Value {
        Value::Metrics(Arc::new(metrics))
    }

    /// Wraps a list of values of type `element`.
    pub fn list(element: PortType, items: Vec<Value>) -> Value {
        Value::List(Arc::new(ValueList { element, items }))
    }

    /// The port type of this value.
    pub fn port_type(&self) -> PortType {
        match self {
            Value::Image(_) => PortType::Image,
            Value::Keypoints(_) => PortType::Keypoints,
            Value::Descriptors(_) => PortType::Descriptors,
            Value::Matches(_) => PortType::Matches,
            Value::Matrix(_) => PortType::Matrix,
            Value::Camera(_) => PortType::Camera,
            Value::Pose(_) => PortType::Pose,
            Value::Points2D(_) => PortType::Points2D,
            Value::PointCloud(_) => PortType::PointCloud,
            Value::Tracks(_) => PortType::Tracks,
            Value::Reconstruction(_) => PortType::Reconstruction,
            Value::Mesh(_) => PortType::Mesh,
            Value::Bvh(_) => PortType::Bvh,
            Value::Scene(_) => PortType::Scene,
            Value::Animation(_) => PortType::Animation,
            Value::Scalar(_) => PortType::Scalar,
            Value::Integer(_) => PortType::Integer,
            Value::Bool(_) => PortType::Bool,
            Value::Text(_) => PortType::Text,
            Value::Metrics(_) => PortType::Metrics,
            Value::List(list) => list.element.clone().list_of(),
        }
    }

    /// Approximate heap bytes held by this value (for peak-memory accounting). Shared payloads are
    /// counted once per value, so callers count each produced value once.
    pub fn byte_size(&self) -> usize {
        const F32X3: usize = 12;
        match self {
            Value::Image(i) => i.byte_size(),
            Value::Keypoints(k) => k.len() * std::mem::size_of::<Keypoint>(),
            Value::Descriptors(d) => match d.as_ref() {
                Descriptors::Float { data, .. } => data.len() * 4,
                Descriptors::Binary { data, .. } => data.len(),
            },
            Value::Matches(m) => m.len() * std::mem::size_of::<Match>(),
            Value::Matrix(m) => m.data.len() * 8,
            Value::Camera(c) => c.params.len() * 8,
            Value::Points2D(p) => p.len() * 16,
            Value::PointCloud(p) => {
                p.positions.len() * F32X3
                    + p.colors.as_ref().map_or(0, |c| c.len() * 3)
                    + p.normals.as_ref().map_or(0, |n| n.len() * F32X3)
            }
            Value::Tracks(t) => t.tracks.iter().map(|t| t.len() * 8 + 24).sum(),
            Value::Reconstruction(r) => {
                r.images
                    .iter()
                    .map(|i| i.points2d.len() * 32 + i.name.len())
                    .sum::<usize>()
                    + r.points
                        .iter()
                        .map(|p| 64 + p.track.len() * 8)
                        .sum::<usize>()
            }
            Value::Mesh(m) => mesh_bytes(m),
            Value::Bvh(b) => {
                b.nodes.len() * 32
                    + b.primitives.len() * 4
                    + b.corners.len() * 36
                    + mesh_bytes(&b.mesh)
            }
            Value::Scene(s) => {
                let shapes: usize = s
                    .objects
                    .iter()
                    .map(|o| match &o.shape {
                        Shape::Mesh(m) => mesh_bytes(m),
                        _ => 128,
                    })
                    .sum();
                let textures: usize = s
                    .materials
                    .iter()
                    .flat_map(Material::textures)
                    .chain(s.lights.iter().filter_map(|l| match l {
                        Light::Environment { map, .. } => map.as_ref(),
                        _ => None,
                    }))
                    .map(|t| t.image.byte_size())
                    .sum();
                shapes + textures
            }
            Value::Animation(a) => a
                .channels
                .iter()
                .map(|c| (c.times.len() + c.values.len()) * 8)
                .sum(),
            Value::Text(t) => t.len(),
            Value::Metrics(m) => m.keys().map(|k| k.len() + 8).sum(),
            Value::List(l) => l.items.iter().map(Value::byte_size).sum(),
            Value::Pose(_) | Value::Scalar(_) | Value::Integer(_) | Value::Bool(_) => 0,
        }
    }
}

fn mesh_bytes(m: &Mesh) -> usize {
    m.positions.len() * 12
        + m.triangles.len() * 12
        + m.normals.as_ref().map_or(0, |n| n.len() * 12)
        + m.uvs.as_ref().map_or(0, |n| n.len() * 8)
        + m.colors.as_ref().map_or(0, |n| n.len() * 12)
        + m.tangents.as_ref().map_or(0, |n| n.len() * 16)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_checks_buffer_size() {
        assert!(Image::from_u8(2, 3, Channels::Rgb, vec![0; 18]).is_ok());
        let err = Image::from_u8(2, 3, Channels::Rgb, vec![0; 17]).unwrap_err();
        assert!(matches!(
            err,
            ValueError::ImageSize {
                expected: 18,
                actual: 17,
                ..
            }
        ));
        assert!(Image::from_u8(0, 5, Channels::Gray, vec![]).is_ok());
        assert!(Image::sample_count(usize::MAX, 2, Channels::Gray).is_err());
    }

    #[test]
    fn list_type_is_known_when_empty() {
        let v = Value::list(PortType::Image, vec![]);
        assert_eq!(v.port_type(), PortType::Image.list_of());
        assert_eq!(v.byte_size(), 0);
    }

    #[test]
    fn byte_size_counts_samples() {
        let img = Image::from_f32(4, 2, Channels::Rgba, vec![0.0; 32]).unwrap();
        assert_eq!(Value::image(img).byte_size(), 128);
    }

    #[test]
    fn pose_matrix_round_trip() {
        for q in [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.5, 0.5, -0.5, 0.5],
            [0.9, 0.1, -0.3, 0.2],
        ] {
            let n = q.iter().map(|v: &f64| v * v).sum::<f64>().sqrt();
            let q = q.map(|v| v / n);
            let p = Pose {
                rotation: q,
                translation: [1.0, 2.0, 3.0],
            };
            let r = p.rotation_matrix();
            let back = Pose::from_rotation_matrix(&r, p.translation);
            let r2 = back.rotation_matrix();
            for (a, b) in r.iter().zip(&r2) {
                assert!((a - b).abs() < 1e-12, "{q:?}");
            }
            let det = r[0] * (r[4] * r[8] - r[5] * r[7]) - r[1] * (r[3] * r[8] - r[5] * r[6])
                + r[2] * (r[3] * r[7] - r[4] * r[6]);
            assert!((det - 1.0).abs() < 1e-12);
        }
        // 90° about z maps x to y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = Pose {
            rotation: [h, 0.0, 0.0, h],
            translation: [0.0; 3],
        }
        .rotation_matrix();
        assert!((r[3] - 1.0).abs() < 1e-12 && (r[1] + 1.0).abs() < 1e-12);
    }

    #[test]
    fn camera_parts() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 510.0,
            cx: 320.0,
            cy: 240.0,
            skew: 0.5,
        };
        let d = Distortion::RadialTangential([0.1, -0.2, 0.001, 0.002, 0.03]);
        let c = Camera::from_parts(640, 480, k, d);
        assert_eq!(c.params.len(), c.model.param_count());
        assert_eq!(c.intrinsics(), k);
        assert_eq!(c.distortion(), d);
        assert_eq!(c.colmap_params().len(), 12);
        let f = Camera::from_parts(640, 480, k, Distortion::Fisheye([0.1, 0.2, 0.3, 0.4]));
        assert_eq!(f.params.len(), f.model.param_count());
        assert_eq!(f.distortion(), Distortion::Fisheye([0.1, 0.2, 0.3, 0.4]));
        assert_eq!(
            f.colmap_params(),
            vec![500.0, 510.0, 320.0, 240.0, 0.1, 0.2, 0.3, 0.4]
        );
        let s = Camera {
            model: CameraModel::SimpleRadial,
            width: 1,
            height: 1,
            params: vec![100.0, 1.0, 2.0, 0.5],
        };
        assert_eq!(s.intrinsics().fy, 100.0);
        assert_eq!(
            s.distortion(),
            Distortion::RadialTangential([0.5, 0.0, 0.0, 0.0, 0.0])
        );
    }

    #[test]
    fn matrix_checks_size() {
        assert!(Matrix::new(2, 2, vec![1.0; 4]).is_ok());
        assert!(Matrix::new(2, 3, vec![1.0; 4]).is_err());
        let m = Matrix::new(2, 2, vec![1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(m.get(1, 0), Some(3.0));
        assert_eq!(m.get(2, 0), None);
    }
}
