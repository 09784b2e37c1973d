//! Time in the engine: a graph with an `animation` section is evaluated once per frame, with
//! numeric parameters driven by keyframe tracks, and its outputs become frame sequences.
//!
//! ```ron
//! Graph(
//!     name: "orbit",
//!     nodes: { ... },
//!     outputs: { "view": "raster.color" },
//!     animation: (
//!         fps: 24,            // frames per second (default 24)
//!         frames: 48,         // how many frames (required)
//!         start: 0,           // index of the first frame (default 0); frame i is at (start + i) / fps s
//!         tracks: {
//!             "scene.azimuth_deg": (interpolation: "catmull_rom",
//!                                   keys: [(0.0, 0.0), (1.0, 120.0), (2.0, 360.0)]),
//!             "scene.target": (interpolation: "linear", keys: [(0.0, [0, 0, 0]), (2.0, [0, 1, 0])],
//!                              easing: "in_out"),
//!             "pick.index": "frame",  // the frame number (integers), or "time" (seconds)
//!         },
//!         encode: { "view": ["gif", "apng", "png"] },  // image outputs: gif by default
//!     ),
//! )
//! ```
//!
//! A track drives one parameter of type float, int (rounded to nearest), or a float list (one
//! number per component; a list of free length takes the keys' length); keys are
//! `(time_s, value)`. Interpolations are those
//! of [`crate::curves`] (`step`, `linear`, `hermite` with optional `tangents`, `catmull_rom`,
//! `centripetal`, `natural_cubic`, `bezier`, `bspline`, `slerp`, `squad` for quaternions).
//! `constant_speed: true` moves along the keys' path at constant speed between the first and
//! last key times (arc-length reparameterization, for camera paths; easing then shapes the
//! distance, not the time). Sampled values are checked against the parameter's range like a
//! `--set` value, with the
//! error pointing at the track. A `--set` on a tracked parameter replaces the track.
//!
//! Frames run one after another; every frame's run shares one [`MemoryCache`], so a node whose
//! content key does not change between frames (no animated parameter upstream) is computed once
//! and reused — the same rule the disk cache follows across runs.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cache::MemoryCache;
use crate::curves::{ArcLength, Easing, Interpolation, Track};
use crate::diag::{Code, Diagnostic, Diagnostics, SourceFile, suggest};
use crate::exec::{RunError, RunOptions, RunReport, run};
use crate::graph::Graph;
use crate::op::Registry;
use crate::params::{ParamSpec, ParamType};
use crate::resolve::{Override, load_source, parse_spec, read_source};
use crate::ron_syntax::{RonValue, Span, Spanned, a_kind};
use crate::spec::{head_span, struct_fields, unknown_field};

const ANIMATION_FIELDS: [&str; 5] = ["fps", "frames", "start", "tracks", "encode"];
const TRACK_FIELDS: [&str; 5] = [
    "interpolation",
    "keys",
    "tangents",
    "easing",
    "constant_speed",
];
/// Samples of the arc-length table of a `constant_speed` track (relative error of the speed
/// ≈ 1e-4 for smooth paths).
const ARC_LENGTH_SAMPLES: usize = 4096;
/// Longest animation accepted, in frames.
pub const MAX_FRAMES: usize = 1_000_000;

/// How an animated image output is also written with `--emit`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Encoding {
    /// Animated GIF (256-colour palette per frame).
    Gif,
    /// Animated PNG (lossless, full colour).
    Apng,
    /// One 8-bit sRGB PNG per frame, in the folder `NAME_png/`.
    Png,
}

impl Encoding {
    /// Every name, as written in `encode`.
    pub const NAMES: [&'static str; 3] = ["gif", "apng", "png"];

    /// From a name in `encode`.
    pub fn from_name(name: &str) -> Option<Encoding> {
        match name {
            "gif" => Some(Encoding::Gif),
            "apng" => Some(Encoding::Apng),
            "png" => Some(Encoding::Png),
            _ => None,
        }
    }

    /// File extension.
    pub fn extension(self) -> &'static str {
        match self {
            Encoding::Gif => "gif",
            Encoding::Apng => "apng",
            Encoding::Png => "png",
        }
    }
}

/// What drives an animated parameter.
#[derive(Debug, Clone)]
pub enum Driver {
    /// Keyframes.
    Keys(Track),
    /// Keyframes travelled at constant speed: the time between the first and last key maps
    /// linearly to the distance along the path (arc-length reparameterization).
    ConstantSpeed(ArcLength),
    /// The frame number.
    Frame,
    /// The frame's time in seconds.
    Time,
}

/// One animated parameter.
#[derive(Debug, Clone)]
pub struct ParamTrack {
    /// Node path (as in `--set`).
    pub node: String,
    /// Parameter name.
    pub param: String,
    /// What drives it.
    pub driver: Driver,
    /// The parameter's type (checked at load).
    ty: ParamType,
    /// Span of the track's key (`"node.param"`) in the graph file.
    key_span: Span,
    /// Span of the track's value.
    value_span: Span,
}

/// A graph with a timeline, ready to be evaluated at any frame.
#[derive(Debug, Clone)]
pub struct Animated {
    source: Arc<SourceFile>,
    base: Vec<Override>,
    /// Frames per second.
    pub fps: f64,
    /// Number of frames.
    pub frames: usize,
    /// Index of the first frame.
    pub start: i64,
    /// The parameter tracks.
    pub tracks: Vec<ParamTrack>,
    /// Encodings per image output name (outputs not listed get GIF).
    pub encode: BTreeMap<String, Vec<Encoding>>,
}

/// The parsed `animation` section, before it is checked against the graph.
struct TimelineSpec {
    fps: f64,
    frames: usize,
    start: i64,
    tracks: Vec<TrackSpec>,
    encode: BTreeMap<String, Vec<Encoding>>,
}

struct TrackSpec {
    node: String,
    param: String,
    key_span: Span,
    value: Spanned<RonValue>,
}

/// Reads a graph file; returns its frame-0 graph and, when it has an `animation` section, the
/// timeline. `overrides` are `--set` values, applied to every frame.
pub fn load_animated(
    registry: &Registry,
    source: &Arc<SourceFile>,
    overrides: &[Override],
) -> Result<(Graph, Option<Animated>), Diagnostics> {
    let mut diags = Diagnostics::default();
    let Some(spec) = parse_spec(source, &mut diags) else {
        return Err(diags);
    };
    let Some(section) = spec.animation.as_ref() else {
        return load_source(registry, source, overrides).map(|g| (g, None));
    };
    let timeline = parse_timeline(source, section, &mut diags);
    // Resolve without the tracks first: its errors are the graph's own.
    let graph = load_source(registry, source, overrides)?;
    let Some(timeline) = timeline else {
        return Err(diags);
    };
    let mut tracks = Vec::new();
    for track in timeline.tracks {
        // A `--set` on a tracked parameter replaces the track.
        if overrides
            .iter()
            .any(|o| o.node.value == track.node && o.param.value == track.param)
        {
            continue;
        }
        if let Some(t) = check_track(source, &graph, track, &mut diags) {
            tracks.push(t);
        }
    }
    for name in timeline.encode.keys() {
        if !graph.outputs.iter().any(|o| &o.name == name) {
            let span = section.span;
            diags.push(
                Diagnostic::at(
                    Code::Animation,
                    source,
                    span,
                    format!("`encode` names `{name}`, which is not a graph output"),
                )
                .label("in this animation section")
                .maybe_help(
                    suggest(name, graph.outputs.iter().map(|o| o.name.as_str()))
                        .map(|s| format!("did you mean `{s}`?")),
                ),
            );
        }
    }
    if !diags.is_empty() {
        diags.sort();
        return Err(diags);
    }
    let animated = Animated {
        source: Arc::clone(source),
        base: overrides.to_vec(),
        fps: timeline.fps,
        frames: timeline.frames,
        start: timeline.start,
        tracks,
        encode: timeline.encode,
    };
    // Every frame must resolve (values inside the parameters' ranges): check them all now, so a
    // bad key is a load error, not a failure at frame 40.
    let mut frame_diags = Diagnostics::default();
    for i in 0..animated.frames {
        if let Err(d) = load_source(registry, source, &animated.overrides_at(i)) {
            let (frame, time) = (animated.frame_number(i), animated.time(i));
            frame_diags.0.extend(d.0.into_iter().map(|mut d| {
                d.message = format!("at frame {frame} ({time:.3} s): {}", d.message);
                d
            }));
            break;
        }
    }
    if !frame_diags.is_empty() {
        return Err(frame_diags);
    }
    Ok((graph, Some(animated)))
}

/// [`load_animated`] from a path.
pub fn load_animated_file(
    registry: &Registry,
    path: &std::path::Path,
    overrides: &[Override],
) -> Result<(Graph, Option<Animated>), Diagnostics> {
    let name = path.to_string_lossy().into_owned();
    let source = read_source(path, &name).map_err(|d| Diagnostics(vec![*d]))?;
    load_animated(registry, &source, overrides)
}

impl Animated {
    /// The frame number of frame `i` (`start + i`).
    pub fn frame_number(&self, i: usize) -> i64 {
        self.start
            .saturating_add(i64::try_from(i).unwrap_or(i64::MAX))
    }

    /// The time of frame `i`, seconds.
    pub fn time(&self, i: usize) -> f64 {
        self.frame_number(i) as f64 / self.fps
    }

    /// The encodings of an image output.
    pub fn encodings(&self, output: &str) -> Vec<Encoding> {
        self.encode
            .get(output)
            .cloned()
            .unwrap_or_else(|| vec![Encoding::Gif])
    }

    /// The `--set` values plus every track sampled at frame `i`.
    pub fn overrides_at(&self, i: usize) -> Vec<Override> {
        let t = self.time(i);
        let mut out = self.base.clone();
        for track in &self.tracks {
            let numbers = match &track.driver {
                Driver::Keys(curve) => curve.sample(t),
                Driver::ConstantSpeed(table) => {
                    let track = table.track();
                    let span = track.end() - track.start();
                    let fraction = if span > 0.0 {
                        ((t - track.start()) / span).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    table.sample_at_fraction(fraction)
                }
                Driver::Frame => vec![self.frame_number(i) as f64],
                Driver::Time => vec![t],
            };
            out.push(Override {
                node: Spanned::new(track.node.clone(), track.key_span),
                param: Spanned::new(track.param.clone(), track.key_span),
                value: Spanned::new(ron_value(&track.ty, &numbers), track.value_span),
                source: Arc::clone(&self.source),
            });
        }
        out
    }

    /// The graph at frame `i`.
    pub fn graph_at(&self, registry: &Registry, i: usize) -> Result<Graph, Diagnostics> {
        load_source(registry, &self.source, &self.overrides_at(i))
    }
}

/// The sampled numbers as a parameter value of type `ty`.
fn ron_value(ty: &ParamType, numbers: &[f64]) -> RonValue {
    match ty {
        ParamType::Optional(inner) => ron_value(inner, numbers),
        ParamType::Int => {
            let v = numbers.first().copied().unwrap_or(0.0).round();
            // Out-of-range values saturate; the parameter's own range check reports them.
            RonValue::Int(if v.is_finite() { v as i64 } else { 0 })
        }
        ParamType::List { .. } => RonValue::List(
            numbers
                .iter()
                .map(|&x| Spanned::new(RonValue::Float(x), Span::new(0, 0)))
                .collect(),
        ),
        _ => RonValue::Float(numbers.first().copied().unwrap_or(0.0)),
    }
}

/// Numbers per value of an animatable parameter type: `Some(Some(n))` fixed, `Some(None)` any
/// (a number list of free length: the keys set it); `None` when it cannot be animated.
fn animatable_width(ty: &ParamType) -> Option<Option<usize>> {
    match ty {
        ParamType::Float | ParamType::Int => Some(Some(1)),
        ParamType::Optional(inner) => animatable_width(inner),
        ParamType::List { element, len } if matches!(**element, ParamType::Float) => Some(*len),
        _ => None,
    }
}

fn animation_diag(
    source: &Arc<SourceFile>,
    span: Span,
    message: impl Into<String>,
    label: &str,
) -> Diagnostic {
    Diagnostic::at(Code::Animation, source, span, message).label(label)
}

fn parse_timeline(
    source: &Arc<SourceFile>,
    section: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Option<TimelineSpec> {
    let fields = struct_fields(source, section, "Animation", "`animation`", diags)?;
    let mut spec = TimelineSpec {
        fps: 24.0,
        frames: 0,
        start: 0,
        tracks: Vec::new(),
        encode: BTreeMap::new(),
    };
    let mut saw_frames = false;
    let before = diags.0.len();
    for (key, value) in fields {
        match key.value.as_str() {
            "fps" => match number(&value.value) {
                Some(f) if f.is_finite() && f > 0.0 && f <= 1e4 => spec.fps = f,
                _ => diags.push(
                    animation_diag(
                        source,
                        value.span,
                        format!(
                            "`fps` must be a number in (0, 10000], found {}",
                            describe(&value.value)
                        ),
                        "frames per second",
                    )
                    .help("e.g. `fps: 24`"),
                ),
            },
            "frames" => match &value.value {
                RonValue::Int(n) if *n >= 1 && (*n as u64) <= MAX_FRAMES as u64 => {
                    saw_frames = true;
                    spec.frames = *n as usize;
                }
                other => {
                    saw_frames = true;
                    diags.push(
                        animation_diag(
                            source,
                            value.span,
                            format!(
                                "`frames` must be an integer in 1..={MAX_FRAMES}, found {}",
                                describe(other)
                            ),
                            "frame count",
                        )
                        .help("e.g. `frames: 48`"),
                    )
                }
            },
            "start" => match &value.value {
                RonValue::Int(n) if n.unsigned_abs() <= 1 << 40 => spec.start = *n,
                other => diags.push(animation_diag(
                    source,
                    value.span,
                    format!(
                        "`start` must be an integer frame index, found {}",
                        describe(other)
                    ),
                    "first frame",
                )),
            },
            "tracks" => spec.tracks = parse_tracks(source, value, diags),
            "encode" => spec.encode = parse_encode(source, value, Code::Animation, diags),
            other => diags.push(unknown_field(
                source,
                key,
                other,
                &ANIMATION_FIELDS,
                "animation",
            )),
        }
    }
    if !saw_frames {
        diags.push(
            animation_diag(
                source,
                head_span(section),
                "the animation has no `frames` field",
                "expected `frames: N` here",
            )
            .help("e.g. `animation: (fps: 24, frames: 48, tracks: { ... })`"),
        );
    }
    (diags.0.len() == before).then_some(spec)
}

pub(crate) fn number(v: &RonValue) -> Option<f64> {
    match v {
        RonValue::Int(i) => Some(*i as f64),
        RonValue::Float(f) => Some(*f),
        _ => None,
    }
}

pub(crate) fn describe(v: &RonValue) -> String {
    match v {
        RonValue::Int(i) => format!("`{i}`"),
        RonValue::Float(f) => format!("`{f}`"),
        RonValue::Str(s) => format!("\"{s}\""),
        other => a_kind(other).to_string(),
    }
}

pub(crate) fn key_string(
    source: &Arc<SourceFile>,
    key: &Spanned<RonValue>,
    what: &str,
    diags: &mut Diagnostics,
) -> Option<String> {
    match &key.value {
        RonValue::Str(s) => Some(s.clone()),
        other => {
            diags.push(animation_diag(
                source,
                key.span,
                format!("{what} keys must be strings, found {}", a_kind(other)),
                "expected a quoted string",
            ));
            None
        }
    }
}

fn parse_tracks(
    source: &Arc<SourceFile>,
    value: &Spanned<RonValue>,
    diags: &mut Diagnostics,
) -> Vec<TrackSpec> {
    let entries = match &value.value {
        RonValue::Map(entries) => entries,
        RonValue::Unit => return Vec::new(),
        other => {
            diags.push(
                animation_diag(
                    source,
                    head_span(value),
                    format!("`tracks` must be a map, found {}", a_kind(other)),
                    "expected `{ \"node.param\": (...) }`",
                )
                .help("e.g. `tracks: { \"blur.sigma\": (interpolation: \"linear\", keys: [(0.0, 1.0), (2.0, 4.0)]) }`"),
            );
            return Vec::new();
        }
    };
    let mut out: Vec<TrackSpec> = Vec::new();
    for (key, track) in entries {
        let Some(target) = key_string(source, key, "`tracks`", diags) else {
            continue;
        };
        let Some((node, param)) = target
            .rsplit_once('.')
            .filter(|(n, p)| !n.is_empty() && !p.is_empty())
        else {
            diags.push(
                animation_diag(
                    source,
                    key.span,
                    format!("track `{target}` must name `node.param`"),
                    "not `node.param`",
                )
                .help("e.g. `\"blur.sigma\"`; a node inside a subgraph is `sub/inner.param`"),
            );
            continue;
        };
        if let Some(first) = out.iter().find(|t| t.node == node && t.param == param) {
            diags.push(
                animation_diag(
                    source,
                    key.span,
                    format!("parameter `{target}` has two tracks"),
                    "second track",
                )
                .related(first.key_span, "first track"),
            );
            continue;
        }
        out.push(TrackSpec {
            node: node.to_string(),
            param: param.to_string(),
            key_span: key.span,
            value: track.clone(),
        });
    }
    out
}

pub(crate) fn parse_encode(
    source: &Arc<SourceFile>,
    value: &Spanned<RonValue>,
    code: Code,
    diags: &mut Diagnostics,
) -> BTreeMap<String, Vec<Encoding>> {
    let animation_diag = |source: &Arc<SourceFile>, span: Span, message: String, label: &str| {
        Diagnostic::at(code, source, span, message).label(label)
    };
    let mut out = BTreeMap::new();
    let entries = match &value.value {
        RonValue::Map(entries) => entries,
        RonValue::Unit => return out,
        other => {
            diags.push(animation_diag(
                source,
                head_span(value),
                format!("`encode` must be a map, found {}", a_kind(other)),
                "expected `{ \"output\": [\"gif\", \"apng\"] }`",
            ));
            return out;
        }
    };
    for (key, list) in entries {
        let Some(name) = key_string(source, key, "`encode`", diags) else {
            continue;
        };
        let RonValue::List(items) = &list.value else {
            diags.push(animation_diag(
                source,
                list.span,
                format!("`encode` of `{name}` must be a list of formats"),
                "expected e.g. `[\"gif\", \"apng\"]`",
            ));
            continue;
        };
        let mut formats = Vec::new();
        for item in items {
            let text = match &item.value {
                RonValue::Str(s) | RonValue::Ident(s) => s.as_str(),
                _ => "",
            };
            match Encoding::from_name(text) {
                Some(e) => {
                    if !formats.contains(&e) {
                        formats.push(e);
                    }
                }
                None => diags.push(
                    animation_diag(
                        source,
                        item.span,
                        format!("unknown animation format {}", describe(&item.value)),
                        "not a format",
                    )
                    .help(format!("formats are {}", Encoding::NAMES.join(", "))),
                ),
            }
        }
        out.insert(name, formats);
    }
    out
}

/// Checks one track against the graph: the node and parameter exist, the parameter can be
/// animated, and the keys fit its width.
fn check_track(
    source: &Arc<SourceFile>,
    graph: &Graph,
    track: TrackSpec,
    diags: &mut Diagnostics,
) -> Option<ParamTrack> {
    let Some(node) = graph.nodes.iter().find(|n| n.name == track.node) else {
        diags.push(
            animation_diag(
                source,
                track.key_span,
                format!(
                    "track `{}.{}`: no node `{}`",
                    track.node, track.param, track.node
                ),
                "unknown node",
            )
            .maybe_help(
                suggest(&track.node, graph.nodes.iter().map(|n| n.name.as_str()))
                    .map(|s| format!("did you mean `{s}`?")),
            ),
        );
        return None;
    };
    let Some(spec): Option<&ParamSpec> = node.info.params.iter().find(|p| p.name == track.param)
    else {
        diags.push(
            animation_diag(
                source,
                track.key_span,
                format!(
                    "track `{}.{}`: `{}` has no parameter `{}`",
                    track.node, track.param, node.info.id, track.param
                ),
                "unknown parameter",
            )
            .maybe_help(
                suggest(
                    &track.param,
                    node.info.params.iter().map(|p| p.name.as_str()),
                )
                .map(|s| format!("did you mean `{s}`?")),
            ),
        );
        return None;
    };
    let Some(width) = animatable_width(&spec.ty) else {
        diags.push(
            animation_diag(
                source,
                track.key_span,
                format!(
                    "track `{}.{}`: a {} parameter cannot be animated",
                    track.node, track.param, spec.ty
                ),
                "not a number",
            )
            .help("tracks drive float and int parameters and lists of floats"),
        );
        return None;
    };
    let driver = match &track.value.value {
        RonValue::Str(s) | RonValue::Ident(s) if s == "frame" || s == "time" => {
            if width != Some(1) {
                diags.push(animation_diag(
                    source,
                    track.value.span,
                    format!(
                        "`{s}` drives one number, but `{}.{}` is a list",
                        track.node, track.param
                    ),
                    "one number",
                ));
                return None;
            }
            if s == "frame" {
                Driver::Frame
            } else {
                Driver::Time
            }
        }
        RonValue::Struct { .. } => parse_keys(source, &track.value, width, diags)?,
        other => {
            diags.push(
                animation_diag(
                    source,
                    track.value.span,
                    format!("a track is `(interpolation: ..., keys: [...])`, `\"frame\"` or `\"time\"`, found {}", a_kind(other)),
                    "not a track",
                )
                .help("e.g. `(interpolation: \"linear\", keys: [(0.0, 1.0), (2.0, 4.0)])`"),
            );
            return None;
        }
    };
    Some(ParamTrack {
        node: track.node,
        param: track.param,
        driver,
        ty: spec.ty.clone(),
        key_span: track.key_span,
        value_span: track.value.span,
    })
}

/// Numbers of one key value: a number, or a list of numbers.
fn key_numbers(v: &RonValue) -> Option<Vec<f64>> {
    match v {
        RonValue::Int(_) | RonValue::Float(_) => number(v).map(|x| vec![x]),
        RonValue::List(items) | RonValue::Tuple { items, .. } => {
            items.iter().map(|i| number(&i.value)).collect()
        }
        _ => None,
    }
}

fn parse_keys(
    source: &Arc<SourceFile>,
    value: &Spanned<RonValue>,
    width: Option<usize>,
    diags: &mut Diagnostics,
) -> Option<Driver> {
    let fields = struct_fields(source, value, "Track", "a track", diags)?;
    let mut constant_speed = false;
    let mut interpolation = Interpolation::Linear;
    let mut easing = Easing::None;
    let mut keys: Option<&Spanned<RonValue>> = None;
    let mut tangents: Option<&Spanned<RonValue>> = None;
    let before = diags.0.len();
    for (key, v) in fields {
        match key.value.as_str() {
            "interpolation" => {
                let name = match &v.value {
                    RonValue::Str(s) | RonValue::Ident(s) => s.as_str(),
                    _ => "",
                };
                match Interpolation::from_name(name) {
                    Some(i) => interpolation = i,
                    None => diags.push(
                        animation_diag(
                            source,
                            v.span,
                            format!("unknown interpolation {}", describe(&v.value)),
                            "not an interpolation",
                        )
                        .help(
                            match suggest(name, Interpolation::NAMES.iter().copied()) {
                                Some(s) => format!("did you mean `{s}`?"),
                                None => format!(
                                    "interpolations are {}",
                                    Interpolation::NAMES.join(", ")
                                ),
                            },
                        ),
                    ),
                }
            }
            "easing" => {
                let name = match &v.value {
                    RonValue::Str(s) | RonValue::Ident(s) => s.as_str(),
                    _ => "",
                };
                match Easing::from_name(name) {
                    Some(e) => easing = e,
                    None => diags.push(
                        animation_diag(
                            source,
                            v.span,
                            format!("unknown easing {}", describe(&v.value)),
                            "not an easing",
                        )
                        .help(format!("easings are {}", Easing::NAMES.join(", "))),
                    ),
                }
            }
            "keys" => keys = Some(v),
            "tangents" => tangents = Some(v),
            "constant_speed" => match &v.value {
                RonValue::Bool(b) => constant_speed = *b,
                other => diags.push(animation_diag(
                    source,
                    v.span,
                    format!(
                        "`constant_speed` must be true or false, found {}",
                        a_kind(other)
                    ),
                    "not a bool",
                )),
            },
            other => diags.push(unknown_field(source, key, other, &TRACK_FIELDS, "track")),
        }
    }
    let Some(keys) = keys else {
        diags.push(animation_diag(
            source,
            head_span(value),
            "the track has no `keys`",
            "expected `keys: [(time_s, value), ...]`",
        ));
        return None;
    };
    let RonValue::List(items) = &keys.value else {
        diags.push(animation_diag(
            source,
            keys.span,
            format!(
                "`keys` must be a list of `(time_s, value)`, found {}",
                a_kind(&keys.value)
            ),
            "not a list",
        ));
        return None;
    };
    // A free-length list parameter takes the first key's length.
    let width = width.or_else(|| {
        items.first().and_then(|item| match &item.value {
            RonValue::Tuple { items, .. } if items.len() == 2 => {
                key_numbers(&items[1].value).map(|v| v.len())
            }
            _ => None,
        })
    });
    let width = width.unwrap_or(1);
    let mut times = Vec::with_capacity(items.len());
    let mut values = Vec::with_capacity(items.len() * width);
    for item in items {
        let pair = match &item.value {
            RonValue::Tuple { items, .. } if items.len() == 2 => {
                number(&items[0].value).zip(key_numbers(&items[1].value))
            }
            _ => None,
        };
        match pair {
            Some((t, v)) if v.len() == width => {
                times.push(t);
                values.extend(v);
            }
            Some((_, v)) => diags.push(animation_diag(
                source,
                item.span,
                format!(
                    "a key holds {} numbers, but the parameter takes {width}",
                    v.len()
                ),
                "wrong width",
            )),
            None => diags.push(
                animation_diag(
                    source,
                    item.span,
                    "a key is `(time_s, value)` with a number or a list of numbers",
                    "not a key",
                )
                .help("e.g. `(0.5, 2.0)` or `(0.5, [0, 1, 0])`"),
            ),
        }
    }
    let tangent_values = match tangents {
        None => None,
        Some(t) => {
            let numbers = match &t.value {
                RonValue::List(items) => items
                    .iter()
                    .map(|i| key_numbers(&i.value))
                    .collect::<Option<Vec<_>>>()
                    .map(|v| v.concat()),
                _ => None,
            };
            if numbers.is_none() {
                diags.push(animation_diag(
                    source,
                    t.span,
                    "`tangents` must be a list with one value per key",
                    "not a list of values",
                ));
            }
            numbers
        }
    };
    if diags.0.len() != before {
        return None;
    }
    let curve =
        Track::new(times, values, width, interpolation).and_then(|c| match tangent_values {
            Some(t) => c.with_tangents(t),
            None => Ok(c),
        });
    let driver = curve.and_then(|c| {
        let c = c.with_easing(easing);
        if constant_speed {
            ArcLength::new(&c, ARC_LENGTH_SAMPLES).map(Driver::ConstantSpeed)
        } else {
            Ok(Driver::Keys(c))
        }
    });
    match driver {
        Ok(d) => Some(d),
        Err(e) => {
            diags.push(animation_diag(
                source,
                keys.span,
                e.to_string(),
                "these keys",
            ));
            None
        }
    }
}

/// One frame's run.
#[derive(Debug)]
pub struct FrameRun {
    /// Position in the animation (0-based).
    pub index: usize,
    /// Frame number (`start + index`).
    pub frame: i64,
    /// Time, seconds.
    pub time: f64,
    /// The run.
    pub report: RunReport,
}

/// What an animation run did.
#[derive(Debug, Clone, Default)]
pub struct TimelineReport {
    /// Frames run.
    pub frames: usize,
    /// Nodes computed, summed over frames.
    pub computed: usize,
    /// Nodes reused from the caches, summed over frames.
    pub cached: usize,
    /// Wall time.
    pub elapsed: Duration,
}

/// Why an animation run stopped.
#[derive(Debug, thiserror::Error)]
pub enum TimelineError {
    /// A frame's graph did not resolve.
    #[error("frame {frame}: {message}")]
    Resolve {
        /// Frame number.
        frame: i64,
        /// The diagnostics, rendered.
        message: String,
    },
    /// A frame could not start.
    #[error("frame {frame}: {source}")]
    Run {
        /// Frame number.
        frame: i64,
        /// Why.
        source: RunError,
    },
    /// The caller's frame handler stopped the run.
    #[error("frame {frame}: {message}")]
    Handler {
        /// Frame number.
        frame: i64,
        /// Why.
        message: String,
    },
}

/// Runs every frame in order, sharing one in-memory cache between frames (the options' own
/// `memory_cache` if set), and hands each frame's run to `on_frame` as soon as it finishes.
/// Node failures do not stop the run; they are in each frame's report.
pub fn run_timeline(
    registry: &Registry,
    animated: &Animated,
    options: &RunOptions,
    mut on_frame: impl FnMut(FrameRun) -> Result<(), String>,
) -> Result<TimelineReport, TimelineError> {
    let started = Instant::now();
    let memory = options
        .memory_cache
        .clone()
        .unwrap_or_else(|| Arc::new(MemoryCache::new()));
    let options = RunOptions {
        memory_cache: Some(Arc::clone(&memory)),
        ..options.clone()
    };
    let mut report = TimelineReport::default();
    for index in 0..animated.frames {
        let frame = animated.frame_number(index);
        let graph = animated
            .graph_at(registry, index)
            .map_err(|d| TimelineError::Resolve {
                frame,
                message: d.to_string(),
            })?;
        let run_report =
            run(&graph, &options).map_err(|source| TimelineError::Run { frame, source })?;
        memory.end_generation();
        report.frames += 1;
        report.computed += run_report.count(crate::exec::NodeStatus::Computed);
        report.cached += run_report.count(crate::exec::NodeStatus::Cached);
        on_frame(FrameRun {
            index,
            frame,
            time: animated.time(index),
            report: run_report,
        })
        .map_err(|message| TimelineError::Handler { frame, message })?;
    }
    report.elapsed = started.elapsed();
    Ok(report)
}
