//! The broken-graph corpus (`tests/broken/`): one file per error kind, plus truncated files,
//! garbage bytes and deep nesting. Each must give exit 2 from both `check` and `run`, with the
//! expected `file:line:col` and message, and never a panic or a backtrace.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{ocellus, root, stderr};

/// (file, expected `line:col` — or `other.ron:line:col` when the problem is in an included file —,
/// expected message fragments).
const CORPUS: &[(&str, &str, &[&str])] = &[
    (
        "01_missing_comma.ron",
        "3:5",
        &["malformed RON: expected `,` or `)`"],
    ),
    ("02_unclosed_paren.ron", "5:5", &["malformed RON"]),
    ("03_truncated.ron", "4:22", &["unterminated string"]),
    ("04_invalid_utf8.ron", "3:16", &["not valid UTF-8"]),
    ("05_binary_garbage.ron", "1:4", &["not valid UTF-8"]),
    ("06_empty.ron", "1:1", &["empty document"]),
    (
        "07_unknown_op_suggest.ron",
        "5:22",
        &[
            "unknown operator `filter.gausian`",
            "did you mean `filter.gaussian`?",
        ],
    ),
    (
        "08_unknown_op.ron",
        "3:22",
        &[
            "unknown operator `mesh.teleport`",
            "`ocellus ops` lists every operator",
        ],
    ),
    (
        "09_unknown_param.ron",
        "4:85",
        &["has no parameter `sigam`", "did you mean `sigma`?"],
    ),
    (
        "10_param_wrong_type.ron",
        "4:92",
        &["`sigma` expects float, found string \"wide\""],
    ),
    (
        "11_param_negative.ron",
        "4:92",
        &["`sigma` must be ≥ 0, got -1.5", "allowed: 0 ≤ x ≤ 1000"],
    ),
    (
        "12_param_too_large.ron",
        "3:57",
        &["`width` must be ≤ 32768, got 100000"],
    ),
    (
        "13_unknown_choice.ron",
        "3:56",
        &["has no choice \"test_crad\"", "did you mean \"test_card\"?"],
    ),
    (
        "14_unquoted_string.ron",
        "3:22",
        &[
            "`op` must be a string, found an identifier",
            "strings are quoted",
        ],
    ),
    (
        "15_type_mismatch.ron",
        "5:60",
        &["type mismatch: `stats.stats` is Metrics, but input `image` of `blur` expects Image"],
    ),
    (
        "16_missing_input.ron",
        "3:9",
        &["missing required input `image` (Image)"],
    ),
    (
        "17_dangling_reference.ron",
        "4:60",
        &["unknown node `crad`", "did you mean `card`?"],
    ),
    (
        "18_unknown_output_port.ron",
        "4:66",
        &["has no output `img`", "did you mean `image`?"],
    ),
    (
        "19_unknown_input_port.ron",
        "4:74",
        &["has no input `mask`", "available inputs: `image`"],
    ),
    (
        "20_duplicate_node.ron",
        "4:9",
        &["duplicate node `card`", "first defined here"],
    ),
    ("21_cycle.ron", "3:9", &["dependency cycle: a → b → a"]),
    (
        "22_self_cycle.ron",
        "3:9",
        &["dependency cycle: loop → loop"],
    ),
    (
        "23_missing_subgraph.ron",
        "3:45",
        &["missing subgraph file", "does_not_exist.ron"],
    ),
    (
        "24_malformed_reference.ron",
        "4:60",
        &["malformed input reference `card`"],
    ),
    (
        "25_unknown_graph_field.ron",
        "3:5",
        &["unknown graph field `node`", "did you mean `nodes`?"],
    ),
    (
        "26_missing_nodes.ron",
        "1:1",
        &["the graph has no `nodes` field"],
    ),
    (
        "27_wrong_struct_name.ron",
        "1:1",
        &["expected `Graph(...)`, found `Pipeline(...)`"],
    ),
    (
        "28_node_without_op.ron",
        "3:9",
        &["node `card` has no `op`"],
    ),
    (
        "29_output_unknown_node.ron",
        "5:24",
        &["unknown node `cards`", "did you mean `card`?"],
    ),
    (
        "30_params_not_struct.ron",
        "3:49",
        &["`params` must be a struct", "found an integer"],
    ),
    (
        "31_nan_param.ron",
        "4:92",
        &["`sigma` must be finite, got NaN"],
    ),
    ("32_even_kernel.ron", "4:84", &["`ksize` must be odd"]),
    (
        "33_float_for_integer.ron",
        "3:57",
        &["`width` expects int, found float `19.5`"],
    ),
    (
        "34_invalid_node_name.ron",
        "3:9",
        &["invalid node name `my.card`"],
    ),
    (
        "35_list_wrong_length.ron",
        "4:89",
        &["`roi` expects 4 values, found 3"],
    ),
    (
        "36_recursive_subgraph.ron",
        "sub/includes_parent.ron:3:46",
        &["includes itself"],
    ),
    ("37_deep_nesting.ron", "1:129", &["nesting too deep"]),
    ("38_integer_overflow.ron", "3:57", &["integer out of range"]),
    (
        "39_many_problems.ron",
        "4:50",
        &["no parameter `widht`", "5 problems found"],
    ),
    (
        "40_subgraph_input_type.ron",
        "5:85",
        &[
            "is Metrics, but input `image` of `blurred` expects Image",
            "1 problem found",
        ],
    ),
    (
        "41_single_quoted_string.ron",
        "3:22",
        &["strings use double quotes"],
    ),
    (
        "42_irrelevant_param.ron",
        "3:49",
        &["`spokes` applies only to kind \"siemens_star\""],
    ),
    (
        "43_subgraph_lists_plugin.ron",
        "sub/with_plugin.ron:2:15",
        &["lists plugin `libsomething.so`", "top-level graph"],
    ),
    (
        "44_animation_unknown_param.ron",
        "5:39",
        &[
            "track `blur.sigam`: `filter.gaussian` has no parameter `sigam`",
            "did you mean `sigma`?",
        ],
    ),
    (
        "45_animation_key_out_of_range.ron",
        "6:62",
        &["at frame 7 (0.700 s): parameter out of range: `sigma` must be ≥ 0"],
    ),
];

#[test]
fn corpus_covers_every_file() {
    let mut files: Vec<String> = std::fs::read_dir(root().join("tests/broken"))
        .unwrap()
        .map(|e| e.unwrap())
        .filter(|e| e.path().is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    let listed: Vec<&str> = CORPUS.iter().map(|(f, _, _)| *f).collect();
    assert_eq!(
        files, listed,
        "every file in tests/broken has an expectation, and only those"
    );
    assert!(CORPUS.len() >= 30);
}

#[test]
fn every_broken_graph_is_reported_precisely_and_never_panics() {
    let mut failures = Vec::new();
    for (file, line_col, fragments) in CORPUS {
        let path = format!("tests/broken/{file}");
        for command in ["check", "run"] {
            let out = ocellus(&[command, &path]);
            let err = stderr(&out);
            let location = if line_col.contains(".ron:") {
                format!("tests/broken/{line_col}")
            } else {
                format!("{path}:{line_col}")
            };
            let mut problems = Vec::new();
            if out.status.code() != Some(2) {
                problems.push(format!("exit {:?} instead of 2", out.status.code()));
            }
            if !err.contains(&location) {
                problems.push(format!("no `{location}`"));
            }
            for fragment in *fragments {
                if !err.contains(fragment) {
                    problems.push(format!("no `{fragment}`"));
                }
            }
            for forbidden in ["panicked", "RUST_BACKTRACE", "stack backtrace"] {
                if err.contains(forbidden) {
                    problems.push(format!("contains `{forbidden}`"));
                }
            }
            if !out.stdout.is_empty() {
                problems.push("printed to stdout".into());
            }
            if !problems.is_empty() {
                failures.push(format!("{command} {file}: {}\n{err}", problems.join(", ")));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

#[test]
fn every_truncation_of_a_valid_graph_is_a_clean_error() {
    let text = std::fs::read_to_string(root().join("graphs/edges.ron")).unwrap();
    let dir = common::temp_dir("truncate");
    let path = dir.join("t.ron");
    // Every 7th prefix keeps the test quick while crossing every token kind.
    for end in (0..text.len())
        .step_by(7)
        .filter(|&e| text.is_char_boundary(e))
    {
        std::fs::write(&path, &text[..end]).unwrap();
        let out = ocellus(&["check", path.to_str().unwrap()]);
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "prefix of {end} bytes: {err}");
        assert!(
            err.contains("t.ron:") && !err.contains("panicked"),
            "prefix of {end} bytes: {err}"
        );
    }
}
