//! Skeletons: a joint hierarchy with rest transforms, forward kinematics and
//! the bind pose used by skinning.
//!
//! # Frames and conventions
//!
//! Every joint `i` has a rest transform `parent_from_joint_rest[i]` that maps
//! points from the joint's frame into its parent's frame (the world frame for
//! a root joint). Joints are stored so that a parent always comes before its
//! children, so forward kinematics is one pass over the joints:
//!
//! ```text
//! world_from_joint[i] = world_from_joint[parent(i)] · parent_from_joint[i]
//! ```
//!
//! The *bind pose* is the rest pose: `joint_from_bind[i]` is the inverse of
//! the rest `world_from_joint[i]`, so a mesh modelled in the rest pose ("bind
//! space") is carried along by the skinning transform
//! `world_from_bind[i] = world_from_joint[i] · joint_from_bind[i]`, which is
//! the identity in the rest pose.
//!
//! Local rotations (used by animation and inverse kinematics) are applied
//! *after* the rest rotation, in the joint's own rest-oriented frame:
//! `parent_from_joint[i] = parent_from_joint_rest[i] · R(local[i])`. The rest
//! translation is kept, so bones keep their lengths.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use thiserror::Error;

/// Errors shared by the skeleton, skinning and inverse-kinematics modules.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum AnimateError {
    /// A per-joint array has the wrong number of entries.
    #[error("joint count mismatch in {what}: expected {expected} entries, got {got}")]
    JointCountMismatch {
        /// Which input was checked.
        what: &'static str,
        /// Number of joints the skeleton (or weights) expects.
        expected: usize,
        /// Number of entries supplied.
        got: usize,
    },
    /// A joint names a parent that does not come before it.
    #[error(
        "joint {joint} ('{name}') has parent {parent}, but a parent must come before its child"
    )]
    ParentAfterChild {
        /// Index of the offending joint.
        joint: usize,
        /// Name of the offending joint.
        name: String,
        /// The parent index it names.
        parent: usize,
    },
    /// Two joints share a name.
    #[error("duplicate joint name '{0}'")]
    DuplicateJointName(String),
    /// A joint index is not smaller than the number of joints.
    #[error("joint index {index} out of range ({count} joints)")]
    JointIndexOutOfRange {
        /// The index supplied.
        index: usize,
        /// Number of joints.
        count: usize,
    },
    /// A value that must be finite is NaN or infinite.
    #[error("non-finite value in {what} (entry {index})")]
    NonFinite {
        /// Which input was checked.
        what: &'static str,
        /// Index of the first offending entry.
        index: usize,
    },
    /// A vertex has no positive skinning weight.
    #[error("vertex {vertex} has skinning weights that sum to zero")]
    ZeroWeightSum {
        /// The vertex index.
        vertex: usize,
    },
    /// A skinning weight is negative.
    #[error("vertex {vertex} has a negative weight {weight} for joint {joint}")]
    NegativeWeight {
        /// The vertex index.
        vertex: usize,
        /// The joint index.
        joint: usize,
        /// The weight supplied.
        weight: f64,
    },
    /// Two arrays that must have the same length do not.
    #[error("length mismatch in {what}: expected {expected}, got {got}")]
    LengthMismatch {
        /// Which input was checked.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Supplied length.
        got: usize,
    },
    /// An inverse-kinematics chain is empty.
    #[error("inverse-kinematics chain is empty")]
    EmptyChain,
    /// Consecutive chain joints are not parent and child.
    #[error("chain not connected: joint {child} is not a child of joint {parent}")]
    ChainNotConnected {
        /// The joint expected to be the parent.
        parent: usize,
        /// The joint expected to be its child.
        child: usize,
    },
    /// Any other invalid argument, with an explanation.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}

/// One joint of a [`Skeleton`].
#[derive(Debug, Clone, PartialEq)]
pub struct Joint {
    /// Unique joint name.
    pub name: String,
    /// Index of the parent joint (`None` for a root); must be smaller than the
    /// joint's own index.
    pub parent: Option<usize>,
    /// Rest transform: maps points from this joint's frame into its parent's
    /// frame (or the world frame for a root).
    pub parent_from_joint_rest: Isometry3<f64>,
}

/// A validated joint hierarchy, parents stored before their children.
#[derive(Debug, Clone, PartialEq)]
pub struct Skeleton {
    joints: Vec<Joint>,
}

/// True when every component of an isometry is finite.
pub(crate) fn isometry_is_finite(iso: &Isometry3<f64>) -> bool {
    iso.translation.vector.iter().all(|v| v.is_finite())
        && iso.rotation.coords.iter().all(|v| v.is_finite())
}

/// True when every component of a unit quaternion is finite.
pub(crate) fn rotation_is_finite(q: &UnitQuaternion<f64>) -> bool {
    q.coords.iter().all(|v| v.is_finite())
}

/// Checks that `values` has `expected` entries and that all are finite.
fn check_isometries(
    what: &'static str,
    values: &[Isometry3<f64>],
    expected: usize,
) -> Result<(), AnimateError> {
    if values.len() != expected {
        return Err(AnimateError::JointCountMismatch {
            what,
            expected,
            got: values.len(),
        });
    }
    if let Some(index) = values.iter().position(|iso| !isometry_is_finite(iso)) {
        return Err(AnimateError::NonFinite { what, index });
    }
    Ok(())
}

impl Skeleton {
    /// Builds a skeleton, checking that every parent index is smaller than its
    /// child's index, that names are unique and that rest transforms are
    /// finite.
    pub fn new(joints: Vec<Joint>) -> Result<Skeleton, AnimateError> {
        let mut names = std::collections::HashSet::with_capacity(joints.len());
        for (index, joint) in joints.iter().enumerate() {
            if let Some(parent) = joint.parent
                && parent >= index
            {
                return Err(AnimateError::ParentAfterChild {
                    joint: index,
                    name: joint.name.clone(),
                    parent,
                });
            }
            if !names.insert(joint.name.as_str()) {
                return Err(AnimateError::DuplicateJointName(joint.name.clone()));
            }
            if !isometry_is_finite(&joint.parent_from_joint_rest) {
                return Err(AnimateError::NonFinite {
                    what: "joint rest transform",
                    index,
                });
            }
        }
        Ok(Skeleton { joints })
    }

    /// A straight chain along `axis`: `lengths.len() + 1` joints named
    /// `joint0`, `joint1`, …; `joint0` is the root at the origin with the
    /// identity rest transform, and joint `k + 1` sits `lengths[k]` further
    /// along the (normalized) axis from joint `k`, with identity rest rotation.
    /// The last joint marks the tip of the last bone. Lengths must be finite
    /// and non-negative (zero-length links are allowed); the axis must be
    /// finite and non-zero.
    pub fn chain(lengths: &[f64], axis: Vector3<f64>) -> Result<Skeleton, AnimateError> {
        let norm = axis.norm();
        if !norm.is_finite() {
            return Err(AnimateError::NonFinite {
                what: "chain axis",
                index: 0,
            });
        }
        if norm <= f64::MIN_POSITIVE {
            return Err(AnimateError::InvalidArgument(
                "chain axis must be non-zero".into(),
            ));
        }
        let unit_axis = axis / norm;
        if let Some(index) = lengths.iter().position(|l| !l.is_finite()) {
            return Err(AnimateError::NonFinite {
                what: "chain lengths",
                index,
            });
        }
        if let Some(index) = lengths.iter().position(|l| *l < 0.0) {
            return Err(AnimateError::InvalidArgument(format!(
                "chain length {index} is negative"
            )));
        }
        let mut joints = Vec::with_capacity(lengths.len() + 1);
        joints.push(Joint {
            name: "joint0".into(),
            parent: None,
            parent_from_joint_rest: Isometry3::identity(),
        });
        for (k, length) in lengths.iter().enumerate() {
            joints.push(Joint {
                name: format!("joint{}", k + 1),
                parent: Some(k),
                parent_from_joint_rest: Isometry3::from_parts(
                    Translation3::from(unit_axis * *length),
                    UnitQuaternion::identity(),
                ),
            });
        }
        Skeleton::new(joints)
    }

    /// All joints, parents before children.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }

    /// The joint at `index`, if any.
    pub fn joint(&self, index: usize) -> Option<&Joint> {
        self.joints.get(index)
    }

    /// Index of the joint called `name`, if any.
    pub fn joint_index(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|joint| joint.name == name)
    }

    /// Number of joints.
    pub fn len(&self) -> usize {
        self.joints.len()
    }

    /// True when the skeleton has no joints.
    pub fn is_empty(&self) -> bool {
        self.joints.is_empty()
    }

    /// Parent of joint `index` (`None` for a root or an index out of range).
    pub fn parent(&self, index: usize) -> Option<usize> {
        self.joints.get(index).and_then(|joint| joint.parent)
    }

    /// Indices of the direct children of joint `index`, in increasing order
    /// (empty for a leaf or an index out of range).
    pub fn children(&self, index: usize) -> Vec<usize> {
        self.joints
            .iter()
            .enumerate()
            .filter(|(_, joint)| joint.parent == Some(index))
            .map(|(child, _)| child)
            .collect()
    }

    /// The rest transforms `parent_from_joint_rest`, one per joint.
    pub fn rest_parent_from_joint(&self) -> Vec<Isometry3<f64>> {
        self.joints
            .iter()
            .map(|joint| joint.parent_from_joint_rest)
            .collect()
    }

    /// Forward kinematics: composes `parent_from_joint` along each parent
    /// chain into `world_from_joint`, in one pass (parents precede children).
    pub fn world_from_joint(
        &self,
        parent_from_joint: &[Isometry3<f64>],
    ) -> Result<Vec<Isometry3<f64>>, AnimateError> {
        check_isometries("parent_from_joint", parent_from_joint, self.joints.len())?;
        Ok(self.compose_unchecked(parent_from_joint))
    }

    /// Forward kinematics on inputs already known to match the skeleton.
    fn compose_unchecked(&self, parent_from_joint: &[Isometry3<f64>]) -> Vec<Isometry3<f64>> {
        let mut world_from_joint: Vec<Isometry3<f64>> = Vec::with_capacity(self.joints.len());
        for (joint, local) in self.joints.iter().zip(parent_from_joint) {
            // `Skeleton::new` guarantees parent < own index, so the parent is
            // already in `world_from_joint`; `get` keeps this panic-free.
            let world = match joint.parent.and_then(|p| world_from_joint.get(p)) {
                Some(world_from_parent) => world_from_parent * local,
                None => *local,
            };
            world_from_joint.push(world);
        }
        world_from_joint
    }

    /// Forward kinematics of the rest pose.
    pub fn rest_world_from_joint(&self) -> Vec<Isometry3<f64>> {
        self.compose_unchecked(&self.rest_parent_from_joint())
    }

    /// The bind pose: `joint_from_bind[i]`, the inverse of the rest
    /// `world_from_joint[i]`. It maps a bind-space (rest-pose, world) point
    /// into joint `i`'s frame.
    pub fn joint_from_bind(&self) -> Vec<Isometry3<f64>> {
        self.rest_world_from_joint()
            .iter()
            .map(|world_from_joint| world_from_joint.inverse())
            .collect()
    }

    /// Local pose from per-joint rotations relative to the rest orientation:
    /// `parent_from_joint[i] = parent_from_joint_rest[i] · R(local[i])`, i.e.
    /// the rest translation is kept and `local[i]` is applied in the joint's
    /// own rest-oriented frame, after the rest rotation. Identity rotations
    /// give the rest pose.
    pub fn pose_from_local_rotations(
        &self,
        local_rotations: &[UnitQuaternion<f64>],
    ) -> Result<Vec<Isometry3<f64>>, AnimateError> {
        if local_rotations.len() != self.joints.len() {
            return Err(AnimateError::JointCountMismatch {
                what: "local rotations",
                expected: self.joints.len(),
                got: local_rotations.len(),
            });
        }
        if let Some(index) = local_rotations.iter().position(|q| !rotation_is_finite(q)) {
            return Err(AnimateError::NonFinite {
                what: "local rotations",
                index,
            });
        }
        Ok(self.pose_unchecked(local_rotations))
    }

    /// `pose_from_local_rotations` on inputs already validated.
    pub(crate) fn pose_unchecked(
        &self,
        local_rotations: &[UnitQuaternion<f64>],
    ) -> Vec<Isometry3<f64>> {
        self.joints
            .iter()
            .zip(local_rotations)
            .map(|(joint, local)| {
                let rest = &joint.parent_from_joint_rest;
                Isometry3::from_parts(rest.translation, rest.rotation * local)
            })
            .collect()
    }

    /// `world_from_joint` for per-joint local rotations (see
    /// [`Skeleton::pose_from_local_rotations`]).
    pub(crate) fn world_from_local_rotations_unchecked(
        &self,
        local_rotations: &[UnitQuaternion<f64>],
    ) -> Vec<Isometry3<f64>> {
        self.compose_unchecked(&self.pose_unchecked(local_rotations))
    }

    /// Skinning transforms `world_from_bind[i] = world_from_joint[i] ·
    /// joint_from_bind[i]`: they carry a bind-space vertex rigidly with joint
    /// `i`, and are the identity in the rest pose.
    pub fn skinning_transforms(
        &self,
        world_from_joint: &[Isometry3<f64>],
    ) -> Result<Vec<Isometry3<f64>>, AnimateError> {
        check_isometries("world_from_joint", world_from_joint, self.joints.len())?;
        Ok(world_from_joint
            .iter()
            .zip(self.joint_from_bind())
            .map(|(world_from_joint, joint_from_bind)| world_from_joint * joint_from_bind)
            .collect())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

    use super::*;
    use nalgebra::{Point3, Vector3};
    use std::f64::consts::FRAC_PI_2;

    fn rot_z(angle: f64) -> UnitQuaternion<f64> {
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle)
    }

    fn assert_point(actual: Point3<f64>, expected: [f64; 3]) {
        for k in 0..3 {
            assert!(
                (actual[k] - expected[k]).abs() <= 1e-12,
                "component {k}: {actual} vs {expected:?}"
            );
        }
    }

    fn origin(iso: &Isometry3<f64>) -> Point3<f64> {
        iso * Point3::origin()
    }

    #[test]
    fn fk_two_joint_chain_with_90_degree_rotation() {
        let skeleton = Skeleton::chain(&[1.0], Vector3::x()).unwrap();
        assert_eq!(skeleton.len(), 2);
        let pose = skeleton
            .pose_from_local_rotations(&[rot_z(FRAC_PI_2), UnitQuaternion::identity()])
            .unwrap();
        let world_from_joint = skeleton.world_from_joint(&pose).unwrap();
        assert_point(origin(&world_from_joint[0]), [0.0, 0.0, 0.0]);
        assert_point(origin(&world_from_joint[1]), [0.0, 1.0, 0.0]);
        // A point one unit along the second joint's x axis.
        assert_point(
            world_from_joint[1] * Point3::new(1.0, 0.0, 0.0),
            [0.0, 2.0, 0.0],
        );
    }

    #[test]
    fn fk_three_joint_chain_with_90_degree_rotations() {
        let skeleton = Skeleton::chain(&[1.0, 2.0], Vector3::x()).unwrap();
        let pose = skeleton
            .pose_from_local_rotations(&[
                rot_z(FRAC_PI_2),
                rot_z(FRAC_PI_2),
                UnitQuaternion::identity(),
            ])
            .unwrap();
        let world_from_joint = skeleton.world_from_joint(&pose).unwrap();
        assert_point(origin(&world_from_joint[1]), [0.0, 1.0, 0.0]);
        assert_point(origin(&world_from_joint[2]), [-2.0, 1.0, 0.0]);
    }

    #[test]
    fn local_rotation_is_applied_after_rest_rotation() {
        // Joint 1 has a rest rotation of +90° about x; its local rotation of
        // +90° about z acts in the rest-oriented frame: parent_from_joint =
        // T(1,0,0) · Rx(90°) · Rz(90°). The child offset (1,0,0) maps to
        // Rx·Rz·(1,0,0) = Rx·(0,1,0) = (0,0,1).
        let joints = vec![
            Joint {
                name: "root".into(),
                parent: None,
                parent_from_joint_rest: Isometry3::identity(),
            },
            Joint {
                name: "mid".into(),
                parent: Some(0),
                parent_from_joint_rest: Isometry3::from_parts(
                    Translation3::new(1.0, 0.0, 0.0),
                    UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2),
                ),
            },
            Joint {
                name: "tip".into(),
                parent: Some(1),
                parent_from_joint_rest: Isometry3::translation(1.0, 0.0, 0.0),
            },
        ];
        let skeleton = Skeleton::new(joints).unwrap();
        let pose = skeleton
            .pose_from_local_rotations(&[
                UnitQuaternion::identity(),
                rot_z(FRAC_PI_2),
                UnitQuaternion::identity(),
            ])
            .unwrap();
        let world_from_joint = skeleton.world_from_joint(&pose).unwrap();
        assert_point(origin(&world_from_joint[2]), [1.0, 0.0, 1.0]);
        // Rest pose: the tip is straight along x.
        let rest = skeleton.rest_world_from_joint();
        assert_point(origin(&rest[2]), [2.0, 0.0, 0.0]);
    }

    #[test]
    fn bind_pose_inverts_rest_pose_and_skinning_is_identity_at_rest() {
        let skeleton = Skeleton::chain(&[1.0, 0.5, 2.0], Vector3::new(1.0, 2.0, -1.0)).unwrap();
        let rest = skeleton.rest_world_from_joint();
        let joint_from_bind = skeleton.joint_from_bind();
        let world_from_bind = skeleton.skinning_transforms(&rest).unwrap();
        for i in 0..skeleton.len() {
            let product = rest[i] * joint_from_bind[i];
            assert!(product.translation.vector.norm() < 1e-12);
            assert!(product.rotation.angle() < 1e-12);
            assert!(world_from_bind[i].translation.vector.norm() < 1e-12);
        }
        // Tip of the chain: 3.5 along the normalized axis.
        let axis = Vector3::new(1.0, 2.0, -1.0).normalize();
        let tip = origin(&rest[3]);
        assert!((tip.coords - axis * 3.5).norm() < 1e-12);
    }

    #[test]
    fn accessors_and_children() {
        let joints = vec![
            Joint {
                name: "hips".into(),
                parent: None,
                parent_from_joint_rest: Isometry3::identity(),
            },
            Joint {
                name: "left".into(),
                parent: Some(0),
                parent_from_joint_rest: Isometry3::translation(0.0, 1.0, 0.0),
            },
            Joint {
                name: "right".into(),
                parent: Some(0),
                parent_from_joint_rest: Isometry3::translation(0.0, -1.0, 0.0),
            },
            Joint {
                name: "left_foot".into(),
                parent: Some(1),
                parent_from_joint_rest: Isometry3::translation(0.0, 0.0, -1.0),
            },
        ];
        let skeleton = Skeleton::new(joints).unwrap();
        assert_eq!(skeleton.joint_index("right"), Some(2));
        assert_eq!(skeleton.joint_index("nope"), None);
        assert_eq!(skeleton.children(0), vec![1, 2]);
        assert_eq!(skeleton.children(1), vec![3]);
        assert!(skeleton.children(3).is_empty());
        assert!(skeleton.children(99).is_empty());
        assert_eq!(skeleton.parent(3), Some(1));
        assert_eq!(skeleton.parent(0), None);
        assert_eq!(skeleton.joint(1).map(|j| j.name.as_str()), Some("left"));
        assert!(!skeleton.is_empty());
    }

    #[test]
    fn validation_errors() {
        let joint = |name: &str, parent: Option<usize>| Joint {
            name: name.into(),
            parent,
            parent_from_joint_rest: Isometry3::identity(),
        };
        assert!(matches!(
            Skeleton::new(vec![joint("a", Some(1)), joint("b", None)]),
            Err(AnimateError::ParentAfterChild { joint: 0, .. })
        ));
        assert!(matches!(
            Skeleton::new(vec![joint("a", Some(0))]),
            Err(AnimateError::ParentAfterChild { .. })
        ));
        assert!(matches!(
            Skeleton::new(vec![joint("a", None), joint("a", Some(0))]),
            Err(AnimateError::DuplicateJointName(_))
        ));
        let mut bad = joint("b", Some(0));
        bad.parent_from_joint_rest.translation.vector.x = f64::NAN;
        assert!(matches!(
            Skeleton::new(vec![joint("a", None), bad]),
            Err(AnimateError::NonFinite { index: 1, .. })
        ));
        let skeleton = Skeleton::chain(&[1.0, 1.0], Vector3::x()).unwrap();
        assert!(matches!(
            skeleton.world_from_joint(&[Isometry3::identity()]),
            Err(AnimateError::JointCountMismatch {
                expected: 3,
                got: 1,
                ..
            })
        ));
        assert!(matches!(
            skeleton.pose_from_local_rotations(&[UnitQuaternion::identity(); 2]),
            Err(AnimateError::JointCountMismatch { .. })
        ));
        assert!(Skeleton::chain(&[1.0], Vector3::zeros()).is_err());
        assert!(Skeleton::chain(&[-1.0], Vector3::x()).is_err());
        assert!(Skeleton::chain(&[f64::INFINITY], Vector3::x()).is_err());
        // Error messages are readable.
        let message = AnimateError::ZeroWeightSum { vertex: 7 }.to_string();
        assert!(message.contains("vertex 7") && message.contains("sum to zero"));
    }
}
