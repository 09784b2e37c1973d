//! Non-linear filter benchmarks: median 5×5 and bilateral d = 9 (σc = σs = 75) on 1080p and
//! 2160p gray and RGB u8 images, the sizes of the OpenCV comparison (`medianBlur(img, 5)`,
//! `bilateralFilter(img, 9, 75, 75)`). Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench nonlinear`.
//!
//! The inputs are the test card rendered at each size; set `OCELLUS_BENCH_INPUTS` to a folder
//! holding `synth_{1080p,2160p}_{gray,rgb}.png` to use those images instead.

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::bilateral::bilateral_filter;
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::kuwahara::{KuwaharaMethod, kuwahara};
use ocellus_nodes::filter::median::median_blur;

const SIZES: [(&str, usize, usize); 2] = [("1080p", 1920, 1080), ("2160p", 3840, 2160)];

/// The benchmark input: a PNG from `OCELLUS_BENCH_INPUTS` when set, else the test card.
fn input(size: &str, width: usize, height: usize, channels: Channels) -> Image {
    let kind = if channels == Channels::Gray {
        "gray"
    } else {
        "rgb"
    };
    if let Ok(dir) = std::env::var("OCELLUS_BENCH_INPUTS") {
        let path = format!("{dir}/synth_{size}_{kind}.png");
        if let Ok(decoded) = image::open(&path) {
            let (w, h) = (decoded.width() as usize, decoded.height() as usize);
            let loaded = if channels == Channels::Gray {
                Image::from_u8(w, h, channels, decoded.to_luma8().into_raw())
            } else {
                Image::from_u8(w, h, channels, decoded.to_rgb8().into_raw())
            };
            match loaded {
                Ok(image) => return image,
                Err(e) => panic!("{path}: {e}"),
            }
        }
    }
    let format = PixelFormat {
        channels,
        depth: Depth::U8,
    };
    match render(Drawing::TestCard { square: 32 }, width, height, format) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn median(c: &mut Criterion) {
    let mut group = c.benchmark_group("median 5x5");
    for (size, w, h) in SIZES {
        for (kind, channels) in [("gray", Channels::Gray), ("rgb", Channels::Rgb)] {
            let image = input(size, w, h, channels);
            group.bench_function(format!("{size} {kind} u8"), |b| {
                b.iter(|| median_blur(black_box(&image), 5, BorderMode::Clamp, 0.0))
            });
        }
    }
    group.finish();
    let image = input("1080p", 1920, 1080, Channels::Gray);
    let mut group = c.benchmark_group("median 1080p gray u8");
    for k in [3, 7, 15] {
        group.bench_function(format!("ksize {k}"), |b| {
            b.iter(|| median_blur(black_box(&image), k, BorderMode::Clamp, 0.0))
        });
    }
    group.finish();
}

fn bilateral(c: &mut Criterion) {
    let mut group = c.benchmark_group("bilateral d9 sc75 ss75");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(5));
    for (size, w, h) in SIZES {
        for (kind, channels) in [("gray", Channels::Gray), ("rgb", Channels::Rgb)] {
            let image = input(size, w, h, channels);
            group.bench_function(format!("{size} {kind} u8"), |b| {
                b.iter(|| {
                    bilateral_filter(
                        black_box(&image),
                        4,
                        75.0,
                        75.0,
                        BorderMode::Reflect101,
                        0.0,
                    )
                })
            });
        }
    }
    group.finish();
}

fn kuwahara_bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("kuwahara r5 1080p rgb u8");
    group.sample_size(10);
    let image = input("1080p", 1920, 1080, Channels::Rgb);
    for (name, method) in [
        ("generalized 8 sectors", KuwaharaMethod::Generalized),
        ("classic", KuwaharaMethod::Classic),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                kuwahara(
                    black_box(&image),
                    method,
                    5,
                    8,
                    8,
                    BorderMode::Reflect101,
                    0.0,
                )
            })
        });
    }
    group.finish();
}

criterion_group!(benches, median, bilateral, kuwahara_bench);
criterion_main!(benches);
