//! General sparse nonlinear least squares, in the manner of Ceres Solver: minimize
//! `½ Σᵢ ρᵢ(‖Lᵢ fᵢ(x_{i1}, …, x_{ik})‖²)` over parameter blocks `x_j`.
//!
//! - A [`Problem`] holds parameter blocks (any size; constant or variable; optionally on a
//!   [`Manifold`], see [`super::manifold`]) and residual blocks: a [`CostFunction`] `fᵢ` of some
//!   blocks, a [`RobustLoss`] `ρᵢ` and an optional whitening `Lᵢ` (a square-root information
//!   matrix, `Lᵢᵀ Lᵢ = Σᵢ⁻¹`, given directly or from a covariance `Σᵢ` by Cholesky). Residuals
//!   and Jacobians are whitened first, then robustified with Triggs' correction (Ceres'
//!   `Corrector`, [`RobustLoss::correction`]), then mapped to the tangent spaces through the
//!   manifolds' `plus_jacobian`.
//! - [`NumericDiffCost`] wraps a residual function with central differences for users
//!   without analytic Jacobians.
//! - The minimizer is Ceres' trust-region loop, the same rules as the bundle adjuster
//!   ([`super::ba`]): Jacobi scaling `1/(1 + ‖J_col‖)` from the first Jacobian; gain ratio
//!   `ρ = actual / predicted` decrease, a step is accepted when `ρ > 1e-3`; stops on the relative
//!   cost change of a trial step `≤ function_tolerance` (the trial is not applied), on
//!   `max |g| ≤ gradient_tolerance` (tangent gradient), on `‖δ‖ ≤ parameter_tolerance (‖x‖ +
//!   parameter_tolerance)`, on the iteration limit (Ceres' count, iteration 0 included) or when
//!   the trust region collapses.
//!   - [`TrustRegionStrategy::LevenbergMarquardt`]: `(JᵀJ + D/Δ) δ = −Jᵀr`, `D` the diagonal of
//!     `JᵀJ` in scaled columns clamped to `[1e-6, 1e32]`, initial radius `Δ = 1e4`; on success
//!     `Δ ← Δ / max(1/3, 1 − (2ρ − 1)³)` (Nielsen), else `Δ` shrinks by a doubling factor.
//!   - [`TrustRegionStrategy::Dogleg`]: Powell's dogleg between the Cauchy point and the
//!     Gauss–Newton step in the scaled variables (Nocedal & Wright, §4.1), Ceres'
//!     `DoglegStrategy`: the Gauss–Newton system gets a small Levenberg regularization `μ D`
//!     (`μ` from 1e-8, ×10 after a failed factorization, ÷5 after a success); on success with
//!     `ρ > 0.75`, `Δ ← max(Δ, 3‖step‖)`; a rejected step halves `Δ` and reuses both steps.
//! - The normal equations `JᵀJ` are assembled block-sparse over the tangent spaces of the
//!   variable blocks and solved by a dense Cholesky (nalgebra) for small tangent dimensions or
//!   by faer's sparse Cholesky (symbolic factorization with AMD ordering once, numeric
//!   factorization per step) for larger ones. A failed factorization rejects the step (the
//!   trust region shrinks); it never panics.
//!
//! Determinism: residual blocks are evaluated in parallel over fixed-size chunks, the normal
//! equations are assembled per block pair in residual order, and every sum runs in a fixed
//! order, so results are bit-identical for any number of threads.
//!
//! References: Agarwal, Mierle et al., Ceres Solver (`TrustRegionMinimizer`,
//! `LevenbergMarquardtStrategy`, `DoglegStrategy`, `Corrector`, manifolds); Nocedal & Wright,
//! "Numerical Optimization" (2nd ed., 2006), ch. 4 (trust regions, the dogleg method);
//! Triggs, McLauchlan, Hartley & Fitzgibbon, "Bundle adjustment — a modern synthesis" (1999)
//! for the robust correction; Nielsen, "Damping parameter in Marquardt's method" (1999);
//! Madsen, Nielsen & Tingleff, "Methods for non-linear least squares problems" (2004).

use std::collections::BTreeMap;
use std::sync::Arc;

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use super::loss::RobustLoss;
pub use super::manifold::{
    AngleAxisManifold, Euclidean, Manifold, QuaternionManifold, SphereManifold, SubsetManifold,
};
pub use super::solve_report::{IterationRecord, Termination};

/// Residual blocks per parallel evaluation chunk.
const RESIDUAL_CHUNK: usize = 64;
/// Largest tangent dimension [`LinearSolverType::Auto`] solves densely.
pub const DENSE_MAX_TANGENT_SIZE: usize = 300;

/// A residual function of some parameter blocks, Ceres' `CostFunction`.
pub trait CostFunction: Send + Sync {
    /// Number of residuals `m`.
    fn num_residuals(&self) -> usize;
    /// Sizes of the parameter blocks it reads, in order.
    fn parameter_block_sizes(&self) -> &[usize];
    /// Writes the `m` residuals at `parameters` (one slice per block) and, where
    /// `jacobians` and its entry for a block are given, the row-major `m × size` Jacobian of
    /// the residuals with respect to that block (ambient coordinates). Returns false where the
    /// function cannot be evaluated (the solver then rejects the step).
    fn evaluate(
        &self,
        parameters: &[&[f64]],
        residuals: &mut [f64],
        jacobians: Option<&mut [Option<&mut [f64]>]>,
    ) -> bool;
}

/// A residual function with Jacobians by central differences, step `h = relative_step · |x|`
/// (`relative_step` where `x = 0`).
pub struct NumericDiffCost<F> {
    function: F,
    num_residuals: usize,
    block_sizes: Vec<usize>,
    relative_step: f64,
}

impl<F> NumericDiffCost<F>
where
    F: Fn(&[&[f64]], &mut [f64]) -> bool + Send + Sync,
{
    /// Wraps `function(parameters, residuals) -> ok` of `num_residuals` residuals and blocks of
    /// `block_sizes`; relative step 1e-6 (Ceres' default).
    pub fn new(num_residuals: usize, block_sizes: &[usize], function: F) -> NumericDiffCost<F> {
        NumericDiffCost {
            function,
            num_residuals,
            block_sizes: block_sizes.to_vec(),
            relative_step: 1e-6,
        }
    }

    /// The same with another relative step.
    pub fn with_relative_step(mut self, relative_step: f64) -> NumericDiffCost<F> {
        self.relative_step = relative_step;
        self
    }
}

impl<F> CostFunction for NumericDiffCost<F>
where
    F: Fn(&[&[f64]], &mut [f64]) -> bool + Send + Sync,
{
    fn num_residuals(&self) -> usize {
        self.num_residuals
    }

    fn parameter_block_sizes(&self) -> &[usize] {
        &self.block_sizes
    }

    fn evaluate(
        &self,
        parameters: &[&[f64]],
        residuals: &mut [f64],
        jacobians: Option<&mut [Option<&mut [f64]>]>,
    ) -> bool {
        if !(self.function)(parameters, residuals) {
            return false;
        }
        let Some(jacobians) = jacobians else {
            return true;
        };
        let m = self.num_residuals;
        let mut copies: Vec<Vec<f64>> = parameters.iter().map(|p| p.to_vec()).collect();
        let mut plus = vec![0.0; m];
        let mut minus = vec![0.0; m];
        for (b, jacobian) in jacobians.iter_mut().enumerate() {
            let Some(jacobian) = jacobian.as_deref_mut() else {
                continue;
            };
            let size = copies[b].len();
            for c in 0..size {
                let x = copies[b][c];
                let h = if x == 0.0 {
                    self.relative_step
                } else {
                    self.relative_step * x.abs()
                };
                copies[b][c] = x + h;
                let ok_plus = {
                    let refs: Vec<&[f64]> = copies.iter().map(|v| v.as_slice()).collect();
                    (self.function)(&refs, &mut plus)
                };
                copies[b][c] = x - h;
                let ok_minus = {
                    let refs: Vec<&[f64]> = copies.iter().map(|v| v.as_slice()).collect();
                    (self.function)(&refs, &mut minus)
                };
                copies[b][c] = x;
                if !ok_plus || !ok_minus {
                    return false;
                }
                for r in 0..m {
                    jacobian[r * size + c] = (plus[r] - minus[r]) / (2.0 * h);
                }
            }
        }
        true
    }
}

/// Identifies a parameter block of a [`Problem`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct BlockId(pub usize);

/// Identifies a residual block of a [`Problem`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ResidualId(pub usize);

/// Errors of problem construction and solving.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NllsError {
    /// A cost function's block sizes disagree with the blocks it is attached to.
    #[error("residual block: cost function expects {expected:?} block sizes, got {got:?}")]
    BlockSizeMismatch {
        /// Sizes the cost function declares.
        expected: Vec<usize>,
        /// Sizes of the given blocks.
        got: Vec<usize>,
    },
    /// A manifold's ambient size is not the block's size, or new values have the wrong size.
    #[error("block {block}: size {block_size} but {what} has size {other_size}")]
    SizeMismatch {
        /// The block.
        block: usize,
        /// Its size.
        block_size: usize,
        /// What disagrees.
        what: &'static str,
        /// Its size.
        other_size: usize,
    },
    /// No such parameter block.
    #[error("unknown parameter block {0}")]
    UnknownBlock(usize),
    /// A residual block reads the same parameter block twice.
    #[error("residual block reads parameter block {0} twice")]
    DuplicateBlock(usize),
    /// A cost function with no residuals.
    #[error("cost function has no residuals")]
    NoResiduals,
    /// The cost at the initial point is not finite or a cost function failed there.
    #[error("initial cost is not finite ({0})")]
    NonFiniteInitialCost(f64),
    /// A covariance or square-root information matrix that cannot be used.
    #[error("bad covariance: {0}")]
    BadCovariance(String),
}

/// How the trust-region step is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrustRegionStrategy {
    /// Levenberg–Marquardt with Ceres' radius update.
    LevenbergMarquardt,
    /// Powell's dogleg.
    Dogleg,
}

/// How the normal equations are solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearSolverType {
    /// Dense up to [`DENSE_MAX_TANGENT_SIZE`] tangent coordinates, sparse beyond.
    Auto,
    /// Dense Cholesky (nalgebra).
    DenseCholesky,
    /// Sparse Cholesky (faer, AMD ordering).
    SparseCholesky,
}

/// Solver settings; the defaults are Ceres'.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolverOptions {
    /// Step computation.
    pub strategy: TrustRegionStrategy,
    /// Linear solver.
    pub linear_solver: LinearSolverType,
    /// Most iterations, Ceres' count (the initial evaluation is iteration 0).
    pub max_iterations: usize,
    /// Stop when a trial step changes the cost by at most this fraction.
    pub function_tolerance: f64,
    /// Stop when the largest tangent gradient component is at most this.
    pub gradient_tolerance: f64,
    /// Stop when `‖δ‖ ≤ parameter_tolerance · (‖x‖ + parameter_tolerance)`.
    pub parameter_tolerance: f64,
    /// Initial trust-region radius.
    pub initial_trust_region_radius: f64,
    /// Largest trust-region radius.
    pub max_trust_region_radius: f64,
    /// Smallest gain ratio of an accepted step.
    pub min_relative_decrease: f64,
}

impl Default for SolverOptions {
    fn default() -> SolverOptions {
        SolverOptions {
            strategy: TrustRegionStrategy::LevenbergMarquardt,
            linear_solver: LinearSolverType::Auto,
            max_iterations: 50,
            function_tolerance: 1e-6,
            gradient_tolerance: 1e-10,
            parameter_tolerance: 1e-8,
            initial_trust_region_radius: 1e4,
            max_trust_region_radius: 1e16,
            min_relative_decrease: 1e-3,
        }
    }
}

/// Result of [`Problem::solve`].
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Cost `½ Σ ρ(‖r‖²)` at the start.
    pub initial_cost: f64,
    /// Cost at the end.
    pub final_cost: f64,
    /// Ceres' iteration count (iteration 0 included, the terminating trial step not).
    pub iterations: usize,
    /// Accepted steps (iteration 0 counts as one, as in Ceres).
    pub successful_steps: usize,
    /// Rejected steps.
    pub unsuccessful_steps: usize,
    /// Why it stopped.
    pub termination: Termination,
    /// The linear solver used (never `Auto`).
    pub linear_solver: LinearSolverType,
    /// The step strategy used.
    pub strategy: TrustRegionStrategy,
    /// Variable tangent coordinates.
    pub tangent_size: usize,
    /// Per-iteration history (iteration 0 first).
    pub history: Vec<IterationRecord>,
}

struct ParameterBlock {
    values: Vec<f64>,
    constant: bool,
    manifold: Option<Arc<dyn Manifold>>,
}

impl ParameterBlock {
    fn tangent_size(&self) -> usize {
        self.manifold
            .as_ref()
            .map_or(self.values.len(), |m| m.tangent_size())
    }
}

struct ResidualBlock {
    cost: Arc<dyn CostFunction>,
    loss: RobustLoss,
    blocks: Vec<usize>,
    /// Row-major `m × m` whitening `L` (`Lᵀ L = Σ⁻¹`).
    sqrt_information: Option<Vec<f64>>,
}

/// A nonlinear least-squares problem.
#[derive(Default)]
pub struct Problem {
    blocks: Vec<ParameterBlock>,
    residuals: Vec<ResidualBlock>,
}

impl std::fmt::Debug for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Problem")
            .field("parameter_blocks", &self.blocks.len())
            .field("residual_blocks", &self.residuals.len())
            .finish()
    }
}

impl Problem {
    /// An empty problem.
    pub fn new() -> Problem {
        Problem::default()
    }

    /// Adds a variable parameter block with initial `values`.
    pub fn add_parameter_block(&mut self, values: &[f64]) -> BlockId {
        self.blocks.push(ParameterBlock {
            values: values.to_vec(),
            constant: false,
            manifold: None,
        });
        BlockId(self.blocks.len() - 1)
    }

    fn block_mut(&mut self, id: BlockId) -> Result<&mut ParameterBlock, NllsError> {
        self.blocks
            .get_mut(id.0)
            .ok_or(NllsError::UnknownBlock(id.0))
    }

    /// Holds a block constant.
    pub fn set_constant(&mut self, id: BlockId) -> Result<(), NllsError> {
        self.block_mut(id)?.constant = true;
        Ok(())
    }

    /// Lets a block vary.
    pub fn set_variable(&mut self, id: BlockId) -> Result<(), NllsError> {
        self.block_mut(id)?.constant = false;
        Ok(())
    }

    /// Whether a block is held constant.
    pub fn is_constant(&self, id: BlockId) -> Result<bool, NllsError> {
        self.blocks
            .get(id.0)
            .map(|b| b.constant)
            .ok_or(NllsError::UnknownBlock(id.0))
    }

    /// Puts a block on a manifold; its ambient size must be the block's size.
    pub fn set_manifold(
        &mut self,
        id: BlockId,
        manifold: Arc<dyn Manifold>,
    ) -> Result<(), NllsError> {
        let block = self.block_mut(id)?;
        if manifold.ambient_size() != block.values.len() {
            return Err(NllsError::SizeMismatch {
                block: id.0,
                block_size: block.values.len(),
                what: "the manifold",
                other_size: manifold.ambient_size(),
            });
        }
        block.manifold = Some(manifold);
        Ok(())
    }

    /// The current values of a block.
    pub fn parameters(&self, id: BlockId) -> Result<&[f64], NllsError> {
        self.blocks
            .get(id.0)
            .map(|b| b.values.as_slice())
            .ok_or(NllsError::UnknownBlock(id.0))
    }

    /// Replaces the values of a block (same size).
    pub fn set_parameters(&mut self, id: BlockId, values: &[f64]) -> Result<(), NllsError> {
        let block = self.block_mut(id)?;
        if values.len() != block.values.len() {
            return Err(NllsError::SizeMismatch {
                block: id.0,
                block_size: block.values.len(),
                what: "the new values",
                other_size: values.len(),
            });
        }
        block.values.copy_from_slice(values);
        Ok(())
    }

    /// Number of parameter blocks.
    pub fn num_parameter_blocks(&self) -> usize {
        self.blocks.len()
    }

    /// Number of residual blocks.
    pub fn num_residual_blocks(&self) -> usize {
        self.residuals.len()
    }

    /// Adds a residual block `½ ρ(‖f(blocks)‖²)`.
    pub fn add_residual_block(
        &mut self,
        cost: Arc<dyn CostFunction>,
        loss: RobustLoss,
        blocks: &[BlockId],
    ) -> Result<ResidualId, NllsError> {
        self.push_residual(cost, loss, blocks, None)
    }

    /// Adds a residual block whitened by a covariance `Σ` (row-major `m × m`, symmetric
    /// positive definite): `½ ρ(‖L f‖²)` with `Lᵀ L = Σ⁻¹`.
    pub fn add_residual_block_with_covariance(
        &mut self,
        cost: Arc<dyn CostFunction>,
        loss: RobustLoss,
        blocks: &[BlockId],
        covariance: &[f64],
    ) -> Result<ResidualId, NllsError> {
        let m = cost.num_residuals();
        let sqrt_information = sqrt_information_from_covariance(covariance, m)?;
        self.push_residual(cost, loss, blocks, Some(sqrt_information))
    }

    /// Adds a residual block whitened by a square-root information matrix `L` (row-major
    /// `m × m`, finite): `½ ρ(‖L f‖²)`.
    pub fn add_residual_block_with_sqrt_information(
        &mut self,
        cost: Arc<dyn CostFunction>,
        loss: RobustLoss,
        blocks: &[BlockId],
        sqrt_information: &[f64],
    ) -> Result<ResidualId, NllsError> {
        let m = cost.num_residuals();
        if sqrt_information.len() != m * m {
            return Err(NllsError::BadCovariance(format!(
                "square-root information has {} entries for {m} residuals",
                sqrt_information.len()
            )));
        }
        if !sqrt_information.iter().all(|v| v.is_finite()) {
            return Err(NllsError::BadCovariance(
                "square-root information is not finite".into(),
            ));
        }
        self.push_residual(cost, loss, blocks, Some(sqrt_information.to_vec()))
    }

    fn push_residual(
        &mut self,
        cost: Arc<dyn CostFunction>,
        loss: RobustLoss,
        blocks: &[BlockId],
        sqrt_information: Option<Vec<f64>>,
    ) -> Result<ResidualId, NllsError> {
        if cost.num_residuals() == 0 {
            return Err(NllsError::NoResiduals);
        }
        let mut got = Vec::with_capacity(blocks.len());
        for (k, id) in blocks.iter().enumerate() {
            let block = self.blocks.get(id.0).ok_or(NllsError::UnknownBlock(id.0))?;
            if blocks[..k].contains(id) {
                return Err(NllsError::DuplicateBlock(id.0));
            }
            got.push(block.values.len());
        }
        let expected = cost.parameter_block_sizes();
        if expected != got.as_slice() {
            return Err(NllsError::BlockSizeMismatch {
                expected: expected.to_vec(),
                got,
            });
        }
        self.residuals.push(ResidualBlock {
            cost,
            loss,
            blocks: blocks.iter().map(|b| b.0).collect(),
            sqrt_information,
        });
        Ok(ResidualId(self.residuals.len() - 1))
    }

    /// The cost `½ Σ ρ(‖L r‖²)` at the current values; `None` if a cost function fails.
    pub fn cost(&self) -> Option<f64> {
        let values: Vec<&[f64]> = self.blocks.iter().map(|b| b.values.as_slice()).collect();
        total_cost(&self.residuals, &values)
    }

    /// Minimizes the cost; the blocks' values are replaced by the solution.
    pub fn solve(&mut self, options: &SolverOptions) -> Result<Summary, NllsError> {
        solve(self, options)
    }
}

/// `L` with `Lᵀ L = Σ⁻¹`: `L = C⁻¹` for the Cholesky factor `Σ = C Cᵀ`.
fn sqrt_information_from_covariance(covariance: &[f64], m: usize) -> Result<Vec<f64>, NllsError> {
    if covariance.len() != m * m {
        return Err(NllsError::BadCovariance(format!(
            "covariance has {} entries for {m} residuals",
            covariance.len()
        )));
    }
    if !covariance.iter().all(|v| v.is_finite()) {
        return Err(NllsError::BadCovariance("covariance is not finite".into()));
    }
    for r in 0..m {
        for c in 0..r {
            let (a, b) = (covariance[r * m + c], covariance[c * m + r]);
            if (a - b).abs() > 1e-12 * (a.abs() + b.abs()).max(f64::MIN_POSITIVE) {
                return Err(NllsError::BadCovariance(
                    "covariance is not symmetric".into(),
                ));
            }
        }
    }
    let sigma = DMatrix::from_row_slice(m, m, covariance);
    let chol = sigma
        .cholesky()
        .ok_or_else(|| NllsError::BadCovariance("covariance is not positive definite".into()))?;
    let inverse = chol
        .l()
        .solve_lower_triangular(&DMatrix::identity(m, m))
        .ok_or_else(|| NllsError::BadCovariance("covariance is singular".into()))?;
    let mut out = vec![0.0; m * m];
    for r in 0..m {
        for c in 0..m {
            out[r * m + c] = inverse[(r, c)];
        }
    }
    if !out.iter().all(|v| v.is_finite()) {
        return Err(NllsError::BadCovariance("covariance is singular".into()));
    }
    Ok(out)
}

/// `v ← L v` for a row-major `m × m` `L` and `cols` columns of the row-major `m × cols` `v`.
fn whiten(l: &[f64], m: usize, cols: usize, v: &mut [f64]) {
    let mut out = vec![0.0; m * cols];
    for r in 0..m {
        for k in 0..m {
            let a = l[r * m + k];
            if a != 0.0 {
                for c in 0..cols {
                    out[r * cols + c] += a * v[k * cols + c];
                }
            }
        }
    }
    v.copy_from_slice(&out);
}

/// Whitened residuals of one residual block and `ρ(‖r‖²)`; `None` if it cannot be evaluated.
fn residual_cost(block: &ResidualBlock, values: &[&[f64]], residuals: &mut [f64]) -> Option<f64> {
    let params: Vec<&[f64]> = block.blocks.iter().map(|&b| values[b]).collect();
    if !block.cost.evaluate(&params, residuals, None) {
        return None;
    }
    let m = residuals.len();
    if let Some(l) = &block.sqrt_information {
        whiten(l, m, 1, residuals);
    }
    let s: f64 = residuals.iter().map(|v| v * v).sum();
    let cost = block.loss.evaluate(s)[0];
    cost.is_finite().then_some(cost)
}

/// `½ Σ ρ(‖L r‖²)` over chunks in order; `None` if any block fails or is not finite.
fn total_cost(residuals: &[ResidualBlock], values: &[&[f64]]) -> Option<f64> {
    let partial: Vec<Option<f64>> = residuals
        .par_chunks(RESIDUAL_CHUNK)
        .map(|chunk| {
            let mut sum = 0.0;
            let mut buffer = Vec::new();
            for block in chunk {
                buffer.clear();
                buffer.resize(block.cost.num_residuals(), 0.0);
                sum += residual_cost(block, values, &mut buffer)?;
            }
            Some(sum)
        })
        .collect();
    let mut sum = 0.0;
    for p in partial {
        sum += p?;
    }
    let cost = 0.5 * sum;
    cost.is_finite().then_some(cost)
}

// ------------------------------------------------------------------ layout

/// One variable block read by a residual block.
#[derive(Clone, Copy)]
struct LocalBlock {
    /// Index into the residual block's parameter list.
    slot: usize,
    /// Variable-block index.
    variable: usize,
    /// Column offset in the residual block's tangent Jacobian.
    column: usize,
}

/// One contribution `J_aᵀ J_b` of a residual block to a block pair of `JᵀJ`.
#[derive(Clone, Copy)]
struct PairContribution {
    residual: usize,
    /// Column offsets of the two blocks in the residual's tangent Jacobian.
    column_row_block: usize,
    column_col_block: usize,
}

/// Structure of the problem fixed during a solve.
struct Layout {
    /// Parameter-block index of each variable block.
    variable_blocks: Vec<usize>,
    /// Tangent size and offset of each variable block.
    tangent_sizes: Vec<usize>,
    tangent_offsets: Vec<usize>,
    tangent_size: usize,
    /// Variable-block index of each parameter block (None for constants).
    variable_of_block: Vec<Option<usize>>,
    /// Per residual block: its variable blocks and the width of its tangent Jacobian.
    locals: Vec<Vec<LocalBlock>>,
    widths: Vec<usize>,
    /// Residual and Jacobian offsets into the flat arrays.
    residual_offsets: Vec<usize>,
    jacobian_offsets: Vec<usize>,
    /// Lower block pairs `(row, col)` of `JᵀJ`, row ≥ col, sorted by column then row.
    pairs: Vec<(usize, usize)>,
    /// Contributions per pair (CSR: `pair_start[p]..pair_start[p + 1]`), residual order.
    pair_start: Vec<usize>,
    contributions: Vec<PairContribution>,
    /// Index of the diagonal pair of each variable block.
    diagonal_pair: Vec<usize>,
}

impl Layout {
    fn new(problem: &Problem) -> Layout {
        let mut variable_blocks = Vec::new();
        let mut variable_of_block = vec![None; problem.blocks.len()];
        let mut tangent_sizes = Vec::new();
        let mut tangent_offsets = Vec::new();
        let mut tangent_size = 0;
        for (b, block) in problem.blocks.iter().enumerate() {
            let t = block.tangent_size();
            if block.constant || t == 0 {
                continue;
            }
            variable_of_block[b] = Some(variable_blocks.len());
            variable_blocks.push(b);
            tangent_sizes.push(t);
            tangent_offsets.push(tangent_size);
            tangent_size += t;
        }
        let mut locals = Vec::with_capacity(problem.residuals.len());
        let mut widths = Vec::with_capacity(problem.residuals.len());
        let mut residual_offsets = Vec::with_capacity(problem.residuals.len() + 1);
        let mut jacobian_offsets = Vec::with_capacity(problem.residuals.len() + 1);
        let (mut r_off, mut j_off) = (0, 0);
        let mut pair_lists: BTreeMap<(usize, usize), Vec<PairContribution>> = BTreeMap::new();
        for (i, residual) in problem.residuals.iter().enumerate() {
            let mut local = Vec::new();
            let mut width = 0;
            for (slot, &b) in residual.blocks.iter().enumerate() {
                if let Some(v) = variable_of_block[b] {
                    local.push(LocalBlock {
                        slot,
                        variable: v,
                        column: width,
                    });
                    width += tangent_sizes[v];
                }
            }
            for a in &local {
                for b in &local {
                    if a.variable >= b.variable {
                        // Keyed by (col, row) so the map iterates column-major.
                        pair_lists
                            .entry((b.variable, a.variable))
                            .or_default()
                            .push(PairContribution {
                                residual: i,
                                column_row_block: a.column,
                                column_col_block: b.column,
                            });
                    }
                }
            }
            let m = residual.cost.num_residuals();
            residual_offsets.push(r_off);
            jacobian_offsets.push(j_off);
            r_off += m;
            j_off += m * width;
            locals.push(local);
            widths.push(width);
        }
        residual_offsets.push(r_off);
        jacobian_offsets.push(j_off);
        // Every variable block has a diagonal block (zero where no residual reads it).
        for v in 0..variable_blocks.len() {
            pair_lists.entry((v, v)).or_default();
        }
        let mut pairs = Vec::with_capacity(pair_lists.len());
        let mut pair_start = vec![0];
        let mut contributions = Vec::new();
        let mut diagonal_pair = vec![usize::MAX; variable_blocks.len()];
        for ((col, row), list) in pair_lists {
            if row == col {
                diagonal_pair[col] = pairs.len();
            }
            pairs.push((row, col));
            contributions.extend(list);
            pair_start.push(contributions.len());
        }
        Layout {
            variable_blocks,
            tangent_sizes,
            tangent_offsets,
            tangent_size,
            variable_of_block,
            locals,
            widths,
            residual_offsets,
            jacobian_offsets,
            pairs,
            pair_start,
            contributions,
            diagonal_pair,
        }
    }
}

// ------------------------------------------------------------------ linearization

/// Corrected tangent Jacobians at a point, with the normal equations and the gradient.
struct Linearization {
    cost: f64,
    /// Row-major `m × width` per residual block, concatenated.
    jacobians: Vec<f64>,
    /// Row-major `t_row × t_col` block per pair of [`Layout::pairs`].
    hessian_blocks: Vec<Vec<f64>>,
    /// `Jᵀ r` over the tangent coordinates.
    gradient: Vec<f64>,
}

/// Evaluates one residual block with tangent Jacobians, whitened and corrected; writes
/// `residuals` (m) and `jacobian` (m × width) and returns `ρ(s)`.
fn linearize_residual(
    block: &ResidualBlock,
    layout: &Layout,
    index: usize,
    values: &[&[f64]],
    plus_jacobians: &[Option<Vec<f64>>],
    residuals: &mut [f64],
    jacobian: &mut [f64],
) -> Option<f64> {
    let (local, width) = (&layout.locals[index], layout.widths[index]);
    let m = residuals.len();
    let params: Vec<&[f64]> = block.blocks.iter().map(|&b| values[b]).collect();
    let mut ambient: Vec<Vec<f64>> = block.blocks.iter().map(|_| Vec::new()).collect();
    for l in local {
        ambient[l.slot] = vec![0.0; m * params[l.slot].len()];
    }
    {
        let mut refs: Vec<Option<&mut [f64]>> = ambient
            .iter_mut()
            .map(|a| {
                if a.is_empty() {
                    None
                } else {
                    Some(a.as_mut_slice())
                }
            })
            .collect();
        if !block.cost.evaluate(&params, residuals, Some(&mut refs)) {
            return None;
        }
    }
    if let Some(l) = &block.sqrt_information {
        whiten(l, m, 1, residuals);
        for a in local {
            let size = params[a.slot].len();
            whiten(l, m, size, &mut ambient[a.slot]);
        }
    }
    // Tangent Jacobian: J_ambient · P.
    for l in local {
        let size = params[l.slot].len();
        let t = layout.tangent_sizes[l.variable];
        let a = &ambient[l.slot];
        match &plus_jacobians[l.variable] {
            None => {
                for r in 0..m {
                    jacobian[r * width + l.column..r * width + l.column + t]
                        .copy_from_slice(&a[r * size..r * size + t]);
                }
            }
            Some(p) => {
                for r in 0..m {
                    for c in 0..t {
                        let mut s = 0.0;
                        for k in 0..size {
                            s += a[r * size + k] * p[k * t + c];
                        }
                        jacobian[r * width + l.column + c] = s;
                    }
                }
            }
        }
    }
    let s: f64 = residuals.iter().map(|v| v * v).sum();
    let rho = block.loss.evaluate(s)[0];
    if !rho.is_finite() || !jacobian.iter().all(|v| v.is_finite()) {
        return None;
    }
    if block.loss != RobustLoss::Trivial {
        let corr = block.loss.correction(s);
        if corr.alpha_sq_norm != 0.0 {
            // J ← J − (α/‖r‖²) r (rᵀ J).
            let rtj: Vec<f64> = (0..width)
                .map(|c| (0..m).map(|r| residuals[r] * jacobian[r * width + c]).sum())
                .collect();
            for r in 0..m {
                for c in 0..width {
                    jacobian[r * width + c] -= corr.alpha_sq_norm * residuals[r] * rtj[c];
                }
            }
        }
        jacobian.iter_mut().for_each(|v| *v *= corr.jacobian_scale);
        residuals.iter_mut().for_each(|v| *v *= corr.residual_scale);
    }
    Some(rho)
}

/// One chunk's `Σ ρ`, corrected residuals and tangent Jacobians.
type ChunkLinearization = (f64, Vec<f64>, Vec<f64>);

fn linearize(problem: &Problem, layout: &Layout, values: &[Vec<f64>]) -> Option<Linearization> {
    let value_refs: Vec<&[f64]> = values.iter().map(|v| v.as_slice()).collect();
    let plus_jacobians: Vec<Option<Vec<f64>>> = layout
        .variable_blocks
        .par_iter()
        .map(|&b| {
            problem.blocks[b].manifold.as_ref().map(|m| {
                let mut p = vec![0.0; m.ambient_size() * m.tangent_size()];
                m.plus_jacobian(&values[b], &mut p);
                p
            })
        })
        .collect();
    let n_res = problem.residuals.len();
    let chunks: Vec<Option<ChunkLinearization>> = (0..n_res)
        .step_by(RESIDUAL_CHUNK)
        .collect::<Vec<usize>>()
        .into_par_iter()
        .map(|first| {
            let last = (first + RESIDUAL_CHUNK).min(n_res);
            let r0 = layout.residual_offsets[first];
            let j0 = layout.jacobian_offsets[first];
            let mut residuals = vec![0.0; layout.residual_offsets[last] - r0];
            let mut jacobians = vec![0.0; layout.jacobian_offsets[last] - j0];
            let mut sum = 0.0;
            for i in first..last {
                let (ra, rb) = (
                    layout.residual_offsets[i] - r0,
                    layout.residual_offsets[i + 1] - r0,
                );
                let (ja, jb) = (
                    layout.jacobian_offsets[i] - j0,
                    layout.jacobian_offsets[i + 1] - j0,
                );
                sum += linearize_residual(
                    &problem.residuals[i],
                    layout,
                    i,
                    &value_refs,
                    &plus_jacobians,
                    &mut residuals[ra..rb],
                    &mut jacobians[ja..jb],
                )?;
            }
            Some((sum, residuals, jacobians))
        })
        .collect();
    let mut sum = 0.0;
    let mut residuals = Vec::with_capacity(*layout.residual_offsets.last()?);
    let mut jacobians = Vec::with_capacity(*layout.jacobian_offsets.last()?);
    for chunk in chunks {
        let (s, r, j) = chunk?;
        sum += s;
        residuals.extend(r);
        jacobians.extend(j);
    }
    let cost = 0.5 * sum;
    if !cost.is_finite() {
        return None;
    }
    // Block pairs of JᵀJ, each summed over its contributions in residual order.
    let hessian_blocks: Vec<Vec<f64>> = (0..layout.pairs.len())
        .into_par_iter()
        .map(|p| {
            let (row, col) = layout.pairs[p];
            let (tr, tc) = (layout.tangent_sizes[row], layout.tangent_sizes[col]);
            let mut h = vec![0.0; tr * tc];
            for k in &layout.contributions[layout.pair_start[p]..layout.pair_start[p + 1]] {
                let i = k.residual;
                let m = layout.residual_offsets[i + 1] - layout.residual_offsets[i];
                let w = layout.widths[i];
                let j = &jacobians[layout.jacobian_offsets[i]..layout.jacobian_offsets[i + 1]];
                for e in 0..m {
                    let jr = &j[e * w + k.column_row_block..e * w + k.column_row_block + tr];
                    let jc = &j[e * w + k.column_col_block..e * w + k.column_col_block + tc];
                    for a in 0..tr {
                        for b in 0..tc {
                            h[a * tc + b] += jr[a] * jc[b];
                        }
                    }
                }
            }
            h
        })
        .collect();
    // Gradient Jᵀ r per variable block, over the residuals of its diagonal pair.
    let gradient_blocks: Vec<Vec<f64>> = (0..layout.variable_blocks.len())
        .into_par_iter()
        .map(|v| {
            let t = layout.tangent_sizes[v];
            let mut g = vec![0.0; t];
            let p = layout.diagonal_pair[v];
            if p == usize::MAX {
                return g;
            }
            for k in &layout.contributions[layout.pair_start[p]..layout.pair_start[p + 1]] {
                let i = k.residual;
                let r = &residuals[layout.residual_offsets[i]..layout.residual_offsets[i + 1]];
                let w = layout.widths[i];
                let j = &jacobians[layout.jacobian_offsets[i]..layout.jacobian_offsets[i + 1]];
                for (e, re) in r.iter().enumerate() {
                    for a in 0..t {
                        g[a] += j[e * w + k.column_row_block + a] * re;
                    }
                }
            }
            g
        })
        .collect();
    let gradient: Vec<f64> = gradient_blocks.into_iter().flatten().collect();
    Some(Linearization {
        cost,
        jacobians,
        hessian_blocks,
        gradient,
    })
}

/// Diagonal of `JᵀJ` over the tangent coordinates.
fn hessian_diagonal(layout: &Layout, lin: &Linearization) -> Vec<f64> {
    let mut d = vec![0.0; layout.tangent_size];
    for (v, &p) in layout.diagonal_pair.iter().enumerate() {
        let t = layout.tangent_sizes[v];
        let o = layout.tangent_offsets[v];
        for a in 0..t {
            d[o + a] = if p == usize::MAX {
                0.0
            } else {
                lin.hessian_blocks[p][a * t + a]
            };
        }
    }
    d
}

/// `‖J δ‖²` over chunks of residual blocks, summed in order.
fn jacobian_step_norm_squared(layout: &Layout, lin: &Linearization, step: &[f64]) -> f64 {
    let n_res = layout.widths.len();
    let partial: Vec<f64> = (0..n_res)
        .step_by(RESIDUAL_CHUNK)
        .collect::<Vec<usize>>()
        .into_par_iter()
        .map(|first| {
            let last = (first + RESIDUAL_CHUNK).min(n_res);
            let mut sum = 0.0;
            for i in first..last {
                let m = layout.residual_offsets[i + 1] - layout.residual_offsets[i];
                let w = layout.widths[i];
                let j = &lin.jacobians[layout.jacobian_offsets[i]..layout.jacobian_offsets[i + 1]];
                for e in 0..m {
                    let mut s = 0.0;
                    for l in &layout.locals[i] {
                        let o = layout.tangent_offsets[l.variable];
                        for a in 0..layout.tangent_sizes[l.variable] {
                            s += j[e * w + l.column + a] * step[o + a];
                        }
                    }
                    sum += s * s;
                }
            }
            sum
        })
        .collect();
    partial.iter().sum()
}

/// Predicted decrease of the Gauss–Newton model: `−(gᵀδ + ½‖Jδ‖²)`.
fn model_decrease(layout: &Layout, lin: &Linearization, step: &[f64]) -> f64 {
    let gd: f64 = lin.gradient.iter().zip(step).map(|(g, d)| g * d).sum();
    -(gd + 0.5 * jacobian_step_norm_squared(layout, lin, step))
}

// ------------------------------------------------------------------ linear solvers

/// Solves `(JᵀJ + diag(damping)) δ = rhs`.
enum LinearSolver {
    Dense,
    Sparse(Box<SparseCholesky>),
}

/// Lower-triangular CSC pattern of `JᵀJ` over the tangent coordinates with its symbolic
/// factorization.
struct SparseCholesky {
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Per stored entry: (pair, index in the pair's block).
    source: Vec<(usize, usize)>,
    /// Stored entry index of each diagonal.
    diagonal: Vec<usize>,
    symbolic: SymbolicLlt<usize>,
}

impl SparseCholesky {
    fn new(layout: &Layout) -> Option<SparseCholesky> {
        let n = layout.tangent_size;
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let mut source = Vec::new();
        let mut diagonal = vec![0; n];
        col_ptr.push(0);
        // Pairs sorted by column block then row block: one column block's pairs are a run.
        let mut p = 0;
        for v in 0..layout.variable_blocks.len() {
            let run_start = p;
            while p < layout.pairs.len() && layout.pairs[p].1 == v {
                p += 1;
            }
            let tc = layout.tangent_sizes[v];
            for c in 0..tc {
                let column = layout.tangent_offsets[v] + c;
                for q in run_start..p {
                    let row_block = layout.pairs[q].0;
                    let tr = layout.tangent_sizes[row_block];
                    let first = if row_block == v { c } else { 0 };
                    for r in first..tr {
                        let row = layout.tangent_offsets[row_block] + r;
                        if row == column {
                            diagonal[column] = row_idx.len();
                        }
                        row_idx.push(row);
                        source.push((q, r * tc + c));
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        if (0..n).any(|c| row_idx.get(diagonal[c]) != Some(&c)) {
            return None;
        }
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        let symbolic = SymbolicLlt::try_new(pattern, faer::Side::Lower).ok()?;
        Some(SparseCholesky {
            n,
            col_ptr,
            row_idx,
            source,
            diagonal,
            symbolic,
        })
    }

    fn solve(&self, lin: &Linearization, damping: &[f64], rhs: &[f64]) -> Option<Vec<f64>> {
        let mut values: Vec<f64> = self
            .source
            .iter()
            .map(|&(p, k)| lin.hessian_blocks[p][k])
            .collect();
        for (c, &d) in self.diagonal.iter().enumerate() {
            values[d] += damping[c];
        }
        let pattern = SymbolicSparseColMatRef::new_checked(
            self.n,
            self.n,
            &self.col_ptr,
            None,
            &self.row_idx,
        );
        let matrix = SparseColMatRef::new(pattern, &values);
        let llt =
            Llt::try_new_with_symbolic(self.symbolic.clone(), matrix, faer::Side::Lower).ok()?;
        let mut x = rhs.to_vec();
        llt.solve_in_place(faer::MatMut::from_column_major_slice_mut(&mut x, self.n, 1));
        x.iter().all(|v| v.is_finite()).then_some(x)
    }
}

fn dense_solve(
    layout: &Layout,
    lin: &Linearization,
    damping: &[f64],
    rhs: &[f64],
) -> Option<Vec<f64>> {
    let n = layout.tangent_size;
    let mut a = DMatrix::<f64>::zeros(n, n);
    for (p, &(row, col)) in layout.pairs.iter().enumerate() {
        let (tr, tc) = (layout.tangent_sizes[row], layout.tangent_sizes[col]);
        let (or, oc) = (layout.tangent_offsets[row], layout.tangent_offsets[col]);
        let h = &lin.hessian_blocks[p];
        for r in 0..tr {
            for c in 0..tc {
                a[(or + r, oc + c)] = h[r * tc + c];
                a[(oc + c, or + r)] = h[r * tc + c];
            }
        }
    }
    for (i, d) in damping.iter().enumerate() {
        a[(i, i)] += d;
    }
    let chol = a.cholesky()?;
    let x = chol.solve(&DVector::from_column_slice(rhs));
    x.iter()
        .all(|v| v.is_finite())
        .then(|| x.as_slice().to_vec())
}

impl LinearSolver {
    fn solve(
        &self,
        layout: &Layout,
        lin: &Linearization,
        damping: &[f64],
        rhs: &[f64],
    ) -> Option<Vec<f64>> {
        match self {
            LinearSolver::Dense => dense_solve(layout, lin, damping, rhs),
            LinearSolver::Sparse(s) => s.solve(lin, damping, rhs),
        }
    }
}

// ------------------------------------------------------------------ minimizer

/// `x ⊞ δ` for every variable block; constant blocks are copied.
fn apply_step(
    problem: &Problem,
    layout: &Layout,
    values: &[Vec<f64>],
    step: &[f64],
) -> Vec<Vec<f64>> {
    (0..values.len())
        .into_par_iter()
        .map(|b| {
            let x = &values[b];
            let Some(v) = layout.variable_of_block[b] else {
                return x.clone();
            };
            let o = layout.tangent_offsets[v];
            let delta = &step[o..o + layout.tangent_sizes[v]];
            match &problem.blocks[b].manifold {
                None => x.iter().zip(delta).map(|(a, d)| a + d).collect(),
                Some(m) => {
                    let mut out = vec![0.0; x.len()];
                    m.plus(x, delta, &mut out);
                    out
                }
            }
        })
        .collect()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, a| m.max(a.abs()))
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}

/// Damping `clamp(d s², 1e-6, 1e32) / s² · factor` per coordinate (Ceres' LM diagonal in
/// Jacobi-scaled columns).
fn scaled_damping(diagonal: &[f64], scale: &[f64], factor: f64) -> Vec<f64> {
    diagonal
        .iter()
        .zip(scale)
        .map(|(d, s)| {
            let s2 = s * s;
            (d * s2).clamp(1e-6, 1e32) / s2 * factor
        })
        .collect()
}

/// Dogleg state between iterations (Ceres' `DoglegStrategy`).
struct DoglegState {
    mu: f64,
    /// Cached Cauchy and Gauss–Newton steps in scaled variables (reused after a rejection).
    cached: Option<(Vec<f64>, Vec<f64>)>,
}

const DOGLEG_MIN_MU: f64 = 1e-8;
const DOGLEG_MAX_MU: f64 = 1.0;
const DOGLEG_MU_INCREASE: f64 = 10.0;

/// The dogleg step in unscaled tangent coordinates and its scaled norm, or None when the
/// Gauss–Newton system cannot be factored even at the largest `μ`.
fn dogleg_step(
    layout: &Layout,
    lin: &Linearization,
    solver: &LinearSolver,
    scale: &[f64],
    radius: f64,
    state: &mut DoglegState,
) -> Option<(Vec<f64>, f64)> {
    if state.cached.is_none() {
        // Scaled gradient gs = S g; Cauchy step −α gs with α = ‖gs‖² / ‖J S gs‖².
        let gs: Vec<f64> = lin.gradient.iter().zip(scale).map(|(g, s)| g * s).collect();
        let sgs: Vec<f64> = gs.iter().zip(scale).map(|(g, s)| g * s).collect();
        let jg2 = jacobian_step_norm_squared(layout, lin, &sgs);
        let gs2: f64 = gs.iter().map(|v| v * v).sum();
        let alpha = if jg2 > 0.0 { gs2 / jg2 } else { 0.0 };
        let cauchy: Vec<f64> = gs.iter().map(|g| -alpha * g).collect();
        let diagonal = hessian_diagonal(layout, lin);
        let rhs: Vec<f64> = lin.gradient.iter().map(|g| -g).collect();
        let mut gauss_newton = None;
        while state.mu <= DOGLEG_MAX_MU {
            let damping = scaled_damping(&diagonal, scale, state.mu);
            if let Some(x) = solver.solve(layout, lin, &damping, &rhs) {
                gauss_newton = Some(x.iter().zip(scale).map(|(x, s)| x / s).collect());
                break;
            }
            state.mu *= DOGLEG_MU_INCREASE;
        }
        state.cached = Some((cauchy, gauss_newton?));
    }
    let (cauchy, gauss_newton) = state.cached.as_ref()?;
    let gn_norm = norm(gauss_newton);
    let scaled: Vec<f64> = if gn_norm <= radius {
        gauss_newton.clone()
    } else {
        let c_norm = norm(cauchy);
        if c_norm >= radius {
            cauchy.iter().map(|c| c * radius / c_norm).collect()
        } else {
            // ‖c + β (gn − c)‖ = Δ for β ∈ [0, 1].
            let d: Vec<f64> = gauss_newton
                .iter()
                .zip(cauchy)
                .map(|(g, c)| g - c)
                .collect();
            let a: f64 = d.iter().map(|v| v * v).sum();
            let b: f64 = cauchy.iter().zip(&d).map(|(c, v)| c * v).sum();
            let c = c_norm * c_norm - radius * radius;
            let disc = (b * b - a * c).max(0.0).sqrt();
            // Stable root of a β² + 2 b β + c = 0 with c < 0.
            let beta = if b <= 0.0 {
                (disc - b) / a
            } else {
                -c / (disc + b)
            };
            cauchy.iter().zip(&d).map(|(c, v)| c + beta * v).collect()
        }
    };
    let step_scaled_norm = norm(&scaled);
    let step = scaled.iter().zip(scale).map(|(y, s)| y * s).collect();
    Some((step, step_scaled_norm))
}

fn solve(problem: &mut Problem, options: &SolverOptions) -> Result<Summary, NllsError> {
    let started = std::time::Instant::now();
    let layout = Layout::new(problem);
    let mut values: Vec<Vec<f64>> = problem.blocks.iter().map(|b| b.values.clone()).collect();
    let linear_solver_type = match options.linear_solver {
        LinearSolverType::Auto if layout.tangent_size <= DENSE_MAX_TANGENT_SIZE => {
            LinearSolverType::DenseCholesky
        }
        LinearSolverType::Auto => LinearSolverType::SparseCholesky,
        s => s,
    };
    let mut summary = Summary {
        initial_cost: 0.0,
        final_cost: 0.0,
        iterations: 1,
        successful_steps: 1,
        unsuccessful_steps: 0,
        termination: Termination::MaxIterations,
        linear_solver: linear_solver_type,
        strategy: options.strategy,
        tangent_size: layout.tangent_size,
        history: Vec::new(),
    };
    let value_refs: Vec<&[f64]> = values.iter().map(|v| v.as_slice()).collect();
    let initial_cost = total_cost(&problem.residuals, &value_refs).unwrap_or(f64::NAN);
    if !initial_cost.is_finite() {
        return Err(NllsError::NonFiniteInitialCost(initial_cost));
    }
    summary.initial_cost = initial_cost;
    summary.final_cost = initial_cost;
    summary.history.push(IterationRecord {
        cost: initial_cost,
        step_norm: 0.0,
        radius: options.initial_trust_region_radius,
        accepted: true,
        time_s: started.elapsed().as_secs_f64(),
        cg_iterations: 0,
    });
    if layout.tangent_size == 0 || problem.residuals.is_empty() {
        summary.termination = Termination::Trivial;
        return Ok(summary);
    }
    let mut lin =
        linearize(problem, &layout, &values).ok_or(NllsError::NonFiniteInitialCost(f64::NAN))?;
    let solver = match linear_solver_type {
        LinearSolverType::SparseCholesky => match SparseCholesky::new(&layout) {
            Some(s) => LinearSolver::Sparse(Box::new(s)),
            None => LinearSolver::Dense,
        },
        _ => LinearSolver::Dense,
    };
    if matches!(solver, LinearSolver::Dense) {
        summary.linear_solver = LinearSolverType::DenseCholesky;
    }
    // Jacobi scaling from the first Jacobian.
    let scale: Vec<f64> = hessian_diagonal(&layout, &lin)
        .iter()
        .map(|d| 1.0 / (1.0 + d.sqrt()))
        .collect();
    let mut radius = options.initial_trust_region_radius;
    let mut decrease_factor = 2.0;
    let mut dogleg = DoglegState {
        mu: DOGLEG_MIN_MU,
        cached: None,
    };
    if max_abs(&lin.gradient) <= options.gradient_tolerance {
        summary.termination = Termination::GradientTolerance;
    } else {
        loop {
            if summary.iterations >= options.max_iterations {
                summary.termination = Termination::MaxIterations;
                break;
            }
            let step = match options.strategy {
                TrustRegionStrategy::LevenbergMarquardt => {
                    let diagonal = hessian_diagonal(&layout, &lin);
                    let damping = scaled_damping(&diagonal, &scale, 1.0 / radius);
                    let rhs: Vec<f64> = lin.gradient.iter().map(|g| -g).collect();
                    solver
                        .solve(&layout, &lin, &damping, &rhs)
                        .map(|s| (s, 0.0))
                }
                TrustRegionStrategy::Dogleg => {
                    dogleg_step(&layout, &lin, &solver, &scale, radius, &mut dogleg)
                }
            };
            let mut record = IterationRecord {
                cost: lin.cost,
                step_norm: 0.0,
                radius,
                accepted: false,
                time_s: 0.0,
                cg_iterations: 0,
            };
            let mut accepted = None;
            let mut scaled_step_norm = 0.0;
            let step_valid = step.is_some();
            if let Some((step, scaled_norm)) = step {
                scaled_step_norm = scaled_norm;
                record.step_norm = norm(&step);
                let predicted = model_decrease(&layout, &lin, &step);
                let trial = apply_step(problem, &layout, &values, &step);
                let trial_refs: Vec<&[f64]> = trial.iter().map(|v| v.as_slice()).collect();
                let new_cost = total_cost(&problem.residuals, &trial_refs).unwrap_or(f64::INFINITY);
                let x_norm = layout
                    .variable_blocks
                    .iter()
                    .flat_map(|&b| values[b].iter())
                    .map(|v| v * v)
                    .sum::<f64>()
                    .sqrt();
                if record.step_norm
                    <= options.parameter_tolerance * (x_norm + options.parameter_tolerance)
                {
                    summary.termination = Termination::ParameterTolerance;
                    break;
                }
                if new_cost.is_finite()
                    && (lin.cost - new_cost).abs() <= options.function_tolerance * lin.cost
                {
                    summary.termination = Termination::FunctionTolerance;
                    break;
                }
                let rho = (lin.cost - new_cost) / predicted;
                if new_cost.is_finite() && predicted > 0.0 && rho > options.min_relative_decrease {
                    accepted = Some((trial, rho));
                }
            }
            summary.iterations += 1;
            let relinearized = accepted.and_then(|(trial, rho)| {
                linearize(problem, &layout, &trial).map(|l| (trial, l, rho))
            });
            if let Some((trial, new_lin, rho)) = relinearized {
                values = trial;
                lin = new_lin;
                summary.successful_steps += 1;
                match options.strategy {
                    TrustRegionStrategy::LevenbergMarquardt => {
                        let factor = 1.0 - (2.0 * rho - 1.0).powi(3);
                        radius =
                            (radius / factor.max(1.0 / 3.0)).min(options.max_trust_region_radius);
                        decrease_factor = 2.0;
                    }
                    TrustRegionStrategy::Dogleg => {
                        if rho > 0.75 {
                            radius = radius
                                .max(3.0 * scaled_step_norm)
                                .min(options.max_trust_region_radius);
                        }
                        dogleg.mu = (2.0 * dogleg.mu / DOGLEG_MU_INCREASE).max(DOGLEG_MIN_MU);
                        dogleg.cached = None;
                    }
                }
                record.cost = lin.cost;
                record.accepted = true;
                record.time_s = started.elapsed().as_secs_f64();
                summary.history.push(record);
                if max_abs(&lin.gradient) <= options.gradient_tolerance {
                    summary.termination = Termination::GradientTolerance;
                    break;
                }
            } else {
                summary.unsuccessful_steps += 1;
                match options.strategy {
                    TrustRegionStrategy::LevenbergMarquardt => {
                        radius /= decrease_factor;
                        decrease_factor *= 2.0;
                    }
                    TrustRegionStrategy::Dogleg => {
                        radius *= 0.5;
                        if !step_valid {
                            dogleg.mu = (dogleg.mu * DOGLEG_MU_INCREASE).min(DOGLEG_MAX_MU);
                            dogleg.cached = None;
                        }
                    }
                }
                record.time_s = started.elapsed().as_secs_f64();
                summary.history.push(record);
                if radius < 1e-32 {
                    summary.termination = Termination::TrustRegionCollapsed;
                    break;
                }
            }
        }
    }
    summary.final_cost = lin.cost;
    for (block, v) in problem.blocks.iter_mut().zip(values) {
        block.values = v;
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose_util::rodrigues;
    use crate::optimize::manifold::quaternion_product;

    /// SplitMix64 with Box–Muller normals, for reproducible test data.
    struct TestRng(u64);

    impl TestRng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }
        fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let u1 = self.uniform().max(1e-300);
            let u2 = self.uniform();
            (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
        }
    }

    /// A residual with a hand-written Jacobian, from closures.
    struct AnalyticCost<F> {
        num_residuals: usize,
        sizes: Vec<usize>,
        function: F,
    }

    impl<F> CostFunction for AnalyticCost<F>
    where
        F: Fn(&[&[f64]], &mut [f64], Option<&mut [Option<&mut [f64]>]>) -> bool + Send + Sync,
    {
        fn num_residuals(&self) -> usize {
            self.num_residuals
        }
        fn parameter_block_sizes(&self) -> &[usize] {
            &self.sizes
        }
        fn evaluate(
            &self,
            parameters: &[&[f64]],
            residuals: &mut [f64],
            jacobians: Option<&mut [Option<&mut [f64]>]>,
        ) -> bool {
            (self.function)(parameters, residuals, jacobians)
        }
    }

    fn analytic<F>(num_residuals: usize, sizes: &[usize], function: F) -> Arc<dyn CostFunction>
    where
        F: Fn(&[&[f64]], &mut [f64], Option<&mut [Option<&mut [f64]>]>) -> bool
            + Send
            + Sync
            + 'static,
    {
        Arc::new(AnalyticCost {
            num_residuals,
            sizes: sizes.to_vec(),
            function,
        })
    }

    fn numeric<F>(num_residuals: usize, sizes: &[usize], function: F) -> Arc<dyn CostFunction>
    where
        F: Fn(&[&[f64]], &mut [f64]) -> bool + Send + Sync + 'static,
    {
        Arc::new(NumericDiffCost::new(num_residuals, sizes, function))
    }

    /// Writes `value` to Jacobian entry `k` of block `b` where requested.
    fn set_jacobian(
        jacobians: &mut Option<&mut [Option<&mut [f64]>]>,
        b: usize,
        k: usize,
        value: f64,
    ) {
        if let Some(j) = jacobians.as_deref_mut()
            && let Some(block) = j[b].as_deref_mut()
        {
            block[k] = value;
        }
    }

    fn tight() -> SolverOptions {
        SolverOptions {
            max_iterations: 200,
            function_tolerance: 1e-15,
            gradient_tolerance: 1e-14,
            parameter_tolerance: 1e-15,
            ..SolverOptions::default()
        }
    }

    /// Powell's singular function on four scalar blocks, Ceres' example.
    fn powell_problem() -> (Problem, [BlockId; 4]) {
        let mut p = Problem::new();
        let x = [3.0, -1.0, 0.0, 1.0].map(|v| p.add_parameter_block(&[v]));
        let s5 = 5f64.sqrt();
        let s10 = 10f64.sqrt();
        // f1 = x1 + 10 x2
        let f1 = analytic(1, &[1, 1], |x, r, mut j| {
            r[0] = x[0][0] + 10.0 * x[1][0];
            set_jacobian(&mut j, 0, 0, 1.0);
            set_jacobian(&mut j, 1, 0, 10.0);
            true
        });
        // f2 = √5 (x3 − x4)
        let f2 = analytic(1, &[1, 1], move |x, r, mut j| {
            r[0] = s5 * (x[0][0] - x[1][0]);
            set_jacobian(&mut j, 0, 0, s5);
            set_jacobian(&mut j, 1, 0, -s5);
            true
        });
        // f3 = (x2 − 2 x3)²
        let f3 = analytic(1, &[1, 1], |x, r, mut j| {
            let d = x[0][0] - 2.0 * x[1][0];
            r[0] = d * d;
            set_jacobian(&mut j, 0, 0, 2.0 * d);
            set_jacobian(&mut j, 1, 0, -4.0 * d);
            true
        });
        // f4 = √10 (x1 − x4)²
        let f4 = analytic(1, &[1, 1], move |x, r, mut j| {
            let d = x[0][0] - x[1][0];
            r[0] = s10 * d * d;
            set_jacobian(&mut j, 0, 0, 2.0 * s10 * d);
            set_jacobian(&mut j, 1, 0, -2.0 * s10 * d);
            true
        });
        let t = RobustLoss::Trivial;
        p.add_residual_block(f1, t, &[x[0], x[1]]).unwrap();
        p.add_residual_block(f2, t, &[x[2], x[3]]).unwrap();
        p.add_residual_block(f3, t, &[x[1], x[2]]).unwrap();
        p.add_residual_block(f4, t, &[x[0], x[3]]).unwrap();
        (p, x)
    }

    #[test]
    fn powell_function_reaches_the_origin() {
        for strategy in [
            TrustRegionStrategy::LevenbergMarquardt,
            TrustRegionStrategy::Dogleg,
        ] {
            let (mut p, x) = powell_problem();
            let s = p
                .solve(&SolverOptions {
                    strategy,
                    ..tight()
                })
                .unwrap();
            assert!((s.initial_cost - 107.5).abs() < 1e-12, "{}", s.initial_cost);
            assert!(s.final_cost < 1e-12, "{strategy:?}: {}", s.final_cost);
            for b in x {
                let v = p.parameters(b).unwrap()[0];
                assert!(v.abs() < 1e-2, "{strategy:?}: x = {v}");
            }
            assert_eq!(s.iterations, s.successful_steps + s.unsuccessful_steps);
            assert_eq!(s.history.len(), s.iterations);
            for w in s.history.windows(2) {
                assert!(w[1].cost <= w[0].cost);
            }
        }
    }

    #[test]
    fn rosenbrock_from_the_standard_start() {
        for strategy in [
            TrustRegionStrategy::LevenbergMarquardt,
            TrustRegionStrategy::Dogleg,
        ] {
            let mut p = Problem::new();
            let x = p.add_parameter_block(&[-1.2, 1.0]);
            // r = (1 − x, 10 (y − x²)).
            let cost = analytic(2, &[2], |x, r, mut j| {
                let (a, b) = (x[0][0], x[0][1]);
                r[0] = 1.0 - a;
                r[1] = 10.0 * (b - a * a);
                set_jacobian(&mut j, 0, 0, -1.0);
                set_jacobian(&mut j, 0, 1, 0.0);
                set_jacobian(&mut j, 0, 2, -20.0 * a);
                set_jacobian(&mut j, 0, 3, 10.0);
                true
            });
            p.add_residual_block(cost, RobustLoss::Trivial, &[x])
                .unwrap();
            let s = p
                .solve(&SolverOptions {
                    strategy,
                    ..tight()
                })
                .unwrap();
            let v = p.parameters(x).unwrap();
            assert!((s.initial_cost - 12.1).abs() < 1e-12);
            assert!(s.final_cost < 1e-20, "{strategy:?}: {}", s.final_cost);
            assert!(
                (v[0] - 1.0).abs() < 1e-9 && (v[1] - 1.0).abs() < 1e-9,
                "{v:?}"
            );
        }
    }

    /// Ceres' curve-fitting data: y = exp(0.3 x + 0.1) + N(0, 0.2²).
    fn curve_data(seed: u64) -> Vec<(f64, f64)> {
        let mut rng = TestRng(seed);
        (0..67)
            .map(|i| {
                let x = i as f64 * 0.075;
                (x, (0.3 * x + 0.1).exp() + 0.2 * rng.normal())
            })
            .collect()
    }

    fn exponential_residual(x: f64, y: f64) -> Arc<dyn CostFunction> {
        analytic(1, &[1, 1], move |p, r, mut j| {
            let e = (p[0][0] * x + p[1][0]).exp();
            r[0] = y - e;
            set_jacobian(&mut j, 0, 0, -x * e);
            set_jacobian(&mut j, 1, 0, -e);
            true
        })
    }

    fn curve_problem(
        data: &[(f64, f64)],
        loss: RobustLoss,
        start: [f64; 2],
    ) -> (Problem, BlockId, BlockId) {
        let mut p = Problem::new();
        let m = p.add_parameter_block(&[start[0]]);
        let c = p.add_parameter_block(&[start[1]]);
        for &(x, y) in data {
            p.add_residual_block(exponential_residual(x, y), loss, &[m, c])
                .unwrap();
        }
        (p, m, c)
    }

    #[test]
    fn curve_fitting_recovers_m_and_c() {
        let data = curve_data(17);
        let mut results = Vec::new();
        for strategy in [
            TrustRegionStrategy::LevenbergMarquardt,
            TrustRegionStrategy::Dogleg,
        ] {
            let (mut p, m, c) = curve_problem(&data, RobustLoss::Trivial, [0.0, 0.0]);
            let s = p
                .solve(&SolverOptions {
                    strategy,
                    ..tight()
                })
                .unwrap();
            let (mv, cv) = (p.parameters(m).unwrap()[0], p.parameters(c).unwrap()[0]);
            assert!(
                (mv - 0.3).abs() < 0.03 && (cv - 0.1).abs() < 0.1,
                "{mv} {cv}"
            );
            // Least squares: the fit is at least as good as the truth.
            let (truth, _, _) = curve_problem(&data, RobustLoss::Trivial, [0.3, 0.1]);
            assert!(s.final_cost <= truth.cost().unwrap());
            // About ½ n σ² at the optimum (1.34 expected).
            assert!(s.final_cost < 2.0, "{}", s.final_cost);
            results.push((mv, cv));
        }
        // LM and dogleg converge to the same minimum.
        assert!((results[0].0 - results[1].0).abs() < 1e-8);
        assert!((results[0].1 - results[1].1).abs() < 1e-8);
    }

    #[test]
    fn robust_losses_reject_outliers_where_least_squares_does_not() {
        // Line y = 2x − 1 with small noise, 30 % of the points shifted up by 5..15.
        let mut rng = TestRng(99);
        let data: Vec<(f64, f64)> = (0..100)
            .map(|i| {
                let x = i as f64 / 10.0;
                let mut y = 2.0 * x - 1.0 + 0.05 * rng.normal();
                if i % 10 < 3 {
                    y += 5.0 + 10.0 * rng.uniform();
                }
                (x, y)
            })
            .collect();
        let fit = |loss: RobustLoss, start: [f64; 2]| {
            let mut p = Problem::new();
            let ab = p.add_parameter_block(&start);
            for &(x, y) in &data {
                let cost = analytic(1, &[2], move |p, r, mut j| {
                    r[0] = p[0][0] * x + p[0][1] - y;
                    set_jacobian(&mut j, 0, 0, x);
                    set_jacobian(&mut j, 0, 1, 1.0);
                    true
                });
                p.add_residual_block(cost, loss, &[ab]).unwrap();
            }
            p.solve(&tight()).unwrap();
            let v = p.parameters(ab).unwrap();
            [v[0], v[1]]
        };
        let plain = fit(RobustLoss::Trivial, [0.0, 0.0]);
        let error = |v: [f64; 2]| (v[0] - 2.0).abs().max((v[1] + 1.0).abs());
        assert!(
            error(plain) > 1.0,
            "least squares is pulled away: {plain:?}"
        );
        let huber = fit(RobustLoss::Huber(0.1), [0.0, 0.0]);
        assert!(error(huber) < 0.1, "Huber {huber:?}");
        let cauchy = fit(RobustLoss::Cauchy(0.2), plain);
        assert!(error(cauchy) < 0.05, "Cauchy {cauchy:?}");
    }

    #[test]
    fn constant_blocks_do_not_move() {
        let mut p = Problem::new();
        let x = p.add_parameter_block(&[1.0, 2.0]);
        let y = p.add_parameter_block(&[-3.0, 0.5]);
        let diff = analytic(2, &[2, 2], |v, r, mut j| {
            for k in 0..2 {
                r[k] = v[0][k] - v[1][k];
                set_jacobian(&mut j, 0, 3 * k, 1.0);
                set_jacobian(&mut j, 1, 3 * k, -1.0);
            }
            true
        });
        p.add_residual_block(diff, RobustLoss::Trivial, &[x, y])
            .unwrap();
        p.set_constant(y).unwrap();
        assert!(p.is_constant(y).unwrap());
        let s = p.solve(&tight()).unwrap();
        assert_eq!(p.parameters(y).unwrap(), &[-3.0, 0.5]);
        let xv = p.parameters(x).unwrap();
        assert!((xv[0] + 3.0).abs() < 1e-12 && (xv[1] - 0.5).abs() < 1e-12);
        assert_eq!(s.tangent_size, 2);
        // All constant: nothing to do.
        p.set_constant(x).unwrap();
        let s = p.solve(&tight()).unwrap();
        assert_eq!(s.termination, Termination::Trivial);
        p.set_variable(x).unwrap();
        assert!(!p.is_constant(x).unwrap());
    }

    #[test]
    fn subset_manifold_keeps_its_fixed_coordinates() {
        let mut p = Problem::new();
        let x = p.add_parameter_block(&[0.0, 5.0, 0.0]);
        p.set_manifold(x, Arc::new(SubsetManifold::new(3, &[1]).unwrap()))
            .unwrap();
        let target = [1.0, -2.0, 3.0];
        let cost = numeric(3, &[3], move |v, r| {
            for ((rk, x), t) in r.iter_mut().zip(v[0]).zip(&target) {
                *rk = x - t;
            }
            // Couple the coordinates so the fixed one matters.
            r[0] += 0.1 * v[0][1];
            true
        });
        p.add_residual_block(cost, RobustLoss::Trivial, &[x])
            .unwrap();
        let s = p.solve(&tight()).unwrap();
        let v = p.parameters(x).unwrap();
        assert_eq!(v[1], 5.0);
        assert!((v[0] - 0.5).abs() < 1e-8, "{v:?}");
        assert!((v[2] - 3.0).abs() < 1e-8, "{v:?}");
        assert_eq!(s.tangent_size, 2);
        // Wrong ambient size is an error.
        assert!(matches!(
            p.set_manifold(x, Arc::new(QuaternionManifold)),
            Err(NllsError::SizeMismatch { .. })
        ));
    }

    /// A rigid motion `q = R p + t` of 3-D points.
    type PoseData = (Vec<[f64; 3]>, Vec<[f64; 3]>, [f64; 3], [f64; 3]);

    fn pose_data() -> PoseData {
        let mut rng = TestRng(5);
        let w_true = [0.4, -0.7, 1.1];
        let t_true = [0.5, -1.0, 2.0];
        let r = rodrigues(w_true);
        let points: Vec<[f64; 3]> = (0..20)
            .map(|_| [rng.normal(), rng.normal(), rng.normal()])
            .collect();
        let observed = points
            .iter()
            .map(|p| {
                let q = r * nalgebra::Vector3::from(*p);
                [q.x + t_true[0], q.y + t_true[1], q.z + t_true[2]]
            })
            .collect();
        (points, observed, w_true, t_true)
    }

    #[test]
    fn rigid_pose_with_angle_axis_and_quaternion() {
        let (points, observed, w_true, t_true) = pose_data();
        let r_true = rodrigues(w_true);
        // Angle-axis on SO(3).
        let mut p = Problem::new();
        let w = p.add_parameter_block(&[0.0, 0.0, 0.0]);
        let t = p.add_parameter_block(&[0.0, 0.0, 0.0]);
        p.set_manifold(w, Arc::new(AngleAxisManifold)).unwrap();
        for (a, b) in points.iter().zip(&observed) {
            let (a, b) = (*a, *b);
            let cost = numeric(3, &[3, 3], move |v, r| {
                let q = rodrigues([v[0][0], v[0][1], v[0][2]]) * nalgebra::Vector3::from(a);
                for (k, rk) in r.iter_mut().enumerate() {
                    *rk = q[k] + v[1][k] - b[k];
                }
                true
            });
            p.add_residual_block(cost, RobustLoss::Trivial, &[w, t])
                .unwrap();
        }
        let s = p.solve(&tight()).unwrap();
        assert!(s.final_cost < 1e-16, "{}", s.final_cost);
        let wv = p.parameters(w).unwrap();
        let r = rodrigues([wv[0], wv[1], wv[2]]);
        assert!((r - r_true).abs().max() < 1e-7);
        for (estimate, truth) in p.parameters(t).unwrap().iter().zip(&t_true) {
            assert!((estimate - truth).abs() < 1e-7);
        }
        // Unit quaternion.
        let mut p = Problem::new();
        let q = p.add_parameter_block(&[1.0, 0.0, 0.0, 0.0]);
        let t = p.add_parameter_block(&[0.0, 0.0, 0.0]);
        p.set_manifold(q, Arc::new(QuaternionManifold)).unwrap();
        for (a, b) in points.iter().zip(&observed) {
            let (a, b) = (*a, *b);
            let cost = numeric(3, &[4, 3], move |v, r| {
                let qv = [v[0][0], v[0][1], v[0][2], v[0][3]];
                let n2: f64 = qv.iter().map(|x| x * x).sum();
                // q p q* / ‖q‖².
                let rotated = quaternion_product(
                    &quaternion_product(&qv, &[0.0, a[0], a[1], a[2]]),
                    &[qv[0], -qv[1], -qv[2], -qv[3]],
                );
                for k in 0..3 {
                    r[k] = rotated[k + 1] / n2 + v[1][k] - b[k];
                }
                true
            });
            p.add_residual_block(cost, RobustLoss::Trivial, &[q, t])
                .unwrap();
        }
        let s = p.solve(&tight()).unwrap();
        assert!(s.final_cost < 1e-16, "{}", s.final_cost);
        let qv = p.parameters(q).unwrap();
        let n: f64 = qv.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!((n - 1.0).abs() < 1e-12, "stays unit: {n}");
        let uq = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            qv[0], qv[1], qv[2], qv[3],
        ));
        assert!((uq.to_rotation_matrix().matrix() - r_true).abs().max() < 1e-7);
        for (estimate, truth) in p.parameters(t).unwrap().iter().zip(&t_true) {
            assert!((estimate - truth).abs() < 1e-7);
        }
    }

    #[test]
    fn covariance_whitening_matches_prescaled_residuals() {
        // Fit a scalar `a` to noisy 2-D observations of (a, a²) with a full covariance.
        let sigma: [f64; 4] = [0.5, 0.2, 0.2, 0.3];
        // Σ = C Cᵀ, C lower; L = C⁻¹.
        let c00 = sigma[0].sqrt();
        let c10 = sigma[2] / c00;
        let c11 = (sigma[3] - c10 * c10).sqrt();
        let l = [1.0 / c00, 0.0, -c10 / (c00 * c11), 1.0 / c11];
        let mut rng = TestRng(3);
        let obs: Vec<[f64; 2]> = (0..10)
            .map(|_| [2.0 + 0.5 * rng.normal(), 4.0 + 0.5 * rng.normal()])
            .collect();
        let model = |v: &[f64], o: [f64; 2], r: &mut [f64]| {
            r[0] = v[0] - o[0];
            r[1] = v[0] * v[0] - o[1];
        };
        let mut whitened = Problem::new();
        let x = whitened.add_parameter_block(&[1.0]);
        let mut manual = Problem::new();
        let y = manual.add_parameter_block(&[1.0]);
        let mut plain = Problem::new();
        let z = plain.add_parameter_block(&[1.0]);
        for &o in &obs {
            let raw = numeric(2, &[1], move |v, r| {
                model(v[0], o, r);
                true
            });
            whitened
                .add_residual_block_with_covariance(raw.clone(), RobustLoss::Trivial, &[x], &sigma)
                .unwrap();
            plain
                .add_residual_block(raw, RobustLoss::Trivial, &[z])
                .unwrap();
            let prescaled = numeric(2, &[1], move |v, r| {
                let mut raw = [0.0; 2];
                model(v[0], o, &mut raw);
                r[0] = l[0] * raw[0] + l[1] * raw[1];
                r[1] = l[2] * raw[0] + l[3] * raw[1];
                true
            });
            manual
                .add_residual_block(prescaled, RobustLoss::Trivial, &[y])
                .unwrap();
        }
        assert!((whitened.cost().unwrap() - manual.cost().unwrap()).abs() < 1e-9);
        let sw = whitened.solve(&tight()).unwrap();
        let sm = manual.solve(&tight()).unwrap();
        let (a, b) = (
            whitened.parameters(x).unwrap()[0],
            manual.parameters(y).unwrap()[0],
        );
        assert!((a - b).abs() < 1e-9, "{a} {b}");
        assert!((sw.final_cost - sm.final_cost).abs() < 1e-9);
        assert!((a - 2.0).abs() < 0.3, "{a}");
        // The weighting matters: the unweighted fit lands elsewhere.
        plain.solve(&tight()).unwrap();
        let c = plain.parameters(z).unwrap()[0];
        assert!((a - c).abs() > 1e-4, "{a} {c}");
        // Bad covariances are errors.
        let cost = numeric(2, &[1], |_, r| {
            r.fill(0.0);
            true
        });
        for bad in [
            vec![1.0, 2.0, 2.0, 1.0],
            vec![1.0, 0.0, 0.0, -1.0],
            vec![1.0, 0.5, 0.0, 1.0],
            vec![1.0, 0.0, 0.0],
            vec![f64::NAN, 0.0, 0.0, 1.0],
        ] {
            assert!(matches!(
                plain.add_residual_block_with_covariance(
                    cost.clone(),
                    RobustLoss::Trivial,
                    &[z],
                    &bad
                ),
                Err(NllsError::BadCovariance(_))
            ));
        }
    }

    #[test]
    fn numeric_diff_agrees_with_analytic_jacobians() {
        let analytic_cost = exponential_residual(1.7, 3.0);
        let numeric_cost = NumericDiffCost::new(1, &[1, 1], |p: &[&[f64]], r: &mut [f64]| {
            r[0] = 3.0 - (p[0][0] * 1.7 + p[1][0]).exp();
            true
        });
        for (m, c) in [(0.3, 0.1), (0.0, 0.0), (-1.2, 2.5)] {
            let params: [&[f64]; 2] = [&[m], &[c]];
            let (mut ra, mut rn) = ([0.0], [0.0]);
            let (mut ja0, mut ja1, mut jn0, mut jn1) = ([0.0], [0.0], [0.0], [0.0]);
            let mut ja = [Some(&mut ja0[..]), Some(&mut ja1[..])];
            assert!(analytic_cost.evaluate(&params, &mut ra, Some(&mut ja)));
            let mut jn = [Some(&mut jn0[..]), Some(&mut jn1[..])];
            assert!(numeric_cost.evaluate(&params, &mut rn, Some(&mut jn)));
            assert_eq!(ra, rn);
            for (a, n) in [(ja0[0], jn0[0]), (ja1[0], jn1[0])] {
                assert!((a - n).abs() < 1e-7 * (1.0 + a.abs()), "{a} vs {n}");
            }
        }
        // A missing Jacobian entry is skipped.
        let mut r = [0.0];
        let mut j1 = [7.0];
        let mut js = [None, Some(&mut j1[..])];
        assert!(numeric_cost.evaluate(&[&[0.3], &[0.1]], &mut r, Some(&mut js)));
        assert!((j1[0] + (0.3f64 * 1.7 + 0.1).exp()).abs() < 1e-6);
    }

    /// A 2-D pose graph: a loop of poses (x, y, θ), odometry and loop closures with noise,
    /// the first pose constant.
    fn pose_graph(poses: usize, seed: u64) -> (Problem, Vec<BlockId>) {
        let mut rng = TestRng(seed);
        let truth: Vec<[f64; 3]> = (0..poses)
            .map(|i| {
                let a = i as f64 * 2.0 * std::f64::consts::PI / poses as f64;
                [
                    10.0 * a.cos(),
                    10.0 * a.sin(),
                    a + std::f64::consts::FRAC_PI_2,
                ]
            })
            .collect();
        let relative = |a: &[f64], b: &[f64]| {
            let (c, s) = (a[2].cos(), a[2].sin());
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let d = b[2] - a[2];
            [c * dx + s * dy, -s * dx + c * dy, d.sin().atan2(d.cos())]
        };
        let mut p = Problem::new();
        // Start from integrated noisy odometry.
        let mut edges = Vec::new();
        for i in 0..poses {
            edges.push((i, (i + 1) % poses));
            if i % 10 == 0 {
                edges.push((i, (i + poses / 2) % poses));
            }
        }
        let measured: Vec<[f64; 3]> = edges
            .iter()
            .map(|&(a, b)| {
                let z = relative(&truth[a], &truth[b]);
                [
                    z[0] + 0.05 * rng.normal(),
                    z[1] + 0.05 * rng.normal(),
                    z[2] + 0.01 * rng.normal(),
                ]
            })
            .collect();
        let mut start = vec![truth[0]];
        for i in 1..poses {
            let prev = start[i - 1];
            let z = measured[edges.iter().position(|&e| e == (i - 1, i)).unwrap_or(0)];
            let (c, s) = (prev[2].cos(), prev[2].sin());
            start.push([
                prev[0] + c * z[0] - s * z[1],
                prev[1] + s * z[0] + c * z[1],
                prev[2] + z[2],
            ]);
        }
        let ids: Vec<BlockId> = start.iter().map(|v| p.add_parameter_block(v)).collect();
        p.set_constant(ids[0]).unwrap();
        for (&(a, b), z) in edges.iter().zip(measured) {
            let cost = numeric(3, &[3, 3], move |v, r| {
                let e = relative(v[0], v[1]);
                r[0] = e[0] - z[0];
                r[1] = e[1] - z[1];
                let d = e[2] - z[2];
                r[2] = d.sin().atan2(d.cos());
                true
            });
            let covariance = [0.0025, 0.0, 0.0, 0.0, 0.0025, 0.0, 0.0, 0.0, 1e-4];
            p.add_residual_block_with_covariance(
                cost,
                RobustLoss::Trivial,
                &[ids[a], ids[b]],
                &covariance,
            )
            .unwrap();
        }
        (p, ids)
    }

    fn all_parameters(p: &Problem, ids: &[BlockId]) -> Vec<f64> {
        ids.iter()
            .flat_map(|&b| p.parameters(b).unwrap().to_vec())
            .collect()
    }

    #[test]
    fn dense_and_sparse_cholesky_agree_on_a_pose_graph() {
        let (start, ids) = pose_graph(150, 8);
        let mut results = Vec::new();
        for solver in [LinearSolverType::Auto, LinearSolverType::DenseCholesky] {
            let (mut p, _) = pose_graph(150, 8);
            let s = p
                .solve(&SolverOptions {
                    linear_solver: solver,
                    ..tight()
                })
                .unwrap();
            // ½ χ² of 495 whitened residuals with 447 degrees of freedom: about 24.
            assert!(
                s.final_cost < 40.0 && s.final_cost < 0.05 * s.initial_cost,
                "{} → {}",
                s.initial_cost,
                s.final_cost
            );
            assert!(s.tangent_size > DENSE_MAX_TANGENT_SIZE);
            results.push((s, all_parameters(&p, &ids)));
        }
        assert_eq!(results[0].0.linear_solver, LinearSolverType::SparseCholesky);
        assert_eq!(results[1].0.linear_solver, LinearSolverType::DenseCholesky);
        let diff = results[0]
            .1
            .iter()
            .zip(&results[1].1)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff < 1e-9, "dense vs sparse differ by {diff}");
        // The constant first pose did not move.
        assert_eq!(&results[0].1[..3], start.parameters(ids[0]).unwrap());
    }

    #[test]
    fn bit_identical_for_one_and_two_threads() {
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut out = Vec::new();
                for strategy in [
                    TrustRegionStrategy::LevenbergMarquardt,
                    TrustRegionStrategy::Dogleg,
                ] {
                    let (mut p, ids) = pose_graph(100, 21);
                    let s = p
                        .solve(&SolverOptions {
                            strategy,
                            linear_solver: LinearSolverType::SparseCholesky,
                            ..SolverOptions::default()
                        })
                        .unwrap();
                    // Timings are the one thing allowed to differ.
                    let mut s = s;
                    s.history.iter_mut().for_each(|h| h.time_s = 0.0);
                    out.push((s, all_parameters(&p, &ids)));
                }
                out
            })
        };
        let (one, two) = (run(1), run(2));
        for ((s1, x1), (s2, x2)) in one.iter().zip(&two) {
            assert_eq!(s1, s2);
            assert!(x1.iter().zip(x2).all(|(a, b)| a.to_bits() == b.to_bits()));
            assert!(s1.successful_steps > 1);
        }
    }

    #[test]
    fn nan_initial_cost_and_bad_construction_are_errors() {
        let mut p = Problem::new();
        let x = p.add_parameter_block(&[f64::NAN]);
        let cost = analytic(1, &[1], |v, r, mut j| {
            r[0] = v[0][0];
            set_jacobian(&mut j, 0, 0, 1.0);
            true
        });
        p.add_residual_block(cost.clone(), RobustLoss::Trivial, &[x])
            .unwrap();
        assert!(matches!(
            p.solve(&SolverOptions::default()),
            Err(NllsError::NonFiniteInitialCost(_))
        ));
        // A cost function that fails at the start.
        let mut q = Problem::new();
        let y = q.add_parameter_block(&[1.0]);
        let failing = analytic(1, &[1], |_, _, _| false);
        q.add_residual_block(failing, RobustLoss::Trivial, &[y])
            .unwrap();
        assert!(matches!(
            q.solve(&SolverOptions::default()),
            Err(NllsError::NonFiniteInitialCost(_))
        ));
        // Construction errors.
        let z = p.add_parameter_block(&[1.0, 2.0]);
        assert!(matches!(
            p.add_residual_block(cost.clone(), RobustLoss::Trivial, &[z]),
            Err(NllsError::BlockSizeMismatch { .. })
        ));
        assert!(matches!(
            p.add_residual_block(cost.clone(), RobustLoss::Trivial, &[BlockId(42)]),
            Err(NllsError::UnknownBlock(42))
        ));
        assert!(matches!(
            p.set_constant(BlockId(9)),
            Err(NllsError::UnknownBlock(9))
        ));
        assert!(matches!(
            p.set_parameters(z, &[1.0]),
            Err(NllsError::SizeMismatch { .. })
        ));
        let pair = analytic(1, &[1, 1], |_, r, _| {
            r[0] = 0.0;
            true
        });
        assert!(matches!(
            p.add_residual_block(pair, RobustLoss::Trivial, &[x, x]),
            Err(NllsError::DuplicateBlock(_))
        ));
    }

    #[test]
    fn failed_steps_are_rejected_not_fatal() {
        // r = 1/√x − ½ cannot be evaluated for x < 0; from x = 12 the Gauss–Newton step
        // (x ← 3x − x^{3/2}) lands at −5.6: rejected, the region shrinks, the solve goes on.
        let mut p = Problem::new();
        let x = p.add_parameter_block(&[12.0]);
        let cost = analytic(1, &[1], |v, r, mut j| {
            if v[0][0] < 0.0 {
                return false;
            }
            let s = v[0][0].sqrt();
            r[0] = 1.0 / s - 0.5;
            set_jacobian(&mut j, 0, 0, -0.5 / (s * v[0][0]));
            true
        });
        p.add_residual_block(cost, RobustLoss::Trivial, &[x])
            .unwrap();
        let s = p.solve(&tight()).unwrap();
        assert!(s.unsuccessful_steps >= 1, "{s:?}");
        assert!(
            (p.parameters(x).unwrap()[0] - 4.0).abs() < 1e-6,
            "{:?}",
            p.parameters(x)
        );
    }
}
