//! Graphs with an `animation` section: parameters driven by tracks, one run per frame, nodes
//! without animated inputs computed once, and load-time errors that point into the file.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{registry, source};
use ocellus_engine::resolve::Override;
use ocellus_engine::timeline::{Animated, Encoding, load_animated, run_timeline};
use ocellus_engine::{RunOptions, Value};

fn animated(reg: &ocellus_engine::Registry, text: &str, set: &[&str]) -> Animated {
    let overrides: Vec<Override> = set.iter().map(|s| Override::parse(s).unwrap()).collect();
    match load_animated(reg, &source("anim.ron", text), &overrides) {
        Ok((_, Some(a))) => a,
        Ok((_, None)) => panic!("no timeline"),
        Err(d) => panic!("did not load:\n{d}"),
    }
}

fn errors(text: &str) -> Vec<String> {
    let (reg, _) = registry();
    match load_animated(&reg, &source("anim.ron", text), &[]) {
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
                .collect()
        }
    }
}

/// Scalar output `name` of every frame.
fn scalars(reg: &ocellus_engine::Registry, a: &Animated, name: &str) -> Vec<f64> {
    let mut out = Vec::new();
    run_timeline(reg, a, &RunOptions::default(), |frame| {
        match frame.report.output(name) {
            Some(Value::Scalar(x)) => out.push(*x),
            Some(Value::List(l)) => out.push(l.items.len() as f64),
            other => return Err(format!("{other:?}")),
        }
        Ok(())
    })
    .unwrap();
    out
}

const RAMP: &str = r#"Graph(
    name: "ramp",
    nodes: {
        "a": (op: "t.source", params: (value: 1.0)),
        "base": (op: "t.source", params: (value: 100.0)),
        "sum": (op: "t.add", inputs: { "a": "base.value" }, params: (offset: 0.0)),
    },
    outputs: { "a": "a.value", "sum": "sum.sum" },
    animation: (
        fps: 4,
        frames: 5,
        tracks: {
            "a.value": (interpolation: "linear", keys: [(0.0, 0.0), (1.0, 10.0)]),
            "sum.offset": (interpolation: "step", keys: [(0.0, 1.0), (0.5, 2.0)]),
        },
    ),
)"#;

#[test]
fn tracks_drive_parameters_frame_by_frame() {
    let (reg, _) = registry();
    let a = animated(&reg, RAMP, &[]);
    assert_eq!((a.frames, a.fps, a.start), (5, 4.0, 0));
    assert_eq!(scalars(&reg, &a, "a"), [0.0, 2.5, 5.0, 7.5, 10.0]);
    assert_eq!(
        scalars(&reg, &a, "sum"),
        [101.0, 101.0, 102.0, 102.0, 102.0]
    );
}

#[test]
fn nodes_without_animated_parameters_run_once() {
    let (reg, calls) = registry();
    let a = animated(&reg, RAMP, &[]);
    let report = run_timeline(&reg, &a, &RunOptions::default(), |_| Ok(())).unwrap();
    assert_eq!(report.frames, 5);
    // `base` never changes: 1 run; `a` changes every frame: 5; `sum` changes at frame 2 only,
    // and frames 1, 3, 4 reuse the previous frame's result: 2.
    assert_eq!(calls.get("t.source"), 1 + 5);
    assert_eq!(calls.get("t.add"), 2);
    assert_eq!(report.computed, 1 + 5 + 2);
    // Reused: `sum` in frames 1, 3, 4 (its upstream then is not needed at all) and `base` in
    // frame 2, where `sum` changes.
    assert_eq!(report.cached, 3 + 1);
}

#[test]
fn set_replaces_a_track_and_applies_to_every_frame() {
    let (reg, _) = registry();
    let a = animated(&reg, RAMP, &["a.value=3.0"]);
    assert_eq!(a.tracks.len(), 1);
    assert_eq!(scalars(&reg, &a, "a"), [3.0; 5]);
}

#[test]
fn frame_and_time_drivers_and_start_offset() {
    let text = r#"Graph(
        nodes: {
            "a": (op: "t.source"),
            "r": (op: "t.repeat", inputs: { "x": "a.value" }),
        },
        outputs: { "t": "a.value", "n": "r.items" },
        animation: (fps: 2, frames: 3, start: 4, tracks: { "a.value": "time", "r.count": frame }),
    )"#;
    let (reg, _) = registry();
    let a = animated(&reg, text, &[]);
    assert_eq!(scalars(&reg, &a, "t"), [2.0, 2.5, 3.0]);
    assert_eq!(scalars(&reg, &a, "n"), [4.0, 5.0, 6.0]);
}

#[test]
fn int_parameters_round_and_easing_shapes_segments() {
    let text = r#"Graph(
        nodes: {
            "a": (op: "t.source"),
            "r": (op: "t.repeat", inputs: { "x": "a.value" }),
        },
        outputs: { "v": "a.value", "n": "r.items" },
        animation: (fps: 4, frames: 5, tracks: {
            "a.value": (interpolation: "linear", easing: "in_out", keys: [(0.0, 0.0), (1.0, 8.0)]),
            "r.count": (interpolation: "linear", keys: [(0.0, 0.0), (1.0, 3.0)]),
        }),
    )"#;
    let (reg, _) = registry();
    let a = animated(&reg, text, &[]);
    // smoothstep(u) = 3u² − 2u³ at u = 0, ¼, ½, ¾, 1.
    assert_eq!(scalars(&reg, &a, "v"), [0.0, 1.25, 4.0, 6.75, 8.0]);
    // 0, 0.75, 1.5, 2.25, 3 rounded to nearest (half away from zero).
    assert_eq!(scalars(&reg, &a, "n"), [0.0, 1.0, 2.0, 2.0, 3.0]);
}

#[test]
fn a_graph_without_animation_has_no_timeline() {
    let (reg, _) = registry();
    let text = r#"Graph(nodes: { "a": (op: "t.source") }, outputs: { "a": "a.value" })"#;
    let (graph, timeline) = load_animated(&reg, &source("plain.ron", text), &[]).unwrap();
    assert!(timeline.is_none());
    assert_eq!(graph.nodes.len(), 1);
}

#[test]
fn encodings_default_to_gif() {
    let text = r#"Graph(
        nodes: { "a": (op: "t.source") },
        outputs: { "a": "a.value", "b": "a.value" },
        animation: (frames: 2, encode: { "a": ["apng", "gif", "apng"] }),
    )"#;
    let (reg, _) = registry();
    let a = animated(&reg, text, &[]);
    assert_eq!(a.encodings("a"), [Encoding::Apng, Encoding::Gif]);
    assert_eq!(a.encodings("b"), [Encoding::Gif]);
    assert_eq!(a.fps, 24.0);
}

fn with_animation(section: &str) -> String {
    format!(
        r#"Graph(
    nodes: {{ "blur": (op: "t.source"), "r": (op: "t.repeat", inputs: {{ "x": "blur.value" }}) }},
    outputs: {{ "a": "blur.value" }},
    animation: {section},
)"#
    )
}

#[test]
fn load_errors_point_into_the_animation_section() {
    let cases: &[(&str, &str)] = &[
        (
            r#"(frames: 3, tracks: { "blr.value": (keys: [(0.0, 1.0)]) })"#,
            "anim.ron:4:38: track `blr.value`: no node `blr` [did you mean `blur`?]",
        ),
        (
            r#"(frames: 3, tracks: { "blur.valeu": (keys: [(0.0, 1.0)]) })"#,
            "anim.ron:4:38: track `blur.valeu`: `t.source` has no parameter `valeu` [did you mean `value`?]",
        ),
        (
            r#"(frames: 3, tracks: { "blur.value": (keys: [(0.0, [1.0, 2.0])]) })"#,
            "a key holds 2 numbers, but the parameter takes 1",
        ),
        (
            r#"(frames: 3, tracks: { "blur.value": (interpolation: "catmul_rom", keys: [(0.0, 1.0)]) })"#,
            "unknown interpolation \"catmul_rom\" [did you mean `catmull_rom`?]",
        ),
        (
            r#"(frames: 3, tracks: { "blur.value": (keys: [(1.0, 1.0), (0.5, 2.0)]) })"#,
            "key times must increase strictly",
        ),
        (
            r#"(fps: 4, tracks: {})"#,
            "the animation has no `frames` field",
        ),
        (r#"(frames: 0)"#, "`frames` must be an integer in 1..="),
        (
            r#"(frames: 2, fsp: 3)"#,
            "unknown animation field `fsp` [did you mean `fps`?]",
        ),
        (
            r#"(frames: 2, encode: { "b": ["gif"] })"#,
            "`encode` names `b`, which is not a graph output [did you mean `a`?]",
        ),
        (
            r#"(frames: 2, encode: { "a": ["mp4"] })"#,
            "unknown animation format \"mp4\"",
        ),
        (
            r#"(frames: 2, tracks: { "blur": (keys: [(0.0, 1.0)]) })"#,
            "track `blur` must name `node.param`",
        ),
        (
            r#"(frames: 2, tracks: { "blur.value": "frames" })"#,
            "a track is `(interpolation: ..., keys: [...])`",
        ),
    ];
    for (section, expected) in cases {
        let errs = errors(&with_animation(section));
        assert!(
            errs.iter().any(|e| e.contains(expected)),
            "{section}: expected `{expected}` in {errs:#?}"
        );
    }
}

#[test]
fn a_key_outside_the_parameter_range_is_a_load_error_at_the_track() {
    // `t.source.value` is limited to [-1000, 1000]; the ramp leaves it at frame 2.
    let errs = errors(&with_animation(
        r#"(fps: 1, frames: 4, tracks: { "blur.value": (keys: [(0.0, 0.0), (3.0, 1500.0)]) })"#,
    ));
    assert_eq!(errs.len(), 1, "{errs:#?}");
    assert!(errs[0].starts_with("anim.ron:4:60:"), "{errs:#?}");
    assert!(errs[0].contains("at frame 3 (3.000 s)"), "{errs:#?}");
    assert!(errs[0].contains("1000"), "{errs:#?}");
}

#[test]
fn duplicate_tracks_are_errors() {
    let errs = errors(&with_animation(
        r#"(frames: 2, tracks: { "blur.value": "time", "blur.value": "frame" })"#,
    ));
    assert!(
        errs.iter()
            .any(|e| e.contains("parameter `blur.value` has two tracks")),
        "{errs:#?}"
    );
}

#[test]
fn constant_speed_tracks_move_equal_distances_per_frame() {
    // Keys at uneven spacing on a line: raw linear interpolation changes speed at the middle
    // key, constant_speed does not.
    let text = |constant: bool| {
        format!(
            r#"Graph(
        nodes: {{ "a": (op: "t.source") }},
        outputs: {{ "a": "a.value" }},
        animation: (fps: 10, frames: 11, tracks: {{
            "a.value": (interpolation: "linear", constant_speed: {constant},
                        keys: [(0.0, 0.0), (0.2, 8.0), (1.0, 10.0)]),
        }}),
    )"#
        )
    };
    let (reg, _) = registry();
    let raw = scalars(&reg, &animated(&reg, &text(false), &[]), "a");
    let even = scalars(&reg, &animated(&reg, &text(true), &[]), "a");
    let steps = |v: &[f64]| v.windows(2).map(|w| w[1] - w[0]).collect::<Vec<_>>();
    assert!((steps(&raw)[0] - 4.0).abs() < 1e-9 && (steps(&raw)[9] - 0.25).abs() < 1e-9);
    for s in steps(&even) {
        assert!((s - 1.0).abs() < 1e-3, "{even:?}");
    }
    assert_eq!((even[0], even[10]), (0.0, 10.0));
}
