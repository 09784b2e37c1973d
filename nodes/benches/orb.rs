//! ORB detect + describe on a 1080p gray u8 image (`synth_1080p_gray.png` from the folder in
//! `OCELLUS_BENCH_INPUTS` when set, the anchors' input; else a rendered test card) at 500 and
//! 2000 features, and dense HOG on the same image. Compare single-threaded with
//! `OCELLUS_BENCH_INPUTS=/tmp/inputs RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench orb`
//! against `cv2.ORB_create(n).detectAndCompute` and `cv2.HOGDescriptor` (one 1920×1080 window).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::describe::hog::{HogParams, hog};
use ocellus_nodes::describe::orb::{OrbParams, orb_detect_and_compute};

const W: usize = 1920;
const H: usize = 1080;

fn gray() -> Image {
    let format = PixelFormat {
        channels: Channels::Gray,
        depth: Depth::U8,
    };
    if let Ok(dir) = std::env::var("OCELLUS_BENCH_INPUTS") {
        let path = std::path::Path::new(&dir).join("synth_1080p_gray.png");
        match image::open(&path) {
            Ok(img) => {
                let g = img.to_luma8();
                if g.width() as usize == W && g.height() as usize == H {
                    return Image::from_u8(W, H, Channels::Gray, g.into_raw())
                        .unwrap_or_else(|e| panic!("{e}"));
                }
                panic!("{}: expected {W}×{H}", path.display());
            }
            Err(e) => panic!("{}: {e}", path.display()),
        }
    }
    match render(Drawing::TestCard { square: 32 }, W, H, format) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn describe(c: &mut Criterion) {
    // The allocator settings of the CLI (freed blocks are reused, not
    // faulted in again); `OCELLUS_BENCH_ALLOCATOR=default` measures with glibc's defaults.
    if std::env::var("OCELLUS_BENCH_ALLOCATOR").as_deref() != Ok("default") {
        ocellus_engine::buffer::keep_freed_memory();
    }
    let g = gray();
    for n in [500u32, 2000] {
        let p = OrbParams {
            max_features: n,
            ..OrbParams::default()
        };
        // Learn the pattern outside the timing.
        let _ = orb_detect_and_compute(&g, &p);
        c.bench_function(&format!("ORB {n}/1080p gray"), |b| {
            b.iter(|| orb_detect_and_compute(black_box(&g), &p))
        });
    }
    let p = HogParams::default();
    c.bench_function("HOG 8/16/9 dense/1080p gray", |b| {
        b.iter(|| hog(black_box(&g), &p))
    });
}

criterion_group!(benches, describe);
criterion_main!(benches);
