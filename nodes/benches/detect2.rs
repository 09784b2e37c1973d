//! Corner and FAST benchmarks on a 1080p gray u8 image (`synth_1080p_gray.png` from the folder
//! in `OCELLUS_BENCH_INPUTS` when set, the anchors' input; else a rendered test card):
//! cornerHarris block 2 ksize 3, goodFeaturesToTrack 2000 Harris, FAST t = 20 with NMS. Compare
//! single-threaded with
//! `OCELLUS_BENCH_INPUTS=/tmp/inputs RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench detect2`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Depth, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::detect::corners::{CornerMethod, corner_response, select_corners};
use ocellus_nodes::detect::fast::fast9;

const W: usize = 1920;
const H: usize = 1080;

fn gray() -> Vec<u8> {
    if let Ok(dir) = std::env::var("OCELLUS_BENCH_INPUTS") {
        let path = std::path::Path::new(&dir).join("synth_1080p_gray.png");
        match image::open(&path) {
            Ok(img) => {
                let g = img.to_luma8();
                if g.width() as usize == W && g.height() as usize == H {
                    return g.into_raw();
                }
                panic!("{}: expected {W}×{H}", path.display());
            }
            Err(e) => panic!("{}: {e}", path.display()),
        }
    }
    let format = PixelFormat {
        channels: Channels::Gray,
        depth: Depth::U8,
    };
    match render(Drawing::TestCard { square: 32 }, W, H, format) {
        Ok(image) => image.as_u8().map(<[u8]>::to_vec).unwrap_or_default(),
        Err(e) => panic!("rendering the benchmark input: {e}"),
    }
}

fn corners(c: &mut Criterion) {
    let g = gray();
    let plane: Vec<f32> = g.iter().map(|&v| f32::from(v)).collect();
    c.bench_function("cornerHarris b2 k3/1080p gray", |b| {
        b.iter(|| {
            corner_response(
                black_box(&plane),
                W,
                H,
                2,
                3,
                CornerMethod::Harris,
                0.04,
                255.0,
            )
        })
    });
    c.bench_function("goodFeaturesToTrack 2000 harris/1080p gray", |b| {
        b.iter(|| {
            let plane: Vec<f32> = black_box(&g).iter().map(|&v| f32::from(v)).collect();
            let r = corner_response(&plane, W, H, 3, 3, CornerMethod::Harris, 0.04, 255.0);
            select_corners(&r, W, H, 0.01, 10.0, 2000)
        })
    });
    c.bench_function("FAST t20 nms/1080p gray", |b| {
        b.iter(|| fast9(black_box(&g), W, H, 20, true))
    });
}

criterion_group!(benches, corners);
criterion_main!(benches);
