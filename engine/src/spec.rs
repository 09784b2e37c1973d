//! `GraphSpec`: the graph file as written, names and values with their spans. Validation
//! ([`crate::resolve`]) turns it into a runnable [`crate::graph::Graph`], collecting every error.
//!
//! The file shape is a contract users, docs and tools rely on:
//!
//! ```ron
//! Graph(
//!     name: "edges",
//!     description: "Canny edges of a generated test card",
//!     nodes: {
//!         "card":  (op: "capture.pattern", params: (kind: "test_card", width: 1920, height: 1080)),
//!         "gray":  (op: "filter.grayscale", inputs: { "image": "card.image" }),
//!     },
//!     outputs: { "gray": "gray.image" },
//! )
//! ```
//!
//! A node input is a reference `"node.port"`, an indexed reference `"node.port[i]"` (one element
//! of a `List<T>` output; negative indices count from the end) or a list literal of references
//! `["left.image", "right.image"]` (a `List<T>` of outputs of one type). Graph `outputs` take
//! references and indexed references.

use std::sync::Arc;

use crate::diag::{Code, Diagnostic, Diagnostics, SourceFile, suggest};
use crate::ron_syntax::{RonValue, Span, Spanned, a_kind};

/// A name with its span.
pub type Name = Spanned<String>;

/// A graph file.
#[derive(Debug, Clone)]
pub struct GraphSpec {
    /// The source it was read from.
    pub source: Arc<SourceFile>,
    /// `name`, if given.
    pub name: Option<Name>,
    /// `description`, if given.
    pub description: Option<Name>,
    /// Inputs a subgraph declares: name and type text (e.g. `"Image"`).
    pub inputs: Vec<(Name, Name)>,
    /// Nodes in file order.
    pub nodes: Vec<NodeSpec>,
    /// Outputs: name and `node.port` reference.
    pub outputs: Vec<(Name, Name)>,
    /// Plugin libraries to load before resolving operators, relative to the file's folder.
    pub plugins: Vec<Name>,
    /// The `animation` section as written (frames, rate, parameter tracks), read by
    /// [`crate::timeline`]; only a top-level graph may have one.
    pub animation: Option<Spanned<RonValue>>,
    /// The `stream` section as written (queue capacity, drop policy, pacing), read by
    /// [`crate::stream`]; only a top-level graph may have one.
    pub stream: Option<Spanned<RonValue>>,
    /// Span of the whole document.
    pub span: Span,
}

/// One node as written.
#[derive(Debug, Clone)]
pub struct NodeSpec {
    /// Node name (the map key).
    pub name: Name,
    /// Operator id.
    pub op: Name,
    /// Inputs: port name and reference (`"node.port"`, `"node.port[i]"` or a list literal).
    pub inputs: Vec<(Name, InputRef)>,
    /// Parameters as written (checked later against the operator's schema).
    pub params: Vec<(Name, Spanned<RonValue>)>,
    /// Span of the `params` value, or of the node when absent.
    pub params_span: Span,
    /// Span of the node's value.
    pub span: Span,
}

/// What a node input is wired to.
#[derive(Debug, Clone)]
pub enum InputRef {
    /// One reference: `"node.port"` or `"node.port[i]"`.
    One(Name),
    /// A list literal `["a.port", "b.port[0]"]`: a list built from the referenced values.
    List {
        /// The element references, in order.
        items: Vec<Name>,
        /// Span of the whole list.
        span: Span,
    },
}

impl InputRef {
    /// Span of the whole value.
    pub fn span(&self) -> Span {
        match self {
            InputRef::One(r) => r.span,
            InputRef::List { span, .. } => *span,
        }
    }

    /// Every reference, in order.
    pub fn references(&self) -> &[Name] {
        match self {
            InputRef::One(r) => std::slice::from_ref(r),
            InputRef::List { items, .. } => items,
        }
    }

    /// The value as written (`"a.x"` or `["a.x", "b.y"]`), as one spanned text for messages.
    pub fn as_text(&self) -> Name {
        match self {
            InputRef::One(r) => r.clone(),
            InputRef::List { items, span } => Spanned {
                value: format!(
                    "[{}]",
                    items
                        .iter()
                        .map(|i| format!("\"{}\"", i.value))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
                span: *span,
            },
        }
    }
}

const GRAPH_FIELDS: [&str; 8] = [
    "name",
    "description",
    "inputs",
    "nodes",
    "outputs",
    "plugins",
    "animation",
    "stream",
];
const NODE_FIELDS: [&str; 3] = ["op", "inputs", "params"];

/// Reads a parsed document as a graph, reporting every shape problem.
pub fn graph_from_ron(
    source: &Arc<SourceFile>,
    doc: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Option<GraphSpec> {
    let fields = struct_fields(source, doc, "Graph", "the graph", diags)?;
    let mut spec = GraphSpec {
        source: Arc::clone(source),
        name: None,
        description: None,
        inputs: Vec::new(),
        nodes: Vec::new(),
        outputs: Vec::new(),
        plugins: Vec::new(),
        animation: None,
        stream: None,
        span: doc.span,
    };
    let mut saw_nodes = false;
    for (key, value) in fields {
        match key.value.as_str() {
            "name" => spec.name = string(source, value, "`name`", diags),
            "description" => spec.description = string(source, value, "`description`", diags),
            "inputs" => spec.inputs = string_map(source, value, "`inputs`", diags),
            "outputs" => spec.outputs = string_map(source, value, "`outputs`", diags),
            "plugins" => spec.plugins = string_list(source, value, "`plugins`", diags),
            "animation" => spec.animation = Some(value.clone()),
            "stream" => spec.stream = Some(value.clone()),
            "nodes" => {
                saw_nodes = true;
                spec.nodes = nodes(source, value, diags);
            }
            other => diags.push(unknown_field(source, key, other, &GRAPH_FIELDS, "graph")),
        }
    }
    if !saw_nodes {
        diags.push(
            Diagnostic::at(Code::Shape, source, head_span(doc), "the graph has no `nodes` field")
                .label("expected `nodes: { ... }` here")
                .help("a graph is `Graph(name: \"...\", nodes: { \"n\": (op: \"family.name\") }, outputs: { ... })`"),
        );
    }
    Some(spec)
}

/// The span of a value's first token (for errors about the value as a whole).
pub(crate) fn head_span(v: &Spanned<RonValue>) -> Span {
    match &v.value {
        RonValue::Struct { name: Some(n), .. } | RonValue::Tuple { name: Some(n), .. } => n.span,
        _ => Span::new(
            v.span.start,
            (v.span.start + 1).min(v.span.end.max(v.span.start + 1)),
        ),
    }
}

pub(crate) fn unknown_field(
    source: &Arc<SourceFile>,
    key: &Name,
    name: &str,
    allowed: &[&str],
    what: &str,
) -> Diagnostic {
    let hint = match suggest(name, allowed.iter().copied()) {
        Some(s) => format!("did you mean `{s}`?"),
        None => format!("a {what} has the fields {}", list(allowed)),
    };
    Diagnostic::at(
        Code::Shape,
        source,
        key.span,
        format!("unknown {what} field `{name}`"),
    )
    .label("unknown field")
    .help(hint)
}

fn list(names: &[&str]) -> String {
    names
        .iter()
        .map(|n| format!("`{n}`"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Fields of a struct value (`Name(...)` with the expected name, or `(...)`); `()` has none.
pub(crate) fn struct_fields<'a>(
    source: &Arc<SourceFile>,
    v: &'a Spanned<RonValue>,
    expected_name: &str,
    what: &str,
    diags: &mut Diagnostics,
) -> Option<&'a [(Name, Spanned<RonValue>)]> {
    match &v.value {
        RonValue::Struct { name, fields } => {
            if let Some(n) = name
                && n.value != expected_name
            {
                diags.push(
                    Diagnostic::at(
                        Code::Shape,
                        source,
                        n.span,
                        format!("expected `{expected_name}(...)`, found `{}(...)`", n.value),
                    )
                    .label("wrong struct name"),
                );
            }
            Some(fields)
        }
        RonValue::Unit => Some(&[]),
        RonValue::Tuple { items, .. } if items.is_empty() => Some(&[]),
        other => {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    head_span(v),
                    format!(
                        "{what} must be a struct `(field: value, ...)`, found {}",
                        a_kind(other)
                    ),
                )
                .label("not a struct"),
            );
            None
        }
    }
}

fn string(
    source: &Arc<SourceFile>,
    v: &Spanned<RonValue>,
    what: &str,
    diags: &mut Diagnostics,
) -> Option<Name> {
    match &v.value {
        RonValue::Str(s) => Some(Spanned {
            value: s.clone(),
            span: v.span,
        }),
        other => {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    v.span,
                    format!("{what} must be a string, found {}", a_kind(other)),
                )
                .label("expected a string")
                .maybe_help(ident_hint(other)),
            );
            None
        }
    }
}

fn ident_hint(v: &RonValue) -> Option<String> {
    match v {
        RonValue::Ident(name) => Some(format!("strings are quoted: \"{name}\"")),
        _ => None,
    }
}

/// A `{ "key": "value" }` map of strings; duplicate keys are errors.
fn string_list(
    source: &Arc<SourceFile>,
    v: &Spanned<RonValue>,
    what: &str,
    diags: &mut Diagnostics,
) -> Vec<Name> {
    match &v.value {
        RonValue::List(items) => items
            .iter()
            .filter_map(|item| string(source, item, &format!("an entry of {what}"), diags))
            .collect(),
        RonValue::Unit => Vec::new(),
        other => {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    head_span(v),
                    format!(
                        "{what} must be a list `[\"path\", ...]`, found {}",
                        a_kind(other)
                    ),
                )
                .label("expected a list"),
            );
            Vec::new()
        }
    }
}

fn string_map(
    source: &Arc<SourceFile>,
    v: &Spanned<RonValue>,
    what: &str,
    diags: &mut Diagnostics,
) -> Vec<(Name, Name)> {
    let entries = match &v.value {
        RonValue::Map(entries) => entries,
        RonValue::Unit => return Vec::new(),
        other => {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    head_span(v),
                    format!(
                        "{what} must be a map `{{ \"key\": \"value\" }}`, found {}",
                        a_kind(other)
                    ),
                )
                .label("expected a map"),
            );
            return Vec::new();
        }
    };
    let mut out: Vec<(Name, Name)> = Vec::new();
    for (k, val) in entries {
        let Some(key) = string(source, k, &format!("a key of {what}"), diags) else {
            continue;
        };
        let Some(value) = string(source, val, &format!("a value of {what}"), diags) else {
            continue;
        };
        if let Some((first, _)) = out.iter().find(|(n, _)| n.value == key.value) {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    key.span,
                    format!("`{}` appears twice in {what}", key.value),
                )
                .label("second entry")
                .related(first.span, "first entry"),
            );
            continue;
        }
        out.push((key, value));
    }
    out
}

/// A node's `inputs`: `{ "port": "node.port" }` or `{ "port": ["a.port", "b.port"] }`.
fn input_map(
    source: &Arc<SourceFile>,
    v: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Vec<(Name, InputRef)> {
    let what = "`inputs`";
    let entries = match &v.value {
        RonValue::Map(entries) => entries,
        RonValue::Unit => return Vec::new(),
        other => {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    head_span(v),
                    format!(
                        "{what} must be a map `{{ \"port\": \"node.port\" }}`, found {}",
                        a_kind(other)
                    ),
                )
                .label("expected a map"),
            );
            return Vec::new();
        }
    };
    let mut out: Vec<(Name, InputRef)> = Vec::new();
    for (k, val) in entries {
        let Some(key) = string(source, k, &format!("a key of {what}"), diags) else {
            continue;
        };
        let value = match &val.value {
            RonValue::List(items) => {
                let mut refs = Vec::with_capacity(items.len());
                let mut ok = true;
                for item in items {
                    match string(
                        source,
                        item,
                        &format!("an element of a list in {what}"),
                        diags,
                    ) {
                        Some(r) => refs.push(r),
                        None => ok = false,
                    }
                }
                if !ok {
                    continue;
                }
                InputRef::List {
                    items: refs,
                    span: val.span,
                }
            }
            _ => match string(source, val, &format!("a value of {what}"), diags) {
                Some(r) => InputRef::One(r),
                None => continue,
            },
        };
        if let Some((first, _)) = out.iter().find(|(n, _)| n.value == key.value) {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    key.span,
                    format!("`{}` appears twice in {what}", key.value),
                )
                .label("second entry")
                .related(first.span, "first entry"),
            );
            continue;
        }
        out.push((key, value));
    }
    out
}

fn nodes(
    source: &Arc<SourceFile>,
    v: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Vec<NodeSpec> {
    let entries = match &v.value {
        RonValue::Map(entries) => entries,
        other => {
            diags.push(
                Diagnostic::at(
                    Code::Shape,
                    source,
                    head_span(v),
                    format!(
                        "`nodes` must be a map `{{ \"name\": (op: ...), ... }}`, found {}",
                        a_kind(other)
                    ),
                )
                .label("expected a map of nodes"),
            );
            return Vec::new();
        }
    };
    let mut out: Vec<NodeSpec> = Vec::new();
    for (k, val) in entries {
        let Some(name) = string(source, k, "a node name", diags) else {
            continue;
        };
        if !valid_node_name(&name.value) {
            diags.push(
                Diagnostic::at(Code::BadName, source, name.span, format!("invalid node name `{}`", name.value))
                    .label("invalid name")
                    .help("node names use letters, digits, `_` and `-` (a `.` separates node and port in references)"),
            );
            continue;
        }
        if let Some(first) = out.iter().find(|n| n.name.value == name.value) {
            diags.push(
                Diagnostic::at(
                    Code::DuplicateNode,
                    source,
                    name.span,
                    format!("duplicate node `{}`", name.value),
                )
                .label("defined again here")
                .related(first.name.span, "first defined here")
                .help("node names must be unique within a graph"),
            );
            continue;
        }
        if let Some(node) = node(source, name, val, diags) {
            out.push(node);
        }
    }
    out
}

/// Node names: non-empty, letters, digits, `_`, `-`.
pub fn valid_node_name(name: &str) -> bool {
    !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

fn node(
    source: &Arc<SourceFile>,
    name: Name,
    v: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Option<NodeSpec> {
    let fields = struct_fields(source, v, "Node", &format!("node `{}`", name.value), diags)?;
    let mut op = None;
    let mut saw_op = false;
    let mut inputs = Vec::new();
    let mut params = Vec::new();
    let mut params_span = name.span;
    for (key, value) in fields {
        match key.value.as_str() {
            "op" => {
                saw_op = true;
                op = string(source, value, "`op`", diags);
            }
            "inputs" => inputs = input_map(source, value, diags),
            "params" => {
                params_span = value.span;
                match &value.value {
                    RonValue::Struct { name: None, fields } => params = fields.clone(),
                    RonValue::Unit => {}
                    RonValue::Tuple { name: None, items } if items.is_empty() => {}
                    other => diags.push(
                        Diagnostic::at(
                            Code::Shape,
                            source,
                            head_span(value),
                            format!(
                                "`params` must be a struct `(name: value, ...)`, found {}",
                                a_kind(other)
                            ),
                        )
                        .label("expected `(name: value, ...)`"),
                    ),
                }
            }
            other => diags.push(unknown_field(source, key, other, &NODE_FIELDS, "node")),
        }
    }
    let Some(op) = op else {
        if saw_op {
            return None;
        }
        diags.push(
            Diagnostic::at(Code::Shape, source, name.span, format!("node `{}` has no `op`", name.value))
                .label("missing `op`")
                .help("every node names its operator: `(op: \"family.name\", ...)`; `ocellus ops` lists them"),
        );
        return None;
    };
    Some(NodeSpec {
        name,
        op,
        inputs,
        params,
        params_span,
        span: v.span,
    })
}

/// Splits a `node.port` reference at its last `.`.
pub fn split_reference(text: &str) -> Option<(&str, &str)> {
    let (node, port) = text.rsplit_once('.')?;
    (!node.is_empty() && !port.is_empty()).then_some((node, port))
}

/// A reference's element index, if any: `"node.port[2]"` → `("node.port", Some(2))`,
/// `"node.port[-1]"` → `("node.port", Some(-1))`, `"node.port"` → `("node.port", None)`. A `[` or
/// `]` that does not form one trailing `[integer]` is an error, returned as a short explanation.
pub fn split_index(text: &str) -> Result<(&str, Option<i64>), String> {
    let Some(open) = text.find('[') else {
        if text.contains(']') {
            return Err("unbalanced `]`".into());
        }
        return Ok((text, None));
    };
    let (base, rest) = text.split_at(open);
    let Some(inner) = rest[1..].strip_suffix(']') else {
        return Err(if rest.contains(']') {
            "nothing may follow the index `[...]`".into()
        } else {
            "missing `]` after the index".into()
        });
    };
    if inner.contains('[') || inner.contains(']') {
        return Err("only one index `[i]` is allowed".into());
    }
    let digits = inner.trim();
    if digits.is_empty() {
        return Err("empty index `[]`".into());
    }
    match digits.parse::<i64>() {
        Ok(i) => Ok((base, Some(i))),
        Err(_) => Err(format!("index `{inner}` is not an integer")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_split_off_references() {
        assert_eq!(split_index("a.b"), Ok(("a.b", None)));
        assert_eq!(split_index("a.b[0]"), Ok(("a.b", Some(0))));
        assert_eq!(split_index("a.b[-1]"), Ok(("a.b", Some(-1))));
        assert_eq!(split_index("a.b[ 7 ]"), Ok(("a.b", Some(7))));
        for bad in [
            "a.b[x]",
            "a.b[1",
            "a.b[]",
            "a.b]",
            "a.b[1]x",
            "a.b[0][1]",
            "a.b[1.5]",
            "a.b[99999999999999999999]",
        ] {
            assert!(split_index(bad).is_err(), "{bad}");
        }
    }
}
