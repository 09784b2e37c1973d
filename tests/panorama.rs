//! `graphs/panorama.ron` against the geometry it was made with: the estimated homographies are
//! within half a pixel of the true ones, and the stitched panorama shows the scene the views were
//! cut from at the places the middle view's geometry puts it.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::root;
use ocellus_engine::value::{PixelData, Value};

/// The middle view's window onto the scene: view pixels → scene pixels (as in the graph).
const SCENE_FROM_MIDDLE: [f64; 9] = [1.0, 0.0, 480.5, 0.0, 1.0, 80.5, 0.0, 0.0, 1.0];

fn output<'a>(outputs: &'a [(String, Value)], name: &str) -> &'a Value {
    &outputs.iter().find(|(n, _)| n == name).unwrap().1
}

fn metric(outputs: &[(String, Value)], name: &str, field: &str) -> f64 {
    let Value::Metrics(m) = output(outputs, name) else {
        panic!("{name} is not Metrics")
    };
    m[field]
}

fn invert_affine(m: &[f64]) -> [f64; 9] {
    // The panorama's homography of the reference view is a pure translation.
    assert_eq!(
        (m[0], m[1], m[3], m[4], m[6], m[7], m[8]),
        (1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0)
    );
    [1.0, 0.0, -m[2], 0.0, 1.0, -m[5], 0.0, 0.0, 1.0]
}

#[test]
fn panorama_matches_the_scene() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let report =
        ocellus_engine::testing::run_graph(&registry, root().join("graphs/panorama.ron"), 2, &[])
            .unwrap();
    assert!(report.failures.is_empty(), "{:?}", report.failures);
    let outputs = &report.outputs;
    for e in ["error_01", "error_12"] {
        let err = metric(outputs, e, "corner_error_px");
        assert!(err < 0.5, "{e}: corner error {err} px");
    }
    assert_eq!(metric(outputs, "metrics", "views"), 3.0);
    assert_eq!(metric(outputs, "metrics", "reference"), 1.0);
    // Registered views agree where they overlap, to the interpolation error of a fine texture.
    let overlap_rms = metric(outputs, "metrics", "overlap_rms");
    assert!(overlap_rms < 3.0, "overlap rms {overlap_rms}");

    let Value::Image(pano) = output(outputs, "panorama") else {
        panic!()
    };
    let Value::Image(scene) = output(outputs, "scene") else {
        panic!()
    };
    let Value::Image(coverage) = output(outputs, "coverage") else {
        panic!()
    };
    let Value::List(homographies) = output(outputs, "homographies") else {
        panic!()
    };
    let Value::Matrix(middle) = &homographies.items[1] else {
        panic!()
    };
    let middle_from_pano = invert_affine(&middle.data);
    // About the scene's covered width: views span x 51..1541 of the scene.
    assert!((1450..1530).contains(&pano.width()), "{}", pano.width());
    let (PixelData::U8(p), PixelData::U8(s), PixelData::U8(c)) =
        (pano.data(), scene.data(), coverage.data())
    else {
        panic!("u8 images expected")
    };
    let (pw, sw, sh) = (pano.width(), scene.width(), scene.height());
    let mut sum_sq = 0.0;
    let mut n = 0usize;
    let mut covered = 0usize;
    for y in 0..pano.height() {
        for x in 0..pw {
            if c[y * pw + x] == 0 {
                continue;
            }
            covered += 1;
            // Panorama pixel → middle view → scene, sampled bilinearly as the views were.
            let (vx, vy) = (
                x as f64 + middle_from_pano[2],
                y as f64 + middle_from_pano[5],
            );
            let (sx, sy) = (vx + SCENE_FROM_MIDDLE[2], vy + SCENE_FROM_MIDDLE[5]);
            if sx < 0.0 || sy < 0.0 || sx > (sw - 1) as f64 || sy > (sh - 1) as f64 {
                continue;
            }
            let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(sw - 1), (y0 + 1).min(sh - 1));
            let (fx, fy) = (sx - x0 as f64, sy - y0 as f64);
            for ch in 0..3 {
                let at = |xx: usize, yy: usize| f64::from(s[(yy * sw + xx) * 3 + ch]);
                let truth = (at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx) * (1.0 - fy)
                    + (at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx) * fy;
                let d = f64::from(p[(y * pw + x) * 3 + ch]) - truth;
                sum_sq += d * d;
                n += 1;
            }
        }
    }
    let rms = (sum_sq / n as f64).sqrt();
    assert!(covered > pw * pano.height() * 3 / 4, "{covered} covered");
    assert!(n > 1_500_000, "{n} samples compared");
    assert!(rms < 3.0, "panorama vs scene: rms {rms} over {n} samples");
}
