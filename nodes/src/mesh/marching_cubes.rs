//! Iso-surface extraction from a scalar grid by marching cubes (Lorensen & Cline, "Marching
//! cubes: a high resolution 3D surface construction algorithm", SIGGRAPH 1987), with the
//! ambiguous faces resolved by the asymptotic decider (Nielson & Hamann, "The asymptotic
//! decider: resolving the ambiguity in marching cubes", Visualization 1991), so that the output
//! is watertight.
//!
//! Instead of the 256-entry case table, each cube's polygons are built from its faces: on every
//! face the crossings of the iso-value are joined by segments, oriented so that the inside
//! region (values `< iso`) lies on their left seen from outside the cube. On a face with four
//! crossings (alternating corner signs) the decider joins the two inside corners when the
//! bilinear interpolant's saddle is inside, which happens exactly when the product of the inside
//! corners' values (relative to `iso`) exceeds that of the outside corners. That test uses only
//! the face's four values, so the two cubes sharing a face draw the same segments there; and the
//! segments of one cube chain into closed loops, the boundaries of the inside region on the
//! cube's surface. Each loop becomes a triangle fan. A fan diagonal never joins two crossings on
//! one face (a neighbouring cube could draw the same diagonal); when no fan apex avoids that,
//! the loop is fanned around an added vertex at its centroid. Hence every edge of the output
//! lies in exactly two triangles, with opposite directions, wherever the surface does not reach
//! the grid's border.
//!
//! One vertex per crossed grid edge, shared by the up to four cubes around it, placed by linear
//! interpolation. Triangles are counter-clockwise seen from outside, i.e. from the side of
//! values `≥ iso`, so their normals point towards increasing values ("negative inside").
//! Vertices are numbered in the order the grid is swept (z slabs, then y rows, then x), so the
//! output depends only on the input.

/// Why an iso-surface cannot be extracted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MarchingCubesError {
    /// The value array does not hold `nx·ny·nz` values.
    #[error("a {nx}×{ny}×{nz} grid needs {needed} values, got {got}")]
    Size {
        /// Grid nodes along x.
        nx: usize,
        /// Grid nodes along y.
        ny: usize,
        /// Grid nodes along z.
        nz: usize,
        /// `nx·ny·nz`.
        needed: usize,
        /// Values given.
        got: usize,
    },
    /// A grid value or the iso-value is NaN or infinite.
    #[error("grid value {index} is not finite")]
    NonFinite {
        /// Index of the first bad value (`usize::MAX` for the iso-value).
        index: usize,
    },
    /// More vertices than 32-bit indices can address.
    #[error("the surface has more than 2^32 − 1 vertices")]
    TooManyVertices,
}

/// A scalar field sampled on the nodes of a regular grid: node `(x, y, z)` holds
/// `values[x + nx·(y + ny·z)]` and lies at `origin + spacing·(x, y, z)`.
#[derive(Debug, Clone, Copy)]
pub struct ScalarGrid<'a> {
    /// Node values, x fastest.
    pub values: &'a [f64],
    /// Nodes per axis.
    pub dims: [usize; 3],
    /// Position of node `(0, 0, 0)`.
    pub origin: [f64; 3],
    /// Distance between neighbouring nodes.
    pub spacing: f64,
}

/// An indexed triangle surface in f64.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct IsoSurface {
    /// Vertex positions.
    pub positions: Vec<[f64; 3]>,
    /// Counter-clockwise triangles seen from outside (the side of values `≥ iso`).
    pub triangles: Vec<[u32; 3]>,
}

/// Corner `c` of a cube is its node `(c & 1, (c >> 1) & 1, c >> 2)` relative to the cube's first.
/// The 12 cube edges as corner pairs (lower corner first), x edges, then y, then z.
const EDGES: [[usize; 2]; 12] = [
    [0, 1],
    [2, 3],
    [4, 5],
    [6, 7],
    [0, 2],
    [1, 3],
    [4, 6],
    [5, 7],
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7],
];

/// The 6 faces as corner cycles, counter-clockwise seen from outside the cube: −x, +x, −y, +y,
/// −z, +z.
const FACES: [[usize; 4]; 6] = [
    [0, 4, 6, 2],
    [1, 3, 7, 5],
    [0, 1, 5, 4],
    [2, 6, 7, 3],
    [0, 2, 3, 1],
    [4, 5, 7, 6],
];

const NO_VERTEX: u32 = u32::MAX;

/// The cube edge joining corners `a` and `b` (adjacent corners).
fn edge_between(a: usize, b: usize) -> usize {
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    EDGES
        .iter()
        .position(|e| e[0] == lo && e[1] == hi)
        .unwrap_or(0)
}

/// Precomputed per-face edge indices and which cube edges share a face.
struct Tables {
    /// `face_edges[f][m]`: the cube edge from `FACES[f][m]` to `FACES[f][m + 1]`.
    face_edges: [[usize; 4]; 6],
    /// `share_face[a][b]`: cube edges `a` and `b` lie on a common face.
    share_face: [[bool; 12]; 12],
}

impl Tables {
    fn new() -> Tables {
        let mut face_edges = [[0; 4]; 6];
        let mut share_face = [[false; 12]; 12];
        for (f, face) in FACES.iter().enumerate() {
            for m in 0..4 {
                face_edges[f][m] = edge_between(face[m], face[(m + 1) % 4]);
            }
            for &a in &face_edges[f] {
                for &b in &face_edges[f] {
                    share_face[a][b] = true;
                }
            }
        }
        Tables {
            face_edges,
            share_face,
        }
    }
}

/// Vertex ids of the crossed edges of one z plane: x edges and y edges, `nx·ny` slots each.
struct PlaneEdges {
    x: Vec<u32>,
    y: Vec<u32>,
}

struct Builder<'a> {
    grid: ScalarGrid<'a>,
    iso: f64,
    out: IsoSurface,
}

impl Builder<'_> {
    fn value(&self, x: usize, y: usize, z: usize) -> f64 {
        let [nx, ny, _] = self.grid.dims;
        self.grid
            .values
            .get(x + nx * (y + ny * z))
            .copied()
            .unwrap_or(0.0)
            - self.iso
    }

    fn push(&mut self, p: [f64; 3]) -> Result<u32, MarchingCubesError> {
        let id = u32::try_from(self.out.positions.len())
            .ok()
            .filter(|&i| i != NO_VERTEX)
            .ok_or(MarchingCubesError::TooManyVertices)?;
        self.out.positions.push(p);
        Ok(id)
    }

    /// The vertex on the edge from node `(x, y, z)` along `axis`, if the edge is crossed.
    fn edge_vertex(
        &mut self,
        x: usize,
        y: usize,
        z: usize,
        axis: usize,
    ) -> Result<u32, MarchingCubesError> {
        let mut n = [x, y, z];
        n[axis] += 1;
        let a = self.value(x, y, z);
        let b = self.value(n[0], n[1], n[2]);
        if (a < 0.0) == (b < 0.0) {
            return Ok(NO_VERTEX);
        }
        // a and b are on opposite sides, so b − a ≠ 0 and t ∈ [0, 1].
        let t = (-a / (b - a)).clamp(0.0, 1.0);
        let g = self.grid;
        let mut p = [x as f64, y as f64, z as f64];
        p[axis] += t;
        self.push([0, 1, 2].map(|k| g.origin[k] + g.spacing * p[k]))
    }

    fn plane(&mut self, z: usize) -> Result<PlaneEdges, MarchingCubesError> {
        let [nx, ny, _] = self.grid.dims;
        let mut plane = PlaneEdges {
            x: vec![NO_VERTEX; nx * ny],
            y: vec![NO_VERTEX; nx * ny],
        };
        for y in 0..ny {
            for x in 0..nx {
                if x + 1 < nx {
                    plane.x[x + nx * y] = self.edge_vertex(x, y, z, 0)?;
                }
                if y + 1 < ny {
                    plane.y[x + nx * y] = self.edge_vertex(x, y, z, 1)?;
                }
            }
        }
        Ok(plane)
    }
}

/// Extracts the iso-surface `value = iso` of `grid` (see the module documentation). A grid with
/// fewer than 2 nodes along an axis has no cubes and gives an empty surface.
pub fn marching_cubes(grid: ScalarGrid<'_>, iso: f64) -> Result<IsoSurface, MarchingCubesError> {
    let [nx, ny, nz] = grid.dims;
    let needed = nx
        .checked_mul(ny)
        .and_then(|v| v.checked_mul(nz))
        .unwrap_or(usize::MAX);
    if grid.values.len() != needed {
        return Err(MarchingCubesError::Size {
            nx,
            ny,
            nz,
            needed,
            got: grid.values.len(),
        });
    }
    if !iso.is_finite() {
        return Err(MarchingCubesError::NonFinite { index: usize::MAX });
    }
    if let Some(index) = grid.values.iter().position(|v| !v.is_finite()) {
        return Err(MarchingCubesError::NonFinite { index });
    }
    let mut b = Builder {
        grid,
        iso,
        out: IsoSurface::default(),
    };
    if nx < 2 || ny < 2 || nz < 2 {
        return Ok(b.out);
    }
    let tables = Tables::new();
    let mut lower = b.plane(0)?;
    for z in 0..nz - 1 {
        let mut vertical = vec![NO_VERTEX; nx * ny];
        for y in 0..ny {
            for x in 0..nx {
                vertical[x + nx * y] = b.edge_vertex(x, y, z, 2)?;
            }
        }
        let upper = b.plane(z + 1)?;
        for y in 0..ny - 1 {
            for x in 0..nx - 1 {
                let d: [f64; 8] =
                    std::array::from_fn(|c| b.value(x + (c & 1), y + ((c >> 1) & 1), z + (c >> 2)));
                let inside = d.iter().filter(|v| **v < 0.0).count();
                if inside == 0 || inside == 8 {
                    continue;
                }
                let ids: [u32; 12] = std::array::from_fn(|e| {
                    let c = EDGES[e][0];
                    let (cx, cy, cz) = (c & 1, (c >> 1) & 1, c >> 2);
                    let slot = (x + cx) + nx * (y + cy);
                    let plane = if cz == 0 { &lower } else { &upper };
                    match e / 4 {
                        0 => plane.x.get(slot),
                        1 => plane.y.get(slot),
                        _ => vertical.get(slot),
                    }
                    .copied()
                    .unwrap_or(NO_VERTEX)
                });
                cube(&mut b, &tables, &d, &ids)?;
            }
        }
        lower = upper;
    }
    Ok(b.out)
}

/// The loops and triangles of one cube with relative corner values `d` and edge vertices `ids`.
fn cube(
    b: &mut Builder<'_>,
    tables: &Tables,
    d: &[f64; 8],
    ids: &[u32; 12],
) -> Result<(), MarchingCubesError> {
    // next[e]: the crossed cube edge the inside region's boundary reaches from edge e.
    let mut next = [usize::MAX; 12];
    for (f, face) in FACES.iter().enumerate() {
        let inside: [bool; 4] = face.map(|c| d[c] < 0.0);
        let exits: Vec<usize> = (0..4)
            .filter(|&m| inside[m] && !inside[(m + 1) % 4])
            .collect();
        let entries: Vec<usize> = (0..4)
            .filter(|&m| !inside[m] && inside[(m + 1) % 4])
            .collect();
        let fe = tables.face_edges[f];
        match (exits.as_slice(), entries.as_slice()) {
            ([m], [n]) => next[fe[*m]] = fe[*n],
            ([m0, m1], [_, _]) => {
                // Alternating signs: the decider. Inside corners are face[m0], face[m1].
                let inside_product = d[face[*m0]] * d[face[*m1]];
                let outside_product = d[face[(m0 + 1) % 4]] * d[face[(m1 + 1) % 4]];
                let joined = inside_product > outside_product;
                for &m in &[*m0, *m1] {
                    let to = if joined { (m + 1) % 4 } else { (m + 3) % 4 };
                    next[fe[m]] = fe[to];
                }
            }
            _ => {}
        }
    }
    let mut seen = [false; 12];
    let mut ring: Vec<usize> = Vec::with_capacity(12);
    for start in 0..12 {
        if seen[start] || next[start] == usize::MAX {
            continue;
        }
        ring.clear();
        let mut e = start;
        while !seen[e] {
            seen[e] = true;
            ring.push(e);
            e = next.get(e).copied().unwrap_or(usize::MAX);
            if e == usize::MAX {
                // Cannot happen: every crossed edge has one successor on each of its faces.
                return Ok(());
            }
        }
        fan(b, tables, &ring, ids)?;
    }
    Ok(())
}

/// Triangulates one loop of cube edges (reversed: the loop runs clockwise seen from outside).
fn fan(
    b: &mut Builder<'_>,
    tables: &Tables,
    ring: &[usize],
    ids: &[u32; 12],
) -> Result<(), MarchingCubesError> {
    let n = ring.len();
    let v: Vec<u32> = ring.iter().map(|&e| ids[e]).collect();
    if v.contains(&NO_VERTEX) {
        return Ok(());
    }
    if n == 3 {
        b.out.triangles.push([v[0], v[2], v[1]]);
        return Ok(());
    }
    let apex = (0..n).find(|&a| {
        (2..n - 1).all(|k| {
            let other = ring[(a + k) % n];
            !tables.share_face[ring[a]][other]
        })
    });
    match apex {
        Some(a) => {
            for k in 1..n - 1 {
                let (p, q) = (v[(a + k) % n], v[(a + k + 1) % n]);
                b.out.triangles.push([v[a], q, p]);
            }
        }
        None => {
            let mut c = [0.0; 3];
            for &i in &v {
                let p = b.out.positions.get(i as usize).copied().unwrap_or([0.0; 3]);
                for k in 0..3 {
                    c[k] += p[k];
                }
            }
            let center = b.push(c.map(|s| s / n as f64))?;
            for k in 0..n {
                let (p, q) = (v[k], v[(k + 1) % n]);
                b.out.triangles.push([center, q, p]);
            }
        }
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::kdtree::KdTree;
    use proptest::prelude::*;
    use std::collections::HashMap;

    /// Topology of a triangle surface: Euler characteristic, and whether it is a closed,
    /// consistently oriented 2-manifold (every directed edge once, with its reverse).
    pub(crate) fn closed_euler(s: &IsoSurface) -> Result<i64, String> {
        let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &s.triangles {
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return Err(format!("degenerate triangle {t:?}"));
            }
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        for (&(a, b), &count) in &directed {
            if count != 1 {
                return Err(format!("directed edge {a}→{b} used {count} times"));
            }
            if !directed.contains_key(&(b, a)) {
                return Err(format!("edge {a}→{b} is a border or misoriented"));
            }
        }
        // Vertex manifoldness: the triangles around each vertex form one cycle.
        let mut around: HashMap<u32, Vec<(u32, u32)>> = HashMap::new();
        for t in &s.triangles {
            for k in 0..3 {
                around
                    .entry(t[k])
                    .or_default()
                    .push((t[(k + 1) % 3], t[(k + 2) % 3]));
            }
        }
        for (v, fans) in &around {
            let succ: HashMap<u32, u32> = fans.iter().copied().collect();
            let mut at = fans[0].0;
            let mut steps = 0;
            loop {
                at = succ[&at];
                steps += 1;
                if at == fans[0].0 {
                    break;
                }
            }
            if steps != fans.len() {
                return Err(format!("vertex {v} is not manifold"));
            }
        }
        let used = around.len() as i64;
        let edges = directed.len() as i64 / 2;
        Ok(used - edges + s.triangles.len() as i64)
    }

    /// Signed volume enclosed (positive for outward orientation).
    pub(crate) fn volume(s: &IsoSurface) -> f64 {
        s.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| s.positions[i as usize]);
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0]))
                    / 6.0
            })
            .sum()
    }

    /// `n` points uniformly on the surface (area-weighted, seeded).
    pub(crate) fn sample_surface(s: &IsoSurface, n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut cumulative = Vec::with_capacity(s.triangles.len());
        let mut total = 0.0;
        for t in &s.triangles {
            let [a, b, c] = t.map(|i| s.positions[i as usize]);
            let u = [0, 1, 2].map(|k| b[k] - a[k]);
            let v = [0, 1, 2].map(|k| c[k] - a[k]);
            let cr = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            total += 0.5 * (cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2]).sqrt();
            cumulative.push(total);
        }
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                let r = rng.uniform() * total;
                let i = cumulative
                    .partition_point(|&c| c < r)
                    .min(s.triangles.len() - 1);
                let [a, b, c] = s.triangles[i].map(|k| s.positions[k as usize]);
                let (mut u, mut v) = (rng.uniform(), rng.uniform());
                if u + v > 1.0 {
                    (u, v) = (1.0 - u, 1.0 - v);
                }
                [0, 1, 2].map(|k| a[k] + u * (b[k] - a[k]) + v * (c[k] - a[k]))
            })
            .collect()
    }

    fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }

    fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    /// The point of triangle `abc` closest to `p` (Ericson, "Real-Time Collision Detection",
    /// §5.1.5: Voronoi regions of the vertices, then the edges, then the face).
    pub(crate) fn closest_on_triangle(
        p: [f64; 3],
        a: [f64; 3],
        b: [f64; 3],
        c: [f64; 3],
    ) -> [f64; 3] {
        let at = |u: [f64; 3], s: f64, v: [f64; 3], t: f64| {
            [0, 1, 2].map(|k| a[k] + s * u[k] + t * v[k])
        };
        let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
        let (d1, d2) = (dot3(ab, ap), dot3(ac, ap));
        if d1 <= 0.0 && d2 <= 0.0 {
            return a;
        }
        let bp = sub(p, b);
        let (d3, d4) = (dot3(ab, bp), dot3(ac, bp));
        if d3 >= 0.0 && d4 <= d3 {
            return b;
        }
        let vc = d1 * d4 - d3 * d2;
        if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
            return at(ab, d1 / (d1 - d3), ac, 0.0);
        }
        let cp = sub(p, c);
        let (d5, d6) = (dot3(ab, cp), dot3(ac, cp));
        if d6 >= 0.0 && d5 <= d6 {
            return c;
        }
        let vb = d5 * d2 - d1 * d6;
        if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
            return at(ab, 0.0, ac, d2 / (d2 - d6));
        }
        let va = d3 * d6 - d5 * d4;
        if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
            let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
            return [0, 1, 2].map(|k| b[k] + w * (c[k] - b[k]));
        }
        let denom = 1.0 / (va + vb + vc);
        at(ab, vb * denom, ac, vc * denom)
    }

    /// Mean and maximum distances both ways between a surface and the truth: `dense` samples
    /// of the surface to the truth by `distance`; the truth's samples `truth` to the surface,
    /// exactly, over the 24 triangles with the nearest centroids (an upper bound in general,
    /// exact on the fine, even triangulations tested here).
    pub(crate) fn chamfer(
        s: &IsoSurface,
        distance: impl Fn(&[f64; 3]) -> f64,
        truth: &[[f64; 3]],
        dense: usize,
    ) -> [f64; 4] {
        let samples = sample_surface(s, dense, 99);
        let to_truth: Vec<f64> = samples.iter().map(&distance).collect();
        let tri = |i: usize| s.triangles[i].map(|k| s.positions[k as usize]);
        let centroids: Vec<[f64; 3]> = (0..s.triangles.len())
            .map(|i| {
                let [a, b, c] = tri(i);
                [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0)
            })
            .collect();
        let tree = KdTree::new(centroids);
        let mut nb = Vec::new();
        let to_surface: Vec<f64> = truth
            .iter()
            .map(|p| {
                tree.knn(p, 24, f64::INFINITY, &mut nb);
                nb.iter()
                    .map(|m| {
                        let [a, b, c] = tri(m.index);
                        let q = closest_on_triangle(*p, a, b, c);
                        dot3(sub(*p, q), sub(*p, q)).sqrt()
                    })
                    .fold(f64::INFINITY, f64::min)
            })
            .collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        [
            mean(&to_truth),
            max(&to_truth),
            mean(&to_surface),
            max(&to_surface),
        ]
    }

    #[test]
    fn closest_point_on_a_triangle_by_region() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]);
        let cases = [
            ([0.5, 0.5, 3.0], [0.5, 0.5, 0.0]),
            ([-1.0, -1.0, 1.0], a),
            ([3.0, -0.5, 0.0], b),
            ([-0.1, 5.0, 0.0], c),
            ([1.0, -2.0, 0.0], [1.0, 0.0, 0.0]),
            ([-2.0, 1.0, 1.0], [0.0, 1.0, 0.0]),
            ([2.0, 2.0, -1.0], [1.0, 1.0, 0.0]),
        ];
        for (p, want) in cases {
            let got = closest_on_triangle(p, a, b, c);
            assert!(
                (0..3).all(|k| (got[k] - want[k]).abs() < 1e-12),
                "{p:?}: {got:?}"
            );
        }
    }

    fn sample_grid(n: usize, h: f64, origin: f64, f: impl Fn([f64; 3]) -> f64) -> Vec<f64> {
        let mut values = Vec::with_capacity(n * n * n);
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    values.push(f([x, y, z].map(|i| origin + h * i as f64)));
                }
            }
        }
        values
    }

    #[test]
    fn faces_are_counter_clockwise_from_outside() {
        let corner = |c: usize| [c & 1, (c >> 1) & 1, c >> 2].map(|v| v as f64);
        for face in FACES {
            let [a, b, c] = [face[0], face[1], face[2]].map(corner);
            let u = [0, 1, 2].map(|k| b[k] - a[k]);
            let v = [0, 1, 2].map(|k| c[k] - b[k]);
            let n = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let centre = [0, 1, 2].map(|k| face.iter().map(|&c| corner(c)[k]).sum::<f64>() / 4.0);
            let outward = [0, 1, 2].map(|k| centre[k] - 0.5);
            assert!(
                (0..3).map(|k| n[k] * outward[k]).sum::<f64>() > 0.0,
                "{face:?}"
            );
        }
    }

    #[test]
    fn one_inside_corner_gives_one_outward_triangle() {
        // Corner 0 at −1, the rest at +1: a triangle cutting it off at the edge midpoints,
        // its normal pointing away from corner 0.
        let mut values = vec![1.0; 8];
        values[0] = -1.0;
        let grid = ScalarGrid {
            values: &values,
            dims: [2, 2, 2],
            origin: [0.0; 3],
            spacing: 2.0,
        };
        let s = marching_cubes(grid, 0.0).unwrap();
        assert_eq!(s.triangles.len(), 1);
        let mut pos = s.positions.clone();
        pos.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(pos, vec![[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]);
        let [a, b, c] = s.triangles[0].map(|i| s.positions[i as usize]);
        let u = [0, 1, 2].map(|k| b[k] - a[k]);
        let v = [0, 1, 2].map(|k| c[k] - a[k]);
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        assert!(n.iter().all(|&x| x > 0.0), "{n:?}");
    }

    #[test]
    fn bad_input_is_an_error_and_flat_grids_are_empty() {
        let values = vec![0.0; 7];
        let g = ScalarGrid {
            values: &values,
            dims: [2, 2, 2],
            origin: [0.0; 3],
            spacing: 1.0,
        };
        assert!(matches!(
            marching_cubes(g, 0.0),
            Err(MarchingCubesError::Size { .. })
        ));
        let mut values = vec![0.0; 8];
        values[3] = f64::NAN;
        let g = ScalarGrid {
            values: &values,
            ..g
        };
        assert_eq!(
            marching_cubes(g, 0.0),
            Err(MarchingCubesError::NonFinite { index: 3 })
        );
        let values = vec![1.0; 8];
        let g = ScalarGrid {
            values: &values,
            ..g
        };
        assert_eq!(
            marching_cubes(g, f64::INFINITY),
            Err(MarchingCubesError::NonFinite { index: usize::MAX })
        );
        let flat = ScalarGrid {
            values: &values,
            dims: [8, 1, 1],
            ..g
        };
        assert!(marching_cubes(flat, 0.0).unwrap().triangles.is_empty());
    }

    #[test]
    fn sphere_is_a_closed_sphere_within_a_fraction_of_a_voxel() {
        let (n, h, r) = (40usize, 0.1, 1.53);
        let c = [1.95, 2.02, 1.97];
        let dist = |p: &[f64; 3]| {
            ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt() - r
        };
        let values = sample_grid(n, h, 0.0, |p| dist(&p));
        let grid = ScalarGrid {
            values: &values,
            dims: [n; 3],
            origin: [0.0; 3],
            spacing: h,
        };
        let s = marching_cubes(grid, 0.0).unwrap();
        assert_eq!(closed_euler(&s), Ok(2));
        let v = volume(&s);
        let truth = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
        assert!((v - truth).abs() < 0.01 * truth, "{v} vs {truth}");
        let on_sphere: Vec<[f64; 3]> = crate::mesh::pointcloud::tests::sphere(4000, c, r, 5);
        let [mean_a, max_a, mean_b, max_b] = chamfer(&s, |p| dist(p).abs(), &on_sphere, 200_000);
        assert!(max_a < 0.5 * h && max_b < 0.5 * h, "{max_a} {max_b}");
        assert!(mean_a < 0.05 * h && mean_b < 0.05 * h, "{mean_a} {mean_b}");
    }

    #[test]
    fn torus_has_euler_characteristic_zero() {
        let (n, h) = (48usize, 0.1);
        let (big, small) = (1.5, 0.55);
        let c = 2.35;
        let dist = |p: &[f64; 3]| {
            let (x, y, z) = (p[0] - c, p[1] - c, p[2] - c);
            (((x * x + y * y).sqrt() - big).powi(2) + z * z).sqrt() - small
        };
        let values = sample_grid(n, h, 0.0, |p| dist(&p));
        let grid = ScalarGrid {
            values: &values,
            dims: [n; 3],
            origin: [0.0; 3],
            spacing: h,
        };
        let s = marching_cubes(grid, 0.0).unwrap();
        assert_eq!(closed_euler(&s), Ok(0));
        assert!(volume(&s) > 0.0);
        let mut rng = SplitMix64::new(8);
        let truth: Vec<[f64; 3]> = (0..4000)
            .map(|_| {
                let (u, v) = (
                    rng.uniform() * std::f64::consts::TAU,
                    rng.uniform() * std::f64::consts::TAU,
                );
                let rr = big + small * v.cos();
                [c + rr * u.cos(), c + rr * u.sin(), c + small * v.sin()]
            })
            .collect();
        let [_, max_a, _, max_b] = chamfer(&s, |p| dist(p).abs(), &truth, 200_000);
        assert!(max_a < 0.5 * h && max_b < 0.5 * h, "{max_a} {max_b}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// Any field on a small grid whose border is outside gives a closed oriented manifold
        /// (saddles, ties at the iso-value and tiny components included).
        #[test]
        fn random_fields_give_closed_manifolds(
            inner in proptest::collection::vec(-3i32..4, 27),
            iso in -1i32..2,
        ) {
            let n = 5;
            let mut values = vec![10.0; n * n * n];
            for z in 0..3 {
                for y in 0..3 {
                    for x in 0..3 {
                        values[(x + 1) + n * ((y + 1) + n * (z + 1))] =
                            f64::from(inner[x + 3 * (y + 3 * z)]);
                    }
                }
            }
            let grid = ScalarGrid { values: &values, dims: [n; 3], origin: [0.0; 3], spacing: 1.0 };
            let s = marching_cubes(grid, f64::from(iso)).unwrap();
            let euler = closed_euler(&s);
            prop_assert!(euler.is_ok(), "{:?}", euler);
            prop_assert!(volume(&s) >= -1e-9);
        }
    }
}
