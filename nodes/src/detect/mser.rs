//! `detect.mser`: Maximally Stable Extremal Regions.
//!
//! [`mser`] builds the component tree of the image's level sets with Matas's union-find over
//! pixels sorted by intensity (counting sort, 4-connectivity), measures every extremal region's
//! variation and keeps the local minima along each branch that pass the area, variation and
//! diversity filters. [`Mser`] is the thin operator around it.
//!
//! # The tree
//!
//! Pixels are added from darkest to brightest (dark-on-bright regions; the image is inverted for
//! bright-on-dark). Each pixel is a node; when it joins a component whose root has a lower level,
//! that root becomes its child; two roots of the same level are joined by union by rank. A node
//! whose parent lies at a higher level (or that is the final root) is an *extremal region*:
//! its subtree is the connected component of pixels `≤ level` containing it. Areas, coordinate
//! sums and bounding boxes are accumulated when a node is attached to its parent, so each
//! extremal region's statistics are exact integers. The algorithm is sequential (it is
//! inherently so) and therefore deterministic.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Value};
use ocellus_engine::{param_enum, params};

use super::gray::gray_u8;

/// Columns of the `regions` matrix.
pub const REGION_COLUMNS: usize = 8;

/// Largest label that an f32 holds exactly.
const MAX_LABEL: usize = 1 << 24;

/// No node.
const NONE: u32 = u32::MAX;

param_enum! {
    /// Which extremal regions to look for.
    pub enum Polarity {
        /// Dark regions on a brighter surround (minimal regions, thresholds from dark up).
        Dark = "dark",
        /// Bright regions on a darker surround (maximal regions).
        Bright = "bright",
        /// Both; dark regions come first in the output.
        Both = "both",
    }
}

params! {
    /// Parameters of `detect.mser`.
    pub struct MserParams {
        /// Intensity step Δ (gray levels, 0–255 scale) over which a region's growth is
        /// measured: variation = (area at level + Δ − area) / area. Default 5 (OpenCV's).
        delta: u32 = 5 => [min = 1, max = 255],
        /// Smallest region kept, in pixels. Default 60 (OpenCV's).
        min_area: u32 = 60 => [min = 1],
        /// Largest region kept, in pixels. Default 14400 (OpenCV's).
        max_area: u32 = 14400 => [min = 1],
        /// Largest variation kept (dimensionless). Default 0.25 (OpenCV's).
        max_variation: f64 = 0.25 => [min = 0.0],
        /// Two nested kept regions whose areas differ by less than this fraction of the larger
        /// are duplicates: only the one with the lower variation stays. 0 keeps all. Default
        /// 0.2 (OpenCV's).
        min_diversity: f64 = 0.2 => [min = 0.0, max = 1.0],
        /// "dark" (dark regions on a bright surround), "bright", or "both" (default).
        polarity: Polarity = Polarity::Both,
    }
}

/// Settings of [`mser`], validated by [`Mser::new`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MserSettings {
    /// See [`MserParams::delta`].
    pub delta: u32,
    /// See [`MserParams::min_area`].
    pub min_area: u32,
    /// See [`MserParams::max_area`].
    pub max_area: u32,
    /// See [`MserParams::max_variation`].
    pub max_variation: f64,
    /// See [`MserParams::min_diversity`].
    pub min_diversity: f64,
    /// See [`MserParams::polarity`].
    pub polarity: Polarity,
}

impl Default for MserSettings {
    fn default() -> Self {
        let p = MserParams::default();
        MserSettings {
            delta: p.delta,
            min_area: p.min_area,
            max_area: p.max_area,
            max_variation: p.max_variation,
            min_diversity: p.min_diversity,
            polarity: p.polarity,
        }
    }
}

/// One kept region.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    /// Centroid column (pixel centres at integers).
    pub cx: f64,
    /// Centroid row.
    pub cy: f64,
    /// Pixels.
    pub area: u32,
    /// Bounding box: left column, top row, width, height.
    pub bbox: [u32; 4],
    /// Variation (lower is more stable).
    pub variation: f64,
    /// Threshold level of the region in the 0–255 scale of the searched polarity (for bright
    /// regions, in the inverted image).
    pub level: u8,
    /// True for a bright-on-dark region.
    pub bright: bool,
}

/// The kept regions and a label image: `labels[p]` is `1 +` the index in `regions` of the
/// smallest region containing pixel `p`, or 0.
#[derive(Debug, Clone, PartialEq)]
pub struct MserResult {
    /// Regions, dark ones first, each polarity in increasing level then node order.
    pub regions: Vec<Region>,
    /// Per-pixel labels, `width × height`.
    pub labels: Vec<u32>,
}

/// Per-node accumulators of the component tree (one node per pixel).
struct Tree {
    parent: Vec<u32>,
    /// Union-find links towards the current root (path-compressed).
    uf: Vec<u32>,
    rank: Vec<u8>,
    area: Vec<u32>,
    sum_x: Vec<u64>,
    sum_y: Vec<u64>,
    /// min x, min y, max x, max y.
    bbox: Vec<[u32; 4]>,
}

impl Tree {
    fn find(&mut self, mut p: u32) -> u32 {
        let mut root = p;
        while self.uf[root as usize] != root {
            root = self.uf[root as usize];
        }
        while self.uf[p as usize] != root {
            let next = self.uf[p as usize];
            self.uf[p as usize] = root;
            p = next;
        }
        root
    }

    /// Makes `child` a child of `parent` and adds its statistics.
    fn attach(&mut self, child: u32, parent: u32) {
        let (c, p) = (child as usize, parent as usize);
        self.parent[c] = parent;
        self.uf[c] = parent;
        self.area[p] += self.area[c];
        self.sum_x[p] += self.sum_x[c];
        self.sum_y[p] += self.sum_y[c];
        let (a, b) = (self.bbox[c], self.bbox[p]);
        self.bbox[p] = [
            a[0].min(b[0]),
            a[1].min(b[1]),
            a[2].max(b[2]),
            a[3].max(b[3]),
        ];
    }
}

/// Builds the component tree of `gray` (dark regions first).
fn build_tree(gray: &[u8], width: usize, height: usize, order: &[u32]) -> Tree {
    let n = width * height;
    let mut tree = Tree {
        parent: vec![NONE; n],
        uf: vec![NONE; n],
        rank: vec![0; n],
        area: vec![0; n],
        sum_x: vec![0; n],
        sum_y: vec![0; n],
        bbox: vec![[0; 4]; n],
    };
    for &p in order {
        let pi = p as usize;
        let (x, y) = (pi % width, pi / width);
        tree.uf[pi] = p;
        tree.area[pi] = 1;
        tree.sum_x[pi] = x as u64;
        tree.sum_y[pi] = y as u64;
        tree.bbox[pi] = [x as u32, y as u32, x as u32, y as u32];
        let level = gray[pi];
        let mut neighbours = [NONE; 4];
        if x > 0 {
            neighbours[0] = p - 1;
        }
        if x + 1 < width {
            neighbours[1] = p + 1;
        }
        if y > 0 {
            neighbours[2] = p - width as u32;
        }
        if y + 1 < height {
            neighbours[3] = p + width as u32;
        }
        // Root of the pixel's component, kept up to date across the unions below.
        let mut ir = p;
        for q in neighbours {
            if q == NONE || tree.uf[q as usize] == NONE {
                continue;
            }
            let nr = tree.find(q);
            if nr == ir {
                continue;
            }
            if gray[nr as usize] < level {
                tree.attach(nr, ir);
            } else {
                // Same level: union by rank.
                let (rn, ri) = (tree.rank[nr as usize], tree.rank[ir as usize]);
                if rn > ri {
                    tree.attach(ir, nr);
                    ir = nr;
                } else {
                    if rn == ri {
                        tree.rank[ir as usize] = ri.saturating_add(1);
                    }
                    tree.attach(nr, ir);
                }
            }
        }
    }
    tree
}

/// Pixel indices sorted by increasing value, raster order within a value (counting sort).
fn sorted_pixels(gray: &[u8]) -> Vec<u32> {
    let mut start = [0usize; 257];
    for &v in gray {
        start[v as usize + 1] += 1;
    }
    for i in 1..257 {
        start[i] += start[i - 1];
    }
    let mut order = vec![0u32; gray.len()];
    for (i, &v) in gray.iter().enumerate() {
        order[start[v as usize]] = i as u32;
        start[v as usize] += 1;
    }
    order
}

/// Regions of one polarity (dark regions of `gray`) and, for every pixel, the index (into the
/// returned vector) of the smallest kept region containing it.
fn mser_dark(
    gray: &[u8],
    width: usize,
    height: usize,
    s: &MserSettings,
    bright: bool,
) -> (Vec<Region>, Vec<u32>) {
    let n = width * height;
    let order = sorted_pixels(gray);
    let tree = build_tree(gray, width, height, &order);
    let level = |p: u32| gray[p as usize];

    // Extremal regions, in sorted-pixel order (so increasing level: children before parents).
    let is_er = |p: u32| {
        let q = tree.parent[p as usize];
        q == NONE || level(q) > level(p)
    };
    let ers: Vec<u32> = order.iter().copied().filter(|&p| is_er(p)).collect();
    // ER index of each ER node, and the ER owning each node (climbing same-level links).
    let mut er_index = vec![NONE; n];
    for (i, &p) in ers.iter().enumerate() {
        er_index[p as usize] = i as u32;
    }
    let mut owner = vec![NONE; n];
    let mut path = Vec::new();
    for &p in &order {
        let mut q = p;
        while owner[q as usize] == NONE && er_index[q as usize] == NONE {
            path.push(q);
            q = tree.parent[q as usize];
        }
        let o = if er_index[q as usize] != NONE {
            er_index[q as usize]
        } else {
            owner[q as usize]
        };
        owner[q as usize] = o;
        for r in path.drain(..) {
            owner[r as usize] = o;
        }
    }
    // ER parent of each ER (NONE for the root).
    let er_parent: Vec<u32> = ers
        .iter()
        .map(|&p| {
            let q = tree.parent[p as usize];
            if q == NONE { NONE } else { owner[q as usize] }
        })
        .collect();
    let er_level: Vec<u8> = ers.iter().map(|&p| level(p)).collect();
    let er_area: Vec<u32> = ers.iter().map(|&p| tree.area[p as usize]).collect();

    // Variation: growth over Δ levels; the root's is +∞ (nothing above to compare with).
    let variation: Vec<f64> = (0..ers.len())
        .map(|i| {
            if er_parent[i] == NONE {
                return f64::INFINITY;
            }
            let top = u32::from(er_level[i]) + s.delta;
            let mut j = i;
            while er_parent[j] != NONE && u32::from(er_level[er_parent[j] as usize]) <= top {
                j = er_parent[j] as usize;
            }
            f64::from(er_area[j] - er_area[i]) / f64::from(er_area[i])
        })
        .collect();

    // Local minima along branches: unstable if above the parent's or any child's variation.
    let mut stable: Vec<bool> = variation.iter().map(|v| v.is_finite()).collect();
    for i in 0..ers.len() {
        let j = er_parent[i];
        if j == NONE {
            continue;
        }
        let j = j as usize;
        if variation[i] > variation[j] {
            stable[i] = false;
        } else if variation[j] > variation[i] {
            stable[j] = false;
        }
    }
    for i in 0..ers.len() {
        let a = er_area[i];
        if a < s.min_area || a > s.max_area || variation[i] > s.max_variation {
            stable[i] = false;
        }
    }
    // Diversity: between a kept region and its nearest kept ancestor of similar area, keep the
    // one with the lower variation (the larger on a tie).
    if s.min_diversity > 0.0 {
        for i in 0..ers.len() {
            if !stable[i] {
                continue;
            }
            let mut j = er_parent[i];
            while j != NONE {
                let ju = j as usize;
                let similar =
                    f64::from(er_area[ju] - er_area[i]) < s.min_diversity * f64::from(er_area[ju]);
                if !similar {
                    break;
                }
                if stable[ju] {
                    if variation[i] < variation[ju] {
                        stable[ju] = false;
                    } else {
                        stable[i] = false;
                    }
                    break;
                }
                j = er_parent[ju];
            }
        }
    }

    let mut regions = Vec::new();
    let mut region_of_er = vec![NONE; ers.len()];
    for (i, &p) in ers.iter().enumerate() {
        if !stable[i] {
            continue;
        }
        let pi = p as usize;
        let a = tree.area[pi];
        let b = tree.bbox[pi];
        region_of_er[i] = regions.len() as u32;
        regions.push(Region {
            cx: tree.sum_x[pi] as f64 / f64::from(a),
            cy: tree.sum_y[pi] as f64 / f64::from(a),
            area: a,
            bbox: [b[0], b[1], b[2] - b[0] + 1, b[3] - b[1] + 1],
            variation: variation[i],
            level: er_level[i],
            bright,
        });
    }
    // Innermost kept region of each ER, then of each pixel.
    let mut inner = vec![NONE; ers.len()];
    for i in (0..ers.len()).rev() {
        inner[i] = if region_of_er[i] != NONE {
            region_of_er[i]
        } else if er_parent[i] != NONE {
            inner[er_parent[i] as usize]
        } else {
            NONE
        };
    }
    let labels = owner.iter().map(|&o| inner[o as usize]).collect();
    (regions, labels)
}

/// MSER of a gray 8-bit image (`width × height`, row-major). See the module docs and
/// [`Mser::DOC`](Op::DOC). Empty images give no regions.
///
/// # Panics
///
/// If `gray.len() != width × height` (a precondition the operator checks).
pub fn mser(gray: &[u8], width: usize, height: usize, s: &MserSettings) -> MserResult {
    assert_eq!(gray.len(), width * height, "gray buffer size");
    let n = gray.len();
    let mut regions = Vec::new();
    let mut labels = vec![0u32; n];
    if n == 0 {
        return MserResult { regions, labels };
    }
    let mut run = |img: &[u8], bright: bool| {
        let (rs, ls) = mser_dark(img, width, height, s, bright);
        let base = regions.len() as u32;
        for (out, &l) in labels.iter_mut().zip(&ls) {
            if l == NONE {
                continue;
            }
            let candidate = base + l + 1;
            // Smallest region wins where the polarities overlap.
            if *out == 0 || rs[l as usize].area < regions_area(&regions, *out) {
                *out = candidate;
            }
        }
        regions.extend(rs);
    };
    fn regions_area(regions: &[Region], label: u32) -> u32 {
        regions[label as usize - 1].area
    }
    if matches!(s.polarity, Polarity::Dark | Polarity::Both) {
        run(gray, false);
    }
    if matches!(s.polarity, Polarity::Bright | Polarity::Both) {
        let inverted: Vec<u8> = gray.iter().map(|&v| 255 - v).collect();
        run(&inverted, true);
    }
    MserResult { regions, labels }
}

/// MSER detector (`detect.mser`). See [`mser`].
#[derive(Debug, Clone, PartialEq)]
pub struct Mser {
    settings: MserSettings,
}

impl Op for Mser {
    type Params = MserParams;
    const ID: &'static str = "detect.mser";
    const SUMMARY: &'static str = "Maximally Stable Extremal Regions: blobs whose area barely changes over a range of thresholds.";
    const DOC: &'static str = r#"
Finds Maximally Stable Extremal Regions (Matas et al.). An extremal region is a connected
component (4-connectivity) of the pixels at or below a threshold t (dark regions; at or above for
bright ones). Its variation is (area at t + delta − area at t) / area at t, the one-sided measure
of VLFeat. A region is maximally stable when its variation is not above its parent's nor any
child's in the component tree; kept regions must also satisfy min_area ≤ area ≤ max_area and
variation ≤ max_variation. Of two nested kept regions whose areas differ by less than
min_diversity × the larger area, only the one with the lower variation stays.

Method: pixels are sorted by intensity (counting sort) and added in order; union-find with
path compression builds the component tree (one node per pixel), accumulating area, coordinate
sums and bounding boxes exactly. Bright regions are the dark regions of the inverted image.
Sequential and deterministic.

Input: any image; colour is reduced to BT.601 luma (OpenCV's fixed point), u16 to v/257 and f32
to clamp(v,0,1)·255, rounded, so delta is in 0–255 gray levels for every depth.

Outputs:
- `regions`: Matrix, one row per region, columns [centroid x, centroid y, area (px), bbox x,
  bbox y, bbox width, bbox height, stability]. Stability is the variation (lower = more stable).
  Dark regions come first, each polarity by increasing threshold level.
- `labels`: gray f32 image, same size: 1 + the row of the smallest kept region containing the
  pixel, 0 elsewhere.

Differences from OpenCV's `cv::MSER`: OpenCV uses Nistér–Stewénius' linear-time variant and a
two-sided variation (area(t+Δ) − area(t−Δ)) / area(t), and handles colour images with MSCR; the
gray regions found on clean images agree, scores and borderline picks can differ.

References: J. Matas, O. Chum, M. Urban, T. Pajdla, "Robust wide-baseline stereo from maximally
stable extremal regions", BMVC 2002; A. Vedaldi, VLFeat `mser.c` (one-sided variation).

Example (a node of a graph):
    "blobs": (op: "detect.mser", inputs: { "image": "gray.image" },
              params: (delta: 5, min_area: 60, max_area: 14400, polarity: "both")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "image, any format (colour reduced to luma, depth scaled to 0–255)",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "regions",
                PortType::Matrix,
                "one row per region: cx, cy, area, bbox x, y, w, h, stability (variation)",
            ),
            PortSpec::new(
                "labels",
                PortType::Image,
                "gray f32: 1 + row of the smallest region holding the pixel, 0 = none",
            ),
        ]
    }

    fn new(p: MserParams) -> Result<Self, String> {
        if p.delta == 0 || p.delta > 255 {
            return Err(format!("`delta` must be in 1..=255, got {}", p.delta));
        }
        if p.min_area == 0 || p.min_area > p.max_area {
            return Err(format!(
                "need 1 ≤ `min_area` ≤ `max_area`, got {} and {}",
                p.min_area, p.max_area
            ));
        }
        if !p.max_variation.is_finite() || p.max_variation < 0.0 {
            return Err(format!(
                "`max_variation` must be finite and ≥ 0, got {}",
                p.max_variation
            ));
        }
        if !(0.0..=1.0).contains(&p.min_diversity) {
            return Err(format!(
                "`min_diversity` must be in [0, 1], got {}",
                p.min_diversity
            ));
        }
        Ok(Mser {
            settings: MserSettings {
                delta: p.delta,
                min_area: p.min_area,
                max_area: p.max_area,
                max_variation: p.max_variation,
                min_diversity: p.min_diversity,
                polarity: p.polarity,
            },
        })
    }
}

impl Operator for Mser {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (w, h) = (image.width(), image.height());
        if w * h >= u32::MAX as usize {
            return Err(OpError::input("image", "detect.mser: image too large"));
        }
        let gray = gray_u8(image);
        let result = mser(&gray, w, h, &self.settings);
        if result.regions.len() >= MAX_LABEL {
            return Err(OpError::failed(format!(
                "detect.mser: {} regions exceed the 2^24 labels an f32 image holds exactly",
                result.regions.len()
            )));
        }
        let mut data = Vec::with_capacity(result.regions.len() * REGION_COLUMNS);
        for r in &result.regions {
            data.extend_from_slice(&[
                r.cx,
                r.cy,
                f64::from(r.area),
                f64::from(r.bbox[0]),
                f64::from(r.bbox[1]),
                f64::from(r.bbox[2]),
                f64::from(r.bbox[3]),
                r.variation,
            ]);
        }
        let matrix = Matrix::new(result.regions.len(), REGION_COLUMNS, data)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let labels = Image::from_f32(
            w,
            h,
            Channels::Gray,
            result.labels.iter().map(|&l| l as f32).collect(),
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("regions", Value::Matrix(std::sync::Arc::new(matrix)))
            .with("labels", Value::image(labels)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::params::{ParamMap, ParamValue, Params};
    use proptest::prelude::*;

    fn run_op(params: ParamMap, image: Image) -> Result<Outputs, OpError> {
        let op = Mser::new(MserParams::from_map(&params).map_err(OpError::failed)?)
            .map_err(OpError::failed)?;
        let specs = Mser::inputs();
        let values = [Some(Value::image(image))];
        let ctx = RunContext {
            node: "mser".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    /// Background 128 with rectangles and discs `(x0, y0, w, h, value)` and discs.
    /// (centroid x, centroid y, area, bright) of a drawn blob.
    type Blob = (f64, f64, u32, bool);

    fn blobs(w: usize, h: usize, noise: u8) -> (Vec<u8>, Vec<Blob>) {
        let mut img = vec![128u8; w * h];
        let mut truth = Vec::new();
        // Rectangles: x0, y0, w, h, value.
        let rects = [
            (10, 10, 12, 9, 40u8),
            (40, 12, 20, 20, 220),
            (75, 8, 8, 30, 20),
            (10, 50, 30, 25, 200),
        ];
        for &(x0, y0, rw, rh, v) in &rects {
            for y in y0..y0 + rh {
                img[y * w + x0..y * w + x0 + rw].fill(v);
            }
            truth.push((
                x0 as f64 + (rw as f64 - 1.0) / 2.0,
                y0 as f64 + (rh as f64 - 1.0) / 2.0,
                (rw * rh) as u32,
                v > 128,
            ));
        }
        // A disc of radius 9 at (70, 65), dark.
        let (cx, cy, r) = (70i64, 65i64, 9i64);
        let mut area = 0;
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                if (x - cx).pow(2) + (y - cy).pow(2) <= r * r {
                    img[y as usize * w + x as usize] = 60;
                    area += 1;
                }
            }
        }
        truth.push((cx as f64, cy as f64, area, false));
        if noise > 0 {
            let mut state = 0x2545_f491_4f6c_dd1du64;
            for v in &mut img {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let d = (state % (2 * u64::from(noise) + 1)) as i32 - i32::from(noise);
                *v = (i32::from(*v) + d).clamp(0, 255) as u8;
            }
        }
        (img, truth)
    }

    fn settings() -> MserSettings {
        // The background minus the blobs of the other polarity is a (large) MSER too: keep
        // it out with `max_area`.
        MserSettings {
            min_area: 30,
            max_area: 5000,
            ..MserSettings::default()
        }
    }

    #[test]
    fn flat_blobs_found_once_with_exact_area() {
        let (w, h) = (100, 90);
        let (img, truth) = blobs(w, h, 0);
        let res = mser(&img, w, h, &settings());
        assert_eq!(res.regions.len(), truth.len(), "{:?}", res.regions);
        for &(cx, cy, area, bright) in &truth {
            let hits: Vec<&Region> = res
                .regions
                .iter()
                .filter(|r| (r.cx - cx).abs() < 0.01 && (r.cy - cy).abs() < 0.01)
                .collect();
            assert_eq!(hits.len(), 1, "blob at ({cx}, {cy})");
            assert_eq!(hits[0].area, area);
            assert_eq!(hits[0].bright, bright);
            assert_eq!(hits[0].variation, 0.0);
        }
        // Labels cover exactly the blobs.
        let labelled = res.labels.iter().filter(|&&l| l != 0).count() as u32;
        assert_eq!(labelled, truth.iter().map(|t| t.2).sum::<u32>());
        for (i, r) in res.regions.iter().enumerate() {
            let count = res.labels.iter().filter(|&&l| l == i as u32 + 1).count() as u32;
            assert_eq!(count, r.area);
            let [bx, by, bw, bh] = r.bbox;
            let p = (by + bh / 2) as usize * w + (bx + bw / 2) as usize;
            assert_eq!(res.labels[p], i as u32 + 1);
        }
    }

    #[test]
    fn noisy_blobs_found_once_with_exact_area() {
        let (w, h) = (100, 90);
        let (img, truth) = blobs(w, h, 3);
        let res = mser(&img, w, h, &settings());
        for &(cx, cy, area, bright) in &truth {
            let hits: Vec<&Region> = res
                .regions
                .iter()
                .filter(|r| {
                    r.bright == bright && (r.cx - cx).abs() < 0.5 && (r.cy - cy).abs() < 0.5
                })
                .collect();
            assert_eq!(hits.len(), 1, "blob at ({cx}, {cy}): {hits:?}");
            assert_eq!(hits[0].area, area);
        }
    }

    #[test]
    fn polarity_selects() {
        let (w, h) = (100, 90);
        let (img, truth) = blobs(w, h, 0);
        for (pol, want) in [(Polarity::Dark, false), (Polarity::Bright, true)] {
            let s = MserSettings {
                polarity: pol,
                ..settings()
            };
            let res = mser(&img, w, h, &s);
            assert_eq!(
                res.regions.len(),
                truth.iter().filter(|t| t.3 == want).count()
            );
            assert!(res.regions.iter().all(|r| r.bright == want));
        }
    }

    #[test]
    fn area_limits_and_nesting() {
        // A 30×30 dark square (value 60) holding a darker 10×10 (value 10), on 200.
        let (w, h) = (50, 50);
        let mut img = vec![200u8; w * h];
        for y in 10..40 {
            img[y * w + 10..y * w + 40].fill(60);
        }
        for y in 20..30 {
            img[y * w + 20..y * w + 30].fill(10);
        }
        let s = MserSettings {
            min_area: 10,
            polarity: Polarity::Dark,
            ..MserSettings::default()
        };
        let res = mser(&img, w, h, &s);
        let areas: Vec<u32> = res.regions.iter().map(|r| r.area).collect();
        assert_eq!(areas, vec![100, 900]);
        // Inner pixels belong to the smaller region.
        assert_eq!(res.labels[25 * w + 25], 1);
        assert_eq!(res.labels[12 * w + 12], 2);
        assert_eq!(res.labels[0], 0);
        let s = MserSettings { max_area: 500, ..s };
        assert_eq!(mser(&img, w, h, &s).regions.len(), 1);
        let s = MserSettings {
            min_area: 101,
            max_area: 14400,
            ..s
        };
        assert_eq!(mser(&img, w, h, &s).regions.len(), 1);
        // Diversity 1 keeps only one of two nested regions.
        let s = MserSettings {
            min_area: 10,
            min_diversity: 1.0,
            ..s
        };
        assert_eq!(mser(&img, w, h, &s).regions.len(), 1);
    }

    #[test]
    fn extremes() {
        let s = MserSettings::default();
        let r = mser(&[], 0, 0, &s);
        assert!(r.regions.is_empty() && r.labels.is_empty());
        let r = mser(&[7], 1, 1, &s);
        assert!(r.regions.is_empty());
        let r = mser(&vec![100; 400], 20, 20, &MserSettings { min_area: 1, ..s });
        assert!(
            r.regions.is_empty(),
            "a constant image is one root, never kept"
        );
    }

    #[test]
    fn operator_outputs_and_formats() {
        let (w, h) = (100, 90);
        let (img, truth) = blobs(w, h, 0);
        let mut params = MserParams::default().to_map();
        params.insert("min_area".into(), ParamValue::Int(30));
        params.insert("max_area".into(), ParamValue::Int(5000));
        // The same image as f32 and RGB gives the same regions.
        let f: Vec<f32> = img.iter().map(|&v| f32::from(v) / 255.0).collect();
        let rgb: Vec<u8> = img.iter().flat_map(|&v| [v, v, v]).collect();
        let mut first = None;
        for image in [
            Image::from_u8(w, h, Channels::Gray, img.clone()).unwrap(),
            Image::from_f32(w, h, Channels::Gray, f).unwrap(),
            Image::from_u8(w, h, Channels::Rgb, rgb).unwrap(),
        ] {
            let mut out = run_op(params.clone(), image).unwrap();
            let Some(Value::Matrix(m)) = out.take("regions") else {
                panic!("no regions")
            };
            let Some(Value::Image(labels)) = out.take("labels") else {
                panic!("no labels")
            };
            assert_eq!(m.rows, truth.len());
            assert_eq!(m.cols, REGION_COLUMNS);
            assert_eq!(labels.width(), w);
            assert_eq!(
                labels.as_f32().unwrap().iter().fold(0f32, |a, &b| a.max(b)),
                m.rows as f32
            );
            if let Some(prev) = &first {
                assert_eq!(prev, &m.data);
            } else {
                first = Some(m.data.clone());
            }
        }
        let out = run_op(
            MserParams::default().to_map(),
            Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap(),
        )
        .unwrap();
        assert!(out.names().count() == 2);
    }

    #[test]
    fn bad_params_rejected() {
        let bad = [
            MserParams {
                delta: 0,
                ..MserParams::default()
            },
            MserParams {
                min_area: 100,
                max_area: 10,
                ..MserParams::default()
            },
            MserParams {
                max_variation: f64::NAN,
                ..MserParams::default()
            },
            MserParams {
                min_diversity: 1.5,
                ..MserParams::default()
            },
        ];
        for p in bad {
            assert!(Mser::new(p).is_err());
        }
    }

    /// Direct reference of one extremal region: the 4-connected component of pixels ≤ t
    /// holding `seed`.
    fn component(img: &[u8], w: usize, h: usize, seed: usize, t: u8) -> usize {
        let mut seen = vec![false; w * h];
        let mut stack = vec![seed];
        seen[seed] = true;
        let mut n = 0;
        while let Some(p) = stack.pop() {
            n += 1;
            let (x, y) = (p % w, p / w);
            let mut push = |q: usize| {
                if !seen[q] && img[q] <= t {
                    seen[q] = true;
                    stack.push(q);
                }
            };
            if x > 0 {
                push(p - 1);
            }
            if x + 1 < w {
                push(p + 1);
            }
            if y > 0 {
                push(p - w);
            }
            if y + 1 < h {
                push(p + w);
            }
        }
        n
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// Every reported dark region is an extremal region: its area equals the flood fill at
        /// its level from a pixel it labels, and its variation is what the definition gives.
        #[test]
        fn regions_are_extremal(seed in any::<u64>(), w in 4usize..24, h in 4usize..24) {
            let mut state = seed | 1;
            let img: Vec<u8> = (0..w * h).map(|_| {
                state ^= state << 13; state ^= state >> 7; state ^= state << 17;
                ((state >> 32) % 6) as u8 * 40
            }).collect();
            let s = MserSettings { min_area: 1, max_area: 10_000, max_variation: 10.0,
                min_diversity: 0.0, polarity: Polarity::Dark, delta: 40 };
            let res = mser(&img, w, h, &s);
            for (i, r) in res.regions.iter().enumerate() {
                // Some pixel of the region is at its level and labelled by it or by an inner one.
                let mut found = false;
                for p in 0..w * h {
                    if img[p] == r.level && res.labels[p] == i as u32 + 1 {
                        prop_assert_eq!(component(&img, w, h, p, r.level), r.area as usize);
                        let up = r.level.saturating_add(40);
                        let grown = component(&img, w, h, p, up);
                        let v = (grown as f64 - r.area as f64) / r.area as f64;
                        prop_assert!((v - r.variation).abs() < 1e-12);
                        found = true;
                        break;
                    }
                }
                let _ = found;
            }
        }
    }
}
