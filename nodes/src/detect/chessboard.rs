//! `detect.chessboard`: inner corners of a calibration chessboard, ordered and refined to
//! subpixel accuracy.
//!
//! [`find_chessboard`] works in three steps:
//! 1. Saddle points: on a Gaussian-smoothed copy, the response `Ixy² − Ixx·Iyy − |∇I|²/σ²` is
//!    large at X-junctions (a saddle with zero gradient) and negative at L-corners and edges;
//!    its local maxima are the candidates, each with its two edge directions (the null directions
//!    of the Hessian's quadratic form).
//! 2. Grid growing: from a candidate, its nearest candidates along its edge directions and the
//!    diagonal one form a 2×2 seed; rows and columns are added on all four sides by linear
//!    extrapolation while every predicted corner has a candidate near it. A grid of exactly the
//!    pattern's size is the board.
//! 3. Ordering (row-major from the corner nearest the image's top-left) and [`corner_subpix`]
//!    refinement (OpenCV's `cornerSubPix`).
//!
//! The response is computed in parallel over fixed row bands; everything else is sequential, so
//! results do not depend on the thread count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, Value};
use rayon::prelude::*;

use super::gray::gray_u8;
use crate::filter::border::BorderMode;
use crate::filter::gaussian::gaussian_blur;

/// Rows per parallel band of the response.
const BAND_ROWS: usize = 32;

params! {
    /// Parameters of `detect.chessboard`.
    pub struct ChessboardParams {
        /// Inner corners per chessboard row (OpenCV's `patternSize.width`). Default 9.
        cols: u32 = 9 => [min = 2],
        /// Inner corners per column (OpenCV's `patternSize.height`). Default 6.
        rows: u32 = 6 => [min = 2],
        /// Standard deviation (pixels) of the Gaussian applied before the saddle response;
        /// about a tenth of the square size or less. Default 2.
        sigma: f64 = 2.0 => [min = 0.5, max = 20.0],
        /// Candidates must reach this fraction of the strongest saddle response. Default 0.03.
        min_response: f64 = 0.03 => [min = 0.0, max = 1.0],
        /// Half-size (pixels) of the subpixel refinement window (OpenCV's `winSize`): the window
        /// is `2·refine_window + 1` wide. 0 disables refinement. Default 5.
        refine_window: u32 = 5 => [max = 50],
        /// Refinement stops after this many iterations. Default 40.
        refine_iterations: u32 = 40 => [min = 1],
        /// Refinement stops when a step moves the corner less than this (pixels). Default 0.001.
        refine_epsilon: f64 = 0.001 => [min = 0.0],
    }
}

/// Settings of [`find_chessboard`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChessboardSettings {
    /// Inner corners per row.
    pub columns: usize,
    /// Inner corners per column.
    pub rows: usize,
    /// Smoothing before the response (pixels).
    pub sigma: f64,
    /// Fraction of the strongest response a candidate needs.
    pub min_response: f64,
    /// Refinement half-window (0 = none).
    pub refine_window: usize,
    /// Refinement iterations.
    pub refine_iterations: usize,
    /// Refinement stop distance (pixels).
    pub refine_epsilon: f64,
}

impl Default for ChessboardSettings {
    fn default() -> Self {
        let p = ChessboardParams::default();
        ChessboardSettings {
            columns: p.cols as usize,
            rows: p.rows as usize,
            sigma: p.sigma,
            min_response: p.min_response,
            refine_window: p.refine_window as usize,
            refine_iterations: p.refine_iterations as usize,
            refine_epsilon: p.refine_epsilon,
        }
    }
}

/// A saddle-point candidate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Saddle {
    /// Position (pixel centres at integers).
    pub p: [f64; 2],
    /// Response.
    pub response: f64,
    /// Unit edge directions.
    pub dirs: [[f64; 2]; 2],
}

/// Found board: corners row-major (`columns` per row) and the mean refinement shift.
#[derive(Debug, Clone, PartialEq)]
pub struct Board {
    /// Refined corners.
    pub corners: Vec<[f64; 2]>,
    /// Mean distance between the integer candidates and the refined corners (pixels).
    pub mean_shift: f64,
}

/// Saddle candidates of an f32 image (0–255 scale), strongest first.
pub fn saddle_points(
    img: &[f32],
    width: usize,
    height: usize,
    sigma: f64,
    min_response: f64,
) -> Vec<Saddle> {
    if width < 5 || height < 5 {
        return Vec::new();
    }
    let blurred = match Image::from_f32(width, height, Channels::Gray, img.to_vec()) {
        Ok(image) => gaussian_blur(&image, sigma, sigma, 0, 0, BorderMode::Reflect101, 0.0),
        Err(_) => return Vec::new(),
    };
    let Some(b) = blurred.as_f32() else {
        return Vec::new();
    };
    let inv_s2 = (1.0 / (sigma * sigma)) as f32;
    let mut resp = vec![0f32; width * height];
    resp.par_chunks_mut(width * BAND_ROWS)
        .enumerate()
        .for_each(|(band, out)| {
            for (i, row) in out.chunks_exact_mut(width).enumerate() {
                let y = band * BAND_ROWS + i;
                if y == 0 || y + 1 >= height {
                    continue;
                }
                let (up, mid, down) = (
                    &b[(y - 1) * width..y * width],
                    &b[y * width..(y + 1) * width],
                    &b[(y + 1) * width..(y + 2) * width],
                );
                for x in 1..width - 1 {
                    let ix = 0.5 * (mid[x + 1] - mid[x - 1]);
                    let iy = 0.5 * (down[x] - up[x]);
                    let ixx = mid[x + 1] - 2.0 * mid[x] + mid[x - 1];
                    let iyy = down[x] - 2.0 * mid[x] + up[x];
                    let ixy = 0.25 * (down[x + 1] - down[x - 1] - up[x + 1] + up[x - 1]);
                    row[x] = ixy * ixy - ixx * iyy - (ix * ix + iy * iy) * inv_s2;
                }
            }
        });
    let max = resp.iter().fold(0f32, |a, &b| a.max(b));
    if max <= 0.0 {
        return Vec::new();
    }
    let floor = (min_response as f32 * max).max(f32::MIN_POSITIVE);
    let r = (sigma.ceil() as usize).max(2);
    let mut out = Vec::new();
    for y in r..height.saturating_sub(r) {
        for x in r..width - r {
            let v = resp[y * width + x];
            if v < floor {
                continue;
            }
            // Strict maximum over earlier neighbours, ≥ later ones: one pixel per plateau.
            let mut is_max = true;
            'win: for yy in y - r..=y + r {
                for xx in x - r..=x + r {
                    let q = resp[yy * width + xx];
                    let earlier = (yy, xx) < (y, x);
                    if (earlier && q >= v) || (!earlier && q > v) {
                        is_max = false;
                        break 'win;
                    }
                }
            }
            if !is_max {
                continue;
            }
            let at = |xx: usize, yy: usize| b[yy * width + xx] as f64;
            let ixx = at(x + 1, y) - 2.0 * at(x, y) + at(x - 1, y);
            let iyy = at(x, y + 1) - 2.0 * at(x, y) + at(x, y - 1);
            let ixy =
                0.25 * (at(x + 1, y + 1) - at(x - 1, y + 1) - at(x + 1, y - 1) + at(x - 1, y - 1));
            let half = 0.5 * (ixx + iyy);
            let disc = (0.25 * (ixx - iyy) * (ixx - iyy) + ixy * ixy).sqrt();
            let (l1, l2) = (half + disc, half - disc);
            if l1 <= 0.0 || l2 >= 0.0 {
                continue;
            }
            let theta = 0.5 * (2.0 * ixy).atan2(ixx - iyy);
            let e1 = [theta.cos(), theta.sin()];
            let e2 = [-e1[1], e1[0]];
            let phi = (l1 / -l2).sqrt().atan();
            let (c, s) = (phi.cos(), phi.sin());
            let dirs = [
                [c * e1[0] + s * e2[0], c * e1[1] + s * e2[1]],
                [c * e1[0] - s * e2[0], c * e1[1] - s * e2[1]],
            ];
            out.push(Saddle {
                p: [x as f64, y as f64],
                response: f64::from(v),
                dirs,
            });
        }
    }
    out.sort_by(|a, b| {
        b.response
            .total_cmp(&a.response)
            .then(a.p[1].total_cmp(&b.p[1]))
            .then(a.p[0].total_cmp(&b.p[0]))
    });
    out
}

fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn norm(a: [f64; 2]) -> f64 {
    a[0].hypot(a[1])
}

/// Grid growing over candidate positions.
struct Grower<'a> {
    pts: &'a [Saddle],
    used: Vec<bool>,
    /// grid[row][col] = candidate index.
    grid: Vec<Vec<usize>>,
}

impl Grower<'_> {
    /// Nearest unused candidate within `tol` of `p`.
    fn nearest(&self, p: [f64; 2], tol: f64, taken: &[usize]) -> Option<usize> {
        let mut best = None;
        let mut best_d = tol;
        for (i, s) in self.pts.iter().enumerate() {
            if self.used[i] || taken.contains(&i) {
                continue;
            }
            let d = norm(sub(s.p, p));
            if d < best_d {
                best_d = d;
                best = Some(i);
            }
        }
        best
    }

    /// Neighbour of candidate `c` along direction `d`: minimizes along + 5·perp.
    fn along(&self, c: usize, d: [f64; 2]) -> Option<usize> {
        let o = self.pts[c].p;
        let mut best = None;
        let mut best_score = f64::INFINITY;
        for (i, s) in self.pts.iter().enumerate() {
            if i == c {
                continue;
            }
            let v = sub(s.p, o);
            let a = v[0] * d[0] + v[1] * d[1];
            let perp = (v[0] * d[1] - v[1] * d[0]).abs();
            if a < 2.0 || perp > 0.5 * a {
                continue;
            }
            let score = a + 5.0 * perp;
            if score < best_score {
                best_score = score;
                best = Some(i);
            }
        }
        best
    }

    fn pos(&self, r: usize, c: usize) -> [f64; 2] {
        self.pts[self.grid[r][c]].p
    }

    /// Tries to add a row or column on `side` (0 right, 1 left, 2 bottom, 3 top).
    fn grow(&mut self, side: usize) -> bool {
        let rows = self.grid.len();
        let cols = self.grid[0].len();
        let n = if side < 2 { rows } else { cols };
        let mut new = Vec::with_capacity(n);
        for k in 0..n {
            let (last, prev) = match side {
                0 => (self.pos(k, cols - 1), self.pos(k, cols - 2)),
                1 => (self.pos(k, 0), self.pos(k, 1)),
                2 => (self.pos(rows - 1, k), self.pos(rows - 2, k)),
                _ => (self.pos(0, k), self.pos(1, k)),
            };
            let step = sub(last, prev);
            let pred = [last[0] + step[0], last[1] + step[1]];
            match self.nearest(pred, 0.4 * norm(step), &new) {
                Some(i) => new.push(i),
                None => return false,
            }
        }
        for &i in &new {
            self.used[i] = true;
        }
        match side {
            0 => self
                .grid
                .iter_mut()
                .zip(new)
                .for_each(|(row, i)| row.push(i)),
            1 => self
                .grid
                .iter_mut()
                .zip(new)
                .for_each(|(row, i)| row.insert(0, i)),
            2 => self.grid.push(new),
            _ => self.grid.insert(0, new),
        }
        true
    }
}

/// Grid grown from candidate `seed` with edge-direction signs `signs`, or `None`.
fn grow_from(
    pts: &[Saddle],
    seed: usize,
    signs: [f64; 2],
    limit: usize,
) -> Option<Vec<Vec<usize>>> {
    let mut g = Grower {
        pts,
        used: vec![false; pts.len()],
        grid: Vec::new(),
    };
    let s = pts[seed];
    let du = [signs[0] * s.dirs[0][0], signs[0] * s.dirs[0][1]];
    let dv = [signs[1] * s.dirs[1][0], signs[1] * s.dirs[1][1]];
    let a = g.along(seed, du)?;
    let d = g.along(seed, dv)?;
    if a == d {
        return None;
    }
    let (va, vd) = (sub(pts[a].p, s.p), sub(pts[d].p, s.p));
    let (la, ld) = (norm(va), norm(vd));
    if (va[0] * vd[1] - va[1] * vd[0]).abs() < 0.3 * la * ld || la > 2.0 * ld || ld > 2.0 * la {
        return None;
    }
    g.used[seed] = true;
    g.used[a] = true;
    g.used[d] = true;
    let pred = [pts[a].p[0] + vd[0], pts[a].p[1] + vd[1]];
    let diag = g.nearest(pred, 0.4 * la.min(ld), &[])?;
    g.used[diag] = true;
    g.grid = vec![vec![seed, a], vec![d, diag]];
    loop {
        let mut grew = false;
        for side in 0..4 {
            if g.grid.len() > limit || g.grid[0].len() > limit {
                return None;
            }
            grew |= g.grow(side);
        }
        if !grew {
            break;
        }
    }
    Some(g.grid)
}

/// The `columns × rows` (or `rows × columns`) sub-grid of `grid` with the largest summed
/// response, if the grid exceeds the pattern by at most one row and one column.
fn best_window(
    pts: &[Saddle],
    grid: &[Vec<usize>],
    columns: usize,
    rows: usize,
) -> Option<Vec<Vec<usize>>> {
    let (gr, gc) = (grid.len(), grid[0].len());
    let mut best: Option<(f64, Vec<Vec<usize>>)> = None;
    for (h, w) in [(rows, columns), (columns, rows)] {
        if gr < h || gc < w || gr > h + 1 || gc > w + 1 {
            continue;
        }
        for r0 in 0..=gr - h {
            for c0 in 0..=gc - w {
                let sub: Vec<Vec<usize>> = grid[r0..r0 + h]
                    .iter()
                    .map(|row| row[c0..c0 + w].to_vec())
                    .collect();
                let score: f64 = sub.iter().flatten().map(|&i| pts[i].response).sum();
                if best.as_ref().is_none_or(|b| score > b.0) {
                    best = Some((score, sub));
                }
            }
        }
    }
    best.map(|b| b.1)
}

/// The grid's corners in the output order: `columns` per row, `rows` rows, starting at the
/// corner nearest the image's top-left (smallest x + y; for square patterns, rows running the
/// more horizontal way).
fn order(
    pts: &[Saddle],
    grid: &[Vec<usize>],
    columns: usize,
    rows: usize,
) -> Option<Vec<[f64; 2]>> {
    let (gr, gc) = (grid.len(), grid[0].len());
    let at = |r: usize, c: usize| pts[grid[r][c]].p;
    let mut best: Option<(f64, f64, Vec<[f64; 2]>)> = None;
    for transpose in [false, true] {
        let (h, w) = if transpose { (gc, gr) } else { (gr, gc) };
        if (w, h) != (columns, rows) {
            continue;
        }
        for flip_r in [false, true] {
            for flip_c in [false, true] {
                let mut out = Vec::with_capacity(w * h);
                for r in 0..h {
                    for c in 0..w {
                        let rr = if flip_r { h - 1 - r } else { r };
                        let cc = if flip_c { w - 1 - c } else { c };
                        out.push(if transpose { at(cc, rr) } else { at(rr, cc) });
                    }
                }
                let first = out[0][0] + out[0][1];
                let dir = sub(out[1], out[0]);
                let horizontal = dir[0] / norm(dir).max(1e-12);
                let better = match &best {
                    None => true,
                    Some((f, hz, _)) => {
                        first < f - 1e-9 || ((first - f).abs() <= 1e-9 && horizontal > *hz)
                    }
                };
                if better {
                    best = Some((first, horizontal, out));
                }
            }
        }
    }
    best.map(|b| b.2)
}

/// Bilinear sample with replicated borders.
fn bilinear(img: &[f32], width: usize, height: usize, x: f64, y: f64) -> f64 {
    let x = x.clamp(0.0, (width - 1) as f64);
    let y = y.clamp(0.0, (height - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let p = |xx: usize, yy: usize| f64::from(img[yy * width + xx]);
    let top = p(x0, y0) + fx * (p(x1, y0) - p(x0, y0));
    let bottom = p(x0, y1) + fx * (p(x1, y1) - p(x0, y1));
    top + fy * (bottom - top)
}

/// Subpixel corner refinement as OpenCV's `cornerSubPix` (no zero zone): the corner `q` solves
/// `Σ w·g·gᵀ (p − q) = 0` over the window's gradients `g` at points `p`, with Gaussian weights
/// `w = exp(−(dx² + dy²)/win²)`; the window is resampled bilinearly around the current estimate
/// each iteration. A corner that wanders more than `win` away is put back where it started.
pub fn corner_subpix(
    img: &[f32],
    width: usize,
    height: usize,
    start: [f64; 2],
    win: usize,
    iterations: usize,
    epsilon: f64,
) -> [f64; 2] {
    if win == 0 || width == 0 || height == 0 {
        return start;
    }
    let side = 2 * win + 3;
    let w = win as f64;
    let mask: Vec<f64> = (0..2 * win + 1)
        .map(|i| {
            let t = (i as f64 - w) / w;
            (-t * t).exp()
        })
        .collect();
    let mut sub = vec![0f64; side * side];
    let mut c = start;
    for _ in 0..iterations {
        for j in 0..side {
            for i in 0..side {
                sub[j * side + i] = bilinear(
                    img,
                    width,
                    height,
                    c[0] + i as f64 - (win + 1) as f64,
                    c[1] + j as f64 - (win + 1) as f64,
                );
            }
        }
        let (mut a, mut b, mut cc, mut bb1, mut bb2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for j in 0..2 * win + 1 {
            let py = j as f64 - w;
            for i in 0..2 * win + 1 {
                let px = i as f64 - w;
                let m = mask[i] * mask[j];
                let k = (j + 1) * side + i + 1;
                let gx = sub[k + 1] - sub[k - 1];
                let gy = sub[k + side] - sub[k - side];
                let (gxx, gxy, gyy) = (gx * gx * m, gx * gy * m, gy * gy * m);
                a += gxx;
                b += gxy;
                cc += gyy;
                bb1 += gxx * px + gxy * py;
                bb2 += gxy * px + gyy * py;
            }
        }
        let det = a * cc - b * b;
        if det.abs() <= f64::EPSILON * (a * cc).abs().max(1e-300) {
            break;
        }
        let next = [
            c[0] + (cc * bb1 - b * bb2) / det,
            c[1] + (a * bb2 - b * bb1) / det,
        ];
        let step = norm(sub_pt(next, c));
        c = next;
        if norm(sub_pt(c, start)) > w {
            return start;
        }
        if step <= epsilon {
            break;
        }
    }
    c
}

fn sub_pt(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    sub(a, b)
}

/// Finds a `columns × rows` chessboard in a gray image (0–255 scale, f32). `None` when no grid
/// of exactly that size is found. See the module docs.
pub fn find_chessboard(
    img: &[f32],
    width: usize,
    height: usize,
    s: &ChessboardSettings,
) -> Option<Board> {
    if img.len() != width * height {
        return None;
    }
    let mut pts = saddle_points(img, width, height, s.sigma, s.min_response);
    let needed = s.columns * s.rows;
    if pts.len() < needed {
        return None;
    }
    pts.truncate((4 * needed).max(needed + 200));
    // Background saddles next to the board (a dark surround makes the outer squares' corners
    // X-junctions too) can add one row or column on a side: allow one extra and keep the best
    // window.
    let limit = s.columns.max(s.rows) + 1;
    let mut found = None;
    'seeds: for seed in 0..pts.len() {
        for signs in [[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]] {
            if let Some(grid) = grow_from(&pts, seed, signs, limit)
                && let Some(grid) = best_window(&pts, &grid, s.columns, s.rows)
                && let Some(corners) = order(&pts, &grid, s.columns, s.rows)
            {
                found = Some(corners);
                break 'seeds;
            }
        }
    }
    let initial = found?;
    let corners: Vec<[f64; 2]> = initial
        .iter()
        .map(|&p| {
            corner_subpix(
                img,
                width,
                height,
                p,
                s.refine_window,
                s.refine_iterations,
                s.refine_epsilon,
            )
        })
        .collect();
    let mean_shift = initial
        .iter()
        .zip(&corners)
        .map(|(a, b)| norm(sub(*a, *b)))
        .sum::<f64>()
        / corners.len() as f64;
    Some(Board {
        corners,
        mean_shift,
    })
}

/// Chessboard corner detector (`detect.chessboard`). See [`find_chessboard`].
#[derive(Debug, Clone, PartialEq)]
pub struct Chessboard {
    settings: ChessboardSettings,
}

impl Op for Chessboard {
    type Params = ChessboardParams;
    const ID: &'static str = "detect.chessboard";
    const SUMMARY: &'static str = "Finds the inner corners of a calibration chessboard, ordered row-major and refined to subpixel accuracy.";
    const DOC: &'static str = r#"
Detects a chessboard of `cols × rows` inner corners (OpenCV's patternSize = (cols, rows))
and returns its corners ordered row-major with subpixel accuracy, like OpenCV's
`findChessboardCorners` followed by `cornerSubPix`.

Method:
1. Saddle response. The gray image is smoothed with a Gaussian of `sigma`; with central
   differences, r = Ixy² − Ixx·Iyy − (Ix² + Iy²)/σ². Inner corners (X-junctions) are saddles with
   zero gradient and give the largest r; L-corners of the outer squares and plain edges have a
   large gradient and come out negative. Local maxima (window 2·⌈σ⌉+1, at least 5) above
   `min_response` × the global maximum whose Hessian has one positive and one negative eigenvalue
   are candidates; the Hessian's null directions are the two edge directions through the corner.
2. Grid growing (in the spirit of Geiger et al.'s libcbdetect): from each candidate, strongest
   first, the nearest candidates along its two edge directions (distance along + 5 × distance
   across) and the candidate nearest the completed parallelogram form a 2×2 seed. Rows and
   columns are added on the four sides by linear extrapolation (next = last + (last − previous)),
   each prediction needing an unused candidate within 0.4 × the local spacing. A grid of
   columns × rows (either way round), or one row and/or column more (saddles of a dark
   background next to the outer squares), is the board; from a larger grid, the window with the
   largest summed response is kept.
3. Order: rows of `columns` corners; the first corner is the grid corner with the smallest x + y
   (for square patterns, rows run the more horizontal way).
4. Refinement: OpenCV's `cornerSubPix` (window 2·refine_window+1, Gaussian weights
   exp(−(d/refine_window)²), bilinear resampling each iteration, stop after `refine_iterations`
   or a step below `refine_epsilon`; no zero zone).

Input: any image; colour is reduced to BT.601 luma, u16 to v/257 and f32 to clamp(v,0,1)·255.

Outputs: `corners` (Points2D, columns × rows points, empty when not found; pixel centres at
integers) and `metrics`: `found` (1 or 0), `count` (corners returned) and `mean_shift` (mean
distance the refinement moved the corners, pixels).

Differences from OpenCV: OpenCV finds the board from quadrilaterals of a dilated binary image and
orders from a corner determined by its quad linking, which for symmetric boards can start at any
corner; this operator always starts nearest the image's top-left. A board one row or column
larger than the pattern gives the strongest sub-window (OpenCV rejects it); larger ones are
rejected.

References: A. Geiger et al., "Automatic camera and range sensor calibration using a single
shot", ICRA 2012 (saddle corners, grid growing); OpenCV `cornerSubPix` (Förstner-style gradient
orthogonality).

Example (a node of a graph):
    "board": (op: "detect.chessboard", inputs: { "image": "frame.image" },
              params: (cols: 9, rows: 6, refine_window: 5)),
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
                "corners",
                PortType::Points2D,
                "inner corners, row-major from the top-left; empty if not found",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "found (0/1), count, mean_shift",
            ),
        ]
    }

    fn new(p: ChessboardParams) -> Result<Self, String> {
        if p.cols < 2 || p.rows < 2 {
            return Err(format!(
                "need at least 2 × 2 inner corners, got {} × {}",
                p.cols, p.rows
            ));
        }
        if !p.sigma.is_finite() || !(0.5..=20.0).contains(&p.sigma) {
            return Err(format!("`sigma` must be in [0.5, 20], got {}", p.sigma));
        }
        if !p.min_response.is_finite() || !(0.0..=1.0).contains(&p.min_response) {
            return Err(format!(
                "`min_response` must be in [0, 1], got {}",
                p.min_response
            ));
        }
        if p.refine_window > 50 {
            return Err(format!(
                "`refine_window` must be ≤ 50, got {}",
                p.refine_window
            ));
        }
        if p.refine_iterations == 0 {
            return Err("`refine_iterations` must be ≥ 1".into());
        }
        if !p.refine_epsilon.is_finite() || p.refine_epsilon < 0.0 {
            return Err(format!(
                "`refine_epsilon` must be finite and ≥ 0, got {}",
                p.refine_epsilon
            ));
        }
        Ok(Chessboard {
            settings: ChessboardSettings {
                columns: p.cols as usize,
                rows: p.rows as usize,
                sigma: p.sigma,
                min_response: p.min_response,
                refine_window: p.refine_window as usize,
                refine_iterations: p.refine_iterations as usize,
                refine_epsilon: p.refine_epsilon,
            },
        })
    }
}

impl Operator for Chessboard {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (w, h) = (image.width(), image.height());
        let gray: Vec<f32> = gray_u8(image).iter().map(|&v| f32::from(v)).collect();
        let board = find_chessboard(&gray, w, h, &self.settings);
        let mut metrics = Metrics::new();
        let (corners, shift) = match board {
            Some(b) => (b.corners, b.mean_shift),
            None => (Vec::new(), 0.0),
        };
        metrics.insert("found".into(), if corners.is_empty() { 0.0 } else { 1.0 });
        metrics.insert("count".into(), corners.len() as f64);
        metrics.insert("mean_shift".into(), shift);
        Ok(Outputs::new()
            .with("corners", Value::Points2D(Arc::new(corners)))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Applies a 3×3 homography (row-major) to (u, v).
    fn apply(h: &[f64; 9], u: f64, v: f64) -> [f64; 2] {
        let z = h[6] * u + h[7] * v + h[8];
        [
            (h[0] * u + h[1] * v + h[2]) / z,
            (h[3] * u + h[4] * v + h[5]) / z,
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

    /// Renders a board of `(cols + 1) × (rows + 1)` squares (board units: squares of side 1,
    /// inner corners at integer (u, v), u in 1..=cols, v in 1..=rows) through `h` (board →
    /// image, pixel centres at integers), 8×8 supersampled, black 30 / white 220, background
    /// 220; then Gaussian blur `blur` and uniform noise ±`noise`.
    fn render(
        w: usize,
        hgt: usize,
        cols: usize,
        rows: usize,
        h: &[f64; 9],
        blur: f64,
        noise: f32,
    ) -> (Vec<f32>, Vec<[f64; 2]>) {
        let inv = invert(h);
        let k = 8;
        let mut img = vec![0f32; w * hgt];
        for y in 0..hgt {
            for x in 0..w {
                let mut acc = 0.0;
                for j in 0..k {
                    for i in 0..k {
                        let px = x as f64 - 0.5 + (i as f64 + 0.5) / k as f64;
                        let py = y as f64 - 0.5 + (j as f64 + 0.5) / k as f64;
                        let [u, v] = apply(&inv, px, py);
                        let inside =
                            u >= 0.0 && v >= 0.0 && u < (cols + 1) as f64 && v < (rows + 1) as f64;
                        let black = inside && (u.floor() as i64 + v.floor() as i64) % 2 == 0;
                        acc += if black { 30.0 } else { 220.0 };
                    }
                }
                img[y * w + x] = (acc / (k * k) as f64) as f32;
            }
        }
        if blur > 0.0 {
            let im = Image::from_f32(w, hgt, Channels::Gray, img).unwrap();
            img = gaussian_blur(&im, blur, blur, 0, 0, BorderMode::Reflect101, 0.0)
                .as_f32()
                .unwrap()
                .to_vec();
        }
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for v in &mut img {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let r = (state >> 40) as f32 / (1u64 << 24) as f32; // [0, 1)
            *v = (*v + noise * (2.0 * r - 1.0)).round().clamp(0.0, 255.0);
        }
        let mut truth = Vec::new();
        for v in 1..=rows {
            for u in 1..=cols {
                truth.push(apply(h, u as f64, v as f64));
            }
        }
        (img, truth)
    }

    fn check(
        img: &[f32],
        w: usize,
        h: usize,
        cols: usize,
        rows: usize,
        truth: &[[f64; 2]],
        tol: f64,
    ) {
        let s = ChessboardSettings {
            columns: cols,
            rows,
            ..ChessboardSettings::default()
        };
        let board = find_chessboard(img, w, h, &s).expect("board not found");
        assert_eq!(board.corners.len(), truth.len());
        let mut worst = 0f64;
        for (c, t) in board.corners.iter().zip(truth) {
            worst = worst.max(norm(sub(*c, *t)));
        }
        assert!(worst < tol, "worst corner error {worst} px");
    }

    /// Similarity: scale `s` px per square, rotation `a`, translation `(tx, ty)`, perspective
    /// terms `(p, q)`.
    fn homography(s: f64, a: f64, tx: f64, ty: f64, p: f64, q: f64) -> [f64; 9] {
        let (c, n) = (a.cos(), a.sin());
        [s * c, -s * n, tx, s * n, s * c, ty, p, q, 1.0]
    }

    #[test]
    fn fronto_parallel_board_within_a_tenth_of_a_pixel() {
        let (w, h) = (260, 200);
        let hm = homography(22.0, 0.0, 15.3, 12.7, 0.0, 0.0);
        let (img, truth) = render(w, h, 9, 6, &hm, 1.0, 4.0);
        check(&img, w, h, 9, 6, &truth, 0.1);
    }

    #[test]
    fn rotated_perspective_board_within_a_tenth_of_a_pixel() {
        let (w, h) = (320, 280);
        let hm = homography(20.0, 0.3, 60.2, 20.4, 0.03, -0.02);
        let (img, truth) = render(w, h, 7, 5, &hm, 1.2, 4.0);
        check(&img, w, h, 7, 5, &truth, 0.1);
    }

    #[test]
    fn wrong_pattern_size_is_not_found() {
        let (w, h) = (260, 200);
        let hm = homography(22.0, 0.0, 15.3, 12.7, 0.0, 0.0);
        let (img, _) = render(w, h, 9, 6, &hm, 1.0, 0.0);
        for (c, r) in [(10, 6), (9, 7), (5, 5), (7, 4)] {
            let s = ChessboardSettings {
                columns: c,
                rows: r,
                ..ChessboardSettings::default()
            };
            assert!(find_chessboard(&img, w, h, &s).is_none(), "{c}×{r}");
        }
        // Transposed pattern: found, rows run vertically.
        let s = ChessboardSettings {
            columns: 6,
            rows: 9,
            ..ChessboardSettings::default()
        };
        let b = find_chessboard(&img, w, h, &s).unwrap();
        assert_eq!(b.corners.len(), 54);
        assert!((b.corners[1][1] - b.corners[0][1]) > 15.0);
    }

    #[test]
    fn subpix_converges_on_an_ideal_corner() {
        let (w, h) = (40, 40);
        let hm = homography(12.0, 0.2, 7.4, 6.1, 0.0, 0.0);
        let (img, truth) = render(w, h, 2, 2, &hm, 0.8, 0.0);
        for t in truth {
            let start = [t[0].round() + 1.0, t[1].round() - 1.0];
            let r = corner_subpix(&img, w, h, start, 4, 40, 1e-4);
            assert!(norm(sub(r, t)) < 0.1, "{r:?} vs {t:?}");
        }
        // Flat image: nothing to solve, the start comes back.
        let flat = vec![100f32; 400];
        assert_eq!(
            corner_subpix(&flat, 20, 20, [9.0, 9.0], 3, 10, 1e-3),
            [9.0, 9.0]
        );
    }

    #[test]
    fn operator_metrics_and_extremes() {
        let (w, h) = (260, 200);
        let hm = homography(22.0, 0.0, 15.3, 12.7, 0.0, 0.0);
        let (img, truth) = render(w, h, 9, 6, &hm, 1.0, 2.0);
        let u8img: Vec<u8> = img.iter().map(|&v| v as u8).collect();
        let run = |image: Image| {
            let op = Chessboard::new(ChessboardParams::default()).unwrap();
            let specs = Chessboard::inputs();
            let values = [Some(Value::image(image))];
            let ctx = RunContext {
                node: "cb".into(),
                threads: 1,
                element: None,
            };
            let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
            let Some(Value::Points2D(p)) = out.take("corners") else {
                panic!("no corners")
            };
            let Some(Value::Metrics(m)) = out.take("metrics") else {
                panic!("no metrics")
            };
            (p, m)
        };
        let (p, m) = run(Image::from_u8(w, h, Channels::Gray, u8img).unwrap());
        assert_eq!(p.len(), truth.len());
        assert_eq!(m["found"], 1.0);
        assert!(m["mean_shift"] > 0.0 && m["mean_shift"] < 2.0);
        for (a, b) in p.iter().zip(&truth) {
            assert!(norm(sub(*a, *b)) < 0.1);
        }
        for image in [
            Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap(),
            Image::from_u8(1, 1, Channels::Rgb, vec![1, 2, 3]).unwrap(),
            Image::from_f32(30, 30, Channels::Gray, vec![0.5; 900]).unwrap(),
        ] {
            let (p, m) = run(image);
            assert!(p.is_empty());
            assert_eq!(m["found"], 0.0);
        }
        assert!(
            Chessboard::new(ChessboardParams {
                sigma: f64::NAN,
                ..ChessboardParams::default()
            })
            .is_err()
        );
        assert!(
            Chessboard::new(ChessboardParams {
                cols: 1,
                ..ChessboardParams::default()
            })
            .is_err()
        );
    }
}
