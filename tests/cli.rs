//! The CLI contract: flags, exit codes, JSON formats, caching and failure isolation, as users and
//! scripts see them.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{ocellus, stderr, stdout, temp_dir};
use serde_json::Value as Json;

const SMALL: &str = r#"Graph(
    name: "small",
    nodes: {
        "card": (op: "capture.pattern", params: (kind: "checkerboard", width: 64, height: 48, square: 8)),
        "gray": (op: "filter.grayscale", inputs: { "image": "card.image" }),
        "blur": (op: "filter.gaussian", inputs: { "image": "gray.image" }, params: (sigma: 1.0)),
        "stats": (op: "analyze.stats", inputs: { "image": "blur.image" }),
        "noise": (op: "capture.pattern", params: (kind: "noise", width: 16, height: 16, seed: 7)),
    },
    outputs: { "blur": "blur.image", "stats": "stats.stats", "noise": "noise.image" },
)
"#;

fn small_graph(dir: &std::path::Path) -> String {
    let path = dir.join("small.ron");
    std::fs::write(&path, SMALL).unwrap();
    path.to_string_lossy().into_owned()
}

#[test]
fn ops_json_documents_every_operator() {
    let out = ocellus(&["ops", "--json"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let ops: Json = serde_json::from_str(&stdout(&out)).unwrap();
    let ops = ops.as_array().unwrap();
    let ids: Vec<&str> = ops.iter().map(|o| o["id"].as_str().unwrap()).collect();
    for id in [
        "capture.pattern",
        "io.read_image",
        "io.write_image",
        "filter.grayscale",
        "filter.gaussian",
        "detect.canny",
        "analyze.stats",
    ] {
        assert!(ids.contains(&id), "{id} missing from ops --json");
    }
    for op in ops {
        let id = op["id"].as_str().unwrap();
        assert_eq!(
            op["family"].as_str().unwrap(),
            id.split('.').next().unwrap()
        );
        assert!(
            !op["summary"].as_str().unwrap().is_empty(),
            "{id} has no summary"
        );
        assert!(!op["doc"].as_str().unwrap().is_empty(), "{id} has no doc");
        assert_eq!(op["origin"], "builtin");
        for port in op["inputs"]
            .as_array()
            .unwrap()
            .iter()
            .chain(op["outputs"].as_array().unwrap())
        {
            assert!(
                port["name"].is_string() && port["type"].is_string(),
                "{id}: {port}"
            );
        }
        for param in op["params"].as_array().unwrap() {
            for key in ["name", "type", "default", "range", "doc", "unit"] {
                assert!(
                    param.get(key).is_some(),
                    "{id}: param without {key}: {param}"
                );
            }
            assert!(
                !param["doc"].as_str().unwrap().is_empty(),
                "{id}.{} undocumented",
                param["name"]
            );
        }
    }
    let gaussian = ops.iter().find(|o| o["id"] == "filter.gaussian").unwrap();
    let sigma = gaussian["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "sigma")
        .unwrap();
    assert_eq!(sigma["type"], "float");
    assert_eq!(sigma["unit"], "px");
}

#[test]
fn ops_shows_one_operator_and_suggests_on_typos() {
    let out = ocellus(&["ops", "filter.gaussian"]);
    assert!(out.status.success());
    let text = stdout(&out);
    assert!(text.contains("sigma") && text.contains("border"), "{text}");
    let out = ocellus(&["ops", "filter.gausian"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("did you mean `filter.gaussian`"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn profile_json_has_the_documented_shape() {
    let dir = temp_dir("profile");
    let graph = small_graph(&dir);
    let profile = dir.join("p.json");
    let out = ocellus(&[
        "run",
        &graph,
        "--repeat",
        "3",
        "--profile",
        profile.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let json: Json = serde_json::from_str(&std::fs::read_to_string(&profile).unwrap()).unwrap();
    let keys: Vec<&str> = json
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    assert_eq!(keys, ["nodes", "peak_bytes", "total_median_ms"]);
    assert!(json["total_median_ms"].as_f64().unwrap() > 0.0);
    assert!(json["peak_bytes"].as_u64().unwrap() >= 64 * 48);
    let nodes = json["nodes"].as_object().unwrap();
    assert_eq!(nodes.len(), 5);
    let blur = &nodes["blur"];
    assert_eq!(blur["op"], "filter.gaussian");
    let (min, med, max) = (
        blur["min_ms"].as_f64().unwrap(),
        blur["median_ms"].as_f64().unwrap(),
        blur["max_ms"].as_f64().unwrap(),
    );
    assert!(min <= med && med <= max, "{blur}");
}

#[test]
fn cache_recomputes_only_downstream_of_a_changed_parameter() {
    let dir = temp_dir("cache");
    let graph = small_graph(&dir);
    let cache = dir.join("cache");
    let cache = cache.to_str().unwrap();
    let run = |extra: &[&str]| {
        let mut args = vec!["run", graph.as_str(), "--cache", cache];
        args.extend_from_slice(extra);
        let out = ocellus(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        (stdout(&out), stderr(&out))
    };
    let (first_out, first) = run(&[]);
    assert!(first.contains("5 computed, 0 cached"), "{first}");
    let (second_out, second) = run(&[]);
    assert!(second.contains("0 computed, 3 cached"), "{second}");
    assert_eq!(first_out, second_out);
    // Changing the blur recomputes blur and stats; gray comes from the cache, card is not needed.
    let (_, third) = run(&["--set", "blur.sigma=2.0"]);
    assert!(third.contains("2 computed, 2 cached"), "{third}");
}

#[test]
fn output_selection_runs_only_what_it_needs() {
    let dir = temp_dir("select");
    let graph = small_graph(&dir);
    let out = ocellus(&["run", &graph, "--output", "noise"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stderr(&out).contains("1 computed"), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(
        text.contains("\"noise\"") && !text.contains("\"blur\""),
        "{text}"
    );
    let out = ocellus(&["run", &graph, "--output", "nois"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("did you mean `noise`"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn set_overrides_are_checked_like_the_file() {
    let dir = temp_dir("set");
    let graph = small_graph(&dir);
    let out = ocellus(&["run", &graph, "--set", "blur.sigma=-1"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("--set:1:12"), "{}", stderr(&out));
    let out = ocellus(&[
        "check",
        &graph,
        "--set",
        "blurr.sigma=1",
        "--set",
        "card.kind=chekerboard",
    ]);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(err.contains("did you mean `blur`"), "{err}");
    assert!(err.contains("did you mean \"checkerboard\""), "{err}");
    assert!(err.contains("2 problems"), "{err}");
    let out = ocellus(&[
        "run",
        &graph,
        "--set",
        "card.kind=noise",
        "--set",
        "card.square=32",
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
}

#[test]
fn a_failing_node_fails_the_run_but_other_outputs_are_emitted() {
    let dir = temp_dir("fail");
    let graph = dir.join("g.ron");
    std::fs::write(
        &graph,
        r#"Graph(
    nodes: {
        "missing": (op: "io.read_image", params: (path: "no_such_file.png")),
        "stats": (op: "analyze.stats", inputs: { "image": "missing.image" }),
        "card": (op: "capture.pattern", params: (width: 32, height: 16)),
    },
    outputs: { "stats": "stats.stats", "card": "card.image" },
)"#,
    )
    .unwrap();
    let emit = dir.join("out");
    let out = ocellus(&[
        "run",
        graph.to_str().unwrap(),
        "--emit",
        emit.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = stderr(&out);
    assert!(
        err.contains("g.ron:3:9: node `missing` (io.read_image) failed"),
        "{err}"
    );
    assert!(err.contains("no_such_file.png"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(emit.join("card.png").exists());
    assert!(!emit.join("stats.json").exists());
}

#[test]
fn write_image_is_a_side_effect_that_always_runs() {
    let dir = temp_dir("write");
    let graph = dir.join("w.ron");
    std::fs::write(
        &graph,
        r#"Graph(
    nodes: {
        "card": (op: "capture.pattern", params: (width: 40, height: 30)),
        "save": (op: "io.write_image", inputs: { "image": "card.image" }, params: (path: "out/card.png")),
    },
    outputs: {},
)"#,
    )
    .unwrap();
    let cache = dir.join("cache");
    for _ in 0..2 {
        std::fs::remove_dir_all(dir.join("out")).ok();
        std::fs::create_dir_all(dir.join("out")).unwrap();
        let out = ocellus(&[
            "run",
            graph.to_str().unwrap(),
            "--cache",
            cache.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
        let written: Vec<_> = std::fs::read_dir(dir.join("out"))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(written, ["card.png"], "exactly the file, no temporaries");
    }
}

#[test]
fn dot_and_snapshot_and_check() {
    let dir = temp_dir("misc");
    let graph = small_graph(&dir);
    let out = ocellus(&["dot", &graph]);
    assert!(out.status.success());
    let dot = stdout(&out);
    assert!(
        dot.starts_with("digraph") && dot.contains("filter.gaussian"),
        "{dot}"
    );
    let out = ocellus(&["check", &graph]);
    assert!(out.status.success());
    assert!(stdout(&out).contains("ok"), "{}", stdout(&out));
    let a = ocellus(&["snapshot", &graph, "--threads", "1"]);
    let b = ocellus(&["snapshot", &graph, "--threads", "2"]);
    assert!(a.status.success());
    assert_eq!(stdout(&a), stdout(&b));
    assert!(stdout(&a).contains("\"stats\""));
}

#[test]
fn unreadable_graph_file_is_a_clean_error() {
    let out = ocellus(&["run", "does/not/exist.ron"]);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(err.contains("cannot read graph file"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}
