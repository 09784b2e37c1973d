//! The ray-casting example: its fixture `graphs/data/bumpy_sphere.ply` is reproduced by the
//! generator below, and `graphs/raycast.ron` gives the depth a direct cast of the generated mesh
//! gives, with a silhouette of the sphere's analytic size.
//!
//! To regenerate the fixture after changing the generator, run this test with
//! `OCELLUS_WRITE_FIXTURES=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::sync::Arc;

use common::{root, temp_dir};
use ocellus_engine::value::{Mesh, PixelData, Value};
use ocellus_nodes::render::bvh::{BvhOptions, build_bvh};
use ocellus_nodes::render::primitives::bumpy_icosphere;
use ocellus_nodes::render::raycast::{LookAtCamera, raycast_depth};

/// The mesh of `graphs/data/bumpy_sphere.ply`.
fn fixture_mesh() -> Mesh {
    Mesh {
        normals: None,
        ..bumpy_icosphere(4, 0.05, 1)
    }
}

#[test]
fn raycast_fixture_is_reproducible() {
    let dir = temp_dir("raycast_fixture");
    let files = ocellus_engine::emit::emit_value(
        &dir,
        "bumpy_sphere",
        &Value::Mesh(Arc::new(fixture_mesh())),
    )
    .unwrap();
    let ply = files
        .iter()
        .find(|p| p.extension().is_some_and(|e| e == "ply"))
        .unwrap();
    let generated = std::fs::read(ply).unwrap();
    let path = root().join("graphs/data/bumpy_sphere.ply");
    if std::env::var_os("OCELLUS_WRITE_FIXTURES").is_some() {
        std::fs::write(&path, &generated).unwrap();
    }
    let stored = std::fs::read(&path).unwrap();
    assert!(stored.len() < 200_000);
    assert!(
        stored == generated,
        "graphs/data/bumpy_sphere.ply differs from the generator"
    );
}

#[test]
fn raycast_graph_matches_a_direct_cast_and_the_analytic_silhouette() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let report =
        ocellus_engine::testing::run_graph(&registry, root().join("graphs/raycast.ron"), 2, &[])
            .unwrap();
    let output = |name: &str| {
        report
            .outputs
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.clone())
            .unwrap()
    };
    let Value::Image(depth) = output("depth") else {
        panic!("depth is not an image")
    };
    let Value::Integer(hits) = output("hits") else {
        panic!("hits is not an Integer")
    };
    let PixelData::F32(depth) = depth.data() else {
        panic!("depth is not f32")
    };
    // The same cast straight from the generator (the file holds the same f32 positions).
    let bvh = build_bvh(Arc::new(fixture_mesh()), &BvhOptions::default()).unwrap();
    let camera =
        LookAtCamera::new(320, 240, 45.0, [0.0, 0.0, -3.0], [0.0; 3], [0.0, 1.0, 0.0]).unwrap();
    let (direct, direct_hits) = raycast_depth(&bvh, &camera);
    assert_eq!(hits as usize, direct_hits);
    assert_eq!(depth, &direct);
    // Every hit lies on the bumpy sphere (radius within 1 ± 0.05) in front of the camera;
    // misses are +inf.
    for (i, &d) in depth.iter().enumerate() {
        if d.is_finite() {
            let ray = camera.ray(i % 320, i / 320);
            let p: Vec<f32> = (0..3)
                .map(|k| ray.origin[k] + d * ray.direction[k])
                .collect();
            let r = p.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((0.94..=1.06).contains(&r), "pixel {i}: radius {r}");
        } else {
            assert_eq!(d, f32::INFINITY);
        }
    }
    // The silhouette of a sphere of radius ≈ 1 seen from 3: a disc of radius f·tan(asin(1/3)).
    let r_px = camera.focal_px * (1.0f64 / 3.0).asin().tan();
    let disc = std::f64::consts::PI * r_px * r_px;
    let rel = (hits as f64 - disc).abs() / disc;
    assert!(rel < 0.1, "hits {hits} vs disc {disc:.0}");
}
