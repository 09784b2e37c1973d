//! Synthetic test frames for the motion operators: a smooth random texture (a sum of Gaussian
//! blobs) rendered exactly under any affine map, so the true motion between two renderings is
//! known analytically.

use ocellus_engine::value::{Channels, Image};

/// splitmix64 step.
fn next(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn uniform(state: &mut u64) -> f64 {
    (next(state) >> 11) as f64 / (1u64 << 53) as f64
}

/// Renders a `width × height` gray f32 image (values about 0–1) of a random blob texture
/// (seeded by `seed`, blob σ `sigma` px, one blob per `4σ²` px² on average) seen through
/// `map`: pixel (x, y) shows the texture at `(a·x + b·y + c, d·x + e·y + f)` for
/// `map = [a, b, c, d, e, f]`. Two renderings with maps `M` and `M∘T` differ by the motion
/// `T⁻¹`.
pub fn blob_texture(
    width: usize,
    height: usize,
    sigma: f64,
    seed: u64,
    map: [f64; 6],
) -> Result<Image, String> {
    // Texture-space bounding box of the image (plus a margin).
    let corners = [
        (0.0, 0.0),
        (width as f64, 0.0),
        (0.0, height as f64),
        (width as f64, height as f64),
    ];
    let tx = |x: f64, y: f64| {
        (
            map[0] * x + map[1] * y + map[2],
            map[3] * x + map[4] * y + map[5],
        )
    };
    let (mut lo, mut hi) = ((f64::MAX, f64::MAX), (f64::MIN, f64::MIN));
    for (x, y) in corners {
        let (u, v) = tx(x, y);
        lo = (lo.0.min(u), lo.1.min(v));
        hi = (hi.0.max(u), hi.1.max(v));
    }
    let margin = 4.0 * sigma;
    // Blobs sit on a jittered grid so the texture is dense and even; the grid is anchored at
    // the texture origin so every rendering sees the same blobs.
    let step = 2.0 * sigma;
    let i0 = ((lo.0 - margin) / step).floor() as i64;
    let i1 = ((hi.0 + margin) / step).ceil() as i64;
    let j0 = ((lo.1 - margin) / step).floor() as i64;
    let j1 = ((hi.1 + margin) / step).ceil() as i64;
    let mut data = vec![0.0f64; width * height];
    // Inverse map, texture → image, to find the pixels a blob touches.
    let det = map[0] * map[4] - map[1] * map[3];
    let inv = [map[4] / det, -map[1] / det, -map[3] / det, map[0] / det];
    let reach = 3.5 * sigma * (inv[0].abs() + inv[1].abs()).max(inv[2].abs() + inv[3].abs());
    let k = -0.5 / (sigma * sigma);
    for j in j0..=j1 {
        for i in i0..=i1 {
            // Per-cell random stream: independent of the rendering window.
            let mut cell = seed
                ^ (i as u64).wrapping_mul(0x1000_0000_01B3)
                ^ (j as u64).wrapping_mul(0x9E37_79B9);
            let _ = next(&mut cell);
            let cx = (i as f64 + uniform(&mut cell)) * step;
            let cy = (j as f64 + uniform(&mut cell)) * step;
            let amp = uniform(&mut cell) * 2.0 - 1.0;
            let (du, dv) = (cx - map[2], cy - map[5]);
            let px = inv[0] * du + inv[1] * dv;
            let py = inv[2] * du + inv[3] * dv;
            let xa = (px - reach).floor().max(0.0) as usize;
            let xb = ((px + reach).ceil().max(-1.0) + 1.0).min(width as f64) as usize;
            let ya = (py - reach).floor().max(0.0) as usize;
            let yb = ((py + reach).ceil().max(-1.0) + 1.0).min(height as f64) as usize;
            for y in ya..yb {
                for x in xa..xb {
                    let (u, v) = tx(x as f64, y as f64);
                    let d2 = (u - cx) * (u - cx) + (v - cy) * (v - cy);
                    data[y * width + x] += amp * (k * d2).exp();
                }
            }
        }
    }
    let samples = data.iter().map(|&v| (0.5 + 0.35 * v) as f32).collect();
    Image::from_f32(width, height, Channels::Gray, samples).map_err(|e| e.to_string())
}
