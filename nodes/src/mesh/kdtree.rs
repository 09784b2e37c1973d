//! Exact nearest-neighbour search over 3-D points: the one k-d tree every `mesh` operator uses.
//!
//! [`KdTree::new`] splits the widest axis of each node's bounding box at the median (leaves of at
//! most [`LEAF_SIZE`] points); queries descend to the query's side first and visit the other side
//! only when the splitting plane is no farther than the current worst neighbour (Friedman, Bentley
//! & Finkel, "An algorithm for finding best matches in logarithmic expected time", ACM TOMS 1977).
//!
//! Results are exact and deterministic: neighbours are ordered by `(squared distance, index)`, so
//! among points at equal distance the lower index wins, whatever the tree shape. Pruning keeps a
//! subtree whose plane distance *equals* the worst distance, which is what makes ties exact.
//!
//! Written here rather than taken from a crate (`kiddo`) so that tie-breaking by index is part
//! of the contract and no dependency is added for ~200 lines.

/// Most points in a leaf.
pub const LEAF_SIZE: usize = 12;

/// One neighbour of a query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Neighbor {
    /// Index of the point in the tree's input order.
    pub index: usize,
    /// Squared Euclidean distance to the query.
    pub dist2: f64,
}

impl Neighbor {
    /// `(dist2, index)` ordering: nearer first, then lower index.
    fn before(&self, other: &Neighbor) -> bool {
        self.dist2 < other.dist2 || (self.dist2 == other.dist2 && self.index < other.index)
    }
}

#[derive(Debug, Clone, Copy)]
struct Node {
    /// The node's points are `order[start..end]`.
    start: usize,
    end: usize,
    /// Splitting axis; `LEAF` for a leaf.
    axis: usize,
    split: f64,
    left: usize,
    right: usize,
}

const LEAF: usize = 3;

/// A k-d tree over 3-D points (see the module documentation). Points must be finite; the
/// operators check that before building one.
#[derive(Debug, Clone)]
pub struct KdTree {
    points: Vec<[f64; 3]>,
    order: Vec<usize>,
    nodes: Vec<Node>,
}

impl KdTree {
    /// Builds the tree over `points` (O(n log n)).
    pub fn new(points: Vec<[f64; 3]>) -> KdTree {
        let mut tree = KdTree {
            order: (0..points.len()).collect(),
            points,
            nodes: Vec::new(),
        };
        if !tree.points.is_empty() {
            tree.build(0, tree.points.len());
        }
        tree
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether the tree holds no point.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points, in input order.
    pub fn points(&self) -> &[[f64; 3]] {
        &self.points
    }

    fn build(&mut self, start: usize, end: usize) -> usize {
        let id = self.nodes.len();
        self.nodes.push(Node {
            start,
            end,
            axis: LEAF,
            split: 0.0,
            left: 0,
            right: 0,
        });
        if end - start <= LEAF_SIZE {
            return id;
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for &i in &self.order[start..end] {
            for a in 0..3 {
                lo[a] = lo[a].min(self.points[i][a]);
                hi[a] = hi[a].max(self.points[i][a]);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
            .unwrap_or(0);
        // All points coincide (or are not finite): one leaf, whatever its size.
        let extent = hi[axis] - lo[axis];
        if extent.is_nan() || extent <= 0.0 {
            return id;
        }
        let mid = start + (end - start) / 2;
        let points = &self.points;
        self.order[start..end].select_nth_unstable_by(mid - start, |&i, &j| {
            points[i][axis].total_cmp(&points[j][axis]).then(i.cmp(&j))
        });
        let split = self.points[self.order[mid]][axis];
        let left = self.build(start, mid);
        let right = self.build(mid, end);
        self.nodes[id] = Node {
            start,
            end,
            axis,
            split,
            left,
            right,
        };
        id
    }

    /// The `k` nearest points to `query` no farther than `sqrt(max_dist2)` (pass
    /// `f64::INFINITY` for no bound), written to `out` ordered by `(dist2, index)`.
    pub fn knn(&self, query: &[f64; 3], k: usize, max_dist2: f64, out: &mut Vec<Neighbor>) {
        out.clear();
        if k == 0 || self.nodes.is_empty() {
            return;
        }
        self.knn_node(0, query, k, max_dist2, out);
    }

    fn knn_node(&self, id: usize, q: &[f64; 3], k: usize, max_dist2: f64, out: &mut Vec<Neighbor>) {
        let node = self.nodes[id];
        if node.axis == LEAF {
            for &i in &self.order[node.start..node.end] {
                let n = Neighbor {
                    index: i,
                    dist2: dist2(q, &self.points[i]),
                };
                if n.dist2 > max_dist2 {
                    continue;
                }
                if out.len() == k {
                    match out.last() {
                        Some(worst) if n.before(worst) => {
                            out.pop();
                        }
                        _ => continue,
                    }
                }
                let at = out.partition_point(|m| m.before(&n));
                out.insert(at, n);
            }
            return;
        }
        let diff = q[node.axis] - node.split;
        let (near, far) = if diff < 0.0 {
            (node.left, node.right)
        } else {
            (node.right, node.left)
        };
        self.knn_node(near, q, k, max_dist2, out);
        let bound = if out.len() == k {
            out.last().map_or(max_dist2, |w| w.dist2)
        } else {
            max_dist2
        };
        if diff * diff <= bound {
            self.knn_node(far, q, k, max_dist2, out);
        }
    }

    /// The nearest point to `query` within `sqrt(max_dist2)`, lowest index on a tie.
    pub fn nearest(&self, query: &[f64; 3], max_dist2: f64) -> Option<Neighbor> {
        let mut out = Vec::with_capacity(1);
        self.knn(query, 1, max_dist2, &mut out);
        out.first().copied()
    }

    /// Every point within `sqrt(radius2)` of `query` (inclusive), written to `out` ordered by
    /// `(dist2, index)`.
    pub fn within(&self, query: &[f64; 3], radius2: f64, out: &mut Vec<Neighbor>) {
        out.clear();
        if !self.nodes.is_empty() {
            self.within_node(0, query, radius2, out);
        }
        out.sort_unstable_by(|a, b| a.dist2.total_cmp(&b.dist2).then(a.index.cmp(&b.index)));
    }

    fn within_node(&self, id: usize, q: &[f64; 3], radius2: f64, out: &mut Vec<Neighbor>) {
        let node = self.nodes[id];
        if node.axis == LEAF {
            for &i in &self.order[node.start..node.end] {
                let d = dist2(q, &self.points[i]);
                if d <= radius2 {
                    out.push(Neighbor { index: i, dist2: d });
                }
            }
            return;
        }
        let diff = q[node.axis] - node.split;
        let (near, far) = if diff < 0.0 {
            (node.left, node.right)
        } else {
            (node.right, node.left)
        };
        self.within_node(near, q, radius2, out);
        if diff * diff <= radius2 {
            self.within_node(far, q, radius2, out);
        }
    }
}

/// Squared Euclidean distance.
pub fn dist2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let (x, y, z) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    x * x + y * y + z * z
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use proptest::prelude::*;

    fn brute_knn(points: &[[f64; 3]], q: &[f64; 3], k: usize, max_dist2: f64) -> Vec<Neighbor> {
        let mut all: Vec<Neighbor> = points
            .iter()
            .enumerate()
            .map(|(index, p)| Neighbor {
                index,
                dist2: dist2(q, p),
            })
            .filter(|n| n.dist2 <= max_dist2)
            .collect();
        all.sort_by(|a, b| a.dist2.total_cmp(&b.dist2).then(a.index.cmp(&b.index)));
        all.truncate(k);
        all
    }

    /// Points on a coarse integer grid, many duplicated, so ties are everywhere.
    fn grid_points(n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| [0, 1, 2].map(|_| rng.below(6) as f64))
            .collect()
    }

    #[test]
    fn knn_and_radius_match_brute_force_with_ties() {
        for (n, seed) in [(1, 1), (13, 2), (500, 3), (2000, 4)] {
            let points = grid_points(n, seed);
            let tree = KdTree::new(points.clone());
            let mut rng = SplitMix64::new(seed + 100);
            let mut out = Vec::new();
            for _ in 0..50 {
                let q = [0, 1, 2].map(|_| rng.below(7) as f64 - 0.5 * rng.below(2) as f64);
                for k in [1, 2, 7, 30] {
                    for max in [f64::INFINITY, 2.0] {
                        tree.knn(&q, k, max, &mut out);
                        assert_eq!(out, brute_knn(&points, &q, k, max), "n {n} k {k}");
                    }
                }
                tree.within(&q, 2.25, &mut out);
                assert_eq!(out, brute_knn(&points, &q, usize::MAX, 2.25));
            }
        }
    }

    #[test]
    fn empty_and_coincident_trees() {
        let empty = KdTree::new(Vec::new());
        assert!(empty.is_empty());
        assert_eq!(empty.nearest(&[0.0; 3], f64::INFINITY), None);
        let mut out = vec![Neighbor {
            index: 9,
            dist2: 0.0,
        }];
        empty.within(&[0.0; 3], 1.0, &mut out);
        assert!(out.is_empty());
        // 100 copies of one point: one leaf; ties resolved by index.
        let same = KdTree::new(vec![[1e6, -1e6, 3.0]; 100]);
        same.knn(&[1e6, -1e6, 3.0], 3, f64::INFINITY, &mut out);
        assert_eq!(out.iter().map(|n| n.index).collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(same.nearest(&[0.0; 3], 1.0), None);
    }

    proptest! {
        #[test]
        fn knn_is_exact_for_any_cloud(
            pts in proptest::collection::vec(proptest::array::uniform3(-1e3f64..1e3), 0..200),
            q in proptest::array::uniform3(-1.2e3f64..1.2e3),
            k in 1usize..20,
            offset in prop_oneof![Just(0.0), Just(1e6)],
        ) {
            let pts: Vec<[f64; 3]> = pts.iter().map(|p| p.map(|v| v + offset)).collect();
            let q = q.map(|v| v + offset);
            let tree = KdTree::new(pts.clone());
            let mut out = Vec::new();
            tree.knn(&q, k, f64::INFINITY, &mut out);
            prop_assert_eq!(out, brute_knn(&pts, &q, k, f64::INFINITY));
        }
    }
}
