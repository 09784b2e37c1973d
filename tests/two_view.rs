//! The two-view reconstruction example `graphs/two_view.ron`: its fixture (two rendered views of
//! a known scene and their camera) is reproduced bit for bit by the generator in
//! `ocellus_nodes::geometry::synthetic`, and the graph's pose and points agree with the scene
//! the views were rendered from. A planar pair makes the graph report a homography.
//!
//! To regenerate the fixture after changing the generator, run this test with
//! `OCELLUS_WRITE_FIXTURES=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::sync::Arc;

use common::root;
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use ocellus_engine::value::{Pose, Value};
use ocellus_nodes::geometry::synthetic::{two_view_cameras, two_view_fixture, two_view_scene};

#[test]
fn generated_two_view_fixture_is_reproducible() {
    let (left, right, camera) = two_view_fixture();
    let data = root().join("graphs/data");
    if std::env::var_os("OCELLUS_WRITE_FIXTURES").is_some() {
        ocellus_engine::image_io::write_image(&data.join("two_view_left.png"), &left).unwrap();
        ocellus_engine::image_io::write_image(&data.join("two_view_right.png"), &right).unwrap();
        ocellus_engine::emit::emit_value(
            &data,
            "two_view_camera",
            &Value::Camera(Arc::new(camera.clone())),
        )
        .unwrap();
    }
    let limits = ocellus_engine::image_io::DecodeLimits::default();
    for (name, image) in [("two_view_left.png", &left), ("two_view_right.png", &right)] {
        let path = data.join(name);
        let kept = ocellus_engine::image_io::read_image(&path, &limits).unwrap();
        assert_eq!(
            &kept,
            image,
            "{} differs from its generator",
            path.display()
        );
        let size = std::fs::metadata(&path).unwrap().len();
        assert!(size < 200_000, "{name} is {size} bytes");
    }
    let dir = std::env::temp_dir().join(format!("ocellus-two-view-{}", std::process::id()));
    let files =
        ocellus_engine::emit::emit_value(&dir, "camera", &Value::Camera(Arc::new(camera))).unwrap();
    assert_eq!(
        std::fs::read_to_string(&files[0]).unwrap(),
        std::fs::read_to_string(data.join("two_view_camera.json")).unwrap(),
        "two_view_camera.json differs from its generator"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

fn run(graph: &str, overrides: &[&str]) -> Vec<(String, Value)> {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    ocellus_engine::testing::run_graph(&registry, root().join(graph), 2, overrides)
        .unwrap_or_else(|e| panic!("{graph}: {e}"))
        .outputs
}

fn output<'a>(outputs: &'a [(String, Value)], name: &str) -> &'a Value {
    &outputs.iter().find(|(n, _)| n == name).unwrap().1
}

fn rt(pose: &Pose) -> (Matrix3<f64>, Vector3<f64>) {
    let [w, x, y, z] = pose.rotation;
    let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
    (
        *q.to_rotation_matrix().matrix(),
        Vector3::from(pose.translation),
    )
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

#[test]
fn two_view_graph_recovers_the_rendered_motion_and_scene() {
    let outputs = run("graphs/two_view.ron", &[]);
    let Value::Text(model) = output(&outputs, "model") else {
        panic!("model");
    };
    assert_eq!(&**model, "essential");
    let Value::Pose(pose) = output(&outputs, "pose") else {
        panic!("pose");
    };
    let (r, t) = rt(pose);
    let (_, c2) = two_view_cameras();
    let r_err = {
        let m = r.transpose() * c2.r;
        ((m.trace() - 1.0) / 2.0)
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    };
    let t_err = angle_deg(&t, &c2.t);
    assert!(r_err < 0.5, "rotation error {r_err}°");
    assert!(t_err < 2.0, "translation direction error {t_err}°");
    // Points, scaled by the true baseline, lie on the scene's surfaces.
    let Value::PointCloud(cloud) = output(&outputs, "points") else {
        panic!("points");
    };
    let Value::Integer(inliers) = output(&outputs, "inliers") else {
        panic!("inliers");
    };
    assert_eq!(cloud.positions.len() as i64, *inliers);
    assert!(*inliers >= 150, "{inliers} inliers");
    let scale = c2.t.norm();
    let scene = two_view_scene();
    let mut rel: Vec<f64> = cloud
        .positions
        .iter()
        .map(|p| {
            let x = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) * scale;
            let d = scene
                .iter()
                .map(|q| q.distance(&x))
                .fold(f64::INFINITY, f64::min);
            d / x.norm().max(1e-9)
        })
        .collect();
    rel.sort_by(f64::total_cmp);
    let median = rel[rel.len() / 2];
    let p90 = rel[rel.len() * 9 / 10];
    assert!(median < 0.005, "median relative distance {median}");
    assert!(p90 < 0.02, "90th percentile relative distance {p90}");
}

#[test]
fn a_planar_pair_is_reported_as_a_homography() {
    // `--set` paths resolve against the working directory, not the graph's folder.
    let data = root().join("graphs/data");
    let left = format!("left.path={}", data.join("features_left.png").display());
    let right = format!("right.path={}", data.join("features_right.png").display());
    let outputs = run("graphs/two_view.ron", &[&left, &right]);
    let Value::Text(model) = output(&outputs, "model") else {
        panic!("model");
    };
    assert_eq!(&**model, "homography");
    let Value::Metrics(report) = output(&outputs, "report") else {
        panic!("report");
    };
    assert_eq!(report.get("planar_or_rotation"), Some(&1.0));
}
