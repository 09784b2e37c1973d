//! The feature-matching example on its generated views: the views are reproduced by their
//! generator graph, and SIFT and ORB matches agree with the homography the views were made with.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{root, temp_dir};
use ocellus_engine::value::{Keypoint, Match, Value};

/// The homography of `graphs/data/make_feature_pair.ron` (left → right pixels).
const H: [[f64; 3]; 3] = [
    [0.872604473, -0.213507943, 94.5686077],
    [0.204034258, 0.811550358, -18.1429492],
    [0.0001078977, -0.000110528542, 1.0],
];

fn run(graph: &str, overrides: &[&str]) -> Vec<(String, Value)> {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    ocellus_engine::testing::run_graph(&registry, root().join(graph), 2, overrides)
        .unwrap_or_else(|e| panic!("{graph}: {e}"))
        .outputs
}

#[test]
fn fixture_views_are_reproduced_by_their_generator() {
    let dir = temp_dir("feature_pair");
    let left = dir.join("left.png");
    let right = dir.join("right.png");
    let set_left = format!("left.path=\"{}\"", left.display());
    let set_right = format!("right.path=\"{}\"", right.display());
    run(
        "graphs/data/make_feature_pair.ron",
        &[set_left.as_str(), set_right.as_str()],
    );
    for (made, kept) in [(left, "features_left.png"), (right, "features_right.png")] {
        let kept = root().join("graphs/data").join(kept);
        assert_eq!(
            std::fs::read(&made).unwrap(),
            std::fs::read(&kept).unwrap(),
            "{} differs from what make_feature_pair.ron renders",
            kept.display()
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Share of matches whose right keypoint lies within `threshold_px` of H · left keypoint.
fn correct_ratio(outputs: &[(String, Value)], threshold_px: f64) -> (usize, f64) {
    let get = |name: &str| &outputs.iter().find(|(n, _)| n == name).unwrap().1;
    let (Value::Keypoints(left), Value::Keypoints(right), Value::Matches(matches)) = (
        get("keypoints_left"),
        get("keypoints_right"),
        get("matches"),
    ) else {
        panic!("unexpected output types");
    };
    let project = |k: &Keypoint| {
        let (x, y) = (f64::from(k.x), f64::from(k.y));
        let w = H[2][0] * x + H[2][1] * y + H[2][2];
        (
            (H[0][0] * x + H[0][1] * y + H[0][2]) / w,
            (H[1][0] * x + H[1][1] * y + H[1][2]) / w,
        )
    };
    let correct = matches
        .iter()
        .filter(|m: &&Match| {
            let (px, py) = project(&left[m.query as usize]);
            let r = &right[m.train as usize];
            (px - f64::from(r.x)).hypot(py - f64::from(r.y)) <= threshold_px
        })
        .count();
    (matches.len(), correct as f64 / matches.len().max(1) as f64)
}

#[test]
fn sift_and_orb_matches_follow_the_true_homography() {
    // OpenCV 5 (SIFT_create(1000) / ORB_create(1000), BFMatcher k-NN, ratio 0.8) on the same
    // views: 235 SIFT matches, 67.7 % correct within 3 px; 306 ORB matches, 75.2 %. The test
    // card's regular grid makes many repeated structures, hence the modest ratios for both.
    for (method, min_matches, min_ratio) in [("sift", 200, 0.65), ("orb", 200, 0.65)] {
        let set = format!("detect.method=\"{method}\"");
        let outputs = run("graphs/features.ron", &[set.as_str()]);
        let (matches, ratio) = correct_ratio(&outputs, 3.0);
        assert!(
            matches >= min_matches && ratio >= min_ratio,
            "{method}: {matches} matches, {:.1} % correct",
            100.0 * ratio
        );
    }
}
