//! The dense-stereo example: its fixture (`graphs/data/stereo_left.png`, `stereo_right.png`
//! and the ground-truth disparity `stereo_truth.pfm`) is reproduced by the generator below,
//! and `graphs/stereo.ron` recovers the truth on it.
//!
//! The scene is layered: a slanted textured background plane (disparity `4 + 0.02·x + 0.03·y`
//! in left pixels) and four fronto-parallel textured objects at known disparities. Both views
//! are rendered exactly from the layers — each right pixel `x′` shows the nearest layer whose
//! point at left `x = x′ + d` covers it — with seeded noise (σ ≈ 1 gray level).
//!
//! To regenerate the fixture after changing the generator, run this test with
//! `OCELLUS_WRITE_FIXTURES=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::root;
use ocellus_engine::image_io::{ImageFormat, encode_image};
use ocellus_engine::value::{Channels, Image, Metrics, Value};

const W: usize = 320;
const H: usize = 240;

/// splitmix64.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A lattice value in [−1, 1].
fn lattice(ix: i64, iy: i64, seed: u64) -> f64 {
    let h = mix(seed ^ mix((ix as u64).wrapping_mul(0x1000_0000_01B3) ^ mix(iy as u64)));
    (h >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// Smooth value noise of cell size `cell` px at the continuous point (u, v).
fn value_noise(u: f64, v: f64, cell: f64, seed: u64) -> f64 {
    let (fu, fv) = (u / cell, v / cell);
    let (iu, iv) = (fu.floor(), fv.floor());
    let (tu, tv) = (fu - iu, fv - iv);
    let (su, sv) = (tu * tu * (3.0 - 2.0 * tu), tv * tv * (3.0 - 2.0 * tv));
    let (iu, iv) = (iu as i64, iv as i64);
    let a = lattice(iu, iv, seed) * (1.0 - su) + lattice(iu + 1, iv, seed) * su;
    let b = lattice(iu, iv + 1, seed) * (1.0 - su) + lattice(iu + 1, iv + 1, seed) * su;
    a * (1.0 - sv) + b * sv
}

/// The texture of layer `seed` at scene point (u, v) (left-view pixels), gray levels.
fn texture(u: f64, v: f64, seed: u64) -> f64 {
    let octaves = [(24.0, 40.0), (8.0, 30.0), (3.0, 28.0), (1.6, 18.0)];
    128.0
        + octaves
            .iter()
            .enumerate()
            .map(|(i, &(cell, amp))| amp * value_noise(u, v, cell, seed * 16 + i as u64))
            .sum::<f64>()
}

/// A fronto-parallel object: disparity and footprint in the left view.
struct Object {
    disparity: f64,
    shape: Shape,
}

enum Shape {
    Disc { cx: f64, cy: f64, r: f64 },
    Rect { x0: f64, y0: f64, x1: f64, y1: f64 },
}

impl Object {
    fn covers(&self, x: f64, y: f64) -> bool {
        match self.shape {
            Shape::Disc { cx, cy, r } => (x - cx).powi(2) + (y - cy).powi(2) <= r * r,
            Shape::Rect { x0, y0, x1, y1 } => (x0..x1).contains(&x) && (y0..y1).contains(&y),
        }
    }
}

/// The objects, nearest (largest disparity) first.
fn objects() -> Vec<Object> {
    vec![
        Object {
            disparity: 40.75,
            shape: Shape::Disc {
                cx: 250.0,
                cy: 185.0,
                r: 32.0,
            },
        },
        Object {
            disparity: 34.25,
            shape: Shape::Disc {
                cx: 95.0,
                cy: 80.0,
                r: 46.0,
            },
        },
        Object {
            disparity: 28.0,
            shape: Shape::Rect {
                x0: 140.0,
                y0: 120.0,
                x1: 232.0,
                y1: 205.0,
            },
        },
        Object {
            disparity: 22.5,
            shape: Shape::Rect {
                x0: 205.0,
                y0: 28.0,
                x1: 300.0,
                y1: 104.0,
            },
        },
    ]
}

/// The background disparity at left pixel (x, y).
fn background_disparity(x: f64, y: f64) -> f64 {
    4.0 + 0.02 * x + 0.03 * y
}

/// Seeded noise, approximately normal with σ 1 gray level (sum of 3 uniforms).
fn noise(i: u64) -> f64 {
    let u = |k: u64| (mix(i * 3 + k) >> 11) as f64 / (1u64 << 53) as f64;
    2.0 * (u(0) + u(1) + u(2) - 1.5)
}

fn quantize(v: f64) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// Left view, right view (u8 gray) and left-view truth disparity (f32, px).
fn fixture() -> (Image, Image, Image) {
    let objs = objects();
    let mut left = Vec::with_capacity(W * H);
    let mut right = Vec::with_capacity(W * H);
    let mut truth = Vec::with_capacity(W * H);
    for y in 0..H {
        let yf = y as f64;
        for x in 0..W {
            let xf = x as f64;
            let i = (y * W + x) as u64;
            // Left: the nearest layer at (x, y).
            let (value, d) = match objs.iter().enumerate().find(|(_, o)| o.covers(xf, yf)) {
                Some((k, o)) => (texture(xf, yf, k as u64 + 1), o.disparity),
                None => (texture(xf, yf, 0), background_disparity(xf, yf)),
            };
            left.push(quantize(value + noise(2 * i)));
            truth.push(d as f32);
            // Right pixel x′: the nearest layer whose left point x′ + d covers it.
            let hit = objs.iter().enumerate().find_map(|(k, o)| {
                let u = xf + o.disparity;
                o.covers(u, yf).then(|| texture(u, yf, k as u64 + 1))
            });
            let value = hit.unwrap_or_else(|| {
                // u = x′ + 4 + 0.02·u + 0.03·y.
                let u = (xf + 4.0 + 0.03 * yf) / (1.0 - 0.02);
                texture(u, yf, 0)
            });
            right.push(quantize(value + noise(2 * i + 1)));
        }
    }
    (
        Image::from_u8(W, H, Channels::Gray, left).unwrap(),
        Image::from_u8(W, H, Channels::Gray, right).unwrap(),
        Image::from_f32(W, H, Channels::Gray, truth).unwrap(),
    )
}

#[test]
fn stereo_fixture_is_reproducible() {
    let (left, right, truth) = fixture();
    let files = [
        (
            "stereo_left.png",
            encode_image(&left, ImageFormat::Png).unwrap(),
        ),
        (
            "stereo_right.png",
            encode_image(&right, ImageFormat::Png).unwrap(),
        ),
        (
            "stereo_truth.pfm",
            encode_image(&truth, ImageFormat::Pfm).unwrap(),
        ),
    ];
    for (name, generated) in files {
        let path = root().join("graphs/data").join(name);
        if std::env::var_os("OCELLUS_WRITE_FIXTURES").is_some() {
            std::fs::write(&path, &generated).unwrap();
        }
        let stored = std::fs::read(&path).unwrap();
        assert!(stored.len() < 400_000, "{name} is {} bytes", stored.len());
        assert!(
            stored == generated,
            "graphs/data/{name} differs from the generator"
        );
    }
}

#[test]
fn stereo_graph_recovers_the_generated_disparities() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let report =
        ocellus_engine::testing::run_graph(&registry, root().join("graphs/stereo.ron"), 2, &[])
            .unwrap();
    let output = |name: &str| {
        report
            .outputs
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.clone())
            .unwrap()
    };
    let Value::Metrics(m) = output("error") else {
        panic!("error is not Metrics")
    };
    let m: &Metrics = &m;
    assert_eq!(m["known"], (W * H) as f64);
    // Occluded background next to each object (≈ 6 % of the image) and the left band whose
    // match is outside the right view have no disparity; nearly all the rest is right.
    assert!(m["bad"] < 0.12, "{m:?}");
    assert!(m["bad_matched"] < 0.01, "{m:?}");
    assert!(m["density"] > 0.88, "{m:?}");
    eprintln!("stereo fixture: {m:?}");
    assert!(m["mean_abs_error_px"] < 0.3, "{m:?}");
    // Disparities at the centre of each object: within the 0.6 px that SGM's subpixel bias
    // towards whole pixels leaves (40.75 is read as 41.26 at the disc's centre).
    let Value::Image(disp) = output("disparity") else {
        panic!("disparity is not an image")
    };
    let d = disp.as_f32().unwrap();
    for (x, y, want) in [
        (250, 185, 40.75),
        (95, 80, 34.25),
        (180, 160, 28.0),
        (260, 60, 22.5),
    ] {
        let got = d[y * W + x];
        assert!(
            (f64::from(got) - want).abs() < 0.6,
            "({x}, {y}): {got} vs {want}"
        );
    }
}
