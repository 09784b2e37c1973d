//! Box and Sobel filter benchmarks, sized like the OpenCV anchors (boxFilter 7×7 on 1080p gray
//! and RGB u8, Sobel dx ksize 3 on 1080p gray u8). Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench filters2`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::box_filter::box_filter;
use ocellus_nodes::filter::sobel::sobel;

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

fn box_7x7(c: &mut Criterion) {
    let mut group = c.benchmark_group("box 7x7");
    for (name, image) in [
        ("1080p gray u8", card(1920, 1080, Channels::Gray)),
        ("1080p rgb u8", card(1920, 1080, Channels::Rgb)),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| box_filter(black_box(&image), 7, 7, true, BorderMode::Reflect101, 0.0))
        });
    }
    group.finish();
}

fn box_31x31(c: &mut Criterion) {
    // Same work per pixel as 7×7: the running sums do not depend on the window size.
    let image = card(1920, 1080, Channels::Gray);
    c.bench_function("box 31x31/1080p gray u8", |b| {
        b.iter(|| box_filter(black_box(&image), 31, 31, true, BorderMode::Reflect101, 0.0))
    });
}

fn sobel_dx(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    c.bench_function("sobel dx ksize 3/1080p gray u8", |b| {
        b.iter(|| {
            sobel(
                black_box(&image),
                1,
                0,
                3,
                1.0,
                0.0,
                BorderMode::Reflect101,
                0.0,
            )
        })
    });
}

criterion_group!(benches, box_7x7, box_31x31, sobel_dx);
criterion_main!(benches);
