//! Point-cloud filters: `mesh.voxel_downsample`, `mesh.remove_outliers` and
//! `mesh.estimate_normals`, plus the conversions every `mesh` operator shares.
//!
//! - [`voxel_downsample`]: one point per occupied voxel of a grid anchored at the cloud's minimum
//!   corner, the centroid of the voxel's points (colors averaged, normals averaged and
//!   renormalized), output ordered by voxel key `(x, y, z)`.
//! - [`statistical_inliers`]: statistical outlier removal as PCL's `StatisticalOutlierRemoval`
//!   (Rusu et al., "Towards 3D point cloud based object maps for household environments", RAS
//!   2008): the mean distance `dᵢ` of each point to its `k` nearest neighbours; a point is kept
//!   when `dᵢ ≤ μ + std_ratio · σ`, `μ`, `σ` the mean and sample standard deviation of all `dᵢ`.
//!   [`radius_inliers`]: a point is kept when at least `min_neighbors` others lie within `radius`.
//! - [`estimate_normals`]: the normal of each point is the eigenvector of the smallest eigenvalue
//!   of the covariance of its `k` nearest neighbours (itself included), computed on coordinates
//!   relative to the point so that clouds far from the origin keep full precision (Hoppe et al.,
//!   "Surface reconstruction from unorganized points", SIGGRAPH 1992, §3.2).
//!   [`orient_towards`] flips normals to face a viewpoint; [`orient_consistent`] propagates one
//!   orientation over the minimum spanning tree of the symmetric k-NN graph weighted by
//!   `1 − |nᵢ·nⱼ|` (Hoppe et al. §3.3), rooted at each component's highest point (largest z)
//!   with its normal turned to +z.
//!
//! Every per-point computation runs in parallel but writes only its own point, and every
//! reduction runs in index order, so results do not depend on the thread count.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::sync::Arc;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, PointCloud, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::kdtree::{KdTree, Neighbor};

/// Points handed to one parallel task; per-point work is independent, so this only sets
/// granularity, never results.
pub const CHUNK: usize = 4096;

/// Largest voxel index per axis: keeps voxel keys exact in i64 and their f64 origin exact.
const MAX_VOXEL_INDEX: f64 = (1u64 << 40) as f64;

/// Why a point-cloud computation failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PointCloudError {
    /// The cloud has fewer points than the computation needs.
    #[error("the point cloud has {got} points, but at least {needed} are needed")]
    TooFewPoints {
        /// Points needed.
        needed: usize,
        /// Points given.
        got: usize,
    },
    /// A position holds NaN or an infinity.
    #[error("point {index} is not finite")]
    NonFinite {
        /// Index of the first bad point.
        index: usize,
    },
    /// An attribute array's length differs from the number of positions.
    #[error("the cloud has {positions} positions but {len} {attribute}")]
    AttributeLength {
        /// `colors` or `normals`.
        attribute: &'static str,
        /// Its length.
        len: usize,
        /// Number of positions.
        positions: usize,
    },
    /// The grid would need more voxels per axis than keys can index.
    #[error(
        "voxel_size {voxel_size} is too small for the cloud's extent {extent} (more than 2^40 voxels per axis)"
    )]
    VoxelTooSmall {
        /// The voxel size.
        voxel_size: f64,
        /// The largest extent of the cloud.
        extent: f64,
    },
}

impl PointCloudError {
    /// The operator error for input `port`.
    pub fn at(self, port: &str) -> OpError {
        OpError::input(port, self.to_string())
    }
}

/// Checks attribute lengths and finiteness, and returns the positions in f64.
pub fn positions_f64(cloud: &PointCloud) -> Result<Vec<[f64; 3]>, PointCloudError> {
    let n = cloud.positions.len();
    if let Some(c) = &cloud.colors
        && c.len() != n
    {
        return Err(PointCloudError::AttributeLength {
            attribute: "colors",
            len: c.len(),
            positions: n,
        });
    }
    if let Some(v) = &cloud.normals
        && v.len() != n
    {
        return Err(PointCloudError::AttributeLength {
            attribute: "normals",
            len: v.len(),
            positions: n,
        });
    }
    if let Some(index) = cloud
        .positions
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(PointCloudError::NonFinite { index });
    }
    Ok(cloud.positions.iter().map(|p| p.map(f64::from)).collect())
}

/// The cloud's normals in f64, if present.
pub fn normals_f64(cloud: &PointCloud) -> Option<Vec<[f64; 3]>> {
    cloud
        .normals
        .as_ref()
        .map(|n| n.iter().map(|v| v.map(f64::from)).collect())
}

/// The point cloud on input `port`.
pub fn cloud_input<'a>(inputs: &Inputs<'a>, port: &str) -> Result<&'a Arc<PointCloud>, OpError> {
    match inputs.require(port)? {
        Value::PointCloud(c) => Ok(c),
        other => Err(OpError::input(
            port,
            format!("expected PointCloud, got {}", other.port_type()),
        )),
    }
}

/// Fails with [`PointCloudError::TooFewPoints`] below `needed` points.
pub fn require_points(n: usize, needed: usize) -> Result<(), PointCloudError> {
    if n < needed {
        Err(PointCloudError::TooFewPoints { needed, got: n })
    } else {
        Ok(())
    }
}

/// `f(i)` for every `i < n`, in parallel over chunks of [`CHUNK`], in index order.
pub fn par_map<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let chunks: Vec<Vec<T>> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| (c * CHUNK..((c + 1) * CHUNK).min(n)).map(&f).collect())
        .collect();
    chunks.into_iter().flatten().collect()
}

/// The points of `cloud` where `keep` is true, attributes carried along, order kept.
pub fn select(cloud: &PointCloud, keep: &[bool]) -> PointCloud {
    fn pick<T: Copy>(v: &[T], keep: &[bool]) -> Vec<T> {
        v.iter()
            .zip(keep)
            .filter(|(_, k)| **k)
            .map(|(x, _)| *x)
            .collect()
    }
    PointCloud {
        positions: pick(&cloud.positions, keep),
        colors: cloud.colors.as_deref().map(|c| pick(c, keep)),
        normals: cloud.normals.as_deref().map(|n| pick(n, keep)),
    }
}

/// A downsampled cloud and the number of input points in each output point's voxel.
#[derive(Debug, Clone, PartialEq)]
pub struct Downsampled {
    /// One point per occupied voxel, ordered by voxel key.
    pub cloud: PointCloud,
    /// Input points per output point.
    pub counts: Vec<usize>,
}

/// Voxel-grid downsampling (see the module documentation). `voxel_size > 0`.
pub fn voxel_downsample(
    cloud: &PointCloud,
    voxel_size: f64,
) -> Result<Downsampled, PointCloudError> {
    let points = positions_f64(cloud)?;
    if points.is_empty() {
        return Ok(Downsampled {
            cloud: PointCloud {
                positions: Vec::new(),
                colors: cloud.colors.as_ref().map(|_| Vec::new()),
                normals: cloud.normals.as_ref().map(|_| Vec::new()),
            },
            counts: Vec::new(),
        });
    }
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    let cells = extent / voxel_size;
    if cells.is_nan() || cells >= MAX_VOXEL_INDEX {
        return Err(PointCloudError::VoxelTooSmall { voxel_size, extent });
    }
    let key = |p: &[f64; 3]| [0, 1, 2].map(|a| ((p[a] - lo[a]) / voxel_size).floor() as i64);
    let mut order: Vec<([i64; 3], usize)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| (key(p), i))
        .collect();
    order.par_sort_unstable();
    let mut out = Downsampled {
        cloud: PointCloud {
            positions: Vec::new(),
            colors: cloud.colors.as_ref().map(|_| Vec::new()),
            normals: cloud.normals.as_ref().map(|_| Vec::new()),
        },
        counts: Vec::new(),
    };
    for group in order.chunk_by(|a, b| a.0 == b.0) {
        let m = group.len() as f64;
        let mut sum = [0.0f64; 3];
        for &(_, i) in group {
            for a in 0..3 {
                sum[a] += points[i][a] - lo[a];
            }
        }
        out.cloud
            .positions
            .push([0, 1, 2].map(|a| (lo[a] + sum[a] / m) as f32));
        if let (Some(src), Some(dst)) = (&cloud.colors, &mut out.cloud.colors) {
            let mut s = [0u64; 3];
            for &(_, i) in group {
                for c in 0..3 {
                    s[c] += u64::from(src[i][c]);
                }
            }
            let n = group.len() as u64;
            dst.push(s.map(|v| ((v + n / 2) / n).min(255) as u8));
        }
        if let (Some(src), Some(dst)) = (&cloud.normals, &mut out.cloud.normals) {
            let mut s = [0.0f64; 3];
            for &(_, i) in group {
                for a in 0..3 {
                    s[a] += f64::from(src[i][a]);
                }
            }
            let norm = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
            // Opposite normals cancelling out: keep the first point's.
            dst.push(if norm > 0.0 && norm.is_finite() {
                s.map(|v| (v / norm) as f32)
            } else {
                src[group[0].1]
            });
        }
        out.counts.push(group.len());
    }
    Ok(out)
}

/// The result of statistical outlier removal.
#[derive(Debug, Clone, PartialEq)]
pub struct StatisticalReport {
    /// `true` for kept points.
    pub keep: Vec<bool>,
    /// Mean over points of the mean neighbour distance, `μ`.
    pub mean_distance: f64,
    /// Sample standard deviation of the mean neighbour distances, `σ`.
    pub std_distance: f64,
    /// The cut-off `μ + std_ratio · σ`.
    pub threshold: f64,
}

/// Statistical outlier removal (see the module documentation). Needs `k ≥ 1` and more than `k`
/// points.
pub fn statistical_inliers(
    tree: &KdTree,
    k: usize,
    std_ratio: f64,
) -> Result<StatisticalReport, PointCloudError> {
    let n = tree.len();
    require_points(n, k + 1)?;
    let points = tree.points();
    let mean_dist = par_map(n, |i| {
        let mut nb = Vec::with_capacity(k + 1);
        tree.knn(&points[i], k + 1, f64::INFINITY, &mut nb);
        // The point itself is among the k + 1 (a duplicate of lower index may come first).
        let mut sum = 0.0;
        for m in nb.iter().filter(|m| m.index != i).take(k) {
            sum += m.dist2.sqrt();
        }
        sum / k as f64
    });
    let mean = mean_dist.iter().sum::<f64>() / n as f64;
    let var = mean_dist
        .iter()
        .map(|d| (d - mean) * (d - mean))
        .sum::<f64>()
        / (n - 1) as f64;
    let std = var.sqrt();
    let threshold = mean + std_ratio * std;
    Ok(StatisticalReport {
        keep: mean_dist.iter().map(|&d| d <= threshold).collect(),
        mean_distance: mean,
        std_distance: std,
        threshold,
    })
}

/// Radius outlier removal: keeps points with at least `min_neighbors` other points within
/// `radius` (inclusive).
pub fn radius_inliers(tree: &KdTree, radius: f64, min_neighbors: usize) -> Vec<bool> {
    let points = tree.points();
    let r2 = radius * radius;
    par_map(tree.len(), |i| {
        let mut nb = Vec::with_capacity(min_neighbors + 1);
        // The k nearest within the radius suffice: the point itself plus `min_neighbors`.
        tree.knn(&points[i], min_neighbors + 1, r2, &mut nb);
        nb.iter().filter(|m| m.index != i).count() >= min_neighbors
    })
}

/// Fewest neighbours (the point included) a covariance is formed from.
pub const MIN_NORMAL_NEIGHBORS: usize = 3;

/// The unit normal of the neighbourhood `nb` of `points[center]`: smallest-eigenvalue
/// eigenvector of the covariance, on coordinates relative to the centre point.
fn pca_normal(points: &[[f64; 3]], center: usize, nb: &[Neighbor]) -> [f64; 3] {
    let c = Vector3::from(points[center]);
    let mut mean = Vector3::zeros();
    for m in nb {
        mean += Vector3::from(points[m.index]) - c;
    }
    mean /= nb.len() as f64;
    let mut cov = Matrix3::zeros();
    for m in nb {
        let d = Vector3::from(points[m.index]) - c - mean;
        cov += d * d.transpose();
    }
    let eigen = SymmetricEigen::new(cov);
    let mut smallest = 0;
    for i in 1..3 {
        if eigen.eigenvalues[i] < eigen.eigenvalues[smallest] {
            smallest = i;
        }
    }
    let v = eigen.eigenvectors.column(smallest);
    let norm = v.norm();
    if norm > 0.0 && norm.is_finite() {
        [v[0] / norm, v[1] / norm, v[2] / norm]
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// PCA normals (see the module documentation), unoriented: the `k` nearest neighbours (itself
/// included), limited to `radius` when given; a point with fewer than
/// [`MIN_NORMAL_NEIGHBORS`] within the radius uses its [`MIN_NORMAL_NEIGHBORS`] nearest.
pub fn estimate_normals(
    tree: &KdTree,
    k: usize,
    radius: Option<f64>,
) -> Result<Vec<[f64; 3]>, PointCloudError> {
    require_points(tree.len(), MIN_NORMAL_NEIGHBORS)?;
    let k = k.max(MIN_NORMAL_NEIGHBORS);
    let r2 = radius.map_or(f64::INFINITY, |r| r * r);
    let points = tree.points();
    Ok(par_map(tree.len(), |i| {
        let mut nb = Vec::with_capacity(k);
        tree.knn(&points[i], k, r2, &mut nb);
        if nb.len() < MIN_NORMAL_NEIGHBORS {
            tree.knn(&points[i], MIN_NORMAL_NEIGHBORS, f64::INFINITY, &mut nb);
        }
        pca_normal(points, i, &nb)
    }))
}

/// Flips each normal so that it faces `viewpoint`: `nᵢ · (viewpoint − pᵢ) ≥ 0`.
pub fn orient_towards(points: &[[f64; 3]], normals: &mut [[f64; 3]], viewpoint: [f64; 3]) {
    for (p, n) in points.iter().zip(normals.iter_mut()) {
        let d = (0..3).map(|a| n[a] * (viewpoint[a] - p[a])).sum::<f64>();
        if d < 0.0 {
            *n = n.map(|v| -v);
        }
    }
}

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Consistent orientation by minimum-spanning-tree propagation over the symmetric `k`-NN graph
/// (see the module documentation).
pub fn orient_consistent(tree: &KdTree, normals: &mut [[f64; 3]], k: usize) {
    let n = tree.len();
    let points = tree.points();
    // Symmetric adjacency: j ∈ knn(i) gives edges i→j and j→i.
    let knn: Vec<Vec<usize>> = par_map(n, |i| {
        let mut nb = Vec::with_capacity(k + 1);
        tree.knn(&points[i], k + 1, f64::INFINITY, &mut nb);
        nb.iter().map(|m| m.index).filter(|&j| j != i).collect()
    });
    let mut adjacency: Vec<Vec<usize>> = knn.clone();
    for (i, list) in knn.iter().enumerate() {
        for &j in list {
            adjacency[j].push(i);
        }
    }
    for list in &mut adjacency {
        list.sort_unstable();
        list.dedup();
    }
    let weight = |i: usize, j: usize, normals: &[[f64; 3]]| -> u64 {
        let w = 1.0 - dot(&normals[i], &normals[j]).abs();
        // Non-negative f64 bit patterns order as the numbers do.
        if w > 0.0 { w.to_bits() } else { 0 }
    };
    let mut roots: Vec<usize> = (0..n).collect();
    roots.sort_by(|&a, &b| points[b][2].total_cmp(&points[a][2]).then(a.cmp(&b)));
    let mut visited = vec![false; n];
    let mut heap: BinaryHeap<Reverse<(u64, usize, usize)>> = BinaryHeap::new();
    for root in roots {
        if visited[root] {
            continue;
        }
        visited[root] = true;
        if normals[root][2] < 0.0 {
            normals[root] = normals[root].map(|v| -v);
        }
        for &j in &adjacency[root] {
            heap.push(Reverse((weight(root, j, normals), j, root)));
        }
        // Prim's algorithm: each point is reached from its parent in the tree.
        while let Some(Reverse((_, j, parent))) = heap.pop() {
            if visited[j] {
                continue;
            }
            visited[j] = true;
            if dot(&normals[j], &normals[parent]) < 0.0 {
                normals[j] = normals[j].map(|v| -v);
            }
            for &m in &adjacency[j] {
                if !visited[m] {
                    heap.push(Reverse((weight(j, m, normals), m, j)));
                }
            }
        }
    }
}

params! {
    /// Parameters of `mesh.voxel_downsample`.
    pub struct VoxelDownsampleParams {
        /// Edge length of the cubic voxels, scene units. Default 0.01.
        voxel_size: f64 = 0.01 => [min = 0.0, unit = "scene units"],
    }
}

/// Voxel-grid downsampling (`mesh.voxel_downsample`). See [`voxel_downsample`].
#[derive(Debug, Clone, PartialEq)]
pub struct VoxelDownsample {
    voxel_size: f64,
}

impl Op for VoxelDownsample {
    type Params = VoxelDownsampleParams;
    const ID: &'static str = "mesh.voxel_downsample";
    const SUMMARY: &'static str =
        "Downsamples a point cloud to the centroid of the points of each occupied voxel.";
    const DOC: &'static str = r#"
Divides space into cubes of edge `voxel_size` anchored at the cloud's minimum corner and
replaces the points of each occupied voxel by their centroid; colors are averaged (rounded) and
normals averaged and renormalized (a voxel whose normals cancel keeps its first point's). The
output is ordered by voxel index (x, then y, then z), so it is the same for any thread count.
Voxel keys are exact integers; a `voxel_size` giving more than 2^40 voxels along an axis is an
error. An empty cloud gives an empty cloud.

Metrics: `input_points`, `output_points`, `max_points_per_voxel`.

Reference: the voxel grid filter of PCL (`pcl::VoxelGrid`) and Open3D
(`voxel_down_sample`).

Example:
    "down": (op: "mesh.voxel_downsample", inputs: { "cloud": "scan.cloud" }, params: (voxel_size: 0.005)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "cloud",
            PortType::PointCloud,
            "The points (colors and normals optional).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "cloud",
                PortType::PointCloud,
                "One point per occupied voxel, same attributes as the input.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "input_points, output_points, max_points_per_voxel.",
            ),
        ]
    }

    fn new(p: VoxelDownsampleParams) -> Result<Self, String> {
        if !(p.voxel_size.is_finite() && p.voxel_size > 0.0) {
            return Err(format!(
                "`voxel_size` must be finite and > 0, got {}",
                p.voxel_size
            ));
        }
        Ok(VoxelDownsample {
            voxel_size: p.voxel_size,
        })
    }
}

impl Operator for VoxelDownsample {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        let d = voxel_downsample(cloud, self.voxel_size).map_err(|e| e.at("cloud"))?;
        let mut m = Metrics::new();
        m.insert("input_points".into(), cloud.positions.len() as f64);
        m.insert("output_points".into(), d.cloud.positions.len() as f64);
        m.insert(
            "max_points_per_voxel".into(),
            d.counts.iter().copied().max().unwrap_or(0) as f64,
        );
        Ok(Outputs::new()
            .with("cloud", Value::PointCloud(Arc::new(d.cloud)))
            .with("metrics", Value::metrics(m)))
    }
}

param_enum! {
    /// Outlier test of `mesh.remove_outliers`.
    pub enum OutlierMethod {
        /// Mean distance to the k nearest neighbours against μ + std_ratio·σ.
        Statistical = "statistical",
        /// At least `min_neighbors` other points within `radius`.
        Radius = "radius",
    }
}

params! {
    /// Parameters of `mesh.remove_outliers`.
    pub struct RemoveOutliersParams {
        /// "statistical" (PCL's StatisticalOutlierRemoval) or "radius". Default "statistical".
        method: OutlierMethod = OutlierMethod::Statistical,
        /// Statistical: neighbours per point (the point itself not counted). Default 20.
        k: u32 = 20 => [min = 1, max = 1000],
        /// Statistical: a point is an outlier when its mean neighbour distance exceeds
        /// μ + std_ratio·σ (σ: standard deviations). Default 2.
        std_ratio: f64 = 2.0,
        /// Radius: the search radius, scene units; required for "radius".
        radius: Option<f64> = None => [min = 0.0, unit = "scene units"],
        /// Radius: fewest other points within `radius` for a point to be kept. Default 2.
        min_neighbors: u32 = 2 => [min = 1, max = 1000],
    }
}

/// Outlier removal (`mesh.remove_outliers`). See [`statistical_inliers`] and
/// [`radius_inliers`].
#[derive(Debug, Clone, PartialEq)]
pub struct RemoveOutliers {
    params: RemoveOutliersParams,
}

impl Op for RemoveOutliers {
    type Params = RemoveOutliersParams;
    const ID: &'static str = "mesh.remove_outliers";
    const SUMMARY: &'static str =
        "Removes isolated points: statistical (k-NN mean distance) or radius outlier removal.";
    const DOC: &'static str = r#"
"statistical" (PCL's StatisticalOutlierRemoval; Rusu et al., RAS 2008): for every point the
mean distance d_i to its `k` nearest neighbours (itself excluded); with μ and σ the mean and
sample standard deviation of all d_i, a point is kept when d_i ≤ μ + std_ratio·σ. Needs more
than `k` points.

"radius": a point is kept when at least `min_neighbors` other points lie within `radius`
(inclusive).

Kept points keep their order and attributes. Metrics: `kept`, `removed`; for "statistical"
also `mean_distance` (μ), `std_distance` (σ) and `threshold`.

Example:
    "clean": (op: "mesh.remove_outliers", inputs: { "cloud": "scan.cloud" }, params: (k: 20, std_ratio: 2.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("cloud", PortType::PointCloud, "The points.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("cloud", PortType::PointCloud, "The kept points."),
            PortSpec::new("removed", PortType::Integer, "Number of points removed."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "kept, removed (and mean_distance, std_distance, threshold for statistical).",
            ),
        ]
    }

    fn new(p: RemoveOutliersParams) -> Result<Self, String> {
        if !p.std_ratio.is_finite() {
            return Err(format!("`std_ratio` must be finite, got {}", p.std_ratio));
        }
        if p.method == OutlierMethod::Radius {
            match p.radius {
                Some(r) if r.is_finite() && r > 0.0 => {}
                Some(r) => return Err(format!("`radius` must be finite and > 0, got {r}")),
                None => return Err("method \"radius\" needs the `radius` param".into()),
            }
        }
        Ok(RemoveOutliers { params: p })
    }
}

impl Operator for RemoveOutliers {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        let points = positions_f64(cloud).map_err(|e| e.at("cloud"))?;
        let tree = KdTree::new(points);
        let mut m = Metrics::new();
        let keep = match self.params.method {
            OutlierMethod::Statistical => {
                let r = statistical_inliers(&tree, self.params.k as usize, self.params.std_ratio)
                    .map_err(|e| e.at("cloud"))?;
                m.insert("mean_distance".into(), r.mean_distance);
                m.insert("std_distance".into(), r.std_distance);
                m.insert("threshold".into(), r.threshold);
                r.keep
            }
            OutlierMethod::Radius => radius_inliers(
                &tree,
                self.params.radius.unwrap_or(0.0),
                self.params.min_neighbors as usize,
            ),
        };
        let kept = keep.iter().filter(|k| **k).count();
        let removed = keep.len() - kept;
        m.insert("kept".into(), kept as f64);
        m.insert("removed".into(), removed as f64);
        Ok(Outputs::new()
            .with("cloud", Value::PointCloud(Arc::new(select(cloud, &keep))))
            .with("removed", Value::Integer(removed as i64))
            .with("metrics", Value::metrics(m)))
    }
}

param_enum! {
    /// How `mesh.estimate_normals` chooses each normal's sign.
    pub enum Orientation {
        /// As the eigen-solver returns it (arbitrary but deterministic).
        None = "none",
        /// Towards the `viewpoint` param.
        Viewpoint = "viewpoint",
        /// Consistent over the surface: MST propagation (Hoppe et al. 1992).
        Consistent = "consistent",
    }
}

params! {
    /// Parameters of `mesh.estimate_normals`.
    pub struct EstimateNormalsParams {
        /// Neighbours per point, the point itself included (at least 3). Default 20.
        k: u32 = 20 => [min = 3, max = 1000],
        /// Only neighbours within this distance, scene units; none: the k nearest. Default none.
        radius: Option<f64> = None => [min = 0.0, unit = "scene units"],
        /// Sign choice: "none", "viewpoint" or "consistent". Default "consistent".
        orientation: Orientation = Orientation::Consistent,
        /// The point normals face with orientation "viewpoint", scene units. Default origin.
        viewpoint: [f64; 3] = [0.0, 0.0, 0.0],
    }
}

/// Normal estimation (`mesh.estimate_normals`). See [`estimate_normals`].
#[derive(Debug, Clone, PartialEq)]
pub struct EstimateNormals {
    params: EstimateNormalsParams,
}

impl Op for EstimateNormals {
    type Params = EstimateNormalsParams;
    const ID: &'static str = "mesh.estimate_normals";
    const SUMMARY: &'static str = "Estimates point normals by PCA of the k nearest neighbours, oriented to a viewpoint or consistently.";
    const DOC: &'static str = r#"
The normal of each point is the unit eigenvector of the smallest eigenvalue of the covariance
of its `k` nearest neighbours (itself included; within `radius` when given, falling back to the
3 nearest where fewer lie within it), computed on coordinates relative to the point, so a cloud
far from the origin keeps full precision.

Orientation:
- "none": the eigen-solver's sign;
- "viewpoint": n_i · (viewpoint − p_i) ≥ 0 (a scanner's position);
- "consistent": Hoppe et al.'s propagation: the minimum spanning tree of the symmetric k-NN
  graph with edge weights 1 − |n_i · n_j|, grown by Prim's algorithm from the highest point
  (largest z) of each connected component, whose normal is turned to +z; each point's normal is
  flipped to agree with its parent's. On a closed surface this points every normal outward.

Needs at least 3 points. Positions, colors and existing normals are replaced by the new ones
(positions and colors unchanged).

Reference: Hoppe, DeRose, Duchamp, McDonald & Stuetzle, "Surface reconstruction from
unorganized points", SIGGRAPH 1992, §3.2–3.3.

Example:
    "normals": (op: "mesh.estimate_normals", inputs: { "cloud": "down.cloud" }, params: (k: 20, orientation: "consistent")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("cloud", PortType::PointCloud, "The points.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "cloud",
            PortType::PointCloud,
            "The input points with unit normals.",
        )]
    }

    fn new(p: EstimateNormalsParams) -> Result<Self, String> {
        if let Some(r) = p.radius
            && !(r.is_finite() && r > 0.0)
        {
            return Err(format!("`radius` must be finite and > 0, got {r}"));
        }
        if !p.viewpoint.iter().all(|v| v.is_finite()) {
            return Err(format!("`viewpoint` must be finite, got {:?}", p.viewpoint));
        }
        Ok(EstimateNormals { params: p })
    }
}

/// PCA normals of `points`, oriented as `orientation` says.
pub fn oriented_normals(
    tree: &KdTree,
    k: usize,
    radius: Option<f64>,
    orientation: Orientation,
    viewpoint: [f64; 3],
) -> Result<Vec<[f64; 3]>, PointCloudError> {
    let mut normals = estimate_normals(tree, k, radius)?;
    match orientation {
        Orientation::None => {}
        Orientation::Viewpoint => orient_towards(tree.points(), &mut normals, viewpoint),
        Orientation::Consistent => orient_consistent(tree, &mut normals, k),
    }
    Ok(normals)
}

impl Operator for EstimateNormals {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        let tree = KdTree::new(positions_f64(cloud).map_err(|e| e.at("cloud"))?);
        let p = &self.params;
        let normals = oriented_normals(&tree, p.k as usize, p.radius, p.orientation, p.viewpoint)
            .map_err(|e| e.at("cloud"))?;
        let out = PointCloud {
            positions: cloud.positions.clone(),
            colors: cloud.colors.clone(),
            normals: Some(normals.iter().map(|n| n.map(|v| v as f32)).collect()),
        };
        Ok(Outputs::new().with("cloud", Value::PointCloud(Arc::new(out))))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use proptest::prelude::*;

    /// `n` points uniformly on a sphere (seeded), with their outward normals.
    pub(crate) fn sphere(n: usize, center: [f64; 3], radius: f64, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                let z = 2.0 * rng.uniform() - 1.0;
                let phi = 2.0 * std::f64::consts::PI * rng.uniform();
                let r = (1.0 - z * z).max(0.0).sqrt();
                [
                    center[0] + radius * r * phi.cos(),
                    center[1] + radius * r * phi.sin(),
                    center[2] + radius * z,
                ]
            })
            .collect()
    }

    pub(crate) fn cloud_of(points: &[[f64; 3]]) -> PointCloud {
        PointCloud {
            positions: points.iter().map(|p| p.map(|v| v as f32)).collect(),
            colors: None,
            normals: None,
        }
    }

    #[test]
    fn one_point_per_voxel_is_the_identity_up_to_order() {
        // A 5×4×3 grid of points, one per voxel, with colors and normals; the coordinates are
        // exact in binary so the voxel of each point is not a rounding accident.
        let mut positions = Vec::new();
        let mut colors = Vec::new();
        let mut normals = Vec::new();
        for x in 0..5 {
            for y in 0..4 {
                for z in 0..3 {
                    positions.push([
                        x as f32 * 0.5 + 0.125,
                        y as f32 * 0.5 + 0.25,
                        z as f32 * 0.5,
                    ]);
                    colors.push([x as u8 * 40, y as u8 * 50, z as u8 * 60]);
                    normals.push([0.6, 0.0, 0.8]);
                }
            }
        }
        // Reverse so output order (by key) differs from input order.
        positions.reverse();
        colors.reverse();
        let cloud = PointCloud {
            positions: positions.clone(),
            colors: Some(colors.clone()),
            normals: Some(normals),
        };
        let d = voxel_downsample(&cloud, 0.5).unwrap();
        assert_eq!(d.counts, vec![1; 60]);
        let mut got: Vec<([u32; 3], [u8; 3])> = d
            .cloud
            .positions
            .iter()
            .zip(d.cloud.colors.as_ref().unwrap())
            .map(|(p, c)| (p.map(f32::to_bits), *c))
            .collect();
        let mut want: Vec<([u32; 3], [u8; 3])> = positions
            .iter()
            .zip(&colors)
            .map(|(p, c)| (p.map(f32::to_bits), *c))
            .collect();
        got.sort_unstable();
        want.sort_unstable();
        assert_eq!(got, want);
        assert!(
            d.cloud
                .normals
                .unwrap()
                .iter()
                .all(|n| *n == [0.6, 0.0, 0.8])
        );
    }

    #[test]
    fn voxel_centroids_counts_and_averages() {
        // Voxels of 1: three points in [0,1)³, one in [2,3)×[0,1)², two (opposite normals) in
        // [0,1)²×[1,2).
        let positions = vec![
            [0.1f32, 0.2, 0.3],
            [2.5, 0.5, 0.5],
            [0.3, 0.4, 0.5],
            [0.5, 0.6, 0.1],
            [0.5, 0.5, 1.5],
            [0.5, 0.5, 1.7],
        ];
        let cloud = PointCloud {
            positions,
            colors: Some(vec![
                [0, 0, 0],
                [9, 9, 9],
                [10, 20, 255],
                [20, 40, 255],
                [1, 1, 1],
                [2, 2, 2],
            ]),
            normals: Some(vec![
                [1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0],
                [0.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
                [0.0, 0.0, -1.0],
            ]),
        };
        let d = voxel_downsample(&cloud, 1.0).unwrap();
        assert_eq!(d.counts, vec![3, 2, 1]);
        assert_eq!(d.counts.iter().sum::<usize>(), 6);
        let p = &d.cloud.positions;
        for (a, want) in [0.3f32, 0.4, 0.3].iter().enumerate() {
            assert!((p[0][a] - want).abs() < 1e-6, "{p:?}");
        }
        assert!((p[1][2] - 1.6).abs() < 1e-6);
        assert_eq!(p[2], [2.5, 0.5, 0.5]);
        let c = d.cloud.colors.as_ref().unwrap();
        assert_eq!(c[0], [10, 20, 170]);
        assert_eq!(c[1], [2, 2, 2]); // (1 + 2) / 2 rounded half up
        let n = d.cloud.normals.as_ref().unwrap();
        let s = 1.0 / 5f32.sqrt();
        assert!((n[0][0] - s).abs() < 1e-6 && (n[0][1] - 2.0 * s).abs() < 1e-6);
        assert_eq!(n[1], [0.0, 0.0, 1.0]); // cancelled: the first point's
        // Empty in, empty out; a voxel too small for the extent is an error.
        let empty = voxel_downsample(&PointCloud::default(), 1.0).unwrap();
        assert!(empty.cloud.positions.is_empty());
        assert!(matches!(
            voxel_downsample(&cloud, 1e-13),
            Err(PointCloudError::VoxelTooSmall { .. })
        ));
        let bad = PointCloud {
            positions: vec![[0.0, f32::NAN, 0.0]],
            ..PointCloud::default()
        };
        assert_eq!(
            voxel_downsample(&bad, 1.0),
            Err(PointCloudError::NonFinite { index: 0 })
        );
    }

    proptest! {
        #[test]
        fn voxel_counts_sum_to_the_input(
            pts in proptest::collection::vec(proptest::array::uniform3(-50f32..50.0), 0..300),
            size in 0.5f64..20.0,
        ) {
            let cloud = PointCloud { positions: pts.clone(), colors: None, normals: None };
            let d = voxel_downsample(&cloud, size).unwrap();
            prop_assert_eq!(d.counts.iter().sum::<usize>(), pts.len());
            prop_assert_eq!(d.cloud.positions.len(), d.counts.len());
            // Idempotent in count: a second pass merges nothing the first kept apart... at
            // least it never grows.
            let again = voxel_downsample(&d.cloud, size).unwrap();
            prop_assert!(again.counts.len() <= d.counts.len());
        }
    }

    #[test]
    fn statistical_removal_drops_far_points_and_keeps_the_surface() {
        let c = [1e6, -2e6, 5e5];
        let mut pts = sphere(2000, c, 1.0, 3);
        let mut rng = SplitMix64::new(4);
        let surface = pts.len();
        for _ in 0..20 {
            let d = [0, 1, 2].map(|_| rng.uniform() * 2.0 - 1.0);
            let norm = dot(&d, &d).sqrt().max(1e-9);
            let r = 3.0 + 3.0 * rng.uniform();
            pts.push([0, 1, 2].map(|a| c[a] + r * d[a] / norm));
        }
        let tree = KdTree::new(pts.clone());
        let r = statistical_inliers(&tree, 10, 1.0).unwrap();
        assert!(r.keep[surface..].iter().all(|k| !k), "far points kept");
        let kept_surface = r.keep[..surface].iter().filter(|k| **k).count();
        assert!(
            kept_surface as f64 >= 0.95 * surface as f64,
            "{kept_surface}"
        );
        // Radius removal: the surface is dense (spacing ~0.04), the far points isolated.
        let keep = radius_inliers(&tree, 0.2, 3);
        assert!(keep[surface..].iter().all(|k| !k));
        assert!(keep[..surface].iter().all(|k| *k));
        assert_eq!(
            statistical_inliers(&KdTree::new(pts[..5].to_vec()), 5, 1.0),
            Err(PointCloudError::TooFewPoints { needed: 6, got: 5 })
        );
    }

    #[test]
    fn statistical_removal_counts_duplicates_as_neighbours() {
        // Four copies of one point and one far point, k = 3: the copies have mean distance 0.
        let mut pts = vec![[1.0, 2.0, 3.0]; 4];
        pts.push([11.0, 2.0, 3.0]);
        let r = statistical_inliers(&KdTree::new(pts), 3, 1.0).unwrap();
        assert_eq!(r.keep, [true, true, true, true, false]);
        // d = [0, 0, 0, 0, 10]: μ = 2, σ² = (4·4 + 64)/4 = 20.
        assert!((r.mean_distance - 2.0).abs() < 1e-12);
        assert!((r.std_distance - 20f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn sphere_normals_viewpoint_and_consistent() {
        for center in [[0.0, 0.0, 0.0], [1e6, 1e6, -1e6]] {
            let pts = sphere(3000, center, 2.0, 7);
            let tree = KdTree::new(pts.clone());
            let outward: Vec<[f64; 3]> = pts
                .iter()
                .map(|p| [0, 1, 2].map(|a| (p[a] - center[a]) / 2.0))
                .collect();
            let toward = oriented_normals(&tree, 15, None, Orientation::Viewpoint, center).unwrap();
            // Viewpoint at the centre: every normal points inward, and is accurate.
            for (n, o) in toward.iter().zip(&outward) {
                assert!(dot(n, o) < -0.99, "{n:?} {o:?}");
            }
            let consistent =
                oriented_normals(&tree, 15, None, Orientation::Consistent, center).unwrap();
            let agree = consistent
                .iter()
                .zip(&outward)
                .filter(|(n, o)| dot(n, o) > 0.0)
                .count();
            assert!(agree as f64 > 0.99 * pts.len() as f64, "{agree}");
            let unit = consistent.iter().all(|n| (dot(n, n) - 1.0).abs() < 1e-12);
            assert!(unit);
        }
    }

    #[test]
    fn normals_of_a_plane_and_degenerate_input() {
        // The plane z = 0.5 x: normal ∝ (−0.5, 0, 1).
        let pts: Vec<[f64; 3]> = (0..100)
            .map(|i| {
                let (x, y) = ((i % 10) as f64, (i / 10) as f64);
                [x, y, 0.5 * x]
            })
            .collect();
        let tree = KdTree::new(pts);
        let n =
            oriented_normals(&tree, 8, None, Orientation::Viewpoint, [0.0, 0.0, 100.0]).unwrap();
        let s = 1.25f64.sqrt();
        for v in &n {
            assert!(
                (v[0] + 0.5 / s).abs() < 1e-9 && v[1].abs() < 1e-9 && (v[2] - 1.0 / s).abs() < 1e-9
            );
        }
        // Within 1.2: the grid neighbours along x (1.118 away) and y (1 away): still exact.
        let r = estimate_normals(&tree, 8, Some(1.2)).unwrap();
        assert!(
            r.iter()
                .all(|v| v[1].abs() < 1e-9 && (v[2].abs() - 1.0 / s).abs() < 1e-9)
        );
        // Within 0.1 nothing: the 3 nearest are used (collinear here), a unit normal all the
        // same.
        let r = estimate_normals(&tree, 8, Some(0.1)).unwrap();
        assert!(r.iter().all(|v| (dot(v, v) - 1.0).abs() < 1e-12));
        assert_eq!(
            estimate_normals(&KdTree::new(vec![[0.0; 3]; 2]), 8, None),
            Err(PointCloudError::TooFewPoints { needed: 3, got: 2 })
        );
        // Coincident points: a finite unit normal, not NaN.
        let same = estimate_normals(&KdTree::new(vec![[5.0; 3]; 4]), 3, None).unwrap();
        assert!(same.iter().all(|v| (dot(v, v) - 1.0).abs() < 1e-12));
    }

    #[test]
    fn normals_do_not_depend_on_the_thread_count() {
        let pts = sphere(9000, [0.0; 3], 1.0, 11);
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let tree = KdTree::new(pts.clone());
                oriented_normals(&tree, 10, None, Orientation::Consistent, [0.0; 3]).unwrap()
            })
        };
        assert_eq!(run(1), run(3));
    }
}
