//! `animate.skin` and `animate.ik`: a chain of bones along an axis — an arm, a tail, a
//! twisting bar — posed by per-bone rotations (given, keyframed by the timeline, or solved by
//! inverse kinematics) and a mesh skinned to it.
//!
//! The skeleton is [`Skeleton::chain`]: joint 0 at `root`, joint k + 1 `bone_lengths[k]` further
//! along `axis`, bone k driven by joint k. Skin weights come from each vertex's position along
//! the axis: bone k's weight is 1 inside it and ramps (smoothstep) across a band of
//! `blend_width` centred on each interior joint, so the weights are a partition of unity.

use std::sync::Arc;

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Mesh, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::ik::{IkMethod, IkOptions, JointLimit, solve_ik};
use super::skeleton::Skeleton;
use super::skinning::{
    SkinWeights, signed_volume, skin_dual_quaternion, skin_linear_blend, skin_rigid,
};
use crate::mesh::halfedge::{mesh_input, mesh_positions};

param_enum! {
    /// Skinning method of `animate.skin`.
    pub enum SkinMethod {
        /// Each vertex follows its most-weighted bone.
        Rigid = "rigid",
        /// Linear blend skinning (Magnenat-Thalmann et al. 1988).
        LinearBlend = "linear_blend",
        /// Dual quaternion skinning (Kavan et al. 2008).
        DualQuaternion = "dual_quaternion",
    }
}

param_enum! {
    /// Solver of `animate.ik`.
    pub enum IkSolver {
        /// Cyclic coordinate descent (Wang & Chen 1991).
        Ccd = "ccd",
        /// Damped least squares on the positional Jacobian (Wampler 1986; Buss 2004).
        DampedLeastSquares = "damped_least_squares",
    }
}

params! {
    /// Parameters of `animate.skin`.
    pub struct SkinParams {
        /// Position of the first joint, scene units. Default (0, 0, 0).
        root: [f64; 3] = [0.0, 0.0, 0.0] => [unit = "scene units"],
        /// Direction of the chain at rest (non-zero). Default +x.
        axis: [f64; 3] = [1.0, 0.0, 0.0],
        /// Bone lengths from the root, scene units (at least one). Default (1, 1).
        bone_lengths: Vec<f64> = vec![1.0, 1.0] => [min = 0.0, unit = "scene units"],
        /// Width of the weight ramp across each interior joint, scene units (0: a hard split).
        /// Default 0.5.
        blend_width: f64 = 0.5 => [min = 0.0, unit = "scene units"],
        /// Per-bone rotation vectors (axis × angle) in degrees, 3 numbers per bone, each in its
        /// parent bone's frame; empty or missing bones stay at rest. The `rotations` input,
        /// when connected, replaces this. Default empty.
        rotations_deg: Vec<f64> = Vec::new() => [unit = "degrees"],
        /// Skinning method: rigid, linear_blend or dual_quaternion. Default dual_quaternion.
        method: SkinMethod = SkinMethod::DualQuaternion,
    }
}

params! {
    /// Parameters of `animate.ik`.
    pub struct IkParams {
        /// Position of the first joint, scene units. Default (0, 0, 0).
        root: [f64; 3] = [0.0, 0.0, 0.0] => [unit = "scene units"],
        /// Direction of the chain at rest (non-zero). Default +x.
        axis: [f64; 3] = [1.0, 0.0, 0.0],
        /// Bone lengths from the root, scene units (at least one). Default (1, 1).
        bone_lengths: Vec<f64> = vec![1.0, 1.0] => [min = 0.0, unit = "scene units"],
        /// Where the tip of the last bone should go, scene units. Default (1, 1, 0).
        target: [f64; 3] = [1.0, 1.0, 0.0] => [unit = "scene units"],
        /// Solver: ccd or damped_least_squares. Default damped_least_squares.
        solver: IkSolver = IkSolver::DampedLeastSquares,
        /// Distance to the target that counts as reached, scene units. Default 1e-5.
        tolerance: f64 = 1e-5 => [min = 0.0, unit = "scene units"],
        /// Most iterations (CCD sweeps). Default 200.
        max_iterations: u32 = 200 => [min = 1, max = 1000000],
        /// Damping of the least-squares step, relative to the chain's reach. Default 0.05.
        damping: f64 = 0.05 => [min = 0.0],
        /// Largest swing of every bone away from its rest direction, degrees; none: free.
        /// Default none.
        cone_deg: Option<f64> = None => [min = 0.0, max = 180.0, unit = "degrees"],
        /// Make every joint a hinge about this axis (joint frame) instead. Default none.
        hinge_axis: Option<[f64; 3]> = None,
        /// Hinge angle range, degrees, when `hinge_axis` is set. Default (−150, 150).
        hinge_range_deg: [f64; 2] = [-150.0, 150.0] => [min = -180.0, max = 180.0, unit = "degrees"],
    }
}

/// The chain skeleton of `bone_lengths` along `axis` (joint 0 at the origin; the caller
/// offsets by the root).
fn chain_skeleton(bone_lengths: &[f64], axis: [f64; 3]) -> Result<Skeleton, String> {
    if bone_lengths.is_empty() {
        return Err("`bone_lengths` needs at least one bone".into());
    }
    Skeleton::chain(bone_lengths, Vector3::from(axis)).map_err(|e| e.to_string())
}

fn unit_axis(axis: [f64; 3]) -> Result<Vector3<f64>, String> {
    let a = Vector3::from(axis);
    let n = a.norm();
    if n > 0.0 && n.is_finite() {
        Ok(a / n)
    } else {
        Err("`axis` must be a finite non-zero vector".into())
    }
}

fn smoothstep(x: f64) -> f64 {
    let t = x.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Weights of each vertex on the bones of the chain (joint k drives bone k; the tip joint gets
/// none): bone k covers `[s_k, s_{k+1}]` along the axis, with smoothstep ramps of
/// `blend_width` centred on the interior joints.
pub fn chain_weights(
    positions_from_root: &[[f64; 3]],
    axis: Vector3<f64>,
    bone_lengths: &[f64],
    blend_width: f64,
) -> Result<SkinWeights, String> {
    let bones = bone_lengths.len();
    let mut joint_at = Vec::with_capacity(bones);
    let mut s = 0.0;
    for l in bone_lengths {
        joint_at.push(s);
        s += l;
    }
    // Fraction of the vertex past joint k (k ≥ 1): 0 before the ramp, 1 after it.
    let past = |k: usize, along: f64| -> f64 {
        if k == 0 {
            1.0
        } else if k >= bones {
            0.0
        } else if blend_width > 0.0 {
            smoothstep((along - joint_at[k]) / blend_width + 0.5)
        } else if along >= joint_at[k] {
            1.0
        } else {
            0.0
        }
    };
    let per_vertex = positions_from_root
        .iter()
        .map(|p| {
            let along = Vector3::from(*p).dot(&axis);
            let mut w: Vec<(usize, f64)> = (0..bones)
                .map(|k| (k, past(k, along) - past(k + 1, along)))
                .filter(|(_, w)| *w > 0.0)
                .collect();
            if w.is_empty() {
                // Rounding at a hard split: the vertex goes to the bone it is in.
                let k = joint_at.iter().rposition(|&j| along >= j).unwrap_or(0);
                w.push((k, 1.0));
            }
            w
        })
        .collect();
    SkinWeights::new(per_vertex, bones + 1).map_err(|e| e.to_string())
}

/// Local joint rotations (all joints, the tip at rest) from rotation vectors in degrees, 3 per
/// bone; missing bones stay at rest.
fn rotations_from_degrees(
    rotations_deg: &[f64],
    bones: usize,
) -> Result<Vec<UnitQuaternion<f64>>, String> {
    if !rotations_deg.len().is_multiple_of(3) {
        return Err(format!(
            "rotations hold {} numbers; they come in threes (a rotation vector per bone)",
            rotations_deg.len()
        ));
    }
    if rotations_deg.len() / 3 > bones {
        return Err(format!(
            "{} rotations for a chain of {bones} bones",
            rotations_deg.len() / 3
        ));
    }
    if !rotations_deg.iter().all(|r| r.is_finite()) {
        return Err("rotations must be finite".into());
    }
    let mut out = vec![UnitQuaternion::identity(); bones + 1];
    for (k, r) in rotations_deg.chunks_exact(3).enumerate() {
        out[k] =
            UnitQuaternion::from_scaled_axis(Vector3::new(r[0], r[1], r[2]).map(f64::to_radians));
    }
    Ok(out)
}

/// `animate.skin`. See the module documentation.
#[derive(Debug, Clone)]
pub struct Skin {
    params: SkinParams,
}

impl Op for Skin {
    type Params = SkinParams;
    const ID: &'static str = "animate.skin";
    const SUMMARY: &'static str =
        "Skins a mesh to a posed chain of bones (rigid, linear blend or dual quaternion).";
    const DOC: &'static str = r#"
Binds `mesh` to a chain of bones at rest — joint 0 at `root`, joint k + 1 `bone_lengths[k]`
further along `axis` — with weights from each vertex's position along the axis (bone k's weight
ramps by smoothstep across a band of `blend_width` centred on each interior joint), poses the
chain with per-bone rotations (`rotations_deg`, 3 numbers per bone, each bone's rotation vector
in its parent's frame; or the `rotations` input, e.g. from `animate.ik`) and deforms the mesh:

- `rigid`: each vertex follows its most-weighted bone;
- `linear_blend`: blended bone matrices (Magnenat-Thalmann, Laperrière & Thalmann 1988), which
  collapse under twist ("candy wrapper") and lose volume at bends;
- `dual_quaternion`: blended unit dual quaternions (Kavan, Collins, Žára & O'Sullivan 2008),
  which keep volume.

Normals are skinned too when the mesh has them. Metrics: `volume`, `rest_volume` and
`volume_ratio` (enclosed signed volume by the divergence theorem; meaningful for closed meshes),
`bones`, `vertices`.

Example (a 180° twist of the second bone):
    "twist": (op: "animate.skin", inputs: { "mesh": "bar.mesh" },
              params: (bone_lengths: [1, 1], rotations_deg: [0, 0, 0, 180, 0, 0],
                       method: "dual_quaternion")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The mesh at rest (bind pose)."),
            PortSpec::new(
                "rotations",
                PortType::Matrix,
                "Per-bone rotation vectors, degrees: one row of 3 per bone (replaces `rotations_deg`).",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The skinned mesh."),
            PortSpec::new("metrics", PortType::Metrics, "Volumes and counts."),
        ]
    }

    fn new(p: SkinParams) -> Result<Self, String> {
        chain_skeleton(&p.bone_lengths, p.axis)?;
        unit_axis(p.axis)?;
        rotations_from_degrees(&p.rotations_deg, p.bone_lengths.len())?;
        if !p.root.iter().all(|c| c.is_finite()) || !p.blend_width.is_finite() {
            return Err("`root` and `blend_width` must be finite".into());
        }
        Ok(Skin { params: p })
    }
}

impl Operator for Skin {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let p = &self.params;
        let mesh = mesh_input(inputs, "mesh")?;
        let rest = mesh_positions(mesh).map_err(|e| OpError::input("mesh", e.to_string()))?;
        let bones = p.bone_lengths.len();
        let rotations = match inputs.get("rotations") {
            Some(Value::Matrix(m)) => {
                if m.cols != 3 {
                    return Err(OpError::input(
                        "rotations",
                        format!("expected one row of 3 per bone, got {} columns", m.cols),
                    ));
                }
                rotations_from_degrees(&m.data, bones)
                    .map_err(|e| OpError::input("rotations", e))?
            }
            Some(other) => {
                return Err(OpError::input(
                    "rotations",
                    format!("expected Matrix, got {}", other.port_type()),
                ));
            }
            None => rotations_from_degrees(&p.rotations_deg, bones).map_err(OpError::failed)?,
        };
        let skeleton = chain_skeleton(&p.bone_lengths, p.axis).map_err(OpError::failed)?;
        let axis = unit_axis(p.axis).map_err(OpError::failed)?;
        let from_root: Vec<[f64; 3]> = rest
            .iter()
            .map(|q| [q[0] - p.root[0], q[1] - p.root[1], q[2] - p.root[2]])
            .collect();
        let weights = chain_weights(&from_root, axis, &p.bone_lengths, p.blend_width)
            .map_err(OpError::failed)?;
        let pose = skeleton
            .pose_from_local_rotations(&rotations)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let world = skeleton
            .world_from_joint(&pose)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let transforms = skeleton
            .skinning_transforms(&world)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let normals: Option<Vec<[f64; 3]>> = mesh
            .normals
            .as_ref()
            .map(|n| n.iter().map(|v| v.map(f64::from)).collect());
        let skin = match p.method {
            SkinMethod::Rigid => skin_rigid,
            SkinMethod::LinearBlend => skin_linear_blend,
            SkinMethod::DualQuaternion => skin_dual_quaternion,
        };
        let skinned = skin(&from_root, normals.as_deref(), &weights, &transforms)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let positions: Vec<[f64; 3]> = skinned
            .positions
            .iter()
            .map(|q| [q[0] + p.root[0], q[1] + p.root[1], q[2] + p.root[2]])
            .collect();
        let rest_volume =
            signed_volume(&rest, &mesh.triangles).map_err(|e| OpError::failed(e.to_string()))?;
        let volume = signed_volume(&positions, &mesh.triangles)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let out = Mesh {
            positions: positions.iter().map(|q| q.map(|c| c as f32)).collect(),
            normals: skinned
                .normals
                .map(|n| n.iter().map(|v| v.map(|c| c as f32)).collect()),
            tangents: None,
            ..(**mesh).clone()
        };
        let mut metrics = Metrics::new();
        metrics.insert("bones".into(), bones as f64);
        metrics.insert("vertices".into(), rest.len() as f64);
        metrics.insert("rest_volume".into(), rest_volume);
        metrics.insert("volume".into(), volume);
        if rest_volume != 0.0 {
            metrics.insert("volume_ratio".into(), volume / rest_volume);
        }
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(out)))
            .with("metrics", Value::metrics(metrics)))
    }
}

/// `animate.ik`. See the module documentation.
#[derive(Debug, Clone)]
pub struct Ik {
    params: IkParams,
}

impl Op for Ik {
    type Params = IkParams;
    const ID: &'static str = "animate.ik";
    const SUMMARY: &'static str =
        "Inverse kinematics of a bone chain: the rotations that put its tip on a target.";
    const DOC: &'static str = r#"
Solves for the per-bone rotations of the chain (joint 0 at `root`, bones `bone_lengths` along
`axis` at rest) that bring the tip of the last bone to `target`, by cyclic coordinate descent
(`ccd`; Wang & Chen 1991) or damped least squares on the positional Jacobian
(`damped_least_squares`; Wampler 1986, Nakamura & Hanafusa 1986, Buss 2004), starting from
rest, within joint limits: every bone's swing within `cone_deg` of its rest direction, or every
joint a hinge about `hinge_axis` within `hinge_range_deg`.

A target farther than the chain's reach (or closer than its shortest reach) is reported
unreachable, and the chain then points at it as far as the limits allow; limits can also make a
target within reach unreachable (`reached` 0).

Outputs: `rotations`, one row per bone with its rotation vector in degrees (in its parent's
frame; `animate.skin`'s `rotations` input); `joints`, the posed joint positions (one row of x, y,
z per joint, root first, tip last); `metrics` with `error` (final distance), `reached`,
`reachable`, `iterations`.

Example:
    "arm": (op: "animate.ik", params: (bone_lengths: [1, 0.8, 0.5], target: [1.2, 1.0, 0.3])),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "rotations",
                PortType::Matrix,
                "Per-bone rotation vectors, degrees (bones × 3).",
            ),
            PortSpec::new(
                "joints",
                PortType::Matrix,
                "Posed joint positions (joints × 3).",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "error, reached, reachable, iterations.",
            ),
        ]
    }

    fn new(p: IkParams) -> Result<Self, String> {
        chain_skeleton(&p.bone_lengths, p.axis)?;
        unit_axis(p.axis)?;
        if !p.root.iter().chain(&p.target).all(|c| c.is_finite()) {
            return Err("`root` and `target` must be finite".into());
        }
        if p.cone_deg.is_some() && p.hinge_axis.is_some() {
            return Err("set `cone_deg` or `hinge_axis`, not both".into());
        }
        if let Some(h) = p.hinge_axis {
            unit_axis(h)
                .map_err(|_| "`hinge_axis` must be a finite non-zero vector".to_string())?;
            if p.hinge_range_deg[0] > p.hinge_range_deg[1] {
                return Err(format!(
                    "`hinge_range_deg` must be (min, max) with min ≤ max, got {:?}",
                    p.hinge_range_deg
                ));
            }
        }
        Ok(Ik { params: p })
    }
}

impl Operator for Ik {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let p = &self.params;
        let bones = p.bone_lengths.len();
        let skeleton = chain_skeleton(&p.bone_lengths, p.axis).map_err(OpError::failed)?;
        let axis = unit_axis(p.axis).map_err(OpError::failed)?;
        let limit = match (p.cone_deg, p.hinge_axis) {
            (Some(c), _) => JointLimit::Cone {
                max_rad: c.to_radians(),
            },
            (None, Some(h)) => JointLimit::Hinge {
                axis: Vector3::from(h),
                min_rad: p.hinge_range_deg[0].to_radians(),
                max_rad: p.hinge_range_deg[1].to_radians(),
            },
            (None, None) => JointLimit::Free,
        };
        let chain: Vec<usize> = (0..bones).collect();
        let end_offset = axis * p.bone_lengths[bones - 1];
        let target = Point3::from(Vector3::from(p.target) - Vector3::from(p.root));
        let options = IkOptions {
            max_iterations: p.max_iterations as usize,
            tolerance: p.tolerance,
            damping: p.damping,
            method: match p.solver {
                IkSolver::Ccd => IkMethod::Ccd,
                IkSolver::DampedLeastSquares => IkMethod::DampedLeastSquares,
            },
        };
        let start = vec![UnitQuaternion::identity(); skeleton.len()];
        let report = solve_ik(
            &skeleton,
            &start,
            &chain,
            end_offset,
            target,
            &vec![limit; bones],
            &options,
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        let rotations: Vec<f64> = report
            .local_rotations
            .iter()
            .take(bones)
            .flat_map(|q| {
                let v = q.scaled_axis();
                [v.x.to_degrees(), v.y.to_degrees(), v.z.to_degrees()]
            })
            .collect();
        let pose = skeleton
            .pose_from_local_rotations(&report.local_rotations)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let world: Vec<Isometry3<f64>> = skeleton
            .world_from_joint(&pose)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let joints: Vec<f64> = world
            .iter()
            .flat_map(|w| {
                let t = w.translation.vector + Vector3::from(p.root);
                [t.x, t.y, t.z]
            })
            .collect();
        let mut metrics = Metrics::new();
        metrics.insert("error".into(), report.error);
        metrics.insert("reached".into(), f64::from(u8::from(report.reached)));
        metrics.insert("reachable".into(), f64::from(u8::from(report.reachable)));
        metrics.insert("iterations".into(), report.iterations as f64);
        let matrix = |rows: usize, data: Vec<f64>| {
            Matrix::new(rows, 3, data)
                .map(|m| Value::Matrix(Arc::new(m)))
                .map_err(|e| OpError::failed(e.to_string()))
        };
        Ok(Outputs::new()
            .with("rotations", matrix(bones, rotations)?)
            .with("joints", matrix(skeleton.len(), joints)?)
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use ocellus_engine::op::Op;

    use super::super::skinning::capped_cylinder;
    use super::*;

    fn ctx() -> RunContext {
        RunContext {
            node: "test".into(),
            threads: 1,
            element: None,
        }
    }

    fn metric(out: &Outputs, port: &str, key: &str) -> f64 {
        match out.get(port) {
            Some(Value::Metrics(m)) => m[key],
            other => panic!("{port}: {other:?}"),
        }
    }

    fn bar() -> Mesh {
        let (positions, triangles) = capped_cylinder(0.2, 2.0, 65, 32);
        Mesh {
            positions: positions.iter().map(|p| p.map(|c| c as f32)).collect(),
            triangles,
            normals: None,
            uvs: None,
            colors: None,
            tangents: None,
        }
    }

    fn skin(params: SkinParams, mesh: Mesh, rotations: Option<Matrix>) -> Outputs {
        let op = Skin::new(params).unwrap();
        let specs = Skin::inputs();
        let values = [
            Some(Value::Mesh(Arc::new(mesh))),
            rotations.map(|m| Value::Matrix(Arc::new(m))),
        ];
        op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap()
    }

    fn twist(method: SkinMethod, degrees: f64) -> f64 {
        let params = SkinParams {
            bone_lengths: vec![1.0, 1.0],
            blend_width: 1.0,
            rotations_deg: vec![0.0, 0.0, 0.0, degrees, 0.0, 0.0],
            method,
            ..SkinParams::default()
        };
        metric(&skin(params, bar(), None), "metrics", "volume_ratio")
    }

    #[test]
    fn twist_180_collapses_linear_blend_and_keeps_dual_quaternion_volume() {
        let lbs = twist(SkinMethod::LinearBlend, 180.0);
        let dqs = twist(SkinMethod::DualQuaternion, 180.0);
        println!("180° twist volume ratio: LBS {lbs:.4}, DQS {dqs:.5}");
        assert!(lbs < 0.8, "LBS {lbs}");
        assert!((dqs - 1.0).abs() < 0.01, "DQS {dqs}");
        // At rest every method returns the mesh.
        for m in [
            SkinMethod::Rigid,
            SkinMethod::LinearBlend,
            SkinMethod::DualQuaternion,
        ] {
            assert!((twist(m, 0.0) - 1.0).abs() < 1e-9);
        }
    }

    #[test]
    fn chain_weights_partition_unity_and_follow_the_bones() {
        let axis = Vector3::x();
        let points: Vec<[f64; 3]> = (0..=60)
            .map(|i| [-0.5 + i as f64 * 0.05, 0.1, 0.0])
            .collect();
        let w = chain_weights(&points, axis, &[1.0, 0.5, 1.0], 0.2).unwrap();
        for (v, p) in points.iter().enumerate() {
            let inf = w.influences(v);
            let sum: f64 = inf.iter().map(|(_, w)| w).sum();
            assert!((sum - 1.0).abs() < 1e-12, "{p:?}: {inf:?}");
            // Away from the joints (at 1 and 1.5) only one bone moves the vertex.
            let x = p[0];
            let expected = if x < 0.9 {
                Some(0)
            } else if (1.1..1.4).contains(&x) {
                Some(1)
            } else if x > 1.6 {
                Some(2)
            } else {
                None
            };
            if let Some(bone) = expected {
                assert_eq!(inf, [(bone, 1.0)], "{p:?}");
            }
        }
    }

    #[test]
    fn rotations_input_replaces_the_parameter() {
        let params = SkinParams {
            rotations_deg: vec![0.0, 0.0, 90.0],
            ..SkinParams::default()
        };
        let from_param = skin(params.clone(), bar(), None);
        let matrix = Matrix::new(2, 3, vec![0.0, 0.0, 90.0, 0.0, 0.0, 0.0]).unwrap();
        let from_input = skin(
            SkinParams {
                rotations_deg: Vec::new(),
                ..params
            },
            bar(),
            Some(matrix),
        );
        assert_eq!(from_param.get("mesh"), from_input.get("mesh"));
        // A 90° turn of the root about z takes +x to +y: the far cap's centre is at (0, 2, 0).
        let Some(Value::Mesh(m)) = from_param.get("mesh") else {
            panic!()
        };
        let top = m.positions.iter().map(|p| p[1]).fold(f32::MIN, f32::max);
        assert!((top - 2.0).abs() < 1e-5, "{top}");
    }

    #[test]
    fn bad_rotations_are_load_errors() {
        for r in [vec![1.0, 2.0], vec![0.0; 9], vec![f64::NAN, 0.0, 0.0]] {
            let params = SkinParams {
                rotations_deg: r.clone(),
                ..SkinParams::default()
            };
            assert!(Skin::new(params).is_err(), "{r:?}");
        }
        assert!(
            Skin::new(SkinParams {
                bone_lengths: vec![],
                ..SkinParams::default()
            })
            .is_err()
        );
        assert!(
            Skin::new(SkinParams {
                axis: [0.0; 3],
                ..SkinParams::default()
            })
            .is_err()
        );
    }

    fn ik(params: IkParams) -> Outputs {
        let op = Ik::new(params).unwrap();
        let specs = Ik::inputs();
        op.run(&ctx(), &Inputs::new(&specs, &[])).unwrap()
    }

    #[test]
    fn ik_reaches_a_reachable_target_and_reports_an_unreachable_one() {
        for solver in [IkSolver::Ccd, IkSolver::DampedLeastSquares] {
            let target = [0.9, 1.1, 0.4];
            let out = ik(IkParams {
                bone_lengths: vec![1.0, 0.8, 0.5],
                root: [0.0, 0.0, 0.0],
                target,
                solver,
                max_iterations: 2000,
                ..IkParams::default()
            });
            assert_eq!(metric(&out, "metrics", "reached"), 1.0);
            assert!(metric(&out, "metrics", "error") < 1e-4);
            // The posed tip (last joint row) is on the target.
            let Some(Value::Matrix(joints)) = out.get("joints") else {
                panic!()
            };
            assert_eq!((joints.rows, joints.cols), (4, 3));
            for (k, t) in target.iter().enumerate() {
                assert!((joints.get(3, k).unwrap() - t).abs() < 1e-4);
            }
            // Bone lengths are kept.
            for j in 0..3 {
                let d: f64 = (0..3)
                    .map(|k| (joints.get(j + 1, k).unwrap() - joints.get(j, k).unwrap()).powi(2))
                    .sum::<f64>()
                    .sqrt();
                assert!((d - [1.0, 0.8, 0.5][j]).abs() < 1e-9);
            }

            let far = ik(IkParams {
                bone_lengths: vec![1.0, 0.8, 0.5],
                root: [1.0, 2.0, 3.0],
                target: [6.0, 2.0, 3.0],
                solver,
                ..IkParams::default()
            });
            assert_eq!(metric(&far, "metrics", "reachable"), 0.0);
            assert_eq!(metric(&far, "metrics", "reached"), 0.0);
            assert!((metric(&far, "metrics", "error") - (5.0 - 2.3)).abs() < 1e-6);
        }
    }

    #[test]
    fn ik_rotations_drive_skin_to_the_same_pose() {
        // The tip of a straight bar skinned by the IK rotations lands on the IK target.
        let target = [0.6, 1.2, 0.0];
        let out = ik(IkParams {
            bone_lengths: vec![1.0, 1.0],
            target,
            hinge_axis: Some([0.0, 0.0, 1.0]),
            ..IkParams::default()
        });
        assert_eq!(metric(&out, "metrics", "reached"), 1.0);
        let Some(Value::Matrix(rotations)) = out.get("rotations") else {
            panic!()
        };
        // Hinge joints about z: rotation vectors along z only.
        for j in 0..2 {
            assert!(rotations.get(j, 0).unwrap().abs() < 1e-9);
            assert!(rotations.get(j, 1).unwrap().abs() < 1e-9);
        }
        let skinned = skin(
            SkinParams {
                bone_lengths: vec![1.0, 1.0],
                blend_width: 0.0,
                method: SkinMethod::Rigid,
                ..SkinParams::default()
            },
            bar(),
            Some(Matrix::clone(rotations)),
        );
        let Some(Value::Mesh(m)) = skinned.get("mesh") else {
            panic!()
        };
        // The far cap's centre vertex (last in the layout) sits on the bar's axis at x = 2.
        let tip = m.positions[m.positions.len() - 1];
        for (k, t) in target.iter().enumerate() {
            assert!((f64::from(tip[k]) - t).abs() < 1e-4, "{tip:?}");
        }
    }

    #[test]
    fn ik_limits_are_checked_at_load() {
        assert!(
            Ik::new(IkParams {
                cone_deg: Some(30.0),
                hinge_axis: Some([0.0, 0.0, 1.0]),
                ..IkParams::default()
            })
            .is_err()
        );
        assert!(
            Ik::new(IkParams {
                hinge_axis: Some([0.0, 0.0, 1.0]),
                hinge_range_deg: [10.0, -10.0],
                ..IkParams::default()
            })
            .is_err()
        );
    }
}
