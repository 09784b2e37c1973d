//! Rasterizer frame-time benchmark: a 1.3 M-triangle bumpy icosphere (subdivision 8, the mesh of
//! the `raycast` example) with a Lambert material under one directional light, drawn at
//! 1920×1080 from (0, 0, −2.6) looking at the origin with a 60° horizontal field of view (the
//! `raycast` example's camera). Prints the best and median frame time of `rasterize` (scene
//! validation, vertex transform, setup, binning, shadow map, tiles, shading) and the hit count.
//!
//! `cargo run --release -p ocellus-nodes --example rasterize -- [SUBDIVISIONS] [REPEATS]
//! [SAMPLES] [CULL] [SHADOW_MAP_SIZE]` (CULL: none, back or front; threads: `RAYON_NUM_THREADS`).

use std::sync::Arc;
use std::time::Instant;

use ocellus_engine::params::ParamKind;
use ocellus_engine::params::ParamValue;
use ocellus_engine::value::{Light, Material, Pose, Scene, SceneObject, Shape};
use ocellus_nodes::render::primitives::bumpy_icosphere;
use ocellus_nodes::render::raster::{Cull, RasterOptions, rasterize};
use ocellus_nodes::render::raycast::LookAtCamera;
use ocellus_nodes::render::scene::scene_camera_from_look_at;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let subdivisions: u32 = args.first().and_then(|s| s.parse().ok()).unwrap_or(8);
    let repeats: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(5).max(1);
    let samples: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let cull = match args.get(3) {
        Some(s) => Cull::from_param(&ParamValue::Str(s.clone()))
            .ok_or_else(|| format!("CULL must be none, back or front, got {s}"))?,
        None => Cull::None,
    };
    let shadow_map_size: u32 = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let mesh = Arc::new(bumpy_icosphere(subdivisions, 0.05, 3));
    let (w, h) = (1920usize, 1080usize);
    let fov_x = 60f64.to_radians();
    let fov_y_deg = (2.0 * ((fov_x / 2.0).tan() * h as f64 / w as f64).atan()).to_degrees();
    let camera = LookAtCamera::new(w, h, fov_y_deg, [0.0, 0.0, -2.6], [0.0; 3], [0.0, 1.0, 0.0])?;
    let scene = Scene {
        materials: vec![Material::default()],
        objects: vec![SceneObject {
            name: "icosphere".into(),
            shape: Shape::Mesh(mesh.clone()),
            world_from_object: Pose::IDENTITY,
            scale: 1.0,
            material: 0,
        }],
        lights: vec![Light::Directional {
            direction: [0.3, -0.8, 0.5],
            irradiance: [3.0; 3],
        }],
        cameras: vec![scene_camera_from_look_at(&camera)],
    };
    let options = RasterOptions {
        cull,
        samples,
        shadow_map_size,
        ..RasterOptions::default()
    };
    let mut frames = Vec::new();
    let mut hits = 0;
    for _ in 0..repeats {
        let t = Instant::now();
        let out = rasterize(&scene, 0, &options)?;
        frames.push(t.elapsed().as_secs_f64());
        hits = out.hits;
    }
    let best = frames.iter().cloned().fold(f64::INFINITY, f64::min);
    println!(
        "{} triangles, {}x{}, samples {samples}, cull {}, shadow map {shadow_map_size}, \
         threads {}: best {:.1} ms, median {:.1} ms per frame; hit ratio {:.3}",
        mesh.triangles.len(),
        w,
        h,
        cull.name(),
        rayon::current_num_threads(),
        best * 1e3,
        median(frames) * 1e3,
        hits as f64 / (w * h) as f64
    );
    Ok(())
}
