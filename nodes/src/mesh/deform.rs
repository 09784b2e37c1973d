//! Handle-based deformation with hard positional constraints: `mesh.deform`.
//!
//! Some vertices (the *handles*) are given new positions, some (the *fixed* vertices) keep
//! theirs; every other vertex follows so that the surface keeps its local shape. Constrained
//! vertices land exactly on their targets: they are eliminated from the linear systems, which
//! are solved for the free vertices only (a sparse Cholesky factorization from `faer`, AMD
//! ordering, factored once and reused for every right-hand side).
//!
//! - [`DeformMethod::Laplacian`]: linear Laplacian surface editing in its plain form (Sorkine,
//!   Cohen-Or, Lipman, Alexa, Rössl & Seidel, "Laplacian surface editing", SGP 2004): minimize
//!   `‖L x − δ‖²`, `δ = L p` the differential coordinates of the rest shape `p`, over the free
//!   vertices, where `L` is the row-normalized Laplacian `(L x)ᵢ = xᵢ − Σⱼ wᵢⱼ xⱼ / Σⱼ wᵢⱼ`
//!   (every vertex's row, the constrained ones included). Written in displacements `d = x − p`
//!   this is `min ‖L d‖²`, whose normal equations `(LᵀL)_FF d_F = −(LᵀL)_FC d_C` are solved.
//!   Linear and fast, but `δ` is not rotated with the surface, so large rotations of the handles
//!   shear and shrink the details.
//! - [`DeformMethod::Arap`]: as-rigid-as-possible surface modeling (Sorkine & Alexa, "As-rigid-
//!   as-possible surface modeling", SGP 2007): minimize
//!   `E(x) = Σᵢ min_{Rᵢ ∈ SO(3)} Σ_{j ∈ N(i)} wᵢⱼ ‖(xᵢ − xⱼ) − Rᵢ (pᵢ − pⱼ)‖²` by alternating a
//!   local step (each cell's best rotation, from the SVD of `Sᵢ = Σⱼ wᵢⱼ (pᵢ − pⱼ)(xᵢ − xⱼ)ᵀ`
//!   with the reflection fixed on the smallest singular value) and a global step (the
//!   prefactored Laplacian system `Σⱼ wᵢⱼ (xᵢ − xⱼ) = Σⱼ wᵢⱼ/2 (Rᵢ + Rⱼ)(pᵢ − pⱼ)` for the free
//!   vertices). Both steps minimize the same energy exactly, so `E` never increases. The
//!   iteration starts from the Laplacian-editing result (with the same weights) and stops after
//!   `iterations` global steps or when one step lowers `E` by at most `tolerance · E`.
//!
//! Edge weights ([`DeformWeights`]): uniform `wᵢⱼ = 1`, or cotangent `wᵢⱼ = (cot αᵢⱼ + cot βᵢⱼ)/2`
//! over the angles opposite the edge (one angle on the boundary). Cotangent weights of very
//! obtuse (non-Delaunay) edges are negative or zero; they are raised to
//! [`COTANGENT_FLOOR`]` × ` the mean positive weight so that the energy stays a sum of squares
//! and the ARAP system positive definite (with no positive weight at all, uniform weights are
//! used).
//!
//! A connected component without any constrained vertex leaves the systems singular (it could
//! float anywhere): that is an error ([`DeformError::UnconstrainedComponent`]), or, with
//! [`Unconstrained::Keep`], the whole component is pinned where it is. Vertices used by no
//! triangle keep their position (or move to their target when they are handles).
//!
//! Every per-vertex step runs in parallel but writes only its own vertex; sums run in index
//! order and the factorization is sequential, so results do not depend on the thread count.

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{
    LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, MatMut, Par, Side};
use nalgebra::{Matrix3, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::halfedge::{NONE, halfedge_of, mesh_input};
use super::normals::{NormalWeighting, cross, dot, norm, sub, vertex_normals};
use super::pointcloud::{par_map, positions_f64};

/// Cotangent weights below this fraction of the mean positive weight are raised to it.
pub const COTANGENT_FLOOR: f64 = 1e-4;

/// Iteration cap of one 3 × 3 SVD (it converges in a handful).
const SVD_MAX_ITERATIONS: usize = 100;

param_enum! {
    /// The deformation energy of `mesh.deform`.
    pub enum DeformMethod {
        /// Linear Laplacian surface editing (Sorkine et al. 2004).
        Laplacian = "laplacian",
        /// As-rigid-as-possible (Sorkine & Alexa 2007), started from the Laplacian result.
        Arap = "arap",
    }
}

param_enum! {
    /// Edge weights of `mesh.deform`.
    pub enum DeformWeights {
        /// Every edge alike.
        Uniform = "uniform",
        /// Cotangent weights (floored at a small positive value).
        Cotangent = "cotangent",
    }
}

param_enum! {
    /// What `mesh.deform` does with a connected component that has no constrained vertex.
    pub enum Unconstrained {
        /// Fail: the system is singular there.
        Error = "error",
        /// Pin every vertex of the component where it is.
        Keep = "keep",
    }
}

/// Why a deformation could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeformError {
    /// No handle was given.
    #[error(
        "no handles: list the vertices to move in `handles` and their new positions in `targets`"
    )]
    NoHandles,
    /// `handles` and `targets` differ in length.
    #[error("{handles} handles but {targets} targets: give one target per handle")]
    LengthMismatch {
        /// Number of handles.
        handles: usize,
        /// Number of targets.
        targets: usize,
    },
    /// A handle or fixed vertex does not exist.
    #[error("`{list}`[{position}] is vertex {vertex}, but the mesh has {vertices} vertices")]
    IndexOutOfRange {
        /// `handles` or `fixed`.
        list: &'static str,
        /// Position in the list.
        position: usize,
        /// The bad index.
        vertex: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// A target holds NaN or an infinity.
    #[error("target {position} (of handle {vertex}) is not finite")]
    NonFiniteTarget {
        /// Position in the list.
        position: usize,
        /// The handle.
        vertex: u32,
    },
    /// One vertex was given two different targets (twice in `handles`, or in `handles` with a
    /// target other than its position and in `fixed`).
    #[error("vertex {vertex} is constrained twice with different targets {first:?} and {second:?}")]
    ConflictingTargets {
        /// The vertex.
        vertex: u32,
        /// One target.
        first: [f64; 3],
        /// The other.
        second: [f64; 3],
    },
    /// A connected component has no constrained vertex, so its position is undetermined.
    #[error(
        "the connected component of vertex {vertex} ({vertices} vertices) has no handle or fixed \
         vertex, so the deformation system is singular there; constrain one of its vertices, or \
         set `unconstrained: \"keep\"` to leave it in place"
    )]
    UnconstrainedComponent {
        /// Its smallest vertex index.
        vertex: u32,
        /// Its number of vertices.
        vertices: usize,
    },
    /// A rest position holds NaN or an infinity.
    #[error("vertex {vertex} is not finite")]
    NonFiniteVertex {
        /// The vertex.
        vertex: usize,
    },
    /// A triangle refers to a missing vertex or uses one vertex twice.
    #[error("triangle {triangle} = {corners:?} is invalid for {vertices} vertices")]
    BadTriangle {
        /// The triangle.
        triangle: usize,
        /// Its corners.
        corners: [u32; 3],
        /// Number of vertices.
        vertices: usize,
    },
    /// The linear system could not be factored or solved.
    #[error("{0}")]
    Solver(String),
}

/// Hard positional constraints: vertices ascending, each with its target.
#[derive(Debug, Clone, PartialEq)]
pub struct Constraints {
    vertices: Vec<u32>,
    targets: Vec<[f64; 3]>,
}

impl Constraints {
    /// Handles moved to `targets` (same length) and `fixed` vertices kept at their `rest`
    /// positions. A vertex may repeat with the same target; different targets are an error.
    pub fn new(
        rest: &[[f64; 3]],
        handles: &[u32],
        targets: &[[f64; 3]],
        fixed: &[u32],
    ) -> Result<Constraints, DeformError> {
        if handles.is_empty() {
            return Err(DeformError::NoHandles);
        }
        if handles.len() != targets.len() {
            return Err(DeformError::LengthMismatch {
                handles: handles.len(),
                targets: targets.len(),
            });
        }
        let n = rest.len();
        let mut all: Vec<(u32, [f64; 3])> = Vec::with_capacity(handles.len() + fixed.len());
        for (list, indices) in [("handles", handles), ("fixed", fixed)] {
            for (position, &vertex) in indices.iter().enumerate() {
                if vertex as usize >= n {
                    return Err(DeformError::IndexOutOfRange {
                        list,
                        position,
                        vertex,
                        vertices: n,
                    });
                }
                let target = if list == "handles" {
                    let t = targets[position];
                    if !t.iter().all(|v| v.is_finite()) {
                        return Err(DeformError::NonFiniteTarget { position, vertex });
                    }
                    t
                } else {
                    rest[vertex as usize]
                };
                all.push((vertex, target));
            }
        }
        all.sort_by_key(|c| c.0);
        let mut vertices: Vec<u32> = Vec::with_capacity(all.len());
        let mut out: Vec<[f64; 3]> = Vec::with_capacity(all.len());
        for (vertex, target) in all {
            if let (Some(&last), Some(&prev)) = (vertices.last(), out.last())
                && last == vertex
            {
                if prev != target {
                    return Err(DeformError::ConflictingTargets {
                        vertex,
                        first: prev,
                        second: target,
                    });
                }
                continue;
            }
            vertices.push(vertex);
            out.push(target);
        }
        Ok(Constraints {
            vertices,
            targets: out,
        })
    }

    /// The constrained vertices, ascending.
    pub fn vertices(&self) -> &[u32] {
        &self.vertices
    }

    /// Their targets.
    pub fn targets(&self) -> &[[f64; 3]] {
        &self.targets
    }
}

/// Options of [`deform`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeformOptions {
    /// The energy.
    pub method: DeformMethod,
    /// Edge weights (of both the Laplacian and the ARAP energy).
    pub weights: DeformWeights,
    /// ARAP: most global steps.
    pub iterations: u32,
    /// ARAP: stop when a step lowers the energy by at most `tolerance ·` energy.
    pub tolerance: f64,
    /// Components without constraints.
    pub unconstrained: Unconstrained,
}

impl Default for DeformOptions {
    fn default() -> Self {
        DeformOptions {
            method: DeformMethod::Arap,
            weights: DeformWeights::Cotangent,
            iterations: 10,
            tolerance: 1e-6,
            unconstrained: Unconstrained::Error,
        }
    }
}

/// The result of [`deform`].
#[derive(Debug, Clone, PartialEq)]
pub struct Deformed {
    /// New positions; constrained vertices exactly at their targets.
    pub positions: Vec<[f64; 3]>,
    /// The ARAP energy (with the chosen weights) of the Laplacian result, then after every ARAP
    /// iteration (one entry for the Laplacian method).
    pub energies: Vec<f64>,
    /// ARAP iterations performed.
    pub iterations: usize,
    /// Vertices pinned because their component had no constraint ([`Unconstrained::Keep`]).
    pub pinned: usize,
}

/// The weighted edge graph of a triangle mesh: both directions, neighbours ascending.
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeGraph {
    start: Vec<usize>,
    neighbour: Vec<u32>,
    weight: Vec<f64>,
}

/// The cotangent of the angle at `p` between `q − p` and `r − p` (0 when degenerate).
fn cot(p: [f64; 3], q: [f64; 3], r: [f64; 3]) -> f64 {
    let (u, v) = (sub(q, p), sub(r, p));
    let s = norm(cross(u, v));
    let c = if s > 0.0 { dot(u, v) / s } else { 0.0 };
    if c.is_finite() { c } else { 0.0 }
}

impl EdgeGraph {
    /// The edges of `triangles` (checked by the caller) with `weights` on `positions`.
    pub fn new(
        positions: &[[f64; 3]],
        triangles: &[[u32; 3]],
        weights: DeformWeights,
    ) -> EdgeGraph {
        let n = positions.len();
        let mut half: Vec<(u64, f64)> = Vec::with_capacity(3 * triangles.len());
        for t in triangles {
            for k in 0..3 {
                let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
                let key = (u64::from(a.min(b)) << 32) | u64::from(a.max(b));
                let w = match weights {
                    DeformWeights::Uniform => 1.0,
                    DeformWeights::Cotangent => {
                        let p = |i: u32| positions[i as usize];
                        0.5 * cot(p(c), p(a), p(b))
                    }
                };
                half.push((key, w));
            }
        }
        half.sort_by_key(|e| e.0);
        let mut edges: Vec<(u64, f64)> = Vec::with_capacity(half.len() / 2 + 1);
        for (key, w) in half {
            match edges.last_mut() {
                Some(last) if last.0 == key => last.1 += w,
                _ => edges.push((key, w)),
            }
        }
        match weights {
            DeformWeights::Uniform => edges.iter_mut().for_each(|e| e.1 = 1.0),
            DeformWeights::Cotangent => {
                let (mut sum, mut count) = (0.0, 0usize);
                for e in &edges {
                    if e.1 > 0.0 {
                        sum += e.1;
                        count += 1;
                    }
                }
                if count == 0 {
                    edges.iter_mut().for_each(|e| e.1 = 1.0);
                } else {
                    let floor = COTANGENT_FLOOR * sum / count as f64;
                    edges.iter_mut().for_each(|e| e.1 = e.1.max(floor));
                }
            }
        }
        let split = |key: u64| ((key >> 32) as usize, (key & 0xffff_ffff) as usize);
        let mut start = vec![0usize; n + 1];
        for &(key, _) in &edges {
            let (a, b) = split(key);
            start[a + 1] += 1;
            start[b + 1] += 1;
        }
        for i in 0..n {
            start[i + 1] += start[i];
        }
        let mut fill = start.clone();
        let mut neighbour = vec![0u32; start[n]];
        let mut weight = vec![0.0; start[n]];
        // Edges ascend by (smaller, larger) end: every row gets its smaller neighbours first, then
        // its larger ones, each ascending.
        for &(key, w) in &edges {
            let (a, b) = split(key);
            for (from, to) in [(a, b), (b, a)] {
                neighbour[fill[from]] = to as u32;
                weight[fill[from]] = w;
                fill[from] += 1;
            }
        }
        EdgeGraph {
            start,
            neighbour,
            weight,
        }
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.start.len() - 1
    }

    /// Whether there is no vertex.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The neighbours of `v` (ascending) and the weights of their edges.
    pub fn row(&self, v: usize) -> (&[u32], &[f64]) {
        let r = self.start[v]..self.start[v + 1];
        (&self.neighbour[r.clone()], &self.weight[r])
    }

    /// Sum of the weights of `v`'s edges.
    fn weight_sum(&self, v: usize) -> f64 {
        self.row(v).1.iter().sum()
    }
}

/// A sparse Cholesky factor `A = L Lᵀ` of a symmetric positive definite matrix (faer, AMD
/// ordering, sequential).
struct Cholesky {
    n: usize,
    symbolic: SymbolicCholesky<usize>,
    factor: Vec<f64>,
}

impl Cholesky {
    /// `columns[j]`: the lower-triangle entries `(row, value)` of column `j`, rows ascending
    /// (the diagonal first). `what` names the matrix in errors.
    fn new(columns: Vec<Vec<(u32, f64)>>, what: &str) -> Result<Cholesky, DeformError> {
        let n = columns.len();
        let nnz = columns.iter().map(Vec::len).sum();
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(nnz);
        let mut values = Vec::with_capacity(nnz);
        col_ptr.push(0);
        for column in &columns {
            for &(r, v) in column {
                row_idx.push(r as usize);
                values.push(v);
            }
            col_ptr.push(row_idx.len());
        }
        let pattern = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        let symbolic = factorize_symbolic_cholesky(
            pattern.as_ref(),
            Side::Lower,
            SymmetricOrdering::Amd,
            Default::default(),
        )
        .map_err(|e| DeformError::Solver(format!("{what}: symbolic Cholesky failed: {e:?}")))?;
        let mut factor = vec![0.0; symbolic.len_val()];
        let scratch = symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default());
        let mut memory = MemBuffer::try_new(scratch)
            .map_err(|_| DeformError::Solver(format!("{what}: out of memory")))?;
        symbolic
            .factorize_numeric_llt::<f64>(
                &mut factor,
                SparseColMatRef::new(pattern.as_ref(), &values),
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut memory),
                Default::default(),
            )
            .map_err(|_| {
                DeformError::Solver(format!(
                    "{what} is not numerically positive definite (degenerate triangles?)"
                ))
            })?;
        Ok(Cholesky {
            n,
            symbolic,
            factor,
        })
    }

    /// Solves `A X = B` in place for `B` of `n` rows and 3 columns (column-major).
    fn solve3(&self, rhs: &mut [f64]) -> Result<(), DeformError> {
        let scratch = self.symbolic.solve_in_place_scratch::<f64>(3, Par::Seq);
        let mut memory = MemBuffer::try_new(scratch)
            .map_err(|_| DeformError::Solver("solve: out of memory".into()))?;
        LltRef::new(&self.symbolic, &self.factor).solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(rhs, self.n, 3),
            Par::Seq,
            MemStack::new(&mut memory),
        );
        if rhs.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(DeformError::Solver(
                "the solution is not finite (ill-conditioned system)".into(),
            ))
        }
    }
}

/// The rotation `R` maximizing `tr(R S)` (so minimizing `Σ w ‖e′ − R e‖²` for
/// `S = Σ w e e′ᵀ`): `V D Uᵀ` from `S = U Σ Vᵀ`, `D` flipping the smallest singular direction
/// when `V Uᵀ` is a reflection. Identity if the SVD does not converge.
pub fn best_rotation(s: &Matrix3<f64>) -> Matrix3<f64> {
    let Some(svd) = s.try_svd(true, true, f64::EPSILON, SVD_MAX_ITERATIONS) else {
        return Matrix3::identity();
    };
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Matrix3::identity();
    };
    let v = vt.transpose();
    let mut r = v * u.transpose();
    if r.determinant() < 0.0 {
        let sv = svd.singular_values;
        let k = (0..3).min_by(|&a, &b| sv[a].total_cmp(&sv[b])).unwrap_or(2);
        // R − 2 v_k u_kᵀ flips the k-th direction.
        r -= 2.0 * v.column(k) * u.column(k).transpose();
    }
    r
}

/// Each vertex's best rotation for `deformed` and the total ARAP energy.
fn local_step(
    graph: &EdgeGraph,
    rest: &[[f64; 3]],
    deformed: &[[f64; 3]],
) -> (Vec<Matrix3<f64>>, f64) {
    let per: Vec<(Matrix3<f64>, f64)> = par_map(graph.len(), |i| {
        let (nb, w) = graph.row(i);
        if nb.is_empty() {
            return (Matrix3::identity(), 0.0);
        }
        let (p, x) = (Vector3::from(rest[i]), Vector3::from(deformed[i]));
        let mut s = Matrix3::zeros();
        for (&j, &wij) in nb.iter().zip(w) {
            let e = p - Vector3::from(rest[j as usize]);
            let f = x - Vector3::from(deformed[j as usize]);
            s += wij * e * f.transpose();
        }
        let r = best_rotation(&s);
        let mut energy = 0.0;
        for (&j, &wij) in nb.iter().zip(w) {
            let e = p - Vector3::from(rest[j as usize]);
            let f = x - Vector3::from(deformed[j as usize]);
            energy += wij * (f - r * e).norm_squared();
        }
        (r, energy)
    });
    let energy = per.iter().map(|p| p.1).sum();
    (per.into_iter().map(|p| p.0).collect(), energy)
}

/// The ARAP energy `Σᵢ min_R Σⱼ wᵢⱼ ‖(xᵢ − xⱼ) − R (pᵢ − pⱼ)‖²` of `deformed` against `rest`.
/// `triangles` must index `rest` (same length as `deformed`).
pub fn arap_energy(
    rest: &[[f64; 3]],
    deformed: &[[f64; 3]],
    triangles: &[[u32; 3]],
    weights: DeformWeights,
) -> f64 {
    let graph = EdgeGraph::new(rest, triangles, weights);
    local_step(&graph, rest, deformed).1
}

/// Connected components of the edge graph: `(component of each vertex, or NONE when the vertex
/// has no edge; number of components)`, numbered in order of their smallest vertex.
fn components(graph: &EdgeGraph) -> (Vec<u32>, usize) {
    let n = graph.len();
    let mut comp = vec![NONE; n];
    let mut count = 0u32;
    let mut stack = Vec::new();
    for s in 0..n {
        if comp[s] != NONE || graph.row(s).0.is_empty() {
            continue;
        }
        comp[s] = count;
        stack.push(s as u32);
        while let Some(v) = stack.pop() {
            for &u in graph.row(v as usize).0 {
                if comp[u as usize] == NONE {
                    comp[u as usize] = count;
                    stack.push(u);
                }
            }
        }
        count += 1;
    }
    (comp, count as usize)
}

/// Lower-triangle columns of `(LᵀL)_FF`, `L` the row-normalized Laplacian, over the free
/// vertices (`index[v]`: position among them, or NONE).
fn bilaplacian_columns(
    graph: &EdgeGraph,
    free: &[u32],
    index: &[u32],
    inv_sum: &[f64],
) -> Vec<Vec<(u32, f64)>> {
    par_map(free.len(), |c| {
        let j = free[c] as usize;
        let mut entries: Vec<(u32, f64)> = Vec::new();
        // Rows i with L_ij ≠ 0: i = j (L_jj = 1) and the neighbours of j (L_ij = −w_ij / W_i).
        let (nb, w) = graph.row(j);
        let rows = std::iter::once((j, 1.0)).chain(
            nb.iter()
                .zip(w)
                .map(|(&i, &wij)| (i as usize, -wij * inv_sum[i as usize])),
        );
        for (i, lij) in rows {
            let (nbi, wi) = graph.row(i);
            let row = std::iter::once((i, 1.0)).chain(
                nbi.iter()
                    .zip(wi)
                    .map(|(&k, &wik)| (k as usize, -wik * inv_sum[i])),
            );
            for (k, lik) in row {
                if index[k] != NONE && k >= j {
                    entries.push((index[k], lij * lik));
                }
            }
        }
        entries.sort_by_key(|e| e.0);
        let mut column: Vec<(u32, f64)> = Vec::with_capacity(entries.len());
        for (r, v) in entries {
            match column.last_mut() {
                Some(last) if last.0 == r => last.1 += v,
                _ => column.push((r, v)),
            }
        }
        column
    })
}

/// Lower-triangle columns of the weighted graph Laplacian over the free vertices.
fn laplacian_columns(graph: &EdgeGraph, free: &[u32], index: &[u32]) -> Vec<Vec<(u32, f64)>> {
    par_map(free.len(), |c| {
        let j = free[c] as usize;
        let (nb, w) = graph.row(j);
        let mut column = vec![(c as u32, w.iter().sum())];
        for (&k, &wjk) in nb.iter().zip(w) {
            if index[k as usize] != NONE && (k as usize) > j {
                column.push((index[k as usize], -wjk));
            }
        }
        column
    })
}

/// `y = L v` for the row-normalized Laplacian.
fn apply_normalized(graph: &EdgeGraph, inv_sum: &[f64], v: &[[f64; 3]]) -> Vec<[f64; 3]> {
    par_map(graph.len(), |i| {
        let (nb, w) = graph.row(i);
        let mut y = v[i];
        for (&j, &wij) in nb.iter().zip(w) {
            for k in 0..3 {
                y[k] -= wij * inv_sum[i] * v[j as usize][k];
            }
        }
        y
    })
}

/// `y = Lᵀ v` for the row-normalized Laplacian (`w` symmetric: a gather over the neighbours).
fn apply_normalized_transpose(graph: &EdgeGraph, inv_sum: &[f64], v: &[[f64; 3]]) -> Vec<[f64; 3]> {
    par_map(graph.len(), |j| {
        let (nb, w) = graph.row(j);
        let mut y = v[j];
        for (&i, &wij) in nb.iter().zip(w) {
            for k in 0..3 {
                y[k] -= wij * inv_sum[i as usize] * v[i as usize][k];
            }
        }
        y
    })
}

/// Solves for the free displacements (`rhs[c]` per free vertex) and writes `rest + d` into
/// `positions`.
fn solve_into(
    factor: &Cholesky,
    rhs: &[[f64; 3]],
    free: &[u32],
    rest: &[[f64; 3]],
    positions: &mut [[f64; 3]],
) -> Result<(), DeformError> {
    let m = free.len();
    let mut b = vec![0.0; 3 * m];
    for (c, r) in rhs.iter().enumerate() {
        for k in 0..3 {
            b[k * m + c] = r[k];
        }
    }
    factor.solve3(&mut b)?;
    for (c, &v) in free.iter().enumerate() {
        let p = rest[v as usize];
        positions[v as usize] = [0, 1, 2].map(|k| p[k] + b[k * m + c]);
    }
    Ok(())
}

/// Deforms the mesh `rest`/`triangles` so that the constrained vertices reach their targets
/// (see the module documentation).
pub fn deform(
    rest: &[[f64; 3]],
    triangles: &[[u32; 3]],
    constraints: &Constraints,
    options: &DeformOptions,
) -> Result<Deformed, DeformError> {
    let n = rest.len();
    if let Some(vertex) = rest.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(DeformError::NonFiniteVertex { vertex });
    }
    for (triangle, t) in triangles.iter().enumerate() {
        if t.iter().any(|&i| i as usize >= n) || t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            return Err(DeformError::BadTriangle {
                triangle,
                corners: *t,
                vertices: n,
            });
        }
    }
    if constraints.vertices.is_empty() {
        return Err(DeformError::NoHandles);
    }
    for (position, &vertex) in constraints.vertices.iter().enumerate() {
        if vertex as usize >= n {
            return Err(DeformError::IndexOutOfRange {
                list: "handles",
                position,
                vertex,
                vertices: n,
            });
        }
    }
    let graph = EdgeGraph::new(rest, triangles, options.weights);

    // Displacements of the constrained vertices; positions start at rest with the targets set.
    let mut constrained = vec![false; n];
    let mut fixed_d = vec![[0.0; 3]; n];
    let mut positions = rest.to_vec();
    for (&v, t) in constraints.vertices.iter().zip(&constraints.targets) {
        let v = v as usize;
        constrained[v] = true;
        fixed_d[v] = sub(*t, rest[v]);
        positions[v] = *t;
    }
    let (comp, count) = components(&graph);
    let mut has_constraint = vec![false; count];
    for (v, &c) in comp.iter().enumerate() {
        if c != NONE && constrained[v] {
            has_constraint[c as usize] = true;
        }
    }
    let mut pinned = 0;
    if let Some(missing) = has_constraint.iter().position(|&h| !h) {
        let size = comp.iter().filter(|&&c| c as usize == missing).count();
        let first = comp
            .iter()
            .position(|&c| c as usize == missing)
            .unwrap_or(0);
        match options.unconstrained {
            Unconstrained::Error => {
                return Err(DeformError::UnconstrainedComponent {
                    vertex: first as u32,
                    vertices: size,
                });
            }
            Unconstrained::Keep => {
                for (v, &c) in comp.iter().enumerate() {
                    if c != NONE && !has_constraint[c as usize] {
                        constrained[v] = true;
                        pinned += 1;
                    }
                }
            }
        }
    }

    let free: Vec<u32> = (0..n as u32)
        .filter(|&v| !constrained[v as usize] && comp[v as usize] != NONE)
        .collect();
    let mut index = vec![NONE; n];
    for (c, &v) in free.iter().enumerate() {
        index[v as usize] = c as u32;
    }

    // Laplacian surface editing: (LᵀL)_FF d_F = −(LᵀL d̃)_F, d̃ the constrained displacements.
    if !free.is_empty() {
        let inv_sum: Vec<f64> = (0..n)
            .map(|v| {
                let s = graph.weight_sum(v);
                if s > 0.0 { 1.0 / s } else { 0.0 }
            })
            .collect();
        let factor = Cholesky::new(
            bilaplacian_columns(&graph, &free, &index, &inv_sum),
            "the Laplacian-editing matrix LᵀL",
        )?;
        let r = apply_normalized(&graph, &inv_sum, &fixed_d);
        let ltr = apply_normalized_transpose(&graph, &inv_sum, &r);
        let rhs: Vec<[f64; 3]> = free.iter().map(|&v| ltr[v as usize].map(|x| -x)).collect();
        solve_into(&factor, &rhs, &free, rest, &mut positions)?;
    }

    let (mut rotations, mut energy) = local_step(&graph, rest, &positions);
    let mut energies = vec![energy];
    let mut iterations = 0;
    if options.method == DeformMethod::Arap && !free.is_empty() && options.iterations > 0 {
        let factor = Cholesky::new(
            laplacian_columns(&graph, &free, &index),
            "the ARAP Laplacian",
        )?;
        while iterations < options.iterations as usize && energy > 0.0 {
            // Σ_k w_jk [((R_j + R_k)/2 − I)(p_j − p_k)] + Σ_{k constrained} w_jk d_k.
            let rhs: Vec<[f64; 3]> = par_map(free.len(), |c| {
                let j = free[c] as usize;
                let (nb, w) = graph.row(j);
                let (pj, rj) = (Vector3::from(rest[j]), &rotations[j]);
                let mut b = Vector3::zeros();
                for (&k, &wjk) in nb.iter().zip(w) {
                    let k = k as usize;
                    let e = pj - Vector3::from(rest[k]);
                    b += wjk * (0.5 * (rj * e + rotations[k] * e) - e);
                    if index[k] == NONE {
                        b += wjk * Vector3::from(fixed_d[k]);
                    }
                }
                [b.x, b.y, b.z]
            });
            solve_into(&factor, &rhs, &free, rest, &mut positions)?;
            let previous = energy;
            (rotations, energy) = local_step(&graph, rest, &positions);
            energies.push(energy);
            iterations += 1;
            if previous - energy <= options.tolerance * previous {
                break;
            }
        }
    }
    Ok(Deformed {
        positions,
        energies,
        iterations,
        pinned,
    })
}

params! {
    /// Parameters of `mesh.deform`.
    pub struct DeformParams {
        /// "arap" (as-rigid-as-possible) or "laplacian" (linear Laplacian editing). Default
        /// "arap".
        method: DeformMethod = DeformMethod::Arap,
        /// Edge weights of both energies: "cotangent" or "uniform". Default "cotangent".
        weights: DeformWeights = DeformWeights::Cotangent,
        /// Vertex indices to move (at least one). Default none.
        handles: Vec<u32> = Vec::new(),
        /// New positions of the handles, one `(x, y, z)` per handle in scene units; leave empty
        /// when the `targets` input is connected. Default none.
        targets: Vec<[f64; 3]> = Vec::new(),
        /// Vertex indices that keep their positions. Default none.
        fixed: Vec<u32> = Vec::new(),
        /// ARAP: most local/global iterations after the Laplacian initial guess. Default 10.
        iterations: u32 = 10 => [max = 100000],
        /// ARAP: stop when an iteration lowers the energy by at most this fraction. Default
        /// 1e-6 (0: run all iterations while the energy decreases).
        tolerance: f64 = 1e-6 => [min = 0.0, max = 1.0],
        /// A connected component with no handle or fixed vertex: "error" (the system is
        /// singular) or "keep" (pin it where it is). Default "error".
        unconstrained: Unconstrained = Unconstrained::Error,
    }
}

/// Handle-based deformation (`mesh.deform`). See [`deform`].
#[derive(Debug, Clone, PartialEq)]
pub struct Deform {
    params: DeformParams,
}

impl Op for Deform {
    type Params = DeformParams;
    const ID: &'static str = "mesh.deform";
    const SUMMARY: &'static str = "Deforms a triangle mesh by moving handle vertices: as-rigid-as-possible or Laplacian editing.";
    const DOC: &'static str = r#"
Moves the `handles` vertices exactly to `targets` (hard constraints), keeps the `fixed` vertices
where they are, and solves for every other vertex so that the surface keeps its local shape.

"laplacian": linear Laplacian surface editing (Sorkine et al., "Laplacian surface editing",
SGP 2004, plain version): minimize ‖L x − δ‖² over the free vertices, L the row-normalized
Laplacian (L x)_i = x_i − Σ_j w_ij x_j / Σ_j w_ij, δ = L p of the rest shape p. One sparse
solve; details are not rotated with the surface, so bends shear and shrink.

"arap": as-rigid-as-possible surface modeling (Sorkine & Alexa, SGP 2007): minimize
E = Σ_i min_{R_i} Σ_j w_ij ‖(x_i − x_j) − R_i (p_i − p_j)‖², alternating the best rotation of
each vertex's cell (SVD of its edge covariance, reflections removed) with a global solve of the
prefactored Laplacian system. Starts from the "laplacian" result (same weights); stops after
`iterations` iterations or when one lowers E by at most `tolerance`·E. E never increases.

`weights`: "cotangent" w_ij = (cot α + cot β)/2 (negative weights of obtuse edges are raised to
1e-4 × the mean positive weight) or "uniform" w_ij = 1. Both systems are factored once (faer
sparse Cholesky, AMD ordering) and reused for every right-hand side.

Targets come from the `targets` parameter, or from the optional `targets` point cloud (one point
per handle, in order; the parameter must then be empty). A vertex listed twice must get the same
target. A connected component without any handle or fixed vertex makes the system singular: an
error, or with `unconstrained: "keep"` it stays in place. Vertices of no triangle keep their
position. Connectivity is unchanged; normals, if present, are recomputed (angle-weighted);
colors and texture coordinates pass through.

Metrics: `iterations` (ARAP iterations run), `energy` (final ARAP energy, with the chosen
weights, in squared scene units; also for "laplacian"), `initial_energy` (of the Laplacian
result), `max_handle_error` (largest distance of a handle from its target in the f32 output),
`max_displacement`, `constrained` (handle and fixed vertices), `pinned` (vertices of
unconstrained components kept in place).

Example:
    "bent": (op: "mesh.deform", inputs: { "mesh": "bar.mesh" }, params: (method: "arap", handles: [40, 41], targets: [(0.0, 1.0, 2.0), (0.5, 1.0, 2.0)], fixed: [0, 1], iterations: 20)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "A manifold triangle mesh."),
            PortSpec::new(
                "targets",
                PortType::PointCloud,
                "New handle positions, one point per entry of `handles`, in order; replaces the \
                 `targets` parameter.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The deformed mesh."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "iterations, energy, initial_energy, max_handle_error, max_displacement, \
                 constrained, pinned.",
            ),
        ]
    }

    fn new(p: DeformParams) -> Result<Self, String> {
        if p.handles.is_empty() {
            return Err(DeformError::NoHandles.to_string());
        }
        if !p.targets.is_empty() && p.targets.len() != p.handles.len() {
            return Err(DeformError::LengthMismatch {
                handles: p.handles.len(),
                targets: p.targets.len(),
            }
            .to_string());
        }
        if !(p.tolerance >= 0.0 && p.tolerance <= 1.0) {
            return Err(format!(
                "`tolerance` must be in [0, 1], got {}",
                p.tolerance
            ));
        }
        Ok(Deform { params: p })
    }
}

impl Operator for Deform {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = mesh_input(inputs, "mesh")?;
        let half = halfedge_of(mesh).map_err(|e| e.at("mesh"))?;
        let rest = half.positions();
        let p = &self.params;
        let targets = match inputs.get("targets") {
            None => p.targets.clone(),
            Some(Value::PointCloud(cloud)) => {
                if !p.targets.is_empty() {
                    return Err(OpError::input(
                        "targets",
                        "both the `targets` input and the `targets` parameter are given; use one",
                    ));
                }
                let t = positions_f64(cloud).map_err(|e| e.at("targets"))?;
                if t.len() != p.handles.len() {
                    return Err(OpError::input(
                        "targets",
                        format!(
                            "the cloud has {} points but there are {} handles: give one point \
                             per handle",
                            t.len(),
                            p.handles.len()
                        ),
                    ));
                }
                t
            }
            Some(other) => {
                return Err(OpError::input(
                    "targets",
                    format!("expected PointCloud, got {}", other.port_type()),
                ));
            }
        };
        let fail = |e: DeformError| OpError::failed(e.to_string());
        let constraints = Constraints::new(rest, &p.handles, &targets, &p.fixed).map_err(fail)?;
        let options = DeformOptions {
            method: p.method,
            weights: p.weights,
            iterations: p.iterations,
            tolerance: p.tolerance,
            unconstrained: p.unconstrained,
        };
        let out = deform(rest, &mesh.triangles, &constraints, &options).map_err(fail)?;
        let positions: Vec<[f32; 3]> = out.positions.iter().map(|v| v.map(|x| x as f32)).collect();
        let max_handle_error = constraints
            .vertices()
            .iter()
            .zip(constraints.targets())
            .map(|(&v, t)| norm(sub(positions[v as usize].map(f64::from), *t)))
            .fold(0.0, f64::max);
        let max_displacement = out
            .positions
            .iter()
            .zip(rest)
            .map(|(a, b)| norm(sub(*a, *b)))
            .fold(0.0, f64::max);
        let normals = mesh.normals.as_ref().map(|_| {
            let (n, _) = vertex_normals(&out.positions, &mesh.triangles, NormalWeighting::Angle);
            n.iter().map(|v| v.map(|x| x as f32)).collect()
        });
        let result = Mesh {
            positions,
            normals,
            ..Mesh::clone(mesh)
        };
        let mut m = Metrics::new();
        m.insert("iterations".into(), out.iterations as f64);
        m.insert("energy".into(), out.energies.last().copied().unwrap_or(0.0));
        m.insert(
            "initial_energy".into(),
            out.energies.first().copied().unwrap_or(0.0),
        );
        m.insert("max_handle_error".into(), max_handle_error);
        m.insert("max_displacement".into(), max_displacement);
        m.insert("constrained".into(), constraints.vertices().len() as f64);
        m.insert("pinned".into(), out.pinned as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(result)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::halfedge::tests::{grid, icosphere};
    use ocellus_engine::value::PointCloud;
    use proptest::prelude::*;

    fn sphere(subdivisions: u32, seed: u64) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let (p, t, _) = icosphere(subdivisions, seed, 0.2).to_triangles().unwrap();
        (p, t)
    }

    /// A `w × h` strip of unit squares in the plane z = 0.
    fn strip(w: u32, h: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        grid(w, h)
    }

    fn max_dist(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| norm(sub(*x, *y)))
            .fold(0.0, f64::max)
    }

    fn options(method: DeformMethod, weights: DeformWeights, iterations: u32) -> DeformOptions {
        DeformOptions {
            method,
            weights,
            iterations,
            tolerance: 0.0,
            unconstrained: Unconstrained::Error,
        }
    }

    fn all_options(iterations: u32) -> Vec<DeformOptions> {
        let mut v = Vec::new();
        for &m in DeformMethod::ALL {
            for &w in DeformWeights::ALL {
                v.push(options(m, w, iterations));
            }
        }
        v
    }

    fn rigid(r: &Matrix3<f64>, t: [f64; 3], p: [f64; 3]) -> [f64; 3] {
        let y = r * Vector3::from(p) + Vector3::from(t);
        [y.x, y.y, y.z]
    }

    /// The quarter-circle bend of the strip `0 ≤ x ≤ length` (an isometry): arclength x along
    /// a circle of radius 2·length/π in the x–z plane.
    fn bend(length: f64, p: [f64; 3]) -> [f64; 3] {
        let r = 2.0 * length / std::f64::consts::PI;
        let a = p[0] / r;
        [r * a.sin(), p[1], r * (1.0 - a.cos())]
    }

    /// The bent-strip problem: columns x ≤ 1 fixed, columns x ≥ w − 1 moved onto the bend.
    fn bent_strip(w: u32, h: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>, Constraints) {
        let (p, t) = strip(w, h);
        let wf = f64::from(w);
        let fixed: Vec<u32> = (0..p.len() as u32)
            .filter(|&v| p[v as usize][0] <= 1.0)
            .collect();
        let handles: Vec<u32> = (0..p.len() as u32)
            .filter(|&v| p[v as usize][0] >= wf - 1.0)
            .collect();
        let targets: Vec<[f64; 3]> = handles.iter().map(|&v| bend(wf, p[v as usize])).collect();
        let c = Constraints::new(&p, &handles, &targets, &fixed).unwrap();
        (p, t, c)
    }

    /// Mean relative change of the edge lengths.
    fn edge_strain(rest: &[[f64; 3]], x: &[[f64; 3]], t: &[[u32; 3]]) -> f64 {
        let g = EdgeGraph::new(rest, t, DeformWeights::Uniform);
        let (mut s, mut count) = (0.0, 0usize);
        for i in 0..g.len() {
            for &j in g.row(i).0 {
                let j = j as usize;
                if j > i {
                    let l0 = norm(sub(rest[i], rest[j]));
                    let l1 = norm(sub(x[i], x[j]));
                    s += (l1 - l0).abs() / l0;
                    count += 1;
                }
            }
        }
        s / count as f64
    }

    #[test]
    fn zero_displacement_returns_the_input() {
        let (p, t) = sphere(2, 4);
        let handles = [0, 5, 17, 60];
        let targets: Vec<[f64; 3]> = handles.iter().map(|&v| p[v as usize]).collect();
        let c = Constraints::new(&p, &handles, &targets, &[3, 90]).unwrap();
        let scale = p.iter().map(|v| norm(*v)).fold(0.0, f64::max);
        for o in all_options(10) {
            let d = deform(&p, &t, &c, &o).unwrap();
            if o.method == DeformMethod::Laplacian {
                // The right-hand side is exactly zero, so is the solution.
                assert_eq!(d.positions, p, "{o:?}");
            }
            assert!(max_dist(&d.positions, &p) <= 1e-12 * scale, "{o:?}");
            assert!(
                d.energies.iter().all(|&e| e < 1e-20),
                "{o:?} {:?}",
                d.energies
            );
        }
    }

    #[test]
    fn one_translation_of_every_handle_translates_the_mesh() {
        let (p, t) = sphere(2, 9);
        let shift = [0.3, -1.25, 2.0];
        let handles = [1, 40, 100];
        let targets: Vec<[f64; 3]> = handles
            .iter()
            .map(|&v| [0, 1, 2].map(|k| p[v as usize][k] + shift[k]))
            .collect();
        let c = Constraints::new(&p, &handles, &targets, &[]).unwrap();
        let moved: Vec<[f64; 3]> = p
            .iter()
            .map(|v| [0, 1, 2].map(|k| v[k] + shift[k]))
            .collect();
        for o in all_options(5) {
            let d = deform(&p, &t, &c, &o).unwrap();
            // Exact in exact arithmetic (L d = 0 for a constant d); the Cholesky solve of LᵀL
            // leaves round-off of order cond · ε.
            let err = max_dist(&d.positions, &moved);
            assert!(err < 1e-9, "{o:?}: {err}");
        }
    }

    #[test]
    fn hand_computed_fan() {
        // A square fan: corners (±1, ±1, 0) constrained, centre 4 free. Lifting corner 0 by h
        // with uniform weights, ‖L d‖² in the centre's z is
        //   (z − h/4)² + (h − z/3)² + 2((h + z)/3)² + (z/3)²,
        // minimal at z = h/4 (derivative 26z/9 − 13h/18 = 0).
        let p = vec![
            [1.0, 1.0, 0.0],
            [-1.0, 1.0, 0.0],
            [-1.0, -1.0, 0.0],
            [1.0, -1.0, 0.0],
            [0.0, 0.0, 0.0],
        ];
        let t = vec![[4, 0, 1], [4, 1, 2], [4, 2, 3], [4, 3, 0]];
        let h = 0.8;
        let c = Constraints::new(&p, &[0], &[[1.0, 1.0, h]], &[1, 2, 3]).unwrap();
        let d = deform(
            &p,
            &t,
            &c,
            &options(DeformMethod::Laplacian, DeformWeights::Uniform, 0),
        )
        .unwrap();
        let centre = d.positions[4];
        assert!(norm(sub(centre, [0.0, 0.0, h / 4.0])) < 1e-15, "{centre:?}");
        assert_eq!(d.positions[0], [1.0, 1.0, h]);
        assert_eq!(d.iterations, 0);
    }

    #[test]
    fn arap_reproduces_one_rigid_motion_of_all_handles() {
        let (p, t) = sphere(2, 11);
        let r = *nalgebra::Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(Vector3::new(1.0, 2.0, -0.5)),
            1.1,
        )
        .matrix();
        let shift = [0.5, -1.0, 2.0];
        let handles: Vec<u32> = (0..p.len() as u32).step_by(9).collect();
        let targets: Vec<[f64; 3]> = handles
            .iter()
            .map(|&v| rigid(&r, shift, p[v as usize]))
            .collect();
        let c = Constraints::new(&p, &handles, &targets, &[]).unwrap();
        let truth: Vec<[f64; 3]> = p.iter().map(|&v| rigid(&r, shift, v)).collect();
        for w in [DeformWeights::Cotangent, DeformWeights::Uniform] {
            let lap = deform(&p, &t, &c, &options(DeformMethod::Laplacian, w, 0)).unwrap();
            // Linear editing does not rotate the details: far from rigid.
            assert!(max_dist(&lap.positions, &truth) > 1e-2, "{w:?}");
            let arap = deform(&p, &t, &c, &options(DeformMethod::Arap, w, 500)).unwrap();
            let err = max_dist(&arap.positions, &truth);
            assert!(
                err < 1e-6,
                "{w:?}: {err} after {} iterations",
                arap.iterations
            );
            assert!(arap.energies.last().copied().unwrap_or(1.0) < 1e-12);
        }
    }

    #[test]
    fn handles_hit_their_targets_exactly() {
        let (p, t) = sphere(2, 5);
        let mut rng = SplitMix64::new(21);
        let handles: Vec<u32> = (0..p.len() as u32).step_by(13).collect();
        let targets: Vec<[f64; 3]> = handles
            .iter()
            .map(|&v| p[v as usize].map(|x| x + 0.4 * (rng.uniform() - 0.5)))
            .collect();
        let fixed = [2u32, 3, 4];
        let c = Constraints::new(&p, &handles, &targets, &fixed).unwrap();
        for o in all_options(10) {
            let d = deform(&p, &t, &c, &o).unwrap();
            for (&v, target) in handles.iter().zip(&targets) {
                assert_eq!(d.positions[v as usize], *target, "{o:?}");
            }
            for &v in &fixed {
                assert_eq!(d.positions[v as usize], p[v as usize], "{o:?}");
            }
            // The free vertices followed.
            let moved = (0..p.len())
                .filter(|&v| !c.vertices().contains(&(v as u32)))
                .filter(|&v| norm(sub(d.positions[v], p[v])) > 1e-3)
                .count();
            assert!(moved > p.len() / 2, "{o:?}: {moved}");
        }
    }

    #[test]
    fn arap_energy_never_increases_and_drops() {
        let (p, t, c) = bent_strip(30, 4);
        for w in [DeformWeights::Cotangent, DeformWeights::Uniform] {
            let d = deform(&p, &t, &c, &options(DeformMethod::Arap, w, 40)).unwrap();
            assert_eq!(d.energies.len(), d.iterations + 1);
            assert!(d.iterations >= 20, "{w:?}: {}", d.iterations);
            for k in 1..d.energies.len() {
                let (a, b) = (d.energies[k - 1], d.energies[k]);
                assert!(b <= a * (1.0 + 1e-12), "{w:?} step {k}: {a} -> {b}");
            }
            let (first, last) = (d.energies[0], d.energies[d.energies.len() - 1]);
            // The Laplacian guess of a gentle bend is already good: a small but real decrease.
            assert!(last < 0.99 * first, "{w:?}: {first} -> {last}");
            // The reported energy is the energy of the returned positions.
            let e = arap_energy(&p, &d.positions, &t, w);
            assert!((e - last).abs() <= 1e-12 * last.max(1e-300), "{e} {last}");
        }
        // A 90° twist of a bumpy sphere (caps above z = 0.7 turned, below −0.7 fixed): the
        // Laplacian guess does not rotate the details, ARAP removes most of its energy.
        let (p, t) = sphere(3, 8);
        let r = *nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), 1.5).matrix();
        let handles: Vec<u32> = (0..p.len() as u32)
            .filter(|&v| p[v as usize][2] > 0.7)
            .collect();
        let fixed: Vec<u32> = (0..p.len() as u32)
            .filter(|&v| p[v as usize][2] < -0.7)
            .collect();
        let targets: Vec<[f64; 3]> = handles
            .iter()
            .map(|&v| rigid(&r, [0.0; 3], p[v as usize]))
            .collect();
        let c = Constraints::new(&p, &handles, &targets, &fixed).unwrap();
        let d = deform(
            &p,
            &t,
            &c,
            &options(DeformMethod::Arap, DeformWeights::Cotangent, 30),
        )
        .unwrap();
        eprintln!("twist energies: {:?}", d.energies);
        for k in 1..d.energies.len() {
            assert!(d.energies[k] <= d.energies[k - 1] * (1.0 + 1e-12));
        }
        let (first, last) = (d.energies[0], d.energies[d.energies.len() - 1]);
        assert!(last < 0.8 * first, "twist: {first} -> {last}");
    }

    #[test]
    fn arap_keeps_edge_lengths_far_better_than_laplacian() {
        let (p, t, c) = bent_strip(40, 4);
        let lap = deform(
            &p,
            &t,
            &c,
            &options(DeformMethod::Laplacian, DeformWeights::Cotangent, 0),
        )
        .unwrap();
        let arap = deform(
            &p,
            &t,
            &c,
            &options(DeformMethod::Arap, DeformWeights::Cotangent, 100),
        )
        .unwrap();
        let (sl, sa) = (
            edge_strain(&p, &lap.positions, &t),
            edge_strain(&p, &arap.positions, &t),
        );
        let truth: Vec<[f64; 3]> = p.iter().map(|&v| bend(40.0, v)).collect();
        let (dl, da) = (
            max_dist(&lap.positions, &truth),
            max_dist(&arap.positions, &truth),
        );
        eprintln!(
            "edge strain: laplacian {sl:.3e}, arap {sa:.3e}; distance from the isometric bend: \
             laplacian {dl:.3e}, arap {da:.3e}"
        );
        // Measured: laplacian 2.6e-3, arap below 5e-5.
        assert!(sl > 1e-3, "laplacian {sl}");
        assert!(sa < 0.05 * sl, "laplacian {sl}, arap {sa}");
        // The bend is an isometry: ARAP lands (nearly) on it.
        assert!(da < 0.5, "{da}");
    }

    #[test]
    fn bad_inputs_are_rejected() {
        let (p, t) = sphere(1, 2);
        let n = p.len();
        let x = [0.0, 0.0, 1.0];
        assert_eq!(
            Constraints::new(&p, &[], &[], &[1]),
            Err(DeformError::NoHandles)
        );
        assert_eq!(
            Constraints::new(&p, &[1, 2], &[x], &[]),
            Err(DeformError::LengthMismatch {
                handles: 2,
                targets: 1
            })
        );
        assert!(matches!(
            Constraints::new(&p, &[1, n as u32], &[x, x], &[]),
            Err(DeformError::IndexOutOfRange {
                list: "handles",
                position: 1,
                ..
            })
        ));
        assert!(matches!(
            Constraints::new(&p, &[1], &[x], &[0, u32::MAX]),
            Err(DeformError::IndexOutOfRange {
                list: "fixed",
                position: 1,
                vertex: u32::MAX,
                ..
            })
        ));
        assert_eq!(
            Constraints::new(&p, &[4, 1], &[x, [f64::NAN, 0.0, 0.0]], &[]),
            Err(DeformError::NonFiniteTarget {
                position: 1,
                vertex: 1
            })
        );
        assert!(matches!(
            Constraints::new(&p, &[3, 3], &[x, [0.0, 0.0, 2.0]], &[]),
            Err(DeformError::ConflictingTargets { vertex: 3, .. })
        ));
        assert!(matches!(
            Constraints::new(&p, &[3], &[x], &[3]),
            Err(DeformError::ConflictingTargets { vertex: 3, .. })
        ));
        // The same target twice, or a fixed handle at its rest position, is fine.
        let c = Constraints::new(&p, &[3, 3, 2], &[x, x, p[2]], &[2]).unwrap();
        assert_eq!(c.vertices(), &[2, 3]);
        assert_eq!(c.targets(), &[p[2], x]);
        let o = DeformOptions::default();
        let mut bad = p.clone();
        bad[7][1] = f64::INFINITY;
        assert_eq!(
            deform(&bad, &t, &c, &o),
            Err(DeformError::NonFiniteVertex { vertex: 7 })
        );
        let mut tris = t.clone();
        tris[5] = [0, 0, 1];
        assert!(matches!(
            deform(&p, &tris, &c, &o),
            Err(DeformError::BadTriangle { triangle: 5, .. })
        ));
        tris[5] = [0, 1, n as u32];
        assert!(matches!(
            deform(&p, &tris, &c, &o),
            Err(DeformError::BadTriangle { triangle: 5, .. })
        ));
        let small = Constraints::new(&p[..3], &[1], &[x], &[]).unwrap();
        assert!(deform(&p[..3], &t, &small, &o).is_err());
    }

    #[test]
    fn unconstrained_components_fail_or_stay() {
        // Two spheres side by side; only the first has handles.
        let (p, t) = sphere(1, 3);
        let n = p.len() as u32;
        let mut p2 = p.clone();
        p2.extend(p.iter().map(|v| [v[0] + 5.0, v[1], v[2]]));
        let mut t2 = t.clone();
        t2.extend(t.iter().map(|f| f.map(|i| i + n)));
        // An isolated vertex too: it stays unless it is a handle.
        p2.push([9.0, 9.0, 9.0]);
        let c = Constraints::new(&p2, &[0, 1], &[[0.0, 0.0, 3.0], p2[1]], &[2]).unwrap();
        for method in DeformMethod::ALL {
            let mut o = options(*method, DeformWeights::Cotangent, 5);
            let err = deform(&p2, &t2, &c, &o).unwrap_err();
            assert_eq!(
                err,
                DeformError::UnconstrainedComponent {
                    vertex: n,
                    vertices: n as usize
                }
            );
            assert!(err.to_string().contains("singular"));
            o.unconstrained = Unconstrained::Keep;
            let d = deform(&p2, &t2, &c, &o).unwrap();
            assert_eq!(d.pinned, n as usize);
            assert_eq!(&d.positions[n as usize..], &p2[n as usize..]);
            assert!(max_dist(&d.positions[..n as usize], &p) > 0.1);
        }
        // An isolated handle moves to its target, the rest is solved as usual.
        let last = 2 * n;
        let c = Constraints::new(&p2, &[0, last], &[p2[0], [1.0, 2.0, 3.0]], &[]).unwrap();
        let o = DeformOptions {
            unconstrained: Unconstrained::Keep,
            ..DeformOptions::default()
        };
        let d = deform(&p2, &t2, &c, &o).unwrap();
        assert_eq!(d.positions[last as usize], [1.0, 2.0, 3.0]);
    }

    #[test]
    fn deformation_does_not_depend_on_the_thread_count() {
        let (p, t) = sphere(3, 6);
        let mut rng = SplitMix64::new(2);
        let handles: Vec<u32> = (0..p.len() as u32).step_by(31).collect();
        let targets: Vec<[f64; 3]> = handles
            .iter()
            .map(|&v| p[v as usize].map(|x| x * (1.0 + 0.5 * rng.uniform())))
            .collect();
        let c = Constraints::new(&p, &handles, &targets, &[]).unwrap();
        for o in all_options(4) {
            let run = |threads| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| deform(&p, &t, &c, &o).unwrap())
            };
            assert_eq!(run(1), run(3), "{o:?}");
        }
    }

    fn run_op(params: DeformParams, values: Vec<Option<Value>>) -> Result<Outputs, OpError> {
        let op = Deform::new(params).map_err(OpError::failed)?;
        let specs = Deform::inputs();
        let ctx = RunContext {
            node: "d".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    #[test]
    fn operator_runs_with_parameter_or_cloud_targets() {
        let (p, t) = sphere(2, 1);
        let (n, _) = vertex_normals(&p, &t, NormalWeighting::Angle);
        let mesh = Mesh {
            positions: p.iter().map(|v| v.map(|x| x as f32)).collect(),
            normals: Some(n.iter().map(|v| v.map(|x| x as f32)).collect()),
            triangles: t.clone(),
            ..Mesh::default()
        };
        let mesh_value = Some(Value::Mesh(Arc::new(mesh.clone())));
        let targets = vec![[0.0, 0.0, 2.0], [0.1, 0.2, -1.5]];
        let params = DeformParams {
            handles: vec![0, 7],
            targets: targets.clone(),
            fixed: vec![20],
            ..DeformParams::default()
        };
        let mut out = run_op(params.clone(), vec![mesh_value.clone(), None]).unwrap();
        let Some(Value::Mesh(m)) = out.take("mesh") else {
            panic!("no mesh")
        };
        let Some(Value::Metrics(metrics)) = out.take("metrics") else {
            panic!("no metrics")
        };
        assert_eq!(m.triangles, t);
        assert!(m.normals.is_some());
        for (&v, target) in [0usize, 7].iter().zip(&targets) {
            assert!(norm(sub(m.positions[v].map(f64::from), *target)) < 1e-6);
        }
        assert!(metrics["max_handle_error"] < 1e-6);
        assert!(metrics["energy"] <= metrics["initial_energy"]);
        assert!(metrics["iterations"] >= 1.0 && metrics["iterations"] <= 10.0);
        assert_eq!(metrics["constrained"], 3.0);

        // The same targets from a point cloud give the same mesh.
        let cloud = PointCloud {
            positions: targets.iter().map(|v| v.map(|x| x as f32)).collect(),
            ..PointCloud::default()
        };
        let cloud_params = DeformParams {
            targets: Vec::new(),
            ..params.clone()
        };
        let cloud_value = Some(Value::PointCloud(Arc::new(cloud.clone())));
        let mut out2 = run_op(
            cloud_params.clone(),
            vec![mesh_value.clone(), cloud_value.clone()],
        )
        .unwrap();
        let Some(Value::Mesh(m2)) = out2.take("mesh") else {
            panic!("no mesh")
        };
        // f32 cloud targets differ from the f64 parameters by rounding only.
        let a: Vec<[f64; 3]> = m.positions.iter().map(|v| v.map(f64::from)).collect();
        let b: Vec<[f64; 3]> = m2.positions.iter().map(|v| v.map(f64::from)).collect();
        assert!(max_dist(&a, &b) < 1e-5);

        // Errors: both target sources, wrong count, bad index, no handles, bad lengths.
        assert!(run_op(params.clone(), vec![mesh_value.clone(), cloud_value]).is_err());
        let short = PointCloud {
            positions: vec![[0.0; 3]],
            ..cloud
        };
        let e = run_op(
            cloud_params,
            vec![mesh_value.clone(), Some(Value::PointCloud(Arc::new(short)))],
        )
        .unwrap_err();
        assert!(e.to_string().contains("one point per handle"), "{e}");
        let far = DeformParams {
            handles: vec![0, 100_000],
            ..params.clone()
        };
        let e = run_op(far, vec![mesh_value.clone(), None]).unwrap_err();
        assert!(e.to_string().contains("100000"), "{e}");
        assert!(Deform::new(DeformParams::default()).is_err());
        assert!(
            Deform::new(DeformParams {
                targets: vec![[0.0; 3]],
                ..params
            })
            .is_err()
        );
    }

    /// Timing on a ~50k-vertex grid (run with `-- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn timing_50k_vertices() {
        let (p, t) = grid(224, 224);
        let w = 224.0;
        let fixed: Vec<u32> = (0..p.len() as u32)
            .filter(|&v| p[v as usize][0] == 0.0)
            .collect();
        let handles: Vec<u32> = (0..p.len() as u32)
            .filter(|&v| p[v as usize][0] == w)
            .collect();
        let targets: Vec<[f64; 3]> = handles.iter().map(|&v| bend(w, p[v as usize])).collect();
        let c = Constraints::new(&p, &handles, &targets, &fixed).unwrap();
        for method in DeformMethod::ALL {
            let o = options(*method, DeformWeights::Cotangent, 10);
            let start = std::time::Instant::now();
            let d = deform(&p, &t, &c, &o).unwrap();
            eprintln!(
                "{} vertices, {} triangles, {}: {} iterations, {:.3} s, energy {:.4e} -> {:.4e}",
                p.len(),
                t.len(),
                method.name(),
                d.iterations,
                start.elapsed().as_secs_f64(),
                d.energies[0],
                d.energies[d.energies.len() - 1]
            );
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        #[test]
        fn constraints_hold_and_energy_falls_at_any_scale(
            seed in any::<u64>(),
            exponent in -4i32..=4,
            offset in -1e4f64..1e4,
            amplitude in 0.0f64..2.0,
        ) {
            let (p0, t) = sphere(1, seed % 7);
            let scale = 10f64.powi(exponent);
            let p: Vec<[f64; 3]> = p0.iter().map(|v| v.map(|x| x * scale + offset)).collect();
            let mut rng = SplitMix64::new(seed);
            let k = 1 + (seed % 5) as usize;
            let handles: Vec<u32> = (0..k).map(|i| (i * 7 + (seed as usize % 3)) as u32).collect();
            let targets: Vec<[f64; 3]> = handles
                .iter()
                .map(|&v| p[v as usize].map(|x| x + amplitude * scale * (rng.uniform() - 0.5)))
                .collect();
            let c = Constraints::new(&p, &handles, &targets, &[]).unwrap();
            for o in all_options(15) {
                let d = deform(&p, &t, &c, &o).unwrap();
                for (&v, x) in c.vertices().iter().zip(c.targets()) {
                    prop_assert_eq!(d.positions[v as usize], *x);
                }
                prop_assert!(d.positions.iter().all(|v| v.iter().all(|x| x.is_finite())));
                // Round-off floor of the energy: position ulps at this offset, squared, per edge.
                let noise = 1e3 * (1e-14 * (offset.abs() + scale)).powi(2);
                for w in d.energies.windows(2) {
                    prop_assert!(w[1] <= w[0] * (1.0 + 1e-9) + noise, "{:?}", d.energies);
                }
                // Nothing moves farther than the handles' span allows (a loose sanity bound).
                let reach = max_dist(&d.positions, &p);
                prop_assert!(reach <= 10.0 * (amplitude + 1.0) * scale, "{}", reach);
            }
        }
    }
}
