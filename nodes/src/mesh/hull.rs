//! 3-D convex hull: `mesh.convex_hull`, by Quickhull (Barber, Dobkin & Huhdanpaa, "The
//! Quickhull algorithm for convex hulls", ACM TOMS 22(4), 1996).
//!
//! [`convex_hull`] starts from a tetrahedron of extreme points and repeatedly takes, for a face
//! with a non-empty outside set, the point of that set farthest above the face (the *eye*); the
//! faces the eye sees (distance above their plane > ε, found by a search over face neighbours
//! from that face) are removed and the horizon — the boundary of the visible region — is coned
//! to the eye. The outside points of the removed faces are handed to the new faces they lie above
//! (farthest-above wins); points above none are inside (or within ε of the hull) and are dropped.
//!
//! Robustness:
//! - everything is computed in f64 on coordinates relative to the centroid, so clouds far from
//!   the origin keep their precision;
//! - ε, the distance within which a point counts as *on* a face plane, is relative to the
//!   coordinate scale (`1e-10` × the largest centroid-relative coordinate unless a tolerance is
//!   given), so the result does not depend on the units;
//! - duplicates and points on faces are never above a face by more than ε, so they never become
//!   hull vertices;
//! - a vertex that ends up on a flat part of the hull (all its faces in one plane, e.g. a point
//!   taken before the corners of a face were) or on a straight crease (its faces in two planes)
//!   is not an extreme point: such vertices are dropped and the hull is rebuilt from the
//!   remaining vertices (a hull of hull vertices only, so the rebuild is cheap), until every
//!   vertex is extreme;
//! - an eye whose visible region is not a disc (possible only within ε of degeneracy) is
//!   skipped and counted in the `skipped_points` metric (it lies within a few ε of the hull).
//!
//! The search is sequential and every tie is broken by the lower point index; the initial
//! assignment of points to faces runs in parallel over fixed chunks. The result is the same for
//! any thread count, and the output (hull vertices in input order, triangles sorted) does not
//! depend on the internal order of faces.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};

use super::normals::{cross, dot, norm, sub};
use super::pointcloud::{PointCloudError, cloud_input, par_map, positions_f64};

/// Default ε relative to the largest centroid-relative coordinate.
pub const RELATIVE_TOLERANCE: f64 = 1e-10;

/// Tolerance on the direction of face normals when deciding whether a vertex is extreme (unit
/// normals whose cross/dot products stay below this are taken as parallel / coplanar).
const NORMAL_TOLERANCE: f64 = 1e-9;

/// At most this many rebuilds that drop non-extreme vertices.
const MAX_PASSES: usize = 8;

/// Why no hull could be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HullError {
    /// Fewer than 4 points.
    #[error("a 3-D convex hull needs at least 4 points, got {0}")]
    TooFewPoints(usize),
    /// A coordinate is NaN or infinite.
    #[error("point {index} is not finite")]
    NonFinite {
        /// Index of the first bad point.
        index: usize,
    },
    /// Attribute lengths do not match.
    #[error("{0}")]
    Cloud(String),
    /// All points coincide (within the tolerance).
    #[error("all {0} points coincide: the hull is a single point")]
    Coincident(usize),
    /// All points lie on one line.
    #[error("all points are collinear: the hull is a segment, not a solid")]
    Collinear,
    /// All points lie in one plane.
    #[error(
        "input is planar (all points within {tolerance:e} of one plane): the hull has no volume; \
         use mesh.delaunay_2d for planar points"
    )]
    Planar {
        /// The tolerance used.
        tolerance: f64,
    },
    /// The tolerance is not a positive finite number.
    #[error("the tolerance must be finite and > 0, got {0}")]
    Tolerance(f64),
    /// Too many points for 32-bit indices.
    #[error("{0} points do not fit 32-bit indices")]
    TooLarge(usize),
}

impl From<PointCloudError> for HullError {
    fn from(e: PointCloudError) -> Self {
        match e {
            PointCloudError::NonFinite { index } => HullError::NonFinite { index },
            other => HullError::Cloud(other.to_string()),
        }
    }
}

/// A convex hull: a closed triangle mesh of the extreme input points.
#[derive(Debug, Clone, PartialEq)]
pub struct Hull {
    /// Indices of the hull vertices into the input, ascending; vertex `i` of the mesh is input
    /// point `vertices[i]`.
    pub vertices: Vec<u32>,
    /// Triangles over the hull vertices (indices into `vertices`), counter-clockwise seen from
    /// outside; each rotated to start at its smallest index, sorted.
    pub triangles: Vec<[u32; 3]>,
    /// Enclosed volume (scene units³).
    pub volume: f64,
    /// Surface area (scene units²).
    pub area: f64,
    /// The tolerance ε used (scene units).
    pub tolerance: f64,
    /// Eyes skipped because their visible region was not a disc (near-degenerate input).
    pub skipped_points: usize,
    /// Quickhull runs (1, plus one per rebuild without non-extreme vertices).
    pub passes: usize,
}

/// A triangle of the hull under construction. Edge `i` runs `v[i] → v[(i + 1) % 3]`; `nb[i]` is
/// the face across it.
#[derive(Debug, Clone)]
struct Face {
    v: [u32; 3],
    nb: [u32; 3],
    /// Unit outward normal.
    n: [f64; 3],
    /// A point of the plane (the vertex the normal was computed at).
    origin: [f64; 3],
    /// Outside set: (point, distance above the plane).
    outside: Vec<(u32, f64)>,
    alive: bool,
}

/// The unit normal of triangle (a, b, c), counter-clockwise; computed at the corner opposite
/// the longest edge (the best-conditioned cross product). Returns the corner used.
fn plane(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let (lab, lbc, lca) = (norm(sub(b, a)), norm(sub(c, b)), norm(sub(a, c)));
    // Corner opposite the longest edge, keeping the cyclic order.
    let (o, p, q) = if lbc >= lab && lbc >= lca {
        (a, b, c)
    } else if lca >= lab {
        (b, c, a)
    } else {
        (c, a, b)
    };
    let n = cross(sub(p, o), sub(q, o));
    let l = norm(n);
    let n = if l > 0.0 { n.map(|x| x / l) } else { [0.0; 3] };
    (n, o)
}

struct Builder<'a> {
    q: &'a [[f64; 3]],
    eps: f64,
    faces: Vec<Face>,
    free: Vec<u32>,
    queue: VecDeque<u32>,
    /// Per face: the eye stamp that marked it visible / checked it.
    visible_stamp: Vec<u32>,
    checked_stamp: Vec<u32>,
    stamp: u32,
    skipped: usize,
}

impl Builder<'_> {
    fn dist(&self, f: u32, p: u32) -> f64 {
        let face = &self.faces[f as usize];
        dot(face.n, sub(self.q[p as usize], face.origin))
    }

    fn new_face(&mut self, v: [u32; 3]) -> u32 {
        let (n, origin) = plane(
            self.q[v[0] as usize],
            self.q[v[1] as usize],
            self.q[v[2] as usize],
        );
        let face = Face {
            v,
            nb: [u32::MAX; 3],
            n,
            origin,
            outside: Vec::new(),
            alive: true,
        };
        if let Some(id) = self.free.pop() {
            let slot = &mut self.faces[id as usize];
            let mut outside = std::mem::take(&mut slot.outside);
            outside.clear();
            *slot = Face { outside, ..face };
            id
        } else {
            self.faces.push(face);
            self.visible_stamp.push(0);
            self.checked_stamp.push(0);
            (self.faces.len() - 1) as u32
        }
    }

    /// Index of edge `a → b` in face `f`.
    fn edge_index(&self, f: u32, a: u32, b: u32) -> Option<usize> {
        let v = self.faces[f as usize].v;
        (0..3).find(|&i| v[i] == a && v[(i + 1) % 3] == b)
    }

    /// One Quickhull step on face `f` (which has a non-empty outside set).
    fn step(&mut self, f: u32) {
        // The eye: farthest above `f`, ties to the lower index.
        let Some(&(eye, _)) = self.faces[f as usize].outside.iter().reduce(|a, b| {
            if b.1 > a.1 || (b.1 == a.1 && b.0 < a.0) {
                b
            } else {
                a
            }
        }) else {
            return;
        };
        self.stamp = self.stamp.wrapping_add(1).max(1);
        let stamp = self.stamp;
        // The visible region: faces the eye is above, connected to `f`.
        let mut visible = vec![f];
        self.visible_stamp[f as usize] = stamp;
        let mut i = 0;
        while i < visible.len() {
            let g = visible[i];
            i += 1;
            for k in 0..3 {
                let h = self.faces[g as usize].nb[k];
                let hu = h as usize;
                if self.visible_stamp[hu] == stamp || self.checked_stamp[hu] == stamp {
                    continue;
                }
                if self.dist(h, eye) > self.eps {
                    self.visible_stamp[hu] = stamp;
                    visible.push(h);
                } else {
                    self.checked_stamp[hu] = stamp;
                }
            }
        }
        // Horizon edges (a → b of a visible face, the face across not visible), chained.
        let mut horizon: Vec<(u32, u32, u32)> = Vec::new();
        for &g in &visible {
            let face = &self.faces[g as usize];
            for k in 0..3 {
                let h = face.nb[k];
                if self.visible_stamp[h as usize] != stamp {
                    horizon.push((face.v[k], face.v[(k + 1) % 3], h));
                }
            }
        }
        let mut by_origin: HashMap<u32, usize> = HashMap::with_capacity(horizon.len());
        let mut simple = true;
        for (k, e) in horizon.iter().enumerate() {
            if by_origin.insert(e.0, k).is_some() {
                simple = false;
            }
        }
        let mut chain = Vec::with_capacity(horizon.len());
        if simple && !horizon.is_empty() {
            let mut k = 0;
            loop {
                chain.push(horizon[k]);
                match by_origin.get(&horizon[k].1) {
                    Some(&next) if next != 0 && chain.len() < horizon.len() => k = next,
                    Some(&0) if chain.len() == horizon.len() => break,
                    _ => {
                        simple = false;
                        break;
                    }
                }
            }
        }
        if !simple || chain.len() < 3 {
            // The visible region is not a disc: only possible within ε of degeneracy. Drop the
            // eye (it is within a few ε of the hull) and carry on.
            let face = &mut self.faces[f as usize];
            face.outside.retain(|&(p, _)| p != eye);
            self.skipped += 1;
            if !face.outside.is_empty() {
                self.queue.push_back(f);
            }
            return;
        }
        // Cone the horizon to the eye.
        let mut orphans: Vec<u32> = Vec::new();
        for &g in &visible {
            let face = &mut self.faces[g as usize];
            face.alive = false;
            orphans.extend(face.outside.iter().map(|&(p, _)| p).filter(|&p| p != eye));
            face.outside.clear();
        }
        // Free the visible faces only after the new ones are linked (their slots are reused).
        let new: Vec<u32> = chain
            .iter()
            .map(|&(a, b, _)| self.new_face([a, b, eye]))
            .collect();
        // Free after allocating so no visible slot is reused while it is still being read.
        self.free.extend(visible.iter().rev());
        let m = new.len();
        for (k, &(a, b, g)) in chain.iter().enumerate() {
            let nf = new[k];
            self.faces[nf as usize].nb = [g, new[(k + 1) % m], new[(k + m - 1) % m]];
            if let Some(j) = self.edge_index(g, b, a) {
                self.faces[g as usize].nb[j] = nf;
            }
        }
        // The new planes, contiguous: the loop below is the hot spot of Quickhull.
        let planes: Vec<([f64; 3], [f64; 3])> = new
            .iter()
            .map(|&nf| (self.faces[nf as usize].n, self.faces[nf as usize].origin))
            .collect();
        for p in orphans {
            let q = self.q[p as usize];
            let mut best: Option<(usize, f64)> = None;
            for (k, (n, o)) in planes.iter().enumerate() {
                let d = dot(*n, sub(q, *o));
                if d > self.eps && best.is_none_or(|(_, bd)| d > bd) {
                    best = Some((k, d));
                }
            }
            if let Some((k, d)) = best {
                self.faces[new[k] as usize].outside.push((p, d));
            }
        }
        for &nf in &new {
            if !self.faces[nf as usize].outside.is_empty() {
                self.queue.push_back(nf);
            }
        }
    }
}

/// Index of the point of `ids` maximizing `key`, ties to the first.
fn argmax(ids: &[u32], key: impl Fn(u32) -> f64) -> (u32, f64) {
    let mut best = (ids[0], key(ids[0]));
    for &i in &ids[1..] {
        let k = key(i);
        if k > best.1 {
            best = (i, k);
        }
    }
    best
}

/// Quickhull of the points `ids` of `q` (centroid-relative); faces as input point triples.
fn quickhull(q: &[[f64; 3]], ids: &[u32], eps: f64) -> Result<(Vec<Face>, usize), HullError> {
    // Extreme points along the axes, then the farthest pair among them.
    let mut extremes = Vec::with_capacity(6);
    for axis in [0, 1, 2] {
        extremes.push(argmax(ids, |i| -q[i as usize][axis]).0);
        extremes.push(argmax(ids, |i| q[i as usize][axis]).0);
    }
    let mut pair = (extremes[0], extremes[1], -1.0);
    for (a_i, &a) in extremes.iter().enumerate() {
        for &b in &extremes[a_i + 1..] {
            let d = norm(sub(q[a as usize], q[b as usize]));
            if d > pair.2 {
                pair = (a, b, d);
            }
        }
    }
    let (p0, p1, d01) = pair;
    if d01 <= eps {
        return Err(HullError::Coincident(ids.len()));
    }
    let (a, b) = (q[p0 as usize], q[p1 as usize]);
    let ab = sub(b, a).map(|x| x / d01);
    let (p2, d2) = argmax(ids, |i| norm(cross(ab, sub(q[i as usize], a))));
    if d2 <= eps {
        return Err(HullError::Collinear);
    }
    let (n, o) = plane(a, b, q[p2 as usize]);
    let (p3, d3) = argmax(ids, |i| dot(n, sub(q[i as usize], o)).abs());
    if d3 <= eps {
        return Err(HullError::Planar { tolerance: eps });
    }
    let mut builder = Builder {
        q,
        eps,
        faces: Vec::new(),
        free: Vec::new(),
        queue: VecDeque::new(),
        visible_stamp: Vec::new(),
        checked_stamp: Vec::new(),
        stamp: 0,
        skipped: 0,
    };
    // Orient the tetrahedron outward: p3 below the base.
    let above = dot(n, sub(q[p3 as usize], o)) > 0.0;
    let (b0, b1, b2) = if above { (p0, p2, p1) } else { (p0, p1, p2) };
    let tris = [[b0, b1, b2], [b1, b0, p3], [b2, b1, p3], [b0, b2, p3]];
    let ids4: Vec<u32> = tris.iter().map(|&t| builder.new_face(t)).collect();
    for &f in &ids4 {
        for k in 0..3 {
            let v = builder.faces[f as usize].v;
            let (x, y) = (v[k], v[(k + 1) % 3]);
            if let Some(&g) = ids4
                .iter()
                .find(|&&g| g != f && builder.edge_index(g, y, x).is_some())
            {
                builder.faces[f as usize].nb[k] = g;
            }
        }
    }
    // Initial outside sets, in parallel, then appended in point order.
    let seeds = [p0, p1, p2, p3];
    let assignment: Vec<Option<(u32, f64)>> = {
        let b = &builder;
        par_map(ids.len(), |k| {
            let p = ids[k];
            if seeds.contains(&p) {
                return None;
            }
            let mut best: Option<(u32, f64)> = None;
            for &f in &ids4 {
                let d = b.dist(f, p);
                if d > eps && best.is_none_or(|(_, bd)| d > bd) {
                    best = Some((f, d));
                }
            }
            best
        })
    };
    for (k, a) in assignment.into_iter().enumerate() {
        if let Some((f, d)) = a {
            builder.faces[f as usize].outside.push((ids[k], d));
        }
    }
    for &f in &ids4 {
        if !builder.faces[f as usize].outside.is_empty() {
            builder.queue.push_back(f);
        }
    }
    while let Some(f) = builder.queue.pop_front() {
        let face = &builder.faces[f as usize];
        if face.alive && !face.outside.is_empty() {
            builder.step(f);
        }
    }
    let skipped = builder.skipped;
    Ok((
        builder.faces.into_iter().filter(|f| f.alive).collect(),
        skipped,
    ))
}

/// Whether the unit normals `ns` of the faces around a vertex make it a corner of the hull:
/// they must not all be parallel (a flat region) nor all perpendicular to one direction (a
/// straight crease).
fn is_corner(ns: &[[f64; 3]]) -> bool {
    // The pair of normals farthest from parallel.
    let mut best = ([0.0; 3], 0.0);
    for (i, &a) in ns.iter().enumerate() {
        for &b in &ns[i + 1..] {
            let c = cross(a, b);
            let l = norm(c);
            if l > best.1 {
                best = (c, l);
            }
        }
    }
    if best.1 <= NORMAL_TOLERANCE {
        return false;
    }
    let d = best.0.map(|x| x / best.1);
    ns.iter().any(|&n| dot(n, d).abs() > NORMAL_TOLERANCE)
}

/// The convex hull of `points` (see the module documentation). `tolerance`: ε in scene units,
/// None for `1e-10` × the largest centroid-relative coordinate.
pub fn convex_hull(points: &[[f64; 3]], tolerance: Option<f64>) -> Result<Hull, HullError> {
    let n = points.len();
    if n < 4 {
        return Err(HullError::TooFewPoints(n));
    }
    if u32::try_from(n).is_err() {
        return Err(HullError::TooLarge(n));
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(HullError::NonFinite { index });
    }
    if let Some(t) = tolerance
        && !(t.is_finite() && t > 0.0)
    {
        return Err(HullError::Tolerance(t));
    }
    let mut c = [0.0; 3];
    for p in points {
        for k in 0..3 {
            c[k] += p[k];
        }
    }
    let c = c.map(|x| x / n as f64);
    let q: Vec<[f64; 3]> = par_map(n, |i| sub(points[i], c));
    let scale = q
        .iter()
        .flat_map(|p| p.iter())
        .fold(0.0f64, |m, &x| m.max(x.abs()));
    let eps = tolerance.unwrap_or(RELATIVE_TOLERANCE * scale);
    if scale == 0.0 || eps <= 0.0 || eps.is_nan() {
        return Err(HullError::Coincident(n));
    }
    let mut ids: Vec<u32> = (0..n as u32).collect();
    let mut skipped = 0;
    let mut passes = 0;
    let faces = loop {
        passes += 1;
        let (faces, s) = quickhull(&q, &ids, eps)?;
        skipped += s;
        let mut used: Vec<u32> = faces.iter().flat_map(|f| f.v).collect();
        used.sort_unstable();
        used.dedup();
        // Normals around each vertex: (vertex, face) pairs grouped by vertex.
        let mut around: Vec<(u32, u32)> = faces
            .iter()
            .enumerate()
            .flat_map(|(i, f)| f.v.map(|v| (v, i as u32)))
            .collect();
        around.sort_unstable();
        let mut corners: Vec<u32> = Vec::with_capacity(used.len());
        let mut normals = Vec::new();
        for group in around.chunk_by(|a, b| a.0 == b.0) {
            normals.clear();
            normals.extend(group.iter().map(|&(_, f)| faces[f as usize].n));
            if is_corner(&normals) {
                corners.push(group[0].0);
            }
        }
        if corners.len() == used.len() || passes >= MAX_PASSES || corners.len() < 4 {
            break faces;
        }
        ids = corners;
    };
    let mut vertices: Vec<u32> = faces.iter().flat_map(|f| f.v).collect();
    vertices.sort_unstable();
    vertices.dedup();
    let index: HashMap<u32, u32> = vertices
        .iter()
        .enumerate()
        .map(|(i, &v)| (v, i as u32))
        .collect();
    let mut triangles: Vec<[u32; 3]> = faces
        .iter()
        .map(|f| {
            let t = f.v.map(|v| index.get(&v).copied().unwrap_or(0));
            let r = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
            [t[r], t[(r + 1) % 3], t[(r + 2) % 3]]
        })
        .collect();
    triangles.sort_unstable();
    let (mut volume, mut area) = (0.0, 0.0);
    for t in &triangles {
        let [a, b, cc] = t.map(|i| q[vertices[i as usize] as usize]);
        let x = cross(sub(b, a), sub(cc, a));
        area += 0.5 * norm(x);
        volume += dot(a, cross(b, cc)) / 6.0;
    }
    Ok(Hull {
        vertices,
        triangles,
        volume,
        area,
        tolerance: eps,
        skipped_points: skipped,
        passes,
    })
}

params! {
    /// Parameters of `mesh.convex_hull`.
    pub struct ConvexHullParams {
        /// Distance within which a point counts as on a face plane (points closer are not
        /// hull vertices); None (the default): 1e-10 × the largest coordinate relative to the
        /// centroid.
        tolerance: Option<f64> = None => [min = 0.0, unit = "scene units"],
    }
}

/// `mesh.convex_hull`. See [`convex_hull`].
#[derive(Debug, Clone, PartialEq)]
pub struct ConvexHull {
    params: ConvexHullParams,
}

impl Op for ConvexHull {
    type Params = ConvexHullParams;
    const ID: &'static str = "mesh.convex_hull";
    const SUMMARY: &'static str = "The 3-D convex hull of a point cloud (Quickhull): a closed, outward-oriented triangle mesh.";
    const DOC: &'static str = r#"
Quickhull (Barber, Dobkin & Huhdanpaa, "The Quickhull algorithm for convex hulls", ACM TOMS
1996): from a tetrahedron of extreme points, repeatedly add the point farthest above a face,
remove the faces it sees and cone their horizon to it; points above no face are inside. Computed
in f64 on centroid-relative coordinates with a tolerance ε relative to the coordinate scale
(`tolerance`, default 1e-10 × the largest centroid-relative coordinate): duplicates, interior
points and points on faces or edges of the hull (within ε) are not hull vertices. A vertex left on
a flat face or a straight edge is dropped and the hull rebuilt from the remaining vertices.

Output: `mesh`, the hull vertices only (in input order, positions copied from the cloud) and
triangles counter-clockwise seen from outside — closed, watertight, Euler characteristic 2.
Fewer than 4 points, coincident, collinear or planar input (use `mesh.delaunay_2d` for planar
points) and non-finite coordinates are errors. The result does not depend on the thread count.

Metrics: `input_points`, `hull_vertices`, `triangles`, `volume` (scene units³), `area` (scene
units²), `tolerance` (ε used), `skipped_points` (eyes skipped in near-degenerate configurations;
normally 0), `passes`.

Example:
    "hull": (op: "mesh.convex_hull", inputs: { "cloud": "scan.cloud" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "cloud",
            PortType::PointCloud,
            "Points (at least 4, not all in one plane).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The hull: closed triangle mesh of the hull vertices, outward (CCW) faces.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "input_points, hull_vertices, triangles, volume, area, tolerance, skipped_points, passes.",
            ),
        ]
    }

    fn new(p: ConvexHullParams) -> Result<Self, String> {
        if let Some(t) = p.tolerance
            && !(t.is_finite() && t > 0.0)
        {
            return Err(format!("`tolerance` must be finite and > 0, got {t}"));
        }
        Ok(ConvexHull { params: p })
    }
}

impl Operator for ConvexHull {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        let points = positions_f64(cloud).map_err(|e| e.at("cloud"))?;
        let hull = convex_hull(&points, self.params.tolerance)
            .map_err(|e| OpError::input("cloud", e.to_string()))?;
        let mesh = Mesh {
            positions: hull
                .vertices
                .iter()
                .map(|&v| cloud.positions[v as usize])
                .collect(),
            triangles: hull.triangles.clone(),
            ..Mesh::default()
        };
        let mut m = Metrics::new();
        m.insert("input_points".into(), points.len() as f64);
        m.insert("hull_vertices".into(), hull.vertices.len() as f64);
        m.insert("triangles".into(), hull.triangles.len() as f64);
        m.insert("volume".into(), hull.volume);
        m.insert("area".into(), hull.area);
        m.insert("tolerance".into(), hull.tolerance);
        m.insert("skipped_points".into(), hull.skipped_points as f64);
        m.insert("passes".into(), hull.passes as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(mesh)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::halfedge::HalfedgeMesh;
    use proptest::prelude::*;

    /// Points rounded to f32 and back, as a cloud would hold them.
    fn f32_points(p: &[[f64; 3]]) -> Vec<[f64; 3]> {
        p.iter().map(|v| v.map(|x| f64::from(x as f32))).collect()
    }

    fn hull_positions(points: &[[f64; 3]], h: &Hull) -> Vec<[f64; 3]> {
        h.vertices.iter().map(|&v| points[v as usize]).collect()
    }

    /// Closed, manifold, consistently oriented, χ = 2, outward, and every point inside or on
    /// every face plane (within `slack`).
    fn check_hull(points: &[[f64; 3]], h: &Hull, slack: f64) {
        let pos = hull_positions(points, h);
        let mesh = HalfedgeMesh::from_triangles(pos.clone(), &h.triangles).unwrap();
        mesh.validate().unwrap();
        assert!(mesh.is_watertight());
        assert_eq!(mesh.euler_characteristic(), 2);
        assert_eq!(mesh.components(), 1);
        assert_eq!(h.triangles.len(), 2 * h.vertices.len() - 4);
        let o = pos[0];
        let v: f64 = h
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| sub(pos[i as usize], o));
                dot(a, cross(b, c)) / 6.0
            })
            .sum();
        assert!(v > 0.0, "inward orientation: {v}");
        assert!((v - h.volume).abs() <= 1e-9 * v.abs().max(1.0));
        // Every vertex is strictly extreme: it is the unique maximum of the sum of its face
        // normals (no vertex in the middle of a face or an edge).
        let mut acc = vec![[0.0f64; 3]; pos.len()];
        for t in &h.triangles {
            let [a, b, c] = t.map(|i| pos[i as usize]);
            let nrm = cross(sub(b, a), sub(c, a));
            let l = norm(nrm);
            for &i in t {
                for k in 0..3 {
                    acc[i as usize][k] += nrm[k] / l;
                }
            }
        }
        let scale = pos.iter().flatten().fold(0.0f64, |m, &x| m.max(x.abs()));
        for (i, d) in acc.iter().enumerate() {
            let di = dot(*d, pos[i]);
            for (j, q) in pos.iter().enumerate() {
                assert!(
                    j == i || dot(*d, *q) < di - 1e-13 * scale * norm(*d),
                    "hull vertex {i} is not strictly extreme"
                );
            }
        }
        for t in &h.triangles {
            let [a, b, c] = t.map(|i| pos[i as usize]);
            let nrm = cross(sub(b, a), sub(c, a));
            let l = norm(nrm);
            assert!(l > 0.0, "degenerate hull triangle");
            let nrm = nrm.map(|x| x / l);
            for p in points {
                let d = dot(nrm, sub(*p, a));
                assert!(d <= slack, "point {p:?} is {d} above a face");
            }
        }
    }

    fn sphere(n: usize, c: [f64; 3], r: f64, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                let z = 2.0 * rng.uniform() - 1.0;
                let phi = std::f64::consts::TAU * rng.uniform();
                let s = (1.0 - z * z).sqrt();
                [
                    c[0] + r * s * phi.cos(),
                    c[1] + r * s * phi.sin(),
                    c[2] + r * z,
                ]
            })
            .collect()
    }

    /// The box [0, 2] × [0, 3] × [0, 5]: its corners, then interior points, points on its
    /// faces, on its edges, and duplicates of the corners.
    fn box_cloud(offset: f64, seed: u64) -> Vec<[f64; 3]> {
        let size = [2.0, 3.0, 5.0];
        let mut p: Vec<[f64; 3]> = Vec::new();
        let mut rng = SplitMix64::new(seed);
        // Interior points first, so that they are seen before some corners.
        for _ in 0..200 {
            p.push([0, 1, 2].map(|k| size[k] * (0.05 + 0.9 * rng.uniform())));
        }
        for i in 0..8 {
            p.push([0, 1, 2].map(|k| if (i >> k) & 1 == 1 { size[k] } else { 0.0 }));
        }
        for _ in 0..100 {
            // On a face: one coordinate at 0 or its size; quarter steps keep them exact.
            let axis = (rng.uniform() * 3.0) as usize % 3;
            let side = rng.uniform() < 0.5;
            let mut x = [0, 1, 2].map(|k| size[k] * ((rng.uniform() * 4.0).floor() / 4.0));
            x[axis] = if side { size[axis] } else { 0.0 };
            p.push(x);
            // On an edge: two coordinates at the extremes.
            let mut e = [0, 1, 2].map(|k| if rng.uniform() < 0.5 { 0.0 } else { size[k] });
            e[axis] = size[axis] * ((rng.uniform() * 8.0).floor() / 8.0);
            p.push(e);
        }
        for i in 0..8 {
            p.push([0, 1, 2].map(|k| if (i >> k) & 1 == 1 { size[k] } else { 0.0 }));
        }
        p.iter().map(|v| v.map(|x| x + offset)).collect()
    }

    #[test]
    fn box_with_interior_face_and_edge_points() {
        for (offset, seed) in [(0.0, 1), (-7.25, 2), (1e6, 3)] {
            let p = f32_points(&box_cloud(offset, seed));
            let h = convex_hull(&p, None).unwrap();
            assert_eq!(h.vertices.len(), 8, "offset {offset}");
            assert_eq!(h.triangles.len(), 12);
            // The corners at their first occurrence (indices 200..208).
            assert_eq!(h.vertices, (200..208).collect::<Vec<u32>>());
            assert!((h.volume - 30.0).abs() < 1e-9, "{}", h.volume);
            assert!((h.area - 62.0).abs() < 1e-9, "{}", h.area);
            assert_eq!(h.skipped_points, 0);
            check_hull(&p, &h, 1e-9 * (1.0 + offset.abs()));
        }
    }

    #[test]
    fn full_lattice_hull_is_its_bounding_box() {
        // All 9³ points of the 1/8 lattice of [0, 1]³ (most on faces and edges), shuffled.
        let mut p: Vec<[f64; 3]> = (0..729)
            .map(|i| [i % 9, (i / 9) % 9, i / 81].map(|c| f64::from(c) / 8.0))
            .collect();
        let mut rng = SplitMix64::new(12);
        for i in (1..p.len()).rev() {
            p.swap(i, rng.below(i + 1));
        }
        let h = convex_hull(&p, None).unwrap();
        assert_eq!(h.vertices.len(), 8);
        assert_eq!(h.triangles.len(), 12);
        for &v in &h.vertices {
            assert!(p[v as usize].iter().all(|&c| c == 0.0 || c == 1.0));
        }
        assert!((h.volume - 1.0).abs() < 1e-12);
        assert!((h.area - 6.0).abs() < 1e-12);
        check_hull(&p, &h, 1e-12);
    }

    #[test]
    fn unit_cube_corners_and_center() {
        let mut p: Vec<[f64; 3]> = (0..8)
            .map(|i| [0, 1, 2].map(|a| if (i >> a) & 1 == 1 { 1.0 } else { -1.0 }))
            .collect();
        p.push([0.0; 3]);
        let h = convex_hull(&p, None).unwrap();
        assert_eq!(h.vertices, (0..8).collect::<Vec<u32>>());
        assert_eq!(h.triangles.len(), 12);
        assert!((h.volume - 8.0).abs() < 1e-12, "{}", h.volume);
        assert_eq!(h.area, 24.0);
    }

    #[test]
    fn tetrahedron_hand_computed() {
        // Volume 1/6, area 3/2 + √3/2, outward faces.
        let p = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.1, 0.1, 0.1],
        ];
        let h = convex_hull(&p, None).unwrap();
        assert_eq!(h.vertices, vec![0, 1, 2, 3]);
        assert_eq!(
            h.triangles,
            vec![[0, 1, 3], [0, 2, 1], [0, 3, 2], [1, 2, 3]]
        );
        assert!((h.volume - 1.0 / 6.0).abs() < 1e-14);
        assert!((h.area - (1.5 + 3f64.sqrt() / 2.0)).abs() < 1e-14);
    }

    #[test]
    fn sphere_points_are_all_hull_vertices() {
        for (n, seed) in [(500, 1), (2000, 2), (2000, 3)] {
            let p = f32_points(&sphere(n, [0.3, -0.2, 0.1], 2.0, seed));
            let h = convex_hull(&p, None).unwrap();
            assert_eq!(h.vertices.len(), n, "seed {seed}");
            check_hull(&p, &h, 1e-9);
            let vs = 4.0 / 3.0 * std::f64::consts::PI * 8.0;
            assert!(h.volume <= vs * (1.0 + 1e-6), "{} > {vs}", h.volume);
            assert!(
                h.volume > vs * if n >= 2000 { 0.99 } else { 0.95 },
                "{}",
                h.volume
            );
        }
    }

    #[test]
    fn large_offset_sphere() {
        // Radius 1000 around (1e6, −2e6, 5e5): f32 quantizes to 1/16, still a valid hull.
        let p = f32_points(&sphere(3000, [1e6, -2e6, 5e5], 1000.0, 9));
        let h = convex_hull(&p, None).unwrap();
        check_hull(&p, &h, 1e-6);
        let vs = 4.0 / 3.0 * std::f64::consts::PI * 1e9;
        assert!((h.volume / vs - 1.0).abs() < 0.01, "{}", h.volume / vs);
        assert!(h.vertices.len() > 2900);
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        assert_eq!(
            convex_hull(&[[0.0; 3]; 3], None),
            Err(HullError::TooFewPoints(3))
        );
        assert_eq!(convex_hull(&[], None), Err(HullError::TooFewPoints(0)));
        assert_eq!(
            convex_hull(&[[1.0, 2.0, 3.0]; 10], None),
            Err(HullError::Coincident(10))
        );
        let line: Vec<[f64; 3]> = (0..10)
            .map(|i| [i as f64, 2.0 * i as f64 + 1e6, -(i as f64)])
            .collect();
        assert_eq!(convex_hull(&line, None), Err(HullError::Collinear));
        let mut rng = SplitMix64::new(4);
        let plane: Vec<[f64; 3]> = (0..100)
            .map(|_| {
                let (u, v) = (rng.uniform(), rng.uniform());
                [u, v, 0.5]
            })
            .collect();
        let e = convex_hull(&plane, None).unwrap_err();
        assert!(matches!(e, HullError::Planar { .. }));
        assert!(e.to_string().contains("mesh.delaunay_2d"), "{e}");
        let mut bad = box_cloud(0.0, 1);
        bad[17][1] = f64::NAN;
        assert_eq!(
            convex_hull(&bad, None),
            Err(HullError::NonFinite { index: 17 })
        );
        assert_eq!(
            convex_hull(&box_cloud(0.0, 1), Some(-1.0)),
            Err(HullError::Tolerance(-1.0))
        );
    }

    #[test]
    fn hull_does_not_depend_on_the_thread_count() {
        let mut rng = SplitMix64::new(5);
        let p: Vec<[f64; 3]> = (0..30_000)
            .map(|_| [rng.uniform(), rng.uniform(), rng.uniform() * rng.uniform()])
            .collect();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| convex_hull(&p, None).unwrap())
        };
        let a = run(1);
        assert_eq!(a, run(4));
        check_hull(&p, &a, 1e-9);
    }

    #[test]
    fn op_outputs_mesh_and_metrics() {
        use ocellus_engine::value::PointCloud;
        let p = f32_points(&box_cloud(0.0, 7));
        let cloud = PointCloud {
            positions: p.iter().map(|v| v.map(|x| x as f32)).collect(),
            ..PointCloud::default()
        };
        let op = ConvexHull::new(ConvexHullParams::default()).unwrap();
        let specs = ConvexHull::inputs();
        let values = [Some(Value::PointCloud(Arc::new(cloud)))];
        let ctx = RunContext {
            node: "hull".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Mesh(m)) = out.take("mesh") else {
            panic!("no mesh")
        };
        assert_eq!(m.positions.len(), 8);
        assert_eq!(m.triangles.len(), 12);
        let Some(Value::Metrics(metrics)) = out.take("metrics") else {
            panic!("no metrics")
        };
        assert_eq!(metrics["hull_vertices"], 8.0);
        assert!((metrics["volume"] - 30.0).abs() < 1e-9);
        let planar = PointCloud {
            positions: vec![
                [0.0, 0.0, 1.0],
                [1.0, 0.0, 1.0],
                [0.0, 1.0, 1.0],
                [1.0, 1.0, 1.0],
            ],
            ..PointCloud::default()
        };
        let values = [Some(Value::PointCloud(Arc::new(planar)))];
        let e = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(e.to_string().contains("planar"), "{e}");
    }

    /// Timing at scale (release-like test profile): `cargo test -p ocellus-nodes --lib
    /// mesh::hull::tests::large_clouds -- --ignored --nocapture`.
    #[test]
    #[ignore = "slow: 10⁶-point hulls"]
    fn large_clouds() {
        for n in [100_000, 1_000_000] {
            let mut rng = SplitMix64::new(5);
            let cube: Vec<[f64; 3]> = f32_points(
                &(0..n)
                    .map(|_| [rng.uniform(), rng.uniform(), rng.uniform()])
                    .collect::<Vec<_>>(),
            );
            let ball = f32_points(&sphere(n, [0.0; 3], 1.0, 6));
            for (name, p) in [("cube", &cube), ("sphere", &ball)] {
                let t = std::time::Instant::now();
                let h = convex_hull(p, None).unwrap();
                let dt = t.elapsed();
                println!(
                    "{name} n = {n}: {dt:?}, {} hull vertices, {} triangles, {} passes",
                    h.vertices.len(),
                    h.triangles.len(),
                    h.passes
                );
                let mesh =
                    HalfedgeMesh::from_triangles(hull_positions(p, &h), &h.triangles).unwrap();
                mesh.validate().unwrap();
                assert!(mesh.is_watertight());
                assert_eq!(mesh.euler_characteristic(), 2);
                assert_eq!(h.skipped_points, 0);
                if name == "sphere" {
                    assert!(h.vertices.len() as f64 > 0.999 * n as f64);
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// Random clouds — on a sphere, in a flat slab, in a tiny box far from the origin, with
        /// duplicates — always give a closed outward hull containing every point.
        #[test]
        fn hull_contains_every_point(
            seed in 0u64..1_000_000,
            n in 4usize..400,
            kind in 0u8..4,
            offset in prop_oneof![Just(0.0), -1e6..1e6f64],
        ) {
            let mut rng = SplitMix64::new(seed);
            let mut p: Vec<[f64; 3]> = match kind {
                0 => sphere(n, [0.0; 3], 1.0, seed),
                1 => (0..n).map(|_| [rng.uniform(), rng.uniform(), 1e-3 * rng.uniform()]).collect(),
                2 => (0..n).map(|_| [rng.uniform(), rng.uniform(), rng.uniform()].map(|x| (x * 8.0).floor() / 8.0)).collect(),
                _ => (0..n).map(|_| [rng.uniform(), rng.uniform(), rng.uniform()]).collect(),
            };
            let dups: Vec<[f64; 3]> = p.iter().step_by(3).copied().collect();
            p.extend(dups);
            // Scale up with the offset so that f32 keeps ~1e-4 relative precision.
            let s = 1.0 + offset.abs() * 1e-3;
            let p = f32_points(&p.iter().map(|v| v.map(|x| x * s + offset)).collect::<Vec<_>>());
            match convex_hull(&p, None) {
                Ok(h) => {
                    prop_assert_eq!(h.skipped_points, 0);
                    check_hull(&p, &h, 1e-8 * (s + offset.abs()));
                }
                Err(HullError::Planar { .. }) | Err(HullError::Collinear) | Err(HullError::Coincident(_)) => {
                    // Only tiny grids can be degenerate.
                    prop_assert!(kind == 2 || n < 8);
                }
                Err(e) => prop_assert!(false, "{e}"),
            }
        }
    }
}
