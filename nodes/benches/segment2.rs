//! Background-subtraction, graph-cut and ROC benchmarks: one background-subtraction step per method on
//! 1080p u8 frames (gray and RGB), a graph cut of a 640×480 noisy two-region image, and the
//! ROC sweep of a 1080p u8 score. Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench segment2`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::analyze::evaluate::roc_curve;
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::segment::background::{
    BackgroundConfig, BackgroundMethod, BackgroundSubtractor,
};
use ocellus_nodes::segment::graph_cut::{DataTerm, graph_cut};

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

/// `image` with a deterministic ±8 jitter.
fn jitter(image: &Image, seed: u32) -> Image {
    let Some(src) = image.as_u8() else {
        panic!("u8 input expected")
    };
    let data = src
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            let h = (i as u32 ^ seed).wrapping_mul(2_654_435_761) >> 28;
            (i32::from(v) + h as i32 - 8).clamp(0, 255) as u8
        })
        .collect();
    match Image::from_u8(image.width(), image.height(), image.channels(), data) {
        Ok(i) => i,
        Err(e) => panic!("{e}"),
    }
}

fn background(c: &mut Criterion) {
    for channels in [Channels::Gray, Channels::Rgb] {
        let base = card(1920, 1080, channels);
        let frames = [jitter(&base, 1), jitter(&base, 2)];
        let mut group = c.benchmark_group(format!("background 1080p {} u8", channels.name()));
        for method in BackgroundMethod::ALL {
            let config = BackgroundConfig {
                method: *method,
                ..BackgroundConfig::default()
            };
            let Ok(mut sub) = BackgroundSubtractor::new(config) else {
                panic!("config")
            };
            let _ = sub.apply(&base);
            let mut k = 0;
            group.bench_function(method.name(), |b| {
                b.iter(|| {
                    k ^= 1;
                    black_box(sub.apply(black_box(&frames[k])))
                })
            });
        }
        group.finish();
    }
}

fn cut(c: &mut Criterion) {
    let (w, h) = (640, 480);
    let data: Vec<u8> = (0..w * h)
        .map(|p| {
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            let inside = (x - 320.0).hypot(y - 240.0) < 150.0;
            let noise = ((p as u32).wrapping_mul(2_654_435_761) >> 26) as f64 - 32.0;
            ((if inside { 170.0 } else { 80.0 }) + 2.0 * noise).clamp(0.0, 255.0) as u8
        })
        .collect();
    let Ok(image) = Image::from_u8(w, h, Channels::Gray, data) else {
        panic!("image")
    };
    let term = DataTerm::Means {
        foreground: vec![170.0],
        background: vec![80.0],
        noise_sigma: 40.0,
    };
    let mut group = c.benchmark_group("graph cut 640x480 gray u8");
    group.sample_size(10);
    for conn in [4, 8] {
        group.bench_function(format!("{conn}-connected"), |b| {
            b.iter(|| graph_cut(black_box(&image), &term, 2.0, 20.0, conn))
        });
    }
    group.finish();
}

fn roc(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    let Some(src) = image.as_u8() else {
        panic!("u8")
    };
    let scores: Vec<f64> = src.iter().map(|&v| f64::from(v)).collect();
    let truth: Vec<bool> = src
        .iter()
        .enumerate()
        .map(|(i, &v)| (v as usize + i).is_multiple_of(3))
        .collect();
    c.bench_function("roc 1080p 256 steps", |b| {
        b.iter(|| roc_curve(black_box(&scores), &truth, 256))
    });
}

criterion_group!(benches, background, cut, roc);
criterion_main!(benches);
