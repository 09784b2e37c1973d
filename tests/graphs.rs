//! Every graph in `graphs/` is snapshot-tested, and its emitted files are byte-identical for
//! `--threads 1`, `2` and `8` and across repeated runs.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{example_graphs, files_below, ocellus, root, stderr, temp_dir};

/// Graphs with a snapshot test below; a new graph must be added here.
const SNAPSHOTTED: &[&str] = &[
    "animate.ron",
    "bal.ron",
    "bundle_adjust.ron",
    "calibrate.ron",
    "codec.ron",
    "decompose.ron",
    "edges.ron",
    "features.ron",
    "filters.ron",
    "homography.ron",
    "hull.ron",
    "learn.ron",
    "lines.ron",
    "many_views.ron",
    "mesh.ron",
    "panorama.ron",
    "poisson.ron",
    "ransac_fundamental.ron",
    "ransac_homography.ron",
    "raycast.ron",
    "reconstruct.ron",
    "render.ron",
    "segment.ron",
    "sensor.ron",
    "servo.ron",
    "sfm.ron",
    "stereo.ron",
    "texture.ron",
    "tour.ron",
    "track.ron",
    "two_branches.ron",
    "two_view.ron",
];

fn summary(graph: &str, threads: usize) -> String {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    // Animated graphs give each output as a list over their frames; the others run once.
    let outputs = ocellus_engine::testing::run_animated_graph(
        &registry,
        root().join("graphs").join(graph),
        threads,
        &[],
    )
    .unwrap_or_else(|e| panic!("{graph}: {e}"));
    ocellus_engine::summary::summarize_outputs(&outputs)
}

fn check_graph(graph: &str) {
    let one = summary(graph, 1);
    let two = summary(graph, 2);
    assert_eq!(one, two, "{graph}: summary differs between 1 and 2 threads");
    insta::assert_snapshot!(graph.trim_end_matches(".ron"), one);
}

#[test]
fn codec() {
    check_graph("codec.ron");
}

#[test]
fn decompose() {
    check_graph("decompose.ron");
}

#[test]
fn hull() {
    check_graph("hull.ron");
}

#[test]
fn learn() {
    check_graph("learn.ron");
}

#[test]
fn sensor() {
    check_graph("sensor.ron");
}

#[test]
fn texture() {
    check_graph("texture.ron");
}

#[test]
fn animate() {
    check_graph("animate.ron");
}

#[test]
fn bal() {
    check_graph("bal.ron");
}

#[test]
fn bundle_adjust() {
    check_graph("bundle_adjust.ron");
}

#[test]
fn edges() {
    check_graph("edges.ron");
}

#[test]
fn features() {
    check_graph("features.ron");
}

#[test]
fn filters() {
    check_graph("filters.ron");
}

#[test]
fn homography() {
    check_graph("homography.ron");
}

#[test]
fn mesh() {
    check_graph("mesh.ron");
}

#[test]
fn poisson() {
    check_graph("poisson.ron");
}

#[test]
fn raycast() {
    check_graph("raycast.ron");
}

#[test]
fn render() {
    check_graph("render.ron");
}

#[test]
fn ransac_homography() {
    check_graph("ransac_homography.ron");
}

#[test]
fn ransac_fundamental() {
    check_graph("ransac_fundamental.ron");
}

#[test]
fn lines() {
    check_graph("lines.ron");
}

#[test]
fn many_views() {
    check_graph("many_views.ron");
}

#[test]
fn segment() {
    check_graph("segment.ron");
}

#[test]
fn panorama() {
    check_graph("panorama.ron");
}

#[test]
fn tour() {
    check_graph("tour.ron");
}

#[test]
fn reconstruct() {
    check_graph("reconstruct.ron");
}

#[test]
fn sfm() {
    check_graph("sfm.ron");
}

#[test]
fn stereo() {
    check_graph("stereo.ron");
}

#[test]
fn two_branches() {
    check_graph("two_branches.ron");
}

#[test]
fn two_view() {
    check_graph("two_view.ron");
}

#[test]
fn every_example_graph_is_snapshot_tested_and_valid() {
    for path in example_graphs() {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            SNAPSHOTTED.contains(&name.as_str()),
            "{name} has no snapshot test in tests/graphs.rs"
        );
        let out = ocellus(&["check", path.to_str().unwrap()]);
        assert!(out.status.success(), "{name}: {}", stderr(&out));
    }
}

#[test]
fn emitted_files_are_identical_for_one_two_and_eight_threads_and_a_repeated_run() {
    for path in example_graphs() {
        let dir = temp_dir("threads");
        let mut emitted = Vec::new();
        // 1, 2 and 8 threads, then 2 again in a fresh process (no cache: a real recompute).
        for (run, threads) in ["1", "2", "8", "2"].into_iter().enumerate() {
            let out_dir = dir.join(format!("{run}_{threads}"));
            let mut args = vec![
                "run",
                path.to_str().unwrap(),
                "--threads",
                threads,
                "--emit",
                out_dir.to_str().unwrap(),
            ];
            // The streamed HD benchmark graph is checked at a reduced size.
            if path.ends_with("track.ron") {
                for set in TRACK_SMALL {
                    args.extend(["--set", set]);
                }
            }
            let out = ocellus(&args);
            assert!(out.status.success(), "{}: {}", path.display(), stderr(&out));
            emitted.push(files_below(&out_dir));
        }
        assert!(!emitted[0].is_empty(), "{} emitted nothing", path.display());
        for (run, other) in emitted.iter().enumerate().skip(1) {
            assert!(
                emitted[0] == *other,
                "{}: files of run {run} (threads 1, 2, 8, 2) differ from the 1-thread run",
                path.display()
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn calibrate() {
    check_graph("calibrate.ron");
}

/// `track.ron` at a reduced size (the full 300 HD frames are the benchmark): the streamed
/// outputs are the same at 1 and 2 threads and equal to a batch run over whole lists (the
/// stateful tracker, background model and metrics keep the same state in both modes).
const TRACK_SMALL: &[&str] = &[
    "clip.frames=16",
    "clip.width=320",
    "clip.height=180",
    "clip.size_px=40",
];

#[test]
fn track() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let path = root().join("graphs").join("track.ron");
    let stream = |threads| {
        ocellus_engine::testing::run_stream_graph(&registry, &path, threads, TRACK_SMALL)
            .unwrap_or_else(|e| panic!("track.ron: {e}"))
    };
    let one = stream(1);
    // Compared as summaries: per-frame metrics hold NaN (no track scored on the first frame).
    let text = |outputs: &[(String, ocellus_engine::Value)]| {
        ocellus_engine::summary::summarize_outputs(outputs)
    };
    assert_eq!(
        text(&one),
        text(&stream(2)),
        "streamed outputs differ between 1 and 2 threads"
    );
    let batch = ocellus_engine::testing::run_graph(&registry, &path, 2, TRACK_SMALL)
        .unwrap_or_else(|e| panic!("track.ron --batch: {e}"));
    assert_eq!(
        text(&batch.outputs),
        text(&one),
        "streamed and batch outputs differ"
    );
    // Every per-frame output has one element per frame.
    for (name, value) in &one {
        if let ocellus_engine::Value::List(list) = value {
            assert_eq!(list.items.len(), 16, "{name}");
        }
    }
    insta::assert_snapshot!("track", text(&one));
}

/// `servo.ron`, a closed loop (the camera is driven by velocities fed back from its own frames):
/// the streamed outputs are the same at 1 and 2 threads. `tests/servo.rs` checks that it
/// converges.
#[test]
fn servo() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let path = root().join("graphs").join("servo.ron");
    let stream = |threads| {
        ocellus_engine::testing::run_stream_graph(&registry, &path, threads, &[])
            .unwrap_or_else(|e| panic!("servo.ron: {e}"))
    };
    let text = |outputs: &[(String, ocellus_engine::Value)]| {
        ocellus_engine::summary::summarize_outputs(outputs)
    };
    let one = text(&stream(1));
    assert_eq!(
        one,
        text(&stream(2)),
        "streamed outputs differ between 1 and 2 threads"
    );
    insta::assert_snapshot!("servo", one);
}
