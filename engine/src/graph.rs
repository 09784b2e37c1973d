//! The resolved, runnable graph: operator instances, typed edges, subgraphs inlined.

use std::sync::Arc;

use crate::diag::SourceFile;
use crate::op::{OpInfo, Operator};
use crate::params::ParamMap;
use crate::ron_syntax::Span;
use crate::types::PortType;

/// Where a node was declared, for run-time error messages.
#[derive(Debug, Clone)]
pub struct Location {
    /// The graph file.
    pub source: Arc<SourceFile>,
    /// The node name's span.
    pub span: Span,
}

impl Location {
    /// `file:line:col`.
    pub fn display(&self) -> String {
        self.source.location(self.span.start)
    }
}

/// An edge source: output `port` of node `node`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct PortRef {
    /// Node index.
    pub node: usize,
    /// Output port index.
    pub port: usize,
}

/// One value an edge reads: an output port, or one element of a list output (`node.port[i]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Tap {
    /// The output port.
    pub from: PortRef,
    /// For `node.port[i]`: the element index; negative counts from the end (`-1` is the last).
    /// Checked against the list's length at run time.
    pub index: Option<i64>,
}

impl Tap {
    /// The whole output port.
    pub fn port(from: PortRef) -> Tap {
        Tap { from, index: None }
    }
}

/// Where an input's value comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EdgeSource {
    /// One output port, or one element of it.
    Tap(Tap),
    /// A list literal `["a.port", "b.port"]`: a `List<element>` built from the values, in order.
    List {
        /// The referenced values, in order (never empty).
        items: Vec<Tap>,
        /// Their common type.
        element: PortType,
    },
}

/// How one input of a node is fed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InputEdge {
    /// Where the value comes from.
    pub source: EdgeSource,
    /// True when the source is `List<T>` feeding a port of type `T`: the node is mapped over it.
    pub mapped: bool,
}

impl InputEdge {
    /// An edge reading a whole output port.
    pub fn port(from: PortRef, mapped: bool) -> InputEdge {
        InputEdge {
            source: EdgeSource::Tap(Tap::port(from)),
            mapped,
        }
    }

    /// Every value this edge reads, in order.
    pub fn taps(&self) -> &[Tap] {
        match &self.source {
            EdgeSource::Tap(tap) => std::slice::from_ref(tap),
            EdgeSource::List { items, .. } => items,
        }
    }

    /// Every output port this edge reads, in order (with repeats).
    pub fn sources(&self) -> impl Iterator<Item = PortRef> + '_ {
        self.taps().iter().map(|t| t.from)
    }
}

/// A node ready to run.
#[derive(Clone)]
pub struct Node {
    /// Qualified name (`sub/blur` for a node inside subgraph node `sub`).
    pub name: String,
    /// Operator description.
    pub info: Arc<OpInfo>,
    /// Configured instance.
    pub op: Arc<dyn Operator>,
    /// Checked parameters, defaults filled in.
    pub params: ParamMap,
    /// One entry per input port of the operator.
    pub inputs: Vec<Option<InputEdge>>,
    /// Output types (wrapped in `List` when the node is mapped).
    pub output_types: Vec<PortType>,
    /// Declaration site.
    pub location: Option<Location>,
}

impl Node {
    /// True when at least one input is mapped over a list.
    pub fn is_mapped(&self) -> bool {
        self.inputs.iter().flatten().any(|e| e.mapped)
    }
}

impl std::fmt::Debug for Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Node")
            .field("name", &self.name)
            .field("op", &self.info.id)
            .field("params", &self.params)
            .field("inputs", &self.inputs)
            .field("output_types", &self.output_types)
            .finish()
    }
}

/// A named graph output.
#[derive(Debug, Clone)]
pub struct GraphOutput {
    /// Output name.
    pub name: String,
    /// Where it comes from.
    pub from: PortRef,
    /// For `node.port[i]`: the element of the list output (negative counts from the end).
    pub index: Option<i64>,
    /// Its type.
    pub ty: PortType,
}

/// A validated graph. Nodes are stored in a topological order: every edge goes from a lower to a
/// higher index.
#[derive(Debug, Clone)]
pub struct Graph {
    /// `name` from the file (or the file stem).
    pub name: String,
    /// `description` from the file.
    pub description: String,
    /// Nodes in topological order.
    pub nodes: Vec<Node>,
    /// Declared outputs, in file order.
    pub outputs: Vec<GraphOutput>,
}

impl Graph {
    /// Index of the node with this qualified name.
    pub fn node_index(&self, name: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n.name == name)
    }

    /// For each node, the nodes consuming its outputs (deduplicated, ascending).
    pub fn consumers(&self) -> Vec<Vec<usize>> {
        let mut consumers = vec![Vec::new(); self.nodes.len()];
        for (i, node) in self.nodes.iter().enumerate() {
            for from in node.inputs.iter().flatten().flat_map(InputEdge::sources) {
                let list: &mut Vec<usize> = &mut consumers[from.node];
                if list.last() != Some(&i) {
                    list.push(i);
                }
            }
        }
        consumers
    }

    /// Graphviz DOT text: nodes labelled with name and op, edges with port names and types.
    pub fn to_dot(&self) -> String {
        let mut out = String::from(
            "digraph ocellus {\n    rankdir=LR;\n    node [shape=record, fontname=\"Helvetica\"];\n",
        );
        out.push_str(&format!("    label={};\n", dot_quote(&self.name)));
        for (i, node) in self.nodes.iter().enumerate() {
            out.push_str(&format!(
                "    n{i} [label={}];\n",
                dot_quote(&format!("{}\\n{}", node.name, node.info.id))
            ));
        }
        for (i, node) in self.nodes.iter().enumerate() {
            for (port, edge) in node.inputs.iter().enumerate() {
                let Some(edge) = edge else { continue };
                let in_name = node.info.inputs.get(port).map_or("?", |p| p.name.as_str());
                let style = if edge.mapped { ", style=bold" } else { "" };
                let taps = edge.taps();
                for (k, tap) in taps.iter().enumerate() {
                    let src = &self.nodes[tap.from.node];
                    let out_name = src
                        .info
                        .outputs
                        .get(tap.from.port)
                        .map_or("?", |p| p.name.as_str());
                    let mut ty = src
                        .output_types
                        .get(tap.from.port)
                        .map(|t| t.to_string())
                        .unwrap_or_default();
                    let mut out_text = out_name.to_string();
                    if let Some(index) = tap.index {
                        out_text.push_str(&format!("[{index}]"));
                        ty = src
                            .output_types
                            .get(tap.from.port)
                            .and_then(PortType::element)
                            .map(|t| t.to_string())
                            .unwrap_or_default();
                    }
                    let in_text =
                        if taps.len() > 1 || matches!(edge.source, EdgeSource::List { .. }) {
                            format!("{in_name}[{k}]")
                        } else {
                            in_name.to_string()
                        };
                    out.push_str(&format!(
                        "    n{} -> n{i} [label={}{style}];\n",
                        tap.from.node,
                        dot_quote(&format!("{out_text} → {in_text}\\n{ty}"))
                    ));
                }
            }
        }
        for (k, output) in self.outputs.iter().enumerate() {
            out.push_str(&format!(
                "    out{k} [shape=oval, label={}];\n    n{} -> out{k};\n",
                dot_quote(&output.name),
                output.from.node
            ));
        }
        out.push_str("}\n");
        out
    }
}

fn dot_quote(text: &str) -> String {
    let mut q = String::with_capacity(text.len() + 2);
    q.push('"');
    for c in text.chars() {
        match c {
            '"' => q.push_str("\\\""),
            '{' | '}' | '|' | '<' | '>' => {
                q.push('\\');
                q.push(c);
            }
            _ => q.push(c),
        }
    }
    q.push('"');
    q
}
