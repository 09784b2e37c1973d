//! The documentation in `docs/`:
//!
//! - `docs/reference/operators.md` is generated from `ocellus --no-plugins ops --json` and must be
//!   current: `OCELLUS_UPDATE_DOCS=1 cargo test --test docs` rewrites it;
//! - the tutorial's graph `docs/tutorial/first.ron` is valid, runs, and has the snapshot the
//!   tutorial shows how to take;
//! - every example graph and every operator id the tutorial names exists, and every relative
//!   link in `docs/` points to a file.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::collections::HashSet;
use std::fmt::Write as _;
use std::path::Path;

use common::{ocellus, root, stderr, stdout, temp_dir};
use serde_json::Value as Json;

/// The generated operator reference, relative to the repository root.
const REFERENCE: &str = "docs/reference/operators.md";
/// Set (to anything but `0` or empty) to rewrite the reference instead of comparing it.
const UPDATE_VAR: &str = "OCELLUS_UPDATE_DOCS";
/// The command that regenerates the reference.
const UPDATE_COMMAND: &str = "OCELLUS_UPDATE_DOCS=1 cargo test --test docs";
/// The tutorial and its graph.
const TUTORIAL: &str = "docs/tutorial.md";
const FIRST_GRAPH: &str = "docs/tutorial/first.ron";

/// Port flags of `ops --json` shown in the inputs and outputs tables, with their labels.
const PORT_FLAGS: &[(&str, &str)] = &[
    ("optional", "optional"),
    ("per_frame", "per frame"),
    ("feedback", "feedback"),
];

/// Every built-in operator, as `ocellus --no-plugins ops --json` describes it (sorted by id).
fn builtin_ops() -> Vec<Json> {
    let out = ocellus(&["--no-plugins", "ops", "--json"]);
    assert!(out.status.success(), "ocellus ops --json: {}", stderr(&out));
    match serde_json::from_slice(&out.stdout).expect("ops --json prints JSON") {
        Json::Array(ops) => ops,
        other => panic!("ops --json: expected an array, got {other}"),
    }
}

fn str_field<'a>(value: &'a Json, key: &str) -> &'a str {
    value[key]
        .as_str()
        .unwrap_or_else(|| panic!("ops --json: `{key}` is not a string in {value}"))
}

fn list_field<'a>(value: &'a Json, key: &str) -> &'a [Json] {
    value[key]
        .as_array()
        .map(Vec::as_slice)
        .unwrap_or_else(|| panic!("ops --json: `{key}` is not a list in {value}"))
}

// ---------------------------------------------------------------------------------------------
// Rendering the reference

/// The anchor GitHub gives a heading: lower case, punctuation other than `-` and `_` dropped,
/// spaces turned into `-`.
fn slug(heading: &str) -> String {
    heading
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// `text` as an inline code span, with a delimiter longer than any backtick run inside.
fn code(text: &str) -> String {
    let longest = text.split(|c| c != '`').map(str::len).max().unwrap_or(0);
    let fence = "`".repeat(longest + 1);
    let pad = if text.starts_with('`') || text.ends_with('`') {
        " "
    } else {
        ""
    };
    format!("{fence}{pad}{text}{pad}{fence}")
}

/// Escapes Markdown in plain text (one paragraph, possibly several lines) so that it reads
/// literally, leaving its `code spans` as they are: `*`, `<`, `~`, `$` and `\` everywhere,
/// `_` at word boundaries, entity-like `&`, `](`, and line starts that would open a heading,
/// a quote, a `+` list or a rule. `- ` bullet lists and `1. ` numbered lists stay lists.
fn escape_inline(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let run_at = |i: usize| chars[i..].iter().take_while(|&&c| c == '`').count();
    let mut out = String::with_capacity(text.len() + text.len() / 8);
    let mut line_start = true;
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c == '`' {
            let n = run_at(i);
            // The closing run has exactly the same length.
            let mut j = i + n;
            let mut close = None;
            while j < chars.len() {
                if chars[j] == '`' {
                    let m = run_at(j);
                    if m == n {
                        close = Some(j);
                        break;
                    }
                    j += m;
                } else {
                    j += 1;
                }
            }
            match close {
                Some(j) => {
                    out.extend(&chars[i..j + n]);
                    i = j + n;
                }
                None => {
                    out.push_str(&"\\`".repeat(n));
                    i += n;
                }
            }
            line_start = false;
            continue;
        }
        if line_start && c != ' ' {
            let rest: String = chars[i..].iter().take_while(|&&c| c != '\n').collect();
            let rule = rest.trim_end().chars().all(|c| c == '-');
            if matches!(c, '#' | '>' | '+' | '=') || (c == '-' && rule) {
                out.push('\\');
            }
            line_start = false;
        }
        let next = chars.get(i + 1).copied();
        match c {
            '\n' => {
                out.push('\n');
                line_start = true;
            }
            '\\' | '*' | '<' | '~' | '$' => {
                out.push('\\');
                out.push(c);
            }
            '_' => {
                let inside_word = i > 0
                    && chars[i - 1].is_alphanumeric()
                    && next.is_some_and(char::is_alphanumeric);
                if !inside_word {
                    out.push('\\');
                }
                out.push('_');
            }
            '&' if next.is_some_and(|n| n.is_ascii_alphanumeric() || n == '#') => {
                out.push_str("&amp;");
            }
            ']' if next == Some('(') => out.push_str("\\]"),
            _ => out.push(c),
        }
        i += 1;
    }
    out
}

/// Text for a table cell: one line, escaped, with `|` escaped (also inside code spans, which
/// GitHub's tables require).
fn cell(text: &str) -> String {
    let one_line = text.split_whitespace().collect::<Vec<_>>().join(" ");
    escape_inline(&one_line).replace('|', "\\|")
}

fn code_cell(text: &str) -> String {
    code(text).replace('|', "\\|")
}

fn indent(line: &str) -> usize {
    line.len() - line.trim_start_matches(' ').len()
}

/// An operator's doc text as Markdown: paragraphs and `- ` / `1. ` lists as written, escaped;
/// blocks indented by four spaces or more (examples, formulas) as fenced code.
fn render_doc(doc: &str) -> String {
    let lines: Vec<&str> = doc.lines().map(str::trim_end).collect();
    let mut blocks: Vec<String> = Vec::new();
    let mut paragraph: Vec<&str> = Vec::new();
    let flush = |paragraph: &mut Vec<&str>, blocks: &mut Vec<String>| {
        if !paragraph.is_empty() {
            blocks.push(escape_inline(&paragraph.join("\n")));
            paragraph.clear();
        }
    };
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        if line.is_empty() {
            flush(&mut paragraph, &mut blocks);
            i += 1;
        } else if indent(line) >= 4 {
            flush(&mut paragraph, &mut blocks);
            // The block runs to its last indented line; blank lines inside it belong to it.
            let mut end = i;
            let mut j = i;
            while j < lines.len() && (lines[j].is_empty() || indent(lines[j]) >= 4) {
                if !lines[j].is_empty() {
                    end = j;
                }
                j += 1;
            }
            let body: Vec<&str> = lines[i..=end]
                .iter()
                .map(|l| l.get(4..).unwrap_or(""))
                .collect();
            let body = body.join("\n");
            let first = body.trim_start();
            let lang = if first.starts_with(['"', '(', '[']) {
                "ron"
            } else {
                "text"
            };
            let longest = body.split(|c| c != '`').map(str::len).max().unwrap_or(0);
            let fence = "`".repeat((longest + 1).max(3));
            blocks.push(format!("{fence}{lang}\n{body}\n{fence}"));
            i = end + 1;
        } else {
            paragraph.push(line);
            i += 1;
        }
    }
    flush(&mut paragraph, &mut blocks);
    blocks.join("\n\n")
}

/// The inputs or outputs table of an operator.
fn render_ports(out: &mut String, title: &str, ports: &[Json]) {
    if ports.is_empty() {
        return;
    }
    let flags: Vec<(&str, &str)> = PORT_FLAGS
        .iter()
        .copied()
        .filter(|(key, _)| ports.iter().any(|p| p[*key].as_bool() == Some(true)))
        .collect();
    writeln!(out, "**{title}**\n").unwrap();
    if flags.is_empty() {
        out.push_str("| name | type | doc |\n|---|---|---|\n");
    } else {
        out.push_str("| name | type | flags | doc |\n|---|---|---|---|\n");
    }
    for port in ports {
        write!(
            out,
            "| {} | {} |",
            code_cell(str_field(port, "name")),
            code_cell(str_field(port, "type"))
        )
        .unwrap();
        if !flags.is_empty() {
            let set: Vec<&str> = flags
                .iter()
                .filter(|(key, _)| port[*key].as_bool() == Some(true))
                .map(|(_, label)| *label)
                .collect();
            write!(out, " {} |", set.join(", ")).unwrap();
        }
        writeln!(out, " {} |", cell(str_field(port, "doc"))).unwrap();
    }
    out.push('\n');
}

/// A parameter value as it is written in a graph file.
fn value_text(value: &Json) -> String {
    match value {
        Json::Null => "None".into(),
        Json::Bool(b) => b.to_string(),
        Json::Number(n) => n.to_string(),
        Json::String(_) => value.to_string(),
        Json::Array(items) => {
            let items: Vec<String> = items.iter().map(value_text).collect();
            format!("[{}]", items.join(", "))
        }
        Json::Object(fields) => {
            let fields: Vec<String> = fields
                .iter()
                .map(|(k, v)| format!("{k}: {}", value_text(v)))
                .collect();
            format!("({})", fields.join(", "))
        }
    }
}

fn render_params(out: &mut String, params: &[Json]) {
    if params.is_empty() {
        return;
    }
    out.push_str("**Parameters**\n\n");
    out.push_str("| name | type | default | range | unit | doc |\n|---|---|---|---|---|---|\n");
    for param in params {
        let ty = str_field(param, "type");
        let default = &param["default"];
        let default = if ty == "path" && default.as_str() == Some("") {
            "*required*".to_string()
        } else {
            code_cell(&value_text(default))
        };
        writeln!(
            out,
            "| {} | {} | {default} | {} | {} | {} |",
            code_cell(str_field(param, "name")),
            code_cell(ty),
            cell(param["range"].as_str().unwrap_or("")),
            cell(param["unit"].as_str().unwrap_or("")),
            cell(str_field(param, "doc")),
        )
        .unwrap();
    }
    out.push('\n');
}

/// The whole reference, from the operators of `ops --json` in their order.
fn render_reference(ops: &[Json]) -> String {
    // Families in the order their first operator appears.
    let mut families: Vec<(&str, Vec<&Json>)> = Vec::new();
    for op in ops {
        let family = str_field(op, "family");
        match families.iter_mut().find(|(f, _)| *f == family) {
            Some((_, members)) => members.push(op),
            None => families.push((family, vec![op])),
        }
    }
    let mut anchors = HashSet::new();
    let mut anchor = |heading: &str| {
        let s = slug(heading);
        assert!(
            anchors.insert(s.clone()),
            "two headings share the anchor #{s}"
        );
        s
    };
    anchor("Operator reference");
    anchor("Families");

    let mut out = String::new();
    out.push_str("# Operator reference\n\n");
    writeln!(
        out,
        "<!-- Generated by tests/docs.rs from `ocellus --no-plugins ops --json`: do not edit by \
         hand.\n     Regenerate with `{UPDATE_COMMAND}`. -->\n"
    )
    .unwrap();
    writeln!(
        out,
        "Every built-in operator of Ocellus — {} operators in {} families — with its ports and \
         parameters.\nThe same text is printed by `ocellus ops OP` (`--json` for tools); operators \
         of loaded plugins\nare listed there too. Parameters go in a node's `params: (...)` or on \
         the command line as\n`--set NODE.PARAM=VALUE`; their types, ranges and units are checked \
         before anything runs.\nAn input port of type `T` fed a `List<T>` maps its operator over \
         the list. See the\n[tutorial](../tutorial.md) for how to use them.\n",
        ops.len(),
        families.len()
    )
    .unwrap();

    out.push_str("## Families\n\n| family | operators |\n|---|---|\n");
    for (family, members) in &families {
        writeln!(out, "| [{family}](#{}) | {} |", slug(family), members.len()).unwrap();
    }
    out.push('\n');

    for (family, members) in &families {
        anchor(family);
        writeln!(out, "## {family}\n").unwrap();
        out.push_str("| operator | summary |\n|---|---|\n");
        for op in members {
            let id = str_field(op, "id");
            writeln!(
                out,
                "| [{}](#{}) | {} |",
                code_cell(id),
                slug(id),
                cell(str_field(op, "summary"))
            )
            .unwrap();
        }
        out.push('\n');

        for op in members {
            let id = str_field(op, "id");
            anchor(id);
            writeln!(out, "### {}\n", code(id)).unwrap();
            let version = op["version"]
                .as_u64()
                .unwrap_or_else(|| panic!("{id}: no version"));
            writeln!(
                out,
                "**v{version}** · {}\n",
                escape_inline(str_field(op, "summary"))
            )
            .unwrap();
            if op["side_effects"].as_bool() == Some(true) {
                out.push_str(
                    "*Side effects:* it acts outside the graph (writes files), so it runs \
                     whenever an output needs it and is never served from the cache.\n\n",
                );
            }
            let doc = render_doc(str_field(op, "doc"));
            if !doc.is_empty() {
                out.push_str(&doc);
                out.push_str("\n\n");
            }
            render_ports(&mut out, "Inputs", list_field(op, "inputs"));
            render_ports(&mut out, "Outputs", list_field(op, "outputs"));
            render_params(&mut out, list_field(op, "params"));
        }
    }
    while out.ends_with("\n\n") {
        out.pop();
    }
    out
}

/// Writes `contents` to `path` atomically: a temporary file beside it, then a rename.
fn write_atomically(path: &Path, contents: &str) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let tmp = path.with_extension(format!("md.{}.tmp", std::process::id()));
    std::fs::write(&tmp, contents).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

fn update_requested() -> bool {
    std::env::var(UPDATE_VAR).is_ok_and(|v| !v.is_empty() && v != "0")
}

#[test]
fn operator_reference_is_current() {
    let ops = builtin_ops();
    assert!(!ops.is_empty(), "ops --json lists no operator");
    let rendered = render_reference(&ops);
    assert_eq!(
        rendered,
        render_reference(&ops),
        "rendering is not deterministic"
    );
    let path = root().join(REFERENCE);
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    if committed == rendered {
        return;
    }
    if update_requested() {
        write_atomically(&path, &rendered);
        eprintln!("rewrote {REFERENCE}");
        return;
    }
    let first_difference = committed
        .lines()
        .zip(rendered.lines())
        .position(|(a, b)| a != b)
        .unwrap_or_else(|| committed.lines().count().min(rendered.lines().count()));
    panic!(
        "{REFERENCE} is not what `ocellus --no-plugins ops --json` gives now (first difference \
         at line {}: {:?}).\nRegenerate it with `{UPDATE_COMMAND}` and commit the result.",
        first_difference + 1,
        rendered
            .lines()
            .nth(first_difference)
            .unwrap_or("<end of file>"),
    );
}

#[test]
fn reference_rendering_escapes_markdown() {
    assert_eq!(slug("analyze.depth_agreement"), "analyzedepth_agreement");
    assert_eq!(code("a`b"), "``a`b``");
    assert_eq!(
        escape_inline("List<T> of 2*x, `a*b<c>`, Σ_{i<k} x_i"),
        "List\\<T> of 2\\*x, `a*b<c>`, Σ\\_{i\\<k} x_i"
    );
    assert_eq!(
        escape_inline("# not a heading\n- a list"),
        "\\# not a heading\n- a list"
    );
    assert_eq!(escape_inline("an ` alone"), "an \\` alone");
    assert_eq!(cell("a | b\n  `c|d`"), "a \\| b `c\\|d`");
    assert_eq!(
        render_doc("Text:\n    \"n\": (op: \"x.y\"),\n\n    more\nEnd."),
        "Text:\n\n```ron\n\"n\": (op: \"x.y\"),\n\nmore\n```\n\nEnd."
    );
    assert_eq!(
        value_text(&serde_json::json!([1.5, null, "s"])),
        "[1.5, None, \"s\"]"
    );
}

// ---------------------------------------------------------------------------------------------
// The tutorial

#[test]
fn tutorial_graph_checks_and_runs() {
    let out = ocellus(&["--no-plugins", "check", FIRST_GRAPH]);
    assert!(out.status.success(), "check: {}", stderr(&out));
    assert!(stdout(&out).contains("ok"), "{}", stdout(&out));

    let dir = temp_dir("docs-first");
    let out = ocellus(&[
        "--no-plugins",
        "run",
        FIRST_GRAPH,
        "--emit",
        dir.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "run: {}", stderr(&out));
    assert!(
        stderr(&out).contains("5 computed"),
        "summary line: {}",
        stderr(&out)
    );
    for file in ["edges.png", "stats.json"] {
        assert!(dir.join(file).is_file(), "run --emit wrote no {file}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The snapshot test the tutorial shows, on its graph.
#[test]
fn tutorial_graph_snapshot() {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    let path = root().join("docs/tutorial/first.ron");
    let summary = |threads| {
        let report = ocellus_engine::testing::run_graph(&registry, &path, threads, &[]).unwrap();
        ocellus_engine::summary::summarize_outputs(&report.outputs)
    };
    let one = summary(1);
    assert_eq!(one, summary(2), "summary differs between 1 and 2 threads");
    insta::assert_snapshot!("tutorial_first", one);
}

/// Where a piece of code in a Markdown file sits.
#[derive(Debug, Clone, PartialEq)]
enum Piece {
    /// An inline code span.
    Inline,
    /// A line of a fenced block with this info string (`ron`, `bash`, `rust`, …).
    Fenced(String),
}

/// The inline code spans (outside fenced blocks) and the lines of the fenced blocks of a
/// Markdown file.
fn code_pieces(markdown: &str) -> Vec<(Piece, String)> {
    let mut pieces = Vec::new();
    // The open fence and its info string.
    let mut fence: Option<(String, String)> = None;
    for line in markdown.lines() {
        let trimmed = line.trim_start();
        match &fence {
            Some((f, lang)) => {
                if trimmed.starts_with(f.as_str())
                    && trimmed.trim_start_matches('`').trim().is_empty()
                {
                    fence = None;
                } else {
                    pieces.push((Piece::Fenced(lang.clone()), line.to_string()));
                }
            }
            None if trimmed.starts_with("```") => {
                let f: String = trimmed.chars().take_while(|&c| c == '`').collect();
                let lang = trimmed[f.len()..].trim().to_string();
                fence = Some((f, lang));
            }
            None => {
                // Every other part lies inside backticks: inline code spans must not cross
                // lines, so that this check sees them.
                assert!(
                    line.matches('`').count() % 2 == 0,
                    "an inline code span crosses a line break at: {line}"
                );
                for (k, part) in line.split('`').enumerate() {
                    if k % 2 == 1 {
                        pieces.push((Piece::Inline, part.to_string()));
                    }
                }
            }
        }
    }
    pieces
}

/// Tokens of the form `word.word` (lower-case ASCII, digits, `_`) that do not sit inside a
/// longer path or identifier, nor before `=`.
fn dotted_tokens(text: &str) -> Vec<&str> {
    let bytes = text.as_bytes();
    let word = |b: u8| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_';
    let mut tokens = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if !word(bytes[i]) || (i > 0 && (word(bytes[i - 1]) || b"./-:".contains(&bytes[i - 1]))) {
            i += 1;
            continue;
        }
        let start = i;
        while i < bytes.len() && word(bytes[i]) {
            i += 1;
        }
        if i + 1 < bytes.len() && bytes[i] == b'.' && word(bytes[i + 1]) {
            i += 1;
            while i < bytes.len() && word(bytes[i]) {
                i += 1;
            }
            let followed = bytes.get(i).copied();
            // `NODE.PARAM=VALUE` (`--set match.ratio=1.0`) names a node, not an operator.
            let part_of_more = followed.is_some_and(|b| {
                b.is_ascii_alphanumeric()
                    || b == b'/'
                    || b == b'='
                    || (b == b'.' && bytes.get(i + 1).is_some_and(|&n| word(n)))
            });
            if !part_of_more {
                tokens.push(&text[start..i]);
            }
        }
    }
    tokens
}

/// File extensions: `render.ron` names a file, not an operator.
const EXTENSIONS: &[&str] = &[
    "ron", "json", "png", "csv", "md", "svg", "rs", "toml", "so", "dylib", "dll", "ply", "obj",
    "txt", "gif",
];

#[test]
fn tutorial_names_only_real_graphs_and_operators() {
    let tutorial = std::fs::read_to_string(root().join(TUTORIAL)).unwrap();
    let ops = builtin_ops();
    let ids: HashSet<&str> = ops.iter().map(|op| str_field(op, "id")).collect();
    let families: HashSet<&str> = ops.iter().map(|op| str_field(op, "family")).collect();

    let mut named = 0;
    let mut unknown = Vec::new();
    for (kind, piece) in code_pieces(&tutorial) {
        // Rust code calls methods (`image.width`), and its operators are the plugin's.
        if kind == Piece::Fenced("rust".into()) {
            continue;
        }
        for token in dotted_tokens(&piece) {
            let (family, name) = token.split_once('.').unwrap();
            if !families.contains(family) || EXTENSIONS.contains(&name) {
                continue;
            }
            named += 1;
            if !ids.contains(token) {
                unknown.push(token.to_string());
            }
        }
    }
    assert!(named >= 5, "the tutorial names only {named} operators");
    assert!(
        unknown.is_empty(),
        "{TUTORIAL} names operators that do not exist: {unknown:?}"
    );

    // Every `graphs/….ron` and `docs/….ron` path it names exists.
    let mut paths = 0;
    for start in ["graphs/", "docs/"] {
        for (at, _) in tutorial.match_indices(start) {
            let before = tutorial[..at].chars().next_back();
            if before.is_some_and(|c| c.is_alphanumeric() || "_./-".contains(c)) {
                continue;
            }
            let path: String = tutorial[at..]
                .chars()
                .take_while(|&c| c.is_alphanumeric() || "_./-".contains(c))
                .collect();
            // A sentence may end right after the path.
            let path = path.trim_end_matches('.');
            if path.ends_with(".ron") {
                paths += 1;
                assert!(
                    root().join(path).is_file(),
                    "{TUTORIAL} names {path}, which does not exist"
                );
            }
        }
    }
    assert!(paths >= 2, "the tutorial names only {paths} graph files");
}

#[test]
fn relative_links_in_docs_resolve() {
    for doc in ["docs/README.md", TUTORIAL] {
        let text = std::fs::read_to_string(root().join(doc)).unwrap();
        let base = root().join(doc);
        let base = base.parent().unwrap();
        for (at, _) in text.match_indices("](") {
            let target: String = text[at + 2..].chars().take_while(|&c| c != ')').collect();
            let file = target.split('#').next().unwrap();
            if file.is_empty() || file.contains("://") {
                continue;
            }
            assert!(
                base.join(file).exists(),
                "{doc} links to {target}, which does not exist"
            );
        }
    }
}
