//! `segment.graph_cut`: binary Markov-random-field segmentation solved exactly by a minimum
//! s–t cut, with the Boykov–Kolmogorov max-flow algorithm.
//!
//! [`MaxFlowGraph`] is the reusable solver (nodes, `add_edge`, `add_tweights`, `maxflow`,
//! `segment`); [`graph_cut`] builds the image energy on it; [`GraphCut`] is the operator.
//!
//! # Numerics
//!
//! Capacities are f64. The minimum cut is exact up to rounding of the capacity sums; the
//! returned flow equals the minimum energy (terminal capacities are reduced as in Kolmogorov's
//! implementation, and the part both terminals share is counted into the flow at once). The
//! solver is sequential and visits nodes in a fixed order, so results do not depend on the
//! thread count.

use std::collections::VecDeque;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, Value};

use super::background::to_levels;

/// Parent marker: not in a search tree.
const FREE: u32 = u32::MAX;
/// Parent marker: the parent is the tree's terminal.
const TERMINAL: u32 = u32::MAX - 1;
/// Parent marker: lost its parent during an augmentation.
const ORPHAN: u32 = u32::MAX - 2;
/// Largest node or arc count (arc indices must stay below the markers).
pub const MAX_ARCS: usize = (u32::MAX - 3) as usize;

/// Which side of the minimum cut a node is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Segment {
    /// Reachable from the source in the residual graph (or free: not separated from it).
    Source,
    /// Reaches the sink in the residual graph.
    Sink,
}

/// A directed graph with source/sink capacities whose maximum flow (and minimum cut) is found
/// by the Boykov–Kolmogorov algorithm ("An experimental comparison of min-cut/max-flow
/// algorithms for energy minimization in vision", IEEE TPAMI 26(9), 2004): two search trees
/// grown from the terminals, augmentation along the path where they meet, and adoption of the
/// orphans an augmentation leaves, with Kolmogorov's timestamp/distance heuristic.
#[derive(Debug, Clone, Default)]
pub struct MaxFlowGraph {
    /// Residual capacity source → node (> 0) or node → sink (< 0).
    tr_cap: Vec<f64>,
    /// First outgoing arc of each node (`FREE` = none).
    first: Vec<u32>,
    /// Arc heads; arcs come in pairs, the sister of arc `a` is `a ^ 1`.
    head: Vec<u32>,
    /// Next outgoing arc of the same tail.
    next: Vec<u32>,
    /// Residual capacities of the arcs.
    r_cap: Vec<f64>,
    /// Flow found so far (including the terminal capacity both terminals share).
    flow: f64,
    /// Tree state of each node after `maxflow`.
    parent: Vec<u32>,
    is_sink: Vec<bool>,
}

impl MaxFlowGraph {
    /// A graph of `n` nodes (numbered 0..n) and no edges.
    pub fn new(n: usize) -> MaxFlowGraph {
        MaxFlowGraph {
            tr_cap: vec![0.0; n],
            first: vec![FREE; n],
            head: Vec::new(),
            next: Vec::new(),
            r_cap: Vec::new(),
            flow: 0.0,
            parent: vec![FREE; n],
            is_sink: vec![false; n],
        }
    }

    /// Reserves room for `edges` more `add_edge` calls.
    pub fn reserve_edges(&mut self, edges: usize) {
        self.head.reserve(2 * edges);
        self.next.reserve(2 * edges);
        self.r_cap.reserve(2 * edges);
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.tr_cap.len()
    }

    /// Adds the edge `i → j` with capacity `cap` and `j → i` with `rev_cap` (both ≥ 0). Errors
    /// on a bad node, a negative or non-finite capacity, or too many arcs.
    pub fn add_edge(&mut self, i: usize, j: usize, cap: f64, rev_cap: f64) -> Result<(), String> {
        let n = self.node_count();
        if i >= n || j >= n {
            return Err(format!("edge {i}–{j} names a node outside 0..{n}"));
        }
        if !(cap >= 0.0 && rev_cap >= 0.0 && cap.is_finite() && rev_cap.is_finite()) {
            return Err(format!(
                "edge capacities must be finite and ≥ 0, got {cap} and {rev_cap}"
            ));
        }
        let a = self.head.len();
        if a + 2 > MAX_ARCS {
            return Err("too many edges".into());
        }
        self.head.push(j as u32);
        self.next.push(self.first[i]);
        self.r_cap.push(cap);
        self.first[i] = a as u32;
        self.head.push(i as u32);
        self.next.push(self.first[j]);
        self.r_cap.push(rev_cap);
        self.first[j] = (a + 1) as u32;
        Ok(())
    }

    /// Adds capacity `source_cap` from the source to node `i` and `sink_cap` from `i` to the
    /// sink (both ≥ 0). The common part min(source, sink) is flow already.
    pub fn add_tweights(&mut self, i: usize, source_cap: f64, sink_cap: f64) -> Result<(), String> {
        if i >= self.node_count() {
            return Err(format!("node {i} outside 0..{}", self.node_count()));
        }
        if !(source_cap >= 0.0 && sink_cap >= 0.0 && source_cap.is_finite() && sink_cap.is_finite())
        {
            return Err(format!(
                "terminal capacities must be finite and ≥ 0, got {source_cap} and {sink_cap}"
            ));
        }
        let (mut s, mut t) = (source_cap, sink_cap);
        let delta = self.tr_cap[i];
        if delta > 0.0 {
            s += delta;
        } else {
            t -= delta;
        }
        self.flow += s.min(t);
        self.tr_cap[i] = s - t;
        Ok(())
    }

    /// The flow so far (the maximum flow after [`maxflow`](Self::maxflow)).
    pub fn flow(&self) -> f64 {
        self.flow
    }

    /// The side of the minimum cut node `i` is on (valid after [`maxflow`](Self::maxflow)).
    pub fn segment(&self, i: usize) -> Segment {
        if self.parent[i] != FREE && self.is_sink[i] {
            Segment::Sink
        } else {
            Segment::Source
        }
    }

    /// Computes the maximum flow and returns its value. Residual capacities are kept, so
    /// capacities can be added and `maxflow` called again.
    pub fn maxflow(&mut self) -> f64 {
        let n = self.node_count();
        let mut state = Search {
            parent: vec![FREE; n],
            is_sink: vec![false; n],
            ts: vec![0; n],
            dist: vec![0; n],
            active: vec![false; n],
            queue: VecDeque::new(),
            orphans: VecDeque::new(),
            time: 0,
        };
        for i in 0..n {
            if self.tr_cap[i] != 0.0 {
                state.parent[i] = TERMINAL;
                state.is_sink[i] = self.tr_cap[i] < 0.0;
                state.dist[i] = 1;
                state.set_active(i);
            }
        }
        let mut current: Option<usize> = None;
        loop {
            let i = match current.take().filter(|&i| state.parent[i] != FREE) {
                Some(i) => i,
                None => match state.next_active() {
                    Some(i) => i,
                    None => break,
                },
            };
            let path = self.grow(&mut state, i);
            state.time += 1;
            if let Some(a) = path {
                current = Some(i);
                self.augment(&mut state, a);
                while let Some(o) = state.orphans.pop_front() {
                    self.adopt(&mut state, o as usize);
                }
            }
        }
        self.parent = state.parent;
        self.is_sink = state.is_sink;
        self.flow
    }

    /// Grows the tree of `i` by one layer; returns an arc from the source tree into the sink
    /// tree if the trees touch.
    fn grow(&self, st: &mut Search, i: usize) -> Option<usize> {
        let sink = st.is_sink[i];
        let mut a = self.first[i];
        while a != FREE {
            let arc = a as usize;
            let cap = if sink {
                self.r_cap[arc ^ 1]
            } else {
                self.r_cap[arc]
            };
            if cap > 0.0 {
                let j = self.head[arc] as usize;
                if st.parent[j] == FREE {
                    st.is_sink[j] = sink;
                    st.parent[j] = (arc ^ 1) as u32;
                    st.ts[j] = st.ts[i];
                    st.dist[j] = st.dist[i] + 1;
                    st.set_active(j);
                } else if st.is_sink[j] != sink {
                    return Some(if sink { arc ^ 1 } else { arc });
                } else if st.ts[j] <= st.ts[i] && st.dist[j] > st.dist[i] {
                    st.parent[j] = (arc ^ 1) as u32;
                    st.ts[j] = st.ts[i];
                    st.dist[j] = st.dist[i] + 1;
                }
            }
            a = self.next[arc];
        }
        None
    }

    /// Pushes the bottleneck capacity along the path through `middle` (source tree → sink
    /// tree) and collects the nodes whose parent link saturates as orphans.
    fn augment(&mut self, st: &mut Search, middle: usize) {
        let mut bottleneck = self.r_cap[middle];
        // Source side: the flow runs parent → child, on the sister of the parent arc.
        let mut i = self.head[middle ^ 1] as usize;
        loop {
            let pa = st.parent[i];
            if pa == TERMINAL {
                bottleneck = bottleneck.min(self.tr_cap[i]);
                break;
            }
            bottleneck = bottleneck.min(self.r_cap[pa as usize ^ 1]);
            i = self.head[pa as usize] as usize;
        }
        let mut i = self.head[middle] as usize;
        loop {
            let pa = st.parent[i];
            if pa == TERMINAL {
                bottleneck = bottleneck.min(-self.tr_cap[i]);
                break;
            }
            bottleneck = bottleneck.min(self.r_cap[pa as usize]);
            i = self.head[pa as usize] as usize;
        }
        self.r_cap[middle ^ 1] += bottleneck;
        self.r_cap[middle] -= bottleneck;
        let mut i = self.head[middle ^ 1] as usize;
        loop {
            let pa = st.parent[i];
            if pa == TERMINAL {
                self.tr_cap[i] -= bottleneck;
                if self.tr_cap[i] <= 0.0 {
                    self.tr_cap[i] = 0.0;
                    st.make_orphan(i);
                }
                break;
            }
            let pa = pa as usize;
            self.r_cap[pa] += bottleneck;
            self.r_cap[pa ^ 1] -= bottleneck;
            let up = self.head[pa] as usize;
            if self.r_cap[pa ^ 1] <= 0.0 {
                self.r_cap[pa ^ 1] = 0.0;
                st.make_orphan(i);
            }
            i = up;
        }
        let mut i = self.head[middle] as usize;
        loop {
            let pa = st.parent[i];
            if pa == TERMINAL {
                self.tr_cap[i] += bottleneck;
                if self.tr_cap[i] >= 0.0 {
                    self.tr_cap[i] = 0.0;
                    st.make_orphan(i);
                }
                break;
            }
            let pa = pa as usize;
            self.r_cap[pa ^ 1] += bottleneck;
            self.r_cap[pa] -= bottleneck;
            let up = self.head[pa] as usize;
            if self.r_cap[pa] <= 0.0 {
                self.r_cap[pa] = 0.0;
                st.make_orphan(i);
            }
            i = up;
        }
        self.flow += bottleneck;
    }

    /// Finds orphan `i` a new parent in its own tree with a path to the terminal, or frees it.
    fn adopt(&self, st: &mut Search, i: usize) {
        let sink = st.is_sink[i];
        let mut best: Option<(u32, u32)> = None;
        let mut a = self.first[i];
        while a != FREE {
            let arc = a as usize;
            let cap = if sink {
                self.r_cap[arc]
            } else {
                self.r_cap[arc ^ 1]
            };
            let j0 = self.head[arc] as usize;
            if cap > 0.0 && st.parent[j0] != FREE && st.is_sink[j0] == sink {
                // Walk up from j0 to the terminal (or an orphan), counting the distance.
                let mut j = j0;
                let mut d = 0u32;
                let valid = loop {
                    if st.ts[j] == st.time {
                        d += st.dist[j];
                        break true;
                    }
                    let p = st.parent[j];
                    d += 1;
                    if p == TERMINAL {
                        st.ts[j] = st.time;
                        st.dist[j] = 1;
                        break true;
                    }
                    if p == ORPHAN {
                        break false;
                    }
                    j = self.head[p as usize] as usize;
                };
                if valid {
                    if best.is_none_or(|(_, bd)| d < bd) {
                        best = Some((a, d));
                    }
                    let mut j = j0;
                    while st.ts[j] != st.time {
                        st.ts[j] = st.time;
                        st.dist[j] = d;
                        d -= 1;
                        j = self.head[st.parent[j] as usize] as usize;
                    }
                }
            }
            a = self.next[arc];
        }
        if let Some((arc, d)) = best {
            st.parent[i] = arc;
            st.ts[i] = st.time;
            st.dist[i] = d + 1;
            return;
        }
        // No parent: free the node; its children become orphans, neighbours that could
        // reach it become active again.
        let mut a = self.first[i];
        while a != FREE {
            let arc = a as usize;
            let j = self.head[arc] as usize;
            let pj = st.parent[j];
            if pj != FREE && st.is_sink[j] == sink {
                let cap = if sink {
                    self.r_cap[arc]
                } else {
                    self.r_cap[arc ^ 1]
                };
                if cap > 0.0 {
                    st.set_active(j);
                }
                if pj != TERMINAL && pj != ORPHAN && self.head[pj as usize] as usize == i {
                    st.make_orphan(j);
                }
            }
            a = self.next[arc];
        }
        st.parent[i] = FREE;
    }
}

/// Search state of one `maxflow` run.
struct Search {
    parent: Vec<u32>,
    is_sink: Vec<bool>,
    ts: Vec<u64>,
    dist: Vec<u32>,
    active: Vec<bool>,
    queue: VecDeque<u32>,
    orphans: VecDeque<u32>,
    time: u64,
}

impl Search {
    fn set_active(&mut self, i: usize) {
        if !self.active[i] {
            self.active[i] = true;
            self.queue.push_back(i as u32);
        }
    }

    fn next_active(&mut self) -> Option<usize> {
        while let Some(i) = self.queue.pop_front() {
            let i = i as usize;
            self.active[i] = false;
            if self.parent[i] != FREE {
                return Some(i);
            }
        }
        None
    }

    fn make_orphan(&mut self, i: usize) {
        self.parent[i] = ORPHAN;
        self.orphans.push_back(i as u32);
    }
}

params! {
    /// Parameters of `segment.graph_cut`.
    pub struct GraphCutParams {
        /// Foreground mean intensity per channel, on a 0–255 scale (u16 / 257, f32 × 255); one
        /// value for every channel or one per channel. Unused when a `probability` image is
        /// connected.
        foreground_mean: Vec<f64> = vec![255.0],
        /// Background mean intensity per channel, as `foreground_mean`.
        background_mean: Vec<f64> = vec![0.0],
        /// Noise standard deviation of the intensity model, gray levels (0–255 scale): the
        /// data cost is |I − mean|² / (2·noise_sigma²). Unused with `probability`.
        noise_sigma: f64 = 30.0,
        /// Smoothness weight λ (dimensionless, ≥ 0): cost of a label change between
        /// neighbours of equal intensity.
        lambda: f64 = 1.0,
        /// Contrast scale σ of the smoothness weight λ·exp(−|ΔI|²/(2σ²)), gray levels.
        sigma: f64 = 10.0,
        /// Neighbourhood: 4 or 8 (diagonal weights divided by √2).
        connectivity: u32 = 4,
    }
}

/// How the data term is given.
#[derive(Debug, Clone, PartialEq)]
pub enum DataTerm {
    /// Gaussian intensity models: means per channel (0–255 scale) and the noise σ.
    Means {
        /// Foreground mean per channel.
        foreground: Vec<f64>,
        /// Background mean per channel.
        background: Vec<f64>,
        /// Noise standard deviation, gray levels.
        noise_sigma: f64,
    },
    /// Per-pixel foreground probability in [0, 1] (row-major, one per pixel): costs −ln p and
    /// −ln(1 − p), p clamped to [1e−6, 1 − 1e−6].
    Probability(Vec<f64>),
}

/// Result of [`graph_cut`].
#[derive(Debug, Clone, PartialEq)]
pub struct GraphCutResult {
    /// Foreground flags, row-major.
    pub foreground: Vec<bool>,
    /// Energy of the labelling.
    pub energy: f64,
    /// Maximum flow (equals the minimum energy).
    pub flow: f64,
}

/// Binary segmentation of `image` minimizing
///
/// `E(x) = Σ_p D_p(x_p) + Σ_{p~q} w_pq·[x_p ≠ x_q]`, `w_pq = λ·exp(−|I_p − I_q|²/(2σ²)) / dist(p,q)`
///
/// over 4- or 8-neighbour pairs, exactly, with a minimum s–t cut (source side = foreground).
pub fn graph_cut(
    image: &Image,
    data: &DataTerm,
    lambda: f64,
    sigma: f64,
    connectivity: u32,
) -> Result<GraphCutResult, String> {
    let (w, h) = (image.width(), image.height());
    let c = image.channels().count();
    let n = w * h;
    let levels = to_levels(image);
    if levels.iter().any(|v| !v.is_finite()) {
        return Err("image contains NaN or infinite samples".into());
    }
    let (d_fg, d_bg) = data_costs(&levels, c, n, data)?;
    let mut g = MaxFlowGraph::new(n);
    let per_pixel = if connectivity == 8 { 4 } else { 2 };
    g.reserve_edges(per_pixel * n);
    let inv = 1.0 / (2.0 * sigma * sigma);
    let weight = |p: usize, q: usize, scale: f64| {
        let d2: f64 = levels[p * c..(p + 1) * c]
            .iter()
            .zip(&levels[q * c..(q + 1) * c])
            .map(|(&a, &b)| f64::from(a - b) * f64::from(a - b))
            .sum();
        lambda * scale * (-d2 * inv).exp()
    };
    let mut failure = None;
    if lambda > 0.0 {
        for_each_pair(w, h, connectivity, |p, q, scale| {
            let wpq = weight(p, q, scale);
            if let Err(e) = g.add_edge(p, q, wpq, wpq) {
                failure.get_or_insert(e);
            }
        });
    }
    if let Some(e) = failure {
        return Err(e);
    }
    for p in 0..n {
        // Cutting source → p puts p on the sink (background) side; p → sink keeps it
        // foreground.
        g.add_tweights(p, d_bg[p], d_fg[p])?;
    }
    let flow = g.maxflow();
    let foreground: Vec<bool> = (0..n).map(|p| g.segment(p) == Segment::Source).collect();
    drop(g);
    let mut energy: f64 = (0..n)
        .map(|p| if foreground[p] { d_fg[p] } else { d_bg[p] })
        .sum();
    if lambda > 0.0 {
        for_each_pair(w, h, connectivity, |p, q, scale| {
            if foreground[p] != foreground[q] {
                energy += weight(p, q, scale);
            }
        });
    }
    Ok(GraphCutResult {
        foreground,
        energy,
        flow,
    })
}

/// Per-pixel costs of the foreground and background labels.
fn data_costs(
    levels: &[f32],
    c: usize,
    n: usize,
    data: &DataTerm,
) -> Result<(Vec<f64>, Vec<f64>), String> {
    match data {
        DataTerm::Means {
            foreground,
            background,
            noise_sigma,
        } => {
            let expand = |m: &[f64], name: &str| -> Result<Vec<f64>, String> {
                match m.len() {
                    1 => Ok(vec![m[0]; c]),
                    k if k == c => Ok(m.to_vec()),
                    k => Err(format!(
                        "`{name}` has {k} values; the image has {c} channels (give 1 or {c})"
                    )),
                }
            };
            let fg = expand(foreground, "foreground_mean")?;
            let bg = expand(background, "background_mean")?;
            let inv = 1.0 / (2.0 * noise_sigma * noise_sigma);
            let cost = |mean: &[f64]| -> Vec<f64> {
                levels
                    .chunks_exact(c.max(1))
                    .map(|px| {
                        px.iter()
                            .zip(mean)
                            .map(|(&v, &m)| (f64::from(v) - m) * (f64::from(v) - m))
                            .sum::<f64>()
                            * inv
                    })
                    .collect()
            };
            Ok((cost(&fg), cost(&bg)))
        }
        DataTerm::Probability(p) => {
            if p.len() != n {
                return Err(format!("probability has {} pixels, the image {n}", p.len()));
            }
            let clamp = |v: f64| v.clamp(1e-6, 1.0 - 1e-6);
            Ok((
                p.iter().map(|&v| -clamp(v).ln()).collect(),
                p.iter().map(|&v| -(1.0 - clamp(v)).ln()).collect(),
            ))
        }
    }
}

/// Calls `f(p, q, distance scale)` for every neighbour pair of a `w × h` grid, once each, in
/// row-major order.
fn for_each_pair(w: usize, h: usize, connectivity: u32, mut f: impl FnMut(usize, usize, f64)) {
    let diag = std::f64::consts::FRAC_1_SQRT_2;
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if x + 1 < w {
                f(p, p + 1, 1.0);
            }
            if y + 1 < h {
                f(p, p + w, 1.0);
                if connectivity == 8 {
                    if x + 1 < w {
                        f(p, p + w + 1, diag);
                    }
                    if x > 0 {
                        f(p, p + w - 1, diag);
                    }
                }
            }
        }
    }
}

/// Graph-cut segmentation (`segment.graph_cut`). See [`graph_cut`].
#[derive(Debug, Clone, PartialEq)]
pub struct GraphCut {
    foreground_mean: Vec<f64>,
    background_mean: Vec<f64>,
    noise_sigma: f64,
    lambda: f64,
    sigma: f64,
    connectivity: u32,
}

impl Op for GraphCut {
    type Params = GraphCutParams;
    const ID: &'static str = "segment.graph_cut";
    const SUMMARY: &'static str =
        "Splits an image into foreground and background by an exact minimum graph cut.";
    const DOC: &'static str = r#"
Labels every pixel foreground or background by minimizing the binary MRF energy

    E(x) = Σ_p D_p(x_p) + Σ_{p~q} w_pq·[x_p ≠ x_q],   w_pq = λ·exp(−|I_p − I_q|²/(2σ²)) / dist(p, q)

exactly (Boykov & Jolly, "Interactive graph cuts for optimal boundary & region segmentation",
ICCV 2001): the energy is the capacity of an s–t cut in a graph with one node per pixel, and
its minimum cut is found with the Boykov–Kolmogorov max-flow algorithm (TPAMI 2004; search
trees from both terminals, augmentation, orphan adoption).

Intensities are on a 0–255 scale for every depth (u16 / 257, f32 × 255); gray, RGB and RGBA
images are accepted (all channels enter |ΔI|² and the data term). Data term D_p:
- from the `probability` input (gray, u8 as /255, u16 as /65535, f32 as is; the image's size):
  D_p(fg) = −ln p, D_p(bg) = −ln(1 − p), p clamped to [1e−6, 1 − 1e−6];
- otherwise Gaussian intensity models: D_p(l) = |I_p − mean_l|² / (2·`noise_sigma`²) with
  `foreground_mean` / `background_mean` (one value or one per channel).
Neighbours are 4- or 8-connected (`connectivity`); diagonal pairs are weighted 1/√2.

Outputs the u8 gray `mask` (255 foreground) and `metrics`: `energy` (of the returned
labelling), `flow` (the maximum flow; equal to the minimum energy up to rounding),
`foreground_pixels`. OpenCV has no direct equivalent (`cv::grabCut` iterates this cut with
colour GMMs).

Example:
    "cut": (op: "segment.graph_cut", inputs: { "image": "scan.image" }, params: (foreground_mean: [200.0], background_mean: [40.0], lambda: 2.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "image",
                PortType::Image,
                "Image to segment (gray/RGB/RGBA, u8/u16/f32).",
            ),
            PortSpec::new(
                "probability",
                PortType::Image,
                "Optional per-pixel foreground probability (gray, image's size); replaces the means.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mask",
                PortType::Image,
                "u8 gray mask: 255 foreground, 0 background.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "energy, flow, foreground_pixels.",
            ),
        ]
    }

    fn new(params: GraphCutParams) -> Result<Self, String> {
        let GraphCutParams {
            foreground_mean,
            background_mean,
            noise_sigma,
            lambda,
            sigma,
            connectivity,
        } = params;
        for (name, m) in [
            ("foreground_mean", &foreground_mean),
            ("background_mean", &background_mean),
        ] {
            if m.is_empty() || m.len() > 4 || m.iter().any(|v| !v.is_finite()) {
                return Err(format!(
                    "`{name}` must hold 1 to 4 finite values, got {m:?}"
                ));
            }
        }
        for (name, v) in [("noise_sigma", noise_sigma), ("sigma", sigma)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "`{name}` must be a positive finite number of gray levels, got {v}"
                ));
            }
        }
        if !(lambda.is_finite() && lambda >= 0.0) {
            return Err(format!("`lambda` must be finite and ≥ 0, got {lambda}"));
        }
        if connectivity != 4 && connectivity != 8 {
            return Err(format!("`connectivity` must be 4 or 8, got {connectivity}"));
        }
        Ok(GraphCut {
            foreground_mean,
            background_mean,
            noise_sigma,
            lambda,
            sigma,
            connectivity,
        })
    }
}

impl Operator for GraphCut {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let data = match inputs.get("probability") {
            Some(Value::Image(p)) => {
                if p.channels() != Channels::Gray
                    || p.width() != image.width()
                    || p.height() != image.height()
                {
                    return Err(OpError::input(
                        "probability",
                        format!(
                            "must be gray {}×{} (the image's size), got {}×{} {}",
                            image.width(),
                            image.height(),
                            p.width(),
                            p.height(),
                            p.channels().name()
                        ),
                    ));
                }
                let probs: Vec<f64> = match p.data() {
                    ocellus_engine::value::PixelData::U8(v) => {
                        v.iter().map(|&s| f64::from(s) / 255.0).collect()
                    }
                    ocellus_engine::value::PixelData::U16(v) => {
                        v.iter().map(|&s| f64::from(s) / 65535.0).collect()
                    }
                    ocellus_engine::value::PixelData::F32(v) => {
                        v.iter().map(|&s| f64::from(s)).collect()
                    }
                };
                if probs.iter().any(|v| v.is_nan()) {
                    return Err(OpError::input("probability", "contains NaN"));
                }
                DataTerm::Probability(probs)
            }
            Some(other) => {
                return Err(OpError::input(
                    "probability",
                    format!("expected Image, got {}", other.port_type()),
                ));
            }
            None => DataTerm::Means {
                foreground: self.foreground_mean.clone(),
                background: self.background_mean.clone(),
                noise_sigma: self.noise_sigma,
            },
        };
        let result = graph_cut(image, &data, self.lambda, self.sigma, self.connectivity)
            .map_err(|e| OpError::input("image", e))?;
        let mask: Vec<u8> = result
            .foreground
            .iter()
            .map(|&f| if f { 255 } else { 0 })
            .collect();
        let count = result.foreground.iter().filter(|&&f| f).count();
        let mask = Image::from_u8(image.width(), image.height(), Channels::Gray, mask)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let mut metrics = Metrics::new();
        metrics.insert("energy".into(), result.energy);
        metrics.insert("flow".into(), result.flow);
        metrics.insert("foreground_pixels".into(), count as f64);
        Ok(Outputs::new()
            .with("mask", Value::image(mask))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use proptest::prelude::*;

    /// Minimum cut by enumerating every partition (source side holds the bit-set nodes).
    fn brute_min_cut(n: usize, edges: &[(usize, usize, f64, f64)], t: &[(f64, f64)]) -> f64 {
        let mut best = f64::INFINITY;
        for set in 0u32..(1 << n) {
            let src = |i: usize| set >> i & 1 == 1;
            let mut cut = 0.0;
            for (i, &(s, k)) in t.iter().enumerate() {
                cut += if src(i) { k } else { s };
            }
            for &(i, j, c, r) in edges {
                if src(i) && !src(j) {
                    cut += c;
                }
                if src(j) && !src(i) {
                    cut += r;
                }
            }
            best = best.min(cut);
        }
        best
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        #[test]
        fn maxflow_equals_brute_force_min_cut(n in 1usize..9, seed in 0u64..1_000_000) {
            let r = randoms(seed, 200);
            let mut k = 0;
            let mut next = || { k += 1; r[k - 1] };
            let mut edges = Vec::new();
            for i in 0..n {
                for j in i + 1..n {
                    if next() < 0.5 {
                        let c = (next() * 10.0).floor();
                        let rc = (next() * 10.0).floor();
                        edges.push((i, j, c, rc));
                    }
                }
            }
            let t: Vec<(f64, f64)> = (0..n)
                .map(|_| ((next() * 12.0).floor(), (next() * 12.0).floor()))
                .collect();
            let mut g = MaxFlowGraph::new(n);
            for &(i, j, c, rc) in &edges {
                g.add_edge(i, j, c, rc).unwrap();
            }
            for (i, &(s, k)) in t.iter().enumerate() {
                g.add_tweights(i, s, k).unwrap();
            }
            let flow = g.maxflow();
            let expected = brute_min_cut(n, &edges, &t);
            prop_assert_eq!(flow, expected);
            // The returned partition is a minimum cut.
            let mut cut = 0.0;
            let src = |i: usize| g.segment(i) == Segment::Source;
            for (i, &(s, k)) in t.iter().enumerate() {
                cut += if src(i) { k } else { s };
            }
            for &(i, j, c, rc) in &edges {
                if src(i) && !src(j) { cut += c; }
                if src(j) && !src(i) { cut += rc; }
            }
            prop_assert_eq!(cut, expected);
        }

        #[test]
        fn graph_cut_energy_is_the_brute_force_minimum(
            w in 1usize..5,
            h in 1usize..5,
            seed in 0u64..1_000_000,
            lambda in 0.0f64..4.0,
            eight in any::<bool>(),
            use_prob in any::<bool>(),
        ) {
            let n = w * h;
            let r = randoms(seed, 2 * n);
            let img: Vec<u8> = r[..n].iter().map(|v| (v * 256.0) as u8).collect();
            let image = Image::from_u8(w, h, Channels::Gray, img).unwrap();
            let data = if use_prob {
                DataTerm::Probability(r[n..].to_vec())
            } else {
                DataTerm::Means { foreground: vec![180.0], background: vec![70.0], noise_sigma: 40.0 }
            };
            let conn = if eight { 8 } else { 4 };
            let res = graph_cut(&image, &data, lambda, 25.0, conn).unwrap();
            // Brute force over all labellings.
            let levels = to_levels(&image);
            let (dfg, dbg) = data_costs(&levels, 1, n, &data).unwrap();
            let mut pairs = Vec::new();
            for_each_pair(w, h, conn, |p, q, s| pairs.push((p, q, s)));
            let mut best = f64::INFINITY;
            for set in 0u32..(1 << n) {
                let fg = |i: usize| set >> i & 1 == 1;
                let mut e: f64 = (0..n).map(|p| if fg(p) { dfg[p] } else { dbg[p] }).sum();
                for &(p, q, s) in &pairs {
                    if fg(p) != fg(q) {
                        let d = f64::from(levels[p] - levels[q]);
                        e += lambda * s * (-d * d / (2.0 * 625.0)).exp();
                    }
                }
                best = best.min(e);
            }
            let tol = 1e-9 * (1.0 + best.abs());
            prop_assert!((res.energy - best).abs() <= tol, "energy {} vs {}", res.energy, best);
            prop_assert!((res.flow - best).abs() <= tol, "flow {} vs {}", res.flow, best);
        }
    }

    #[test]
    fn hand_computed_two_node_cut() {
        // s→0: 5, 0→t: 1, s→1: 2, 1→t: 6, edge 0→1: 3, 1→0: 0.
        // Cuts: {0,1} on source: 1+6 = 7; {} : 5+2 = 7; {0}: 1 + 2 + 3 = 6; {1}: 5+6+0 = 11.
        let mut g = MaxFlowGraph::new(2);
        g.add_tweights(0, 5.0, 1.0).unwrap();
        g.add_tweights(1, 2.0, 6.0).unwrap();
        g.add_edge(0, 1, 3.0, 0.0).unwrap();
        assert_eq!(g.maxflow(), 6.0);
        assert_eq!(g.segment(0), Segment::Source);
        assert_eq!(g.segment(1), Segment::Sink);
        assert!(g.add_edge(0, 2, 1.0, 1.0).is_err());
        assert!(g.add_edge(0, 1, -1.0, 1.0).is_err());
        assert!(g.add_tweights(0, f64::NAN, 1.0).is_err());
    }

    /// A noisy two-region image: a disc of level 170 on 80, with uniform noise ±`noise`.
    fn noisy_disc(w: usize, h: usize, noise: f64, seed: u64) -> (Image, Vec<bool>) {
        let r = randoms(seed, w * h);
        let (cx, cy, rad) = (w as f64 / 2.0, h as f64 / 2.0, w.min(h) as f64 / 3.0);
        let mut truth = Vec::new();
        let img = (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
                let inside = (x - cx).hypot(y - cy) < rad;
                truth.push(inside);
                let base = if inside { 170.0 } else { 80.0 };
                (base + noise * (2.0 * r[p] - 1.0))
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
            .collect();
        (Image::from_u8(w, h, Channels::Gray, img).unwrap(), truth)
    }

    #[test]
    fn noisy_two_region_image_is_segmented() {
        let (w, h) = (64, 48);
        let (image, truth) = noisy_disc(w, h, 70.0, 3);
        let data = DataTerm::Means {
            foreground: vec![170.0],
            background: vec![80.0],
            noise_sigma: 40.0,
        };
        // Per-pixel thresholding (λ = 0) makes many mistakes; the smoothed cut almost none.
        let errors = |f: &[bool]| f.iter().zip(&truth).filter(|(a, b)| a != b).count();
        let raw = graph_cut(&image, &data, 0.0, 10.0, 4).unwrap();
        for conn in [4, 8] {
            let res = graph_cut(&image, &data, 2.0, 1000.0, conn).unwrap();
            let e = errors(&res.foreground);
            assert!(
                e * 10 < errors(&raw.foreground) && e < w * h / 50,
                "{conn}: {e} errors vs {} unsmoothed",
                errors(&raw.foreground)
            );
            assert!((res.energy - res.flow).abs() < 1e-9 * res.energy);
        }
    }

    #[test]
    fn rgb_and_tiny_images_work() {
        let image = Image::from_u8(2, 1, Channels::Rgb, vec![250, 0, 0, 0, 0, 250]).unwrap();
        let data = DataTerm::Means {
            foreground: vec![255.0, 0.0, 0.0],
            background: vec![0.0, 0.0, 255.0],
            noise_sigma: 30.0,
        };
        let res = graph_cut(&image, &data, 0.5, 10.0, 8).unwrap();
        assert_eq!(res.foreground, [true, false]);
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        let res = graph_cut(&empty, &data, 1.0, 10.0, 4);
        assert!(res.is_err()); // 3 means for a gray image
        let gray_data = DataTerm::Means {
            foreground: vec![200.0],
            background: vec![0.0],
            noise_sigma: 30.0,
        };
        let res = graph_cut(&empty, &gray_data, 1.0, 10.0, 4).unwrap();
        assert!(res.foreground.is_empty() && res.energy == 0.0);
        let one = Image::from_f32(1, 1, Channels::Gray, vec![0.9]).unwrap();
        let res = graph_cut(&one, &gray_data, 1.0, 10.0, 4).unwrap();
        assert_eq!(res.foreground, [true]);
    }

    fn run_op(params: GraphCutParams, values: [Option<Value>; 2]) -> Result<Outputs, OpError> {
        let op = GraphCut::new(params).map_err(OpError::failed)?;
        let specs = GraphCut::inputs();
        let ctx = RunContext {
            node: "cut".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    #[test]
    fn operator_with_probability_input() {
        let (w, h) = (16, 12);
        let (image, truth) = noisy_disc(w, h, 0.0, 1);
        let prob: Vec<f32> = truth.iter().map(|&t| if t { 0.8 } else { 0.3 }).collect();
        let prob = Image::from_f32(w, h, Channels::Gray, prob).unwrap();
        let mut out = run_op(
            GraphCutParams::default(),
            [Some(Value::image(image.clone())), Some(Value::image(prob))],
        )
        .unwrap();
        let Some(Value::Image(mask)) = out.take("mask") else {
            panic!("no mask");
        };
        let expected: Vec<u8> = truth.iter().map(|&t| if t { 255 } else { 0 }).collect();
        assert_eq!(mask.as_u8().unwrap(), expected);
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("no metrics");
        };
        assert!((m["energy"] - m["flow"]).abs() < 1e-9);
        assert_eq!(
            m["foreground_pixels"] as usize,
            truth.iter().filter(|&&t| t).count()
        );
        let bad = Image::from_f32(3, 3, Channels::Gray, vec![0.5; 9]).unwrap();
        assert!(
            run_op(
                GraphCutParams::default(),
                [Some(Value::image(image)), Some(Value::image(bad))]
            )
            .is_err()
        );
        let p = GraphCutParams {
            connectivity: 6,
            ..GraphCutParams::default()
        };
        assert!(GraphCut::new(p).is_err());
        let p = GraphCutParams {
            lambda: f64::NAN,
            ..GraphCutParams::default()
        };
        assert!(GraphCut::new(p).is_err());
    }
}
