//! The triangle rasterizer behind `render.rasterize`: a tiled, parallel, watertight scan
//! converter with a z-buffer, near-plane clipping, analytic impostors for spheres, planes and
//! quadrics, perspective-correct interpolation, MSAA, textures, per-model shading, directional
//! shadow maps and sorted alpha blending.
//!
//! Pipeline of [`rasterize_view`]:
//!
//! 1. **Vertices.** Mesh vertices go to world space (`R·(scale·p) + t`) and then to the
//!    homogeneous clip space of the camera, `(X, Y, W) = (fx·x + skew·y + cx·z, fy·y + cy·z, z)`
//!    for the camera-space point `(x, y, z)`; pixel coordinates are `(X/W, Y/W)` with pixel
//!    centres at integers (see [`View`]).
//! 2. **Triangle setup.** Back/front faces are culled by winding; triangles entirely outside
//!    one frustum plane are dropped; triangles crossing the near plane `W = near` or leaving
//!    the guard band ([`GUARD_BAND`] pixels around the viewport) are clipped by
//!    Sutherland–Hodgman in homogeneous coordinates (Sutherland & Hodgman 1974; Blinn & Newell
//!    1978) and fan-triangulated. Intersection points are computed from the two ends of an
//!    edge in a canonical order, so two triangles sharing a clipped edge get bit-identical
//!    new vertices and stay watertight. Vertices are snapped to [`SUBPIXEL_BITS`] fractional
//!    bits.
//! 3. **Binning.** Primitives are binned to [`TILE`]×[`TILE`] screen tiles by their bounding
//!    boxes, in scene order (chunks binned in parallel, concatenated in order).
//! 4. **Tiles in parallel.** Each tile scans its primitives in scene order with Pineda's edge
//!    functions (Pineda 1988) in i64 fixed point, evaluated incrementally across the
//!    primitive's bounding box, with the top-left fill rule (a sample exactly on an edge
//!    belongs to the triangle for which that edge is a top or left edge), so a sample on an
//!    edge shared by two triangles is drawn by exactly one. The z-buffer holds `1/w` (larger
//!    is nearer), a linear function of the pixel position obtained from the inverse of the
//!    3×3 matrix of the triangle's clip-space corners (2-D homogeneous rasterization, Olano &
//!    Greer 1997); a primitive replaces a sample only when strictly nearer, so equal depths
//!    keep the earlier primitive in scene order and the image is the same for any thread
//!    count. Analytic shapes are per-pixel impostors: their clipped bounding box gives a
//!    screen rectangle where every sample's ray is intersected exactly and z-tested against
//!    the triangles in the same buffer.
//! 5. **Shading** (visibility buffer). Each pixel shades each distinct visible primitive once
//!    (MSAA; Akeley 1993): at the pixel centre when that primitive is the one visible at the
//!    centre, otherwise at its first covered sample (like centroid sampling, so attributes
//!    are never extrapolated off a triangle). Attributes are interpolated perspective-correctly
//!    (Heckbert & Moreton 1991): the three linear functions `kᵢ(x, y)` of the homogeneous
//!    setup are `λᵢ/wᵢ` up to a common factor, `Σ kᵢ = 1/w`, and an attribute is
//!    `Σ kᵢ aᵢ / Σ kᵢ`; uv derivatives for mip-mapping are the analytic derivatives of that
//!    quotient. Transparent primitives (`opacity < 1`) are then drawn back to front by
//!    centroid depth and blended "over" (Porter & Duff 1984) without writing depth.
//!
//! The `depth`, `normals`, `ids` and `hits` outputs describe the sample at the pixel centre
//! (also with 4× MSAA, where a fifth, centre sample is rasterized alongside the four
//! rotated-grid ones), so they are comparable with [`super::raycast::raycast_depth`].

use std::f64::consts::PI;

use ocellus_engine::value::{
    Channels, Image, Light, Material, Mesh, PixelData, Scene, Shading, Shape, Value,
};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, param_enum, params,
};
use rayon::prelude::*;

use super::scene::View;
use super::texture::TextureSampler;

/// Fractional bits of snapped screen coordinates (1/256 pixel).
pub const SUBPIXEL_BITS: u32 = 8;
const SUB: i64 = 1 << SUBPIXEL_BITS;
/// Side of the square screen tiles rasterized as one work item, pixels.
pub const TILE: usize = 64;
const TT: usize = TILE * TILE;
/// Width of the guard band around the viewport, pixels: triangles reaching farther are
/// clipped to it, so snapped coordinates stay below 2²⁵ and the i64 edge functions cannot
/// overflow.
pub const GUARD_BAND: f64 = 65_536.0;
/// Sample offsets in 1/256 pixel for 4× MSAA: the rotated grid of Direct3D's standard
/// pattern (±1/8, ±3/8 px).
pub const RGSS_OFFSETS: [[i64; 2]; 4] = [[-32, -96], [96, -32], [-96, 32], [32, 96]];
/// The sample pattern with `samples = 1`: the pixel centre.
const PATTERN_1: [[i64; 2]; 1] = [[0, 0]];
/// With `samples = 4`: the pixel centre (for depth, ids, normals, hits) then the four
/// rotated-grid colour samples.
const PATTERN_5: [[i64; 2]; 5] = [[0, 0], [-32, -96], [96, -32], [-96, 32], [32, 96]];
/// Marks an empty sample and an impostor primitive.
const NONE: u32 = u32::MAX;
/// Largest `shadow_map_size`.
pub const MAX_SHADOW_MAP_SIZE: u32 = 8192;

type V3 = [f64; 3];

#[inline(always)]
fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
#[inline(always)]
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
#[inline(always)]
fn mul(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
#[inline(always)]
fn hadamard(a: V3, b: V3) -> V3 {
    [a[0] * b[0], a[1] * b[1], a[2] * b[2]]
}
#[inline(always)]
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline(always)]
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
#[inline(always)]
fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
/// `a / |a|`, or zero for a zero vector.
#[inline(always)]
fn normalize(a: V3) -> V3 {
    let n = norm(a);
    if n > 0.0 { mul(a, 1.0 / n) } else { [0.0; 3] }
}
fn rotate(r: &[f64; 9], v: V3) -> V3 {
    [
        r[0] * v[0] + r[1] * v[1] + r[2] * v[2],
        r[3] * v[0] + r[4] * v[1] + r[5] * v[2],
        r[6] * v[0] + r[7] * v[1] + r[8] * v[2],
    ]
}
fn rotate_t(r: &[f64; 9], v: V3) -> V3 {
    [
        r[0] * v[0] + r[3] * v[1] + r[6] * v[2],
        r[1] * v[0] + r[4] * v[1] + r[7] * v[2],
        r[2] * v[0] + r[5] * v[1] + r[8] * v[2],
    ]
}
fn f3(a: [f32; 3]) -> V3 {
    a.map(f64::from)
}

/// An orthonormal basis `(t, b)` completing the unit vector `n` to a right-handed frame
/// `(t, b, n)` (Duff et al., "Building an orthonormal basis, revisited", JCGT 2017).
pub fn orthonormal_basis(n: V3) -> (V3, V3) {
    let sign = if n[2] >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sign + n[2]);
    let b = n[0] * n[1] * a;
    (
        [1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]],
        [b, sign + n[1] * n[1] * a, -n[1]],
    )
}

/// Inverse of the 3×3 matrix whose columns are `c`, or `None` when singular.
fn inverse_of_columns(c: &[V3; 3]) -> Option<[V3; 3]> {
    // Rows of the inverse are the cross products of pairs of columns over the determinant.
    let r0 = cross(c[1], c[2]);
    let r1 = cross(c[2], c[0]);
    let r2 = cross(c[0], c[1]);
    let det = dot(c[0], r0);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    Some([mul(r0, inv), mul(r1, inv), mul(r2, inv)])
}

param_enum! {
    /// Which triangles are discarded by winding.
    pub enum Cull {
        /// Draw both sides.
        None = "none",
        /// Discard triangles facing away from the camera.
        Back = "back",
        /// Discard triangles facing the camera.
        Front = "front",
    }
}

/// Options of [`rasterize_view`].
#[derive(Debug, Clone, PartialEq)]
pub struct RasterOptions {
    /// Face culling by winding.
    pub cull: Cull,
    /// Samples per pixel: 1 or 4 (rotated-grid MSAA).
    pub samples: u32,
    /// Near-plane distance along the optical axis, world units (> 0).
    pub near: f64,
    /// Side of each directional light's shadow map, texels; 0 disables shadows.
    pub shadow_map_size: u32,
    /// Colour of samples no surface covers, linear RGB.
    pub background: [f32; 3],
}

impl Default for RasterOptions {
    fn default() -> Self {
        RasterOptions {
            cull: Cull::None,
            samples: 1,
            near: 1e-3,
            shadow_map_size: 1024,
            background: [0.0; 3],
        }
    }
}

impl RasterOptions {
    /// Why the options are unusable, if they are.
    pub fn validate(&self) -> Result<(), String> {
        if self.samples != 1 && self.samples != 4 {
            return Err(format!("`samples` must be 1 or 4, got {}", self.samples));
        }
        if !(self.near > 0.0 && self.near.is_finite()) {
            return Err(format!("`near` must be finite and > 0, got {}", self.near));
        }
        if self.shadow_map_size > MAX_SHADOW_MAP_SIZE {
            return Err(format!(
                "`shadow_map_size` must be at most {MAX_SHADOW_MAP_SIZE}, got {}",
                self.shadow_map_size
            ));
        }
        if !self.background.iter().all(|v| v.is_finite()) {
            return Err("`background` must be finite".into());
        }
        Ok(())
    }

    fn pattern(&self) -> &'static [[i64; 2]] {
        if self.samples == 4 {
            &PATTERN_5
        } else {
            &PATTERN_1
        }
    }
}

/// What [`rasterize_view`] produces, row-major, `width × height` pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct RasterOutput {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Linear RGB radiance, 3 per pixel (MSAA resolved by averaging the samples).
    pub color: Vec<f32>,
    /// Distance from the eye along the pixel centre's unit ray to the visible surface, `+∞`
    /// where nothing covers the centre.
    pub depth: Vec<f32>,
    /// World-space unit normal of the visible surface at the centre (interpolated vertex
    /// normals, or the face normal; turned to face the camera), 3 per pixel, 0 where empty.
    pub normals: Vec<f32>,
    /// Index in `scene.objects` of the surface visible at the centre, −1 where empty.
    pub ids: Vec<f32>,
    /// Pixels whose centre is covered.
    pub hits: usize,
}

// ---------------------------------------------------------------------------------------------
// Projection.

/// A pixel sample's ray: origin, unit direction, smallest usable `t` (the near plane) and the
/// camera-z of the unit direction (perspective) used to turn `t` into the z-buffer key.
#[derive(Debug, Clone, Copy)]
struct SampleRay {
    origin: V3,
    dir: V3,
    t_min: f64,
    dz: f64,
}

/// The camera of a pass: the perspective main view, or the orthographic view of a directional
/// light's shadow map.
#[derive(Debug, Clone)]
enum Projector {
    Perspective {
        view: View,
        near: f64,
    },
    Orthographic {
        ex: V3,
        ey: V3,
        ez: V3,
        /// World coordinates along `ex`, `ey` of texel (0, 0)'s centre.
        x0: f64,
        y0: f64,
        texel: f64,
        /// Depth origin along `ez`.
        d0: f64,
        size: usize,
    },
}

impl Projector {
    fn size(&self) -> (usize, usize) {
        match self {
            Projector::Perspective { view, .. } => (view.width, view.height),
            Projector::Orthographic { size, .. } => (*size, *size),
        }
    }

    /// Homogeneous clip coordinates `(X, Y, W)` of a world point.
    #[inline]
    fn clip(&self, p: V3) -> V3 {
        match self {
            Projector::Perspective { view, .. } => {
                let c = view.to_camera(p);
                [
                    view.fx * c[0] + view.skew * c[1] + view.cx * c[2],
                    view.fy * c[1] + view.cy * c[2],
                    c[2],
                ]
            }
            Projector::Orthographic {
                ex,
                ey,
                x0,
                y0,
                texel,
                ..
            } => [(dot(p, *ex) - x0) / texel, (dot(p, *ey) - y0) / texel, 1.0],
        }
    }

    /// The weight of a vertex in the z-buffer key `Σ kᵢ·weightᵢ`: 1 in perspective (the key is
    /// `1/w`), minus the depth in orthographic views (the key is `−depth`; `kᵢ` are then the
    /// plain barycentrics).
    #[inline]
    fn key_weight(&self, p: V3) -> f64 {
        match self {
            Projector::Perspective { .. } => 1.0,
            Projector::Orthographic { ez, d0, .. } => -(dot(p, *ez) - d0),
        }
    }

    fn near(&self) -> Option<f64> {
        match self {
            Projector::Perspective { near, .. } => Some(*near),
            Projector::Orthographic { .. } => None,
        }
    }

    /// The ray through pixel coordinates `(x, y)`.
    #[inline]
    fn ray(&self, x: f64, y: f64) -> SampleRay {
        match self {
            Projector::Perspective { view, near } => {
                let dir = view.ray_direction(x, y);
                let r = &view.rotation;
                let dz = r[6] * dir[0] + r[7] * dir[1] + r[8] * dir[2];
                SampleRay {
                    origin: view.eye,
                    dir,
                    t_min: near / dz,
                    dz,
                }
            }
            Projector::Orthographic {
                ex,
                ey,
                ez,
                x0,
                y0,
                texel,
                d0,
                ..
            } => SampleRay {
                origin: add(
                    add(mul(*ex, x0 + x * texel), mul(*ey, y0 + y * texel)),
                    mul(*ez, *d0),
                ),
                dir: *ez,
                t_min: f64::NEG_INFINITY,
                dz: 1.0,
            },
        }
    }

    /// The z-buffer key of the point at `t` along `ray`.
    #[inline]
    fn key(&self, ray: &SampleRay, t: f64) -> f64 {
        match self {
            Projector::Perspective { .. } => 1.0 / (t * ray.dz),
            Projector::Orthographic { .. } => -t,
        }
    }

    /// Whether a triangle with world corners `p` faces the camera (counter-clockwise seen
    /// from the camera in a right-handed world: the screen-space winding, evaluated in 3-D
    /// so that it is also defined for triangles crossing the near plane); `None` edge-on.
    fn front_facing(&self, p: &[V3; 3]) -> Option<bool> {
        let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        let s = match self {
            Projector::Perspective { view, .. } => dot(n, sub(view.eye, p[0])),
            Projector::Orthographic { ez, .. } => -dot(n, *ez),
        };
        if s > 0.0 {
            Some(true)
        } else if s < 0.0 {
            Some(false)
        } else {
            None
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Scene geometry.

/// An analytic shape in world coordinates, drawn as a per-pixel impostor.
#[derive(Debug, Clone)]
enum Analytic {
    Sphere {
        center: V3,
        radius: f64,
        /// Object-to-world rotation (texture coordinates follow the object).
        rotation: [f64; 9],
    },
    Plane {
        point: V3,
        normal: V3,
        /// In-plane axes of the texture coordinates (world units).
        t1: V3,
        t2: V3,
        half: f64,
    },
    Quadric {
        q: [[f64; 4]; 4],
        min: V3,
        max: V3,
        rotation: [f64; 9],
        translation: V3,
        scale: f64,
    },
}

/// A ray–shape intersection: parameter and outward unit normal.
#[derive(Debug, Clone, Copy)]
struct ShapeHit {
    t: f64,
    n: V3,
}

/// Real roots of `a t² + b t + c = 0` in increasing order (numerically stable form).
fn quadratic_roots(a: f64, b: f64, c: f64) -> [Option<f64>; 2] {
    if a == 0.0 {
        if b == 0.0 {
            return [None, None];
        }
        return [Some(-c / b), None];
    }
    let disc = b * b - 4.0 * a * c;
    if disc.is_nan() || disc < 0.0 {
        return [None, None];
    }
    let s = disc.sqrt();
    let q = -0.5 * (b + if b >= 0.0 { s } else { -s });
    let (r0, r1) = if q == 0.0 { (0.0, 0.0) } else { (q / a, c / q) };
    if r0 <= r1 {
        [Some(r0), Some(r1)]
    } else {
        [Some(r1), Some(r0)]
    }
}

impl Analytic {
    /// Intersections of `o + t·d` (`d` unit) in increasing `t`.
    fn hits(&self, o: V3, d: V3) -> [Option<ShapeHit>; 2] {
        match self {
            Analytic::Sphere { center, radius, .. } => {
                // Hearn & Baker's form with the discriminant from the closest approach
                // (Haines et al., "Precision improvements for ray/sphere intersection", 2019).
                let oc = sub(o, *center);
                let b = dot(oc, d);
                let closest = sub(oc, mul(d, b));
                let disc = radius * radius - dot(closest, closest);
                if disc.is_nan() || disc < 0.0 {
                    return [None, None];
                }
                let c = dot(oc, oc) - radius * radius;
                let q = -b - if b >= 0.0 { disc.sqrt() } else { -disc.sqrt() };
                let (mut t0, mut t1) = if q == 0.0 { (0.0, 0.0) } else { (q, c / q) };
                if t0 > t1 {
                    std::mem::swap(&mut t0, &mut t1);
                }
                let hit = |t: f64| ShapeHit {
                    t,
                    n: mul(sub(add(o, mul(d, t)), *center), 1.0 / radius),
                };
                [Some(hit(t0)), Some(hit(t1))]
            }
            Analytic::Plane {
                point,
                normal,
                t1,
                t2,
                half,
            } => {
                let den = dot(*normal, d);
                if den == 0.0 {
                    return [None, None];
                }
                let t = dot(sub(*point, o), *normal) / den;
                if !t.is_finite() {
                    return [None, None];
                }
                if half.is_finite() {
                    let rel = sub(add(o, mul(d, t)), *point);
                    if dot(rel, *t1).abs() > *half || dot(rel, *t2).abs() > *half {
                        return [None, None];
                    }
                }
                [Some(ShapeHit { t, n: *normal }), None]
            }
            Analytic::Quadric {
                q,
                min,
                max,
                rotation,
                translation,
                scale,
            } => {
                let oo = mul(rotate_t(rotation, sub(o, *translation)), 1.0 / scale);
                let dd = mul(rotate_t(rotation, d), 1.0 / scale);
                let oh = [oo[0], oo[1], oo[2], 1.0];
                let dh = [dd[0], dd[1], dd[2], 0.0];
                let qv = |v: &[f64; 4]| -> [f64; 4] {
                    [0, 1, 2, 3].map(|i| (0..4).map(|j| q[i][j] * v[j]).sum::<f64>())
                };
                let qo = qv(&oh);
                let qd = qv(&dh);
                let a = (0..4).map(|i| dh[i] * qd[i]).sum::<f64>();
                let b = 2.0 * (0..4).map(|i| dh[i] * qo[i]).sum::<f64>();
                let c = (0..4).map(|i| oh[i] * qo[i]).sum::<f64>();
                // A nearly vanishing quadratic term (the ray parallel to a cylinder's axis, a
                // paraboloid's axis) is solved as linear.
                let scale_ab = a.abs() * 1e12;
                let a = if scale_ab < b.abs() && a.abs() < 1e-12 * (b * b + c.abs()) {
                    0.0
                } else {
                    a
                };
                let roots = quadratic_roots(a, b, c);
                let mut out = [None, None];
                let mut k = 0;
                for t in roots.into_iter().flatten() {
                    if !t.is_finite() {
                        continue;
                    }
                    let x = add(oo, mul(dd, t));
                    let inside = (0..3).all(|i| x[i] >= min[i] && x[i] <= max[i]);
                    if !inside {
                        continue;
                    }
                    let xh = [x[0], x[1], x[2], 1.0];
                    let g = qv(&xh);
                    let n = normalize(rotate(rotation, [g[0], g[1], g[2]]));
                    if n == [0.0; 3] {
                        continue;
                    }
                    out[k] = Some(ShapeHit { t, n });
                    k += 1;
                }
                out
            }
        }
    }

    /// The first intersection at `t ≥ t_min` that survives culling.
    #[inline]
    fn first_hit(&self, ray: &SampleRay, cull: Cull) -> Option<ShapeHit> {
        self.hits(ray.origin, ray.dir)
            .into_iter()
            .flatten()
            .find(|h| {
                if h.t.is_nan() || h.t < ray.t_min {
                    return false;
                }
                let front = dot(h.n, ray.dir) < 0.0;
                match cull {
                    Cull::None => true,
                    Cull::Back => front,
                    Cull::Front => !front,
                }
            })
    }

    /// World corners of a bounding box, or `None` when unbounded.
    fn bounds(&self) -> Option<[V3; 8]> {
        let corners = |lo: V3, hi: V3| -> [V3; 8] {
            [0, 1, 2, 3, 4, 5, 6, 7].map(|i| {
                [
                    if i & 1 == 0 { lo[0] } else { hi[0] },
                    if i & 2 == 0 { lo[1] } else { hi[1] },
                    if i & 4 == 0 { lo[2] } else { hi[2] },
                ]
            })
        };
        let out = match self {
            Analytic::Sphere { center, radius, .. } => {
                corners(sub(*center, [*radius; 3]), add(*center, [*radius; 3]))
            }
            Analytic::Plane {
                point,
                t1,
                t2,
                half,
                ..
            } => {
                let a = mul(*t1, *half);
                let b = mul(*t2, *half);
                let c = [
                    add(*point, add(a, b)),
                    add(*point, sub(a, b)),
                    sub(*point, add(a, b)),
                    sub(*point, sub(a, b)),
                ];
                [c[0], c[1], c[2], c[3], c[0], c[1], c[2], c[3]]
            }
            Analytic::Quadric {
                min,
                max,
                rotation,
                translation,
                scale,
                ..
            } => corners(*min, *max).map(|c| add(rotate(rotation, mul(c, *scale)), *translation)),
        };
        out.iter()
            .all(|c| c.iter().all(|v| v.is_finite()))
            .then_some(out)
    }

    /// Texture coordinates of a point on (or, for ray differentials, near) the surface.
    fn uv(&self, p: V3) -> [f64; 2] {
        match self {
            Analytic::Sphere {
                center, rotation, ..
            } => sphere_uv(normalize(rotate_t(rotation, sub(p, *center)))),
            Analytic::Plane { point, t1, t2, .. } => {
                let rel = sub(p, *point);
                [dot(rel, *t1), dot(rel, *t2)]
            }
            Analytic::Quadric { .. } => [0.0, 0.0],
        }
    }

    /// `∂P/∂u` and `∂P/∂v` at the surface point `p` with outward normal `n` (an arbitrary
    /// frame where the shape has no texture coordinates).
    fn tangents(&self, p: V3, n: V3) -> (V3, V3) {
        match self {
            Analytic::Sphere {
                center,
                radius,
                rotation,
            } => {
                let d = normalize(rotate_t(rotation, sub(p, *center)));
                let (tu, tv) = sphere_tangents(d);
                (
                    mul(rotate(rotation, tu), *radius),
                    mul(rotate(rotation, tv), *radius),
                )
            }
            Analytic::Plane { t1, t2, .. } => (*t1, *t2),
            Analytic::Quadric { .. } => orthonormal_basis(n),
        }
    }

    fn wraps_u(&self) -> bool {
        matches!(self, Analytic::Sphere { .. })
    }
}

/// Texture coordinates of the unit direction `d` (object frame) on a sphere: `u` the
/// longitude about +y, `v = 1 − θ/π` with `θ` the polar angle from +y, so the north pole is
/// the top row of the image (OBJ convention, `v` up) — the same longitude/latitude layout as
/// the environment maps' [`TextureSampler::sample_direction`].
pub fn sphere_uv(d: V3) -> [f64; 2] {
    let u = 0.5 + d[0].atan2(-d[2]) / (2.0 * PI);
    let v = 1.0 - d[1].clamp(-1.0, 1.0).acos() / PI;
    [u, v]
}

/// `∂d/∂u`, `∂d/∂v` of the unit direction `d` for [`sphere_uv`] (zero `∂d/∂u` at the poles).
fn sphere_tangents(d: V3) -> (V3, V3) {
    // d = (sin θ sin φ, cos θ, −sin θ cos φ) with φ = 2π(u − ½), θ = π(1 − v).
    let sin_t = (d[0] * d[0] + d[2] * d[2]).sqrt();
    let (sp, cp) = if sin_t > 0.0 {
        (d[0] / sin_t, -d[2] / sin_t)
    } else {
        (0.0, 1.0)
    };
    let cos_t = d[1];
    let du = mul([sin_t * cp, 0.0, sin_t * sp], 2.0 * PI);
    // ∂d/∂θ = (cos θ sin φ, −sin θ, −cos θ cos φ); ∂θ/∂v = −π.
    let dv = mul([cos_t * sp, -sin_t, -cos_t * cp], -PI);
    (du, dv)
}

/// A mesh object in world coordinates.
#[derive(Debug)]
struct MeshGeom<'a> {
    mesh: &'a Mesh,
    world: Vec<V3>,
    /// World-space unit vertex normals.
    normals: Option<Vec<V3>>,
}

#[derive(Debug)]
// Few per scene (one per object), so the size difference does not matter.
#[allow(clippy::large_enum_variant)]
enum Geom<'a> {
    Mesh(MeshGeom<'a>),
    Analytic(Analytic),
}

/// Everything about a scene the passes read.
#[derive(Debug)]
struct Prepared<'a> {
    geom: Vec<Geom<'a>>,
    /// Whether each object is drawn in the opaque pass.
    opaque: Vec<bool>,
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// The checks [`rasterize_view`] makes on a scene before drawing it, with messages naming the
/// offending object, material or light.
pub fn validate_scene(scene: &Scene) -> Result<(), String> {
    for (i, m) in scene.materials.iter().enumerate() {
        let name = &m.name;
        let scalars = [
            m.roughness,
            m.metalness,
            m.specular,
            m.shininess,
            m.opacity,
            m.ior,
            m.transmission,
        ];
        if !m
            .albedo
            .iter()
            .chain(&m.emission)
            .chain(&scalars)
            .all(|v| v.is_finite())
        {
            return Err(format!(
                "material {i} (`{name}`) has a non-finite parameter"
            ));
        }
        if !(0.0..=1.0).contains(&m.opacity) {
            return Err(format!(
                "material {i} (`{name}`): `opacity` must be in [0, 1], got {}",
                m.opacity
            ));
        }
        if m.shininess < 0.0 {
            return Err(format!(
                "material {i} (`{name}`): `shininess` must be ≥ 0, got {}",
                m.shininess
            ));
        }
    }
    for (i, o) in scene.objects.iter().enumerate() {
        let name = &o.name;
        if o.material as usize >= scene.materials.len() {
            return Err(format!(
                "object {i} (`{name}`) uses material {} but the scene has {} material(s)",
                o.material,
                scene.materials.len()
            ));
        }
        if !(o.scale > 0.0 && o.scale.is_finite()) {
            return Err(format!(
                "object {i} (`{name}`): `scale` must be finite and > 0, got {}",
                o.scale
            ));
        }
        let q = o.world_from_object.rotation;
        let qn = q.iter().map(|v| v * v).sum::<f64>();
        if !(q.iter().all(|v| v.is_finite())
            && qn > 0.0
            && finite3(&o.world_from_object.translation))
        {
            return Err(format!(
                "object {i} (`{name}`): `world_from_object` must be finite with a non-zero \
                 quaternion"
            ));
        }
        match &o.shape {
            Shape::Mesh(m) => {
                validate_mesh(m).map_err(|e| format!("object {i} (`{name}`): {e}"))?
            }
            Shape::Sphere { center, radius } => {
                if !(finite3(center) && *radius > 0.0 && radius.is_finite()) {
                    return Err(format!(
                        "object {i} (`{name}`): a sphere needs a finite centre and a finite \
                         radius > 0, got radius {radius}"
                    ));
                }
            }
            Shape::Plane {
                point,
                normal,
                half_extent,
            } => {
                if !finite3(point) || !finite3(normal) || dot(*normal, *normal) == 0.0 {
                    return Err(format!(
                        "object {i} (`{name}`): a plane needs a finite point and a finite \
                         non-zero normal"
                    ));
                }
                if half_extent.is_nan() || *half_extent <= 0.0 {
                    return Err(format!(
                        "object {i} (`{name}`): a plane's `half_extent` must be > 0 (or +inf), \
                         got {half_extent}"
                    ));
                }
            }
            Shape::Quadric {
                coefficients,
                min,
                max,
            } => {
                if !coefficients.iter().all(|v| v.is_finite()) {
                    return Err(format!(
                        "object {i} (`{name}`): quadric coefficients must be finite"
                    ));
                }
                if (0..3).any(|k| min[k].is_nan() || max[k].is_nan() || min[k] > max[k]) {
                    return Err(format!(
                        "object {i} (`{name}`): a quadric's clip box needs min ≤ max on every \
                         axis (infinite bounds allowed, NaN not)"
                    ));
                }
            }
        }
    }
    for (i, l) in scene.lights.iter().enumerate() {
        let ok = match l {
            Light::Point {
                position,
                intensity,
            } => finite3(position) && intensity.iter().all(|v| v.is_finite()),
            Light::Directional {
                direction,
                irradiance,
            } => {
                finite3(direction)
                    && dot(*direction, *direction) > 0.0
                    && irradiance.iter().all(|v| v.is_finite())
            }
            Light::Area {
                corner,
                edge_u,
                edge_v,
                radiance,
            } => {
                finite3(corner)
                    && finite3(edge_u)
                    && finite3(edge_v)
                    && norm(cross(*edge_u, *edge_v)) > 0.0
                    && radiance.iter().all(|v| v.is_finite())
            }
            Light::Environment { radiance, .. } => radiance.iter().all(|v| v.is_finite()),
        };
        if !ok {
            return Err(format!(
                "light {i} has a non-finite value or a zero direction / degenerate area"
            ));
        }
    }
    Ok(())
}

fn validate_mesh(m: &Mesh) -> Result<(), String> {
    if let Some(k) = m
        .positions
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(format!(
            "vertex {k} has a non-finite position {:?}",
            m.positions[k]
        ));
    }
    let n = m.positions.len();
    if let Some(k) = m
        .triangles
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= n))
    {
        return Err(format!(
            "triangle {k} {:?} indexes past the {n} vertices",
            m.triangles[k]
        ));
    }
    let check = |what: &str, len: Option<usize>, finite: bool| -> Result<(), String> {
        match len {
            Some(l) if l != n => Err(format!("{l} {what} for {n} vertices")),
            Some(_) if !finite => Err(format!("non-finite {what}")),
            _ => Ok(()),
        }
    };
    check(
        "normals",
        m.normals.as_ref().map(Vec::len),
        m.normals
            .iter()
            .flatten()
            .all(|v| v.iter().all(|x| x.is_finite())),
    )?;
    check(
        "uvs",
        m.uvs.as_ref().map(Vec::len),
        m.uvs
            .iter()
            .flatten()
            .all(|v| v.iter().all(|x| x.is_finite())),
    )?;
    check(
        "colors",
        m.colors.as_ref().map(Vec::len),
        m.colors
            .iter()
            .flatten()
            .all(|v| v.iter().all(|x| x.is_finite())),
    )
}

/// World-space geometry of a validated scene.
fn prepare(scene: &Scene) -> Prepared<'_> {
    let geom = scene
        .objects
        .iter()
        .map(|o| {
            let rotation = o.world_from_object.rotation_matrix();
            let t = o.world_from_object.translation;
            let s = o.scale;
            let to_world = |p: V3| add(rotate(&rotation, mul(p, s)), t);
            match &o.shape {
                Shape::Mesh(m) => {
                    let world: Vec<V3> = m
                        .positions
                        .par_iter()
                        .with_min_len(4096)
                        .map(|p| to_world(f3(*p)))
                        .collect();
                    let normals = m.normals.as_ref().map(|ns| {
                        ns.par_iter()
                            .with_min_len(4096)
                            .map(|n| normalize(rotate(&rotation, f3(*n))))
                            .collect()
                    });
                    Geom::Mesh(MeshGeom {
                        mesh: m,
                        world,
                        normals,
                    })
                }
                Shape::Sphere { center, radius } => Geom::Analytic(Analytic::Sphere {
                    center: to_world(*center),
                    radius: radius * s,
                    rotation,
                }),
                Shape::Plane {
                    point,
                    normal,
                    half_extent,
                } => {
                    let n_obj = normalize(*normal);
                    let (a, b) = orthonormal_basis(n_obj);
                    Geom::Analytic(Analytic::Plane {
                        point: to_world(*point),
                        normal: rotate(&rotation, n_obj),
                        t1: rotate(&rotation, a),
                        t2: rotate(&rotation, b),
                        half: half_extent * s,
                    })
                }
                Shape::Quadric {
                    coefficients: c,
                    min,
                    max,
                } => Geom::Analytic(Analytic::Quadric {
                    q: [
                        [c[0], c[1], c[2], c[3]],
                        [c[1], c[4], c[5], c[6]],
                        [c[2], c[5], c[7], c[8]],
                        [c[3], c[6], c[8], c[9]],
                    ],
                    min: *min,
                    max: *max,
                    rotation,
                    translation: t,
                    scale: s,
                }),
            }
        })
        .collect();
    let opaque = scene
        .objects
        .iter()
        .map(|o| {
            scene
                .materials
                .get(o.material as usize)
                .is_none_or(|m| m.opacity >= 1.0)
        })
        .collect();
    Prepared { geom, opaque }
}

// ---------------------------------------------------------------------------------------------
// Primitive setup.

/// One rasterizable primitive: a (possibly clipped) triangle in fixed point with its z-buffer
/// key plane, or an impostor's screen rectangle.
#[derive(Debug, Clone, Copy)]
struct Prim {
    /// Snapped corners, positively oriented (unused by impostors).
    v: [[i32; 2]; 3],
    /// `key = key[0]·x + key[1]·y + key[2]` at pixel coordinates (triangles).
    key: [f64; 3],
    /// Pixel range `[x0, y0, x1, y1]` (inclusive) that may hold covered samples.
    bbox: [u16; 4],
    object: u32,
    /// Triangle index in the mesh; [`NONE`] for an impostor.
    tri: u32,
}

/// A convex polygon in clip space (at most 3 + 5 clip planes vertices).
#[derive(Clone, Copy)]
struct Poly {
    v: [V3; 9],
    n: usize,
}

/// Lexicographic order of the bit patterns, so an edge is always interpolated from the same
/// end whichever triangle clips it.
fn canonical_first(a: &V3, b: &V3) -> bool {
    for k in 0..3 {
        if a[k] != b[k] {
            return a[k] < b[k];
        }
    }
    true
}

/// Sutherland–Hodgman: the part of `poly` where `plane · (X, Y, W, 1) ≥ 0`.
fn clip_poly(poly: &Poly, plane: [f64; 4]) -> Poly {
    let f = |c: &V3| plane[0] * c[0] + plane[1] * c[1] + plane[2] * c[2] + plane[3];
    let mut out = Poly {
        v: [[0.0; 3]; 9],
        n: 0,
    };
    for i in 0..poly.n {
        let a = poly.v[i];
        let b = poly.v[(i + 1) % poly.n];
        let (fa, fb) = (f(&a), f(&b));
        if fa >= 0.0 && out.n < 9 {
            out.v[out.n] = a;
            out.n += 1;
        }
        if (fa >= 0.0) != (fb >= 0.0) && out.n < 9 {
            let (p, q, fp, fq) = if canonical_first(&a, &b) {
                (a, b, fa, fb)
            } else {
                (b, a, fb, fa)
            };
            let t = fp / (fp - fq);
            out.v[out.n] = [0, 1, 2].map(|k| p[k] + t * (q[k] - p[k]));
            out.n += 1;
        }
    }
    out
}

#[inline]
fn floor_div(a: i64, b: i64) -> i64 {
    a.div_euclid(b)
}
#[inline]
fn ceil_div(a: i64, b: i64) -> i64 {
    -(-a).div_euclid(b)
}

/// Setup shared by every triangle of one pass.
struct SetupCtx<'p> {
    proj: &'p Projector,
    width: usize,
    height: usize,
    cull: Cull,
    /// Largest sample offset from a pixel centre, 1/256 px.
    reach: i64,
    /// Clip planes `(a, b, e, g)`: `a X + b Y + e W + g ≥ 0` inside; near first (if any),
    /// then the four guard-band planes.
    clip_planes: Vec<[f64; 4]>,
    /// The four viewport planes (trivial rejection), 1 px beyond the edge pixels' centres.
    view_planes: [[f64; 4]; 4],
}

impl<'p> SetupCtx<'p> {
    fn new(proj: &'p Projector, cull: Cull, reach: i64) -> Self {
        let (width, height) = proj.size();
        let (w, h) = (width as f64, height as f64);
        let g = GUARD_BAND;
        let mut clip_planes = Vec::with_capacity(5);
        if let Some(near) = proj.near() {
            clip_planes.push([0.0, 0.0, 1.0, -near]);
        }
        clip_planes.extend([
            [1.0, 0.0, g, 0.0],
            [-1.0, 0.0, w - 1.0 + g, 0.0],
            [0.0, 1.0, g, 0.0],
            [0.0, -1.0, h - 1.0 + g, 0.0],
        ]);
        SetupCtx {
            proj,
            width,
            height,
            cull,
            reach,
            clip_planes,
            view_planes: [
                [1.0, 0.0, 1.0, 0.0],
                [-1.0, 0.0, w, 0.0],
                [0.0, 1.0, 1.0, 0.0],
                [0.0, -1.0, h, 0.0],
            ],
        }
    }

    /// Appends the primitives of one triangle (none when culled, off-screen, degenerate or
    /// between sample positions).
    fn triangle(&self, c: [V3; 3], p: [V3; 3], object: u32, tri: u32, out: &mut Vec<Prim>) {
        let eval = |pl: &[f64; 4], v: &V3| pl[0] * v[0] + pl[1] * v[1] + pl[2] * v[2] + pl[3];
        // Trivial rejection: all corners outside one frustum plane.
        for pl in self.view_planes.iter().chain(&self.clip_planes[..1]) {
            if c.iter().all(|v| eval(pl, v) < 0.0) {
                return;
            }
        }
        match (self.cull, self.proj.front_facing(&p)) {
            (_, None) => return,
            (Cull::Back, Some(false)) | (Cull::Front, Some(true)) => return,
            _ => {}
        }
        let mut poly = Poly {
            v: [
                c[0], c[1], c[2], [0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3],
            ],
            n: 3,
        };
        for pl in &self.clip_planes {
            if poly.v[..poly.n].iter().any(|v| eval(pl, v) < 0.0) {
                poly = clip_poly(&poly, *pl);
                if poly.n < 3 {
                    return;
                }
            }
        }
        let mut fixed = [[0i64; 2]; 9];
        for (f, v) in fixed.iter_mut().zip(&poly.v[..poly.n]) {
            let (x, y) = (v[0] / v[2], v[1] / v[2]);
            if !(x.is_finite() && y.is_finite()) {
                return;
            }
            *f = [
                (x * SUB as f64).round() as i64,
                (y * SUB as f64).round() as i64,
            ];
        }
        let mut key = None;
        for i in 1..poly.n - 1 {
            let (a, mut b, mut cc) = (fixed[0], fixed[i], fixed[i + 1]);
            let area = (b[0] - a[0]) * (cc[1] - a[1]) - (b[1] - a[1]) * (cc[0] - a[0]);
            if area == 0 {
                continue;
            }
            if area < 0 {
                std::mem::swap(&mut b, &mut cc);
            }
            let r = self.reach;
            let x_lo = ceil_div(a[0].min(b[0]).min(cc[0]) - r, SUB).max(0);
            let x_hi = floor_div(a[0].max(b[0]).max(cc[0]) + r, SUB).min(self.width as i64 - 1);
            let y_lo = ceil_div(a[1].min(b[1]).min(cc[1]) - r, SUB).max(0);
            let y_hi = floor_div(a[1].max(b[1]).max(cc[1]) + r, SUB).min(self.height as i64 - 1);
            if x_lo > x_hi || y_lo > y_hi {
                continue;
            }
            if key.is_none() {
                // 2-D homogeneous setup of the original triangle: kᵢ(x, y) = M⁻¹ (x, y, 1).
                let Some(minv) = inverse_of_columns(&c) else {
                    return;
                };
                let w = p.map(|q| self.proj.key_weight(q));
                let row = [0, 1, 2].map(|j| (0..3).map(|i| w[i] * minv[i][j]).sum::<f64>());
                if !row.iter().all(|v| v.is_finite()) {
                    return;
                }
                key = Some(row);
            }
            let Some(k) = key else { return };
            out.push(Prim {
                v: [a, b, cc].map(|q| [q[0] as i32, q[1] as i32]),
                key: k,
                bbox: [x_lo as u16, y_lo as u16, x_hi as u16, y_hi as u16],
                object,
                tri,
            });
        }
    }

    /// The impostor of an analytic shape: its bounding box clipped to the near plane and
    /// projected, or the whole screen when unbounded.
    fn impostor(&self, a: &Analytic, object: u32) -> Option<Prim> {
        let (w, h) = (self.width as f64, self.height as f64);
        let full = Prim {
            v: [[0; 2]; 3],
            key: [0.0; 3],
            bbox: [0, 0, (self.width - 1) as u16, (self.height - 1) as u16],
            object,
            tri: NONE,
        };
        let Some(corners) = a.bounds() else {
            return Some(full);
        };
        let clip = corners.map(|c| self.proj.clip(c));
        let near = self.proj.near();
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        let mut take = |c: V3| {
            let (x, y) = (c[0] / c[2], c[1] / c[2]);
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        };
        let in_front = |c: &V3| near.is_none_or(|n| c[2] >= n);
        for c in &clip {
            if in_front(c) {
                take(*c);
            }
        }
        if let Some(n) = near {
            // Box edges (corners differing in one bit) crossing the near plane.
            for i in 0..8usize {
                for bit in [1usize, 2, 4] {
                    let j = i | bit;
                    if j == i {
                        continue;
                    }
                    let (p, q) = (clip[i], clip[j]);
                    if (p[2] >= n) != (q[2] >= n) {
                        let t = (n - p[2]) / (q[2] - p[2]);
                        take([0, 1, 2].map(|k| p[k] + t * (q[k] - p[k])));
                    }
                }
            }
        }
        if !(lo[0] <= hi[0] && lo[1] <= hi[1]) {
            return None;
        }
        let x0 = (lo[0] - 1.0).floor().max(0.0);
        let y0 = (lo[1] - 1.0).floor().max(0.0);
        let x1 = (hi[0] + 1.0).ceil().min(w - 1.0);
        let y1 = (hi[1] + 1.0).ceil().min(h - 1.0);
        if !(x0 <= x1 && y0 <= y1) {
            return None;
        }
        Some(Prim {
            bbox: [x0 as u16, y0 as u16, x1 as u16, y1 as u16],
            ..full
        })
    }
}

/// Clip coordinates of every mesh vertex of every object (empty for analytic shapes).
fn clip_vertices(prep: &Prepared<'_>, proj: &Projector) -> Vec<Vec<V3>> {
    prep.geom
        .iter()
        .map(|g| match g {
            Geom::Mesh(m) => m
                .world
                .par_iter()
                .with_min_len(4096)
                .map(|p| proj.clip(*p))
                .collect(),
            Geom::Analytic(_) => Vec::new(),
        })
        .collect()
}

/// Triangles per parallel setup chunk.
const SETUP_CHUNK: usize = 8192;

/// The primitives of the selected objects in scene order.
fn setup_objects(
    prep: &Prepared<'_>,
    clip: &[Vec<V3>],
    ctx: &SetupCtx<'_>,
    select: impl Fn(usize) -> bool,
) -> Vec<Prim> {
    let mut out = Vec::new();
    for (o, g) in prep.geom.iter().enumerate() {
        if !select(o) {
            continue;
        }
        match g {
            Geom::Mesh(m) => {
                let c = &clip[o];
                let tris = &m.mesh.triangles;
                let chunks: Vec<Vec<Prim>> = tris
                    .par_chunks(SETUP_CHUNK)
                    .enumerate()
                    .map(|(ci, chunk)| {
                        let mut v = Vec::with_capacity(chunk.len());
                        for (k, t) in chunk.iter().enumerate() {
                            let idx = t.map(|i| i as usize);
                            ctx.triangle(
                                idx.map(|i| c[i]),
                                idx.map(|i| m.world[i]),
                                o as u32,
                                (ci * SETUP_CHUNK + k) as u32,
                                &mut v,
                            );
                        }
                        v
                    })
                    .collect();
                out.reserve(chunks.iter().map(Vec::len).sum());
                for c in chunks {
                    out.extend(c);
                }
            }
            Geom::Analytic(a) => out.extend(ctx.impostor(a, o as u32)),
        }
    }
    out
}

/// The tile grid of an image.
#[derive(Debug, Clone, Copy)]
struct Tiles {
    nx: usize,
    ny: usize,
    width: usize,
    height: usize,
}

impl Tiles {
    fn new(width: usize, height: usize) -> Tiles {
        Tiles {
            nx: width.div_ceil(TILE),
            ny: height.div_ceil(TILE),
            width,
            height,
        }
    }
    fn count(&self) -> usize {
        self.nx * self.ny
    }
    /// Pixel rectangle `[x0, y0, x1, y1)` of tile `i`.
    fn rect(&self, i: usize) -> [usize; 4] {
        let (x0, y0) = ((i % self.nx) * TILE, (i / self.nx) * TILE);
        [
            x0,
            y0,
            (x0 + TILE).min(self.width),
            (y0 + TILE).min(self.height),
        ]
    }
}

/// Primitives per parallel binning chunk.
const BIN_CHUNK: usize = 65_536;

/// Per tile, the indices (plus `base`) of the primitives whose box overlaps it, in order.
fn bin(prims: &[Prim], tiles: &Tiles, base: u32) -> Vec<Vec<u32>> {
    let parts: Vec<Vec<Vec<u32>>> = prims
        .par_chunks(BIN_CHUNK)
        .enumerate()
        .map(|(ci, chunk)| {
            let mut bins = vec![Vec::new(); tiles.count()];
            for (k, p) in chunk.iter().enumerate() {
                let idx = base + (ci * BIN_CHUNK + k) as u32;
                let [x0, y0, x1, y1] = p.bbox.map(usize::from);
                for ty in y0 / TILE..=y1 / TILE {
                    for tx in x0 / TILE..=x1 / TILE {
                        bins[ty * tiles.nx + tx].push(idx);
                    }
                }
            }
            bins
        })
        .collect();
    (0..tiles.count())
        .into_par_iter()
        .map(|t| {
            let mut v = Vec::with_capacity(parts.iter().map(|p| p[t].len()).sum());
            for p in &parts {
                v.extend_from_slice(&p[t]);
            }
            v
        })
        .collect()
}

/// Calls `f(pixel index in the tile, sample, key)` for every sample of `rect` that `prim`
/// covers: top-left fill rule for triangles, an exact ray intersection for impostors.
#[inline]
fn cover<F: FnMut(usize, usize, f64)>(
    prim: &Prim,
    rect: [usize; 4],
    pattern: &[[i64; 2]],
    proj: &Projector,
    geom: &[Geom<'_>],
    cull: Cull,
    mut f: F,
) {
    let [bx0, by0, bx1, by1] = prim.bbox.map(usize::from);
    let (x0, y0) = (bx0.max(rect[0]), by0.max(rect[1]));
    let (x1, y1) = (bx1.min(rect[2] - 1), by1.min(rect[3] - 1));
    if x0 > x1 || y0 > y1 {
        return;
    }
    if prim.tri == NONE {
        let Some(Geom::Analytic(a)) = geom.get(prim.object as usize) else {
            return;
        };
        for y in y0..=y1 {
            for x in x0..=x1 {
                let p = (y - rect[1]) * TILE + (x - rect[0]);
                for (s, o) in pattern.iter().enumerate() {
                    let (sx, sy) = (
                        x as f64 + o[0] as f64 / SUB as f64,
                        y as f64 + o[1] as f64 / SUB as f64,
                    );
                    let ray = proj.ray(sx, sy);
                    if let Some(hit) = a.first_hit(&ray, cull) {
                        f(p, s, proj.key(&ray, hit.t));
                    }
                }
            }
        }
        return;
    }
    // Edge k runs from corner k to corner k + 1: E(p) = A (px − ax) + B (py − ay) with
    // A = ay − by, B = bx − ax, positive inside. Non-top-left edges need E > 0 (bias −1).
    let mut ea = [0i64; 3];
    let mut eb = [0i64; 3];
    let mut e0 = [0i64; 3];
    for k in 0..3 {
        let a = prim.v[k].map(i64::from);
        let b = prim.v[(k + 1) % 3].map(i64::from);
        let (ca, cb) = (a[1] - b[1], b[0] - a[0]);
        let top_left = ca > 0 || (ca == 0 && cb > 0);
        ea[k] = ca;
        eb[k] = cb;
        // Value at the centre of pixel (x0, y0).
        e0[k] =
            ca * (x0 as i64 * SUB - a[0]) + cb * (y0 as i64 * SUB - a[1]) - i64::from(!top_left);
    }
    let step_x = ea.map(|a| a * SUB);
    let step_y = eb.map(|b| b * SUB);
    let [kx, ky, kc] = prim.key;
    for (s, o) in pattern.iter().enumerate() {
        let off = [0, 1, 2].map(|k| ea[k] * o[0] + eb[k] * o[1]);
        let (fx, fy) = (o[0] as f64 / SUB as f64, o[1] as f64 / SUB as f64);
        let mut row = [0, 1, 2].map(|k| e0[k] + off[k]);
        for y in y0..=y1 {
            let mut e = row;
            let base = (y - rect[1]) * TILE;
            let ky_term = ky * (y as f64 + fy) + kc;
            for x in x0..=x1 {
                if (e[0] | e[1] | e[2]) >= 0 {
                    f(base + (x - rect[0]), s, kx * (x as f64 + fx) + ky_term);
                }
                e = [e[0] + step_x[0], e[1] + step_x[1], e[2] + step_x[2]];
            }
            row = [row[0] + step_y[0], row[1] + step_y[1], row[2] + step_y[2]];
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Shadow maps.

/// World-space bounds of the scene's bounded geometry (meshes, spheres, finite planes,
/// bounded quadrics), or `None` when there is none.
fn scene_bounds(prep: &Prepared<'_>) -> Option<(V3, V3)> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let mut take = |p: &V3| {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    };
    for g in &prep.geom {
        match g {
            Geom::Mesh(m) => {
                let (a, b) = m
                    .world
                    .par_iter()
                    .with_min_len(4096)
                    .fold(
                        || ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
                        |(mut a, mut b), p| {
                            for k in 0..3 {
                                a[k] = a[k].min(p[k]);
                                b[k] = b[k].max(p[k]);
                            }
                            (a, b)
                        },
                    )
                    .reduce(
                        || ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
                        |(a, b), (c, d)| {
                            (
                                [0, 1, 2].map(|k| a[k].min(c[k])),
                                [0, 1, 2].map(|k| b[k].max(d[k])),
                            )
                        },
                    );
                if a[0] <= b[0] {
                    take(&a);
                    take(&b);
                }
            }
            Geom::Analytic(a) => {
                if let Some(c) = a.bounds() {
                    c.iter().for_each(&mut take);
                }
            }
        }
    }
    (lo[0] <= hi[0]).then_some((lo, hi))
}

/// The depth map of a directional light (Williams 1978): an orthographic view along the
/// light's direction fitted to the scene bounds, one depth (along the direction) per texel.
#[derive(Debug, Clone)]
struct ShadowMap {
    proj: Projector,
    size: usize,
    depth: Vec<f32>,
}

impl ShadowMap {
    fn build(prep: &Prepared<'_>, bounds: (V3, V3), direction: V3, size: usize) -> ShadowMap {
        let ez = normalize(direction);
        let (ex, ey) = orthonormal_basis(ez);
        let (lo, hi) = bounds;
        let mut r = [[f64::INFINITY, f64::NEG_INFINITY]; 3];
        for i in 0..8 {
            let c = [
                if i & 1 == 0 { lo[0] } else { hi[0] },
                if i & 2 == 0 { lo[1] } else { hi[1] },
                if i & 4 == 0 { lo[2] } else { hi[2] },
            ];
            for (k, axis) in [ex, ey, ez].iter().enumerate() {
                let d = dot(c, *axis);
                r[k] = [r[k][0].min(d), r[k][1].max(d)];
            }
        }
        // Square texels over the larger extent, one texel of margin on each side.
        let extent = (r[0][1] - r[0][0]).max(r[1][1] - r[1][0]).max(1e-9);
        let texel = extent / (size as f64 - 2.0).max(1.0);
        let cx = 0.5 * (r[0][0] + r[0][1]);
        let cy = 0.5 * (r[1][0] + r[1][1]);
        let half = 0.5 * (size as f64 - 1.0) * texel;
        let proj = Projector::Orthographic {
            ex,
            ey,
            ez,
            x0: cx - half,
            y0: cy - half,
            texel,
            d0: r[2][0],
            size,
        };
        let clip = clip_vertices(prep, &proj);
        let ctx = SetupCtx::new(&proj, Cull::None, 0);
        let prims = setup_objects(prep, &clip, &ctx, |_| true);
        let tiles = Tiles::new(size, size);
        let bins = bin(&prims, &tiles, 0);
        let keys: Vec<Vec<f64>> = (0..tiles.count())
            .into_par_iter()
            .map(|t| {
                let rect = tiles.rect(t);
                let mut key = vec![f64::NEG_INFINITY; TT];
                for &i in &bins[t] {
                    cover(
                        &prims[i as usize],
                        rect,
                        &PATTERN_1,
                        &proj,
                        &prep.geom,
                        Cull::None,
                        |p, _, k| {
                            if k > key[p] {
                                key[p] = k;
                            }
                        },
                    );
                }
                key
            })
            .collect();
        let mut depth = vec![f32::INFINITY; size * size];
        for (t, key) in keys.iter().enumerate() {
            let [x0, y0, x1, y1] = tiles.rect(t);
            for y in y0..y1 {
                for x in x0..x1 {
                    let k = key[(y - y0) * TILE + (x - x0)];
                    if k > f64::NEG_INFINITY {
                        depth[y * size + x] = -k as f32;
                    }
                }
            }
        }
        ShadowMap { proj, size, depth }
    }

    /// Fraction of a 3×3 percentage-closer filter (Reeves, Salesin & Cook 1987) around the
    /// point `p` with facing normal `n` that sees the light, with a slope-scaled bias of
    /// `texel · (1 + 2.2 tan θ)` (θ between `n` and the light; the kernel reaches ≈ 2.1 texels).
    /// Points outside the map are lit.
    fn lit(&self, p: V3, n: V3) -> f64 {
        let Projector::Orthographic {
            ex,
            ey,
            ez,
            x0,
            y0,
            texel,
            d0,
            ..
        } = &self.proj
        else {
            return 1.0;
        };
        let x = (dot(p, *ex) - x0) / texel;
        let y = (dot(p, *ey) - y0) / texel;
        let d = dot(p, *ez) - d0;
        let c = (-dot(n, *ez)).abs().max(1e-3);
        let tan = ((1.0 - c * c).max(0.0).sqrt() / c).min(20.0);
        let bias = texel * (1.0 + 2.2 * tan);
        let (cx, cy) = (x.round(), y.round());
        let size = self.size as f64;
        let mut lit = 0u32;
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (tx, ty) = (cx + f64::from(dx), cy + f64::from(dy));
                let seen = if tx < 0.0 || ty < 0.0 || tx >= size || ty >= size {
                    true
                } else {
                    let stored = self.depth[ty as usize * self.size + tx as usize];
                    f64::from(stored) >= d - bias
                };
                lit += u32::from(seen);
            }
        }
        f64::from(lit) / 9.0
    }
}

// ---------------------------------------------------------------------------------------------
// Lights and the environment.

// Few per scene (one per light), so the size difference does not matter.
#[allow(clippy::large_enum_variant)]
/// A light ready for shading.
#[derive(Debug, Clone)]
enum DirectLight {
    Point {
        position: V3,
        intensity: V3,
    },
    Directional {
        to_light: V3,
        irradiance: V3,
        shadow: Option<ShadowMap>,
    },
    /// An area light approximated by a point at its centre with intensity
    /// `radiance · area · cos θ_light` (one-sided).
    Area {
        centre: V3,
        normal: V3,
        area: f64,
        radiance: V3,
    },
}

impl DirectLight {
    /// Unit direction to the light and irradiance on a surface facing it, at `p`.
    #[inline]
    fn incident(&self, p: V3) -> Option<(V3, V3)> {
        match self {
            DirectLight::Point {
                position,
                intensity,
            } => {
                let d = sub(*position, p);
                let r2 = dot(d, d);
                (r2 > 0.0).then(|| (mul(d, 1.0 / r2.sqrt()), mul(*intensity, 1.0 / r2)))
            }
            DirectLight::Directional {
                to_light,
                irradiance,
                ..
            } => Some((*to_light, *irradiance)),
            DirectLight::Area {
                centre,
                normal,
                area,
                radiance,
            } => {
                let d = sub(*centre, p);
                let r2 = dot(d, d);
                if r2 <= 0.0 {
                    return None;
                }
                let l = mul(d, 1.0 / r2.sqrt());
                let cos_light = -dot(*normal, l);
                (cos_light > 0.0).then(|| (l, mul(*radiance, area * cos_light / r2)))
            }
        }
    }

    #[inline]
    fn lit(&self, p: V3, n: V3) -> f64 {
        match self {
            DirectLight::Directional {
                shadow: Some(m), ..
            } => m.lit(p, n),
            _ => 1.0,
        }
    }
}

/// Six cube faces of an environment's radiance with a box-filtered mip chain (Greene 1986).
#[derive(Debug, Clone)]
struct CubeMap {
    /// Per level: side, then 6 faces × side² texels (+x, −x, +y, −y, +z, −z; OpenGL layout).
    levels: Vec<(usize, Vec<V3>)>,
}

/// Direction through face `f` at face coordinates `s, t ∈ [−1, 1]` (OpenGL cube layout).
fn cube_direction(f: usize, s: f64, t: f64) -> V3 {
    match f {
        0 => [1.0, -t, -s],
        1 => [-1.0, -t, s],
        2 => [s, 1.0, t],
        3 => [s, -1.0, -t],
        4 => [s, -t, 1.0],
        _ => [-s, -t, -1.0],
    }
}

/// Face and face coordinates in `[0, 1]` of a direction.
fn cube_face(d: V3) -> (usize, f64, f64) {
    let a = d.map(f64::abs);
    let (f, ma, sc, tc) = if a[0] >= a[1] && a[0] >= a[2] {
        if d[0] > 0.0 {
            (0, a[0], -d[2], -d[1])
        } else {
            (1, a[0], d[2], -d[1])
        }
    } else if a[1] >= a[2] {
        if d[1] > 0.0 {
            (2, a[1], d[0], d[2])
        } else {
            (3, a[1], d[0], -d[2])
        }
    } else if d[2] > 0.0 {
        (4, a[2], d[0], -d[1])
    } else {
        (5, a[2], -d[0], -d[1])
    };
    if ma == 0.0 {
        return (4, 0.5, 0.5);
    }
    (f, 0.5 * (sc / ma + 1.0), 0.5 * (tc / ma + 1.0))
}

impl CubeMap {
    fn build(size: usize, radiance: impl Fn(V3) -> V3 + Sync) -> CubeMap {
        let n = size;
        let base: Vec<V3> = (0..6 * n * n)
            .into_par_iter()
            .map(|i| {
                let f = i / (n * n);
                let (j, k) = ((i % (n * n)) / n, i % n);
                let s = 2.0 * (k as f64 + 0.5) / n as f64 - 1.0;
                let t = 2.0 * (j as f64 + 0.5) / n as f64 - 1.0;
                radiance(normalize(cube_direction(f, s, t)))
            })
            .collect();
        let mut levels = vec![(n, base)];
        while let Some((m, prev)) = levels.last().filter(|(m, _)| *m > 1) {
            let h = m / 2;
            let mut next = vec![[0.0; 3]; 6 * h * h];
            for f in 0..6 {
                for j in 0..h {
                    for k in 0..h {
                        let at = |jj: usize, kk: usize| prev[f * m * m + jj * m + kk];
                        let sum = add(
                            add(at(2 * j, 2 * k), at(2 * j, 2 * k + 1)),
                            add(at(2 * j + 1, 2 * k), at(2 * j + 1, 2 * k + 1)),
                        );
                        next[f * h * h + j * h + k] = mul(sum, 0.25);
                    }
                }
            }
            levels.push((h, next));
        }
        CubeMap { levels }
    }

    /// Solid-angle weighted mean of level 0 (texel solid angle ∝ (1 + s² + t²)^(−3/2)).
    fn mean(&self) -> V3 {
        let (n, texels) = &self.levels[0];
        let mut acc = [0.0; 3];
        let mut wsum = 0.0;
        for (i, c) in texels.iter().enumerate() {
            let (j, k) = ((i % (n * n)) / n, i % n);
            let s = 2.0 * (k as f64 + 0.5) / *n as f64 - 1.0;
            let t = 2.0 * (j as f64 + 0.5) / *n as f64 - 1.0;
            let w = (1.0 + s * s + t * t).powf(-1.5);
            acc = add(acc, mul(*c, w));
            wsum += w;
        }
        mul(acc, 1.0 / wsum)
    }

    fn bilinear(&self, level: usize, f: usize, s: f64, t: f64) -> V3 {
        let (n, texels) = &self.levels[level.min(self.levels.len() - 1)];
        let n = *n;
        let x = (s * n as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let y = (t * n as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(n - 1), (y0 + 1).min(n - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let at = |j: usize, k: usize| texels[f * n * n + j * n + k];
        let top = add(mul(at(y0, x0), 1.0 - fx), mul(at(y0, x1), fx));
        let bottom = add(mul(at(y1, x0), 1.0 - fx), mul(at(y1, x1), fx));
        add(mul(top, 1.0 - fy), mul(bottom, fy))
    }

    /// Radiance along `d`, blurred by `roughness ∈ [0, 1]` (level `roughness · (levels − 1)`,
    /// trilinear).
    fn sample(&self, d: V3, roughness: f64) -> V3 {
        let (f, s, t) = cube_face(d);
        let lod = roughness.clamp(0.0, 1.0) * (self.levels.len() - 1) as f64;
        let l0 = lod.floor() as usize;
        let w = lod - l0 as f64;
        let a = self.bilinear(l0, f, s, t);
        if w == 0.0 {
            return a;
        }
        add(mul(a, 1.0 - w), mul(self.bilinear(l0 + 1, f, s, t), w))
    }
}

/// The environment lights summed: their mean radiance (ambient) and, when any has a map, a
/// cube map of the total for reflections.
#[derive(Debug, Clone)]
struct Environment {
    mean: V3,
    cube: Option<CubeMap>,
}

impl Environment {
    fn new(scene: &Scene) -> Result<Environment, String> {
        let mut constant = [0.0; 3];
        let mut maps = Vec::new();
        for l in &scene.lights {
            if let Light::Environment { radiance, map } = l {
                match map {
                    Some(t) => maps.push((f3(*radiance), TextureSampler::new(t)?, t.image.width())),
                    None => constant = add(constant, f3(*radiance)),
                }
            }
        }
        if maps.is_empty() {
            return Ok(Environment {
                mean: constant,
                cube: None,
            });
        }
        let widest = maps.iter().map(|m| m.2).max().unwrap_or(32);
        let size = (widest / 4).clamp(8, 128).next_power_of_two().min(128);
        let cube = CubeMap::build(size, |d| {
            let mut r = constant;
            for (radiance, sampler, _) in &maps {
                let c = sampler.sample_direction(d);
                r = add(r, hadamard(*radiance, [c[0], c[1], c[2]].map(f64::from)));
            }
            r
        });
        Ok(Environment {
            mean: cube.mean(),
            cube: Some(cube),
        })
    }

    fn radiance(&self, d: V3, roughness: f64) -> V3 {
        match &self.cube {
            Some(c) => c.sample(d, roughness),
            None => self.mean,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Shading.

/// A material's textures, converted once.
struct MaterialTextures {
    albedo: Option<TextureSampler>,
    normal: Option<TextureSampler>,
    roughness: Option<TextureSampler>,
    metalness: Option<TextureSampler>,
    emission: Option<TextureSampler>,
}

impl MaterialTextures {
    fn new(m: &Material) -> Result<MaterialTextures, String> {
        let s = |t: &Option<ocellus_engine::value::Texture>, what: &str| {
            t.as_ref()
                .map(TextureSampler::new)
                .transpose()
                .map_err(|e| format!("material `{}`: {what} texture: {e}", m.name))
        };
        Ok(MaterialTextures {
            albedo: s(&m.albedo_texture, "albedo")?,
            normal: s(&m.normal_texture, "normal")?,
            roughness: s(&m.roughness_texture, "roughness")?,
            metalness: s(&m.metalness_texture, "metalness")?,
            emission: s(&m.emission_texture, "emission")?,
        })
    }
}

/// Vertex data for Gouraud shading.
#[derive(Debug, Clone, Copy)]
struct Corners {
    p: [V3; 3],
    n: [V3; 3],
    /// Perspective-correct barycentrics of the shading point.
    b: [f64; 3],
}

/// The visible surface at one shading point.
#[derive(Debug, Clone, Copy)]
struct Surface {
    object: usize,
    p: V3,
    /// Distance from the eye along the unit pixel ray.
    t: f64,
    /// Unit vector to the eye.
    v: V3,
    /// Geometric normal, facing the eye.
    ng: V3,
    /// Interpolated (shading) normal, on the eye's side with `ng`.
    ns: V3,
    uv: [f64; 2],
    duv_dx: [f64; 2],
    duv_dy: [f64; 2],
    /// Interpolated vertex colour (1 without).
    color: V3,
    dpdu: V3,
    dpdv: V3,
    corners: Option<Corners>,
}

/// Normal mapping in tangent space: `n' = normalize(x·T + y·B + z·N)` with `(x, y, z) =
/// 2·rgb − 1`, `T` the Gram–Schmidt orthogonalization of `∂P/∂u` against the interpolated `N`
/// and `B = ±N × T` with the handedness of `∂P/∂v` (Lengyel 2001; Mikkelsen 2008).
fn perturb_normal(n: V3, dpdu: V3, dpdv: V3, rgb: [f32; 4]) -> V3 {
    let m = [0, 1, 2].map(|k| 2.0 * f64::from(rgb[k]) - 1.0);
    let mut t = normalize(sub(dpdu, mul(n, dot(n, dpdu))));
    if t == [0.0; 3] {
        t = orthonormal_basis(n).0;
    }
    let mut b = cross(n, t);
    if dot(b, dpdv) < 0.0 {
        b = mul(b, -1.0);
    }
    let out = normalize(add(add(mul(t, m[0]), mul(b, m[1])), mul(n, m[2])));
    if out == [0.0; 3] { n } else { out }
}

/// Blinn–Phong specular lobe `specular · (s + 8)/(8π) · (n·h)^s` (Blinn 1977, energy
/// normalized).
#[inline]
fn blinn_phong_lobe(n: V3, l: V3, v: V3, specular: f64, s: f64) -> f64 {
    if specular == 0.0 {
        return 0.0;
    }
    let h = normalize(add(l, v));
    specular * (s + 8.0) / (8.0 * PI) * dot(n, h).max(0.0).powf(s)
}

/// Schlick–GGX metallic–roughness BRDF (Walter et al. 2007; Karis 2013): Lambert
/// `(1 − m)·albedo/π` plus `D·G·F / (4 (n·l)(n·v))` with `α = roughness²` (at least 10⁻³),
/// Smith–Schlick `k = (roughness + 1)²/8` and `F0 = 0.04 (1 − m) + albedo·m`.
fn pbr_brdf(n: V3, l: V3, v: V3, albedo: V3, roughness: f64, metal: f64) -> V3 {
    let h = normalize(add(l, v));
    let nl = dot(n, l).max(1e-6);
    let nv = dot(n, v).max(1e-4);
    let nh = dot(n, h).max(0.0);
    let vh = dot(v, h).max(0.0);
    let a = (roughness * roughness).max(1e-3);
    let a2 = a * a;
    let dd = nh * nh * (a2 - 1.0) + 1.0;
    let d = a2 / (PI * dd * dd);
    let k = (roughness + 1.0) * (roughness + 1.0) / 8.0;
    let g = nl / (nl * (1.0 - k) + k) * nv / (nv * (1.0 - k) + k);
    let fw = (1.0 - vh).powi(5);
    let spec = d * g / (4.0 * nl * nv);
    [0, 1, 2].map(|c| {
        let f0 = 0.04 * (1.0 - metal) + albedo[c] * metal;
        let f = f0 + (1.0 - f0) * fw;
        (1.0 - metal) * albedo[c] / PI + spec * f
    })
}

/// Karis's analytic fit of the split-sum environment BRDF ("Physically based shading on
/// mobile", 2014): the scale and bias applied to `F0`.
fn env_brdf(roughness: f64, nv: f64) -> (f64, f64) {
    let c0 = [-1.0, -0.0275, -0.572, 0.022];
    let c1 = [1.0, 0.0425, 1.04, -0.04];
    let r = [0, 1, 2, 3].map(|i| roughness * c0[i] + c1[i]);
    let a004 = (r[0] * r[0]).min((-9.28 * nv).exp2()) * r[0] + r[1];
    (-1.04 * a004 + r[2], 1.04 * a004 + r[3])
}

/// Everything the tiles of one render read.
struct Renderer<'a> {
    scene: &'a Scene,
    view: &'a View,
    proj: Projector,
    prep: &'a Prepared<'a>,
    clip: Vec<Vec<V3>>,
    prims: Vec<Prim>,
    textures: &'a [MaterialTextures],
    lights: &'a [DirectLight],
    env: &'a Environment,
    cull: Cull,
    pattern: &'static [[i64; 2]],
    background: V3,
}

/// One tile's results, `TILE`-strided.
struct TileOut {
    color: Vec<[f32; 3]>,
    depth: Vec<f32>,
    normal: Vec<[f32; 3]>,
    id: Vec<f32>,
    hits: usize,
}

impl Renderer<'_> {
    fn surface(&self, prim: &Prim, x: f64, y: f64) -> Option<Surface> {
        let object = prim.object as usize;
        match self.prep.geom.get(object)? {
            Geom::Mesh(m) => self.triangle_surface(m, object, prim.tri as usize, x, y),
            Geom::Analytic(a) => self.impostor_surface(a, object, x, y),
        }
    }

    fn triangle_surface(
        &self,
        m: &MeshGeom<'_>,
        object: usize,
        tri: usize,
        x: f64,
        y: f64,
    ) -> Option<Surface> {
        let idx = m.mesh.triangles.get(tri)?.map(|i| i as usize);
        let clip = &self.clip[object];
        let minv = inverse_of_columns(&idx.map(|i| clip[i]))?;
        let k = [0, 1, 2].map(|i| minv[i][0] * x + minv[i][1] * y + minv[i][2]);
        let s = k[0] + k[1] + k[2];
        if !(s > 0.0 && s.is_finite()) {
            return None;
        }
        let b = k.map(|v| v / s);
        let (sx, sy) = (
            minv[0][0] + minv[1][0] + minv[2][0],
            minv[0][1] + minv[1][1] + minv[2][1],
        );
        let dbx = [0, 1, 2].map(|i| (minv[i][0] - b[i] * sx) / s);
        let dby = [0, 1, 2].map(|i| (minv[i][1] - b[i] * sy) / s);
        let pw = idx.map(|i| m.world[i]);
        let lerp3 =
            |a: [V3; 3], w: [f64; 3]| add(add(mul(a[0], w[0]), mul(a[1], w[1])), mul(a[2], w[2]));
        let p = lerp3(pw, b);
        let t = norm(self.view.camera_direction(x, y)) / s;
        let v = normalize(sub(self.view.eye, p));
        let mut ng = normalize(cross(sub(pw[1], pw[0]), sub(pw[2], pw[0])));
        let flip = dot(ng, v) < 0.0;
        if flip {
            ng = mul(ng, -1.0);
        }
        let vn = m
            .normals
            .as_ref()
            .map(|ns| idx.map(|i| if flip { mul(ns[i], -1.0) } else { ns[i] }));
        let ns = vn
            .map(|n| normalize(lerp3(n, b)))
            .filter(|n| *n != [0.0; 3])
            .unwrap_or(ng);
        let (mut uv, mut duv_dx, mut duv_dy) = ([0.0; 2], [0.0; 2], [0.0; 2]);
        let (mut dpdu, mut dpdv) = orthonormal_basis(ns);
        if let Some(uvs) = &m.mesh.uvs {
            let u = idx.map(|i| uvs[i].map(f64::from));
            for c in 0..2 {
                uv[c] = b[0] * u[0][c] + b[1] * u[1][c] + b[2] * u[2][c];
                duv_dx[c] = dbx[0] * u[0][c] + dbx[1] * u[1][c] + dbx[2] * u[2][c];
                duv_dy[c] = dby[0] * u[0][c] + dby[1] * u[1][c] + dby[2] * u[2][c];
            }
            let (e1, e2) = (sub(pw[1], pw[0]), sub(pw[2], pw[0]));
            let (d1, d2) = (
                [u[1][0] - u[0][0], u[1][1] - u[0][1]],
                [u[2][0] - u[0][0], u[2][1] - u[0][1]],
            );
            let det = d1[0] * d2[1] - d2[0] * d1[1];
            if det != 0.0 && det.is_finite() {
                dpdu = mul(sub(mul(e1, d2[1]), mul(e2, d1[1])), 1.0 / det);
                dpdv = mul(sub(mul(e2, d1[0]), mul(e1, d2[0])), 1.0 / det);
            }
        }
        let color = match &m.mesh.colors {
            Some(cs) => lerp3(idx.map(|i| f3(cs[i])), b),
            None => [1.0; 3],
        };
        Some(Surface {
            object,
            p,
            t,
            v,
            ng,
            ns,
            uv,
            duv_dx,
            duv_dy,
            color,
            dpdu,
            dpdv,
            corners: Some(Corners {
                p: pw,
                n: vn.unwrap_or([ng; 3]),
                b,
            }),
        })
    }

    fn impostor_surface(&self, a: &Analytic, object: usize, x: f64, y: f64) -> Option<Surface> {
        let ray = self.proj.ray(x, y);
        let hit = a.first_hit(&ray, self.cull)?;
        let p = add(ray.origin, mul(ray.dir, hit.t));
        let n = if dot(hit.n, ray.dir) > 0.0 {
            mul(hit.n, -1.0)
        } else {
            hit.n
        };
        let uv = a.uv(p);
        // Ray differentials (Igehy 1999): the neighbouring pixels' rays meet the tangent plane.
        let diff = |dx: f64, dy: f64| -> [f64; 2] {
            let r = self.proj.ray(x + dx, y + dy);
            let den = dot(r.dir, n);
            if den == 0.0 {
                return [0.0; 2];
            }
            let q = add(r.origin, mul(r.dir, dot(sub(p, r.origin), n) / den));
            let w = a.uv(q);
            let mut d = [w[0] - uv[0], w[1] - uv[1]];
            if a.wraps_u() {
                d[0] -= d[0].round();
            }
            if d.iter().all(|v| v.is_finite()) {
                d
            } else {
                [0.0; 2]
            }
        };
        let (dpdu, dpdv) = a.tangents(p, hit.n);
        Some(Surface {
            object,
            p,
            t: hit.t,
            v: mul(ray.dir, -1.0),
            ng: n,
            ns: n,
            uv,
            duv_dx: diff(1.0, 0.0),
            duv_dy: diff(0.0, 1.0),
            color: [1.0; 3],
            dpdu,
            dpdv,
            corners: None,
        })
    }

    /// Radiance towards the eye and coverage (opacity) of a surface point.
    fn shade(&self, s: &Surface) -> (V3, f64) {
        let Some(m) = self
            .scene
            .objects
            .get(s.object)
            .and_then(|o| self.scene.materials.get(o.material as usize))
        else {
            return ([0.0; 3], 1.0);
        };
        let Some(tex) = self
            .scene
            .objects
            .get(s.object)
            .and_then(|o| self.textures.get(o.material as usize))
        else {
            return ([0.0; 3], 1.0);
        };
        let uv = s.uv.map(|v| v as f32);
        let (gx, gy) = (s.duv_dx.map(|v| v as f32), s.duv_dy.map(|v| v as f32));
        let read = |t: &Option<TextureSampler>| t.as_ref().map(|t| t.sample_grad(uv, gx, gy));
        let rgb = |c: [f32; 4]| [c[0], c[1], c[2]].map(f64::from);
        let mut albedo = hadamard(f3(m.albedo), s.color);
        let mut alpha = f64::from(m.opacity);
        if let Some(c) = read(&tex.albedo) {
            albedo = hadamard(albedo, rgb(c));
            alpha *= f64::from(c[3]);
        }
        let mut out = f3(m.emission);
        if let Some(c) = read(&tex.emission) {
            out = hadamard(out, rgb(c));
        }
        if m.shading == Shading::Unlit {
            return (add(out, albedo), alpha);
        }
        let base = if m.shading == Shading::Flat {
            s.ng
        } else {
            s.ns
        };
        let n = match read(&tex.normal) {
            Some(c) => perturb_normal(base, s.dpdu, s.dpdv, c),
            None => base,
        };
        let v = s.v;
        let mut roughness = f64::from(m.roughness);
        if let Some(c) = read(&tex.roughness) {
            roughness *= f64::from(c[0]);
        }
        let roughness = roughness.clamp(0.0, 1.0);
        let mut metal = f64::from(m.metalness);
        if let Some(c) = read(&tex.metalness) {
            metal *= f64::from(c[0]);
        }
        let metal = metal.clamp(0.0, 1.0);
        let (spec, sh) = (f64::from(m.specular), f64::from(m.shininess));
        for light in self.lights {
            if let (Shading::Gouraud, Some(c)) = (m.shading, &s.corners) {
                // Lighting at the three corners (Lambert + Blinn–Phong), interpolated;
                // the shadow is looked up per pixel.
                let mut diffuse = [0.0; 3];
                let mut specular = [0.0; 3];
                for i in 0..3 {
                    let Some((l, e)) = light.incident(c.p[i]) else {
                        continue;
                    };
                    let cos = dot(c.n[i], l);
                    if cos <= 0.0 {
                        continue;
                    }
                    let vi = normalize(sub(self.view.eye, c.p[i]));
                    let w = c.b[i] * cos;
                    diffuse = add(diffuse, mul(e, w / PI));
                    specular = add(
                        specular,
                        mul(e, w * blinn_phong_lobe(c.n[i], l, vi, spec, sh)),
                    );
                }
                if diffuse == [0.0; 3] && specular == [0.0; 3] {
                    continue;
                }
                let lit = light.lit(s.p, s.ng);
                out = add(out, mul(add(hadamard(albedo, diffuse), specular), lit));
                continue;
            }
            let Some((l, e)) = light.incident(s.p) else {
                continue;
            };
            let cos = dot(n, l);
            if cos <= 0.0 {
                continue;
            }
            let lit = light.lit(s.p, s.ng);
            if lit == 0.0 {
                continue;
            }
            let f: V3 = match m.shading {
                Shading::Pbr => pbr_brdf(n, l, v, albedo, roughness, metal),
                Shading::Phong => {
                    let r = sub(mul(n, 2.0 * cos), l);
                    let lobe = if spec == 0.0 {
                        0.0
                    } else {
                        spec * (sh + 2.0) / (2.0 * PI) * dot(r, v).max(0.0).powf(sh)
                    };
                    mul(albedo, 1.0 / PI).map(|c| c + lobe)
                }
                Shading::BlinnPhong | Shading::Flat | Shading::Gouraud => {
                    let lobe = blinn_phong_lobe(n, l, v, spec, sh);
                    mul(albedo, 1.0 / PI).map(|c| c + lobe)
                }
                Shading::Lambert | Shading::Unlit => mul(albedo, 1.0 / PI),
            };
            out = add(out, mul(hadamard(f, e), cos * lit));
        }
        if self.env.mean != [0.0; 3] || self.env.cube.is_some() {
            if m.shading == Shading::Pbr {
                out = add(out, mul(hadamard(albedo, self.env.mean), 1.0 - metal));
                let nv = dot(n, v).max(1e-4);
                let r = sub(mul(n, 2.0 * dot(n, v)), v);
                let (sa, sb) = env_brdf(roughness, nv);
                let li = self.env.radiance(r, roughness);
                let refl = [0, 1, 2].map(|c| {
                    let f0 = 0.04 * (1.0 - metal) + albedo[c] * metal;
                    li[c] * (f0 * sa + sb)
                });
                out = add(out, refl);
            } else {
                out = add(out, hadamard(albedo, self.env.mean));
            }
        }
        (out, alpha)
    }

    fn sample_position(&self, x: usize, y: usize, s: usize) -> (f64, f64) {
        let o = self.pattern[s];
        (
            x as f64 + o[0] as f64 / SUB as f64,
            y as f64 + o[1] as f64 / SUB as f64,
        )
    }

    fn render_tile(&self, rect: [usize; 4], opaque: &[u32], transparent: &[u32]) -> TileOut {
        let ns = self.pattern.len();
        let colour_samples: &[usize] = if ns == 1 { &[0] } else { &[1, 2, 3, 4] };
        let nc = colour_samples.len();
        let mut key = vec![f64::NEG_INFINITY; TT * ns];
        let mut id = vec![NONE; TT * ns];
        for &pi in opaque {
            cover(
                &self.prims[pi as usize],
                rect,
                self.pattern,
                &self.proj,
                &self.prep.geom,
                self.cull,
                |p, s, k| {
                    let i = p * ns + s;
                    if k > key[i] {
                        key[i] = k;
                        id[i] = pi;
                    }
                },
            );
        }
        let mut out = TileOut {
            color: vec![[0.0; 3]; TT],
            depth: vec![f32::INFINITY; TT],
            normal: vec![[0.0; 3]; TT],
            id: vec![-1.0; TT],
            hits: 0,
        };
        let mut gkey = vec![f64::NEG_INFINITY; TT];
        let mut col = vec![[0.0f64; 3]; TT * nc];
        let g_write = |out: &mut TileOut, p: usize, s: &Surface| {
            out.depth[p] = s.t as f32;
            out.normal[p] = s.ns.map(|v| v as f32);
            out.id[p] = s.object as f32;
        };
        for y in rect[1]..rect[3] {
            for x in rect[0]..rect[2] {
                let p = (y - rect[1]) * TILE + (x - rect[0]);
                let cid = id[p * ns];
                let centre = if cid == NONE {
                    None
                } else {
                    self.surface(&self.prims[cid as usize], x as f64, y as f64)
                };
                if let Some(s) = &centre {
                    gkey[p] = key[p * ns];
                    g_write(&mut out, p, s);
                }
                let mut shaded: [(u32, V3); 4] = [(NONE, [0.0; 3]); 4];
                let mut n_shaded = 0;
                for (j, &cs) in colour_samples.iter().enumerate() {
                    let pid = id[p * ns + cs];
                    let c = if pid == NONE {
                        self.background
                    } else if let Some(&(_, c)) = shaded[..n_shaded].iter().find(|e| e.0 == pid) {
                        c
                    } else {
                        let surf = if pid == cid {
                            centre
                        } else {
                            let (sx, sy) = self.sample_position(x, y, cs);
                            self.surface(&self.prims[pid as usize], sx, sy)
                        };
                        let c = surf.map_or(self.background, |s| self.shade(&s).0);
                        shaded[n_shaded] = (pid, c);
                        n_shaded += 1;
                        c
                    };
                    col[p * nc + j] = c;
                }
            }
        }
        if !transparent.is_empty() {
            let mut mask = vec![0u8; TT];
            let mut tkey = vec![f64::NEG_INFINITY; TT];
            let mut touched: Vec<usize> = Vec::new();
            for &pi in transparent {
                let prim = &self.prims[pi as usize];
                touched.clear();
                cover(
                    prim,
                    rect,
                    self.pattern,
                    &self.proj,
                    &self.prep.geom,
                    self.cull,
                    |p, s, k| {
                        if k > key[p * ns + s] {
                            if mask[p] == 0 {
                                touched.push(p);
                            }
                            mask[p] |= 1 << s;
                            if s == 0 {
                                tkey[p] = k;
                            }
                        }
                    },
                );
                for &p in &touched {
                    let m = mask[p];
                    mask[p] = 0;
                    let (x, y) = (rect[0] + p % TILE, rect[1] + p / TILE);
                    let centre_hit = m & 1 != 0;
                    let bits = if ns == 1 { m & 1 } else { m >> 1 };
                    let at = if centre_hit {
                        (x as f64, y as f64)
                    } else if bits != 0 {
                        self.sample_position(x, y, colour_samples[bits.trailing_zeros() as usize])
                    } else {
                        continue;
                    };
                    let Some(surf) = self.surface(prim, at.0, at.1) else {
                        continue;
                    };
                    let (c, alpha) = self.shade(&surf);
                    for j in 0..nc {
                        if bits & (1 << j) != 0 {
                            let d = &mut col[p * nc + j];
                            *d = add(mul(c, alpha), mul(*d, 1.0 - alpha));
                        }
                    }
                    if centre_hit && tkey[p] > gkey[p] {
                        gkey[p] = tkey[p];
                        g_write(&mut out, p, &surf);
                    }
                }
            }
        }
        for y in rect[1]..rect[3] {
            for x in rect[0]..rect[2] {
                let p = (y - rect[1]) * TILE + (x - rect[0]);
                let mut sum = [0.0; 3];
                for j in 0..nc {
                    sum = add(sum, col[p * nc + j]);
                }
                out.color[p] = mul(sum, 1.0 / nc as f64).map(|v| v as f32);
                out.hits += usize::from(gkey[p] > f64::NEG_INFINITY);
            }
        }
        out
    }
}

/// Depth along the view direction of a primitive's centroid (for sorting transparent ones).
fn centroid_depth(prim: &Prim, prep: &Prepared<'_>, view: &View) -> f64 {
    let z = |p: V3| view.to_camera(p)[2];
    match prep.geom.get(prim.object as usize) {
        Some(Geom::Mesh(m)) => m.mesh.triangles.get(prim.tri as usize).map_or(0.0, |t| {
            t.iter().map(|&i| z(m.world[i as usize])).sum::<f64>() / 3.0
        }),
        Some(Geom::Analytic(a)) => match (a.bounds(), a) {
            (Some(c), _) => c.iter().map(|&p| z(p)).sum::<f64>() / 8.0,
            (None, Analytic::Plane { point, .. }) => z(*point),
            (None, Analytic::Quadric { translation, .. }) => z(*translation),
            (None, Analytic::Sphere { center, .. }) => z(*center),
        },
        None => 0.0,
    }
}

/// Renders scene camera `camera` of `scene`. See [`rasterize_view`].
pub fn rasterize(
    scene: &Scene,
    camera: usize,
    options: &RasterOptions,
) -> Result<RasterOutput, String> {
    let c = scene.cameras.get(camera).ok_or_else(|| {
        format!(
            "camera index {camera} is out of range: the scene has {} camera(s)",
            scene.cameras.len()
        )
    })?;
    let view = View::new(c)?;
    rasterize_view(scene, &view, options)
}

/// Rasterizes `scene` as seen by `view` (see the module documentation for the pipeline).
///
/// The image is a pinhole image: a thin-lens camera's aperture is not simulated (no depth of
/// field). Errors: invalid options, non-finite vertices or parameters, triangle indices past
/// the vertices, mismatched attribute arrays, a material index past `scene.materials`, or a
/// texture the sampler refuses.
pub fn rasterize_view(
    scene: &Scene,
    view: &View,
    options: &RasterOptions,
) -> Result<RasterOutput, String> {
    SceneRaster::new(scene, options)?.render(view)
}

/// What rasterizing a scene needs whatever the view (validated scene, flattened geometry,
/// converted textures and their mipmaps, lights with their shadow maps, the environment),
/// built once so that several views of one scene share it: [`SceneRaster::render`] equals
/// [`rasterize_view`] with the same scene and options.
pub struct SceneRaster<'a> {
    scene: &'a Scene,
    options: RasterOptions,
    prep: Prepared<'a>,
    textures: Vec<MaterialTextures>,
    lights: Vec<DirectLight>,
    env: Environment,
}

impl<'a> SceneRaster<'a> {
    /// Validates `options` and `scene` and prepares everything view-independent (errors as
    /// [`rasterize_view`]'s).
    pub fn new(scene: &'a Scene, options: &RasterOptions) -> Result<SceneRaster<'a>, String> {
        options.validate()?;
        validate_scene(scene)?;
        let prep = prepare(scene);
        let textures = scene
            .materials
            .iter()
            .map(MaterialTextures::new)
            .collect::<Result<Vec<_>, _>>()?;
        let bounds = if options.shadow_map_size > 0 {
            scene_bounds(&prep)
        } else {
            None
        };
        let lights: Vec<DirectLight> = scene
            .lights
            .iter()
            .filter_map(|l| match l {
                Light::Point {
                    position,
                    intensity,
                } => Some(DirectLight::Point {
                    position: *position,
                    intensity: f3(*intensity),
                }),
                Light::Directional {
                    direction,
                    irradiance,
                } => Some(DirectLight::Directional {
                    to_light: mul(normalize(*direction), -1.0),
                    irradiance: f3(*irradiance),
                    shadow: bounds.map(|b| {
                        ShadowMap::build(&prep, b, *direction, options.shadow_map_size as usize)
                    }),
                }),
                Light::Area {
                    corner,
                    edge_u,
                    edge_v,
                    radiance,
                } => {
                    let n = cross(*edge_u, *edge_v);
                    Some(DirectLight::Area {
                        centre: add(*corner, mul(add(*edge_u, *edge_v), 0.5)),
                        normal: normalize(n),
                        area: norm(n),
                        radiance: f3(*radiance),
                    })
                }
                Light::Environment { .. } => None,
            })
            .collect();
        let env = Environment::new(scene)?;
        Ok(SceneRaster {
            scene,
            options: options.clone(),
            prep,
            textures,
            lights,
            env,
        })
    }

    /// Rasterizes the prepared scene as seen by `view`.
    pub fn render(&self, view: &View) -> Result<RasterOutput, String> {
        let (scene, options, prep) = (self.scene, &self.options, &self.prep);
        let proj = Projector::Perspective {
            view: view.clone(),
            near: options.near,
        };
        let clip = clip_vertices(prep, &proj);
        let pattern = options.pattern();
        let reach = if options.samples == 4 { 96 } else { 0 };
        let ctx = SetupCtx::new(&proj, options.cull, reach);
        let mut prims = setup_objects(prep, &clip, &ctx, |o| prep.opaque[o]);
        let n_opaque = prims.len();
        let mut transparent: Vec<(f64, Prim)> =
            setup_objects(prep, &clip, &ctx, |o| !prep.opaque[o])
                .into_iter()
                .map(|p| (centroid_depth(&p, prep, view), p))
                .collect();
        // Back to front; the sort is stable, so equal depths keep scene order.
        transparent.sort_by(|a, b| b.0.total_cmp(&a.0));
        prims.extend(transparent.into_iter().map(|(_, p)| p));
        let tiles = Tiles::new(view.width, view.height);
        let opaque_bins = bin(&prims[..n_opaque], &tiles, 0);
        let transparent_bins = bin(&prims[n_opaque..], &tiles, n_opaque as u32);
        let renderer = Renderer {
            scene,
            view,
            proj,
            prep,
            clip,
            prims,
            textures: &self.textures,
            lights: &self.lights,
            env: &self.env,
            cull: options.cull,
            pattern,
            background: f3(options.background),
        };
        let outs: Vec<TileOut> = (0..tiles.count())
            .into_par_iter()
            .map(|t| renderer.render_tile(tiles.rect(t), &opaque_bins[t], &transparent_bins[t]))
            .collect();
        let (w, h) = (view.width, view.height);
        let mut out = RasterOutput {
            width: w,
            height: h,
            color: vec![0.0; 3 * w * h],
            depth: vec![f32::INFINITY; w * h],
            normals: vec![0.0; 3 * w * h],
            ids: vec![-1.0; w * h],
            hits: 0,
        };
        for (t, o) in outs.iter().enumerate() {
            let [x0, y0, x1, y1] = tiles.rect(t);
            for y in y0..y1 {
                for x in x0..x1 {
                    let p = (y - y0) * TILE + (x - x0);
                    let q = y * w + x;
                    out.color[3 * q..3 * q + 3].copy_from_slice(&o.color[p]);
                    out.normals[3 * q..3 * q + 3].copy_from_slice(&o.normal[p]);
                    out.depth[q] = o.depth[p];
                    out.ids[q] = o.id[p];
                }
            }
            out.hits += o.hits;
        }
        Ok(out)
    }
}

/// For every pixel, how many primitives (clipped triangle pieces and impostors, opaque or
/// not, after culling) cover its centre, ignoring depth: the fill-rule check (a closed
/// watertight surface seen from outside covers each centre an even number of times; a
/// single layer exactly once).
pub fn coverage_counts(
    scene: &Scene,
    view: &View,
    options: &RasterOptions,
) -> Result<Vec<u32>, String> {
    options.validate()?;
    validate_scene(scene)?;
    let prep = prepare(scene);
    let proj = Projector::Perspective {
        view: view.clone(),
        near: options.near,
    };
    let clip = clip_vertices(&prep, &proj);
    let ctx = SetupCtx::new(&proj, options.cull, 0);
    let prims = setup_objects(&prep, &clip, &ctx, |_| true);
    let tiles = Tiles::new(view.width, view.height);
    let bins = bin(&prims, &tiles, 0);
    let counts: Vec<Vec<u32>> = (0..tiles.count())
        .into_par_iter()
        .map(|t| {
            let mut c = vec![0u32; TT];
            for &i in &bins[t] {
                cover(
                    &prims[i as usize],
                    tiles.rect(t),
                    &PATTERN_1,
                    &proj,
                    &prep.geom,
                    options.cull,
                    |p, _, _| c[p] += 1,
                );
            }
            c
        })
        .collect();
    let mut out = vec![0u32; view.width * view.height];
    for (t, c) in counts.iter().enumerate() {
        let [x0, y0, x1, y1] = tiles.rect(t);
        for y in y0..y1 {
            for x in x0..x1 {
                out[y * view.width + x] = c[(y - y0) * TILE + (x - x0)];
            }
        }
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Operator.

params! {
    /// Parameters of [`Rasterize`].
    pub struct RasterizeParams {
        /// Index into the scene's cameras. Default 0.
        camera: u32 = 0,
        /// Face culling by screen-space winding: "none", "back" or "front". Default "none".
        cull: Cull = Cull::None,
        /// Samples per pixel: 1, or 4 for rotated-grid MSAA. Default 1.
        samples: u32 = 1 => [min = 1, max = 4],
        /// Near-plane distance along the optical axis, world units (> 0). Default 0.001.
        near: f64 = 1e-3,
        /// Side of each directional light's shadow map, texels (0 disables shadows,
        /// at most 8192). Default 1024.
        shadow_map_size: u32 = 1024 => [max = 8192],
        /// Colour where no surface covers a sample, linear RGB. Default black.
        background: [f64; 3] = [0.0, 0.0, 0.0],
    }
}

/// `render.rasterize`. See [`rasterize_view`].
#[derive(Debug, Clone)]
pub struct Rasterize {
    camera: usize,
    options: RasterOptions,
}

impl Op for Rasterize {
    type Params = RasterizeParams;
    const ID: &'static str = "render.rasterize";
    const SUMMARY: &'static str = "Rasterizes a scene: z-buffered, tiled and parallel, with MSAA, \
                                   textures, shading models, shadow maps and alpha blending.";
    const DOC: &'static str = r#"
Draws `scene` from `scene.cameras[camera]` (a pinhole image; a thin lens's aperture is not
simulated) with a tiled, parallel triangle rasterizer. Mesh objects are transformed to world
(scale, then `world_from_object`) and clip space, culled by winding (`cull`: "none", "back",
"front"), clipped against the near plane `near` and a guard band (Sutherland–Hodgman in
homogeneous coordinates, crossing triangles are clipped, not dropped), snapped to 1/256 px and
scan-converted with Pineda edge functions in i64 fixed point and the top-left fill rule, so
shared edges are watertight. Spheres, planes (also infinite) and quadrics are exact per-pixel
impostors: each sample's ray is intersected analytically inside the shape's projected
bounding box and z-tested against the triangles. Triangles are binned to 64×64 tiles, which
are drawn in parallel, each in scene order; equal depths keep the earlier primitive, so the
image is the same for any thread count.

Attributes (depth, uv, normals, colours, tangents) are interpolated perspective-correctly
(Heckbert & Moreton 1991) from the triangle's 2-D homogeneous setup (Olano & Greer 1997);
texture uv derivatives come analytically from the same interpolation (ray differentials for
impostors), so trilinear and anisotropic filtering work. `samples: 4` rasterizes a rotated
grid of four samples (coverage and depth per sample) and shades each visible primitive once
per pixel (MSAA), at the pixel centre when it is the primitive visible there, else at its
first covered sample; colours are averaged.

Shading (`Material::shading`), radiance in W·sr⁻¹·m⁻² for lights given as irradiance E (W·m⁻²)
on a surface facing them: Unlit = albedo·texture (+ emission); Lambert = albedo/π·E·cosθ;
Phong = (albedo/π + specular·(s+2)/(2π)·(r·v)^s)·E·cosθ (Phong 1975); Blinn–Phong and Flat
(face normal) = (albedo/π + specular·(s+8)/(8π)·(n·h)^s)·E·cosθ (Blinn 1977); Gouraud = the
same evaluated at the vertices and interpolated (Gouraud 1971); Pbr = (1−m)·albedo/π +
GGX·Smith·Schlick (Walter et al. 2007; Karis 2013). Vertex colours multiply the albedo.
Normal maps are applied in tangent space (TBN from the triangle's uv derivatives,
Gram–Schmidt against the interpolated normal). Lights: point (E = I/r²), directional (E),
area (approximated by a point at its centre with intensity radiance·area·cosθ_light),
environment (ambient radiance·albedo, the map's solid-angle mean when it has one; Pbr
materials add a reflection looked up along the reflected view vector in a cube map built once
per render from the map (Greene 1986), blurred by roughness and weighted by Karis's analytic
split-sum fit). Emission is added. Both sides of a surface are lit (normals turned to the
viewer). Directional lights cast shadows through an orthographic shadow map of
`shadow_map_size`² texels fitted to the scene bounds (Williams 1978), filtered 3×3 PCF with
a slope-scaled bias (Reeves et al. 1987); other lights cast none. Every object casts shadows.

Materials with `opacity < 1` are drawn after all opaque primitives, back to front by
primitive centroid depth, blended "over" with alpha = opacity × albedo-texture alpha,
without writing depth. Samples no surface covers get `background` (environment lights light
surfaces; they are not drawn behind them).

Outputs: `color` (RGB f32 linear), and at each pixel centre `depth` (f32 distance along the
unit pixel ray, +inf where empty, as `render.raycast`), `normals` (RGB f32 world-space unit
normal facing the camera, 0 where empty), `ids` (f32 index into `scene.objects`, −1 where
empty) and `hits` (pixels whose centre is covered); these four include transparent surfaces.

Errors: camera index out of range, a distorted camera, non-finite vertices or parameters, bad
triangle indices, a material index past the scene's materials, `samples` other than 1 or 4.

Reference: Pineda, "A parallel algorithm for polygon rasterization" (SIGGRAPH 1988);
Sutherland & Hodgman, "Reentrant polygon clipping" (CACM 1974); Olano & Greer, "Triangle scan
conversion using 2D homogeneous coordinates" (HWWS 1997); Heckbert & Moreton, "Interpolation
for polygon texture mapping and shading" (1991); Akeley, "RealityEngine graphics" (SIGGRAPH
1993); Williams, "Casting curved shadows on curved surfaces" (SIGGRAPH 1978); Reeves, Salesin
& Cook, "Rendering antialiased shadows with depth maps" (SIGGRAPH 1987); Porter & Duff,
"Compositing digital images" (SIGGRAPH 1984).

Example:
    "frame": (op: "render.rasterize", inputs: { "scene": "scene.scene" },
              params: (camera: 0, cull: "back", samples: 4, shadow_map_size: 2048)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "scene",
            PortType::Scene,
            "Materials, objects, lights and cameras.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("color", PortType::Image, "RGB f32 linear radiance."),
            PortSpec::new(
                "depth",
                PortType::Image,
                "f32 gray: distance along the pixel centre's unit ray, +inf where empty.",
            ),
            PortSpec::new(
                "normals",
                PortType::Image,
                "RGB f32: world-space unit normal at the pixel centre, 0 where empty.",
            ),
            PortSpec::new(
                "ids",
                PortType::Image,
                "f32 gray: index of the visible object, −1 where empty.",
            ),
            PortSpec::new("hits", PortType::Integer, "Pixels whose centre is covered."),
        ]
    }

    fn new(p: RasterizeParams) -> Result<Self, String> {
        let options = RasterOptions {
            cull: p.cull,
            samples: p.samples,
            near: p.near,
            shadow_map_size: p.shadow_map_size,
            background: p.background.map(|v| v as f32),
        };
        options.validate()?;
        Ok(Rasterize {
            camera: p.camera as usize,
            options,
        })
    }
}

impl Operator for Rasterize {
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
        let r =
            rasterize(scene, self.camera, &self.options).map_err(|e| OpError::input("scene", e))?;
        let image = |channels: Channels, data: Vec<f32>| {
            Image::new(r.width, r.height, channels, PixelData::F32(data))
                .map(Value::image)
                .map_err(|e| OpError::failed(e.to_string()))
        };
        Ok(Outputs::new()
            .with("color", image(Channels::Rgb, r.color.clone())?)
            .with("depth", image(Channels::Gray, r.depth.clone())?)
            .with("normals", image(Channels::Rgb, r.normals.clone())?)
            .with("ids", image(Channels::Gray, r.ids.clone())?)
            .with("hits", Value::Integer(r.hits as i64)))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use ocellus_engine::value::{
        Camera, CameraModel, Pose, SceneCamera, SceneObject, Texture, TextureFilter, TextureWrap,
    };

    use super::*;
    use crate::render::bvh::{BvhOptions, build_bvh};
    use crate::render::primitives::bumpy_icosphere;
    use crate::render::raycast::{LookAtCamera, raycast_depth};
    use crate::render::scene::scene_camera_from_look_at;

    fn look_at(w: usize, h: usize, fov: f64, eye: V3, target: V3) -> LookAtCamera {
        LookAtCamera::new(w, h, fov, eye, target, [0.0, 1.0, 0.0]).unwrap()
    }

    fn object(shape: Shape, material: u32) -> SceneObject {
        SceneObject {
            name: "o".into(),
            shape,
            world_from_object: Pose::IDENTITY,
            scale: 1.0,
            material,
        }
    }

    fn mesh_shape(positions: Vec<[f32; 3]>, triangles: Vec<[u32; 3]>) -> Shape {
        Shape::Mesh(Arc::new(Mesh {
            positions,
            triangles,
            ..Mesh::default()
        }))
    }

    /// The quad `corner + s·a + t·b`, s, t ∈ [0, 1], as two triangles with uvs (s, t)·uv_max.
    fn quad(corner: V3, a: V3, b: V3, uv_max: f32) -> Mesh {
        let p = |s: f64, t: f64| add(corner, add(mul(a, s), mul(b, t))).map(|v| v as f32);
        Mesh {
            positions: vec![p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            normals: None,
            uvs: Some(vec![
                [0.0, 0.0],
                [uv_max, 0.0],
                [uv_max, uv_max],
                [0.0, uv_max],
            ]),
            colors: None,
            tangents: None,
        }
    }

    fn unlit(albedo: [f32; 3], opacity: f32) -> Material {
        Material {
            albedo,
            opacity,
            shading: Shading::Unlit,
            ..Material::default()
        }
    }

    fn scene(materials: Vec<Material>, objects: Vec<SceneObject>, lights: Vec<Light>) -> Scene {
        Scene {
            materials,
            objects,
            lights,
            cameras: Vec::new(),
        }
    }

    fn no_shadows() -> RasterOptions {
        RasterOptions {
            shadow_map_size: 0,
            ..RasterOptions::default()
        }
    }

    fn view_of(c: &LookAtCamera) -> View {
        View::new(&scene_camera_from_look_at(c)).unwrap()
    }

    /// Coverage and depth agreement with the BVH ray caster: (coverage %, depth % within
    /// relative 1e-4 among pixels both cover).
    fn agreement(scene: &Scene, mesh: Mesh, camera: &LookAtCamera) -> (f64, f64) {
        let bvh = build_bvh(Arc::new(mesh), &BvhOptions::default()).unwrap();
        let (rays, _) = raycast_depth(&bvh, camera);
        let r = rasterize_view(scene, &view_of(camera), &no_shadows()).unwrap();
        assert!(r.depth.iter().all(|d| !d.is_nan()));
        assert!(r.color.iter().chain(&r.normals).all(|v| v.is_finite()));
        let n = rays.len();
        let same_cover = rays
            .iter()
            .zip(&r.depth)
            .filter(|(a, b)| a.is_finite() == b.is_finite())
            .count();
        let both: Vec<(f32, f32)> = rays
            .iter()
            .zip(&r.depth)
            .filter(|(a, b)| a.is_finite() && b.is_finite())
            .map(|(a, b)| (*a, *b))
            .collect();
        let close = both
            .iter()
            .filter(|(a, b)| ((a - b) / a).abs() <= 1e-4)
            .count();
        let hits = r.depth.iter().filter(|d| d.is_finite()).count();
        assert_eq!(hits, r.hits);
        (
            100.0 * same_cover as f64 / n as f64,
            100.0 * close as f64 / both.len().max(1) as f64,
        )
    }

    #[test]
    fn agrees_with_the_ray_caster_on_a_bumpy_icosphere() {
        let mesh = bumpy_icosphere(5, 0.05, 11);
        let s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(mesh.clone())), 0)],
            vec![],
        );
        let cameras = [
            ("front", look_at(96, 72, 40.0, [0.0, 0.0, -4.0], [0.0; 3])),
            (
                "oblique",
                look_at(80, 80, 55.0, [2.5, 1.8, -2.2], [0.2, -0.1, 0.0]),
            ),
            // Inside the sphere: every view ray meets it.
            (
                "inside",
                look_at(64, 64, 120.0, [0.1, 0.2, -0.3], [1.0, 0.5, -2.0]),
            ),
        ];
        for (name, cam) in cameras {
            let (cover, depth) = agreement(&s, mesh.clone(), &cam);
            eprintln!("{name}: coverage agrees on {cover:.3} %, depth within 1e-4 on {depth:.3} %");
            assert!(cover >= 99.5 && depth >= 99.5, "{name}: {cover} {depth}");
        }
        // Close: the same mesh 50× larger (triangles ≈ 2 units across), the eye 0.3 above the
        // surface looking along it, so the triangles under the eye cross the near plane and
        // their clipped parts fill the bottom of the view.
        let mut big = mesh.clone();
        for p in &mut big.positions {
            *p = p.map(|v| v * 50.0);
        }
        let bvh = build_bvh(Arc::new(big.clone()), &BvhOptions::default()).unwrap();
        let probe = crate::render::bvh::Ray {
            origin: [0.0, 0.0, -100.0],
            direction: [0.0, 0.0, 1.0],
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        let surface_z = -100.0 + f64::from(crate::render::bvh::intersect(&bvh, &probe).unwrap().t);
        let eye = [0.0, 0.0, surface_z - 0.3];
        let cam = look_at(96, 64, 70.0, eye, add(eye, [1.0, 0.25, 0.0]));
        let s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(big.clone())), 0)],
            vec![],
        );
        let (cover, depth) = agreement(&s, big.clone(), &cam);
        eprintln!("close: coverage agrees on {cover:.3} %, depth within 1e-4 on {depth:.3} %");
        assert!(cover >= 99.5 && depth >= 99.5, "close: {cover} {depth}");
        let view = view_of(&cam);
        let z: Vec<f64> = big
            .positions
            .iter()
            .map(|p| view.to_camera(f3(*p))[2])
            .collect();
        let crossing = big
            .triangles
            .iter()
            .filter(|t| {
                let zs = t.map(|i| z[i as usize]);
                let near_eye = t
                    .iter()
                    .all(|&i| norm(sub(f3(big.positions[i as usize]), eye)) < 6.0);
                near_eye && zs.iter().any(|&v| v < 1e-3) && zs.iter().any(|&v| v > 1e-3)
            })
            .count();
        assert!(crossing >= 2, "{crossing}");
    }

    /// Nearest `t > t_min` of the unit ray `o + t d` on a sphere, written independently.
    fn sphere_t(o: V3, d: V3, c: V3, r: f64, t_min: f64) -> Option<f64> {
        let oc = sub(o, c);
        let b = dot(oc, d);
        let disc = b * b - (dot(oc, oc) - r * r);
        if disc < 0.0 {
            return None;
        }
        [-b - disc.sqrt(), -b + disc.sqrt()]
            .into_iter()
            .find(|&t| t >= t_min)
    }

    #[test]
    fn sphere_impostor_is_the_analytic_sphere() {
        // Object-space sphere at (0.2, −0.1, 0.3), r 0.8, scaled 1.5, rotated and moved.
        let pose = Pose {
            rotation: [0.9, 0.1, -0.3, 0.2],
            translation: [0.3, -0.2, 0.5],
        };
        let mut o = object(
            Shape::Sphere {
                center: [0.2, -0.1, 0.3],
                radius: 0.8,
            },
            0,
        );
        o.world_from_object = pose;
        o.scale = 1.5;
        let c = add(
            rotate(&pose.rotation_matrix(), mul([0.2, -0.1, 0.3], 1.5)),
            pose.translation,
        );
        let r = 1.2;
        let s = scene(vec![Material::default()], vec![o], vec![]);
        for (eye, fov) in [([0.5, 1.0, -5.0], 40.0), (add(c, [0.1, 0.2, -0.3]), 100.0)] {
            let cam = look_at(64, 48, fov, eye, c);
            let view = view_of(&cam);
            let out = rasterize_view(&s, &view, &no_shadows()).unwrap();
            let mut checked = 0;
            for y in 0..48 {
                for x in 0..64 {
                    let d = view.ray_direction(x as f64, y as f64);
                    let dz = view.to_camera(add(view.eye, d))[2] - view.to_camera(view.eye)[2];
                    let expect = sphere_t(view.eye, d, c, r, 1e-3 / dz);
                    let got = out.depth[y * 64 + x];
                    match expect {
                        Some(t) => {
                            assert!((f64::from(got) - t).abs() <= 1e-6 * t, "{x},{y}: {got} {t}");
                            checked += 1;
                        }
                        None => assert!(got.is_infinite(), "{x},{y}: {got}"),
                    }
                }
            }
            assert!(checked > 200, "{checked}");
            assert_eq!(out.hits, checked);
        }
    }

    fn checker_texture(filter: TextureFilter) -> Texture {
        // 2×2 checkerboard, black and white.
        let px = vec![
            0.0, 0.0, 0.0, 1.0, 1.0, 1.0, //
            1.0, 1.0, 1.0, 0.0, 0.0, 0.0,
        ];
        Texture {
            image: Arc::new(Image::from_f32(2, 2, Channels::Rgb, px).unwrap()),
            wrap: TextureWrap::Repeat,
            filter,
            border: [0.0; 4],
            max_anisotropy: 1,
            uv_scale: [1.0, 1.0],
        }
    }

    #[test]
    fn checkerboard_is_perspective_correct() {
        // Ground quad y = 0, x ∈ [−4, 4], z ∈ [0, 40], uv 0..8 (64 checkers along z), seen at
        // a grazing angle; nearest filtering, unlit white.
        let n = 8.0f32;
        let mesh = quad([-4.0, 0.0, 0.0], [8.0, 0.0, 0.0], [0.0, 0.0, 40.0], n);
        let tex = checker_texture(TextureFilter::Nearest);
        let sampler = TextureSampler::new(&tex).unwrap();
        let mut m = unlit([1.0; 3], 1.0);
        m.albedo_texture = Some(tex);
        let s = scene(
            vec![m],
            vec![object(Shape::Mesh(Arc::new(mesh.clone())), 0)],
            vec![],
        );
        let (w, h) = (128usize, 96usize);
        let cam = look_at(w, h, 60.0, [0.5, 1.0, -1.0], [0.0, 0.0, 20.0]);
        let view = view_of(&cam);
        let out = rasterize_view(&s, &view, &no_shadows()).unwrap();
        let (mut ok, mut bad, mut affine_bad, mut tested) = (0, 0, 0, 0);
        let proj: Vec<V3> = mesh
            .positions
            .iter()
            .map(|p| view.project(f3(*p)).unwrap())
            .collect();
        let uvs = mesh.uvs.clone().unwrap();
        for y in 0..h {
            for x in 0..w {
                let d = view.ray_direction(x as f64, y as f64);
                if d[1] >= 0.0 {
                    continue;
                }
                let t = -view.eye[1] / d[1];
                let p = add(view.eye, mul(d, t));
                if !(p[0].abs() < 4.0 && p[2] > 0.0 && p[2] < 40.0) {
                    continue;
                }
                let uv = [(p[0] + 4.0) / 8.0 * n as f64, p[2] / 40.0 * n as f64];
                // Skip samples within 2 % of a texel of a checker edge.
                let near_edge = uv.iter().any(|&c| {
                    let f = (2.0 * c).fract();
                    !(0.02..=0.98).contains(&f)
                });
                if near_edge {
                    continue;
                }
                tested += 1;
                let expect = sampler.sample([uv[0] as f32, uv[1] as f32])[0];
                let got = out.color[3 * (y * w + x)];
                if got == expect {
                    ok += 1;
                } else {
                    bad += 1;
                }
                // Affine (screen-space) interpolation over the triangle holding p.
                let (s_, t_) = ((p[0] + 4.0) / 8.0, p[2] / 40.0);
                let tri = if t_ <= s_ { [0, 1, 2] } else { [0, 2, 3] };
                let q = tri.map(|i| proj[i]);
                let area = (q[1][0] - q[0][0]) * (q[2][1] - q[0][1])
                    - (q[1][1] - q[0][1]) * (q[2][0] - q[0][0]);
                let lam = |a: V3, b: V3| {
                    ((b[0] - a[0]) * (y as f64 - a[1]) - (b[1] - a[1]) * (x as f64 - a[0])) / area
                };
                let l = [lam(q[1], q[2]), lam(q[2], q[0]), lam(q[0], q[1])];
                let au = (0..3)
                    .map(|k| l[k] * f64::from(uvs[tri[k]][0]))
                    .sum::<f64>();
                let av = (0..3)
                    .map(|k| l[k] * f64::from(uvs[tri[k]][1]))
                    .sum::<f64>();
                if sampler.sample([au as f32, av as f32])[0] != expect {
                    affine_bad += 1;
                }
            }
        }
        eprintln!(
            "checkerboard: {ok} of {tested} pixels match the analytic texel ({bad} differ); \
             affine interpolation would miss {affine_bad}"
        );
        assert!(tested > 3000, "{tested}");
        assert_eq!(bad, 0);
        assert!(affine_bad * 5 > tested, "affine {affine_bad} of {tested}");
    }

    /// A camera at the origin looking along +z with fx = fy = 32 and an integer principal
    /// point, so a point at depth 1 lands on pixel `(32x + cx, 32y + cy)` exactly.
    fn integer_view(w: u32, h: u32, cx: f64, cy: f64) -> View {
        View::new(&SceneCamera {
            camera: Camera {
                model: CameraModel::Pinhole,
                width: w,
                height: h,
                params: vec![32.0, 32.0, cx, cy],
            },
            camera_from_world: Pose::IDENTITY,
            aperture_radius: 0.0,
            focus_distance: 1.0,
        })
        .unwrap()
    }

    #[test]
    fn top_left_rule_draws_every_centre_exactly_once() {
        let view = integer_view(40, 36, 16.0, 16.0);
        // Pixel (px, py) at depth z.
        let at = |px: f64, py: f64, z: f64| -> [f32; 3] {
            [
                ((px - 16.0) / 32.0 * z) as f32,
                ((py - 16.0) / 32.0 * z) as f32,
                z as f32,
            ]
        };
        // Square (2, 2)–(29, 29) split along the diagonal through the centres (k, k).
        let sq = mesh_shape(
            vec![
                at(2.0, 2.0, 1.0),
                at(29.0, 2.0, 1.0),
                at(29.0, 29.0, 1.0),
                at(2.0, 29.0, 1.0),
            ],
            vec![[0, 1, 2], [0, 2, 3]],
        );
        let s = scene(vec![Material::default()], vec![object(sq, 0)], vec![]);
        let counts = coverage_counts(&s, &view, &no_shadows()).unwrap();
        for y in 0..36 {
            for x in 0..40 {
                // Left and top edges are in, right and bottom out.
                let inside = (2..29).contains(&x) && (2..29).contains(&y);
                assert_eq!(counts[y * 40 + x], u32::from(inside), "({x}, {y})");
            }
        }
        // A jittered grid of quads at random depths tiling beyond the screen, with some
        // vertices on pixel centres and some edges through them: every centre exactly once.
        let mut rng = crate::describe::brief::SplitMix64::new(5);
        let mut rand = || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let (nx, ny) = (9usize, 8usize);
        let mut positions = Vec::new();
        for j in 0..=ny {
            for i in 0..=nx {
                let (bx, by) = (i as f64 * 6.0 - 5.0, j as f64 * 6.0 - 5.0);
                // Every third vertex exactly on a pixel centre (depth 2 keeps it exact).
                if (i + j) % 3 == 0 {
                    positions.push(at(bx, by, 2.0));
                } else {
                    let (px, py) = (bx + 2.0 * rand() - 1.0, by + 2.0 * rand() - 1.0);
                    positions.push(at(px, py, 1.0 + 2.0 * rand()));
                }
            }
        }
        let mut triangles = Vec::new();
        for j in 0..ny as u32 {
            for i in 0..nx as u32 {
                let v = |a: u32, b: u32| (j + b) * (nx as u32 + 1) + i + a;
                if (i + j) % 2 == 0 {
                    triangles.extend([[v(0, 0), v(1, 0), v(1, 1)], [v(0, 0), v(1, 1), v(0, 1)]]);
                } else {
                    triangles.extend([[v(0, 0), v(1, 0), v(0, 1)], [v(1, 0), v(1, 1), v(0, 1)]]);
                }
            }
        }
        let s = scene(
            vec![Material::default()],
            vec![object(mesh_shape(positions, triangles), 0)],
            vec![],
        );
        let counts = coverage_counts(&s, &view, &no_shadows()).unwrap();
        let wrong: Vec<usize> = (0..counts.len()).filter(|&i| counts[i] != 1).collect();
        assert!(wrong.is_empty(), "pixels not drawn once: {wrong:?}");
        // A closed surface from outside: every centre is covered an even number of times.
        let ico = bumpy_icosphere(3, 0.05, 2);
        let s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(ico)), 0)],
            vec![],
        );
        let cam = look_at(64, 64, 50.0, [0.3, 0.2, -3.0], [0.0; 3]);
        let counts = coverage_counts(&s, &view_of(&cam), &no_shadows()).unwrap();
        assert!(counts.iter().all(|c| c % 2 == 0));
        assert!(counts.iter().filter(|&&c| c >= 2).count() > 500);
    }

    #[test]
    fn near_plane_clipping_keeps_the_visible_part() {
        // A floor triangle passing under and behind the camera, and a huge one far off-screen
        // on one side (guard band).
        let floor = Mesh {
            positions: vec![[-5.0, -1.0, -5.0], [5.0, -1.0, -5.0], [0.0, -1.0, 10.0]],
            triangles: vec![[0, 1, 2]],
            ..Mesh::default()
        };
        let cam = look_at(64, 48, 70.0, [0.0; 3], [0.0, -0.2, 1.0]);
        let s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(floor.clone())), 0)],
            vec![],
        );
        let (cover, depth) = agreement(&s, floor, &cam);
        eprintln!("behind-camera triangle: coverage {cover:.2} %, depth {depth:.2} %");
        assert!(cover >= 99.5 && depth >= 99.5);
        let huge = Mesh {
            positions: vec![[-1e6, -1.0, -1e6], [1e6, -1.0, -1e6], [0.0, -1.0, 1e6]],
            triangles: vec![[0, 1, 2]],
            ..Mesh::default()
        };
        let s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(huge.clone())), 0)],
            vec![],
        );
        // The f32 ray caster is imprecise at 10⁶ units: compare with the plane y = −1.
        let view = view_of(&cam);
        let out = rasterize_view(&s, &view, &no_shadows()).unwrap();
        for y in 0..48 {
            for x in 0..64 {
                let d = view.ray_direction(x as f64, y as f64);
                let got = f64::from(out.depth[y * 64 + x]);
                if d[1] < -1e-3 {
                    let t = -1.0 / d[1];
                    assert!((got - t).abs() <= 1e-5 * t, "({x}, {y}) {got} vs {t}");
                } else if d[1] >= 0.0 {
                    assert!(got.is_infinite());
                }
            }
        }
        // Corners behind the camera, at the eye and on the camera plane: no panic, no NaN.
        let view = view_of(&cam);
        let odd = Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, -1.0, 0.0],
                [0.0, -1.0, 3.0],
                [0.0, 0.0, -1.0],
                [1.0, 0.0, -2.0],
                [0.0, 1.0, -3.0],
            ],
            triangles: vec![[0, 1, 2], [3, 4, 5], [0, 3, 1], [2, 1, 4]],
            ..Mesh::default()
        };
        let s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(odd)), 0)],
            vec![Light::Directional {
                direction: [0.0, -1.0, 0.0],
                irradiance: [1.0; 3],
            }],
        );
        let r = rasterize_view(&s, &view, &RasterOptions::default()).unwrap();
        assert!(r.color.iter().chain(&r.normals).all(|v| v.is_finite()));
        assert!(r.depth.iter().all(|v| !v.is_nan()));
    }

    /// Intersection of pixel (x, y)'s centre ray with the plane y = 0.
    fn ground_point(view: &View, x: usize, y: usize) -> Option<V3> {
        let d = view.ray_direction(x as f64, y as f64);
        (d[1] < 0.0).then(|| add(view.eye, mul(d, -view.eye[1] / d[1])))
    }

    #[test]
    fn lambert_matches_the_radiometric_formula() {
        // Radiance L = albedo/π · E · cos θ for irradiance E on a surface facing the light.
        let albedo = [0.8f32, 0.5, 0.3];
        let e = [2.0f32, 1.5, 1.0];
        let dir = normalize([0.3, -1.0, 0.2]);
        let ground = quad([-10.0, 0.0, -10.0], [20.0, 0.0, 0.0], [0.0, 0.0, 20.0], 1.0);
        let cam = look_at(48, 40, 60.0, [0.5, 3.0, -4.0], [0.0; 3]);
        let view = view_of(&cam);
        let material = Material {
            albedo,
            ..Material::default()
        };
        let point = [1.0, 2.0, 0.5];
        let intensity = [3.0f32, 2.0, 1.0];
        let area = ([-0.5, 2.5, -0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        for (k, light) in [
            Light::Directional {
                direction: dir,
                irradiance: e,
            },
            Light::Point {
                position: point,
                intensity,
            },
            // A unit square at y = 2.5 radiating downwards (edge_u × edge_v = −y).
            Light::Area {
                corner: area.0,
                edge_u: area.1,
                edge_v: area.2,
                radiance: [4.0, 4.0, 4.0],
            },
            Light::Environment {
                radiance: [0.25, 0.5, 1.0],
                map: None,
            },
        ]
        .into_iter()
        .enumerate()
        {
            let s = scene(
                vec![material.clone()],
                vec![object(Shape::Mesh(Arc::new(ground.clone())), 0)],
                vec![light],
            );
            // With shadows on: a lone plane must not shadow itself.
            let out = rasterize_view(&s, &view, &RasterOptions::default()).unwrap();
            let mut n = 0;
            for y in 0..40 {
                for x in 0..48 {
                    let Some(p) = ground_point(&view, x, y) else {
                        continue;
                    };
                    if p[0].abs() > 9.9 || p[2].abs() > 9.9 {
                        continue;
                    }
                    let radiance: V3 = match k {
                        0 => mul(f3(e), -dir[1] / PI),
                        1 => {
                            let d = sub(point, p);
                            let r2 = dot(d, d);
                            mul(f3(intensity), d[1] / r2.sqrt() / r2 / PI)
                        }
                        2 => {
                            let c = [0.0, 2.5, 0.0];
                            let d = sub(c, p);
                            let r2 = dot(d, d);
                            let cos = d[1] / r2.sqrt();
                            // Intensity radiance · area · cos θ_light, then E = I cos θ / r².
                            mul([4.0; 3], 1.0 * cos * cos / r2 / PI)
                        }
                        _ => [0.25, 0.5, 1.0],
                    };
                    for c in 0..3 {
                        let expect = f64::from(albedo[c]) * radiance[c];
                        let got = f64::from(out.color[3 * (y * 48 + x) + c]);
                        assert!(
                            (got - expect).abs() <= 1e-5 * expect.abs().max(1e-3),
                            "light {k} ({x}, {y}) channel {c}: {got} vs {expect}"
                        );
                    }
                    n += 1;
                }
            }
            assert!(n > 800, "{n}");
        }
    }

    #[test]
    fn specular_highlights_sit_at_the_mirror_direction() {
        // Light travelling so that its mirror reflection at (0.8, 0, 0.4) reaches the eye.
        let dir = normalize([-0.8, -2.0, -3.4]);
        let ground = quad([-10.0, 0.0, -10.0], [20.0, 0.0, 0.0], [0.0, 0.0, 20.0], 1.0);
        let (w, h) = (96usize, 96usize);
        let cam = look_at(w, h, 60.0, [0.0, 2.0, -3.0], [0.5, 0.0, 0.0]);
        let view = view_of(&cam);
        // Mirror point: P on y = 0 with the reflected light direction pointing at the eye.
        let r = [dir[0], -dir[1], dir[2]];
        let p = sub(view.eye, mul(r, view.eye[1] / r[1]));
        assert!(norm(sub(p, [0.8, 0.0, 0.4])) < 1e-9);
        let expect = view.project(p).unwrap();
        for shading in [Shading::Phong, Shading::BlinnPhong] {
            let m = Material {
                albedo: [0.0; 3],
                specular: 1.0,
                shininess: 400.0,
                shading,
                ..Material::default()
            };
            let s = scene(
                vec![m],
                vec![object(Shape::Mesh(Arc::new(ground.clone())), 0)],
                vec![Light::Directional {
                    direction: dir,
                    irradiance: [1.0; 3],
                }],
            );
            let out = rasterize_view(&s, &view, &no_shadows()).unwrap();
            let best = (0..w * h)
                .max_by(|&a, &b| out.color[3 * a].total_cmp(&out.color[3 * b]))
                .unwrap();
            let (bx, by) = ((best % w) as f64, (best / w) as f64);
            let dist = ((bx - expect[0]).powi(2) + (by - expect[1]).powi(2)).sqrt();
            eprintln!(
                "{shading:?}: highlight at ({bx}, {by}), mirror point projects to ({:.2}, {:.2})",
                expect[0], expect[1]
            );
            assert!(dist <= 1.0, "{shading:?}: {dist}");
            assert!(out.color[3 * best] > 1.0);
        }
    }

    #[test]
    fn a_flat_normal_map_changes_nothing() {
        let flat = Texture {
            image: Arc::new(
                Image::from_f32(2, 2, Channels::Rgb, [0.5, 0.5, 1.0].repeat(4)).unwrap(),
            ),
            wrap: TextureWrap::Repeat,
            filter: TextureFilter::Bilinear,
            border: [0.0; 4],
            max_anisotropy: 1,
            uv_scale: [1.0, 1.0],
        };
        let ground = quad([-3.0, -1.0, -3.0], [6.0, 0.0, 0.0], [0.0, 0.2, 6.0], 4.0);
        let cam = look_at(64, 48, 60.0, [0.3, 1.5, -4.0], [0.0; 3]);
        let lights = vec![
            Light::Point {
                position: [1.0, 2.0, -1.0],
                intensity: [5.0; 3],
            },
            Light::Directional {
                direction: [0.2, -1.0, 0.4],
                irradiance: [1.0; 3],
            },
        ];
        for shading in [Shading::BlinnPhong, Shading::Pbr, Shading::Phong] {
            let base = Material {
                albedo: [0.7, 0.6, 0.5],
                specular: 0.5,
                shininess: 20.0,
                roughness: 0.4,
                metalness: 0.3,
                shading,
                ..Material::default()
            };
            let mut mapped = base.clone();
            mapped.normal_texture = Some(flat.clone());
            let objects = vec![
                object(Shape::Mesh(Arc::new(ground.clone())), 0),
                object(
                    Shape::Sphere {
                        center: [0.0, 0.0, 0.0],
                        radius: 0.7,
                    },
                    0,
                ),
            ];
            let render = |m: Material| {
                let s = scene(vec![m], objects.clone(), lights.clone());
                rasterize_view(&s, &view_of(&cam), &no_shadows()).unwrap()
            };
            let (a, b) = (render(base), render(mapped));
            let worst = a
                .color
                .iter()
                .zip(&b.color)
                .map(|(x, y)| (x - y).abs() / x.abs().max(1e-3))
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "{shading:?}: {worst}");
            assert!(a.color.iter().any(|&v| v > 0.05));
        }
    }

    #[test]
    fn directional_shadows_fall_where_the_occluder_projects() {
        let dir = normalize([0.3, -1.0, 0.15]);
        let e = [1.0f32; 3];
        let albedo = 0.6f32;
        let occluder = quad([-0.5, 1.0, -0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1.0);
        let s = scene(
            vec![Material {
                albedo: [albedo; 3],
                ..Material::default()
            }],
            vec![
                object(
                    Shape::Plane {
                        point: [0.0; 3],
                        normal: [0.0, 1.0, 0.0],
                        half_extent: f64::INFINITY,
                    },
                    0,
                ),
                object(Shape::Mesh(Arc::new(occluder)), 0),
            ],
            vec![Light::Directional {
                direction: dir,
                irradiance: e,
            }],
        );
        let (w, h) = (96usize, 80usize);
        let cam = look_at(w, h, 50.0, [0.5, 3.5, -2.5], [-0.3, 0.0, 0.0]);
        let view = view_of(&cam);
        let size = 512;
        let out = rasterize_view(
            &s,
            &view,
            &RasterOptions {
                shadow_map_size: size,
                ..RasterOptions::default()
            },
        )
        .unwrap();
        // The map spans the occluder's footprint across the light (≈ 1.1 world units).
        let band = 4.0 * 1.2 / f64::from(size);
        let lit = f64::from(albedo) / PI * -dir[1];
        let l = mul(dir, -1.0);
        let (mut dark, mut bright) = (0, 0);
        for y in 0..h {
            for x in 0..w {
                if out.ids[y * w + x] != 0.0 {
                    continue;
                }
                let Some(p) = ground_point(&view, x, y) else {
                    continue;
                };
                // Towards the light up to the occluder's height.
                let q = add(p, mul(l, 1.0 / l[1]));
                let inside = 0.5 - q[0].abs().max(q[2].abs());
                let got = f64::from(out.color[3 * (y * w + x)]);
                if inside > band {
                    assert_eq!(got, 0.0, "({x}, {y}) should be in shadow");
                    dark += 1;
                } else if inside < -band {
                    assert!((got - lit).abs() <= 1e-5 * lit, "({x}, {y}) {got} vs {lit}");
                    bright += 1;
                }
            }
        }
        eprintln!("shadow: {dark} pixels dark, {bright} lit");
        assert!(dark > 150 && bright > 1000, "{dark} {bright}");
    }

    #[test]
    fn alpha_blending_is_over_back_to_front() {
        // Opaque blue quad at z = 3, half-opaque red at z = 2 and green at z = 1.5.
        let q = |z: f64, s: f64| quad([-s, -s, z], [2.0 * s, 0.0, 0.0], [0.0, 2.0 * s, 0.0], 1.0);
        let cam = look_at(32, 32, 60.0, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]);
        let materials = vec![
            unlit([0.0, 0.0, 1.0], 1.0),
            unlit([1.0, 0.0, 0.0], 0.5),
            unlit([0.0, 1.0, 0.0], 0.5),
        ];
        let blue = object(Shape::Mesh(Arc::new(q(3.0, 10.0))), 0);
        let red = object(Shape::Mesh(Arc::new(q(2.0, 10.0))), 1);
        let green = object(Shape::Mesh(Arc::new(q(1.5, 0.5))), 2);
        let centre = 3 * (16 * 32 + 16);
        let corner = 3 * (32 + 1);
        for objects in [
            vec![blue.clone(), red.clone()],
            vec![red.clone(), blue.clone()],
        ] {
            let s = scene(materials.clone(), objects, vec![]);
            let out = rasterize_view(&s, &view_of(&cam), &no_shadows()).unwrap();
            assert_eq!(&out.color[centre..centre + 3], &[0.5, 0.0, 0.5]);
        }
        for objects in [
            vec![blue.clone(), red.clone(), green.clone()],
            vec![green, red, blue],
        ] {
            let s = scene(materials.clone(), objects.clone(), vec![]);
            let out = rasterize_view(&s, &view_of(&cam), &no_shadows()).unwrap();
            // Green over (red over blue).
            assert_eq!(&out.color[centre..centre + 3], &[0.25, 0.5, 0.25]);
            assert_eq!(&out.color[corner..corner + 3], &[0.5, 0.0, 0.5]);
            // Depth and ids describe the nearest surface, transparent or not.
            let green_index = objects.iter().position(|o| o.material == 2).unwrap();
            assert_eq!(out.ids[16 * 32 + 16], green_index as f32);
            assert!(
                (out.depth[16 * 32 + 16] - 2.5).abs() < 1e-3,
                "{}",
                out.depth[16 * 32 + 16]
            );
        }
    }

    fn busy_scene() -> Scene {
        let ico = bumpy_icosphere(4, 0.08, 3);
        let mut ico_object = object(Shape::Mesh(Arc::new(ico)), 0);
        ico_object.world_from_object.translation = [-0.8, 0.0, 0.0];
        let mut ball = object(
            Shape::Sphere {
                center: [0.0; 3],
                radius: 0.6,
            },
            1,
        );
        ball.world_from_object.translation = [0.9, -0.2, 0.3];
        let glass = object(
            Shape::Mesh(Arc::new(quad(
                [-1.5, -0.5, -1.0],
                [3.0, 0.0, 0.0],
                [0.0, 1.2, 0.0],
                1.0,
            ))),
            2,
        );
        let mut s = scene(
            vec![
                Material {
                    albedo: [0.7, 0.4, 0.3],
                    specular: 0.3,
                    shading: Shading::BlinnPhong,
                    ..Material::default()
                },
                Material {
                    shading: Shading::Pbr,
                    metalness: 0.8,
                    roughness: 0.3,
                    ..Material::default()
                },
                Material {
                    albedo: [0.2, 0.6, 0.9],
                    opacity: 0.4,
                    ..Material::default()
                },
                Material::default(),
            ],
            vec![
                ico_object,
                ball,
                glass,
                object(
                    Shape::Plane {
                        point: [0.0, -1.1, 0.0],
                        normal: [0.0, 1.0, 0.0],
                        half_extent: f64::INFINITY,
                    },
                    3,
                ),
            ],
            vec![
                Light::Directional {
                    direction: [0.3, -1.0, 0.2],
                    irradiance: [2.0; 3],
                },
                Light::Point {
                    position: [0.0, 2.0, -2.0],
                    intensity: [3.0; 3],
                },
                Light::Environment {
                    radiance: [0.1; 3],
                    map: None,
                },
            ],
        );
        s.cameras.push(scene_camera_from_look_at(&look_at(
            80,
            60,
            55.0,
            [0.4, 1.0, -4.0],
            [0.0, -0.2, 0.0],
        )));
        s
    }

    #[test]
    fn one_and_three_threads_give_identical_images() {
        let s = busy_scene();
        for samples in [1, 4] {
            let options = RasterOptions {
                samples,
                shadow_map_size: 256,
                ..RasterOptions::default()
            };
            let run = |k: usize| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(k)
                    .build()
                    .unwrap()
                    .install(|| rasterize(&s, 0, &options).unwrap())
            };
            let (a, b) = (run(1), run(3));
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a.color), bits(&b.color));
            assert_eq!(bits(&a.depth), bits(&b.depth));
            assert_eq!(bits(&a.normals), bits(&b.normals));
            assert_eq!(a.ids, b.ids);
            assert_eq!(a.hits, b.hits);
            assert!(a.hits > 1000);
        }
    }

    #[test]
    fn msaa_blends_edges_and_keeps_interiors() {
        // A lit red sphere impostor (one primitive) and a white unlit quad, over black.
        let mut s = scene(
            vec![
                Material {
                    albedo: [0.8, 0.2, 0.2],
                    ..Material::default()
                },
                unlit([1.0; 3], 1.0),
            ],
            vec![
                object(
                    Shape::Sphere {
                        center: [0.5, 0.0, 0.0],
                        radius: 0.8,
                    },
                    0,
                ),
                object(
                    Shape::Mesh(Arc::new(quad(
                        [-1.9, -0.7, -0.5],
                        [1.1, 0.1, 0.0],
                        [0.2, 1.3, 0.0],
                        1.0,
                    ))),
                    1,
                ),
            ],
            vec![Light::Directional {
                direction: [0.2, -0.5, 1.0],
                irradiance: [3.0; 3],
            }],
        );
        let (w, h) = (64usize, 48usize);
        s.cameras.push(scene_camera_from_look_at(&look_at(
            w,
            h,
            60.0,
            [0.0, 0.0, -3.0],
            [0.0; 3],
        )));
        let one = rasterize(&s, 0, &no_shadows()).unwrap();
        let four = rasterize(
            &s,
            0,
            &RasterOptions {
                samples: 4,
                ..no_shadows()
            },
        )
        .unwrap();
        // Depth, ids, normals and hits come from the centre sample: unchanged.
        assert_eq!(one.depth, four.depth);
        assert_eq!(one.normals, four.normals);
        assert_eq!(one.ids, four.ids);
        assert_eq!(one.hits, four.hits);
        let (mut interior, mut differing) = (0, 0);
        for y in 0..h {
            for x in 0..w {
                let id = one.ids[y * w + x];
                // Pixels whose neighbours' centres all see the same object: every sample
                // sees it too (both shapes are convex).
                let uniform = (y.saturating_sub(1)..(y + 2).min(h)).all(|yy| {
                    (x.saturating_sub(1)..(x + 2).min(w)).all(|xx| one.ids[yy * w + xx] == id)
                });
                let p = 3 * (y * w + x);
                let (a, b) = (&one.color[p..p + 3], &four.color[p..p + 3]);
                if uniform {
                    assert_eq!(a, b, "interior ({x}, {y})");
                    interior += usize::from(id >= 0.0);
                } else if a != b {
                    differing += 1;
                }
                // Grey pixels are the white quad over black: coverage in quarters.
                if b[0] == b[1] && b[1] == b[2] {
                    let q = 4.0 * b[0];
                    assert_eq!(q, q.round(), "({x}, {y}) {b:?}");
                }
            }
        }
        let quarters = four
            .color
            .chunks(3)
            .filter(|c| c[1] == c[0] && [0.25, 0.5, 0.75].contains(&c[0]))
            .count();
        eprintln!(
            "msaa: {interior} interior pixels equal samples = 1, {differing} edge pixels differ, \
             {quarters} quad-edge pixels at 1/4, 1/2, 3/4"
        );
        assert!(interior > 500 && differing > 40 && quarters > 10);
    }

    #[test]
    fn culling_selects_the_near_or_far_side() {
        let ico = bumpy_icosphere(4, 0.0, 1);
        let mut s = scene(
            vec![Material::default()],
            vec![object(Shape::Mesh(Arc::new(ico)), 0)],
            vec![],
        );
        s.cameras.push(scene_camera_from_look_at(&look_at(
            48,
            48,
            50.0,
            [0.0, 0.0, -3.0],
            [0.0; 3],
        )));
        let run = |cull| {
            rasterize(
                &s,
                0,
                &RasterOptions {
                    cull,
                    ..no_shadows()
                },
            )
            .unwrap()
        };
        let (none, back, front) = (run(Cull::None), run(Cull::Back), run(Cull::Front));
        assert_eq!(none.depth, back.depth);
        assert!(front.hits > 500);
        for i in 0..48 * 48 {
            if none.depth[i].is_finite() && front.depth[i].is_finite() {
                assert!(front.depth[i] > none.depth[i]);
            }
        }
    }

    #[test]
    fn gouraud_equals_lambert_where_lighting_is_linear() {
        let ground = quad([-4.0, 0.0, -4.0], [8.0, 0.0, 0.0], [0.0, 0.0, 8.0], 1.0);
        let cam = look_at(32, 32, 60.0, [0.0, 2.0, -3.0], [0.0; 3]);
        let render = |shading| {
            let s = scene(
                vec![Material {
                    shading,
                    ..Material::default()
                }],
                vec![object(Shape::Mesh(Arc::new(ground.clone())), 0)],
                vec![Light::Directional {
                    direction: [0.3, -1.0, 0.2],
                    irradiance: [1.0; 3],
                }],
            );
            rasterize_view(&s, &view_of(&cam), &no_shadows()).unwrap()
        };
        let (g, l) = (render(Shading::Gouraud), render(Shading::Lambert));
        for (a, b) in g.color.iter().zip(&l.color) {
            assert!((a - b).abs() <= 1e-6, "{a} {b}");
        }
        assert!(l.hits > 500);
    }

    #[test]
    fn degenerate_input_is_handled_or_refused() {
        let cam = look_at(16, 12, 60.0, [0.0, 0.0, -3.0], [0.0; 3]);
        let view = view_of(&cam);
        // Empty scene: background everywhere.
        let empty = scene(vec![], vec![], vec![]);
        let out = rasterize_view(
            &empty,
            &view,
            &RasterOptions {
                background: [0.1, 0.2, 0.3],
                ..RasterOptions::default()
            },
        )
        .unwrap();
        assert_eq!(out.hits, 0);
        assert!(out.depth.iter().all(|d| *d == f32::INFINITY));
        assert!(out.ids.iter().all(|d| *d == -1.0));
        assert!(out.color.chunks(3).all(|c| c == [0.1, 0.2, 0.3]));
        // Zero-area triangles: nothing drawn.
        let flat = mesh_shape(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [2.0, 2.0, 0.0],
                [0.5, 0.0, 0.0],
            ],
            vec![[0, 1, 2], [3, 3, 3], [0, 0, 1]],
        );
        let s = scene(vec![Material::default()], vec![object(flat, 0)], vec![]);
        assert_eq!(rasterize_view(&s, &view, &no_shadows()).unwrap().hits, 0);
        // NaN vertex.
        let nan = mesh_shape(
            vec![[0.0, 0.0, 0.0], [1.0, f32::NAN, 0.0], [0.0, 1.0, 0.0]],
            vec![[0, 1, 2]],
        );
        let s = scene(vec![Material::default()], vec![object(nan, 0)], vec![]);
        let e = rasterize_view(&s, &view, &no_shadows()).unwrap_err();
        assert!(e.contains("vertex 1") && e.contains("non-finite"), "{e}");
        // Bad triangle index and bad material index.
        let bad = mesh_shape(vec![[0.0; 3]; 3], vec![[0, 1, 3]]);
        let s = scene(vec![Material::default()], vec![object(bad, 0)], vec![]);
        assert!(
            rasterize_view(&s, &view, &no_shadows())
                .unwrap_err()
                .contains("triangle 0")
        );
        let ball = Shape::Sphere {
            center: [0.0; 3],
            radius: 1.0,
        };
        let s = scene(
            vec![Material::default()],
            vec![object(ball.clone(), 1)],
            vec![],
        );
        let e = rasterize_view(&s, &view, &no_shadows()).unwrap_err();
        assert!(e.contains("material 1"), "{e}");
        // 1×1 image.
        let mut s = scene(vec![Material::default()], vec![object(ball, 0)], vec![]);
        s.cameras.push(scene_camera_from_look_at(&look_at(
            1,
            1,
            30.0,
            [0.0, 0.0, -3.0],
            [0.0; 3],
        )));
        let out = rasterize(&s, 0, &RasterOptions::default()).unwrap();
        assert_eq!(out.hits, 1);
        assert!((out.depth[0] - 2.0).abs() < 1e-6);
        // Camera index out of range; bad options.
        let e = rasterize(&s, 1, &RasterOptions::default()).unwrap_err();
        assert!(e.contains("out of range"), "{e}");
        for bad in [
            RasterOptions {
                samples: 2,
                ..RasterOptions::default()
            },
            RasterOptions {
                near: 0.0,
                ..RasterOptions::default()
            },
            RasterOptions {
                shadow_map_size: 9000,
                ..RasterOptions::default()
            },
        ] {
            assert!(rasterize(&s, 0, &bad).is_err());
        }
    }

    #[test]
    fn operator_runs_on_a_scene_value() {
        let mut s = busy_scene();
        s.cameras[0].camera.width = 40;
        s.cameras[0].camera.height = 30;
        let op = Rasterize::new(RasterizeParams {
            samples: 4,
            cull: Cull::Back,
            ..RasterizeParams::default()
        })
        .unwrap();
        let specs = Rasterize::inputs();
        let ctx = RunContext {
            node: "r".into(),
            threads: 1,
            element: None,
        };
        let values = vec![Some(Value::Scene(Arc::new(s.clone())))];
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(color)) = out.take("color") else {
            panic!("no colour")
        };
        assert_eq!(
            (color.width(), color.height(), color.channels()),
            (40, 30, Channels::Rgb)
        );
        let Some(Value::Integer(hits)) = out.take("hits") else {
            panic!("no hits")
        };
        let direct = rasterize(
            &s,
            0,
            &RasterOptions {
                samples: 4,
                cull: Cull::Back,
                ..RasterOptions::default()
            },
        )
        .unwrap();
        assert_eq!(hits as usize, direct.hits);
        assert_eq!(color.as_f32().unwrap(), &direct.color[..]);
        assert!(
            Rasterize::new(RasterizeParams {
                samples: 3,
                ..RasterizeParams::default()
            })
            .is_err()
        );
        let op = Rasterize::new(RasterizeParams {
            camera: 5,
            ..RasterizeParams::default()
        })
        .unwrap();
        let e = op.run(&ctx, &Inputs::new(&specs, &values)).err().unwrap();
        assert!(e.to_string().contains("out of range"), "{e}");
    }
}
