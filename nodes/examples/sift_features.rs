//! SIFT on one image file: prints the keypoint count and the detect+describe time, and optionally
//! writes keypoints and descriptors as little-endian f32 records.
//!
//! `cargo run --release -p ocellus-nodes --example sift_features -- IMAGE [MAX_FEATURES] [OUT]`
//!
//! OUT holds a u32 count, then per keypoint x, y, size, angle, response, octave (as f32) and the
//! 128 descriptor values.

use std::io::Write;
use std::time::Instant;

use ocellus_engine::value::{Channels, Descriptors, Image};
use ocellus_nodes::describe::sift::{SiftParams, sift_detect_and_compute};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: sift_features IMAGE [MAX_FEATURES] [OUT]");
        std::process::exit(2);
    };
    let max_features: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0);
    let gray = match image::open(path) {
        Ok(img) => img.to_luma8(),
        Err(e) => {
            eprintln!("{path}: {e}");
            std::process::exit(1);
        }
    };
    let (w, h) = (gray.width() as usize, gray.height() as usize);
    let image = match Image::from_u8(w, h, Channels::Gray, gray.into_raw()) {
        Ok(i) => i,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
    };
    let params = SiftParams {
        max_features,
        ..SiftParams::default()
    };
    let mut best = f64::INFINITY;
    let mut result = None;
    for _ in 0..5 {
        let t = Instant::now();
        let r = sift_detect_and_compute(&image, &params);
        best = best.min(t.elapsed().as_secs_f64());
        result = Some(r);
    }
    let (keypoints, descriptors) = match result {
        Some(Ok(r)) => r,
        Some(Err(e)) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
        None => return,
    };
    println!(
        "{path}: {} keypoints, best of 5: {:.1} ms",
        keypoints.len(),
        best * 1e3
    );
    if let Some(out) = args.get(3) {
        let Descriptors::Float { data, .. } = &descriptors else {
            return;
        };
        let mut bytes = Vec::new();
        bytes.extend_from_slice(&(keypoints.len() as u32).to_le_bytes());
        for (k, d) in keypoints.iter().zip(data.chunks_exact(128)) {
            for v in [k.x, k.y, k.size, k.angle, k.response, k.octave as f32] {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            for v in d {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        if let Err(e) = std::fs::File::create(out).and_then(|mut f| f.write_all(&bytes)) {
            eprintln!("{out}: {e}");
            std::process::exit(1);
        }
    }
}
