//! Snapshot-testing helpers: run a graph file and get a stable, human-readable RON summary of its
//! outputs (see [`crate::summary`]), for `insta::assert_snapshot!`.
//!
//! ```no_run
//! # fn registry() -> ocellus_engine::Registry { ocellus_engine::Registry::new() }
//! let summary = ocellus_engine::testing::snapshot_graph(&registry(), "graphs/edges.ron").unwrap();
//! // insta::assert_snapshot!(summary);
//! ```

use std::path::Path;

use crate::exec::{RunOptions, RunReport, run};
use crate::op::Registry;
use crate::resolve::{Override, load_graph};
use crate::summary::summarize_outputs;

/// Loads and runs a graph file with `threads` workers (0 = all cores) and `--set`-style
/// overrides. Load errors, run errors and node failures are returned as text.
pub fn run_graph(
    registry: &Registry,
    path: impl AsRef<Path>,
    threads: usize,
    overrides: &[&str],
) -> Result<RunReport, String> {
    let overrides = parse_overrides(overrides)?;
    let graph = load_graph(registry, path.as_ref(), &overrides).map_err(|d| d.to_string())?;
    let options = RunOptions {
        threads,
        ..RunOptions::default()
    };
    let report = run(&graph, &options).map_err(|e| e.to_string())?;
    if !report.failures.is_empty() {
        let lines: Vec<String> = report.failures.iter().map(ToString::to_string).collect();
        return Err(lines.join("\n"));
    }
    Ok(report)
}

/// Runs a graph file and returns the summary of all its outputs.
pub fn snapshot_graph(registry: &Registry, path: impl AsRef<Path>) -> Result<String, String> {
    let report = run_graph(registry, path, 0, &[])?;
    Ok(summarize_outputs(&report.outputs))
}

/// Runs an animated graph file (one with an `animation` section) over all its frames and
/// returns each output as a list over frames, in output order — what a snapshot of an
/// animation shows. A graph without a timeline runs once, as [`run_graph`].
pub fn run_animated_graph(
    registry: &Registry,
    path: impl AsRef<Path>,
    threads: usize,
    overrides: &[&str],
) -> Result<Vec<(String, crate::value::Value)>, String> {
    let overrides = parse_overrides(overrides)?;
    let (graph, animated) =
        crate::timeline::load_animated_file(registry, path.as_ref(), &overrides)
            .map_err(|d| d.to_string())?;
    let options = RunOptions {
        threads,
        ..RunOptions::default()
    };
    let Some(animated) = animated else {
        let report = run(&graph, &options).map_err(|e| e.to_string())?;
        if !report.failures.is_empty() {
            let lines: Vec<String> = report.failures.iter().map(ToString::to_string).collect();
            return Err(lines.join("\n"));
        }
        return Ok(report.outputs);
    };
    let mut columns: Vec<(String, crate::types::PortType, Vec<crate::value::Value>)> = graph
        .outputs
        .iter()
        .filter(|o| options.outputs.is_empty() || options.outputs.contains(&o.name))
        .map(|o| (o.name.clone(), o.ty.clone(), Vec::new()))
        .collect();
    crate::timeline::run_timeline(registry, &animated, &options, |frame| {
        if !frame.report.failures.is_empty() {
            let lines: Vec<String> = frame
                .report
                .failures
                .iter()
                .map(ToString::to_string)
                .collect();
            return Err(lines.join("\n"));
        }
        for (name, _, values) in &mut columns {
            match frame.report.output(name) {
                Some(v) => values.push(v.clone()),
                None => return Err(format!("output `{name}` missing")),
            }
        }
        Ok(())
    })
    .map_err(|e| e.to_string())?;
    Ok(columns
        .into_iter()
        .map(|(name, ty, values)| (name, crate::value::Value::list(ty, values)))
        .collect())
}

/// Streams a graph file with a `stream` section and returns every output in declaration
/// order: each streamed output as the list of its per-frame values (what a batch run gives),
/// the others as they are. With `threads` workers; `--set`-style overrides.
pub fn run_stream_graph(
    registry: &Registry,
    path: impl AsRef<Path>,
    threads: usize,
    overrides: &[&str],
) -> Result<Vec<(String, crate::value::Value)>, String> {
    let overrides = parse_overrides(overrides)?;
    let (graph, spec) = crate::stream::load_streamed_file(registry, path.as_ref(), &overrides)
        .map_err(|d| d.to_string())?;
    let spec =
        spec.ok_or_else(|| format!("{} has no `stream` section", path.as_ref().display()))?;
    let options = RunOptions {
        threads,
        ..RunOptions::default()
    };
    let mut columns: Vec<(String, Vec<crate::value::Value>)> = Vec::new();
    let report = crate::stream::run_stream(&graph, &spec, &options, |frame| {
        for (name, value) in &frame.outputs {
            match columns.iter_mut().find(|(n, _)| n == name) {
                Some((_, values)) => values.push(value.clone()),
                None => columns.push((name.clone(), vec![value.clone()])),
            }
        }
        Ok(())
    })
    .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for o in &graph.outputs {
        if let Some((_, values)) = columns.iter().find(|(n, _)| n == &o.name) {
            let element = o.ty.element().cloned().unwrap_or(o.ty.clone());
            out.push((
                o.name.clone(),
                crate::value::Value::list(element, values.clone()),
            ));
        } else if let Some((_, v)) = report.outputs.iter().find(|(n, _)| n == &o.name) {
            out.push((o.name.clone(), v.clone()));
        }
    }
    Ok(out)
}

/// `--set`-style overrides, or the first one's parse error as text.
fn parse_overrides(overrides: &[&str]) -> Result<Vec<Override>, String> {
    overrides
        .iter()
        .map(|o| Override::parse(o).map_err(|d| d.to_string()))
        .collect()
}
