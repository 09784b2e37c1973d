//! Filter benchmarks, sized like the OpenCV anchors in `shared/anchors/bench_image.py`
//! (GaussianBlur 5×5 σ 1.5 on 1080p gray and RGB, cvtColor RGB2GRAY). Compare single-threaded
//! with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench filters`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::gaussian::gaussian_blur;
use ocellus_nodes::filter::grayscale::{LumaStandard, grayscale};

fn format(channels: Channels) -> PixelFormat {
    PixelFormat {
        channels,
        depth: Depth::U8,
    }
}

/// A test card: edges, gratings and ramps, so the data is not trivially compressible.
fn card(width: usize, height: usize, channels: Channels) -> Image {
    match render(
        Drawing::TestCard { square: 32 },
        width,
        height,
        format(channels),
    ) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn gaussian(c: &mut Criterion) {
    let mut group = c.benchmark_group("gaussian 5x5 sigma 1.5");
    for (name, image) in [
        ("1080p gray u8", card(1920, 1080, Channels::Gray)),
        ("1080p rgb u8", card(1920, 1080, Channels::Rgb)),
        ("2160p gray u8", card(3840, 2160, Channels::Gray)),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                gaussian_blur(
                    black_box(&image),
                    1.5,
                    1.5,
                    5,
                    5,
                    BorderMode::Reflect101,
                    0.0,
                )
            })
        });
    }
    group.finish();
}

fn gray(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Rgb);
    c.bench_function("grayscale bt601 1080p rgb u8", |b| {
        b.iter(|| grayscale(black_box(&image), LumaStandard::Bt601))
    });
}

fn pattern(c: &mut Criterion) {
    c.bench_function("pattern test_card 1080p rgb u8", |b| {
        b.iter(|| {
            render(
                black_box(Drawing::TestCard { square: 32 }),
                1920,
                1080,
                format(Channels::Rgb),
            )
        })
    });
}

criterion_group!(benches, gaussian, gray, pattern);
criterion_main!(benches);
