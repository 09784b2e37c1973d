//! Scheduler semantics, checked by counting operator calls: demand, sharing, caching, mapping,
//! failure isolation, thread-count independence.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{load, registry, temp_dir};
use ocellus_engine::exec::NodeStatus;
use ocellus_engine::resolve::{Override, load_graph, load_source};
use ocellus_engine::{RunOptions, Value, run};

const BRANCHES: &str = r#"Graph(
    name: "branches",
    nodes: {
        "a": (op: "t.source", params: (value: 1.0)),
        "b": (op: "t.source", params: (value: 2.0)),
        "ab": (op: "t.add", inputs: { "a": "a.value", "b": "b.value" }),
        "c": (op: "t.source", params: (value: 10.0)),
        "c2": (op: "t.add", inputs: { "a": "c.value" }, params: (offset: 0.5)),
    },
    outputs: { "left": "ab.sum", "right": "c2.sum" },
)"#;

fn scalar(report: &ocellus_engine::RunReport, name: &str) -> f64 {
    match report.output(name) {
        Some(Value::Scalar(x)) => *x,
        other => panic!("output {name}: {other:?}"),
    }
}

#[test]
fn runs_everything_by_default() {
    let (reg, calls) = registry();
    let graph = load(&reg, BRANCHES);
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "left"), 3.0);
    assert_eq!(scalar(&report, "right"), 10.5);
    assert_eq!(calls.total(), 5);
    assert_eq!(report.count(NodeStatus::Computed), 5);
    // Outputs come in declaration order.
    let names: Vec<&str> = report.outputs.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["left", "right"]);
}

#[test]
fn computes_only_what_the_selected_output_needs() {
    let (reg, calls) = registry();
    let graph = load(&reg, BRANCHES);
    let options = RunOptions {
        outputs: vec!["right".into()],
        ..RunOptions::default()
    };
    let report = run(&graph, &options).unwrap();
    assert_eq!(report.outputs.len(), 1);
    assert_eq!(scalar(&report, "right"), 10.5);
    assert_eq!(calls.get("t.source"), 1);
    assert_eq!(calls.get("t.add"), 1);
    assert_eq!(report.count(NodeStatus::Idle), 3);
}

#[test]
fn unknown_selected_output_is_an_error_with_suggestion() {
    let (reg, _) = registry();
    let graph = load(&reg, BRANCHES);
    let options = RunOptions {
        outputs: vec!["rigth".into()],
        ..RunOptions::default()
    };
    let err = run(&graph, &options).unwrap_err().to_string();
    assert!(
        err.contains("no output `rigth`") && err.contains("did you mean `right`"),
        "{err}"
    );
}

#[test]
fn identical_subgraphs_run_once() {
    let (reg, calls) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "x1": (op: "t.source", params: (value: 4.0)),
            "x2": (op: "t.source", params: (value: 4.0)),
            "y1": (op: "t.add", inputs: { "a": "x1.value" }),
            "y2": (op: "t.add", inputs: { "a": "x2.value" }),
            "z": (op: "t.add", inputs: { "a": "y1.sum", "b": "y2.sum" }),
        }, outputs: { "z": "z.sum", "y2": "y2.sum" })"#,
    );
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "z"), 8.0);
    assert_eq!(scalar(&report, "y2"), 4.0);
    assert_eq!(calls.get("t.source"), 1);
    assert_eq!(calls.get("t.add"), 2);
    assert_eq!(report.count(NodeStatus::Shared), 2);
}

#[test]
fn a_failing_branch_does_not_stop_the_others() {
    let (reg, calls) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "x": (op: "t.source", params: (value: 1.0)),
            "bad": (op: "t.fail", inputs: { "x": "x.value" }),
            "after": (op: "t.add", inputs: { "a": "bad.y" }),
            "boom": (op: "t.panic", inputs: { "x": "x.value" }),
            "good": (op: "t.add", inputs: { "a": "x.value" }, params: (offset: 1.0)),
        }, outputs: { "after": "after.sum", "good": "good.sum", "boom": "boom.y" })"#,
    );
    for threads in [1, 2] {
        let report = run(
            &graph,
            &RunOptions {
                threads,
                ..RunOptions::default()
            },
        )
        .unwrap();
        assert_eq!(scalar(&report, "good"), 2.0);
        assert!(report.output("after").is_none());
        assert_eq!(report.failures.len(), 2);
        let bad = &report.failures[0];
        assert_eq!(bad.node, "bad");
        assert_eq!(bad.op, "t.fail");
        assert_eq!(bad.location.as_deref(), Some("test.ron:3:13"));
        assert!(bad.to_string().contains("deliberate failure"));
        assert!(
            report.failures[1].message.contains("deliberate panic"),
            "{}",
            report.failures[1]
        );
        assert_eq!(report.count(NodeStatus::Skipped), 1);
    }
    assert_eq!(calls.get("t.add"), 2, "`after` must never run");
}

#[test]
fn list_inputs_map_the_operator() {
    let (reg, calls) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "x": (op: "t.source", params: (value: 1.0)),
            "many": (op: "t.repeat", inputs: { "x": "x.value" }, params: (count: 4)),
            "plus": (op: "t.add", inputs: { "a": "many.items", "b": "x.value" }),
            "pairs": (op: "t.add", inputs: { "a": "many.items", "b": "plus.sum" }),
            "total": (op: "t.collect", inputs: { "items": "pairs.sum" }),
        }, outputs: { "plus": "plus.sum", "total": "total.total" })"#,
    );
    assert!(graph.nodes[graph.node_index("plus").unwrap()].is_mapped());
    let report = run(&graph, &RunOptions::default()).unwrap();
    // items = 1,2,3,4; plus = 2,3,4,5; pairs = 3,5,7,9.
    let Some(Value::List(plus)) = report.output("plus") else {
        panic!("plus is not a list")
    };
    assert_eq!(plus.items, [2.0, 3.0, 4.0, 5.0].map(Value::Scalar));
    assert_eq!(scalar(&report, "total"), 24.0);
    assert_eq!(calls.get("t.add"), 8);
}

#[test]
fn mapped_lists_of_different_lengths_fail_cleanly() {
    let (reg, _) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "x": (op: "t.source"),
            "three": (op: "t.repeat", inputs: { "x": "x.value" }, params: (count: 3)),
            "two": (op: "t.repeat", inputs: { "x": "x.value" }, params: (count: 2)),
            "sum": (op: "t.add", inputs: { "a": "three.items", "b": "two.items" }),
        }, outputs: { "sum": "sum.sum" })"#,
    );
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(report.failures.len(), 1);
    assert!(
        report.failures[0].message.contains("differ in length"),
        "{}",
        report.failures[0]
    );
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let (reg, _) = registry();
    let graph = load(&reg, BRANCHES);
    let one = run(
        &graph,
        &RunOptions {
            threads: 1,
            ..RunOptions::default()
        },
    )
    .unwrap();
    let four = run(
        &graph,
        &RunOptions {
            threads: 4,
            ..RunOptions::default()
        },
    )
    .unwrap();
    assert_eq!(one.outputs, four.outputs);
}

#[test]
fn disk_cache_recomputes_only_downstream_of_a_change() {
    let (reg, calls) = registry();
    let dir = temp_dir("cache");
    let cache = dir.join("cache");
    let options = RunOptions {
        cache_dir: Some(cache.clone()),
        ..RunOptions::default()
    };
    let source = common::source("test.ron", BRANCHES);
    let first = run(&load_source(&reg, &source, &[]).unwrap(), &options).unwrap();
    assert_eq!(first.count(NodeStatus::Computed), 5);
    assert_eq!(calls.total(), 5);

    // Unchanged: everything needed comes from the cache, no operator runs.
    let second = run(&load_source(&reg, &source, &[]).unwrap(), &options).unwrap();
    assert_eq!(calls.total(), 5);
    assert_eq!(
        second.count(NodeStatus::Cached),
        2,
        "only the two output nodes are loaded"
    );
    assert_eq!(second.outputs, first.outputs);

    // Change `b`: `b` and `ab` recompute; `a` is loaded; the right branch stays cached.
    let set = [Override::parse("b.value=5").unwrap()];
    let third = run(&load_source(&reg, &source, &set).unwrap(), &options).unwrap();
    assert_eq!(scalar(&third, "left"), 6.0);
    assert_eq!(third.count(NodeStatus::Computed), 2);
    assert_eq!(third.count(NodeStatus::Cached), 2);
    assert_eq!(calls.get("t.source"), 3 + 1);
    assert_eq!(calls.get("t.add"), 2 + 1);

    // A corrupt entry is recomputed, not trusted.
    for entry in std::fs::read_dir(&cache).unwrap() {
        std::fs::write(entry.unwrap().path(), b"garbage").unwrap();
    }
    let fourth = run(&load_source(&reg, &source, &[]).unwrap(), &options).unwrap();
    assert_eq!(fourth.outputs, first.outputs);
    assert_eq!(fourth.count(NodeStatus::Computed), 5);
}

/// `recompute` runs the named node and everything downstream of it although the memory cache
/// holds them, while the rest still comes from the cache; unknown names are an error.
#[test]
fn recompute_bypasses_the_cache_downstream_of_the_named_nodes() {
    let (reg, calls) = registry();
    let graph = load(&reg, BRANCHES);
    let memory = std::sync::Arc::new(ocellus_engine::cache::MemoryCache::new());
    let options = RunOptions {
        memory_cache: Some(std::sync::Arc::clone(&memory)),
        ..RunOptions::default()
    };
    let first = run(&graph, &options).unwrap();
    assert_eq!(calls.total(), 5);
    assert_eq!(first.count(NodeStatus::Computed), 5);

    let again = RunOptions {
        recompute: vec!["b".into()],
        ..options.clone()
    };
    let second = run(&graph, &again).unwrap();
    assert_eq!(second.outputs, first.outputs);
    // `b` and `ab` run again; `c2` is loaded (its upstream `c` is not needed).
    assert_eq!(calls.get("t.source"), 3 + 1);
    assert_eq!(calls.get("t.add"), 2 + 1);
    assert_eq!(second.count(NodeStatus::Computed), 2);
    let status = |name: &str| second.nodes.iter().find(|n| n.name == name).unwrap().status;
    assert_eq!(status("a"), NodeStatus::Cached);
    assert_eq!(status("c2"), NodeStatus::Cached);
    assert_eq!(status("c"), NodeStatus::Idle);

    let unknown = RunOptions {
        recompute: vec!["bx".into()],
        ..options
    };
    let e = run(&graph, &unknown).err().unwrap().to_string();
    assert!(
        e.contains("no node `bx`") && e.contains("did you mean `b`"),
        "{e}"
    );
}

#[test]
fn subgraphs_are_inlined_with_inputs_and_outputs() {
    let (reg, _) = registry();
    let dir = temp_dir("subgraph");
    std::fs::write(
        dir.join("inc.ron"),
        r#"Graph(
            inputs: { "x": "Scalar" },
            nodes: { "plus": (op: "t.add", inputs: { "a": "inputs.x" }, params: (offset: 1.0)) },
            outputs: { "y": "plus.sum" },
        )"#,
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("nested")).unwrap();
    std::fs::write(
        dir.join("nested/main.ron"),
        r#"Graph(nodes: {
            "s": (op: "t.source", params: (value: 2.0)),
            "inc1": (op: "graph", params: (path: "../inc.ron"), inputs: { "x": "s.value" }),
            "inc2": (op: "graph", params: (path: "../inc.ron"), inputs: { "x": "inc1.y" }),
        }, outputs: { "result": "inc2.y" })"#,
    )
    .unwrap();
    let graph = load_graph(&reg, &dir.join("nested/main.ron"), &[]).unwrap();
    assert!(graph.node_index("inc2/plus").is_some());
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "result"), 4.0);

    // Overrides reach into subgraphs.
    let set = [Override::parse("inc2/plus.offset=10").unwrap()];
    let graph = load_graph(&reg, &dir.join("nested/main.ron"), &set).unwrap();
    assert_eq!(
        scalar(&run(&graph, &RunOptions::default()).unwrap(), "result"),
        13.0
    );
}

#[test]
fn recursive_and_missing_subgraphs_are_reported() {
    let (reg, _) = registry();
    let dir = temp_dir("recursive");
    std::fs::write(
        dir.join("a.ron"),
        r#"Graph(nodes: { "b": (op: "graph", params: (path: "b.ron")) }, outputs: {})"#,
    )
    .unwrap();
    std::fs::write(
        dir.join("b.ron"),
        r#"Graph(nodes: { "a": (op: "graph", params: (path: "a.ron")), "m": (op: "graph", params: (path: "missing.ron")) }, outputs: {})"#,
    )
    .unwrap();
    let err = load_graph(&reg, &dir.join("a.ron"), &[]).unwrap_err();
    let text = err.to_string();
    assert!(text.contains("includes itself"), "{text}");
    assert!(text.contains("missing subgraph file"), "{text}");
    assert!(text.contains("b.ron:1:"), "{text}");
}
