//! Ray tracer speed: prepares a scene with one 1.3 M-triangle bumpy icosphere
//! (`bumpy_icosphere(8, 0.05, 1)`, Lambertian) and renders it with `render_trace` through a
//! 1920×1080 pinhole camera at (0, 0, −2.6) looking at the origin with a 60° horizontal field of
//! view (the raycast benchmark's camera). Default: Whitted with no lights at 1 sample per pixel,
//! so the time is intersections plus hit records. Prints the scene preparation time (world
//! transform and BVH build), the best and median render time, and Mrays/s counting every
//! primary ray: `spp` jittered rays per pixel plus the pixel-centre ray of the depth/normal/id
//! outputs.
//!
//! `cargo run --release -p ocellus-nodes --example trace -- [SUBDIVISIONS] [REPEATS] [SPP]
//! [whitted|path]` (threads: `RAYON_NUM_THREADS`).

use std::sync::Arc;
use std::time::Instant;

use ocellus_engine::value::{Material, Pose, Scene, SceneObject, Shape};
use ocellus_nodes::render::primitives::bumpy_icosphere;
use ocellus_nodes::render::raycast::LookAtCamera;
use ocellus_nodes::render::scene::{View, scene_camera_from_look_at};
use ocellus_nodes::render::trace::{Integrator, TraceOptions, TraceScene, render_trace};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let subdivisions: u32 = args.first().and_then(|s| s.parse().ok()).unwrap_or(8);
    let repeats: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(3).max(1);
    let spp: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let integrator = match args.get(3).map(String::as_str) {
        Some("path") => Integrator::Path,
        _ => Integrator::Whitted,
    };
    let (w, h) = (1920usize, 1080usize);
    let fov_x = 60f64.to_radians();
    let fov_y_deg = (2.0 * ((fov_x / 2.0).tan() * h as f64 / w as f64).atan()).to_degrees();
    let camera = LookAtCamera::new(w, h, fov_y_deg, [0.0, 0.0, -2.6], [0.0; 3], [0.0, 1.0, 0.0])?;
    let mesh = Arc::new(bumpy_icosphere(subdivisions, 0.05, 1));
    let triangles = mesh.triangles.len();
    let scene = Scene {
        materials: vec![Material {
            roughness: 1.0,
            ..Material::default()
        }],
        objects: vec![SceneObject {
            name: "sphere".into(),
            shape: Shape::Mesh(mesh),
            world_from_object: Pose::IDENTITY,
            scale: 1.0,
            material: 0,
        }],
        lights: vec![],
        cameras: vec![scene_camera_from_look_at(&camera)],
    };
    let view = View::new(&scene.cameras[0])?;
    let t = Instant::now();
    let prepared = TraceScene::new(&scene, [0.0; 3])?;
    let prepare = t.elapsed().as_secs_f64();
    let options = TraceOptions {
        integrator,
        spp,
        ..TraceOptions::default()
    };
    let mut times = Vec::new();
    let mut hits = 0;
    for _ in 0..repeats {
        let t = Instant::now();
        let out = render_trace(&prepared, &view, &options)?;
        times.push(t.elapsed().as_secs_f64());
        hits = out.hits;
    }
    let best = times.iter().cloned().fold(f64::INFINITY, f64::min);
    let rays = (w * h) as f64 * (f64::from(spp) + 1.0);
    println!(
        "{triangles} triangles; {:?}, spp {spp}; threads {}",
        integrator,
        rayon::current_num_threads()
    );
    println!("prepare (world transform + BVH): {:.1} ms", prepare * 1e3);
    println!(
        "render: best {:.1} ms, median {:.1} ms; {:.2} Mrays/s (best, {} primary rays: {} jittered + {} pixel-centre); hit ratio {:.3}",
        best * 1e3,
        median(times.clone()) * 1e3,
        rays / best / 1e6,
        rays,
        (w * h) as f64 * f64::from(spp),
        w * h,
        hits as f64 / (w * h) as f64
    );
    Ok(())
}
