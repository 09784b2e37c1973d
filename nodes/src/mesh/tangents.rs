//! Per-vertex tangents by MikkTSpace: `mesh.tangents`.
//!
//! MikkTSpace (Mikkelsen, "Simulation of wrinkled surfaces revisited", MSc thesis, University of
//! Copenhagen, 2008) is the tangent space that Blender, Substance, xNormal and glTF (which
//! requires it when tangents are absent) bake normal maps in, so a normal map baked elsewhere
//! shades correctly only with these tangents. [`corner_tangents`] runs the reference algorithm
//! (the `mikktspace` crate, a port of Mikkelsen's C code) on every triangle corner: tangents
//! along `∂P/∂u` averaged over the corners that share a vertex, position, normal and uv,
//! orthogonalized against the normal, with the handedness `w = ±1` of `∂P/∂v` so that the
//! bitangent is `w · (n × t)`.
//!
//! MikkTSpace gives each corner its own tangent; corners of one vertex differ where the uv
//! layout is mirrored (opposite handedness) or otherwise splits the tangent frame.
//! [`split_by_tangent`] turns the corner tangents into a per-vertex attribute: a vertex whose
//! corners all agree (bit for bit) keeps its index; one whose corners disagree is split into one
//! copy per distinct tangent (same position, normal, uv and color), ordered by first appearance
//! in triangle order and numbered right after the original, so positions, normals and uvs stay
//! consistent and nothing is split that does not need to be. Vertices no triangle uses keep a
//! tangent perpendicular to their normal (`w = +1`).
//!
//! Tangents come out unit and orthogonal to the normal: a corner whose MikkTSpace tangent is
//! zero or not finite (degenerate uvs or triangles; the reference code gives zero there), or
//! not orthogonal to the normal within 1e-4, is replaced by the Gram–Schmidt projection of its
//! tangent on the normal's plane or, when that vanishes, by a fixed perpendicular of the normal
//! (the axis least aligned with it, projected); these are counted in `repaired_corners`. Lengths
//! off by more than 4 ulp are renormalized in f64, so PLY files read back bit for bit.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params::NoParams;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};

use super::halfedge::{MeshError, mesh_input, mesh_positions};
use super::normals::{NormalWeighting, vertex_normals};

/// The mesh as MikkTSpace sees it: triangles of per-vertex attributes; tangents out per corner.
struct Corners<'a> {
    positions: &'a [[f32; 3]],
    normals: &'a [[f32; 3]],
    uvs: &'a [[f32; 2]],
    triangles: &'a [[u32; 3]],
    out: Vec<[f32; 4]>,
}

impl Corners<'_> {
    fn vertex(&self, face: usize, vert: usize) -> usize {
        self.triangles
            .get(face)
            .and_then(|t| t.get(vert))
            .map_or(0, |&i| i as usize)
    }
}

impl mikktspace::Geometry for Corners<'_> {
    fn num_faces(&self) -> usize {
        self.triangles.len()
    }

    fn num_vertices_of_face(&self, _face: usize) -> usize {
        3
    }

    fn position(&self, face: usize, vert: usize) -> [f32; 3] {
        let v = self.vertex(face, vert);
        self.positions.get(v).copied().unwrap_or_default()
    }

    fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
        let v = self.vertex(face, vert);
        self.normals.get(v).copied().unwrap_or([0.0, 0.0, 1.0])
    }

    fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
        let v = self.vertex(face, vert);
        self.uvs.get(v).copied().unwrap_or_default()
    }

    fn set_tangent_encoded(&mut self, tangent: [f32; 4], face: usize, vert: usize) {
        if let Some(slot) = self.out.get_mut(3 * face + vert) {
            *slot = tangent;
        }
    }
}

fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `v / |v|`, or `None` when `v` has no direction.
fn unit3(v: [f64; 3]) -> Option<[f64; 3]> {
    let len = dot3(v, v).sqrt();
    (len > 1e-20 && len.is_finite()).then(|| v.map(|c| c / len))
}

/// `n` normalized (`+z` when it has no direction).
fn unit_normal(n: [f32; 3]) -> [f64; 3] {
    unit3(n.map(f64::from)).unwrap_or([0.0, 0.0, 1.0])
}

/// A fixed unit vector perpendicular to the unit `n`: the coordinate axis least aligned with
/// it (the first on ties), projected on its plane. `+x` for `n = +z`.
pub fn perpendicular(n: [f64; 3]) -> [f64; 3] {
    let a = n.map(f64::abs);
    let k = if a[0] <= a[1] && a[0] <= a[2] {
        0
    } else if a[1] <= a[2] {
        1
    } else {
        2
    };
    let mut e = [0.0; 3];
    e[k] = 1.0;
    let d = dot3(e, n);
    unit3([e[0] - d * n[0], e[1] - d * n[1], e[2] - d * n[2]]).unwrap_or([1.0, 0.0, 0.0])
}

/// A corner's final tangent, unit and orthogonal to the unit normal `n`, with `w = ±1`; and
/// whether it had to be repaired (zero, not finite or not orthogonal).
pub fn finish_tangent(t: [f32; 4], n: [f64; 3]) -> ([f32; 4], bool) {
    let w = if t[3] < 0.0 { -1.0 } else { 1.0 };
    let v = [t[0], t[1], t[2]].map(f64::from);
    let len = dot3(v, v).sqrt();
    let finite = t[..3].iter().all(|c| c.is_finite());
    let orthogonal = finite && len > 0.0 && (dot3(v, n) / len).abs() <= 1e-4;
    let unit = (len - 1.0).abs() <= 4.0 * f64::from(f32::EPSILON);
    if orthogonal && unit {
        return ([t[0], t[1], t[2], w], false);
    }
    let repaired = !(orthogonal && (len - 1.0).abs() <= 1e-4);
    let d = if finite { dot3(v, n) } else { 0.0 };
    let projected = if finite {
        unit3([v[0] - d * n[0], v[1] - d * n[1], v[2] - d * n[2]])
    } else {
        None
    };
    let u = projected.unwrap_or_else(|| perpendicular(n));
    ([u[0] as f32, u[1] as f32, u[2] as f32, w], repaired)
}

/// Errors of [`corner_tangents`] beyond those of the mesh itself.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TangentError {
    /// The mesh has no texture coordinates.
    #[error("the mesh has no uvs; MikkTSpace tangents follow the texture coordinates")]
    NoUvs,
    /// A uv or normal is NaN or infinite.
    #[error("vertex {index} has a non-finite {what}")]
    NonFinite {
        /// The vertex.
        index: usize,
        /// `uv` or `normal`.
        what: &'static str,
    },
    /// The reference code gave up (it reports failure only for empty input) or panicked.
    #[error("MikkTSpace could not process the mesh")]
    Failed,
}

/// MikkTSpace tangents of every triangle corner (`[3·t + k]` for corner `k` of triangle `t`),
/// each finished by [`finish_tangent`] against its vertex's normalized normal, and the number
/// of corners repaired. `normals` and `uvs` are per vertex; indices must be in range and the
/// values finite (see [`tangents`], which checks).
pub fn corner_tangents(
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    uvs: &[[f32; 2]],
    triangles: &[[u32; 3]],
) -> Result<(Vec<[f32; 4]>, usize), TangentError> {
    let unit: Vec<[f64; 3]> = normals.iter().map(|&n| unit_normal(n)).collect();
    let unit32: Vec<[f32; 3]> = unit.iter().map(|n| n.map(|c| c as f32)).collect();
    let mut geometry = Corners {
        positions,
        normals: &unit32,
        uvs,
        triangles,
        // NaN until set: a corner the reference code skips is repaired below.
        out: vec![[f32::NAN; 4]; 3 * triangles.len()],
    };
    if !triangles.is_empty() {
        let ok = catch_unwind(AssertUnwindSafe(|| {
            mikktspace::generate_tangents(&mut geometry)
        }));
        if !matches!(ok, Ok(true)) {
            return Err(TangentError::Failed);
        }
    }
    let mut repaired = 0;
    let mut out = geometry.out;
    for (c, t) in out.iter_mut().enumerate() {
        let v = triangles
            .get(c / 3)
            .and_then(|tri| tri.get(c % 3))
            .map_or(0, |&i| i as usize);
        let n = unit.get(v).copied().unwrap_or([0.0, 0.0, 1.0]);
        let (done, fixed) = finish_tangent(*t, n);
        *t = done;
        repaired += usize::from(fixed);
    }
    Ok((out, repaired))
}

/// `mesh` with per-vertex `tangents` from per-corner ones, splitting only the vertices whose
/// corners disagree (see the [module documentation](self)), and the number of vertices added.
/// `normals` replaces the mesh's normals (they are needed for unused vertices' tangents).
pub fn split_by_tangent(mesh: &Mesh, normals: &[[f32; 3]], corners: &[[f32; 4]]) -> (Mesh, usize) {
    let n = mesh.positions.len();
    // Distinct tangents of each vertex in order of first appearance, and each corner's choice.
    let mut variants: Vec<Vec<[f32; 4]>> = vec![Vec::new(); n];
    let mut choice: Vec<u32> = Vec::with_capacity(corners.len());
    for (c, t) in corners.iter().enumerate() {
        let v = mesh
            .triangles
            .get(c / 3)
            .and_then(|tri| tri.get(c % 3))
            .map_or(0, |&i| i as usize);
        let Some(list) = variants.get_mut(v) else {
            choice.push(0);
            continue;
        };
        let bits = t.map(f32::to_bits);
        let k = match list.iter().position(|u| u.map(f32::to_bits) == bits) {
            Some(k) => k,
            None => {
                list.push(*t);
                list.len() - 1
            }
        };
        choice.push(k as u32);
    }
    // Copies of vertex v start at base[v].
    let mut base = Vec::with_capacity(n);
    let mut total = 0usize;
    for list in &variants {
        base.push(total as u32);
        total += list.len().max(1);
    }
    let copies = |v: usize| variants.get(v).map_or(1, |l| l.len().max(1));
    fn repeat<T: Copy>(values: &[T], copies: &dyn Fn(usize) -> usize, total: usize) -> Vec<T> {
        let mut out = Vec::with_capacity(total);
        for (v, x) in values.iter().enumerate() {
            out.extend(std::iter::repeat_n(*x, copies(v)));
        }
        out
    }
    let mut tangents = Vec::with_capacity(total);
    for (v, list) in variants.iter().enumerate() {
        if list.is_empty() {
            let t = perpendicular(unit_normal(normals.get(v).copied().unwrap_or_default()));
            tangents.push([t[0] as f32, t[1] as f32, t[2] as f32, 1.0]);
        } else {
            tangents.extend_from_slice(list);
        }
    }
    let triangles = mesh
        .triangles
        .iter()
        .enumerate()
        .map(|(t, tri)| {
            std::array::from_fn(|k| {
                let v = tri[k] as usize;
                let b = base.get(v).copied().unwrap_or(0);
                b + choice.get(3 * t + k).copied().unwrap_or(0)
            })
        })
        .collect();
    let out = Mesh {
        positions: repeat(&mesh.positions, &copies, total),
        triangles,
        normals: Some(repeat(normals, &copies, total)),
        uvs: mesh.uvs.as_deref().map(|u| repeat(u, &copies, total)),
        colors: mesh.colors.as_deref().map(|c| repeat(c, &copies, total)),
        tangents: Some(tangents),
    };
    (out, total - n)
}

/// What [`tangents`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TangentReport {
    /// Vertices added by splitting.
    pub added_vertices: usize,
    /// Corners whose MikkTSpace tangent was zero, not finite or not orthogonal.
    pub repaired_corners: usize,
    /// Whether the normals were computed (the mesh had none).
    pub computed_normals: bool,
}

/// `mesh` with MikkTSpace tangents (see the [module documentation](self)). Needs uvs; normals
/// are computed (angle-weighted, as `mesh.normals`) when missing.
pub fn tangents(mesh: &Mesh) -> Result<(Mesh, TangentReport), OpError> {
    let positions = mesh_positions(mesh).map_err(|e| e.at("mesh"))?;
    if mesh.triangles.is_empty() {
        return Err(MeshError::Empty.at("mesh"));
    }
    let input = |e: TangentError| OpError::input("mesh", e.to_string());
    let uvs = mesh
        .uvs
        .as_deref()
        .ok_or(TangentError::NoUvs)
        .map_err(input)?;
    let bad = |what, index| input(TangentError::NonFinite { index, what });
    if let Some(i) = uvs.iter().position(|u| !u.iter().all(|c| c.is_finite())) {
        return Err(bad("uv", i));
    }
    let computed;
    let normals: &[[f32; 3]] = match mesh.normals.as_deref() {
        Some(n) => {
            if let Some(i) = n.iter().position(|v| !v.iter().all(|c| c.is_finite())) {
                return Err(bad("normal", i));
            }
            n
        }
        None => {
            let (n, _) = vertex_normals(&positions, &mesh.triangles, NormalWeighting::Angle);
            computed = n.iter().map(|v| v.map(|c| c as f32)).collect::<Vec<_>>();
            &computed
        }
    };
    let (corners, repaired) =
        corner_tangents(&mesh.positions, normals, uvs, &mesh.triangles).map_err(input)?;
    let (out, added) = split_by_tangent(mesh, normals, &corners);
    Ok((
        out,
        TangentReport {
            added_vertices: added,
            repaired_corners: repaired,
            computed_normals: mesh.normals.is_none(),
        },
    ))
}

/// MikkTSpace tangents (`mesh.tangents`). See [`tangents`].
#[derive(Debug, Clone, PartialEq)]
pub struct Tangents;

impl Op for Tangents {
    type Params = NoParams;
    const ID: &'static str = "mesh.tangents";
    const SUMMARY: &'static str =
        "Computes per-vertex MikkTSpace tangents (xyz + handedness w) from uvs and normals.";
    const DOC: &'static str = r#"
Per-vertex tangents in MikkTSpace (Mikkelsen, "Simulation of wrinkled surfaces revisited",
2008), the tangent space Blender, Substance and glTF bake normal maps in: xyz is the unit
tangent along increasing u, orthogonal to the normal; w = ±1 is the handedness, the bitangent
being w · (n × t) (w = −1 where the uvs are mirrored).

MikkTSpace computes a tangent per triangle corner. A vertex whose corners all get the same
tangent keeps its index; one whose corners differ (a mirrored uv seam, say) is split into one
copy per tangent, with the same position, normal, uv and color, numbered right after it. So a
mesh that needs no split keeps its vertices and triangles exactly.

Needs uvs (an error without them). Normals are used as given (normalized); a mesh without
normals gets angle-weighted ones, as from `mesh.normals`. Corners where MikkTSpace gives no
direction (degenerate uvs or triangles) get the tangent projected on the normal's plane, or a
fixed perpendicular of the normal; they are counted. Colors pass through.

Metrics: `vertices`, `added_vertices`, `repaired_corners`, `computed_normals` (0 or 1).

Example:
    "t": (op: "mesh.tangents", inputs: { "mesh": "model.mesh" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "mesh",
            PortType::Mesh,
            "A triangle mesh with uvs (and normals, else they are computed).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The mesh with normals and tangents; vertices split where corner tangents differ.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "vertices, added_vertices, repaired_corners, computed_normals.",
            ),
        ]
    }

    fn new(_: NoParams) -> Result<Self, String> {
        Ok(Tangents)
    }
}

impl Operator for Tangents {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = mesh_input(inputs, "mesh")?;
        let (out, report) = tangents(mesh)?;
        let mut m = Metrics::new();
        m.insert("vertices".into(), out.positions.len() as f64);
        m.insert("added_vertices".into(), report.added_vertices as f64);
        m.insert("repaired_corners".into(), report.repaired_corners as f64);
        m.insert(
            "computed_normals".into(),
            f64::from(u8::from(report.computed_normals)),
        );
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(out)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::mesh_write::write_ply;

    /// An `nx × ny` grid of unit squares in the z = 0 plane, two counter-clockwise triangles
    /// each, normals +z, uvs from `uv(x, y)`.
    fn grid(nx: u32, ny: u32, uv: impl Fn(f32, f32) -> [f32; 2]) -> Mesh {
        let mut positions = Vec::new();
        for j in 0..=ny {
            for i in 0..=nx {
                positions.push([i as f32, j as f32, 0.0]);
            }
        }
        let id = |i: u32, j: u32| j * (nx + 1) + i;
        let mut triangles = Vec::new();
        for j in 0..ny {
            for i in 0..nx {
                triangles.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
                triangles.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
            }
        }
        Mesh {
            uvs: Some(positions.iter().map(|p| uv(p[0], p[1])).collect()),
            normals: Some(vec![[0.0, 0.0, 1.0]; positions.len()]),
            positions,
            triangles,
            ..Mesh::default()
        }
    }

    fn assert_frame(t: [f32; 4], expected: [f32; 4]) {
        for k in 0..4 {
            assert!((t[k] - expected[k]).abs() < 1e-5, "{t:?} vs {expected:?}");
        }
    }

    /// Unit, orthogonal to the normal, w = ±1, finite.
    fn assert_valid(mesh: &Mesh) {
        let (Some(t), Some(n)) = (&mesh.tangents, &mesh.normals) else {
            panic!("no tangents or normals")
        };
        assert_eq!(t.len(), mesh.positions.len());
        for (t, n) in t.iter().zip(n) {
            assert!(t.iter().all(|c| c.is_finite()), "{t:?}");
            let v = [t[0], t[1], t[2]].map(f64::from);
            assert!(
                (dot3(v, v).sqrt() - 1.0).abs() <= 4.0 * f64::from(f32::EPSILON),
                "{t:?}"
            );
            assert!(dot3(v, unit_normal(*n)).abs() < 1e-5, "{t:?} · {n:?}");
            assert!(t[3] == 1.0 || t[3] == -1.0, "{t:?}");
        }
        assert!(
            mesh.triangles
                .iter()
                .flatten()
                .all(|&i| (i as usize) < t.len())
        );
    }

    #[test]
    fn planar_grid_tangents_follow_u_with_the_right_handedness() {
        let plain = grid(4, 3, |x, y| [x / 4.0, y / 3.0]);
        let (out, report) = tangents(&plain).unwrap();
        assert_valid(&out);
        assert_eq!(report, TangentReport::default());
        // Nothing to split: same vertices, same triangles.
        assert_eq!(out.positions, plain.positions);
        assert_eq!(out.triangles, plain.triangles);
        for t in out.tangents.as_ref().unwrap() {
            assert_frame(*t, [1.0, 0.0, 0.0, 1.0]);
        }
        // Mirrored u: the tangent turns around and the bitangent w·(n × t) = +y needs w = −1.
        let mirrored = grid(4, 3, |x, y| [1.0 - x / 4.0, y / 3.0]);
        let (out, _) = tangents(&mirrored).unwrap();
        for t in out.tangents.as_ref().unwrap() {
            assert_frame(*t, [-1.0, 0.0, 0.0, -1.0]);
        }
        // Mirrored v instead: the tangent stays, the handedness flips.
        let flipped = grid(4, 3, |x, y| [x / 4.0, -y / 3.0]);
        let (out, _) = tangents(&flipped).unwrap();
        for t in out.tangents.as_ref().unwrap() {
            assert_frame(*t, [1.0, 0.0, 0.0, -1.0]);
        }
        // u along y: the tangent follows.
        let turned = grid(4, 3, |x, y| [y, -x]);
        let (out, _) = tangents(&turned).unwrap();
        for t in out.tangents.as_ref().unwrap() {
            assert_frame(*t, [0.0, 1.0, 0.0, 1.0]);
        }
    }

    #[test]
    fn a_mirror_seam_splits_exactly_the_seam_vertices() {
        // u = |x − 2|: mirrored left of x = 2. The seam column's 4 vertices get two frames.
        let mesh = grid(4, 3, |x, y| [(x - 2.0).abs() / 2.0, y / 3.0]);
        let (out, report) = tangents(&mesh).unwrap();
        assert_valid(&out);
        assert_eq!(report.added_vertices, 4);
        assert_eq!(out.positions.len(), mesh.positions.len() + 4);
        assert_eq!(out.triangles.len(), mesh.triangles.len());
        let t = out.tangents.as_ref().unwrap();
        let (uvs, normals) = (out.uvs.as_ref().unwrap(), out.normals.as_ref().unwrap());
        for (tri, old) in out.triangles.iter().zip(&mesh.triangles) {
            // Each corner keeps its position, uv and normal, and takes the frame of its side.
            for (&v, &o) in tri.iter().zip(old) {
                let (v, o) = (v as usize, o as usize);
                assert_eq!(out.positions[v], mesh.positions[o]);
                assert_eq!(uvs[v], mesh.uvs.as_ref().unwrap()[o]);
                assert_eq!(normals[v], [0.0, 0.0, 1.0]);
            }
            let centre_x: f32 = old
                .iter()
                .map(|&i| mesh.positions[i as usize][0])
                .sum::<f32>()
                / 3.0;
            let side = if centre_x < 2.0 {
                [-1.0, 0.0, 0.0, -1.0]
            } else {
                [1.0, 0.0, 0.0, 1.0]
            };
            for &v in tri {
                assert_frame(t[v as usize], side);
            }
        }
        // The copies follow their originals: vertex (2, 0) is 2 and its copy 3.
        assert_eq!(out.positions[2], out.positions[3]);
        assert_eq!(out.positions[4], [3.0, 0.0, 0.0]);
    }

    /// A UV sphere: `rings` bands from pole to pole, `segments` around, a seam column of
    /// duplicated vertices at u = 0 / 1 and pole rows with their own u (degenerate triangles
    /// there). u = φ/2π eastward, v = 1 − θ/π northward.
    fn uv_sphere(rings: u32, segments: u32, normals: bool) -> Mesh {
        let mut positions = Vec::new();
        let mut uvs = Vec::new();
        for i in 0..=rings {
            let theta = std::f64::consts::PI * f64::from(i) / f64::from(rings);
            for j in 0..=segments {
                let phi = std::f64::consts::TAU * f64::from(j) / f64::from(segments);
                positions.push(
                    [
                        phi.cos() * theta.sin(),
                        phi.sin() * theta.sin(),
                        theta.cos(),
                    ]
                    .map(|c| c as f32),
                );
                uvs.push([j as f32 / segments as f32, 1.0 - i as f32 / rings as f32]);
            }
        }
        let id = |i: u32, j: u32| i * (segments + 1) + j;
        let mut triangles = Vec::new();
        for i in 0..rings {
            for j in 0..segments {
                let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
                triangles.push([a, b, c]);
                triangles.push([a, c, d]);
            }
        }
        Mesh {
            normals: normals.then(|| positions.clone()),
            positions,
            triangles,
            uvs: Some(uvs),
            ..Mesh::default()
        }
    }

    #[test]
    fn sphere_tangents_point_along_increasing_u() {
        for given_normals in [true, false] {
            let mesh = uv_sphere(12, 24, given_normals);
            let (out, report) = tangents(&mesh).unwrap();
            assert_valid(&out);
            assert_eq!(report.computed_normals, !given_normals);
            let t = out.tangents.as_ref().unwrap();
            let mut checked = 0;
            for (p, t) in out.positions.iter().zip(t) {
                let p = p.map(f64::from);
                if p[2].abs() > 0.9 {
                    continue;
                }
                // East, the direction of increasing φ and so of u.
                let east = unit3([-p[1], p[0], 0.0]).unwrap();
                let v = [t[0], t[1], t[2]].map(f64::from);
                assert!(dot3(v, east) > 0.99, "at {p:?}: {t:?}");
                // v grows northward, n × east is north: right-handed.
                assert_eq!(t[3], 1.0, "at {p:?}");
                checked += 1;
            }
            assert!(checked > 200, "{checked}");
            // The seam vertices are already separate (u = 0 and u = 1): no split needed.
            assert_eq!(report.added_vertices, 0);
        }
    }

    #[test]
    fn degenerate_uvs_and_triangles_give_valid_tangents() {
        // Every uv the same: MikkTSpace has no direction anywhere.
        let flat = grid(3, 3, |_, _| [0.5, 0.5]);
        let (out, _) = tangents(&flat).unwrap();
        assert_valid(&out);
        // MikkTSpace falls back to a valid frame itself here (no repair needed); either way the
        // result is unit and orthogonal to the normal, checked above.
        // uvs collapsed to a line (v constant): u still gives the direction.
        let line = grid(3, 3, |x, _| [x, 0.0]);
        let (out, _) = tangents(&line).unwrap();
        assert_valid(&out);
        // Collinear and repeated-index triangles, an unused vertex, a tilted normal, a zero
        // normal, huge and tiny coordinates.
        let mesh = Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [2.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [5.0, 5.0, 5.0],
                [3.0e38, -3.0e38, 1e-45],
            ],
            triangles: vec![[0, 1, 2], [0, 0, 3], [0, 1, 3], [1, 5, 3]],
            normals: Some(vec![
                [0.0, 0.0, 1.0],
                [0.0, 0.0, 2.0],
                [0.0, 0.0, 0.0],
                [0.3, 0.0, 1.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
            ]),
            uvs: Some(vec![
                [0.0, 0.0],
                [1.0, 0.0],
                [2.0, 0.0],
                [0.0, 1.0],
                [0.0; 2],
                [1e30, -1e30],
            ]),
            colors: Some(vec![[0.1, 0.2, 0.3]; 6]),
            tangents: None,
        };
        let (out, _) = tangents(&mesh).unwrap();
        assert_valid(&out);
        assert_eq!(out.colors.as_ref().map(Vec::len), Some(out.positions.len()));
        // The unused vertex 4 keeps its index offset order and a perpendicular of its normal.
        let unused = out
            .positions
            .iter()
            .position(|p| *p == [5.0, 5.0, 5.0])
            .unwrap();
        assert_eq!(out.tangents.as_ref().unwrap()[unused], [0.0, 1.0, 0.0, 1.0]);
    }

    #[test]
    fn finish_tangent_repairs_and_keeps() {
        let z = [0.0, 0.0, 1.0];
        assert_eq!(
            finish_tangent([1.0, 0.0, 0.0, 1.0], z),
            ([1.0, 0.0, 0.0, 1.0], false)
        );
        assert_eq!(
            finish_tangent([0.0, 0.0, 0.0, -1.0], z),
            ([1.0, 0.0, 0.0, -1.0], true)
        );
        assert_eq!(
            finish_tangent([f32::NAN, 0.0, 0.0, f32::NAN], z),
            ([1.0, 0.0, 0.0, 1.0], true)
        );
        // Tilted out of the plane: projected back.
        let (t, fixed) = finish_tangent([0.0, 0.6, 0.8, 1.0], z);
        assert!(fixed);
        assert_eq!(t, [0.0, 1.0, 0.0, 1.0]);
        // Along the normal: no projection, the fixed perpendicular.
        assert_eq!(
            finish_tangent([0.0, 0.0, 3.0, 1.0], z),
            ([1.0, 0.0, 0.0, 1.0], true)
        );
        // Slightly long: renormalized, not counted.
        let (t, fixed) = finish_tangent([1.000_01, 0.0, 0.0, 1.0], z);
        assert!(!fixed);
        assert_eq!(t, [1.0, 0.0, 0.0, 1.0]);
        let p = perpendicular(unit3([1.0, 1.0, 1.0]).unwrap());
        assert!(dot3(p, [1.0, 1.0, 1.0]).abs() < 1e-12 && (dot3(p, p) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn errors_name_the_problem() {
        let mut no_uvs = grid(2, 2, |x, y| [x, y]);
        no_uvs.uvs = None;
        assert!(
            tangents(&no_uvs)
                .unwrap_err()
                .to_string()
                .contains("no uvs")
        );
        let mut nan = grid(2, 2, |x, y| [x, y]);
        nan.uvs.as_mut().unwrap()[4][1] = f32::NAN;
        let err = tangents(&nan).unwrap_err().to_string();
        assert!(err.contains("vertex 4") && err.contains("uv"), "{err}");
        let mut short = grid(2, 2, |x, y| [x, y]);
        short.uvs.as_mut().unwrap().pop();
        assert!(tangents(&short).is_err());
        let empty = Mesh {
            triangles: Vec::new(),
            ..grid(1, 1, |x, y| [x, y])
        };
        assert!(tangents(&empty).is_err());
    }

    #[test]
    fn tangents_survive_a_ply_round_trip_bit_for_bit() {
        let (out, _) = tangents(&uv_sphere(6, 8, true)).unwrap();
        let mut bytes = Vec::new();
        write_ply(&mut bytes, &out, true).unwrap();
        let back = crate::io::read_mesh::parse_ply(&bytes).unwrap();
        let bits = |m: &Mesh| -> Vec<[u32; 4]> {
            m.tangents
                .iter()
                .flatten()
                .map(|t| t.map(f32::to_bits))
                .collect()
        };
        assert_eq!(bits(&back), bits(&out));
        assert_eq!(back.triangles, out.triangles);
    }

    #[test]
    fn operator_through_the_registry() {
        let mut registry = ocellus_engine::Registry::new();
        crate::register_builtins(&mut registry).unwrap();
        let factory = registry.get("mesh.tangents").unwrap();
        let op = factory.build(&ocellus_engine::ParamMap::new()).unwrap();
        let specs = Tangents::inputs();
        let mut mesh = grid(4, 3, |x, y| [(x - 2.0).abs(), y]);
        mesh.normals = None;
        let values = [Some(Value::Mesh(Arc::new(mesh)))];
        let ctx = RunContext {
            node: "t".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("no metrics")
        };
        assert_eq!(m.get("added_vertices"), Some(&4.0));
        assert_eq!(m.get("vertices"), Some(&24.0));
        assert_eq!(m.get("computed_normals"), Some(&1.0));
        let Some(Value::Mesh(mesh)) = out.take("mesh") else {
            panic!("no mesh")
        };
        assert_valid(&mesh);
    }
}
