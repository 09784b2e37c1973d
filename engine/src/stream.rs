//! Streaming: a graph whose source yields a frame sequence runs frame by frame, its stages
//! pipelined across frames on bounded channels.
//!
//! ```ron
//! Graph(
//!     name: "track",
//!     nodes: {
//!         "video": (op: "capture.moving_shapes", params: (frames: 300)),
//!         "gray":  (op: "filter.grayscale", inputs: { "image": "video.frames" }),
//!         "bg":    (op: "segment.background", inputs: { "frames": "gray.image" }),
//!     },
//!     outputs: { "mask": "bg.masks" },
//!     stream: (
//!         capacity: 4,         // packets per channel (default 4)
//!         policy: "block",     // "block" (default): a full queue stops the source;
//!                              // "drop": a frame that finds a queue full is dropped and counted
//!         rate_fps: 30,        // pace the sources in real time (required by "drop")
//!         sources: ["video"],  // default: every node that can stream
//!         encode: { "mask": ["gif"] },   // image outputs written with --emit (gif by default)
//!         metrics: ["csv", "jsonl"],     // metrics outputs written with --emit (csv by default)
//!         feedback: { "camera.velocity": "servo.velocity" },   // see below
//!     ),
//! )
//! ```
//!
//! The graph is typed exactly as in a batch run, where a source's sequence is a `List<T>` and
//! everything downstream works on whole lists; streaming changes when values exist, not what
//! they are. Each needed node falls in one class:
//!
//! - **static**: depends on no stream; runs once before the first frame (cached as usual);
//! - **source**: an operator with `per_frame` outputs ([`crate::op::FrameSource`]): produces
//!   frame `k` on demand, stamped with its capture time;
//! - **per-frame**: mapped over a streamed list (a `List<T>` feeding a `T` port): runs once
//!   per packet, as a batch run runs it once per element;
//! - **sequence**: a stateful operator reading streamed lists on its `per_frame` ports
//!   ([`crate::op::SequenceState`]): pushed one frame at a time, finished after the last;
//! - **final**: anything else that reads a stream (a whole list, an element `[i]`, a list
//!   literal, or a value only known at the end): runs after the last frame on the gathered
//!   lists, as in a batch run. Its inputs are held in memory for the whole stream.
//!
//! Sources, per-frame and sequence nodes are pipeline stages, one thread each, connected by
//! bounded crossbeam channels of `capacity` packets: while frame k+1 is filtered, frame k is
//! matched. The stages run their operators on the run's rayon pool of `threads` workers, so
//! `threads` bounds the cores in use. Every stage handles packets in order, so results never
//! depend on the thread count or on timing — except which frames `policy: "drop"` drops.
//!
//! A stage with several streamed inputs aligns them by timestamp (as MediaPipe's default input
//! policy does): it waits for one packet on every input; when their timestamps differ, the
//! older packets are discarded (counted as *unaligned*) until all agree. Inputs from one source
//! always agree.
//!
//! **Feedback** closes a loop without a cycle in the graph: `feedback: { "src.port":
//! "node.output" }` delivers what `node` computed on `output` for frame k to the source `src`
//! on its feedback input `port` ([`crate::op::PortSpec::feedback`], [`FrameSource::feed`])
//! before `src` produces frame k + 1 — a camera moved by a controller that watches its images,
//! as a back edge does in MediaPipe. `node` must work on `src`'s frames alone, frame by frame
//! (per-frame or sequence), and the types must agree; `policy: "drop"` is refused (a dropped
//! frame would leave the loop without its value), and so is a batch run. The source waits for
//! the loop before each frame, so a loop runs at its latency: the stages still overlap with
//! the ones outside the loop.
//!
//! Memory is bounded by the channels (about `capacity` packets per edge) plus each stage's own
//! state, whatever the sequence length — unless final nodes gather a stream.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, bounded};

use crate::diag::{Code, Diagnostic, Diagnostics, SourceFile, suggest};
use crate::exec::{
    RunError, RunOptions, RunReport, collect_outputs, panic_message, run_node, select,
};
use crate::graph::{EdgeSource, Graph, GraphOutput, InputEdge, PortRef};
use crate::op::{FrameSource, Inputs, OpError, Packet, Registry, RunContext, SequenceState};
use crate::resolve::{Override, load_source, parse_spec, read_source};
use crate::ron_syntax::{RonValue, Spanned, a_kind};
use crate::spec::{head_span, struct_fields, unknown_field};
use crate::timeline::{Encoding, describe, number, parse_encode};
use crate::value::Value;

const STREAM_FIELDS: [&str; 7] = [
    "capacity", "policy", "rate_fps", "sources", "encode", "metrics", "feedback",
];
/// Largest channel capacity, packets.
pub const MAX_CAPACITY: usize = 4096;

/// What a source does with a frame that finds a queue full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Policy {
    /// Wait until there is room (backpressure): no frame is lost.
    Block,
    /// Drop the frame and count it (a live camera's flow limiter).
    Drop,
}

/// How per-frame metrics outputs are written with `--emit`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum MetricsFormat {
    /// `NAME.csv`: a header and one row per frame.
    Csv,
    /// `NAME.jsonl`: one JSON object per frame, written as frames arrive.
    Jsonl,
}

impl MetricsFormat {
    /// Every name, as written in `metrics`.
    pub const NAMES: [&'static str; 2] = ["csv", "jsonl"];
}

/// The checked `stream` section.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamSpec {
    /// Packets each channel holds.
    pub capacity: usize,
    /// Full-queue policy.
    pub policy: Policy,
    /// Real-time pacing of the sources, frames per second.
    pub rate_fps: Option<f64>,
    /// Source node names; empty: every needed node that can stream.
    pub sources: Vec<String>,
    /// Encodings per image output (outputs not listed get GIF).
    pub encode: BTreeMap<String, Vec<Encoding>>,
    /// Formats of metrics outputs.
    pub metrics: Vec<MetricsFormat>,
    /// Feedback edges: later values delivered to a source before its next frame.
    pub feedback: Vec<Feedback>,
}

/// One feedback edge of a stream: `to: from` in the section's `feedback` map. The value that
/// the stage `from.0` computes on its output `from.1` for frame `k` is delivered to the source
/// `to.0` on its feedback input `to.1` before the source produces frame `k + 1`
/// ([`FrameSource::feed`]). This closes a loop — a camera driven by a controller that watches
/// its images — without a cycle in the graph: the edge crosses from one frame to the next, as
/// a back edge does in MediaPipe. The source therefore waits for frame `k` to go through the
/// loop before it produces frame `k + 1`: the loop runs at its latency, not its throughput.
#[derive(Debug, Clone, PartialEq)]
pub struct Feedback {
    /// Source node and its feedback input port.
    pub to: (String, String),
    /// Producing node and its output port.
    pub from: (String, String),
    /// The map entry, for diagnostics.
    pub span: crate::ron_syntax::Span,
}

impl Default for StreamSpec {
    fn default() -> Self {
        StreamSpec {
            capacity: 4,
            policy: Policy::Block,
            rate_fps: None,
            sources: Vec::new(),
            encode: BTreeMap::new(),
            metrics: vec![MetricsFormat::Csv],
            feedback: Vec::new(),
        }
    }
}

fn stream_diag(
    source: &Arc<SourceFile>,
    span: crate::ron_syntax::Span,
    message: impl Into<String>,
    label: &str,
) -> Diagnostic {
    Diagnostic::at(Code::Stream, source, span, message).label(label)
}

/// Reads a graph file; returns its graph and, when it has a `stream` section, the checked
/// section. Errors for a section that is malformed, names unknown nodes or outputs, or a graph
/// with nothing that can stream.
pub fn load_streamed(
    registry: &Registry,
    source: &Arc<SourceFile>,
    overrides: &[Override],
) -> Result<(Graph, Option<StreamSpec>), Diagnostics> {
    let mut diags = Diagnostics::default();
    let Some(spec) = parse_spec(source, &mut diags) else {
        return Err(diags);
    };
    let graph = load_source(registry, source, overrides)?;
    let Some(section) = spec.stream.as_ref() else {
        return Ok((graph, None));
    };
    if let Some(animation) = &spec.animation {
        diags.push(
            stream_diag(
                source,
                head_span(animation),
                "a graph cannot both stream and have an `animation` timeline",
                "this timeline",
            )
            .help("drive the source's frames from the stream, or remove the `stream` section"),
        );
        return Err(diags);
    }
    let Some(stream) = parse_stream(source, section, &mut diags) else {
        return Err(diags);
    };
    for name in &stream.sources {
        match graph.node_index(name) {
            None => diags.push(
                stream_diag(
                    source,
                    section.span,
                    format!("`sources` names `{name}`, which is not a node"),
                    "in this stream section",
                )
                .maybe_help(
                    suggest(name, graph.nodes.iter().map(|n| n.name.as_str()))
                        .map(|s| format!("did you mean `{s}`?")),
                ),
            ),
            Some(i) if !can_stream(&graph, i) => diags.push(
                stream_diag(
                    source,
                    section.span,
                    format!(
                        "`sources` names `{name}` ({}), which has no frame-sequence output",
                        graph.nodes[i].info.id
                    ),
                    "in this stream section",
                )
                .help("a source is an operator with `per_frame` outputs, e.g. `capture.sequence`"),
            ),
            Some(_) => {}
        }
    }
    for name in stream.encode.keys() {
        if !graph.outputs.iter().any(|o| &o.name == name) {
            diags.push(
                stream_diag(
                    source,
                    section.span,
                    format!("`encode` names `{name}`, which is not a graph output"),
                    "in this stream section",
                )
                .maybe_help(
                    suggest(name, graph.outputs.iter().map(|o| o.name.as_str()))
                        .map(|s| format!("did you mean `{s}`?")),
                ),
            );
        }
    }
    if diags.is_empty() {
        check_feedback(source, &graph, &stream, &mut diags);
    }
    if diags.is_empty()
        && let Err(message) = plan(&graph, &stream, &[])
    {
        diags.push(
            stream_diag(source, head_span(section), message, "this stream section")
                .help("a stream needs a source with `per_frame` outputs, such as `capture.sequence` or `capture.moving_shapes`"),
        );
    }
    if !diags.is_empty() {
        diags.sort();
        return Err(diags);
    }
    Ok((graph, Some(stream)))
}

/// [`load_streamed`] from a path.
pub fn load_streamed_file(
    registry: &Registry,
    path: &std::path::Path,
    overrides: &[Override],
) -> Result<(Graph, Option<StreamSpec>), Diagnostics> {
    let name = path.to_string_lossy().into_owned();
    let source = read_source(path, &name).map_err(|d| Diagnostics(vec![*d]))?;
    load_streamed(registry, &source, overrides)
}

fn parse_stream(
    source: &Arc<SourceFile>,
    section: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Option<StreamSpec> {
    let fields = struct_fields(source, section, "Stream", "`stream`", diags)?;
    let before = diags.0.len();
    let mut spec = StreamSpec::default();
    let mut policy_span = None;
    for (key, value) in fields {
        match key.value.as_str() {
            "capacity" => match &value.value {
                RonValue::Int(n) if *n >= 1 && (*n as u64) <= MAX_CAPACITY as u64 => {
                    spec.capacity = *n as usize;
                }
                other => diags.push(
                    stream_diag(
                        source,
                        value.span,
                        format!(
                            "`capacity` must be an integer in 1..={MAX_CAPACITY}, found {}",
                            describe(other)
                        ),
                        "packets per channel",
                    )
                    .help("e.g. `capacity: 4`"),
                ),
            },
            "policy" => {
                policy_span = Some(value.span);
                match &value.value {
                    RonValue::Str(s) | RonValue::Ident(s) if s == "block" => {
                        spec.policy = Policy::Block;
                    }
                    RonValue::Str(s) | RonValue::Ident(s) if s == "drop" => {
                        spec.policy = Policy::Drop;
                    }
                    other => diags.push(
                        stream_diag(
                            source,
                            value.span,
                            format!(
                                "`policy` must be \"block\" or \"drop\", found {}",
                                describe(other)
                            ),
                            "full-queue policy",
                        )
                        .help("\"block\" waits for room; \"drop\" drops the frame and counts it"),
                    ),
                }
            }
            "rate_fps" => match (&value.value, number(&value.value)) {
                (RonValue::Unit, _) => spec.rate_fps = None,
                (_, Some(f)) if f.is_finite() && f > 0.0 && f <= 1e6 => spec.rate_fps = Some(f),
                (other, _) => diags.push(stream_diag(
                    source,
                    value.span,
                    format!(
                        "`rate_fps` must be a number in (0, 1000000], found {}",
                        describe(other)
                    ),
                    "frames per second",
                )),
            },
            "sources" => match &value.value {
                RonValue::List(items) => {
                    for item in items {
                        match &item.value {
                            RonValue::Str(s) => spec.sources.push(s.clone()),
                            other => diags.push(stream_diag(
                                source,
                                item.span,
                                format!("`sources` holds node names, found {}", a_kind(other)),
                                "expected a quoted node name",
                            )),
                        }
                    }
                }
                other => diags.push(stream_diag(
                    source,
                    value.span,
                    format!(
                        "`sources` must be a list of node names, found {}",
                        a_kind(other)
                    ),
                    "expected e.g. `[\"video\"]`",
                )),
            },
            "encode" => spec.encode = parse_encode(source, value, Code::Stream, diags),
            "metrics" => match &value.value {
                RonValue::List(items) => {
                    spec.metrics.clear();
                    for item in items {
                        let format = match &item.value {
                            RonValue::Str(s) | RonValue::Ident(s) if s == "csv" => {
                                Some(MetricsFormat::Csv)
                            }
                            RonValue::Str(s) | RonValue::Ident(s) if s == "jsonl" => {
                                Some(MetricsFormat::Jsonl)
                            }
                            _ => None,
                        };
                        match format {
                            Some(f) if !spec.metrics.contains(&f) => spec.metrics.push(f),
                            Some(_) => {}
                            None => diags.push(
                                stream_diag(
                                    source,
                                    item.span,
                                    format!("unknown metrics format {}", describe(&item.value)),
                                    "not a format",
                                )
                                .help(format!("formats are {}", MetricsFormat::NAMES.join(", "))),
                            ),
                        }
                    }
                }
                other => diags.push(stream_diag(
                    source,
                    value.span,
                    format!(
                        "`metrics` must be a list of formats, found {}",
                        a_kind(other)
                    ),
                    "expected e.g. `[\"csv\", \"jsonl\"]`",
                )),
            },
            "feedback" => spec.feedback = parse_feedback(source, value, diags),
            other => diags.push(unknown_field(source, key, other, &STREAM_FIELDS, "stream")),
        }
    }
    if spec.policy == Policy::Drop && !spec.feedback.is_empty() {
        let span = policy_span.unwrap_or_else(|| head_span(section));
        diags.push(
            stream_diag(
                source,
                span,
                "`policy: \"drop\"` cannot be used with `feedback`: a dropped frame would leave the loop without its fed-back value",
                "drop policy in a feedback loop",
            )
            .help("use `policy: \"block\"` (the default)"),
        );
    }
    if spec.policy == Policy::Drop && spec.rate_fps.is_none() {
        let span = policy_span.unwrap_or_else(|| head_span(section));
        diags.push(
            stream_diag(
                source,
                span,
                "`policy: \"drop\"` needs `rate_fps`: frames are dropped when they are due and the pipeline is full",
                "drop policy without a frame rate",
            )
            .help("add e.g. `rate_fps: 30`, or use `policy: \"block\"`"),
        );
    }
    (diags.0.len() == before).then_some(spec)
}

/// `feedback: { "source.port": "node.port", … }`.
fn parse_feedback(
    source: &Arc<SourceFile>,
    value: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Vec<Feedback> {
    let RonValue::Map(entries) = &value.value else {
        diags.push(
            stream_diag(
                source,
                value.span,
                format!(
                    "`feedback` must be a map from source inputs to outputs, found {}",
                    a_kind(&value.value)
                ),
                "expected a map",
            )
            .help("e.g. `feedback: { \"camera.velocity\": \"servo.velocity\" }`"),
        );
        return Vec::new();
    };
    let port = |v: &Spanned<RonValue>, what: &str, diags: &mut Diagnostics| match &v.value {
        RonValue::Str(s) => match s.rsplit_once('.') {
            Some((node, port)) if !node.is_empty() && !port.is_empty() => {
                Some((node.to_string(), port.to_string()))
            }
            _ => {
                diags.push(
                    stream_diag(
                        source,
                        v.span,
                        format!("`feedback` {what} must be `node.port`, found \"{s}\""),
                        "not `node.port`",
                    )
                    .help("e.g. `\"servo.velocity\"`"),
                );
                None
            }
        },
        other => {
            diags.push(stream_diag(
                source,
                v.span,
                format!(
                    "`feedback` {what} must be a quoted `node.port`, found {}",
                    a_kind(other)
                ),
                "expected a string",
            ));
            None
        }
    };
    let mut edges: Vec<Feedback> = Vec::new();
    for (key, target) in entries {
        let to = port(key, "keys (source inputs)", diags);
        let from = port(target, "values (outputs)", diags);
        let (Some(to), Some(from)) = (to, from) else {
            continue;
        };
        let span = crate::ron_syntax::Span {
            start: key.span.start,
            end: target.span.end,
        };
        if edges.iter().any(|e| e.to == to) {
            diags.push(stream_diag(
                source,
                key.span,
                format!("`feedback` feeds `{}.{}` twice", to.0, to.1),
                "fed again here",
            ));
            continue;
        }
        edges.push(Feedback { to, from, span });
    }
    edges
}

/// Checks the feedback edges against the graph and its stream plan.
fn check_feedback(
    source: &Arc<SourceFile>,
    graph: &Graph,
    stream: &StreamSpec,
    diags: &mut Diagnostics,
) {
    let at = |edge: &Feedback, message: String, help: Option<String>| {
        stream_diag(source, edge.span, message, "this feedback edge").maybe_help(help)
    };
    let node_help = |name: &str| {
        suggest(name, graph.nodes.iter().map(|n| n.name.as_str()))
            .map(|s| format!("did you mean `{s}`?"))
    };
    let mut structural = Vec::new();
    for edge in &stream.feedback {
        let (to_node, to_port) = (&edge.to.0, &edge.to.1);
        let (from_node, from_port) = (&edge.from.0, &edge.from.1);
        let Some(t) = graph.node_index(to_node) else {
            diags.push(at(
                edge,
                format!("`feedback` feeds `{to_node}`, which is not a node"),
                node_help(to_node),
            ));
            continue;
        };
        let Some(f) = graph.node_index(from_node) else {
            diags.push(at(
                edge,
                format!("`feedback` reads `{from_node}`, which is not a node"),
                node_help(from_node),
            ));
            continue;
        };
        let target = &graph.nodes[t];
        let Some(tp) = target.info.inputs.iter().position(|p| &p.name == to_port) else {
            diags.push(at(
                edge,
                format!("`{to_node}` ({}) has no input `{to_port}`", target.info.id),
                suggest(to_port, target.info.inputs.iter().map(|p| p.name.as_str()))
                    .map(|s| format!("did you mean `{s}`?")),
            ));
            continue;
        };
        if !can_stream(graph, t) || !target.info.inputs[tp].feedback {
            diags.push(at(
                edge,
                format!(
                    "`{to_node}.{to_port}` ({}) is not a feedback input of a frame source",
                    target.info.id
                ),
                Some("feedback goes into a source's feedback port, e.g. `capture.moving_camera`'s `velocity`".into()),
            ));
            continue;
        }
        if target.inputs[tp].is_some() {
            diags.push(at(
                edge,
                format!("`{to_node}.{to_port}` is fed back and also wired in `inputs`"),
                Some("remove it from the node's `inputs`".into()),
            ));
            continue;
        }
        let producer = &graph.nodes[f];
        let Some(fp) = producer
            .info
            .outputs
            .iter()
            .position(|p| &p.name == from_port)
        else {
            diags.push(at(
                edge,
                format!(
                    "`{from_node}` ({}) has no output `{from_port}`",
                    producer.info.id
                ),
                suggest(
                    from_port,
                    producer.info.outputs.iter().map(|p| p.name.as_str()),
                )
                .map(|s| format!("did you mean `{s}`?")),
            ));
            continue;
        };
        let produced = &producer.output_types[fp];
        let element = produced.element().unwrap_or(produced);
        let expected = &target.info.inputs[tp].ty;
        if element != expected {
            diags.push(at(
                edge,
                format!(
                    "type mismatch: `{from_node}.{from_port}` gives {element} per frame, `{to_node}.{to_port}` takes {expected}"
                ),
                None,
            ));
            continue;
        }
        if f == t {
            diags.push(at(
                edge,
                format!("`{to_node}` cannot feed its own output back into itself"),
                None,
            ));
            continue;
        }
        let sources = stream_ancestors(graph, f);
        if sources != [t] {
            diags.push(at(
                edge,
                format!(
                    "`{from_node}` must work on `{to_node}`'s frames (and no other source's) to feed it back"
                ),
                Some("feedback closes a loop: the fed-back value must be computed from the source's own frames".into()),
            ));
            continue;
        }
        structural.push((edge, f, fp));
    }
    if !diags.is_empty() {
        return;
    }
    // What the plan makes of the producers: they must run per frame.
    // (A plan that fails is reported by the caller.)
    if let Ok(plan) = plan(graph, stream, &[]) {
        for (edge, f, fp) in structural {
            if !(plan.is_stage(f) && plan.is_streamed(PortRef { node: f, port: fp })) {
                diags.push(at(
                    edge,
                    format!(
                        "`{}.{}` is not produced frame by frame ({} node), so it cannot be fed back",
                        edge.from.0,
                        edge.from.1,
                        plan.class[f].name()
                    ),
                    Some("feed back an output of a node mapped over the frames or of a sequence operator".into()),
                ));
            }
        }
    }
}

/// The frame sources (nodes that can stream) that node `i` depends on, itself included,
/// in index order.
fn stream_ancestors(graph: &Graph, i: usize) -> Vec<usize> {
    let mut seen = vec![false; graph.nodes.len()];
    let mut stack = vec![i];
    let mut found = Vec::new();
    while let Some(j) = stack.pop() {
        if std::mem::replace(&mut seen[j], true) {
            continue;
        }
        if can_stream(graph, j) {
            found.push(j);
            continue;
        }
        stack.extend(
            graph.nodes[j]
                .inputs
                .iter()
                .flatten()
                .flat_map(InputEdge::sources)
                .map(|p| p.node),
        );
    }
    found.sort_unstable();
    found
}

/// Whether node `i`'s operator can be a stream source: `per_frame` outputs, no `per_frame`
/// inputs.
fn can_stream(graph: &Graph, i: usize) -> bool {
    let info = &graph.nodes[i].info;
    info.outputs.iter().any(|p| p.per_frame) && !info.inputs.iter().any(|p| p.per_frame)
}

/// How a node runs in a stream (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NodeClass {
    /// Not needed by the requested outputs.
    Idle,
    /// Runs once before the stream.
    Static,
    /// Produces frames.
    Source,
    /// Mapped over a stream: runs per packet.
    PerFrame,
    /// Stateful: pushed per packet, finished at the end.
    Sequence,
    /// Runs after the stream on gathered lists.
    Final,
}

impl NodeClass {
    /// Lower-case name for reports.
    pub fn name(self) -> &'static str {
        match self {
            NodeClass::Idle => "idle",
            NodeClass::Static => "static",
            NodeClass::Source => "source",
            NodeClass::PerFrame => "per-frame",
            NodeClass::Sequence => "sequence",
            NodeClass::Final => "final",
        }
    }
}

/// How each node of a graph runs in a stream.
#[derive(Debug, Clone)]
struct StreamPlan {
    class: Vec<NodeClass>,
    /// Per node, per output port: streamed one element per packet.
    streamed: Vec<Vec<bool>>,
    /// Streamed ports gathered into whole lists for final nodes or indexed outputs.
    gathered: BTreeSet<PortRef>,
    /// Requested outputs: (name, from, index, streamed per frame).
    outputs: Vec<(String, PortRef, Option<i64>, bool)>,
}

impl StreamPlan {
    fn is_streamed(&self, p: PortRef) -> bool {
        self.streamed[p.node].get(p.port).copied().unwrap_or(false)
    }

    fn is_stage(&self, i: usize) -> bool {
        matches!(
            self.class[i],
            NodeClass::Source | NodeClass::PerFrame | NodeClass::Sequence
        )
    }
}

fn plan(graph: &Graph, spec: &StreamSpec, selected: &[String]) -> Result<StreamPlan, String> {
    let n = graph.nodes.len();
    let mut requested: Vec<&GraphOutput> = Vec::new();
    let mut roots = Vec::new();
    if selected.is_empty() {
        requested.extend(&graph.outputs);
        roots.extend((0..n).filter(|&i| graph.nodes[i].info.side_effects));
    } else {
        for name in selected {
            match graph.outputs.iter().find(|o| &o.name == name) {
                Some(o) => requested.push(o),
                None => {
                    let hint = suggest(name, graph.outputs.iter().map(|o| o.name.as_str()))
                        .map(|s| format!(" (did you mean `{s}`?)"))
                        .unwrap_or_default();
                    return Err(format!("the graph has no output `{name}`{hint}"));
                }
            }
        }
    }
    roots.extend(requested.iter().map(|o| o.from.node));
    // A feedback producer runs even when no requested output reads it: it drives a source.
    roots.extend(
        spec.feedback
            .iter()
            .filter_map(|e| graph.node_index(&e.from.0)),
    );
    let mut needed = vec![false; n];
    let mut stack = roots;
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
                .map(|p| p.node),
        );
    }
    let is_source = |i: usize| {
        can_stream(graph, i)
            && (spec.sources.is_empty() || spec.sources.iter().any(|s| s == &graph.nodes[i].name))
    };
    let mut class = vec![NodeClass::Idle; n];
    let mut streamed: Vec<Vec<bool>> = graph
        .nodes
        .iter()
        .map(|node| vec![false; node.info.outputs.len()])
        .collect();
    let mut gathered = BTreeSet::new();
    for i in (0..n).filter(|&i| needed[i]) {
        let node = &graph.nodes[i];
        let reads_stream = |p: &PortRef| streamed[p.node].get(p.port).copied().unwrap_or(false);
        let mut any_streamed = false;
        let mut any_final = false;
        let mut all_mapped = true;
        let mut all_sequence = true;
        for (edge, port) in node.inputs.iter().zip(&node.info.inputs) {
            let Some(edge) = edge else { continue };
            for tap in edge.taps() {
                if class[tap.from.node] == NodeClass::Final
                    || (class[tap.from.node] == NodeClass::Sequence && !reads_stream(&tap.from))
                {
                    any_final = true;
                }
            }
            let streamed_taps: Vec<_> = edge
                .taps()
                .iter()
                .filter(|t| reads_stream(&t.from))
                .collect();
            if streamed_taps.is_empty() {
                if port.per_frame {
                    all_sequence = false; // a sequence port fed a whole static list
                }
                continue;
            }
            any_streamed = true;
            let whole = matches!(edge.source, EdgeSource::Tap(t) if t.index.is_none());
            if !(whole && edge.mapped) {
                all_mapped = false;
            }
            if !(whole && !edge.mapped && port.per_frame) {
                all_sequence = false;
            }
        }
        let has_per_frame_inputs = node.info.inputs.iter().any(|p| p.per_frame);
        class[i] = if any_final {
            NodeClass::Final
        } else if !any_streamed {
            if is_source(i) {
                NodeClass::Source
            } else if node.info.side_effects {
                NodeClass::Final
            } else {
                NodeClass::Static
            }
        } else if all_mapped && !has_per_frame_inputs {
            NodeClass::PerFrame
        } else if all_sequence && has_per_frame_inputs {
            NodeClass::Sequence
        } else {
            NodeClass::Final
        };
        match class[i] {
            NodeClass::Source | NodeClass::Sequence => {
                for (slot, spec) in streamed[i].iter_mut().zip(&node.info.outputs) {
                    *slot = spec.per_frame;
                }
            }
            NodeClass::PerFrame => streamed[i].iter_mut().for_each(|s| *s = true),
            _ => {}
        }
        if class[i] == NodeClass::Final {
            for tap in node.inputs.iter().flatten().flat_map(|e| e.taps()) {
                if streamed[tap.from.node][tap.from.port] {
                    gathered.insert(tap.from);
                }
            }
        }
    }
    if !class.contains(&NodeClass::Source) {
        return Err(if spec.sources.is_empty() {
            "nothing the requested outputs need can stream: no node has a frame-sequence output"
                .to_string()
        } else {
            "none of the `sources` is needed by the requested outputs".to_string()
        });
    }
    let mut outputs = Vec::new();
    for o in requested {
        let s = streamed[o.from.node][o.from.port];
        if s && o.index.is_some() {
            gathered.insert(o.from);
        }
        outputs.push((o.name.clone(), o.from, o.index, s && o.index.is_none()));
    }
    Ok(StreamPlan {
        class,
        streamed,
        gathered,
        outputs,
    })
}

/// One packet's worth of a stage's outputs: streamed ports hold this frame's element.
#[derive(Debug)]
struct FrameMsg {
    packet: Packet,
    values: Vec<Option<Value>>,
}

/// One frame as the caller of [`run_stream`] sees it.
#[derive(Debug, Clone)]
pub struct StreamFrame {
    /// The packet.
    pub packet: Packet,
    /// Frames the sink has received so far, this one included.
    pub position: usize,
    /// Frames the longest source has (dropped ones included).
    pub total: usize,
    /// The source's nominal rate, frames per second (from its first two timestamps; 30 when
    /// it has one frame).
    pub fps: f64,
    /// This frame's element of every streamed graph output, in declaration order.
    pub outputs: Vec<(String, Value)>,
}

/// What a stage did.
#[derive(Debug, Clone)]
pub struct StageReport {
    /// Qualified node name.
    pub name: String,
    /// Operator id.
    pub op: String,
    /// How it ran.
    pub class: NodeClass,
    /// Packets it handled (per-frame and sequence nodes) or produced (sources).
    pub frames: usize,
    /// Time in its operator.
    pub busy: Duration,
}

/// The result of a stream.
#[derive(Debug, Clone, Default)]
pub struct StreamReport {
    /// Frames the sources produced and sent.
    pub frames: usize,
    /// Frames dropped by `policy: "drop"`.
    pub dropped: usize,
    /// Packets discarded while aligning inputs by timestamp.
    pub unaligned: usize,
    /// Packets that reached the end of the pipeline.
    pub completed: usize,
    /// Largest delay of a paced source behind its schedule (`rate_fps`).
    pub max_lateness: Duration,
    /// Every needed node, in graph order.
    pub stages: Vec<StageReport>,
    /// Graph outputs that are not streamed (static or final), in declaration order.
    pub outputs: Vec<(String, Value)>,
    /// The run of the static nodes.
    pub statics: RunReport,
    /// Wall time of the stream (static nodes excluded).
    pub elapsed: Duration,
}

impl StreamReport {
    /// Frames per second through the pipeline.
    pub fn fps(&self) -> f64 {
        let s = self.elapsed.as_secs_f64();
        if s > 0.0 {
            self.completed as f64 / s
        } else {
            0.0
        }
    }

    /// One line: `300 frames in 4.21 s (71.3 frames/s), 0 dropped, 0 unaligned`.
    pub fn summary_line(&self) -> String {
        format!(
            "{} frames in {:.2} s ({:.1} frames/s), {} dropped, {} unaligned",
            self.completed,
            self.elapsed.as_secs_f64(),
            self.fps(),
            self.dropped,
            self.unaligned
        )
    }
}

/// Why a stream failed.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// The run could not start (threads, cache, unknown output).
    #[error(transparent)]
    Run(#[from] RunError),
    /// The graph cannot stream as asked.
    #[error("{0}")]
    Plan(String),
    /// A static node failed.
    #[error("{0}")]
    Static(String),
    /// A node failed at a frame (or at the end of the stream).
    #[error("{}node `{node}` ({op}) failed{}: {message}", .location.as_ref().map(|l| format!("{l}: ")).unwrap_or_default(), .frame.map(|f| format!(" at frame {f}")).unwrap_or_default())]
    Node {
        /// Qualified node name.
        node: String,
        /// Operator id.
        op: String,
        /// `file:line:col` of its declaration.
        location: Option<String>,
        /// The frame (source index), if the failure belongs to one.
        frame: Option<usize>,
        /// The error.
        message: String,
    },
    /// The per-frame callback failed (e.g. writing a file).
    #[error("{0}")]
    Sink(String),
}

/// Shared state of the stage threads.
struct Shared {
    abort: AtomicBool,
    failure: Mutex<Option<StreamError>>,
    dropped: AtomicUsize,
    unaligned: AtomicUsize,
    frames: AtomicUsize,
    lateness_us: AtomicUsize,
}

impl Shared {
    fn fail(&self, error: StreamError) {
        if let Ok(mut f) = self.failure.lock()
            && f.is_none()
        {
            *f = Some(error);
        }
        self.abort.store(true, Ordering::Release);
    }

    fn aborted(&self) -> bool {
        self.abort.load(Ordering::Acquire)
    }
}

fn node_error(graph: &Graph, i: usize, frame: Option<usize>, message: String) -> StreamError {
    let node = &graph.nodes[i];
    StreamError::Node {
        node: node.name.clone(),
        op: node.info.id.clone(),
        location: node.location.as_ref().map(|l| l.display()),
        frame,
        message,
    }
}

/// Runs a streaming graph: static nodes first, then the pipelined stages frame by frame, then
/// final nodes. `on_frame` sees every packet that reaches the end of the pipeline, in order; an
/// error from it stops the stream.
pub fn run_stream(
    graph: &Graph,
    spec: &StreamSpec,
    options: &RunOptions,
    mut on_frame: impl FnMut(&StreamFrame) -> Result<(), String>,
) -> Result<StreamReport, StreamError> {
    let plan = plan(graph, spec, &options.outputs).map_err(StreamError::Plan)?;
    let (pool, threads) = crate::exec::thread_pool(options.threads)?;
    let n = graph.nodes.len();

    // 1. Static values the stream reads, and static graph outputs.
    let mut wanted: BTreeSet<(PortRef, Option<i64>)> = BTreeSet::new();
    for i in (0..n).filter(|&i| !matches!(plan.class[i], NodeClass::Static | NodeClass::Idle)) {
        for tap in graph.nodes[i]
            .inputs
            .iter()
            .flatten()
            .flat_map(|e| e.taps())
        {
            if plan.class[tap.from.node] == NodeClass::Static {
                wanted.insert((tap.from, None));
            }
        }
    }
    for (_, from, index, _) in &plan.outputs {
        if plan.class[from.node] == NodeClass::Static {
            wanted.insert((*from, *index));
        }
    }
    let mut static_graph = graph.clone();
    static_graph.outputs = wanted
        .iter()
        .map(|(from, index)| GraphOutput {
            name: format!("#{}.{}[{index:?}]", from.node, from.port),
            from: *from,
            index: *index,
            ty: graph.nodes[from.node].output_types[from.port].clone(),
        })
        .collect();
    let static_options = RunOptions {
        threads,
        outputs: static_graph
            .outputs
            .iter()
            .map(|o| o.name.clone())
            .collect(),
        progress: None,
        ..options.clone()
    };
    let statics_report = if static_graph.outputs.is_empty() {
        RunReport::default()
    } else {
        crate::exec::run(&static_graph, &static_options)?
    };
    if !statics_report.failures.is_empty() {
        let lines: Vec<String> = statics_report
            .failures
            .iter()
            .map(ToString::to_string)
            .collect();
        return Err(StreamError::Static(lines.join("\n")));
    }
    // Whole values by port (index None), for stage inputs and final nodes.
    let mut values: HashMap<PortRef, Value> = HashMap::new();
    let mut static_outputs: HashMap<(PortRef, Option<i64>), Value> = HashMap::new();
    for ((from, index), out) in wanted.iter().zip(&static_graph.outputs) {
        if let Some(v) = statics_report.output(&out.name) {
            if index.is_none() {
                values.insert(*from, v.clone());
            }
            static_outputs.insert((*from, *index), v.clone());
        }
    }

    // 2. Sources, with their static outputs.
    let ctx_for = |i: usize, element: Option<usize>| RunContext {
        node: graph.nodes[i].name.clone(),
        threads,
        element,
    };
    let mut sources: HashMap<usize, Box<dyn FrameSource>> = HashMap::new();
    let mut states: HashMap<usize, Box<dyn SequenceState>> = HashMap::new();
    for i in 0..n {
        let node = &graph.nodes[i];
        match plan.class[i] {
            NodeClass::Source => {
                let inputs = whole_inputs(graph, None, i, &values)
                    .map_err(|m| node_error(graph, i, None, m))?;
                let ctx = ctx_for(i, None);
                let made = pool.install(|| {
                    catch_unwind(AssertUnwindSafe(|| {
                        node.op
                            .frame_source(&ctx, &Inputs::new(&node.info.inputs, &inputs))
                    }))
                });
                let mut source = match made {
                    Ok(Some(Ok(s))) => s,
                    Ok(Some(Err(e))) => return Err(node_error(graph, i, None, e.to_string())),
                    Ok(None) => {
                        return Err(node_error(
                            graph,
                            i,
                            None,
                            "the operator declares frame-sequence outputs but cannot stream them"
                                .into(),
                        ));
                    }
                    Err(p) => return Err(node_error(graph, i, None, panic_message(p.as_ref()))),
                };
                let mut statics = pool
                    .install(|| source.statics(&ctx))
                    .map_err(|e| node_error(graph, i, None, e.to_string()))?;
                for (port, spec) in node.info.outputs.iter().enumerate() {
                    if !spec.per_frame
                        && let Some(v) = statics.take(&spec.name)
                    {
                        values.insert(PortRef { node: i, port }, v);
                    }
                }
                sources.insert(i, source);
            }
            NodeClass::Sequence => {
                // The per-frame ports are the streamed ones: unset here.
                let inputs = whole_inputs(graph, Some(&plan), i, &values)
                    .map_err(|m| node_error(graph, i, None, m))?;
                let ctx = ctx_for(i, None);
                let made = pool.install(|| {
                    catch_unwind(AssertUnwindSafe(|| {
                        node.op
                            .sequence(&ctx, &Inputs::new(&node.info.inputs, &inputs))
                    }))
                });
                match made {
                    Ok(Some(Ok(s))) => {
                        states.insert(i, s);
                    }
                    Ok(Some(Err(e))) => return Err(node_error(graph, i, None, e.to_string())),
                    Ok(None) => {
                        return Err(node_error(
                            graph,
                            i,
                            None,
                            "the operator declares frame-sequence inputs but keeps no sequence state"
                                .into(),
                        ));
                    }
                    Err(p) => return Err(node_error(graph, i, None, panic_message(p.as_ref()))),
                }
            }
            _ => {}
        }
    }

    // 3. Channels: one per (producer stage, consumer) pair; the sink is consumer `n`.
    let sink = n;
    let mut consumers: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); n];
    for i in (0..n).filter(|&i| plan.is_stage(i)) {
        for tap in graph.nodes[i]
            .inputs
            .iter()
            .flatten()
            .flat_map(|e| e.taps())
        {
            if plan.is_stage(tap.from.node) && plan.is_streamed(tap.from) {
                consumers[tap.from.node].insert(i);
            }
        }
    }
    for (_, from, _, per_frame) in &plan.outputs {
        if *per_frame {
            consumers[from.node].insert(sink);
        }
    }
    for p in &plan.gathered {
        consumers[p.node].insert(sink);
    }
    // Feedback: (source, its input port, the producing port).
    let mut feedback: Vec<(usize, String, PortRef)> = Vec::new();
    for edge in &spec.feedback {
        let found = graph
            .node_index(&edge.to.0)
            .zip(graph.node_index(&edge.from.0));
        let Some((t, f)) = found else {
            return Err(StreamError::Plan(format!(
                "feedback `{}.{}`: `{}.{}` is not in the graph",
                edge.to.0, edge.to.1, edge.from.0, edge.from.1
            )));
        };
        let port = graph.nodes[f]
            .info
            .outputs
            .iter()
            .position(|p| p.name == edge.from.1);
        match port {
            Some(port) if plan.class[t] == NodeClass::Source && plan.is_stage(f) => {
                feedback.push((t, edge.to.1.clone(), PortRef { node: f, port }));
            }
            _ => {
                return Err(StreamError::Plan(format!(
                    "feedback `{}.{}` from `{}.{}`: not a source fed by a stage",
                    edge.to.0, edge.to.1, edge.from.0, edge.from.1
                )));
            }
        }
    }
    for (t, _, from) in &feedback {
        consumers[from.node].insert(*t);
    }
    for i in (0..n).filter(|&i| plan.is_stage(i)) {
        // (A stage read only by a source, through feedback, is terminal too.)
        if consumers[i]
            .iter()
            .all(|&c| c != sink && plan.class[c] == NodeClass::Source)
        {
            consumers[i].insert(sink); // completion of terminal stages
        }
    }
    let mut senders: Vec<Vec<Sender<Arc<FrameMsg>>>> = vec![Vec::new(); n];
    let mut receivers: Vec<Vec<(usize, Receiver<Arc<FrameMsg>>)>> = vec![Vec::new(); n + 1];
    for (producer, list) in consumers.iter().enumerate() {
        for &c in list {
            let (tx, rx) = bounded(spec.capacity);
            senders[producer].push(tx);
            receivers[c].push((producer, rx));
        }
    }

    let shared = Shared {
        abort: AtomicBool::new(false),
        failure: Mutex::new(None),
        dropped: AtomicUsize::new(0),
        unaligned: AtomicUsize::new(0),
        frames: AtomicUsize::new(0),
        lateness_us: AtomicUsize::new(0),
    };
    let busy: Vec<Mutex<(usize, Duration)>> =
        (0..n).map(|_| Mutex::new((0, Duration::ZERO))).collect();
    let finals: Mutex<HashMap<PortRef, Value>> = Mutex::new(HashMap::new());
    let mut gathered_items: BTreeMap<PortRef, Vec<Value>> =
        plan.gathered.iter().map(|p| (*p, Vec::new())).collect();
    let mut completed = 0usize;
    let started = Instant::now();
    let total_frames: usize = sources.values().map(|s| s.frames()).max().unwrap_or(0);
    let nominal_fps = sources
        .values()
        .find(|s| s.frames() == total_frames)
        .filter(|s| s.frames() >= 2)
        .map(|s| s.timestamp_us(1) - s.timestamp_us(0))
        .filter(|&d| d > 0)
        .map_or(30.0, |d| 1e6 / d as f64);

    std::thread::scope(|scope| {
        let mut receivers = receivers;
        let sink_receivers = receivers.pop().unwrap_or_default();
        for (i, (rx, tx)) in receivers.into_iter().zip(senders).enumerate() {
            if !plan.is_stage(i) {
                continue;
            }
            let (shared, busy, finals, values, pool, plan) =
                (&shared, &busy, &finals, &values, &pool, &plan);
            let source = sources.remove(&i);
            let state = states.remove(&i);
            let ctx_for = &ctx_for;
            let fed: Vec<(String, PortRef)> = feedback
                .iter()
                .filter(|(t, _, _)| *t == i)
                .map(|(_, port, from)| (port.clone(), *from))
                .collect();
            let name = format!("ocellus-stage-{i}");
            let spawned = std::thread::Builder::new()
                .name(name)
                .spawn_scoped(scope, move || {
                    let stage = Stage {
                        graph,
                        plan,
                        index: i,
                        values,
                        pool,
                        shared,
                        busy: &busy[i],
                        outputs: tx,
                    };
                    match source {
                        Some(source) => {
                            stage.run_source(source, spec, ctx_for(i, None), rx, &fed);
                        }
                        None => stage.run_inner(rx, state, ctx_for, finals),
                    }
                });
            if let Err(e) = spawned {
                shared.fail(StreamError::Plan(format!(
                    "cannot start a stage thread: {e}"
                )));
            }
        }
        // The sink, here.
        let progress = options.progress.as_ref();
        let mut heads: Vec<Option<Arc<FrameMsg>>> = vec![None; sink_receivers.len()];
        while let Some(msgs) = next_aligned(&sink_receivers, &mut heads, &shared) {
            completed += 1;
            let mut outputs = Vec::new();
            let read = |p: &PortRef| -> Option<Value> {
                let k = sink_receivers
                    .iter()
                    .position(|(prod, _)| *prod == p.node)?;
                msgs[k].values.get(p.port).cloned().flatten()
            };
            for (name, from, _, per_frame) in &plan.outputs {
                if *per_frame && let Some(v) = read(from) {
                    outputs.push((name.clone(), v));
                }
            }
            for (p, items) in &mut gathered_items {
                if let Some(v) = read(p) {
                    items.push(v);
                }
            }
            let frame = StreamFrame {
                packet: msgs[0].packet,
                position: completed,
                total: total_frames,
                fps: nominal_fps,
                outputs,
            };
            if let Err(e) = on_frame(&frame) {
                shared.fail(StreamError::Sink(e));
                break;
            }
            if let Some(progress) = progress {
                progress(completed, total_frames);
            }
        }
        drop(sink_receivers);
    });
    let elapsed = started.elapsed();
    if let Some(e) = shared.failure.lock().ok().and_then(|mut f| f.take()) {
        return Err(e);
    }

    // 4. Final nodes, on the gathered lists and the sequences' final outputs.
    for (p, items) in gathered_items {
        let element = graph.nodes[p.node].output_types[p.port]
            .element()
            .cloned()
            .unwrap_or(crate::types::PortType::Integer);
        values.insert(p, Value::list(element, items));
    }
    if let Ok(mut f) = finals.lock() {
        values.extend(f.drain());
    }
    for i in (0..n).filter(|&i| plan.class[i] == NodeClass::Final) {
        let node = &graph.nodes[i];
        let inputs =
            whole_inputs(graph, None, i, &values).map_err(|m| node_error(graph, i, None, m))?;
        let ctx = ctx_for(i, None);
        let t0 = Instant::now();
        let result = guarded(&pool, || run_node(node, &ctx, &inputs))
            .map_err(|e| node_error(graph, i, None, e.to_string()))?;
        if let Ok(mut b) = busy[i].lock() {
            *b = (1, t0.elapsed());
        }
        for (port, v) in result.into_iter().enumerate() {
            values.insert(PortRef { node: i, port }, v);
        }
    }
    let mut outputs = Vec::new();
    for (name, from, index, per_frame) in &plan.outputs {
        if *per_frame {
            continue;
        }
        let value = match static_outputs.get(&(*from, *index)) {
            Some(v) => v.clone(),
            None => {
                let Some(v) = values.get(from) else { continue };
                select(graph, from.node, from.port, *index, v)
                    .map_err(|m| StreamError::Static(format!("output `{name}`: {m}")))?
            }
        };
        outputs.push((name.clone(), value));
    }
    let stages = (0..n)
        .filter(|&i| plan.class[i] != NodeClass::Idle)
        .map(|i| {
            let (frames, busy) = busy[i].lock().map(|b| *b).unwrap_or_default();
            StageReport {
                name: graph.nodes[i].name.clone(),
                op: graph.nodes[i].info.id.clone(),
                class: plan.class[i],
                frames,
                busy,
            }
        })
        .collect();
    Ok(StreamReport {
        frames: shared.frames.load(Ordering::Relaxed),
        dropped: shared.dropped.load(Ordering::Relaxed),
        unaligned: shared.unaligned.load(Ordering::Relaxed),
        completed,
        max_lateness: Duration::from_micros(shared.lateness_us.load(Ordering::Relaxed) as u64),
        stages,
        outputs,
        statics: statics_report,
        elapsed,
    })
}

/// The whole value an edge reads from `values` (static results, gathered lists, final
/// outputs), with `[i]` selections and list literals applied.
fn whole_value(
    graph: &Graph,
    edge: &InputEdge,
    values: &HashMap<PortRef, Value>,
) -> Result<Value, String> {
    let read = |tap: &crate::graph::Tap| -> Result<Value, String> {
        let v = values.get(&tap.from).ok_or_else(|| {
            let node = &graph.nodes[tap.from.node];
            let port = node
                .info
                .outputs
                .get(tap.from.port)
                .map_or("?", |p| p.name.as_str());
            format!("`{}.{port}` has no value", node.name)
        })?;
        select(graph, tap.from.node, tap.from.port, tap.index, v)
    };
    match &edge.source {
        EdgeSource::Tap(tap) => read(tap),
        EdgeSource::List { items, element } => Ok(Value::list(
            element.clone(),
            items.iter().map(read).collect::<Result<_, _>>()?,
        )),
    }
}

/// The whole value of every connected input of node `i`, from `values`; with a plan, the
/// inputs that read a stream are left unset (a stage receives those per packet).
fn whole_inputs(
    graph: &Graph,
    streams: Option<&StreamPlan>,
    i: usize,
    values: &HashMap<PortRef, Value>,
) -> Result<Vec<Option<Value>>, String> {
    let node = &graph.nodes[i];
    let mut out = Vec::with_capacity(node.inputs.len());
    for edge in &node.inputs {
        out.push(match edge {
            Some(edge) if !streams.is_some_and(|p| edge.sources().any(|s| p.is_streamed(s))) => {
                Some(whole_value(graph, edge, values)?)
            }
            _ => None,
        });
    }
    Ok(out)
}

/// Receives one packet from every input and aligns them by timestamp (older ones are
/// discarded and counted). `None` at the end of any input or on abort.
fn next_aligned(
    receivers: &[(usize, Receiver<Arc<FrameMsg>>)],
    heads: &mut [Option<Arc<FrameMsg>>],
    shared: &Shared,
) -> Option<Vec<Arc<FrameMsg>>> {
    loop {
        if shared.aborted() {
            return None;
        }
        for (head, (_, rx)) in heads.iter_mut().zip(receivers) {
            if head.is_none() {
                *head = Some(rx.recv().ok()?);
            }
        }
        let newest = heads
            .iter()
            .flatten()
            .map(|m| m.packet.timestamp_us)
            .max()?;
        let mut discarded = false;
        for head in heads.iter_mut() {
            if head
                .as_ref()
                .is_some_and(|m| m.packet.timestamp_us < newest)
            {
                *head = None;
                discarded = true;
                shared.unaligned.fetch_add(1, Ordering::Relaxed);
            }
        }
        if !discarded {
            return heads.iter_mut().map(Option::take).collect();
        }
    }
}

/// Runs `f` on the pool; a panic becomes the operator's error.
fn guarded<T: Send>(
    pool: &rayon::ThreadPool,
    f: impl FnOnce() -> Result<T, OpError> + Send,
) -> Result<T, OpError> {
    pool.install(|| catch_unwind(AssertUnwindSafe(f)))
        .unwrap_or_else(|p| {
            Err(OpError::failed(format!(
                "operator panicked: {}",
                panic_message(p.as_ref())
            )))
        })
}

/// One pipeline stage.
struct Stage<'a> {
    graph: &'a Graph,
    plan: &'a StreamPlan,
    index: usize,
    values: &'a HashMap<PortRef, Value>,
    pool: &'a rayon::ThreadPool,
    shared: &'a Shared,
    busy: &'a Mutex<(usize, Duration)>,
    outputs: Vec<Sender<Arc<FrameMsg>>>,
}

impl Stage<'_> {
    /// One packet handled in `took`.
    fn account(&self, took: Duration) {
        if let Ok(mut b) = self.busy.lock() {
            b.0 += 1;
            b.1 += took;
        }
    }

    /// Operator time outside a packet (feedback, the end of the stream).
    fn account_time(&self, took: Duration) {
        if let Ok(mut b) = self.busy.lock() {
            b.1 += took;
        }
    }

    fn fail(&self, frame: Option<usize>, message: String) {
        self.shared
            .fail(node_error(self.graph, self.index, frame, message));
    }

    /// Sends to every consumer; false when one has gone (the stream is ending).
    fn send(&self, msg: FrameMsg) -> bool {
        let msg = Arc::new(msg);
        self.outputs
            .iter()
            .all(|tx| tx.send(Arc::clone(&msg)).is_ok())
    }

    /// Produces the source's frames. `feedback` lists the receivers of the stages that feed
    /// values back, and `fed` which of their ports go to which input.
    fn run_source(
        mut self,
        source: Box<dyn FrameSource>,
        spec: &StreamSpec,
        ctx: RunContext,
        feedback: Vec<(usize, Receiver<Arc<FrameMsg>>)>,
        fed: &[(String, PortRef)],
    ) {
        self.produce(source, spec, ctx, &feedback, fed);
        if feedback.is_empty() {
            return;
        }
        // The feedback producers send their last frame's values too: close this source's
        // outputs so the pipeline can end, and take what they send until they have finished
        // (a closed receiver would make them stop before finishing their own state).
        self.outputs.clear();
        for (_, rx) in &feedback {
            while rx.recv().is_ok() {}
        }
    }

    fn produce(
        &self,
        mut source: Box<dyn FrameSource>,
        spec: &StreamSpec,
        ctx: RunContext,
        feedback: &[(usize, Receiver<Arc<FrameMsg>>)],
        fed: &[(String, PortRef)],
    ) {
        let node = &self.graph.nodes[self.index];
        let start = Instant::now();
        let mut previous: Option<i64> = None;
        let mut last_sent: Option<usize> = None;
        for k in 0..source.frames() {
            if self.shared.aborted() {
                return;
            }
            // Close the loop: the values computed from the last frame sent, before this one.
            if let Some(last) = last_sent {
                for (producer, rx) in feedback {
                    let Ok(msg) = rx.recv() else {
                        return; // the producer stopped: the stream is failing
                    };
                    if msg.packet.index != last {
                        self.fail(
                            Some(k),
                            format!(
                                "feedback from `{}` belongs to frame {}, expected frame {last}",
                                self.graph.nodes[*producer].name, msg.packet.index
                            ),
                        );
                        return;
                    }
                    for (port, from) in fed.iter().filter(|(_, f)| f.node == *producer) {
                        let Some(value) = msg.values.get(from.port).and_then(Option::as_ref) else {
                            self.fail(
                                Some(k),
                                format!(
                                    "`{}` sent no `{}` to feed back",
                                    self.graph.nodes[from.node].name,
                                    self.graph.nodes[from.node].info.outputs[from.port].name
                                ),
                            );
                            return;
                        };
                        let frame_ctx = RunContext {
                            element: Some(k),
                            ..ctx.clone()
                        };
                        let t0 = Instant::now();
                        let result = guarded(self.pool, || source.feed(&frame_ctx, k, port, value));
                        self.account_time(t0.elapsed());
                        if let Err(e) = result {
                            self.fail(Some(k), format!("feedback on `{port}`: {e}"));
                            return;
                        }
                    }
                }
            }
            let timestamp_us = source.timestamp_us(k);
            if previous.is_some_and(|p| timestamp_us <= p) {
                self.fail(Some(k), format!("timestamps must increase: frame {k} is at {timestamp_us} µs, not after {} µs", previous.unwrap_or_default()));
                return;
            }
            previous = Some(timestamp_us);
            if let Some(rate) = spec.rate_fps {
                let due = start + Duration::from_secs_f64(k as f64 / rate);
                let now = Instant::now();
                if due > now {
                    std::thread::sleep(due - now);
                } else {
                    let late = (now - due).as_micros() as usize;
                    self.shared.lateness_us.fetch_max(late, Ordering::Relaxed);
                }
            }
            if spec.policy == Policy::Drop && self.outputs.iter().any(|tx| tx.is_full()) {
                self.shared.dropped.fetch_add(1, Ordering::Relaxed);
                continue;
            }
            let t0 = Instant::now();
            let frame_ctx = RunContext {
                element: Some(k),
                ..ctx.clone()
            };
            let produced = guarded(self.pool, || source.frame(&frame_ctx, k));
            self.account(t0.elapsed());
            let mut produced = match produced {
                Ok(o) => o,
                Err(e) => {
                    self.fail(Some(k), e.to_string());
                    return;
                }
            };
            let mut values = Vec::with_capacity(node.info.outputs.len());
            for (spec, streamed) in node
                .info
                .outputs
                .iter()
                .zip(&self.plan.streamed[self.index])
            {
                if !streamed {
                    values.push(None);
                    continue;
                }
                match produced.take(&spec.name) {
                    Some(v) => values.push(Some(v)),
                    None => {
                        self.fail(
                            Some(k),
                            format!("the source produced no `{}` for frame {k}", spec.name),
                        );
                        return;
                    }
                }
            }
            self.shared.frames.fetch_add(1, Ordering::Relaxed);
            if !self.send(FrameMsg {
                packet: Packet {
                    index: k,
                    timestamp_us,
                },
                values,
            }) {
                return;
            }
            last_sent = Some(k);
        }
    }

    fn run_inner(
        self,
        receivers: Vec<(usize, Receiver<Arc<FrameMsg>>)>,
        mut state: Option<Box<dyn SequenceState>>,
        ctx_for: &dyn Fn(usize, Option<usize>) -> RunContext,
        finals: &Mutex<HashMap<PortRef, Value>>,
    ) {
        let node = &self.graph.nodes[self.index];
        let mut heads: Vec<Option<Arc<FrameMsg>>> = vec![None; receivers.len()];
        // Whole values of the edges that do not read a stream, once.
        let statics = match whole_inputs(self.graph, Some(self.plan), self.index, self.values) {
            Ok(s) => s,
            Err(m) => {
                self.fail(None, m);
                return;
            }
        };
        while let Some(msgs) = next_aligned(&receivers, &mut heads, self.shared) {
            let packet = msgs[0].packet;
            let mut inputs = statics.clone();
            for ((slot, edge), spec) in inputs.iter_mut().zip(&node.inputs).zip(&node.info.inputs) {
                let Some(edge) = edge else { continue };
                let EdgeSource::Tap(tap) = edge.source else {
                    continue;
                };
                if self.plan.is_streamed(tap.from) {
                    let k = receivers.iter().position(|(p, _)| *p == tap.from.node);
                    *slot = k.and_then(|k| msgs[k].values.get(tap.from.port).cloned().flatten());
                } else if edge.mapped && state.is_none() {
                    // A static list mapped alongside the stream: this frame's element.
                    *slot = match slot.take() {
                        Some(Value::List(list)) => match list.items.get(packet.index) {
                            Some(v) => Some(v.clone()),
                            None => {
                                self.fail(Some(packet.index), format!(
                                    "input `{}`: the mapped list has {} elements, the stream reached frame {}",
                                    spec.name, list.items.len(), packet.index
                                ));
                                return;
                            }
                        },
                        other => other,
                    };
                }
            }
            if let Err(e) = crate::exec::check_finite_inputs(node, &inputs) {
                self.fail(Some(packet.index), e.to_string());
                return;
            }
            let ctx = ctx_for(self.index, Some(packet.index));
            let t0 = Instant::now();
            let result = guarded(self.pool, || {
                let ins = Inputs::new(&node.info.inputs, &inputs);
                match state.as_mut() {
                    Some(state) => state.push(&ctx, packet, &ins).and_then(|mut out| {
                        node.info
                            .outputs
                            .iter()
                            .filter(|s| s.per_frame)
                            .map(|s| {
                                let v = out.take(&s.name).ok_or_else(|| {
                                    OpError::failed(format!("no value for output `{}`", s.name))
                                })?;
                                let expected = s.ty.element().cloned().unwrap_or(s.ty.clone());
                                if v.port_type() != expected {
                                    return Err(OpError::failed(format!(
                                        "produced {} on output `{}`, declared {expected}",
                                        v.port_type(),
                                        s.name
                                    )));
                                }
                                Ok(Some(v))
                            })
                            .collect::<Result<Vec<_>, _>>()
                    }),
                    None => node
                        .op
                        .run(&ctx, &ins)
                        .and_then(|out| collect_outputs(node, out, true))
                        .map(|v| v.into_iter().map(Some).collect()),
                }
            });
            self.account(t0.elapsed());
            let per_frame = match result {
                Ok(v) => v,
                Err(e) => {
                    self.fail(Some(packet.index), e.to_string());
                    return;
                }
            };
            // Sequence nodes return only their per-frame outputs: spread them over the ports.
            let values = if state.is_some() {
                let mut it = per_frame.into_iter();
                node.info
                    .outputs
                    .iter()
                    .map(|s| {
                        if s.per_frame {
                            it.next().flatten()
                        } else {
                            None
                        }
                    })
                    .collect()
            } else {
                per_frame
            };
            if !self.send(FrameMsg { packet, values }) {
                return;
            }
        }
        if self.shared.aborted() {
            return;
        }
        if let Some(mut state) = state {
            let ctx = ctx_for(self.index, None);
            let t0 = Instant::now();
            let result = guarded(self.pool, || state.finish(&ctx));
            self.account_time(t0.elapsed());
            match result {
                Ok(mut out) => {
                    if let Ok(mut f) = finals.lock() {
                        for (port, spec) in node.info.outputs.iter().enumerate() {
                            if !spec.per_frame
                                && let Some(v) = out.take(&spec.name)
                            {
                                f.insert(
                                    PortRef {
                                        node: self.index,
                                        port,
                                    },
                                    v,
                                );
                            }
                        }
                    }
                }
                Err(e) => self.fail(None, format!("at the end of the stream: {e}")),
            }
        }
    }
}
