//! `match.approximate`: approximate two-nearest-neighbour matching for large descriptor sets.
//!
//! - Float descriptors: a randomized k-d forest (Silpa-Anan & Hartley 2008, as in FLANN's
//!   `KDTreeIndex`). Each tree splits at the mean of a dimension drawn at random among the
//!   [`TOP_DIMS`] of highest variance (estimated on up to [`VARIANCE_SAMPLE`] points), down to
//!   leaves of `leaf_size` points.
//! - Binary descriptors: hierarchical clustering trees (Muja & Lowe 2012, FLANN's
//!   `HierarchicalClusteringIndex`): each node picks `branching` random member points as
//!   centres and gives every point to its nearest centre (Hamming), down to leaves.
//!
//! Search is best-bin-first over all trees at once: one priority queue of unexplored branches
//! (k-d: ordered by a lower bound of the distance, the squared gap to the splitting plane;
//! clustering: by the distance to the branch's centre), descending to leaves and measuring their
//! points exactly until `checks` distinct points were measured. Branches whose lower bound
//! exceeds the current second-nearest distance are skipped (k-d: squared gap; clustering: the
//! triangle inequality `d(q, c) − radius`), and these bounds are exact, so with an unlimited
//! budget (`checks: 0`) the result is the exact search's, ties included.
//!
//! Trees are built from a seed (each tree from `splitmix64(seed + tree)`), queries are
//! searched in parallel in fixed chunks, each independently: identical results for any thread
//! count.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Match, Value};
use rayon::prelude::*;

use super::{DescriptorRows, Metric, Norm, Top2, descriptors, hamming, prepare, ratio_accepts};
use crate::capture::pattern::splitmix64;

/// Points whose variance picks a k-d split dimension.
pub const VARIANCE_SAMPLE: usize = 100;

/// The split dimension is drawn among this many of highest variance.
pub const TOP_DIMS: usize = 5;

/// Queries per parallel task.
const QUERY_CHUNK: usize = 32;

/// Largest number of trees.
pub const MAX_TREES: u32 = 64;

params! {
    /// Parameters of `match.approximate`.
    pub struct ApproximateParams {
        /// Number of randomized trees searched together. More trees: better recall per check,
        /// more memory and build time. Default 4.
        trees: u32 = 4 => [min = 1, max = 64],
        /// Largest number of descriptors measured per query (the recall / speed knob); 0
        /// searches until the result is exact. Default 64.
        checks: u32 = 64,
        /// Lowe's ratio test: keep the nearest if `d1 < ratio · d2`; 1 disables. Default 0.8.
        ratio: f64 = 0.8 => [above = 0.0, max = 1.0],
        /// Seed of the tree construction. Default 0.
        seed: u64 = 0,
        /// Distance: "auto" (L2 for float, Hamming for binary), "l2", "l2_squared" or
        /// "hamming". Default "auto".
        norm: Norm = Norm::Auto,
        /// Largest number of points in a leaf (binary trees: at least `branching`). Default 4.
        leaf_size: u32 = 4 => [min = 1, max = 10000],
        /// Children per node of the binary clustering trees. Default 16.
        branching: u32 = 16 => [min = 2, max = 1024],
    }
}

/// Options of [`approximate_match`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnnOptions {
    /// Trees (≥ 1).
    pub trees: usize,
    /// Distinct points measured per query; 0 = unlimited (exact).
    pub checks: usize,
    /// Lowe's ratio (≥ 1 disables).
    pub ratio: f64,
    /// Construction seed.
    pub seed: u64,
    /// Points per leaf (≥ 1).
    pub leaf_size: usize,
    /// Clustering branching factor (≥ 2).
    pub branching: usize,
}

impl Default for AnnOptions {
    fn default() -> Self {
        AnnOptions {
            trees: 4,
            checks: 64,
            ratio: 0.8,
            seed: 0,
            leaf_size: 4,
            branching: 16,
        }
    }
}

/// Approximate matcher (`match.approximate`). See [`approximate_match`].
#[derive(Debug, Clone, PartialEq)]
pub struct Approximate {
    options: AnnOptions,
    norm: Norm,
}

impl Op for Approximate {
    type Params = ApproximateParams;
    const ID: &'static str = "match.approximate";
    const SUMMARY: &'static str =
        "Approximate nearest-neighbour descriptor matching (k-d forest / clustering trees).";
    const DOC: &'static str = r#"
Finds approximate two nearest train descriptors of every query and keeps the nearest if it
passes Lowe's ratio test (`d1 < ratio · d2`), like `match.brute_force` but sublinear per query
for large sets (≥ ~5000 descriptors).

Method (FLANN's): float descriptors go into `trees` randomized k-d trees (split at the mean of a
dimension drawn among the 5 of highest variance, estimated on 100 points); binary ones into
`trees` hierarchical clustering trees (`branching` random centres per node, Hamming
assignment). Search is best-bin-first over all trees with one priority queue, measuring exact
distances (the same as `match.brute_force`) until `checks` distinct descriptors were measured.
Branches that cannot hold anything nearer than the current second neighbour are skipped with
exact bounds, so `checks: 0` (unlimited) returns exactly the brute-force result. Recall grows
with `checks` and `trees`; on 10k × 10k clustered SIFT-like data, checks 128 with 4 trees finds
the true nearest neighbour for most queries.

Deterministic given `seed` and independent of the thread count. Distances and `norm` as in
`match.brute_force` (L2 true distance for float, Hamming bits for binary). Matches are sorted
by query index; empty sets give no matches; mismatched kinds or widths are an error.
Differences from OpenCV's FlannBasedMatcher: the same algorithms, but seeded (FLANN uses a
global RNG), ties go to the lower train index, and binary data use clustering trees rather
than LSH.

References: C. Silpa-Anan, R. Hartley, "Optimised KD-trees for fast image descriptor matching",
CVPR 2008; M. Muja, D. G. Lowe, "Fast matching of binary features", CRV 2012; FLANN;
J. S. Beis, D. G. Lowe, "Shape indexing using approximate nearest-neighbour search", CVPR 1997
(best-bin-first).

Example:
    "ann": (op: "match.approximate", inputs: { "query": "sift1.descriptors",
            "train": "sift2.descriptors" }, params: (trees: 4, checks: 128, ratio: 0.8)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "query",
                PortType::Descriptors,
                "Descriptors of the first view.",
            ),
            PortSpec::new(
                "train",
                PortType::Descriptors,
                "Descriptors of the second view (indexed), same kind and width.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "matches",
            PortType::Matches,
            "Accepted matches, sorted by query index.",
        )]
    }

    fn new(params: ApproximateParams) -> Result<Self, String> {
        let ApproximateParams {
            trees,
            checks,
            ratio,
            seed,
            norm,
            leaf_size,
            branching,
        } = params;
        if !(ratio > 0.0 && ratio <= 1.0) {
            return Err(format!("`ratio` must be in (0, 1], got {ratio}"));
        }
        if !(1..=MAX_TREES).contains(&trees) {
            return Err(format!("`trees` must be 1..={MAX_TREES}, got {trees}"));
        }
        if leaf_size == 0 || branching < 2 {
            return Err("`leaf_size` must be ≥ 1 and `branching` ≥ 2".into());
        }
        Ok(Approximate {
            options: AnnOptions {
                trees: trees as usize,
                checks: checks as usize,
                ratio,
                seed,
                leaf_size: leaf_size as usize,
                branching: branching as usize,
            },
            norm,
        })
    }
}

impl Operator for Approximate {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let query = descriptors(inputs, "query")?;
        let train = descriptors(inputs, "train")?;
        let (metric, q, t) = prepare(query, train, self.norm)?;
        let matches = approximate_match(&q, &t, metric, &self.options);
        Ok(Outputs::new().with("matches", Value::Matches(matches.into())))
    }
}

/// Approximate matches of `query` against `train` (same kind and width, from
/// [`prepare`](super::prepare)): two nearest neighbours by best-bin-first search of a k-d forest
/// (float) or clustering trees (binary), then the ratio test. Sorted by query index.
pub fn approximate_match(
    query: &DescriptorRows<'_>,
    train: &DescriptorRows<'_>,
    metric: Metric,
    options: &AnnOptions,
) -> Vec<Match> {
    if query.is_empty() || train.is_empty() {
        return Vec::new();
    }
    let tops = approximate_knn2(query, train, options);
    tops.iter()
        .enumerate()
        .filter(|(_, top)| top.found() && ratio_accepts(top, metric, options.ratio))
        .map(|(q, top)| Match {
            query: q as u32,
            train: top.i1,
            distance: metric.report(top.d1),
        })
        .collect()
}

/// A tree node: leaf over `order[start..end]` or an inner node.
#[derive(Debug, Clone)]
enum Node {
    Leaf {
        start: u32,
        end: u32,
    },
    /// k-d split: points with `x[dim] ≤ value` on the left, `≥ value` on the right.
    Split {
        dim: u32,
        value: f32,
        left: u32,
        right: u32,
    },
    /// Clustering node: children `first..first + count` of `clusters`.
    Clusters {
        first: u32,
        count: u32,
    },
}

/// A child of a clustering node: centre row, radius (largest member distance), node id.
#[derive(Debug, Clone, Copy)]
struct Cluster {
    centre: u32,
    radius: f64,
    node: u32,
}

/// One tree: nodes (root first) and the leaf point order.
#[derive(Debug, Clone, Default)]
struct Tree {
    nodes: Vec<Node>,
    clusters: Vec<Cluster>,
    order: Vec<u32>,
}

/// A deterministic random stream (SplitMix64 over a counter).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(1);
        splitmix64(self.0)
    }

    /// Uniform in `0..n` (n ≥ 1).
    fn below(&mut self, n: usize) -> usize {
        ((u128::from(self.next()) * n as u128) >> 64) as usize
    }
}

/// Two approximate nearest neighbours of every query.
fn approximate_knn2(
    query: &DescriptorRows<'_>,
    train: &DescriptorRows<'_>,
    options: &AnnOptions,
) -> Vec<Top2> {
    let trees: Vec<Tree> = (0..options.trees.max(1))
        .into_par_iter()
        .map(|k| {
            let mut rng = Rng(splitmix64(options.seed.wrapping_add(k as u64)));
            match train {
                DescriptorRows::Float { dim, data } => {
                    build_kd(data, *dim, options.leaf_size.max(1), &mut rng)
                }
                DescriptorRows::Binary { words, data } => build_clusters(
                    data,
                    *words,
                    options.leaf_size.max(1),
                    options.branching.max(2),
                    &mut rng,
                ),
            }
        })
        .collect();
    let nt = train.len();
    let budget = if options.checks == 0 {
        usize::MAX
    } else {
        options.checks
    };
    let mut out = vec![Top2::default(); query.len()];
    out.par_chunks_mut(QUERY_CHUNK)
        .enumerate()
        .for_each(|(c, tops)| {
            let mut stamp = vec![u32::MAX; nt];
            let mut heap = BinaryHeap::new();
            for (i, top) in tops.iter_mut().enumerate() {
                let q = c * QUERY_CHUNK + i;
                *top = search(query, q, train, &trees, budget, &mut stamp, &mut heap);
            }
        });
    out
}

/// A queued branch: (order key bits, tree, node, lower bound bits); smallest first.
type Entry = Reverse<(u64, u32, u32, u64)>;

/// Best-bin-first search of query row `q`.
fn search(
    query: &DescriptorRows<'_>,
    q: usize,
    train: &DescriptorRows<'_>,
    trees: &[Tree],
    budget: usize,
    stamp: &mut [u32],
    heap: &mut BinaryHeap<Entry>,
) -> Top2 {
    heap.clear();
    let mut top = Top2::default();
    let mut checks = 0usize;
    let tag = q as u32;
    for k in 0..trees.len() {
        heap.push(Reverse((0, k as u32, 0, 0)));
    }
    while let Some(Reverse((_, k, node, bound))) = heap.pop() {
        if checks >= budget {
            break;
        }
        let tree = &trees[k as usize];
        let mut node = node as usize;
        let mut bound = f64::from_bits(bound);
        // Descend to a leaf, queueing the other branches.
        loop {
            if bound > top.d2 {
                break;
            }
            match &tree.nodes[node] {
                Node::Leaf { start, end } => {
                    for &p in &tree.order[*start as usize..*end as usize] {
                        if stamp[p as usize] != tag {
                            stamp[p as usize] = tag;
                            checks += 1;
                            top.offer(query.distance(q, train, p as usize), p);
                        }
                    }
                    break;
                }
                Node::Split {
                    dim,
                    value,
                    left,
                    right,
                } => {
                    let DescriptorRows::Float { dim: d, data } = query else {
                        break;
                    };
                    let x = data[q * d + *dim as usize];
                    let gap = f64::from(x) - f64::from(*value);
                    let (near, far) = if gap <= 0.0 {
                        (*left, *right)
                    } else {
                        (*right, *left)
                    };
                    let far_bound = bound.max(gap * gap);
                    if far_bound <= top.d2 {
                        heap.push(Reverse((far_bound.to_bits(), k, far, far_bound.to_bits())));
                    }
                    node = near as usize;
                }
                Node::Clusters { first, count } => {
                    let DescriptorRows::Binary { words, data } = query else {
                        break;
                    };
                    let qrow = &data[q * words..(q + 1) * words];
                    let DescriptorRows::Binary { data: tdata, .. } = train else {
                        break;
                    };
                    let mut best: Option<(f64, u32, f64)> = None;
                    for cl in &tree.clusters[*first as usize..(*first + *count) as usize] {
                        let c = cl.centre as usize;
                        let d = f64::from(hamming(qrow, &tdata[c * words..(c + 1) * words]));
                        let lb = bound.max(d - cl.radius);
                        if lb > top.d2 {
                            continue;
                        }
                        match best {
                            Some((bd, _, _)) if bd <= d => {
                                heap.push(Reverse((d.to_bits(), k, cl.node, lb.to_bits())));
                            }
                            _ => {
                                if let Some((bd, bn, blb)) = best {
                                    heap.push(Reverse((bd.to_bits(), k, bn, blb.to_bits())));
                                }
                                best = Some((d, cl.node, lb));
                            }
                        }
                    }
                    let Some((_, n, lb)) = best else { break };
                    node = n as usize;
                    bound = lb;
                }
            }
        }
    }
    top
}

/// A randomized k-d tree over the float rows.
fn build_kd(data: &[f32], dim: usize, leaf_size: usize, rng: &mut Rng) -> Tree {
    let n = data.len() / dim;
    let mut tree = Tree {
        order: (0..n as u32).collect(),
        ..Tree::default()
    };
    // Work list of (node id, start, end); nodes are created before their children.
    tree.nodes.push(Node::Leaf {
        start: 0,
        end: n as u32,
    });
    let mut stack = vec![(0usize, 0usize, n)];
    let mut mean = vec![0.0f64; dim];
    let mut var = vec![0.0f64; dim];
    while let Some((id, start, end)) = stack.pop() {
        if end - start <= leaf_size {
            continue;
        }
        let idx = &mut tree.order[start..end];
        let sample = &idx[..idx.len().min(VARIANCE_SAMPLE)];
        mean.fill(0.0);
        var.fill(0.0);
        for &p in sample {
            for (m, &x) in mean
                .iter_mut()
                .zip(&data[p as usize * dim..(p as usize + 1) * dim])
            {
                *m += f64::from(x);
            }
        }
        let inv = 1.0 / sample.len() as f64;
        mean.iter_mut().for_each(|m| *m *= inv);
        for &p in sample {
            for ((v, m), &x) in var
                .iter_mut()
                .zip(&mean)
                .zip(&data[p as usize * dim..(p as usize + 1) * dim])
            {
                let d = f64::from(x) - m;
                *v += d * d;
            }
        }
        // Dimensions of highest variance (ties: lower dimension), nonzero only.
        let mut dims: Vec<usize> = (0..dim).filter(|&d| var[d] > 0.0).collect();
        dims.sort_by(|&a, &b| var[b].total_cmp(&var[a]).then(a.cmp(&b)));
        dims.truncate(TOP_DIMS);
        if dims.is_empty() {
            // The sample is constant: try the whole node before giving up.
            let first = idx[0] as usize;
            let row = &data[first * dim..(first + 1) * dim];
            let varying = (0..dim).find(|&d| {
                idx.iter()
                    .any(|&p| data[p as usize * dim + d].to_bits() != row[d].to_bits())
            });
            match varying {
                Some(d) => {
                    dims.push(d);
                    mean[d] = idx
                        .iter()
                        .map(|&p| f64::from(data[p as usize * dim + d]))
                        .sum::<f64>()
                        / idx.len() as f64;
                }
                None => continue, // identical points: one leaf
            }
        }
        let d = dims[rng.below(dims.len())];
        let value = mean[d] as f32;
        // Sort by the key (then index), cut at the mean, moving the cut through a block of
        // keys equal to the mean towards the middle; if rounding put the mean outside the
        // keys, cut in the middle at that key. Left keys ≤ split ≤ right keys either way.
        let key = |p: u32| data[p as usize * dim + d];
        idx.sort_by(|&a, &b| key(a).total_cmp(&key(b)).then(a.cmp(&b)));
        let below = idx.partition_point(|&p| key(p) < value);
        let upto = idx.partition_point(|&p| key(p) <= value);
        let half = idx.len() / 2;
        let (cut, split) = match half.clamp(below, upto) {
            0 => (half, key(idx[half])),
            c if c == idx.len() => (half, key(idx[half])),
            c => (c, value),
        };
        let left = tree.nodes.len();
        tree.nodes.push(Node::Leaf {
            start: start as u32,
            end: (start + cut) as u32,
        });
        tree.nodes.push(Node::Leaf {
            start: (start + cut) as u32,
            end: end as u32,
        });
        tree.nodes[id] = Node::Split {
            dim: d as u32,
            value: split,
            left: left as u32,
            right: left as u32 + 1,
        };
        stack.push((left + 1, start + cut, end));
        stack.push((left, start, start + cut));
    }
    tree
}

/// A hierarchical clustering tree over the binary word rows.
fn build_clusters(
    data: &[u64],
    words: usize,
    leaf_size: usize,
    branching: usize,
    rng: &mut Rng,
) -> Tree {
    let n = data.len() / words;
    let row = |p: u32| &data[p as usize * words..(p as usize + 1) * words];
    let mut tree = Tree {
        order: (0..n as u32).collect(),
        ..Tree::default()
    };
    tree.nodes.push(Node::Leaf {
        start: 0,
        end: n as u32,
    });
    let mut stack = vec![(0usize, 0usize, n)];
    while let Some((id, start, end)) = stack.pop() {
        let count = end - start;
        if count <= leaf_size.max(branching) {
            continue;
        }
        let idx = &mut tree.order[start..end];
        // Random distinct centres: a partial Fisher–Yates shuffle of the node's points.
        let mut pick: Vec<u32> = idx.to_vec();
        let mut centres: Vec<u32> = Vec::with_capacity(branching);
        for i in 0..pick.len() {
            if centres.len() == branching {
                break;
            }
            let j = i + rng.below(pick.len() - i);
            pick.swap(i, j);
            let c = pick[i];
            if centres.iter().all(|&o| row(o) != row(c)) {
                centres.push(c);
            }
        }
        if centres.len() < 2 {
            continue; // all points identical
        }
        // Assign to the nearest centre (ties: first centre), then group.
        let mut label = vec![0u32; count];
        let mut radius = vec![0u32; centres.len()];
        for (l, &p) in label.iter_mut().zip(idx.iter()) {
            let (mut best, mut bd) = (0usize, u32::MAX);
            for (ci, &c) in centres.iter().enumerate() {
                let d = hamming(row(p), row(c));
                if d < bd {
                    bd = d;
                    best = ci;
                }
            }
            *l = best as u32;
            radius[best] = radius[best].max(bd);
        }
        let mut pairs: Vec<(u32, u32)> = label.iter().copied().zip(idx.iter().copied()).collect();
        pairs.sort_unstable();
        for (slot, &(_, p)) in idx.iter_mut().zip(&pairs) {
            *slot = p;
        }
        let first = tree.clusters.len();
        let mut offset = start;
        for (ci, &c) in centres.iter().enumerate() {
            let size = label.iter().filter(|&&l| l as usize == ci).count();
            let node = tree.nodes.len();
            tree.nodes.push(Node::Leaf {
                start: offset as u32,
                end: (offset + size) as u32,
            });
            tree.clusters.push(Cluster {
                centre: c,
                radius: f64::from(radius[ci]),
                node: node as u32,
            });
            stack.push((node, offset, offset + size));
            offset += size;
        }
        tree.nodes[id] = Node::Clusters {
            first: first as u32,
            count: centres.len() as u32,
        };
    }
    tree
}

#[cfg(test)]
mod tests {
    use super::super::brute_force::{MatchOptions, brute_force_match};
    use super::super::test_support::{random_binary, random_float, stream};
    use super::*;
    use ocellus_engine::value::Descriptors;
    use proptest::prelude::*;

    /// Clustered SIFT-like rows (integer values), `clusters` centres plus noise.
    fn clustered(n: usize, dim: usize, clusters: usize, seed: u64) -> Descriptors {
        let mut next = stream(seed);
        let centres: Vec<f32> = (0..clusters * dim).map(|_| (next() % 120) as f32).collect();
        let mut data = Vec::with_capacity(n * dim);
        for _ in 0..n {
            let c = (next() as usize) % clusters;
            for d in 0..dim {
                let noise = (next() % 41) as f32 - 20.0;
                data.push((centres[c * dim + d] + noise).max(0.0));
            }
        }
        Descriptors::Float { dim, data }
    }

    fn exact_and_ann(
        q: &Descriptors,
        t: &Descriptors,
        options: &AnnOptions,
    ) -> (Vec<Match>, Vec<Match>) {
        let (metric, qr, tr) = prepare(q, t, Norm::Auto).unwrap();
        let bf = MatchOptions {
            ratio: options.ratio,
            ..MatchOptions::default()
        };
        (
            brute_force_match(&qr, &tr, metric, &bf, None),
            approximate_match(&qr, &tr, metric, options),
        )
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(16))]

        #[test]
        fn unlimited_checks_equal_brute_force(
            nq in 0usize..80, nt in 0usize..400, dim in 1usize..20, levels in 2u64..8,
            trees in 1usize..4, leaf in 1usize..12, seed in 0u64..100,
        ) {
            let q = random_float(nq, dim, levels, seed);
            let t = random_float(nt, dim, levels, seed + 3);
            let options = AnnOptions { trees, checks: 0, ratio: 1.0, seed, leaf_size: leaf,
                ..AnnOptions::default() };
            let (a, b) = exact_and_ann(&q, &t, &options);
            prop_assert_eq!(a, b);
        }

        #[test]
        fn unlimited_checks_equal_brute_force_binary(
            nq in 0usize..80, nt in 0usize..500, bytes in 1usize..12, trees in 1usize..4,
            branching in 2usize..9, leaf in 1usize..20, seed in 0u64..100,
        ) {
            let q = random_binary(nq, bytes, seed);
            let t = random_binary(nt, bytes, seed + 3);
            let options = AnnOptions { trees, checks: 0, ratio: 0.9, seed, leaf_size: leaf,
                branching };
            let (a, b) = exact_and_ann(&q, &t, &options);
            prop_assert_eq!(a, b);
        }
    }

    /// Fraction of queries whose approximate nearest equals the exact one.
    fn recall(exact: &[Match], ann: &[Match]) -> f64 {
        let hits = exact
            .iter()
            .zip(ann)
            .filter(|(a, b)| a.train == b.train)
            .count();
        hits as f64 / exact.len() as f64
    }

    /// Queries that are noisy copies (±`noise`) of train rows `0..n`, as in real matching.
    fn noisy_copies(t: &Descriptors, n: usize, noise: u64, seed: u64) -> Descriptors {
        let Descriptors::Float { dim, data } = t else {
            unreachable!()
        };
        let mut next = stream(seed);
        Descriptors::Float {
            dim: *dim,
            data: data[..n * dim]
                .iter()
                .map(|&v| v + (next() % (2 * noise + 1)) as f32 - noise as f32)
                .collect(),
        }
    }

    #[test]
    fn float_recall_grows_with_checks() {
        let t = clustered(3000, 32, 40, 2);
        let q = noisy_copies(&t, 600, 6, 1);
        let mut last = 0.0;
        for checks in [16, 64, 256, 1024] {
            let options = AnnOptions {
                checks,
                ratio: 1.0,
                ..AnnOptions::default()
            };
            let (a, b) = exact_and_ann(&q, &t, &options);
            assert_eq!(b.len(), 600);
            let r = recall(&a, &b);
            assert!(r >= last - 0.02, "recall {r} after {last}");
            last = r;
        }
        assert!(last >= 0.97, "recall at 1024 checks: {last}");
    }

    #[test]
    fn binary_recall_with_near_duplicates() {
        // Train rows are queries with 0–3 flipped bits among random others.
        let t = random_binary(4000, 32, 5);
        let Descriptors::Binary { data, .. } = &t else {
            unreachable!()
        };
        let mut next = stream(9);
        let mut q = data[..500 * 32].to_vec();
        for row in q.chunks_exact_mut(32) {
            for _ in 0..(next() % 4) {
                let bit = next() as usize % 256;
                row[bit / 8] ^= 1 << (bit % 8);
            }
        }
        let q = Descriptors::Binary { bytes: 32, data: q };
        let options = AnnOptions {
            checks: 400,
            ..AnnOptions::default()
        };
        let (a, b) = exact_and_ann(&q, &t, &options);
        assert!(recall(&a, &b) >= 0.9, "{}", recall(&a, &b));
    }

    #[test]
    fn deterministic_and_seeded() {
        let q = clustered(300, 16, 10, 3);
        let t = clustered(900, 16, 10, 4);
        let (metric, qr, tr) = prepare(&q, &t, Norm::Auto).unwrap();
        let options = AnnOptions {
            checks: 24,
            ..AnnOptions::default()
        };
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| approximate_match(&qr, &tr, metric, &options));
        let many = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap()
            .install(|| approximate_match(&qr, &tr, metric, &options));
        assert_eq!(one, many);
    }

    #[test]
    fn constant_and_empty_sets() {
        let q = Descriptors::Float {
            dim: 4,
            data: vec![1.0; 40],
        };
        let (metric, qr, tr) = prepare(&q, &q, Norm::Auto).unwrap();
        let options = AnnOptions {
            ratio: 1.0,
            checks: 3,
            ..AnnOptions::default()
        };
        let m = approximate_match(&qr, &tr, metric, &options);
        assert_eq!(m.len(), 10);
        assert!(m.iter().all(|m| m.distance == 0.0 && m.train == 0));
        let e = Descriptors::Binary {
            bytes: 32,
            data: vec![],
        };
        let (metric, qr, tr) = prepare(&e, &e, Norm::Auto).unwrap();
        assert!(approximate_match(&qr, &tr, metric, &options).is_empty());
        assert!(
            Approximate::new(ApproximateParams {
                trees: 0,
                ..ApproximateParams::default()
            })
            .is_err()
        );
    }
}
