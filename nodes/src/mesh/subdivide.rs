//! Subdivision surfaces: `mesh.subdivide` (Loop and Catmull–Clark) with their limit masks.
//!
//! **Loop** (C. Loop, "Smooth subdivision surfaces based on triangles", M.S. thesis, Utah 1987),
//! triangles only: every triangle becomes four through its edge midpoints;
//! - edge point of an interior edge `ab` with opposite corners `c`, `d`: `3/8 (a + b) + 1/8 (c + d)`;
//! - vertex point of an interior vertex of valence `n`: `(1 − nβ) v + β Σ vᵢ` with Loop's original
//!   `β = (5/8 − (3/8 + 1/4 cos(2π/n))²) / n` (not Warren's simplification `3/(8n)`);
//! - limit position: `(1 − nγ) v + γ Σ vᵢ`, `γ = 1 / (n + 3/(8β))` (the left eigenvector of the
//!   local subdivision matrix; `1/2, 1/12, …` for `n = 6`).
//!
//! **Catmull–Clark** (Catmull & Clark, "Recursively generated B-spline surfaces on arbitrary
//! topological meshes", CAD 1978), any polygons, output quads;
//! - face point: the centroid; edge point of an interior edge: `(a + b + F₁ + F₂) / 4`;
//! - vertex point of an interior vertex of valence `n`: `(Q + 2R + (n − 3) v) / n`, `Q` the mean
//!   of the adjacent face points, `R` the mean of the adjacent edge midpoints;
//! - limit position (quad meshes, so from level 1 on): `(n² v + 4 Σ eᵢ + Σ fᵢ) / (n (n + 5))`,
//!   `eᵢ` the edge neighbours, `fᵢ` the diagonal corners of the quads around `v` (Halstead,
//!   Kass & DeRose, "Efficient, fair interpolation using Catmull–Clark surfaces", SIGGRAPH 1993).
//!
//! **Boundaries** (both schemes) follow the cubic B-spline curve of the boundary polygon, so a
//! boundary never depends on the interior (Hoppe et al., "Piecewise smooth surface
//! reconstruction", SIGGRAPH 1994): boundary edge point `(a + b) / 2`, boundary vertex point
//! `3/4 v + 1/8 (v₋ + v₊)` (its two boundary neighbours), limit `(v₋ + 4 v + v₊) / 6`.
//!
//! Old vertices keep their indices, then come the edge points (edges in order of their lower
//! halfedge), then (Catmull–Clark) the face points, so a level-`k` vertex `v` is vertex `v` at
//! level `k + 1` too; the tests use that: its limit position computed at both levels is the
//! same point. Every point is computed independently in parallel and sums run in rotation
//! order, so results do not depend on the thread count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::halfedge::{HalfedgeMesh, MeshError, NONE, mesh_input, mesh_positions};
use super::normals::{NormalWeighting, vertex_normals};
use super::pointcloud::par_map;

fn add(a: &mut [f64; 3], b: [f64; 3]) {
    for k in 0..3 {
        a[k] += b[k];
    }
}

fn lerp3(terms: &[(f64, [f64; 3])]) -> [f64; 3] {
    let mut s = [0.0; 3];
    for (w, p) in terms {
        for k in 0..3 {
            s[k] += w * p[k];
        }
    }
    s
}

/// Loop's original vertex weight `β(n)`.
pub fn loop_beta(n: usize) -> f64 {
    let n = n as f64;
    let c = 3.0 / 8.0 + 0.25 * (std::f64::consts::TAU / n).cos();
    (5.0 / 8.0 - c * c) / n
}

/// Per-halfedge edge index (edges numbered in order of their lower halfedge) and the lower
/// halfedge of each edge. The mesh must have no removed element.
fn edge_index(mesh: &HalfedgeMesh) -> (Vec<u32>, Vec<u32>) {
    let nh = mesh.halfedge_capacity();
    let mut id = vec![NONE; nh];
    let mut edges = Vec::with_capacity(nh / 2);
    for h in 0..nh as u32 {
        let t = mesh.twin(h);
        if h < t {
            id[h as usize] = edges.len() as u32;
            id[t as usize] = edges.len() as u32;
            edges.push(h);
        }
    }
    (id, edges)
}

/// `(v₋, v₊)`: the boundary neighbours of boundary vertex `v`.
fn boundary_neighbors(mesh: &HalfedgeMesh, v: u32) -> (u32, u32) {
    let h = mesh.vertex_halfedge(v);
    (mesh.origin(mesh.prev(h)), mesh.dest(h))
}

/// One Loop step of the per-vertex data `data` (positions or any attribute) over the triangle
/// mesh `mesh`: old vertices first, then one point per edge.
pub fn loop_points(mesh: &HalfedgeMesh, data: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let (_, edges) = edge_index(mesh);
    let nv = mesh.vertex_capacity() as u32;
    let mut out = par_map(nv as usize, |v| {
        let v = v as u32;
        let p = data[v as usize];
        if mesh.vertex_halfedge(v) == NONE {
            p
        } else if mesh.is_boundary_vertex(v) {
            let (a, b) = boundary_neighbors(mesh, v);
            lerp3(&[
                (0.75, p),
                (0.125, data[a as usize]),
                (0.125, data[b as usize]),
            ])
        } else {
            let mut sum = [0.0; 3];
            let mut n = 0;
            for h in mesh.outgoing(v) {
                add(&mut sum, data[mesh.dest(h) as usize]);
                n += 1;
            }
            let beta = loop_beta(n);
            lerp3(&[(1.0 - n as f64 * beta, p), (beta, sum)])
        }
    });
    out.extend(par_map(edges.len(), |e| {
        let h = edges[e];
        let t = mesh.twin(h);
        let (a, b) = (data[mesh.origin(h) as usize], data[mesh.origin(t) as usize]);
        if mesh.is_boundary_edge(h) {
            lerp3(&[(0.5, a), (0.5, b)])
        } else {
            let c = data[mesh.origin(mesh.prev(h)) as usize];
            let d = data[mesh.origin(mesh.prev(t)) as usize];
            lerp3(&[(0.375, a), (0.375, b), (0.125, c), (0.125, d)])
        }
    }));
    out
}

/// One Loop step of a triangle mesh's connectivity (vertex numbering of [`loop_points`]).
pub fn loop_triangles(mesh: &HalfedgeMesh) -> Vec<[u32; 3]> {
    let (id, _) = edge_index(mesh);
    let nv = mesh.vertex_capacity() as u32;
    let mut out = Vec::with_capacity(4 * mesh.face_capacity());
    for f in 0..mesh.face_capacity() as u32 {
        let h0 = mesh.face_halfedge(f);
        let (h1, h2) = (mesh.next(h0), mesh.prev(h0));
        let [a, b, c] = [h0, h1, h2].map(|h| mesh.origin(h));
        let [m0, m1, m2] = [h0, h1, h2].map(|h| nv + id[h as usize]);
        out.extend([[a, m0, m2], [b, m1, m0], [c, m2, m1], [m0, m1, m2]]);
    }
    out
}

/// Limit positions of a triangle mesh's vertices under Loop subdivision.
pub fn loop_limit(mesh: &HalfedgeMesh) -> Vec<[f64; 3]> {
    par_map(mesh.vertex_capacity(), |v| {
        let v = v as u32;
        let p = mesh.position(v);
        if mesh.vertex_halfedge(v) == NONE {
            p
        } else if mesh.is_boundary_vertex(v) {
            boundary_limit(mesh, v)
        } else {
            let mut sum = [0.0; 3];
            let mut n = 0;
            for h in mesh.outgoing(v) {
                add(&mut sum, mesh.position(mesh.dest(h)));
                n += 1;
            }
            let gamma = 1.0 / (n as f64 + 3.0 / (8.0 * loop_beta(n)));
            lerp3(&[(1.0 - n as f64 * gamma, p), (gamma, sum)])
        }
    })
}

fn boundary_limit(mesh: &HalfedgeMesh, v: u32) -> [f64; 3] {
    let (a, b) = boundary_neighbors(mesh, v);
    lerp3(&[
        (4.0 / 6.0, mesh.position(v)),
        (1.0 / 6.0, mesh.position(a)),
        (1.0 / 6.0, mesh.position(b)),
    ])
}

/// One Catmull–Clark step of the per-vertex data over the polygon mesh `mesh`: old vertices,
/// then edge points, then face points.
pub fn catmull_clark_points(mesh: &HalfedgeMesh, data: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let (_, edges) = edge_index(mesh);
    let face_points = par_map(mesh.face_capacity(), |f| {
        let mut s = [0.0; 3];
        let mut n = 0.0;
        for h in mesh.face_cycle(f as u32) {
            add(&mut s, data[mesh.origin(h) as usize]);
            n += 1.0;
        }
        s.map(|x| x / n)
    });
    let mut out = par_map(mesh.vertex_capacity(), |v| {
        let v = v as u32;
        let p = data[v as usize];
        if mesh.vertex_halfedge(v) == NONE {
            p
        } else if mesh.is_boundary_vertex(v) {
            let (a, b) = boundary_neighbors(mesh, v);
            lerp3(&[
                (0.75, p),
                (0.125, data[a as usize]),
                (0.125, data[b as usize]),
            ])
        } else {
            let (mut q, mut r) = ([0.0; 3], [0.0; 3]);
            let mut n = 0;
            for h in mesh.outgoing(v) {
                add(&mut q, face_points[mesh.face(h) as usize]);
                add(
                    &mut r,
                    lerp3(&[(0.5, p), (0.5, data[mesh.dest(h) as usize])]),
                );
                n += 1;
            }
            let n = n as f64;
            lerp3(&[(1.0 / (n * n), q), (2.0 / (n * n), r), ((n - 3.0) / n, p)])
        }
    });
    out.extend(par_map(edges.len(), |e| {
        let h = edges[e];
        let t = mesh.twin(h);
        let (a, b) = (data[mesh.origin(h) as usize], data[mesh.origin(t) as usize]);
        if mesh.is_boundary_edge(h) {
            lerp3(&[(0.5, a), (0.5, b)])
        } else {
            let (f1, f2) = (
                face_points[mesh.face(h) as usize],
                face_points[mesh.face(t) as usize],
            );
            lerp3(&[(0.25, a), (0.25, b), (0.25, f1), (0.25, f2)])
        }
    }));
    out.extend(face_points);
    out
}

/// One Catmull–Clark step of a polygon mesh's connectivity: one quad per face corner,
/// `[corner, edge point after it, face point, edge point before it]`.
pub fn catmull_clark_quads(mesh: &HalfedgeMesh) -> Vec<[u32; 4]> {
    let (id, edges) = edge_index(mesh);
    let nv = mesh.vertex_capacity() as u32;
    let first_face = nv + edges.len() as u32;
    let mut out = Vec::with_capacity(mesh.halfedge_capacity());
    for f in 0..mesh.face_capacity() as u32 {
        for h in mesh.face_cycle(f) {
            out.push([
                mesh.origin(h),
                nv + id[h as usize],
                first_face + f,
                nv + id[mesh.prev(h) as usize],
            ]);
        }
    }
    out
}

/// Limit positions under Catmull–Clark subdivision of a quad mesh's vertices; fails on a face
/// that is not a quad.
pub fn catmull_clark_limit(mesh: &HalfedgeMesh) -> Result<Vec<[f64; 3]>, MeshError> {
    for f in 0..mesh.face_capacity() as u32 {
        if !mesh.face_alive(f) {
            continue;
        }
        let len = mesh.face_cycle(f).count();
        if len != 4 {
            return Err(MeshError::NotQuad {
                face: f as usize,
                len,
            });
        }
    }
    Ok(par_map(mesh.vertex_capacity(), |v| {
        let v = v as u32;
        let p = mesh.position(v);
        if mesh.vertex_halfedge(v) == NONE {
            p
        } else if mesh.is_boundary_vertex(v) {
            boundary_limit(mesh, v)
        } else {
            let (mut e, mut d) = ([0.0; 3], [0.0; 3]);
            let mut n = 0;
            for h in mesh.outgoing(v) {
                add(&mut e, mesh.position(mesh.dest(h)));
                add(&mut d, mesh.position(mesh.dest(mesh.next(h))));
                n += 1;
            }
            let n = n as f64;
            let s = 1.0 / (n * (n + 5.0));
            lerp3(&[(n * n * s, p), (4.0 * s, e), (s, d)])
        }
    }))
}

param_enum! {
    /// The scheme of `mesh.subdivide`.
    pub enum SubdivisionMethod {
        /// Loop's triangle scheme.
        Loop = "loop",
        /// Catmull–Clark (quads, triangulated for output).
        CatmullClark = "catmull_clark",
    }
}

/// Triangles after `levels` steps of `method` on `triangles` triangles.
pub fn subdivided_triangles(method: SubdivisionMethod, triangles: u64, levels: u32) -> u64 {
    if levels == 0 {
        return triangles;
    }
    let grow = 4u64.saturating_pow(levels.saturating_sub(1));
    match method {
        SubdivisionMethod::Loop => triangles.saturating_mul(4).saturating_mul(grow),
        // 3 quads per triangle, ×4 per further level, 2 triangles per quad.
        SubdivisionMethod::CatmullClark => triangles.saturating_mul(6).saturating_mul(grow),
    }
}

/// A subdivided triangle mesh and its per-vertex attributes.
#[derive(Debug, Clone, PartialEq)]
pub struct Subdivided {
    /// Positions.
    pub positions: Vec<[f64; 3]>,
    /// Triangles (Catmull–Clark quads split along their corner-to-face-point diagonal).
    pub triangles: Vec<[u32; 3]>,
    /// Attributes, subdivided with the position masks.
    pub attributes: Vec<Vec<[f64; 3]>>,
}

/// `levels` steps of `method` on a triangle mesh, carrying `attributes` (per-vertex 3-vectors)
/// with the same masks; the mesh must be a 2-manifold (checked every level).
pub fn subdivide(
    positions: Vec<[f64; 3]>,
    triangles: &[[u32; 3]],
    attributes: Vec<Vec<[f64; 3]>>,
    method: SubdivisionMethod,
    levels: u32,
) -> Result<Subdivided, MeshError> {
    let mut positions = positions;
    let mut attributes = attributes;
    let mut triangles = triangles.to_vec();
    let mut quads: Vec<[u32; 4]> = Vec::new();
    for level in 0..levels {
        let mesh = if level == 0 || method == SubdivisionMethod::Loop {
            HalfedgeMesh::from_triangles(positions, &triangles)?
        } else {
            let faces: Vec<Vec<u32>> = quads.iter().map(|q| q.to_vec()).collect();
            HalfedgeMesh::from_polygons(positions, &faces)?
        };
        let step = match method {
            SubdivisionMethod::Loop => loop_points,
            SubdivisionMethod::CatmullClark => catmull_clark_points,
        };
        positions = step(&mesh, mesh.positions());
        attributes = attributes.iter().map(|a| step(&mesh, a)).collect();
        match method {
            SubdivisionMethod::Loop => triangles = loop_triangles(&mesh),
            SubdivisionMethod::CatmullClark => quads = catmull_clark_quads(&mesh),
        }
    }
    if method == SubdivisionMethod::CatmullClark && levels > 0 {
        triangles = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
    }
    Ok(Subdivided {
        positions,
        triangles,
        attributes,
    })
}

/// Largest `levels` of `mesh.subdivide`.
pub const MAX_LEVELS: u32 = 8;

params! {
    /// Parameters of `mesh.subdivide`.
    pub struct SubdivideParams {
        /// "loop" or "catmull_clark". Default "loop".
        method: SubdivisionMethod = SubdivisionMethod::Loop,
        /// Subdivision steps (0 to 8). Default 1.
        levels: u32 = 1 => [min = 0, max = 8],
        /// Largest number of output triangles; more is an error before any work. Default
        /// 20 000 000.
        max_triangles: u64 = 20_000_000 => [min = 1],
    }
}

/// Subdivision (`mesh.subdivide`). See [`subdivide`].
#[derive(Debug, Clone, PartialEq)]
pub struct Subdivide {
    params: SubdivideParams,
}

impl Op for Subdivide {
    type Params = SubdivideParams;
    const ID: &'static str = "mesh.subdivide";
    const SUMMARY: &'static str =
        "Subdivides a triangle mesh `levels` times: Loop or Catmull–Clark, with boundary rules.";
    const DOC: &'static str = r#"
"loop" (Loop 1987): each triangle becomes four; edge points 3/8 (a + b) + 1/8 (c + d), vertex
points (1 − nβ) v + β Σ neighbours with Loop's original β(n) = (5/8 − (3/8 + 1/4 cos 2π/n)²)/n.

"catmull_clark" (Catmull & Clark 1978): face points (centroids), edge points
(a + b + F₁ + F₂)/4, vertex points (Q + 2R + (n − 3) v)/n; the first level turns each triangle
into three quads, later levels each quad into four; the final quads are split into two
triangles along the diagonal from the original corner to the face point.

Boundaries follow the cubic B-spline of the boundary polygon (midpoints, 3/4 v + 1/8 of the two
boundary neighbours), so open meshes keep their boundary curve. The mesh must be a consistently
oriented 2-manifold (checked each level). Colors and texture coordinates are subdivided with the
same masks (no seam handling); normals, if present, are recomputed (angle-weighted).

The output size is checked before any work: Loop gives 4^levels × triangles, Catmull–Clark
6 × 4^(levels − 1) × triangles; above `max_triangles` it is an error.

Metrics: `input_triangles`, `output_triangles`, `output_vertices`.

Example:
    "smooth": (op: "mesh.subdivide", inputs: { "mesh": "cube.mesh" }, params: (method: "catmull_clark", levels: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "mesh",
            PortType::Mesh,
            "A manifold triangle mesh.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The subdivided triangle mesh."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "input_triangles, output_triangles, output_vertices.",
            ),
        ]
    }

    fn new(p: SubdivideParams) -> Result<Self, String> {
        if p.levels > MAX_LEVELS {
            return Err(format!(
                "`levels` must be at most {MAX_LEVELS}, got {}",
                p.levels
            ));
        }
        if p.max_triangles == 0 {
            return Err("`max_triangles` must be at least 1".into());
        }
        Ok(Subdivide { params: p })
    }
}

impl Operator for Subdivide {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = mesh_input(inputs, "mesh")?;
        let p = &self.params;
        let want = subdivided_triangles(p.method, mesh.triangles.len() as u64, p.levels);
        if want > p.max_triangles {
            return Err(MeshError::TooLarge(format!(
                "subdividing {} triangles {} times gives {want} triangles, above max_triangles {}",
                mesh.triangles.len(),
                p.levels,
                p.max_triangles
            ))
            .at("mesh"));
        }
        let positions = mesh_positions(mesh).map_err(|e| e.at("mesh"))?;
        if mesh.triangles.is_empty() {
            return Err(MeshError::Empty.at("mesh"));
        }
        let to64 = |v: &Vec<[f32; 3]>| v.iter().map(|c| c.map(f64::from)).collect::<Vec<_>>();
        let mut attributes = Vec::new();
        if let Some(c) = &mesh.colors {
            attributes.push(to64(c));
        }
        if let Some(uv) = &mesh.uvs {
            attributes.push(
                uv.iter()
                    .map(|t| [f64::from(t[0]), f64::from(t[1]), 0.0])
                    .collect(),
            );
        }
        let s = subdivide(positions, &mesh.triangles, attributes, p.method, p.levels)
            .map_err(|e| e.at("mesh"))?;
        let to32 = |v: &[[f64; 3]]| v.iter().map(|c| c.map(|x| x as f32)).collect::<Vec<_>>();
        let mut attrs = s.attributes.iter();
        let colors = mesh
            .colors
            .as_ref()
            .and_then(|_| attrs.next())
            .map(|c| to32(c));
        let uvs = mesh.uvs.as_ref().and_then(|_| attrs.next()).map(|c| {
            c.iter()
                .map(|t| [t[0] as f32, t[1] as f32])
                .collect::<Vec<_>>()
        });
        let normals = mesh.normals.as_ref().map(|_| {
            let (n, _) = vertex_normals(&s.positions, &s.triangles, NormalWeighting::Angle);
            to32(&n)
        });
        let out = Mesh {
            positions: to32(&s.positions),
            triangles: s.triangles,
            normals,
            uvs,
            colors,
            tangents: None,
        };
        let mut m = Metrics::new();
        m.insert("input_triangles".into(), mesh.triangles.len() as f64);
        m.insert("output_triangles".into(), out.triangles.len() as f64);
        m.insert("output_vertices".into(), out.positions.len() as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(out)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::halfedge::tests::{cube_quads, grid, icosphere, octahedron};
    use crate::mesh::normals::{cross, dot, sub};

    fn close(a: [f64; 3], b: [f64; 3], tol: f64) -> bool {
        (0..3).all(|k| (a[k] - b[k]).abs() <= tol)
    }

    /// Area and signed volume of a polygon mesh, fanned from each face's first corner.
    fn area_volume(p: &[[f64; 3]], faces: &[Vec<u32>]) -> (f64, f64) {
        let (mut area, mut volume) = (0.0, 0.0);
        for f in faces {
            let a = p[f[0] as usize];
            for w in f[1..].windows(2) {
                let (b, c) = (p[w[0] as usize], p[w[1] as usize]);
                let n = cross(sub(b, a), sub(c, a));
                area += 0.5 * dot(n, n).sqrt();
                volume += dot(a, cross(b, c)) / 6.0;
            }
        }
        (area, volume)
    }

    #[test]
    fn loop_beta_and_masks_by_hand() {
        assert!((loop_beta(6) - 1.0 / 16.0).abs() < 1e-15);
        // n = 3: (5/8 − (3/8 − 1/8)²)/3 = (5/8 − 1/16)/3 = 3/16.
        assert!((loop_beta(3) - 3.0 / 16.0).abs() < 1e-15);
        // A regular vertex's limit mask is 1/2 centre, 1/12 each neighbour.
        let (p, t) = grid(2, 2);
        let m = HalfedgeMesh::from_triangles(p, &t).unwrap();
        let lim = loop_limit(&m);
        // Vertex 4 = (1, 1) is interior with 6 neighbours in the flat grid: stays put.
        assert!(close(lim[4], [1.0, 1.0, 0.0], 1e-15));
        // Corner 0 = (0, 0) on the boundary: (v₋ + 4v + v₊)/6 with neighbours (1,0) and (0,1).
        assert!(close(lim[0], [1.0 / 6.0, 1.0 / 6.0, 0.0], 1e-15));
        // One step of the octahedron: edge points of the unit octahedron.
        let oct = octahedron();
        let p = loop_points(&oct, oct.positions());
        assert_eq!(p.len(), 6 + 12);
        // Vertex (1,0,0), n = 4: β = (5/8 − 3/8·3/8)/4 = 31/256; its neighbours (0,±1,0) and
        // (0,0,±1) sum to 0, so it moves to (1 − 4β, 0, 0).
        let beta = loop_beta(4);
        assert!((beta - 31.0 / 256.0).abs() < 1e-15);
        assert!(close(p[0], [1.0 - 4.0 * beta, 0.0, 0.0], 1e-15));
        // Edge (0, 2) = (1,0,0)–(0,1,0), opposite corners (0,0,±1): 3/8 (1, 1, 0).
        let (id, _) = edge_index(&oct);
        let e = id[oct.find_halfedge(0, 2).unwrap() as usize] as usize;
        assert!(close(p[6 + e], [0.375, 0.375, 0.0], 1e-15));
    }

    #[test]
    fn loop_keeps_topology_and_its_limit_surface() {
        for mut mesh in [icosphere(0, 1, 0.5), {
            let (p, t) = grid(3, 2);
            let p = p
                .iter()
                .map(|v| [v[0], v[1], 0.1 * v[0] * v[1] - 0.2 * v[0] * v[0]])
                .collect();
            HalfedgeMesh::from_triangles(p, &t).unwrap()
        }] {
            let (chi, loops) = (mesh.euler_characteristic(), mesh.boundary_loops().len());
            for _ in 0..3 {
                let (v, e, f) = (mesh.num_vertices(), mesh.num_edges(), mesh.num_faces());
                let limit = loop_limit(&mesh);
                let p = loop_points(&mesh, mesh.positions());
                let t = loop_triangles(&mesh);
                let next = HalfedgeMesh::from_triangles(p, &t).unwrap();
                next.validate().unwrap();
                assert_eq!(next.num_vertices(), v + e);
                assert_eq!(next.num_faces(), 4 * f);
                assert_eq!(next.num_edges(), 2 * e + 3 * f);
                assert_eq!(next.euler_characteristic(), chi);
                assert_eq!(next.boundary_loops().len(), loops);
                // Old vertex v is vertex v again; its limit point does not move.
                let again = loop_limit(&next);
                for (i, q) in limit.iter().enumerate() {
                    assert!(close(*q, again[i], 1e-12), "{i}: {q:?} {:?}", again[i]);
                }
                mesh = next;
            }
        }
    }

    #[test]
    fn catmull_clark_cube_limit_points_by_hand() {
        let (p, q) = cube_quads();
        let m = HalfedgeMesh::from_polygons(p, &q).unwrap();
        // Corner (1,1,1): (9 v + 4 Σe + Σf)/24 with Σe = (1,1,1), Σf = (−1,−1,−1): (½,½,½).
        let lim = catmull_clark_limit(&m).unwrap();
        for (v, l) in m.positions().iter().zip(&lim) {
            assert!(close(*l, v.map(|x| 0.5 * x), 1e-15));
        }
        // Level 1: corner points (Q + 2R)/3 = 5/9 (±1, ±1, ±1); edge points 3/4 (·); the face
        // point (0, 0, 1) is regular, its limit (16·1 + 4·4·3/4 + 4·5/9)/36 = 68/81 on z.
        let p1 = catmull_clark_points(&m, m.positions());
        assert!(close(p1[7], [5.0 / 9.0; 3], 1e-15));
        let faces: Vec<Vec<u32>> = catmull_clark_quads(&m).iter().map(|q| q.to_vec()).collect();
        let m1 = HalfedgeMesh::from_polygons(p1, &faces).unwrap();
        let lim1 = catmull_clark_limit(&m1).unwrap();
        // The face point of face 1 (z = +1) is vertex 8 + 12 + 1.
        assert!(close(m1.position(21), [0.0, 0.0, 1.0], 1e-15));
        assert!(close(lim1[21], [0.0, 0.0, 68.0 / 81.0], 1e-15));
    }

    #[test]
    fn catmull_clark_cube_converges_to_its_limit_surface() {
        let (p, q) = cube_quads();
        let mut mesh = HalfedgeMesh::from_polygons(p, &q).unwrap();
        let mut faces = q;
        let mut measures = vec![area_volume(mesh.positions(), &faces)];
        let mut gaps = Vec::new();
        for level in 0..5 {
            let (v, e, f) = (mesh.num_vertices(), mesh.num_edges(), mesh.num_faces());
            let corners: usize = faces.iter().map(Vec::len).sum();
            let limit = catmull_clark_limit(&mesh).unwrap();
            // How far the control points are from the surface, for the convergence rate.
            let gap = (0..v)
                .map(|i| {
                    let d = sub(limit[i], mesh.position(i as u32));
                    dot(d, d).sqrt()
                })
                .fold(0.0, f64::max);
            gaps.push(gap);
            let p = catmull_clark_points(&mesh, mesh.positions());
            faces = catmull_clark_quads(&mesh)
                .iter()
                .map(|q| q.to_vec())
                .collect();
            let next = HalfedgeMesh::from_polygons(p, &faces).unwrap();
            next.validate().unwrap();
            assert_eq!(next.num_vertices(), v + e + f);
            assert_eq!(next.num_faces(), corners);
            assert_eq!(next.num_edges(), 2 * e + corners);
            assert!(next.is_watertight());
            assert_eq!((next.euler_characteristic(), next.genus()), (2, 0));
            let again = catmull_clark_limit(&next).unwrap();
            for i in 0..v {
                assert!(close(limit[i], again[i], 1e-12), "level {level} vertex {i}");
            }
            measures.push(area_volume(next.positions(), &faces));
            mesh = next;
        }
        // Control points approach the surface about 4× closer each level (O(h²)).
        for w in gaps.windows(2).skip(1) {
            let r = w[1] / w[0];
            assert!(r > 0.15 && r < 0.35, "{gaps:?}");
        }
        // Area and volume converge geometrically (successive differences shrink ≥ 2.5×),
        // volume decreasing from the cube's 8 and staying above the inscribed limit corners'
        // cube (side 1, volume 1).
        for w in measures.windows(3) {
            let (d0, d1) = ((w[1].0 - w[0].0).abs(), (w[2].0 - w[1].0).abs());
            assert!(d1 < d0 / 2.5, "area {measures:?}");
            let (d0, d1) = ((w[1].1 - w[0].1).abs(), (w[2].1 - w[1].1).abs());
            assert!(d1 < d0 / 2.5, "volume {measures:?}");
            assert!(w[2].1 < w[1].1 && w[2].1 > 1.0);
        }
    }

    #[test]
    fn catmull_clark_of_triangles_and_open_meshes() {
        // Triangles → quads at level 1; from there the limit points agree level to level, on
        // the boundary too (a curved open grid).
        let (p, t) = grid(3, 2);
        let p: Vec<[f64; 3]> = p.iter().map(|v| [v[0], v[1], 0.3 * v[0] * v[1]]).collect();
        let s = subdivide(
            p.clone(),
            &t,
            vec![p.clone()],
            SubdivisionMethod::CatmullClark,
            1,
        )
        .unwrap();
        assert_eq!(s.triangles.len(), 6 * t.len());
        // The attribute (a copy of the positions) follows the positions exactly.
        assert_eq!(s.attributes[0], s.positions);
        let m0 = HalfedgeMesh::from_triangles(p, &t).unwrap();
        let p1 = catmull_clark_points(&m0, m0.positions());
        let q1: Vec<Vec<u32>> = catmull_clark_quads(&m0)
            .iter()
            .map(|q| q.to_vec())
            .collect();
        let m1 = HalfedgeMesh::from_polygons(p1, &q1).unwrap();
        m1.validate().unwrap();
        assert_eq!(m1.boundary_loops().len(), 1);
        let l1 = catmull_clark_limit(&m1).unwrap();
        let p2 = catmull_clark_points(&m1, m1.positions());
        let q2: Vec<Vec<u32>> = catmull_clark_quads(&m1)
            .iter()
            .map(|q| q.to_vec())
            .collect();
        let m2 = HalfedgeMesh::from_polygons(p2, &q2).unwrap();
        let l2 = catmull_clark_limit(&m2).unwrap();
        for i in 0..m1.vertex_capacity() {
            assert!(close(l1[i], l2[i], 1e-12), "{i}");
        }
        assert!(matches!(
            catmull_clark_limit(&m0),
            Err(MeshError::NotQuad { len: 3, .. })
        ));
    }

    #[test]
    fn subdivide_counts_caps_and_rejects_non_manifold_input() {
        assert_eq!(subdivided_triangles(SubdivisionMethod::Loop, 10, 3), 640);
        assert_eq!(
            subdivided_triangles(SubdivisionMethod::CatmullClark, 10, 3),
            960
        );
        assert_eq!(subdivided_triangles(SubdivisionMethod::Loop, 10, 0), 10);
        assert_eq!(
            subdivided_triangles(SubdivisionMethod::Loop, u64::MAX / 2, 8),
            u64::MAX
        );
        let (p, t) = grid(2, 1);
        let s = subdivide(p.clone(), &t, vec![], SubdivisionMethod::Loop, 2).unwrap();
        assert_eq!(s.triangles.len(), 16 * t.len());
        let s0 = subdivide(p.clone(), &t, vec![], SubdivisionMethod::Loop, 0).unwrap();
        assert_eq!((s0.positions, s0.triangles), (p.clone(), t.clone()));
        let bad = [[0, 1, 2], [0, 1, 3], [0, 1, 4]];
        assert!(matches!(
            subdivide(p, &bad, vec![], SubdivisionMethod::Loop, 1),
            Err(MeshError::NonManifoldEdge { .. })
        ));
    }

    #[test]
    fn subdivision_does_not_depend_on_the_thread_count() {
        let m = crate::render::primitives::bumpy_icosphere(2, 0.2, 5);
        let p: Vec<[f64; 3]> = m.positions.iter().map(|v| v.map(f64::from)).collect();
        let run = |threads, method| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| subdivide(p.clone(), &m.triangles, vec![], method, 2).unwrap())
        };
        for method in [SubdivisionMethod::Loop, SubdivisionMethod::CatmullClark] {
            assert_eq!(run(1, method), run(3, method));
        }
    }

    /// One Loop level of a ~100 k-triangle mesh (run with `--release --ignored`).
    #[test]
    #[ignore]
    fn loop_timing_100k() {
        let m = crate::render::primitives::bumpy_icosphere(6, 0.2, 5);
        let p: Vec<[f64; 3]> = m.positions.iter().map(|v| v.map(f64::from)).collect();
        let start = std::time::Instant::now();
        let s = subdivide(p, &m.triangles, vec![], SubdivisionMethod::Loop, 1).unwrap();
        eprintln!(
            "loop: {} → {} triangles in {:.3} s",
            m.triangles.len(),
            s.triangles.len(),
            start.elapsed().as_secs_f64()
        );
    }
}
