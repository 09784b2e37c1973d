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
    },
    outputs: { "total": "c.total", "each": "m.sum" },
)"#;

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
