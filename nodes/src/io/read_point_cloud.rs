//! `io.read_point_cloud`: read a point cloud from a PLY file (ASCII or binary).
//!
//! The file is parsed by [`parse_ply`] of `io.read_mesh`, so every PLY feature, limit and error
//! of that reader applies (any scalar type, either byte order, unknown elements and properties
//! skipped, hostile counts rejected before allocation, errors naming the line or byte). The
//! `vertex` element gives the points: `x y z`, optional `nx ny nz` (normalised; a zero normal is
//! an error) and optional `red green blue`. A `face` element, if any, is read and ignored.
//!
//! Colors: a [`PointCloud`] holds sRGB bytes, as `--emit` writes them. The mesh reader decodes
//! integer colors (divided by the type's maximum) with the sRGB curve to linear; they are encoded
//! back here and rounded, which gives every `uchar` value back exactly. Float colors are taken as
//! linear 0..1, as the mesh reader does, and encoded the same way (clamped).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_engine::value::PointCloud;
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use super::read_mesh::parse_ply;

/// Linear RGB → sRGB byte (clamped to 0..=1, NaN → 0), the engine emitter's encoding.
fn srgb_byte(c: f32) -> u8 {
    let c = if c.is_nan() { 0.0 } else { f64::from(c) };
    let encoded = if c >= 1.0 {
        1.0
    } else if c <= 0.003_130_8 {
        12.92 * c.max(0.0)
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (encoded * 255.0).round().clamp(0.0, 255.0) as u8
}

/// Parses a PLY point cloud (see the [module documentation](self)).
pub fn parse_point_cloud(bytes: &[u8]) -> Result<PointCloud, super::read_mesh::MeshError> {
    let mesh = parse_ply(bytes)?;
    Ok(PointCloud {
        colors: mesh
            .colors
            .map(|c| c.iter().map(|rgb| rgb.map(srgb_byte)).collect()),
        normals: mesh.normals,
        positions: mesh.positions,
    })
}

/// Reads and parses a PLY point cloud file.
pub fn read_point_cloud(path: &Path) -> Result<PointCloud, OpError> {
    let bytes = ocellus_engine::limits::read_file(path).map_err(|e| OpError::io(path, e))?;
    parse_point_cloud(&bytes).map_err(|e| OpError::failed(format!("{}: {e}", path.display())))
}

ocellus_engine::params! {
    /// Parameters of [`ReadPointCloud`].
    pub struct ReadPointCloudParams {
        /// The point cloud file, `.ply`; relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
    }
}

/// `io.read_point_cloud`. See [`parse_point_cloud`].
pub struct ReadPointCloud {
    params: ReadPointCloudParams,
}

impl Op for ReadPointCloud {
    type Params = ReadPointCloudParams;
    const ID: &'static str = "io.read_point_cloud";
    const SUMMARY: &'static str =
        "Read a point cloud (positions, optional normals and colors) from a PLY file.";
    const DOC: &'static str = r#"
Reads the `vertex` element of a PLY file (Turk, Stanford 1994; ascii, binary_little_endian or
binary_big_endian 1.0, any scalar types) as a point cloud: `x y z`, optional `nx ny nz`
(normalised) and optional `red green blue`. Other elements (faces included) and properties
are skipped. The parser is io.read_mesh's: malformed files are errors naming the line or byte
offset (bad numbers, NaN/Inf, zero normals, truncation, counts larger than the file).

Colors come out as sRGB bytes: integer colors are the file's values (scaled to 0..255 for
wider types), float colors are taken as linear 0..1 and sRGB-encoded. Files written by
`--emit` (binary PLY point clouds) read back exactly.

Example:
    "points": (op: "io.read_point_cloud", params: (path: "data/poisson_points.ply")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "cloud",
            PortType::PointCloud,
            "The points, with the file's normals and colors when it has them.",
        )]
    }

    fn new(params: ReadPointCloudParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        let ply = params
            .path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
        if !ply {
            return Err(format!(
                "`{}`: unknown point cloud format; the file name must end in .ply",
                params.path.display()
            ));
        }
        Ok(ReadPointCloud { params })
    }
}

impl Operator for ReadPointCloud {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = read_point_cloud(&self.params.path)?;
        Ok(Outputs::new().with("cloud", Value::PointCloud(Arc::new(cloud))))
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
    use crate::io::read_mesh::MeshError;
    use ocellus_engine::emit::emit_value;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "ocellus-read-point-cloud-{}-{name}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn ascii_with_normals_and_colors() {
        let text = "ply\nformat ascii 1.0\ncomment two points\nelement vertex 2\n\
            property float x\nproperty float y\nproperty float z\n\
            property float nx\nproperty float ny\nproperty float nz\n\
            property uchar red\nproperty uchar green\nproperty uchar blue\n\
            property float quality\nend_header\n\
            1 2 3 0 0 2 255 0 7 0.5\n-1.5 0 1e3 3 4 0 12 128 200 1\n";
        let c = parse_point_cloud(text.as_bytes()).unwrap();
        assert_eq!(c.positions, vec![[1.0, 2.0, 3.0], [-1.5, 0.0, 1000.0]]);
        assert_eq!(c.normals, Some(vec![[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]]));
        assert_eq!(c.colors, Some(vec![[255, 0, 7], [12, 128, 200]]));
    }

    #[test]
    fn every_byte_color_reads_back_exactly() {
        // One point per byte value, written by the engine's emitter (binary little endian).
        let cloud = PointCloud {
            positions: (0..256).map(|i| [i as f32, 0.5, -2.0]).collect(),
            colors: Some((0..256).map(|i| [i as u8, 255 - i as u8, 3]).collect()),
            normals: Some((0..256).map(|_| [0.0, 1.0, 0.0]).collect()),
        };
        let dir = scratch("bytes");
        let files = emit_value(&dir, "pts", &Value::PointCloud(Arc::new(cloud.clone()))).unwrap();
        let back = read_point_cloud(&files[0]).unwrap();
        assert_eq!(back, cloud);
        let plain = PointCloud {
            positions: vec![[1.0, 2.0, 3.0]],
            ..PointCloud::default()
        };
        let files = emit_value(&dir, "plain", &Value::PointCloud(Arc::new(plain.clone()))).unwrap();
        assert_eq!(read_point_cloud(&files[0]).unwrap(), plain);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn big_endian_doubles_and_faces_ignored() {
        let mut bytes = b"ply\nformat binary_big_endian 1.0\nelement vertex 1\n\
            property double x\nproperty double y\nproperty double z\n\
            element face 1\nproperty list uchar int vertex_indices\nend_header\n"
            .to_vec();
        for v in [0.25f64, -4.0, 8.5] {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        bytes.push(3);
        for i in [0i32, 0, 0] {
            bytes.extend_from_slice(&i.to_be_bytes());
        }
        let c = parse_point_cloud(&bytes).unwrap();
        assert_eq!(c.positions, vec![[0.25, -4.0, 8.5]]);
        assert_eq!((c.normals, c.colors), (None, None));
    }

    #[test]
    fn bad_files_are_clear_errors() {
        let truncated = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n\
            property float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0";
        assert!(matches!(
            parse_point_cloud(truncated),
            Err(MeshError::CountExceedsData { .. })
        ));
        let nan = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
            property float z\nend_header\n1 nan 2\n";
        let e = parse_point_cloud(nan.as_bytes()).unwrap_err();
        assert_eq!(
            e.location(),
            Some(crate::io::read_mesh::Location::Line(8)),
            "{e}"
        );
        let zero = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
            property float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
            end_header\n1 2 3 0 0 0\n";
        assert!(matches!(
            parse_point_cloud(zero.as_bytes()),
            Err(MeshError::ZeroNormal { .. })
        ));
        assert!(parse_point_cloud(b"not a ply file").is_err());
        let missing = read_point_cloud(Path::new("/nonexistent/points.ply")).unwrap_err();
        assert!(missing.to_string().contains("points.ply"), "{missing}");
        let params = |p: &str| ReadPointCloudParams {
            path: PathBuf::from(p),
        };
        assert!(ReadPointCloud::new(params("")).is_err());
        assert!(ReadPointCloud::new(params("points.xyz")).is_err());
        assert!(ReadPointCloud::new(params("points.PLY")).is_ok());
    }
}
