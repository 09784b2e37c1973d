//! `mesh.poisson`: screened Poisson surface reconstruction from oriented points (Kazhdan,
//! Bolitho & Hoppe, "Poisson surface reconstruction", SGP 2006; Kazhdan & Hoppe, "Screened
//! Poisson surface reconstruction", ACM TOG 32(3), 2013).
//!
//! The points are scaled into the unit cube `[0, 1]³` (their bounding cube, centred, enlarged
//! by `scale`). An implicit function `χ` on the nodes of a grid of `2^depth` cells per axis
//! minimises the discrete form of KH13's energy (their eq. 2, with unit sample weights)
//!
//! ```text
//! E(χ) = ∫ |∇χ − V|² dx + α · (A / N) · Σₛ χ(pₛ)²
//! ```
//!
//! - `V`: the normals splatted onto the grid nodes with trilinear weights (the first-order
//!   B-spline of KBH06 §4), `V = Σₛ nₛ B(x − pₛ)`, each at its sample's own depth (KBH06 §4.3's
//!   adaptive splatting: the finest depth at which a kernel estimate of the sample density
//!   reaches `samples_per_node` per cell, at most [`MAX_SPLAT_COARSENING`] levels coarser; a
//!   coarser splat is the coarser level's tent, `2^k` cells wide, on this level's nodes), so
//!   where points are sparse for the grid the field is smooth; the gradient term is the graph Laplacian of the
//!   node grid (the natural, Neumann, boundary) against finite differences of `V` along the grid
//!   edges.
//! - the screening term: `χ(pₛ)` trilinear in the 8 corners of the sample's cell; `A / N` is the
//!   surface area per sample, estimated by counting occupied cells (`A ≈ occupied · h² / 1.5`,
//!   1.5 the mean cell-crossing factor of a randomly oriented plane) at the finest level that
//!   holds at least [`SAMPLES_PER_AREA_CELL`] samples per occupied cell.
//!
//! The normal equations `(L + β S) χ = b` with `β = α · (A/N) · 2^depth` (the `1/h` of the
//! finite-element scaling, KH13 §4.3) are solved coarse to fine, as KH13's cascadic solver: at
//! depth [`BASE_DEPTH`] (or `depth` if smaller) on every node by conjugate gradients with a
//! Jacobi preconditioner, then at each finer depth the coarser solution is prolonged
//! (trilinearly) and only the nodes within [`BAND`] cells of a cell holding samples are solved
//! for, the others keeping the prolonged values: the finer levels refine where the surface is,
//! like the adaptive octree of KBH06, while `χ` stays defined on the whole grid so that the
//! extracted surface is closed.
//!
//! The surface is the level set `χ = mean of χ at the samples` (KH13 §4.4), extracted by
//! [`marching_cubes`] (watertight, counter-clockwise outward). With `density_trim = q > 0`,
//! the vertices whose sample density (a trilinear splat of the samples four levels coarser,
//! i.e. over 16 finest cells) is below the `q`-quantile of the vertices' densities are removed
//! with their triangles, as Open3D's density-based trimming (the result is then open).
//!
//! Determinism: the splats are gathered per node in sample order, every parallel loop writes
//! only its own outputs, and the conjugate-gradient dot products are reduced per fixed chunk of
//! [`CHUNK`] nodes and the partial sums added in chunk order, so the result is the same for any
//! number of threads.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, PointCloud, Value};
use rayon::prelude::*;

use super::marching_cubes::{IsoSurface, MarchingCubesError, ScalarGrid, marching_cubes};
use super::pointcloud::{cloud_input, positions_f64};

/// Nodes per parallel work item and per partial sum of a dot product.
pub const CHUNK: usize = 4096;
/// Depth of the first, full-grid solve.
pub const BASE_DEPTH: u32 = 5;
/// Finer levels solve the nodes within this many cells (Chebyshev) of a cell holding samples.
pub const BAND: usize = 3;
/// Largest `depth`: 513³ nodes take about 2.5 GB.
pub const MAX_DEPTH: u32 = 9;
/// The area estimate uses the finest level with at least this many samples per occupied cell.
pub const SAMPLES_PER_AREA_CELL: f64 = 4.0;
/// Levels above the finest at which the trimming density is splatted.
const DENSITY_LEVELS: u32 = 4;
/// Most levels a sample's splat is coarsened below the solved level (a tent of 2^k cells;
/// 2^k − 1 must not exceed [`BAND`], so the whole splat lies on active nodes).
pub const MAX_SPLAT_COARSENING: u32 = 2;
/// Relative residual at which the base solve stops.
const BASE_TOLERANCE: f64 = 1e-6;
/// Relative residual reduction at which a finer solve stops.
const LEVEL_TOLERANCE: f64 = 1e-4;
/// Most iterations of the base solve.
const BASE_MAX_ITERATIONS: usize = 1000;
/// Most iterations at each finer level.
const LEVEL_MAX_ITERATIONS: usize = 200;

/// Why a reconstruction failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoissonError {
    /// The cloud has no normals.
    #[error(
        "the point cloud has no normals; Poisson reconstruction needs oriented points (add mesh.estimate_normals with orientation: \"consistent\")"
    )]
    NoNormals,
    /// Too few points.
    #[error("the point cloud has {got} points, but at least {needed} are needed")]
    TooFewPoints {
        /// Points needed.
        needed: usize,
        /// Points given.
        got: usize,
    },
    /// A position or normal is not usable.
    #[error("point {index}: {what}")]
    BadPoint {
        /// Index of the point.
        index: usize,
        /// What is wrong.
        what: String,
    },
    /// All points coincide.
    #[error("all points coincide; the cloud has no extent to reconstruct")]
    NoExtent,
    /// A parameter out of range.
    #[error("{0}")]
    Param(String),
    /// The extraction failed.
    #[error("iso-surface extraction: {0}")]
    Extraction(#[from] MarchingCubesError),
}

/// Options of [`reconstruct`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoissonOptions {
    /// Grid of `2^depth` cells per axis, `1..=MAX_DEPTH`.
    pub depth: u32,
    /// Screening weight α (0: plain Poisson, KBH06).
    pub screening: f64,
    /// Side of the reconstruction cube over the largest extent of the points, `≥ 1`.
    pub scale: f64,
    /// Quantile of vertex densities below which vertices are removed, `[0, 1)`.
    pub density_trim: f64,
    /// Adaptive splatting: a sample's normal is splatted at the finest level whose cell around
    /// it holds at least this many samples (at most [`MAX_SPLAT_COARSENING`] levels coarser
    /// than the level being solved); 0 splats every sample at the solved level. `≥ 0`.
    pub samples_per_node: f64,
}

impl Default for PoissonOptions {
    fn default() -> Self {
        PoissonOptions {
            depth: 8,
            screening: 4.0,
            scale: 1.1,
            density_trim: 0.0,
            samples_per_node: 0.5,
        }
    }
}

impl PoissonOptions {
    /// Checks every option.
    pub fn check(&self) -> Result<(), PoissonError> {
        if !(1..=MAX_DEPTH).contains(&self.depth) {
            return Err(PoissonError::Param(format!(
                "`depth` must be in 1..={MAX_DEPTH} (a 2^depth grid; depth {MAX_DEPTH} needs about 2.5 GB), got {}",
                self.depth
            )));
        }
        if !(self.screening.is_finite() && self.screening >= 0.0) {
            return Err(PoissonError::Param(format!(
                "`screening` must be finite and ≥ 0, got {}",
                self.screening
            )));
        }
        if !(self.scale.is_finite() && (1.0..=100.0).contains(&self.scale)) {
            return Err(PoissonError::Param(format!(
                "`scale` must be in [1, 100], got {}",
                self.scale
            )));
        }
        if !(self.samples_per_node.is_finite() && (0.0..=1e6).contains(&self.samples_per_node)) {
            return Err(PoissonError::Param(format!(
                "`samples_per_node` must be in [0, 1e6], got {}",
                self.samples_per_node
            )));
        }
        if !(self.density_trim.is_finite() && (0.0..1.0).contains(&self.density_trim)) {
            return Err(PoissonError::Param(format!(
                "`density_trim` must be in [0, 1), got {}",
                self.density_trim
            )));
        }
        Ok(())
    }
}

/// What [`reconstruct`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct PoissonReport {
    /// The surface, in the points' coordinates.
    pub surface: IsoSurface,
    /// Conjugate-gradient iterations over all levels.
    pub iterations: usize,
    /// Final relative residual `‖b − Aχ‖ / ‖b‖` of the finest level's system.
    pub residual: f64,
    /// The iso-value (mean of χ at the samples).
    pub iso_value: f64,
    /// Nodes solved for at the finest level.
    pub active_nodes: usize,
    /// Vertices removed by density trimming.
    pub trimmed_vertices: usize,
}

/// The 8 corner nodes of a sample's cell with their trilinear weights.
type Corners = [(usize, f64); 8];

/// Positions and normals.
pub type OrientedPoints = (Vec<[f64; 3]>, Vec<[f64; 3]>);

/// One grid level: `res` cells, `res + 1` nodes per axis.
#[derive(Debug, Clone, Copy)]
struct Level {
    res: usize,
}

impl Level {
    fn nodes(&self) -> usize {
        self.res + 1
    }

    fn count(&self) -> usize {
        self.nodes().pow(3)
    }

    fn index(&self, x: usize, y: usize, z: usize) -> usize {
        let n = self.nodes();
        x + n * (y + n * z)
    }

    /// The cell of unit-cube point `u` and the 8 corner nodes with trilinear weights.
    fn corners(&self, u: &[f64; 3]) -> ([usize; 3], [(usize, f64); 8]) {
        let r = self.res as f64;
        let mut cell = [0usize; 3];
        let mut f = [0.0f64; 3];
        for a in 0..3 {
            let s = (u[a] * r).clamp(0.0, r);
            let c = (s.floor() as usize).min(self.res - 1);
            cell[a] = c;
            f[a] = s - c as f64;
        }
        let corners = std::array::from_fn(|k| {
            let (dx, dy, dz) = (k & 1, (k >> 1) & 1, k >> 2);
            let w = [dx, dy, dz]
                .iter()
                .zip(f)
                .map(|(&d, f)| if d == 1 { f } else { 1.0 - f })
                .product::<f64>();
            (self.index(cell[0] + dx, cell[1] + dy, cell[2] + dz), w)
        });
        (cell, corners)
    }
}

/// `Σ a·b`, reduced per chunk of [`CHUNK`] in a fixed order.
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let partial: Vec<f64> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>())
        .collect();
    partial.iter().sum()
}

/// The linear system of one level, restricted to its active nodes.
struct System {
    /// Active nodes (grid indices), increasing.
    active: Vec<usize>,
    /// Per active node, the compact index of its 6 grid neighbours (−x, +x, −y, +y, −z, +z),
    /// `u32::MAX` where inactive, `u32::MAX - 1` where outside the grid.
    neighbors: Vec<[u32; 6]>,
    /// Per sample, its 8 corners as (compact index, weight).
    sample_corners: Vec<[(u32, f64); 8]>,
    /// CSR from active node to (sample, weight).
    offsets: Vec<usize>,
    entries: Vec<(u32, f64)>,
    /// Screening weight β.
    beta: f64,
    /// Jacobi diagonal.
    diagonal: Vec<f64>,
}

const INACTIVE: u32 = u32::MAX;
const OUTSIDE: u32 = u32::MAX - 1;

impl System {
    /// `y = A x` on compact vectors (inactive neighbours count as 0).
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let along: Vec<f64> = self
            .sample_corners
            .par_iter()
            .map(|c| {
                c.iter()
                    .map(|&(i, w)| x.get(i as usize).map_or(0.0, |v| w * v))
                    .sum::<f64>()
            })
            .collect();
        y.par_chunks_mut(CHUNK).enumerate().for_each(|(c, out)| {
            for (k, v) in out.iter_mut().enumerate() {
                let i = c * CHUNK + k;
                let mut s = 0.0;
                let mut degree = 0.0;
                for &j in &self.neighbors[i] {
                    if j != OUTSIDE {
                        degree += 1.0;
                        if j != INACTIVE {
                            s += x[j as usize];
                        }
                    }
                }
                let mut screen = 0.0;
                for &(smp, w) in &self.entries[self.offsets[i]..self.offsets[i + 1]] {
                    screen += w * along[smp as usize];
                }
                *v = degree * x[i] - s + self.beta * screen;
            }
        });
    }
}

/// Samples in unit-cube coordinates with their normals.
struct Samples {
    points: Vec<[f64; 3]>,
    normals: Vec<[f64; 3]>,
    /// Per sample, the finest depth at which its normal is splatted.
    splat_depth: Vec<u32>,
}

/// Per sample, the finest depth `≤ depth` at which the sample density around it reaches
/// `samples_per_node` samples per cell (PoissonRecon's adaptive splatting, KBH06 §4.3: where
/// samples are sparse for the grid the normal field is splatted wider, so the fine levels do
/// not follow the noise of isolated samples). The density at a level is a kernel estimate: every
/// sample splatted onto the level's nodes with trilinear weights and read back at each sample
/// through its 8 corners (`Σ_t B(p_s − p_t)`, in samples per cell), so it does not depend on
/// where cell boundaries fall. Sums run in sample order: deterministic.
fn splat_depths(points: &[[f64; 3]], depth: u32, samples_per_node: f64) -> Vec<u32> {
    let mut out = vec![0; points.len()];
    if samples_per_node <= 0.0 {
        return vec![depth; points.len()];
    }
    let mut settled = vec![false; points.len()];
    for d in (0..=depth).rev() {
        let l = Level { res: 1 << d };
        let corners: Vec<Corners> = points.par_iter().map(|u| l.corners(u).1).collect();
        let mut splat: Vec<(usize, u32, f64)> = corners
            .iter()
            .enumerate()
            .flat_map(|(s, c)| c.iter().map(move |&(g, w)| (g, s as u32, w)))
            .collect();
        splat.par_sort_unstable_by_key(|t| (t.0, t.1));
        let mut nodes: Vec<usize> = Vec::new();
        let mut weight: Vec<f64> = Vec::new();
        for &(g, _, w) in &splat {
            if nodes.last() == Some(&g) {
                if let Some(last) = weight.last_mut() {
                    *last += w;
                }
            } else {
                nodes.push(g);
                weight.push(w);
            }
        }
        for (s, c) in corners.iter().enumerate() {
            if settled[s] {
                continue;
            }
            let density: f64 = c
                .iter()
                .map(|&(g, w)| nodes.binary_search(&g).map_or(0.0, |i| w * weight[i]))
                .sum();
            if density >= samples_per_node || d == 0 {
                settled[s] = true;
                out[s] = d;
            }
        }
        if settled.iter().all(|&s| s) {
            break;
        }
    }
    out
}

/// The splat of sample `u` at `level` coarsened by `k` levels: a separable tent of half-width
/// `2^k` cells (the linear B-spline of the coarser level), normalised to unit sum; `k = 0` is the
/// trilinear splat on the cell's 8 corners.
fn splat_nodes(level: Level, u: &[f64; 3], k: u32, out: &mut Vec<(usize, f64)>) {
    out.clear();
    if k == 0 {
        out.extend(level.corners(u).1);
        return;
    }
    let r = level.res as f64;
    let w = f64::from(1u32 << k);
    let axis = |a: usize| -> Vec<(usize, f64)> {
        let p = (u[a] * r).clamp(0.0, r);
        let lo = (p - w).ceil().max(0.0) as usize;
        let hi = ((p + w).floor() as usize).min(level.res);
        (lo..=hi)
            .filter_map(|j| {
                let t = 1.0 - (j as f64 - p).abs() / w;
                (t > 0.0).then_some((j, t / w))
            })
            .collect()
    };
    let (ax, ay, az) = (axis(0), axis(1), axis(2));
    for &(z, wz) in &az {
        for &(y, wy) in &ay {
            for &(x, wx) in &ax {
                out.push((level.index(x, y, z), wx * wy * wz));
            }
        }
    }
}

/// Builds the system of `level` over the nodes within `band` cells of a cell holding samples
/// (every node when `None`) and its right-hand side.
fn build_system(
    level: Level,
    samples: &Samples,
    beta: f64,
    band: Option<usize>,
) -> (System, Vec<f64>) {
    let n = level.nodes();
    let total = level.count();
    let per_sample: Vec<([usize; 3], Corners)> = samples
        .points
        .par_iter()
        .map(|u| level.corners(u))
        .collect();
    let active: Vec<usize> = match band {
        None => (0..total).collect(),
        Some(b) => {
            let mut cells: Vec<[usize; 3]> = per_sample.iter().map(|(c, _)| *c).collect();
            cells.par_sort_unstable();
            cells.dedup();
            let mut mark = vec![false; total];
            for c in &cells {
                let lo = c.map(|v| v.saturating_sub(b));
                let hi = c.map(|v| (v + 1 + b).min(n - 1));
                for z in lo[2]..=hi[2] {
                    for y in lo[1]..=hi[1] {
                        let row = level.index(0, y, z);
                        if let Some(s) = mark.get_mut(row + lo[0]..=row + hi[0]) {
                            s.fill(true);
                        }
                    }
                }
            }
            mark.iter()
                .enumerate()
                .filter_map(|(i, &m)| m.then_some(i))
                .collect()
        }
    };
    let mut index = vec![INACTIVE; total];
    for (k, &g) in active.iter().enumerate() {
        index[g] = k as u32;
    }
    let neighbors: Vec<[u32; 6]> = active
        .par_iter()
        .map(|&g| {
            let (x, y, z) = (g % n, (g / n) % n, g / (n * n));
            let coord = [x, y, z];
            let stride = [1, n, n * n];
            let mut out = [OUTSIDE; 6];
            for a in 0..3 {
                if coord[a] > 0 {
                    out[2 * a] = index[g - stride[a]];
                }
                if coord[a] + 1 < n {
                    out[2 * a + 1] = index[g + stride[a]];
                }
            }
            out
        })
        .collect();
    // (node, sample, weight), sorted by node then sample: the gathers below run in sample order.
    let mut triples: Vec<(usize, u32, f64)> = per_sample
        .iter()
        .enumerate()
        .flat_map(|(s, (_, c))| c.iter().map(move |&(g, w)| (g, s as u32, w)))
        .collect();
    triples.par_sort_unstable_by_key(|t| (t.0, t.1));
    let m = active.len();
    let mut offsets = vec![0usize; m + 1];
    for t in &triples {
        let k = index[t.0];
        if k != INACTIVE {
            offsets[k as usize + 1] += 1;
        }
    }
    for k in 0..m {
        offsets[k + 1] += offsets[k];
    }
    let entries: Vec<(u32, f64)> = triples
        .iter()
        .filter(|t| index[t.0] != INACTIVE)
        .map(|t| (t.1, t.2))
        .collect();
    let sample_corners: Vec<[(u32, f64); 8]> = per_sample
        .iter()
        .map(|(_, c)| c.map(|(g, w)| (index[g], w)))
        .collect();
    // Splatted normals per active node: each sample's tent (trilinear at its splat depth, see
    // `splat_depths`) gathered per node in sample order.
    let depth = level.res.trailing_zeros();
    let coarsening = |s: usize| {
        depth
            .saturating_sub(samples.splat_depth[s])
            .min(MAX_SPLAT_COARSENING)
    };
    let adaptive = (0..samples.points.len()).any(|s| coarsening(s) > 0);
    let field: Vec<[f64; 3]> = if adaptive {
        let chunks: Vec<Vec<(usize, u32, f64)>> = samples
            .points
            .par_chunks(CHUNK)
            .enumerate()
            .map(|(c, pts)| {
                let mut nodes = Vec::new();
                let mut out = Vec::new();
                for (i, u) in pts.iter().enumerate() {
                    let s = c * CHUNK + i;
                    splat_nodes(level, u, coarsening(s), &mut nodes);
                    out.extend(
                        nodes
                            .iter()
                            .filter(|(g, _)| index[*g] != INACTIVE)
                            .map(|&(g, w)| (g, s as u32, w)),
                    );
                }
                out
            })
            .collect();
        let mut splats: Vec<(usize, u32, f64)> = chunks.into_iter().flatten().collect();
        splats.par_sort_unstable_by_key(|t| (t.0, t.1));
        let mut field = vec![[0.0; 3]; m];
        for &(g, s, w) in &splats {
            let nrm = samples.normals[s as usize];
            let v = &mut field[index[g] as usize];
            for a in 0..3 {
                v[a] += w * nrm[a];
            }
        }
        field
    } else {
        (0..m)
            .into_par_iter()
            .map(|k| {
                let mut v = [0.0; 3];
                for &(s, w) in &entries[offsets[k]..offsets[k + 1]] {
                    let nrm = samples.normals[s as usize];
                    for a in 0..3 {
                        v[a] += w * nrm[a];
                    }
                }
                v
            })
            .collect()
    };
    // b = h²-free divergence: Σ_edges into the node of V_e minus those out of it, V_e the mean
    // of its end nodes' components along the edge; scaled by res² so that χ has the same scale
    // at every level.
    let scale = (level.res * level.res) as f64;
    let rhs: Vec<f64> = (0..m)
        .into_par_iter()
        .map(|k| {
            let mut b = 0.0;
            for a in 0..3 {
                let own = field[k][a];
                let at = |j: u32| {
                    if j == INACTIVE || j == OUTSIDE {
                        0.0
                    } else {
                        field[j as usize][a]
                    }
                };
                if neighbors[k][2 * a] != OUTSIDE {
                    b += 0.5 * (at(neighbors[k][2 * a]) + own);
                }
                if neighbors[k][2 * a + 1] != OUTSIDE {
                    b -= 0.5 * (own + at(neighbors[k][2 * a + 1]));
                }
            }
            b * scale
        })
        .collect();
    let diagonal: Vec<f64> = (0..m)
        .into_par_iter()
        .map(|k| {
            let degree = neighbors[k].iter().filter(|&&j| j != OUTSIDE).count() as f64;
            let screen: f64 = entries[offsets[k]..offsets[k + 1]]
                .iter()
                .map(|&(_, w)| w * w)
                .sum();
            degree + beta * screen
        })
        .collect();
    (
        System {
            active,
            neighbors,
            sample_corners,
            offsets,
            entries,
            beta,
            diagonal,
        },
        rhs,
    )
}

/// Where a level's solve runs and when it stops.
#[derive(Debug, Clone, Copy)]
struct Stop {
    /// Solve only within this many cells of the samples (`None`: every node).
    band: Option<usize>,
    /// Stop when the residual norm falls below `tolerance` times the reference.
    tolerance: f64,
    /// Most iterations.
    max_iterations: usize,
    /// The reference is the initial residual (else the right-hand side).
    relative_to_start: bool,
}

/// Solves one level in place: `chi` holds the prolonged values on entry (kept at inactive
/// nodes). Returns iterations, the final relative residual `‖b − Aχ‖ / ‖b‖` and the number of
/// nodes solved for.
fn solve_level(
    level: Level,
    samples: &Samples,
    beta: f64,
    chi: &mut [f64],
    stop: Stop,
) -> (usize, f64, usize) {
    let Stop {
        band,
        tolerance,
        max_iterations,
        relative_to_start,
    } = stop;
    let (sys, b) = build_system(level, samples, beta, band);
    let n = level.nodes();
    let stride = [1, n, n * n];
    let m = sys.active.len();
    // r = b − A χ with the full χ (inactive neighbours at their fixed values).
    let chi_ro: &[f64] = chi;
    let along: Vec<f64> = samples
        .points
        .par_iter()
        .map(|u| interpolate(level, chi_ro, u))
        .collect();
    let mut r: Vec<f64> = (0..m)
        .into_par_iter()
        .map(|k| {
            let g = sys.active[k];
            let mut s = 0.0;
            let mut degree = 0.0;
            for a in 0..3 {
                if sys.neighbors[k][2 * a] != OUTSIDE {
                    degree += 1.0;
                    s += chi_ro[g - stride[a]];
                }
                if sys.neighbors[k][2 * a + 1] != OUTSIDE {
                    degree += 1.0;
                    s += chi_ro[g + stride[a]];
                }
            }
            let screen: f64 = sys.entries[sys.offsets[k]..sys.offsets[k + 1]]
                .iter()
                .map(|&(smp, w)| w * along[smp as usize])
                .sum();
            b[k] - (degree * chi_ro[g] - s + beta * screen)
        })
        .collect();
    let b_norm = dot(&b, &b).sqrt();
    let r0_norm = dot(&r, &r).sqrt();
    let reference = if relative_to_start { r0_norm } else { b_norm };
    let mut delta = vec![0.0; m];
    let mut z: Vec<f64> = r.iter().zip(&sys.diagonal).map(|(r, d)| r / d).collect();
    let mut p = z.clone();
    let mut q = vec![0.0; m];
    let mut rz = dot(&r, &z);
    let mut iterations = 0;
    let mut r_norm = r0_norm;
    while iterations < max_iterations && r_norm > tolerance * reference && r_norm > 0.0 {
        sys.apply(&p, &mut q);
        let pq = dot(&p, &q);
        if pq.is_nan() || pq <= 0.0 {
            break;
        }
        let step = rz / pq;
        delta
            .par_chunks_mut(CHUNK)
            .zip(r.par_chunks_mut(CHUNK))
            .zip(p.par_chunks(CHUNK).zip(q.par_chunks(CHUNK)))
            .for_each(|((d, r), (p, q))| {
                for (((d, r), p), q) in d.iter_mut().zip(r.iter_mut()).zip(p).zip(q) {
                    *d += step * p;
                    *r -= step * q;
                }
            });
        iterations += 1;
        r_norm = dot(&r, &r).sqrt();
        z.par_chunks_mut(CHUNK)
            .zip(r.par_chunks(CHUNK).zip(sys.diagonal.par_chunks(CHUNK)))
            .for_each(|(z, (r, d))| {
                for ((z, r), d) in z.iter_mut().zip(r).zip(d) {
                    *z = r / d;
                }
            });
        let rz_new = dot(&r, &z);
        let ratio = rz_new / rz;
        rz = rz_new;
        p.par_chunks_mut(CHUNK)
            .zip(z.par_chunks(CHUNK))
            .for_each(|(p, z)| {
                for (p, z) in p.iter_mut().zip(z) {
                    *p = z + ratio * *p;
                }
            });
    }
    for (k, &g) in sys.active.iter().enumerate() {
        chi[g] += delta[k];
    }
    let residual = if b_norm > 0.0 { r_norm / b_norm } else { 0.0 };
    (iterations, residual, m)
}

/// Trilinear prolongation of a level's node values to the next finer level.
fn prolong(coarse: Level, values: &[f64]) -> Vec<f64> {
    let fine = Level {
        res: coarse.res * 2,
    };
    let nf = fine.nodes();
    let taps = |f: usize| -> [(usize, f64); 2] {
        if f.is_multiple_of(2) {
            [(f / 2, 1.0), (f / 2, 0.0)]
        } else {
            [(f / 2, 0.5), (f / 2 + 1, 0.5)]
        }
    };
    let mut out = vec![0.0; fine.count()];
    out.par_chunks_mut(nf * nf)
        .enumerate()
        .for_each(|(z, slab)| {
            let tz = taps(z);
            for y in 0..nf {
                let ty = taps(y);
                for x in 0..nf {
                    let tx = taps(x);
                    let mut v = 0.0;
                    for &(cz, wz) in &tz {
                        for &(cy, wy) in &ty {
                            for &(cx, wx) in &tx {
                                let w = wx * wy * wz;
                                if w != 0.0 {
                                    v += w * values[coarse.index(cx, cy, cz)];
                                }
                            }
                        }
                    }
                    slab[x + nf * y] = v;
                }
            }
        });
    out
}

/// Trilinear interpolation of node values at unit-cube point `u`.
fn interpolate(level: Level, values: &[f64], u: &[f64; 3]) -> f64 {
    let (_, c) = level.corners(u);
    c.iter().map(|&(g, w)| w * values[g]).sum()
}

/// Screened Poisson reconstruction (see the module documentation) of oriented points.
pub fn reconstruct(
    points: &[[f64; 3]],
    normals: &[[f64; 3]],
    options: &PoissonOptions,
) -> Result<PoissonReport, PoissonError> {
    options.check()?;
    if points.len() < 4 {
        return Err(PoissonError::TooFewPoints {
            needed: 4,
            got: points.len(),
        });
    }
    if normals.len() != points.len() {
        return Err(PoissonError::BadPoint {
            index: normals.len().min(points.len()),
            what: format!("{} normals for {} points", normals.len(), points.len()),
        });
    }
    let mut unit_normals = Vec::with_capacity(normals.len());
    for (index, (p, n)) in points.iter().zip(normals).enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(PoissonError::BadPoint {
                index,
                what: "position is not finite".into(),
            });
        }
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if !(len.is_finite() && len > 0.0) {
            return Err(PoissonError::BadPoint {
                index,
                what: format!("normal {n:?} is zero or not finite"),
            });
        }
        unit_normals.push(n.map(|v| v / len));
    }
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    if !(extent > 0.0 && extent.is_finite()) {
        return Err(PoissonError::NoExtent);
    }
    let side = extent * options.scale;
    let origin: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]) - 0.5 * side);
    let samples = Samples {
        points: points
            .iter()
            .map(|p| std::array::from_fn(|a| (p[a] - origin[a]) / side))
            .collect(),
        splat_depth: Vec::new(),
        normals: unit_normals,
    };
    let samples = Samples {
        splat_depth: splat_depths(&samples.points, options.depth, options.samples_per_node),
        ..samples
    };
    let area_per_sample = area_per_sample(&samples.points, options.depth);
    let depth = options.depth;
    let base = depth.min(BASE_DEPTH);
    let mut level = Level { res: 1 << base };
    let beta_at = |l: Level| options.screening * area_per_sample * l.res as f64;
    let mut chi = vec![0.0; level.count()];
    let (mut iterations, mut residual, _) = solve_level(
        level,
        &samples,
        beta_at(level),
        &mut chi,
        Stop {
            band: None,
            tolerance: BASE_TOLERANCE,
            max_iterations: BASE_MAX_ITERATIONS,
            relative_to_start: false,
        },
    );
    let mut active_nodes = level.count();
    for _ in base..depth {
        chi = prolong(level, &chi);
        level = Level { res: level.res * 2 };
        let (it, res, active) = solve_level(
            level,
            &samples,
            beta_at(level),
            &mut chi,
            Stop {
                band: Some(BAND),
                tolerance: LEVEL_TOLERANCE,
                max_iterations: LEVEL_MAX_ITERATIONS,
                relative_to_start: true,
            },
        );
        iterations += it;
        residual = res;
        active_nodes = active;
    }
    let iso_value = samples
        .points
        .iter()
        .map(|u| interpolate(level, &chi, u))
        .sum::<f64>()
        / samples.points.len() as f64;
    let h = side / level.res as f64;
    let mut surface = marching_cubes(
        ScalarGrid {
            values: &chi,
            dims: [level.nodes(); 3],
            origin,
            spacing: h,
        },
        iso_value,
    )?;
    let mut trimmed_vertices = 0;
    if options.density_trim > 0.0 && !surface.positions.is_empty() {
        let coarse = Level {
            res: 1 << depth.saturating_sub(DENSITY_LEVELS).max(1),
        };
        let mut density = vec![0.0; coarse.count()];
        for u in &samples.points {
            let (_, c) = coarse.corners(u);
            for (g, w) in c {
                density[g] += w;
            }
        }
        let at_vertex: Vec<f64> = surface
            .positions
            .iter()
            .map(|p| {
                let u: [f64; 3] = std::array::from_fn(|a| (p[a] - origin[a]) / side);
                interpolate(coarse, &density, &u)
            })
            .collect();
        let mut sorted = at_vertex.clone();
        sorted.sort_by(f64::total_cmp);
        let cut =
            sorted[((options.density_trim * sorted.len() as f64) as usize).min(sorted.len() - 1)];
        let keep: Vec<bool> = at_vertex.iter().map(|&d| d >= cut).collect();
        trimmed_vertices = keep.iter().filter(|k| !**k).count();
        surface = remove_vertices(&surface, &keep);
    }
    Ok(PoissonReport {
        surface,
        iterations,
        residual,
        iso_value,
        active_nodes,
        trimmed_vertices,
    })
}

/// `A / N` in unit-cube units (see the module documentation).
fn area_per_sample(points: &[[f64; 3]], depth: u32) -> f64 {
    let n = points.len() as f64;
    let mut level = depth;
    loop {
        let l = Level { res: 1 << level };
        let mut cells: Vec<[usize; 3]> = points.iter().map(|u| l.corners(u).0).collect();
        cells.par_sort_unstable();
        cells.dedup();
        let occupied = cells.len() as f64;
        if n >= SAMPLES_PER_AREA_CELL * occupied || level <= 1 {
            let h = 1.0 / l.res as f64;
            return occupied * h * h / 1.5 / n;
        }
        level -= 1;
    }
}

/// The surface without the vertices where `keep` is false and the triangles using them.
fn remove_vertices(s: &IsoSurface, keep: &[bool]) -> IsoSurface {
    let mut map = vec![u32::MAX; s.positions.len()];
    let mut out = IsoSurface::default();
    for (i, p) in s.positions.iter().enumerate() {
        if keep[i] {
            map[i] = out.positions.len() as u32;
            out.positions.push(*p);
        }
    }
    out.triangles = s
        .triangles
        .iter()
        .filter_map(|t| {
            let m = t.map(|i| map[i as usize]);
            (!m.contains(&u32::MAX)).then_some(m)
        })
        .collect();
    out
}

/// Area-weighted vertex normals of a surface (unit; `[0, 0, 1]` where undefined).
pub fn vertex_normals(s: &IsoSurface) -> Vec<[f64; 3]> {
    let mut acc = vec![[0.0f64; 3]; s.positions.len()];
    for t in &s.triangles {
        let [a, b, c] = t.map(|i| s.positions[i as usize]);
        let u = [0, 1, 2].map(|k| b[k] - a[k]);
        let v = [0, 1, 2].map(|k| c[k] - a[k]);
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        for &i in t {
            for k in 0..3 {
                acc[i as usize][k] += n[k];
            }
        }
    }
    acc.iter()
        .map(|n| {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len > 0.0 && len.is_finite() {
                n.map(|v| v / len)
            } else {
                [0.0, 0.0, 1.0]
            }
        })
        .collect()
}

params! {
    /// Parameters of `mesh.poisson`.
    pub struct PoissonParams {
        /// Grid resolution: 2^depth cells per axis over the padded bounding cube (depth 8: 256³
        /// cells). At most 9. Default 8.
        depth: u32 = 8 => [min = 1, max = 9],
        /// Screening weight α of the sample-interpolation term (0: unscreened Poisson, KBH06).
        /// Default 4, as PoissonRecon.
        screening: f64 = 4.0 => [min = 0.0],
        /// Side of the reconstruction cube over the points' largest extent. Default 1.1.
        scale: f64 = 1.1 => [min = 1.0, max = 100.0],
        /// Removes the vertices whose sample density is below this quantile of all vertices'
        /// densities (0: keep everything, a closed surface). Default 0.
        density_trim: f64 = 0.0 => [min = 0.0, max = 1.0],
        /// Adaptive splatting: each normal is splatted at the finest depth where the density
        /// of points around it reaches this many per cell (up to 2 levels coarser), smoothing
        /// the field where points are sparse for the grid (PoissonRecon's `--samplesPerNode`);
        /// 0: always at the solved depth. Higher smooths noisy, sparse scans more at high
        /// depth. Default 0.5.
        samples_per_node: f64 = 0.5 => [min = 0.0, max = 1e6],
    }
}

/// Screened Poisson surface reconstruction (`mesh.poisson`). See [`reconstruct`].
#[derive(Debug, Clone, PartialEq)]
pub struct Poisson {
    options: PoissonOptions,
}

impl Op for Poisson {
    type Params = PoissonParams;
    const ID: &'static str = "mesh.poisson";
    const SUMMARY: &'static str = "Reconstructs a watertight surface from oriented points by screened Poisson reconstruction.";
    const DOC: &'static str = r#"
Fits an implicit function χ whose gradient matches the points' normals and whose value at the
points is constant, and returns its level set through the points: screened Poisson surface
reconstruction.

The points are scaled into their bounding cube enlarged by `scale`, split into 2^depth cells per
axis. The normals are splatted onto the grid nodes with trilinear weights into a vector field V
— each at the finest depth where the density of points around it reaches `samples_per_node`
per cell (up to 2 levels coarser: adaptive splatting, so sparse points do not make the fine
levels follow their noise),
and χ minimises ∫|∇χ − V|² + α·(A/N)·Σ χ(p)² (A/N the surface area per point, estimated from
occupied cells): a Laplacian against the divergence of V, plus the screening term at the
points. The system is solved coarse to fine by Jacobi-preconditioned conjugate gradients: on the
whole grid at depth 5, then at each finer depth only within 3 cells of the points, starting from
the prolonged coarser solution (a narrow band that plays the role of the paper's octree). The
surface is the level set χ = mean of χ at the points, extracted by marching cubes with the
asymptotic decider: closed, watertight, triangles counter-clockwise seen from outside, with
area-weighted vertex normals. `density_trim` > 0 removes the vertices whose density of nearby
points (a splat four levels coarser) is below that quantile, opening the surface where data is
missing (Open3D's density trimming).

Needs at least 4 points with normals (mesh.estimate_normals with orientation "consistent" gives
them); normals are normalised, zero or non-finite ones are errors. Results do not depend on the
thread count.

Metrics: `vertices`, `triangles`, `iterations` (conjugate-gradient iterations, all levels),
`residual` (relative residual of the finest level), `iso_value`, `active_nodes` (nodes solved
at the finest level), `trimmed_vertices`.

References: Kazhdan, Bolitho & Hoppe, "Poisson surface reconstruction", SGP 2006; Kazhdan &
Hoppe, "Screened Poisson surface reconstruction", ACM TOG 32(3), 2013; Nielson & Hamann, "The
asymptotic decider", Visualization 1991.

Example:
    "poisson": (op: "mesh.poisson", inputs: { "cloud": "points.cloud" }, params: (depth: 8, screening: 4.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "cloud",
            PortType::PointCloud,
            "Oriented points: positions with outward normals.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The reconstructed surface with vertex normals.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "vertices, triangles, iterations, residual, iso_value, active_nodes, trimmed_vertices.",
            ),
        ]
    }

    fn new(p: PoissonParams) -> Result<Self, String> {
        let options = PoissonOptions {
            depth: p.depth,
            screening: p.screening,
            scale: p.scale,
            density_trim: p.density_trim,
            samples_per_node: p.samples_per_node,
        };
        options.check().map_err(|e| e.to_string())?;
        Ok(Poisson { options })
    }
}

/// The positions and normals of an oriented cloud.
pub fn oriented_points(cloud: &PointCloud) -> Result<OrientedPoints, OpError> {
    let points = positions_f64(cloud).map_err(|e| e.at("cloud"))?;
    let normals = cloud
        .normals
        .as_ref()
        .ok_or_else(|| OpError::input("cloud", PoissonError::NoNormals.to_string()))?;
    Ok((points, normals.iter().map(|n| n.map(f64::from)).collect()))
}

/// The engine mesh of a surface, with vertex normals.
pub fn to_mesh(surface: &IsoSurface) -> Mesh {
    Mesh {
        positions: surface
            .positions
            .iter()
            .map(|p| p.map(|v| v as f32))
            .collect(),
        triangles: surface.triangles.clone(),
        normals: Some(
            vertex_normals(surface)
                .iter()
                .map(|n| n.map(|v| v as f32))
                .collect(),
        ),
        uvs: None,
        colors: None,
        tangents: None,
    }
}

impl Operator for Poisson {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let cloud = cloud_input(inputs, "cloud")?;
        let (points, normals) = oriented_points(cloud)?;
        let report = reconstruct(&points, &normals, &self.options).map_err(|e| match e {
            PoissonError::Param(m) => OpError::failed(m),
            other => OpError::input("cloud", other.to_string()),
        })?;
        let mut m = Metrics::new();
        m.insert("vertices".into(), report.surface.positions.len() as f64);
        m.insert("triangles".into(), report.surface.triangles.len() as f64);
        m.insert("iterations".into(), report.iterations as f64);
        m.insert("residual".into(), report.residual);
        m.insert("iso_value".into(), report.iso_value);
        m.insert("active_nodes".into(), report.active_nodes as f64);
        m.insert("trimmed_vertices".into(), report.trimmed_vertices as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(to_mesh(&report.surface))))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wide_splats_are_partitions_of_unity_with_linear_precision() {
        // Every tent sums to 1 and reproduces the point (first moment), at every coarsening.
        let level = Level { res: 64 };
        let mut nodes = Vec::new();
        for u in [[0.5, 0.5, 0.5], [0.2031, 0.7777, 0.4], [0.3, 0.30001, 0.61]] {
            for k in 0..=MAX_SPLAT_COARSENING {
                splat_nodes(level, &u, k, &mut nodes);
                assert!(nodes.len() <= (2usize << k).pow(3));
                let sum: f64 = nodes.iter().map(|n| n.1).sum();
                assert!((sum - 1.0).abs() < 1e-12, "k {k}: {sum}");
                let n = level.nodes();
                for a in 0..3 {
                    let moment: f64 = nodes
                        .iter()
                        .map(|&(g, w)| {
                            let c = [g % n, (g / n) % n, g / (n * n)][a];
                            w * c as f64 / level.res as f64
                        })
                        .sum();
                    assert!((moment - u[a]).abs() < 1e-12, "k {k} axis {a}");
                }
            }
        }
    }

    #[test]
    fn splat_depth_follows_the_local_sample_count() {
        // 64 samples in one depth-6 cell and one isolated sample: the cluster splats at the
        // finest depth where its cells hold ≥ 2 of them, the lone sample at depth 0 (only the
        // root cell holds it with others).
        let mut points: Vec<[f64; 3]> = (0..64)
            .map(|i| {
                let (x, y, z) = (i % 4, (i / 4) % 4, i / 16);
                [
                    0.5 + 0.003 * x as f64,
                    0.5 + 0.003 * y as f64,
                    0.5 + 0.003 * z as f64,
                ]
            })
            .collect();
        points.push([0.9, 0.1, 0.1]);
        let d = splat_depths(&points, 8, 1.5);
        // Alone, the sample's own weight is at most 1 < 1.5 at every level until the root
        // cell's corners gather the cluster's weight too.
        assert!(d[64] <= 1, "{}", d[64]);
        // At depth 8 (cells of 1/256 ≈ 0.0039) neighbours 0.003 apart: about 2 samples per
        // cell around each (1.5 reached at depth 8 or 7); at depth 6 the cluster is dense.
        assert!(d[..64].iter().all(|&v| v >= 7), "{:?}", &d[..64]);
        // A threshold no sample's own weight can miss keeps everything at depth; 0 disables.
        assert!(splat_depths(&points, 8, 0.125).iter().all(|&v| v == 8));
        assert!(splat_depths(&points, 8, 0.0).iter().all(|&v| v == 8));
    }
    use crate::describe::brief::SplitMix64;
    use crate::mesh::marching_cubes::tests::{chamfer, closed_euler, volume};

    /// `n` points on a sphere with outward normals, positions displaced along the normal by
    /// Gaussian noise of standard deviation `noise`.
    fn noisy_sphere(
        n: usize,
        c: [f64; 3],
        r: f64,
        noise: f64,
        seed: u64,
    ) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let on = crate::mesh::pointcloud::tests::sphere(n, c, r, seed);
        let mut rng = SplitMix64::new(seed + 1);
        let normals: Vec<[f64; 3]> = on
            .iter()
            .map(|p| [0, 1, 2].map(|a| (p[a] - c[a]) / r))
            .collect();
        let points = on
            .iter()
            .zip(&normals)
            .map(|(p, n)| {
                let e = noise * rng.normal();
                [0, 1, 2].map(|a| p[a] + e * n[a])
            })
            .collect();
        (points, normals)
    }

    #[test]
    fn noisy_sphere_is_reconstructed_within_a_fraction_of_a_cell() {
        let (c, r) = ([0.3, -0.2, 0.1], 1.0);
        let (points, normals) = noisy_sphere(20_000, c, r, 0.005, 21);
        let options = PoissonOptions {
            depth: 6,
            ..PoissonOptions::default()
        };
        let report = reconstruct(&points, &normals, &options).unwrap();
        let s = &report.surface;
        assert_eq!(closed_euler(s), Ok(2));
        assert!(volume(s) > 0.0);
        let h = 2.0 * r * options.scale / 64.0;
        let truth = crate::mesh::pointcloud::tests::sphere(5000, c, r, 77);
        let dist = |p: &[f64; 3]| {
            ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt() - r
        };
        let [mean_a, max_a, mean_b, max_b] = chamfer(s, |p| dist(p).abs(), &truth, 100_000);
        eprintln!(
            "sphere: h {h} chamfer {mean_a} {max_a} {mean_b} {max_b}, {report:?}",
            report = (
                report.iterations,
                report.residual,
                report.iso_value,
                report.active_nodes
            )
        );
        assert!(mean_a + mean_b < 0.2 * h, "{mean_a} {mean_b} (h = {h})");
        assert!(max_a < h && max_b < h, "{max_a} {max_b}");
    }

    #[test]
    fn noisy_torus_is_reconstructed_with_its_hole() {
        let (big, small) = (1.0, 0.4);
        let mut rng = SplitMix64::new(5);
        let mut points = Vec::new();
        let mut normals = Vec::new();
        while points.len() < 30_000 {
            let (u, v) = (
                rng.uniform() * std::f64::consts::TAU,
                rng.uniform() * std::f64::consts::TAU,
            );
            // Area-uniform: accept with probability ∝ the local radius.
            if rng.uniform() * (big + small) > big + small * v.cos() {
                continue;
            }
            let n = [v.cos() * u.cos(), v.cos() * u.sin(), v.sin()];
            let e = 0.004 * rng.normal();
            let rr = big + small * v.cos();
            points.push([
                rr * u.cos() + e * n[0],
                rr * u.sin() + e * n[1],
                small * v.sin() + e * n[2],
            ]);
            normals.push(n);
        }
        let options = PoissonOptions {
            depth: 6,
            ..PoissonOptions::default()
        };
        let report = reconstruct(&points, &normals, &options).unwrap();
        let s = &report.surface;
        assert_eq!(closed_euler(s), Ok(0));
        let h = 2.0 * (big + small) * options.scale / 64.0;
        let dist = |p: &[f64; 3]| {
            (((p[0] * p[0] + p[1] * p[1]).sqrt() - big).powi(2) + p[2] * p[2]).sqrt() - small
        };
        let truth: Vec<[f64; 3]> = (0..5000)
            .map(|_| {
                let (u, v) = (
                    rng.uniform() * std::f64::consts::TAU,
                    rng.uniform() * std::f64::consts::TAU,
                );
                let rr = big + small * v.cos();
                [rr * u.cos(), rr * u.sin(), small * v.sin()]
            })
            .collect();
        let [mean_a, max_a, mean_b, max_b] = chamfer(s, |p| dist(p).abs(), &truth, 100_000);
        eprintln!("torus: h {h} chamfer {mean_a} {max_a} {mean_b} {max_b}");
        assert!(mean_a + mean_b < 0.2 * h, "{mean_a} {mean_b} (h = {h})");
        assert!(max_a < h && max_b < h, "{max_a} {max_b}");
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let (points, normals) = noisy_sphere(3000, [0.0; 3], 1.0, 0.01, 3);
        let options = PoissonOptions {
            depth: 6,
            density_trim: 0.1,
            ..PoissonOptions::default()
        };
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| reconstruct(&points, &normals, &options).unwrap())
        };
        let (one, three) = (run(1), run(3));
        assert_eq!(one, three);
        assert!(one.trimmed_vertices > 0);
    }

    #[test]
    fn density_trimming_opens_the_surface_where_points_are_missing() {
        // A hemisphere's points: untrimmed, the far side is closed by a smooth cap; trimmed,
        // the cap's vertices (far from any point) go.
        let (all, all_n) = noisy_sphere(8000, [0.0; 3], 1.0, 0.0, 9);
        let (points, normals): (Vec<_>, Vec<_>) = all
            .into_iter()
            .zip(all_n)
            .filter(|(p, _)| p[2] > 0.0)
            .unzip();
        let base = PoissonOptions {
            depth: 5,
            ..PoissonOptions::default()
        };
        let closed = reconstruct(&points, &normals, &base).unwrap();
        assert_eq!(closed.trimmed_vertices, 0);
        let trimmed = reconstruct(
            &points,
            &normals,
            &PoissonOptions {
                density_trim: 0.3,
                ..base
            },
        )
        .unwrap();
        assert!(trimmed.trimmed_vertices > 0);
        let low = |s: &IsoSurface| s.positions.iter().filter(|p| p[2] < -0.5).count();
        let (kept, all) = (low(&trimmed.surface), low(&closed.surface));
        assert!(all > 20 && kept < all / 4, "{kept} of {all}");
    }

    #[test]
    fn bad_input_and_options_are_errors() {
        let (points, normals) = noisy_sphere(100, [0.0; 3], 1.0, 0.0, 1);
        let o = PoissonOptions::default();
        assert!(matches!(
            reconstruct(&points[..3], &normals[..3], &o),
            Err(PoissonError::TooFewPoints { needed: 4, got: 3 })
        ));
        let mut bad = normals.clone();
        bad[7] = [0.0; 3];
        assert!(matches!(
            reconstruct(&points, &bad, &o),
            Err(PoissonError::BadPoint { index: 7, .. })
        ));
        let mut nan = points.clone();
        nan[2][1] = f64::NAN;
        assert!(matches!(
            reconstruct(&nan, &normals, &o),
            Err(PoissonError::BadPoint { index: 2, .. })
        ));
        let same = vec![[1.0; 3]; 10];
        assert_eq!(
            reconstruct(&same, &normals[..10], &o),
            Err(PoissonError::NoExtent)
        );
        for bad in [
            PoissonOptions { depth: 10, ..o },
            PoissonOptions { depth: 0, ..o },
            PoissonOptions {
                screening: f64::NAN,
                ..o
            },
            PoissonOptions { scale: 0.9, ..o },
            PoissonOptions {
                samples_per_node: f64::NAN,
                ..o
            },
            PoissonOptions {
                density_trim: 1.0,
                ..o
            },
        ] {
            assert!(
                matches!(
                    reconstruct(&points, &normals, &bad),
                    Err(PoissonError::Param(_))
                ),
                "{bad:?}"
            );
        }
        let cloud = PointCloud {
            positions: points.iter().map(|p| p.map(|v| v as f32)).collect(),
            colors: None,
            normals: None,
        };
        let err = oriented_points(&cloud).unwrap_err();
        assert!(err.to_string().contains("no normals"), "{err}");
    }
}
