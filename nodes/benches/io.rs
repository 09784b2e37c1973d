//! Image file I/O: decode and encode a 1080p test card as PNG (8-bit RGB and 16-bit gray) and
//! PFM (f32 RGB). `cargo bench -p ocellus-nodes --bench io`

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::image_io::{DecodeLimits, ImageFormat, decode_image, encode_image};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};

fn card(channels: Channels, depth: Depth) -> Image {
    match render(
        Drawing::TestCard { square: 32 },
        1920,
        1080,
        PixelFormat { channels, depth },
    ) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn io(c: &mut Criterion) {
    let limits = DecodeLimits::default();
    let path = Path::new("bench");
    for (name, image, format) in [
        (
            "png rgb u8",
            card(Channels::Rgb, Depth::U8),
            ImageFormat::Png,
        ),
        (
            "png gray u16",
            card(Channels::Gray, Depth::U16),
            ImageFormat::Png,
        ),
        (
            "pfm rgb f32",
            card(Channels::Rgb, Depth::F32),
            ImageFormat::Pfm,
        ),
    ] {
        let bytes = match encode_image(&image, format) {
            Ok(b) => b,
            Err(e) => panic!("{name}: {e}"),
        };
        c.bench_function(&format!("encode 1080p {name}"), |b| {
            b.iter(|| black_box(encode_image(&image, format).is_ok()))
        });
        c.bench_function(&format!("decode 1080p {name}"), |b| {
            b.iter(|| black_box(decode_image(&bytes, path, &limits).is_ok()))
        });
    }
}

criterion_group!(benches, io);
criterion_main!(benches);
