//! Streaming graphs: sources produce frames one at a time, per-frame and stateful stages run
//! pipelined on bounded channels, and the results equal a batch run over whole lists.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::source;

use std::sync::atomic::{AtomicI64, AtomicUsize, Ordering};
use std::time::Duration;

use ocellus_engine::op::{FrameSource, Op, Packet, SequenceState, run_sequence_batch};
use ocellus_engine::stream::{NodeClass, StreamError, StreamFrame, load_streamed, run_stream};
use ocellus_engine::{
    Inputs, OpError, Operator, Outputs, PortSpec, PortType, Registry, RunContext, RunOptions,
    Value, params,
};

params! {
    /// `s.count`.
    pub struct CountParams {
        /// Frames.
        frames: u32 = 10 => [min = 1, max = 10000000],
        /// Frame rate (timestamps).
        fps: f64 = 10.0 => [min = 0.001, max = 1000000.0],
        /// Added to every value.
        offset: f64 = 0.0,
        /// Record how far ahead of the `s.slow` stages the source runs (one test at a time).
        track_lead: bool = false,
    }
}

/// Source: value k + offset for frame k.
struct Count(CountParams);

/// Frames produced by every `s.count` source of the process minus frames finished by every
/// `s.slow` stage: how far the sources run ahead.
static PRODUCED: AtomicI64 = AtomicI64::new(0);
static CONSUMED: AtomicI64 = AtomicI64::new(0);
static MAX_LEAD: AtomicI64 = AtomicI64::new(0);

impl Op for Count {
    type Params = CountParams;
    const ID: &'static str = "s.count";
    const SUMMARY: &'static str = "counts";
    const DOC: &'static str = "counts";
    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }
    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("values", PortType::Scalar.list_of(), "k + offset").per_frame(),
            PortSpec::new("count", PortType::Integer, "frames"),
        ]
    }
    fn new(p: CountParams) -> Result<Self, String> {
        Ok(Count(p))
    }
}

impl Operator for Count {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let items = (0..self.0.frames)
            .map(|k| Value::Scalar(f64::from(k) + self.0.offset))
            .collect();
        Ok(Outputs::new()
            .with("values", Value::list(PortType::Scalar, items))
            .with("count", Value::Integer(i64::from(self.0.frames))))
    }

    fn frame_source(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn FrameSource>, OpError>> {
        Some(Ok(Box::new(CountSource {
            frames: self.0.frames as usize,
            fps: self.0.fps,
            offset: self.0.offset,
            track_lead: self.0.track_lead,
        })))
    }
}

struct CountSource {
    frames: usize,
    fps: f64,
    offset: f64,
    track_lead: bool,
}

impl FrameSource for CountSource {
    fn frames(&self) -> usize {
        self.frames
    }
    fn timestamp_us(&self, index: usize) -> i64 {
        (index as f64 * 1e6 / self.fps).round() as i64
    }
    fn frame(&mut self, _ctx: &RunContext, index: usize) -> Result<Outputs, OpError> {
        if self.track_lead {
            let lead =
                PRODUCED.fetch_add(1, Ordering::SeqCst) + 1 - CONSUMED.load(Ordering::SeqCst);
            MAX_LEAD.fetch_max(lead, Ordering::SeqCst);
        }
        Ok(Outputs::new().with("values", Value::Scalar(index as f64 + self.offset)))
    }
    fn statics(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("count", Value::Integer(self.frames as i64)))
    }
}

params! {
    /// `s.square`.
    pub struct SquareParams {
        /// Fails at this value.
        fail_at: Option<f64> = None,
    }
}

/// Per element: x², or an error at `fail_at`.
struct Square(SquareParams);

impl Op for Square {
    type Params = SquareParams;
    const ID: &'static str = "s.square";
    const SUMMARY: &'static str = "squares";
    const DOC: &'static str = "squares";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("x", PortType::Scalar, "x")]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("y", PortType::Scalar, "x²")]
    }
    fn new(p: SquareParams) -> Result<Self, String> {
        Ok(Square(p))
    }
}

impl Operator for Square {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let x = inputs.scalar("x")?;
        if self.0.fail_at == Some(x) {
            return Err(OpError::failed(format!("{x} is not allowed")));
        }
        Ok(Outputs::new().with("y", Value::Scalar(x * x)))
    }
}

params! {
    /// `s.slow`.
    pub struct SlowParams {
        /// Sleep per element, ms.
        sleep_ms: u32 = 0,
        /// Count finished elements for the backpressure test.
        count: bool = false,
    }
}

/// Per element: x, after a sleep (a slow stage).
struct Slow(SlowParams);

impl Op for Slow {
    type Params = SlowParams;
    const ID: &'static str = "s.slow";
    const SUMMARY: &'static str = "slow";
    const DOC: &'static str = "slow";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("x", PortType::Scalar, "x")]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("y", PortType::Scalar, "x")]
    }
    fn new(p: SlowParams) -> Result<Self, String> {
        Ok(Slow(p))
    }
}

impl Operator for Slow {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        std::thread::sleep(Duration::from_millis(u64::from(self.0.sleep_ms)));
        if self.0.count {
            CONSUMED.fetch_add(1, Ordering::SeqCst);
        }
        Ok(Outputs::new().with("y", Value::Scalar(inputs.scalar("x")?)))
    }
}

/// Per element: a + b.
struct Add2;

impl Op for Add2 {
    type Params = ocellus_engine::NoParams;
    const ID: &'static str = "s.add2";
    const SUMMARY: &'static str = "adds";
    const DOC: &'static str = "adds";
    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("a", PortType::Scalar, "a"),
            PortSpec::new("b", PortType::Scalar, "b"),
        ]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("sum", PortType::Scalar, "a + b")]
    }
    fn new(_: ocellus_engine::NoParams) -> Result<Self, String> {
        Ok(Add2)
    }
}

impl Operator for Add2 {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with(
            "sum",
            Value::Scalar(inputs.scalar("a")? + inputs.scalar("b")?),
        ))
    }
}

/// Stateful: running sums (and the frame index seen), total at the end.
struct CumSum;

impl Op for CumSum {
    type Params = ocellus_engine::NoParams;
    const ID: &'static str = "s.cumsum";
    const SUMMARY: &'static str = "running sum";
    const DOC: &'static str = "running sum";
    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("values", PortType::Scalar.list_of(), "x per frame").per_frame(),
            PortSpec::new("scale", PortType::Scalar, "multiplies").optional(),
        ]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("sums", PortType::Scalar.list_of(), "running sum").per_frame(),
            PortSpec::new("indices", PortType::Integer.list_of(), "packet index").per_frame(),
            PortSpec::new("total", PortType::Scalar, "the sum"),
        ]
    }
    fn new(_: ocellus_engine::NoParams) -> Result<Self, String> {
        Ok(CumSum)
    }
}

impl Operator for CumSum {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_sequence_batch(self, ctx, inputs, &Self::outputs())
    }
    fn sequence(
        &self,
        _ctx: &RunContext,
        inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        assert!(
            inputs.get("values").is_none(),
            "per-frame input set at start"
        );
        let scale = if inputs.get("scale").is_some() {
            inputs.scalar("scale").unwrap()
        } else {
            1.0
        };
        Some(Ok(Box::new(CumSumState { sum: 0.0, scale })))
    }
}

struct CumSumState {
    sum: f64,
    scale: f64,
}

impl SequenceState for CumSumState {
    fn push(
        &mut self,
        _ctx: &RunContext,
        packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        self.sum += self.scale * inputs.scalar("values")?;
        Ok(Outputs::new()
            .with("sums", Value::Scalar(self.sum))
            .with("indices", Value::Integer(packet.index as i64)))
    }
    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("total", Value::Scalar(self.sum)))
    }
}

params! {
    /// `s.plant`.
    pub struct PlantParams {
        /// Frames.
        frames: u32 = 10 => [min = 1, max = 10000000],
        /// State at frame 0.
        start: f64 = 1.0,
    }
}

/// Source with feedback: state x, frame k shows x_k; a value u fed back after frame k gives
/// x_{k+1} = x_k + u (nothing fed back: x stays). A NaN fed back is an error.
struct Plant(PlantParams);

impl Op for Plant {
    type Params = PlantParams;
    const ID: &'static str = "s.plant";
    const SUMMARY: &'static str = "integrates fed-back steps";
    const DOC: &'static str = "integrates fed-back steps";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("u", PortType::Scalar, "step").feedback()]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("x", PortType::Scalar.list_of(), "state").per_frame()]
    }
    fn new(p: PlantParams) -> Result<Self, String> {
        Ok(Plant(p))
    }
}

impl Operator for Plant {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        assert!(inputs.get("u").is_none(), "a feedback port is never wired");
        let items = (0..self.0.frames)
            .map(|_| Value::Scalar(self.0.start))
            .collect();
        Ok(Outputs::new().with("x", Value::list(PortType::Scalar, items)))
    }
    fn frame_source(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn FrameSource>, OpError>> {
        Some(Ok(Box::new(PlantSource {
            frames: self.0.frames as usize,
            x: self.0.start,
            fed: Vec::new(),
        })))
    }
}

struct PlantSource {
    frames: usize,
    x: f64,
    /// Frame indices at which feedback arrived.
    fed: Vec<usize>,
}

impl FrameSource for PlantSource {
    fn frames(&self) -> usize {
        self.frames
    }
    fn timestamp_us(&self, index: usize) -> i64 {
        index as i64 * 1000
    }
    fn frame(&mut self, _ctx: &RunContext, index: usize) -> Result<Outputs, OpError> {
        // With a loop, feedback arrives exactly once before every frame but the first.
        let expected: Vec<usize> = (1..=index).collect();
        if !self.fed.is_empty() && self.fed != expected {
            return Err(OpError::failed(format!(
                "frame {index} after feedback at {:?}",
                self.fed
            )));
        }
        Ok(Outputs::new().with("x", Value::Scalar(self.x)))
    }
    fn feed(
        &mut self,
        _ctx: &RunContext,
        index: usize,
        port: &str,
        value: &Value,
    ) -> Result<(), OpError> {
        assert_eq!(port, "u");
        let Value::Scalar(u) = value else {
            return Err(OpError::failed("not a scalar"));
        };
        if !u.is_finite() {
            return Err(OpError::failed(format!("step {u} is not finite")));
        }
        self.fed.push(index);
        self.x += u;
        Ok(())
    }
}

params! {
    /// `s.gain`.
    pub struct GainParams {
        /// Factor.
        k: f64 = -0.5,
    }
}

/// Per element: k · x.
struct Gain(GainParams);

impl Op for Gain {
    type Params = GainParams;
    const ID: &'static str = "s.gain";
    const SUMMARY: &'static str = "scales";
    const DOC: &'static str = "scales";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("x", PortType::Scalar, "x")]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("y", PortType::Scalar, "k · x")]
    }
    fn new(p: GainParams) -> Result<Self, String> {
        Ok(Gain(p))
    }
}

impl Operator for Gain {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        Ok(Outputs::new().with("y", Value::Scalar(self.0.k * inputs.scalar("x")?)))
    }
}

/// The common test operators (`t.collect` sums a list) and the streaming ones above.
fn registry() -> Registry {
    let (mut reg, _) = common::registry();
    reg.register::<Count>().unwrap();
    reg.register::<Square>().unwrap();
    reg.register::<Slow>().unwrap();
    reg.register::<Add2>().unwrap();
    reg.register::<CumSum>().unwrap();
    reg.register::<Plant>().unwrap();
    reg.register::<Gain>().unwrap();
    reg
}

fn load(text: &str) -> (ocellus_engine::Graph, ocellus_engine::stream::StreamSpec) {
    match load_streamed(&registry(), &source("stream.ron", text), &[]) {
        Ok((g, Some(s))) => (g, s),
        Ok((_, None)) => panic!("no stream section"),
        Err(d) => panic!("did not load:\n{d}"),
    }
}

fn errors(text: &str) -> String {
    match load_streamed(&registry(), &source("stream.ron", text), &[]) {
        Ok(_) => panic!("loaded, but errors were expected"),
        Err(d) => {
            d.0.iter()
                .map(|d| {
                    format!(
                        "{}: {} [{}]",
                        d.location().unwrap_or_default(),
                        d.message,
                        d.help.clone().unwrap_or_default()
                    )
                })
                .collect::<Vec<_>>()
                .join("\n")
        }
    }
}

/// Streams and returns (frames seen by the sink, report).
fn stream(text: &str, threads: usize) -> (Vec<StreamFrame>, ocellus_engine::stream::StreamReport) {
    let (graph, spec) = load(text);
    let mut frames = Vec::new();
    let options = RunOptions {
        threads,
        ..RunOptions::default()
    };
    let report = run_stream(&graph, &spec, &options, |f| {
        frames.push(f.clone());
        Ok(())
    })
    .unwrap();
    (frames, report)
}

fn scalar_column(frames: &[StreamFrame], name: &str) -> Vec<f64> {
    frames
        .iter()
        .map(|f| match f.outputs.iter().find(|(n, _)| n == name) {
            Some((_, Value::Scalar(x))) => *x,
            other => panic!("{name}: {other:?}"),
        })
        .collect()
}

const PIPELINE: &str = r#"Graph(
    name: "pipeline",
    nodes: {
        "src": (op: "s.count", params: (frames: 20, offset: 1.0)),
        "scale": (op: "s.count", params: (frames: 1, offset: 3.0)),
        "sq": (op: "s.square", inputs: { "x": "src.values" }),
        "sum": (op: "s.cumsum", inputs: { "values": "sq.y", "scale": "scale.values[0]" }),
        "total": (op: "t.collect", inputs: { "items": "sq.y" }),
        "last": (op: "s.square", inputs: { "x": "sq.y[-1]" }),
    },
    outputs: {
        "squares": "sq.y", "sums": "sum.sums", "indices": "sum.indices", "cum": "sum.total",
        "total": "total.total", "last": "last.y", "count": "src.count",
    },
    stream: (capacity: 2, sources: ["src"]),
)"#;

#[test]
fn nodes_are_classified_by_how_they_read_the_stream() {
    let (_, report) = stream(PIPELINE, 2);
    let class = |name: &str| {
        report
            .stages
            .iter()
            .find(|s| s.name == name)
            .map(|s| s.class)
            .unwrap()
    };
    assert_eq!(class("src"), NodeClass::Source);
    // Not listed in `sources`: an ordinary node, run once before the stream.
    assert_eq!(class("scale"), NodeClass::Static);
    assert_eq!(class("sq"), NodeClass::PerFrame);
    assert_eq!(class("sum"), NodeClass::Sequence);
    assert_eq!(class("total"), NodeClass::Final);
    assert_eq!(class("last"), NodeClass::Final);
    assert_eq!(report.completed, 20);
    assert_eq!((report.dropped, report.unaligned), (0, 0));
    let stage = |name: &str| {
        report
            .stages
            .iter()
            .find(|s| s.name == name)
            .unwrap()
            .frames
    };
    assert_eq!((stage("src"), stage("sq"), stage("sum")), (20, 20, 20));
}

#[test]
fn streaming_gives_the_batch_values_at_any_thread_count() {
    let reg = registry();
    let (graph, _) = load(PIPELINE);
    let batch = ocellus_engine::run(&graph, &RunOptions::default()).unwrap();
    assert!(batch.failures.is_empty(), "{:?}", batch.failures);
    for threads in [1, 2, 5] {
        let streamed = {
            let path = std::env::temp_dir().join(format!(
                "ocellus-stream-{}-{threads}.ron",
                std::process::id()
            ));
            std::fs::write(&path, PIPELINE).unwrap();
            let out = ocellus_engine::testing::run_stream_graph(&reg, &path, threads, &[]);
            let _ = std::fs::remove_file(&path);
            out.unwrap()
        };
        assert_eq!(
            ocellus_engine::summary::summarize_outputs(&streamed),
            ocellus_engine::summary::summarize_outputs(&batch.outputs),
            "{threads} threads"
        );
    }
    // Hand-computed: squares of 1..=20, scaled running sums (scale 3), their total.
    let (frames, report) = stream(PIPELINE, 2);
    let squares: Vec<f64> = (1..=20).map(|k| f64::from(k * k)).collect();
    assert_eq!(scalar_column(&frames, "squares"), squares);
    let sums = scalar_column(&frames, "sums");
    assert_eq!(sums[2], 3.0 * (1.0 + 4.0 + 9.0));
    let total: f64 = squares.iter().sum();
    let out = |name: &str| {
        report
            .outputs
            .iter()
            .find(|(n, _)| n == name)
            .unwrap()
            .1
            .clone()
    };
    assert!(matches!(out("total"), Value::Scalar(x) if x == total));
    assert!(matches!(out("cum"), Value::Scalar(x) if x == 3.0 * total));
    assert!(matches!(out("last"), Value::Scalar(x) if x == 400.0 * 400.0));
    assert!(matches!(out("count"), Value::Integer(20)));
    // Packets carry their source index and timestamp (10 fps: 100 ms apart).
    for (k, f) in frames.iter().enumerate() {
        assert_eq!(f.packet.index, k);
        assert_eq!(f.packet.timestamp_us, k as i64 * 100_000);
        assert_eq!(f.position, k + 1);
        assert_eq!(f.total, 20);
    }
    assert!((frames[0].fps - 10.0).abs() < 1e-9);
}

#[test]
fn a_slow_stage_applies_backpressure_and_memory_stays_bounded() {
    // One slow stage after the source; with capacity 1 the source may run only a few frames
    // ahead of it: one in the channel, one being handed over, one in the slow stage.
    let text = r#"Graph(
        name: "backpressure",
        nodes: {
            "src": (op: "s.count", params: (frames: 40, track_lead: true)),
            "slow": (op: "s.slow", inputs: { "x": "src.values" }, params: (sleep_ms: 2, count: true)),
        },
        outputs: { "y": "slow.y" },
        stream: (capacity: 1),
    )"#;
    PRODUCED.store(0, Ordering::SeqCst);
    CONSUMED.store(0, Ordering::SeqCst);
    MAX_LEAD.store(0, Ordering::SeqCst);
    let (frames, report) = stream(text, 2);
    assert_eq!(frames.len(), 40);
    assert_eq!(report.dropped, 0);
    let lead = MAX_LEAD.load(Ordering::SeqCst);
    assert!(
        (1..=4).contains(&lead),
        "the source ran {lead} frames ahead"
    );
    assert_eq!(
        scalar_column(&frames, "y"),
        (0..40).map(f64::from).collect::<Vec<_>>()
    );
}

#[test]
fn the_drop_policy_drops_and_counts_frames_a_full_pipeline_cannot_take() {
    // 1000 frames/s into a stage taking 3 ms per frame: most frames find the queue full.
    let text = r#"Graph(
        name: "drop",
        nodes: {
            "src": (op: "s.count", params: (frames: 200, fps: 1000.0)),
            "slow": (op: "s.slow", inputs: { "x": "src.values" }, params: (sleep_ms: 3)),
            "sum": (op: "s.cumsum", inputs: { "values": "slow.y" }),
        },
        outputs: { "indices": "sum.indices", "y": "slow.y" },
        stream: (capacity: 2, policy: "drop", rate_fps: 1000),
    )"#;
    let (frames, report) = stream(text, 2);
    assert!(report.dropped > 0, "nothing dropped");
    assert_eq!(report.completed + report.dropped, 200);
    assert_eq!(report.frames, report.completed);
    // The frames that got through are in order, with gaps where frames were dropped, and the
    // stateful stage saw exactly those.
    let indices: Vec<usize> = frames.iter().map(|f| f.packet.index).collect();
    assert!(indices.windows(2).all(|w| w[0] < w[1]));
    assert!(indices.windows(2).any(|w| w[1] > w[0] + 1));
    for f in &frames {
        let seen = f.outputs.iter().find(|(n, _)| n == "indices").unwrap();
        assert!(matches!(seen.1, Value::Integer(i) if i as usize == f.packet.index));
    }
}

#[test]
fn streams_of_different_rates_are_aligned_by_timestamp() {
    // 10 frames at 10 fps (0, 100, …, 900 ms) and 5 at 5 fps (0, 200, …, 800 ms): only the
    // common timestamps meet; the 100, 300, 500, 700 ms packets are discarded.
    let text = r#"Graph(
        name: "align",
        nodes: {
            "fast": (op: "s.count", params: (frames: 10, fps: 10.0)),
            "slow": (op: "s.count", params: (frames: 5, fps: 5.0, offset: 100.0)),
            "add": (op: "s.add2", inputs: { "a": "fast.values", "b": "slow.values" }),
        },
        outputs: { "sum": "add.sum" },
        stream: (capacity: 4),
    )"#;
    let (frames, report) = stream(text, 2);
    // fast k (at 100k ms) + slow j (at 200j ms, value j + 100) with k = 2j.
    assert_eq!(
        scalar_column(&frames, "sum"),
        [100.0, 103.0, 106.0, 109.0, 112.0]
    );
    let stamps: Vec<i64> = frames.iter().map(|f| f.packet.timestamp_us).collect();
    assert_eq!(stamps, [0, 200_000, 400_000, 600_000, 800_000]);
    assert_eq!(report.unaligned, 4);
}

#[test]
fn a_failing_frame_stops_the_stream_naming_node_and_frame() {
    let text = r#"Graph(
        name: "fails",
        nodes: {
            "src": (op: "s.count", params: (frames: 50)),
            "sq": (op: "s.square", inputs: { "x": "src.values" }, params: (fail_at: Some(7.0))),
            "sum": (op: "s.cumsum", inputs: { "values": "sq.y" }),
        },
        outputs: { "sums": "sum.sums" },
        stream: (),
    )"#;
    let (graph, spec) = load(text);
    let mut seen = 0;
    let err = run_stream(&graph, &spec, &RunOptions::default(), |_| {
        seen += 1;
        Ok(())
    })
    .unwrap_err();
    match &err {
        StreamError::Node {
            node,
            frame,
            message,
            location,
            ..
        } => {
            assert_eq!(node, "sq");
            assert_eq!(*frame, Some(7));
            assert!(message.contains("7 is not allowed"), "{message}");
            assert!(
                location.as_deref().unwrap_or("").starts_with("stream.ron:"),
                "{location:?}"
            );
        }
        other => panic!("{other}"),
    }
    assert!(seen <= 7, "{seen} frames after the failure");
    assert!(err.to_string().contains("failed at frame 7"), "{err}");
}

#[test]
fn a_failing_sink_stops_the_stream() {
    let (graph, spec) = load(PIPELINE);
    let count = AtomicUsize::new(0);
    let err = run_stream(&graph, &spec, &RunOptions::default(), |_| {
        if count.fetch_add(1, Ordering::SeqCst) == 3 {
            Err("disk full".into())
        } else {
            Ok(())
        }
    })
    .unwrap_err();
    assert!(
        matches!(err, StreamError::Sink(ref m) if m == "disk full"),
        "{err}"
    );
}

#[test]
fn bad_stream_sections_are_load_errors_pointing_into_the_file() {
    let graph = |stream: &str| {
        format!(
            r#"Graph(
    name: "g",
    nodes: {{
        "src": (op: "s.count"),
        "sq": (op: "s.square", inputs: {{ "x": "src.values" }}),
    }},
    outputs: {{ "y": "sq.y" }},
    stream: {stream},
)"#
        )
    };
    let e = errors(&graph(r#"(policy: "drop")"#));
    assert!(
        e.contains("needs `rate_fps`") && e.starts_with("stream.ron:8:"),
        "{e}"
    );
    let e = errors(&graph(r#"(policy: "sometimes")"#));
    assert!(e.contains("`policy` must be \"block\" or \"drop\""), "{e}");
    let e = errors(&graph("(capacity: 0)"));
    assert!(
        e.contains("`capacity` must be an integer in 1..=4096"),
        "{e}"
    );
    let e = errors(&graph(r#"(sources: ["srx"])"#));
    assert!(
        e.contains("`sources` names `srx`") && e.contains("did you mean `src`?"),
        "{e}"
    );
    let e = errors(&graph(r#"(sources: ["sq"])"#));
    assert!(e.contains("has no frame-sequence output"), "{e}");
    let e = errors(&graph("(capacty: 3)"));
    assert!(e.contains("capacty") && e.contains("capacity"), "{e}");
    let e = errors(&graph(r#"(encode: { "z": ["gif"] })"#));
    assert!(
        e.contains("`encode` names `z`") && e.contains("did you mean `y`?"),
        "{e}"
    );
    let e = errors(&graph(r#"(metrics: ["xml"])"#));
    assert!(e.contains("unknown metrics format"), "{e}");
    let e = errors(
        r#"Graph(
    name: "g",
    nodes: { "src": (op: "s.count") },
    outputs: { "v": "src.count" },
    stream: (),
    animation: (frames: 3),
)"#,
    );
    assert!(
        e.contains("cannot both stream and have an `animation`"),
        "{e}"
    );
}

#[test]
fn a_long_stream_runs_in_bounded_memory() {
    // 100 000 frames through a source, a per-frame node and a stateful one: only the last
    // frame is kept by the sink here, and nothing gathers, so the run holds a few packets.
    let text = r#"Graph(
        name: "long",
        nodes: {
            "src": (op: "s.count", params: (frames: 100000, fps: 1000.0)),
            "sq": (op: "s.square", inputs: { "x": "src.values" }),
            "sum": (op: "s.cumsum", inputs: { "values": "sq.y" }),
        },
        outputs: { "total": "sum.total" },
        stream: (capacity: 8),
    )"#;
    let (graph, spec) = load(text);
    let report = run_stream(&graph, &spec, &RunOptions::default(), |_| Ok(())).unwrap();
    assert_eq!(report.completed, 100_000);
    // Σ k² for k < 100 000 = (n−1)n(2n−1)/6.
    let n = 100_000f64;
    let expected = (n - 1.0) * n * (2.0 * n - 1.0) / 6.0;
    let Some((_, Value::Scalar(total))) = report.outputs.first() else {
        panic!("{:?}", report.outputs)
    };
    assert!((total - expected).abs() / expected < 1e-12);
}

/// A proportional loop: the plant shows x_k, the controller computes u_k = −½ x_k, fed back:
/// x_{k+1} = x_k + u_k = x_k / 2.
const LOOP: &str = r#"Graph(
    name: "loop",
    nodes: {
        "plant": (op: "s.plant", params: (frames: 30, start: 1024.0)),
        "ctl": (op: "s.gain", inputs: { "x": "plant.x" }, params: (k: -0.5)),
        "sum": (op: "s.cumsum", inputs: { "values": "plant.x" }),
    },
    outputs: { "x": "plant.x", "total": "sum.total" },
    stream: (capacity: 3, feedback: { "plant.u": "ctl.y" }),
)"#;

#[test]
fn feedback_closes_a_loop_frame_by_frame_at_any_thread_count() {
    for threads in [1, 2, 4] {
        let (frames, report) = stream(LOOP, threads);
        let xs = scalar_column(&frames, "x");
        let expected: Vec<f64> = (0..30).map(|k| 1024.0 * 0.5f64.powi(k)).collect();
        assert_eq!(xs, expected, "{threads} threads");
        // The controller runs although no output reads it: it drives the plant.
        let ctl = report.stages.iter().find(|s| s.name == "ctl").unwrap();
        assert_eq!((ctl.class, ctl.frames), (NodeClass::PerFrame, 30));
        let total: f64 = expected.iter().sum();
        assert!(
            matches!(report.outputs.first(), Some((_, Value::Scalar(t))) if *t == total),
            "the sequence stage finished after the loop: {:?}",
            report.outputs
        );
    }
    // Without the feedback edge the plant holds still: the loop is what moves it.
    let open = LOOP.replace(r#", feedback: { "plant.u": "ctl.y" }"#, "");
    let (frames, _) = stream(&open, 2);
    assert!(scalar_column(&frames, "x").iter().all(|&x| x == 1024.0));
}

#[test]
fn a_sequence_stage_can_feed_back() {
    // u_k = Σ_{j≤k} x_j (a running sum), so x_{k+1} = x_k + Σ_{j≤k} x_j.
    let text = LOOP.replace(r#""plant.u": "ctl.y""#, r#""plant.u": "sum.sums""#);
    let text = text
        .replace("start: 1024.0", "start: 1.0")
        .replace("frames: 30", "frames: 12");
    let (frames, _) = stream(&text, 2);
    let mut x = 1.0;
    let mut sum = 0.0;
    let mut expected = Vec::new();
    for _ in 0..12 {
        expected.push(x);
        sum += x;
        x += sum;
    }
    assert_eq!(scalar_column(&frames, "x"), expected);
}

#[test]
fn a_failure_inside_the_loop_ends_the_stream_without_hanging() {
    // A gain of −1e308 on x = 1e10 gives u = −∞ after frame 0: the source refuses it.
    let text = LOOP.replace("params: (k: -0.5)", "params: (k: -1e308)");
    let text = text.replace("start: 1024.0", "start: 1e10");
    let (graph, spec) = load(&text);
    let err = run_stream(&graph, &spec, &RunOptions::default(), |_| Ok(())).unwrap_err();
    let message = err.to_string();
    assert!(
        message.contains("plant") && message.contains("not finite") && message.contains("frame 1"),
        "{message}"
    );
    // A failing stage inside the loop: the source stops waiting for its feedback.
    let text = r#"Graph(
        name: "g",
        nodes: {
            "plant": (op: "s.plant", params: (frames: 10, start: 3.0)),
            "sq": (op: "s.square", inputs: { "x": "plant.x" }, params: (fail_at: 3.0)),
            "ctl": (op: "s.gain", inputs: { "x": "sq.y" }),
        },
        outputs: { "x": "plant.x" },
        stream: (feedback: { "plant.u": "ctl.y" }),
    )"#;
    let (graph, spec) = load(text);
    let err = run_stream(&graph, &spec, &RunOptions::default(), |_| Ok(())).unwrap_err();
    assert!(
        err.to_string().contains("`sq`") && err.to_string().contains("frame 0"),
        "{err}"
    );
}

#[test]
fn bad_feedback_edges_are_load_errors() {
    let graph = |nodes: &str, feedback: &str| {
        format!(
            r#"Graph(
    name: "g",
    nodes: {{
        "plant": (op: "s.plant"),
        "ctl": (op: "s.gain", inputs: {{ "x": "plant.x" }}),
        "sum": (op: "s.cumsum", inputs: {{ "values": "plant.x" }}),
        "src": (op: "s.count"),
        "other": (op: "s.gain", inputs: {{ "x": "src.values" }}),
        "all": (op: "t.collect", inputs: {{ "items": "ctl.y" }}),{nodes}
    }},
    outputs: {{ "x": "plant.x", "o": "other.y", "all": "all.total" }},
    stream: (feedback: {feedback}),
)"#
        )
    };
    let e = errors(&graph("", r#"{ "plant.u": "ctll.y" }"#));
    assert!(
        e.contains("reads `ctll`, which is not a node") && e.contains("did you mean `ctl`?"),
        "{e}"
    );
    assert!(e.starts_with("stream.ron:12:"), "{e}");
    let e = errors(&graph("", r#"{ "plant.v": "ctl.y" }"#));
    assert!(e.contains("has no input `v`"), "{e}");
    let e = errors(&graph("", r#"{ "ctl.x": "ctl.y" }"#));
    assert!(
        e.contains("is not a feedback input of a frame source"),
        "{e}"
    );
    let e = errors(&graph("", r#"{ "plant.u": "ctl.z" }"#));
    assert!(e.contains("has no output `z`"), "{e}");
    let e = errors(&graph("", r#"{ "plant.u": "sum.indices" }"#));
    assert!(e.contains("type mismatch") && e.contains("Integer"), "{e}");
    let e = errors(&graph("", r#"{ "plant.u": "other.y" }"#));
    assert!(e.contains("must work on `plant`'s frames"), "{e}");
    let e = errors(&graph("", r#"{ "plant.u": "all.total" }"#));
    assert!(
        e.contains("not produced frame by frame (final node)"),
        "{e}"
    );
    let e = errors(&graph("", r#"{ "plant.u": "plant.x" }"#));
    assert!(e.contains("cannot feed its own output back"), "{e}");
    let e = errors(&graph("", r#"{ "plant.u": "ctl" }"#));
    assert!(e.contains("must be `node.port`"), "{e}");
    let e = errors(&graph("", r#"["ctl.y"]"#));
    assert!(e.contains("must be a map"), "{e}");
    let e = errors(&graph(
        "",
        r#"{ "plant.u": "ctl.y" }, policy: "drop", rate_fps: 30"#,
    ));
    assert!(e.contains("cannot be used with `feedback`"), "{e}");
    let e = errors(&graph("", r#"{ "plant.u": "ctl.y" }"#).replace(
        r#""plant": (op: "s.plant"),"#,
        r#""plant": (op: "s.plant", inputs: { "u": "src.values[0]" }),"#,
    ));
    assert!(e.contains("fed back and also wired"), "{e}");
}
