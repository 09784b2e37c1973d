//! Skinning: deforming a bind-pose mesh with a posed skeleton, plus blend
//! shapes (morph targets) and small mesh helpers used by tests and operators.
//!
//! Three methods are provided, all taking the skinning transforms
//! `world_from_bind[i] = world_from_joint[i] · joint_from_bind[i]` (see
//! [`Skeleton::skinning_transforms`](super::skeleton::Skeleton::skinning_transforms)):
//!
//! * [`skin_rigid`]: every vertex follows its most-weighted joint.
//! * [`skin_linear_blend`]: linear blend skinning (Magnenat-Thalmann, Laperrière
//!   & Thalmann 1988, "Joint-dependent local deformations for hand animation
//!   and object grasping"; also called skeletal subspace deformation). The
//!   weighted sum of the 3×4 joint matrices is applied to the vertex. It is
//!   cheap but collapses under twists (the "candy-wrapper" artefact) and loses
//!   volume at bent joints.
//! * [`skin_dual_quaternion`]: dual quaternion skinning (Kavan, Collins, Žára
//!   & O'Sullivan 2008, "Geometric skinning with approximate dual quaternion
//!   blending", ACM TOG 27(4)). Unit dual quaternions are blended linearly and
//!   renormalized, which always yields a rigid transform per vertex.

use nalgebra::{Isometry3, Matrix3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use super::skeleton::{AnimateError, isometry_is_finite};

/// Per-vertex skinning weights: for each vertex a short list of
/// `(joint index, weight)` pairs, validated and normalized to sum to one.
///
/// Each list is stored sorted by decreasing weight (ties by increasing joint
/// index), so the first entry is the vertex's most-weighted ("dominant")
/// joint. Duplicate joint indices are merged by summing, and zero weights are
/// dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct SkinWeights {
    per_vertex: Vec<Vec<(usize, f64)>>,
    joint_count: usize,
}

impl SkinWeights {
    /// Validates and normalizes weights for a skeleton of `joint_count`
    /// joints: every joint index must be `< joint_count`, every weight finite
    /// and non-negative, and every vertex's weights must have a positive sum.
    pub fn new(
        per_vertex: Vec<Vec<(usize, f64)>>,
        joint_count: usize,
    ) -> Result<SkinWeights, AnimateError> {
        SkinWeights::with_max_influences(per_vertex, joint_count, None)
    }

    /// As [`SkinWeights::new`], and when `max_influences` is `Some(k)` only
    /// the `k` largest weights of each vertex are kept (then renormalized).
    /// `Some(0)` is rejected.
    pub fn with_max_influences(
        per_vertex: Vec<Vec<(usize, f64)>>,
        joint_count: usize,
        max_influences: Option<usize>,
    ) -> Result<SkinWeights, AnimateError> {
        if max_influences == Some(0) {
            return Err(AnimateError::InvalidArgument(
                "max_influences must be at least 1".into(),
            ));
        }
        let mut normalized = Vec::with_capacity(per_vertex.len());
        for (vertex, influences) in per_vertex.into_iter().enumerate() {
            let mut merged: Vec<(usize, f64)> = Vec::with_capacity(influences.len());
            for (joint, weight) in influences {
                if joint >= joint_count {
                    return Err(AnimateError::JointIndexOutOfRange {
                        index: joint,
                        count: joint_count,
                    });
                }
                if !weight.is_finite() {
                    return Err(AnimateError::NonFinite {
                        what: "skinning weights",
                        index: vertex,
                    });
                }
                if weight < 0.0 {
                    return Err(AnimateError::NegativeWeight {
                        vertex,
                        joint,
                        weight,
                    });
                }
                if weight == 0.0 {
                    continue;
                }
                match merged.iter_mut().find(|(j, _)| *j == joint) {
                    Some((_, w)) => *w += weight,
                    None => merged.push((joint, weight)),
                }
            }
            merged.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
            if let Some(k) = max_influences {
                merged.truncate(k);
            }
            let sum: f64 = merged.iter().map(|(_, w)| w).sum();
            if !sum.is_finite() {
                return Err(AnimateError::NonFinite {
                    what: "skinning weight sum",
                    index: vertex,
                });
            }
            if sum <= 0.0 {
                return Err(AnimateError::ZeroWeightSum { vertex });
            }
            for (_, w) in &mut merged {
                *w /= sum;
            }
            normalized.push(merged);
        }
        Ok(SkinWeights {
            per_vertex: normalized,
            joint_count,
        })
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> usize {
        self.per_vertex.len()
    }

    /// Number of joints the weights refer to.
    pub fn joint_count(&self) -> usize {
        self.joint_count
    }

    /// The normalized influences of `vertex`, largest first (empty when out
    /// of range).
    pub fn influences(&self, vertex: usize) -> &[(usize, f64)] {
        self.per_vertex.get(vertex).map_or(&[], Vec::as_slice)
    }

    /// All vertices' normalized influences.
    pub fn per_vertex(&self) -> &[Vec<(usize, f64)>] {
        &self.per_vertex
    }

    /// The most-weighted joint of `vertex` (`None` when out of range).
    pub fn dominant_joint(&self, vertex: usize) -> Option<usize> {
        self.influences(vertex).first().map(|(joint, _)| *joint)
    }
}

/// Result of skinning: deformed positions and, when normals were given,
/// deformed unit normals.
#[derive(Debug, Clone, PartialEq)]
pub struct Skinned {
    /// Deformed vertex positions (world frame).
    pub positions: Vec<[f64; 3]>,
    /// Deformed normals, present when input normals were supplied.
    pub normals: Option<Vec<[f64; 3]>>,
}

/// A dual quaternion `real + ε·dual` used by dual quaternion skinning (Kavan
/// et al. 2008). A *unit* dual quaternion (|real| = 1, real·dual = 0)
/// represents the rigid transform "rotate by `real`, then translate by
/// `t = 2·dual·conj(real)`".
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DualQuaternion {
    /// Rotation part.
    pub real: Quaternion<f64>,
    /// Translation part: `dual = ½·t·real` for a unit dual quaternion.
    pub dual: Quaternion<f64>,
}

impl DualQuaternion {
    /// The identity transform.
    pub fn identity() -> DualQuaternion {
        DualQuaternion {
            real: Quaternion::identity(),
            dual: Quaternion::new(0.0, 0.0, 0.0, 0.0),
        }
    }

    /// The unit dual quaternion of a rigid transform: `real = q`,
    /// `dual = ½·(0, t)·q`.
    pub fn from_isometry(iso: &Isometry3<f64>) -> DualQuaternion {
        let real = *iso.rotation.quaternion();
        let dual = Quaternion::from_imag(iso.translation.vector) * real * 0.5;
        DualQuaternion { real, dual }
    }

    /// The rigid transform of this dual quaternion, normalizing first;
    /// `None` when the real part is (near) zero or not finite.
    pub fn to_isometry(&self) -> Option<Isometry3<f64>> {
        let unit = self.normalize()?;
        Some(Isometry3::from_parts(
            Translation3::from(unit.translation()),
            unit.rotation(),
        ))
    }

    /// Scales both parts by `s`.
    pub fn scale(&self, s: f64) -> DualQuaternion {
        DualQuaternion {
            real: self.real * s,
            dual: self.dual * s,
        }
    }

    /// Component-wise sum.
    pub fn add(&self, other: &DualQuaternion) -> DualQuaternion {
        DualQuaternion {
            real: self.real + other.real,
            dual: self.dual + other.dual,
        }
    }

    /// Unit dual quaternion closest in the usual sense: both parts divided by
    /// |real|, then the component of `dual` along `real` removed so that
    /// `real·dual = 0`. `None` when |real| is (near) zero or not finite.
    pub fn normalize(&self) -> Option<DualQuaternion> {
        let norm = self.real.norm();
        if !norm.is_finite() || norm <= 1e-300 || !self.dual.coords.iter().all(|v| v.is_finite()) {
            return None;
        }
        let real = self.real / norm;
        let dual = self.dual / norm;
        let dual = dual - real * real.dot(&dual);
        Some(DualQuaternion { real, dual })
    }

    /// Rotation of a unit dual quaternion (the real part, renormalized).
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::new_normalize(self.real)
    }

    /// Translation of a unit dual quaternion: `2·dual·conj(real)`.
    pub fn translation(&self) -> Vector3<f64> {
        (self.dual * self.real.conjugate()).imag() * 2.0
    }

    /// Applies a unit dual quaternion to a point: rotation then translation.
    pub fn transform_point(&self, point: &Point3<f64>) -> Point3<f64> {
        self.rotation() * point + self.translation()
    }
}

fn check_skin_inputs(
    positions: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    weights: &SkinWeights,
    world_from_bind: &[Isometry3<f64>],
) -> Result<(), AnimateError> {
    if positions.len() != weights.vertex_count() {
        return Err(AnimateError::LengthMismatch {
            what: "positions vs skinning weights",
            expected: weights.vertex_count(),
            got: positions.len(),
        });
    }
    if let Some(normals) = normals
        && normals.len() != positions.len()
    {
        return Err(AnimateError::LengthMismatch {
            what: "normals vs positions",
            expected: positions.len(),
            got: normals.len(),
        });
    }
    if world_from_bind.len() != weights.joint_count() {
        return Err(AnimateError::JointCountMismatch {
            what: "skinning transforms",
            expected: weights.joint_count(),
            got: world_from_bind.len(),
        });
    }
    if let Some(index) = world_from_bind.iter().position(|x| !isometry_is_finite(x)) {
        return Err(AnimateError::NonFinite {
            what: "skinning transforms",
            index,
        });
    }
    let finite = |p: &[f64; 3]| p.iter().all(|v| v.is_finite());
    if let Some(index) = positions.iter().position(|p| !finite(p)) {
        return Err(AnimateError::NonFinite {
            what: "positions",
            index,
        });
    }
    if let Some(index) = normals.and_then(|n| n.iter().position(|p| !finite(p))) {
        return Err(AnimateError::NonFinite {
            what: "normals",
            index,
        });
    }
    Ok(())
}

fn point(p: &[f64; 3]) -> Point3<f64> {
    Point3::new(p[0], p[1], p[2])
}

fn vector(v: &[f64; 3]) -> Vector3<f64> {
    Vector3::new(v[0], v[1], v[2])
}

fn array(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// The skinning transform of a vertex's dominant joint (identity if the
/// vertex or joint is missing, which validated inputs exclude).
fn dominant_transform(
    weights: &SkinWeights,
    vertex: usize,
    world_from_bind: &[Isometry3<f64>],
) -> Isometry3<f64> {
    weights
        .dominant_joint(vertex)
        .and_then(|joint| world_from_bind.get(joint))
        .copied()
        .unwrap_or_else(Isometry3::identity)
}

/// Rigid skinning: each vertex (and normal) follows the skinning transform
/// `world_from_bind` of its most-weighted joint.
///
/// `positions` (and `normals`) are in bind space; `world_from_bind` has one
/// entry per joint of `weights`.
pub fn skin_rigid(
    positions: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    weights: &SkinWeights,
    world_from_bind: &[Isometry3<f64>],
) -> Result<Skinned, AnimateError> {
    check_skin_inputs(positions, normals, weights, world_from_bind)?;
    let transform_of = |vertex| dominant_transform(weights, vertex, world_from_bind);
    let out_positions = positions
        .iter()
        .enumerate()
        .map(|(vertex, p)| array(&(transform_of(vertex) * point(p)).coords))
        .collect();
    let out_normals = normals.map(|normals| {
        normals
            .iter()
            .enumerate()
            .map(|(vertex, n)| array(&(transform_of(vertex).rotation * vector(n))))
            .collect()
    });
    Ok(Skinned {
        positions: out_positions,
        normals: out_normals,
    })
}

/// The cofactor matrix `cof(A) = det(A)·A⁻ᵀ`, defined even for singular `A`.
fn cofactor(a: &Matrix3<f64>) -> Matrix3<f64> {
    let c0 = a.column(0).into_owned();
    let c1 = a.column(1).into_owned();
    let c2 = a.column(2).into_owned();
    Matrix3::from_columns(&[c1.cross(&c2), c2.cross(&c0), c0.cross(&c1)])
}

/// Linear blend skinning (Magnenat-Thalmann et al. 1988; "skeletal subspace
/// deformation"): each vertex is transformed by the weighted sum of its
/// joints' 3×4 skinning matrices, `p' = (Σ wᵢ Rᵢ) p + Σ wᵢ tᵢ`.
///
/// Normals are transformed by the inverse transpose of the blended 3×3 part
/// and renormalized. The cofactor matrix (a positive multiple of the inverse
/// transpose) is used so a singular blend (e.g. the 180° candy-wrapper
/// collapse) cannot produce NaN; if the transformed normal vanishes, the
/// dominant joint's rotation is used instead.
pub fn skin_linear_blend(
    positions: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    weights: &SkinWeights,
    world_from_bind: &[Isometry3<f64>],
) -> Result<Skinned, AnimateError> {
    check_skin_inputs(positions, normals, weights, world_from_bind)?;
    let matrices: Vec<(Matrix3<f64>, Vector3<f64>)> = world_from_bind
        .iter()
        .map(|x| {
            (
                x.rotation.to_rotation_matrix().into_inner(),
                x.translation.vector,
            )
        })
        .collect();
    let blended = |vertex: usize| {
        let mut linear = Matrix3::zeros();
        let mut offset = Vector3::zeros();
        for (joint, weight) in weights.influences(vertex) {
            if let Some((rotation, translation)) = matrices.get(*joint) {
                linear += rotation * *weight;
                offset += translation * *weight;
            }
        }
        (linear, offset)
    };
    let mut out_positions = Vec::with_capacity(positions.len());
    let mut out_normals = normals.map(|n| Vec::with_capacity(n.len()));
    for (vertex, p) in positions.iter().enumerate() {
        let (linear, offset) = blended(vertex);
        out_positions.push(array(&(linear * vector(p) + offset)));
        if let (Some(out), Some(normal)) = (
            out_normals.as_mut(),
            normals.and_then(|normals| normals.get(vertex)),
        ) {
            let n = vector(normal);
            let det = linear.determinant();
            let sign = if det < 0.0 { -1.0 } else { 1.0 };
            let transformed = cofactor(&linear) * n * sign;
            let length = transformed.norm();
            let result = if length > 1e-12 * (1.0 + n.norm()) && length.is_finite() {
                transformed * (n.norm() / length)
            } else {
                dominant_transform(weights, vertex, world_from_bind).rotation * n
            };
            out.push(array(&result));
        }
    }
    Ok(Skinned {
        positions: out_positions,
        normals: out_normals,
    })
}

/// Dual quaternion skinning (Kavan, Collins, Žára & O'Sullivan 2008): each
/// skinning transform becomes a unit dual quaternion; per vertex they are
/// blended with weights, each first sign-aligned with the vertex's
/// most-weighted joint (q and −q are the same rotation, so the one in the
/// pivot's hemisphere is used), then normalized and applied. Normals are
/// rotated by the blended rotation.
pub fn skin_dual_quaternion(
    positions: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    weights: &SkinWeights,
    world_from_bind: &[Isometry3<f64>],
) -> Result<Skinned, AnimateError> {
    check_skin_inputs(positions, normals, weights, world_from_bind)?;
    let dual_quaternions: Vec<DualQuaternion> = world_from_bind
        .iter()
        .map(DualQuaternion::from_isometry)
        .collect();
    let mut out_positions = Vec::with_capacity(positions.len());
    let mut out_normals = normals.map(|n| Vec::with_capacity(n.len()));
    for (vertex, p) in positions.iter().enumerate() {
        let influences = weights.influences(vertex);
        let pivot = influences
            .first()
            .and_then(|(joint, _)| dual_quaternions.get(*joint))
            .copied()
            .unwrap_or_else(DualQuaternion::identity);
        let mut sum = DualQuaternion {
            real: Quaternion::new(0.0, 0.0, 0.0, 0.0),
            dual: Quaternion::new(0.0, 0.0, 0.0, 0.0),
        };
        for (joint, weight) in influences {
            if let Some(dq) = dual_quaternions.get(*joint) {
                let signed = if dq.real.dot(&pivot.real) < 0.0 {
                    -*weight
                } else {
                    *weight
                };
                sum = sum.add(&dq.scale(signed));
            }
        }
        // After sign alignment the real part's projection on the pivot is at
        // least the pivot's weight, so normalization only fails on garbage.
        let blended = sum.normalize().unwrap_or(pivot);
        out_positions.push(array(&blended.transform_point(&point(p)).coords));
        if let (Some(out), Some(normal)) = (
            out_normals.as_mut(),
            normals.and_then(|normals| normals.get(vertex)),
        ) {
            out.push(array(&(blended.rotation() * vector(normal))));
        }
    }
    Ok(Skinned {
        positions: out_positions,
        normals: out_normals,
    })
}

/// Blend shapes (morph targets): `base + Σₖ weights[k]·deltas[k]`, where each
/// delta set has one offset per base vertex. Weights may be any finite value
/// (negative and > 1 extrapolate).
pub fn apply_blend_shapes(
    base: &[[f64; 3]],
    deltas: &[Vec<[f64; 3]>],
    weights: &[f64],
) -> Result<Vec<[f64; 3]>, AnimateError> {
    if deltas.len() != weights.len() {
        return Err(AnimateError::LengthMismatch {
            what: "blend shape weights vs delta sets",
            expected: deltas.len(),
            got: weights.len(),
        });
    }
    if let Some(index) = weights.iter().position(|w| !w.is_finite()) {
        return Err(AnimateError::NonFinite {
            what: "blend shape weights",
            index,
        });
    }
    if let Some(shape) = deltas.iter().find(|d| d.len() != base.len()) {
        return Err(AnimateError::LengthMismatch {
            what: "blend shape deltas vs base vertices",
            expected: base.len(),
            got: shape.len(),
        });
    }
    let mut out = base.to_vec();
    for (shape, weight) in deltas.iter().zip(weights) {
        if *weight == 0.0 {
            continue;
        }
        for (p, d) in out.iter_mut().zip(shape) {
            for (coordinate, offset) in p.iter_mut().zip(d) {
                *coordinate += weight * offset;
            }
        }
    }
    Ok(out)
}

/// A closed capped cylinder along +x from `x = 0` to `x = length`, as an
/// indexed triangle mesh with consistently outward-facing (counter-clockwise
/// seen from outside) triangles.
///
/// Vertex layout: ring `r` (0 ≤ r < `rings`, at `x = length·r/(rings−1)`)
/// holds `segments` vertices `r·segments + s` at angle `2π·s/segments`,
/// `(x, radius·cos θ, radius·sin θ)`; then the centre of the `x = 0` cap and
/// the centre of the `x = length` cap. `rings` is raised to at least 2 and
/// `segments` to at least 3. Meant for modest sizes (indices are `u32`).
pub fn capped_cylinder(
    radius: f64,
    length: f64,
    rings: usize,
    segments: usize,
) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let rings = rings.max(2);
    let segments = segments.max(3);
    let mut positions = Vec::with_capacity(rings * segments + 2);
    for r in 0..rings {
        let x = length * r as f64 / (rings - 1) as f64;
        for s in 0..segments {
            let theta = std::f64::consts::TAU * s as f64 / segments as f64;
            positions.push([x, radius * theta.cos(), radius * theta.sin()]);
        }
    }
    let start_cap = (rings * segments) as u32;
    let end_cap = start_cap + 1;
    positions.push([0.0, 0.0, 0.0]);
    positions.push([length, 0.0, 0.0]);
    let index = |r: usize, s: usize| (r * segments + s % segments) as u32;
    let mut triangles = Vec::with_capacity(2 * (rings - 1) * segments + 2 * segments);
    for r in 0..rings - 1 {
        for s in 0..segments {
            let a = index(r, s);
            let b = index(r, s + 1);
            let c = index(r + 1, s);
            let d = index(r + 1, s + 1);
            triangles.push([a, b, c]);
            triangles.push([b, d, c]);
        }
    }
    for s in 0..segments {
        triangles.push([start_cap, index(0, s + 1), index(0, s)]);
        triangles.push([end_cap, index(rings - 1, s), index(rings - 1, s + 1)]);
    }
    (positions, triangles)
}

/// Two-bone weights for a mesh along +x of the given `length`: joint 0 (root
/// at `x = 0`) and joint 1 (at `x = length/2`). Joint 1's weight ramps
/// smoothly (smoothstep `3t² − 2t³`) from 0 to 1 across
/// `[length/2 − blend_width/2, length/2 + blend_width/2]`; joint 0 gets the
/// rest. A `blend_width ≤ 0` gives a hard split at the middle.
pub fn cylinder_two_bone_weights(
    positions: &[[f64; 3]],
    length: f64,
    blend_width: f64,
) -> Result<SkinWeights, AnimateError> {
    if !length.is_finite() || !blend_width.is_finite() {
        return Err(AnimateError::NonFinite {
            what: "cylinder length or blend width",
            index: 0,
        });
    }
    let middle = 0.5 * length;
    let mut per_vertex = Vec::with_capacity(positions.len());
    for (vertex, p) in positions.iter().enumerate() {
        let x = p[0];
        if !x.is_finite() {
            return Err(AnimateError::NonFinite {
                what: "positions",
                index: vertex,
            });
        }
        let w1 = if blend_width > 0.0 {
            let t = ((x - (middle - 0.5 * blend_width)) / blend_width).clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t)
        } else if x >= middle {
            1.0
        } else {
            0.0
        };
        per_vertex.push(vec![(0, 1.0 - w1), (1, w1)]);
    }
    SkinWeights::new(per_vertex, 2)
}

/// Signed volume enclosed by a closed triangle mesh, by the divergence
/// theorem: `Σ p₀·(p₁ × p₂) / 6` over triangles. Positive for outward
/// (counter-clockwise from outside) orientation. Errors on an index out of
/// range.
pub fn signed_volume(positions: &[[f64; 3]], triangles: &[[u32; 3]]) -> Result<f64, AnimateError> {
    let mut six_volume = 0.0;
    for triangle in triangles {
        let mut corners = [Vector3::zeros(); 3];
        for (corner, index) in corners.iter_mut().zip(triangle) {
            let index = *index as usize;
            let p = positions
                .get(index)
                .ok_or(AnimateError::InvalidArgument(format!(
                    "triangle vertex index {index} out of range ({} vertices)",
                    positions.len()
                )))?;
            *corner = vector(p);
        }
        six_volume += corners[0].dot(&corners[1].cross(&corners[2]));
    }
    Ok(six_volume / 6.0)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

    use super::super::skeleton::Skeleton;
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    const RADIUS: f64 = 0.2;
    const LENGTH: f64 = 2.0;
    const RINGS: usize = 65; // odd, so ring 32 sits exactly at the middle (x = 1)
    const SEGMENTS: usize = 32;
    const BLEND_WIDTH: f64 = 1.0;

    type SkinFn = fn(
        &[[f64; 3]],
        Option<&[[f64; 3]]>,
        &SkinWeights,
        &[Isometry3<f64>],
    ) -> Result<Skinned, AnimateError>;

    const METHODS: [(&str, SkinFn); 3] = [
        ("rigid", skin_rigid),
        ("lbs", skin_linear_blend),
        ("dqs", skin_dual_quaternion),
    ];

    fn cylinder_normals(positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
        positions
            .iter()
            .map(|p| {
                let r = (p[1] * p[1] + p[2] * p[2]).sqrt();
                if r > 0.0 {
                    [0.0, p[1] / r, p[2] / r]
                } else {
                    [1.0, 0.0, 0.0]
                }
            })
            .collect()
    }

    struct Scene {
        positions: Vec<[f64; 3]>,
        triangles: Vec<[u32; 3]>,
        weights: SkinWeights,
        skeleton: Skeleton,
    }

    fn scene() -> Scene {
        let (positions, triangles) = capped_cylinder(RADIUS, LENGTH, RINGS, SEGMENTS);
        let weights = cylinder_two_bone_weights(&positions, LENGTH, BLEND_WIDTH).unwrap();
        let skeleton = Skeleton::chain(&[LENGTH / 2.0], Vector3::x()).unwrap();
        Scene {
            positions,
            triangles,
            weights,
            skeleton,
        }
    }

    fn skinning_for(skeleton: &Skeleton, rotations: &[UnitQuaternion<f64>]) -> Vec<Isometry3<f64>> {
        let pose = skeleton.pose_from_local_rotations(rotations).unwrap();
        let world_from_joint = skeleton.world_from_joint(&pose).unwrap();
        skeleton.skinning_transforms(&world_from_joint).unwrap()
    }

    fn max_distance(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(p, q)| (vector(p) - vector(q)).norm())
            .fold(0.0, f64::max)
    }

    fn middle_ring_radius(positions: &[[f64; 3]]) -> f64 {
        let ring = (RINGS - 1) / 2;
        let sum: f64 = (0..SEGMENTS)
            .map(|s| {
                let p = positions[ring * SEGMENTS + s];
                (p[1] * p[1] + p[2] * p[2]).sqrt()
            })
            .sum();
        sum / SEGMENTS as f64
    }

    #[test]
    fn capped_cylinder_is_closed_and_outward() {
        let (positions, triangles) = capped_cylinder(RADIUS, LENGTH, RINGS, SEGMENTS);
        assert_eq!(positions.len(), RINGS * SEGMENTS + 2);
        // Exact volume of the polygonal prism: n/2 · sin(2π/n) · r² · L.
        let n = SEGMENTS as f64;
        let prism = 0.5 * n * (std::f64::consts::TAU / n).sin() * RADIUS * RADIUS * LENGTH;
        let volume = signed_volume(&positions, &triangles).unwrap();
        assert!((volume - prism).abs() < 1e-12, "{volume} vs {prism}");
        // Every edge is shared by exactly two triangles, in opposite directions.
        let mut edges = std::collections::HashMap::new();
        for t in &triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &count) in &edges {
            assert_eq!(count, 1);
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} is a boundary");
        }
        // Moving the mesh does not change its volume (closedness).
        let shifted: Vec<[f64; 3]> = positions
            .iter()
            .map(|p| [p[0] + 3.0, p[1] - 1.0, p[2] + 7.0])
            .collect();
        let moved = signed_volume(&shifted, &triangles).unwrap();
        assert!((moved - volume).abs() < 1e-12);
        assert!(signed_volume(&positions, &[[0, 1, 99_999]]).is_err());
    }

    #[test]
    fn bind_pose_reproduces_rest_mesh() {
        let scene = scene();
        let normals = cylinder_normals(&scene.positions);
        let rest = scene.skeleton.rest_world_from_joint();
        let world_from_bind = scene.skeleton.skinning_transforms(&rest).unwrap();
        for (name, method) in METHODS {
            let skinned = method(
                &scene.positions,
                Some(&normals),
                &scene.weights,
                &world_from_bind,
            )
            .unwrap();
            let error = max_distance(&skinned.positions, &scene.positions);
            assert!(error <= 1e-12, "{name}: {error}");
            let normal_error = max_distance(skinned.normals.as_ref().unwrap(), &normals);
            assert!(normal_error <= 1e-12, "{name}: normals {normal_error}");
        }
    }

    #[test]
    fn rigid_motion_of_whole_skeleton_moves_vertices_rigidly() {
        let scene = scene();
        let normals = cylinder_normals(&scene.positions);
        let motion = Isometry3::from_parts(
            Translation3::new(0.3, -2.0, 5.0),
            UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::new(1.0, -2.0, 0.5)),
                2.1,
            ),
        );
        let bend = [
            UnitQuaternion::identity(),
            UnitQuaternion::from_euler_angles(0.4, -0.7, 1.1),
        ];
        for rotations in [[UnitQuaternion::identity(); 2], bend] {
            let pose = scene
                .skeleton
                .pose_from_local_rotations(&rotations)
                .unwrap();
            let mut moved_pose = pose.clone();
            moved_pose[0] = motion * pose[0];
            let world = scene.skeleton.world_from_joint(&pose).unwrap();
            let moved_world = scene.skeleton.world_from_joint(&moved_pose).unwrap();
            let skinning = scene.skeleton.skinning_transforms(&world).unwrap();
            let moved_skinning = scene.skeleton.skinning_transforms(&moved_world).unwrap();
            for (name, method) in METHODS {
                let base =
                    method(&scene.positions, Some(&normals), &scene.weights, &skinning).unwrap();
                let moved = method(
                    &scene.positions,
                    Some(&normals),
                    &scene.weights,
                    &moved_skinning,
                )
                .unwrap();
                let expected: Vec<[f64; 3]> = base
                    .positions
                    .iter()
                    .map(|p| array(&(motion * point(p)).coords))
                    .collect();
                let error = max_distance(&moved.positions, &expected);
                assert!(error < 1e-12, "{name}: {error}");
                let expected_normals: Vec<[f64; 3]> = base
                    .normals
                    .unwrap()
                    .iter()
                    .map(|n| array(&(motion.rotation * vector(n))))
                    .collect();
                let error = max_distance(moved.normals.as_ref().unwrap(), &expected_normals);
                assert!(error < 1e-12, "{name}: normals {error}");
            }
        }
        // Identity pose moved by `motion`: every vertex is exactly `motion · p`.
        let world: Vec<Isometry3<f64>> = scene
            .skeleton
            .rest_world_from_joint()
            .iter()
            .map(|w| motion * w)
            .collect();
        let skinning = scene.skeleton.skinning_transforms(&world).unwrap();
        for (name, method) in METHODS {
            let skinned = method(&scene.positions, None, &scene.weights, &skinning).unwrap();
            let expected: Vec<[f64; 3]> = scene
                .positions
                .iter()
                .map(|p| array(&(motion * point(p)).coords))
                .collect();
            let error = max_distance(&skinned.positions, &expected);
            assert!(error < 1e-12, "{name}: {error}");
        }
    }

    #[test]
    fn twist_180_candy_wrapper_lbs_collapses_dqs_keeps_volume() {
        let scene = scene();
        let rest_volume = signed_volume(&scene.positions, &scene.triangles).unwrap();
        let rest_radius = middle_ring_radius(&scene.positions);
        let twist = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI);
        let skinning = skinning_for(&scene.skeleton, &[UnitQuaternion::identity(), twist]);
        let normals = cylinder_normals(&scene.positions);
        let lbs =
            skin_linear_blend(&scene.positions, Some(&normals), &scene.weights, &skinning).unwrap();
        let dqs = skin_dual_quaternion(&scene.positions, Some(&normals), &scene.weights, &skinning)
            .unwrap();
        let lbs_ratio = signed_volume(&lbs.positions, &scene.triangles).unwrap() / rest_volume;
        let dqs_ratio = signed_volume(&dqs.positions, &scene.triangles).unwrap() / rest_volume;
        let lbs_radius = middle_ring_radius(&lbs.positions);
        let dqs_radius = middle_ring_radius(&dqs.positions);
        println!(
            "180° twist ({RINGS}x{SEGMENTS}, r={RADIUS}, blend width {BLEND_WIDTH}): \
             LBS volume ratio {lbs_ratio:.6}, middle radius {lbs_radius:.3e}; \
             DQS volume ratio {dqs_ratio:.6}, middle radius {dqs_radius:.6} (rest {rest_radius:.6})"
        );
        assert!(
            lbs_ratio < 0.8,
            "LBS should lose > 20 % volume: {lbs_ratio}"
        );
        assert!(lbs_radius < 1e-3 * RADIUS, "LBS middle radius {lbs_radius}");
        assert!(
            (dqs_ratio - 1.0).abs() < 0.05,
            "DQS volume ratio {dqs_ratio}"
        );
        assert!(
            (dqs_radius - rest_radius).abs() < 1e-9,
            "DQS middle radius {dqs_radius} vs {rest_radius}"
        );
        // No NaN anywhere, including LBS normals on the collapsed ring.
        for skinned in [&lbs, &dqs] {
            assert!(skinned.positions.iter().flatten().all(|v| v.is_finite()));
            assert!(
                skinned
                    .normals
                    .as_ref()
                    .unwrap()
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite())
            );
        }
    }

    #[test]
    fn bend_90_lbs_loses_more_volume_than_dqs() {
        let scene = scene();
        let rest_volume = signed_volume(&scene.positions, &scene.triangles).unwrap();
        let bend = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), FRAC_PI_2);
        let skinning = skinning_for(&scene.skeleton, &[UnitQuaternion::identity(), bend]);
        let lbs = skin_linear_blend(&scene.positions, None, &scene.weights, &skinning).unwrap();
        let dqs = skin_dual_quaternion(&scene.positions, None, &scene.weights, &skinning).unwrap();
        let lbs_ratio = signed_volume(&lbs.positions, &scene.triangles).unwrap() / rest_volume;
        let dqs_ratio = signed_volume(&dqs.positions, &scene.triangles).unwrap() / rest_volume;
        println!("90° bend: LBS volume ratio {lbs_ratio:.6}; DQS volume ratio {dqs_ratio:.6}");
        assert!(lbs_ratio < dqs_ratio);
        assert!((1.0 - lbs_ratio) > 2.0 * (1.0 - dqs_ratio).abs());
        // The tip cap centre follows joint 1 exactly (weight 1 there).
        let tip = scene.positions.len() - 1;
        let expected = skinning[1] * point(&scene.positions[tip]);
        for skinned in [&lbs, &dqs] {
            assert!((vector(&skinned.positions[tip]) - expected.coords).norm() < 1e-12);
        }
    }

    fn sample_isometry() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(1.5, -0.25, 4.0),
            UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::new(0.2, 1.0, -0.7)),
                2.8,
            ),
        )
    }

    #[test]
    fn dual_quaternion_round_trip_and_point_transform() {
        let iso = sample_isometry();
        let dq = DualQuaternion::from_isometry(&iso);
        let back = dq.to_isometry().unwrap();
        assert!((back.translation.vector - iso.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&iso.rotation) < 1e-12);
        let p = Point3::new(0.3, -1.2, 2.2);
        assert!((dq.transform_point(&p) - iso * p).norm() < 1e-12);
        // A scaled (non-unit) dual quaternion normalizes back to the same one.
        let scaled = dq.scale(3.7).normalize().unwrap();
        assert!((scaled.real - dq.real).norm() < 1e-12);
        assert!((scaled.dual - dq.dual).norm() < 1e-12);
        assert!(dq.scale(0.0).normalize().is_none());
        let identity = DualQuaternion::identity().to_isometry().unwrap();
        assert!(identity.translation.vector.norm() == 0.0 && identity.rotation.angle() == 0.0);
    }

    #[test]
    fn dqs_of_single_joint_equals_rigid_transform() {
        let iso = sample_isometry();
        let positions = vec![[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-4.0, 0.5, 0.25]];
        let normals = vec![[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [1.0, 0.0, 0.0]];
        // Vertex 0 fully on joint 1; vertices 1, 2 blend joints that share the
        // same transform (blending identical transforms must be that transform).
        let weights = SkinWeights::new(
            vec![
                vec![(1, 1.0)],
                vec![(0, 0.3), (1, 0.7)],
                vec![(0, 0.5), (1, 0.5)],
            ],
            2,
        )
        .unwrap();
        let skinned =
            skin_dual_quaternion(&positions, Some(&normals), &weights, &[iso, iso]).unwrap();
        for (k, p) in positions.iter().enumerate() {
            let expected = iso * point(p);
            assert!((vector(&skinned.positions[k]) - expected.coords).norm() < 1e-12);
            let expected_normal = iso.rotation * vector(&normals[k]);
            let normal = vector(&skinned.normals.as_ref().unwrap()[k]);
            assert!((normal - expected_normal).norm() < 1e-12);
        }
        // LBS and rigid agree in this case too.
        for method in [skin_linear_blend as SkinFn, skin_rigid] {
            let other = method(&positions, Some(&normals), &weights, &[iso, iso]).unwrap();
            assert!(max_distance(&other.positions, &skinned.positions) < 1e-12);
        }
    }

    #[test]
    fn antipodal_quaternions_give_the_same_result() {
        let a = sample_isometry();
        let b = Isometry3::from_parts(
            Translation3::new(-1.0, 0.5, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.9),
        );
        // Same rigid transform as `b`, stored with the negated quaternion.
        let b_negated = Isometry3::from_parts(
            b.translation,
            UnitQuaternion::new_unchecked(-b.rotation.into_inner()),
        );
        let positions = vec![[0.5, 0.5, 0.5], [1.0, -1.0, 2.0], [3.0, 0.0, -2.0]];
        let weights = SkinWeights::new(
            vec![
                vec![(0, 0.5), (1, 0.5)],
                vec![(0, 0.2), (1, 0.8)],
                vec![(0, 0.9), (1, 0.1)],
            ],
            2,
        )
        .unwrap();
        let plain = skin_dual_quaternion(&positions, None, &weights, &[a, b]).unwrap();
        let negated = skin_dual_quaternion(&positions, None, &weights, &[a, b_negated]).unwrap();
        assert!(max_distance(&plain.positions, &negated.positions) < 1e-12);
        // And negating the pivot too changes nothing.
        let a_negated = Isometry3::from_parts(
            a.translation,
            UnitQuaternion::new_unchecked(-a.rotation.into_inner()),
        );
        let both = skin_dual_quaternion(&positions, None, &weights, &[a_negated, b]).unwrap();
        assert!(max_distance(&plain.positions, &both.positions) < 1e-12);
        // Without sign alignment the blend of q and −q would differ wildly:
        // check the result is a sensible rigid blend (between the two images).
        let pa = a * point(&positions[0]);
        let pb = b * point(&positions[0]);
        let mid = vector(&plain.positions[0]);
        assert!((mid - pa.coords).norm() < (pa - pb).norm() + 1e-9);
    }

    #[test]
    fn blend_shapes_are_linear_in_weights() {
        let base = vec![[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]];
        let d1 = vec![[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
        let d2 = vec![[0.0, 0.0, -1.0], [0.5, 0.5, 0.5]];
        let deltas = vec![d1.clone(), d2.clone()];
        let out = apply_blend_shapes(&base, &deltas, &[0.25, -2.0]).unwrap();
        for v in 0..2 {
            for k in 0..3 {
                let expected = base[v][k] + 0.25 * d1[v][k] - 2.0 * d2[v][k];
                assert!((out[v][k] - expected).abs() < 1e-15);
            }
        }
        assert_eq!(
            apply_blend_shapes(&base, &deltas, &[0.0, 0.0]).unwrap(),
            base
        );
        assert_eq!(apply_blend_shapes(&base, &[], &[]).unwrap(), base);
        assert!(matches!(
            apply_blend_shapes(&base, &deltas, &[1.0]),
            Err(AnimateError::LengthMismatch { .. })
        ));
        assert!(matches!(
            apply_blend_shapes(&base, &[vec![[0.0; 3]]], &[1.0]),
            Err(AnimateError::LengthMismatch { .. })
        ));
        assert!(apply_blend_shapes(&base, &deltas, &[f64::NAN, 0.0]).is_err());
    }

    #[test]
    fn weights_validation_and_normalization() {
        let weights =
            SkinWeights::new(vec![vec![(2, 1.0), (0, 3.0), (2, 1.0), (1, 0.0)]], 3).unwrap();
        assert_eq!(weights.influences(0), &[(0, 0.6), (2, 0.4)]);
        assert_eq!(weights.dominant_joint(0), Some(0));
        assert_eq!(weights.dominant_joint(5), None);
        let capped = SkinWeights::with_max_influences(
            vec![vec![(0, 0.1), (1, 0.5), (2, 0.3), (3, 0.1)]],
            4,
            Some(2),
        )
        .unwrap();
        let influences = capped.influences(0);
        assert_eq!(influences.len(), 2);
        assert_eq!(influences[0].0, 1);
        assert_eq!(influences[1].0, 2);
        assert!((influences[0].1 - 0.625).abs() < 1e-15);
        assert!((influences[1].1 - 0.375).abs() < 1e-15);
        assert!(matches!(
            SkinWeights::new(vec![vec![(0, 0.0)]], 1),
            Err(AnimateError::ZeroWeightSum { vertex: 0 })
        ));
        assert!(matches!(
            SkinWeights::new(vec![vec![(0, 1.0)], vec![]], 1),
            Err(AnimateError::ZeroWeightSum { vertex: 1 })
        ));
        assert!(matches!(
            SkinWeights::new(vec![vec![(0, -0.5), (1, 1.0)]], 2),
            Err(AnimateError::NegativeWeight { .. })
        ));
        assert!(matches!(
            SkinWeights::new(vec![vec![(3, 1.0)]], 2),
            Err(AnimateError::JointIndexOutOfRange { index: 3, count: 2 })
        ));
        assert!(SkinWeights::new(vec![vec![(0, f64::INFINITY)]], 1).is_err());
        assert!(SkinWeights::with_max_influences(vec![], 1, Some(0)).is_err());
    }

    #[test]
    fn skinning_rejects_mismatched_inputs() {
        let weights = SkinWeights::new(vec![vec![(0, 1.0)], vec![(1, 1.0)]], 2).unwrap();
        let positions = [[0.0; 3], [1.0, 0.0, 0.0]];
        let transforms = [Isometry3::identity(); 2];
        for (_, method) in METHODS {
            assert!(matches!(
                method(&positions[..1], None, &weights, &transforms),
                Err(AnimateError::LengthMismatch { .. })
            ));
            assert!(matches!(
                method(&positions, Some(&positions[..1]), &weights, &transforms),
                Err(AnimateError::LengthMismatch { .. })
            ));
            assert!(matches!(
                method(&positions, None, &weights, &transforms[..1]),
                Err(AnimateError::JointCountMismatch { .. })
            ));
            let mut bad = transforms;
            bad[1].translation.vector.y = f64::NAN;
            assert!(matches!(
                method(&positions, None, &weights, &bad),
                Err(AnimateError::NonFinite { .. })
            ));
            assert!(
                method(
                    &[[f64::NAN, 0.0, 0.0], [0.0; 3]],
                    None,
                    &weights,
                    &transforms
                )
                .is_err()
            );
        }
    }

    #[test]
    fn lbs_normals_use_inverse_transpose() {
        // A 75/25 blend of the identity and a half turn about x gives the
        // anisotropic blended matrix diag(1, 0.5, 0.5). The normal (1, 1, 0)/√2
        // must map along A⁻ᵀ n ∝ (1, 2, 0), not along A n ∝ (1, 0.5, 0).
        let half_turn = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 2.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI),
        );
        let weights = SkinWeights::new(vec![vec![(0, 0.75), (1, 0.25)]], 2).unwrap();
        let n = std::f64::consts::FRAC_1_SQRT_2;
        let skinned = skin_linear_blend(
            &[[0.0; 3]],
            Some(&[[n, n, 0.0]]),
            &weights,
            &[Isometry3::identity(), half_turn],
        )
        .unwrap();
        let expected = Vector3::new(1.0, 2.0, 0.0).normalize();
        let normal = vector(&skinned.normals.unwrap()[0]);
        assert!((normal - expected).norm() < 1e-12, "{normal} vs {expected}");
        assert!((skinned.positions[0][2] - 0.5).abs() < 1e-15);
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

        #[test]
        fn random_skinning_is_finite_and_dqs_is_rigid_per_joint(
            log_scale in -3.0f64..4.0,
            joint_params in proptest::collection::vec(
                (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0, -PI..PI, -1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
                1..5,
            ),
            vertex_params in proptest::collection::vec(
                ((-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0), proptest::collection::vec((0usize..8, 0.0f64..1.0), 1..5)),
                2..12,
            ),
        ) {
            let scale = 10f64.powf(log_scale);
            let joint_count = joint_params.len();
            let world_from_bind: Vec<Isometry3<f64>> = joint_params
                .iter()
                .map(|&(ax, ay, az, angle, tx, ty, tz)| {
                    let axis = Vector3::new(ax, ay, az + 1e-3);
                    Isometry3::from_parts(
                        Translation3::new(tx * scale, ty * scale, tz * scale),
                        UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle),
                    )
                })
                .collect();
            let positions: Vec<[f64; 3]> = vertex_params
                .iter()
                .map(|((x, y, z), _)| [x * scale, y * scale, z * scale])
                .collect();
            let normals: Vec<[f64; 3]> = positions
                .iter()
                .map(|p| {
                    let n = vector(p);
                    let len = n.norm();
                    if len > 0.0 { array(&(n / len)) } else { [1.0, 0.0, 0.0] }
                })
                .collect();
            let per_vertex: Vec<Vec<(usize, f64)>> = vertex_params
                .iter()
                .map(|(_, influences)| {
                    let mut list: Vec<(usize, f64)> = influences
                        .iter()
                        .map(|&(j, w)| (j % joint_count, w))
                        .collect();
                    list[0].1 += 1e-3; // keep the sum positive
                    list
                })
                .collect();
            let weights = SkinWeights::new(per_vertex, joint_count).unwrap();
            for (name, method) in METHODS {
                let skinned = method(&positions, Some(&normals), &weights, &world_from_bind).unwrap();
                prop_assert!(skinned.positions.iter().flatten().all(|v| v.is_finite()), "{} positions", name);
                prop_assert!(skinned.normals.unwrap().iter().flatten().all(|v| v.is_finite()), "{} normals", name);
            }
            // Vertices bound only to joint 0 move rigidly under DQS.
            let single = SkinWeights::new(vec![vec![(0, 1.0)]; positions.len()], joint_count).unwrap();
            let skinned = skin_dual_quaternion(&positions, None, &single, &world_from_bind).unwrap();
            for i in 0..positions.len() {
                for j in i + 1..positions.len() {
                    let before = (vector(&positions[i]) - vector(&positions[j])).norm();
                    let after = (vector(&skinned.positions[i]) - vector(&skinned.positions[j])).norm();
                    prop_assert!((before - after).abs() <= 1e-12 * scale * 10.0, "{} vs {}", before, after);
                }
            }
        }
    }
}
