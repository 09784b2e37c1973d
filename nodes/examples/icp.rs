//! Point-cloud evaluation on a mesh's vertices (the Stanford bunny in BENCHMARKS.md): normal
//! estimation, voxel downsampling and ICP (both methods) against a known transform.
//!
//! ```text
//! RAYON_NUM_THREADS=1 cargo run --release -p ocellus-nodes --example icp -- ../shared/data/mesh_bunny/bun_zipper.ply
//! ```
//!
//! The source is the target moved by the inverse of a known `target_from_source` (30° about the
//! oblique axis (1, −2, 0.7) plus a translation of 20 % of the bounding-box diagonal), once with
//! the same points (noise-free: exact recovery expected) and once voxel-downsampled (a different
//! sampling of the same surface). Times are the median of `REPEATS` runs after one warm-up run.

use std::path::PathBuf;
use std::time::Instant;

use nalgebra::Vector3;
use ocellus_engine::value::PointCloud;
use ocellus_nodes::io::read_mesh::read_mesh;
use ocellus_nodes::mesh::icp::{
    IcpMethod, IcpOptions, Rigid, icp, rotation_angle, rotation_from_vector,
};
use ocellus_nodes::mesh::kdtree::KdTree;
use ocellus_nodes::mesh::pointcloud::{Orientation, oriented_normals, voxel_downsample};

const REPEATS: usize = 5;

/// One warm-up run, then the median time of `REPEATS` runs, and the last result.
fn median_ms<T>(mut f: impl FnMut() -> T) -> (f64, T) {
    let mut value = f();
    let mut times = Vec::new();
    for _ in 0..REPEATS {
        let t = Instant::now();
        value = f();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    (times[REPEATS / 2], value)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let path: PathBuf = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "../shared/data/mesh_bunny/bun_zipper.ply".into())
        .into();
    let mesh = read_mesh(&path).map_err(|e| e.to_string())?;
    let target: Vec<[f64; 3]> = mesh.positions.iter().map(|p| p.map(f64::from)).collect();
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &target {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let diagonal = Vector3::from(hi) - Vector3::from(lo);
    let size = diagonal.norm();
    println!(
        "{}: {} points, bounding-box diagonal {size:.4}, threads {}",
        path.display(),
        target.len(),
        rayon::current_num_threads()
    );

    let (ms, normals) = median_ms(|| {
        let tree = KdTree::new(target.clone());
        oriented_normals(&tree, 20, None, Orientation::Consistent, [0.0; 3])
    });
    let normals = normals?;
    println!("estimate_normals k 20 consistent: {ms:.1} ms");
    let (ms, _) = median_ms(|| {
        let tree = KdTree::new(target.clone());
        oriented_normals(&tree, 20, None, Orientation::Viewpoint, [0.0, 0.0, 1.0])
    });
    println!("estimate_normals k 20 viewpoint:  {ms:.1} ms");

    let cloud = PointCloud {
        positions: mesh.positions.clone(),
        colors: None,
        normals: None,
    };
    let voxel = 0.005;
    let (ms, down) = median_ms(|| voxel_downsample(&cloud, voxel));
    let down = down?;
    println!(
        "voxel_downsample {voxel}: {ms:.1} ms, {} -> {} points",
        target.len(),
        down.cloud.positions.len()
    );

    let truth = Rigid {
        rotation: rotation_from_vector(
            &(Vector3::new(1.0, -2.0, 0.7).normalize() * 30f64.to_radians()),
        ),
        translation: Vector3::new(0.6, -0.3, 0.5).normalize() * (0.2 * size),
    };
    let source_from_target = truth.inverse();
    let same: Vec<[f64; 3]> = target.iter().map(|p| source_from_target.apply(p)).collect();
    let resampled: Vec<[f64; 3]> = down
        .cloud
        .positions
        .iter()
        .map(|p| source_from_target.apply(&p.map(f64::from)))
        .collect();
    for (name, source) in [("same points", &same), ("voxel-downsampled", &resampled)] {
        for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
            let options = IcpOptions {
                method,
                ..IcpOptions::default()
            };
            let (ms, report) = median_ms(|| {
                icp(
                    source,
                    &target,
                    Some(&normals),
                    &Rigid::identity(),
                    &options,
                )
            });
            let r = report?;
            let e_rot =
                rotation_angle(&(r.target_from_source.rotation * truth.rotation.transpose()));
            let e_t = (r.target_from_source.translation - truth.translation).norm();
            println!(
                "icp {method:?} {name} ({} pts): {ms:.1} ms, {} iterations, converged {}, rotation error {:.3e} rad, translation error {:.3e} (relative {:.3e}), rmse {:.3e}, fitness {:.4}",
                source.len(),
                r.iterations,
                r.converged,
                e_rot,
                e_t,
                e_t / size,
                r.rmse,
                r.fitness
            );
        }
    }
    Ok(())
}
