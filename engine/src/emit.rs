//! Writing graph outputs to a folder (`ocellus run G.ron --emit DIR`).
//!
//! [`emit_value`] writes one named output. Users' scripts read these files, so the names and
//! formats below are a contract:
//!
//! | value | file(s) | content |
//! |-------|---------|---------|
//! | Image u8 / u16 | `NAME.png` | 8- or 16-bit PNG, gray/rgb/rgba |
//! | Image f32 gray / rgb | `NAME.pfm` | little-endian PFM |
//! | Image f32 rgba | `NAME.tiff` | 32-bit float TIFF |
//! | Image of zero area | `NAME.json` | `{"width":W,"height":H,"format":"rgb_u8"}` (no image format stores an empty image) |
//! | Matrix | `NAME.json` | `{"rows":R,"cols":C,"data":[row-major…]}` |
//! | Scalar, Integer, Bool, Text | `NAME.json` | the bare JSON value |
//! | Metrics | `NAME.json` | object name → number, keys sorted |
//! | Keypoints | `NAME.json` | `[{"x","y","size","angle","response","octave"}…]` |
//! | Matches | `NAME.json` | `[{"query","train","distance"}…]` |
//! | Camera | `NAME.json` | `{"width","height","fx","fy","cx","cy","skew","distortion":D}`; D is `{"model":"radial_tangential","k1","k2","p1","p2","k3"}`, `{"model":"fisheye","k1","k2","k3","k4"}` or `{"model":"none"}` (COLMAP's radial models give `radial_tangential` with `p1 = p2 = 0`) |
//! | Pose | `NAME.json` | `{"rotation":[r00,r01,r02,r10,…,r22],"translation":[x,y,z]}`: R row-major, `x_to = R·x_from + t` |
//! | Points2D | `NAME.json` | `[[x,y]…]` |
//! | Descriptors | `NAME.json` | `{"kind":"float"\|"binary","rows","cols","data":[…]}`; for binary, `cols` counts bytes and `data` holds bytes 0..=255 |
//! | Tracks | `NAME.json` | `{"tracks":[[{"image","keypoint"}…]…]}` |
//! | Animation | `NAME.json` | `{"duration","channels":[{"target","times","width","values"}…]}` |
//! | Scene | `NAME.json` | full scene, see below |
//! | Bvh | `NAME.json` | its shape: `{"triangles","nodes","leaves","max_depth","max_leaf_size","min":[x,y,z],"max":[x,y,z]}` (the root box; `null` corners when empty) |
//! | PointCloud | `NAME.ply` | binary little-endian PLY: `float x y z`, then `uchar red green blue` if colored, then `float nx ny nz` if it has normals |
//! | Mesh | `NAME.obj` and `NAME.ply` | see below |
//! | Reconstruction | folder `NAME/` | COLMAP text model: `cameras.txt`, `images.txt`, `points3D.txt` |
//! | List | folder `NAME/` | element `i` emitted as `NAME/i`, zero-padded to the width of the largest index (`00` … `11` for 12 elements); nested lists nest folders |
//!
//! JSON files are compact, end with a newline, and use the shortest representation that reads
//! back to the same float. JSON has no NaN or infinity: **non-finite numbers are written as
//! `null`**. Text formats (OBJ, COLMAP) write non-finite numbers as `NaN`, `inf`, `-inf`; PLY
//! stores them bit for bit.
//!
//! **Meshes.** `NAME.obj`: `v x y z` (with `r g b` appended when the mesh has colors), `vt u v`
//! when it has uvs, `vn x y z` when it has normals, then faces with 1-based indices in the form
//! the attributes allow: `f a b c`, `f a/a b/b c/c` (uvs), `f a//a b//b c//c` (normals),
//! `f a/a/a …` (both). `NAME.ply`: vertex properties `float x y z`, `float nx ny nz`, `float s t`,
//! `uchar red green blue` (each group only when present), and faces as
//! `property list uchar int vertex_indices`. Mesh colors are linear RGB; both files store them
//! sRGB-encoded, as viewers expect (floats 0..1 in OBJ, bytes in PLY). A mesh with tangents gets
//! `float tx ty tz tw` after the other PLY vertex properties (OBJ has no place for them). Both
//! files come from [`crate::mesh_write`], which `io.write_mesh` uses too.
//!
//! **Scene.** One `NAME.json`: `{"materials":[{"name","albedo","roughness","metalness",
//! "emission","specular","shininess","transmission","ior","opacity","shading","textures":
//! {"albedo"|"normal"|"roughness"|"metalness"|"emission":{"width","height","channels",
//! "depth","wrap","filter","border","max_anisotropy","uv_scale"}}}…],"objects":[{"name",
//! "shape":{"type":"mesh","vertex_count","triangle_count","mesh":{"positions","triangles",
//! "normals","uvs","colors"}} or {"type":"sphere","center","radius"} or {"type":"plane",
//! "point","normal","half_extent"} or {"type":"quadric","coefficients","min","max"},
//! "world_from_object":Pose,"scale","material"}…],"lights":[{"type":"point","position",
//! "intensity"} or {"type":"directional","direction","irradiance"} or {"type":"area","corner",
//! "edge_u","edge_v","radiance"} or {"type":"environment","radiance","map":texture or null}…],
//! "cameras":[{"camera":Camera,"camera_from_world":Pose,"aperture_radius","focus_distance"}…]}`.
//! Absent optional mesh attributes are `null`, texels are not written, and non-finite numbers
//! (an infinite plane's `half_extent`) are `null`.
//!
//! **Reconstruction.** COLMAP's text layout and header comments; cameras with skew
//! (radial–tangential → `FULL_OPENCV`, fisheye → `OPENCV_FISHEYE`) lose the skew, which COLMAP
//! cannot represent (see [`Camera::colmap_params`]); images and points are written
//! in increasing id order, an image's `POINTS2D` line is empty when it has no observations, and
//! a 2-D point without a 3-D point has `POINT3D_ID` `-1`. Image names must not contain line
//! breaks.
//!
//! Every file is written through [`write_atomic`](crate::image_io::write_atomic), and the same
//! value always gives the same bytes. Folders are created as needed; files already in an output
//! folder that the value does not produce are left alone (a shorter list does not delete the
//! extra elements of an earlier run).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::image_io::{self, ImageIoError, write_atomic_with};
use crate::mesh_write;
use crate::summary::fmt_sig6;
use crate::value::{
    Bvh, Camera, Channels, Depth, Descriptors, Distortion, Image, Light, Matrix, Mesh, PointCloud,
    Pose, Reconstruction, Scene, Shading, Shape, Texture, TextureFilter, TextureWrap, Value,
    ValueList,
};

/// Errors writing outputs.
#[derive(Debug, thiserror::Error)]
pub enum EmitError {
    /// The output name cannot be used as a file name.
    #[error("output name {name:?} cannot be a file name: {reason}")]
    InvalidName {
        /// The name.
        name: String,
        /// Why not.
        reason: &'static str,
    },
    /// A file or folder could not be written.
    #[error("cannot write `{}`: {error}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The operating system's error.
        error: io::Error,
    },
    /// An image could not be encoded or written.
    #[error(transparent)]
    Image(#[from] ImageIoError),
    /// The value is inconsistent and cannot be written in its format (e.g. a triangle index
    /// past the last vertex).
    #[error("cannot write output `{name}`: {reason}")]
    InvalidValue {
        /// The output name.
        name: String,
        /// What is wrong.
        reason: String,
    },
}

/// Writes `value` into `dir` under `name` (see the [module docs](self) for file names and
/// formats) and returns the files written, in order. `dir` is created if missing.
pub fn emit_value(dir: &Path, name: &str, value: &Value) -> Result<Vec<PathBuf>, EmitError> {
    check_name(name)?;
    create_dir(dir)?;
    let json_path = || dir.join(format!("{name}.json"));
    let one = |path: PathBuf, result: Result<(), EmitError>| result.map(|()| vec![path]);
    match value {
        Value::Image(image) => emit_image(dir, name, image),
        Value::Matrix(m) => {
            let path = json_path();
            one(path.clone(), write_json(&path, &MatrixJson::from(&**m)))
        }
        Value::Scalar(x) => one(json_path(), write_json(&json_path(), x)),
        Value::Integer(i) => one(json_path(), write_json(&json_path(), i)),
        Value::Bool(b) => one(json_path(), write_json(&json_path(), b)),
        Value::Text(t) => one(json_path(), write_json(&json_path(), &**t)),
        Value::Metrics(m) => one(json_path(), write_json(&json_path(), &**m)),
        Value::Keypoints(k) => one(json_path(), write_json(&json_path(), &**k)),
        Value::Matches(m) => one(json_path(), write_json(&json_path(), &**m)),
        Value::Camera(c) => one(
            json_path(),
            write_json(&json_path(), &CameraJson::from(&**c)),
        ),
        Value::Pose(p) => one(json_path(), write_json(&json_path(), &PoseJson::from(p))),
        Value::Points2D(p) => one(json_path(), write_json(&json_path(), &**p)),
        Value::Descriptors(d) => one(
            json_path(),
            write_json(&json_path(), &DescriptorsJson::from(&**d)),
        ),
        Value::Tracks(t) => one(json_path(), write_json(&json_path(), &**t)),
        Value::Animation(a) => one(json_path(), write_json(&json_path(), &**a)),
        Value::Scene(s) => one(
            json_path(),
            write_json(&json_path(), &SceneJson::from(&**s)),
        ),
        Value::PointCloud(p) => {
            let path = dir.join(format!("{name}.ply"));
            one(path.clone(), write_point_cloud_ply(&path, name, p))
        }
        Value::Mesh(m) => emit_mesh(dir, name, m),
        Value::Bvh(b) => one(json_path(), write_json(&json_path(), &BvhJson::from(&**b))),
        Value::Reconstruction(r) => emit_reconstruction(&dir.join(name), name, r),
        Value::List(list) => emit_list(&dir.join(name), list),
    }
}

/// The JSON that [`emit_value`] writes for `value` (without the trailing newline), for the
/// values it writes as JSON; `None` for images, point clouds, meshes, reconstructions and lists.
/// Language bindings return exactly what the CLI emits from this.
pub fn json_text(value: &Value) -> Option<String> {
    let text = match value {
        Value::Matrix(m) => serde_json::to_string(&MatrixJson::from(&**m)),
        Value::Scalar(x) => serde_json::to_string(x),
        Value::Integer(i) => serde_json::to_string(i),
        Value::Bool(b) => serde_json::to_string(b),
        Value::Text(t) => serde_json::to_string(&**t),
        Value::Metrics(m) => serde_json::to_string(&**m),
        Value::Keypoints(k) => serde_json::to_string(&**k),
        Value::Matches(m) => serde_json::to_string(&**m),
        Value::Camera(c) => serde_json::to_string(&CameraJson::from(&**c)),
        Value::Pose(p) => serde_json::to_string(&PoseJson::from(p)),
        Value::Points2D(p) => serde_json::to_string(&**p),
        Value::Descriptors(d) => serde_json::to_string(&DescriptorsJson::from(&**d)),
        Value::Tracks(t) => serde_json::to_string(&**t),
        Value::Animation(a) => serde_json::to_string(&**a),
        Value::Scene(s) => serde_json::to_string(&SceneJson::from(&**s)),
        Value::Bvh(b) => serde_json::to_string(&BvhJson::from(&**b)),
        Value::Image(_)
        | Value::PointCloud(_)
        | Value::Mesh(_)
        | Value::Reconstruction(_)
        | Value::List(_) => return None,
    };
    text.ok()
}

/// Rejects names that are not a single, ordinary path component.
fn check_name(name: &str) -> Result<(), EmitError> {
    let reason = if name.is_empty() {
        "it is empty"
    } else if name == "." || name == ".." {
        "it is `.` or `..`"
    } else if name.contains(['/', '\\']) {
        "it contains a path separator"
    } else if name.chars().any(char::is_control) {
        "it contains a control character"
    } else {
        return Ok(());
    };
    Err(EmitError::InvalidName {
        name: name.to_string(),
        reason,
    })
}

fn create_dir(dir: &Path) -> Result<(), EmitError> {
    crate::temp_files::prepare_dir(dir).map_err(|error| EmitError::Io {
        path: dir.to_path_buf(),
        error,
    })
}

fn io_error(path: &Path) -> impl FnOnce(io::Error) -> EmitError + '_ {
    move |error| EmitError::Io {
        path: path.to_path_buf(),
        error,
    }
}

fn invalid(name: &str, reason: impl Into<String>) -> EmitError {
    EmitError::InvalidValue {
        name: name.to_string(),
        reason: reason.into(),
    }
}

/// Compact JSON plus a trailing newline, streamed into an atomic write.
/// The shape of a BVH (the tree itself is not written).
#[derive(Serialize)]
struct BvhJson {
    triangles: usize,
    nodes: usize,
    leaves: usize,
    max_depth: usize,
    max_leaf_size: usize,
    min: Option<[f32; 3]>,
    max: Option<[f32; 3]>,
}

impl From<&Bvh> for BvhJson {
    fn from(b: &Bvh) -> BvhJson {
        let stats = b.stats();
        BvhJson {
            triangles: b.primitives.len(),
            nodes: stats.nodes,
            leaves: stats.leaves,
            max_depth: stats.max_depth,
            max_leaf_size: stats.max_leaf_size,
            min: b.nodes.first().map(|n| n.min),
            max: b.nodes.first().map(|n| n.max),
        }
    }
}

fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<(), EmitError> {
    write_atomic_with(path, |w| {
        serde_json::to_writer(&mut *w, value).map_err(io::Error::from)?;
        w.write_all(b"\n")
    })
    .map_err(io_error(path))
}

fn emit_image(dir: &Path, name: &str, image: &Image) -> Result<Vec<PathBuf>, EmitError> {
    if image.is_empty() {
        let path = dir.join(format!("{name}.json"));
        let format = image.format().to_string();
        let json = EmptyImageJson {
            width: image.width(),
            height: image.height(),
            format: &format,
        };
        write_json(&path, &json)?;
        return Ok(vec![path]);
    }
    let extension = match (image.depth(), image.channels()) {
        (Depth::U8 | Depth::U16, _) => "png",
        (Depth::F32, Channels::Gray | Channels::Rgb) => "pfm",
        (Depth::F32, Channels::Rgba) => "tiff",
    };
    let path = dir.join(format!("{name}.{extension}"));
    image_io::write_image(&path, image)?;
    Ok(vec![path])
}

#[derive(Serialize)]
struct EmptyImageJson<'a> {
    width: usize,
    height: usize,
    format: &'a str,
}

#[derive(Serialize)]
struct MatrixJson<'a> {
    rows: usize,
    cols: usize,
    data: &'a [f64],
}

impl<'a> From<&'a Matrix> for MatrixJson<'a> {
    fn from(m: &'a Matrix) -> Self {
        MatrixJson {
            rows: m.rows,
            cols: m.cols,
            data: &m.data,
        }
    }
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraJson {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    skew: f64,
    distortion: DistortionJson,
}

#[derive(Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case", deny_unknown_fields)]
enum DistortionJson {
    None,
    RadialTangential {
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
        k3: f64,
    },
    Fisheye {
        k1: f64,
        k2: f64,
        k3: f64,
        k4: f64,
    },
}

impl From<&Camera> for CameraJson {
    fn from(c: &Camera) -> Self {
        let k = c.intrinsics();
        let distortion = match c.distortion() {
            Distortion::None => DistortionJson::None,
            Distortion::RadialTangential([k1, k2, p1, p2, k3]) => {
                DistortionJson::RadialTangential { k1, k2, p1, p2, k3 }
            }
            Distortion::Fisheye([k1, k2, k3, k4]) => DistortionJson::Fisheye { k1, k2, k3, k4 },
        };
        CameraJson {
            width: c.width,
            height: c.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            skew: k.skew,
            distortion,
        }
    }
}

/// Reads a camera written by [`emit_value`] (the `Camera` row of the table in the
/// [module docs](self)): `{"width","height","fx","fy","cx","cy","skew","distortion":D}`.
/// Unknown or missing keys, non-finite numbers, non-positive focal lengths and a zero image
/// size are errors (the message names the problem). `"none"` with zero skew gives a
/// [`CameraModel::Pinhole`](crate::value::CameraModel::Pinhole) camera, radial–tangential (or
/// `"none"` with skew) a
/// [`CameraModel::RadialTangential`](crate::value::CameraModel::RadialTangential) one and
/// fisheye a [`CameraModel::Fisheye`](crate::value::CameraModel::Fisheye) one, so that the
/// camera read back emits the same text again.
pub fn camera_from_json(text: &str) -> Result<Camera, String> {
    let c: CameraJson = serde_json::from_str(text).map_err(|e| format!("not a camera: {e}"))?;
    if c.width == 0 || c.height == 0 {
        return Err(format!(
            "image size must be positive, got {}×{}",
            c.width, c.height
        ));
    }
    let (distortion, coefficients): (Distortion, Vec<f64>) = match c.distortion {
        DistortionJson::None => (Distortion::None, Vec::new()),
        DistortionJson::RadialTangential { k1, k2, p1, p2, k3 } => (
            Distortion::RadialTangential([k1, k2, p1, p2, k3]),
            vec![k1, k2, p1, p2, k3],
        ),
        DistortionJson::Fisheye { k1, k2, k3, k4 } => {
            (Distortion::Fisheye([k1, k2, k3, k4]), vec![k1, k2, k3, k4])
        }
    };
    let all = [c.fx, c.fy, c.cx, c.cy, c.skew];
    if !all.iter().chain(&coefficients).all(|v| v.is_finite()) {
        return Err("camera has a null or non-finite parameter".into());
    }
    if !(c.fx > 0.0 && c.fy > 0.0) {
        return Err(format!(
            "focal lengths must be > 0, got fx = {}, fy = {}",
            c.fx, c.fy
        ));
    }
    let k = crate::value::Intrinsics {
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        skew: c.skew,
    };
    if matches!(distortion, Distortion::None) && c.skew == 0.0 {
        return Ok(Camera {
            model: crate::value::CameraModel::Pinhole,
            width: c.width,
            height: c.height,
            params: vec![c.fx, c.fy, c.cx, c.cy],
        });
    }
    Ok(Camera::from_parts(c.width, c.height, k, distortion))
}

/// A pose as a row-major rotation matrix and a translation.
#[derive(Serialize)]
struct PoseJson {
    rotation: [f64; 9],
    translation: [f64; 3],
}

impl From<&Pose> for PoseJson {
    fn from(p: &Pose) -> Self {
        PoseJson {
            rotation: p.rotation_matrix(),
            translation: p.translation,
        }
    }
}

#[derive(Serialize)]
#[serde(untagged)]
enum DescriptorData<'a> {
    Float(&'a [f32]),
    Binary(&'a [u8]),
}

#[derive(Serialize)]
struct DescriptorsJson<'a> {
    kind: &'static str,
    rows: usize,
    cols: usize,
    data: DescriptorData<'a>,
}

impl<'a> From<&'a Descriptors> for DescriptorsJson<'a> {
    fn from(d: &'a Descriptors) -> Self {
        let rows = d.len();
        match d {
            Descriptors::Float { dim, data } => DescriptorsJson {
                kind: "float",
                rows,
                cols: *dim,
                data: DescriptorData::Float(data),
            },
            Descriptors::Binary { bytes, data } => DescriptorsJson {
                kind: "binary",
                rows,
                cols: *bytes,
                data: DescriptorData::Binary(data),
            },
        }
    }
}

#[derive(Serialize)]
struct SceneJson<'a> {
    materials: Vec<MaterialJson<'a>>,
    objects: Vec<SceneObjectJson<'a>>,
    lights: Vec<LightJson>,
    cameras: Vec<SceneCameraJson>,
}

#[derive(Serialize)]
struct TextureJson {
    width: usize,
    height: usize,
    channels: Channels,
    depth: Depth,
    wrap: TextureWrap,
    filter: TextureFilter,
    border: [f32; 4],
    max_anisotropy: u32,
    uv_scale: [f32; 2],
}

impl From<&Texture> for TextureJson {
    fn from(t: &Texture) -> Self {
        TextureJson {
            width: t.image.width(),
            height: t.image.height(),
            channels: t.image.channels(),
            depth: t.image.depth(),
            wrap: t.wrap,
            filter: t.filter,
            border: t.border,
            max_anisotropy: t.max_anisotropy,
            uv_scale: t.uv_scale,
        }
    }
}

#[derive(Serialize)]
struct MaterialJson<'a> {
    name: &'a str,
    albedo: [f32; 3],
    roughness: f32,
    metalness: f32,
    emission: [f32; 3],
    specular: f32,
    shininess: f32,
    transmission: f32,
    ior: f32,
    opacity: f32,
    shading: Shading,
    textures: BTreeMap<&'static str, TextureJson>,
}

#[derive(Serialize)]
#[serde(tag = "type", rename_all = "lowercase")]
enum ShapeJson<'a> {
    Mesh {
        vertex_count: usize,
        triangle_count: usize,
        mesh: &'a Mesh,
    },
    Sphere {
        center: [f64; 3],
        radius: f64,
    },
    Plane {
        point: [f64; 3],
        normal: [f64; 3],
        half_extent: f64,
    },
    Quadric {
        coefficients: [f64; 10],
        min: [f64; 3],
        max: [f64; 3],
    },
}

#[derive(Serialize)]
struct SceneObjectJson<'a> {
    name: &'a str,
    shape: ShapeJson<'a>,
    world_from_object: PoseJson,
    scale: f64,
    material: u32,
}

#[derive(Serialize)]
#[serde(tag = "type", rename_all = "lowercase")]
enum LightJson {
    Point {
        position: [f64; 3],
        intensity: [f32; 3],
    },
    Directional {
        direction: [f64; 3],
        irradiance: [f32; 3],
    },
    Area {
        corner: [f64; 3],
        edge_u: [f64; 3],
        edge_v: [f64; 3],
        radiance: [f32; 3],
    },
    Environment {
        radiance: [f32; 3],
        map: Option<TextureJson>,
    },
}

#[derive(Serialize)]
struct SceneCameraJson {
    camera: CameraJson,
    camera_from_world: PoseJson,
    aperture_radius: f64,
    focus_distance: f64,
}

impl<'a> From<&'a Scene> for SceneJson<'a> {
    fn from(s: &'a Scene) -> Self {
        SceneJson {
            materials: s
                .materials
                .iter()
                .map(|m| {
                    let textures = [
                        ("albedo", &m.albedo_texture),
                        ("normal", &m.normal_texture),
                        ("roughness", &m.roughness_texture),
                        ("metalness", &m.metalness_texture),
                        ("emission", &m.emission_texture),
                    ]
                    .into_iter()
                    .filter_map(|(k, t)| t.as_ref().map(|t| (k, TextureJson::from(t))))
                    .collect();
                    MaterialJson {
                        name: &m.name,
                        albedo: m.albedo,
                        roughness: m.roughness,
                        metalness: m.metalness,
                        emission: m.emission,
                        specular: m.specular,
                        shininess: m.shininess,
                        transmission: m.transmission,
                        ior: m.ior,
                        opacity: m.opacity,
                        shading: m.shading,
                        textures,
                    }
                })
                .collect(),
            objects: s
                .objects
                .iter()
                .map(|o| SceneObjectJson {
                    name: &o.name,
                    shape: match &o.shape {
                        Shape::Mesh(m) => ShapeJson::Mesh {
                            vertex_count: m.positions.len(),
                            triangle_count: m.triangles.len(),
                            mesh: m,
                        },
                        &Shape::Sphere { center, radius } => ShapeJson::Sphere { center, radius },
                        &Shape::Plane {
                            point,
                            normal,
                            half_extent,
                        } => ShapeJson::Plane {
                            point,
                            normal,
                            half_extent,
                        },
                        &Shape::Quadric {
                            coefficients,
                            min,
                            max,
                        } => ShapeJson::Quadric {
                            coefficients,
                            min,
                            max,
                        },
                    },
                    world_from_object: PoseJson::from(&o.world_from_object),
                    scale: o.scale,
                    material: o.material,
                })
                .collect(),
            lights: s
                .lights
                .iter()
                .map(|l| match l {
                    &Light::Point {
                        position,
                        intensity,
                    } => LightJson::Point {
                        position,
                        intensity,
                    },
                    &Light::Directional {
                        direction,
                        irradiance,
                    } => LightJson::Directional {
                        direction,
                        irradiance,
                    },
                    &Light::Area {
                        corner,
                        edge_u,
                        edge_v,
                        radiance,
                    } => LightJson::Area {
                        corner,
                        edge_u,
                        edge_v,
                        radiance,
                    },
                    Light::Environment { radiance, map } => LightJson::Environment {
                        radiance: *radiance,
                        map: map.as_ref().map(TextureJson::from),
                    },
                })
                .collect(),
            cameras: s
                .cameras
                .iter()
                .map(|c| SceneCameraJson {
                    camera: CameraJson::from(&c.camera),
                    camera_from_world: PoseJson::from(&c.camera_from_world),
                    aperture_radius: c.aperture_radius,
                    focus_distance: c.focus_distance,
                })
                .collect(),
        }
    }
}

/// Checks that an optional per-vertex attribute has one entry per vertex.
fn check_attribute<T>(
    name: &str,
    what: &str,
    attribute: Option<&Vec<T>>,
    vertices: usize,
) -> Result<(), EmitError> {
    match attribute {
        Some(a) if a.len() != vertices => Err(invalid(
            name,
            format!("{} {what} for {vertices} vertices", a.len()),
        )),
        _ => Ok(()),
    }
}

fn write_point_cloud_ply(path: &Path, name: &str, cloud: &PointCloud) -> Result<(), EmitError> {
    let n = cloud.positions.len();
    check_attribute(name, "colors", cloud.colors.as_ref(), n)?;
    check_attribute(name, "normals", cloud.normals.as_ref(), n)?;
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\n\
         property float x\nproperty float y\nproperty float z\n"
    );
    if cloud.colors.is_some() {
        header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    if cloud.normals.is_some() {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    header.push_str("end_header\n");
    write_atomic_with(path, |w| {
        w.write_all(header.as_bytes())?;
        for (i, p) in cloud.positions.iter().enumerate() {
            write_f32s(w, p)?;
            if let Some(c) = cloud.colors.as_ref().and_then(|c| c.get(i)) {
                w.write_all(c)?;
            }
            if let Some(n) = cloud.normals.as_ref().and_then(|n| n.get(i)) {
                write_f32s(w, n)?;
            }
        }
        Ok(())
    })
    .map_err(io_error(path))
}

fn write_f32s(w: &mut dyn Write, values: &[f32]) -> io::Result<()> {
    for v in values {
        w.write_all(&v.to_le_bytes())?;
    }
    Ok(())
}

fn emit_mesh(dir: &Path, name: &str, mesh: &Mesh) -> Result<Vec<PathBuf>, EmitError> {
    mesh_write::check_mesh(mesh).map_err(|reason| invalid(name, reason))?;
    let obj = dir.join(format!("{name}.obj"));
    write_atomic_with(&obj, |w| mesh_write::write_obj(w, mesh)).map_err(io_error(&obj))?;
    let ply = dir.join(format!("{name}.ply"));
    write_atomic_with(&ply, |w| mesh_write::write_ply(w, mesh, true)).map_err(io_error(&ply))?;
    Ok(vec![obj, ply])
}

fn emit_reconstruction(
    folder: &Path,
    name: &str,
    r: &Reconstruction,
) -> Result<Vec<PathBuf>, EmitError> {
    if let Some(image) = r.images.iter().find(|i| i.name.contains(['\n', '\r'])) {
        return Err(invalid(
            name,
            format!("image {} has a line break in its name", image.id),
        ));
    }
    create_dir(folder)?;

    let cameras = folder.join("cameras.txt");
    write_atomic_with(&cameras, |w| {
        writeln!(w, "# Camera list with one line of data per camera:")?;
        writeln!(w, "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")?;
        writeln!(w, "# Number of cameras: {}", r.cameras.len())?;
        for (id, camera) in &r.cameras {
            write!(
                w,
                "{id} {} {} {}",
                camera.model.colmap_name(),
                camera.width,
                camera.height
            )?;
            for p in camera.colmap_params() {
                write!(w, " {p}")?;
            }
            writeln!(w)?;
        }
        Ok(())
    })
    .map_err(io_error(&cameras))?;

    let mut images: Vec<_> = r.images.iter().collect();
    images.sort_by_key(|i| i.id);
    let observations: usize = images
        .iter()
        .map(|i| i.points2d.iter().filter(|(_, id)| id.is_some()).count())
        .sum();
    let mean_observations = if images.is_empty() {
        0.0
    } else {
        observations as f64 / images.len() as f64
    };
    let images_path = folder.join("images.txt");
    write_atomic_with(&images_path, |w| {
        writeln!(w, "# Image list with two lines of data per image:")?;
        writeln!(
            w,
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
        )?;
        writeln!(w, "#   POINTS2D[] as (X, Y, POINT3D_ID)")?;
        writeln!(
            w,
            "# Number of images: {}, mean observations per image: {}",
            images.len(),
            fmt_sig6(mean_observations)
        )?;
        for image in &images {
            let Pose {
                rotation: [qw, qx, qy, qz],
                translation: [tx, ty, tz],
            } = image.camera_from_world;
            writeln!(
                w,
                "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}",
                image.id, image.camera_id, image.name
            )?;
            let mut line = String::new();
            for ([x, y], point) in &image.points2d {
                if !line.is_empty() {
                    line.push(' ');
                }
                let _ = match point {
                    Some(id) => write!(line, "{x} {y} {id}"),
                    None => write!(line, "{x} {y} -1"),
                };
            }
            line.push('\n');
            w.write_all(line.as_bytes())?;
        }
        Ok(())
    })
    .map_err(io_error(&images_path))?;

    let mut points: Vec<_> = r.points.iter().collect();
    points.sort_by_key(|p| p.id);
    let track_total: usize = points.iter().map(|p| p.track.len()).sum();
    let mean_track = if points.is_empty() {
        0.0
    } else {
        track_total as f64 / points.len() as f64
    };
    let points_path = folder.join("points3D.txt");
    write_atomic_with(&points_path, |w| {
        writeln!(w, "# 3D point list with one line of data per point:")?;
        writeln!(
            w,
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"
        )?;
        writeln!(
            w,
            "# Number of points: {}, mean track length: {}",
            points.len(),
            fmt_sig6(mean_track)
        )?;
        for p in &points {
            let [x, y, z] = p.position;
            let [red, green, blue] = p.color;
            write!(
                w,
                "{} {x} {y} {z} {red} {green} {blue} {}",
                p.id, p.error_px
            )?;
            for (image, index) in &p.track {
                write!(w, " {image} {index}")?;
            }
            writeln!(w)?;
        }
        Ok(())
    })
    .map_err(io_error(&points_path))?;

    Ok(vec![cameras, images_path, points_path])
}

fn emit_list(folder: &Path, list: &ValueList) -> Result<Vec<PathBuf>, EmitError> {
    create_dir(folder)?;
    let width = list.items.len().saturating_sub(1).to_string().len();
    let mut written = Vec::new();
    for (i, item) in list.items.iter().enumerate() {
        written.extend(emit_value(folder, &format!("{i:0width$}"), item)?);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use std::fs;
    use std::sync::Arc;

    use serde_json::json;

    use super::*;
    use crate::image_io::{DecodeLimits, read_image};
    use crate::types::PortType;
    use crate::value::{
        Animation, AnimationChannel, CameraModel, Distortion, Intrinsics, Keypoint, Match,
        Material, Metrics, ReconImage, ReconPoint, SceneCamera, SceneObject, TrackElement, Tracks,
    };

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("ocellus-emit-{}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    fn read_json(path: &Path) -> serde_json::Value {
        let text = fs::read_to_string(path).unwrap();
        assert!(text.ends_with('\n'));
        serde_json::from_str(&text).unwrap()
    }

    fn emit_json(dir: &Path, value: Value) -> serde_json::Value {
        let files = emit_value(dir, "v", &value).unwrap();
        assert_eq!(files, [dir.join("v.json")]);
        read_json(&files[0])
    }

    #[test]
    fn cameras_read_back_to_the_same_text() {
        let dir = scratch("camera_back");
        let cameras = [
            Camera {
                model: CameraModel::SimpleRadial,
                width: 640,
                height: 480,
                params: vec![500.0, 320.0, 240.0, 0.01],
            },
            Camera {
                model: CameraModel::Pinhole,
                width: 64,
                height: 48,
                params: vec![50.5, 51.0, 32.25, 24.0],
            },
            Camera::from_parts(
                640,
                480,
                Intrinsics {
                    fx: 500.0,
                    fy: 501.0,
                    cx: 320.0,
                    cy: 240.0,
                    skew: 0.25,
                },
                Distortion::Fisheye([0.1, -0.2, 0.01, 0.002]),
            ),
        ];
        for camera in cameras {
            let files = emit_value(&dir, "c", &Value::Camera(Arc::new(camera.clone()))).unwrap();
            let text = fs::read_to_string(&files[0]).unwrap();
            let back = camera_from_json(&text).unwrap();
            assert_eq!(back.intrinsics(), camera.intrinsics());
            assert_eq!(back.distortion(), camera.distortion());
            let again = emit_value(&dir, "d", &Value::Camera(Arc::new(back))).unwrap();
            assert_eq!(fs::read_to_string(&again[0]).unwrap(), text);
        }
        for (bad, why) in [
            ("", "not a camera"),
            ("{\"width\":1}", "missing field"),
            (
                "{\"width\":0,\"height\":4,\"fx\":1,\"fy\":1,\"cx\":0,\"cy\":0,\"skew\":0,\"distortion\":{\"model\":\"none\"}}",
                "image size",
            ),
            (
                "{\"width\":4,\"height\":4,\"fx\":-1,\"fy\":1,\"cx\":0,\"cy\":0,\"skew\":0,\"distortion\":{\"model\":\"none\"}}",
                "focal",
            ),
            (
                "{\"width\":4,\"height\":4,\"fx\":1,\"fy\":1,\"cx\":null,\"cy\":0,\"skew\":0,\"distortion\":{\"model\":\"none\"}}",
                "not a camera",
            ),
            (
                "{\"width\":4,\"height\":4,\"fx\":1,\"fy\":1,\"cx\":0,\"cy\":0,\"skew\":0,\"distortion\":{\"model\":\"kannala\"}}",
                "unknown variant",
            ),
            (
                "{\"width\":4,\"height\":4,\"fx\":1,\"fy\":1,\"cx\":0,\"cy\":0,\"skew\":0,\"f\":2,\"distortion\":{\"model\":\"none\"}}",
                "unknown field",
            ),
        ] {
            let e = camera_from_json(bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }

    #[test]
    fn json_values() {
        let dir = scratch("json");
        assert_eq!(emit_json(&dir, Value::Scalar(0.1)), json!(0.1));
        assert_eq!(fs::read_to_string(dir.join("v.json")).unwrap(), "0.1\n");
        assert_eq!(emit_json(&dir, Value::Scalar(f64::NAN)), json!(null));
        assert_eq!(emit_json(&dir, Value::Integer(-7)), json!(-7));
        assert_eq!(emit_json(&dir, Value::Bool(false)), json!(false));
        assert_eq!(
            emit_json(&dir, Value::Text("a \"b\"".into())),
            json!("a \"b\"")
        );

        let m = Matrix::new(2, 3, vec![1.0, 2.0, 3.0, 4.0, f64::INFINITY, 0.5]).unwrap();
        assert_eq!(
            emit_json(&dir, Value::Matrix(Arc::new(m))),
            json!({"rows": 2, "cols": 3, "data": [1.0, 2.0, 3.0, 4.0, null, 0.5]})
        );
        assert_eq!(
            fs::read_to_string(dir.join("v.json")).unwrap(),
            "{\"rows\":2,\"cols\":3,\"data\":[1.0,2.0,3.0,4.0,null,0.5]}\n"
        );

        let mut metrics = Metrics::new();
        metrics.insert("zeta".into(), 1.0);
        metrics.insert("alpha".into(), f64::NAN);
        emit_json(&dir, Value::metrics(metrics));
        assert_eq!(
            fs::read_to_string(dir.join("v.json")).unwrap(),
            "{\"alpha\":null,\"zeta\":1.0}\n"
        );

        let keypoints = vec![Keypoint {
            x: 1.5,
            y: 2.0,
            size: 3.0,
            angle: -1.0,
            response: 0.1,
            octave: 2,
        }];
        assert_eq!(
            emit_json(&dir, Value::Keypoints(Arc::new(keypoints))),
            json!([{"x": 1.5, "y": 2.0, "size": 3.0, "angle": -1.0, "response": 0.1, "octave": 2}])
        );
        // f32 values keep their shortest f32 spelling.
        assert!(
            fs::read_to_string(dir.join("v.json"))
                .unwrap()
                .contains("\"response\":0.1,")
        );

        let matches = vec![Match {
            query: 3,
            train: 9,
            distance: 0.25,
        }];
        assert_eq!(
            emit_json(&dir, Value::Matches(Arc::new(matches))),
            json!([{"query": 3, "train": 9, "distance": 0.25}])
        );
        let camera = Camera {
            model: CameraModel::SimpleRadial,
            width: 640,
            height: 480,
            params: vec![500.0, 320.0, 240.0, 0.01],
        };
        assert_eq!(
            emit_json(&dir, Value::Camera(Arc::new(camera))),
            json!({"width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0,
                   "skew": 0.0,
                   "distortion": {"model": "radial_tangential", "k1": 0.01, "k2": 0.0, "p1": 0.0,
                                  "p2": 0.0, "k3": 0.0}})
        );
        let full = Camera::from_parts(
            640,
            480,
            Intrinsics {
                fx: 500.0,
                fy: 501.0,
                cx: 320.0,
                cy: 240.0,
                skew: 0.25,
            },
            Distortion::RadialTangential([0.1, -0.2, 0.001, 0.002, 0.05]),
        );
        assert_eq!(
            emit_json(&dir, Value::Camera(Arc::new(full))),
            json!({"width": 640, "height": 480, "fx": 500.0, "fy": 501.0, "cx": 320.0, "cy": 240.0,
                   "skew": 0.25,
                   "distortion": {"model": "radial_tangential", "k1": 0.1, "k2": -0.2, "p1": 0.001,
                                  "p2": 0.002, "k3": 0.05}})
        );
        let fisheye = Camera::from_parts(
            320,
            240,
            Intrinsics {
                fx: 200.0,
                fy: 200.0,
                cx: 160.0,
                cy: 120.0,
                skew: 0.0,
            },
            Distortion::Fisheye([0.1, 0.01, -0.002, 0.0005]),
        );
        assert_eq!(
            emit_json(&dir, Value::Camera(Arc::new(fisheye))),
            json!({"width": 320, "height": 240, "fx": 200.0, "fy": 200.0, "cx": 160.0, "cy": 120.0,
                   "skew": 0.0,
                   "distortion": {"model": "fisheye", "k1": 0.1, "k2": 0.01, "k3": -0.002,
                                  "k4": 0.0005}})
        );
        let pinhole = Camera {
            model: CameraModel::Pinhole,
            width: 4,
            height: 3,
            params: vec![10.0, 11.0, 2.0, 1.5],
        };
        assert_eq!(
            emit_json(&dir, Value::Camera(Arc::new(pinhole))),
            json!({"width": 4, "height": 3, "fx": 10.0, "fy": 11.0, "cx": 2.0, "cy": 1.5,
                   "skew": 0.0, "distortion": {"model": "none"}})
        );
        let pose = Pose {
            rotation: [1.0, 0.0, 0.0, 0.0],
            translation: [1.0, 2.0, 3.0],
        };
        assert_eq!(
            emit_json(&dir, Value::Pose(pose)),
            json!({"rotation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                   "translation": [1.0, 2.0, 3.0]})
        );
        // 90° about z: x → y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let v = emit_json(
            &dir,
            Value::Pose(Pose {
                rotation: [h, 0.0, 0.0, h],
                translation: [0.0; 3],
            }),
        );
        let r: Vec<f64> = v["rotation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let want = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        assert!(
            r.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12),
            "{r:?}"
        );
        assert_eq!(
            emit_json(
                &dir,
                Value::Points2D(Arc::new(vec![[1.0, 2.0], [3.5, -4.0]]))
            ),
            json!([[1.0, 2.0], [3.5, -4.0]])
        );
        let float = Descriptors::Float {
            dim: 2,
            data: vec![0.5, 1.0, 1.5, 2.0, 2.5, 3.0],
        };
        assert_eq!(
            emit_json(&dir, Value::Descriptors(Arc::new(float))),
            json!({"kind": "float", "rows": 3, "cols": 2, "data": [0.5, 1.0, 1.5, 2.0, 2.5, 3.0]})
        );
        let binary = Descriptors::Binary {
            bytes: 2,
            data: vec![255, 0, 1, 2],
        };
        assert_eq!(
            emit_json(&dir, Value::Descriptors(Arc::new(binary))),
            json!({"kind": "binary", "rows": 2, "cols": 2, "data": [255, 0, 1, 2]})
        );
        let tracks = Tracks {
            tracks: vec![vec![TrackElement {
                image: 0,
                keypoint: 4,
            }]],
        };
        assert_eq!(
            emit_json(&dir, Value::Tracks(Arc::new(tracks))),
            json!({"tracks": [[{"image": 0, "keypoint": 4}]]})
        );
        let animation = Animation {
            duration: 2.0,
            channels: vec![AnimationChannel {
                target: "joint.translation".into(),
                times: vec![0.0, 2.0],
                width: 1,
                values: vec![0.0, 1.0],
            }],
        };
        assert_eq!(
            emit_json(&dir, Value::Animation(Arc::new(animation))),
            json!({"duration": 2.0, "channels": [{"target": "joint.translation", "times": [0.0, 2.0], "width": 1, "values": [0.0, 1.0]}]})
        );
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn images_pick_their_format() {
        let dir = scratch("images");
        let limits = DecodeLimits::default();
        let cases = [
            (
                Image::from_u8(2, 1, Channels::Rgb, vec![1, 2, 3, 4, 5, 6]).unwrap(),
                "png",
            ),
            (
                Image::from_u16(1, 2, Channels::Gray, vec![1000, 65535]).unwrap(),
                "png",
            ),
            (
                Image::from_f32(1, 1, Channels::Gray, vec![0.5]).unwrap(),
                "pfm",
            ),
            (
                Image::from_f32(1, 1, Channels::Rgba, vec![0.5, -1.0, 2.0, 1.0]).unwrap(),
                "tiff",
            ),
        ];
        for (image, ext) in cases {
            let files = emit_value(&dir, "img", &Value::image(image.clone())).unwrap();
            assert_eq!(files, [dir.join(format!("img.{ext}"))]);
            assert_eq!(read_image(&files[0], &limits).unwrap(), image);
        }
        let empty = Image::from_u8(0, 4, Channels::Rgb, vec![]).unwrap();
        let files = emit_value(&dir, "empty", &Value::image(empty)).unwrap();
        assert_eq!(
            read_json(&files[0]),
            json!({"width": 0, "height": 4, "format": "rgb_u8"})
        );
        fs::remove_dir_all(&dir).unwrap();
    }

    /// Parses a binary little-endian PLY: header lines and the body bytes.
    fn split_ply(bytes: &[u8]) -> (Vec<String>, &[u8]) {
        let end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let header = std::str::from_utf8(&bytes[..end])
            .unwrap()
            .lines()
            .map(str::to_string)
            .collect();
        (header, &bytes[end..])
    }

    fn f32_at(body: &[u8], offset: usize) -> f32 {
        f32::from_le_bytes(body[offset..offset + 4].try_into().unwrap())
    }

    #[test]
    fn point_cloud_ply() {
        let dir = scratch("cloud");
        let cloud = PointCloud {
            positions: vec![[1.0, 2.0, 3.0], [-1.0, 0.5, f32::NAN]],
            colors: Some(vec![[255, 0, 10], [1, 2, 3]]),
            normals: Some(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
        };
        let files = emit_value(&dir, "pts", &Value::PointCloud(Arc::new(cloud))).unwrap();
        assert_eq!(files, [dir.join("pts.ply")]);
        let bytes = fs::read(&files[0]).unwrap();
        let (header, body) = split_ply(&bytes);
        assert_eq!(
            header,
            [
                "ply",
                "format binary_little_endian 1.0",
                "element vertex 2",
                "property float x",
                "property float y",
                "property float z",
                "property uchar red",
                "property uchar green",
                "property uchar blue",
                "property float nx",
                "property float ny",
                "property float nz",
                "end_header",
            ]
        );
        let stride = 12 + 3 + 12;
        assert_eq!(body.len(), 2 * stride);
        assert_eq!(
            [f32_at(body, 0), f32_at(body, 4), f32_at(body, 8)],
            [1.0, 2.0, 3.0]
        );
        assert_eq!(&body[12..15], &[255, 0, 10]);
        assert_eq!(f32_at(body, 23), 1.0);
        assert_eq!(f32_at(body, stride), -1.0);
        assert!(f32_at(body, stride + 8).is_nan());
        assert_eq!(&body[stride + 12..stride + 15], &[1, 2, 3]);

        // Positions only.
        let plain = PointCloud {
            positions: vec![[0.0; 3]],
            ..PointCloud::default()
        };
        emit_value(&dir, "plain", &Value::PointCloud(Arc::new(plain))).unwrap();
        let bytes = fs::read(dir.join("plain.ply")).unwrap();
        let (header, body) = split_ply(&bytes);
        assert_eq!(header.len(), 7);
        assert_eq!(body.len(), 12);

        let bad = PointCloud {
            positions: vec![[0.0; 3]; 2],
            colors: Some(vec![[0; 3]]),
            normals: None,
        };
        let err = emit_value(&dir, "bad", &Value::PointCloud(Arc::new(bad))).unwrap_err();
        assert!(matches!(err, EmitError::InvalidValue { .. }), "{err}");
        assert!(!dir.join("bad.ply").exists());
        fs::remove_dir_all(&dir).unwrap();
    }

    fn quad(normals: bool, uvs: bool, colors: bool) -> Mesh {
        Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.5],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            normals: normals.then(|| vec![[0.0, 0.0, 1.0]; 4]),
            uvs: uvs.then(|| vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]),
            colors: colors
                .then(|| vec![[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.0, 2.0], [0.0; 3]]),
            tangents: None,
        }
    }

    #[test]
    fn mesh_obj_face_syntax() {
        let dir = scratch("mesh-obj");
        for (normals, uvs, face) in [
            (false, false, "f 1 3 4"),
            (false, true, "f 1/1 3/3 4/4"),
            (true, false, "f 1//1 3//3 4//4"),
            (true, true, "f 1/1/1 3/3/3 4/4/4"),
        ] {
            let files =
                emit_value(&dir, "m", &Value::Mesh(Arc::new(quad(normals, uvs, false)))).unwrap();
            assert_eq!(files, [dir.join("m.obj"), dir.join("m.ply")]);
            let obj = fs::read_to_string(&files[0]).unwrap();
            let lines: Vec<&str> = obj.lines().collect();
            assert_eq!(lines[0], "# 4 vertices, 2 triangles");
            assert_eq!(lines[1], "v 0 0 0");
            assert_eq!(lines[4], "v 0 1 0.5");
            assert_eq!(
                obj.lines().filter(|l| l.starts_with("vt ")).count(),
                if uvs { 4 } else { 0 }
            );
            assert_eq!(
                obj.lines().filter(|l| l.starts_with("vn ")).count(),
                if normals { 4 } else { 0 }
            );
            assert_eq!(*lines.last().unwrap(), face);
        }
        let files =
            emit_value(&dir, "c", &Value::Mesh(Arc::new(quad(false, false, true)))).unwrap();
        let obj = fs::read_to_string(&files[0]).unwrap();
        assert!(obj.contains("\nv 1 0 0 1 1 1\n"), "{obj}");
        assert!(obj.contains("\nv 1 1 0 0.735357 0 1\n"), "{obj}");

        let mut bad = quad(false, false, false);
        bad.triangles.push([0, 1, 4]);
        let err = emit_value(&dir, "bad", &Value::Mesh(Arc::new(bad))).unwrap_err();
        assert!(err.to_string().contains("vertex 4"), "{err}");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn mesh_ply_layout() {
        let dir = scratch("mesh-ply");
        let files = emit_value(&dir, "m", &Value::Mesh(Arc::new(quad(true, true, true)))).unwrap();
        let bytes = fs::read(&files[1]).unwrap();
        let (header, body) = split_ply(&bytes);
        assert_eq!(
            header,
            [
                "ply",
                "format binary_little_endian 1.0",
                "element vertex 4",
                "property float x",
                "property float y",
                "property float z",
                "property float nx",
                "property float ny",
                "property float nz",
                "property float s",
                "property float t",
                "property uchar red",
                "property uchar green",
                "property uchar blue",
                "element face 2",
                "property list uchar int vertex_indices",
                "end_header",
            ]
        );
        let stride = 12 + 12 + 8 + 3;
        assert_eq!(body.len(), 4 * stride + 2 * 13);
        // Vertex 2: position (1, 1, 0), uv (1, 1), color linear (0.5, 0, 2) → sRGB (188, 0, 255).
        let v2 = &body[2 * stride..3 * stride];
        assert_eq!(
            [f32_at(v2, 0), f32_at(v2, 4), f32_at(v2, 8)],
            [1.0, 1.0, 0.0]
        );
        assert_eq!([f32_at(v2, 24), f32_at(v2, 28)], [1.0, 1.0]);
        assert_eq!(&v2[32..35], &[188, 0, 255]);
        let faces = &body[4 * stride..];
        assert_eq!(faces[0], 3);
        let index = |f: usize, k: usize| {
            i32::from_le_bytes(
                faces[f * 13 + 1 + 4 * k..f * 13 + 5 + 4 * k]
                    .try_into()
                    .unwrap(),
            )
        };
        assert_eq!([index(0, 0), index(0, 1), index(0, 2)], [0, 1, 2]);
        assert_eq!([index(1, 0), index(1, 1), index(1, 2)], [0, 2, 3]);
        fs::remove_dir_all(&dir).unwrap();
    }

    fn small_reconstruction() -> Reconstruction {
        let mut cameras = BTreeMap::new();
        cameras.insert(
            1,
            Camera {
                model: CameraModel::Pinhole,
                width: 640,
                height: 480,
                params: vec![500.0, 501.5, 320.0, 240.0],
            },
        );
        let images = vec![
            ReconImage {
                id: 2,
                camera_id: 1,
                name: "b.jpg".into(),
                camera_from_world: Pose {
                    rotation: [0.5, 0.5, -0.5, 0.5],
                    translation: [1.0, -2.0, 0.25],
                },
                points2d: vec![([10.0, 20.0], Some(7)), ([30.5, 40.0], Some(8))],
            },
            ReconImage {
                id: 1,
                camera_id: 1,
                name: "a.jpg".into(),
                camera_from_world: Pose::IDENTITY,
                points2d: vec![
                    ([1.0, 2.0], Some(7)),
                    ([3.0, 4.0], None),
                    ([5.0, 6.0], Some(9)),
                ],
            },
        ];
        let points = vec![
            ReconPoint {
                id: 9,
                position: [0.0, 0.0, 5.0],
                color: [0, 0, 255],
                error_px: 0.5,
                track: vec![(1, 2)],
            },
            ReconPoint {
                id: 7,
                position: [1.0, 2.0, 3.0],
                color: [255, 128, 0],
                error_px: 0.75,
                track: vec![(1, 0), (2, 0)],
            },
            ReconPoint {
                id: 8,
                position: [-1.5, 0.0, 4.0],
                color: [10, 20, 30],
                error_px: 1.25,
                track: vec![(2, 1)],
            },
        ];
        Reconstruction {
            cameras,
            images,
            points,
        }
    }

    #[test]
    fn reconstruction_colmap_text() {
        let dir = scratch("colmap");
        let files = emit_value(
            &dir,
            "sparse",
            &Value::Reconstruction(Arc::new(small_reconstruction())),
        )
        .unwrap();
        let folder = dir.join("sparse");
        assert_eq!(
            files,
            [
                folder.join("cameras.txt"),
                folder.join("images.txt"),
                folder.join("points3D.txt")
            ]
        );
        assert_eq!(
            fs::read_to_string(&files[0]).unwrap(),
            "# Camera list with one line of data per camera:\n\
             #   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n\
             # Number of cameras: 1\n\
             1 PINHOLE 640 480 500 501.5 320 240\n"
        );
        assert_eq!(
            fs::read_to_string(&files[1]).unwrap(),
            "# Image list with two lines of data per image:\n\
             #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
             #   POINTS2D[] as (X, Y, POINT3D_ID)\n\
             # Number of images: 2, mean observations per image: 2\n\
             1 1 0 0 0 0 0 0 1 a.jpg\n\
             1 2 7 3 4 -1 5 6 9\n\
             2 0.5 0.5 -0.5 0.5 1 -2 0.25 1 b.jpg\n\
             10 20 7 30.5 40 8\n"
        );
        assert_eq!(
            fs::read_to_string(&files[2]).unwrap(),
            "# 3D point list with one line of data per point:\n\
             #   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n\
             # Number of points: 3, mean track length: 1.33333\n\
             7 1 2 3 255 128 0 0.75 1 0 2 0\n\
             8 -1.5 0 4 10 20 30 1.25 2 1\n\
             9 0 0 5 0 0 255 0.5 1 2\n"
        );

        // An image without observations gets an empty POINTS2D line.
        let mut r = small_reconstruction();
        r.images[0].points2d.clear();
        emit_value(&dir, "sparse", &Value::Reconstruction(Arc::new(r))).unwrap();
        let text = fs::read_to_string(folder.join("images.txt")).unwrap();
        assert!(text.ends_with("0.25 1 b.jpg\n\n"), "{text}");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn scene_json() {
        let dir = scratch("scene");
        let scene = Scene {
            materials: vec![Material::default()],
            objects: vec![
                SceneObject {
                    name: "quad".into(),
                    shape: Shape::Mesh(Arc::new(quad(false, false, false))),
                    world_from_object: Pose::IDENTITY,
                    scale: 1.0,
                    material: 0,
                },
                SceneObject {
                    name: "floor".into(),
                    shape: Shape::Plane {
                        point: [0.0; 3],
                        normal: [0.0, 1.0, 0.0],
                        half_extent: f64::INFINITY,
                    },
                    world_from_object: Pose::IDENTITY,
                    scale: 1.0,
                    material: 0,
                },
            ],
            lights: vec![Light::Point {
                position: [0.0, 5.0, 0.0],
                intensity: [1.0, 1.0, 1.0],
            }],
            cameras: vec![SceneCamera {
                camera: Camera {
                    model: CameraModel::SimplePinhole,
                    width: 64,
                    height: 48,
                    params: vec![50.0, 32.0, 24.0],
                },
                camera_from_world: Pose::IDENTITY,
                aperture_radius: 0.0,
                focus_distance: 1.0,
            }],
        };
        let v = emit_json(&dir, Value::Scene(Arc::new(scene)));
        assert_eq!(v["objects"][0]["name"], "quad");
        assert_eq!(v["objects"][0]["shape"]["type"], "mesh");
        assert_eq!(v["objects"][0]["shape"]["vertex_count"], 4);
        assert_eq!(v["objects"][0]["shape"]["triangle_count"], 2);
        assert_eq!(
            v["objects"][0]["shape"]["mesh"]["triangles"],
            json!([[0, 1, 2], [0, 2, 3]])
        );
        assert_eq!(v["objects"][0]["shape"]["mesh"]["normals"], json!(null));
        assert_eq!(v["objects"][1]["shape"]["half_extent"], json!(null));
        assert_eq!(v["materials"][0]["shading"], "lambert");
        assert_eq!(v["cameras"][0]["focus_distance"], 1.0);
        assert_eq!(
            v["lights"][0],
            json!({"type": "point", "position": [0.0, 5.0, 0.0], "intensity": [1.0, 1.0, 1.0]})
        );
        assert_eq!(
            v["cameras"][0]["camera"]["distortion"],
            json!({"model": "none"})
        );
        assert_eq!(
            v["cameras"][0]["camera_from_world"]["rotation"],
            json!([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
        );
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn lists_are_folders_with_padded_names() {
        let dir = scratch("list");
        let items: Vec<Value> = (0..12).map(Value::Integer).collect();
        let files = emit_value(&dir, "seq", &Value::list(PortType::Integer, items)).unwrap();
        assert_eq!(files.len(), 12);
        assert_eq!(files[0], dir.join("seq").join("00.json"));
        assert_eq!(files[11], dir.join("seq").join("11.json"));
        assert_eq!(read_json(&files[11]), json!(11));

        let nested = Value::list(
            PortType::Scalar.list_of(),
            vec![Value::list(PortType::Scalar, vec![Value::Scalar(1.5); 3])],
        );
        let files = emit_value(&dir, "nested", &nested).unwrap();
        assert_eq!(
            files,
            [
                dir.join("nested/0/0.json"),
                dir.join("nested/0/1.json"),
                dir.join("nested/0/2.json")
            ]
        );
        let empty = emit_value(&dir, "none", &Value::list(PortType::Image, vec![])).unwrap();
        assert!(empty.is_empty());
        assert!(dir.join("none").is_dir());
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn names_are_checked() {
        let dir = scratch("names");
        for bad in ["", ".", "..", "a/b", "a\\b", "a\nb"] {
            let err = emit_value(&dir, bad, &Value::Bool(true)).unwrap_err();
            assert!(matches!(err, EmitError::InvalidName { .. }), "{bad:?}");
        }
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn output_is_deterministic() {
        let dir = scratch("determinism");
        let value = Value::Mesh(Arc::new(quad(true, true, true)));
        let first = emit_value(&dir, "m", &value).unwrap();
        let bytes: Vec<Vec<u8>> = first.iter().map(|p| fs::read(p).unwrap()).collect();
        let again = emit_value(&dir, "m", &value).unwrap();
        let bytes_again: Vec<Vec<u8>> = again.iter().map(|p| fs::read(p).unwrap()).collect();
        assert_eq!(bytes, bytes_again);
        // Only the outputs themselves: no temp files left.
        let mut names: Vec<String> = fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["m.obj", "m.ply"]);
        fs::remove_dir_all(&dir).unwrap();
    }
}
