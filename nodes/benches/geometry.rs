//! Geometry benchmarks, sized like the OpenCV anchors: resize (area ½ and bilinear 2×) on 1080p
//! and 2160p gray and RGB u8, pyrDown, a warpAffine rotation and the integral image on 1080p.
//! Compare single-threaded with `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench
//! geometry` against OpenCV with `cv2.setNumThreads(1)`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::integral::integral;
use ocellus_nodes::filter::pyramid::{pyr_down, pyr_up};
use ocellus_nodes::filter::resize::{Interpolation, Target, resize};
use ocellus_nodes::filter::warp::{Transform, WarpInterpolation, WarpOptions, invert_affine, warp};

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

fn inputs() -> Vec<(&'static str, Image)> {
    vec![
        ("1080p gray", card(1920, 1080, Channels::Gray)),
        ("1080p rgb", card(1920, 1080, Channels::Rgb)),
        ("2160p gray", card(3840, 2160, Channels::Gray)),
        ("2160p rgb", card(3840, 2160, Channels::Rgb)),
    ]
}

fn resize_area_half(c: &mut Criterion) {
    let mut group = c.benchmark_group("resize area 0.5x");
    for (name, image) in inputs() {
        group.bench_function(name, |b| {
            b.iter(|| {
                resize(
                    black_box(&image),
                    Target::Scale(0.5, 0.5),
                    Interpolation::Area,
                )
            })
        });
    }
    group.finish();
}

fn resize_bilinear_double(c: &mut Criterion) {
    let mut group = c.benchmark_group("resize bilinear 2x");
    group.sample_size(20);
    for (name, image) in inputs() {
        group.bench_function(name, |b| {
            b.iter(|| {
                resize(
                    black_box(&image),
                    Target::Scale(2.0, 2.0),
                    Interpolation::Bilinear,
                )
            })
        });
    }
    group.finish();
}

fn resize_other(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    let mut group = c.benchmark_group("resize 1080p gray");
    for (name, method) in [
        ("bilinear 0.7x", Interpolation::Bilinear),
        ("bicubic 0.7x", Interpolation::Bicubic),
        ("area 0.7x", Interpolation::Area),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| resize(black_box(&image), Target::Size(1344, 756), method))
        });
    }
    group.finish();
}

fn pyramids(c: &mut Criterion) {
    let mut group = c.benchmark_group("pyramid 1080p");
    for (name, image) in [
        ("pyrDown gray", card(1920, 1080, Channels::Gray)),
        ("pyrDown rgb", card(1920, 1080, Channels::Rgb)),
    ] {
        group.bench_function(name, |b| b.iter(|| pyr_down(black_box(&image))));
    }
    let small = card(960, 540, Channels::Gray);
    group.bench_function("pyrUp gray 540p", |b| {
        b.iter(|| pyr_up(black_box(&small), 1920, 1080))
    });
    group.finish();
}

fn warp_rotation(c: &mut Criterion) {
    // cv2.getRotationMatrix2D((960, 540), 30, 0.9), bilinear, constant border.
    let a = 30f64.to_radians();
    let (al, be) = (0.9 * a.cos(), 0.9 * a.sin());
    let m = [
        al,
        be,
        (1.0 - al) * 960.0 - be * 540.0,
        -be,
        al,
        be * 960.0 + (1.0 - al) * 540.0,
    ];
    let t = match invert_affine(&m) {
        Ok(inv) => Transform::Affine(inv),
        Err(e) => panic!("{e}"),
    };
    let options = WarpOptions {
        size: None,
        interpolation: WarpInterpolation::Bilinear,
        border: BorderMode::Constant,
        border_value: 0.0,
    };
    let mut group = c.benchmark_group("warpAffine rotation 1080p");
    group.sample_size(20);
    for (name, image) in [
        ("gray", card(1920, 1080, Channels::Gray)),
        ("rgb", card(1920, 1080, Channels::Rgb)),
    ] {
        group.bench_function(name, |b| b.iter(|| warp(black_box(&image), &t, &options)));
    }
    group.finish();
}

fn integral_image(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Gray);
    c.bench_function("integral f64/1080p gray", |b| {
        b.iter(|| integral(black_box(&image)))
    });
}

criterion_group!(
    benches,
    resize_area_half,
    resize_bilinear_double,
    resize_other,
    pyramids,
    warp_rotation,
    integral_image
);
criterion_main!(benches);
