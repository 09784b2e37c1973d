//! SIFT + ratio-test matching + robust homography between two images; with a ground-truth
//! homography, prints the mean transfer error of the four image corners.
//!
//! `cargo run --release -p ocellus-nodes --example homography_pair -- LEFT RIGHT [TRUTH]
//! [METHOD] [THRESHOLD_PX]`
//!
//! TRUTH: a text file holding the 9 entries of H (left → right), row-major, as whitespace-
//! separated numbers; an OpenCV XML/YAML matrix file works too (the numbers between `<data>` and
//! `</data>`, or after `data:`).

use std::time::Instant;

use ocellus_engine::value::{Channels, Image};
use ocellus_nodes::describe::sift::{SiftParams, sift_detect_and_compute};
use ocellus_nodes::geometry::homography::transfer;
use ocellus_nodes::geometry::ransac::{Method, RobustOptions};
use ocellus_nodes::geometry::two_view::{correspondences, find_homography, matched_points};
use ocellus_nodes::matching::Norm;
use ocellus_nodes::matching::brute_force::{MatchOptions, brute_force_match};

fn gray(path: &str) -> Image {
    let img = image::open(path).unwrap_or_else(|e| {
        eprintln!("{path}: {e}");
        std::process::exit(1)
    });
    let g = img.to_luma8();
    let (w, h) = (g.width() as usize, g.height() as usize);
    Image::from_u8(w, h, Channels::Gray, g.into_raw()).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(1)
    })
}

fn read_truth(path: &str) -> Option<nalgebra::Matrix3<f64>> {
    let text = std::fs::read_to_string(path).ok()?;
    let body = match (text.find("<data>"), text.find("</data>")) {
        (Some(a), Some(b)) => &text[a + 6..b],
        _ => match text.find("data:") {
            Some(a) => &text[a + 5..],
            None => &text,
        },
    };
    let numbers: Vec<f64> = body
        .split(|c: char| c.is_whitespace() || c == ',' || c == '[' || c == ']')
        .filter_map(|s| s.parse().ok())
        .collect();
    (numbers.len() >= 9).then(|| nalgebra::Matrix3::from_row_slice(&numbers[..9]))
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: homography_pair LEFT RIGHT [TRUTH] [METHOD] [THRESHOLD_PX]");
        std::process::exit(2);
    }
    let (left, right) = (gray(&args[1]), gray(&args[2]));
    let method = match args.get(4).map(String::as_str).unwrap_or("lo_ransac") {
        "ransac" => Method::Ransac,
        "msac" => Method::Msac,
        "prosac" => Method::Prosac,
        _ => Method::LoRansac,
    };
    let threshold = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(3.0);
    let params = SiftParams::default();
    let (kl, dl) = sift_detect_and_compute(&left, &params).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(1)
    });
    let (kr, dr) = sift_detect_and_compute(&right, &params).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(1)
    });
    let (metric, ql, qr) =
        ocellus_nodes::matching::prepare(&dl, &dr, Norm::Auto).unwrap_or_else(|e| {
            eprintln!("{e}");
            std::process::exit(1)
        });
    let matches = brute_force_match(&ql, &qr, metric, &MatchOptions::default(), None);
    let (pl, pr) = matched_points(&kl, &kr, &matches, true).unwrap_or_default();
    let data = correspondences(&pl, &pr).unwrap_or_default();
    let options = RobustOptions {
        method,
        threshold,
        ..RobustOptions::default()
    };
    let mut best = f64::INFINITY;
    let mut result = None;
    for _ in 0..20 {
        let t = Instant::now();
        let r = find_homography(&data, &options, true);
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
    println!(
        "{} / {} keypoints, {} matches, {} inliers, {} trials, find_homography best {:.3} ms",
        kl.len(),
        kr.len(),
        matches.len(),
        estimate.inliers,
        estimate.trials,
        best * 1e3
    );
    let h = estimate.matrix / estimate.matrix[(2, 2)];
    println!("H = {h}");
    if let Some(truth) = args.get(3).and_then(|p| read_truth(p)) {
        let (w, hh) = (left.width() as f64, left.height() as f64);
        let corners = [[0.0, 0.0], [w, 0.0], [0.0, hh], [w, hh]];
        let err: f64 = corners
            .iter()
            .map(|p| match (transfer(&h, p), transfer(&truth, p)) {
                (Some(a), Some(b)) => (a[0] - b[0]).hypot(a[1] - b[1]),
                _ => f64::INFINITY,
            })
            .sum::<f64>()
            / 4.0;
        println!("mean corner transfer error vs truth: {err:.3} px");
    }
}
