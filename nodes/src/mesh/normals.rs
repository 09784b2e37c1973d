//! Vertex normals of a triangle mesh: `mesh.normals`.
//!
//! [`vertex_normals`] sums the face normals around each vertex and normalizes:
//! - area weighting: each face adds its cross product `(b − a) × (c − a)`, i.e. twice its area
//!   times its unit normal (the classic Gouraud average with area weights);
//! - angle weighting: each face adds its unit normal times its interior angle at the vertex
//!   (Thürmer & Wüthrich, "Computing vertex normals from polygonal facets", JGT 1998), which does
//!   not depend on how a flat region is triangulated.
//!
//! Faces are visited in index order and each vertex sums in that order, so the result is the
//! same for any thread count. A vertex with no face or only degenerate faces (zero sum) gets no
//! direction; it is reported and given `+z`.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};
use ocellus_engine::{param_enum, params};

use super::halfedge::{MeshError, mesh_input, mesh_positions};

param_enum! {
    /// How `mesh.normals` weights the faces around a vertex.
    pub enum NormalWeighting {
        /// By face area.
        Area = "area",
        /// By the face's interior angle at the vertex.
        Angle = "angle",
    }
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// The angle between `u` and `v` (robust near 0 and π: `atan2(|u × v|, u · v)`).
pub(crate) fn angle(u: [f64; 3], v: [f64; 3]) -> f64 {
    norm(cross(u, v)).atan2(dot(u, v))
}

/// Unit vertex normals and the number of vertices that had no direction (given `+z`).
/// Triangles must index `positions` (checked by the caller).
pub fn vertex_normals(
    positions: &[[f64; 3]],
    triangles: &[[u32; 3]],
    weighting: NormalWeighting,
) -> (Vec<[f64; 3]>, usize) {
    let mut acc = vec![[0.0f64; 3]; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| positions[i as usize]);
        let n = cross(sub(b, a), sub(c, a));
        match weighting {
            NormalWeighting::Area => {
                for &i in t {
                    let s = &mut acc[i as usize];
                    for k in 0..3 {
                        s[k] += n[k];
                    }
                }
            }
            NormalWeighting::Angle => {
                let len = norm(n);
                if len == 0.0 || !len.is_finite() {
                    continue;
                }
                let unit = n.map(|v| v / len);
                let corners = [(a, b, c), (b, c, a), (c, a, b)];
                for (&i, (p, q, r)) in t.iter().zip(corners) {
                    let w = angle(sub(q, p), sub(r, p));
                    let s = &mut acc[i as usize];
                    for k in 0..3 {
                        s[k] += w * unit[k];
                    }
                }
            }
        }
    }
    let mut missing = 0;
    let normals = acc
        .into_iter()
        .map(|n| {
            let len = norm(n);
            if len > 0.0 && len.is_finite() {
                n.map(|v| v / len)
            } else {
                missing += 1;
                [0.0, 0.0, 1.0]
            }
        })
        .collect();
    (normals, missing)
}

params! {
    /// Parameters of `mesh.normals`.
    pub struct NormalsParams {
        /// Face weights: "area" (face area) or "angle" (interior angle at the vertex).
        /// Default "angle".
        weighting: NormalWeighting = NormalWeighting::Angle,
    }
}

/// Vertex normals (`mesh.normals`). See [`vertex_normals`].
#[derive(Debug, Clone, PartialEq)]
pub struct Normals {
    weighting: NormalWeighting,
}

impl Op for Normals {
    type Params = NormalsParams;
    const ID: &'static str = "mesh.normals";
    const SUMMARY: &'static str =
        "Computes unit vertex normals of a triangle mesh, area- or angle-weighted.";
    const DOC: &'static str = r#"
Each vertex normal is the normalized sum of the normals of the triangles around it:
- "area": each triangle adds (b − a) × (c − a), its unit normal times twice its area;
- "angle": each triangle adds its unit normal times its interior angle at the vertex
  (Thürmer & Wüthrich, "Computing vertex normals from polygonal facets", JGT 1998), which
  does not change when a flat region is triangulated differently.

Triangles are taken counter-clockwise, so normals point to the side from which the corners
turn counter-clockwise. A vertex without faces (or only degenerate ones) gets +z and is
counted in the metric `vertices_without_normal`. Positions, triangles, uvs and colors pass
through unchanged; tangents, which belong to the old normals, are dropped (rerun
`mesh.tangents`). No manifold structure is needed.

Metrics: `vertices`, `triangles`, `vertices_without_normal`.

Example:
    "n": (op: "mesh.normals", inputs: { "mesh": "bunny.mesh" }, params: (weighting: "angle")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("mesh", PortType::Mesh, "A triangle mesh.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("mesh", PortType::Mesh, "The mesh with unit vertex normals."),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "vertices, triangles, vertices_without_normal.",
            ),
        ]
    }

    fn new(p: NormalsParams) -> Result<Self, String> {
        Ok(Normals {
            weighting: p.weighting,
        })
    }
}

impl Operator for Normals {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = mesh_input(inputs, "mesh")?;
        let positions = mesh_positions(mesh).map_err(|e| e.at("mesh"))?;
        if mesh.triangles.is_empty() {
            return Err(MeshError::Empty.at("mesh"));
        }
        let (normals, missing) = vertex_normals(&positions, &mesh.triangles, self.weighting);
        let out = Mesh {
            normals: Some(normals.iter().map(|n| n.map(|v| v as f32)).collect()),
            // Tangents are orthogonal to the old normals; `mesh.tangents` recomputes them.
            tangents: None,
            ..Mesh::clone(mesh)
        };
        let mut m = Metrics::new();
        m.insert("vertices".into(), positions.len() as f64);
        m.insert("triangles".into(), mesh.triangles.len() as f64);
        m.insert("vertices_without_normal".into(), missing as f64);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(out)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::halfedge::tests::{cube_triangles, grid};

    #[test]
    fn cube_corner_normals_point_along_the_diagonal_with_angle_weights() {
        let (p, t) = cube_triangles();
        let (n, missing) = vertex_normals(&p, &t, NormalWeighting::Angle);
        assert_eq!(missing, 0);
        // Each corner sees three faces with a total angle of π/2 each, however they are
        // split: the normal is the corner's direction.
        for (v, nv) in p.iter().zip(&n) {
            let want = v.map(|x| x / 3f64.sqrt());
            for k in 0..3 {
                assert!((nv[k] - want[k]).abs() < 1e-12, "{v:?} {nv:?}");
            }
        }
        // Area weights depend on how the faces are split (corner 1 lies in one triangle of
        // some faces and two of others): compare with the sum written out.
        let (a, _) = vertex_normals(&p, &t, NormalWeighting::Area);
        let mut want = [0.0; 3];
        for f in t.iter().filter(|f| f.contains(&1)) {
            let [x, y, z] = f.map(|i| p[i as usize]);
            let c = cross(sub(y, x), sub(z, x));
            for k in 0..3 {
                want[k] += c[k];
            }
        }
        let len = norm(want);
        for k in 0..3 {
            assert!((a[1][k] - want[k] / len).abs() < 1e-12);
        }
    }

    #[test]
    fn flat_grid_is_plus_z_and_isolated_vertices_are_counted() {
        let (mut p, t) = grid(3, 2);
        p.push([9.0, 9.0, 9.0]);
        for w in [NormalWeighting::Area, NormalWeighting::Angle] {
            let (n, missing) = vertex_normals(&p, &t, w);
            assert_eq!(missing, 1);
            assert!(n.iter().all(|v| *v == [0.0, 0.0, 1.0]));
        }
        // Reversing the triangles reverses the normals.
        let rev: Vec<[u32; 3]> = t.iter().map(|f| [f[0], f[2], f[1]]).collect();
        let (n, _) = vertex_normals(&p, &rev, NormalWeighting::Angle);
        assert!(n[..p.len() - 1].iter().all(|v| *v == [0.0, 0.0, -1.0]));
    }

    #[test]
    fn angle_weights_ignore_the_triangulation_of_a_flat_fan() {
        // A vertex at a right-angled fold: the flat side (normal +z) as one triangle or as
        // three, the other side (normal +y) one triangle. The angles at vertex 0 sum to π/2
        // on each side either way, so the normal is the same.
        let p = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.9, 0.1, 0.0],
            [2.0, 2.0, 0.0],
        ];
        let coarse = [[0, 1, 2], [0, 3, 1]];
        let fine = [[0, 1, 4], [0, 4, 5], [0, 5, 2], [0, 3, 1]];
        assert_ne!(
            vertex_normals(&p, &coarse, NormalWeighting::Area).0[0],
            vertex_normals(&p, &fine, NormalWeighting::Area).0[0]
        );
        let (a, _) = vertex_normals(&p, &coarse, NormalWeighting::Angle);
        let (b, _) = vertex_normals(&p, &fine, NormalWeighting::Angle);
        for k in 0..3 {
            assert!((a[0][k] - b[0][k]).abs() < 1e-12);
        }
        // Two faces at a right angle with π/2 each: the bisector.
        let s = 0.5f64.sqrt();
        assert!(
            a[0][0].abs() < 1e-12 && (a[0][1] - s).abs() < 1e-12 && (a[0][2] - s).abs() < 1e-12
        );
    }
}
