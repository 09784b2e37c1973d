//! Calibrated minimal-solver benchmarks: five-point essential matrix, Lambda Twist P3P, EPnP
//! (n = 100, Gauss–Newton included, no LM) and DLT triangulation of 1000 points. Compare
//! single-threaded with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench
//! geometry_solvers` against OpenCV with `cv2.setNumThreads(1)` (`findEssentialMat` on 5
//! points, `solvePnP` with `SOLVEPNP_P3P` / `SOLVEPNP_EPNP`, `triangulatePoints`).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use ocellus_nodes::geometry::essential::essential_five_point;
use ocellus_nodes::geometry::pnp::{epnp, p3p};
use ocellus_nodes::geometry::pose_util::Intrinsics;
use ocellus_nodes::geometry::triangulate::{TriangulationMethod, View, triangulate_points};

fn lcg(seed: &mut u64) -> f64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

fn k() -> Intrinsics {
    match Intrinsics::new(800.0, 800.0, 320.0, 240.0) {
        Ok(k) => k,
        Err(e) => panic!("{e}"),
    }
}

/// Camera 2 pose and `n` world points in front of camera 1 (identity).
fn scene(n: usize) -> (Matrix3<f64>, Vector3<f64>, Vec<Vector3<f64>>) {
    let mut s = 42;
    let r = *Rotation3::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)).matrix();
    let t = Vector3::new(-1.0, 0.1, 0.2);
    let pts = (0..n)
        .map(|_| {
            Vector3::new(
                2.0 * lcg(&mut s),
                1.5 * lcg(&mut s),
                6.0 + 2.0 * lcg(&mut s),
            )
        })
        .collect();
    (r, t, pts)
}

fn five_point(c: &mut Criterion) {
    let (r, t, pts) = scene(5);
    let x1: [Vector2<f64>; 5] =
        std::array::from_fn(|i| Vector2::new(pts[i].x / pts[i].z, pts[i].y / pts[i].z));
    let x2: [Vector2<f64>; 5] = std::array::from_fn(|i| {
        let q = r * pts[i] + t;
        Vector2::new(q.x / q.z, q.y / q.z)
    });
    c.bench_function("five-point essential", |b| {
        b.iter(|| essential_five_point(black_box(&x1), black_box(&x2)))
    });
}

fn p3p_bench(c: &mut Criterion) {
    let (r, t, pts) = scene(3);
    let bearings: [Vector3<f64>; 3] = std::array::from_fn(|i| r * pts[i] + t);
    let world: [Vector3<f64>; 3] = std::array::from_fn(|i| pts[i]);
    c.bench_function("p3p lambda twist", |b| {
        b.iter(|| p3p(black_box(&bearings), black_box(&world)))
    });
}

fn epnp_bench(c: &mut Criterion) {
    let (r, t, pts) = scene(100);
    let kk = k();
    let px: Vec<[f64; 2]> = pts.iter().map(|p| kk.project(&(r * p + t))).collect();
    let w: Vec<[f64; 3]> = pts.iter().map(|p| [p.x, p.y, p.z]).collect();
    c.bench_function("epnp n=100", |b| {
        b.iter(|| epnp(black_box(&kk), black_box(&px), black_box(&w)))
    });
}

fn triangulate_bench(c: &mut Criterion) {
    let (r, t, pts) = scene(1000);
    let kk = k();
    let v1 = View {
        r: Matrix3::identity(),
        t: Vector3::zeros(),
        k: kk,
    };
    let v2 = View { r, t, k: kk };
    let p1: Vec<[f64; 2]> = pts.iter().map(|p| kk.project(p)).collect();
    let p2: Vec<[f64; 2]> = pts.iter().map(|p| kk.project(&(r * p + t))).collect();
    let mut group = c.benchmark_group("triangulate 1000");
    for (name, m) in [
        ("dlt", TriangulationMethod::Dlt),
        ("midpoint", TriangulationMethod::Midpoint),
        ("optimal", TriangulationMethod::Optimal),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| triangulate_points(&v1, &v2, black_box(&p1), black_box(&p2), m, 1.0))
        });
    }
    group.finish();
}

criterion_group!(
    benches,
    five_point,
    p3p_bench,
    epnp_bench,
    triangulate_bench
);
criterion_main!(benches);
