//! `ocellus run --report FILE.html`: one self-contained HTML page per run — the graph drawn as an
//! inline SVG diagram, per-node time and output bytes as bars, cache reuse, and a preview of
//! every requested output (images inline as PNG `data:` URIs, meshes and point clouds as rendered
//! thumbnails, metrics and matrices as tables, everything else summarized).
//!
//! The page loads nothing from anywhere: no external style sheet, font, image or script, so it
//! opens offline and from `file://`. A small inline script checks on `load` that every image
//! decoded (`data-report-ok="1"` on `<body>`) and records script errors and `console.error`
//! calls (`data-report-errors`), which the browser test reads back. Apart from the timings the
//! page is deterministic: no dates, no absolute paths beyond those given on the command line.

use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::process::ExitCode;
use std::sync::Arc;

use ocellus_engine::exec::NodeStatus;
use ocellus_engine::image_io::{ImageFormat, encode_image, write_atomic};
use ocellus_engine::summary::{fmt_sig6, summarize_value};
use ocellus_engine::value::{
    Light, Material, Matrix, Mesh, Metrics, PointCloud, Pose, Reconstruction, Scene, SceneObject,
    Shape,
};
use ocellus_engine::{Channels, Graph, Image, PixelData, Registry, RunReport, Value};
use ocellus_nodes::render::mesh_scene::{MeshSceneParams, framing, framing_camera};
use ocellus_nodes::render::raster::{Cull, RasterOptions, rasterize};

use crate::cli::{EXIT_INVALID, RunArgs};
use crate::profile::Profile;
use crate::report::render_bytes;

/// Longest side of an image preview, pixels.
const MAX_PREVIEW_SIDE: usize = 512;
/// Longest side of a list element's preview, pixels.
const MAX_LIST_PREVIEW_SIDE: usize = 160;
/// List elements previewed as images or thumbnails.
const MAX_LIST_PREVIEWS: usize = 6;
/// Size of mesh and point-cloud thumbnails, pixels.
const THUMB_WIDTH: usize = 240;
const THUMB_HEIGHT: usize = 180;
/// Thumbnail background, sRGB.
const THUMB_BACKGROUND: [u8; 3] = [40, 44, 52];
/// Rows of a matrix shown in its table.
const MATRIX_ROWS: usize = 20;
/// Columns of a matrix shown in its table.
const MATRIX_COLS: usize = 12;
/// Items listed for keypoints, matches and 2-D points.
const FIRST_ITEMS: usize = 8;
/// Lines of a value summary shown before it is cut.
const SUMMARY_LINES: usize = 40;

/// Refuses `--report` before anything runs when the graph does not run as one ordinary run (an
/// animation without `--frame`, a stream without `--batch`): exit 2 with a hint.
pub fn refuse_unsupported(registry: &Registry, args: &RunArgs) -> Result<(), ExitCode> {
    if args.report.is_none() {
        return Ok(());
    }
    // Errors in these sections are reported by the run itself; only a valid section refuses.
    let stream = match crate::streaming::stream_spec(registry, &args.graph, &args.set) {
        Ok(Some(spec)) if !args.batch => Some(spec.feedback.is_empty()),
        _ => None,
    };
    let animates = args.frame.is_none()
        && matches!(
            crate::animation::timeline(registry, &args.graph, &args.set),
            Ok(Some(_))
        );
    let hint = if let Some(batchable) = stream {
        format!(
            "`{}` streams{}",
            args.graph.display(),
            if batchable {
                " (`--batch` runs it as one batch run)"
            } else {
                ""
            }
        )
    } else if animates {
        format!(
            "`{}` is animated (`--frame N` runs one frame as an ordinary run)",
            args.graph.display()
        )
    } else {
        return Ok(());
    };
    eprintln!("error: --report is not supported for animated/streaming graphs yet: {hint}");
    Err(ExitCode::from(EXIT_INVALID))
}

/// Writes the report of `reports` (the `--repeat` runs of `graph`; the last one's statuses and
/// outputs are shown) to `path` atomically, creating its folder, and prints `report: PATH`.
pub fn write_report(
    path: &Path,
    args: &RunArgs,
    graph: &Graph,
    reports: &[RunReport],
    threads: usize,
) -> Result<(), String> {
    let Some(last) = reports.last() else {
        return Err("no run to report".into());
    };
    let page = Page {
        args,
        graph,
        last,
        profile: Profile::from_reports(reports),
        runs: reports.len(),
        threads,
    };
    let html = page.render();
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        ocellus_engine::temp_files::prepare_dir(parent)
            .map_err(|e| format!("cannot create {}: {e}", parent.display()))?;
    }
    write_atomic(path, html.as_bytes())
        .map_err(|e| format!("cannot write report {}: {e}", path.display()))?;
    eprintln!("report: {}", path.display());
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Text helpers.

/// Escapes text for HTML element content and quoted attribute values.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Standard base64 (RFC 4648, `+/`, `=` padding).
pub fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            chunk.get(1).copied().unwrap_or(0),
            chunk.get(2).copied().unwrap_or(0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(char::from(ALPHABET[((n >> (18 - 6 * k)) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// `text` cut to `max` characters, with an ellipsis when cut.
fn truncate(text: &str, max: usize) -> String {
    if text.chars().count() <= max {
        text.to_string()
    } else {
        let mut cut: String = text.chars().take(max.saturating_sub(1)).collect();
        cut.push('…');
        cut
    }
}

/// Milliseconds for people: `0.042 ms`, `3.41 ms`, `412 ms`, `12.3 s`.
fn render_ms(ms: f64) -> String {
    if ms >= 10_000.0 {
        format!("{:.1} s", ms / 1e3)
    } else if ms >= 100.0 {
        format!("{ms:.0} ms")
    } else if ms >= 1.0 {
        format!("{ms:.2} ms")
    } else {
        format!("{ms:.3} ms")
    }
}

fn status_name(status: NodeStatus) -> &'static str {
    match status {
        NodeStatus::Computed => "computed",
        NodeStatus::Cached => "cached",
        NodeStatus::Shared => "shared",
        NodeStatus::Failed => "failed",
        NodeStatus::Skipped => "skipped",
        NodeStatus::Idle => "idle",
    }
}

/// (stroke / bar colour, box fill) of a status.
fn status_colors(status: Option<NodeStatus>) -> (&'static str, &'static str) {
    match status {
        Some(NodeStatus::Computed) => ("#2f9e44", "#ebfbee"),
        Some(NodeStatus::Cached) => ("#1c7ed6", "#e7f5ff"),
        Some(NodeStatus::Shared) => ("#7048e8", "#f3f0ff"),
        Some(NodeStatus::Failed) => ("#e03131", "#fff5f5"),
        Some(NodeStatus::Skipped) => ("#f08c00", "#fff9db"),
        Some(NodeStatus::Idle) | None => ("#adb5bd", "#f8f9fa"),
    }
}

const STATUSES: [NodeStatus; 6] = [
    NodeStatus::Computed,
    NodeStatus::Cached,
    NodeStatus::Shared,
    NodeStatus::Failed,
    NodeStatus::Skipped,
    NodeStatus::Idle,
];

fn chip(status: NodeStatus) -> String {
    let name = status_name(status);
    format!("<span class=\"chip s-{name}\">{name}</span>")
}

// ---------------------------------------------------------------------------------------------
// Layout of the diagram.

/// Column and row of every node: the column is the longest path from a source (a node without
/// inputs), rows order each column by the mean row of the node's predecessors (a one-pass
/// barycentre ordering, ties in graph order). `preds[i]` lists the predecessors of node `i`;
/// nodes are in topological order, so predecessors come first.
pub fn layout(preds: &[Vec<usize>]) -> Vec<(usize, usize)> {
    let n = preds.len();
    let mut column = vec![0usize; n];
    for i in 0..n {
        column[i] = preds[i]
            .iter()
            .filter(|&&p| p < i)
            .map(|&p| column[p] + 1)
            .max()
            .unwrap_or(0);
    }
    let columns = column.iter().max().map_or(0, |c| c + 1);
    let mut row = vec![0usize; n];
    for c in 0..columns {
        let mut members: Vec<(f64, usize)> = (0..n)
            .filter(|&i| column[i] == c)
            .map(|i| {
                let placed: Vec<f64> = preds[i]
                    .iter()
                    .filter(|&&p| p < i)
                    .map(|&p| row[p] as f64)
                    .collect();
                let key = if placed.is_empty() {
                    f64::MAX
                } else {
                    placed.iter().sum::<f64>() / placed.len() as f64
                };
                (key, i)
            })
            .collect();
        if c > 0 {
            members.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        }
        for (r, &(_, i)) in members.iter().enumerate() {
            row[i] = r;
        }
    }
    column.into_iter().zip(row).collect()
}

/// A box of the diagram, px.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Rect {
    x: f64,
    y: f64,
    w: f64,
    h: f64,
}

/// Node height, px.
const BOX_H: f64 = 46.0;
/// Output pill height, px (centred in a node-sized slot).
const PILL_H: f64 = 26.0;
const DIAGRAM_MARGIN: f64 = 12.0;
/// Width of a diagram section's content, px (the page's width less paddings).
const DIAGRAM_FIT_WIDTH: f64 = 1130.0;

/// Where the boxes of a layered layout go: left to right (layers are columns, the usual
/// orientation), or top to bottom when left to right would have to shrink the text a lot and
/// top to bottom fits the page. Items from `first_pill` on are output pills.
struct DiagramGeometry {
    /// Slot of each item: a node's box; a pill is drawn inside its slot (see [`Self::shape`]).
    slots: Vec<Rect>,
    item_w: Vec<f64>,
    first_pill: usize,
    vertical: bool,
    width: f64,
    height: f64,
}

impl DiagramGeometry {
    fn new(places: &[(usize, usize)], item_w: &[f64], first_pill: usize) -> DiagramGeometry {
        let horizontal = Self::left_to_right(places, item_w, first_pill);
        if horizontal.width <= 1.25 * DIAGRAM_FIT_WIDTH {
            return horizontal;
        }
        let vertical = Self::top_to_bottom(places, item_w, first_pill);
        if vertical.width <= DIAGRAM_FIT_WIDTH
            || (horizontal.width > DIAGRAM_MAX_SCALED_WIDTH && vertical.width < horizontal.width)
        {
            vertical
        } else {
            horizontal
        }
    }

    /// Items per layer.
    fn per_layer(places: &[(usize, usize)]) -> Vec<usize> {
        let layers = places.iter().map(|p| p.0 + 1).max().unwrap_or(0);
        let mut per_layer = vec![0usize; layers];
        for &(c, _) in places {
            per_layer[c] += 1;
        }
        per_layer
    }

    /// Columns as wide as their widest box, 56 px apart; rows 60 px apart, each column centred.
    fn left_to_right(
        places: &[(usize, usize)],
        item_w: &[f64],
        first_pill: usize,
    ) -> DiagramGeometry {
        const ROW_PITCH: f64 = 60.0;
        const COL_GAP: f64 = 56.0;
        let per_layer = Self::per_layer(places);
        let mut column_w = vec![0.0f64; per_layer.len()];
        for (&(c, _), &w) in places.iter().zip(item_w) {
            column_w[c] = column_w[c].max(w);
        }
        let mut column_x = Vec::with_capacity(column_w.len());
        let mut x = DIAGRAM_MARGIN;
        for w in &column_w {
            column_x.push(x);
            x += w + COL_GAP;
        }
        let max_rows = per_layer.iter().copied().max().unwrap_or(0).max(1);
        let inner_h = (max_rows as f64 - 1.0) * ROW_PITCH + BOX_H;
        let slots = places
            .iter()
            .map(|&(c, r)| {
                let span = (per_layer[c] as f64 - 1.0) * ROW_PITCH + BOX_H;
                Rect {
                    x: column_x[c],
                    y: DIAGRAM_MARGIN + (inner_h - span) / 2.0 + r as f64 * ROW_PITCH,
                    w: column_w[c],
                    h: BOX_H,
                }
            })
            .collect();
        let inner_w =
            column_w.iter().sum::<f64>() + COL_GAP * column_w.len().saturating_sub(1) as f64;
        DiagramGeometry {
            slots,
            item_w: item_w.to_vec(),
            first_pill,
            vertical: false,
            width: inner_w + 2.0 * DIAGRAM_MARGIN,
            height: inner_h + 2.0 * DIAGRAM_MARGIN,
        }
    }

    /// Layers as rows 44 px apart, boxes 20 px apart, each row centred.
    fn top_to_bottom(
        places: &[(usize, usize)],
        item_w: &[f64],
        first_pill: usize,
    ) -> DiagramGeometry {
        const LAYER_GAP: f64 = 44.0;
        const ITEM_GAP: f64 = 20.0;
        let layers = Self::per_layer(places).len();
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); layers];
        for (i, &(c, _)) in places.iter().enumerate() {
            members[c].push(i);
        }
        let layer_w: Vec<f64> = members
            .iter_mut()
            .map(|m| {
                m.sort_by_key(|&i| places[i].1);
                m.iter().map(|&i| item_w[i]).sum::<f64>()
                    + ITEM_GAP * m.len().saturating_sub(1) as f64
            })
            .collect();
        let inner_w = layer_w.iter().copied().fold(0.0, f64::max);
        let mut slots = vec![
            Rect {
                x: 0.0,
                y: 0.0,
                w: 0.0,
                h: BOX_H,
            };
            places.len()
        ];
        for (c, m) in members.iter().enumerate() {
            let mut x = DIAGRAM_MARGIN + (inner_w - layer_w[c]) / 2.0;
            for &i in m {
                slots[i] = Rect {
                    x,
                    y: DIAGRAM_MARGIN + c as f64 * (BOX_H + LAYER_GAP),
                    w: item_w[i],
                    h: BOX_H,
                };
                x += item_w[i] + ITEM_GAP;
            }
        }
        DiagramGeometry {
            slots,
            item_w: item_w.to_vec(),
            first_pill,
            vertical: true,
            width: inner_w + 2.0 * DIAGRAM_MARGIN,
            height: 2.0 * DIAGRAM_MARGIN + layers as f64 * (BOX_H + LAYER_GAP)
                - if layers > 0 { LAYER_GAP } else { 0.0 },
        }
    }

    /// The drawn box of item `i`: a node fills its slot; a pill is `PILL_H` high, its own
    /// width, at the slot's left and vertically centred.
    fn shape(&self, i: usize) -> Rect {
        let slot = self.slots[i];
        if i < self.first_pill {
            slot
        } else {
            Rect {
                x: slot.x,
                y: slot.y + (BOX_H - PILL_H) / 2.0,
                w: self.item_w[i].min(slot.w),
                h: PILL_H,
            }
        }
    }

    /// A cubic curve from item `from` to item `to`: right side to left side, or bottom to top.
    fn edge(&self, from: usize, to: usize) -> String {
        let (a, b) = (self.shape(from), self.shape(to));
        if self.vertical {
            let (x1, y1) = (a.x + a.w / 2.0, a.y + a.h);
            let (x2, y2) = (b.x + b.w / 2.0, b.y - 2.0);
            let dy = ((y2 - y1) / 2.0).max(18.0);
            format!(
                "M{x1:.1},{y1:.1} C{x1:.1},{:.1} {x2:.1},{:.1} {x2:.1},{y2:.1}",
                y1 + dy,
                y2 - dy
            )
        } else {
            let (x1, y1) = (a.x + a.w, a.y + a.h / 2.0);
            let (x2, y2) = (b.x - 2.0, b.y + b.h / 2.0);
            let dx = ((x2 - x1) / 2.0).max(24.0);
            format!(
                "M{x1:.1},{y1:.1} C{:.1},{y1:.1} {:.1},{y2:.1} {x2:.1},{y2:.1}",
                x1 + dx,
                x2 - dx
            )
        }
    }
}

/// Estimated width (px) of a node name of `chars` characters (13 px, semi-bold).
fn name_width(chars: usize) -> f64 {
    chars as f64 * 8.0
}

/// Estimated width (px) of `chars` characters of the smaller diagram text (11.5 px).
fn small_width(chars: usize) -> f64 {
    chars as f64 * 6.6
}

/// Diagrams up to this wide (px) are scaled down to fit the page; wider ones scroll.
const DIAGRAM_MAX_SCALED_WIDTH: f64 = 1700.0;

// ---------------------------------------------------------------------------------------------
// The page.

struct Page<'a> {
    args: &'a RunArgs,
    graph: &'a Graph,
    last: &'a RunReport,
    profile: Profile,
    runs: usize,
    threads: usize,
}

impl Page<'_> {
    /// Status of graph node `i` in the last run.
    fn status(&self, i: usize) -> Option<NodeStatus> {
        let name = &self.graph.nodes.get(i)?.name;
        match self.last.nodes.get(i) {
            Some(n) if &n.name == name => Some(n.status),
            _ => self
                .last
                .nodes
                .iter()
                .find(|n| &n.name == name)
                .map(|n| n.status),
        }
    }

    fn output_bytes(&self, i: usize) -> usize {
        let Some(node) = self.graph.nodes.get(i) else {
            return 0;
        };
        match self.last.nodes.get(i) {
            Some(n) if n.name == node.name => n.output_bytes,
            _ => self
                .last
                .nodes
                .iter()
                .find(|n| n.name == node.name)
                .map_or(0, |n| n.output_bytes),
        }
    }

    /// Median milliseconds of a computed node.
    fn median_ms(&self, i: usize) -> Option<f64> {
        let node = self.graph.nodes.get(i)?;
        self.profile.nodes.get(&node.name).map(|p| p.median_ms)
    }

    fn render(&self) -> String {
        let mut html = String::with_capacity(1 << 16);
        html.push_str("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n");
        html.push_str("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n");
        html.push_str(&format!(
            "<title>{} — ocellus run report</title>\n<style>{STYLE}</style>\n</head>\n<body>\n",
            escape(&self.graph.name)
        ));
        html.push_str(&format!("<script>{SCRIPT}</script>\n<main>\n"));
        html.push_str(&self.header());
        html.push_str(&self.problems());
        html.push_str(&self.diagram_section());
        html.push_str(&self.outputs_section());
        html.push_str(&self.nodes_section());
        html.push_str(&self.cache_section());
        html.push_str(&self.distributed_section());
        html.push_str(&format!(
            "<footer>ocellus {} · a self-contained page: nothing here is loaded from elsewhere · \
             timings vary from run to run</footer>\n</main>\n</body>\n</html>\n",
            env!("CARGO_PKG_VERSION")
        ));
        html
    }

    fn header(&self) -> String {
        let mut h = String::from("<header>\n");
        h.push_str(&format!("<h1>{}</h1>\n", escape(&self.graph.name)));
        if !self.graph.description.is_empty() {
            h.push_str(&format!(
                "<p class=\"desc\">{}</p>\n",
                escape(&self.graph.description)
            ));
        }
        let mut facts: Vec<(String, String)> = vec![(
            "graph".into(),
            format!(
                "<code>{}</code>",
                escape(&self.args.graph.display().to_string())
            ),
        )];
        if !self.args.set.is_empty() {
            let sets: Vec<String> = self
                .args
                .set
                .iter()
                .map(|s| format!("<code>{}</code>", escape(s)))
                .collect();
            facts.push(("overrides".into(), sets.join(" ")));
        }
        if !self.args.output.is_empty() {
            facts.push(("outputs".into(), escape(&self.args.output.join(", "))));
        }
        facts.push(("threads".into(), self.threads.to_string()));
        let time = if self.runs > 1 {
            format!(
                "{} <span class=\"muted\">median of {} runs</span>",
                render_ms(self.profile.total_median_ms),
                self.runs
            )
        } else {
            render_ms(self.last.elapsed.as_secs_f64() * 1e3)
        };
        facts.push(("time".into(), time));
        let counts: Vec<String> = STATUSES
            .iter()
            .filter(|s| **s != NodeStatus::Idle || self.last.count(**s) > 0)
            .map(|&s| {
                format!(
                    "<span class=\"count\"><i class=\"dot s-{}\"></i>{} {}</span>",
                    status_name(s),
                    self.last.count(s),
                    status_name(s)
                )
            })
            .collect();
        facts.push((
            format!("{} nodes", self.graph.nodes.len()),
            counts.join(" "),
        ));
        facts.push((
            "peak outputs".into(),
            format!(
                "<span title=\"{} bytes held by live node outputs at most\">{}</span>",
                self.profile.peak_bytes,
                render_bytes(self.profile.peak_bytes)
            ),
        ));
        h.push_str("<dl class=\"facts\">\n");
        for (term, value) in facts {
            h.push_str(&format!(
                "<div><dt>{}</dt><dd>{value}</dd></div>\n",
                escape(&term)
            ));
        }
        h.push_str("</dl>\n</header>\n");
        h
    }

    fn problems(&self) -> String {
        if self.last.failures.is_empty() && self.last.warnings.is_empty() {
            return String::new();
        }
        let mut s = String::from("<section class=\"problems\">\n<h2>Problems</h2>\n<ul>\n");
        for f in &self.last.failures {
            s.push_str(&format!(
                "<li><b class=\"fail\">error</b> {}</li>\n",
                escape(&f.to_string())
            ));
        }
        for w in &self.last.warnings {
            s.push_str(&format!(
                "<li><b class=\"warn\">warning</b> {}</li>\n",
                escape(w)
            ));
        }
        s.push_str("</ul>\n</section>\n");
        s
    }

    // -- Diagram ------------------------------------------------------------------------------

    fn diagram_section(&self) -> String {
        let legend: Vec<String> = STATUSES
            .iter()
            .map(|&s| {
                format!(
                    "<span class=\"count\"><i class=\"dot s-{0}\"></i>{0}</span>",
                    status_name(s)
                )
            })
            .collect();
        format!(
            "<section>\n<h2>Graph</h2>\n<div class=\"diagram\">{}</div>\n\
             <p class=\"legend\">{} <span class=\"muted\">· bold edges map a node over a list · \
             time is the node's median over the runs</span></p>\n</section>\n",
            self.diagram_svg(),
            legend.join(" ")
        )
    }

    fn diagram_svg(&self) -> String {
        let graph = self.graph;
        let n = graph.nodes.len();
        // Edges, one per (source, target) pair, with their port labels.
        let mut edges: Vec<(usize, usize, bool, Vec<String>)> = Vec::new();
        let mut preds: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (i, node) in graph.nodes.iter().enumerate() {
            for (port, edge) in node.inputs.iter().enumerate() {
                let Some(edge) = edge else { continue };
                let in_name = node.info.inputs.get(port).map_or("?", |p| p.name.as_str());
                for tap in edge.taps() {
                    let src = tap.from.node;
                    if src >= i {
                        continue;
                    }
                    let out_name = graph.nodes[src]
                        .info
                        .outputs
                        .get(tap.from.port)
                        .map_or("?", |p| p.name.as_str());
                    let index = tap.index.map(|k| format!("[{k}]")).unwrap_or_default();
                    let label = format!(
                        "{}.{out_name}{index} → {}.{in_name}",
                        graph.nodes[src].name, node.name
                    );
                    if let Some(e) = edges.iter_mut().find(|e| e.0 == src && e.1 == i) {
                        e.2 |= edge.mapped;
                        e.3.push(label);
                    } else {
                        edges.push((src, i, edge.mapped, vec![label]));
                        preds[i].push(src);
                    }
                }
            }
        }
        // The graph outputs are laid out as items of their own, one column right of their node.
        let outputs: Vec<(usize, &str)> = graph
            .outputs
            .iter()
            .filter(|out| out.from.node < n)
            .map(|out| (out.from.node, out.name.as_str()))
            .collect();
        preds.extend(outputs.iter().map(|&(node, _)| vec![node]));
        let places = layout(&preds);
        let items = places.len();
        let pill_w =
            |name: &str| (small_width(name.chars().count()) * 1.1 + 26.0).clamp(64.0, 300.0);
        let item_w: Vec<f64> = (0..items)
            .map(|i| match (graph.nodes.get(i), i.checked_sub(n)) {
                (Some(node), _) => {
                    let time_chars = self.median_ms(i).map_or(0, |ms| render_ms(ms).len() + 2);
                    (name_width(node.name.chars().count())
                        .max(small_width(node.info.id.chars().count() + time_chars))
                        + 28.0)
                        .clamp(120.0, 300.0)
                }
                (None, Some(k)) => outputs.get(k).map_or(64.0, |o| pill_w(o.1)),
                (None, None) => 64.0,
            })
            .collect();
        let geometry = DiagramGeometry::new(&places, &item_w, n);
        let (width, height) = (geometry.width, geometry.height);
        let fit = if width <= DIAGRAM_MAX_SCALED_WIDTH {
            " style=\"max-width:100%;height:auto\""
        } else {
            ""
        };
        let mut svg = format!(
            "<svg class=\"graph\" width=\"{width:.0}\" height=\"{height:.0}\"{fit} \
             viewBox=\"0 0 {width:.0} {height:.0}\" role=\"img\" aria-label=\"graph {}\">\n\
             <defs><marker id=\"arrow\" viewBox=\"0 0 10 10\" refX=\"9\" refY=\"5\" \
             markerUnits=\"userSpaceOnUse\" markerWidth=\"9\" markerHeight=\"9\" orient=\"auto\">\
             <path d=\"M0,0 L10,5 L0,10 z\" fill=\"#868e96\"/></marker></defs>\n",
            escape(&graph.name)
        );
        for (src, dst, mapped, labels) in &edges {
            svg.push_str(&format!(
                "<path class=\"edge{}\" d=\"{}\" marker-end=\"url(#arrow)\"><title>{}{}</title></path>\n",
                if *mapped { " mapped" } else { "" },
                geometry.edge(*src, *dst),
                escape(&labels.join("\n")),
                if *mapped { "\n(mapped over the list)" } else { "" }
            ));
        }
        for (k, (node, name)) in outputs.iter().enumerate() {
            let r = geometry.shape(n + k);
            let max_pill = ((r.w - 24.0) / (6.6 * 1.1)).floor() as usize;
            svg.push_str(&format!(
                "<path class=\"edge out\" d=\"{}\" marker-end=\"url(#arrow)\"/>\n",
                geometry.edge(*node, n + k)
            ));
            svg.push_str(&format!(
                "<g class=\"output\"><title>output {full}</title><rect x=\"{x:.1}\" \
                 y=\"{y:.1}\" width=\"{w:.1}\" height=\"{h:.1}\" rx=\"{round:.1}\"/>\
                 <text x=\"{mid:.1}\" y=\"{base:.1}\" text-anchor=\"middle\">{label}</text></g>\n",
                full = escape(name),
                label = escape(&truncate(name, max_pill)),
                x = r.x,
                y = r.y,
                w = r.w,
                h = r.h,
                round = r.h / 2.0,
                mid = r.x + r.w / 2.0,
                base = r.y + r.h / 2.0 + 4.3,
            ));
        }
        for (i, node) in graph.nodes.iter().enumerate() {
            let Rect { x, y, w, h } = geometry.shape(i);
            let max_name = ((w - 24.0) / 8.0).floor() as usize;
            let max_op = ((w - 24.0) / 6.6).floor() as usize;
            let status = self.status(i);
            let (stroke, fill) = status_colors(status);
            let status_text = status.map_or("not run", status_name);
            let time = self.median_ms(i).map(render_ms);
            let time_chars = time.as_ref().map_or(0, |t| t.chars().count() + 2);
            let tip = format!(
                "{} ({}) — {status_text}{}",
                node.name,
                node.info.id,
                time.as_ref().map(|t| format!(", {t}")).unwrap_or_default()
            );
            svg.push_str(&format!(
                "<g class=\"node s-{status_text}\"><title>{}</title>\
                 <rect x=\"{x:.1}\" y=\"{y:.1}\" width=\"{w:.1}\" height=\"{h}\" rx=\"6\" \
                 fill=\"{fill}\" stroke=\"{stroke}\" stroke-width=\"1.5\"/>\
                 <rect x=\"{x:.1}\" y=\"{y:.1}\" width=\"7\" height=\"{h}\" rx=\"3\" fill=\"{stroke}\"/>\
                 <text class=\"name\" x=\"{:.1}\" y=\"{:.1}\">{}</text>\
                 <text class=\"op\" x=\"{:.1}\" y=\"{:.1}\">{}</text>",
                escape(&tip),
                x + 15.0,
                y + 19.0,
                escape(&truncate(&node.name, max_name)),
                x + 15.0,
                y + 36.0,
                escape(&truncate(&node.info.id, max_op.saturating_sub(time_chars))),
            ));
            if let Some(t) = time {
                svg.push_str(&format!(
                    "<text class=\"time\" x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">{}</text>",
                    x + w - 8.0,
                    y + 36.0,
                    escape(&t)
                ));
            }
            svg.push_str("</g>\n");
        }
        svg.push_str("</svg>");
        svg
    }

    // -- Per-node table -----------------------------------------------------------------------

    fn nodes_section(&self) -> String {
        let n = self.graph.nodes.len();
        let max_ms = (0..n).filter_map(|i| self.median_ms(i)).fold(0.0, f64::max);
        let max_bytes = (0..n).map(|i| self.output_bytes(i)).max().unwrap_or(0);
        let mut s = String::from(
            "<section>\n<h2>Per-node time and memory</h2>\n<table class=\"nodes\">\n<thead><tr>\
             <th>node</th><th>operator</th><th>status</th><th class=\"num\">time</th><th></th>\
             <th class=\"num\">output bytes</th><th></th></tr></thead>\n<tbody>\n",
        );
        let mut total_ms = 0.0;
        for (i, node) in self.graph.nodes.iter().enumerate() {
            let status = self.status(i);
            let time = match self.median_ms(i) {
                Some(ms) => {
                    total_ms += ms;
                    let spread = match self.profile.nodes.get(&node.name) {
                        Some(p) if self.runs > 1 => format!(
                            " <span class=\"muted\">({}–{})</span>",
                            render_ms(p.min_ms),
                            render_ms(p.max_ms)
                        ),
                        _ => String::new(),
                    };
                    (
                        format!("{}{spread}", render_ms(ms)),
                        bar(ms, max_ms, "time"),
                    )
                }
                None => ("—".to_string(), String::new()),
            };
            let bytes = self.output_bytes(i);
            let memory = if bytes > 0 {
                (
                    render_bytes(bytes as u64),
                    bar(bytes as f64, max_bytes as f64, "mem"),
                )
            } else {
                ("—".to_string(), String::new())
            };
            s.push_str(&format!(
                "<tr><td><code>{}</code></td><td>{}</td><td>{}</td><td class=\"num\">{}</td>\
                 <td class=\"barcell\">{}</td><td class=\"num\">{}</td><td class=\"barcell\">{}</td></tr>\n",
                escape(&node.name),
                escape(&node.info.id),
                status.map_or_else(|| "—".to_string(), chip),
                time.0,
                time.1,
                memory.0,
                memory.1
            ));
        }
        let wall = if self.runs > 1 {
            self.profile.total_median_ms
        } else {
            self.last.elapsed.as_secs_f64() * 1e3
        };
        s.push_str(&format!(
            "</tbody>\n<tfoot><tr><td colspan=\"3\">sum of node times · wall time of the run</td>\
             <td class=\"num\">{} · {}</td><td></td><td class=\"num\">peak {}</td><td></td></tr></tfoot>\n\
             </table>\n<p class=\"note\">Time: the operator's median over {} run{}{}; output bytes: \
             the values the node produced (computed or loaded from the cache).</p>\n</section>\n",
            render_ms(total_ms),
            render_ms(wall),
            render_bytes(self.profile.peak_bytes),
            self.runs,
            if self.runs == 1 { "" } else { "s" },
            if self.runs > 1 {
                " (min–max in brackets)"
            } else {
                ""
            },
        ));
        s
    }

    // -- Cache reuse --------------------------------------------------------------------------

    fn cache_section(&self) -> String {
        let total = self.last.nodes.len();
        let mut s = String::from("<section>\n<h2>Cache reuse</h2>\n<div class=\"stack\">");
        for status in STATUSES {
            let count = self.last.count(status);
            if count > 0 {
                s.push_str(&format!(
                    "<div class=\"s-{0}\" style=\"flex-grow:{count}\" title=\"{count} {0}\">{count} {0}</div>",
                    status_name(status)
                ));
            }
        }
        s.push_str("</div>\n");
        let cached = self.last.count(NodeStatus::Cached);
        let shared = self.last.count(NodeStatus::Shared);
        let needed = total - self.last.count(NodeStatus::Idle);
        let reused = cached + shared;
        let percent = if needed > 0 {
            100.0 * reused as f64 / needed as f64
        } else {
            0.0
        };
        s.push_str(&format!(
            "<p><b>{reused} of {needed}</b> needed node{} reused ({percent:.0} %): {cached} loaded \
             from the cache, {shared} shared with an identical node of this run; {} computed.</p>\n",
            if needed == 1 { "" } else { "s" },
            self.last.count(NodeStatus::Computed)
        ));
        let cache = if self.args.repeat > 1 {
            "<code>--repeat</code> runs without the disk cache, so every repeat computes."
                .to_string()
        } else if let Some(dir) = &self.args.cache {
            format!(
                "Disk cache: <code>{}</code>.",
                escape(&dir.display().to_string())
            )
        } else {
            "No disk cache (<code>--cache DIR</code> keeps results across runs); identical \
             nodes are still computed once."
                .to_string()
        };
        s.push_str(&format!("<p class=\"note\">{cache}</p>\n"));
        for status in [NodeStatus::Cached, NodeStatus::Shared, NodeStatus::Idle] {
            let names: Vec<String> = self
                .last
                .nodes
                .iter()
                .filter(|n| n.status == status)
                .map(|n| format!("<code>{}</code>", escape(&n.name)))
                .collect();
            if !names.is_empty() {
                s.push_str(&format!("<p>{} {}</p>\n", chip(status), names.join(", ")));
            }
        }
        s.push_str("</section>\n");
        s
    }

    /// `--ray`: each distributed list map (elements done, reused, tasks) and the per-worker
    /// time table. Empty when nothing ran distributed.
    fn distributed_section(&self) -> String {
        let stages = &self.last.distributed;
        if stages.is_empty() {
            return String::new();
        }
        let mut s = String::from(
            "<section>\n<h2>Distributed list maps</h2>\n<table class=\"nodes\">\n<thead><tr>\
             <th>node</th><th>op</th><th>items</th><th>reused</th><th>tasks</th>\
             <th>failed</th><th>wall</th><th>sent</th><th>received</th></tr></thead>\n<tbody>\n",
        );
        for st in stages {
            s.push_str(&format!(
                "<tr><td><code>{}</code></td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>\
                 <td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>\n",
                escape(&st.node),
                escape(&st.op),
                st.items,
                st.reused,
                st.tasks,
                st.failed_tasks,
                render_ms(st.elapsed.as_secs_f64() * 1e3),
                render_bytes(st.bytes_sent as u64),
                render_bytes(st.bytes_received as u64)
            ));
        }
        s.push_str(
            "</tbody>\n</table>\n<h3>Per-worker time</h3>\n<table class=\"nodes\">\n\
            <thead><tr><th>node</th><th>worker</th><th>tasks</th><th>items</th><th>busy</th>\
            </tr></thead>\n<tbody>\n",
        );
        for st in stages {
            for (worker, w) in &st.workers {
                s.push_str(&format!(
                    "<tr><td><code>{}</code></td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>\n",
                    escape(&st.node),
                    escape(worker),
                    w.tasks,
                    w.items,
                    render_ms(w.busy_seconds * 1e3)
                ));
            }
        }
        s.push_str("</tbody>\n</table>\n</section>\n");
        s
    }

    // -- Outputs ------------------------------------------------------------------------------

    fn outputs_section(&self) -> String {
        let requested: Vec<_> = self
            .graph
            .outputs
            .iter()
            .filter(|o| self.args.output.is_empty() || self.args.output.contains(&o.name))
            .collect();
        let mut s = format!(
            "<section>\n<h2>Outputs <span class=\"muted\">({})</span></h2>\n<div class=\"cards\">\n",
            requested.len()
        );
        for output in requested {
            let node = self.graph.nodes.get(output.from.node);
            let port = node
                .and_then(|n| n.info.outputs.get(output.from.port))
                .map_or("?", |p| p.name.as_str());
            let index = output.index.map(|k| format!("[{k}]")).unwrap_or_default();
            let source = format!("{}.{port}{index}", node.map_or("?", |n| n.name.as_str()));
            let value = self.last.output(&output.name);
            let ty = value.map_or_else(|| output.ty.to_string(), |v| v.port_type().to_string());
            let wide = match value {
                Some(Value::Image(image)) => {
                    // Landscape images wider than a card's column span two columns.
                    let long = image.width().max(image.height()).max(1);
                    image.width() * MAX_PREVIEW_SIDE.min(long) / long > 360
                        && image.width() * 2 >= image.height() * 3
                }
                _ => false,
            };
            s.push_str(&format!(
                "<article class=\"card output{}\" id=\"output-{}\">\n<h3>{}</h3>\n\
                 <p class=\"meta\"><span class=\"type\">{}</span> from <code>{}</code></p>\n",
                if wide { " wide" } else { "" },
                escape(&output.name),
                escape(&output.name),
                escape(&ty),
                escape(&source)
            ));
            match value {
                Some(v) => s.push_str(&preview(v, &output.name)),
                None => {
                    let why = match self.status(output.from.node) {
                        Some(NodeStatus::Failed) => "its node failed (see Problems)",
                        Some(NodeStatus::Skipped) => "an upstream node failed",
                        _ => "the run did not produce it",
                    };
                    s.push_str(&format!("<p class=\"missing\">Not produced: {why}.</p>\n"));
                }
            }
            s.push_str("</article>\n");
        }
        s.push_str("</div>\n</section>\n");
        s
    }
}

/// A horizontal bar of `value / max`.
fn bar(value: f64, max: f64, class: &str) -> String {
    let percent = if max > 0.0 {
        (100.0 * value / max).clamp(0.5, 100.0)
    } else {
        0.0
    };
    format!(
        "<div class=\"track\"><div class=\"bar {class}\" style=\"width:{percent:.1}%\"></div></div>"
    )
}

// ---------------------------------------------------------------------------------------------
// Output previews.

/// The body of an output's card.
fn preview(value: &Value, name: &str) -> String {
    match value {
        Value::Image(image) => image_html(image, name, MAX_PREVIEW_SIDE),
        Value::Mesh(mesh) => mesh_html(mesh, name),
        Value::PointCloud(cloud) => point_cloud_html(cloud, name),
        Value::Reconstruction(r) => reconstruction_html(r, name),
        Value::Metrics(m) => metrics_html(m),
        Value::Matrix(m) => matrix_html(m),
        Value::Scalar(x) => format!("<p class=\"big\">{}</p>\n", escape(&fmt_sig6(*x))),
        Value::Integer(x) => format!("<p class=\"big\">{x}</p>\n"),
        Value::Bool(x) => format!("<p class=\"big\">{x}</p>\n"),
        Value::Text(t) => format!(
            "<pre class=\"text\">{}</pre>\n<p class=\"note\">{} characters</p>\n",
            escape(&truncate(t, 4000)),
            t.chars().count()
        ),
        Value::Keypoints(k) => {
            let rows: Vec<Vec<String>> = k
                .iter()
                .take(FIRST_ITEMS)
                .map(|p| {
                    vec![
                        fmt_sig6(f64::from(p.x)),
                        fmt_sig6(f64::from(p.y)),
                        fmt_sig6(f64::from(p.size)),
                        fmt_sig6(f64::from(p.angle)),
                        fmt_sig6(f64::from(p.response)),
                    ]
                })
                .collect();
            format!(
                "<p><b>{}</b> keypoints</p>\n{}",
                k.len(),
                small_table(&["x", "y", "size", "angle", "response"], &rows, k.len())
            )
        }
        Value::Matches(m) => {
            let rows: Vec<Vec<String>> = m
                .iter()
                .take(FIRST_ITEMS)
                .map(|x| {
                    vec![
                        x.query.to_string(),
                        x.train.to_string(),
                        fmt_sig6(f64::from(x.distance)),
                    ]
                })
                .collect();
            format!(
                "<p><b>{}</b> matches</p>\n{}",
                m.len(),
                small_table(&["query", "train", "distance"], &rows, m.len())
            )
        }
        Value::Points2D(p) => {
            let rows: Vec<Vec<String>> = p
                .iter()
                .take(FIRST_ITEMS)
                .map(|q| vec![fmt_sig6(q[0]), fmt_sig6(q[1])])
                .collect();
            format!(
                "<p><b>{}</b> points</p>\n{}",
                p.len(),
                small_table(&["x", "y"], &rows, p.len())
            )
        }
        Value::Tracks(t) => {
            let lengths: Vec<usize> = t.tracks.iter().map(Vec::len).collect();
            let mean = if lengths.is_empty() {
                0.0
            } else {
                lengths.iter().sum::<usize>() as f64 / lengths.len() as f64
            };
            format!(
                "<p><b>{}</b> tracks, mean length {mean:.2}, longest {}</p>\n{}",
                lengths.len(),
                lengths.iter().max().copied().unwrap_or(0),
                summary_pre(value)
            )
        }
        Value::List(list) => list_html(&list.items, &list.element.to_string(), name),
        _ => summary_pre(value),
    }
}

/// The snapshot summary of a value, cut to [`SUMMARY_LINES`] lines.
fn summary_pre(value: &Value) -> String {
    let text = summarize_value(value);
    let lines: Vec<&str> = text.lines().collect();
    let mut shown = lines
        .iter()
        .take(SUMMARY_LINES)
        .map(|l| truncate(l, 300))
        .collect::<Vec<_>>()
        .join("\n");
    if lines.len() > SUMMARY_LINES {
        shown.push_str(&format!("\n… {} more lines", lines.len() - SUMMARY_LINES));
    }
    format!("<pre class=\"summary\">{}</pre>\n", escape(&shown))
}

/// A table of the first rows of a longer sequence of `total` items.
fn small_table(head: &[&str], rows: &[Vec<String>], total: usize) -> String {
    if rows.is_empty() {
        return String::new();
    }
    let mut s = String::from("<table class=\"small\"><thead><tr><th class=\"num\">#</th>");
    for h in head {
        s.push_str(&format!("<th class=\"num\">{}</th>", escape(h)));
    }
    s.push_str("</tr></thead><tbody>\n");
    for (i, row) in rows.iter().enumerate() {
        s.push_str(&format!("<tr><td class=\"num muted\">{i}</td>"));
        for cell in row {
            s.push_str(&format!("<td class=\"num\">{}</td>", escape(cell)));
        }
        s.push_str("</tr>\n");
    }
    s.push_str("</tbody></table>\n");
    if total > rows.len() {
        s.push_str(&format!(
            "<p class=\"note\">first {} of {total}</p>\n",
            rows.len()
        ));
    }
    s
}

fn metrics_html(metrics: &Metrics) -> String {
    if metrics.is_empty() {
        return "<p class=\"muted\">no metrics</p>\n".into();
    }
    let mut s = String::from("<div class=\"scroll\"><table class=\"kv\"><tbody>\n");
    for (name, value) in metrics.iter() {
        s.push_str(&format!(
            "<tr><th>{}</th><td class=\"num\">{}</td></tr>\n",
            escape(name),
            escape(&fmt_sig6(*value))
        ));
    }
    s.push_str("</tbody></table></div>\n");
    s.push_str(&format!(
        "<p class=\"note\">{} entr{}</p>\n",
        metrics.len(),
        if metrics.len() == 1 { "y" } else { "ies" }
    ));
    s
}

fn matrix_html(m: &Matrix) -> String {
    let mut s = format!("<p><b>{}×{}</b> matrix</p>\n", m.rows, m.cols);
    if m.rows == 0 || m.cols == 0 {
        return s;
    }
    let cols = m.cols.min(MATRIX_COLS);
    s.push_str("<div class=\"scroll\"><table class=\"matrix\"><thead><tr><th></th>");
    for c in 0..cols {
        s.push_str(&format!("<th class=\"num\">{c}</th>"));
    }
    if m.cols > cols {
        s.push_str("<th>…</th>");
    }
    s.push_str("</tr></thead><tbody>\n");
    for r in 0..m.rows.min(MATRIX_ROWS) {
        s.push_str(&format!("<tr><th class=\"num\">{r}</th>"));
        for c in 0..cols {
            let v = m.get(r, c).map(fmt_sig6).unwrap_or_default();
            s.push_str(&format!("<td class=\"num\">{}</td>", escape(&v)));
        }
        if m.cols > cols {
            s.push_str("<td>…</td>");
        }
        s.push_str("</tr>\n");
    }
    s.push_str("</tbody></table></div>\n");
    if m.rows > MATRIX_ROWS || m.cols > cols {
        s.push_str(&format!(
            "<p class=\"note\">first {} rows and {cols} columns shown</p>\n",
            m.rows.min(MATRIX_ROWS)
        ));
    }
    s
}

fn list_html(items: &[Value], element: &str, name: &str) -> String {
    let mut s = format!(
        "<p><b>{}</b> element{} of type {}</p>\n",
        items.len(),
        if items.len() == 1 { "" } else { "s" },
        escape(element)
    );
    let visual = |v: &Value| {
        matches!(
            v,
            Value::Image(_) | Value::Mesh(_) | Value::PointCloud(_) | Value::Reconstruction(_)
        )
    };
    if items.iter().take(MAX_LIST_PREVIEWS).any(visual) {
        s.push_str("<div class=\"strip\">\n");
        for (i, item) in items.iter().take(MAX_LIST_PREVIEWS).enumerate() {
            let alt = format!("{name}[{i}]");
            let body = match item {
                Value::Image(image) => image_html(image, &alt, MAX_LIST_PREVIEW_SIDE),
                Value::Mesh(mesh) => thumbnail_html(render_mesh(mesh), &alt),
                Value::PointCloud(c) => thumbnail_html(
                    splat_points(&c.positions, c.colors.as_deref(), c.normals.as_deref()),
                    &alt,
                ),
                Value::Reconstruction(r) => thumbnail_html(reconstruction_thumbnail(r), &alt),
                other => summary_pre(other),
            };
            s.push_str(&format!(
                "<figure>{body}<figcaption>[{i}]</figcaption></figure>\n"
            ));
        }
        s.push_str("</div>\n");
        if items.len() > MAX_LIST_PREVIEWS {
            s.push_str(&format!(
                "<p class=\"note\">first {MAX_LIST_PREVIEWS} of {} shown</p>\n",
                items.len()
            ));
        }
    } else if !items.is_empty() {
        let list = Value::list(
            items
                .first()
                .map_or(ocellus_engine::PortType::Scalar, Value::port_type),
            items.to_vec(),
        );
        s.push_str(&summary_pre(&list));
    }
    s
}

fn bounds_text(positions: &[[f32; 3]]) -> String {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in positions.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    if lo[0] > hi[0] {
        return "no finite positions".into();
    }
    let f = |v: [f32; 3]| {
        format!(
            "({}, {}, {})",
            fmt_sig6(f64::from(v[0])),
            fmt_sig6(f64::from(v[1])),
            fmt_sig6(f64::from(v[2]))
        )
    };
    format!("bounds {} – {}", f(lo), f(hi))
}

fn mesh_html(mesh: &Arc<Mesh>, name: &str) -> String {
    let thumb = if mesh.triangles.is_empty() {
        splat_points(&mesh.positions, None, mesh.normals.as_deref())
    } else {
        render_mesh(mesh)
    };
    let attrs: Vec<&str> = [
        (mesh.normals.is_some(), "normals"),
        (mesh.uvs.is_some(), "uvs"),
        (mesh.colors.is_some(), "colors"),
        (mesh.tangents.is_some(), "tangents"),
    ]
    .into_iter()
    .filter_map(|(has, n)| has.then_some(n))
    .collect();
    format!(
        "{}<p><b>{}</b> vertices, <b>{}</b> triangles{}</p>\n<p class=\"note\">{}</p>\n",
        thumbnail_html(thumb, name),
        mesh.positions.len(),
        mesh.triangles.len(),
        if attrs.is_empty() {
            String::new()
        } else {
            format!(" · {}", attrs.join(", "))
        },
        escape(&bounds_text(&mesh.positions))
    )
}

fn point_cloud_html(cloud: &PointCloud, name: &str) -> String {
    let thumb = splat_points(
        &cloud.positions,
        cloud.colors.as_deref(),
        cloud.normals.as_deref(),
    );
    let attrs: Vec<&str> = [
        (cloud.colors.is_some(), "colors"),
        (cloud.normals.is_some(), "normals"),
    ]
    .into_iter()
    .filter_map(|(has, n)| has.then_some(n))
    .collect();
    format!(
        "{}<p><b>{}</b> points{}</p>\n<p class=\"note\">{}</p>\n",
        thumbnail_html(thumb, name),
        cloud.positions.len(),
        if attrs.is_empty() {
            String::new()
        } else {
            format!(" · {}", attrs.join(", "))
        },
        escape(&bounds_text(&cloud.positions))
    )
}

/// The points in their colours and the camera centres as orange markers.
fn reconstruction_thumbnail(r: &Reconstruction) -> Result<Pixels, String> {
    let positions: Vec<[f32; 3]> = r
        .points
        .iter()
        .map(|p| p.position.map(|c| c as f32))
        .collect();
    let colors: Vec<[u8; 3]> = r.points.iter().map(|p| p.color).collect();
    let centres: Vec<[f32; 3]> = r
        .images
        .iter()
        .map(|image| {
            let pose = &image.camera_from_world;
            let m = pose.rotation_matrix();
            let t = pose.translation;
            [0, 1, 2].map(|j| -(0..3).map(|i| m[3 * i + j] * t[i]).sum::<f64>() as f32)
        })
        .collect();
    splat_scene(&positions, Some(&colors), None, &centres)
}

/// The points within 1.2 × the 95th-percentile distance from the per-axis median (all of
/// them when there are few), so that a handful of outliers does not shrink the view.
fn robust_subset(points: &[[f32; 3]]) -> Vec<[f32; 3]> {
    if points.len() < 20 {
        return points.to_vec();
    }
    let median = [0, 1, 2].map(|k| {
        let mut v: Vec<f32> = points.iter().map(|p| p[k]).collect();
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    });
    let distance = |p: &[f32; 3]| {
        (0..3)
            .map(|k| (f64::from(p[k]) - f64::from(median[k])).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let mut d: Vec<f64> = points.iter().map(distance).collect();
    d.sort_by(f64::total_cmp);
    let limit = 1.2 * d[(d.len() - 1) * 95 / 100];
    points
        .iter()
        .filter(|p| distance(p) <= limit)
        .copied()
        .collect()
}

fn reconstruction_html(r: &Reconstruction, name: &str) -> String {
    let mean_error = if r.points.is_empty() {
        0.0
    } else {
        r.points.iter().map(|p| p.error_px).sum::<f64>() / r.points.len() as f64
    };
    format!(
        "{}<p><b>{}</b> cameras, <b>{}</b> images, <b>{}</b> points, mean reprojection error \
         {} px</p>\n",
        thumbnail_html(reconstruction_thumbnail(r), name),
        r.cameras.len(),
        r.images.len(),
        r.points.len(),
        escape(&fmt_sig6(mean_error))
    )
}

// ---------------------------------------------------------------------------------------------
// Pixels: display conversion, downscaling, PNG data URIs, thumbnails.

/// 8-bit pixels ready for PNG.
#[derive(Debug, Clone, PartialEq)]
struct Pixels {
    width: usize,
    height: usize,
    channels: Channels,
    data: Vec<u8>,
}

fn linear_to_srgb(c: f32) -> f32 {
    if c.is_nan() || c <= 0.0 {
        0.0
    } else if c >= 1.0 {
        1.0
    } else if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

fn srgb_to_linear(v: u8) -> f32 {
    let c = f32::from(v) / 255.0;
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn unit_byte(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Finite minimum, maximum and the count of non-finite samples.
fn finite_range(values: impl Iterator<Item = f64>) -> (f64, f64, usize) {
    let (mut lo, mut hi, mut bad) = (f64::INFINITY, f64::NEG_INFINITY, 0);
    for v in values {
        if v.is_finite() {
            lo = lo.min(v);
            hi = hi.max(v);
        } else {
            bad += 1;
        }
    }
    (lo, hi, bad)
}

/// 8-bit display pixels of an image and a note on how its values were mapped (empty for u8):
/// u16 scaled by 255/65535 (stretched from 0 to the largest value when that is under 4096);
/// f32 colour taken as linear light and sRGB-encoded (as the renderers produce it), f32 gray
/// stretched from its smallest to its largest finite value; non-finite samples show as 0.
fn display_pixels(image: &Image) -> (Pixels, String) {
    let (width, height, channels) = (image.width(), image.height(), image.channels());
    let (data, note) = match image.data() {
        PixelData::U8(d) => (d.clone(), String::new()),
        PixelData::U16(d) => {
            let max = d.iter().copied().max().unwrap_or(0);
            let min = d.iter().copied().min().unwrap_or(0);
            if max > 0 && max < 4096 {
                let data = d
                    .iter()
                    .map(|&v| ((u32::from(v) * 255 + u32::from(max) / 2) / u32::from(max)) as u8)
                    .collect();
                (
                    data,
                    format!("u16 values {min} … {max}, stretched from 0 … {max} for display"),
                )
            } else {
                let data = d
                    .iter()
                    .map(|&v| ((u32::from(v) * 255 + 32767) / 65535) as u8)
                    .collect();
                (
                    data,
                    format!("u16 values {min} … {max}, shown as value / 257"),
                )
            }
        }
        PixelData::F32(d) => {
            let (lo, hi, bad) = finite_range(d.iter().map(|&v| f64::from(v)));
            let range = if lo <= hi {
                format!("f32 values {} … {}", fmt_sig6(lo), fmt_sig6(hi))
            } else {
                "f32, no finite values".to_string()
            };
            let bad_note = if bad > 0 {
                format!(", {bad} non-finite shown as 0")
            } else {
                String::new()
            };
            if channels == Channels::Gray {
                let span = hi - lo;
                let data = d
                    .iter()
                    .map(|&v| {
                        let v = f64::from(v);
                        if !v.is_finite() {
                            0
                        } else if span > 0.0 {
                            (255.0 * (v - lo) / span).round().clamp(0.0, 255.0) as u8
                        } else {
                            unit_byte(v as f32)
                        }
                    })
                    .collect();
                (
                    data,
                    format!("{range}{bad_note}; stretched from min … max to black … white"),
                )
            } else {
                let per_pixel = channels.count();
                let data = d
                    .iter()
                    .enumerate()
                    .map(|(i, &v)| {
                        if !v.is_finite() {
                            0
                        } else if channels == Channels::Rgba && i % per_pixel == 3 {
                            unit_byte(v)
                        } else {
                            unit_byte(linear_to_srgb(v))
                        }
                    })
                    .collect();
                let clamp = if lo < 0.0 || hi > 1.0 {
                    ", clamped to 0 … 1"
                } else {
                    ""
                };
                (
                    data,
                    format!("{range}{bad_note}; linear light, sRGB-encoded for display{clamp}"),
                )
            }
        }
    };
    (
        Pixels {
            width,
            height,
            channels,
            data,
        },
        note,
    )
}

/// Area-averaged downscale so that the longer side is at most `max_side`.
fn downscale(p: Pixels, max_side: usize) -> Pixels {
    let long = p.width.max(p.height);
    if long <= max_side || p.width == 0 || p.height == 0 {
        return p;
    }
    let scale = max_side as f64 / long as f64;
    let nw = ((p.width as f64 * scale).round() as usize).clamp(1, max_side);
    let nh = ((p.height as f64 * scale).round() as usize).clamp(1, max_side);
    let c = p.channels.count();
    let mut data = vec![0u8; nw * nh * c];
    let mut sums = vec![0u64; c];
    for oy in 0..nh {
        let y0 = oy * p.height / nh;
        let y1 = ((oy + 1) * p.height / nh).max(y0 + 1).min(p.height);
        for ox in 0..nw {
            let x0 = ox * p.width / nw;
            let x1 = ((ox + 1) * p.width / nw).max(x0 + 1).min(p.width);
            sums.iter_mut().for_each(|s| *s = 0);
            for y in y0..y1 {
                let row = &p.data[(y * p.width + x0) * c..(y * p.width + x1) * c];
                for px in row.chunks_exact(c) {
                    for (s, &v) in sums.iter_mut().zip(px) {
                        *s += u64::from(v);
                    }
                }
            }
            let count = ((y1 - y0) * (x1 - x0)) as u64;
            let out = &mut data[(oy * nw + ox) * c..(oy * nw + ox + 1) * c];
            for (o, s) in out.iter_mut().zip(&sums) {
                *o = ((s + count / 2) / count) as u8;
            }
        }
    }
    Pixels {
        width: nw,
        height: nh,
        channels: p.channels,
        data,
    }
}

/// `data:image/png;base64,…` of 8-bit pixels.
fn png_data_uri(p: &Pixels) -> Result<String, String> {
    let image =
        Image::from_u8(p.width, p.height, p.channels, p.data.clone()).map_err(|e| e.to_string())?;
    let png = encode_image(&image, ImageFormat::Png).map_err(|e| e.to_string())?;
    Ok(format!("data:image/png;base64,{}", base64(&png)))
}

/// An `<img>` of pixels; small images are enlarged with visible pixels.
fn img_tag(p: &Pixels, alt: &str, min_width: usize) -> Result<String, String> {
    let uri = png_data_uri(p)?;
    let factor = if p.width > 0 && p.width < min_width {
        (min_width / p.width).clamp(1, 8)
    } else {
        1
    };
    let class = if factor > 1 {
        " class=\"pixelated\""
    } else {
        ""
    };
    Ok(format!(
        "<img{class} src=\"{uri}\" width=\"{}\" height=\"{}\" alt=\"{}\">",
        p.width * factor,
        p.height * factor,
        escape(alt)
    ))
}

fn image_html(image: &Image, alt: &str, max_side: usize) -> String {
    let size = format!("{}×{} {}", image.width(), image.height(), image.format());
    if image.is_empty() {
        return format!("<p class=\"muted\">empty image ({size})</p>\n");
    }
    let (pixels, note) = display_pixels(image);
    let pixels = downscale(pixels, max_side);
    let shown = if pixels.width != image.width() {
        format!(", shown at {}×{}", pixels.width, pixels.height)
    } else {
        String::new()
    };
    let min_width = if max_side >= MAX_PREVIEW_SIDE {
        240
    } else {
        96
    };
    match img_tag(&pixels, alt, min_width) {
        Ok(img) => format!(
            "<div class=\"preview\">{img}</div>\n<p class=\"note\">{}{}{}</p>\n",
            escape(&size),
            escape(&shown),
            if note.is_empty() {
                String::new()
            } else {
                format!("<br>{}", escape(&note))
            }
        ),
        Err(e) => format!(
            "<p class=\"missing\">{}: no preview ({})</p>\n",
            escape(&size),
            escape(&e)
        ),
    }
}

fn thumbnail_html(thumb: Result<Pixels, String>, alt: &str) -> String {
    match thumb.and_then(|p| img_tag(&p, alt, 0)) {
        Ok(img) => format!("<div class=\"preview\">{img}</div>\n"),
        Err(e) => format!("<p class=\"missing\">no thumbnail: {}</p>\n", escape(&e)),
    }
}

/// Runs a renderer, turning a panic into an error (the report must not take the run down).
fn guarded(f: impl FnOnce() -> Result<Pixels, String>) -> Result<Pixels, String> {
    std::panic::catch_unwind(AssertUnwindSafe(f))
        .unwrap_or_else(|_| Err("the thumbnail renderer failed".into()))
}

fn thumb_params() -> MeshSceneParams {
    MeshSceneParams {
        width: THUMB_WIDTH as u32,
        height: THUMB_HEIGHT as u32,
        albedo: [0.70, 0.74, 0.80],
        ..MeshSceneParams::default()
    }
}

/// A shaded 240×180 view of a mesh: `render.mesh_scene`'s framing camera and lights,
/// `render.rasterize` with 4× MSAA and shadows, sRGB-encoded.
fn render_mesh(mesh: &Arc<Mesh>) -> Result<Pixels, String> {
    guarded(|| {
        let params = thumb_params();
        let (camera, light_direction) = framing_camera(&mesh.positions, &params)?;
        let radius = framing(&mesh.positions, None).map_or(1.0, |(_, r)| r);
        let scene = Scene {
            materials: vec![Material {
                name: "mesh".into(),
                albedo: params.albedo.map(|a| a as f32),
                ..Material::default()
            }],
            objects: vec![SceneObject {
                name: "mesh".into(),
                shape: Shape::Mesh(Arc::clone(mesh)),
                world_from_object: Pose::IDENTITY,
                scale: 1.0,
                material: 0,
            }],
            lights: vec![
                Light::Directional {
                    direction: light_direction,
                    irradiance: [params.light_irradiance as f32; 3],
                },
                Light::Environment {
                    radiance: [params.ambient as f32; 3],
                    map: None,
                },
            ],
            cameras: vec![camera],
        };
        let options = RasterOptions {
            cull: Cull::None,
            samples: 4,
            near: (radius * 1e-3).max(1e-9),
            shadow_map_size: 512,
            background: THUMB_BACKGROUND.map(srgb_to_linear),
        };
        let out = rasterize(&scene, 0, &options)?;
        Ok(Pixels {
            width: out.width,
            height: out.height,
            channels: Channels::Rgb,
            data: out
                .color
                .iter()
                .map(|&c| unit_byte(linear_to_srgb(c)))
                .collect(),
        })
    })
}

/// A 240×180 view of points seen by `render.mesh_scene`'s framing camera: z-buffered square
/// splats, coloured by the points' colours (or a blue), shaded by the normals towards the key
/// light when present, and darker with depth.
fn splat_points(
    positions: &[[f32; 3]],
    colors: Option<&[[u8; 3]]>,
    normals: Option<&[[f32; 3]]>,
) -> Result<Pixels, String> {
    splat_scene(positions, colors, normals, &[])
}

/// [`splat_points`] with `markers` (camera centres) drawn over the points in orange; the view
/// frames the points (without far outliers) and the markers.
fn splat_scene(
    positions: &[[f32; 3]],
    colors: Option<&[[u8; 3]]>,
    normals: Option<&[[f32; 3]]>,
    markers: &[[f32; 3]],
) -> Result<Pixels, String> {
    guarded(|| {
        let finite: Vec<[f32; 3]> = positions
            .iter()
            .filter(|p| p.iter().all(|c| c.is_finite()))
            .copied()
            .collect();
        let mut finite = robust_subset(&finite);
        finite.extend(markers.iter().filter(|p| p.iter().all(|c| c.is_finite())));
        let params = thumb_params();
        let (camera, light_direction) = framing_camera(&finite, &params)?;
        let (target, radius) =
            framing(&finite, None).ok_or("the points have no finite positions")?;
        let r = camera.camera_from_world.rotation_matrix();
        let t = camera.camera_from_world.translation;
        let [fx, fy, cx, cy] = match camera.camera.params.as_slice() {
            [fx, fy, cx, cy, ..] => [*fx, *fy, *cx, *cy],
            _ => return Err("unexpected camera model".into()),
        };
        let eye = [0, 1, 2].map(|j| -(0..3).map(|i| r[3 * i + j] * t[i]).sum::<f64>());
        let distance = (0..3)
            .map(|k| (eye[k] - target[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        let (near, far) = (distance - radius, distance + radius.max(1e-12));
        let (w, h) = (THUMB_WIDTH, THUMB_HEIGHT);
        let mut depth = vec![f64::INFINITY; w * h];
        let mut data: Vec<u8> = std::iter::repeat_n(THUMB_BACKGROUND, w * h)
            .flatten()
            .collect();
        let half: i64 = match positions.len() {
            0..=4_000 => 2,
            4_001..=40_000 => 1,
            _ => 0,
        };
        for (i, p) in positions.iter().chain(markers).enumerate() {
            if !p.iter().all(|c| c.is_finite()) {
                continue;
            }
            let x = [0, 1, 2]
                .map(|k| (0..3).map(|j| r[3 * k + j] * f64::from(p[j])).sum::<f64>() + t[k]);
            if x[2] <= 1e-12 {
                continue;
            }
            let u = (fx * x[0] / x[2] + cx).round() as i64;
            let v = (fy * x[1] / x[2] + cy).round() as i64;
            let fade = 1.0 - 0.55 * ((x[2] - near) / (far - near)).clamp(0.0, 1.0);
            let shade = match normals.and_then(|n| n.get(i)) {
                Some(n) => {
                    let d = -(f64::from(n[0]) * light_direction[0]
                        + f64::from(n[1]) * light_direction[1]
                        + f64::from(n[2]) * light_direction[2]);
                    0.35 + 0.65 * d.abs().min(1.0)
                }
                None => 1.0,
            };
            let marker = i >= positions.len();
            let base = if marker {
                [255, 146, 43]
            } else {
                colors
                    .and_then(|c| c.get(i))
                    .copied()
                    .unwrap_or([116, 172, 236])
            };
            let shade = if marker { 1.0 / fade } else { shade };
            let color = base.map(|b| (f64::from(b) * fade * shade).round().clamp(0.0, 255.0) as u8);
            let half = if marker { 2 } else { half };
            for dv in -half..=half {
                for du in -half..=half {
                    let (uu, vv) = (u + du, v + dv);
                    if uu < 0 || vv < 0 || uu >= w as i64 || vv >= h as i64 {
                        continue;
                    }
                    let k = vv as usize * w + uu as usize;
                    if marker || x[2] < depth[k] {
                        depth[k] = if marker { f64::NEG_INFINITY } else { x[2] };
                        data[3 * k..3 * k + 3].copy_from_slice(&color);
                    }
                }
            }
        }
        Ok(Pixels {
            width: w,
            height: h,
            channels: Channels::Rgb,
            data,
        })
    })
}

// ---------------------------------------------------------------------------------------------
// Style and script.

const STYLE: &str = r#"
:root{--fg:#212529;--muted:#6c757d;--line:#e3e6ea;--bg:#f4f5f7;--card:#fff}
*{box-sizing:border-box}
body{margin:0;background:var(--bg);color:var(--fg);font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,"Liberation Sans","DejaVu Sans",Arial,sans-serif}
main{max-width:1220px;margin:0 auto;padding:22px 24px 32px}
header{margin-bottom:6px}
h1{margin:0 0 2px;font-size:26px;letter-spacing:-.01em}
h2{font-size:16px;margin:0 0 12px}
h3{font-size:15px;margin:0}
code{font:12.5px/1.3 "DejaVu Sans Mono",ui-monospace,Menlo,Consolas,monospace;background:#f1f3f5;padding:1px 4px;border-radius:4px}
.desc{margin:0 0 14px;color:#495057;font-size:15px}
.muted{color:var(--muted);font-weight:400}
.facts{display:flex;flex-wrap:wrap;gap:10px 28px;margin:0}
.facts dt{font-size:11px;text-transform:uppercase;letter-spacing:.06em;color:var(--muted)}
.facts dd{margin:0;font-weight:600}
.count{display:inline-flex;align-items:center;gap:5px;margin-right:10px;white-space:nowrap;font-weight:500}
.dot{display:inline-block;width:10px;height:10px;border-radius:50%}
section{background:var(--card);border:1px solid var(--line);border-radius:10px;padding:16px 18px;margin:16px 0;box-shadow:0 1px 2px rgba(0,0,0,.03)}
section.problems{border-color:#ffc9c9;background:#fff5f5}
.problems ul{margin:0;padding-left:18px}
.fail{color:#c92a2a}.warn{color:#e67700}
.diagram{overflow-x:auto;padding-bottom:4px}
svg.graph text{font-family:system-ui,"Liberation Sans","DejaVu Sans",Arial,sans-serif}
svg.graph .name{font-size:13px;font-weight:600;fill:#212529}
svg.graph .op{font-size:11.5px;fill:#6c757d}
svg.graph .time{font-size:11.5px;fill:#343a40;font-variant-numeric:tabular-nums}
svg.graph .edge{fill:none;stroke:#868e96;stroke-width:1.5}
svg.graph .edge.mapped{stroke-width:3.2}
svg.graph .edge.out{stroke-dasharray:4 3}
svg.graph .output rect{fill:#fff;stroke:#495057;stroke-width:1.2}
svg.graph .output text{font-size:12.5px;fill:#212529;font-weight:600}
.legend{margin:8px 0 0;font-size:12.5px}
.chip{display:inline-block;padding:0 8px;border-radius:999px;font-size:12px;line-height:19px;color:#fff;font-weight:600}
.s-computed{background:#2f9e44}.s-cached{background:#1c7ed6}.s-shared{background:#7048e8}
.s-failed{background:#e03131}.s-skipped{background:#f08c00}.s-idle{background:#adb5bd}
.cards{display:grid;grid-template-columns:repeat(auto-fill,minmax(340px,1fr));gap:14px}
.card{border:1px solid var(--line);border-radius:8px;padding:12px 14px;background:#fff;min-width:0}
@media (min-width:800px){.card.wide{grid-column:span 2}}
.card .meta{color:var(--muted);font-size:12.5px;margin:2px 0 10px}
.card .type{display:inline-block;background:#e7f5ff;color:#1864ab;border-radius:4px;padding:0 6px;font-weight:600}
.card p{margin:6px 0}
.preview img{max-width:100%;height:auto;display:block;border-radius:4px;border:1px solid var(--line);background:#fff}
img.pixelated{image-rendering:pixelated}
.strip{display:flex;flex-wrap:wrap;gap:8px}
.strip figure{margin:0}
.strip figcaption{font-size:11.5px;color:var(--muted);text-align:center}
.note{color:var(--muted);font-size:12px;margin:6px 0 0}
.missing{color:#c92a2a}
.big{font-size:26px;font-weight:600;margin:4px 0}
pre{white-space:pre-wrap;word-break:break-word;font:12px/1.4 "DejaVu Sans Mono",ui-monospace,Menlo,Consolas,monospace;background:#f8f9fa;border:1px solid var(--line);border-radius:6px;padding:8px;margin:6px 0;max-height:340px;overflow:auto}
table{border-collapse:collapse;width:100%}
th,td{padding:4px 8px;border-bottom:1px solid var(--line);text-align:left;vertical-align:middle}
thead th{font-size:11.5px;text-transform:uppercase;letter-spacing:.04em;color:var(--muted);font-weight:600}
tfoot td{color:var(--muted);border-bottom:0}
.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
table.kv th{font-weight:500;color:#343a40}
table.small,table.kv,table.matrix{font-size:12.5px}
.scroll{max-height:340px;overflow:auto;border:1px solid var(--line);border-radius:6px}
.scroll table tr:last-child>*{border-bottom:0}
.barcell{width:22%}
.track{background:#f1f3f5;border-radius:3px;height:10px;min-width:100px}
.bar{height:10px;border-radius:3px}
.bar.time{background:#4c6ef5}.bar.mem{background:#f59f00}
.stack{display:flex;height:22px;border-radius:6px;overflow:hidden;margin:4px 0 10px;font-size:12px;color:#fff;font-weight:600}
.stack div{display:flex;align-items:center;justify-content:center;white-space:nowrap;overflow:hidden;min-width:4px}
footer{color:var(--muted);font-size:12px;text-align:center;margin-top:18px}
"#;

/// Records script errors and `console.error` calls in `data-report-errors`; on `load`, sets
/// `data-report-ok="1"` when every image decoded, and counts the output cards that start
/// inside the first screenful (`data-outputs`, `data-outputs-in-view`).
const SCRIPT: &str = r#"
(function () {
  var errors = [];
  function fail(message) {
    errors.push(String(message));
    if (document.body) { document.body.setAttribute('data-report-errors', errors.join(' | ')); }
  }
  window.onerror = function (message, source, line) { fail(message + ' (' + line + ')'); };
  var consoleError = console.error;
  console.error = function () {
    fail(Array.prototype.join.call(arguments, ' '));
    if (consoleError) { consoleError.apply(console, arguments); }
  };
  window.addEventListener('load', function () {
    var broken = [];
    for (var i = 0; i < document.images.length; i++) {
      var img = document.images[i];
      if (!img.complete || img.naturalWidth === 0) { broken.push(img.alt || String(i)); }
    }
    var cards = document.querySelectorAll('article.output');
    var inView = 0;
    for (var k = 0; k < cards.length; k++) {
      if (cards[k].getBoundingClientRect().top < window.innerHeight) { inView++; }
    }
    document.body.dataset.outputs = String(cards.length);
    document.body.dataset.outputsInView = String(inView);
    if (errors.length) { document.body.setAttribute('data-report-errors', errors.join(' | ')); }
    if (broken.length) { fail('images that did not load: ' + broken.join(', ')); }
    else { document.body.dataset.reportOk = '1'; }
  });
})();
"#;

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn escapes_html() {
        assert_eq!(
            escape(r#"<a href="x">Tom & 'Jerry'</a>"#),
            "&lt;a href=&quot;x&quot;&gt;Tom &amp; &#39;Jerry&#39;&lt;/a&gt;"
        );
        assert_eq!(escape("plain → text"), "plain → text");
        assert_eq!(escape(""), "");
    }

    #[test]
    fn base64_matches_rfc_4648_vectors() {
        for (input, expected) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), expected, "{input:?}");
        }
        assert_eq!(base64(&[0xff, 0xfe, 0xfd, 0x00]), "//79AA==");
    }

    #[test]
    fn layout_columns_are_longest_paths() {
        // 0 → 1 → 3, 0 → 2 → 3, 0 → 3, 4 (isolated) → 5, 1 → 5
        let preds = vec![vec![], vec![0], vec![0], vec![1, 2, 0], vec![], vec![4, 1]];
        let places = layout(&preds);
        let columns: Vec<usize> = places.iter().map(|p| p.0).collect();
        assert_eq!(columns, vec![0, 1, 1, 2, 0, 2]);
        // Rows are distinct within a column.
        for c in 0..3 {
            let mut rows: Vec<usize> = places.iter().filter(|p| p.0 == c).map(|p| p.1).collect();
            rows.sort_unstable();
            assert_eq!(rows, (0..rows.len()).collect::<Vec<_>>());
        }
        // Barycentre order: node 3 (preds at rows 0, 1, 0) above node 5 (preds at rows 1, 0).
        assert!(places[3].1 < places[5].1);
        assert!(layout(&[]).is_empty());
    }

    #[test]
    fn downscale_averages_and_keeps_aspect() {
        let p = Pixels {
            width: 4,
            height: 2,
            channels: Channels::Gray,
            data: vec![0, 255, 10, 20, 255, 0, 30, 40],
        };
        let small = downscale(p.clone(), 2);
        assert_eq!((small.width, small.height), (2, 1));
        assert_eq!(small.data, vec![128, 25]);
        assert_eq!(downscale(p.clone(), 4), p);
    }

    #[test]
    fn f32_gray_is_stretched_and_noted() {
        let image = Image::from_f32(3, 1, Channels::Gray, vec![-1.0, 1.0, f32::INFINITY]).unwrap();
        let (pixels, note) = display_pixels(&image);
        assert_eq!(pixels.data, vec![0, 255, 0]);
        assert!(note.contains("-1 … 1"), "{note}");
        assert!(note.contains("1 non-finite"), "{note}");
    }

    #[test]
    fn thumbnails_render_meshes_and_points() {
        let mesh = Arc::new(ocellus_nodes::render::primitives::bumpy_icosphere(
            2, 0.05, 1,
        ));
        let thumb = render_mesh(&mesh).unwrap();
        assert_eq!((thumb.width, thumb.height), (THUMB_WIDTH, THUMB_HEIGHT));
        let background = thumb
            .data
            .chunks_exact(3)
            .filter(|p| *p == THUMB_BACKGROUND)
            .count();
        assert!(background < THUMB_WIDTH * THUMB_HEIGHT * 9 / 10);
        let points = splat_points(&mesh.positions, None, None).unwrap();
        assert!(points.data.chunks_exact(3).any(|p| p != THUMB_BACKGROUND));
        assert!(splat_points(&[], None, None).is_err());
    }
}
