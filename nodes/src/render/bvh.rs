//! Bounding-volume hierarchy over a triangle mesh: binned SAH construction, nearest-hit and
//! any-hit ray traversal, watertight ray–triangle intersection.
//!
//! Construction follows Wald, "On fast construction of SAH-based bounding volume hierarchies"
//! (IEEE RT 2007): at each node the triangle centroids are binned along each axis, the surface
//! area heuristic `C_trav + (A_L N_L + A_R N_R) / A` is evaluated at every bin boundary, and the
//! cheapest split wins unless a leaf is cheaper (`N` triangle tests) and small enough. Subtrees
//! above [`PARALLEL_MIN_TRIANGLES`] are built in parallel with `rayon::join`; the tree depends only
//! on the mesh and the options, never on the thread count.
//!
//! Traversal is the classic stack-based one: the slab test against both children (Kay & Kajiya
//! 1986, NaN-safe min/max), nearer child first, farther one pushed.
//! Intersection is the watertight test of Woop, Benthin & Wald (JCGT 2013), two-sided, in f32.

use std::sync::Arc;

use ocellus_engine::value::{Bvh, BvhNode, Mesh};

/// Subtrees with more triangles than this are built in parallel.
pub const PARALLEL_MIN_TRIANGLES: usize = 16_384;

/// Deepest tree the traversal stack holds (a binned SAH tree over `u32` triangles stays far
/// below; the builder falls back to median splits long before).
pub const MAX_DEPTH: usize = 64;

/// Build settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BvhOptions {
    /// Centroid bins per axis in the SAH sweep, 2..=256.
    pub bins: usize,
    /// Most triangles in a leaf, 1..=64.
    pub max_leaf_size: usize,
    /// Cost of visiting an inner node relative to one ray–triangle test, > 0.
    pub traversal_cost: f32,
}

impl BvhOptions {
    /// Why the options are out of range, if they are.
    pub fn validate(&self) -> Result<(), String> {
        if !(2..=256).contains(&self.bins) {
            return Err(format!("`bins` must be 2..=256, got {}", self.bins));
        }
        if !(1..=64).contains(&self.max_leaf_size) {
            return Err(format!(
                "`max_leaf_size` must be 1..=64, got {}",
                self.max_leaf_size
            ));
        }
        if !(self.traversal_cost.is_finite() && self.traversal_cost > 0.0) {
            return Err(format!(
                "`traversal_cost` must be finite and > 0, got {}",
                self.traversal_cost
            ));
        }
        Ok(())
    }
}

impl Default for BvhOptions {
    fn default() -> Self {
        BvhOptions {
            bins: 16,
            max_leaf_size: 4,
            traversal_cost: 1.0,
        }
    }
}

/// Why a BVH could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BvhError {
    /// A vertex has a NaN or infinite coordinate.
    #[error("vertex {vertex} has a non-finite coordinate {position:?}")]
    NonFiniteVertex {
        /// Vertex index.
        vertex: usize,
        /// Its position.
        position: [f32; 3],
    },
    /// A triangle refers to a vertex that does not exist.
    #[error("triangle {triangle} refers to vertex {index}, but the mesh has {vertices} vertices")]
    IndexOutOfRange {
        /// Triangle index.
        triangle: usize,
        /// The bad vertex index.
        index: u32,
        /// Vertex count.
        vertices: usize,
    },
    /// More triangles than `u32` indexes.
    #[error("{0} triangles is more than a BVH indexes (u32)")]
    TooManyTriangles(usize),
    /// Options out of range.
    #[error("{0}")]
    Options(String),
}

/// Axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Aabb {
    min: [f32; 3],
    max: [f32; 3],
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    fn grow(&mut self, p: [f32; 3]) {
        for (k, v) in p.into_iter().enumerate() {
            self.min[k] = self.min[k].min(v);
            self.max[k] = self.max[k].max(v);
        }
    }

    fn merge(&mut self, b: &Aabb) {
        for k in 0..3 {
            self.min[k] = self.min[k].min(b.min[k]);
            self.max[k] = self.max[k].max(b.max[k]);
        }
    }

    /// Half the surface area (the SAH only compares ratios); 0 for an empty box.
    fn half_area(&self) -> f32 {
        let d = [0, 1, 2].map(|k| (self.max[k] - self.min[k]).max(0.0));
        d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    }
}

/// Per-triangle box and centroid.
#[derive(Debug, Clone, Copy)]
struct PrimBox {
    bounds: Aabb,
    centroid: [f32; 3],
}

/// Validates the mesh and builds the hierarchy over all its triangles (degenerate ones
/// included: they are simply never hit).
pub fn build_bvh(mesh: Arc<Mesh>, options: &BvhOptions) -> Result<Bvh, BvhError> {
    options.validate().map_err(BvhError::Options)?;
    if mesh.triangles.len() > u32::MAX as usize / 2 {
        return Err(BvhError::TooManyTriangles(mesh.triangles.len()));
    }
    if let Some((vertex, p)) = mesh
        .positions
        .iter()
        .enumerate()
        .find(|(_, p)| !p.iter().all(|v| v.is_finite()))
    {
        return Err(BvhError::NonFiniteVertex {
            vertex,
            position: *p,
        });
    }
    let n_vertices = mesh.positions.len();
    for (triangle, t) in mesh.triangles.iter().enumerate() {
        if let Some(&index) = t.iter().find(|&&i| i as usize >= n_vertices) {
            return Err(BvhError::IndexOutOfRange {
                triangle,
                index,
                vertices: n_vertices,
            });
        }
    }
    let corners_of = |t: &[u32; 3]| t.map(|i| mesh.positions[i as usize]);
    let prims: Vec<PrimBox> = mesh
        .triangles
        .iter()
        .map(|t| {
            let mut bounds = Aabb::EMPTY;
            let c = corners_of(t);
            for p in c {
                bounds.grow(p);
            }
            let centroid = [0, 1, 2].map(|k| (c[0][k] + c[1][k] + c[2][k]) / 3.0);
            PrimBox { bounds, centroid }
        })
        .collect();
    let mut ids: Vec<u32> = (0..prims.len() as u32).collect();
    let nodes = if prims.is_empty() {
        Vec::new()
    } else {
        siblings_adjacent(&build_node(&prims, &mut ids, 0, 0, options))
    };
    let corners: Vec<[[f32; 3]; 3]> = ids
        .iter()
        .map(|&i| corners_of(&mesh.triangles[i as usize]))
        .collect();
    Ok(Bvh {
        nodes,
        primitives: ids,
        corners,
        mesh,
    })
}

/// Builds the subtree over `ids` (which start at `start` in the final primitive order) and
/// returns its nodes, depth-first with the subtree root first; inner offsets are relative to
/// the subtree, leaf offsets absolute.
fn build_node(
    prims: &[PrimBox],
    ids: &mut [u32],
    start: usize,
    depth: usize,
    options: &BvhOptions,
) -> Vec<BvhNode> {
    let mut bounds = Aabb::EMPTY;
    let mut centroid_bounds = Aabb::EMPTY;
    for &i in ids.iter() {
        let p = &prims[i as usize];
        bounds.merge(&p.bounds);
        centroid_bounds.grow(p.centroid);
    }
    let n = ids.len();
    let leaf = |ids: &[u32]| {
        vec![BvhNode {
            min: bounds.min,
            offset: start as u32,
            max: bounds.max,
            count: ids.len() as u32,
        }]
    };
    if n <= 1 {
        return leaf(ids);
    }
    let split = best_split(prims, ids, &bounds, &centroid_bounds, options);
    let leaf_cost = n as f32;
    let mid = match split {
        Some((cost, axis, bin)) if n > options.max_leaf_size || cost < leaf_cost => {
            partition(prims, ids, &centroid_bounds, axis, bin, options.bins)
        }
        None if n > options.max_leaf_size => n / 2,
        _ => return leaf(ids),
    };
    // Past MAX_DEPTH - 1 levels the traversal stack could overflow; split by halves only
    // (never reached for real meshes: a median split halves the count).
    let mid = if depth + 1 >= MAX_DEPTH - 8 {
        n / 2
    } else {
        mid
    };
    let (left_ids, right_ids) = ids.split_at_mut(mid);
    let (left, right) = if n > PARALLEL_MIN_TRIANGLES {
        rayon::join(
            || build_node(prims, left_ids, start, depth + 1, options),
            || build_node(prims, right_ids, start + mid, depth + 1, options),
        )
    } else {
        (
            build_node(prims, left_ids, start, depth + 1, options),
            build_node(prims, right_ids, start + mid, depth + 1, options),
        )
    };
    let mut nodes = Vec::with_capacity(1 + left.len() + right.len());
    let right_base = 1 + left.len();
    nodes.push(BvhNode {
        min: bounds.min,
        offset: right_base as u32,
        max: bounds.max,
        count: 0,
    });
    nodes.extend(left.into_iter().map(|mut c| {
        if !c.is_leaf() {
            c.offset += 1;
        }
        c
    }));
    nodes.extend(right.into_iter().map(|mut c| {
        if !c.is_leaf() {
            c.offset += right_base as u32;
        }
        c
    }));
    nodes
}

/// Reorders a depth-first tree (first child next to its parent, `offset` = second child) so
/// that every node's two children are adjacent (`offset` = first child, `offset + 1` = second):
/// a traversal step then reads both child boxes from one 64-byte pair. Pairs are laid out in
/// depth-first order of their parents, so a subtree stays mostly contiguous.
fn siblings_adjacent(depth_first: &[BvhNode]) -> Vec<BvhNode> {
    let mut out = Vec::with_capacity(depth_first.len());
    out.push(depth_first[0]);
    // (old index, new index) of inner nodes whose children still need slots.
    let mut stack = vec![(0usize, 0usize)];
    while let Some((old, new)) = stack.pop() {
        let node = depth_first[old];
        if node.is_leaf() {
            continue;
        }
        let (a, b) = (old + 1, node.offset as usize);
        let first = out.len();
        out.push(depth_first[a]);
        out.push(depth_first[b]);
        out[new].offset = first as u32;
        // Second child pushed first so the first child's subtree is laid out next.
        stack.push((b, first + 1));
        stack.push((a, first));
    }
    out
}

/// The bin of centroid coordinate `c` along an axis binned from `lo` with `scale` bins per
/// unit.
fn bin_of(c: f32, lo: f32, scale: f32, bins: usize) -> usize {
    (((c - lo) * scale) as usize).min(bins - 1)
}

/// Cheapest SAH split `(cost, axis, last bin of the left side)` in units of one triangle
/// test, or `None` when every centroid coincides.
fn best_split(
    prims: &[PrimBox],
    ids: &[u32],
    bounds: &Aabb,
    centroid_bounds: &Aabb,
    options: &BvhOptions,
) -> Option<(f32, usize, usize)> {
    let bins = options.bins;
    let parent_area = bounds.half_area();
    let mut best: Option<(f32, usize, usize)> = None;
    let mut counts = vec![0u32; bins];
    let mut boxes = vec![Aabb::EMPTY; bins];
    let mut right_area = vec![0.0f32; bins];
    let mut right_count = vec![0u32; bins];
    for axis in 0..3 {
        let lo = centroid_bounds.min[axis];
        let extent = centroid_bounds.max[axis] - lo;
        if extent.is_nan() || extent <= 0.0 {
            continue;
        }
        let scale = bins as f32 / extent;
        counts.iter_mut().for_each(|c| *c = 0);
        boxes.iter_mut().for_each(|b| *b = Aabb::EMPTY);
        for &i in ids {
            let p = &prims[i as usize];
            let b = bin_of(p.centroid[axis], lo, scale, bins);
            counts[b] += 1;
            boxes[b].merge(&p.bounds);
        }
        // Sweep from the right: right_area[b] / right_count[b] cover bins b..bins.
        let mut acc = Aabb::EMPTY;
        let mut count = 0u32;
        for b in (1..bins).rev() {
            acc.merge(&boxes[b]);
            count += counts[b];
            right_area[b] = acc.half_area();
            right_count[b] = count;
        }
        let mut acc = Aabb::EMPTY;
        let mut count = 0u32;
        for b in 0..bins - 1 {
            acc.merge(&boxes[b]);
            count += counts[b];
            let rc = right_count[b + 1];
            if count == 0 || rc == 0 {
                continue;
            }
            let cost = if parent_area > 0.0 {
                options.traversal_cost
                    + (acc.half_area() * count as f32 + right_area[b + 1] * rc as f32) / parent_area
            } else {
                // A flat, zero-area node: any split costs its halves' counts.
                options.traversal_cost + count.max(rc) as f32
            };
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, b));
            }
        }
    }
    best
}

/// Reorders `ids` so those whose centroid falls in bins `..=bin` along `axis` come first;
/// returns how many.
fn partition(
    prims: &[PrimBox],
    ids: &mut [u32],
    centroid_bounds: &Aabb,
    axis: usize,
    bin: usize,
    bins: usize,
) -> usize {
    let lo = centroid_bounds.min[axis];
    let scale = bins as f32 / (centroid_bounds.max[axis] - lo);
    let left = |i: u32| bin_of(prims[i as usize].centroid[axis], lo, scale, bins) <= bin;
    let (mut a, mut b) = (0usize, ids.len());
    while a < b {
        if left(ids[a]) {
            a += 1;
        } else {
            b -= 1;
            ids.swap(a, b);
        }
    }
    a
}

/// A ray `origin + t · direction`, `t` in `(t_min, t_max)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// Origin.
    pub origin: [f32; 3],
    /// Direction (any length; `t` is in its units).
    pub direction: [f32; 3],
    /// Hits at `t ≤ t_min` are ignored.
    pub t_min: f32,
    /// Hits at `t ≥ t_max` are ignored.
    pub t_max: f32,
}

/// The nearest hit of a ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter of the hit.
    pub t: f32,
    /// The triangle's index in the mesh.
    pub triangle: u32,
    /// Barycentric coordinate of the triangle's second corner.
    pub u: f32,
    /// Barycentric coordinate of the third corner.
    pub v: f32,
}

#[inline(always)]
fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// A ray prepared for the watertight test: the axis `kz` along which the direction is largest,
/// the other two axes (swapped for a negative `kz` component so winding is kept), and the shear
/// that maps the direction onto `+kz` with unit length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShearedRay {
    origin: [f32; 3],
    k: [usize; 3],
    shear: [f32; 3],
}

impl ShearedRay {
    /// Prepares `origin + t · direction`; `None` for a zero or non-finite direction.
    pub fn new(origin: [f32; 3], direction: [f32; 3]) -> Option<ShearedRay> {
        if !direction.iter().all(|v| v.is_finite()) || direction == [0.0; 3] {
            return None;
        }
        let a = direction.map(f32::abs);
        let kz = if a[0] >= a[1] && a[0] >= a[2] {
            0
        } else if a[1] >= a[2] {
            1
        } else {
            2
        };
        let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
        if direction[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        Some(ShearedRay {
            origin,
            k: [kx, ky, kz],
            shear: [
                direction[kx] / direction[kz],
                direction[ky] / direction[kz],
                1.0 / direction[kz],
            ],
        })
    }
}

/// Watertight ray–triangle intersection (Woop, Benthin & Wald, JCGT 2013): `(t, u, v)` with
/// `u`, `v` the barycentric weights of the second and third corners, two-sided, when
/// `t_min < t < t_max`. Shared edges and vertices are never missed by both triangles: the edge
/// functions of a shared edge are exact negations, and ties (an edge function of exactly 0) are
/// recomputed in f64.
#[inline(always)]
pub fn intersect_triangle(
    ray: &ShearedRay,
    c: &[[f32; 3]; 3],
    t_min: f32,
    t_max: f32,
) -> Option<(f32, f32, f32)> {
    let [kx, ky, kz] = ray.k;
    let [sx, sy, sz] = ray.shear;
    let a = sub(c[0], ray.origin);
    let b = sub(c[1], ray.origin);
    let cc = sub(c[2], ray.origin);
    let ax = a[kx] - sx * a[kz];
    let ay = a[ky] - sy * a[kz];
    let bx = b[kx] - sx * b[kz];
    let by = b[ky] - sy * b[kz];
    let cx = cc[kx] - sx * cc[kz];
    let cy = cc[ky] - sy * cc[kz];
    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        let (ax, ay, bx, by, cx, cy) = (
            f64::from(ax),
            f64::from(ay),
            f64::from(bx),
            f64::from(by),
            f64::from(cx),
            f64::from(cy),
        );
        u = (cx * by - cy * bx) as f32;
        v = (ax * cy - ay * cx) as f32;
        w = (bx * ay - by * ax) as f32;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let t_scaled = u * (sz * a[kz]) + v * (sz * b[kz]) + w * (sz * cc[kz]);
    let inv_det = 1.0 / det;
    let t = t_scaled * inv_det;
    (t > t_min && t < t_max).then_some((t, v * inv_det, w * inv_det))
}

/// Entry distance of the ray into `node`'s box, or `INFINITY` when it misses within
/// `(t_min, t_max)`.
#[inline(always)]
fn slab(node: &BvhNode, origin: [f32; 3], inv: [f32; 3], t_min: f32, t_max: f32) -> f32 {
    let mut near = t_min;
    let mut far = t_max;
    for k in 0..3 {
        let t0 = (node.min[k] - origin[k]) * inv[k];
        let t1 = (node.max[k] - origin[k]) * inv[k];
        // No NaN can arise (finite boxes, finite `inv`), so plain comparisons (one minss /
        // maxss each) replace f32::min/max's NaN handling.
        let (lo, hi) = if t0 < t1 { (t0, t1) } else { (t1, t0) };
        near = if lo > near { lo } else { near };
        far = if hi < far { hi } else { far };
    }
    if near <= far { near } else { f32::INFINITY }
}

/// Nearest hit of `ray` in `bvh`.
pub fn intersect(bvh: &Bvh, ray: &Ray) -> Option<Hit> {
    traverse::<false>(bvh, ray)
}

/// Whether anything blocks `ray` (any hit, for shadow rays).
pub fn occluded(bvh: &Bvh, ray: &Ray) -> bool {
    traverse::<true>(bvh, ray).is_some()
}

fn traverse<const ANY: bool>(bvh: &Bvh, ray: &Ray) -> Option<Hit> {
    let nodes = &bvh.nodes;
    if nodes.is_empty() || ray.t_min.is_nan() || ray.t_max.is_nan() || ray.t_min >= ray.t_max {
        return None;
    }
    let o = ray.origin;
    let sheared = ShearedRay::new(o, ray.direction)?;
    // A zero direction component would make the slab test compute 0 · ∞ = NaN for a ray lying
    // in a box face's plane; a tiny stand-in component tilts the ray into one side of the
    // plane instead (the triangle test keeps the exact direction).
    let inv = ray.direction.map(|v| {
        if v.abs() < f32::MIN_POSITIVE {
            1.0 / f32::MIN_POSITIVE.copysign(v)
        } else {
            1.0 / v
        }
    });
    let mut t_best = ray.t_max;
    let mut best: Option<(u32, f32, f32)> = None;
    let mut stack = [0u32; MAX_DEPTH];
    let mut top = 0usize;
    let mut current = 0usize;
    if slab(&nodes[0], o, inv, ray.t_min, t_best) == f32::INFINITY {
        return None;
    }
    loop {
        let node = &nodes[current];
        if node.is_leaf() {
            let first = node.offset as usize;
            let last = first + node.count as usize;
            for k in first..last {
                if let Some((t, u, v)) =
                    intersect_triangle(&sheared, &bvh.corners[k], ray.t_min, t_best)
                {
                    t_best = t;
                    best = Some((k as u32, u, v));
                    if ANY {
                        return best.map(|(k, u, v)| Hit {
                            t,
                            triangle: bvh.primitives[k as usize],
                            u,
                            v,
                        });
                    }
                }
            }
        } else {
            let a = node.offset as usize;
            let b = a + 1;
            let ta = slab(&nodes[a], o, inv, ray.t_min, t_best);
            let tb = slab(&nodes[b], o, inv, ray.t_min, t_best);
            let (near, t_near, far, t_far) = if ta <= tb {
                (a, ta, b, tb)
            } else {
                (b, tb, a, ta)
            };
            if t_near != f32::INFINITY {
                if t_far != f32::INFINITY && top < MAX_DEPTH {
                    stack[top] = far as u32;
                    top += 1;
                }
                current = near;
                continue;
            }
        }
        // Pop the next subtree that the ray can still reach before t_best.
        loop {
            if top == 0 {
                return best.map(|(k, u, v)| Hit {
                    t: t_best,
                    triangle: bvh.primitives[k as usize],
                    u,
                    v,
                });
            }
            top -= 1;
            let next = stack[top] as usize;
            if slab(&nodes[next], o, inv, ray.t_min, t_best) != f32::INFINITY {
                current = next;
                break;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::primitives::bumpy_icosphere;

    fn brute_force(mesh: &Mesh, ray: &Ray) -> Option<(f32, u32)> {
        let mut best: Option<(f32, u32)> = None;
        let sheared = ShearedRay::new(ray.origin, ray.direction)?;
        for (i, t) in mesh.triangles.iter().enumerate() {
            let c = t.map(|k| mesh.positions[k as usize]);
            let t_max = best.map_or(ray.t_max, |b| b.0);
            if let Some((t, _, _)) = intersect_triangle(&sheared, &c, ray.t_min, t_max) {
                best = Some((t, i as u32));
            }
        }
        best
    }

    /// Every node's box contains its children's boxes and its triangles; every triangle is in
    /// exactly one leaf; leaves respect the size bound unless forced.
    fn check_structure(bvh: &Bvh, max_leaf: usize) {
        let n = bvh.mesh.triangles.len();
        let mut seen = vec![0u32; n];
        let mut stack = vec![0usize];
        let contains = |outer: &BvhNode, p: [f32; 3]| {
            (0..3).all(|k| outer.min[k] <= p[k] && p[k] <= outer.max[k])
        };
        while let Some(i) = stack.pop() {
            let node = bvh.nodes[i];
            if node.is_leaf() {
                assert!(node.count as usize <= max_leaf.max(1));
                for k in node.offset as usize..(node.offset + node.count) as usize {
                    seen[bvh.primitives[k] as usize] += 1;
                    for p in bvh.corners[k] {
                        assert!(contains(&node, p), "leaf {i} box misses a corner");
                    }
                }
            } else {
                for c in [node.offset as usize, node.offset as usize + 1] {
                    let child = bvh.nodes[c];
                    assert!(contains(&node, child.min) && contains(&node, child.max));
                    stack.push(c);
                }
            }
        }
        assert!(seen.iter().all(|&s| s == 1), "each triangle in one leaf");
        let stats = bvh.stats();
        assert_eq!(stats.nodes, 2 * stats.leaves - 1, "a full binary tree");
    }

    #[test]
    fn tree_is_well_formed_and_corners_follow_primitives() {
        let mesh = Arc::new(bumpy_icosphere(3, 0.05, 11));
        for options in [
            BvhOptions::default(),
            BvhOptions {
                bins: 2,
                max_leaf_size: 1,
                traversal_cost: 0.125,
            },
            BvhOptions {
                bins: 64,
                max_leaf_size: 16,
                traversal_cost: 4.0,
            },
        ] {
            let bvh = build_bvh(mesh.clone(), &options).unwrap();
            check_structure(&bvh, options.max_leaf_size);
            for (k, &p) in bvh.primitives.iter().enumerate() {
                let t = mesh.triangles[p as usize];
                assert_eq!(bvh.corners[k], t.map(|i| mesh.positions[i as usize]));
            }
        }
    }

    #[test]
    fn nearest_hit_equals_brute_force() {
        let mesh = Arc::new(bumpy_icosphere(3, 0.08, 5));
        let bvh = build_bvh(mesh.clone(), &BvhOptions::default()).unwrap();
        let mut rng = crate::describe::brief::SplitMix64::new(9);
        let mut hits = 0;
        for _ in 0..2000 {
            let mut r = || (rng.next_u64() >> 11) as f32 / (1u64 << 53) as f32 * 2.0 - 1.0;
            let origin = [3.0 * r(), 3.0 * r(), 3.0 * r()];
            let target = [0.8 * r(), 0.8 * r(), 0.8 * r()];
            let ray = Ray {
                origin,
                direction: sub(target, origin),
                t_min: 0.0,
                t_max: f32::INFINITY,
            };
            let fast = intersect(&bvh, &ray);
            let slow = brute_force(&mesh, &ray);
            assert_eq!(fast.map(|h| (h.t, h.triangle)), slow, "ray {ray:?}");
            assert_eq!(occluded(&bvh, &ray), slow.is_some());
            hits += usize::from(slow.is_some());
        }
        assert!(hits > 1500, "most rays aim inside the sphere: {hits}");
    }

    #[test]
    fn axis_parallel_rays_and_rays_inside_the_box_hit() {
        // A unit square in z = 0 made of two triangles; rays along the axes.
        let mesh = Arc::new(Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            ..Mesh::default()
        });
        let bvh = build_bvh(mesh, &BvhOptions::default()).unwrap();
        let down = |x: f32, y: f32| Ray {
            origin: [x, y, 2.0],
            direction: [0.0, 0.0, -1.0],
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        let h = intersect(&bvh, &down(0.25, 0.75)).unwrap();
        assert_eq!((h.t, h.triangle), (2.0, 1));
        let h = intersect(&bvh, &down(0.75, 0.25)).unwrap();
        assert_eq!((h.t, h.triangle), (2.0, 0));
        assert!(intersect(&bvh, &down(1.5, 0.5)).is_none());
        // A ray lying in the plane of the (flat) box misses without NaN trouble.
        let grazing = Ray {
            origin: [-1.0, 0.5, 0.0],
            direction: [1.0, 0.0, 0.0],
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        assert!(intersect(&bvh, &grazing).is_none());
        // t_max and t_min bound the hit.
        let mut r = down(0.25, 0.25);
        r.t_max = 2.0;
        assert!(intersect(&bvh, &r).is_none());
        r.t_max = 2.5;
        r.t_min = 2.0;
        assert!(intersect(&bvh, &r).is_none());
    }

    #[test]
    fn same_tree_for_any_thread_count() {
        let mesh = Arc::new(bumpy_icosphere(6, 0.05, 3));
        assert!(mesh.triangles.len() > PARALLEL_MIN_TRIANGLES * 2);
        let build = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| build_bvh(mesh.clone(), &BvhOptions::default()).unwrap())
        };
        let one = build(1);
        let three = build(3);
        assert_eq!(one.nodes, three.nodes);
        assert_eq!(one.primitives, three.primitives);
        check_structure(&one, 4);
    }

    #[test]
    fn bad_meshes_and_options_are_errors() {
        let mut mesh = bumpy_icosphere(1, 0.0, 1);
        mesh.positions[3][1] = f32::NAN;
        assert!(matches!(
            build_bvh(Arc::new(mesh), &BvhOptions::default()),
            Err(BvhError::NonFiniteVertex { vertex: 3, .. })
        ));
        let mut mesh = bumpy_icosphere(1, 0.0, 1);
        mesh.triangles[2][1] = 10_000;
        assert!(matches!(
            build_bvh(Arc::new(mesh), &BvhOptions::default()),
            Err(BvhError::IndexOutOfRange {
                triangle: 2,
                index: 10_000,
                ..
            })
        ));
        let mesh = Arc::new(bumpy_icosphere(1, 0.0, 1));
        for options in [
            BvhOptions {
                bins: 1,
                ..BvhOptions::default()
            },
            BvhOptions {
                max_leaf_size: 0,
                ..BvhOptions::default()
            },
            BvhOptions {
                traversal_cost: f32::NAN,
                ..BvhOptions::default()
            },
        ] {
            assert!(matches!(
                build_bvh(mesh.clone(), &options),
                Err(BvhError::Options(_))
            ));
        }
        // Empty and single-triangle meshes are fine.
        let empty = build_bvh(Arc::new(Mesh::default()), &BvhOptions::default()).unwrap();
        assert!(empty.nodes.is_empty());
        let ray = Ray {
            origin: [0.0; 3],
            direction: [0.0, 0.0, 1.0],
            t_min: 0.0,
            t_max: 1.0,
        };
        assert!(intersect(&empty, &ray).is_none());
    }

    #[test]
    fn rays_through_vertices_and_edges_of_a_closed_mesh_always_hit() {
        // Watertightness: a ray from outside a closed convex mesh aimed exactly at a vertex or
        // an edge midpoint, not grazing it, must hit (Möller–Trumbore can miss every triangle
        // there). The un-bumped icosphere is convex with its vertices on the unit sphere, so
        // its outward normal at a target p is ≈ p.
        let mesh = Arc::new(bumpy_icosphere(3, 0.0, 2));
        let bvh = build_bvh(mesh.clone(), &BvhOptions::default()).unwrap();
        let mut targets: Vec<[f32; 3]> = mesh.positions.clone();
        for t in &mesh.triangles {
            let (a, b) = (mesh.positions[t[0] as usize], mesh.positions[t[1] as usize]);
            targets.push([0, 1, 2].map(|k| 0.5 * (a[k] + b[k])));
        }
        let mut tested = 0;
        for (i, p) in targets.iter().enumerate() {
            for origin in [
                [0.0, 0.0, -3.0],
                [2.5, 1.5, 0.5],
                [0.0, 3.0, 0.0],
                [p[0] * 4.0, p[1] * 4.0, p[2] * 4.0],
            ] {
                let d = sub(*p, origin);
                let cos = -(d[0] * p[0] + d[1] * p[1] + d[2] * p[2])
                    / (d.iter().map(|v| v * v).sum::<f32>().sqrt()
                        * p.iter().map(|v| v * v).sum::<f32>().sqrt());
                if cos < 0.2 {
                    continue; // back-facing or grazing: the ray may only touch the surface
                }
                tested += 1;
                let ray = Ray {
                    origin,
                    direction: d,
                    t_min: 0.0,
                    t_max: f32::INFINITY,
                };
                assert!(
                    intersect(&bvh, &ray).is_some(),
                    "target {i} {p:?} from {origin:?}: brute force {:?}",
                    brute_force(&mesh, &ray)
                );
            }
        }
        assert!(tested > 3000, "{tested}");
    }

    #[test]
    fn coincident_triangles_still_split_into_bounded_leaves() {
        // 100 copies of one triangle: every centroid coincides, so splits are by halves.
        let mesh = Arc::new(Mesh {
            positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2]; 100],
            ..Mesh::default()
        });
        let bvh = build_bvh(mesh, &BvhOptions::default()).unwrap();
        check_structure(&bvh, 4);
        let ray = Ray {
            origin: [0.2, 0.2, 1.0],
            direction: [0.0, 0.0, -1.0],
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        assert_eq!(intersect(&bvh, &ray).map(|h| h.t), Some(1.0));
    }
}
