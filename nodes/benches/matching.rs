//! Descriptor matching benchmarks sized like the OpenCV anchors: brute-force 2-NN + ratio on
//! 2000 × 2000 ORB-like (32-byte) and SIFT-like (128-float) descriptors, and the approximate
//! matcher on 10 000 × 10 000 clustered SIFT-like descriptors at a few `checks` budgets.
//! Compare single-threaded with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench
//! matching`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::Descriptors;
use ocellus_nodes::matching::approximate::{AnnOptions, approximate_match};
use ocellus_nodes::matching::brute_force::{MatchOptions, brute_force_match};
use ocellus_nodes::matching::{Norm, prepare};

/// A deterministic xorshift stream.
fn stream(seed: u64) -> impl FnMut() -> u64 {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    }
}

fn orb_like(n: usize, seed: u64) -> Descriptors {
    let mut next = stream(seed);
    Descriptors::Binary {
        bytes: 32,
        data: (0..n * 32).map(|_| next() as u8).collect(),
    }
}

/// SIFT-like rows: integer values 0..=255 (SIFT's range), cluster centres plus noise.
fn sift_like(n: usize, clusters: usize, seed: u64) -> Descriptors {
    let mut next = stream(seed);
    let centres: Vec<f32> = (0..clusters * 128).map(|_| (next() % 120) as f32).collect();
    let mut data = Vec::with_capacity(n * 128);
    for _ in 0..n {
        let c = (next() as usize) % clusters;
        for d in 0..128 {
            let noise = (next() % 61) as f32 - 30.0;
            data.push((centres[c * 128 + d] + noise).clamp(0.0, 255.0).round());
        }
    }
    Descriptors::Float { dim: 128, data }
}

fn brute_force(c: &mut Criterion) {
    let mut group = c.benchmark_group("match.brute_force");
    let options = MatchOptions::default();
    let (a, b) = (orb_like(2000, 1), orb_like(2000, 2));
    let (metric, q, t) = prepare(&a, &b, Norm::Auto).unwrap_or_else(|e| panic!("{e}"));
    group.bench_function("ORB 2000x2000 knn2 ratio 0.8", |bench| {
        bench.iter(|| brute_force_match(black_box(&q), black_box(&t), metric, &options, None))
    });
    let cross = MatchOptions {
        ratio: 1.0,
        cross_check: true,
        max_distance: None,
    };
    group.bench_function("ORB 2000x2000 cross-check", |bench| {
        bench.iter(|| brute_force_match(black_box(&q), black_box(&t), metric, &cross, None))
    });
    let (a, b) = (sift_like(2000, 200, 3), sift_like(2000, 200, 4));
    let (metric, q, t) = prepare(&a, &b, Norm::Auto).unwrap_or_else(|e| panic!("{e}"));
    group.bench_function("SIFT 2000x2000 knn2 ratio 0.8", |bench| {
        bench.iter(|| brute_force_match(black_box(&q), black_box(&t), metric, &options, None))
    });
    group.finish();
}

/// Noisy copies (±15) of the first `n` rows of `t`, so every query has a true match.
fn noisy_copies(t: &Descriptors, n: usize, seed: u64) -> Descriptors {
    let Descriptors::Float { dim, data } = t else {
        panic!("float descriptors expected")
    };
    let mut next = stream(seed);
    Descriptors::Float {
        dim: *dim,
        data: data[..n * dim]
            .iter()
            .map(|&v| v + (next() % 31) as f32 - 15.0)
            .collect(),
    }
}

fn approximate(c: &mut Criterion) {
    let mut group = c.benchmark_group("match.approximate");
    group.sample_size(10);
    let b = sift_like(10_000, 500, 6);
    let a = noisy_copies(&b, 10_000, 5);
    let (metric, q, t) = prepare(&a, &b, Norm::Auto).unwrap_or_else(|e| panic!("{e}"));
    let exact_options = MatchOptions {
        ratio: 1.0,
        ..MatchOptions::default()
    };
    let exact = brute_force_match(&q, &t, metric, &exact_options, None);
    for checks in [16, 32, 64, 128, 256] {
        let options = AnnOptions {
            checks,
            ..AnnOptions::default()
        };
        let recall_options = AnnOptions {
            ratio: 1.0,
            ..options
        };
        let ann = approximate_match(&q, &t, metric, &recall_options);
        let hits = exact
            .iter()
            .zip(&ann)
            .filter(|(e, a)| e.train == a.train)
            .count();
        eprintln!(
            "checks {checks}: recall of the exact nearest neighbour {:.4}",
            hits as f64 / exact.len() as f64
        );
        group.bench_function(format!("SIFT 10k x 10k checks {checks}"), |bench| {
            bench.iter(|| approximate_match(black_box(&q), black_box(&t), metric, &options))
        });
    }
    group.bench_function("SIFT 10k x 10k brute force", |bench| {
        bench.iter(|| {
            brute_force_match(
                black_box(&q),
                black_box(&t),
                metric,
                &MatchOptions::default(),
                None,
            )
        })
    });
    group.finish();
}

criterion_group!(benches, brute_force, approximate);
criterion_main!(benches);
