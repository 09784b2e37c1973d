//! An interrupted run leaves only complete files. A run writing six 3000 × 3000 noise images
//! (36 MB of PNG that does not compress) is stopped while a write is in flight — seen as its
//! hidden temp file in the output folder — by SIGINT, SIGTERM and SIGKILL, at several moments.
//! Every file left under an output's name must be byte-identical to the one an uninterrupted run
//! writes; after SIGINT/SIGTERM no temp file may remain and the process ends by the signal (so a
//! shell loop stops too), and after SIGKILL (which no process can catch) the next run into the
//! folder removes them.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test
#![cfg(unix)]

mod common;

use std::collections::BTreeMap;
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::temp_dir;

const GRAPH: &str = r#"(
    nodes: {
        "a": (op: "capture.pattern", params: (kind: "noise", width: 3000, height: 3000, seed: 1)),
        "b": (op: "capture.pattern", params: (kind: "noise", width: 3000, height: 3000, seed: 2)),
        "c": (op: "capture.pattern", params: (kind: "noise", width: 3000, height: 3000, seed: 3)),
        "d": (op: "capture.pattern", params: (kind: "noise", width: 3000, height: 3000, seed: 4)),
        "e": (op: "capture.pattern", params: (kind: "noise", width: 3000, height: 3000, seed: 5)),
        "f": (op: "capture.pattern", params: (kind: "noise", width: 3000, height: 3000, seed: 6)),
    },
    outputs: { "a": "a.image", "b": "b.image", "c": "c.image", "d": "d.image", "e": "e.image", "f": "f.image" },
)"#;

fn spawn(graph: &Path, out: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_ocellus"))
        .args([
            "run",
            graph.to_str().unwrap(),
            "--emit",
            out.to_str().unwrap(),
        ])
        .args(["--threads", "2"])
        .env_remove("OCELLUS_LOG")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Files in a folder by name, with contents.
fn contents(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| {
            let path = e.ok()?.path();
            // A temp file may vanish between listing and reading.
            let bytes = std::fs::read(&path).ok()?;
            Some((path.file_name()?.to_string_lossy().into_owned(), bytes))
        })
        .collect()
}

fn temp_files(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(|e| Some(e.ok()?.file_name().to_string_lossy().into_owned()))
                .filter(|n| n.starts_with('.'))
                .collect()
        })
        .unwrap_or_default()
}

/// Waits until a write is in flight (a temp file exists), then `extra` longer; false if the run
/// ended first.
fn wait_for_a_write(child: &mut Child, dir: &Path, extra: Duration) -> bool {
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(120) {
        if child.try_wait().unwrap().is_some() {
            return false;
        }
        if !temp_files(dir).is_empty() {
            std::thread::sleep(extra);
            return true;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    panic!("no write started within two minutes");
}

fn send(child: &Child, signal: &str) {
    let status = Command::new("kill")
        .args(["-s", signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

/// Every non-hidden file in `dir` is complete: identical to the uninterrupted run's.
fn assert_only_complete(dir: &Path, reference: &BTreeMap<String, Vec<u8>>, case: &str) {
    for (name, bytes) in contents(dir) {
        if name.starts_with('.') {
            continue;
        }
        let Some(expected) = reference.get(&name) else {
            panic!("{case}: unexpected file {name}");
        };
        assert!(
            bytes == *expected,
            "{case}: {name} differs from the complete file"
        );
    }
}

fn setup() -> (PathBuf, PathBuf, BTreeMap<String, Vec<u8>>) {
    let dir = temp_dir("interrupt");
    let graph = dir.join("noise.ron");
    std::fs::write(&graph, GRAPH).unwrap();
    let reference_dir = dir.join("reference");
    let status = spawn(&graph, &reference_dir).wait().unwrap();
    assert!(status.success());
    let reference = contents(&reference_dir);
    assert_eq!(reference.len(), 6, "{:?}", reference.keys());
    assert!(temp_files(&reference_dir).is_empty());
    (dir, graph, reference)
}

#[test]
fn sigint_and_sigterm_mid_write_leave_only_complete_files_and_no_temp_files() {
    let (dir, graph, reference) = setup();
    let mut interrupted = 0;
    for (k, (signal, number, extra_ms)) in [
        ("INT", 2, 0),
        ("TERM", 15, 0),
        ("INT", 2, 15),
        ("TERM", 15, 40),
        ("TERM", 15, 120),
    ]
    .into_iter()
    .enumerate()
    {
        let out = dir.join(format!("out-{k}"));
        let mut child = spawn(&graph, &out);
        if !wait_for_a_write(&mut child, &out, Duration::from_millis(extra_ms)) {
            continue;
        }
        send(&child, signal);
        let output = child.wait_with_output().unwrap();
        let case = format!("SIG{signal} +{extra_ms} ms");
        let stderr = String::from_utf8_lossy(&output.stderr);
        if output.status.code() == Some(0) {
            // The run finished just before the signal arrived: everything must be there.
            assert_eq!(contents(&out), reference, "{case}");
            continue;
        }
        // Ended by the signal itself (after cleaning up), as a shell expects of an interrupted
        // child.
        assert_eq!(output.status.signal(), Some(number), "{case}: {stderr}");
        assert!(stderr.contains("interrupted"), "{case}: {stderr}");
        assert_eq!(
            temp_files(&out),
            Vec::<String>::new(),
            "{case}: temp files left"
        );
        assert_only_complete(&out, &reference, &case);
        interrupted += 1;
    }
    assert!(
        interrupted >= 3,
        "only {interrupted} runs were interrupted mid-write"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn sigkill_mid_write_leaves_only_complete_outputs_and_the_next_run_sweeps_its_temp_files() {
    let (dir, graph, reference) = setup();
    let out = dir.join("out");
    let mut child = spawn(&graph, &out);
    assert!(wait_for_a_write(&mut child, &out, Duration::from_millis(5)));
    send(&child, "KILL");
    child.wait().unwrap();
    assert_only_complete(&out, &reference, "SIGKILL");
    let left = temp_files(&out);
    assert!(
        !left.is_empty(),
        "the killed run left no temp file to sweep"
    );
    assert!(
        left.iter()
            .all(|n| n.ends_with(".ocellus.tmp") || n.ends_with(".ocellus.part")),
        "{left:?}"
    );
    // The next run into the folder completes and removes what the killed one left.
    let status = spawn(&graph, &out).wait().unwrap();
    assert!(status.success());
    assert_eq!(temp_files(&out), Vec::<String>::new());
    assert_eq!(contents(&out), reference);
    std::fs::remove_dir_all(&dir).unwrap();
}
