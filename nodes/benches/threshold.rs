//! Threshold and histogram-equalization benchmarks on a 1080p gray u8 test card: Otsu
//! threshold, adaptive mean threshold 11×11, global equalization and CLAHE (clip 40, 8×8
//! tiles). Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench threshold`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::histogram::{ColorMode, clahe, equalize};
use ocellus_nodes::filter::threshold::{
    AdaptiveMethod, AdaptiveMode, ThresholdMethod, ThresholdMode, adaptive_threshold, threshold,
};

/// A u8 test card: edges, gratings and ramps, so the data is not trivially compressible.
fn card(width: usize, height: usize, channels: Channels) -> Image {
    let format = PixelFormat {
        channels,
        depth: Depth::U8,
    };
    match render(Drawing::TestCard { square: 32 }, width, height, format) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn thresholds(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    let mut group = c.benchmark_group("threshold 1080p gray u8");
    group.bench_function("otsu", |b| {
        b.iter(|| {
            threshold(
                black_box(&image),
                ThresholdMethod::Otsu,
                ThresholdMode::Binary,
                0.0,
                255.0,
            )
        })
    });
    group.bench_function("fixed binary", |b| {
        b.iter(|| {
            threshold(
                black_box(&image),
                ThresholdMethod::Fixed,
                ThresholdMode::Binary,
                127.0,
                255.0,
            )
        })
    });
    group.bench_function("adaptive mean 11x11", |b| {
        b.iter(|| {
            adaptive_threshold(
                black_box(&image),
                AdaptiveMethod::Mean,
                11,
                2.0,
                AdaptiveMode::Binary,
                255.0,
            )
        })
    });
    group.bench_function("adaptive gaussian 11x11", |b| {
        b.iter(|| {
            adaptive_threshold(
                black_box(&image),
                AdaptiveMethod::Gaussian,
                11,
                2.0,
                AdaptiveMode::Binary,
                255.0,
            )
        })
    });
    group.finish();
}

fn equalization(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    let mut group = c.benchmark_group("equalization 1080p gray u8");
    group.bench_function("equalize", |b| {
        b.iter(|| equalize(black_box(&image), ColorMode::Luma))
    });
    group.bench_function("clahe 40 8x8", |b| {
        b.iter(|| clahe(black_box(&image), 40.0, [8, 8], ColorMode::Luma))
    });
    group.finish();
}

criterion_group!(benches, thresholds, equalization);
criterion_main!(benches);
