//! Every graph in `graphs/` is snapshot-tested, and the files it emits do not depend on the
//! thread count. A graph that runs once is computed in this process with 8 threads (its
//! snapshot, and its outputs written by the CLI's `emit_value`) and by the CLI in a fresh process
//! with `--threads 1`; every emitted file must be byte-identical. Animated and streamed graphs,
//! whose CLI writes frame by frame, are snapshot-tested from a run in this process with 2 threads
//! and run by the CLI with `--threads 1` and `--threads 8`. Each graph has its own test, so the
//! two test threads share the work.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::path::Path;

use common::{example_graphs, files_below, ocellus, root, stderr, temp_dir};
use ocellus_engine::Value;

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

fn outputs(graph: &str, threads: usize) -> Vec<(String, Value)> {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    // Animated graphs give each output as a list over their frames; the others run once.
    ocellus_engine::testing::run_animated_graph(
        &registry,
        root().join("graphs").join(graph),
        threads,
        &[],
    )
    .unwrap_or_else(|e| panic!("{graph}: {e}"))
}

/// Whether `graph` has an `animation` section: the CLI then writes its outputs frame by frame.
fn is_animated(graph: &str) -> bool {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let path = root().join("graphs").join(graph);
    ocellus_engine::timeline::load_animated_file(&registry, &path, &[])
        .unwrap_or_else(|e| panic!("{graph}: {e}"))
        .1
        .is_some()
}

fn check_graph(graph: &str) {
    let stem = graph.trim_end_matches(".ron");
    if is_animated(graph) {
        let summary = ocellus_engine::summary::summarize_outputs(&outputs(graph, 2));
        insta::assert_snapshot!(stem, summary);
        check_emitted_files(graph, &[]);
        return;
    }
    let outputs = outputs(graph, 8);
    insta::assert_snapshot!(stem, ocellus_engine::summary::summarize_outputs(&outputs));
    let dir = temp_dir("threads");
    let in_process = dir.join("8");
    for (name, value) in &outputs {
        ocellus_engine::emit::emit_value(&in_process, name, value)
            .unwrap_or_else(|e| panic!("{graph}: output `{name}`: {e}"));
    }
    let cli = dir.join("1");
    run_cli(graph, "1", &cli, &[]);
    assert_same_files(graph, &in_process, &cli);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `ocellus run GRAPH --threads THREADS --emit OUT_DIR` with `--set` overrides, in a fresh
/// process (no cache: a real recompute).
fn run_cli(graph: &str, threads: &str, out_dir: &Path, sets: &[&str]) {
    let path = root().join("graphs").join(graph);
    let mut args = vec![
        "run",
        path.to_str().unwrap(),
        "--threads",
        threads,
        "--emit",
        out_dir.to_str().unwrap(),
    ];
    for set in sets {
        args.extend(["--set", set]);
    }
    let out = ocellus(&args);
    assert!(out.status.success(), "{graph}: {}", stderr(&out));
}

/// Every file below `many` (written from a run with several threads) equals the one at the same
/// path below `one` (one thread), and there is at least one.
fn assert_same_files(graph: &str, many: &Path, one: &Path) {
    let (many, one) = (files_below(many), files_below(one));
    assert!(!one.is_empty(), "{graph} emitted nothing");
    let names = |files: &[(std::path::PathBuf, Vec<u8>)]| -> Vec<String> {
        files.iter().map(|(p, _)| p.display().to_string()).collect()
    };
    assert_eq!(
        names(&many),
        names(&one),
        "{graph}: different files emitted"
    );
    for ((path, a), (_, b)) in many.iter().zip(&one) {
        assert!(
            a == b,
            "{graph}: {} differs between 1 thread and several",
            path.display()
        );
    }
}

/// Runs `graph` through the CLI with `--threads 1` and with `--threads 8`, in fresh processes,
/// and requires every emitted file to be byte-identical.
fn check_emitted_files(graph: &str, sets: &[&str]) {
    let dir = temp_dir("threads");
    for threads in ["1", "8"] {
        run_cli(graph, threads, &dir.join(threads), sets);
    }
    assert_same_files(graph, &dir.join("8"), &dir.join("1"));
    std::fs::remove_dir_all(&dir).unwrap();
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
        // Its test function has run at least once: listing a graph above without one fails here.
        let stem = name.trim_end_matches(".ron");
        assert!(
            root()
                .join("tests/snapshots")
                .join(format!("graphs__{stem}.snap"))
                .is_file(),
            "{name}: no tests/snapshots/graphs__{stem}.snap; add its #[test] to tests/graphs.rs"
        );
        let out = ocellus(&["check", path.to_str().unwrap()]);
        assert!(out.status.success(), "{name}: {}", stderr(&out));
    }
}

#[test]
fn calibrate() {
    check_graph("calibrate.ron");
}

/// `track.ron` at a reduced size (the full 300 HD frames are the benchmark): the streamed
/// outputs equal a batch run over whole lists (the stateful tracker, background model and
/// metrics keep the same state in both modes), and the emitted files do not depend on the
/// thread count.
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
    let streamed = ocellus_engine::testing::run_stream_graph(&registry, &path, 2, TRACK_SMALL)
        .unwrap_or_else(|e| panic!("track.ron: {e}"));
    // Compared as summaries: per-frame metrics hold NaN (no track scored on the first frame).
    let text = |outputs: &[(String, ocellus_engine::Value)]| {
        ocellus_engine::summary::summarize_outputs(outputs)
    };
    let batch = ocellus_engine::testing::run_graph(&registry, &path, 2, TRACK_SMALL)
        .unwrap_or_else(|e| panic!("track.ron --batch: {e}"));
    assert_eq!(
        text(&batch.outputs),
        text(&streamed),
        "streamed and batch outputs differ"
    );
    // Every per-frame output has one element per frame.
    for (name, value) in &streamed {
        if let ocellus_engine::Value::List(list) = value {
            assert_eq!(list.items.len(), 16, "{name}");
        }
    }
    insta::assert_snapshot!("track", text(&streamed));
    check_emitted_files("track.ron", TRACK_SMALL);
}

/// `servo.ron`, a closed loop (the camera is driven by velocities fed back from its own frames):
/// snapshot-tested streamed, and its emitted files do not depend on the thread count.
/// `tests/servo.rs` checks that it converges.
#[test]
fn servo() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let path = root().join("graphs").join("servo.ron");
    let streamed = ocellus_engine::testing::run_stream_graph(&registry, &path, 2, &[])
        .unwrap_or_else(|e| panic!("servo.ron: {e}"));
    insta::assert_snapshot!(
        "servo",
        ocellus_engine::summary::summarize_outputs(&streamed)
    );
    check_emitted_files("servo.ron", &[]);
}
