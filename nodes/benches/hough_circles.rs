//! `detect.hough_circles` benchmark: a 1920×1080 gray u8 image with ten antialiased discs
//! (radii 31–147 px, sub-pixel centres) on a noisy background. Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench hough_circles` against
//! `cv2.HoughCircles(cv2.GaussianBlur(img, (0, 0), 1), cv2.HOUGH_GRADIENT, dp, 20, param1=100,
//! param2=30, minRadius, maxRadius)` on the same image.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_nodes::detect::hough_circles::{CircleOptions, hough_circles};

/// Centres and radii (px) of the discs.
const DISCS: [(f64, f64, f64); 10] = [
    (473.697, 843.604, 31.134),
    (262.454, 481.243, 95.681),
    (366.092, 752.397, 82.277),
    (759.811, 556.748, 34.777),
    (1112.595, 758.344, 75.982),
    (609.909, 116.773, 110.508),
    (634.035, 395.486, 146.550),
    (1099.510, 517.101, 135.922),
    (1393.343, 751.607, 58.761),
    (1558.129, 693.417, 48.433),
];

/// Discs of level 190 on 60, 8×8 supersampled within a pixel of their boundary, plus uniform
/// noise in ±10 from a fixed seed.
fn scene(width: usize, height: usize) -> Vec<u8> {
    let mut state = 7u64;
    let mut noise = move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64 * 20.0 - 10.0
    };
    let mut img = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            let (fx, fy) = (x as f64, y as f64);
            let mut cover = 0.0f64;
            for &(cx, cy, r) in &DISCS {
                let d = (fx - cx).hypot(fy - cy);
                let c = if d < r - 1.0 {
                    1.0
                } else if d > r + 1.0 {
                    0.0
                } else {
                    let mut n = 0;
                    for sy in 0..8 {
                        for sx in 0..8 {
                            let px = fx - 0.5 + (f64::from(sx) + 0.5) / 8.0;
                            let py = fy - 0.5 + (f64::from(sy) + 0.5) / 8.0;
                            n += usize::from((px - cx).hypot(py - cy) < r);
                        }
                    }
                    n as f64 / 64.0
                };
                cover = cover.max(c);
            }
            let v = 60.0 + 130.0 * cover + noise();
            img.push(v.round().clamp(0.0, 255.0) as u8);
        }
    }
    img
}

fn circles(c: &mut Criterion) {
    let (w, h) = (1920, 1080);
    let img = scene(w, h);
    let mut group = c.benchmark_group("hough_circles 1080p gray u8 10 discs");
    group.sample_size(20);
    for (name, dp, min_radius, max_radius) in [
        ("dp1 r0-any", 1.0, 0.0, 0.0),
        ("dp1 r10-160", 1.0, 10.0, 160.0),
        ("dp2 r10-160", 2.0, 10.0, 160.0),
    ] {
        let o = CircleOptions {
            dp,
            min_radius,
            max_radius,
            ..CircleOptions::default()
        };
        let found = hough_circles(&img, w, h, &o).unwrap_or_default();
        assert!(
            found.len() >= DISCS.len(),
            "{name}: {} circles",
            found.len()
        );
        group.bench_function(name, |b| {
            b.iter(|| hough_circles(black_box(&img), w, h, black_box(&o)))
        });
    }
    group.finish();
}

criterion_group!(benches, circles);
criterion_main!(benches);
