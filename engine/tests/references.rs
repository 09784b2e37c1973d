//! List literals of references (`["a.value", "b.value"]`) and indexed references
//! (`"r.items[0]"`, `"r.items[-1]"`): validation, mapping, passing as a list, run-time range
//! errors, cache keys and demand.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{errors, load, registry};
use ocellus_engine::exec::NodeStatus;
use ocellus_engine::resolve::load_source;
use ocellus_engine::{RunOptions, RunReport, Value, run};

fn scalar(report: &RunReport, name: &str) -> f64 {
    match report.output(name) {
        Some(Value::Scalar(x)) => *x,
        other => panic!("output {name}: {other:?}"),
    }
}

fn scalars(report: &RunReport, name: &str) -> Vec<f64> {
    match report.output(name) {
        Some(Value::List(list)) => list
            .items
            .iter()
            .map(|v| match v {
                Value::Scalar(x) => *x,
                other => panic!("element of {name}: {other:?}"),
            })
            .collect(),
        other => panic!("output {name}: {other:?}"),
    }
}

fn only(outputs: &[&str]) -> RunOptions {
    RunOptions {
        outputs: outputs.iter().map(|s| s.to_string()).collect(),
        ..RunOptions::default()
    }
}

#[test]
fn a_list_literal_into_a_scalar_port_maps_the_node() {
    let (reg, calls) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "a": (op: "t.source", params: (value: 1.0)),
            "b": (op: "t.source", params: (value: 2.0)),
            "c": (op: "t.source", params: (value: 10.0)),
            "m": (op: "t.add", inputs: { "a": ["a.value", "c.value", "b.value"] }, params: (offset: 0.5)),
        }, outputs: { "each": "m.sum" })"#,
    );
    let m = &graph.nodes[graph.node_index("m").unwrap()];
    assert!(m.is_mapped());
    assert_eq!(m.output_types[0].to_string(), "List<Scalar>");
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalars(&report, "each"), [1.5, 10.5, 2.5]);
    assert_eq!(calls.get("t.add"), 3);
    // Every referenced node is a dependency: the DOT text has one edge per element.
    let dot = graph.to_dot();
    assert_eq!(dot.matches("-> n3").count(), 3, "{dot}");
}

#[test]
fn a_list_literal_into_a_list_port_is_passed_as_the_list() {
    let (reg, calls) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "a": (op: "t.source", params: (value: 1.0)),
            "b": (op: "t.source", params: (value: 2.0)),
            "c": (op: "t.collect", inputs: { "items": ["a.value", "b.value", "a.value"] }),
        }, outputs: { "total": "c.total" })"#,
    );
    assert!(!graph.nodes[graph.node_index("c").unwrap()].is_mapped());
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "total"), 4.0);
    assert_eq!(calls.get("t.collect"), 1);
}

const INDEXED: &str = r#"Graph(nodes: {
    "s": (op: "t.source", params: (value: 1.0)),
    "r": (op: "t.repeat", inputs: { "x": "s.value" }, params: (count: 3)),
    "first": (op: "t.add", inputs: { "a": "r.items[0]", "b": "r.items[-1]" }),
    "pair": (op: "t.collect", inputs: { "items": ["r.items[-1]", "r.items[1]"] }),
}, outputs: {
    "first": "first.sum",
    "second": "r.items[1]",
    "last": "r.items[-1]",
    "pair": "pair.total",
})"#;

#[test]
fn indexed_references_select_elements_in_inputs_and_outputs() {
    let (reg, _) = registry();
    let graph = load(&reg, INDEXED);
    let last = graph.outputs.iter().find(|o| o.name == "last").unwrap();
    assert_eq!(last.index, Some(-1));
    assert_eq!(last.ty.to_string(), "Scalar");
    assert!(!graph.nodes[graph.node_index("first").unwrap()].is_mapped());
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert!(report.failures.is_empty(), "{:?}", report.failures);
    // r.items = [1, 2, 3]
    assert_eq!(scalar(&report, "first"), 1.0 + 3.0);
    assert_eq!(scalar(&report, "second"), 2.0);
    assert_eq!(scalar(&report, "last"), 3.0);
    assert_eq!(scalar(&report, "pair"), 3.0 + 2.0);
}

#[test]
fn an_index_out_of_range_fails_at_run_time_naming_node_port_index_and_length() {
    let (reg, _) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "s": (op: "t.source", params: (value: 1.0)),
            "r": (op: "t.repeat", inputs: { "x": "s.value" }, params: (count: 3)),
            "bad": (op: "t.add", inputs: { "a": "r.items[-4]" }),
            "after": (op: "t.add", inputs: { "a": "bad.sum" }),
            "fine": (op: "t.add", inputs: { "a": "r.items[2]" }),
        }, outputs: { "after": "after.sum", "fine": "fine.sum", "far": "r.items[3]" })"#,
    );
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "fine"), 3.0);
    assert!(report.output("after").is_none() && report.output("far").is_none());
    let text: Vec<String> = report.failures.iter().map(ToString::to_string).collect();
    assert_eq!(text.len(), 2, "{text:?}");
    assert!(
        text.iter().any(|t| t.contains("node `bad`")
            && t.contains("input `a`")
            && t.contains("index -4 is out of range for `r.items`, a list of 3 elements")
            && t.starts_with("test.ron:4:")),
        "{text:?}"
    );
    assert!(
        text.iter().any(|t| t.contains("output `far`")
            && t.contains("index 3 is out of range for `r.items`, a list of 3 elements")),
        "{text:?}"
    );
    let status = |name: &str| {
        report
            .nodes
            .iter()
            .find(|n| n.name == name)
            .map(|n| n.status)
            .unwrap()
    };
    assert_eq!(status("bad"), NodeStatus::Failed);
    assert_eq!(status("after"), NodeStatus::Skipped);
}

#[test]
fn indexing_an_empty_list_is_out_of_range() {
    let (reg, _) = registry();
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "s": (op: "t.source"),
            "r": (op: "t.repeat", inputs: { "x": "s.value" }, params: (count: 0)),
        }, outputs: { "last": "r.items[-1]" })"#,
    );
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(report.failures.len(), 1);
    assert!(
        report.failures[0]
            .message
            .contains("index -1 is out of range for `r.items`, a list of 0 elements"),
        "{}",
        report.failures[0]
    );
}

#[test]
fn list_literal_and_index_errors_are_reported_at_their_positions() {
    let (reg, _) = registry();
    let found = errors(
        &reg,
        r#"Graph(nodes: {
    "s": (op: "t.source"),
    "r": (op: "t.repeat", inputs: { "x": "s.value" }),
    "mix": (op: "t.collect", inputs: { "items": ["s.value", "r.items"] }),
    "flat": (op: "t.add", inputs: { "a": "s.value[0]" }),
    "word": (op: "t.add", inputs: { "a": "r.items[x]" }),
    "open": (op: "t.add", inputs: { "a": "r.items[1" }),
    "tail": (op: "t.add", inputs: { "a": "r.items[1]x" }),
    "none": (op: "t.collect", inputs: { "items": [] }),
    "typo": (op: "t.collect", inputs: { "items": ["s.value", "s.vlue", "zz.value"] }),
    "twice": (op: "t.add", inputs: { "a": "r.items[0][1]" }),
}, outputs: { "o": "s.value[-1]" })"#,
    );
    let expected = [
        (
            "test.ron:4:61",
            "type mismatch in list: `r.items` is List<Scalar>, but `s.value` is Scalar",
        ),
        ("test.ron:5:42", "`s.value` is Scalar, not a list"),
        (
            "test.ron:6:42",
            "malformed input reference `r.items[x]`: index `x` is not an integer",
        ),
        (
            "test.ron:7:42",
            "malformed input reference `r.items[1`: missing `]`",
        ),
        ("test.ron:8:42", "malformed input reference `r.items[1]x`"),
        ("test.ron:9:50", "empty input list `[]`"),
        ("test.ron:10:65", "node `s` (t.source) has no output `vlue`"),
        ("test.ron:10:72", "input refers to unknown node `zz`"),
        (
            "test.ron:11:43",
            "malformed input reference `r.items[0][1]`",
        ),
        ("test.ron:12:20", "`s.value` is Scalar, not a list"),
    ];
    for (location, message) in expected {
        assert!(
            found
                .iter()
                .any(|f| f.starts_with(location) && f.contains(message)),
            "expected `{location}: …{message}…` among:\n{}",
            found.join("\n")
        );
    }
    assert_eq!(found.len(), expected.len(), "{}", found.join("\n"));
}

#[test]
fn references_inside_a_list_literal_get_suggestions() {
    let (reg, _) = registry();
    let source = common::source(
        "s.ron",
        r#"Graph(nodes: {
            "src": (op: "t.source"),
            "c": (op: "t.collect", inputs: { "items": ["src.value", "src.valeu", "srcc.value"] }),
        }, outputs: {})"#,
    );
    let diags = load_source(&reg, &source, &[]).unwrap_err();
    let helps: Vec<String> = diags.0.iter().filter_map(|d| d.help.clone()).collect();
    for expected in ["did you mean `value`?", "did you mean `src`?"] {
        assert!(
            helps.iter().any(|h| h == expected),
            "{expected} not in {helps:?}"
        );
    }
}

#[test]
fn a_list_literal_wired_to_a_wrong_port_type_is_a_mismatch() {
    let (reg, _) = registry();
    let found = errors(
        &reg,
        r#"Graph(nodes: {
    "r": (op: "t.repeat", inputs: { "x": ["s.value"] }),
    "s": (op: "t.source"),
    "c": (op: "t.collect", inputs: { "items": ["r.items", "r.items"] }),
}, outputs: {})"#,
    );
    // `x` (Scalar) accepts a List<Scalar> by mapping, so `r` is mapped and `r.items` is
    // List<List<Scalar>>; `items` (List<Scalar>) does not accept a list of those.
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].starts_with("test.ron:4:47")
            && found[0].contains(
                "is List<List<List<Scalar>>>, but input `items` of `c` expects List<Scalar>"
            ),
        "{found:?}"
    );
}

#[test]
fn cache_keys_depend_on_list_order_and_indices() {
    let (reg, calls) = registry();
    // Equal keys are computed once per run (`Shared`), so the call count shows key equality.
    let graph = load(
        &reg,
        r#"Graph(nodes: {
            "a": (op: "t.source", params: (value: 1.0)),
            "b": (op: "t.source", params: (value: 2.0)),
            "ab": (op: "t.collect", inputs: { "items": ["a.value", "b.value"] }),
            "ab2": (op: "t.collect", inputs: { "items": ["a.value", "b.value"] }),
            "ba": (op: "t.collect", inputs: { "items": ["b.value", "a.value"] }),
            "r": (op: "t.repeat", inputs: { "x": "a.value" }),
            "i0": (op: "t.add", inputs: { "a": "r.items[0]" }),
            "i0b": (op: "t.add", inputs: { "a": "r.items[0]" }),
            "i1": (op: "t.add", inputs: { "a": "r.items[1]" }),
            "whole": (op: "t.add", inputs: { "a": "r.items" }),
            "one": (op: "t.add", inputs: { "a": ["a.value"] }),
            "plain": (op: "t.add", inputs: { "a": "a.value" }),
        }, outputs: {
            "ab": "ab.total", "ab2": "ab2.total", "ba": "ba.total",
            "i0": "i0.sum", "i0b": "i0b.sum", "i1": "i1.sum", "whole": "whole.sum",
            "one": "one.sum", "plain": "plain.sum",
        })"#,
    );
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "ab"), scalar(&report, "ba"));
    let status = |name: &str| {
        report
            .nodes
            .iter()
            .find(|n| n.name == name)
            .map(|n| n.status)
            .unwrap()
    };
    assert_eq!(status("ab2"), NodeStatus::Shared);
    assert_eq!(status("ba"), NodeStatus::Computed);
    assert_eq!(status("i0b"), NodeStatus::Shared);
    assert_eq!(status("i1"), NodeStatus::Computed);
    assert_eq!(status("whole"), NodeStatus::Computed);
    assert_eq!(status("one"), NodeStatus::Computed);
    assert_eq!(status("plain"), NodeStatus::Computed);
    assert_eq!(calls.get("t.collect"), 2);
    // i0, i1, whole (3 elements), one (1 element), plain.
    assert_eq!(calls.get("t.add"), 1 + 1 + 3 + 1 + 1);
}

#[test]
fn the_disk_cache_tells_list_orders_apart() {
    let (reg, calls) = registry();
    let dir = common::temp_dir("refs-cache");
    let text = |order: &str| {
        format!(
            r#"Graph(nodes: {{
                "a": (op: "t.source", params: (value: 1.0)),
                "b": (op: "t.source", params: (value: 2.0)),
                "c": (op: "t.collect", inputs: {{ "items": {order} }}),
            }}, outputs: {{ "total": "c.total" }})"#
        )
    };
    let options = RunOptions {
        cache_dir: Some(dir.clone()),
        ..RunOptions::default()
    };
    let ab = load(&reg, &text(r#"["a.value", "b.value"]"#));
    let ba = load(&reg, &text(r#"["b.value", "a.value"]"#));
    run(&ab, &options).unwrap();
    assert_eq!(calls.get("t.collect"), 1);
    let again = run(&ab, &options).unwrap();
    assert_eq!(again.count(NodeStatus::Cached), 1);
    assert_eq!(calls.get("t.collect"), 1);
    let other = run(&ba, &options).unwrap();
    // The sources are shared with the first graph; the collector is not.
    assert_eq!(other.count(NodeStatus::Cached), 2);
    assert_eq!(other.count(NodeStatus::Computed), 1);
    assert_eq!(calls.get("t.collect"), 2);
    let _ = std::fs::remove_dir_all(dir);
}

const BRANCHES: &str = r#"Graph(nodes: {
    "a": (op: "t.source", params: (value: 1.0)),
    "b": (op: "t.source", params: (value: 2.0)),
    "ab": (op: "t.collect", inputs: { "items": ["a.value", "b.value"] }),
    "c": (op: "t.source", params: (value: 5.0)),
    "r": (op: "t.repeat", inputs: { "x": "c.value" }),
    "d": (op: "t.source", params: (value: 7.0)),
}, outputs: { "left": "ab.total", "right": "r.items[-1]", "alone": "d.value" })"#;

#[test]
fn only_what_the_requested_outputs_need_runs() {
    let (reg, calls) = registry();
    let graph = load(&reg, BRANCHES);
    let report = run(&graph, &only(&["left"])).unwrap();
    assert_eq!(scalar(&report, "left"), 3.0);
    assert_eq!(calls.get("t.source"), 2);
    assert_eq!(calls.get("t.repeat"), 0);
    assert_eq!(report.count(NodeStatus::Idle), 3);

    let (reg, calls) = registry();
    let graph = load(&reg, BRANCHES);
    let report = run(&graph, &only(&["right"])).unwrap();
    assert_eq!(scalar(&report, "right"), 7.0);
    assert_eq!(calls.get("t.source"), 1);
    assert_eq!(calls.get("t.collect"), 0);
    assert_eq!(report.outputs.len(), 1);
}

#[test]
fn a_list_literal_feeds_a_subgraph_input() {
    let (reg, _) = registry();
    let dir = common::temp_dir("refs-sub");
    std::fs::write(
        dir.join("sum.ron"),
        r#"Graph(
            inputs: { "items": "List<Scalar>" },
            nodes: { "c": (op: "t.collect", inputs: { "items": "inputs.items" }) },
            outputs: { "total": "c.total", "first": "inputs.items[0]" },
        )"#,
    )
    .unwrap();
    let main = dir.join("main.ron");
    std::fs::write(
        &main,
        r#"Graph(nodes: {
            "a": (op: "t.source", params: (value: 1.0)),
            "b": (op: "t.source", params: (value: 2.0)),
            "sub": (op: "graph", params: (path: "sum.ron"), inputs: { "items": ["b.value", "a.value"] }),
        }, outputs: { "total": "sub.total", "first": "sub.first" })"#,
    )
    .unwrap();
    let graph = ocellus_engine::load_graph(&reg, &main, &[]).unwrap();
    let report = run(&graph, &RunOptions::default()).unwrap();
    assert_eq!(scalar(&report, "total"), 3.0);
    assert_eq!(scalar(&report, "first"), 2.0);
    let _ = std::fs::remove_dir_all(dir);
}
