//! Particle and mass–spring physics for the `animate` family.
//!
//! A [`ParticleSystem`] is a set of point masses (position, velocity, inverse mass; inverse mass
//! 0 pins a particle in place) joined by damped Hooke [`Spring`]s, under uniform gravity and linear
//! air drag. [`step`] advances it by one frame (`dt`, split into `substeps` equal substeps) with
//! one of five [`Integrator`]s, and resolves [`Collider`] contacts after every substep;
//! [`simulate`] runs many frames, reports energy and momentum per frame ([`FrameReport`]) and
//! stops cleanly when the state blows up ([`Divergence`]).
//!
//! Methods and references:
//! - explicit (forward) Euler, symplectic (semi-implicit) Euler and velocity Verlet (Störmer–
//!   Verlet): Hairer, Lubich & Wanner, *Geometric Numerical Integration*, 2nd ed., Springer 2006,
//!   chapters I and VI. The two symplectic methods keep a modified energy and so have bounded
//!   energy error when `h·ω < 2` for the stiffest mode `ω = √(k/m)`; explicit Euler multiplies a
//!   harmonic oscillator's energy by exactly `1 + h²ω²` per step.
//! - classic fourth-order Runge–Kutta (Kutta 1901) on the first-order system `(x, v)`.
//! - implicit Euler: the linearised backward Euler of Baraff & Witkin, "Large steps in cloth
//!   simulation", SIGGRAPH 1998 (§3, implicit integration; §5, constraints): one Newton step
//!   of backward Euler, `(M − h ∂f/∂v − h² ∂f/∂x) Δv = h (f₀ + h ∂f/∂x v₀)`, with 3×3 spring
//!   blocks (stiffness and damping), solved by Jacobi-preconditioned conjugate gradients
//!   (Shewchuk, "An introduction to the conjugate gradient method without the agonizing pain",
//!   1994, §B3) to the relative residual `cg_tolerance` or `cg_max_iterations`. Definiteness:
//!   the transverse stiffness term `(1 − L/|d|)` of a compressed spring is clamped at 0, so
//!   every spring block is positive semi-definite. Pinned particles are handled by filtering
//!   (Baraff & Witkin's modified PCG with the constraint projection `S = 0` for a pinned
//!   particle): their rows and columns are projected out, which leaves the free block
//!   symmetric positive definite.
//! - collisions: position projection onto the collider surface offset by the margin, then an
//!   inelastic velocity response with restitution and a Coulomb friction bound on the tangential
//!   velocity change (Bridson, Fedkiw & Anderson, "Robust treatment of collisions, contact and
//!   friction for cloth animation", SIGGRAPH 2002, whose friction model this is).
//!
//! Limits: contacts are point–surface only (no edge or self collisions, no continuous
//! collision detection), so a particle that moves further than the margin plus the mesh band
//! in one substep can pass through a thin mesh; colliders whose margin shells overlap (a
//! sphere resting on a plane) can hold a particle in a contradiction that
//! [`COLLISION_PASSES`] sweeps do not resolve.
//!
//! Conventions: SI units (m, kg, s, N); y is up for the builders and the default gravity
//! ([`EARTH_GRAVITY`]); everything is f64. Forces are accumulated in a fixed order (springs in
//! their list order, then gravity and drag per particle), every reduction is sequential, and no
//! randomness or threads are used: a rerun is bit-identical.

use std::fmt;
use std::str::FromStr;

/// A 3-vector (position in m, velocity in m/s, force in N, …).
pub type Vec3 = [f64; 3];

/// Standard gravity, pointing down the y axis (m/s²).
pub const EARTH_GRAVITY: Vec3 = [0.0, -9.81, 0.0];

/// Energy floor of the divergence reference scale, in joules (see [`simulate`]).
pub const ENERGY_FLOOR: f64 = 1e-6;

/// Springs shorter than this (m) have no defined direction: in that state they exert no force
/// and contribute no Jacobian block, except zero-rest-length springs, whose force `−k d` and
/// Jacobian `k I` need no direction (their damping is dropped there).
pub const MIN_SPRING_LENGTH: f64 = 1e-12;

/// How many times the collider list is swept per particle and substep, at most: a push out of
/// one collider can push the particle into another, so the sweep repeats until a pass changes
/// nothing or this many passes have run.
pub const COLLISION_PASSES: usize = 4;

/// Contacts closer than this to the offset surface (m) count as resolved: it keeps a particle
/// that was just projected (and sits there up to rounding) from being resolved again.
pub const CONTACT_SLOP: f64 = 1e-12;

/// Errors of the physics module: invalid systems, options, colliders and builder inputs, and a
/// state that stopped being finite during [`step`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PhysicsError {
    /// The frame time step is zero, negative or not finite.
    #[error("the time step dt must be finite and > 0 s, got {0}")]
    InvalidTimeStep(f64),
    /// `substeps` is zero.
    #[error("substeps must be at least 1, got 0")]
    ZeroSubsteps,
    /// A simulation option is out of its range.
    #[error("option `{name}` = {value} is invalid: it must be {expected}")]
    InvalidOption {
        /// The option's field name.
        name: &'static str,
        /// The rejected value.
        value: f64,
        /// The accepted range, in words.
        expected: &'static str,
    },
    /// The per-particle arrays do not have one entry per particle.
    #[error(
        "particle arrays differ in length: {positions} positions, {velocities} velocities, \
         {inverse_masses} inverse masses"
    )]
    LengthMismatch {
        /// `positions.len()`.
        positions: usize,
        /// `velocities.len()`.
        velocities: usize,
        /// `inverse_masses.len()`.
        inverse_masses: usize,
    },
    /// A position, velocity or the gravity vector has a NaN or infinite component.
    #[error("the {field} of particle {index} is not finite")]
    NonFiniteInput {
        /// `"position"` or `"velocity"`.
        field: &'static str,
        /// The particle.
        index: usize,
    },
    /// An inverse mass is negative, not finite, or so small that the mass overflows.
    #[error(
        "particle {index} has inverse mass {value}: it must be 0 (pinned) or finite and > 0 with \
         a finite mass (a negative mass is not allowed)"
    )]
    InvalidInverseMass {
        /// The particle.
        index: usize,
        /// The rejected inverse mass (1/kg).
        value: f64,
    },
    /// Gravity or drag is not finite, or drag is negative.
    #[error("system parameter `{name}` = {value} is invalid: it must be {expected}")]
    InvalidSystem {
        /// `"gravity"` or `"drag"`.
        name: &'static str,
        /// The rejected value (for gravity, the first bad component).
        value: f64,
        /// The accepted range, in words.
        expected: &'static str,
    },
    /// A spring refers to a particle that does not exist.
    #[error(
        "spring {spring} connects particles {a} and {b}, but the system has {particles} particles"
    )]
    SpringIndexOutOfRange {
        /// The spring's index in `springs`.
        spring: usize,
        /// Its first end.
        a: usize,
        /// Its second end.
        b: usize,
        /// The number of particles.
        particles: usize,
    },
    /// A spring connects a particle to itself.
    #[error("spring {spring} connects particle {index} to itself")]
    SpringSelfLoop {
        /// The spring's index in `springs`.
        spring: usize,
        /// The particle at both ends.
        index: usize,
    },
    /// A spring's rest length, stiffness or damping is negative or not finite.
    #[error("spring {spring} has {field} = {value}: it must be finite and >= 0")]
    InvalidSpring {
        /// The spring's index in `springs`.
        spring: usize,
        /// `"rest_length"`, `"stiffness"` or `"damping"`.
        field: &'static str,
        /// The rejected value.
        value: f64,
    },
    /// A collider's geometry is unusable.
    #[error("collider {index} is invalid: {reason}")]
    InvalidCollider {
        /// The collider's index in the list.
        index: usize,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A builder ([`cloth_grid`], [`rope`]) got an unusable option.
    #[error("builder option `{name}` is invalid: {reason}")]
    InvalidBuilder {
        /// The option's field name.
        name: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A substep produced a NaN or infinite position or velocity. The system was reset to the
    /// state before that substep (the last finite state).
    #[error(
        "the state became non-finite at particle {particle} in substep {substep}; the last finite \
         state was kept (reduce dt, raise substeps or use implicit_euler)"
    )]
    NonFiniteState {
        /// The first particle with a non-finite position or velocity.
        particle: usize,
        /// The substep (0-based, within the frame) that produced it.
        substep: usize,
    },
    /// The total energy passed the divergence threshold in a substep (only raised by internal
    /// callers that set a threshold; [`simulate`] reports it as a [`Divergence`] instead).
    #[error("the total energy {energy} J passed the divergence threshold in substep {substep}")]
    EnergyDiverged {
        /// The energy of the rejected state (J).
        energy: f64,
        /// The substep (0-based, within the frame).
        substep: usize,
    },
    /// [`Integrator::from_str`] got a name that is not in [`Integrator::NAMES`].
    #[error(
        "unknown integrator `{0}`: expected one of explicit_euler, symplectic_euler, \
         velocity_verlet, rk4, implicit_euler"
    )]
    UnknownIntegrator(String),
}

/// A damped Hooke spring between particles `a` and `b`: the force on `a` is
/// `−(k (|d| − L) + c (v_a − v_b)·u) u` with `d = x_a − x_b`, `u = d/|d|`, and the force on `b`
/// is its negative: the spring of Baraff & Witkin 1998 §4 with condition `C = |d| − L`, its
/// damping along `∂C/∂x`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spring {
    /// First particle.
    pub a: usize,
    /// Second particle (≠ `a`).
    pub b: usize,
    /// Rest length `L` (m, ≥ 0). A zero rest length makes the force exactly linear, `−k d`.
    pub rest_length: f64,
    /// Stiffness `k` (N/m, ≥ 0).
    pub stiffness: f64,
    /// Damping `c` along the spring (N·s/m, ≥ 0).
    pub damping: f64,
}

/// Point masses joined by springs, under uniform gravity and linear drag.
///
/// The three per-particle arrays have one entry per particle. An inverse mass of 0 pins the
/// particle: no integrator or collider moves it, and every step sets its velocity to zero.
/// Energies and momenta ([`ParticleSystem::measure`]) count free particles only (a pinned
/// particle has infinite mass and never moves).
#[derive(Debug, Clone, PartialEq)]
pub struct ParticleSystem {
    /// Positions (m).
    pub positions: Vec<Vec3>,
    /// Velocities (m/s).
    pub velocities: Vec<Vec3>,
    /// Inverse masses (1/kg); 0 = pinned (infinite mass).
    pub inverse_masses: Vec<f64>,
    /// Springs, applied in this order.
    pub springs: Vec<Spring>,
    /// Gravitational acceleration (m/s²).
    pub gravity: Vec3,
    /// Linear air drag coefficient per particle (N·s/m): force `−drag · v` on every free
    /// particle.
    pub drag: f64,
}

impl ParticleSystem {
    /// A system of free or pinned particles at rest, with no springs, [`EARTH_GRAVITY`] and no
    /// drag. `inverse_masses` must have one entry per position (checked by [`Self::validate`]).
    pub fn new(positions: Vec<Vec3>, inverse_masses: Vec<f64>) -> Self {
        let velocities = vec![[0.0; 3]; positions.len()];
        Self {
            positions,
            velocities,
            inverse_masses,
            springs: Vec::new(),
            gravity: EARTH_GRAVITY,
            drag: 0.0,
        }
    }

    /// The number of particles.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether the system has no particles.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Checks the system: equal array lengths, finite positions and velocities, inverse masses
    /// 0 or finite > 0 with a finite reciprocal, finite gravity, finite non-negative drag, and
    /// springs with in-range distinct ends and finite non-negative rest length, stiffness and
    /// damping. Returns the first problem found.
    pub fn validate(&self) -> Result<(), PhysicsError> {
        let n = self.positions.len();
        if self.velocities.len() != n || self.inverse_masses.len() != n {
            return Err(PhysicsError::LengthMismatch {
                positions: n,
                velocities: self.velocities.len(),
                inverse_masses: self.inverse_masses.len(),
            });
        }
        for (index, (x, v)) in self.positions.iter().zip(&self.velocities).enumerate() {
            if !finite3(*x) {
                return Err(PhysicsError::NonFiniteInput {
                    field: "position",
                    index,
                });
            }
            if !finite3(*v) {
                return Err(PhysicsError::NonFiniteInput {
                    field: "velocity",
                    index,
                });
            }
        }
        for (index, &w) in self.inverse_masses.iter().enumerate() {
            let ok = w == 0.0 || (w.is_finite() && w > 0.0 && (1.0 / w).is_finite());
            if !ok {
                return Err(PhysicsError::InvalidInverseMass { index, value: w });
            }
        }
        if let Some(&g) = self.gravity.iter().find(|g| !g.is_finite()) {
            return Err(PhysicsError::InvalidSystem {
                name: "gravity",
                value: g,
                expected: "finite",
            });
        }
        if !(self.drag.is_finite() && self.drag >= 0.0) {
            return Err(PhysicsError::InvalidSystem {
                name: "drag",
                value: self.drag,
                expected: "finite and >= 0 N·s/m",
            });
        }
        for (spring, s) in self.springs.iter().enumerate() {
            if s.a >= n || s.b >= n {
                return Err(PhysicsError::SpringIndexOutOfRange {
                    spring,
                    a: s.a,
                    b: s.b,
                    particles: n,
                });
            }
            if s.a == s.b {
                return Err(PhysicsError::SpringSelfLoop { spring, index: s.a });
            }
            for (field, value) in [
                ("rest_length", s.rest_length),
                ("stiffness", s.stiffness),
                ("damping", s.damping),
            ] {
                if !(value.is_finite() && value >= 0.0) {
                    return Err(PhysicsError::InvalidSpring {
                        spring,
                        field,
                        value,
                    });
                }
            }
        }
        Ok(())
    }

    /// Energies and momenta of the current state (the `cg_iterations`, `cg_converged` and
    /// `collisions` fields are 0 / `true` / 0).
    ///
    /// Kinetic `Σ ½ m |v|²`, gravitational `Σ −m g·x` (zero at the origin), spring
    /// `Σ ½ k (|d| − L)²`, linear momentum `Σ m v`, angular momentum `Σ m x × v` about the origin,
    /// all over free particles (springs: all), summed in index order.
    pub fn measure(&self) -> FrameReport {
        let mut kinetic = 0.0;
        let mut gravitational = 0.0;
        let mut linear = [0.0; 3];
        let mut angular = [0.0; 3];
        let mut max_speed: f64 = 0.0;
        for ((x, v), &w) in self
            .positions
            .iter()
            .zip(&self.velocities)
            .zip(&self.inverse_masses)
        {
            if w <= 0.0 {
                continue;
            }
            let m = 1.0 / w;
            kinetic += 0.5 * m * dot(*v, *v);
            gravitational -= m * dot(self.gravity, *x);
            linear = axpy(linear, m, *v);
            angular = axpy(angular, m, cross(*x, *v));
            max_speed = max_speed.max(norm(*v));
        }
        let spring = spring_energy(&self.springs, &self.positions);
        FrameReport {
            kinetic_energy: kinetic,
            gravitational_energy: gravitational,
            spring_energy: spring,
            total_energy: kinetic + gravitational + spring,
            linear_momentum: linear,
            angular_momentum: angular,
            max_speed,
            cg_iterations: 0,
            cg_converged: true,
            collisions: 0,
        }
    }

    /// The total mechanical energy (kinetic + gravitational + spring, J) of the current state;
    /// the same number as [`Self::measure`]'s `total_energy`.
    pub fn total_energy(&self) -> f64 {
        self.measure().total_energy
    }
}

/// Time integrators. Names (for graphs and command lines): [`Integrator::NAMES`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Integrator {
    /// Forward Euler: `x += h v₀`, `v += h a(x₀, v₀)`. First order, energy grows by `1 + h²ω²`
    /// per step on an oscillator (Hairer, Lubich & Wanner 2006, ch. I): a reference, not for use.
    ExplicitEuler,
    /// Symplectic (semi-implicit) Euler: `v += h a(x₀, v₀)`, then `x += h v`. First order,
    /// symplectic; conserves linear and angular momentum exactly for central internal forces;
    /// stable for `h ω < 2` (Hairer, Lubich & Wanner 2006, ch. VI).
    SymplecticEuler,
    /// Velocity Verlet (Störmer–Verlet): `v½ = v + h/2 a(x, v)`, `x += h v½`,
    /// `v = v½ + h/2 a(x, v½)`; second order and symplectic for conservative forces; damping and
    /// drag are evaluated with the half-step velocity (explicit approximation). Stable for
    /// `h ω < 2` (Hairer, Lubich & Wanner 2006, ch. I).
    VelocityVerlet,
    /// Classic fourth-order Runge–Kutta on `(x, v)`; four force evaluations per step
    /// (Kutta 1901). Not symplectic; stable for `h ω` up to about 2.8.
    Rk4,
    /// Linearised backward Euler of Baraff & Witkin 1998 solved by filtered Jacobi-PCG;
    /// unconditionally stable for springs, damps high frequencies. The default.
    #[default]
    ImplicitEuler,
}

impl Integrator {
    /// Every integrator, in the order of [`Integrator::NAMES`].
    pub const ALL: [Integrator; 5] = [
        Integrator::ExplicitEuler,
        Integrator::SymplecticEuler,
        Integrator::VelocityVerlet,
        Integrator::Rk4,
        Integrator::ImplicitEuler,
    ];

    /// The integrators' names, in the order of [`Integrator::ALL`].
    pub const NAMES: [&'static str; 5] = [
        "explicit_euler",
        "symplectic_euler",
        "velocity_verlet",
        "rk4",
        "implicit_euler",
    ];

    /// The integrator's name (one of [`Integrator::NAMES`]).
    pub fn name(self) -> &'static str {
        match self {
            Integrator::ExplicitEuler => "explicit_euler",
            Integrator::SymplecticEuler => "symplectic_euler",
            Integrator::VelocityVerlet => "velocity_verlet",
            Integrator::Rk4 => "rk4",
            Integrator::ImplicitEuler => "implicit_euler",
        }
    }

    /// The integrator with this exact name, if any.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|i| i.name() == name)
    }
}

impl fmt::Display for Integrator {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Integrator {
    type Err = PhysicsError;

    /// [`Integrator::from_name`] with a typed error.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::from_name(s).ok_or_else(|| PhysicsError::UnknownIntegrator(s.to_owned()))
    }
}

/// A surface that can report the point on it closest to a query point; the owner implements it
/// with a BVH over a triangle mesh.
pub trait MeshCollider {
    /// The closest surface point to `p` and the outward unit surface normal there, or `None`
    /// when there is no surface (or none within the implementation's search range). The normal
    /// decides inside versus outside: `p` is behind the surface when `(p − closest)·normal < 0`.
    fn closest(&self, p: Vec3) -> Option<(Vec3, Vec3)>;
}

/// Static collision geometry. Contacts are resolved after every substep (see [`SimOptions`]):
/// a particle closer than `margin` to the surface (or behind it) is moved onto the surface
/// offset by `margin` along the normal, and its velocity gets the restitution / friction
/// response (Bridson, Fedkiw & Anderson 2002).
pub enum Collider {
    /// The half-space above an infinite plane through `point` with (not necessarily unit)
    /// `normal`; every particle below `margin` above the plane is pushed up to it.
    Plane {
        /// A point on the plane (m).
        point: Vec3,
        /// The plane's normal, pointing to the free side; must be finite and non-zero.
        normal: Vec3,
    },
    /// A solid sphere; every particle closer than `radius + margin` to the centre is pushed out
    /// radially (straight up, +y, from the exact centre).
    Sphere {
        /// The centre (m).
        center: Vec3,
        /// The radius (m, finite, ≥ 0).
        radius: f64,
    },
    /// A triangle mesh behind a [`MeshCollider`]. With `q` the closest point and `n` its
    /// normal, a particle at distance `d = |p − q|` collides when it is in front
    /// (`(p − q)·n ≥ 0`) and `d < margin`, or behind and `d < mesh_band`; it is moved to
    /// `q + margin · n`. Particles further behind than the band are left alone (they are taken
    /// to be on the far side of a thin sheet, or deep inside a solid).
    Mesh(Box<dyn MeshCollider + Send + Sync>),
}

impl fmt::Debug for Collider {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Collider::Plane { point, normal } => f
                .debug_struct("Plane")
                .field("point", point)
                .field("normal", normal)
                .finish(),
            Collider::Sphere { center, radius } => f
                .debug_struct("Sphere")
                .field("center", center)
                .field("radius", radius)
                .finish(),
            Collider::Mesh(_) => f.write_str("Mesh(..)"),
        }
    }
}

/// Options of [`step`] and [`simulate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimOptions {
    /// Frame time step (s, finite, > 0). One [`step`] advances the system by `dt`.
    pub dt: f64,
    /// Equal substeps per frame (≥ 1); the integrator step is `h = dt / substeps`, and
    /// collisions are resolved after each substep.
    pub substeps: usize,
    /// The integrator.
    pub integrator: Integrator,
    /// Coefficient of restitution in [0, 1]: the normal velocity into a collider is reversed and
    /// scaled by it.
    pub restitution: f64,
    /// Coulomb friction coefficient (≥ 0): the tangential speed is reduced by
    /// `friction × (normal velocity change)`, never past zero.
    pub friction: f64,
    /// Collision margin / thickness (m, ≥ 0), applied to every collider.
    pub margin: f64,
    /// How far behind a mesh surface (m, ≥ 0, may be infinite) a particle is still pushed out
    /// (see [`Collider::Mesh`]).
    pub mesh_band: f64,
    /// Relative tolerance of the implicit solve: CG stops when `‖r‖₂ ≤ tol · ‖b‖₂` (finite, > 0).
    pub cg_tolerance: f64,
    /// Most CG iterations per implicit substep (≥ 1). When reached, the current iterate is used
    /// and the report's `cg_converged` is false.
    pub cg_max_iterations: usize,
    /// [`simulate`] stops when the total energy exceeds this factor times the reference scale
    /// (> 0; may be infinite to disable the energy test).
    pub divergence_factor: f64,
}

impl Default for SimOptions {
    /// `dt` 1/60 s, 1 substep, implicit Euler, restitution 0, friction 0.3, margin 1 mm,
    /// mesh band 5 cm, CG tolerance 1e-6 and at most 200 iterations, divergence factor 1e3.
    fn default() -> Self {
        Self {
            dt: 1.0 / 60.0,
            substeps: 1,
            integrator: Integrator::ImplicitEuler,
            restitution: 0.0,
            friction: 0.3,
            margin: 1e-3,
            mesh_band: 0.05,
            cg_tolerance: 1e-6,
            cg_max_iterations: 200,
            divergence_factor: 1e3,
        }
    }
}

impl SimOptions {
    /// Checks every option's range (see the field docs).
    pub fn validate(&self) -> Result<(), PhysicsError> {
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return Err(PhysicsError::InvalidTimeStep(self.dt));
        }
        if self.substeps == 0 {
            return Err(PhysicsError::ZeroSubsteps);
        }
        let checks: [(&'static str, f64, bool, &'static str); 6] = [
            (
                "restitution",
                self.restitution,
                (0.0..=1.0).contains(&self.restitution),
                "in [0, 1]",
            ),
            (
                "friction",
                self.friction,
                self.friction.is_finite() && self.friction >= 0.0,
                "finite and >= 0",
            ),
            (
                "margin",
                self.margin,
                self.margin.is_finite() && self.margin >= 0.0,
                "finite and >= 0 m",
            ),
            (
                "mesh_band",
                self.mesh_band,
                self.mesh_band >= 0.0,
                ">= 0 m (infinity allowed)",
            ),
            (
                "cg_tolerance",
                self.cg_tolerance,
                self.cg_tolerance.is_finite() && self.cg_tolerance > 0.0,
                "finite and > 0",
            ),
            (
                "divergence_factor",
                self.divergence_factor,
                self.divergence_factor > 0.0,
                "> 0 (infinity allowed)",
            ),
        ];
        for (name, value, ok, expected) in checks {
            if !ok {
                return Err(PhysicsError::InvalidOption {
                    name,
                    value,
                    expected,
                });
            }
        }
        if self.cg_max_iterations == 0 {
            return Err(PhysicsError::InvalidOption {
                name: "cg_max_iterations",
                value: 0.0,
                expected: ">= 1",
            });
        }
        Ok(())
    }
}

/// What one [`step`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepReport {
    /// Substeps completed.
    pub substeps: usize,
    /// CG iterations over all substeps (0 unless the integrator is implicit Euler).
    pub cg_iterations: usize,
    /// Whether every implicit solve reached `cg_tolerance` (true for explicit integrators).
    pub cg_converged: bool,
    /// Particle–collider contacts resolved over all substeps (a particle pushed out of two
    /// colliders counts twice; a repeated sweep counts again).
    pub collisions: usize,
}

/// State measures after a frame, plus the frame's solver and contact counts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameReport {
    /// `Σ ½ m |v|²` over free particles (J).
    pub kinetic_energy: f64,
    /// `Σ −m g·x` over free particles (J; zero at the origin).
    pub gravitational_energy: f64,
    /// `Σ ½ k (|d| − L)²` over springs (J).
    pub spring_energy: f64,
    /// Kinetic + gravitational + spring (J).
    pub total_energy: f64,
    /// `Σ m v` over free particles (kg·m/s).
    pub linear_momentum: Vec3,
    /// `Σ m x × v` about the origin over free particles (kg·m²/s).
    pub angular_momentum: Vec3,
    /// Largest free-particle speed (m/s).
    pub max_speed: f64,
    /// CG iterations in this frame.
    pub cg_iterations: usize,
    /// Whether every implicit solve of the frame converged.
    pub cg_converged: bool,
    /// Contacts resolved in this frame.
    pub collisions: usize,
}

/// Why a simulation was stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DivergenceReason {
    /// A position or velocity became NaN or infinite (first offending particle).
    NonFinite {
        /// The particle.
        particle: usize,
    },
    /// The total energy exceeded the threshold.
    EnergyExceeded,
}

/// Where and why [`simulate`] stopped early.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Divergence {
    /// The frame (0-based) during which the blow-up was detected; it has no [`FrameReport`].
    pub frame: usize,
    /// The global substep number (1-based: substep 1 is the first substep of frame 0) whose
    /// result was rejected.
    pub step: usize,
    /// The total energy of the rejected state (J); infinite when the state was not finite.
    pub energy: f64,
    /// The energy threshold in force (J): `divergence_factor × reference scale`.
    pub threshold: f64,
    /// What was detected.
    pub reason: DivergenceReason,
}

/// The result of [`simulate`].
#[derive(Debug, Clone, PartialEq)]
pub struct SimulationReport {
    /// One report per completed frame.
    pub frames: Vec<FrameReport>,
    /// `Some` when the run stopped early; the system then holds the last finite, accepted state
    /// (after the last good substep).
    pub diverged: Option<Divergence>,
    /// Substeps completed.
    pub steps: usize,
}

/// Advances `system` by one frame: `options.substeps` substeps of `h = dt / substeps` with the
/// chosen integrator, each followed by collision resolution against `colliders` in list order.
///
/// Validates the options, colliders and system first. When a substep produces a non-finite
/// position or velocity, the system is reset to the state before that substep and
/// [`PhysicsError::NonFiniteState`] is returned. No energy test is made here (see
/// [`simulate`]).
pub fn step(
    system: &mut ParticleSystem,
    colliders: &[Collider],
    options: &SimOptions,
) -> Result<StepReport, PhysicsError> {
    options.validate()?;
    validate_colliders(colliders)?;
    system.validate()?;
    let mut ws = Workspace::default();
    run_substeps(system, colliders, options, &mut ws, None).map_err(|f| match f.kind {
        Failure::NonFinite { particle } => PhysicsError::NonFiniteState {
            particle,
            substep: f.substep,
        },
        Failure::Energy { energy } => PhysicsError::EnergyDiverged {
            energy,
            substep: f.substep,
        },
    })
}

/// Runs `frames` frames of [`step`], calling `on_frame(frame, system, report)` after each, and
/// stops early on a blow-up.
///
/// Blow-up detection runs after every substep: the state is rejected when a position or
/// velocity is not finite, or when its total mechanical energy `E` is not `≤ divergence_factor
/// × E_ref`, with the reference scale
/// `E_ref = max(|E₀|, K₀, S₀, ENERGY_FLOOR)` — `E₀`, `K₀`, `S₀` the initial total, kinetic and
/// spring energy, [`ENERGY_FLOOR`] = 1e-6 J. The system is then reset to the state before the
/// rejected substep, no further frames run, and the report's `diverged` says where (the
/// interrupted frame gets no report and no callback). Invalid input is an `Err`.
pub fn simulate(
    system: &mut ParticleSystem,
    colliders: &[Collider],
    options: &SimOptions,
    frames: usize,
    mut on_frame: impl FnMut(usize, &ParticleSystem, &FrameReport),
) -> Result<SimulationReport, PhysicsError> {
    options.validate()?;
    validate_colliders(colliders)?;
    system.validate()?;
    let initial = system.measure();
    let reference = initial
        .total_energy
        .abs()
        .max(initial.kinetic_energy)
        .max(initial.spring_energy)
        .max(ENERGY_FLOOR);
    let threshold = options.divergence_factor * reference;
    let mut ws = Workspace::default();
    let mut report = SimulationReport {
        frames: Vec::with_capacity(frames),
        diverged: None,
        steps: 0,
    };
    for frame in 0..frames {
        match run_substeps(system, colliders, options, &mut ws, Some(threshold)) {
            Ok(step_report) => {
                report.steps += step_report.substeps;
                let mut frame_report = system.measure();
                frame_report.cg_iterations = step_report.cg_iterations;
                frame_report.cg_converged = step_report.cg_converged;
                frame_report.collisions = step_report.collisions;
                on_frame(frame, system, &frame_report);
                report.frames.push(frame_report);
            }
            Err(failure) => {
                report.steps += failure.substep;
                let (energy, reason) = match failure.kind {
                    Failure::NonFinite { particle } => {
                        (f64::INFINITY, DivergenceReason::NonFinite { particle })
                    }
                    Failure::Energy { energy } => (energy, DivergenceReason::EnergyExceeded),
                };
                report.diverged = Some(Divergence {
                    frame,
                    step: report.steps + 1,
                    energy,
                    threshold,
                    reason,
                });
                break;
            }
        }
    }
    Ok(report)
}

/// Checks collider geometry: finite plane point and finite non-zero normal; finite sphere
/// centre and finite non-negative radius. Meshes are not inspected.
pub fn validate_colliders(colliders: &[Collider]) -> Result<(), PhysicsError> {
    for (index, c) in colliders.iter().enumerate() {
        let reason = match c {
            Collider::Plane { point, normal } => {
                if !finite3(*point) {
                    Some("the plane point is not finite")
                } else if normalized(*normal).is_none() {
                    Some("the plane normal must be finite and non-zero")
                } else {
                    None
                }
            }
            Collider::Sphere { center, radius } => {
                if !finite3(*center) {
                    Some("the sphere centre is not finite")
                } else if !(radius.is_finite() && *radius >= 0.0) {
                    Some("the sphere radius must be finite and >= 0")
                } else {
                    None
                }
            }
            Collider::Mesh(_) => None,
        };
        if let Some(reason) = reason {
            return Err(PhysicsError::InvalidCollider { index, reason });
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Builders
// ---------------------------------------------------------------------------------------------

/// Which cloth particles [`cloth_grid`] pins. Row `j = 0` is the edge at the smallest z.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ClothPin {
    /// Nothing pinned.
    #[default]
    None,
    /// The two corners of row `j = 0`.
    TwoCorners,
    /// All four corners.
    FourCorners,
    /// The whole row `j = 0`.
    Edge,
}

/// Options of [`cloth_grid`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClothOptions {
    /// Particles along x (≥ 2).
    pub nx: usize,
    /// Particles along z (≥ 2).
    pub ny: usize,
    /// Centre of the cloth (m); the cloth lies in the horizontal plane `y = center[1]`.
    pub center: Vec3,
    /// Extent along x and z (m, finite, > 0).
    pub size: [f64; 2],
    /// Total mass (kg, finite, > 0), shared evenly by all particles; pinned particles' share is
    /// dropped (they become infinite masses).
    pub total_mass: f64,
    /// Stiffness of the structural springs, between grid neighbours along x and z (N/m).
    pub structural_stiffness: f64,
    /// Stiffness of the shear springs, along both diagonals of every cell (N/m).
    pub shear_stiffness: f64,
    /// Stiffness of the bend springs, between particles two apart along x and z (N/m).
    pub bend_stiffness: f64,
    /// Damping of every spring (N·s/m).
    pub damping: f64,
    /// Total linear air drag of the cloth (N·s/m), split evenly over the particles, so the
    /// terminal velocity `total_mass · g / drag` does not depend on the resolution.
    pub drag: f64,
    /// Gravity (m/s²).
    pub gravity: Vec3,
    /// Pinned particles.
    pub pin: ClothPin,
}

impl Default for ClothOptions {
    /// 16 × 16 particles, 1 m × 1 m centred at (0, 1, 0), 0.5 kg; structural 1000 N/m, shear
    /// 100 N/m, bend 10 N/m, spring damping 0.01 N·s/m, total drag 0.2 N·s/m,
    /// [`EARTH_GRAVITY`], nothing pinned.
    fn default() -> Self {
        Self {
            nx: 16,
            ny: 16,
            center: [0.0, 1.0, 0.0],
            size: [1.0, 1.0],
            total_mass: 0.5,
            structural_stiffness: 1000.0,
            shear_stiffness: 100.0,
            bend_stiffness: 10.0,
            damping: 0.01,
            drag: 0.2,
            gravity: EARTH_GRAVITY,
            pin: ClothPin::None,
        }
    }
}

/// A rectangular cloth as a mass–spring grid (the structural / shear / bend layout of
/// Provot, "Deformation constraints in a mass-spring model to describe rigid cloth behavior",
/// Graphics Interface 1995).
///
/// Particle `(i, j)` (`0 ≤ i < nx` along x, `0 ≤ j < ny` along z) has index `i + nx · j` and sits
/// at `center + (−size_x/2 + i·size_x/(nx−1), 0, −size_z/2 + j·size_z/(ny−1))`, at rest.
/// Springs are listed structural (x then z neighbours, row by row), then shear, then bend, all
/// with their rest length at the initial spacing. [`grid_triangles`] gives the matching mesh.
pub fn cloth_grid(options: &ClothOptions) -> Result<ParticleSystem, PhysicsError> {
    let o = options;
    if o.nx < 2 || o.ny < 2 {
        return Err(PhysicsError::InvalidBuilder {
            name: "nx/ny",
            reason: "a cloth grid needs at least 2 particles along each side",
        });
    }
    let n =
        o.nx.checked_mul(o.ny)
            .filter(|&n| u32::try_from(n).is_ok())
            .ok_or(PhysicsError::InvalidBuilder {
                name: "nx/ny",
                reason: "the grid has more particles than 32-bit triangle indices can address",
            })?;
    let positive = |v: f64| v.is_finite() && v > 0.0;
    let non_negative = |v: f64| v.is_finite() && v >= 0.0;
    if !finite3(o.center) {
        return Err(builder_error("center", "must be finite"));
    }
    if !(positive(o.size[0]) && positive(o.size[1])) {
        return Err(builder_error("size", "must be finite and > 0 m"));
    }
    if !positive(o.total_mass) {
        return Err(builder_error("total_mass", "must be finite and > 0 kg"));
    }
    for (name, v) in [
        ("structural_stiffness", o.structural_stiffness),
        ("shear_stiffness", o.shear_stiffness),
        ("bend_stiffness", o.bend_stiffness),
        ("damping", o.damping),
        ("drag", o.drag),
    ] {
        if !non_negative(v) {
            return Err(builder_error(name, "must be finite and >= 0"));
        }
    }
    if !finite3(o.gravity) {
        return Err(builder_error("gravity", "must be finite"));
    }
    let (nx, ny) = (o.nx, o.ny);
    let dx = o.size[0] / (nx - 1) as f64;
    let dz = o.size[1] / (ny - 1) as f64;
    let x0 = o.center[0] - 0.5 * o.size[0];
    let z0 = o.center[2] - 0.5 * o.size[1];
    let mut positions = Vec::with_capacity(n);
    for j in 0..ny {
        for i in 0..nx {
            positions.push([x0 + i as f64 * dx, o.center[1], z0 + j as f64 * dz]);
        }
    }
    let w = n as f64 / o.total_mass;
    let mut inverse_masses = vec![w; n];
    let mut pin = |i: usize, j: usize| {
        if let Some(m) = inverse_masses.get_mut(i + nx * j) {
            *m = 0.0;
        }
    };
    match o.pin {
        ClothPin::None => {}
        ClothPin::TwoCorners => {
            pin(0, 0);
            pin(nx - 1, 0);
        }
        ClothPin::FourCorners => {
            pin(0, 0);
            pin(nx - 1, 0);
            pin(0, ny - 1);
            pin(nx - 1, ny - 1);
        }
        ClothPin::Edge => (0..nx).for_each(|i| pin(i, 0)),
    }
    let mut springs = Vec::new();
    let mut link = |a: usize, b: usize, stiffness: f64| {
        if let (Some(&pa), Some(&pb)) = (positions.get(a), positions.get(b)) {
            springs.push(Spring {
                a,
                b,
                rest_length: norm(sub(pa, pb)),
                stiffness,
                damping: o.damping,
            });
        }
    };
    let id = |i: usize, j: usize| i + nx * j;
    for j in 0..ny {
        for i in 0..nx {
            if i + 1 < nx {
                link(id(i, j), id(i + 1, j), o.structural_stiffness);
            }
            if j + 1 < ny {
                link(id(i, j), id(i, j + 1), o.structural_stiffness);
            }
        }
    }
    for j in 0..ny - 1 {
        for i in 0..nx - 1 {
            link(id(i, j), id(i + 1, j + 1), o.shear_stiffness);
            link(id(i + 1, j), id(i, j + 1), o.shear_stiffness);
        }
    }
    for j in 0..ny {
        for i in 0..nx {
            if i + 2 < nx {
                link(id(i, j), id(i + 2, j), o.bend_stiffness);
            }
            if j + 2 < ny {
                link(id(i, j), id(i, j + 2), o.bend_stiffness);
            }
        }
    }
    Ok(ParticleSystem {
        velocities: vec![[0.0; 3]; n],
        positions,
        inverse_masses,
        springs,
        gravity: o.gravity,
        drag: o.drag / n as f64,
    })
}

/// The triangles of an `nx × ny` [`cloth_grid`]: two per cell, `[v00, v01, v10]` and
/// `[v10, v01, v11]` with `vij = (i + di) + nx (j + dj)`, wound so that the normal of the flat
/// grid, `(p1 − p0) × (p2 − p0)`, points along +y. Empty when a side has fewer than 2 particles
/// or the grid has more vertices than `u32` can index.
pub fn grid_triangles(nx: usize, ny: usize) -> Vec<[u32; 3]> {
    if nx < 2
        || ny < 2
        || nx
            .checked_mul(ny)
            .and_then(|n| u32::try_from(n).ok())
            .is_none()
    {
        return Vec::new();
    }
    let mut tris = Vec::with_capacity(2 * (nx - 1) * (ny - 1));
    // nx * ny fits u32 (checked above), so every index below does.
    let id = |i: usize, j: usize| (i + nx * j) as u32;
    for j in 0..ny - 1 {
        for i in 0..nx - 1 {
            let (v00, v10, v01, v11) = (id(i, j), id(i + 1, j), id(i, j + 1), id(i + 1, j + 1));
            tris.push([v00, v01, v10]);
            tris.push([v10, v01, v11]);
        }
    }
    tris
}

/// Options of [`rope`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RopeOptions {
    /// The pinned end (m).
    pub start: Vec3,
    /// The free end (m), different from `start`.
    pub end: Vec3,
    /// Number of springs (≥ 1); the rope has `segments + 1` particles.
    pub segments: usize,
    /// Mass of the free particles together (kg, finite, > 0).
    pub total_mass: f64,
    /// Stiffness of each segment spring (N/m).
    pub stiffness: f64,
    /// Damping of each segment spring (N·s/m).
    pub damping: f64,
    /// Total linear drag (N·s/m), split evenly over the free particles.
    pub drag: f64,
    /// Gravity (m/s²).
    pub gravity: Vec3,
}

impl Default for RopeOptions {
    /// A 1 m rope along +x from (0, 1, 0), 20 segments, 0.2 kg, 500 N/m per segment, damping
    /// 0.01 N·s/m, drag 0.05 N·s/m, [`EARTH_GRAVITY`].
    fn default() -> Self {
        Self {
            start: [0.0, 1.0, 0.0],
            end: [1.0, 1.0, 0.0],
            segments: 20,
            total_mass: 0.2,
            stiffness: 500.0,
            damping: 0.01,
            drag: 0.05,
            gravity: EARTH_GRAVITY,
        }
    }
}

/// A chain of `segments + 1` particles evenly spaced on the segment from `start` (particle 0,
/// pinned) to `end`, joined by `segments` springs at their rest length, at rest.
pub fn rope(options: &RopeOptions) -> Result<ParticleSystem, PhysicsError> {
    let o = options;
    if o.segments == 0 {
        return Err(builder_error("segments", "a rope needs at least 1 segment"));
    }
    if !(finite3(o.start) && finite3(o.end)) {
        return Err(builder_error("start/end", "must be finite"));
    }
    let length = norm(sub(o.end, o.start));
    if length == 0.0 || !length.is_finite() {
        return Err(builder_error(
            "start/end",
            "must be different points a finite distance apart",
        ));
    }
    if !(o.total_mass.is_finite() && o.total_mass > 0.0) {
        return Err(builder_error("total_mass", "must be finite and > 0 kg"));
    }
    for (name, v) in [
        ("stiffness", o.stiffness),
        ("damping", o.damping),
        ("drag", o.drag),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(builder_error(name, "must be finite and >= 0"));
        }
    }
    if !finite3(o.gravity) {
        return Err(builder_error("gravity", "must be finite"));
    }
    let n = o.segments + 1;
    let step = scale(sub(o.end, o.start), 1.0 / o.segments as f64);
    let positions: Vec<Vec3> = (0..n).map(|i| axpy(o.start, i as f64, step)).collect();
    let mut inverse_masses = vec![o.segments as f64 / o.total_mass; n];
    if let Some(first) = inverse_masses.first_mut() {
        *first = 0.0;
    }
    let springs = positions
        .windows(2)
        .enumerate()
        .map(|(i, w)| Spring {
            a: i,
            b: i + 1,
            rest_length: match w {
                [p, q] => norm(sub(*q, *p)),
                _ => 0.0,
            },
            stiffness: o.stiffness,
            damping: o.damping,
        })
        .collect();
    Ok(ParticleSystem {
        velocities: vec![[0.0; 3]; n],
        positions,
        inverse_masses,
        springs,
        gravity: o.gravity,
        drag: o.drag / o.segments as f64,
    })
}

fn builder_error(name: &'static str, reason: &'static str) -> PhysicsError {
    PhysicsError::InvalidBuilder { name, reason }
}

// ---------------------------------------------------------------------------------------------
// Stepping
// ---------------------------------------------------------------------------------------------

enum Failure {
    NonFinite { particle: usize },
    Energy { energy: f64 },
}

struct StepFailure {
    /// Substeps of this frame completed before the rejected one (= its 0-based index).
    substep: usize,
    kind: Failure,
}

/// Scratch buffers, reused across substeps.
#[derive(Default)]
struct Workspace {
    force: Vec<Vec3>,
    acc: Vec<Vec3>,
    xt: Vec<Vec3>,
    vt: Vec<Vec3>,
    asum: Vec<Vec3>,
    vsum: Vec<Vec3>,
    // implicit Euler
    kblk: Vec<Sym3>,
    cblk: Vec<Sym3>,
    mass_term: Vec<f64>,
    precond: Vec<Vec3>,
    rhs: Vec<Vec3>,
    dv: Vec<Vec3>,
    r: Vec<Vec3>,
    z: Vec<Vec3>,
    p: Vec<Vec3>,
    q: Vec<Vec3>,
    prev_x: Vec<Vec3>,
    prev_v: Vec<Vec3>,
}

fn resize(buf: &mut Vec<Vec3>, n: usize) {
    buf.clear();
    buf.resize(n, [0.0; 3]);
}

/// The read-only model data the integrators need.
struct Model<'a> {
    springs: &'a [Spring],
    inverse_masses: &'a [f64],
    gravity: Vec3,
    drag: f64,
}

fn run_substeps(
    system: &mut ParticleSystem,
    colliders: &[Collider],
    options: &SimOptions,
    ws: &mut Workspace,
    threshold: Option<f64>,
) -> Result<StepReport, StepFailure> {
    let h = options.dt / options.substeps as f64;
    let mut report = StepReport {
        substeps: 0,
        cg_iterations: 0,
        cg_converged: true,
        collisions: 0,
    };
    for substep in 0..options.substeps {
        ws.prev_x.clone_from(&system.positions);
        ws.prev_v.clone_from(&system.velocities);
        let ParticleSystem {
            positions,
            velocities,
            inverse_masses,
            springs,
            gravity,
            drag,
        } = system;
        let model = Model {
            springs,
            inverse_masses,
            gravity: *gravity,
            drag: *drag,
        };
        for (v, &w) in velocities.iter_mut().zip(model.inverse_masses) {
            if w <= 0.0 {
                *v = [0.0; 3];
            }
        }
        let (iterations, converged) = match options.integrator {
            Integrator::ExplicitEuler => {
                explicit_euler(&model, positions, velocities, h, ws);
                (0, true)
            }
            Integrator::SymplecticEuler => {
                symplectic_euler(&model, positions, velocities, h, ws);
                (0, true)
            }
            Integrator::VelocityVerlet => {
                velocity_verlet(&model, positions, velocities, h, ws);
                (0, true)
            }
            Integrator::Rk4 => {
                rk4(&model, positions, velocities, h, ws);
                (0, true)
            }
            Integrator::ImplicitEuler => {
                implicit_euler(&model, positions, velocities, h, options, ws)
            }
        };
        let collisions = collide_all(
            colliders,
            positions,
            velocities,
            model.inverse_masses,
            options,
        );
        let non_finite = positions
            .iter()
            .zip(velocities.iter())
            .position(|(x, v)| !(finite3(*x) && finite3(*v)));
        let failure = match (non_finite, threshold) {
            (Some(particle), _) => Some(Failure::NonFinite { particle }),
            (None, Some(limit)) => {
                let energy = system.total_energy();
                // NaN compares as unordered and is rejected too.
                let over = energy.partial_cmp(&limit).is_none_or(|o| o.is_gt());
                over.then_some(Failure::Energy { energy })
            }
            (None, None) => None,
        };
        if let Some(kind) = failure {
            system.positions.clone_from(&ws.prev_x);
            system.velocities.clone_from(&ws.prev_v);
            return Err(StepFailure { substep, kind });
        }
        report.substeps += 1;
        report.cg_iterations += iterations;
        report.cg_converged &= converged;
        report.collisions += collisions;
    }
    Ok(report)
}

/// Adds the spring forces at `(x, v)` to `f`, springs in list order.
fn add_spring_forces(springs: &[Spring], x: &[Vec3], v: &[Vec3], f: &mut [Vec3]) {
    for s in springs {
        let (Some(&xa), Some(&xb), Some(&va), Some(&vb)) =
            (x.get(s.a), x.get(s.b), v.get(s.a), v.get(s.b))
        else {
            continue;
        };
        let Some((u, len)) = spring_frame(xa, xb) else {
            if s.rest_length == 0.0 {
                // A zero-rest-length spring is linear, −k d, and needs no direction.
                let fa = scale(sub(xa, xb), -s.stiffness);
                add_at(f, s.a, fa);
                add_at(f, s.b, scale(fa, -1.0));
            }
            continue;
        };
        let magnitude = s.stiffness * (len - s.rest_length) + s.damping * dot(sub(va, vb), u);
        let fa = scale(u, -magnitude);
        add_at(f, s.a, fa);
        add_at(f, s.b, scale(fa, -1.0));
    }
}

/// Accelerations at `(x, v)`: `g + w (f_springs − drag v)` for free particles, 0 for pinned.
fn accelerations(model: &Model, x: &[Vec3], v: &[Vec3], force: &mut Vec<Vec3>, acc: &mut [Vec3]) {
    resize(force, x.len());
    add_spring_forces(model.springs, x, v, force);
    for (((a, f), vi), &w) in acc
        .iter_mut()
        .zip(force.iter())
        .zip(v)
        .zip(model.inverse_masses)
    {
        *a = if w > 0.0 {
            axpy(model.gravity, w, axpy(*f, -model.drag, *vi))
        } else {
            [0.0; 3]
        };
    }
}

fn explicit_euler(model: &Model, x: &mut [Vec3], v: &mut [Vec3], h: f64, ws: &mut Workspace) {
    resize(&mut ws.acc, x.len());
    accelerations(model, x, v, &mut ws.force, &mut ws.acc);
    for ((xi, vi), ai) in x.iter_mut().zip(v.iter_mut()).zip(&ws.acc) {
        *xi = axpy(*xi, h, *vi);
        *vi = axpy(*vi, h, *ai);
    }
}

fn symplectic_euler(model: &Model, x: &mut [Vec3], v: &mut [Vec3], h: f64, ws: &mut Workspace) {
    resize(&mut ws.acc, x.len());
    accelerations(model, x, v, &mut ws.force, &mut ws.acc);
    for ((xi, vi), ai) in x.iter_mut().zip(v.iter_mut()).zip(&ws.acc) {
        *vi = axpy(*vi, h, *ai);
        *xi = axpy(*xi, h, *vi);
    }
}

fn velocity_verlet(model: &Model, x: &mut [Vec3], v: &mut [Vec3], h: f64, ws: &mut Workspace) {
    resize(&mut ws.acc, x.len());
    accelerations(model, x, v, &mut ws.force, &mut ws.acc);
    for ((xi, vi), ai) in x.iter_mut().zip(v.iter_mut()).zip(&ws.acc) {
        *vi = axpy(*vi, 0.5 * h, *ai);
        *xi = axpy(*xi, h, *vi);
    }
    accelerations(model, x, v, &mut ws.force, &mut ws.acc);
    for (vi, ai) in v.iter_mut().zip(&ws.acc) {
        *vi = axpy(*vi, 0.5 * h, *ai);
    }
}

fn rk4(model: &Model, x: &mut [Vec3], v: &mut [Vec3], h: f64, ws: &mut Workspace) {
    let n = x.len();
    for buf in [
        &mut ws.acc,
        &mut ws.xt,
        &mut ws.vt,
        &mut ws.asum,
        &mut ws.vsum,
    ] {
        resize(buf, n);
    }
    // Stage 1 at (x, v).
    accelerations(model, x, v, &mut ws.force, &mut ws.acc);
    ws.asum.copy_from_slice(&ws.acc);
    ws.vsum.copy_from_slice(v);
    ws.vt.copy_from_slice(v);
    // Stages 2 and 3 at half steps, weight 2; stage 4 at the full step, weight 1.
    for (fraction, weight) in [(0.5, 2.0), (0.5, 2.0), (1.0, 1.0)] {
        for i in 0..n {
            let (Some(&x0), Some(&v0), Some(&a), Some(xt), Some(vt)) = (
                x.get(i),
                v.get(i),
                ws.acc.get(i),
                ws.xt.get_mut(i),
                ws.vt.get_mut(i),
            ) else {
                continue;
            };
            // `vt` holds the previous stage's velocity (v itself before stage 2).
            *xt = axpy(x0, fraction * h, *vt);
            *vt = axpy(v0, fraction * h, a);
        }
        accelerations(model, &ws.xt, &ws.vt, &mut ws.force, &mut ws.acc);
        for (((asum, vsum), a), vt) in ws
            .asum
            .iter_mut()
            .zip(ws.vsum.iter_mut())
            .zip(&ws.acc)
            .zip(&ws.vt)
        {
            *asum = axpy(*asum, weight, *a);
            *vsum = axpy(*vsum, weight, *vt);
        }
    }
    for (((xi, vi), asum), vsum) in x.iter_mut().zip(v.iter_mut()).zip(&ws.asum).zip(&ws.vsum) {
        *xi = axpy(*xi, h / 6.0, *vsum);
        *vi = axpy(*vi, h / 6.0, *asum);
    }
}

/// One linearised backward-Euler substep (Baraff & Witkin 1998, §3 and §5):
/// `A Δv = b` with `A = M + h (D + drag I) + h² K` and `b = h (f₀ − h K v₀)`, where for each
/// spring `K_s = k (û ûᵀ + max(0, 1 − L/|d|) (I − û ûᵀ))` is the stiffness block (`∂f_a/∂x_a =
/// −K_s`) with the transverse term clamped at zero under compression (|d| < L), which keeps
/// `K_s` positive semi-definite (the compressed spring then has its axial stiffness only), and
/// `D_s = c û ûᵀ` is the damping block (`∂f_a/∂v_a = −D_s`; the position derivative of the
/// damping force is dropped, as in Baraff & Witkin). Pinned rows and columns are filtered out,
/// so the solved block is SPD. Returns (CG iterations, converged).
fn implicit_euler(
    model: &Model,
    x: &mut [Vec3],
    v: &mut [Vec3],
    h: f64,
    options: &SimOptions,
    ws: &mut Workspace,
) -> (usize, bool) {
    let n = x.len();
    for buf in [
        &mut ws.precond,
        &mut ws.rhs,
        &mut ws.dv,
        &mut ws.r,
        &mut ws.z,
        &mut ws.p,
        &mut ws.q,
    ] {
        resize(buf, n);
    }
    resize(&mut ws.force, n);
    add_spring_forces(model.springs, x, v, &mut ws.force);

    ws.kblk.clear();
    ws.cblk.clear();
    for s in model.springs {
        let frame = match (x.get(s.a), x.get(s.b)) {
            (Some(&xa), Some(&xb)) => spring_frame(xa, xb),
            _ => None,
        };
        let (k, c) = match frame {
            Some((u, len)) => {
                let t = (1.0 - s.rest_length / len).max(0.0);
                let uu = outer(u);
                let k = sym_add(
                    sym_scale(uu, s.stiffness * (1.0 - t)),
                    sym_identity(s.stiffness * t),
                );
                (k, sym_scale(uu, s.damping))
            }
            // Degenerate length: a zero-rest-length spring keeps its exact Jacobian k I.
            None if s.rest_length == 0.0 => (sym_identity(s.stiffness), [0.0; 6]),
            None => ([0.0; 6], [0.0; 6]),
        };
        ws.kblk.push(k);
        ws.cblk.push(sym_add(sym_scale(k, h * h), sym_scale(c, h)));
    }

    // q = K v0 (graph-Laplacian assembly of the spring blocks).
    apply_blocks(model.springs, &ws.kblk, v, &mut ws.q);
    ws.mass_term.clear();
    for (i, &w) in model.inverse_masses.iter().enumerate() {
        let free = w > 0.0;
        let m = if free { 1.0 / w } else { 0.0 };
        ws.mass_term
            .push(if free { m + h * model.drag } else { 0.0 });
        let (Some(&f), Some(&vi), Some(&kv), Some(b)) =
            (ws.force.get(i), v.get(i), ws.q.get(i), ws.rhs.get_mut(i))
        else {
            continue;
        };
        *b = if free {
            let f0 = axpy(axpy(f, m, model.gravity), -model.drag, vi);
            scale(axpy(f0, -h, kv), h)
        } else {
            [0.0; 3]
        };
    }
    // Jacobi preconditioner: inverse diagonal of A over free particles, 0 for pinned.
    for (d, &m) in ws.precond.iter_mut().zip(&ws.mass_term) {
        *d = [m; 3];
    }
    for (s, c) in model.springs.iter().zip(&ws.cblk) {
        let diag = [c[0], c[3], c[5]];
        add_at(&mut ws.precond, s.a, diag);
        add_at(&mut ws.precond, s.b, diag);
    }
    for (d, &w) in ws.precond.iter_mut().zip(model.inverse_masses) {
        *d = if w > 0.0 {
            [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]]
        } else {
            [0.0; 3]
        };
    }

    let (iterations, converged) = pcg(model, ws, options.cg_tolerance, options.cg_max_iterations);
    for (((xi, vi), dv), &w) in x
        .iter_mut()
        .zip(v.iter_mut())
        .zip(&ws.dv)
        .zip(model.inverse_masses)
    {
        if w > 0.0 {
            *vi = add(*vi, *dv);
            *xi = axpy(*xi, h, *vi);
        }
    }
    (iterations, converged)
}

/// Filtered, Jacobi-preconditioned conjugate gradients on `A Δv = b` (ws.rhs → ws.dv), starting
/// from `Δv = 0`; stops at `‖r‖ ≤ tol ‖b‖`, at `max_iterations`, or on a non-positive curvature
/// (which exact arithmetic rules out). The system is solved for `b / max|bᵢ|` and the result
/// scaled back, so that the dot products neither underflow nor overflow for tiny or huge states.
fn pcg(model: &Model, ws: &mut Workspace, tol: f64, max_iterations: usize) -> (usize, bool) {
    ws.dv.fill([0.0; 3]);
    let b_scale = ws
        .rhs
        .iter()
        .flat_map(|b| b.iter())
        .fold(0.0f64, |m, c| m.max(c.abs()));
    if !(b_scale > 0.0 && b_scale.is_finite()) {
        return (0, b_scale == 0.0);
    }
    for (r, b) in ws.r.iter_mut().zip(&ws.rhs) {
        // Divide (not multiply by the reciprocal, which overflows for a subnormal scale).
        *r = b.map(|c| c / b_scale);
    }
    let (iterations, converged) = pcg_unit(model, ws, tol, max_iterations);
    for dv in &mut ws.dv {
        *dv = scale(*dv, b_scale);
    }
    (iterations, converged)
}

/// The CG loop of [`pcg`], on the right-hand side already in `ws.r` (largest entry 1).
fn pcg_unit(model: &Model, ws: &mut Workspace, tol: f64, max_iterations: usize) -> (usize, bool) {
    let target = tol * dot_all(&ws.r, &ws.r).sqrt();
    precondition(&ws.precond, &ws.r, &mut ws.z);
    ws.p.copy_from_slice(&ws.z);
    let mut rz = dot_all(&ws.r, &ws.z);
    for iteration in 1..=max_iterations {
        apply_system(model, ws);
        let pq = dot_all(&ws.p, &ws.q);
        if !(pq > 0.0 && pq.is_finite()) {
            return (iteration - 1, false);
        }
        let alpha = rz / pq;
        for (((dv, r), p), q) in ws.dv.iter_mut().zip(ws.r.iter_mut()).zip(&ws.p).zip(&ws.q) {
            *dv = axpy(*dv, alpha, *p);
            *r = axpy(*r, -alpha, *q);
        }
        if dot_all(&ws.r, &ws.r).sqrt() <= target {
            return (iteration, true);
        }
        precondition(&ws.precond, &ws.r, &mut ws.z);
        let rz_new = dot_all(&ws.r, &ws.z);
        let beta = rz_new / rz;
        rz = rz_new;
        for (p, z) in ws.p.iter_mut().zip(&ws.z) {
            *p = axpy(*z, beta, *p);
        }
    }
    (max_iterations, false)
}

/// ws.q = S A S ws.p, with S the pinned-particle filter.
fn apply_system(model: &Model, ws: &mut Workspace) {
    for ((q, p), &m) in ws.q.iter_mut().zip(&ws.p).zip(&ws.mass_term) {
        *q = scale(*p, m);
    }
    add_blocks(model.springs, &ws.cblk, &ws.p, &mut ws.q);
    for (q, &w) in ws.q.iter_mut().zip(model.inverse_masses) {
        if w <= 0.0 {
            *q = [0.0; 3];
        }
    }
}

/// out = Σ_s (blocks as a Laplacian) · p.
fn apply_blocks(springs: &[Spring], blocks: &[Sym3], p: &[Vec3], out: &mut [Vec3]) {
    out.fill([0.0; 3]);
    add_blocks(springs, blocks, p, out);
}

/// out += Σ_s B_s (p_a − p_b) at a and −B_s (p_a − p_b) at b.
fn add_blocks(springs: &[Spring], blocks: &[Sym3], p: &[Vec3], out: &mut [Vec3]) {
    for (s, blk) in springs.iter().zip(blocks) {
        let (Some(&pa), Some(&pb)) = (p.get(s.a), p.get(s.b)) else {
            continue;
        };
        let y = sym_mul(blk, sub(pa, pb));
        add_at(out, s.a, y);
        add_at(out, s.b, scale(y, -1.0));
    }
}

fn precondition(precond: &[Vec3], r: &[Vec3], z: &mut [Vec3]) {
    for ((z, r), d) in z.iter_mut().zip(r).zip(precond) {
        *z = [r[0] * d[0], r[1] * d[1], r[2] * d[2]];
    }
}

// ---------------------------------------------------------------------------------------------
// Collisions
// ---------------------------------------------------------------------------------------------

fn collide_all(
    colliders: &[Collider],
    x: &mut [Vec3],
    v: &mut [Vec3],
    inverse_masses: &[f64],
    options: &SimOptions,
) -> usize {
    if colliders.is_empty() {
        return 0;
    }
    let mut count = 0;
    for ((xi, vi), &w) in x.iter_mut().zip(v.iter_mut()).zip(inverse_masses) {
        if w <= 0.0 || !(finite3(*xi) && finite3(*vi)) {
            continue;
        }
        for _ in 0..COLLISION_PASSES {
            let mut any = false;
            for c in colliders {
                if collide_one(c, xi, vi, options) {
                    any = true;
                    count += 1;
                }
            }
            if !any {
                break;
            }
        }
    }
    count
}

/// Resolves one particle against one collider; true when it was in contact.
fn collide_one(collider: &Collider, x: &mut Vec3, v: &mut Vec3, o: &SimOptions) -> bool {
    let margin = o.margin;
    match collider {
        Collider::Plane { point, normal } => {
            let Some(n) = normalized(*normal) else {
                return false;
            };
            let phi = dot(sub(*x, *point), n);
            if phi < margin - CONTACT_SLOP {
                *x = axpy(*x, margin - phi, n);
                respond(v, n, o);
                true
            } else {
                false
            }
        }
        Collider::Sphere { center, radius } => {
            let d = sub(*x, *center);
            let len = norm(d);
            let reach = radius + margin;
            if len < reach - CONTACT_SLOP {
                let n = if len > 0.0 {
                    scale(d, 1.0 / len)
                } else {
                    [0.0, 1.0, 0.0]
                };
                *x = axpy(*center, reach, n);
                respond(v, n, o);
                true
            } else {
                false
            }
        }
        Collider::Mesh(mesh) => {
            let Some((q, normal)) = mesh.closest(*x) else {
                return false;
            };
            let Some(n) = normalized(normal) else {
                return false;
            };
            if !finite3(q) {
                return false;
            }
            let rel = sub(*x, q);
            let dist = norm(rel);
            let hit = if dot(rel, n) >= 0.0 {
                dist < margin - CONTACT_SLOP
            } else {
                dist < o.mesh_band
            };
            if hit {
                *x = axpy(q, margin, n);
                respond(v, n, o);
            }
            hit
        }
    }
}

/// Velocity response at a contact with unit normal `n`: when the particle moves into the
/// surface (`v·n < 0`), the normal velocity becomes `−e v·n`, and the tangential velocity is
/// shortened by `μ (1 + e) |v·n|` (Coulomb bound), stopping at zero.
fn respond(v: &mut Vec3, n: Vec3, o: &SimOptions) {
    let vn = dot(*v, n);
    if vn >= 0.0 {
        return;
    }
    let vt = axpy(*v, -vn, n);
    let dvn = -(1.0 + o.restitution) * vn;
    let vt_len = norm(vt);
    let limit = o.friction * dvn;
    let vt_new = if vt_len <= limit {
        [0.0; 3]
    } else {
        scale(vt, 1.0 - limit / vt_len)
    };
    *v = axpy(vt_new, -o.restitution * vn, n);
}

// ---------------------------------------------------------------------------------------------
// Small vector and symmetric-matrix helpers
// ---------------------------------------------------------------------------------------------

/// Symmetric 3×3 matrix as (xx, xy, xz, yy, yz, zz).
type Sym3 = [f64; 6];

fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// a + s b.
fn axpy(a: Vec3, s: f64, b: Vec3) -> Vec3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

fn finite3(a: Vec3) -> bool {
    a.iter().all(|c| c.is_finite())
}

fn normalized(a: Vec3) -> Option<Vec3> {
    let len = norm(a);
    (len.is_finite() && len > 0.0).then(|| scale(a, 1.0 / len))
}

fn add_at(buf: &mut [Vec3], i: usize, d: Vec3) {
    if let Some(e) = buf.get_mut(i) {
        *e = add(*e, d);
    }
}

fn dot_all(a: &[Vec3], b: &[Vec3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| dot(*x, *y)).sum()
}

/// (unit direction a → from b, length) of `xa − xb`, or `None` below [`MIN_SPRING_LENGTH`].
fn spring_frame(xa: Vec3, xb: Vec3) -> Option<(Vec3, f64)> {
    let d = sub(xa, xb);
    let len = norm(d);
    (len > MIN_SPRING_LENGTH && len.is_finite()).then(|| (scale(d, 1.0 / len), len))
}

fn spring_energy(springs: &[Spring], x: &[Vec3]) -> f64 {
    springs
        .iter()
        .map(|s| match (x.get(s.a), x.get(s.b)) {
            (Some(&xa), Some(&xb)) => {
                let stretch = norm(sub(xa, xb)) - s.rest_length;
                0.5 * s.stiffness * stretch * stretch
            }
            _ => 0.0,
        })
        .sum()
}

fn outer(u: Vec3) -> Sym3 {
    [
        u[0] * u[0],
        u[0] * u[1],
        u[0] * u[2],
        u[1] * u[1],
        u[1] * u[2],
        u[2] * u[2],
    ]
}

fn sym_identity(s: f64) -> Sym3 {
    [s, 0.0, 0.0, s, 0.0, s]
}

fn sym_scale(m: Sym3, s: f64) -> Sym3 {
    m.map(|e| e * s)
}

fn sym_add(a: Sym3, b: Sym3) -> Sym3 {
    [
        a[0] + b[0],
        a[1] + b[1],
        a[2] + b[2],
        a[3] + b[3],
        a[4] + b[4],
        a[5] + b[5],
    ]
}

fn sym_mul(m: &Sym3, v: Vec3) -> Vec3 {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[1] * v[0] + m[3] * v[1] + m[4] * v[2],
        m[2] * v[0] + m[4] * v[1] + m[5] * v[2],
    ]
}

#[cfg(test)]
mod tests {
    // Test code: a failed unwrap is a failed test.
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;
    use proptest::prelude::*;
    use std::time::Instant;

    /// A free particle of mass `mass` on a zero-rest-length spring (exactly linear, `f = −k d`)
    /// to a pinned anchor at the origin, displaced by `displacement` along x, no gravity.
    fn anchored_oscillator(mass: f64, stiffness: f64, displacement: f64) -> ParticleSystem {
        let mut s = ParticleSystem::new(
            vec![[0.0; 3], [displacement, 0.0, 0.0]],
            vec![0.0, 1.0 / mass],
        );
        s.gravity = [0.0; 3];
        s.springs.push(Spring {
            a: 0,
            b: 1,
            rest_length: 0.0,
            stiffness,
            damping: 0.0,
        });
        s
    }

    fn options(integrator: Integrator, dt: f64, substeps: usize) -> SimOptions {
        SimOptions {
            dt,
            substeps,
            integrator,
            margin: 0.0,
            ..SimOptions::default()
        }
    }

    fn run_energies(
        system: &mut ParticleSystem,
        o: &SimOptions,
        frames: usize,
    ) -> (Vec<f64>, SimulationReport) {
        let mut energies = vec![system.total_energy()];
        let report = simulate(system, &[], o, frames, |_, _, r| {
            energies.push(r.total_energy)
        })
        .unwrap();
        (energies, report)
    }

    fn all_finite(s: &ParticleSystem) -> bool {
        s.positions.iter().chain(&s.velocities).all(|p| finite3(*p))
    }

    const STIFF_K: f64 = 1e5;
    const STEPS: usize = 10_000;

    #[test]
    fn stiff_spring_explicit_euler_divergence_is_detected() {
        let (m, h) = (10.0, 1.0 / 60.0);
        let mut s = anchored_oscillator(m, STIFF_K, 0.1);
        let (energies, report) =
            run_energies(&mut s, &options(Integrator::ExplicitEuler, h, 1), STEPS);
        let d = report
            .diverged
            .expect("explicit Euler must be reported as diverged");
        let growth = 1.0 + h * h * STIFF_K / m;
        let ratios: Vec<f64> = energies.windows(2).map(|w| w[1] / w[0]).collect();
        println!(
            "explicit Euler k=1e5 m=10 h=1/60: diverged at frame {} step {} energy {:.3e} J \
             threshold {:.3e} J; per-step energy ratios {:?} (1 + h²ω² = {growth:.6})",
            d.frame, d.step, d.energy, d.threshold, ratios
        );
        assert!(d.step <= STEPS && d.frame < STEPS);
        assert_eq!(d.reason, DivergenceReason::EnergyExceeded);
        assert_eq!(report.frames.len(), d.frame);
        assert_eq!(report.steps + 1, d.step);
        assert!(d.energy > d.threshold);
        // E_ref = initial energy ½ k x² = 500 J, threshold 5e5 J.
        assert!((d.threshold - 1e3 * 500.0).abs() < 1e-6);
        assert!(!ratios.is_empty());
        for r in &ratios {
            assert!((r - growth).abs() < 1e-9 * growth, "ratio {r} vs {growth}");
        }
        // The rejected step would have multiplied the kept state's energy by the same factor.
        assert!((d.energy / s.total_energy() - growth).abs() < 1e-9 * growth);
        assert!(all_finite(&s));
        assert!(s.total_energy() <= d.threshold);
    }

    #[test]
    fn stiff_spring_symplectic_methods_stay_bounded() {
        let (m, h) = (10.0, 1.0 / 60.0);
        let a = 0.5 * h * (STIFF_K / m).sqrt(); // h ω / 2 = 0.8333
        // Symplectic Euler keeps v² + ω²x² − hω² x v: E oscillates between Q/(1 + a) and
        // Q/(1 − a). Velocity Verlet keeps v² + (1 − a²) ω² x²: E/Q lies in [1, 1/(1 − a²)].
        let bounds = [
            (Integrator::SymplecticEuler, (1.0 + a) / (1.0 - a)),
            (Integrator::VelocityVerlet, 1.0 / (1.0 - a * a)),
        ];
        for (integrator, bound) in bounds {
            let mut s = anchored_oscillator(m, STIFF_K, 0.1);
            let (e, report) = run_energies(&mut s, &options(integrator, h, 1), STEPS);
            assert!(
                report.diverged.is_none(),
                "{integrator}: {:?}",
                report.diverged
            );
            assert_eq!(e.len(), STEPS + 1);
            let max = e.iter().copied().fold(f64::MIN, f64::max);
            let min = e.iter().copied().fold(f64::MAX, f64::min);
            let first = e[..1000].iter().copied().fold(f64::MIN, f64::max);
            let last = e[e.len() - 1000..].iter().copied().fold(f64::MIN, f64::max);
            println!(
                "{integrator} k=1e5 m=10 h=1/60 (hω={:.4}) over {STEPS} steps: energy in \
                 [{min:.3}, {max:.3}] J, max/min {:.4} (bound {bound:.4}); max first 1000 \
                 {first:.4} J, last 1000 {last:.4} J",
                2.0 * a,
                max / min
            );
            assert!(
                max / min <= bound * (1.0 + 1e-9),
                "{integrator}: {}",
                max / min
            );
            assert!(max / min > 0.9 * bound, "the band should be explored");
            assert!(last <= first * 1.01);
        }
    }

    #[test]
    fn stiff_spring_implicit_euler_is_stable_and_damps() {
        let h = 1.0 / 60.0;
        for m in [10.0, 1.0] {
            let mut s = anchored_oscillator(m, STIFF_K, 0.1);
            let (e, report) =
                run_energies(&mut s, &options(Integrator::ImplicitEuler, h, 1), STEPS);
            assert!(report.diverged.is_none());
            assert!(all_finite(&s));
            for w in e.windows(2) {
                assert!(
                    // (+1e-300: the state decays into subnormals, where rounding is coarse.)
                    w[1] <= w[0] * (1.0 + 1e-12) + 1e-300,
                    "energy rose: {} -> {}",
                    w[0],
                    w[1]
                );
            }
            // Linear spring: backward Euler divides ω²x² + v² by exactly 1 + h²ω² per step.
            let expected = 1.0 / (1.0 + h * h * STIFF_K / m);
            let first = e[1] / e[0];
            let iters: usize = report.frames.iter().map(|f| f.cg_iterations).sum();
            println!(
                "implicit Euler k=1e5 m={m} (hω={:.3}): first-step energy ratio {first:.6} \
                 (exact 1/(1+h²ω²) = {expected:.6}), final energy {:.3e} J, CG iterations \
                 {iters} over {STEPS} steps",
                h * (STIFF_K / m).sqrt(),
                e[e.len() - 1]
            );
            assert!((first - expected).abs() < 1e-9);
            assert!(e[e.len() - 1] < 1e-6 * e[0]);
            assert!(report.frames.iter().all(|f| f.cg_converged));
        }
        // At m = 1 kg, h ω ≈ 5.27 > 2: symplectic Euler must blow up and be caught.
        let mut s = anchored_oscillator(1.0, STIFF_K, 0.1);
        let (_, report) = run_energies(&mut s, &options(Integrator::SymplecticEuler, h, 1), STEPS);
        let d = report
            .diverged
            .expect("symplectic Euler at h ω > 2 must diverge");
        println!(
            "symplectic Euler k=1e5 m=1: diverged at frame {} step {} ({:?})",
            d.frame, d.step, d.reason
        );
        assert!(d.step <= STEPS);
        assert!(all_finite(&s));
    }

    #[test]
    fn rk4_matches_the_analytic_oscillator_with_fourth_order_convergence() {
        let (m, k, x0): (f64, f64, f64) = (1.0, 4.0, 0.1);
        let omega = (k / m).sqrt();
        let error = |frames: usize| {
            let dt = 1.0 / frames as f64;
            let mut s = anchored_oscillator(m, k, x0);
            let r = simulate(
                &mut s,
                &[],
                &options(Integrator::Rk4, dt, 1),
                frames,
                |_, _, _| {},
            )
            .unwrap();
            assert!(r.diverged.is_none());
            let t = frames as f64 * dt;
            let (x, v) = (s.positions[1][0], s.velocities[1][0]);
            let (xe, ve) = (x0 * (omega * t).cos(), -x0 * omega * (omega * t).sin());
            ((x - xe).powi(2) + ((v - ve) / omega).powi(2)).sqrt()
        };
        let (e20, e40, e80) = (error(20), error(40), error(80));
        let (r1, r2) = (e20 / e40, e40 / e80);
        println!(
            "RK4 ω=2 after 1 s: error dt=1/20 {e20:.3e}, 1/40 {e40:.3e}, 1/80 {e80:.3e} m; \
             ratios {r1:.3}, {r2:.3}"
        );
        assert!(e40 < 1e-6);
        assert!((12.0..=20.0).contains(&r1), "{r1}");
        assert!((12.0..=20.0).contains(&r2), "{r2}");
    }

    /// Three particles of different masses on damped springs (not at rest length), spinning
    /// and drifting, no gravity or drag.
    fn spinning_triangle() -> ParticleSystem {
        let positions = vec![[1.0, 0.0, 0.0], [-0.5, 0.8, 0.1], [-0.4, -0.9, -0.2]];
        let inverse_masses = vec![1.0, 0.5, 1.0 / 3.0];
        let mut s = ParticleSystem::new(positions.clone(), inverse_masses);
        s.gravity = [0.0; 3];
        let spin = [0.3, 0.5, 2.0];
        let drift = [0.2, -0.1, 0.05];
        s.velocities = positions
            .iter()
            .map(|p| add(cross(spin, *p), drift))
            .collect();
        for (a, b) in [(0, 1), (1, 2), (2, 0)] {
            let len = norm(sub(positions[a], positions[b]));
            s.springs.push(Spring {
                a,
                b,
                rest_length: 0.8 * len,
                stiffness: 50.0,
                damping: 0.5,
            });
        }
        s
    }

    #[test]
    fn momentum_is_conserved_by_the_symplectic_methods() {
        for integrator in [Integrator::SymplecticEuler, Integrator::VelocityVerlet] {
            let mut s = spinning_triangle();
            let start = s.measure();
            let r = simulate(
                &mut s,
                &[],
                &options(integrator, 1.0 / 240.0, 1),
                2000,
                |_, _, _| {},
            )
            .unwrap();
            assert!(r.diverged.is_none());
            let end = s.measure();
            let dp =
                norm(sub(end.linear_momentum, start.linear_momentum)) / norm(start.linear_momentum);
            let dl = norm(sub(end.angular_momentum, start.angular_momentum))
                / norm(start.angular_momentum);
            println!(
                "{integrator} spinning triangle 2000 steps: relative change of linear momentum \
                 {dp:.2e}, angular momentum {dl:.2e}; spring energy start {:.3} end {:.3} J",
                start.spring_energy, end.spring_energy
            );
            assert!(dp < 1e-9);
            assert!(dl < 1e-9);
            // It really moved and vibrated.
            assert!((end.spring_energy - start.spring_energy).abs() > 1e-3);
        }
    }

    #[test]
    fn free_fall_matches_the_closed_form() {
        let (y0, g, h, frames) = (10.0, 9.81, 1.0 / 60.0, 60usize);
        for integrator in Integrator::ALL {
            let mut s = ParticleSystem::new(vec![[0.5, y0, -0.25]], vec![2.0]);
            let r = simulate(
                &mut s,
                &[],
                &options(integrator, h, 1),
                frames,
                |_, _, _| {},
            )
            .unwrap();
            assert!(r.diverged.is_none());
            let n = frames as f64;
            let t = n * h;
            let exact = y0 - 0.5 * g * t * t;
            let y = s.positions[0][1];
            // First-order methods: symplectic (and implicit, identical without springs) Euler
            // lands at y0 − g h² n(n+1)/2, explicit Euler at y0 − g h² n(n−1)/2.
            let expected = match integrator {
                Integrator::SymplecticEuler | Integrator::ImplicitEuler => {
                    y0 - 0.5 * g * h * h * n * (n + 1.0)
                }
                Integrator::ExplicitEuler => y0 - 0.5 * g * h * h * n * (n - 1.0),
                Integrator::VelocityVerlet | Integrator::Rk4 => exact,
            };
            println!(
                "{integrator} free fall 1 s: y {y:.12} exact {exact:.12} error {:.3e} m",
                y - exact
            );
            assert!(
                (y - expected).abs() < 1e-9,
                "{integrator}: {y} vs {expected}"
            );
            assert!((s.velocities[0][1] + g * t).abs() < 1e-9);
            assert_eq!(s.positions[0][0], 0.5);
            assert_eq!(s.positions[0][2], -0.25);
        }
    }

    #[test]
    fn grid_triangles_face_up_and_cover_the_grid() {
        let (nx, ny) = (5, 4);
        let cloth = cloth_grid(&ClothOptions {
            nx,
            ny,
            ..ClothOptions::default()
        })
        .unwrap();
        let tris = grid_triangles(nx, ny);
        assert_eq!(tris.len(), 2 * (nx - 1) * (ny - 1));
        let mut area = 0.0;
        for t in &tris {
            let [a, b, c] = t.map(|i| cloth.positions[i as usize]);
            let nrm = cross(sub(b, a), sub(c, a));
            assert!(nrm[1] > 0.0 && nrm[0] == 0.0 && nrm[2] == 0.0, "{t:?}");
            area += 0.5 * norm(nrm);
        }
        assert!((area - 1.0).abs() < 1e-12);
        assert!(grid_triangles(1, 5).is_empty());
        // Spring counts: structural, shear, bend.
        let expected =
            (nx - 1) * ny + nx * (ny - 1) + 2 * (nx - 1) * (ny - 1) + (nx - 2) * ny + nx * (ny - 2);
        assert_eq!(cloth.springs.len(), expected);
        cloth.validate().unwrap();
        let mass: f64 = cloth.inverse_masses.iter().map(|w| 1.0 / w).sum();
        assert!((mass - 0.5).abs() < 1e-12);
    }

    const SPHERE_CENTER: Vec3 = [0.0, 0.35, 0.0];
    const SPHERE_RADIUS: f64 = 0.3;

    struct ClothRun {
        positions: Vec<Vec3>,
        kinetic: Vec<f64>,
        min_sphere_clearance: f64,
        min_height: f64,
        cg_iterations: usize,
        collisions: usize,
        seconds: f64,
    }

    fn drop_cloth() -> ClothRun {
        let start = Instant::now();
        let (nx, ny) = (24, 24);
        let top = SPHERE_CENTER[1] + SPHERE_RADIUS;
        let mut cloth = cloth_grid(&ClothOptions {
            nx,
            ny,
            center: [0.0, top + 0.5, 0.0],
            size: [1.0, 1.0],
            total_mass: 0.5,
            drag: 1.0,
            ..ClothOptions::default()
        })
        .unwrap();
        let colliders = [
            Collider::Plane {
                point: [0.0; 3],
                normal: [0.0, 1.0, 0.0],
            },
            Collider::Sphere {
                center: SPHERE_CENTER,
                radius: SPHERE_RADIUS,
            },
        ];
        let o = SimOptions {
            dt: 1.0 / 60.0,
            substeps: 3,
            integrator: Integrator::ImplicitEuler,
            restitution: 0.0,
            friction: 0.5,
            margin: 0.005,
            cg_tolerance: 1e-5,
            cg_max_iterations: 200,
            ..SimOptions::default()
        };
        let mut run = ClothRun {
            positions: Vec::new(),
            kinetic: Vec::new(),
            min_sphere_clearance: f64::INFINITY,
            min_height: f64::INFINITY,
            cg_iterations: 0,
            collisions: 0,
            seconds: 0.0,
        };
        for _ in 0..120 {
            let rep = step(&mut cloth, &colliders, &o).unwrap();
            run.cg_iterations += rep.cg_iterations;
            run.collisions += rep.collisions;
            for p in &cloth.positions {
                let clearance = norm(sub(*p, SPHERE_CENTER)) - (SPHERE_RADIUS + o.margin);
                run.min_sphere_clearance = run.min_sphere_clearance.min(clearance);
                run.min_height = run.min_height.min(p[1] - o.margin);
            }
            run.kinetic.push(cloth.measure().kinetic_energy);
        }
        run.positions = cloth.positions;
        run.seconds = start.elapsed().as_secs_f64();
        run
    }

    #[test]
    fn cloth_drapes_over_a_sphere_and_settles_deterministically() {
        let first = drop_cloth();
        let peak = first.kinetic.iter().copied().fold(0.0, f64::max);
        let end = first.kinetic[first.kinetic.len() - 1];
        let corners = [0usize, 23, 24 * 23, 24 * 24 - 1].map(|i| first.positions[i][1]);
        let top = SPHERE_CENTER[1] + SPHERE_RADIUS;
        println!(
            "cloth 24x24 on sphere, 120 frames x 3 substeps implicit Euler: {:.3} s; peak KE \
             {peak:.4} J, final KE {end:.3e} J ({:.3} % of peak); corner heights {corners:?} \
             (sphere top {top}); min sphere clearance {:.3e} m, min height above plane margin \
             {:.3e} m; CG iterations {} ({:.1}/substep), contacts {}",
            first.seconds,
            100.0 * end / peak,
            first.min_sphere_clearance,
            first.min_height,
            first.cg_iterations,
            first.cg_iterations as f64 / 360.0,
            first.collisions
        );
        assert!(first.min_sphere_clearance >= -1e-9);
        assert!(first.min_height >= -1e-9);
        assert!(end < 0.01 * peak);
        assert!(corners.iter().all(|&y| y < top - 0.1));
        assert!(first.collisions > 0);
        let second = drop_cloth();
        let same = first
            .positions
            .iter()
            .zip(&second.positions)
            .all(|(a, b)| a.map(f64::to_bits) == b.map(f64::to_bits));
        assert!(same, "rerun is not bit-identical");
    }

    /// A brute-force triangle-mesh collider for tests.
    struct TriangleSoup {
        triangles: Vec<[Vec3; 3]>,
    }

    /// The mesh module's closest point on a triangle, for the brute-force collider.
    fn closest_on_triangle(p: Vec3, [a, b, c]: [Vec3; 3]) -> Vec3 {
        crate::mesh::metrics::closest_point_on_triangle(p, a, b, c)
    }

    impl MeshCollider for TriangleSoup {
        fn closest(&self, p: Vec3) -> Option<(Vec3, Vec3)> {
            let mut best: Option<(f64, Vec3, Vec3)> = None;
            for t in &self.triangles {
                let q = closest_on_triangle(p, *t);
                let d = norm(sub(p, q));
                if best.is_none_or(|(bd, _, _)| d < bd) {
                    let n = normalized(cross(sub(t[1], t[0]), sub(t[2], t[0])))?;
                    best = Some((d, q, n));
                }
            }
            best.map(|(_, q, n)| (q, n))
        }
    }

    /// The axis-aligned cube [−½, ½]³ as 12 outward-wound triangles.
    fn unit_cube() -> TriangleSoup {
        let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
        let neg = |v: Vec3| scale(v, -1.0);
        // (normal, t1, t2) with t1 × t2 = normal.
        let faces = [
            (x, y, z),
            (neg(x), z, y),
            (y, z, x),
            (neg(y), x, z),
            (z, x, y),
            (neg(z), y, x),
        ];
        let mut triangles = Vec::new();
        for (n, t1, t2) in faces {
            assert_eq!(cross(t1, t2), n);
            let c = scale(n, 0.5);
            let corner = |s1: f64, s2: f64| axpy(axpy(c, s1, t1), s2, t2);
            let (p00, p10, p11, p01) = (
                corner(-0.5, -0.5),
                corner(0.5, -0.5),
                corner(0.5, 0.5),
                corner(-0.5, 0.5),
            );
            triangles.push([p00, p10, p11]);
            triangles.push([p00, p11, p01]);
        }
        TriangleSoup { triangles }
    }

    #[test]
    fn mesh_collider_stops_a_falling_particle_at_the_thickness() {
        let thickness = 0.02;
        let colliders = [Collider::Mesh(Box::new(unit_cube()))];
        let o = SimOptions {
            dt: 1.0 / 60.0,
            substeps: 4,
            integrator: Integrator::SymplecticEuler,
            margin: thickness,
            mesh_band: 0.1,
            friction: 0.5,
            ..SimOptions::default()
        };
        let mut s = ParticleSystem::new(vec![[0.13, 1.5, -0.21]], vec![1.0]);
        let mut min_y = f64::INFINITY;
        let mut contacts = 0;
        for _ in 0..120 {
            contacts += step(&mut s, &colliders, &o).unwrap().collisions;
            min_y = min_y.min(s.positions[0][1]);
        }
        let p = s.positions[0];
        println!(
            "mesh cube: particle rests at {p:?} (surface + thickness = {}), lowest y after any \
             step {min_y:.12}, speed {:.3e} m/s, {contacts} contacts",
            0.5 + thickness,
            norm(s.velocities[0])
        );
        assert!(min_y >= 0.5 + thickness - 1e-9);
        assert!((p[1] - (0.5 + thickness)).abs() < 1e-9);
        assert!((p[0] - 0.13).abs() < 1e-12 && (p[2] + 0.21).abs() < 1e-12);
        assert!(norm(s.velocities[0]) < 1e-9);

        // Inside, within the band below the top face: pushed out through the top. Deeper than
        // the band: left alone.
        let mut inside =
            ParticleSystem::new(vec![[0.1, 0.45, 0.2], [0.0, 0.0, 0.05]], vec![1.0, 1.0]);
        inside.gravity = [0.0; 3];
        step(&mut inside, &colliders, &o).unwrap();
        assert!(norm(sub(inside.positions[0], [0.1, 0.5 + thickness, 0.2])) < 1e-12);
        assert_eq!(inside.positions[1], [0.0, 0.0, 0.05]);
    }

    #[test]
    fn sphere_bounce_uses_restitution_and_plane_friction_is_coulomb() {
        // Head-on into a sphere at 2 m/s, e = 0.5, no gravity: leaves at 1 m/s, outside.
        let colliders = [Collider::Sphere {
            center: [0.0; 3],
            radius: 1.0,
        }];
        let mut s = ParticleSystem::new(vec![[1.02, 0.0, 0.0]], vec![1.0]);
        s.gravity = [0.0; 3];
        s.velocities[0] = [-2.0, 0.0, 0.0];
        let o = SimOptions {
            integrator: Integrator::SymplecticEuler,
            restitution: 0.5,
            margin: 0.01,
            ..SimOptions::default()
        };
        step(&mut s, &colliders, &o).unwrap();
        println!(
            "sphere bounce: position {:?} velocity {:?}",
            s.positions[0], s.velocities[0]
        );
        assert!((s.velocities[0][0] - 1.0).abs() < 1e-12);
        assert!(norm(s.positions[0]) >= 1.01 - 1e-9);

        // Sliding on a plane at 2 m/s with μ = 0.5: decelerates at μ g.
        let plane = [Collider::Plane {
            point: [0.0; 3],
            normal: [0.0, 2.0, 0.0],
        }];
        let mut s = ParticleSystem::new(vec![[0.0, 0.0, 0.0]], vec![1.0]);
        s.velocities[0] = [2.0, 0.0, 0.0];
        let o = SimOptions {
            dt: 0.2,
            substeps: 120,
            integrator: Integrator::SymplecticEuler,
            friction: 0.5,
            margin: 0.0,
            ..SimOptions::default()
        };
        step(&mut s, &plane, &o).unwrap();
        let expected = 2.0 - 0.5 * 9.81 * 0.2;
        println!(
            "plane friction: speed after 0.2 s {:.6} (μ g t law {expected:.6})",
            s.velocities[0][0]
        );
        assert!((s.velocities[0][0] - expected).abs() < 0.01 * expected);
        assert!(s.positions[0][1] >= -1e-12);
    }

    #[test]
    fn pinned_particles_never_move() {
        for integrator in Integrator::ALL {
            let mut cloth = cloth_grid(&ClothOptions {
                nx: 6,
                ny: 6,
                pin: ClothPin::TwoCorners,
                ..ClothOptions::default()
            })
            .unwrap();
            let mut rope_sys = rope(&RopeOptions::default()).unwrap();
            let ground = [Collider::Plane {
                point: [0.0, -5.0, 0.0],
                normal: [0.0, 1.0, 0.0],
            }];
            // Small steps so that even explicit Euler survives a while.
            let o = options(integrator, 1.0 / 600.0, 2);
            for sys in [&mut cloth, &mut rope_sys] {
                let pinned: Vec<(usize, Vec3)> = sys
                    .inverse_masses
                    .iter()
                    .enumerate()
                    .filter(|(_, w)| **w == 0.0)
                    .map(|(i, _)| (i, sys.positions[i]))
                    .collect();
                assert!(!pinned.is_empty());
                let free_before = sys.positions[sys.len() - 1];
                let mut moved = false;
                let r = simulate(sys, &ground, &o, 50, |_, s, _| {
                    for (i, p) in &pinned {
                        moved |= s.positions[*i] != *p || s.velocities[*i] != [0.0; 3];
                    }
                })
                .unwrap();
                assert!(!moved, "{integrator}: a pinned particle moved");
                assert!(
                    sys.positions[sys.len() - 1] != free_before,
                    "{integrator}: nothing moved"
                );
                let _ = r;
            }
        }
    }

    #[test]
    fn validation_reports_typed_errors() {
        let good = anchored_oscillator(1.0, 1.0, 0.1);
        good.validate().unwrap();
        let mut s = good.clone();
        s.springs[0].b = 7;
        assert!(matches!(
            s.validate(),
            Err(PhysicsError::SpringIndexOutOfRange {
                spring: 0,
                b: 7,
                ..
            })
        ));
        let mut s = good.clone();
        s.springs[0].b = 0;
        assert!(matches!(
            s.validate(),
            Err(PhysicsError::SpringSelfLoop {
                spring: 0,
                index: 0
            })
        ));
        let mut s = good.clone();
        s.springs[0].stiffness = -1.0;
        assert!(matches!(
            s.validate(),
            Err(PhysicsError::InvalidSpring {
                field: "stiffness",
                ..
            })
        ));
        let mut s = good.clone();
        s.inverse_masses[1] = -2.0;
        assert!(matches!(
            s.validate(),
            Err(PhysicsError::InvalidInverseMass { index: 1, .. })
        ));
        let mut s = good.clone();
        s.positions[1][2] = f64::NAN;
        let e = s.validate().unwrap_err();
        println!("error message: {e}");
        assert!(matches!(
            e,
            PhysicsError::NonFiniteInput {
                field: "position",
                index: 1
            }
        ));
        let mut s = good.clone();
        s.velocities.pop();
        assert!(matches!(
            s.validate(),
            Err(PhysicsError::LengthMismatch { .. })
        ));

        let mut s = good.clone();
        let bad_dt = SimOptions {
            dt: 0.0,
            ..SimOptions::default()
        };
        assert_eq!(
            step(&mut s, &[], &bad_dt),
            Err(PhysicsError::InvalidTimeStep(0.0))
        );
        let zero = SimOptions {
            substeps: 0,
            ..SimOptions::default()
        };
        assert_eq!(step(&mut s, &[], &zero), Err(PhysicsError::ZeroSubsteps));
        let e = SimOptions {
            restitution: 1.5,
            ..SimOptions::default()
        };
        assert!(matches!(
            step(&mut s, &[], &e),
            Err(PhysicsError::InvalidOption {
                name: "restitution",
                ..
            })
        ));
        let bad_plane = [Collider::Plane {
            point: [0.0; 3],
            normal: [0.0; 3],
        }];
        assert!(matches!(
            step(&mut s, &bad_plane, &SimOptions::default()),
            Err(PhysicsError::InvalidCollider { index: 0, .. })
        ));
        assert!(
            cloth_grid(&ClothOptions {
                nx: 1,
                ..ClothOptions::default()
            })
            .is_err()
        );
        assert!(
            rope(&RopeOptions {
                segments: 0,
                ..RopeOptions::default()
            })
            .is_err()
        );
        assert_eq!(s, good, "failed calls must not touch the system");

        // A step that overflows is rejected and the last finite state is kept.
        let mut s = ParticleSystem::new(vec![[1e308, 0.0, 0.0]], vec![1.0]);
        s.velocities[0] = [1e308, 0.0, 0.0];
        let before = s.clone();
        let r = step(&mut s, &[], &options(Integrator::ExplicitEuler, 1.0, 1));
        assert_eq!(
            r,
            Err(PhysicsError::NonFiniteState {
                particle: 0,
                substep: 0
            })
        );
        assert_eq!(s, before);
    }

    #[test]
    fn integrator_names_round_trip() {
        for (i, name) in Integrator::ALL.iter().zip(Integrator::NAMES) {
            assert_eq!(i.name(), name);
            assert_eq!(Integrator::from_name(name), Some(*i));
            assert_eq!(name.parse::<Integrator>(), Ok(*i));
        }
        assert_eq!(Integrator::from_name("verlet"), None);
        assert!(matches!(
            "rk5".parse::<Integrator>(),
            Err(PhysicsError::UnknownIntegrator(_))
        ));
    }

    fn network() -> impl Strategy<Value = ParticleSystem> {
        (2usize..8).prop_flat_map(|n| {
            let particles = prop::collection::vec(
                (
                    [-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64],
                    -3.0..3.0f64,
                    0u8..4,
                ),
                n,
            );
            let springs = prop::collection::vec(
                (0..n, 1..n, -2.0..4.0f64, 0.0..2.0f64, 0.5..1.5f64),
                1..3 * n,
            );
            (particles, springs).prop_map(move |(particles, springs)| {
                let positions: Vec<Vec3> = particles.iter().map(|p| p.0).collect();
                // Masses log-uniform in [1e-3, 1e3] kg; about one particle in four pinned.
                let inverse_masses = particles
                    .iter()
                    .map(|p| if p.2 == 0 { 0.0 } else { 10f64.powf(-p.1) })
                    .collect();
                let mut s = ParticleSystem::new(positions.clone(), inverse_masses);
                for (a, offset, log_k, damping, stretch) in springs {
                    let b = (a + offset) % n;
                    s.springs.push(Spring {
                        a,
                        b,
                        rest_length: stretch * norm(sub(positions[a], positions[b])),
                        stiffness: 10f64.powf(log_k), // 1e-2 .. 1e4 N/m
                        damping,
                    });
                }
                s
            })
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        #[test]
        fn implicit_euler_never_produces_nan(mut s in network()) {
            let ground = [Collider::Plane { point: [0.0, -1.5, 0.0], normal: [0.0, 1.0, 0.0] }];
            let o = SimOptions { cg_max_iterations: 50, ..SimOptions::default() };
            let mut finite = true;
            let r = simulate(&mut s, &ground, &o, 60, |_, sys, f| {
                finite &= all_finite(sys) && f.total_energy.is_finite() && f.max_speed.is_finite();
            }).unwrap();
            prop_assert!(finite);
            prop_assert!(all_finite(&s));
            match r.diverged {
                None => prop_assert_eq!(r.frames.len(), 60),
                Some(d) => prop_assert_eq!(r.frames.len(), d.frame),
            }
        }
    }
}
