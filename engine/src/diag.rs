//! Diagnostics: every problem found in a graph, with its file, span, a message, and a hint.
//! Rendered by `miette` at the CLI as `file:line:col` with a source snippet and caret.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::ron_syntax::{Span, line_col};

/// A source text a diagnostic can point into: a graph file, or a `--set` argument.
#[derive(Debug)]
pub struct SourceFile {
    /// Name shown to the user (the path as given, or `--set`).
    pub name: String,
    /// Path on disk, if this is a file.
    pub path: Option<PathBuf>,
    /// The text (lossily decoded if the file was not valid UTF-8).
    pub text: String,
    named: miette::NamedSource<String>,
}

impl SourceFile {
    /// A source with a display name and text.
    pub fn new(
        name: impl Into<String>,
        path: Option<PathBuf>,
        text: impl Into<String>,
    ) -> Arc<Self> {
        let name = name.into();
        let text = text.into();
        let named = miette::NamedSource::new(name.clone(), text.clone());
        Arc::new(SourceFile {
            name,
            path,
            text,
            named,
        })
    }

    /// The folder relative paths in this source resolve against (the file's folder; the working
    /// directory for command-line sources).
    pub fn base_dir(&self) -> PathBuf {
        self.path
            .as_deref()
            .and_then(Path::parent)
            .map(Path::to_path_buf)
            .unwrap_or_default()
    }

    /// `name:line:col` of a byte offset.
    pub fn location(&self, offset: usize) -> String {
        let (line, col) = line_col(&self.text, offset);
        format!("{}:{line}:{col}", self.name)
    }
}

/// What kind of problem a diagnostic reports; the code is stable and documented.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Code {
    /// The file could not be read.
    Io,
    /// The file is not valid UTF-8.
    Encoding,
    /// Malformed RON.
    Syntax,
    /// The document is RON but not shaped like a graph (missing or unknown fields, wrong kinds).
    Shape,
    /// Unknown operator id.
    UnknownOp,
    /// Unknown parameter name.
    UnknownParam,
    /// A parameter value of the wrong type.
    ParamType,
    /// A parameter value outside its range, or not among its choices.
    ParamRange,
    /// Parameters that are invalid together.
    ParamInvalid,
    /// Unknown input port of an operator.
    UnknownInput,
    /// Unknown output port on a referenced node.
    UnknownOutput,
    /// A reference to a node that does not exist.
    Dangling,
    /// A reference that is not `node.port`.
    BadReference,
    /// Edge type mismatch.
    TypeMismatch,
    /// A required input is not connected.
    MissingInput,
    /// Two nodes with one name.
    DuplicateNode,
    /// A node name with forbidden characters.
    BadName,
    /// A dependency cycle.
    Cycle,
    /// A subgraph file is missing or includes itself.
    Subgraph,
    /// An unknown graph output (in `--output`).
    UnknownGraphOutput,
    /// A malformed `--set`.
    BadOverride,
    /// A plugin listed in the graph could not be loaded, or plugins are disabled.
    Plugin,
    /// A malformed `animation` section or track.
    Animation,
    /// A malformed `stream` section, or a graph that cannot stream.
    Stream,
}

impl Code {
    /// The stable code, e.g. `E0020`.
    pub fn as_str(self) -> &'static str {
        match self {
            Code::Io => "ocellus::io",
            Code::Encoding => "ocellus::encoding",
            Code::Syntax => "ocellus::syntax",
            Code::Shape => "ocellus::shape",
            Code::UnknownOp => "ocellus::unknown_op",
            Code::UnknownParam => "ocellus::unknown_param",
            Code::ParamType => "ocellus::param_type",
            Code::ParamRange => "ocellus::param_range",
            Code::ParamInvalid => "ocellus::param_invalid",
            Code::UnknownInput => "ocellus::unknown_input",
            Code::UnknownOutput => "ocellus::unknown_output",
            Code::Dangling => "ocellus::dangling_reference",
            Code::BadReference => "ocellus::bad_reference",
            Code::TypeMismatch => "ocellus::type_mismatch",
            Code::MissingInput => "ocellus::missing_input",
            Code::DuplicateNode => "ocellus::duplicate_node",
            Code::BadName => "ocellus::bad_name",
            Code::Cycle => "ocellus::cycle",
            Code::Subgraph => "ocellus::subgraph",
            Code::UnknownGraphOutput => "ocellus::unknown_output_name",
            Code::BadOverride => "ocellus::bad_override",
            Code::Plugin => "ocellus::plugin",
            Code::Animation => "ocellus::animation",
            Code::Stream => "ocellus::stream",
        }
    }
}

/// A secondary location shown with a diagnostic.
#[derive(Debug, Clone)]
pub struct Related {
    /// Where.
    pub span: Span,
    /// What is there.
    pub label: String,
}

/// One problem in a graph.
#[derive(Debug, Clone)]
pub struct Diagnostic {
    /// Kind.
    pub code: Code,
    /// One-line message.
    pub message: String,
    /// The source it points into, if any.
    pub source: Option<Arc<SourceFile>>,
    /// The primary span.
    pub span: Option<Span>,
    /// Label at the primary span.
    pub label: String,
    /// Further locations in the same source.
    pub related: Vec<Related>,
    /// A hint: the nearest valid name, the expected form.
    pub help: Option<String>,
}

impl Diagnostic {
    /// A diagnostic at a span of a source.
    pub fn at(
        code: Code,
        source: &Arc<SourceFile>,
        span: Span,
        message: impl Into<String>,
    ) -> Self {
        Diagnostic {
            code,
            message: message.into(),
            source: Some(Arc::clone(source)),
            span: Some(span),
            label: String::new(),
            related: Vec::new(),
            help: None,
        }
    }

    /// A diagnostic without a position.
    pub fn bare(code: Code, message: impl Into<String>) -> Self {
        Diagnostic {
            code,
            message: message.into(),
            source: None,
            span: None,
            label: String::new(),
            related: Vec::new(),
            help: None,
        }
    }

    /// Sets the label at the primary span.
    pub fn label(mut self, label: impl Into<String>) -> Self {
        self.label = label.into();
        self
    }

    /// Sets the hint.
    pub fn help(mut self, help: impl Into<String>) -> Self {
        self.help = Some(help.into());
        self
    }

    /// Sets the hint if there is one.
    pub fn maybe_help(mut self, help: Option<String>) -> Self {
        if help.is_some() {
            self.help = help;
        }
        self
    }

    /// Adds a secondary location.
    pub fn related(mut self, span: Span, label: impl Into<String>) -> Self {
        self.related.push(Related {
            span,
            label: label.into(),
        });
        self
    }

    /// `file:line:col` of the primary span, if any.
    pub fn location(&self) -> Option<String> {
        match (&self.source, self.span) {
            (Some(source), Some(span)) => Some(source.location(span.start)),
            (Some(source), None) => Some(source.name.clone()),
            _ => None,
        }
    }
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for Diagnostic {}

impl miette::Diagnostic for Diagnostic {
    fn code<'a>(&'a self) -> Option<Box<dyn fmt::Display + 'a>> {
        Some(Box::new(self.code.as_str()))
    }

    fn help<'a>(&'a self) -> Option<Box<dyn fmt::Display + 'a>> {
        self.help
            .as_ref()
            .map(|h| Box::new(h.as_str()) as Box<dyn fmt::Display>)
    }

    fn source_code(&self) -> Option<&dyn miette::SourceCode> {
        self.source
            .as_ref()
            .map(|s| &s.named as &dyn miette::SourceCode)
    }

    fn labels(&self) -> Option<Box<dyn Iterator<Item = miette::LabeledSpan> + '_>> {
        let span = self.span?;
        self.source.as_ref()?;
        let primary = miette::LabeledSpan::new_primary_with_span(
            (!self.label.is_empty()).then(|| self.label.clone()),
            (span.start, span.len()),
        );
        let related = self.related.iter().map(|r| {
            miette::LabeledSpan::new_with_span(Some(r.label.clone()), (r.span.start, r.span.len()))
        });
        Some(Box::new(std::iter::once(primary).chain(related)))
    }
}

/// All problems found while loading a graph.
#[derive(Debug, Clone, Default)]
pub struct Diagnostics(pub Vec<Diagnostic>);

impl Diagnostics {
    /// Adds one.
    pub fn push(&mut self, d: Diagnostic) {
        self.0.push(d);
    }

    /// True when nothing was found.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Number found.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Sorts by source and position so reports read top to bottom; stable for equal positions.
    pub fn sort(&mut self) {
        self.0.sort_by(|a, b| {
            let ka = (
                a.source.as_ref().map(|s| s.name.clone()),
                a.span.map(|s| s.start),
            );
            let kb = (
                b.source.as_ref().map(|s| s.name.clone()),
                b.span.map(|s| s.start),
            );
            ka.cmp(&kb)
        });
    }
}

impl fmt::Display for Diagnostics {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for d in &self.0 {
            match d.location() {
                Some(loc) => writeln!(f, "{loc}: {}", d.message)?,
                None => writeln!(f, "{}", d.message)?,
            }
        }
        Ok(())
    }
}

impl std::error::Error for Diagnostics {}

/// The nearest candidate to `name` by edit distance, if it is close enough to be a likely typo.
pub fn suggest<'a>(name: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let limit = (name.chars().count() / 3).max(2);
    let lower = name.to_lowercase();
    candidates
        .into_iter()
        .map(|c| (edit_distance(&lower, &c.to_lowercase()), c))
        .filter(|(d, _)| *d <= limit)
        .min_by(|a, b| a.0.cmp(&b.0).then_with(|| a.1.cmp(b.1)))
        .map(|(_, c)| c)
}

/// Levenshtein distance over chars.
pub fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diag = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let next = (diag + usize::from(ca != *cb))
                .min(row[j] + 1)
                .min(row[j + 1] + 1);
            diag = row[j + 1];
            row[j + 1] = next;
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edit_distances() {
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("gaussian", "gaussian"), 0);
        assert_eq!(edit_distance("ab", "ba"), 2);
    }

    #[test]
    fn suggestions() {
        let ops = ["filter.gaussian", "filter.grayscale", "detect.canny"];
        assert_eq!(suggest("filter.gausian", ops), Some("filter.gaussian"));
        assert_eq!(suggest("detect.cany", ops), Some("detect.canny"));
        assert_eq!(suggest("mesh.poisson", ops), None);
        assert_eq!(suggest("Sigma", ["sigma", "ksize"]), Some("sigma"));
    }

    #[test]
    fn location_is_one_based() {
        let src = SourceFile::new("g.ron", None, "ab\ncd");
        assert_eq!(src.location(0), "g.ron:1:1");
        assert_eq!(src.location(4), "g.ron:2:2");
    }
}
