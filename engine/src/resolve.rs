//! Validation: turns a [`GraphSpec`] into a runnable [`Graph`], reporting every problem at once —
//! unknown operators, ports and parameters (with the nearest valid name), parameter types and
//! ranges, edge type mismatches, missing inputs, dangling references, cycles and subgraph files.
//!
//! Subgraph nodes (`op: "graph", params: (path: "sub.ron")`) are inlined: their nodes join the
//! graph under `NODE/inner` names, and the subgraph's declared `outputs` become the node's ports.
//! A subgraph may declare typed `inputs: { "image": "Image" }`, referenced inside it as
//! `inputs.image` and fed by the subgraph node's `inputs`.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::diag::{Code, Diagnostic, Diagnostics, SourceFile, suggest};
use crate::graph::{EdgeSource, Graph, GraphOutput, InputEdge, Location, Node, PortRef, Tap};
use crate::op::Registry;
use crate::params::{ParamMap, ParamSpec, ParamType, ParamValue};
use crate::ron_syntax::{self, RonValue, Span, Spanned};
use crate::spec::{GraphSpec, InputRef, NodeSpec, graph_from_ron, split_index, split_reference};
use crate::types::PortType;

/// The pseudo-operator that includes another graph file.
pub const SUBGRAPH_OP: &str = "graph";
/// The reserved node name through which a subgraph reads its declared inputs.
pub const SUBGRAPH_INPUTS: &str = "inputs";
/// Deepest subgraph nesting accepted.
pub const MAX_SUBGRAPH_DEPTH: usize = 32;
/// Largest graph file read.
pub const MAX_GRAPH_FILE_BYTES: u64 = 16 << 20;

/// A `--set NODE.PARAM=VALUE` override, checked like the file itself.
#[derive(Debug, Clone)]
pub struct Override {
    /// Node path; `sub/inner` reaches into subgraph node `sub`.
    pub node: Spanned<String>,
    /// Parameter name.
    pub param: Spanned<String>,
    /// The value.
    pub value: Spanned<RonValue>,
    /// The argument text, for diagnostics.
    pub source: Arc<SourceFile>,
}

impl Override {
    /// Parses `NODE.PARAM=VALUE`. `VALUE` is RON; a bare word (or anything that is not valid RON)
    /// is taken as a string.
    pub fn parse(arg: &str) -> Result<Override, Box<Diagnostic>> {
        let source = SourceFile::new("--set", None, arg);
        let bad = |span: Span, msg: &str| {
            Box::new(
                Diagnostic::at(Code::BadOverride, &source, span, msg.to_string())
                    .help("write `--set NODE.PARAM=VALUE`, e.g. `--set blur.sigma=2.5`"),
            )
        };
        let Some(eq) = arg.find('=') else {
            return Err(bad(Span::new(0, arg.len()), "missing `=` in --set"));
        };
        let key = &arg[..eq];
        let Some(dot) = key.rfind('.') else {
            return Err(bad(
                Span::new(0, eq),
                "missing `.` between node and parameter in --set",
            ));
        };
        let (node, param) = (&key[..dot], &key[dot + 1..]);
        if node.is_empty() || param.is_empty() {
            return Err(bad(
                Span::new(0, eq),
                "empty node or parameter name in --set",
            ));
        }
        let value_text = &arg[eq + 1..];
        let offset = eq + 1;
        let value = match ron_syntax::parse(value_text) {
            Ok(v) => match v.value {
                RonValue::Ident(word) => Spanned {
                    value: RonValue::Str(word),
                    span: v.span,
                },
                _ => v,
            },
            Err(_) => Spanned {
                value: RonValue::Str(value_text.to_string()),
                span: Span::new(0, value_text.len()),
            },
        };
        Ok(Override {
            node: Spanned {
                value: node.to_string(),
                span: Span::new(0, dot),
            },
            param: Spanned {
                value: param.to_string(),
                span: Span::new(dot + 1, eq),
            },
            value: shift(value, offset),
            source,
        })
    }
}

/// Moves every span of a value by `offset` bytes.
fn shift(v: Spanned<RonValue>, offset: usize) -> Spanned<RonValue> {
    let span = Span::new(v.span.start + offset, v.span.end + offset);
    let sh = |n: Spanned<String>| Spanned {
        value: n.value,
        span: Span::new(n.span.start + offset, n.span.end + offset),
    };
    let value = match v.value {
        RonValue::Option(Some(inner)) => RonValue::Option(Some(Box::new(shift(*inner, offset)))),
        RonValue::List(items) => {
            RonValue::List(items.into_iter().map(|i| shift(i, offset)).collect())
        }
        RonValue::Map(entries) => RonValue::Map(
            entries
                .into_iter()
                .map(|(k, v)| (shift(k, offset), shift(v, offset)))
                .collect(),
        ),
        RonValue::Struct { name, fields } => RonValue::Struct {
            name: name.map(sh),
            fields: fields
                .into_iter()
                .map(|(k, v)| (sh(k), shift(v, offset)))
                .collect(),
        },
        RonValue::Tuple { name, items } => RonValue::Tuple {
            name: name.map(sh),
            items: items.into_iter().map(|i| shift(i, offset)).collect(),
        },
        other => other,
    };
    Spanned { value, span }
}

/// Reads a graph file as text, reporting unreadable or non-UTF-8 files as diagnostics.
pub fn read_source(path: &Path, display_name: &str) -> Result<Arc<SourceFile>, Box<Diagnostic>> {
    let bytes =
        crate::limits::read_capped(path, MAX_GRAPH_FILE_BYTES, "graph files").map_err(|e| {
            Box::new(Diagnostic::bare(
                Code::Io,
                format!("cannot read graph file `{display_name}`: {e}"),
            ))
        })?;
    match String::from_utf8(bytes) {
        Ok(text) => Ok(SourceFile::new(
            display_name,
            Some(path.to_path_buf()),
            text,
        )),
        Err(e) => {
            let offset = e.utf8_error().valid_up_to();
            let text = String::from_utf8_lossy(e.as_bytes()).into_owned();
            // Map the byte offset into the lossy text: the prefix is unchanged.
            let source = SourceFile::new(display_name, Some(path.to_path_buf()), text);
            let end = source.text[offset..]
                .chars()
                .next()
                .map_or(offset, |c| offset + c.len_utf8());
            Err(Box::new(
                Diagnostic::at(
                    Code::Encoding,
                    &source,
                    Span::new(offset, end),
                    "the file is not valid UTF-8",
                )
                .label("invalid byte here")
                .help("graph files are UTF-8 RON text"),
            ))
        }
    }
}

/// Parses a source into a [`GraphSpec`], reporting syntax and shape problems.
pub fn parse_spec(source: &Arc<SourceFile>, diags: &mut Diagnostics) -> Option<GraphSpec> {
    match ron_syntax::parse(&source.text) {
        Ok(doc) => graph_from_ron(source, &doc, diags),
        Err(e) => {
            let mut d = Diagnostic::at(
                Code::Syntax,
                source,
                e.span,
                format!("malformed RON: {}", e.message),
            )
            .label("here");
            if let Some(help) = e.help {
                d = d.help(help);
            }
            diags.push(d);
            None
        }
    }
}

/// Loads, checks and resolves a graph file.
pub fn load_graph(
    registry: &Registry,
    path: &Path,
    overrides: &[Override],
) -> Result<Graph, Diagnostics> {
    let name = path.to_string_lossy().into_owned();
    let source = read_source(path, &name).map_err(|d| Diagnostics(vec![*d]))?;
    load_source(registry, &source, overrides)
}

/// Like [`load_graph`], but first loads the plugins the graph lists in `plugins: [...]` (paths
/// relative to the graph file) into `registry`. With `allow_plugins` false, a graph that lists
/// plugins is refused. A plugin that fails to load is a diagnostic at its string in the file.
/// Only the top-level file may list plugins; a subgraph that lists any is an error.
pub fn load_graph_with_plugins(
    registry: &mut Registry,
    path: &Path,
    overrides: &[Override],
    allow_plugins: bool,
) -> Result<Graph, Diagnostics> {
    let name = path.to_string_lossy().into_owned();
    let source = read_source(path, &name).map_err(|d| Diagnostics(vec![*d]))?;
    let mut scratch = Diagnostics::default();
    if let Some(spec) = parse_spec(&source, &mut scratch) {
        let mut diags = Diagnostics::default();
        for plugin in &spec.plugins {
            if !allow_plugins {
                diags.push(
                    Diagnostic::at(
                        Code::Plugin,
                        &source,
                        plugin.span,
                        format!(
                            "the graph needs plugin `{}`, but plugins are disabled",
                            plugin.value
                        ),
                    )
                    .label("plugin listed here")
                    .help("run without `--no-plugins` to load it"),
                );
                continue;
            }
            let file = source.base_dir().join(&plugin.value);
            if let Err(e) = crate::plugin::load_plugin(&file, registry) {
                diags.push(
                    Diagnostic::at(Code::Plugin, &source, plugin.span, e.to_string())
                        .label("this plugin could not be loaded"),
                );
            }
        }
        if !diags.is_empty() {
            return Err(diags);
        }
    }
    load_source(registry, &source, overrides)
}

/// Checks and resolves a graph from an already-read source.
pub fn load_source(
    registry: &Registry,
    source: &Arc<SourceFile>,
    overrides: &[Override],
) -> Result<Graph, Diagnostics> {
    let mut diags = Diagnostics::default();
    let Some(spec) = parse_spec(source, &mut diags) else {
        return Err(diags);
    };
    let mut ctx = Resolver {
        registry,
        diags,
        nodes: Vec::new(),
        include_stack: source.path.iter().map(|p| canonical(p)).collect(),
    };
    for (name, _) in &spec.inputs {
        ctx.diags.push(
            Diagnostic::at(
                Code::Subgraph,
                source,
                name.span,
                format!("graph input `{}` is not bound", name.value),
            )
            .label("declared here")
            .help("a graph with `inputs` is a subgraph: include it with `(op: \"graph\", params: (path: \"...\"), inputs: { ... })`"),
        );
    }
    let scope_inputs = HashMap::new();
    let overrides: Vec<&Override> = overrides.iter().collect();
    let exports = ctx.resolve_scope(&spec, "", &scope_inputs, &overrides, 0);
    let mut outputs = Vec::new();
    for (name, reference) in &spec.outputs {
        match exports.get(&name.value) {
            Some(Source::Port(tap, ty)) => outputs.push(GraphOutput {
                name: name.value.clone(),
                from: tap.from,
                index: tap.index,
                ty: ty.clone(),
            }),
            Some(Source::List { .. }) => ctx.diags.push(
                Diagnostic::at(
                    Code::BadReference,
                    source,
                    reference.span,
                    format!(
                        "output `{}` is a list literal; a graph output names one port",
                        name.value
                    ),
                )
                .label("a list literal")
                .help("feed the list to a node and output that node's port"),
            ),
            _ => {}
        }
    }
    if !ctx.diags.is_empty() {
        ctx.diags.sort();
        return Err(ctx.diags);
    }
    let fallback_name = source
        .path
        .as_deref()
        .and_then(Path::file_stem)
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "graph".into());
    Ok(Graph {
        name: spec.name.map_or(fallback_name, |n| n.value),
        description: spec.description.map(|d| d.value).unwrap_or_default(),
        nodes: ctx.nodes,
        outputs,
    })
}

fn canonical(path: &Path) -> PathBuf {
    path.canonicalize().unwrap_or_else(|_| path.to_path_buf())
}

/// What a reference resolves to.
#[derive(Debug, Clone)]
enum Source {
    /// A typed port (or one element of it) of a runnable node.
    Port(Tap, PortType),
    /// A list literal of runnable ports: `ty` is `List<element>`.
    List {
        items: Vec<Tap>,
        element: PortType,
        ty: PortType,
    },
    /// A typed port of a node that has its own errors: downstream type checks still happen, but
    /// the consumer cannot run.
    Typed(PortType),
    /// Something upstream is unknown (e.g. an unknown operator); don't pile on more errors.
    Poisoned,
}

impl Source {
    fn ty(&self) -> Option<&PortType> {
        match self {
            Source::Port(_, t) | Source::Typed(t) | Source::List { ty: t, .. } => Some(t),
            Source::Poisoned => None,
        }
    }
}

/// A resolved node of one scope.
enum Slot {
    /// Not yet resolved (or unreachable because of a cycle).
    Pending,
    /// An operator node.
    Op { index: usize },
    /// An operator node with errors of its own: its ports are known, but it will not run.
    Invalid {
        info: Arc<crate::op::OpInfo>,
        output_types: Vec<PortType>,
    },
    /// A subgraph node: its exported outputs.
    Subgraph {
        exports: Exports,
        names: Vec<String>,
    },
    /// Had errors.
    Failed,
}

struct Resolver<'a> {
    registry: &'a Registry,
    diags: Diagnostics,
    nodes: Vec<Node>,
    include_stack: Vec<PathBuf>,
}

type Exports = HashMap<String, Source>;

impl Resolver<'_> {
    /// Resolves the nodes of one graph file, appending them in topological order; returns its
    /// outputs by name (`None` for outputs whose source failed).
    fn resolve_scope(
        &mut self,
        spec: &GraphSpec,
        prefix: &str,
        scope_inputs: &HashMap<String, Source>,
        overrides: &[&Override],
        depth: usize,
    ) -> Exports {
        let source = Arc::clone(&spec.source);
        let index: HashMap<&str, usize> = spec
            .nodes
            .iter()
            .enumerate()
            .map(|(i, n)| (n.name.value.as_str(), i))
            .collect();
        self.check_override_targets(spec, &index, overrides);

        // Dependencies by name, for ordering and cycle detection.
        let mut deps: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); spec.nodes.len()];
        for (i, node) in spec.nodes.iter().enumerate() {
            for reference in node.inputs.iter().flat_map(|(_, r)| r.references()) {
                if let Ok((base, _)) = split_index(&reference.value)
                    && let Some((target, _)) = split_reference(base)
                    && let Some(&j) = index.get(target)
                {
                    deps[i].insert(j);
                }
            }
        }
        self.report_cycles(spec, &deps);

        let mut slots: Vec<Slot> = spec.nodes.iter().map(|_| Slot::Pending).collect();
        for i in topological_order(&deps) {
            let node = &spec.nodes[i];
            let node_overrides: Vec<&Override> = overrides
                .iter()
                .copied()
                .filter(|o| first_segment(&o.node.value) == node.name.value)
                .collect();
            slots[i] = if node.op.value == SUBGRAPH_OP {
                self.resolve_subgraph(
                    spec,
                    node,
                    &index,
                    &slots,
                    scope_inputs,
                    &node_overrides,
                    prefix,
                    depth,
                )
            } else {
                self.resolve_op(
                    spec,
                    node,
                    &index,
                    &slots,
                    scope_inputs,
                    &node_overrides,
                    prefix,
                )
            };
        }

        let mut exports = Exports::new();
        for (name, reference) in &spec.outputs {
            let resolved =
                self.resolve_reference(&source, reference, &index, &slots, scope_inputs, "output");
            exports.insert(name.value.clone(), resolved.unwrap_or(Source::Poisoned));
        }
        exports
    }

    fn check_override_targets(
        &mut self,
        spec: &GraphSpec,
        index: &HashMap<&str, usize>,
        overrides: &[&Override],
    ) {
        for o in overrides {
            let first = first_segment(&o.node.value);
            if !index.contains_key(first) {
                let hint =
                    suggest(first, index.keys().copied()).map(|s| format!("did you mean `{s}`?"));
                let scope = spec.source.name.clone();
                self.diags.push(
                    Diagnostic::at(
                        Code::BadOverride,
                        &o.source,
                        o.node.span,
                        format!("--set names node `{first}`, which is not in {scope}"),
                    )
                    .label("unknown node")
                    .maybe_help(hint),
                );
            }
        }
    }

    fn report_cycles(&mut self, spec: &GraphSpec, deps: &[BTreeSet<usize>]) {
        let mut g = petgraph::graph::DiGraph::<usize, ()>::new();
        let ids: Vec<_> = (0..deps.len()).map(|i| g.add_node(i)).collect();
        for (i, d) in deps.iter().enumerate() {
            for &j in d {
                g.add_edge(ids[j], ids[i], ());
            }
        }
        let mut cycles: Vec<Vec<usize>> = petgraph::algo::tarjan_scc(&g)
            .into_iter()
            .map(|scc| {
                let mut members: Vec<usize> = scc.iter().map(|&n| g[n]).collect();
                members.sort_unstable();
                members
            })
            .filter(|members| members.len() > 1 || deps[members[0]].contains(&members[0]))
            .collect();
        cycles.sort();
        for members in cycles {
            let names: Vec<String> = members
                .iter()
                .map(|&m| format!("`{}`", spec.nodes[m].name.value))
                .collect();
            let first = &spec.nodes[members[0]];
            let mut d = Diagnostic::at(
                Code::Cycle,
                &spec.source,
                first.name.span,
                format!("dependency cycle: {}", cycle_text(&members, deps, spec)),
            )
            .label("part of the cycle")
            .help(format!(
                "a graph must be acyclic; break the cycle between {}",
                names.join(", ")
            ));
            for &m in &members[1..] {
                d = d.related(spec.nodes[m].name.span, "also in the cycle");
            }
            self.diags.push(d);
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn resolve_op(
        &mut self,
        spec: &GraphSpec,
        node: &NodeSpec,
        index: &HashMap<&str, usize>,
        slots: &[Slot],
        scope_inputs: &HashMap<String, Source>,
        overrides: &[&Override],
        prefix: &str,
    ) -> Slot {
        let source = &spec.source;
        let Some(factory) = self.registry.get(&node.op.value) else {
            let candidates = self.registry.ids().chain(std::iter::once(SUBGRAPH_OP));
            let hint = match suggest(&node.op.value, candidates) {
                Some(s) => format!("did you mean `{s}`?"),
                None => "`ocellus ops` lists every operator".to_string(),
            };
            self.diags.push(
                Diagnostic::at(
                    Code::UnknownOp,
                    source,
                    node.op.span,
                    format!("unknown operator `{}`", node.op.value),
                )
                .label("no such operator")
                .help(hint),
            );
            // Still check references, so dangling ones are reported too.
            for (_, input) in &node.inputs {
                self.resolve_input(source, input, index, slots, scope_inputs);
            }
            return Slot::Failed;
        };
        let factory = Arc::clone(factory);
        let info = Arc::new(factory.info().clone());
        let errors_before = self.diags.len();
        for o in overrides.iter().filter(|o| o.node.value.contains('/')) {
            self.diags.push(
                Diagnostic::at(
                    Code::BadOverride,
                    &o.source,
                    o.node.span,
                    format!("`{}` is an operator node, not a subgraph", node.name.value),
                )
                .label("not a subgraph")
                .help(format!("write `--set {}.PARAM=VALUE`", node.name.value)),
            );
        }
        let params = self.check_params(source, node, &info.params, overrides);

        let mut inputs: Vec<Option<InputEdge>> = vec![None; info.inputs.len()];
        let mut poisoned = false;
        for (port, input) in &node.inputs {
            let resolved = self.resolve_input(source, input, index, slots, scope_inputs);
            let Some(port_index) = info.inputs.iter().position(|p| p.name == port.value) else {
                let names: Vec<&str> = info.inputs.iter().map(|p| p.name.as_str()).collect();
                self.diags.push(unknown_name_diag(
                    Code::UnknownInput,
                    source,
                    port,
                    &format!("operator `{}` has no input `{}`", info.id, port.value),
                    "no such input",
                    &names,
                    "inputs",
                ));
                continue;
            };
            let expected = &info.inputs[port_index].ty;
            let Some(ty) = resolved.as_ref().and_then(Source::ty) else {
                poisoned = true;
                continue;
            };
            let mapped = if ty == expected {
                false
            } else if ty.element() == Some(expected) {
                true
            } else {
                self.diags.push(type_mismatch(
                    source,
                    &input.as_text(),
                    ty,
                    &node.name.value,
                    port,
                    expected,
                ));
                continue;
            };
            match resolved {
                Some(Source::Port(tap, _)) => {
                    inputs[port_index] = Some(InputEdge {
                        source: EdgeSource::Tap(tap),
                        mapped,
                    })
                }
                Some(Source::List { items, element, .. }) => {
                    inputs[port_index] = Some(InputEdge {
                        source: EdgeSource::List { items, element },
                        mapped,
                    })
                }
                _ => poisoned = true,
            }
        }
        let connected: BTreeSet<&str> = node.inputs.iter().map(|(p, _)| p.value.as_str()).collect();
        let missing: Vec<String> = info
            .inputs
            .iter()
            .filter(|p| !p.optional && !connected.contains(p.name.as_str()))
            .map(|p| format!("`{}` ({})", p.name, p.ty))
            .collect();
        if !missing.is_empty() {
            let plural = if missing.len() > 1 { "s" } else { "" };
            self.diags.push(
                Diagnostic::at(
                    Code::MissingInput,
                    source,
                    node.name.span,
                    format!(
                        "node `{}` ({}) is missing required input{plural} {}",
                        node.name.value,
                        info.id,
                        missing.join(", ")
                    ),
                )
                .label("missing input")
                .help(format!(
                    "connect it with `inputs: {{ \"{}\": \"other_node.port\" }}`",
                    info.inputs
                        .iter()
                        .find(|p| !p.optional && !connected.contains(p.name.as_str()))
                        .map_or("port", |p| p.name.as_str())
                )),
            );
        }
        let mapped = inputs.iter().flatten().any(|e| e.mapped);
        let output_types: Vec<PortType> = info
            .outputs
            .iter()
            .map(|p| {
                if mapped {
                    p.ty.clone().list_of()
                } else {
                    p.ty.clone()
                }
            })
            .collect();
        let invalid = Slot::Invalid {
            info: Arc::clone(&info),
            output_types: output_types.clone(),
        };
        let Some(params) = params else {
            return invalid;
        };
        let op = match factory.build(&params) {
            Ok(op) => op,
            Err(message) => {
                self.diags.push(
                    Diagnostic::at(
                        Code::ParamInvalid,
                        source,
                        node.params_span,
                        format!("invalid parameters for `{}`: {message}", node.name.value),
                    )
                    .label("these parameters"),
                );
                return invalid;
            }
        };
        if poisoned || self.diags.len() > errors_before {
            return invalid;
        }
        self.nodes.push(Node {
            name: format!("{prefix}{}", node.name.value),
            info,
            op,
            params,
            inputs,
            output_types,
            location: Some(Location {
                source: Arc::clone(source),
                span: node.name.span,
            }),
        });
        Slot::Op {
            index: self.nodes.len() - 1,
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn resolve_subgraph(
        &mut self,
        spec: &GraphSpec,
        node: &NodeSpec,
        index: &HashMap<&str, usize>,
        slots: &[Slot],
        scope_inputs: &HashMap<String, Source>,
        overrides: &[&Override],
        prefix: &str,
        depth: usize,
    ) -> Slot {
        let source = &spec.source;
        let own: Vec<&Override> = overrides
            .iter()
            .copied()
            .filter(|o| !o.node.value.contains('/'))
            .collect();
        let inner: Vec<Override> = overrides
            .iter()
            .filter_map(|o| {
                let (_, rest) = o.node.value.split_once('/')?;
                let mut o = (*o).clone();
                o.node.value = rest.to_string();
                Some(o)
            })
            .collect();
        let schema = [ParamSpec::new(
            "path",
            &PathBuf::new(),
            "The graph file to include, relative to this file.",
        )];
        let Some(params) = self.check_params(source, node, &schema, &own) else {
            return Slot::Failed;
        };
        let path = match params.get("path") {
            Some(ParamValue::Str(p)) if !p.is_empty() => PathBuf::from(p),
            _ => {
                self.diags.push(
                    Diagnostic::at(
                        Code::Subgraph,
                        source,
                        node.params_span,
                        format!("subgraph node `{}` needs `path`", node.name.value),
                    )
                    .label("missing `path`")
                    .help("write `params: (path: \"other.ron\")`"),
                );
                return Slot::Failed;
            }
        };
        let path_span = node
            .params
            .iter()
            .find(|(k, _)| k.value == "path")
            .map_or(node.params_span, |(_, v)| v.span);
        let path_source = own
            .iter()
            .find(|o| o.param.value == "path")
            .map(|o| (Arc::clone(&o.source), o.value.span))
            .unwrap_or_else(|| (Arc::clone(source), path_span));
        let key = canonical(&path);
        if depth >= MAX_SUBGRAPH_DEPTH || self.include_stack.contains(&key) {
            let chain: Vec<String> = self
                .include_stack
                .iter()
                .chain(std::iter::once(&key))
                .map(|p| p.display().to_string())
                .collect();
            self.diags.push(
                Diagnostic::at(
                    Code::Subgraph,
                    &path_source.0,
                    path_source.1,
                    format!("subgraph `{}` includes itself", path.display()),
                )
                .label("recursive include")
                .help(format!("include chain: {}", chain.join(" → "))),
            );
            return Slot::Failed;
        }
        let sub_source = match read_source(&path, &path.to_string_lossy()) {
            Ok(s) => s,
            Err(d) if d.source.is_none() => {
                self.diags.push(
                    Diagnostic::at(
                        Code::Subgraph,
                        &path_source.0,
                        path_source.1,
                        format!("missing subgraph file `{}`", path.display()),
                    )
                    .label("cannot read this file")
                    .help(d.message),
                );
                return Slot::Failed;
            }
            Err(d) => {
                self.diags.push(*d);
                return Slot::Failed;
            }
        };
        let Some(sub_spec) = parse_spec(&sub_source, &mut self.diags) else {
            return Slot::Failed;
        };
        // Plugins are loaded once, before validation, from the top-level graph only: a subgraph
        // that names its own would otherwise be silently ignored.
        for plugin in &sub_spec.plugins {
            self.diags.push(
                Diagnostic::at(
                    Code::Plugin,
                    &sub_source,
                    plugin.span,
                    format!("subgraph `{}` lists plugin `{}`", path.display(), plugin.value),
                )
                .label("plugins are loaded by the top-level graph")
                .help("move this entry to the `plugins` list of the top-level graph, or pass it with `--plugin`"),
            );
        }

        if let Some(section) = &sub_spec.animation {
            self.diags.push(
                Diagnostic::at(
                    Code::Animation,
                    &sub_source,
                    crate::spec::head_span(section),
                    format!("subgraph `{}` has an `animation` section", path.display()),
                )
                .label("only the top-level graph has a timeline")
                .help("move the tracks to the top-level graph's `animation`, naming `sub/inner.param`"),
            );
        }

        if let Some(section) = &sub_spec.stream {
            self.diags.push(
                Diagnostic::at(
                    Code::Stream,
                    &sub_source,
                    crate::spec::head_span(section),
                    format!("subgraph `{}` has a `stream` section", path.display()),
                )
                .label("only the top-level graph says how it streams")
                .help("move the `stream` section to the top-level graph"),
            );
        }

        // Bind the subgraph's declared inputs.
        let mut bound: HashMap<String, Source> = HashMap::new();
        let mut ok = true;
        for (name, ty_text) in &sub_spec.inputs {
            let Some(declared) = PortType::parse(&ty_text.value) else {
                self.diags.push(
                    Diagnostic::at(
                        Code::Shape,
                        &sub_source,
                        ty_text.span,
                        format!("unknown type `{}`", ty_text.value),
                    )
                    .label("not a port type")
                    .maybe_help(
                        suggest(
                            &ty_text.value,
                            crate::types::SCALAR_PORT_TYPES
                                .iter()
                                .map(PortType::base_name),
                        )
                        .map(|s| format!("did you mean `{s}`?")),
                    ),
                );
                ok = false;
                continue;
            };
            let given = node.inputs.iter().find(|(p, _)| p.value == name.value);
            let Some((port, input)) = given else {
                self.diags.push(
                    Diagnostic::at(
                        Code::MissingInput,
                        source,
                        node.name.span,
                        format!(
                            "subgraph node `{}` is missing input `{}` ({declared})",
                            node.name.value, name.value
                        ),
                    )
                    .label("missing input"),
                );
                ok = false;
                continue;
            };
            match self.resolve_input(source, input, index, slots, scope_inputs) {
                Some(src) if src.ty() == Some(&declared) => {
                    ok &= matches!(src, Source::Port(..) | Source::List { .. });
                    bound.insert(name.value.clone(), src);
                }
                Some(src) => {
                    if let Some(ty) = src.ty() {
                        self.diags.push(type_mismatch(
                            source,
                            &input.as_text(),
                            ty,
                            &node.name.value,
                            port,
                            &declared,
                        ));
                    }
                    ok = false;
                }
                None => ok = false,
            }
        }
        // Inputs that failed to bind are still declared: the subgraph must not report them as
        // unknown, only skip what depends on them.
        for (name, _) in &sub_spec.inputs {
            bound.entry(name.value.clone()).or_insert(Source::Poisoned);
        }
        for (port, _) in &node.inputs {
            if !sub_spec.inputs.iter().any(|(n, _)| n.value == port.value) {
                let names: Vec<&str> = sub_spec
                    .inputs
                    .iter()
                    .map(|(n, _)| n.value.as_str())
                    .collect();
                self.diags.push(unknown_name_diag(
                    Code::UnknownInput,
                    source,
                    port,
                    &format!(
                        "subgraph `{}` has no input `{}`",
                        path.display(),
                        port.value
                    ),
                    "no such input",
                    &names,
                    "inputs",
                ));
                ok = false;
            }
        }
        let names: Vec<String> = sub_spec
            .outputs
            .iter()
            .map(|(n, _)| n.value.clone())
            .collect();
        let inner_refs: Vec<&Override> = inner.iter().collect();
        self.include_stack.push(key);
        let exports = self.resolve_scope(
            &sub_spec,
            &format!("{prefix}{}/", node.name.value),
            &bound,
            &inner_refs,
            depth + 1,
        );
        self.include_stack.pop();
        if !ok {
            return Slot::Failed;
        }
        Slot::Subgraph { exports, names }
    }

    /// Resolves a node input: one reference, or a list literal of references of one type.
    fn resolve_input(
        &mut self,
        source: &Arc<SourceFile>,
        input: &InputRef,
        index: &HashMap<&str, usize>,
        slots: &[Slot],
        scope_inputs: &HashMap<String, Source>,
    ) -> Option<Source> {
        let (items, span) = match input {
            InputRef::One(r) => {
                return self.resolve_reference(source, r, index, slots, scope_inputs, "input");
            }
            InputRef::List { items, span } => (items, *span),
        };
        if items.is_empty() {
            self.diags.push(
                Diagnostic::at(Code::BadReference, source, span, "empty input list `[]`")
                    .label("no references")
                    .help("a list literal names at least one output, e.g. [\"left.image\", \"right.image\"]"),
            );
            return None;
        }
        let mut first: Option<(&Spanned<String>, PortType)> = None;
        let mut taps = Vec::with_capacity(items.len());
        let (mut ok, mut runnable, mut poisoned) = (true, true, false);
        for item in items {
            let Some(src) =
                self.resolve_reference(source, item, index, slots, scope_inputs, "input")
            else {
                ok = false;
                continue;
            };
            let ty = match &src {
                Source::Poisoned => {
                    poisoned = true;
                    continue;
                }
                Source::List { .. } => {
                    self.diags.push(
                        Diagnostic::at(
                            Code::BadReference,
                            source,
                            item.span,
                            format!("`{}` is itself a list literal", item.value),
                        )
                        .label("a list literal inside a list literal")
                        .help("list literals cannot be nested"),
                    );
                    ok = false;
                    continue;
                }
                Source::Port(_, t) | Source::Typed(t) => t.clone(),
            };
            match &first {
                None => first = Some((item, ty.clone())),
                Some((f, fty)) if *fty != ty => {
                    self.diags.push(
                        Diagnostic::at(
                            Code::TypeMismatch,
                            source,
                            item.span,
                            format!(
                                "type mismatch in list: `{}` is {ty}, but `{}` is {fty}",
                                item.value, f.value
                            ),
                        )
                        .label(format!("this is {ty}"))
                        .related(f.span, format!("the list's first element is {fty}"))
                        .help("every element of a list literal has the same type"),
                    );
                    ok = false;
                    continue;
                }
                Some(_) => {}
            }
            match src {
                Source::Port(tap, _) => taps.push(tap),
                _ => runnable = false,
            }
        }
        if !ok {
            return None;
        }
        if poisoned {
            return Some(Source::Poisoned);
        }
        let (_, element) = first?;
        let ty = element.clone().list_of();
        Some(if runnable {
            Source::List {
                items: taps,
                element,
                ty,
            }
        } else {
            Source::Typed(ty)
        })
    }

    /// Resolves `node.port` or `node.port[i]` in a scope, reporting malformed, dangling,
    /// unknown-port and non-list-indexed references.
    fn resolve_reference(
        &mut self,
        source: &Arc<SourceFile>,
        reference: &Spanned<String>,
        index: &HashMap<&str, usize>,
        slots: &[Slot],
        scope_inputs: &HashMap<String, Source>,
        what: &str,
    ) -> Option<Source> {
        let (base, element) = match split_index(&reference.value) {
            Ok(split) => split,
            Err(why) => {
                self.diags.push(
                    Diagnostic::at(
                        Code::BadReference,
                        source,
                        reference.span,
                        format!(
                            "malformed {what} reference `{}`: {why}",
                            reference.value
                        ),
                    )
                    .label("expected `node.port` or `node.port[index]`")
                    .help("an index selects one element of a list output: \"detect.keypoints[0]\", or \"detect.keypoints[-1]\" for the last"),
                );
                return None;
            }
        };
        let resolved =
            self.resolve_port_reference(source, reference, base, index, slots, scope_inputs, what)?;
        match element {
            None => Some(resolved),
            Some(i) => self.index_source(source, reference, base, resolved, i),
        }
    }

    /// Applies `[i]` to a resolved reference.
    fn index_source(
        &mut self,
        source: &Arc<SourceFile>,
        reference: &Spanned<String>,
        base: &str,
        resolved: Source,
        i: i64,
    ) -> Option<Source> {
        let not_a_list = |ty: &PortType| {
            Diagnostic::at(
                Code::TypeMismatch,
                source,
                reference.span,
                format!("`{base}` is {ty}, not a list: it cannot be indexed with `[{i}]`"),
            )
            .label(format!("this is {ty}"))
            .help(format!(
                "only list outputs can be indexed; write \"{base}\""
            ))
        };
        match resolved {
            Source::Poisoned => Some(Source::Poisoned),
            Source::Typed(ty) => match ty.element() {
                Some(element) => Some(Source::Typed(element.clone())),
                None => {
                    self.diags.push(not_a_list(&ty));
                    None
                }
            },
            Source::Port(tap, ty) => {
                let Some(element) = ty.element() else {
                    self.diags.push(not_a_list(&ty));
                    return None;
                };
                if tap.index.is_some() {
                    self.diags.push(
                        Diagnostic::at(
                            Code::BadReference,
                            source,
                            reference.span,
                            format!("`{base}` already selects one list element; it cannot be indexed again"),
                        )
                        .label("indexed twice"),
                    );
                    return None;
                }
                Some(Source::Port(
                    Tap {
                        from: tap.from,
                        index: Some(i),
                    },
                    element.clone(),
                ))
            }
            Source::List { items, element, .. } => match list_position(items.len(), i) {
                Some(k) => Some(Source::Port(items[k], element)),
                None => {
                    self.diags.push(
                        Diagnostic::at(
                            Code::BadReference,
                            source,
                            reference.span,
                            format!(
                                "index {i} is out of range for `{base}`, a list of {} elements",
                                items.len()
                            ),
                        )
                        .label("out of range"),
                    );
                    None
                }
            },
        }
    }

    /// Resolves the `node.port` part of a reference.
    #[allow(clippy::too_many_arguments)]
    fn resolve_port_reference(
        &mut self,
        source: &Arc<SourceFile>,
        reference: &Spanned<String>,
        base: &str,
        index: &HashMap<&str, usize>,
        slots: &[Slot],
        scope_inputs: &HashMap<String, Source>,
        what: &str,
    ) -> Option<Source> {
        let Some((target, port)) = split_reference(base) else {
            self.diags.push(
                Diagnostic::at(
                    Code::BadReference,
                    source,
                    reference.span,
                    format!("malformed {what} reference `{}`", reference.value),
                )
                .label("expected `node.port`")
                .help("references name a node and one of its output ports, e.g. \"blur.image\""),
            );
            return None;
        };
        if target == SUBGRAPH_INPUTS && !index.contains_key(target) {
            if let Some(s) = scope_inputs.get(port) {
                return Some(s.clone());
            }
            if !scope_inputs.is_empty() {
                let names: Vec<&str> = scope_inputs.keys().map(String::as_str).collect();
                let port_span = sub_span(source, reference, base.len() - port.len(), base.len());
                self.diags.push(unknown_name_diag(
                    Code::UnknownOutput,
                    source,
                    &Spanned {
                        value: port.to_string(),
                        span: port_span,
                    },
                    &format!("this graph has no input `{port}`"),
                    "no such graph input",
                    &names,
                    "inputs",
                ));
                return None;
            }
        }
        let Some(&j) = index.get(target) else {
            let hint =
                suggest(target, index.keys().copied()).map(|s| format!("did you mean `{s}`?"));
            self.diags.push(
                Diagnostic::at(
                    Code::Dangling,
                    source,
                    reference.span,
                    format!("{what} refers to unknown node `{target}`"),
                )
                .label("no node with this name")
                .maybe_help(hint),
            );
            return None;
        };
        // The reference text is a quoted string: the port starts after the last `.`.
        let port_span = sub_span(source, reference, base.len() - port.len(), base.len());
        let port_name = Spanned {
            value: port.to_string(),
            span: port_span,
        };
        let (info, output_types, global) = match &slots[j] {
            Slot::Op { index: global } => {
                let node = &self.nodes[*global];
                (
                    Arc::clone(&node.info),
                    node.output_types.clone(),
                    Some(*global),
                )
            }
            Slot::Invalid { info, output_types } => (Arc::clone(info), output_types.clone(), None),
            Slot::Subgraph { exports, names } => {
                return match exports.get(port) {
                    Some(src) => Some(src.clone()),
                    None => {
                        let names: Vec<&str> = names.iter().map(String::as_str).collect();
                        let msg = format!("subgraph node `{target}` has no output `{port}`");
                        self.unknown_output(source, &port_name, &msg, &names);
                        None
                    }
                };
            }
            Slot::Failed | Slot::Pending => return Some(Source::Poisoned),
        };
        match info.outputs.iter().position(|p| p.name == port) {
            Some(p) => {
                let ty = output_types[p].clone();
                Some(match global {
                    Some(node) => Source::Port(Tap::port(PortRef { node, port: p }), ty),
                    None => Source::Typed(ty),
                })
            }
            None => {
                let names: Vec<&str> = info.outputs.iter().map(|p| p.name.as_str()).collect();
                let msg = format!("node `{target}` ({}) has no output `{port}`", info.id);
                self.unknown_output(source, &port_name, &msg, &names);
                None
            }
        }
    }

    fn unknown_output(
        &mut self,
        source: &Arc<SourceFile>,
        port: &Spanned<String>,
        message: &str,
        names: &[&str],
    ) {
        let d = unknown_name_diag(
            Code::UnknownOutput,
            source,
            port,
            message,
            "no such output",
            names,
            "outputs",
        );
        self.diags.push(d);
    }

    /// Checks a node's parameters (file values, then `--set` overrides) against a schema.
    fn check_params(
        &mut self,
        source: &Arc<SourceFile>,
        node: &NodeSpec,
        schema: &[ParamSpec],
        overrides: &[&Override],
    ) -> Option<ParamMap> {
        let mut given: Vec<(&Spanned<String>, &Spanned<RonValue>, &Arc<SourceFile>)> =
            node.params.iter().map(|(k, v)| (k, v, source)).collect();
        for o in overrides.iter().filter(|o| !o.node.value.contains('/')) {
            given.retain(|(k, _, _)| k.value != o.param.value);
            given.push((&o.param, &o.value, &o.source));
        }
        let mut map = ParamMap::new();
        let mut ok = true;
        for (key, value, src) in given {
            let Some(spec) = schema.iter().find(|s| s.name == key.value) else {
                let names: Vec<&str> = schema.iter().map(|s| s.name.as_str()).collect();
                let msg = format!(
                    "operator `{}` has no parameter `{}`",
                    node.op.value, key.value
                );
                self.diags.push(unknown_name_diag(
                    Code::UnknownParam,
                    src,
                    key,
                    &msg,
                    "unknown parameter",
                    &names,
                    "parameters",
                ));
                ok = false;
                continue;
            };
            match convert(src, value, &spec.ty, spec) {
                Ok(v) => {
                    map.insert(spec.name.clone(), v);
                }
                Err(d) => {
                    self.diags.push(*d);
                    ok = false;
                }
            }
        }
        for spec in schema {
            map.entry(spec.name.clone())
                .or_insert_with(|| spec.default.clone());
        }
        ok.then_some(map)
    }
}

/// The element `i` (negative: from the end) of a list of `len` elements, if in range.
pub fn list_position(len: usize, i: i64) -> Option<usize> {
    if i >= 0 {
        usize::try_from(i).ok().filter(|&k| k < len)
    } else {
        usize::try_from(i.unsigned_abs())
            .ok()
            .and_then(|back| len.checked_sub(back))
    }
}

/// The span of bytes `start..end` of a reference's text inside its quoted string in the file;
/// the whole reference when the file spells it differently (e.g. with escapes).
fn sub_span(source: &SourceFile, reference: &Spanned<String>, start: usize, end: usize) -> Span {
    let quoted = source
        .text
        .get(reference.span.start..reference.span.end)
        .and_then(|t| t.strip_prefix('"'))
        .and_then(|t| t.strip_suffix('"'));
    if quoted == Some(reference.value.as_str()) {
        let at = reference.span.start + 1;
        Span::new(at + start, at + end)
    } else {
        reference.span
    }
}

fn first_segment(path: &str) -> &str {
    path.split('/').next().unwrap_or(path)
}

/// Kahn's algorithm, always taking the lowest-numbered ready node so the order is stable. Nodes
/// on or downstream of a cycle are left out (the cycle is reported separately).
fn topological_order(deps: &[BTreeSet<usize>]) -> Vec<usize> {
    let n = deps.len();
    let mut remaining: Vec<usize> = deps.iter().map(BTreeSet::len).collect();
    let mut dependents = vec![Vec::new(); n];
    for (i, d) in deps.iter().enumerate() {
        for &j in d {
            dependents[j].push(i);
        }
    }
    let mut ready: BTreeSet<usize> = (0..n).filter(|&i| remaining[i] == 0).collect();
    let mut order = Vec::with_capacity(n);
    while let Some(i) = ready.pop_first() {
        order.push(i);
        for &k in &dependents[i] {
            remaining[k] -= 1;
            if remaining[k] == 0 {
                ready.insert(k);
            }
        }
    }
    order
}

/// `a → b → c → a`, following dependencies inside one cycle.
fn cycle_text(members: &[usize], deps: &[BTreeSet<usize>], spec: &GraphSpec) -> String {
    let set: BTreeSet<usize> = members.iter().copied().collect();
    let start = members[0];
    let mut path = vec![start];
    let mut current = start;
    // Walk consumer edges: the node that depends on `current` within the cycle.
    for _ in 0..members.len() {
        let next = members.iter().copied().find(|&m| {
            deps[m].contains(&current) && set.contains(&m) && (m == start || !path.contains(&m))
        });
        match next {
            Some(m) => {
                path.push(m);
                if m == start {
                    break;
                }
                current = m;
            }
            None => break,
        }
    }
    path.iter()
        .map(|&i| spec.nodes[i].name.value.as_str())
        .collect::<Vec<_>>()
        .join(" → ")
}

#[allow(clippy::too_many_arguments)]
fn unknown_name_diag(
    code: Code,
    source: &Arc<SourceFile>,
    name: &Spanned<String>,
    message: &str,
    label: &str,
    candidates: &[&str],
    what: &str,
) -> Diagnostic {
    let help = match suggest(&name.value, candidates.iter().copied()) {
        Some(s) => format!("did you mean `{s}`?"),
        None if candidates.is_empty() => format!("it has no {what}"),
        None => format!(
            "available {what}: {}",
            candidates
                .iter()
                .map(|c| format!("`{c}`"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    Diagnostic::at(code, source, name.span, message.to_string())
        .label(label.to_string())
        .help(help)
}

fn type_mismatch(
    source: &Arc<SourceFile>,
    reference: &Spanned<String>,
    found: &PortType,
    node: &str,
    port: &Spanned<String>,
    expected: &PortType,
) -> Diagnostic {
    Diagnostic::at(
        Code::TypeMismatch,
        source,
        reference.span,
        format!(
            "type mismatch: `{}` is {found}, but input `{}` of `{node}` expects {expected}",
            reference.value, port.value
        ),
    )
    .label(format!("this is {found}"))
    .related(port.span, format!("expects {expected}"))
}

/// Converts a written value to a checked parameter value of type `ty`.
fn convert(
    source: &Arc<SourceFile>,
    v: &Spanned<RonValue>,
    ty: &ParamType,
    spec: &ParamSpec,
) -> Result<ParamValue, Box<Diagnostic>> {
    let mismatch = || {
        let mut d = Diagnostic::at(
            Code::ParamType,
            source,
            v.span,
            format!(
                "parameter `{}` expects {ty}, found {}",
                spec.name,
                describe(&v.value)
            ),
        )
        .label(format!("expected {ty}"));
        if let (RonValue::Ident(word), ParamType::Str | ParamType::Path) = (&v.value, ty) {
            d = d.help(format!("strings are quoted: \"{word}\""));
        } else if let (RonValue::Float(x), ParamType::Int) = (&v.value, ty) {
            d = d.help(format!(
                "`{}` takes whole numbers, e.g. {}",
                spec.name,
                x.round()
            ));
        }
        Box::new(d)
    };
    let range = |x: f64| -> Result<(), Box<Diagnostic>> {
        spec.check_range(x).map_err(|msg| {
            Box::new(
                Diagnostic::at(
                    Code::ParamRange,
                    source,
                    v.span,
                    format!("parameter out of range: {msg}"),
                )
                .label("out of range")
                .maybe_help(spec.range_text().map(|r| format!("allowed: {r}"))),
            )
        })
    };
    match (ty, &v.value) {
        (ParamType::Bool, RonValue::Bool(b)) => Ok(ParamValue::Bool(*b)),
        (ParamType::Int, RonValue::Int(i)) => {
            range(*i as f64)?;
            Ok(ParamValue::Int(*i))
        }
        (ParamType::Float, RonValue::Int(i)) => {
            range(*i as f64)?;
            Ok(ParamValue::Float(*i as f64))
        }
        (ParamType::Float, RonValue::Float(x)) => {
            if !x.is_finite() {
                return Err(Box::new(
                    Diagnostic::at(
                        Code::ParamRange,
                        source,
                        v.span,
                        format!("parameter `{}` must be finite, got {x}", spec.name),
                    )
                    .label("not a finite number"),
                ));
            }
            range(*x)?;
            Ok(ParamValue::Float(*x))
        }
        (ParamType::Str, RonValue::Str(s)) => Ok(ParamValue::Str(s.clone())),
        (ParamType::Path, RonValue::Str(s)) => {
            let p = Path::new(s);
            let resolved = if p.is_absolute() || s.is_empty() {
                p.to_path_buf()
            } else {
                source.base_dir().join(p)
            };
            Ok(ParamValue::Str(resolved.to_string_lossy().into_owned()))
        }
        (ParamType::Choice(names), RonValue::Str(s) | RonValue::Ident(s)) => {
            if names.iter().any(|n| n == s) {
                Ok(ParamValue::Str(s.clone()))
            } else {
                let hint = match suggest(s, names.iter().map(String::as_str)) {
                    Some(best) => format!("did you mean \"{best}\"?"),
                    None => format!("expected {ty}"),
                };
                Err(Box::new(
                    Diagnostic::at(
                        Code::ParamRange,
                        source,
                        v.span,
                        format!("parameter `{}` has no choice \"{s}\"", spec.name),
                    )
                    .label("unknown choice")
                    .help(hint),
                ))
            }
        }
        (
            ParamType::List { element, len },
            RonValue::List(items) | RonValue::Tuple { name: None, items },
        ) => {
            if let Some(n) = len
                && items.len() != *n
            {
                return Err(Box::new(
                    Diagnostic::at(
                        Code::ParamType,
                        source,
                        v.span,
                        format!(
                            "parameter `{}` expects {n} values, found {}",
                            spec.name,
                            items.len()
                        ),
                    )
                    .label(format!("expected {ty}")),
                ));
            }
            let values = items
                .iter()
                .map(|item| convert(source, item, element, spec))
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ParamValue::List(values))
        }
        (ParamType::Optional(_), RonValue::Option(None)) => Ok(ParamValue::None),
        (ParamType::Optional(inner), RonValue::Option(Some(x))) => convert(source, x, inner, spec),
        (ParamType::Optional(inner), _) => convert(source, v, inner, spec),
        _ => Err(mismatch()),
    }
}

fn describe(v: &RonValue) -> String {
    match v {
        RonValue::Bool(b) => format!("boolean `{b}`"),
        RonValue::Int(i) => format!("integer `{i}`"),
        RonValue::Float(x) => format!("float `{x}`"),
        RonValue::Str(s) => format!("string {s:?}"),
        RonValue::Ident(s) => format!("bare word `{s}`"),
        other => crate::ron_syntax::a_kind(other),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn list_positions_count_from_either_end() {
        assert_eq!(list_position(3, 0), Some(0));
        assert_eq!(list_position(3, 2), Some(2));
        assert_eq!(list_position(3, 3), None);
        assert_eq!(list_position(3, -1), Some(2));
        assert_eq!(list_position(3, -3), Some(0));
        assert_eq!(list_position(3, -4), None);
        assert_eq!(list_position(0, 0), None);
        assert_eq!(list_position(0, -1), None);
        assert_eq!(list_position(5, i64::MIN), None);
        assert_eq!(list_position(5, i64::MAX), None);
    }

    #[test]
    fn topological_order_is_stable_and_skips_cycles() {
        let deps: Vec<BTreeSet<usize>> = vec![
            BTreeSet::from([2]),
            BTreeSet::new(),
            BTreeSet::new(),
            BTreeSet::from([4]),
            BTreeSet::from([3]),
        ];
        assert_eq!(topological_order(&deps), vec![1, 2, 0]);
    }

    #[test]
    fn overrides_parse() {
        let o = Override::parse("blur.sigma=2.5").unwrap();
        assert_eq!(o.node.value, "blur");
        assert_eq!(o.param.value, "sigma");
        assert_eq!(o.value.value, RonValue::Float(2.5));
        assert_eq!(&o.source.text[o.value.span.start..o.value.span.end], "2.5");
        let word = Override::parse("card.kind=checkerboard").unwrap();
        assert_eq!(word.value.value, RonValue::Str("checkerboard".into()));
        let list = Override::parse("a/b.roi=[0, 0, 3, 4]").unwrap();
        assert_eq!(list.node.value, "a/b");
        assert!(matches!(list.value.value, RonValue::List(ref items) if items.len() == 4));
        let text = Override::parse("n.path=some file.png").unwrap();
        assert_eq!(text.value.value, RonValue::Str("some file.png".into()));
        assert!(Override::parse("blur=2").is_err());
        assert!(Override::parse("blur.sigma").is_err());
        assert!(Override::parse(".sigma=1").is_err());
    }
}
