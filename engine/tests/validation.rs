//! Validation reports every problem at once, each at the right `file:line:col`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{errors, load, registry};
use ocellus_engine::resolve::{Override, load_source};

#[test]
fn every_problem_of_a_file_is_reported_with_its_position() {
    let (reg, _) = registry();
    let found = errors(
        &reg,
        r#"Graph(
    nodes: {
        "a": (op: "t.sorce"),
        "b": (op: "t.source", params: (valu: 1.0)),
        "c": (op: "t.source", params: (value: "x")),
        "d": (op: "t.source", params: (value: 5000)),
        "e": (op: "t.add", inputs: { "a": "zz.value" }),
        "f": (op: "t.add", inputs: { "a": "c.vlue", "q": "c.value" }),
        "g": (op: "t.add"),
        "h": (op: "t.source", params: (value: 13)),
        "i": (op: "t.add", inputs: { "a": "i.sum" }),
        "j": (op: "t.add", inputs: { "a": "k.sum" }),
        "k": (op: "t.add", inputs: { "a": "j.sum" }),
        "l": (op: "t.add", inputs: { "a": "m" }),
        "m": (op: "t.repeat", inputs: { "x": "b.value" }),
        "n": (op: "t.collect", inputs: { "items": "c.value" }),
    },
    outputs: { "out": "nowhere.value" },
)"#,
    );
    let expected = [
        ("test.ron:3:19", "unknown operator `t.sorce`"),
        ("test.ron:4:40", "has no parameter `valu`"),
        ("test.ron:5:47", "expects float, found string \"x\""),
        ("test.ron:6:47", "must be ≤ 1000, got 5000"),
        ("test.ron:7:43", "unknown node `zz`"),
        ("test.ron:8:46", "has no output `vlue`"),
        ("test.ron:8:53", "has no input `q`"),
        ("test.ron:9:9", "missing required input `a` (Scalar)"),
        ("test.ron:10:39", "13 is unlucky"),
        ("test.ron:11:9", "dependency cycle: i → i"),
        ("test.ron:12:9", "dependency cycle: j → k → j"),
        ("test.ron:14:43", "malformed input reference `m`"),
        (
            "test.ron:16:51",
            "`c.value` is Scalar, but input `items` of `n` expects List<Scalar>",
        ),
        ("test.ron:18:23", "output refers to unknown node `nowhere`"),
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
fn suggestions_name_the_nearest_valid_name() {
    let (reg, _) = registry();
    let source = common::source(
        "s.ron",
        r#"Graph(nodes: {
            "src": (op: "t.sorce"),
            "sum": (op: "t.add", inputs: { "a": "srcc.value" }, params: (ofset: 1.0)),
        }, outputs: {})"#,
    );
    let diags = load_source(&reg, &source, &[]).unwrap_err();
    let helps: Vec<String> = diags.0.iter().filter_map(|d| d.help.clone()).collect();
    for expected in [
        "did you mean `t.source`?",
        "did you mean `src`?",
        "did you mean `offset`?",
    ] {
        assert!(
            helps.iter().any(|h| h == expected),
            "{expected} not in {helps:?}"
        );
    }
}

#[test]
fn overrides_are_checked_with_their_own_positions() {
    let (reg, _) = registry();
    let source = common::source(
        "o.ron",
        r#"Graph(nodes: { "s": (op: "t.source") }, outputs: { "v": "s.value" })"#,
    );
    let set = [
        Override::parse("s.value=2000").unwrap(),
        Override::parse("s.vale=1").unwrap(),
        Override::parse("x.value=1").unwrap(),
    ];
    let diags = load_source(&reg, &source, &set).unwrap_err();
    let found: Vec<String> = diags
        .0
        .iter()
        .map(|d| format!("{}: {}", d.location().unwrap(), d.message))
        .collect();
    assert!(
        found
            .iter()
            .any(|f| f.starts_with("--set:1:9") && f.contains("≤ 1000")),
        "{found:?}"
    );
    assert!(
        found
            .iter()
            .any(|f| f.starts_with("--set:1:3") && f.contains("no parameter `vale`")),
        "{found:?}"
    );
    assert!(
        found
            .iter()
            .any(|f| f.starts_with("--set:1:1") && f.contains("node `x`")),
        "{found:?}"
    );
}

#[test]
fn integer_parameters_reject_fractions_and_accept_in_range_values() {
    let (reg, _) = registry();
    let found = errors(
        &reg,
        r#"Graph(nodes: {
            "s": (op: "t.source"),
            "r": (op: "t.repeat", inputs: { "x": "s.value" }, params: (count: 2.5)),
        }, outputs: {})"#,
    );
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].contains("expects int, found float `2.5`"),
        "{found:?}"
    );
    let g = load(
        &reg,
        r#"Graph(nodes: {
            "s": (op: "t.source", params: (value: -3)),
            "r": (op: "t.repeat", inputs: { "x": "s.value" }, params: (count: 0)),
        }, outputs: { "r": "r.items" })"#,
    );
    assert_eq!(g.nodes.len(), 2);
}

#[test]
fn graphs_with_unbound_inputs_cannot_run_directly() {
    let (reg, _) = registry();
    let found = errors(
        &reg,
        r#"Graph(inputs: { "x": "Scalar" }, nodes: { "p": (op: "t.add", inputs: { "a": "inputs.x" }) }, outputs: {})"#,
    );
    assert!(
        found
            .iter()
            .any(|f| f.contains("graph input `x` is not bound")),
        "{found:?}"
    );
}
