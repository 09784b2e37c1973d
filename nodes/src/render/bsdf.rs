//! Physically-based shading formulas as pure functions, shared by the renderers: exact
//! dielectric Fresnel equations, Schlick's approximation, Snell refraction, the GGX
//! (Trowbridge–Reitz) microfacet distribution with the Smith masking functions, visible-normal
//! sampling, cosine-weighted hemisphere sampling and the small vector helpers they need.
//!
//! Local shading frames have the surface normal along +z. Directions point away from the
//! surface (`wo` towards the viewer, `wi` towards the light), pbrt's convention.
//!
//! References: Walter, Marschner, Li & Torrance, "Microfacet models for refraction through rough
//! surfaces" (EGSR 2007); Heitz, "Understanding the masking-shadowing function in
//! microfacet-based BRDFs" (JCGT 2014) and "Sampling the GGX distribution of visible normals"
//! (JCGT 2018); Schlick, "An inexpensive BRDF model for physically-based rendering" (CGF 1994);
//! Shirley & Chiu, "A low distortion map between disk and square" (JGT 1997); Duff et al.,
//! "Building an orthonormal basis, revisited" (JCGT 2017); Pharr, Jakob & Humphreys, "Physically
//! Based Rendering" (4th ed.) §9.

use std::f64::consts::PI;

/// A 3-vector.
pub type Vec3 = [f64; 3];

/// `a + b`.
#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a − b`.
#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `s · a`.
#[inline]
pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Component-wise product.
#[inline]
pub fn mul(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] * b[0], a[1] * b[1], a[2] * b[2]]
}

/// `a + s · b`.
#[inline]
pub fn madd(a: Vec3, b: Vec3, s: f64) -> Vec3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

/// Dot product.
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Cross product.
#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Euclidean length.
#[inline]
pub fn length(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|`, or `None` for a zero or non-finite vector.
#[inline]
pub fn normalize(a: Vec3) -> Option<Vec3> {
    let n = length(a);
    (n > 0.0 && n.is_finite()).then(|| scale(a, 1.0 / n))
}

/// An orthonormal basis `(t, b)` completing the unit vector `n` to a right-handed frame
/// `t × b = n`, continuous except across `n_z = 0⁻` (Duff et al. 2017, branchless).
pub fn orthonormal_basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1f64.copysign(n[2]);
    let a = -1.0 / (sign + n[2]);
    let b = n[0] * n[1] * a;
    (
        [1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]],
        [b, sign + n[1] * n[1] * a, -n[1]],
    )
}

/// A shading frame: unit tangent, bitangent and normal (right-handed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Tangent (local x).
    pub t: Vec3,
    /// Bitangent (local y).
    pub b: Vec3,
    /// Normal (local z).
    pub n: Vec3,
}

impl Frame {
    /// The frame around `n` with the tangent closest to `tangent` (Gram–Schmidt; the
    /// [`orthonormal_basis`] when `tangent` is parallel to `n` or zero).
    pub fn new(n: Vec3, tangent: Vec3) -> Frame {
        let t = normalize(madd(tangent, n, -dot(tangent, n)));
        match t {
            Some(t) => Frame {
                t,
                b: cross(n, t),
                n,
            },
            None => {
                let (t, b) = orthonormal_basis(n);
                Frame { t, b, n }
            }
        }
    }

    /// World direction in local coordinates.
    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        [dot(v, self.t), dot(v, self.b), dot(v, self.n)]
    }

    /// Local direction in world coordinates.
    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        [
            self.t[0] * v[0] + self.b[0] * v[1] + self.n[0] * v[2],
            self.t[1] * v[0] + self.b[1] * v[1] + self.n[1] * v[2],
            self.t[2] * v[0] + self.b[2] * v[1] + self.n[2] * v[2],
        ]
    }
}

/// Mirror reflection of `wo` (pointing away from the surface) about the unit normal `n`:
/// `2 (wo·n) n − wo`.
#[inline]
pub fn reflect(wo: Vec3, n: Vec3) -> Vec3 {
    madd(scale(wo, -1.0), n, 2.0 * dot(wo, n))
}

/// Snell refraction of `wi` (unit, pointing away from the surface on the side of `n`) through a
/// boundary with relative index `eta = η_t / η_i` (the far side's over `wi`'s side). `n` must
/// be on `wi`'s side (`wi·n ≥ 0`). Returns the transmitted unit direction (pointing away on
/// the far side), or `None` on total internal reflection (`sin²θ_t ≥ 1`).
pub fn refract(wi: Vec3, n: Vec3, eta: f64) -> Option<Vec3> {
    let cos_i = dot(n, wi).clamp(0.0, 1.0);
    let sin2_i = (1.0 - cos_i * cos_i).max(0.0);
    let sin2_t = sin2_i / (eta * eta);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some(madd(scale(wi, -1.0 / eta), n, cos_i / eta - cos_t))
}

/// Unpolarized Fresnel reflectance of a smooth dielectric boundary (the exact Fresnel
/// equations, the mean of the s- and p-polarized reflectances). `cos_i` is the cosine between
/// the incident direction and the normal on the incident side; a negative `cos_i` means the
/// ray arrives from the other side and `eta` is inverted. `eta = η_t / η_i`. Returns 1 on total
/// internal reflection.
pub fn fresnel_dielectric(cos_i: f64, eta: f64) -> f64 {
    let (cos_i, eta) = if cos_i < 0.0 {
        (-cos_i, 1.0 / eta)
    } else {
        (cos_i, eta)
    };
    let cos_i = cos_i.min(1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).max(0.0).sqrt();
    let r_parallel = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perpendicular = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parallel * r_parallel + r_perpendicular * r_perpendicular)
}

/// Schlick's approximation `F0 + (1 − F0)(1 − cos)⁵` per channel.
#[inline]
pub fn fresnel_schlick(f0: Vec3, cos: f64) -> Vec3 {
    let m = (1.0 - cos.clamp(0.0, 1.0)).powi(5);
    f0.map(|f| f + (1.0 - f) * m)
}

/// GGX normal distribution `D(h) = α² / (π ((α² − 1) cos²θ_h + 1)²)` for the local half
/// vector's cosine `cos_h = h_z` (Walter et al. 2007, eq. 33).
#[inline]
pub fn ggx_d(cos_h: f64, alpha: f64) -> f64 {
    if cos_h <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let c2 = cos_h * cos_h;
    let d = c2 * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

/// Smith's auxiliary function `Λ(w) = (−1 + √(1 + α² tan²θ)) / 2` of GGX (Heitz 2014, eq. 72)
/// for a local direction `w`.
#[inline]
pub fn ggx_lambda(w: Vec3, alpha: f64) -> f64 {
    let cos2 = w[2] * w[2];
    if cos2 == 0.0 {
        return f64::INFINITY;
    }
    let tan2 = (w[0] * w[0] + w[1] * w[1]) / cos2;
    0.5 * (-1.0 + (1.0 + alpha * alpha * tan2).sqrt())
}

/// Smith masking `G1(w) = 1 / (1 + Λ(w))`.
#[inline]
pub fn ggx_g1(w: Vec3, alpha: f64) -> f64 {
    1.0 / (1.0 + ggx_lambda(w, alpha))
}

/// Height-correlated Smith masking–shadowing `G2 = 1 / (1 + Λ(wo) + Λ(wi))` (Heitz 2014,
/// eq. 99).
#[inline]
pub fn ggx_g2(wo: Vec3, wi: Vec3, alpha: f64) -> f64 {
    1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))
}

/// A visible GGX normal for the local view direction `wo` (`wo_z > 0`) from two uniform
/// numbers (Heitz 2018, listing 1, isotropic `α`): the half vector `h` distributed with
/// `D_wo(h) = G1(wo) max(0, wo·h) D(h) / wo_z`.
pub fn ggx_sample_visible_normal(wo: Vec3, alpha: f64, u1: f64, u2: f64) -> Vec3 {
    // Stretch the view vector to the hemisphere configuration.
    let vh = normalize([alpha * wo[0], alpha * wo[1], wo[2]]).unwrap_or([0.0, 0.0, 1.0]);
    let lensq = vh[0] * vh[0] + vh[1] * vh[1];
    let t1 = if lensq > 0.0 {
        scale([-vh[1], vh[0], 0.0], 1.0 / lensq.sqrt())
    } else {
        [1.0, 0.0, 0.0]
    };
    let t2 = cross(vh, t1);
    // A point on the projected area: a disk, its far half squashed by the view angle.
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh[2]);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
    let nh = add(
        add(scale(t1, p1), scale(t2, p2)),
        scale(vh, (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt()),
    );
    // Unstretch.
    normalize([alpha * nh[0], alpha * nh[1], nh[2].max(0.0)]).unwrap_or([0.0, 0.0, 1.0])
}

/// Solid-angle density of `wi` when it is the reflection of `wo` about a visible normal drawn
/// by [`ggx_sample_visible_normal`]: `G1(wo) D(h) / (4 wo_z)` with `h = normalize(wo + wi)`
/// (Heitz 2018, eq. 17 with the reflection Jacobian `1 / (4 |wo·h|)`). Defined for every `wi`,
/// below the horizon included (the sampler can produce those; the renderer discards them).
pub fn ggx_reflection_pdf(wo: Vec3, wi: Vec3, alpha: f64) -> f64 {
    if wo[2] <= 0.0 {
        return 0.0;
    }
    let Some(h) = normalize(add(wo, wi)) else {
        return 0.0;
    };
    // The sampler only produces upper-hemisphere normals facing `wo`.
    if h[2] <= 0.0 || dot(wo, h) <= 0.0 {
        return 0.0;
    }
    ggx_g1(wo, alpha) * ggx_d(h[2], alpha) / (4.0 * wo[2])
}

/// The GGX conductor BRDF `F(wo·h) D(h) G2(wo, wi) / (4 cos_o cos_i)` per channel with
/// Schlick's Fresnel from `f0`, for local directions on the upper hemisphere (0 otherwise).
pub fn ggx_reflection_brdf(wo: Vec3, wi: Vec3, alpha: f64, f0: Vec3) -> Vec3 {
    if wo[2] <= 0.0 || wi[2] <= 0.0 {
        return [0.0; 3];
    }
    let Some(h) = normalize(add(wo, wi)) else {
        return [0.0; 3];
    };
    let d = ggx_d(h[2], alpha);
    let g = ggx_g2(wo, wi, alpha);
    let f = fresnel_schlick(f0, dot(wo, h));
    let k = d * g / (4.0 * wo[2] * wi[2]);
    f.map(|c| c * k)
}

/// Concentric map of the unit square onto the unit disk (Shirley & Chiu 1997): area
/// preserving, low distortion.
pub fn concentric_disk(u1: f64, u2: f64) -> [f64; 2] {
    let a = 2.0 * u1 - 1.0;
    let b = 2.0 * u2 - 1.0;
    if a == 0.0 && b == 0.0 {
        return [0.0, 0.0];
    }
    let (r, phi) = if a.abs() > b.abs() {
        (a, 0.25 * PI * (b / a))
    } else {
        (b, 0.5 * PI - 0.25 * PI * (a / b))
    };
    [r * phi.cos(), r * phi.sin()]
}

/// Cosine-weighted local direction on the upper hemisphere (Malley's method: a concentric
/// disk point lifted to the hemisphere), density `cos θ / π`.
pub fn cosine_hemisphere(u1: f64, u2: f64) -> Vec3 {
    let [x, y] = concentric_disk(u1, u2);
    [x, y, (1.0 - x * x - y * y).max(0.0).sqrt()]
}

/// The power heuristic with β = 2 for two strategies with one sample each (Veach 1997,
/// §9.2.4): `p_a² / (p_a² + p_b²)`.
#[inline]
pub fn power_heuristic(pdf_a: f64, pdf_b: f64) -> f64 {
    let a = pdf_a * pdf_a;
    let b = pdf_b * pdf_b;
    if a == 0.0 || !b.is_finite() {
        0.0
    } else if !a.is_finite() {
        1.0
    } else {
        a / (a + b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fresnel_exact_values() {
        for n in [1.33f64, 1.5, 2.4] {
            // Normal incidence: ((n − 1) / (n + 1))², from either side.
            let r0 = ((n - 1.0) / (n + 1.0)).powi(2);
            assert!((fresnel_dielectric(1.0, n) - r0).abs() < 1e-15);
            assert!((fresnel_dielectric(-1.0, 1.0 / n) - r0).abs() < 1e-15);
            // Brewster's angle tan θ_B = n: the p-reflectance vanishes, so F = R_s / 2 with
            // R_s = ((n² − 1)/(n² + 1))².
            let theta_b = n.atan();
            let rs = ((n * n - 1.0) / (n * n + 1.0)).powi(2);
            assert!((fresnel_dielectric(theta_b.cos(), n) - 0.5 * rs).abs() < 1e-12);
            // Total internal reflection beyond the critical angle from inside.
            let critical = (1.0 / n).asin();
            assert_eq!(fresnel_dielectric((critical + 1e-6).cos(), 1.0 / n), 1.0);
            assert!(fresnel_dielectric((critical - 1e-3).cos(), 1.0 / n) < 1.0);
            // Reciprocity: the same reflectance seen from the refracted side.
            let ti = 0.6f64;
            let tt = (ti.sin() / n).asin();
            let a = fresnel_dielectric(ti.cos(), n);
            let b = fresnel_dielectric(tt.cos(), 1.0 / n);
            assert!((a - b).abs() < 1e-12, "{a} {b}");
            // Grazing incidence reflects everything.
            assert!((fresnel_dielectric(0.0, n) - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn refraction_obeys_snell_and_total_internal_reflection() {
        let n = [0.0, 0.0, 1.0];
        let eta = 1.5;
        for theta in [0.0f64, 0.3, 0.9, 1.4] {
            let wi = [theta.sin(), 0.0, theta.cos()];
            let wt = refract(wi, n, eta).unwrap();
            assert!((length(wt) - 1.0).abs() < 1e-14);
            assert!(wt[2] <= 0.0, "transmitted below the surface");
            let sin_t = (wt[0] * wt[0] + wt[1] * wt[1]).sqrt();
            assert!((sin_t * eta - theta.sin()).abs() < 1e-14, "Snell");
            assert!(wt[0] <= 0.0, "tangential component flips side");
            // Reversibility: light arriving along −wt leaves along −wi.
            let back = refract(wt, scale(n, -1.0), 1.0 / eta).unwrap();
            for k in 0..3 {
                assert!((back[k] - wi[k]).abs() < 1e-12, "{back:?} vs {wi:?}");
            }
        }
        // From glass to air beyond the critical angle asin(1/1.5).
        let critical = (1.0f64 / 1.5).asin();
        let wi = [(critical + 0.01).sin(), 0.0, (critical + 0.01).cos()];
        assert!(refract(wi, n, 1.0 / 1.5).is_none());
        let wi = [(critical - 0.01).sin(), 0.0, (critical - 0.01).cos()];
        assert!(refract(wi, n, 1.0 / 1.5).is_some());
        // Reflection.
        let r = reflect([0.6, 0.0, 0.8], n);
        assert!((r[0] + 0.6).abs() < 1e-15 && (r[2] - 0.8).abs() < 1e-15);
    }

    /// The density of the visible-normal reflection sampler integrates to 1 over the sphere (it
    /// is a density of the sampler's output), and its mass above the horizon is ≤ 1 and, at
    /// normal incidence, exactly the GGX probability 1/(1 + α²) of θ_h < 45°. Checked by stratified uniform-sphere Monte Carlo; also the
    /// histogram of actual samples agrees with the density on a few cones.
    #[test]
    fn ggx_sampling_pdf_integrates_to_one() {
        let n_theta = 400;
        let n_phi = 800;
        for &alpha in &[0.1, 0.3, 0.6, 1.0] {
            for &theta_o in &[0.0f64, 0.7, 1.3] {
                let wo = [theta_o.sin(), 0.0, theta_o.cos()];
                let mut sphere = 0.0;
                let mut upper = 0.0;
                // Midpoint rule in (cos θ, φ): uniform in solid angle.
                for i in 0..n_theta {
                    let z = -1.0 + 2.0 * (i as f64 + 0.5) / n_theta as f64;
                    let r = (1.0 - z * z).sqrt();
                    for j in 0..n_phi {
                        let phi = 2.0 * PI * (j as f64 + 0.5) / n_phi as f64;
                        let wi = [r * phi.cos(), r * phi.sin(), z];
                        let p = ggx_reflection_pdf(wo, wi, alpha);
                        sphere += p;
                        if z > 0.0 {
                            upper += p;
                        }
                    }
                }
                let dw = 4.0 * PI / (n_theta * n_phi) as f64;
                sphere *= dw;
                upper *= dw;
                let tol = if alpha < 0.2 { 0.03 } else { 0.01 };
                assert!(
                    (sphere - 1.0).abs() < tol,
                    "α {alpha} θo {theta_o}: ∫pdf = {sphere}"
                );
                assert!(upper <= sphere + 1e-9);
                if theta_o == 0.0 {
                    // At normal incidence the visible normals are D·cos distributed and the
                    // reflection stays above the horizon iff θ_h < 45°: mass 1/(1 + α²).
                    let exact = 1.0 / (1.0 + alpha * alpha);
                    assert!((upper - exact).abs() < tol, "α {alpha}: {upper} vs {exact}");
                }
            }
        }
    }

    #[test]
    fn ggx_samples_follow_their_density() {
        // Fraction of samples inside a cone around a direction vs ∫ pdf over that cone.
        let alpha = 0.4;
        let wo = normalize([0.5, 0.2, 0.8]).unwrap();
        let axis = reflect(wo, [0.0, 0.0, 1.0]);
        let cone_cos = 0.9;
        let n = 200_000;
        let mut rng = 12345u64;
        let mut next = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut inside = 0usize;
        for _ in 0..n {
            let h = ggx_sample_visible_normal(wo, alpha, next(), next());
            let wi = reflect(wo, h);
            if dot(wi, axis) > cone_cos {
                inside += 1;
            }
        }
        let frac = inside as f64 / n as f64;
        // ∫_cone pdf dω by uniform sampling of the cone.
        let (t, b) = orthonormal_basis(axis);
        let m = 400_000;
        let mut acc = 0.0;
        for _ in 0..m {
            let z = cone_cos + (1.0 - cone_cos) * next();
            let phi = 2.0 * PI * next();
            let r = (1.0 - z * z).sqrt();
            let wi = add(
                add(scale(t, r * phi.cos()), scale(b, r * phi.sin())),
                scale(axis, z),
            );
            acc += ggx_reflection_pdf(wo, wi, alpha);
        }
        let integral = acc / m as f64 * 2.0 * PI * (1.0 - cone_cos);
        assert!(
            (frac - integral).abs() < 0.01,
            "sampled {frac} vs ∫pdf {integral}"
        );
    }

    #[test]
    fn ggx_terms_are_consistent() {
        // D is normalized: ∫ D(h) cos θ_h dω_h = 1.
        for alpha in [0.05, 0.3, 1.0] {
            let n = 20_000;
            let mut acc = 0.0;
            for i in 0..n {
                let z = (i as f64 + 0.5) / n as f64;
                acc += ggx_d(z, alpha) * z;
            }
            let integral = acc * 2.0 * PI / n as f64;
            assert!((integral - 1.0).abs() < 2e-3, "α {alpha}: {integral}");
        }
        // G1 of the normal direction is 1, and falls towards grazing.
        assert_eq!(ggx_g1([0.0, 0.0, 1.0], 0.5), 1.0);
        assert!(ggx_g1([0.99, 0.0, 0.141], 0.5) < 0.7);
        // Cosine sampling and the disk map stay on their domains.
        for (a, b) in [(0.0, 0.0), (1.0, 1.0), (0.3, 0.9), (0.5, 0.5)] {
            let [x, y] = concentric_disk(a, b);
            assert!(x * x + y * y <= 1.0 + 1e-12);
            let w = cosine_hemisphere(a, b);
            assert!((length(w) - 1.0).abs() < 1e-12 && w[2] >= 0.0);
        }
        let (t, b) = orthonormal_basis(normalize([0.3, -0.4, -0.8]).unwrap());
        assert!(dot(t, b).abs() < 1e-15 && (length(t) - 1.0).abs() < 1e-15);
        assert!((power_heuristic(1.0, 1.0) - 0.5).abs() < 1e-15);
    }
}
