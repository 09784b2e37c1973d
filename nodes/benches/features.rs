//! SIFT detect + describe on a 1080p gray u8 image (`synth_1080p_gray.png` from the folder in
//! `OCELLUS_BENCH_INPUTS` when set, the anchors' input; else a rendered test card), with
//! OpenCV's `SIFT_create(2000)` settings. Compare single-threaded with
//! `OCELLUS_BENCH_INPUTS=/tmp/inputs RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench features`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::describe::sift::{SiftParams, sift_detect_and_compute};

const W: usize = 1920;
const H: usize = 1080;

fn gray() -> Image {
    if let Ok(dir) = std::env::var("OCELLUS_BENCH_INPUTS") {
        let path = std::path::Path::new(&dir).join("synth_1080p_gray.png");
        match image::open(&path) {
            Ok(img) => {
                let g = img.to_luma8();
                if g.width() as usize != W || g.height() as usize != H {
                    panic!("{}: expected {W}×{H}", path.display());
                }
                return match Image::from_u8(W, H, Channels::Gray, g.into_raw()) {
                    Ok(i) => i,
                    Err(e) => panic!("{e}"),
                };
            }
            Err(e) => panic!("{}: {e}", path.display()),
        }
    }
    let format = PixelFormat {
        channels: Channels::Gray,
        depth: Depth::U8,
    };
    match render(Drawing::TestCard { square: 32 }, W, H, format) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn sift(c: &mut Criterion) {
    let image = gray();
    let params = SiftParams {
        max_features: 2000,
        ..SiftParams::default()
    };
    let mut group = c.benchmark_group("features");
    group.sample_size(10);
    group.bench_function("SIFT(2000) detect+describe/1080p gray", |b| {
        b.iter(|| sift_detect_and_compute(black_box(&image), &params))
    });
    group.finish();
}

criterion_group!(benches, sift);
criterion_main!(benches);
