//! The Poisson reconstruction example: its input, `graphs/data/poisson_points.ply`, is
//! reproduced by the generator below, and `graphs/poisson.ron` reconstructs the shape from it.
//!
//! The shape is a union of three primitives with a known signed distance (the minimum of
//! theirs): a torus around the z axis (ring radius 0.6, tube radius 0.2), a sphere (centre
//! (0.6, 0, 0.2), radius 0.3) bulging from the tube, and a capsule (segment (0, ±0.8, 0), radius
//! 0.1) across the hole, which splits it in two: a closed surface of genus 2. 30 000 points are
//! drawn uniformly by area on the union's surface (each primitive by its area, points inside
//! another primitive rejected), with the primitive's exact outward normal, and displaced along
//! the normal by seeded Gaussian noise (σ = 0.002, an eighth of a cell at depth 7).
//!
//! To regenerate the fixture after changing the generator, run this test with
//! `OCELLUS_WRITE_FIXTURES=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::collections::HashMap;
use std::f64::consts::{PI, TAU};
use std::sync::Arc;

use common::{Rng, length, root, sample_mesh, temp_dir};
use ocellus_engine::emit::emit_value;
use ocellus_engine::value::{Metrics, PointCloud, Value};

const POINTS: usize = 30_000;
const NOISE: f64 = 0.002;
const RING: f64 = 0.6;
const TUBE: f64 = 0.2;
const BALL_CENTRE: [f64; 3] = [0.6, 0.0, 0.2];
const BALL: f64 = 0.3;
const BAR_HALF: f64 = 0.8;
const BAR: f64 = 0.1;

fn torus(p: [f64; 3]) -> f64 {
    length([(p[0] * p[0] + p[1] * p[1]).sqrt() - RING, p[2], 0.0]) - TUBE
}

fn ball(p: [f64; 3]) -> f64 {
    length([0, 1, 2].map(|a| p[a] - BALL_CENTRE[a])) - BALL
}

fn bar(p: [f64; 3]) -> f64 {
    let y = p[1].clamp(-BAR_HALF, BAR_HALF);
    length([p[0], p[1] - y, p[2]]) - BAR
}

/// Signed distance to the shape (exact outside; inside, a bound).
fn shape(p: [f64; 3]) -> f64 {
    torus(p).min(ball(p)).min(bar(p))
}

/// A uniform point on primitive `k`'s surface with its outward normal.
fn on_primitive(k: usize, rng: &mut Rng) -> ([f64; 3], [f64; 3]) {
    match k {
        0 => loop {
            let (u, v) = (TAU * rng.uniform(), TAU * rng.uniform());
            if rng.uniform() * (RING + TUBE) <= RING + TUBE * v.cos() {
                let n = [v.cos() * u.cos(), v.cos() * u.sin(), v.sin()];
                let r = RING + TUBE * v.cos();
                return ([r * u.cos(), r * u.sin(), TUBE * v.sin()], n);
            }
        },
        1 => {
            let n = rng.direction();
            ([0, 1, 2].map(|a| BALL_CENTRE[a] + BALL * n[a]), n)
        }
        _ => {
            let side = TAU * BAR * 2.0 * BAR_HALF;
            let caps = 4.0 * PI * BAR * BAR;
            if rng.uniform() * (side + caps) < side {
                let (y, t) = (BAR_HALF * (2.0 * rng.uniform() - 1.0), TAU * rng.uniform());
                let n = [t.cos(), 0.0, t.sin()];
                ([BAR * n[0], y, BAR * n[2]], n)
            } else {
                let n = rng.direction();
                let y = if n[1] >= 0.0 { BAR_HALF } else { -BAR_HALF };
                ([BAR * n[0], y + BAR * n[1], BAR * n[2]], n)
            }
        }
    }
}

/// `n` points uniform on the union's surface, with normals; displaced by `noise` along them.
fn sample_shape(n: usize, noise: f64, seed: u64) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let areas = [
        4.0 * PI * PI * RING * TUBE,
        4.0 * PI * BALL * BALL,
        TAU * BAR * 2.0 * BAR_HALF + 4.0 * PI * BAR * BAR,
    ];
    let total: f64 = areas.iter().sum();
    let sdf: [fn([f64; 3]) -> f64; 3] = [torus, ball, bar];
    let mut rng = Rng(seed);
    let (mut points, mut normals) = (Vec::with_capacity(n), Vec::with_capacity(n));
    while points.len() < n {
        let r = rng.uniform() * total;
        let k = if r < areas[0] {
            0
        } else if r < areas[0] + areas[1] {
            1
        } else {
            2
        };
        let (p, nrm) = on_primitive(k, &mut rng);
        if (0..3).any(|j| j != k && sdf[j](p) < 0.0) {
            continue;
        }
        let e = noise * rng.normal();
        points.push([0, 1, 2].map(|a| p[a] + e * nrm[a]));
        normals.push(nrm);
    }
    (points, normals)
}

fn fixture() -> PointCloud {
    let (points, normals) = sample_shape(POINTS, NOISE, 2026);
    PointCloud {
        positions: points.iter().map(|p| p.map(|v| v as f32)).collect(),
        colors: None,
        normals: Some(normals.iter().map(|p| p.map(|v| v as f32)).collect()),
    }
}

#[test]
fn poisson_fixture_is_reproducible() {
    let dir = temp_dir("poisson-fixture");
    let files = emit_value(
        &dir,
        "poisson_points",
        &Value::PointCloud(Arc::new(fixture())),
    )
    .unwrap();
    let generated = std::fs::read(&files[0]).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    let path = root().join("graphs/data/poisson_points.ply");
    if std::env::var_os("OCELLUS_WRITE_FIXTURES").is_some() {
        std::fs::write(&path, &generated).unwrap();
    }
    let stored = std::fs::read(&path).unwrap();
    assert!(stored.len() < 1_000_000, "{} bytes", stored.len());
    assert!(
        stored == generated,
        "graphs/data/poisson_points.ply differs from the generator"
    );
}

#[test]
fn poisson_graph_reconstructs_the_shape() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let report =
        ocellus_engine::testing::run_graph(&registry, root().join("graphs/poisson.ron"), 2, &[])
            .unwrap();
    let output = |name: &str| {
        report
            .outputs
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.clone())
            .unwrap()
    };
    let Value::Mesh(mesh) = output("mesh") else {
        panic!("mesh is not a Mesh")
    };
    let Value::Metrics(m) = output("metrics") else {
        panic!("metrics is not Metrics")
    };
    let m: &Metrics = &m;
    assert_eq!(m["triangles"], mesh.triangles.len() as f64);
    // Closed and consistently oriented: every directed edge once, its reverse too; genus 2.
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
    assert_eq!(euler, -2, "Euler characteristic of a genus-2 surface");
    // Accuracy against the true surface, both ways (cell: 2.2 · 1.1 / 128 ≈ 0.019).
    let on_mesh = sample_mesh(&mesh, 200_000, 1);
    let to_truth = on_mesh.iter().map(|p| shape(*p).abs()).sum::<f64>() / on_mesh.len() as f64;
    let (truth, _) = sample_shape(3000, 0.0, 7);
    let mut grid: HashMap<[i64; 3], Vec<[f64; 3]>> = HashMap::new();
    let cell = 0.02;
    for p in &on_mesh {
        grid.entry(p.map(|v| (v / cell).floor() as i64))
            .or_default()
            .push(*p);
    }
    let to_mesh = truth
        .iter()
        .map(|p| {
            let c = p.map(|v| (v / cell).floor() as i64);
            let mut best = f64::INFINITY;
            for dz in -2..=2 {
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        for q in grid
                            .get(&[c[0] + dx, c[1] + dy, c[2] + dz])
                            .into_iter()
                            .flatten()
                        {
                            best = best.min(length([0, 1, 2].map(|a| p[a] - q[a])));
                        }
                    }
                }
            }
            best
        })
        .sum::<f64>()
        / truth.len() as f64;
    eprintln!("poisson graph: mesh→truth {to_truth}, truth→mesh {to_mesh}, {m:?}");
    assert!(to_truth < 0.003 && to_mesh < 0.004, "{to_truth} {to_mesh}");
}
