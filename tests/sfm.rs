//! Structure from motion end to end: the default photos of `graphs/sfm.ron` are what their
//! generator renders, and `graphs/reconstruct.ron` recovers the cameras that rendered its views
//! within the accuracy users expect of SfM on clean data.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{root, temp_dir};
use ocellus_engine::value::Value;

fn run(graph: &str, overrides: &[&str]) -> Vec<(String, Value)> {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    ocellus_engine::testing::run_graph(&registry, root().join(graph), 2, overrides)
        .unwrap_or_else(|e| panic!("{graph}: {e}"))
        .outputs
}

fn metric(outputs: &[(String, Value)], output: &str, name: &str) -> f64 {
    match &outputs.iter().find(|(n, _)| n == output).unwrap().1 {
        Value::Metrics(m) => *m.get(name).unwrap_or_else(|| panic!("no metric {name}")),
        other => panic!("{output} is {}", other.port_type()),
    }
}

#[test]
fn default_photos_are_reproduced_by_their_generator() {
    let dir = temp_dir("sfm_views");
    let pattern = dir.join("view.jpg");
    let set = format!("write.path=\"{}\"", pattern.display());
    run("graphs/data/make_sfm_views.ron", &[set.as_str()]);
    for k in 0..12 {
        let name = format!("view_{k:04}.jpg");
        assert_eq!(
            std::fs::read(dir.join(&name)).unwrap(),
            std::fs::read(root().join("graphs/data/sfm_views").join(&name)).unwrap(),
            "graphs/data/sfm_views/{name} differs from what make_sfm_views.ron renders"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn reconstruction_matches_the_rendering_cameras() {
    let out = run("graphs/reconstruct.ron", &[]);
    let m = |name: &str| metric(&out, "error", name);
    // The acceptance: median rotation error < 0.1°, camera-centre error < 0.5 % of the
    // scene size after similarity alignment, reprojection RMS < 0.5 px, ≥ 90 % registered.
    assert!(
        m("rotation_error_median_deg") < 0.1,
        "{}",
        m("rotation_error_median_deg")
    );
    assert!(
        m("center_error_median_rel") < 0.005,
        "{}",
        m("center_error_median_rel")
    );
    assert!(
        m("center_error_max_rel") < 0.005,
        "{}",
        m("center_error_max_rel")
    );
    assert!(
        m("reprojection_rms_px") < 0.5,
        "{}",
        m("reprojection_rms_px")
    );
    assert!(
        m("registered_fraction") >= 0.9,
        "{}",
        m("registered_fraction")
    );
    assert!(m("points") > 1000.0, "{}", m("points"));

    // Dense: the fused mesh against the true surface (the same fusion of the renderer's exact
    // depth maps), within 5 cm in a room 8 m across. Measured: precision 0.956, recall 0.636,
    // F-score 0.764, mean distance to the truth 1.7 cm; 61 % of the pixels keep a depth.
    let e = |name: &str| metric(&out, "mesh_error", name);
    assert!(e("precision") > 0.93, "{}", e("precision"));
    assert!(e("recall") > 0.58, "{}", e("recall"));
    assert!(e("f_score") > 0.72, "{}", e("f_score"));
    assert!(e("mean_a_to_b") < 0.03, "{}", e("mean_a_to_b"));
    let d = |name: &str| metric(&out, "dense", name);
    assert_eq!(d("views"), 12.0);
    assert!(d("valid_fraction") > 0.5, "{}", d("valid_fraction"));
    // The rendering of the mesh resembles the rendering of the truth from the same viewpoint.
    let v = |name: &str| metric(&out, "view_error", name);
    assert!(v("ssim") > 0.4, "{}", v("ssim"));
}

#[test]
fn uncalibrated_sfm_estimates_the_focal_length() {
    // True focal length of the default photos: 192 / tan(25°) = 411.75 px; the prior is
    // 1.2 × 512 = 614.4 px.
    let out = run("graphs/sfm.ron", &[]);
    let r = |name: &str| metric(&out, "report", name);
    let truth = 192.0 / 25f64.to_radians().tan();
    assert_eq!(r("registered"), 12.0);
    assert!(
        (r("focal_px") - truth).abs() < 0.005 * truth,
        "{}",
        r("focal_px")
    );
    assert!(
        r("reprojection_rms_px") < 0.5,
        "{}",
        r("reprojection_rms_px")
    );
}
