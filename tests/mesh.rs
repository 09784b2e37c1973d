//! The mesh example: `graphs/mesh.ron` takes raw points (no normals) through normal estimation,
//! screened Poisson reconstruction, quadric simplification and a rasterized view. Its input,
//! `graphs/data/mesh_points.ply`, is reproduced by the generator below.
//!
//! The shape is a rounded box (half extents 0.6 × 0.3 × 0.35, edge radius 0.1: the box's
//! offset surface, flat faces joined by quarter cylinders and sphere octants) with a dome (a
//! sphere of radius 0.28 centred on its top face) — known signed distance: the minimum of the
//! two. 12 000 points are drawn uniformly by area on the union's surface (points of one part
//! inside the other rejected) and displaced along the true normal by seeded Gaussian noise
//! (σ = 0.002). The normals are not stored: the graph estimates and orients them.
//!
//! To regenerate the fixture after changing the generator, run this test with
//! `OCELLUS_WRITE_FIXTURES=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::collections::HashMap;
use std::f64::consts::{FRAC_PI_2, PI};
use std::sync::Arc;

use common::{Rng, length, output, root, sample_mesh, temp_dir};
use ocellus_engine::emit::emit_value;
use ocellus_engine::value::{Metrics, PointCloud, Value};

const POINTS: usize = 12_000;
const NOISE: f64 = 0.002;
const HALF: [f64; 3] = [0.6, 0.3, 0.35];
const EDGE: f64 = 0.1;
const DOME_CENTRE: [f64; 3] = [0.0, HALF[1] + EDGE, 0.0];
const DOME: f64 = 0.28;

fn rounded_box(p: [f64; 3]) -> f64 {
    let q = [0, 1, 2].map(|k| p[k].abs() - HALF[k]);
    let outside = length(q.map(|v| v.max(0.0)));
    outside + q[0].max(q[1]).max(q[2]).min(0.0) - EDGE
}

fn dome(p: [f64; 3]) -> f64 {
    length([0, 1, 2].map(|k| p[k] - DOME_CENTRE[k])) - DOME
}

/// Signed distance to the union (exact outside and on the surface away from the crease).
fn shape(p: [f64; 3]) -> f64 {
    rounded_box(p).min(dome(p))
}

/// A uniform point on the rounded box with its outward normal.
fn on_rounded_box(rng: &mut Rng) -> ([f64; 3], [f64; 3]) {
    let b = HALF;
    let faces = [0, 1, 2].map(|a| 2.0 * 4.0 * b[(a + 1) % 3] * b[(a + 2) % 3]);
    let edges = [0, 1, 2].map(|a| 4.0 * 2.0 * b[a] * FRAC_PI_2 * EDGE);
    let corners = 4.0 * PI * EDGE * EDGE;
    let total = faces.iter().sum::<f64>() + edges.iter().sum::<f64>() + corners;
    let sign = |rng: &mut Rng| if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
    let mut r = rng.uniform() * total;
    for a in 0..3 {
        if r < faces[a] {
            // The face perpendicular to axis a.
            let (i, j) = ((a + 1) % 3, (a + 2) % 3);
            let s = sign(rng);
            let mut p = [0.0; 3];
            p[a] = s * (b[a] + EDGE);
            p[i] = b[i] * (2.0 * rng.uniform() - 1.0);
            p[j] = b[j] * (2.0 * rng.uniform() - 1.0);
            let mut n = [0.0; 3];
            n[a] = s;
            return (p, n);
        }
        r -= faces[a];
    }
    for a in 0..3 {
        if r < edges[a] {
            // A quarter cylinder along axis a.
            let (i, j) = ((a + 1) % 3, (a + 2) % 3);
            let (si, sj) = (sign(rng), sign(rng));
            let t = FRAC_PI_2 * rng.uniform();
            let mut n = [0.0; 3];
            n[i] = si * t.cos();
            n[j] = sj * t.sin();
            let mut p = [0.0; 3];
            p[a] = b[a] * (2.0 * rng.uniform() - 1.0);
            p[i] = si * b[i] + EDGE * n[i];
            p[j] = sj * b[j] + EDGE * n[j];
            return (p, n);
        }
        r -= edges[a];
    }
    // A sphere octant at a corner: the octant is the sign pattern of the direction.
    let n = rng.direction();
    let p = [0, 1, 2].map(|k| b[k].copysign(n[k]) + EDGE * n[k]);
    (p, n)
}

/// `n` points uniform on the union's surface with their true normals, displaced by `noise`.
fn sample_shape(n: usize, noise: f64, seed: u64) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let b = HALF;
    let box_area = [0, 1, 2]
        .map(|a| 8.0 * b[(a + 1) % 3] * b[(a + 2) % 3] + 8.0 * b[a] * FRAC_PI_2 * EDGE)
        .iter()
        .sum::<f64>()
        + 4.0 * PI * EDGE * EDGE;
    let dome_area = 4.0 * PI * DOME * DOME;
    let mut rng = Rng(seed);
    let (mut points, mut normals) = (Vec::with_capacity(n), Vec::with_capacity(n));
    while points.len() < n {
        let (p, nrm) = if rng.uniform() * (box_area + dome_area) < box_area {
            let (p, nrm) = on_rounded_box(&mut rng);
            if dome(p) < 0.0 {
                continue;
            }
            (p, nrm)
        } else {
            let nrm = rng.direction();
            let p = [0, 1, 2].map(|k| DOME_CENTRE[k] + DOME * nrm[k]);
            if rounded_box(p) < 0.0 {
                continue;
            }
            (p, nrm)
        };
        let e = noise * rng.normal();
        points.push([0, 1, 2].map(|a| p[a] + e * nrm[a]));
        normals.push(nrm);
    }
    (points, normals)
}

fn fixture() -> PointCloud {
    let (points, _) = sample_shape(POINTS, NOISE, 2027);
    PointCloud {
        positions: points.iter().map(|p| p.map(|v| v as f32)).collect(),
        colors: None,
        normals: None,
    }
}

#[test]
fn the_generator_samples_the_surface_uniformly() {
    // On the surface (noise 0), every sample has zero signed distance and its normal is the
    // distance gradient; the share of samples on the dome's cap above the box is its share of
    // the area (a cap of height h has area 2πRh).
    let (points, normals) = sample_shape(20_000, 0.0, 5);
    let h = 1e-6;
    for (p, n) in points.iter().zip(&normals) {
        assert!(shape(*p).abs() < 1e-12, "{p:?}: {}", shape(*p));
        if rounded_box(*p).abs() < 1e-4 && dome(*p).abs() < 1e-4 {
            continue; // on the crease the distance has no gradient
        }
        let g = [0, 1, 2].map(|k| {
            let (mut a, mut b) = (*p, *p);
            a[k] += h;
            b[k] -= h;
            (shape(a) - shape(b)) / (2.0 * h)
        });
        let d = [0, 1, 2].map(|k| g[k] - n[k]);
        assert!(length(d) < 1e-4, "{p:?}: gradient {g:?} vs normal {n:?}");
    }
    let top = HALF[1] + EDGE;
    let cap_area = 2.0 * PI * DOME * DOME; // the upper hemisphere, above the top face
    let on_cap = points.iter().filter(|p| p[1] > top + 1e-9).count() as f64;
    let b = HALF;
    let box_area: f64 = [0, 1, 2]
        .map(|a| 8.0 * b[(a + 1) % 3] * b[(a + 2) % 3] + 8.0 * b[a] * FRAC_PI_2 * EDGE)
        .iter()
        .sum::<f64>()
        + 4.0 * PI * EDGE * EDGE
        - PI * DOME * DOME; // the disc the dome covers on the top face
    let expected = cap_area / (cap_area + box_area);
    let share = on_cap / points.len() as f64;
    assert!((share - expected).abs() < 0.01, "{share} vs {expected}");
}

#[test]
fn mesh_fixture_is_reproducible() {
    let dir = temp_dir("mesh-fixture");
    let files = emit_value(&dir, "mesh_points", &Value::PointCloud(Arc::new(fixture()))).unwrap();
    let generated = std::fs::read(&files[0]).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    let path = root().join("graphs/data/mesh_points.ply");
    if std::env::var_os("OCELLUS_WRITE_FIXTURES").is_some() {
        std::fs::write(&path, &generated).unwrap();
    }
    let stored = std::fs::read(&path).unwrap();
    assert!(stored.len() < 400_000, "{} bytes", stored.len());
    assert!(
        stored == generated,
        "graphs/data/mesh_points.ply differs from the generator"
    );
}

#[test]
fn mesh_graph_reconstructs_simplifies_and_renders_the_shape() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let report =
        ocellus_engine::testing::run_graph(&registry, root().join("graphs/mesh.ron"), 2, &[])
            .unwrap();
    let Value::Mesh(mesh) = output(&report, "mesh") else {
        panic!("mesh is not a Mesh")
    };
    let Value::Metrics(simplify) = output(&report, "simplify") else {
        panic!("simplify is not Metrics")
    };
    let simplify: &Metrics = &simplify;
    assert!(mesh.triangles.len() <= 4000, "{}", mesh.triangles.len());
    assert!(mesh.triangles.len() >= 3900, "{}", mesh.triangles.len());
    assert_eq!(simplify["output_triangles"], mesh.triangles.len() as f64);
    // Closed, consistently oriented, genus 0 after simplification.
    let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
        }
    }
    assert!(directed.values().all(|&c| c == 1));
    assert!(
        directed
            .keys()
            .all(|&(a, b)| directed.contains_key(&(b, a)))
    );
    let euler =
        mesh.positions.len() as i64 - directed.len() as i64 / 2 + mesh.triangles.len() as i64;
    assert_eq!(euler, 2, "Euler characteristic of a sphere-like surface");
    // Outward: positive volume, close to the true one (box offset + dome cap beyond it).
    let volume: f64 = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.positions[i as usize].map(f64::from));
            (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0]))
                / 6.0
        })
        .sum();
    let b = HALF;
    let r = EDGE;
    let box_volume = 8.0 * b[0] * b[1] * b[2]
        + 2.0 * r * 4.0 * (b[0] * b[1] + b[1] * b[2] + b[2] * b[0])
        + PI * r * r * 2.0 * (b[0] + b[1] + b[2])
        + 4.0 / 3.0 * PI * r * r * r;
    let dome_volume = 2.0 / 3.0 * PI * DOME * DOME * DOME; // the half above the top face
    let truth = box_volume + dome_volume;
    assert!((volume / truth - 1.0).abs() < 0.02, "{volume} vs {truth}");
    // Accuracy: mesh samples lie on the true surface (cell at depth 7 ≈ 0.012).
    let on_mesh = sample_mesh(&mesh, 50_000, 3);
    let distances: Vec<f64> = on_mesh.iter().map(|p| shape(*p).abs()).collect();
    let mean = distances.iter().sum::<f64>() / distances.len() as f64;
    let max = distances.iter().copied().fold(0.0, f64::max);
    eprintln!("mesh graph: mean |sdf| {mean}, max {max}, {simplify:?}");
    assert!(mean < 0.003 && max < 0.03, "mean {mean} max {max}");
    // The view: the whole shape inside the frame (the border is background), a lit side
    // brighter than the shadowed one, and the shape covering a sensible share of the image.
    let Value::Image(image) = output(&report, "view") else {
        panic!("view is not an Image")
    };
    let (w, h) = (image.width(), image.height());
    assert_eq!((w, h), (320, 240));
    let pixels = image.as_f32().expect("an f32 colour image");
    let luminance: Vec<f32> = pixels.chunks(3).map(|c| c[0] + c[1] + c[2]).collect();
    let covered = |i: usize| luminance[i] > 0.0;
    let border = (0..w)
        .flat_map(|x| [x, (h - 1) * w + x])
        .chain((0..h).flat_map(|y| [y * w, y * w + w - 1]))
        .filter(|&i| covered(i))
        .count();
    assert_eq!(border, 0, "the shape touches the image border");
    let share = (0..w * h).filter(|&i| covered(i)).count() as f64 / (w * h) as f64;
    assert!((0.1..0.7).contains(&share), "covered share {share}");
    // Pixels inside the silhouette (all four neighbours covered, so no partial MSAA coverage):
    // the top face, lit at 40° from its normal, is several times brighter than the +x side,
    // which faces away from the key light and gets the ambient term only.
    let mut inside: Vec<f32> = (1..h - 1)
        .flat_map(|y| (1..w - 1).map(move |x| y * w + x))
        .filter(|&i| [i, i - 1, i + 1, i - w, i + w].into_iter().all(covered))
        .map(|i| luminance[i])
        .collect();
    inside.sort_by(f32::total_cmp);
    let (dim, lit) = (inside[inside.len() / 20], inside[inside.len() * 19 / 20]);
    assert!(lit > 3.0 * dim, "5th percentile {dim}, 95th {lit}");
}
