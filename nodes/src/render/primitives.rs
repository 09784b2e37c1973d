//! Procedural meshes for tests, fixtures and benchmarks.

use std::collections::HashMap;

use ocellus_engine::value::Mesh;

use crate::describe::brief::SplitMix64;

/// The geodesic icosphere: an icosahedron whose faces are split into four `subdivisions`
/// times (20 · 4ˢ triangles, 10 · 4ˢ + 2 vertices), every vertex on the unit sphere, then
/// displaced radially by `1 + amplitude · Σₖ sin(kₖ · v + φₖ) / 12` over twelve waves whose
/// wave vectors (≈ 6 per unit, random directions) and phases come from `seed`, so the surface
/// is not a perfect sphere and a BVH over it is not trivially balanced. Triangles are
/// counter-clockwise seen from outside; normals are area-weighted face normals, normalized.
/// `subdivisions` is clamped to 0..=10 (21 M triangles).
pub fn bumpy_icosphere(subdivisions: u32, amplitude: f32, seed: u64) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut positions: Vec<[f64; 3]> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .into_iter()
    .map(normalized)
    .collect();
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions.min(10) {
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::with_capacity(triangles.len() * 2);
        let mut next = Vec::with_capacity(triangles.len() * 4);
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<[f64; 3]>| {
            let key = (a.min(b), a.max(b));
            *midpoints.entry(key).or_insert_with(|| {
                let (p, q) = (positions[a as usize], positions[b as usize]);
                positions.push(normalized([p[0] + q[0], p[1] + q[1], p[2] + q[2]]));
                (positions.len() - 1) as u32
            })
        };
        for [a, b, c] in triangles {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        triangles = next;
    }
    let mut rng = SplitMix64::new(seed);
    let waves: Vec<([f64; 3], f64)> = (0..12)
        .map(|_| {
            let z = 2.0 * rng.uniform() - 1.0;
            let phi = 2.0 * std::f64::consts::PI * rng.uniform();
            let r = (1.0 - z * z).max(0.0).sqrt();
            let k = 6.0 * (0.5 + rng.uniform());
            (
                [k * r * phi.cos(), k * r * phi.sin(), k * z],
                2.0 * std::f64::consts::PI * rng.uniform(),
            )
        })
        .collect();
    let positions: Vec<[f32; 3]> = positions
        .iter()
        .map(|v| {
            let bump: f64 = waves
                .iter()
                .map(|(k, phase)| (k[0] * v[0] + k[1] * v[1] + k[2] * v[2] + phase).sin())
                .sum();
            let r = 1.0 + f64::from(amplitude) * bump / 12.0;
            [(v[0] * r) as f32, (v[1] * r) as f32, (v[2] * r) as f32]
        })
        .collect();
    let normals = vertex_normals(&positions, &triangles);
    Mesh {
        positions,
        triangles,
        normals: Some(normals),
        uvs: None,
        colors: None,
        tangents: None,
    }
}

fn normalized(p: [f64; 3]) -> [f64; 3] {
    let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
    [p[0] / n, p[1] / n, p[2] / n]
}

/// Area-weighted vertex normals (the sum of adjacent faces' cross products, normalized; +z for
/// a vertex without area).
pub fn vertex_normals(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> Vec<[f32; 3]> {
    let mut acc = vec![[0.0f64; 3]; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| positions[i as usize].map(f64::from));
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        for &i in t {
            for k in 0..3 {
                acc[i as usize][k] += n[k];
            }
        }
    }
    acc.into_iter()
        .map(|n| {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len > 0.0 {
                [
                    (n[0] / len) as f32,
                    (n[1] / len) as f32,
                    (n[2] / len) as f32,
                ]
            } else {
                [0.0, 0.0, 1.0]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icosphere_counts_closure_and_orientation() {
        for s in 0..4 {
            let m = bumpy_icosphere(s, 0.0, 1);
            assert_eq!(m.triangles.len(), 20 * 4usize.pow(s));
            assert_eq!(m.positions.len(), 10 * 4usize.pow(s) + 2);
            // Closed 2-manifold: every edge is used once in each direction.
            let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
            for t in &m.triangles {
                for k in 0..3 {
                    *edges.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
                }
            }
            for (&(a, b), &n) in &edges {
                assert_eq!(n, 1);
                assert_eq!(edges.get(&(b, a)), Some(&1));
            }
            // Unit radius without bumps; outward (CCW from outside) faces: the signed volume
            // is positive and approaches 4π/3.
            assert!(m.positions.iter().all(|p| {
                ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 1.0).abs() < 1e-6
            }));
            let volume: f64 = m
                .triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| m.positions[i as usize].map(f64::from));
                    (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                        + a[2] * (b[0] * c[1] - b[1] * c[0]))
                        / 6.0
                })
                .sum();
            // An inscribed polyhedron: below the ball's volume, approaching it as 4⁻ˢ.
            let ball = 4.0 * std::f64::consts::PI / 3.0;
            assert!(volume > 0.0 && volume < ball);
            if s == 3 {
                assert!(volume > 0.98 * ball, "{volume} vs {ball}");
            }
        }
    }

    #[test]
    fn bumps_stay_within_the_amplitude_and_normals_are_unit() {
        let m = bumpy_icosphere(3, 0.1, 7);
        let radii: Vec<f32> = m
            .positions
            .iter()
            .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
            .collect();
        assert!(radii.iter().all(|r| (r - 1.0).abs() <= 0.1 + 1e-6));
        let spread = radii.iter().cloned().fold(f32::NEG_INFINITY, f32::max)
            - radii.iter().cloned().fold(f32::INFINITY, f32::min);
        assert!(spread > 0.02, "the surface is bumpy: {spread}");
        for (p, n) in m.positions.iter().zip(m.normals.as_ref().unwrap()) {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-5);
            assert!(p[0] * n[0] + p[1] * n[1] + p[2] * n[2] > 0.0, "outward");
        }
        assert_eq!(bumpy_icosphere(3, 0.1, 7), m, "deterministic");
        assert_ne!(bumpy_icosphere(3, 0.1, 8), m, "seeded");
    }
}
