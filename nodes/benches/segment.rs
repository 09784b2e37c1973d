//! Segmentation benchmarks: connected components (labels only, and with statistics) on an
//! Otsu-binarized gray image at 1080p and 2160p, the inputs of OpenCV's
//! `connectedComponents(binary, connectivity=8, ltype=CV_32S)` and
//! `connectedComponentsWithStats`. Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench segment`.
//!
//! Also k-means (k = 8, 10 iterations, 1 attempt; `cv2.kmeans` with `TERM_CRITERIA_MAX_ITER`
//! 10 and `KMEANS_PP_CENTERS` does the same work) and the marker watershed (a marker every 64 px;
//! `cv2.watershed`) on the 1080p RGB image.
//!
//! With `OCELLUS_BENCH_INPUTS` set to a folder holding `synth_1080p_gray.png` and
//! `synth_2160p_gray.png` those are binarized; otherwise generated test cards of the same sizes.

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::image_io::{DecodeLimits, read_image};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::threshold::{ThresholdMethod, ThresholdMode, threshold};
use ocellus_nodes::segment::components::connected_components;
use ocellus_nodes::segment::kmeans::{KmeansConfig, kmeans};
use ocellus_nodes::segment::watershed::watershed;

fn load(name: &str, channels: Channels, width: usize, height: usize) -> Image {
    let suffix = if channels == Channels::Gray {
        "gray"
    } else {
        "rgb"
    };
    match std::env::var("OCELLUS_BENCH_INPUTS") {
        Ok(dir) => match read_image(
            &Path::new(&dir).join(format!("synth_{name}_{suffix}.png")),
            &DecodeLimits::default(),
        ) {
            Ok(image) => image,
            Err(e) => panic!("reading the benchmark input: {e}"),
        },
        Err(_) => {
            let format = PixelFormat {
                channels,
                depth: Depth::U8,
            };
            match render(Drawing::TestCard { square: 32 }, width, height, format) {
                Ok(image) => image,
                Err(e) => panic!("rendering the benchmark input: {e}"),
            }
        }
    }
}

fn input(name: &str, width: usize, height: usize) -> Image {
    let gray = load(name, Channels::Gray, width, height);
    match threshold(
        &gray,
        ThresholdMethod::Otsu,
        ThresholdMode::Binary,
        0.0,
        255.0,
    ) {
        Ok((binary, _)) => binary,
        Err(e) => panic!("binarizing the benchmark input: {e}"),
    }
}

fn components(c: &mut Criterion) {
    let mut group = c.benchmark_group("components 8");
    for (name, w, h) in [("1080p", 1920, 1080), ("2160p", 3840, 2160)] {
        let image = input(name, w, h);
        match connected_components(&image, true, true) {
            Ok(l) => {
                let area: u64 = l.stats.iter().map(|s| s.area).sum();
                eprintln!("{name}: {} components, {area} foreground pixels", l.count);
            }
            Err(e) => panic!("labeling the benchmark input: {e}"),
        }
        group.bench_function(format!("{name} labels"), |b| {
            b.iter(|| connected_components(black_box(&image), true, false))
        });
        group.bench_function(format!("{name} labels+stats"), |b| {
            b.iter(|| connected_components(black_box(&image), true, true))
        });
    }
    group.finish();
}

fn kmeans_rgb(c: &mut Criterion) {
    let image = load("1080p", Channels::Rgb, 1920, 1080);
    let config = KmeansConfig {
        k: 8,
        max_iterations: 10,
        epsilon: 0.0,
        attempts: 1,
        seed: 0,
    };
    c.bench_function("kmeans k8 10 iterations/1080p rgb u8", |b| {
        b.iter(|| kmeans(black_box(&image), &config))
    });
}

fn watershed_rgb(c: &mut Criterion) {
    let image = load("1080p", Channels::Rgb, 1920, 1080);
    let (w, h) = (image.width(), image.height());
    let mut markers = vec![0f32; w * h];
    let mut label = 0.0;
    for y in (32..h).step_by(64) {
        for x in (32..w).step_by(64) {
            label += 1.0;
            markers[y * w + x] = label;
        }
    }
    let markers = match Image::from_f32(w, h, Channels::Gray, markers) {
        Ok(m) => m,
        Err(e) => panic!("benchmark markers: {e}"),
    };
    c.bench_function("watershed grid markers/1080p rgb u8", |b| {
        b.iter(|| watershed(black_box(&image), &markers))
    });
}

criterion_group!(benches, components, kmeans_rgb, watershed_rgb);
criterion_main!(benches);
