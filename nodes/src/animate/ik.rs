//! Inverse kinematics for a joint chain: cyclic coordinate descent and
//! damped least squares, with hinge and cone joint limits.
//!
//! A *chain* is a list of joint indices from the root to the end-effector
//! joint, each the parent of the next. The end effector is the point
//! `end_offset` in the last chain joint's frame. The solvers change only the
//! local rotations of the chain joints (see
//! [`Skeleton::pose_from_local_rotations`](super::skeleton::Skeleton::pose_from_local_rotations)
//! for the convention `parent_from_joint = rest · R(local)`).
//!
//! * [`IkMethod::Ccd`]: cyclic coordinate descent (Wang & Chen 1991, "A
//!   combined optimization method for solving the inverse kinematics problem
//!   of mechanical manipulators", IEEE Trans. Robotics and Automation 7(4);
//!   popularised for games by Lander 1998, "Oh my god, I inverted kine!").
//!   From the end toward the root, each joint is rotated so that
//!   joint→effector points along joint→target, then projected onto its limit.
//! * [`IkMethod::DampedLeastSquares`]: damped least squares (Wampler 1986,
//!   "Manipulator inverse kinematic solutions based on vector formulations and
//!   damped least-squares methods"; Nakamura & Hanafusa 1986, "Inverse
//!   kinematic solutions with singularity robustness for robot manipulator
//!   control"; survey: Buss 2004, "Introduction to inverse kinematics with
//!   Jacobian transpose, pseudoinverse and damped least squares methods").
//!   `Δθ = Jᵀ (J Jᵀ + λ² I)⁻¹ e` with a clamped error `e`, a clamped step and
//!   an adaptive λ: a step is kept only if it lowers the error (then λ is
//!   halved), otherwise it is discarded and λ is multiplied by four. Limits
//!   are projected after each step (no active set: a step pushed back by a
//!   limit is simply judged by the error it achieves). When DLS stops
//!   without reaching the target, one CCD sweep is tried and kept only if it
//!   lowers the error; it lines a stretched chain up with the target exactly.
//!
//! # Joint limits
//!
//! Limits are expressed relative to the joint's rest orientation, i.e. on the
//! local rotation `R(local)`:
//!
//! * [`JointLimit::Hinge`]: the local rotation is a rotation about `axis`
//!   (given in the joint's own frame) by an angle in `[min_rad, max_rad]`
//!   (angles are measured in `(−π, π]`, so meaningful limits lie in that
//!   range). Anything else is projected onto the hinge by keeping only the
//!   twist about the axis (swing–twist decomposition), then clamping the
//!   angle to the nearest bound (measured around the circle).
//! * [`JointLimit::Cone`]: the angle between the rotated and the rest
//!   direction of the child bone (towards the next chain joint, or
//!   `end_offset` for the last joint) is at most `max_rad`. Twist about the
//!   bone is not limited. A violating rotation keeps its twist and has its
//!   swing shortened to `max_rad`. A zero-length bone makes the cone vacuous.

use nalgebra::{Isometry3, Matrix3, Point3, Unit, UnitQuaternion, Vector3};

use super::skeleton::{AnimateError, Skeleton, rotation_is_finite};

/// A joint limit for one chain joint, relative to its rest orientation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointLimit {
    /// Any rotation.
    Free,
    /// Rotation only about `axis` (joint frame, need not be unit length) by an
    /// angle in `[min_rad, max_rad]` ⊆ `[−π, π]`.
    Hinge {
        /// Hinge axis in the joint's frame.
        axis: Vector3<f64>,
        /// Smallest allowed angle (radians).
        min_rad: f64,
        /// Largest allowed angle (radians).
        max_rad: f64,
    },
    /// The child bone may swing at most `max_rad` away from its rest
    /// direction; twist about the bone is free.
    Cone {
        /// Largest swing angle (radians).
        max_rad: f64,
    },
}

/// Which solver [`solve_ik`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IkMethod {
    /// Cyclic coordinate descent (Wang & Chen 1991; Lander 1998).
    Ccd,
    /// Damped least squares (Wampler 1986; Nakamura & Hanafusa 1986; Buss 2004).
    DampedLeastSquares,
}

/// Options for [`solve_ik`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkOptions {
    /// Maximum number of iterations: CCD sweeps, or DLS step attempts
    /// (including discarded ones). Default 100.
    pub max_iterations: usize,
    /// Distance to the target (scene units) at which the solve stops and
    /// counts as reached. Default `1e-5`.
    pub tolerance: f64,
    /// Relative DLS damping: the initial λ is `damping ×` the chain's reach
    /// (sum of link lengths and `|end_offset|`), which keeps the solver scale
    /// invariant. Must be positive. Default `0.05`. Unused by CCD.
    pub damping: f64,
    /// Solver. Default [`IkMethod::DampedLeastSquares`].
    pub method: IkMethod,
}

impl Default for IkOptions {
    fn default() -> Self {
        IkOptions {
            max_iterations: 100,
            tolerance: 1e-5,
            damping: 0.05,
            method: IkMethod::DampedLeastSquares,
        }
    }
}

/// Why a solve stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IkTermination {
    /// The error fell to the tolerance.
    Converged,
    /// The iteration cap was hit first.
    MaxIterations,
    /// No further progress was possible (an unreachable target, joint limits,
    /// or a chain that cannot move the effector).
    Stalled,
}

/// Outcome of [`solve_ik`].
#[derive(Debug, Clone, PartialEq)]
pub struct IkReport {
    /// Local rotations of all skeleton joints; only chain joints differ from
    /// the input (and those always satisfy their limits).
    pub local_rotations: Vec<UnitQuaternion<f64>>,
    /// Iterations performed (CCD sweeps or DLS step attempts).
    pub iterations: usize,
    /// Final distance from the end effector to the target.
    pub error: f64,
    /// `error <= tolerance`.
    pub reached: bool,
    /// Whether the target is within the chain's geometric reach, ignoring
    /// limits: `min_reach ≤ |target − root| ≤ max_reach`, where `max_reach`
    /// is the sum of link lengths and `min_reach = max(0, 2·longest − sum)`.
    /// A reachable target may still not be reached when limits forbid it.
    pub reachable: bool,
    /// Error after projecting the start pose onto the limits, then after each
    /// iteration (`iterations + 1` entries). For DLS it is non-increasing
    /// (discarded steps repeat the previous value); for CCD a limit
    /// projection can occasionally raise it, and the best pose seen is
    /// returned.
    pub error_history: Vec<f64>,
    /// Why the solve stopped.
    pub termination: IkTermination,
}

/// A limit with validated, normalized parameters.
#[derive(Debug, Clone, Copy)]
enum Limit {
    Free,
    Hinge {
        axis: Unit<Vector3<f64>>,
        min_rad: f64,
        max_rad: f64,
    },
    Cone {
        max_rad: f64,
    },
}

fn validate_limit(index: usize, limit: &JointLimit) -> Result<Limit, AnimateError> {
    match *limit {
        JointLimit::Free => Ok(Limit::Free),
        JointLimit::Hinge {
            axis,
            min_rad,
            max_rad,
        } => {
            if !axis.iter().all(|v| v.is_finite()) || !min_rad.is_finite() || !max_rad.is_finite() {
                return Err(AnimateError::NonFinite {
                    what: "joint limits",
                    index,
                });
            }
            let axis = Unit::try_new(axis, 1e-12).ok_or_else(|| {
                AnimateError::InvalidArgument(format!("hinge axis of chain joint {index} is zero"))
            })?;
            if min_rad > max_rad {
                return Err(AnimateError::InvalidArgument(format!(
                    "hinge limits of chain joint {index}: min {min_rad} > max {max_rad}"
                )));
            }
            Ok(Limit::Hinge {
                axis,
                min_rad,
                max_rad,
            })
        }
        JointLimit::Cone { max_rad } => {
            if !max_rad.is_finite() {
                return Err(AnimateError::NonFinite {
                    what: "joint limits",
                    index,
                });
            }
            if max_rad < 0.0 {
                return Err(AnimateError::InvalidArgument(format!(
                    "cone limit of chain joint {index} is negative"
                )));
            }
            Ok(Limit::Cone { max_rad })
        }
    }
}

/// Wraps an angle into `(−π, π]`.
fn wrap_angle(angle: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    let wrapped = angle - tau * ((angle + std::f64::consts::PI) / tau).floor();
    // `wrapped` is in [−π, π); map −π to π.
    if wrapped <= -std::f64::consts::PI {
        wrapped + tau
    } else {
        wrapped
    }
}

/// Signed angle of the twist of `rotation` about the unit `axis`, in `(−π, π]`
/// (swing–twist decomposition).
fn twist_angle(rotation: &UnitQuaternion<f64>, axis: &Unit<Vector3<f64>>) -> f64 {
    let q = rotation.quaternion();
    let s = q.imag().dot(axis);
    wrap_angle(2.0 * s.atan2(q.w))
}

/// Clamps `angle` (in `(−π, π]`) to `[min, max]`, choosing the bound nearest
/// around the circle when outside.
fn clamp_angle(angle: f64, min: f64, max: f64) -> f64 {
    if (min..=max).contains(&angle) {
        return angle;
    }
    let to_min = wrap_angle(angle - min).abs();
    let to_max = wrap_angle(angle - max).abs();
    if to_min <= to_max { min } else { max }
}

/// Removes rounding drift from a unit quaternion's norm.
fn renormalize(q: UnitQuaternion<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::new_normalize(q.into_inner())
}

/// Any unit vector perpendicular to `v` (which must be non-zero).
fn perpendicular(v: &Vector3<f64>) -> Unit<Vector3<f64>> {
    let helper = if v.x.abs() <= v.y.abs() && v.x.abs() <= v.z.abs() {
        Vector3::x()
    } else if v.y.abs() <= v.z.abs() {
        Vector3::y()
    } else {
        Vector3::z()
    };
    Unit::new_normalize(v.cross(&helper))
}

/// The shortest rotation taking direction `from` to direction `to` (both
/// non-zero); a half turn about a perpendicular axis when they are opposite.
fn rotation_between(from: &Vector3<f64>, to: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::rotation_between(from, to).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&perpendicular(from), std::f64::consts::PI)
    })
}

/// Projects a local rotation onto a limit; `bone` is the child-bone vector in
/// the joint's frame (used by cones).
fn project(
    limit: &Limit,
    rotation: &UnitQuaternion<f64>,
    bone: &Vector3<f64>,
) -> UnitQuaternion<f64> {
    match limit {
        Limit::Free => *rotation,
        Limit::Hinge {
            axis,
            min_rad,
            max_rad,
        } => {
            let angle = clamp_angle(twist_angle(rotation, axis), *min_rad, *max_rad);
            UnitQuaternion::from_axis_angle(axis, angle)
        }
        Limit::Cone { max_rad } => {
            let length = bone.norm();
            if length <= 1e-300 {
                return *rotation;
            }
            let rest_direction = bone / length;
            let rotated = rotation * rest_direction;
            let swing_angle = rest_direction.dot(&rotated).clamp(-1.0, 1.0).acos();
            if swing_angle <= *max_rad {
                return *rotation;
            }
            let swing = rotation_between(&rest_direction, &rotated);
            let twist = swing.inverse() * rotation;
            let swing_axis = swing
                .axis()
                .unwrap_or_else(|| perpendicular(&rest_direction));
            renormalize(UnitQuaternion::from_axis_angle(&swing_axis, *max_rad) * twist)
        }
    }
}

/// Angle of the swing of `rotation` that moves the unit `rest_direction`.
#[cfg(test)]
fn swing_angle(rotation: &UnitQuaternion<f64>, rest_direction: &Vector3<f64>) -> f64 {
    rest_direction
        .dot(&(rotation * rest_direction))
        .clamp(-1.0, 1.0)
        .acos()
}

/// A validated solve.
struct Problem<'a> {
    skeleton: &'a Skeleton,
    chain: &'a [usize],
    limits: Vec<Limit>,
    /// Child-bone vector of each chain joint, in the joint's frame.
    bones: Vec<Vector3<f64>>,
    end_offset: Point3<f64>,
    target: Point3<f64>,
    reach: f64,
}

/// Forward-kinematics snapshot of a pose.
struct State {
    rotations: Vec<UnitQuaternion<f64>>,
    world_from_joint: Vec<Isometry3<f64>>,
    effector: Point3<f64>,
    error: f64,
}

impl Problem<'_> {
    fn evaluate(&self, rotations: Vec<UnitQuaternion<f64>>) -> State {
        let world_from_joint = self
            .skeleton
            .world_from_local_rotations_unchecked(&rotations);
        let effector = self
            .chain
            .last()
            .and_then(|last| world_from_joint.get(*last))
            .map_or(self.end_offset, |world| world * self.end_offset);
        let error = (self.target - effector).norm();
        State {
            rotations,
            world_from_joint,
            effector,
            error,
        }
    }

    fn joint_position(&self, state: &State, joint: usize) -> Point3<f64> {
        state
            .world_from_joint
            .get(joint)
            .map_or_else(Point3::origin, |world| world * Point3::origin())
    }

    fn world_rotation(&self, state: &State, joint: usize) -> UnitQuaternion<f64> {
        state
            .world_from_joint
            .get(joint)
            .map_or_else(UnitQuaternion::identity, |world| world.rotation)
    }

    fn local(&self, state: &State, joint: usize) -> UnitQuaternion<f64> {
        state
            .rotations
            .get(joint)
            .copied()
            .unwrap_or_else(UnitQuaternion::identity)
    }

    /// Rotation of the joint's rest-oriented frame before its local rotation:
    /// `world_rotation = frame · local`, computed as the parent's world
    /// rotation times the rest rotation (not via `local⁻¹`, which would let
    /// rounding in `local` compound from one update to the next).
    fn pre_frame(&self, state: &State, joint: usize) -> UnitQuaternion<f64> {
        let rest = self
            .skeleton
            .joint(joint)
            .map_or_else(UnitQuaternion::identity, |j| {
                j.parent_from_joint_rest.rotation
            });
        match self.skeleton.parent(joint) {
            Some(parent) => self.world_rotation(state, parent) * rest,
            None => rest,
        }
    }

    /// One CCD update of chain joint `k`, returning its new local rotation
    /// (already projected onto its limit), or `None` when the geometry is
    /// degenerate (effector or target at the joint).
    fn ccd_rotation(&self, state: &State, k: usize) -> Option<UnitQuaternion<f64>> {
        let joint = *self.chain.get(k)?;
        let limit = self.limits.get(k)?;
        let bone = self.bones.get(k)?;
        let position = self.joint_position(state, joint);
        let to_effector = state.effector - position;
        let to_target = self.target - position;
        let scale = self.reach.max(f64::MIN_POSITIVE);
        if to_effector.norm() <= 1e-12 * scale || to_target.norm() <= 1e-12 * scale {
            return None;
        }
        let local = self.local(state, joint);
        let updated = match limit {
            Limit::Hinge { axis, .. } => {
                let world_axis = self.world_rotation(state, joint) * axis.into_inner();
                let u = to_effector - world_axis * world_axis.dot(&to_effector);
                let v = to_target - world_axis * world_axis.dot(&to_target);
                if u.norm() <= 1e-12 * scale || v.norm() <= 1e-12 * scale {
                    return None;
                }
                let delta = world_axis.dot(&u.cross(&v)).atan2(u.dot(&v));
                UnitQuaternion::from_axis_angle(axis, twist_angle(&local, axis) + delta)
            }
            Limit::Free | Limit::Cone { .. } => {
                let world_delta = rotation_between(&to_effector, &to_target);
                let frame = self.pre_frame(state, joint);
                renormalize(frame.inverse() * world_delta * frame * local)
            }
        };
        Some(project(limit, &updated, bone))
    }

    fn with_rotation(&self, state: &State, joint: usize, rotation: UnitQuaternion<f64>) -> State {
        let mut rotations = state.rotations.clone();
        if let Some(slot) = rotations.get_mut(joint) {
            *slot = rotation;
        }
        self.evaluate(rotations)
    }

    /// One CCD sweep from the end joint to the root.
    fn ccd_sweep(&self, mut state: State) -> State {
        for k in (0..self.chain.len()).rev() {
            if let (Some(rotation), Some(joint)) = (self.ccd_rotation(&state, k), self.chain.get(k))
            {
                state = self.with_rotation(&state, *joint, rotation);
            }
        }
        state
    }

    /// World-frame rotation axes of the DLS unknowns: three per free or cone
    /// joint, one per hinge. Each entry is (chain index, world axis).
    fn dls_axes(&self, state: &State) -> Vec<(usize, Vector3<f64>)> {
        let mut axes = Vec::with_capacity(3 * self.chain.len());
        for (k, (joint, limit)) in self.chain.iter().zip(&self.limits).enumerate() {
            match limit {
                Limit::Hinge { axis, .. } => {
                    axes.push((k, self.world_rotation(state, *joint) * axis.into_inner()));
                }
                Limit::Free | Limit::Cone { .. } => {
                    axes.push((k, Vector3::x()));
                    axes.push((k, Vector3::y()));
                    axes.push((k, Vector3::z()));
                }
            }
        }
        axes
    }

    /// One damped-least-squares step with damping `lambda`: the new, limited
    /// pose, or `None` when the damped system cannot be solved.
    fn dls_step(&self, state: &State, lambda: f64) -> Option<State> {
        let axes = self.dls_axes(state);
        let columns: Vec<Vector3<f64>> = axes
            .iter()
            .map(|(k, axis)| {
                let joint = self.chain.get(*k).copied().unwrap_or(0);
                axis.cross(&(state.effector - self.joint_position(state, joint)))
            })
            .collect();
        // Clamp the task-space error (Buss 2004) so far targets give steady
        // steps along the local linearization.
        let mut error = self.target - state.effector;
        let max_error = 0.5 * self.reach;
        let norm = error.norm();
        if norm > max_error {
            error *= max_error / norm;
        }
        let mut jjt = Matrix3::identity() * (lambda * lambda);
        for column in &columns {
            jjt += column * column.transpose();
        }
        let solved = jjt.cholesky()?.solve(&error);
        let mut deltas: Vec<f64> = columns.iter().map(|c| c.dot(&solved)).collect();
        // Clamp the step: no joint turns by more than `MAX_STEP` radians.
        const MAX_STEP: f64 = 0.5;
        let mut per_joint = vec![0.0_f64; self.chain.len()];
        for ((k, _), delta) in axes.iter().zip(&deltas) {
            if let Some(sum) = per_joint.get_mut(*k) {
                *sum += delta * delta;
            }
        }
        let largest = per_joint.iter().fold(0.0_f64, |m, s| m.max(s.sqrt()));
        if !largest.is_finite() {
            return None;
        }
        if largest > MAX_STEP {
            let shrink = MAX_STEP / largest;
            deltas.iter_mut().for_each(|d| *d *= shrink);
        }
        let mut world_increments = vec![Vector3::zeros(); self.chain.len()];
        for ((k, axis), delta) in axes.iter().zip(&deltas) {
            if let Some(increment) = world_increments.get_mut(*k) {
                *increment += axis * *delta;
            }
        }
        let mut rotations = state.rotations.clone();
        for (k, ((joint, limit), increment)) in self
            .chain
            .iter()
            .zip(&self.limits)
            .zip(&world_increments)
            .enumerate()
        {
            let local = self.local(state, *joint);
            let updated = match limit {
                Limit::Hinge { axis, .. } => {
                    let world_axis = self.world_rotation(state, *joint) * axis.into_inner();
                    let delta = increment.dot(&world_axis);
                    UnitQuaternion::from_axis_angle(axis, twist_angle(&local, axis) + delta)
                }
                Limit::Free | Limit::Cone { .. } => {
                    let frame = self.pre_frame(state, *joint);
                    renormalize(
                        frame.inverse()
                            * UnitQuaternion::from_scaled_axis(*increment)
                            * frame
                            * local,
                    )
                }
            };
            let bone = self.bones.get(k).copied().unwrap_or_else(Vector3::zeros);
            if let Some(slot) = rotations.get_mut(*joint) {
                *slot = project(limit, &updated, &bone);
            }
        }
        Some(self.evaluate(rotations))
    }
}

/// Solves inverse kinematics for `chain` (root → end-effector joint) so that
/// the point `end_offset` in the last chain joint's frame reaches `target`
/// (world frame), starting from `local_rotations` (one per skeleton joint).
///
/// The start pose of the chain joints is first projected onto `limits` (one
/// per chain joint). The solver is [`IkMethod::Ccd`] (Wang & Chen 1991;
/// Lander 1998) or [`IkMethod::DampedLeastSquares`] (Wampler 1986; Nakamura &
/// Hanafusa 1986; Buss 2004), see the module documentation. Iterations are
/// capped by `options.max_iterations`; an unreachable target leaves the chain
/// stretched toward it as far as the limits allow. Degenerate inputs (target
/// at a joint, zero-length links, singular Jacobians) never produce NaN.
pub fn solve_ik(
    skeleton: &Skeleton,
    local_rotations: &[UnitQuaternion<f64>],
    chain: &[usize],
    end_offset: Vector3<f64>,
    target: Point3<f64>,
    limits: &[JointLimit],
    options: &IkOptions,
) -> Result<IkReport, AnimateError> {
    if local_rotations.len() != skeleton.len() {
        return Err(AnimateError::JointCountMismatch {
            what: "local rotations",
            expected: skeleton.len(),
            got: local_rotations.len(),
        });
    }
    if let Some(index) = local_rotations.iter().position(|q| !rotation_is_finite(q)) {
        return Err(AnimateError::NonFinite {
            what: "local rotations",
            index,
        });
    }
    let (&root, _) = chain.split_first().ok_or(AnimateError::EmptyChain)?;
    for &joint in chain {
        if joint >= skeleton.len() {
            return Err(AnimateError::JointIndexOutOfRange {
                index: joint,
                count: skeleton.len(),
            });
        }
    }
    for pair in chain.windows(2) {
        if let [parent, child] = *pair
            && skeleton.parent(child) != Some(parent)
        {
            return Err(AnimateError::ChainNotConnected { parent, child });
        }
    }
    if limits.len() != chain.len() {
        return Err(AnimateError::LengthMismatch {
            what: "joint limits vs chain joints",
            expected: chain.len(),
            got: limits.len(),
        });
    }
    let limits = limits
        .iter()
        .enumerate()
        .map(|(index, limit)| validate_limit(index, limit))
        .collect::<Result<Vec<_>, _>>()?;
    if !end_offset.iter().all(|v| v.is_finite()) {
        return Err(AnimateError::NonFinite {
            what: "end offset",
            index: 0,
        });
    }
    if !target.iter().all(|v| v.is_finite()) {
        return Err(AnimateError::NonFinite {
            what: "target",
            index: 0,
        });
    }
    if !options.tolerance.is_finite() || options.tolerance < 0.0 {
        return Err(AnimateError::InvalidArgument(
            "tolerance must be finite and non-negative".into(),
        ));
    }
    if !options.damping.is_finite() || options.damping <= 0.0 {
        return Err(AnimateError::InvalidArgument(
            "damping must be finite and positive".into(),
        ));
    }

    let bones: Vec<Vector3<f64>> = chain
        .iter()
        .skip(1)
        .map(|child| {
            skeleton.joint(*child).map_or_else(Vector3::zeros, |j| {
                j.parent_from_joint_rest.translation.vector
            })
        })
        .chain(std::iter::once(end_offset))
        .collect();
    let link_lengths: Vec<f64> = bones.iter().map(|b| b.norm()).collect();
    let reach: f64 = link_lengths.iter().sum();
    let longest = link_lengths.iter().fold(0.0_f64, |m, l| m.max(*l));
    let min_reach = (2.0 * longest - reach).max(0.0);

    let problem = Problem {
        skeleton,
        chain,
        limits,
        bones,
        end_offset: Point3::from(end_offset),
        target,
        reach,
    };

    let mut start = local_rotations.to_vec();
    for (k, joint) in chain.iter().enumerate() {
        if let (Some(slot), Some(limit), Some(bone)) = (
            start.get_mut(*joint),
            problem.limits.get(k),
            problem.bones.get(k),
        ) {
            *slot = project(limit, slot, bone);
        }
    }
    let mut state = problem.evaluate(start);
    let root_position = problem.joint_position(&state, root);
    let distance = (target - root_position).norm();
    let slack = 1e-12 * (1.0 + reach + distance);
    let reachable = distance <= reach + slack && distance + slack >= min_reach;

    let mut history = vec![state.error];
    let mut termination = IkTermination::MaxIterations;
    let mut iterations = 0;
    if state.error <= options.tolerance {
        termination = IkTermination::Converged;
    } else if reach <= f64::MIN_POSITIVE {
        // Zero-length chain: no rotation moves the effector.
        termination = IkTermination::Stalled;
    } else {
        match options.method {
            IkMethod::Ccd => {
                let mut best_rotations = state.rotations.clone();
                let mut best_error = state.error;
                while iterations < options.max_iterations {
                    iterations += 1;
                    let previous = state.error;
                    state = problem.ccd_sweep(state);
                    history.push(state.error);
                    if state.error < best_error {
                        best_error = state.error;
                        best_rotations.clone_from(&state.rotations);
                    }
                    if state.error <= options.tolerance {
                        termination = IkTermination::Converged;
                        break;
                    }
                    if (previous - state.error).abs() <= 1e-12 * reach {
                        termination = IkTermination::Stalled;
                        break;
                    }
                }
                if best_error < state.error {
                    state = problem.evaluate(best_rotations);
                }
            }
            IkMethod::DampedLeastSquares => {
                let initial_lambda = options.damping * reach;
                let min_lambda = 1e-6 * reach;
                let max_lambda = 1e6 * reach.max(initial_lambda);
                let mut lambda = initial_lambda;
                while iterations < options.max_iterations {
                    iterations += 1;
                    match problem.dls_step(&state, lambda) {
                        Some(next) if next.error < state.error => {
                            state = next;
                            lambda = (lambda * 0.5).max(min_lambda);
                        }
                        _ => lambda *= 4.0,
                    }
                    history.push(state.error);
                    if state.error <= options.tolerance {
                        termination = IkTermination::Converged;
                        break;
                    }
                    if lambda > max_lambda {
                        termination = IkTermination::Stalled;
                        break;
                    }
                }
                if termination != IkTermination::Converged {
                    // Polish with one CCD sweep (kept only if it helps): it
                    // lines the effector up with the root→target ray, which
                    // the damped steps approach only slowly when stretched.
                    let polished = problem.ccd_sweep(problem.evaluate(state.rotations.clone()));
                    if polished.error < state.error {
                        state = polished;
                        if let Some(last) = history.last_mut() {
                            *last = state.error;
                        }
                        if state.error <= options.tolerance {
                            termination = IkTermination::Converged;
                        }
                    }
                }
            }
        }
    }

    Ok(IkReport {
        reached: state.error <= options.tolerance,
        error: state.error,
        local_rotations: state.rotations,
        iterations,
        reachable,
        error_history: history,
        termination,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

    use super::*;
    use std::f64::consts::PI;

    /// splitmix64: a tiny deterministic generator for test data.
    struct SplitMix64(u64);

    impl SplitMix64 {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }

        /// Uniform in [lo, hi).
        fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
            let unit = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
            lo + (hi - lo) * unit
        }

        fn unit_vector(&mut self) -> Vector3<f64> {
            loop {
                let v = Vector3::new(
                    self.uniform(-1.0, 1.0),
                    self.uniform(-1.0, 1.0),
                    self.uniform(-1.0, 1.0),
                );
                let n = v.norm();
                if n > 0.1 && n <= 1.0 {
                    return v / n;
                }
            }
        }
    }

    struct TestChain {
        skeleton: Skeleton,
        chain: Vec<usize>,
        limits: Vec<JointLimit>,
        end_offset: Vector3<f64>,
        reach: f64,
    }

    /// `n` rotating joints along x plus a tip joint; the effector is the tip.
    /// Limits cycle Free, Hinge (about z, then y), Cone.
    fn test_chain(n: usize) -> TestChain {
        let lengths: Vec<f64> = (0..n).map(|k| 1.0 - 0.1 * (k % 4) as f64).collect();
        let skeleton = Skeleton::chain(&lengths, Vector3::x()).unwrap();
        let limits = (0..n)
            .map(|k| match k % 3 {
                0 => JointLimit::Free,
                1 => JointLimit::Hinge {
                    axis: if k % 2 == 1 {
                        Vector3::z()
                    } else {
                        Vector3::new(0.0, 2.0, 0.0)
                    },
                    min_rad: -2.0,
                    max_rad: 1.5,
                },
                _ => JointLimit::Cone { max_rad: 1.2 },
            })
            .collect();
        let last = lengths.last().copied().unwrap_or(0.0);
        TestChain {
            skeleton,
            chain: (0..n).collect(),
            limits,
            end_offset: Vector3::x() * last,
            reach: lengths.iter().sum(),
        }
    }

    /// Random local rotations within `limits`.
    fn random_pose(rng: &mut SplitMix64, test: &TestChain) -> Vec<UnitQuaternion<f64>> {
        let mut rotations = vec![UnitQuaternion::identity(); test.skeleton.len()];
        for (k, limit) in test.limits.iter().enumerate() {
            rotations[test.chain[k]] = match *limit {
                JointLimit::Free => UnitQuaternion::from_axis_angle(
                    &Unit::new_normalize(rng.unit_vector()),
                    rng.uniform(-PI, PI),
                ),
                JointLimit::Hinge {
                    axis,
                    min_rad,
                    max_rad,
                } => UnitQuaternion::from_axis_angle(
                    &Unit::new_normalize(axis),
                    rng.uniform(min_rad, max_rad),
                ),
                JointLimit::Cone { max_rad } => {
                    let phi = rng.uniform(0.0, 2.0 * PI);
                    let swing_axis = Unit::new_normalize(Vector3::new(0.0, phi.cos(), phi.sin()));
                    let swing =
                        UnitQuaternion::from_axis_angle(&swing_axis, rng.uniform(0.0, max_rad));
                    let twist =
                        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), rng.uniform(-PI, PI));
                    swing * twist
                }
            };
        }
        rotations
    }

    fn effector(test: &TestChain, rotations: &[UnitQuaternion<f64>]) -> Point3<f64> {
        let pose = test.skeleton.pose_from_local_rotations(rotations).unwrap();
        let world = test.skeleton.world_from_joint(&pose).unwrap();
        world[*test.chain.last().unwrap()] * Point3::from(test.end_offset)
    }

    fn assert_limits(test: &TestChain, rotations: &[UnitQuaternion<f64>]) {
        for (k, limit) in test.limits.iter().enumerate() {
            let q = rotations[test.chain[k]];
            match *limit {
                JointLimit::Free => {}
                JointLimit::Hinge {
                    axis,
                    min_rad,
                    max_rad,
                } => {
                    let axis = Unit::new_normalize(axis);
                    let off_axis = q.imag() - axis.into_inner() * q.imag().dot(&axis);
                    assert!(off_axis.norm() < 1e-12, "hinge {k} rotates off-axis: {q:?}");
                    let angle = twist_angle(&q, &axis);
                    assert!(
                        angle >= min_rad - 1e-12 && angle <= max_rad + 1e-12,
                        "hinge {k} angle {angle} outside [{min_rad}, {max_rad}]"
                    );
                }
                JointLimit::Cone { max_rad } => {
                    let bone = if k + 1 < test.chain.len() {
                        test.skeleton
                            .joint(test.chain[k + 1])
                            .unwrap()
                            .parent_from_joint_rest
                            .translation
                            .vector
                    } else {
                        test.end_offset
                    };
                    let angle = swing_angle(&q, &bone.normalize());
                    assert!(
                        angle <= max_rad + 1e-9,
                        "cone {k} angle {angle} > {max_rad}"
                    );
                }
            }
        }
    }

    fn options(method: IkMethod) -> IkOptions {
        IkOptions {
            method,
            ..IkOptions::default()
        }
    }

    #[test]
    fn random_reachable_targets_are_reached_within_limits() {
        for (n, seed) in [(3usize, 1u64), (5, 2), (7, 3)] {
            let test = test_chain(n);
            let mut rng = SplitMix64(seed);
            let start = vec![UnitQuaternion::identity(); test.skeleton.len()];
            let targets: Vec<Point3<f64>> = (0..12)
                .map(|_| effector(&test, &random_pose(&mut rng, &test)))
                .collect();
            for method in [IkMethod::Ccd, IkMethod::DampedLeastSquares] {
                let mut iteration_counts = Vec::new();
                let mut worst: f64 = 0.0;
                for &target in &targets {
                    let max_iterations = match method {
                        // CCD converges linearly; on the 3-joint chain (Free,
                        // Hinge, Cone: barely redundant) it needs up to ~1000
                        // sweeps. A sweep costs one FK per chain joint.
                        IkMethod::Ccd => 2000,
                        // DLS uses the default cap.
                        IkMethod::DampedLeastSquares => 100,
                    };
                    let report = solve_ik(
                        &test.skeleton,
                        &start,
                        &test.chain,
                        test.end_offset,
                        target,
                        &test.limits,
                        &IkOptions {
                            max_iterations,
                            ..options(method)
                        },
                    )
                    .unwrap();
                    assert!(report.reachable);
                    assert!(
                        report.error <= 1e-4,
                        "{method:?} n={n}: error {} after {} iterations ({:?}), target {target}",
                        report.error,
                        report.iterations,
                        report.termination
                    );
                    // The reported error is the real distance.
                    let reached = effector(&test, &report.local_rotations);
                    assert!(((reached - target).norm() - report.error).abs() < 1e-12);
                    assert_limits(&test, &report.local_rotations);
                    // Joints outside the chain (the tip) are untouched.
                    assert_eq!(report.local_rotations[n], start[n]);
                    assert_eq!(report.error_history.len(), report.iterations + 1);
                    if method == IkMethod::DampedLeastSquares {
                        assert!(
                            report.error_history.windows(2).all(|w| w[1] <= w[0]),
                            "DLS history increased: {:?}",
                            report.error_history
                        );
                    }
                    iteration_counts.push(report.iterations);
                    worst = worst.max(report.error);
                }
                println!(
                    "IK {method:?} {n} joints: iterations {iteration_counts:?}, worst error {worst:.2e}"
                );
            }
        }
    }

    #[test]
    fn unreachable_target_points_the_chain_at_it() {
        for limited in [false, true] {
            let mut test = test_chain(5);
            if !limited {
                test.limits = vec![JointLimit::Free; 5];
            }
            let start: Vec<UnitQuaternion<f64>> = {
                let mut rng = SplitMix64(99);
                random_pose(&mut rng, &test)
            };
            let direction = Vector3::new(0.3, 0.8, -0.52).normalize();
            let target = Point3::from(direction * 2.0 * test.reach);
            for method in [IkMethod::Ccd, IkMethod::DampedLeastSquares] {
                let report = solve_ik(
                    &test.skeleton,
                    &start,
                    &test.chain,
                    test.end_offset,
                    target,
                    &test.limits,
                    &options(method),
                )
                .unwrap();
                assert!(!report.reachable);
                assert!(!report.reached);
                assert!(report.iterations <= 100);
                let tip = effector(&test, &report.local_rotations);
                let along = tip.coords.dot(&direction);
                let off_ray = (tip.coords - direction * along).norm();
                println!(
                    "unreachable ({method:?}, limited={limited}): error {:.9} (ideal {:.9}), \
                     off-ray {off_ray:.2e}, {} iterations, {:?}",
                    report.error, test.reach, report.iterations, report.termination
                );
                assert!(along > 0.0);
                assert!(off_ray <= 1e-6 * test.reach, "off the ray by {off_ray}");
                // Stretched straight: the distance left is (nearly) 2L − L.
                assert!(
                    report.error - test.reach <= 1e-6 * test.reach,
                    "not stretched: error {} vs {}",
                    report.error,
                    test.reach
                );
                assert_limits(&test, &report.local_rotations);
            }
        }
    }

    #[test]
    fn degenerate_inputs_never_nan() {
        let test = test_chain(3);
        let start = vec![UnitQuaternion::identity(); test.skeleton.len()];
        for method in [IkMethod::Ccd, IkMethod::DampedLeastSquares] {
            // Target at the root: closer than the minimum reach (0 here is
            // not below it, since 1.0 + 0.9 ≥ 0.8), so reachable; no NaN.
            let report = solve_ik(
                &test.skeleton,
                &start,
                &test.chain,
                test.end_offset,
                Point3::origin(),
                &test.limits,
                &options(method),
            )
            .unwrap();
            assert!(report.error.is_finite());
            assert!(report.local_rotations.iter().all(rotation_is_finite));
            assert!(report.reachable);
            // A chain whose last joint is the tip (zero lever arm), with a
            // zero end offset and a zero-length link in the middle.
            let skeleton = Skeleton::chain(&[1.0, 0.0, 1.0], Vector3::x()).unwrap();
            let report = solve_ik(
                &skeleton,
                &[UnitQuaternion::identity(); 4],
                &[0, 1, 2, 3],
                Vector3::zeros(),
                Point3::new(0.5, 1.2, 0.3),
                &[
                    JointLimit::Free,
                    JointLimit::Cone { max_rad: 0.5 },
                    JointLimit::Free,
                    JointLimit::Cone { max_rad: 0.1 },
                ],
                &options(method),
            )
            .unwrap();
            assert!(report.error.is_finite() && report.reached, "{report:?}");
            // A zero-reach chain does nothing and reports so.
            let point = Skeleton::chain(&[0.0], Vector3::x()).unwrap();
            let report = solve_ik(
                &point,
                &[UnitQuaternion::identity(); 2],
                &[0, 1],
                Vector3::zeros(),
                Point3::new(1.0, 0.0, 0.0),
                &[JointLimit::Free; 2],
                &options(method),
            )
            .unwrap();
            assert_eq!(report.termination, IkTermination::Stalled);
            assert!(!report.reachable && !report.reached);
            assert!((report.error - 1.0).abs() < 1e-15);
            // Target exactly at the effector: converged at once.
            let tip = effector(&test, &start);
            let report = solve_ik(
                &test.skeleton,
                &start,
                &test.chain,
                test.end_offset,
                tip,
                &test.limits,
                &options(method),
            )
            .unwrap();
            assert_eq!(report.iterations, 0);
            assert!(report.reached);
        }
    }

    #[test]
    fn too_close_target_is_unreachable() {
        // Links 1.0 and 0.2: minimum reach 0.8.
        let skeleton = Skeleton::chain(&[1.0, 0.2], Vector3::x()).unwrap();
        let report = solve_ik(
            &skeleton,
            &[UnitQuaternion::identity(); 3],
            &[0, 1],
            Vector3::x() * 0.2,
            Point3::new(0.0, 0.3, 0.0),
            &[JointLimit::Free; 2],
            &IkOptions::default(),
        )
        .unwrap();
        assert!(!report.reachable && !report.reached);
        assert!((report.error - 0.5).abs() < 1e-6, "{}", report.error);
    }

    #[test]
    fn limits_can_make_a_reachable_target_unreached() {
        // A single hinge about z limited to [0, 0.5]: a target at −90° is
        // within reach but not allowed.
        let skeleton = Skeleton::chain(&[1.0], Vector3::x()).unwrap();
        let limits = [JointLimit::Hinge {
            axis: Vector3::z(),
            min_rad: 0.0,
            max_rad: 0.5,
        }];
        for method in [IkMethod::Ccd, IkMethod::DampedLeastSquares] {
            let report = solve_ik(
                &skeleton,
                &[UnitQuaternion::identity(); 2],
                &[0],
                Vector3::x(),
                Point3::new(0.0, -1.0, 0.0),
                &limits,
                &options(method),
            )
            .unwrap();
            assert!(report.reachable && !report.reached);
            assert!(report.iterations < 100, "{method:?}: {}", report.iterations);
            let angle = twist_angle(&report.local_rotations[0], &Vector3::z_axis());
            assert!(
                angle.abs() < 1e-9,
                "{method:?}: stays at the nearest bound, got {angle}"
            );
        }
    }

    #[test]
    fn limit_projection() {
        let axis = Vector3::z_axis();
        let hinge = Limit::Hinge {
            axis,
            min_rad: -0.5,
            max_rad: 1.0,
        };
        let bone = Vector3::x();
        // Off-axis parts are dropped, the twist kept.
        let q = UnitQuaternion::from_axis_angle(&axis, 0.7)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.3);
        let p = project(&hinge, &q, &bone);
        assert!((twist_angle(&p, &axis) - 0.7).abs() < 0.05);
        assert!((p.imag() - axis.into_inner() * p.imag().dot(&axis)).norm() < 1e-15);
        // Clamped to the nearest bound around the circle.
        let over = UnitQuaternion::from_axis_angle(&axis, 2.0);
        assert!((twist_angle(&project(&hinge, &over, &bone), &axis) - 1.0).abs() < 1e-12);
        let under = UnitQuaternion::from_axis_angle(&axis, -1.5);
        assert!((twist_angle(&project(&hinge, &under, &bone), &axis) + 0.5).abs() < 1e-12);
        // −3.0 is nearer to +1.0 than to −0.5 when going round through ±π.
        let far = UnitQuaternion::from_axis_angle(&axis, -3.0);
        assert!((twist_angle(&project(&hinge, &far, &bone), &axis) - 1.0).abs() < 1e-12);
        // Cones shorten the swing and keep the twist.
        let cone = Limit::Cone { max_rad: 0.4 };
        let twist = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 1.3);
        let swing = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 1.0);
        let p = project(&cone, &(swing * twist), &bone);
        assert!((swing_angle(&p, &bone) - 0.4).abs() < 1e-12);
        let expected = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.4) * twist;
        assert!(p.angle_to(&expected) < 1e-12);
        let inside = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.3);
        assert_eq!(project(&cone, &inside, &bone), inside);
        // Half-turn swing (antiparallel) still projects to the cone boundary.
        let flip = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), PI);
        assert!((swing_angle(&project(&cone, &flip, &bone), &bone) - 0.4).abs() < 1e-9);
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-12);
    }

    #[test]
    fn validation_errors() {
        let test = test_chain(3);
        let start = vec![UnitQuaternion::identity(); test.skeleton.len()];
        let solve = |rotations: &[UnitQuaternion<f64>],
                     chain: &[usize],
                     limits: &[JointLimit],
                     target: Point3<f64>,
                     options: IkOptions| {
            solve_ik(
                &test.skeleton,
                rotations,
                chain,
                test.end_offset,
                target,
                limits,
                &options,
            )
        };
        let target = Point3::new(1.0, 1.0, 0.0);
        let default = IkOptions::default();
        assert!(matches!(
            solve(&start[..2], &test.chain, &test.limits, target, default),
            Err(AnimateError::JointCountMismatch { .. })
        ));
        assert!(matches!(
            solve(&start, &[], &[], target, default),
            Err(AnimateError::EmptyChain)
        ));
        assert!(matches!(
            solve(&start, &[0, 2], &test.limits[..2], target, default),
            Err(AnimateError::ChainNotConnected {
                parent: 0,
                child: 2
            })
        ));
        assert!(matches!(
            solve(&start, &[0, 9], &test.limits[..2], target, default),
            Err(AnimateError::JointIndexOutOfRange { index: 9, .. })
        ));
        assert!(matches!(
            solve(&start, &test.chain, &test.limits[..1], target, default),
            Err(AnimateError::LengthMismatch { .. })
        ));
        assert!(matches!(
            solve(
                &start,
                &test.chain,
                &test.limits,
                Point3::new(f64::NAN, 0.0, 0.0),
                default
            ),
            Err(AnimateError::NonFinite { .. })
        ));
        let bad_hinge = [
            JointLimit::Free,
            JointLimit::Hinge {
                axis: Vector3::z(),
                min_rad: 1.0,
                max_rad: 0.0,
            },
            JointLimit::Free,
        ];
        assert!(solve(&start, &test.chain, &bad_hinge, target, default).is_err());
        let zero_axis = [
            JointLimit::Hinge {
                axis: Vector3::zeros(),
                min_rad: 0.0,
                max_rad: 1.0,
            },
            JointLimit::Free,
            JointLimit::Free,
        ];
        assert!(solve(&start, &test.chain, &zero_axis, target, default).is_err());
        let no_damping = IkOptions {
            damping: 0.0,
            ..default
        };
        assert!(solve(&start, &test.chain, &test.limits, target, no_damping).is_err());
    }

    #[test]
    fn start_pose_outside_limits_is_projected() {
        let test = test_chain(3);
        let mut start = vec![UnitQuaternion::identity(); test.skeleton.len()];
        start[1] = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 2.5);
        start[2] = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2.5);
        let report = solve_ik(
            &test.skeleton,
            &start,
            &test.chain,
            test.end_offset,
            Point3::new(1.0, 1.0, 0.5),
            &test.limits,
            &IkOptions {
                max_iterations: 0,
                ..IkOptions::default()
            },
        )
        .unwrap();
        assert_eq!(report.iterations, 0);
        assert_eq!(report.error_history.len(), 1);
        assert_limits(&test, &report.local_rotations);
    }
}
