//! Motion benchmarks: pyramidal KLT tracking of 2000 points between two 1080p u8 renderings of a
//! smooth random texture shifted by a known sub-pixel translation (like OpenCV's
//! `calcOpticalFlowPyrLK` with a 21×21 window and 3 levels). Compare single-threaded with
//! `RAYON_NUM_THREADS=1 cargo bench -p ocellus-nodes --bench motion`.
//!
//! With `OCELLUS_MOTION_FRAMES=<folder>` set, the two frames are also written there as raw u8
//! (`previous.u8`, `next.u8`, 1920×1080) and the points as `points.f32` (x, y pairs), so other
//! implementations can be timed on the same input.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ocellus_engine::value::{Channels, Image, PixelData};
use ocellus_nodes::video::klt::{KltSettings, track_klt};
use ocellus_nodes::video::synth::blob_texture;

/// Known shift of the content between the frames, px.
const SHIFT: (f64, f64) = (2.3, -1.6);

fn frame(map: [f64; 6]) -> Image {
    let image = match blob_texture(1920, 1080, 3.0, 11, map) {
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
    match Image::from_u8(1920, 1080, Channels::Gray, bytes) {
        Ok(image) => image,
        Err(e) => panic!("{e}"),
    }
}

fn klt(c: &mut Criterion) {
    let a = frame([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let b = frame([1.0, 0.0, -SHIFT.0, 0.0, 1.0, -SHIFT.1]);
    // 2000 points on a 50 × 40 grid inside a 40 px margin.
    let mut points = Vec::new();
    for j in 0..40 {
        for i in 0..50 {
            points.push([40.0 + i as f32 * 36.7 + 0.3, 40.0 + j as f32 * 25.0 + 0.7]);
        }
    }
    if let Ok(dir) = std::env::var("OCELLUS_MOTION_FRAMES") {
        let dir = std::path::Path::new(&dir);
        for (name, image) in [("previous.u8", &a), ("next.u8", &b)] {
            if let PixelData::U8(v) = image.data() {
                let _ = std::fs::write(dir.join(name), v);
            }
        }
        let raw: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let _ = std::fs::write(dir.join("points.f32"), raw);
    }
    let settings = KltSettings::default();
    let tracks = match track_klt(&a, &b, &points, &settings) {
        Ok(t) => t,
        Err(e) => panic!("{e}"),
    };
    let mut errors: Vec<f32> = points
        .iter()
        .zip(&tracks)
        .filter(|(_, t)| t.tracked)
        .map(|(p, t)| {
            ((t.x - p[0] - SHIFT.0 as f32).powi(2) + (t.y - p[1] - SHIFT.1 as f32).powi(2)).sqrt()
        })
        .collect();
    errors.sort_by(f32::total_cmp);
    println!(
        "klt: {} of {} tracked, median end-point error {:.4} px",
        errors.len(),
        points.len(),
        errors.get(errors.len() / 2).copied().unwrap_or(f32::NAN)
    );
    let mut group = c.benchmark_group("klt");
    group.sample_size(10);
    group.bench_function(
        "1080p u8, 2000 points, 21x21, 3 levels, fb check",
        |bench| {
            bench.iter(|| track_klt(black_box(&a), black_box(&b), black_box(&points), &settings))
        },
    );
    let no_fb = KltSettings {
        forward_backward: 0.0,
        ..settings
    };
    group.bench_function("1080p u8, 2000 points, 21x21, 3 levels, no fb", |bench| {
        bench.iter(|| track_klt(black_box(&a), black_box(&b), black_box(&points), &no_fb))
    });
    group.finish();
}

criterion_group!(benches, klt);
criterion_main!(benches);
