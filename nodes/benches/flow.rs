//! Dense optical flow benchmarks: Horn–Schunck and dense Lucas–Kanade between two 640×480 u8
//! renderings of a smooth random texture under a known motion (a 1.5° rotation about the centre
//! plus a (2.4, −1.3) px shift, up to ~6 px), the kind of pair OpenCV's
//! `calcOpticalFlowFarneback` and `DISOpticalFlow` are timed on. The mean end-point error over
//! the pixels 10 px inside the frame is printed. Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench flow`.
//!
//! With `OCELLUS_FLOW_FRAMES=<folder>` set, the frames are also written there as raw u8
//! (`previous.u8`, `next.u8`, 640×480) and the true flow as `truth.f32` (u, v interleaved), so
//! other implementations can be measured on the same input.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Image, PixelData};
use ocellus_nodes::video::dense_lk::{LkSettings, flow_lk};
use ocellus_nodes::video::flow::FlowField;
use ocellus_nodes::video::horn_schunck::{HsSettings, flow_horn_schunck};
use ocellus_nodes::video::synth::blob_texture;

const W: usize = 640;
const H: usize = 480;

/// Texture map of `next`: content rotated by 1.5° about the centre and shifted by (2.4, −1.3).
fn motion() -> [f64; 6] {
    let t = 1.5f64.to_radians();
    let (c, s) = (t.cos(), t.sin());
    let (cx, cy) = (W as f64 / 2.0 + 2.4, H as f64 / 2.0 - 1.3);
    // next(x) = tex(R⁻¹ (x − c') + c) with c' = c + shift.
    let (ox, oy) = (W as f64 / 2.0, H as f64 / 2.0);
    [c, s, ox - c * cx - s * cy, -s, c, oy + s * cx - c * cy]
}

fn frame(map: [f64; 6]) -> Image {
    let image = match blob_texture(W, H, 3.0, 21, map) {
        Ok(image) => image,
        Err(e) => panic!("rendering the benchmark input: {e}"),
    };
    let PixelData::F32(v) = image.data() else {
        panic!("texture is f32")
    };
    let bytes = v
        .iter()
        .map(|&s| (s * 255.0).round().clamp(0.0, 255.0) as u8)
        .collect();
    match Image::from_u8(W, H, Channels::Gray, bytes) {
        Ok(image) => image,
        Err(e) => panic!("{e}"),
    }
}

/// The true flow of [`motion`]: the texture point p seen at p in `previous` is at
/// `A⁻¹ (p − t)` in `next`.
fn truth() -> FlowField {
    let m = motion();
    let det = m[0] * m[4] - m[1] * m[3];
    let mut f = FlowField::zeros(W, H);
    for y in 0..H {
        for x in 0..W {
            let (px, py) = (x as f64 - m[2], y as f64 - m[5]);
            f.u[y * W + x] = ((m[4] * px - m[1] * py) / det - x as f64) as f32;
            f.v[y * W + x] = ((-m[3] * px + m[0] * py) / det - y as f64) as f32;
        }
    }
    f
}

fn epe(flow: &FlowField, truth: &FlowField) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for y in 10..H - 10 {
        for x in 10..W - 10 {
            let i = y * W + x;
            let (du, dv) = (flow.u[i] - truth.u[i], flow.v[i] - truth.v[i]);
            sum += f64::from((du * du + dv * dv).sqrt());
            n += 1;
        }
    }
    sum / n as f64
}

fn flow(c: &mut Criterion) {
    let a = frame([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let b = frame(motion());
    let truth = truth();
    if let Ok(dir) = std::env::var("OCELLUS_FLOW_FRAMES") {
        let dir = std::path::Path::new(&dir);
        for (name, image) in [("previous.u8", &a), ("next.u8", &b)] {
            if let PixelData::U8(v) = image.data() {
                let _ = std::fs::write(dir.join(name), v);
            }
        }
        let raw: Vec<u8> = truth
            .u
            .iter()
            .zip(&truth.v)
            .flat_map(|(u, v)| [u.to_le_bytes(), v.to_le_bytes()])
            .flatten()
            .collect();
        let _ = std::fs::write(dir.join("truth.f32"), raw);
    }
    let hs = HsSettings::default();
    let lk = LkSettings::default();
    let fast_hs = HsSettings {
        warps: 1,
        iterations: 10,
        ..hs
    };
    let fast_lk = LkSettings {
        iterations: 2,
        ..lk
    };
    for (name, f) in [
        ("horn_schunck default", flow_horn_schunck(&a, &b, &hs)),
        (
            "horn_schunck 1 warp, 10 iterations",
            flow_horn_schunck(&a, &b, &fast_hs),
        ),
        ("lk default", flow_lk(&a, &b, &lk)),
        ("lk 2 iterations", flow_lk(&a, &b, &fast_lk)),
    ] {
        match f {
            Ok(f) => println!("{name}: mean end-point error {:.4} px", epe(&f, &truth)),
            Err(e) => panic!("{e}"),
        }
    }
    let mut group = c.benchmark_group("flow");
    group.sample_size(10);
    group.bench_function("640x480 u8, horn_schunck default", |bench| {
        bench.iter(|| flow_horn_schunck(black_box(&a), black_box(&b), &hs))
    });
    group.bench_function("640x480 u8, horn_schunck 1 warp 10 iterations", |bench| {
        bench.iter(|| flow_horn_schunck(black_box(&a), black_box(&b), &fast_hs))
    });
    group.bench_function("640x480 u8, lk default", |bench| {
        bench.iter(|| flow_lk(black_box(&a), black_box(&b), &lk))
    });
    group.bench_function("640x480 u8, lk 2 iterations", |bench| {
        bench.iter(|| flow_lk(black_box(&a), black_box(&b), &fast_lk))
    });
    group.finish();
}

criterion_group!(benches, flow);
criterion_main!(benches);
