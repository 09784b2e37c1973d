//! Laplacian smoothing: `mesh.smooth`.
//!
//! One step moves every interior vertex by `λ L(v)`, `L(v) = Σ wⱼ (vⱼ − v) / Σ wⱼ` over its
//! neighbours, all vertices from the previous positions (Jacobi), so the order of vertices does
//! not matter and the result does not depend on the thread count. Boundary vertices stay fixed.
//! - uniform weights `wⱼ = 1` (the umbrella operator; it also evens out the triangles);
//! - cotangent weights `wⱼ = (cot αⱼ + cot βⱼ) / 2`, `αⱼ`, `βⱼ` the angles opposite the edge
//!   (Desbrun, Meyer, Schröder & Barr, "Implicit fairing of irregular meshes using diffusion and
//!   curvature flow", SIGGRAPH 1999), which move a vertex along the normal only: a planar region
//!   stays exactly in place. A vertex whose cotangent weights do not sum to a positive number (a
//!   fan of very obtuse triangles) falls back to uniform weights for that step.
//!
//! Taubin's λ|μ smoothing (Taubin, "A signal processing approach to fair surface design",
//! SIGGRAPH 1995) follows every `λ` step with a `μ` step, `μ < −λ < 0`, which undoes the
//! shrinking of plain Laplacian smoothing (a low-pass filter instead of a heat flow).

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::halfedge::{HalfedgeMesh, NONE, halfedge_of, mesh_input};
use super::normals::{NormalWeighting, cross, dot, norm, sub, vertex_normals};
use super::pointcloud::par_map;

param_enum! {
    /// The Laplacian of `mesh.smooth`.
    pub enum SmoothWeights {
        /// Every neighbour alike.
        Uniform = "uniform",
        /// Cotangent weights (mean-curvature flow).
        Cotangent = "cotangent",
    }
}

/// The cotangent of the angle at `p` between `q − p` and `r − p`.
fn cot(p: [f64; 3], q: [f64; 3], r: [f64; 3]) -> f64 {
    let (u, v) = (sub(q, p), sub(r, p));
    let s = norm(cross(u, v));
    if s > 0.0 { dot(u, v) / s } else { 0.0 }
}

/// `L(v)` for every vertex (zero on the boundary and for isolated vertices).
pub fn laplacian(
    mesh: &HalfedgeMesh,
    positions: &[[f64; 3]],
    weights: SmoothWeights,
) -> Vec<[f64; 3]> {
    par_map(mesh.vertex_capacity(), |v| {
        let v = v as u32;
        if !mesh.vertex_alive(v) || mesh.vertex_halfedge(v) == NONE || mesh.is_boundary_vertex(v) {
            return [0.0; 3];
        }
        let p = positions[v as usize];
        let weighted = |cotangent: bool| {
            let (mut s, mut w) = ([0.0; 3], 0.0);
            for h in mesh.outgoing(v) {
                let q = positions[mesh.dest(h) as usize];
                let wj = if cotangent {
                    // Opposite corners of the two triangles of the edge (interior vertex: both
                    // exist).
                    let a = positions[mesh.origin(mesh.prev(h)) as usize];
                    let t = mesh.twin(h);
                    let b = positions[mesh.origin(mesh.prev(t)) as usize];
                    0.5 * (cot(a, p, q) + cot(b, q, p))
                } else {
                    1.0
                };
                let d = sub(q, p);
                for k in 0..3 {
                    s[k] += wj * d[k];
                }
                w += wj;
            }
            (s, w)
        };
        let (mut s, mut w) = weighted(weights == SmoothWeights::Cotangent);
        if !(w > 0.0 && w.is_finite()) {
            (s, w) = weighted(false);
        }
        s.map(|x| x / w)
    })
}

/// `iterations` smoothing steps of `lambda` (each followed by a `mu` step when given).
pub fn smooth(
    mesh: &HalfedgeMesh,
    weights: SmoothWeights,
    iterations: u32,
    lambda: f64,
    mu: Option<f64>,
) -> Vec<[f64; 3]> {
    let mut p = mesh.positions().to_vec();
    let factors: Vec<f64> = std::iter::once(lambda).chain(mu).collect();
    for _ in 0..iterations {
        for &f in &factors {
            let l = laplacian(mesh, &p, weights);
            for (x, d) in p.iter_mut().zip(&l) {
                for k in 0..3 {
                    x[k] += f * d[k];
                }
            }
        }
    }
    p
}

params! {
    /// Parameters of `mesh.smooth`.
    pub struct SmoothParams {
        /// "uniform" or "cotangent" weights. Default "uniform".
        weights: SmoothWeights = SmoothWeights::Uniform,
        /// Smoothing steps (each a λ step, and a μ step with Taubin). Default 10.
        iterations: u32 = 10 => [min = 0, max = 100000],
        /// Step factor λ, in (0, 1]. Default 0.5.
        lambda: f64 = 0.5 => [min = 0.0, max = 1.0],
        /// Taubin's μ (negative, |μ| > λ; e.g. −0.53 with λ = 0.5); none: plain Laplacian
        /// smoothing. Default none.
        mu: Option<f64> = None => [min = -1.0, max = 0.0],
    }
}

/// Laplacian and Taubin smoothing (`mesh.smooth`). See [`smooth`].
#[derive(Debug, Clone, PartialEq)]
pub struct Smooth {
    params: SmoothParams,
}

impl Op for Smooth {
    type Params = SmoothParams;
    const ID: &'static str = "mesh.smooth";
    const SUMMARY: &'static str =
        "Smooths a triangle mesh: Laplacian (uniform or cotangent weights) or Taubin λ|μ.";
    const DOC: &'static str = r#"
Each step moves every interior vertex v by λ·L(v), L(v) = Σ w_j (v_j − v) / Σ w_j, all from the
previous positions; boundary vertices stay fixed. "uniform": w_j = 1. "cotangent":
w_j = (cot α_j + cot β_j)/2 (Desbrun et al., SIGGRAPH 1999), moving vertices along the normal
only, so flat regions stay put (a vertex whose weights do not sum to a positive number uses
uniform weights). With `mu` (Taubin, "A signal processing approach to fair surface design",
SIGGRAPH 1995) every λ step is followed by a μ step, μ < −λ, which keeps the volume that plain
Laplacian smoothing shrinks. Connectivity is unchanged; normals, if present, are recomputed
(angle-weighted); colors and texture coordinates pass through; tangents are dropped (rerun
`mesh.tangents`).

Metrics: `iterations`, `max_displacement` (scene units).

Example:
    "fair": (op: "mesh.smooth", inputs: { "mesh": "scan.mesh" }, params: (iterations: 20, lambda: 0.5, mu: -0.53)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "mesh",
            PortType::Mesh,
            "A manifold triangle mesh.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The smoothed mesh."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "iterations, max_displacement.",
            ),
        ]
    }

    fn new(p: SmoothParams) -> Result<Self, String> {
        if !(p.lambda > 0.0 && p.lambda <= 1.0) {
            return Err(format!("`lambda` must be in (0, 1], got {}", p.lambda));
        }
        if let Some(mu) = p.mu
            && !(mu.is_finite() && mu < -p.lambda && mu >= -1.0)
        {
            return Err(format!(
                "`mu` must satisfy −1 ≤ mu < −lambda = {}, got {mu}",
                -p.lambda
            ));
        }
        Ok(Smooth { params: p })
    }
}

impl Operator for Smooth {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = mesh_input(inputs, "mesh")?;
        let half = halfedge_of(mesh).map_err(|e| e.at("mesh"))?;
        let p = &self.params;
        let out = smooth(&half, p.weights, p.iterations, p.lambda, p.mu);
        let moved = out
            .iter()
            .zip(half.positions())
            .map(|(a, b)| norm(sub(*a, *b)))
            .fold(0.0, f64::max);
        let normals = mesh.normals.as_ref().map(|_| {
            let (n, _) = vertex_normals(&out, &mesh.triangles, NormalWeighting::Angle);
            n.iter().map(|v| v.map(|x| x as f32)).collect()
        });
        let result = Mesh {
            positions: out.iter().map(|v| v.map(|x| x as f32)).collect(),
            normals,
            // Moved vertices invalidate tangent frames; `mesh.tangents` recomputes them.
            tangents: None,
            ..Mesh::clone(mesh)
        };
        let mut m = Metrics::new();
        m.insert("iterations".into(), f64::from(p.iterations));
        m.insert("max_displacement".into(), moved);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(result)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::halfedge::tests::{grid, icosphere};
    use crate::mesh::metrics::signed_volume;

    #[test]
    fn planes_stay_planes_and_boundaries_stay_put() {
        // A tilted plane with jittered vertices: uniform smoothing keeps every vertex in the
        // plane; cotangent smoothing does not move any (linear precision); the boundary is fixed.
        let (p, t) = grid(6, 5);
        let mut rng = SplitMix64::new(3);
        let plane = |x: f64, y: f64| 0.3 * x - 0.2 * y + 1.0;
        let p: Vec<[f64; 3]> = p
            .iter()
            .map(|v| {
                let (x, y) = (
                    v[0] + 0.2 * (rng.uniform() - 0.5),
                    v[1] + 0.2 * (rng.uniform() - 0.5),
                );
                [x, y, plane(x, y)]
            })
            .collect();
        let mesh = HalfedgeMesh::from_triangles(p.clone(), &t).unwrap();
        let u = smooth(&mesh, SmoothWeights::Uniform, 5, 0.5, None);
        for (i, (a, b)) in u.iter().zip(&p).enumerate() {
            assert!((a[2] - plane(a[0], a[1])).abs() < 1e-12);
            if mesh.is_boundary_vertex(i as u32) {
                assert_eq!(a, b);
            }
        }
        assert!(u.iter().zip(&p).any(|(a, b)| norm(sub(*a, *b)) > 1e-3));
        let c = smooth(&mesh, SmoothWeights::Cotangent, 5, 0.5, None);
        for (a, b) in c.iter().zip(&p) {
            assert!(norm(sub(*a, *b)) < 1e-12, "{a:?} {b:?}");
        }
    }

    #[test]
    fn taubin_keeps_the_volume_that_laplacian_smoothing_loses() {
        let mesh = icosphere(3, 4, 0.0);
        let (p0, t, _) = mesh.to_triangles().unwrap();
        let mut rng = SplitMix64::new(8);
        let noisy: Vec<[f64; 3]> = p0
            .iter()
            .map(|v| {
                let r = 1.0 + 0.03 * (rng.uniform() - 0.5);
                v.map(|x| x * r)
            })
            .collect();
        let mesh = HalfedgeMesh::from_triangles(noisy.clone(), &t).unwrap();
        let roughness = |p: &[[f64; 3]]| {
            let r: Vec<f64> = p.iter().map(|v| norm(*v)).collect();
            let m = r.iter().sum::<f64>() / r.len() as f64;
            // Relative to the mean radius, so that shrinking alone does not count.
            (r.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / r.len() as f64).sqrt() / m
        };
        let v0 = signed_volume(&noisy, &t);
        for weights in [SmoothWeights::Uniform, SmoothWeights::Cotangent] {
            let lap = smooth(&mesh, weights, 20, 0.5, None);
            let tau = smooth(&mesh, weights, 20, 0.5, Some(-0.53));
            let (vl, vt) = (signed_volume(&lap, &t), signed_volume(&tau, &t));
            assert!(roughness(&lap) < 0.8 * roughness(&noisy));
            assert!(roughness(&tau) < 0.5 * roughness(&noisy));
            assert!((v0 - vl) / v0 > 0.05, "{weights:?} laplacian {vl} of {v0}");
            assert!(
                ((v0 - vt) / v0).abs() < 0.3 * (v0 - vl) / v0,
                "{weights:?} taubin {vt}"
            );
        }
    }

    #[test]
    fn smoothing_does_not_depend_on_the_thread_count() {
        let mesh = icosphere(4, 1, 0.3);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| smooth(&mesh, SmoothWeights::Cotangent, 3, 0.5, Some(-0.53)))
        };
        assert_eq!(run(1), run(3));
    }
}
