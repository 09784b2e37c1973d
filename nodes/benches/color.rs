//! Colour and type conversion benchmarks on a 1080p RGB u8 test card: RGB → HSV, Lab and
//! YCbCr (and back), and u8 → f32. Compare single-threaded with OpenCV's `cvtColor` /
//! `convertTo`: `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench color`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::filter::color::{Conversion, convert_color};
use ocellus_nodes::filter::convert::convert_type;

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

fn conversions(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Rgb);
    let mut group = c.benchmark_group("convert_color 1080p rgb u8");
    for conversion in [
        Conversion::RgbToHsv,
        Conversion::HsvToRgb,
        Conversion::RgbToLab,
        Conversion::LabToRgb,
        Conversion::RgbToYcbcr,
        Conversion::YcbcrToRgb,
    ] {
        group.bench_function(conversion.name(), |b| {
            b.iter(|| convert_color(black_box(&image), conversion))
        });
    }
    group.finish();
}

fn to_float(c: &mut Criterion) {
    let image = card(1920, 1080, Channels::Rgb);
    c.bench_function("convert_type u8 to f32/1080p rgb", |b| {
        b.iter(|| convert_type(black_box(&image), Depth::F32, None, 0.0))
    });
}

criterion_group!(benches, conversions, to_float);
criterion_main!(benches);
