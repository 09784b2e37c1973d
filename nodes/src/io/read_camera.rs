//! `io.read_camera`: read camera intrinsics from the JSON file that `--emit` writes for a
//! `Camera` output (`{"width","height","fx","fy","cx","cy","skew","distortion":D}`), so a
//! calibration saved by one graph feeds another. Parsing is the engine's
//! [`camera_from_json`](ocellus_engine::emit::camera_from_json), the inverse of the emitter.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_engine::emit::camera_from_json;
use ocellus_engine::value::Camera;
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

ocellus_engine::params! {
    /// Parameters of [`ReadCamera`].
    pub struct ReadCameraParams {
        /// The camera JSON file; relative paths resolve against the graph file's folder.
        /// Required.
        path: PathBuf = PathBuf::new(),
    }
}

/// Reads and parses a camera file; errors name the file.
pub fn read_camera(path: &Path) -> Result<Camera, OpError> {
    let text = ocellus_engine::limits::read_text(path).map_err(|e| OpError::io(path, e))?;
    camera_from_json(&text).map_err(|e| OpError::failed(format!("{}: {e}", path.display())))
}

/// `io.read_camera`. See [`read_camera`].
pub struct ReadCamera {
    params: ReadCameraParams,
}

impl Op for ReadCamera {
    type Params = ReadCameraParams;
    const ID: &'static str = "io.read_camera";
    const SUMMARY: &'static str = "Read camera intrinsics from the JSON file `--emit` writes.";
    const DOC: &'static str = r#"
Reads a camera in the format `ocellus run --emit` writes for Camera outputs:
`{"width","height","fx","fy","cx","cy","skew","distortion":D}` with D one of
`{"model":"radial_tangential","k1","k2","p1","p2","k3"}`, `{"model":"fisheye","k1","k2","k3","k4"}`
or `{"model":"none"}` (OpenCV's coefficient names and order). Reading an emitted camera and
emitting it again gives the same file. Unknown or missing keys, null/non-finite numbers,
focal lengths ≤ 0 and a zero image size are errors naming the file.

Output `camera`: "none" with zero skew gives a pinhole camera, otherwise the full
radial–tangential (OpenCV `FULL_OPENCV` layout with skew) or fisheye model.

Example:
    "camera": (op: "io.read_camera", params: (path: "data/two_view_camera.json")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "camera",
            PortType::Camera,
            "The camera intrinsics and lens distortion.",
        )]
    }

    fn new(params: ReadCameraParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadCamera { params })
    }
}

impl Operator for ReadCamera {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let camera = read_camera(&self.params.path)?;
        Ok(Outputs::new().with("camera", Value::Camera(Arc::new(camera))))
    }

    /// The file's contents decide the result, so they are part of the cache key.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let bytes = ocellus_engine::limits::read_file(&self.params.path)
            .map_err(|e| OpError::io(&self.params.path, e))?;
        Ok(ocellus_engine::cache::content_hash(&bytes).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::emit::emit_value;
    use ocellus_engine::value::{Distortion, Intrinsics};

    fn scratch(tag: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("ocellus-read-camera-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn run(path: &Path) -> Result<Camera, OpError> {
        let op = ReadCamera::new(ReadCameraParams {
            path: path.to_path_buf(),
        })
        .unwrap();
        let ctx = RunContext {
            node: "camera".into(),
            threads: 1,
            element: None,
        };
        let specs = ReadCamera::inputs();
        let mut out = op.run(&ctx, &Inputs::new(&specs, &[]))?;
        match out.take("camera") {
            Some(Value::Camera(c)) => Ok((*c).clone()),
            _ => panic!("no camera"),
        }
    }

    #[test]
    fn emitted_camera_reads_back() {
        let dir = scratch("round");
        let camera = Camera::from_parts(
            640,
            480,
            Intrinsics {
                fx: 520.5,
                fy: 519.25,
                cx: 321.0,
                cy: 239.5,
                skew: 0.0,
            },
            Distortion::RadialTangential([-0.1, 0.02, 0.001, -0.002, 0.0]),
        );
        let files = emit_value(&dir, "cam", &Value::Camera(Arc::new(camera.clone()))).unwrap();
        let back = run(&files[0]).unwrap();
        assert_eq!(back, camera);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn bad_files_are_clear_errors() {
        let dir = scratch("bad");
        let missing = run(&dir.join("none.json")).unwrap_err().to_string();
        assert!(missing.contains("none.json"), "{missing}");
        let path = dir.join("bad.json");
        std::fs::write(&path, "{\"width\": 640}").unwrap();
        let e = run(&path).unwrap_err().to_string();
        assert!(e.contains("bad.json") && e.contains("missing field"), "{e}");
        std::fs::write(&path, "[1, 2]").unwrap();
        assert!(run(&path).is_err());
        assert!(
            ReadCamera::new(ReadCameraParams {
                path: PathBuf::new()
            })
            .is_err()
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
