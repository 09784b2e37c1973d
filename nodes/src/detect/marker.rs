//! `detect.aruco`: ArUco-style square fiducial markers with a built-in 4×4 dictionary.
//!
//! Pipeline of [`detect_markers`]: adaptive mean threshold, outer borders of the dark
//! 8-connected components traced with Suzuki–Abe's border following, Douglas–Peucker polygon
//! approximation to convex quadrilaterals, corners refined by intersecting least-squares lines
//! fitted to the four sides, perspective sampling of the `(bits + 2)²` cell grid, border check
//! and dictionary look-up over the four rotations with bit-error correction.
//!
//! The dictionary ([`dictionary`]) is generated deterministically here: see its docs.
//! [`render_marker`] draws marker `i` for tests and graphs. Sequential and deterministic.

use std::sync::{Arc, OnceLock};

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};

use super::gray::gray_u8;

/// Data bits per side.
pub const BITS: usize = 4;
/// Cells per side including the black border.
pub const CELLS: usize = BITS + 2;
/// Markers in the dictionary.
pub const DICTIONARY_SIZE: usize = 50;
/// Minimum Hamming distance between any two codes (all rotations) and between a code and its
/// own rotations.
pub const MIN_DISTANCE: u32 = 4;
/// Columns of the `markers` matrix.
pub const MARKER_COLUMNS: usize = 9;

/// Fraction of the border cells allowed to read white.
const MAX_BORDER_ERROR_RATE: f64 = 0.35;

/// 90° clockwise rotation of a 4×4 code (bit `15 − (4r + c)` is cell row r, column c; 1 = white).
pub fn rotate_code(code: u16) -> u16 {
    let mut out = 0u16;
    for r in 0..BITS {
        for c in 0..BITS {
            // New (r, c) takes old (BITS − 1 − c, r).
            let bit = (code >> (15 - (4 * (BITS - 1 - c) + r))) & 1;
            out |= bit << (15 - (4 * r + c));
        }
    }
    out
}

/// The four rotations `rot^k(code)`, k = 0..3.
fn rotations(code: u16) -> [u16; 4] {
    let r1 = rotate_code(code);
    let r2 = rotate_code(r1);
    [code, r1, r2, rotate_code(r2)]
}

/// The built-in dictionary: 50 codes of 4×4 bits (1 = white cell, bit 15 = top-left cell, row
/// by row). Generated greedily from the xorshift64 sequence seeded with `0x853c49e6748fea9b`
/// (`s ^= s << 13; s ^= s >> 7; s ^= s << 17`, candidate = bits 32–47 of `s`): a candidate is
/// accepted when it has 5 to 11 white cells, differs from its own 90°, 180° and 270° rotations
/// in at least 4 bits, and from every rotation of every accepted code in at least 4 bits. So one
/// wrong bit is always corrected and rotations are never ambiguous.
pub fn dictionary() -> &'static [u16] {
    static DICT: OnceLock<Vec<u16>> = OnceLock::new();
    DICT.get_or_init(|| {
        let mut s: u64 = 0x853c_49e6_748f_ea9b;
        let mut accepted: Vec<u16> = Vec::with_capacity(DICTIONARY_SIZE);
        while accepted.len() < DICTIONARY_SIZE {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            let c = ((s >> 32) & 0xffff) as u16;
            if !(5..=11).contains(&c.count_ones()) {
                continue;
            }
            let rs = rotations(c);
            if rs[1..].iter().any(|&r| (r ^ c).count_ones() < MIN_DISTANCE) {
                continue;
            }
            if accepted.iter().any(|&a| {
                rotations(a)
                    .iter()
                    .any(|&r| (r ^ c).count_ones() < MIN_DISTANCE)
            }) {
                continue;
            }
            accepted.push(c);
        }
        accepted
    })
}

/// Marker `id` drawn with `cell` pixels per cell and a white quiet zone of `quiet` pixels:
/// a gray u8 square of side `CELLS · cell + 2 · quiet` (0 = black, 255 = white). `None` for an
/// id outside the dictionary.
pub fn render_marker(id: usize, cell: usize, quiet: usize) -> Option<Vec<u8>> {
    let code = *dictionary().get(id)?;
    let side = CELLS * cell + 2 * quiet;
    let mut img = vec![255u8; side * side];
    for y in 0..CELLS * cell {
        for x in 0..CELLS * cell {
            let (r, c) = (y / cell, x / cell);
            let white = if r == 0 || c == 0 || r == CELLS - 1 || c == CELLS - 1 {
                false
            } else {
                (code >> (15 - (4 * (r - 1) + (c - 1)))) & 1 == 1
            };
            img[(y + quiet) * side + x + quiet] = if white { 255 } else { 0 };
        }
    }
    Some(img)
}

params! {
    /// Parameters of `detect.aruco`.
    pub struct ArucoParams {
        /// Side (pixels, odd) of the adaptive-threshold window. Default 23.
        block_size: u32 = 23 => [min = 3],
        /// A pixel is dark when it is more than this many gray levels (0–255) below its window's
        /// mean. Default 7 (OpenCV's `adaptiveThreshConstant`).
        threshold_offset: f64 = 7.0,
        /// Smallest marker outline perimeter, pixels. Default 40.
        min_perimeter: u32 = 40 => [min = 4],
        /// Douglas–Peucker tolerance as a fraction of the outline's length. Default 0.03
        /// (OpenCV's `polygonalApproxAccuracyRate`).
        approx_accuracy: f64 = 0.03 => [above = 0.0, max = 0.5],
        /// Largest number of wrong data bits corrected (0–1; the dictionary's codes differ in at
        /// least 4 bits). Default 1.
        max_correction: u32 = 1 => [max = 1],
    }
}

/// Settings of [`detect_markers`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArucoSettings {
    /// See [`ArucoParams::block_size`].
    pub block_size: usize,
    /// See [`ArucoParams::threshold_offset`].
    pub threshold_offset: f64,
    /// See [`ArucoParams::min_perimeter`].
    pub min_perimeter: usize,
    /// See [`ArucoParams::approx_accuracy`].
    pub approx_accuracy: f64,
    /// See [`ArucoParams::max_correction`].
    pub max_correction: u32,
}

impl Default for ArucoSettings {
    fn default() -> Self {
        let p = ArucoParams::default();
        ArucoSettings {
            block_size: p.block_size as usize,
            threshold_offset: p.threshold_offset,
            min_perimeter: p.min_perimeter as usize,
            approx_accuracy: p.approx_accuracy,
            max_correction: p.max_correction,
        }
    }
}

/// A detected marker.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Marker {
    /// Dictionary index.
    pub id: usize,
    /// Corners clockwise from the marker's own top-left (pixel centres at integers).
    pub corners: [[f64; 2]; 4],
    /// Data bits that were corrected.
    pub errors: u32,
}

/// Dark mask: `v < window mean − offset`, window `block × block` clipped to the image.
fn adaptive_threshold(
    gray: &[u8],
    width: usize,
    height: usize,
    block: usize,
    offset: f64,
) -> Vec<bool> {
    let stride = width + 1;
    let mut integral = vec![0u64; stride * (height + 1)];
    for y in 0..height {
        let mut row = 0u64;
        for x in 0..width {
            row += u64::from(gray[y * width + x]);
            integral[(y + 1) * stride + x + 1] = integral[y * stride + x + 1] + row;
        }
    }
    let r = block / 2;
    let mut out = vec![false; width * height];
    for y in 0..height {
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(height));
        for x in 0..width {
            let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(width));
            let sum = integral[y1 * stride + x1] + integral[y0 * stride + x0]
                - integral[y0 * stride + x1]
                - integral[y1 * stride + x0];
            let n = ((y1 - y0) * (x1 - x0)) as f64;
            out[y * width + x] = f64::from(gray[y * width + x]) < sum as f64 / n - offset;
        }
    }
    out
}

/// Neighbour offsets (row, col), counter-clockwise on screen starting to the right (Suzuki–Abe's
/// numbering).
const DIRS: [(isize, isize); 8] = [
    (0, 1),
    (-1, 1),
    (-1, 0),
    (-1, -1),
    (0, -1),
    (1, -1),
    (1, 0),
    (1, 1),
];

/// Outer borders (as (x, y) pixel lists) of the 8-connected components of `mask`, one per
/// component, each traced from its first pixel in raster order with Suzuki–Abe's border
/// following (steps 3.1–3.5 of the paper).
fn outer_borders(
    mask: &[bool],
    width: usize,
    height: usize,
    min_len: usize,
) -> Vec<Vec<[usize; 2]>> {
    let at = |r: isize, c: isize| -> bool {
        r >= 0
            && c >= 0
            && (r as usize) < height
            && (c as usize) < width
            && mask[r as usize * width + c as usize]
    };
    let mut seen = vec![false; width * height];
    let mut stack = Vec::new();
    let mut borders = Vec::new();
    for start in 0..width * height {
        if !mask[start] || seen[start] {
            continue;
        }
        // Mark the component (8-connectivity).
        seen[start] = true;
        stack.push(start);
        let mut size = 0usize;
        while let Some(p) = stack.pop() {
            size += 1;
            let (r, c) = ((p / width) as isize, (p % width) as isize);
            for (dr, dc) in DIRS {
                if at(r + dr, c + dc) {
                    let q = (r + dr) as usize * width + (c + dc) as usize;
                    if !seen[q] {
                        seen[q] = true;
                        stack.push(q);
                    }
                }
            }
        }
        if size < min_len / 4 {
            continue;
        }
        let (r0, c0) = ((start / width) as isize, (start % width) as isize);
        // 3.1: clockwise from the left neighbour (a 0-pixel) for a 1-pixel.
        let mut first = None;
        for k in 0..8 {
            let d = (4 + 8 - k) % 8; // 4 = left, then clockwise
            if at(r0 + DIRS[d].0, c0 + DIRS[d].1) {
                first = Some(d);
                break;
            }
        }
        let Some(d1) = first else {
            continue; // isolated pixel
        };
        let (r1, c1) = (r0 + DIRS[d1].0, c0 + DIRS[d1].1);
        let mut border = vec![[c0 as usize, r0 as usize]];
        // 3.2
        let (mut r2, mut c2) = (r1, c1);
        let (mut r3, mut c3) = (r0, c0);
        let limit = 4 * width * height + 8;
        loop {
            // 3.3: counter-clockwise around (r3, c3) starting after (r2, c2).
            let from = DIRS
                .iter()
                .position(|&(dr, dc)| (r3 + dr, c3 + dc) == (r2, c2))
                .unwrap_or(0);
            let mut next = None;
            for k in 1..=8 {
                let d = (from + k) % 8;
                if at(r3 + DIRS[d].0, c3 + DIRS[d].1) {
                    next = Some((r3 + DIRS[d].0, c3 + DIRS[d].1));
                    break;
                }
            }
            let Some((r4, c4)) = next else { break };
            // 3.5
            if (r4, c4) == (r0, c0) && (r3, c3) == (r1, c1) {
                break;
            }
            (r2, c2) = (r3, c3);
            (r3, c3) = (r4, c4);
            border.push([c3 as usize, r3 as usize]);
            if border.len() > limit {
                break;
            }
        }
        // The walk ends on (r1, c1) having re-entered the start: drop the repeated start.
        if border.len() > 1 && border.last() == Some(&[c0 as usize, r0 as usize]) {
            border.pop();
        }
        if border.len() >= min_len {
            borders.push(border);
        }
    }
    borders
}

/// Distance from `p` to the line through `a` and `b`.
fn line_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len = dx.hypot(dy);
    if len == 0.0 {
        return (p[0] - a[0]).hypot(p[1] - a[1]);
    }
    ((p[0] - a[0]) * dy - (p[1] - a[1]) * dx).abs() / len
}

/// Douglas–Peucker simplification of the open polyline `pts[lo..=hi]`; pushes kept indices
/// (excluding `hi`).
fn dp(pts: &[[f64; 2]], lo: usize, hi: usize, eps: f64, out: &mut Vec<usize>) {
    let mut stack = vec![(lo, hi)];
    let mut kept = vec![lo];
    while let Some((a, b)) = stack.pop() {
        let mut far = 0.0;
        let mut idx = a;
        for i in a + 1..b {
            let d = line_distance(pts[i], pts[a], pts[b]);
            if d > far {
                far = d;
                idx = i;
            }
        }
        if far > eps {
            kept.push(idx);
            stack.push((a, idx));
            stack.push((idx, b));
        }
    }
    kept.sort_unstable();
    out.extend(kept);
}

/// Closed-contour Douglas–Peucker: indices of the kept vertices, in contour order.
fn approx_polygon(pts: &[[f64; 2]], eps: f64) -> Vec<usize> {
    let n = pts.len();
    if n < 3 {
        return (0..n).collect();
    }
    // Split at the point farthest from the first one.
    let far = (1..n)
        .max_by(|&i, &j| {
            let di = (pts[i][0] - pts[0][0]).hypot(pts[i][1] - pts[0][1]);
            let dj = (pts[j][0] - pts[0][0]).hypot(pts[j][1] - pts[0][1]);
            di.total_cmp(&dj).then(j.cmp(&i))
        })
        .unwrap_or(1);
    let mut closed: Vec<[f64; 2]> = pts.to_vec();
    closed.push(pts[0]);
    let mut out = Vec::new();
    dp(&closed, 0, far, eps, &mut out);
    dp(&closed, far, n, eps, &mut out);
    out
}

/// Least-squares line (point, unit direction) through `pts`.
fn fit_line(pts: &[[f64; 2]]) -> Option<([f64; 2], [f64; 2])> {
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p[0]).sum::<f64>() / n;
    let my = pts.iter().map(|p| p[1]).sum::<f64>() / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p[0] - mx, p[1] - my);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    Some(([mx, my], [theta.cos(), theta.sin()]))
}

fn intersect(a: ([f64; 2], [f64; 2]), b: ([f64; 2], [f64; 2])) -> Option<[f64; 2]> {
    let (p, d) = a;
    let (q, e) = b;
    let den = d[0] * e[1] - d[1] * e[0];
    if den.abs() < 1e-9 {
        return None;
    }
    let t = ((q[0] - p[0]) * e[1] - (q[1] - p[1]) * e[0]) / den;
    Some([p[0] + t * d[0], p[1] + t * d[1]])
}

/// Homography mapping the unit-cell square `(0,0), (S,0), (S,S), (0,S)` (S = [`CELLS`]) to
/// `quad`, as `[h0..h8]` row-major with h8 = 1.
fn square_to_quad(quad: &[[f64; 2]; 4]) -> Option<[f64; 9]> {
    let s = CELLS as f64;
    let src = [[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]];
    let mut a = [[0f64; 9]; 8];
    for k in 0..4 {
        let ([u, v], [x, y]) = (src[k], quad[k]);
        a[2 * k] = [u, v, 1.0, 0.0, 0.0, 0.0, -u * x, -v * x, x];
        a[2 * k + 1] = [0.0, 0.0, 0.0, u, v, 1.0, -u * y, -v * y, y];
    }
    // Gaussian elimination with partial pivoting on the 8×8 system.
    for col in 0..8 {
        let piv = (col..8).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, piv);
        let pivot = a[col];
        for (row, line) in a.iter_mut().enumerate() {
            if row != col {
                let f = line[col] / pivot[col];
                for (x, &p) in line[col..].iter_mut().zip(&pivot[col..]) {
                    *x -= f * p;
                }
            }
        }
    }
    let mut h = [0f64; 9];
    for i in 0..8 {
        h[i] = a[i][8] / a[i][i];
    }
    h[8] = 1.0;
    Some(h)
}

fn apply(h: &[f64; 9], u: f64, v: f64) -> [f64; 2] {
    let z = h[6] * u + h[7] * v + h[8];
    [
        (h[0] * u + h[1] * v + h[2]) / z,
        (h[3] * u + h[4] * v + h[5]) / z,
    ]
}

fn bilinear(gray: &[u8], width: usize, height: usize, p: [f64; 2]) -> f64 {
    let x = p[0].clamp(0.0, (width - 1) as f64);
    let y = p[1].clamp(0.0, (height - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let g = |xx: usize, yy: usize| f64::from(gray[yy * width + xx]);
    let top = g(x0, y0) + fx * (g(x1, y0) - g(x0, y0));
    let bottom = g(x0, y1) + fx * (g(x1, y1) - g(x0, y1));
    top + fy * (bottom - top)
}

/// Refined, clockwise corners of a contour approximated by a convex quadrilateral, or `None`.
fn quad_of(border: &[[usize; 2]], s: &ArucoSettings) -> Option<[[f64; 2]; 4]> {
    let pts: Vec<[f64; 2]> = border.iter().map(|p| [p[0] as f64, p[1] as f64]).collect();
    let eps = s.approx_accuracy * pts.len() as f64;
    let mut v = approx_polygon(&pts, eps);
    // The contour's start (its first pixel in raster order) is always a vertex of the
    // approximation; drop it, and any other vertex, when it lies on the line through its
    // neighbours.
    let mut k = 0;
    while v.len() > 3 && k < v.len() {
        let n = v.len();
        let (a, b, c) = (pts[v[(k + n - 1) % n]], pts[v[k]], pts[v[(k + 1) % n]]);
        if line_distance(b, a, c) < eps {
            v.remove(k);
        } else {
            k += 1;
        }
    }
    if v.len() != 4 {
        return None;
    }
    let corners: Vec<[f64; 2]> = v.iter().map(|&i| pts[i]).collect();
    // Convexity and minimum side.
    let mut sign = 0.0;
    for k in 0..4 {
        let (a, b, c) = (corners[k], corners[(k + 1) % 4], corners[(k + 2) % 4]);
        let cross = (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0]);
        if cross == 0.0 || (sign != 0.0 && cross.signum() != sign) {
            return None;
        }
        sign = cross.signum();
        let side = (b[0] - a[0]).hypot(b[1] - a[1]);
        if side < 0.1 * pts.len() as f64 {
            return None;
        }
    }
    // Side lines from the contour points between vertices (ends trimmed), moved half a pixel
    // outwards: the traced pixels are the outermost dark ones, whose centres lie about half a
    // pixel inside the edge.
    let centroid = [
        corners.iter().map(|p| p[0]).sum::<f64>() / 4.0,
        corners.iter().map(|p| p[1]).sum::<f64>() / 4.0,
    ];
    let n = pts.len();
    let mut lines = Vec::with_capacity(4);
    for k in 0..4 {
        let (a, b) = (v[k], v[(k + 1) % 4]);
        let len = (b + n - a) % n;
        let trim = len / 6;
        let side: Vec<[f64; 2]> = (trim..=len - trim).map(|i| pts[(a + i) % n]).collect();
        let (p, d) = fit_line(&side)?;
        let mut normal = [-d[1], d[0]];
        if (p[0] - centroid[0]) * normal[0] + (p[1] - centroid[1]) * normal[1] < 0.0 {
            normal = [-normal[0], -normal[1]];
        }
        lines.push(([p[0] + 0.5 * normal[0], p[1] + 0.5 * normal[1]], d));
    }
    let mut quad = [[0.0; 2]; 4];
    for k in 0..4 {
        quad[k] = intersect(lines[(k + 3) % 4], lines[k])?;
    }
    // Clockwise on screen (y down) means a positive shoelace sum.
    let area: f64 = (0..4)
        .map(|k| quad[k][0] * quad[(k + 1) % 4][1] - quad[(k + 1) % 4][0] * quad[k][1])
        .sum();
    if area < 0.0 {
        quad.swap(1, 3);
    }
    Some(quad)
}

/// Reads the cell grid of `quad` (row-major, `true` = white) from the gray image.
fn read_cells(
    gray: &[u8],
    width: usize,
    height: usize,
    quad: &[[f64; 2]; 4],
) -> Option<[bool; CELLS * CELLS]> {
    let h = square_to_quad(quad)?;
    // Cell means from 3×3 samples in the middle of each cell (margins 0.2 cell).
    let mut means = [0f64; CELLS * CELLS];
    for r in 0..CELLS {
        for c in 0..CELLS {
            let mut acc = 0.0;
            for j in 0..3 {
                for i in 0..3 {
                    let u = c as f64 + 0.2 + 0.3 * i as f64;
                    let v = r as f64 + 0.2 + 0.3 * j as f64;
                    acc += bilinear(gray, width, height, apply(&h, u, v));
                }
            }
            means[r * CELLS + c] = acc / 9.0;
        }
    }
    // Threshold halfway between the darkest border cell level and the quiet zone half a cell
    // outside the marker.
    let s = CELLS as f64;
    let mut outside = 0.0;
    let mut count = 0.0;
    for k in 0..CELLS {
        let t = k as f64 + 0.5;
        for (u, v) in [(t, -0.4), (t, s + 0.4), (-0.4, t), (s + 0.4, t)] {
            outside += bilinear(gray, width, height, apply(&h, u, v));
            count += 1.0;
        }
    }
    let outside = outside / count;
    let border: Vec<f64> = (0..CELLS * CELLS)
        .filter(|&i| {
            let (r, c) = (i / CELLS, i % CELLS);
            r == 0 || c == 0 || r == CELLS - 1 || c == CELLS - 1
        })
        .map(|i| means[i])
        .collect();
    let mut sorted = border.clone();
    sorted.sort_by(f64::total_cmp);
    let dark = sorted[sorted.len() / 2];
    if outside - dark < 10.0 {
        return None;
    }
    let t = 0.5 * (outside + dark);
    let mut cells = [false; CELLS * CELLS];
    for (c, &m) in cells.iter_mut().zip(&means) {
        *c = m > t;
    }
    let white_border = border.iter().filter(|&&m| m > t).count();
    if white_border as f64 > MAX_BORDER_ERROR_RATE * border.len() as f64 {
        return None;
    }
    Some(cells)
}

/// Markers of a gray 8-bit image, sorted by id then by first corner (y, x).
///
/// # Panics
///
/// If `gray.len() != width × height`.
pub fn detect_markers(gray: &[u8], width: usize, height: usize, s: &ArucoSettings) -> Vec<Marker> {
    assert_eq!(gray.len(), width * height, "gray buffer size");
    if width < 3 || height < 3 {
        return Vec::new();
    }
    let mask = adaptive_threshold(gray, width, height, s.block_size, s.threshold_offset);
    let borders = outer_borders(&mask, width, height, s.min_perimeter);
    let dict = dictionary();
    let mut found: Vec<Marker> = Vec::new();
    for border in &borders {
        let Some(quad) = quad_of(border, s) else {
            continue;
        };
        let Some(cells) = read_cells(gray, width, height, &quad) else {
            continue;
        };
        let mut code = 0u16;
        for r in 0..BITS {
            for c in 0..BITS {
                if cells[(r + 1) * CELLS + c + 1] {
                    code |= 1 << (15 - (4 * r + c));
                }
            }
        }
        // Best (distance, id, rotation): observed == rot^j(code_id) means the marker's top-left
        // is observed corner j.
        let mut best: Option<(u32, usize, usize)> = None;
        for (id, &m) in dict.iter().enumerate() {
            for (j, &r) in rotations(m).iter().enumerate() {
                let d = (r ^ code).count_ones();
                if best.is_none_or(|b| d < b.0) {
                    best = Some((d, id, j));
                }
            }
        }
        let Some((d, id, j)) = best else { continue };
        if d > s.max_correction {
            continue;
        }
        let corners = [
            quad[j],
            quad[(j + 1) % 4],
            quad[(j + 2) % 4],
            quad[(j + 3) % 4],
        ];
        found.push(Marker {
            id,
            corners,
            errors: d,
        });
    }
    found.sort_by(|a, b| {
        a.id.cmp(&b.id)
            .then(a.corners[0][1].total_cmp(&b.corners[0][1]))
            .then(a.corners[0][0].total_cmp(&b.corners[0][0]))
    });
    found
}

/// ArUco-style marker detector (`detect.aruco`). See [`detect_markers`].
#[derive(Debug, Clone, PartialEq)]
pub struct Aruco {
    settings: ArucoSettings,
}

impl Op for Aruco {
    type Params = ArucoParams;
    const ID: &'static str = "detect.aruco";
    const SUMMARY: &'static str =
        "Detects square 4×4 fiducial markers of the built-in dictionary: ids and corners.";
    const DOC: &'static str = r#"
Detects ArUco-style square markers: a black border one cell wide around 4×4 data cells (white =
1), on a white quiet zone. The dictionary is this project's own (not OpenCV's DICT_4X4_50): 50
codes generated deterministically (see `detect::marker::dictionary`), any two differing in at
least 4 bits under every rotation, so 1 bit error is corrected and orientation is unambiguous.
`detect::marker::render_marker(id, cell, quiet)` draws marker `id`.

Method (after OpenCV's `aruco::detectMarkers`):
1. Adaptive threshold: dark where value < mean of the `block_size`² window − `threshold_offset`.
2. Contours: the outer border of each 8-connected dark component, traced with Suzuki–Abe's
   border following; outlines shorter than `min_perimeter` pixels are dropped.
3. Douglas–Peucker approximation (tolerance `approx_accuracy` × outline length); convex
   quadrilaterals whose sides are at least a tenth of the outline length are kept.
4. Corners: least-squares lines fitted to each side's outline pixels (ends trimmed), moved half
   a pixel outwards, intersected.
5. Bits: the homography of the quad samples each of the 6×6 cells (3×3 bilinear samples in
   the middle of the cell); threshold halfway between the border cells' median and the quiet zone
   half a cell outside; at most 35 % of border cells may read white.
6. Identification: Hamming distance of the 16 bits to the four rotations of every code; the
   best within `max_correction` wins, and its rotation sets the corner order.

Input: any image; colour is reduced to BT.601 luma, u16 to v/257 and f32 to clamp(v,0,1)·255.

Outputs: `markers`, a Matrix with one row per marker [id, x0, y0, x1, y1, x2, y2, x3, y3]: the
corners clockwise (on screen) starting at the marker's own top-left, pixel centres at integers,
rows sorted by id; and `metrics`: `count`.

Differences from OpenCV: own dictionary; a single threshold window instead of a scan over
window sizes; corners from side-line fits (like CORNER_REFINE_CONTOUR) rather than raw polygon
vertices; markers touching other dark regions merge with them and are missed.

References: S. Garrido-Jurado et al., "Automatic generation and detection of highly reliable
fiducial markers under occlusion", Pattern Recognition 47(6), 2014; S. Suzuki, K. Abe,
"Topological structural analysis of digitized binary images by border following", CVGIP 30(1),
1985; D. Douglas, T. Peucker, Cartographica 10(2), 1973.

Example (a node of a graph):
    "markers": (op: "detect.aruco", inputs: { "image": "frame.image" },
                params: (block_size: 23, max_correction: 1)),
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
                "markers",
                PortType::Matrix,
                "rows [id, x0, y0, x1, y1, x2, y2, x3, y3], corners clockwise from top-left",
            ),
            PortSpec::new("metrics", PortType::Metrics, "count"),
        ]
    }

    fn new(p: ArucoParams) -> Result<Self, String> {
        if p.block_size < 3 || p.block_size.is_multiple_of(2) {
            return Err(format!(
                "`block_size` must be odd and ≥ 3, got {}",
                p.block_size
            ));
        }
        if !p.threshold_offset.is_finite() {
            return Err("`threshold_offset` must be finite".into());
        }
        if p.min_perimeter < 4 {
            return Err(format!(
                "`min_perimeter` must be ≥ 4, got {}",
                p.min_perimeter
            ));
        }
        if !p.approx_accuracy.is_finite() || p.approx_accuracy <= 0.0 || p.approx_accuracy > 0.5 {
            return Err(format!(
                "`approx_accuracy` must be in (0, 0.5], got {}",
                p.approx_accuracy
            ));
        }
        if p.max_correction > 1 {
            return Err(format!(
                "`max_correction` must be 0 or 1, got {}",
                p.max_correction
            ));
        }
        Ok(Aruco {
            settings: ArucoSettings {
                block_size: p.block_size as usize,
                threshold_offset: p.threshold_offset,
                min_perimeter: p.min_perimeter as usize,
                approx_accuracy: p.approx_accuracy,
                max_correction: p.max_correction,
            },
        })
    }
}

impl Operator for Aruco {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let gray = gray_u8(image);
        let found = detect_markers(&gray, image.width(), image.height(), &self.settings);
        let mut data = Vec::with_capacity(found.len() * MARKER_COLUMNS);
        for m in &found {
            data.push(m.id as f64);
            for c in &m.corners {
                data.extend_from_slice(c);
            }
        }
        let matrix = Matrix::new(found.len(), MARKER_COLUMNS, data)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let mut metrics = Metrics::new();
        metrics.insert("count".into(), found.len() as f64);
        Ok(Outputs::new()
            .with("markers", Value::Matrix(Arc::new(matrix)))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::{Channels, Image};

    #[test]
    fn dictionary_is_well_separated() {
        let d = dictionary();
        assert_eq!(d.len(), DICTIONARY_SIZE);
        for (i, &a) in d.iter().enumerate() {
            let ra = rotations(a);
            for &r in &ra[1..] {
                assert!((r ^ a).count_ones() >= MIN_DISTANCE);
            }
            for &b in &d[i + 1..] {
                for &r in &rotations(b) {
                    assert!((r ^ a).count_ones() >= MIN_DISTANCE);
                }
            }
        }
        // Rotating four times is the identity; one rotation moves the top-left bit to the
        // top-right.
        assert_eq!(rotations(rotate_code(0x1234))[3], 0x1234);
        assert_eq!(rotate_code(0x8000), 0x1000);
    }

    #[test]
    fn render_draws_border_and_bits() {
        let img = render_marker(3, 2, 1).unwrap();
        let side = CELLS * 2 + 2;
        assert_eq!(img.len(), side * side);
        assert_eq!(img[0], 255); // quiet zone
        assert_eq!(img[side + 1], 0); // border
        let code = dictionary()[3];
        let top_left_bit = (code >> 15) & 1 == 1;
        assert_eq!(img[3 * side + 3] == 255, top_left_bit);
        assert!(render_marker(DICTIONARY_SIZE, 2, 0).is_none());
    }

    /// Draws marker `id` through homography `h` (marker cell coordinates 0..CELLS → image,
    /// pixel centres at integers) into `img` (white background), 4×4 supersampled. Returns the
    /// true corners clockwise from the marker's top-left.
    fn draw(img: &mut [u8], w: usize, hgt: usize, id: usize, h: &[f64; 9]) -> [[f64; 2]; 4] {
        let code = dictionary()[id];
        let inv = invert(h);
        let s = CELLS as f64;
        for y in 0..hgt {
            for x in 0..w {
                let mut acc = 0.0;
                let mut touched = false;
                for j in 0..4 {
                    for i in 0..4 {
                        let px = x as f64 - 0.5 + (i as f64 + 0.5) / 4.0;
                        let py = y as f64 - 0.5 + (j as f64 + 0.5) / 4.0;
                        let [u, v] = apply(&inv, px, py);
                        let value = if u >= 0.0 && v >= 0.0 && u < s && v < s {
                            touched = true;
                            let (r, c) = (v as usize, u as usize);
                            let white = r > 0
                                && c > 0
                                && r < CELLS - 1
                                && c < CELLS - 1
                                && (code >> (15 - (4 * (r - 1) + (c - 1)))) & 1 == 1;
                            if white { 235.0 } else { 25.0 }
                        } else {
                            f64::from(img[y * w + x])
                        };
                        acc += value;
                    }
                }
                if touched {
                    img[y * w + x] = (acc / 16.0).round() as u8;
                }
            }
        }
        [
            apply(h, 0.0, 0.0),
            apply(h, s, 0.0),
            apply(h, s, s),
            apply(h, 0.0, s),
        ]
    }

    fn invert(h: &[f64; 9]) -> [f64; 9] {
        let [a, b, c, d, e, f, g, hh, i] = *h;
        let co = [
            e * i - f * hh,
            c * hh - b * i,
            b * f - c * e,
            f * g - d * i,
            a * i - c * g,
            c * d - a * f,
            d * hh - e * g,
            b * g - a * hh,
            a * e - b * d,
        ];
        let det = a * co[0] + b * co[3] + c * co[6];
        co.map(|v| v / det)
    }

    /// Cell size `s` px, rotation `a` about the marker's top-left, perspective terms `(p, q)`
    /// applied in marker coordinates, then translation: `x = t + A·(u, v) / (1 + p·u + q·v)`.
    fn hom(s: f64, a: f64, tx: f64, ty: f64, p: f64, q: f64) -> [f64; 9] {
        let (c, n) = (a.cos(), a.sin());
        [
            s * c + tx * p,
            -s * n + tx * q,
            tx,
            s * n + ty * p,
            s * c + ty * q,
            ty,
            p,
            q,
            1.0,
        ]
    }

    /// Image, width, height and (id, true corners) of each marker.
    type Scene = (Vec<u8>, usize, usize, Vec<(usize, [[f64; 2]; 4])>);

    fn scene() -> Scene {
        let (w, h) = (420, 320);
        let mut img = vec![240u8; w * h];
        let placements = [
            (0, hom(9.0, 0.0, 20.3, 25.6, 0.0, 0.0)),
            (7, hom(8.0, 0.5, 190.0, 20.0, 0.0, 0.0)),
            (23, hom(10.0, 2.2, 360.0, 150.0, 0.0, 0.0)),
            (49, hom(8.0, -0.3, 40.0, 180.0, 0.02, 0.015)),
            (31, hom(7.0, 3.6, 270.0, 300.0, -0.015, 0.01)),
        ];
        let truth = placements
            .iter()
            .map(|(id, hm)| (*id, draw(&mut img, w, h, *id, hm)))
            .collect();
        (img, w, h, truth)
    }

    #[test]
    fn finds_all_markers_with_corners_within_a_pixel() {
        let (img, w, h, truth) = scene();
        let found = detect_markers(&img, w, h, &ArucoSettings::default());
        assert_eq!(found.len(), truth.len(), "{found:?}");
        for (id, corners) in &truth {
            let m = found.iter().find(|m| m.id == *id).expect("marker missing");
            for (a, b) in m.corners.iter().zip(corners) {
                let e = (a[0] - b[0]).hypot(a[1] - b[1]);
                assert!(e < 1.0, "marker {id}: corner {a:?} vs {b:?} ({e} px)");
            }
        }
    }

    #[test]
    fn one_flipped_bit_is_corrected_only_when_allowed() {
        let (w, h) = (120, 120);
        let mut img = vec![240u8; w * h];
        let corners = draw(&mut img, w, h, 5, &hom(12.0, 0.0, 24.0, 24.0, 0.0, 0.0));
        // Flip the top-left data cell (cell (1, 1) spans pixels 36..48).
        for y in 37..47 {
            for x in 37..47 {
                img[y * w + x] = 255 - img[y * w + x];
            }
        }
        let found = detect_markers(&img, w, h, &ArucoSettings::default());
        assert_eq!(found.len(), 1);
        assert_eq!(found[0].id, 5);
        assert_eq!(found[0].errors, 1);
        assert!((found[0].corners[0][0] - corners[0][0]).abs() < 1.0);
        let strict = ArucoSettings {
            max_correction: 0,
            ..ArucoSettings::default()
        };
        assert!(detect_markers(&img, w, h, &strict).is_empty());
    }

    #[test]
    fn operator_output_and_extremes() {
        let (img, w, h, truth) = scene();
        let rgb: Vec<u16> = img.iter().flat_map(|&v| [u16::from(v) * 257; 3]).collect();
        let run = |image: Image| {
            let op = Aruco::new(ArucoParams::default()).unwrap();
            let specs = Aruco::inputs();
            let values = [Some(Value::image(image))];
            let ctx = RunContext {
                node: "aruco".into(),
                threads: 1,
                element: None,
            };
            let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
            let Some(Value::Matrix(m)) = out.take("markers") else {
                panic!("no markers")
            };
            let Some(Value::Metrics(me)) = out.take("metrics") else {
                panic!("no metrics")
            };
            (m, me)
        };
        let (m, me) = run(Image::from_u16(w, h, Channels::Rgb, rgb).unwrap());
        assert_eq!(m.rows, truth.len());
        assert_eq!(m.cols, MARKER_COLUMNS);
        assert_eq!(me["count"], truth.len() as f64);
        let mut ids: Vec<f64> = (0..m.rows).map(|r| m.data[r * MARKER_COLUMNS]).collect();
        let sorted = {
            let mut s = ids.clone();
            s.sort_by(f64::total_cmp);
            s
        };
        assert_eq!(ids, sorted);
        ids.dedup();
        assert_eq!(ids.len(), truth.len());
        for image in [
            Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap(),
            Image::from_u8(1, 1, Channels::Gray, vec![0]).unwrap(),
            Image::from_u8(20, 20, Channels::Gray, vec![128; 400]).unwrap(),
        ] {
            let (m, me) = run(image);
            assert_eq!(m.rows, 0);
            assert_eq!(me["count"], 0.0);
        }
        for bad in [
            ArucoParams {
                block_size: 10,
                ..ArucoParams::default()
            },
            ArucoParams {
                threshold_offset: f64::INFINITY,
                ..ArucoParams::default()
            },
            ArucoParams {
                approx_accuracy: 0.0,
                ..ArucoParams::default()
            },
            ArucoParams {
                max_correction: 2,
                ..ArucoParams::default()
            },
        ] {
            assert!(Aruco::new(bad).is_err());
        }
    }

    #[test]
    fn polygon_approximation_keeps_square_corners() {
        let mut pts = Vec::new();
        for i in 0..10 {
            pts.push([i as f64, 0.0]);
        }
        for i in 0..10 {
            pts.push([10.0, i as f64]);
        }
        for i in 0..10 {
            pts.push([10.0 - i as f64, 10.0]);
        }
        for i in 0..10 {
            pts.push([0.0, 10.0 - i as f64]);
        }
        let v = approx_polygon(&pts, 1.0);
        assert_eq!(v, vec![0, 10, 20, 30]);
    }
}
