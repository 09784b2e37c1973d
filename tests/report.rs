//! `ocellus run --report FILE.html`: the self-contained run report, checked as text (every node
//! in the diagram, every output, images inline, nothing loaded from elsewhere) and, where
//! Chromium is installed, opened as a user would: headless, with no console errors, every image
//! decoded, every output on the first screen, and a screenshot that shows the page.
//!
//! Without Chromium the browser checks are skipped, unless `OCELLUS_REQUIRE_CHROMIUM=1` (CI
//! installs Debian's `chromium` and sets it).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{ocellus, stderr, temp_dir};

/// Flags for a headless, offline, throw-away Chromium.
const CHROMIUM_FLAGS: [&str; 7] = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
];
const CHROMIUM_TIMEOUT: Duration = Duration::from_secs(60);

/// The page background (`--bg` in the report's style) and status colours.
const BACKGROUND: [u8; 3] = [0xf4, 0xf5, 0xf7];
const COMPUTED: [u8; 3] = [0x2f, 0x9e, 0x44];
const CACHED: [u8; 3] = [0x1c, 0x7e, 0xd6];

/// Runs `ocellus run ARGS --report PATH`, expecting success, and returns the page.
fn run_with_report(args: &[&str], report: &Path) -> String {
    let report_arg = report.to_string_lossy().into_owned();
    let mut all: Vec<&str> = vec!["run"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--report", &report_arg]);
    let out = ocellus(&all);
    let err = stderr(&out);
    assert!(out.status.success(), "ocellus {all:?} failed:\n{err}");
    assert!(
        err.lines()
            .last()
            .is_some_and(|l| l == format!("report: {report_arg}")),
        "the last line of stderr names the report:\n{err}"
    );
    std::fs::read_to_string(report).unwrap()
}

/// The text checks every report passes.
fn check_page(html: &str, nodes: &[&str], outputs: &[&str], images: bool) {
    assert!(html.starts_with("<!DOCTYPE html>"));
    let start = html
        .find("<svg class=\"graph\"")
        .expect("an inline SVG diagram");
    let svg = &html[start..start + html[start..].find("</svg>").expect("the SVG ends")];
    for node in nodes {
        assert!(
            svg.contains(&format!(">{node}</text>")),
            "node `{node}` is drawn in the diagram"
        );
    }
    for output in outputs {
        assert!(
            html.contains(&format!("id=\"output-{output}\"")),
            "output `{output}` has a card"
        );
        assert!(
            svg.contains(&format!(">{output}</text>")),
            "output `{output}` is in the diagram"
        );
    }
    if images {
        assert!(
            html.contains("src=\"data:image/png;base64,"),
            "images inline as PNG"
        );
    }
    // Nothing is loaded from elsewhere.
    for attr in ["src=", "href="] {
        for (at, _) in html.match_indices(attr) {
            let value = html[at + attr.len()..].trim_start_matches(['"', '\'']);
            for bad in ["http://", "https://", "//", "file:"] {
                assert!(
                    !value.starts_with(bad),
                    "external resource: {}",
                    &html[at..(at + 80).min(html.len())]
                );
            }
        }
    }
    for bad in ["<link", "@import", "<iframe", "<object", "<embed"] {
        assert!(!html.contains(bad), "the page contains {bad}");
    }
    assert!(!html.contains("url(http"), "the style loads a URL");
}

/// `/usr/bin/chromium`, or `chromium` on `PATH`.
fn chromium() -> Option<PathBuf> {
    let standard = PathBuf::from("/usr/bin/chromium");
    if standard.is_file() {
        return Some(standard);
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join("chromium"))
            .find(|p| p.is_file())
    })
}

/// Chromium, or `None` after saying why the browser checks are skipped (a failure instead when
/// `OCELLUS_REQUIRE_CHROMIUM=1`).
fn chromium_or_skip() -> Option<PathBuf> {
    let found = chromium();
    if found.is_none() {
        assert!(
            std::env::var("OCELLUS_REQUIRE_CHROMIUM").as_deref() != Ok("1"),
            "OCELLUS_REQUIRE_CHROMIUM=1 but chromium is not installed"
        );
        println!("chromium not found, skipping the browser check");
    }
    found
}

/// Runs headless Chromium on `page` with `extra` flags and a fresh profile folder, killing it
/// after [`CHROMIUM_TIMEOUT`]; stdout goes to `stdout_file`. Returns Chromium's stderr.
fn run_chromium(
    chromium: &Path,
    dir: &Path,
    tag: &str,
    extra: &[String],
    page: &Path,
    stdout_file: &Path,
) -> String {
    let profile = dir.join(format!("chromium-profile-{tag}"));
    let _ = std::fs::remove_dir_all(&profile);
    std::fs::create_dir_all(&profile).unwrap();
    let stderr_file = dir.join(format!("chromium-{tag}.stderr"));
    let url = format!("file://{}", page.canonicalize().unwrap().display());
    let mut child = Command::new(chromium)
        .args(CHROMIUM_FLAGS)
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--window-size=1280,2400")
        .args(extra)
        .arg(&url)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(stdout_file).unwrap())
        .stderr(std::fs::File::create(&stderr_file).unwrap())
        .spawn()
        .expect("chromium starts");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > CHROMIUM_TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "chromium did not finish within {CHROMIUM_TIMEOUT:?}:\n{}",
                std::fs::read_to_string(&stderr_file).unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let log = std::fs::read_to_string(&stderr_file).unwrap_or_default();
    assert!(status.success(), "chromium failed ({status}):\n{log}");
    let _ = std::fs::remove_dir_all(&profile);
    log
}

/// Opens the report in headless Chromium: the DOM after `load` says every image decoded, no
/// script error or `console.error` happened and every output card starts on the first screen;
/// the 1280-wide screenshot is not blank and shows each of `status_colours`.
fn browser_check(page: &Path, outputs: usize, status_colours: &[[u8; 3]]) {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let dir = page.parent().unwrap();
    let started = Instant::now();

    let dom_file = dir.join("dom.html");
    run_chromium(
        &chromium,
        dir,
        "dom",
        &["--dump-dom".to_string()],
        page,
        &dom_file,
    );
    let dom = std::fs::read_to_string(&dom_file).unwrap();
    let body_at = dom.find("<body").expect("the DOM has a body");
    let body = &dom[body_at..body_at + dom[body_at..].find('>').unwrap() + 1];
    assert!(
        !body.contains("data-report-errors"),
        "script errors in the page: {body}"
    );
    assert!(
        body.contains("data-report-ok=\"1\""),
        "the page's load check did not pass: {body}"
    );
    assert!(
        body.contains(&format!("data-outputs=\"{outputs}\"")),
        "{body}"
    );
    assert!(
        body.contains(&format!("data-outputs-in-view=\"{outputs}\"")),
        "every output card starts on the first screen: {body}"
    );

    let shot = dir.join("shot.png");
    let _ = std::fs::remove_file(&shot);
    run_chromium(
        &chromium,
        dir,
        "shot",
        &[format!("--screenshot={}", shot.display())],
        page,
        &dir.join("shot.stdout"),
    );
    let image = ocellus_engine::image_io::read_image(
        &shot,
        &ocellus_engine::image_io::DecodeLimits::default(),
    )
    .expect("the screenshot is a PNG");
    assert_eq!(image.width(), 1280);
    let data = image.as_u8().expect("an 8-bit screenshot");
    let channels = image.channels().count();
    assert!(channels >= 3);
    let pixels: Vec<[u8; 3]> = data
        .chunks_exact(channels)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    let painted = pixels.iter().filter(|p| **p != BACKGROUND).count();
    assert!(
        painted * 100 >= pixels.len() * 2,
        "the screenshot is nearly blank: {painted} of {} pixels differ from the background",
        pixels.len()
    );
    let mut colours: Vec<[u8; 3]> = pixels.iter().map(|p| p.map(|c| c >> 4)).collect();
    colours.sort_unstable();
    colours.dedup();
    assert!(
        colours.len() >= 12,
        "only {} distinct colours in the screenshot",
        colours.len()
    );
    for colour in status_colours {
        let count = pixels.iter().filter(|p| *p == colour).count();
        assert!(
            count >= 200,
            "status colour {colour:?} covers only {count} pixels"
        );
    }
    println!(
        "browser check of {} in {:.1} s",
        page.display(),
        started.elapsed().as_secs_f64()
    );
}

#[test]
fn edges_report_shows_the_graph_the_cache_and_the_image() {
    let dir = temp_dir("report-edges");
    let cache = dir.join("cache").to_string_lossy().into_owned();
    let small = [
        "graphs/edges.ron",
        "--set",
        "card.width=320",
        "--set",
        "card.height=240",
        "--cache",
        &cache,
    ];
    // First run: everything computed; the report goes into folders that do not exist yet.
    let first_path = dir.join("first/nested/report.html");
    let first = run_with_report(&small, &first_path);
    check_page(&first, &["card", "gray", "blur", "edges"], &["edges"], true);
    assert!(first.contains("4 computed"));
    assert_eq!(first.matches("class=\"node s-computed\"").count(), 4);
    assert!(
        first.contains("320×240 gray_u8"),
        "the image's size and format are shown"
    );

    // Second run with another threshold: the blur is reused from the disk cache, its inputs
    // are not needed, the edges are computed again.
    let mut changed = small.to_vec();
    changed.extend_from_slice(&["--set", "edges.high=140"]);
    let page = dir.join("report.html");
    let html = run_with_report(&changed, &page);
    check_page(&html, &["card", "gray", "blur", "edges"], &["edges"], true);
    for (node, status) in [
        ("card", "idle"),
        ("gray", "idle"),
        ("blur", "cached"),
        ("edges", "computed"),
    ] {
        assert!(
            html.contains(&format!("<g class=\"node s-{status}\"><title>{node} (")),
            "`{node}` is drawn as {status}"
        );
    }
    assert!(
        html.contains("<b>1 of 2</b> needed nodes reused"),
        "cache reuse is summarized"
    );
    assert!(
        html.contains("<code>edges.high=140</code>"),
        "overrides are listed"
    );
    browser_check(&page, 1, &[COMPUTED, CACHED]);
}

#[test]
fn hull_report_previews_mesh_points_metrics_and_view() {
    let dir = temp_dir("report-hull");
    let page = dir.join("report.html");
    let args = [
        "graphs/hull.ron",
        "--set",
        "hull.resolution=48",
        "--repeat",
        "2",
    ];
    let html = run_with_report(&args, &page);
    let outputs = ["mesh", "points", "metrics", "view"];
    check_page(
        &html,
        &["scene", "shots", "hull", "view_scene", "view"],
        &outputs,
        true,
    );
    // The mesh and point-cloud thumbnails and the rendered view.
    assert_eq!(
        html.matches("src=\"data:image/png;base64,").count(),
        3,
        "three previews"
    );
    assert!(
        html.contains(" vertices, <b>") && html.contains(" triangles"),
        "mesh counts"
    );
    assert!(html.contains(" points"), "point count");
    assert!(html.contains("<th>volume</th>"), "metrics as a table");
    assert!(
        html.contains("linear light, sRGB-encoded"),
        "the f32 view's conversion is noted"
    );
    assert!(html.contains("median of 2 runs"), "--repeat timing");
    browser_check(&page, outputs.len(), &[COMPUTED]);
}

#[test]
fn report_is_refused_for_animations_and_a_bad_path_fails_the_run() {
    let dir = temp_dir("report-refused");
    let page = dir.join("report.html");
    let out = ocellus(&[
        "run",
        "graphs/animate.ron",
        "--report",
        &page.to_string_lossy(),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("--report is not supported for animated/streaming graphs yet"),
        "{}",
        stderr(&out)
    );
    assert!(!page.exists());

    // A folder that cannot be created: the run succeeds, the report fails with exit 1.
    let blocker = dir.join("file");
    std::fs::write(&blocker, "not a folder").unwrap();
    let bad = blocker.join("report.html");
    let out = ocellus(&[
        "run",
        "graphs/edges.ron",
        "--set",
        "card.width=64",
        "--set",
        "card.height=48",
        "--report",
        &bad.to_string_lossy(),
    ]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("error: cannot create"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn report_of_a_failed_run_lists_the_problem_and_the_missing_output() {
    let dir = temp_dir("report-failed");
    let graph = dir.join("broken.ron");
    std::fs::write(
        &graph,
        r#"Graph(
    name: "broken <&>",
    description: "A branch that fails: <b>escaped</b>",
    nodes: {
        "card": (op: "capture.pattern", params: (kind: "checkerboard", width: 64, height: 48, square: 8)),
        "missing": (op: "io.read_image", params: (path: "does-not-exist.png")),
        "gray": (op: "filter.grayscale", inputs: { "image": "missing.image" }),
    },
    outputs: { "card": "card.image", "gray": "gray.image" },
)
"#,
    )
    .unwrap();
    let page = dir.join("report.html");
    let out = ocellus(&[
        "run",
        &graph.to_string_lossy(),
        "--report",
        &page.to_string_lossy(),
    ]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    let html = std::fs::read_to_string(&page).unwrap();
    check_page(&html, &["card", "missing", "gray"], &["card", "gray"], true);
    assert!(
        html.contains("<h1>broken &lt;&amp;&gt;</h1>"),
        "text is escaped"
    );
    assert!(html.contains("&lt;b&gt;escaped&lt;/b&gt;"));
    assert!(html.contains("<section class=\"problems\">"));
    assert!(html.contains("node `missing` (io.read_image) failed"));
    assert!(html.contains("<g class=\"node s-failed\"><title>missing ("));
    assert!(html.contains("<g class=\"node s-skipped\"><title>gray ("));
    assert!(html.contains("Not produced: an upstream node failed."));
}
