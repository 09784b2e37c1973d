//! `animate.cloth`: a rectangular mass–spring cloth dropped onto the objects of a scene,
//! simulated for a number of frames, as one mesh per frame plus the energy and momentum of
//! every frame.
//!
//! The simulation is [`super::physics`]: structural, shear and bend springs (Provot 1995,
//! "Deformation constraints in a mass-spring model to describe rigid cloth behavior"),
//! integrated by the chosen [`Integrator`] — by default the linearized implicit Euler of Baraff
//! & Witkin 1998 ("Large steps in cloth simulation") — with collisions against the spheres,
//! planes and meshes of the optional `colliders` scene after every substep.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Mesh, Metrics, Pose, Scene, Shape, Value};
use ocellus_engine::{param_enum, params};

use super::physics::{
    ClothOptions, ClothPin, Collider, FrameReport, Integrator, MeshCollider, ParticleSystem,
    SimOptions, cloth_grid, grid_triangles, simulate,
};
use crate::mesh::metrics::TriangleTree;
use crate::mesh::normals::{NormalWeighting, vertex_normals};

param_enum! {
    /// Which particles of `animate.cloth` are held in place.
    pub enum Pin {
        /// None: the cloth falls freely.
        None = "none",
        /// The two corners of the first row (smallest z).
        TwoCorners = "two_corners",
        /// All four corners.
        FourCorners = "four_corners",
        /// The whole first row.
        Edge = "edge",
    }
}

param_enum! {
    /// Time integrator of `animate.cloth`.
    pub enum IntegratorName {
        /// Forward Euler (unstable for any undamped spring; for comparison).
        ExplicitEuler = "explicit_euler",
        /// Semi-implicit (symplectic) Euler: stable while h·√(k/m) < 2.
        SymplecticEuler = "symplectic_euler",
        /// Velocity Verlet: second order, symplectic, stable while h·√(k/m) < 2.
        VelocityVerlet = "velocity_verlet",
        /// Classic fourth-order Runge–Kutta.
        Rk4 = "rk4",
        /// Linearized backward Euler (Baraff & Witkin 1998), CG solve: stable at any step.
        ImplicitEuler = "implicit_euler",
    }
}

impl IntegratorName {
    fn integrator(self) -> Integrator {
        match self {
            IntegratorName::ExplicitEuler => Integrator::ExplicitEuler,
            IntegratorName::SymplecticEuler => Integrator::SymplecticEuler,
            IntegratorName::VelocityVerlet => Integrator::VelocityVerlet,
            IntegratorName::Rk4 => Integrator::Rk4,
            IntegratorName::ImplicitEuler => Integrator::ImplicitEuler,
        }
    }
}

params! {
    /// Parameters of `animate.cloth`.
    pub struct ClothParams {
        /// Particles along x (≥ 2). Default 24.
        columns: u32 = 24 => [min = 2, max = 1024],
        /// Particles along z (≥ 2). Default 24.
        rows: u32 = 24 => [min = 2, max = 1024],
        /// Extent along x and z, metres. Default (1, 1).
        size_m: [f64; 2] = [1.0, 1.0] => [min = 0.0, unit = "m"],
        /// Centre of the cloth at rest, metres; it lies in the horizontal plane y = center.y.
        /// Default (0, 1, 0).
        center: [f64; 3] = [0.0, 1.0, 0.0] => [unit = "m"],
        /// Total mass, kilograms. Default 0.5.
        mass_kg: f64 = 0.5 => [min = 0.0, unit = "kg"],
        /// Stiffness of the springs between grid neighbours, N/m. Default 1000.
        structural_stiffness: f64 = 1000.0 => [min = 0.0, unit = "N/m"],
        /// Stiffness of the diagonal (shear) springs, N/m. Default 100.
        shear_stiffness: f64 = 100.0 => [min = 0.0, unit = "N/m"],
        /// Stiffness of the springs two particles apart (bending), N/m. Default 10.
        bend_stiffness: f64 = 10.0 => [min = 0.0, unit = "N/m"],
        /// Damping along every spring, N·s/m. Default 0.01.
        spring_damping: f64 = 0.01 => [min = 0.0, unit = "N·s/m"],
        /// Total air drag of the cloth, N·s/m (split over the particles). Default 0.2.
        drag: f64 = 0.2 => [min = 0.0, unit = "N·s/m"],
        /// Gravity, m/s². Default (0, −9.81, 0).
        gravity: [f64; 3] = [0.0, -9.81, 0.0] => [unit = "m/s²"],
        /// Pinned particles: none, two_corners, four_corners or edge. Default none.
        pin: Pin = Pin::None,
        /// Integrator. Default implicit_euler.
        integrator: IntegratorName = IntegratorName::ImplicitEuler,
        /// Frames to output (frame 0 is the rest state). Default 48.
        frames: u32 = 48 => [min = 1, max = 100000],
        /// Frames per second: each frame advances 1/fps seconds. Default 24.
        fps: f64 = 24.0 => [min = 0.0, max = 10000.0, unit = "1/s"],
        /// Integration substeps per frame (collisions are resolved after each). Default 4.
        substeps: u32 = 4 => [min = 1, max = 10000],
        /// Coefficient of restitution of contacts, in [0, 1]. Default 0.
        restitution: f64 = 0.0 => [min = 0.0, max = 1.0],
        /// Coulomb friction coefficient of contacts. Default 0.3.
        friction: f64 = 0.3 => [min = 0.0],
        /// Collision margin (cloth thickness), metres. Default 0.005.
        margin_m: f64 = 0.005 => [min = 0.0, unit = "m"],
        /// How far behind a mesh or finite-plane surface a particle is still pushed out, metres.
        /// Default 0.05.
        mesh_band_m: f64 = 0.05 => [min = 0.0, unit = "m"],
        /// Relative residual at which the implicit solve's conjugate gradients stop. Default 1e-6.
        cg_tolerance: f64 = 1e-6 => [min = 0.0],
        /// Most conjugate-gradient iterations per implicit substep. Default 200.
        cg_max_iterations: u32 = 200 => [min = 1, max = 100000],
        /// The run fails as diverged when the total energy exceeds this many times its initial
        /// scale. Default 1000.
        divergence_factor: f64 = 1000.0 => [min = 1.0],
    }
}

/// Columns of the `energy` matrix.
pub const ENERGY_COLUMNS: [&str; 14] = [
    "time_s",
    "kinetic_j",
    "gravitational_j",
    "spring_j",
    "total_j",
    "momentum_x",
    "momentum_y",
    "momentum_z",
    "angular_momentum_x",
    "angular_momentum_y",
    "angular_momentum_z",
    "max_speed_m_s",
    "cg_iterations",
    "collisions",
];

/// `animate.cloth`. See the module documentation.
#[derive(Debug, Clone)]
pub struct Cloth {
    params: ClothParams,
}

impl Op for Cloth {
    type Params = ClothParams;
    const ID: &'static str = "animate.cloth";
    const SUMMARY: &'static str =
        "Simulates a mass–spring cloth falling onto a scene's objects; one mesh per frame.";
    const DOC: &'static str = r#"
A `columns × rows` grid of particles (`mass_kg` in all, `size_m` wide, lying flat at `center`)
joined by structural, shear and bend springs (Provot 1995) falls under `gravity` with air
`drag` and collides with every object of the optional `colliders` scene: spheres and infinite
planes exactly, finite planes and meshes through their triangles (closest point in a BVH,
pushed out along the face normal when closer than `margin_m` or up to `mesh_band_m` behind the
surface). Object poses and scales of the scene apply. Quadric objects are refused.

Each frame advances `1/fps` s in `substeps` equal steps of the `integrator`:
`explicit_euler`, `symplectic_euler`, `velocity_verlet`, `rk4` or `implicit_euler` (default;
the linearized backward Euler of Baraff & Witkin 1998 with a conjugate-gradient solve, stable
at any step). The explicit methods are conditionally stable: symplectic Euler and Verlet need
`h·√(k/m) < 2` for the stiffest spring. A blow-up — a non-finite state, or a total energy above
`divergence_factor` times the initial scale — fails the node with the frame, step and energy.

Outputs: `frames`, one mesh per frame (frame 0 the rest state; grid uvs, area-weighted
normals); `energy`, one row per frame with the columns time_s, kinetic_j, gravitational_j
(relative to y = 0 along −gravity), spring_j, total_j, momentum_x/y/z, angular_momentum_x/y/z
(about the origin), max_speed_m_s, cg_iterations, collisions; `metrics` with the peak and final
kinetic energy, total steps, the lowest clearance to the spheres and infinite planes, and
`frames_over_mesh_band`: frames in which the fastest particle moved farther in one substep than
`mesh_band_m + margin_m`. Contacts with meshes and finite planes are found only that far behind
the surface, so in such frames a particle may have passed through one (no continuous collision
detection): raise `substeps` (or `mesh_band_m`) until it is 0.

Example:
    "cloth": (op: "animate.cloth", inputs: { "colliders": "stage.scene" },
              params: (columns: 24, rows: 24, center: [0, 1, 0], frames: 48, fps: 24)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "colliders",
                PortType::Scene,
                "Objects the cloth collides with (spheres, planes, meshes); materials, lights and cameras are not used.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Mesh.list_of(),
                "The cloth, one mesh per frame.",
            ),
            PortSpec::new(
                "energy",
                PortType::Matrix,
                "Per-frame energy and momentum (columns in the doc).",
            ),
            PortSpec::new("metrics", PortType::Metrics, "Simulation summary."),
        ]
    }

    fn new(p: ClothParams) -> Result<Self, String> {
        if !(p.size_m.iter().all(|s| *s > 0.0 && s.is_finite())) {
            return Err(format!("`size_m` must be positive, got {:?}", p.size_m));
        }
        if !(p.mass_kg > 0.0 && p.mass_kg.is_finite()) {
            return Err(format!("`mass_kg` must be positive, got {}", p.mass_kg));
        }
        if p.fps.is_nan() || p.fps <= 0.0 {
            return Err(format!("`fps` must be positive, got {}", p.fps));
        }
        if p.cg_tolerance.is_nan() || p.cg_tolerance <= 0.0 {
            return Err("`cg_tolerance` must be positive".into());
        }
        let finite = p.center.iter().chain(&p.gravity).all(|c| c.is_finite())
            && [
                p.structural_stiffness,
                p.shear_stiffness,
                p.bend_stiffness,
                p.spring_damping,
                p.drag,
                p.friction,
                p.margin_m,
                p.mesh_band_m,
                p.divergence_factor,
            ]
            .iter()
            .all(|v| v.is_finite());
        if !finite {
            return Err("cloth parameters must be finite".into());
        }
        Ok(Cloth { params: p })
    }
}

/// A triangle mesh collider: the closest point in a BVH and that triangle's unit normal.
struct TriangleCollider {
    tree: TriangleTree,
    normals: Vec<[f64; 3]>,
}

impl MeshCollider for TriangleCollider {
    fn closest(&self, p: [f64; 3]) -> Option<([f64; 3], [f64; 3])> {
        let hit = self.tree.closest(p)?;
        let normal = *self.normals.get(hit.triangle as usize)?;
        Some((hit.point, normal))
    }
}

fn triangle_collider(positions: Vec<[f64; 3]>, triangles: Vec<[u32; 3]>) -> Option<Collider> {
    let mut normals = Vec::with_capacity(triangles.len());
    let mut kept = Vec::with_capacity(triangles.len());
    for t in &triangles {
        let [a, b, c] = t.map(|i| positions.get(i as usize).copied());
        let (Some(a), Some(b), Some(c)) = (a, b, c) else {
            return None;
        };
        let n = cross(sub(b, a), sub(c, a));
        let len = dot(n, n).sqrt();
        // Degenerate triangles have no side to push out to.
        if len > 0.0 && len.is_finite() {
            normals.push(n.map(|x| x / len));
            kept.push(*t);
        }
    }
    if kept.is_empty() {
        return None;
    }
    Some(Collider::Mesh(Box::new(TriangleCollider {
        tree: TriangleTree::new(positions, kept),
        normals,
    })))
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn apply(pose: &Pose, scale: f64, p: [f64; 3]) -> [f64; 3] {
    let r = pose.rotation_matrix();
    let s = p.map(|c| c * scale);
    [0, 1, 2]
        .map(|i| r[3 * i] * s[0] + r[3 * i + 1] * s[1] + r[3 * i + 2] * s[2] + pose.translation[i])
}

fn rotate(pose: &Pose, v: [f64; 3]) -> [f64; 3] {
    let r = pose.rotation_matrix();
    [0, 1, 2].map(|i| r[3 * i] * v[0] + r[3 * i + 1] * v[1] + r[3 * i + 2] * v[2])
}

/// The scene's objects as colliders, in world coordinates.
pub fn scene_colliders(scene: &Scene) -> Result<Vec<Collider>, String> {
    let mut out = Vec::new();
    for object in &scene.objects {
        let (pose, scale) = (&object.world_from_object, object.scale);
        match &object.shape {
            Shape::Sphere { center, radius } => out.push(Collider::Sphere {
                center: apply(pose, scale, *center),
                radius: radius * scale,
            }),
            Shape::Plane {
                point,
                normal,
                half_extent,
            } => {
                let point = apply(pose, scale, *point);
                let normal = rotate(pose, *normal);
                if half_extent.is_infinite() {
                    out.push(Collider::Plane { point, normal });
                } else {
                    // A finite square: two triangles, front side along the normal.
                    let len = dot(normal, normal).sqrt();
                    if !(len > 0.0 && len.is_finite()) {
                        return Err(format!("object `{}`: plane normal is zero", object.name));
                    }
                    let n = normal.map(|c| c / len);
                    let helper = if n[0].abs() < 0.9 {
                        [1.0, 0.0, 0.0]
                    } else {
                        [0.0, 1.0, 0.0]
                    };
                    let u = cross(n, helper);
                    let ul = dot(u, u).sqrt();
                    let u = u.map(|c| c / ul);
                    let v = cross(n, u);
                    let h = half_extent * scale;
                    let corner = |su: f64, sv: f64| {
                        [0, 1, 2].map(|k| point[k] + h * (su * u[k] + sv * v[k]))
                    };
                    let positions = vec![
                        corner(-1.0, -1.0),
                        corner(1.0, -1.0),
                        corner(1.0, 1.0),
                        corner(-1.0, 1.0),
                    ];
                    // (u, v, n) is right-handed, so counter-clockwise in (u, v) faces +n.
                    let collider = triangle_collider(positions, vec![[0, 1, 2], [0, 2, 3]])
                        .ok_or_else(|| format!("object `{}`: degenerate plane", object.name))?;
                    out.push(collider);
                }
            }
            Shape::Mesh(mesh) => {
                let positions: Vec<[f64; 3]> = mesh
                    .positions
                    .iter()
                    .map(|p| apply(pose, scale, p.map(f64::from)))
                    .collect();
                if mesh
                    .triangles
                    .iter()
                    .flatten()
                    .any(|&i| i as usize >= positions.len())
                {
                    return Err(format!(
                        "object `{}`: a triangle indexes past the vertices",
                        object.name
                    ));
                }
                if let Some(c) = triangle_collider(positions, mesh.triangles.clone()) {
                    out.push(c);
                }
            }
            Shape::Quadric { .. } => {
                return Err(format!(
                    "object `{}` is a quadric; cloth collides with spheres, planes and meshes only",
                    object.name
                ));
            }
        }
    }
    Ok(out)
}

/// The cloth's state as a mesh: grid uvs, area-weighted normals.
fn cloth_mesh(
    system: &ParticleSystem,
    triangles: &[[u32; 3]],
    columns: usize,
    rows: usize,
) -> Mesh {
    let (normals, _) = vertex_normals(&system.positions, triangles, NormalWeighting::Area);
    let uvs = (0..rows)
        .flat_map(|j| {
            (0..columns).map(move |i| {
                [
                    i as f32 / (columns - 1).max(1) as f32,
                    j as f32 / (rows - 1).max(1) as f32,
                ]
            })
        })
        .collect();
    Mesh {
        positions: system
            .positions
            .iter()
            .map(|p| p.map(|c| c as f32))
            .collect(),
        triangles: triangles.to_vec(),
        normals: Some(normals.iter().map(|n| n.map(|c| c as f32)).collect()),
        uvs: Some(uvs),
        colors: None,
        tangents: None,
    }
}

fn energy_row(time: f64, r: &FrameReport) -> [f64; 14] {
    [
        time,
        r.kinetic_energy,
        r.gravitational_energy,
        r.spring_energy,
        r.total_energy,
        r.linear_momentum[0],
        r.linear_momentum[1],
        r.linear_momentum[2],
        r.angular_momentum[0],
        r.angular_momentum[1],
        r.angular_momentum[2],
        r.max_speed,
        r.cg_iterations as f64,
        r.collisions as f64,
    ]
}

/// Smallest signed clearance of any particle to the spheres and infinite planes (metres; the
/// margin included), or +∞ without such colliders.
fn clearance(system: &ParticleSystem, colliders: &[Collider]) -> f64 {
    let mut lowest = f64::INFINITY;
    for p in &system.positions {
        for c in colliders {
            let d = match c {
                Collider::Sphere { center, radius } => {
                    dot(sub(*p, *center), sub(*p, *center)).sqrt() - radius
                }
                Collider::Plane { point, normal } => {
                    let len = dot(*normal, *normal).sqrt();
                    dot(sub(*p, *point), *normal) / len
                }
                Collider::Mesh(_) => continue,
            };
            lowest = lowest.min(d);
        }
    }
    lowest
}

impl Operator for Cloth {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let p = &self.params;
        let colliders = match inputs.get("colliders") {
            Some(Value::Scene(scene)) => {
                scene_colliders(scene).map_err(|e| OpError::input("colliders", e))?
            }
            Some(other) => {
                return Err(OpError::input(
                    "colliders",
                    format!("expected Scene, got {}", other.port_type()),
                ));
            }
            None => Vec::new(),
        };
        let (columns, rows) = (p.columns as usize, p.rows as usize);
        let options = ClothOptions {
            nx: columns,
            ny: rows,
            center: p.center,
            size: p.size_m,
            total_mass: p.mass_kg,
            structural_stiffness: p.structural_stiffness,
            shear_stiffness: p.shear_stiffness,
            bend_stiffness: p.bend_stiffness,
            damping: p.spring_damping,
            drag: p.drag,
            gravity: p.gravity,
            pin: match p.pin {
                Pin::None => ClothPin::None,
                Pin::TwoCorners => ClothPin::TwoCorners,
                Pin::FourCorners => ClothPin::FourCorners,
                Pin::Edge => ClothPin::Edge,
            },
        };
        let mut system = cloth_grid(&options).map_err(|e| OpError::failed(e.to_string()))?;
        let sim = SimOptions {
            dt: 1.0 / p.fps,
            substeps: p.substeps as usize,
            integrator: p.integrator.integrator(),
            restitution: p.restitution,
            friction: p.friction,
            margin: p.margin_m,
            mesh_band: p.mesh_band_m,
            cg_tolerance: p.cg_tolerance,
            cg_max_iterations: p.cg_max_iterations as usize,
            divergence_factor: p.divergence_factor,
        };
        let triangles = grid_triangles(columns, rows);
        let frames = p.frames as usize;
        let mut meshes = Vec::with_capacity(frames);
        let mut energy = Vec::with_capacity(frames * ENERGY_COLUMNS.len());
        meshes.push(Value::Mesh(Arc::new(cloth_mesh(
            &system, &triangles, columns, rows,
        ))));
        energy.extend(energy_row(0.0, &system.measure()));
        let mut lowest = clearance(&system, &colliders);
        // Mesh (and finite-plane) contacts are found within `mesh_band_m` behind the surface:
        // a particle that travels farther than that in one substep can pass through.
        let has_mesh = colliders.iter().any(|c| matches!(c, Collider::Mesh(_)));
        let substep_s = 1.0 / (p.fps * f64::from(p.substeps));
        let mut frames_over_band = 0usize;
        let report = simulate(
            &mut system,
            &colliders,
            &sim,
            frames - 1,
            |frame, state, r| {
                meshes.push(Value::Mesh(Arc::new(cloth_mesh(
                    state, &triangles, columns, rows,
                ))));
                energy.extend(energy_row((frame + 1) as f64 / p.fps, r));
                lowest = lowest.min(clearance(state, &colliders));
                if has_mesh && r.max_speed * substep_s > p.mesh_band_m + p.margin_m {
                    frames_over_band += 1;
                }
            },
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        if let Some(d) = &report.diverged {
            return Err(OpError::failed(format!(
                "the {} simulation diverged at frame {} (step {}): energy {:.4e} J exceeds {:.4e} J ({:?}); use implicit_euler, more substeps or softer springs",
                p.integrator.name(),
                d.frame + 1,
                d.step,
                d.energy,
                d.threshold,
                d.reason
            )));
        }
        let kinetic: Vec<f64> = energy
            .chunks_exact(ENERGY_COLUMNS.len())
            .map(|row| row[1])
            .collect();
        let mut metrics = Metrics::new();
        metrics.insert("frames".into(), frames as f64);
        metrics.insert("steps".into(), report.steps as f64);
        metrics.insert("particles".into(), system.len() as f64);
        metrics.insert("springs".into(), system.springs.len() as f64);
        metrics.insert("colliders".into(), colliders.len() as f64);
        metrics.insert(
            "peak_kinetic_energy_j".into(),
            kinetic.iter().copied().fold(0.0, f64::max),
        );
        metrics.insert(
            "final_kinetic_energy_j".into(),
            kinetic.last().copied().unwrap_or(0.0),
        );
        if lowest.is_finite() {
            metrics.insert("min_clearance_m".into(), lowest);
        }
        metrics.insert("frames_over_mesh_band".into(), frames_over_band as f64);
        let energy = Matrix::new(frames, ENERGY_COLUMNS.len(), energy)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("frames", Value::list(PortType::Mesh, meshes))
            .with("energy", Value::Matrix(Arc::new(energy)))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use ocellus_engine::op::Op;
    use ocellus_engine::value::{SceneObject, Shape};

    use super::*;

    fn ctx() -> RunContext {
        RunContext {
            node: "cloth".into(),
            threads: 1,
            element: None,
        }
    }

    fn object(shape: Shape, translation: [f64; 3], scale: f64) -> SceneObject {
        SceneObject {
            name: "o".into(),
            shape,
            world_from_object: Pose {
                rotation: [1.0, 0.0, 0.0, 0.0],
                translation,
            },
            scale,
            material: 0,
        }
    }

    fn run(params: ClothParams, scene: Option<Scene>) -> Result<Outputs, OpError> {
        let op = Cloth::new(params).map_err(OpError::failed)?;
        let specs = Cloth::inputs();
        let values = [scene.map(|s| Value::Scene(Arc::new(s)))];
        op.run(&ctx(), &Inputs::new(&specs, &values))
    }

    #[test]
    fn colliders_come_from_the_scene_with_poses_and_scales() {
        // A unit sphere scaled by 0.3 and moved to (0.2, 0.35, 0); a finite floor at y = 0.
        let scene = Scene {
            objects: vec![
                object(
                    Shape::Sphere {
                        center: [0.0, 0.0, 0.0],
                        radius: 1.0,
                    },
                    [0.2, 0.35, 0.0],
                    0.3,
                ),
                object(
                    Shape::Plane {
                        point: [0.0, 0.0, 0.0],
                        normal: [0.0, 1.0, 0.0],
                        half_extent: 2.0,
                    },
                    [0.0, 0.0, 0.0],
                    1.0,
                ),
            ],
            ..Scene::default()
        };
        let colliders = scene_colliders(&scene).unwrap();
        assert!(matches!(colliders[0], Collider::Sphere { center, radius }
            if center == [0.2, 0.35, 0.0] && (radius - 0.3).abs() < 1e-15));
        assert!(matches!(colliders[1], Collider::Mesh(_)));
        let params = ClothParams {
            columns: 16,
            rows: 16,
            center: [0.2, 0.9, 0.0],
            frames: 36,
            fps: 24.0,
            margin_m: 0.01,
            ..ClothParams::default()
        };
        let out = run(params, Some(scene)).unwrap();
        let Some(Value::List(frames)) = out.get("frames") else {
            panic!()
        };
        assert_eq!(frames.items.len(), 36);
        for frame in &frames.items {
            let Value::Mesh(m) = frame else { panic!() };
            for p in &m.positions {
                let d = [p[0] as f64 - 0.2, p[1] as f64 - 0.35, p[2] as f64];
                let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!(r >= 0.3 + 0.01 - 1e-5, "inside the ball: {p:?} at {r}");
                assert!(p[1] >= 0.01 - 1e-4, "below the floor: {p:?}");
            }
        }
        // It has draped: the lowest particle is below the ball's centre.
        let Value::Mesh(last) = &frames.items[35] else {
            panic!()
        };
        let lowest = last.positions.iter().map(|p| p[1]).fold(f32::MAX, f32::min);
        assert!(lowest < 0.35, "{lowest}");
        let Some(Value::Matrix(energy)) = out.get("energy") else {
            panic!()
        };
        assert_eq!((energy.rows, energy.cols), (36, ENERGY_COLUMNS.len()));
        assert_eq!(energy.get(0, 1), Some(0.0)); // at rest at frame 0
        assert!((energy.get(35, 0).unwrap() - 35.0 / 24.0).abs() < 1e-12);
    }

    #[test]
    fn quadrics_are_refused_and_divergence_fails_the_node() {
        let scene = Scene {
            objects: vec![object(
                Shape::Quadric {
                    coefficients: [1.0; 10],
                    min: [-1.0; 3],
                    max: [1.0; 3],
                },
                [0.0; 3],
                1.0,
            )],
            ..Scene::default()
        };
        let e = run(ClothParams::default(), Some(scene))
            .unwrap_err()
            .to_string();
        assert!(e.contains("quadric"), "{e}");
        // Explicit Euler on a cloth that hits a ball: every spring mode grows by
        // √(1 + h²ω²) per step, so it blows up, and the node says where.
        let ball = Scene {
            objects: vec![object(
                Shape::Sphere {
                    center: [0.0, 0.35, 0.0],
                    radius: 0.3,
                },
                [0.0; 3],
                1.0,
            )],
            ..Scene::default()
        };
        let failed = run(
            ClothParams {
                integrator: IntegratorName::ExplicitEuler,
                frames: 48,
                ..ClothParams::default()
            },
            Some(ball.clone()),
        );
        let Err(e) = failed else {
            panic!("explicit Euler did not diverge")
        };
        let e = e.to_string();
        assert!(
            e.contains("explicit_euler simulation diverged at frame"),
            "{e}"
        );
        // Implicit Euler takes the same steps and stays stable.
        assert!(
            run(
                ClothParams {
                    frames: 48,
                    ..ClothParams::default()
                },
                Some(ball)
            )
            .is_ok()
        );
    }

    #[test]
    fn a_free_cloth_falls_as_gravity_says() {
        // No colliders, no drag, no pins: the centre of mass falls g t²/2 (implicit Euler,
        // fine steps: to 1 %), the cloth keeps its shape.
        let out = run(
            ClothParams {
                columns: 4,
                rows: 4,
                drag: 0.0,
                frames: 25,
                fps: 24.0,
                substeps: 20,
                ..ClothParams::default()
            },
            None,
        )
        .unwrap();
        let Some(Value::List(frames)) = out.get("frames") else {
            panic!()
        };
        let Value::Mesh(last) = &frames.items[24] else {
            panic!()
        };
        let mean_y: f64 = last.positions.iter().map(|p| f64::from(p[1])).sum::<f64>() / 16.0;
        let expected = 1.0 - 0.5 * 9.81 * 1.0;
        assert!(
            (mean_y - expected).abs() < 0.01 * 4.9,
            "{mean_y} vs {expected}"
        );
    }
}
