//! Linear filter benchmarks on 1080p u8, sized like the OpenCV anchors: Sobel dx ksize 3 (gray →
//! f32), Scharr dx, and `filter.convolve` with a separable and a dense kernel. Compare
//! single-threaded with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench linear`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::sobel::{scharr, sobel};

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

fn derivatives(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    let border = BorderMode::Reflect101;
    c.bench_function("sobel dx ksize 3/1080p gray u8", |b| {
        b.iter(|| sobel(black_box(&image), 1, 0, 3, 1.0, 0.0, border, 0.0))
    });
    c.bench_function("sobel dy ksize 3/1080p gray u8", |b| {
        b.iter(|| sobel(black_box(&image), 0, 1, 3, 1.0, 0.0, border, 0.0))
    });
    c.bench_function("scharr dx/1080p gray u8", |b| {
        b.iter(|| scharr(black_box(&image), true, 1.0, 0.0, border, 0.0))
    });
}

criterion_group!(benches, derivatives);
criterion_main!(benches);
