//! Distributed list maps: a mapped node's elements run as tasks somewhere else (a Ray
//! cluster, another process), in chunks, with every finished element kept under its content key
//! so a re-run after a failure reuses it.
//!
//! The engine stays in charge of the graph: it plans, gathers a mapped node's inputs, and hands
//! the node's *missing* elements to a [`TaskRunner`] as self-contained task payloads. A payload
//! names the operator by id and carries its checked parameters, its fingerprint, the limits of
//! the run, the global indices of the chunk's elements and the chunk's inputs in the value codec
//! (the engine's own serialized form, [`crate::codec`]). A worker runs it with [`run_task`] —
//! the same per-element code path as a local run — and returns the chunk's outputs in the same
//! codec. Results are therefore byte-identical to a local run.
//!
//! # Content keys of elements
//! An element's key is BLAKE3 over the operator id and version, its parameters, its
//! fingerprint (file contents for readers) and the content hash of each of the element's
//! inputs. Unlike node keys (which follow the graph), element keys follow the data: the same
//! image described with the same parameters is found again even from another graph. Each
//! finished element is stored in the item cache as soon as its task returns, so an interrupted
//! or failed run loses only the chunks in flight.
//!
//! # What is distributed
//! Mapped nodes of built-in operators without side effects. Writers (side effects) run where
//! the files are; operators loaded from a plugin library at run time run locally too, since a
//! worker cannot be assumed to have the library.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::cache::DiskCache;
use crate::codec::{decode_values, encode_values};
use crate::graph::{InputEdge, Node, PortRef};
use crate::op::{OpError, Origin, Registry, RunContext};
use crate::params::{ParamMap, ParamValue};
use crate::value::Value;

/// First bytes of a task payload.
pub const TASK_MAGIC: [u8; 8] = *b"OCTASK01";
/// First bytes of a task result.
pub const RESULT_MAGIC: [u8; 8] = *b"OCRSLT01";
/// Bumped when the element key derivation changes.
/// Bumped when the element key derivation changes; the engine's version is part of it, so an
/// operator fixed in a new release never reuses the old release's elements.
const ITEM_SCHEME: &[u8] = concat!("ocellus-item-v1/", env!("CARGO_PKG_VERSION")).as_bytes();

/// One mapped node handed to a runner.
#[derive(Debug, Clone)]
pub struct Stage {
    /// Qualified node name.
    pub node: String,
    /// Operator id.
    pub op: String,
    /// Elements of the node's list.
    pub items: usize,
    /// Elements found in the item cache (not sent).
    pub reused: usize,
}

/// A finished task, as the runner reports it.
#[derive(Debug, Clone)]
pub struct TaskDone {
    /// Index into the task list given to [`TaskRunner::run`].
    pub task: usize,
    /// The task's result bytes ([`run_task`]'s output), or the worker's error.
    pub result: Result<Vec<u8>, String>,
    /// Which worker ran it (e.g. `127.0.0.1:pid 4711`).
    pub worker: String,
    /// Seconds the worker spent on it.
    pub seconds: f64,
}

/// Runs task payloads somewhere: a Ray cluster, another process, this process.
pub trait TaskRunner: Send + Sync {
    /// Runs every task, in any order and anywhere, calling `done` once per finished task on
    /// the calling thread. A task's own failure is reported through `done` (its `result`); an
    /// `Err` from `done` means the run gives up: stop and return that error. `Err` from `run`
    /// is a failure of the runner itself (the cluster went away).
    fn run(
        &self,
        stage: &Stage,
        tasks: Vec<Vec<u8>>,
        done: &mut dyn FnMut(TaskDone) -> Result<(), String>,
    ) -> Result<(), String>;
}

/// Progress of distributed stages: (node, elements done, elements in the stage).
pub type ItemProgressFn = Arc<dyn Fn(&str, usize, usize) + Send + Sync>;

/// How a run distributes its list maps.
#[derive(Clone)]
pub struct Distribution {
    /// Where tasks run.
    pub runner: Arc<dyn TaskRunner>,
    /// Elements per task; 0 picks it from the stage's size (about 64 tasks, 1 to 16 elements
    /// each).
    pub items_per_task: usize,
    /// Where finished elements are kept by content key (reused by later runs); `None` keeps
    /// nothing.
    pub item_cache: Option<std::path::PathBuf>,
    /// Called as elements finish.
    pub progress: Option<ItemProgressFn>,
}

impl std::fmt::Debug for Distribution {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Distribution")
            .field("items_per_task", &self.items_per_task)
            .field("item_cache", &self.item_cache)
            .finish_non_exhaustive()
    }
}

/// Time and work of one worker within a stage.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WorkerStats {
    /// Tasks it finished.
    pub tasks: usize,
    /// Elements in those tasks.
    pub items: usize,
    /// Seconds it spent running them (as it measured).
    pub busy_seconds: f64,
}

/// What one distributed stage did.
#[derive(Debug, Clone, Default)]
pub struct StageStats {
    /// Qualified node name.
    pub node: String,
    /// Operator id.
    pub op: String,
    /// Elements in the node's list.
    pub items: usize,
    /// Elements reused from the item cache.
    pub reused: usize,
    /// Tasks sent.
    pub tasks: usize,
    /// Tasks that failed (the stage fails with the first).
    pub failed_tasks: usize,
    /// Wall time from the first task sent to the last result.
    pub elapsed: Duration,
    /// Payload bytes sent and result bytes received.
    pub bytes_sent: usize,
    /// Result bytes received.
    pub bytes_received: usize,
    /// Per worker, by the runner's name for it.
    pub workers: BTreeMap<String, WorkerStats>,
}

/// True when `node` is a mapped node whose elements can run on another machine.
pub fn distributable(node: &Node) -> bool {
    node.is_mapped() && !node.info.side_effects && matches!(node.info.origin, Origin::Builtin)
}

/// The elements per task for `items` elements when the user left it to us: enough tasks to
/// balance (about 64 per stage), never more than 16 elements in one.
fn auto_items_per_task(items: usize) -> usize {
    items.div_ceil(64).clamp(1, 16)
}

/// Runs a mapped node's elements through `distribution`: cached elements are loaded, the rest
/// sent as tasks; the result is the node's outputs exactly as [`crate::exec::run_node`] gives
/// them. `stats` receives the stage's record.
pub fn run_mapped(
    node: &Node,
    inputs: &[Option<Value>],
    distribution: &Distribution,
    stats: &Mutex<Vec<StageStats>>,
) -> Result<Vec<Value>, OpError> {
    crate::exec::check_finite_inputs(node, inputs)?;
    let n = crate::exec::mapped_len(node, inputs)?;
    let fingerprint = node.op.fingerprint()?;
    let element_types: Vec<_> = node.info.outputs.iter().map(|p| p.ty.clone()).collect();
    let cache = distribution
        .item_cache
        .as_deref()
        .and_then(|dir| match DiskCache::open(dir) {
            Ok(cache) => Some(cache),
            Err(e) => {
                tracing::warn!(
                    "item cache {}: {e}; elements will not be kept",
                    dir.display()
                );
                None
            }
        });

    // Keys of every element, then what the cache already holds.
    let whole_hashes: Vec<Option<[u8; 32]>> = node
        .inputs
        .iter()
        .zip(inputs)
        .map(|(edge, value)| match (edge, value) {
            (Some(e), Some(v)) if !e.mapped => Some(value_hash(v)),
            _ => None,
        })
        .collect();
    let keys: Vec<[u8; 32]> = (0..n)
        .into_par_iter()
        .map(|k| element_key(node, &fingerprint, inputs, &whole_hashes, k))
        .collect();
    let mut slots: Vec<Option<Vec<Value>>> = keys
        .par_iter()
        .map(|key| cache.as_ref().and_then(|c| c.load(key, &element_types)))
        .collect();
    let missing: Vec<usize> = (0..n).filter(|&k| slots[k].is_none()).collect();
    let reused = n - missing.len();

    let per_task = match distribution.items_per_task {
        0 => auto_items_per_task(missing.len()),
        k => k,
    };
    let chunks: Vec<&[usize]> = missing.chunks(per_task).collect();
    let limits = crate::limits::get();
    let tasks: Vec<Vec<u8>> = chunks
        .par_iter()
        .map(|chunk| encode_task(node, &fingerprint, inputs, chunk, &limits))
        .collect();
    let stage = Stage {
        node: node.name.clone(),
        op: node.info.id.clone(),
        items: n,
        reused,
    };
    let mut record = StageStats {
        node: node.name.clone(),
        op: node.info.id.clone(),
        items: n,
        reused,
        tasks: tasks.len(),
        bytes_sent: tasks.iter().map(Vec::len).sum(),
        ..StageStats::default()
    };
    let mut done_items = reused;
    if let Some(progress) = &distribution.progress {
        progress(&node.name, done_items, n);
    }
    let started = Instant::now();
    let mut store_errors = Vec::new();
    let mut first_failure: Option<String> = None;
    let outcome = if tasks.is_empty() {
        Ok(())
    } else {
        distribution
            .runner
            .run(&stage, tasks, &mut |finished: TaskDone| {
                let Some(chunk) = chunks.get(finished.task) else {
                    return Err(format!(
                        "runner reported task {} of {}",
                        finished.task,
                        chunks.len()
                    ));
                };
                let worker = record.workers.entry(finished.worker.clone()).or_default();
                worker.tasks += 1;
                worker.busy_seconds += finished.seconds;
                let bytes = match finished.result {
                    Ok(bytes) => bytes,
                    Err(message) => {
                        record.failed_tasks += 1;
                        let message = format!(
                            "elements {}: {message} (on {})",
                            describe_chunk(chunk),
                            finished.worker
                        );
                        first_failure.get_or_insert(message.clone());
                        return Err(message);
                    }
                };
                worker.items += chunk.len();
                record.bytes_received += bytes.len();
                let values = decode_result(&bytes, node, chunk.len())?;
                for (&k, element) in chunk.iter().zip(values) {
                    if let Some(cache) = &cache
                        && let Err(e) = cache.store(&keys[k], &element)
                    {
                        store_errors.push(e.to_string());
                    }
                    slots[k] = Some(element);
                }
                done_items += chunk.len();
                if let Some(progress) = &distribution.progress {
                    progress(&node.name, done_items, n);
                }
                Ok(())
            })
    };
    record.elapsed = started.elapsed();
    if let Ok(mut all) = stats.lock() {
        all.push(record);
    }
    if let Err(message) = outcome {
        return Err(OpError::failed(first_failure.unwrap_or(message)));
    }
    if let Some(e) = store_errors.first() {
        tracing::warn!(
            "item cache: could not store an element of `{}`: {e}",
            node.name
        );
    }

    let elements = slots
        .into_iter()
        .enumerate()
        .map(|(k, slot)| {
            slot.ok_or_else(|| OpError::failed(format!("the runner finished without element {k}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(crate::exec::gather_columns(node, elements))
}

fn describe_chunk(chunk: &[usize]) -> String {
    match (chunk.first(), chunk.last()) {
        (Some(a), Some(b)) if a == b => format!("{a}"),
        (Some(a), Some(b)) => format!("{a}..={b}"),
        _ => String::from("none"),
    }
}

fn value_hash(value: &Value) -> [u8; 32] {
    *blake3::hash(&encode_values(std::slice::from_ref(value))).as_bytes()
}

/// An element's content key (see the module docs).
fn element_key(
    node: &Node,
    fingerprint: &[u8],
    inputs: &[Option<Value>],
    whole_hashes: &[Option<[u8; 32]>],
    k: usize,
) -> [u8; 32] {
    let mut h = blake3::Hasher::new();
    let field = |h: &mut blake3::Hasher, bytes: &[u8]| {
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    field(&mut h, ITEM_SCHEME);
    field(&mut h, node.info.id.as_bytes());
    h.update(&node.info.version.to_le_bytes());
    for (name, value) in &node.params {
        field(&mut h, name.as_bytes());
        field(&mut h, value.to_string().as_bytes());
    }
    field(&mut h, fingerprint);
    for ((edge, value), whole) in node.inputs.iter().zip(inputs).zip(whole_hashes) {
        match (edge, value) {
            (Some(e), Some(Value::List(list))) if e.mapped => {
                h.update(&[2]);
                match list.items.get(k) {
                    Some(item) => h.update(&value_hash(item)),
                    None => h.update(&[0]),
                };
            }
            (_, Some(_)) => {
                h.update(&[1]);
                if let Some(hash) = whole {
                    h.update(hash);
                }
            }
            (_, None) => {
                h.update(&[0]);
            }
        }
    }
    *h.finalize().as_bytes()
}

// ---------------------------------------------------------------------------------------------
// Payloads

/// Input kinds in a payload.
const INPUT_ABSENT: u8 = 0;
const INPUT_WHOLE: u8 = 1;
const INPUT_MAPPED: u8 = 2;

struct Writer(Vec<u8>);

impl Writer {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn bytes(&mut self, b: &[u8]) {
        self.u64(b.len() as u64);
        self.0.extend_from_slice(b);
    }
    fn param(&mut self, v: &ParamValue) {
        match v {
            ParamValue::Bool(b) => {
                self.u8(0);
                self.u8(u8::from(*b));
            }
            ParamValue::Int(i) => {
                self.u8(1);
                self.0.extend_from_slice(&i.to_le_bytes());
            }
            ParamValue::Float(x) => {
                self.u8(2);
                self.u64(x.to_bits());
            }
            ParamValue::Str(s) => {
                self.u8(3);
                self.bytes(s.as_bytes());
            }
            ParamValue::List(items) => {
                self.u8(4);
                self.u64(items.len() as u64);
                for item in items {
                    self.param(item);
                }
            }
            ParamValue::None => self.u8(5),
        }
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    depth: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let Some((head, rest)) = self.bytes.split_at_checked(n) else {
            return Err("task payload is truncated".into());
        };
        self.bytes = rest;
        Ok(head)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.array::<1>()?[0])
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    /// A count of items of at least `min_bytes` each, checked against what is left.
    fn count(&mut self, min_bytes: usize) -> Result<usize, String> {
        let n = self.u64()?;
        if n.saturating_mul(min_bytes.max(1) as u64) > self.bytes.len() as u64 {
            return Err("task payload declares more items than it holds".into());
        }
        Ok(n as usize)
    }
    fn bytes(&mut self) -> Result<&'a [u8], String> {
        let n = self.count(1)?;
        self.take(n)
    }
    fn string(&mut self) -> Result<String, String> {
        String::from_utf8(self.bytes()?.to_vec()).map_err(|_| "task payload: bad UTF-8".into())
    }
    fn param(&mut self) -> Result<ParamValue, String> {
        Ok(match self.u8()? {
            0 => ParamValue::Bool(self.u8()? != 0),
            1 => ParamValue::Int(i64::from_le_bytes(self.array()?)),
            2 => ParamValue::Float(f64::from_bits(self.u64()?)),
            3 => ParamValue::Str(self.string()?),
            4 => {
                if self.depth >= 8 {
                    return Err("task payload: parameter lists nest too deeply".into());
                }
                let n = self.count(1)?;
                self.depth += 1;
                let items = (0..n).map(|_| self.param()).collect::<Result<_, _>>()?;
                self.depth -= 1;
                ParamValue::List(items)
            }
            5 => ParamValue::None,
            t => return Err(format!("task payload: unknown parameter tag {t}")),
        })
    }
}

/// The payload of one task: `chunk` holds the (global) element indices it computes.
fn encode_task(
    node: &Node,
    fingerprint: &[u8],
    inputs: &[Option<Value>],
    chunk: &[usize],
    limits: &crate::limits::Limits,
) -> Vec<u8> {
    let mut w = Writer(Vec::new());
    w.0.extend_from_slice(&TASK_MAGIC);
    w.bytes(node.name.as_bytes());
    w.bytes(node.info.id.as_bytes());
    w.u32(node.info.version);
    w.u64(node.params.len() as u64);
    for (name, value) in &node.params {
        w.bytes(name.as_bytes());
        w.param(value);
    }
    w.bytes(fingerprint);
    w.u64(limits.max_image_pixels);
    w.u64(limits.max_alloc_bytes);
    w.u64(limits.max_list_len);
    w.u64(chunk.len() as u64);
    for &k in chunk {
        w.u64(k as u64);
    }
    w.u64(node.inputs.len() as u64);
    let mut values = Vec::new();
    for (edge, value) in node.inputs.iter().zip(inputs) {
        match (edge, value) {
            (Some(e), Some(Value::List(list))) if e.mapped => {
                w.u8(INPUT_MAPPED);
                let items = chunk
                    .iter()
                    .filter_map(|&k| list.items.get(k).cloned())
                    .collect();
                values.push(Value::list(list.element.clone(), items));
            }
            (_, Some(v)) => {
                w.u8(INPUT_WHOLE);
                values.push(v.clone());
            }
            (_, None) => w.u8(INPUT_ABSENT),
        }
    }
    w.bytes(&encode_values(&values));
    w.0
}

/// Runs one task payload with the operators of `registry`: the worker's side of a distributed
/// map. Returns the result bytes (the chunk's outputs, one list per output port, in the value
/// codec) or a message saying why the chunk failed.
///
/// The task's limits (`--max-image-pixels` and the others, as the driver had them) apply to
/// this call only when `apply_limits` is true, which sets them for the whole process: what a
/// worker process does ([`run_worker_task`]); a runner inside the driver's process leaves
/// them as they are. An operator's panic is caught and returned as an error.
pub fn run_task(registry: &Registry, payload: &[u8]) -> Result<Vec<u8>, String> {
    run_task_with(registry, payload, false)
}

/// [`run_task`] in a worker process: the driver's limits are applied first.
pub fn run_worker_task(registry: &Registry, payload: &[u8]) -> Result<Vec<u8>, String> {
    run_task_with(registry, payload, true)
}

fn run_task_with(
    registry: &Registry,
    payload: &[u8],
    apply_limits: bool,
) -> Result<Vec<u8>, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        decode_and_run(registry, payload, apply_limits)
    }))
    .unwrap_or_else(|payload| {
        Err(format!(
            "operator panicked: {}",
            crate::exec::panic_message(payload.as_ref())
        ))
    })
}

fn decode_and_run(
    registry: &Registry,
    payload: &[u8],
    apply_limits: bool,
) -> Result<Vec<u8>, String> {
    let Some(body) = payload.strip_prefix(&TASK_MAGIC) else {
        return Err("not an ocellus task payload (or one from another version)".into());
    };
    let mut r = Reader {
        bytes: body,
        depth: 0,
    };
    let name = r.string()?;
    let op_id = r.string()?;
    let version = r.u32()?;
    let n_params = r.count(2)?;
    let mut params = ParamMap::new();
    for _ in 0..n_params {
        let key = r.string()?;
        let value = r.param()?;
        params.insert(key, value);
    }
    let fingerprint = r.bytes()?.to_vec();
    let limits = crate::limits::Limits {
        max_image_pixels: r.u64()?,
        max_alloc_bytes: r.u64()?,
        max_list_len: r.u64()?,
    };
    let n_elements = r.count(8)?;
    let elements: Vec<usize> = (0..n_elements)
        .map(|_| r.u64().map(|k| k as usize))
        .collect::<Result<_, _>>()?;
    let n_inputs = r.count(1)?;
    let kinds: Vec<u8> = (0..n_inputs).map(|_| r.u8()).collect::<Result<_, _>>()?;
    let values = decode_values(r.bytes()?).map_err(|e| format!("task inputs: {e}"))?;
    if !r.bytes.is_empty() {
        return Err("task payload has trailing bytes".into());
    }

    let Some(factory) = registry.get(&op_id) else {
        return Err(format!("operator `{op_id}` is not known on this worker"));
    };
    let info = factory.info().clone();
    if info.version != version {
        return Err(format!(
            "operator `{op_id}` is version {} on this worker, {version} on the driver",
            info.version
        ));
    }
    if kinds.len() != info.inputs.len() {
        return Err(format!(
            "operator `{op_id}` has {} inputs on this worker, {} in the task",
            info.inputs.len(),
            kinds.len()
        ));
    }
    let op = factory.build(&params)?;
    // The engine's own fingerprint check: a reader whose file changed under the driver's feet
    // is not silently run on other contents.
    let here = op.fingerprint().map_err(|e| e.to_string())?;
    if here != fingerprint {
        return Err(format!(
            "operator `{op_id}` sees different input files on this worker than on the driver"
        ));
    }
    if apply_limits {
        crate::limits::set(limits);
    }

    let mut values = values.into_iter();
    let mut inputs: Vec<Option<Value>> = Vec::with_capacity(kinds.len());
    let mut edges: Vec<Option<InputEdge>> = Vec::with_capacity(kinds.len());
    for kind in &kinds {
        let edge = |mapped| InputEdge::port(PortRef { node: 0, port: 0 }, mapped);
        match *kind {
            INPUT_ABSENT => {
                inputs.push(None);
                edges.push(None);
            }
            INPUT_WHOLE | INPUT_MAPPED => {
                let Some(value) = values.next() else {
                    return Err("task payload has fewer inputs than it declares".into());
                };
                if *kind == INPUT_MAPPED {
                    match &value {
                        Value::List(list) if list.items.len() == elements.len() => {}
                        _ => {
                            return Err(
                                "task payload: a mapped input is not the chunk's list".into()
                            );
                        }
                    }
                }
                inputs.push(Some(value));
                edges.push(Some(edge(*kind == INPUT_MAPPED)));
            }
            k => return Err(format!("task payload: unknown input kind {k}")),
        }
    }
    if values.next().is_some() {
        return Err("task payload has more inputs than it declares".into());
    }
    if !edges.iter().flatten().any(|e| e.mapped) {
        return Err("task payload maps over no input".into());
    }
    let output_types = info
        .outputs
        .iter()
        .map(|p| p.ty.clone().list_of())
        .collect();
    let node = Node {
        name,
        info: Arc::new(info),
        op,
        params,
        inputs: edges,
        output_types,
        location: None,
    };
    let ctx = RunContext {
        node: node.name.clone(),
        threads: rayon::current_num_threads(),
        element: None,
    };
    crate::exec::check_finite_inputs(&node, &inputs).map_err(|e| e.to_string())?;
    let per_element: Vec<Result<Vec<Value>, OpError>> = (0..elements.len())
        .into_par_iter()
        .map(|local| crate::exec::run_element(&node, &ctx, &inputs, local, elements[local]))
        .collect();
    let elements = per_element
        .into_iter()
        .enumerate()
        .map(|(local, result)| result.map_err(|e| format!("list element {}: {e}", elements[local])))
        .collect::<Result<Vec<_>, _>>()?;
    let outputs = crate::exec::gather_columns(&node, elements);
    let mut out = RESULT_MAGIC.to_vec();
    out.extend_from_slice(&encode_values(&outputs));
    Ok(out)
}

/// Per-element outputs of a task result for `node`, checked against its ports.
fn decode_result(bytes: &[u8], node: &Node, len: usize) -> Result<Vec<Vec<Value>>, String> {
    let Some(body) = bytes.strip_prefix(&RESULT_MAGIC) else {
        return Err("a worker returned something that is not an ocellus task result".into());
    };
    let outputs = decode_values(body).map_err(|e| format!("a worker's result: {e}"))?;
    if outputs.len() != node.info.outputs.len() {
        return Err(format!(
            "a worker returned {} outputs for `{}`, which has {}",
            outputs.len(),
            node.name,
            node.info.outputs.len()
        ));
    }
    let mut elements: Vec<Vec<Value>> = vec![Vec::with_capacity(outputs.len()); len];
    for (value, spec) in outputs.into_iter().zip(&node.info.outputs) {
        match value {
            Value::List(list)
                if list.element == spec.ty
                    && list.items.len() == len
                    && list.items.iter().all(|item| item.port_type() == spec.ty) =>
            {
                for (element, item) in elements.iter_mut().zip(list.items.iter()) {
                    element.push(item.clone());
                }
            }
            other => {
                return Err(format!(
                    "a worker returned {} on `{}.{}`, expected a list of {len} {}",
                    other.port_type(),
                    node.name,
                    spec.name,
                    spec.ty
                ));
            }
        }
    }
    Ok(elements)
}

/// Runs tasks in this process on the current thread pool: the reference runner (tests compare
/// it with local runs) and a way to exercise the distributed path without a cluster.
pub struct LocalRunner {
    registry: Registry,
    /// Tasks run at once (1 = one after another).
    pub parallel: usize,
}

impl LocalRunner {
    /// A runner using these operators.
    pub fn new(registry: Registry) -> LocalRunner {
        LocalRunner {
            registry,
            parallel: 2,
        }
    }
}

impl TaskRunner for LocalRunner {
    fn run(
        &self,
        _stage: &Stage,
        tasks: Vec<Vec<u8>>,
        done: &mut dyn FnMut(TaskDone) -> Result<(), String>,
    ) -> Result<(), String> {
        let worker = format!("local:pid {}", std::process::id());
        for (batch_start, batch) in tasks
            .chunks(self.parallel.max(1))
            .enumerate()
            .map(|(b, batch)| (b * self.parallel.max(1), batch))
        {
            let results: Vec<(Result<Vec<u8>, String>, f64)> = batch
                .par_iter()
                .map(|payload| {
                    let started = Instant::now();
                    let result = run_task(&self.registry, payload);
                    (result, started.elapsed().as_secs_f64())
                })
                .collect();
            for (offset, (result, seconds)) in results.into_iter().enumerate() {
                done(TaskDone {
                    task: batch_start + offset,
                    result,
                    worker: worker.clone(),
                    seconds,
                })?;
            }
        }
        Ok(())
    }
}
