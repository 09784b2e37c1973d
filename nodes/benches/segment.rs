//! Segmentation benchmarks: connected components (labels only, and with statistics) on an
//! Otsu-binarized gray image at 1080p and 2160p, the inputs of OpenCV's
//! `connectedComponents(binary, connectivity=8, ltype=CV_32S)` and
//! `connectedComponentsWithStats`. Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench segment`.
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

fn input(name: &str, width: usize, height: usize) -> Image {
    let gray = match std::env::var("OCELLUS_BENCH_INPUTS") {
        Ok(dir) => match read_image(
            &Path::new(&dir).join(format!("synth_{name}_gray.png")),
            &DecodeLimits::default(),
        ) {
            Ok(image) => image,
            Err(e) => panic!("reading the benchmark input: {e}"),
        },
        Err(_) => {
            let format = PixelFormat {
                channels: Channels::Gray,
                depth: Depth::U8,
            };
            match render(Drawing::TestCard { square: 32 }, width, height, format) {
                Ok(image) => image,
                Err(e) => panic!("rendering the benchmark input: {e}"),
            }
        }
    };
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

criterion_group!(benches, components);
criterion_main!(benches);
