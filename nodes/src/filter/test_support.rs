//! Helpers shared by the filter tests: every border mode, and deterministic random images.

use ocellus_engine::value::{Channels, Image};

use super::border::BorderMode;

/// Every border mode, in OpenCV's order.
pub const MODES: [BorderMode; 5] = [
    BorderMode::Constant,
    BorderMode::Wrap,
    BorderMode::Reflect,
    BorderMode::Reflect101,
    BorderMode::Clamp,
];

/// Deterministic pseudo-random numbers in 0..1 (splitmix64 of a counter).
pub fn randoms(seed: u64, n: usize) -> Vec<f64> {
    let mut state = seed;
    (0..n)
        .map(|_| {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        })
        .collect()
}

/// A random u8 image with samples uniform in 0..=255.
pub fn random_u8(w: usize, h: usize, channels: Channels, seed: u64) -> Image {
    let n = w * h * channels.count();
    let data = randoms(seed, n).iter().map(|r| (r * 256.0) as u8).collect();
    match Image::from_u8(w, h, channels, data) {
        Ok(image) => image,
        Err(e) => panic!("random test image: {e}"),
    }
}
