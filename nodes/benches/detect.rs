//! Benchmarks of the detectors and measurements on 1080p inputs.
//!
//! Reference: OpenCV 5.0's `cv::Canny` 50/150, aperture 3, L1, one thread, takes 8.6 ms on the
//! team's 1080p gray anchor image (a different, more textured input than the scene below), on the
//! development machines. Timings drift between runs there; compare in one sitting.
//!
//! ```text
//! cargo bench -p ocellus-nodes --bench detect
//! RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench detect
//! ```

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Image};
use ocellus_nodes::analyze::stats::stats_metrics;
use ocellus_nodes::detect::canny::canny;

const WIDTH: usize = 1920;
const HEIGHT: usize = 1080;

/// Deterministic pseudo-random numbers (splitmix64).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A synthetic camera-like scene of one channel: a smooth shaded background, 60 filled discs and
/// 60 rectangles of random grey levels, a slight blur (two 3×3 box passes) and ±2 levels of noise.
fn scene(width: usize, height: usize, seed: u64) -> Vec<u8> {
    let mut rng = Rng(seed);
    let mut img: Vec<f32> = (0..width * height)
        .map(|i| {
            let (x, y) = ((i % width) as f32, (i / width) as f32);
            110.0 + 40.0 * (x / 300.0).sin() * (y / 220.0).cos()
        })
        .collect();
    for _ in 0..60 {
        let (cx, cy) = (rng.unit() * width as f32, rng.unit() * height as f32);
        let r = 10.0 + rng.unit() * 150.0;
        let level = rng.unit() * 255.0;
        let (x0, x1) = ((cx - r).max(0.0) as usize, ((cx + r) as usize).min(width));
        let (y0, y1) = ((cy - r).max(0.0) as usize, ((cy + r) as usize).min(height));
        for y in y0..y1 {
            for x in x0..x1 {
                let (dx, dy) = (x as f32 - cx, y as f32 - cy);
                if dx * dx + dy * dy <= r * r {
                    img[y * width + x] = level;
                }
            }
        }
    }
    for _ in 0..60 {
        let (x0, y0) = (
            (rng.unit() * width as f32) as usize,
            (rng.unit() * height as f32) as usize,
        );
        let x1 = (x0 + 20 + (rng.unit() * 300.0) as usize).min(width);
        let y1 = (y0 + 20 + (rng.unit() * 200.0) as usize).min(height);
        let level = rng.unit() * 255.0;
        for y in y0..y1 {
            img[y * width + x0..y * width + x1].fill(level);
        }
    }
    for _ in 0..2 {
        let src = img.clone();
        for y in 0..height {
            for x in 0..width {
                let mut s = 0.0;
                for (dy, dx) in (0..9).map(|k| (k / 3, k % 3)) {
                    let yy = (y + dy).saturating_sub(1).min(height - 1);
                    let xx = (x + dx).saturating_sub(1).min(width - 1);
                    s += src[yy * width + xx];
                }
                img[y * width + x] = s / 9.0;
            }
        }
    }
    img.iter()
        .map(|&v| (v + (rng.unit() - 0.5) * 4.0).round().clamp(0.0, 255.0) as u8)
        .collect()
}

fn benches(c: &mut Criterion) {
    let gray = scene(WIDTH, HEIGHT, 1);
    let edges = canny(&gray, WIDTH, HEIGHT, 50.0, 150.0, 3, false);
    let count = edges.iter().filter(|&&e| e != 0).count();
    println!(
        "canny input: {WIDTH}×{HEIGHT} synthetic scene, {count} edge pixels ({:.2} %), {} threads",
        100.0 * count as f64 / (WIDTH * HEIGHT) as f64,
        rayon::current_num_threads()
    );
    c.bench_function("canny 50/150 aperture 3 L1, 1080p gray u8", |b| {
        b.iter(|| canny(black_box(&gray), WIDTH, HEIGHT, 50.0, 150.0, 3, false))
    });
    c.bench_function("canny 50/150 aperture 3 L2, 1080p gray u8", |b| {
        b.iter(|| canny(black_box(&gray), WIDTH, HEIGHT, 50.0, 150.0, 3, true))
    });

    let rgb: Vec<u8> = {
        let planes = [scene(WIDTH, HEIGHT, 2), scene(WIDTH, HEIGHT, 3), gray];
        (0..WIDTH * HEIGHT)
            .flat_map(|i| planes.iter().map(move |p| p[i]))
            .collect()
    };
    let image = match Image::from_u8(WIDTH, HEIGHT, Channels::Rgb, rgb) {
        Ok(image) => image,
        Err(e) => panic!("bench image: {e}"),
    };
    let floats: Vec<f32> = image
        .as_u8()
        .unwrap_or_default()
        .iter()
        .map(|&v| f32::from(v) / 255.0)
        .collect();
    let image_f32 = match Image::from_f32(WIDTH, HEIGHT, Channels::Rgb, floats) {
        Ok(image) => image,
        Err(e) => panic!("bench image: {e}"),
    };
    c.bench_function("stats, 1080p rgb u8", |b| {
        b.iter(|| stats_metrics(black_box(&image), None))
    });
    c.bench_function("stats, 1080p rgb f32", |b| {
        b.iter(|| stats_metrics(black_box(&image_f32), None))
    });
}

criterion_group!(detect, benches);
criterion_main!(detect);
