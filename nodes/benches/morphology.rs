//! Morphology benchmarks, sized like the OpenCV anchor in `shared/anchors/bench_image.py`
//! (`morphologyEx` OPEN, rect 5×5, 1080p gray u8). Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench morphology`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::morphology::{
    MorphBorder, Operation, Shape, StructuringElement, dilate, erode, morphology,
};

/// A test card: edges, gratings and ramps, so the data is not trivially compressible.
fn card(channels: Channels) -> Image {
    card_sized(channels, 1920, 1080)
}

fn card_sized(channels: Channels, width: usize, height: usize) -> Image {
    let format = PixelFormat {
        channels,
        depth: Depth::U8,
    };
    match render(Drawing::TestCard { square: 32 }, width, height, format) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn element(shape: Shape, size: usize) -> StructuringElement {
    match StructuringElement::new(shape, size, size) {
        Some(element) => element,
        None => panic!("element {size}×{size}"),
    }
}

fn open(c: &mut Criterion) {
    let mut group = c.benchmark_group("morphology open rect 5x5");
    let rect = element(Shape::Rect, 5);
    for (name, image) in [
        ("1080p gray u8", card(Channels::Gray)),
        ("1080p rgb u8", card(Channels::Rgb)),
        ("2160p gray u8", card_sized(Channels::Gray, 3840, 2160)),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                morphology(
                    black_box(&image),
                    Operation::Open,
                    &rect,
                    1,
                    MorphBorder::Neutral,
                )
            })
        });
    }
    group.finish();
}

fn erode_sizes(c: &mut Criterion) {
    let gray = card(Channels::Gray);
    let mut group = c.benchmark_group("erode 1080p gray u8");
    for (name, shape, size) in [
        ("rect 5x5", Shape::Rect, 5),
        ("rect 15x15", Shape::Rect, 15),
        ("rect 31x31", Shape::Rect, 31),
        ("ellipse 5x5", Shape::Ellipse, 5),
    ] {
        let e = element(shape, size);
        group.bench_function(name, |b| {
            b.iter(|| erode(black_box(&gray), &e, 1, MorphBorder::Neutral))
        });
    }
    group.finish();
    let rect = element(Shape::Rect, 5);
    c.bench_function("dilate 1080p gray u8/rect 5x5", |b| {
        b.iter(|| dilate(black_box(&gray), &rect, 1, MorphBorder::Neutral))
    });
}

fn distance(c: &mut Criterion) {
    use ocellus_nodes::filter::distance::{Metric, distance_transform};
    let gray = card(Channels::Gray);
    let Some(data) = gray.as_u8() else {
        panic!("the card is u8")
    };
    let binary: Vec<u8> = data
        .iter()
        .map(|&v| if v > 100 { 255 } else { 0 })
        .collect();
    let mask = match Image::from_u8(1920, 1080, Channels::Gray, binary) {
        Ok(image) => image,
        Err(e) => panic!("mask: {e}"),
    };
    c.bench_function("distance_transform 1080p euclidean", |b| {
        b.iter(|| distance_transform(black_box(&mask), Metric::Euclidean))
    });
}

criterion_group!(benches, erode_sizes, open, distance);
criterion_main!(benches);
