//! The halfedge mesh every mesh-processing operator works on, its invariants and its local
//! operations, plus the conversions from and to the engine's indexed `Mesh`.
//!
//! [`HalfedgeMesh`] stores, per halfedge, its `twin` (the opposite halfedge of the same edge),
//! `next` and `prev` (the cycle of its face, or of its boundary loop), its `origin` vertex and
//! its `face`; a halfedge on the boundary has no face ([`NONE`]) and its `next`/`prev` run along
//! the boundary loop. Every vertex keeps one outgoing halfedge, the boundary one when the vertex
//! lies on the boundary, so that "is this a boundary vertex" is one lookup and rotating from it
//! visits the whole fan. Every face keeps one of its halfedges. This is the layout of OpenMesh
//! (Botsch, Steinberg, Bischoff & Kobbelt, "OpenMesh — a generic and efficient polygon mesh data
//! structure", OpenSG 2002) with explicit twins, so that a collapse can re-pair halfedges.
//!
//! Building from an indexed polygon mesh sorts the undirected edges, which rejects (typed
//! [`MeshError`]) an edge of more than two faces, two faces using an edge in the same direction
//! (inconsistent orientation or a duplicated face) and a vertex whose faces form more than one
//! fan (a "bow tie", or two cones touching at a tip). [`HalfedgeMesh::validate`] re-checks every
//! invariant from scratch; tests call it after every operation.
//!
//! Local operations on triangles, all keeping the invariants:
//! - [`HalfedgeMesh::flip_edge`]: the diagonal of the two triangles of an interior edge is turned;
//!   refused when the new edge already exists.
//! - [`HalfedgeMesh::split_edge`]: a new vertex on the edge, each adjacent triangle split in two.
//! - [`HalfedgeMesh::collapse_edge`]: the edge's origin is merged into its destination, its one or
//!   two triangles vanish. [`HalfedgeMesh::can_collapse`] is the link condition of Dey, Edelsbrunner,
//!   Guha & Nekhayev ("Topology preserving edge contraction", Publ. Inst. Math. 1999): the
//!   contraction of `ab` keeps a 2-manifold exactly when `Lk(a) ∩ Lk(b) = Lk(ab)`, with the
//!   boundary closed off by a virtual vertex joined to every boundary vertex (so both ends on the
//!   boundary of an interior edge, or a triangle with two boundary edges, are refused).
//!
//! Removed elements are only marked; indices of the others stay valid, and
//! [`HalfedgeMesh::to_polygons`] compacts.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, OpError};
use ocellus_engine::value::{Mesh, Value};
use rayon::prelude::*;

/// "No element": the face of a boundary halfedge, the halfedge of an isolated vertex.
pub const NONE: u32 = u32::MAX;

/// Why a mesh could not be read as a 2-manifold (or is not one any more).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// The mesh has no face.
    #[error("the mesh has no triangles")]
    Empty,
    /// A position holds NaN or an infinity.
    #[error("vertex {index} is not finite")]
    NonFinite {
        /// Index of the first bad vertex.
        index: usize,
    },
    /// A face refers to a vertex that does not exist.
    #[error("face {face} refers to vertex {index}, but the mesh has {vertices} vertices")]
    IndexOutOfRange {
        /// The face.
        face: usize,
        /// The bad index.
        index: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// A face has fewer than three corners.
    #[error("face {face} has {len} corners; at least 3 are needed")]
    FaceTooSmall {
        /// The face.
        face: usize,
        /// Its corners.
        len: usize,
    },
    /// A face uses one vertex twice (a degenerate face).
    #[error("face {face} uses vertex {vertex} twice")]
    RepeatedVertex {
        /// The face.
        face: usize,
        /// The repeated vertex.
        vertex: u32,
    },
    /// An edge belongs to more than two faces.
    #[error("edge ({a}, {b}) is shared by {faces} faces; a manifold edge has at most 2")]
    NonManifoldEdge {
        /// One end.
        a: u32,
        /// The other end.
        b: u32,
        /// Faces using it.
        faces: usize,
    },
    /// Two faces traverse an edge in the same direction.
    #[error(
        "edge ({a}, {b}) is traversed twice in the same direction: adjacent faces are \
         inconsistently oriented (or a face is repeated)"
    )]
    InconsistentOrientation {
        /// Origin of both traversals.
        a: u32,
        /// Destination of both traversals.
        b: u32,
    },
    /// The faces around a vertex form more than one fan.
    #[error("vertex {vertex} is non-manifold: its faces form more than one fan")]
    NonManifoldVertex {
        /// The vertex.
        vertex: u32,
    },
    /// An attribute array's length differs from the number of positions.
    #[error("the mesh has {positions} positions but {len} {attribute}")]
    AttributeLength {
        /// `normals`, `uvs` or `colors`.
        attribute: &'static str,
        /// Its length.
        len: usize,
        /// Number of positions.
        positions: usize,
    },
    /// The mesh (or a result) would not fit 32-bit indices or the allowed size.
    #[error("the mesh is too large: {0}")]
    TooLarge(String),
    /// A face is not a triangle where triangles are needed.
    #[error("face {face} has {len} corners, but a triangle mesh is needed")]
    NotTriangle {
        /// The face.
        face: usize,
        /// Its corners.
        len: usize,
    },
    /// A face is not a quad where quads are needed (Catmull–Clark limit positions).
    #[error("face {face} has {len} corners, but a quad mesh is needed (subdivide once first)")]
    NotQuad {
        /// The face.
        face: usize,
        /// Its corners.
        len: usize,
    },
    /// [`HalfedgeMesh::validate`] found a broken invariant.
    #[error("invalid halfedge structure: {0}")]
    Corrupt(String),
}

impl MeshError {
    /// The operator error for input `port`.
    pub fn at(self, port: &str) -> OpError {
        OpError::input(port, self.to_string())
    }
}

/// Why a local operation was refused; the mesh is left unchanged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum LocalOpError {
    /// The halfedge does not exist (removed or out of range).
    #[error("the halfedge does not exist")]
    NoSuchHalfedge,
    /// Flipping needs two faces.
    #[error("a boundary edge cannot be flipped")]
    BoundaryEdge,
    /// A face next to the edge is not a triangle.
    #[error("the faces next to the edge must be triangles")]
    NotTriangle,
    /// The flipped edge exists already (flipping would make a double edge).
    #[error("the flipped edge already exists")]
    EdgeExists,
    /// The link condition fails: collapsing would change the topology.
    #[error("collapsing the edge would break the manifold (link condition)")]
    LinkCondition,
}

/// A halfedge mesh (see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct HalfedgeMesh {
    positions: Vec<[f64; 3]>,
    vertex_halfedge: Vec<u32>,
    vertex_alive: Vec<bool>,
    twin: Vec<u32>,
    next: Vec<u32>,
    prev: Vec<u32>,
    origin: Vec<u32>,
    face: Vec<u32>,
    halfedge_alive: Vec<bool>,
    face_halfedge: Vec<u32>,
    face_alive: Vec<bool>,
    live_vertices: usize,
    live_halfedges: usize,
    live_faces: usize,
}

/// The outgoing halfedges of a vertex, rotating through `next(twin(h))`.
#[derive(Debug, Clone)]
pub struct Outgoing<'a> {
    mesh: &'a HalfedgeMesh,
    start: u32,
    current: u32,
    left: usize,
}

impl Iterator for Outgoing<'_> {
    type Item = u32;

    fn next(&mut self) -> Option<u32> {
        if self.current == NONE || self.left == 0 {
            return None;
        }
        self.left -= 1;
        let h = self.current;
        let n = self.mesh.next[self.mesh.twin[h as usize] as usize];
        self.current = if n == self.start { NONE } else { n };
        Some(h)
    }
}

/// The halfedges of a face (or boundary loop), following `next`.
#[derive(Debug, Clone)]
pub struct Cycle<'a> {
    mesh: &'a HalfedgeMesh,
    start: u32,
    current: u32,
    left: usize,
}

impl Iterator for Cycle<'_> {
    type Item = u32;

    fn next(&mut self) -> Option<u32> {
        if self.current == NONE || self.left == 0 {
            return None;
        }
        self.left -= 1;
        let h = self.current;
        let n = self.mesh.next[h as usize];
        self.current = if n == self.start { NONE } else { n };
        Some(h)
    }
}

/// A polygon mesh in indexed form, as [`HalfedgeMesh::to_polygons`] returns it.
#[derive(Debug, Clone, PartialEq)]
pub struct IndexedPolygons {
    /// Vertex positions.
    pub positions: Vec<[f64; 3]>,
    /// Faces, counter-clockwise vertex indices.
    pub faces: Vec<Vec<u32>>,
    /// For each vertex of the halfedge mesh its index here, [`NONE`] for removed vertices.
    pub vertex_map: Vec<u32>,
}

impl HalfedgeMesh {
    /// The halfedge mesh of a triangle mesh (see the module documentation for what is refused).
    pub fn from_triangles(
        positions: Vec<[f64; 3]>,
        triangles: &[[u32; 3]],
    ) -> Result<HalfedgeMesh, MeshError> {
        build(positions, triangles.len(), |f| &triangles[f][..])
    }

    /// The halfedge mesh of a polygon mesh (faces of any size ≥ 3, counter-clockwise).
    pub fn from_polygons(
        positions: Vec<[f64; 3]>,
        faces: &[Vec<u32>],
    ) -> Result<HalfedgeMesh, MeshError> {
        build(positions, faces.len(), |f| &faces[f][..])
    }

    /// Vertex slots (removed ones included): valid vertex indices are below this.
    pub fn vertex_capacity(&self) -> usize {
        self.positions.len()
    }

    /// Halfedge slots (removed ones included).
    pub fn halfedge_capacity(&self) -> usize {
        self.origin.len()
    }

    /// Face slots (removed ones included).
    pub fn face_capacity(&self) -> usize {
        self.face_halfedge.len()
    }

    /// Vertices not removed (isolated ones included).
    pub fn num_vertices(&self) -> usize {
        self.live_vertices
    }

    /// Edges not removed.
    pub fn num_edges(&self) -> usize {
        self.live_halfedges / 2
    }

    /// Faces not removed.
    pub fn num_faces(&self) -> usize {
        self.live_faces
    }

    /// All position slots (removed vertices keep their last position).
    pub fn positions(&self) -> &[[f64; 3]] {
        &self.positions
    }

    /// Position of vertex `v`.
    pub fn position(&self, v: u32) -> [f64; 3] {
        self.positions[v as usize]
    }

    /// Moves vertex `v`.
    pub fn set_position(&mut self, v: u32, p: [f64; 3]) {
        self.positions[v as usize] = p;
    }

    /// Whether vertex `v` exists.
    pub fn vertex_alive(&self, v: u32) -> bool {
        self.vertex_alive.get(v as usize).copied().unwrap_or(false)
    }

    /// Whether halfedge `h` exists.
    pub fn halfedge_alive(&self, h: u32) -> bool {
        self.halfedge_alive
            .get(h as usize)
            .copied()
            .unwrap_or(false)
    }

    /// Whether face `f` exists.
    pub fn face_alive(&self, f: u32) -> bool {
        self.face_alive.get(f as usize).copied().unwrap_or(false)
    }

    /// The opposite halfedge of the same edge.
    pub fn twin(&self, h: u32) -> u32 {
        self.twin[h as usize]
    }

    /// The next halfedge of `h`'s face or boundary loop.
    pub fn next(&self, h: u32) -> u32 {
        self.next[h as usize]
    }

    /// The previous halfedge of `h`'s face or boundary loop.
    pub fn prev(&self, h: u32) -> u32 {
        self.prev[h as usize]
    }

    /// The vertex `h` leaves.
    pub fn origin(&self, h: u32) -> u32 {
        self.origin[h as usize]
    }

    /// The vertex `h` points to.
    pub fn dest(&self, h: u32) -> u32 {
        self.origin[self.twin[h as usize] as usize]
    }

    /// `h`'s face, [`NONE`] on the boundary.
    pub fn face(&self, h: u32) -> u32 {
        self.face[h as usize]
    }

    /// Whether `h` has no face.
    pub fn is_boundary_halfedge(&self, h: u32) -> bool {
        self.face[h as usize] == NONE
    }

    /// Whether either side of `h`'s edge has no face.
    pub fn is_boundary_edge(&self, h: u32) -> bool {
        self.is_boundary_halfedge(h) || self.is_boundary_halfedge(self.twin(h))
    }

    /// One outgoing halfedge of `v` (the boundary one on the boundary), [`NONE`] if isolated.
    pub fn vertex_halfedge(&self, v: u32) -> u32 {
        self.vertex_halfedge[v as usize]
    }

    /// Whether `v` lies on the boundary.
    pub fn is_boundary_vertex(&self, v: u32) -> bool {
        let h = self.vertex_halfedge[v as usize];
        h != NONE && self.face[h as usize] == NONE
    }

    /// One halfedge of face `f`.
    pub fn face_halfedge(&self, f: u32) -> u32 {
        self.face_halfedge[f as usize]
    }

    /// The outgoing halfedges of `v`, starting at [`HalfedgeMesh::vertex_halfedge`].
    pub fn outgoing(&self, v: u32) -> Outgoing<'_> {
        let start = self.vertex_halfedge[v as usize];
        Outgoing {
            mesh: self,
            start,
            current: start,
            left: self.origin.len(),
        }
    }

    /// Number of edges at `v`.
    pub fn valence(&self, v: u32) -> usize {
        self.outgoing(v).count()
    }

    /// The halfedges of the cycle (face or boundary loop) through `h`, starting at `h`.
    pub fn cycle(&self, h: u32) -> Cycle<'_> {
        Cycle {
            mesh: self,
            start: h,
            current: h,
            left: self.origin.len(),
        }
    }

    /// The halfedges of face `f`.
    pub fn face_cycle(&self, f: u32) -> Cycle<'_> {
        self.cycle(self.face_halfedge[f as usize])
    }

    /// The vertices of triangle `f` (the first three corners of any face).
    pub fn triangle(&self, f: u32) -> [u32; 3] {
        let h = self.face_halfedge[f as usize];
        let n = self.next(h);
        [self.origin(h), self.origin(n), self.origin(self.next(n))]
    }

    /// The halfedge from `a` to `b`, if that edge exists.
    pub fn find_halfedge(&self, a: u32, b: u32) -> Option<u32> {
        self.outgoing(a).find(|&h| self.dest(h) == b)
    }

    /// Whether every face has three corners.
    pub fn is_triangle_mesh(&self) -> bool {
        (0..self.face_capacity() as u32)
            .filter(|&f| self.face_alive(f))
            .all(|f| self.face_cycle(f).count() == 3)
    }

    /// Checks every invariant (see the module documentation); `Corrupt` names the first broken
    /// one.
    pub fn validate(&self) -> Result<(), MeshError> {
        let corrupt = |m: String| Err(MeshError::Corrupt(m));
        let (nv, nh, nf) = (
            self.positions.len(),
            self.origin.len(),
            self.face_halfedge.len(),
        );
        if self.vertex_halfedge.len() != nv
            || self.vertex_alive.len() != nv
            || [&self.twin, &self.next, &self.prev, &self.face]
                .iter()
                .any(|a| a.len() != nh)
            || self.halfedge_alive.len() != nh
            || self.face_alive.len() != nf
        {
            return corrupt("array lengths differ".into());
        }
        let live_v = self.vertex_alive.iter().filter(|a| **a).count();
        let live_h = self.halfedge_alive.iter().filter(|a| **a).count();
        let live_f = self.face_alive.iter().filter(|a| **a).count();
        if (live_v, live_h, live_f) != (self.live_vertices, self.live_halfedges, self.live_faces) {
            return corrupt("element counts are stale".into());
        }
        let mut face_size = vec![0usize; nf];
        let mut out_degree = vec![0usize; nv];
        let mut boundary_out = vec![0usize; nv];
        for h in 0..nh as u32 {
            if !self.halfedge_alive(h) {
                continue;
            }
            let (t, n, p, o, f) = (
                self.twin(h),
                self.next(h),
                self.prev(h),
                self.origin(h),
                self.face(h),
            );
            if !self.halfedge_alive(t) || t == h || self.twin(t) != h {
                return corrupt(format!("halfedge {h}: twin({h}) = {t} is not its inverse"));
            }
            if !self.halfedge_alive(n) || self.prev(n) != h {
                return corrupt(format!("halfedge {h}: prev(next) is not {h}"));
            }
            if !self.halfedge_alive(p) || self.next(p) != h {
                return corrupt(format!("halfedge {h}: next(prev) is not {h}"));
            }
            if !self.vertex_alive(o) {
                return corrupt(format!("halfedge {h} leaves removed vertex {o}"));
            }
            if self.origin(n) != self.origin(t) {
                return corrupt(format!("halfedge {h}: next does not start where it ends"));
            }
            if self.face(n) != f {
                return corrupt(format!("halfedge {h}: next lies in another face"));
            }
            if f == NONE {
                if self.face(t) == NONE {
                    return corrupt(format!("edge of halfedge {h} has no face on either side"));
                }
                boundary_out[o as usize] += 1;
            } else {
                if !self.face_alive(f) {
                    return corrupt(format!("halfedge {h} lies in removed face {f}"));
                }
                face_size[f as usize] += 1;
            }
            if o == self.dest(h) {
                return corrupt(format!("halfedge {h} is a loop at vertex {o}"));
            }
            out_degree[o as usize] += 1;
        }
        for f in 0..nf as u32 {
            if !self.face_alive(f) {
                continue;
            }
            let h = self.face_halfedge(f);
            if !self.halfedge_alive(h) || self.face(h) != f {
                return corrupt(format!("face {f}: its halfedge lies elsewhere"));
            }
            let cycle = self.face_cycle(f).count();
            if cycle < 3 || cycle != face_size[f as usize] {
                return corrupt(format!(
                    "face {f}: cycle of {cycle} halfedges, {} claim the face",
                    face_size[f as usize]
                ));
            }
            let mut corners: Vec<u32> = self.face_cycle(f).map(|h| self.origin(h)).collect();
            corners.sort_unstable();
            if corners.windows(2).any(|w| w[0] == w[1]) {
                return corrupt(format!("face {f} repeats a vertex"));
            }
        }
        let mut ring = Vec::new();
        for v in 0..nv as u32 {
            if !self.vertex_alive(v) {
                if out_degree[v as usize] > 0 {
                    return corrupt(format!("removed vertex {v} has halfedges"));
                }
                continue;
            }
            let h = self.vertex_halfedge(v);
            if h == NONE {
                if out_degree[v as usize] > 0 {
                    return corrupt(format!("vertex {v} has edges but no halfedge"));
                }
                continue;
            }
            if !self.halfedge_alive(h) || self.origin(h) != v {
                return corrupt(format!("vertex {v}: its halfedge does not leave it"));
            }
            if boundary_out[v as usize] > 1 {
                return corrupt(format!("vertex {v} is non-manifold (two boundary fans)"));
            }
            if boundary_out[v as usize] == 1 && !self.is_boundary_halfedge(h) {
                return corrupt(format!(
                    "boundary vertex {v} does not keep its boundary halfedge"
                ));
            }
            ring.clear();
            ring.extend(self.outgoing(v).map(|h| self.dest(h)));
            if ring.len() != out_degree[v as usize] {
                return corrupt(format!(
                    "vertex {v}: rotation visits {} of {} outgoing halfedges (non-manifold)",
                    ring.len(),
                    out_degree[v as usize]
                ));
            }
            ring.sort_unstable();
            if ring.windows(2).any(|w| w[0] == w[1]) {
                return corrupt(format!("vertex {v} has a double edge"));
            }
        }
        Ok(())
    }

    /// Boundary loops as vertex cycles (in boundary order, the surface on the left... of the
    /// reversed loop: each loop follows the boundary halfedges), ordered by their lowest
    /// halfedge.
    pub fn boundary_loops(&self) -> Vec<Vec<u32>> {
        let mut seen = vec![false; self.origin.len()];
        let mut loops = Vec::new();
        for h in 0..self.origin.len() as u32 {
            if !self.halfedge_alive(h) || !self.is_boundary_halfedge(h) || seen[h as usize] {
                continue;
            }
            let mut l = Vec::new();
            for b in self.cycle(h) {
                seen[b as usize] = true;
                l.push(self.origin(b));
            }
            loops.push(l);
        }
        loops
    }

    /// `V − E + F` over existing elements (isolated vertices count).
    pub fn euler_characteristic(&self) -> i64 {
        self.live_vertices as i64 - self.num_edges() as i64 + self.live_faces as i64
    }

    /// Connected components of the surface (isolated vertices not counted).
    pub fn components(&self) -> usize {
        let n = self.positions.len();
        let mut parent: Vec<u32> = (0..n as u32).collect();
        fn find(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                let g = parent[parent[x as usize] as usize];
                parent[x as usize] = g;
                x = g;
            }
            x
        }
        for h in 0..self.origin.len() as u32 {
            if self.halfedge_alive(h) {
                let (a, b) = (
                    find(&mut parent, self.origin(h)),
                    find(&mut parent, self.dest(h)),
                );
                if a != b {
                    parent[a.max(b) as usize] = a.min(b);
                }
            }
        }
        (0..n as u32)
            .filter(|&v| self.vertex_alive(v) && self.vertex_halfedge(v) != NONE)
            .filter(|&v| find(&mut parent, v) == v)
            .count()
    }

    /// Vertices without any edge.
    pub fn isolated_vertices(&self) -> usize {
        (0..self.positions.len() as u32)
            .filter(|&v| self.vertex_alive(v) && self.vertex_halfedge(v) == NONE)
            .count()
    }

    /// The genus summed over components: `χ = 2c − 2g − b` for `c` components with `b`
    /// boundary loops, isolated vertices left out of `χ`.
    pub fn genus(&self) -> i64 {
        let chi = self.euler_characteristic() - self.isolated_vertices() as i64;
        let c = self.components() as i64;
        let b = self.boundary_loops().len() as i64;
        (2 * c - b - chi) / 2
    }

    /// Whether the mesh is a closed 2-manifold: at least one face and no boundary.
    pub fn is_watertight(&self) -> bool {
        self.live_faces > 0
            && (0..self.origin.len() as u32)
                .all(|h| !self.halfedge_alive(h) || !self.is_boundary_halfedge(h))
    }

    /// The existing elements as an indexed polygon mesh: vertices and faces in index order.
    pub fn to_polygons(&self) -> IndexedPolygons {
        let mut vertex_map = vec![NONE; self.positions.len()];
        let mut positions = Vec::with_capacity(self.live_vertices);
        for (v, (&alive, &p)) in self.vertex_alive.iter().zip(&self.positions).enumerate() {
            if alive {
                vertex_map[v] = positions.len() as u32;
                positions.push(p);
            }
        }
        let faces = (0..self.face_capacity() as u32)
            .filter(|&f| self.face_alive(f))
            .map(|f| {
                self.face_cycle(f)
                    .map(|h| vertex_map[self.origin(h) as usize])
                    .collect()
            })
            .collect();
        IndexedPolygons {
            positions,
            faces,
            vertex_map,
        }
    }

    /// The existing elements as an indexed triangle mesh, with the vertex map of
    /// [`IndexedPolygons`]; fails on a face that is not a triangle.
    #[allow(clippy::type_complexity)]
    pub fn to_triangles(&self) -> Result<(Vec<[f64; 3]>, Vec<[u32; 3]>, Vec<u32>), MeshError> {
        let p = self.to_polygons();
        let mut triangles = Vec::with_capacity(p.faces.len());
        for (i, f) in p.faces.iter().enumerate() {
            match f[..] {
                [a, b, c] => triangles.push([a, b, c]),
                _ => {
                    return Err(MeshError::NotTriangle {
                        face: i,
                        len: f.len(),
                    });
                }
            }
        }
        Ok((p.positions, triangles, p.vertex_map))
    }

    /// Checks that `h` exists and that its faces are triangles.
    fn check_triangles_at(&self, h: u32) -> Result<(), LocalOpError> {
        if !self.halfedge_alive(h) {
            return Err(LocalOpError::NoSuchHalfedge);
        }
        for s in [h, self.twin(h)] {
            if !self.is_boundary_halfedge(s) && self.next(self.next(self.next(s))) != s {
                return Err(LocalOpError::NotTriangle);
            }
        }
        Ok(())
    }

    /// Turns the interior edge of `h` (faces `abc` and `bad`, `h = a→b`) into the edge `cd`; `h`
    /// becomes `c→d`.
    pub fn flip_edge(&mut self, h: u32) -> Result<(), LocalOpError> {
        self.check_triangles_at(h)?;
        let t = self.twin(h);
        if self.is_boundary_edge(h) {
            return Err(LocalOpError::BoundaryEdge);
        }
        let (h1, h2) = (self.next(h), self.prev(h));
        let (t1, t2) = (self.next(t), self.prev(t));
        let (a, b) = (self.origin(h), self.origin(t));
        let (c, d) = (self.origin(h2), self.origin(t2));
        if c == d || self.find_halfedge(c, d).is_some() {
            return Err(LocalOpError::EdgeExists);
        }
        let (f0, f1) = (self.face(h), self.face(t));
        // f0 = (d, b, c): t2, h1, h;  f1 = (c, a, d): h2, t1, t.
        self.origin[h as usize] = c;
        self.origin[t as usize] = d;
        self.link(t2, h1);
        self.link(h1, h);
        self.link(h, t2);
        self.link(h2, t1);
        self.link(t1, t);
        self.link(t, h2);
        for (s, f) in [(t2, f0), (h1, f0), (h, f0), (h2, f1), (t1, f1), (t, f1)] {
            self.face[s as usize] = f;
        }
        self.face_halfedge[f0 as usize] = h;
        self.face_halfedge[f1 as usize] = t;
        if self.vertex_halfedge[a as usize] == h {
            self.vertex_halfedge[a as usize] = t1;
        }
        if self.vertex_halfedge[b as usize] == t {
            self.vertex_halfedge[b as usize] = h1;
        }
        Ok(())
    }

    fn link(&mut self, a: u32, b: u32) {
        self.next[a as usize] = b;
        self.prev[b as usize] = a;
    }

    fn push_halfedge_pair(&mut self, a: u32, b: u32) -> (u32, u32) {
        let h = self.origin.len() as u32;
        for (o, t) in [(a, h + 1), (b, h)] {
            self.origin.push(o);
            self.twin.push(t);
            self.next.push(NONE);
            self.prev.push(NONE);
            self.face.push(NONE);
            self.halfedge_alive.push(true);
        }
        self.live_halfedges += 2;
        (h, h + 1)
    }

    fn push_face(&mut self, h: u32) -> u32 {
        self.face_halfedge.push(h);
        self.face_alive.push(true);
        self.live_faces += 1;
        (self.face_halfedge.len() - 1) as u32
    }

    /// Splits the edge of `h = a→b` at `position` by a new vertex `m`, joined to the opposite
    /// vertex of each adjacent triangle. Returns `m`; `h` becomes `a→m`.
    pub fn split_edge(&mut self, h: u32, position: [f64; 3]) -> Result<u32, LocalOpError> {
        self.check_triangles_at(h)?;
        let t = self.twin(h);
        let b = self.origin(t);
        let m = self.positions.len() as u32;
        self.positions.push(position);
        self.vertex_alive.push(true);
        self.vertex_halfedge.push(NONE);
        self.live_vertices += 1;
        // The edge m→b: g (in h's side), gt (in t's side).
        let (g, gt) = self.push_halfedge_pair(m, b);
        self.origin[t as usize] = m;
        // h's side: (a, b, c) → (a, m, c) + (m, b, c).
        if self.is_boundary_halfedge(h) {
            let n = self.next(h);
            self.link(h, g);
            self.link(g, n);
        } else {
            let (h1, h2) = (self.next(h), self.prev(h));
            let c = self.origin(h2);
            let (k, kt) = self.push_halfedge_pair(m, c);
            let f0 = self.face(h);
            self.link(h, k);
            self.link(k, h2);
            self.face[k as usize] = f0;
            self.face_halfedge[f0 as usize] = h;
            let f2 = self.push_face(g);
            self.link(g, h1);
            self.link(h1, kt);
            self.link(kt, g);
            for s in [g, h1, kt] {
                self.face[s as usize] = f2;
            }
        }
        // t's side: (b, a, d) → (m, a, d) + (b, m, d).
        if self.is_boundary_halfedge(t) {
            let p = self.prev(t);
            self.link(p, gt);
            self.link(gt, t);
        } else {
            let (t1, t2) = (self.next(t), self.prev(t));
            let d = self.origin(t2);
            let (j, jt) = self.push_halfedge_pair(d, m);
            let f1 = self.face(t);
            self.link(t1, j);
            self.link(j, t);
            self.face[j as usize] = f1;
            self.face_halfedge[f1 as usize] = t;
            let f3 = self.push_face(gt);
            self.link(gt, jt);
            self.link(jt, t2);
            self.link(t2, gt);
            for s in [gt, jt, t2] {
                self.face[s as usize] = f3;
            }
        }
        if self.vertex_halfedge[b as usize] == t {
            self.vertex_halfedge[b as usize] = gt;
        }
        self.vertex_halfedge[m as usize] = if self.is_boundary_halfedge(t) { t } else { g };
        Ok(m)
    }

    /// Whether collapsing `h` keeps a 2-manifold of the same topology (the link condition of
    /// the module documentation); `Ok` when it does.
    pub fn can_collapse(&self, h: u32) -> Result<(), LocalOpError> {
        self.check_triangles_at(h)?;
        let t = self.twin(h);
        let (a, b) = (self.origin(h), self.origin(t));
        if self.is_boundary_vertex(a) && self.is_boundary_vertex(b) && !self.is_boundary_edge(h) {
            return Err(LocalOpError::LinkCondition);
        }
        let mut opposite = [NONE; 2];
        for (i, s) in [h, t].into_iter().enumerate() {
            if self.is_boundary_halfedge(s) {
                continue;
            }
            let (s1, s2) = (self.next(s), self.prev(s));
            opposite[i] = self.origin(s2);
            // Both other edges of the triangle on the boundary: the virtual vertex's edge to the
            // opposite corner is in both links.
            if self.is_boundary_halfedge(self.twin(s1)) && self.is_boundary_halfedge(self.twin(s2))
            {
                return Err(LocalOpError::LinkCondition);
            }
        }
        // Vertex part: the common neighbours are exactly the opposite corners.
        for ha in self.outgoing(a) {
            let x = self.dest(ha);
            if x == b || opposite.contains(&x) {
                continue;
            }
            if self.outgoing(b).any(|hb| self.dest(hb) == x) {
                return Err(LocalOpError::LinkCondition);
            }
        }
        // Edge part: the edge cd in both links means triangles acd and bcd both exist.
        let [c, d] = opposite;
        if c != NONE && c == d {
            // Two triangles on the same three vertices (a closed two-face pillow).
            return Err(LocalOpError::LinkCondition);
        }
        if c != NONE && d != NONE {
            let has_triangle = |v: u32| {
                self.outgoing(v).any(|s| {
                    !self.is_boundary_halfedge(s) && {
                        let x = self.dest(s);
                        let y = self.origin(self.prev(s));
                        (x == c && y == d) || (x == d && y == c)
                    }
                })
            };
            if has_triangle(a) && has_triangle(b) {
                return Err(LocalOpError::LinkCondition);
            }
        }
        Ok(())
    }

    /// Collapses the edge of `h = a→b`: `a` is removed, its edges go to `b`, which moves to
    /// `position`; the one or two triangles of the edge are removed. Refused (mesh unchanged)
    /// when [`HalfedgeMesh::can_collapse`] refuses. Returns `b`.
    pub fn collapse_edge(&mut self, h: u32, position: [f64; 3]) -> Result<u32, LocalOpError> {
        self.can_collapse(h)?;
        let t = self.twin(h);
        let (a, b) = (self.origin(h), self.origin(t));
        let moved: Vec<u32> = self.outgoing(a).collect();
        // (vertex, an outgoing halfedge it surely keeps) for b and the opposite corners.
        let mut touched = [(b, NONE), (NONE, NONE), (NONE, NONE)];
        for (i, s) in [h, t].into_iter().enumerate() {
            if self.is_boundary_halfedge(s) {
                // Drop s from its boundary loop; next(s) leaves a or b and will leave b.
                let (p, n) = (self.prev(s), self.next(s));
                self.link(p, n);
                touched[0].1 = n;
            } else {
                // The triangle (s, s1, s2) vanishes; the twins of s1 and s2 become one edge:
                // o1 leaves the opposite corner, o2 leaves a or b and will leave b.
                let (s1, s2) = (self.next(s), self.prev(s));
                let (o1, o2) = (self.twin(s1), self.twin(s2));
                self.twin[o1 as usize] = o2;
                self.twin[o2 as usize] = o1;
                touched[i + 1] = (self.origin(s2), o1);
                touched[0].1 = o2;
                let f = self.face(s);
                self.face_alive[f as usize] = false;
                self.live_faces -= 1;
                for r in [s1, s2] {
                    self.kill_halfedge(r);
                }
            }
        }
        self.kill_halfedge(h);
        self.kill_halfedge(t);
        for s in moved {
            if self.halfedge_alive[s as usize] {
                self.origin[s as usize] = b;
            }
        }
        self.vertex_alive[a as usize] = false;
        self.vertex_halfedge[a as usize] = NONE;
        self.live_vertices -= 1;
        self.positions[b as usize] = position;
        for (v, candidate) in touched {
            if v != NONE {
                self.reset_vertex_halfedge(v, candidate);
            }
        }
        Ok(b)
    }

    fn kill_halfedge(&mut self, h: u32) {
        self.halfedge_alive[h as usize] = false;
        self.live_halfedges -= 1;
    }

    /// Points `v` at an existing outgoing halfedge (its current one if still there, else
    /// `candidate`), the boundary one if there is one.
    fn reset_vertex_halfedge(&mut self, v: u32, candidate: u32) {
        let current = self.vertex_halfedge[v as usize];
        let start = if current != NONE && self.halfedge_alive[current as usize] {
            current
        } else {
            candidate
        };
        self.vertex_halfedge[v as usize] = start;
        if let Some(b) = self.outgoing(v).find(|&s| self.is_boundary_halfedge(s)) {
            self.vertex_halfedge[v as usize] = b;
        }
    }
}

fn build<'a>(
    positions: Vec<[f64; 3]>,
    nf: usize,
    face_of: impl Fn(usize) -> &'a [u32],
) -> Result<HalfedgeMesh, MeshError> {
    let nv = positions.len();
    if let Some(index) = positions
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(MeshError::NonFinite { index });
    }
    let mut total = 0usize;
    let mut sorted = Vec::new();
    for f in 0..nf {
        let fv = face_of(f);
        if fv.len() < 3 {
            return Err(MeshError::FaceTooSmall {
                face: f,
                len: fv.len(),
            });
        }
        if let Some(&index) = fv.iter().find(|&&i| i as usize >= nv) {
            return Err(MeshError::IndexOutOfRange {
                face: f,
                index,
                vertices: nv,
            });
        }
        sorted.clear();
        sorted.extend_from_slice(fv);
        sorted.sort_unstable();
        if let Some(w) = sorted.windows(2).find(|w| w[0] == w[1]) {
            return Err(MeshError::RepeatedVertex {
                face: f,
                vertex: w[0],
            });
        }
        total += fv.len();
    }
    if nv >= NONE as usize || nf >= NONE as usize || total >= (NONE / 2) as usize {
        return Err(MeshError::TooLarge(format!(
            "{nv} vertices, {nf} faces, {total} corners exceed 32-bit halfedge indices"
        )));
    }
    let mut origin = Vec::with_capacity(2 * total);
    let mut next = Vec::with_capacity(2 * total);
    let mut prev = Vec::with_capacity(2 * total);
    let mut face = Vec::with_capacity(2 * total);
    let mut face_halfedge = Vec::with_capacity(nf);
    for f in 0..nf {
        let fv = face_of(f);
        let base = origin.len() as u32;
        let n = fv.len() as u32;
        for (i, &v) in fv.iter().enumerate() {
            let i = i as u32;
            origin.push(v);
            next.push(base + (i + 1) % n);
            prev.push(base + (i + n - 1) % n);
            face.push(f as u32);
        }
        face_halfedge.push(base);
    }
    // Pair halfedges by undirected edge; ties sort by halfedge index, so pairing is
    // deterministic.
    let dest = |h: usize| origin[next[h] as usize];
    let mut keys: Vec<(u64, u32)> = (0..total)
        .map(|h| {
            let (a, b) = (origin[h], dest(h));
            ((u64::from(a.min(b)) << 32) | u64::from(a.max(b)), h as u32)
        })
        .collect();
    keys.par_sort_unstable();
    let mut twin = vec![NONE; total];
    for group in keys.chunk_by(|x, y| x.0 == y.0) {
        match *group {
            [_] => {}
            [(_, h0), (_, h1)] => {
                if origin[h0 as usize] == origin[h1 as usize] {
                    return Err(MeshError::InconsistentOrientation {
                        a: origin[h0 as usize],
                        b: dest(h0 as usize),
                    });
                }
                twin[h0 as usize] = h1;
                twin[h1 as usize] = h0;
            }
            _ => {
                let h = group[0].1 as usize;
                return Err(MeshError::NonManifoldEdge {
                    a: origin[h].min(dest(h)),
                    b: origin[h].max(dest(h)),
                    faces: group.len(),
                });
            }
        }
    }
    // Boundary halfedges, one per unpaired halfedge, appended in that halfedge's order.
    let mut boundary_out = vec![NONE; nv];
    for h in 0..total {
        if twin[h] != NONE {
            continue;
        }
        let b = origin.len() as u32;
        let o = origin[next[h] as usize];
        if boundary_out[o as usize] != NONE {
            return Err(MeshError::NonManifoldVertex { vertex: o });
        }
        boundary_out[o as usize] = b;
        origin.push(o);
        twin.push(h as u32);
        twin[h] = b;
        next.push(NONE);
        prev.push(NONE);
        face.push(NONE);
    }
    for b in total..origin.len() {
        // b: u→v; the boundary continues with the boundary halfedge leaving v.
        let v = origin[twin[b] as usize];
        let nb = boundary_out[v as usize];
        next[b] = nb;
        prev[nb as usize] = b as u32;
    }
    let nh = origin.len();
    let mut vertex_halfedge = vec![NONE; nv];
    let mut out_degree = vec![0usize; nv];
    for (h, &o) in origin.iter().enumerate() {
        let o = o as usize;
        out_degree[o] += 1;
        if vertex_halfedge[o] == NONE {
            vertex_halfedge[o] = h as u32;
        }
    }
    for v in 0..nv {
        if boundary_out[v] != NONE {
            vertex_halfedge[v] = boundary_out[v];
        }
    }
    let mesh = HalfedgeMesh {
        positions,
        vertex_halfedge,
        vertex_alive: vec![true; nv],
        twin,
        next,
        prev,
        origin,
        face,
        halfedge_alive: vec![true; nh],
        face_halfedge,
        face_alive: vec![true; nf],
        live_vertices: nv,
        live_halfedges: nh,
        live_faces: nf,
    };
    // One fan per vertex: the rotation from its halfedge visits all its outgoing halfedges.
    if let Some(v) = (0..nv).find(|&v| {
        mesh.vertex_halfedge[v] != NONE && mesh.outgoing(v as u32).count() != out_degree[v]
    }) {
        return Err(MeshError::NonManifoldVertex { vertex: v as u32 });
    }
    Ok(mesh)
}

/// The mesh on input `port`.
pub fn mesh_input<'a>(inputs: &Inputs<'a>, port: &str) -> Result<&'a Arc<Mesh>, OpError> {
    match inputs.require(port)? {
        Value::Mesh(m) => Ok(m),
        other => Err(OpError::input(
            port,
            format!("expected Mesh, got {}", other.port_type()),
        )),
    }
}

/// Checks attribute lengths, indices and finiteness, and returns the positions in f64.
pub fn mesh_positions(mesh: &Mesh) -> Result<Vec<[f64; 3]>, MeshError> {
    let n = mesh.positions.len();
    for (attribute, len) in [
        ("normals", mesh.normals.as_ref().map(Vec::len)),
        ("uvs", mesh.uvs.as_ref().map(Vec::len)),
        ("colors", mesh.colors.as_ref().map(Vec::len)),
        ("tangents", mesh.tangents.as_ref().map(Vec::len)),
    ] {
        if let Some(len) = len
            && len != n
        {
            return Err(MeshError::AttributeLength {
                attribute,
                len,
                positions: n,
            });
        }
    }
    if let Some(index) = mesh
        .positions
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(MeshError::NonFinite { index });
    }
    for (face, t) in mesh.triangles.iter().enumerate() {
        if let Some(&index) = t.iter().find(|&&i| i as usize >= n) {
            return Err(MeshError::IndexOutOfRange {
                face,
                index,
                vertices: n,
            });
        }
    }
    Ok(mesh.positions.iter().map(|p| p.map(f64::from)).collect())
}

/// The halfedge mesh of a `Mesh` value (checked; no face is an error).
pub fn halfedge_of(mesh: &Mesh) -> Result<HalfedgeMesh, MeshError> {
    let positions = mesh_positions(mesh)?;
    if mesh.triangles.is_empty() {
        return Err(MeshError::Empty);
    }
    HalfedgeMesh::from_triangles(positions, &mesh.triangles)
}

/// A `Mesh` value of f64 positions and triangles, no attributes.
pub fn mesh_of(positions: &[[f64; 3]], triangles: Vec<[u32; 3]>) -> Mesh {
    Mesh {
        positions: positions.iter().map(|p| p.map(|v| v as f32)).collect(),
        triangles,
        normals: None,
        uvs: None,
        colors: None,
        tangents: None,
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use proptest::prelude::*;

    /// The cube `[-1, 1]³` as six outward quads.
    pub(crate) fn cube_quads() -> (Vec<[f64; 3]>, Vec<Vec<u32>>) {
        let positions = (0..8)
            .map(|i| [0, 1, 2].map(|a| if (i >> a) & 1 == 1 { 1.0 } else { -1.0 }))
            .collect();
        let faces = vec![
            vec![0, 2, 3, 1], // z = -1
            vec![4, 5, 7, 6], // z = +1
            vec![0, 1, 5, 4], // y = -1
            vec![2, 6, 7, 3], // y = +1
            vec![0, 4, 6, 2], // x = -1
            vec![1, 3, 7, 5], // x = +1
        ];
        (positions, faces)
    }

    /// The cube's quads split into triangles.
    pub(crate) fn cube_triangles() -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let (p, q) = cube_quads();
        let t = q
            .iter()
            .flat_map(|f| [[f[0], f[1], f[2]], [f[0], f[2], f[3]]])
            .collect();
        (p, t)
    }

    /// A `w × h` grid of unit squares in the plane z = 0, each split into two triangles,
    /// counter-clockwise seen from +z.
    pub(crate) fn grid(w: u32, h: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let mut p = Vec::new();
        for y in 0..=h {
            for x in 0..=w {
                p.push([f64::from(x), f64::from(y), 0.0]);
            }
        }
        let id = |x: u32, y: u32| y * (w + 1) + x;
        let mut t = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (a, b, c, d) = (id(x, y), id(x + 1, y), id(x + 1, y + 1), id(x, y + 1));
                t.push([a, b, c]);
                t.push([a, c, d]);
            }
        }
        (p, t)
    }

    /// A torus of `n × m` quads split into triangles (genus 1).
    pub(crate) fn torus(n: u32, m: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let mut p = Vec::new();
        for i in 0..n {
            for j in 0..m {
                let (u, v) = (
                    f64::from(i) / f64::from(n) * std::f64::consts::TAU,
                    f64::from(j) / f64::from(m) * std::f64::consts::TAU,
                );
                let r = 2.0 + 0.7 * v.cos();
                p.push([r * u.cos(), r * u.sin(), 0.7 * v.sin()]);
            }
        }
        let id = |i: u32, j: u32| (i % n) * m + (j % m);
        let mut t = Vec::new();
        for i in 0..n {
            for j in 0..m {
                let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
                t.push([a, b, c]);
                t.push([a, c, d]);
            }
        }
        (p, t)
    }

    pub(crate) fn icosphere(subdivisions: u32, seed: u64, amplitude: f32) -> HalfedgeMesh {
        let m = crate::render::primitives::bumpy_icosphere(subdivisions, amplitude, seed);
        let p = m.positions.iter().map(|v| v.map(f64::from)).collect();
        HalfedgeMesh::from_triangles(p, &m.triangles).unwrap()
    }

    #[test]
    fn cube_counts_and_topology() {
        let (p, q) = cube_quads();
        let m = HalfedgeMesh::from_polygons(p.clone(), &q).unwrap();
        m.validate().unwrap();
        assert_eq!((m.num_vertices(), m.num_edges(), m.num_faces()), (8, 12, 6));
        assert_eq!(m.euler_characteristic(), 2);
        assert_eq!(m.genus(), 0);
        assert!(m.is_watertight());
        assert!(m.boundary_loops().is_empty());
        assert!((0..8).all(|v| m.valence(v) == 3));
        assert!(!m.is_triangle_mesh());
        let back = m.to_polygons();
        assert_eq!(back.positions, p);
        assert_eq!(back.faces, q);
        assert!(matches!(
            m.to_triangles(),
            Err(MeshError::NotTriangle { face: 0, len: 4 })
        ));
        let (p, t) = cube_triangles();
        let m = HalfedgeMesh::from_triangles(p, &t).unwrap();
        m.validate().unwrap();
        assert_eq!((m.num_edges(), m.num_faces()), (18, 12));
        assert_eq!(m.to_triangles().unwrap().1, t);
    }

    #[test]
    fn grid_and_torus_topology() {
        let (p, t) = grid(4, 3);
        let m = HalfedgeMesh::from_triangles(p, &t).unwrap();
        m.validate().unwrap();
        // V = 20, E = 4·4 + 5·3 + 12 = 43, F = 24: χ = 1, a disc.
        assert_eq!(m.euler_characteristic(), 1);
        assert_eq!(m.genus(), 0);
        assert!(!m.is_watertight());
        let loops = m.boundary_loops();
        assert_eq!(loops.len(), 1);
        assert_eq!(loops[0].len(), 14);
        assert!(m.is_boundary_vertex(0) && !m.is_boundary_vertex(6));
        let (p, t) = torus(8, 6);
        let m = HalfedgeMesh::from_triangles(p, &t).unwrap();
        m.validate().unwrap();
        assert_eq!(m.euler_characteristic(), 0);
        assert_eq!(m.genus(), 1);
        assert!(m.is_watertight());
        // Two disjoint cubes: two components, genus 0 each.
        let (p, mut t) = cube_triangles();
        let mut p2 = p.clone();
        p2.extend(p.iter().map(|v| [v[0] + 5.0, v[1], v[2]]));
        t.extend(t.clone().iter().map(|f| f.map(|i| i + 8)));
        let m = HalfedgeMesh::from_triangles(p2, &t).unwrap();
        assert_eq!(
            (m.components(), m.genus(), m.euler_characteristic()),
            (2, 0, 4)
        );
    }

    #[test]
    fn non_manifold_input_is_refused_with_its_reason() {
        let p = vec![[0.0; 3]; 6];
        // Three triangles on edge (0, 1).
        let t = [[0, 1, 2], [1, 0, 3], [0, 1, 4]];
        assert_eq!(
            HalfedgeMesh::from_triangles(p.clone(), &t),
            Err(MeshError::NonManifoldEdge {
                a: 0,
                b: 1,
                faces: 3
            })
        );
        // Two triangles traversing (0, 1) the same way.
        assert_eq!(
            HalfedgeMesh::from_triangles(p.clone(), &[[0, 1, 2], [0, 1, 3]]),
            Err(MeshError::InconsistentOrientation { a: 0, b: 1 })
        );
        // A bow tie at vertex 0.
        assert_eq!(
            HalfedgeMesh::from_triangles(p.clone(), &[[0, 1, 2], [0, 3, 4]]),
            Err(MeshError::NonManifoldVertex { vertex: 0 })
        );
        // Two closed tetrahedra sharing a vertex: no boundary, still two fans.
        let mut p2 = vec![[0.0; 3]; 7];
        p2[0] = [0.0; 3];
        let tet = |o: u32| {
            [
                [0, o + 1, o + 2],
                [0, o + 2, o + 3],
                [0, o + 3, o + 1],
                [o + 1, o + 3, o + 2],
            ]
        };
        let mut t2 = tet(0).to_vec();
        t2.extend(tet(3));
        assert_eq!(
            HalfedgeMesh::from_triangles(p2.clone(), &t2),
            Err(MeshError::NonManifoldVertex { vertex: 0 })
        );
        assert!(matches!(
            HalfedgeMesh::from_triangles(p.clone(), &[[0, 1, 9]]),
            Err(MeshError::IndexOutOfRange { index: 9, .. })
        ));
        assert!(matches!(
            HalfedgeMesh::from_triangles(p.clone(), &[[0, 1, 1]]),
            Err(MeshError::RepeatedVertex { vertex: 1, .. })
        ));
        assert!(matches!(
            HalfedgeMesh::from_polygons(p.clone(), &[vec![0, 1]]),
            Err(MeshError::FaceTooSmall { len: 2, .. })
        ));
        let mut bad = p;
        bad[3] = [0.0, f64::NAN, 0.0];
        assert_eq!(
            HalfedgeMesh::from_triangles(bad, &[[0, 1, 2]]),
            Err(MeshError::NonFinite { index: 3 })
        );
    }

    #[test]
    fn validate_catches_a_broken_structure() {
        let (p, t) = cube_triangles();
        let good = HalfedgeMesh::from_triangles(p, &t).unwrap();
        let mut m = good.clone();
        m.twin[0] = m.twin[1];
        assert!(matches!(m.validate(), Err(MeshError::Corrupt(_))));
        let mut m = good.clone();
        m.next.swap(0, 1);
        assert!(matches!(m.validate(), Err(MeshError::Corrupt(_))));
        let mut m = good.clone();
        m.vertex_halfedge[3] = m.twin[m.vertex_halfedge[3] as usize];
        assert!(matches!(m.validate(), Err(MeshError::Corrupt(_))));
        let mut m = good;
        m.live_faces += 1;
        assert!(matches!(m.validate(), Err(MeshError::Corrupt(_))));
    }

    #[test]
    fn flip_turns_the_diagonal_and_refuses_boundary_and_double_edges() {
        // A square 0-1-2-3 split along 0-2.
        let p = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ];
        let mut m = HalfedgeMesh::from_triangles(p, &[[0, 1, 2], [0, 2, 3]]).unwrap();
        let h = m.find_halfedge(0, 2).unwrap();
        m.flip_edge(h).unwrap();
        m.validate().unwrap();
        assert!(m.find_halfedge(0, 2).is_none());
        assert!(m.find_halfedge(1, 3).is_some() && m.find_halfedge(3, 1).is_some());
        let (_, mut t, _) = m.to_triangles().unwrap();
        for f in &mut t {
            let r = f
                .iter()
                .position(|&v| v == *f.iter().min().unwrap())
                .unwrap();
            f.rotate_left(r);
        }
        t.sort_unstable();
        assert_eq!(t, vec![[0, 1, 3], [1, 2, 3]]);
        let b = m.find_halfedge(0, 1).unwrap();
        assert_eq!(m.flip_edge(b), Err(LocalOpError::BoundaryEdge));
        // Tetrahedron: every flip would double an edge.
        let tet = HalfedgeMesh::from_triangles(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            &[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap();
        let mut t2 = tet.clone();
        assert_eq!(t2.flip_edge(0), Err(LocalOpError::EdgeExists));
        assert_eq!(t2, tet);
        // Flipping twice restores the connectivity.
        let (p, t) = grid(3, 3);
        let mut g = HalfedgeMesh::from_triangles(p, &t).unwrap();
        let h = g.find_halfedge(5, 10).unwrap();
        let before = g.to_polygons();
        g.flip_edge(h).unwrap();
        g.flip_edge(h).unwrap();
        g.validate().unwrap();
        let mut a: Vec<Vec<u32>> = before.faces.iter().map(|f| canonical(f)).collect();
        let mut b: Vec<Vec<u32>> = g.to_polygons().faces.iter().map(|f| canonical(f)).collect();
        a.sort();
        b.sort();
        assert_eq!(a, b);
    }

    fn canonical(f: &[u32]) -> Vec<u32> {
        let r = f.iter().enumerate().min_by_key(|(_, v)| **v).unwrap().0;
        let mut v = f.to_vec();
        v.rotate_left(r);
        v
    }

    #[test]
    fn split_adds_a_vertex_two_faces_and_keeps_the_area() {
        let (p, t) = grid(2, 2);
        let mut m = HalfedgeMesh::from_triangles(p, &t).unwrap();
        // Interior diagonal and a boundary edge.
        for (a, b) in [(0, 4), (1, 0), (4, 5)] {
            let h = m.find_halfedge(a, b).unwrap();
            let (v, e, f) = (m.num_vertices(), m.num_edges(), m.num_faces());
            let faces = 2 - usize::from(m.is_boundary_edge(h));
            let pa = m.position(a);
            let pb = m.position(b);
            let mid = [0, 1, 2].map(|i| 0.5 * (pa[i] + pb[i]));
            let x = m.split_edge(h, mid).unwrap();
            m.validate().unwrap();
            assert_eq!(m.num_vertices(), v + 1);
            assert_eq!(m.num_faces(), f + faces);
            assert_eq!(m.num_edges(), e + 1 + faces);
            assert_eq!(m.origin(h), a);
            assert_eq!(m.dest(h), x);
            assert!(m.find_halfedge(x, b).is_some());
            assert_eq!(m.euler_characteristic(), 1);
        }
        let (p, t, _) = m.to_triangles().unwrap();
        let area: f64 = t.iter().map(|f| area_of(&p, f)).sum();
        assert!((area - 4.0).abs() < 1e-12);
        // All triangles keep facing +z.
        assert!(t.iter().all(|f| signed_z(&p, f) > 0.0));
    }

    fn area_of(p: &[[f64; 3]], f: &[u32; 3]) -> f64 {
        let [a, b, c] = f.map(|i| p[i as usize]);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
    }

    fn signed_z(p: &[[f64; 3]], f: &[u32; 3]) -> f64 {
        let [a, b, c] = f.map(|i| p[i as usize]);
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    }

    #[test]
    fn collapse_removes_a_vertex_and_honours_the_link_condition() {
        let (p, t) = grid(3, 3);
        let mut m = HalfedgeMesh::from_triangles(p, &t).unwrap();
        // Interior edge 5→6 (both interior vertices): two faces go.
        let h = m.find_halfedge(5, 6).unwrap();
        let b = m.collapse_edge(h, [1.5, 1.0, 0.0]).unwrap();
        m.validate().unwrap();
        assert_eq!(b, 6);
        assert!(!m.vertex_alive(5));
        assert_eq!((m.num_vertices(), m.num_faces()), (15, 16));
        assert_eq!(m.euler_characteristic(), 1);
        // Boundary edge 1→2: one face goes.
        let h = m.find_halfedge(1, 2).unwrap();
        m.collapse_edge(h, [1.5, 0.0, 0.0]).unwrap();
        m.validate().unwrap();
        assert_eq!((m.num_vertices(), m.num_faces()), (14, 15));
        assert_eq!(m.boundary_loops().len(), 1);
        // An interior edge between two boundary vertices is refused: 4 = (0,1), 9 = (1, 2)?
        // Build one directly: a strip of two triangles, the diagonal joins boundary vertices.
        let strip = HalfedgeMesh::from_triangles(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            &[[0, 1, 2], [0, 2, 3]],
        )
        .unwrap();
        let d = strip.find_halfedge(0, 2).unwrap();
        assert_eq!(strip.can_collapse(d), Err(LocalOpError::LinkCondition));
        // A lone triangle: every edge has both others on the boundary.
        let lone = HalfedgeMesh::from_triangles(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            &[[0, 1, 2]],
        )
        .unwrap();
        assert_eq!(lone.can_collapse(0), Err(LocalOpError::LinkCondition));
        // Tetrahedron: collapsing any edge would leave two faces glued back to back.
        let mut tet = HalfedgeMesh::from_triangles(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            &[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap();
        let before = tet.clone();
        for h in 0..12 {
            assert_eq!(
                tet.collapse_edge(h, [0.0; 3]),
                Err(LocalOpError::LinkCondition)
            );
        }
        assert_eq!(tet, before);
        // Octahedron: collapsing an edge is fine (6 → 5 vertices, a square pyramid... of
        // triangles), but a vertex of valence 3 next to the edge blocks the next one.
        let mut oct = octahedron();
        let h = oct.find_halfedge(0, 2).unwrap();
        oct.collapse_edge(h, [0.0; 3]).unwrap();
        oct.validate().unwrap();
        assert_eq!(
            (oct.num_vertices(), oct.num_faces(), oct.genus()),
            (5, 6, 0)
        );
        assert!(oct.is_watertight());
    }

    pub(crate) fn octahedron() -> HalfedgeMesh {
        let p = vec![
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
        ];
        let t = [
            [0, 2, 4],
            [2, 1, 4],
            [1, 3, 4],
            [3, 0, 4],
            [2, 0, 5],
            [1, 2, 5],
            [3, 1, 5],
            [0, 3, 5],
        ];
        HalfedgeMesh::from_triangles(p, &t).unwrap()
    }

    /// A small random mesh: a perturbed icosphere, a perturbed torus or a grid.
    pub(crate) fn random_mesh(kind: u8, seed: u64) -> HalfedgeMesh {
        let mut rng = SplitMix64::new(seed);
        let (mut p, t) = match kind % 3 {
            0 => {
                let m = crate::render::primitives::bumpy_icosphere(1, 0.3, seed);
                (
                    m.positions.iter().map(|v| v.map(f64::from)).collect(),
                    m.triangles,
                )
            }
            1 => torus(6 + (seed % 3) as u32, 5),
            _ => grid(3 + (seed % 3) as u32, 4),
        };
        for v in &mut p {
            for x in v.iter_mut() {
                *x += 0.1 * (rng.uniform() - 0.5);
            }
        }
        HalfedgeMesh::from_triangles(p, &t).unwrap()
    }

    #[derive(Debug, Clone)]
    enum Action {
        Flip(u32),
        Split(u32),
        Collapse(u32),
    }

    fn action() -> impl Strategy<Value = Action> {
        prop_oneof![
            any::<u32>().prop_map(Action::Flip),
            any::<u32>().prop_map(Action::Split),
            any::<u32>().prop_map(Action::Collapse),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn invariants_hold_after_every_local_operation(
            kind in 0u8..3,
            seed in any::<u64>(),
            actions in proptest::collection::vec(action(), 1..60),
        ) {
            let mut m = random_mesh(kind, seed);
            let chi = m.euler_characteristic();
            let genus = m.genus();
            let loops = m.boundary_loops().len();
            for a in actions {
                let pick = |r: u32, m: &HalfedgeMesh| {
                    let n = m.halfedge_capacity() as u32;
                    (0..n).map(|i| (r % n + i) % n).find(|&h| m.halfedge_alive(h))
                };
                let Some(h) = pick(match a { Action::Flip(r) | Action::Split(r) | Action::Collapse(r) => r }, &m) else { break };
                let before = m.clone();
                let (v, f) = (m.num_vertices(), m.num_faces());
                let boundary = m.is_boundary_edge(h);
                let faces = 2 - usize::from(boundary);
                let (pa, pb) = (m.position(m.origin(h)), m.position(m.dest(h)));
                let mid = [0, 1, 2].map(|i| 0.5 * (pa[i] + pb[i]));
                let result = match a {
                    Action::Flip(_) => m.flip_edge(h).map(|_| (v, f)),
                    Action::Split(_) => m.split_edge(h, mid).map(|_| (v + 1, f + faces)),
                    Action::Collapse(_) => m.collapse_edge(h, mid).map(|_| (v - 1, f - faces)),
                };
                match result {
                    Ok(counts) => prop_assert_eq!((m.num_vertices(), m.num_faces()), counts),
                    Err(_) => prop_assert_eq!(&m, &before),
                }
                if let Err(e) = m.validate() {
                    return Err(TestCaseError::fail(format!("{a:?} on {h}: {e}")));
                }
                prop_assert_eq!(m.euler_characteristic(), chi);
                prop_assert_eq!(m.genus(), genus);
                prop_assert_eq!(m.boundary_loops().len(), loops);
                // The indexed round trip rebuilds the same structure.
                let (p, t, _) = m.to_triangles().unwrap();
                let again = HalfedgeMesh::from_triangles(p, &t).unwrap();
                again.validate().unwrap();
                prop_assert_eq!(again.num_edges(), m.num_edges());
            }
        }
    }
}
