//! The scheduler: demand-driven, parallel, cached.
//!
//! 1. **Demand.** Only nodes that the requested outputs (and, without a selection, side-effect
//!    nodes such as file writers) depend on are considered.
//! 2. **Keys.** Each node gets a content key: BLAKE3 of (op id, op version, canonical params,
//!    operator fingerprint, input keys). Keys depend on the graph, not on data, so they are known
//!    before anything runs.
//! 3. **Sharing and cache.** Nodes with equal keys are computed once per run. With a disk cache, a
//!    node whose key is stored is loaded instead of computed — and then its upstream nodes are not
//!    needed at all.
//! 4. **Parallel run.** Ready nodes are spawned on a rayon pool of `threads` workers; operators
//!    parallelise inside on the same pool. A node's outputs are dropped as soon as its last
//!    consumer finished (unless they are graph outputs).
//! 5. **Failures.** A failing node (error or panic) fails only its downstream nodes; every other
//!    branch completes and its outputs are returned.
//!
//! Outputs never depend on the thread count: scheduling order changes only timings, which are
//! reported in [`RunReport`], never in values.

use std::collections::HashMap;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::cache::{DiskCache, MemoryCache};
use crate::diag::suggest;
use crate::graph::{EdgeSource, Graph, InputEdge, Node, Tap};
use crate::op::{Inputs, OpError, RunContext};
use crate::resolve::list_position;
use crate::value::Value;

/// Bumped when the key derivation or cache format changes.
const KEY_SCHEME: &[u8] = b"ocellus-key-v1";

/// A node's content key.
pub type Key = [u8; 32];

/// Progress callback: (nodes finished, nodes to run).
pub type ProgressFn = Arc<dyn Fn(usize, usize) + Send + Sync>;

/// How to run a graph.
#[derive(Clone, Default)]
pub struct RunOptions {
    /// Worker threads; 0 uses every core.
    pub threads: usize,
    /// Output names to produce; empty produces all outputs and runs side-effect nodes.
    pub outputs: Vec<String>,
    /// Persistent result cache folder.
    pub cache_dir: Option<PathBuf>,
    /// Called as nodes finish.
    pub progress: Option<ProgressFn>,
    /// In-memory results shared between runs (the frames of an animation); checked before
    /// the disk cache.
    pub memory_cache: Option<Arc<MemoryCache>>,
    /// Nodes computed even when a cache holds their result, and with them everything
    /// downstream (their new results are stored as usual): what a parameter sweep times while
    /// the unchanged upstream comes from the cache. Unknown names are an error.
    pub recompute: Vec<String>,
    /// Run distributable list maps as tasks elsewhere ([`crate::distribute`]).
    pub distribution: Option<crate::distribute::Distribution>,
}

/// The caches a run reads and fills.
#[derive(Clone, Copy)]
struct Caches<'a> {
    disk: Option<&'a DiskCache>,
    memory: Option<&'a MemoryCache>,
}

impl Caches<'_> {
    fn load(&self, key: &Key, node: &Node) -> Option<Arc<[Value]>> {
        if let Some(values) = self.memory.and_then(|m| m.load(key, &node.output_types)) {
            return Some(values);
        }
        let values: Arc<[Value]> = self.disk?.load(key, &node.output_types)?.into();
        if let Some(memory) = self.memory {
            memory.store(key, values.clone());
        }
        Some(values)
    }
}

/// Errors that stop a run before it starts.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// `--output NAME` names no graph output.
    #[error("the graph has no output `{name}`{}", .suggestion.as_ref().map(|s| format!(" (did you mean `{s}`?)")).unwrap_or_default())]
    UnknownOutput {
        /// The name asked for.
        name: String,
        /// The nearest output name.
        suggestion: Option<String>,
    },
    /// `recompute` names no node of the graph.
    #[error("the graph has no node `{name}`{}", .suggestion.as_ref().map(|s| format!(" (did you mean `{s}`?)")).unwrap_or_default())]
    UnknownNode {
        /// The name asked for.
        name: String,
        /// The nearest node name.
        suggestion: Option<String>,
    },
    /// The thread pool could not be created.
    #[error("cannot start {threads} worker threads: {message}")]
    Threads {
        /// Threads asked for.
        threads: usize,
        /// Why.
        message: String,
    },
    /// The cache folder cannot be used.
    #[error("cache folder {path}: {message}")]
    Cache {
        /// The folder.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// What happened to a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NodeStatus {
    /// Ran its operator.
    Computed,
    /// Loaded from the disk cache.
    Cached,
    /// Identical to another node of this run, whose result it shares.
    Shared,
    /// Its operator failed.
    Failed,
    /// Not run because an upstream node failed.
    Skipped,
    /// Not needed: no requested output depends on it, or a cached result made it unnecessary.
    Idle,
}

/// Per-node record of a run.
#[derive(Debug, Clone)]
pub struct NodeReport {
    /// Qualified node name.
    pub name: String,
    /// Operator id.
    pub op: String,
    /// What happened.
    pub status: NodeStatus,
    /// Time spent in the operator (zero unless computed).
    pub elapsed: Duration,
    /// Bytes of the node's outputs (computed or loaded from a cache; zero otherwise).
    pub output_bytes: usize,
}

/// A node that failed, with where it was declared.
#[derive(Debug, Clone)]
pub struct NodeFailure {
    /// Qualified node name.
    pub node: String,
    /// Operator id.
    pub op: String,
    /// `file:line:col` of the node's declaration.
    pub location: Option<String>,
    /// The operator's error.
    pub message: String,
}

impl std::fmt::Display for NodeFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.location {
            Some(loc) => write!(
                f,
                "{loc}: node `{}` ({}) failed: {}",
                self.node, self.op, self.message
            ),
            None => write!(
                f,
                "node `{}` ({}) failed: {}",
                self.node, self.op, self.message
            ),
        }
    }
}

/// The result of a run: outputs that could be computed, failures, and statistics.
#[derive(Debug, Clone, Default)]
pub struct RunReport {
    /// Requested outputs that were produced, in the graph's declaration order.
    pub outputs: Vec<(String, Value)>,
    /// Failed nodes, in graph order.
    pub failures: Vec<NodeFailure>,
    /// Every node of the graph, in graph order.
    pub nodes: Vec<NodeReport>,
    /// Problems that did not fail the run (e.g. a cache write that failed).
    pub warnings: Vec<String>,
    /// Largest number of bytes held by live node outputs at any time.
    pub peak_bytes: usize,
    /// Wall time of the whole run.
    pub elapsed: Duration,
    /// Mapped nodes whose elements ran as distributed tasks, in the order they finished.
    pub distributed: Vec<crate::distribute::StageStats>,
}

impl RunReport {
    /// Number of nodes with the given status.
    pub fn count(&self, status: NodeStatus) -> usize {
        self.nodes.iter().filter(|n| n.status == status).count()
    }

    /// The output with this name.
    pub fn output(&self, name: &str) -> Option<&Value> {
        self.outputs.iter().find(|(n, _)| n == name).map(|(_, v)| v)
    }

    /// One line: `4 computed, 1 cached, 0 shared, 0 failed, 0 skipped`.
    pub fn summary_line(&self) -> String {
        format!(
            "{} computed, {} cached, {} shared, {} failed, {} skipped",
            self.count(NodeStatus::Computed),
            self.count(NodeStatus::Cached),
            self.count(NodeStatus::Shared),
            self.count(NodeStatus::Failed),
            self.count(NodeStatus::Skipped)
        )
    }
}

/// Plan for one run, before anything executes.
struct Plan {
    /// For each node: the node whose result it uses (itself, or an identical earlier node).
    canonical: Vec<usize>,
    /// Nodes that run their operator.
    run: Vec<bool>,
    /// Results loaded from the cache.
    loaded: HashMap<usize, Arc<[Value]>>,
    /// Content keys (for needed nodes).
    keys: Vec<Option<Key>>,
    /// Failures found while planning (fingerprints).
    failed: HashMap<usize, String>,
    /// Requested outputs: (name, canonical node, port, element index).
    requested: Vec<(String, usize, usize, Option<i64>)>,
    /// Nodes whose status is `Shared`.
    shared: Vec<bool>,
}

/// Runs a graph.
pub fn run(graph: &Graph, options: &RunOptions) -> Result<RunReport, RunError> {
    let (pool, threads) = thread_pool(options.threads)?;
    let cache = match &options.cache_dir {
        Some(dir) => Some(DiskCache::open(dir).map_err(|e| RunError::Cache {
            path: dir.clone(),
            message: e.to_string(),
        })?),
        None => None,
    };
    let start = Instant::now();
    let caches = Caches {
        disk: cache.as_ref(),
        memory: options.memory_cache.as_deref(),
    };
    let plan = plan(graph, &options.outputs, &options.recompute, caches)?;
    let mut report = pool.install(|| {
        execute(
            graph,
            &plan,
            caches,
            threads,
            options.progress.as_ref(),
            options.distribution.as_ref(),
        )
    });
    report.elapsed = start.elapsed();
    Ok(report)
}

/// The run's worker pool and its size: `threads` workers, 0 for every core.
pub(crate) fn thread_pool(threads: usize) -> Result<(rayon::ThreadPool, usize), RunError> {
    let threads = if threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        threads
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("ocellus-{i}"))
        .build()
        .map_err(|e| RunError::Threads {
            threads,
            message: e.to_string(),
        })?;
    Ok((pool, threads))
}

fn plan(
    graph: &Graph,
    selected: &[String],
    recompute: &[String],
    caches: Caches<'_>,
) -> Result<Plan, RunError> {
    let n = graph.nodes.len();
    // Nodes that must not come from a cache: those named, and (nodes are in topological
    // order) everything fed by one of them.
    let mut fresh = vec![false; n];
    for name in recompute {
        let Some(i) = graph.nodes.iter().position(|node| &node.name == name) else {
            return Err(RunError::UnknownNode {
                name: name.clone(),
                suggestion: suggest(name, graph.nodes.iter().map(|node| node.name.as_str()))
                    .map(str::to_string),
            });
        };
        fresh[i] = true;
    }
    for i in 0..n {
        if !fresh[i]
            && graph.nodes[i]
                .inputs
                .iter()
                .flatten()
                .flat_map(InputEdge::sources)
                .any(|from| fresh[from.node])
        {
            fresh[i] = true;
        }
    }
    // Requested outputs and roots.
    let mut requested = Vec::new();
    let mut roots = Vec::new();
    if selected.is_empty() {
        for out in &graph.outputs {
            requested.push((out.name.clone(), out.from.node, out.from.port, out.index));
            roots.push(out.from.node);
        }
        roots.extend((0..n).filter(|&i| graph.nodes[i].info.side_effects));
    } else {
        for name in selected {
            let Some(out) = graph.outputs.iter().find(|o| &o.name == name) else {
                return Err(RunError::UnknownOutput {
                    name: name.clone(),
                    suggestion: suggest(name, graph.outputs.iter().map(|o| o.name.as_str()))
                        .map(str::to_string),
                });
            };
            if !requested.iter().any(|(r, _, _, _)| r == name) {
                requested.push((out.name.clone(), out.from.node, out.from.port, out.index));
                roots.push(out.from.node);
            }
        }
        requested.sort_by_key(|(name, _, _, _)| graph.outputs.iter().position(|o| &o.name == name));
    }

    // Everything the roots depend on.
    let mut needed = vec![false; n];
    let mut stack = roots.clone();
    while let Some(i) = stack.pop() {
        if std::mem::replace(&mut needed[i], true) {
            continue;
        }
        stack.extend(
            graph.nodes[i]
                .inputs
                .iter()
                .flatten()
                .flat_map(InputEdge::sources)
                .map(|from| from.node),
        );
    }

    // Keys, in topological order; identical non-side-effect nodes share one result.
    let mut keys: Vec<Option<Key>> = vec![None; n];
    let mut canonical: Vec<usize> = (0..n).collect();
    let mut shared = vec![false; n];
    let mut failed = HashMap::new();
    let mut first_with_key: HashMap<Key, usize> = HashMap::new();
    for i in (0..n).filter(|&i| needed[i]) {
        let node = &graph.nodes[i];
        let fingerprint = match catch_unwind(AssertUnwindSafe(|| node.op.fingerprint())) {
            Ok(Ok(f)) => f,
            Ok(Err(e)) => {
                failed.insert(i, e.to_string());
                continue;
            }
            Err(payload) => {
                failed.insert(i, panic_message(payload.as_ref()));
                continue;
            }
        };
        let Some(key) = node_key(node, &fingerprint, &keys) else {
            continue; // an input's key is missing: its source failed to plan
        };
        keys[i] = Some(key);
        if !node.info.side_effects {
            match first_with_key.get(&key) {
                Some(&j) => {
                    canonical[i] = j;
                    shared[i] = true;
                }
                None => {
                    first_with_key.insert(key, i);
                }
            }
        }
    }

    if let Some(memory) = caches.memory {
        for key in keys.iter().flatten() {
            memory.touch(key);
        }
    }

    // A fresh node shared onto an identical earlier one makes that one fresh too.
    for i in 0..n {
        if fresh[i] {
            fresh[canonical[i]] = true;
        }
    }

    // Walk demand again, stopping at cached results.
    let mut run = vec![false; n];
    let mut loaded: HashMap<usize, Arc<[Value]>> = HashMap::new();
    let mut visited = vec![false; n];
    let mut stack: Vec<usize> = roots.iter().map(|&r| canonical[r]).collect();
    while let Some(i) = stack.pop() {
        let c = canonical[i];
        if std::mem::replace(&mut visited[c], true) {
            continue;
        }
        let node = &graph.nodes[c];
        if let (Some(key), false, false) = (keys[c], node.info.side_effects, fresh[c])
            && let Some(values) = caches.load(&key, node)
        {
            loaded.insert(c, values);
            continue;
        }
        run[c] = true;
        stack.extend(
            node.inputs
                .iter()
                .flatten()
                .flat_map(InputEdge::sources)
                .map(|from| canonical[from.node]),
        );
    }
    for (_, node, _, _) in &mut requested {
        *node = canonical[*node];
    }
    // A shared node counts as shared only if its canonical twin is actually used.
    for i in 0..n {
        if shared[i] && !(needed[i] && (run[canonical[i]] || loaded.contains_key(&canonical[i]))) {
            shared[i] = false;
        }
    }
    Ok(Plan {
        canonical,
        run,
        loaded,
        keys,
        failed,
        requested,
        shared,
    })
}

fn node_key(node: &Node, fingerprint: &[u8], keys: &[Option<Key>]) -> Option<Key> {
    let mut h = blake3::Hasher::new();
    let field = |h: &mut blake3::Hasher, bytes: &[u8]| {
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    field(&mut h, KEY_SCHEME);
    field(&mut h, node.info.id.as_bytes());
    field(&mut h, &node.info.version.to_le_bytes());
    for (name, value) in &node.params {
        field(&mut h, name.as_bytes());
        field(&mut h, value.to_string().as_bytes());
    }
    field(&mut h, fingerprint);
    let tap = |h: &mut blake3::Hasher, tap: &Tap| -> Option<()> {
        h.update(&keys[tap.from.node]?);
        h.update(&(tap.from.port as u64).to_le_bytes());
        Some(())
    };
    for input in &node.inputs {
        match input.as_ref().map(|e| (e, &e.source)) {
            // A whole port hashes as it always has, so existing cache entries stay valid.
            Some((edge, EdgeSource::Tap(t @ Tap { index: None, .. }))) => {
                h.update(&[1, u8::from(edge.mapped)]);
                tap(&mut h, t)?;
            }
            Some((edge, EdgeSource::Tap(t @ Tap { index: Some(i), .. }))) => {
                h.update(&[3, u8::from(edge.mapped)]);
                tap(&mut h, t)?;
                h.update(&i.to_le_bytes());
            }
            Some((edge, EdgeSource::List { items, element })) => {
                h.update(&[2, u8::from(edge.mapped)]);
                field(&mut h, element.to_string().as_bytes());
                h.update(&(items.len() as u64).to_le_bytes());
                for t in items {
                    tap(&mut h, t)?;
                    match t.index {
                        Some(i) => {
                            h.update(&[1]);
                            h.update(&i.to_le_bytes());
                        }
                        None => {
                            h.update(&[0]);
                        }
                    }
                }
            }
            None => {
                h.update(&[0]);
            }
        }
    }
    Some(*h.finalize().as_bytes())
}

/// Mutable state shared by the tasks of one run.
struct State<'a> {
    graph: &'a Graph,
    plan: &'a Plan,
    caches: Caches<'a>,
    threads: usize,
    /// Outputs of each canonical node while alive.
    results: Vec<Mutex<Option<Arc<[Value]>>>>,
    /// Dependencies (distinct canonical sources that run) not yet finished.
    pending: Vec<AtomicUsize>,
    /// Running consumers not yet finished, per canonical source.
    consumers_left: Vec<AtomicUsize>,
    /// Results kept to the end (requested outputs).
    pinned: Vec<bool>,
    /// Running dependents of each node.
    dependents: Vec<Vec<usize>>,
    /// Distinct canonical sources of each node.
    sources: Vec<Vec<usize>>,
    status: Vec<Mutex<NodeStatus>>,
    elapsed: Vec<Mutex<Duration>>,
    output_bytes: Vec<AtomicUsize>,
    failures: Mutex<Vec<(usize, String)>>,
    warnings: Mutex<Vec<String>>,
    live_bytes: AtomicUsize,
    peak_bytes: AtomicUsize,
    done: AtomicUsize,
    total: usize,
    progress: Option<&'a ProgressFn>,
    distribution: Option<&'a crate::distribute::Distribution>,
    distributed: Mutex<Vec<crate::distribute::StageStats>>,
}

fn execute(
    graph: &Graph,
    plan: &Plan,
    caches: Caches<'_>,
    threads: usize,
    progress: Option<&ProgressFn>,
    distribution: Option<&crate::distribute::Distribution>,
) -> RunReport {
    let n = graph.nodes.len();
    let canonical = &plan.canonical;
    let mut sources: Vec<Vec<usize>> = vec![Vec::new(); n];
    let mut dependents: Vec<Vec<usize>> = vec![Vec::new(); n];
    let mut consumers = vec![0usize; n];
    for i in (0..n).filter(|&i| plan.run[i]) {
        let mut s: Vec<usize> = graph.nodes[i]
            .inputs
            .iter()
            .flatten()
            .flat_map(InputEdge::sources)
            .map(|from| canonical[from.node])
            .collect();
        s.sort_unstable();
        s.dedup();
        for &j in &s {
            consumers[j] += 1;
            if plan.run[j] {
                dependents[j].push(i);
            }
        }
        sources[i] = s;
    }
    let mut pinned = vec![false; n];
    for (_, node, _, _) in &plan.requested {
        pinned[*node] = true;
    }
    let state = State {
        graph,
        plan,
        caches,
        threads,
        results: (0..n)
            .map(|i| Mutex::new(plan.loaded.get(&i).cloned()))
            .collect(),
        pending: (0..n)
            .map(|i| AtomicUsize::new(sources[i].iter().filter(|&&j| plan.run[j]).count()))
            .collect(),
        consumers_left: consumers.iter().map(|&c| AtomicUsize::new(c)).collect(),
        pinned,
        dependents,
        sources,
        status: (0..n)
            .map(|i| {
                Mutex::new(if plan.loaded.contains_key(&i) {
                    NodeStatus::Cached
                } else if plan.shared[i] {
                    NodeStatus::Shared
                } else {
                    NodeStatus::Idle
                })
            })
            .collect(),
        elapsed: (0..n).map(|_| Mutex::new(Duration::ZERO)).collect(),
        output_bytes: (0..n)
            .map(|i| AtomicUsize::new(plan.loaded.get(&i).map_or(0, |v| bytes_of(v))))
            .collect(),
        failures: Mutex::new(Vec::new()),
        warnings: Mutex::new(Vec::new()),
        live_bytes: AtomicUsize::new(plan.loaded.values().map(|v| bytes_of(v)).sum()),
        peak_bytes: AtomicUsize::new(0),
        done: AtomicUsize::new(0),
        total: plan.run.iter().filter(|&&r| r).count(),
        progress,
        distribution,
        distributed: Mutex::new(Vec::new()),
    };
    state
        .peak_bytes
        .store(state.live_bytes.load(Ordering::Relaxed), Ordering::Relaxed);
    if let Some(progress) = progress {
        progress(0, state.total);
    }

    rayon::scope(|scope| {
        for i in 0..n {
            if plan.run[i] && state.pending[i].load(Ordering::Relaxed) == 0 {
                let state = &state;
                scope.spawn(move |scope| run_task(scope, state, i));
            }
        }
    });

    let State {
        results,
        status,
        elapsed,
        output_bytes,
        failures,
        warnings,
        peak_bytes,
        distributed,
        ..
    } = state;
    let status: Vec<NodeStatus> = status
        .into_iter()
        .map(|s| s.into_inner().unwrap_or(NodeStatus::Failed))
        .collect();
    let results: Vec<Option<Arc<[Value]>>> = results
        .into_iter()
        .map(|r| r.into_inner().unwrap_or(None))
        .collect();
    let mut failures = failures.into_inner().unwrap_or_default();
    let mut outputs = Vec::new();
    for (name, node, port, index) in &plan.requested {
        if let Some(Some(values)) = results.get(*node)
            && let Some(v) = values.get(*port)
        {
            match select(graph, *node, *port, *index, v) {
                Ok(v) => outputs.push((name.clone(), v)),
                Err(message) => failures.push((*node, format!("output `{name}`: {message}"))),
            }
        }
    }
    failures.sort_by_key(|(i, _)| *i);
    RunReport {
        outputs,
        failures: failures
            .into_iter()
            .map(|(i, message)| {
                let node = &graph.nodes[i];
                NodeFailure {
                    node: node.name.clone(),
                    op: node.info.id.clone(),
                    location: node.location.as_ref().map(|l| l.display()),
                    message,
                }
            })
            .collect(),
        nodes: graph
            .nodes
            .iter()
            .zip(status)
            .zip(elapsed)
            .zip(output_bytes)
            .map(|(((node, status), elapsed), bytes)| NodeReport {
                name: node.name.clone(),
                op: node.info.id.clone(),
                status,
                elapsed: elapsed.into_inner().unwrap_or_default(),
                output_bytes: bytes.into_inner(),
            })
            .collect(),
        warnings: warnings.into_inner().unwrap_or_default(),
        peak_bytes: peak_bytes.into_inner(),
        elapsed: Duration::ZERO,
        distributed: distributed.into_inner().unwrap_or_default(),
    }
}

fn bytes_of(values: &[Value]) -> usize {
    values.iter().map(Value::byte_size).sum()
}

fn set_status(state: &State<'_>, i: usize, status: NodeStatus) {
    if let Ok(mut s) = state.status[i].lock() {
        *s = status;
    }
}

fn run_task<'s>(scope: &rayon::Scope<'s>, state: &'s State<'s>, i: usize) {
    let node = &state.graph.nodes[i];
    // Gather inputs; an upstream failure skips this node.
    let mut upstream_failed = state.plan.failed.contains_key(&i);
    let mut inputs: Vec<Option<Value>> = Vec::with_capacity(node.inputs.len());
    let mut selection_error = None;
    for (edge, spec) in node.inputs.iter().zip(&node.info.inputs) {
        let value = match edge {
            Some(e) => match gather(state, e) {
                Ok(Some(v)) => Some(v),
                Ok(None) => {
                    upstream_failed = true;
                    None
                }
                Err(message) => {
                    selection_error
                        .get_or_insert_with(|| format!("input `{}`: {message}", spec.name));
                    None
                }
            },
            None => None,
        };
        inputs.push(value);
    }

    if let Some(message) = state.plan.failed.get(&i) {
        record_failure(state, i, message.clone());
    } else if upstream_failed {
        set_status(state, i, NodeStatus::Skipped);
    } else if let Some(message) = selection_error {
        record_failure(state, i, message);
    } else {
        let ctx = RunContext {
            node: node.name.clone(),
            threads: state.threads,
            element: None,
        };
        let started = Instant::now();
        let outcome = catch_unwind(AssertUnwindSafe(|| match state.distribution {
            Some(d) if crate::distribute::distributable(node) => {
                crate::distribute::run_mapped(node, &inputs, d, &state.distributed)
            }
            _ => run_node(node, &ctx, &inputs),
        }))
        .unwrap_or_else(|payload| {
            Err(OpError::failed(format!(
                "operator panicked: {}",
                panic_message(payload.as_ref())
            )))
        });
        if let Ok(mut e) = state.elapsed[i].lock() {
            *e = started.elapsed();
        }
        let outcome = outcome.and_then(|values| check_list_lengths(node, values));
        match outcome {
            Ok(values) => {
                let values: Arc<[Value]> = values.into();
                if let (Some(memory), Some(key), false) = (
                    state.caches.memory,
                    state.plan.keys[i],
                    node.info.side_effects,
                ) {
                    memory.store(&key, values.clone());
                }
                if let (Some(cache), Some(key), false) = (
                    state.caches.disk,
                    state.plan.keys[i],
                    node.info.side_effects,
                ) && let Err(e) = cache.store(&key, &values)
                    && let Ok(mut w) = state.warnings.lock()
                {
                    w.push(format!(
                        "cache: could not store the result of `{}`: {e}",
                        node.name
                    ));
                }
                let bytes = bytes_of(&values);
                state.output_bytes[i].store(bytes, Ordering::Relaxed);
                let live = state.live_bytes.fetch_add(bytes, Ordering::Relaxed) + bytes;
                state.peak_bytes.fetch_max(live, Ordering::Relaxed);
                if let Ok(mut slot) = state.results[i].lock() {
                    *slot = Some(values);
                }
                set_status(state, i, NodeStatus::Computed);
                // Nobody will read it: free at once.
                if state.consumers_left[i].load(Ordering::Acquire) == 0 && !state.pinned[i] {
                    release(state, i);
                }
            }
            Err(e) => record_failure(state, i, e.to_string()),
        }
    }
    drop(inputs);

    // Release inputs whose last consumer this was.
    for &src in &state.sources[i] {
        if state.consumers_left[src].fetch_sub(1, Ordering::AcqRel) == 1 && !state.pinned[src] {
            release(state, src);
        }
    }
    let done = state.done.fetch_add(1, Ordering::Relaxed) + 1;
    if let Some(progress) = state.progress {
        progress(done, state.total);
    }
    for &d in &state.dependents[i] {
        if state.pending[d].fetch_sub(1, Ordering::AcqRel) == 1 {
            scope.spawn(move |scope| run_task(scope, state, d));
        }
    }
}

/// The value an edge delivers: `Ok(None)` when a source has no result (it failed), `Err` when
/// an index is out of range.
fn gather(state: &State<'_>, edge: &InputEdge) -> Result<Option<Value>, String> {
    let read = |tap: &Tap| -> Result<Option<Value>, String> {
        let src = state.plan.canonical[tap.from.node];
        let value = state.results[src].lock().ok().and_then(|guard| {
            guard
                .as_ref()
                .and_then(|vals| vals.get(tap.from.port).cloned())
        });
        match value {
            Some(v) => select(state.graph, tap.from.node, tap.from.port, tap.index, &v).map(Some),
            None => Ok(None),
        }
    };
    match &edge.source {
        EdgeSource::Tap(tap) => read(tap),
        EdgeSource::List { items, element } => {
            let mut values = Vec::with_capacity(items.len());
            for tap in items {
                match read(tap)? {
                    Some(v) => values.push(v),
                    None => return Ok(None),
                }
            }
            Ok(Some(Value::list(element.clone(), values)))
        }
    }
}

/// `value` itself, or its element `index` (negative: from the end); out of range is an error
/// naming the node, port, index and length.
pub(crate) fn select(
    graph: &Graph,
    node: usize,
    port: usize,
    index: Option<i64>,
    value: &Value,
) -> Result<Value, String> {
    let Some(i) = index else {
        return Ok(value.clone());
    };
    let node = &graph.nodes[node];
    let port = node.info.outputs.get(port).map_or("?", |p| p.name.as_str());
    let Value::List(list) = value else {
        return Err(format!(
            "`{}.{port}` is not a list, it cannot be indexed with [{i}]",
            node.name
        ));
    };
    match list_position(list.items.len(), i) {
        Some(k) => Ok(list.items[k].clone()),
        None => Err(format!(
            "index {i} is out of range for `{}.{port}`, a list of {} element{}",
            node.name,
            list.items.len(),
            if list.items.len() == 1 { "" } else { "s" }
        )),
    }
}

fn release(state: &State<'_>, i: usize) {
    let taken = state.results[i]
        .lock()
        .ok()
        .and_then(|mut slot| slot.take());
    if let Some(values) = taken {
        state
            .live_bytes
            .fetch_sub(bytes_of(&values), Ordering::Relaxed);
    }
}

fn record_failure(state: &State<'_>, i: usize, message: String) {
    set_status(state, i, NodeStatus::Failed);
    if let Ok(mut f) = state.failures.lock() {
        f.push((i, message));
    }
}

pub(crate) fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic".to_string()
    }
}

/// Refuses a result holding a list longer than the run's `--max-list-len` (lists of lists
/// count each level), naming the output port.
fn check_list_lengths(node: &Node, values: Vec<Value>) -> Result<Vec<Value>, OpError> {
    fn longest(value: &Value) -> usize {
        match value {
            Value::List(list) => list
                .items
                .iter()
                .map(longest)
                .max()
                .unwrap_or(0)
                .max(list.items.len()),
            _ => 0,
        }
    }
    for (value, spec) in values.iter().zip(&node.info.outputs) {
        let n = longest(value);
        if n > 0 {
            crate::limits::check_count(
                &format!("elements in a list on output `{}`", spec.name),
                n as u64,
            )
            .map_err(OpError::failed)?;
        }
    }
    Ok(values)
}

/// The NaN/Inf policy: no non-finite geometric value reaches an operator that has not said it
/// accepts one (RELIABILITY.md). Called before every operator call, batch or streamed.
pub fn check_finite_inputs(node: &Node, inputs: &[Option<Value>]) -> Result<(), OpError> {
    for (value, spec) in inputs.iter().zip(&node.info.inputs) {
        if let Some(value) = value
            && !spec.non_finite
            && let Some(at) = value.non_finite_at()
        {
            return Err(OpError::input(
                &spec.name,
                format!("{at} is not finite (NaN or infinity); this input needs finite values"),
            ));
        }
    }
    Ok(())
}

/// Runs one node's operator: once, or once per list element for a mapped node.
pub fn run_node(
    node: &Node,
    ctx: &RunContext,
    inputs: &[Option<Value>],
) -> Result<Vec<Value>, OpError> {
    check_finite_inputs(node, inputs)?;
    if !node.is_mapped() {
        let outputs = node.op.run(ctx, &Inputs::new(&node.info.inputs, inputs))?;
        return collect_outputs(node, outputs, false);
    }
    let n = mapped_len(node, inputs)?;
    let per_element: Vec<Result<Vec<Value>, OpError>> = (0..n)
        .into_par_iter()
        .map(|k| run_element(node, ctx, inputs, k, k))
        .collect();
    let elements = per_element
        .into_iter()
        .enumerate()
        .map(|(k, result)| result.map_err(|e| OpError::failed(format!("list element {k}: {e}"))))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(gather_columns(node, elements))
}

/// A mapped node's outputs from its elements' outputs: one list per output port, in element
/// order.
pub(crate) fn gather_columns(node: &Node, elements: Vec<Vec<Value>>) -> Vec<Value> {
    let mut columns: Vec<Vec<Value>> =
        vec![Vec::with_capacity(elements.len()); node.info.outputs.len()];
    for values in elements {
        for (column, value) in columns.iter_mut().zip(values) {
            column.push(value);
        }
    }
    columns
        .into_iter()
        .zip(&node.info.outputs)
        .map(|(items, spec)| Value::list(spec.ty.clone(), items))
        .collect()
}

/// The length of a mapped node's lists: every mapped input must be a list, all of one length.
pub(crate) fn mapped_len(node: &Node, inputs: &[Option<Value>]) -> Result<usize, OpError> {
    let mut len: Option<(usize, &str)> = None;
    for (edge, (value, spec)) in node.inputs.iter().zip(inputs.iter().zip(&node.info.inputs)) {
        if !edge.as_ref().is_some_and(|e| e.mapped) {
            continue;
        }
        let Some(Value::List(list)) = value else {
            return Err(OpError::input(&spec.name, "expected a list to map over"));
        };
        match len {
            None => len = Some((list.items.len(), &spec.name)),
            Some((n, first)) if n != list.items.len() => {
                return Err(OpError::input(
                    &spec.name,
                    format!(
                        "mapped list inputs differ in length: `{first}` has {n} elements, `{}` has {}",
                        spec.name,
                        list.items.len()
                    ),
                ));
            }
            Some(_) => {}
        }
    }
    Ok(len.map_or(0, |(n, _)| n))
}

/// Runs a mapped node's operator on element `local` of its mapped lists, as list element
/// `element` of the whole map (what the operator sees in [`RunContext::element`]).
pub(crate) fn run_element(
    node: &Node,
    ctx: &RunContext,
    inputs: &[Option<Value>],
    local: usize,
    element: usize,
) -> Result<Vec<Value>, OpError> {
    let element_inputs: Vec<Option<Value>> = node
        .inputs
        .iter()
        .zip(inputs)
        .map(|(edge, value)| match (edge, value) {
            (Some(e), Some(Value::List(list))) if e.mapped => list.items.get(local).cloned(),
            (_, v) => v.clone(),
        })
        .collect();
    let element_ctx = RunContext {
        element: Some(element),
        ..ctx.clone()
    };
    let outputs = node.op.run(
        &element_ctx,
        &Inputs::new(&node.info.inputs, &element_inputs),
    )?;
    collect_outputs(node, outputs, true)
}

/// Orders an operator's outputs by its declared ports, checking presence and types.
pub(crate) fn collect_outputs(
    node: &Node,
    mut outputs: crate::op::Outputs,
    element: bool,
) -> Result<Vec<Value>, OpError> {
    let mut values = Vec::with_capacity(node.info.outputs.len());
    for (spec, declared) in node.info.outputs.iter().zip(&node.output_types) {
        let Some(value) = outputs.take(&spec.name) else {
            return Err(OpError::failed(format!(
                "operator `{}` did not produce its output `{}`",
                node.info.id, spec.name
            )));
        };
        let expected = if element { &spec.ty } else { declared };
        let got = value.port_type();
        if &got != expected {
            return Err(OpError::failed(format!(
                "operator `{}` produced {got} on output `{}`, declared {expected}",
                node.info.id, spec.name
            )));
        }
        values.push(value);
    }
    Ok(values)
}
