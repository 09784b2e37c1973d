//! Primary-ray casting benchmark: builds the BVH over a 1.3 M-triangle bumpy icosphere
//! (subdivision 8, the size of `../shared/anchors/bench_raycast.py`'s mesh) and casts one ray
//! per pixel of a 1920×1080 pinhole camera at (0, 0, −2.6) looking at the origin with a 60°
//! horizontal field of view (the anchor's camera). Prints the best and median build time, cast
//! time, Mrays/s and the hit ratio.
//!
//! `cargo run --release -p ocellus-nodes --example raycast -- [SUBDIVISIONS] [REPEATS]
//! [MAX_LEAF_SIZE] [TRAVERSAL_COST] [BINS]`
//! (threads: `RAYON_NUM_THREADS`).

use std::sync::Arc;
use std::time::Instant;

use ocellus_nodes::render::bvh::{BvhOptions, build_bvh};
use ocellus_nodes::render::primitives::bumpy_icosphere;
use ocellus_nodes::render::raycast::{LookAtCamera, raycast_depth};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let subdivisions: u32 = args.first().and_then(|s| s.parse().ok()).unwrap_or(8);
    let repeats: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(5).max(1);
    let defaults = BvhOptions::default();
    let options = BvhOptions {
        max_leaf_size: args
            .get(2)
            .and_then(|s| s.parse().ok())
            .unwrap_or(defaults.max_leaf_size),
        traversal_cost: args
            .get(3)
            .and_then(|s| s.parse().ok())
            .unwrap_or(defaults.traversal_cost),
        bins: args
            .get(4)
            .and_then(|s| s.parse().ok())
            .unwrap_or(defaults.bins),
    };
    let mesh = Arc::new(bumpy_icosphere(subdivisions, 0.05, 3));
    let (w, h) = (1920usize, 1080usize);
    let fov_x = 60f64.to_radians();
    let fov_y_deg = (2.0 * ((fov_x / 2.0).tan() * h as f64 / w as f64).atan()).to_degrees();
    let camera = LookAtCamera::new(w, h, fov_y_deg, [0.0, 0.0, -2.6], [0.0; 3], [0.0, 1.0, 0.0])?;
    let mut builds = Vec::new();
    let mut bvh = None;
    for _ in 0..repeats {
        let t = Instant::now();
        let b = build_bvh(mesh.clone(), &options).map_err(|e| e.to_string())?;
        builds.push(t.elapsed().as_secs_f64());
        bvh = Some(b);
    }
    let bvh = bvh.ok_or("no build")?;
    let stats = bvh.stats();
    let mut casts = Vec::new();
    let mut hits = 0;
    for _ in 0..repeats {
        let t = Instant::now();
        let (_, n) = raycast_depth(&bvh, &camera);
        casts.push(t.elapsed().as_secs_f64());
        hits = n;
    }
    let rays = (w * h) as f64;
    let best = casts.iter().cloned().fold(f64::INFINITY, f64::min);
    println!(
        "{} triangles; BVH {} nodes, {} leaves, depth {}, largest leaf {}",
        mesh.triangles.len(),
        stats.nodes,
        stats.leaves,
        stats.max_depth,
        stats.max_leaf_size
    );
    println!(
        "build: best {:.1} ms, median {:.1} ms",
        builds.iter().cloned().fold(f64::INFINITY, f64::min) * 1e3,
        median(builds.clone()) * 1e3
    );
    println!(
        "cast {}x{}: best {:.1} ms, median {:.1} ms, {:.2} Mrays/s (median), hit ratio {:.3}",
        w,
        h,
        best * 1e3,
        median(casts.clone()) * 1e3,
        rays / median(casts) / 1e6,
        hits as f64 / rays
    );
    Ok(())
}
