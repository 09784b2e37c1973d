//! Robust two-view estimation on a correspondence file: prints the model, inliers, time per
//! call, and the mean error over the correspondences flagged 1 (hand-checked) when the file has
//! flags (7-column format).
//!
//! `cargo run --release -p ocellus-nodes --example ransac_eval -- h|f PTS_FILE [METHOD]
//! [THRESHOLD_PX] [REPEATS]`
//!
//! METHOD: ransac, msac, lo_ransac (default) or prosac. The error is the forward transfer
//! distance `‖H x_left − x_right‖` for `h` and the Sampson distance for `f`, pixels.

use std::time::Instant;

use ocellus_nodes::geometry::fundamental::sampson_error2;
use ocellus_nodes::geometry::homography::transfer;
use ocellus_nodes::geometry::ransac::{Method, RobustOptions};
use ocellus_nodes::geometry::two_view::{correspondences, find_fundamental, find_homography};
use ocellus_nodes::io::read_correspondences::read_correspondences;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: ransac_eval h|f PTS_FILE [METHOD] [THRESHOLD_PX] [REPEATS]");
        std::process::exit(2);
    }
    let homography = args[1] == "h";
    let file = match read_correspondences(std::path::Path::new(&args[2])) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
    };
    let method = match args.get(3).map(String::as_str).unwrap_or("lo_ransac") {
        "ransac" => Method::Ransac,
        "msac" => Method::Msac,
        "prosac" => Method::Prosac,
        _ => Method::LoRansac,
    };
    let threshold = args
        .get(4)
        .and_then(|s| s.parse().ok())
        .unwrap_or(if homography { 3.0 } else { 1.0 });
    let repeats: usize = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(20);
    let data = match correspondences(&file.left, &file.right) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
    };
    let options = RobustOptions {
        method,
        threshold,
        ..RobustOptions::default()
    };
    let run = || {
        if homography {
            find_homography(&data, &options, true)
        } else {
            find_fundamental(&data, &options, true)
        }
    };
    let mut best = f64::INFINITY;
    let mut result = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        let r = run();
        best = best.min(t.elapsed().as_secs_f64());
        result = Some(r);
    }
    let estimate = match result {
        Some(Ok(e)) => e,
        Some(Err(e)) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
        None => return,
    };
    let m = estimate.matrix;
    println!(
        "{}: {} correspondences, {} inliers, {} trials, best time {:.3} ms",
        args[2],
        data.len(),
        estimate.inliers,
        estimate.trials,
        best * 1e3
    );
    println!(
        "model (row-major): {:?}",
        (0..9).map(|i| m[(i / 3, i % 3)]).collect::<Vec<_>>()
    );
    if let Some(flags) = &file.flags {
        let errors: Vec<f64> = data
            .iter()
            .zip(flags)
            .filter(|(_, f)| **f == 1)
            .map(|(c, _)| {
                if homography {
                    transfer(&m, &c[0])
                        .map_or(f64::INFINITY, |p| (p[0] - c[1][0]).hypot(p[1] - c[1][1]))
                } else {
                    sampson_error2(&m, c).sqrt()
                }
            })
            .collect();
        let mean = errors.iter().sum::<f64>() / errors.len().max(1) as f64;
        println!(
            "mean error on {} checked correspondences: {mean:.4} px",
            errors.len()
        );
    }
}
