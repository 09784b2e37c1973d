//! The operator interface and the registry. Built-in operators and plugin operators go through the
//! same [`OpFactory`] and [`Operator`] traits and the same [`Registry`].

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use crate::params::{ParamMap, ParamSpec, Params};
use crate::types::PortType;
use crate::value::{Image, Value};

/// A named, typed port of an operator.
#[derive(Debug, Clone, PartialEq)]
pub struct PortSpec {
    /// Port name, unique among the operator's inputs (or outputs).
    pub name: String,
    /// Type.
    pub ty: PortType,
    /// What flows through it.
    pub doc: String,
    /// Inputs only: whether the port may be left unconnected.
    pub optional: bool,
    /// A `List<T>` port that is a frame sequence: a source's output streamed one element per
    /// packet, or a sequence operator's input consumed (and output produced) one element per
    /// packet. See [`crate::stream`].
    pub per_frame: bool,
    /// Inputs of a frame source only: the port takes a value fed back from later in a stream
    /// (the stream section's `feedback`), delivered with [`FrameSource::feed`] before each
    /// frame after the first. It is never wired in `inputs`; a batch run leaves it unset.
    pub feedback: bool,
    /// Inputs only: the operator accepts NaN and infinities in a geometric value on this port
    /// (see [`Value::non_finite_at`](crate::value::Value::non_finite_at)); by default the
    /// scheduler refuses them before the operator runs, naming the node and the element.
    pub non_finite: bool,
}

impl PortSpec {
    /// A required port.
    pub fn new(name: &str, ty: PortType, doc: &str) -> PortSpec {
        PortSpec {
            name: name.to_string(),
            ty,
            doc: doc.to_string(),
            optional: false,
            per_frame: false,
            feedback: false,
            non_finite: false,
        }
    }

    /// Marks an input that accepts non-finite geometric values (an operator that cleans them
    /// out, say); see [`PortSpec::non_finite`].
    pub fn accepts_non_finite(mut self) -> PortSpec {
        self.non_finite = true;
        self
    }

    /// Marks an optional input of a frame source as a feedback port (see
    /// [`PortSpec::feedback`]).
    pub fn feedback(mut self) -> PortSpec {
        self.feedback = true;
        self.optional = true;
        self
    }

    /// Marks a `List<T>` port as a frame sequence (see [`PortSpec::per_frame`]).
    pub fn per_frame(mut self) -> PortSpec {
        self.per_frame = true;
        self
    }

    /// Marks an input port as optional.
    pub fn optional(mut self) -> PortSpec {
        self.optional = true;
        self
    }
}

/// Where an operator comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Origin {
    /// Compiled into Ocellus.
    Builtin,
    /// Linked into the host program by its author (statically registered, not part of Ocellus).
    Static(String),
    /// Loaded at run time from a shared library.
    Plugin {
        /// Plugin name from its descriptor.
        plugin: String,
        /// The library file.
        library: PathBuf,
    },
}

impl std::fmt::Display for Origin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Origin::Builtin => f.write_str("builtin"),
            Origin::Static(name) => write!(f, "static:{name}"),
            Origin::Plugin { plugin, library } => {
                write!(f, "plugin:{plugin} ({})", library.display())
            }
        }
    }
}

/// Everything the engine and the docs know about an operator.
#[derive(Debug, Clone, PartialEq)]
pub struct OpInfo {
    /// `family.name`.
    pub id: String,
    /// Bumped whenever outputs change for the same inputs and params (invalidates caches).
    pub version: u32,
    /// One line.
    pub summary: String,
    /// Method, formula, references.
    pub doc: String,
    /// Inputs, in order.
    pub inputs: Vec<PortSpec>,
    /// Outputs, in order.
    pub outputs: Vec<PortSpec>,
    /// Parameters.
    pub params: Vec<ParamSpec>,
    /// True for operators whose effect is outside the graph (writing files): they always run
    /// when demanded and are never served from the cache.
    pub side_effects: bool,
    /// Where it comes from.
    pub origin: Origin,
}

impl OpInfo {
    /// The family (`filter` of `filter.gaussian`).
    pub fn family(&self) -> &str {
        self.id.split_once('.').map_or(self.id.as_str(), |(f, _)| f)
    }

    /// Input port by name.
    pub fn input(&self, name: &str) -> Option<&PortSpec> {
        self.inputs.iter().find(|p| p.name == name)
    }

    /// Output port by name.
    pub fn output(&self, name: &str) -> Option<&PortSpec> {
        self.outputs.iter().find(|p| p.name == name)
    }
}

/// An error raised by an operator at run time.
#[derive(Debug, thiserror::Error)]
pub enum OpError {
    /// An input value is unsuitable (wrong pixel format, wrong size, degenerate data).
    #[error("input `{port}`: {message}")]
    Input {
        /// Input port.
        port: String,
        /// What is wrong.
        message: String,
    },
    /// A file could not be read or written.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// Any other failure.
    #[error("{0}")]
    Failed(String),
}

impl OpError {
    /// An input error.
    pub fn input(port: &str, message: impl Into<String>) -> OpError {
        OpError::Input {
            port: port.to_string(),
            message: message.into(),
        }
    }

    /// A generic failure.
    pub fn failed(message: impl Into<String>) -> OpError {
        OpError::Failed(message.into())
    }

    /// A file error.
    pub fn io(path: impl Into<PathBuf>, message: impl std::fmt::Display) -> OpError {
        OpError::Io {
            path: path.into(),
            message: message.to_string(),
        }
    }
}

/// What an operator may know about the run it is part of.
#[derive(Debug, Clone)]
pub struct RunContext {
    /// The node being run.
    pub node: String,
    /// Worker threads in the pool the operator runs on (rayon calls use this pool).
    pub threads: usize,
    /// For a mapped node, the index of the list element being processed.
    pub element: Option<usize>,
}

/// The inputs handed to one operator call, by port name.
pub struct Inputs<'a> {
    specs: &'a [PortSpec],
    values: &'a [Option<Value>],
}

impl<'a> Inputs<'a> {
    /// Pairs `values` with `specs` (same order).
    pub fn new(specs: &'a [PortSpec], values: &'a [Option<Value>]) -> Inputs<'a> {
        Inputs { specs, values }
    }

    /// The port descriptions, in order.
    pub fn specs(&self) -> &'a [PortSpec] {
        self.specs
    }

    /// The values, one per port, in order.
    pub fn values(&self) -> &'a [Option<Value>] {
        self.values
    }

    /// The value on port `name`, if connected.
    pub fn get(&self, name: &str) -> Option<&'a Value> {
        let index = self.specs.iter().position(|s| s.name == name)?;
        self.values.get(index)?.as_ref()
    }

    /// The value on required port `name`.
    pub fn require(&self, name: &str) -> Result<&'a Value, OpError> {
        self.get(name)
            .ok_or_else(|| OpError::input(name, "not connected"))
    }

    /// The image on port `name`.
    pub fn image(&self, name: &str) -> Result<&'a Arc<Image>, OpError> {
        match self.require(name)? {
            Value::Image(image) => Ok(image),
            other => Err(wrong_type(name, "Image", other)),
        }
    }

    /// The number on port `name` (integers are widened).
    pub fn scalar(&self, name: &str) -> Result<f64, OpError> {
        match self.require(name)? {
            Value::Scalar(x) => Ok(*x),
            Value::Integer(i) => Ok(*i as f64),
            other => Err(wrong_type(name, "Scalar", other)),
        }
    }

    /// The integer on port `name`.
    pub fn integer(&self, name: &str) -> Result<i64, OpError> {
        match self.require(name)? {
            Value::Integer(i) => Ok(*i),
            other => Err(wrong_type(name, "Integer", other)),
        }
    }

    /// The text on port `name`.
    pub fn text(&self, name: &str) -> Result<&'a str, OpError> {
        match self.require(name)? {
            Value::Text(t) => Ok(t),
            other => Err(wrong_type(name, "Text", other)),
        }
    }
}

fn wrong_type(port: &str, expected: &str, got: &Value) -> OpError {
    OpError::input(
        port,
        format!("expected {expected}, got {}", got.port_type()),
    )
}

/// The outputs of one operator call, by port name.
#[derive(Debug, Default, Clone)]
pub struct Outputs {
    values: Vec<(String, Value)>,
}

impl Outputs {
    /// No outputs yet.
    pub fn new() -> Outputs {
        Outputs::default()
    }

    /// Adds (or replaces) output `name`.
    pub fn with(mut self, name: &str, value: Value) -> Outputs {
        self.set(name, value);
        self
    }

    /// Sets output `name`.
    pub fn set(&mut self, name: &str, value: Value) {
        if let Some(slot) = self.values.iter_mut().find(|(n, _)| n == name) {
            slot.1 = value;
        } else {
            self.values.push((name.to_string(), value));
        }
    }

    /// Output `name`, if set.
    pub fn get(&self, name: &str) -> Option<&Value> {
        self.values.iter().find(|(n, _)| n == name).map(|(_, v)| v)
    }

    /// Takes output `name`.
    pub fn take(&mut self, name: &str) -> Option<Value> {
        let index = self.values.iter().position(|(n, _)| n == name)?;
        Some(self.values.swap_remove(index).1)
    }

    /// Names of the outputs set.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.values.iter().map(|(n, _)| n.as_str())
    }
}

/// A configured operator instance: parameters are already checked and bound.
pub trait Operator: Send + Sync {
    /// Computes the outputs from the inputs. Must be deterministic: the same inputs give
    /// bit-identical outputs whatever the thread count.
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError>;

    /// Extra bytes for the cache key, for operators whose result depends on something outside the
    /// graph (a source file's contents). Called before the run.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        Ok(Vec::new())
    }

    /// For an operator whose `per_frame` outputs can be produced one frame at a time (a
    /// capture source): the producer, configured from the node's inputs (all of them whole
    /// values). `None` (the default) when the operator cannot stream.
    fn frame_source(
        &self,
        ctx: &RunContext,
        inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn FrameSource>, OpError>> {
        let _ = (ctx, inputs);
        None
    }

    /// For a sequence operator (one with `per_frame` inputs): a fresh state, configured from the
    /// inputs that are not `per_frame` (those are unset here). `None` (the default) when the
    /// operator only runs on whole lists.
    fn sequence(
        &self,
        ctx: &RunContext,
        inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        let _ = (ctx, inputs);
        None
    }
}

/// Where one packet of a stream sits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Packet {
    /// Position of the frame in its source's sequence (0-based). Dropped frames leave gaps.
    pub index: usize,
    /// When the frame was captured, microseconds on the source's clock. A batch run (whole
    /// lists) numbers frames by index and sets this to the index.
    pub timestamp_us: i64,
}

/// Produces a source's `per_frame` outputs one frame at a time (see
/// [`Operator::frame_source`]).
pub trait FrameSource: Send {
    /// Number of frames.
    fn frames(&self) -> usize;
    /// Capture time of frame `index`, microseconds; strictly increasing with `index`.
    fn timestamp_us(&self, index: usize) -> i64;
    /// Element `index` of every `per_frame` output, by port name.
    fn frame(&mut self, ctx: &RunContext, index: usize) -> Result<Outputs, OpError>;
    /// The outputs that are not `per_frame` (e.g. a frame count), known before the first frame.
    fn statics(&mut self, ctx: &RunContext) -> Result<Outputs, OpError> {
        let _ = ctx;
        Ok(Outputs::new())
    }
    /// A value fed back on the feedback input `port` (see [`PortSpec::feedback`]): what the
    /// stream computed from frame `index − 1`, delivered before `frame(ctx, index)` is asked
    /// for. Frame 0 gets nothing: the source starts from its own initial state. The default
    /// refuses, for sources without feedback ports.
    fn feed(
        &mut self,
        ctx: &RunContext,
        index: usize,
        port: &str,
        value: &Value,
    ) -> Result<(), OpError> {
        let _ = (ctx, index, value);
        Err(OpError::failed(format!(
            "this source takes no feedback on `{port}`"
        )))
    }
}

/// The state a sequence operator keeps between frames (see [`Operator::sequence`]).
///
/// A batch run feeds the elements of the whole lists in order ([`run_sequence_batch`]); a
/// stream feeds the same elements as they arrive. The same frames therefore give the same
/// results in both modes — the state must depend only on the frames and their `index`, never
/// on timing.
pub trait SequenceState: Send {
    /// One frame: the `per_frame` inputs hold this frame's element, the others their whole
    /// value. Returns this frame's element of every `per_frame` output.
    fn push(
        &mut self,
        ctx: &RunContext,
        packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError>;
    /// After the last frame: every output that is not `per_frame`.
    fn finish(&mut self, ctx: &RunContext) -> Result<Outputs, OpError>;
}

/// Runs a sequence operator on whole lists: every connected `per_frame` input must be a list of
/// the same length; elements are pushed in order (packet `index` = timestamp = position), the
/// `per_frame` outputs are collected into lists and the state's final outputs added.
pub fn run_sequence_batch(
    op: &dyn Operator,
    ctx: &RunContext,
    inputs: &Inputs<'_>,
    outputs: &[PortSpec],
) -> Result<Outputs, OpError> {
    let specs = inputs.specs();
    let values = inputs.values();
    let statics: Vec<Option<Value>> = specs
        .iter()
        .zip(values)
        .map(|(spec, v)| if spec.per_frame { None } else { v.clone() })
        .collect();
    let mut state = op
        .sequence(ctx, &Inputs::new(specs, &statics))
        .ok_or_else(|| OpError::failed("the operator has no sequence state"))??;
    let mut frames: Option<(usize, &str)> = None;
    for (spec, value) in specs.iter().zip(values) {
        if !spec.per_frame {
            continue;
        }
        let Some(value) = value else { continue };
        let Value::List(list) = value else {
            return Err(OpError::input(&spec.name, "expected a list of frames"));
        };
        match frames {
            None => frames = Some((list.items.len(), &spec.name)),
            Some((n, first)) if n != list.items.len() => {
                return Err(OpError::input(
                    &spec.name,
                    format!(
                        "frame lists differ in length: `{first}` has {n} frames, `{}` has {}",
                        spec.name,
                        list.items.len()
                    ),
                ));
            }
            Some(_) => {}
        }
    }
    let n = frames.map_or(0, |(n, _)| n);
    let per_frame: Vec<&PortSpec> = outputs.iter().filter(|s| s.per_frame).collect();
    let mut columns: Vec<Vec<Value>> = vec![Vec::with_capacity(n); per_frame.len()];
    let mut element = statics.clone();
    for k in 0..n {
        for ((slot, spec), value) in element.iter_mut().zip(specs).zip(values) {
            if spec.per_frame {
                *slot = match value {
                    Some(Value::List(list)) => list.items.get(k).cloned(),
                    _ => None,
                };
            }
        }
        let frame_ctx = RunContext {
            element: Some(k),
            ..ctx.clone()
        };
        let packet = Packet {
            index: k,
            timestamp_us: k as i64,
        };
        let mut out = state
            .push(&frame_ctx, packet, &Inputs::new(specs, &element))
            .map_err(|e| OpError::failed(format!("frame {k}: {e}")))?;
        for (column, spec) in columns.iter_mut().zip(&per_frame) {
            let value = out.take(&spec.name).ok_or_else(|| {
                OpError::failed(format!("frame {k}: no value for output `{}`", spec.name))
            })?;
            column.push(value);
        }
    }
    let mut result = state.finish(ctx)?;
    for (items, spec) in columns.into_iter().zip(per_frame) {
        let element = spec.ty.element().cloned().unwrap_or(PortType::Integer);
        result.set(&spec.name, Value::list(element, items));
    }
    Ok(result)
}

/// Builds operator instances from checked parameters.
pub trait OpFactory: Send + Sync {
    /// The operator's description.
    fn info(&self) -> &OpInfo;

    /// A configured instance. Cross-field checks that the schema cannot express (e.g. `low ≤
    /// high`) fail here, and the loader reports them at the node's `params` position.
    fn build(&self, params: &ParamMap) -> Result<Arc<dyn Operator>, String>;
}

/// A built-in operator: a struct with typed [`Params`], constructed from them.
///
/// Implementing this (plus [`Operator`]) is all a built-in needs; [`Registry::register`] wraps it
/// in a factory.
pub trait Op: Operator + Sized + 'static {
    /// Parameter struct (see [`params!`](crate::params!)).
    type Params: Params;
    /// `family.name`.
    const ID: &'static str;
    /// See [`OpInfo::version`].
    const VERSION: u32 = 1;
    /// One line.
    const SUMMARY: &'static str;
    /// Method, formula, references.
    const DOC: &'static str;
    /// See [`OpInfo::side_effects`].
    const SIDE_EFFECTS: bool = false;

    /// Input ports.
    fn inputs() -> Vec<PortSpec>;
    /// Output ports.
    fn outputs() -> Vec<PortSpec>;
    /// An instance with checked parameters; `Err` for cross-field problems.
    fn new(params: Self::Params) -> Result<Self, String>;

    /// The description built from the associated items.
    fn info() -> OpInfo {
        OpInfo {
            id: Self::ID.to_string(),
            version: Self::VERSION,
            summary: Self::SUMMARY.to_string(),
            doc: Self::DOC.trim().to_string(),
            inputs: Self::inputs(),
            outputs: Self::outputs(),
            params: Self::Params::schema(),
            side_effects: Self::SIDE_EFFECTS,
            origin: Origin::Builtin,
        }
    }
}

struct TypedFactory<T: Op> {
    info: OpInfo,
    _op: std::marker::PhantomData<fn() -> T>,
}

impl<T: Op> OpFactory for TypedFactory<T> {
    fn info(&self) -> &OpInfo {
        &self.info
    }

    fn build(&self, params: &ParamMap) -> Result<Arc<dyn Operator>, String> {
        let typed = T::Params::from_map(params)?;
        Ok(Arc::new(T::new(typed)?))
    }
}

/// Errors registering operators.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegistryError {
    /// Two operators claim one id.
    #[error("operator `{id}` is registered twice ({first} and {second})")]
    Duplicate {
        /// The id.
        id: String,
        /// Origin of the first.
        first: String,
        /// Origin of the second.
        second: String,
    },
    /// An id is not `family.name`.
    #[error("operator id `{0}` is not of the form `family.name` (lower-case letters, digits, `_`)")]
    BadId(String),
}

/// All known operators by id.
#[derive(Default, Clone)]
pub struct Registry {
    ops: BTreeMap<String, Arc<dyn OpFactory>>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Registry {
        Registry::default()
    }

    /// Registers a built-in operator type.
    pub fn register<T: Op>(&mut self) -> Result<(), RegistryError> {
        self.register_factory(Arc::new(TypedFactory::<T> {
            info: T::info(),
            _op: std::marker::PhantomData,
        }))
    }

    /// Registers any factory (plugins use this).
    pub fn register_factory(&mut self, factory: Arc<dyn OpFactory>) -> Result<(), RegistryError> {
        let id = factory.info().id.clone();
        if !valid_op_id(&id) {
            return Err(RegistryError::BadId(id));
        }
        if let Some(existing) = self.ops.get(&id) {
            return Err(RegistryError::Duplicate {
                id,
                first: existing.info().origin.to_string(),
                second: factory.info().origin.to_string(),
            });
        }
        self.ops.insert(id, factory);
        Ok(())
    }

    /// The factory for `id`.
    pub fn get(&self, id: &str) -> Option<&Arc<dyn OpFactory>> {
        self.ops.get(id)
    }

    /// All operator ids, sorted.
    pub fn ids(&self) -> impl Iterator<Item = &str> {
        self.ops.keys().map(String::as_str)
    }

    /// All factories, sorted by id.
    pub fn iter(&self) -> impl Iterator<Item = &Arc<dyn OpFactory>> {
        self.ops.values()
    }

    /// Number of operators.
    pub fn len(&self) -> usize {
        self.ops.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.ops.is_empty()
    }
}

/// `family.name`, each part `[a-z][a-z0-9_]*`.
pub fn valid_op_id(id: &str) -> bool {
    let part = |s: &str| {
        let mut chars = s.chars();
        chars.next().is_some_and(|c| c.is_ascii_lowercase())
            && chars.all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
    };
    matches!(id.split_once('.'), Some((family, name)) if part(family) && part(name))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::NoParams;

    struct Twice;

    impl Operator for Twice {
        fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
            Ok(Outputs::new().with("y", Value::Scalar(2.0 * inputs.scalar("x")?)))
        }
    }

    impl Op for Twice {
        type Params = NoParams;
        const ID: &'static str = "test.twice";
        const SUMMARY: &'static str = "Doubles a number.";
        const DOC: &'static str = "y = 2x";
        fn inputs() -> Vec<PortSpec> {
            vec![PortSpec::new("x", PortType::Scalar, "input")]
        }
        fn outputs() -> Vec<PortSpec> {
            vec![PortSpec::new("y", PortType::Scalar, "output")]
        }
        fn new(_: NoParams) -> Result<Self, String> {
            Ok(Twice)
        }
    }

    #[test]
    fn registry_builds_and_runs() {
        let mut reg = Registry::new();
        reg.register::<Twice>().unwrap();
        assert!(matches!(
            reg.register::<Twice>(),
            Err(RegistryError::Duplicate { .. })
        ));
        let factory = reg.get("test.twice").unwrap();
        assert_eq!(factory.info().family(), "test");
        let op = factory.build(&ParamMap::new()).unwrap();
        let specs = Twice::inputs();
        let values = [Some(Value::Scalar(4.0))];
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        assert_eq!(out.take("y"), Some(Value::Scalar(8.0)));
    }

    #[test]
    fn op_ids() {
        assert!(valid_op_id("filter.gaussian"));
        assert!(valid_op_id("io.read_image"));
        assert!(!valid_op_id("filter"));
        assert!(!valid_op_id("Filter.gaussian"));
        assert!(!valid_op_id("filter.gauss.ian"));
        assert!(!valid_op_id(".x"));
    }

    #[test]
    fn inputs_report_wrong_types() {
        let specs = vec![PortSpec::new("x", PortType::Scalar, "")];
        let values = [Some(Value::Bool(true))];
        let inputs = Inputs::new(&specs, &values);
        let err = inputs.scalar("x").unwrap_err().to_string();
        assert!(err.contains("expected Scalar, got Bool"), "{err}");
        assert!(inputs.image("missing").is_err());
    }
}
