//! Span-preserving parser for RON (Rusty Object Notation).
//!
//! Ocellus graphs are written in RON. We parse RON ourselves instead of using the `ron`
//! crate because:
//!
//! * `ron` deserializes straight into Rust types and does not record where each value came
//!   from, so a loader cannot point at the offending node, parameter or edge;
//! * `ron` stops at the first problem, but the graph loader must report *every* error of a
//!   file at once (unknown ops, wrong parameter types, dangling edges, duplicate keys, ...),
//!   each with `file:line:col`.
//!
//! [`parse`] turns text into a small syntax tree ([`RonValue`]) in which every value, struct
//! field name and map key carries its byte [`Span`]; [`line_col`] turns an offset into a
//! human position. A *syntax* error is still fatal for its file (one [`ParseError`] is
//! returned, since the rest of the text cannot be interpreted reliably), but all semantic
//! checks on the tree can be collected and reported together.
//!
//! The parser is hand-written, runs in linear time, never panics on any input, and limits
//! nesting to [`MAX_DEPTH`] levels so hostile input cannot overflow the stack.
//! [`to_ron_string`] renders a tree back to compact, deterministic RON text.

use std::collections::HashMap;
use std::fmt;
use std::str::CharIndices;

/// Deepest nesting of lists, maps, structs, tuples and `Some(..)` that [`parse`] accepts.
pub const MAX_DEPTH: usize = 128;

/// Byte range `start..end` into the source text.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Span {
    /// Offset of the first byte.
    pub start: usize,
    /// Offset one past the last byte.
    pub end: usize,
}

impl Span {
    /// Creates the span `start..end`.
    pub fn new(start: usize, end: usize) -> Self {
        Self { start, end }
    }

    /// Length in bytes.
    pub fn len(&self) -> usize {
        self.end.saturating_sub(self.start)
    }

    /// Whether the span covers no bytes.
    pub fn is_empty(&self) -> bool {
        self.end <= self.start
    }

    /// Smallest span covering both `self` and `other`.
    pub fn join(self, other: Span) -> Span {
        Span::new(self.start.min(other.start), self.end.max(other.end))
    }
}

/// A value together with the span of the source text it was parsed from.
#[derive(Debug, Clone, PartialEq)]
pub struct Spanned<T> {
    /// The parsed value.
    pub value: T,
    /// Where the value is in the source.
    pub span: Span,
}

impl<T> Spanned<T> {
    /// Wraps `value` with `span`.
    pub fn new(value: T, span: Span) -> Self {
        Self { value, span }
    }
}

/// One RON value; nested values carry their own spans.
#[derive(Debug, Clone, PartialEq)]
pub enum RonValue {
    /// `true` / `false`.
    Bool(bool),
    /// An integer literal (decimal, `0x`, `0o`, `0b`), which must fit in an `i64`.
    Int(i64),
    /// A literal with `.` or an exponent, or `inf` / `-inf` / `NaN`.
    Float(f64),
    /// `"..."` with escapes, or a raw string `r#"..."#`.
    Str(String),
    /// `'a'`.
    Char(char),
    /// `()`.
    Unit,
    /// A bare identifier such as `test_card` or `Reflect101` (also `r#name`).
    Ident(String),
    /// `None` / `Some(x)`.
    Option(Option<Box<Spanned<RonValue>>>),
    /// `[a, b, c]`.
    List(Vec<Spanned<RonValue>>),
    /// `{ key: value, ... }`; entries in source order, duplicate keys kept.
    Map(Vec<(Spanned<RonValue>, Spanned<RonValue>)>),
    /// `Name(field: value, ...)` or `(field: value, ...)`.
    Struct {
        /// The struct name, if written.
        name: Option<Spanned<String>>,
        /// Fields in source order; names are unique.
        fields: Vec<(Spanned<String>, Spanned<RonValue>)>,
    },
    /// `Name(a, b)` or `(a, b)`; `Name()` is a tuple with no items.
    Tuple {
        /// The tuple name, if written.
        name: Option<Spanned<String>>,
        /// Items in source order.
        items: Vec<Spanned<RonValue>>,
    },
}

impl RonValue {
    /// Short human name of the kind, for error messages ("integer", "struct", ...).
    pub fn kind_name(&self) -> &'static str {
        match self {
            RonValue::Bool(_) => "boolean",
            RonValue::Int(_) => "integer",
            RonValue::Float(_) => "float",
            RonValue::Str(_) => "string",
            RonValue::Char(_) => "char",
            RonValue::Unit => "unit",
            RonValue::Ident(_) => "identifier",
            RonValue::Option(_) => "option",
            RonValue::List(_) => "list",
            RonValue::Map(_) => "map",
            RonValue::Struct { .. } => "struct",
            RonValue::Tuple { .. } => "tuple",
        }
    }
}

/// A syntax error with the span of the offending text.
#[derive(Debug, Clone, PartialEq)]
pub struct ParseError {
    /// What went wrong, e.g. "expected `,` or `)`".
    pub message: String,
    /// Where it went wrong (zero-width at the end of input for a premature end).
    pub span: Span,
    /// Optional hint, e.g. "strings use double quotes".
    pub help: Option<String>,
}

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)?;
        if let Some(help) = &self.help {
            write!(f, " (help: {help})")?;
        }
        Ok(())
    }
}

impl std::error::Error for ParseError {}

/// Parses a whole document: exactly one value, surrounded by whitespace and comments.
///
/// Leading `#![enable(...)]` extension attributes are accepted and ignored.
pub fn parse(src: &str) -> Result<Spanned<RonValue>, ParseError> {
    let mut p = Parser {
        src,
        pos: if src.starts_with('\u{feff}') { 3 } else { 0 },
        depth: 0,
    };
    p.parse_attributes()?;
    p.skip_ws()?;
    if p.peek().is_none() {
        let end = Span::new(src.len(), src.len());
        return fail("empty document, expected a value", end, "");
    }
    let value = p.parse_value()?;
    p.skip_ws()?;
    if p.pos < src.len() {
        return fail(
            "unexpected trailing characters",
            p.here(),
            "a RON document holds exactly one value",
        );
    }
    Ok(value)
}

/// 1-based `(line, column)` of byte `offset` in `src`; the column counts chars.
///
/// An offset past the end maps to the end; an offset inside a multi-byte char maps to that char.
pub fn line_col(src: &str, offset: usize) -> (usize, usize) {
    let mut off = offset.min(src.len());
    while off > 0 && !src.is_char_boundary(off) {
        off -= 1;
    }
    let before = src.get(..off).unwrap_or_default();
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let line = before.bytes().filter(|&b| b == b'\n').count() + 1;
    let col = before.get(line_start..).unwrap_or_default().chars().count() + 1;
    (line, col)
}

/// Renders a value as compact, deterministic RON text that [`parse`] reads back.
///
/// Floats use the shortest round-trip form and always contain `.` or `e` (or are
/// `inf`/`NaN`); identifiers that would read back as keywords are written `r#name`.
pub fn to_ron_string(v: &RonValue) -> String {
    let mut out = String::new();
    write_value(&mut out, v);
    out
}

fn write_value(out: &mut String, v: &RonValue) {
    match v {
        RonValue::Bool(b) => out.push_str(if *b { "true" } else { "false" }),
        RonValue::Int(i) => out.push_str(&i.to_string()),
        RonValue::Float(f) => {
            let text = format!("{f:?}");
            out.push_str(&text);
            if !text.contains(['.', 'e', 'E', 'n', 'N']) {
                out.push_str(".0");
            }
        }
        RonValue::Str(s) => {
            out.push('"');
            s.chars().for_each(|c| push_escaped(out, c, '"'));
            out.push('"');
        }
        RonValue::Char(c) => {
            out.push('\'');
            push_escaped(out, *c, '\'');
            out.push('\'');
        }
        RonValue::Unit => out.push_str("()"),
        RonValue::Ident(name) => write_ident(out, name),
        RonValue::Option(None) => out.push_str("None"),
        RonValue::Option(Some(inner)) => {
            out.push_str("Some");
            write_seq(out, '(', ')', std::slice::from_ref(&**inner), write_item);
        }
        RonValue::List(items) => write_seq(out, '[', ']', items, write_item),
        RonValue::Map(entries) => write_seq(out, '{', '}', entries, |out, (k, v)| {
            write_value(out, &k.value);
            out.push(':');
            write_value(out, &v.value);
        }),
        RonValue::Struct { name, fields } => {
            if let Some(name) = name {
                write_ident(out, &name.value);
            }
            write_seq(out, '(', ')', fields, |out, (k, v)| {
                write_ident(out, &k.value);
                out.push(':');
                write_value(out, &v.value);
            });
        }
        RonValue::Tuple { name, items } => {
            if let Some(name) = name {
                write_ident(out, &name.value);
            }
            write_seq(out, '(', ')', items, write_item);
        }
    }
}

fn write_item(out: &mut String, item: &Node) {
    write_value(out, &item.value);
}

fn write_seq<T>(out: &mut String, open: char, close: char, items: &[T], f: fn(&mut String, &T)) {
    out.push(open);
    for (i, item) in items.iter().enumerate() {
        if i > 0 {
            out.push(',');
        }
        f(out, item);
    }
    out.push(close);
}

fn write_ident(out: &mut String, name: &str) {
    let keyword = matches!(name, "true" | "false" | "inf" | "NaN" | "None" | "Some");
    out.push_str(if keyword { "r#" } else { "" });
    out.push_str(name);
}

fn push_escaped(out: &mut String, c: char, quote: char) {
    match c {
        '\\' => out.push_str("\\\\"),
        '\n' => out.push_str("\\n"),
        '\r' => out.push_str("\\r"),
        '\t' => out.push_str("\\t"),
        '\0' => out.push_str("\\0"),
        c if c == quote => {
            out.push('\\');
            out.push(c);
        }
        c if c.is_control() => out.push_str(&format!("\\u{{{:x}}}", u32::from(c))),
        c => out.push(c),
    }
}

type Node = Spanned<RonValue>;
type PResult<T> = Result<T, ParseError>;

const ESCAPE_HELP: &str = "valid escapes are \\n \\r \\t \\\\ \\\" \\' \\0 and \\u{1F600}";
const UNICODE_HELP: &str = "write unicode escapes as `\\u{1F600}`: 1 to 6 hex digits of a char";
const ATTR_HELP: &str = "extension attributes look like `#![enable(implicit_some)]`";
const FIELD_HELP: &str = "struct fields are written `name: value`";
const COLON_HELP: &str =
    "`key: value` pairs belong in a map `{...}` or in a struct with identifier field names";

/// Builds an error; an empty `help` means none.
fn error(message: impl Into<String>, span: Span, help: impl Into<String>) -> ParseError {
    let help: String = help.into();
    let help = (!help.is_empty()).then_some(help);
    ParseError {
        message: message.into(),
        span,
        help,
    }
}

fn fail<T>(message: impl Into<String>, span: Span, help: impl Into<String>) -> PResult<T> {
    Err(error(message, span, help))
}

fn node(value: RonValue, start: usize, end: usize) -> Node {
    Spanned::new(value, Span::new(start, end))
}

fn is_ident_start(b: u8) -> bool {
    b.is_ascii_alphabetic() || b == b'_'
}

fn is_ident_continue(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'_'
}

/// Decodes the escape after the backslash at `esc`; `it` yields offsets relative to `base`.
/// `Ok(None)` means the input ended inside the escape.
fn escape(it: &mut CharIndices<'_>, base: usize, esc: usize) -> PResult<Option<char>> {
    let Some((i, c)) = it.next() else {
        return Ok(None);
    };
    let decoded = match c {
        'n' => '\n',
        'r' => '\r',
        't' => '\t',
        '0' => '\0',
        '\\' | '"' | '\'' => c,
        'u' => {
            let bad =
                |end: usize| error("invalid unicode escape", Span::new(esc, end), UNICODE_HELP);
            match it.next() {
                None => return Ok(None),
                Some((_, '{')) => {}
                Some((j, c)) => return Err(bad(base + j + c.len_utf8())),
            }
            let (mut value, mut digits) = (0u32, 0);
            loop {
                match it.next() {
                    None => return Ok(None),
                    Some((j, '}')) => match char::from_u32(value).filter(|_| digits > 0) {
                        Some(ch) => break ch,
                        None => return Err(bad(base + j + 1)),
                    },
                    Some((j, c)) => match c.to_digit(16) {
                        Some(d) if digits < 6 => (value, digits) = (value * 16 + d, digits + 1),
                        _ => return Err(bad(base + j + c.len_utf8())),
                    },
                }
            }
        }
        other => {
            let span = Span::new(esc, base + i + other.len_utf8());
            return fail(
                format!("invalid escape `\\{}`", other.escape_debug()),
                span,
                ESCAPE_HELP,
            );
        }
    };
    Ok(Some(decoded))
}

/// Recursive-descent parser over the source; `pos` is always on a char boundary.
struct Parser<'a> {
    src: &'a str,
    pos: usize,
    depth: usize,
}

impl<'a> Parser<'a> {
    fn peek(&self) -> Option<u8> {
        self.src.as_bytes().get(self.pos).copied()
    }

    fn peek_at(&self, ahead: usize) -> Option<u8> {
        self.src.as_bytes().get(self.pos + ahead).copied()
    }

    fn slice(&self, start: usize, end: usize) -> &'a str {
        self.src.get(start..end).unwrap_or_default()
    }

    fn char_at(&self, at: usize) -> Option<char> {
        self.src.get(at..).and_then(|s| s.chars().next())
    }

    fn char_span(&self, at: usize) -> Span {
        Span::new(at, at + self.char_at(at).map_or(0, char::len_utf8))
    }

    /// Span of the char at the current position.
    fn here(&self) -> Span {
        self.char_span(self.pos)
    }

    fn unclosed(&self, open: usize) -> String {
        let (line, col) = line_col(self.src, open);
        let c = self.char_at(open).unwrap_or('(');
        format!("the `{c}` at line {line}, column {col} is not closed")
    }

    fn eof(&self, expected: &str, open: Option<usize>) -> ParseError {
        let message = format!("unexpected end of input, expected {expected}");
        let help = open.map(|open| self.unclosed(open)).unwrap_or_default();
        error(message, Span::new(self.src.len(), self.src.len()), help)
    }

    fn unexpected(&self, at: usize) -> ParseError {
        let Some(c) = self.char_at(at) else {
            return self.eof("a value", None);
        };
        let help = match c {
            '#' => "`#![enable(...)]` attributes are only allowed at the start of the document",
            '=' => "use `:` between a field name and its value",
            ',' => "expected a value before this comma",
            ';' => "separate items with `,`",
            _ => "expected a value",
        };
        let message = format!("unexpected character `{}`", c.escape_debug());
        error(message, self.char_span(at), help)
    }

    /// Skips whitespace, `// line` comments and nesting `/* block */` comments.
    fn skip_ws(&mut self) -> PResult<()> {
        loop {
            match (self.peek(), self.peek_at(1)) {
                (Some(b' ' | b'\t' | b'\n' | b'\r'), _) => self.pos += 1,
                (Some(b'/'), Some(b'/')) => {
                    let rest = self.src.as_bytes().get(self.pos..).unwrap_or_default();
                    self.pos += rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
                }
                (Some(b'/'), Some(b'*')) => {
                    let start = self.pos;
                    self.pos += 2;
                    let mut level = 1usize;
                    while level > 0 {
                        match (self.peek(), self.peek_at(1)) {
                            (None, _) => {
                                let span = Span::new(start, start + 2);
                                let help = "block comments nest: every `/*` needs its own `*/`";
                                return fail("unterminated block comment", span, help);
                            }
                            (Some(b'/'), Some(b'*')) => {
                                level += 1;
                                self.pos += 2;
                            }
                            (Some(b'*'), Some(b'/')) => {
                                level -= 1;
                                self.pos += 2;
                            }
                            _ => self.pos += 1,
                        }
                    }
                }
                _ => return Ok(()),
            }
        }
    }

    /// Skips any number of `#![enable(name, ...)]` attributes.
    fn parse_attributes(&mut self) -> PResult<()> {
        while self.skip_ws().map(|()| self.peek() == Some(b'#'))? {
            self.pos += 1;
            for token in ["!", "[", "enable", "("] {
                self.expect_token(token)?;
            }
            self.skip_ws()?;
            while self.peek().is_some_and(is_ident_start) {
                self.scan_ident();
                self.skip_ws()?;
                if self.peek() != Some(b',') {
                    break;
                }
                self.pos += 1;
                self.skip_ws()?;
            }
            self.expect_token(")")?;
            self.expect_token("]")?;
        }
        Ok(())
    }

    fn expect_token(&mut self, token: &str) -> PResult<()> {
        self.skip_ws()?;
        let rest = self.src.get(self.pos..).unwrap_or_default();
        let word = token.bytes().all(is_ident_continue);
        let after = rest.as_bytes().get(token.len()).copied();
        if rest.starts_with(token) && !(word && after.is_some_and(is_ident_continue)) {
            self.pos += token.len();
            return Ok(());
        }
        if rest.is_empty() {
            return Err(self.eof(&format!("`{token}`"), None));
        }
        fail(format!("expected `{token}`"), self.here(), ATTR_HELP)
    }

    /// Scans `[A-Za-z0-9_]*` from the current position (empty if none).
    fn scan_ident(&mut self) -> &'a str {
        let start = self.pos;
        while self.peek().is_some_and(is_ident_continue) {
            self.pos += 1;
        }
        self.slice(start, self.pos)
    }

    /// Scans a field name `ident` or `r#ident`; `None` (position unchanged) if there is none.
    fn scan_field_name(&mut self) -> Option<Spanned<String>> {
        let start = self.pos;
        match (self.peek(), self.peek_at(1)) {
            (Some(b'r'), Some(b'#')) if self.peek_at(2).is_some_and(is_ident_start) => {
                self.pos += 2
            }
            (Some(b'r'), Some(b'#' | b'"')) => return None, // a raw string
            (Some(b), _) if is_ident_start(b) => {}
            _ => return None,
        }
        let name = self.scan_ident().to_string();
        Some(Spanned::new(name, Span::new(start, self.pos)))
    }

    fn parse_value(&mut self) -> PResult<Node> {
        self.skip_ws()?;
        let start = self.pos;
        match self.peek() {
            None => Err(self.eof("a value", None)),
            Some(b'"') => self.parse_string(),
            Some(b'\'') => self.parse_char(),
            Some(b'[') => {
                let mut items = Vec::new();
                self.seq(b']', "a value or `]`", |p| {
                    items.push(p.parse_value()?);
                    Ok(None)
                })?;
                Ok(node(RonValue::List(items), start, self.pos))
            }
            Some(b'{') => {
                let mut entries = Vec::new();
                self.seq(b'}', "a map key or `}`", |p| {
                    let key = p.parse_value()?;
                    p.expect_colon("map key", "map entries are written `key: value`")?;
                    entries.push((key, p.parse_value()?));
                    Ok(None)
                })?;
                Ok(node(RonValue::Map(entries), start, self.pos))
            }
            Some(b'(') => self.parse_paren(None, start),
            Some(b'r') if matches!(self.peek_at(1), Some(b'"' | b'#')) => self.parse_raw(),
            Some(b'0'..=b'9' | b'+' | b'-' | b'.') => self.parse_number(),
            Some(b) if is_ident_start(b) => {
                let name = self.scan_ident().to_string();
                self.ident_tail(name, start, false)
            }
            Some(_) => Err(self.unexpected(start)),
        }
    }

    /// Parses `open item, item, ... close` (trailing comma allowed), starting on `open`.
    /// `item` parses one item; it may return the span of an identifier item, used for a hint
    /// when the separator after it is missing (`(a 1)` probably meant `(a: 1)`).
    fn seq<F>(&mut self, close: u8, expected: &str, mut item: F) -> PResult<()>
    where
        F: FnMut(&mut Self) -> PResult<Option<Span>>,
    {
        let open = self.pos;
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            let help = "flatten the document; deeply nested values are not supported";
            return fail(
                format!("nesting too deep (limit {MAX_DEPTH})"),
                self.here(),
                help,
            );
        }
        self.pos += 1;
        while !self.at_close(open, close, expected)? {
            let hint = item(self)?;
            if self.item_end(open, close, hint)? {
                break;
            }
        }
        self.depth -= 1;
        Ok(())
    }

    /// Skips whitespace and consumes `close` if it is next.
    fn at_close(&mut self, open: usize, close: u8, expected: &str) -> PResult<bool> {
        self.skip_ws()?;
        match self.peek() {
            Some(b) if b == close => {
                self.pos += 1;
                Ok(true)
            }
            None => Err(self.eof(expected, Some(open))),
            _ => Ok(false),
        }
    }

    /// After an item: consumes `,` (→ `false`) or `close` (→ `true`).
    fn item_end(&mut self, open: usize, close: u8, ident: Option<Span>) -> PResult<bool> {
        self.skip_ws()?;
        let found = match self.peek() {
            Some(b) if b == b',' || b == close => {
                self.pos += 1;
                return Ok(b == close);
            }
            found => found,
        };
        let expected = format!("`,` or `{}`", char::from(close));
        let hint = ident.map(|s| self.slice(s.start, s.end));
        let help = match (found, hint) {
            (None, _) => return Err(self.eof(&expected, Some(open))),
            (Some(b')' | b']' | b'}'), _) => self.unclosed(open),
            (_, Some(n)) => format!("if `{n}` is a field name, write `{n}: value`"),
            (Some(b':'), None) => COLON_HELP.to_string(),
            (Some(_), None) => "items must be separated by commas".to_string(),
        };
        fail(format!("expected {expected}"), self.here(), help)
    }

    fn expect_colon(&mut self, after: &str, help: &str) -> PResult<()> {
        self.skip_ws()?;
        match self.peek() {
            Some(b':') => {
                self.pos += 1;
                Ok(())
            }
            None => Err(self.eof("`:`", None)),
            Some(_) => fail(format!("expected `:` after {after}"), self.here(), help),
        }
    }

    /// After an identifier (already consumed): keyword, `Some(..)`, named struct/tuple, or ident.
    fn ident_tail(&mut self, name: String, start: usize, raw: bool) -> PResult<Node> {
        let span = Span::new(start, self.pos);
        let keyword = match name.as_str() {
            _ if raw => None,
            "true" => Some(RonValue::Bool(true)),
            "false" => Some(RonValue::Bool(false)),
            "inf" => Some(RonValue::Float(f64::INFINITY)),
            "NaN" => Some(RonValue::Float(f64::NAN)),
            "None" => Some(RonValue::Option(None)),
            _ => None,
        };
        if let Some(value) = keyword {
            return Ok(Spanned::new(value, span));
        }
        self.skip_ws()?;
        let is_some = !raw && name == "Some";
        if self.peek() == Some(b'(') {
            if is_some {
                return self.parse_some(start);
            }
            return self.parse_paren(Some(Spanned::new(name, span)), start);
        }
        self.pos = span.end;
        if is_some {
            return fail(
                "expected `(` after `Some`",
                span,
                "write `Some(value)`, or `None`",
            );
        }
        Ok(Spanned::new(RonValue::Ident(name), span))
    }

    /// `Some(value)`, starting on the `(`.
    fn parse_some(&mut self, start: usize) -> PResult<Node> {
        let mut inner = None;
        self.seq(b')', "a value or `)`", |p| {
            if inner.is_some() {
                return fail("expected `)`", p.here(), "`Some` holds exactly one value");
            }
            inner = Some(Box::new(p.parse_value()?));
            Ok(None)
        })?;
        let span = Span::new(start, self.pos);
        match inner {
            Some(inner) => Ok(Spanned::new(RonValue::Option(Some(inner)), span)),
            None => fail("`Some` needs a value", span, "write `None` for no value"),
        }
    }

    /// Unit, struct or tuple, starting on the `(`; `start` is where the value (name) began.
    fn parse_paren(&mut self, name: Option<Spanned<String>>, start: usize) -> PResult<Node> {
        let open = self.pos;
        self.pos += 1;
        // Lookahead: the first item is `ident:` (not `::`) in a struct.
        let is_struct = self.skip_ws().is_ok()
            && self.scan_field_name().is_some()
            && self.skip_ws().is_ok()
            && self.peek() == Some(b':')
            && self.peek_at(1) != Some(b':');
        self.pos = open;
        let value = if is_struct {
            let mut fields = Vec::new();
            let mut seen = HashMap::new();
            self.seq(b')', "a field name or `)`", |p| {
                fields.push(p.parse_field(&mut seen)?);
                Ok(None)
            })?;
            RonValue::Struct { name, fields }
        } else {
            let mut items = Vec::new();
            self.seq(b')', "a value or `)`", |p| {
                let item = p.parse_value()?;
                let ident = matches!(item.value, RonValue::Ident(_)).then_some(item.span);
                items.push(item);
                Ok(ident)
            })?;
            match name {
                None if items.is_empty() => RonValue::Unit,
                name => RonValue::Tuple { name, items },
            }
        };
        Ok(node(value, start, self.pos))
    }

    fn parse_field(
        &mut self,
        seen: &mut HashMap<String, Span>,
    ) -> PResult<(Spanned<String>, Node)> {
        let Some(name) = self.scan_field_name() else {
            let help = match self.peek() {
                Some(b'"') => "field names are bare identifiers, without quotes",
                _ => FIELD_HELP,
            };
            return fail("expected a field name", self.here(), help);
        };
        if let Some(first) = seen.insert(name.value.clone(), name.span) {
            let (line, col) = line_col(self.src, first.start);
            let help = format!(
                "`{}` was first set at line {line}, column {col}",
                name.value
            );
            return fail(format!("duplicate field `{}`", name.value), name.span, help);
        }
        self.expect_colon(&format!("field name `{}`", name.value), FIELD_HELP)?;
        Ok((name, self.parse_value()?))
    }

    /// `r"..."`, `r#"..."#` (any number of `#`), or the raw identifier `r#name`.
    fn parse_raw(&mut self) -> PResult<Node> {
        let start = self.pos;
        let bytes = self.src.as_bytes();
        let mut p = start + 1;
        while bytes.get(p) == Some(&b'#') {
            p += 1;
        }
        let hashes = p - start - 1;
        match bytes.get(p) {
            Some(b'"') => {
                let content = p + 1;
                let mut from = content;
                // Only quotes are candidates, and the `#` runs checked after them are disjoint,
                // so this stays linear however many `#` there are.
                while let Some(q) = bytes
                    .get(from..)
                    .and_then(|r| r.iter().position(|&b| b == b'"'))
                {
                    let (quote, end) = (from + q, from + q + 1 + hashes);
                    if bytes
                        .get(quote + 1..end)
                        .is_some_and(|h| h.iter().all(|&b| b == b'#'))
                    {
                        let text = self.slice(content, quote).to_string();
                        self.pos = end;
                        return Ok(node(RonValue::Str(text), start, end));
                    }
                    from = quote + 1;
                }
                let help = format!("close it with `\"{}`", "#".repeat(hashes));
                fail(
                    "unterminated raw string",
                    Span::new(start, bytes.len()),
                    help,
                )
            }
            Some(&b) if hashes == 1 && is_ident_start(b) => {
                self.pos = p;
                let name = self.scan_ident().to_string();
                self.ident_tail(name, start, true)
            }
            _ => {
                let help = "raw strings look like `r#\"...\"#`, raw identifiers like `r#name`";
                fail(
                    "expected `\"` or an identifier after `r#`",
                    Span::new(start, p),
                    help,
                )
            }
        }
    }

    fn parse_string(&mut self) -> PResult<Node> {
        let start = self.pos;
        let base = start + 1;
        let mut it = self.src.get(base..).unwrap_or_default().char_indices();
        let mut out = String::new();
        while let Some((i, c)) = it.next() {
            match c {
                '"' => {
                    self.pos = base + i + 1;
                    return Ok(node(RonValue::Str(out), start, self.pos));
                }
                '\\' => match escape(&mut it, base, base + i)? {
                    Some(e) => out.push(e),
                    None => break,
                },
                c => out.push(c),
            }
        }
        fail(
            "unterminated string",
            Span::new(start, self.src.len()),
            "add a closing `\"`",
        )
    }

    fn parse_char(&mut self) -> PResult<Node> {
        let start = self.pos;
        let base = start + 1;
        let rest = self.src.get(base..).unwrap_or_default();
        let mut it = rest.char_indices();
        let quotes = "strings use double quotes";
        let unterminated = |end| {
            error(
                "unterminated character literal",
                Span::new(start, end),
                quotes,
            )
        };
        let c = match it.next() {
            None => return Err(unterminated(self.src.len())),
            Some((_, '\'')) => {
                return fail(
                    "empty character literal",
                    Span::new(start, base + 1),
                    quotes,
                );
            }
            Some((i, '\\')) => {
                escape(&mut it, base, base + i)?.ok_or_else(|| unterminated(self.src.len()))?
            }
            Some((_, c)) => c,
        };
        if let Some((k, '\'')) = it.next() {
            self.pos = base + k + 1;
            return Ok(node(RonValue::Char(c), start, self.pos));
        }
        let line = rest.split('\n').next().unwrap_or_default();
        match line.find('\'') {
            Some(q) => {
                let message = "character literal may only contain one character";
                fail(message, Span::new(start, base + q + 1), quotes)
            }
            None => Err(unterminated(base + line.len())),
        }
    }

    fn parse_number(&mut self) -> PResult<Node> {
        let start = self.pos;
        let neg = self.peek() == Some(b'-');
        if matches!(self.peek(), Some(b'+' | b'-')) {
            self.pos += 1;
        }
        let sign = self.slice(start, self.pos);
        match self.peek() {
            Some(b'0'..=b'9') => {}
            Some(b'.') if self.peek_at(1).is_some_and(|b| b.is_ascii_digit()) => {
                self.pos += 1;
                let digits_at = self.pos;
                self.eat_digits(10);
                let digits = self.slice(digits_at, self.pos);
                let span = Span::new(start, self.pos);
                let help = format!("write `{sign}0.{digits}`");
                return fail("a float needs a digit before the `.`", span, help);
            }
            _ if sign.is_empty() => return Err(self.unexpected(start)),
            _ => {
                let word = self.scan_ident();
                let span = Span::new(start, self.pos.max(start + 1));
                let value = match word {
                    "inf" if neg => f64::NEG_INFINITY,
                    "inf" => f64::INFINITY,
                    "NaN" => f64::NAN,
                    _ => return fail(format!("expected a number after `{sign}`"), span, ""),
                };
                return Ok(Spanned::new(RonValue::Float(value), span));
            }
        }
        let radix = match (self.peek_at(0), self.peek_at(1)) {
            (Some(b'0'), Some(b'x')) => Some((16, "hexadecimal")),
            (Some(b'0'), Some(b'o')) => Some((8, "octal")),
            (Some(b'0'), Some(b'b')) => Some((2, "binary")),
            _ => None,
        };
        if let Some((radix, what)) = radix {
            self.pos += 2;
            let (magnitude, count) = self.eat_digits(radix);
            if count == 0 {
                return fail(
                    format!("expected {what} digits"),
                    Span::new(start, self.pos),
                    "",
                );
            }
            return self.finish_int(start, neg, magnitude);
        }
        let (magnitude, _) = self.eat_digits(10);
        let mut is_float = false;
        if self.peek() == Some(b'.') {
            is_float = true;
            self.pos += 1;
            self.eat_digits(10);
        }
        if matches!(self.peek(), Some(b'e' | b'E')) {
            is_float = true;
            self.pos += 1;
            if matches!(self.peek(), Some(b'+' | b'-')) {
                self.pos += 1;
            }
            if self.eat_digits(10).1 == 0 {
                let span = Span::new(start, self.pos);
                return fail(
                    "expected digits in the exponent",
                    span,
                    "write e.g. `1e3` or `1.5e-3`",
                );
            }
        }
        if !is_float {
            return self.finish_int(start, neg, magnitude);
        }
        self.check_number_end()?;
        let span = Span::new(start, self.pos);
        let text = self.slice(start, self.pos).replace('_', "");
        match text.parse::<f64>() {
            Ok(f) => Ok(Spanned::new(RonValue::Float(f), span)),
            Err(_) => fail("invalid float literal", span, ""),
        }
    }

    /// Consumes digits of `radix` and `_` separators: (magnitude if it fits in u64, digit count).
    fn eat_digits(&mut self, radix: u32) -> (Option<u64>, usize) {
        let mut value = Some(0u64);
        let mut count = 0;
        while let Some(b) = self.peek() {
            if b != b'_' {
                let Some(d) = char::from(b).to_digit(radix) else {
                    break;
                };
                value =
                    value.and_then(|v| v.checked_mul(u64::from(radix))?.checked_add(u64::from(d)));
                count += 1;
            }
            self.pos += 1;
        }
        (value, count)
    }

    /// Rejects a letter, digit or `.` glued to the end of a number.
    fn check_number_end(&self) -> PResult<()> {
        match self.peek() {
            Some(b) if is_ident_continue(b) || b == b'.' => fail(
                format!("invalid character `{}` in number", char::from(b)),
                self.here(),
                "",
            ),
            _ => Ok(()),
        }
    }

    fn finish_int(&self, start: usize, neg: bool, magnitude: Option<u64>) -> PResult<Node> {
        self.check_number_end()?;
        let span = Span::new(start, self.pos);
        let value = match magnitude {
            Some(m) if neg => 0i64.checked_sub_unsigned(m),
            Some(m) => i64::try_from(m).ok(),
            None => None,
        };
        match value {
            Some(v) => Ok(Spanned::new(RonValue::Int(v), span)),
            None => fail("integer out of range", span, "integers must fit in an i64"),
        }
    }
}

/// The kind of a value with its article, for messages: "an integer", "a string".
pub fn a_kind(value: &RonValue) -> String {
    let kind = value.kind_name();
    let article = if kind.starts_with(['a', 'e', 'i', 'o', 'u']) {
        "an"
    } else {
        "a"
    };
    format!("{article} {kind}")
}
#[cfg(test)]
mod tests {
    use super::*;
    use RonValue::{Bool, Char, Float, Ident, Int, List, Str};

    const DOC: &str = r#"Graph(
    name: "edges",
    nodes: {
        "card":  (op: "capture.pattern",  params: (kind: "test_card", width: 1920, height: 1080)),
        "blur":  (op: "filter.gaussian",  inputs: { "image": "card.image" }, params: (sigma: 1.5)),
    },
    outputs: { "edges": "edges.edges" },
)"#;

    fn ok(src: &str) -> Node {
        parse(src).unwrap_or_else(|e| panic!("parse({src:?}) failed: {e} at {:?}", e.span))
    }

    fn fail(src: &str) -> ParseError {
        match parse(src) {
            Ok(v) => panic!("parse({src:?}) unexpectedly succeeded: {v:?}"),
            Err(e) => e,
        }
    }

    fn sp(start: usize, end: usize) -> Span {
        Span::new(start, end)
    }

    fn s(text: &str) -> RonValue {
        Str(text.to_string())
    }

    /// Asserts `src` parses to `value` spanning `start..end`.
    fn check(src: &str, value: RonValue, start: usize, end: usize) {
        let v = ok(src);
        assert_eq!((v.value, v.span), (value, sp(start, end)), "{src:?}");
    }

    /// Asserts `src` fails with a message containing `msg` at `start..end`.
    fn check_err(src: &str, msg: &str, start: usize, end: usize) -> ParseError {
        let e = fail(src);
        assert!(e.message.contains(msg), "{src:?}: {e:?} lacks {msg:?}");
        assert_eq!(e.span, sp(start, end), "{src:?}: span of {:?}", e.message);
        e
    }

    type Name<'v> = Option<&'v Spanned<String>>;

    fn struct_of(v: &RonValue) -> (Name<'_>, &[(Spanned<String>, Node)]) {
        match v {
            RonValue::Struct { name, fields } => (name.as_ref(), fields),
            _ => panic!("not a struct: {v:?}"),
        }
    }

    fn tuple_of(v: &RonValue) -> (Name<'_>, &[Node]) {
        match v {
            RonValue::Tuple { name, items } => (name.as_ref(), items),
            _ => panic!("not a tuple: {v:?}"),
        }
    }

    fn map_of(v: &RonValue) -> &[(Node, Node)] {
        match v {
            RonValue::Map(entries) => entries,
            _ => panic!("not a map: {v:?}"),
        }
    }

    fn field<'v>(v: &'v RonValue, name: &str) -> &'v Node {
        let found = struct_of(v).1.iter().find(|(k, _)| k.value == name);
        found.map_or_else(|| panic!("no field {name}"), |(_, v)| v)
    }

    fn entry<'v>(v: &'v RonValue, key: &str) -> &'v Node {
        let found = map_of(v).iter().find(|(k, _)| k.value == s(key));
        found.map_or_else(|| panic!("no key {key}"), |(_, v)| v)
    }

    /// The value with every span reset, to compare values modulo positions.
    fn strip(v: &RonValue) -> RonValue {
        let st = |x: &Node| Spanned::new(strip(&x.value), Span::default());
        let name = |x: &Spanned<String>| Spanned::new(x.value.clone(), Span::default());
        match v {
            RonValue::Option(o) => RonValue::Option(o.as_deref().map(|x| Box::new(st(x)))),
            List(items) => List(items.iter().map(st).collect()),
            RonValue::Map(es) => RonValue::Map(es.iter().map(|(k, v)| (st(k), st(v))).collect()),
            RonValue::Struct { name: n, fields } => RonValue::Struct {
                name: n.as_ref().map(name),
                fields: fields.iter().map(|(k, v)| (name(k), st(v))).collect(),
            },
            RonValue::Tuple { name: n, items } => RonValue::Tuple {
                name: n.as_ref().map(name),
                items: items.iter().map(st).collect(),
            },
            other => other.clone(),
        }
    }

    #[test]
    fn span_helpers() {
        let a = sp(3, 7);
        assert_eq!((a.len(), a.is_empty()), (4, false));
        assert!(sp(5, 5).is_empty() && sp(9, 2).is_empty());
        assert_eq!(sp(9, 2).len(), 0);
        assert_eq!(a.join(sp(10, 12)), sp(3, 12));
        assert_eq!(sp(10, 12).join(a), sp(3, 12));
        assert_eq!(a.join(sp(4, 5)), a);
    }

    #[test]
    fn numbers() {
        for (src, value, start, end) in [
            ("  42 ", Int(42), 2, 4),
            ("-17", Int(-17), 0, 3),
            ("+5", Int(5), 0, 2),
            ("1_000_000", Int(1_000_000), 0, 9),
            ("0xff", Int(255), 0, 4),
            ("0xFF_FF", Int(0xffff), 0, 7),
            ("0o17", Int(15), 0, 4),
            ("0b1010", Int(10), 0, 6),
            ("-0x10", Int(-16), 0, 5),
            ("007", Int(7), 0, 3),
            ("9223372036854775807", Int(i64::MAX), 0, 19),
            ("-9223372036854775808", Int(i64::MIN), 0, 20),
            ("1.5", Float(1.5), 0, 3),
            ("1e3", Float(1000.0), 0, 3),
            ("-2.", Float(-2.0), 0, 3),
            ("1.", Float(1.0), 0, 2),
            (" 2.5e-3", Float(0.0025), 1, 7),
            ("1E+2", Float(100.0), 0, 4),
            ("1_000.25", Float(1000.25), 0, 8),
            ("inf", Float(f64::INFINITY), 0, 3),
            ("-inf", Float(f64::NEG_INFINITY), 0, 4),
            ("+inf", Float(f64::INFINITY), 0, 4),
        ] {
            check(src, value, start, end);
        }
        let nan = ok(" NaN");
        assert!(matches!(nan.value, Float(f) if f.is_nan()) && nan.span == sp(1, 4));
        assert!(matches!(ok("-NaN").value, Float(f) if f.is_nan()));
    }

    #[test]
    fn number_errors() {
        for (src, msg, start, end) in [
            ("9223372036854775808", "integer out of range", 0, 19),
            ("[1, -9223372036854775809]", "integer out of range", 4, 24),
            ("0xffffffffffffffffff", "integer out of range", 0, 20),
            ("0x", "expected hexadecimal digits", 0, 2),
            ("0b102", "invalid character `2` in number", 4, 5),
            ("12abc", "invalid character `a` in number", 2, 3),
            ("-", "expected a number after `-`", 0, 1),
            ("-x", "expected a number after `-`", 0, 2),
            ("1e", "expected digits in the exponent", 0, 2),
            ("1.2.3", "invalid character `.` in number", 3, 4),
            (".", "unexpected character `.`", 0, 1),
        ] {
            check_err(src, msg, start, end);
        }
        let e = check_err(".5", "a float needs a digit before the `.`", 0, 2);
        assert_eq!(e.help.as_deref(), Some("write `0.5`"));
        let e = check_err("-.25", "a float needs a digit before the `.`", 0, 4);
        assert_eq!(e.help.as_deref(), Some("write `-0.25`"));
    }

    #[test]
    fn strings_and_chars() {
        for (src, value, start, end) in [
            (r#""hello""#, s("hello"), 0, 7),
            (r#" "a\nb\t\"q\"\\\0\'" "#, s("a\nb\t\"q\"\\\0'"), 1, 20),
            (r#""\u{1F600}x""#, s("\u{1F600}x"), 0, 12),
            ("\"héllo\"", s("héllo"), 0, 8),
            ("\"multi\nline\"", s("multi\nline"), 0, 12),
            (r#"r"a\nb""#, s("a\\nb"), 0, 7),
            (r##"r#"say "hi""#"##, s("say \"hi\""), 0, 13),
            (r###"r##"a "# b"##"###, s("a \"# b"), 0, 13),
            (r#"r"""#, s(""), 0, 3),
            ("'a'", Char('a'), 0, 3),
            (" '\\n'", Char('\n'), 1, 5),
            ("'\\''", Char('\''), 0, 4),
            ("'é'", Char('é'), 0, 4),
            ("'\\u{e9}'", Char('é'), 0, 8),
        ] {
            check(src, value, start, end);
        }
    }

    #[test]
    fn string_and_char_errors() {
        for (src, msg, start, end) in [
            (r#"  "abc"#, "unterminated string", 2, 6),
            (r#""abc\"#, "unterminated string", 0, 5),
            (r##"r#"abc"##, "unterminated raw string", 0, 6),
            (r#""a\qb""#, "invalid escape `\\q`", 2, 4),
            (r#""\u{110000}""#, "invalid unicode escape", 1, 11),
            (r#""\u{}""#, "invalid unicode escape", 1, 5),
            (r#""\u{1234567}""#, "invalid unicode escape", 1, 11),
            (r#""\u0041""#, "invalid unicode escape", 1, 4),
            ("r##x", "expected `\"` or an identifier after `r#`", 0, 3),
            ("''", "empty character literal", 0, 2),
            ("'a", "unterminated character literal", 0, 2),
            ("'ab\n'", "unterminated character literal", 0, 3),
        ] {
            check_err(src, msg, start, end);
        }
        let e = check_err("['abc']", "may only contain one character", 1, 6);
        assert_eq!(e.help.as_deref(), Some("strings use double quotes"));
    }

    #[test]
    fn keywords_idents_unit_options() {
        for (src, value, start, end) in [
            ("true", Bool(true), 0, 4),
            (" false ", Bool(false), 1, 6),
            ("()", RonValue::Unit, 0, 2),
            ("( /* c */ )", RonValue::Unit, 0, 11),
            ("test_card", Ident("test_card".into()), 0, 9),
            ("Reflect101", Ident("Reflect101".into()), 0, 10),
            ("_x", Ident("_x".into()), 0, 2),
            ("r#true", Ident("true".into()), 0, 6),
            ("r#Some", Ident("Some".into()), 0, 6),
            ("None", RonValue::Option(None), 0, 4),
        ] {
            check(src, value, start, end);
        }
        let inner = Box::new(Spanned::new(Int(5), sp(6, 7)));
        check("Some( 5 )", RonValue::Option(Some(inner)), 0, 9);
        let inner = Box::new(Spanned::new(s("x"), sp(11, 14)));
        let inner = Box::new(Spanned::new(RonValue::Option(Some(inner)), sp(6, 16)));
        check("Some (Some(\"x\",))", RonValue::Option(Some(inner)), 0, 17);
        check_err("Some", "expected `(` after `Some`", 0, 4);
        check_err("Some()", "`Some` needs a value", 0, 6);
        check_err("Some(1, 2)", "expected `)`", 8, 9);
    }

    #[test]
    fn lists_and_maps() {
        let items = vec![
            node(Int(1), 1, 2),
            node(Float(2.5), 4, 7),
            node(s("x"), 9, 12),
        ];
        check("[1, 2.5, \"x\",]", List(items), 0, 14);
        check("[ ]", List(vec![]), 0, 3);
        check("{}", RonValue::Map(vec![]), 0, 2);
        let v = ok(r#"{ "a": 1, "b": [], "a": 2, }"#);
        assert_eq!(v.span, sp(0, 28));
        let entries = map_of(&v.value);
        assert_eq!(entries.len(), 3, "duplicate keys are kept");
        assert_eq!(entries[0].0, Spanned::new(s("a"), sp(2, 5)));
        assert_eq!(entries[0].1, Spanned::new(Int(1), sp(7, 8)));
        assert_eq!(entries[1].1.span, sp(15, 17));
        assert_eq!(entries[2].1, Spanned::new(Int(2), sp(24, 25)));
        let v = ok("{1: x, (1, 2): Some(3)}");
        let key = &map_of(&v.value)[1].0;
        assert_eq!((key.span, key.value.kind_name()), (sp(7, 13), "tuple"));
    }

    #[test]
    fn structs_and_tuples() {
        let v = ok("Foo(a: 1, b: \"x\",)");
        assert_eq!(v.span, sp(0, 18));
        let (name, fields) = struct_of(&v.value);
        assert_eq!(name, Some(&Spanned::new("Foo".to_string(), sp(0, 3))));
        assert_eq!(fields[0].0, Spanned::new("a".to_string(), sp(4, 5)));
        assert_eq!(fields[0].1, Spanned::new(Int(1), sp(7, 8)));
        assert_eq!(fields[1].0.span.join(fields[1].1.span), sp(10, 16));

        let v = ok(" ( x : 1 )");
        assert_eq!(v.span, sp(1, 10));
        assert!(matches!(struct_of(&v.value), (None, fields) if fields.len() == 1));

        let v = ok("Foo (1, Bar)");
        assert_eq!(v.span, sp(0, 12));
        let (name, items) = tuple_of(&v.value);
        assert_eq!(name.map(|n| n.span), Some(sp(0, 3)));
        assert_eq!(items[1], node(Ident("Bar".into()), 8, 11));

        assert!(matches!(tuple_of(&ok("(1, \"two\")").value), (None, items) if items.len() == 2));
        assert!(matches!(tuple_of(&ok("(5)").value), (None, items) if items.len() == 1));
        let v = ok("Empty()");
        assert_eq!(v.span, sp(0, 7));
        assert!(matches!(tuple_of(&v.value), (Some(_), items) if items.is_empty()));
        let v = ok("r#Some(r#type: 1, true: 2)");
        let (name, fields) = struct_of(&v.value);
        assert_eq!(name.map(|n| n.value.as_str()), Some("Some"));
        assert_eq!(fields[0].0, Spanned::new("type".to_string(), sp(7, 13)));
        assert_eq!(fields[1].0.value, "true");
    }

    #[test]
    fn full_document() {
        let v = ok(DOC);
        assert_eq!(v.span, sp(0, DOC.len()));
        let (name, fields) = struct_of(&v.value);
        assert_eq!(name.map(|n| n.value.as_str()), Some("Graph"));
        let names: Vec<&str> = fields.iter().map(|(k, _)| k.value.as_str()).collect();
        assert_eq!(names, ["name", "nodes", "outputs"]);
        assert_eq!(line_col(DOC, fields[1].0.span.start), (3, 5));
        assert_eq!(line_col(DOC, fields[2].0.span.start), (7, 5));
        assert_eq!(field(&v.value, "name").value, s("edges"));

        let nodes = field(&v.value, "nodes");
        assert_eq!(line_col(DOC, nodes.span.start), (3, 12));
        assert_eq!(line_col(DOC, nodes.span.end), (6, 6));
        let entries = map_of(&nodes.value);
        assert_eq!(entries.len(), 2);
        assert_eq!(line_col(DOC, entries[1].0.span.start), (5, 9));
        assert_eq!(entries[1].0.span.len(), 6);

        let card = entry(&nodes.value, "card");
        assert_eq!(field(&card.value, "op").value, s("capture.pattern"));
        let params = field(&card.value, "params");
        assert_eq!(field(&params.value, "kind").value, s("test_card"));
        let width = field(&params.value, "width");
        assert_eq!(width.value, Int(1920));
        assert_eq!(line_col(DOC, width.span.start), (4, 78));
        assert_eq!(field(&params.value, "height").value, Int(1080));

        let blur = entry(&nodes.value, "blur");
        let image = entry(&field(&blur.value, "inputs").value, "image");
        assert_eq!(image.value, s("card.image"));
        assert_eq!(line_col(DOC, image.span.start), (5, 62));
        let sigma = field(&field(&blur.value, "params").value, "sigma");
        assert_eq!((&sigma.value, sigma.span), (&Float(1.5), sp(231, 234)));
        assert_eq!(line_col(DOC, sigma.span.start), (5, 94));
        let outputs = field(&v.value, "outputs");
        assert_eq!(entry(&outputs.value, "edges").value, s("edges.edges"));
    }

    #[test]
    fn syntax_errors() {
        for (src, msg, start, end) in [
            ("[1, é]", "unexpected character `é`", 4, 6),
            ("[1 2]", "expected `,` or `]`", 3, 4),
            ("(a: [1, 2)", "expected `,` or `]`", 9, 10),
            ("(a::b)", "expected `,` or `)`", 2, 3),
            (
                "Foo(a: 1, b 2)",
                "expected `:` after field name `b`",
                12,
                13,
            ),
            ("(a: 1, b = 2)", "expected `:` after field name `b`", 9, 10),
            ("{\"k\" 1}", "expected `:` after map key", 5, 6),
            ("1 2", "unexpected trailing characters", 2, 3),
            ("(a: 1))", "unexpected trailing characters", 6, 7),
            ("1 / 2", "unexpected trailing characters", 2, 3),
            ("", "empty document, expected a value", 0, 0),
            ("  // only a comment\n", "empty document", 20, 20),
            ("[,]", "unexpected character `,`", 1, 2),
            ("5 #![enable(a)]", "unexpected trailing characters", 2, 3),
        ] {
            check_err(src, msg, start, end);
        }
        for (src, expected) in [
            ("[1, 2", "`,` or `]`"),
            ("[1,", "a value or `]`"),
            ("{\"a\": ", "a value"),
            ("{\"a\" ", "`:`"),
            ("Some(1", "`,` or `)`"),
            ("X(a: 1, b", "`:`"),
        ] {
            let end = src.len();
            check_err(
                src,
                &format!("unexpected end of input, expected {expected}"),
                end,
                end,
            );
        }
        let e = check_err("[1, @]", "unexpected character `@`", 4, 5);
        assert_eq!(e.message, "unexpected character `@`");
        let e = check_err(
            "(a: 1",
            "unexpected end of input, expected `,` or `)`",
            5,
            5,
        );
        assert_eq!(
            e.help.as_deref(),
            Some("the `(` at line 1, column 1 is not closed")
        );
        let e = check_err("(a: 1 b: 2)", "expected `,` or `)`", 6, 7);
        assert_eq!(e.message, "expected `,` or `)`");
        let e = check_err("Foo(a 1)", "expected `,` or `)`", 6, 7);
        assert_eq!(
            e.help.as_deref(),
            Some("if `a` is a field name, write `a: value`")
        );
        let e = check_err("(a: 1, \"b\": 2)", "expected a field name", 7, 8);
        assert_eq!(
            e.help.as_deref(),
            Some("field names are bare identifiers, without quotes")
        );
        let src = "(x: 1,\n y: 2,\n x: 3)";
        let e = check_err(src, "duplicate field `x`", 15, 16);
        assert_eq!(
            e.help.as_deref(),
            Some("`x` was first set at line 1, column 2")
        );
        assert_eq!(line_col(src, e.span.start), (3, 2));
    }

    #[test]
    fn comments_and_attributes() {
        check("// c\n/* a /* b */ c */ 7 // end", Int(7), 23, 24);
        check("/***/1/*/ */", Int(1), 5, 6);
        let items = vec![
            node(Int(1), 1, 2),
            node(Int(2), 12, 13),
            node(Int(3), 26, 27),
        ];
        check("[1, /* x */ 2 /**/, // y\n 3]", List(items), 0, 28);
        check_err("1 /* a /* b */", "unterminated block comment", 2, 4);
        check_err("[1, /* /* */ 2]", "unterminated block comment", 4, 6);
        let src = "#![enable(implicit_some)]\n#![ enable ( unwrap_newtypes, a , ) ]\n 5";
        check(src, Int(5), 65, 66);
        check_err("#x", "expected `!`", 1, 2);
        check_err("#![feature(x)] 1", "expected `enable`", 3, 4);
        check_err("#![enabled(x)] 1", "expected `enable`", 3, 4);
        check_err("#![enable(x y)] 1", "expected `)`", 12, 13);
        check_err(
            "#![enable(x",
            "unexpected end of input, expected `)`",
            11,
            11,
        );
        check_err(
            "#![enable(x)",
            "unexpected end of input, expected `]`",
            12,
            12,
        );
    }

    #[test]
    fn truncations_never_panic() {
        for (i, _) in DOC.char_indices().skip(1) {
            let prefix = &DOC[..i];
            match parse(prefix) {
                // `G`, `Gr`, ... `Graph` are complete identifiers.
                Ok(v) => assert!(
                    i <= 5 && v.value == Ident(prefix.into()),
                    "{prefix:?} parsed"
                ),
                Err(e) => assert!(
                    i > 5 && e.span.start <= e.span.end && e.span.end <= i,
                    "{e:?}"
                ),
            }
        }
        let multibyte = "(s: \"héllo\", c: 'é', r: r#\"ü\"#)";
        assert!(parse(multibyte).is_ok());
        for (i, _) in multibyte.char_indices() {
            assert!(parse(&multibyte[..i]).is_err(), "{i}");
        }
    }

    #[test]
    fn nesting_limit() {
        for open in ["[", "(", "{", "Some(", "A(", "(a:"] {
            let e = fail(&open.repeat(100_000));
            assert_eq!(e.message, "nesting too deep (limit 128)", "{open}");
            let paren_at = open.find(['[', '(', '{']).unwrap_or_default();
            assert_eq!(e.span.start, MAX_DEPTH * open.len() + paren_at, "{open}");
        }
        let nested = |depth: usize| format!("{}{}", "[".repeat(depth), "]".repeat(depth));
        assert!(parse(&nested(MAX_DEPTH)).is_ok());
        check_err(
            &nested(MAX_DEPTH + 1),
            "nesting too deep",
            MAX_DEPTH,
            MAX_DEPTH + 1,
        );
        // Depth is released when a container closes.
        let inner = nested(MAX_DEPTH - 1);
        assert!(parse(&format!("[{inner}, {inner}, {inner}]")).is_ok());
    }

    #[test]
    fn large_inputs_stay_linear() {
        let hashes = "#".repeat(2000);
        let raw = format!("r{hashes}\"{}", "#".repeat(200_000));
        check_err(&raw, "unterminated raw string", 0, raw.len());
        let raw = format!(
            "r{hashes}\"{}\"{hashes}",
            format!("\"{}", &hashes[1..]).repeat(100)
        );
        assert!(matches!(ok(&raw).value, Str(text) if text.len() == 200_000));
        check_err(&"/*".repeat(100_000), "unterminated block comment", 0, 2);
        let list = format!("[{}]", "x, 1.5, \"s\", (a: 1), ".repeat(20_000));
        assert!(matches!(ok(&list).value, List(items) if items.len() == 80_000));
    }

    fn xorshift(state: &mut u64) -> u64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        *state
    }

    fn assert_sane(src: &str) {
        if let Err(e) = parse(src) {
            let Span { start, end } = e.span;
            assert!(start <= end && end <= src.len(), "{src:?}: {e:?}");
            assert!(
                src.is_char_boundary(start) && src.is_char_boundary(end),
                "{src:?}: {e:?}"
            );
            assert!(!e.message.is_empty());
        }
    }

    #[test]
    fn garbage_never_panics() {
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let alphabet = b"()[]{},:\"'#!r/*\\ \n_aZ09.+-exbuS{}NoneSome";
        let pick = |state: &mut u64| alphabet[(xorshift(state) % alphabet.len() as u64) as usize];
        for round in 0..3000 {
            let len = xorshift(&mut state) % 64;
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    if round % 2 == 0 {
                        xorshift(&mut state) as u8
                    } else {
                        pick(&mut state)
                    }
                })
                .collect();
            assert_sane(&String::from_utf8_lossy(&bytes));
        }
        for _ in 0..2000 {
            let mut bytes = DOC.as_bytes().to_vec();
            for _ in 0..3 {
                let at = (xorshift(&mut state) % bytes.len() as u64) as usize;
                bytes[at] = pick(&mut state);
            }
            assert_sane(&String::from_utf8_lossy(&bytes));
        }
    }

    #[test]
    fn line_col_positions() {
        let text = "ab\ncé\u{1F600}x\n\nz";
        for (offset, expected) in [
            (0, (1, 1)),
            (2, (1, 3)),
            (3, (2, 1)),
            (4, (2, 2)),  // é
            (5, (2, 2)),  // inside é
            (6, (2, 3)),  // the emoji
            (8, (2, 3)),  // inside the emoji
            (10, (2, 4)), // x
            (12, (3, 1)),
            (13, (4, 1)),
            (14, (4, 2)),
            (1000, (4, 2)),
        ] {
            assert_eq!(line_col(text, offset), expected, "offset {offset}");
        }
        assert_eq!(line_col("", 5), (1, 1));
        let src = "[\n  \"ü\", @]";
        assert_eq!(line_col(src, fail(src).span.start), (2, 8));
    }

    #[test]
    fn rendering_round_trips() {
        let v = ok(
            r#"Foo(a: 1, b: [1.0, -2.5, 1e20, inf, -inf], c: {"k\n": 'x'}, d: Some(()),
            e: None, f: Bar(x, r#true), g: (), h: '\'')"#,
        );
        let text = r#"Foo(a:1,b:[1.0,-2.5,1e20,inf,-inf],c:{"k\n":'x'},d:Some(()),e:None,f:Bar(x,r#true),g:(),h:'\'')"#;
        assert_eq!(to_ron_string(&v.value), text);
        assert_eq!(to_ron_string(&Float(f64::NAN)), "NaN");
        assert_eq!(to_ron_string(&Float(3.0)), "3.0");
        assert_eq!(to_ron_string(&s("q\"\\\u{1}")), r#""q\"\\\u{1}""#);
        assert_eq!(to_ron_string(&Ident("None".into())), "r#None");
        assert_eq!(to_ron_string(&Int(i64::MIN)), "-9223372036854775808");
        for src in [
            DOC,
            "[1, 2.5, 1e-7, 123456789.125, -0.0, \"é\\u{1F600}\\t\", 'x', true, ()]",
            "{ (1, Name()): [Some(None)], \"k\": r#\"raw \"q\"\"# }",
            "Outer(inner: (a: r#Some, b: Tag(1,)), list: [], map: {})",
        ] {
            let v = ok(src);
            let text = to_ron_string(&v.value);
            assert_eq!(strip(&ok(&text).value), strip(&v.value), "{text}");
            assert_eq!(to_ron_string(&ok(&text).value), text, "deterministic");
        }
    }

    #[test]
    fn kinds_and_display() {
        let kinds = [
            "true", "1", "1.", "\"s\"", "'c'", "()", "x", "None", "[]", "{}", "(a: 1)", "(1)",
        ]
        .map(|src| ok(src).value.kind_name());
        let expected = [
            "boolean",
            "integer",
            "float",
            "string",
            "char",
            "unit",
            "identifier",
        ];
        assert_eq!(kinds[..7], expected);
        assert_eq!(kinds[7..], ["option", "list", "map", "struct", "tuple"]);
        let e = fail("'ab'");
        let help = "(help: strings use double quotes)";
        assert_eq!(
            e.to_string(),
            format!("character literal may only contain one character {help}")
        );
        assert_eq!(fail("").to_string(), "empty document, expected a value");
        let boxed: Box<dyn std::error::Error> = Box::new(e);
        assert!(!boxed.to_string().is_empty());
    }
}
