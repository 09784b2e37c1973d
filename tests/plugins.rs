//! Plugins end to end: builds the example plugin (and fake ones) as real shared libraries and
//! loads them through the CLI in every supported way.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use common::{root, stderr, stdout, temp_dir};
use serde_json::Value as Json;

/// Builds the plugin crates (`minimal`, `kuwahara`, `lines`) once per test process, in their own
/// target folder (the outer `cargo test` holds the lock of the main one), and returns the
/// folder holding the libraries.
fn plugin_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let target = root().join("target").join("plugin-tests");
        let status = Command::new(env!("CARGO"))
            .args(["build", "--quiet"])
            .args([
                "-p",
                "ocellus-plugin-minimal",
                "-p",
                "ocellus-plugin-kuwahara",
                "-p",
                "ocellus-plugin-lines",
            ])
            .arg("--target-dir")
            .arg(&target)
            .current_dir(root())
            .status()
            .expect("cargo runs");
        assert!(status.success(), "building the plugins failed");
        target.join("debug")
    })
}

/// The built library of plugin crate `ocellus_plugin_NAME`.
fn plugin_library(name: &str) -> PathBuf {
    let lib = plugin_dir().join(library_name(&format!("ocellus_plugin_{name}")));
    assert!(lib.is_file(), "{} not found", lib.display());
    lib
}

/// The minimal example plugin.
fn minimal_plugin() -> &'static Path {
    static LIB: OnceLock<PathBuf> = OnceLock::new();
    LIB.get_or_init(|| plugin_library("minimal"))
}

fn library_name(stem: &str) -> String {
    format!(
        "{}{stem}{}",
        std::env::consts::DLL_PREFIX,
        std::env::consts::DLL_SUFFIX
    )
}

/// Compiles a single-file fixture from `tests/fixtures` into a cdylib in `dir`.
fn fixture_library(source: &str, dir: &Path) -> PathBuf {
    let rustc = std::env::var_os("RUSTC").unwrap_or_else(|| "rustc".into());
    let out = dir.join(library_name(source));
    let status = Command::new(rustc)
        .args(["--edition", "2024", "--crate-type", "cdylib", "-o"])
        .arg(&out)
        .arg(root().join("tests/fixtures").join(format!("{source}.rs")))
        .status()
        .expect("rustc runs");
    assert!(status.success(), "compiling fixture {source} failed");
    out
}

/// Runs `ocellus ARGS` with `OCELLUS_PLUGIN_PATH` set to `plugin_path` (or unset).
fn ocellus_env(args: &[&str], plugin_path: Option<&Path>) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_ocellus"));
    cmd.args(args)
        .current_dir(root())
        .env_remove("OCELLUS_LOG")
        .env_remove("OCELLUS_PLUGIN_PATH");
    if let Some(p) = plugin_path {
        cmd.env("OCELLUS_PLUGIN_PATH", p);
    }
    cmd.output().expect("ocellus binary runs")
}

const NODES: &str = r#"
    nodes: {
        "card": (op: "capture.pattern", params: (kind: "checkerboard", width: 32, height: 16, square: 8)),
        "inv": (op: "minimal.invert", inputs: { "image": "card.image" }),
        "st": (op: "minimal.stats", inputs: { "image": "inv.image" }, params: (label: "inverted")),
    },
    outputs: { "inv": "inv.image", "mean": "st.mean", "pixels": "st.pixels", "text": "st.text", "metrics": "st.metrics" },
)
"#;

fn graph_file(dir: &Path, plugins: Option<&str>) -> String {
    let path = dir.join("plug.ron");
    let plugins = plugins.map_or(String::new(), |p| format!("    plugins: [{p:?}],\n"));
    std::fs::write(
        &path,
        format!("Graph(\n    name: \"plug\",\n{plugins}{NODES}"),
    )
    .unwrap();
    path.to_string_lossy().into_owned()
}

fn assert_expected_outputs(out: &Output) {
    assert!(out.status.success(), "{}", stderr(out));
    let text = stdout(out);
    for needle in [
        r#""inv": Image(width: 32, height: 16, format: "rgb_u8", min: [0, 0, 0], mean: [127.5, 127.5, 127.5], max: [255, 255, 255]"#,
        r#""mean": Scalar(127.5)"#,
        r#""pixels": Integer(512)"#,
        r#""text": Text("inverted: mean 127.500 over 512 pixels")"#,
        r#""pixels": 512"#,
    ] {
        assert!(text.contains(needle), "missing {needle} in\n{text}");
    }
}

#[test]
fn runs_a_plugin_given_with_the_flag() {
    let dir = temp_dir("plugin-flag");
    let graph = graph_file(&dir, None);
    let lib = minimal_plugin().to_str().unwrap();
    assert_expected_outputs(&ocellus_env(&["run", &graph, "--plugin", lib], None));
    // The other commands take the flag too.
    for cmd in ["check", "dot", "snapshot"] {
        let out = ocellus_env(&[cmd, &graph, "--plugin", lib], None);
        assert!(out.status.success(), "{cmd}: {}", stderr(&out));
    }
}

#[test]
fn runs_a_plugin_from_the_environment() {
    let dir = temp_dir("plugin-env");
    let graph = graph_file(&dir, None);
    // A folder contributes every library in it.
    let folder = dir.join("plugins");
    std::fs::create_dir_all(&folder).unwrap();
    std::fs::copy(minimal_plugin(), folder.join(library_name("minimal"))).unwrap();
    std::fs::write(folder.join("README.txt"), "not a library").unwrap();
    assert_expected_outputs(&ocellus_env(&["run", &graph], Some(&folder)));
    // And a file directly.
    assert_expected_outputs(&ocellus_env(&["run", &graph], Some(minimal_plugin())));
}

#[test]
fn runs_a_plugin_listed_in_the_graph() {
    let dir = temp_dir("plugin-graph");
    std::fs::copy(minimal_plugin(), dir.join(library_name("minimal"))).unwrap();
    let graph = graph_file(&dir, Some(&library_name("minimal")));
    assert_expected_outputs(&ocellus_env(&["run", &graph], None));
    // Also named on the command line: loading the same library twice is harmless.
    let lib = dir.join(library_name("minimal"));
    let out = ocellus_env(
        &["snapshot", &graph, "--plugin", lib.to_str().unwrap()],
        None,
    );
    assert!(out.status.success(), "{}", stderr(&out));
}

#[test]
fn a_missing_graph_plugin_is_a_diagnostic_at_its_string() {
    let dir = temp_dir("plugin-graph-missing");
    let graph = graph_file(&dir, Some("nowhere/libnothing.so"));
    let out = ocellus_env(&["check", &graph], None);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(err.contains("ocellus::plugin"), "{err}");
    assert!(err.contains("plug.ron:3:15"), "{err}");
    assert!(err.contains("libnothing.so"), "{err}");
}

#[test]
fn ops_shows_the_plugin_origin() {
    let lib = minimal_plugin();
    let out = ocellus_env(&["ops", "--json", "--plugin", lib.to_str().unwrap()], None);
    assert!(out.status.success(), "{}", stderr(&out));
    let ops: Json = serde_json::from_str(&stdout(&out)).unwrap();
    let invert = ops
        .as_array()
        .unwrap()
        .iter()
        .find(|o| o["id"] == "minimal.invert")
        .expect("minimal.invert listed");
    let origin = invert["origin"].as_str().unwrap();
    assert!(origin.starts_with("plugin:minimal ("), "{origin}");
    assert!(origin.contains("ocellus_plugin_minimal"), "{origin}");
    let guard = ocellus_env(
        &["ops", "minimal.guard", "--plugin", lib.to_str().unwrap()],
        None,
    );
    let text = stdout(&guard);
    assert!(text.contains("plugin:minimal"), "{text}");
    assert!(text.contains("panic: bool = false"), "{text}");
}

const FAILING: &str = r#"Graph(
    name: "failing",
    nodes: {
        "card": (op: "capture.pattern", params: (kind: "checkerboard", width: 16, height: 16, square: 4)),
        "inv": (op: "minimal.invert", inputs: { "image": "card.image" }),
        "st": (op: "minimal.stats", inputs: { "image": "card.image" }),
        "boom": (op: "minimal.guard", inputs: { "x": "st.mean" }, params: (panic: true)),
        "nope": (op: "minimal.guard", inputs: { "x": "st.mean" }, params: (fail: true)),
    },
    outputs: { "inv": "inv.image", "boom": "boom.y", "nope": "nope.y" },
)
"#;

#[test]
fn a_panicking_plugin_fails_only_its_node() {
    let dir = temp_dir("plugin-panic");
    let graph = dir.join("failing.ron");
    std::fs::write(&graph, FAILING).unwrap();
    let emit = dir.join("out");
    let lib = minimal_plugin().to_str().unwrap();
    let out = ocellus_env(
        &[
            "run",
            graph.to_str().unwrap(),
            "--plugin",
            lib,
            "--emit",
            emit.to_str().unwrap(),
        ],
        None,
    );
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("boom"), "{err}");
    assert!(err.contains("plugin `minimal` panicked"), "{err}");
    assert!(err.contains("guard asked to panic"), "{err}");
    assert!(err.contains("nope"), "{err}");
    assert!(
        err.contains("plugin `minimal`: guard asked to fail"),
        "{err}"
    );
    assert!(!err.contains("RUST_BACKTRACE"), "{err}");
    assert!(!err.contains("panicked at"), "{err}");
    assert!(emit.join("inv.png").is_file(), "other branches are emitted");
}

#[test]
fn no_plugins_refuses_every_source() {
    let dir = temp_dir("plugin-disabled");
    let lib = minimal_plugin();
    std::fs::copy(lib, dir.join(library_name("minimal"))).unwrap();
    let graph = graph_file(&dir, Some(&library_name("minimal")));
    let out = ocellus_env(&["run", &graph, "--no-plugins"], Some(lib));
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(err.contains("plugins are disabled"), "{err}");
    // The environment is ignored: the ops stay unknown.
    let plain = graph_file(&dir, None);
    let out = ocellus_env(&["check", &plain, "--no-plugins"], Some(lib));
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("minimal.invert"), "{}", stderr(&out));
    let out = ocellus_env(&["ops", "--json", "--no-plugins"], Some(lib));
    assert!(!stdout(&out).contains("minimal."), "{}", stdout(&out));
}

#[test]
fn an_abi_mismatch_is_refused_before_anything_runs() {
    let dir = temp_dir("plugin-abi");
    let lib = fixture_library("bad_abi_plugin", &dir);
    let out = ocellus_env(&["ops", "--plugin", lib.to_str().unwrap()], None);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(
        err.contains(&lib.display().to_string()) || err.contains("bad_abi_plugin"),
        "{err}"
    );
    assert!(err.contains("ABI version 999"), "{err}");
    assert!(err.contains("speaks version 1"), "{err}");
}

#[test]
fn a_library_without_the_symbol_is_refused() {
    let dir = temp_dir("plugin-symbol");
    let lib = fixture_library("no_symbol_plugin", &dir);
    let out = ocellus_env(&["ops", "--plugin", lib.to_str().unwrap()], None);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(err.contains("no_symbol_plugin"), "{err}");
    assert!(
        err.contains("does not export `ocellus_plugin_descriptor`"),
        "{err}"
    );
}

#[test]
fn a_file_that_is_no_library_is_refused() {
    let dir = temp_dir("plugin-junk");
    let junk = dir.join(library_name("junk"));
    std::fs::write(&junk, "this is text, not a shared library").unwrap();
    let out = ocellus_env(&["ops", "--plugin", junk.to_str().unwrap()], None);
    assert_eq!(out.status.code(), Some(2));
    let err = stderr(&out);
    assert!(err.contains("cannot load plugin"), "{err}");
    assert!(err.contains("junk"), "{err}");
    let out = ocellus_env(&["ops", "--plugin", "/nonexistent/libx.so"], None);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn the_readme_plugin_is_the_compiled_sdk_example() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let start = readme
        .find("// src/lib.rs\n")
        .expect("README shows a plugin lib.rs")
        + 14;
    let shown = &readme[start..start + readme[start..].find("```").unwrap()];
    let sdk = std::fs::read_to_string(root().join("plugins/sdk/src/lib.rs")).unwrap();
    let doc: Vec<&str> = sdk
        .lines()
        .filter_map(|l| l.strip_prefix("//!"))
        .map(|l| l.strip_prefix(' ').unwrap_or(l))
        .collect();
    let open = doc.iter().position(|l| *l == "```").unwrap();
    let close = open + 1 + doc[open + 1..].iter().position(|l| *l == "```").unwrap();
    let tested = doc[open + 1..close].join("\n") + "\n";
    assert_eq!(
        shown, tested,
        "README's plugin differs from the SDK doc-test"
    );
}

/// Runs an example graph of a plugin crate with 1 and 2 threads; the summaries must agree.
fn example_graph_summary(plugin: &str, graph: &str) -> String {
    let lib = plugin_library(plugin);
    let graph = root()
        .join("plugins")
        .join(plugin)
        .join("graphs")
        .join(graph);
    let mut summaries = Vec::new();
    for threads in ["1", "2"] {
        let out = ocellus_env(
            &[
                "snapshot",
                graph.to_str().unwrap(),
                "--threads",
                threads,
                "--plugin",
                lib.to_str().unwrap(),
            ],
            None,
        );
        assert!(out.status.success(), "{}", stderr(&out));
        summaries.push(stdout(&out));
    }
    assert_eq!(
        summaries[0], summaries[1],
        "summary differs between 1 and 2 threads"
    );
    summaries.swap_remove(0)
}

#[test]
fn kuwahara_painterly_graph() {
    let summary = example_graph_summary("kuwahara", "painterly.ron");
    insta::assert_snapshot!("kuwahara_painterly", summary);
}

#[test]
fn lines_segments_graph() {
    let summary = example_graph_summary("lines", "segments.ron");
    assert!(summary.contains("\"segments\": Matrix"), "{summary}");
    insta::assert_snapshot!("lines_segments", summary);
}
