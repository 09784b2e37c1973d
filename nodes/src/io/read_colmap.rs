//! `io.read_colmap`: read a COLMAP text model (`cameras.txt`, `images.txt`, `points3D.txt`) into
//! a reconstruction — the exact inverse of the engine's COLMAP writer
//! (`ocellus_engine::emit`, the `--emit` of a Reconstruction).
//!
//! Layout (COLMAP's `ReadCamerasText`, `ReadImagesText`, `ReadPoints3DText`): lines starting
//! with `#` and blank lines are skipped, except that each image takes two lines — `IMAGE_ID QW
//! QX QY QZ TX TY TZ CAMERA_ID NAME`, then the `POINTS2D[] as (X, Y, POINT3D_ID)` line, which is
//! read whatever it holds (it is empty for an image without observations). `POINT3D_ID` −1 is
//! "no 3-D point". Points: `POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)`.
//!
//! Camera models, to the engine's [`CameraModel`] (the inverse of
//! [`Camera::colmap_params`]): `SIMPLE_PINHOLE`, `PINHOLE`, `SIMPLE_RADIAL`, `RADIAL` and
//! `OPENCV` keep their parameters; `FULL_OPENCV` `fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6` becomes
//! [`CameraModel::RadialTangential`] `[fx, fy, cx, cy, 0, k1, k2, p1, p2, k3]` (its rational
//! terms `k4 k5 k6` must be 0); `OPENCV_FISHEYE` `fx fy cx cy k1 k2 k3 k4` becomes
//! [`CameraModel::Fisheye`] `[fx, fy, cx, cy, 0, k1, k2, k3, k4]`. Other COLMAP models are
//! errors.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{
    Camera, CameraModel, Pose, ReconImage, ReconPoint, Reconstruction, Value,
};

/// The COLMAP model names this reader maps onto engine models.
pub const SUPPORTED_MODELS: &str = "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, \
                                    FULL_OPENCV, OPENCV_FISHEYE";

/// One data line being parsed: its tokens and where it is, for error messages.
struct Line<'a> {
    file: &'a str,
    number: usize,
    tokens: std::str::SplitWhitespace<'a>,
}

impl<'a> Line<'a> {
    fn new(file: &'a str, number: usize, text: &'a str) -> Line<'a> {
        Line {
            file,
            number,
            tokens: text.split_whitespace(),
        }
    }

    /// `path:line: message`.
    fn error(&self, message: impl std::fmt::Display) -> String {
        format!("{}:{}: {message}", self.file, self.number)
    }

    fn token(&mut self, what: &str) -> Result<&'a str, String> {
        self.tokens
            .next()
            .ok_or_else(|| self.error(format!("missing {what}")))
    }

    fn parse<T: FromStr>(&mut self, what: &str, kind: &str) -> Result<T, String> {
        let t = self.token(what)?;
        t.parse()
            .map_err(|_| self.error(format!("{what} `{t}` is not {kind}")))
    }

    fn float(&mut self, what: &str) -> Result<f64, String> {
        let t = self.token(what)?;
        let v: f64 = t
            .parse()
            .map_err(|_| self.error(format!("{what} `{t}` is not a number")))?;
        if !v.is_finite() {
            return Err(self.error(format!("{what} `{t}` is not finite")));
        }
        Ok(v)
    }

    fn rest(&mut self) -> Vec<&'a str> {
        self.tokens.by_ref().collect()
    }
}

/// The data lines of a text: 1-based line numbers and contents, without comments and blanks.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l))
        .filter(|(_, l)| {
            let t = l.trim();
            !t.is_empty() && !t.starts_with('#')
        })
}

/// The engine camera for a COLMAP model name and its parameters, or an error message.
pub fn camera_from_colmap(
    model: &str,
    width: u32,
    height: u32,
    params: &[f64],
) -> Result<Camera, String> {
    let (engine_model, expected) = match model {
        "SIMPLE_PINHOLE" => (CameraModel::SimplePinhole, 3),
        "PINHOLE" => (CameraModel::Pinhole, 4),
        "SIMPLE_RADIAL" => (CameraModel::SimpleRadial, 4),
        "RADIAL" => (CameraModel::Radial, 5),
        "OPENCV" => (CameraModel::OpenCv, 8),
        "FULL_OPENCV" => (CameraModel::RadialTangential, 12),
        "OPENCV_FISHEYE" => (CameraModel::Fisheye, 8),
        other => {
            return Err(format!(
                "camera model `{other}` is not supported (supported: {SUPPORTED_MODELS})"
            ));
        }
    };
    if params.len() != expected {
        return Err(format!(
            "camera model {model} takes {expected} parameters, got {}",
            params.len()
        ));
    }
    let params = match engine_model {
        CameraModel::RadialTangential => {
            if params[9..].iter().any(|&k| k != 0.0) {
                return Err(format!(
                    "FULL_OPENCV with rational terms k4 k5 k6 = {} {} {} is not supported \
                     (they must be 0)",
                    params[9], params[10], params[11]
                ));
            }
            let mut p = params[..4].to_vec();
            p.push(0.0);
            p.extend_from_slice(&params[4..9]);
            p
        }
        CameraModel::Fisheye => {
            let mut p = params[..4].to_vec();
            p.push(0.0);
            p.extend_from_slice(&params[4..]);
            p
        }
        _ => params.to_vec(),
    };
    Ok(Camera {
        model: engine_model,
        width,
        height,
        params,
    })
}

/// Parses `cameras.txt`; `file` names it in errors.
pub fn parse_cameras(text: &str, file: &str) -> Result<BTreeMap<u32, Camera>, String> {
    let mut cameras = BTreeMap::new();
    for (number, content) in data_lines(text) {
        let mut line = Line::new(file, number, content);
        let id: u32 = line.parse("CAMERA_ID", "a non-negative integer")?;
        let model = line.token("MODEL")?;
        let width: u32 = line.parse("WIDTH", "a non-negative integer")?;
        let height: u32 = line.parse("HEIGHT", "a non-negative integer")?;
        let mut params = Vec::new();
        for k in 0.. {
            if line.tokens.clone().next().is_none() {
                break;
            }
            params.push(line.float(&format!("parameter {k}"))?);
        }
        let camera =
            camera_from_colmap(model, width, height, &params).map_err(|e| line.error(e))?;
        if cameras.insert(id, camera).is_some() {
            return Err(line.error(format!("camera {id} is defined twice")));
        }
    }
    Ok(cameras)
}

/// A quaternion `[w, x, y, z]` scaled to unit length (left as it is when already exactly
/// unit, so a written model reads back bit for bit); errors when zero.
fn unit_quaternion(q: [f64; 4]) -> Result<[f64; 4], String> {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(n > 0.0 && n.is_finite()) {
        return Err(format!(
            "quaternion {} {} {} {} has no direction (norm {n})",
            q[0], q[1], q[2], q[3]
        ));
    }
    Ok(if n == 1.0 { q } else { q.map(|v| v / n) })
}

/// Parses `images.txt`, checking camera ids against `cameras`; `file` names it in errors.
pub fn parse_images(
    text: &str,
    file: &str,
    cameras: &BTreeMap<u32, Camera>,
) -> Result<Vec<ReconImage>, String> {
    let mut images = Vec::new();
    let mut ids = HashSet::new();
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l));
    while let Some((number, content)) = lines.next() {
        let trimmed = content.trim();
        if trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let mut line = Line::new(file, number, trimmed);
        let id: u32 = line.parse("IMAGE_ID", "a non-negative integer")?;
        let mut q = [0.0; 4];
        for (v, what) in q.iter_mut().zip(["QW", "QX", "QY", "QZ"]) {
            *v = line.float(what)?;
        }
        let mut t = [0.0; 3];
        for (v, what) in t.iter_mut().zip(["TX", "TY", "TZ"]) {
            *v = line.float(what)?;
        }
        let camera_id: u32 = line.parse("CAMERA_ID", "a non-negative integer")?;
        // The name is the rest of the line, so names with spaces survive.
        let name = name_after_tokens(trimmed, 9);
        if name.is_empty() {
            return Err(line.error("missing NAME"));
        }
        let rotation = unit_quaternion(q).map_err(|e| line.error(e))?;
        if !cameras.contains_key(&camera_id) {
            return Err(line.error(format!(
                "image {id} refers to camera {camera_id}, which is not in cameras.txt"
            )));
        }
        if !ids.insert(id) {
            return Err(line.error(format!("image {id} is defined twice")));
        }
        let Some((number, content)) = lines.next() else {
            return Err(format!(
                "{file}:{number}: image {id} has no POINTS2D line (the file ends)"
            ));
        };
        let mut line = Line::new(file, number, content);
        let tokens = line.rest();
        if !tokens.len().is_multiple_of(3) {
            return Err(line.error(format!(
                "POINTS2D of image {id} has {} numbers, not a multiple of 3 (X Y POINT3D_ID)",
                tokens.len()
            )));
        }
        let mut points2d = Vec::with_capacity(tokens.len() / 3);
        for (k, triple) in tokens.chunks(3).enumerate() {
            let mut xy = [0.0; 2];
            for (v, (t, axis)) in xy.iter_mut().zip(triple.iter().zip(["X", "Y"])) {
                *v = Line::new(file, number, t).float(&format!("{axis} of 2-D point {k}"))?;
            }
            let point = match triple[2] {
                "-1" => None,
                t => Some(t.parse::<u64>().map_err(|_| {
                    line.error(format!(
                        "POINT3D_ID of 2-D point {k} `{t}` is neither -1 nor a non-negative \
                         integer"
                    ))
                })?),
            };
            points2d.push((xy, point));
        }
        images.push(ReconImage {
            id,
            camera_id,
            name: name.to_string(),
            camera_from_world: Pose {
                rotation,
                translation: t,
            },
            points2d,
        });
    }
    Ok(images)
}

/// What follows the first `n` whitespace-separated tokens of `line`, trimmed.
fn name_after_tokens(line: &str, n: usize) -> &str {
    let mut rest = line.trim_start();
    for _ in 0..n {
        let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
        rest = rest[end..].trim_start();
    }
    rest.trim_end()
}

/// Parses `points3D.txt`, checking every track entry against `images`; `file` names it in
/// errors.
pub fn parse_points(
    text: &str,
    file: &str,
    images: &[ReconImage],
) -> Result<Vec<ReconPoint>, String> {
    let sizes: HashMap<u32, usize> = images.iter().map(|i| (i.id, i.points2d.len())).collect();
    let mut points = Vec::new();
    let mut ids = HashSet::new();
    for (number, content) in data_lines(text) {
        let mut line = Line::new(file, number, content);
        let id: u64 = line.parse("POINT3D_ID", "a non-negative integer")?;
        let mut position = [0.0; 3];
        for (v, what) in position.iter_mut().zip(["X", "Y", "Z"]) {
            *v = line.float(what)?;
        }
        let mut color = [0u8; 3];
        for (v, what) in color.iter_mut().zip(["R", "G", "B"]) {
            *v = line.parse(what, "an integer 0..=255")?;
        }
        let error_px = line.float("ERROR")?;
        let tokens = line.rest();
        if !tokens.len().is_multiple_of(2) {
            return Err(line.error(format!(
                "TRACK of point {id} has {} numbers, not pairs (IMAGE_ID POINT2D_IDX)",
                tokens.len()
            )));
        }
        let mut track = Vec::with_capacity(tokens.len() / 2);
        for (k, pair) in tokens.chunks(2).enumerate() {
            let image: u32 = Line::new(file, number, pair[0]).parse(
                &format!("IMAGE_ID of track entry {k}"),
                "a non-negative integer",
            )?;
            let index: u32 = Line::new(file, number, pair[1]).parse(
                &format!("POINT2D_IDX of track entry {k}"),
                "a non-negative integer",
            )?;
            let Some(&size) = sizes.get(&image) else {
                return Err(line.error(format!(
                    "track entry {k} of point {id} refers to image {image}, which is not in \
                     images.txt"
                )));
            };
            if index as usize >= size {
                return Err(line.error(format!(
                    "track entry {k} of point {id}: POINT2D_IDX {index} is out of range \
                     (image {image} has {size} 2-D points)"
                )));
            }
            track.push((image, index));
        }
        if !ids.insert(id) {
            return Err(line.error(format!("point {id} is defined twice")));
        }
        points.push(ReconPoint {
            id,
            position,
            color,
            error_px,
            track,
        });
    }
    Ok(points)
}

/// Reads the COLMAP text model in `folder` (see the module documentation). Cameras, images and
/// points keep their file order.
pub fn read_colmap(folder: &Path) -> Result<Reconstruction, OpError> {
    let read = |name: &str| -> Result<(String, String), OpError> {
        let path = folder.join(name);
        let text = ocellus_engine::limits::read_text(&path).map_err(|e| OpError::io(&path, e))?;
        Ok((path.display().to_string(), text))
    };
    let (cameras_file, cameras_text) = read("cameras.txt")?;
    let (images_file, images_text) = read("images.txt")?;
    let (points_file, points_text) = read("points3D.txt")?;
    let cameras = parse_cameras(&cameras_text, &cameras_file).map_err(OpError::failed)?;
    let images = parse_images(&images_text, &images_file, &cameras).map_err(OpError::failed)?;
    let points = parse_points(&points_text, &points_file, &images).map_err(OpError::failed)?;
    Ok(Reconstruction {
        cameras,
        images,
        points,
    })
}

params! {
    /// Parameters of `io.read_colmap`.
    pub struct ReadColmapParams {
        /// The folder holding `cameras.txt`, `images.txt` and `points3D.txt`; relative paths
        /// resolve against the graph file's folder. Required.
        path: PathBuf = PathBuf::new(),
    }
}

/// `io.read_colmap`. See [`read_colmap`].
#[derive(Debug, Clone, PartialEq)]
pub struct ReadColmap {
    params: ReadColmapParams,
}

impl Op for ReadColmap {
    type Params = ReadColmapParams;
    const ID: &'static str = "io.read_colmap";
    const SUMMARY: &'static str =
        "Read a COLMAP text model (cameras.txt, images.txt, points3D.txt) into a reconstruction.";
    const DOC: &'static str = r#"
Reads the sparse model COLMAP writes with `model_converter --output_type TXT` (and Ocellus's
own `--emit` of a Reconstruction, which it reads back exactly) from the folder `path`:
- cameras.txt: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`;
- images.txt: two lines per image, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` (the
  camera_from_world pose; NAME is the rest of the line) and `POINTS2D[] as (X, Y, POINT3D_ID)`,
  which may be empty; POINT3D_ID -1 means none;
- points3D.txt: `POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)`.
Lines starting with `#` and blank lines are skipped (but the line after an image line is
always its POINTS2D line).

Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV as themselves;
FULL_OPENCV as the radial–tangential model with skew 0 (its rational terms k4 k5 k6 must be
0); OPENCV_FISHEYE as the fisheye model with skew 0. Any other model is an error naming it.

Checks, each failing with `file:line: message`: numbers parse and are finite, ids are unique,
every image's camera exists, every quaternion is non-zero (it is normalized), every track
entry names an existing image and a POINT2D_IDX within that image's 2-D points. Cameras,
images and points keep the files' order.

Example:
    "sparse": (op: "io.read_colmap", params: (path: "colmap/sparse/0")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "reconstruction",
            PortType::Reconstruction,
            "The cameras, posed images and 3-D points of the model.",
        )]
    }

    fn new(params: ReadColmapParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadColmap { params })
    }
}

impl Operator for ReadColmap {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let r = read_colmap(&self.params.path)?;
        Ok(Outputs::new().with("reconstruction", Value::Reconstruction(Arc::new(r))))
    }

    /// The three files' contents decide the result.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let mut all = Vec::new();
        for name in ["cameras.txt", "images.txt", "points3D.txt"] {
            let path = self.params.path.join(name);
            let bytes =
                ocellus_engine::limits::read_file(&path).map_err(|e| OpError::io(&path, e))?;
            all.extend_from_slice(&ocellus_engine::cache::content_hash(&bytes));
        }
        Ok(ocellus_engine::cache::content_hash(&all).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::emit::emit_value;

    /// A fresh temporary folder, removed when dropped.
    struct TempDir(PathBuf);

    impl TempDir {
        fn new(tag: &str) -> TempDir {
            let dir = std::env::temp_dir().join(format!(
                "ocellus-colmap-{tag}-{}-{:?}",
                std::process::id(),
                std::thread::current().id()
            ));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            TempDir(dir)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    /// Two cameras of different models (one written as FULL_OPENCV), three images (one
    /// without observations), three points; images and points in id order, as emit writes.
    fn model() -> Reconstruction {
        let mut cameras = BTreeMap::new();
        cameras.insert(
            1,
            Camera {
                model: CameraModel::SimpleRadial,
                width: 640,
                height: 480,
                params: vec![500.25, 320.0, 240.5, -0.03125],
            },
        );
        cameras.insert(
            4,
            Camera {
                model: CameraModel::RadialTangential,
                width: 1024,
                height: 768,
                params: vec![
                    800.0, 801.5, 512.0, 384.0, 0.0, 0.1, -0.02, 1e-3, -2e-4, 0.005,
                ],
            },
        );
        let images = vec![
            ReconImage {
                id: 1,
                camera_id: 1,
                name: "a.jpg".into(),
                camera_from_world: Pose::IDENTITY,
                points2d: vec![
                    ([1.5, 2.0], Some(7)),
                    ([3.0, 4.0], None),
                    ([5.0, 6.25], Some(9)),
                ],
            },
            ReconImage {
                id: 2,
                camera_id: 4,
                name: "views/b c.png".into(),
                camera_from_world: Pose {
                    rotation: [0.5, 0.5, -0.5, 0.5],
                    translation: [1.0, -2.0, 0.1],
                },
                points2d: vec![([10.0, 20.0], Some(7)), ([30.5, 40.0], Some(9))],
            },
            ReconImage {
                id: 5,
                camera_id: 1,
                name: "empty.jpg".into(),
                camera_from_world: Pose {
                    rotation: [0.0, 0.0, 1.0, 0.0],
                    translation: [0.0, 0.0, -3.75],
                },
                points2d: Vec::new(),
            },
        ];
        let points = vec![
            ReconPoint {
                id: 7,
                position: [1.0, 2.0, 3.0],
                color: [255, 128, 0],
                error_px: 0.75,
                track: vec![(1, 0), (2, 0)],
            },
            ReconPoint {
                id: 8,
                position: [-1.5, 0.0, 4.0e-7],
                color: [10, 20, 30],
                error_px: -1.0,
                track: Vec::new(),
            },
            ReconPoint {
                id: 9,
                position: [0.0, 0.0, 5.0],
                color: [0, 0, 255],
                error_px: 0.5,
                track: vec![(1, 2), (2, 1)],
            },
        ];
        Reconstruction {
            cameras,
            images,
            points,
        }
    }

    #[test]
    fn emit_then_read_round_trips() {
        let dir = TempDir::new("round");
        let r = model();
        emit_value(
            &dir.0,
            "sparse",
            &Value::Reconstruction(Arc::new(r.clone())),
        )
        .unwrap();
        let back = read_colmap(&dir.0.join("sparse")).unwrap();
        assert_eq!(back, r);
        // And through the operator.
        let op = ReadColmap::new(ReadColmapParams {
            path: dir.0.join("sparse"),
        })
        .unwrap();
        let ctx = RunContext {
            node: "sparse".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&[], &[])).unwrap();
        assert_eq!(
            out.take("reconstruction"),
            Some(Value::Reconstruction(Arc::new(r)))
        );
        assert!(op.fingerprint().is_ok());
    }

    #[test]
    fn every_model_maps_inverse_to_colmap_params() {
        let cases: [(CameraModel, Vec<f64>); 7] = [
            (CameraModel::SimplePinhole, vec![100.0, 1.0, 2.0]),
            (CameraModel::Pinhole, vec![100.0, 101.0, 1.0, 2.0]),
            (CameraModel::SimpleRadial, vec![100.0, 1.0, 2.0, 0.1]),
            (CameraModel::Radial, vec![100.0, 1.0, 2.0, 0.1, -0.2]),
            (
                CameraModel::OpenCv,
                vec![100.0, 101.0, 1.0, 2.0, 0.1, -0.2, 0.01, 0.02],
            ),
            (
                CameraModel::RadialTangential,
                vec![100.0, 101.0, 1.0, 2.0, 0.0, 0.1, -0.2, 0.01, 0.02, 0.03],
            ),
            (
                CameraModel::Fisheye,
                vec![100.0, 101.0, 1.0, 2.0, 0.0, 0.1, -0.2, 0.01, 0.02],
            ),
        ];
        for (model, params) in cases {
            let camera = Camera {
                model,
                width: 10,
                height: 20,
                params,
            };
            let back =
                camera_from_colmap(model.colmap_name(), 10, 20, &camera.colmap_params()).unwrap();
            assert_eq!(back, camera, "{model:?}");
        }
        // FULL_OPENCV's parameter order, by hand.
        let c = camera_from_colmap(
            "FULL_OPENCV",
            1,
            1,
            &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 0.0, 0.0, 0.0],
        )
        .unwrap();
        assert_eq!(c.params, [1.0, 2.0, 3.0, 4.0, 0.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
        let c = camera_from_colmap(
            "OPENCV_FISHEYE",
            1,
            1,
            &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0],
        )
        .unwrap();
        assert_eq!(c.params, [1.0, 2.0, 3.0, 4.0, 0.0, 5.0, 6.0, 7.0, 8.0]);
    }

    #[test]
    fn comments_blank_lines_and_quaternion_normalization() {
        let cameras = "# a comment\n\n1 PINHOLE 10 10 5 5 5 5\n   \n";
        let cams = parse_cameras(cameras, "cameras.txt").unwrap();
        assert_eq!(cams[&1].params, [5.0, 5.0, 5.0, 5.0]);
        let images =
            "# header\n\n1 2 0 0 0 1 2 3 1 x.png\n\n# between\n2 0 0 0 -4 0 0 0 1 y.png\n1 1 -1\n";
        let imgs = parse_images(images, "images.txt", &cams).unwrap();
        assert_eq!(imgs.len(), 2);
        assert_eq!(imgs[0].camera_from_world.rotation, [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(imgs[0].camera_from_world.translation, [1.0, 2.0, 3.0]);
        assert!(imgs[0].points2d.is_empty());
        assert_eq!(imgs[1].camera_from_world.rotation, [0.0, 0.0, 0.0, -1.0]);
        assert_eq!(imgs[1].points2d, [([1.0, 1.0], None)]);
        let pts = parse_points("# c\n3 0 0 0 1 2 3 0.5 2 0\n", "points3D.txt", &imgs).unwrap();
        assert_eq!(pts[0].track, [(2, 0)]);
        assert_eq!(pts[0].color, [1, 2, 3]);
    }

    #[test]
    fn malformed_files_name_file_and_line() {
        let cam = "1 PINHOLE 10 10 5 5 5 5\n";
        let cams = parse_cameras(cam, "c").unwrap();
        let camera_cases = [
            (
                "1 FOV 10 10 5 5 5 5 0.1\n",
                "c:1: camera model `FOV` is not supported",
            ),
            (
                "# x\n1 PINHOLE 10 10 5 5 5\n",
                "c:2: camera model PINHOLE takes 4 parameters, got 3",
            ),
            (
                "1 PINHOLE 10 10 5 5 5 5\n1 PINHOLE 10 10 5 5 5 5\n",
                "c:2: camera 1 is defined twice",
            ),
            (
                "1 PINHOLE -10 10 5 5 5 5\n",
                "c:1: WIDTH `-10` is not a non-negative integer",
            ),
            (
                "1 PINHOLE 10 10 5 nan 5 5\n",
                "c:1: parameter 1 `nan` is not finite",
            ),
            ("1 PINHOLE 10\n", "c:1: missing HEIGHT"),
            (
                "1 FULL_OPENCV 1 1 1 1 1 1 0 0 0 0 0 0.5 0 0\n",
                "c:1: FULL_OPENCV with rational terms",
            ),
        ];
        for (text, expected) in camera_cases {
            let err = parse_cameras(text, "c").unwrap_err();
            assert!(err.contains(expected), "{text:?}: {err}");
        }
        let image_cases = [
            (
                "1 1 0 0 0 0 0 0 2 a.png\n\n",
                "i:1: image 1 refers to camera 2",
            ),
            (
                "1 0 0 0 0 0 0 0 1 a.png\n\n",
                "i:1: quaternion 0 0 0 0 has no direction",
            ),
            (
                "1 1 0 0 inf 0 0 0 1 a.png\n\n",
                "i:1: QZ `inf` is not finite",
            ),
            ("1 1 0 0 0 0 0 0 1\n\n", "i:1: missing NAME"),
            (
                "#\n1 1 0 0 0 0 0 0 1 a.png",
                "i:2: image 1 has no POINTS2D line",
            ),
            (
                "1 1 0 0 0 0 0 0 1 a.png\n1 2\n",
                "i:2: POINTS2D of image 1 has 2 numbers",
            ),
            (
                "1 1 0 0 0 0 0 0 1 a.png\n1 2 -2\n",
                "i:2: POINT3D_ID of 2-D point 0 `-2`",
            ),
            (
                "1 1 0 0 0 0 0 0 1 a.png\n1 x 3\n",
                "i:2: Y of 2-D point 0 `x` is not a number",
            ),
            (
                "1 1 0 0 0 0 0 0 1 a.png\n\n1 1 0 0 0 0 0 0 1 b.png\n\n",
                "i:3: image 1 is defined twice",
            ),
        ];
        for (text, expected) in image_cases {
            let err = parse_images(text, "i", &cams).unwrap_err();
            assert!(err.contains(expected), "{text:?}: {err}");
        }
        let imgs = parse_images("1 1 0 0 0 0 0 0 1 a.png\n0 0 4 1 1 4\n", "i", &cams).unwrap();
        let point_cases = [
            (
                "4 0 0 0 1 2 3 0.5 1 2\n",
                "p:1: track entry 0 of point 4: POINT2D_IDX 2 is out of range",
            ),
            (
                "4 0 0 0 1 2 3 0.5 3 0\n",
                "p:1: track entry 0 of point 4 refers to image 3",
            ),
            (
                "4 0 0 0 1 2 3 0.5 1\n",
                "p:1: TRACK of point 4 has 1 numbers",
            ),
            (
                "4 0 0 0 1 256 3 0.5\n",
                "p:1: G `256` is not an integer 0..=255",
            ),
            ("4 0 NaN 0 1 2 3 0.5\n", "p:1: Y `NaN` is not finite"),
            ("4 0 0 0 1 2 3\n", "p:1: missing ERROR"),
            (
                "4 0 0 0 1 2 3 0.5\n#\n4 0 0 0 1 2 3 0.5\n",
                "p:3: point 4 is defined twice",
            ),
            ("-4 0 0 0 1 2 3 0.5\n", "p:1: POINT3D_ID `-4`"),
        ];
        for (text, expected) in point_cases {
            let err = parse_points(text, "p", &imgs).unwrap_err();
            assert!(err.contains(expected), "{text:?}: {err}");
        }
    }

    #[test]
    fn missing_files_and_params() {
        assert!(ReadColmap::new(ReadColmapParams::default()).is_err());
        let dir = TempDir::new("missing");
        let err = read_colmap(&dir.0).unwrap_err().to_string();
        assert!(err.contains("cameras.txt"), "{err}");
    }
}
