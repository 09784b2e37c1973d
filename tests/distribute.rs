//! Distributed list maps without a cluster: the engine's task path (chunked payloads, the
//! worker's `run_task`, content-keyed element reuse) driven by in-process runners, checked
//! against ordinary local runs byte for byte. The Ray runner itself is tested from Python
//! (python/tests/test_ray.py).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::path::Path;
use std::sync::{Arc, Mutex};

use common::{root, temp_dir};
use ocellus_engine::codec::encode_values;
use ocellus_engine::distribute::{
    Distribution, LocalRunner, Stage, TaskDone, TaskRunner, distributable, run_task,
};
use ocellus_engine::{Graph, Override, Registry, RunOptions, RunReport};

fn registry() -> Registry {
    ocellus_nodes::builtin_registry().unwrap()
}

fn load(graph: &str, sets: &[&str]) -> Graph {
    let overrides: Vec<Override> = sets.iter().map(|s| Override::parse(s).unwrap()).collect();
    ocellus_engine::load_graph(&registry(), &root().join("graphs").join(graph), &overrides)
        .unwrap_or_else(|d| panic!("{d}"))
}

fn run(graph: &Graph, distribution: Option<Distribution>) -> RunReport {
    let options = RunOptions {
        threads: 2,
        distribution,
        ..RunOptions::default()
    };
    ocellus_engine::run(graph, &options).unwrap()
}

fn distribution(runner: Arc<dyn TaskRunner>, items: usize, cache: Option<&Path>) -> Distribution {
    Distribution {
        runner,
        items_per_task: items,
        item_cache: cache.map(Path::to_path_buf),
        progress: None,
    }
}

/// Every output in the value codec, by name.
fn encoded(report: &RunReport) -> Vec<(String, Vec<u8>)> {
    assert!(report.failures.is_empty(), "{:?}", report.failures);
    report
        .outputs
        .iter()
        .map(|(name, value)| (name.clone(), encode_values(std::slice::from_ref(value))))
        .collect()
}

fn stage<'a>(report: &'a RunReport, node: &str) -> &'a ocellus_engine::distribute::StageStats {
    report
        .distributed
        .iter()
        .find(|s| s.node == node)
        .unwrap_or_else(|| panic!("no distributed stage `{node}`: {:?}", report.distributed))
}

/// Records every payload and stops the run after `fail_after` tasks of `node` (a cluster that
/// went away), delegating the rest to a local runner.
struct Flaky {
    inner: LocalRunner,
    node: &'static str,
    fail_after: Option<usize>,
    payloads: Mutex<Vec<Vec<u8>>>,
}

impl TaskRunner for Flaky {
    fn run(
        &self,
        stage: &Stage,
        tasks: Vec<Vec<u8>>,
        done: &mut dyn FnMut(TaskDone) -> Result<(), String>,
    ) -> Result<(), String> {
        self.payloads.lock().unwrap().extend(tasks.iter().cloned());
        match self.fail_after {
            Some(k) if stage.node == self.node => {
                let kept: Vec<Vec<u8>> = tasks.into_iter().take(k).collect();
                self.inner.run(stage, kept, done)?;
                Err("the cluster went away".into())
            }
            _ => self.inner.run(stage, tasks, done),
        }
    }
}

fn flaky(node: &'static str, fail_after: Option<usize>) -> Arc<Flaky> {
    Arc::new(Flaky {
        inner: LocalRunner::new(registry()),
        node,
        fail_after,
        payloads: Mutex::new(Vec::new()),
    })
}

#[test]
fn distributed_runs_are_byte_identical_to_local_for_any_chunking() {
    let graph = load("many_views.ron", &[]);
    let local = encoded(&run(&graph, None));
    for items in [0, 1, 7] {
        let report = run(
            &graph,
            Some(distribution(
                Arc::new(LocalRunner::new(registry())),
                items,
                None,
            )),
        );
        assert_eq!(encoded(&report), local, "{items} items per task");
        let features = stage(&report, "features");
        assert_eq!(features.items, 48);
        assert_eq!(features.reused, 0);
        let per_task = if items == 0 { 1 } else { items };
        assert_eq!(features.tasks, 48_usize.div_ceil(per_task));
        let matching = stage(&report, "match");
        // 48 views, each with the next 3: 45·3 + 2 + 1 pairs.
        assert_eq!(matching.items, 138);
        assert_eq!(
            matching.workers.values().map(|w| w.items).sum::<usize>(),
            138
        );
    }
}

#[test]
fn a_rerun_after_a_failure_reuses_the_finished_elements() {
    let graph = load("many_views.ron", &[]);
    let local = encoded(&run(&graph, None));
    let cache = temp_dir("distribute-rerun");
    // 5 elements per task; the cluster is lost after 4 of the 10 feature tasks.
    let first = run(
        &graph,
        Some(distribution(flaky("features", Some(4)), 5, Some(&cache))),
    );
    assert_eq!(first.failures.len(), 1, "{:?}", first.failures);
    assert_eq!(first.failures[0].node, "features");
    assert!(first.failures[0].message.contains("the cluster went away"));
    assert!(first.outputs.is_empty());

    let second = run(&graph, Some(distribution(flaky("", None), 5, Some(&cache))));
    assert_eq!(encoded(&second), local);
    let features = stage(&second, "features");
    assert_eq!((features.reused, features.tasks), (20, 6));
    assert_eq!(stage(&second, "match").reused, 0);

    // A third run finds every element of both maps.
    let third = run(&graph, Some(distribution(flaky("", None), 5, Some(&cache))));
    assert_eq!(encoded(&third), local);
    for node in ["features", "match"] {
        let s = stage(&third, node);
        assert_eq!((s.reused, s.tasks), (s.items, 0), "{node}");
    }
    let _ = std::fs::remove_dir_all(&cache);
}

#[test]
fn element_keys_follow_parameters_and_inputs() {
    let cache = temp_dir("distribute-keys");
    let runner = || -> Arc<dyn TaskRunner> { Arc::new(LocalRunner::new(registry())) };
    let graph = load("many_views.ron", &[]);
    run(&graph, Some(distribution(runner(), 0, Some(&cache))));
    // A matcher parameter: the features are reused, no pair is.
    let ratio = load("many_views.ron", &["match.ratio=0.7"]);
    let report = run(&ratio, Some(distribution(runner(), 0, Some(&cache))));
    assert_eq!(encoded(&report), encoded(&run(&ratio, None)));
    assert_eq!(stage(&report, "features").reused, 48);
    assert_eq!(stage(&report, "match").reused, 0);
    // Fewer features: new descriptors, so neither map reuses anything.
    let fewer = load("many_views.ron", &["features.max_features=300"]);
    let report = run(&fewer, Some(distribution(runner(), 0, Some(&cache))));
    assert_eq!(encoded(&report), encoded(&run(&fewer, None)));
    assert_eq!(stage(&report, "features").reused, 0);
    assert_eq!(stage(&report, "match").reused, 0);
    let _ = std::fs::remove_dir_all(&cache);
}

#[test]
fn a_failing_task_fails_the_node_naming_elements_and_worker() {
    struct Broken;
    impl TaskRunner for Broken {
        fn run(
            &self,
            _stage: &Stage,
            tasks: Vec<Vec<u8>>,
            done: &mut dyn FnMut(TaskDone) -> Result<(), String>,
        ) -> Result<(), String> {
            for task in 0..tasks.len() {
                done(TaskDone {
                    task,
                    result: Err("out of memory".into()),
                    worker: "10.0.0.7 pid 42".into(),
                    seconds: 0.5,
                })?;
            }
            Ok(())
        }
    }
    let graph = load("features.ron", &[]);
    let report = run(&graph, Some(distribution(Arc::new(Broken), 1, None)));
    assert_eq!(report.failures.len(), 1);
    let message = &report.failures[0].message;
    assert_eq!(report.failures[0].node, "detect");
    assert!(message.contains("elements 0"), "{message}");
    assert!(message.contains("out of memory"), "{message}");
    assert!(message.contains("10.0.0.7 pid 42"), "{message}");
    assert_eq!(stage(&report, "detect").failed_tasks, 1);
}

#[test]
fn the_worker_refuses_damaged_payloads_without_panicking() {
    let graph = load("features.ron", &[]);
    let recorder = flaky("", None);
    let report = run(&graph, Some(distribution(recorder.clone(), 1, None)));
    assert!(report.failures.is_empty());
    let payloads = recorder.payloads.lock().unwrap().clone();
    assert_eq!(payloads.len(), 2, "one task per view");
    let registry = registry();
    let payload = &payloads[0];
    let good = run_task(&registry, payload).unwrap();
    assert_eq!(run_task(&registry, payload).unwrap(), good, "deterministic");
    // Every truncation is an error.
    let step = (payload.len() / 300).max(1);
    for cut in (0..payload.len()).step_by(step) {
        assert!(
            run_task(&registry, &payload[..cut]).is_err(),
            "cut at {cut}"
        );
    }
    // Flipped bytes in the header: an error or a result, never a panic.
    for at in 0..payload.len().min(400) {
        let mut bad = payload.clone();
        bad[at] ^= 0x5a;
        let _ = run_task(&registry, &bad);
    }
    // An operator the worker does not have.
    let unknown = payload
        .windows(b"describe.features".len())
        .position(|w| w == b"describe.features")
        .unwrap();
    let mut renamed = payload.clone();
    renamed[unknown..unknown + 8].copy_from_slice(b"xescribe");
    let err = run_task(&registry, &renamed).unwrap_err();
    assert!(err.contains("not known on this worker"), "{err}");
}

#[test]
fn only_builtin_maps_without_side_effects_are_distributed() {
    let graph = load("features.ron", &[]);
    let mapped: Vec<&str> = graph
        .nodes
        .iter()
        .filter(|n| distributable(n))
        .map(|n| n.name.as_str())
        .collect();
    assert_eq!(mapped, vec!["detect"]);
    let report = run(
        &graph,
        Some(distribution(
            Arc::new(LocalRunner::new(registry())),
            0,
            None,
        )),
    );
    assert_eq!(report.distributed.len(), 1);
    assert_eq!(encoded(&report), encoded(&run(&graph, None)));
}

#[test]
fn ray_without_a_usable_driver_is_a_clear_error() {
    let graph = root().join("graphs/features.ron");
    let graph = graph.to_str().unwrap();
    let run = |python: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_ocellus"))
            .args(["run", graph, "--ray", "127.0.0.1:9"])
            .env("OCELLUS_PYTHON", python)
            .output()
            .unwrap()
    };
    // No interpreter at all.
    let out = run("/nonexistent/python3");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("--ray needs Python with the `ocellus` package"),
        "{stderr}"
    );
    // An interpreter that exits at once (no package, no Ray).
    let out = run("/bin/false");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("the Ray driver"), "{stderr}");
    assert!(stderr.contains("did not start"), "{stderr}");

    // --items-per-task means nothing without --ray.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_ocellus"))
        .args(["run", graph, "--items-per-task", "4"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}
