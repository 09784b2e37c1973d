//! `io.write_mesh`: write a triangle mesh as Wavefront OBJ, PLY or STL, atomically.
//!
//! The bytes come from [`ocellus_engine::mesh_write`], the same code `--emit` uses, so what this
//! writes [`read_mesh`](super::read_mesh) reads back: positions and triangles always (bit for
//! bit, text formats included: floats are printed as the shortest decimal that reads back to the
//! same `f32`), and whatever the format carries of the rest: OBJ normals, uvs and colors; PLY
//! normals, uvs, colors (as sRGB bytes) and tangents; STL nothing else (its facet normals are
//! computed from the positions, and the reader welds equal positions, so unused and duplicate
//! vertices do not survive).

use std::path::PathBuf;

use ocellus_engine::mesh_write::{MeshFileFormat, check_finite, write_mesh_file};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use super::write_image::numbered;

ocellus_engine::params! {
    /// Parameters of [`WriteMesh`].
    pub struct WriteMeshParams {
        /// Destination; the extension picks the format: `.obj` (Wavefront OBJ), `.ply` (PLY) or
        /// `.stl` (STL). Relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
        /// Binary (true) or text (false) PLY and STL; OBJ is text only (true is an error).
        /// Default: binary for PLY (little-endian) and STL.
        binary: Option<bool> = None,
    }
}

/// Writes a mesh file (`io.write_mesh`). The file appears complete or not at all (temporary
/// file + rename).
pub struct WriteMesh {
    path: PathBuf,
    format: MeshFileFormat,
}

impl Op for WriteMesh {
    type Params = WriteMeshParams;
    const ID: &'static str = "io.write_mesh";
    const SUMMARY: &'static str =
        "Write a triangle mesh as Wavefront OBJ, PLY or STL (ASCII or binary), atomically.";
    const DOC: &'static str = r#"
Writes the mesh in the format of the path's extension, through a temporary file renamed into
place: readers never see a partial file, and a failed write leaves no file behind.

- .obj: `v x y z [r g b]`, `vt u v`, `vn x y z` and faces `f a/a/a …` with 1-based indices.
- .ply: binary little-endian (default) or ASCII (`binary: false`); vertex properties
  `float x y z`, `nx ny nz`, `s t`, `uchar red green blue`, `float tx ty tz tw`, each group only
  when the mesh has it; faces `list uchar int vertex_indices`.
- .stl: binary (default; 80-byte header not starting with "solid") or ASCII; one facet per
  triangle with its normal computed from the positions. STL keeps positions only.

Colors are linear in the mesh and written sRGB-encoded, as `--emit` does. Text formats print
the shortest decimal that reads back to the same float, so `io.read_mesh` gets the positions
back bit for bit from every format. A mesh with NaN or infinite positions, normals, uvs or
tangents, or with a triangle index past the last vertex, is an error (nothing is written).
Runs whenever the graph runs without an output selection (a side effect); never cached.
Mapped over a list, element k goes to `NAME_000k.EXT`.

Example:
    "save": (op: "io.write_mesh", inputs: { "mesh": "fair.mesh" }, params: (path: "out/fair.stl")),
"#;
    const SIDE_EFFECTS: bool = true;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("mesh", PortType::Mesh, "The mesh to write.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("path", PortType::Text, "The file written.")]
    }

    fn new(p: WriteMeshParams) -> Result<Self, String> {
        if p.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        let format = MeshFileFormat::from_path(&p.path, p.binary)?;
        Ok(WriteMesh {
            path: p.path,
            format,
        })
    }
}

impl Operator for WriteMesh {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = match inputs.require("mesh")? {
            Value::Mesh(m) => m,
            other => {
                return Err(OpError::input(
                    "mesh",
                    format!("expected Mesh, got {}", other.port_type()),
                ));
            }
        };
        check_finite(mesh).map_err(|e| OpError::input("mesh", e))?;
        let path = match ctx.element {
            Some(k) => numbered(&self.path, k),
            None => self.path.clone(),
        };
        write_mesh_file(&path, mesh, self.format).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("path", Value::Text(path.to_string_lossy().into())))
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;
    use std::sync::Arc;

    use ocellus_engine::mesh_write::{write_obj, write_ply, write_stl};
    use ocellus_engine::value::Mesh;
    use proptest::prelude::*;

    use super::*;
    use crate::io::read_mesh::{parse_obj, parse_ply, parse_stl, read_mesh};

    const ALL: [MeshFileFormat; 5] = [
        MeshFileFormat::Obj,
        MeshFileFormat::PlyAscii,
        MeshFileFormat::PlyBinary,
        MeshFileFormat::StlAscii,
        MeshFileFormat::StlBinary,
    ];

    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("ocellus-write-mesh-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// `mesh` written in `format` and parsed back, in memory.
    fn round_trip(mesh: &Mesh, format: MeshFileFormat) -> Mesh {
        let mut bytes = Vec::new();
        match format {
            MeshFileFormat::Obj => write_obj(&mut bytes, mesh),
            MeshFileFormat::PlyAscii => write_ply(&mut bytes, mesh, false),
            MeshFileFormat::PlyBinary => write_ply(&mut bytes, mesh, true),
            MeshFileFormat::StlAscii => write_stl(&mut bytes, mesh, false),
            MeshFileFormat::StlBinary => write_stl(&mut bytes, mesh, true),
        }
        .unwrap();
        let parsed = match format {
            MeshFileFormat::Obj => parse_obj(&String::from_utf8(bytes).unwrap()),
            MeshFileFormat::PlyAscii | MeshFileFormat::PlyBinary => parse_ply(&bytes),
            MeshFileFormat::StlAscii | MeshFileFormat::StlBinary => parse_stl(&bytes),
        };
        parsed.unwrap_or_else(|e| panic!("{}: {e}", format.name()))
    }

    fn bits<const N: usize>(v: &[[f32; N]]) -> Vec<[u32; N]> {
        v.iter().map(|p| p.map(f32::to_bits)).collect()
    }

    /// Each triangle's corners' position bits: what STL keeps.
    fn soup(mesh: &Mesh) -> Vec<[[u32; 3]; 3]> {
        mesh.triangles
            .iter()
            .map(|t| t.map(|i| mesh.positions[i as usize].map(f32::to_bits)))
            .collect()
    }

    fn close<const N: usize>(a: &[[f32; N]], b: &[[f32; N]], tol: f32) -> bool {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(x, y)| x.iter().zip(y).all(|(p, q)| (p - q).abs() <= tol))
    }

    /// PLY colors are sRGB bytes: half a step through the steepest part of the curve.
    const BYTE_TOL: f32 = 0.5 / 255.0 * 2.4 / 1.055 + 1e-6;

    /// Checks what `format` must keep of `mesh` in `back`.
    fn check(mesh: &Mesh, back: &Mesh, format: MeshFileFormat) -> Result<(), TestCaseError> {
        let name = format.name();
        if matches!(format, MeshFileFormat::StlAscii | MeshFileFormat::StlBinary) {
            prop_assert_eq!(soup(back), soup(mesh), "{}: corner positions", name);
            // Welded: no two vertices share their bits, and every vertex is used.
            let mut distinct = bits(&back.positions);
            distinct.sort_unstable();
            distinct.dedup();
            prop_assert_eq!(distinct.len(), back.positions.len(), "{}: welded", name);
            let mut used = vec![false; back.positions.len()];
            for &i in back.triangles.iter().flatten() {
                used[i as usize] = true;
            }
            prop_assert!(used.iter().all(|&u| u), "{}: unused vertex", name);
            prop_assert!(back.normals.is_none() && back.uvs.is_none());
            prop_assert!(back.colors.is_none() && back.tangents.is_none());
            return Ok(());
        }
        prop_assert_eq!(bits(&back.positions), bits(&mesh.positions), "{}", name);
        prop_assert_eq!(&back.triangles, &mesh.triangles, "{}", name);
        prop_assert_eq!(
            back.uvs.as_deref().map(bits),
            mesh.uvs.as_deref().map(bits),
            "{}: uvs",
            name
        );
        prop_assert_eq!(back.normals.is_some(), mesh.normals.is_some(), "{}", name);
        if let (Some(a), Some(b)) = (&back.normals, &mesh.normals) {
            prop_assert!(close(a, b, 1e-6), "{}: normals", name);
        }
        prop_assert_eq!(back.colors.is_some(), mesh.colors.is_some(), "{}", name);
        if let (Some(a), Some(b)) = (&back.colors, &mesh.colors) {
            let tol = if format == MeshFileFormat::Obj {
                1e-6
            } else {
                BYTE_TOL
            };
            prop_assert!(close(a, b, tol), "{}: colors", name);
        }
        if format == MeshFileFormat::Obj {
            prop_assert!(back.tangents.is_none());
        } else {
            // Unit tangents read back bit for bit.
            prop_assert_eq!(
                back.tangents.as_deref().map(bits),
                mesh.tangents.as_deref().map(bits),
                "{}: tangents",
                name
            );
        }
        Ok(())
    }

    /// A quad with every attribute; its vertices appear in order, so STL keeps them too.
    fn quad() -> Mesh {
        Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.5, 0.0, -0.0],
                [1.5, 1.0, 0.25],
                [0.0, 1.0, 1e-40],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            normals: Some(vec![[0.0, 0.0, 1.0]; 4]),
            uvs: Some(vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]),
            colors: Some(vec![
                [0.0, 0.5, 1.0],
                [1.0, 1.0, 1.0],
                [0.2, 0.0, 0.0],
                [0.0; 3],
            ]),
            tangents: Some(vec![
                [1.0, 0.0, 0.0, 1.0],
                [1.0, 0.0, 0.0, 1.0],
                [0.6, 0.8, 0.0, -1.0],
                [0.0, 1.0, 0.0, -1.0],
            ]),
        }
    }

    fn run_op(path: &Path, binary: Option<bool>, mesh: &Mesh) -> Result<PathBuf, OpError> {
        let op = WriteMesh::new(WriteMeshParams {
            path: path.to_path_buf(),
            binary,
        })
        .map_err(OpError::failed)?;
        let specs = WriteMesh::inputs();
        let values = [Some(Value::Mesh(Arc::new(mesh.clone())))];
        let ctx = RunContext {
            node: "w".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values))?;
        match out.take("path") {
            Some(Value::Text(p)) => Ok(PathBuf::from(&*p)),
            other => panic!("no path: {other:?}"),
        }
    }

    #[test]
    fn every_format_reads_back_through_the_files() {
        let dir = scratch("formats");
        let mesh = quad();
        for (file, binary, format) in [
            ("m.obj", None, MeshFileFormat::Obj),
            ("m.ply", None, MeshFileFormat::PlyBinary),
            ("a.ply", Some(false), MeshFileFormat::PlyAscii),
            ("m.stl", None, MeshFileFormat::StlBinary),
            ("a.STL", Some(false), MeshFileFormat::StlAscii),
        ] {
            let written = run_op(&dir.join(file), binary, &mesh).unwrap();
            assert_eq!(written, dir.join(file));
            let back = read_mesh(&written).unwrap();
            check(&mesh, &back, format).unwrap();
            let bytes = std::fs::read(&written).unwrap();
            let is_text = bytes.iter().all(|b| b.is_ascii());
            assert_eq!(
                is_text,
                matches!(
                    format,
                    MeshFileFormat::Obj | MeshFileFormat::PlyAscii | MeshFileFormat::StlAscii
                ),
                "{file}"
            );
        }
        // The quad's vertices are all used, distinct and in order: STL gives them back exactly.
        let stl = read_mesh(&dir.join("m.stl")).unwrap();
        assert_eq!(bits(&stl.positions), bits(&mesh.positions));
        assert_eq!(stl.triangles, mesh.triangles);
        // Only the five files; no temp files.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 5);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn bad_meshes_and_params_write_nothing() {
        let dir = scratch("errors");
        let mut nan = quad();
        nan.positions[1][2] = f32::NAN;
        let err = run_op(&dir.join("nan.ply"), None, &nan).unwrap_err();
        assert!(err.to_string().contains("vertex 1"), "{err}");
        let mut inf = quad();
        inf.tangents.as_mut().unwrap()[3][0] = f32::INFINITY;
        assert!(run_op(&dir.join("inf.ply"), None, &inf).is_err());
        let mut bad = quad();
        bad.triangles.push([0, 1, 9]);
        let err = run_op(&dir.join("bad.stl"), None, &bad).unwrap_err();
        assert!(err.to_string().contains("vertex 9"), "{err}");
        // A missing folder fails cleanly.
        assert!(run_op(&dir.join("missing/m.obj"), None, &quad()).is_err());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        // Params are checked when the graph loads.
        for (path, binary) in [("m.obj", Some(true)), ("m.off", None), ("", None)] {
            assert!(
                WriteMesh::new(WriteMeshParams {
                    path: path.into(),
                    binary
                })
                .is_err(),
                "{path}"
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn mapped_elements_get_numbered_files() {
        let dir = scratch("mapped");
        let op = WriteMesh::new(WriteMeshParams {
            path: dir.join("part.stl"),
            binary: None,
        })
        .unwrap();
        let specs = WriteMesh::inputs();
        let values = [Some(Value::Mesh(Arc::new(quad())))];
        let ctx = RunContext {
            node: "w".into(),
            threads: 1,
            element: Some(7),
        };
        op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        assert!(dir.join("part_0007.stl").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn registered_beside_read_mesh() {
        let mut registry = ocellus_engine::Registry::new();
        crate::register_builtins(&mut registry).unwrap();
        let info = registry.get("io.write_mesh").unwrap().info();
        assert_eq!(info.inputs[0].ty, PortType::Mesh);
        assert_eq!(info.outputs[0].ty, PortType::Text);
    }

    /// Floats worth writing: extremes, subnormals, signed zeros, ordinary values.
    fn coordinate() -> impl Strategy<Value = f32> {
        prop_oneof![
            3 => -1e3f32..1e3,
            1 => prop::sample::select(vec![
                f32::MAX,
                f32::MIN,
                f32::MIN_POSITIVE,
                -f32::MIN_POSITIVE,
                1e-45,
                -1e-45,
                1.17e-38,
                0.0,
                -0.0,
                1.0 / 3.0,
                16_777_216.0,
            ]),
            1 => any::<u32>().prop_map(f32::from_bits).prop_filter("finite", |v| v.is_finite()),
        ]
    }

    fn unit(v: [f32; 3]) -> Option<[f32; 3]> {
        let len = v.iter().map(|c| f64::from(*c).powi(2)).sum::<f64>().sqrt();
        (len > 1e-3).then(|| v.map(|c| (f64::from(c) / len) as f32))
    }

    /// A random mesh: up to 10 vertices, 12 triangles, any attributes, extreme positions.
    fn mesh_strategy() -> impl Strategy<Value = Mesh> {
        (1usize..10)
            .prop_flat_map(|n| {
                (
                    prop::collection::vec([coordinate(), coordinate(), coordinate()], n),
                    prop::collection::vec([0..n as u32, 0..n as u32, 0..n as u32], 0..12),
                    any::<[bool; 4]>(),
                    prop::collection::vec([-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0], n),
                    prop::collection::vec([coordinate(), coordinate()], n),
                    prop::collection::vec([0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0], n),
                    prop::collection::vec(any::<bool>(), n),
                )
            })
            .prop_map(
                |(positions, triangles, [n, t, c, g], dirs, uvs, colors, signs)| {
                    let dirs: Vec<[f32; 3]> = dirs
                        .iter()
                        .map(|d| unit(*d).unwrap_or([0.0, 0.0, 1.0]))
                        .collect();
                    Mesh {
                        positions,
                        triangles,
                        normals: n.then(|| dirs.clone()),
                        uvs: t.then_some(uvs),
                        colors: c.then_some(colors),
                        tangents: g.then(|| {
                            dirs.iter()
                                .zip(&signs)
                                .map(|(d, &s)| [d[1], d[2], d[0], if s { 1.0 } else { -1.0 }])
                                .collect()
                        }),
                    }
                },
            )
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            cases: 200,
            rng_seed: proptest::test_runner::RngSeed::Fixed(20_261_203),
            ..ProptestConfig::default()
        })]

        #[test]
        fn random_meshes_round_trip_in_every_format(mesh in mesh_strategy()) {
            for format in ALL {
                let back = round_trip(&mesh, format);
                check(&mesh, &back, format)?;
            }
        }
    }
}
