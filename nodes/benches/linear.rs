//! Linear filter benchmarks on 1080p u8, sized like the OpenCV anchors: Sobel dx ksize 3 (gray →
//! f32), Scharr dx, and `filter.convolve` with a separable and a dense kernel. Compare
//! single-threaded with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench linear`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::convolve::{ConvolveOptions, Kernel, convolve};
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

fn convolutions(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    let sharpen = Kernel::from_rows(&[
        vec![0.0, -1.0, 0.0],
        vec![-1.0, 5.0, -1.0],
        vec![0.0, -1.0, 0.0],
    ]);
    let binomial = [1.0, 4.0, 6.0, 4.0, 1.0];
    let separable = Kernel::from_rows(
        &binomial
            .iter()
            .map(|a| binomial.iter().map(|b| a * b / 256.0).collect())
            .collect::<Vec<_>>(),
    );
    let (Ok(sharpen), Ok(separable)) = (sharpen, separable) else {
        panic!("benchmark kernels");
    };
    for (name, kernel) in [
        ("convolve dense 3x3/1080p gray u8", sharpen),
        ("convolve separable 5x5/1080p gray u8", separable),
    ] {
        let options = ConvolveOptions::centred(&kernel);
        c.bench_function(name, |b| {
            b.iter(|| convolve(black_box(&image), &kernel, &options))
        });
    }
}

criterion_group!(benches, derivatives, convolutions);
criterion_main!(benches);
