//! Writing triangle meshes: Wavefront OBJ, PLY (ASCII or binary little-endian) and STL (ASCII or
//! binary). One implementation, used by `--emit` ([`crate::emit`]) and by the `io.write_mesh`
//! operator.
//!
//! | format | content |
//! |--------|---------|
//! | OBJ | `v x y z` (with `r g b` appended when the mesh has colors, sRGB-encoded 0..1), `vt u v` when it has uvs, `vn x y z` when it has normals, faces `f a b c` / `f a/a …` / `f a//a …` / `f a/a/a …` with 1-based indices |
//! | PLY | vertex properties `float x y z`, `float nx ny nz`, `float s t`, `uchar red green blue` (sRGB bytes), `float tx ty tz tw` (each group only when present, in that order), faces `property list uchar int vertex_indices`; `format ascii 1.0` or `binary_little_endian 1.0` |
//! | STL | one facet per triangle with its unit normal computed from the positions (`0 0 0` for a degenerate triangle); binary: an 80-byte header that does not start with `solid`, `u32` count, 50 bytes per triangle (attribute byte count 0); ASCII: `solid ocellus` … `endsolid ocellus`. STL holds positions only: normals, uvs, colors, tangents and unused vertices are not written |
//!
//! Text formats print floats with Rust's `{}`, the shortest decimal that reads back to the same
//! `f32`, so finite values round-trip bit for bit (`-0`, subnormals and `f32::MAX` included);
//! non-finite values print as `NaN`, `inf`, `-inf`. Binary formats store the bits. The same mesh
//! always gives the same bytes. [`write_mesh_file`] writes through
//! [`write_atomic_with`](crate::image_io::write_atomic_with): a failed write leaves no partial
//! file.

use std::fmt::Write as _;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use crate::image_io::write_atomic_with;
use crate::value::Mesh;

/// A mesh file format and encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFileFormat {
    /// Wavefront OBJ (text).
    Obj,
    /// PLY, `format ascii 1.0`.
    PlyAscii,
    /// PLY, `format binary_little_endian 1.0`.
    PlyBinary,
    /// ASCII STL.
    StlAscii,
    /// Binary STL.
    StlBinary,
}

impl MeshFileFormat {
    /// The format of `path` by its extension (`.obj`, `.ply`, `.stl`, any case). `binary`:
    /// `None` picks binary for PLY and STL; OBJ is text only, so `Some(true)` is an error there.
    pub fn from_path(path: &Path, binary: Option<bool>) -> Result<MeshFileFormat, String> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match (ext.as_deref(), binary) {
            (Some("obj"), Some(true)) => Err(format!(
                "`{}`: OBJ is a text format; leave `binary` unset (or false) for .obj",
                path.display()
            )),
            (Some("obj"), _) => Ok(MeshFileFormat::Obj),
            (Some("ply"), Some(false)) => Ok(MeshFileFormat::PlyAscii),
            (Some("ply"), _) => Ok(MeshFileFormat::PlyBinary),
            (Some("stl"), Some(false)) => Ok(MeshFileFormat::StlAscii),
            (Some("stl"), _) => Ok(MeshFileFormat::StlBinary),
            _ => Err(format!(
                "`{}`: unknown mesh format; the file name must end in .obj, .ply or .stl",
                path.display()
            )),
        }
    }

    /// A short name: `obj`, `ply ascii`, `ply binary`, `stl ascii`, `stl binary`.
    pub fn name(self) -> &'static str {
        match self {
            MeshFileFormat::Obj => "obj",
            MeshFileFormat::PlyAscii => "ply ascii",
            MeshFileFormat::PlyBinary => "ply binary",
            MeshFileFormat::StlAscii => "stl ascii",
            MeshFileFormat::StlBinary => "stl binary",
        }
    }
}

/// Errors writing a mesh file.
#[derive(Debug, thiserror::Error)]
pub enum MeshWriteError {
    /// The mesh cannot be written in this format (see [`check_mesh`]).
    #[error("cannot write `{}`: {reason}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The file could not be written.
    #[error("cannot write `{}`: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        error: io::Error,
    },
}

/// Checks what every format needs: one entry per vertex in each attribute, triangle indices
/// below the vertex count, at most `i32::MAX` vertices (PLY indices are `int`). The reason names
/// the first problem.
pub fn check_mesh(mesh: &Mesh) -> Result<(), String> {
    let n = mesh.positions.len();
    for (what, len) in [
        ("normals", mesh.normals.as_ref().map(Vec::len)),
        ("uvs", mesh.uvs.as_ref().map(Vec::len)),
        ("colors", mesh.colors.as_ref().map(Vec::len)),
        ("tangents", mesh.tangents.as_ref().map(Vec::len)),
    ] {
        if let Some(len) = len
            && len != n
        {
            return Err(format!("{len} {what} for {n} vertices"));
        }
    }
    if let Some((t, i)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find_map(|(t, tri)| tri.iter().find(|&&i| i as usize >= n).map(|i| (t, *i)))
    {
        return Err(format!(
            "triangle {t} uses vertex {i}, but the mesh has {n} vertices"
        ));
    }
    if n > i32::MAX as usize {
        return Err("PLY face indices are 32-bit signed integers".into());
    }
    Ok(())
}

/// Checks that every position, normal, uv and tangent is finite (the readers reject NaN and
/// infinities). Colors are clamped when encoded, so they are not checked.
pub fn check_finite(mesh: &Mesh) -> Result<(), String> {
    fn first_bad<const N: usize>(values: &[[f32; N]]) -> Option<usize> {
        values.iter().position(|v| v.iter().any(|c| !c.is_finite()))
    }
    let groups: [(&str, Option<usize>); 4] = [
        ("position", first_bad(&mesh.positions)),
        ("normal", mesh.normals.as_deref().and_then(first_bad)),
        ("uv", mesh.uvs.as_deref().and_then(first_bad)),
        ("tangent", mesh.tangents.as_deref().and_then(first_bad)),
    ];
    for (what, bad) in groups {
        if let Some(i) = bad {
            return Err(format!("vertex {i} has a non-finite {what}"));
        }
    }
    Ok(())
}

/// Linear RGB → sRGB-encoded, clamped to 0..=1 (NaN → 0).
pub(crate) fn linear_to_srgb(c: f32) -> f32 {
    let c = if c.is_nan() { 0.0 } else { f64::from(c) };
    let encoded = if c >= 1.0 {
        // Exactly 1: the curve's formula lands a rounding error away from it.
        1.0
    } else if c <= 0.003_130_8 {
        12.92 * c.max(0.0)
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    encoded as f32
}

fn srgb_byte(c: f32) -> u8 {
    // In range by construction: linear_to_srgb returns 0..=1.
    (linear_to_srgb(c) * 255.0).round() as u8
}

fn write_f32s(w: &mut dyn Write, values: &[f32]) -> io::Result<()> {
    for v in values {
        w.write_all(&v.to_le_bytes())?;
    }
    Ok(())
}

fn bad_index() -> io::Error {
    io::Error::new(
        io::ErrorKind::InvalidInput,
        "a triangle index is past the last vertex",
    )
}

/// Writes a Wavefront OBJ (see the [module docs](self)). Attributes shorter than the positions
/// are written as they are (check with [`check_mesh`] first).
pub fn write_obj(w: &mut dyn Write, mesh: &Mesh) -> io::Result<()> {
    writeln!(
        w,
        "# {} vertices, {} triangles",
        mesh.positions.len(),
        mesh.triangles.len()
    )?;
    let mut line = String::new();
    for (i, [x, y, z]) in mesh.positions.iter().enumerate() {
        line.clear();
        let _ = write!(line, "v {x} {y} {z}");
        if let Some([r, g, b]) = mesh.colors.as_ref().and_then(|c| c.get(i)) {
            let _ = write!(
                line,
                " {} {} {}",
                linear_to_srgb(*r),
                linear_to_srgb(*g),
                linear_to_srgb(*b)
            );
        }
        line.push('\n');
        w.write_all(line.as_bytes())?;
    }
    for [u, v] in mesh.uvs.iter().flatten() {
        writeln!(w, "vt {u} {v}")?;
    }
    for [x, y, z] in mesh.normals.iter().flatten() {
        writeln!(w, "vn {x} {y} {z}")?;
    }
    let (uvs, normals) = (mesh.uvs.is_some(), mesh.normals.is_some());
    for triangle in &mesh.triangles {
        line.clear();
        line.push('f');
        for &i in triangle {
            let k = u64::from(i) + 1;
            let _ = match (uvs, normals) {
                (false, false) => write!(line, " {k}"),
                (true, false) => write!(line, " {k}/{k}"),
                (false, true) => write!(line, " {k}//{k}"),
                (true, true) => write!(line, " {k}/{k}/{k}"),
            };
        }
        line.push('\n');
        w.write_all(line.as_bytes())?;
    }
    Ok(())
}

/// The PLY header for `mesh` in `format` (`ascii` or `binary_little_endian`).
fn ply_header(mesh: &Mesh, format: &str) -> String {
    let mut header = format!(
        "ply\nformat {format} 1.0\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n",
        mesh.positions.len()
    );
    if mesh.normals.is_some() {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if mesh.uvs.is_some() {
        header.push_str("property float s\nproperty float t\n");
    }
    if mesh.colors.is_some() {
        header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    if mesh.tangents.is_some() {
        header.push_str(
            "property float tx\nproperty float ty\nproperty float tz\nproperty float tw\n",
        );
    }
    let _ = write!(
        header,
        "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.triangles.len()
    );
    header
}

/// Writes a PLY file, binary little-endian or ASCII (see the [module docs](self)). Triangle
/// indices must be below the vertex count and the count at most `i32::MAX` ([`check_mesh`]);
/// otherwise this fails with [`io::ErrorKind::InvalidInput`] after writing part of the data.
pub fn write_ply(w: &mut dyn Write, mesh: &Mesh, binary: bool) -> io::Result<()> {
    let n = mesh.positions.len();
    if n > i32::MAX as usize {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "PLY face indices are 32-bit signed integers",
        ));
    }
    let header = ply_header(
        mesh,
        if binary {
            "binary_little_endian"
        } else {
            "ascii"
        },
    );
    w.write_all(header.as_bytes())?;
    let normals = mesh.normals.as_deref();
    let uvs = mesh.uvs.as_deref();
    let colors = mesh.colors.as_deref();
    let tangents = mesh.tangents.as_deref();
    let mut line = String::new();
    for (i, p) in mesh.positions.iter().enumerate() {
        let normal = normals.and_then(|a| a.get(i));
        let uv = uvs.and_then(|a| a.get(i));
        let color = colors.and_then(|a| a.get(i)).map(|c| c.map(srgb_byte));
        let tangent = tangents.and_then(|a| a.get(i));
        if binary {
            write_f32s(w, p)?;
            if let Some(v) = normal {
                write_f32s(w, v)?;
            }
            if let Some(v) = uv {
                write_f32s(w, v)?;
            }
            if let Some(c) = color {
                w.write_all(&c)?;
            }
            if let Some(v) = tangent {
                write_f32s(w, v)?;
            }
        } else {
            line.clear();
            let floats = p
                .iter()
                .chain(normal.into_iter().flatten())
                .chain(uv.into_iter().flatten());
            for (k, v) in floats.enumerate() {
                let _ = write!(line, "{}{v}", if k == 0 { "" } else { " " });
            }
            for c in color.into_iter().flatten() {
                let _ = write!(line, " {c}");
            }
            for v in tangent.into_iter().flatten() {
                let _ = write!(line, " {v}");
            }
            line.push('\n');
            w.write_all(line.as_bytes())?;
        }
    }
    for triangle in &mesh.triangles {
        if triangle.iter().any(|&i| i as usize >= n) {
            return Err(bad_index());
        }
        if binary {
            let mut face = [3u8; 13];
            for (dst, &i) in face[1..].as_chunks_mut::<4>().0.iter_mut().zip(triangle) {
                // Below the vertex count, itself ≤ i32::MAX.
                *dst = i.to_le_bytes();
            }
            w.write_all(&face)?;
        } else {
            writeln!(w, "3 {} {} {}", triangle[0], triangle[1], triangle[2])?;
        }
    }
    Ok(())
}

/// The unit normal of a triangle by the right-hand rule (`0 0 0` when it has no direction).
pub fn facet_normal(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> [f32; 3] {
    let d = |p: [f32; 3], q: [f32; 3]| [0, 1, 2].map(|k| f64::from(p[k]) - f64::from(q[k]));
    let (u, v) = (d(b, a), d(c, a));
    let n = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 && len.is_finite() {
        n.map(|x| (x / len) as f32)
    } else {
        [0.0; 3]
    }
}

/// The 80-byte header of binary STL files written here (it must not start with `solid`, which
/// would make other readers take the file for ASCII).
pub const STL_HEADER: &[u8; 80] =
    b"binary STL written by Ocellus                                                   ";

/// Writes an STL file, binary or ASCII (see the [module docs](self)): the triangles' corner
/// positions and facet normals. Fails with [`io::ErrorKind::InvalidInput`] on an index past the
/// last vertex or more than `u32::MAX` triangles (binary).
pub fn write_stl(w: &mut dyn Write, mesh: &Mesh, binary: bool) -> io::Result<()> {
    let corners = |t: &[u32; 3]| -> io::Result<[[f32; 3]; 3]> {
        let p = |i: u32| {
            mesh.positions
                .get(i as usize)
                .copied()
                .ok_or_else(bad_index)
        };
        Ok([p(t[0])?, p(t[1])?, p(t[2])?])
    };
    if binary {
        let count = u32::try_from(mesh.triangles.len()).map_err(|_| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                "binary STL holds at most 2³² − 1 triangles",
            )
        })?;
        w.write_all(STL_HEADER)?;
        w.write_all(&count.to_le_bytes())?;
        let mut record = [0u8; 50];
        for t in &mesh.triangles {
            let [a, b, c] = corners(t)?;
            let n = facet_normal(a, b, c);
            for (k, v) in n.iter().chain(&a).chain(&b).chain(&c).enumerate() {
                record[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
            }
            // The attribute byte count stays 0.
            w.write_all(&record)?;
        }
    } else {
        w.write_all(b"solid ocellus\n")?;
        let mut text = String::new();
        for t in &mesh.triangles {
            let [a, b, c] = corners(t)?;
            let [nx, ny, nz] = facet_normal(a, b, c);
            text.clear();
            let _ = writeln!(text, "  facet normal {nx} {ny} {nz}\n    outer loop");
            for [x, y, z] in [a, b, c] {
                let _ = writeln!(text, "      vertex {x} {y} {z}");
            }
            text.push_str("    endloop\n  endfacet\n");
            w.write_all(text.as_bytes())?;
        }
        w.write_all(b"endsolid ocellus\n")?;
    }
    Ok(())
}

/// Writes `mesh` to `path` in `format`, atomically (temp file + rename; nothing is left behind
/// on error). The mesh is checked with [`check_mesh`] first.
pub fn write_mesh_file(
    path: &Path,
    mesh: &Mesh,
    format: MeshFileFormat,
) -> Result<(), MeshWriteError> {
    check_mesh(mesh).map_err(|reason| MeshWriteError::Invalid {
        path: path.to_path_buf(),
        reason,
    })?;
    if matches!(format, MeshFileFormat::StlBinary) && u32::try_from(mesh.triangles.len()).is_err() {
        return Err(MeshWriteError::Invalid {
            path: path.to_path_buf(),
            reason: "binary STL holds at most 2³² − 1 triangles".into(),
        });
    }
    write_atomic_with(path, |w| match format {
        MeshFileFormat::Obj => write_obj(w, mesh),
        MeshFileFormat::PlyAscii => write_ply(w, mesh, false),
        MeshFileFormat::PlyBinary => write_ply(w, mesh, true),
        MeshFileFormat::StlAscii => write_stl(w, mesh, false),
        MeshFileFormat::StlBinary => write_stl(w, mesh, true),
    })
    .map_err(|error| MeshWriteError::Io {
        path: path.to_path_buf(),
        error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad() -> Mesh {
        Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, -0.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            ..Mesh::default()
        }
    }

    fn bytes(mesh: &Mesh, format: MeshFileFormat) -> Vec<u8> {
        let mut out = Vec::new();
        match format {
            MeshFileFormat::Obj => write_obj(&mut out, mesh),
            MeshFileFormat::PlyAscii => write_ply(&mut out, mesh, false),
            MeshFileFormat::PlyBinary => write_ply(&mut out, mesh, true),
            MeshFileFormat::StlAscii => write_stl(&mut out, mesh, false),
            MeshFileFormat::StlBinary => write_stl(&mut out, mesh, true),
        }
        .unwrap();
        out
    }

    #[test]
    fn formats_by_extension_and_binary_flag() {
        let f = |p: &str, b| MeshFileFormat::from_path(Path::new(p), b);
        assert_eq!(f("a.obj", None), Ok(MeshFileFormat::Obj));
        assert_eq!(f("a.OBJ", Some(false)), Ok(MeshFileFormat::Obj));
        assert!(f("a.obj", Some(true)).unwrap_err().contains("text"));
        assert_eq!(f("a.ply", None), Ok(MeshFileFormat::PlyBinary));
        assert_eq!(f("a.Ply", Some(false)), Ok(MeshFileFormat::PlyAscii));
        assert_eq!(f("a.stl", None), Ok(MeshFileFormat::StlBinary));
        assert_eq!(f("a.STL", Some(true)), Ok(MeshFileFormat::StlBinary));
        assert_eq!(f("a.stl", Some(false)), Ok(MeshFileFormat::StlAscii));
        for bad in ["a.off", "a", "a.stl.gz", ""] {
            assert!(f(bad, None).unwrap_err().contains(".stl"), "{bad}");
        }
    }

    #[test]
    fn binary_stl_layout() {
        let b = bytes(&quad(), MeshFileFormat::StlBinary);
        assert_eq!(b.len(), 84 + 2 * 50);
        assert!(!b.starts_with(b"solid"));
        assert_eq!(&b[80..84], &2u32.to_le_bytes());
        let f = |at: usize| f32::from_le_bytes(b[at..at + 4].try_into().unwrap());
        // Triangle 0: normal +z, then corners 0, 1, 2; attribute count 0.
        assert_eq!([f(84), f(88), f(92)], [0.0, 0.0, 1.0]);
        assert_eq!([f(96 + 12), f(96 + 16), f(96 + 20)], [1.0, 0.0, 0.0]);
        assert_eq!(&b[84 + 48..84 + 50], &[0, 0]);
        // Triangle 1's last corner keeps its -0.0.
        assert_eq!(f(134 + 12 + 24 + 8).to_bits(), (-0.0f32).to_bits());
    }

    #[test]
    fn ascii_stl_and_ply_text() {
        let text = String::from_utf8(bytes(&quad(), MeshFileFormat::StlAscii)).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "solid ocellus");
        assert_eq!(lines[1], "  facet normal 0 0 1");
        assert_eq!(lines[2], "    outer loop");
        assert_eq!(lines[3], "      vertex 0 0 0");
        assert_eq!(lines[12], "      vertex 0 1 -0");
        assert_eq!(lines.last(), Some(&"endsolid ocellus"));
        assert_eq!(lines.len(), 2 + 2 * 7);

        let mut mesh = quad();
        mesh.colors = Some(vec![[1.0, 0.0, 0.5], [0.0; 3], [0.0; 3], [0.0; 3]]);
        mesh.tangents = Some(vec![[1.0, 0.0, 0.0, -1.0]; 4]);
        let text = String::from_utf8(bytes(&mesh, MeshFileFormat::PlyAscii)).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[1], "format ascii 1.0");
        let body = lines.iter().position(|l| *l == "end_header").unwrap() + 1;
        assert!(lines[..body].contains(&"property float tw"));
        assert_eq!(lines[body], "0 0 0 255 0 188 1 0 0 -1");
        assert_eq!(lines[body + 4], "3 0 1 2");
        assert_eq!(lines.len(), body + 6);
    }

    #[test]
    fn binary_ply_appends_tangents_after_colors() {
        let mut mesh = quad();
        mesh.tangents = Some(vec![[0.0, 1.0, 0.0, 1.0]; 4]);
        let b = bytes(&mesh, MeshFileFormat::PlyBinary);
        let header = ply_header(&mesh, "binary_little_endian");
        assert!(b.starts_with(header.as_bytes()));
        let body = &b[header.len()..];
        assert_eq!(body.len(), 4 * 28 + 2 * 13);
        let f = |at: usize| f32::from_le_bytes(body[at..at + 4].try_into().unwrap());
        assert_eq!([f(12), f(16), f(20), f(24)], [0.0, 1.0, 0.0, 1.0]);
    }

    #[test]
    fn facet_normals_handle_degenerate_and_huge_triangles() {
        assert_eq!(
            facet_normal([0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]),
            [0.0; 3]
        );
        let m = f32::MAX;
        assert_eq!(
            facet_normal([-m, -m, 0.0], [m, -m, 0.0], [-m, m, 0.0]),
            [0.0, 0.0, 1.0]
        );
        assert_eq!(
            facet_normal([0.0; 3], [1e-45, 0.0, 0.0], [0.0, 0.0, 1e-45]),
            [0.0, -1.0, 0.0]
        );
    }

    #[test]
    fn checks_name_the_problem() {
        let mut bad = quad();
        bad.triangles.push([0, 1, 4]);
        assert!(check_mesh(&bad).unwrap_err().contains("vertex 4"));
        let mut short = quad();
        short.tangents = Some(vec![[1.0, 0.0, 0.0, 1.0]; 3]);
        assert_eq!(check_mesh(&short).unwrap_err(), "3 tangents for 4 vertices");
        let mut nan = quad();
        nan.positions[2][1] = f32::NAN;
        assert_eq!(
            check_finite(&nan).unwrap_err(),
            "vertex 2 has a non-finite position"
        );
        assert!(check_finite(&quad()).is_ok());
        // Writers never panic on a bad index; they fail.
        for format in [
            MeshFileFormat::PlyAscii,
            MeshFileFormat::PlyBinary,
            MeshFileFormat::StlAscii,
            MeshFileFormat::StlBinary,
        ] {
            let mut out = Vec::new();
            let r = match format {
                MeshFileFormat::PlyAscii => write_ply(&mut out, &bad, false),
                MeshFileFormat::PlyBinary => write_ply(&mut out, &bad, true),
                MeshFileFormat::StlAscii => write_stl(&mut out, &bad, false),
                _ => write_stl(&mut out, &bad, true),
            };
            assert_eq!(r.unwrap_err().kind(), io::ErrorKind::InvalidInput);
        }
    }

    #[test]
    fn file_writes_are_atomic() {
        let dir = std::env::temp_dir().join(format!("ocellus-mesh-write-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("m.stl");
        write_mesh_file(&path, &quad(), MeshFileFormat::StlBinary).unwrap();
        assert_eq!(std::fs::read(&path).unwrap().len(), 184);
        let mut bad = quad();
        bad.triangles.push([9, 0, 1]);
        let err = write_mesh_file(&path, &bad, MeshFileFormat::StlAscii).unwrap_err();
        assert!(matches!(err, MeshWriteError::Invalid { .. }), "{err}");
        // The earlier file is intact and nothing else was left in the folder.
        assert_eq!(std::fs::read(&path).unwrap().len(), 184);
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
