//! `render.trace`: a Whitted ray tracer and a Kajiya path tracer over a [`Scene`].
//!
//! **Geometry.** Every mesh object is transformed to world space (uniform scale, then
//! `world_from_object`; normals rotated) and merged into one triangle mesh with a per-triangle
//! object index, under one BVH ([`build_bvh`], watertight f32 traversal from [`super::bvh`]).
//! Analytic shapes are intersected exactly in f64: spheres and planes are transformed to world
//! space once (centre, radius, point, normal and in-plane axes), quadrics get the ray
//! transformed into object space instead (the ray parameter `t` is the same in both spaces, so
//! hits compare directly). Area lights are one-sided emitting parallelograms: camera and BSDF
//! rays hit them (black on the back), and they cast shadows.
//!
//! **Self-intersection.** Mesh hit points are computed from barycentrics in f32 and pushed off
//! the surface along the geometric normal by Wächter & Binder's integer-ULP offset (Ray Tracing
//! Gems ch. 6, 2019), matched to the f32 BVH. Analytic hit points are first projected back onto
//! the surface (sphere radius, plane distance, one Newton step on the quadric) and then offset
//! by `2⁻⁴⁰` times the coordinate magnitude of the point and the shape (≈ 4000 f64 ULPs: far
//! above the rounding of the re-intersection, far below any visible scale); both work at 10⁵
//! and beyond.
//!
//! **Materials.** One BSDF serves both integrators: a convex mix of a Lambertian base with
//! weight `(1 − metalness)(1 − transmission)`, a GGX conductor with weight `metalness` (Walter
//! et al. 2007; Schlick Fresnel with `F0 = albedo`; height-correlated Smith G2; `α =
//! roughness²`, a perfect mirror when `α < 10⁻³`), and a smooth dielectric with weight
//! `(1 − metalness)·transmission` (exact Fresnel, Snell refraction, total internal reflection,
//! transmission tinted by `albedo` and scaled by `1/η²` for radiance; every dielectric surface
//! separates air, on its front side, from the material, so nested dielectrics are not tracked
//! as media). A metalness-0 opaque
//! material is purely Lambertian (there is no dielectric coat), so an albedo-1 surface
//! conserves energy exactly. Textures (albedo, normal, roughness, metalness, emission) are
//! point-sampled with [`TextureSampler::sample`] at the hit's uv (the filter of the texture
//! applies at level 0, no mip selection). Emission is one-sided (front face).
//!
//! **Integrators.** `whitted` (Whitted 1980): emission, direct lighting from point,
//! directional and area lights with shadow rays through the non-delta lobes (an area light is
//! sampled once per camera sample, uniformly on the parallelogram), recursion into perfect
//! mirrors and dielectrics up to `max_depth` levels, skipping branches that carry less than
//! 10⁻⁶ of the pixel (Hall & Greenberg 1983); diffuse surfaces do not gather environment light.
//! `path` (Kajiya 1986): cosine-weighted diffuse sampling (Malley), GGX visible-normal sampling
//! (Heitz 2018), next-event estimation to every point, directional and area light (one sample
//! each), the power heuristic between light and BSDF sampling for area lights (Veach 1997);
//! emissive surfaces and the environment are reached by BSDF sampling only (weight 1), i.e. the
//! environment is sampled with the BSDF's own distribution (cosine-weighted on diffuse
//! surfaces); Russian roulette from `rr_depth` with survival `clamp(max(throughput), 0.05,
//! 0.95)`.
//!
//! **Sampling.** Every (pixel, sample) has its own counter-based random stream (a SplitMix64
//! hash of `seed`, pixel index, sample index and draw counter), so images are bit-identical for
//! any thread count; 16×16 tiles run in parallel.

use std::f64::consts::PI;
use std::sync::Arc;

use ocellus_engine::value::{
    Channels, Image, Light, Material, Mesh, PixelData, Pose, Scene, Shape, Texture,
};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value, param_enum,
    params,
};
use rayon::prelude::*;

use super::bsdf::{
    Frame, Vec3, add, concentric_disk, cosine_hemisphere, cross, dot, fresnel_dielectric,
    fresnel_schlick, ggx_reflection_brdf, ggx_reflection_pdf, ggx_sample_visible_normal, length,
    madd, mul, normalize, orthonormal_basis, power_heuristic, reflect, refract, scale, sub,
};
use super::bvh::{self, BvhOptions, build_bvh};
use super::scene::View;
use super::texture::TextureSampler;

/// Side of the square pixel tiles traced as one parallel work item.
const TILE: usize = 16;

/// Below this GGX `α` the metal lobe is a perfect mirror.
const MIN_ALPHA: f64 = 1e-3;

/// Whitted branches contributing less than this fraction of the pixel are not traced.
const WHITTED_MIN_WEIGHT: f64 = 1e-6;

/// Relative offset of analytic hit points (`2⁻⁴⁰` of the coordinate magnitude).
const ANALYTIC_OFFSET: f64 = 1.0 / (1u64 << 40) as f64;

// ---------------------------------------------------------------------------------------------
// Random numbers.

#[inline]
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// A counter-based random stream for one (pixel, sample): draw `k` is a SplitMix64 hash
/// (Steele, Lea & Flood 2014) of the stream key and `k`, the key a hash of seed, pixel and
/// sample. No state is shared between streams, so results do not depend on scheduling.
#[derive(Debug, Clone)]
pub struct SampleRng {
    key: u64,
    counter: u64,
}

impl SampleRng {
    /// The stream of sample `sample` of pixel `pixel` under `seed`.
    pub fn new(seed: u64, pixel: u64, sample: u64) -> SampleRng {
        let k = mix64(seed ^ 0x5851_F42D_4C95_7F2D);
        let k = mix64(k ^ pixel.wrapping_mul(GOLDEN));
        let k = mix64(k ^ sample.wrapping_mul(0xD1B5_4A32_D192_ED03));
        SampleRng { key: k, counter: 0 }
    }

    /// The next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.counter = self.counter.wrapping_add(1);
        mix64(self.key ^ mix64(self.counter.wrapping_mul(GOLDEN)))
    }

    /// A uniform number in `[0, 1)` (53 bits).
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

// ---------------------------------------------------------------------------------------------
// Ray origin offsets.

/// Wächter & Binder's offset of an f32 hit point `p` along the unit normal `n` (the side the
/// new ray leaves on): each coordinate moves by `256 · n_k` units in the last place (integer
/// arithmetic on the float bits), or by `n_k / 65536` within `1/32` of the origin where ULPs
/// vanish ("A fast and robust method for avoiding self-intersection", Ray Tracing Gems 2019).
pub fn offset_ray_origin(p: [f32; 3], n: [f32; 3]) -> [f32; 3] {
    const ORIGIN: f32 = 1.0 / 32.0;
    const FLOAT_SCALE: f32 = 1.0 / 65536.0;
    const INT_SCALE: f32 = 256.0;
    std::array::from_fn(|k| {
        if p[k].abs() < ORIGIN {
            p[k] + FLOAT_SCALE * n[k]
        } else {
            let of = (INT_SCALE * n[k]) as i32;
            let bits = p[k].to_bits() as i32;
            let moved = if p[k] < 0.0 {
                bits.wrapping_sub(of)
            } else {
                bits.wrapping_add(of)
            };
            f32::from_bits(moved as u32)
        }
    })
}

fn max_abs(p: Vec3) -> f64 {
    p[0].abs().max(p[1].abs()).max(p[2].abs())
}

/// Offset of an f64 analytic hit point along the unit normal `n` by `2⁻⁴⁰ · (|p|∞ + magnitude)`
/// (`magnitude`: the shape's own coordinate scale, e.g. `|centre|∞ + radius`).
fn offset_analytic(p: Vec3, n: Vec3, magnitude: f64) -> Vec3 {
    let eps = ANALYTIC_OFFSET * (max_abs(p) + magnitude).max(f64::MIN_POSITIVE);
    madd(p, n, eps)
}

// ---------------------------------------------------------------------------------------------
// Analytic intersections.

/// Roots of `a t² + 2 β t + c = 0` (the half-`b` form) in increasing order, computed without
/// cancellation (`q = −(β + sign(β) √Δ)`, `t = c/q` and `q/a`); `disc` is `β² − a c` computed by
/// the caller (possibly in a more accurate form).
fn stable_roots(a: f64, beta: f64, c: f64, disc: f64) -> Option<(f64, f64)> {
    if disc < 0.0 || !disc.is_finite() || a == 0.0 {
        return None;
    }
    let q = -(beta + disc.sqrt().copysign(beta));
    if q == 0.0 {
        // β = 0 and Δ = 0: a double root at −β/a = 0.
        return Some((0.0, 0.0));
    }
    let (t0, t1) = (c / q, q / a);
    Some(if t0 <= t1 { (t0, t1) } else { (t1, t0) })
}

/// Nearest `t ∈ (t_min, t_max)` where `o + t d` meets the sphere, for any nonzero `d`. The
/// discriminant is computed as `a (r² − |f − (f·d / a) d|²)` with `f = o − c` and the near root
/// as `c/q` (Haines, Günther, Akenine-Möller & Pharr, "Precision improvements for ray/sphere
/// intersection", Ray Tracing Gems 2019), accurate for a unit sphere 10⁵ away and for grazing
/// rays; a ray from inside hits the far side.
pub fn intersect_sphere(
    o: Vec3,
    d: Vec3,
    center: Vec3,
    radius: f64,
    t_min: f64,
    t_max: f64,
) -> Option<f64> {
    let f = sub(o, center);
    let a = dot(d, d);
    if a == 0.0 {
        return None;
    }
    let beta = dot(f, d);
    let l = madd(f, d, -beta / a);
    let disc = a * (radius * radius - dot(l, l));
    let c = dot(f, f) - radius * radius;
    let (t0, t1) = stable_roots(a, beta, c, disc)?;
    [t0, t1].into_iter().find(|&t| t > t_min && t < t_max)
}

/// `t ∈ (t_min, t_max)` where `o + t d` meets the plane through `point` with unit `normal`,
/// within the square `|(p − point)·tangent| ≤ half_extent`, `|(p − point)·bitangent| ≤
/// half_extent` (any `half_extent` for an infinite plane is `+∞`), with the in-plane
/// coordinates. Rays parallel to the plane miss.
#[allow(clippy::too_many_arguments)]
pub fn intersect_plane(
    o: Vec3,
    d: Vec3,
    point: Vec3,
    normal: Vec3,
    tangent: Vec3,
    bitangent: Vec3,
    half_extent: f64,
    t_min: f64,
    t_max: f64,
) -> Option<(f64, [f64; 2])> {
    let denom = dot(normal, d);
    if denom == 0.0 {
        return None;
    }
    let t = dot(normal, sub(point, o)) / denom;
    if !(t > t_min && t < t_max) {
        return None;
    }
    let q = sub(madd(o, d, t), point);
    let uv = [dot(q, tangent), dot(q, bitangent)];
    (uv[0].abs() <= half_extent && uv[1].abs() <= half_extent).then_some((t, uv))
}

/// The symmetric 4×4 matrix of a quadric's upper triangle
/// `[q00, q01, q02, q03, q11, q12, q13, q22, q23, q33]`: its 3×3 block (row-major), the linear
/// column `(q03, q13, q23)` and `q33`.
fn quadric_parts(q: &[f64; 10]) -> ([f64; 9], Vec3, f64) {
    (
        [q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7]],
        [q[3], q[6], q[8]],
        q[9],
    )
}

fn mat3_mul(m: &[f64; 9], v: Vec3) -> Vec3 {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    ]
}

fn mat3_mul_transposed(m: &[f64; 9], v: Vec3) -> Vec3 {
    [
        m[0] * v[0] + m[3] * v[1] + m[6] * v[2],
        m[1] * v[0] + m[4] * v[1] + m[7] * v[2],
        m[2] * v[0] + m[5] * v[1] + m[8] * v[2],
    ]
}

/// `(x, 1)ᵀ Q (x, 1)` of a quadric.
pub fn quadric_value(q: &[f64; 10], p: Vec3) -> f64 {
    let (m, l, c) = quadric_parts(q);
    dot(p, mat3_mul(&m, p)) + 2.0 * dot(l, p) + c
}

/// The gradient `2 (Q₃ x + l)` of a quadric at `p` (the outward normal direction of an
/// ellipsoid written with `q33 < 0`).
pub fn quadric_gradient(q: &[f64; 10], p: Vec3) -> Vec3 {
    let (m, l, _) = quadric_parts(q);
    scale(add(mat3_mul(&m, p), l), 2.0)
}

/// Nearest `t ∈ (t_min, t_max)` where `o + t d` meets the quadric `(x,1)ᵀ Q (x,1) = 0` inside
/// the box `min`–`max` (inclusive): the roots of `(dᵀQ₃d) t² + 2 (dᵀQ₃o + lᵀd) t + F(o) = 0`,
/// stable form, a linear equation when the quadratic term vanishes, tested in increasing order
/// against the box.
pub fn intersect_quadric(
    o: Vec3,
    d: Vec3,
    q: &[f64; 10],
    min: Vec3,
    max: Vec3,
    t_min: f64,
    t_max: f64,
) -> Option<f64> {
    let (m, l, c0) = quadric_parts(q);
    let md = mat3_mul(&m, d);
    let mo = mat3_mul(&m, o);
    let a = dot(d, md);
    let beta = dot(d, mo) + dot(l, d);
    let c = dot(o, mo) + 2.0 * dot(l, o) + c0;
    let roots = if a == 0.0 {
        if beta == 0.0 {
            return None;
        }
        let t = -c / (2.0 * beta);
        (t, t)
    } else {
        stable_roots(a, beta, c, beta * beta - a * c)?
    };
    let inside = |t: f64| {
        let p = madd(o, d, t);
        (0..3).all(|k| p[k] >= min[k] && p[k] <= max[k])
    };
    [roots.0, roots.1]
        .into_iter()
        .find(|&t| t > t_min && t < t_max && inside(t))
}

/// `(t, s, u)` where `o + t d` meets the parallelogram `corner + s·edge_u + u·edge_v`,
/// `s, u ∈ [0, 1]`, `t ∈ (t_min, t_max)` (two-sided).
pub fn intersect_parallelogram(
    o: Vec3,
    d: Vec3,
    corner: Vec3,
    edge_u: Vec3,
    edge_v: Vec3,
    t_min: f64,
    t_max: f64,
) -> Option<(f64, f64, f64)> {
    let n = cross(edge_u, edge_v);
    let denom = dot(n, d);
    if denom == 0.0 {
        return None;
    }
    let t = dot(n, sub(corner, o)) / denom;
    if !(t > t_min && t < t_max) {
        return None;
    }
    let q = sub(madd(o, d, t), corner);
    let nn = dot(n, n);
    let s = dot(cross(q, edge_v), n) / nn;
    let u = dot(cross(edge_u, q), n) / nn;
    ((0.0..=1.0).contains(&s) && (0.0..=1.0).contains(&u)).then_some((t, s, u))
}

/// Texture coordinates of a unit direction in an object frame: `u` the longitude about +y,
/// `v = 1 − θ/π` with `θ` the polar angle from +y (so `v = 1` at the north pole, the top row
/// of an OBJ-convention texture), matching the equirectangular environment lookup.
pub fn direction_uv(w: Vec3) -> [f64; 2] {
    let u = 0.5 + w[0].atan2(-w[2]) / (2.0 * PI);
    let v = 1.0 - w[1].clamp(-1.0, 1.0).acos() / PI;
    [u, v]
}

/// The object-frame tangent `∂w/∂u` (unnormalized direction of increasing [`direction_uv`]
/// `u`) and bitangent `∂w/∂v` of a unit direction; `None` at the poles.
fn direction_uv_frame(w: Vec3) -> Option<(Vec3, Vec3)> {
    let t = normalize([-w[2], 0.0, w[0]])?;
    // Increasing v moves towards +y along the meridian.
    let b = normalize(madd([0.0, 1.0, 0.0], w, -w[1]))?;
    Some((t, b))
}

// ---------------------------------------------------------------------------------------------
// The traceable scene.

#[derive(Debug, Clone)]
enum Analytic {
    Sphere {
        center: Vec3,
        radius: f64,
        /// Object-to-world rotation (row-major), for texture coordinates.
        rotation: [f64; 9],
    },
    Plane {
        point: Vec3,
        normal: Vec3,
        tangent: Vec3,
        bitangent: Vec3,
        half_extent: f64,
    },
    Quadric {
        coefficients: [f64; 10],
        min: Vec3,
        max: Vec3,
        rotation: [f64; 9],
        translation: Vec3,
        scale: f64,
    },
}

#[derive(Debug, Clone)]
struct AnalyticObject {
    object: u32,
    shape: Analytic,
}

#[derive(Debug, Clone)]
struct AreaLight {
    corner: Vec3,
    edge_u: Vec3,
    edge_v: Vec3,
    normal: Vec3,
    area: f64,
    radiance: Vec3,
}

#[derive(Debug, Clone)]
struct ObjectInfo {
    material: u32,
    has_normals: bool,
    has_uvs: bool,
}

struct Environment {
    radiance: Vec3,
    map: Option<TextureSampler>,
}

struct MaterialSamplers {
    material: Material,
    albedo: Option<TextureSampler>,
    normal: Option<TextureSampler>,
    roughness: Option<TextureSampler>,
    metalness: Option<TextureSampler>,
    emission: Option<TextureSampler>,
}

/// A scene ready for ray tracing: one BVH over all mesh triangles in world space (with their
/// object indices), the analytic shapes in world space, lights, environment and materials with
/// their texture samplers.
pub struct TraceScene {
    bvh: Option<ocellus_engine::value::Bvh>,
    triangle_object: Vec<u32>,
    objects: Vec<ObjectInfo>,
    analytic: Vec<AnalyticObject>,
    area_lights: Vec<AreaLight>,
    point_lights: Vec<(Vec3, Vec3)>,
    directional_lights: Vec<(Vec3, Vec3)>,
    environment: Vec<Environment>,
    materials: Vec<MaterialSamplers>,
    background: Vec3,
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|c| c.is_finite())
}

fn rgb(c: [f32; 3]) -> Vec3 {
    c.map(f64::from)
}

fn check_radiance(what: &str, c: [f32; 3]) -> Result<Vec3, String> {
    if c.iter().all(|v| v.is_finite() && *v >= 0.0) {
        Ok(rgb(c))
    } else {
        Err(format!("{what} must be finite and ≥ 0, got {c:?}"))
    }
}

fn sampler(t: &Option<Texture>, what: &str) -> Result<Option<TextureSampler>, String> {
    t.as_ref()
        .map(|t| TextureSampler::new(t).map_err(|e| format!("{what}: {e}")))
        .transpose()
}

fn check_material(i: usize, m: &Material) -> Result<(), String> {
    let name = if m.name.is_empty() {
        format!("material {i}")
    } else {
        format!("material {i} (`{}`)", m.name)
    };
    if !m.albedo.iter().all(|v| (0.0..=1.0).contains(v)) {
        return Err(format!(
            "{name}: albedo must be in [0, 1], got {:?}",
            m.albedo
        ));
    }
    for (field, v) in [
        ("roughness", m.roughness),
        ("metalness", m.metalness),
        ("transmission", m.transmission),
    ] {
        if !(0.0..=1.0).contains(&v) {
            return Err(format!("{name}: {field} must be in [0, 1], got {v}"));
        }
    }
    if !(m.ior.is_finite() && m.ior > 0.0) {
        return Err(format!("{name}: ior must be finite and > 0, got {}", m.ior));
    }
    check_radiance(&format!("{name}: emission"), m.emission)?;
    Ok(())
}

fn pose_parts(pose: &Pose, scale: f64, what: &str) -> Result<([f64; 9], Vec3), String> {
    if !(pose.rotation.iter().all(|v| v.is_finite()) && finite3(&pose.translation)) {
        return Err(format!("{what}: the pose must be finite"));
    }
    if !(scale.is_finite() && scale > 0.0) {
        return Err(format!("{what}: scale must be finite and > 0, got {scale}"));
    }
    Ok((pose.rotation_matrix(), pose.translation))
}

impl TraceScene {
    /// Validates `scene` and prepares it for tracing; `background` is the radiance of escaping
    /// rays when the scene has no environment light. Errors name the offending object, light
    /// or material: non-finite or out-of-range vertices, indices, normals, poses, scales, shape
    /// parameters, light parameters or material parameters, a material index out of range, a
    /// texture that cannot be sampled.
    pub fn new(scene: &Scene, background: [f64; 3]) -> Result<TraceScene, String> {
        if !background.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(format!(
                "`background` must be finite and ≥ 0, got {background:?}"
            ));
        }
        let mut materials = Vec::with_capacity(scene.materials.len());
        for (i, m) in scene.materials.iter().enumerate() {
            check_material(i, m)?;
            let what = |t: &str| format!("material {i} {t} texture");
            materials.push(MaterialSamplers {
                material: m.clone(),
                albedo: sampler(&m.albedo_texture, &what("albedo"))?,
                normal: sampler(&m.normal_texture, &what("normal"))?,
                roughness: sampler(&m.roughness_texture, &what("roughness"))?,
                metalness: sampler(&m.metalness_texture, &what("metalness"))?,
                emission: sampler(&m.emission_texture, &what("emission"))?,
            });
        }
        if scene.objects.len() > u32::MAX as usize {
            return Err("too many objects".into());
        }
        let mut merged = Mesh::default();
        let mut normals: Vec<[f32; 3]> = Vec::new();
        let mut uvs: Vec<[f32; 2]> = Vec::new();
        let any_normals = scene
            .objects
            .iter()
            .any(|o| matches!(&o.shape, Shape::Mesh(m) if m.normals.is_some()));
        let any_uvs = scene
            .objects
            .iter()
            .any(|o| matches!(&o.shape, Shape::Mesh(m) if m.uvs.is_some()));
        let mut triangle_object = Vec::new();
        let mut objects = Vec::with_capacity(scene.objects.len());
        let mut analytic = Vec::new();
        for (index, o) in scene.objects.iter().enumerate() {
            let what = if o.name.is_empty() {
                format!("object {index}")
            } else {
                format!("object {index} (`{}`)", o.name)
            };
            if o.material as usize >= scene.materials.len() {
                return Err(format!(
                    "{what}: material index {} is out of range ({} materials)",
                    o.material,
                    scene.materials.len()
                ));
            }
            let (r, t) = pose_parts(&o.world_from_object, o.scale, &what)?;
            let s = o.scale;
            let to_world = |p: Vec3| add(mat3_mul(&r, scale(p, s)), t);
            let mut info = ObjectInfo {
                material: o.material,
                has_normals: false,
                has_uvs: false,
            };
            match &o.shape {
                Shape::Mesh(mesh) => {
                    let base = merged.positions.len();
                    if base + mesh.positions.len() > u32::MAX as usize {
                        return Err(format!("{what}: too many vertices in the scene"));
                    }
                    for (i, p) in mesh.positions.iter().enumerate() {
                        if !p.iter().all(|v| v.is_finite()) {
                            return Err(format!(
                                "{what}: vertex {i} has a non-finite coordinate {p:?}"
                            ));
                        }
                        let w = to_world(p.map(f64::from)).map(|v| v as f32);
                        if !w.iter().all(|v| v.is_finite()) {
                            return Err(format!(
                                "{what}: vertex {i} overflows f32 in world space ({p:?})"
                            ));
                        }
                        merged.positions.push(w);
                    }
                    let nv = mesh.positions.len();
                    for (i, tri) in mesh.triangles.iter().enumerate() {
                        if let Some(&bad) = tri.iter().find(|&&k| k as usize >= nv) {
                            return Err(format!(
                                "{what}: triangle {i} refers to vertex {bad}, but the mesh has {nv} vertices"
                            ));
                        }
                        merged.triangles.push(tri.map(|k| k + base as u32));
                        triangle_object.push(index as u32);
                    }
                    if any_normals {
                        match &mesh.normals {
                            Some(ns) if ns.len() == nv => {
                                for (i, n) in ns.iter().enumerate() {
                                    if !n.iter().all(|v| v.is_finite()) {
                                        return Err(format!(
                                            "{what}: normal {i} is not finite ({n:?})"
                                        ));
                                    }
                                    let w = mat3_mul(&r, n.map(f64::from));
                                    let w = normalize(w).unwrap_or([0.0; 3]);
                                    normals.push(w.map(|v| v as f32));
                                }
                                info.has_normals = true;
                            }
                            Some(ns) => {
                                return Err(format!(
                                    "{what}: {} normals for {nv} vertices",
                                    ns.len()
                                ));
                            }
                            None => normals.extend(std::iter::repeat_n([0.0f32; 3], nv)),
                        }
                    }
                    if any_uvs {
                        match &mesh.uvs {
                            Some(us) if us.len() == nv => {
                                if let Some((i, uv)) = us
                                    .iter()
                                    .enumerate()
                                    .find(|(_, uv)| !uv.iter().all(|v| v.is_finite()))
                                {
                                    return Err(format!(
                                        "{what}: texture coordinate {i} is not finite ({uv:?})"
                                    ));
                                }
                                uvs.extend_from_slice(us);
                                info.has_uvs = true;
                            }
                            Some(us) => {
                                return Err(format!(
                                    "{what}: {} texture coordinates for {nv} vertices",
                                    us.len()
                                ));
                            }
                            None => uvs.extend(std::iter::repeat_n([0.0f32; 2], nv)),
                        }
                    }
                }
                Shape::Sphere { center, radius } => {
                    if !(finite3(center) && radius.is_finite() && *radius > 0.0) {
                        return Err(format!(
                            "{what}: a sphere needs a finite centre and radius > 0, got {center:?}, {radius}"
                        ));
                    }
                    analytic.push(AnalyticObject {
                        object: index as u32,
                        shape: Analytic::Sphere {
                            center: to_world(*center),
                            radius: radius * s,
                            rotation: r,
                        },
                    });
                }
                Shape::Plane {
                    point,
                    normal,
                    half_extent,
                } => {
                    let n = normalize(*normal).filter(|_| finite3(point));
                    let Some(n) = n.filter(|_| *half_extent > 0.0) else {
                        return Err(format!(
                            "{what}: a plane needs a finite point, a nonzero finite normal and half_extent > 0 (+inf allowed), got {point:?}, {normal:?}, {half_extent}"
                        ));
                    };
                    let (tu, tv) = orthonormal_basis(n);
                    analytic.push(AnalyticObject {
                        object: index as u32,
                        shape: Analytic::Plane {
                            point: to_world(*point),
                            normal: mat3_mul(&r, n),
                            tangent: mat3_mul(&r, tu),
                            bitangent: mat3_mul(&r, tv),
                            half_extent: half_extent * s,
                        },
                    });
                }
                Shape::Quadric {
                    coefficients,
                    min,
                    max,
                } => {
                    let ok = coefficients.iter().all(|v| v.is_finite())
                        && coefficients.iter().any(|v| *v != 0.0)
                        && (0..3).all(|k| !min[k].is_nan() && !max[k].is_nan() && min[k] <= max[k]);
                    if !ok {
                        return Err(format!(
                            "{what}: a quadric needs finite, not all zero coefficients and a clip box with min ≤ max, got {coefficients:?}, {min:?}–{max:?}"
                        ));
                    }
                    analytic.push(AnalyticObject {
                        object: index as u32,
                        shape: Analytic::Quadric {
                            coefficients: *coefficients,
                            min: *min,
                            max: *max,
                            rotation: r,
                            translation: t,
                            scale: s,
                        },
                    });
                }
            }
            objects.push(info);
        }
        if any_normals {
            merged.normals = Some(normals);
        }
        if any_uvs {
            merged.uvs = Some(uvs);
        }
        let bvh = if merged.triangles.is_empty() {
            None
        } else {
            Some(build_bvh(Arc::new(merged), &BvhOptions::default()).map_err(|e| e.to_string())?)
        };
        let mut area_lights = Vec::new();
        let mut point_lights = Vec::new();
        let mut directional_lights = Vec::new();
        let mut environment = Vec::new();
        for (i, light) in scene.lights.iter().enumerate() {
            let what = format!("light {i}");
            match light {
                Light::Point {
                    position,
                    intensity,
                } => {
                    if !finite3(position) {
                        return Err(format!("{what}: position must be finite"));
                    }
                    let i = check_radiance(&format!("{what}: intensity"), *intensity)?;
                    point_lights.push((*position, i));
                }
                Light::Directional {
                    direction,
                    irradiance,
                } => {
                    let d = normalize(*direction).ok_or_else(|| {
                        format!("{what}: direction must be finite and nonzero, got {direction:?}")
                    })?;
                    let e = check_radiance(&format!("{what}: irradiance"), *irradiance)?;
                    directional_lights.push((d, e));
                }
                Light::Area {
                    corner,
                    edge_u,
                    edge_v,
                    radiance,
                } => {
                    if !(finite3(corner) && finite3(edge_u) && finite3(edge_v)) {
                        return Err(format!("{what}: corner and edges must be finite"));
                    }
                    let n = cross(*edge_u, *edge_v);
                    let area = length(n);
                    let normal = normalize(n).filter(|_| area > 0.0).ok_or_else(|| {
                        format!("{what}: the edges of an area light must not be parallel or zero")
                    })?;
                    let l = check_radiance(&format!("{what}: radiance"), *radiance)?;
                    area_lights.push(AreaLight {
                        corner: *corner,
                        edge_u: *edge_u,
                        edge_v: *edge_v,
                        normal,
                        area,
                        radiance: l,
                    });
                }
                Light::Environment { radiance, map } => {
                    let l = check_radiance(&format!("{what}: radiance"), *radiance)?;
                    environment.push(Environment {
                        radiance: l,
                        map: sampler(map, &format!("{what}: map"))?,
                    });
                }
            }
        }
        Ok(TraceScene {
            bvh,
            triangle_object,
            objects,
            analytic,
            area_lights,
            point_lights,
            directional_lights,
            environment,
            materials,
            background,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Hits.

/// What a ray hit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HitTarget {
    /// A scene object and its material (indices into the scene's lists).
    Object {
        /// Object index.
        object: u32,
        /// Material index.
        material: u32,
    },
    /// An area light (index among the scene's area lights, in light order).
    AreaLight(u32),
}

/// A ray–surface hit record.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceHit {
    /// Ray parameter (distance for a unit direction).
    pub t: f64,
    /// World position.
    pub position: Vec3,
    /// Unit geometric normal on the front side (counter-clockwise winding for meshes, outward
    /// for spheres, the given normal for planes, the gradient for quadrics, `edge_u × edge_v`
    /// for area lights).
    pub geometric_normal: Vec3,
    /// Unit shading normal (interpolated vertex normals where the mesh has them, else the
    /// geometric normal), on the geometric normal's side.
    pub shading_normal: Vec3,
    /// Texture coordinates.
    pub uv: [f64; 2],
    /// Unit tangent along increasing `u`, orthogonal to the shading normal.
    pub tangent: Vec3,
    /// Unit bitangent along increasing `v`, orthogonal to the shading normal and tangent.
    pub bitangent: Vec3,
    /// What was hit.
    pub target: HitTarget,
    /// Origin for rays leaving on the front side (offset off the surface).
    pub origin_front: Vec3,
    /// Origin for rays leaving on the back side.
    pub origin_back: Vec3,
}

impl SurfaceHit {
    /// Origin of a new ray leaving the surface along `direction`.
    #[inline]
    pub fn spawn_origin(&self, direction: Vec3) -> Vec3 {
        if dot(direction, self.geometric_normal) >= 0.0 {
            self.origin_front
        } else {
            self.origin_back
        }
    }

    /// The object index, if an object was hit.
    pub fn object(&self) -> Option<u32> {
        match self.target {
            HitTarget::Object { object, .. } => Some(object),
            HitTarget::AreaLight(_) => None,
        }
    }
}

enum Candidate {
    Triangle(bvh::Hit),
    Analytic(usize, f64, [f64; 2]),
    Light(usize, f64, f64, f64),
}

fn tangent_frame(n: Vec3, tangent: Option<Vec3>, bitangent: Option<Vec3>) -> (Vec3, Vec3) {
    let frame = Frame::new(n, tangent.unwrap_or([0.0; 3]));
    // Keep the texture's handedness: the bitangent points along increasing v.
    let sign = match bitangent {
        Some(b) if dot(b, frame.b) < 0.0 => -1.0,
        _ => 1.0,
    };
    (frame.t, scale(frame.b, sign))
}

impl TraceScene {
    /// Nearest hit of the ray `origin + t · direction` (unit direction), `t ∈ (0, t_max)`;
    /// area lights are included when `lights` is set.
    pub fn intersect(
        &self,
        origin: Vec3,
        direction: Vec3,
        t_max: f64,
        lights: bool,
    ) -> Option<SurfaceHit> {
        let mut best: Option<Candidate> = None;
        let mut t_best = t_max;
        if let Some(b) = &self.bvh {
            let ray = bvh::Ray {
                origin: origin.map(|v| v as f32),
                direction: direction.map(|v| v as f32),
                t_min: 0.0,
                t_max: t_best as f32,
            };
            if let Some(hit) = bvh::intersect(b, &ray) {
                t_best = f64::from(hit.t);
                best = Some(Candidate::Triangle(hit));
            }
        }
        for (i, a) in self.analytic.iter().enumerate() {
            if let Some((t, uv)) = intersect_analytic(&a.shape, origin, direction, t_best) {
                t_best = t;
                best = Some(Candidate::Analytic(i, t, uv));
            }
        }
        if lights {
            for (i, l) in self.area_lights.iter().enumerate() {
                if let Some((t, s, u)) = intersect_parallelogram(
                    origin, direction, l.corner, l.edge_u, l.edge_v, 0.0, t_best,
                ) {
                    t_best = t;
                    best = Some(Candidate::Light(i, t, s, u));
                }
            }
        }
        match best? {
            Candidate::Triangle(hit) => self.triangle_hit(&hit),
            Candidate::Analytic(i, t, uv) => Some(self.analytic_hit(i, origin, direction, t, uv)),
            Candidate::Light(i, t, s, u) => {
                let l = &self.area_lights[i];
                let p = add(l.corner, add(scale(l.edge_u, s), scale(l.edge_v, u)));
                let magnitude = max_abs(l.corner) + max_abs(l.edge_u) + max_abs(l.edge_v);
                let (tangent, bitangent) = tangent_frame(l.normal, Some(l.edge_u), Some(l.edge_v));
                Some(SurfaceHit {
                    t,
                    position: p,
                    geometric_normal: l.normal,
                    shading_normal: l.normal,
                    uv: [s, u],
                    tangent,
                    bitangent,
                    target: HitTarget::AreaLight(i as u32),
                    origin_front: offset_analytic(p, l.normal, magnitude),
                    origin_back: offset_analytic(p, scale(l.normal, -1.0), magnitude),
                })
            }
        }
    }

    /// Whether anything (objects and area lights) blocks `origin + t · direction` for
    /// `t ∈ (0, t_max)`.
    pub fn occluded(&self, origin: Vec3, direction: Vec3, t_max: f64) -> bool {
        if let Some(b) = &self.bvh {
            let ray = bvh::Ray {
                origin: origin.map(|v| v as f32),
                direction: direction.map(|v| v as f32),
                t_min: 0.0,
                t_max: t_max as f32,
            };
            if bvh::occluded(b, &ray) {
                return true;
            }
        }
        self.analytic
            .iter()
            .any(|a| intersect_analytic(&a.shape, origin, direction, t_max).is_some())
            || self.area_lights.iter().any(|l| {
                intersect_parallelogram(origin, direction, l.corner, l.edge_u, l.edge_v, 0.0, t_max)
                    .is_some()
            })
    }

    fn triangle_hit(&self, hit: &bvh::Hit) -> Option<SurfaceHit> {
        let b = self.bvh.as_ref()?;
        let mesh = &b.mesh;
        let tri = *mesh.triangles.get(hit.triangle as usize)?;
        let object = *self.triangle_object.get(hit.triangle as usize)?;
        let info = self.objects.get(object as usize)?;
        let [v0, v1, v2] = tri.map(|k| mesh.positions[k as usize]);
        let (b1, b2) = (hit.u, hit.v);
        let b0 = 1.0 - b1 - b2;
        // The hit point from barycentrics in f32 (Wächter & Binder), not origin + t·d.
        let p32: [f32; 3] = std::array::from_fn(|k| b0 * v0[k] + b1 * v1[k] + b2 * v2[k]);
        let w = |v: [f32; 3]| v.map(f64::from);
        let (p0, p1, p2) = (w(v0), w(v1), w(v2));
        let e1 = sub(p1, p0);
        let e2 = sub(p2, p0);
        let ng = normalize(cross(e1, e2))?;
        let ng32 = ng.map(|v| v as f32);
        let front = offset_ray_origin(p32, ng32);
        let back = offset_ray_origin(p32, ng32.map(|v| -v));
        let (b0, b1, b2) = (f64::from(b0), f64::from(b1), f64::from(b2));
        let mut ns = ng;
        if info.has_normals
            && let Some(normals) = &mesh.normals
        {
            let [n0, n1, n2] = tri.map(|k| w(normals[k as usize]));
            let n = add(add(scale(n0, b0), scale(n1, b1)), scale(n2, b2));
            if let Some(n) = normalize(n).filter(|n| dot(*n, ng) > 0.0) {
                ns = n;
            }
        }
        let mut uv = [0.0, 0.0];
        let mut dpdu = None;
        let mut dpdv = None;
        if info.has_uvs
            && let Some(uvs) = &mesh.uvs
        {
            let [t0, t1, t2] = tri.map(|k| uvs[k as usize].map(f64::from));
            uv = [
                b0 * t0[0] + b1 * t1[0] + b2 * t2[0],
                b0 * t0[1] + b1 * t1[1] + b2 * t2[1],
            ];
            // Lengyel's tangent from the uv gradients of the triangle.
            let (du1, dv1) = (t1[0] - t0[0], t1[1] - t0[1]);
            let (du2, dv2) = (t2[0] - t0[0], t2[1] - t0[1]);
            let det = du1 * dv2 - du2 * dv1;
            if det != 0.0 && det.is_finite() {
                let r = 1.0 / det;
                dpdu = Some(scale(sub(scale(e1, dv2), scale(e2, dv1)), r));
                dpdv = Some(scale(sub(scale(e2, du1), scale(e1, du2)), r));
            }
        }
        let (tangent, bitangent) = tangent_frame(ns, dpdu, dpdv);
        Some(SurfaceHit {
            t: f64::from(hit.t),
            position: w(p32),
            geometric_normal: ng,
            shading_normal: ns,
            uv,
            tangent,
            bitangent,
            target: HitTarget::Object {
                object,
                material: info.material,
            },
            origin_front: w(front),
            origin_back: w(back),
        })
    }

    fn analytic_hit(&self, i: usize, o: Vec3, d: Vec3, t: f64, uv: [f64; 2]) -> SurfaceHit {
        let a = &self.analytic[i];
        let info = &self.objects[a.object as usize];
        let target = HitTarget::Object {
            object: a.object,
            material: info.material,
        };
        let p = madd(o, d, t);
        let (p, n, uv, tangent, bitangent, magnitude) = match &a.shape {
            Analytic::Sphere {
                center,
                radius,
                rotation,
            } => {
                let n = normalize(sub(p, *center)).unwrap_or(scale(d, -1.0));
                let p = madd(*center, n, *radius);
                let w = mat3_mul_transposed(rotation, n);
                let (t_obj, b_obj) = direction_uv_frame(w).unzip();
                let (tangent, bitangent) = tangent_frame(
                    n,
                    t_obj.map(|v| mat3_mul(rotation, v)),
                    b_obj.map(|v| mat3_mul(rotation, v)),
                );
                (
                    p,
                    n,
                    direction_uv(w),
                    tangent,
                    bitangent,
                    max_abs(*center) + radius,
                )
            }
            Analytic::Plane {
                point,
                normal,
                tangent,
                bitangent,
                ..
            } => {
                let p = madd(p, *normal, -dot(sub(p, *point), *normal));
                (p, *normal, uv, *tangent, *bitangent, max_abs(*point))
            }
            Analytic::Quadric {
                coefficients,
                rotation,
                translation,
                scale: s,
                ..
            } => {
                let to_obj =
                    |x: Vec3| scale(mat3_mul_transposed(rotation, sub(x, *translation)), 1.0 / s);
                let mut po = to_obj(p);
                // One Newton step back onto the surface along the gradient.
                let g = quadric_gradient(coefficients, po);
                let g2 = dot(g, g);
                if g2 > 0.0 {
                    let step = quadric_value(coefficients, po) / g2;
                    if step.is_finite() {
                        po = madd(po, g, -step);
                    }
                }
                let g = quadric_gradient(coefficients, po);
                let n = normalize(mat3_mul(rotation, g)).unwrap_or(scale(d, -1.0));
                let pw = add(mat3_mul(rotation, scale(po, *s)), *translation);
                let dir = normalize(po).unwrap_or([0.0, 1.0, 0.0]);
                let (t_obj, b_obj) = direction_uv_frame(dir).unzip();
                let (tangent, bitangent) = tangent_frame(
                    n,
                    t_obj.map(|v| mat3_mul(rotation, v)),
                    b_obj.map(|v| mat3_mul(rotation, v)),
                );
                (
                    pw,
                    n,
                    direction_uv(dir),
                    tangent,
                    bitangent,
                    max_abs(*translation) + s * max_abs(po),
                )
            }
        };
        SurfaceHit {
            t,
            position: p,
            geometric_normal: n,
            shading_normal: n,
            uv,
            tangent,
            bitangent,
            target,
            origin_front: offset_analytic(p, n, magnitude),
            origin_back: offset_analytic(p, scale(n, -1.0), magnitude),
        }
    }

    /// Radiance arriving along `direction` from infinitely far away: the sum of the
    /// environment lights (radiance × map), or the background when there are none.
    pub fn escaped(&self, direction: Vec3) -> Vec3 {
        if self.environment.is_empty() {
            return self.background;
        }
        let mut l = [0.0; 3];
        for e in &self.environment {
            let m = match &e.map {
                Some(map) => {
                    let c = map.sample_direction(direction);
                    [c[0], c[1], c[2]].map(f64::from)
                }
                None => [1.0; 3],
            };
            l = add(l, mul(e.radiance, m));
        }
        l
    }
}

fn intersect_analytic(shape: &Analytic, o: Vec3, d: Vec3, t_max: f64) -> Option<(f64, [f64; 2])> {
    match shape {
        Analytic::Sphere { center, radius, .. } => {
            intersect_sphere(o, d, *center, *radius, 0.0, t_max).map(|t| (t, [0.0; 2]))
        }
        Analytic::Plane {
            point,
            normal,
            tangent,
            bitangent,
            half_extent,
        } => intersect_plane(
            o,
            d,
            *point,
            *normal,
            *tangent,
            *bitangent,
            *half_extent,
            0.0,
            t_max,
        ),
        Analytic::Quadric {
            coefficients,
            min,
            max,
            rotation,
            translation,
            scale: s,
        } => {
            let oo = scale(mat3_mul_transposed(rotation, sub(o, *translation)), 1.0 / s);
            let od = scale(mat3_mul_transposed(rotation, d), 1.0 / s);
            intersect_quadric(oo, od, coefficients, *min, *max, 0.0, t_max).map(|t| (t, [0.0; 2]))
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Materials and the BSDF.

/// Material parameters at a surface point, textures applied.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadingPoint {
    /// Base colour.
    pub albedo: Vec3,
    /// Roughness.
    pub roughness: f64,
    /// Metalness.
    pub metalness: f64,
    /// Transmission.
    pub transmission: f64,
    /// Index of refraction.
    pub ior: f64,
    /// Emitted radiance.
    pub emission: Vec3,
    /// Shading normal after normal mapping (front side).
    pub normal: Vec3,
    /// Tangent of the shading frame.
    pub tangent: Vec3,
}

fn tex(s: &Option<TextureSampler>, uv: [f64; 2]) -> Option<[f64; 4]> {
    s.as_ref()
        .map(|s| s.sample([uv[0] as f32, uv[1] as f32]).map(f64::from))
}

impl TraceScene {
    /// The material of a hit object evaluated at the hit (textures point-sampled at its uv;
    /// the normal map perturbs the shading normal in the hit's tangent frame). `None` for area
    /// light hits.
    pub fn shading_point(&self, hit: &SurfaceHit) -> Option<ShadingPoint> {
        let HitTarget::Object { material, .. } = hit.target else {
            return None;
        };
        let m = self.materials.get(material as usize)?;
        let mat = &m.material;
        let uv = hit.uv;
        let mut albedo = rgb(mat.albedo);
        if let Some(c) = tex(&m.albedo, uv) {
            albedo = mul(albedo, [c[0], c[1], c[2]]);
        }
        let mut roughness = f64::from(mat.roughness);
        if let Some(c) = tex(&m.roughness, uv) {
            roughness *= c[0];
        }
        let mut metalness = f64::from(mat.metalness);
        if let Some(c) = tex(&m.metalness, uv) {
            metalness *= c[0];
        }
        let mut emission = rgb(mat.emission);
        if let Some(c) = tex(&m.emission, uv) {
            emission = mul(emission, [c[0], c[1], c[2]]);
        }
        let mut normal = hit.shading_normal;
        if let Some(c) = tex(&m.normal, uv) {
            let local = [2.0 * c[0] - 1.0, 2.0 * c[1] - 1.0, 2.0 * c[2] - 1.0];
            let n = add(
                add(scale(hit.tangent, local[0]), scale(hit.bitangent, local[1])),
                scale(hit.shading_normal, local[2]),
            );
            if let Some(n) = normalize(n).filter(|n| dot(*n, hit.geometric_normal) > 0.0) {
                normal = n;
            }
        }
        let clamp01 = |v: f64| {
            if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                0.0
            }
        };
        Some(ShadingPoint {
            albedo: albedo.map(clamp01),
            roughness: clamp01(roughness),
            metalness: clamp01(metalness),
            transmission: f64::from(mat.transmission),
            ior: f64::from(mat.ior),
            emission: emission.map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 }),
            normal,
            tangent: hit.tangent,
        })
    }
}

/// The BSDF at a shading point, seen from `wo`: the convex mix of Lambertian, GGX conductor
/// and smooth dielectric lobes (see the module documentation).
#[derive(Debug, Clone, Copy)]
pub struct Bsdf {
    frame: Frame,
    ng: Vec3,
    albedo: Vec3,
    w_diffuse: f64,
    w_metal: f64,
    w_glass: f64,
    alpha: f64,
    /// `η_t / η_i` for light crossing from `wo`'s side to the other.
    eta: f64,
}

/// A sampled BSDF direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BsdfSample {
    /// The new direction (unit, world).
    pub wi: Vec3,
    /// Throughput factor: `f·|cos θ_i| / pdf` (for a delta lobe, the lobe's reflectance or
    /// transmittance).
    pub weight: Vec3,
    /// Solid-angle density of the non-delta mixture, 0 for a delta lobe.
    pub pdf: f64,
    /// Whether a delta lobe (mirror, dielectric) was sampled.
    pub delta: bool,
}

impl Bsdf {
    /// The BSDF for light leaving towards `wo` (unit, world).
    pub fn new(sp: &ShadingPoint, hit: &SurfaceHit, wo: Vec3) -> Bsdf {
        let front = dot(wo, hit.geometric_normal) >= 0.0;
        let sign = if front { 1.0 } else { -1.0 };
        let ng = scale(hit.geometric_normal, sign);
        let mut ns = scale(sp.normal, sign);
        if dot(ns, ng) <= 0.0 {
            ns = ng;
        }
        let m = sp.metalness;
        let tr = sp.transmission;
        Bsdf {
            frame: Frame::new(ns, sp.tangent),
            ng,
            albedo: sp.albedo,
            w_diffuse: (1.0 - m) * (1.0 - tr),
            w_metal: m,
            w_glass: (1.0 - m) * tr,
            alpha: sp.roughness * sp.roughness,
            eta: if front { sp.ior } else { 1.0 / sp.ior },
        }
    }

    fn metal_is_delta(&self) -> bool {
        self.alpha < MIN_ALPHA
    }

    /// Whether any non-delta lobe has weight (light sampling can contribute).
    pub fn has_non_delta(&self) -> bool {
        self.w_diffuse > 0.0 || (self.w_metal > 0.0 && !self.metal_is_delta())
    }

    /// `f(wo, wi)·|cos θ_i|` (shading cosine) of the non-delta lobes and their sampling density.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> (Vec3, f64) {
        if dot(wi, self.ng) <= 0.0 || dot(wo, self.ng) < 0.0 {
            return ([0.0; 3], 0.0);
        }
        let wo_l = self.frame.to_local(wo);
        let wi_l = self.frame.to_local(wi);
        if wi_l[2] <= 0.0 {
            return ([0.0; 3], 0.0);
        }
        let mut f = [0.0; 3];
        let mut pdf = 0.0;
        if self.w_diffuse > 0.0 {
            f = madd(f, self.albedo, self.w_diffuse * wi_l[2] / PI);
            pdf += self.w_diffuse * wi_l[2] / PI;
        }
        if self.w_metal > 0.0 && !self.metal_is_delta() {
            let brdf = ggx_reflection_brdf(wo_l, wi_l, self.alpha, self.albedo);
            f = madd(f, brdf, self.w_metal * wi_l[2]);
            pdf += self.w_metal * ggx_reflection_pdf(wo_l, wi_l, self.alpha);
        }
        (f, pdf)
    }

    fn non_delta_sample(&self, wo: Vec3, wi: Vec3) -> Option<BsdfSample> {
        let (f, pdf) = self.eval(wo, wi);
        (pdf > 0.0).then(|| BsdfSample {
            wi,
            weight: scale(f, 1.0 / pdf),
            pdf,
            delta: false,
        })
    }

    /// Mirror reflection about the shading normal, if it leaves on `wo`'s side.
    fn mirror(&self, wo: Vec3) -> Option<Vec3> {
        let wi = reflect(wo, self.frame.n);
        (dot(wi, self.ng) > 0.0).then_some(wi)
    }

    /// Fresnel reflectance of the metal lobe's mirror (Schlick with `F0 = albedo`).
    fn mirror_reflectance(&self, wo: Vec3) -> Vec3 {
        fresnel_schlick(self.albedo, dot(wo, self.frame.n))
    }

    /// The dielectric's reflectance towards the mirror direction, its refracted direction
    /// (`None` on total internal reflection or when it would leave on the wrong side) and the
    /// transmitted throughput `albedo / η²`.
    fn dielectric(&self, wo: Vec3) -> (f64, Option<Vec3>, Vec3) {
        let cos_o = dot(wo, self.frame.n).max(0.0);
        let f = fresnel_dielectric(cos_o, self.eta);
        let t = refract(wo, self.frame.n, self.eta).filter(|t| dot(*t, self.ng) < 0.0);
        let f = if t.is_none() { 1.0 } else { f };
        (f, t, scale(self.albedo, 1.0 / (self.eta * self.eta)))
    }

    /// Samples a lobe by its weight, then a direction in it: cosine-weighted (Malley) for the
    /// diffuse lobe, a GGX visible normal (Heitz 2018) for the metal, mirror/refraction by the
    /// Fresnel reflectance for the dielectric. `None` when the sample leaves on the wrong side.
    pub fn sample(&self, wo: Vec3, rng: &mut SampleRng) -> Option<BsdfSample> {
        let lobe = rng.next_f64();
        let (u1, u2) = (rng.next_f64(), rng.next_f64());
        if lobe < self.w_diffuse {
            let wi = self.frame.to_world(cosine_hemisphere(u1, u2));
            if dot(wi, self.ng) <= 0.0 {
                return None;
            }
            self.non_delta_sample(wo, wi)
        } else if lobe < self.w_diffuse + self.w_metal {
            if self.metal_is_delta() {
                let wi = self.mirror(wo)?;
                return Some(BsdfSample {
                    wi,
                    weight: self.mirror_reflectance(wo),
                    pdf: 0.0,
                    delta: true,
                });
            }
            let wo_l = self.frame.to_local(wo);
            if wo_l[2] <= 0.0 {
                return None;
            }
            let h = ggx_sample_visible_normal(wo_l, self.alpha, u1, u2);
            let wi_l = reflect(wo_l, h);
            if wi_l[2] <= 0.0 {
                return None;
            }
            let wi = self.frame.to_world(wi_l);
            self.non_delta_sample(wo, wi)
        } else if self.w_glass > 0.0 {
            let (f, t, transmitted) = self.dielectric(wo);
            if u1 < f {
                let wi = self.mirror(wo)?;
                Some(BsdfSample {
                    wi,
                    weight: [1.0; 3],
                    pdf: 0.0,
                    delta: true,
                })
            } else {
                let wi = t?;
                Some(BsdfSample {
                    wi,
                    weight: transmitted,
                    pdf: 0.0,
                    delta: true,
                })
            }
        } else {
            None
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Integrators.

param_enum! {
    /// Light transport algorithm of `render.trace`.
    pub enum Integrator {
        /// Kajiya path tracing with next-event estimation and MIS.
        Path = "path",
        /// Whitted ray tracing: direct light, mirrors, refraction.
        Whitted = "whitted",
    }
}

param_enum! {
    /// Tone curve applied to the colour output of `render.trace`.
    pub enum ToneMap {
        /// Linear radiance (times the exposure).
        None = "none",
        /// Reinhard et al. 2002 global operator `L/(1+L)` on luminance, colour scaled by it.
        Reinhard = "reinhard",
        /// Narkowicz's fitted ACES filmic curve, per channel, clamped to [0, 1].
        Aces = "aces",
    }
}

/// Settings of a render.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TraceOptions {
    /// Integrator.
    pub integrator: Integrator,
    /// Samples per pixel, 1..=65536.
    pub spp: u32,
    /// Most scattering events along a path (Whitted: reflection/refraction levels), 0..=64.
    pub max_depth: u32,
    /// Bounces before Russian roulette starts (path), 0..=64.
    pub rr_depth: u32,
    /// Seed of the random streams.
    pub seed: u64,
    /// Tone curve.
    pub tone_map: ToneMap,
    /// Exposure in stops (the radiance is multiplied by `2^exposure` before the curve).
    pub exposure: f64,
}

impl Default for TraceOptions {
    fn default() -> Self {
        TraceOptions {
            integrator: Integrator::Path,
            spp: 16,
            max_depth: 8,
            rr_depth: 3,
            seed: 0,
            tone_map: ToneMap::None,
            exposure: 0.0,
        }
    }
}

impl TraceOptions {
    /// Why the options are out of range, if they are.
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=65_536).contains(&self.spp) {
            return Err(format!("`spp` must be 1..=65536, got {}", self.spp));
        }
        if self.max_depth > 64 {
            return Err(format!(
                "`max_depth` must be 0..=64, got {}",
                self.max_depth
            ));
        }
        if self.rr_depth > 64 {
            return Err(format!("`rr_depth` must be 0..=64, got {}", self.rr_depth));
        }
        if !(self.exposure.is_finite() && self.exposure.abs() <= 64.0) {
            return Err(format!(
                "`exposure` must be finite within ±64 stops, got {}",
                self.exposure
            ));
        }
        Ok(())
    }
}

/// Luminance weights (Rec. 709 / sRGB primaries).
const LUMA: Vec3 = [0.2126, 0.7152, 0.0722];

/// Narkowicz's fit of the ACES filmic curve, `x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14)`
/// clamped to [0, 1] ("ACES filmic tone mapping curve", 2016), without the 0.6 pre-scale of
/// his note (use `exposure` for that).
pub fn aces_narkowicz(x: f64) -> f64 {
    let y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14);
    y.clamp(0.0, 1.0)
}

/// Exposure (`2^exposure`) then the tone curve.
pub fn tone_map(c: Vec3, mode: ToneMap, exposure: f64) -> Vec3 {
    let c = scale(c, exposure.exp2());
    match mode {
        ToneMap::None => c,
        ToneMap::Reinhard => {
            let l = dot(c, LUMA);
            if l > 0.0 {
                scale(c, 1.0 / (1.0 + l))
            } else {
                [0.0; 3]
            }
        }
        ToneMap::Aces => c.map(aces_narkowicz),
    }
}

fn is_zero(c: Vec3) -> bool {
    c == [0.0; 3]
}

struct Integration<'a> {
    scene: &'a TraceScene,
    options: &'a TraceOptions,
}

impl Integration<'_> {
    /// Direct light at a hit through the non-delta lobes: every point and directional light,
    /// one uniform sample on every area light (MIS-weighted against BSDF sampling with the
    /// power heuristic when `mis`).
    fn direct(
        &self,
        hit: &SurfaceHit,
        bsdf: &Bsdf,
        wo: Vec3,
        rng: &mut SampleRng,
        mis: bool,
    ) -> Vec3 {
        let s = self.scene;
        let p = hit.position;
        let mut l = [0.0; 3];
        for &(position, intensity) in &s.point_lights {
            let to = sub(position, p);
            let d2 = dot(to, to);
            let Some(wi) = normalize(to) else { continue };
            let (f, _) = bsdf.eval(wo, wi);
            if is_zero(f) {
                continue;
            }
            let o = hit.spawn_origin(wi);
            let to_o = sub(position, o);
            let dist = length(to_o);
            let Some(dir) = normalize(to_o) else { continue };
            if !s.occluded(o, dir, dist) {
                l = add(l, scale(mul(f, intensity), 1.0 / d2));
            }
        }
        for &(direction, irradiance) in &s.directional_lights {
            let wi = scale(direction, -1.0);
            let (f, _) = bsdf.eval(wo, wi);
            if is_zero(f) {
                continue;
            }
            let o = hit.spawn_origin(wi);
            if !s.occluded(o, wi, f64::INFINITY) {
                l = add(l, mul(f, irradiance));
            }
        }
        for light in &s.area_lights {
            let (u1, u2) = (rng.next_f64(), rng.next_f64());
            let y = add(
                light.corner,
                add(scale(light.edge_u, u1), scale(light.edge_v, u2)),
            );
            let to = sub(y, p);
            let d2 = dot(to, to);
            let Some(wi) = normalize(to) else { continue };
            let cos_l = -dot(wi, light.normal);
            if cos_l <= 0.0 {
                continue;
            }
            let (f, pdf_bsdf) = bsdf.eval(wo, wi);
            if is_zero(f) {
                continue;
            }
            let pdf_light = d2 / (light.area * cos_l);
            let o = hit.spawn_origin(wi);
            let to_o = sub(y, o);
            let Some(dir) = normalize(to_o) else { continue };
            if s.occluded(o, dir, length(to_o) * (1.0 - 1e-7)) {
                continue;
            }
            let w = if mis {
                power_heuristic(pdf_light, pdf_bsdf)
            } else {
                1.0
            };
            l = add(l, scale(mul(f, light.radiance), w / pdf_light));
        }
        l
    }

    fn front_emission(hit: &SurfaceHit, direction: Vec3, emission: Vec3) -> Vec3 {
        if dot(direction, hit.geometric_normal) < 0.0 {
            emission
        } else {
            [0.0; 3]
        }
    }

    /// Whitted radiance along a ray whose contribution to the pixel is scaled by `weight`
    /// (the largest channel of the product of reflectances and transmittances above it).
    /// Branches whose weight would fall below [`WHITTED_MIN_WEIGHT`] are not traced (Hall &
    /// Greenberg's adaptive tree-depth control, 1983), which bounds the otherwise exponential
    /// reflection/refraction tree.
    fn whitted(
        &self,
        origin: Vec3,
        direction: Vec3,
        depth: u32,
        weight: f64,
        rng: &mut SampleRng,
    ) -> Vec3 {
        let s = self.scene;
        let Some(hit) = s.intersect(origin, direction, f64::INFINITY, true) else {
            return s.escaped(direction);
        };
        let sp = match hit.target {
            HitTarget::AreaLight(i) => {
                let light = &s.area_lights[i as usize];
                return Self::front_emission(&hit, direction, light.radiance);
            }
            HitTarget::Object { .. } => match s.shading_point(&hit) {
                Some(sp) => sp,
                None => return [0.0; 3],
            },
        };
        let wo = scale(direction, -1.0);
        let mut l = Self::front_emission(&hit, direction, sp.emission);
        let bsdf = Bsdf::new(&sp, &hit, wo);
        if bsdf.has_non_delta() {
            l = add(l, self.direct(&hit, &bsdf, wo, rng, false));
        }
        if depth >= self.options.max_depth {
            return l;
        }
        let branch = |l: &mut Vec3, wi: Vec3, factor: Vec3, rng: &mut SampleRng| {
            let w = weight * factor[0].max(factor[1]).max(factor[2]);
            if w >= WHITTED_MIN_WEIGHT {
                let r = self.whitted(hit.spawn_origin(wi), wi, depth + 1, w, rng);
                *l = add(*l, mul(factor, r));
            }
        };
        if bsdf.w_metal > 0.0
            && bsdf.metal_is_delta()
            && let Some(wi) = bsdf.mirror(wo)
        {
            let factor = scale(bsdf.mirror_reflectance(wo), bsdf.w_metal);
            branch(&mut l, wi, factor, rng);
        }
        if bsdf.w_glass > 0.0 {
            let (f, t, transmitted) = bsdf.dielectric(wo);
            if f > 0.0
                && let Some(wi) = bsdf.mirror(wo)
            {
                branch(&mut l, wi, [bsdf.w_glass * f; 3], rng);
            }
            if let Some(wt) = t {
                branch(
                    &mut l,
                    wt,
                    scale(transmitted, bsdf.w_glass * (1.0 - f)),
                    rng,
                );
            }
        }
        l
    }

    /// Path-traced radiance along a camera ray.
    fn path(&self, origin: Vec3, direction: Vec3, rng: &mut SampleRng) -> Vec3 {
        let s = self.scene;
        let mut l = [0.0; 3];
        let mut beta = [1.0; 3];
        let (mut o, mut d) = (origin, direction);
        // Density of the BSDF sample that produced the current ray (None: camera or delta).
        let mut prev_pdf: Option<f64> = None;
        let mut bounce = 0u32;
        loop {
            let Some(hit) = s.intersect(o, d, f64::INFINITY, true) else {
                l = add(l, mul(beta, s.escaped(d)));
                break;
            };
            let sp = match hit.target {
                HitTarget::AreaLight(i) => {
                    let light = &s.area_lights[i as usize];
                    let le = Self::front_emission(&hit, d, light.radiance);
                    if !is_zero(le) {
                        let w = match prev_pdf {
                            None => 1.0,
                            Some(pdf_bsdf) => {
                                let cos_l = -dot(d, light.normal);
                                let pdf_light = hit.t * hit.t / (light.area * cos_l);
                                power_heuristic(pdf_bsdf, pdf_light)
                            }
                        };
                        l = add(l, scale(mul(beta, le), w));
                    }
                    break;
                }
                HitTarget::Object { .. } => match s.shading_point(&hit) {
                    Some(sp) => sp,
                    None => break,
                },
            };
            l = add(l, mul(beta, Self::front_emission(&hit, d, sp.emission)));
            if bounce >= self.options.max_depth {
                break;
            }
            let wo = scale(d, -1.0);
            let bsdf = Bsdf::new(&sp, &hit, wo);
            if bsdf.has_non_delta() {
                l = add(l, mul(beta, self.direct(&hit, &bsdf, wo, rng, true)));
            }
            let Some(sample) = bsdf.sample(wo, rng) else {
                break;
            };
            beta = mul(beta, sample.weight);
            bounce += 1;
            if bounce > self.options.rr_depth {
                let q = beta[0].max(beta[1]).max(beta[2]).clamp(0.05, 0.95);
                if rng.next_f64() >= q {
                    break;
                }
                beta = scale(beta, 1.0 / q);
            }
            if is_zero(beta) {
                break;
            }
            prev_pdf = (!sample.delta).then_some(sample.pdf);
            o = hit.spawn_origin(sample.wi);
            d = sample.wi;
        }
        l
    }

    fn radiance(&self, origin: Vec3, direction: Vec3, rng: &mut SampleRng) -> Vec3 {
        match self.options.integrator {
            Integrator::Whitted => self.whitted(origin, direction, 0, 1.0, rng),
            Integrator::Path => self.path(origin, direction, rng),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Rendering.

/// The images of a render, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct TraceImages {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// RGB radiance (after exposure and tone curve), 3 per pixel.
    pub color: Vec<f32>,
    /// Distance along the pixel-centre unit ray to the first object, `+∞` on a miss.
    pub depth: Vec<f32>,
    /// World-space shading normal of the first object at the pixel centre (normal map applied,
    /// front side, not flipped towards the camera), 0 on a miss; 3 per pixel.
    pub normals: Vec<f32>,
    /// Object index of the first hit at the pixel centre, −1 on a miss.
    pub ids: Vec<f32>,
    /// Pixel-centre primary ray origins, 3 per pixel.
    pub ray_origins: Vec<f32>,
    /// Pixel-centre primary ray unit directions, 3 per pixel.
    pub ray_directions: Vec<f32>,
    /// Pixels whose centre ray hit an object.
    pub hits: usize,
}

#[derive(Clone, Copy, Default)]
struct PixelOut {
    color: [f32; 3],
    depth: f32,
    normal: [f32; 3],
    id: f32,
    origin: [f32; 3],
    direction: [f32; 3],
    hit: bool,
}

/// Renders `scene` through `view`: `spp` samples per pixel, jittered in an `n × n` grid of
/// strata (`n = ⌊√spp⌋`; the remaining samples uniformly over the pixel), a thin-lens point per
/// sample from the concentric disk map (Shirley & Chiu 1997) when the view has an aperture;
/// the box-filtered mean radiance, then exposure and tone curve. The geometric outputs come
/// from the pixel-centre ray through the lens centre. 16×16 tiles run in parallel; the result
/// is the same for any thread count.
pub fn render_trace(
    scene: &TraceScene,
    view: &View,
    options: &TraceOptions,
) -> Result<TraceImages, String> {
    options.validate()?;
    let (w, h) = (view.width, view.height);
    let tiles_x = w.div_ceil(TILE);
    let tiles = tiles_x * h.div_ceil(TILE);
    let integration = Integration { scene, options };
    let spp = options.spp as usize;
    let strata = (spp as f64).sqrt().floor() as usize;
    let inv_spp = 1.0 / spp as f64;
    let traced: Vec<Vec<PixelOut>> = (0..tiles)
        .into_par_iter()
        .map(|tile| {
            let (x0, y0) = ((tile % tiles_x) * TILE, (tile / tiles_x) * TILE);
            let (x1, y1) = ((x0 + TILE).min(w), (y0 + TILE).min(h));
            let mut out = Vec::with_capacity((x1 - x0) * (y1 - y0));
            for y in y0..y1 {
                for x in x0..x1 {
                    let mut px = PixelOut {
                        depth: f32::INFINITY,
                        id: -1.0,
                        ..PixelOut::default()
                    };
                    let (o, d) = view.lens_ray(x as f64, y as f64, [0.0, 0.0]);
                    px.origin = o.map(|v| v as f32);
                    px.direction = d.map(|v| v as f32);
                    if let Some(hit) = scene.intersect(o, d, f64::INFINITY, false) {
                        px.hit = true;
                        px.depth = hit.t as f32;
                        px.id = hit.object().map_or(-1.0, |i| i as f32);
                        let n = scene
                            .shading_point(&hit)
                            .map_or(hit.shading_normal, |sp| sp.normal);
                        px.normal = n.map(|v| v as f32);
                    }
                    let pixel = (y * w + x) as u64;
                    let mut sum = [0.0; 3];
                    for s in 0..spp {
                        let mut rng = SampleRng::new(options.seed, pixel, s as u64);
                        let (jx, jy) = (rng.next_f64(), rng.next_f64());
                        let (jx, jy) = if s < strata * strata {
                            (
                                ((s % strata) as f64 + jx) / strata as f64,
                                ((s / strata) as f64 + jy) / strata as f64,
                            )
                        } else {
                            (jx, jy)
                        };
                        let lens = concentric_disk(rng.next_f64(), rng.next_f64());
                        let (o, d) = view.lens_ray(x as f64 + jx - 0.5, y as f64 + jy - 0.5, lens);
                        let l = integration.radiance(o, d, &mut rng);
                        // A non-finite sample (never expected) is dropped rather than
                        // poisoning the pixel.
                        if l.iter().all(|v| v.is_finite()) {
                            sum = add(sum, l);
                        }
                    }
                    let c = tone_map(scale(sum, inv_spp), options.tone_map, options.exposure);
                    px.color = c.map(|v| v as f32);
                    out.push(px);
                }
            }
            out
        })
        .collect();
    let n = w * h;
    let mut images = TraceImages {
        width: w,
        height: h,
        color: vec![0.0; 3 * n],
        depth: vec![f32::INFINITY; n],
        normals: vec![0.0; 3 * n],
        ids: vec![-1.0; n],
        ray_origins: vec![0.0; 3 * n],
        ray_directions: vec![0.0; 3 * n],
        hits: 0,
    };
    for (tile, pixels) in traced.iter().enumerate() {
        let (x0, y0) = ((tile % tiles_x) * TILE, (tile / tiles_x) * TILE);
        let tw = (x0 + TILE).min(w) - x0;
        for (k, px) in pixels.iter().enumerate() {
            let i = (y0 + k / tw) * w + x0 + k % tw;
            images.color[3 * i..3 * i + 3].copy_from_slice(&px.color);
            images.depth[i] = px.depth;
            images.normals[3 * i..3 * i + 3].copy_from_slice(&px.normal);
            images.ids[i] = px.id;
            images.ray_origins[3 * i..3 * i + 3].copy_from_slice(&px.origin);
            images.ray_directions[3 * i..3 * i + 3].copy_from_slice(&px.direction);
            images.hits += usize::from(px.hit);
        }
    }
    Ok(images)
}

/// Renders camera `camera` of `scene` (see [`TraceScene::new`] and [`render_trace`]).
pub fn trace_scene(
    scene: &Scene,
    camera: usize,
    background: [f64; 3],
    options: &TraceOptions,
) -> Result<TraceImages, String> {
    options.validate()?;
    let c = scene.cameras.get(camera).ok_or_else(|| {
        format!(
            "camera {camera} does not exist (the scene has {} cameras)",
            scene.cameras.len()
        )
    })?;
    let view = View::new(c)?;
    let prepared = TraceScene::new(scene, background)?;
    render_trace(&prepared, &view, options)
}

// ---------------------------------------------------------------------------------------------
// Operator.

params! {
    /// Parameters of [`Trace`].
    pub struct TraceParams {
        /// Index of the scene camera to render. Default 0.
        camera: u32 = 0,
        /// `path` (Kajiya path tracing, NEE + MIS) or `whitted`. Default `path`.
        integrator: Integrator = Integrator::Path,
        /// Samples per pixel, 1..=65536. Default 16.
        spp: u32 = 16 => [min = 1, max = 65536],
        /// Most scattering events per path (Whitted: reflection/refraction levels), 0..=64.
        /// Default 8.
        max_depth: u32 = 8 => [max = 64],
        /// Bounces before Russian roulette (path tracer), 0..=64. Default 3.
        rr_depth: u32 = 3 => [max = 64],
        /// Seed of the per-pixel random streams. Default 0.
        seed: u64 = 0,
        /// Tone curve of the colour output: `none`, `reinhard` or `aces`. Default `none`.
        tone_map: ToneMap = ToneMap::None,
        /// Exposure, stops (colour × 2^exposure before the curve). Default 0.
        exposure: f64 = 0.0 => [min = -64.0, max = 64.0, unit = "stops"],
        /// Radiance of escaping rays when the scene has no environment light, linear RGB.
        /// Default black.
        background: [f64; 3] = [0.0, 0.0, 0.0],
    }
}

/// `render.trace`. See [`render_trace`].
#[derive(Debug, Clone)]
pub struct Trace {
    camera: usize,
    background: [f64; 3],
    options: TraceOptions,
}

impl Op for Trace {
    type Params = TraceParams;
    const ID: &'static str = "render.trace";
    const SUMMARY: &'static str = "Ray traces a scene (Whitted or path tracing with NEE and MIS): colour, depth, normals, ids, rays.";
    const DOC: &'static str = r#"
Renders camera `camera` of `scene` by ray tracing. Mesh objects are merged in world space
under one BVH (watertight triangle test); spheres, planes and quadrics are intersected exactly
in f64 (Haines et al. 2019 for spheres). Ray origins are offset off surfaces with Wächter &
Binder's method (2019) for meshes and a magnitude-relative epsilon for analytic shapes.

Materials: a convex mix of Lambertian (weight (1−metalness)(1−transmission)), GGX conductor
(weight metalness; Walter et al. 2007, Schlick F0 = albedo, height-correlated Smith G2,
α = roughness², mirror below α = 1e-3) and smooth dielectric (weight (1−metalness)·transmission;
exact Fresnel, Snell, total internal reflection). Textures are point-sampled at the hit's uv.
Emission is one-sided. Area lights are one-sided emitting parallelograms that also block light.

`integrator: "whitted"` (Whitted 1980): emission, direct light from point, directional and
area lights (one area sample per camera sample) with shadow rays, mirror reflection and
refraction up to `max_depth` levels (branches carrying < 1e-6 of the pixel are skipped, Hall &
Greenberg 1983); escaping rays see the environment (or `background`).
`integrator: "path"` (Kajiya 1986): cosine-weighted diffuse and GGX visible-normal sampling
(Heitz 2018), next-event estimation to every light, the power heuristic (Veach 1997) between
light and BSDF sampling for area lights; emissive surfaces and the environment are found by
BSDF sampling; Russian roulette after `rr_depth` bounces with survival
clamp(max throughput, 0.05, 0.95); at most `max_depth` scattering events.

Pixels take `spp` stratified jittered samples (box filter) and, with an aperture, thin-lens
rays (concentric disk, Shirley & Chiu 1997). Random numbers are a counter-based hash of
`seed`, pixel and sample, so the images are bit-identical for any thread count. `exposure`
(stops) and `tone_map` (`none`, `reinhard` on luminance, `aces` Narkowicz fit per channel)
apply to `color` only; no sRGB encoding is applied.

Outputs: `color` (RGB f32), `depth` (f32 gray: distance along the pixel-centre unit ray to the
first object, +inf on a miss; comparable with render.raycast), `normals` (RGB f32 world
shading normal at the pixel centre, 0 on a miss), `ids` (f32 gray object index, −1 on a miss),
`ray_origins` and `ray_directions` (RGB f32 pixel-centre primary rays), `hits` (Integer: pixels
whose centre ray hit an object).

References: Whitted, "An improved illumination model for shaded display" (CACM 1980); Kajiya,
"The rendering equation" (SIGGRAPH 1986); Veach, PhD thesis (1997); Walter et al., "Microfacet
models for refraction through rough surfaces" (EGSR 2007); Heitz, "Sampling the GGX
distribution of visible normals" (JCGT 2018); Haines et al. and Wächter & Binder, Ray Tracing
Gems (2019); Reinhard et al., "Photographic tone reproduction" (SIGGRAPH 2002).

Example:
    "image": (op: "render.trace", inputs: { "scene": "scene.scene" },
              params: (integrator: "path", spp: 64, max_depth: 8, tone_map: "aces")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "scene",
            PortType::Scene,
            "Objects, materials, lights and cameras.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("color", PortType::Image, "RGB f32 radiance (tone-mapped)."),
            PortSpec::new(
                "depth",
                PortType::Image,
                "f32 gray: distance along the pixel-centre unit ray, +inf on a miss.",
            ),
            PortSpec::new(
                "normals",
                PortType::Image,
                "RGB f32 world-space shading normal, 0 on a miss.",
            ),
            PortSpec::new(
                "ids",
                PortType::Image,
                "f32 gray object index, −1 on a miss.",
            ),
            PortSpec::new(
                "ray_origins",
                PortType::Image,
                "RGB f32 pixel-centre primary ray origins.",
            ),
            PortSpec::new(
                "ray_directions",
                PortType::Image,
                "RGB f32 pixel-centre primary ray unit directions.",
            ),
            PortSpec::new(
                "hits",
                PortType::Integer,
                "Pixels whose centre ray hit an object.",
            ),
        ]
    }

    fn new(p: TraceParams) -> Result<Self, String> {
        let options = TraceOptions {
            integrator: p.integrator,
            spp: p.spp,
            max_depth: p.max_depth,
            rr_depth: p.rr_depth,
            seed: p.seed,
            tone_map: p.tone_map,
            exposure: p.exposure,
        };
        options.validate()?;
        if !p.background.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(format!(
                "`background` must be finite and ≥ 0, got {:?}",
                p.background
            ));
        }
        Ok(Trace {
            camera: p.camera as usize,
            background: p.background,
            options,
        })
    }
}

fn image(w: usize, h: usize, channels: Channels, data: Vec<f32>) -> Result<Value, OpError> {
    Image::new(w, h, channels, PixelData::F32(data))
        .map(Value::image)
        .map_err(|e| OpError::failed(e.to_string()))
}

impl Operator for Trace {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let scene = match inputs.require("scene")? {
            Value::Scene(s) => s,
            other => {
                return Err(OpError::input(
                    "scene",
                    format!("expected Scene, got {}", other.port_type()),
                ));
            }
        };
        let out = trace_scene(scene, self.camera, self.background, &self.options)
            .map_err(|e| OpError::input("scene", e))?;
        let (w, h) = (out.width, out.height);
        Ok(Outputs::new()
            .with("color", image(w, h, Channels::Rgb, out.color)?)
            .with("depth", image(w, h, Channels::Gray, out.depth)?)
            .with("normals", image(w, h, Channels::Rgb, out.normals)?)
            .with("ids", image(w, h, Channels::Gray, out.ids)?)
            .with("ray_origins", image(w, h, Channels::Rgb, out.ray_origins)?)
            .with(
                "ray_directions",
                image(w, h, Channels::Rgb, out.ray_directions)?,
            )
            .with("hits", Value::Integer(out.hits as i64)))
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::render::primitives::bumpy_icosphere;
    use crate::render::raycast::{LookAtCamera, raycast_depth};
    use crate::render::scene::scene_camera_from_look_at;
    use ocellus_engine::value::{SceneCamera, SceneObject};

    fn camera(
        w: usize,
        h: usize,
        fov_y: f64,
        eye: [f64; 3],
        target: [f64; 3],
        up: [f64; 3],
    ) -> SceneCamera {
        scene_camera_from_look_at(&LookAtCamera::new(w, h, fov_y, eye, target, up).unwrap())
    }

    fn lambert(albedo: [f32; 3]) -> Material {
        Material {
            albedo,
            roughness: 1.0,
            metalness: 0.0,
            ..Material::default()
        }
    }

    fn object(shape: Shape, material: u32) -> SceneObject {
        SceneObject {
            name: String::new(),
            shape,
            world_from_object: Pose::IDENTITY,
            scale: 1.0,
            material,
        }
    }

    fn sphere(center: [f64; 3], radius: f64) -> Shape {
        Shape::Sphere { center, radius }
    }

    fn infinite_plane(point: [f64; 3], normal: [f64; 3]) -> Shape {
        Shape::Plane {
            point,
            normal,
            half_extent: f64::INFINITY,
        }
    }

    fn options(integrator: Integrator, spp: u32) -> TraceOptions {
        TraceOptions {
            integrator,
            spp,
            ..TraceOptions::default()
        }
    }

    fn environment(radiance: f32) -> Light {
        Light::Environment {
            radiance: [radiance; 3],
            map: None,
        }
    }

    fn pixel(img: &TraceImages, x: usize, y: usize) -> [f64; 3] {
        let i = 3 * (y * img.width + x);
        [0, 1, 2].map(|k| f64::from(img.color[i + k]))
    }

    /// Pixels whose centre ray and its four neighbours' centre rays all hit an object (so the
    /// whole pixel footprint sees it, for a convex object).
    fn interior(img: &TraceImages) -> Vec<(usize, usize)> {
        let (w, h) = (img.width, img.height);
        let hit = |x: usize, y: usize| img.ids[y * w + x] >= 0.0;
        let mut v = Vec::new();
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                if hit(x, y) && hit(x - 1, y) && hit(x + 1, y) && hit(x, y - 1) && hit(x, y + 1) {
                    v.push((x, y));
                }
            }
        }
        v
    }

    fn furnace(shape: Shape, material: Material, spp: u32) -> TraceImages {
        let scene = Scene {
            materials: vec![material],
            objects: vec![object(shape, 0)],
            lights: vec![environment(1.0)],
            cameras: vec![camera(
                24,
                24,
                40.0,
                [0.0, 0.0, -4.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            )],
        };
        trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Path, spp)).unwrap()
    }

    fn mean_over(img: &TraceImages, pixels: &[(usize, usize)]) -> f64 {
        let s: f64 = pixels
            .iter()
            .map(|&(x, y)| pixel(img, x, y).iter().sum::<f64>() / 3.0)
            .sum();
        s / pixels.len() as f64
    }

    #[test]
    fn white_furnace_lambertian() {
        let mut flat = bumpy_icosphere(3, 0.0, 1);
        flat.normals = None;
        let smooth = bumpy_icosphere(4, 0.0, 1);
        let shapes = [
            ("sphere", sphere([0.0; 3], 1.0)),
            ("flat icosphere", Shape::Mesh(Arc::new(flat))),
            ("smooth icosphere", Shape::Mesh(Arc::new(smooth))),
        ];
        for (name, shape) in shapes {
            // Albedo 1: every pixel, object or environment, is exactly the environment.
            let img = furnace(shape.clone(), lambert([1.0; 3]), 8);
            let mean =
                img.color.iter().map(|&v| f64::from(v)).sum::<f64>() / img.color.len() as f64;
            let worst = img
                .color
                .iter()
                .map(|&v| (f64::from(v) - 1.0).abs())
                .fold(0.0, f64::max);
            eprintln!("furnace {name}, albedo 1: mean {mean:.6}, worst pixel error {worst:.2e}");
            assert!((mean - 1.0).abs() < 0.01, "{name}: mean {mean}");
            assert!(worst < 0.01, "{name}: worst pixel error {worst}");
            assert!(img.hits > 100);
            // Albedo 0.5 on a convex object: L = ρ L_env.
            let img = furnace(shape, lambert([0.5; 3]), 8);
            let inside = interior(&img);
            let mean = mean_over(&img, &inside);
            let worst = inside
                .iter()
                .flat_map(|&(x, y)| pixel(&img, x, y))
                .map(|v| (v - 0.5).abs() / 0.5)
                .fold(0.0, f64::max);
            eprintln!(
                "furnace {name}, albedo 0.5: mean {mean:.6}, worst pixel rel. error {worst:.2e}"
            );
            assert!((mean - 0.5).abs() < 0.005, "{name}: mean {mean}");
            assert!(worst < 0.01, "{name}: {worst}");
        }
    }

    /// `E(μ) = ∫ f_GGX(wo, wi) cos θ_i dω_i` with F = 1 by the midpoint rule in (cos θ, φ).
    fn directional_albedo(mu: f64, alpha: f64) -> f64 {
        let wo = [(1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu];
        let (nz, nphi) = (160, 160);
        let mut sum = 0.0;
        for i in 0..nz {
            let z = (i as f64 + 0.5) / nz as f64;
            let r = (1.0 - z * z).sqrt();
            // Symmetric in φ: integrate over [0, π] and double.
            for j in 0..nphi {
                let phi = PI * (j as f64 + 0.5) / nphi as f64;
                let wi = [r * phi.cos(), r * phi.sin(), z];
                sum += ggx_reflection_brdf(wo, wi, alpha, [1.0; 3])[0] * z;
            }
        }
        sum * 2.0 * PI / (nz * nphi) as f64
    }

    #[test]
    fn white_furnace_ggx_metal_does_not_gain_energy() {
        let mut means = Vec::new();
        for roughness in [0.2f32, 0.5, 1.0] {
            let metal = Material {
                albedo: [1.0; 3],
                metalness: 1.0,
                roughness,
                ..Material::default()
            };
            let img = furnace(sphere([0.0; 3], 1.0), metal, 16);
            let inside = interior(&img);
            let mean = mean_over(&img, &inside);
            let max = img.color.iter().map(|&v| f64::from(v)).fold(0.0, f64::max);
            // The directional albedo E(μ) = ∫ f cos dω of the BRDF by quadrature (independent
            // of the sampler), at each interior pixel's viewing cosine.
            let view = View::new(&camera(
                24,
                24,
                40.0,
                [0.0, 0.0, -4.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            ))
            .unwrap();
            let alpha = f64::from(roughness).powi(2);
            let mut expected = 0.0;
            for &(x, y) in &inside {
                let (o, d) = view.lens_ray(x as f64, y as f64, [0.0; 2]);
                let t = intersect_sphere(o, d, [0.0; 3], 1.0, 0.0, f64::INFINITY).unwrap();
                let n = madd(o, d, t);
                expected += directional_albedo(-dot(d, n), alpha);
            }
            expected /= inside.len() as f64;
            eprintln!(
                "furnace GGX metal roughness {roughness}: mean {mean:.4} (quadrature of the BRDF {expected:.4}), max pixel {max:.4}"
            );
            // F = 1, so a single scattering weight G2/G1 ≤ 1: no pixel can exceed 1.
            assert!(max <= 1.0 + 1e-6, "roughness {roughness}: {max}");
            assert!(mean <= 1.0, "roughness {roughness}: {mean}");
            if roughness >= 0.5 {
                assert!(
                    (mean - expected).abs() < 0.015 * expected,
                    "{mean} vs {expected}"
                );
            }
            means.push(mean);
        }
        // Single-scattering GGX loses more energy the rougher it is.
        assert!(means[0] > means[1] && means[1] > means[2], "{means:?}");
        assert!(means[0] > 0.97, "{means:?}");
    }

    #[test]
    fn glass_sphere_in_white_furnace_conserves_energy() {
        let glass = Material {
            albedo: [1.0; 3],
            transmission: 1.0,
            ior: 1.5,
            metalness: 0.0,
            roughness: 0.0,
            ..Material::default()
        };
        // Whitted splits at every interface; for a sphere the internal angle repeats, so no
        // light is trapped by total internal reflection and only depth truncation loses energy.
        let scene = Scene {
            materials: vec![glass],
            objects: vec![object(sphere([0.0; 3], 1.0), 0)],
            lights: vec![environment(1.0)],
            cameras: vec![camera(
                24,
                24,
                40.0,
                [0.0, 0.0, -4.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            )],
        };
        let mut opts = options(Integrator::Whitted, 1);
        opts.max_depth = 16;
        let img = trace_scene(&scene, 0, [0.0; 3], &opts).unwrap();
        // Pixels well inside the silhouette (grazing Fresnel keeps energy inside long).
        let view = View::new(&scene.cameras[0]).unwrap();
        let mut n = 0;
        for y in 0..24 {
            for x in 0..24 {
                let (o, d) = view.lens_ray(x as f64, y as f64, [0.0; 2]);
                let closest = length(madd(o, d, -dot(o, d)));
                if closest < 0.7 {
                    n += 1;
                    for c in pixel(&img, x, y) {
                        assert!((c - 1.0).abs() < 1e-3, "({x},{y}) {c}");
                    }
                }
            }
        }
        assert!(n > 50);
        opts.integrator = Integrator::Path;
        opts.spp = 32;
        let img = trace_scene(&scene, 0, [0.0; 3], &opts).unwrap();
        let inside = interior(&img);
        let mean = mean_over(&img, &inside);
        eprintln!("glass sphere furnace, path: mean {mean:.4}");
        assert!((mean - 1.0).abs() < 0.02, "{mean}");
    }

    #[test]
    fn whitted_tree_is_bounded_at_depth_64() {
        // Three concentric glass spheres at max_depth 64: a full split at every interface would
        // be 2⁶⁴ rays per pixel; weight pruning keeps it small. Every interface conserves
        // energy (each dielectric surface separates air from glass), so the furnace stays at 1
        // up to truncation.
        let glass = Material {
            albedo: [1.0; 3],
            transmission: 1.0,
            ior: 1.5,
            ..Material::default()
        };
        let scene = Scene {
            materials: vec![glass],
            objects: [1.0, 0.7, 0.4]
                .iter()
                .map(|&r| object(sphere([0.0; 3], r), 0))
                .collect(),
            lights: vec![environment(1.0)],
            cameras: vec![camera(
                12,
                12,
                40.0,
                [0.0, 0.0, -4.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            )],
        };
        let mut opts = options(Integrator::Whitted, 1);
        opts.max_depth = 64;
        let img = trace_scene(&scene, 0, [0.0; 3], &opts).unwrap();
        let inside = interior(&img);
        let mean = mean_over(&img, &inside);
        let min = inside
            .iter()
            .flat_map(|&(x, y)| pixel(&img, x, y))
            .fold(f64::INFINITY, f64::min);
        eprintln!("nested glass, Whitted depth 64: mean {mean:.5}, darkest {min:.5}");
        assert!((mean - 1.0).abs() < 0.01 && min > 0.9, "{mean} {min}");
    }

    /// ρ/π · I cos θ / r² at the pixel-centre hit on the plane y = y0.
    fn point_light_expected(
        view: &View,
        x: usize,
        y: usize,
        y0: f64,
        light: [f64; 3],
        intensity: [f64; 3],
        albedo: [f64; 3],
    ) -> [f64; 3] {
        let (o, d) = view.lens_ray(x as f64, y as f64, [0.0; 2]);
        let t = (y0 - o[1]) / d[1];
        let p = madd(o, d, t);
        let r = sub(light, p);
        let r2 = dot(r, r);
        let cos = r[1] / r2.sqrt();
        [0, 1, 2].map(|k| albedo[k] / PI * intensity[k] * cos / r2)
    }

    fn quad_mesh(center: [f64; 3], half: f64) -> Shape {
        let [cx, cy, cz] = center;
        let p = |x: f64, z: f64| [(cx + x) as f32, cy as f32, (cz + z) as f32];
        Shape::Mesh(Arc::new(Mesh {
            positions: vec![
                p(-half, -half),
                p(half, -half),
                p(half, half),
                p(-half, half),
            ],
            // Counter-clockwise seen from +y.
            triangles: vec![[0, 2, 1], [0, 3, 2]],
            ..Mesh::default()
        }))
    }

    fn lit_plane_check(offset: [f64; 3], light_height: f64, tol: f64) {
        let albedo = [0.6, 0.4, 0.2];
        let intensity = [5.0, 3.0, 2.0];
        let light = add(offset, [0.3, light_height, -0.2]);
        let eye = add(offset, [0.0, 10.0, 0.0]);
        // Small pixels (0.044 units) and 4×4 strata keep the box filter's deviation from the
        // pixel-centre value far below 1 %.
        let (w, h) = (48, 36);
        let cam = camera(w, h, 12.0, eye, offset, [0.0, 0.0, 1.0]);
        let view = View::new(&cam).unwrap();
        let dir_light = normalize([0.3, -1.0, 0.2]).unwrap();
        for (name, shape) in [
            ("analytic plane", infinite_plane(offset, [0.0, 1.0, 0.0])),
            ("mesh plane", quad_mesh(offset, 50.0)),
        ] {
            for integrator in [Integrator::Whitted, Integrator::Path] {
                let mut scene = Scene {
                    materials: vec![lambert(albedo.map(|v| v as f32))],
                    objects: vec![object(shape.clone(), 0)],
                    lights: vec![Light::Point {
                        position: light,
                        intensity: intensity.map(|v| v as f32),
                    }],
                    cameras: vec![cam.clone()],
                };
                let img = trace_scene(&scene, 0, [0.0; 3], &options(integrator, 16)).unwrap();
                let mut worst = 0.0f64;
                for y in 0..h {
                    for x in 0..w {
                        let e =
                            point_light_expected(&view, x, y, offset[1], light, intensity, albedo);
                        let got = pixel(&img, x, y);
                        for k in 0..3 {
                            worst = worst.max((got[k] - e[k]).abs() / e[k]);
                        }
                    }
                }
                eprintln!(
                    "{name} at {offset:?}, point light, {integrator:?}: worst rel. error {worst:.2e}"
                );
                assert!(worst < tol, "{name} {integrator:?}: {worst}");
                // A directional light: ρ/π E cos θ everywhere.
                scene.lights = vec![Light::Directional {
                    direction: dir_light,
                    irradiance: [2.0; 3],
                }];
                let img = trace_scene(&scene, 0, [0.0; 3], &options(integrator, 1)).unwrap();
                let cos = -dir_light[1];
                for k in 0..3 {
                    let e = albedo[k] / PI * 2.0 * cos;
                    for y in 0..h {
                        for x in 0..w {
                            let got = pixel(&img, x, y)[k];
                            assert!(
                                (got - e).abs() < 1e-3 * e,
                                "{name} {integrator:?} {got} vs {e}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn lambertian_plane_under_point_and_directional_light() {
        lit_plane_check([0.0; 3], 2.0, 0.01);
    }

    #[test]
    fn huge_coordinates_neither_self_shadow_nor_lose_precision() {
        // 10⁵ away from the origin the f32 ULP is 2⁻⁷; the surface still sees its light.
        lit_plane_check([1.0e5, -1.0e5, 1.0e5], 6.0, 0.01);
    }

    #[test]
    fn spawned_rays_never_rehit_their_surface() {
        let mut rng = SampleRng::new(7, 0, 0);
        for &offset in &[0.0, 1.0e5, -3.0e5] {
            for trial in 0..20 {
                // A random triangle and a sphere, far from the origin.
                let n = normalize([
                    rng.next_f64() - 0.5,
                    rng.next_f64() - 0.5,
                    rng.next_f64() - 0.5,
                ])
                .unwrap();
                let (t, b) = orthonormal_basis(n);
                let c = [offset + 3.0, offset - 1.0, offset + 2.0];
                let corner =
                    |a: f64, bb: f64| add(c, add(scale(t, a), scale(b, bb))).map(|v| v as f32);
                let mesh = Mesh {
                    positions: vec![corner(-5.0, -5.0), corner(5.0, -5.0), corner(0.0, 5.0)],
                    triangles: vec![[0, 1, 2]],
                    ..Mesh::default()
                };
                let scene = Scene {
                    materials: vec![lambert([0.5; 3])],
                    objects: vec![object(Shape::Mesh(Arc::new(mesh)), 0)],
                    ..Scene::default()
                };
                let ts = TraceScene::new(&scene, [0.0; 3]).unwrap();
                let eye = madd(c, n, 20.0 * if trial % 2 == 0 { 1.0 } else { -1.0 });
                let d = normalize(sub(madd(c, t, 0.3 * rng.next_f64()), eye)).unwrap();
                let hit = ts
                    .intersect(eye, d, f64::INFINITY, true)
                    .expect("hits the triangle");
                for _ in 0..50 {
                    let w = normalize([
                        rng.next_f64() - 0.5,
                        rng.next_f64() - 0.5,
                        rng.next_f64() - 0.5,
                    ])
                    .unwrap();
                    let o = hit.spawn_origin(w);
                    assert!(
                        ts.intersect(o, w, f64::INFINITY, true).is_none(),
                        "offset {offset}"
                    );
                    assert!(!ts.occluded(o, w, 1e9));
                }
                // A sphere: outward rays escape, inward rays cross the whole chord.
                let scene = Scene {
                    materials: vec![lambert([0.5; 3])],
                    objects: vec![object(sphere(c, 1.0), 0)],
                    ..Scene::default()
                };
                let ts = TraceScene::new(&scene, [0.0; 3]).unwrap();
                let eye = madd(c, n, 10.0);
                let hit = ts
                    .intersect(eye, scale(n, -1.0), f64::INFINITY, true)
                    .unwrap();
                assert!((hit.t - 9.0).abs() < 1e-9, "{}", hit.t);
                for _ in 0..50 {
                    let w = normalize([
                        rng.next_f64() - 0.5,
                        rng.next_f64() - 0.5,
                        rng.next_f64() - 0.5,
                    ])
                    .unwrap();
                    let o = hit.spawn_origin(w);
                    let again = ts.intersect(o, w, f64::INFINITY, true);
                    let cos = dot(w, hit.geometric_normal);
                    if cos > 0.0 {
                        assert!(again.is_none());
                    } else {
                        // No self-hit near t = 0: the far side of the chord 2|cos θ|.
                        let chord = -2.0 * cos;
                        let Some(again) = again else {
                            panic!("offset {offset}: cos {cos}, origin {o:?}, hit {hit:?}");
                        };
                        let t = again.t;
                        // Starting δ below the surface lengthens the chord by about δ/|cos θ|.
                        let depth = length(sub(o, hit.position));
                        let tol = 1e-9 + 2.0 * depth / cos.abs();
                        assert!((t - chord).abs() < tol, "offset {offset}: {t} vs {chord}");
                    }
                }
            }
        }
    }

    /// Irradiance from a uniform polygon of radiance L at a point with normal n: Lambert's
    /// formula E = (L/2) Σ Γ_i (n · (v_i × v_{i+1}) / |v_i × v_{i+1}|), Γ_i the angle between
    /// successive unit vertex directions.
    fn polygon_irradiance(p: Vec3, n: Vec3, vertices: &[Vec3], radiance: f64) -> f64 {
        let k = vertices.len();
        let mut sum = 0.0;
        for i in 0..k {
            let a = normalize(sub(vertices[i], p)).unwrap();
            let b = normalize(sub(vertices[(i + 1) % k], p)).unwrap();
            let gamma = dot(a, b).clamp(-1.0, 1.0).acos();
            sum += gamma * dot(n, normalize(cross(a, b)).unwrap());
        }
        0.5 * radiance * sum.abs()
    }

    #[test]
    fn area_light_irradiance_matches_lambert_polygon_formula() {
        let albedo = 0.5;
        let radiance = 2.0;
        let corner = [-0.5, 1.0, -0.5];
        let (eu, ev) = ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        let square = [
            corner,
            add(corner, eu),
            add(add(corner, eu), ev),
            add(corner, ev),
        ];
        // Looking at the floor under the light from the side, below the emitter.
        let cam = camera(6, 6, 8.0, [3.0, 0.6, 0.2], [0.2, 0.0, 0.1], [0.0, 1.0, 0.0]);
        let view = View::new(&cam).unwrap();
        let scene = Scene {
            materials: vec![lambert([albedo as f32; 3])],
            objects: vec![object(infinite_plane([0.0; 3], [0.0, 1.0, 0.0]), 0)],
            lights: vec![Light::Area {
                corner,
                edge_u: eu,
                edge_v: ev,
                radiance: [radiance as f32; 3],
            }],
            cameras: vec![cam],
        };
        for integrator in [Integrator::Path, Integrator::Whitted] {
            let img = trace_scene(&scene, 0, [0.0; 3], &options(integrator, 1024)).unwrap();
            let mut ratio_sum = 0.0;
            let mut worst = 0.0f64;
            for y in 0..6 {
                for x in 0..6 {
                    let (o, d) = view.lens_ray(x as f64, y as f64, [0.0; 2]);
                    let p = madd(o, d, -o[1] / d[1]);
                    let e = polygon_irradiance(p, [0.0, 1.0, 0.0], &square, radiance);
                    let expected = albedo / PI * e;
                    let got = pixel(&img, x, y)[0];
                    ratio_sum += got / expected;
                    worst = worst.max((got / expected - 1.0).abs());
                }
            }
            let mean = ratio_sum / 36.0;
            eprintln!(
                "area light, {integrator:?}: mean ratio to Lambert's formula {mean:.4}, worst pixel {worst:.3}"
            );
            assert!((mean - 1.0).abs() < 0.02, "{integrator:?}: {mean}");
            assert!(worst < 0.08, "{integrator:?}: {worst}");
        }
    }

    #[test]
    fn mirror_reflects_an_emitter_at_the_mirror_angle() {
        let mirror = Material {
            albedo: [1.0; 3],
            metalness: 1.0,
            roughness: 0.0,
            ..Material::default()
        };
        let emitter = Material {
            albedo: [0.0; 3],
            emission: [3.0, 2.0, 1.0],
            ..Material::default()
        };
        let (c, r) = ([0.0, 1.0, 2.0], 0.3);
        let mirrored = [c[0], -c[1], c[2]];
        let eye = [0.0, 1.0, -2.0];
        let cam = camera(32, 32, 30.0, eye, [0.0; 3], [0.0, 1.0, 0.0]);
        let view = View::new(&cam).unwrap();
        let scene = Scene {
            materials: vec![mirror, emitter],
            objects: vec![
                object(infinite_plane([0.0; 3], [0.0, 1.0, 0.0]), 0),
                object(sphere(c, r), 1),
            ],
            lights: vec![],
            cameras: vec![cam],
        };
        for integrator in [Integrator::Whitted, Integrator::Path] {
            let img = trace_scene(&scene, 0, [0.0; 3], &options(integrator, 4)).unwrap();
            let (mut inside, mut outside) = (0, 0);
            for y in 0..32 {
                for x in 0..32 {
                    let sees = |dx: f64, dy: f64, radius: f64| {
                        let (o, d) = view.lens_ray(x as f64 + dx, y as f64 + dy, [0.0; 2]);
                        intersect_sphere(o, d, mirrored, radius, 0.0, f64::INFINITY).is_some()
                    };
                    let got = pixel(&img, x, y);
                    let corners = [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)];
                    if corners.iter().all(|&(dx, dy)| sees(dx, dy, r)) {
                        inside += 1;
                        assert_eq!(got, [3.0, 2.0, 1.0], "{integrator:?} ({x},{y})");
                    } else if (0..25).all(|k| {
                        !sees(
                            (k % 5) as f64 / 4.0 - 0.5,
                            (k / 5) as f64 / 4.0 - 0.5,
                            1.2 * r,
                        )
                    }) {
                        outside += 1;
                        assert_eq!(got, [0.0; 3], "{integrator:?} ({x},{y})");
                    }
                }
            }
            assert!(inside > 20 && outside > 500, "{inside} {outside}");
        }
    }

    fn texture(w: usize, h: usize, texels: Vec<[f32; 3]>) -> Texture {
        use ocellus_engine::value::{TextureFilter, TextureWrap};
        let data: Vec<f32> = texels.into_iter().flatten().collect();
        Texture {
            image: Arc::new(Image::new(w, h, Channels::Rgb, PixelData::F32(data)).unwrap()),
            wrap: TextureWrap::Repeat,
            filter: TextureFilter::Nearest,
            border: [0.0; 4],
            max_anisotropy: 1,
            uv_scale: [1.0, 1.0],
        }
    }

    /// A floor y = 0 seen from straight above, lit by a directional light from straight above
    /// with irradiance π (so a Lambertian pixel shows its albedo).
    fn floor_scene(material: Material) -> Scene {
        Scene {
            materials: vec![material],
            objects: vec![object(infinite_plane([0.0; 3], [0.0, 1.0, 0.0]), 0)],
            lights: vec![Light::Directional {
                direction: [0.0, -1.0, 0.0],
                irradiance: [PI as f32; 3],
            }],
            cameras: vec![camera(
                20,
                20,
                20.0,
                [0.0, 5.0, 0.0],
                [0.0; 3],
                [0.0, 0.0, 1.0],
            )],
        }
    }

    #[test]
    fn textures_drive_material_parameters() {
        // The floor's uv are its in-plane coordinates (u = x, v = −z for normal +y). A 2×1
        // albedo texture: texel 0 for frac(u) < 1/2, texel 1 otherwise.
        let (ta, tb) = ([0.9f32, 0.5, 0.1], [0.2f32, 0.4, 0.8]);
        let mut m = lambert([1.0; 3]);
        m.albedo_texture = Some(texture(2, 1, vec![ta, tb]));
        let scene = floor_scene(m);
        let view = View::new(&scene.cameras[0]).unwrap();
        let img = trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Whitted, 4)).unwrap();
        let texel_at = |x: f64, y: f64| {
            let (o, d) = view.lens_ray(x, y, [0.0; 2]);
            let p = madd(o, d, -o[1] / d[1]);
            usize::from(p[0].rem_euclid(1.0) >= 0.5)
        };
        let mut checked = 0;
        for y in 0..20 {
            for x in 0..20 {
                let (xf, yf) = (x as f64, y as f64);
                let k = texel_at(xf, yf);
                let same = [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)]
                    .iter()
                    .all(|&(dx, dy)| texel_at(xf + dx, yf + dy) == k);
                if same {
                    checked += 1;
                    let want = if k == 0 { ta } else { tb };
                    let got = pixel(&img, x, y);
                    for c in 0..3 {
                        assert!(
                            (got[c] - f64::from(want[c])).abs() < 1e-5,
                            "({x},{y}) {got:?}"
                        );
                    }
                }
            }
        }
        assert!(checked > 100, "{checked}");
        // A flat normal map (0.5, 0.5, 1) changes nothing; a tilted one tilts the normal by α
        // towards the tangent (+x here) and dims the light by cos α.
        let base = trace_scene(
            &floor_scene(lambert([0.5; 3])),
            0,
            [0.0; 3],
            &options(Integrator::Whitted, 1),
        )
        .unwrap();
        let mut m = lambert([0.5; 3]);
        m.normal_texture = Some(texture(1, 1, vec![[0.5, 0.5, 1.0]]));
        let flat = trace_scene(
            &floor_scene(m.clone()),
            0,
            [0.0; 3],
            &options(Integrator::Whitted, 1),
        )
        .unwrap();
        assert_eq!(base, flat);
        let alpha = 0.5f64;
        let texel = [0.5 + 0.5 * alpha.sin(), 0.5, 0.5 + 0.5 * alpha.cos()].map(|v| v as f32);
        m.normal_texture = Some(texture(1, 1, vec![texel]));
        let tilted = trace_scene(
            &floor_scene(m),
            0,
            [0.0; 3],
            &options(Integrator::Whitted, 1),
        )
        .unwrap();
        let n_texel = texel.map(|v| 2.0 * f64::from(v) - 1.0);
        let n_len = length(n_texel);
        for i in 0..400 {
            let n = &tilted.normals[3 * i..3 * i + 3];
            assert!((f64::from(n[0]) - n_texel[0] / n_len).abs() < 1e-6, "{n:?}");
            assert!((f64::from(n[1]) - n_texel[2] / n_len).abs() < 1e-6, "{n:?}");
            assert!(n[2].abs() < 1e-6);
            let want = 0.5 * n_texel[2] / n_len;
            assert!((f64::from(tilted.color[3 * i]) - want).abs() < 1e-6);
        }
        // Metalness and roughness textures multiply their parameters: metalness 1 × 0 is
        // Lambertian; roughness 1 × 0 is a mirror, which a directional light cannot reach
        // through the lens (black); emission × its texture.
        let mut m = Material {
            albedo: [0.5; 3],
            metalness: 1.0,
            roughness: 1.0,
            ..Material::default()
        };
        m.metalness_texture = Some(texture(1, 1, vec![[0.0; 3]]));
        let img = trace_scene(
            &floor_scene(m.clone()),
            0,
            [0.0; 3],
            &options(Integrator::Whitted, 1),
        )
        .unwrap();
        assert!((img.color[0] - 0.5).abs() < 1e-6);
        m.metalness_texture = None;
        m.roughness_texture = Some(texture(1, 1, vec![[0.0; 3]]));
        let img = trace_scene(
            &floor_scene(m),
            0,
            [0.0; 3],
            &options(Integrator::Whitted, 1),
        )
        .unwrap();
        assert!(img.color.iter().all(|&v| v == 0.0));
        let mut m = Material {
            albedo: [0.0; 3],
            emission: [2.0; 3],
            ..Material::default()
        };
        m.emission_texture = Some(texture(1, 1, vec![[0.5, 0.25, 1.0]]));
        let img = trace_scene(&floor_scene(m), 0, [0.0; 3], &options(Integrator::Path, 2)).unwrap();
        assert_eq!(&img.color[0..3], &[1.0, 0.5, 2.0]);
    }

    #[test]
    fn environment_map_is_looked_up_by_direction() {
        // u = ½ + atan2(x, −z)/2π: looking along −x reads the left half, along +x the right.
        let (a, b) = ([1.0f32, 0.5, 0.25], [0.1f32, 0.2, 0.3]);
        let env = Light::Environment {
            radiance: [2.0; 3],
            map: Some(texture(2, 1, vec![a, b])),
        };
        for (target, want) in [([-1.0, 0.0, 0.0], a), ([1.0, 0.0, 0.0], b)] {
            let scene = Scene {
                lights: vec![env.clone()],
                cameras: vec![camera(4, 4, 10.0, [0.0; 3], target, [0.0, 1.0, 0.0])],
                ..Scene::default()
            };
            let img = trace_scene(&scene, 0, [9.0; 3], &options(Integrator::Path, 2)).unwrap();
            for i in 0..16 {
                for c in 0..3 {
                    assert_eq!(
                        img.color[3 * i + c],
                        2.0 * want[c],
                        "the background is unused"
                    );
                }
            }
        }
        // A white map in the furnace: an albedo-1 sphere is invisible.
        let scene = Scene {
            materials: vec![lambert([1.0; 3])],
            objects: vec![object(sphere([0.0; 3], 1.0), 0)],
            lights: vec![Light::Environment {
                radiance: [1.0; 3],
                map: Some(texture(1, 1, vec![[1.0; 3]])),
            }],
            cameras: vec![camera(
                8,
                8,
                40.0,
                [0.0, 0.0, -4.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            )],
        };
        let img = trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Path, 2)).unwrap();
        assert!(img.color.iter().all(|&v| (v - 1.0).abs() < 1e-6));
    }

    #[test]
    fn ray_sphere_hits() {
        let c = [0.0; 3];
        let z = [0.0, 0.0, 1.0];
        assert_eq!(
            intersect_sphere([0.0, 0.0, -5.0], z, c, 1.0, 0.0, f64::INFINITY),
            Some(4.0)
        );
        // From inside: the far side.
        assert_eq!(
            intersect_sphere([0.0; 3], z, c, 1.0, 0.0, f64::INFINITY),
            Some(1.0)
        );
        assert_eq!(
            intersect_sphere([0.0, 0.0, 0.5], z, c, 1.0, 0.0, f64::INFINITY),
            Some(0.5)
        );
        // Behind the ray, beyond t_max, a miss.
        assert_eq!(
            intersect_sphere([0.0, 0.0, 5.0], z, c, 1.0, 0.0, f64::INFINITY),
            None
        );
        assert_eq!(
            intersect_sphere([0.0, 0.0, -5.0], z, c, 1.0, 0.0, 3.9),
            None
        );
        assert_eq!(
            intersect_sphere([0.0, 2.0, -5.0], z, c, 1.0, 0.0, f64::INFINITY),
            None
        );
        // Unnormalized directions give t in their units.
        assert_eq!(
            intersect_sphere(
                [0.0, 0.0, -5.0],
                [0.0, 0.0, 2.0],
                c,
                1.0,
                0.0,
                f64::INFINITY
            ),
            Some(2.0)
        );
        // Grazing: y = 1 − δ hits at z = −√(2δ − δ²); exactly tangent touches; beyond misses.
        for delta in [1e-4f64, 1e-8, 1e-12] {
            let y = 1.0 - delta;
            // The exact δ of the rounded origin (Sterbenz) and the conditioning of the grazing
            // root: dt/dy = 1/√(2δ), so a rounding of y moves t by ε/√(2δ).
            let delta = 1.0 - y;
            let t = intersect_sphere([0.0, y, -5.0], z, c, 1.0, 0.0, f64::INFINITY).unwrap();
            let expected = 5.0 - (2.0 * delta - delta * delta).sqrt();
            let tol = 8.0 * f64::EPSILON / (2.0 * delta).sqrt() + 1e-14;
            assert!((t - expected).abs() < tol, "δ {delta}: {t} vs {expected}");
        }
        assert_eq!(
            intersect_sphere([0.0, 1.0, -5.0], z, c, 1.0, 0.0, f64::INFINITY),
            Some(5.0)
        );
        assert_eq!(
            intersect_sphere([0.0, 1.0 + 1e-9, -5.0], z, c, 1.0, 0.0, f64::INFINITY),
            None
        );
        // A unit sphere 10⁵ away: exact along the axis, and on slanted rays the hit point lies
        // on the sphere to 1e-9 (the textbook discriminant loses ~1e-6 here).
        let far = [1.0e5, 0.0, 0.0];
        assert_eq!(
            intersect_sphere([0.0; 3], [1.0, 0.0, 0.0], far, 1.0, 0.0, f64::INFINITY),
            Some(1.0e5 - 1.0)
        );
        let mut rng = SampleRng::new(3, 0, 0);
        for _ in 0..200 {
            let (r, phi) = (0.999 * rng.next_f64().sqrt(), 2.0 * PI * rng.next_f64());
            let target = add(far, [0.0, r * phi.cos(), r * phi.sin()]);
            let d = normalize(target).unwrap();
            let t = intersect_sphere([0.0; 3], d, far, 1.0, 0.0, f64::INFINITY).unwrap();
            let residual = length(sub(scale(d, t), far)) - 1.0;
            assert!(residual.abs() < 1e-9, "{residual}");
        }
    }

    #[test]
    fn ray_plane_hits() {
        let n = [0.0, 1.0, 0.0];
        let (t, b) = orthonormal_basis(n);
        let hit = |o: Vec3, d: Vec3, h: f64| {
            intersect_plane(o, d, [0.0; 3], n, t, b, h, 0.0, f64::INFINITY)
        };
        let down = [0.0, -1.0, 0.0];
        let (tt, uv) = hit([0.3, 2.0, -0.4], down, 1.0).unwrap();
        assert_eq!(tt, 2.0);
        assert!((uv[0] - dot([0.3, 0.0, -0.4], t)).abs() < 1e-15);
        assert!((uv[1] - dot([0.3, 0.0, -0.4], b)).abs() < 1e-15);
        // Outside the square, inside the infinite plane.
        assert!(hit([30.0, 2.0, 0.0], down, 1.0).is_none());
        assert_eq!(hit([3e7, 2.0, -1e6], down, f64::INFINITY).unwrap().0, 2.0);
        // From below (two-sided), slanted, parallel, pointing away.
        assert_eq!(hit([0.0, -3.0, 0.0], [0.0, 1.0, 0.0], 1.0).unwrap().0, 3.0);
        let d = normalize([1.0, -1.0, 0.0]).unwrap();
        let (tt, _) = hit([-1.0, 1.0, 0.0], d, 1.0).unwrap();
        assert!((tt - 2f64.sqrt()).abs() < 1e-15);
        assert!(hit([0.0, 1.0, 0.0], [1.0, 0.0, 0.0], f64::INFINITY).is_none());
        assert!(hit([0.0, 1.0, 0.0], [0.0, 1.0, 0.0], f64::INFINITY).is_none());
        // Parallelogram (area light): inside and outside.
        let p = intersect_parallelogram(
            [0.25, 2.0, 0.75],
            down,
            [0.0; 3],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            0.0,
            9.0,
        );
        assert_eq!(p, Some((2.0, 0.25, 0.75)));
        assert!(
            intersect_parallelogram(
                [1.25, 2.0, 0.5],
                down,
                [0.0; 3],
                [1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0],
                0.0,
                9.0
            )
            .is_none()
        );
    }

    #[test]
    fn ray_quadric_hits_and_matches_the_analytic_sphere() {
        let unit_sphere = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, -1.0];
        let big = [-10.0; 3];
        let bigmax = [10.0; 3];
        let mut rng = SampleRng::new(5, 1, 2);
        for _ in 0..500 {
            let o = [0, 1, 2].map(|_| 6.0 * rng.next_f64() - 3.0);
            let d = normalize([0, 1, 2].map(|_| rng.next_f64() - 0.5)).unwrap();
            let a = intersect_sphere(o, d, [0.0; 3], 1.0, 0.0, f64::INFINITY);
            let b = intersect_quadric(o, d, &unit_sphere, big, bigmax, 0.0, f64::INFINITY);
            match (a, b) {
                (Some(a), Some(b)) => {
                    assert!((a - b).abs() < 1e-9 * a.max(1.0), "{a} {b}");
                    let p = madd(o, d, b);
                    let g = normalize(quadric_gradient(&unit_sphere, p)).unwrap();
                    for k in 0..3 {
                        assert!((g[k] - p[k]).abs() < 1e-9);
                    }
                }
                (None, None) => {}
                other => panic!("sphere vs quadric disagree: {other:?} for {o:?} {d:?}"),
            }
        }
        // The cylinder x² + y² = 1 clipped to |z| ≤ 1.
        let cylinder = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0];
        let (lo, hi) = ([-2.0, -2.0, -1.0], [2.0, 2.0, 1.0]);
        let x = [1.0, 0.0, 0.0];
        assert_eq!(
            intersect_quadric([-5.0, 0.0, 0.0], x, &cylinder, lo, hi, 0.0, f64::INFINITY),
            Some(4.0)
        );
        assert_eq!(
            intersect_quadric([-5.0, 0.0, 2.0], x, &cylinder, lo, hi, 0.0, f64::INFINITY),
            None
        );
        assert_eq!(
            intersect_quadric([0.5, 0.0, 0.0], x, &cylinder, lo, hi, 0.0, f64::INFINITY),
            Some(0.5)
        );
        // Along the axis the quadratic and linear terms vanish: no hit.
        assert_eq!(
            intersect_quadric(
                [0.0, 0.0, -5.0],
                [0.0, 0.0, 1.0],
                &cylinder,
                lo,
                hi,
                0.0,
                f64::INFINITY
            ),
            None
        );
        // A slanted ray entering the box through the cap hits the wall at z = 0.5.
        let d = normalize([1.0, 0.0, 1.0]).unwrap();
        let t =
            intersect_quadric([0.5, 0.0, 0.0], d, &cylinder, lo, hi, 0.0, f64::INFINITY).unwrap();
        assert!((t - 0.5 * 2f64.sqrt()).abs() < 1e-12);
        // The paraboloid z = x² + y² hit from above: the quadratic term is 0 (linear case).
        let paraboloid = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -0.5, 0.0];
        let t = intersect_quadric(
            [0.5, 0.0, 5.0],
            [0.0, 0.0, -1.0],
            &paraboloid,
            [-9.0; 3],
            [9.0; 3],
            0.0,
            f64::INFINITY,
        );
        assert_eq!(t, Some(4.75));
        let g = quadric_gradient(&paraboloid, [0.5, 0.0, 0.25]);
        assert_eq!(g, [1.0, 0.0, -1.0]);
    }

    #[test]
    fn transformed_quadric_and_sphere_objects_agree() {
        // The same unit sphere as a Sphere and as a Quadric under a rotation, translation and
        // scale 2: same hits, normals and positions through the scene's intersection.
        let pose = Pose {
            rotation: [0.8, 0.2, -0.5, 0.26],
            translation: [1.0, -2.0, 3.0],
        };
        let mk = |shape: Shape| {
            let scene = Scene {
                materials: vec![lambert([0.5; 3])],
                objects: vec![SceneObject {
                    name: "s".into(),
                    shape,
                    world_from_object: pose,
                    scale: 2.0,
                    material: 0,
                }],
                ..Scene::default()
            };
            TraceScene::new(&scene, [0.0; 3]).unwrap()
        };
        let a = mk(sphere([0.1, 0.2, 0.3], 1.0));
        let q = [1.0, 0.0, 0.0, -0.1, 1.0, 0.0, -0.2, 1.0, -0.3, 0.14 - 1.0];
        let b = mk(Shape::Quadric {
            coefficients: q,
            min: [-5.0; 3],
            max: [5.0; 3],
        });
        let mut rng = SampleRng::new(9, 9, 9);
        let mut hits = 0;
        for _ in 0..300 {
            let o = [0, 1, 2].map(|k| pose.translation[k] + 12.0 * rng.next_f64() - 6.0);
            let aim = [0, 1, 2].map(|k| a_center(&pose)[k] + 5.0 * rng.next_f64() - 2.5);
            let d = normalize(sub(aim, o)).unwrap();
            let ha = a.intersect(o, d, f64::INFINITY, true);
            let hb = b.intersect(o, d, f64::INFINITY, true);
            assert_eq!(ha.is_some(), hb.is_some());
            if let (Some(ha), Some(hb)) = (ha, hb) {
                hits += 1;
                assert!((ha.t - hb.t).abs() < 1e-9 * ha.t.max(1.0));
                for k in 0..3 {
                    assert!((ha.geometric_normal[k] - hb.geometric_normal[k]).abs() < 1e-9);
                    assert!((ha.position[k] - hb.position[k]).abs() < 1e-9);
                }
                assert!((length(sub(ha.position, a_center(&pose))) - 2.0).abs() < 1e-12);
            }
        }
        assert!(hits > 150, "{hits}");
    }

    #[test]
    fn transformed_planes_and_meshes_follow_their_pose() {
        // A plane z = 0 (normal +z, half-extent 1) rotated 90° about x and scaled by 2: the
        // world plane y = 0 with normal −y... rotated: R_x(90°) maps +z to −y, half-extent 2.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let pose = Pose {
            rotation: [h, h, 0.0, 0.0],
            translation: [0.0, 1.0, 0.0],
        };
        let scene = Scene {
            materials: vec![lambert([0.5; 3])],
            objects: vec![SceneObject {
                name: "p".into(),
                shape: Shape::Plane {
                    point: [0.0; 3],
                    normal: [0.0, 0.0, 1.0],
                    half_extent: 1.0,
                },
                world_from_object: pose,
                scale: 2.0,
                material: 0,
            }],
            ..Scene::default()
        };
        let ts = TraceScene::new(&scene, [0.0; 3]).unwrap();
        let down = [0.0, -1.0, 0.0];
        let hit = ts
            .intersect([1.9, 5.0, -1.9], down, f64::INFINITY, true)
            .unwrap();
        assert!((hit.t - 4.0).abs() < 1e-12);
        for k in 0..3 {
            assert!((hit.geometric_normal[k] - [0.0, -1.0, 0.0][k]).abs() < 1e-12);
        }
        assert!(
            ts.intersect([2.1, 5.0, 0.0], down, f64::INFINITY, true)
                .is_none()
        );
        // A posed, scaled icosphere against the analytic sphere under the same transform:
        // depth within the tessellation error, world-space shading normals close.
        let pose = Pose {
            rotation: [0.9, -0.3, 0.2, 0.25],
            translation: [0.5, -0.2, 0.3],
        };
        let cam = camera(
            32,
            32,
            50.0,
            [0.5, -0.2, -6.0],
            [0.5, -0.2, 0.3],
            [0.0, 1.0, 0.0],
        );
        let render = |shape: Shape| {
            let scene = Scene {
                materials: vec![lambert([0.5; 3])],
                objects: vec![SceneObject {
                    name: "s".into(),
                    shape,
                    world_from_object: pose,
                    scale: 1.5,
                    material: 0,
                }],
                lights: vec![],
                cameras: vec![cam.clone()],
            };
            trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Whitted, 1)).unwrap()
        };
        let mesh = render(Shape::Mesh(Arc::new(bumpy_icosphere(5, 0.0, 1))));
        let exact = render(sphere([0.0; 3], 1.0));
        let mut compared = 0;
        for i in 0..32 * 32 {
            if mesh.depth[i].is_finite() && exact.depth[i].is_finite() {
                compared += 1;
                let (a, b) = (f64::from(mesh.depth[i]), f64::from(exact.depth[i]));
                assert!((a - b).abs() < 2e-3 * b, "{a} vs {b}");
                let dn: f64 = (0..3)
                    .map(|k| f64::from(mesh.normals[3 * i + k] - exact.normals[3 * i + k]).powi(2))
                    .sum();
                assert!(dn.sqrt() < 0.02, "{dn}");
            }
        }
        assert!(compared > 200 && (mesh.hits as i64 - exact.hits as i64).abs() < 8);
    }

    fn a_center(pose: &Pose) -> Vec3 {
        let r = pose.rotation_matrix();
        add(mat3_mul(&r, [0.2, 0.4, 0.6]), pose.translation)
    }

    #[test]
    fn depth_matches_raycast_on_a_mesh() {
        let mesh = Arc::new(bumpy_icosphere(3, 0.05, 2));
        let la =
            LookAtCamera::new(64, 48, 50.0, [0.3, 0.2, -3.0], [0.0; 3], [0.0, 1.0, 0.0]).unwrap();
        let bvh = build_bvh(mesh.clone(), &BvhOptions::default()).unwrap();
        let (depth, hits) = raycast_depth(&bvh, &la);
        let scene = Scene {
            materials: vec![lambert([0.5; 3])],
            objects: vec![object(Shape::Mesh(mesh), 0)],
            lights: vec![],
            cameras: vec![scene_camera_from_look_at(&la)],
        };
        let img = trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Whitted, 1)).unwrap();
        assert_eq!(img.hits, hits);
        for (i, (&a, &b)) in depth.iter().zip(&img.depth).enumerate() {
            assert_eq!(a.is_finite(), b.is_finite(), "pixel {i}");
            if a.is_finite() {
                assert!((a - b).abs() <= 1e-5 * a, "pixel {i}: {a} vs {b}");
                assert_eq!(img.ids[i], 0.0);
            } else {
                assert_eq!(img.ids[i], -1.0);
            }
        }
        // An analytic sphere: the normal output is (eye + depth·dir − c)/r and the ray outputs
        // are the view's pixel-centre rays.
        let scene = Scene {
            materials: vec![lambert([0.5; 3])],
            objects: vec![object(sphere([0.1, 0.0, 0.2], 0.8), 0)],
            lights: vec![],
            cameras: vec![scene_camera_from_look_at(&la)],
        };
        let img = trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Whitted, 1)).unwrap();
        let view = View::new(&scene.cameras[0]).unwrap();
        let mut n = 0;
        for y in 0..48 {
            for x in 0..64 {
                let i = y * 64 + x;
                let (o, d) = view.lens_ray(x as f64, y as f64, [0.0; 2]);
                for k in 0..3 {
                    assert_eq!(img.ray_origins[3 * i + k], o[k] as f32);
                    assert_eq!(img.ray_directions[3 * i + k], d[k] as f32);
                }
                let t = intersect_sphere(o, d, [0.1, 0.0, 0.2], 0.8, 0.0, f64::INFINITY);
                match t {
                    Some(t) => {
                        n += 1;
                        assert!((f64::from(img.depth[i]) - t).abs() < 1e-6 * t);
                        let p = madd(o, d, t);
                        let nn = scale(sub(p, [0.1, 0.0, 0.2]), 1.0 / 0.8);
                        for k in 0..3 {
                            assert!((f64::from(img.normals[3 * i + k]) - nn[k]).abs() < 1e-5);
                        }
                    }
                    None => {
                        assert_eq!(img.depth[i], f32::INFINITY);
                        assert_eq!(&img.normals[3 * i..3 * i + 3], &[0.0; 3]);
                    }
                }
            }
        }
        assert_eq!(n, img.hits);
    }

    /// Second moment about the centroid of an image's first channel, pixels², and its sum.
    fn moments(img: &TraceImages) -> (f64, f64) {
        let (w, h) = (img.width, img.height);
        let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for y in 0..h {
            for x in 0..w {
                let v = pixel(img, x, y)[0];
                s += v;
                sx += v * x as f64;
                sy += v * y as f64;
            }
        }
        let (mx, my) = (sx / s, sy / s);
        let mut m = 0.0;
        for y in 0..h {
            for x in 0..w {
                let v = pixel(img, x, y)[0];
                m += v * ((x as f64 - mx).powi(2) + (y as f64 - my).powi(2));
            }
        }
        (m / s, s)
    }

    #[test]
    fn thin_lens_focus_and_circle_of_confusion() {
        let la =
            LookAtCamera::new(49, 49, 30.0, [0.0; 3], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]).unwrap();
        let f = la.focal_px;
        let mut cam = scene_camera_from_look_at(&la);
        cam.aperture_radius = 0.2;
        cam.focus_distance = 4.0;
        let emitter = Material {
            albedo: [0.0; 3],
            emission: [1.0; 3],
            ..Material::default()
        };
        // An emissive square of half-side 1.5 px facing the camera at depth z.
        let a_px = 1.5;
        let render = |z: f64| {
            let scene = Scene {
                materials: vec![emitter.clone()],
                objects: vec![object(
                    Shape::Plane {
                        point: [0.0, 0.0, z],
                        normal: [0.0, 0.0, -1.0],
                        half_extent: a_px * z / f,
                    },
                    0,
                )],
                lights: vec![],
                cameras: vec![cam.clone()],
            };
            trace_scene(&scene, 0, [0.0; 3], &options(Integrator::Whitted, 256)).unwrap()
        };
        // Box-sampled uniform square: second moment 2a²/3 − 1/6 on the pixel grid (the
        // discretization removes 1/12 per axis), flux (2a)².
        let square_m = 2.0 * a_px * a_px / 3.0 - 1.0 / 6.0;
        let (m, flux) = moments(&render(4.0));
        eprintln!("in focus: second moment {m:.4} (square alone {square_m:.4}), flux {flux:.3}");
        assert!((m - square_m).abs() < 0.02, "{m}");
        assert!((flux - 9.0).abs() < 0.09, "{flux}");
        // Off focus: a uniform disk of radius R = f · A · |1/z_f − 1/z| convolved with it.
        let z = 2.0;
        let r_coc = f * 0.2 * (1.0f64 / 4.0 - 1.0 / z).abs();
        let (m, flux) = moments(&render(z));
        let r_measured = (2.0 * (m - square_m)).sqrt();
        eprintln!(
            "off focus: CoC radius {r_measured:.3} px vs analytic {r_coc:.3} px, flux {flux:.3}"
        );
        assert!(
            (r_measured - r_coc).abs() < 0.03 * r_coc,
            "{r_measured} vs {r_coc}"
        );
        assert!((flux - 9.0).abs() < 0.3, "{flux}");
    }

    fn busy_scene() -> Scene {
        let glass = Material {
            albedo: [1.0; 3],
            transmission: 1.0,
            ..Material::default()
        };
        let metal = Material {
            albedo: [0.9, 0.7, 0.4],
            metalness: 1.0,
            roughness: 0.3,
            ..Material::default()
        };
        let glow = Material {
            emission: [2.0, 1.0, 0.5],
            ..Material::default()
        };
        Scene {
            materials: vec![lambert([0.7, 0.6, 0.5]), glass, metal, glow],
            objects: vec![
                object(infinite_plane([0.0, -1.0, 0.0], [0.0, 1.0, 0.0]), 0),
                object(sphere([-0.8, -0.3, 0.5], 0.7), 1),
                object(Shape::Mesh(Arc::new(bumpy_icosphere(2, 0.05, 4))), 2),
                object(sphere([1.2, 0.4, 1.0], 0.3), 3),
            ],
            lights: vec![
                Light::Area {
                    corner: [-1.0, 2.0, -1.0],
                    edge_u: [0.0, 0.0, 2.0],
                    edge_v: [2.0, 0.0, 0.0],
                    radiance: [4.0; 3],
                },
                Light::Point {
                    position: [2.0, 2.0, -2.0],
                    intensity: [3.0; 3],
                },
                environment(0.2),
            ],
            cameras: vec![camera(
                37,
                29,
                50.0,
                [0.0, 0.5, -4.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            )],
        }
    }

    #[test]
    fn deterministic_for_any_thread_count_and_seeded() {
        let scene = busy_scene();
        for integrator in [Integrator::Path, Integrator::Whitted] {
            let opts = options(integrator, 4);
            let run = |threads: usize, opts: TraceOptions| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| trace_scene(&scene, 0, [0.0; 3], &opts).unwrap())
            };
            let one = run(1, opts);
            let three = run(3, opts);
            assert_eq!(one, three, "{integrator:?}");
            assert!(one.color.iter().all(|v| v.is_finite() && *v >= 0.0));
            let mut other = opts;
            other.seed = 1;
            let reseeded = run(3, other);
            assert_ne!(
                one.color, reseeded.color,
                "{integrator:?}: the seed changes the noise"
            );
            assert_eq!(one.depth, reseeded.depth);
            // Same mean brightness within noise.
            let mean = |v: &[f32]| v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64;
            let (a, b) = (mean(&one.color), mean(&reseeded.color));
            assert!((a - b).abs() < 0.05 * a, "{a} {b}");
        }
    }

    #[test]
    fn degenerate_inputs() {
        let cam = camera(5, 3, 40.0, [0.0, 0.0, -3.0], [0.0; 3], [0.0, 1.0, 0.0]);
        // Empty scene: the background everywhere, no hits.
        let empty = Scene {
            cameras: vec![cam.clone()],
            ..Scene::default()
        };
        let bg = [0.25, 0.5, 0.125];
        for integrator in [Integrator::Path, Integrator::Whitted] {
            let img = trace_scene(&empty, 0, bg, &options(integrator, 2)).unwrap();
            assert_eq!(img.hits, 0);
            for i in 0..15 {
                assert_eq!(&img.color[3 * i..3 * i + 3], &[0.25, 0.5, 0.125]);
                assert_eq!(img.depth[i], f32::INFINITY);
                assert_eq!(img.ids[i], -1.0);
            }
        }
        // 1×1 image.
        let one = Scene {
            materials: vec![lambert([0.5; 3])],
            objects: vec![object(sphere([0.0; 3], 1.0), 0)],
            lights: vec![environment(1.0)],
            cameras: vec![camera(
                1,
                1,
                10.0,
                [0.0, 0.0, -3.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
            )],
        };
        let img = trace_scene(&one, 0, [0.0; 3], &options(Integrator::Path, 4)).unwrap();
        assert_eq!((img.width, img.height, img.hits), (1, 1, 1));
        assert!((img.color[0] - 0.5).abs() < 1e-6 && (img.depth[0] - 2.0).abs() < 1e-6);
        // Errors.
        let mut nan = bumpy_icosphere(1, 0.0, 1);
        nan.positions[3][1] = f32::NAN;
        let bad = Scene {
            materials: vec![lambert([0.5; 3])],
            objects: vec![object(Shape::Mesh(Arc::new(nan)), 0)],
            cameras: vec![cam.clone()],
            ..Scene::default()
        };
        let e = trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default()).unwrap_err();
        assert!(e.contains("vertex 3") && e.contains("non-finite"), "{e}");
        let mut bad = one.clone();
        bad.objects[0].material = 1;
        let e = trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default()).unwrap_err();
        assert!(e.contains("material index 1"), "{e}");
        let e = trace_scene(&one, 1, [0.0; 3], &TraceOptions::default()).unwrap_err();
        assert!(e.contains("camera 1"), "{e}");
        let e = trace_scene(&one, 0, [0.0; 3], &options(Integrator::Path, 0)).unwrap_err();
        assert!(e.contains("spp"), "{e}");
        let mut bad = one.clone();
        bad.materials[0].roughness = f32::NAN;
        assert!(
            trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default())
                .unwrap_err()
                .contains("roughness")
        );
        let mut bad = one.clone();
        bad.objects[0].shape = sphere([0.0; 3], -1.0);
        assert!(trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default()).is_err());
        bad.objects[0].shape = infinite_plane([0.0; 3], [0.0; 3]);
        assert!(trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default()).is_err());
        let mut bad = one.clone();
        bad.objects[0].scale = 0.0;
        assert!(
            trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default())
                .unwrap_err()
                .contains("scale")
        );
        let mut bad = one.clone();
        bad.lights.push(Light::Area {
            corner: [0.0; 3],
            edge_u: [1.0, 0.0, 0.0],
            edge_v: [2.0, 0.0, 0.0],
            radiance: [1.0; 3],
        });
        assert!(
            trace_scene(&bad, 0, [0.0; 3], &TraceOptions::default())
                .unwrap_err()
                .contains("parallel")
        );
        assert!(trace_scene(&one, 0, [f64::NAN, 0.0, 0.0], &TraceOptions::default()).is_err());
        let mut opts = TraceOptions {
            max_depth: 65,
            ..TraceOptions::default()
        };
        assert!(opts.validate().is_err());
        opts.max_depth = 8;
        opts.exposure = f64::INFINITY;
        assert!(opts.validate().is_err());
    }

    #[test]
    fn tone_curves() {
        // Reinhard on luminance: a gray of luminance L maps to L/(1+L); hue is kept.
        let g = tone_map([1.0; 3], ToneMap::Reinhard, 0.0);
        for c in g {
            assert!((c - 0.5).abs() < 1e-12);
        }
        let g = tone_map([1.0; 3], ToneMap::Reinhard, 1.0);
        assert!(
            (g[0] - 2.0 / 3.0).abs() < 1e-12,
            "one stop doubles the input"
        );
        let c = tone_map([0.4, 0.2, 0.1], ToneMap::Reinhard, 0.0);
        assert!((c[0] / c[1] - 2.0).abs() < 1e-12 && (c[1] / c[2] - 2.0).abs() < 1e-12);
        let l = 0.2126 * 0.4 + 0.7152 * 0.2 + 0.0722 * 0.1;
        assert!((c[0] - 0.4 / (1.0 + l)).abs() < 1e-12);
        // ACES (Narkowicz): 0 → 0, 1 → 2.54/3.16, saturates to 1, monotone.
        assert_eq!(aces_narkowicz(0.0), 0.0);
        assert!((aces_narkowicz(1.0) - 2.54 / 3.16).abs() < 1e-12);
        assert_eq!(aces_narkowicz(100.0), 1.0);
        let mut prev = 0.0;
        for i in 1..200 {
            let y = aces_narkowicz(i as f64 * 0.05);
            assert!(y >= prev);
            prev = y;
        }
        assert_eq!(
            tone_map([3.0, 0.5, 0.0], ToneMap::None, -1.0),
            [1.5, 0.25, 0.0]
        );
    }

    #[test]
    fn random_streams_are_uniform_and_independent() {
        let mut a = SampleRng::new(0, 5, 0);
        let mut b = SampleRng::new(0, 5, 1);
        let mut c = SampleRng::new(1, 5, 0);
        let n = 100_000;
        let (mut sa, mut sab, mut equal) = (0.0, 0.0, 0);
        for _ in 0..n {
            let (x, y, z) = (a.next_f64(), b.next_f64(), c.next_f64());
            assert!((0.0..1.0).contains(&x));
            sa += x;
            sab += (x - 0.5) * (y - 0.5);
            equal += usize::from(x == y || x == z);
        }
        assert!((sa / n as f64 - 0.5).abs() < 0.005);
        assert!((sab / n as f64).abs() < 0.002, "streams are uncorrelated");
        assert_eq!(equal, 0);
        // Reproducible.
        let mut d = SampleRng::new(0, 5, 0);
        let mut e = SampleRng::new(0, 5, 0);
        assert_eq!(d.next_u64(), e.next_u64());
    }

    #[test]
    fn operator_runs_and_validates_params() {
        let op = Trace::new(TraceParams {
            spp: 2,
            ..TraceParams::default()
        })
        .unwrap();
        let scene = busy_scene();
        let specs = Trace::inputs();
        let values = vec![Some(Value::Scene(Arc::new(scene)))];
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        for name in [
            "color",
            "depth",
            "normals",
            "ids",
            "ray_origins",
            "ray_directions",
        ] {
            assert!(out.names().any(|n| n == name), "{name}");
        }
        let mut out = out;
        match out.take("color") {
            Some(Value::Image(img)) => {
                assert_eq!(
                    (img.width(), img.height(), img.channels()),
                    (37, 29, Channels::Rgb)
                );
            }
            other => panic!("{other:?}"),
        }
        match out.take("hits") {
            Some(Value::Integer(h)) => assert!(h > 100),
            other => panic!("{other:?}"),
        }
        assert!(
            Trace::new(TraceParams {
                spp: 0,
                ..TraceParams::default()
            })
            .is_err()
        );
        assert!(
            Trace::new(TraceParams {
                background: [-1.0, 0.0, 0.0],
                ..TraceParams::default()
            })
            .is_err()
        );
        let bad = TraceParams {
            camera: 3,
            ..TraceParams::default()
        };
        let op = Trace::new(bad).unwrap();
        assert!(op.run(&ctx, &Inputs::new(&specs, &values)).is_err());
    }
}
