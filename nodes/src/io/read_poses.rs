//! `io.read_poses`: ground-truth cameras in the Middlebury multi-view format (`NAME_par.txt`,
//! Seitz, Curless, Diebel, Scharstein & Szeliski, "A comparison and evaluation of multi-view
//! stereo reconstruction algorithms", CVPR 2006).
//!
//! The file holds the number of images, then one line per image: `name k11 k12 k13 k21 k22 k23
//! k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3`, with `x ~ K [R | t] X`. So
//! `(R, t)` is camera_from_world and `K` a pinhole matrix with skew `k12`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::Matrix3;
use ocellus_engine::image_io::{DecodeLimits, read_image};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Camera, Distortion, Intrinsics, Pose, Value};

use crate::geometry::pose_util::nearest_rotation;

/// Largest entry of `|RᵀR − I|` accepted for a rotation before it is re-orthonormalized.
pub const ROTATION_TOLERANCE: f64 = 1e-6;

/// Largest `|k21|`, `|k31|`, `|k32|` accepted, relative to `|k33|` (K is upper triangular).
const K_LOWER_TOLERANCE: f64 = 1e-9;

/// One camera of a par file.
#[derive(Debug, Clone, PartialEq)]
pub struct ParCamera {
    /// The image file name, as written.
    pub name: String,
    /// The pinhole matrix, normalized so that `K[2][2] = 1`.
    pub intrinsics: Intrinsics,
    /// camera_from_world, with `R` re-orthonormalized.
    pub camera_from_world: Pose,
}

/// Parses a par file's text; errors are `file:line: message`.
pub fn parse_par(text: &str, file: &str) -> Result<Vec<ParCamera>, String> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l))
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((number, first)) = lines.next() else {
        return Err(format!(
            "{file}:1: empty file: expected the number of images"
        ));
    };
    let count: usize = first.trim().parse().map_err(|_| {
        format!(
            "{file}:{number}: the number of images `{}` is not a non-negative integer",
            first.trim()
        )
    })?;
    let mut cameras = Vec::with_capacity(count.min(text.len() / 22 + 1));
    let mut last = number;
    for (number, line) in lines {
        last = number;
        let at = |m: String| format!("{file}:{number}: {m}");
        if cameras.len() == count {
            return Err(at(format!(
                "more image lines than the {count} the first line announces"
            )));
        }
        let tokens: Vec<&str> = line.split_whitespace().collect();
        if tokens.len() != 22 {
            return Err(at(format!(
                "expected a name and 21 numbers (K, R, t), got {} fields",
                tokens.len()
            )));
        }
        let mut v = [0.0; 21];
        for (k, (x, t)) in v.iter_mut().zip(&tokens[1..]).enumerate() {
            *x = t
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| at(format!("number {} `{t}` is not a finite number", k + 1)))?;
        }
        let intrinsics = intrinsics_from_k(&v[..9]).map_err(at)?;
        let r = Matrix3::from_row_slice(&v[9..18]);
        let rotation = checked_rotation(&r).map_err(at)?;
        let rotation: [f64; 9] = std::array::from_fn(|k| rotation[(k / 3, k % 3)]);
        cameras.push(ParCamera {
            name: tokens[0].to_string(),
            intrinsics,
            camera_from_world: Pose::from_rotation_matrix(&rotation, [v[18], v[19], v[20]]),
        });
    }
    if cameras.len() < count {
        return Err(format!(
            "{file}:{last}: the first line announces {count} images, the file has {}",
            cameras.len()
        ));
    }
    Ok(cameras)
}

/// The intrinsics of a row-major K, which must be upper triangular with `k33 ≠ 0` (it is
/// divided by `k33`) and positive focal lengths.
fn intrinsics_from_k(k: &[f64]) -> Result<Intrinsics, String> {
    let k33 = k[8];
    if k33 == 0.0 {
        return Err("K[3][3] is 0".into());
    }
    let lower = k[3].abs().max(k[6].abs()).max(k[7].abs());
    if lower > K_LOWER_TOLERANCE * k33.abs() {
        return Err(format!(
            "K is not upper triangular (k21 {}, k31 {}, k32 {})",
            k[3], k[6], k[7]
        ));
    }
    let (fx, fy) = (k[0] / k33, k[4] / k33);
    if !(fx > 0.0 && fy > 0.0) {
        return Err(format!(
            "K's focal lengths must be positive, got {fx} and {fy}"
        ));
    }
    Ok(Intrinsics {
        fx,
        fy,
        cx: k[2] / k33,
        cy: k[5] / k33,
        skew: k[1] / k33,
    })
}

/// `r` re-orthonormalized by SVD, after checking it is a rotation within
/// [`ROTATION_TOLERANCE`].
fn checked_rotation(r: &Matrix3<f64>) -> Result<Matrix3<f64>, String> {
    if r.determinant() < 0.0 {
        return Err("R has a negative determinant (a reflection, not a rotation)".into());
    }
    let off = (r.transpose() * r - Matrix3::identity()).amax();
    if off.is_nan() || off > ROTATION_TOLERANCE {
        return Err(format!(
            "R is not orthonormal: |RᵀR − I| reaches {off:.3e} (tolerance {ROTATION_TOLERANCE:e})"
        ));
    }
    nearest_rotation(r).ok_or_else(|| "R cannot be re-orthonormalized".to_string())
}

params! {
    /// Parameters of `io.read_poses`.
    pub struct ReadPosesParams {
        /// The par file (`NAME_par.txt`); relative paths resolve against the graph file's
        /// folder. Required.
        path: PathBuf = PathBuf::new(),
        /// Image width for the cameras; 0 (the default) reads it from each line's image file,
        /// next to the par file.
        width: u32 = 0 => [unit = "px"],
        /// Image height for the cameras; 0 (the default) reads it from each line's image file,
        /// next to the par file.
        height: u32 = 0 => [unit = "px"],
    }
}

/// `io.read_poses`. See [`parse_par`].
#[derive(Debug, Clone, PartialEq)]
pub struct ReadPoses {
    params: ReadPosesParams,
}

impl ReadPoses {
    /// The size of the image `name` names, read next to the par file.
    fn image_size(&self, name: &str) -> Result<(u32, u32), OpError> {
        let folder = self.params.path.parent().unwrap_or(Path::new(""));
        let image = folder.join(name);
        if !image.is_file() {
            return Err(OpError::failed(format!(
                "{}: image {} not found: set `width` and `height`, or put the images next to \
                 the par file",
                self.params.path.display(),
                image.display()
            )));
        }
        if let Ok(size) = image::image_dimensions(&image) {
            return Ok(size);
        }
        let decoded = read_image(&image, &DecodeLimits::default())
            .map_err(|e| OpError::failed(format!("{}: {e}", image.display())))?;
        Ok((decoded.width() as u32, decoded.height() as u32))
    }
}

impl Op for ReadPoses {
    type Params = ReadPosesParams;
    const ID: &'static str = "io.read_poses";
    const SUMMARY: &'static str =
        "Read ground-truth cameras and poses in the Middlebury multi-view format (NAME_par.txt).";
    const DOC: &'static str = r#"
Reads the camera file of the Middlebury multi-view stereo data sets (Seitz et al., "A
comparison and evaluation of multi-view stereo reconstruction algorithms", CVPR 2006): the
number of images, then per image
`name k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3`,
where a world point X projects to x ~ K·[R | t]·X. Blank lines are skipped.

Outputs, one element per line in file order: `cameras`, pinhole cameras with fx = k11,
skew = k12, cx = k13, fy = k22, cy = k23 (K divided by k33; it must be upper triangular with
positive focal lengths) and no distortion, with size `width` × `height` — or, when those are
0, the size of the image file named on the line, looked up next to the par file; `poses`, the
camera_from_world (R, t), R re-orthonormalized by SVD after checking it is a rotation within
1e-6 (|RᵀR − I| per entry; a negative determinant is an error); `names`, the image names.
K is taken as written (no half-pixel shift).

Errors name `file:line`: a count that does not match the lines, a line without 22 fields,
a non-finite number, K or R as above.

Example:
    "truth": (op: "io.read_poses", params: (path: "temple/templeSR_par.txt")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "cameras",
                PortType::Camera.list_of(),
                "Pinhole camera (with skew, no distortion) per image, in file order.",
            ),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "camera_from_world per image, in file order.",
            ),
            PortSpec::new(
                "names",
                PortType::Text.list_of(),
                "Image name per image, as written in the file.",
            ),
        ]
    }

    fn new(params: ReadPosesParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        if (params.width == 0) != (params.height == 0) {
            return Err("set both `width` and `height`, or neither".into());
        }
        Ok(ReadPoses { params })
    }
}

impl Operator for ReadPoses {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let path = &self.params.path;
        let text = ocellus_engine::limits::read_text(path).map_err(|e| OpError::io(path, e))?;
        let parsed = parse_par(&text, &path.display().to_string()).map_err(OpError::failed)?;
        let (mut cameras, mut poses, mut names) = (Vec::new(), Vec::new(), Vec::new());
        for c in parsed {
            let (width, height) = if self.params.width > 0 {
                (self.params.width, self.params.height)
            } else {
                self.image_size(&c.name)?
            };
            let camera = Camera::from_parts(width, height, c.intrinsics, Distortion::None);
            cameras.push(Value::Camera(Arc::new(camera)));
            poses.push(Value::Pose(c.camera_from_world));
            names.push(Value::Text(c.name.as_str().into()));
        }
        Ok(Outputs::new()
            .with("cameras", Value::list(PortType::Camera, cameras))
            .with("poses", Value::list(PortType::Pose, poses))
            .with("names", Value::list(PortType::Text, names)))
    }

    /// The par file's contents decide the result (and, without `width`/`height`, the image
    /// files' sizes, which are read at run time).
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let path = &self.params.path;
        let bytes = ocellus_engine::limits::read_file(path).map_err(|e| OpError::io(path, e))?;
        Ok(ocellus_engine::cache::content_hash(&bytes).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::CameraModel;

    /// A rotation of 90° about z, and one of 180° about x.
    const TWO: &str = "2\n\
        a.png 500 0.5 320 0 510 240 0 0 1 0 -1 0 1 0 0 0 0 1 1 2 3\n\
        \n\
        b.png 1000 0 160 0 1000 120 0 0 2 1 0 0 0 -1 0 0 0 -1 -0.5 0 4\n";

    #[test]
    fn parses_two_cameras() {
        let cams = parse_par(TWO, "t_par.txt").unwrap();
        assert_eq!(cams.len(), 2);
        assert_eq!(cams[0].name, "a.png");
        assert_eq!(
            cams[0].intrinsics,
            Intrinsics {
                fx: 500.0,
                fy: 510.0,
                cx: 320.0,
                cy: 240.0,
                skew: 0.5
            }
        );
        // K is divided by k33 = 2.
        assert_eq!(cams[1].intrinsics.fx, 500.0);
        assert_eq!(cams[1].intrinsics.cy, 60.0);
        let r = cams[0].camera_from_world.rotation_matrix();
        let expected = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        for (a, b) in r.iter().zip(&expected) {
            assert!((a - b).abs() < 1e-15, "{r:?}");
        }
        assert_eq!(cams[0].camera_from_world.translation, [1.0, 2.0, 3.0]);
        let r = cams[1].camera_from_world.rotation_matrix();
        let expected = [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0];
        for (a, b) in r.iter().zip(&expected) {
            assert!((a - b).abs() < 1e-15, "{r:?}");
        }
    }

    #[test]
    fn nearly_orthonormal_rotations_are_cleaned() {
        let e = 1e-8;
        let text = format!(
            "1\nx.png 1 0 0 0 1 0 0 0 1 {} 0 0 0 1 0 0 0 1 0 0 0\n",
            1.0 + e
        );
        let cams = parse_par(&text, "f").unwrap();
        assert_eq!(cams[0].camera_from_world.rotation, [1.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn errors_name_file_and_line() {
        let cases = [
            ("", "f:1: empty file"),
            ("two\n", "f:1: the number of images `two`"),
            (
                "1\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0\n",
                "f:2: expected a name and 21",
            ),
            (
                "1\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 nan\n",
                "f:2: number 21 `nan`",
            ),
            (
                "1\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 -1 0 0 0\n",
                "f:2: R has a negative determinant",
            ),
            (
                "1\na.png 1 0 0 0 1 0 0 0 1 1.001 0 0 0 1 0 0 0 1 0 0 0\n",
                "f:2: R is not orthonormal",
            ),
            (
                "1\na.png 1 0 0 0.5 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 0\n",
                "f:2: K is not upper triangular",
            ),
            (
                "1\na.png -1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 0\n",
                "f:2: K's focal lengths must be positive",
            ),
            (
                "2\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 0\n",
                "f:2: the first line announces 2 images, the file has 1",
            ),
            (
                "0\na.png 1 0 0 0 1 0 0 0 1 1 0 0 0 1 0 0 0 1 0 0 0\n",
                "f:2: more image lines than the 0",
            ),
        ];
        for (text, expected) in cases {
            let err = parse_par(text, "f").unwrap_err();
            assert!(err.contains(expected), "{text:?}: {err}");
        }
    }

    fn temp_file(tag: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "ocellus-poses-{tag}-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t_par.txt");
        std::fs::write(&path, text).unwrap();
        path
    }

    fn ctx() -> RunContext {
        RunContext {
            node: "truth".into(),
            threads: 1,
            element: None,
        }
    }

    #[test]
    fn op_outputs_lists_and_sizes() {
        let path = temp_file("op", TWO);
        let op = ReadPoses::new(ReadPosesParams {
            path: path.clone(),
            width: 640,
            height: 480,
        })
        .unwrap();
        let mut out = op.run(&ctx(), &Inputs::new(&[], &[])).unwrap();
        let Some(Value::List(cameras)) = out.take("cameras") else {
            panic!("expected cameras");
        };
        let Value::Camera(c) = &cameras.items[0] else {
            panic!("expected a camera");
        };
        assert_eq!(c.model, CameraModel::RadialTangential);
        assert_eq!((c.width, c.height), (640, 480));
        assert_eq!(
            c.params,
            [500.0, 510.0, 320.0, 240.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0]
        );
        let Some(Value::List(names)) = out.take("names") else {
            panic!("expected names");
        };
        assert_eq!(
            names.items,
            [Value::Text("a.png".into()), Value::Text("b.png".into())]
        );
        let Some(Value::List(poses)) = out.take("poses") else {
            panic!("expected poses");
        };
        assert_eq!(poses.items.len(), 2);

        // Without a size, the images are looked up next to the par file.
        let sized = ReadPoses::new(ReadPosesParams {
            path: path.clone(),
            width: 0,
            height: 0,
        })
        .unwrap();
        let err = sized
            .run(&ctx(), &Inputs::new(&[], &[]))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("a.png not found") && err.contains("`width`"),
            "{err}"
        );
        let folder = path.parent().unwrap();
        for (name, w) in [("a.png", 3), ("b.png", 5)] {
            let image = ocellus_engine::value::Image::from_u8(
                w,
                2,
                ocellus_engine::value::Channels::Gray,
                vec![0; w * 2],
            )
            .unwrap();
            ocellus_engine::image_io::write_image(&folder.join(name), &image).unwrap();
        }
        let mut out = sized.run(&ctx(), &Inputs::new(&[], &[])).unwrap();
        let Some(Value::List(cameras)) = out.take("cameras") else {
            panic!("expected cameras");
        };
        let sizes: Vec<(u32, u32)> = cameras
            .items
            .iter()
            .map(|c| match c {
                Value::Camera(c) => (c.width, c.height),
                _ => panic!("expected cameras"),
            })
            .collect();
        assert_eq!(sizes, [(3, 2), (5, 2)]);
        let _ = std::fs::remove_dir_all(folder);
        assert!(
            ReadPoses::new(ReadPosesParams {
                path,
                width: 10,
                height: 0
            })
            .is_err()
        );
    }
}
