//! Property tests at the extremes of the loader: whatever bytes a graph file holds, loading never
//! panics, and every diagnostic points inside its source on a character boundary.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::registry;
use ocellus_engine::resolve::load_source;
use ocellus_engine::ron_syntax::{parse, to_ron_string};
use proptest::prelude::*;

const VALID: &str = r#"Graph(
    name: "props",
    nodes: {
        "a": (op: "t.source", params: (value: 1.5)),
        "b": (op: "t.add", inputs: { "a": "a.value", "b": "a.value" }, params: (offset: -2)),
        "r": (op: "t.repeat", inputs: { "x": "b.sum" }, params: (count: 3)),
        "m": (op: "t.add", inputs: { "a": "r.items" }),
        "c": (op: "t.collect", inputs: { "items": "m.sum" }),
        "l": (op: "t.collect", inputs: { "items": ["a.value", "b.sum", "r.items[-1]"] }),
        "p": (op: "t.add", inputs: { "a": ["a.value", "r.items[1]"], "b": "r.items[0]" }),
    },
    outputs: { "total": "c.total", "each": "m.sum", "first": "r.items[0]", "list": "l.total" },
)"#;

/// Reference texts: valid, indexed, malformed, odd characters.
fn reference() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("a.value".to_string()),
        Just("r.items".to_string()),
        "[a-z]{1,2}\\.[a-z]{1,6}",
        ("(a|r|m|zz)\\.(value|items|sum|x)", any::<i64>()).prop_map(|(r, i)| format!("{r}[{i}]")),
        ("(a|r)\\.(value|items)", "[\\[\\]0-9x\\- ]{0,6}")
            .prop_map(|(r, tail)| format!("{r}{tail}")),
        "\\PC{0,12}",
    ]
}

/// RON text for an input: one quoted reference or a list literal of them.
fn input_text() -> impl Strategy<Value = String> {
    let quote = |r: String| format!("{r:?}");
    prop_oneof![
        reference().prop_map(quote),
        prop::collection::vec(reference(), 0..4).prop_map(move |items| {
            let items: Vec<String> = items.into_iter().map(quote).collect();
            format!("[{}]", items.join(", "))
        }),
    ]
}

fn check_diagnostics(text: &str) {
    let (reg, _) = registry();
    let source = common::source("p.ron", text);
    if let Err(diags) = load_source(&reg, &source, &[]) {
        assert!(!diags.is_empty());
        for d in &diags.0 {
            if let (Some(src), Some(span)) = (&d.source, d.span) {
                assert!(
                    span.start <= span.end && span.end <= src.text.len(),
                    "{d:?}"
                );
                assert!(
                    src.text.is_char_boundary(span.start) && src.text.is_char_boundary(span.end),
                    "{d:?}"
                );
            }
        }
    }
}

#[test]
fn the_valid_graph_loads() {
    let (reg, _) = registry();
    assert!(load_source(&reg, &common::source("p.ron", VALID), &[]).is_ok());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    #[test]
    fn byte_edits_never_panic(edits in prop::collection::vec((0usize..VALID.len(), any::<u8>()), 1..6)) {
        let mut bytes = VALID.as_bytes().to_vec();
        for (at, byte) in edits {
            bytes[at] = byte;
        }
        check_diagnostics(&String::from_utf8_lossy(&bytes));
    }

    #[test]
    fn deletions_and_duplications_never_panic(start in 0usize..VALID.len(), len in 0usize..40, dup in any::<bool>()) {
        let end = (start + len).min(VALID.len());
        if VALID.is_char_boundary(start) && VALID.is_char_boundary(end) {
            let text = if dup {
                format!("{}{}", &VALID[..end], &VALID[start..])
            } else {
                format!("{}{}", &VALID[..start], &VALID[end..])
            };
            check_diagnostics(&text);
        }
    }

    #[test]
    fn generated_references_never_panic(
        port in "(a|b|items|x)",
        op in "(t\\.add|t\\.collect|t\\.repeat|graph)",
        input in input_text(),
        output in reference(),
    ) {
        let text = format!(
            "Graph(nodes: {{ \"a\": (op: \"t.source\"), \"r\": (op: \"t.repeat\", inputs: {{ \"x\": \"a.value\" }}), \"n\": (op: {op:?}, inputs: {{ {port:?}: {input} }}) }}, outputs: {{ \"o\": {output:?}, \"n\": \"n.sum\" }})"
        );
        check_diagnostics(&text);
        // Whatever loads also runs without panicking.
        let (reg, _) = registry();
        if let Ok(graph) = load_source(&reg, &common::source("p.ron", &text), &[]) {
            ocellus_engine::run(&graph, &ocellus_engine::RunOptions { threads: 1, ..Default::default() }).unwrap();
        }
    }

    #[test]
    fn arbitrary_text_never_panics(text in "\\PC{0,200}") {
        check_diagnostics(&text);
    }

    #[test]
    fn parsed_documents_round_trip_through_canonical_text(edits in prop::collection::vec((0usize..VALID.len(), any::<u8>()), 0..3)) {
        let mut bytes = VALID.as_bytes().to_vec();
        for (at, byte) in edits {
            bytes[at] = byte;
        }
        let text = String::from_utf8_lossy(&bytes);
        if let Ok(doc) = parse(&text) {
            let canonical = to_ron_string(&doc.value);
            let again = parse(&canonical).expect("canonical text parses");
            prop_assert_eq!(to_ron_string(&again.value), canonical);
        }
    }
}
