//! Frequency-domain and noise benchmarks: forward 2-D DFT of 1024×1024 and 1920×1080 gray
//! planes (compare `cv2.dft(img, flags=cv2.DFT_COMPLEX_OUTPUT)` on CV_32F), the round trip
//! through the inverse, a Gaussian frequency filter, the 8×8 DCT and Gaussian noise on 1080p.
//! Compare single-threaded with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench frequency`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::frequency::dct::dct_8x8;
use ocellus_nodes::filter::frequency::fft::{fft2d, ifft2d};
use ocellus_nodes::filter::frequency::haar::haar;
use ocellus_nodes::filter::frequency::pass::{FilterKind, PassBand, frequency_filter};
use ocellus_nodes::filter::frequency::to_planes;
use ocellus_nodes::filter::noise::{NoiseModel, add_noise};

/// A u8 test card: edges, gratings and ramps.
fn card(width: usize, height: usize) -> Image {
    let format = PixelFormat {
        channels: Channels::Gray,
        depth: Depth::U8,
    };
    match render(Drawing::TestCard { square: 32 }, width, height, format) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn fft(c: &mut Criterion) {
    let mut group = c.benchmark_group("fft");
    for (name, w, h) in [("1024x1024", 1024, 1024), ("1080p", 1920, 1080)] {
        let plane = to_planes(&card(w, h)).remove(0);
        group.bench_function(format!("forward {name} gray f32"), |b| {
            b.iter(|| fft2d(black_box(&plane), w, h, false))
        });
        let (re, im) = fft2d(&plane, w, h, false);
        group.bench_function(format!("inverse {name} gray f32"), |b| {
            b.iter(|| ifft2d(black_box(&re), black_box(&im), w, h, false))
        });
    }
    group.finish();
}

fn others(c: &mut Criterion) {
    let image = card(1920, 1080);
    c.bench_function("frequency_filter gaussian low/1080p gray u8", |b| {
        b.iter(|| {
            frequency_filter(
                black_box(&image),
                FilterKind::Gaussian,
                PassBand::Low,
                0.05,
                1,
            )
        })
    });
    c.bench_function("dct 8x8/1080p gray u8", |b| {
        b.iter(|| dct_8x8(black_box(&image), false))
    });
    c.bench_function("haar 3 levels/1080p gray u8", |b| {
        b.iter(|| haar(black_box(&image), 3, false))
    });
    c.bench_function("noise gaussian/1080p gray u8", |b| {
        b.iter(|| add_noise(black_box(&image), NoiseModel::Gaussian { sigma: 10.0 }, 1))
    });
    c.bench_function("noise poisson/1080p gray u8", |b| {
        b.iter(|| add_noise(black_box(&image), NoiseModel::Poisson { scale: 1.0 }, 1))
    });
}

criterion_group!(benches, fft, others);
criterion_main!(benches);
